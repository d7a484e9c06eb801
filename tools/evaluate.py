"""`fabric-imitate evaluate`: trials with the object moved and rotated away
from the demo's pose (the paper's Transformation protocol), for our method,
its ablations, or the scripted demo itself.

Each trial is stored as one JSON line as soon as it finishes, so an
interrupted evaluation resumes where it stopped.
"""

import dataclasses as dc
import hashlib
import json
import math
import os
import sys
import time
from pathlib import Path

import numpy as np
from fabric_imitation.learning.errors import InputError
from fabric_imitation.tools.executors import EXECUTORS, RunJobs

# Method -> (controller of MakeImitationDiagram, changes to the scenario's
# MPC settings).
METHODS = {
    "ours": ("mpc", {}),
    # The ablations as the paper defines them (Sec. V-C). No MPC applies f_I's
    # action towards the subgoal as it is: no sampling, no projection onto
    # the safe set, no check (the referee judges what it does), f_I even
    # where the scenario's prior is the grasped corners'. No Prior samples
    # around zero; No Cost drops the constraint cost.
    "no_mpc": ("mpc", {"use_mpc": False, "use_cost": False, "prior": "inverse"}),
    "no_prior": ("mpc", {"use_prior": False}),
    "no_cost": ("mpc", {"use_cost": False}),
    # An extra row: the first action of the scenario's prior, projected onto
    # the safe set (ends the episode where no valid action is near).
    "no_mpc_safe": ("mpc", {"use_mpc": False}),
    # The baselines (learning/baselines.py), trained by
    # `fabric-imitate train-baselines` on the same prior dataset.
    "zero": ("zero", {}),
    "cfm": ("cfm", {}),
    "tcn": ("tcn", {}),
    "tcn_mpc": ("tcn_mpc", {}),  # TCN's reward on our planner, safe set and prior
    # Replay: the demo's grasped-corner path (f_R on its frames) followed in
    # the object frame of the trial; no learning beyond f_R.
    "replay": ("replay", {}),
    "scripted": (None, {}),  # the scripted demonstration at the trial's pose
}
BASELINE_METHODS = ("zero", "cfm", "tcn", "tcn_mpc")
# Trial i of sampling seed K seeds its controller with i + this x K.
SAMPLING_SEED_STRIDE = 1000


# Protocol -> (largest move of the object [m], largest turn [deg]) away
# from the demo's pose: the paper's Translation and Transformation, and
# "wide", its "arbitrarily within the workspace".
PROTOCOLS = {
    "translation": (0.10, 0.0),
    "transformation": (0.10, 45.0),
    "wide": (0.15, 90.0),
}


def ProtocolPoses(
    scenario_name: str, protocol: str, *, trials: int, seed: int, scenario_text=""
) -> list[list[float]]:
    """The seeded pose list of `protocol` (see PROTOCOLS)."""
    if protocol not in PROTOCOLS:
        raise InputError(
            f"unknown protocol {protocol!r}; known: {', '.join(PROTOCOLS)}"
        )
    shift, yaw = PROTOCOLS[protocol]
    return TrialPoses(
        scenario_name,
        trials=trials,
        seed=seed,
        max_shift=shift,
        max_yaw_deg=yaw,
        scenario_text=scenario_text,
    )


def TrialScenario(
    name: str,
    text: str,
    pose: list[float] | None,
    cloth_start: list[float] | None = None,
    policy=None,
):
    """Scenario `name` with the YAML overrides `text` and, if given, the
    trial's object pose and the cloth's start ([dx, dy, dyaw_deg] from the
    scenario's cloth pose) on top, with `policy`'s settings (a Policy;
    default the shipped priors')."""
    import yaml
    from fabric_imitation.scenarios.loader import LoadScenario

    overrides = yaml.safe_load(text) if text.strip() else {}
    if not isinstance(overrides, dict):
        raise InputError(f"--scenario_text is not a YAML mapping: {text!r}")
    if pose is not None:
        overrides["object"] = {**overrides.get("object", {}), "pose": pose}
    if cloth_start is not None and any(cloth_start):
        base = LoadScenario(
            scenario_name=name,
            scenario_text=yaml.safe_dump(overrides) if overrides else "",
        ).cloth.pose
        moved = [round(b + d, 4) for b, d in zip(base, cloth_start, strict=True)]
        overrides["cloth"] = {**overrides.get("cloth", {}), "pose": moved}
    return LoadScenario(
        scenario_name=name,
        scenario_text=yaml.safe_dump(overrides) if overrides else "",
        policy=policy,
    )


# Each trial's cloth starts moved up to this far [m] and turned up to this
# much [deg] on the table from the scenario's cloth pose (the grippers start
# at its near corners); the demo keeps the nominal start.
CLOTH_START_SHIFT = 0.02
CLOTH_START_TURN_DEG = 10.0
# The cloth starts come from their own random stream, seeded (pose seed,
# this), so that adding them left every seed's object poses as they were.
CLOTH_STREAM = 1


