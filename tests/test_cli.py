"""The CLI checks what it can before any work starts: one-line errors, exit
status 2, in well under the time the heavy imports take."""

import subprocess
import sys
import time

import pytest
from fabric_imitation.tools.cli import main


@pytest.mark.parametrize(
    "argv, message",
    [
        (
            ["imitate", "--scenario-text", "cloth: {engine: [vbd"],
            "--scenario-text: YAML syntax error at line 1, column",
        ),
        (["imitate", "--scenario-text", "- 1\n- 2"], "must be a YAML mapping"),
        (
            ["watch", "/no/runs.jsonl", "--scenario", "box", "--trial", "0"],
            "no evaluate file /no/runs.jsonl",
        ),
        (["evaluate", "--trials", "0", "--out", "x.jsonl"], "--trials must be at"),
        (["evaluate", "--workers", "0", "--out", "x.jsonl"], "--workers must be at"),
        (
            ["evaluate", "--sampling-seed", "-1", "--out", "x.jsonl"],
            "--sampling-seed must be >= 0",
        ),
        (
            ["imitate", "--record", "/no/such/dir/run.html"],
            "--record /no/such/dir/run.html: directory /no/such/dir does not exist",
        ),
        (
            [
                "demo",
                "record",
                "--scenario",
                "box",
                "--out",
                "d",
                "--video",
                "/no/v.mp4",
            ],
            "--video /no/v.mp4: directory /no does not exist",
        ),
    ],
)
def test_bad_arguments_are_one_line_errors(argv, message, capsys):
    assert main(argv) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1, err
    assert err.startswith("fabric-imitate: error: ") and message in err, err


def test_argument_errors_come_before_heavy_imports():
    t0 = time.perf_counter()
    result = subprocess.run(
        [
            sys.executable,
            "-m",
            "fabric_imitation.tools.cli",
            "evaluate",
            "--trials",
            "0",
            "--out",
            "x.jsonl",
        ],
        capture_output=True,
        text=True,
        timeout=60,
    )
    seconds = time.perf_counter() - t0
    assert result.returncode == 2
    assert "--trials must be at least 1" in result.stderr
    assert seconds < 2.0, seconds


def test_old_flag_spellings_work_with_a_note(capsys):
    assert main(["imitate", "--scenario_text", "[1]"]) == 2
    err = capsys.readouterr().err
    assert "note: --scenario_text is now spelled --scenario-text" in err
    assert "must be a YAML mapping" in err


@pytest.mark.parametrize("verbose", [False, True])
def test_native_chatter_is_filtered_unless_verbose(verbose):
    code = (
        "import os, time\n"
        "from fabric_imitation.tools.cli import _stdout_for_summary_only\n"
        f"out = _stdout_for_summary_only(verbose={verbose})\n"
        "os.write(1, b'Polishing not needed - no active set\\nsolver says hi\\n')\n"
        "time.sleep(0.3)\n"
        "out.write('{}\\n')\n"
    )
    result = subprocess.run(
        [sys.executable, "-c", code], capture_output=True, text=True, timeout=60
    )
    assert result.stdout == "{}\n"  # stdout keeps only the summary
    assert "solver says hi" in result.stderr
    assert ("Polishing" in result.stderr) == verbose


@pytest.mark.parametrize(
    "text, field",
    [
        ("camera: {width: abc}", "camera.width"),
        ("cloth: {vbd: {resolution: 16}}", "cloth.vbd.resolution"),
    ],
)
def test_a_value_of_the_wrong_type_names_its_field(text, field, capsys):
    assert main(["imitate", "--scenario-text", text]) == 2
    err = capsys.readouterr().err
    assert f"--scenario-text: {field}: " in err and err.count("\n") == 1, err


def test_an_object_pose_merges_into_a_one_line_scenario_text():
    from argparse import Namespace

    from fabric_imitation.tools.cli import LoadScenarioFromArgs

    scenario = LoadScenarioFromArgs(
        Namespace(
            scenario="box",
            scenario_file=None,
            scenario_text="{cloth: {pose: [0.01, 0.22, 5.0]}, object: {friction: 0.7}}",
            object_pose=[0.05, -0.1, 30.0],
            policy=None,
            policy_text="mpc: {max_iterations: 7}",
        )
    )
    assert scenario.object.pose == [0.05, -0.1, 30.0]
    assert scenario.object.friction == 0.7
    assert scenario.cloth.pose == [0.01, 0.22, 5.0]
    assert scenario.mpc.max_iterations == 7
