"""The `meshfg` console script: offline tools of meshfg_ros, one subcommand each.

A subcommand is a pair of small functions, `add_arguments(parser)` and `run(args) -> exit code`,
registered in the COMMANDS table at the end of this file. Run functions import what they need
when called, so `meshfg --help` starts fast (the estimator pulls in torch).
Bad input (a missing or wrong recording, topic, mesh, parameter, an existing output) ends with
one line `meshfg <command>: error: <message>` on stderr and exit code 1, never a traceback;
nothing existing is overwritten.
"""

from __future__ import annotations

import argparse
import json
import shlex
import sys
import time
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

REPOSITORY_ROOT = Path(__file__).resolve().parents[1]
BUNDLED_RECORDING_DIRS = (REPOSITORY_ROOT / "bags", Path(sys.prefix) / "share" / "meshfg_ros" / "bags")
DEMO_SCENARIO = "cao-push"
DEMO_SEED = 0


@dataclass(frozen=True)
class Command:
    """One subcommand: its name, one-line help, argument set-up and run function."""

    name: str
    help: str
    add_arguments: Callable[[argparse.ArgumentParser], None]
    run: Callable[[argparse.Namespace], int]


# Exception classes that mean bad input, by module: reported in one line, without a traceback.
# Looked up in sys.modules only: an exception's class is defined in a module already imported,
# so the error path never imports anything (the estimator's modules pull in torch).
_USER_ERRORS: tuple[tuple[str, tuple[str, ...]], ...] = (
    ("meshfg_ros.io.recording", ("RecordingError",)),
    ("meshfg_ros.core.geometry.mesh", ("MeshFileError", "InvalidMeshError", "DegenerateMeshError")),
    ("meshfg_ros.core.inputs.patient_mesh", ("PatientMeshError",)),
    ("meshfg_ros.parameters", ("ParameterError",)),
    ("meshfg_ros.synthetic.scenarios", ("ScenarioError",)),
    ("meshfg_ros.core.physics.simulator", ("SimulatorConfigError", "SimulatorInputError")),
    ("meshfg_ros.core.estimation.estimator", ("EstimatorConfigError",)),
    ("meshfg_ros.blas", ("BlasSettingError",)),
    ("meshfg_ros.core.worker_threads", ("WorkerThreadsSettingError",)),
    ("meshfg_ros.replay", ("ReplayError",)),
    ("meshfg_ros.evaluation.evaluate", ("EvaluationError",)),
    ("meshfg_ros.evaluation.render", ("OutputDirectoryError",)),
    ("meshfg_ros.nodes.parameter_client", ("ParameterClientError",)),
)


def is_user_error(error: BaseException) -> bool:
    """Whether `error` reports bad input (a file, topic, mesh, parameter, existing output)."""
    if isinstance(error, OSError):
        return True
    for module_name, class_names in _USER_ERRORS:
        module = sys.modules.get(module_name)
        if module is not None and isinstance(error, tuple(getattr(module, name) for name in class_names)):
            return True
    return False


def _error_text(error: BaseException) -> str:
    if isinstance(error, OSError) and error.strerror:
        text = f"{error.strerror}: {error.filename}" if error.filename else error.strerror
    else:
        text = str(error) or type(error).__name__
    return " ".join(text.split())


def _progress(description: str):
    """A progress(iterable, total) wrapper drawing a tqdm bar on stderr."""
    from tqdm import tqdm

    def wrap(iterable, total):
        return tqdm(iterable, total=total, desc=description, unit="step", file=sys.stderr, dynamic_ncols=True)

    return wrap


def _positive_integer(text: str) -> int:
    """argparse type: an integer >= 1."""
    try:
        value = int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"{text!r} is not an integer") from None
    if value < 1:
        raise argparse.ArgumentTypeError(f"{value} is not a positive integer")
    return value


def bundled_recording(name: str) -> Path | None:
    """Path of the bundled recording `name` (repository bags/ or the installed share), if any."""
    for directory in BUNDLED_RECORDING_DIRS:
        if (directory / name / "metadata.yaml").is_file():
            return directory / name
    return None


