"""Loads the method's policy (learning/policy.py): the `policy.yaml` kept
with the priors, or another file, with inline YAML overrides on top, as a
scenario is loaded (file -> inline text)."""

import json
from pathlib import Path

from fabric_imitation.learning.errors import InputError
from fabric_imitation.learning.policy import POLICY_FILE, Policy
from fabric_imitation.learning.priors import CHECKPOINT_JSON, DEFAULT_PRIORS
from pydrake.common.yaml import yaml_dump_typed, yaml_load_typed


def PriorsSha256(priors_dir: Path | str) -> str:
    """The checksum of a priors directory's tensors file, as its
    priors.json records it (load_priors checks the file against it)."""
    file = Path(priors_dir) / CHECKPOINT_JSON
    try:
        return str(json.loads(file.read_text())["tensors"]["sha256"])
    except FileNotFoundError:
        raise InputError(f"priors checkpoint not found: {file}") from None
    except (ValueError, KeyError, TypeError):
        raise InputError(f"priors {file} are corrupt: no tensors checksum") from None


def LoadPolicy(
    *,
    priors_dir: Path | str | None = None,
    filename: Path | str | None = None,
    policy_text: str = "",
    check_priors: bool = True,
) -> Policy:
    """The policy of `filename` (default: `policy.yaml` in `priors_dir`,
    default the shipped priors), with the YAML mapping `policy_text` merged
    on top. `check_priors=False` skips the checksum test (for a policy
    about to be written for new priors).

    Raises:
        InputError: a missing file, an unknown field, a bad value, or a
            policy whose priors checksum is not that of `priors_dir`.
    """
    priors_dir = Path(priors_dir) if priors_dir else DEFAULT_PRIORS
    filename = Path(filename) if filename else priors_dir / POLICY_FILE
    if not filename.is_file():
        raise InputError(
            f"policy file not found: {filename} (`fabric-imitate train` writes "
            "one beside the priors)"
        )
    policy = _load(filename=str(filename), where=f"policy {filename}")
    if policy_text.strip():
        policy = _load(data=policy_text, defaults=policy, where="--policy-text")
    expected = PriorsSha256(priors_dir) if check_priors else policy.priors_sha256
    if policy.priors_sha256 != expected:
        raise InputError(
            f"policy {filename} was chosen for priors {policy.priors_sha256[:12]!s}, "
            f"the priors {priors_dir} are {expected[:12]}"
        )
    return policy


def _load(*, where: str, **kwargs) -> Policy:
    try:
        policy = yaml_load_typed(schema=Policy, **kwargs)
        policy.__post_init__()
    except (RuntimeError, ValueError, TypeError) as e:
        raise InputError(f"{where}: {' '.join(str(e).split())}") from None
    return policy


def DumpPolicy(policy: Policy) -> str:
    """The policy as YAML that LoadPolicy reads back."""
    return yaml_dump_typed(policy, schema=Policy)


def WritePolicy(policy: Policy, priors_dir: Path | str) -> Path:
    """Writes `policy` as the policy file of `priors_dir` (whole, through a
    temporary file)."""
    path = Path(priors_dir) / POLICY_FILE
    tmp = path.with_suffix(".yaml.tmp")
    tmp.write_text(
        "# The method's settings for the priors beside this file "
        "(learning/policy.py;\n# each field's meaning is in its config "
        "class: SafetyConfig, MpcConfig,\n# RewardConfig, TrackerConfig).\n"
        + DumpPolicy(policy)
    )
    tmp.replace(path)
    return path
