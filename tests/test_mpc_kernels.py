"""The MPC's fast paths against the reference code they replace: the
compiled polygon IoU, the rules and rewards batched over every horizon
step, f_D/f_I with their normalisers folded in."""

import dataclasses as dc
import math
from pathlib import Path

import numpy as np
import pytest
import torch
from fabric_imitation.learning import polygon_kernel
from fabric_imitation.learning.demo_learning import DemoModel, RewardConfig
from fabric_imitation.learning.mpc import Mpc, MpcConfig
from fabric_imitation.learning.polygon import iou, iou_pairs
from fabric_imitation.learning.safety import (
    RULES,
    SafetyConfig,
    SafetyContext,
    direction_angles,
    rule_violations,
)


def star_polygons(n, k, seed, *, spread=0.05):
    """n simple (star-shaped, some concave) polygons of k vertices, half of
    them clockwise."""
    g = torch.Generator().manual_seed(seed)
    ang = torch.sort(torch.rand(n, k, generator=g) * 2 * math.pi, -1).values
    r = 0.15 * (0.3 + torch.rand(n, k, generator=g))
    c = (torch.rand(n, 1, 2, generator=g) - 0.5) * spread
    P = torch.stack([r * ang.cos(), r * ang.sin()], -1) + c
    clockwise = torch.rand(n, generator=g) < 0.5
    return torch.where(clockwise[:, None, None], P.flip(-2), P)


def test_compiled_iou_matches_the_reference_on_random_polygons():
    A, B = star_polygons(400, 8, 0), star_polygons(6, 8, 1)
    ref = iou(A.double()[:, None], B.double()[None])
    got = iou_pairs(A, B)
    assert got.shape == (400, 6) and got.dtype == torch.float32
    assert 0.05 < float(ref.mean()) < 0.95  # the batch overlaps partly
    assert float((got.double() - ref).abs().max()) < 1e-6
    # Disjoint, identical and nested polygons.
    far = B + 10.0
    assert float(iou_pairs(A[:5], far).abs().max()) == 0.0
    # (1 and 1/4 up to polygon.SHIFT's generic offset of a few micrometres)
    same = iou_pairs(B, B).diagonal()
    assert float((same - 1).abs().max()) < 1e-3
    assert float(iou_pairs(B[:1] * 0.5, B[:1])) == pytest.approx(0.25, abs=1e-3)
    # Other vertex counts (polygons of 4 against 12).
    A4, B12 = star_polygons(50, 4, 2), star_polygons(3, 12, 3)
    ref = iou(A4.double()[:, None], B12.double()[None])
    assert float((iou_pairs(A4, B12).double() - ref).abs().max()) < 1e-6
    # The states' own polygons: axis-aligned 8-keypoint rectangles (collinear
    # midpoints, shared edges), moved and turned a little.
    g = torch.Generator().manual_seed(6)
    flat = torch.as_tensor(np.stack([cloth(0.02 * j)[:, :2] for j in range(6)]))
    yaw = 0.2 * (torch.rand(200, generator=g) - 0.5)
    R = torch.stack([yaw.cos(), -yaw.sin(), yaw.sin(), yaw.cos()], -1).view(-1, 2, 2)
    moved = flat[torch.randint(6, (200,), generator=g)] @ R.transpose(-1, -2)
    moved = moved + 0.05 * (torch.rand(200, 1, 2, generator=g) - 0.5)
    ref = iou(moved.double()[:, None], flat.double()[None])
    assert float((iou_pairs(moved, flat).double() - ref).abs().max()) < 1e-6


def test_torch_fallback_gives_the_same_iou(monkeypatch):
    A, B = star_polygons(100, 8, 4), star_polygons(6, 8, 5)
    if polygon_kernel.load() is None:
        pytest.skip("no C compiler on this machine: iou_pairs is the fallback")
    compiled = iou_pairs(A, B)
    monkeypatch.setitem(polygon_kernel._LOADED, "kernel", None)
    fallback = iou_pairs(A, B)
    assert float((compiled - fallback).abs().max()) < 1e-6