# --------------------------------------------------------------------------- synth
def _synth_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("scenario", help="cube-translate, cube-shear-spd, cube-shear-nonspd, cao-push, liver-push, "
                                         "slab-inclusion, dome-tilted, liver-gravity, kidney-drag, flap-bend, sheet-cut "
                                         "or organ-slab (organ scale, for the bench)")
    parser.add_argument("--out", required=True, type=Path, help="new recording directory to write")
    parser.add_argument("--seed", type=int, default=0, help="random seed of the scenario (default 0)")
    parser.add_argument("--max-points", type=_positive_integer, default=None,
                        help="cap on points per cloud (seeded subsample)")


def run_synth(args: argparse.Namespace) -> int:
    from meshfg_ros.synthetic.recordings import synthesize

    counts = synthesize(args.scenario, args.out, seed=args.seed, max_points=args.max_points,
                        progress=_progress(f"synth {args.scenario} truth"))
    print(f"wrote {args.out}: " + ", ".join(f"{topic} x{count}" for topic, count in sorted(counts.items())))
    return 0


# --------------------------------------------------------------------------- replay
def _replay_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("bag", type=Path, help="input recording (rosbag2 directory)")
    parser.add_argument("--out", required=True, type=Path, help="new recording directory for the outputs")
    parser.add_argument("--config", type=Path, help="YAML of parameters over the recording's scenario defaults "
                                                    "(a flat mapping, or the /** section of a ROS 2 params file)")
    parser.add_argument("--factors", help="factor configuration (overrides the config's 'factors')")
    parser.add_argument("--mesh", type=Path, help="initial mesh file (.msh, .vtu, .vtk) instead of the recording's")


def _replay_overrides(args: argparse.Namespace) -> dict:
    from meshfg_ros.replay import config_overrides

    overrides = config_overrides(args.config) if args.config is not None else {}
    if args.factors is not None:
        overrides["factors"] = args.factors
    return overrides


def run_replay(args: argparse.Namespace) -> int:
    from meshfg_ros.replay import write_replay

    counts = write_replay(args.bag, args.out, _replay_overrides(args), args.mesh, _progress("replay"))
    print(f"wrote {args.out}: " + ", ".join(f"{topic} x{count}" for topic, count in sorted(counts.items())))
    return 0


# --------------------------------------------------------------------------- eval
def _eval_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("outbag", type=Path, help="output recording of `meshfg replay`")
    parser.add_argument("--truth", required=True, type=Path, help="recording with /meshfg/ground_truth")
    parser.add_argument("--json", type=Path, help="new JSON file for the metrics (metres)")
    parser.add_argument("--samples", type=_positive_integer, default=None,
                        help="surface samples per mesh (default 10000)")
    parser.add_argument("--calibration-plot", type=Path, metavar="PNG",
                        help="new PNG of the reliability diagrams of the factor graph's position_std "
                             "(needs a replay that publishes it, on the truth's mesh)")


def run_eval(args: argparse.Namespace) -> int:
    from meshfg_ros.evaluation.evaluate import (
        DEFAULT_SAMPLES,
        EvaluationError,
        evaluate_recordings,
        format_tables,
        write_json,
    )

    _refuse_existing(args.json)
    _refuse_existing(args.calibration_plot)
    samples = DEFAULT_SAMPLES if args.samples is None else args.samples
    evaluation = evaluate_recordings(args.outbag, args.truth, samples)
    if args.calibration_plot is not None and "calibration" not in evaluation:
        raise EvaluationError(f"no calibration plot: {args.outbag} has no position_std on the truth's mesh")
    print(format_tables(evaluation))
    if args.json is not None:
        write_json(evaluation, args.json)
        print(f"\nwrote {args.json}")
    if args.calibration_plot is not None:
        from meshfg_ros.evaluation.render import write_calibration_plot

        print(f"wrote {write_calibration_plot(evaluation, args.calibration_plot)}")
    return 0


