"""`fabric-imitate report`: every table and figure of the evaluation, built
from the trial lines that `fabric-imitate evaluate` writes (one JSON object
per line), so that nothing in the results page is typed by hand.

One table per (protocol, on_violation); one row per (scenario, method). All
intervals are 95 %:

- a success rate: the Wilson score interval (Wilson 1927);
- a method against `ours` on the same poses: the difference of the paired
  success rates with Newcombe's square-and-add interval built from the
  marginals' Wilson intervals and the corrected phi (Newcombe 1998, Stat Med
  17:2635, method 10), and McNemar's exact test (a two-sided binomial test of
  the discordant pairs against 1/2).

numpy and matplotlib only: no pydrake, no torch.
"""

import json
import math
import os
import re
import statistics
import tempfile
from collections import Counter
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from fabric_imitation.learning.errors import InputError

Z95 = statistics.NormalDist().inv_cdf(0.975)

# Fingerprints that must agree within a table, and within a row as well.
TABLE_FINGERPRINTS = ("code", "priors", "baselines")
# Per task (every method's row of one scenario in a table): the referee's
# thresholds belong to the task, and paired rows must share scene and demo.
ROW_FINGERPRINTS = ("referee", "scenario", "demo")
# Pose seeds from here on are test seeds (docs/benchmark.md, seed ledger).
FIRST_TEST_SEED = 1000
REQUIRED = (
    "scenario",
    "method",
    "trial",
    "protocol",
    "pose_seed",
    "sampling_seed",
    "on_violation",
    "success",
    "fingerprint",
)
# What a trial measured: two lines of the same trial must agree on these.
OUTCOME = (
    "success",
    "error",
    "termination",
    "halt",
    "final_iou",
    "final_chamfer",
    "rule_breaks_true",
    "collisions",
    "steps",
)
# Huo et al., Table I: success % per method on (box, hang).
PAPER_TASKS = ("box", "hang")
PAPER_TABLE_I = {
    "zero": (1.8, 0.0),
    "cfm": (0.0, 1.4),
    "tcn": (6.6, 2.4),
    "no_mpc": (0.0, 3.0),
    "no_prior": (14.4, 7.4),
    "no_cost": (3.0, 2.2),
    "ours": (81.9, 72.7),
}
METHOD_ORDER = (
    "ours",
    "no_mpc",
    "no_prior",
    "no_cost",
    "zero",
    "cfm",
    "tcn",
    "replay",
    "scripted",
)
PROTOCOL_ORDER = ("translation", "transformation", "wide")
VIOLATION_ORDER = ("stop", "count")
# Protocol and on_violation become parts of figure file names.
_NAME = re.compile(r"[A-Za-z0-9_.-]+")


def Wilson(successes: int, trials: int, z: float = Z95) -> tuple[float, float]:
    """Wilson's score interval of a binomial proportion (Wilson 1927):
    (p + z^2/2n -+ z sqrt(p(1-p)/n + z^2/4n^2)) / (1 + z^2/n)."""
    if trials < 1 or not 0 <= successes <= trials:
        raise ValueError(
            f"need 0 <= successes <= trials, trials >= 1; got {successes} / {trials}"
        )
    p = successes / trials
    scale = 1 + z * z / trials
    center = (p + z * z / (2 * trials)) / scale
    half = z / scale * math.sqrt(p * (1 - p) / trials + z * z / (4 * trials**2))
    return max(0.0, center - half), min(1.0, center + half)


def NewcombePaired(
    a: int, b: int, c: int, d: int, z: float = Z95
) -> tuple[float, float, float]:
    """Difference p1 - p2 of paired proportions and its interval, Newcombe
    (1998, Stat Med 17:2635), method 10. Pairs: a both succeed, b only the
    first, c only the second, d neither; p1 = (a+b)/n, p2 = (a+c)/n.

    With (l_i, u_i) the Wilson intervals of p_i and phi the corrected phi
    coefficient of the 2x2 table,
    L = D - sqrt((p1-l1)^2 - 2 phi (p1-l1)(u2-p2) + (u2-p2)^2),
    U = D + sqrt((p2-l2)^2 - 2 phi (p2-l2)(u1-p1) + (u1-p1)^2).
    phi = C / sqrt((a+b)(c+d)(a+c)(b+d)) (0 when a margin is empty), with
    C = ad - bc - n/2 if ad - bc > n/2, 0 if 0 <= ad - bc <= n/2, ad - bc
    if ad - bc < 0."""
    n = a + b + c + d
    if n < 1 or min(a, b, c, d) < 0:
        raise ValueError(f"need counts >= 0 and at least one pair; got {a, b, c, d}")
    p1, p2 = (a + b) / n, (a + c) / n
    l1, u1 = Wilson(a + b, n, z)
    l2, u2 = Wilson(a + c, n, z)
    margins = (a + b) * (c + d) * (a + c) * (b + d)
    cross = a * d - b * c
    if margins == 0 or 0 <= cross <= n / 2:
        phi = 0.0
    else:
        phi = (cross - n / 2 if cross > 0 else cross) / math.sqrt(margins)
    diff = (b - c) / n
    x, y = p1 - l1, u2 - p2
    lower = diff - math.sqrt(max(0.0, x * x - 2 * phi * x * y + y * y))
    x, y = p2 - l2, u1 - p1
    upper = diff + math.sqrt(max(0.0, x * x - 2 * phi * x * y + y * y))
    return diff, lower, upper


