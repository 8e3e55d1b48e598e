"""fednav-sim: ``run`` publishes a scenario over Zenoh; ``eval`` runs it in-process; ``fleet``,
``eval-rinex`` and ``rinex2raw`` (their own modules' parsers)."""

from __future__ import annotations

import argparse
import json
import sys

from fednav.service.blas import one_blas_thread
from fednav.service.imu_batch import batch_size_arg

SCENARIO_HELP = (
    "a scenario file, or the name of a shipped one (simulators/scenarios/<name>.toml), e.g. "
    "demo_aircraft, seed000_faults, seed001_montecarlo"
)
RUN_EXAMPLES = """examples:
  fednav-sim run demo_aircraft --speed 10 --connect tcp/127.0.0.1:7447
  fednav-sim run my_scenario.toml --speed 0 --vehicle alpha --seed 3     # as fast as the service takes it"""
EVAL_EXAMPLES = """examples:
  fednav-sim eval demo_aircraft
  fednav-sim eval seed000_faults --runs 5 --seed 7 --window 400 550 --json
  fednav-sim eval seed001_montecarlo --seed 11"""


DEFAULT_IMU_BATCH = 10  # simulators.publisher.DEFAULT_IMU_BATCH (not imported: zenoh loads lazily)


def _seed_list(text: str) -> list[int]:
    try:
        seeds = [int(x) for x in text.split(",") if x.strip()]
    except ValueError:
        raise argparse.ArgumentTypeError(f"not a comma-separated list of integers: {text!r}") from None
    if len(seeds) < 2 or len(set(seeds)) != len(seeds) or min(seeds) < 0:
        raise argparse.ArgumentTypeError("give at least two different seeds >= 0, e.g. 3,103,203")
    return seeds


def _name_list(text: str) -> list[str]:
    names = [x.strip() for x in text.split(",") if x.strip()]
    if not names:
        raise argparse.ArgumentTypeError("give one or more pipeline names, e.g. tc,tc_imm_sel")
    return names


def parse_args(argv: list[str] | None = None) -> argparse.Namespace:
    from fednav.service.__main__ import version

    raw = argparse.RawDescriptionHelpFormatter
    ap = argparse.ArgumentParser(
        prog="fednav-sim",
        description="fednav sensor simulators: publish a scenario over Zenoh (run), or evaluate the "
        "service's pipelines on it in-process, faster than real time (eval); a fleet of vehicles (fleet); "
        "real RINEX data (eval-rinex, rinex2raw)",
    )
    ap.add_argument("--version", action="version", version=f"fednav-sim {version()}")
    sub = ap.add_subparsers(dest="cmd", required=True)
    r = sub.add_parser("run", help="publish a scenario over Zenoh", epilog=RUN_EXAMPLES, formatter_class=raw)
    r.add_argument("scenario", help=SCENARIO_HELP)
    r.add_argument(
        "--speed", type=float, default=1.0, help="pacing, x real time (default 1); 0 = as fast as possible"
    )
    r.add_argument(
        "--connect", action="append", help="Zenoh endpoint, repeatable (default tcp/127.0.0.1:7447)"
    )
    r.add_argument("--zenoh-config", help="a Zenoh json5 config file (TLS, access control)")
    r.add_argument("--vehicle", default="v1", help="vehicle name in the keys (default v1)")
    r.add_argument("--seed", type=int, help="noise seed (default: the scenario's)")
    r.add_argument("--prefix", default="fednav", help="key prefix (default fednav)")
    r.add_argument(
        "--imu-batch",
        type=batch_size_arg,
        default=DEFAULT_IMU_BATCH,
        metavar="N",
        help=f"IMU samples per binary ImuBatch (default {DEFAULT_IMU_BATCH}); 1 = one JSON ImuSample each",
    )
    e = sub.add_parser(
        "eval",
        help="run a scenario through the service pipelines in-process",
        epilog=EVAL_EXAMPLES,
        formatter_class=raw,
    )
    e.add_argument("scenario", help=SCENARIO_HELP)
    e.add_argument(
        "--runs", type=int, default=1, help="seeded Monte Carlo runs: seeds S, S+1, ... (default 1)"
    )
    e.add_argument("--seed", type=int, help="first seed S (default: the scenario's)")
    e.add_argument(
        "--seeds",
        type=_seed_list,
        help="several seed sets, e.g. 3,103,203: --runs runs from each first seed; prints every figure's "
        "mean over the sets with its min-max spread (and each set's own result with --json)",
    )
    e.add_argument("--json", action="store_true", help="print the result as JSON instead of the table")
    e.add_argument(
        "--pipelines",
        type=_name_list,
        metavar="A,B",
        help="run only these of the scenario's pipelines (its [service] table's names), e.g. tc,tc_imm_sel",
    )
    e.add_argument(
        "--window",
        type=float,
        nargs=2,
        metavar=("T0", "T1"),
        help="also report metrics inside [T0, T1] s from the scenario start",
    )
    # parsed by their own modules (_main dispatches them before this parser): listed for --help
    sub.add_parser("fleet", add_help=False, help="publish N simulated vehicles from one process over Zenoh")
    sub.add_parser(
        "eval-rinex", add_help=False, help="tightly coupled (GNSS-only) vs gnss-lib-py WLS on real RINEX data"
    )
    sub.add_parser(
        "rinex2raw", add_help=False, help="RINEX 2/3 observation + navigation -> GnssRaw JSON lines"
    )
    return ap.parse_args(argv)


