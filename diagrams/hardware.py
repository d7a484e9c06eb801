"""The cloth station on real drivers: two Pandas over LCM (Drake's
PandaCommandSender / PandaStatusReceiver), hand open commands for release, and
the camera from LCM images. It exports the same ports as the simulated Panda
station; the simulation-only ground-truth ports carry NaN here.

`MakeSimulatedLab` is the other end without hardware: the simulated cloth
station whose arms answer the same LCM channels (PandaCommandReceiver /
PandaStatusSender), whose hand commands open the grasps and whose camera
publishes lcmt_image_array, e.g. over `DrakeLcm("memq://")` in one process.
"""

import numpy as np
from drake import (
    lcmt_image_array,
    lcmt_panda_command,
    lcmt_panda_status,
    lcmt_schunk_wsg_command,
)
from fabric_imitation.diagrams.panda import (
    AddBimanualDiffIk,
    HandOrientation,
    MakeBimanualIk,
    SolveHandsAt,
)
from fabric_imitation.diagrams.station import (
    CLOTH_LABEL,
    ClothResolution,
    ClothStation,
    StationPorts,
)
from fabric_imitation.learning.state import NUM_KEYPOINTS, SIDES
from fabric_imitation.scenarios.poses import GraspCorners, PoseOnTable
from fabric_imitation.scenarios.schema import Scenario
from fabric_imitation.systems.lcm_drivers import (
    ArmStateFromStatus,
    CameraWatchdog,
    FreezeAfter,
    HandOpening,
    HandPositions,
    ReleaseFromHandCommand,
    StatusWatchdog,
)
from fabric_imitation.systems.panda_parts import (
    ARM_JOINTS,
    InstanceName,
)
from fabric_imitation.systems.station_parts import FabricMask, ReleaseLatch
from pydrake.common.value import AbstractValue
from pydrake.lcm import DrakeLcm
from pydrake.manipulation import (
    PandaCommandReceiver,
    PandaCommandSender,
    PandaControlMode,
    PandaStatusReceiver,
    PandaStatusSender,
    SchunkWsgCommandReceiver,
    SchunkWsgCommandSender,
)
from pydrake.systems.framework import (
    Diagram,
    DiagramBuilder,
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
)
from pydrake.systems.sensors import ImageToLcmImageArrayT, LcmImageArrayToImages

HAND_FORCE = 40.0  # [N] grip force limit sent with every hand command
# Messages are encoded and decoded in C++ (use_cpp_serializer) where a C++
# system consumes them. Never subscribe with a Python handler on the
# DrakeLcm (`lcm.Subscribe(channel, handler)`) while a simulation runs:
# pydrake 1.58 calls it without the GIL and crashes (segfault).


def HandChannel(command_channel: str) -> str:
    return command_channel.replace("COMMAND", "HAND_COMMAND")