def McNemarExact(b: int, c: int) -> float:
    """Two-sided p-value of McNemar's exact test: b of the b + c discordant
    pairs against Binomial(b + c, 1/2), twice the smaller tail, at most 1."""
    n = b + c
    if n == 0:
        return 1.0
    tail = sum(math.comb(n, k) for k in range(min(b, c) + 1))
    return min(1.0, 2 * tail / 2**n)


@dataclass(frozen=True)
class Trial:
    """One trial line and where it was read ("file line N")."""

    where: str
    row: dict

    def __getitem__(self, name: str):
        return self.row[name]

    @property
    def table(self) -> tuple[str, str]:
        return self.row["protocol"], self.row["on_violation"]

    @property
    def cell(self) -> tuple[str, str]:
        return self.row["scenario"], self.row["method"]

    @property
    def identity(self) -> tuple:
        r = self.row
        return (*self.cell, *self.table, r["pose_seed"], r["sampling_seed"], r["trial"])


def _check_line(row, where: str) -> None:
    if not isinstance(row, dict):
        raise InputError(f"{where}: not a JSON object")
    if "pose_seed" not in row:
        older = " (it has 'seed': an older evaluate wrote it)" if "seed" in row else ""
        raise InputError(
            f"{where}: no 'pose_seed'{older}; run fabric-imitate evaluate again"
        )
    for name in REQUIRED:
        if name not in row:
            raise InputError(f"{where}: no {name!r} field")
    for name in ("trial", "pose_seed", "sampling_seed"):
        if type(row[name]) is not int:
            raise InputError(f"{where}: {name!r} must be an integer, got {row[name]!r}")
    for name in ("scenario", "method"):
        if not isinstance(row[name], str) or not row[name]:
            raise InputError(f"{where}: {name!r} must be a name, got {row[name]!r}")
    for name in ("protocol", "on_violation"):
        if not isinstance(row[name], str) or not _NAME.fullmatch(row[name]):
            raise InputError(
                f"{where}: {name!r} must be letters, digits, '_', '-' or '.', "
                f"got {row[name]!r}"
            )
    if not isinstance(row["success"], bool):
        raise InputError(f"{where}: 'success' must be true or false")
    fingerprint = row["fingerprint"]
    if not isinstance(fingerprint, dict):
        raise InputError(f"{where}: 'fingerprint' must be an object")
    for name in (*TABLE_FINGERPRINTS, *ROW_FINGERPRINTS):
        if name not in fingerprint:
            raise InputError(f"{where}: the fingerprint has no {name!r}")


def ScenarioLabel(row: dict) -> str:
    """The trial's scenario name, with its `--scenario-text` (whitespace
    collapsed) in brackets where it has one: a variant of a named scenario
    (another object size, say) is another task."""
    text = " ".join(str(row.get("scenario_text") or "").split())
    return f"{row['scenario']} [{text}]" if text else row["scenario"]


def LoadTrials(runs: list[Path]) -> list[Trial]:
    """Every trial line of `runs`, checked (fields, fingerprints agree within
    a table and a row, no trial twice with different outcomes), the same
    trial read twice kept once. A trial run with `--scenario-text` is a row
    of its own, named by the scenario and the text (`ScenarioLabel`)."""
    if not runs:
        raise InputError("no run files given")
    trials = []
    for path in runs:
        path = Path(path)
        if not path.is_file():
            raise InputError(f"{path}: no such file")
        count = 0
        for number, line in enumerate(path.read_text().splitlines(), start=1):
            if not line.strip():
                continue
            where = f"{path} line {number}"
            try:
                row = json.loads(line)
            except json.JSONDecodeError as e:
                raise InputError(f"{where}: not JSON ({e.msg})") from None
            _check_line(row, where)
            trials.append(Trial(where, {**row, "scenario": ScenarioLabel(row)}))
            count += 1
        if count == 0:
            raise InputError(f"{path}: no trials")
    _check_fingerprints(trials)
    _check_seed_blocks(trials)
    return _once(trials)


