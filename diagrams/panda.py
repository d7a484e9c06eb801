"""Two Franka Panda arms for the cloth station: model loading from a registry
package, initial configurations by IK, and bimanual differential IK.

The arms' description comes from the PyPI package example-robot-data
(`panda_description`); Drake's own `drake_models` Panda is downloaded at run
time and is not used.
"""

import dataclasses as dc
import logging
import math
from importlib import metadata
from pathlib import Path

import numpy as np
from fabric_imitation.learning.errors import InputError
from fabric_imitation.learning.state import SIDES
from fabric_imitation.scenarios.schema import PandaConfig, Scenario
from fabric_imitation.systems.panda_parts import (
    ARM_JOINTS,
    FINGER_OPENING,
    TCP_FRAME,
    ArmCommand,
    ArmStates,
    GravityCompensatedCommand,
    HandTargets,
    InstanceName,
    TcpPositions,
)
from pydrake.math import RigidTransform, RollPitchYaw, RotationMatrix
from pydrake.multibody.inverse_kinematics import (
    DifferentialInverseKinematicsController,
    DifferentialInverseKinematicsSystem,
    InverseKinematics,
)
from pydrake.multibody.math import SpatialVelocity
from pydrake.multibody.parsing import Parser
from pydrake.multibody.plant import MultibodyPlant
from pydrake.multibody.tree import PdControllerGains
from pydrake.planning import (
    DofMask,
    JointLimits,
    RobotDiagramBuilder,
    SceneGraphCollisionChecker,
)
from pydrake.solvers import Solve
from pydrake.systems.framework import LeafSystem
from pydrake.systems.primitives import (
    ConstantVectorSource,
    Demultiplexer,
    Multiplexer,
    StateInterpolatorWithDiscreteDerivative,
)

_LOG = logging.getLogger("fabric_imitation.panda")


def PackagePath(package: str) -> Path:
    """Share directory of a robot-description registry package (cmeel layout:
    site-packages/cmeel.prefix/share/<package>), which its URDFs address as
    package://<package>/..."""
    try:
        dist = metadata.distribution(package)
    except metadata.PackageNotFoundError:
        raise InputError(f"robot package {package!r} is not installed") from None
    path = Path(dist.locate_file(f"cmeel.prefix/share/{package}"))
    if not path.is_dir():
        raise InputError(f"robot package {package!r} has no share/{package} folder")
    return path


def AddPandaModels(plant: MultibodyPlant, config: PandaConfig) -> dict:
    """Parses both arms into `plant`, welds their bases, renames them
    left_panda / right_panda; returns {side: model instance}."""
    parser = Parser(plant)
    if not parser.package_map().Contains(config.package):
        parser.package_map().Add(config.package, str(PackagePath(config.package)))
    instances = {}
    for side in SIDES:
        try:
            (instance,) = parser.AddModels(url=config.model)
        except Exception as e:  # noqa: BLE001 (parser errors are bad input here)
            raise InputError(
                f"cannot load robot model {config.model!r}: "
                f"{' '.join(str(e).split())[:160]}"
            ) from None
        plant.RenameModelInstance(instance, InstanceName(side))
        base = getattr(config, side).base
        X_WB = RigidTransform(
            RotationMatrix.MakeZRotation(math.radians(base[2])), [base[0], base[1], 0.0]
        )
        plant.WeldFrames(
            plant.world_frame(), plant.GetFrameByName("panda_link0", instance), X_WB
        )
        instances[side] = instance
    return instances


def HandOrientation(side: str, base_yaw_deg: float) -> RotationMatrix:
    """The fixed hand orientation: pointing down, fingers across the arm."""
    return RotationMatrix(
        RollPitchYaw(math.pi, 0.0, math.radians(base_yaw_deg) - math.pi / 4)
    )


def ArmJointNames() -> list[str]:
    return [f"panda_joint{i}" for i in range(1, ARM_JOINTS + 1)]


