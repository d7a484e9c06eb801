"""LeafSystems of the hardware station and its simulated lab: the arms'
states from the Panda drivers' status, the hands' positions by forward
kinematics, the hand commands, and watchdogs that end a run whose driver
or camera has gone silent."""

import numpy as np
from drake import lcmt_image_array
from fabric_imitation.learning.state import SIDES
from fabric_imitation.systems.panda_parts import (
    ARM_JOINTS,
    FINGER_OPENING,
    TCP_FRAME,
    InstanceName,
)
from pydrake.common.value import AbstractValue
from pydrake.systems.framework import BasicVector, EventStatus, LeafSystem

HAND_OPEN_MM = 80.0


class ArmStateFromStatus(LeafSystem):
    """[q_arm, fingers, v_arm, 0, 0] from a driver's measured joints.

    Input ports: ``position`` (7), ``velocity`` (7).
    Output ports: ``state`` (18).
    """

    def __init__(self):
        super().__init__()
        self._q = self.DeclareVectorInputPort("position", ARM_JOINTS)
        self._v = self.DeclareVectorInputPort("velocity", ARM_JOINTS)
        self.DeclareVectorOutputPort("state", 2 * (ARM_JOINTS + 2), self._calc)

    def _calc(self, context, output: BasicVector) -> None:
        output.SetFromVector(
            np.concatenate(
                [
                    self._q.Eval(context),
                    [FINGER_OPENING] * 2,
                    self._v.Eval(context),
                    [0.0, 0.0],
                ]
            )
        )


class HandPositions(LeafSystem):
    """Forward kinematics of the hands' TCPs from both arms' joint positions
    (on the control model of the arms).

    Input ports: ``positions`` (control-plant positions).
    Output ports: ``left``, ``right`` (3, world).
    """

    def __init__(self, robot_plant):
        super().__init__()
        self._plant = robot_plant
        self._frames = {
            side: robot_plant.GetFrameByName(
                TCP_FRAME, robot_plant.GetModelInstanceByName(InstanceName(side))
            )
            for side in SIDES
        }
        self._q = self.DeclareVectorInputPort("positions", robot_plant.num_positions())
        # A scratch context for kinematics; no run state lives in it.
        self._scratch = robot_plant.CreateDefaultContext()
        for side in SIDES:
            self.DeclareVectorOutputPort(
                side, 3, lambda c, o, side=side: o.SetFromVector(self._fk(c, side))
            )

    def _fk(self, context, side: str) -> np.ndarray:
        self._plant.SetPositions(self._scratch, self._q.Eval(context))
        return self._frames[side].CalcPoseInWorld(self._scratch).translation()


class StatusWatchdog(LeafSystem):
    """Fails the simulation with a clear message when a driver's status has
    not arrived within `timeout` seconds (PandaStatusReceiver reports all-zero
    joints until the first message; joint 4 of a real Panda cannot be 0).

    Input ports: ``position_measured`` (7).
    """

    def __init__(self, *, channel: str, timeout: float, period: float):
        super().__init__()
        self._channel, self._timeout = channel, timeout
        self._q = self.DeclareVectorInputPort("position_measured", ARM_JOINTS)
        self.DeclarePeriodicPublishEvent(period, 0.0, self._check)

    def _check(self, context) -> EventStatus:
        silent = not np.any(self._q.Eval(context))
        if context.get_time() >= self._timeout and silent:
            raise RuntimeError(
                f"no lcmt_panda_status on {self._channel} for {self._timeout} s; is "
                "the Panda driver running and on the same LCM bus?"
            )
        return EventStatus.Succeeded()


