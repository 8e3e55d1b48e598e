"""Real-time factor of seed-002 transfer alignment: three slave IMUs at 100 Hz (one core).

1. ``bank``: the 27-state bank of three slaves alone (relative mechanisation of every 100 Hz
   sample + one filter epoch per 0.1 s), plain KF and adaptive (Sage-Husa R + chi2 fading).
2. ``engine``: the whole vehicle path of the service -- VehicleEngine with one transfer_alignment
   pipeline (the master's loosely coupled INS/GNSS + the node bank), fed the validated message
   stream of four IMU nodes, GNSS, truth and node truth (message construction excluded).

Usage: .venv/bin/python benchmarks/seed002_transfer.py [--seconds 120]
"""

from __future__ import annotations

import argparse
import hashlib
import json
import os
import time

os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")

import numpy as np  # noqa: E402

from fednav.service import keys  # noqa: E402
from fednav.service.config import TransferAlignmentConfig  # noqa: E402
from fednav.service.engine import VehicleEngine  # noqa: E402
from fednav.service.pipelines.transfer_alignment import bank_from_config  # noqa: E402
from fednav.simulators.evaluate import service_config  # noqa: E402
from fednav.simulators.scenario import load_scenario, parse_scenario  # noqa: E402
from fednav.simulators.wing import WingSimulation  # noqa: E402


def scenario(seconds: float, pipelines: list[dict]):
    d = load_scenario("seed002_wing").model_dump()
    d["duration_s"] = seconds
    segs, acc = [], 0.0
    for s in d["segments"]:
        if acc + s["duration_s"] <= seconds:
            segs.append(s)
            acc += s["duration_s"]
    d["segments"] = segs
    d["service"] = dict(d["service"]) | {"pipelines": pipelines}
    return parse_scenario(d)


def bench_bank(sc, mode: str) -> float:
    sim = WingSimulation(sc, seed=1)
    dth_m, dv_m = sim.master._dth, sim.master._dv
    dth_s = np.stack([n.dtheta_rad for n in sim.nodes], axis=1)
    dv_s = np.stack([n.dvel_mps for n in sim.nodes], axis=1)
    bank = bank_from_config(TransferAlignmentConfig(name="b", filter=mode, fading=mode == "akf"))
    t0 = time.perf_counter()
    for k in range(1, dth_m.shape[0]):
        bank.push(dth_m[k], dv_m[k], dth_s[k], dv_s[k], 0.01, k * 0.01)
    return sc.duration_s / (time.perf_counter() - t0)


def bench_engine(sc, repeats: int = 3) -> tuple[float, float]:
    """(wall-clock, process CPU-time) real-time factors, best of ``repeats`` runs (the CPU-time
    figure is the one-core figure when other processes share the core)."""

    class Sink:
        def on_estimate(self, *a):
            pass

        def on_output(self, *a):
            pass

        def on_truth(self, *a):
            pass

    events = [(keys.parse_input(k), m) for k, m in WingSimulation(sc, seed=1)]
    wall, cpu = [], []
    for _ in range(repeats):
        eng = VehicleEngine("v1", service_config(sc), Sink())
        t0, c0 = time.perf_counter(), time.process_time()
        for pk, m in events:
            eng.handle(pk.kind, pk.sensor_id, m)
        wall.append(sc.duration_s / (time.perf_counter() - t0))
        cpu.append(sc.duration_s / (time.process_time() - c0))
    return max(wall), max(cpu)


def engine_digest(sc) -> str:
    """sha256 of every Alignment message (JSON) and the final bank state of an engine run: equal
    digests before and after a speed change mean bit-identical estimates."""
    h = hashlib.sha256()

    class Sink:
        def on_estimate(self, *a):
            pass

        def on_output(self, vehicle, msg, truth=None):
            h.update(msg.model_dump_json().encode())

        def on_truth(self, *a):
            pass

    eng = VehicleEngine("v1", service_config(sc), Sink())
    for k, m in WingSimulation(sc, seed=1):
        pk = keys.parse_input(k)
        eng.handle(pk.kind, pk.sensor_id, m)
    for p in eng.pipelines:
        if getattr(p, "ta", None) is not None:
            for a in (p.ta.x, p.ta.P, p.ta.C_ms, p.ta.V):
                h.update(np.ascontiguousarray(a).tobytes())
    return h.hexdigest()[:16]


def main() -> int:
    ap = argparse.ArgumentParser()
    ap.add_argument("--seconds", type=float, default=120.0)
    ap.add_argument("--digest-only", action="store_true", help="print the 20 s engine digest only")
    args = ap.parse_args()
    short = scenario(20.0, [{"name": "ta", "kind": "transfer_alignment", "filter": "akf"}])
    if args.digest_only:
        print(json.dumps({"engine_digest_20s": engine_digest(short)}))
        return 0
    sc = scenario(args.seconds, [{"name": "ta", "kind": "transfer_alignment", "filter": "akf"}])
    wall, cpu = bench_engine(sc)
    out = {
        "scenario_s": args.seconds,
        "slaves": 3,
        "imu_rate_hz": 100.0,
        "bank_kf_rtf": round(bench_bank(sc, "kf"), 1),
        "bank_akf_rtf": round(bench_bank(sc, "akf"), 1),
        "engine_akf_rtf": round(wall, 1),
        "engine_akf_rtf_cpu": round(cpu, 1),
        "engine_digest_20s": engine_digest(short),
        "cpu_count": os.cpu_count(),
        "load_avg_1min": round(os.getloadavg()[0], 2),
    }
    print(json.dumps(out, indent=2))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
