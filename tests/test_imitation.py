"""Demo learning, reward, termination, MPC and the imitation systems."""

import dataclasses as dc
import math

import numpy as np
import pytest
import torch
from fabric_imitation.learning.demo_learning import (
    DemoModel,
    RewardConfig,
    centred_states,
    learn_from_demo,
)
from fabric_imitation.learning.mpc import Mpc, MpcConfig
from fabric_imitation.learning.polygon import iou
from fabric_imitation.learning.safety import (
    SafetyConfig,
    SafetyContext,
    rule_violations,
    valid_actions,
)
from fabric_imitation.learning.state import world_to_object
from fabric_imitation.systems.imitation import DemoReward, KeypointEstimator
from pydrake.math import RigidTransform, RotationMatrix
from pydrake.systems.sensors import ImageDepth32F, ImageGrey8U


def square(x0, y0, side, z=0.0):
    """An 8-keypoint flat cloth: grasped edge at y0, far edge at y0 + side."""
    h = side / 2
    x = np.array([-h, 0, h, h, h, 0, -h, -h]) + x0
    y = np.array([0, 0, 0, h, side, side, side, h]) + y0
    return np.stack([x, y, np.full(8, z)], 1).astype(np.float32)


def test_iou_of_hand_made_polygons():
    t = torch.as_tensor
    a, b = t(square(0, 0, 0.3)[:, :2]), t(square(0.15, 0, 0.3)[:, :2])
    assert float(iou(a, b)) == pytest.approx(1 / 3, abs=1e-4)
    assert float(iou(a, a)) == pytest.approx(1.0, abs=1e-4)
    assert float(iou(a, t(square(1.0, 0, 0.3)[:, :2]))) == 0.0
    inner = t(square(0.0, 0.075, 0.15)[:, :2])
    assert float(iou(a, inner)) == pytest.approx(0.25, abs=1e-4)
    # Non-convex: an L (three unit squares) against the unit square in its
    # missing corner's neighbour: overlap 1, union 3.
    ell = t([[0, 0], [2, 0], [2, 1], [1, 1], [1, 2], [0, 2]], dtype=torch.float32)
    unit = t([[1, 0], [2, 0], [2, 1], [1, 1]], dtype=torch.float32)
    assert float(iou(ell, unit)) == pytest.approx(1 / 3, abs=1e-4)


def _grid_area(P, Q, n=600):
    """Areas of P n Q and P u Q by even-odd tests on an n x n grid (numpy)."""
    lo = np.minimum(P.min(0), Q.min(0))
    hi = np.maximum(P.max(0), Q.max(0))
    xs = lo[0] + (np.arange(n) + 0.5) * (hi[0] - lo[0]) / n
    ys = lo[1] + (np.arange(n) + 0.5) * (hi[1] - lo[1]) / n
    X, Y = np.meshgrid(xs, ys)

    def inside(poly):
        a, b = poly, np.roll(poly, -1, 0)
        hit = np.zeros(X.shape, bool)
        for (ax, ay), (bx, by) in zip(a, b, strict=True):
            if ay == by:
                continue
            crosses = (ay > Y) != (by > Y)
            hit ^= crosses & (ax + (Y - ay) * (bx - ax) / (by - ay) > X)
        return hit

    p, q = inside(P), inside(Q)
    cell = (hi - lo).prod() / n**2
    return (p & q).sum() * cell, (p | q).sum() * cell


def test_iou_of_random_star_polygons_matches_a_fine_grid():
    rng = np.random.default_rng(3)
    A, B = [], []
    for _ in range(12):
        pair = []
        for _ in range(2):
            ang = np.sort(rng.uniform(0, 2 * np.pi, 8))
            r = 0.1 * rng.uniform(0.5, 1.0, 8)  # star-shaped: simple
            c = rng.normal(0, 0.03, 2)
            pair.append(np.stack([r * np.cos(ang), r * np.sin(ang)], 1) + c)
        A.append(pair[0])
        B.append(pair[1])
    A, B = np.array(A, np.float32), np.array(B, np.float32)
    got = iou(torch.as_tensor(A), torch.as_tensor(B)).numpy()
    for k in range(len(A)):
        inter, union = _grid_area(A[k], B[k])
        assert got[k] == pytest.approx(inter / union, abs=0.01)


