"""The csam command: parses its arguments, runs the pipelines of csam_ros.run and prints what
they gave (docs/ARCHITECTURE.md)."""

from __future__ import annotations

import argparse
import sys
from contextlib import nullcontext
from dataclasses import replace
from functools import partial
from pathlib import Path
from typing import TYPE_CHECKING

from csam_ros.run.command_errors import input_errors, one_line
from csam_ros.run.live import LiveRunError

if TYPE_CHECKING:
    from csam_ros.core.joining.result import RunSummary
    from csam_ros.figures.worker import FigureWorker

DESCRIPTION = "C-SAM multi-robot SLAM on ROS 2: live and offline runs, data sets, evaluation."
EPILOG = "csam COMMAND --help describes a command's options; docs/ARCHITECTURE.md the design."


def _print_lines(lines: list[str], indent: str = "") -> None:
    for line in lines:
        print(f"{indent}{line}")


def _finish(out: Path, summary: RunSummary, worker: FigureWorker | None = None) -> None:
    """Write the run's summary.json and figures into ``out``; say what the run gave."""
    from csam_ros.core.joining.notes import NoteKind
    from csam_ros.run.results import write_results

    figures = write_results(out, summary, worker)
    result = summary.result
    print(f"result in {out}/")
    for name, r in result.robots.items():
        print(f"  {name}: {r.alignment}, {len(r.stamps)} poses")
    for note in result.notes:
        if note.kind is NoteKind.NO_LOCAL_MAP or note.not_converged:
            print(f"  {note}")
    print(f"  {len(result.features)} features, {len(result.associations)} associations")
    print("  summary.json, " + ", ".join(p.name for p in figures))


def cmd_demo(args: argparse.Namespace) -> int:
    from csam_ros.datasets.scenario import load_scenario
    from csam_ros.run.demo import demo_links, demo_live_run, run_demo
    from csam_ros.run.results import figures_drawn_aside, fresh_dir, latency_lines

    links = demo_links(args.hosts, args.loss, args.link_rate, args.base_link_rate, args.cut)
    scenario = load_scenario(args.scenario)
    out = fresh_dir(args.out, scenario.name)
    seed = scenario.seed if args.seed is None else args.seed
    print(
        f"csam demo: scenario {scenario.name} ({len(scenario.robots)} robots), seed {seed}, "
        f"rate {args.rate}, output {out}/"
    )
    run = demo_live_run(args.scenario, out, seed, args.rate, args.isolated)
    # the figures' worker imports matplotlib while the run goes on, and draws once it has ended
    with figures_drawn_aside() as worker:
        summary = run_demo(run, links, args.foxglove)
        _finish(out, replace(summary, scenario=scenario.name), worker)
    _print_lines(latency_lines(out / "bag", summary), "  ")
    return 0


def cmd_simulate(args: argparse.Namespace) -> int:
    """Write a scenario's sensor topics straight to a bag: no DDS, no nodes."""
    from csam_ros.run.simulate import simulate_to_bag

    _print_lines(simulate_to_bag(args.scenario, args.out, args.seed))
    return 0


def cmd_replay(args: argparse.Namespace) -> int:
    from csam_ros.run.live import run_live
    from csam_ros.run.offline import offline_summary, reading_ahead
    from csam_ros.run.params import load_config_document, merger_params, smoother_params
    from csam_ros.run.replay import check_replay, replay_live_run
    from csam_ros.run.results import figures_drawn_aside, fresh_dir, latency_lines

    bag = args.bag
    check_replay(bag, args.offline, args.save_state, args.resume)
    document = load_config_document(args.config)
    # offline, the bag is read on the other core while the core's modules are imported here,
    # then the figures' worker imports matplotlib there while the core (or the nodes) compute
    ahead = reading_ahead(bag, document, args.resume) if args.offline else nullcontext()
    with ahead as reading:
        merger, smoother = merger_params(document), smoother_params(document)
        out = fresh_dir(args.out, f"replay-{bag.name}")
        with figures_drawn_aside() as worker:
            if args.offline:
                summary, _ = offline_summary(bag, document, args.resume, args.save_state, reading)
            else:
                run = replay_live_run(bag, out, args.rate, merger, smoother, args.isolated)
                summary = run_live(run)
            scenario = summary.scenario or bag.resolve().name
            _finish(out, replace(summary, source=str(bag), scenario=scenario), worker)
    if not args.offline:
        _print_lines(latency_lines(out / "bag", summary), "  ")
    return 0


def cmd_evaluate(args: argparse.Namespace) -> int:
    from csam_ros.run.evaluation import draw_over_truth, evaluate_run, evaluation_lines

    evaluation = evaluate_run(args.dir)
    _print_lines(evaluation_lines(evaluation))
    figure = draw_over_truth(evaluation)
    if figure is not None:
        print(f"  {figure}: the joined map over the true features (grey crosses)")
    return 0


