"""The imitation diagram and `fabric-imitate imitate`, the main job, in stages:

    PrepareImitation (learn from the demo once: f_R on its frames, train f_A)
      -> MakeImitationDiagram (station + perception + reward + MPC + loggers)
      -> RunEpisode (simulate; returns the loggers' records)
      -> ScoreEpisode (success, IoU, Chamfer, rule breaks, latencies)

station -> fabric mask, depth -> KeypointEstimator -> (DemoReward, MpcController)
MpcController -> GripperTargetIntegrator -> station; MpcController.release ->
station.release. Events within a control step are staggered (estimator at
offset 0, controller at +1 ms, target integrator at +2 ms) so each uses the
fresh result of the one before.

Episode records come from Drake's `VectorLogSink`s publishing once per control
period at k * dt. A publish at time t sees the state before the discrete
updates due at t, so record k holds the true cloth at k * dt (what the
estimator sees at that step) and the estimator's and the controller's results
of step k - 1. `EpisodeTransitions` pairs them up.
"""

import dataclasses as dc
import signal
import sys
import threading
import time
from pathlib import Path

import numpy as np
import torch
from fabric_imitation.diagrams.recording import MakeRecordingMeshcat
from fabric_imitation.diagrams.referee import (
    ON_VIOLATION,
    FirstBreak,
    JudgeTransitions,
    ObjectSafetyContext,
    TaskReferee,
)
from fabric_imitation.diagrams.simulation import (
    AddClothRecorder,
    AddVideoRecorder,
    CaptureFrame,
    Frame,
    WriteOutputs,
)
from fabric_imitation.diagrams.station import (
    SIDES,
    AdvanceStationTo,
    CameraModelFromConfig,
    ClothStation,
    GraspCorners,
    InitializeStation,
    MakeClothStation,
    StationPorts,
)
from fabric_imitation.diagrams.success import TaskSuccess
from fabric_imitation.learning.demo_io import Demo, LoadDemo
from fabric_imitation.learning.demo_learning import (
    DemoModel,
    RewardConfig,
    learn_from_demo,
    track_grasped_corners,
)
from fabric_imitation.learning.errors import InputError
from fabric_imitation.learning.geometry import PinholeCamera
from fabric_imitation.learning.metrics import (
    chamfer_distance,
    cloud_from_depth,
    raster_iou,
)
from fabric_imitation.learning.mpc import Mpc, MpcConfig
from fabric_imitation.learning.priors import Priors, load_priors
from fabric_imitation.learning.safety import RULES, SafetyContext, rule_violations
from fabric_imitation.learning.state import (
    PlanarPose,
    corner_indices,
    world_to_object,
)
from fabric_imitation.scenarios.schema import Scenario
from fabric_imitation.systems.imitation import (
    RUNNING,
    TERMINATION_NAMES,
    CfmController,
    ChamferToDemo,
    DemoReward,
    KeypointEstimator,
    MpcController,
    PlanarPoseVector,
    ReplayController,
    ZeroController,
)
from fabric_imitation.systems.referee import HALT_COLLISION, HALT_RULE_BREAK, Referee
from fabric_imitation.systems.targets import GripperTargetIntegrator
from fabric_imitation.systems.visualization import VideoRecorder
from pydrake.systems.analysis import Simulator
from pydrake.systems.framework import Diagram, DiagramBuilder
from pydrake.systems.primitives import LogVectorOutput, Multiplexer, VectorLogSink

PACKAGE_ROOT = Path(__file__).resolve().parent.parent
DEFAULT_PRIORS = PACKAGE_ROOT / "learning" / "priors" / "default"
DEFAULT_DEMOS = PACKAGE_ROOT / "scenarios" / "demos"
EVENT_STAGGER = 1e-3  # [s]
NUM_KEYPOINTS = 8


def DemoStates(
    priors: Priors, demo: Demo, config: RewardConfig | None = None
) -> np.ndarray:
    """S_E^1..T: f_R on every demo frame, in the demo's object frame, with
    the grasped corners tracked through the frames (track_grasped_corners;
    `config`: the scenario's reward settings)."""
    p_W, spread = priors.keypoints_and_spread(demo.mask, demo.depth)
    states = world_to_object(p_W, demo.object_pose)
    return track_grasped_corners(states, spread, config or RewardConfig())


def DefaultDemoDir(scenario_name: str, scenario: Scenario) -> Path:
    """The shipped demo for `scenario_name`, else the one of its task (the
    box demo serves box_panda)."""
    own = DEFAULT_DEMOS / scenario_name
    return own if own.exists() else DEFAULT_DEMOS / scenario.task


