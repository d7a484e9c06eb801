"""The main job end to end (tiny settings) and its bad inputs."""

import json
import shutil
import subprocess
import sys

import numpy as np
import pytest
from fabric_imitation.diagrams.imitation import DEFAULT_DEMOS, DEFAULT_PRIORS
from fabric_imitation.diagrams.station import ClothResolution
from fabric_imitation.learning.errors import InputError
from fabric_imitation.learning.mpc import MpcConfig
from fabric_imitation.scenarios.loader import LoadScenario
from fabric_imitation.scenarios.schema import ClothConfig
from fabric_imitation.tools.episode import Imitate

from tests.conftest import SmallCloth

DEFAULT_ENGINE = ClothConfig().engine

TINY_MPC = MpcConfig(
    num_samples=40, horizon=2, elites=5, max_iterations=1, step_cap_factor=0.0
)


@pytest.mark.slow
def test_imitate_smoke_run_with_tiny_settings():
    scenario = LoadScenario(
        scenario_name="box",
        scenario_text=SmallCloth(DEFAULT_ENGINE) + "motion: {settle_seconds: 0.2}",
    )
    # Tiny on the engine the run uses, not only on the other one.
    assert np.prod(ClothResolution(scenario)) <= 6 * 6 * 2
    summary = Imitate(
        scenario=scenario, scenario_name="box", mpc_config=TINY_MPC, progress=False
    )
    assert summary["error"] is None
    assert summary["termination"] in ("step cap", "classifier", "infeasible")
    assert 1 <= summary["steps"] <= 5
    assert summary["executed_violations"] == 0
    for key in (
        "success",
        "final_iou",
        "final_chamfer",
        "mpc_step_ms",
        "demo_to_first_action_s",
        "wall_seconds",
    ):
        assert key in summary
    assert 0.0 <= summary["final_iou"] <= 1.0


def test_shipped_priors_and_demos_exist():
    assert (DEFAULT_PRIORS / "priors.pt").is_file()
    manifest = json.loads((DEFAULT_PRIORS / "manifest.json").read_text())
    bar = manifest["quality_bar"]
    metrics = json.loads((DEFAULT_PRIORS / "metrics.json").read_text())
    assert metrics == manifest["held_out_metrics"]
    # The bar is checked on the shipped metrics, not on the manifest's word.
    assert metrics["keypoint_error_visible_mm"] <= bar["keypoint_error_visible_mm_max"]
    assert metrics["keypoint_visible_fraction"] >= 0.9
    assert metrics["f_D_ratio"] <= bar["f_D_ratio_max"]
    assert metrics["f_I_ratio"] <= bar["f_I_ratio_max"]
    assert bar["met"]
    for task in ("box", "hang", "box_big"):
        assert (DEFAULT_DEMOS / task / "manifest.json").is_file()


def _cli(*args):
    return subprocess.run(
        [sys.executable, "-m", "fabric_imitation.tools.cli", "imitate", *args],
        capture_output=True,
        text=True,
        timeout=300,
    )


def test_missing_demo_directory(tmp_path):
    result = _cli("--scenario", "box", "--demo", str(tmp_path / "nope"))
    assert result.returncode == 2
    assert "demo directory not found" in result.stderr
    assert result.stderr.strip().count("\n") == 0


def test_demo_with_an_empty_mask_frame(tmp_path):
    demo = tmp_path / "demo"
    shutil.copytree(DEFAULT_DEMOS / "box", demo)
    obs = dict(np.load(demo / "observations.npz"))
    obs["mask"][3] = 0
    np.savez_compressed(demo / "observations.npz", **obs)
    manifest = json.loads((demo / "manifest.json").read_text())
    manifest["files"].pop("observations.npz")  # skip the checksum, keep the check
    (demo / "manifest.json").write_text(json.dumps(manifest))
    with pytest.raises(InputError, match=r"fabric mask is empty in frame\(s\) \[3\]"):
        Imitate(
            scenario=LoadScenario(scenario_name="box"),
            scenario_name="box",
            demo_dir=demo,
            progress=False,
        )


def test_demo_from_another_camera():
    scenario = LoadScenario(
        scenario_name="box",
        scenario_text=(
            "camera: {width: 160, height: 160, focal: !FovDegrees {y: 40.0}}"
        ),
    )
    with pytest.raises(InputError, match="another camera"):
        Imitate(scenario=scenario, scenario_name="box", progress=False)


def test_priors_that_do_not_match_the_camera_image_size():
    scenario = LoadScenario(
        scenario_name="box", scenario_text="camera: {width: 120, height: 120}"
    )
    with pytest.raises(InputError, match=r"trained on \(160, 160\) images"):
        Imitate(scenario=scenario, scenario_name="box", progress=False)


@pytest.mark.slow
def test_object_pose_outside_the_workspace():
    result = _cli("--scenario", "box", "--object-pose", "0.2", "-0.6", "0")
    assert result.returncode == 2
    assert "outside the workspace" in result.stderr


def test_demo_of_another_task():
    with pytest.raises(InputError, match="shows the 'hang' task"):
        Imitate(
            scenario=LoadScenario(scenario_name="box"),
            scenario_name="box",
            demo_dir=DEFAULT_DEMOS / "hang",
            progress=False,
        )


def test_hardware_flags_name_the_problem(capsys):
    from fabric_imitation.tools.cli import main

    assert main(["imitate", "--scenario", "box", "--hardware"]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "--hardware needs a scenario with Panda" in err
    args = ["--scenario", "box_panda", "--hardware", "--record", "x.html"]
    assert main(["imitate", *args]) == 2
    assert "--record shows the simulated cloth" in capsys.readouterr().err
    assert main(["imitate", "--scenario", "box", "--lcm-url", "memq://"]) == 2
    assert "--lcm-url is for --hardware" in capsys.readouterr().err
