"""The Zero, CFM and TCN baselines (learning/baselines.py): training on a
small synthetic prior dataset, checkpoints, and each one's run-time rule."""

import hashlib
import json
import subprocess
import types

import numpy as np
import pytest
import torch
from fabric_imitation.learning.baselines import (
    BaselineTrainConfig,
    CfmPlanner,
    TcnMpc,
    ZeroFollower,
    load_baselines,
    train_baselines,
)
from fabric_imitation.learning.demo_learning import DemoModel, RewardConfig
from fabric_imitation.learning.errors import InputError
from fabric_imitation.learning.mpc import MpcConfig
from fabric_imitation.learning.safety import SafetyConfig, SafetyContext, valid_actions

M = 8


def square(centre, yaw=0.0, size=0.3):
    """8 boundary keypoints of a flat square cloth, counter-clockwise from the
    left grasped corner s1 (index 0), s2 at index 2."""
    h = size / 2
    local = np.array(
        [[-h, -h], [0, -h], [h, -h], [h, 0], [h, h], [0, h], [-h, h], [-h, 0]]
    )
    c, s = np.cos(yaw), np.sin(yaw)
    p = local @ np.array([[c, s], [-s, c]]) + centre
    return np.c_[p, np.zeros(M)]


def synthetic_dataset(episodes=60, length=10, seed=0):
    """A cloth that slides with the mean of its grippers' moves, lifted
    corners rising with theirs: enough structure for every baseline."""
    rng = np.random.default_rng(seed)
    S, Sn, A, ep, st = [], [], [], [], []
    for e in range(episodes):
        s = square(rng.uniform(-0.1, 0.1, 2), rng.uniform(-np.pi, np.pi))
        for k in range(length):
            a = rng.uniform(-0.03, 0.03, 6)
            a[[2, 5]] = np.abs(a[[2, 5]]) * (s[[0, 2], 2] < 0.2)
            nxt = s.copy()
            nxt[:, :2] += (a[:2] + a[3:5]) / 2
            nxt[0] += [0, 0, a[2]]
            nxt[2] += [0, 0, a[5]]
            S.append(s), Sn.append(nxt), A.append(a), ep.append(e), st.append(k)
            s = nxt
    arrays = {
        "keypoints": np.array(S, np.float32),
        "keypoints_next": np.array(Sn, np.float32),
        "action": np.array(A, np.float32),
        "episode": np.array(ep),
        "step": np.array(st),
    }
    return types.SimpleNamespace(arrays=arrays, fingerprint="synthetic")


@pytest.fixture(scope="module")
def trained():
    cfg = BaselineTrainConfig(epochs=15, tcn_demo_steps=20)
    return train_baselines(synthetic_dataset(), cfg=cfg, log=lambda _: None), cfg


def test_zero_inverse_model_recovers_the_move(trained):
    b, _ = trained
    s = square([0.05, -0.02], 0.7)
    move = np.array([0.02, -0.01, 0.0])
    g = s.copy()
    g[:, :2] += move[:2]
    a = b.zero_action(torch.tensor(s), torch.tensor(g)).numpy()
    # The cloth moves with the mean of the two grippers' moves.
    mean_move = (a[:3] + a[3:]) / 2
    assert np.abs(mean_move[:2] - move[:2]).max() < 0.006, a


def test_cfm_and_tcn_learn_their_contrasts(trained):
    b, _ = trained
    assert b.metrics["cfm_top1"] > 0.5
    assert b.metrics["tcn_near_before_far"] > 0.8


def test_checkpoint_round_trip_gives_the_trained_networks(trained, tmp_path):
    b, _ = trained
    b.save(tmp_path)
    loaded = load_baselines(tmp_path, num_keypoints=M)
    s = torch.tensor(square([0.0, 0.1], 0.3), dtype=torch.float32)
    g = s + torch.tensor([0.01, 0.0, 0.0])
    A = torch.rand(5, 6) * 0.06 - 0.03
    assert torch.equal(b.zero_action(s, g), loaded.zero_action(s, g))
    assert torch.equal(b.cfm_predict(s, A), loaded.cfm_predict(s, A))
    assert torch.equal(b.tcn_embed(g[None], s), loaded.tcn_embed(g[None], s))
    with pytest.raises(InputError, match="use 8 keypoints, the scenario uses 6"):
        load_baselines(tmp_path, num_keypoints=6)


class _RunsCode:
    def __init__(self, path):
        self.path = str(path)

    def __reduce__(self):
        return (subprocess.call, (["touch", self.path],))


def test_a_baselines_file_that_would_run_code_is_refused(trained, tmp_path):
    b, _ = trained
    b.save(tmp_path)
    witness = tmp_path / "code-ran"
    tensors = torch.load(tmp_path / "baselines.pt", weights_only=True)
    tensors["payload"] = _RunsCode(witness)
    torch.save(tensors, tmp_path / "baselines.pt")
    description = json.loads((tmp_path / "baselines.json").read_text())
    description["tensors"]["sha256"] = hashlib.sha256(
        (tmp_path / "baselines.pt").read_bytes()
    ).hexdigest()
    (tmp_path / "baselines.json").write_text(json.dumps(description))
    with pytest.raises(InputError, match="need pickle"):
        load_baselines(tmp_path)
    assert not witness.exists()
    (tmp_path / "baselines.json").write_text("{not json")
    with pytest.raises(InputError, match="corrupt"):
        load_baselines(tmp_path)
    with pytest.raises(InputError, match="baselines checkpoint not found"):
        load_baselines(tmp_path / "missing")