def ClothStarts(
    scenario_name: str,
    poses: list[list[float]],
    *,
    seed: int,
    scenario_text: str = "",
) -> list[list[float]]:
    """[dx, dy, dyaw_deg] of the cloth's start for each trial pose; a start
    that does not fit with the trial's object (the scenario refuses it) is
    drawn again."""
    rng = np.random.default_rng([seed, CLOTH_STREAM])
    starts = []
    for pose in poses:
        while True:
            r = CLOTH_START_SHIFT * math.sqrt(rng.uniform())
            a = rng.uniform(0, 2 * math.pi)
            start = [
                round(r * math.cos(a), 4),
                round(r * math.sin(a), 4),
                round(rng.uniform(-CLOTH_START_TURN_DEG, CLOTH_START_TURN_DEG), 2),
            ]
            try:
                _CheckGrippersClear(
                    TrialScenario(scenario_name, scenario_text, pose, start)
                )
            except InputError:
                continue
            starts.append(start)
            break
    return starts


def TrialPoses(
    scenario_name: str,
    *,
    trials: int,
    seed: int,
    max_shift: float = 0.10,
    max_yaw_deg: float = 45.0,
    scenario_text: str = "",
) -> list[list[float]]:
    """Object poses moved up to `max_shift` and turned up to `max_yaw_deg` from
    the scenario's; poses outside the workspace or on the cloth are redrawn."""
    base = TrialScenario(scenario_name, scenario_text, None)
    rng = np.random.default_rng(seed)
    poses = []
    while len(poses) < trials:
        r = max_shift * math.sqrt(rng.uniform())
        a = rng.uniform(0, 2 * math.pi)
        yaw = rng.uniform(-max_yaw_deg, max_yaw_deg) if max_yaw_deg > 0 else 0.0
        p = base.object.pose
        pose = [
            round(p[0] + r * math.cos(a), 4),
            round(p[1] + r * math.sin(a), 4),
            round(p[2] + yaw, 2),
        ]
        try:
            _CheckGrippersClear(TrialScenario(scenario_name, scenario_text, pose))
        except InputError:
            continue
        poses.append(pose)
    return poses


# What each worker learned from the demos, by scenario name: set once per
# process (`_set_prepared`), so f_A is trained once per scenario, not per trial.
_PREPARED: dict = {}


def _set_prepared(prepared: dict) -> None:
    import logging

    import torch

    # As in the CLI: no CUDA warning from torch's extension helper in each worker.
    logging.getLogger("torch.utils.cpp_extension").setLevel(logging.ERROR)

    torch.set_num_threads(1)
    _PREPARED.update(prepared)


def _prepare(job: dict):
    """PrepareImitation for the scenario of `job` (at its base pose)."""
    import torch
    from fabric_imitation.diagrams.imitation import DefaultDemoDir, PrepareImitation
    from fabric_imitation.tools.episode import TorchThreads

    torch.set_num_threads(TorchThreads())
    scenario = TrialScenario(
        job["scenario"], job["scenario_text"], None, policy=_JobPolicy(job)
    )
    return PrepareImitation(
        scenario,
        demo_dir=job.get("demo") or DefaultDemoDir(job["scenario"], scenario),
        priors_dir=job.get("priors"),
        baselines=job.get("baselines", False),
    )


def _JobPolicy(job: dict):
    """The policy a job runs with: its file (default: the priors') and
    inline overrides."""
    from fabric_imitation.scenarios.policy import LoadPolicy

    return LoadPolicy(
        priors_dir=job.get("priors"),
        filename=job.get("policy"),
        policy_text=job.get("policy_text", ""),
    )


def _run_trial(
    job: dict,
    *,
    record: Path | None = None,
    video: Path | None = None,
    progress: bool = False,
) -> dict:
    """One trial of `job` (an evaluate job or a trial line of one); `record`
    and `video` (WatchTrial) write its meshcat recording and camera video."""
    import torch

    torch.set_num_threads(1)
    scenario = TrialScenario(
        job["scenario"],
        job["scenario_text"],
        job["pose"],
        job.get("cloth_start"),
        policy=_JobPolicy(job),
    )
    t0 = time.perf_counter()
    if job["method"] == "scripted":
        summary = ScriptedTrial(scenario, on_violation=job.get("on_violation", "stop"))
    else:
        from fabric_imitation.tools.episode import Imitate

        controller, changes = METHODS[job["method"]]
        try:
            summary = Imitate(
                scenario=scenario,
                scenario_name=job["scenario"],
                prepared=_PREPARED[job["scenario"]],
                mpc_config=dc.replace(scenario.mpc, **changes),
                controller=controller,
                progress=progress,
                record=record,
                video=video,
                seed=job["trial"] + SAMPLING_SEED_STRIDE * job.get("sampling_seed", 0),
                on_violation=job.get("on_violation", "stop"),
            )
        except Exception as e:  # noqa: BLE001 (one failed trial; the sweep goes on)
            summary = {
                "success": False,
                "error": f"{type(e).__name__}: {' '.join(str(e).split())[:300]}",
            }
    import resource

    return {
        **job,
        **summary,
        "trial_seconds": round(time.perf_counter() - t0, 1),
        # The worker process and its largest resident set so far [MB]: a
        # sweep's memory is flat when these stay flat across its trials.
        "worker": {
            "pid": os.getpid(),
            "max_rss_mb": round(
                resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024, 1
            ),
        },
    }


