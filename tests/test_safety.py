"""Each rule of the safe action set (paper Sec. IV-B) on hand-built states."""

import numpy as np
import pytest
from fabric_imitation.learning.safety import (
    SafetyConfig,
    SafetyContext,
    demo_direction_angle,
    rule_violations,
    valid_actions_np,
)
from fabric_imitation.learning.state import corner_indices

L = 0.30


def flat_state():
    """8 keypoints of a flat 30 x 30 cloth, grasped edge at y = 0."""
    x = np.array([-0.15, 0.0, 0.15, 0.15, 0.15, 0.0, -0.15, -0.15])
    y = np.array([0.0, 0.0, 0.0, 0.15, 0.30, 0.30, 0.30, 0.15])
    return np.stack([x, y, np.zeros(8)], 1)


CTX = SafetyContext(
    edge_length=L,
    workspace_lower=np.array([-0.4, -0.4, -0.01]),
    workspace_upper=np.array([0.4, 0.4, 0.5]),
)
CFG = SafetyConfig()


def violated(A, S=None, ctx=CTX, S_next=None, config=CFG):
    import torch

    t = torch.as_tensor
    S = flat_state() if S is None else S
    out = rule_violations(
        t(S),
        t(np.asarray(A, float)),
        config,
        ctx,
        None if S_next is None else t(S_next),
    )
    return {k for k, v in out.items() if bool(v)}


def test_pulling_back_and_lifting_is_valid():
    assert violated([0, -0.02, 0.02, 0, -0.02, 0.02]) == set()
    assert valid_actions_np(flat_state(), [0, -0.02, 0.02, 0, -0.02, 0.02], CFG, CTX)


def test_action_bound():
    assert violated([0, -0.04, 0, 0, -0.02, 0]) == {"bounds"}


def test_grasp_distance_band():
    # Together: 0.30 - 2 * 0.03 = 0.24 > tau_c * L = 0.15 is fine ...
    assert "distance" not in violated([0.03, 0, 0, -0.03, 0, 0])
    # ... pulled apart beyond tau_f * L = 0.315 is not.
    assert "distance" in violated([-0.03, 0, 0, 0.03, 0, 0])
    S = flat_state()
    S[0, 0], S[2, 0] = -0.08, 0.08  # grippers 16 cm apart
    assert "distance" in violated([0.01, 0, 0, -0.01, 0, 0], S=S)


def test_move_direction_against_the_edge():
    # Edge s1 - s3 points to -y; pushing into the cloth (+y) is 180 degrees.
    assert "direction" in violated([0, 0.02, 0, 0, -0.02, 0])
    # Sideways (90 degrees) is below tau_d = 100 degrees.
    assert "direction" not in violated([0.01, 0, 0, 0.01, 0, 0])
    # A tiny move has no direction.
    assert "direction" not in violated([0, 0.001, 0, 0, 0, 0])


def test_direction_angles_are_rule_2s_measure():
    from fabric_imitation.learning.safety import direction_angles

    t = __import__("torch").as_tensor
    A = t([[0, 0.02, 0, 0.02, 0, 0], [0, -0.02, 0, 0, 0.001, 0]])
    angles = direction_angles(t(flat_state()), A, CFG.min_move)
    np.testing.assert_allclose(angles.numpy(), [[180.0, 90.0], [0.0, 0.0]], atol=0.05)


def test_cloth_inside_the_workspace():
    S = flat_state() + [0.0, -0.39, 0.0]
    assert "workspace" in violated([0, -0.02, 0, 0, -0.02, 0], S=S)
    S_next = flat_state() + [0.3, 0, 0]  # a predicted state off the side
    assert "workspace" in violated([0, 0, 0, 0, 0, 0], S_next=S_next)
    assert "workspace" in violated([0, 0, -0.02, 0, 0, 0])  # below the table
    # A predicted state inside, but a gripper target above the ceiling.
    S = flat_state()
    S[0, 2] = 0.49
    inside = flat_state() + [0, 0, 0.2]
    assert "workspace" in violated([0, 0, 0.02, 0, 0, 0], S=S, S_next=inside)
    assert "workspace" not in violated([0, 0, 0.0, 0, 0, 0], S=S, S_next=inside)


