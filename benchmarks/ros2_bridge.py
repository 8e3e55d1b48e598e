"""Cost of the ROS 2 bridge per message (figures printed; not timed tests), in-process, one core:

1. decode: CDR Imu -> ImuSample, CDR NavSatFix + Twist -> GnssFix (RosInput.decode: the wire models
   built and validated straight from the CDR values, no JSON);
2. encode: one output epoch -> Odometry + NavSatFix (+ TF) CDR (exact input stamps looked up);
   one Health -> DiagnosticArray CDR.

Usage: .venv/bin/python benchmarks/ros2_bridge.py [--n 5000]
"""

from __future__ import annotations

import argparse
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--n", type=int, default=5000, help="messages per figure (default: %(default)s)")
    args = ap.parse_args()
    from fednav.service import earth
    from fednav.service.ins.mechanisation import NavState
    from fednav.service.messages import Health, PipelineHealth
    from fednav.service.transport import ros2
    from fednav.simulators.ros2_publish import example_config, ros_samples
    from fednav.simulators.scenario import load_scenario

    cfg = example_config(outputs={"tf": True})
    sc = load_scenario(ROOT / "simulators" / "scenarios" / "demo_aircraft.toml")
    samples = []
    for s in ros_samples(sc, 1, cfg):
        samples.append(s)
        if len(samples) >= args.n:
            break
    imu = [(k, p) for k, p, _ in samples if "/imu/" in k]
    gnss = [(k, p) for k, p, _ in samples if "/gnss/" in k]
    rin = ros2.RosInput(cfg)
    t0 = time.perf_counter()
    for k, p in imu:
        rin.decode(k, p)
    imu_us = (time.perf_counter() - t0) / len(imu) * 1e6
    t0 = time.perf_counter()
    for _ in range(max(1, 2000 // max(1, len(gnss)))):
        for k, p in gnss:
            rin.decode(k, p)
    reps = max(1, 2000 // max(1, len(gnss)))
    gnss_us = (time.perf_counter() - t0) / (reps * len(gnss)) * 1e6

    enc = ros2.RosEncoder(cfg)
    nav = NavState(
        t=1.3e9,
        lat_rad=0.7,
        lon_rad=2.07,
        h_m=100.0,
        vel_enu_mps=np.array([80.0, 80.0, 0.0]),
        q_nb=earth.mat_to_quat(earth.rpy_to_mat_nb(np.radians([1.0, 2.0, -45.0]))),
    )
    A = np.random.default_rng(0).normal(size=(9, 9)) * 0.1
    P9 = A @ A.T + np.eye(9) * 1e-3
    t0 = time.perf_counter()
    n = 2000
    for _ in range(n):
        enc.cdr(enc.odometry("lc", nav, P9))
        enc.cdr(enc.navsatfix(nav, P9, "aided"))
        enc.cdr(enc.tf("lc", nav))
    epoch_us = (time.perf_counter() - t0) / n * 1e6
    h = Health(
        t=1.3e9,
        uptime_s=1.0,
        received=1,
        accepted=1,
        rejected={"late": 1},
        dropped_overload=0,
        queue_depth=0,
        latency_ms={"p50": 1.0, "p99": 2.0, "max": 3.0},
        pipelines={f"p{i}": PipelineHealth(status="aided", last_t=1.3e9, updates=1) for i in range(7)},
    )
    t0 = time.perf_counter()
    for _ in range(n):
        enc.cdr(enc.diagnostics("v1", h))
    diag_us = (time.perf_counter() - t0) / n * 1e6
    print(f"decode Imu -> ImuSample (validated model):    {imu_us:8.1f} us/message ({len(imu)} messages)")
    print(f"decode NavSatFix or Twist (pairing included): {gnss_us:8.1f} us/message")
    print(f"encode Odometry + NavSatFix + TF (one epoch): {epoch_us:8.1f} us/epoch")
    print(f"encode DiagnosticArray (7 pipelines):         {diag_us:8.1f} us/message")
    print(
        f"=> one core decodes ~{1e6 / imu_us:,.0f} Imu/s; "
        f"10 Hz outputs of one pipeline take {epoch_us * 10 / 1e4:.2f} % of a core"
    )
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
