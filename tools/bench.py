"""`fabric-imitate bench sim`: real-time factor of the cloth simulation per
scenario, on one core, in two phases, with physical-correctness checks.

Both cloth engines (vbd, fem) side by side. Phase "flat": the cloth lies flat
on the table, grippers holding still. Phase "moving": the scripted task
motion (prior: a 36 cm lift). Phase "draped": box / box_big after the
scripted cover motion and release (cloth resting over the box), hang after
the scripted hang (cloth on the plate), prior with the cloth hanging from
the grippers 36 cm up. Real-time factors in wall time and in process CPU
time (the latter is what a loaded machine does not change).
"""

import contextlib
import dataclasses as dc
import hashlib
import json
import os
import platform
import sys
import time
from pathlib import Path

import numpy as np
from fabric_imitation.diagrams.station import StationPorts
from fabric_imitation.learning.errors import InputError
from fabric_imitation.learning.state import SIDES
from fabric_imitation.scenarios.loader import LoadScenario
from fabric_imitation.scenarios.schema import Scenario
from fabric_imitation.tasks.demos import ScriptedDemoPlan
from fabric_imitation.tasks.success import (
    DrapeReach,
    InObjectFrame,
    ReachDistances,
    SideFlapReach,
    TaskSuccess,
)
from fabric_imitation.tools.simulation import OpenLoopRun

DEFAULT_SCENARIOS = ("prior", "box", "hang", "box_big", "box_panda", "hang_panda")
# A vertex may sink this far [m] into the table or the object (contact is
# compliant; the slab is 4 mm thick) before the check fails.
PENETRATION_TOLERANCE = 0.006
# Upward vertex speed [m/s] that counts as "thrown".
THROWN_SPEED = 1.0


def _checks(
    scenario: Scenario, samples: list[tuple[float, np.ndarray]], grippers_z: float
) -> dict:
    P = np.stack([p for _, p in samples])  # (T, N, 3)
    t = np.array([s for s, _ in samples])
    below = float(-P[..., 2].min())
    out = {"deepest_below_table_mm": round(1000 * max(below, 0.0), 2)}
    ok = below <= PENETRATION_TOLERANCE
    if scenario.object.kind != "none":
        p_O = InObjectFrame(scenario, P)
        half = np.array(scenario.object.size) / 2
        depth = np.minimum.reduce(
            [
                half[0] - np.abs(p_O[..., 0]),
                half[1] - np.abs(p_O[..., 1]),
                2 * half[2] - p_O[..., 2],
                p_O[..., 2],
            ]
        )
        inside = float(depth.max())
        out["deepest_inside_object_mm"] = round(1000 * max(inside, 0.0), 2)
        ok &= inside <= PENETRATION_TOLERANCE
        top = scenario.object.size[2]
    else:
        top = 0.0
    if len(t) > 1:
        vz = np.diff(P[..., 2], axis=0) / np.diff(t)[:, None]
        out["max_upward_speed"] = round(float(vz.max()), 3)
        ok &= vz.max() <= THROWN_SPEED
    ceiling = max(grippers_z, top) + 0.05
    out["highest_vertex"] = round(float(P[..., 2].max()), 4)
    ok &= P[..., 2].max() <= ceiling
    out["physically_ok"] = bool(ok)
    return out


def _measure(run: OpenLoopRun, times: list[float], scenario: Scenario) -> dict:
    """Advances through `times`, timing only the physics (wall and process
    CPU time; samples are read between), with the physical checks."""
    t0 = run.context.get_time()
    samples = [(t0, run.capture_positions())]
    grippers_z = _grippers_z(run)
    wall = cpu = 0.0
    for t in times:
        w, c = time.perf_counter(), time.process_time()
        run.advance_to(t)
        wall += time.perf_counter() - w
        cpu += time.process_time() - c
        samples.append((run.context.get_time(), run.capture_positions()))
        grippers_z = max(grippers_z, _grippers_z(run))
    seconds = times[-1] - t0
    dt = scenario.plant_config.time_step
    return {
        "sim_seconds": round(seconds, 3),
        "wall_seconds": round(wall, 3),
        "realtime_factor": round(seconds / wall, 3),
        "realtime_factor_cpu": round(seconds / max(cpu, 1e-9), 3),
        "ms_per_step": round(1000 * wall / (seconds / dt), 2),
        **_checks(scenario, samples, grippers_z),
    }


def _grippers_z(run: OpenLoopRun) -> float:
    """The higher gripper's measured height (no camera rendering)."""
    return max(
        float(
            run.station.diagram.GetOutputPort(StationPorts.ee_measured(side)).Eval(
                run.station_context
            )[2]
        )
        for side in SIDES
    )


