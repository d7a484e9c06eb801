"""LeafSystems of the imitation diagram: keypoint estimator, demo reward, MPC
controller, and the object pose as a vector for loggers. Torch objects come
in through the constructor (built elsewhere); per-run values live in the
Context."""

import logging
import time

import numpy as np
import torch
from fabric_imitation.learning.state import (
    PlanarPose,
    corner_indices,
    object_to_world,
    world_to_object,
)
from fabric_imitation.learning.tracker import KeypointTracker
from fabric_imitation.systems.referee import HALT_COLLISION, HALT_RULE_BREAK
from pydrake.common.value import AbstractValue
from pydrake.math import RigidTransform
from pydrake.systems.framework import BasicVector, EventStatus, LeafSystem
from pydrake.systems.sensors import ImageDepth32F, ImageGrey8U

_LOG = logging.getLogger("fabric_imitation.mpc")

# MpcController termination codes (output "termination").
RUNNING, TERMINATED_CLASSIFIER, TERMINATED_INFEASIBLE, TERMINATED_STEP_CAP = 0, 1, 2, 3
# Ended by the benchmark's referee (systems/referee.py, input ``halt``).
TERMINATED_RULE_BREAK, TERMINATED_COLLISION = 4, 5
TERMINATION_NAMES = {
    RUNNING: "running",
    TERMINATED_CLASSIFIER: "classifier",
    TERMINATED_INFEASIBLE: "infeasible",
    TERMINATED_STEP_CAP: "step cap",
    TERMINATED_RULE_BREAK: "rule_break",
    TERMINATED_COLLISION: "collision",
}


class PlanarPoseVector(LeafSystem):
    """The object pose as a vector [x, y, yaw] (for loggers and plots).

    Input ports: ``pose`` (RigidTransform X_WO).
    Output ports: ``vector`` (3).
    """

    def __init__(self):
        super().__init__()
        self._pose = self.DeclareAbstractInputPort(
            "pose", AbstractValue.Make(RigidTransform())
        )
        self.DeclareVectorOutputPort(
            "vector",
            3,
            lambda c, o: o.SetFromVector(
                PlanarPose.FromRigidTransform(self._pose.Eval(c))
            ),
        )


def _DeclareCameraInputs(system: LeafSystem, width: int, height: int):
    """The ``mask`` (ImageGrey8U), ``depth`` (ImageDepth32F) and
    ``object_pose`` (RigidTransform) input ports of a system that reads the
    station's camera."""
    return (
        system.DeclareAbstractInputPort(
            "mask", AbstractValue.Make(ImageGrey8U(width, height))
        ),
        system.DeclareAbstractInputPort(
            "depth", AbstractValue.Make(ImageDepth32F(width, height))
        ),
        system.DeclareAbstractInputPort(
            "object_pose", AbstractValue.Make(RigidTransform())
        ),
    )