@dc.dataclass
class PreparedImitation:
    """What is learned from one demo, once, and shared by every episode that
    imitates it (any object pose, any MPC variant)."""

    demo: Demo
    priors: Priors
    demo_states: np.ndarray  # (T, M, 3), demo object frame
    model: DemoModel  # demo states + f_A + termination classifier
    registration: dict  # f_A training summary
    seconds: float  # wall time of the preparation
    # With baselines=True: the Zero/CFM/TCN networks, TCN also trained on
    # this demo (learning/baselines.py).
    baselines: object | None = None


def PrepareImitation(
    scenario: Scenario,
    *,
    demo_dir: Path,
    priors_dir: Path | None = None,
    baselines: bool = False,
) -> PreparedImitation:
    """Loads the priors and the demo, checks they fit `scenario` (task,
    camera), runs f_R on the demo's frames and trains f_A; with `baselines`
    also loads the baselines' networks from the priors directory and trains
    TCN on the demo's states."""
    if scenario.task == "prior":
        raise InputError("the prior scene has no task to imitate; use box, hang, ...")
    t0 = time.perf_counter()
    demo_dir = Path(demo_dir)
    priors_dir = Path(priors_dir) if priors_dir else DEFAULT_PRIORS
    camera = CameraModelFromConfig(scenario.camera)
    priors = load_priors(
        priors_dir,
        num_keypoints=NUM_KEYPOINTS,
        image_size=(scenario.camera.height, scenario.camera.width),
        camera=camera,
    )
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
    if priors.prior_states is None:
        raise InputError(f"priors {priors_dir} carry no prior states for f_A")
    states = DemoStates(priors, demo, scenario.reward)
    model, info = learn_from_demo(states, priors.prior_states, scenario.reward)
    nets = None
    if baselines:
        from fabric_imitation.learning.baselines import (
            BaselineTrainConfig,
            load_baselines,
        )

        nets = load_baselines(priors_dir, num_keypoints=NUM_KEYPOINTS)
        nets, seconds = nets.tcn_on_demo(states, BaselineTrainConfig(**nets.config))
        info = {**info, "tcn_on_demo_seconds": round(seconds, 2)}
    return PreparedImitation(
        demo=demo,
        priors=priors,
        demo_states=states,
        model=model,
        registration=info,
        seconds=time.perf_counter() - t0,
        baselines=nets,
    )


@dc.dataclass
class ImitationDiagram:
    """The built imitation diagram and the systems runners use."""

    diagram: Diagram
    station: ClothStation
    estimator: KeypointEstimator
    reward: DemoReward
    controller: MpcController | ReplayController
    targets: GripperTargetIntegrator
    mpc: Mpc
    loggers: dict[str, VectorLogSink]
    step_seconds: float
    meshcat: object | None = None
    hardware: bool = False  # the station is made of LCM drivers
    start_time: float = 0.0  # [s] of the first control step
    scenario: Scenario | None = None
    lcm: object | None = None
    video: VideoRecorder | None = None  # with video=True


