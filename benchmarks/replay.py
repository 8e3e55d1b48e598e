"""fednav-replay throughput and the service's real-time factor on a replayed log.

One simulated drive (tests/replay_files.py: at rest, then accelerating and turning; IMU 100 Hz,
GNSS 5 Hz) written in every input format, then per format:
- parse: events/s of the parser alone (read, convert, build wire messages; no Zenoh);
- to nothing: ``fednav-replay`` as a process publishing to a bare Zenoh peer whose subscriber
  only counts (the transport's and the publisher's cost);
- to the service: ``fednav-replay`` publishing to a running fednav-service (one loosely coupled
  pipeline, static alignment) as fast as it takes them; the service's real-time factor is the
  log's duration over the wall time from the replay's start until the service is idle.

Usage: .venv/bin/python benchmarks/replay.py [--duration 300] [--json]
"""

from __future__ import annotations

import argparse
import json
import os
import shutil
import signal
import sys
import tempfile
import threading
import time
from pathlib import Path

os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")
sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from fednav.replay.mapping import load_mapping  # noqa: E402
from fednav.replay.sources import all_events  # noqa: E402
from fednav.simulators.processes import Proc, free_port, start_service, wait_idle  # noqa: E402
from tests import replay_files as rf  # noqa: E402

CASES = ("ros2", "ros1", "mcap", "nmea_csv", "ubx")


def replay_proc(mapping: Path, port: int) -> tuple[int, dict]:
    p = Proc(
        [sys.executable, "-m", "fednav.replay", str(mapping), "--connect", f"tcp/127.0.0.1:{port}", "--json"],
        "fednav-replay",
    )
    rc = p.wait(timeout=600)
    lines = p.output().strip().splitlines()
    return rc, json.loads(lines[-1]) if rc == 0 else {"error": p.output()}


def parse_rate(mapping: Path) -> tuple[int, float]:
    m, base = load_mapping(mapping)
    t = time.perf_counter()
    n = sum(1 for _ in all_events(m, base))
    return n, n / (time.perf_counter() - t)


def to_nothing(mapping: Path) -> float:
    """Messages/s published by fednav-replay to a bare peer that only counts them."""
    import zenoh

    port = free_port()
    c = zenoh.Config()
    c.insert_json5("mode", '"peer"')
    c.insert_json5("scouting/multicast/enabled", "false")
    c.insert_json5("listen/endpoints", json.dumps([f"tcp/127.0.0.1:{port}"]))
    count = [0]
    lock = threading.Lock()

    def cb(_s) -> None:
        with lock:
            count[0] += 1

    with zenoh.open(c) as s:
        sub = s.declare_subscriber("fednav/**", cb)
        rc, out = replay_proc(mapping, port)
        time.sleep(0.5)
        sub.undeclare()
    assert rc == 0, out
    assert count[0] == out["published"]["messages"], (count[0], out["published"])
    return out["published"]["messages_per_s"]


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser()
    ap.add_argument("--duration", type=float, default=300.0, help="log length, s")
    ap.add_argument("--json", action="store_true")
    args = ap.parse_args(argv)
    tmp = Path(tempfile.mkdtemp(prefix="fednav_replay_bench_"))
    drive = rf.simulate_drive(tmp, duration_s=args.duration)
    mappings = rf.write_all(tmp / "logs", drive)
    log_s = drive.imu[-1].t - drive.imu[0].t
    results: dict[str, dict] = {}
    for case in CASES:
        n, rate = parse_rate(mappings[case])
        results[case] = {"messages": n, "parse_msgs_per_s": round(rate), "to_nothing_msgs_per_s": None}
        results[case]["to_nothing_msgs_per_s"] = round(to_nothing(mappings[case]))
    port = free_port()
    svc = start_service(port, config=rf.service_config(tmp, align_s=8.0))
    try:
        for case in CASES:
            t = time.monotonic()
            rc, out = replay_proc(mappings[case], port)
            assert rc == 0, out
            st = wait_idle(port, vehicle=case, timeout_s=600)
            wall = time.monotonic() - t
            assert st is not None
            results[case]["to_service_msgs_per_s"] = round(out["published"]["messages_per_s"])
            results[case]["service_realtime_factor"] = round(log_s / wall, 1)
    finally:
        svc.signal(signal.SIGTERM)
        svc.wait(timeout=60)
        shutil.rmtree(tmp, ignore_errors=True)
    doc = {"log_s": round(log_s, 1), "imu_hz": 100, "gnss_hz": 5, "cases": results}
    if args.json:
        print(json.dumps(doc, indent=2))
        return 0
    print(f"replayed log: {log_s:.0f} s, IMU 100 Hz + GNSS 5 Hz, one loosely coupled pipeline")
    print(
        f"{'format':10s} {'messages':>9s} {'parse msg/s':>12s} {'to nothing':>11s} "
        f"{'to service':>11s} {'service RTF':>12s}"
    )
    for case, r in results.items():
        print(
            f"{case:10s} {r['messages']:9d} {r['parse_msgs_per_s']:12d} {r['to_nothing_msgs_per_s']:11d} "
            f"{r['to_service_msgs_per_s']:11d} {r['service_realtime_factor']:11.1f}x"
        )
    print("(service RTF: log duration / wall time from the replay's start until the service is idle,")
    print(" process start-up and the idle poll of 0.3 s included)")
    return 0


if __name__ == "__main__":
    sys.exit(main())
