"""The `fabric-imitate` command line. Thin: each subcommand parses flags and
calls one keyword-only library function; every subcommand accepts --json
(its summary as one JSON object on stdout; progress and logs on stderr)."""

import argparse
import dataclasses as dc
import json
import logging
import sys
from collections.abc import Callable
from pathlib import Path

from fabric_imitation.learning.errors import InputError

_COMMANDS: dict[str, tuple[Callable, Callable]] = {}


def command(name: str):
    """Registers `run(args) -> dict` under `name`; `add(parser)` adds flags."""

    def wrap(add: Callable):
        def register(run: Callable):
            _COMMANDS[name] = (add, run)
            return run

        return register

    return wrap


_SCENARIOS_FILE = (
    Path(__file__).resolve().parent.parent / "scenarios" / "scenarios.yaml"
)

# Old flag spellings, still accepted with a note (one spelling: hyphens).
_OLD_SPELLINGS = {
    "--scenario_file": "--scenario-file",
    "--scenario_text": "--scenario-text",
    "--policy_text": "--policy-text",
}

DESCRIPTIONS = {
    "simulate": "Simulate a scenario's station (cloth held or the scripted task "
    "motion), optionally recording it.",
    "demo record": "Record a demo (observation-only video, depth and masks) of "
    "the scripted task in simulation.",
    "demo import": "Build a demo from a person's RGB-D recording (video + depth "
    "PNGs + intrinsics, or a ROS bag): fabric masks by colour, the object's "
    "pose from its ArUco marker.",
    "collect": "Collect prior transitions in the contact-free prior scene "
    "(random safe actions), resumable.",
    "train": "Train the priors f_R, f_D and f_I on a collected dataset.",
    "train-baselines": "Train the Zero, CFM and TCN baselines' networks on a "
    "collected dataset (next to the priors).",
    "imitate": "Imitate a demo with the priors at once, in simulation or on "
    "real drivers (--hardware): the main job.",
    "evaluate": "Run imitation trials with the object moved and turned, per "
    "scenario and method; resumable; writes a summary and a plot.",
    "watch": "Run one trial of an evaluate file again as evaluate ran it (its "
    "poses, demo, policy, sampling seed), with a meshcat recording and the "
    "camera's video, and say whether it took the same course.",
    "bench sim": "Real-time factors of the cloth engines per phase.",
    "bench collect": "Collection rate with 1 and 2 workers.",
    "bench train": "Training throughput.",
    "bench mpc": "MPC iterations and control steps, idle and with one core loaded.",
    "bench occlusion": "f_R's keypoint error as more of the fabric is hidden "
    "(grippers, partial masks), on the shipped demos' frames.",
    "bench demos": "The scripted demos over each object kind's size range "
    "(corners and centre, nominal and two moved poses): successes, rule breaks, "
    "contacts and refusals.",
    "bench tracker": "The keypoint tracker against f_R alone on the shipped "
    "demos' frames, and f_R's error model (error against heatmap spread).",
    "report": "Build the evaluation's tables and figures (success with Wilson "
    "intervals, paired comparisons against ours, stop against count) from "
    "evaluate's trial lines.",
    "compare": "Paired comparison of two runs of one method on the same poses "
    "(before and after a change, a mechanism off and on): the difference of "
    "success rates with Newcombe's interval and McNemar's test, per task and "
    "over all.",
    "diagram": "Draw the imitation diagram (its systems, ports and connections) "
    "as SVG, with its Graphviz source beside it: README's picture.",
}


def _scenario_names() -> str:
    import yaml

    try:
        with open(_SCENARIOS_FILE) as f:
            return ", ".join(yaml.safe_load(f))
    except (OSError, yaml.YAMLError, TypeError):
        return "see scenarios/scenarios.yaml"


def _scenario_flags(
    parser: argparse.ArgumentParser, *, required=True, default: str | None = None
) -> None:
    parser.add_argument(
        "--scenario",
        required=required,
        default=default,
        help=f"named scenario: {_scenario_names()}"
        + (f" (default: {default})" if default else ""),
    )
    parser.add_argument(
        "--scenario-file",
        "--scenario_file",
        dest="scenario_file",
        type=Path,
        default=None,
        help="YAML file of named scenarios (default: the built-in one)",
    )
    parser.add_argument(
        "--scenario-text",
        "--scenario_text",
        dest="scenario_text",
        default="",
        help="YAML mapping merged on top of the named scenario, e.g. "
        "'cloth: {engine: fem}'",
    )
    parser.add_argument(
        "--object-pose",
        nargs=3,
        type=float,
        default=None,
        metavar=("X", "Y", "YAW"),
        help="object pose on the table: x, y [m], yaw [deg]",
    )