def MakeImitationDiagram(
    scenario: Scenario,
    prepared: PreparedImitation,
    *,
    mpc_config: MpcConfig | None = None,
    meshcat=None,
    seed: int | None = None,
    hardware: bool = False,
    lcm=None,
    video: bool = False,
    controller: str = "mpc",
    on_violation: str = "stop",
) -> ImitationDiagram:
    """Station + perception + demo reward + MPC + target integration, with a
    logger per signal an episode is scored on (period: the control step).

    With `hardware=True` the station is made of LCM drivers on `lcm`
    (`MakeClothStation(..., hardware=True)`); the first control step then
    waits one control period for the drivers' status and the camera's
    images, the gripper targets start from the measured hands at that step,
    and nothing reads simulation ground truth.

    `controller`: "mpc" (the method), "replay" (the Replay baseline: the
    demo's grasped-corner path followed in the object frame of now,
    `ReplayController`), "zero", "cfm", "tcn" (the paper's baselines,
    learning/baseline_policies.py), or "tcn_mpc" (the TCN reward on this
    method's planner; `prepared` must have been made with `baselines=True`
    for these four).

    With `video=True` a `VideoRecorder` keeps the control camera's images
    and (simulation) an oblique people's camera's at VIDEO_FPS.

    In simulation the benchmark's `Referee` judges every executed action on
    the true keypoints by the task's rules (diagrams/referee.py) and watches
    gripper-object contact; with `on_violation="stop"` its ``halt`` ends the
    episode ("rule_break" or "collision"), with "count" it only records. On
    hardware there is no true cloth and no referee."""
    if on_violation not in ON_VIOLATION:
        raise InputError(
            f"unknown on-violation rule {on_violation!r}; use "
            f"{' or '.join(ON_VIOLATION)}"
        )
    cfg = mpc_config or scenario.mpc
    priors, demo = prepared.priors, prepared.model
    dt = scenario.motion.step_seconds
    start = dt if hardware else 0.0
    m = priors.num_keypoints
    builder = DiagramBuilder()
    if hardware:
        from pydrake.lcm import DrakeLcm

        lcm = lcm or DrakeLcm(scenario.grippers.panda.lcm_url)
    station = MakeClothStation(
        scenario,
        meshcat=meshcat,
        hardware=hardware,
        lcm=lcm,
        people_camera=video and not hardware,
    )
    builder.AddNamedSystem("station", station.diagram)
    cam = scenario.camera
    estimator = builder.AddNamedSystem(
        "keypoint_estimator",
        KeypointEstimator(
            priors=priors,
            num_keypoints=m,
            width=cam.width,
            height=cam.height,
            period=dt,
            offset=start,
            misread_grasp_error=scenario.safety.misread_grasp_error,
            max_side_length=scenario.safety.misread_side_stretch
            * scenario.cloth.size[1],
        ),
    )
    reward = builder.AddNamedSystem(
        "demo_reward", DemoReward(demo=demo, num_keypoints=m)
    )
    if controller in ("zero", "cfm", "tcn", "tcn_mpc") and prepared.baselines is None:
        raise InputError(
            f"controller {controller!r} needs PrepareImitation(..., baselines=True)"
        )
    mpc_args = dict(
        dynamics=priors,
        demo=demo,
        safety=scenario.safety,
        safety_ctx=ObjectSafetyContext(scenario, estimated=True),
        config=cfg,
    )
    if controller == "tcn_mpc":
        from fabric_imitation.learning.baseline_policies import TcnMpc

        mpc = TcnMpc(baselines=prepared.baselines, **mpc_args)
    else:
        mpc = Mpc(**mpc_args)
    timing = dict(
        num_keypoints=m,
        period=dt,
        offset=start + EVENT_STAGGER,
        step_cap=int(cfg.step_cap_factor * demo.T) + 5,
    )
    seed = scenario.random_seed if seed is None else seed
    # The baselines' moves pass only the driver's limits (max_step, reach box).
    from fabric_imitation.learning.limits import DriverLimits

    limits = DriverLimits.FromSafety(scenario.safety, mpc_args["safety_ctx"])
    if controller in ("mpc", "tcn_mpc"):
        system = MpcController(mpc=mpc, seed=seed, **timing)
    elif controller == "zero":
        from fabric_imitation.learning.baseline_policies import ZeroFollower

        follower = ZeroFollower(prepared.baselines, prepared.demo_states, limits=limits)
        system = ZeroController(follower=follower, **timing)
    elif controller == "cfm":
        from fabric_imitation.learning.baseline_policies import (
            CfmConfig,
            CfmPlanner,
        )

        planner = CfmPlanner(
            prepared.baselines,
            prepared.demo_states,
            limits=limits,
            config=CfmConfig(num_samples=cfg.num_samples),
        )
        system = CfmController(planner=planner, seed=seed, **timing)
    elif controller == "tcn":
        from fabric_imitation.learning.baseline_policies import TcnPlanner
        from fabric_imitation.systems.imitation import TcnController

        # H: the control steps the demo took, from its frame times.
        times = prepared.demo.manifest.get("frame_times") or []
        planner = TcnPlanner(
            prepared.baselines,
            priors,
            prepared.demo_states,
            limits=limits,
            demo_steps=round((times[-1] - times[0]) / dt) if len(times) > 1 else None,
        )
        system = TcnController(planner=planner, seed=seed, **timing)
    elif controller == "replay":
        corners = corner_indices(m)
        path = prepared.demo_states[:, [corners["s1"], corners["s2"]]]
        system = ReplayController(
            path=path, max_step=scenario.safety.max_step, **timing
        )
    else:
        raise InputError(
            f"unknown controller {controller!r}; use mpc, replay, zero, cfm, tcn "
            "or tcn_mpc"
        )
    controller = builder.AddNamedSystem("controller", system)
    targets = builder.AddNamedSystem(
        "targets",
        GripperTargetIntegrator(
            step_seconds=dt,
            offset=start + 2 * EVENT_STAGGER,
            start_at_first_step=hardware,
        ),
    )
    pose = builder.AddNamedSystem("object_pose", PlanarPoseVector())
    builder.Connect(
        station.diagram.GetOutputPort(StationPorts.OBJECT_POSE),
        pose.GetInputPort("pose"),
    )
    builder.Connect(
        station.diagram.GetOutputPort(StationPorts.MASK), estimator.GetInputPort("mask")
    )
    builder.Connect(
        station.diagram.GetOutputPort(StationPorts.DEPTH),
        estimator.GetInputPort("depth"),
    )
    for system in (estimator, controller):
        builder.Connect(
            station.diagram.GetOutputPort(StationPorts.OBJECT_POSE),
            system.GetInputPort("object_pose"),
        )
    grippers = builder.AddNamedSystem("gripper_positions", Multiplexer([3, 3]))
    for k, side in enumerate(SIDES):
        builder.Connect(
            station.diagram.GetOutputPort(StationPorts.ee_measured(side)),
            grippers.get_input_port(k),
        )
    builder.Connect(grippers.get_output_port(), estimator.GetInputPort("grippers"))
    builder.Connect(grippers.get_output_port(), targets.GetInputPort("measured"))
    for system in (reward, controller):
        builder.Connect(
            estimator.GetOutputPort("keypoints"), system.GetInputPort("keypoints")
        )
    if controller.HasInputPort("remembered_far_corners"):
        builder.Connect(
            estimator.GetOutputPort("remembered_far_corners"),
            controller.GetInputPort("remembered_far_corners"),
        )
    if not hardware:
        referee = _AddReferee(builder, scenario, station, controller, m, dt, start)
        if on_violation == "stop":
            builder.Connect(
                referee.GetOutputPort("halt"), controller.GetInputPort("halt")
            )
    builder.Connect(controller.GetOutputPort("action"), targets.GetInputPort("action"))
    builder.Connect(
        controller.GetOutputPort("release"),
        station.diagram.GetInputPort(StationPorts.RELEASE),
    )
    for side in SIDES:
        builder.Connect(
            targets.GetOutputPort(f"{side}.ee_target"),
            station.diagram.GetInputPort(StationPorts.ee_target(side)),
        )
    # The paper's Chamfer distance to the demo's last frame, every step.
    camera_model = PinholeCamera.from_model(CameraModelFromConfig(scenario.camera))
    target_W = cloud_from_depth(
        camera_model,
        prepared.demo.final_depth,
        prepared.demo.final_mask,
        np.random.default_rng(0),
    )
    chamfer = builder.AddNamedSystem(
        "chamfer_to_demo",
        ChamferToDemo(
            camera=camera_model,
            target_O=world_to_object(target_W, prepared.demo.object_pose),
            width=cam.width,
            height=cam.height,
            period=dt,
            offset=start,
        ),
    )
    for port, name in (
        (StationPorts.MASK, "mask"),
        (StationPorts.DEPTH, "depth"),
        (StationPorts.OBJECT_POSE, "object_pose"),
    ):
        builder.Connect(station.diagram.GetOutputPort(port), chamfer.GetInputPort(name))
    logged = {
        "chamfer": chamfer.GetOutputPort("chamfer"),
        "estimated_keypoints": estimator.GetOutputPort("keypoints"),
        "object_pose": pose.GetOutputPort("vector"),
        "grippers": grippers.get_output_port(),
        "reward": reward.GetOutputPort("reward"),
        **{
            name: controller.GetOutputPort(name)
            for name in (
                "action",
                "termination",
                "steps",
                "progress",
                "solve_ms",
                "iterations",
            )
        },
    }
    if not hardware:
        logged["true_keypoints"] = station.diagram.GetOutputPort(
            StationPorts.CLOTH_KEYPOINTS
        )
        logged["halt"] = referee.GetOutputPort("halt")
        if station.diagram.HasOutputPort(StationPorts.GRIPPER_OBJECT_CONTACT):
            logged["contact"] = station.diagram.GetOutputPort(
                StationPorts.GRIPPER_OBJECT_CONTACT
            )
    loggers = {}
    for name, port in logged.items():
        loggers[name] = LogVectorOutput(port, builder, publish_period=dt)
        loggers[name].set_name(f"log.{name}")
    if meshcat is not None and not hardware:
        AddClothRecorder(builder, station, meshcat)
    for system, port in (
        (estimator, "keypoints"),
        (reward, "progress"),
        (reward, "reward"),
        (reward, "done"),
        (controller, "action"),
        (controller, "termination"),
    ):
        builder.ExportOutput(system.GetOutputPort(port), port)
    recorder = AddVideoRecorder(builder, station) if video else None
    diagram = builder.Build()
    diagram.set_name("imitation")
    return ImitationDiagram(
        diagram=diagram,
        station=station,
        estimator=estimator,
        reward=reward,
        controller=controller,
        targets=targets,
        mpc=mpc,
        loggers=loggers,
        step_seconds=dt,
        meshcat=meshcat,
        hardware=hardware,
        start_time=start,
        scenario=scenario,
        lcm=lcm,
        video=recorder,
    )