# --------------------------------------------------------------------------- render
def _render_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("outbag", type=Path, help="output recording of `meshfg replay`")
    parser.add_argument("--out", required=True, type=Path, help="new (or empty) directory for the PNGs")
    parser.add_argument("--truth", type=Path, help="recording with /meshfg/ground_truth (error colours and plots)")


def run_render(args: argparse.Namespace) -> int:
    from meshfg_ros.evaluation.render import render

    for path in render(args.outbag, args.out, args.truth):
        print(f"wrote {path}")
    return 0


# --------------------------------------------------------------------------- demo
def _demo_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--out", type=Path, help="new (or empty) output directory (default: the first free "
                                                 "out/demo, out/demo-2, ... in the current directory)")


def _free_directory(base: Path) -> Path:
    candidate, index = base, 1
    while candidate.exists() and (not candidate.is_dir() or any(candidate.iterdir())):
        index += 1
        candidate = base.with_name(f"{base.name}-{index}")
    return candidate


def run_demo(args: argparse.Namespace) -> int:
    """The main job on bundled data: replay the airway push, evaluate, render, print the tables."""
    from meshfg_ros.evaluation.evaluate import evaluate_recordings, format_tables, write_json
    from meshfg_ros.evaluation.render import prepare_output_directory, render
    from meshfg_ros.replay import write_replay
    from meshfg_ros.synthetic.recordings import synthesize

    started = time.perf_counter()
    out = prepare_output_directory(args.out if args.out is not None else _free_directory(Path("out") / "demo"))
    bag = bundled_recording(DEMO_SCENARIO)
    if bag is None:
        bag = out / DEMO_SCENARIO
        print(f"no bundled {DEMO_SCENARIO} recording: synthesising {bag} (seed {DEMO_SEED})", file=sys.stderr)
        synthesize(DEMO_SCENARIO, bag, seed=DEMO_SEED)
    replay_bag = out / "replay"
    write_replay(bag, replay_bag, progress=_progress("replay"))
    evaluation = evaluate_recordings(replay_bag, bag)
    write_json(evaluation, out / "evaluation.json")
    pictures = render(replay_bag, out / "pictures", bag, evaluation)
    print(format_tables(evaluation))
    print(f"\ninput recording: {bag}\nreplay output:   {replay_bag}\nmetrics (JSON):  {out / 'evaluation.json'}")
    print("pictures:        " + "\n                 ".join(str(p) for p in pictures))
    print(f"demo finished in {time.perf_counter() - started:.1f} s")
    return 0


# --------------------------------------------------------------------------- ablation
def _ablation_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--scenario", required=True, choices=("cube-translate", "cube-shear-spd", "cube-shear-nonspd"))
    parser.add_argument("--steps", type=_positive_integer, default=15, help="steps at 1 Hz (default 15, as the paper)")
    parser.add_argument("--seed", type=int, default=0, help="scenario seed (default 0)")
    parser.add_argument("--json", type=Path, help="write the table as JSON (never overwritten)")
    parser.add_argument("--plot", type=Path, help="write the table as a PNG bar chart (never overwritten)")


def run_ablation(args: argparse.Namespace) -> int:
    from meshfg_ros.evaluation.ablation import format_table, run_ablation, write_plot

    _refuse_existing(args.json)
    _refuse_existing(args.plot)
    result = run_ablation(args.scenario, steps=args.steps, seed=args.seed)
    print(format_table(result))
    if args.json is not None:
        args.json.write_text(json.dumps(result, indent=2))
        print(f"\nwrote {args.json}")
    if args.plot is not None:
        write_plot(result, args.plot)
        print(f"wrote {args.plot}")
    return 0


# --------------------------------------------------------------------------- accuracy
ACCURACY_SCENES = ("cube-shear-spd", "cao-push", "liver-push", "slab-inclusion", "dome-tilted", "liver-gravity",
                   "kidney-drag", "flap-bend", "sheet-cut")


