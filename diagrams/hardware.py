"""The cloth station on real drivers: two Pandas over LCM (Drake's
PandaCommandSender / PandaStatusReceiver), hand open commands for release, and
the camera from LCM images. It exports the same ports as the simulated Panda
station; the simulation-only ground-truth ports carry NaN here.

`MakeSimulatedPandaDrivers` is the other end for tests: a plant with the two
arms that answers the same LCM channels (PandaCommandReceiver /
PandaStatusSender), e.g. over `DrakeLcm("memq://")` in one process.
"""

import numpy as np
from drake import (
    lcmt_image_array,
    lcmt_panda_command,
    lcmt_panda_status,
    lcmt_schunk_wsg_command,
)
from fabric_imitation.diagrams.panda import (
    ARM_JOINTS,
    FINGER_OPENING,
    SIDES,
    TCP_FRAME,
    AddArmActuators,
    AddPandaModels,
    ArmCommand,
    ArmStates,
    FilterArmCollisions,
    HandOrientation,
    HandTargets,
    InstanceName,
    MakeBimanualIk,
    SolveHandsAt,
)
from fabric_imitation.diagrams.station import (
    CLOTH_LABEL,
    NUM_KEYPOINTS,
    GraspCorners,
    PoseOnTable,
    StationPorts,
)
from fabric_imitation.scenarios.schema import Scenario
from fabric_imitation.systems.station_parts import FabricMask, ReleaseLatch
from pydrake.common.value import AbstractValue
from pydrake.lcm import DrakeLcm
from pydrake.manipulation import (
    PandaCommandReceiver,
    PandaCommandSender,
    PandaControlMode,
    PandaStatusReceiver,
    PandaStatusSender,
)
from pydrake.multibody.plant import AddMultibodyPlant
from pydrake.systems.framework import (
    BasicVector,
    Diagram,
    DiagramBuilder,
    EventStatus,
    LeafSystem,
)
from pydrake.systems.lcm import (
    LcmInterfaceSystem,
    LcmPublisherSystem,
    LcmSubscriberSystem,
)
from pydrake.systems.primitives import (
    ConstantValueSource,
    ConstantVectorSource,
    Demultiplexer,
    Multiplexer,
    StateInterpolatorWithDiscreteDerivative,
)
from pydrake.systems.sensors import LcmImageArrayToImages

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


class HandOpenCommand(LeafSystem):
    """lcmt_schunk_wsg_command for a parallel gripper: closed while grasping,
    open once released.

    Input ports: ``released`` (1).
    Output ports: ``command`` (lcmt_schunk_wsg_command).
    """

    def __init__(self):
        super().__init__()
        self._released = self.DeclareVectorInputPort("released", 1)
        self.DeclareAbstractOutputPort(
            "command", lambda: AbstractValue.Make(lcmt_schunk_wsg_command()), self._calc
        )

    def _calc(self, context, output) -> None:
        msg = lcmt_schunk_wsg_command()
        msg.utime = int(context.get_time() * 1e6)
        msg.target_position_mm = (
            HAND_OPEN_MM if self._released.Eval(context)[0] > 0.5 else 0
        )
        msg.force = 40.0
        output.set_value(msg)


def HandChannel(command_channel: str) -> str:
    return command_channel.replace("COMMAND", "HAND_COMMAND")