def MakeHardwareClothStation(
    scenario: Scenario, *, lcm: DrakeLcm | None = None
) -> ClothStation:
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
    diff_ik = AddBimanualDiffIk(builder, scenario, ik, q0, orientations)
    stack = diff_ik.arm_states
    latch = builder.AddNamedSystem("release_latch", ReleaseLatch(period=dt))
    builder.ExportInput(latch.GetInputPort("release"), StationPorts.RELEASE)
    builder.ExportOutput(latch.GetOutputPort("released"), StationPorts.RELEASED)
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
        arm_q = diff_ik.arm_commanded[side]
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
        hand = builder.AddNamedSystem(f"{side}.hand_opening", HandOpening())
        builder.Connect(latch.GetOutputPort("released"), hand.GetInputPort("released"))
        hand_command = builder.AddNamedSystem(
            f"{side}.hand_command", SchunkWsgCommandSender(HAND_FORCE)
        )
        builder.Connect(
            hand.GetOutputPort("position"), hand_command.GetInputPort("position")
        )
        hand_pub = builder.AddNamedSystem(
            f"{side}.hand_publisher",
            LcmPublisherSystem.Make(
                HandChannel(arm.command_channel),
                lcmt_schunk_wsg_command,
                lcm,
                publish_period=dt,
                use_cpp_serializer=True,
            ),
        )
        builder.Connect(hand_command.get_output_port(), hand_pub.get_input_port())
    _add_lcm_camera(builder, scenario, lcm)
    object_pose = builder.AddNamedSystem(
        "object_pose",
        ConstantValueSource(AbstractValue.Make(PoseOnTable(scenario.object.pose))),
    )
    builder.ExportOutput(object_pose.get_output_port(), StationPorts.OBJECT_POSE)
    # Simulation-only ports, unknown (NaN) on hardware, sized as the
    # simulated station's for the same scenario (its engine's slab mesh).
    n = int(np.prod(ClothResolution(scenario)))
    unknowns = [
        (StationPorts.CLOTH_POSITIONS, 3 * n),
        (StationPorts.CLOTH_KEYPOINTS, 3 * NUM_KEYPOINTS),
    ]
    if scenario.object.kind != "none":
        unknowns.append((StationPorts.GRIPPER_OBJECT_CONTACT, 3))
    for name, size in unknowns:
        unknown = builder.AddNamedSystem(
            name, ConstantVectorSource(np.full(size, np.nan))
        )
        builder.ExportOutput(unknown.get_output_port(), name)
    diagram = builder.Build()
    diagram.set_name("cloth_station_hardware")
    color, _ = scenario.camera.MakeCameras()
    return ClothStation(
        diagram=diagram,
        scenario=scenario,
        camera_info=color.core().intrinsics(),
        X_WCamera=scenario.camera.X_PB.GetDeterministicValue(),
        X_WO=PoseOnTable(scenario.object.pose),
        initialize=diff_ik.initialize,
        # The IK's control model and collision checker must outlive the
        # diagram, which refers to them.
        keep_alive=(ik, q0),
        hardware=True,
    )


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
    # A camera that stops is caught within one control period: half of one
    # without a new image (a camera driver sends 15-30 per second).
    watchdog = builder.AddNamedSystem(
        "camera.watchdog",
        CameraWatchdog(
            channel=channel,
            timeout=scenario.motion.step_seconds / 2,
            startup=scenario.grippers.panda.status_timeout,
            period=scenario.plant_config.time_step,
        ),
    )
    # Its own subscriber, decoding in Python to read the timestamps.
    stamps = builder.AddNamedSystem(
        "camera.watchdog_subscriber",
        LcmSubscriberSystem.Make(channel, lcmt_image_array, lcm),
    )
    builder.Connect(stamps.get_output_port(), watchdog.GetInputPort("images"))
    builder.ExportOutput(images.color_image_output_port(), StationPorts.RGB)
    builder.ExportOutput(images.depth_image_output_port(), StationPorts.DEPTH)
    builder.ExportOutput(images.label_image_output_port(), StationPorts.LABEL)
    mask = builder.AddNamedSystem(
        "fabric_mask",
        FabricMask(width=config.width, height=config.height, cloth_label=CLOTH_LABEL),
    )
    builder.Connect(images.label_image_output_port(), mask.GetInputPort("label_image"))
    builder.ExportOutput(mask.GetOutputPort("mask"), StationPorts.MASK)


def HoldArms(station: ClothStation, station_context, lcm) -> None:
    """Tells both Panda drivers to hold their measured joint positions (one
    lcmt_panda_command each, published now): what `imitate --hardware` does
    when it is interrupted."""
    config = station.scenario.grippers.panda
    for side in SIDES:
        q = np.array(
            station.diagram.GetOutputPort(
                f"{InstanceName(side)}.position_measured"
            ).Eval(station_context)
        )
        msg = lcmt_panda_command()
        msg.utime = int(station_context.get_time() * 1e6)
        msg.num_joint_position = ARM_JOINTS
        msg.joint_position = list(q)
        msg.control_mode_expected = int(PandaControlMode.kPosition)
        lcm.Publish(getattr(config, side).command_channel, msg.encode())


