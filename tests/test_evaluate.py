"""Evaluation bookkeeping: aggregates and the Table-I markdown agree with the
trials' JSON lines."""

import numpy as np
import pytest
from fabric_imitation.learning.mpc import MpcConfig
from fabric_imitation.tools.evaluate import (
    METHODS,
    PROTOCOLS,
    ResultsMarkdown,
    _aggregate,
)


def _row(trial, success, breaks, steps, iou):
    rules = {"any": breaks, "bounds": 0, "distance": 0, "direction": breaks}
    return {
        "trial": trial,
        "success": success,
        "final_iou": iou,
        "final_chamfer": 0.001,
        "executed_violations": 0,
        "executed_violations_ground_truth": breaks,
        "rule_breaks_true": {**rules, "workspace": 0, "object": 0},
        "termination": "classifier",
        "mpc_step_ms": {"p50": 60.0, "p95": 90.0},
        "steps": steps,
        "trial_seconds": 10.0,
    }


def test_the_table_agrees_with_the_trials():
    rows = [
        _row(0, True, 0, 20, 0.9),
        _row(1, False, 3, 40, 0.5),
        _row(2, True, 1, 30, 0.7),
    ]
    cell = _aggregate(rows)
    assert (cell["successes"], cell["trials"]) == (2, 3)
    assert cell["executed_violations_ground_truth"] == 4
    assert cell["trials_with_true_rule_breaks"] == 2
    assert cell["steps_mean"] == 30.0
    summary = {
        "protocol": "wide",
        "protocol_band": {
            "max_shift_m": PROTOCOLS["wide"][0],
            "max_turn_deg": PROTOCOLS["wide"][1],
        },
        "seed": 4,
        "trials_per_cell": 3,
        "results": {"hang": {"replay": cell}},
    }
    table = ResultsMarkdown(summary)
    assert (
        "| hang | replay | 2 / 3 (67%) | 0.70 +- 0.16 | 0.0010 | 4 (2) | 30.0 |"
        in table
    )
    assert "Protocol `wide` (object moved <= 15 cm, turned <= 90 deg)" in table


def test_final_iou_is_bounded_for_a_twisted_outline():
    import numpy as np
    import torch
    from fabric_imitation.learning.metrics import raster_iou
    from fabric_imitation.learning.polygon import iou

    square = np.array([[0, 0], [0.3, 0], [0.3, 0.3], [0, 0.3]])
    for shift in (0.0, 0.1, 0.2):
        moved = square + [shift, 0.05]
        exact = float(iou(torch.as_tensor(square), torch.as_tensor(moved)))
        assert abs(raster_iou(square, moved) - exact) < 0.01
    bow_tie = np.array([[0, 0], [0.3, 0.3], [0.3, 0], [0, 0.3]])
    assert 0.45 < raster_iou(bow_tie, square) < 0.55
    assert raster_iou(bow_tie, bow_tie) == 1.0


@pytest.mark.slow
def test_an_evaluation_killed_mid_way_resumes_without_repeating_or_losing(tmp_path):
    import json
    import os
    import signal
    import subprocess
    import sys
    import time

    from conftest import SmallCloth
    from fabric_imitation.tools.evaluate import Machine

    out = tmp_path / "eval.jsonl"
    command = [
        sys.executable,
        "-m",
        "fabric_imitation.tools.cli",
        "evaluate",
        "--scenarios",
        "box",
        "--methods",
        "scripted",
        "--trials",
        "3",
        "--scenario-text",
        SmallCloth("vbd"),
        "--out",
        str(out),
    ]
    first = subprocess.Popen(
        command, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL
    )
    deadline = time.time() + 240
    while time.time() < deadline and not (out.exists() and out.read_text().count("\n")):
        time.sleep(0.2)
    os.kill(first.pid, signal.SIGKILL)
    first.wait()
    before = out.read_text().splitlines()
    assert 1 <= len(before) < 3
    subprocess.run(command, check=True, capture_output=True, timeout=300)
    rows = [json.loads(line) for line in out.read_text().splitlines()]
    assert out.read_text().splitlines()[: len(before)] == before  # kept as written
    assert sorted(r["trial"] for r in rows) == [0, 1, 2]  # none repeated, none lost
    # Each line says which machine ran it (`compare` reads it).
    assert {r["machine"]["id"] for r in rows} == {Machine()["id"]}
    summary = json.loads((tmp_path / "eval.jsonl.summary.json").read_text())
    assert summary["results"]["box"]["scripted"]["trials"] == 3


def test_a_trial_that_raises_is_one_failed_row(monkeypatch):
    """A crash inside a trial is recorded as that trial's failure (the sweep
    goes on), and the cell counts it without its episode figures."""
    import fabric_imitation.tools.episode as episode
    import fabric_imitation.tools.evaluate as evaluate

    def crash(**kwargs):
        raise ValueError("the controller exploded")

    monkeypatch.setattr(episode, "Imitate", crash)
    monkeypatch.setitem(evaluate._PREPARED, "box", object())
    row = evaluate._run_trial(
        {
            "scenario": "box",
            "method": "zero",
            "trial": 3,
            "pose": [0.0, -0.14, 10.0],
            "scenario_text": "",
        }
    )
    assert row["success"] is False and row["trial"] == 3
    assert row["error"] == "ValueError: the controller exploded"
    cell = _aggregate([_row(0, True, 0, 20, 0.9), row])
    assert (cell["successes"], cell["trials"], cell["crashed"]) == (1, 2, 1)
    assert cell["steps_mean"] == 20.0


