"""The benchmark's referee as a LeafSystem: it watches the simulator's true
keypoints and the executed actions, and raises ``halt`` at the first action
that breaks a rule or at the first gripper-object contact."""

from collections.abc import Callable

import numpy as np
from fabric_imitation.learning.state import PlanarPose, world_to_object
from pydrake.common.value import AbstractValue
from pydrake.math import RigidTransform
from pydrake.systems.framework import EventStatus, LeafSystem

# ``halt`` codes.
NO_HALT, HALT_RULE_BREAK, HALT_COLLISION = 0, 1, 2


class Referee(LeafSystem):
    """Judges each executed action on the true cloth, once per control step.

    At control step k (time start + k * dt, the estimator's time) it reads
    the true keypoints, which are the state after the action of step k - 1,
    the controller's ``action`` and ``steps`` outputs (that action, and
    whether one was taken), and the station's gripper-object contact. A
    broken rule or a contact latches ``halt``; a controller whose ``halt``
    input is connected ends the episode at its next update, before it acts
    again.

    Simulation only (true keypoints).

    Input ports: ``true_keypoints`` (3M, world), ``object_pose``
    (RigidTransform X_WO), ``action`` (6, world), ``steps`` (1),
    ``contact`` (3, optional: the station's ``grippers.object_contact``).
    Output ports: ``halt`` (3: code NO_HALT / HALT_RULE_BREAK /
    HALT_COLLISION, the index of the broken rule in `rules` (-1 for a
    contact), the number of actions executed when it halted); from state.
    """

    def __init__(
        self,
        *,
        judge: Callable[[np.ndarray, np.ndarray, np.ndarray], str | None],
        rules: tuple[str, ...],
        num_keypoints: int,
        period: float,
        offset: float,
    ):
        super().__init__()
        self._judge = judge
        self._rules = rules
        self._m = num_keypoints
        self._kp = self.DeclareVectorInputPort("true_keypoints", 3 * num_keypoints)
        self._pose = self.DeclareAbstractInputPort(
            "object_pose", AbstractValue.Make(RigidTransform())
        )
        self._action = self.DeclareVectorInputPort("action", 6)
        self._steps = self.DeclareVectorInputPort("steps", 1)
        self._contact = self.DeclareVectorInputPort("contact", 3)
        # The keypoints (object frame) and step count of the last update.
        self._previous = self.DeclareDiscreteState(
            np.r_[np.full(3 * num_keypoints, np.nan), 0.0]
        )
        self._halt = self.DeclareDiscreteState(np.array([NO_HALT, -1.0, 0.0]))
        self.DeclarePeriodicDiscreteUpdateEvent(period, offset, self._update)
        self.DeclareStateOutputPort("halt", self._halt)

    def _update(self, context, discrete_state) -> EventStatus:
        pose = PlanarPose.FromRigidTransform(self._pose.Eval(context))
        now = world_to_object(self._kp.Eval(context).reshape(self._m, 3), pose)
        steps = float(self._steps.Eval(context)[0])
        previous = context.get_discrete_state(self._previous).value()
        halt = context.get_discrete_state(self._halt).value().copy()
        if halt[0] == NO_HALT:
            if steps > previous[-1] and np.all(np.isfinite(previous[:-1])):
                action = pose.vector_to_object(
                    self._action.Eval(context).reshape(2, 3)
                ).ravel()
                rule = self._judge(previous[:-1].reshape(self._m, 3), action, now)
                if rule is not None:
                    halt = np.array([HALT_RULE_BREAK, self._rules.index(rule), steps])
            if (
                halt[0] == NO_HALT
                and self._contact.HasValue(context)
                and self._contact.Eval(context)[0] > 0
            ):
                halt = np.array([HALT_COLLISION, -1.0, steps])
        discrete_state.get_mutable_vector(self._previous).SetFromVector(
            np.r_[now.ravel(), steps]
        )
        discrete_state.get_mutable_vector(self._halt).SetFromVector(halt)
        return EventStatus.Succeeded()
