"""The policy: the method's settings, apart from the scene, kept with the
priors and checked against them."""

import dataclasses as dc
import json
import shutil

import pytest
from fabric_imitation.learning.errors import InputError
from fabric_imitation.learning.policy import POLICY_FIELDS, POLICY_FILE, Policy
from fabric_imitation.learning.priors import DEFAULT_PRIORS
from fabric_imitation.scenarios.loader import LoadScenario
from fabric_imitation.scenarios.policy import (
    DumpPolicy,
    LoadPolicy,
    PriorsSha256,
    WritePolicy,
)


def test_shipped_policy_is_for_the_shipped_priors_and_round_trips(tmp_path):
    policy = LoadPolicy()
    assert policy.priors_sha256 == PriorsSha256(DEFAULT_PRIORS)
    assert len(policy.priors_sha256) == 64
    # Every field is written out, and read back the same.
    text = DumpPolicy(policy)
    for field in POLICY_FIELDS:
        assert f"\n{field}:\n" in f"\n{text}"
    shutil.copy(DEFAULT_PRIORS / "priors.json", tmp_path / "priors.json")
    path = WritePolicy(policy, tmp_path)
    assert path == tmp_path / POLICY_FILE and not list(tmp_path.glob("*.tmp"))
    assert LoadPolicy(priors_dir=tmp_path) == policy
    assert DumpPolicy(LoadPolicy(priors_dir=tmp_path)) == text


def test_policy_text_overrides_nested_fields():
    policy = LoadPolicy(policy_text="mpc: {max_iterations: 8}\nsafety: {tau_c: 0.4}")
    assert policy.mpc.max_iterations == 8 and policy.safety.tau_c == 0.4
    assert policy.mpc.num_samples == LoadPolicy().mpc.num_samples  # untouched
    scenario = LoadScenario(scenario_name="hang", policy=policy)
    assert scenario.mpc.max_iterations == 8 and scenario.object.kind == "plate"


@pytest.mark.parametrize(
    "text, message",
    [
        ("mpc: {max_iterations: 0}", "mpc.max_iterations"),
        ("mpc: {tau_conv: 0}", "mpc.tau_conv"),
        ("mpc: {elites: 501}", "mpc.elites"),
        ("mpc: {execute: mean}", "execute"),
        ("reward: {w_p: -1.0}", "reward.w_p must be non-negative"),
        ("safety: {tau_d_demo_margin_deg: -1}", "safety.tau_d_demo_margin_deg"),
        ("safety: {tau_dd: 1}", "tau_dd"),
        ("cloth: {size: [1, 1]}", "cloth"),
    ],
)
def test_bad_policies_raise_one_line_errors(text, message):
    with pytest.raises(InputError) as info:
        LoadPolicy(policy_text=text)
    assert message in str(info.value)
    assert "\n" not in str(info.value)


def test_policy_for_other_priors_is_refused(tmp_path):
    priors = tmp_path / "priors"
    priors.mkdir()
    shutil.copy(DEFAULT_PRIORS / "priors.json", priors / "priors.json")
    other = dc.replace(LoadPolicy(), priors_sha256="0" * 64)
    WritePolicy(other, priors)
    with pytest.raises(InputError, match="was chosen for priors 000000000000"):
        LoadPolicy(priors_dir=priors)
    # Priors with no policy beside them, and the shipped policy given for
    # other priors.
    (priors / POLICY_FILE).unlink()
    with pytest.raises(InputError, match="policy file not found"):
        LoadPolicy(priors_dir=priors)
    description = json.loads((priors / "priors.json").read_text())
    description["tensors"]["sha256"] = "f" * 64
    (priors / "priors.json").write_text(json.dumps(description))
    with pytest.raises(InputError, match="the priors .* are ffffffffffff"):
        LoadPolicy(priors_dir=priors, filename=DEFAULT_PRIORS / POLICY_FILE)


def test_a_scenario_file_that_sets_a_policy_field_is_refused(tmp_path):
    file = tmp_path / "scenes.yaml"
    file.write_text(
        "base: &Base\n  task: box\n  object: {kind: box}\n"
        "  safety: {tau_d_deg: 120.0}\nmine:\n  <<: *Base\n"
    )
    for name in ("base", "mine"):  # also through a YAML anchor
        with pytest.raises(InputError) as info:
            LoadScenario(scenario_name=name, filename=file)
        assert str(info.value) == (
            f"scenario {name!r} sets safety: the method's settings belong in the "
            "policy file beside the priors (learning/priors/default/policy.yaml), "
            "or in --policy / --policy-text"
        )


def test_policy_holds_exactly_the_method_settings():
    assert POLICY_FIELDS == ("safety", "mpc", "reward", "tracker")
    assert [f.name for f in dc.fields(Policy)] == ["priors_sha256", *POLICY_FIELDS]