def test_the_kernel_is_built_once_into_the_cache(tmp_path, monkeypatch):
    monkeypatch.setenv("FABRIC_IMITATION_CACHE", str(tmp_path))
    polygon_kernel.forget()
    try:
        if polygon_kernel.load() is None:
            pytest.skip("no C compiler on this machine")
        (built,) = tmp_path.glob("polygon_kernel-*.so")
        assert not list(tmp_path.glob("*.tmp"))
        stamp = built.stat().st_mtime_ns
        polygon_kernel.forget()
        assert polygon_kernel.load() is not None
        assert built.stat().st_mtime_ns == stamp  # loaded, not rebuilt
        # A library that does not load is built again (a new file: the old
        # one stays mapped into this process).
        built.unlink()
        built.write_bytes(b"not a shared library")
        polygon_kernel.forget()
        assert polygon_kernel.load() is not None
        A, B = star_polygons(10, 8, 7), star_polygons(2, 8, 8)
        ref = iou(A.double()[:, None], B.double()[None])
        assert float((iou_pairs(A, B).double() - ref).abs().max()) < 1e-6
    finally:
        polygon_kernel.forget()  # the next test loads from its own cache
    with pytest.raises(ValueError, match="iou_pairs needs"):
        iou_pairs(torch.zeros(3, 8), torch.zeros(2, 8, 2))


class LinearDynamics:
    """f_D: the grasped corners move with the grippers, the rest half as
    much; f_I its inverse on the grasped corners."""

    def forward(self, S, A):
        move = torch.zeros_like(S)
        move[..., 0, :] = A[..., None, :3][..., 0, :]
        move[..., 2, :] = A[..., None, 3:][..., 0, :]
        rest = (A[..., :3] + A[..., 3:])[..., None, :] / 4
        move[..., [1, 3, 4, 5, 6, 7], :] = rest
        return S + move

    def inverse(self, S, S_next):
        return torch.cat(
            [S_next[..., 0, :] - S[..., 0, :], S_next[..., 2, :] - S[..., 2, :]], -1
        )


class ShiftRegistration:
    def __call__(self, S, S_E):
        T = (S_E - S).mean(-2)
        return torch.zeros_like(T), T


def cloth(y0=0.0, side=0.3, z=0.0):
    h = side / 2
    x = np.array([-h, 0, h, h, h, 0, -h, -h])
    y = np.array([0, 0, 0, h, side, side, side, h]) + y0
    return np.stack([x, y, np.full(8, z)], 1).astype(np.float32)


def make_mpc(**safety):
    demo = np.stack([cloth(0.1 - 0.03 * j, z=0.01 * j) for j in range(8)])
    model = DemoModel(demo, ShiftRegistration(), RewardConfig())
    ctx = SafetyContext(
        edge_length=0.3,
        workspace_lower=np.array([-0.4, -0.4, 0.0]),
        workspace_upper=np.array([0.4, 0.5, 0.5]),
        object_size=np.array([0.1, 0.1, 0.05]),
        frame_pose=np.array([0.05, -0.1, 0.4]),
        far_corners_may_hang=True,
        side_length=0.3,
    )
    return Mpc(
        dynamics=LinearDynamics(),
        demo=model,
        safety=SafetyConfig(tau_d_deg=95.0, **safety),
        safety_ctx=ctx,
        config=MpcConfig(num_samples=300, horizon=4, elites=30),
    )


