"""The Zero, CFM and TCN baselines (learning/baselines.py,
learning/baseline_policies.py): training on a small synthetic prior dataset,
checkpoints, the driver's limits, each one's run-time rule, and their
independence from the paper's contribution (safe set, action prior)."""

import hashlib
import json
import math
import subprocess
import types

import numpy as np
import pytest
import torch
from fabric_imitation.learning import baseline_policies, mpc, safety
from fabric_imitation.learning.baseline_policies import (
    CfmPlanner,
    TcnConfig,
    TcnMpc,
    TcnPlanner,
    ZeroConfig,
    ZeroFollower,
    aligned_frame,
)
from fabric_imitation.learning.baselines import (
    BaselineTrainConfig,
    load_baselines,
    train_baselines,
)
from fabric_imitation.learning.demo_learning import DemoModel, RewardConfig
from fabric_imitation.learning.errors import InputError
from fabric_imitation.learning.limits import DriverLimits, limit_actions
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


def test_goal_recognizer_learns_when_a_goal_is_reached(trained):
    b, cfg = trained
    curves = b.metrics["curves"]
    loss = [row[curves["columns"].index("recognizer")] for row in curves["per_epoch"]]
    assert loss[-1] < 0.8 * loss[0], loss
    assert b.metrics["zero_recognizer_accuracy"] > 0.7
    # A goal one step of the synthetic cloth away is reached, six are not.
    s = square([0.0, 0.0], 0.4)
    near, far = s.copy(), s.copy()
    near[:, 1] -= 0.005
    far[:, 1] -= 0.12
    p = b.zero_reached(torch.tensor(s), torch.tensor(np.stack([s, near, far])))
    assert p.shape == (3,)
    assert p[0] > 0.5 and p[1] > 0.5 and p[2] < 0.5, p


def test_recognizer_labels_come_from_time_in_the_episode():
    from fabric_imitation.learning.baselines import _recognizer_pairs

    episode = torch.tensor([0] * 10 + [1] * 3 + [2] * 12)
    step = torch.cat([torch.arange(10), torch.arange(3), torch.arange(12)])
    cfg = BaselineTrainConfig(recognizer_positive_steps=1, recognizer_negative_steps=4)
    i, j, label = _recognizer_pairs(
        episode, step, 4000, cfg, torch.Generator().manual_seed(0)
    )
    assert (episode[i] == episode[j]).all()
    gap = (step[i] - step[j]).abs()
    assert (gap[label == 1] <= 1).all() and (gap[label == 0] >= 4).all()
    assert not (episode[i[label == 0]] == 1).any()  # 3 steps: no negative
    assert 0.45 < float(label.mean()) < 0.6


def test_checkpoint_round_trip_gives_the_trained_networks(trained, tmp_path):
    b, _ = trained
    b.save(tmp_path)
    loaded = load_baselines(tmp_path, num_keypoints=M)
    s = torch.tensor(square([0.0, 0.1], 0.3), dtype=torch.float32)
    g = s + torch.tensor([0.01, 0.0, 0.0])
    A = torch.rand(5, 6) * 0.06 - 0.03
    torch.testing.assert_close(
        b.zero_action(s, g), loaded.zero_action(s, g), rtol=0, atol=0
    )
    torch.testing.assert_close(
        b.zero_reached(s, torch.stack([s, g])),
        loaded.zero_reached(s, torch.stack([s, g])),
        rtol=0,
        atol=0,
    )
    torch.testing.assert_close(
        b.cfm_predict(s, A), loaded.cfm_predict(s, A), rtol=0, atol=0
    )
    torch.testing.assert_close(
        b.tcn_embed(g[None], s), loaded.tcn_embed(g[None], s), rtol=0, atol=0
    )
    with pytest.raises(InputError, match="use 8 keypoints, the scenario uses 6"):
        load_baselines(tmp_path, num_keypoints=6)