def LoadScenarioFromArgs(args):
    from fabric_imitation.scenarios.loader import LoadScenario

    text = args.scenario_text
    if getattr(args, "object_pose", None) is not None:
        import yaml

        # Merged into the mapping (the text may be a one-line flow mapping,
        # which a further line would not extend).
        overrides = yaml.safe_load(text) if text and text.strip() else {}
        overrides["object"] = {
            **overrides.get("object", {}),
            "pose": [float(v) for v in args.object_pose],
        }
        text = yaml.safe_dump(overrides)
    policy = None
    if hasattr(args, "policy_text"):
        from fabric_imitation.scenarios.policy import LoadPolicy

        policy = LoadPolicy(
            priors_dir=getattr(args, "priors", None),
            filename=args.policy,
            policy_text=args.policy_text,
        )
    scenario = LoadScenario(
        scenario_name=args.scenario,
        filename=args.scenario_file,
        scenario_text=text,
        policy=policy,
    )
    if args.object_pose is not None and scenario.object.kind == "none":
        raise InputError(f"scenario {args.scenario!r} has no object to place")
    return scenario


def _add_simulate(p):
    _scenario_flags(p)
    p.add_argument(
        "--duration",
        type=float,
        default=2.0,
        help="seconds to simulate with --motion hold",
    )
    p.add_argument(
        "--motion",
        choices=["hold", "scripted"],
        default="hold",
        help="hold the grippers still, or run the task's scripted demo",
    )
    p.add_argument(
        "--record",
        type=Path,
        default=None,
        help="write a meshcat recording (HTML) here",
    )
    p.add_argument(
        "--video", type=Path, default=None, help="write the camera's view (mp4) here"
    )


@command("simulate")(_add_simulate)
def _simulate(args) -> dict:
    from fabric_imitation.tools.runs import Simulate

    return Simulate(
        scenario=LoadScenarioFromArgs(args),
        scenario_name=args.scenario,
        duration=args.duration,
        motion=args.motion,
        record=args.record,
        video=args.video,
    )


def _add_demo_record(p):
    _scenario_flags(p)
    p.add_argument("--out", type=Path, required=True, help="demo directory to write")
    p.add_argument(
        "--record",
        type=Path,
        default=None,
        help="write a meshcat recording (HTML) here",
    )
    p.add_argument(
        "--video", type=Path, default=None, help="write the camera's view (mp4) here"
    )
    p.add_argument(
        "--export-raw",
        type=Path,
        default=None,
        help="also write what an RGB-D camera driver would record here "
        "(rgb.mp4, depth/*.png in mm, intrinsics.yaml), for `demo import`",
    )
    p.add_argument(
        "--raw-scale",
        type=int,
        default=4,
        help="raw camera resolution as a multiple of the control camera's",
    )
    p.add_argument("--raw-fps", type=float, default=15.0)


@command("demo record")(_add_demo_record)
def _demo_record(args) -> dict:
    from fabric_imitation.tools.demo_record import RecordDemo

    return RecordDemo(
        scenario=LoadScenarioFromArgs(args),
        scenario_name=args.scenario,
        out=args.out,
        record=args.record,
        video=args.video,
        export_raw=args.export_raw,
        raw_scale=args.raw_scale,
        raw_fps=args.raw_fps,
    )


