"""Open-loop runs of the station (scripted demos, data collection, benchmarks)
and the outputs of a run: videos and the meshcat recording."""

import dataclasses as dc
import sys
import time
from collections.abc import Callable
from pathlib import Path

import numpy as np
from fabric_imitation.diagrams.recorders import (
    AddClothRecorder,
    AddVideoRecorder,
    CaptureFrame,
    Frame,
)
from fabric_imitation.diagrams.station import (
    AdvanceStationTo,
    InitializeStation,
    MakeClothStation,
    StationPorts,
)
from fabric_imitation.learning.demo_io import VIDEO_MIN_SIZE, WriteVideo
from fabric_imitation.learning.state import SIDES
from fabric_imitation.scenarios.poses import GraspCorners
from fabric_imitation.scenarios.schema import Scenario
from fabric_imitation.systems.targets import ActionPlayer, GripperTargetIntegrator
from fabric_imitation.systems.visualization import (
    RgbdRecorder,
    VideoRecorder,
)
from fabric_imitation.tasks.success import SuccessReport, TaskSuccess
from pydrake.geometry import Meshcat
from pydrake.systems.analysis import Simulator
from pydrake.systems.framework import DiagramBuilder


class SimulationDivergedError(RuntimeError):
    """The physics engine failed or produced non-finite cloth positions."""


def WriteOutputs(
    summary: dict, *, video=None, recorder=None, record=None, meshcat=None
):
    """Writes the run's videos and meshcat recording after the run, last; a
    file that cannot be written goes into `summary["output_errors"]`
    instead of losing the summary. Returns `summary`."""
    from fabric_imitation.diagrams.recording import SaveRecording

    errors = []
    if video is not None and recorder is not None:
        try:
            summary["videos"] = WriteVideos(recorder, Path(video))
        except OSError as e:
            errors.append(f"--video {video}: {e}")
    if record is not None and meshcat is not None:
        try:
            SaveRecording(meshcat, record)
        except OSError as e:
            errors.append(f"--record {record}: {e}")
    if errors:
        summary["output_errors"] = errors
    return summary


def PeopleVideoPath(path: Path) -> Path:
    """run.mp4 -> run.people.mp4: the oblique camera's video."""
    return path.with_name(path.stem + ".people" + path.suffix)


def WriteVideos(recorder: VideoRecorder, path: Path) -> list[str]:
    """The recorder's control-camera frames to `path` (upscaled to at least
    VIDEO_MIN_SIZE) and, when recorded, the people's camera's to
    `PeopleVideoPath(path)`, H.264 at its frame rate. Returns the paths."""
    written = []
    for port, out in (
        (StationPorts.RGB, path),
        (StationPorts.PEOPLE_RGB, PeopleVideoPath(path)),
    ):
        frames = recorder.frames.get(port)
        if frames:
            WriteVideo(out, frames, recorder.fps, min_size=VIDEO_MIN_SIZE)
            written.append(str(out))
    return written


@dc.dataclass
class RunResult:
    scenario: Scenario
    frames: list[Frame]  # initial + one per control step, up to the release
    final: Frame  # after release and settling
    success: SuccessReport
    sim_seconds: float
    wall_seconds: float
    error: str | None = None
    # Panda arms only: smallest joint-limit margin [rad] and largest distance
    # [m] between a hand and its target at the end of a control step.
    robot: dict | None = None

    @property
    def realtime_factor(self) -> float:
        return self.sim_seconds / max(self.wall_seconds, 1e-9)