def test_a_checkpoint_without_the_goal_recognizer_is_refused(trained, tmp_path):
    b, _ = trained
    b.save(tmp_path)
    tensors = torch.load(tmp_path / "baselines.pt", weights_only=True)
    tensors = {k: v for k, v in tensors.items() if not k.startswith("zero_recognizer.")}
    _rewrite_tensors(tmp_path, tensors)
    with pytest.raises(InputError, match="lack the zero_recognizer network") as e:
        load_baselines(tmp_path)
    assert "\n" not in str(e.value) and "train-baselines" in str(e.value)


def _rewrite_tensors(directory, tensors) -> None:
    """Saves `tensors` as the baselines' tensors file with a matching sha256
    in baselines.json (so only what the tensors hold is under test)."""
    torch.save(tensors, directory / "baselines.pt")
    description = json.loads((directory / "baselines.json").read_text())
    description["tensors"]["sha256"] = hashlib.sha256(
        (directory / "baselines.pt").read_bytes()
    ).hexdigest()
    (directory / "baselines.json").write_text(json.dumps(description))


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
    _rewrite_tensors(tmp_path, tensors)
    with pytest.raises(InputError, match="need pickle"):
        load_baselines(tmp_path)
    assert not witness.exists()
    (tmp_path / "baselines.json").write_text("{not json")
    with pytest.raises(InputError, match="corrupt"):
        load_baselines(tmp_path)
    with pytest.raises(InputError, match="baselines checkpoint not found"):
        load_baselines(tmp_path / "missing")


def _limits(max_step=0.03):
    return DriverLimits(
        max_step=max_step,
        workspace_lower=[-0.5, -0.5, -0.01],
        workspace_upper=[0.5, 0.5, 0.5],
    )


def test_driver_limits_bound_each_axis_and_keep_targets_in_the_box():
    limits = _limits()
    g = torch.tensor([[0.0, 0.0, 0.1], [0.2, 0.0, 0.1]])
    A = torch.tensor([[0.05, -0.01, 0.0, 0.01, 0.02, -0.04]])
    np.testing.assert_allclose(
        limit_actions(g, A, limits)[0], [0.03, -0.01, 0, 0.01, 0.02, -0.03], atol=1e-7
    )
    # Near the box's +x face and the table: the targets stop at them.
    g = torch.tensor([[0.49, 0.0, 0.01], [0.0, 0.0, 0.2]])
    A = torch.tensor([0.03, 0.0, -0.03, 0.0, 0.0, 0.03])
    np.testing.assert_allclose(
        limit_actions(g, A, limits), [0.01, 0, -0.01, 0, 0, 0.03], atol=1e-6
    )
    # States in an object frame turned 90 degrees at x = 0.3: its +y is world
    # -x, so world x >= -0.5 stops a gripper at object y = 0.8.
    pose = [0.3, 0.0, math.pi / 2]
    g = torch.tensor([[0.0, 0.79, 0.1], [0.0, 0.0, 0.1]])
    A = torch.tensor([0.0, 0.03, 0.0, 0.0, 0.03, 0.0])
    np.testing.assert_allclose(
        limit_actions(g, A, limits, pose), [0, 0.01, 0, 0, 0.03, 0], atol=1e-6
    )
    # A gripper outside the box comes back at most max_step per axis.
    g = torch.tensor([[0.7, 0.0, 0.1], [0.0, 0.0, 0.1]])
    out = limit_actions(g, torch.zeros(6), limits)
    np.testing.assert_allclose(out, [-0.03, 0, 0, 0, 0, 0], atol=1e-6)
    with pytest.raises(ValueError, match="max_step"):
        _limits(0.0)


class _TowardsGoal:
    """A stand-in Zero: each gripper straight to its corner's goal; a goal is
    reached within 5 mm (mean keypoint distance)."""

    def zero_action(self, S, G):
        return torch.cat([G[0] - S[0], G[2] - S[2]])

    def zero_reached(self, S, G):
        d = (G - S).norm(dim=-1).mean(-1)
        return (d < 0.005).float()