def _add_demo_import(p):
    _scenario_flags(p)
    p.add_argument("--out", type=Path, required=True, help="demo directory to write")
    src = p.add_argument_group(
        "recording (a video, its depth and intrinsics; or a bag)"
    )
    src.add_argument("--rgb", type=Path, help="colour video (mp4)")
    src.add_argument(
        "--depth", type=Path, help="directory of 16-bit PNGs [mm], or an .npz"
    )
    src.add_argument(
        "--intrinsics", type=Path, help="YAML: width, height, fx, fy, cx, cy"
    )
    src.add_argument("--bag", type=Path, help="ROS 1 (.bag) or ROS 2 bag")
    src.add_argument("--color-topic", default="/camera/color/image_raw")
    src.add_argument(
        "--depth-topic", default="/camera/aligned_depth_to_color/image_raw"
    )
    src.add_argument("--info-topic", default="/camera/color/camera_info")
    masks = p.add_argument_group("fabric masks (one of)")
    masks.add_argument(
        "--fabric-hsv",
        nargs=6,
        type=int,
        metavar=("H_LO", "S_LO", "V_LO", "H_HI", "S_HI", "V_HI"),
        help="the fabric's colour box in OpenCV HSV (H 0-179, S, V 0-255)",
    )
    masks.add_argument("--mask-video", type=Path, help="a video of the masks")
    marker = p.add_argument_group("the object's marker (default: the scenario's)")
    marker.add_argument("--marker-dict", default=None)
    marker.add_argument("--marker-id", type=int, default=None)
    marker.add_argument("--marker-size", type=float, default=None, help="[m]")
    marker.add_argument(
        "--table-marker-id",
        type=int,
        default=None,
        help="a marker lying on the table that gives the camera's pose",
    )
    marker.add_argument("--table-marker-size", type=float, default=0.10)
    marker.add_argument(
        "--table-marker-pose",
        nargs=3,
        type=float,
        default=[0.0, 0.0, 0.0],
        metavar=("X", "Y", "YAW"),
        help="its centre on the table [m] and turn [deg] in the world frame",
    )
    p.add_argument(
        "--step-seconds",
        type=float,
        default=None,
        help="control period the frames are subsampled to (default: the "
        "scenario's motion.step_seconds)",
    )


@command("demo import")(_add_demo_import)
def _demo_import(args) -> dict:
    from fabric_imitation.learning.demo_import import (
        MarkerSpec,
        ReadBag,
        ReadRecording,
        ReadVideo,
    )
    from fabric_imitation.tools.demo_record import ImportDemoForScenario

    scenario = LoadScenarioFromArgs(args)
    if args.bag is not None:
        recording = ReadBag(
            args.bag,
            color_topic=args.color_topic,
            depth_topic=args.depth_topic,
            info_topic=args.info_topic,
        )
    elif None in (args.rgb, args.depth, args.intrinsics):
        raise InputError("give --rgb, --depth and --intrinsics, or --bag")
    else:
        recording = ReadRecording(args.rgb, args.depth, args.intrinsics)
    if (args.fabric_hsv is None) == (args.mask_video is None):
        raise InputError("give one of --fabric-hsv or --mask-video")
    masks = None
    if args.mask_video is not None:
        frames, _ = ReadVideo(args.mask_video)
        masks = frames.max(axis=3) > 127
    spec = scenario.object.marker
    marker = MarkerSpec(
        dictionary=args.marker_dict or spec.dictionary,
        marker_id=spec.id if args.marker_id is None else args.marker_id,
        size=args.marker_size or spec.size,
        offset=list(spec.offset),
    )
    table = None
    if args.table_marker_id is not None:
        table = {
            "id": args.table_marker_id,
            "size": args.table_marker_size,
            "pose": args.table_marker_pose,
        }
    hsv = None
    if args.fabric_hsv is not None:
        hsv = (tuple(args.fabric_hsv[:3]), tuple(args.fabric_hsv[3:]))
    return ImportDemoForScenario(
        recording=recording,
        scenario=scenario,
        scenario_name=args.scenario,
        out=args.out,
        hsv=hsv,
        masks=masks,
        marker=marker,
        table_marker=table,
        step_seconds=args.step_seconds,
    )


def _add_collect(p):
    _scenario_flags(p)
    p.add_argument(
        "--transitions",
        type=int,
        default=10000,
        help="number of transitions to collect",
    )
    p.add_argument("--out", type=Path, required=True, help="dataset file (HDF5)")
    p.add_argument("--workers", type=int, default=1, help="parallel workers")
    p.add_argument("--executor", choices=["local", "ray"], default="local")
    p.add_argument(
        "--seed",
        type=int,
        default=None,
        help="random seed (default: the scenario's random_seed)",
    )


@command("collect")(_add_collect)
def _collect(args) -> dict:
    from fabric_imitation.tools.collect import Collect

    return Collect(
        scenario=LoadScenarioFromArgs(args),
        scenario_name=args.scenario,
        transitions=args.transitions,
        out=args.out,
        workers=args.workers,
        executor=args.executor,
        seed=args.seed,
    )


