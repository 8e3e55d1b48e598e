"""Seed 000 Table 2 claim, paired: method 2 (per-observation isolation) vs method 1 (subsystem).

Runs ``fed_vector`` and ``fed_vector_sysiso`` of ``seed000_faults`` side by side on the SAME
simulated data, one seed at a time, and compares their RMS inside the 400-550 s window (the
velocity-only BDS fault is 450-500 s). Paired differences of mean-square errors cancel most of
the run-to-run noise, so the printed z = mean / standard error says whether a difference is real.
``--control`` adds the same comparison between two CENTRALISED filters (per-observation vs
per-sensor isolation, no information sharing at all): it separates what the isolation method
gives from what the federated sharing does. Too slow for the test suite (about 8 s per seed
on one core, 12 s with the control).

Usage: .venv/bin/python benchmarks/seed000_methods.py [--seeds 20] [--first 200] [--control] [--json]
"""

from __future__ import annotations

import argparse
import json
import os

os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")

import numpy as np  # noqa: E402

from fednav.simulators.evaluate import evaluate  # noqa: E402
from fednav.simulators.scenario import load_scenario  # noqa: E402

M2, M1 = "fed_vector", "fed_vector_sysiso"
CONTROL = [
    {"name": "central_obs", "kind": "centralized", "fault_handling": "per_observation"},
    {"name": "central_sys", "kind": "centralized", "fault_handling": "subsystem"},
]
KEYS = ("lat_m", "lon_m", "h_m", "ve_mps", "vn_mps", "vu_mps")


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--seeds", type=int, default=20)
    ap.add_argument("--first", type=int, default=200)
    ap.add_argument("--window", type=float, nargs=2, default=(400.0, 550.0))
    ap.add_argument("--control", action="store_true", help="also compare two centralised filters")
    ap.add_argument("--json", action="store_true")
    a = ap.parse_args(argv)
    sc = load_scenario("seed000_faults")
    service = dict(sc.service)
    service["pipelines"] = [p for p in service["pipelines"] if p["name"] in (M1, M2)]
    pairs = [(M1, M2)]
    if a.control:
        service["pipelines"] = service["pipelines"] + CONTROL
        pairs.append(("central_sys", "central_obs"))
    sc = sc.model_copy(update={"service": service})
    per_run = []
    for s in range(a.first, a.first + a.seeds):
        r = evaluate(sc, runs=1, seed=s, window=tuple(a.window))["pipelines"]
        per_run.append({m: r[m]["window"]["rms"] for pair in pairs for m in pair})
    out = {"seeds": [a.first, a.first + a.seeds - 1], "window_s": list(a.window), "pairs": {}}
    for m1, m2 in pairs:
        comp = out["pairs"][f"{m2} vs {m1}"] = {}
        for k in KEYS:
            ms1 = np.array([r[m1][k] ** 2 for r in per_run])
            ms2 = np.array([r[m2][k] ** 2 for r in per_run])
            d = ms2 - ms1
            se = d.std(ddof=1) / np.sqrt(d.size) if d.size > 1 else float("nan")
            comp[k] = {
                "method1_rms": float(np.sqrt(ms1.mean())),
                "method2_rms": float(np.sqrt(ms2.mean())),
                "z": float(d.mean() / se) if se > 0 else float("nan"),  # < 0: method 2 better
                "method2_better_runs": int((d < 0).sum()),
            }
    if a.json:
        print(json.dumps(out, indent=1))
        return 0
    last = a.first + a.seeds - 1
    print(f"seed 000 window {a.window[0]:g}-{a.window[1]:g} s, seeds {a.first}..{last} (paired)")
    for title, comp in out["pairs"].items():
        print(f"\n{title}  (method 2 = per-observation isolation)")
        print(f"{'component':10s} {'method 1':>10s} {'method 2':>10s} {'z (m2-m1)':>10s} {'m2 better':>10s}")
        for k, c in comp.items():
            print(
                f"{k:10s} {c['method1_rms']:10.4f} {c['method2_rms']:10.4f} {c['z']:10.2f}"
                f" {c['method2_better_runs']:>6d}/{a.seeds}"
            )
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