def test_returns_and_curves_follow_the_trials(tmp_path):
    """Fig. 8's curves: the return drops by one warning per rule-breaking
    action and gains the success reward at the end; shorter episodes hold
    their last value in the mean; the plot is written."""
    from fabric_imitation.tools.evaluate import (
        SUCCESS_REWARD,
        WARNING_REWARD,
        EpisodeReturns,
        _padded_mean,
        _plot_curves,
    )

    row = {"steps": 4, "true_rule_break_steps": [1, 2], "success": True}
    np.testing.assert_allclose(
        EpisodeReturns(row),
        [0, WARNING_REWARD, 2 * WARNING_REWARD, 2 * WARNING_REWARD + SUCCESS_REWARD],
    )
    np.testing.assert_allclose(
        _padded_mean([np.array([1.0, 2.0]), np.array([3.0])]), [2.0, 2.5]
    )
    rows = [
        {**_row(0, True, 0, 3, 0.9), "chamfer_over_steps": [0.004, 0.002, 0.001]},
        {**_row(1, False, 1, 2, 0.5), "chamfer_over_steps": [0.004, 0.003]},
    ]
    path = tmp_path / "curves.png"
    _plot_curves({("box", "ours"): rows, ("box", "zero"): rows[1:]}, path)
    assert path.stat().st_size > 10_000


@pytest.mark.slow
def test_ray_and_local_evaluations_write_the_same_trials(tmp_path):
    """`--executor ray` (a local Ray) stores the same trial rows and summary
    as local processes."""
    import json

    import pytest

    ray = pytest.importorskip("ray")
    from fabric_imitation.tools.evaluate import Evaluate

    common = dict(
        scenario_names=["box"],
        methods=["scripted"],
        trials=2,
        seed=0,
        scenario_text="cloth: {vbd: {resolution: [8, 8]}}",
        progress=False,
    )
    local = Evaluate(out=tmp_path / "local.jsonl", workers=1, **common)
    ray.init(num_cpus=2, include_dashboard=False, log_to_driver=False)
    try:
        remote = Evaluate(
            out=tmp_path / "ray.jsonl", workers=2, executor="ray", **common
        )
    finally:
        ray.shutdown()

    def rows(name):
        lines = (tmp_path / name).read_text().splitlines()
        return sorted(
            (
                {
                    k: v
                    for k, v in json.loads(line).items()
                    if k not in ("trial_seconds", "worker")
                }
                for line in lines
            ),
            key=lambda r: r["trial"],
        )

    assert len(rows("local.jsonl")) == 2
    assert rows("local.jsonl") == rows("ray.jsonl")
    assert local["results"] == remote["results"]


def test_occlusion_hides_the_asked_fraction_of_the_fabric():
    from fabric_imitation.tools.bench import Occlude

    rng = np.random.default_rng(0)
    mask = np.zeros((160, 160), np.uint8)
    mask[40:120, 30:130] = 1
    for kind in ("grippers", "side"):
        for fraction in (0.0, 0.2, 0.5):
            hidden = Occlude(mask, fraction, kind, rng)
            lost = 1 - hidden.sum() / mask.sum()
            assert fraction - 0.01 <= lost < fraction + 0.08, (kind, fraction, lost)
            assert not np.any(hidden & (mask == 0))


def _fake_episodes(monkeypatch, steps: int = 20) -> list[dict]:
    """Replaces each episode with a fixed row of `steps` steps and learning
    from the demo with nothing; returns the list that each episode's keyword
    arguments are appended to."""
    import fabric_imitation.tools.episode as episode
    import fabric_imitation.tools.evaluate as evaluate

    calls: list[dict] = []

    def imitate(**kwargs):
        calls.append(kwargs)
        row = _row(0, True, 0, steps, 0.9)
        row["chamfer_over_steps"] = [0.2, 0.1]
        return {k: v for k, v in row.items() if k not in ("trial", "trial_seconds")}

    monkeypatch.setattr(episode, "Imitate", imitate)
    monkeypatch.setattr(evaluate, "_prepare", lambda job: object())
    return calls