def MakeHardwareClothStation(
    scenario: Scenario, *, lcm: DrakeLcm | None = None
) -> Diagram:
    """The station's ports on real Panda drivers over LCM (see module doc)."""
    config = scenario.grippers.panda
    lcm = lcm or DrakeLcm(config.lcm_url)
    dt = scenario.plant_config.time_step
    builder = DiagramBuilder()
    builder.AddNamedSystem("lcm", LcmInterfaceSystem(lcm))
    ik = MakeBimanualIk(scenario, dt)
    robot_plant = ik.robot.plant()
    orientations = {
        side: HandOrientation(side, getattr(config, side).base[2]) for side in SIDES
    }
    q0 = SolveHandsAt(robot_plant, GraspCorners(scenario), orientations)
    shoulders = {
        side: np.array([*getattr(config, side).base[:2], 0.333]) for side in SIDES
    }
    targets = builder.AddNamedSystem(
        "hand_targets",
        HandTargets(
            frame_names=ik.frame_names,
            orientations=orientations,
            shoulders=shoulders,
            reach=0.80,
            min_height=0.0,
            period=dt,
        ),
    )
    controller = builder.AddNamedSystem("diff_ik", ik.controller)
    builder.Connect(
        targets.GetOutputPort("desired_poses"), controller.GetInputPort("desired_poses")
    )
    nominal = builder.AddNamedSystem("nominal_posture", ConstantVectorSource(q0))
    builder.Connect(
        nominal.get_output_port(), controller.GetInputPort("nominal_posture")
    )
    stack = builder.AddNamedSystem("arm_states", ArmStates(ARM_JOINTS + 2))
    builder.Connect(
        stack.GetOutputPort("state"), controller.GetInputPort("estimated_state")
    )
    latch = builder.AddNamedSystem("release_latch", ReleaseLatch(period=dt))
    builder.ExportInput(latch.GetInputPort("release"), StationPorts.RELEASE)
    builder.ExportOutput(latch.GetOutputPort("released"), StationPorts.RELEASED)
    nq = robot_plant.num_positions()
    positions = builder.AddNamedSystem(
        "measured_positions", Demultiplexer([ARM_JOINTS + 2] * 4)
    )
    builder.Connect(stack.GetOutputPort("state"), positions.get_input_port())
    full_q = builder.AddNamedSystem("measured_q", Multiplexer([ARM_JOINTS + 2] * 2))
    builder.Connect(positions.get_output_port(0), full_q.get_input_port(0))
    builder.Connect(positions.get_output_port(1), full_q.get_input_port(1))
    fk = builder.AddNamedSystem("hand_positions", HandPositions(robot_plant))
    builder.Connect(full_q.get_output_port(), fk.GetInputPort("positions"))
    for side in SIDES:
        arm = getattr(config, side)
        builder.ExportInput(
            targets.GetInputPort(f"{side}.ee_target"), StationPorts.ee_target(side)
        )
        command = builder.AddNamedSystem(
            f"{side}.arm_command",
            ArmCommand(indices=ik.arm_position_indices[side], nq=nq),
        )
        builder.Connect(
            controller.GetOutputPort("commanded_position"),
            command.GetInputPort("commanded_position"),
        )
        arm_q = builder.AddNamedSystem(
            f"{side}.arm_commanded", Demultiplexer([ARM_JOINTS, 2])
        )
        builder.Connect(command.GetOutputPort("position"), arm_q.get_input_port())
        sender = builder.AddNamedSystem(
            f"{side}.command_sender",
            PandaCommandSender(ARM_JOINTS, PandaControlMode.kPosition),
        )
        builder.Connect(arm_q.get_output_port(0), sender.GetInputPort("position"))
        publisher = builder.AddNamedSystem(
            f"{side}.command_publisher",
            LcmPublisherSystem.Make(
                arm.command_channel,
                lcmt_panda_command,
                lcm,
                publish_period=dt,
                use_cpp_serializer=True,
            ),
        )
        builder.Connect(sender.get_output_port(), publisher.get_input_port())
        subscriber = builder.AddNamedSystem(
            f"{side}.status_subscriber",
            LcmSubscriberSystem.Make(
                arm.status_channel, lcmt_panda_status, lcm, use_cpp_serializer=True
            ),
        )
        receiver = builder.AddNamedSystem(
            f"{side}.status_receiver", PandaStatusReceiver(ARM_JOINTS)
        )
        builder.Connect(subscriber.get_output_port(), receiver.get_input_port())
        watchdog = builder.AddNamedSystem(
            f"{side}.status_watchdog",
            StatusWatchdog(
                channel=arm.status_channel, timeout=config.status_timeout, period=dt
            ),
        )
        builder.Connect(
            receiver.GetOutputPort("position_measured"),
            watchdog.GetInputPort("position_measured"),
        )
        state = builder.AddNamedSystem(f"{side}.arm_state", ArmStateFromStatus())
        builder.Connect(
            receiver.GetOutputPort("position_measured"), state.GetInputPort("position")
        )
        builder.Connect(
            receiver.GetOutputPort("velocity_measured"), state.GetInputPort("velocity")
        )
        builder.Connect(
            state.GetOutputPort("state"), stack.GetInputPort(f"{side}_state")
        )
        builder.ExportOutput(fk.GetOutputPort(side), StationPorts.ee_measured(side))
        builder.ExportOutput(
            receiver.GetOutputPort("position_measured"),
            f"{InstanceName(side)}.position_measured",
        )
        builder.ExportOutput(
            arm_q.get_output_port(0), f"{InstanceName(side)}.position_commanded"
        )
        hand = builder.AddNamedSystem(f"{side}.hand_command", HandOpenCommand())
        builder.Connect(latch.GetOutputPort("released"), hand.GetInputPort("released"))
        hand_pub = builder.AddNamedSystem(
            f"{side}.hand_publisher",
            LcmPublisherSystem.Make(
                HandChannel(arm.command_channel),
                lcmt_schunk_wsg_command,
                lcm,
                publish_period=dt,
            ),
        )
        builder.Connect(hand.GetOutputPort("command"), hand_pub.get_input_port())
    builder.ExportOutput(targets.GetOutputPort("saturated"), "hands.target_saturated")
    _add_lcm_camera(builder, scenario, lcm)
    object_pose = builder.AddNamedSystem(
        "object_pose",
        ConstantValueSource(AbstractValue.Make(PoseOnTable(scenario.object.pose))),
    )
    builder.ExportOutput(object_pose.get_output_port(), StationPorts.OBJECT_POSE)
    n = int(np.prod(scenario.cloth.resolution))
    for name, size in (
        (StationPorts.CLOTH_POSITIONS, 3 * n),
        (StationPorts.CLOTH_KEYPOINTS, 3 * NUM_KEYPOINTS),
    ):
        unknown = builder.AddNamedSystem(
            name, ConstantVectorSource(np.full(size, np.nan))
        )
        builder.ExportOutput(unknown.get_output_port(), name)
    station = builder.Build()
    station.set_name("cloth_station_hardware")

    def initialize(station, station_context):
        station.GetSubsystemByName("diff_ik").set_initial_position(
            station.GetMutableSubsystemContext(controller, station_context), q0
        )

    station.handles = _HardwareHandles(scenario=scenario, initialize=initialize, q0=q0)
    return station