def _AddReferee(builder, scenario, station, controller, m: int, dt, start) -> Referee:
    """The benchmark's referee, fed by the true keypoints, the controller's
    executed actions and the station's gripper-object contact."""
    rules = TaskReferee(scenario.task)

    def judge(before_O, action_O, after_O) -> str | None:
        hit = FirstBreak(
            JudgeTransitions(
                rules, scenario, before_O[None], action_O[None], after_O[None]
            )
        )
        return None if hit is None else hit[1]

    referee = builder.AddNamedSystem(
        "referee",
        Referee(judge=judge, rules=RULES, num_keypoints=m, period=dt, offset=start),
    )
    builder.Connect(
        station.diagram.GetOutputPort(StationPorts.CLOTH_KEYPOINTS),
        referee.GetInputPort("true_keypoints"),
    )
    builder.Connect(
        station.diagram.GetOutputPort(StationPorts.OBJECT_POSE),
        referee.GetInputPort("object_pose"),
    )
    for name in ("action", "steps"):
        builder.Connect(controller.GetOutputPort(name), referee.GetInputPort(name))
    if station.diagram.HasOutputPort(StationPorts.GRIPPER_OBJECT_CONTACT):
        builder.Connect(
            station.diagram.GetOutputPort(StationPorts.GRIPPER_OBJECT_CONTACT),
            referee.GetInputPort("contact"),
        )
    return referee