def _add_train(p):
    p.add_argument(
        "--data",
        type=Path,
        required=True,
        action="append",
        help="prior dataset (HDF5); with --forward-only it may be given "
        "several times, and f_D learns them together",
    )
    p.add_argument("--out", type=Path, required=True, help="checkpoint directory")
    p.add_argument("--epochs", type=int, default=20, help="epochs of f_D and f_I")
    p.add_argument("--keypoint-epochs", type=int, default=10, help="epochs of f_R")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument(
        "--forward-only",
        type=Path,
        default=None,
        metavar="PRIORS",
        help="train f_D only, from a fresh start, on the --data sets; keep "
        "these priors' f_R, f_I, normalisers and prior states",
    )


@command("train")(_add_train)
def _train(args) -> dict:
    from fabric_imitation.learning.policy import POLICY_FILE
    from fabric_imitation.learning.train import (
        TrainConfig,
        train_forward,
        train_priors,
    )

    config = TrainConfig(
        epochs=args.epochs, seed=args.seed, keypoint_epochs=args.keypoint_epochs
    )
    from fabric_imitation.scenarios.policy import (
        LoadPolicy,
        PriorsSha256,
        WritePolicy,
    )

    if args.forward_only is None and len(args.data) > 1:
        raise InputError("several --data need --forward-only (f_R learns one dataset)")
    if args.forward_only is not None:
        # The new priors get the policy of the priors they start from.
        base = Path(args.forward_only)
        policy = LoadPolicy(
            filename=base / POLICY_FILE if (base / POLICY_FILE).is_file() else None,
            check_priors=False,
        )
        result = train_forward(data=args.data, base=base, out=args.out, config=config)
    else:
        # The new priors get the policy of the priors they replace (or the
        # shipped one), for their own checksum.
        own = Path(args.out) / POLICY_FILE
        policy = LoadPolicy(filename=own if own.is_file() else None, check_priors=False)
        result = train_priors(data=args.data[0], out=args.out, config=config)
    policy = dc.replace(policy, priors_sha256=PriorsSha256(args.out))
    return {**result, "policy": str(WritePolicy(policy, args.out))}


def _add_train_baselines(p):
    p.add_argument("--data", type=Path, required=True, help="prior dataset (HDF5)")
    p.add_argument(
        "--out",
        type=Path,
        required=True,
        help="checkpoint directory (the priors' directory, so evaluate finds them)",
    )
    p.add_argument("--epochs", type=int, default=20)
    p.add_argument("--seed", type=int, default=0)


@command("train-baselines")(_add_train_baselines)
def _train_baselines(args) -> dict:
    from fabric_imitation.learning.baselines import (
        BaselineTrainConfig,
        TrainBaselines,
    )

    return TrainBaselines(
        data=args.data,
        out=args.out,
        config=BaselineTrainConfig(epochs=args.epochs, seed=args.seed),
    )


def _add_imitate(p):
    _scenario_flags(p, required=False, default="box")
    p.add_argument(
        "--demo",
        type=Path,
        default=None,
        help="demo directory (default: the shipped demo of the scenario)",
    )
    p.add_argument(
        "--priors",
        type=Path,
        default=None,
        help="priors checkpoint directory (default: the shipped priors)",
    )
    p.add_argument(
        "--record",
        type=Path,
        default=None,
        help="write a meshcat recording (HTML) here",
    )
    p.add_argument(
        "--video", type=Path, default=None, help="write the camera's view (mp4) here"
    )
    p.add_argument("--seed", type=int, default=None, help="MPC sampling seed")
    p.add_argument(
        "--hardware",
        action="store_true",
        help="run on real Panda drivers and camera over LCM (a panda scenario, "
        "e.g. box_panda); nothing is scored against simulation ground truth",
    )
    p.add_argument(
        "--lcm-url",
        default=None,
        help="LCM bus for --hardware (default: the scenario's grippers.panda.lcm_url)",
    )
    _on_violation_flag(p)
    _policy_flags(p)


def _policy_flags(p) -> None:
    p.add_argument(
        "--policy",
        type=Path,
        default=None,
        help="the method's settings: a policy YAML file (default: policy.yaml "
        "beside the priors)",
    )
    p.add_argument(
        "--policy-text",
        "--policy_text",
        dest="policy_text",
        default="",
        help="YAML mapping merged on top of the policy, e.g. "
        "'mpc: {max_iterations: 8}'",
    )


def _on_violation_flag(p) -> None:
    p.add_argument(
        "--on-violation",
        default="stop",
        help="stop (default): in simulation an episode ends as a failure at "
        "the first executed action that breaks a rule of the task's referee "
        "on the true cloth, or at the first gripper-object contact; count: "
        "the episode goes on and the breaks are only counted",
    )


