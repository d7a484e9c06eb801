"""The cloth station: MultibodyPlant + SceneGraph with table, task object, FEM
cloth, two grippers holding the cloth's near corners, and a top-down RGB-D
camera. Built from a Scenario, in the manner of `MakeHardwareStation`.

Exported ports (names in `StationPorts`):

    inputs   left.ee_target, right.ee_target   gripper position targets, world [m]
             release                           > 0.5 opens both grasps (latched)
    outputs  left.ee_position_measured, right.ee_position_measured
             camera.rgb_image, camera.depth_image, camera.label_image
             camera.fabric_mask                 ImageGrey8U, 255 on the cloth
             object.pose                        RigidTransform X_WO
             released                           1 once the grasps are open
             cloth.positions                    simulation only: 3N vertex positions
             cloth.keypoints                    simulation only: 3M ordered keypoints
             camera.people_rgb_image            with people_camera=True: an oblique
                                                480 x 480 view for videos

Opening the FEM grasps changes plant parameters, which no event may do: run
a station with `AdvanceStationTo(simulator, station, t)` instead of
`simulator.AdvanceTo(t)` (the runners in this package do); it opens them
between steps once `released` turns on.
"""

import dataclasses as dc
import os
from pathlib import Path

import numpy as np
from fabric_imitation.learning.errors import InputError
from fabric_imitation.learning.object_shape import ObjectParts
from fabric_imitation.learning.state import NUM_KEYPOINTS, SIDES
from fabric_imitation.scenarios.poses import ClothPose, GraspCorners, PoseOnTable
from fabric_imitation.scenarios.schema import Scenario
from fabric_imitation.systems.cloth_mesh import ClothMesh, MakeClothMesh, TopTriangles
from fabric_imitation.systems.gripper_contact import (
    ANCHOR_CAPSULES,
    ANCHOR_HAND_YAW,
    AnchorHandCapsules,
    GripperBody,
    GripperObjectContact,
    PandaLinkCapsules,
)
from fabric_imitation.systems.station_parts import (
    ClothGroundTruth,
    FabricMask,
    ReleaseLatch,
)
from pydrake.common import MemoryFile
from pydrake.common.value import AbstractValue
from pydrake.geometry import (
    AddContactMaterial,
    Box,
    Capsule,
    CollisionFilterDeclaration,
    Cylinder,
    GeometryInstance,
    GeometrySet,
    InMemoryMesh,
    MakePhongIllustrationProperties,
    MakeRenderEngineVtk,
    Mesh,
    MeshcatVisualizer,
    MeshcatVisualizerParams,
    PerceptionProperties,
    ProximityProperties,
    RenderEngineVtkParams,
    RenderLabel,
    Rgba,
    Role,
    Sphere,
)
from pydrake.math import RigidTransform, RotationMatrix
from pydrake.multibody.fem import DeformableBodyConfig, MaterialModel
from pydrake.multibody.plant import (
    AddMultibodyPlant,
    CoulombFriction,
    MultibodyPlant,
)
from pydrake.multibody.tree import (
    PdControllerGains,
    PrismaticJoint,
    SpatialInertia,
)
from pydrake.systems.analysis import Simulator
from pydrake.systems.framework import Diagram, DiagramBuilder
from pydrake.systems.primitives import (
    ConstantValueSource,
    Demultiplexer,
    StateInterpolatorWithDiscreteDerivative,
)
from pydrake.systems.sensors import CameraInfo, RgbdSensor

CLOTH_LABEL = 7
TABLE_LABEL = 1
OBJECT_LABEL = 2
CLIP_RADIUS = 0.01


class StationPorts:
    """Port names of the station (one place, so nobody retypes them)."""

    @staticmethod
    def ee_target(side: str) -> str:
        return f"{side}.ee_target"

    @staticmethod
    def ee_measured(side: str) -> str:
        return f"{side}.ee_position_measured"

    RELEASE = "release"
    RELEASED = "released"
    RGB = "camera.rgb_image"
    DEPTH = "camera.depth_image"
    LABEL = "camera.label_image"
    MASK = "camera.fabric_mask"
    OBJECT_POSE = "object.pose"
    CLOTH_POSITIONS = "cloth.positions"
    CLOTH_KEYPOINTS = "cloth.keypoints"
    PEOPLE_RGB = "camera.people_rgb_image"  # only with people_camera=True
    # Simulation only, with a task object: gripper-object contact so far
    # (GripperObjectContact's ``contact``: plant steps, first time, depth).
    GRIPPER_OBJECT_CONTACT = "grippers.object_contact"
    # Only with raw_camera_scale: the control camera's view at that many
    # times its resolution, as an RGB-D camera driver gives it.
    RAW_RGB = "camera.raw_rgb_image"
    RAW_DEPTH = "camera.raw_depth_image"


