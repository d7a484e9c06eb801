"""`fabric-imitate collect`: random safe bimanual motions recorded as
transitions (paper Sec. IV-B): in the contact-free prior scene, or in a task's
scene, where the cloth also meets the object (data with contact for f_D;
`train --forward-only`).

Episodes are the unit of work: episode e draws from RNG(seed, e) only, so the
data are the same for any worker count or executor, and a resumed run
recomputes exactly the episodes that were not yet stored.
"""

import contextlib
import dataclasses as dc
import json
import subprocess
import sys
import time
from collections.abc import Iterator
from pathlib import Path

import numpy as np
import torch
from fabric_imitation.diagrams.station import (
    CameraModelFromConfig,
    InitializeStation,
    MakeClothStation,
    StationPorts,
)
from fabric_imitation.learning.dataset import (
    FIELDS,
    Consolidate,
    EncodeDepth,
    ReadInfo,
    ShardEpisodes,
    WriteShard,
)
from fabric_imitation.learning.errors import InputError
from fabric_imitation.learning.safety import valid_actions
from fabric_imitation.learning.state import (
    NUM_KEYPOINTS,
    SIDES,
    PlanarPose,
    world_to_object,
)
from fabric_imitation.scenarios.loader import DumpScenario, LoadScenario
from fabric_imitation.scenarios.poses import GraspCorners, ObjectPlanarPose
from fabric_imitation.scenarios.schema import Scenario
from fabric_imitation.systems.targets import GripperTargetIntegrator
from fabric_imitation.tasks.referee import HandSpheres, TaskSafetyContext
from fabric_imitation.tools.executors import EXECUTORS, RunJobs
from pydrake.systems.analysis import Simulator
from pydrake.systems.framework import DiagramBuilder


def CodeVersion() -> str:
    try:
        out = subprocess.run(
            ["git", "rev-parse", "--short", "HEAD"],
            cwd=Path(__file__).parent,
            capture_output=True,
            text=True,
            timeout=5,
        )
        if out.returncode == 0:
            return out.stdout.strip()
    except OSError:
        pass
    from importlib.metadata import version

    return version("fabric-imitation")


