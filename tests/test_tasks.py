"""Scripted demos, success predicates, demo files and recordings, on the real
simulator. The scripted demos run at full resolution (they are the physics
sanity check), so they take tens of seconds each."""

import base64
import json
import re
import subprocess
import sys

import msgpack
import numpy as np
import pytest
from fabric_imitation.diagrams.recording import MakeRecordingMeshcat, SaveRecording
from fabric_imitation.learning.demo_io import LoadDemo
from fabric_imitation.learning.errors import InputError
from fabric_imitation.scenarios.loader import LoadScenario
from fabric_imitation.tasks.demos import ScriptedDemoPlan
from fabric_imitation.tools.demo_record import RecordDemo
from fabric_imitation.tools.simulation import OpenLoopRun

from tests.conftest import SMALL_CLOTH


@pytest.mark.slow
@pytest.mark.parametrize("name", ["box", "hang", "box_big", "cylinder", "rail"])
def test_scripted_demo_succeeds_and_untouched_cloth_does_not(name):
    scenario = LoadScenario(scenario_name=name)
    plan = ScriptedDemoPlan(scenario)
    done = OpenLoopRun(
        scenario, actions=plan.actions, release_step=plan.release_step
    ).run(capture_frames=False)
    assert done.error is None
    assert done.success.success, done.success.details
    # The untouched cloth lies flat on the table, where a fine mesh is slow
    # (the hang towel: 2.4 s per step); the predicate does not need it.
    coarse = LoadScenario(
        scenario_name=name, scenario_text="cloth: {resolution: [11, 11, 2]}"
    )
    still = OpenLoopRun(coarse, actions=np.zeros((2, 6)), release_step=2).run(
        capture_frames=False
    )
    assert not still.success.success, still.success.details


@pytest.mark.parametrize(
    "name, size, bound",
    [
        ("hang", [0.17, 0.01, 0.12], "less than 0.200 m"),
        ("rail", [0.45, 0.02, 0.18], "less than 0.200 m"),
        ("rail", [0.32, 0.02, 0.24], "plus both posts"),
        ("cylinder", [0.06, 0.06, 0.15], "more than 0.47 of the top's depth"),
        ("box", [0.28, 0.09, 0.06], "grasped edge's span"),
    ],
)
def test_a_size_the_scripted_demo_cannot_serve_is_refused_with_its_bound(
    name, size, bound
):
    scenario = LoadScenario(
        scenario_name=name, scenario_text=f"object: {{size: {size}}}"
    )
    with pytest.raises(InputError, match=bound) as e:
        ScriptedDemoPlan(scenario)
    assert "\n" not in str(e.value)


def _demo_record(*args: str) -> subprocess.CompletedProcess:
    """`fabric-imitate demo record ARGS` in a subprocess (exit code and
    stderr as a user sees them)."""
    return subprocess.run(
        [sys.executable, "-m", "fabric_imitation.tools.cli", "demo", "record", *args],
        capture_output=True,
        text=True,
        timeout=120,
    )


def test_a_size_the_scripted_demo_cannot_serve_exits_2_with_one_line(tmp_path):
    out = tmp_path / "demo"
    done = _demo_record(
        "--scenario",
        "hang",
        "--scenario-text",
        "object: {size: [0.17, 0.01, 0.12]}",
        "--out",
        str(out),
    )
    assert done.returncode == 2
    lines = done.stderr.strip().splitlines()
    assert lines[-1].startswith("fabric-imitate: error: the scripted hang cannot")
    assert not out.exists()


def test_scripted_plan_is_defined_in_the_object_frame():
    a = LoadScenario(scenario_name="box")
    b = LoadScenario(
        scenario_name="box", scenario_text="object: {pose: [0.05, -0.10, 30.0]}"
    )
    wa, wb = ScriptedDemoPlan(a).waypoints_W, ScriptedDemoPlan(b).waypoints_W
    yaw = np.radians(30.0)
    R = np.array(
        [[np.cos(yaw), -np.sin(yaw), 0], [np.sin(yaw), np.cos(yaw), 0], [0, 0, 1]]
    )
    # Waypoints after the first (lift) move rigidly with the object.
    for pa, pb in zip(wa[1:], wb[1:], strict=True):
        pa_O = pa - [0.0, -0.14, 0.0]
        np.testing.assert_allclose(pb, pa_O @ R.T + [0.05, -0.10, 0.0], atol=1e-9)
    assert np.abs(ScriptedDemoPlan(b).actions).max() <= a.safety.max_step + 1e-12


