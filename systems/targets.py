"""Gripper targets from relative moves, and a player for fixed action lists."""

import numpy as np
from pydrake.systems.framework import BasicVector, EventStatus, LeafSystem


class GripperTargetIntegrator(LeafSystem):
    """Turns relative moves A = [a_L, a_R] (6-vector, metres per control step)
    into world position targets for the two grippers.

    Every `step_seconds` it latches the ``action`` input: the new segment runs
    from the current goal to goal + A, and the targets ramp linearly along it
    over the step, so the grippers move smoothly instead of jumping.

    Input ports: ``action`` (6), ``measured`` (6, optional: the grippers'
    measured positions [left, right]; when connected, an initialization event
    starts the targets there, or, with `start_at_first_step`, the first
    latch does: on real drivers the measurement is valid only once their
    first status has arrived).
    Output ports: ``left.ee_target`` (3), ``right.ee_target`` (3),
    ``goal`` (6, the end of the current segment). None depends directly on an
    input (they are computed from state and time).

    State: discrete [start (6), goal (6), t_start (1), started (1)]. Until
    then the targets are the initial positions:
    `SetInitialPositions(context, p_left, p_right)`.
    """

    def __init__(
        self,
        *,
        step_seconds: float,
        offset: float = 0.0,
        start_at_first_step: bool = False,
    ):
        super().__init__()
        self._dt = step_seconds
        self._late_start = start_at_first_step
        self._action = self.DeclareVectorInputPort("action", 6)
        self._measured = self.DeclareVectorInputPort("measured", 6)
        self._state = self.DeclareDiscreteState(14)
        self.DeclarePeriodicDiscreteUpdateEvent(step_seconds, offset, self._latch)
        self.DeclareInitializationDiscreteUpdateEvent(self._start_at_measured)
        from_state = {self.time_ticket(), self.discrete_state_ticket(self._state)}
        self.DeclareVectorOutputPort(
            "left.ee_target",
            3,
            lambda c, o: o.SetFromVector(self._target(c)[:3]),
            prerequisites_of_calc=from_state,
        )
        self.DeclareVectorOutputPort(
            "right.ee_target",
            3,
            lambda c, o: o.SetFromVector(self._target(c)[3:]),
            prerequisites_of_calc=from_state,
        )
        self.DeclareVectorOutputPort(
            "goal",
            6,
            lambda c, o: o.SetFromVector(self._x(c)[6:12]),
            prerequisites_of_calc=from_state,
        )

    def SetInitialPositions(self, context, p_left, p_right) -> None:
        p = np.concatenate([p_left, p_right])
        context.SetDiscreteState(self._state, np.concatenate([p, p, [0.0, 0.0]]))

    def _start_at_measured(self, context, discrete_state) -> EventStatus:
        if self._late_start or not self._measured.HasValue(context):
            return EventStatus.DidNothing()
        p = self._measured.Eval(context)
        discrete_state.get_mutable_vector(self._state).SetFromVector(
            np.concatenate([p, p, [context.get_time(), 1.0]])
        )
        return EventStatus.Succeeded()

    def _x(self, context) -> np.ndarray:
        return context.get_discrete_state(self._state).value()

    def _target(self, context) -> np.ndarray:
        x = self._x(context)
        s = np.clip((context.get_time() - x[12]) / self._dt, 0.0, 1.0)
        return x[:6] + s * (x[6:12] - x[:6])

    def _latch(self, context, discrete_state) -> EventStatus:
        x = self._x(context)
        action = self._action.Eval(context) if self._action.HasValue(context) else 0
        start = x[6:12]
        if not x[13] and self._late_start and self._measured.HasValue(context):
            start = self._measured.Eval(context)
        discrete_state.get_mutable_vector(self._state).SetFromVector(
            np.concatenate([start, start + action, [context.get_time(), 1.0]])
        )
        return EventStatus.Succeeded()


class ActionPlayer(LeafSystem):
    """Plays a fixed list of actions, one per control step, then zeros, and
    raises ``release`` from step `release_step` on.

    Step k covers [k * step_seconds, (k + 1) * step_seconds).

    Output ports: ``action`` (6), ``release`` (1).
    """

    def __init__(
        self, *, actions: np.ndarray, step_seconds: float, release_step: int | None
    ):
        super().__init__()
        self._actions = np.asarray(actions, dtype=float).reshape(-1, 6)
        self._dt = step_seconds
        self._release_step = release_step
        self.DeclareVectorOutputPort("action", 6, self._calc_action)
        self.DeclareVectorOutputPort("release", 1, self._calc_release)

    def _step(self, context) -> int:
        # The small offset keeps a step boundary in the step that starts there.
        return int(np.floor(context.get_time() / self._dt + 1e-6))

    def _calc_action(self, context, output: BasicVector) -> None:
        k = self._step(context)
        output.SetFromVector(
            self._actions[k] if 0 <= k < len(self._actions) else np.zeros(6)
        )

    def _calc_release(self, context, output: BasicVector) -> None:
        released = (
            self._release_step is not None and self._step(context) >= self._release_step
        )
        output.SetFromVector([1.0 if released else 0.0])