def _CheckGrippersClear(scenario) -> None:
    from fabric_imitation.tasks.referee import CheckGrippersClear

    CheckGrippersClear(scenario)


def ScriptedTrial(scenario, *, on_violation: str = "stop") -> dict:
    """The task's scripted demo at the scenario's poses, judged as a method's
    trial: success, and the referee's rule breaks on the true cloth and the
    gripper-object contacts. It is never cut short (the demo is the
    ceiling), but under "stop" a break or a contact makes it a failure."""
    from fabric_imitation.diagrams.station import StationPorts
    from fabric_imitation.learning.state import PlanarPose, world_to_object
    from fabric_imitation.tasks.demos import ScriptedDemoPlan
    from fabric_imitation.tasks.referee import JudgeTransitions, TaskReferee
    from fabric_imitation.tools.simulation import OpenLoopRun

    plan = ScriptedDemoPlan(scenario)
    run = OpenLoopRun(scenario, actions=plan.actions, release_step=plan.release_step)
    station = run.station.diagram
    pose = PlanarPose.FromDegrees(scenario.object.pose)

    def keypoints_O() -> np.ndarray:
        p_W = station.GetOutputPort(StationPorts.CLOTH_KEYPOINTS).Eval(
            run.station_context
        )
        return world_to_object(np.reshape(p_W, (-1, 3)), np.array(pose))

    states = [keypoints_O()]
    result = run.run(
        capture_frames=False, on_step=lambda k, frame: states.append(keypoints_O())
    )
    n = len(states) - 1
    actions_O = np.array(
        [pose.vector_to_object(a.reshape(2, 3)).ravel() for a in plan.actions[:n]]
    ).reshape(n, 6)
    judged = JudgeTransitions(
        TaskReferee(scenario.task),
        scenario,
        np.array(states[:-1]).reshape(n, -1, 3),
        actions_O,
        np.array(states[1:]).reshape(n, -1, 3),
    )
    summary = {
        "success": bool(result.success.success),
        "success_details": result.success.details,
        "error": result.error,
        "rule_breaks_true": {rule: int(v.sum()) for rule, v in judged.items()},
        "true_rule_break_steps": np.flatnonzero(judged["any"]).tolist(),
        "steps": n,
    }
    if station.HasOutputPort(StationPorts.GRIPPER_OBJECT_CONTACT):
        contact = station.GetOutputPort(StationPorts.GRIPPER_OBJECT_CONTACT).Eval(
            run.station_context
        )
        summary["collisions"] = int(contact[0])
    if on_violation == "stop" and (
        summary["rule_breaks_true"]["any"] or summary.get("collisions")
    ):
        summary["success"] = False
    return summary


def _aggregate(rows: list[dict]) -> dict:
    from fabric_imitation.learning.safety import RULES

    ok = [r["success"] for r in rows]
    out = {
        "trials": len(rows),
        "successes": int(sum(ok)),
        "success_rate": round(float(np.mean(ok)), 3) if rows else None,
    }
    # Rows of trials that crashed (an exception in the trial, recorded as a
    # failure) carry no episode figures.
    crashed = [r for r in rows if "final_iou" not in r and "termination" not in r]
    if len(crashed) < len(rows) and any("final_iou" in r for r in rows):
        out["crashed"] = len(crashed)
        rows = [r for r in rows if r not in crashed]
        ious = np.array([r["final_iou"] for r in rows])
        ch = np.array([r["final_chamfer"] for r in rows])
        out.update(
            {
                "iou_mean": round(float(ious.mean()), 3),
                "iou_std": round(float(ious.std()), 3),
                "chamfer_mean": round(float(ch.mean()), 6),
                "executed_violations": int(sum(r["executed_violations"] for r in rows)),
                "executed_violations_ground_truth": int(
                    sum(r["executed_violations_ground_truth"] for r in rows)
                ),
                "rule_breaks_true": {
                    rule: int(
                        sum(r.get("rule_breaks_true", {}).get(rule, 0) for r in rows)
                    )
                    for rule in ("any", *RULES)
                },
                "trials_with_true_rule_breaks": int(
                    sum(r["executed_violations_ground_truth"] > 0 for r in rows)
                ),
                "steps_mean": round(float(np.mean([r["steps"] for r in rows])), 1),
                "trial_seconds_mean": round(
                    float(np.mean([r["trial_seconds"] for r in rows])), 1
                ),
                "terminations": {
                    t: sum(r["termination"] == t for r in rows)
                    for t in sorted({r["termination"] for r in rows})
                },
                "mpc_step_ms_p95_max": max(
                    (r["mpc_step_ms"]["p95"] or 0) for r in rows
                ),
            }
        )
    return out