def main(argv: list[str] | None = None) -> int:
    from fednav.service.stop_signals import stop_on_sigint

    stop_on_sigint()  # (even when started with SIGINT ignored; SIGUSR1: every thread's stack)
    try:
        return _main(argv)
    except KeyboardInterrupt:  # Ctrl-C (SIGINT): a stop asked for, not a failure to trace back
        print("fednav-sim: interrupted", file=sys.stderr)
        return 130


def _main(argv: list[str] | None = None) -> int:
    rest = sys.argv[1:] if argv is None else argv
    one_blas_thread()
    if rest and rest[0] in ("rinex2raw", "eval-rinex"):  # real RINEX data (docs/real_rinex.md)
        from fednav.simulators.rinex_eval import cli

        return cli(rest)
    if rest and rest[0] == "fleet":  # N vehicles from one process (fleet load and tests)
        from fednav.simulators.fleet import main as fleet_main

        return fleet_main(rest[1:])
    args = parse_args(argv)
    from fednav.simulators.scenario import load_scenario_cli

    scenario = load_scenario_cli(args.scenario, "fednav-sim")
    if scenario is None:
        return 2
    if args.cmd == "run":
        from fednav.simulators.publisher import MatchTimeout, publish_stream, report_end, session_args_problem

        problem = session_args_problem(args.connect, args.zenoh_config)
        if problem:
            print(f"fednav-sim: {problem}", file=sys.stderr)
            return 2
        from fednav.simulators.stream import Simulation
        from fednav.simulators.wing import WingSimulation

        make = WingSimulation if scenario.wing is not None else Simulation  # seed 002: wing nodes too
        sim = make(scenario, seed=args.seed, vehicle=args.vehicle, prefix=args.prefix)
        try:
            stats = publish_stream(
                sim,
                speed=args.speed,
                connect=args.connect,
                zenoh_config=args.zenoh_config,
                imu_batch=args.imu_batch,
            )
        except MatchTimeout as exc:
            print(f"fednav-sim: {exc}", file=sys.stderr)
            return 3
        print(f"fednav-sim: published {stats['messages']} messages in {stats['wall_s']:.1f} s", flush=True)
        return report_end(stats, "fednav-sim", [args.vehicle])
    from fednav.service.config import ConfigError
    from fednav.simulators.evaluate import evaluate, format_table

    if args.runs < 1:
        print("--runs must be >= 1", file=sys.stderr)
        return 2
    if args.seeds and args.seed is not None:
        print("--seed and --seeds: give one of them", file=sys.stderr)
        return 2
    if scenario.wing is not None:  # transfer alignment (seed 002): per-node alignment metrics
        if args.pipelines:
            print("--pipelines: not for transfer-alignment scenarios", file=sys.stderr)
            return 2
        from fednav.simulators import transfer_eval

        if args.seeds:
            sets = [transfer_eval.evaluate(scenario, runs=args.runs, seed=s) for s in args.seeds]
            return _print_seed_sets(sets, args)
        seed = scenario.seed if args.seed is None else args.seed
        result = transfer_eval.evaluate(scenario, runs=args.runs, seed=seed)
        print(json.dumps(result, indent=2) if args.json else transfer_eval.format_table(result))
        return 0
    if args.seeds:
        try:
            sets = [
                evaluate(
                    scenario,
                    runs=args.runs,
                    seed=s,
                    window=tuple(args.window) if args.window else None,
                    pipelines=args.pipelines,
                )
                for s in args.seeds
            ]
        except ConfigError as exc:
            print(exc, file=sys.stderr)
            return 2
        return _print_seed_sets(sets, args)
    from fednav.simulators.progress import EvalProgress

    bar = EvalProgress(scenario, args.runs, enabled=not args.json and sys.stderr.isatty())
    try:
        result = evaluate(
            scenario,
            runs=args.runs,
            seed=args.seed,
            window=tuple(args.window) if args.window else None,
            progress=bar.run_done,
            on_time=bar.at,
            pipelines=args.pipelines,
        )
    except ConfigError as exc:
        print(exc, file=sys.stderr)
        return 2
    finally:
        bar.close()
    print(json.dumps(result, indent=2) if args.json else format_table(result))
    return 0


def _print_seed_sets(sets: list[dict], args) -> int:
    from fednav.simulators.evaluate import across_seed_sets, format_seed_sets

    summary = across_seed_sets(sets)
    if args.json:
        print(json.dumps({"seed_sets": summary, "sets": sets}, indent=2))
    else:
        print(format_seed_sets(summary))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
