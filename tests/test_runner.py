"""The imitation runner's pieces: episode scoring from the loggers' records,
the MPC controller's frames and outputs, the gripper target integrator and
the release latch."""

import math
import types

import numpy as np
import pytest
import torch
from fabric_imitation.learning.mpc import MpcResult
from fabric_imitation.learning.safety import SafetyContext, rule_violations
from fabric_imitation.learning.state import PlanarPose, object_to_world
from fabric_imitation.scenarios.loader import LoadScenario
from fabric_imitation.systems.imitation import (
    RUNNING,
    TERMINATED_CLASSIFIER,
    MpcController,
)
from fabric_imitation.systems.station_parts import ReleaseLatch
from fabric_imitation.systems.targets import GripperTargetIntegrator
from fabric_imitation.tasks.referee import TaskSafetyContext
from fabric_imitation.tools.episode import EpisodeRun, EpisodeTransitions, ScoreEpisode
from pydrake.math import RigidTransform, RotationMatrix
from pydrake.systems.analysis import Simulator
from pydrake.systems.framework import DiagramBuilder
from pydrake.systems.primitives import ConstantVectorSource

DT = 0.2


def flat(y0=-0.1):
    """8 keypoints of a flat 30 x 30 cm cloth on the table (object frame)."""
    x = np.array([-0.15, 0.0, 0.15, 0.15, 0.15, 0.0, -0.15, -0.15])
    y = np.array([0.0, 0.0, 0.0, 0.15, 0.30, 0.30, 0.30, 0.15]) + y0
    return np.stack([x, y, np.zeros(8)], 1)


def crafted_run(pose, actions_O, true_after_shift):
    """Records as the loggers write them (row k at k * dt): row k holds the
    true keypoints at k * dt and the estimate and action of step k - 1.
    Step j moves both grasped corners by actions_O[j]; the true cloth moves
    with them (plus `true_after_shift` on every point after the last step)."""
    n = len(actions_O)
    S = [flat()]
    for a in actions_O:
        nxt = S[-1].copy()
        nxt[0] += a[:3]
        nxt[2] += a[3:]
        S.append(nxt)
    S[-1] = S[-1] + true_after_shift
    rows = n + 3  # rows 0..n + 2: steps run in rows 1..n, then settle
    logs = {
        name: np.zeros((rows, size))
        for name, size in (
            ("estimated_keypoints", 24),
            ("true_keypoints", 24),
            ("object_pose", 3),
            ("action", 6),
            ("termination", 1),
            ("steps", 1),
            ("solve_ms", 1),
            ("iterations", 1),
            ("converged", 1),
        )
    }
    for k in range(rows):
        logs["object_pose"][k] = pose
        logs["true_keypoints"][k] = object_to_world(S[min(k, n)], pose).ravel()
        if k >= 1:
            logs["estimated_keypoints"][k] = S[min(k - 1, n)].ravel()
            logs["steps"][k] = min(k, n)
            logs["termination"][k] = RUNNING if k <= n else TERMINATED_CLASSIFIER
            logs["solve_ms"][k] = 50.0 + k
            logs["iterations"][k] = k
            logs["converged"][k] = k % 2
        if 1 <= k <= n:
            a_W = PlanarPose(*pose).vector_to_world(actions_O[k - 1].reshape(2, 3))
            logs["action"][k] = a_W.ravel()
    return EpisodeRun(
        times=DT * np.arange(rows),
        logs=logs,
        final=None,
        first_action_s=0.0,
        wall_seconds=0.0,
    )


@pytest.fixture(scope="module")
def box():
    return LoadScenario(scenario_name="box")


def test_transitions_pair_each_action_with_the_states_around_it(box):
    pose = np.array([0.02, -0.1, math.radians(30)])
    actions = np.array([[0, 0, 0.02, 0, 0, 0.02], [0, -0.01, 0.02, 0, -0.01, 0.02]])
    run = crafted_run(pose, actions, 0.0)
    tr = EpisodeTransitions(run.times, run.logs)
    np.testing.assert_allclose(tr.action, actions, atol=1e-12)
    np.testing.assert_allclose(tr.true_before[0], flat(), atol=1e-12)
    np.testing.assert_allclose(
        tr.true_after[1][0], flat()[0] + actions.sum(0)[:3], atol=1e-12
    )
    # The estimate after a step is the next step's estimate, not the same.
    np.testing.assert_allclose(tr.estimated_after[0], tr.estimated_before[1])
    assert not np.allclose(tr.estimated_after[0], tr.estimated_before[0])