def _hash_files(paths: list[Path], root: Path | None = None) -> str:
    """16 hex digits of sha256 over the files' names (relative to `root`)
    and contents, in sorted order; "none" for no files."""
    paths = sorted(p for p in paths if p.is_file())
    if not paths:
        return "none"
    h = hashlib.sha256()
    for p in paths:
        h.update(str(p.relative_to(root) if root else p.name).encode())
        h.update(p.read_bytes())
    return h.hexdigest()[:16]


def CodeFingerprint() -> str:
    """The project's Python sources and scenario files."""
    root = Path(__file__).resolve().parent.parent
    files = [
        p
        for folder in ("learning", "scenarios", "systems", "tasks", "diagrams", "tools")
        for p in (root / folder).rglob("*")
        if p.suffix in (".py", ".yaml")
        and "__pycache__" not in p.parts
        and "demos" not in p.parts  # the demo's own fingerprint covers it
        and p.name != "report.py"  # reads trial lines, makes none
    ]
    return _hash_files(files, root)


# x86 vector extensions that change which floating-point code paths torch,
# numpy and the cloth's compiled kernels take, most capable first.
VECTOR_EXTENSIONS = ("avx512f", "avx2", "avx", "sse4_2")


def Machine() -> dict:
    """The machine a trial ran on, as far as its floating point goes: the
    CPU model, the widest vector extension it has, torch's version, and a
    short id of the three. The same seed gives the same trial on one
    machine, idle or busy; on a CPU with other vector extensions the
    sums round differently and trajectories part after a few steps, so
    paired comparisons are run on one machine (`compare` says when the
    sides differ)."""
    import platform

    import torch

    model, flags = "", set()
    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            key, _, value = line.partition(":")
            if key.strip() == "model name" and not model:
                model = value.strip()
            elif key.strip() == "flags" and not flags:
                flags = set(value.split())
    except OSError:  # not Linux: the architecture only
        pass
    model = model or platform.processor() or platform.machine()
    vector = next((v for v in VECTOR_EXTENSIONS if v in flags), platform.machine())
    text = json.dumps([model, vector, torch.__version__])
    return {
        "cpu": model,
        "vector": vector,
        "torch": torch.__version__,
        "id": hashlib.sha256(text.encode()).hexdigest()[:8],
    }


def TrialFingerprints(
    scenario_name: str,
    *,
    scenario_text: str,
    demo: Path | None,
    priors: Path | None,
    policy=None,
) -> dict:
    """What a trial's figures depend on besides its poses and seeds: the
    code, the priors, the baselines, the referee's rules, the demo and the
    scenario (at its nominal poses). Rows of a table must share the first
    four; a row also the last two (`fabric-imitate report` checks)."""
    from fabric_imitation.diagrams.imitation import DEFAULT_PRIORS, DefaultDemoDir
    from fabric_imitation.scenarios.schema import Scenario
    from fabric_imitation.tasks.referee import TaskReferee
    from pydrake.common.yaml import yaml_dump_typed

    scenario = TrialScenario(scenario_name, scenario_text, None, policy=policy)
    priors_dir = Path(priors) if priors else DEFAULT_PRIORS
    demo_dir = Path(demo) if demo else DefaultDemoDir(scenario_name, scenario)
    text = yaml_dump_typed(scenario, schema=Scenario)
    return {
        "code": CodeFingerprint(),
        "priors": _hash_files([priors_dir / "priors.pt", priors_dir / "priors.json"]),
        "baselines": _hash_files(
            [priors_dir / "baselines.pt", priors_dir / "baselines.json"]
        ),
        "referee": TaskReferee(scenario.task).fingerprint(),
        "demo": _hash_files(list(demo_dir.glob("*"))),
        "scenario": hashlib.sha256(text.encode()).hexdigest()[:16],
    }


# Trials one worker process runs before a fresh one replaces it: a process's
# memory grows with the pydrake and torch objects of each trial's diagram,
# so a long sweep runs in fresh processes.
WORKER_TRIALS = 10