def test_batched_rollout_matches_the_step_by_step_reference():
    mpc = make_mpc()
    S = torch.as_tensor(cloth(0.05, z=0.02))
    g = torch.Generator().manual_seed(0)
    pull = torch.tensor([0.0, -0.02, 0.0, 0.0, -0.02, 0.0])
    X = mpc._clip(pull + 0.01 * torch.randn(300, 4, 6, generator=g))
    window = mpc._window(1)
    reward, cost = mpc.rollout(S, X, window)
    # Reference: the rules one horizon step at a time, every sequence scored.
    s = S.expand(len(X), *S.shape)
    ref_cost = torch.zeros(len(X))
    broken = {rule: torch.zeros(len(X), dtype=torch.bool) for rule in RULES}
    visited, edge = [], []
    cfg = mpc.config
    for k in range(4):
        # The cost near rule 2's edge (mpc.edge_cost), one step at a time.
        angle = direction_angles(s, X[:, k], mpc.safety.min_move)
        start = mpc.safety.tau_d_deg - cfg.edge_band_deg
        near = ((angle - start) / cfg.edge_band_deg).clamp(0.0, 1.0)
        edge.append(cfg.edge_cost * near.sum(-1))
        s_next = mpc.dynamics.forward(s, X[:, k])
        v = rule_violations(s, X[:, k], mpc.safety, mpc.ctx, S_next=s_next)
        bad = torch.zeros(len(X), dtype=torch.bool)
        for rule in RULES:
            bad |= v[rule]
            broken[rule] |= v[rule]
        ref_cost += bad.float()
        visited.append(s_next)
        s = s_next
    r, _ = mpc.demo.reward(torch.stack(visited), window)
    r = r - torch.stack(edge)
    ref_reward = (0.9 ** torch.arange(4.0)[:, None] * r).sum(0)
    assert cfg.edge_cost > 0 and float(torch.stack(edge).max()) > 0
    assert torch.equal(cost, ref_cost)
    feasible = cost == 0
    assert 0 < int(feasible.sum()) < len(X)  # both kinds in the batch
    assert float((reward[feasible] - ref_reward[feasible]).abs().max()) < 1e-5
    assert bool(torch.isinf(reward[~feasible]).all())  # never scored
    assert mpc.blocking_rules(S, X) == {k: int(b.sum()) for k, b in broken.items()}


def test_the_rollout_window_is_h_plus_one_demo_states_from_j_minus_one():
    mpc = make_mpc()  # demo of 8 states, h = 4
    assert mpc._window(0) == (0, 5)
    assert mpc._window(3) == (2, 7)
    assert mpc._window(7) == (3, 8)  # never past the demo's end
    mpc.config = dc.replace(mpc.config, rollout_window=False)
    assert mpc._window(3) == (0, 8)  # the whole demo
    S = torch.as_tensor(cloth(0.05, z=0.02))
    X = torch.zeros(10, 4, 6)
    reward, _ = mpc.rollout(S, X, mpc._window(3))
    r, _ = mpc.demo.reward(S.expand(4, 10, *S.shape))
    assert torch.allclose(reward, (0.9 ** torch.arange(4.0)[:, None] * r).sum(0))


def _warm(mpc, **config):
    mpc.config = dc.replace(mpc.config, warm_start=True, **config)
    return mpc


def test_a_carried_distribution_starts_the_next_step_shifted_by_one():
    mpc = _warm(make_mpc(), max_iterations=1, beta=1e-6)
    S = torch.as_tensor(cloth(0.05, z=0.02))
    mu = torch.zeros(4, 6)
    mu[:, [1, 4]] = -0.001 * torch.arange(4.0)[:, None]  # step k: pull by k mm
    var = torch.full((4, 6), 1e-6)
    result = mpc.solve(S, noise=(mu, var))
    assert result.feasible
    shifted = torch.cat([mu[1:], mu[-1:]])
    assert torch.allclose(result.noise[0], shifted, atol=1e-7)
    # Without warm_start the same call starts from (0, sigma0^2).
    mpc.config = dc.replace(mpc.config, warm_start=False)
    cold = mpc.solve(S, noise=(mu, var))
    assert float(cold.noise[0].abs().max()) < 1e-7
    assert float(cold.noise[1].min()) > 0.5 * mpc.config.sigma0**2