class Exact:
    """f_A stand-in: the exact translation between centroids, no rotation."""

    def __call__(self, S, S_E):
        T = (S_E - S).mean(-2)
        return torch.zeros_like(T), T


def demo_model(states, **cfg):
    return DemoModel(np.asarray(states), Exact(), RewardConfig(**cfg))


def pulled_demo(n=8, step=0.03):
    """A demo pulling a flat cloth towards -y, step by step."""
    return np.stack([square(0, 0.1 - step * j, 0.3, z=0.01) for j in range(n)])


def test_progress_by_iou_and_by_centre_when_nothing_overlaps():
    model = demo_model(pulled_demo())
    J, best = model.progress(
        torch.as_tensor(square(0, 0.1 - 0.03 * 3, 0.3, z=0.01))[None]
    )
    assert int(J[0]) == 3 and float(best[0]) == pytest.approx(1.0, abs=1e-4)
    far = torch.as_tensor(square(0, -1.0, 0.3))[None]  # overlaps no demo state
    J, best = model.progress(far)
    assert float(best[0]) == 0.0 and int(J[0]) == 7  # nearest centre: the last


def test_reward_and_termination_on_hand_made_states():
    states = pulled_demo()
    model = demo_model(states, w_p=10.0, w_n=10.0, tau_i=0.9)
    S3 = torch.as_tensor(states[3])
    r, J = model.reward(S3[None])
    # J = 3, subgoal S_E[4] is 3 cm away: R = 3 - 10 * 0.03.
    assert int(J[0]) == 3
    assert float(r[0]) == pytest.approx(3 - 10 * 0.03, abs=1e-5)
    # Overshoot: past the last state, D_N = mean distance to S_E^T.
    past = torch.as_tensor(states[-1] - [0, 0.01, 0])
    r_past, J_past = model.reward(past[None])
    assert int(J_past[0]) == 7
    assert float(r_past[0]) == pytest.approx(7 - 10 * 0.01 - 10 * 0.01, abs=1e-4)
    assert bool(model.done(torch.as_tensor(states[-1])))
    assert not bool(model.done(torch.as_tensor(states[-2])))
    assert not bool(model.done(past + torch.tensor([0.0, -0.05, 0.0])))


def test_termination_progress_slack_lets_the_state_before_the_last_end():
    # A 3 cm pull of a 30 cm square: S_E^{T-2} has IoU 27/33 = 0.82 with S_E^T.
    states = pulled_demo()
    before_last = torch.as_tensor(states[-2])
    assert not bool(demo_model(states, tau_i=0.8).done(before_last))
    slack = demo_model(states, tau_i=0.8, done_progress_slack=1)
    assert bool(slack.done(before_last))
    assert bool(slack.done(torch.as_tensor(states[-1])))
    # Two states back (IoU 24/36) fails the IoU test whatever the slack.
    assert not bool(slack.done(torch.as_tensor(states[-3])))
    assert not bool(
        demo_model(states, tau_i=0.6, done_progress_slack=1).done(
            torch.as_tensor(states[-3])
        )
    )
    with pytest.raises(ValueError, match="done_progress_slack"):
        RewardConfig(done_progress_slack=-1)


def test_d_p_on_hand_made_states():
    states = pulled_demo()
    S = states[3].copy()
    S[[0, 2], 0] += [0.02, -0.02]  # grasped corners 4 cm closer together
    S[[0, 2], 2] += 0.01
    sub = states[4]
    T = (sub - S).mean(0)
    base = demo_model(states, w_p=10.0)
    r0, J = base.reward(torch.as_tensor(S)[None])
    assert int(J[0]) == 3
    assert float(r0[0]) == pytest.approx(3 - 10 * np.linalg.norm(T), abs=1e-4)