class EpisodeCollector:
    """One station, reused for every episode by resetting its context."""

    def __init__(self, scenario: Scenario):
        self.scenario = scenario
        builder = DiagramBuilder()
        self.station = MakeClothStation(scenario)
        station = builder.AddNamedSystem("station", self.station.diagram)
        integrator = builder.AddNamedSystem(
            "targets",
            GripperTargetIntegrator(step_seconds=scenario.motion.step_seconds),
        )
        for side in SIDES:
            builder.Connect(
                integrator.GetOutputPort(f"{side}.ee_target"),
                station.GetInputPort(StationPorts.ee_target(side)),
            )
        builder.ExportInput(integrator.GetInputPort("action"), "action")
        self.diagram = builder.Build()
        self.simulator = Simulator(self.diagram)
        self.context = self.simulator.get_mutable_context()
        corners = GraspCorners(scenario)
        integrator.SetInitialPositions(
            integrator.GetMyMutableContextFromRoot(self.context),
            corners["left"],
            corners["right"],
        )
        station.GetInputPort(StationPorts.RELEASE).FixValue(
            station.GetMyMutableContextFromRoot(self.context), [0.0]
        )
        InitializeStation(
            self.station, station.GetMyMutableContextFromRoot(self.context)
        )
        self.default_context = self.context.Clone()
        self.station_context = station.GetMyContextFromRoot(self.context)
        self.action_port = self.diagram.GetInputPort("action")
        self.safety_ctx = TaskSafetyContext(scenario)
        # In a scene with an object the rules judge states in the object's
        # frame (rule 4 on the grasped points and on the hands' spheres, so
        # that the hands do not strike the object); the data stay in the
        # world frame, as f_D and f_I read each state in its own canonical
        # frame.
        self.object_pose = None
        if scenario.object.kind != "none":
            self.object_pose = ObjectPlanarPose(scenario)
            self.safety_ctx = dc.replace(
                self.safety_ctx, hand_spheres=HandSpheres(scenario)
            )

    def _observe(self):
        def port(name):
            return self.station.diagram.GetOutputPort(name).Eval(self.station_context)

        return (
            np.array(port(StationPorts.MASK).data[:, :, 0]),
            EncodeDepth(np.array(port(StationPorts.DEPTH).data[:, :, 0])),
            np.array(port(StationPorts.CLOTH_KEYPOINTS), np.float32).reshape(-1, 3),
            np.stack([port(StationPorts.ee_measured(s)) for s in SIDES]).astype(
                np.float32
            ),
        )

    def _sample(
        self, rng: np.random.Generator, S: np.ndarray, drift: np.ndarray
    ) -> np.ndarray | None:
        cfg = self.scenario.collection
        bound = self.scenario.safety.max_step
        noise = rng.uniform(-1, 1, size=(cfg.candidates, 6)) * cfg.noise * bound
        A = np.clip(np.tile(drift, 2) + noise, -bound, bound)
        S_frame, A_frame = S, A
        if self.object_pose is not None:
            S_frame = world_to_object(S, self.object_pose)
            pose = PlanarPose(*self.object_pose)
            A_frame = pose.vector_to_object(A.reshape(-1, 2, 3)).reshape(A.shape)
        ok = valid_actions(
            torch.as_tensor(S_frame, dtype=torch.float64)[None],
            torch.as_tensor(A_frame),
            self.scenario.safety,
            self.safety_ctx,
        ).numpy()
        hits = np.flatnonzero(ok)
        return (A[hits[0]], int(hits[0])) if len(hits) else (None, len(A))

    def run_episode(self, episode: int, seed: int) -> dict[str, np.ndarray]:
        """Runs one episode; returns its transitions (possibly none)."""
        cfg = self.scenario.collection
        rng = np.random.default_rng([seed, episode])
        drift = rng.uniform(cfg.drift_lower, cfg.drift_upper)
        warmup = int(rng.integers(0, cfg.max_warmup_steps + 1))
        self.context.SetTimeStateAndParametersFrom(self.default_context)
        self.simulator.Initialize()
        dt = self.scenario.motion.step_seconds
        rows: dict[str, list] = {k: [] for k in FIELDS}
        flip_at = warmup + cfg.episode_length // 2
        flip = rng.random() < cfg.reverse_probability
        obs = self._observe()
        for k in range(warmup + cfg.episode_length):
            if k == flip_at and flip:
                drift = drift * np.array([1.0, 1.0, -1.0])
            A, rejected = self._sample(rng, obs[2], drift)
            if A is None:
                break
            self.action_port.FixValue(self.context, A)
            try:
                self.simulator.AdvanceTo((k + 1) * dt)
            except RuntimeError:
                break  # a diverged episode ends; what was recorded is kept
            nxt = self._observe()
            if not np.all(np.isfinite(nxt[2])):
                break
            if k >= warmup:
                for name, a, b in zip(
                    ("mask", "depth", "keypoints", "grippers"), obs, nxt, strict=True
                ):
                    rows[name].append(a)
                    rows[name + "_next"].append(b)
                rows["action"].append(A.astype(np.float32))
                rows["episode"].append(episode)
                rows["step"].append(k - warmup)
                rows["rejected"].append(rejected)
            obs = nxt
        if not rows["action"]:
            return {"action": np.zeros((0, 6), np.float32)}
        out = {name: np.stack(values) for name, values in rows.items()}
        for name in ("episode", "step", "rejected"):
            out[name] = np.asarray(rows[name], np.int32)
        return out


# --- executors ------------------------------------------------------------

_WORKER: dict = {}


def _worker_init(scenario_yaml: str) -> None:
    torch.set_num_threads(1)
    _WORKER["collector"] = EpisodeCollector(LoadScenario(scenario_text=scenario_yaml))


def _worker_episode(job: tuple[str, int, int]) -> tuple[int, int]:
    path, episode, seed = job
    data = _WORKER["collector"].run_episode(episode, seed)
    WriteShard(Path(path), episode, data)
    return episode, len(data["action"])


