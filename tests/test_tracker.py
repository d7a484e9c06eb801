"""The keypoint tracker (learning/tracker.py) and the estimator that runs it."""

import numpy as np
import pytest
from fabric_imitation.diagrams.imitation import DEFAULT_DEMOS, DEFAULT_PRIORS
from fabric_imitation.learning.demo_io import LoadDemo
from fabric_imitation.learning.errors import InputError
from fabric_imitation.learning.priors import load_priors
from fabric_imitation.learning.state import corner_indices
from fabric_imitation.learning.tracker import (
    KeypointTracker,
    TrackerConfig,
    fit_measurement_model,
    measurement_sigma,
    project_out_of_box,
    track_frames,
)
from fabric_imitation.scenarios.loader import LoadScenario
from fabric_imitation.systems.imitation import KeypointEstimator
from pydrake.math import RigidTransform
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
def hang_run():
    priors = load_priors(DEFAULT_PRIORS)
    demo = LoadDemo(DEFAULT_DEMOS / "hang")
    truth = np.load(demo.path / "ground_truth.npz")["keypoints_W"]
    run = track_frames(
        priors,
        demo.mask,
        demo.depth,
        truth[:, GRASPED],
        TrackerConfig(enabled=True),
        object_pose=demo.object_pose,
    )
    return run, truth


def test_tracked_far_corners_beat_f_r_where_the_towel_hides_them(hang_run):
    """The shipped hang demo: where the towel's far corners hang behind the
    plate and f_R puts them more than 8 cm off, the tracked corners are at
    least twice as close to the true ones."""
    run, truth = hang_run
    e_fr = np.linalg.norm(run["measured"] - truth, axis=-1)[:, FAR]
    e_tr = np.linalg.norm(run["tracked"] - truth, axis=-1)[:, FAR]
    off = e_fr > 0.08
    assert off.sum() >= 10
    assert e_tr[off].mean() <= 0.5 * e_fr[off].mean()


def test_tracker_follows_f_r_where_it_is_sure(hang_run):
    """Where f_R's heatmap is sharp (spread <= 4 px), the tracked keypoint
    stays within 1 cm of f_R's."""
    run, _ = hang_run
    others = [k for k in range(M) if k not in GRASPED]
    sure = run["spread"][:, others] <= 4.0
    assert sure.sum() >= 10
    gap = np.linalg.norm(run["tracked"] - run["measured"], axis=-1)[:, others]
    assert gap[sure].max() <= 0.01


def test_first_frame_and_no_move_take_f_r_and_the_grippers():
    dut = tracker()
    z = square()
    grasped = z[GRASPED] + 0.01
    x, v = dut.step(None, z, np.full(M, 3.0), grasped=grasped)
    np.testing.assert_allclose(x[GRASPED], grasped)
    np.testing.assert_allclose(np.delete(x, GRASPED, 0), np.delete(z, GRASPED, 0))
    assert (v[GRASPED] == 0).all() and (np.delete(v, GRASPED) > 0).all()
    x2, _ = dut.step((x, v), z + 0.05, np.full(M, 3.0), action=None)
    np.testing.assert_allclose(x2, z + 0.05)


def test_fusion_weighs_prediction_and_reading_by_their_errors():
    """A diffuse heatmap leaves the keypoint where f_D puts it; a sharp one
    takes f_R's reading; the variance shrinks on fusion."""
    dut = tracker(process_noise=0.02)
    x0 = square()
    v0 = np.full(M, 1e-4)
    move = np.array([0.01, 0.0, 0.0, 0.01, 0.0, 0.0])
    predicted = x0 + [0.01, 0.0, 0.0]
    reading = predicted + [0.0, 0.10, 0.0]
    spread = np.array([40.0] * 4 + [0.0] * 4)
    x, v = dut.step((x0, v0), reading, spread, action=move)
    np.testing.assert_allclose(x[:4], predicted[:4], atol=0.002)
    np.testing.assert_allclose(x[4:], reading[4:], atol=0.012)
    prior = v0 + 0.02**2
    assert (v < prior).all()


def test_measurement_model_and_its_fit():
    config = TrackerConfig(measurement_base=0.005, measurement_per_px2=3e-4)
    np.testing.assert_allclose(measurement_sigma([0.0, 10.0], config), [0.005, 0.035])
    s = np.linspace(2, 30, 50)
    base, per = fit_measurement_model(s, 0.004 + 2e-4 * s**2)
    assert base == pytest.approx(0.004, abs=1e-9)
    assert per == pytest.approx(2e-4, rel=1e-6)
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
        LoadScenario(scenario_name="hang", scenario_text="tracker: {process_noise: 0}")


class SpreadPriors:
    """f_R stand-in: fixed keypoints and spreads."""

    def __init__(self, points, spread):
        self.points, self.spread = points, spread

    def keypoints_and_spread(self, mask, depth):
        return self.points, self.spread


def test_estimator_tracks_with_the_grippers_measured_move():
    """With a tracker, the second update predicts from the first estimate and
    the grippers' move; a corner f_R cannot see (diffuse heatmap) stays
    where the prediction puts it, not where f_R reads it."""
    start = square(0.0, 0.2)
    priors = SpreadPriors(start, np.full(M, 3.0))
    dut = KeypointEstimator(
        priors=priors,
        num_keypoints=M,
        width=32,
        height=24,
        period=0.2,
        tracker=tracker(),
    )
    context = dut.CreateDefaultContext()
    dut.GetInputPort("mask").FixValue(context, ImageGrey8U(32, 24))
    dut.GetInputPort("depth").FixValue(context, ImageDepth32F(32, 24))
    dut.GetInputPort("object_pose").FixValue(context, RigidTransform())
    grippers = dut.GetInputPort("grippers")

    def update(g):
        grippers.FixValue(context, np.ravel(g))
        state = context.get_discrete_state().Clone()
        dut.CalcForcedDiscreteVariableUpdate(context, state)
        context.SetDiscreteState(state)
        return dut.GetOutputPort("keypoints").Eval(context).reshape(M, 3)

    first = update(start[GRASPED])
    np.testing.assert_allclose(first, start, atol=1e-9)
    move = np.array([0.0, 0.02, 0.0])
    # f_R's guess, up by 8 cm, diffuse where it cannot see the far side.
    priors.points = start + [0.0, 0.0, 0.08]
    priors.spread = np.array([3.0] * 4 + [40.0] * 4)
    second = update(start[GRASPED] + move)
    np.testing.assert_allclose(second[GRASPED], start[GRASPED] + move, atol=1e-9)
    np.testing.assert_allclose(second[4:], start[4:] + move, atol=0.003)
    with pytest.raises(ValueError, match="tracker has 8 keypoints"):
        KeypointEstimator(
            priors=priors,
            num_keypoints=12,
            width=32,
            height=24,
            period=0.2,
            tracker=tracker(),
        )
