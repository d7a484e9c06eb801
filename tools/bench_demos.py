"""`fabric-imitate bench demos`: the scripted demos over each object kind's
size range, judged as Table I judges a method's trial.

For each kind (box and cylinder to cover, plate and rail to hang a towel
on) the corners and the centre of its size range with the 30 x 30 cm cloth
and sizes near the scripted demo's bounds,
each at the named scenario's nominal object pose and at two moved and
turned poses (moved up to 10 cm and turned up to 45 degrees, pose seed 0,
development; a size refused gets the nominal pose only): whether
the demo succeeds, the referee's rule breaks on the true cloth and the
gripper-object contacts; a size the scripted demo cannot serve is refused
with the geometric bound (tasks/demos.py, CheckDemoServes) and counted as
refused. Each case is one line of a JSON-lines file as it finishes, so an
interrupted run resumes; the summary per kind goes to the JSON file.
"""

import itertools
import json
import sys
from pathlib import Path

from fabric_imitation.learning.errors import InputError

# Kind -> (named scenario, size range per axis [m]: (low, high), or a
# single value where the range fixes it).
SIZE_RANGES = {
    "box": ("box", ((0.08, 0.20), (0.08, 0.12), (0.04, 0.12))),
    "cylinder": ("cylinder", ((0.06, 0.12), None, (0.06, 0.15))),
    "plate": ("hang", ((0.12, 0.24), (0.01,), (0.12, 0.22))),
    "rail": ("rail", ((0.45,), (0.02,), (0.18, 0.30))),
}
MOVED_POSES = 2
# Sizes near the scripted demos' geometric bounds (CheckDemoServes), inside
# the ranges, that show where the served part of a range ends.
NEAR_BOUNDS = {
    "box": ([0.14, 0.09, 0.075], [0.20, 0.12, 0.089]),
    "cylinder": ([0.09, 0.09, 0.075], [0.12, 0.12, 0.089]),
    "plate": ([0.12, 0.01, 0.20], [0.24, 0.01, 0.20]),
    "rail": ([0.45, 0.02, 0.20],),
}


def RangeSizes(kind: str) -> list[list[float]]:
    """The corners and the centre of `kind`'s size range (a cylinder's y
    size is its diameter), then its NEAR_BOUNDS sizes."""
    _, axes = SIZE_RANGES[kind]
    values = [None if a is None else (a if len(a) == 1 else (a[0], a[1])) for a in axes]
    centre = [None if a is None else round(sum(a) / len(a), 4) for a in axes]
    corners = [list(c) for c in itertools.product(*[v or (None,) for v in values])]
    sizes = []
    for s in [*corners, centre, *NEAR_BOUNDS[kind]]:
        s = [s[0], s[0] if s[1] is None else s[1], s[2]]
        if s not in sizes:
            sizes.append(s)
    return sizes


def _size_text(size: list[float]) -> str:
    return json.dumps({"object": {"size": size}})


def _cases() -> list[dict]:
    """Every (kind, size, pose); the moved poses are drawn for each size
    (TrialPoses keeps the object clear of the cloth and the grippers), the
    sizes the scripted demo cannot serve get the nominal pose only."""
    from fabric_imitation.scenarios.loader import LoadScenario
    from fabric_imitation.tasks.demos import CheckDemoServes
    from fabric_imitation.tools.evaluate import TrialPoses

    cases = []
    for kind, (name, _) in SIZE_RANGES.items():
        for size in RangeSizes(kind):
            text = _size_text(size)
            scenario = LoadScenario(scenario_name=name, scenario_text=text)
            poses = [list(scenario.object.pose)]
            try:
                CheckDemoServes(scenario)
                poses += TrialPoses(
                    name, trials=MOVED_POSES, seed=0, scenario_text=text
                )
            except InputError:
                pass
            cases += [
                {"kind": kind, "size": size, "pose": pose, "pose_index": i}
                for i, pose in enumerate(poses)
            ]
    return cases


def _key(case: dict) -> str:
    return json.dumps([case["kind"], case["size"], case["pose"]])


def _run_case(case: dict) -> dict:
    from fabric_imitation.tools.evaluate import ScriptedTrial, TrialScenario

    name = SIZE_RANGES[case["kind"]][0]
    try:
        scenario = TrialScenario(name, _size_text(case["size"]), case["pose"])
        trial = ScriptedTrial(scenario, on_violation="count")
    except InputError as e:
        return {**case, "refused": str(e)}
    return {
        **case,
        "success": trial["success"],
        "rule_breaks_true": trial["rule_breaks_true"]["any"],
        "collisions": trial.get("collisions", 0),
        "error": trial["error"],
        "success_details": trial["success_details"],
    }


def BenchDemos(*, out: Path, workers: int = 1) -> dict:
    """Runs the cases not yet in `out`'s JSON-lines file (<out>.jsonl),
    appending each as it finishes; writes the summary to `out`."""
    from fabric_imitation.tools.executors import RunJobs

    out = Path(out)
    lines = out.with_suffix(".jsonl")
    done = {}
    if lines.exists():
        for line in lines.read_text().splitlines():
            if line.strip():
                row = json.loads(line)
                done[_key(row)] = row
    todo = [c for c in _cases() if _key(c) not in done]
    total = len(done) + len(todo)
    with lines.open("a") as f:
        for row in RunJobs(_run_case, todo, workers=workers, ordered=False):
            f.write(json.dumps(row) + "\n")
            f.flush()
            done[_key(row)] = row
            verdict = (
                "refused"
                if "refused" in row
                else ("success" if row["success"] else "failure")
            )
            print(
                f"bench demos: {len(done)}/{total} {row['kind']} {row['size']} "
                f"pose {row['pose_index']}: {verdict}",
                file=sys.stderr,
                flush=True,
            )
    summary = {}
    for kind in SIZE_RANGES:
        rows = [r for r in done.values() if r["kind"] == kind]
        run = [r for r in rows if "refused" not in r]
        summary[kind] = {
            "cases": len(rows),
            "refused": len(rows) - len(run),
            "run": len(run),
            "successes": sum(r["success"] for r in run),
            "rule_breaks_true": sum(r["rule_breaks_true"] for r in run),
            "collisions": sum(r["collisions"] for r in run),
            "sizes": {
                json.dumps(s): (
                    "refused"
                    if any("refused" in r for r in rows if r["size"] == s)
                    else (
                        f"{sum(r['success'] for r in rows if r['size'] == s)}/"
                        f"{sum(r['size'] == s for r in rows)}"
                    )
                )
                for s in RangeSizes(kind)
            },
        }
    result = {"ranges": {k: v[1] for k, v in SIZE_RANGES.items()}, "kinds": summary}
    tmp = out.with_suffix(".tmp")
    tmp.write_text(json.dumps(result, indent=1))
    tmp.replace(out)
    return result