def test_an_executed_action_that_breaks_the_workspace_rule_is_counted(box):
    pose = np.array([0.0, -0.14, math.radians(-20)])
    ok = np.array([0, 0, 0.02, 0, 0, 0.02])
    summary = ScoreEpisode(box, None, crafted_run(pose, np.array([ok, ok]), 0.0))
    assert summary["rule_breaks_true"]["any"] == 0
    assert summary["executed_violations"] == 0
    # The second action leaves the cloth 1 m up on the true cloth and in the
    # estimate: the workspace rule (ceiling 0.5 m) is broken once in each.
    summary = ScoreEpisode(
        box, None, crafted_run(pose, np.array([ok, ok]), np.array([0, 0, 1.0]))
    )
    assert summary["rule_breaks_true"] == {
        "any": 1,
        "bounds": 0,
        "distance": 0,
        "direction": 0,
        "workspace": 1,
        "object": 0,
    }
    assert summary["executed_violations_ground_truth"] == 1
    assert summary["rule_breaks_estimated"]["workspace"] == 1
    assert summary["steps"] == 2
    assert summary["termination"] == "classifier"
    assert summary["mpc_step_ms"]["p50"] == pytest.approx(51.5)
    # Iterations and the convergence test of the two decided steps (rows 1, 2).
    assert summary["mpc_iterations"] == {"mean": 1.5, "max": 2}
    assert summary["mpc_converged_fraction"] == 0.5


def test_scoring_uses_the_logged_object_pose(box):
    # The left gripper slides over the table into the box's footprint (in the
    # object frame): the object rule fires at the object's pose, turned and
    # moved, and only once the gripper is inside.
    pose = np.array([0.05, 0.02, math.radians(60)])
    move = np.array([0.025, 0.03, 0.0, 0, 0, 0.0])
    run = crafted_run(pose, np.array([move] * 4), 0.0)
    summary = ScoreEpisode(box, None, run)
    assert summary["rule_breaks_true"]["object"] == 2
    assert summary["rule_breaks_estimated"]["object"] == 2


def test_rule_2_for_estimates_allows_for_hidden_hanging_corners(box):
    """The controller judges rule 2 also with the far corners dropped to the
    surface below them: lowering the grasped edge towards a far corner that
    f_R sees up by the gripper (the top of a hanging side) is refused."""
    S = flat()
    S[[0, 2], 2] = 0.25  # grasped edge lifted
    S[[4, 6], 1] = S[0, 1] - 0.02  # far corners seen just behind it,
    S[[4, 6], 2] = 0.25  # at its height
    a = torch.tensor([0.0, 0.01, -0.02, 0.0, 0.01, -0.02], dtype=torch.float64)
    t = torch.as_tensor(S)
    plain = TaskSafetyContext(box)
    estimated = TaskSafetyContext(box, estimated=True)
    assert not bool(rule_violations(t, a, box.safety, plain)["direction"])
    assert bool(rule_violations(t, a, box.safety, estimated)["direction"])
    # Lifting stays allowed.
    up = torch.tensor([0.0, 0.0, 0.02, 0.0, 0.0, 0.02], dtype=torch.float64)
    assert not bool(rule_violations(t, up, box.safety, estimated)["direction"])


class FixedMpc:
    """Returns one object-frame action; records the frame pose it was given."""

    def __init__(self, action_O, done=False, ctx=None):
        self.action = torch.as_tensor(action_O, dtype=torch.float32)
        self.frames = []
        self.done = done
        self.config = types.SimpleNamespace(num_samples=1, horizon=2)
        self.noises = []
        self.ctx = ctx or SafetyContext(
            edge_length=0.3,
            workspace_lower=np.array([-0.45, -0.45, -0.01]),
            workspace_upper=np.array([0.45, 0.45, 0.5]),
        )

    def finished(self, S, steps):
        return self.done

    def solve(
        self,
        S,
        *,
        step,
        seed,
        frame_pose=None,
        noise=None,
    ):
        self.frames.append(np.array(frame_pose))
        self.noises.append(noise)
        # A distinct noise distribution per step (mu = step, variance 0.5).
        carried = (torch.full((2, 6), float(step)), torch.full((2, 6), 0.5))
        return MpcResult(self.action, True, 3, 1.0, 7, 0.01, noise=carried)