def Evaluate(
    *,
    scenario_names: list[str],
    methods: list[str],
    trials: int,
    out: Path,
    workers: int = 1,
    seed: int = 0,
    demo: Path | None = None,
    priors: Path | None = None,
    scenario_text: str = "",
    policy: Path | None = None,
    policy_text: str = "",
    progress: bool = True,
    protocol: str = "transformation",
    executor: str = "local",
    sampling_seed: int = 0,
    on_violation: str = "stop",
    worker_trials: int = WORKER_TRIALS,
) -> dict:
    """Runs `trials` trials per scenario and method (resumable via `out`,
    a JSON-lines file of finished trials); writes `out`.summary.json and a
    bar plot `out`.png. `scenario_text` (YAML) overrides every scenario, e.g.
    "cloth: {engine: fem}"; the method's settings are the policy file
    `policy` (default: the priors') with `policy_text` (YAML) on top.

    `seed` draws the object poses; `sampling_seed` the controllers' random
    sampling (trial i samples with seed i + SAMPLING_SEED_STRIDE x
    sampling_seed): the same poses under another sampling seed are an
    equally valid run, so their spread is the run-to-run spread of a
    count. `seed` also draws each trial's cloth start (ClothStarts).

    `on_violation`: "stop" ends a trial at the referee's first rule break or
    gripper-object contact on the true cloth (tasks/referee.py); "count"
    only counts. Trials run in worker processes that are replaced after
    `worker_trials` trials each (0: with one worker, in this process)."""
    _CheckEvaluateArgs(
        methods=methods,
        executor=executor,
        sampling_seed=sampling_seed,
        on_violation=on_violation,
        worker_trials=worker_trials,
    )
    out = Path(out)
    from fabric_imitation.scenarios.policy import LoadPolicy

    chosen = LoadPolicy(priors_dir=priors, filename=policy, policy_text=policy_text)
    run = dict(
        protocol=protocol,
        sampling_seed=sampling_seed,
        on_violation=on_violation,
        pose_seed=seed,
    )
    resumed = _ResumedTrials(out, run)
    pose_lists = {
        name: ProtocolPoses(
            name, protocol, trials=trials, seed=seed, scenario_text=scenario_text
        )
        for name in scenario_names
    }
    cloth_starts = {
        name: ClothStarts(name, poses, seed=seed, scenario_text=scenario_text)
        for name, poses in pose_lists.items()
    }
    fingerprints = {
        name: TrialFingerprints(
            name, scenario_text=scenario_text, demo=demo, priors=priors, policy=chosen
        )
        for name in scenario_names
    }
    _CheckResumable(resumed.values(), fingerprints, scenario_text, out)
    common = {
        "machine": Machine(),
        "demo": str(demo) if demo else None,
        "priors": str(priors) if priors else None,
        "scenario_text": scenario_text,
        "policy": str(policy) if policy else None,
        "policy_text": policy_text,
        "protocol": protocol,
        "sampling_seed": sampling_seed,
        "baselines": any(m in BASELINE_METHODS for m in methods),
    }
    jobs = [
        {
            "scenario": name,
            "method": method,
            "trial": i,
            "pose": pose,
            "cloth_start": cloth_starts[name][i],
            "pose_seed": seed,
            "on_violation": on_violation,
            "fingerprint": fingerprints[name],
            **common,
        }
        for name, poses in pose_lists.items()
        for method in methods
        for i, pose in enumerate(poses)
        if (name, method, i) not in resumed
    ]
    prepared, prepare_seconds = _PrepareDemos(jobs)
    store = _TrialStore(out, dict(resumed), total=len(jobs) if progress else None)
    # What was learned from the demos goes to every worker once.
    for row in RunJobs(
        _run_trial,
        jobs,
        workers=workers,
        executor=executor,
        init=_set_prepared,
        init_args=(prepared,),
        tasks_per_worker=worker_trials,
        ordered=False,
    ):
        store.add(row)
    store.close()
    cells = {
        (name, method): [
            r
            for (s, m, _), r in sorted(store.done.items())
            if s == name and m == method and r["trial"] < trials
        ]
        for name in scenario_names
        for method in methods
    }
    table = {}
    for (name, method), rows in cells.items():
        table.setdefault(name, {})[method] = _aggregate(rows)
    summary = {
        "protocol": protocol,
        "protocol_band": {
            "max_shift_m": PROTOCOLS[protocol][0],
            "max_turn_deg": PROTOCOLS[protocol][1],
        },
        "trials_per_cell": trials,
        "seed": seed,
        "sampling_seed": sampling_seed,
        "on_violation": on_violation,
        "poses": pose_lists,
        "cloth_starts": cloth_starts,
        "fingerprints": fingerprints,
        "prepare_seconds": prepare_seconds,
        "results": table,
        "failures": [
            {k: r.get(k) for k in FAILURE_FIELDS}
            for r in store.done.values()
            if not r["success"]
        ],
    }
    Path(str(out) + ".summary.json").write_text(json.dumps(summary, indent=1))
    _plot(table, Path(str(out) + ".png"))
    _plot_curves(cells, Path(str(out) + ".curves.png"))
    Path(str(out) + ".md").write_text(ResultsMarkdown(summary))
    return summary