def test_keypoint_net_spread_is_small_where_the_heatmap_is_sharp():
    from fabric_imitation.learning.models import KeypointNet, KeypointNetConfig

    net = KeypointNet(KeypointNetConfig(num_keypoints=2)).eval()
    x = torch.zeros(1, 2, 32, 32)
    x[0, 0, 8:24, 8:24] = 1.0

    def sharp_and_flat(_):
        logits = torch.zeros(1, 2, 16, 16)
        logits[0, 0, 4, 10] = 50.0  # all mass in one cell
        return logits

    net.heatmaps = sharp_and_flat
    uv, spread = net.locate(x)
    torch.testing.assert_close(uv, net(x))
    # A cell of the 16 x 16 heatmap spans 2 input pixels.
    torch.testing.assert_close(uv[0, 0], torch.tensor([20.5, 8.5]))
    assert float(spread[0, 0]) < 1e-3
    # A flat heatmap: the spread of a uniform 32 x 32 square, 32 / sqrt(6).
    assert abs(float(spread[0, 1]) - 32 / math.sqrt(6)) < 0.05


@pytest.mark.slow
def test_registration_recovers_a_known_rigid_transform():
    rng = np.random.default_rng(0)
    source = square(0.0, 0.0, 0.3) + rng.normal(0, 0.005, (8, 3)).astype(np.float32)
    source[:, 2] = np.abs(source[:, 2])
    yaw = math.radians(20)
    R = np.array(
        [
            [math.cos(yaw), -math.sin(yaw), 0],
            [math.sin(yaw), math.cos(yaw), 0],
            [0, 0, 1],
        ],
        np.float32,
    )
    target = source @ R.T + np.array([0.05, -0.02, 0.0], np.float32)
    prior = np.stack(
        [square(0, 0, 0.3) + rng.normal(0, 0.01, (8, 3)) for _ in range(64)]
    )
    # f_A learns to register turned and moved states from sources turned and
    # moved so (with the sources only centred on the demo, the error here is
    # about 3 cm).
    model, info = learn_from_demo(
        target[None],
        prior.astype(np.float32),
        RewardConfig(registration_steps=1500, source_yaw_deg=60.0, source_shift=0.15),
    )
    aligned, e, T = model.f_A.align(torch.as_tensor(source), torch.as_tensor(target))
    error = (aligned - torch.as_tensor(target)).norm(dim=-1).mean()
    assert float(error.detach()) < 0.01
    assert float(e[2].detach()) == pytest.approx(yaw, abs=math.radians(5))


def test_f_a_sources_are_centred_on_the_demo_and_turned_only_when_asked():
    rng = np.random.default_rng(0)
    S = torch.as_tensor(
        np.stack([square(*rng.uniform(-0.2, 0.2, 2), 0.3) for _ in range(16)])
    )
    around = torch.tensor([0.05, 0.3])
    still = centred_states(S, around)
    centroids = still[..., :2].mean(-2)
    assert torch.allclose(centroids, around.expand(16, 2), atol=1e-6)
    # Unturned: each state only moved.
    assert torch.allclose(still - still[:, :1], S - S[:, :1], atol=1e-6)
    gen = torch.Generator().manual_seed(0)
    turned = centred_states(S, around, 60.0, 0.0, gen)
    assert torch.allclose(turned[..., :2].mean(-2), around.expand(16, 2), atol=1e-6)
    # Turned rigidly about the vertical: shapes and heights kept, edges turned.
    assert torch.allclose(torch.cdist(turned, turned), torch.cdist(S, S), atol=1e-5)
    assert torch.equal(turned[..., 2], S[..., 2])
    edge, edge0 = turned[:, 2] - turned[:, 0], S[:, 2] - S[:, 0]
    yaw = torch.atan2(edge[:, 1], edge[:, 0]) - torch.atan2(edge0[:, 1], edge0[:, 0])
    assert yaw.abs().max() <= math.radians(60) + 1e-5
    assert yaw.abs().max() > math.radians(10)
    with pytest.raises(ValueError, match="source_yaw_deg"):
        RewardConfig(source_yaw_deg=-1.0)


