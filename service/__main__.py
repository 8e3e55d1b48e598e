"""fednav-service entry point: argument parsing only; the work is in service.app."""

from __future__ import annotations

import argparse
import logging
import signal
import sys
import threading
from pathlib import Path

from service import config as config_mod


def parse_args(argv: list[str] | None = None) -> argparse.Namespace:
    ap = argparse.ArgumentParser(prog="fednav-service", description="fednav navigation fusion service")
    ap.add_argument("--config", type=Path, help="service TOML config")
    ap.add_argument("--config-table", help="use this table of the TOML file (e.g. a scenario's 'service')")
    ap.add_argument("--rrd", type=Path, help="recording path (.rrd)")
    ap.add_argument("--no-record", action="store_true", help="do not write a recording")
    ap.add_argument("--viewer", help="also stream live to a Rerun viewer (gRPC URL)")
    ap.add_argument("--listen", action="append", help="Zenoh endpoint to listen on (repeatable)")
    ap.add_argument("--connect", action="append", help="Zenoh endpoint to connect to (repeatable)")
    ap.add_argument("--zenoh-config", help="a full Zenoh json5 config file")
    ap.add_argument("--vehicle", action="append", help="vehicle(s) to serve (overrides config)")
    ap.add_argument("--log-level", default="INFO")
    return ap.parse_args(argv)


def main(argv: list[str] | None = None) -> int:
    args = parse_args(argv)
    logging.basicConfig(level=args.log_level.upper(), format="%(asctime)s %(name)s %(levelname)s %(message)s")
    try:
        cfg = config_mod.load(args.config, args.config_table) if args.config else config_mod.ServiceConfig()
        if args.vehicle:
            cfg = cfg.model_copy(update={"vehicles": args.vehicle})
    except config_mod.ConfigError as exc:
        print(exc, file=sys.stderr)
        return 2
    from service.app import Service

    listen = args.listen
    if args.connect and not args.listen:
        listen = []
    svc = Service(
        cfg,
        rrd=args.rrd,
        viewer=args.viewer,
        listen=listen,
        connect=args.connect,
        zenoh_config_file=args.zenoh_config,
        record=not args.no_record,
    )
    stop = threading.Event()
    signal.signal(signal.SIGINT, lambda *_: stop.set())
    signal.signal(signal.SIGTERM, lambda *_: stop.set())
    import zenoh

    try:
        svc.start()
    except zenoh.ZError as exc:  # bad Zenoh config file, certificate or endpoint, port in use
        print(f"fednav-service: Zenoh session not opened: {exc}", file=sys.stderr)
        return 2
    print(f"fednav-service ready (recording: {svc.rrd_path if not args.no_record else 'off'})", flush=True)
    while not stop.wait(0.2):
        pass
    svc.stop()
    print("fednav-service stopped", flush=True)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