# What the summary lists of each failed trial.
FAILURE_FIELDS = (
    "scenario",
    "method",
    "trial",
    "pose",
    "termination",
    "success_details",
    "error",
)


def _CheckEvaluateArgs(
    *, methods, executor, sampling_seed, on_violation, worker_trials
) -> None:
    from fabric_imitation.tasks.referee import ON_VIOLATION

    if on_violation not in ON_VIOLATION:
        raise InputError(
            f"unknown --on-violation {on_violation!r}; use {' or '.join(ON_VIOLATION)}"
        )
    if worker_trials < 0:
        raise InputError(f"worker_trials must be >= 0, got {worker_trials}")
    if sampling_seed < 0:
        raise InputError(f"--sampling-seed must be >= 0, got {sampling_seed}")
    if executor not in EXECUTORS:
        raise InputError(f"unknown executor {executor!r}; use local or ray")
    unknown = [m for m in methods if m not in METHODS]
    if unknown:
        raise InputError(f"unknown method(s) {unknown}; known: {', '.join(METHODS)}")


def _ResumedTrials(out: Path, run: dict) -> dict:
    """(scenario, method, trial) -> the row, for the trial lines of `out` of
    this run (protocol, sampling seed, rule, pose seed); a line cut by a
    kill is skipped, so its trial runs again."""
    done = {}
    if not out.exists():
        return done
    for line in out.read_text().splitlines():
        try:
            row = json.loads(line)
        except json.JSONDecodeError:
            continue
        if (
            row.get("protocol", "transformation") == run["protocol"]
            and row.get("sampling_seed", 0) == run["sampling_seed"]
            and row.get("on_violation") == run["on_violation"]
            and row.get("pose_seed") == run["pose_seed"]
        ):
            done[(row["scenario"], row["method"], row["trial"])] = row
    return done


def _CheckResumable(rows, fingerprints: dict, scenario_text: str, out: Path) -> None:
    for row in rows:
        if row["scenario"] in fingerprints and (
            row.get("fingerprint") != fingerprints[row["scenario"]]
            or row.get("scenario_text", "") != scenario_text
        ):
            raise InputError(
                f"{out} holds trials of {row['scenario']} run with other code, "
                "priors, baselines, demo, scenario or policy settings (their "
                "fingerprint or --scenario-text differs); give another --out"
            )


def _PrepareDemos(jobs: list[dict]) -> tuple[dict, dict]:
    """Learns from each scenario's demo once (f_R on its frames, f_A), here:
    scenario -> what was learned, and the seconds it took."""
    prepared, seconds = {}, {}
    for job in jobs:
        if job["method"] != "scripted" and job["scenario"] not in prepared:
            t0 = time.perf_counter()
            prepared[job["scenario"]] = _prepare(job)
            seconds[job["scenario"]] = round(time.perf_counter() - t0, 1)
    return prepared, seconds


# What a trial line holds of its job: enough to run the trial again.
_JOB_FIELDS = (
    "scenario",
    "method",
    "trial",
    "pose",
    "cloth_start",
    "pose_seed",
    "on_violation",
    "demo",
    "priors",
    "scenario_text",
    "policy",
    "policy_text",
    "protocol",
    "sampling_seed",
    "baselines",
)


def WatchTrial(
    *,
    runs: Path,
    scenario: str,
    trial: int,
    method: str | None = None,
    demo: Path | None = None,
    record: Path | None = None,
    video: Path | None = None,
    progress: bool = True,
) -> dict:
    """Runs trial `trial` of `scenario` in the evaluate file `runs` again as
    evaluate ran it (its object pose, cloth start, demo, priors, policy,
    sampling seed and stopping rule), writing its meshcat recording
    (`record`, HTML) and the camera's video (`video`, mp4) to watch it.
    `method` picks one where the file holds several; `demo`, a demo
    directory in place of the one the line names (recorded again elsewhere).

    Returns the new run's summary with `row` (the file's steps, termination
    and success), `same_course` (whether the run repeats the row's Chamfer
    curve, steps and termination) and `differs` (what differs from the
    row's run: code, priors, demo, ..., machine; on another machine or code
    the same trial can take another course)."""
    row = _TrialRow(Path(runs), scenario, trial, method)
    if row["method"] == "scripted":
        raise InputError(
            "watch runs a controller's trial; the scripted demo is watched "
            "with `fabric-imitate simulate --record` or `demo record`"
        )
    if row["method"] not in METHODS:
        raise InputError(
            f"trial line's method {row['method']!r} is unknown to this code; "
            f"known: {', '.join(METHODS)}"
        )
    job = {k: row.get(k) for k in _JOB_FIELDS}
    if demo is not None:
        job["demo"] = str(demo)
    for key in ("demo", "priors", "policy"):
        if job[key] and not Path(job[key]).exists():
            raise InputError(
                f"the trial's {key} {job[key]} does not exist"
                + (" (give its place with --demo)" if key == "demo" else "")
            )
    now = TrialFingerprints(
        scenario,
        scenario_text=job["scenario_text"] or "",
        demo=job["demo"],
        priors=job["priors"],
        policy=_JobPolicy(job),
    )
    differs = [k for k, v in now.items() if row.get("fingerprint", {}).get(k) != v]
    if (row.get("machine") or {}).get("id") != Machine()["id"]:
        differs.append("machine")
    prepared, _ = _PrepareDemos([job])
    _set_prepared(prepared)
    new = _run_trial(job, record=record, video=video, progress=progress)
    new.pop("worker", None)
    keys = ("steps", "termination", "success")
    return {
        **new,
        "runs": str(runs),
        "row": {k: row.get(k) for k in keys},
        "same_course": all(new.get(k) == row.get(k) for k in keys)
        and new.get("chamfer_over_steps") == row.get("chamfer_over_steps"),
        "differs": differs,
    }


