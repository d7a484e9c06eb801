"""`imitate --hardware` end to end over LCM in one process (memq): the
imitation diagram on the hardware station on one side, a simulated lab
(cloth, two Pandas answering the drivers' channels, a camera publishing
images) on the other. They share nothing but the LCM bus."""

import os
import re
import signal

import numpy as np
import pytest
from drake import lcmt_panda_command
from fabric_imitation.diagrams.hardware import (
    MakeHardwareClothStation,
    MakeSimulatedLab,
)
from fabric_imitation.diagrams.imitation import (
    DefaultDemoDir,
    MakeImitationDiagram,
    PrepareImitation,
)
from fabric_imitation.diagrams.station import MakeClothStation, StationPorts
from fabric_imitation.scenarios.loader import LoadScenario
from fabric_imitation.tasks.success import TaskSuccess
from fabric_imitation.tools.episode import RunEpisode, ScoreEpisode
from pydrake.common.value import AbstractValue
from pydrake.lcm import DrakeLcm
from pydrake.systems.framework import DiagramBuilder, LeafSystem
from pydrake.systems.lcm import LcmSubscriberSystem


def _hardware_run(scenario, *, stop_camera_at=None):
    prepared = PrepareImitation(
        scenario, demo_dir=DefaultDemoDir("box_panda", scenario)
    )
    lcm = DrakeLcm("memq://")
    imitation = MakeImitationDiagram(scenario, prepared, hardware=True, lcm=lcm)
    lab, lab_station = MakeSimulatedLab(
        scenario, lcm=lcm, camera_period=0.05, camera_until=stop_camera_at
    )
    builder = DiagramBuilder()
    builder.AddSystem(imitation.diagram)
    builder.AddSystem(lab)
    root = builder.Build()
    # The imitation side's systems connect to nothing of the lab's.
    assert not any(
        lab.GetSubsystemByName("lab_station") is s
        for s in imitation.diagram.GetSystems()
    )
    run = RunEpisode(
        imitation, settle_seconds=scenario.motion.settle_seconds, root=root
    )
    return prepared, run, lab, lab_station


@pytest.mark.slow
def test_imitate_on_lcm_drivers_covers_the_box_in_the_simulated_lab():
    scenario = LoadScenario(scenario_name="box_panda")
    prepared, run, lab, lab_station = _hardware_run(scenario)
    summary = ScoreEpisode(scenario, prepared, run)
    assert summary["error"] is None, summary
    assert summary["termination"] == "classifier", summary
    assert "success" not in summary
    assert "none on hardware" in summary["ground_truth"]
    assert summary["steps"] >= 10
    # Judged afterwards on the lab's true cloth, which the imitation never read.
    station = lab_station.diagram
    context = station.GetMyContextFromRoot(run.simulator.get_context())
    positions = np.array(
        station.GetOutputPort(StationPorts.CLOTH_POSITIONS).Eval(context)
    ).reshape(-1, 3)
    report = TaskSuccess(scenario, positions, lab_station.mesh.top_layer)
    assert report.success, report.details
    released = station.GetOutputPort(StationPorts.RELEASED).Eval(context)
    assert released[0] == 1.0  # the hand open commands reached the lab


@pytest.mark.slow
def test_a_camera_that_stops_ends_the_run_within_one_control_period():
    scenario = LoadScenario(scenario_name="box_panda")
    _, run, _, _ = _hardware_run(scenario, stop_camera_at=0.6)
    assert run.error is not None
    match = re.search(r"stopped sending images at t = ([0-9.]+) s", run.error)
    assert match, run.error
    last_image = float(match.group(1))
    assert 0.5 <= last_image <= 0.65, run.error
    stopped_at = run.simulator.get_context().get_time()
    assert stopped_at - last_image <= scenario.motion.step_seconds, stopped_at


class _CtrlC(LeafSystem):
    """Sends this process SIGINT (Ctrl-C) at time `at`, mid-step."""

    def __init__(self, at):
        super().__init__()
        self.DeclarePeriodicPublishEvent(1e6, at, self._interrupt)

    def _interrupt(self, context):
        os.kill(os.getpid(), signal.SIGINT)


@pytest.mark.slow
def test_ctrl_c_tells_both_arms_to_hold_and_says_so():
    scenario = LoadScenario(scenario_name="box_panda")
    prepared = PrepareImitation(
        scenario, demo_dir=DefaultDemoDir("box_panda", scenario)
    )
    lcm = DrakeLcm("memq://")
    imitation = MakeImitationDiagram(scenario, prepared, hardware=True, lcm=lcm)
    lab, _ = MakeSimulatedLab(scenario, lcm=lcm)
    builder = DiagramBuilder()
    for system in (imitation.diagram, lab, _CtrlC(0.65)):
        builder.AddSystem(system)
    # What the drivers receive (a Python handler on DrakeLcm itself would be
    # called from inside the simulation; a subscriber system is the safe way).
    commands = {
        side: builder.AddSystem(
            LcmSubscriberSystem.Make(
                getattr(scenario.grippers.panda, side).command_channel,
                lcmt_panda_command,
                lcm,
            )
        )
        for side in ("left", "right")
    }
    root = builder.Build()
    with pytest.raises(KeyboardInterrupt, match="told to hold"):
        RunEpisode(imitation, settle_seconds=1.0, root=root)
    lcm.HandleSubscriptions(0)
    for subscriber in commands.values():
        value = AbstractValue.Make(lcmt_panda_command())
        assert subscriber.WaitForMessage(0, value, timeout=0.1) > 0
        hold = value.get_value()
        # The last command, sent when Ctrl-C was acted on (at the end of the
        # control step under way), holds the measured joint positions.
        assert hold.num_joint_position == 7
        assert 0.65 <= hold.utime / 1e6 <= 0.65 + scenario.motion.step_seconds
        # sent by the runner (at k * dt + 3 ms), not by the IK's command
        # publisher (every 10 ms)
        assert hold.utime % 10000 == 3000, hold.utime
        assert np.all(np.isfinite(hold.joint_position))


@pytest.mark.parametrize("engine", ["vbd", "fem"])
def test_hardware_cloth_ports_have_the_simulated_station_sizes(engine):
    # FEM and VBD grids of different sizes: each engine's slab must decide.
    text = (
        f"cloth: {{engine: {engine}, resolution: [5, 5, 2], "
        "vbd: {resolution: [6, 6]}}\n"
    )
    scenario = LoadScenario(scenario_name="box_panda", scenario_text=text)
    simulated = MakeClothStation(scenario).diagram
    hardware = MakeHardwareClothStation(scenario, lcm=DrakeLcm("memq://")).diagram
    for name in (StationPorts.CLOTH_POSITIONS, StationPorts.CLOTH_KEYPOINTS):
        assert (
            hardware.GetOutputPort(name).size() == simulated.GetOutputPort(name).size()
        ), name