@command("imitate")(_add_imitate)
def _imitate(args) -> dict:
    from fabric_imitation.tools.episode import Imitate

    scenario = LoadScenarioFromArgs(args)
    lcm = None
    if args.hardware:
        if scenario.grippers.kind != "panda":
            raise InputError(
                f"--hardware needs a scenario with Panda arms (grippers.kind: "
                f"panda), e.g. box_panda; {args.scenario!r} has "
                f"{scenario.grippers.kind}"
            )
        if args.record is not None:
            raise InputError("--record shows the simulated cloth; not with --hardware")
        from pydrake.lcm import DrakeLcm

        lcm = DrakeLcm(args.lcm_url or scenario.grippers.panda.lcm_url)
    elif args.lcm_url is not None:
        raise InputError("--lcm-url is for --hardware")
    return Imitate(
        scenario=scenario,
        scenario_name=args.scenario,
        demo_dir=args.demo,
        priors_dir=args.priors,
        record=args.record,
        video=args.video,
        seed=args.seed,
        hardware=args.hardware,
        lcm=lcm,
        on_violation=args.on_violation,
    )


def _add_evaluate(p):
    p.add_argument(
        "--scenarios", nargs="+", default=["box", "hang"], help="scenario names"
    )
    p.add_argument(
        "--methods",
        nargs="+",
        default=["ours"],
        help="ours; the ablations no_mpc, no_prior, no_cost; the baselines "
        "zero, cfm, tcn (trained by train-baselines); extra rows no_mpc_safe, "
        "tcn_mpc, replay; scripted",
    )
    p.add_argument(
        "--protocol",
        default="transformation",
        help="object poses: translation (moved <= 10 cm), transformation "
        "(moved <= 10 cm, turned <= 45 deg; default), wide (moved <= 15 cm, "
        "turned <= 90 deg)",
    )
    p.add_argument("--trials", type=int, default=10, help="trials per scenario")
    p.add_argument(
        "--out",
        type=Path,
        required=True,
        help="JSON-lines file of trials (resumed if it exists)",
    )
    p.add_argument("--workers", type=int, default=1, help="parallel trials")
    p.add_argument(
        "--executor",
        choices=["local", "ray"],
        default="local",
        help="local processes, or Ray actors (a running cluster if `ray` is "
        "connected, else a local one with --workers CPUs)",
    )
    p.add_argument("--seed", type=int, default=0, help="seed of the trial poses")
    p.add_argument(
        "--sampling-seed",
        type=int,
        default=0,
        help="seed of the controllers' sampling (same poses, another run; default 0)",
    )
    p.add_argument(
        "--demo", type=Path, default=None, help="demo directory (default: shipped)"
    )
    p.add_argument(
        "--priors", type=Path, default=None, help="priors (default: shipped)"
    )
    p.add_argument(
        "--scenario-text",
        "--scenario_text",
        dest="scenario_text",
        default="",
        help='YAML overrides for every scenario, e.g. "cloth: {engine: fem}"',
    )
    _on_violation_flag(p)
    _policy_flags(p)


@command("evaluate")(_add_evaluate)
def _evaluate(args) -> dict:
    from fabric_imitation.tools.evaluate import Evaluate

    return Evaluate(
        scenario_names=args.scenarios,
        methods=args.methods,
        trials=args.trials,
        out=args.out,
        workers=args.workers,
        seed=args.seed,
        demo=args.demo,
        priors=args.priors,
        scenario_text=args.scenario_text,
        policy=args.policy,
        policy_text=args.policy_text,
        protocol=args.protocol,
        executor=args.executor,
        sampling_seed=args.sampling_seed,
        on_violation=args.on_violation,
    )


def _add_watch(p):
    p.add_argument("runs", type=Path, help="an evaluate file (JSON lines)")
    p.add_argument(
        "--scenario", required=True, help="the trial's scenario, as in the file"
    )
    p.add_argument("--trial", type=int, required=True, help="the trial's number")
    p.add_argument(
        "--method", default=None, help="where the file holds several methods"
    )
    p.add_argument(
        "--demo",
        type=Path,
        default=None,
        help="demo directory in place of the one the trial line names",
    )
    p.add_argument(
        "--record", type=Path, default=None, help="write a meshcat recording (HTML)"
    )
    p.add_argument(
        "--video", type=Path, default=None, help="write the camera's view (mp4)"
    )


