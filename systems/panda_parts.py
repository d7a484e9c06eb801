"""The Panda arms' LeafSystems: the simulated driver's gravity compensation,
hand targets kept in reach, the arms' states and commands in the control
plant's order, and the hands' TCP positions."""

import logging

import numpy as np
from fabric_imitation.learning.state import SIDES
from pydrake.common.value import AbstractValue
from pydrake.math import RigidTransform
from pydrake.multibody.plant import MultibodyPlant
from pydrake.systems.framework import BasicVector, BusValue, LeafSystem

_LOG = logging.getLogger("fabric_imitation.panda")
ARM_JOINTS = 7
FINGER_OPENING = 0.02  # [m] each finger, held by its PD actuator
TCP_FRAME = "panda_hand_tcp"


def InstanceName(side: str) -> str:
    return f"{side}_panda"


class GravityCompensatedCommand(LeafSystem):
    """The simulated driver's gravity compensation: the desired state
    (9 positions, 9 velocities of one arm and its fingers) with each arm
    joint's position moved by -tau_g(q) / kp, q the arm's measured
    positions, so that the plant's joint PD adds -tau_g(q) to its torque and
    holds the arm's weight (as the real driver's position control does); the
    arm then moves as a weightless arm under the plain PD would, up to the
    one-step lag of q.

    With gravity switched off on the arms instead, the PD's impulses vanish
    at rest, and Drake 1.58's SAP solver, whose tolerance is relative to
    them, fails to converge about a second into a hold; holding the weight
    keeps them finite.

    Args:
        plant: a model of the arms with gravity (the IK's control model).
        instance: the arm's model instance in `plant`.
        kp: the joint PD's stiffness [N m / rad].

    Input ports: ``desired_state`` (2n), ``measured_state`` (2n: the
    station plant's state of the arm). Output: ``desired_state`` (2n).
    """

    def __init__(self, plant: MultibodyPlant, instance, kp: float):
        super().__init__()
        self._plant = plant
        self._instance = instance
        self._context = plant.CreateDefaultContext()
        self._kp = kp
        self._n = n = plant.num_positions(instance)
        self._desired = self.DeclareVectorInputPort("desired_state", 2 * n)
        self._measured = self.DeclareVectorInputPort("measured_state", 2 * n)
        self.DeclareVectorOutputPort("desired_state", 2 * n, self._calc)

    def _calc(self, context, output):
        x = self._desired.Eval(context).copy()
        plant, instance = self._plant, self._instance
        q = self._measured.Eval(context)[: self._n]
        plant.SetPositions(self._context, instance, q)
        tau = plant.GetVelocitiesFromArray(
            instance, plant.CalcGravityGeneralizedForces(self._context)
        )
        x[:ARM_JOINTS] -= tau[:ARM_JOINTS] / self._kp
        output.SetFromVector(x)


class HandTargets(LeafSystem):
    """Hand position targets -> desired TCP poses (fixed downward orientation)
    for the differential IK, kept inside each arm's reach and above the table.

    A target outside is moved to the nearest reachable point; the
    ``saturated`` output (1 per hand, from state) and a log line report it.

    Input ports: ``left.ee_target``, ``right.ee_target`` (3, world).
    Output ports: ``desired_poses`` (BusValue of RigidTransform keyed by the
    scoped TCP frame names), ``saturated`` (2).
    """

    def __init__(
        self,
        *,
        frame_names: dict,
        orientations: dict,
        shoulders: dict,
        reach: float,
        min_height: float,
        period: float,
    ):
        super().__init__()
        self._names = frame_names
        self._R = orientations
        self._shoulders = {k: np.asarray(v) for k, v in shoulders.items()}
        self._reach = reach
        self._min_z = min_height
        self._targets = {
            side: self.DeclareVectorInputPort(f"{side}.ee_target", 3) for side in SIDES
        }
        self._saturated = self.DeclareDiscreteState(2)
        self.DeclarePeriodicDiscreteUpdateEvent(period, 0.0, self._check)
        self.DeclareAbstractOutputPort(
            "desired_poses", lambda: AbstractValue.Make(BusValue()), self._calc
        )
        self.DeclareStateOutputPort("saturated", self._saturated)

    def Clamp(self, side: str, p: np.ndarray) -> np.ndarray:
        c = self._shoulders[side]
        d = p - c
        n = np.linalg.norm(d)
        q = c + d * (self._reach / n) if n > self._reach else np.array(p, float)
        q[2] = max(q[2], self._min_z)
        return q

    def _calc(self, context, output) -> None:
        bus = output.get_mutable_value()
        for side in SIDES:
            p = self.Clamp(side, self._targets[side].Eval(context))
            bus.Set(
                self._names[side], AbstractValue.Make(RigidTransform(self._R[side], p))
            )

    def _check(self, context, discrete_state):
        flags = []
        before = context.get_discrete_state(self._saturated).value()
        for k, side in enumerate(SIDES):
            p = self._targets[side].Eval(context)
            hit = float(np.linalg.norm(self.Clamp(side, p) - p) > 1e-9)
            if hit and not before[k]:
                _LOG.warning(
                    "%s hand target %s is out of reach; saturated",
                    side,
                    np.round(p, 3).tolist(),
                )
            flags.append(hit)
        discrete_state.get_mutable_vector(self._saturated).SetFromVector(flags)


class ArmStates(LeafSystem):
    """Stacks the two arms' plant states [q_l, v_l], [q_r, v_r] into the
    control plant's order [q_l, q_r, v_l, v_r].

    Input ports: ``left_state``, ``right_state`` (2n each).
    Output ports: ``state`` (4n).
    """

    def __init__(self, n: int):
        super().__init__()
        self._n = n
        self._l = self.DeclareVectorInputPort("left_state", 2 * n)
        self._r = self.DeclareVectorInputPort("right_state", 2 * n)
        self.DeclareVectorOutputPort("state", 4 * n, self._calc)

    def _calc(self, context, output: BasicVector) -> None:
        n = self._n
        left, right = self._l.Eval(context), self._r.Eval(context)
        output.SetFromVector(np.concatenate([left[:n], right[:n], left[n:], right[n:]]))


class ArmCommand(LeafSystem):
    """One arm's joint position command from the controller's full command,
    with the fingers held open: [q_arm (7), fingers (2)].

    Input ports: ``commanded_position`` (control plant positions).
    Output ports: ``position`` (9).
    """

    def __init__(self, *, indices: list[int], nq: int):
        super().__init__()
        self._idx = np.asarray(indices)
        self._q = self.DeclareVectorInputPort("commanded_position", nq)
        self.DeclareVectorOutputPort("position", ARM_JOINTS + 2, self._calc)

    def _calc(self, context, output: BasicVector) -> None:
        q = self._q.Eval(context)
        output.SetFromVector(np.concatenate([q[self._idx], [FINGER_OPENING] * 2]))


class TcpPositions(LeafSystem):
    """World positions of the two hands' TCPs from the plant's body poses.

    Input ports: ``body_poses`` (the plant's list of RigidTransform).
    Output ports: ``left``, ``right`` (3).
    """

    def __init__(self, *, body_indices: dict):
        super().__init__()
        self._idx = body_indices
        self._poses = self.DeclareAbstractInputPort(
            "body_poses", AbstractValue.Make([RigidTransform()])
        )
        for side in SIDES:
            self.DeclareVectorOutputPort(
                side,
                3,
                lambda c, o, side=side: o.SetFromVector(
                    self._poses.Eval(c)[self._idx[side]].translation()
                ),
            )