@dc.dataclass
class EpisodeRun:
    """What `RunEpisode` returns: the loggers' records, one row per control
    period (row k at time k * dt), and what the camera saw."""

    times: np.ndarray  # (K,)
    logs: dict[str, np.ndarray]  # name -> (K, size)
    final: Frame | None  # after the settle (simulation only)
    first_action_s: float  # wall time from the start of the run to action 0
    wall_seconds: float
    error: str | None = None
    top_layer: np.ndarray | None = None  # the cloth's top-surface vertices
    simulator: Simulator | None = None  # the run's, at its end


def RunEpisode(
    imitation: ImitationDiagram,
    *,
    settle_seconds: float,
    progress: str | None = None,
    root: Diagram | None = None,
    realtime_rate: float = 0.0,
) -> EpisodeRun:
    """Simulates until the controller ends the episode, then `settle_seconds`
    more (the released cloth settles). A diverging simulation, or a driver or
    camera that stops, ends the run with `error` set; the records up to
    there are kept.

    `root`: a diagram that holds `imitation.diagram` and other systems to
    simulate alongside it (tests: a simulated lab on the same LCM);
    `realtime_rate`: 1.0 on real drivers.

    Ctrl-C is acted on between control steps: on hardware the arms are told
    to hold where they are; then KeyboardInterrupt is raised with a message
    saying when (and that)."""
    t0 = time.perf_counter()
    station = imitation.station
    simulator = Simulator(root or imitation.diagram)
    simulator.set_target_realtime_rate(realtime_rate)
    context = simulator.get_mutable_context()
    InitializeStation(station, station.diagram.GetMyMutableContextFromRoot(context))
    if imitation.hardware:
        # Until its first step the targets hold the grasp corners, where the
        # station's IK assumes the hands start.
        corners = GraspCorners(imitation.scenario)
        imitation.targets.SetInitialPositions(
            imitation.targets.GetMyMutableContextFromRoot(context),
            corners["left"],
            corners["right"],
        )
    simulator.Initialize()
    station_context = station.diagram.GetMyContextFromRoot(context)
    controller_context = imitation.controller.GetMyContextFromRoot(context)
    termination = imitation.controller.GetOutputPort("termination")
    dt = imitation.step_seconds
    first_action_s, error, bar = None, None, None
    if progress:
        from tqdm import tqdm

        bar = tqdm(desc=progress, unit="step", file=sys.stderr, leave=False)
    start = imitation.start_time
    with _CtrlC() as ctrl_c:
        try:
            k = 0
            while True:
                t = start + k * dt + 3 * EVENT_STAGGER
                AdvanceStationTo(simulator, station, t)
                ctrl_c.check()
                if first_action_s is None:
                    first_action_s = time.perf_counter() - t0
                if termination.Eval(controller_context)[0] != RUNNING:
                    break
                if bar is not None:
                    bar.update()
                k += 1
            end = context.get_time() + settle_seconds
            while context.get_time() < end - 1e-9:
                AdvanceStationTo(simulator, station, min(end, context.get_time() + dt))
                ctrl_c.check()
        except RuntimeError as e:
            error = " ".join(str(e).split())[:300]
        except KeyboardInterrupt:
            message = f"at t = {context.get_time():.2f} s"
            if imitation.hardware:
                from fabric_imitation.diagrams.hardware import HoldArms

                HoldArms(station, station_context, imitation.lcm)
                message += "; both arms were told to hold their measured positions"
            raise KeyboardInterrupt(message) from None
        finally:
            if bar is not None:
                bar.close()
    final = None if imitation.hardware else CaptureFrame(station, station_context)
    logs, times = {}, None
    for name, logger in imitation.loggers.items():
        log = logger.FindLog(context)
        logs[name] = np.array(log.data()).T
        times = np.array(log.sample_times())
    return EpisodeRun(
        times=times,
        logs=logs,
        final=final,
        first_action_s=first_action_s or float("nan"),
        wall_seconds=time.perf_counter() - t0,
        error=error,
        top_layer=None if imitation.hardware else station.mesh.top_layer,
        simulator=simulator,
    )