def _TrialRow(runs: Path, scenario: str, trial: int, method: str | None) -> dict:
    """The trial line of `runs` for (scenario, trial[, method])."""
    if not runs.is_file():
        raise InputError(f"no evaluate file {runs}")
    rows = []
    for line in runs.read_text().splitlines():
        try:
            rows.append(json.loads(line))
        except json.JSONDecodeError:
            continue  # a line cut by a kill: that trial has no row
    rows = [r for r in rows if isinstance(r, dict) and "scenario" in r and "trial" in r]
    if not rows:
        raise InputError(f"{runs} holds no trial lines of `fabric-imitate evaluate`")
    names = sorted({r["scenario"] for r in rows})
    if scenario not in names:
        raise InputError(
            f"{runs} has no {scenario!r} trials; it has {', '.join(names)}"
        )
    found = [r for r in rows if r["scenario"] == scenario and r["trial"] == trial]
    if method is not None:
        found = [r for r in found if r.get("method") == method]
    if not found:
        trials = sorted({r["trial"] for r in rows if r["scenario"] == scenario})
        raise InputError(
            f"{runs} has no {scenario!r} trial {trial}"
            + (f" of method {method!r}" if method else "")
            + f"; its trials: {trials[0]}-{trials[-1]}"
        )
    methods = sorted({r.get("method") for r in found})
    if len(methods) > 1:
        raise InputError(
            f"{scenario!r} trial {trial} ran with methods {', '.join(methods)} in "
            f"{runs}: pick one with --method"
        )
    if len(found) > 1:
        runs_of = sorted(
            {(r.get("pose_seed"), r.get("sampling_seed", 0)) for r in found}, key=str
        )
        raise InputError(
            f"{runs} holds {len(found)} runs of {scenario!r} trial {trial} "
            f"(pose seed, sampling seed: {runs_of}); watch reads a file of one run"
        )
    return found[0]


class _TrialStore:
    """Appends each finished trial to `out` (flushed to disk: a sweep killed
    at any moment resumes), and shows progress with the running success of
    each scenario and method, e.g. "box/ours 4/5" (`total` None: quiet)."""

    def __init__(self, out: Path, done: dict, total: int | None):
        self.out, self.done = out, done
        self.bar = None
        if total is not None:
            from tqdm import tqdm

            self.bar = tqdm(total=total, desc="evaluate", unit="trial", file=sys.stderr)
        out.parent.mkdir(parents=True, exist_ok=True)

    def add(self, row: dict) -> None:
        with open(self.out, "a") as f:
            f.write(json.dumps(row) + "\n")
            f.flush()
            os.fsync(f.fileno())
        self.done[(row["scenario"], row["method"], row["trial"])] = row
        if self.bar is not None:
            self.bar.update()
            cells = {}
            for (scenario, method, _), r in self.done.items():
                ok, n = cells.get(f"{scenario}/{method}", (0, 0))
                cells[f"{scenario}/{method}"] = (ok + bool(r["success"]), n + 1)
            self.bar.set_postfix_str(
                " ".join(f"{k} {ok}/{n}" for k, (ok, n) in sorted(cells.items()))
            )

    def close(self) -> None:
        if self.bar is not None:
            self.bar.close()


