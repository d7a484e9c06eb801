"""The imitation diagram and `fabric-imitate imitate`, the main job.

station -> fabric mask, depth -> KeypointEstimator -> (DemoReward, MpcController)
MpcController -> GripperTargetIntegrator -> station; MpcController.release ->
station.release. Events within a control step are staggered (estimator at
offset 0, controller at +1 ms, target integrator at +2 ms) so each uses the
fresh result of the one before.
"""

import sys
import time
from pathlib import Path

import numpy as np
import torch
from fabric_imitation.diagrams.recording import MakeRecordingMeshcat, SaveRecording
from fabric_imitation.diagrams.simulation import CaptureFrame
from fabric_imitation.diagrams.station import (
    SIDES,
    AddReleaseMonitor,
    CameraModelFromConfig,
    GraspCorners,
    InitializeStation,
    MakeClothStation,
    StationPorts,
)
from fabric_imitation.diagrams.success import TaskSuccess
from fabric_imitation.learning.demo_io import Demo, LoadDemo, WriteVideo
from fabric_imitation.learning.demo_learning import DemoModel, learn_from_demo
from fabric_imitation.learning.errors import InputError
from fabric_imitation.learning.metrics import chamfer_distance, cloud_from_depth
from fabric_imitation.learning.mpc import Mpc, MpcConfig
from fabric_imitation.learning.polygon import iou
from fabric_imitation.learning.priors import Priors, load_priors
from fabric_imitation.learning.safety import SafetyContext, valid_actions
from fabric_imitation.learning.state import world_to_object
from fabric_imitation.scenarios.schema import Scenario, yaw_rad
from fabric_imitation.systems.imitation import (
    RUNNING,
    TERMINATION_NAMES,
    DemoReward,
    KeypointEstimator,
    MpcController,
    SuccessMonitor,
)
from fabric_imitation.systems.targets import GripperTargetIntegrator
from fabric_imitation.systems.visualization import ClothFrameRecorder
from pydrake.systems.analysis import Simulator
from pydrake.systems.framework import Diagram, DiagramBuilder
from pydrake.systems.primitives import Multiplexer

PACKAGE_ROOT = Path(__file__).resolve().parent.parent
DEFAULT_PRIORS = PACKAGE_ROOT / "learning" / "priors" / "default"
DEFAULT_DEMOS = PACKAGE_ROOT / "scenarios" / "demos"
EVENT_STAGGER = 1e-3  # [s]


def ObjectPose(scenario: Scenario) -> np.ndarray:
    p = scenario.object.pose
    return np.array([p[0], p[1], yaw_rad(p)])


def ObjectSafetyContext(scenario: Scenario) -> SafetyContext:
    """Safety rules for states in the object frame of `scenario`."""
    lower = np.array(scenario.workspace.lower, float)
    lower[2] = max(lower[2], -scenario.cloth.thickness)
    return SafetyContext(
        edge_length=scenario.cloth.size[0],
        workspace_lower=lower,
        workspace_upper=np.array(scenario.workspace.upper, float),
        object_size=np.array(scenario.object.size, float)
        if scenario.object.kind != "none"
        else None,
        frame_pose=ObjectPose(scenario),
    )


def DemoStates(priors: Priors, demo: Demo) -> np.ndarray:
    """S_E^1..T: f_R on every demo frame, in the demo's object frame."""
    p_W = priors.keypoints(demo.mask, demo.depth)
    return world_to_object(p_W, demo.object_pose)


