"""The keypoint tracker (learning/tracker.py) and the estimator that runs it."""

import numpy as np
import pytest
from fabric_imitation.diagrams.imitation import DEFAULT_DEMOS, DEFAULT_PRIORS
from fabric_imitation.learning.demo_io import LoadDemo
from fabric_imitation.learning.errors import InputError
from fabric_imitation.learning.priors import load_priors
from fabric_imitation.learning.state import corner_indices
from fabric_imitation.learning.tracker import (
    MIN_MEASUREMENT_BASE,
    KeypointTracker,
    TrackerConfig,
    fit_measurement_model,
    measurement_sigma,
    project_out_of_box,
    running_median,
    track_frames,
)
from fabric_imitation.scenarios.loader import LoadScenario
from fabric_imitation.scenarios.policy import LoadPolicy
from fabric_imitation.systems.imitation import KeypointEstimator
from fabric_imitation.tools.bench import TRACKER_OFF_M, TRACKER_SURE_SPREAD_PX
from pydrake.math import RigidTransform, RotationMatrix
from pydrake.systems.sensors import ImageDepth32F, ImageGrey8U

M = 8
IDX = corner_indices(M)
FAR = [IDX["s3"], IDX["s4"]]
GRASPED = [IDX["s1"], IDX["s2"]]


def square(x0=0.0, y0=0.0, side=0.3, z=0.0):
    h = side / 2
    x = np.array([-h, 0, h, h, h, 0, -h, -h]) + x0
    y = np.array([0, 0, 0, h, side, side, side, h]) + y0
    return np.stack([x, y, np.full(8, z)], 1)


def shift_forward(S, A):
    """A stand-in f_D: every keypoint moves by the mean of the two moves."""
    S = np.asarray(S, dtype=np.float64)
    A = np.asarray(A, dtype=np.float64)
    move = (A[..., :3] + A[..., 3:]) / 2
    return S + move[..., None, :]


def tracker(**config):
    return KeypointTracker(
        forward=shift_forward, num_keypoints=M, config=TrackerConfig(**config)
    )


@pytest.fixture(scope="module")
def hang():
    priors = load_priors(DEFAULT_PRIORS)
    assert priors.num_keypoints == M
    demo = LoadDemo(DEFAULT_DEMOS / "hang")
    truth = np.load(demo.path / "ground_truth.npz")["keypoints_W"]

    def run(forward=None):
        class Swapped:  # the priors with another f_D
            def __getattr__(self, name):
                return forward if name == "forward" else getattr(priors, name)

        return track_frames(
            priors if forward is None else Swapped(),
            demo.mask,
            demo.depth,
            truth[:, GRASPED],
            TrackerConfig(enabled=True),
            object_pose=demo.object_pose,
        )

    return run, truth, priors, demo


def test_tracked_far_corners_beat_f_r_where_the_towel_hides_them(hang):
    """The shipped hang demo: where the towel's far corners hang behind the
    plate and f_R puts them more than 8 cm off, the tracked corners are at
    least twice as close to the true ones. f_D's prediction is part of it:
    with no prediction (each keypoint stays where it was), the tracked
    keypoints other than the grasped corners are further off."""
    run, truth, _, _ = hang
    tracked = run()
    e_fr = np.linalg.norm(tracked["measured"] - truth, axis=-1)[:, FAR]
    e_tr = np.linalg.norm(tracked["tracked"] - truth, axis=-1)[:, FAR]
    off = e_fr > TRACKER_OFF_M
    assert off.sum() >= 10
    assert e_tr[off].mean() <= 0.5 * e_fr[off].mean()
    others = [k for k in range(M) if k not in GRASPED]
    still = run(lambda S, A: S)
    e_still = np.linalg.norm(still["tracked"] - truth, axis=-1)[:, others]
    e_all = np.linalg.norm(tracked["tracked"] - truth, axis=-1)[:, others]
    assert e_still.mean() > e_all.mean() + 0.005


def test_tracker_follows_f_r_where_it_is_sure(hang):
    """Where f_R's heatmap is sharp (spread <= 4 px), the tracked keypoint
    stays within 1 cm of f_R's."""
    run, _, _, _ = hang
    tracked = run()
    others = [k for k in range(M) if k not in GRASPED]
    sure = tracked["spread"][:, others] <= TRACKER_SURE_SPREAD_PX
    assert sure.sum() >= 10
    gap = np.linalg.norm(tracked["tracked"] - tracked["measured"], axis=-1)[:, others]
    assert gap[sure].max() <= 0.01