def _grid(t0: float, seconds: float, every: float = 0.05) -> list[float]:
    n = max(1, int(round(seconds / every)))
    return [t0 + (k + 1) * seconds / n for k in range(n)]


def BenchScenario(
    name: str,
    *,
    engine: str = "vbd",
    flat_seconds: float = 1.0,
    draped_seconds: float = 1.5,
    drapes: list | None = None,
) -> dict:
    """Real-time factors of one scenario on one engine in three phases:
    flat (lying on the table, grippers still), moving (the scripted task
    motion, or a 36 cm lift in the prior scene) and draped (after release:
    over the box or the plate; the prior cloth hanging from the grippers).
    A box cover's settled cloth is appended to `drapes` (for DrapePlot)."""
    scenario = LoadScenario(
        scenario_name=name, scenario_text=f"cloth: {{engine: {engine}}}"
    )
    step = scenario.motion.step_seconds
    flat_run = OpenLoopRun(scenario, actions=np.zeros((1, 6)), release_step=None)
    # One untimed step first: the vbd engine builds its newton model and
    # captures its step on the first update (about a second, once per
    # station), which is set-up, not simulation.
    warm = scenario.plant_config.time_step
    flat_run.advance_to(warm)
    flat = _measure(flat_run, _grid(warm, flat_seconds), scenario)
    if scenario.task == "prior":
        actions, release_step = np.tile([0, 0, 0.03, 0, 0, 0.03], (12, 1)), None
    else:
        plan = ScriptedDemoPlan(scenario)
        actions, release_step = plan.actions, plan.release_step
    run = OpenLoopRun(scenario, actions=actions, release_step=release_step)
    run.advance_to(warm)
    moving = _measure(run, [(k + 1) * step for k in range(len(actions))], scenario)
    t_end = step * (release_step if release_step is not None else len(actions))
    t_end = max(t_end, run.context.get_time()) + 0.1
    run.advance_to(t_end)
    draped = _measure(run, _grid(t_end, draped_seconds), scenario)
    settled = run.capture_positions()
    if scenario.task != "prior":
        report = TaskSuccess(scenario, settled, run.station.mesh.top_layer)
        draped["task_success"] = bool(report.success)
        draped["physically_ok"] = draped["physically_ok"] and (
            scenario.task != "hang" or report.success
        )
    if scenario.task == "box":
        draped["drape_reach_m"] = round(DrapeReach(scenario, settled), 4)
        sides, ends = SideFlapReach(scenario, settled)
        draped["side_flap_reach_m"] = {
            "left_right": round(sides, 4),
            "front_back": round(ends, 4),
        }
        if drapes is not None:
            drapes.append(
                {
                    "label": f"{name} on {engine}",
                    "scenario": scenario,
                    "positions_W": settled,
                    "reach": draped["drape_reach_m"],
                }
            )
    return {
        "scenario": name,
        "engine": engine,
        "cloth_vertices": len(flat_run.station.mesh.vertices),
        "time_step": scenario.plant_config.time_step,
        "flat": flat,
        "moving": moving,
        "draped": draped,
    }


def BenchSim(
    *,
    scenario_names=None,
    engines=("vbd", "fem"),
    flat_seconds: float = 1.0,
    out: Path | None = None,
    progress: bool = True,
) -> dict:
    """Runs BenchScenario for each scenario and engine, pinned to one core.
    With `out`, the JSON goes there and the settled box covers, seen from the
    front, the side and above, to `out` with the suffix .png (DrapePlot)."""
    if hasattr(os, "sched_setaffinity"):
        os.sched_setaffinity(0, {sorted(os.sched_getaffinity(0))[0]})
    os.environ["OMP_NUM_THREADS"] = "1"
    results, drapes = [], []
    for name in scenario_names or DEFAULT_SCENARIOS:
        for engine in engines:
            if progress:
                print(f"bench sim: {name} on {engine}", file=sys.stderr, flush=True)
            results.append(
                BenchScenario(
                    name, engine=engine, flat_seconds=flat_seconds, drapes=drapes
                )
            )
            if out is not None:  # partial results survive an interrupted run
                _write(out, _sim_summary(results))
    summary = _sim_summary(results)
    if out is not None:
        _write(out, summary)
        if drapes:
            DrapePlot(drapes, Path(out).with_suffix(".png"))
    return summary