@command("watch")(_add_watch)
def _watch(args) -> dict:
    from fabric_imitation.tools.evaluate import WatchTrial

    return WatchTrial(
        runs=args.runs,
        scenario=args.scenario,
        trial=args.trial,
        method=args.method,
        demo=args.demo,
        record=args.record,
        video=args.video,
    )


def _add_bench_sim(p):
    p.add_argument(
        "--scenarios",
        nargs="+",
        default=None,
        help="scenario names (default: prior box hang box_big box_panda hang_panda)",
    )
    p.add_argument(
        "--engines",
        nargs="+",
        default=["vbd", "fem"],
        choices=["vbd", "fem"],
        help="cloth engines to measure side by side (default: both)",
    )
    p.add_argument(
        "--flat-seconds",
        type=float,
        default=1.0,
        help="simulated seconds of the flat phase",
    )
    p.add_argument(
        "--out",
        type=Path,
        default=None,
        help="also write the JSON here, and the settled box covers (front, "
        "side and top views) to the same name with .png",
    )


@command("bench sim")(_add_bench_sim)
def _bench_sim(args) -> dict:
    from fabric_imitation.tools.bench import BenchSim

    return BenchSim(
        scenario_names=args.scenarios,
        engines=args.engines,
        flat_seconds=args.flat_seconds,
        out=args.out,
    )


def _add_bench_collect(p):
    p.add_argument(
        "--transitions",
        type=int,
        default=400,
        help="transitions per run (each worker count is one run)",
    )
    p.add_argument("--out", type=Path, default=None, help="also write the JSON here")


@command("bench collect")(_add_bench_collect)
def _bench_collect(args) -> dict:
    from fabric_imitation.tools.bench import BenchCollect

    return BenchCollect(transitions=args.transitions, out=args.out)


def _add_bench_train(p):
    p.add_argument("--data", type=Path, required=True, help="prior dataset (HDF5)")
    p.add_argument(
        "--keypoint-epochs",
        type=int,
        default=None,
        help="epochs of f_R (default: the training default, 10)",
    )
    p.add_argument("--out", type=Path, default=None, help="also write the JSON here")


@command("bench train")(_add_bench_train)
def _bench_train(args) -> dict:
    from fabric_imitation.tools.bench import BenchTrain

    return BenchTrain(
        data=args.data, out=args.out, keypoint_epochs=args.keypoint_epochs
    )


def _add_bench_mpc(p):
    p.add_argument(
        "--scenarios",
        nargs="+",
        default=None,
        help="tasks whose shipped demos are used (default: box hang box_big, "
        "bench.MPC_SCENARIOS)",
    )
    p.add_argument("--priors", type=Path, default=None)
    p.add_argument("--demo", type=Path, default=None, help="with one scenario")
    p.add_argument("--steps", type=int, default=40, help="control steps timed")
    p.add_argument("--out", type=Path, default=None, help="also write the JSON here")
    _policy_flags(p)


@command("bench mpc")(_add_bench_mpc)
def _bench_mpc(args) -> dict:
    from fabric_imitation.scenarios.policy import LoadPolicy
    from fabric_imitation.tools.bench import MPC_SCENARIOS, BenchMpc

    return BenchMpc(
        scenario_names=args.scenarios or MPC_SCENARIOS,
        policy=LoadPolicy(
            priors_dir=args.priors, filename=args.policy, policy_text=args.policy_text
        ),
        priors_dir=args.priors,
        demo_dir=args.demo,
        steps=args.steps,
        out=args.out,
        progress=True,
    )


def _add_bench_occlusion(p):
    p.add_argument("--priors", type=Path, default=None)
    p.add_argument("--seed", type=int, default=0)
    p.add_argument(
        "--out", type=Path, default=None, help="also write the JSON (and a plot) here"
    )


@command("bench occlusion")(_add_bench_occlusion)
def _bench_occlusion(args) -> dict:
    from fabric_imitation.tools.bench import BenchOcclusion

    return BenchOcclusion(priors_dir=args.priors, out=args.out, seed=args.seed)


def _add_bench_tracker(p):
    p.add_argument("--priors", type=Path, default=None)
    p.add_argument(
        "--out", type=Path, default=None, help="also write the JSON (and a plot) here"
    )


@command("bench tracker")(_add_bench_tracker)
def _bench_tracker(args) -> dict:
    from fabric_imitation.tools.bench import BenchTracker

    return BenchTracker(priors_dir=args.priors, out=args.out)


