"""``fednav-replay MAPPING.toml``: publish recorded logs over Zenoh as live sensors.

The mapping file (replay/mapping.py, example in replay/examples/) names the streams. The tool
reads every stream once and checks it (replay/checks.py), then publishes all streams merged in
time order, with the keys, JSON wire messages and publisher settings of ``fednav-sim run``
(simulators/publisher.py: reliable, blocking congestion control, waits for the service to
match). ``--speed 0`` (default) publishes as fast as the service takes it; ``--speed 1`` at
recorded pace. A progress bar is drawn on a terminal (not with ``--json`` or when stderr is not
a terminal). The service's endpoint: ``--connect``, else the mapping's ``endpoint``, else the
publisher's default (tcp/127.0.0.1:7447).

``--suggest-config [OUT.toml]`` (replay/suggest.py) estimates the IMU's noise and bias level and the
fixes' error from the log and writes a service configuration (to stdout without OUT), with where
each number came from; it publishes nothing.

Exit codes: 0 done, 1 usage/mapping error, 2 checks failed, 3 no service matched, 4 the subscribers
went away during the stream, 5 no fednav service serves the vehicle (the messages reached other
subscribers only).
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from collections.abc import Iterable, Iterator
from pathlib import Path

from fednav.service.blas import one_blas_thread
from fednav.service.imu_batch import batch_size_arg
from fednav.service.messages import WireModel

from .checks import Report, run_checks
from .mapping import MappingError, load_mapping
from .sources import SourceError, all_events


class Progress:
    """A one-line progress bar on stderr (count, percent, sensor time, messages/s)."""

    def __init__(self, total: int, enabled: bool, stream=None):
        self.total, self.enabled = max(total, 1), enabled
        self.out = stream or sys.stderr
        self.n = 0
        self.t0 = time.monotonic()
        self._last = 0.0
        self._t_first: float | None = None

    def step(self, t: float) -> None:
        self.n += 1
        if self._t_first is None:
            self._t_first = t
        now = time.monotonic()
        if self.enabled and (now - self._last > 0.1 or self.n == self.total):
            self._last = now
            frac = min(self.n / self.total, 1.0)
            bar = "#" * int(30 * frac) + "." * (30 - int(30 * frac))
            rate = self.n / max(now - self.t0, 1e-9)
            self.out.write(
                f"\r[{bar}] {100 * frac:5.1f}% {self.n}/{self.total} msgs  "
                f"+{t - self._t_first:7.1f} s log  {rate:8.0f} msg/s"
            )
            self.out.flush()

    def close(self) -> None:
        if self.enabled:
            self.out.write("\n")
            self.out.flush()


def keyed(
    events: Iterable, prefix: str, vehicle: str, progress: Progress | None = None
) -> Iterator[tuple[str, WireModel]]:
    """Events -> (full key, message) for simulators.publisher.publish_stream."""
    for ev in events:
        if progress is not None:
            progress.step(ev.t_gps_s)
        yield f"{prefix}/{vehicle}/{ev.key_suffix}", ev.msg


def parse_args(argv: list[str] | None) -> argparse.Namespace:
    from fednav.simulators.publisher import timeout_arg

    ap = argparse.ArgumentParser(
        prog="fednav-replay", description="Publish recorded sensor logs over Zenoh as live fednav sensors."
    )
    ap.add_argument("mapping", type=Path, help="mapping file (TOML), see replay/examples/")
    ap.add_argument(
        "--check", action="store_true", help="only check the logs and the mapping; publish nothing"
    )
    ap.add_argument("--speed", type=float, default=0.0, help="0: as fast as possible (default); 1: real time")
    ap.add_argument(
        "--connect",
        action="append",
        default=None,
        help="Zenoh endpoint of the service (default: the mapping's 'endpoint', else tcp/127.0.0.1:7447)",
    )
    ap.add_argument("--listen", action="append", default=None, help="Zenoh endpoint to listen on")
    ap.add_argument("--zenoh-config", default=None, help="Zenoh config file (TLS, access control)")
    ap.add_argument("--vehicle", default=None, help="override the mapping's vehicle name")
    ap.add_argument("--match-timeout", type=timeout_arg, default=30.0, help="seconds to wait for the service")
    ap.add_argument("--force", action="store_true", help="publish even when a check fails")
    ap.add_argument(
        "--imu-batch",
        type=batch_size_arg,
        default=10,
        metavar="N",
        help="IMU samples per binary ImuBatch (default 10); 1 = one JSON ImuSample each",
    )
    ap.add_argument("--json", action="store_true", help="print one JSON summary on stdout, no progress bar")
    ap.add_argument(
        "--suggest-config",
        nargs="?",
        const="-",
        default=None,
        metavar="OUT.toml",
        help="estimate the IMU grade, fix sigmas and correlated error from the log and write a service "
        "configuration (stdout without OUT.toml); publishes nothing",
    )
    return ap.parse_args(argv)


def main(argv: list[str] | None = None) -> int:
    from fednav.service.stop_signals import stop_on_sigint

    stop_on_sigint()  # (even when started with SIGINT ignored; SIGUSR1: every thread's stack)
    try:
        return _main(argv)
    except KeyboardInterrupt:  # Ctrl-C (SIGINT): a stop asked for, not a failure to trace back
        print("fednav-replay: interrupted", file=sys.stderr)
        return 130


def _main(argv: list[str] | None = None) -> int:
    args = parse_args(argv)
    one_blas_thread()
    if args.zenoh_config and not Path(args.zenoh_config).is_file():
        print(f"fednav-replay: --zenoh-config {args.zenoh_config}: no such file", file=sys.stderr)
        return 1
    if args.speed < 0:
        print("fednav-replay: --speed must be >= 0", file=sys.stderr)
        return 1
    try:
        mapping, base = load_mapping(args.mapping)
    except MappingError as exc:
        print(exc, file=sys.stderr)
        return 1
    vehicle = args.vehicle or mapping.vehicle
    report: Report = run_checks(mapping, base)
    mapping = report.mapping  # boot_offset_s = "auto" resolved
    summary: dict = {"vehicle": vehicle, "check": report.as_dict()}
    out = sys.stderr if args.suggest_config == "-" and not args.json else sys.stdout
    # --force publishes despite the errors, but not a stream whose boot offset was not derived: its
    # stamps convert to no time
    underived = [s.sensor_id for s in mapping.streams if s.boot_offset_s == "auto"]
    forced = bool(report.errors) and args.force and not args.check and args.suggest_config is None
    if not args.json:
        print(f"fednav-replay {args.mapping} -> {mapping.prefix}/{vehicle}/...", file=out)
        print(report.text(forced=forced and not underived), file=out)
    if args.suggest_config is not None:
        return _suggest(args, mapping, base, report, summary)
    if forced and underived:
        print(
            "fednav-replay: --force cannot publish: boot_offset_s = 'auto' of stream(s) "
            f"{', '.join(map(repr, underived))} was not derived: write boot_offset_s in the mapping",
            file=sys.stderr,
        )
    if args.check or (report.errors and not args.force) or (forced and underived):
        if args.json:
            print(json.dumps(summary))
        return 2 if report.errors else 0
    import zenoh

    from fednav.simulators.publisher import MatchTimeout, publish_stream, report_end

    progress = Progress(report.total, enabled=not args.json and sys.stderr.isatty())
    try:
        result = publish_stream(
            keyed(all_events(mapping, base), mapping.prefix, vehicle, progress),
            speed=args.speed,
            connect=args.connect or ([mapping.endpoint] if mapping.endpoint else None),
            listen=args.listen,
            zenoh_config=args.zenoh_config,
            match_timeout_s=args.match_timeout,
            imu_batch=args.imu_batch,
        )
    except MatchTimeout as exc:
        progress.close()
        print(
            f"fednav-replay: {exc}: is fednav-service running and serving vehicle {vehicle!r}?",
            file=sys.stderr,
        )
        return 3
    except SourceError as exc:
        progress.close()
        print(f"fednav-replay: {exc}", file=sys.stderr)
        return 1
    except zenoh.ZError as exc:
        progress.close()
        where = ", ".join(args.connect or [mapping.endpoint or "tcp/127.0.0.1:7447"])
        print(
            f"fednav-replay: cannot reach a Zenoh peer at {where} ({exc}): is fednav-service running?",
            file=sys.stderr,
        )
        return 3
    progress.close()
    rate = result["messages"] / max(result["wall_s"], 1e-9)
    summary["published"] = {**result, "messages_per_s": rate}
    if args.json:
        print(json.dumps(summary))
    else:
        print(f"published {result['messages']} messages in {result['wall_s']:.2f} s ({rate:.0f} msg/s)")
    return report_end(result, "fednav-replay", [vehicle])


def _suggest(args, mapping, base: Path, report: Report, summary: dict) -> int:
    """``--suggest-config``: refused while a check fails (unless --force: the estimate would be
    made from wrongly mapped data)."""
    from .suggest import SuggestError, suggest_config

    if report.errors and not args.force:
        print(
            "fednav-replay: --suggest-config needs a mapping that passes the checks: fix the errors above "
            "(or --force)",
            file=sys.stderr,
        )
        if args.json:
            print(json.dumps(summary))
        return 2
    try:
        sug = suggest_config(mapping, base, report)
    except SuggestError as exc:
        print(f"fednav-replay: --suggest-config: {exc}", file=sys.stderr)
        return 1
    summary["suggestion"] = sug.as_dict()
    if args.suggest_config == "-":
        if args.json:
            print(json.dumps(summary))
        else:
            print(sug.toml)
        return 0
    Path(args.suggest_config).write_text(sug.toml)
    if args.json:
        print(json.dumps(summary))
    else:
        print(sug.summary_text())
        print(f"wrote {args.suggest_config}: start the service with --config {args.suggest_config}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
