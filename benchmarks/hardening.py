"""Hardening figures: accuracy under single hostile messages versus the clean run, and the cost of
screening (real-time factor with and without the innovation gate), in-process on the demo.

    .venv/bin/python benchmarks/hardening.py [--runs 3] [--seed 7]

For each run (seeds S, S+1, ...) the demo stream goes through the service's engine (the same code
as the service) once clean and once with every attack of tests/test_hostile.py injected at 100 s
(one IMU sample 1e6 s ahead, an InitialNav 1000 s ahead, a current InitialNav 11 km off, a fix at
lat 0 / lon 0 / h -12 km, a fix claiming 1e-9 m, 50 IMU samples slipped between genuine ones, 5
star-tracker messages under new ids). Printed: horizontal RMS and max error against truth, clean
vs attacked, with the gate (default) and without it; and the real-time factor of the clean run
with and without the gate, measured in the same process, alternating.
"""

from __future__ import annotations

import argparse
import math
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from fednav.service import keys  # noqa: E402
from fednav.service.engine import VehicleEngine  # noqa: E402
from fednav.service.messages import GnssFix, ImuSample, InitialNav, StarAttitude  # noqa: E402
from fednav.simulators.evaluate import CollectingSink, service_config  # noqa: E402
from fednav.simulators.scenario import load_scenario  # noqa: E402
from fednav.simulators.stream import Simulation  # noqa: E402

ATTACK_AT_S = 100.0


def attacks(imu: ImuSample, fix: GnssFix, init: InitialNav) -> list[tuple[str, object]]:
    t = imu.t
    return [
        ("imu", imu.model_copy(update={"t": t + 1e6})),
        ("init", init.model_copy(update={"t": t + 1000.0})),
        ("init", init.model_copy(update={"t": t, "lat_deg": init.lat_deg + 0.1})),
        (
            "gnss_fix",
            fix.model_copy(update={"t": t + 0.05, "lat_deg": 0.0, "lon_deg": 0.0, "height_m": -11999.0}),
        ),
        (
            "gnss_fix",
            fix.model_copy(
                update={"t": t + 0.07, "pos_std_enu_m": (1e-9,) * 3, "vel_std_enu_mps": (1e-9,) * 3}
            ),
        ),
    ] + [
        ("star", StarAttitude(t=t + 0.01 * i, rpy_deg=(20.0, -15.0, 55.0), rpy_std_deg=(0.001,) * 3))
        for i in range(5)
    ]


def run(sc, seed: int, gate: bool, attack: bool) -> tuple[float, float, float]:
    cfg = service_config(sc)
    if not gate:
        cfg = cfg.model_copy(
            update={
                "pipelines": [p.model_copy(update={"innovation_gate_sigma": None}) for p in cfg.pipelines]
            }
        )
    sink = CollectingSink()
    eng = VehicleEngine("v1", cfg, sink)
    init = fix = None
    done = False
    extra = 0
    t0 = time.perf_counter()
    for key, msg in Simulation(sc, seed=seed):
        pk = keys.parse_input(key)
        eng.handle(pk.kind, pk.sensor_id, msg)
        init = msg if isinstance(msg, InitialNav) else init
        fix = msg if isinstance(msg, GnssFix) else fix
        if not attack or not isinstance(msg, ImuSample) or msg.t - sc.t0_gps_s < ATTACK_AT_S:
            continue
        if extra < 50:
            extra += 1
            eng.handle(
                "imu", "main", msg.model_copy(update={"t": msg.t + 0.005, "dvel_mps": (1.0, 1.0, 1.0)})
            )
        if not done:
            done = True
            for i, (kind, m) in enumerate(attacks(msg, fix, init)):
                eng.handle(kind, f"spoof{i}" if kind == "star" else ("main" if kind != "init" else ""), m)
    wall = time.perf_counter() - t0
    err = np.array(sink.records["lc"].err)
    h = np.hypot(err[:, 0], err[:, 1])
    return float(math.sqrt(np.mean(h * h))), float(h.max()), sc.duration_s / wall


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--runs", type=int, default=3)
    ap.add_argument("--seed", type=int, default=7)
    a = ap.parse_args()
    sc = load_scenario("demo_aircraft")
    rows = {}
    for gate in (True, False):
        for attack in (False, True):
            res = [run(sc, a.seed + i, gate, attack) for i in range(a.runs)]
            rows[(gate, attack)] = (
                float(np.sqrt(np.mean([r[0] ** 2 for r in res]))),
                max(r[1] for r in res),
                float(np.median([r[2] for r in res])),
            )
    print(f"demo, {a.runs} run(s) from seed {a.seed}, {sc.duration_s:.0f} s, attacks at {ATTACK_AT_S:.0f} s")
    print(f"{'gate':>6}{'input':>10}{'h RMS m':>10}{'h max m':>10}{'x real time':>13}")
    for (gate, attack), (rms, mx, rtf) in rows.items():
        label = f"{'on' if gate else 'off':>6}{'attacked' if attack else 'clean':>10}"
        print(f"{label}{rms:10.2f}{mx:10.2f}{rtf:13.0f}")
    on, off = rows[(True, False)][2], rows[(False, False)][2]
    print(f"cost of screening (clean run): {on:.0f}x real time with the gate, {off:.0f}x without")


if __name__ == "__main__":
    main()
