import subprocess
import sys

import pytest
from fabric_imitation.learning.errors import InputError
from fabric_imitation.scenarios.loader import DumpScenario, LoadScenario, ScenarioNames


@pytest.mark.parametrize("name", ScenarioNames())
def test_every_scenario_loads_and_round_trips(name):
    scenario = LoadScenario(scenario_name=name)
    text = DumpScenario(scenario)
    again = LoadScenario(scenario_text=text)
    assert DumpScenario(again) == text
    assert scenario.random_seed == again.random_seed


def test_named_scenarios_match_the_design():
    assert {"prior", "box", "hang", "box_big"} <= set(ScenarioNames())
    box = LoadScenario(scenario_name="box")
    assert box.object.kind == "box" and box.object.size == [0.14, 0.09, 0.06]
    hang = LoadScenario(scenario_name="hang")
    assert hang.object.kind == "plate" and hang.object.size == [0.17, 0.01, 0.20]
    big = LoadScenario(scenario_name="box_big")
    assert big.object.size == [0.30, 0.15, 0.05]
    assert sorted(big.cloth.size) == [0.30, 0.40]
    assert LoadScenario(scenario_name="prior").object.kind == "none"


def test_no_named_scenario_sets_the_method():
    """Every scenario runs the one policy: the method's fields of each named
    scenario are the shipped policy's."""
    from fabric_imitation.learning.policy import POLICY_FIELDS
    from fabric_imitation.scenarios.policy import LoadPolicy

    policy = LoadPolicy()
    for name in ScenarioNames():
        scenario = LoadScenario(scenario_name=name)
        for field in POLICY_FIELDS:
            assert getattr(scenario, field) == getattr(policy, field), (name, field)


def test_inline_overrides_merge_into_nested_fields():
    s = LoadScenario(
        scenario_name="box",
        scenario_text="cloth: {youngs_modulus: 2.0e4}\nrandom_seed: 7",
    )
    assert s.cloth.youngs_modulus == 2.0e4
    assert s.cloth.size == [0.30, 0.30]  # untouched sibling field
    assert s.random_seed == 7
    assert s.object.kind == "box"


@pytest.mark.parametrize(
    "kwargs, message",
    [
        (dict(scenario_name="boxx"), "unknown scenario 'boxx'"),
        (dict(scenario_name="box", scenario_text="cloth: {frction: 1.0}"), "frction"),
        (
            dict(scenario_name="box", scenario_text="object: {pose: [0.7, 0.0, 0.0]}"),
            "outside the workspace",
        ),
        (
            dict(scenario_name="box", scenario_text="cloth: {size: [1.2, 0.3]}"),
            "does not fit on the",
        ),
        (
            dict(scenario_name="box", scenario_text="object: {pose: [0.0, 0.2, 0.0]}"),
            "overlaps the cloth",
        ),
        (
            dict(scenario_name="box", scenario_text="cloth: {poissons_ratio: 0.7}"),
            "cloth.poissons_ratio",
        ),
        (
            dict(scenario_name="box", scenario_text="mpc: {max_iterations: 8}"),
            "--scenario-text sets mpc: the method's settings belong in the policy",
        ),
        (
            dict(scenario_name="hang", scenario_text="{reward: {w_p: 1}, safety: {}}"),
            "sets safety, reward",
        ),
    ],
)
def test_bad_scenarios_raise_one_line_errors(kwargs, message):
    with pytest.raises(InputError) as info:
        LoadScenario(**kwargs)
    assert message in str(info.value)
    assert "\n" not in str(info.value)


def test_cli_reports_bad_input_in_one_line_with_nonzero_exit(tmp_path):
    out = tmp_path / "demo"
    result = subprocess.run(
        [
            sys.executable,
            "-m",
            "fabric_imitation.tools.cli",
            "demo",
            "record",
            "--scenario",
            "nope",
            "--out",
            str(out),
        ],
        capture_output=True,
        text=True,
        timeout=120,
    )
    assert result.returncode == 2
    assert result.stderr.strip().count("\n") == 0
    assert "unknown scenario 'nope'" in result.stderr
    assert not out.exists()


def test_evaluate_scenario_text_applies_to_every_trial_pose():
    from fabric_imitation.tools.evaluate import TrialPoses, TrialScenario

    text = "cloth: {engine: fem}\nobject: {friction: 0.8}"
    poses = TrialPoses("box", trials=3, seed=1, scenario_text=text)
    assert poses == TrialPoses("box", trials=3, seed=1)  # same seeded poses
    s = TrialScenario("box", text, poses[0])
    assert s.cloth.engine == "fem" and s.object.friction == 0.8
    assert s.object.pose == poses[0] and s.object.kind == "box"
    assert TrialScenario("box", "", None).cloth.engine == "vbd"
    with pytest.raises(InputError, match="not a YAML mapping"):
        TrialScenario("box", "- 1", None)


def test_protocols_draw_poses_in_their_bands():
    import math

    from fabric_imitation.tools.evaluate import PROTOCOLS, ProtocolPoses

    base = LoadScenario(scenario_name="hang").object.pose
    lists = {}
    for protocol, (shift, turn) in PROTOCOLS.items():
        poses = ProtocolPoses("hang", protocol, trials=12, seed=3)
        assert poses == ProtocolPoses("hang", protocol, trials=12, seed=3)
        for x, y, yaw in poses:
            assert math.hypot(x - base[0], y - base[1]) <= shift + 1e-6
            assert abs(yaw - base[2]) <= turn + 1e-6
        lists[protocol] = poses
    assert all(p[2] == base[2] for p in lists["translation"])
    assert max(abs(p[2] - base[2]) for p in lists["wide"]) > 45