class _HardwareHandles:
    def __init__(self, *, scenario, initialize, q0):
        self.scenario = scenario
        self.initialize = initialize
        self.q0 = q0


def _add_lcm_camera(builder: DiagramBuilder, scenario: Scenario, lcm) -> None:
    config = scenario.camera
    channel = scenario.grippers.panda.camera_channel
    subscriber = builder.AddNamedSystem(
        "camera.subscriber",
        LcmSubscriberSystem.Make(
            channel, lcmt_image_array, lcm, use_cpp_serializer=True
        ),
    )
    images = builder.AddNamedSystem("camera.images", LcmImageArrayToImages())
    builder.Connect(subscriber.get_output_port(), images.image_array_t_input_port())
    builder.ExportOutput(images.color_image_output_port(), StationPorts.RGB)
    builder.ExportOutput(images.depth_image_output_port(), StationPorts.DEPTH)
    builder.ExportOutput(images.label_image_output_port(), StationPorts.LABEL)
    mask = builder.AddNamedSystem(
        "fabric_mask",
        FabricMask(width=config.width, height=config.height, cloth_label=CLOTH_LABEL),
    )
    builder.Connect(images.label_image_output_port(), mask.GetInputPort("label_image"))
    builder.ExportOutput(mask.GetOutputPort("mask"), StationPorts.MASK)