def _check_seed_blocks(trials: list[Trial]) -> None:
    """A table is all development seeds or all test seeds, never both."""
    blocks: dict[tuple, dict[bool, Trial]] = {}
    for t in trials:
        blocks.setdefault(t.table, {}).setdefault(t["pose_seed"] >= FIRST_TEST_SEED, t)
    for table, kinds in blocks.items():
        if len(kinds) == 2:
            raise InputError(
                "table {}/{} mixes development pose seeds ({}) and test pose seeds "
                "({}); report them apart".format(
                    *table, kinds[False].where, kinds[True].where
                )
            )


def _check_fingerprints(trials: list[Trial]) -> None:
    first: dict[tuple, Trial] = {}
    for t in trials:
        for group, names, what in (
            (t.table, TABLE_FINGERPRINTS, "table {}/{}".format(*t.table)),
            (
                (*t.table, t.cell[0]),
                ROW_FINGERPRINTS,
                "task {} of table {}/{}".format(t.cell[0], *t.table),
            ),
        ):
            other = first.setdefault(group, t)
            for name in names:
                mine, theirs = t["fingerprint"][name], other["fingerprint"][name]
                if mine != theirs:
                    raise InputError(
                        f"{what}: fingerprint {name!r} differs: {theirs!r} "
                        f"({other.where}) vs {mine!r} ({t.where})"
                    )


def _once(trials: list[Trial]) -> list[Trial]:
    seen: dict[tuple, Trial] = {}
    for t in trials:
        other = seen.setdefault(t.identity, t)
        outcome = json.dumps([t.row.get(k) for k in OUTCOME], sort_keys=True)
        if outcome != json.dumps([other.row.get(k) for k in OUTCOME], sort_keys=True):
            scenario, method, protocol, violation, pose, sampling, trial = t.identity
            raise InputError(
                f"{other.where} and {t.where}: trial {trial} of {scenario}/{method} "
                f"({protocol}, {violation}, pose seed {pose}, sampling seed "
                f"{sampling}) twice with different outcomes"
            )
    return list(seen.values())


def _order(values, known) -> list:
    rank = {v: i for i, v in enumerate(known)}
    return sorted(set(values), key=lambda v: (rank.get(v, len(rank)), v))


def Pairs(left: list[Trial], right: list[Trial]) -> list[tuple[Trial, Trial]]:
    """Trials of `left` and `right` on the same pose (same scenario, protocol,
    pose seed and trial; the caller picks the rest): equal sampling seeds
    pair first, the rest in order of sampling seed; the unpaired are left out."""
    groups: dict[tuple, tuple[dict, dict]] = {}
    for side, trials in enumerate((left, right)):
        for t in trials:
            key = (t["scenario"], t["protocol"], t["pose_seed"], t["trial"])
            groups.setdefault(key, ({}, {}))[side][t["sampling_seed"]] = t
    pairs = []
    for key in sorted(groups):
        lhs, rhs = groups[key]
        for seed in sorted(lhs.keys() & rhs.keys()):
            pairs.append((lhs.pop(seed), rhs.pop(seed)))
        pairs += [
            (lhs[i], rhs[j]) for i, j in zip(sorted(lhs), sorted(rhs), strict=False)
        ]
    return pairs


def CellStats(trials: list[Trial]) -> dict:
    """A row of a table: successes with the Wilson interval, IoU mean and
    (population) standard deviation, Chamfer mean, true rule breaks,
    collisions, terminations by kind; crashed trials count as failures."""
    rows = [t.row for t in trials]
    successes = sum(r["success"] for r in rows)
    low, high = Wilson(successes, len(rows))
    iou = np.array([r["final_iou"] for r in rows if r.get("final_iou") is not None])
    chamfer = [r["final_chamfer"] for r in rows if r.get("final_chamfer") is not None]
    breaks = [
        int(r["rule_breaks_true"].get("any", 0))
        for r in rows
        if isinstance(r.get("rule_breaks_true"), dict)
    ]
    collisions = [int(r["collisions"]) for r in rows if r.get("collisions") is not None]
    ends = Counter(r["termination"] for r in rows if r.get("termination"))
    errors = sum(bool(r.get("error")) and not r.get("termination") for r in rows)
    if errors:
        ends["error"] = errors
    return {
        "trials": len(rows),
        "successes": int(successes),
        "success_rate": successes / len(rows),
        "wilson95": [low, high],
        "iou_mean": float(iou.mean()) if iou.size else None,
        "iou_std": float(iou.std()) if iou.size else None,
        "chamfer_mean": float(np.mean(chamfer)) if chamfer else None,
        "rule_breaks_true": sum(breaks) if breaks else None,
        "trials_with_rule_breaks": sum(b > 0 for b in breaks) if breaks else None,
        "collisions": sum(collisions) if collisions else None,
        "trials_with_collisions": sum(c > 0 for c in collisions)
        if collisions
        else None,
        "terminations": dict(sorted(ends.items())),
        "fingerprint": {k: trials[0]["fingerprint"][k] for k in ROW_FINGERPRINTS},
    }