def cmd_bag_recover(args: argparse.Namespace) -> int:
    """Write every message of a cut or damaged bag that still verifies into a new bag."""
    from csam_ros.bag import recover_bag

    _print_lines(recover_bag(args.bag, args.out).lines())
    return 0


def cmd_bandwidth(args: argparse.Namespace) -> int:
    """Print what each robot's topics carried, and how it grew over the run."""
    from csam_ros.run.bandwidth import bandwidth_lines, measure_bandwidth
    from csam_ros.run.errors import warn

    _print_lines(bandwidth_lines(measure_bandwidth(args.bag, on_damage=warn)))
    return 0


def cmd_import(a: argparse.Namespace) -> int:
    from csam_ros.run.importing import import_dataset

    count, robots = import_dataset(
        a.format, a.source, a.out, a.robots, a.start, a.duration, a.config, a.occlude, a.stress
    )
    print(f"wrote {count} messages of {robots} robot(s) to {a.out}")
    return 0


def cmd_calibrate(a: argparse.Namespace) -> int:
    """Estimate a data set's noise model and range scales; write them as a config file."""
    from csam_ros.run.calibration import calibrate_dataset

    flushed = partial(print, flush=True)  # each round as it ends
    options = (a.config, a.no_swaps, a.robots, a.start, a.duration, a.rounds, flushed)
    _print_lines(calibrate_dataset(a.source, a.out, *options))
    return 0


ISOLATED_HELP = (
    "run the nodes on a private ROS domain, discovery on this host only (default: the "
    "caller's ROS_DOMAIN_ID and discovery range, where RViz, Foxglove or ros2 topic echo see "
    "the run)"
)
SCENARIO_HELP = "map_joining, sensor_extension, chain, or a scenario YAML file"
SEED_HELP = "noise seed (default: the scenario's)"
OUT_HELP = "output directory, new or empty (default: runs/<name>-<time>)"
VIEW_HELP = "serve the run to Foxglove at ws://127.0.0.1:PORT (default 8765; 0: any free port)"