def _html_commands(path):
    html = path.read_text()
    blobs = re.findall(r"data:application/octet-binary;base64,([A-Za-z0-9+/=]+)", html)
    return [
        msgpack.unpackb(base64.b64decode(b), raw=False, strict_map_key=False)
        for b in blobs
    ]


def test_recording_animates_the_cloth(tmp_path):
    scenario = LoadScenario(scenario_name="prior", scenario_text=SMALL_CLOTH)
    html = tmp_path / "run.html"
    meshcat = MakeRecordingMeshcat()
    lift = np.tile([0, 0, 0.03, 0, 0, 0.03], (3, 1))
    OpenLoopRun(scenario, actions=lift, release_step=None, meshcat=meshcat).run(
        capture_frames=False
    )
    SaveRecording(meshcat, html)
    commands = _html_commands(html)
    meshes = {
        c["path"]: c
        for c in commands
        if c["type"] == "set_object" and c["path"].startswith("/cloth_frames/")
    }
    assert len(meshes) >= 8
    first, last = sorted(meshes)[0], sorted(meshes)[-1]

    def vertices(c):
        geometry = c["object"]["geometries"][0]
        data = geometry["data"]["attributes"]["position"]["array"]
        raw = data.data if isinstance(data, msgpack.ExtType) else data
        return np.frombuffer(raw, dtype=np.float32).reshape(-1, 3)

    lifted = vertices(meshes[last])[:, 2].max() - vertices(meshes[first])[:, 2].max()
    assert lifted > 0.05
    animation = next(c for c in commands if c["type"] == "set_animation")
    tracks = {a["path"]: a["clip"]["tracks"] for a in animation["animations"]}
    shown = [
        p
        for p in meshes
        if any(k["value"] for t in tracks.get(p, []) for k in t["keys"])
    ]
    assert len(shown) == len(meshes)  # every frame is shown at its time
    hidden = [
        c
        for c in commands
        if c["type"] == "set_property"
        and c["path"].startswith("/drake/scene/deformable")
        and c["property"] == "visible"
        and c["value"] is False
    ]
    assert hidden  # Drake's static last-shape cloth is hidden


@pytest.mark.slow
def test_demo_record_writes_an_observation_only_demo(tmp_path):
    scenario = LoadScenario(scenario_name="box")
    out = tmp_path / "demo"
    video = tmp_path / "view.mp4"
    summary = RecordDemo(
        scenario=scenario, scenario_name="box", out=out, video=video, progress=False
    )
    assert summary["success"] is True
    demo = LoadDemo(out)
    assert demo.num_frames == summary["num_frames"] >= 10
    assert demo.mask.shape[1:] == (160, 160)
    assert "action" not in json.dumps(demo.manifest)
    assert video.stat().st_size > 1000
    # Same request again: nothing recorded, same summary.
    again = RecordDemo(scenario=scenario, scenario_name="box", out=out, progress=False)
    assert again["recorded"] is False and again["success"] is True
    # A different demo into the same directory is refused.
    moved = LoadScenario(
        scenario_name="box", scenario_text="object: {pose: [0.05, -0.14, 10.0]}"
    )
    with pytest.raises(InputError, match="already holds a different demo"):
        RecordDemo(scenario=moved, scenario_name="box", out=out, progress=False)
    # So is the same demo in another version of the scenario (here another
    # cloth setting): it would be stale, not a finished run to resume.
    changed = LoadScenario(
        scenario_name="box", scenario_text="cloth: {vbd: {iterations: 3}}"
    )
    with pytest.raises(InputError, match="another version of scenario box"):
        RecordDemo(scenario=changed, scenario_name="box", out=out, progress=False)
    # A truncated file is detected.
    obs = out / "observations.npz"
    obs.write_bytes(obs.read_bytes()[:1000])
    with pytest.raises(InputError, match="truncated or changed"):
        LoadDemo(out)


def test_demo_record_rejects_an_object_pose_outside_the_workspace(tmp_path):
    out = tmp_path / "demo"
    result = _demo_record(
        "--scenario", "box", "--out", str(out), "--object-pose", "0.9", "0", "0"
    )
    assert result.returncode == 2
    assert "outside the workspace" in result.stderr
    assert not out.exists()