class Linear:
    """A fake dynamics model: the grasped corners move by a_L, a_R, every other
    keypoint by their mean."""

    def forward(self, S, A):
        S = torch.as_tensor(S, dtype=torch.float32)
        A = torch.as_tensor(A, dtype=torch.float32)
        a_l, a_r = A[..., None, :3], A[..., None, 3:]
        move = ((a_l + a_r) / 2).expand(S.shape).clone()
        move[..., 0, :] = a_l[..., 0, :]
        move[..., 2, :] = a_r[..., 0, :]
        return S + move

    def inverse(self, S, S_next):
        d = torch.as_tensor(S_next) - torch.as_tensor(S)
        return torch.cat([d[..., 0, :], d[..., 2, :]], -1)


CTX = SafetyContext(
    edge_length=0.3,
    workspace_lower=np.array([-0.45, -0.45, -0.01]),
    workspace_upper=np.array([0.45, 0.45, 0.5]),
)


def linear_goal_mpc(dynamics, model, **config) -> Mpc:
    """A 200-sample, 3-step MPC with three iterations every step."""
    return Mpc(
        dynamics=dynamics,
        demo=model,
        safety=SafetyConfig(),
        safety_ctx=CTX,
        config=MpcConfig(
            num_samples=200,
            horizon=3,
            elites=20,
            max_iterations=3,
            **config,
        ),
    )


def run_to_goal(mpc: Mpc, S: torch.Tensor, steps: int = 30) -> torch.Tensor:
    """Closed loop on the `Linear` model until the classifier fires; every
    applied action must be feasible. Returns the final state."""
    model = mpc.demo
    for step in range(steps):
        if bool(model.done(S)):
            break
        result = mpc.solve(S, step=step)
        assert result.feasible
        assert bool(valid_actions(S, result.action, mpc.safety, CTX))
        S = Linear().forward(S, result.action)
    return S


@pytest.mark.parametrize("use_prior", [True, False])
def test_mpc_on_a_linear_model_reaches_the_goal_and_stays_feasible(use_prior):
    states = pulled_demo(n=8)
    model = demo_model(states, tau_i=0.9)
    mpc = linear_goal_mpc(Linear(), model, use_prior=use_prior)
    S = torch.as_tensor(states[0] + [0.02, 0.0, 0.0])  # a little to the side
    S = run_to_goal(mpc, S)
    assert bool(model.done(S)), (S - torch.as_tensor(states[-1])).norm(dim=-1).mean()


class WrongInverse(Linear):
    """A model error: f_I points away from the goal."""

    def inverse(self, S, S_next):
        return -super().inverse(S, S_next)


def small_mpc(dynamics, states) -> Mpc:
    """A 50-sample, 2-step MPC following `states` with `dynamics`."""
    return Mpc(
        dynamics=dynamics,
        demo=demo_model(states),
        safety=SafetyConfig(),
        safety_ctx=CTX,
        config=MpcConfig(num_samples=50, horizon=2, elites=5, max_iterations=2),
    )


def test_an_invalid_prior_action_is_repaired_unless_switched_off():
    states = pulled_demo(n=8)
    mpc = linear_goal_mpc(
        WrongInverse(), demo_model(states, tau_i=0.9), prior="inverse"
    )
    # The (wrong) f_I pushes the grasped corners 3 cm back into the cloth:
    # rule 2 forbids it, and the repair puts a valid action in its place.
    S = torch.as_tensor(states[0])
    raw = mpc._clip(WrongInverse().inverse(S[None], torch.as_tensor(states[1])[None]))
    assert not bool(valid_actions(S, raw[0], mpc.safety, CTX))
    repaired = mpc.action_prior(S, torch.Generator().manual_seed(0))[0]
    assert bool(valid_actions(S, repaired, mpc.safety, CTX))
    mpc.config = dc.replace(mpc.config, repair_prior=False)
    assert torch.equal(mpc.action_prior(S)[0], raw[0])