def _accuracy_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--out", type=Path, default=Path("out") / "accuracy",
                        help="output directory (default out/accuracy): replays, synthesised scenes (reused), "
                             "accuracy.json, accuracy.png and calibration.png")
    parser.add_argument("--scenes", nargs="+", choices=ACCURACY_SCENES, default=list(ACCURACY_SCENES),
                        help="scenes (default: all)")
    parser.add_argument("--seeds", type=int, nargs="+", default=[0],
                        help="scene seeds (default 0: the bundled recordings); with several, each seed's run goes "
                             "to OUT/seed<N>/ and OUT/accuracy.json and .png pool them")
    parser.add_argument("--json", type=Path, help="also write the result here (never overwritten)")
    parser.add_argument("--plot", type=Path, help="also write the PNG summary here (never overwritten)")
    parser.add_argument("--calibration-plot", type=Path, metavar="PNG",
                        help="also write the reliability diagrams of the published std here (never overwritten)")
    _results_argument(parser, "accuracy")


def _results_argument(parser: argparse.ArgumentParser, section: str, why: str = "") -> None:
    parser.add_argument("--results", type=Path, metavar="MD",
                        help=f"also write the printed tables into this markdown file's '{section}' section ({why}with "
                             "the machine and the commit; e.g. docs/results.md; created if missing, its other "
                             "sections kept)")


def _write_results(args: argparse.Namespace, section: str, report: str, markdown: bool,
                   machine: str | None = None) -> None:
    """The printed report into --results' section (results_file.py), said on stdout; `machine`:
    the CPU it was measured on (default: this process's)."""
    if args.results is None:
        return
    from meshfg_ros import results_file

    results_file.write_section(args.results, section, args.command_line, report, markdown=markdown, machine=machine)
    print(f"wrote section '{section}' of {args.results}")


def run_accuracy(args: argparse.Namespace) -> int:
    from meshfg_ros.evaluation import accuracy

    _refuse_existing(args.json)
    _refuse_existing(args.plot)
    _refuse_existing(args.calibration_plot)
    seeds = list(dict.fromkeys(args.seeds))

    def progress(name):
        return _progress(f"accuracy {name}")

    if len(seeds) == 1:
        result = accuracy.run_accuracy(args.out, tuple(args.scenes), seeds[0], bundled_recording, progress)
        table, write_plot = accuracy.format_table(result), accuracy.write_plot
    else:
        result = accuracy.run_accuracy_seeds(args.out, tuple(args.scenes), seeds, bundled_recording, progress)
        table, write_plot = accuracy.format_seeds_table(result), accuracy.write_seeds_plot
    print(table)
    _write_results(args, "accuracy" if len(seeds) == 1 else "accuracy over seeds", table, markdown=True)
    outputs = [args.out / "accuracy.json", args.out / "accuracy.png", args.out / "calibration.png"]
    accuracy.save(result, outputs[0])
    write_plot(result, outputs[1])
    accuracy.write_calibration_plot(result, outputs[2])
    if args.json is not None:
        accuracy.save(result, args.json)
        outputs.append(args.json)
    if args.plot is not None:
        write_plot(result, args.plot)
        outputs.append(args.plot)
    if args.calibration_plot is not None:
        accuracy.write_calibration_plot(result, args.calibration_plot)
        outputs.append(args.calibration_plot)
    print("\nwrote " + ", ".join(str(path) for path in outputs))
    return 0


# --------------------------------------------------------------------------- bench
def _bench_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--json", type=Path, help="write the figures as JSON (never overwritten)")
    parser.add_argument("--plot", type=Path, help="write a PNG of latencies vs targets and baselines")
    sections = ("core", "estimator", "loaded", "baselines", "live", "organ_live")
    parser.add_argument("--sections", nargs="+", default=list(sections), choices=sections,
                        help="what to measure (default: all; loaded: the estimator with one busy process per core; "
                             "organ_live: the live pipeline at organ scale, idle and loaded)")
    parser.add_argument("--bag", type=Path, help="recording for the live section (default: bundled cao-push)")
    parser.add_argument("--organ-bag", type=Path,
                        help="organ-scale recording for organ_live (default: the organ-slab scene, synthesized "
                             "once into the user's cache, ~/.cache/meshfg/)")
    parser.add_argument("--runs", type=_positive_integer, default=1,
                        help="measure this many times in a row and say in how many runs each target held "
                             "(default 1)")
    _results_argument(parser, "bench on <this CPU>", "a section per CPU model, since speed depends on it; ")