def MakeSimulatedLab(
    scenario: Scenario,
    *,
    lcm: DrakeLcm,
    camera_period: float = 0.05,
    camera_until: float | None = None,
) -> tuple[Diagram, ClothStation]:
    """The other end of `MakeHardwareClothStation` without hardware: the
    simulated cloth station with two Pandas that answer the drivers' LCM
    channels (joint position commands in, status out, hand commands open the
    grasps) and a camera that publishes its colour, depth and label images
    as lcmt_image_array every `camera_period` seconds, as a camera driver
    does (with `camera_until`, its images stop changing from then on, as a
    stalled camera's). Returns (lab diagram, its station) -- the station's
    ground truth is for judging the run afterwards; nothing else connects
    to it."""
    from fabric_imitation.diagrams.station import MakeClothStation

    config = scenario.grippers.panda
    dt = scenario.plant_config.time_step
    builder = DiagramBuilder()
    lab_station = MakeClothStation(scenario, joint_commands=True)
    station = builder.AddNamedSystem("lab_station", lab_station.diagram)
    release = builder.AddNamedSystem("hand_release", ReleaseFromHandCommand())
    builder.Connect(
        release.GetOutputPort("release"), station.GetInputPort(StationPorts.RELEASE)
    )
    for side in SIDES:
        arm, name = getattr(config, side), InstanceName(side)
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
        builder.Connect(
            station.GetOutputPort(f"{name}.position_measured"),
            receiver.GetInputPort("position_measured"),
        )
        builder.Connect(
            receiver.GetOutputPort("position"),
            station.GetInputPort(f"{name}.position_command"),
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
            station.GetOutputPort(f"{name}.position_measured"),
            sender.GetInputPort("position_measured"),
        )
        builder.Connect(
            station.GetOutputPort(f"{name}.velocity_measured"),
            sender.GetInputPort("velocity_measured"),
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
        hand = builder.AddNamedSystem(
            f"{side}.hand_subscriber",
            LcmSubscriberSystem.Make(
                HandChannel(arm.command_channel),
                lcmt_schunk_wsg_command,
                lcm,
                use_cpp_serializer=True,
            ),
        )
        opening = builder.AddNamedSystem(
            f"{side}.hand_receiver", SchunkWsgCommandReceiver(0.0, HAND_FORCE)
        )
        builder.Connect(hand.get_output_port(), opening.GetInputPort("command_message"))
        builder.Connect(opening.GetOutputPort("position"), release.GetInputPort(side))
    # Compressed: Drake 1.58's LcmImageArrayToImages decodes uncompressed
    # float depth and label images only partly (rows after the first few
    # bytes come back as zeros); the zlib path is exact.
    images = builder.AddNamedSystem(
        "camera.to_lcm",
        ImageToLcmImageArrayT("color", "depth", "label", do_compress=True),
    )
    for port, name in (
        (StationPorts.RGB, "color"),
        (StationPorts.DEPTH, "depth"),
        (StationPorts.LABEL, "label"),
    ):
        builder.Connect(station.GetOutputPort(port), images.GetInputPort(name))
    camera = builder.AddNamedSystem(
        "camera.publisher",
        LcmPublisherSystem.Make(
            config.camera_channel,
            lcmt_image_array,
            lcm,
            publish_period=camera_period,
            use_cpp_serializer=True,
        ),
    )
    message = images.image_array_t_msg_output_port()
    if camera_until is not None:
        freeze = builder.AddNamedSystem(
            "camera.stall",
            FreezeAfter(message.Allocate(), period=camera_period, until=camera_until),
        )
        builder.Connect(message, freeze.GetInputPort("u"))
        message = freeze.GetOutputPort("y")
    builder.Connect(message, camera.get_input_port())
    lab = builder.Build()
    lab.set_name("simulated_lab")
    return lab, lab_station
