"""Benchmarks of the backbone (figures printed; not timed tests).

1. Real-time factor of ``fednav-sim eval`` on the demo scenario (in-process, one core).
2. End-to-end latency over loopback Zenoh at nominal rates: IMU sample published -> the Solution
   it triggers received by a plain Zenoh subscriber (both clocks in this process).
3. Highest IMU rate the service sustains without backlog: the demo stream published as fast as
   the service keeps up (reliable, blocking), IMU samples processed per second of wall time,
   expressed as a multiple of a 200 Hz IMU; with ImuBatches of 10 samples (the simulators'
   default) and with one JSON ImuSample per sample.
A fleet (many vehicles, one service): benchmarks/fleet_load.py.

Usage: .venv/bin/python benchmarks/run_all.py [--quick]
"""

from __future__ import annotations

import argparse
import json
import signal
import threading
import time
from pathlib import Path

import numpy as np
import zenoh

ROOT = Path(__file__).resolve().parents[1]
DEMO = ROOT / "simulators" / "scenarios" / "demo_aircraft.toml"


def bench_eval_rtf(runs: int) -> dict:
    from fednav.simulators.evaluate import evaluate
    from fednav.simulators.scenario import load_scenario

    sc = load_scenario(DEMO)
    evaluate(sc, runs=1)  # warm-up
    t0 = time.perf_counter()
    res = evaluate(sc, runs=runs)
    wall = time.perf_counter() - t0
    return {
        "scenario": sc.name,
        "runs": runs,
        "sensor_s": runs * sc.duration_s,
        "wall_s": wall,
        "realtime_factor": runs * sc.duration_s / wall,
        "h_rms_m": res["pipelines"]["lc"]["h_rms_m"],
    }


def _client(port: int) -> zenoh.Session:
    from fednav.service.config import ZenohConfig
    from fednav.service.transport.zenoh_io import make_config

    return zenoh.open(make_config(ZenohConfig(mode="client"), listen=[], connect=[f"tcp/127.0.0.1:{port}"]))


def bench_latency(duration_s: float) -> dict:
    """Nominal-rate publication (speed 1) and Solution receipt in this process."""
    from fednav.service import keys
    from fednav.simulators.processes import free_port, start_service
    from fednav.simulators.scenario import load_scenario
    from fednav.simulators.stream import Simulation

    port = free_port()
    svc = start_service(port, config=DEMO, table="service")
    s = _client(port)
    sent: dict[int, float] = {}
    lat: list[float] = []
    lock = threading.Lock()

    def on_sol(sample):
        now = time.perf_counter()
        t = json.loads(sample.payload.to_bytes())["t"]
        with lock:
            t0 = sent.get(round(t * 1e6))
        if t0 is not None:
            lat.append(now - t0)

    sub = s.declare_subscriber(keys.nav("v1", "lc", "solution"), on_sol)
    pubs = {}
    sc = load_scenario(DEMO)
    try:
        wall0 = None
        t_first = None
        for key, msg in Simulation(sc, seed=1):
            p = pubs.get(key)
            if p is None:
                p = pubs[key] = s.declare_publisher(
                    key,
                    congestion_control=zenoh.CongestionControl.BLOCK,
                    reliability=zenoh.Reliability.RELIABLE,
                )
                while not p.matching_status.matching:
                    time.sleep(0.01)
            if t_first is None:
                t_first, wall0 = msg.t, time.perf_counter()
            if msg.t - t_first > duration_s:
                break
            delay = wall0 + (msg.t - t_first) - time.perf_counter()
            if delay > 0:
                time.sleep(delay)
            payload = msg.to_json()
            with lock:
                sent[round(msg.t * 1e6)] = time.perf_counter()  # the IMU sample (last of its instant)
            p.put(payload)
        time.sleep(1.0)
    finally:
        sub.undeclare()
        s.close()
        svc.signal(signal.SIGINT)
        svc.wait(timeout=60)
    a = np.array(lat) * 1e3
    return {
        "solutions": int(a.size),
        "p50_ms": float(np.percentile(a, 50)),
        "p99_ms": float(np.percentile(a, 99)),
        "max_ms": float(a.max()),
        "imu_hz": 100,
        "gnss_hz": 1,
    }


def bench_throughput(imu_batch: int) -> dict:
    from fednav.simulators.processes import free_port, start_service, start_sim, wait_idle

    port = free_port()
    svc = start_service(port, config=DEMO, table="service")
    try:
        t0 = time.perf_counter()
        sim = start_sim(port, DEMO, speed=0.0, imu_batch=imu_batch)
        sim.wait(timeout=600)
        st = wait_idle(port, timeout_s=600)
        wall = time.perf_counter() - t0 - 0.6  # wait_idle needs two equal polls (~0.3 s each)
    finally:
        svc.signal(signal.SIGINT)
        svc.wait(timeout=60)
    h = st["health"]
    imu_samples = 30000
    rate = imu_samples / wall
    return {
        "imu_batch": imu_batch,
        "messages_received": h["received"],
        "imu_samples": imu_samples,
        "wall_s": wall,
        "imu_rate_hz": rate,
        "multiple_of_200hz": rate / 200.0,
        "latency_p99_ms_under_load": h["latency_ms"]["p99"],
    }


def main() -> int:
    ap = argparse.ArgumentParser()
    ap.add_argument("--quick", action="store_true")
    args = ap.parse_args()
    out = {}
    out["eval_realtime_factor"] = bench_eval_rtf(runs=1 if args.quick else 3)
    print(json.dumps({"eval_realtime_factor": out["eval_realtime_factor"]}, indent=2), flush=True)
    out["latency"] = bench_latency(20.0 if args.quick else 60.0)
    print(json.dumps({"latency": out["latency"]}, indent=2), flush=True)
    for n in (10, 1):  # ImuBatch of 10 (the simulators' default) and JSON per sample
        out[f"throughput_batch{n}"] = bench_throughput(n)
        print(json.dumps({f"throughput_batch{n}": out[f"throughput_batch{n}"]}, indent=2), flush=True)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