def test_the_grasp_prior_heads_for_the_subgoals_grasped_corners():
    states = pulled_demo(n=8)
    mpc = linear_goal_mpc(WrongInverse(), demo_model(states, tau_i=0.9))
    assert mpc.config.prior == "grasp"  # the default
    S = torch.as_tensor(states[0] + [0.01, 0.0, 0.0], dtype=torch.float32)
    # f_I (wrong here) is not read: each gripper moves straight towards the
    # subgoal's grasped corner, clipped to one step's bound.
    J, _ = mpc.demo.progress(S[None])
    goal = mpc.demo.states[min(int(J[0]) + 1, mpc.demo.T - 1)]
    want = mpc._clip(torch.cat([goal[0] - S[0], goal[2] - S[2]]))
    prior = mpc.action_prior(S, torch.Generator().manual_seed(0))
    assert torch.allclose(prior[0], want, atol=1e-6)
    assert bool(valid_actions(S, prior[0], mpc.safety, CTX))
    with pytest.raises(ValueError, match="mpc.prior must be inverse or grasp"):
        MpcConfig(prior="replay")


def test_mpc_reports_no_feasible_action():
    states = pulled_demo()
    # The far edge lies 15 cm beyond the workspace: no move brings it back in
    # one step, so every sequence violates rule 3.
    start = square(0, 0.3, 0.3, z=0.01)
    mpc = small_mpc(Linear(), states)
    assert not mpc.solve(torch.as_tensor(start)).feasible


def test_demo_reward_system():
    states = pulled_demo()
    model = demo_model(states)
    dut = DemoReward(demo=model, num_keypoints=8)
    context = dut.CreateDefaultContext()
    dut.GetInputPort("keypoints").FixValue(context, states[2].ravel())
    r, J = model.reward(torch.as_tensor(states[2])[None])
    assert dut.GetOutputPort("progress").Eval(context)[0] == 2
    assert dut.GetOutputPort("reward").Eval(context)[0] == pytest.approx(float(r[0]))
    assert dut.GetOutputPort("done").Eval(context)[0] == 0
    dut.GetInputPort("keypoints").FixValue(context, states[-1].ravel())
    assert dut.GetOutputPort("done").Eval(context)[0] == 1


class FixedPriors:
    def __init__(self, points):
        self.points = points
        self.seen = []

    def keypoints(self, mask, depth):
        self.seen.append((mask.shape, depth.shape))
        return self.points


def test_keypoint_estimator_system_outputs_object_frame_keypoints():
    p_W = square(0.1, 0.2, 0.3, z=0.01)
    priors = FixedPriors(p_W)
    dut = KeypointEstimator(
        priors=priors, num_keypoints=8, width=32, height=24, period=0.2
    )
    context = dut.CreateDefaultContext()
    dut.GetInputPort("mask").FixValue(context, ImageGrey8U(32, 24))
    dut.GetInputPort("depth").FixValue(context, ImageDepth32F(32, 24))
    X_WO = RigidTransform(RotationMatrix.MakeZRotation(0.5), [0.05, -0.1, 0.0])
    dut.GetInputPort("object_pose").FixValue(context, X_WO)
    state = dut.CreateDefaultContext().get_discrete_state()
    dut.CalcForcedDiscreteVariableUpdate(context, state)
    context.SetDiscreteState(state)
    expected = world_to_object(p_W, [0.05, -0.1, 0.5])
    np.testing.assert_allclose(
        dut.GetOutputPort("keypoints").Eval(context), expected.ravel(), atol=1e-6
    )
    assert priors.seen == [((24, 32), (24, 32))]