class KeypointEstimator(LeafSystem):
    """f_R on the camera's fabric mask and depth -> M keypoints in the object
    frame, updated once per control step (periodic event).

    The grasped corners s1, s2 are where the grippers hold them, so when the
    optional ``grippers`` input is connected they are taken from it (the
    robot's own measurement) instead of from the image, where a corner can
    hide under the cloth, unless ``grasped_from_grippers`` is false.

    With a ``tracker`` (learning/tracker.py), the ``keypoints`` output is
    f_R's reading fused with f_D's prediction from the previous estimate and
    the grippers' measured move since the last update, so a corner hidden
    under the cloth or behind the object keeps a predicted place (estimate
    and variance are discrete state). Without the ``grippers`` input there
    is no move to predict with, and the output is f_R's reading.

    Input ports: ``mask`` (ImageGrey8U), ``depth`` (ImageDepth32F),
    ``object_pose`` (RigidTransform X_WO), ``grippers`` (6, optional: left
    and right gripper positions in world).
    Output ports: ``keypoints`` (3M, object frame; from state).

    Args:
        priors: anything with ``keypoints(mask, depth) -> (M, 3)`` world
            points (and ``keypoints_and_spread`` with a tracker).
        tracker: a KeypointTracker in the object frame, or None.
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
        tracker: KeypointTracker | None = None,
        grasped_from_grippers: bool = True,
    ):
        super().__init__()
        self._priors = priors
        self._tracker = tracker
        self._grasped_from_grippers = grasped_from_grippers
        if tracker is not None and tracker.num_keypoints != num_keypoints:
            raise ValueError(
                f"the tracker has {tracker.num_keypoints} keypoints, the "
                f"estimator {num_keypoints}"
            )
        self._mask, self._depth, self._pose = _DeclareCameraInputs(self, width, height)
        self._grippers = self.DeclareVectorInputPort("grippers", 6)
        idx = corner_indices(num_keypoints)
        self._corners = [idx[k] for k in ("s1", "s2")]
        self._state = self.DeclareDiscreteState(3 * num_keypoints)
        # The tracker's estimate is the `keypoints` state; its variance per
        # keypoint and axis, the grippers (world) and the object pose [x, y,
        # yaw_rad] at the last update (NaN before the first). The variance
        # is the same in x and y, so it holds in a frame turned about z.
        self._variance = self.DeclareDiscreteState(
            BasicVector(np.full(3 * num_keypoints, np.nan))
        )
        self._last_grippers = self.DeclareDiscreteState(BasicVector(np.full(6, np.nan)))
        self._last_pose = self.DeclareDiscreteState(BasicVector(np.full(3, np.nan)))
        self.DeclarePeriodicDiscreteUpdateEvent(period, offset, self._update)
        self.DeclareForcedDiscreteUpdateEvent(self._update)
        self.DeclareStateOutputPort("keypoints", self._state)

    def _update(self, context, discrete_state) -> EventStatus:
        mask = self._mask.Eval(context).data[:, :, 0]
        depth = self._depth.Eval(context).data[:, :, 0]
        if self._tracker is None:
            p_W, spread = np.array(self._priors.keypoints(mask, depth)), None
        else:
            p_W, spread = self._priors.keypoints_and_spread(mask, depth)
            p_W = np.array(p_W)
        grippers = None
        if self._grippers.HasValue(context):
            grippers = self._grippers.Eval(context).reshape(2, 3)
            if self._grasped_from_grippers:
                p_W[self._corners] = grippers
        pose = PlanarPose.FromRigidTransform(self._pose.Eval(context))
        p_O = world_to_object(p_W, pose)
        if self._tracker is not None:
            p_O = self._track(context, discrete_state, p_O, spread, grippers, pose)
        discrete_state.get_mutable_vector(self._state).SetFromVector(p_O.ravel())
        return EventStatus.Succeeded()

    def _track(
        self,
        context,
        discrete_state,
        p_O: np.ndarray,
        spread: np.ndarray,
        grippers: np.ndarray | None,
        pose: PlanarPose,
    ) -> np.ndarray:
        """The tracker's step from the estimate of the last update (moved
        into this update's object frame, should the object have moved);
        stores the new estimate's variance, the grippers and the pose.
        Returns the estimate (M, 3), object frame."""
        variance = context.get_discrete_state(self._variance).value().reshape(-1, 3)
        last_pose = context.get_discrete_state(self._last_pose).value()
        previous = None
        if np.all(np.isfinite(variance)) and np.all(np.isfinite(last_pose)):
            estimate = context.get_discrete_state(self._state).value().reshape(-1, 3)
            estimate = world_to_object(object_to_world(estimate, last_pose), pose)
            previous = (estimate, variance)
        grasped = action = None
        if grippers is not None:
            grasped = world_to_object(grippers, pose)
            last = context.get_discrete_state(self._last_grippers).value()
            if np.all(np.isfinite(last)):
                action = (grasped - world_to_object(last.reshape(2, 3), pose)).ravel()
            discrete_state.get_mutable_vector(self._last_grippers).SetFromVector(
                grippers.ravel()
            )
        if not self._grasped_from_grippers:
            grasped = None
        x, v = self._tracker.step(previous, p_O, spread, action=action, grasped=grasped)
        discrete_state.get_mutable_vector(self._variance).SetFromVector(v.ravel())
        discrete_state.get_mutable_vector(self._last_pose).SetFromVector(
            np.asarray(pose)
        )
        return x


class ChamferToDemo(LeafSystem):
    """The paper's Chamfer distance (Section V-B) between the fabric seen now
    and the demo's last frame, once per control step: `points` points
    back-projected from the depth inside the fabric mask, evenly down-
    sampled, in the object frame, against `target_O` (the same from the
    demo's last frame in its object frame). For curves over the control
    steps (the paper's Fig. 8 a-b); the controller does not read it.

    Input ports: ``mask`` (ImageGrey8U), ``depth`` (ImageDepth32F),
    ``object_pose`` (RigidTransform X_WO).
    Output port: ``chamfer`` (1, m^2; from state).
    """

    def __init__(
        self,
        *,
        camera,
        target_O: np.ndarray,
        width: int,
        height: int,
        period: float,
        offset: float = 0.0,
    ):
        super().__init__()
        self._camera = camera
        self._target = np.asarray(target_O, float)
        self._mask, self._depth, self._pose = _DeclareCameraInputs(self, width, height)
        self._state = self.DeclareDiscreteState(1)
        self.DeclarePeriodicDiscreteUpdateEvent(period, offset, self._update)
        self.DeclareStateOutputPort("chamfer", self._state)

    def _update(self, context, discrete_state) -> EventStatus:
        from fabric_imitation.learning.metrics import (
            chamfer_distance,
            cloud_from_depth,
        )

        cloud_W = cloud_from_depth(
            self._camera,
            self._depth.Eval(context).data[:, :, 0],
            self._mask.Eval(context).data[:, :, 0],
            np.random.default_rng(0),
        )
        pose = PlanarPose.FromRigidTransform(self._pose.Eval(context))
        d = chamfer_distance(world_to_object(cloud_W, pose), self._target)
        discrete_state.get_mutable_vector(self._state).SetFromVector([d])
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


class StepController(LeafSystem):
    """A controller that decides one relative move per control step; the base
    of `MpcController` and `ReplayController`, which give the same outputs,
    so runners and scoring treat them alike.

    Subclasses implement `Finished(S, steps)` (a termination code or None,
    checked before the step cap) and `Decide(context, S, pose, steps,
    progress) -> (code, action_O or None, progress, iterations[, states])`:
    a termination code
    (RUNNING to act), the move in the object frame, the demo step matched
    and the iterations spent. At the step cap the episode ends. After the
    end (release, zero action) the grippers lift `retreat_step` metres in
    each of `retreat_steps` steps, clear of the released cloth. The action's
    frame uses the object pose read from ``object_pose`` at each step (on
    hardware it can come from a marker).

    Input ports: ``keypoints`` (3M, object frame), ``object_pose``
    (RigidTransform X_WO), ``halt`` (3, optional: the benchmark referee's;
    a positive code ends the episode as "rule_break" or "collision" before
    the next action).
    Output ports (all from state, i.e. the result of the last step):
    ``action`` (6, world-frame relative moves [a_L, a_R]), ``release`` (1),
    ``termination`` (1, one of TERMINATION_NAMES' codes), ``steps`` (1,
    actions taken), ``progress`` (1, the demo step J the state matched),
    ``solve_ms`` (1), ``iterations`` (1), ``converged`` (1: the step met the
    paper's convergence test), ``retreated`` (1).
    """

    def __init__(
        self,
        *,
        num_keypoints: int,
        period: float,
        offset: float,
        step_cap: int,
        retreat_steps: int = 3,
        retreat_step: float = 0.03,
        memory_size: int = 1,
    ):
        super().__init__()
        self._retreat = (retreat_steps, retreat_step)
        self._m = num_keypoints
        self._cap = step_cap
        self._kp = self.DeclareVectorInputPort("keypoints", 3 * num_keypoints)
        self._pose = self.DeclareAbstractInputPort(
            "object_pose", AbstractValue.Make(RigidTransform())
        )
        self._halt = self.DeclareVectorInputPort("halt", 3)
        self._state = {
            name: self.DeclareDiscreteState(size)
            for name, size in (
                ("action", 6),
                ("release", 1),
                ("termination", 1),
                ("steps", 1),
                ("progress", 1),
                ("solve_ms", 1),
                ("iterations", 1),
                # 1 where the step met the paper's convergence test (MPC)
                ("converged", 1),
                ("retreated", 1),  # lifting steps taken after the release
                # a subclass's own (ZeroController, MpcController)
                ("memory", memory_size),
            )
        }
        self.DeclarePeriodicDiscreteUpdateEvent(period, offset, self._update)
        for name, index in self._state.items():
            self.DeclareStateOutputPort(name, index)

    def _get(self, context, name: str) -> np.ndarray:
        # A copy: the context's vector is overwritten by later updates.
        return context.get_discrete_state(self._state[name]).value().copy()

    def _halted(self, context) -> int | None:
        """The referee's termination code, if it has halted the episode."""
        if not self._halt.HasValue(context):
            return None
        code = int(self._halt.Eval(context)[0])
        return {
            HALT_RULE_BREAK: TERMINATED_RULE_BREAK,
            HALT_COLLISION: TERMINATED_COLLISION,
        }.get(code)

    def Finished(self, S, steps: int) -> int | None:
        """A termination code if the task is done in state S after `steps`
        actions (checked before the step cap), else None."""
        return None

    def Decide(self, context, S, pose: PlanarPose, steps: int, progress: int):
        raise NotImplementedError

    def _update(self, context, discrete_state) -> EventStatus:
        def put(name, value):
            discrete_state.get_mutable_vector(self._state[name]).SetFromVector(
                np.atleast_1d(value)
            )

        if self._get(context, "termination")[0] != RUNNING:
            done = int(self._get(context, "retreated")[0])
            steps, lift = self._retreat
            put("action", [0, 0, lift, 0, 0, lift] if done < steps else np.zeros(6))
            put("retreated", min(done + 1, steps))
            return EventStatus.Succeeded()
        S = torch.as_tensor(
            self._kp.Eval(context).reshape(self._m, 3), dtype=torch.float32
        )
        pose = PlanarPose.FromRigidTransform(self._pose.Eval(context))
        steps = int(self._get(context, "steps")[0])
        t0 = time.perf_counter()
        progress = int(self._get(context, "progress")[0])
        action_W = np.zeros(6)
        iterations = 0
        code = self._halted(context)
        if code is None:
            code = self.Finished(S, steps)
        if code is None and steps >= self._cap:
            code = TERMINATED_STEP_CAP
        if code is None:
            code, action_O, progress, iterations, *states = self.Decide(
                context, S, pose, steps, progress
            )
            for name, value in (states[0] if states else {}).items():
                put(name, value)
            if code == RUNNING:
                action_W = pose.vector_to_world(np.reshape(action_O, (2, 3))).ravel()
                steps += 1
        put("action", action_W)
        put("release", 1.0 if code != RUNNING else 0.0)
        put("termination", code)
        put("steps", steps)
        put("progress", progress)
        put("solve_ms", 1000 * (time.perf_counter() - t0))
        put("iterations", iterations)
        return EventStatus.Succeeded()


class MpcController(StepController):
    """Sampling MPC following the demo (learning/mpc.py), once per control
    step (see StepController for ports). Ends the episode when the
    termination classifier fires, when no feasible action exists, or at the
    step cap. The rules use the object pose of the
    step."""

    def __init__(self, *, mpc, seed: int = 0, **kwargs):
        # memory: [mu (h x 6), variance (h x 6)]: the noise distribution
        # carried to the next step (mpc.warm_start); a zero variance means
        # none carried.
        self._h = mpc.config.horizon
        super().__init__(memory_size=12 * self._h, **kwargs)
        self._mpc = mpc
        self._seed = seed

    def Finished(self, S, steps) -> int | None:
        return TERMINATED_CLASSIFIER if self._mpc.finished(S, steps) else None

    def Decide(self, context, S, pose, steps, progress):
        mu, var = self._get(context, "memory").reshape(2, self._h, 6)
        noise = (mu, var) if var.any() else None
        result = self._mpc.solve(
            S,
            step=steps,
            seed=self._seed,
            frame_pose=pose,
            noise=noise,
        )
        if not result.feasible:
            _LOG.warning(
                "no feasible action at step %d (of %d sampled sequences, "
                "how many break each rule: %s); releasing",
                steps,
                self._mpc.config.num_samples,
                result.blocked_by,
            )
            return (
                TERMINATED_INFEASIBLE,
                None,
                result.progress,
                result.iterations,
                {"converged": 0.0},
            )
        return (
            RUNNING,
            result.action.numpy(),
            result.progress,
            result.iterations,
            {
                "memory": np.concatenate(
                    [np.ravel(x) for x in result.noise or (np.zeros(12 * self._h),)]
                ),
                "converged": float(result.converged),
            },
        )


class ReplayController(StepController):
    """The Replay baseline: no learning beyond f_R. It follows the demo's
    grasped-corner path (`path`, (T, 2, 3): s1 and s2 per demo frame, in the
    demo's object frame, as f_R saw them), mapped into the object frame of
    now: each step it moves the grippers (the measured s1, s2 of
    ``keypoints``) towards the next point of the path, at most `max_step`
    per axis, and releases once the path's end is reached within `tolerance`
    (see StepController for ports and the step cap)."""

    def __init__(self, *, path, max_step: float, tolerance: float = 0.01, **kwargs):
        super().__init__(**kwargs)
        self._path = np.asarray(path, float).reshape(-1, 6)
        self._max_step = max_step
        self._tolerance = tolerance
        self._s1, self._s2 = (corner_indices(self._m)[k] for k in ("s1", "s2"))

    def Decide(self, context, S, pose, steps, progress):
        grippers = np.concatenate([S[self._s1].numpy(), S[self._s2].numpy()])
        last = len(self._path) - 1
        k = min(progress, last)
        # Skip the path points the grippers are already at.
        while (
            k < last and np.abs(self._path[k + 1] - grippers).max() <= self._tolerance
        ):
            k += 1
        if k == last and np.abs(self._path[k] - grippers).max() <= self._tolerance:
            return TERMINATED_CLASSIFIER, None, k, 0
        gap = self._path[min(k + 1, last)] - grippers
        action = np.clip(gap, -self._max_step, self._max_step)
        reached = np.abs(gap).max() <= self._max_step + 1e-6
        return RUNNING, action, min(k + 1, last) if reached else k, 0


class ZeroController(StepController):
    """The Zero baseline (learning/baseline_policies.py `ZeroFollower`): the
    goal-conditioned inverse model towards the demo's frames one after
    another, the next once the goal recognizer says the state has reached
    this one (see StepController for ports and the step cap). ``progress``
    is the subgoal; the steps spent on it are kept in the ``memory`` state.
    Ends ("classifier") once the recognizer has passed the demo's last frame,
    ("step cap") where the last subgoal ran out of tries."""

    def __init__(self, *, follower, **kwargs):
        super().__init__(**kwargs)
        self._follower = follower

    def Decide(self, context, S, pose, steps, progress):
        tries = int(self._get(context, "memory")[0])
        step = self._follower.decide(S, progress, tries, np.array(pose))
        if step.action is None:
            code = TERMINATED_STEP_CAP if step.gave_up else TERMINATED_CLASSIFIER
            return code, None, step.subgoal, 0, {"memory": 0}
        return RUNNING, step.action.numpy(), step.subgoal, 0, {"memory": step.tries}


class CfmController(StepController):
    """The CFM baseline (learning/baseline_policies.py `CfmPlanner`): one-step
    model-predictive control in the contrastive latent space towards the
    demo's final frame (see StepController for ports and the step cap);
    ``progress`` is the demo frame nearest in latent space, ``iterations``
    the number of sampled moves."""

    def __init__(self, *, planner, seed: int = 0, **kwargs):
        super().__init__(**kwargs)
        self._planner = planner
        self._seed = seed

    def Finished(self, S, steps) -> int | None:
        return TERMINATED_CLASSIFIER if self._planner.finished(S) else None

    def Decide(self, context, S, pose, steps, progress):
        action, nearest = self._planner.decide(
            S, np.array(pose), self._seed * 100003 + steps
        )
        samples = self._planner.config.num_samples
        return RUNNING, action.numpy(), nearest, samples


class TcnController(StepController):
    """The TCN baseline (learning/baseline_policies.py `TcnPlanner`): a
    cross-entropy search over f_D rollouts for the time-aligned TCN reward
    (see StepController for ports and the step cap); ``progress`` is the
    aligned demo frame, ``iterations`` the search's."""

    def __init__(self, *, planner, seed: int = 0, **kwargs):
        super().__init__(**kwargs)
        self._planner = planner
        self._seed = seed

    def Finished(self, S, steps) -> int | None:
        return TERMINATED_CLASSIFIER if self._planner.finished(S, steps) else None

    def Decide(self, context, S, pose, steps, progress):
        action, aligned, iterations = self._planner.decide(
            S, steps, np.array(pose), self._seed * 100003 + steps
        )
        return RUNNING, action.numpy(), aligned, iterations