def _episodes_to_do(start: int, skip: set[int]) -> Iterator[int]:
    e = start
    while True:
        if e not in skip:
            yield e
        e += 1


@dc.dataclass
class _Progress:
    target: int
    done: int
    bar: object

    def add(self, n: int) -> None:
        n = min(n, self.target - self.done)
        self.done += n
        if self.bar is not None:
            self.bar.update(n)


def Collect(
    *,
    scenario: Scenario,
    scenario_name: str,
    transitions: int,
    out: Path,
    workers: int = 1,
    executor: str = "local",
    seed: int | None = None,
    show_progress: bool = True,
) -> dict:
    """Collects `transitions` transitions into the dataset `out` (resumable).

    Returns the JSON summary: transitions, episodes, rejected/ended episodes,
    transitions per minute of this run.
    """
    if transitions <= 0:
        raise InputError(f"--transitions must be positive, got {transitions}")
    if workers < 1:
        raise InputError(f"--workers must be at least 1, got {workers}")
    if executor not in EXECUTORS:
        raise InputError(f"unknown executor {executor!r}; use local or ray")
    seed = scenario.random_seed if seed is None else seed
    out = Path(out)
    scenario_yaml = DumpScenario(scenario)
    metadata = {
        "scenario_name": scenario_name,
        "scenario_yaml": scenario_yaml,
        "seed": seed,
        "code_version": CodeVersion(),
    }
    metadata["camera"] = json.dumps(CameraModelFromConfig(scenario.camera).to_json())
    metadata["num_keypoints"] = NUM_KEYPOINTS
    wall0 = time.perf_counter()
    info = Consolidate(out, target=transitions, metadata=metadata)
    have = info.num_transitions if info else 0
    if info is not None and info.num_transitions >= transitions and info.complete:
        return _summary(out, transitions, 0, time.perf_counter() - wall0, resumed=True)
    shards = ShardEpisodes(out)
    done_before = have + sum(_shard_len(f) for e, f in sorted(shards.items()))
    bar = None
    if show_progress:
        from tqdm import tqdm

        bar = tqdm(
            total=transitions,
            initial=min(done_before, transitions),
            desc="collect",
            unit="tr",
            file=sys.stderr,
        )
    tracker = _Progress(target=transitions, done=min(done_before, transitions), bar=bar)
    start = info.num_episodes if info else 0

    def progress(n: int) -> bool:
        tracker.add(n)
        return tracker.done >= transitions

    if tracker.done < transitions:
        jobs = ((str(out), e, seed) for e in _episodes_to_do(start, set(shards)))
        with contextlib.closing(
            RunJobs(
                _worker_episode,
                jobs,
                workers=workers,
                executor=executor,
                init=_worker_init,
                init_args=(scenario_yaml,),
            )
        ) as results:
            for _, n in results:
                if progress(n):
                    break
    if bar is not None:
        bar.close()
    Consolidate(out, target=transitions, metadata=metadata)
    new = tracker.done - min(done_before, transitions)
    return _summary(
        out,
        transitions,
        new,
        time.perf_counter() - wall0,
        resumed=info is not None or bool(shards),
    )


def _shard_len(f: Path) -> int:
    try:
        with np.load(f) as z:
            return len(z["action"])
    except Exception:  # noqa: BLE001
        return 0


def _summary(out: Path, target: int, new: int, wall: float, resumed: bool) -> dict:
    import h5py

    info = ReadInfo(out)
    rejected = 0
    if info is not None:
        with h5py.File(out, "r") as f:
            rejected = int(f["rejected"][:].sum())
    return {
        "rejected_samples": rejected,
        "out": str(out),
        "transitions": info.num_transitions if info else 0,
        "target_transitions": target,
        "episodes": info.num_episodes if info else 0,
        "complete": bool(info.complete) if info else False,
        "new_transitions": new,
        "wall_seconds": round(wall, 2),
        "transitions_per_minute": round(60 * new / max(wall, 1e-9), 1),
        "resumed": resumed,
        "fingerprint": str(info.attrs["fingerprint"]) if info else None,
    }