def test_a_sampling_seed_is_another_run_of_the_same_poses(tmp_path, monkeypatch):
    """--sampling-seed K reseeds every trial's controller (trial i: i + 1000
    K) at the same poses; rows of one sampling seed are never resumed as
    another's."""
    import json

    import fabric_imitation.tools.evaluate as evaluate

    calls = _fake_episodes(monkeypatch)
    out = tmp_path / "eval.jsonl"
    common = dict(
        scenario_names=["box"],
        methods=["ours"],
        trials=2,
        out=out,
        progress=False,
        worker_trials=0,
    )
    first = evaluate.Evaluate(**common)
    again = evaluate.Evaluate(**common, sampling_seed=3)
    assert [c["seed"] for c in calls] == [0, 1, 3000, 3001]
    assert first["poses"] == again["poses"] and again["sampling_seed"] == 3
    evaluate.Evaluate(**common, sampling_seed=3)  # resumed: nothing to run
    assert len(calls) == 4
    rows = [json.loads(line) for line in out.read_text().splitlines()]
    assert sorted((r["sampling_seed"], r["trial"]) for r in rows) == [
        (0, 0),
        (0, 1),
        (3, 0),
        (3, 1),
    ]
    assert "sampling seed 3" in (tmp_path / "eval.jsonl.md").read_text()


def test_the_no_mpc_ablation_applies_f_i_whatever_the_policys_prior():
    # The paper's No MPC applies f_I's action; the shipped prior is the
    # grasped corners', so the ablation must name f_I itself.
    assert MpcConfig().prior == "grasp"
    _, changes = METHODS["no_mpc"]
    assert changes["prior"] == "inverse" and not changes["use_mpc"]
    _, ours = METHODS["ours"]
    assert "prior" not in ours


def test_watch_runs_a_trial_again_as_evaluate_ran_it(tmp_path, monkeypatch):
    """`watch` gives the controller the trial line's object pose, cloth start
    and sampling seed, passes the recording and video on, and says whether
    the run took the row's course."""
    import fabric_imitation.tools.evaluate as evaluate

    calls = _fake_episodes(monkeypatch)
    out = tmp_path / "eval.jsonl"
    evaluate.Evaluate(
        scenario_names=["box"],
        methods=["ours"],
        trials=2,
        out=out,
        progress=False,
        worker_trials=0,
        sampling_seed=3,
    )
    ran = calls[1] if calls[1]["seed"] == 3001 else calls[0]
    record, video = tmp_path / "t1.html", tmp_path / "t1.mp4"
    watched = evaluate.WatchTrial(
        runs=out, scenario="box", trial=1, record=record, video=video, progress=False
    )
    again = calls[-1]
    assert again["seed"] == 3001
    assert list(again["scenario"].object.pose) == list(ran["scenario"].object.pose)
    assert list(again["scenario"].cloth.pose) == list(ran["scenario"].cloth.pose)
    assert again["record"] == record and again["video"] == video
    assert watched["same_course"] and watched["differs"] == []
    assert watched["row"] == {"steps": 20, "termination": "classifier", "success": True}
    _fake_episodes(monkeypatch, steps=21)  # another course
    assert not evaluate.WatchTrial(runs=out, scenario="box", trial=1, progress=False)[
        "same_course"
    ]


def test_watch_refuses_what_it_cannot_run(tmp_path):
    import json

    from fabric_imitation.learning.errors import InputError
    from fabric_imitation.tools.evaluate import WatchTrial

    out = tmp_path / "eval.jsonl"
    rows = [
        {"scenario": "box", "method": m, "trial": t, "pose_seed": 0}
        for m in ("ours", "scripted")
        for t in (0, 1)
    ] + [{"scenario": "cylinder", "method": "ours", "trial": 0, "demo": "/no/demo"}]
    out.write_text("".join(json.dumps(r) + "\n" for r in rows) + '{"scen')
    for kwargs, message in [
        (dict(runs=tmp_path / "none.jsonl", scenario="box", trial=0), "no evaluate"),
        (
            dict(runs=out, scenario="hang", trial=0),
            "no 'hang' trials; it has box, cylinder",
        ),
        (dict(runs=out, scenario="cylinder", trial=0), "give its place with --demo"),
        (dict(runs=out, scenario="box", trial=5), "its trials: 0-1"),
        (dict(runs=out, scenario="box", trial=0), "pick one with --method"),
        (dict(runs=out, scenario="box", trial=0, method="scripted"), "scripted"),
    ]:
        with pytest.raises(InputError, match=message):
            WatchTrial(progress=False, **kwargs)


@pytest.mark.slow
def test_a_watched_trial_takes_the_course_evaluate_recorded(tmp_path):
    """`watch` runs a real trial again step for step on the machine that ran
    it: the same Chamfer curve, steps and termination, nothing differing."""
    from conftest import SmallCloth
    from fabric_imitation.tools.evaluate import Evaluate, WatchTrial

    out = tmp_path / "eval.jsonl"
    Evaluate(
        scenario_names=["box"],
        methods=["ours"],
        trials=2,
        seed=3,
        sampling_seed=1,
        scenario_text=SmallCloth("vbd"),
        out=out,
        progress=False,
        worker_trials=0,
    )
    watched = WatchTrial(
        runs=out,
        scenario="box",
        trial=1,
        video=tmp_path / "t1.mp4",
        progress=False,
    )
    assert watched["same_course"], (watched["row"], watched["steps"])
    assert watched["differs"] == []
    assert (tmp_path / "t1.mp4").stat().st_size > 0
