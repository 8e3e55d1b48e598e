"""Consistency of the loosely coupled filter on REAL receiver fixes (docs/own_data.md, "Consistency
on real fixes"; issue 10, deliverable 3).

``python -m fednav.simulators.real_fix_eval DIR [--json out.json]`` on the Wuhan 2015 RINEX data
(``DIR/*.??o`` + ``*.??n``, GPS, 1 Hz, static start and static end):

1. Real fixes: per epoch, the weighted least-squares single-point solution of ``simulators.rinex_eval``
   (the existing solver ``solve_position`` with the service's Saastamoinen troposphere, sigma / sin E
   weights, 10 deg mask) and the Doppler velocity by ``solve_velocity`` at that position. Their
   covariance is the solver's ``(H' W H)^-1`` times the a posteriori unit-weight variance
   ``sigma0^2 = sum(w r^2) / (n - 4)`` pooled over the whole file (one per file, as a receiver's
   residual-based sigma: per-epoch values with 2-4 degrees of freedom scatter by 2x); the velocity
   sigma uses the same geometry with the range rates' pooled sigma0. East/north/up sigmas go into
   ``GnssFix.pos_std_enu_m`` / ``vel_std_enu_mps``.
2. A stationary simulated IMU (noise-free angle increments = earth rate, velocity increments =
   normal gravity up; body axes = ENU): the antenna did not move in the static parts, so this IS
   the true IMU output, and no IMU error is simulated. The filter assumes the ``industrial_mems``
   grade (``--imu-grade``); with a noise-free IMU the grade only sets the filter's process noise,
   i.e. how fast it forgets old fixes. With the GM states it barely matters (the correlated error
   is modelled and the Doppler velocity, sigma ~1 cm/s, carries the position between fixes); fixes
   fused as independent are averaged the longer the better the assumed IMU, so the white filter
   is the more overconfident the better the grade (measured, docs/own_data.md).
3. The unmodified ``LooselyCoupled`` pipeline, started at the first fix of each static part (its
   sigma as the initial position sigma), without Gauss-Markov states and with them for several
   correlation times.
4. Per static part, the reference is that part's mean WLS position (there is no ground truth): the
   error is estimate minus mean; reported per axis: RMS error, RMS reported sigma, their ratio, and
   the mean 3-D position NEES / 3, over the epochs after the first ``SKIP_S`` seconds of the part.
   The mean absorbs the part's constant error, so the errors are errors about the mean; a filter
   whose sigma also covers a constant offset looks underconfident against it.

The fixes' time correlation is measured too: the autocorrelation of each axis' deviation from the
part mean and the lag where it falls below 1/e.
"""

from __future__ import annotations

import argparse
import json
import math
import sys
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from fednav.service import earth
from fednav.service.config import GnssCorrelatedError, ImuModel, LooselyCoupledConfig
from fednav.service.estimation.measurements import atmosphere as atm
from fednav.service.estimation.snapshot import solve_position, solve_velocity
from fednav.service.ins.alignment import InitStd
from fednav.service.ins.mechanisation import NavState
from fednav.service.messages import GnssFix
from fednav.service.pipelines.loosely_coupled import LooselyCoupled
from fednav.simulators.gnss.rinex_raw import iter_gnss_raw
from fednav.simulators.rinex_eval import enu, find_files, spp, static_segments

MASK_DEG = 10.0
SKIP_S = 60.0  # the filter's first minute of each part (initial convergence) is left out
IMU_RATE_HZ = 10.0
CORRELATION_TIMES_S = (10.0, 30.0, 100.0, 300.0)


@dataclass
class RealFixes:
    t: np.ndarray  # (E,) GPS s
    pos_ecef_m: np.ndarray  # (E, 3), NaN where unsolved
    unit_cov_enu: np.ndarray  # (E, 3, 3) (H' W H)^-1 of the position, ENU, per unit-weight variance
    vel_enu_mps: np.ndarray  # (E, 3)
    sigma0_pos_m: float  # pooled a posteriori unit-weight sigma of the pseudoranges, m (zenith)
    sigma0_vel_mps: float  # the same for the range rates, m/s
    seg: tuple[tuple[float, float], tuple[float, float]]  # static start, static end (GPS s)

    def pos_std_enu_m(self, scale: float = 1.0) -> np.ndarray:
        return scale * self.sigma0_pos_m * np.sqrt(np.diagonal(self.unit_cov_enu, axis1=1, axis2=2))

    def vel_std_enu_mps(self) -> np.ndarray:
        return self.sigma0_vel_mps * np.sqrt(np.diagonal(self.unit_cov_enu, axis1=1, axis2=2))