def test_tracked_demo_states_are_closer_to_the_truth_on_hang(hang):
    """With a tracker, the demo's states are tracked as the imitation's are
    (the demo's own grasped-corner track standing in for grippers): the far
    corners where f_R is off come closer to the truth."""
    from fabric_imitation.diagrams.imitation import DemoStates, _Tracker
    from fabric_imitation.learning.state import world_to_object

    _, truth, priors, demo = hang
    scenario = LoadScenario(scenario_name="hang")
    plain = DemoStates(priors, demo)
    tracked = DemoStates(priors, demo, _Tracker(scenario, priors))
    truth_O = world_to_object(truth, demo.object_pose)
    e_plain = np.linalg.norm(plain - truth_O, axis=-1)[:, FAR]
    e_tracked = np.linalg.norm(tracked - truth_O, axis=-1)[:, FAR]
    off = e_plain > TRACKER_OFF_M
    assert off.sum() >= 10
    assert e_tracked[off].mean() < 0.75 * e_plain[off].mean()
    np.testing.assert_allclose(tracked[:, GRASPED], plain[:, GRASPED])


def test_first_frame_and_no_move_take_f_r_and_the_grippers():
    dut = tracker()
    z = square()
    grasped = z[GRASPED] + 0.01
    x, v = dut.step(None, z, np.full(M, 3.0), grasped=grasped)
    np.testing.assert_allclose(x[GRASPED], grasped)
    np.testing.assert_allclose(np.delete(x, GRASPED, 0), np.delete(z, GRASPED, 0))
    assert v.shape == (M, 3)
    assert (v[GRASPED] == 0).all() and (np.delete(v, GRASPED, 0) > 0).all()
    x2, _ = dut.step((x, v), z + 0.05, np.full(M, 3.0), action=None)
    np.testing.assert_allclose(x2, z + 0.05)


def test_fusion_weighs_prediction_and_reading_by_their_errors():
    """Per keypoint: gain g = v- / (v- + r), x = x- + g (z - x-), v = (1 - g)
    v-, with v- = v + q^2 and r = (base + per_px2 spread^2)^2. A diffuse
    heatmap leaves the keypoint near where f_D puts it, a sharp one near
    f_R's reading."""
    config = dict(process_noise=0.02, measurement_base=0.006, measurement_per_px2=3e-4)
    dut = tracker(**config)
    x0 = square()
    v0 = np.linspace(1e-5, 1e-3, M)
    move = np.array([0.01, 0.0, 0.0, 0.01, 0.0, 0.0])
    predicted = x0 + [0.01, 0.0, 0.0]
    reading = predicted + [0.0, 0.10, 0.0]
    spread = np.array([40.0] * 4 + [0.0, 2.0, 4.0, 8.0])
    x, v = dut.step((x0, v0), reading, spread, action=move)
    prior = v0 + 0.02**2
    r = (0.006 + 3e-4 * spread**2) ** 2
    gain = prior / (prior + r)
    np.testing.assert_allclose(
        x, predicted + gain[:, None] * (reading - predicted), atol=1e-7
    )
    np.testing.assert_allclose(
        v, ((1 - gain) * prior)[:, None].repeat(3, 1), rtol=1e-12
    )
    assert (gain[:4] < 0.01).all() and (gain[4:6] > 0.9).all()


