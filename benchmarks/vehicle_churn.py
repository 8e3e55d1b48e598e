"""A fleet whose names come and go: does a '*' service's memory and vehicle count stay bounded?

Waves of ``--vehicles`` fleet vehicles, each wave under new names (``fednav-sim fleet --stem
wK``), publish ``--duration`` scenario seconds at ``--speed``; after each wave the benchmark waits
``--idle`` + 3 s and reads the service's RSS (/proc) and its ServiceHealth (active vehicles,
vehicles released idle, refused for the vehicle limit). One service with ``[intake]
vehicle_idle_s = --idle`` and one with ``vehicle_idle_s = 0`` (never released: the behaviour
before it existed) are run one after the other, without a recording (``--record``: with one,
``rrd_vehicle_interval_s = 1``; its footer's per-chunk metadata then grows the RSS with the
recording's length whatever the vehicles, docs/SCALING.md).

Usage: .venv/bin/python benchmarks/vehicle_churn.py [--vehicles 30] [--waves 6] [--duration 15]
       [--speed 1] [--idle 5] [--record] [--json]
"""

from __future__ import annotations

import argparse
import json
import signal
import sys
import tempfile
import threading
import time
from pathlib import Path

from fleet_load import rss_mb, service_config


def run(idle_s: float, args, tmp: Path, record: bool = True) -> list[dict]:
    import zenoh

    from fednav.service.config import ZenohConfig
    from fednav.service.transport.zenoh_io import make_config
    from fednav.simulators.processes import Proc, free_port, start_service

    port = free_port()
    cfg = service_config(tmp, None, True)
    cfg.write_text(cfg.read_text() + f"vehicle_idle_s = {idle_s}\n")  # (it ends in its [intake] table)
    if record:
        svc = start_service(port, config=cfg, rrd=tmp / f"churn_{idle_s}.rrd")
    else:
        svc = start_service(port, config=cfg, extra=["--no-record"])
    s = zenoh.open(make_config(ZenohConfig(mode="client"), listen=[], connect=[f"tcp/127.0.0.1:{port}"]))
    health: list[dict] = []
    lock = threading.Lock()

    def on_health(sample) -> None:
        with lock:
            health.append(json.loads(sample.payload.to_bytes()))

    sub = s.declare_subscriber("fednav/_services/*/health", on_health)
    rows = []
    try:
        time.sleep(1.0)
        rows.append({"wave": 0, "rss_mb": round(rss_mb(svc.p.pid), 1), "active": 0, "released": 0})
        for k in range(1, args.waves + 1):
            gen = Proc(
                [sys.executable, "-m", "fednav.simulators", "fleet", "--vehicles", str(args.vehicles)]
                + ["--stem", f"w{k}x", "--duration", str(args.duration), "--speed", str(args.speed)]
                + ["--connect", f"tcp/127.0.0.1:{port}"],
                "fednav-sim fleet",
            )
            rc = gen.wait(timeout=args.duration / args.speed * 20 + 300)
            if rc != 0:
                raise RuntimeError(f"fednav-sim fleet exited {rc}: {gen.output()[-2000:]}")
            time.sleep(idle_s + 3.0 if idle_s else 3.0)
            with lock:
                h = health[-1] if health else {}
            rows.append(
                {
                    "wave": k,
                    "rss_mb": round(rss_mb(svc.p.pid), 1),
                    "active": len(h.get("active_vehicles", [])),
                    "released": h.get("vehicles_released_idle", 0),
                    "vehicle_limit": h.get("refused_before_routing", {}).get("vehicle_limit", 0),
                }
            )
    finally:
        sub.undeclare()
        s.close()
        svc.signal(signal.SIGTERM)
        rc = svc.wait(timeout=120)
    if rc != 0:
        raise RuntimeError(f"service exited {rc}")
    return rows


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--vehicles", type=int, default=30)
    ap.add_argument("--waves", type=int, default=6)
    ap.add_argument("--duration", type=float, default=15.0)
    ap.add_argument("--speed", type=float, default=1.0)
    ap.add_argument("--idle", type=float, default=5.0)
    ap.add_argument("--record", action="store_true", help="the service records (.rrd)")
    ap.add_argument("--json", action="store_true")
    args = ap.parse_args()
    out = {}
    with tempfile.TemporaryDirectory() as d:
        for idle_s in (args.idle, 0.0):
            out[idle_s] = run(idle_s, args, Path(d), record=args.record)
            if not args.json:
                print(f"vehicle_idle_s = {idle_s:g}: {args.vehicles} new names per wave")
                for r in out[idle_s]:
                    print(
                        f"  after wave {r['wave']}: RSS {r['rss_mb']:.0f} MB, active {r['active']}, "
                        f"released idle {r['released']}"
                    )
    if args.json:
        print(json.dumps({str(k): v for k, v in out.items()}, indent=1))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