def _add_bench_demos(p):
    p.add_argument(
        "--out",
        type=Path,
        default=Path("bench_demos.json"),
        help="summary JSON; each case also goes to <out>.jsonl as it finishes "
        "(a rerun resumes from it)",
    )
    p.add_argument("--workers", type=int, default=2)


@command("bench demos")(_add_bench_demos)
def _bench_demos(args) -> dict:
    from fabric_imitation.tools.bench_demos import BenchDemos

    return BenchDemos(out=args.out, workers=args.workers)


def _add_report(p):
    p.add_argument(
        "runs",
        nargs="+",
        type=Path,
        help="JSON-lines files of trials written by `fabric-imitate evaluate`",
    )
    p.add_argument(
        "--out",
        type=Path,
        required=True,
        help="Markdown file to write; one figure per table beside it, "
        "<out stem>_<protocol>_<on_violation>.png",
    )


@command("report")(_add_report)
def _report(args) -> dict:
    from fabric_imitation.tools.report import Report

    return Report(runs=args.runs, out=args.out)


def _add_compare(p):
    p.add_argument(
        "--base",
        nargs="+",
        type=Path,
        required=True,
        help="trial lines of the base run",
    )
    p.add_argument(
        "--new", nargs="+", type=Path, required=True, help="trial lines of the new run"
    )
    p.add_argument("--method", default="ours", help="method compared (default ours)")
    p.add_argument("--out", type=Path, default=None, help="also write Markdown here")


@command("compare")(_add_compare)
def _compare(args) -> dict:
    from fabric_imitation.tools.report import Compare

    return Compare(base=args.base, new=args.new, method=args.method, out=args.out)


def _add_diagram(p):
    p.add_argument(
        "--out",
        type=Path,
        default=Path("docs/imitation_diagram.svg"),
        help="SVG file to write (default docs/imitation_diagram.svg); the "
        "Graphviz source goes beside it (.dot)",
    )
    p.add_argument("--scenario", default="box", help="scenario whose demo it imitates")


@command("diagram")(_add_diagram)
def _diagram(args) -> dict:
    from fabric_imitation.tools.picture import DrawImitationDiagram

    return DrawImitationDiagram(out=args.out, scenario_name=args.scenario)


# The referee's rules for a violation (tasks/referee.py's ON_VIOLATION;
# repeated here so that a bad flag is refused before torch is imported).
ON_VIOLATION = ("stop", "count")


def _CheckYamlMapping(text: str, flag: str) -> None:
    """`text` (a flag's value) is empty or a YAML mapping."""
    if not text or not text.strip():
        return
    import yaml

    try:
        data = yaml.safe_load(text)
    except yaml.YAMLError as e:
        mark = getattr(e, "problem_mark", None)
        where = f" at line {mark.line + 1}, column {mark.column + 1}" if mark else ""
        problem = getattr(e, "problem", None) or "not valid YAML"
        raise InputError(f"{flag}: YAML syntax error{where}: {problem}") from None
    if not isinstance(data, dict):
        example = (
            "'cloth: {engine: fem}'"
            if flag == "--scenario-text"
            else ("'mpc: {max_iterations: 8}'")
        )
        raise InputError(
            f"{flag} must be a YAML mapping such as {example}, got {text!r}"
        )


def _CheckArgs(args) -> None:
    """What can be checked before any work starts (and before Drake or torch
    are imported): the YAML of --scenario-text and --policy-text, counts that must be
    positive, --on-violation, and that output files can be created where
    asked."""
    rule = getattr(args, "on_violation", None)
    if rule is not None and rule not in ON_VIOLATION:
        raise InputError(
            f"unknown --on-violation {rule!r}; use {' or '.join(ON_VIOLATION)}"
        )
    for flag in ("scenario_text", "policy_text"):
        _CheckYamlMapping(getattr(args, flag, ""), "--" + flag.replace("_", "-"))
    for name in ("trials", "workers", "transitions", "steps"):
        value = getattr(args, name, None)
        if value is not None and value < 1:
            raise InputError(f"--{name} must be at least 1, got {value}")
    protocol = getattr(args, "protocol", None)
    if protocol is not None:
        from fabric_imitation.tools.evaluate import PROTOCOLS

        if protocol not in PROTOCOLS:
            raise InputError(
                f"unknown protocol {protocol!r}; known: {', '.join(PROTOCOLS)}"
            )
    for name in ("record", "video"):
        path = getattr(args, name, None)
        if path is not None and not Path(path).resolve().parent.is_dir():
            raise InputError(
                f"--{name} {path}: directory {Path(path).resolve().parent} "
                "does not exist"
            )


