"""The benchmark's referee: solid grippers, the stopping rule, the scripted
demos keeping the referee's rules, and the trials' cloth starts."""

import numpy as np
import pytest
from conftest import SMALL_CLOTH
from fabric_imitation.learning.safety import RULES
from fabric_imitation.learning.state import corner_indices
from fabric_imitation.scenarios.loader import LoadScenario
from fabric_imitation.scenarios.policy import LoadPolicy
from fabric_imitation.systems.imitation import (
    RUNNING,
    TERMINATED_RULE_BREAK,
    StepController,
)
from fabric_imitation.systems.referee import HALT_RULE_BREAK, Referee
from fabric_imitation.tasks.referee import (
    REFEREES,
    FirstBreak,
    JudgeTransitions,
    TaskReferee,
)
from pydrake.common.value import AbstractValue
from pydrake.math import RigidTransform
from pydrake.systems.analysis import Simulator
from pydrake.systems.framework import DiagramBuilder
from pydrake.systems.primitives import ConstantValueSource, ConstantVectorSource


def _flat_cloth() -> np.ndarray:
    """Keypoints (8, 3) of a flat 30 x 30 cm cloth 22 cm in front of the box
    (object frame), grasped edge towards the robot (-y)."""
    idx = corner_indices(8)
    S = np.tile([0.0, 0.22, 0.0], (8, 1))  # only the corners matter here
    S[idx["s1"]] = [-0.15, 0.07, 0.0]
    S[idx["s2"]] = [0.15, 0.07, 0.0]
    S[idx["s3"]] = [-0.15, 0.37, 0.0]
    S[idx["s4"]] = [0.15, 0.37, 0.0]
    return S


def test_the_referee_judges_the_papers_rules_with_the_tasks_thresholds():
    scenario = LoadScenario(scenario_name="box")
    S = _flat_cloth()[None]
    lift = np.array([[0, 0, 0.02, 0, 0, 0.02]])
    towards_far_corner = np.array([[0, 0.02, 0.0, 0, 0.02, 0.0]])
    rules = TaskReferee("box")
    ok = JudgeTransitions(rules, scenario, S, lift, S + [0, 0, 0.0])
    assert FirstBreak(ok) is None
    bad = JudgeTransitions(rules, scenario, S, towards_far_corner, S)
    assert FirstBreak(bad) == (0, "direction")
    # The controller's own settings do not move the referee.
    tuned = LoadScenario(
        scenario_name="box",
        policy=LoadPolicy(
            policy_text="safety: {tau_d_deg: 179.0, tau_d_from_demo: false}"
        ),
    )
    assert FirstBreak(JudgeTransitions(rules, tuned, S, towards_far_corner, S))
    assert rules.fingerprint() != REFEREES["hang"].fingerprint()


class _Pusher(StepController):
    """Moves the grasped corners towards the far corners every step."""

    def Decide(self, context, S, pose, steps, progress):
        return RUNNING, np.array([0, 0.02, 0, 0, 0.02, 0]), progress, 0


def _run(on_violation: str, seconds: float = 1.0):
    scenario = LoadScenario(scenario_name="box")
    rules = TaskReferee("box")

    def judge(before, action, after):
        hit = FirstBreak(
            JudgeTransitions(rules, scenario, before[None], action[None], after[None])
        )
        return None if hit is None else hit[1]

    builder = DiagramBuilder()
    dt = 0.2
    controller = builder.AddSystem(
        _Pusher(num_keypoints=8, period=dt, offset=1e-3, step_cap=100)
    )
    referee = builder.AddSystem(
        Referee(judge=judge, rules=RULES, num_keypoints=8, period=dt, offset=0.0)
    )
    # The object at the origin: object frame = world.
    cloth = builder.AddSystem(ConstantVectorSource(_flat_cloth().ravel()))
    pose = builder.AddSystem(ConstantValueSource(AbstractValue.Make(RigidTransform())))
    builder.Connect(cloth.get_output_port(), controller.GetInputPort("keypoints"))
    builder.Connect(cloth.get_output_port(), referee.GetInputPort("true_keypoints"))
    for system in (controller, referee):
        builder.Connect(pose.get_output_port(), system.GetInputPort("object_pose"))
    for name in ("action", "steps"):
        builder.Connect(controller.GetOutputPort(name), referee.GetInputPort(name))
    if on_violation == "stop":
        builder.Connect(referee.GetOutputPort("halt"), controller.GetInputPort("halt"))
    diagram = builder.Build()
    simulator = Simulator(diagram)
    simulator.AdvanceTo(seconds)
    context = simulator.get_context()
    return (
        controller.GetOutputPort("termination").Eval(
            controller.GetMyContextFromRoot(context)
        )[0],
        controller.GetOutputPort("steps").Eval(
            controller.GetMyContextFromRoot(context)
        )[0],
        referee.GetOutputPort("halt").Eval(referee.GetMyContextFromRoot(context)),
    )


