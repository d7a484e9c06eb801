"""Loads a Scenario: file -> named entry -> inline overrides (as Drake's
hardware_sim does)."""

import copy
from pathlib import Path

from fabric_imitation.learning.errors import InputError
from fabric_imitation.learning.policy import POLICY_FIELDS, Policy
from fabric_imitation.scenarios.policy import LoadPolicy
from fabric_imitation.scenarios.schema import Scenario
from pydrake.common.yaml import yaml_dump_typed, yaml_load_typed

DEFAULT_SCENARIOS_FILE = Path(__file__).with_name("scenarios.yaml")


def ScenarioNames(filename: Path | str = DEFAULT_SCENARIOS_FILE) -> list[str]:
    """The named entries of a scenarios file, in file order."""
    import yaml

    with open(filename) as f:
        return list(yaml.safe_load(f).keys())


def LoadScenario(
    *,
    scenario_name: str | None = None,
    filename: Path | str | None = None,
    scenario_text: str = "",
    policy: Policy | None = None,
) -> Scenario:
    """Returns the named scenario of `filename` (default: the built-in file),
    with the YAML mapping `scenario_text` merged on top, and the method's
    settings of `policy` (default: the shipped priors' policy) in its
    policy fields (`POLICY_FIELDS`), which a scenario may not set.

    Raises:
        InputError: unknown file or name, a misspelled field, a bad value, a
            policy field in the scenario.
    """
    filename = Path(filename) if filename is not None else DEFAULT_SCENARIOS_FILE
    scenario = Scenario()
    if scenario_name is not None:
        if not filename.is_file():
            raise InputError(f"scenario file not found: {filename}")
        names = ScenarioNames(filename)
        if scenario_name not in names:
            raise InputError(
                f"unknown scenario {scenario_name!r}; known: {', '.join(names)}"
            )
        where = f"scenario {scenario_name!r}"
        _RefusePolicyFields(_EntryData(filename, scenario_name), where)
        scenario = _load(
            filename=str(filename),
            child_name=scenario_name,
            defaults=scenario,
            where=where,
        )
    if scenario_text.strip():
        _RefusePolicyFields(_TextData(scenario_text), "--scenario-text")
        scenario = _load(data=scenario_text, defaults=scenario, where="--scenario-text")
    policy = policy or LoadPolicy()
    for field in POLICY_FIELDS:
        setattr(scenario, field, copy.deepcopy(getattr(policy, field)))
    scenario.validate()
    return scenario


def _EntryData(filename: Path, name: str):
    import yaml

    with open(filename) as f:
        return yaml.safe_load(f).get(name)


def _TextData(text: str):
    import yaml

    try:
        return yaml.safe_load(text)
    except yaml.YAMLError:
        return None  # yaml_load_typed names the syntax error


def _RefusePolicyFields(data, where: str) -> None:
    """A scene may not set the method's settings (learning/policy.py)."""
    fields = [k for k in POLICY_FIELDS if isinstance(data, dict) and k in data]
    if fields:
        raise InputError(
            f"{where} sets {', '.join(fields)}: the method's settings belong in "
            "the policy file beside the priors (learning/priors/default/"
            "policy.yaml), or in --policy / --policy-text"
        )


def _load(*, where: str, **kwargs) -> Scenario:
    try:
        return yaml_load_typed(schema=Scenario, **kwargs)
    except (RuntimeError, ValueError, TypeError) as e:
        message = " ".join(str(e).split())
        field = _BadField(kwargs.get("defaults"), kwargs.get("data"))
        if field:
            message = f"{field}: {message}"
        raise InputError(f"{where}: {message}") from None


def _BadField(defaults, text: str | None) -> str | None:
    """The dotted name of the first value in the YAML `text` whose type does
    not match the default it replaces (a number where a list is, a word
    where a number is), for errors that name no field."""
    import yaml

    try:
        data = yaml.safe_load(text) if text else None
    except yaml.YAMLError:
        return None

    def walk(obj, value, path):
        if isinstance(value, dict):
            for key, item in value.items():
                if not hasattr(obj, str(key)):
                    return None
                found = walk(getattr(obj, str(key)), item, f"{path}{key}.")
                if found:
                    return found
            return None
        name = path[:-1]
        if isinstance(obj, bool):
            return None if isinstance(value, bool) else name
        if isinstance(obj, int | float):
            ok = isinstance(value, int | float) and not isinstance(value, bool)
            return None if ok else name
        if isinstance(obj, str):
            return None if isinstance(value, str) else name
        if isinstance(obj, list):
            return None if isinstance(value, list) else name
        return None

    return walk(defaults, data, "") if isinstance(data, dict) else None


def DumpScenario(scenario: Scenario) -> str:
    """The scene of `scenario` (its policy fields left out) as YAML that
    LoadScenario(scenario_text=...) reads back."""
    kept, skip = [], False
    for line in yaml_dump_typed(scenario).splitlines(keepends=True):
        if not line[:1].isspace():  # a top-level field
            skip = line.split(":")[0] in POLICY_FIELDS
        if not skip:
            kept.append(line)
    return "".join(kept)