def test_a_vertical_error_model_weighs_height_apart_from_place():
    """With f_R's vertical error given apart from its horizontal one, a
    diffuse reading moves the estimate in x and y as far as its horizontal
    error allows and hardly at all in z; without it, the same in all three."""
    flat = dict(process_noise=0.02, measurement_base=0.006, measurement_per_px2=3e-4)
    split = dict(
        process_noise=0.02,
        measurement_base=0.008,
        measurement_per_px2=6e-5,
        measurement_vertical_base=0.001,
        measurement_vertical_per_px2=3e-4,
    )
    x0 = square()
    v0 = np.full(M, 1e-4)
    move = np.zeros(6)
    reading = x0 + [0.05, 0.0, 0.10]  # f_R: 5 cm aside, 10 cm too high
    spread = np.full(M, 20.0)
    x_flat, v_flat = tracker(**flat).step((x0, v0), reading, spread, action=move)
    x_split, v_split = tracker(**split).step((x0, v0), reading, spread, action=move)
    prior = 1e-4 + 0.02**2
    g_h = prior / (prior + (0.008 + 6e-5 * 400) ** 2)
    g_z = prior / (prior + (0.001 + 3e-4 * 400) ** 2)
    np.testing.assert_allclose(x_split[:, 0] - x0[:, 0], g_h * 0.05, atol=1e-7)
    np.testing.assert_allclose(x_split[:, 2] - x0[:, 2], g_z * 0.10, atol=1e-7)
    np.testing.assert_allclose(v_split[:, 0], v_split[:, 1])
    assert g_h > 0.25 and g_z < 0.05
    # The flat model moves x and z by the same fraction of the offset.
    np.testing.assert_allclose(
        (x_flat - x0)[:, 0] / 0.05, (x_flat - x0)[:, 2] / 0.10, atol=1e-6
    )
    assert np.all(v_flat[:, 0] == v_flat[:, 2])
    with pytest.raises(ValueError, match="go together"):
        TrackerConfig(measurement_vertical_base=0.001)
    with pytest.raises(ValueError, match="vertical_base must be positive"):
        TrackerConfig(measurement_vertical_base=0.0, measurement_vertical_per_px2=1e-4)


def test_a_broken_estimate_starts_again_from_f_r():
    dut = tracker()
    z = square()
    bad = (np.full((M, 3), np.nan), np.full(M, 1e-4))
    move = np.zeros(6)
    x, v = dut.step(bad, z, np.full(M, 3.0), action=move)
    np.testing.assert_allclose(x, z)
    assert np.all(np.isfinite(v))


def test_measurement_model_and_its_fit():
    config = TrackerConfig(measurement_base=0.005, measurement_per_px2=3e-4)
    np.testing.assert_allclose(measurement_sigma([0.0, 10.0], config), [0.005, 0.035])
    s = np.linspace(2, 30, 50)
    base, per = fit_measurement_model(s, 0.004 + 2e-4 * s**2)
    assert base == pytest.approx(0.004, abs=1e-9)
    assert per == pytest.approx(2e-4, rel=1e-6)
    # An error that is about zero for a sharp heatmap: the base is held at
    # the floor and the slope fitted alone.
    base, per = fit_measurement_model(s, 3e-4 * s**2 - 0.002)
    assert base == MIN_MEASUREMENT_BASE
    assert 0 < per < 3e-4
    with pytest.raises(ValueError, match="at least two"):
        fit_measurement_model([1.0], [0.01])


def test_projection_puts_points_inside_the_object_on_its_nearest_face():
    size = [0.14, 0.09, 0.06]
    p = np.array(
        [
            [0.0, 0.0, 0.055],  # under the top -> top
            [0.068, 0.0, 0.03],  # by the +x face -> +x face
            [0.0, -0.04, 0.02],  # by the -y face -> -y face
            [0.2, 0.0, 0.03],  # outside: stays
            [0.0, 0.0, 0.07],  # above: stays
        ]
    )
    q = project_out_of_box(p, size)
    np.testing.assert_allclose(q[0], [0.0, 0.0, 0.06])
    np.testing.assert_allclose(q[1], [0.07, 0.0, 0.03])
    np.testing.assert_allclose(q[2], [0.0, -0.045, 0.02])
    np.testing.assert_allclose(q[3:], p[3:])


def test_shapes_and_settings_are_checked():
    dut = tracker()
    with pytest.raises(ValueError, match=r"keypoints must be \(8, 3\)"):
        dut.step(None, np.zeros((4, 3)), np.zeros(4))
    with pytest.raises(ValueError, match=r"spreads must be \(8,\)"):
        dut.step(None, np.zeros((8, 3)), np.zeros(3))
    with pytest.raises(InputError, match="tracker.process_noise"):
        LoadPolicy(policy_text="tracker: {process_noise: 0}")


class SpreadPriors:
    """f_R stand-in: fixed keypoints and spreads."""

    def __init__(self, points, spread):
        self.points, self.spread = points, spread

    def keypoints_and_spread(self, mask, depth):
        return self.points, self.spread


def left_forward(S, A):
    """A stand-in f_D: every keypoint moves by the left gripper's move."""
    S = np.asarray(S, dtype=np.float64)
    return S + np.asarray(A, dtype=np.float64)[..., None, :3]


