"""`fabric-imitate simulate`: one run of a scenario, holding still or scripted."""

from pathlib import Path

import numpy as np
from fabric_imitation.diagrams.recording import MakeRecordingMeshcat
from fabric_imitation.learning.errors import InputError
from fabric_imitation.scenarios.schema import Scenario
from fabric_imitation.tasks.demos import ScriptedDemoPlan
from fabric_imitation.tools.demo_record import RunSummary
from fabric_imitation.tools.simulation import OpenLoopRun, WriteOutputs


def Simulate(
    *,
    scenario: Scenario,
    scenario_name: str,
    duration: float = 2.0,
    motion: str = "hold",
    record: Path | None = None,
    video: Path | None = None,
    progress: bool = True,
) -> dict:
    """Simulates `scenario`; `motion` is "hold" (grippers still for `duration`
    seconds) or "scripted" (the task's scripted demo, release, settling)."""
    if motion == "hold":
        if duration <= 0:
            raise InputError(f"--duration must be positive, got {duration}")
        steps = int(np.ceil(duration / scenario.motion.step_seconds - 1e-9))
        actions, release_step = np.zeros((steps, 6)), None
    elif motion == "scripted":
        plan = ScriptedDemoPlan(scenario)
        actions, release_step = plan.actions, plan.release_step
    else:
        raise InputError(f"unknown motion {motion!r}; use hold or scripted")
    meshcat = MakeRecordingMeshcat() if record else None
    run = OpenLoopRun(
        scenario,
        actions=actions,
        release_step=release_step,
        meshcat=meshcat,
        video=video is not None,
    )
    result = run.run(capture_frames=False, progress=progress)
    summary = {
        "scenario": scenario_name,
        "motion": motion,
        "cloth_vertices": len(run.station.mesh.vertices),
        "time_step": scenario.plant_config.time_step,
        "contact_approximation": scenario.plant_config.discrete_contact_approximation,
        **RunSummary(result),
    }
    return WriteOutputs(
        summary, video=video, recorder=run.video, record=record, meshcat=meshcat
    )