def test_a_converged_carried_distribution_converges_at_once():
    # The plain reward: with the cost near rule 2's edge on, the carried
    # distribution here meets the test at the second iteration, not the
    # first (the cost reorders the elites a little).
    mpc = _warm(make_mpc(), max_iterations=30, edge_cost=0.0)
    S = torch.as_tensor(cloth(0.05, z=0.02))
    first = mpc.solve(S)  # from (0, sigma0^2): many iterations
    assert first.converged and first.iterations > 3
    again = mpc.solve(S, noise=first.noise)
    assert again.converged and again.iterations == 1


def test_a_carried_distribution_with_nothing_feasible_starts_over():
    mpc = _warm(make_mpc(), max_iterations=30)
    S = torch.as_tensor(cloth(0.05, z=0.02))
    # Both grippers 10 cm along +x, +y, +z at every step: every sample
    # breaks a rule (the direction rule).
    mu, var = torch.full((4, 6), 0.1), torch.full((4, 6), 1e-8)
    result = mpc.solve(S, noise=(mu, var))
    assert result.feasible and result.converged
    assert float(result.action.abs().max()) < mpc.safety.max_step


def test_folded_priors_match_the_normalised_networks():
    import fabric_imitation.learning as learning
    from fabric_imitation.learning.geometry import (
        from_frame,
        rotate_actions,
        to_frame,
    )
    from fabric_imitation.learning.priors import canonical_inputs, load_priors

    p = load_priors(Path(learning.__file__).parent / "priors" / "default")
    g = torch.Generator().manual_seed(0)
    S = torch.rand(200, 8, 3, generator=g) * 0.3
    A = (torch.rand(200, 6, generator=g) - 0.5) * 0.06
    with torch.no_grad():
        Sc, origin, yaw = canonical_inputs(S)
        x = torch.cat(
            [
                p.norms["state"].encode(Sc.flatten(-2)),
                p.norms["action"].encode(rotate_actions(A, -yaw)),
            ],
            -1,
        )
        delta = p.norms["delta"].decode(p.f_D(x)).reshape(Sc.shape)
        S_next = from_frame(Sc + delta, origin, yaw)
        x = torch.cat(
            [
                p.norms["state"].encode(Sc.flatten(-2)),
                p.norms["state"].encode(to_frame(S_next, origin, yaw).flatten(-2)),
            ],
            -1,
        )
        A_back = rotate_actions(p.norms["action"].decode(p.f_I(x)), yaw)
    assert float((p.forward(S, A) - S_next).abs().max()) < 1e-5
    assert float((p.inverse(S, S_next) - A_back).abs().max()) < 1e-5
    # Training changes the weights: the folded copy follows.
    with torch.no_grad():
        p.f_D.net[0].bias.add_(0.1)
    changed = p.forward(S, A)
    assert float((changed - S_next).abs().max()) > 1e-3


def _assert_same_weights(a: torch.nn.Module, b: torch.nn.Module) -> None:
    for x, y in zip(a.state_dict().values(), b.state_dict().values(), strict=True):
        assert torch.equal(x, y)