def run_bench(args: argparse.Namespace) -> int:
    from meshfg_ros.benchmarks import bench

    _refuse_existing(args.json)
    _refuse_existing(args.plot)
    bag = args.bag if args.bag is not None else bundled_recording(DEMO_SCENARIO)
    organ_bag = None
    if "organ_live" in args.sections:
        organ_bag = args.organ_bag if args.organ_bag is not None else bench.organ_recording()
    results, printed = [], []
    for number in range(1, args.runs + 1):
        if args.runs > 1:
            print(f"bench: run {number} of {args.runs}", file=sys.stderr)
        results.append(bench.run_bench(tuple(args.sections), bag, organ_bag=organ_bag))
        heading = f"Run {number} of {args.runs}:\n" if args.runs > 1 else ""
        printed.append(("\n" if number > 1 else "") + heading + bench.format_report(results[-1]))
        print(printed[-1], flush=True)
    if args.runs == 1:
        bench.save(results[0], args.json)
        if args.plot is not None:
            bench.write_plot(results[0], args.plot)
    else:
        printed.append("\n" + bench.format_tally(results))
        print(printed[-1])
        bench.save({"runs": results, "tally": bench.tally(results)}, args.json)
        if args.plot is not None:
            bench.write_tally_plot(results, args.plot)
    if args.plot is not None:
        print(f"wrote {args.plot}")
    from meshfg_ros.results_file import bench_section

    cpu = results[0]["machine"]["cpu"]
    _write_results(args, bench_section(cpu), "\n".join(printed), markdown=False, machine=cpu)
    return 0


# --------------------------------------------------------------------------- fuzz
def _fuzz_arguments(parser: argparse.ArgumentParser) -> None:
    def seconds(text: str) -> float:
        try:
            value = float(text)
        except ValueError:
            raise argparse.ArgumentTypeError(f"{text!r} is not a number") from None
        if not value > 0.0:
            raise argparse.ArgumentTypeError(f"{value} is not a positive number of seconds")
        return value

    parser.add_argument("--decoder-cases", type=_positive_integer, default=10_000,
                        help="PointCloud2 messages to decode (default 10000)")
    parser.add_argument("--update-calls", type=_positive_integer, default=2_000,
                        help="estimator updates, bad and good input mixed (default 2000)")
    parser.add_argument("--replays", type=_positive_integer, default=20,
                        help="hostile copies of the recording to replay (default 20)")
    parser.add_argument("--no-recovery", action="store_true", help="skip the recovery measurement")
    parser.add_argument("--seed", type=int, default=0, help="seed of every campaign (default 0)")
    parser.add_argument("--timeout", type=seconds, default=60.0,
                        help="seconds a case may run before it counts as a hang (default 60)")
    parser.add_argument("--bag", type=Path, help="recording of the update, replay and recovery campaigns "
                                                 "(default: the bundled cao-push)")
    parser.add_argument("--json", type=Path,
                        help="also write the counts and recovery figures as JSON (never overwritten)")


def run_fuzz(args: argparse.Namespace) -> int:
    """Exit code 0 when no case crashed, hung, returned NaN or a wrong answer, else 1."""
    from meshfg_ros.fuzz import format_report, run_fuzz, save

    _refuse_existing(args.json)
    bag = args.bag if args.bag is not None else bundled_recording(DEMO_SCENARIO)
    if bag is None:
        raise FileNotFoundError(2, "No bundled recording (pass --bag)", DEMO_SCENARIO)
    results = run_fuzz(bag, args.decoder_cases, args.update_calls, args.replays, not args.no_recovery, args.seed,
                       args.timeout, show_progress=True)
    print(format_report(results))
    if args.json is not None:
        save(results, args.json)
        print(f"\nwrote {args.json}")
    return 1 if any(counts.failures for counts in results) else 0


