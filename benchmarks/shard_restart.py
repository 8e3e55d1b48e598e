"""A local shard killed mid-run (SIGKILL): its vehicles' horizontal errors after shard 0 restarts it.

    .venv/bin/python benchmarks/shard_restart.py [--kill-after 60] [--duration 120]

One service with ``--shards 2`` (one loosely coupled pipeline) and ``fednav-sim fleet --vehicles 8
--truth`` at real time; shard 1 is killed ``--kill-after`` seconds in. Prints, per vehicle of
shard 1: the largest gap between two of its solutions (the restart; sensor seconds), the
horizontal RMS error over the 30 s before the kill, over the first 10 s after the
restart (and its maximum) and from 20 s after it, and the statuses of the first 10 s. One run of
the fleet simulator's fixed seeds: a figure of this run, not of every fleet.
"""

from __future__ import annotations

import argparse
import json
import math
import os
import signal
import sys
import tempfile
import threading
import time
from pathlib import Path

import numpy as np


def _rms(values: list[float]) -> float | None:
    return float(np.sqrt(np.mean(np.square(values)))) if values else None


def run(kill_after_s: float, duration_s: float, vehicles: int) -> dict:
    import zenoh

    from fednav.service import fleet
    from fednav.service.config import ZenohConfig
    from fednav.service.transport.zenoh_io import make_config
    from fednav.simulators.fleet import vehicle_names
    from fednav.simulators.processes import Proc, free_port, start_service

    tmp = Path(tempfile.mkdtemp(prefix="shard_restart_"))
    cfg = tmp / "fleet.toml"
    cfg.write_text('vehicles = ["*"]\npipelines = [{ name = "lc", kind = "loosely_coupled" }]\n')
    port = free_port()
    svc = start_service(port, config=cfg, extra=["--shards", "2"])
    with open(f"/proc/{svc.p.pid}/task/{svc.p.pid}/children") as f:
        child = int(f.read().split()[0])
    theirs = [v for v in vehicle_names(vehicles) if fleet.shard_of(v, 2) == 1]
    s = zenoh.open(make_config(ZenohConfig(mode="client"), listen=[], connect=[f"tcp/127.0.0.1:{port}"]))
    sols: dict[str, list] = {}
    truth: dict[str, dict] = {}
    lock = threading.Lock()

    def on_sol(sample) -> None:
        d = json.loads(sample.payload.to_bytes())
        with lock:
            sols.setdefault(str(sample.key_expr).split("/")[1], []).append(
                (d["t"], d["lat_deg"], d["lon_deg"], d["status"])
            )

    def on_truth(sample) -> None:
        d = json.loads(sample.payload.to_bytes())
        with lock:
            truth.setdefault(str(sample.key_expr).split("/")[1], {})[round(d["t"], 3)] = (
                d["lat_deg"],
                d["lon_deg"],
            )

    subs = [
        s.declare_subscriber("fednav/*/nav/lc/solution", on_sol),
        s.declare_subscriber("fednav/*/truth", on_truth),
    ]
    gen = Proc(
        [sys.executable, "-m", "fednav.simulators", "fleet", "--vehicles", str(vehicles)]
        + ["--duration", str(duration_s), "--truth", "--connect", f"tcp/127.0.0.1:{port}"],
        "fednav-sim fleet",
    )
    try:
        time.sleep(kill_after_s)
        with lock:
            t_kill = max(x[0] for v in theirs for x in sols.get(v, [(0.0,)]))
        os.kill(child, signal.SIGKILL)
        gen.wait(timeout=duration_s + 120)
        time.sleep(3.0)
    finally:
        for sub in subs:
            sub.undeclare()
        s.close()
        svc.signal(signal.SIGTERM)
        svc.wait(timeout=60)
    out = {}
    for v in theirs:
        rows = []
        for t, lat, lon, status in sols.get(v, []):
            tr = truth.get(v, {}).get(round(t, 3))
            if tr is None:
                continue
            dn = math.radians(lat - tr[0]) * 6371000.0
            de = math.radians(lon - tr[1]) * 6371000.0 * math.cos(math.radians(tr[0]))
            rows.append((t - t_kill, math.hypot(dn, de), status))
        times = np.array([r[0] for r in rows])
        window = np.flatnonzero((times[1:] > -5.0) & (times[:-1] < 30.0))  # pairs around the kill
        if len(window) == 0:
            out[v] = {"solutions": len(rows)}
            continue
        i = window[np.argmax(np.diff(times)[window])]  # the restart: the largest gap there
        after = rows[i + 1 :]
        t0 = after[0][0]
        first10 = [r for r in after if r[0] < t0 + 10.0]
        out[v] = {
            "solution_gap_s": float(times[i + 1] - times[i]),
            "rms_30s_before_m": _rms([r[1] for r in rows if -30.0 < r[0] <= 0.0]),
            "rms_first_10s_m": _rms([r[1] for r in first10]),
            "max_first_10s_m": max(r[1] for r in first10),
            "rms_from_20s_m": _rms([r[1] for r in after if r[0] > t0 + 20.0]),
            "statuses_first_10s": sorted({r[2] for r in first10}),
        }
    return out


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--kill-after", type=float, default=60.0, help="wall seconds before shard 1 is killed")
    ap.add_argument("--duration", type=float, default=120.0, help="the fleet's sensor seconds (real time)")
    ap.add_argument("--vehicles", type=int, default=8)
    args = ap.parse_args()
    for v, r in run(args.kill_after, args.duration, args.vehicles).items():
        fig = {k: round(x, 2) if isinstance(x, float) else x for k, x in r.items()}
        print(v, json.dumps(fig))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