def _controller(mpc, yaw):
    """The controller after its first step (its update at t = 0)."""
    dut = MpcController(mpc=mpc, num_keypoints=8, period=DT, offset=0.0, step_cap=10)
    simulator = Simulator(dut)
    context = simulator.get_mutable_context()
    dut.GetInputPort("keypoints").FixValue(context, flat().ravel())
    X_WO = RigidTransform(RotationMatrix.MakeZRotation(yaw), [0.1, -0.05, 0.0])
    dut.GetInputPort("object_pose").FixValue(context, X_WO)
    simulator.AdvanceTo(0.5 * DT)
    return dut, context


def test_mpc_controller_applies_object_frame_actions_in_the_turned_world():
    mpc = FixedMpc([0.02, 0.0, 0.01, 0.0, -0.02, 0.0])
    dut, context = _controller(mpc, math.pi / 2)
    action = dut.GetOutputPort("action").Eval(context)
    # Object x is world y, object y is world -x when turned by 90 degrees.
    np.testing.assert_allclose(action, [0, 0.02, 0.01, 0.02, 0, 0], atol=1e-7)
    np.testing.assert_allclose(mpc.frames[0], [0.1, -0.05, math.pi / 2], atol=1e-9)
    out = {
        name: dut.GetOutputPort(name).Eval(context)[0]
        for name in ("termination", "steps", "progress", "iterations", "release")
    }
    assert out == {
        "termination": RUNNING,
        "steps": 1,
        "progress": 7,
        "iterations": 3,
        "release": 0.0,
    }
    assert dut.GetOutputPort("solve_ms").Eval(context)[0] >= 0


def test_mpc_controller_carries_the_noise_distribution_to_the_next_step():
    """The MPC's (mu, variance) after a step is handed to the next step's
    solve (mpc.warm_start); the first step of an episode gets none."""
    mpc = FixedMpc(np.zeros(6))
    dut, context = _controller(mpc, 0.0)
    simulator = Simulator(dut, context)
    simulator.AdvanceTo(2.5 * DT)
    assert mpc.noises[0] is None
    for step, noise in enumerate(mpc.noises[1:]):
        mu, var = noise
        np.testing.assert_array_equal(mu, np.full((2, 6), step))
        np.testing.assert_array_equal(var, np.full((2, 6), 0.5))
    assert len(mpc.noises) == 3


def test_mpc_controller_stops_releases_and_lifts_the_grippers_clear():
    dut, context = _controller(FixedMpc(np.full(6, 0.01), done=True), 0.3)
    assert dut.GetOutputPort("termination").Eval(context)[0] == TERMINATED_CLASSIFIER
    assert dut.GetOutputPort("release").Eval(context)[0] == 1.0
    np.testing.assert_array_equal(dut.GetOutputPort("action").Eval(context), 0)
    # Then three steps up by 3 cm each (world z), then still; no step counted.
    simulator = Simulator(dut, context)
    lifts = []
    for k in range(1, 6):
        simulator.AdvanceTo((k + 0.5) * DT)
        lifts.append(dut.GetOutputPort("action").Eval(context).copy())
    np.testing.assert_allclose(lifts[:3], [[0, 0, 0.03, 0, 0, 0.03]] * 3)
    np.testing.assert_array_equal(lifts[3:], 0)
    assert dut.GetOutputPort("steps").Eval(context)[0] == 0