def PairedStats(pairs: list[tuple[Trial, Trial]]) -> dict:
    """First against second of each pair: the 2x2 counts, the difference of
    success rates with Newcombe's interval, McNemar's exact p-value."""
    a = sum(x["success"] and y["success"] for x, y in pairs)
    b = sum(x["success"] and not y["success"] for x, y in pairs)
    c = sum(not x["success"] and y["success"] for x, y in pairs)
    d = len(pairs) - a - b - c
    out = {"pairs": len(pairs), "both": a, "first_only": b, "second_only": c}
    out["neither"] = d
    out["first_successes"], out["second_successes"] = a + b, a + c
    if pairs:
        diff, low, high = NewcombePaired(a, b, c, d)
        out.update(
            difference=diff, newcombe95=[low, high], mcnemar_p=McNemarExact(b, c)
        )
    return out


def _paper(method: str, scenario: str) -> float | None:
    if method in PAPER_TABLE_I and scenario in PAPER_TASKS:
        return PAPER_TABLE_I[method][PAPER_TASKS.index(scenario)]
    return None


def _num(value, fmt: str) -> str:
    return "-" if value is None else format(value, fmt)


def _pp(paired: dict) -> tuple[str, str, str]:
    if not paired["pairs"]:
        return "-", "-", "-"
    low, high = paired["newcombe95"]
    return (
        f"{100 * paired['difference']:+.1f} pp",
        f"[{100 * low:+.1f}, {100 * high:+.1f}] pp",
        f"{paired['mcnemar_p']:.3g}",
    )


def _table_markdown(table: dict, figure: str) -> list[str]:
    fp = table["fingerprint"]
    lines = [
        f"## Protocol `{table['protocol']}`, on violation `{table['on_violation']}`",
        "",
        f"Pose seeds: {', '.join(map(str, table['pose_seeds']))}. Sampling seeds: "
        f"{', '.join(map(str, table['sampling_seeds']))}.",
        "Fingerprints: "
        + ", ".join(f"{k} `{fp[k]}`" for k in TABLE_FINGERPRINTS)
        + ".",
        "",
        "| task | method | success | Wilson 95 % [%] | paper Table I [%] | IoU "
        "(mean ± SD) | Chamfer (mean) | true rule breaks (trials) | collisions "
        "(trials) | terminations | referee / scenario / demo fingerprint |",
        "|---|---|---|---|---|---|---|---|---|---|---|",
    ]
    for r in table["rows"]:
        iou = (
            "-"
            if r["iou_mean"] is None
            else f"{r['iou_mean']:.2f} ± {r['iou_std']:.2f}"
        )
        breaks = (
            "-"
            if r["rule_breaks_true"] is None
            else f"{r['rule_breaks_true']} ({r['trials_with_rule_breaks']})"
        )
        hits = (
            "-"
            if r["collisions"] is None
            else f"{r['collisions']} ({r['trials_with_collisions']})"
        )
        ends = ", ".join(f"{k} {v}" for k, v in r["terminations"].items()) or "-"
        low, high = r["wilson95"]
        lines.append(
            f"| {r['scenario']} | {r['method']} | {r['successes']} / {r['trials']} "
            f"({100 * r['success_rate']:.1f} %) | [{100 * low:.1f}, {100 * high:.1f}] "
            f"| {_num(_paper(r['method'], r['scenario']), '.1f')} | {iou} "
            f"| {_num(r['chamfer_mean'], '.3g')} | {breaks} | {hits} | {ends} "
            f"| `{r['fingerprint']['referee']}` / `{r['fingerprint']['scenario']}` "
            f"/ `{r['fingerprint']['demo']}` |"
        )
    lines += [
        "",
        f"![success rates, {table['protocol']}, {table['on_violation']}]({figure})",
        "",
    ]
    if table["paired"]:
        lines += [
            "Against `ours` on the same poses (difference method - ours; "
            "Newcombe's paired interval; McNemar's exact test):",
            "",
            "| task | method | pairs | both / method only / ours only / neither "
            "| difference | 95 % interval | McNemar p |",
            "|---|---|---|---|---|---|---|",
        ]
        for p in table["paired"]:
            diff, interval, pvalue = _pp(p)
            lines.append(
                f"| {p['scenario']} | {p['method']} | {p['pairs']} | {p['both']} / "
                f"{p['first_only']} / {p['second_only']} / {p['neither']} | {diff} "
                f"| {interval} | {pvalue} |"
            )
        lines.append("")
    return lines