@dc.dataclass(frozen=True)
class ClothStation:
    """A built cloth station, as `MakeClothStation` returns it.

    `diagram` is the Drake Diagram to add to a builder; its ports are named by
    StationPorts. The other fields are what runners need besides ports. Keep
    this object for as long as the diagram is used: it also holds objects the
    diagram's systems refer to (`keep_alive`). On a hardware station the
    simulation-only fields are None.
    """

    diagram: Diagram
    scenario: Scenario
    camera_info: CameraInfo
    X_WCamera: RigidTransform
    X_WO: RigidTransform
    plant: MultibodyPlant | None = None
    mesh: ClothMesh | None = None
    cloth_id: object = None  # fem: DeformableBodyId; vbd: the ClothSimulator
    weld_ids: tuple = ()  # fem: the clip welds (MultibodyConstraintId)
    clips: tuple = ()  # fem: the clip bodies (RigidBody)
    X_WCloth: RigidTransform | None = None
    initialize: object = None  # callable(diagram, diagram_context) or None
    keep_alive: tuple = ()
    hardware: bool = False


_MATERIALS = {
    "linear_corotated": MaterialModel.kLinearCorotated,
    "corotated": MaterialModel.kCorotated,
    "neohookean": MaterialModel.kNeoHookean,
    "linear": MaterialModel.kLinear,
}


# Point-contact stiffness [N/m] of the rigid geometry the grippers meet (the
# table, the task object and the anchors' hands): a hand pushed against the
# object by its full actuator force (kp x 5 cm, 150 N) sinks about 0.3 mm in,
# where the plant's default stiffness lets it sink 7 mm.
RIGID_POINT_STIFFNESS = 1e6


def _friction_props(
    mu: float, point_stiffness: float | None = None
) -> ProximityProperties:
    props = ProximityProperties()
    AddContactMaterial(
        friction=CoulombFriction(mu, mu),
        point_stiffness=point_stiffness,
        properties=props,
    )
    return props


def _static_parts(scenario: Scenario, X_WO: RigidTransform) -> dict:
    """Name -> (X_WP part centre in world, shape "box" or "cylinder" (its
    axis along the part frame's z), size, friction) of the table and the
    task object's parts (learning/object_shape.py), if it has any."""
    table, obj = scenario.table, scenario.object
    parts = {
        "table": (
            RigidTransform([0, 0, -table.size[2] / 2]),
            "box",
            table.size,
            table.friction,
        )
    }
    if obj.kind != "none":
        shapes = ObjectParts(obj.kind, obj.size)
        for i, part in enumerate(shapes):
            # Drake's and newton's cylinders run along z; a bar along x is
            # turned onto it.
            R = (
                RotationMatrix.MakeYRotation(np.pi / 2)
                if part.axis == "x"
                else RotationMatrix()
            )
            name = "object" if len(shapes) == 1 else f"object_{i}"
            parts[name] = (
                X_WO @ RigidTransform(R, list(part.centre)),
                part.kind,
                part.size,
                obj.friction,
            )
    return parts


def _add_table_and_object(plant: MultibodyPlant, scenario: Scenario) -> RigidTransform:
    obj = scenario.object
    X_WO = PoseOnTable(obj.pose)
    parts = _static_parts(scenario, X_WO)
    X_WB, _, size, mu = parts.pop("table")
    _register_shape(
        plant,
        plant.world_body(),
        X_WB,
        "box",
        size,
        "table",
        mu,
        Rgba(0.72, 0.56, 0.40, 1.0),
        TABLE_LABEL,
    )
    if parts:
        body = plant.AddRigidBody(
            "object",
            plant.AddModelInstance("object"),
            SpatialInertia.SolidBoxWithMass(1.0, *obj.size),
        )
        plant.WeldFrames(plant.world_frame(), body.body_frame(), X_WO)
        for name, (X_WP, shape, size, mu) in parts.items():
            _register_shape(
                plant,
                body,
                X_WO.inverse() @ X_WP,
                shape,
                size,
                name.replace("object", obj.kind),
                mu,
                Rgba(0.25, 0.35, 0.75, 1.0),
                OBJECT_LABEL,
            )
        if obj.marker.id >= 0:
            _add_marker_plaque(plant, body, obj.marker)
    return X_WO


# A marker's printed sheet: the black square plus a white margin of one
# marker cell each side (4 x 4 markers are 6 cells wide with their border).
MARKER_MARGIN_CELLS = 1


def MarkerTexture(dictionary: str, marker_id: int) -> Path:
    """A PNG of ArUco marker `marker_id` of `dictionary` with a white margin
    (generated by OpenCV, cached under the user's cache directory)."""
    import cv2

    cache = (
        Path(os.environ.get("XDG_CACHE_HOME", Path.home() / ".cache"))
        / "fabric-imitation"
        / "markers"
    )
    path = cache / f"{dictionary}_{marker_id}.png"
    if path.is_file():
        return path
    cache.mkdir(parents=True, exist_ok=True)
    aruco = cv2.aruco.getPredefinedDictionary(getattr(cv2.aruco, dictionary))
    cells = aruco.markerSize + 2
    pixels = 60 * cells
    image = cv2.aruco.generateImageMarker(aruco, marker_id, pixels)
    margin = 60 * MARKER_MARGIN_CELLS
    image = cv2.copyMakeBorder(
        image, margin, margin, margin, margin, cv2.BORDER_CONSTANT, value=255
    )
    tmp = path.with_name(f"{path.stem}.{os.getpid()}.png")
    cv2.imwrite(str(tmp), cv2.cvtColor(image, cv2.COLOR_GRAY2BGR))
    tmp.replace(path)
    return path


