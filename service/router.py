"""``fednav-router``: a Zenoh router for a fleet of fednav services, simulators and readers.

One process, no fusion: a Zenoh session opened in ``router`` mode (eclipse-zenoh's own router,
not the ``zenohd`` binary) routes publications, queries and liveliness between its clients and
peers. Services connect to it in client mode (``service/configs/fleet/service.json5``), so do the
simulators and readers; several services can then share one bus and one fleet (docs/fleet.md).

The session config is fednav's (``zenoh_io.make_config``): loopback listen endpoint by default,
multicast scouting and gossip off; ``--zenoh-config FILE`` is overlaid as for the service (TLS,
access control) and ``--listen``/``--connect`` replace the file's endpoints. The router adds no
access control of its own (the outputs guard is the service's): only a file that sets
``access_control`` restricts what the router routes (``service/configs/fleet/secure/router.json5``).

``--readers``: a router for the fleet's readers (dashboards, recorders, other clients), connected
to the fleet's router with ``--connect``: every put it sends to a client goes with congestion
control drop, so a reader that stops reading loses its own samples and holds nobody. A reader
subscribed to ``fednav/**`` on the fleet's router itself holds every vehicle's inputs and
Solutions (the publishers' puts block on its full queue: 5.1 s without any Solution for all ten
vehicles of a run, until Zenoh closed its link); the fleet's router stays lossless for the
services, which the as-fast-as-possible replays need (docs/fleet.md, "Readers on their own
router").

SIGINT/SIGTERM close the session cleanly. Prints ``fednav-router ready`` once it listens; a Zenoh
error at start (bad file, port in use, missing certificate) exits with code 2 and the reason.
"""

from __future__ import annotations

import argparse
import json
import signal
import sys
import threading
from pathlib import Path

DEFAULT_LISTEN = "tcp/127.0.0.1:7447"
READY_TEXT = "fednav-router ready"

EXAMPLES = """examples:
  fednav-router --listen tcp/127.0.0.1:7447
  fednav-router --listen tcp/0.0.0.0:7447                       # every interface (a real fleet)
  fednav-router --zenoh-config service/configs/fleet/secure/router.json5   # mutual TLS + access control
  fednav-router --readers --listen tcp/127.0.0.1:7448 --connect tcp/127.0.0.1:7447  # readers' router
  fednav-service --connect tcp/127.0.0.1:7447 --zenoh-config service/configs/fleet/service.json5
docs/fleet.md: topology, configs per role, fednav-fleet status / record."""


def parse_args(argv: list[str] | None = None) -> argparse.Namespace:
    ap = argparse.ArgumentParser(
        prog="fednav-router",
        description="Zenoh router for a fleet of fednav services, simulators and readers "
        "(loopback and no multicast scouting unless told otherwise)",
        epilog=EXAMPLES,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    ap.add_argument(
        "--listen",
        action="append",
        help=f"Zenoh endpoint to listen on, repeatable (default: the file's, else {DEFAULT_LISTEN})",
    )
    ap.add_argument(
        "--connect", action="append", help="another router to connect to, repeatable (a router mesh)"
    )
    ap.add_argument("--zenoh-config", help="a Zenoh json5 config file (TLS, access control)")
    ap.add_argument(
        "--readers",
        action="store_true",
        help="a router for readers: never waits for a client that reads slowly (its puts to clients "
        "are dropped when that client's queue is full); connect it to the fleet's router with --connect",
    )
    return ap.parse_args(argv)


def _usage_error(args: argparse.Namespace) -> str | None:
    from fednav.service.transport.zenoh_io import endpoint_error

    for ep in (args.listen or []) + (args.connect or []):
        err = endpoint_error(ep)
        if err:
            return err
    if args.zenoh_config and not Path(args.zenoh_config).is_file():
        return f"--zenoh-config {args.zenoh_config}: no such file"
    return None


def router_config(
    listen: list[str] | None = None,
    connect: list[str] | None = None,
    config_file: str | None = None,
    readers: bool = False,
):
    """The router's Zenoh config: fednav's safe defaults in router mode, ``config_file`` overlaid,
    explicit endpoints. No outputs guard (``outputs_prefix`` is not given). ``readers``: the QoS
    overwrite that sends every put to a client with congestion control drop
    (``zenoh_io.egress_drop_rules``), after the file's own rules. Raises ValueError when the file
    asks for another mode."""
    from fednav.service.config import ZenohConfig
    from fednav.service.transport.zenoh_io import egress_drop_rules, make_config

    conf = make_config(
        ZenohConfig(mode="router", listen=[DEFAULT_LISTEN], connect=[]),
        listen=listen,
        connect=connect,
        config_file=config_file,
    )
    mode = json.loads(conf.get_json("mode"))
    if mode != "router":
        raise ValueError(f"the config file sets mode {mode!r}; fednav-router runs a router")
    if readers:
        rules = json.loads(conf.get_json("qos/network")) or []
        conf.insert_json5("qos/network", json.dumps(rules + egress_drop_rules()))
    return conf


def main(argv: list[str] | None = None) -> int:
    args = parse_args(argv)
    problem = _usage_error(args)
    if problem:
        print(f"fednav-router: {problem}", file=sys.stderr)
        return 2
    import zenoh

    from fednav.service.__main__ import zenoh_error_text

    try:
        conf = router_config(args.listen, args.connect, args.zenoh_config, readers=args.readers)
    except ValueError as exc:
        print(f"fednav-router: {exc}", file=sys.stderr)
        return 2
    except zenoh.ZError as exc:
        print(f"fednav-router: bad Zenoh config ({zenoh_error_text(exc)})", file=sys.stderr)
        return 2
    stop = threading.Event()
    signal.signal(signal.SIGINT, lambda *_: stop.set())
    signal.signal(signal.SIGTERM, lambda *_: stop.set())
    try:
        session = zenoh.open(conf)
    except zenoh.ZError as exc:
        print(
            f"fednav-router: cannot open the Zenoh router ({zenoh_error_text(exc)}); "
            "is the port in use? try another --listen port",
            file=sys.stderr,
        )
        return 2
    listen = json.loads(conf.get_json("listen/endpoints"))
    if isinstance(listen, dict):  # a mode-dependent value: {router: [...], peer: [...], ...}
        listen = listen.get("router", [])
    acl = json.loads(conf.get_json("access_control")).get("enabled", False)
    print(
        f"{READY_TEXT}: zid {session.zid()} listening on {', '.join(map(str, listen)) or 'nothing'}"
        f"{' (access control on)' if acl else ''}"
        f"{' (readers: never waits for a slow client)' if args.readers else ''}",
        flush=True,
    )
    try:
        while not stop.wait(0.2):
            pass
    finally:
        session.close()
    print("fednav-router stopped", flush=True)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