def real_fixes(folder: str | Path) -> RealFixes:
    """Per-epoch WLS position + Doppler velocity with the service's corrections (module docstring)."""
    obs_path, nav_path = find_files(Path(folder))
    msgs = [m for _, m in iter_gnss_raw(obs_path, nav_path)]
    s = spp(msgs)
    seg = static_segments(s.t, np.linalg.norm(s.vel_ecef_mps, axis=1))
    x0 = s.pos_ecef_m[np.flatnonzero(np.all(np.isfinite(s.pos_ecef_m), axis=1))[0]]
    llh = earth.ecef_to_llh(x0)
    c_en = earth.mat_en(float(llh[0]), float(llh[1]))
    zenith = atm.saastamoinen_zenith_m(float(llh[0]), float(llh[2]))

    def delay(rx, sat_rx):  # as simulators.rinex_eval.ours_wls
        d = sat_rx - rx
        el = np.arcsin(np.clip((d @ c_en)[:, 2] / np.linalg.norm(d, axis=1), -1.0, 1.0))
        return zenith * atm.tropo_mapping(np.maximum(el, 0.0))

    n_ep = len(msgs)
    pos = np.full((n_ep, 3), np.nan)
    vel = np.full((n_ep, 3), np.nan)
    cov = np.full((n_ep, 3, 3), np.nan)
    wrr_p = wrr_v = 0.0
    dof = 0
    for e, m in enumerate(msgs):
        sp = np.array([q.sat_pos_ecef_m for q in m.sats]).reshape(-1, 3)
        if len(sp) < 5:
            continue
        d = sp - x0
        el = np.arcsin((d @ c_en)[:, 2] / np.linalg.norm(d, axis=1))
        use = el >= math.radians(MASK_DEG)
        if use.sum() < 5:  # 4 unknowns + one redundant range for the residual-based sigma
            continue
        w = np.sin(el[use]) ** 2
        sol = solve_position(
            np.array([q.pseudorange_m for q in m.sats])[use],
            sp[use],
            np.array([q.sat_clock_m for q in m.sats])[use],
            x0_ecef_m=x0,
            weights=w,
            delay_fn=delay,
        )
        if not sol.converged:
            continue
        v = solve_velocity(
            np.array([q.range_rate_mps for q in m.sats])[use],
            sol.pos_ecef_m,
            sp[use],
            np.array([q.sat_vel_ecef_mps for q in m.sats])[use],
            np.array([q.sat_clock_drift_mps for q in m.sats])[use],
            weights=w,
        )
        pos[e] = sol.pos_ecef_m
        vel[e] = v.vel_ecef_mps @ c_en
        cov[e] = c_en.T @ sol.cov[:3, :3] @ c_en
        wrr_p += float(np.sum(w * sol.residuals_m**2))
        wrr_v += float(np.sum(w * v.residuals_mps**2))
        dof += int(use.sum()) - 4
    return RealFixes(s.t, pos, cov, vel, math.sqrt(wrr_p / dof), math.sqrt(wrr_v / dof), seg)


def correlation_time_s(dev: np.ndarray, dt_s: float = 1.0) -> tuple[float, np.ndarray]:
    """Lag (s) where the sample autocorrelation of ``dev`` (mean removed) first falls below 1/e,
    and the autocorrelation itself."""
    x = dev - dev.mean()
    ac = np.correlate(x, x, "full")[len(x) - 1 :] / float(x @ x)
    below = np.flatnonzero(ac < 1.0 / math.e)
    return (float(below[0]) * dt_s if len(below) else float("inf")), ac