def _add_marker_plaque(plant: MultibodyPlant, body, marker) -> None:
    """The marker printed on a 1 mm plaque lying on the object's surface at
    the marker's offset height (its face 1 mm above it; visual only: the
    cloth does not touch it)."""
    import cv2

    cells = (
        cv2.aruco.getPredefinedDictionary(
            getattr(cv2.aruco, marker.dictionary)
        ).markerSize
        + 2
    )
    side = marker.size * (cells + 2 * MARKER_MARGIN_CELLS) / cells
    x, y, z, yaw = marker.offset
    X_OP = RigidTransform(
        RotationMatrix.MakeZRotation(np.radians(yaw)), [x, y, z + 0.0005]
    )
    instance = GeometryInstance(X_OP, Box(side, side, 0.001), "marker")
    texture = str(MarkerTexture(marker.dictionary, marker.id))
    illustration = MakePhongIllustrationProperties([1.0, 1.0, 1.0, 1.0])
    illustration.AddProperty("phong", "diffuse_map", texture)
    instance.set_illustration_properties(illustration)
    perception = _perception(Rgba(1.0, 1.0, 1.0, 1.0), OBJECT_LABEL)
    perception.AddProperty("phong", "diffuse_map", texture)
    instance.set_perception_properties(perception)
    plant.RegisterVisualGeometry(body, instance)


HAND_LABEL = 4
HAND_RADIUS = 0.035  # [m]
HAND_RGBA = (0.87, 0.66, 0.54, 1.0)  # skin


def _add_hands(plant: MultibodyPlant, holders: dict, X_holder_clip: dict) -> None:
    """A skin-coloured sphere at each gripper, seen by the cameras only: the
    operator's hands in a simulated person's demo."""
    for side in SIDES:
        instance = GeometryInstance(
            X_holder_clip[side], Sphere(HAND_RADIUS), f"{side}_hand"
        )
        instance.set_illustration_properties(
            MakePhongIllustrationProperties(list(HAND_RGBA))
        )
        instance.set_perception_properties(_perception(Rgba(*HAND_RGBA), HAND_LABEL))
        plant.RegisterVisualGeometry(holders[side], instance)


def _register_shape(
    plant, body, X_BG, kind, size, name, mu, color: Rgba, label: int
) -> None:
    """A box, or a cylinder (size: diameter, diameter, length along z), with
    collision, illustration and perception roles."""
    shape = Cylinder(size[0] / 2, size[2]) if kind == "cylinder" else Box(*size)
    plant.RegisterCollisionGeometry(
        body, X_BG, shape, name, _friction_props(mu, RIGID_POINT_STIFFNESS)
    )
    instance = GeometryInstance(X_BG, shape, name)
    instance.set_illustration_properties(MakePhongIllustrationProperties(color.rgba))
    instance.set_perception_properties(_perception(color, label))
    plant.RegisterVisualGeometry(body, instance)


def _perception(color: Rgba, label: int) -> PerceptionProperties:
    """Perception role with a render label, so the camera's label image tells
    table, object and cloth apart."""
    perception = PerceptionProperties()
    perception.AddProperty("label", "id", RenderLabel(label))
    perception.AddProperty("phong", "diffuse", color)
    return perception


def _cloth_instance(
    mesh: ClothMesh, X_WC: RigidTransform, color=(0.85, 0.15, 0.15)
) -> GeometryInstance:
    """The slab as a deformable geometry with illustration and perception
    (render label) roles, for either engine, in `color` (RGB)."""
    shape = Mesh(InMemoryMesh(mesh_file=MemoryFile(mesh.to_vtk(), ".vtk", "cloth.vtk")))
    instance = GeometryInstance(X_WC, shape, "cloth")
    instance.set_illustration_properties(MakePhongIllustrationProperties([*color, 1.0]))
    instance.set_perception_properties(_perception(Rgba(*color, 1.0), CLOTH_LABEL))
    return instance


def _add_cloth(plant: MultibodyPlant, scenario: Scenario, mesh: ClothMesh):
    cloth = scenario.cloth
    X_WC = ClothPose(scenario)
    instance = _cloth_instance(mesh, X_WC, scenario.cloth.color)
    instance.set_proximity_properties(_friction_props(cloth.friction))
    config = DeformableBodyConfig()
    config.set_youngs_modulus(cloth.youngs_modulus)
    config.set_poissons_ratio(cloth.poissons_ratio)
    config.set_mass_density(cloth.mass_density)
    config.set_mass_damping_coefficient(cloth.mass_damping)
    config.set_stiffness_damping_coefficient(cloth.stiffness_damping)
    config.set_material_model(_MATERIALS[cloth.material_model])
    model = plant.mutable_deformable_model()
    cloth_id = model.RegisterDeformableBody(instance, config, 1.0)
    return cloth_id, X_WC


def ClothResolution(scenario: Scenario) -> list[int]:
    """(nx, ny, nz) of the cloth's slab mesh: the FEM resolution, or the VBD
    sheet's grid with two layers (its top face and one thickness below)."""
    cloth = scenario.cloth
    if cloth.engine == "fem":
        return list(cloth.resolution)
    return [*cloth.vbd.resolution, 2]