class _CtrlC:
    """Ctrl-C (SIGINT) during a run sets a flag instead of raising inside a
    system's callback (which Drake's C++ cannot unwind through); `check()`,
    called between `AdvanceTo` calls, then raises KeyboardInterrupt there."""

    def __enter__(self):
        self._hit = False
        self._previous = None
        if threading.current_thread() is threading.main_thread():
            self._previous = signal.signal(signal.SIGINT, self._on_sigint)
        return self

    def _on_sigint(self, signum, frame) -> None:
        self._hit = True

    def check(self) -> None:
        if self._hit:
            raise KeyboardInterrupt

    def __exit__(self, *exc) -> None:
        if self._previous is not None:
            signal.signal(signal.SIGINT, self._previous)


@dc.dataclass
class Transitions:
    """The executed actions of an episode with the states around them, all in
    the object frame (rows: one per executed action)."""

    action: np.ndarray  # (n, 6)
    estimated_before: np.ndarray  # (n, M, 3)
    estimated_after: np.ndarray  # (n, M, 3)
    true_before: np.ndarray | None  # (n, M, 3), simulation only
    true_after: np.ndarray | None


def EpisodeTransitions(times: np.ndarray, logs: dict[str, np.ndarray]) -> Transitions:
    """Pairs every executed action with the states before and after it.

    Row k of the records (time k * dt) holds the true keypoints at k * dt and
    the estimate, action and step count computed in step k - 1. The action of
    step k - 1 was executed when the step count grew from row k - 1 to row k;
    its states are: estimated before = row k's estimate, after = row k + 1's;
    true before = row k - 1's true keypoints, after = row k's. Actions whose
    after-state was not recorded (a run cut short) are left out.
    """
    steps = logs["steps"][:, 0]
    rows = [
        k
        for k in range(1, len(times) - 1)
        if steps[k] > steps[k - 1]  # the action logged in row k was executed
    ]
    m = logs["estimated_keypoints"].shape[1] // 3
    pose = logs["object_pose"]

    def stack(values):
        return (
            np.array(values).reshape(len(rows), -1, 3) if rows else np.zeros((0, m, 3))
        )

    def est(k):
        return logs["estimated_keypoints"][k].reshape(m, 3)

    def true(k):
        return world_to_object(logs["true_keypoints"][k].reshape(m, 3), pose[k])

    has_true = "true_keypoints" in logs
    return Transitions(
        action=np.array(
            [
                PlanarPose(*pose[k]).vector_to_object(logs["action"][k].reshape(2, 3))
                for k in rows
            ]
        ).reshape(len(rows), 6),
        estimated_before=stack([est(k) for k in rows]),
        estimated_after=stack([est(k + 1) for k in rows]),
        true_before=stack([true(k - 1) for k in rows]) if has_true else None,
        true_after=stack([true(k) for k in rows]) if has_true else None,
    )


def CountRuleBreaks(
    before: np.ndarray,
    action: np.ndarray,
    after: np.ndarray,
    scenario: Scenario,
    safety_ctx: SafetyContext,
) -> dict:
    """How many transitions break any safety rule (judged on the state before
    and after each action), how many break each rule, and (key "at") the
    indices of the transitions that break any."""
    if len(action) == 0:
        return {"any": 0, **{rule: 0 for rule in RULES}, "at": []}
    t = torch.as_tensor
    bad = rule_violations(
        t(before, dtype=torch.float64),
        t(action, dtype=torch.float64),
        scenario.safety,
        safety_ctx,
        S_next=t(after, dtype=torch.float64),
    )
    any_bad = torch.zeros(len(action), dtype=torch.bool)
    for v in bad.values():
        any_bad |= v
    return {
        "any": int(any_bad.sum()),
        **{r: int(bad[r].sum()) for r in RULES},
        "at": torch.nonzero(any_bad)[:, 0].tolist(),
    }