def test_zero_moves_to_the_next_frame_when_the_recognizer_says_reached():
    demo = np.stack([square([0.0, 0.1 - 0.02 * k]) for k in range(4)])
    follower = ZeroFollower(
        _TowardsGoal(), demo, limits=_limits(), config=ZeroConfig(max_tries=3)
    )
    S = torch.tensor(demo[0], dtype=torch.float32)
    step = follower.decide(S, 0, 0)
    assert step.subgoal == 1 and step.tries == 1
    np.testing.assert_allclose(step.action, [0, -0.02, 0, 0, -0.02, 0], atol=1e-6)
    # Not reached: the same subgoal again.
    step = follower.decide(S, 1, 1)
    assert step.subgoal == 1 and step.tries == 2
    # Reached frame 1: it heads for 2 (only the subgoal is checked: a state
    # past it, at frame 2, has not reached it).
    step = follower.decide(torch.tensor(demo[1], dtype=torch.float32), 1, 2)
    assert step.subgoal == 2 and step.tries == 1
    step = follower.decide(torch.tensor(demo[2], dtype=torch.float32), 1, 2)
    assert step.subgoal == 1 and step.tries == 3
    # The cap: after max_tries on a subgoal, the next one anyway.
    step = follower.decide(S, 2, 3)
    assert step.subgoal == 3 and step.tries == 1
    # Far moves are bounded per axis.
    np.testing.assert_allclose(step.action, [0, -0.03, 0, 0, -0.03, 0], atol=1e-6)
    # The last frame reached: done by the recognizer ...
    step = follower.decide(torch.tensor(demo[3], dtype=torch.float32), 3, 1)
    assert step.action is None and step.subgoal == 3 and not step.gave_up
    # ... or the last subgoal out of tries.
    step = follower.decide(S, 3, 3)
    assert step.action is None and step.gave_up


def test_cfm_heads_for_the_demos_final_frame_in_latent_space(trained):
    b, _ = trained
    demo = np.stack([square([0.0, 0.1 - 0.02 * k]) for k in range(5)])
    planner = CfmPlanner(b, demo, limits=_limits())
    S = torch.tensor(demo[0], dtype=torch.float32)
    a, nearest = planner.decide(S, [0.0, 0.0, 0.0], seed=1)
    assert nearest == 0
    assert a.abs().max() <= 0.03 + 1e-6
    # The chosen move's predicted latent is the nearest of the samples' to
    # the final frame's (the samples as the driver executes them: the
    # grippers on the table top do not go lower).
    gen = torch.Generator().manual_seed(1)
    A = (torch.rand(planner.config.num_samples, 6, generator=gen) * 2 - 1) * 0.03
    A = limit_actions(S[[0, 2]], A, _limits(), [0.0, 0.0, 0.0])
    assert (A[:, [2, 5]] >= 0).all()
    goal = b.cfm_latent(torch.tensor(demo[-1], dtype=torch.float32), S)
    d = (b.cfm_predict(S, A) - goal).norm(dim=-1)
    torch.testing.assert_close(a, A[d.argmin()], atol=1e-6, rtol=0)
    # Towards the final frame: the grippers' mean move points along -y.
    assert (a[1] + a[4]) / 2 < 0, a
    assert not planner.finished(S)
    assert planner.finished(torch.tensor(demo[-1], dtype=torch.float32))


def test_tcn_time_alignment():
    # One demo frame per control step (H = T - 1): frame t, then the last.
    assert [aligned_frame(t, 5, 4) for t in range(7)] == [0, 1, 2, 3, 4, 4, 4]
    # A demo of 5 frames over 8 control steps: every other step a new frame,
    # halves rounded up.
    assert [aligned_frame(t, 5, 8) for t in range(10)] == [0, 1, 1, 2, 2, 3, 3, 4, 4, 4]
    # 9 frames over 4 steps: every other frame.
    assert [aligned_frame(t, 9, 4) for t in range(6)] == [0, 2, 4, 6, 8, 8]