def _stop_markdown(rows: list[dict]) -> list[str]:
    lines = [
        "## What stopping at a violation costs",
        "",
        "The same poses run with `stop` and with `count` (difference stop - "
        "count; Newcombe's paired interval; McNemar's exact test):",
        "",
        "| protocol | task | method | pairs | stop | count | difference "
        "| 95 % interval | McNemar p |",
        "|---|---|---|---|---|---|---|---|---|",
    ]
    for p in rows:
        diff, interval, pvalue = _pp(p)
        lines.append(
            f"| {p['protocol']} | {p['scenario']} | {p['method']} | {p['pairs']} "
            f"| {p['first_successes']} / {p['pairs']} | {p['second_successes']} / "
            f"{p['pairs']} | {diff} | {interval} | {pvalue} |"
        )
    return [*lines, ""]


_METHODS_NOTE = """## How the figures are computed

- Success: successes / trials; a trial that raised is a failure. Interval:
  Wilson's score interval, (p + z²/2n ∓ z √(p(1-p)/n + z²/4n²)) / (1 + z²/n),
  z = 1.96 (E. B. Wilson, J. Am. Stat. Assoc. 22:209, 1927).
- IoU: mean and population standard deviation over the trials that scored
  one; Chamfer: mean as the trial lines give it.
- Paired difference (a: both succeed, b: first only, c: second only, d:
  neither; n pairs): D = (b - c)/n with Newcombe's method 10 (R. G.
  Newcombe, Stat. Med. 17:2635, 1998): from the Wilson intervals (l1, u1),
  (l2, u2) of the marginals p1 = (a+b)/n, p2 = (a+c)/n,
  L = D - √((p1-l1)² - 2φ(p1-l1)(u2-p2) + (u2-p2)²),
  U = D + √((p2-l2)² - 2φ(p2-l2)(u1-p1) + (u1-p1)²), where
  φ = C / √((a+b)(c+d)(a+c)(b+d)) (0 if a margin is empty) and C = ad - bc -
  n/2 if ad - bc > n/2, 0 if 0 ≤ ad - bc ≤ n/2, ad - bc if ad - bc < 0.
  Pairs: same scenario, protocol, on_violation, pose seed and trial (equal
  sampling seeds first); trials without a partner are left out.
- McNemar's exact test: p = min(1, 2 Σ_{k ≤ min(b, c)} C(b+c, k) / 2^(b+c)).
"""