def parser() -> argparse.ArgumentParser:
    """The csam command's arguments: each subcommand and option with what it does."""
    p = argparse.ArgumentParser(prog="csam", description=DESCRIPTION, epilog=EPILOG)
    sub = p.add_subparsers(dest="command", required=True, metavar="COMMAND", help="one of:")

    demo = sub.add_parser("demo", help="simulate, smooth, merge and record a scenario")
    demo.add_argument("--scenario", default="map_joining", help=SCENARIO_HELP)
    demo.add_argument("--out", type=Path, help=OUT_HELP)
    demo.add_argument("--seed", type=int, help=SEED_HELP)
    demo.add_argument(
        "--rate",
        type=float,
        default=8.0,
        help="simulation speed relative to real time (0: as fast as possible)",
    )
    demo.add_argument("--isolated", action="store_true", help=ISOLATED_HELP)
    demo.add_argument("--foxglove", nargs="?", const=8765, type=int, metavar="PORT", help=VIEW_HELP)
    demo.add_argument(
        "--hosts",
        action="store_true",
        help="each robot (its simulator and smoother) and the base station (merger, recorder) "
        "on a host of its own: network namespaces joined by a bridge (needs root)",
    )
    demo.add_argument(
        "--loss",
        type=float,
        default=0.0,
        help="with --hosts: probability that a host's link drops a packet (e.g. 0.1)",
    )
    demo.add_argument(
        "--link-rate",
        type=float,
        default=0.0,
        metavar="KBIT_S",
        help="with --hosts: each host's link carries at most this many kbit/s each way",
    )
    demo.add_argument(
        "--base-link-rate",
        type=float,
        default=0.0,
        metavar="KBIT_S",
        help="with --hosts: the base station's link (the one every robot's data shares) "
        "carries at most this many kbit/s each way, whatever --link-rate gives the others",
    )
    demo.add_argument(
        "--cut",
        metavar="ROBOT:START-END",
        help="with --hosts: cut that robot's link from START to END wall-clock seconds after "
        "its data starts (the robot goes on alone and comes back)",
    )
    demo.set_defaults(func=cmd_demo)

    sim = sub.add_parser(
        "simulate", help="write a scenario's sensor topics straight to a bag (no DDS, no nodes)"
    )
    sim.add_argument("--scenario", default="map_joining", help=SCENARIO_HELP)
    sim.add_argument("--out", type=Path, required=True, help="bag directory to write (new)")
    sim.add_argument("--seed", type=int, help=SEED_HELP)
    sim.set_defaults(func=cmd_simulate)

    replay = sub.add_parser("replay", help="run a recorded bag's sensor topics through C-SAM")
    replay.add_argument("bag", type=Path, help="bag directory or .mcap file to replay")
    replay.add_argument("--out", type=Path, help=OUT_HELP.replace("<name>", "replay-<bag>"))
    replay.add_argument("--rate", type=float, default=1.0, help="playback speed (0: max)")
    replay.add_argument(
        "--offline", action="store_true", help="feed the bag to the core in stamp order, no DDS"
    )
    replay.add_argument(
        "--config",
        type=Path,
        help="YAML with csam:, local_map:, merger: and input: sections (e.g. config/mrclam.yaml)",
    )
    replay.add_argument("--isolated", action="store_true", help=ISOLATED_HELP)
    replay.add_argument(
        "--save-state",
        type=Path,
        help="with --offline: write the replay's state (accepted data, result) to this .npz",
    )
    replay.add_argument(
        "--resume",
        type=Path,
        help="with --offline: continue from a state saved by --save-state (this bag's data "
        "follows its data)",
    )
    replay.set_defaults(func=cmd_replay)

    imp = sub.add_parser("import", help="convert a data set into a bag of sensor topics")
    imp.add_argument("format", choices=["mrclam", "slam2d"], help="the source's format")
    imp.add_argument("source", type=Path, help="MR.CLAM data set directory or 2D SLAM file")
    imp.add_argument("--out", type=Path, required=True, help="bag directory to write (new)")
    imp.add_argument("--robots", help="MR.CLAM robots, e.g. 1,2,3")
    imp.add_argument("--start", type=float, default=0.0, help="MR.CLAM: seconds after start")
    imp.add_argument("--duration", type=float, help="MR.CLAM: seconds to import")
    imp.add_argument(
        "--config",
        type=Path,
        help="MR.CLAM: config with the noise model, range scales and truth swaps "
        "(default: the installed mrclam.yaml; see csam calibrate)",
    )
    imp.add_argument(
        "--occlude",
        metavar="ROBOT:START-END[,...]|stress",
        help="MR.CLAM: drop a robot's landmark observations (not those of other robots) over "
        "windows of seconds after the data set's first stamp; 'stress': the robot that sees "
        "landmarks least often, every other 90 s window from 90 s after its start (half its "
        "run)",
    )
    imp.add_argument("--odometry-stress", dest="stress", help="MR.CLAM: e.g. turn_driving=1.5")
    imp.set_defaults(func=cmd_import)

    ev = sub.add_parser("evaluate", help="compare a run with its ground truth: metrics.json")
    ev.add_argument("dir", type=Path, help="run directory (its summary.json and bag)")
    ev.set_defaults(func=cmd_evaluate)

    cal = sub.add_parser(
        "calibrate", help="estimate a data set's noise model and range scales: a config file"
    )
    cal.add_argument("format", choices=["mrclam"], help="the source's format")
    cal.add_argument("source", type=Path, help="MR.CLAM data set directory")
    cal.add_argument("--out", type=Path, required=True, help="config file to write (new)")
    cal.add_argument(
        "--config",
        type=Path,
        help="config whose window, truth swaps and other sections the new file keeps "
        "(default: the installed mrclam.yaml)",
    )
    cal.add_argument("--no-swaps", action="store_true", help="ignore the config's truth swaps")
    cal.add_argument("--robots", help="robots to calibrate on, e.g. 1,2,3 (default: all)")
    cal.add_argument("--start", type=float, default=0.0, help="seconds after the data start")
    cal.add_argument("--duration", type=float, help="seconds of data to calibrate on")
    cal.add_argument("--rounds", type=int, default=12, help="most expectation-maximisation rounds")
    cal.set_defaults(func=cmd_calibrate)

    bandwidth = sub.add_parser(
        "bandwidth",
        help="bytes per robot, topic and second of a bag, and by tenth of the run what each "
        "robot sent to the base station",
    )
    bandwidth.add_argument("bag", type=Path, help="bag directory or .mcap file")
    bandwidth.set_defaults(func=cmd_bandwidth)

    bag = sub.add_parser("bag", help="bag tools: recover a killed or damaged recording")
    bag_tools = bag.add_subparsers(
        dest="bag_command", required=True, metavar="TOOL", help="one of:"
    )
    recover = bag_tools.add_parser(
        "recover",
        help="rewrite a bag cut short (recording killed) or with damaged chunks into a "
        "complete one that every reader opens; the bag itself is left as it is",
    )
    recover.add_argument("bag", type=Path, help="bag directory or .mcap file")
    recover.add_argument("--out", type=Path, help="the new bag directory (default: BAG-recovered)")
    recover.set_defaults(func=cmd_bag_recover)
    return p


def main(argv: list[str] | None = None) -> int:
    args = parser().parse_args(argv)
    try:
        return args.func(args)
    except input_errors() as err:  # the last resort: readers raise their own named errors
        print(f"csam {args.command}: {one_line(err)}", file=sys.stderr)
        return 2
    except LiveRunError as err:
        print(f"csam {args.command}: the run failed: {err}", file=sys.stderr)
        return 1
    except KeyboardInterrupt:
        return 130
    except Exception as err:  # the nodes' shutdown on SIGTERM surfaces here
        if type(err).__name__ == "ExternalShutdownException":
            return 143
        raise


if __name__ == "__main__":
    sys.exit(main())
