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
import time
from pathlib import Path

import numpy as np
from fabric_imitation.diagrams.recorders import AddClothRecorder, AddVideoRecorder
from fabric_imitation.diagrams.station import (
    CameraModelFromConfig,
    ClothStation,
    MakeClothStation,
    StationPorts,
)
from fabric_imitation.learning.demo_io import Demo, LoadDemo
from fabric_imitation.learning.demo_learning import (
    DemoModel,
    learn_from_demo,
)
from fabric_imitation.learning.errors import InputError
from fabric_imitation.learning.geometry import PinholeCamera
from fabric_imitation.learning.metrics import (
    cloud_from_depth,
)
from fabric_imitation.learning.mpc import Mpc, MpcConfig
from fabric_imitation.learning.priors import DEFAULT_PRIORS, Priors, load_priors
from fabric_imitation.learning.safety import RULES, SafetyConfig
from fabric_imitation.learning.state import (
    NUM_KEYPOINTS,
    SIDES,
    corner_indices,
    world_to_object,
)
from fabric_imitation.learning.tracker import (
    KeypointTracker,
    running_median,
    track_states,
)
from fabric_imitation.scenarios.schema import Scenario
from fabric_imitation.systems.imitation import (
    CfmController,
    ChamferToDemo,
    DemoReward,
    KeypointEstimator,
    MpcController,
    PlanarPoseVector,
    ReplayController,
    ZeroController,
)
from fabric_imitation.systems.referee import Referee
from fabric_imitation.systems.targets import GripperTargetIntegrator
from fabric_imitation.systems.visualization import VideoRecorder
from fabric_imitation.tasks.referee import (
    ON_VIOLATION,
    FirstBreak,
    JudgeTransitions,
    TaskReferee,
    TaskSafetyContext,
)
from pydrake.systems.framework import Diagram, DiagramBuilder
from pydrake.systems.primitives import LogVectorOutput, Multiplexer, VectorLogSink

PACKAGE_ROOT = Path(__file__).resolve().parent.parent
DEFAULT_DEMOS = PACKAGE_ROOT / "scenarios" / "demos"
EVENT_STAGGER = 1e-3  # [s]


def DemoStates(
    priors: Priors,
    demo: Demo,
    tracker: KeypointTracker | None = None,
) -> np.ndarray:
    """S_E^1..T: f_R on every demo frame, in the demo's object frame. With a
    `tracker` (object frame), the states are tracked as the imitation's are,
    the demo's grasped corners (f_R's, through a running median of
    `tracker.config.demo_grasped_median` frames) standing in for the
    grippers the video does not measure, so demo and imitation states come
    from the same estimator."""
    p_W, spread = priors.keypoints_and_spread(demo.mask, demo.depth)
    states = world_to_object(p_W, demo.object_pose)
    if tracker is None:
        return states
    idx = corner_indices(priors.num_keypoints)
    grasped = running_median(
        states[:, [idx["s1"], idx["s2"]]], tracker.config.demo_grasped_median
    )
    return track_states(tracker, states, spread, grasped)