# --------------------------------------------------------------------------- mesh
def _mesh_arguments(parser: argparse.ArgumentParser) -> None:
    actions = parser.add_subparsers(dest="mesh_action", required=True, metavar="ACTION")
    info = actions.add_parser("info", help="size, units guess, element quality, fixed vertices and groups of a "
                                           "mesh file", description="What a mesh file holds, before using it.")
    info.add_argument("file", type=Path, help="tetrahedral mesh (.msh, .vtu, .vtk, ...)")
    info.add_argument("--clouds", type=Path, metavar="BAG",
                      help="a recording of the scene (its first clouds, world frame): which units make the mesh "
                           "agree with them, as the estimator node checks them")
    info.add_argument("--mesh-pose", type=float, nargs=7, default=[0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 1.0],
                      metavar=("X", "Y", "Z", "QX", "QY", "QZ", "QW"),
                      help="mesh_pose to place the mesh with for --clouds (default: identity)")
    info.set_defaults(mesh_run=run_mesh_info)
    export = actions.add_parser("export", help="write a recording's initial mesh to a mesh file",
                                description="Write the first /meshfg/initial_mesh of a recording to a mesh file "
                                            "(by extension: .msh, .vtu or .vtk), fixed vertices as point data "
                                            "'fixed'.")
    export.add_argument("bag", type=Path, help="recording (rosbag2 directory)")
    export.add_argument("--out", required=True, type=Path, help="new mesh file (never overwritten)")
    export.set_defaults(mesh_run=run_mesh_export)


def run_mesh(args: argparse.Namespace) -> int:
    return args.mesh_run(args)


def run_mesh_info(args: argparse.Namespace) -> int:
    import numpy as np

    from meshfg_ros.core.inputs.patient_mesh import ORGAN_SIZE_RANGE_M, plausible_units, read_patient_mesh
    from meshfg_ros.synthetic.mismatch_scenes import radius_ratios

    read = read_patient_mesh(args.file)
    mesh = read.mesh
    sides = mesh.vertices.max(axis=0) - mesh.vertices.min(axis=0)
    units = plausible_units(float(sides.max()))
    low, high = ORGAN_SIZE_RANGE_M
    if not units:
        units_text = f"none of m, cm, mm makes the largest side ({sides.max():.3g}) an organ's {low:g}-{high:g} m"
    else:
        units_text = " or ".join(f"{unit}: the largest side is {sides.max() * metres:.3g} m at mesh_scale {metres:g}"
                                 for unit, metres in units) + f" (organs: {low:g}-{high:g} m)"
        if len(units) > 1:
            units_text += "; only the clouds tell which (--clouds BAG, or the estimator's check of its first clouds)"
    quality = radius_ratios(mesh.vertices, mesh.tetrahedra)
    groups = ", ".join(f"{name} ({indices.size} vertices)" for name, indices in sorted(read.groups.items()))
    rows = [
        ("vertices", f"{mesh.vertex_count}"),
        ("tetrahedra", f"{mesh.tetrahedron_count} (surface: {len(mesh.surface_triangles)} triangles)"),
        ("bounding box", f"{sides[0]:.4g} x {sides[1]:.4g} x {sides[2]:.4g} (file units), "
                         f"diagonal {np.linalg.norm(sides):.4g}"),
        ("units (guess)", units_text),
        *([("units (clouds)", _units_from_clouds(mesh, args.clouds, args.mesh_pose))] if args.clouds else []),
        ("element quality", f"radius ratio min {quality.min():.3f}, median {np.median(quality):.3f} "
                            "(1: regular tetrahedron, 0: flat)"),
        ("fixed vertices", f"{mesh.fixed_vertices.size} (point data 'fixed')"),
        ("groups", groups or "none"),
    ]
    print(str(args.file))
    for label, text in rows:
        print(f"  {label + ':':<17}{text}")
    return 0