def GraspedVertices(scenario: Scenario, p_C: np.ndarray) -> dict:
    """Side -> indices of the points p_C (cloth frame) inside each grasped
    corner's g x g capture square (inclusive, 0.5 mm slack)."""
    cloth = scenario.cloth
    g = cloth.grasp_size + 5e-4
    hx, hy = cloth.size[0] / 2, cloth.size[1] / 2
    near = p_C[:, 1] <= -hy + g
    return {
        "left": np.flatnonzero(near & (p_C[:, 0] <= -hx + g)),
        "right": np.flatnonzero(near & (p_C[:, 0] >= hx - g)),
    }


def _add_vbd_cloth(builder, scene_graph, scenario, mesh, X_WC, X_WO):
    """The VBD cloth system, with its slab registered as a deformable
    geometry of its own SceneGraph source (camera and meshcat see it)."""
    from fabric_imitation.systems.cloth_simulator import (
        ClothSimulator,
        StaticCollider,
    )

    cloth, vbd = scenario.cloth, scenario.cloth.vbd
    source = scene_graph.RegisterSource("vbd_cloth")
    geometry_id = scene_graph.RegisterDeformableGeometry(
        source,
        scene_graph.world_frame_id(),
        _cloth_instance(mesh, X_WC, scenario.cloth.color),
        1.0,
    )
    top = mesh.top_layer.ravel()
    colliders = [
        StaticCollider(
            X_WB,
            tuple(size),
            mu,
            contact=vbd.table_contact if name == "table" else "surface",
            shape=shape,
        )
        for name, (X_WB, shape, size, mu) in _static_parts(scenario, X_WO).items()
    ]
    system = ClothSimulator(
        sheet_W=(
            X_WC.GetAsMatrix34() @ np.c_[mesh.vertices[top], np.ones(len(top))].T
        ).T,
        triangles=TopTriangles(
            np.arange(len(top)).reshape(mesh.top_layer.shape),
            checkerboard=vbd.triangulation == "checkerboard",
        ),
        slab_top=top,
        slab_bottom=mesh.grid[:, :, 0].ravel(),
        thickness=cloth.thickness,
        keypoint_vertices=mesh.keypoint_vertices(NUM_KEYPOINTS),
        grasped=GraspedVertices(scenario, mesh.vertices[top]),
        grippers_W0=GraspCorners(scenario),
        colliders=colliders,
        settings=vbd,
        friction=cloth.friction,
        time_step=scenario.plant_config.time_step,
        geometry_id=geometry_id,
    )
    system = builder.AddNamedSystem("vbd_cloth", system)
    builder.Connect(
        system.GetOutputPort("geometry_configuration"),
        scene_graph.get_source_configuration_port(source),
    )
    return system


def _add_xyz_joints(
    plant: MultibodyPlant, instance, body, p_W0: np.ndarray, carriage_mass: float
) -> list[PrismaticJoint]:
    """Mounts `body` on world through x, y, z prismatic joints (two light
    carriages in between), starting at p_W0."""
    carriage = SpatialInertia.SolidSphereWithMass(carriage_mass, 0.01)
    carriage_x = plant.AddRigidBody("carriage_x", instance, carriage)
    carriage_y = plant.AddRigidBody("carriage_y", instance, carriage)
    parents = [plant.world_body(), carriage_x, carriage_y]
    children = [carriage_x, carriage_y, body]
    joints = []
    for axis in range(3):
        joint = plant.AddJoint(
            PrismaticJoint(
                "xyz"[axis],
                parents[axis].body_frame(),
                children[axis].body_frame(),
                np.eye(3)[axis],
                -1.0,
                1.0,
                0.0,
            )
        )
        joint.set_default_translation(p_W0[axis])
        joints.append(joint)
    return joints


def _add_anchor(plant: MultibodyPlant, scenario: Scenario, side: str, p_W0: np.ndarray):
    """A gripper on x/y/z prismatic joints with PD-controlled actuators."""
    g = scenario.grippers
    instance = plant.AddModelInstance(f"{side}_anchor")
    anchor = plant.AddRigidBody(
        "anchor", instance, SpatialInertia.SolidSphereWithMass(g.anchor_mass, 0.02)
    )
    for joint in _add_xyz_joints(plant, instance, anchor, p_W0, 0.05):
        actuator = plant.AddJointActuator(joint.name(), joint, 200.0)
        actuator.set_controller_gains(PdControllerGains(p=g.kp, d=g.kd))
    plant.RegisterVisualGeometry(
        anchor, RigidTransform(), Sphere(0.012), f"{side}_anchor", [0.2, 0.2, 0.2, 1.0]
    )
    # Collision role only (the cameras see the sphere alone): a Franka
    # hand holding the corner from above, so the table and the task object
    # stop the anchor as they would stop the hand. The prior scene, which has
    # no object, keeps its grippers as the shipped priors were collected
    # with: free over the table (its safe actions keep them above it).
    solid = scenario.object.kind != "none"
    for k, capsule in enumerate(ANCHOR_CAPSULES if solid else ()):
        a, b = np.array(capsule.p_a), np.array(capsule.p_b)
        X_AG = RigidTransform(
            ANCHOR_HAND_YAW @ RotationMatrix.MakeFromOneVector(b - a, 2),
            ANCHOR_HAND_YAW @ ((a + b) / 2),
        )
        plant.RegisterCollisionGeometry(
            anchor,
            X_AG,
            Capsule(capsule.radius, float(np.linalg.norm(b - a))),
            f"{side}_hand_{k}",
            _friction_props(0.5, RIGID_POINT_STIFFNESS),
        )
    plant.gravity_field().set_enabled(instance, False)
    return instance, anchor