def MakeImitationDiagram(
    scenario: Scenario,
    *,
    priors: Priors,
    demo: DemoModel,
    mpc_config: MpcConfig | None = None,
    meshcat=None,
    seed: int | None = None,
) -> Diagram:
    """Station + perception + demo reward + MPC + target integration."""
    cfg = mpc_config or scenario.mpc
    dt = scenario.motion.step_seconds
    m = priors.num_keypoints
    builder = DiagramBuilder()
    station = builder.AddNamedSystem(
        "station", MakeClothStation(scenario, meshcat=meshcat)
    )
    cam = scenario.camera
    estimator = builder.AddNamedSystem(
        "keypoint_estimator",
        KeypointEstimator(
            priors=priors,
            num_keypoints=m,
            width=cam.width,
            height=cam.height,
            period=dt,
            offset=0.0,
        ),
    )
    reward = builder.AddNamedSystem(
        "demo_reward", DemoReward(demo=demo, num_keypoints=m)
    )
    mpc = Mpc(
        dynamics=priors,
        demo=demo,
        safety=scenario.safety,
        safety_ctx=ObjectSafetyContext(scenario),
        config=cfg,
    )
    controller = builder.AddNamedSystem(
        "mpc_controller",
        MpcController(
            mpc=mpc,
            num_keypoints=m,
            period=dt,
            offset=EVENT_STAGGER,
            step_cap=int(cfg.step_cap_factor * demo.T) + 5,
            seed=scenario.random_seed if seed is None else seed,
        ),
    )
    targets = builder.AddNamedSystem(
        "targets", GripperTargetIntegrator(step_seconds=dt, offset=2 * EVENT_STAGGER)
    )
    handles = station.handles
    monitor = builder.AddNamedSystem(
        "success_monitor",
        SuccessMonitor(
            judge=lambda p: TaskSuccess(scenario, p, handles.mesh.top_layer).success,
            num_vertices=len(handles.mesh.vertices),
        ),
    )
    builder.Connect(
        station.GetOutputPort(StationPorts.MASK), estimator.GetInputPort("mask")
    )
    builder.Connect(
        station.GetOutputPort(StationPorts.DEPTH), estimator.GetInputPort("depth")
    )
    for system in (estimator, controller):
        builder.Connect(
            station.GetOutputPort(StationPorts.OBJECT_POSE),
            system.GetInputPort("object_pose"),
        )
    grippers = builder.AddNamedSystem("gripper_positions", Multiplexer([3, 3]))
    for k, side in enumerate(SIDES):
        builder.Connect(
            station.GetOutputPort(StationPorts.ee_measured(side)),
            grippers.get_input_port(k),
        )
    builder.Connect(grippers.get_output_port(), estimator.GetInputPort("grippers"))
    for system in (reward, controller):
        builder.Connect(
            estimator.GetOutputPort("keypoints"), system.GetInputPort("keypoints")
        )
    builder.Connect(controller.GetOutputPort("action"), targets.GetInputPort("action"))
    builder.Connect(
        controller.GetOutputPort("release"), station.GetInputPort(StationPorts.RELEASE)
    )
    for side in SIDES:
        builder.Connect(
            targets.GetOutputPort(f"{side}.ee_target"),
            station.GetInputPort(StationPorts.ee_target(side)),
        )
    builder.Connect(
        station.GetOutputPort(StationPorts.CLOTH_POSITIONS),
        monitor.GetInputPort("positions"),
    )
    if meshcat is not None:
        from fabric_imitation.diagrams.cloth_mesh import TopTriangles

        recorder = builder.AddNamedSystem(
            "cloth_recorder",
            ClothFrameRecorder(
                meshcat=meshcat,
                num_vertices=len(handles.mesh.vertices),
                triangles=TopTriangles(handles.mesh.top_layer),
                period=1 / 16,
            ),
        )
        builder.Connect(
            station.GetOutputPort(StationPorts.CLOTH_POSITIONS),
            recorder.GetInputPort("positions"),
        )
    for system, port in (
        (estimator, "keypoints"),
        (reward, "progress"),
        (reward, "reward"),
        (reward, "done"),
        (controller, "status"),
        (controller, "action"),
        (monitor, "success"),
    ):
        builder.ExportOutput(system.GetOutputPort(port), port)
    diagram = builder.Build()
    diagram.set_name("imitation")
    diagram.station = station
    diagram.targets = targets
    diagram.mpc = mpc
    return diagram


def _chamfer(camera, frame_depth, frame_mask, demo: Demo, pose_now, rng) -> float:
    a = cloud_from_depth(camera, frame_depth, frame_mask, rng)
    b = cloud_from_depth(camera, demo.final_depth, demo.final_mask, rng)
    return chamfer_distance(
        world_to_object(a, pose_now), world_to_object(b, demo.object_pose)
    )