def _units_from_clouds(mesh, bag: Path, mesh_pose: list[float], clouds: int = 3) -> str:
    """Which units make `mesh` (file units) agree with the first `clouds` clouds of `bag`, as the
    estimator node checks its first clouds (core/inputs/patient_mesh.py), and why the others do not."""
    import itertools

    from meshfg_ros.core.inputs.patient_mesh import UNITS, PatientMeshError, check_against_clouds, place_mesh
    from meshfg_ros.io.messages import PointCloudRecord
    from meshfg_ros.io.recording import RecordingReader
    from meshfg_ros.topics import POINTS_TOPIC

    with RecordingReader(bag) as reader:
        reader.require(POINTS_TOPIC, PointCloudRecord)
        first = list(itertools.islice(reader.records(POINTS_TOPIC, PointCloudRecord), clouds))
    agree, disagree = [], []
    for unit, metres in UNITS.items():
        try:
            check_against_clouds(place_mesh(mesh, metres, mesh_pose), [cloud.points for cloud in first],
                                 scale_origin=mesh_pose[:3])
            agree.append(f"{unit} (mesh_scale {metres:g})")
        except PatientMeshError as error:
            disagree.append(f"{unit}: {error}")
    frames = sorted({cloud.frame_id for cloud in first})
    verdict = (f"{' and '.join(agree)} {'agrees' if len(agree) == 1 else 'agree'}" if agree else "no unit agrees")
    return (f"{verdict} with the first {len(first)} clouds of {bag} (frame {', '.join(frames)}); "
            + "; ".join(disagree))


def run_mesh_export(args: argparse.Namespace) -> int:
    from meshfg_ros.core.geometry.mesh import save_mesh
    from meshfg_ros.io.messages import MeshState
    from meshfg_ros.io.recording import RecordingReader, TopicNotFoundError
    from meshfg_ros.topics import INITIAL_MESH_TOPIC

    _refuse_existing(args.out)
    with RecordingReader(args.bag) as reader:
        state = next(iter(reader.records(INITIAL_MESH_TOPIC, MeshState)), None)
    if state is None:
        raise TopicNotFoundError(f"{INITIAL_MESH_TOPIC} in {args.bag} holds no mesh")
    mesh = state.tet_mesh(name=args.out.stem)
    save_mesh(mesh, args.out)
    print(f"wrote {args.out}: {mesh.vertex_count} vertices, {mesh.tetrahedron_count} tetrahedra, "
          f"{mesh.fixed_vertices.size} fixed, in frame {state.frame_id!r}")
    return 0


# --------------------------------------------------------------------------- params
def _params_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("bag", type=Path, help="recording (rosbag2 directory)")
    parser.add_argument("--out", type=Path, help="new ROS 2 parameters file (default: print it)")


def run_params(args: argparse.Namespace) -> int:
    """The parameters the replay of the recording uses, as a ROS 2 parameters file (`/**`)."""
    from meshfg_ros.parameters import parameters_yaml
    from meshfg_ros.replay import recording_parameters

    _refuse_existing(args.out)
    parameters = recording_parameters(args.bag)
    text = (f"# meshfg params {args.bag.name}: the parameters of its replay, for the live nodes "
            f"(--ros-args --params-file this file).\n" + parameters_yaml(parameters))
    if args.out is None:
        print(text, end="")
    else:
        args.out.write_text(text)
        print(f"wrote {args.out}")
    return 0