def _gripper_bodies(plant: MultibodyPlant, scenario: Scenario) -> list[GripperBody]:
    """The plant bodies that make up the grippers, with their capsules."""
    if scenario.grippers.kind == "panda":
        return [
            GripperBody(
                int(plant.GetBodyByName(link, instance).index()), capsules, link
            )
            for instance in (
                plant.GetModelInstanceByName(f"{side}_panda") for side in SIDES
            )
            for link, capsules in PandaLinkCapsules().items()
        ]
    yawed = AnchorHandCapsules()
    return [
        GripperBody(
            int(
                plant.GetBodyByName(
                    "anchor", plant.GetModelInstanceByName(f"{side}_anchor")
                ).index()
            ),
            yawed,
            f"{side}_anchor",
        )
        for side in SIDES
    ]


def _filter_anchor_collisions(plant: MultibodyPlant, scene_graph, cloth_id) -> None:
    """The anchors' hands touch the table and the task object only: not each
    other, and not the FEM cloth they hold (the grasp is a weld)."""
    hands = GeometrySet(
        [
            g
            for side in SIDES
            for g in plant.GetCollisionGeometriesForBody(
                plant.GetBodyByName(
                    "anchor", plant.GetModelInstanceByName(f"{side}_anchor")
                )
            )
        ]
    )
    declaration = CollisionFilterDeclaration().ExcludeWithin(hands)
    if cloth_id is not None:
        declaration.ExcludeBetween(
            hands, GeometrySet(plant.deformable_model().GetGeometryId(cloth_id))
        )
    scene_graph.collision_filter_manager().Apply(declaration)


def _add_clip(
    plant: MultibodyPlant,
    scenario: Scenario,
    side: str,
    holder,
    X_HolderClip: RigidTransform,
    cloth_id,
    X_WC: RigidTransform,
    p_W0: np.ndarray,
):
    """A light free clip that carries the grasped corner, welded to the gripper.

    The corner's vertices are fixed to the clip; releasing switches the weld
    off (a deformable fixed constraint itself cannot be switched off in Drake
    1.58).
    """
    cloth = scenario.cloth
    instance = plant.AddModelInstance(f"{side}_clip")
    # Heavy while grasped: SAP regularises a weld by the welded bodies' masses,
    # and a gram-scale clip lets the cloth pull it 8 cm off the gripper.
    # The release monitor makes it light again.
    clip = plant.AddRigidBody(
        "clip",
        instance,
        SpatialInertia.SolidSphereWithMass(scenario.grippers.anchor_mass, CLIP_RADIUS),
    )
    X_WClip = RigidTransform(p_W0)
    plant.SetDefaultFloatingBaseBodyPose(clip, X_WClip)
    plant.gravity_field().set_enabled(instance, False)
    weld_id = plant.AddWeldConstraint(holder, X_HolderClip, clip, RigidTransform())
    # Capture region: a g x g square reaching inwards from the corner.
    g = cloth.grasp_size
    sign = -1.0 if side == "left" else 1.0
    p_C_center = np.array(
        [sign * (cloth.size[0] / 2 - g / 2), -(cloth.size[1] / 2 - g / 2), 0.0]
    )
    X_WG = RigidTransform(X_WC.rotation(), X_WC @ p_C_center)
    X_ClipG = X_WClip.inverse() @ X_WG
    # Slightly larger than g so vertices exactly on the square's edge count.
    shape = Box(g + 1e-3, g + 1e-3, 4 * cloth.thickness)
    plant.mutable_deformable_model().AddFixedConstraint(
        cloth_id, clip, X_WClip.inverse() @ X_WC, shape, X_ClipG
    )
    return weld_id, clip


