"""The method's settings, kept apart from the scene: the controller's safety
rules, the MPC, the demo reward and the keypoint tracker.

A scenario describes a scene and its task; a policy describes how the
method imitates in any of them. One policy serves every task: what must
differ between tasks is computed from the demo (`SafetyConfig.
tau_d_from_demo`). The policy is kept as `policy.yaml` beside the priors it
was chosen with and names their checksum, so a policy is never run with
priors it was not measured on (scenarios/policy.py loads it).
"""

import dataclasses as dc

from fabric_imitation.learning.demo_learning import RewardConfig
from fabric_imitation.learning.mpc import MpcConfig
from fabric_imitation.learning.safety import SafetyConfig
from fabric_imitation.learning.tracker import TrackerConfig

# The policy file's name in a priors directory.
POLICY_FILE = "policy.yaml"


@dc.dataclass
class Policy:
    # sha256 of the priors' tensors file this policy goes with (the
    # "tensors.sha256" of the priors' priors.json).
    priors_sha256: str = ""
    # The controller's rules of the safe action set (paper Sec. IV-B).
    safety: SafetyConfig = dc.field(default_factory=SafetyConfig)
    # The sampling MPC (Algorithm 1; the defaults are N = 500, h = 5).
    mpc: MpcConfig = dc.field(default_factory=MpcConfig)
    # The demo reward R_E and its registration network f_A (Sec. IV-C).
    reward: RewardConfig = dc.field(default_factory=RewardConfig)
    # The keypoint tracker (learning/tracker.py).
    tracker: TrackerConfig = dc.field(default_factory=TrackerConfig)

    def __post_init__(self):
        for sub in (self.safety, self.mpc, self.reward, self.tracker):
            sub.__post_init__()


# The Policy's parts, which a scenario may not set.
POLICY_FIELDS = tuple(f.name for f in dc.fields(Policy) if f.name != "priors_sha256")