def SolveHandPosition(
    plant: MultibodyPlant,
    instance,
    p_WG: np.ndarray,
    R_WG: RotationMatrix,
    q_seed: np.ndarray,
) -> np.ndarray:
    """Full-plant positions with the hand's TCP at p_WG, orientation R_WG."""
    context = plant.CreateDefaultContext()
    ik = InverseKinematics(plant, context, with_joint_limits=True)
    frame = plant.GetFrameByName(TCP_FRAME, instance)
    ik.AddPositionConstraint(
        frame, np.zeros(3), plant.world_frame(), p_WG - 1e-4, p_WG + 1e-4
    )
    ik.AddOrientationConstraint(
        frame, RotationMatrix(), plant.world_frame(), R_WG, 1e-3
    )
    prog = ik.get_mutable_prog()
    q = ik.q()
    prog.AddQuadraticErrorCost(np.eye(len(q)) * 1e-2, q_seed, q)
    prog.SetInitialGuess(q, q_seed)
    result = Solve(prog)
    if not result.is_success():
        raise InputError(
            f"the {plant.GetModelInstanceName(instance)} hand cannot "
            f"reach {np.round(p_WG, 3).tolist()} pointing down"
        )
    return result.GetSolution(q)


def HomeSeed(plant: MultibodyPlant) -> np.ndarray:
    """A comfortable seed: elbow up, hand down."""
    q = plant.GetPositions(plant.CreateDefaultContext()).copy()
    seed = [0.0, 0.3, 0.0, -2.0, 0.0, 2.3, 0.0]
    for side in SIDES:
        instance = plant.GetModelInstanceByName(InstanceName(side))
        for name, value in zip(ArmJointNames(), seed, strict=True):
            joint = plant.GetJointByName(name, instance)
            q[joint.position_start()] = value
    return q


def AddArmActuators(plant: MultibodyPlant, instance, config: PandaConfig) -> None:
    """PD-controlled actuators: the simulated position-controlled driver
    (arm joints) and fingers held open. The arms have their weight; the
    driver compensates it (GravityCompensatedCommand)."""
    for name in ArmJointNames() + ["panda_finger_joint1", "panda_finger_joint2"]:
        joint = plant.GetJointByName(name, instance)
        actuator = plant.AddJointActuator(f"{name}_actuator", joint, 1000.0)
        actuator.set_controller_gains(PdControllerGains(p=config.kp, d=config.kd))


@dc.dataclass
class BimanualIk:
    """The control-side differential IK of both arms (its own plant)."""

    controller: DifferentialInverseKinematicsController
    robot: object  # RobotDiagram of the two arms only
    frame_names: dict  # side -> scoped TCP frame name
    arm_position_indices: dict  # side -> indices in the control plant's q


def MakeBimanualIk(scenario: Scenario, dt: float) -> BimanualIk:
    """One DifferentialInverseKinematicsController for both hands, on a
    control-only model of the two arms (no cloth, no table)."""
    config = scenario.grippers.panda
    builder = RobotDiagramBuilder(time_step=0.0)
    plant = builder.plant()
    instances = AddPandaModels(plant, config)
    plant.Finalize()
    robot = builder.Build()
    checker = SceneGraphCollisionChecker(
        model=robot,
        robot_model_instances=list(instances.values()),
        edge_step_size=0.05,
        env_collision_padding=0.0,
    )
    recipe = DifferentialInverseKinematicsSystem.Recipe()
    recipe.AddIngredient(
        DifferentialInverseKinematicsSystem.LeastSquaresCost(
            DifferentialInverseKinematicsSystem.LeastSquaresCost.Config()
        )
    )
    recipe.AddIngredient(
        DifferentialInverseKinematicsSystem.JointCenteringCost(
            DifferentialInverseKinematicsSystem.JointCenteringCost.Config()
        )
    )
    # The model's joint limits: velocities up to `joint_velocity_scale` of
    # theirs, and near a position limit the velocity towards it scaled down
    # to zero (Drake's default margins, 0.0025 / 0.1 rad). Without them an
    # arm at full stretch can flip its elbow through straight (joint 4 past
    # its -0.07 rad limit) and whip the hand 5 cm in 10 ms, which diverges
    # the cloth.
    limits = JointLimits(plant)
    scale = config.joint_velocity_scale
    recipe.AddIngredient(
        DifferentialInverseKinematicsSystem.JointVelocityLimitConstraint(
            DifferentialInverseKinematicsSystem.JointVelocityLimitConstraint.Config(),
            JointLimits(
                limits.position_lower(),
                limits.position_upper(),
                scale * limits.velocity_lower(),
                scale * limits.velocity_upper(),
                limits.acceleration_lower(),
                limits.acceleration_upper(),
            ),
        )
    )
    speed = config.max_hand_speed
    limit = SpatialVelocity(w=np.full(3, 2.0), v=np.full(3, speed))
    nq = plant.num_positions()
    system = DifferentialInverseKinematicsSystem(
        recipe, "world", checker, DofMask(nq, True), dt, 1.0, limit
    )
    controller = DifferentialInverseKinematicsController(system, [])
    names, indices = {}, {}
    for side, instance in instances.items():
        names[side] = (
            plant.GetFrameByName(TCP_FRAME, instance).scoped_name().to_string()
        )
        indices[side] = [
            plant.GetJointByName(n, instance).position_start() for n in ArmJointNames()
        ]
    return BimanualIk(
        controller=controller,
        robot=robot,
        frame_names=names,
        arm_position_indices=indices,
    )