def MakeClothStation(
    scenario: Scenario,
    *,
    meshcat=None,
    hardware: bool = False,
    lcm=None,
    joint_commands: bool = False,
    people_camera: bool = False,
    raw_camera_scale: int = 0,
) -> ClothStation:
    """Builds the cloth station for `scenario` (see module docstring) and
    returns it as a ClothStation: add `.diagram` to a builder.

    With `hardware=True` (Panda grippers only) the same ports are made of LCM
    drivers (diagrams/hardware.py) on `lcm` (default: the scenario's bus).

    With `grippers.kind: panda` the grippers are two Franka Pandas driven by
    one bimanual differential-IK controller inside the station; the ports are
    the same, plus each arm's joint positions and the IK saturation flags.
    Call `InitializeStation(station, station_context)` on a new context (the
    runners here do) before simulating. With `joint_commands=True` the
    simulated arms take joint positions (``{arm}.position_command``) instead
    of gripper targets, as real Panda drivers do (diagrams/hardware.py's
    `MakeSimulatedLab` puts such a station behind LCM).

    Args:
        scenario: a validated Scenario.
        meshcat: optional pydrake Meshcat to visualise in.
    """
    if (hardware or joint_commands) and scenario.grippers.kind != "panda":
        raise InputError(
            "a hardware station or joint commands need grippers.kind: panda"
        )
    if hardware:
        from fabric_imitation.diagrams.hardware import MakeHardwareClothStation

        return MakeHardwareClothStation(scenario, lcm=lcm)
    builder = DiagramBuilder()
    plant, scene_graph = AddMultibodyPlant(scenario.plant_config, builder)
    plant.set_name("plant")
    fem = scenario.cloth.engine == "fem"
    mesh = MakeClothMesh(
        scenario.cloth.size, scenario.cloth.thickness, ClothResolution(scenario)
    )
    X_WO = _add_table_and_object(plant, scenario)
    if fem:
        cloth_id, X_WC = _add_cloth(plant, scenario, mesh)
    else:
        cloth_id, X_WC = None, ClothPose(scenario)
    dt = scenario.plant_config.time_step
    grippers = _add_grippers(builder, plant, scene_graph, scenario, cloth_id, X_WC)
    plant.Finalize()
    if scenario.grippers.kind != "panda":
        _filter_anchor_collisions(plant, scene_graph, cloth_id if fem else None)
    if scenario.object.kind != "none":
        _add_contact_monitor(builder, plant, scenario, X_WO)

    initialize = None
    if grippers.pandas is not None:
        initialize = grippers.pandas.Wire(builder, joint_commands=joint_commands)
        measured = {
            side: builder.GetSubsystemByName("tcp_positions").GetOutputPort(side)
            for side in SIDES
        }
    else:
        anchors = {s: grippers.anchors[s][0] for s in SIDES}
        measured = _wire_anchors(builder, plant, anchors, dt)

    latch = builder.AddNamedSystem("release_latch", ReleaseLatch(period=dt))
    builder.ExportInput(latch.GetInputPort("release"), StationPorts.RELEASE)
    builder.ExportOutput(latch.GetOutputPort("released"), StationPorts.RELEASED)

    X_WCamera, camera_info = _add_camera(builder, scenario, scene_graph)
    if people_camera:
        _add_people_camera(builder, scenario, scene_graph)
    if raw_camera_scale:
        _add_raw_camera(builder, scenario, scene_graph, raw_camera_scale)

    object_pose = builder.AddNamedSystem(
        "object_pose", ConstantValueSource(AbstractValue.Make(X_WO))
    )
    builder.ExportOutput(object_pose.get_output_port(), StationPorts.OBJECT_POSE)

    if fem:
        truth = _add_fem_truth(builder, plant, mesh, cloth_id)
    else:
        truth = _add_vbd_cloth(builder, scene_graph, scenario, mesh, X_WC, X_WO)
        cloth_id = truth
        for side in SIDES:
            builder.Connect(
                measured[side], truth.GetInputPort(f"{side}.gripper_position")
            )
        builder.Connect(latch.GetOutputPort("released"), truth.GetInputPort("release"))
    builder.ExportOutput(truth.GetOutputPort("positions"), StationPorts.CLOTH_POSITIONS)
    builder.ExportOutput(truth.GetOutputPort("keypoints"), StationPorts.CLOTH_KEYPOINTS)

    if meshcat is not None:
        MeshcatVisualizer.AddToBuilder(
            builder,
            scene_graph,
            meshcat,
            MeshcatVisualizerParams(role=Role.kIllustration, prefix="scene"),
        )
    diagram = builder.Build()
    diagram.set_name("cloth_station")
    return ClothStation(
        diagram=diagram,
        scenario=scenario,
        camera_info=camera_info,
        X_WCamera=X_WCamera,
        X_WO=X_WO,
        plant=plant,
        mesh=mesh,
        cloth_id=cloth_id,
        weld_ids=tuple(w for w, _ in grippers.welds),
        clips=tuple(c for _, c in grippers.welds),
        X_WCloth=X_WC,
        initialize=initialize,
    )


@dc.dataclass
class _Grippers:
    """The station's grippers in the plant: Panda arms or anchors, and (FEM
    cloth) each grasped corner's weld and clip."""

    pandas: object | None  # panda.PandaGrippers
    anchors: dict | None  # side -> (model instance, body)
    welds: list  # (weld id, clip body) per side


def _add_grippers(builder, plant, scene_graph, scenario, cloth_id, X_WC) -> _Grippers:
    corners = GraspCorners(scenario)
    pandas, anchors = None, None
    if scenario.grippers.kind == "panda":
        from fabric_imitation.diagrams.panda import AddPandaGrippers

        pandas = AddPandaGrippers(builder, plant, scene_graph, scenario, corners)
        holders = pandas.tcp_bodies
        X_holder_clip = pandas.X_TcpClip
    else:
        anchors = {
            side: _add_anchor(plant, scenario, side, corners[side]) for side in SIDES
        }
        holders = {side: anchors[side][1] for side in SIDES}
        X_holder_clip = {side: RigidTransform() for side in SIDES}
    if scenario.grippers.hands:
        _add_hands(plant, holders, X_holder_clip)
    welds = [
        _add_clip(
            plant,
            scenario,
            side,
            holders[side],
            X_holder_clip[side],
            cloth_id,
            X_WC,
            corners[side],
        )
        for side in (SIDES if cloth_id is not None else ())
    ]
    return _Grippers(pandas=pandas, anchors=anchors, welds=welds)


