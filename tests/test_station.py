import cv2
import numpy as np
import pytest
from fabric_imitation.diagrams.station import (
    AdvanceStationTo,
    MakeClothStation,
    StationPorts,
)
from fabric_imitation.learning.state import corner_indices
from fabric_imitation.scenarios.loader import LoadScenario
from fabric_imitation.scenarios.poses import GraspCorners
from fabric_imitation.systems.cloth_mesh import TopTriangles
from pydrake.math import RigidTransform
from pydrake.systems.analysis import Simulator

from tests.conftest import SmallCloth

EXPECTED_PORTS = {
    "inputs": {"left.ee_target", "right.ee_target", "release"},
    "outputs": {
        "left.ee_position_measured",
        "right.ee_position_measured",
        "released",
        "camera.rgb_image",
        "camera.depth_image",
        "camera.label_image",
        "camera.fabric_mask",
        "object.pose",
        "cloth.positions",
        "cloth.keypoints",
        "grippers.object_contact",  # with a task object
    },
}


ENGINES = ["vbd", "fem"]


class Rig:
    """A station in a simulator, driven by fixed gripper targets."""

    def __init__(self, name="prior", engine="vbd"):
        self.scenario = LoadScenario(
            scenario_name=name, scenario_text=SmallCloth(engine)
        )
        self.built = MakeClothStation(self.scenario)
        self.station = self.built.diagram
        self.simulator = Simulator(self.station)
        self.context = self.simulator.get_mutable_context()
        self.corners = GraspCorners(self.scenario)
        self.release(False)
        self.move(0.0)
        self.simulator.Initialize()

    def port(self, name):
        return self.station.GetOutputPort(name).Eval(self.context)

    def move(self, dz):
        for side in ("left", "right"):
            self.station.GetInputPort(f"{side}.ee_target").FixValue(
                self.context, self.corners[side] + [0, 0, dz]
            )

    def advance_to(self, t):
        AdvanceStationTo(self.simulator, self.built, t)

    def release(self, on=True):
        self.station.GetInputPort("release").FixValue(self.context, [float(on)])

    def lift(self, height, seconds=0.5, steps=10):
        t0 = self.context.get_time()
        for k in range(steps):
            self.move(height * (k + 1) / steps)
            self.advance_to(t0 + seconds * (k + 1) / steps)

    def keypoints(self):
        return np.asarray(self.port(StationPorts.CLOTH_KEYPOINTS)).reshape(-1, 3)

    def positions(self):
        return np.asarray(self.port(StationPorts.CLOTH_POSITIONS)).reshape(-1, 3)


@pytest.mark.parametrize("engine", ENGINES)
def test_station_exports_the_documented_ports(engine):
    station = MakeClothStation(
        LoadScenario(scenario_name="box", scenario_text=SmallCloth(engine))
    ).diagram
    inputs = {
        station.get_input_port(i).get_name() for i in range(station.num_input_ports())
    }
    outputs = {
        station.get_output_port(i).get_name() for i in range(station.num_output_ports())
    }
    assert inputs == EXPECTED_PORTS["inputs"]
    assert outputs == EXPECTED_PORTS["outputs"]
    context = station.CreateDefaultContext()
    X_WO = station.GetOutputPort("object.pose").Eval(context)
    assert isinstance(X_WO, RigidTransform)
    np.testing.assert_allclose(X_WO.translation(), [0.0, -0.14, 0.0])


@pytest.mark.parametrize("engine", ENGINES)
def test_keypoints_are_ordered_around_the_boundary(engine):
    rig = Rig(engine=engine)
    S = rig.keypoints()
    idx = corner_indices(len(S))
    np.testing.assert_allclose(S[idx["s1"]], rig.corners["left"], atol=1e-6)
    np.testing.assert_allclose(S[idx["s2"]], rig.corners["right"], atol=1e-6)
    assert S[idx["s3"], 0] < 0 < S[idx["s4"], 0]  # far-left, far-right
    assert S[idx["s3"], 1] > S[idx["s1"], 1]  # far side is +y
    x, y = S[:, 0], S[:, 1]
    area = 0.5 * np.sum(x * np.roll(y, -1) - np.roll(x, -1) * y)
    assert area == pytest.approx(0.30 * 0.30, rel=1e-6)  # counter-clockwise


@pytest.mark.parametrize("engine", ENGINES)
def test_grasped_corners_follow_a_10cm_lift_within_5mm(engine):
    rig = Rig(engine=engine)
    rig.lift(0.10)
    rig.advance_to(rig.context.get_time() + 0.5)
    S = rig.keypoints()
    idx = corner_indices(len(S))
    for side, k in (("left", "s1"), ("right", "s2")):
        target = rig.corners[side] + [0, 0, 0.10]
        assert np.linalg.norm(S[idx[k]] - target) < 0.005
    far = S[idx["s3"], 2]
    assert far < 0.02  # the far edge still lies on the table


@pytest.mark.parametrize("engine", ENGINES)
def test_release_drops_the_cloth_onto_the_table(engine):
    rig = Rig(engine=engine)
    rig.lift(0.05)
    held = rig.keypoints()[0, 2]
    assert held > 0.04
    rig.release()
    rig.advance_to(rig.context.get_time() + 1.0)
    assert rig.port("released")[0] == 1.0
    p = rig.positions()
    assert p[:, 2].max() < 0.015  # everything lies on the table again
    assert p[:, 2].min() > -0.01
    # Gripper targets stayed up: the corners are no longer held.
    assert rig.port("left.ee_position_measured")[2] > 0.045


@pytest.mark.parametrize("engine", ENGINES)
def test_fabric_mask_matches_the_projected_cloth(engine):
    rig = Rig(engine=engine)
    rig.lift(0.08)
    mask = rig.port(StationPorts.MASK).data[:, :, 0] > 0
    info = rig.built.camera_info
    X_CW = rig.built.X_WCamera.inverse()
    K = np.array(
        [
            [info.focal_x(), 0, info.center_x()],
            [0, info.focal_y(), info.center_y()],
            [0, 0, 1],
        ]
    )
    p_C = (
        X_CW.GetAsMatrix4() @ np.c_[rig.positions(), np.ones(len(rig.positions()))].T
    )[:3].T
    uv = (p_C @ K.T)[:, :2] / p_C[:, 2:3]
    truth = np.zeros(mask.shape, np.uint8)
    tris = TopTriangles(rig.built.mesh.top_layer)
    for t in tris:
        cv2.fillPoly(truth, [np.round(uv[t] * 16).astype(np.int32)], 1, shift=4)
    truth = truth > 0
    iou = (mask & truth).sum() / (mask | truth).sum()
    assert iou >= 0.8, iou


def test_meshcat_recording_draws_the_cloth_in_its_own_colour():
    from fabric_imitation.diagrams.recorders import AddClothRecorder
    from pydrake.geometry import Meshcat
    from pydrake.systems.framework import DiagramBuilder

    color = [0.15, 0.62, 0.30]
    scenario = LoadScenario(
        scenario_name="box",
        scenario_text=f"cloth: {{vbd: {{resolution: [6, 6]}}, color: {color}}}",
    )
    station = MakeClothStation(scenario)
    builder = DiagramBuilder()
    builder.AddSystem(station.diagram)
    recorder = AddClothRecorder(builder, station, Meshcat())
    assert recorder.rgba().rgba.tolist() == pytest.approx([*color, 1.0])