def SolveHandsAt(
    robot_plant: MultibodyPlant, targets: dict, orientations: dict
) -> np.ndarray:
    """Control-plant positions with each hand's TCP at targets[side]."""
    q = HomeSeed(robot_plant)
    for side in SIDES:
        instance = robot_plant.GetModelInstanceByName(InstanceName(side))
        q = SolveHandPosition(
            robot_plant, instance, targets[side], orientations[side], q
        )
    return q


# The Panda's shoulder (joint 2) above its base [m], and how far from it the
# hand targets may go [m]: the arm's reach, less a margin that keeps the IK
# away from full stretch.
SHOULDER_HEIGHT = 0.333
HAND_REACH = 0.80


@dc.dataclass
class BimanualDiffIk:
    """The arms' command side, shared by the simulated and the hardware
    station: gripper targets -> HandTargets -> differential IK -> one joint
    command per arm. What feeds ``arm_states`` (the measured joints) and
    what the commands drive (a plant or LCM drivers) differ."""

    arm_states: LeafSystem  # inputs "{side}_state"
    commands: dict  # side -> ArmCommand (output "position": arm + fingers)
    arm_commanded: dict  # side -> Demultiplexer (output 0: the 7 arm joints)
    initialize: object  # (station, station_context) -> None: IK starts at q0