def run_part(
    fx: RealFixes,
    part: tuple[float, float],
    gm: GnssCorrelatedError | None,
    imu: ImuModel,
    sigma_scale: float = 1.0,
) -> dict:
    """The loosely coupled pipeline over one static part; statistics against the part's mean."""
    sel = np.flatnonzero((fx.t >= part[0]) & (fx.t <= part[1]) & np.isfinite(fx.pos_ecef_m[:, 0]))
    ref = fx.pos_ecef_m[sel].mean(axis=0)
    p_std = fx.pos_std_enu_m(sigma_scale)
    v_std = fx.vel_std_enu_mps()
    cfg = LooselyCoupledConfig(name="lc_real", gnss_correlated_error=gm)
    pipe = LooselyCoupled(cfg, imu, 1.0)
    llh0 = earth.ecef_to_llh(fx.pos_ecef_m[sel[0]])
    lat, lon, h = (float(v) for v in llh0)
    pipe.start(
        NavState(fx.t[sel[0]], lat, lon, h, np.zeros(3), np.array([1.0, 0.0, 0.0, 0.0])),
        InitStd(p_std[sel[0]], np.full(3, 0.1), np.radians([1.0, 1.0, 5.0])),
    )
    g = earth.gravity_normal(lat, h)
    w_ie = np.array([0.0, earth.OMEGA_IE_RPS * math.cos(lat), earth.OMEGA_IE_RPS * math.sin(lat)])
    dt = 1.0 / IMU_RATE_HZ
    t_ins = fx.t[sel[0]]
    err, sig2, nees = [], [], []
    for e in sel:
        while t_ins + 0.5 * dt < fx.t[e]:
            t_ins += dt
            pipe.push_imu(w_ie * dt, np.array([0.0, 0.0, g * dt]), dt, t_ins)
        la, lo, hh = earth.ecef_to_llh(fx.pos_ecef_m[e])
        fix = GnssFix(
            t=float(fx.t[e]),
            lat_deg=math.degrees(la),
            lon_deg=math.degrees(lo),
            height_m=float(hh),
            vel_enu_mps=tuple(float(v) for v in fx.vel_enu_mps[e]),
            pos_std_enu_m=tuple(float(v) for v in p_std[e]),
            vel_std_enu_mps=tuple(float(v) for v in v_std[e]),
        )
        pipe.apply("gnss_fix", "wls", fix)
        if fx.t[e] < fx.t[sel[0]] + SKIP_S:
            continue
        est = pipe.estimate()
        n = est.nav
        d = enu(earth.llh_to_ecef(np.array([n.lat_rad, n.lon_rad, n.h_m]))[None, :], ref)[0]
        P = est.P9[:3, :3]
        err.append(d)
        sig2.append(np.diag(P))
        nees.append(float(d @ np.linalg.solve(P, d)))
    err_a, sig2_a = np.array(err), np.array(sig2)
    rms_e = np.sqrt(np.mean(err_a**2, axis=0))
    rms_s = np.sqrt(np.mean(sig2_a, axis=0))
    return {
        "epochs": len(err),
        "rms_err_enu_m": rms_e.tolist(),
        "rms_sigma_enu_m": rms_s.tolist(),
        "ratio_enu": (rms_e / rms_s).tolist(),
        "nees_per_dof": float(np.mean(nees)) / 3.0,
        "refused": int(sum(pipe.screened.values())),
    }