class _Centroid:
    """A stand-in TCN embedding: the cloth's centroid."""

    def tcn_embed(self, P, S):
        return torch.as_tensor(P, dtype=torch.float32).mean(-2)


class _Slides:
    """A stand-in f_D: the cloth slides with the mean of the grippers'
    moves; no inverse model."""

    def forward(self, S, A):
        return S + ((A[..., :3] + A[..., 3:]) / 2)[..., None, :]

    def inverse(self, S, S_next):
        raise AssertionError("the baselines have no action prior from f_I")


def test_tcn_searches_f_d_rollouts_for_the_time_aligned_frame():
    demo = np.stack([square([0.0, 0.1 - 0.02 * k]) for k in range(6)])
    planner = TcnPlanner(
        _Centroid(), _Slides(), demo, limits=_limits(), config=TcnConfig(horizon=2)
    )
    assert planner.H == 5
    S = torch.tensor(demo[2], dtype=torch.float32)
    a, aligned, iterations = planner.decide(S, 2, [0.0, 0.0, 0.0], seed=0)
    assert aligned == 2 and iterations == 3
    # The frames of steps 3 and 4 lie 2 and 4 cm along -y: the mean move
    # heads there, bounded per axis.
    mean = (a[:3] + a[3:]) / 2
    assert -0.03 <= float(mean[1]) < -0.01 and abs(float(mean[0])) < 0.01, a
    assert a.abs().max() <= 0.03 + 1e-6
    last = torch.tensor(demo[-1], dtype=torch.float32)
    assert not planner.finished(last, 4)  # the demo's time is not up
    assert planner.finished(last, 5)
    assert not planner.finished(S, 5)


def test_tcn_mpc_is_the_tcn_reward_on_our_planner(trained):
    b, cfg = trained
    rules = SafetyConfig()
    ctx = SafetyContext(
        edge_length=0.3,
        workspace_lower=np.array([-0.5, -0.5, -0.01]),
        workspace_upper=np.array([0.5, 0.5, 0.5]),
    )
    demo = np.stack([square([0.0, 0.1 - 0.03 * k]) for k in range(6)])
    b_demo, _ = b.tcn_on_demo(demo, cfg)
    model = DemoModel(demo, registration=None, config=RewardConfig())
    planner = TcnMpc(
        baselines=b_demo,
        dynamics=None,
        demo=model,
        safety=rules,
        safety_ctx=ctx,
        config=MpcConfig(horizon=2),
    )
    S = torch.tensor(demo[2], dtype=torch.float32)
    assert planner.current_progress(S, 2) == 2
    # Rollout step i is compared with demo state step + i + 1.
    assert torch.equal(planner._aligned(0), model.states[3])
    assert torch.equal(planner._aligned(5), model.states[5])  # after the end: the last
    assert not planner.finished(torch.tensor(demo[-1], dtype=torch.float32), 2)
    assert planner.finished(torch.tensor(demo[-1], dtype=torch.float32), 5)


def _forbid_everything():
    """Rules no action passes: rule 1's band of grasped-edge lengths is
    empty, rule 2 allows no direction, and the object's box (rule 4) covers
    the whole workspace."""
    rules = SafetyConfig(tau_c=0.99999, tau_f=1.0, tau_d_deg=0.01)
    ctx = SafetyContext(
        edge_length=0.3,
        workspace_lower=np.array([-0.5, -0.5, -0.01]),
        workspace_upper=np.array([0.5, 0.5, 0.5]),
        object_size=np.array([5.0, 5.0, 5.0]),
        far_corners_may_hang=True,
    )
    return rules, ctx


def _raises(*args, **kwargs):
    raise AssertionError("the baselines must not use the paper's contribution")