def _Halt(logs: dict[str, np.ndarray]) -> dict:
    """The referee's verdict: `halt` (None, or the kind, the rule and the
    actions executed when it halted) and `collisions` (plant steps on which
    a gripper touched the object; None in a scene without one)."""
    code, rule, step = logs["halt"][-1] if "halt" in logs else (0, -1, 0)
    halt = None
    if code == HALT_RULE_BREAK:
        halt = {"kind": "rule_break", "rule": RULES[int(rule)], "step": int(step)}
    elif code == HALT_COLLISION:
        halt = {"kind": "collision", "rule": None, "step": int(step)}
    contact = logs.get("contact")
    return {
        "halt": halt,
        "collisions": int(contact[-1, 0]) if contact is not None else None,
    }


def _chamfer(camera, frame: Frame, demo: Demo, pose_now, rng) -> float:
    a = cloud_from_depth(camera, frame.depth, frame.mask, rng)
    b = cloud_from_depth(camera, demo.final_depth, demo.final_mask, rng)
    return chamfer_distance(
        world_to_object(a, pose_now), world_to_object(b, demo.object_pose)
    )


def ScoreEpisode(
    scenario: Scenario,
    prepared: PreparedImitation,
    run: EpisodeRun,
    on_violation: str = "stop",
) -> dict:
    """Success, final IoU and Chamfer distance against the demo's end state
    (simulation ground truth), rule breaks of the executed actions on the
    estimated and on the true keypoints, and control-step latencies."""
    logs = run.logs
    steps = logs["steps"][:, 0]
    termination = int(logs["termination"][-1, 0])
    solved = np.flatnonzero(np.diff(steps, prepend=0) > 0)
    solve_ms = logs["solve_ms"][solved, 0]

    def percentile(q):
        return round(float(np.percentile(solve_ms, q)), 1) if len(solve_ms) else None

    pose = PlanarPose(*logs["object_pose"][-1])
    safety_ctx = dc.replace(ObjectSafetyContext(scenario), frame_pose=np.array(pose))
    tr = EpisodeTransitions(run.times, logs)
    estimated = CountRuleBreaks(
        tr.estimated_before, tr.action, tr.estimated_after, scenario, safety_ctx
    )
    estimated.pop("at")
    # Row k holds the Chamfer distance of the image at (k - 1) dt, where the
    # rows whose step count grew decided an action: the distance seen
    # before each executed action, then the last one (after the settle).
    chamfer_rows = [*solved, len(steps) - 1]
    summary = {
        "steps": int(steps[-1]),
        "chamfer_over_steps": [
            round(float(logs["chamfer"][k, 0]), 6) for k in chamfer_rows
        ]
        if "chamfer" in logs
        else None,
        "termination": "diverged" if run.error else TERMINATION_NAMES[termination],
        "rule_breaks_estimated": estimated,
        "executed_violations": estimated["any"],
        "mpc_step_ms": {"p50": percentile(50), "p95": percentile(95)},
        "error": run.error,
    }
    if tr.true_before is not None:
        # The benchmark referee's rules (diagrams/referee.py), not the
        # controller's.
        judged = JudgeTransitions(
            TaskReferee(scenario.task),
            scenario,
            tr.true_before,
            tr.action,
            tr.true_after,
            frame_pose=np.array(pose),
        )
        true = {rule: int(v.sum()) for rule, v in judged.items()}
        # The executed actions (0-based) that broke a rule on the true cloth.
        summary["true_rule_break_steps"] = np.flatnonzero(judged["any"]).tolist()
        summary["rule_breaks_true"] = true
        summary["executed_violations_ground_truth"] = true["any"]
        summary.update(_Halt(logs))
    if tr.true_before is None:
        summary["ground_truth"] = (
            "none on hardware: success, IoU, Chamfer distance and rule breaks on "
            "the true cloth are not scored"
        )
    if run.final is not None:
        final = run.final
        report = TaskSuccess(scenario, final.positions_W, run.top_layer)
        demo = prepared.demo
        if (demo.path / "ground_truth.npz").is_file():
            gt = np.load(demo.path / "ground_truth.npz")
            demo_final_W = gt["final_keypoints_W"]
            summary["demo_final_from"] = "ground truth"
        else:  # an imported demo: what f_R sees in its last frame
            demo_final_W = prepared.priors.keypoints(demo.final_mask, demo.final_depth)
            summary["demo_final_from"] = "f_R on the demo's last frame"
        demo_final = world_to_object(demo_final_W, demo.object_pose)
        final_O = world_to_object(final.keypoints_W, pose)
        final_iou = raster_iou(final_O[:, :2], demo_final[:, :2])
        chamfer = _chamfer(
            PinholeCamera.from_model(CameraModelFromConfig(scenario.camera)),
            final,
            demo,
            pose,
            np.random.default_rng(0),
        )
        summary.update(
            # Under "stop" the referee's verdict is final, also where it came
            # after the controller had ended (a contact while the last move
            # finished, or on the way clear).
            success=bool(report.success)
            and run.error is None
            and not (on_violation == "stop" and summary.get("halt")),
            success_details=report.details,
            final_iou=round(final_iou, 3),
            final_chamfer=round(chamfer, 6),
        )
    return summary