def test_grippers_clear_of_the_object():
    ctx = SafetyContext(
        edge_length=L,
        workspace_lower=CTX.workspace_lower,
        workspace_upper=CTX.workspace_upper,
        object_size=np.array([0.14, 0.09, 0.06]),
    )
    S = flat_state() + [0, 0.10, 0.0]
    # Left gripper ends at (-0.12, 0.08, 0.02): above the box footprint? no,
    # x = -0.12 is outside |x| < 0.07 + 0.02; y in range; so it is clear.
    assert "object" not in violated([0.03, -0.02, 0.02, 0, 0, 0], S=S, ctx=ctx)
    S2 = flat_state()
    S2[0] = [-0.05, 0.06, 0.03]
    assert "object" in violated([0.0, -0.02, 0.0, 0, 0, 0], S=S2, ctx=ctx)
    S2[0, 2] = 0.12  # high above the box: clear
    assert "object" not in violated([0.0, -0.02, 0.0, 0, 0, 0], S=S2, ctx=ctx)


def test_the_hand_shape_keeps_the_hand_out_of_the_object():
    """With hand spheres, a gripper whose grasped point keeps the 2 cm margin
    but whose hand reaches into the box breaks rule 4; above the box top it
    does not. The spheres are world-aligned and turn into a turned object's
    frame: an offset along world x lies along the object's -y when the
    object is turned +90 degrees."""
    size = np.array([0.14, 0.09, 0.06])
    base = dict(
        edge_length=L,
        workspace_lower=CTX.workspace_lower,
        workspace_upper=CTX.workspace_upper,
        object_size=size,
    )
    # One sphere, 5 cm along world +x from the grasped point, radius 1 cm.
    sphere = np.array([[0.05, 0.0, 0.0, 0.01]])
    points = SafetyContext(**base)
    hand = SafetyContext(**base, hand_spheres=sphere)
    S = flat_state()
    S[0] = [-0.12, 0.0, 0.03]  # 5 cm left of the box's -x face, mid-height
    stay = [0.0, 0.0, 0.0, 0, 0, 0]
    assert "object" not in violated(stay, S=S, ctx=points)
    assert "object" in violated(stay, S=S, ctx=hand)  # the sphere is at x = -0.07
    S[0, 2] = 0.08  # above the top: clear
    assert "object" not in violated(stay, S=S, ctx=hand)
    # Turned +90 degrees: world +x is the object's -y, so the sphere lies
    # 5 cm towards -y of a point 5 cm in front of the -y face: not in it.
    turned = SafetyContext(
        **base, hand_spheres=sphere, frame_pose=np.array([0, 0, np.pi / 2])
    )
    S[0] = [-0.12, 0.0, 0.03]
    assert "object" not in violated(stay, S=S, ctx=turned)
    S[0] = [0.0, 0.095, 0.03]  # 5 cm beyond the +y face: the sphere reaches it
    assert "object" in violated(stay, S=S, ctx=turned)
    assert "object" not in violated(stay, S=S, ctx=points)


def test_the_hand_margin_keeps_the_hand_that_far_from_the_object():
    """hand_margin: a hand sphere 5 mm from the object's face passes with no
    margin and breaks rule 4 with a 1 cm one; 15 mm away it passes both."""
    size = np.array([0.14, 0.09, 0.06])
    sphere = np.array([[0.05, 0.0, 0.0, 0.01]])  # 5 cm along +x, radius 1 cm
    ctx = SafetyContext(
        edge_length=L,
        workspace_lower=CTX.workspace_lower,
        workspace_upper=CTX.workspace_upper,
        object_size=size,
        hand_spheres=sphere,
    )
    margin = SafetyConfig(hand_margin=0.01)
    stay = [0.0, 0.0, 0.0, 0, 0, 0]
    S = flat_state()
    # The sphere's centre at x = -0.085: its surface 5 mm from the -x face.
    S[0] = [-0.135, 0.0, 0.03]
    no_margin = SafetyConfig(hand_margin=0.0)
    assert "object" not in violated(stay, S=S, ctx=ctx, config=no_margin)
    assert "object" in violated(stay, S=S, ctx=ctx, config=margin)
    S[0] = [-0.145, 0.0, 0.03]  # 15 mm: clear of the margin
    assert "object" not in violated(stay, S=S, ctx=ctx, config=margin)
    with pytest.raises(ValueError, match="hand_margin"):
        SafetyConfig(hand_margin=-0.01)