def _build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="fabric-imitate",
        description="One-shot imitation of cloth tasks from one demo video.",
    )
    groups = parser.add_subparsers(dest="command", required=True)
    nested: dict[str, argparse._SubParsersAction] = {}
    for name, (add, _) in _COMMANDS.items():
        words = name.split()
        text = DESCRIPTIONS.get(name)
        if len(words) == 1:
            sub = groups.add_parser(words[0], help=text, description=text)
        else:
            if words[0] not in nested:
                group = groups.add_parser(words[0], help=f"{words[0]} subcommands")
                nested[words[0]] = group.add_subparsers(
                    dest="subcommand", required=True
                )
            sub = nested[words[0]].add_parser(words[1], help=text, description=text)
        sub.add_argument(
            "--json",
            action="store_true",
            help="print the summary as one JSON object on stdout",
        )
        sub.add_argument(
            "-v",
            "--verbose",
            action="store_true",
            help="also show solver and third-party chatter (filtered by default)",
        )
        add(sub)
        sub.set_defaults(_name=name)
    return parser


def _print(summary: dict, as_json: bool, out) -> None:
    if as_json:
        print(json.dumps(summary, default=str), file=out, flush=True)
        return
    for key, value in summary.items():
        print(f"{key}: {json.dumps(value, default=str)}", file=out, flush=True)


# Lines that tell a user nothing: the QP solver of Drake's differential IK
# prints the first on every solve; the Panda URDF's tags Drake ignores; the
# renderer skipping the arms' .dae visuals.
CHATTER = (
    "Polishing not needed",
    "found as a child of 'joint' is currently unsupported",
    "RenderEngineVtk only supports Mesh specifications",
    "Allocating contexts to support implicit context parallelism",
)


class _DropChatter(logging.Filter):
    def filter(self, record: logging.LogRecord) -> bool:
        message = record.getMessage()
        return not any(c in message for c in CHATTER)


def _stdout_for_summary_only(verbose: bool = False):
    """Points file descriptor 1 at stderr for the rest of the process (through
    a filter of CHATTER unless `verbose`) and returns a stream on the real
    stdout: native libraries print there and would otherwise break the
    one-JSON-object stdout."""
    import os
    import threading

    sys.stdout.flush()
    saved = os.dup(1)
    if verbose:
        os.dup2(2, 1)
    else:
        read, write = os.pipe()
        os.dup2(write, 1)
        os.close(write)

        def forward():
            with os.fdopen(read, "r", errors="replace") as lines:
                for line in lines:
                    if not any(c in line for c in CHATTER):
                        sys.stderr.write(line)

        threading.Thread(target=forward, daemon=True).start()
        logging.getLogger("drake").addFilter(_DropChatter())
    sys.stdout = sys.stderr
    return os.fdopen(saved, "w")


def main(argv: list[str] | None = None) -> int:
    # torch's C++ extension helper, imported by parts of torch, warns on every
    # run that a machine without CUDA has no CUDA runtime; nothing here uses it.
    logging.getLogger("torch.utils.cpp_extension").setLevel(logging.ERROR)
    parser = _build_parser()
    argv = sys.argv[1:] if argv is None else list(argv)
    for word in argv:
        old = word.split("=")[0]
        if old in _OLD_SPELLINGS:
            print(
                f"fabric-imitate: note: {old} is now spelled {_OLD_SPELLINGS[old]}",
                file=sys.stderr,
            )
    args = parser.parse_args(argv)
    _, run = _COMMANDS[args._name]
    try:
        _CheckArgs(args)
    except InputError as e:
        print(f"fabric-imitate: error: {e}", file=sys.stderr)
        return 2
    out = _stdout_for_summary_only(verbose=args.verbose)
    try:
        summary = run(args)
    except InputError as e:
        print(f"fabric-imitate: error: {e}", file=sys.stderr)
        return 2
    except KeyboardInterrupt as e:
        detail = f" {e}" if str(e) else ""
        print(f"fabric-imitate: interrupted{detail}", file=sys.stderr)
        return 130
    _print(summary, args.json, out)
    return 0


if __name__ == "__main__":
    sys.exit(main())