class HandOpening(LeafSystem):
    """The parallel gripper's commanded opening: closed while grasping, open
    (HAND_OPEN_MM) once released; Drake's SchunkWsgCommandSender turns it
    into the lcmt_schunk_wsg_command (encoded in C++).

    Input ports: ``released`` (1).
    Output ports: ``position`` (1, [m]).
    """

    def __init__(self):
        super().__init__()
        self._released = self.DeclareVectorInputPort("released", 1)
        self.DeclareVectorOutputPort("position", 1, self._calc)

    def _calc(self, context, output: BasicVector) -> None:
        released = self._released.Eval(context)[0] > 0.5
        output.SetFromVector([HAND_OPEN_MM / 1000 if released else 0.0])


class CameraWatchdog(LeafSystem):
    """Fails the run with a clear message when the camera's images stop: no
    image within `startup` seconds of the start, or none for `timeout`
    seconds since the last (a new image is one with a new timestamp, so a
    driver that repeats a stale frame counts as stopped).

    Input ports: ``images`` (lcmt_image_array, decoded in Python: the last
    message).
    """

    def __init__(self, *, channel: str, timeout: float, startup: float, period: float):
        super().__init__()
        self._channel = channel
        self._timeout, self._startup = timeout, startup
        self._images = self.DeclareAbstractInputPort(
            "images", AbstractValue.Make(lcmt_image_array())
        )
        # [utime of the last image, time it arrived here, images seen (0/1)]
        self._state = self.DeclareDiscreteState(3)
        self.DeclarePeriodicDiscreteUpdateEvent(period, 0.0, self._check)

    def _check(self, context, discrete_state) -> EventStatus:
        last_utime, arrived, seen = context.get_discrete_state(self._state).value()
        msg = self._images.Eval(context)
        t = context.get_time()
        if msg.num_images > 0 and msg.header.utime != last_utime:
            last_utime, arrived, seen = msg.header.utime, t, 1.0
        if not seen and t > self._startup:
            raise RuntimeError(
                f"no camera images on {self._channel} for {self._startup:g} s; is "
                "the camera driver running and on the same LCM bus?"
            )
        if seen and t - arrived > self._timeout:
            raise RuntimeError(
                f"the camera on {self._channel} stopped sending images at "
                f"t = {arrived:.2f} s (none for {t - arrived:.2f} s)"
            )
        discrete_state.get_mutable_vector(self._state).SetFromVector(
            [last_utime, arrived, seen]
        )
        return EventStatus.Succeeded()


class ReleaseFromHandCommand(LeafSystem):
    """The simulated lab's reading of the hand commands: released once a
    hand is told to open (commanded opening above half of HAND_OPEN_MM).

    Input ports: ``left``, ``right`` (1: commanded opening [m], from
    SchunkWsgCommandReceiver).
    Output ports: ``release`` (1).
    """

    def __init__(self):
        super().__init__()
        self._hands = [self.DeclareVectorInputPort(side, 1) for side in SIDES]
        self.DeclareVectorOutputPort("release", 1, self._calc)

    def _calc(self, context, output: BasicVector) -> None:
        opened = any(
            port.Eval(context)[0] > HAND_OPEN_MM / 2000 for port in self._hands
        )
        output.SetFromVector([1.0 if opened else 0.0])


class FreezeAfter(LeafSystem):
    """Passes an abstract value through, sampled every `period`, until time
    `until`; then keeps the last one (a camera driver that stalls).

    Input ports: ``u``. Output ports: ``y`` (from state).
    """

    def __init__(self, model_value: AbstractValue, *, period: float, until: float):
        super().__init__()
        self._until = until
        self._u = self.DeclareAbstractInputPort("u", model_value)
        self._state = self.DeclareAbstractState(model_value)
        self.DeclarePeriodicUnrestrictedUpdateEvent(period, 0.0, self._sample)
        self.DeclareStateOutputPort("y", self._state)

    def _sample(self, context, state) -> EventStatus:
        if context.get_time() >= self._until:
            return EventStatus.DidNothing()
        state.get_mutable_abstract_state(self._state).SetFrom(
            self._u.EvalAbstract(context)
        )
        return EventStatus.Succeeded()
