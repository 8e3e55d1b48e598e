"""Seed 003: real-time factor of the outlier IMM pipeline (tc_imm, 4 models) against the plain
tightly coupled KF (tc), measured side by side on one core.

One stream of ``seed003_outliers`` (``--duration`` s: IMU 100 Hz, GPS + BDS raw at 10 Hz, the
10 highest satellites, i.e. 20 rows per epoch with range rates) is simulated once; then the
service's engine (``service.engine.VehicleEngine``, solutions built at 10 Hz as the service does,
outputs discarded) runs it with ONE pipeline at a time, alternating the pipelines ``--repeat``
times; the best wall time of each gives its real-time factor (stream duration / wall time).
Pipelines: ``tc`` (tightly_coupled, no integrity), ``tc_imm`` (paper likelihood),
``tc_imm_gauss`` (Gaussian likelihood), ``tc_gate`` (one model + chi-square gate).

Usage: OPENBLAS_NUM_THREADS=1 .venv/bin/python benchmarks/seed003_imm.py [--duration 60] [--repeat 3] [--json]
"""

from __future__ import annotations

import argparse
import json
import time

from seed003_remedies import pin_clock

from fednav.service import config as config_mod
from fednav.service import keys
from fednav.service.engine import VehicleEngine
from fednav.simulators.scenario import load_scenario, parse_scenario
from fednav.simulators.stream import Simulation

PIPELINES = {
    "tc": {"kind": "tightly_coupled", "integrity": False, "elevation_mask_deg": 5.0},
    "tc_imm": {"kind": "imm_tightly_coupled", "likelihood": "paper", "selection_correction": False},
    "tc_imm_gauss": {"kind": "imm_tightly_coupled", "likelihood": "gaussian", "selection_correction": False},
    "tc_gate": {
        "kind": "imm_tightly_coupled",
        "models": ["normal"],
        "gate_p_fa": 0.001,
        "likelihood": "paper",
        "selection_correction": False,
    },
}


class DiscardSink:
    """Builds every Solution (as the service does) and drops it."""

    def on_estimate(self, vehicle, out) -> None:
        out.solution()

    def on_output(self, vehicle, msg, err9=None) -> None:
        pass

    def on_truth(self, vehicle, truth) -> None:
        pass


def stream(duration_s: float, seed: int) -> tuple[list, object]:
    d = load_scenario("seed003_outliers").model_dump()
    d["duration_s"] = duration_s
    segs, total = [], 0.0
    for seg in d["segments"]:
        if total + seg["duration_s"] > duration_s:
            break
        segs.append(seg)
        total += seg["duration_s"]
    d["segments"] = segs
    d["faults"] = [dict(f, start_s=1.0, duration_s=duration_s - 1.0) for f in d["faults"][:1]]
    sc = parse_scenario(d, "seed003_outliers (benchmark variant)")
    msgs = []
    for key, msg in Simulation(sc, seed=seed):
        pk = keys.parse_input(key)
        msgs.append((pk.kind, pk.sensor_id, msg))
    return msgs, sc


def run(name: str, msgs: list, sc) -> tuple[float, int]:
    cfg = config_mod.from_dict({**sc.service, "pipelines": pin_clock([{"name": name, **PIPELINES[name]}])})
    engine = VehicleEngine("v1", cfg, DiscardSink())
    t0 = time.perf_counter()
    for kind, sid, msg in msgs:
        engine.handle(kind, sid, msg)
    wall = time.perf_counter() - t0
    return wall, engine.pipelines[0].updates


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--duration", type=float, default=60.0)
    ap.add_argument("--repeat", type=int, default=3)
    ap.add_argument("--seed", type=int, default=3)
    ap.add_argument("--json", action="store_true")
    args = ap.parse_args(argv)
    msgs, sc = stream(args.duration, args.seed)
    raw = [m for k, _, m in msgs if k == "gnss_raw"]
    sats = sum(len(m.sats) for m in raw) / max(len(raw), 1)
    best: dict[str, float] = {}
    updates: dict[str, int] = {}
    for _ in range(args.repeat):
        for name in PIPELINES:
            wall, updates[name] = run(name, msgs, sc)
            best[name] = min(best.get(name, float("inf")), wall)
    out = {
        "duration_s": args.duration,
        "satellites_mean": sats,
        "repeat": args.repeat,
        "pipelines": {
            n: {
                "wall_s": best[n],
                "realtime_factor": args.duration / best[n],
                "updates": updates[n],
                "ms_per_gnss_epoch": 1e3 * best[n] / max(len(raw), 1),
            }
            for n in PIPELINES
        },
    }
    out["imm_cost_vs_tc"] = best["tc_imm"] / best["tc"]
    if args.json:
        print(json.dumps(out, indent=2))
        return 0
    print(
        f"seed003_outliers, {args.duration:.0f} s stream, {sats:.1f} satellites per epoch "
        f"({2 * sats:.0f} rows), best of {args.repeat}, one pipeline at a time"
    )
    for n, e in out["pipelines"].items():
        print(
            f"  {n:<14}{e['realtime_factor']:8.1f}x real time   {e['ms_per_gnss_epoch']:6.2f} ms per "
            f"GNSS epoch (all work: 10 IMU samples, 1 GNSS update, 1 solution)   {e['updates']} updates"
        )
    print(f"  tc_imm / tc wall time: {out['imm_cost_vs_tc']:.2f}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