def _estimator(priors, **kwargs):
    dut = KeypointEstimator(
        priors=priors, num_keypoints=M, width=32, height=24, period=0.2, **kwargs
    )
    context = dut.CreateDefaultContext()
    dut.GetInputPort("mask").FixValue(context, ImageGrey8U(32, 24))
    dut.GetInputPort("depth").FixValue(context, ImageDepth32F(32, 24))
    return dut, context


def _update(dut, context, grippers=None):
    if grippers is not None:
        dut.GetInputPort("grippers").FixValue(context, np.ravel(grippers))
    state = context.get_discrete_state().Clone()
    dut.CalcForcedDiscreteVariableUpdate(context, state)
    context.SetDiscreteState(state)
    return dut.GetOutputPort("keypoints").Eval(context).reshape(M, 3)


def test_estimator_tracks_with_the_grippers_measured_move():
    """The object turned 30 degrees and moved: the second update predicts
    from the first estimate and the grippers' move, both in the object
    frame; a corner f_R cannot see (diffuse heatmap) stays where the
    prediction puts it, not where f_R reads it. A fresh context starts
    again from f_R."""
    from fabric_imitation.learning.state import object_to_world

    pose = np.array([0.1, -0.14, np.radians(30.0)])
    X_WO = RigidTransform(RotationMatrix.MakeZRotation(pose[2]), [*pose[:2], 0.0])
    start_O = square(0.0, 0.2)
    start_W = object_to_world(start_O, pose)
    priors = SpreadPriors(start_W, np.full(M, 3.0))
    dut, context = _estimator(
        priors,
        tracker=KeypointTracker(
            forward=left_forward, num_keypoints=M, config=TrackerConfig()
        ),
    )
    dut.GetInputPort("object_pose").FixValue(context, X_WO)
    first = _update(dut, context, start_W[GRASPED])
    np.testing.assert_allclose(first, start_O, atol=1e-9)
    # The left gripper moves 2 cm along the object's y, the right one does
    # not: left_forward moves every keypoint by the left move.
    move_O = np.array([0.0, 0.02, 0.0])
    grippers_O = start_O[GRASPED] + [move_O, [0.0, 0.0, 0.0]]
    grippers_W = object_to_world(grippers_O, pose)
    # f_R's guess, up by 8 cm, diffuse where it cannot see the far side.
    priors.points = object_to_world(start_O + [0.0, 0.0, 0.08], pose)
    priors.spread = np.array([3.0] * 4 + [40.0] * 4)
    second = _update(dut, context, grippers_W)
    np.testing.assert_allclose(second[GRASPED], grippers_O, atol=1e-9)
    np.testing.assert_allclose(second[4:], start_O[4:] + move_O, atol=0.003)
    fresh = dut.CreateDefaultContext()
    dut.GetInputPort("mask").FixValue(fresh, ImageGrey8U(32, 24))
    dut.GetInputPort("depth").FixValue(fresh, ImageDepth32F(32, 24))
    dut.GetInputPort("object_pose").FixValue(fresh, X_WO)
    again = _update(dut, fresh, grippers_W)
    np.testing.assert_allclose(again[4:], start_O[4:] + [0.0, 0.0, 0.08], atol=1e-9)


def test_grasped_corners_from_f_r_where_switched_off():
    """With `grasped_from_grippers` false, s1 and s2 are f_R's reading fused
    with the prediction like every other keypoint (the grippers' move still
    drives the prediction); with it, they are the measured grippers."""
    start = square(0.0, 0.2)
    grippers = start[GRASPED] + [[0.0, 0.02, 0.0], [0.0, 0.0, 0.0]]
    seen = start + [0.0, 0.0, 0.01]  # f_R 1 cm up, everywhere, sharp
    for from_grippers in (True, False):
        priors = SpreadPriors(start, np.full(M, 3.0))
        tracker = KeypointTracker(
            forward=left_forward, num_keypoints=M, config=TrackerConfig()
        )
        dut, context = _estimator(
            priors, tracker=tracker, grasped_from_grippers=from_grippers
        )
        dut.GetInputPort("object_pose").FixValue(context, RigidTransform())
        _update(dut, context, start[GRASPED])
        priors.points = seen
        second = _update(dut, context, grippers)
        if from_grippers:
            np.testing.assert_allclose(second[GRASPED], grippers, atol=1e-9)
        else:
            predicted = start[GRASPED] + [0.0, 0.02, 0.0]
            # Between the prediction and f_R's reading, neither exactly.
            assert np.all(np.abs(second[GRASPED] - predicted).max(-1) > 1e-4)
            assert np.all(np.abs(second[GRASPED] - seen[GRASPED]).max(-1) > 1e-4)


