"""LeafSystems of the imitation diagram: keypoint estimator, demo reward, MPC
controller, success monitor. Torch objects come in through the constructor
(built elsewhere); per-run values live in the Context."""

import logging
import time

import numpy as np
import torch
from fabric_imitation.learning.state import corner_indices, world_to_object
from pydrake.common.value import AbstractValue
from pydrake.math import RigidTransform
from pydrake.systems.framework import BasicVector, EventStatus, LeafSystem
from pydrake.systems.sensors import ImageDepth32F, ImageGrey8U

_LOG = logging.getLogger("fabric_imitation.mpc")

# MpcController status codes (output "status"[1]).
RUNNING, TERMINATED_CLASSIFIER, TERMINATED_INFEASIBLE, TERMINATED_STEP_CAP = 0, 1, 2, 3
TERMINATION_NAMES = {
    RUNNING: "running",
    TERMINATED_CLASSIFIER: "classifier",
    TERMINATED_INFEASIBLE: "infeasible",
    TERMINATED_STEP_CAP: "step cap",
}


def _pose_vector(X_WO: RigidTransform) -> np.ndarray:
    """[x, y, yaw] of an object pose on the table."""
    R = X_WO.rotation().matrix()
    return np.array([*X_WO.translation()[:2], np.arctan2(R[1, 0], R[0, 0])])


class KeypointEstimator(LeafSystem):
    """f_R on the camera's fabric mask and depth -> M keypoints in the object
    frame, updated once per control step (periodic event).

    The grasped corners s1, s2 are where the grippers hold them, so when the
    optional ``grippers`` input is connected they are taken from it (the
    robot's own measurement) instead of from the image, where a corner can
    hide under the cloth.

    Input ports: ``mask`` (ImageGrey8U), ``depth`` (ImageDepth32F),
    ``object_pose`` (RigidTransform X_WO), ``grippers`` (6, optional: left
    and right gripper positions in world).
    Output ports: ``keypoints`` (3M, object frame; from state).

    Args:
        priors: anything with ``keypoints(mask, depth) -> (M, 3)`` world points.
    """

    def __init__(
        self,
        *,
        priors,
        num_keypoints: int,
        width: int,
        height: int,
        period: float,
        offset: float = 0.0,
    ):
        super().__init__()
        self._priors = priors
        self._mask = self.DeclareAbstractInputPort(
            "mask", AbstractValue.Make(ImageGrey8U(width, height))
        )
        self._depth = self.DeclareAbstractInputPort(
            "depth", AbstractValue.Make(ImageDepth32F(width, height))
        )
        self._pose = self.DeclareAbstractInputPort(
            "object_pose", AbstractValue.Make(RigidTransform())
        )
        self._grippers = self.DeclareVectorInputPort("grippers", 6)
        self._corners = [corner_indices(num_keypoints)[k] for k in ("s1", "s2")]
        self._state = self.DeclareDiscreteState(3 * num_keypoints)
        self.DeclarePeriodicDiscreteUpdateEvent(period, offset, self._update)
        self.DeclareForcedDiscreteUpdateEvent(self._update)
        self.DeclareStateOutputPort("keypoints", self._state)

    def _update(self, context, discrete_state) -> EventStatus:
        mask = self._mask.Eval(context).data[:, :, 0]
        depth = self._depth.Eval(context).data[:, :, 0]
        p_W = np.array(self._priors.keypoints(mask, depth))
        if self._grippers.HasValue(context):
            p_W[self._corners] = self._grippers.Eval(context).reshape(2, 3)
        p_O = world_to_object(p_W, _pose_vector(self._pose.Eval(context)))
        discrete_state.get_mutable_vector(self._state).SetFromVector(p_O.ravel())
        return EventStatus.Succeeded()


class DemoReward(LeafSystem):
    """The demo's state-alignment reward of the current keypoints.

    Input ports: ``keypoints`` (3M, object frame).
    Output ports: ``progress`` (J), ``reward`` (R_E), ``done`` (termination
    classifier, 0/1).
    """

    def __init__(self, *, demo, num_keypoints: int):
        super().__init__()
        self._demo = demo
        self._m = num_keypoints
        self._kp = self.DeclareVectorInputPort("keypoints", 3 * num_keypoints)
        self.DeclareVectorOutputPort("progress", 1, self._calc_progress)
        self.DeclareVectorOutputPort("reward", 1, self._calc_reward)
        self.DeclareVectorOutputPort("done", 1, self._calc_done)

    def _S(self, context) -> torch.Tensor:
        return torch.as_tensor(
            self._kp.Eval(context).reshape(self._m, 3), dtype=torch.float32
        )

    def _calc_progress(self, context, output: BasicVector):
        J, _ = self._demo.progress(self._S(context)[None])
        output.SetFromVector([float(J[0])])

    def _calc_reward(self, context, output: BasicVector):
        r, _ = self._demo.reward(self._S(context)[None])
        output.SetFromVector([float(r[0])])

    def _calc_done(self, context, output: BasicVector):
        output.SetFromVector([float(self._demo.done(self._S(context))[()])])