def _add_contact_monitor(builder, plant, scenario: Scenario, X_WO) -> None:
    """GripperObjectContact on the plant's body poses, every plant step."""
    contact = builder.AddNamedSystem(
        "gripper_object_contact",
        GripperObjectContact(
            grippers=_gripper_bodies(plant, scenario),
            X_WO=X_WO,
            object_kind=scenario.object.kind,
            object_size=np.array(scenario.object.size, float),
            period=scenario.plant_config.time_step,
        ),
    )
    builder.Connect(
        plant.get_body_poses_output_port(), contact.GetInputPort("body_poses")
    )
    builder.ExportOutput(
        contact.GetOutputPort("contact"), StationPorts.GRIPPER_OBJECT_CONTACT
    )


def _add_fem_truth(builder, plant, mesh: ClothMesh, cloth_id) -> ClothGroundTruth:
    """The FEM cloth's vertex positions and keypoints from the plant."""
    model = plant.deformable_model()
    truth = builder.AddNamedSystem(
        "cloth_ground_truth",
        ClothGroundTruth(
            geometry_id=model.GetGeometryId(cloth_id),
            num_vertices=len(mesh.vertices),
            keypoint_vertices=mesh.keypoint_vertices(NUM_KEYPOINTS),
        ),
    )
    builder.Connect(
        plant.get_deformable_body_configuration_output_port(),
        truth.GetInputPort("configuration"),
    )
    return truth


def _wire_anchors(
    builder: DiagramBuilder, plant: MultibodyPlant, anchors: dict, dt: float
) -> dict:
    """Position targets -> PD desired states of the anchors' joints. Returns
    the output port of each anchor's measured world position."""
    measured = {}
    for side in SIDES:
        interpolator = builder.AddNamedSystem(
            f"{side}.target_interpolator",
            StateInterpolatorWithDiscreteDerivative(3, dt, True),
        )
        builder.Connect(
            interpolator.get_output_port(),
            plant.get_desired_state_input_port(anchors[side]),
        )
        builder.ExportInput(interpolator.get_input_port(), StationPorts.ee_target(side))
        demux = builder.AddNamedSystem(f"{side}.state_demux", Demultiplexer([3, 3]))
        builder.Connect(
            plant.get_state_output_port(anchors[side]), demux.get_input_port()
        )
        builder.ExportOutput(demux.get_output_port(0), StationPorts.ee_measured(side))
        measured[side] = demux.get_output_port(0)
    return measured


def InitializeStation(station: ClothStation, station_context) -> None:
    """Sets what a new station context needs before simulation (the Panda
    differential IK's starting joint positions); nothing for anchors."""
    if station.initialize is not None:
        station.initialize(station.diagram, station_context)


def _add_camera(builder: DiagramBuilder, scenario: Scenario, scene_graph):
    """A top-down RgbdSensor that renders on demand (no periodic rendering:
    images are computed only when a port is evaluated)."""
    config = scenario.camera
    if not scene_graph.HasRenderer(config.renderer_name):
        scene_graph.AddRenderer(
            config.renderer_name, MakeRenderEngineVtk(RenderEngineVtkParams())
        )
    color_camera, depth_camera = config.MakeCameras()
    X_WCamera = config.X_PB.GetDeterministicValue()
    sensor = builder.AddNamedSystem(
        "camera",
        RgbdSensor(
            parent_id=scene_graph.world_frame_id(),
            X_PB=X_WCamera,
            color_camera=color_camera,
            depth_camera=depth_camera,
        ),
    )
    builder.Connect(
        scene_graph.get_query_output_port(), sensor.query_object_input_port()
    )
    builder.ExportOutput(sensor.color_image_output_port(), StationPorts.RGB)
    builder.ExportOutput(sensor.depth_image_32F_output_port(), StationPorts.DEPTH)
    builder.ExportOutput(sensor.label_image_output_port(), StationPorts.LABEL)
    mask = builder.AddNamedSystem(
        "fabric_mask",
        FabricMask(width=config.width, height=config.height, cloth_label=CLOTH_LABEL),
    )
    builder.Connect(sensor.label_image_output_port(), mask.GetInputPort("label_image"))
    builder.ExportOutput(mask.GetOutputPort("mask"), StationPorts.MASK)
    return X_WCamera, color_camera.core().intrinsics()


PEOPLE_CAMERA_SIZE = 480  # [px]
# Where the people's camera looks from and at [m, world]: in front of the
# table, to the right and above, so the cloth, the object and both grippers
# (or arms) are in view, and their heights can be seen.
PEOPLE_CAMERA_EYE = np.array([0.55, 0.75, 0.6])
PEOPLE_CAMERA_TARGET = np.array([0.0, 0.0, 0.05])