def test_rules_are_batched():
    rng = np.random.default_rng(0)
    S = np.broadcast_to(flat_state(), (200, 8, 3))
    A = rng.uniform(-0.03, 0.03, (200, 6))
    batched = valid_actions_np(S, A, CFG, CTX)
    one_by_one = [bool(valid_actions_np(S[i], A[i], CFG, CTX)) for i in range(200)]
    assert batched.tolist() == one_by_one
    assert 0 < batched.sum() < 200


def test_each_rule_on_a_batch_of_samples_and_steps_equals_one_at_a_time():
    """The MPC judges all (samples, horizon) predicted states at once: every
    rule's verdict on a random (50, 5) batch (states moved up to 4 cm, an
    object in the scene, predicted next states given) equals the verdict of
    each state alone."""
    import torch

    rng = np.random.default_rng(3)
    ctx = SafetyContext(
        edge_length=L,
        workspace_lower=CTX.workspace_lower,
        workspace_upper=CTX.workspace_upper,
        object_size=np.array([0.12, 0.08, 0.06]),
        far_corners_may_hang=True,
    )
    # The grippers 9 cm apart, at the box's front face and height, so that
    # every rule, the object's too, holds for some states and not others.
    base = flat_state() + [0.0, -0.06, 0.03]
    base[[0, 2], 0] *= 0.3
    S = base + rng.uniform(-0.04, 0.04, (50, 5, 8, 3))
    S[..., 2] = np.abs(S[..., 2])
    A = rng.uniform(-0.035, 0.035, (50, 5, 6))
    S_next = S + rng.uniform(-0.03, 0.03, S.shape)
    t = torch.as_tensor
    batched = rule_violations(t(S), t(A), CFG, ctx, t(S_next))
    assert set(batched) >= {"bounds", "distance", "direction", "workspace", "object"}
    for name, verdict in batched.items():
        assert verdict.shape == (50, 5), name
        one = [
            bool(
                rule_violations(t(S[i, k]), t(A[i, k]), CFG, ctx, t(S_next[i, k]))[name]
            )
            for i in range(50)
            for k in range(5)
        ]
        assert verdict.reshape(-1).tolist() == one, name
    for name in ("bounds", "distance", "direction", "workspace", "object"):
        assert 0 < int(batched[name].sum()) < 250, name


def test_bad_thresholds_are_rejected():
    with pytest.raises(ValueError, match="tau_c"):
        SafetyConfig(tau_c=1.2, tau_f=1.0)


# The hang scene's 17 x 1 x 20 cm plate.
PLATE = SafetyContext(
    edge_length=L,
    workspace_lower=CTX.workspace_lower,
    workspace_upper=CTX.workspace_upper,
    object_size=np.array([0.17, 0.01, 0.20]),
)


def _breaks_direction(S, A, cfg: SafetyConfig, ctx: SafetyContext) -> bool:
    """Rule 2 (direction) on one recorded state S (8, 3) and action A (6,)."""
    import torch

    out = rule_violations(torch.as_tensor(S), torch.as_tensor(A), cfg, ctx)
    return bool(out["direction"])