def Imitate(
    *,
    scenario: Scenario,
    scenario_name: str,
    demo_dir: Path | None = None,
    priors_dir: Path | None = None,
    mpc_config: MpcConfig | None = None,
    record: Path | None = None,
    video: Path | None = None,
    progress: bool = True,
    seed: int | None = None,
) -> dict:
    """Runs one imitation episode; returns the JSON summary."""
    if scenario.task == "prior":
        raise InputError("the prior scene has no task to imitate; use box, hang, ...")
    wall0 = time.perf_counter()
    torch.set_num_threads(min(2, torch.get_num_threads()))
    demo_dir = Path(demo_dir) if demo_dir else DEFAULT_DEMOS / scenario_name
    priors_dir = Path(priors_dir) if priors_dir else DEFAULT_PRIORS
    camera = CameraModelFromConfig(scenario.camera)
    priors = load_priors(
        priors_dir,
        num_keypoints=8,
        image_size=(scenario.camera.height, scenario.camera.width),
        camera=camera,
    )
    t_demo = time.perf_counter()
    demo = LoadDemo(demo_dir)
    if demo.task != scenario.task:
        raise InputError(
            f"demo {demo_dir} shows the {demo.task!r} task, the scenario "
            f"is {scenario.task!r}"
        )
    if not demo.camera.same_as(camera):
        raise InputError(
            f"demo {demo_dir} was recorded with another camera "
            "(intrinsics or pose differ from the scenario's)"
        )
    states = DemoStates(priors, demo)
    if priors.prior_states is None:
        raise InputError(f"priors {priors_dir} carry no prior states for f_A")
    model, demo_info = learn_from_demo(states, priors.prior_states, scenario.reward)
    meshcat = MakeRecordingMeshcat() if record else None
    diagram = MakeImitationDiagram(
        scenario,
        priors=priors,
        demo=model,
        mpc_config=mpc_config,
        meshcat=meshcat,
        seed=seed,
    )
    diagram.mpc.WarmUp(states[0])
    station = diagram.station
    simulator = Simulator(diagram)
    AddReleaseMonitor(simulator, station)
    context = simulator.get_mutable_context()
    corners = GraspCorners(scenario)
    diagram.targets.SetInitialPositions(
        diagram.targets.GetMyMutableContextFromRoot(context),
        corners["left"],
        corners["right"],
    )
    InitializeStation(station, station.GetMyMutableContextFromRoot(context))
    simulator.Initialize()
    dt = scenario.motion.step_seconds
    station_context = station.GetMyContextFromRoot(context)
    safety_ctx = ObjectSafetyContext(scenario)
    pose = ObjectPose(scenario)
    m = priors.num_keypoints

    def out(name):
        return np.array(diagram.GetOutputPort(name).Eval(context))

    solve_ms, violations, violations_gt, frames = [], 0, 0, []
    first_action_s = None
    error = None
    bar = None
    if progress:
        from tqdm import tqdm

        bar = tqdm(
            desc=f"imitate {scenario_name}", unit="step", file=sys.stderr, leave=False
        )
    k = 0
    try:
        while True:
            gt_before = world_to_object(
                np.array(
                    station.GetOutputPort(StationPorts.CLOTH_KEYPOINTS).Eval(
                        station_context
                    )
                ).reshape(m, 3),
                pose,
            )
            simulator.AdvanceTo(k * dt + 3 * EVENT_STAGGER)
            status = out("status")
            if first_action_s is None:
                first_action_s = time.perf_counter() - t_demo
            if status[1] != RUNNING:
                break
            solve_ms.append(float(status[3]))
            S = out("keypoints").reshape(m, 3)
            yaw = pose[2]
            R = np.array(
                [
                    [np.cos(yaw), np.sin(yaw), 0],
                    [-np.sin(yaw), np.cos(yaw), 0],
                    [0, 0, 1],
                ]
            )
            A_O = (out("action").reshape(2, 3) @ R.T).ravel()
            simulator.AdvanceTo((k + 1) * dt)
            k += 1
            S_next = out("keypoints").reshape(m, 3)
            gt_after = world_to_object(
                np.array(
                    station.GetOutputPort(StationPorts.CLOTH_KEYPOINTS).Eval(
                        station_context
                    )
                ).reshape(m, 3),
                pose,
            )
            t = torch.as_tensor
            violations += int(
                not valid_actions(
                    t(S, dtype=torch.float64),
                    t(A_O),
                    scenario.safety,
                    safety_ctx,
                    S_next=t(S_next, dtype=torch.float64),
                )
            )
            violations_gt += int(
                not valid_actions(
                    t(gt_before, dtype=torch.float64),
                    t(A_O),
                    scenario.safety,
                    safety_ctx,
                    S_next=t(gt_after, dtype=torch.float64),
                )
            )
            if video is not None:
                frames.append(CaptureFrame(station, station_context).rgb)
            if bar is not None:
                bar.update()
        simulator.AdvanceTo(context.get_time() + scenario.motion.settle_seconds)
    except RuntimeError as e:
        error = " ".join(str(e).split())[:300]
    finally:
        if bar is not None:
            bar.close()
    status = out("status")
    final = CaptureFrame(station, station_context)
    report = TaskSuccess(scenario, final.positions_W, station.handles.mesh.top_layer)
    gt = np.load(demo.path / "ground_truth.npz")
    demo_final = world_to_object(gt["final_keypoints_W"], demo.object_pose)
    final_O = world_to_object(final.keypoints_W, pose)
    final_iou = float(
        iou(
            torch.as_tensor(final_O[:, :2]),
            torch.as_tensor(demo_final[:, :2], dtype=torch.float64),
        )
    )
    from fabric_imitation.learning.geometry import PinholeCamera

    chamfer = _chamfer(
        PinholeCamera.from_model(camera),
        final.depth,
        final.mask,
        demo,
        pose,
        np.random.default_rng(0),
    )
    if video is not None:
        WriteVideo(video, frames + [final.rgb], 1.0 / dt)
    if record is not None:
        SaveRecording(meshcat, record)
    summary = {
        "scenario": scenario_name,
        "object_pose": list(scenario.object.pose),
        "success": bool(report.success) and error is None,
        "success_details": report.details,
        "steps": int(status[2]),
        "termination": "diverged" if error else TERMINATION_NAMES[int(status[1])],
        "executed_violations": violations,
        "executed_violations_ground_truth": violations_gt,
        "mpc_step_ms": {
            "p50": round(float(np.percentile(solve_ms, 50)), 1) if solve_ms else None,
            "p95": round(float(np.percentile(solve_ms, 95)), 1) if solve_ms else None,
        },
        "final_iou": round(final_iou, 3),
        "final_chamfer": round(chamfer, 6),
        "demo_frames": demo.num_frames,
        "demo_to_first_action_s": round(first_action_s or float("nan"), 2),
        "registration": demo_info,
        "wall_seconds": round(time.perf_counter() - wall0, 2),
        "error": error,
    }
    return summary