def test_stop_ends_the_episode_at_the_first_rule_break_and_names_the_rule():
    termination, steps, halt = _run("stop")
    assert termination == TERMINATED_RULE_BREAK
    assert steps == 1  # the breaking action was executed; no other after it
    assert halt[0] == HALT_RULE_BREAK and RULES[int(halt[1])] == "direction"
    assert halt[2] == 1


def test_count_keeps_going_after_a_rule_break():
    termination, steps, halt = _run("count")
    assert termination == RUNNING
    assert steps == 5
    assert halt[0] == HALT_RULE_BREAK and halt[2] == 1  # still recorded


def test_an_anchor_driven_into_the_box_stops_on_its_face_and_reports_contact():
    """A gripper whose target lies 5 cm inside the box top stops within 5 mm
    of the face, and the station reports the contact."""
    from fabric_imitation.diagrams.station import (
        AdvanceStationTo,
        InitializeStation,
        MakeClothStation,
        StationPorts,
    )
    from fabric_imitation.scenarios.poses import GraspCorners
    from fabric_imitation.systems.targets import ActionPlayer, GripperTargetIntegrator

    scenario = LoadScenario(scenario_name="box", scenario_text=SMALL_CLOTH)
    station = MakeClothStation(scenario)
    start = GraspCorners(scenario)["left"]
    p_box = station.X_WO.translation()
    top = scenario.object.size[2]
    # Up, over the box's centre, then down to 5 cm below its top.
    path = [
        start + [0, 0, 0.12],
        [p_box[0], p_box[1], top + 0.064],
        [p_box[0], p_box[1], top - 0.05],
    ]
    actions, p = [], start.copy()
    for target in np.array(path, float):
        while np.abs(target - p).max() > 1e-9:
            a = np.clip(target - p, -0.03, 0.03)
            p = p + a
            actions.append(np.r_[a, 0, 0, 0])
    builder = DiagramBuilder()
    st = builder.AddSystem(station.diagram)
    player = builder.AddSystem(
        ActionPlayer(actions=np.array(actions), step_seconds=0.2, release_step=None)
    )
    targets = builder.AddSystem(GripperTargetIntegrator(step_seconds=0.2))
    builder.Connect(player.GetOutputPort("action"), targets.GetInputPort("action"))
    for side in ("left", "right"):
        builder.Connect(
            targets.GetOutputPort(f"{side}.ee_target"),
            st.GetInputPort(StationPorts.ee_target(side)),
        )
    hold = builder.AddSystem(ConstantVectorSource([0.0]))
    builder.Connect(hold.get_output_port(), st.GetInputPort(StationPorts.RELEASE))
    simulator = Simulator(builder.Build())
    context = simulator.get_mutable_context()
    corners = GraspCorners(scenario)
    targets.SetInitialPositions(
        targets.GetMyMutableContextFromRoot(context), corners["left"], corners["right"]
    )
    station_context = st.GetMyMutableContextFromRoot(context)
    InitializeStation(station, station_context)
    simulator.Initialize()
    AdvanceStationTo(simulator, station, 0.2 * (len(actions) + 3))
    p_left = st.GetOutputPort(StationPorts.ee_measured("left")).Eval(station_context)
    contact = st.GetOutputPort(StationPorts.GRIPPER_OBJECT_CONTACT).Eval(
        station_context
    )
    # The fingertips (the anchor's origin) rest on the top face.
    assert abs(p_left[2] - top) < 0.005, p_left
    assert contact[0] > 0 and contact[1] > 0  # steps in contact, first time
    assert contact[2] < 0.005  # deepest penetration