def test_target_integrator_starts_at_the_measured_grippers_and_ramps():
    builder = DiagramBuilder()
    dut = builder.AddSystem(GripperTargetIntegrator(step_seconds=DT))
    start = np.array([0.1, -0.2, 0.05, -0.1, -0.2, 0.05])
    action = np.array([0.02, 0.0, 0.01, -0.02, 0.0, 0.03])
    measured = builder.AddSystem(ConstantVectorSource(start))
    builder.Connect(measured.get_output_port(), dut.GetInputPort("measured"))
    source = builder.AddSystem(ConstantVectorSource(action))
    builder.Connect(source.get_output_port(), dut.GetInputPort("action"))
    diagram = builder.Build()
    simulator = Simulator(diagram)
    context = dut.GetMyContextFromRoot(simulator.get_context())
    simulator.Initialize()

    def target():
        return np.concatenate(
            [
                dut.GetOutputPort(f"{s}.ee_target").Eval(context)
                for s in ("left", "right")
            ]
        )

    np.testing.assert_allclose(target(), start, atol=1e-12)
    simulator.AdvanceTo(0.5 * DT)  # the first action, latched at t = 0, half way
    np.testing.assert_allclose(target(), start + 0.5 * action, atol=1e-9)
    simulator.AdvanceTo(DT + 0.25 * DT)  # a second segment, a quarter of the way
    np.testing.assert_allclose(target(), start + 1.25 * action, atol=1e-9)
    np.testing.assert_allclose(
        dut.GetOutputPort("goal").Eval(context), start + 2 * action, atol=1e-9
    )


def test_release_latch_stays_released():
    dut = ReleaseLatch(period=0.01)
    simulator = Simulator(dut)
    context = simulator.get_mutable_context()
    port = dut.GetInputPort("release")
    port.FixValue(context, [0.0])
    simulator.AdvanceTo(0.05)
    assert dut.GetOutputPort("released").Eval(context)[0] == 0.0
    port.FixValue(context, [1.0])
    simulator.AdvanceTo(0.1)
    assert dut.GetOutputPort("released").Eval(context)[0] == 1.0
    port.FixValue(context, [0.0])
    simulator.AdvanceTo(0.2)
    assert dut.GetOutputPort("released").Eval(context)[0] == 1.0


def test_replay_follows_a_known_path_in_a_turned_object_frame():
    from fabric_imitation.systems.imitation import ReplayController

    # The demo's grasped corners (object frame): lift 6 cm, then forward 4 cm.
    s1, s2 = np.array([-0.15, 0.0, 0.0]), np.array([0.15, 0.0, 0.0])
    steps_O = [[0, 0, 0.03]] * 2 + [[0, 0.02, 0]] * 2
    path = [np.concatenate([s1, s2])]
    for d in steps_O:
        path.append(path[-1] + np.tile(d, 2))
    dut = ReplayController(
        path=np.array(path).reshape(-1, 2, 3),
        max_step=0.03,
        num_keypoints=8,
        period=DT,
        offset=0.0,
        step_cap=20,
    )
    simulator = Simulator(dut)
    context = simulator.get_mutable_context()
    yaw = math.pi / 2
    X_WO = RigidTransform(RotationMatrix.MakeZRotation(yaw), [0.2, 0.1, 0.0])
    dut.GetInputPort("object_pose").FixValue(context, X_WO)
    S = flat(y0=0.0)
    actions = []
    for k in range(8):
        dut.GetInputPort("keypoints").FixValue(context, S.ravel())
        simulator.AdvanceTo((k + 0.5) * DT)
        if dut.GetOutputPort("termination").Eval(context)[0] != RUNNING:
            break
        a_W = dut.GetOutputPort("action").Eval(context).copy()
        actions.append(a_W)
        # The grippers follow exactly (the object frame of the state).
        a_O = PlanarPose(0.2, 0.1, yaw).vector_to_object(a_W.reshape(2, 3))
        S[0] += a_O[0]
        S[2] += a_O[1]
    expected_W = [
        PlanarPose(0.2, 0.1, yaw).vector_to_world(np.tile(d, (2, 1))).ravel()
        for d in steps_O
    ]
    np.testing.assert_allclose(actions, expected_W, atol=1e-6)  # float32 states
    assert dut.GetOutputPort("termination").Eval(context)[0] == TERMINATED_CLASSIFIER
    assert dut.GetOutputPort("release").Eval(context)[0] == 1.0
