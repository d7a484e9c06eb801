"""The task object's shape (learning/object_shape.py) and where it is read:
the rule on the object, the gripper contact monitor, the schema's sizes."""

import numpy as np
import pytest
import torch
from fabric_imitation.learning.errors import InputError
from fabric_imitation.learning.object_shape import (
    ObjectParts,
    ObjectSignedDistance,
    object_signed_distance,
)
from fabric_imitation.scenarios.loader import LoadScenario


@pytest.mark.parametrize(
    "kind, size, point, distance",
    [
        ("box", [0.14, 0.09, 0.06], [0.0, 0.0, 0.03], -0.03),
        ("box", [0.14, 0.09, 0.06], [0.10, 0.0, 0.03], 0.03),
        ("plate", [0.17, 0.01, 0.20], [0.0, 0.02, 0.10], 0.015),
        # A can 10 cm across: 2 cm out from its side, and beside a corner
        # of its bounding box, which is outside the can.
        ("cylinder", [0.10, 0.10, 0.10], [0.07, 0.0, 0.05], 0.02),
        ("cylinder", [0.10, 0.10, 0.10], [0.048, 0.048, 0.05], 0.0179),
        ("cylinder", [0.10, 0.10, 0.10], [0.0, 0.0, 0.12], 0.02),
        # A rail 45 cm wide, 2 cm bar, 24 cm high: under the bar between the
        # posts is outside it, in a post or in the bar inside.
        ("rail", [0.45, 0.02, 0.24], [0.0, 0.0, 0.10], 0.12),
        ("rail", [0.45, 0.02, 0.24], [0.215, 0.0, 0.10], -0.01),
        ("rail", [0.45, 0.02, 0.24], [0.0, 0.0, 0.235], -0.005),
        ("rail", [0.45, 0.02, 0.24], [0.0, 0.03, 0.23], 0.02),
    ],
)
def test_signed_distance_of_each_kind(kind, size, point, distance):
    assert ObjectSignedDistance([point], kind, size)[0] == pytest.approx(
        distance, abs=2e-4
    )
    p = torch.tensor([point], dtype=torch.float32)
    assert float(object_signed_distance(p, kind, size)[0]) == pytest.approx(
        distance, abs=2e-4
    )


def test_the_parts_lie_in_the_bounding_box():
    for kind, size in [
        ("box", [0.14, 0.09, 0.06]),
        ("cylinder", [0.09, 0.09, 0.08]),
        ("rail", [0.45, 0.02, 0.24]),
    ]:
        for part in ObjectParts(kind, size):
            c, s = np.array(part.centre), np.array(part.size)
            if part.axis == "x":
                s = s[[2, 0, 1]]
            assert np.all(np.abs(c[:2]) + s[:2] / 2 <= np.array(size[:2]) / 2 + 1e-9)
            assert c[2] - s[2] / 2 >= -1e-9 and c[2] + s[2] / 2 <= size[2] + 1e-9


def test_rule_on_the_object_reads_its_shape():
    """A gripper beside the can's bounding-box corner is clear of the can;
    the same point beside a box of that size is in the rule's margin."""
    from fabric_imitation.learning.safety import rule_violations
    from fabric_imitation.tasks.referee import TaskReferee, TaskSafetyContext

    can = LoadScenario(scenario_name="cylinder")
    box = LoadScenario(
        scenario_name="box", scenario_text="object: {size: [0.09, 0.09, 0.08]}"
    )
    S = torch.zeros(1, 8, 3, dtype=torch.float64)
    corner = torch.tensor([0.055, 0.055, 0.05], dtype=torch.float64)
    S[0, 0] = corner
    S[0, 2] = corner + torch.tensor([0.1, 0.0, 0.0], dtype=torch.float64)
    A = torch.zeros(1, 6, dtype=torch.float64)
    config = TaskReferee("box").safety()
    on_can = rule_violations(S, A, config, TaskSafetyContext(can))["object"]
    on_box = rule_violations(S, A, config, TaskSafetyContext(box))["object"]
    assert not bool(on_can[0]) and bool(on_box[0])


def test_gripper_contact_reads_the_shape():
    from fabric_imitation.systems.gripper_contact import (
        Capsule,
        CapsulesPenetration,
    )
    from pydrake.math import RigidTransform

    finger = (Capsule((0.0, 0.0, 0.0), (0.0, 0.0, 0.03), 0.01),)
    # 3 cm under the rail's bar between the posts: clear; in a post: inside.
    under_bar = RigidTransform([0.0, 0.0, 0.15])
    in_post = RigidTransform([0.215, 0.0, 0.10])
    size = np.array([0.45, 0.02, 0.24])
    assert CapsulesPenetration(finger, under_bar, "rail", size) < 0
    assert CapsulesPenetration(finger, in_post, "rail", size) > 0


@pytest.mark.parametrize(
    "text, message",
    [
        ("object: {kind: cylinder, size: [0.09, 0.10, 0.08]}", "must be equal"),
        ("object: {kind: rail, size: [0.05, 0.02, 0.24]}", "3 times its bar"),
    ],
)
def test_the_schema_refuses_shapes_that_do_not_make_sense(text, message):
    with pytest.raises(InputError, match=message):
        LoadScenario(scenario_name="box", scenario_text=text)