def evaluate(
    folder: str | Path,
    taus_s: tuple[float, ...] = CORRELATION_TIMES_S,
    imu_grade: str = "industrial_mems",
    fx: RealFixes | None = None,
    calibrated: bool = False,
    white: bool = True,
) -> dict:
    """Fix statistics per static part and the filter's consistency rows (module docstring).

    ``calibrated``: the fixes' sigmas are scaled by one factor k so that on the static START they
    match the fixes' scatter about its mean (k = mean over E/N/U of scatter / RMS sigma); the static
    END is then an independent check. Without it the sigmas are the solver's (k = 1)."""
    fx = real_fixes(folder) if fx is None else fx
    imu = ImuModel(grade=imu_grade)
    k = 1.0
    if calibrated:
        a, b = fx.seg[0]
        sel = (fx.t >= a) & (fx.t <= b) & np.isfinite(fx.pos_ecef_m[:, 0])
        dev = enu(fx.pos_ecef_m[sel], fx.pos_ecef_m[sel].mean(axis=0))
        k = float(np.mean(dev.std(axis=0) / np.sqrt(np.mean(fx.pos_std_enu_m()[sel] ** 2, axis=0))))
    med_std = np.nanmedian(fx.pos_std_enu_m(k), axis=0)
    out: dict = {
        "data": Path(folder).name,
        "imu_grade": imu_grade,
        "sigma_scale": k,
        "sigma0_pos_m": fx.sigma0_pos_m,
        "sigma0_vel_mps": fx.sigma0_vel_mps,
        "fix_sigma_median_enu_m": med_std.tolist(),
        "parts": {},
    }
    # the correlated part: the fix sigma's share that is correlated from one epoch to the next,
    # from the lag-1 autocorrelation of the static start (all of it here: rho_1 ~ 0.97)
    for name, part in zip(("static_start", "static_end"), fx.seg, strict=True):
        sel = (fx.t >= part[0]) & (fx.t <= part[1]) & np.isfinite(fx.pos_ecef_m[:, 0])
        dev = enu(fx.pos_ecef_m[sel], fx.pos_ecef_m[sel].mean(axis=0))
        taus, rho1 = [], []
        for ax in range(3):
            tau, ac = correlation_time_s(dev[:, ax])
            taus.append(tau)
            rho1.append(float(ac[1]))
        std_fix = fx.pos_std_enu_m(k)[sel]
        out["parts"][name] = {
            "span_s": [float(part[0] - fx.t[0]), float(part[1] - fx.t[0])],
            "fix_scatter_enu_m": dev.std(axis=0).tolist(),
            "fix_rms_sigma_enu_m": np.sqrt(np.mean(std_fix**2, axis=0)).tolist(),
            "fix_correlation_time_enu_s": taus,
            "fix_lag1_autocorrelation_enu": rho1,
            "rows": {},
        }
    rho1 = float(np.mean(out["parts"]["static_start"]["fix_lag1_autocorrelation_enu"]))
    gm_sigma = tuple(float(v) for v in math.sqrt(max(rho1, 0.0)) * med_std)
    out["gm_sigma_enu_m"] = list(gm_sigma)
    configs: list[tuple[str, GnssCorrelatedError | None]] = [("white (no GM states)", None)] if white else []
    configs += [
        (f"GM tau {tau:g} s", GnssCorrelatedError(sigma_enu_m=gm_sigma, correlation_time_s=tau))
        for tau in taus_s
    ]
    for name, part in zip(("static_start", "static_end"), fx.seg, strict=True):
        for label, gm in configs:
            out["parts"][name]["rows"][label] = run_part(fx, part, gm, imu, k)
    return out


def format_result(r: dict) -> str:
    f3 = lambda v: "/".join(f"{x:.2f}" for x in v)  # noqa: E731
    lines = [
        f"{r['data']}: filter IMU grade {r['imu_grade']}; fix sigma scale {r['sigma_scale']:.3f}; "
        f"pooled sigma0 {r['sigma0_pos_m']:.2f} m "
        f"(pseudorange, zenith), {r['sigma0_vel_mps']:.4f} m/s (range rate); median fix sigma E/N/U "
        f"{f3(r['fix_sigma_median_enu_m'])} m; GM sigma E/N/U {f3(r['gm_sigma_enu_m'])} m",
    ]
    for name, p in r["parts"].items():
        lines += [
            "",
            f"{name} ({p['span_s'][0]:.0f}-{p['span_s'][1]:.0f} s): fixes scatter E/N/U "
            f"{f3(p['fix_scatter_enu_m'])} m, their RMS sigma {f3(p['fix_rms_sigma_enu_m'])} m, "
            f"correlation time (1/e) {f3(p['fix_correlation_time_enu_s'])} s, "
            f"lag-1 autocorrelation {f3(p['fix_lag1_autocorrelation_enu'])}",
            "| filter | RMS err E/N/U m | RMS sigma E/N/U m | err/sigma E/N/U | NEES/3 | epochs |",
            "|---|---|---|---|---|---|",
        ]
        for label, row in p["rows"].items():
            lines.append(
                f"| {label} | {f3(row['rms_err_enu_m'])} | {f3(row['rms_sigma_enu_m'])} | "
                f"{f3(row['ratio_enu'])} | {row['nees_per_dof']:.2f} | {row['epochs']} |"
            )
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("folder", help="RINEX folder (e.g. ../shared/data/real/psins_wuhan_2015)")
    ap.add_argument("--imu-grade", default="industrial_mems")
    ap.add_argument("--tau", type=float, nargs="+", default=list(CORRELATION_TIMES_S))
    ap.add_argument(
        "--calibrated",
        action="store_true",
        help="scale the fix sigmas to the static start's scatter (the static end is the check)",
    )
    ap.add_argument("--json", default=None, help="also write the figures to this file")
    args = ap.parse_args(argv)
    r = evaluate(args.folder, tuple(args.tau), args.imu_grade, calibrated=args.calibrated)
    print(format_result(r))
    if args.json:
        with open(args.json, "w") as f:
            json.dump(r, f, indent=2)
    return 0


if __name__ == "__main__":
    sys.exit(main())