# --------------------------------------------------------------------------- param
def _param_arguments(parser: argparse.ArgumentParser) -> None:
    actions = parser.add_subparsers(dest="param_action", required=True, metavar="ACTION")
    get = actions.add_parser("get", help="print parameters of a running node",
                             description="Print parameters of a running node (as `ros2 param get`).")
    get.add_argument("node", help="fully qualified node name, e.g. /meshfg/estimator_node")
    get.add_argument("names", nargs="+", help="parameter names")
    put = actions.add_parser("set", help="set a parameter of a running node (the dynamic ones)",
                             description="Set a parameter of a running node (as `ros2 param set`); the node "
                                         "range-checks it and answers with the reason when it refuses.")
    put.add_argument("node", help="fully qualified node name, e.g. /meshfg/estimator_node")
    put.add_argument("name", help="parameter name")
    put.add_argument("value", help="the value, in YAML: 0.002, true, [0.0, 0.0, 1.0], a string")
    parser.add_argument("--timeout", type=float, default=10.0, help="seconds to wait for the node (default 10)")


def run_param(args: argparse.Namespace) -> int:
    """Read or set a running node's parameters over its parameter services (nodes/parameter_client.py)."""
    import yaml

    from meshfg_ros.nodes.parameter_client import get_parameters, set_parameter

    if args.param_action == "get":
        for name, value in get_parameters(args.node, args.names, args.timeout).items():
            print(f"{name}: {value}")
        return 0
    value = yaml.safe_load(args.value)
    set_parameter(args.node, args.name, value, args.timeout)
    print(f"{args.node}: {args.name} = {value!r}")
    return 0


def _refuse_existing(path: Path | None) -> None:
    if path is not None and (path.exists() or path.is_symlink()):
        raise FileExistsError(17, "File exists (never overwritten)", str(path))


COMMANDS: tuple[Command, ...] = (
    Command("synth", "write a synthetic scenario as a rosbag2 recording", _synth_arguments, run_synth),
    Command("replay", "run simulator + estimator over a recording as the nodes would", _replay_arguments,
            run_replay),
    Command("eval", "the paper's metrics of a replay against the ground truth", _eval_arguments, run_eval),
    Command("render", "PNG pictures of a replay", _render_arguments, run_render),
    Command("demo", "replay, evaluate and render the bundled airway-push recording", _demo_arguments, run_demo),
    Command("ablation", "the paper's Table I: factor configurations on a deforming cube", _ablation_arguments,
            run_ablation),
    Command("accuracy", "factor graph against the simulation alone on nine scenes, default settings",
            _accuracy_arguments, run_accuracy),
    Command("bench", "latency and speed figures against targets and baselines", _bench_arguments, run_bench),
    Command("fuzz", "hostile input against the decoder, the estimator and the replay; recovery from faults",
            _fuzz_arguments, run_fuzz),
    Command("mesh", "inspect a mesh file (info), or write a recording's initial mesh to one (export)",
            _mesh_arguments, run_mesh),
    Command("params", "the ROS 2 parameters file that makes the live nodes run as the replay of a recording",
            _params_arguments, run_params),
    Command("param", "get or set a running node's parameters (`ros2 param get|set` without the ros2 command)",
            _param_arguments, run_param),
)


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog="meshfg", description="Offline tools of meshfg_ros.")
    subparsers = parser.add_subparsers(dest="command", required=True, metavar="COMMAND")
    for command in COMMANDS:
        subparser = subparsers.add_parser(command.name, help=command.help, description=command.help)
        command.add_arguments(subparser)
        subparser.set_defaults(run=command.run)
    return parser


def main(argv: list[str] | None = None) -> int:
    """Entry point of the `meshfg` console script; returns the exit code."""
    argv = sys.argv[1:] if argv is None else list(argv)
    args = build_parser().parse_args(argv)
    args.command_line = "meshfg " + shlex.join(argv)  # what --results says made a section
    try:
        from meshfg_ros import process_settings

        process_settings.configure()  # before any command loads cvxopt (BLAS, huge pages, worker threads)
        return args.run(args)
    except KeyboardInterrupt:
        print(f"meshfg {args.command}: interrupted", file=sys.stderr)
        return 130
    except Exception as error:
        if not is_user_error(error):
            raise
        print(f"meshfg {args.command}: error: {_error_text(error)}", file=sys.stderr)
        return 1


if __name__ == "__main__":
    sys.exit(main())
