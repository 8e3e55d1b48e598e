"""Is 'aided' truthful on clean data? Per GNSS pipeline family of benchmarks/hardening.py, over
several seeds of its clean scenario (the demo aircraft with fixes, raw BeiDou and a star tracker,
300 s, no corruption): the epochs reported 'aided' while the horizontal error exceeds 3x the
reported horizontal sigma (hypot of the east and north sigmas: the criterion of the hardening
tables), the largest ratio, and the normalised horizontal error squared (east and north, 2.0 for
a consistent filter) of each run (NEES_u, the vertical one, 1.0).

And how many epochs beyond 3 sigma a consistent filter would give: per epoch, the probability
that a zero-mean Gaussian error with the reported east and north sigmas (their correlation is
not recorded: taken as independent) lies beyond 3x their hypot, summed over the epochs reported
'aided' (0.27 % per epoch for an elongated ellipse, the 1-D 3-sigma tail; 0.01 % for a round
one); vertically 0.27 % of them. Observed well above expected means the sigmas understate the
error; near it means the excursions are the tails a consistent filter has (they come in long
runs when the error is correlated in time, so a few runs hold them all).

Also the vertical: epochs 'aided' while the height error exceeds 3x the reported vertical sigma.
``--scenario NAME`` runs that scenario as it is (its own pipelines, its own faults: e.g.
``demo_product``, whose 40-55 s GNSS step is part of the scenario) instead of the clean GNSS one;
``--family underwater`` (or ``demo``, ``ta``) the clean scenario of another family of
benchmarks/hardening.py. ``--soft-gate-prob P`` (or ``none``) sets ``soft_gate_prob`` of every
pipeline on the federated core (docs/DESIGN-NOTES.md, "The soft edge of the gate") for a
side-by-side run. The table also gives the horizontal and vertical RMS over every run.

Usage: OPENBLAS_NUM_THREADS=1 .venv/bin/python benchmarks/status_truth.py --seeds 7-15 [--scenario NAME]
       [--family gnss|demo|ta|underwater] [--soft-gate-prob P|none] [--zero initial,imu,dvl]
"""

from __future__ import annotations

import argparse
import math
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


def _tail_table(n: int = 201) -> tuple[np.ndarray, np.ndarray]:
    """P(r^2 z1^2 + z2^2 > 9 (1 + r^2)) for z1, z2 standard normal and r in [0, 1] (the ratio of
    the smaller to the larger sigma), by quadrature over z1 (deterministic)."""
    from scipy.special import erfc

    r = np.linspace(0.0, 1.0, n)
    z = np.linspace(-12.0, 12.0, 4801)
    w = np.exp(-0.5 * z * z) / math.sqrt(2.0 * math.pi) * (z[1] - z[0])
    rest = 9.0 * (1.0 + r[:, None] ** 2) - (r[:, None] * z[None, :]) ** 2
    p2 = np.where(rest > 0.0, erfc(np.sqrt(np.maximum(rest, 0.0) / 2.0)), 1.0)  # P(|z2| > sqrt(rest))
    return r, p2 @ w


_R, _P = _tail_table()
#: P(|z| > 3) of a standard normal: the vertical criterion's tail for a consistent filter
VERTICAL_TAIL = 0.0026997960632601866


def expected_beyond_3_sigma(sd_e: np.ndarray, sd_n: np.ndarray) -> np.ndarray:
    """Per epoch, the probability that a consistent filter's horizontal error exceeds 3x the hypot
    of its east and north sigmas (independent axes)."""
    a, b = np.abs(sd_e), np.abs(sd_n)
    r = np.minimum(a, b) / np.maximum(np.maximum(a, b), 1e-300)
    return np.interp(r, _R, _P)


