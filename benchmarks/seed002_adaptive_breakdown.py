"""Seed 002: where the adaptive filter's parts help or hurt (figures printed, one seeded run).

One 300 s run of seed002_wing (seed 2) through five node banks: plain KF (nominal calm R), plain
KF given the turbulence R, adaptive R + fading on P (the paper's AKF, fading added to P), adaptive
R only, and the AKF with the literal S J S' fading. Printed per node: the adapted R
(1 sigma) in calm air and in the turbulence windows (true vibration: 0.3 / 1.2 arcmin, rate about
0.19 / 0.76 deg/s), NEES (9 dof: misalignment, flexure angle, lever arm) and heading RMSE in calm
air and in turbulence, and per flight segment.

Usage: .venv/bin/python benchmarks/seed002_adaptive_breakdown.py [--seed 2]
"""

from __future__ import annotations

import argparse

import numpy as np

from fednav.service.config import TransferAlignmentConfig as T
from fednav.simulators import transfer_eval as te
from fednav.simulators.scenario import load_scenario

SEGMENTS = [(60, 100), (100, 160), (160, 220), (220, 260), (260, 300)]


def main() -> int:
    ap = argparse.ArgumentParser()
    ap.add_argument("--seed", type=int, default=2)
    args = ap.parse_args()
    sc = load_scenario("seed002_wing")
    v = {"r_vel_vibration": True}  # the scenario's nominal R (calm-air vibration, node velocity too)
    cfgs = [
        T(name="kf", filter="kf", **v),
        T(name="kf_turbR", filter="kf", r_att_arcmin=1.2, r_rate_dps=0.76, **v),
        T(name="akf", filter="akf", fading=True, **v),
        T(name="akf_r", filter="akf", fading=False, **v),
        T(name="akf_scaled", filter="akf", fading=True, fading_form="scaled", **v),
    ]
    r = te.run_once(sc, cfgs, args.seed)
    t = r["kf"]["t"]
    turb = np.zeros_like(t, dtype=bool)
    for t0, t1 in sc.wing.turbulence:
        turb |= (t > t0 + 2.0) & (t < t1 - 2.0)
    calm = ~turb & (t > 60.0)
    scale = np.array([3437.75, 1e3, 57.2958])  # arcmin, mm/s, deg/s (velocity: the forward axis)
    for c in cfgs:
        o = r[c.name]
        R = np.sqrt(o["R"])[:, :, [0, 4, 6]] * scale
        print(f"{c.name}: R 1-sigma per node [att arcmin, vel mm/s, rate deg/s]")
        print("   calm ", np.round(R[calm].mean(0), 3).tolist())
        print("   turb ", np.round(R[turb].mean(0), 3).tolist())
        for name, sel in (("calm", calm), ("turbulence", turb)):
            nees = np.nanmean(o["nees"][sel], 0).round(1)
            head = np.degrees(np.sqrt(np.mean(o["head"][sel] ** 2, 0))).round(4)
            lever = np.sqrt(np.mean(np.sum(o["lever"][sel] ** 2, axis=-1), 0)).round(4)
            print(f"   {name:<11} NEES {nees}  heading RMSE deg {head}  lever arm RMSE m {lever}")
        for s0, s1 in SEGMENTS:
            sel = (t >= s0) & (t < s1)
            nees = np.nanmean(o["nees"][sel], 0).round(1)
            head = np.degrees(np.sqrt(np.mean(o["head"][sel] ** 2, 0))).round(4)
            print(f"   {s0:>3}-{s1:<3} s   NEES {nees}  heading RMSE deg {head}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
