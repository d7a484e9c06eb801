"""`fabric-imitate demo record`: run the scripted demonstration of a task and
save it as an observation-only demo."""

from pathlib import Path

import numpy as np
from fabric_imitation.diagrams.recording import MakeRecordingMeshcat
from fabric_imitation.diagrams.station import CameraModelFromConfig, ClothStation
from fabric_imitation.learning.demo_io import (
    CameraModel,
    ExistingDemoRequest,
    WriteDemo,
)
from fabric_imitation.learning.errors import InputError
from fabric_imitation.scenarios.loader import DumpScenario
from fabric_imitation.scenarios.schema import Scenario
from fabric_imitation.tasks.demos import ScriptedDemoPlan
from fabric_imitation.tools.simulation import OpenLoopRun, RunResult, WriteOutputs


def StationCameraModel(station: ClothStation) -> CameraModel:
    return CameraModel.FromIntrinsics(
        station.camera_info, station.X_WCamera.GetAsMatrix4()
    )


def RunSummary(result: RunResult) -> dict:
    return {
        "success": bool(result.success.success),
        "success_details": result.success.details,
        "sim_seconds": round(result.sim_seconds, 3),
        "wall_seconds": round(result.wall_seconds, 3),
        "realtime_factor": round(result.realtime_factor, 3),
        "error": result.error,
        **({"robot": result.robot} if result.robot else {}),
    }


def RecordDemo(
    *,
    scenario: Scenario,
    scenario_name: str,
    out: Path,
    record: Path | None = None,
    video: Path | None = None,
    progress: bool = True,
    export_raw: Path | None = None,
    raw_scale: int = 4,
    raw_fps: float = 15.0,
) -> dict:
    """Records the scripted demo of `scenario` into `out`; returns a summary.

    With `export_raw`, also writes there what an RGB-D camera driver at the
    control camera's pose would record (learning/demo_import.py's format):
    the camera at `raw_scale` times the control camera's resolution,
    `raw_fps` frames per second, from the start to the end of the settle.

    Re-running with the same request on a finished directory records nothing
    and returns the stored summary; a directory holding another demo, or the
    same demo recorded in another version of the scenario (its
    scenario.yaml differs: another cloth engine setting, say), is an
    InputError.
    """
    out = Path(out)
    request = {
        "task": scenario.task,
        "scenario_name": scenario_name,
        "object_pose": [round(float(v), 6) for v in scenario.object.pose],
        "cloth_pose": [round(float(v), 6) for v in scenario.cloth.pose],
    }
    existing = ExistingDemoRequest(out)
    if existing is not None:
        if {k: existing.get(k) for k in request} != request:
            raise InputError(
                f"output directory {out} already holds a different demo "
                f"({existing.get('scenario_name')} at object pose "
                f"{existing.get('object_pose')})"
            )
        stored = out / "scenario.yaml"
        if not stored.is_file() or stored.read_text() != DumpScenario(scenario):
            raise InputError(
                f"output directory {out} holds this demo recorded in another "
                f"version of scenario {scenario_name} (its scenario.yaml "
                "differs); remove the directory to record it again"
            )
        return {
            **{k: existing[k] for k in existing if k not in ("files",)},
            "out": str(out),
            "recorded": False,
        }
    # Checked before the run, so a full raw directory does not cost a run.
    raw_dir = Path(export_raw) if export_raw is not None else None
    full = raw_dir is not None and raw_dir.exists()
    if full and (not raw_dir.is_dir() or any(raw_dir.iterdir())):
        raise InputError(f"raw output directory {export_raw} is not empty")
    plan = ScriptedDemoPlan(scenario)
    meshcat = MakeRecordingMeshcat() if record else None
    run = OpenLoopRun(
        scenario,
        actions=plan.actions,
        release_step=plan.release_step,
        meshcat=meshcat,
        video=video is not None,
        raw_camera_scale=raw_scale if export_raw else 0,
        raw_fps=raw_fps,
    )
    result = run.run(progress=progress)
    if result.error is not None:
        raise RuntimeError(f"the demo simulation failed: {result.error}")
    frames = result.frames
    summary = RunSummary(result)
    summary["frame_times"] = [round(f.time, 4) for f in frames]
    summary["step_seconds"] = scenario.motion.step_seconds
    WriteDemo(
        out,
        request=request,
        rgb=[f.rgb for f in frames] + [result.final.rgb],
        depth=np.stack([f.depth for f in frames]),
        mask=np.stack([f.mask for f in frames]),
        final_depth=result.final.depth,
        final_mask=result.final.mask,
        camera=StationCameraModel(run.station),
        scenario_yaml=DumpScenario(scenario),
        ground_truth={
            "keypoints_W": np.stack([f.keypoints_W for f in frames]),
            "final_positions_W": result.final.positions_W,
            "final_keypoints_W": result.final.keypoints_W,
        },
        summary=summary,
        fps=1.0 / scenario.motion.step_seconds,
    )
    if export_raw is not None:
        from fabric_imitation.diagrams.station import RawCameraConfig
        from fabric_imitation.learning.demo_import import WriteRawRecording

        raw = CameraModelFromConfig(RawCameraConfig(scenario, raw_scale))
        WriteRawRecording(
            export_raw,
            rgb=run.raw.rgb,
            depth=run.raw.depth,
            fps=raw_fps,
            intrinsics={
                "width": raw.width,
                "height": raw.height,
                "fx": raw.fx,
                "fy": raw.fy,
                "cx": raw.cx,
                "cy": raw.cy,
            },
        )
        summary["export_raw"] = {
            "out": str(export_raw),
            "frames": len(run.raw.rgb),
            "fps": raw_fps,
            "size": [raw.width, raw.height],
        }
    WriteOutputs(
        summary, video=video, recorder=run.video, record=record, meshcat=meshcat
    )
    return {
        **request,
        "num_frames": len(frames),
        **summary,
        "out": str(out),
        "recorded": True,
    }


def ImportDemoForScenario(
    *,
    recording,
    scenario: Scenario,
    scenario_name: str,
    out: Path,
    marker=None,
    step_seconds: float | None = None,
    **kwargs,
) -> dict:
    """`fabric-imitate demo import`: learning/demo_import.py's `ImportDemo`
    for `scenario`: its control camera, task and control period, and (unless
    `marker` is given) the object's marker it describes."""
    from fabric_imitation.learning.demo_import import ImportDemo, MarkerSpec

    if marker is None:
        spec = scenario.object.marker
        marker = MarkerSpec(spec.dictionary, spec.id, spec.size, list(spec.offset))
    if marker.marker_id < 0:
        raise InputError(
            "no marker: give --marker-id or set object.marker in the scenario"
        )
    return ImportDemo(
        recording=recording,
        camera=CameraModelFromConfig(scenario.camera),
        task=scenario.task,
        scenario_name=scenario_name,
        scenario_yaml=DumpScenario(scenario),
        step_seconds=step_seconds or scenario.motion.step_seconds,
        out=out,
        marker=marker,
        **kwargs,
    )