def test_estimator_without_grippers_gives_f_r_reading():
    """No grippers input: no move to predict with, so each update is f_R's
    reading as it is."""
    start = square(0.0, 0.2)
    priors = SpreadPriors(start, np.full(M, 3.0))
    dut, context = _estimator(
        priors,
        tracker=KeypointTracker(
            forward=left_forward, num_keypoints=M, config=TrackerConfig()
        ),
    )
    dut.GetInputPort("object_pose").FixValue(context, RigidTransform())
    np.testing.assert_allclose(_update(dut, context), start, atol=1e-9)
    priors.points = start + [0.0, 0.0, 0.08]
    priors.spread = np.full(M, 40.0)
    np.testing.assert_allclose(_update(dut, context), priors.points, atol=1e-9)


def test_the_scenario_switches_the_tracker_on():
    from fabric_imitation.diagrams.imitation import _KeypointEstimator

    class Priors:
        num_keypoints = M
        forward = staticmethod(left_forward)

    scenario = LoadScenario(scenario_name="box")
    assert _KeypointEstimator(scenario, Priors(), 0.0)._tracker is not None
    scenario = LoadScenario(
        scenario_name="box", policy=LoadPolicy(policy_text="tracker: {enabled: false}")
    )
    assert _KeypointEstimator(scenario, Priors(), 0.0)._tracker is None
    with pytest.raises(ValueError, match="tracker has 8 keypoints"):
        KeypointEstimator(
            priors=Priors(),
            num_keypoints=12,
            width=32,
            height=24,
            period=0.2,
            tracker=tracker(),
        )


def test_running_median_drops_a_one_frame_spike_and_keeps_a_ramp():
    ramp = np.linspace(0, 1, 9)[:, None] * np.array([1.0, 2.0, 3.0])
    np.testing.assert_allclose(running_median(ramp, 3), ramp)
    np.testing.assert_allclose(running_median(ramp, 5), ramp)
    spiked = ramp.copy()
    spiked[4] += [0.0, 0.0, -2.0]  # one frame read far off
    out = running_median(spiked, 3)
    step = np.abs(ramp[1] - ramp[0])
    # Every row within one frame's move of the ramp: the spike is gone.
    assert np.all(np.abs(out - ramp) <= step + 1e-12)
    # The ends are kept (a window centred there has one frame), and 1 is a copy.
    spiked[0] += 0.1
    assert running_median(spiked, 3)[0] == pytest.approx(spiked[0])
    np.testing.assert_array_equal(running_median(spiked, 1), spiked)
    with pytest.raises(ValueError, match="demo_grasped_median"):
        TrackerConfig(demo_grasped_median=2)


def test_the_demos_grasped_track_drops_f_rs_one_frame_misread_on_hang(hang):
    """The shipped hang demo: f_R reads a grasped corner more than 10 cm
    from the true one in a frame between good ones; with the demo's
    grasped-corner track the running median of three frames, that frame's
    corner is within 2 cm of the truth, and the other frames' move by at
    most 1 cm."""
    import dataclasses as dc

    from fabric_imitation.diagrams.imitation import DemoStates, _Tracker
    from fabric_imitation.learning.state import world_to_object

    _, truth, priors, demo = hang
    scenario = LoadScenario(scenario_name="hang")
    tracker = _Tracker(scenario, priors)
    raw = DemoStates(priors, demo, tracker)
    tracker.config = dc.replace(tracker.config, demo_grasped_median=3)
    median = DemoStates(priors, demo, tracker)
    truth_O = world_to_object(truth, demo.object_pose)[:, GRASPED]
    e_raw = np.linalg.norm(raw[:, GRASPED] - truth_O, axis=-1).max(1)
    e_median = np.linalg.norm(median[:, GRASPED] - truth_O, axis=-1).max(1)
    misread = e_raw > 0.10
    assert 1 <= misread.sum() <= 2
    assert e_median[misread].max() <= 0.02
    moved = np.linalg.norm(median[:, GRASPED] - raw[:, GRASPED], axis=-1).max(1)
    assert moved[~misread].max() <= 0.012