def Imitate(
    *,
    scenario: Scenario,
    scenario_name: str,
    demo_dir: Path | None = None,
    priors_dir: Path | None = None,
    prepared: PreparedImitation | None = None,
    mpc_config: MpcConfig | None = None,
    record: Path | None = None,
    video: Path | None = None,
    progress: bool = True,
    seed: int | None = None,
    hardware: bool = False,
    lcm=None,
    co_simulate=None,
    controller: str = "mpc",
    on_violation: str = "stop",
) -> dict:
    """Runs one imitation episode; returns the JSON summary. `prepared` (from
    `PrepareImitation`) skips learning from the demo again.

    `hardware`: on real Panda drivers and camera over LCM (`lcm`, default:
    the scenario's bus), in real time. `co_simulate(lcm) -> Diagram`: a
    diagram simulated alongside on the same `lcm` (tests: `MakeSimulatedLab`
    over memq); then the run is not paced to real time."""
    wall0 = time.perf_counter()
    torch.set_num_threads(TorchThreads())
    if prepared is None:
        prepared = PrepareImitation(
            scenario,
            demo_dir=Path(demo_dir)
            if demo_dir
            else DefaultDemoDir(scenario_name, scenario),
            priors_dir=priors_dir,
        )
    t_build = time.perf_counter()
    meshcat = MakeRecordingMeshcat() if record else None
    imitation = MakeImitationDiagram(
        scenario,
        prepared,
        mpc_config=mpc_config,
        meshcat=meshcat,
        seed=seed,
        hardware=hardware,
        lcm=lcm,
        video=video is not None,
        controller=controller,
        on_violation=on_violation,
    )
    root = None
    if co_simulate is not None:
        builder = DiagramBuilder()
        builder.AddSystem(imitation.diagram)
        builder.AddSystem(co_simulate(imitation.lcm))
        root = builder.Build()
    imitation.mpc.WarmUp(prepared.demo_states[0])
    build_s = time.perf_counter() - t_build
    run = RunEpisode(
        imitation,
        settle_seconds=scenario.motion.settle_seconds,
        progress=f"imitate {scenario_name}" if progress else None,
        root=root,
        realtime_rate=1.0 if hardware and co_simulate is None else 0.0,
    )
    summary = {
        "scenario": scenario_name,
        "station": "hardware (LCM drivers)" if hardware else "simulation",
        "object_pose": list(scenario.object.pose),
        "on_violation": None if hardware else on_violation,
        **ScoreEpisode(scenario, prepared, run, on_violation),
    }
    # Writing files comes last and cannot lose the run's summary.
    WriteOutputs(
        summary, video=video, recorder=imitation.video, record=record, meshcat=meshcat
    )
    summary.update(
        {
            "demo_frames": prepared.demo.num_frames,
            "prepare_seconds": round(prepared.seconds, 2),
            "demo_to_first_action_s": round(
                prepared.seconds + build_s + run.first_action_s, 2
            ),
            "registration": prepared.registration,
            "wall_seconds": round(time.perf_counter() - wall0, 2),
        }
    )
    return summary


def TorchThreads() -> int:
    """Torch threads for the controller and f_A's training: one.

    Measured with `bench mpc` (box, N = 500, h = 5, this project's 2-core
    machine): one sampling iteration takes about 56 ms on one thread and
    75 ms on two (the tensors are too small for torch's intra-op threads to
    pay), and with another process keeping one core busy two threads spin
    against it (p95 337 ms) while one thread keeps its pace (p95 79 ms).
    OMP_WAIT_POLICY=PASSIVE fixed the loaded case but made the idle one 14x
    slower."""
    return 1