def test_registration_is_cached_per_demo_and_priors(tmp_path, monkeypatch):
    from fabric_imitation.learning.demo_learning import learn_from_demo

    monkeypatch.setenv("FABRIC_IMITATION_CACHE", str(tmp_path))
    demo = np.stack([cloth(0.1 - 0.03 * j, z=0.01 * j) for j in range(6)])
    prior = np.stack([cloth(0.02 * j) for j in range(20)])
    cfg = RewardConfig(registration_steps=20, registration_batch=16)
    fresh, info = learn_from_demo(demo, prior, cfg)
    assert info["registration_cached"] is False
    again, info = learn_from_demo(demo, prior, cfg)
    assert info["registration_cached"] is True
    _assert_same_weights(fresh.f_A.net, again.f_A.net)
    # A cache hit leaves torch's global stream where training does.
    learn_from_demo(demo, prior, cfg, cache=False)
    after_training = torch.random.get_rng_state()
    learn_from_demo(demo, prior, cfg)
    assert torch.equal(torch.random.get_rng_state(), after_training)
    # Another demo is registered anew.
    _, info = learn_from_demo(demo[:-1], prior, cfg)
    assert info["registration_cached"] is False
    # A corrupt or empty entry is trained over, from the seeded start.
    for junk in (b"not a checkpoint", b""):
        for p in tmp_path.glob("registration-*.pt"):
            p.write_bytes(junk)
        retrained, info = learn_from_demo(demo, prior, cfg)
        assert info["registration_cached"] is False
        _assert_same_weights(fresh.f_A.net, retrained.f_A.net)
        _, info = learn_from_demo(demo, prior, cfg)
        assert info["registration_cached"] is True
    assert not list(tmp_path.glob("*.tmp"))


@pytest.mark.slow
def test_the_same_seed_gives_the_same_actions_idle_and_under_load():
    """box with the shipped priors, demo and settings: 10 control steps
    idle, then again with another process keeping a core busy; the
    iteration count, never the clock, decides, so every action is equal.
    The starts are the demo's states moved by 2 mm, near enough that the
    safe set holds an action at each (1 cm leaves some steps with none)."""
    from fabric_imitation.tools.bench import OneCoreBusy, _PreparedMpc

    torch.set_num_threads(1)
    _, mpc, states = _PreparedMpc("box", None, None, 500, 5)
    rng = np.random.default_rng(1)
    starts = [states[k] + rng.normal(0, 0.002, states[k].shape) for k in range(10)]

    def actions():
        results, noise = [], None
        for k, S in enumerate(starts):
            S = torch.as_tensor(S, dtype=torch.float32)
            results.append(mpc.solve(S, step=k, seed=3, noise=noise))
            noise = results[-1].noise  # carried as MpcController does
        return results

    idle = actions()
    with OneCoreBusy():
        loaded = actions()
    assert all(r.feasible for r in idle)
    for a, b in zip(idle, loaded, strict=True):
        assert torch.equal(a.action, b.action)
        assert a.iterations == b.iterations


def test_the_grasp_prior_heads_for_the_grasped_path_through_its_median():
    """A demo whose left grasped corner is misread 20 cm high in one state:
    from the state before it, the grasp prior's first move lifts the left
    gripper by the whole step bound with the path as it is, and with the
    path through a median of three states by the next state's rise (the
    median takes a neighbour's value)."""
    demo = np.stack([cloth(0.1 - 0.03 * j, z=0.01 * j) for j in range(8)])
    demo[3, 0, 2] += 0.2
    model = DemoModel(demo, ShiftRegistration(), RewardConfig())
    ctx = SafetyContext(
        edge_length=0.3,
        workspace_lower=np.array([-0.4, -0.4, 0.0]),
        workspace_upper=np.array([0.4, 0.5, 0.5]),
    )

    def first_move(frames):
        mpc = Mpc(
            dynamics=LinearDynamics(),
            demo=model,
            safety=SafetyConfig(tau_d_deg=180.0),
            safety_ctx=ctx,
            config=MpcConfig(horizon=2, grasp_path_median=frames),
        )
        S = torch.as_tensor(demo[2])
        assert mpc.current_progress(S, 0) == 2
        return mpc.action_prior(S)[0].numpy()

    assert first_move(1)[2] == pytest.approx(0.03)  # clipped at the step bound
    assert first_move(3)[2] == pytest.approx(0.02, abs=1e-6)
    with pytest.raises(ValueError, match="grasp_path_median"):
        MpcConfig(grasp_path_median=0)
