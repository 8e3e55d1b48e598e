"""Fleet failover: a router, three services sharing the fleet ([fleet] sharding = "rendezvous"), N
vehicles from the fleet simulator; kill -9 of the busiest service, then a new service joining.

Printed per run (handover on, then the same with handed-over states never used: a cold start):
- settled assignment: vehicles per service, vehicles served by none or by two, duplicate Solutions;
- failover: for the killed service's vehicles, the wall time from the kill to their first new
  Solution (p50 / max), Solutions lost (epochs with no Solution), the horizontal error after the
  takeover (max, and the time until every moved vehicle is back under the clean run's 95th
  percentile);
- rejoin: the same for the vehicles the joining service takes.

``--kill-after S``: the kill S seconds after the simulator started publishing (default 33: the
fleet's demo aircraft climbs; 75 is 10 s into its 3 deg/s turn); ``--no-cold``: the handover run only.

Usage: .venv/bin/python benchmarks/fleet_failover.py [--vehicles 100] [--imu-rate 100]
       [--kill-after 33] [--no-cold] [--json]
"""

from __future__ import annotations

import argparse
import json
import math
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

from fednav.simulators.fleet import vehicle_names
from fednav.simulators.fleet_watch import FleetWatch
from fednav.simulators.processes import Proc, free_port, stop_all


def _service(port: int, cfg: Path) -> Proc:
    p = Proc(
        [
            sys.executable,
            "-m",
            "fednav.service",
            "--config",
            str(cfg),
            "--no-record",
            "--connect",
            f"tcp/127.0.0.1:{port}",
        ],
        "fednav-service",
    )
    if not p.wait_for("fednav-service ready", timeout=60):
        raise RuntimeError(p.output())
    return p


def _zid(p: Proc) -> str:
    return p.output().split("fednav-service up: zid=", 1)[1].split()[0]


def _takeover(watch: FleetWatch, moved: list[str], t_event_wall: float, last_t: dict, bound: float) -> dict:
    """Figures of the vehicles that moved at ``t_event_wall`` (their last sensor time before it in
    ``last_t``)."""
    gaps, errs_max, back_s, lost = [], [], [], 0
    worst = None
    for v in moved:
        with watch.lock:
            after = [(w, t) for w, t, _ in watch.sols.get(v, []) if t > last_t[v]]
        if not after:
            gaps.append(math.inf)
            continue
        gaps.append(min(w for w, _ in after) - t_event_wall)
        ts = sorted({round(t * 10) for _, t in after})
        lost += (ts[-1] - ts[0] + 1 - len(ts)) if ts else 0
        with watch.lock:
            pairs = []
            for _, t, m in watch.sols.get(v, []):
                tr = watch.truth.get((v, round(t * 1e6)))
                if tr is not None and t > last_t[v]:
                    dn = math.radians(m["lat_deg"] - tr["lat_deg"]) * 6.371e6
                    de = (
                        math.radians(m["lon_deg"] - tr["lon_deg"])
                        * 6.371e6
                        * math.cos(math.radians(tr["lat_deg"]))
                    )
                    pairs.append((t, math.hypot(de, dn)))
        if pairs:
            pairs.sort()
            errs_max.append(max(e for _, e in pairs))
            if errs_max[-1] >= max(errs_max):
                worst = (v, [(round(t - last_t[v], 1), round(e, 1)) for t, e in pairs[:8]])
            over = [t for t, e in pairs if e > bound]
            back_s.append((over[-1] - last_t[v]) if over else 0.0)
    g = np.array(gaps)
    return {
        "vehicles": len(moved),
        "gap_s_p50": round(float(np.median(g)), 2) if g.size else None,
        "gap_s_max": round(float(g.max()), 2) if g.size else None,
        "epochs_lost_after_takeover": int(lost),
        "h_err_max_m": round(float(max(errs_max)), 2) if errs_max else None,
        "back_under_p95_s_max": round(float(max(back_s)), 1) if back_s else None,
        "worst_vehicle": worst,  # (name, [(s after its last Solution before the event, error m), ...])
    }