def test_the_edge_cost_charges_moves_near_rule_2s_threshold():
    """mpc.edge_cost: a move 90 degrees from its side, with tau_d 100 and a
    15-degree band, costs a third of edge_cost at its step; a move along
    the side or no move costs nothing; the rollout's reward is the reward
    without it less the discounted cost."""
    import math

    states = pulled_demo(n=8)
    S = torch.as_tensor(states[0])

    def mpc(**config):
        return Mpc(
            dynamics=Linear(),
            demo=demo_model(states),
            safety=SafetyConfig(tau_d_deg=100.0),
            safety_ctx=CTX,
            config=MpcConfig(num_samples=2, horizon=2, elites=1, **config),
        )

    # s1 - s3 points to -y (the grasped edge pulled towards -y): +x is 90
    # degrees from it, -y 0 degrees.
    X = torch.zeros(2, 2, 6, dtype=S.dtype)
    X[0, 0, 0] = 0.02  # left gripper along +x at step 0
    X[1, :, 1] = -0.02  # both steps along -y: along the side
    on = mpc(edge_cost=3.0, edge_band_deg=15.0)
    states_h = on._predicted_states(S, X)
    cost = on._edge_cost(states_h[:-1], X)
    torch.testing.assert_close(cost, torch.tensor([[1.0, 0.0], [0.0, 0.0]]))
    with_cost, _ = on.rollout(S, X, on._window(0))
    without, _ = mpc(edge_cost=0.0).rollout(S, X, on._window(0))
    assert float(without[0] - with_cost[0]) == pytest.approx(1.0, abs=1e-5)
    assert float(without[1] - with_cost[1]) == pytest.approx(0.0, abs=1e-6)
    assert math.isfinite(float(with_cost[0]))
    with pytest.raises(ValueError, match="edge_cost"):
        MpcConfig(edge_cost=-1.0)


def test_each_ablation_changes_only_what_it_names():
    """No MPC applies the prior's first action; No Prior samples around zero
    instead of around the prior; No Cost takes an action that breaks a rule
    where ours refuses it (a demo that pushes the grasped edge back onto the
    cloth: rule 2)."""
    states = pulled_demo(n=8)
    S = torch.as_tensor(states[0])

    def mpc(**config):
        return Mpc(
            dynamics=Linear(),
            demo=demo_model(states, tau_i=0.9),
            safety=SafetyConfig(),
            safety_ctx=CTX,
            config=MpcConfig(
                num_samples=200, horizon=3, elites=20, max_iterations=1, **config
            ),
        )

    ours = mpc(sigma0=1e-4)
    prior = ours.action_prior(S)[0]
    assert float(prior.norm()) > 0.02  # a 3 cm pull towards -y
    no_mpc = mpc(use_mpc=False).solve(S)
    assert torch.equal(no_mpc.action, prior) and no_mpc.iterations == 0
    assert torch.allclose(ours.solve(S).action, prior, atol=1e-3)
    assert float(mpc(sigma0=1e-4, use_prior=False).solve(S).action.norm()) < 1e-3
    # Back onto the cloth: the grasped corners move towards the far ones.
    pushed = np.stack([square(0, 0.1 + 0.03 * j, 0.3, z=0.01) for j in range(8)])
    S = torch.as_tensor(pushed[0])

    def breaks_rule_2(result):
        v = rule_violations(S, result.action, SafetyConfig(), CTX)
        return bool(v["direction"])

    def against(**config):
        return Mpc(
            dynamics=Linear(),
            demo=demo_model(pushed, tau_i=0.9),
            safety=SafetyConfig(),
            safety_ctx=CTX,
            config=MpcConfig(num_samples=200, horizon=3, elites=20, **config),
        ).solve(S)

    refused = against()
    assert not refused.feasible or not breaks_rule_2(refused)
    assert breaks_rule_2(against(use_cost=False))