def without_errors(sc, which: list[str]):
    """The scenario with the named random errors fixed at zero (``--zero``)."""
    unknown = set(which) - {"initial", "imu", "dvl"}
    if unknown:
        raise SystemExit(f"--zero: unknown {sorted(unknown)}; use initial, imu, dvl")
    update: dict = {}
    if "initial" in which:
        update["initial_errors"] = sc.initial_errors.model_copy(
            update={"mode": "fixed"} | {k: (0.0,) * 3 for k in ("pos_enu_m", "vel_enu_mps", "rpy_arcsec")}
        )
    if "imu" in which:
        zero = (0.0,) * 3
        update["imu"] = sc.imu.model_copy(
            update={"bias_mode": "fixed", "gyro_bias_dph": zero, "accel_bias_ug": zero}
            | {k: zero for k in ("gyro_scale_ppm", "accel_scale_ppm") if hasattr(sc.imu, k)}
        )
    if "dvl" in which and sc.dvl is not None:
        update["dvl"] = sc.dvl.model_copy(
            update={"error_mode": "fixed", "offset_mps": (0.0,) * 3, "scale": (0.0,) * 3}
        )
    return sc.model_copy(update=update) if update else sc


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--seeds", default="7-15", help="a range (7-15) or a list (7,9,11)")
    ap.add_argument("--scenario", help="run this scenario as it is (default: the clean GNSS one)")
    ap.add_argument("--family", default="gnss", choices=sorted(hb.FAMILIES), help="clean scenario of")
    ap.add_argument("--soft-gate-prob", help="soft_gate_prob of the federated-core pipelines (or none)")
    ap.add_argument(
        "--zero",
        default="",
        help="simulate without these random errors, comma-separated: initial (the initial state's), "
        "imu (biases), dvl (offset and scale): which of them a run's excursions come from",
    )
    args = ap.parse_args()
    build, _, start, aiding = hb.FAMILIES[args.family]
    sc = build() if args.scenario is None else load_scenario(args.scenario)
    sc = without_errors(sc, [z for z in args.zero.split(",") if z])
    if args.soft_gate_prob is not None:
        value = None if args.soft_gate_prob.lower() == "none" else float(args.soft_gate_prob)
        for p in sc.service.get("pipelines", []):
            if p.get("kind") in ("federated", "centralized", "underwater"):
                p["soft_gate_prob"] = value
    per: dict[str, list[tuple]] = {}
    for seed in seeds_of(args.seeds):
        rec, _, _ = hb.run_case(sc, seed, None, None, start, aiding)
        for name, (t, err, sd, st) in rec.items():
            aided = np.array(st) == "aided"
            h, hs = hb._h(err, sd)
            lies = int(np.sum(aided & (h > 3.0 * hs)))
            expected = float(np.sum(expected_beyond_3_sigma(sd[:, 0], sd[:, 1])[aided]))
            expected_v = VERTICAL_TAIL * int(np.sum(aided))
            v = np.abs(err[:, 2]) / sd[:, 2]
            lies_v = int(np.sum(aided & (v > 3.0)))
            nees_h = float(np.mean((err[:, 0] / sd[:, 0]) ** 2 + (err[:, 1] / sd[:, 1]) ** 2))
            nees_u = float(np.mean(v**2))
            row = (
                seed,
                lies,
                float(np.max(h / hs)),
                nees_h,
                lies_v,
                float(np.max(v)),
                expected,
                expected_v,
                nees_u,
                float(np.mean(h**2)),
                float(np.mean(err[:, 2] ** 2)),
            )
            per.setdefault(name, []).append(row)
            print(
                f"seed {seed:3d} {name:8s} epochs {len(t)} aided beyond 3 sigma {lies:4d} "
                f"(consistent: {expected:.1f}) "
                f"max h/sigma_h {np.max(h / hs):.2f} NEES_h {nees_h:.2f} | vertical: aided beyond 3 sigma "
                f"{lies_v:4d} (consistent: {expected_v:.1f}) max |up|/sigma_up {np.max(v):.2f} "
                f"NEES_u {nees_u:.2f}",
                flush=True,
            )
    head = (
        "| pipeline | runs 'aided' beyond 3 sigma | epochs (a consistent filter: expected) | max h / sigma_h "
        "| NEES_h mean [min - max] "
        "| vertical: runs / epochs 'aided' beyond 3 sigma (expected) | max abs(up) / sigma_up | NEES_u mean "
        "| RMS h / up m |"
    )
    print("\n" + head)
    print("|---|---|---|---|---|---|---|---|---|")
    for name, rows in per.items():
        lies = [r[1] for r in rows]
        nees = [r[3] for r in rows]
        lies_v = [r[4] for r in rows]
        print(
            f"| `{name}` | {sum(x > 0 for x in lies)} of {len(rows)} | {sum(lies)} "
            f"({sum(r[6] for r in rows):.0f}) | "
            f"{max(r[2] for r in rows):.2f} | {np.mean(nees):.2f} [{min(nees):.2f} - {max(nees):.2f}] | "
            f"{sum(x > 0 for x in lies_v)} of {len(rows)} / {sum(lies_v)} ({sum(r[7] for r in rows):.0f}) | "
            f"{max(r[5] for r in rows):.2f} | {np.mean([r[8] for r in rows]):.2f} | "
            f"{math.sqrt(np.mean([r[9] for r in rows])):.4f} / "
            f"{math.sqrt(np.mean([r[10] for r in rows])):.4f} |"
        )
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