@pytest.mark.parametrize("name", ["zero", "cfm", "tcn"])
def test_each_baseline_acts_where_the_safe_set_is_empty(trained, name, monkeypatch):
    """Fault injection: with rules that forbid every action and the safe
    set, the action priors (f_I, the MPC's) and the demo model all
    raising, each baseline still acts, within
    the driver's limits (built from the same safety objects, as
    MakeImitationDiagram does)."""
    b, cfg = trained
    rules, ctx = _forbid_everything()
    demo = np.stack([square([0.0, 0.1 - 0.02 * k]) for k in range(6)])
    S = torch.tensor(demo[1], dtype=torch.float32)
    A = (torch.rand(5000, 6, generator=torch.Generator().manual_seed(0)) * 2 - 1) * 0.03
    assert not valid_actions(S.expand(len(A), -1, -1), A, rules, ctx).any()
    assert not valid_actions(S, torch.zeros(6), rules, ctx)
    limits = DriverLimits.FromSafety(rules, ctx)
    for module in (safety, mpc, baseline_policies):
        for attr in ("valid_actions", "rule_violations"):
            if hasattr(module, attr):
                monkeypatch.setattr(module, attr, _raises)
    for attr in ("action_prior", "solve", "rollout", "_nearest_valid"):
        monkeypatch.setattr(mpc.Mpc, attr, _raises)
    for attr in ("progress", "reward", "done"):
        monkeypatch.setattr(DemoModel, attr, _raises)
    pose = [0.05, -0.1, 0.3]
    if name == "zero":
        step = ZeroFollower(b, demo, limits=limits).decide(S, 0, 0, pose)
        action = step.action
    elif name == "cfm":
        action, _ = CfmPlanner(b, demo, limits=limits).decide(S, pose, seed=0)
    else:
        b_demo, _ = b.tcn_on_demo(demo, cfg)
        planner = TcnPlanner(b_demo, _Slides(), demo, limits=limits)
        action, _, _ = planner.decide(S, 1, pose, seed=0)
    assert action is not None and action.shape == (6,)
    assert torch.isfinite(action).all()
    assert 1e-4 < float(action.abs().max()) <= rules.max_step + 1e-6, action


@pytest.mark.slow
@pytest.mark.parametrize("controller", ["zero", "cfm", "tcn", "tcn_mpc"])
def test_each_shipped_baseline_acts_in_a_short_episode(controller):
    """The shipped networks drive the station for a few steps on box (a
    coarse cloth, a step cap of 7) and the episode is scored."""
    from fabric_imitation.diagrams.imitation import (
        DefaultDemoDir,
        MakeImitationDiagram,
        PrepareImitation,
    )
    from fabric_imitation.scenarios.loader import LoadScenario
    from fabric_imitation.scenarios.policy import LoadPolicy
    from fabric_imitation.tools.episode import RunEpisode, ScoreEpisode

    scenario = LoadScenario(
        scenario_name="box",
        scenario_text="cloth: {vbd: {resolution: [8, 8]}}",
        policy=LoadPolicy(
            policy_text="mpc: {step_cap_factor: 0.1, num_samples: 100, "
            "max_iterations: 1}"
        ),
    )
    prepared = PrepareImitation(
        scenario, demo_dir=DefaultDemoDir("box", scenario), baselines=True
    )
    # The referee only counts: the test is about the baseline acting.
    imitation = MakeImitationDiagram(
        scenario, prepared, controller=controller, on_violation="count"
    )
    run = RunEpisode(imitation, settle_seconds=0.2)
    summary = ScoreEpisode(scenario, prepared, run)
    assert run.error is None
    assert 1 <= summary["steps"] <= 7, summary
    assert np.abs(run.logs["action"]).max() > 0.005
    assert summary["termination"] in ("step cap", "classifier")
    assert len(summary["chamfer_over_steps"]) == summary["steps"] + 1
