"""Is 'aided' truthful on clean data? Per GNSS pipeline family of benchmarks/hardening.py, over
several seeds of its clean scenario (the demo aircraft with fixes, raw BeiDou and a star tracker,
300 s, no corruption): the epochs reported 'aided' while the horizontal error exceeds 3x the
reported horizontal sigma (hypot of the east and north sigmas: the criterion of the hardening
tables), the largest ratio, and the normalised horizontal error squared (east and north, 2.0 for
a consistent filter) of each run.

Also the vertical: epochs 'aided' while the height error exceeds 3x the reported vertical sigma.
``--scenario NAME`` runs that scenario as it is (its own pipelines, its own faults: e.g.
``demo_product``, whose 40-55 s GNSS step is part of the scenario) instead of the clean GNSS one.

Usage: OPENBLAS_NUM_THREADS=1 .venv/bin/python benchmarks/status_truth.py --seeds 7-15 [--scenario NAME]
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))

import hardening as hb  # noqa: E402

from fednav.simulators.scenario import load_scenario  # noqa: E402


def seeds_of(text: str) -> list[int]:
    if "-" in text:
        lo, hi = (int(x) for x in text.split("-"))
        return list(range(lo, hi + 1))
    return [int(x) for x in text.split(",")]


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--seeds", default="7-15", help="a range (7-15) or a list (7,9,11)")
    ap.add_argument("--scenario", help="run this scenario as it is (default: the clean GNSS one)")
    args = ap.parse_args()
    sc = hb.gnss_scenario() if args.scenario is None else load_scenario(args.scenario)
    per: dict[str, list[tuple[int, int, float, float, int, float]]] = {}
    for seed in seeds_of(args.seeds):
        rec, _, _ = hb.run_case(sc, seed, None, None, hb.FAMILIES["gnss"][2], "gnss_fix")
        for name, (t, err, sd, st) in rec.items():
            aided = np.array(st) == "aided"
            h, hs = hb._h(err, sd)
            lies = int(np.sum(aided & (h > 3.0 * hs)))
            v = np.abs(err[:, 2]) / sd[:, 2]
            lies_v = int(np.sum(aided & (v > 3.0)))
            nees_h = float(np.mean((err[:, 0] / sd[:, 0]) ** 2 + (err[:, 1] / sd[:, 1]) ** 2))
            per.setdefault(name, []).append(
                (seed, lies, float(np.max(h / hs)), nees_h, lies_v, float(np.max(v)))
            )
            print(
                f"seed {seed:3d} {name:8s} epochs {len(t)} aided beyond 3 sigma {lies:4d} "
                f"max h/sigma_h {np.max(h / hs):.2f} NEES_h {nees_h:.2f} | vertical: aided beyond 3 sigma "
                f"{lies_v:4d} max |up|/sigma_up {np.max(v):.2f}",
                flush=True,
            )
    head = (
        "| pipeline | runs 'aided' beyond 3 sigma | epochs | max h / sigma_h | NEES_h mean [min - max] "
        "| vertical: runs / epochs 'aided' beyond 3 sigma | max abs(up) / sigma_up |"
    )
    print("\n" + head)
    print("|---|---|---|---|---|---|---|")
    for name, rows in per.items():
        lies = [r[1] for r in rows]
        nees = [r[3] for r in rows]
        lies_v = [r[4] for r in rows]
        print(
            f"| `{name}` | {sum(x > 0 for x in lies)} of {len(rows)} | {sum(lies)} | "
            f"{max(r[2] for r in rows):.2f} | {np.mean(nees):.2f} [{min(nees):.2f} - {max(nees):.2f}] | "
            f"{sum(x > 0 for x in lies_v)} of {len(rows)} / {sum(lies_v)} | {max(r[5] for r in rows):.2f} |"
        )
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