class OpenLoopRun:
    """A station driven by a fixed action list.

    Args:
        scenario: the scenario.
        actions: (K, 6) relative moves, one per control step.
        release_step: the control step at which the grasps open (None: never).
        meshcat: record the run into this meshcat (cloth animated).
    """

    def __init__(
        self,
        scenario: Scenario,
        *,
        actions: np.ndarray,
        release_step: int | None,
        meshcat: Meshcat | None = None,
        video: bool = False,
        raw_camera_scale: int = 0,
        raw_fps: float = 15.0,
    ):
        self.scenario = scenario
        self.actions = np.asarray(actions, dtype=float).reshape(-1, 6)
        self.release_step = release_step
        self.step_seconds = scenario.motion.step_seconds
        builder = DiagramBuilder()
        self.station = MakeClothStation(
            scenario,
            meshcat=meshcat,
            people_camera=video,
            raw_camera_scale=raw_camera_scale,
        )
        station = builder.AddNamedSystem("station", self.station.diagram)
        integrator = builder.AddNamedSystem(
            "targets", GripperTargetIntegrator(step_seconds=self.step_seconds)
        )
        player = builder.AddNamedSystem(
            "player",
            ActionPlayer(
                actions=self.actions,
                step_seconds=self.step_seconds,
                release_step=release_step,
            ),
        )
        builder.Connect(
            player.GetOutputPort("action"), integrator.GetInputPort("action")
        )
        builder.Connect(
            player.GetOutputPort("release"), station.GetInputPort(StationPorts.RELEASE)
        )
        for side in SIDES:
            builder.Connect(
                integrator.GetOutputPort(f"{side}.ee_target"),
                station.GetInputPort(StationPorts.ee_target(side)),
            )
        self.meshcat = meshcat
        self.video = AddVideoRecorder(builder, self.station) if video else None
        # What an RGB-D camera driver would record (demo record --export-raw).
        self.raw = None
        if raw_camera_scale:
            cam = scenario.camera
            self.raw = builder.AddNamedSystem(
                "raw_recorder",
                RgbdRecorder(
                    width=cam.width * raw_camera_scale,
                    height=cam.height * raw_camera_scale,
                    fps=raw_fps,
                ),
            )
            for port, name in (
                (StationPorts.RAW_RGB, "rgb"),
                (StationPorts.RAW_DEPTH, "depth"),
            ):
                builder.Connect(
                    station.GetOutputPort(port), self.raw.GetInputPort(name)
                )
        if meshcat is not None:
            AddClothRecorder(builder, self.station, meshcat)
        self.diagram = builder.Build()
        self.integrator = integrator
        self.simulator = Simulator(self.diagram)
        self.context = self.simulator.get_mutable_context()
        corners = GraspCorners(scenario)
        integrator.SetInitialPositions(
            integrator.GetMyMutableContextFromRoot(self.context),
            corners["left"],
            corners["right"],
        )
        self.station_context = station.GetMyContextFromRoot(self.context)
        InitializeStation(
            self.station, station.GetMyMutableContextFromRoot(self.context)
        )
        self.simulator.Initialize()

    @property
    def num_steps(self) -> int:
        return len(self.actions)

    def capture(self) -> Frame:
        return CaptureFrame(self.station, self.station_context)

    robot: dict | None = None

    def _robot_stats(self) -> None:
        """Joint-limit margin and hand tracking error of Panda arms."""
        station, plant = self.station.diagram, self.station.plant
        if not station.HasOutputPort("left_panda.position_measured"):
            return
        targets_context = self.integrator.GetMyContextFromRoot(self.context)
        margin, error = np.inf, 0.0
        for side in SIDES:
            instance = plant.GetModelInstanceByName(f"{side}_panda")
            q = station.GetOutputPort(f"{side}_panda.position_measured").Eval(
                self.station_context
            )
            joints = [
                plant.GetJointByName(f"panda_joint{i}", instance) for i in range(1, 8)
            ]
            lower = np.array([j.position_lower_limits()[0] for j in joints])
            upper = np.array([j.position_upper_limits()[0] for j in joints])
            margin = min(margin, float(np.min(np.minimum(q - lower, upper - q))))
            target = self.integrator.GetOutputPort(f"{side}.ee_target").Eval(
                targets_context
            )
            measured = station.GetOutputPort(StationPorts.ee_measured(side)).Eval(
                self.station_context
            )
            error = max(error, float(np.linalg.norm(measured - target)))
        old = self.robot or {
            "min_joint_limit_margin_rad": np.inf,
            "max_hand_tracking_error_m": 0.0,
        }
        self.robot = {
            "min_joint_limit_margin_rad": round(
                min(old["min_joint_limit_margin_rad"], margin), 4
            ),
            "max_hand_tracking_error_m": round(
                max(old["max_hand_tracking_error_m"], error), 4
            ),
        }

    def capture_positions(self) -> np.ndarray:
        """Ground-truth cloth vertices (N, 3), without rendering."""
        port = self.station.diagram.GetOutputPort(StationPorts.CLOTH_POSITIONS)
        return np.array(port.Eval(self.station_context)).reshape(-1, 3)

    def advance_to(self, t: float) -> None:
        try:
            AdvanceStationTo(self.simulator, self.station, t)
        except RuntimeError as e:
            raise SimulationDivergedError(" ".join(str(e).split())[:300]) from None
        positions = self.station.diagram.GetOutputPort(
            StationPorts.CLOTH_POSITIONS
        ).Eval(self.station_context)
        if not np.all(np.isfinite(positions)):
            raise SimulationDivergedError(
                f"non-finite cloth positions at t = {t:.2f} s"
            )

    def run(
        self,
        *,
        capture_frames: bool = True,
        settle: bool = True,
        progress: bool = False,
        on_step: Callable[[int, Frame | None], None] | None = None,
    ) -> RunResult:
        """Runs every action (capturing a frame after each), then releases and
        settles for `motion.settle_seconds` if a release step was given."""
        wall0 = time.perf_counter()
        frames = [self.capture()] if capture_frames else []
        steps = range(self.num_steps)
        bar = None
        if progress:
            from tqdm import tqdm

            bar = tqdm(
                total=self.num_steps,
                desc=self.scenario.task,
                unit="step",
                file=sys.stderr,
                leave=False,
            )
        error = None
        try:
            for k in steps:
                self.advance_to((k + 1) * self.step_seconds)
                self._robot_stats()
                frame = self.capture() if capture_frames else None
                if frame is not None:
                    frames.append(frame)
                if on_step is not None:
                    on_step(k, frame)
                if bar is not None:
                    bar.update()
            if settle and self.release_step is not None:
                t_release = max(
                    self.release_step * self.step_seconds, self.context.get_time()
                )
                self.advance_to(t_release)
                self.advance_to(t_release + self.scenario.motion.settle_seconds)
        except SimulationDivergedError as e:
            error = str(e)
        finally:
            if bar is not None:
                bar.close()
        final = self.capture()
        report = TaskSuccess(
            self.scenario, final.positions_W, self.station.mesh.top_layer
        )
        if error is not None:
            report = SuccessReport(False, {"error": error})
        return RunResult(
            robot=self.robot,
            scenario=self.scenario,
            frames=frames,
            final=final,
            success=report,
            sim_seconds=self.context.get_time(),
            wall_seconds=time.perf_counter() - wall0,
            error=error,
        )