def _Tracker(scenario: Scenario, priors: Priors) -> KeypointTracker | None:
    """The scenario's keypoint tracker in the object frame, or None."""
    if not scenario.tracker.enabled:
        return None
    return KeypointTracker(
        forward=priors.forward,
        num_keypoints=priors.num_keypoints,
        config=scenario.tracker,
        object_size=scenario.object.size if scenario.object.kind != "none" else None,
    )


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
    # The controller's rules for this demo (the policy's, rule 2's threshold
    # from the demo where the policy says so: SafetyConfig.for_demo).
    safety: SafetyConfig
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
    states = DemoStates(priors, demo, _Tracker(scenario, priors))
    model, info = learn_from_demo(states, priors.prior_states, scenario.reward)
    safety = scenario.safety.for_demo(states)
    info = {**info, "tau_d_deg": round(safety.tau_d_deg, 2)}
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
        safety=safety,
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
    the true keypoints by the task's rules (tasks/referee.py) and watches
    gripper-object contact; with `on_violation="stop"` its ``halt`` ends the
    episode ("rule_break" or "collision"), with "count" it only records. On
    hardware there is no true cloth and no referee."""
    if on_violation not in ON_VIOLATION:
        raise InputError(
            f"unknown on-violation rule {on_violation!r}; use "
            f"{' or '.join(ON_VIOLATION)}"
        )
    if controller not in CONTROLLERS:
        raise InputError(
            f"unknown controller {controller!r}; use {', '.join(CONTROLLERS)}"
        )
    if controller in BASELINE_CONTROLLERS and prepared.baselines is None:
        raise InputError(
            f"controller {controller!r} needs PrepareImitation(..., baselines=True)"
        )
    cfg = mpc_config or scenario.mpc
    dt = scenario.motion.step_seconds
    start = dt if hardware else 0.0
    m = prepared.priors.num_keypoints
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
    estimator = builder.AddNamedSystem(
        "keypoint_estimator", _KeypointEstimator(scenario, prepared.priors, start)
    )
    reward = builder.AddNamedSystem(
        "demo_reward", DemoReward(demo=prepared.model, num_keypoints=m)
    )
    parts = _ControllerParts(
        scenario=scenario,
        prepared=prepared,
        config=cfg,
        seed=scenario.random_seed if seed is None else seed,
        timing=dict(
            num_keypoints=m,
            period=dt,
            offset=start + EVENT_STAGGER,
            step_cap=int(cfg.step_cap_factor * prepared.model.T) + 5,
        ),
    )
    mpc = parts.mpc(controller)
    system = CONTROLLERS[controller](parts, mpc)
    controller = builder.AddNamedSystem("controller", system)
    targets = builder.AddNamedSystem(
        "targets",
        GripperTargetIntegrator(
            step_seconds=dt,
            offset=start + 2 * EVENT_STAGGER,
            start_at_first_step=hardware,
        ),
    )
    pose, grippers = _WireLoop(builder, station, estimator, reward, controller, targets)
    referee = None
    if not hardware:
        referee = _AddReferee(builder, scenario, station, controller, m, dt, start)
        if on_violation == "stop":
            builder.Connect(
                referee.GetOutputPort("halt"), controller.GetInputPort("halt")
            )
    _WireCommands(builder, station, controller, targets)
    chamfer = _AddChamfer(builder, scenario, prepared, station, start)
    logged = {
        "chamfer": chamfer.GetOutputPort("chamfer"),
        "estimated_keypoints": estimator.GetOutputPort("keypoints"),
        "object_pose": pose.GetOutputPort("vector"),
        "grippers": grippers.get_output_port(),
        "reward": reward.GetOutputPort("reward"),
        **{name: controller.GetOutputPort(name) for name in CONTROLLER_LOGS},
    }
    if referee is not None:
        logged.update(_GroundTruthLogs(station, referee))
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


# The controller outputs every episode logs, once per control step.
CONTROLLER_LOGS = (
    "action",
    "termination",
    "steps",
    "progress",
    "solve_ms",
    "iterations",
    "converged",
)


def _KeypointEstimator(
    scenario: Scenario, priors: Priors, start: float
) -> KeypointEstimator:
    cam = scenario.camera
    return KeypointEstimator(
        priors=priors,
        num_keypoints=priors.num_keypoints,
        width=cam.width,
        height=cam.height,
        period=scenario.motion.step_seconds,
        offset=start,
        tracker=_Tracker(scenario, priors),
        grasped_from_grippers=scenario.tracker.grasped_from_grippers,
    )


@dc.dataclass
class _ControllerParts:
    """What every step controller is built from."""

    scenario: Scenario
    prepared: PreparedImitation
    config: MpcConfig
    seed: int
    timing: dict  # num_keypoints, period, offset, step_cap

    def mpc(self, controller: str) -> Mpc:
        """The method's planner (with the TCN reward for "tcn_mpc"); every
        ImitationDiagram keeps one."""
        args = dict(
            dynamics=self.prepared.priors,
            demo=self.prepared.model,
            safety=self.prepared.safety,
            safety_ctx=TaskSafetyContext(self.scenario, estimated=True),
            config=self.config,
        )
        if controller == "tcn_mpc":
            from fabric_imitation.learning.baseline_policies import TcnMpc

            return TcnMpc(baselines=self.prepared.baselines, **args)
        return Mpc(**args)

    def limits(self):
        """The driver's limits (max_step, reach box): all the baselines'
        moves must pass."""
        from fabric_imitation.learning.limits import DriverLimits

        return DriverLimits.FromSafety(
            self.prepared.safety, TaskSafetyContext(self.scenario, estimated=True)
        )


def _MpcController(parts: _ControllerParts, mpc: Mpc):
    return MpcController(mpc=mpc, seed=parts.seed, **parts.timing)


def _ZeroController(parts: _ControllerParts, mpc: Mpc):
    from fabric_imitation.learning.baseline_policies import ZeroFollower

    prepared = parts.prepared
    follower = ZeroFollower(
        prepared.baselines, prepared.demo_states, limits=parts.limits()
    )
    return ZeroController(follower=follower, **parts.timing)


def _CfmController(parts: _ControllerParts, mpc: Mpc):
    from fabric_imitation.learning.baseline_policies import CfmConfig, CfmPlanner

    planner = CfmPlanner(
        parts.prepared.baselines,
        parts.prepared.demo_states,
        limits=parts.limits(),
        config=CfmConfig(num_samples=parts.config.num_samples),
    )
    return CfmController(planner=planner, seed=parts.seed, **parts.timing)


def _TcnController(parts: _ControllerParts, mpc: Mpc):
    from fabric_imitation.learning.baseline_policies import TcnPlanner
    from fabric_imitation.systems.imitation import TcnController

    prepared, dt = parts.prepared, parts.scenario.motion.step_seconds
    # H: the control steps the demo took, from its frame times.
    times = prepared.demo.manifest.get("frame_times") or []
    planner = TcnPlanner(
        prepared.baselines,
        prepared.priors,
        prepared.demo_states,
        limits=parts.limits(),
        demo_steps=round((times[-1] - times[0]) / dt) if len(times) > 1 else None,
    )
    return TcnController(planner=planner, seed=parts.seed, **parts.timing)


def _ReplayController(parts: _ControllerParts, mpc: Mpc):
    corners = corner_indices(parts.timing["num_keypoints"])
    path = parts.prepared.demo_states[:, [corners["s1"], corners["s2"]]]
    return ReplayController(
        path=path, max_step=parts.scenario.safety.max_step, **parts.timing
    )


# `controller` of MakeImitationDiagram -> its step controller, given the
# parts and the planner (which only "mpc" and "tcn_mpc" use).
CONTROLLERS = {
    "mpc": _MpcController,
    "replay": _ReplayController,
    "zero": _ZeroController,
    "cfm": _CfmController,
    "tcn": _TcnController,
    "tcn_mpc": _MpcController,
}
BASELINE_CONTROLLERS = ("zero", "cfm", "tcn", "tcn_mpc")


def _WireLoop(builder, station, estimator, reward, controller, targets):
    """Station -> object pose, mask, depth, measured grippers -> estimator ->
    reward and controller. Returns the pose vector and grippers systems."""
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
    return pose, grippers


def _WireCommands(builder, station, controller, targets) -> None:
    """Controller -> relative moves -> targets -> station; its release."""
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


def _AddChamfer(builder, scenario, prepared, station, start) -> ChamferToDemo:
    """The paper's Chamfer distance to the demo's last frame, every step."""
    cam = scenario.camera
    camera_model = PinholeCamera(CameraModelFromConfig(cam))
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
            period=scenario.motion.step_seconds,
            offset=start,
        ),
    )
    for port, name in (
        (StationPorts.MASK, "mask"),
        (StationPorts.DEPTH, "depth"),
        (StationPorts.OBJECT_POSE, "object_pose"),
    ):
        builder.Connect(station.diagram.GetOutputPort(port), chamfer.GetInputPort(name))
    return chamfer


def _GroundTruthLogs(station, referee) -> dict:
    """Simulation only: the true keypoints, the referee's halt and the
    gripper-object contact."""
    logged = {
        "true_keypoints": station.diagram.GetOutputPort(StationPorts.CLOTH_KEYPOINTS),
        "halt": referee.GetOutputPort("halt"),
    }
    if station.diagram.HasOutputPort(StationPorts.GRIPPER_OBJECT_CONTACT):
        logged["contact"] = station.diagram.GetOutputPort(
            StationPorts.GRIPPER_OBJECT_CONTACT
        )
    return logged


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
