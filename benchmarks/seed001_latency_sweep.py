"""Seed 001 ramp: detection latency against pseudorange noise, GNSS rate and detector.

The scenario is ``simulators/scenarios/seed001_ramp.toml`` (0.63 m/s ramp on GEO3 = C03 from
11 s, six largest-GDOP BDS satellites, NPA), shortened to ``--duration`` seconds. For every
pseudorange noise (1 sigma, white), GNSS rate and detector, the ramp is run with ``--seeds``
noise seeds through ``fednav-sim eval``'s in-process path, and the script prints the latency of
the first detection after the onset (median / max over seeds), how many runs excluded C03 and
no other satellite, and the median HPL. Detectors:

- ``ss``: solution separation only (seed 001 as printed; ``TightlyCoupled.RESIDUAL_WINDOWS = ()``);
- ``ss+res``: separation plus the satellite residual test against the sub-filter that excludes
  the satellite, windows of 1 and 10 epochs (the service's default; docs/seed001.md).

The paper's figure is 2 s (flagged at 13 s). Usage:

    OPENBLAS_NUM_THREADS=1 .venv/bin/python benchmarks/seed001_latency_sweep.py \\
        [--noise 0.25 0.5 1 2 3] [--rates 10 1] [--seeds 3] [--duration 40] [--json]
"""

from __future__ import annotations

import argparse
import json
import time

import numpy as np

from fednav.service.pipelines.tightly_coupled import TightlyCoupled
from fednav.simulators.evaluate import evaluate
from fednav.simulators.scenario import load_scenario, parse_scenario

DETECTORS = {"ss": (), "ss+res": TightlyCoupled.RESIDUAL_WINDOWS}


def variant(sigma_m: float, rate_hz: float, duration_s: float):
    base = load_scenario("seed001_ramp")
    d = base.model_dump()
    d["gnss_raw"]["pseudorange_sigma_m"] = sigma_m
    d["gnss_raw"]["rate_hz"] = rate_hz
    d["duration_s"] = duration_s
    f = d["faults"][0]
    f["duration_s"] = min(f["duration_s"], duration_s - f["start_s"])
    segs, total = [], 0.0
    for seg in d["segments"]:  # the segments that fit (the rest is padded with straight flight)
        if total + seg["duration_s"] > duration_s:
            break
        segs.append(seg)
        total += seg["duration_s"]
    d["segments"] = segs
    return parse_scenario(d, "seed001_ramp (sweep variant)")


def run(sigma_m: float, rate_hz: float, detector: str, seeds: int, duration_s: float) -> dict:
    sc = variant(sigma_m, rate_hz, duration_s)
    saved = TightlyCoupled.RESIDUAL_WINDOWS
    TightlyCoupled.RESIDUAL_WINDOWS = DETECTORS[detector]
    try:
        lat, only_c03, hpl = [], 0, []
        for s in range(1, seeds + 1):
            g = evaluate(sc, runs=1, seed=s)["pipelines"]["tc_mhss"]["integrity"]
            x = g["detection_latency_s"]
            lat.append(np.nan if x is None else x)
            only_c03 += g["excluded_satellites"] == ["C03"]
            hpl.append(g["hpl_m"]["median"])
    finally:
        TightlyCoupled.RESIDUAL_WINDOWS = saved
    lat = np.array(lat)
    return {
        "noise_m": sigma_m,
        "rate_hz": rate_hz,
        "detector": detector,
        "seeds": seeds,
        "latency_median_s": float(np.nanmedian(lat)) if np.any(np.isfinite(lat)) else None,
        "latency_max_s": float(np.max(lat)) if np.all(np.isfinite(lat)) else None,
        "latency_runs_s": [None if not np.isfinite(x) else round(float(x), 3) for x in lat],
        "excluded_only_c03": only_c03,
        "hpl_median_m": float(np.median(hpl)),
    }


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--noise", type=float, nargs="+", default=[0.25, 0.5, 1.0, 2.0, 3.0])
    ap.add_argument("--rates", type=float, nargs="+", default=[10.0, 1.0])
    ap.add_argument("--detectors", nargs="+", default=list(DETECTORS), choices=list(DETECTORS))
    ap.add_argument("--seeds", type=int, default=3)
    ap.add_argument("--duration", type=float, default=40.0, help="run length, s (onset at 11 s)")
    ap.add_argument("--json", action="store_true")
    a = ap.parse_args(argv)
    rows = []
    t0 = time.perf_counter()
    if not a.json:
        print(
            f"seed001 ramp 0.63 m/s on C03 from 11 s; {a.seeds} seed(s) each; latency = first detection "
            "after the onset (paper: 2 s)"
        )
        print(
            f"{'noise m':>8}{'rate Hz':>8}{'detector':>9}{'lat med s':>11}{'lat max s':>11}"
            f"{'C03 only':>10}{'HPL med m':>11}"
        )
    for sigma in a.noise:
        for rate in a.rates:
            for det in a.detectors:
                r = run(sigma, rate, det, a.seeds, a.duration)
                rows.append(r)
                if not a.json:
                    med = "never" if r["latency_median_s"] is None else f"{r['latency_median_s']:.2f}"
                    mx = ">run" if r["latency_max_s"] is None else f"{r['latency_max_s']:.2f}"
                    print(
                        f"{sigma:8.2f}{rate:8.0f}{det:>9}{med:>11}{mx:>11}"
                        f"{str(r['excluded_only_c03']) + '/' + str(a.seeds):>10}{r['hpl_median_m']:11.1f}",
                        flush=True,
                    )
    if a.json:
        print(json.dumps(rows, indent=2))
    else:
        print(f"({time.perf_counter() - t0:.0f} s)")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