def _plot(table: dict, path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    scenarios = _order([r["scenario"] for r in table["rows"]], PAPER_TASKS)
    methods = _order([r["method"] for r in table["rows"]], METHOD_ORDER)
    cells = {(r["scenario"], r["method"]): r for r in table["rows"]}
    width = 0.8 / len(methods)
    width_in = 3 + 0.45 * len(scenarios) * len(methods)
    # Labels turned 30 degrees, so that long ones (a scenario with its
    # --scenario-text) do not run into each other; the figure grows by the
    # longest label's height (0.055 inch a character at font size 7).
    label_in = math.sin(math.radians(30)) * 0.055 * max(len(s) for s in scenarios)
    fig, ax = plt.subplots(figsize=(max(5.0, width_in), 3.2 + label_in))
    paper_label = "paper Table I"
    for k, method in enumerate(methods):
        x = np.arange(len(scenarios)) + (k - (len(methods) - 1) / 2) * width
        rate, low, high, paper = [], [], [], []
        for s in scenarios:
            r = cells.get((s, method))
            rate.append(r["success_rate"] if r else np.nan)
            # Clamped: at 0 % or 100 % the bound equals the rate up to rounding.
            low.append(max(r["success_rate"] - r["wilson95"][0], 0.0) if r else 0)
            high.append(max(r["wilson95"][1] - r["success_rate"], 0.0) if r else 0)
            value = _paper(method, s)
            paper.append(np.nan if value is None else value / 100)
        ax.bar(x, rate, width, yerr=[low, high], capsize=2, label=method)
        if not np.all(np.isnan(paper)):
            ax.plot(x, paper, "kx", label=paper_label)
            paper_label = None
    ax.set_xticks(
        np.arange(len(scenarios)), scenarios, rotation=30, ha="right", fontsize=7
    )
    ax.set_ylabel("success rate (Wilson 95 %)")
    ax.set_ylim(0, 1.05)
    ax.set_title(
        f"{table['protocol']}, on violation: {table['on_violation']}", fontsize=9
    )
    ax.legend(fontsize=7, loc="upper left", bbox_to_anchor=(1.0, 1.0))
    fig.tight_layout()
    fig.savefig(path, format="png", dpi=90)
    plt.close(fig)


def _temp_beside(path: Path) -> Path:
    fd, name = tempfile.mkstemp(dir=path.parent, prefix=f".{path.name}.", suffix=".tmp")
    os.close(fd)
    return Path(name)


def Report(*, runs: list[Path], out: Path) -> dict:
    """Writes `out` (Markdown: one table per protocol and on_violation, the
    paired comparisons against `ours`, stop against count) and one figure per
    table beside it, `<out stem>_<protocol>_<on_violation>.png`, from the
    trial lines of `runs`. Nothing is written when any input is refused."""
    runs, out = [Path(p) for p in runs], Path(out)
    if not out.parent.is_dir():
        raise InputError(f"--out {out}: directory {out.parent} does not exist")
    if any(out.resolve() == p.resolve() for p in runs):
        raise InputError(f"--out {out} is one of the run files")
    trials = LoadTrials(runs)
    tables, figures = [], {}
    protocols = _order([t["protocol"] for t in trials], PROTOCOL_ORDER)
    violations = _order([t["on_violation"] for t in trials], VIOLATION_ORDER)
    for protocol in protocols:
        for violation in violations:
            mine = [t for t in trials if t.table == (protocol, violation)]
            if not mine:
                continue
            table = _Table(mine)
            figure = out.with_name(f"{out.stem}_{protocol}_{violation}.png")
            if any(figure.resolve() == p.resolve() for p in runs):
                raise InputError(f"figure {figure} would overwrite a run file")
            table["figure"] = str(figure)
            figures[figure] = table
            tables.append(table)
    stop_vs_count = _StopVsCount(trials, protocols)
    command = " ".join(["fabric-imitate report", *map(str, runs), "--out", str(out)])
    lines = [
        f"Generated by `{command}` from the trial lines of those files; do not "
        "edit by hand.",
        "",
        "# Evaluation results",
        "",
    ]
    for table in tables:
        lines += _table_markdown(table, Path(table["figure"]).name)
    if stop_vs_count:
        lines += _stop_markdown(stop_vs_count)
    lines.append(_METHODS_NOTE)
    temps: list[tuple[Path, Path]] = []
    try:
        for figure, table in figures.items():
            temps.append((_temp_beside(figure), figure))
            _plot(table, temps[-1][0])
        temps.append((_temp_beside(out), out))
        temps[-1][0].write_text("\n".join(lines))
        for temp, final in temps:
            os.replace(temp, final)
    finally:
        for temp, _ in temps:
            temp.unlink(missing_ok=True)
    return {
        "out": str(out),
        "figures": [str(f) for f in figures],
        "trials": len(trials),
        "tables": tables,
        "stop_vs_count": stop_vs_count,
    }


def _Table(mine: list[Trial]) -> dict:
    """One table's rows and its paired comparisons against `ours`, from the
    trials of one protocol and on_violation rule."""
    by_cell: dict[tuple, list[Trial]] = {}
    for t in mine:
        by_cell.setdefault(t.cell, []).append(t)
    scenarios = _order([s for s, _ in by_cell], PAPER_TASKS)
    methods = _order([m for _, m in by_cell], METHOD_ORDER)
    cells = [(s, m) for s in scenarios for m in methods if (s, m) in by_cell]
    return {
        "protocol": mine[0]["protocol"],
        "on_violation": mine[0]["on_violation"],
        "pose_seeds": sorted({t["pose_seed"] for t in mine}),
        "sampling_seeds": sorted({t["sampling_seed"] for t in mine}),
        "fingerprint": {k: mine[0]["fingerprint"][k] for k in TABLE_FINGERPRINTS},
        "rows": [
            {"scenario": s, "method": m} | CellStats(by_cell[s, m]) for s, m in cells
        ],
        "paired": [
            {"scenario": s, "method": m}
            | PairedStats(Pairs(by_cell[s, m], by_cell[s, "ours"]))
            for s, m in cells
            if m != "ours" and (s, "ours") in by_cell
        ],
    }


def _StopVsCount(trials: list[Trial], protocols: list[str]) -> list[dict]:
    """Per protocol, task and method: the paired difference of `stop` and
    `count` on the same poses, where both were run."""
    found = []
    for protocol in protocols:
        rows = [t for t in trials if t["protocol"] == protocol]
        for scenario in _order([t["scenario"] for t in rows], PAPER_TASKS):
            for method in _order([t["method"] for t in rows], METHOD_ORDER):
                sides = [
                    [
                        t
                        for t in rows
                        if t.cell == (scenario, method) and t["on_violation"] == v
                    ]
                    for v in ("stop", "count")
                ]
                pairs = Pairs(*sides)
                if pairs:
                    found.append(
                        {"protocol": protocol, "scenario": scenario, "method": method}
                        | PairedStats(pairs)
                    )
    return found


# Two trials are on the same pose where their poses and cloth starts agree
# to this (metres, degrees as written in the trial lines).
SAME_POSE_TOLERANCE = 1e-4


def Compare(
    *,
    base: list[Path],
    new: list[Path],
    method: str = "ours",
    out: Path | None = None,
) -> dict:
    """Paired comparison of two runs of `method` on the same poses: `base`
    (for example the code before a change, or a mechanism off) against
    `new`. Trials pair by scenario, protocol, pose seed, trial and sampling
    seed, and must have the same object pose and cloth start; per scenario
    and over all of them: the 2 x 2 counts, the difference new - base of the
    success rates with Newcombe's interval, McNemar's exact p-value, and each
    side's true rule breaks and collisions. Each side is checked as `report`
    checks a table (one code, priors and referee fingerprint); the sides may
    differ in anything but the referee. Writes Markdown to `out` when
    given."""
    base, new = [Path(p) for p in base], [Path(p) for p in new]
    if out is not None:
        out = Path(out)
        if not out.parent.is_dir():
            raise InputError(f"--out {out}: directory {out.parent} does not exist")
        if any(out.resolve() == p.resolve() for p in [*base, *new]):
            raise InputError(f"--out {out} is one of the run files")
    sides = {
        name: _compare_side(name, runs, method)
        for name, runs in (("base", base), ("new", new))
    }
    if sides["base"][0]["on_violation"] != sides["new"][0]["on_violation"]:
        raise InputError(
            "--base and --new ran under different --on-violation rules: "
            f"{sides['base'][0]['on_violation']} and {sides['new'][0]['on_violation']}"
        )
    pairs = [
        (n, b)
        for b, n in Pairs(sides["base"], sides["new"])
        if b["sampling_seed"] == n["sampling_seed"]
    ]
    if not pairs:
        raise InputError("--base and --new share no trial (same poses and seeds)")
    for n, b in pairs:
        _check_same_trial(b, n)
        if b["fingerprint"]["referee"] != n["fingerprint"]["referee"]:
            raise InputError(
                f"{b.where} and {n.where}: judged by different referees "
                f"({b['fingerprint']['referee']} against "
                f"{n['fingerprint']['referee']}); success means different things"
            )

    def side_counts(trials) -> dict:
        rows = [t.row for t in trials]
        return {
            "successes": sum(r["success"] for r in rows),
            "rule_breaks_true": sum(
                int(r["rule_breaks_true"].get("any", 0))
                for r in rows
                if isinstance(r.get("rule_breaks_true"), dict)
            ),
            "collisions": sum(int(r.get("collisions") or 0) for r in rows),
        }

    def summary(chosen) -> dict:
        stats = PairedStats(chosen)
        return {
            "pairs": stats["pairs"],
            "base": side_counts([b for _, b in chosen]),
            "new": side_counts([n for n, _ in chosen]),
            "both": stats["both"],
            "new_only": stats["first_only"],
            "base_only": stats["second_only"],
            "neither": stats["neither"],
            "difference": stats["difference"],
            "newcombe95": stats["newcombe95"],
            "mcnemar_p": stats["mcnemar_p"],
        }

    scenarios = _order([n["scenario"] for n, _ in pairs], PAPER_TASKS)
    rows = {s: summary([p for p in pairs if p[0]["scenario"] == s]) for s in scenarios}
    result = {
        "method": method,
        "on_violation": sides["base"][0]["on_violation"],
        "base": [str(p) for p in base],
        "new": [str(p) for p in new],
        "out": None if out is None else str(out),
        "fingerprints": {
            name: {
                field: sorted({t["fingerprint"][field] for t in trials})
                for field in (*TABLE_FINGERPRINTS, *ROW_FINGERPRINTS)
            }
            for name, trials in sides.items()
        },
        "machines": {
            name: sorted({t.row["machine"]["id"] for t in trials if "machine" in t.row})
            for name, trials in sides.items()
        },
        "base_code": sides["base"][0]["fingerprint"]["code"],
        "new_code": sides["new"][0]["fingerprint"]["code"],
        "unpaired": {
            "base": len(sides["base"]) - len(pairs),
            "new": len(sides["new"]) - len(pairs),
        },
        "pose_seeds": sorted({n["pose_seed"] for n, _ in pairs}),
        "scenarios": rows,
        "all": summary(pairs),
    }
    if out is not None:
        temp = _temp_beside(out)
        try:
            temp.write_text(_compare_markdown(result))
            os.replace(temp, out)
        finally:
            temp.unlink(missing_ok=True)
    return result


def _compare_side(name: str, runs: list[Path], method: str) -> list[Trial]:
    """One side of `Compare`: the trials of `method`, of one code and priors
    fingerprint and one stopping rule."""
    trials = [t for t in LoadTrials(runs) if t["method"] == method]
    if not trials:
        raise InputError(f"--{name}: no trials of method {method!r}")
    for field in ("code", "priors"):
        values = sorted({t["fingerprint"][field] for t in trials})
        if len(values) > 1:
            raise InputError(
                f"--{name}: trials of more than one {field} fingerprint "
                f"({', '.join(values)})"
            )
    violations = sorted({t["on_violation"] for t in trials})
    if len(violations) > 1:
        raise InputError(
            f"--{name}: trials under more than one --on-violation "
            f"({', '.join(violations)})"
        )
    return trials


def _check_same_trial(b: Trial, n: Trial) -> None:
    """Refuses a pair whose object pose or cloth start differ, or where one
    side records a cloth start and the other does not."""
    for field in ("pose", "cloth_start"):
        if (field in b.row) != (field in n.row):
            raise InputError(
                f"{b.where} and {n.where}: only one of the two records {field!r}"
            )
        if field not in b.row:
            continue
        x, y = np.asarray(b[field], dtype=float), np.asarray(n[field], dtype=float)
        if (
            x.shape != y.shape
            or not np.all(np.isfinite(x))
            or not np.all(np.isfinite(y))
            or not np.allclose(x, y, rtol=0.0, atol=SAME_POSE_TOLERANCE)
        ):
            raise InputError(
                f"{b.where} and {n.where}: the same trial has a different "
                f"{field} ({b[field]} against {n[field]})"
            )


def _machines_markdown(machines: dict) -> list[str]:
    """A note where the two sides ran on different machines (trial lines'
    `machine` id; lines written before it was recorded say nothing)."""
    base, new = machines["base"], machines["new"]
    if not base or not new or (base == new and len(base) == 1):
        return []
    return [
        "",
        f"Machines: base {', '.join(base)}, new {', '.join(new)}. On another "
        "CPU the same seed rounds differently and trajectories part, so the "
        "pairs differ by the machine as well as by the change.",
    ]


def _compare_markdown(result: dict) -> str:
    command = " ".join(
        [
            "fabric-imitate compare --base",
            *result["base"],
            "--new",
            *result["new"],
            "--method",
            result["method"],
            *(["--out", result["out"]] if result["out"] else []),
        ]
    )
    lines = [
        f"Generated by `{command}`; do not edit by hand.",
        "",
        f"`{result['method']}`, on violation `{result['on_violation']}`, pose "
        f"seeds {', '.join(map(str, result['pose_seeds']))}; code "
        f"`{result['base_code']}` (base) against `{result['new_code']}` (new).",
        *_machines_markdown(result["machines"]),
        "",
        "| task | pairs | base | new | both / new only / base only / neither "
        "| difference (new - base) | 95 % interval | McNemar p | rule breaks "
        "base / new | collisions base / new |",
        "|---|---|---|---|---|---|---|---|---|---|",
    ]
    for name, row in [*result["scenarios"].items(), ("all", result["all"])]:
        low, high = row["newcombe95"]
        lines.append(
            f"| {name} | {row['pairs']} | {row['base']['successes']} | "
            f"{row['new']['successes']} | {row['both']} / {row['new_only']} / "
            f"{row['base_only']} / {row['neither']} | "
            f"{100 * row['difference']:+.1f} pp | [{100 * low:+.1f}, "
            f"{100 * high:+.1f}] pp | {row['mcnemar_p']:.3g} | "
            f"{row['base']['rule_breaks_true']} / {row['new']['rule_breaks_true']} | "
            f"{row['base']['collisions']} / {row['new']['collisions']} |"
        )
    return "\n".join(lines) + "\n"