def test_a_side_hanging_free_below_a_gripper_hangs_straight_down():
    """A towel carried 33 cm up behind the plate (hang, seed 2, trial 1,
    step 18): f_R puts the left far corner s3 up by the grippers, the true
    one hangs 4.6 cm behind the plumb line, 6 cm over the table. The left
    gripper moves 2.7 cm down and back: 153 degrees off the true side, 145
    off straight up. With tau_D 140 degrees the controller, judging the side
    as hanging straight below the gripper, refuses it; at 150 it passes;
    held lower than the side is long (the towel partly on the table), the
    hypothesis does not apply."""
    import dataclasses as dc

    import torch

    estimate = np.array(
        [
            [-0.146, 0.209, 0.331],  # s1
            [0.017, 0.212, 0.298],
            [0.153, 0.207, 0.325],  # s2
            [0.124, 0.297, 0.213],
            [0.070, 0.353, 0.115],  # s4
            [0.002, 0.236, 0.307],
            [-0.084, 0.221, 0.317],  # s3, as f_R sees it
            [-0.124, 0.237, 0.330],
        ]
    )
    truth = estimate.copy()
    truth[6] = [-0.152, 0.255, 0.061]
    A = torch.tensor([-0.0086, 0.0132, -0.0219, -0.0027, 0.016, 0.001])
    plate = PLATE
    controller = dc.replace(plate, far_corners_may_hang=True)

    def direction(S, ctx, tau_d=140.0):
        return _breaks_direction(S, A, SafetyConfig(tau_d_deg=tau_d), ctx)

    assert direction(truth, plate, 150.0)
    assert not direction(estimate, plate)  # as f_R sees it, the move looks safe
    assert direction(estimate, controller)
    assert not direction(estimate, controller, 150.0)
    assert not direction(estimate - [0.0, 0.0, 0.05], controller)


def _demo_moving_at(angles_deg: list[float], m: int = 8) -> np.ndarray:
    """Demo states (T, m, 3) whose grasped corners move 1 cm a step at the
    given angles [deg] from their sides (the sides point along +y: far
    corners at y = -0.3, grasped ones at y = 0), in the x-y plane."""
    idx = corner_indices(m)
    S = np.zeros((len(angles_deg) + 1, m, 3))
    S[0, idx["s1"]], S[0, idx["s2"]] = [-0.1, 0.0, 0.0], [0.1, 0.0, 0.0]
    for t, angle in enumerate(np.radians(angles_deg)):
        move = 0.01 * np.array([np.sin(angle), np.cos(angle), 0.0])
        S[t + 1] = S[t]
        S[t + 1, idx["s1"]] += move
        S[t + 1, idx["s2"]] += move
    # Each state's far corners 0.3 m behind its grasped ones (sides along +y).
    S[:, idx["s3"]] = S[:, idx["s1"]] - [0.0, 0.3, 0.0]
    S[:, idx["s4"]] = S[:, idx["s2"]] - [0.0, 0.3, 0.0]
    return S


def test_rule_2_threshold_from_the_demo_ignores_one_misread_frame():
    # Held for two moves, 120 degrees counts; a single 170-degree spike does not.
    demo = _demo_moving_at([10.0, 120.0, 120.0, 30.0, 170.0, 40.0, 20.0])
    assert demo_direction_angle(demo, 0.002) == pytest.approx(120.0, abs=1e-6)
    config = SafetyConfig(tau_d_demo_margin_deg=5.0)
    assert config.for_demo(demo).tau_d_deg == pytest.approx(125.0, abs=1e-6)
    fixed = SafetyConfig(tau_d_deg=100.0, tau_d_from_demo=False)
    assert fixed.for_demo(demo).tau_d_deg == 100.0
    # Moves too short to have a direction say nothing.
    assert demo_direction_angle(demo, 0.02) == 0.0
    with pytest.raises(ValueError, match="tau_d_demo_margin_deg"):
        SafetyConfig(tau_d_demo_margin_deg=-1.0)


def test_rule_2_threshold_from_the_demo_stops_at_the_ceiling():
    # The demo's moves held at 165 degrees for two moves: the threshold is
    # the demo's angle below the ceiling and the ceiling above it.
    demo = _demo_moving_at([10.0, 165.0, 165.0, 30.0])
    assert demo_direction_angle(demo, 0.002) == pytest.approx(165.0, abs=1e-6)
    capped = SafetyConfig(tau_d_max_deg=150.0).for_demo(demo)
    assert capped.tau_d_deg == pytest.approx(150.0)
    roomy = SafetyConfig(tau_d_max_deg=170.0).for_demo(demo)
    assert roomy.tau_d_deg == pytest.approx(165.0, abs=1e-6)
    with pytest.raises(ValueError, match="tau_d_max_deg"):
        SafetyConfig(tau_d_max_deg=0.0)