class _TowardsGoal:
    """A stand-in inverse model: each gripper straight to its corner's goal."""

    def zero_action(self, S, G):
        return torch.cat([G[0] - S[0], G[2] - S[2]])


def test_zero_steps_through_the_demo_states_as_subgoals():
    demo = np.stack([square([0.0, 0.1 - 0.02 * k]) for k in range(4)])
    follower = ZeroFollower(_TowardsGoal(), demo, max_step=0.03, reach=0.005)
    S = torch.tensor(demo[0], dtype=torch.float32)
    a, j, tries = follower.decide(S, 0, 0)
    assert j == 1 and tries == 1
    np.testing.assert_allclose(a.numpy(), [0, -0.02, 0, 0, -0.02, 0], atol=1e-6)
    # At subgoal 1: it heads for 2.
    a, j, tries = follower.decide(torch.tensor(demo[1], dtype=torch.float32), j, tries)
    assert j == 2 and tries == 1
    # Not reached after `patience` tries: the next subgoal anyway.
    _, j, tries = follower.decide(S, 2, 3)
    assert j == 3 and tries == 1
    # At the last state: done.
    a, j, _ = follower.decide(torch.tensor(demo[3], dtype=torch.float32), 3, 1)
    assert a is None and j == 3


def _rules():
    safety = SafetyConfig()
    ctx = SafetyContext(
        edge_length=0.3,
        workspace_lower=np.array([-0.5, -0.5, -0.01]),
        workspace_upper=np.array([0.5, 0.5, 0.5]),
    )
    return safety, ctx


def test_cfm_picks_a_valid_action_towards_the_next_demo_state(trained):
    b, _ = trained
    safety, ctx = _rules()
    demo = np.stack([square([0.0, 0.1 - 0.02 * k]) for k in range(5)])
    planner = CfmPlanner(b, demo, safety=safety, safety_ctx=ctx, num_samples=300)
    S = torch.tensor(demo[0], dtype=torch.float32)
    a, J, valid = planner.decide(S, 0, [0.0, 0.0, 0.0], seed=1)
    assert J == 0 and valid > 0
    assert bool(valid_actions(S, a, safety, ctx))
    # Towards the demo's next state: the grippers' mean move points along -y.
    assert (a[1] + a[4]) / 2 < 0, a
    # At the demo's last state the episode ends.
    a, J, _ = planner.decide(
        torch.tensor(demo[-1], dtype=torch.float32), 4, [0, 0, 0], 1
    )
    assert a is None and J == 4


def test_tcn_reward_is_aligned_in_time_and_ends_after_the_demo(trained):
    b, cfg = trained
    safety, ctx = _rules()
    demo = np.stack([square([0.0, 0.1 - 0.03 * k]) for k in range(6)])
    b_demo, _ = b.tcn_on_demo(demo, cfg)
    model = DemoModel(demo, registration=None, config=RewardConfig())
    mpc = TcnMpc(
        baselines=b_demo,
        dynamics=None,
        demo=model,
        safety=safety,
        safety_ctx=ctx,
        config=MpcConfig(horizon=2),
    )
    S = torch.tensor(demo[2], dtype=torch.float32)
    assert mpc.current_progress(S, 2, None) == 2
    # Rollout step i is compared with demo state step + i + 1.
    assert torch.equal(mpc._aligned(0), model.states[3])
    assert torch.equal(mpc._aligned(5), model.states[5])  # after the end: the last
    assert not mpc.finished(torch.tensor(demo[-1], dtype=torch.float32), 2)
    assert mpc.finished(torch.tensor(demo[-1], dtype=torch.float32), 5)


@pytest.mark.slow
@pytest.mark.parametrize("controller", ["zero", "cfm", "tcn"])
def test_each_shipped_baseline_acts_in_a_short_episode(controller):
    """The shipped networks drive the station for a few steps on box (a
    coarse cloth, a step cap of 7) and the episode is scored."""
    from fabric_imitation.diagrams.imitation import (
        DefaultDemoDir,
        MakeImitationDiagram,
        PrepareImitation,
        RunEpisode,
        ScoreEpisode,
    )
    from fabric_imitation.scenarios.loader import LoadScenario

    scenario = LoadScenario(
        scenario_name="box",
        scenario_text="{cloth: {vbd: {resolution: [8, 8]}}, "
        "mpc: {step_cap_factor: 0.1, num_samples: 100, max_iterations: 1}}",
    )
    prepared = PrepareImitation(
        scenario, demo_dir=DefaultDemoDir("box", scenario), baselines=True
    )
    imitation = MakeImitationDiagram(scenario, prepared, controller=controller)
    run = RunEpisode(imitation, settle_seconds=0.2)
    summary = ScoreEpisode(scenario, prepared, run)
    assert run.error is None
    assert 1 <= summary["steps"] <= 7, summary
    assert np.abs(run.logs["action"]).max() > 0.005
    assert summary["termination"] in ("step cap", "classifier")
    assert len(summary["chamfer_over_steps"]) == summary["steps"] + 1