def LookAt(eye: np.ndarray, target: np.ndarray) -> RigidTransform:
    """A camera pose (Drake's camera frame: +z forward, +x right, +y down)
    at `eye` looking at `target`, upright with respect to world z."""
    forward = (target - eye) / np.linalg.norm(target - eye)
    right = np.cross(forward, [0.0, 0.0, 1.0])
    right /= np.linalg.norm(right)
    down = np.cross(forward, right)
    return RigidTransform(RotationMatrix(np.stack([right, down, forward], 1)), eye)


def _add_people_camera(builder: DiagramBuilder, scenario: Scenario, scene_graph):
    """A second colour camera, oblique and larger, for videos people watch;
    nothing in the diagram reads it. Exports ``camera.people_rgb_image``."""
    from pydrake.common.schema import Transform
    from pydrake.systems.sensors import CameraConfig

    config = CameraConfig(
        width=PEOPLE_CAMERA_SIZE,
        height=PEOPLE_CAMERA_SIZE,
        focal=CameraConfig.FovDegrees(y=50.0),
        renderer_name=scenario.camera.renderer_name,
        background=scenario.camera.background,
        X_PB=Transform(LookAt(PEOPLE_CAMERA_EYE, PEOPLE_CAMERA_TARGET)),
    )
    sensor = _add_sensor(builder, scene_graph, "people_camera", config)
    builder.ExportOutput(sensor.color_image_output_port(), StationPorts.PEOPLE_RGB)


def _add_sensor(builder: DiagramBuilder, scene_graph, name: str, config) -> RgbdSensor:
    """An RgbdSensor named `name` fixed in the world where the CameraConfig
    `config` puts it, connected to the scene graph."""
    color_camera, depth_camera = config.MakeCameras()
    sensor = builder.AddNamedSystem(
        name,
        RgbdSensor(
            parent_id=scene_graph.world_frame_id(),
            X_PB=config.X_PB.GetDeterministicValue(),
            color_camera=color_camera,
            depth_camera=depth_camera,
        ),
    )
    builder.Connect(
        scene_graph.get_query_output_port(), sensor.query_object_input_port()
    )
    return sensor


def RawCameraConfig(scenario: Scenario, scale: int):
    """The control camera's CameraConfig at `scale` times its resolution (the
    same pose and field of view)."""
    import copy

    config = copy.deepcopy(scenario.camera)
    config.name = "raw_camera"
    config.width *= scale
    config.height *= scale
    return config


def _add_raw_camera(builder: DiagramBuilder, scenario: Scenario, scene_graph, scale):
    sensor = _add_sensor(
        builder, scene_graph, "raw_camera", RawCameraConfig(scenario, scale)
    )
    builder.ExportOutput(sensor.color_image_output_port(), StationPorts.RAW_RGB)
    builder.ExportOutput(sensor.depth_image_32F_output_port(), StationPorts.RAW_DEPTH)


def CameraModelFromConfig(config):
    """The project's CameraModel (intrinsics, X_WC) of a Drake CameraConfig."""
    from fabric_imitation.learning.demo_io import CameraModel

    color, _ = config.MakeCameras()
    return CameraModel.FromIntrinsics(
        color.core().intrinsics(), config.X_PB.GetDeterministicValue().GetAsMatrix4()
    )


def _welded(station: ClothStation, root_context) -> bool:
    if not station.weld_ids:
        return False
    plant_context = station.plant.GetMyContextFromRoot(root_context)
    return any(
        station.plant.GetConstraintActiveStatus(plant_context, weld)
        for weld in station.weld_ids
    )


def ApplyRelease(station: ClothStation, root_context) -> bool:
    """Opens the FEM clip welds once the station's `released` output is on;
    returns whether the grasps are open. Changes plant parameters, so call it
    only between `AdvanceTo` calls (`AdvanceStationTo` does)."""
    diagram, plant = station.diagram, station.plant
    station_context = diagram.GetMyContextFromRoot(root_context)
    if diagram.GetOutputPort(StationPorts.RELEASED).Eval(station_context)[0] <= 0.5:
        return False
    plant_context = plant.GetMyMutableContextFromRoot(root_context)
    for weld, clip in zip(station.weld_ids, station.clips, strict=True):
        if plant.GetConstraintActiveStatus(plant_context, weld):
            plant.SetConstraintActiveStatus(plant_context, weld, False)
            clip.SetSpatialInertiaInBodyFrame(
                plant_context,
                SpatialInertia.SolidSphereWithMass(
                    station.scenario.grippers.clip_mass, CLIP_RADIUS
                ),
            )
    return True


def AdvanceStationTo(simulator: Simulator, station: ClothStation, t: float) -> None:
    """`simulator.AdvanceTo(t)` for a diagram holding `station`.

    While the FEM cloth's clip welds are on, it advances one plant step at a
    time and opens them (`ApplyRelease`) right after the step in which the
    station's `released` output turns on; otherwise (the vbd cloth, whose
    release is a port, or welds already open) it is one `AdvanceTo`.
    """
    root = simulator.get_mutable_context()
    if not _welded(station, root):
        simulator.AdvanceTo(t)
        return
    h = station.plant.time_step()
    while root.get_time() < t - 1e-12:
        simulator.AdvanceTo(min(t, root.get_time() + h))
        if ApplyRelease(station, root):
            simulator.AdvanceTo(t)
            return