def DrapePlot(drapes: list[dict], path: Path) -> None:
    """Settled box covers, one row each (dicts with `label`, `scenario`,
    `positions_W`, `reach`), seen from the front (x-z), the side (y-z) and
    above (x-y) in the box's frame: cloth vertices coloured by height, the
    box outlined, the reach figure's bounds dashed (3 cm up; 3 cm around the
    footprint) and the vertex that sets the figure crossed. Written
    atomically."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    from matplotlib.patches import FancyBboxPatch, Rectangle

    views = ((0, 2, "front (x-z)"), (1, 2, "side (y-z)"), (0, 1, "above (x-y)"))
    fig, axes = plt.subplots(
        len(drapes), 3, figsize=(13, 3.4 * len(drapes)), squeeze=False
    )
    for row, d in zip(axes, drapes, strict=True):
        scenario = d["scenario"]
        p_O = InObjectFrame(scenario, d["positions_W"])
        size = np.array(scenario.object.size)
        half = size[:2] / 2
        beyond = ReachDistances(scenario, p_O)
        k = int(np.argmax(beyond))
        for ax, (u, v, title) in zip(row, views, strict=True):
            ax.scatter(p_O[:, u], p_O[:, v], s=2, c=p_O[:, 2], cmap="viridis")
            if v == 2:
                ax.add_patch(Rectangle((-half[u], 0), size[u], size[2], fill=False))
                ax.axhline(0.03, color="r", ls="--", lw=0.6)
                for x in (-half[u] - 0.03, half[u] + 0.03):
                    ax.axvline(x, color="r", ls="--", lw=0.6)
            else:
                ax.add_patch(Rectangle(tuple(-half), *size[:2], fill=False))
                ax.add_patch(
                    FancyBboxPatch(
                        tuple(-half),
                        *size[:2],
                        boxstyle="round,pad=0.03",
                        fill=False,
                        ec="r",
                        ls="--",
                        lw=0.6,
                    )
                )
            if beyond[k] > 0:
                ax.plot(p_O[k, u], p_O[k, v], "rx", ms=8)
            ax.set_aspect("equal")
            ax.grid(alpha=0.3)
            ax.set_title(f"{d['label']}: {title}", fontsize=8)
        row[0].set_ylabel(f"reach {100 * d['reach']:.1f} cm")
    fig.tight_layout()
    tmp = Path(path).with_suffix(".tmp.png")
    fig.savefig(tmp, dpi=90)
    plt.close(fig)
    tmp.replace(path)


def _sim_summary(results: list) -> dict:
    return {
        "benchmark": "sim",
        "machine": {"cpu": platform.processor() or platform.machine(), "cores_used": 1},
        "target_realtime_factor": {"vbd": 1.0, "fem": 0.5},
        "target_drape_reach_m": 0.03,
        "scenarios": results,
    }


def _write(path: Path, data: dict) -> None:
    tmp = Path(path).with_suffix(".tmp")
    tmp.write_text(json.dumps(data, indent=1))
    tmp.replace(path)


def BenchCollect(
    *,
    transitions: int = 400,
    workers=(1, 2),
    out: Path | None = None,
    workdir: Path | None = None,
) -> dict:
    """Transitions per minute of prior collection with 1 and 2 workers."""
    import shutil
    import tempfile

    from fabric_imitation.tools.collect import Collect

    scenario = LoadScenario(scenario_name="prior")
    root = Path(workdir or tempfile.mkdtemp(prefix="bench_collect_"))
    rows = []
    try:
        for k in workers:
            path = root / f"w{k}.h5"
            t0 = time.perf_counter()
            summary = Collect(
                scenario=scenario,
                scenario_name="prior",
                transitions=transitions,
                out=path,
                workers=k,
                show_progress=False,
            )
            wall = time.perf_counter() - t0
            tpm = 60 * summary["transitions"] / wall
            rows.append(
                {
                    "workers": k,
                    "transitions": summary["transitions"],
                    "wall_seconds": round(wall, 1),
                    "transitions_per_minute": round(tpm, 1),
                    "minutes_for_10000": round(10000 / tpm, 1),
                    "fingerprint": summary["fingerprint"],
                }
            )
    finally:
        if workdir is None:
            shutil.rmtree(root, ignore_errors=True)
    result = {
        "benchmark": "collect",
        "target_minutes_for_10000": 30,
        "runs": rows,
        "same_data_for_every_worker_count": len({r["fingerprint"] for r in rows}) == 1,
    }
    if out is not None:
        Path(out).write_text(json.dumps(result, indent=1))
    return result


def BenchTrain(
    *, data: Path, out: Path | None = None, keypoint_epochs: int | None = None
) -> dict:
    """Wall time of training the priors on CPU (default settings, or fewer f_R
    epochs), with the held-out metrics reached."""
    import tempfile

    import torch
    from fabric_imitation.learning.train import TrainConfig, train_priors

    torch.set_num_threads(2)
    config = TrainConfig()
    if keypoint_epochs is not None:
        config.keypoint_epochs = keypoint_epochs
    with tempfile.TemporaryDirectory() as tmp:
        t0 = time.perf_counter()
        metrics = train_priors(data=data, out=Path(tmp), config=config, progress=False)
        wall = time.perf_counter() - t0
    result = {
        "benchmark": "train",
        "target_minutes": 10,
        "threads": 2,
        "epochs": config.epochs,
        "keypoint_epochs": config.keypoint_epochs,
        "wall_seconds": round(wall, 1),
        "minutes": round(wall / 60, 2),
        "metrics": metrics,
    }
    if out is not None:
        Path(out).write_text(json.dumps(result, indent=1))
    return result


def _spin(ready) -> None:
    """A process that keeps one core busy (what a user's other job does)."""
    ready.set()
    while True:
        pass


@contextlib.contextmanager
def OneCoreBusy():
    """Within the block another process keeps one core busy; it has started
    spinning when the block begins."""
    import multiprocessing as mp

    context = mp.get_context("spawn")
    ready = context.Event()
    busy = context.Process(target=_spin, args=(ready,), daemon=True)
    busy.start()
    try:
        if not ready.wait(120):
            raise RuntimeError("the process meant to keep a core busy did not start")
        yield
    finally:
        busy.terminate()
        busy.join()


# Scenarios `bench mpc` times by default: one demo of each kind.
MPC_SCENARIOS = ("box", "hang", "box_big")


def BenchMpc(
    *,
    scenario_names=MPC_SCENARIOS,
    policy=None,
    priors_dir: Path | None = None,
    demo_dir: Path | None = None,
    steps: int = 40,
    out: Path | None = None,
    num_samples: int = 500,
    horizon: int = 5,
    threads: int | None = None,
    progress: bool = False,
) -> dict:
    """MPC control steps (N = 500, h = 5, each scenario's own iteration cap
    and convergence test) from the demo's states and perturbed ones, idle
    and with another process keeping one core busy: ms per sampling
    iteration, iterations per step, ms per step, the fraction of steps
    converged by the paper's test, and how many steps chose another action
    under load (0: the actions do not depend on the load). Also the time
    from a demo to the first action (f_R on the demo frames, f_A, first
    solve) the first time on this machine (an empty cache: the IoU kernel
    built, f_A trained) and when the same demo and priors were prepared
    before. `threads`: torch threads (default: what the main job picks,
    `TorchThreads()`). `policy`: the method's settings (default: the
    priors' policy file)."""
    import tempfile

    import torch
    from fabric_imitation.learning import polygon_kernel
    from fabric_imitation.tools.episode import TorchThreads

    if demo_dir is not None and len(scenario_names) != 1:
        raise InputError("a demo directory needs exactly one scenario")
    if steps < 1:
        raise InputError(f"steps must be at least 1, got {steps}")
    for name in scenario_names:
        # an unknown name fails here, at once
        LoadScenario(scenario_name=name, policy=policy)
    torch.set_num_threads(threads or TorchThreads())
    scenarios = {}
    for name in scenario_names:
        if progress:
            print(f"bench mpc: {name}", file=sys.stderr)
        with tempfile.TemporaryDirectory() as cache:
            saved = os.environ.get("FABRIC_IMITATION_CACHE")
            os.environ["FABRIC_IMITATION_CACHE"] = cache
            polygon_kernel.forget()
            try:
                first, _, _ = _PreparedMpc(
                    name, priors_dir, demo_dir, num_samples, horizon, policy
                )
                again, mpc, states = _PreparedMpc(
                    name, priors_dir, demo_dir, num_samples, horizon, policy
                )
            finally:
                if saved is None:
                    del os.environ["FABRIC_IMITATION_CACHE"]
                else:
                    os.environ["FABRIC_IMITATION_CACHE"] = saved
                polygon_kernel.forget()  # the one built in the deleted cache
        scenarios[name] = _TimeMpcSteps(mpc, states, steps) | {
            "demo_to_first_action_s": {"first_time": first, "prepared_before": again},
        }
    result = {
        "benchmark": "mpc",
        "threads": torch.get_num_threads(),
        "omp_wait_policy": os.environ.get("OMP_WAIT_POLICY", "(default)"),
        "num_samples": num_samples,
        "horizon": horizon,
        "steps": steps,
        "iou": "compiled kernel" if polygon_kernel.load() else "torch",
        "scenarios": scenarios,
        "targets": {
            "iteration_ms_p50": 20,
            "step_ms_p95": 75,
            "step_ms_p95_one_core_loaded": 150,
            "converged_fraction": 0.9,
            "actions_changed_under_load": 0,
            "demo_to_first_action_s": {"first_time": 15, "prepared_before": 5},
        },
    }
    if out is not None:
        _write(Path(out), result)
    return result


def _PreparedMpc(name, priors_dir, demo_dir, num_samples, horizon, policy=None):
    """(seconds from loading the demo to the first action, the Mpc, the
    demo's states) for scenario `name`'s shipped demo (or `demo_dir`)."""
    import torch
    from fabric_imitation.diagrams.imitation import DefaultDemoDir, PrepareImitation
    from fabric_imitation.learning.mpc import Mpc
    from fabric_imitation.tasks.referee import TaskSafetyContext

    scenario = LoadScenario(scenario_name=name, policy=policy)
    t0 = time.perf_counter()
    prepared = PrepareImitation(
        scenario,
        demo_dir=demo_dir or DefaultDemoDir(name, scenario),
        priors_dir=priors_dir,
    )
    mpc = Mpc(
        dynamics=prepared.priors,
        demo=prepared.model,
        safety=prepared.safety,
        safety_ctx=TaskSafetyContext(scenario, estimated=True),
        config=dc.replace(scenario.mpc, num_samples=num_samples, horizon=horizon),
    )
    mpc.solve(torch.as_tensor(prepared.demo_states[0], dtype=torch.float32))
    return round(time.perf_counter() - t0, 2), mpc, prepared.demo_states


# [m] noise added to each keypoint of the demo's states that `bench mpc`
# solves from: about f_R's error on visible corners (4.5 mm held out), small
# enough that every start has a feasible action, as the steps of an episode
# have (an episode ends at the first step without one).
BENCH_STATE_NOISE = 0.003


def _TimeMpcSteps(mpc, states, steps: int) -> dict:
    """`steps` solves, one after another as in an episode, from the demo's
    states (in order) with BENCH_STATE_NOISE of noise, idle and with one core
    busy. With `mpc.warm_start`, each step starts from the previous one's
    noise distribution, as MpcController carries it."""
    import torch

    rng = np.random.default_rng(0)
    perturbed = [
        states[k % len(states)] + rng.normal(0, BENCH_STATE_NOISE, states[0].shape)
        for k in range(steps)
    ]

    def measure():
        results, noise = [], None
        for k, S in enumerate(perturbed):
            result = mpc.solve(
                torch.as_tensor(S, dtype=torch.float32), step=k, noise=noise
            )
            noise = result.noise if result.feasible else None
            results.append(result)
        step_ms = [1000 * r.seconds for r in results]
        iteration_ms = [1000 * t for r in results for t in r.iteration_seconds]
        iterations = [r.iterations for r in results]
        return results, {
            "iteration_ms": _percentiles(iteration_ms, (50, 95)),
            "iterations_per_step": {
                "mean": round(float(np.mean(iterations)), 2),
                "max": int(np.max(iterations)),
            },
            "step_ms": _percentiles(step_ms, (50, 95))
            | {"max": round(max(step_ms), 1)},
            "converged_fraction": round(
                float(np.mean([r.converged for r in results])), 3
            ),
            "feasible_fraction": round(
                float(np.mean([r.feasible for r in results])), 3
            ),
        }

    idle_results, idle = measure()
    with OneCoreBusy():
        loaded_results, loaded = measure()
    changed = sum(
        not torch.equal(a.action, b.action)
        for a, b in zip(idle_results, loaded_results, strict=True)
    )
    return {
        "max_iterations": mpc.config.max_iterations,
        "tau_conv": mpc.config.tau_conv,
        "warm_start": mpc.config.warm_start,
        "state_noise_m": BENCH_STATE_NOISE,
        "idle": idle,
        "one_core_loaded": loaded,
        "actions_changed_under_load": changed,
    }


def _percentiles(values, qs) -> dict:
    return {f"p{q}": round(float(np.percentile(values, q)), 1) for q in qs}


# Fractions of the fabric's mask hidden, and how (`bench occlusion`).
OCCLUDED_FRACTIONS = (0.0, 0.1, 0.2, 0.3, 0.4, 0.5)
OCCLUSIONS = ("grippers", "side")


def Occlude(mask: np.ndarray, fraction: float, kind: str, rng) -> np.ndarray:
    """A copy of `mask` (H, W) with about `fraction` of its pixels hidden:
    "grippers" - discs the size of a hand seen from above (7 px at 160 px)
    dropped on the fabric until the fraction is reached, as grippers and
    arms hide it; "side" - the fabric cut off from one side (a band whose
    edge moves in from a random side), as a partial mask is."""
    import cv2

    on = mask > 0
    total = int(on.sum())
    out = on.copy()
    if fraction <= 0 or total == 0:
        return out.astype(np.uint8)
    if kind == "grippers":
        ys, xs = np.nonzero(on)
        while (on & ~out).sum() < fraction * total:
            i = int(rng.integers(len(ys)))
            disc = np.zeros(out.shape, np.uint8)
            cv2.circle(disc, (int(xs[i]), int(ys[i])), 7, 1, -1)
            out &= disc == 0
        return out.astype(np.uint8)
    # side: the pixels of the fabric furthest along a random direction.
    angle = rng.uniform(0, 2 * np.pi)
    ys, xs = np.nonzero(on)
    along = xs * np.cos(angle) + ys * np.sin(angle)
    cut = np.quantile(along, 1 - fraction)
    out[ys[along > cut], xs[along > cut]] = False
    return out.astype(np.uint8)


def BenchOcclusion(
    *,
    demo_names=("box", "hang", "box_big"),
    priors_dir: Path | None = None,
    out: Path | None = None,
    seed: int = 0,
) -> dict:
    """f_R's keypoint error [mm] against the simulator's true keypoints on
    the shipped demos' frames as more of the fabric's mask is hidden
    (OCCLUSIONS, OCCLUDED_FRACTIONS). Writes JSON and, next to it, a plot."""
    import torch
    from fabric_imitation.diagrams.imitation import DEFAULT_DEMOS, DEFAULT_PRIORS
    from fabric_imitation.learning.demo_io import LoadDemo
    from fabric_imitation.learning.priors import load_priors

    torch.set_num_threads(1)
    priors = load_priors(priors_dir or DEFAULT_PRIORS)
    rng = np.random.default_rng(seed)
    errors = {kind: {f: [] for f in OCCLUDED_FRACTIONS} for kind in OCCLUSIONS}
    frames = 0
    for name in demo_names:
        demo = LoadDemo(DEFAULT_DEMOS / name)
        truth = np.load(demo.path / "ground_truth.npz")["keypoints_W"]
        for mask, depth, p_W in zip(demo.mask, demo.depth, truth, strict=True):
            frames += 1
            for kind in OCCLUSIONS:
                for f in OCCLUDED_FRACTIONS:
                    hidden = Occlude(mask, f, kind, rng)
                    if not hidden.any():
                        continue
                    est = priors.keypoints(hidden, depth)
                    errors[kind][f].append(
                        1000 * float(np.linalg.norm(est - p_W, axis=1).mean())
                    )
    table = {
        kind: [
            {
                "occluded_fraction": f,
                "frames": len(v),
                "keypoint_error_mm_mean": round(float(np.mean(v)), 2),
                "keypoint_error_mm_p90": round(float(np.percentile(v, 90)), 2),
            }
            for f, v in per.items()
            if v
        ]
        for kind, per in errors.items()
    }
    summary = {
        "benchmark": "occlusion",
        "demos": list(demo_names),
        "frames": frames,
        "seed": seed,
        "results": table,
    }
    if out is not None:
        _write(Path(out), summary)
        _plot_occlusion(table, Path(out).with_suffix(".png"))
    return summary


def _pyplot():
    """matplotlib's pyplot on the Agg backend (no screen)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    return plt


def _save_figure(fig, path: Path, dpi: int) -> None:
    """Writes `fig` to `path` whole (through a file beside it) and closes it."""
    tmp = path.with_name(path.name + ".tmp.png")
    fig.savefig(tmp, dpi=dpi)
    _pyplot().close(fig)
    tmp.replace(path)


def _plot_occlusion(table: dict, path: Path) -> None:
    plt = _pyplot()
    fig, ax = plt.subplots(figsize=(5, 3.2))
    for kind, rows in table.items():
        x = [100 * r["occluded_fraction"] for r in rows]
        (line,) = ax.plot(
            x, [r["keypoint_error_mm_mean"] for r in rows], "o-", label=f"{kind} (mean)"
        )
        ax.plot(
            x,
            [r["keypoint_error_mm_p90"] for r in rows],
            "--",
            color=line.get_color(),
            alpha=0.6,
            label=f"{kind} (90th percentile)",
        )
    ax.set_xlabel("fabric mask hidden [%]")
    ax.set_ylabel("f_R keypoint error [mm]")
    ax.legend(fontsize=7)
    ax.grid(alpha=0.3)
    fig.tight_layout()
    _save_figure(fig, path, dpi=100)


# `bench tracker`'s variants: the tracker as configured (f_D predicts), with
# the object projection, with every keypoint moved by the mean of the two
# grippers' moves instead of f_D ("rigid"), with no move at all ("still"),
# and with f_R's height error apart from its horizontal one ("vertical_model").
TRACKER_VARIANTS = ("tracked", "object_projection", "rigid_prediction", "no_prediction")
TRACKER_PREDICTIONS = {
    "tracked": None,
    "object_projection": None,
    "rigid_prediction": lambda S, A: S + (A[..., :3] + A[..., 3:])[..., None, :] / 2,
    "no_prediction": lambda S, A: S,
}


def _TrackVariant(priors, config, variant, pose, size, measured, spread, grasped):
    """World keypoints (T, M, 3) tracked with `config` and the prediction of
    `variant` (TRACKER_PREDICTIONS; f_D's where it names none) from
    f_R's world readings `measured` with their `spread`, the grippers at
    `grasped` (T, 2, 3, world); the tracker runs in the object frame `pose`."""
    from fabric_imitation.learning.state import object_to_world, world_to_object
    from fabric_imitation.learning.tracker import KeypointTracker, track_states

    def to_object(p_W: np.ndarray) -> np.ndarray:
        return world_to_object(p_W.reshape(-1, 3), pose).reshape(p_W.shape)

    tracker = KeypointTracker(
        forward=TRACKER_PREDICTIONS.get(variant) or priors.forward,
        num_keypoints=priors.num_keypoints,
        config=config,
        object_size=size,
    )
    out = track_states(tracker, to_object(measured), spread, to_object(grasped))
    return object_to_world(out.reshape(-1, 3), pose).reshape(out.shape)


# f_R is "sure" of a keypoint whose heatmap spread is at most this [px].
TRACKER_SURE_SPREAD_PX = 4.0
# A far corner "f_R misreads": more than this [m] from the true one.
TRACKER_OFF_M = 0.08


def BenchTracker(
    *,
    demo_names=("box", "hang", "box_big"),
    priors_dir: Path | None = None,
    out: Path | None = None,
) -> dict:
    """The keypoint tracker (learning/tracker.py, its default settings)
    against f_R alone on the shipped demos' frames, both compared with the
    simulator's true keypoints; the grippers' moves are those of the true
    grasped corners. Also the tracker with other predictions in place of
    f_D's (TRACKER_VARIANTS) and with f_R's vertical error apart from its
    horizontal one ("vertical_model", the fits below). Also fits, on the
    same frames, the errors the tracker's settings take: f_R's mean error
    against heatmap spread (3-D, and horizontal and vertical apart) and f_D's
    one-step error (mean and root mean square). Writes JSON and, next
    to it, a plot of the far corners' errors."""
    import torch
    from fabric_imitation.diagrams.imitation import DEFAULT_DEMOS, DEFAULT_PRIORS
    from fabric_imitation.learning.demo_io import LoadDemo
    from fabric_imitation.learning.priors import load_priors
    from fabric_imitation.learning.state import corner_indices
    from fabric_imitation.learning.tracker import (
        TrackerConfig,
        fit_measurement_model,
    )

    torch.set_num_threads(1)
    priors = load_priors(priors_dir or DEFAULT_PRIORS)
    idx = corner_indices(priors.num_keypoints)
    far = [idx["s3"], idx["s4"]]
    others = [k for k in range(priors.num_keypoints) if k not in (idx["s1"], idx["s2"])]
    config = TrackerConfig(enabled=True, object_projection=False)
    # f_R once per demo; its errors fit the measurement models first, so
    # that the tracker with the fitted vertical model is one of the variants.
    frames = {}
    spreads, errors, horizontal, vertical, one_step = [], [], [], [], []
    for name in demo_names:
        demo = LoadDemo(DEFAULT_DEMOS / name)
        truth = np.load(demo.path / "ground_truth.npz")["keypoints_W"]
        scenario = LoadScenario(scenario_text=demo.scenario_yaml)
        size = scenario.object.size if scenario.object.kind != "none" else None
        grasped = truth[:, [idx["s1"], idx["s2"]]]
        measured, spread = priors.keypoints_and_spread(demo.mask, demo.depth)
        frames[name] = (demo, truth, size, grasped, measured, spread)
        diff = (measured - truth)[:, others]
        spreads.append(spread[:, others].ravel())
        errors.append(np.linalg.norm(diff, axis=-1).ravel())
        # Per axis, as the tracker applies it: x and y each a sample.
        horizontal.append(np.abs(diff[..., :2]).ravel())
        vertical.append(np.abs(diff[..., 2]).ravel())
        # f_D's one-step error from the true state and the true move.
        moves = (grasped[1:] - grasped[:-1]).reshape(-1, 6)
        e_fd = np.linalg.norm(
            priors.forward(truth[:-1], moves).numpy() - truth[1:], axis=-1
        )
        one_step.append(e_fd[:, others].ravel())
    spread_all = np.concatenate(spreads)
    base, per_px2 = fit_measurement_model(spread_all, np.concatenate(errors))
    h_base, h_per_px2 = fit_measurement_model(
        np.repeat(spread_all, 2), np.concatenate(horizontal)
    )
    v_base, v_per_px2 = fit_measurement_model(spread_all, np.concatenate(vertical))
    configs = {
        variant: dc.replace(config, object_projection=variant == "object_projection")
        for variant in TRACKER_VARIANTS
    }
    configs["vertical_model"] = dc.replace(
        config,
        measurement_base=h_base,
        measurement_per_px2=h_per_px2,
        measurement_vertical_base=v_base,
        measurement_vertical_per_px2=v_per_px2,
    )
    results, curves = {}, {}
    for name, (demo, truth, size, grasped, measured, spread) in frames.items():
        runs = {
            variant: _TrackVariant(
                priors,
                cfg,
                variant,
                demo.object_pose,
                size,
                measured,
                spread,
                grasped,
            )
            for variant, cfg in configs.items()
        }
        e_fr = np.linalg.norm(measured - truth, axis=-1)
        errors_of = {v: np.linalg.norm(run - truth, axis=-1) for v, run in runs.items()}
        e_tr = errors_of["tracked"]
        off = e_fr[:, far] > TRACKER_OFF_M
        sure = spread[:, others] <= TRACKER_SURE_SPREAD_PX
        follow = np.linalg.norm(runs["tracked"] - measured, axis=-1)[:, others]

        def cm(x) -> float | None:
            return round(100 * float(np.mean(x)), 2) if np.size(x) else None

        results[name] = {
            "frames": len(truth),
            "error_cm_mean": {
                "f_R": cm(e_fr[:, others]),
                **{v: cm(e[:, others]) for v, e in errors_of.items()},
            },
            "far_corners_f_R_off": int(off.sum()),
            "far_corners_where_f_R_off_error_cm_mean": {
                "f_R": cm(e_fr[:, far][off]),
                **{v: cm(e[:, far][off]) for v, e in errors_of.items()},
            },
            "f_D_one_step_error_cm_mean": cm(one_step[len(results)]),
            "sure_keypoints": int(sure.sum()),
            "sure_tracked_from_f_R_cm_max": (
                round(100 * float(follow[sure].max()), 2) if sure.any() else None
            ),
        }
        curves[name] = (
            100 * e_fr[:, far].mean(1),
            100 * e_tr[:, far].mean(1),
        )
    summary = {
        "benchmark": "tracker",
        "demos": list(demo_names),
        "config": dc.asdict(config),
        "sure_spread_px": TRACKER_SURE_SPREAD_PX,
        "off_m": TRACKER_OFF_M,
        "measurement_model_fit": {
            "base_m": round(base, 5),
            "per_px2_m": float(f"{per_px2:.3g}"),
            "horizontal": {
                "base_m": round(h_base, 5),
                "per_px2_m": float(f"{h_per_px2:.3g}"),
            },
            "vertical": {
                "base_m": round(v_base, 5),
                "per_px2_m": float(f"{v_per_px2:.3g}"),
            },
        },
        "f_D_one_step_error_m": {
            "mean": round(float(np.concatenate(one_step).mean()), 4),
            "rms": round(float(np.sqrt(np.mean(np.concatenate(one_step) ** 2))), 4),
        },
        "priors_sha256": hashlib.sha256(
            (Path(priors_dir or DEFAULT_PRIORS) / "priors.pt").read_bytes()
        ).hexdigest()[:16],
        "in_sample": "the error model and the tracker's errors come from the same "
        "frames",
        "results": results,
    }
    if out is not None:
        _write(Path(out), summary)
        _plot_tracker(curves, Path(out).with_suffix(".png"))
    return summary


def _plot_tracker(curves: dict, path: Path) -> None:
    plt = _pyplot()
    fig, axes = plt.subplots(
        1, len(curves), figsize=(4 * len(curves), 3), squeeze=False
    )
    for ax, (name, (fr, tr)) in zip(axes[0], curves.items(), strict=True):
        ax.plot(fr, "o-", ms=3, label="f_R alone")
        ax.plot(tr, "s-", ms=3, label="tracked")
        ax.set_title(name)
        ax.set_xlabel("demo frame")
        ax.set_ylabel("far corners' error [cm]")
        ax.legend(fontsize=7)
    fig.tight_layout()
    _save_figure(fig, path, dpi=110)