class MpcController(LeafSystem):
    """Sampling MPC following the demo (learning/mpc.py), once per control step.

    Ends the episode (release, zero action) when the termination classifier
    fires, when no feasible action exists, or at the step cap.

    Input ports: ``keypoints`` (3M, object frame), ``object_pose``
    (RigidTransform X_WO).
    Output ports: ``action`` (6, world-frame relative moves [a_L, a_R]),
    ``release`` (1), ``status`` (4: feasible, termination code, steps taken,
    milliseconds of the last solve) -- all from state.
    """

    def __init__(
        self,
        *,
        mpc,
        num_keypoints: int,
        period: float,
        offset: float,
        step_cap: int,
        seed: int = 0,
    ):
        super().__init__()
        self._mpc = mpc
        self._m = num_keypoints
        self._cap = step_cap
        self._seed = seed
        self._kp = self.DeclareVectorInputPort("keypoints", 3 * num_keypoints)
        self._pose = self.DeclareAbstractInputPort(
            "object_pose", AbstractValue.Make(RigidTransform())
        )
        self._action = self.DeclareDiscreteState(6)
        self._release = self.DeclareDiscreteState(1)
        self._status = self.DeclareDiscreteState(4)
        self._progress = self.DeclareDiscreteState(1)  # J of the last step
        self.DeclarePeriodicDiscreteUpdateEvent(period, offset, self._update)
        self.DeclareStateOutputPort("action", self._action)
        self.DeclareStateOutputPort("release", self._release)
        self.DeclareStateOutputPort("status", self._status)

    def _update(self, context, discrete_state) -> EventStatus:
        status = context.get_discrete_state(self._status).value().copy()
        if status[1] != RUNNING:
            discrete_state.get_mutable_vector(self._action).SetZero()
            return EventStatus.Succeeded()
        S = torch.as_tensor(
            self._kp.Eval(context).reshape(self._m, 3), dtype=torch.float32
        )
        steps = int(status[2])
        t0 = time.perf_counter()
        code = RUNNING
        if bool(self._mpc.demo.done(S)):
            code = TERMINATED_CLASSIFIER
        elif steps >= self._cap:
            code = TERMINATED_STEP_CAP
        action_W = np.zeros(6)
        feasible = 1.0
        if code == RUNNING:
            previous = int(context.get_discrete_state(self._progress).value()[0])
            result = self._mpc.solve(
                S, step=steps, seed=self._seed, previous_progress=previous
            )
            discrete_state.get_mutable_vector(self._progress).SetFromVector(
                [result.progress]
            )
            if result.feasible:
                yaw = _pose_vector(self._pose.Eval(context))[2]
                c, s = np.cos(yaw), np.sin(yaw)
                R = np.array([[c, -s, 0], [s, c, 0], [0, 0, 1]])
                action_W = (result.action.numpy().reshape(2, 3) @ R.T).ravel()
                steps += 1
            else:
                code, feasible = TERMINATED_INFEASIBLE, 0.0
                _LOG.warning(
                    "no feasible action at step %d (of %d sampled sequences, "
                    "how many break each rule: %s); releasing",
                    steps,
                    self._mpc.config.num_samples,
                    result.blocked_by,
                )
        ms = 1000 * (time.perf_counter() - t0)
        discrete_state.get_mutable_vector(self._action).SetFromVector(action_W)
        discrete_state.get_mutable_vector(self._release).SetFromVector(
            [1.0 if code != RUNNING else 0.0]
        )
        discrete_state.get_mutable_vector(self._status).SetFromVector(
            [feasible, code, steps, ms]
        )
        return EventStatus.Succeeded()


class SuccessMonitor(LeafSystem):
    """Task success judged on simulation ground truth (for evaluation only).

    Input ports: ``positions`` (3N cloth vertices, world).
    Output ports: ``success`` (1).

    Args:
        judge: callable(positions (N, 3)) -> bool.
    """

    def __init__(self, *, judge, num_vertices: int):
        super().__init__()
        self._judge = judge
        self._p = self.DeclareVectorInputPort("positions", 3 * num_vertices)
        self.DeclareVectorOutputPort("success", 1, self._calc)

    def _calc(self, context, output: BasicVector):
        ok = self._judge(self._p.Eval(context).reshape(-1, 3))
        output.SetFromVector([1.0 if ok else 0.0])