def ResultsMarkdown(summary: dict) -> str:
    """The summary's results as a Markdown table in the layout of the
    paper's Table I (one row per task and method)."""
    lines = [
        f"Protocol `{summary['protocol']}` (object moved <= "
        f"{summary['protocol_band']['max_shift_m'] * 100:g} cm, turned <= "
        f"{summary['protocol_band']['max_turn_deg']:g} deg), pose seed "
        f"{summary['seed']}, sampling seed {summary.get('sampling_seed', 0)}, "
        f"{summary['trials_per_cell']} trials per cell.",
        "",
        "| task | method | success | IoU | Chamfer [m] | true rule breaks "
        "(trials with any) | steps (mean) |",
        "|---|---|---|---|---|---|---|",
    ]
    for task, methods in summary["results"].items():
        for method, r in methods.items():
            if not r["trials"]:
                continue
            success = (
                f"{r['successes']} / {r['trials']} ({100 * r['success_rate']:.0f}%)"
            )
            if "iou_mean" in r:
                iou = f"{r['iou_mean']:.2f} +- {r['iou_std']:.2f}"
                chamfer = f"{r['chamfer_mean']:.4f}"
                breaks = (
                    f"{r['executed_violations_ground_truth']} "
                    f"({r['trials_with_true_rule_breaks']})"
                )
                steps = f"{r['steps_mean']:.1f}" if "steps_mean" in r else "-"
            else:
                iou = chamfer = breaks = steps = "-"
            lines.append(
                f"| {task} | {method} | {success} | {iou} | {chamfer} | {breaks} "
                f"| {steps} |"
            )
    return "\n".join(lines) + "\n"


def _plot(table: dict, path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    names = list(table)
    methods = sorted({m for v in table.values() for m in v})
    fig, ax = plt.subplots(figsize=(1.5 + 1.2 * len(names) * len(methods) / 2, 3))
    width = 0.8 / max(len(methods), 1)
    for k, m in enumerate(methods):
        rates = [table[n].get(m, {}).get("success_rate") or 0 for n in names]
        ax.bar(np.arange(len(names)) + k * width, rates, width, label=m)
    ax.set_xticks(np.arange(len(names)) + 0.4 - width / 2, names)
    ax.set_ylabel("success rate")
    ax.set_ylim(0, 1)
    ax.legend(fontsize=8)
    fig.tight_layout()
    fig.savefig(path, dpi=90)
    plt.close(fig)


# The accumulated return of Fig. 8 c-d: the paper gives "a positive reward
# for episodic success and a negative warning reward" for each action that
# breaks a safety rule, without values; these are ours.
SUCCESS_REWARD = 10.0
WARNING_REWARD = -1.0


def EpisodeReturns(row: dict) -> np.ndarray:
    """Accumulated return after each executed action of one trial:
    WARNING_REWARD for each action that broke a rule on the true cloth,
    SUCCESS_REWARD at the last action if the trial succeeded."""
    n = max(int(row.get("steps") or 0), 1)
    r = np.zeros(n)
    for k in row.get("true_rule_break_steps") or []:
        r[min(k, n - 1)] += WARNING_REWARD
    if row.get("success"):
        r[-1] += SUCCESS_REWARD
    return np.cumsum(r)


def _padded_mean(series: list) -> np.ndarray:
    """Mean over trials of series of different lengths, each held at its
    last value after it ends (an episode that ended stays where it ended)."""
    n = max(len(x) for x in series)
    return np.mean([np.r_[x, np.full(n - len(x), x[-1])] for x in series], 0)


def _plot_curves(cells: dict, path: Path) -> None:
    """Per task: the mean Chamfer distance to the demo's last frame before
    each control step (Fig. 8 a-b) and the mean accumulated return (Fig. 8
    c-d) of each method."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    names = sorted({name for name, _ in cells})
    fig, axes = plt.subplots(
        2, len(names), figsize=(4.5 * len(names), 6), squeeze=False
    )
    for col, name in enumerate(names):
        for (task, method), rows in cells.items():
            if task != name or not rows:
                continue
            chamfer = [
                np.array(r["chamfer_over_steps"], float)
                for r in rows
                if r.get("chamfer_over_steps")
            ]
            if chamfer:
                axes[0, col].plot(1000 * _padded_mean(chamfer), label=method)
            if any("steps" in r for r in rows):
                axes[1, col].plot(
                    _padded_mean([EpisodeReturns(r) for r in rows]), label=method
                )
        axes[0, col].set_title(f"{name}: Chamfer distance to the demo's end")
        axes[0, col].set_ylabel("Chamfer distance [1e-3 m^2]")
        axes[1, col].set_title(f"{name}: accumulated return")
        axes[1, col].set_xlabel("control step")
        axes[1, col].set_ylabel(
            f"return (+{SUCCESS_REWARD:g} success, {WARNING_REWARD:g} per rule break)"
        )
        for ax in axes[:, col]:
            if ax.get_legend_handles_labels()[0]:
                ax.legend(fontsize=7)
            else:  # only failed or empty trials: nothing to plot
                ax.text(
                    0.5,
                    0.5,
                    "no data",
                    ha="center",
                    va="center",
                    transform=ax.transAxes,
                )
    fig.tight_layout()
    fig.savefig(path, dpi=90)
    plt.close(fig)