def MakeSimulatedPandaDrivers(scenario: Scenario, *, lcm: DrakeLcm) -> Diagram:
    """Two simulated Panda drivers on LCM: joint position commands in,
    status out, arms starting at the grasp configuration."""
    config = scenario.grippers.panda
    dt = scenario.plant_config.time_step
    builder = DiagramBuilder()
    plant, scene_graph = AddMultibodyPlant(scenario.plant_config, builder)
    instances = AddPandaModels(plant, config)
    for instance in instances.values():
        AddArmActuators(plant, instance, config)
    FilterArmCollisions(plant, scene_graph, instances)
    plant.Finalize()
    ik = MakeBimanualIk(scenario, dt)
    orientations = {
        side: HandOrientation(side, getattr(config, side).base[2]) for side in SIDES
    }
    q0 = SolveHandsAt(ik.robot.plant(), GraspCorners(scenario), orientations)
    for side, instance in instances.items():
        plant.SetDefaultPositions(
            instance,
            q0[ik.arm_position_indices[side][0] : ik.arm_position_indices[side][0] + 9],
        )
        arm = getattr(config, side)
        subscriber = builder.AddNamedSystem(
            f"{side}.command_subscriber",
            LcmSubscriberSystem.Make(
                arm.command_channel, lcmt_panda_command, lcm, use_cpp_serializer=True
            ),
        )
        receiver = builder.AddNamedSystem(
            f"{side}.command_receiver",
            PandaCommandReceiver(ARM_JOINTS, PandaControlMode.kPosition),
        )
        builder.Connect(
            subscriber.get_output_port(), receiver.GetInputPort("lcmt_panda_command")
        )
        state = builder.AddNamedSystem(f"{side}.state", Demultiplexer([7, 2, 7, 2]))
        builder.Connect(plant.get_state_output_port(instance), state.get_input_port())
        builder.Connect(
            state.get_output_port(0), receiver.GetInputPort("position_measured")
        )
        with_fingers = builder.AddNamedSystem(
            f"{side}.with_fingers", Multiplexer([7, 2])
        )
        fingers = builder.AddNamedSystem(
            f"{side}.fingers", ConstantVectorSource([FINGER_OPENING] * 2)
        )
        builder.Connect(
            receiver.GetOutputPort("position"), with_fingers.get_input_port(0)
        )
        builder.Connect(fingers.get_output_port(), with_fingers.get_input_port(1))
        interpolator = builder.AddNamedSystem(
            f"{side}.interpolator", StateInterpolatorWithDiscreteDerivative(9, dt, True)
        )
        builder.Connect(with_fingers.get_output_port(), interpolator.get_input_port())
        builder.Connect(
            interpolator.get_output_port(), plant.get_desired_state_input_port(instance)
        )
        sender = builder.AddNamedSystem(f"{side}.status_sender", PandaStatusSender(7))
        zeros = builder.AddNamedSystem(
            f"{side}.zeros", ConstantVectorSource(np.zeros(7))
        )
        builder.Connect(
            receiver.GetOutputPort("position"),
            sender.GetInputPort("position_commanded"),
        )
        builder.Connect(
            state.get_output_port(0), sender.GetInputPort("position_measured")
        )
        builder.Connect(
            state.get_output_port(2), sender.GetInputPort("velocity_measured")
        )
        for port in (
            "velocity_commanded",
            "acceleration_commanded",
            "torque_commanded",
            "torque_measured",
            "torque_external",
        ):
            builder.Connect(zeros.get_output_port(), sender.GetInputPort(port))
        publisher = builder.AddNamedSystem(
            f"{side}.status_publisher",
            LcmPublisherSystem.Make(
                arm.status_channel,
                lcmt_panda_status,
                lcm,
                publish_period=dt,
                use_cpp_serializer=True,
            ),
        )
        builder.Connect(sender.get_output_port(), publisher.get_input_port())
    drivers = builder.Build()
    drivers.set_name("simulated_panda_drivers")
    drivers.plant = plant
    drivers.instances = instances
    return drivers
