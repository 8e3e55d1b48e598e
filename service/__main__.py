"""fednav-service entry point: argument parsing only; the work is in service.app."""

from __future__ import annotations

import argparse
import logging
import signal
import sys
import threading
import time
from pathlib import Path

from fednav.service import config as config_mod
from fednav.service.blas import one_blas_thread

EXAMPLES = """examples:
  fednav-service --config service/configs/example.toml --rrd recordings/run.rrd
  fednav-service --config simulators/scenarios/seed000_faults.toml --config-table service
  fednav-service --vehicle '*' --listen tcp/0.0.0.0:7447          # every vehicle, all interfaces
  fednav-service --connect tcp/router.local:7447 --no-record      # behind a Zenoh router
SIGINT/SIGTERM stop it cleanly (queues drained, .rrd complete). Configuration reference:
service/config.py; docs: README.md, docs/ARCHITECTURE.md, docs/SECURITY.md."""


def version() -> str:
    from importlib.metadata import PackageNotFoundError
    from importlib.metadata import version as dist_version

    try:
        return dist_version("fednav")
    except PackageNotFoundError:
        return "unknown (not installed)"


def parse_args(argv: list[str] | None = None) -> argparse.Namespace:
    ap = argparse.ArgumentParser(
        prog="fednav-service",
        description="fednav navigation fusion service: sensors in over Zenoh; solutions, faults, "
        "integrity and health out over Zenoh and to a Rerun recording",
        epilog=EXAMPLES,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    ap.add_argument("--version", action="version", version=f"fednav-service {version()}")
    ap.add_argument(
        "--config", type=Path, help="service TOML config (default: built-in defaults, vehicle v1)"
    )
    ap.add_argument("--config-table", help="use this table of the TOML file (e.g. a scenario's 'service')")
    ap.add_argument("--rrd", type=Path, help="recording path (default: recordings/fednav-<time>.rrd)")
    ap.add_argument("--no-record", action="store_true", help="do not write a recording")
    ap.add_argument(
        "--viewer", help="also stream live to a Rerun viewer, e.g. rerun+http://127.0.0.1:9876/proxy"
    )
    ap.add_argument(
        "--listen",
        action="append",
        help="Zenoh endpoint to listen on, repeatable (default tcp/127.0.0.1:7447)",
    )
    ap.add_argument(
        "--connect", action="append", help="Zenoh endpoint to connect to, repeatable (e.g. a router)"
    )
    ap.add_argument("--zenoh-config", help="a Zenoh json5 config file (TLS, access control, routers)")
    ap.add_argument(
        "--vehicle", action="append", help="vehicle(s) to serve, '*' for all (default: the config's)"
    )
    ap.add_argument("--log-level", default="INFO", help="DEBUG, INFO, WARNING, ERROR (default INFO)")
    ap.add_argument(
        "--shards",
        type=int,
        default=1,
        help="spread the vehicles over this many processes (rendezvous hashing; each writes its own "
        "recording, run.shardI.rrd): where one process's Python (GIL) is the limit, e.g. one per core",
    )
    ap.add_argument("--shard", help=argparse.SUPPRESS)  # I/K: a shard started by --shards
    ap.add_argument("--shard-group", help=argparse.SUPPRESS)  # its shards' private handover group
    return ap.parse_args(argv)


def zenoh_error_text(exc: BaseException) -> str:
    """A Zenoh error's first line without the Rust source locations it carries."""
    import re

    text = str(exc).strip().splitlines()[0] if str(exc).strip() else type(exc).__name__
    return re.sub(r"\s*at /\S+\.rs:\d+\.?", "", text).strip(" .")


def _usage_error(args: argparse.Namespace) -> str | None:
    """A mistake in the command line, as one line (None if there is none)."""
    from fednav.service.transport.zenoh_io import endpoint_error

    for ep in (args.listen or []) + (args.connect or []):
        err = endpoint_error(ep)
        if err:
            return err
    if args.zenoh_config and not Path(args.zenoh_config).is_file():
        return f"--zenoh-config {args.zenoh_config}: no such file"
    if args.config and not Path(args.config).is_file():
        return f"--config {args.config}: no such file"
    if not 1 <= args.shards <= 64:
        return f"--shards {args.shards}: use 1..64"
    if args.shard:
        from fednav.service.shards import parse_shard

        try:
            parse_shard(args.shard)
        except ValueError as exc:
            return str(exc)
    return None


def main(argv: list[str] | None = None) -> int:
    args = parse_args(argv)
    one_blas_thread()
    logging.basicConfig(level=args.log_level.upper(), format="%(asctime)s %(name)s %(levelname)s %(message)s")
    problem = _usage_error(args)
    if problem:
        print(f"fednav-service: {problem}", file=sys.stderr)
        return 2
    try:
        cfg = config_mod.load(args.config, args.config_table) if args.config else config_mod.ServiceConfig()
        if args.vehicle:
            cfg = cfg.model_copy(update={"vehicles": args.vehicle})
    except config_mod.ConfigError as exc:
        print(f"fednav-service: {exc}", file=sys.stderr)
        return 2
    if cfg.ros2 is not None:
        from fednav.service.transport.ros2 import RosUnavailable, typestore

        try:
            typestore(cfg.ros2.distro)
        except RosUnavailable as exc:
            print(f"fednav-service: [ros2] is configured but {exc}", file=sys.stderr)
            return 2
    from fednav.service.app import Service
    from fednav.service.shards import READY_TEXT, READY_ZID, ShardSupervisor, parse_shard

    listen = args.listen
    if args.connect and not args.listen:
        listen = []
    shard = parse_shard(args.shard) if args.shard else (0, args.shards) if args.shards > 1 else None
    supervisor = None
    if shard is not None and args.shard is None:  # shard 0: the children connect to it
        client = cfg.zenoh.mode == "client"
        supervisor = ShardSupervisor(
            sys.argv[1:] if argv is None else argv,
            args.shards,
            connect=(args.connect or cfg.zenoh.connect) if client else None,
            rrd=None if args.no_record else args.rrd,
        )
        if not client:
            listen = list(listen if listen is not None else cfg.zenoh.listen) + [supervisor.socket_endpoint]
    stop = threading.Event()
    svc = Service(
        cfg,
        rrd=args.rrd,
        viewer=args.viewer,
        listen=listen,
        connect=args.connect,
        zenoh_config_file=args.zenoh_config,
        record=not args.no_record,
        shard=shard,
        feeds=supervisor.feeds if supervisor is not None else None,
        # a shard started by --shards: its inputs come from shard 0 on its standard input, and
        # the end of that pipe (shard 0 stopped or gone) stops it
        feed_fd=sys.stdin.fileno() if args.shard else None,
        on_feed_end=stop.set,
        shard_group=supervisor.group if supervisor is not None else args.shard_group,
    )
    if supervisor is not None:
        supervisor.states_for = svc.shard_states
        svc.shard_members = supervisor.by_zid
    if supervisor is not None and not args.no_record:
        supervisor.rrd = Path(svc.rrd_path)  # each shard's recording beside shard 0's
    signal.signal(signal.SIGINT, lambda *_: stop.set())
    signal.signal(signal.SIGTERM, lambda *_: stop.set())
    try:
        svc.start()
    except Exception as exc:  # the Zenoh session could not open: say why in one line
        import zenoh

        if not isinstance(exc, zenoh.ZError):
            raise
        first = zenoh_error_text(exc)
        print(
            f"fednav-service: cannot open the Zenoh session ({first}); is the port in use by another "
            "service? try another --listen port, or --connect to that service's router",
            file=sys.stderr,
        )
        svc.stop()
        return 2
    from fednav.service.vehicle import tune_gc

    tune_gc()
    if args.shard:
        print(READY_TEXT.format(i=shard[0], k=shard[1]) + READY_ZID.format(zid=svc.session.zid()), flush=True)
    if supervisor is not None and not supervisor.start():
        print("fednav-service: a shard did not start (see its output above)", file=sys.stderr)
        supervisor.stop()
        svc.stop()
        return 2
    if not args.shard:  # a shard said its own ready line above
        print(
            f"fednav-service ready (recording: {svc.rrd_path if not args.no_record else 'off'})", flush=True
        )
    while not stop.wait(0.2):
        pass
    if supervisor is not None:
        supervisor.stop()  # (bounded: each shard has its own watchdog; killed after 60 s)
    shutdown_watchdog(svc)
    svc.stop()
    print("fednav-service stopped", flush=True)
    return 0


#: a stop (all but the recording's close) that takes longer than this is stuck: the stacks of
#: every thread are written to stderr and the process exits with SHUTDOWN_STUCK_EXIT
SHUTDOWN_WATCHDOG_S = 30.0
SHUTDOWN_STUCK_EXIT = 3


def shutdown_watchdog(
    svc, limit_s: float = SHUTDOWN_WATCHDOG_S, backstop_after_s: float = 10.0
) -> threading.Thread:
    """Bound a stop's time: SIGINT/SIGTERM must end the process. The drain of the vehicles' queues
    is bounded (5 s), the recording is closed before the Zenoh session, and a Zenoh call can
    block at shutdown (a callback thread waiting for the GIL while a close waits for it; a router
    going away at the same moment): after ``limit_s`` outside the recording's close (which may
    take long for a large file) the watchdog dumps every thread's stack to stderr, says which
    stage was stuck and exits the process. Behind it, faulthandler's own timer (a C thread: it
    fires even when a deadlock holds the GIL, and during the interpreter's exit) does the same
    ``backstop_after_s`` later (exit code 1), re-armed while the recording is being closed."""
    import faulthandler
    import os

    from fednav.service.app import RECORDING_STAGE

    backstop_s = limit_s + backstop_after_s
    faulthandler.dump_traceback_later(backstop_s, exit=True, file=sys.stderr)

    def watch() -> None:
        spent, last = 0.0, time.monotonic()
        while True:
            time.sleep(0.25)
            now = time.monotonic()
            if svc.stopping != RECORDING_STAGE:
                spent += now - last
            else:
                faulthandler.dump_traceback_later(backstop_s - spent, exit=True, file=sys.stderr)
            last = now
            if spent > limit_s:
                print(
                    f"fednav-service: shutdown stuck for {limit_s:.0f} s in stage {svc.stopping!r}; "
                    "exiting (every thread's stack follows)",
                    file=sys.stderr,
                    flush=True,
                )
                faulthandler.dump_traceback(file=sys.stderr, all_threads=True)
                os._exit(SHUTDOWN_STUCK_EXIT)

    t = threading.Thread(target=watch, name="fednav-shutdown-watchdog", daemon=True)
    t.start()
    return t


if __name__ == "__main__":
    raise SystemExit(main())