@pytest.mark.slow
@pytest.mark.parametrize("task", ["box", "hang", "cylinder", "rail"])
def test_the_scripted_demos_keep_the_referees_rules_without_collisions(task):
    """At the nominal pose and a moved and turned one, on the shipped cloth
    (`task`: the named scenario; cylinder is judged as a cover, rail as a
    hang). The can's cover is not asked to succeed at the moved pose: the
    scripted demo leaves 0.79 of its top covered there (the bar is 0.9)."""
    from fabric_imitation.tools.evaluate import (
        ClothStarts,
        ProtocolPoses,
        ScriptedTrial,
        TrialScenario,
    )

    poses = [None, *ProtocolPoses(task, "transformation", trials=1, seed=0)]
    starts = [None, *ClothStarts(task, poses[1:], seed=0)]
    for pose, start in zip(poses, starts, strict=True):
        trial = ScriptedTrial(TrialScenario(task, "", pose, start))
        if pose is None or task != "cylinder":
            assert trial["success"], (pose, trial)
        assert trial["rule_breaks_true"]["any"] == 0, (pose, trial)
        assert trial["collisions"] == 0, (pose, trial)


def test_the_cloth_start_is_drawn_from_the_seed_within_its_band():
    from fabric_imitation.tools.evaluate import (
        CLOTH_START_SHIFT,
        CLOTH_START_TURN_DEG,
        ClothStarts,
        ProtocolPoses,
        TrialScenario,
    )

    poses = ProtocolPoses("box", "transformation", trials=6, seed=0)
    # The object poses of existing seeds are as they were before cloth starts.
    assert poses[:2] == [[-0.0099, -0.0608, -41.31], [0.005, -0.1519, 37.15]]
    first = ClothStarts("box", poses, seed=0)
    assert first == ClothStarts("box", poses, seed=0)
    assert first != ClothStarts("box", poses, seed=1)
    for dx, dy, dyaw in first:
        assert np.hypot(dx, dy) <= CLOTH_START_SHIFT + 1e-9
        assert abs(dyaw) <= CLOTH_START_TURN_DEG
    scenario = TrialScenario("box", "", poses[0], first[0])
    nominal = LoadScenario(scenario_name="box").cloth.pose
    assert np.allclose(np.array(scenario.cloth.pose) - nominal, first[0], atol=1e-4)


def test_an_unknown_on_violation_rule_is_one_line_and_exit_2(capsys):
    from fabric_imitation.tasks import referee
    from fabric_imitation.tools import cli
    from fabric_imitation.tools.cli import main

    assert cli.ON_VIOLATION == referee.ON_VIOLATION

    code = main(
        [
            "evaluate",
            "--scenarios",
            "box",
            "--out",
            "/nonexistent/x.jsonl",
            "--on-violation",
            "pause",
        ]
    )
    err = capsys.readouterr().err.strip().splitlines()
    assert code == 2 and len(err) == 1 and "pause" in err[0]


def test_the_controllers_hand_shape_is_the_grippers_capsules():
    """`safety.hand_shape` (the default) gives the controller's rule 4
    spheres covering the anchors' hand capsules (every capsule's axis near a
    sphere's centre); the referee's view, and the setting off, keep point
    grippers."""
    from fabric_imitation.scenarios.loader import LoadScenario
    from fabric_imitation.scenarios.policy import LoadPolicy
    from fabric_imitation.systems.gripper_contact import GraspCapsules
    from fabric_imitation.tasks.referee import TaskSafetyContext

    scenario = LoadScenario(
        scenario_name="box", policy=LoadPolicy(policy_text="safety: {hand_shape: true}")
    )
    spheres = TaskSafetyContext(scenario, estimated=True).hand_spheres
    assert spheres is not None and spheres.shape[1] == 4
    for capsule in GraspCapsules(scenario):
        axis = capsule.samples(0.05)
        gaps = np.linalg.norm(axis[:, None] - spheres[None, :, :3], axis=-1)
        assert (gaps.min(1) <= 0.5 * capsule.radius).all()
    assert TaskSafetyContext(scenario).hand_spheres is None
    points = LoadScenario(
        scenario_name="box",
        policy=LoadPolicy(policy_text="safety: {hand_shape: false}"),
    )
    assert TaskSafetyContext(points, estimated=True).hand_spheres is None