def run(n: int, imu_rate: float, handover: bool, tmp: Path, kill_after: float = 33.0) -> dict:
    cfg = tmp / f"svc_{handover}.toml"
    cfg.write_text(
        'vehicles = ["*"]\npipelines = [{ name = "lc", kind = "loosely_coupled" }]\n'
        '[zenoh]\nmode = "client"\n[fleet]\nsharding = "rendezvous"\n'
        f"handover_max_age_s = {5.0 if handover else 1e-6}\n"
    )
    port = free_port()
    router = Proc(
        [sys.executable, "-m", "fednav.service.router", "--listen", f"tcp/127.0.0.1:{port}"], "router"
    )
    assert router.wait_for("fednav-router ready", timeout=30), router.output()
    procs = [router]
    watch = FleetWatch(port)
    names = vehicle_names(n)
    out: dict = {"handover": handover, "vehicles": n}
    try:
        svcs = [_service(port, cfg) for _ in range(3)]
        procs += svcs
        gen = Proc(
            [
                sys.executable,
                "-m",
                "fednav.simulators",
                "fleet",
                "--vehicles",
                str(n),
                "--duration",
                "150",
                "--imu-rate",
                str(imu_rate),
                "--fix-rate",
                "1",
                "--truth",
                "--connect",
                f"tcp/127.0.0.1:{port}",
            ],
            "fleet",
        )
        procs.append(gen)
        assert gen.wait_for("publishing", timeout=300), gen.output()
        t_pub = time.monotonic()
        time.sleep(25.0)
        t_settled = time.monotonic()
        time.sleep(max(8.0, t_pub + kill_after - time.monotonic()))
        asg = watch.assignment(t_settled)
        served = [v for vs in asg.values() for v in vs]
        dup = sum(watch.duplicates(v, t_settled) for v in names)
        out["settled"] = {
            "per_service": sorted(len(v) for v in asg.values()),
            "served_by_none": len(set(names) - set(served)),
            "served_twice": len(served) - len(set(served)),
            "duplicate_solutions": dup,
        }
        clean = np.concatenate([watch.h_errors(v, 0, math.inf) for v in names])
        bound = float(np.percentile(clean, 95))
        out["clean_h_err_p95_m"] = round(bound, 2)
        by_zid = {_zid(p): p for p in svcs}
        victim_zid = max(asg, key=lambda z: len(asg[z]))
        moved = list(asg[victim_zid])
        last = {v: watch.last_t(v) for v in moved}
        t_kill = time.monotonic()
        by_zid[victim_zid].kill()
        time.sleep(30.0)
        out["failover"] = _takeover(watch, moved, t_kill, last, bound)
        before = watch.assignment(time.monotonic() - 2.0)
        owner_before = {v: z for z, vs in before.items() for v in vs}
        last2 = {v: watch.last_t(v) for v in names}
        t_join = time.monotonic()
        new = _service(port, cfg)
        procs.append(new)
        time.sleep(25.0)
        after = watch.assignment(time.monotonic() - 2.0)
        taken = [v for v in after.get(_zid(new), [])]
        out["rejoin"] = _takeover(watch, taken, t_join, last2, bound)
        out["rejoin"]["moved_only_to_the_new_service"] = all(
            owner_before.get(v) == z for z, vs in after.items() if z != _zid(new) for v in vs
        )
        dup_after = sum(watch.duplicates(v, time.monotonic() - 10.0) for v in names)
        out["rejoin"]["duplicate_solutions_last_10_s"] = dup_after
    finally:
        stop_all(procs)
        watch.close()
    return out


def main() -> int:
    ap = argparse.ArgumentParser()
    ap.add_argument("--vehicles", type=int, default=100)
    ap.add_argument("--imu-rate", type=float, default=100.0)
    ap.add_argument("--kill-after", type=float, default=33.0)
    ap.add_argument("--no-cold", action="store_true")
    ap.add_argument("--json", action="store_true")
    args = ap.parse_args()
    res = []
    with tempfile.TemporaryDirectory() as d:
        for handover in (True,) if args.no_cold else (True, False):
            r = run(args.vehicles, args.imu_rate, handover, Path(d), args.kill_after)
            res.append(r)
            if not args.json:
                print(json.dumps(r), flush=True)
    if args.json:
        print(json.dumps(res, indent=2))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