def AddBimanualDiffIk(
    builder, scenario: Scenario, ik: BimanualIk, q0: np.ndarray, orientations: dict
) -> BimanualDiffIk:
    """Adds hand targets, the bimanual differential IK and per-arm joint
    commands to `builder`; exports ``{side}.ee_target``,
    ``{arm}.position_commanded`` and ``hands.target_saturated``."""
    from fabric_imitation.diagrams.station import StationPorts

    config = scenario.grippers.panda
    dt = scenario.plant_config.time_step
    shoulders = {
        side: np.array([*getattr(config, side).base[:2], SHOULDER_HEIGHT])
        for side in SIDES
    }
    targets = builder.AddNamedSystem(
        "hand_targets",
        HandTargets(
            frame_names=ik.frame_names,
            orientations=orientations,
            shoulders=shoulders,
            reach=HAND_REACH,
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
    nq = ik.robot.plant().num_positions()
    commands, arm_commanded = {}, {}
    for side in SIDES:
        builder.ExportInput(
            targets.GetInputPort(f"{side}.ee_target"), StationPorts.ee_target(side)
        )
        commands[side] = builder.AddNamedSystem(
            f"{side}.arm_command",
            ArmCommand(indices=ik.arm_position_indices[side], nq=nq),
        )
        builder.Connect(
            controller.GetOutputPort("commanded_position"),
            commands[side].GetInputPort("commanded_position"),
        )
        arm_commanded[side] = builder.AddNamedSystem(
            f"{side}.arm_commanded", Demultiplexer([ARM_JOINTS, 2])
        )
        builder.Connect(
            commands[side].GetOutputPort("position"),
            arm_commanded[side].get_input_port(),
        )
        builder.ExportOutput(
            arm_commanded[side].get_output_port(0),
            f"{InstanceName(side)}.position_commanded",
        )
    builder.ExportOutput(targets.GetOutputPort("saturated"), "hands.target_saturated")
    q_start = np.array(q0, copy=True)

    def initialize(station, station_context):
        ik_controller = station.GetSubsystemByName("diff_ik")
        ik_controller.set_initial_position(
            station.GetMutableSubsystemContext(ik_controller, station_context), q_start
        )

    return BimanualDiffIk(
        arm_states=stack,
        commands=commands,
        arm_commanded=arm_commanded,
        initialize=initialize,
    )


@dc.dataclass
class PandaGrippers:
    """Arms added to a station plant; `Wire` connects them after Finalize."""

    scenario: Scenario
    plant: MultibodyPlant
    scene_graph: object
    instances: dict
    tcp_bodies: dict
    X_TcpClip: dict
    ik: BimanualIk
    q0: np.ndarray  # control-plant positions at the grasp corners
    orientations: dict

    def Wire(self, builder, *, joint_commands: bool = False):
        """Targets -> HandTargets -> diff IK -> joint PD; exports the ports.
        Returns the context initializer.

        With `joint_commands` the arms take joint positions from outside
        instead (what a Panda driver does with an lcmt_panda_command): input
        ``{arm}.position_command`` (7) per arm, plus output
        ``{arm}.velocity_measured``; no IK, no ``ee_target`` inputs, no
        initializer (the arms start at the grasp configuration)."""
        from fabric_imitation.diagrams.station import StationPorts

        plant, scenario = self.plant, self.scenario
        dt = scenario.plant_config.time_step
        robot_plant = self.ik.robot.plant()
        # Default joint angles: the IK solution at the grasp corners.
        for side, instance in self.instances.items():
            robot_instance = robot_plant.GetModelInstanceByName(InstanceName(side))
            for name in ArmJointNames():
                q = self.q0[
                    robot_plant.GetJointByName(name, robot_instance).position_start()
                ]
                plant.GetJointByName(name, instance).set_default_angle(q)
            for name in ("panda_finger_joint1", "panda_finger_joint2"):
                plant.GetJointByName(name, instance).set_default_translation(
                    FINGER_OPENING
                )
        tcp = builder.AddNamedSystem(
            "tcp_positions",
            TcpPositions(
                body_indices={side: self.tcp_bodies[side].index() for side in SIDES}
            ),
        )
        builder.Connect(
            plant.get_body_poses_output_port(), tcp.GetInputPort("body_poses")
        )
        if joint_commands:
            self._WireJointCommands(builder, tcp)
            return None
        diff_ik = AddBimanualDiffIk(
            builder, scenario, self.ik, self.q0, self.orientations
        )
        for side in SIDES:
            builder.Connect(
                plant.get_state_output_port(self.instances[side]),
                diff_ik.arm_states.GetInputPort(f"{side}_state"),
            )
            interpolator = builder.AddNamedSystem(
                f"{side}.joint_interpolator",
                StateInterpolatorWithDiscreteDerivative(ARM_JOINTS + 2, dt, True),
            )
            builder.Connect(
                diff_ik.commands[side].GetOutputPort("position"),
                interpolator.get_input_port(),
            )
            self._ConnectDesiredState(builder, side, interpolator.get_output_port())
            builder.ExportOutput(
                tcp.GetOutputPort(side), StationPorts.ee_measured(side)
            )
            arm_q = builder.AddNamedSystem(
                f"{side}.arm_positions", Demultiplexer([ARM_JOINTS, 2, ARM_JOINTS + 2])
            )
            builder.Connect(
                plant.get_state_output_port(self.instances[side]),
                arm_q.get_input_port(),
            )
            builder.ExportOutput(
                arm_q.get_output_port(0), f"{InstanceName(side)}.position_measured"
            )
        return diff_ik.initialize

    def _ConnectDesiredState(self, builder, side: str, desired_state) -> None:
        """desired_state -> the driver's gravity compensation -> the arm's
        PD actuators in the station plant."""
        control = self.ik.robot.plant()
        compensation = builder.AddNamedSystem(
            f"{side}.gravity_compensation",
            GravityCompensatedCommand(
                control,
                control.GetModelInstanceByName(InstanceName(side)),
                self.scenario.grippers.panda.kp,
            ),
        )
        builder.Connect(desired_state, compensation.GetInputPort("desired_state"))
        builder.Connect(
            self.plant.get_state_output_port(self.instances[side]),
            compensation.GetInputPort("measured_state"),
        )
        builder.Connect(
            compensation.get_output_port(),
            self.plant.get_desired_state_input_port(self.instances[side]),
        )

    def _WireJointCommands(self, builder, tcp) -> None:
        from fabric_imitation.diagrams.station import StationPorts

        dt = self.scenario.plant_config.time_step
        fingers = builder.AddNamedSystem(
            "finger_opening", ConstantVectorSource([FINGER_OPENING] * 2)
        )
        for side in SIDES:
            arm = InstanceName(side)
            command = builder.AddNamedSystem(
                f"{side}.arm_command", Multiplexer([ARM_JOINTS, 2])
            )
            builder.ExportInput(command.get_input_port(0), f"{arm}.position_command")
            builder.Connect(fingers.get_output_port(), command.get_input_port(1))
            interpolator = builder.AddNamedSystem(
                f"{side}.joint_interpolator",
                StateInterpolatorWithDiscreteDerivative(ARM_JOINTS + 2, dt, True),
            )
            builder.Connect(command.get_output_port(), interpolator.get_input_port())
            self._ConnectDesiredState(builder, side, interpolator.get_output_port())
            state = builder.AddNamedSystem(
                f"{side}.arm_state", Demultiplexer([ARM_JOINTS, 2, ARM_JOINTS, 2])
            )
            builder.Connect(
                self.plant.get_state_output_port(self.instances[side]),
                state.get_input_port(),
            )
            builder.ExportOutput(state.get_output_port(0), f"{arm}.position_measured")
            builder.ExportOutput(state.get_output_port(2), f"{arm}.velocity_measured")
            builder.ExportOutput(
                tcp.GetOutputPort(side), StationPorts.ee_measured(side)
            )


def AddPandaGrippers(
    builder, plant: MultibodyPlant, scene_graph, scenario: Scenario, corners: dict
) -> PandaGrippers:
    """Adds both arms to the station plant (before Finalize): models and
    the PD actuators of the simulated driver (which compensates the arms'
    weight); solves the grasp configuration on the control model."""
    config = scenario.grippers.panda
    dt = scenario.plant_config.time_step
    ik = MakeBimanualIk(scenario, dt)
    orientations = {
        side: HandOrientation(side, getattr(config, side).base[2]) for side in SIDES
    }
    q0 = SolveHandsAt(ik.robot.plant(), corners, orientations)
    instances = AddPandaModels(plant, config)
    tcp_bodies, X_TcpClip = {}, {}
    for side, instance in instances.items():
        AddArmActuators(plant, instance, config)
        tcp_bodies[side] = plant.GetBodyByName(TCP_FRAME, instance)
        # The clip stays world-aligned at the corner while the hand points down.
        X_TcpClip[side] = RigidTransform(orientations[side].inverse(), np.zeros(3))
    FilterArmCollisions(plant, scene_graph, instances)
    ShowArmsToCameras(plant, config, instances)
    AddMounts(plant, config)
    return PandaGrippers(
        scenario=scenario,
        plant=plant,
        scene_graph=scene_graph,
        instances=instances,
        tcp_bodies=tcp_bodies,
        X_TcpClip=X_TcpClip,
        ik=ik,
        q0=q0,
        orientations=orientations,
    )


ARM_LABEL = 3  # render label of the arms in the camera's label image
ARM_RGBA = (0.82, 0.82, 0.85, 1.0)
# Link -> (collision mesh of the package, yaw of its visual origin [rad]).
_LINK_MESHES = {
    **{f"panda_link{i}": (f"link{i}.stl", 0.0) for i in range(8)},
    "panda_hand": ("hand.stl", 0.0),
    "panda_leftfinger": ("finger.stl", 0.0),
    "panda_rightfinger": ("finger.stl", math.pi),
}


MOUNT_SIZE = (0.24, 0.24, 0.75)  # [m] pedestal under each Panda base, to the floor


def AddMounts(plant, config: PandaConfig) -> None:
    """A pedestal under each arm's base, from the floor to the table top (seen
    by meshcat and the cameras; it touches nothing)."""
    from pydrake.geometry import (
        Box,
        GeometryInstance,
        IllustrationProperties,
        PerceptionProperties,
        RenderLabel,
        Rgba,
    )

    color = Rgba(0.3, 0.3, 0.32, 1.0)
    for side in SIDES:
        base = getattr(config, side).base
        X_WM = RigidTransform([base[0], base[1], -MOUNT_SIZE[2] / 2])
        geometry = GeometryInstance(X_WM, Box(*MOUNT_SIZE), f"{side}_panda_mount")
        illustration = IllustrationProperties()
        illustration.AddProperty("phong", "diffuse", color)
        geometry.set_illustration_properties(illustration)
        perception = PerceptionProperties()
        perception.AddProperty("label", "id", RenderLabel(ARM_LABEL))
        perception.AddProperty("phong", "diffuse", color)
        geometry.set_perception_properties(perception)
        plant.RegisterVisualGeometry(plant.world_body(), geometry)


def StlToObj(data: bytes) -> str:
    """A binary STL's triangles as Wavefront OBJ text (shared vertices, one
    normal per face: the renderer needs normals)."""
    (count,) = np.frombuffer(data[80:84], np.uint32)
    records = np.frombuffer(
        data[84 : 84 + 50 * int(count)],
        dtype=np.dtype([("n", "<f4", 3), ("v", "<f4", (3, 3)), ("a", "<u2")]),
    )
    corners = records["v"].astype(float)
    normals = np.cross(corners[:, 1] - corners[:, 0], corners[:, 2] - corners[:, 0])
    normals /= np.maximum(np.linalg.norm(normals, axis=1, keepdims=True), 1e-12)
    points, faces = np.unique(corners.reshape(-1, 3), axis=0, return_inverse=True)
    faces = faces.reshape(-1, 3) + 1
    lines = [f"v {x:.6f} {y:.6f} {z:.6f}" for x, y, z in points]
    lines += [f"vn {x:.6f} {y:.6f} {z:.6f}" for x, y, z in normals]
    lines += [
        f"f {a}//{k} {b}//{k} {c}//{k}" for k, (a, b, c) in enumerate(faces, start=1)
    ]
    return "\n".join(lines) + "\n"


def ShowArmsToCameras(plant, config: PandaConfig, instances) -> None:
    """Gives each arm link a perception-only copy of its collision mesh (the
    package's .stl, converted to OBJ in memory), so the cameras render the
    arms: the model's visual meshes are .dae, which Drake's VTK renderer
    skips. The top-down camera then sees the arms cover the cloth as a real
    camera would (label ARM_LABEL: not cloth in the fabric mask)."""
    from pydrake.common import MemoryFile
    from pydrake.geometry import (
        GeometryInstance,
        InMemoryMesh,
        Mesh,
        PerceptionProperties,
        RenderLabel,
        Rgba,
    )

    folder = PackagePath(config.package) / "robots/panda_description/meshes/collision"
    objs = {}
    for link, (stl, yaw) in _LINK_MESHES.items():
        if stl not in objs:
            path = folder / stl
            if not path.is_file():
                return  # another robot package layout: the arms stay unseen
            objs[stl] = StlToObj(path.read_bytes())
        for side, instance in instances.items():
            if not plant.HasBodyNamed(link, instance):
                continue
            shape = Mesh(InMemoryMesh(mesh_file=MemoryFile(objs[stl], ".obj", stl)))
            geometry = GeometryInstance(
                RigidTransform(RotationMatrix.MakeZRotation(yaw), np.zeros(3)),
                shape,
                f"{side}_{link}_seen",
            )
            properties = PerceptionProperties()
            properties.AddProperty("label", "id", RenderLabel(ARM_LABEL))
            properties.AddProperty("phong", "diffuse", Rgba(*ARM_RGBA))
            geometry.set_perception_properties(properties)
            plant.RegisterVisualGeometry(plant.GetBodyByName(link, instance), geometry)


def FilterArmCollisions(plant, scene_graph, instances) -> None:
    """The arms touch nothing (contact with the cloth and table is not
    modelled; the safe action set keeps the hands clear of the object)."""
    from pydrake.geometry import CollisionFilterDeclaration, GeometrySet

    arm_bodies = [
        b
        for inst in instances.values()
        for b in (plant.get_body(i) for i in plant.GetBodyIndices(inst))
    ]
    arm = GeometrySet(
        [g for b in arm_bodies for g in plant.GetCollisionGeometriesForBody(b)]
    )
    everything = GeometrySet(scene_graph.model_inspector().GetAllGeometryIds())
    scene_graph.collision_filter_manager().Apply(
        CollisionFilterDeclaration().ExcludeBetween(arm, everything)
    )
