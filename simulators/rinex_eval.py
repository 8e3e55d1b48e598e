"""Tightly coupled raw-GNSS pipeline on real RINEX data beside a least-squares peer (docs/real_rinex.md).

``fednav-sim rinex2raw OBS NAV [NAV...] --out file.jsonl``: GnssRaw epochs as JSON lines.
``fednav-sim eval-rinex DIR [--json]``: the table of docs/real_rinex.md on ``DIR/*.??o`` + ``*.??n``.

Ours: the service's :class:`~service.pipelines.tightly_coupled.TightlyCoupled` pipeline (raw-GNSS
measurement model with troposphere, broadcast ionosphere when the navigation header has it,
elevation weighting and mask; MHSS integrity with sub-filters) in a GNSS-only mode: the data has no
IMU, so the pipeline is fed a *stationary* IMU (angle increments = earth rate, velocity increments =
normal gravity, body axes = ENU) and told the IMU is very poor (velocity random walk
``GNSS_ONLY_VRW_UG`` ~ 1 m/s/sqrt(s), i.e. vehicle accelerations of ~1 m/s^2 are process noise). The
INS then only carries position with the filter's velocity, which the Doppler range rates observe:
a constant-velocity GNSS filter built from the unmodified pipeline.

Peer: gnss-lib-py's weighted least squares (``gnss_lib_py.algorithms.snapshot.solve_wls``, equal
weights) on the same epochs and pseudoranges, with gnss-lib-py's own broadcast orbit and clock
(``gnss_lib_py.utils.sv_models.find_sv_states``: IS-GPS-200 orbit, clock polynomial, relativistic
term and T_GD) and its Earth-rotation correction. The files are read by our readers and handed to
gnss-lib-py as NavData: its RINEX path (georinex 1.16) fails on these files (RINEX 2 observation
file: an xarray dtype promotion error; navigation file: it keeps one record per satellite,
"duplicate times detected").
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
from fednav.service.config import ClockModel, ImuModel, TightlyCoupledConfig
from fednav.service.estimation.snapshot import solve_position, solve_velocity
from fednav.service.ins.alignment import InitStd
from fednav.service.ins.mechanisation import NavState
from fednav.service.messages import GnssRaw, Integrity
from fednav.service.pipelines.tightly_coupled import TightlyCoupled
from fednav.simulators.gnss.rinex import read_rinex2_nav
from fednav.simulators.gnss.rinex_raw import ConversionStats, iter_gnss_raw, read_observations

GNSS_ONLY_VRW_UG = 1.0e5  # 1e5 ug/sqrt(Hz) = 0.98 m/s/sqrt(s): the vehicle's accelerations as noise
STATIC_SPEED_MPS = 0.3  # Doppler speed below which an epoch counts as at rest
STATIC_MARGIN_S = 10.0  # epochs this close to a motion are left out of the static parts


def find_files(folder: Path) -> tuple[Path, Path]:
    obs = sorted(p for p in folder.iterdir() if p.suffix[-1:].lower() == "o")
    nav = sorted(p for p in folder.iterdir() if p.suffix[-1:].lower() in ("n", "p"))
    if not obs or not nav:
        raise FileNotFoundError(f"{folder}: needs a RINEX observation (*.??o) and navigation (*.??n) file")
    return obs[0], nav[0]


# --- our epoch-wise solution (static detection, initial state) ------------------------------------------
@dataclass(frozen=True)
class Spp:
    t: np.ndarray  # (E,)
    pos_ecef_m: np.ndarray  # (E, 3), NaN where unsolved
    vel_ecef_mps: np.ndarray  # (E, 3)


def spp(msgs: list[GnssRaw]) -> Spp:
    """Unweighted single-point position + Doppler velocity per epoch (the simulator's solvers)."""
    t = np.array([m.t for m in msgs])
    pos = np.full((len(msgs), 3), np.nan)
    vel = np.full((len(msgs), 3), np.nan)
    x0 = None
    for e, m in enumerate(msgs):
        if len(m.sats) < 5:
            continue
        pr = np.array([s.pseudorange_m for s in m.sats])
        sp = np.array([s.sat_pos_ecef_m for s in m.sats])
        sv = np.array([s.sat_vel_ecef_mps for s in m.sats])
        sol = solve_position(pr, sp, np.array([s.sat_clock_m for s in m.sats]), x0_ecef_m=x0)
        if not sol.converged:
            continue
        x0 = pos[e] = sol.pos_ecef_m
        rr = np.array([s.range_rate_mps for s in m.sats])
        vel[e] = solve_velocity(
            rr, sol.pos_ecef_m, sp, sv, np.array([s.sat_clock_drift_mps for s in m.sats])
        ).vel_ecef_mps
    return Spp(t, pos, vel)


def static_segments(t: np.ndarray, speed_mps: np.ndarray) -> tuple[tuple[float, float], tuple[float, float]]:
    """(start, end) of the static beginning and static end: before the first / after the last epoch
    moving faster than ``STATIC_SPEED_MPS``, less ``STATIC_MARGIN_S``."""
    moving = np.flatnonzero(np.nan_to_num(speed_mps, nan=0.0) > STATIC_SPEED_MPS)
    if len(moving) == 0:
        return (t[0], t[-1]), (t[-1], t[-1])
    return (t[0], t[moving[0]] - STATIC_MARGIN_S), (t[moving[-1]] + STATIC_MARGIN_S, t[-1])


# --- peer ------------------------------------------------------------------------------------------------
def peer_wls(
    obs_path: Path, nav_path: Path, ref_ecef_m: np.ndarray, mask_deg: float = 10.0
) -> tuple[np.ndarray, np.ndarray] | None:
    """gnss-lib-py WLS per epoch -> (t (E,), ECEF (E, 3)); None when gnss-lib-py is not installed.

    Same elevation mask and weights (sin^2 E, i.e. sigma / sin E) as ours, elevations from
    ``ref_ecef_m``; the troposphere is gnss-lib-py's own model (``gnss_models._calculate_tropo_delay``,
    exponential height profile / (sin E + c2)); no ionosphere (the navigation file has no Klobuchar
    coefficients)."""
    try:
        from gnss_lib_py.algorithms.snapshot import solve_wls
        from gnss_lib_py.navdata.navdata import NavData
        from gnss_lib_py.utils.gnss_models import _calculate_tropo_delay
        from gnss_lib_py.utils.sv_models import find_sv_states
    except ImportError:
        return None
    obs = read_observations(obs_path)
    eph = read_rinex2_nav(nav_path)
    code = "GC1" if "GC1" in obs.types else "GC1C"
    pr = obs.values[:, :, obs.types.index(code)]
    ee, ss = np.nonzero(np.isfinite(pr) & np.array([s[0] == "G" for s in obs.ids])[None, :])
    t_rx = obs.t_gps_s[ee]
    prn = np.array([int(obs.ids[s][1:]) for s in ss])
    rec = np.full(len(ee), -1)
    healthy = eph.params["health"] == 0
    for p in np.unique(prn):
        rows = np.flatnonzero((eph.prn == p) & healthy)
        if len(rows) == 0:
            continue
        sel = prn == p
        age = np.abs(t_rx[sel, None] - eph.toe_gps_s[rows][None, :])
        rec[np.flatnonzero(sel)] = rows[np.argmin(age, axis=1)]
    ok = rec >= 0
    ee, prn, rec, t_rx = ee[ok], prn[ok], rec[ok], t_rx[ok]
    p = eph.params
    ephem = NavData()
    ephem["gnss_id"] = np.array(["gps"] * len(rec), dtype=object)
    ephem["sv_id"] = prn
    names = {
        "gps_week": "week", "t_oe": "toe_sow", "e": "e", "omega": "omega", "Omega_0": "omega0",
        "OmegaDot": "omega_dot", "sqrtA": "sqrt_a", "deltaN": "delta_n", "IDOT": "idot", "i_0": "i0",
        "C_is": "cis", "C_ic": "cic", "C_rs": "crs", "C_rc": "crc", "C_uc": "cuc", "C_us": "cus",
        "M_0": "m0", "SVclockBias": "af0", "SVclockDrift": "af1", "SVclockDriftRate": "af2", "TGD": "tgd",
    }  # fmt: skip
    for glp_name, ours in names.items():
        ephem[glp_name] = p[ours][rec]
    ephem["t_oc"] = np.mod(eph.toc_gps_s[rec], 604800.0)
    prv = pr[ee, [obs.ids.index(f"G{q:02d}") for q in prn]]
    gps_millis_tx = 1000.0 * (t_rx - prv / 299792458.0)
    sv = find_sv_states(gps_millis_tx, ephem)
    sat = np.stack([sv["x_sv_m"], sv["y_sv_m"], sv["z_sv_m"]], -1)
    llh = earth.ecef_to_llh(ref_ecef_m)
    los = sat - ref_ecef_m
    up = (los @ earth.mat_en(float(llh[0]), float(llh[1])))[:, 2] / np.linalg.norm(los, axis=1)
    el = np.arcsin(np.clip(up, -1.0, 1.0))
    keep = el >= math.radians(mask_deg)
    tropo = np.asarray(_calculate_tropo_delay(None, ref_ecef_m, sv_posvel=sv)).reshape(-1)
    meas = NavData()
    meas["gps_millis"] = 1000.0 * t_rx[keep]
    for k, axis in enumerate("xyz"):
        meas[f"{axis}_sv_m"] = sat[keep, k]
    meas["corr_pr_m"] = (prv + sv["b_sv_m"] - tropo)[keep]
    meas["weights"] = np.sin(el[keep]) ** 2
    est = solve_wls(meas, weight_type="weights")
    return np.asarray(est["gps_millis"]) / 1000.0, np.stack(
        [est["x_rx_wls_m"], est["y_rx_wls_m"], est["z_rx_wls_m"]], -1
    )


# --- ours ------------------------------------------------------------------------------------------------
def ours_wls(
    msgs: list[GnssRaw], x0_ecef_m: np.ndarray, mask_deg: float = 10.0
) -> tuple[np.ndarray, np.ndarray]:
    """Epoch-wise weighted least squares with the service's corrections (Saastamoinen x DO-229
    mapping, sigma / sin E, mask), no filtering: separates the model from the filter's smoothing."""
    from fednav.service.estimation.measurements import atmosphere as atm

    llh = earth.ecef_to_llh(x0_ecef_m)
    c_en = earth.mat_en(float(llh[0]), float(llh[1]))
    zenith = atm.saastamoinen_zenith_m(float(llh[0]), float(llh[2]))

    def delay(rx, sat_rx):
        d = sat_rx - rx
        el = np.arcsin(np.clip((d @ c_en)[:, 2] / np.linalg.norm(d, axis=1), -1.0, 1.0))
        return zenith * atm.tropo_mapping(np.maximum(el, 0.0))

    t = np.array([m.t for m in msgs])
    out = np.full((len(msgs), 3), np.nan)
    for e, m in enumerate(msgs):
        sp = np.array([s.sat_pos_ecef_m for s in m.sats]).reshape(-1, 3)
        if len(sp) < 4:
            continue
        d = sp - x0_ecef_m
        el = np.arcsin((d @ c_en)[:, 2] / np.linalg.norm(d, axis=1))
        use = el >= math.radians(mask_deg)
        if use.sum() < 4:
            continue
        pr = np.array([s.pseudorange_m for s in m.sats])[use]
        ck = np.array([s.sat_clock_m for s in m.sats])[use]
        sol = solve_position(
            pr, sp[use], ck, x0_ecef_m=x0_ecef_m, weights=np.sin(el[use]) ** 2, delay_fn=delay
        )
        if sol.converged:
            out[e] = sol.pos_ecef_m
    return t, out


def tc_config(**over) -> TightlyCoupledConfig:
    base = dict(
        name="tc_rinex",
        clock=ClockModel(init_bias_std_m=100.0, init_drift_std_mps=10.0),
        integrity=True,
        sub_sub_filters=True,
        exclusion=True,
        troposphere=True,
        ionosphere=True,
        elevation_weighting=True,
        elevation_mask_deg=10.0,
    )
    base.update(over)
    return TightlyCoupledConfig(**base)


def gnss_only_imu() -> ImuModel:
    return ImuModel(gyro_bias_dph=0.01, accel_bias_ug=10.0, arw_dpsh=0.01, vrw_ugpsHz=GNSS_ONLY_VRW_UG)


@dataclass
class OursResult:
    t: np.ndarray
    pos_ecef_m: np.ndarray
    hpl_m: np.ndarray
    vpl_m: np.ndarray
    alarms: int
    detections: int
    excluded_epochs: dict[str, int]


def run_ours(msgs: list[GnssRaw], x0_ecef_m: np.ndarray, imu_rate_hz: float = 10.0, **cfg) -> OursResult:
    """The tightly coupled pipeline in GNSS-only mode (module docstring) over all epochs."""
    pipe = TightlyCoupled(tc_config(**cfg), gnss_only_imu(), 1.0)
    llh0 = earth.ecef_to_llh(x0_ecef_m)
    lat, lon, h = (float(v) for v in llh0)
    nav = NavState(msgs[0].t, lat, lon, h, np.zeros(3), np.array([1.0, 0.0, 0.0, 0.0]))
    pipe.start(nav, InitStd(np.full(3, 30.0), np.full(3, 1.0), np.radians([1.0, 1.0, 5.0])))
    g = earth.gravity_normal(lat, h)
    w_ie = np.array([0.0, earth.OMEGA_IE_RPS * math.cos(lat), earth.OMEGA_IE_RPS * math.sin(lat)])
    dt = 1.0 / imu_rate_hz
    t_ins = msgs[0].t
    out_t, out_p, hpl, vpl = [], [], [], []
    alarms = detections = 0
    excluded: dict[str, int] = {}
    for m in msgs:
        while t_ins + 0.5 * dt < m.t:
            t_ins += dt
            pipe.push_imu(w_ie * dt, np.array([0.0, 0.0, g * dt]), dt, t_ins)
        extra = pipe.apply("gnss_raw", "rinex", m)
        est = pipe.estimate().nav
        out_t.append(m.t)
        out_p.append(earth.llh_to_ecef(np.array([est.lat_rad, est.lon_rad, est.h_m])))
        integ = [x for x in extra if isinstance(x, Integrity)]
        hpl.append(integ[0].hpl_m if integ else np.nan)
        vpl.append(integ[0].vpl_m if integ else np.nan)
        if integ:
            alarms += int(integ[0].alarm)
            detections += int(integ[0].detected)
            for sid in integ[0].excluded:
                excluded[sid] = excluded.get(sid, 0) + 1
    return OursResult(
        np.array(out_t), np.array(out_p), np.array(hpl), np.array(vpl), alarms, detections, excluded
    )


# --- statistics ------------------------------------------------------------------------------------------
def enu(pos_ecef_m: np.ndarray, ref_ecef_m: np.ndarray) -> np.ndarray:
    llh = earth.ecef_to_llh(ref_ecef_m)
    return (pos_ecef_m - ref_ecef_m) @ earth.mat_en(float(llh[0]), float(llh[1]))


def scatter(pos_ecef_m: np.ndarray) -> dict[str, float]:
    """Standard deviation about the mean, E/N/U and horizontal (rms of the 2-D deviation), m."""
    p = pos_ecef_m[np.all(np.isfinite(pos_ecef_m), axis=1)]
    d = enu(p, p.mean(axis=0))
    d = d - d.mean(axis=0)
    s = np.sqrt(np.mean(d**2, axis=0))
    return {
        "E": float(s[0]),
        "N": float(s[1]),
        "U": float(s[2]),
        "H": float(math.hypot(s[0], s[1])),
        "n": len(p),
    }


def difference(a_ecef: np.ndarray, b_ecef: np.ndarray, ref_ecef: np.ndarray) -> dict[str, float]:
    """RMS and max of a - b in ENU (E/N/U rms, H rms, H max), m."""
    ok = np.all(np.isfinite(a_ecef), axis=1) & np.all(np.isfinite(b_ecef), axis=1)
    d = enu(a_ecef[ok], ref_ecef) - enu(b_ecef[ok], ref_ecef)
    r = np.sqrt(np.mean(d**2, axis=0))
    return {
        "E": float(r[0]), "N": float(r[1]), "U": float(r[2]), "H": float(math.hypot(r[0], r[1])),
        "H_max": float(np.max(np.hypot(d[:, 0], d[:, 1]))), "n": int(ok.sum()),
    }  # fmt: skip


def evaluate_rinex(folder: str | Path, stop_after_s: float | None = None, **cfg) -> dict:
    """The table of docs/real_rinex.md; ``cfg`` overrides the pipeline configuration (``tc_config``)."""
    folder = Path(folder)
    obs_path, nav_path = find_files(folder)
    stats = ConversionStats()
    msgs = [m for _, m in iter_gnss_raw(obs_path, nav_path, stats=stats)]
    if stop_after_s is not None:
        msgs = [m for m in msgs if m.t <= msgs[0].t + stop_after_s]
    s = spp(msgs)
    speed = np.linalg.norm(s.vel_ecef_mps, axis=1)
    seg_a, seg_b = static_segments(s.t, speed)
    x0 = s.pos_ecef_m[np.flatnonzero(np.all(np.isfinite(s.pos_ecef_m), axis=1))[0]]
    ours = run_ours(msgs, x0, **cfg)
    peer = peer_wls(obs_path, nav_path, x0)
    snap = ours_wls(msgs, x0)
    result: dict = {
        "data": str(folder.name),
        "epochs": len(msgs),
        "observations": stats.observations,
        "dropped": stats.dropped,
        "static_start_s": [float(seg_a[0] - s.t[0]), float(seg_a[1] - s.t[0])],
        "static_end_s": [float(seg_b[0] - s.t[0]), float(seg_b[1] - s.t[0])],
        "klobuchar_in_nav": bool(msgs[0].iono),
    }
    warm = ours.t >= ours.t[0] + 60.0  # the filter's first minute (clock and position converge) is left out
    for key, (a, b) in (("static_start", seg_a), ("static_end", seg_b)):
        sel_o = (ours.t >= a) & (ours.t <= b) & warm
        result[f"ours_{key}"] = scatter(ours.pos_ecef_m[sel_o]) if sel_o.sum() > 10 else None
        sel_s = (snap[0] >= a) & (snap[0] <= b)
        result[f"ours_wls_{key}"] = scatter(snap[1][sel_s]) if sel_s.sum() > 10 else None
        if peer is not None:
            sel_p = (peer[0] >= a) & (peer[0] <= b)
            result[f"peer_{key}"] = scatter(peer[1][sel_p]) if sel_p.sum() > 10 else None
    drive = (ours.t > seg_a[1]) & (ours.t < seg_b[0])
    if peer is not None and drive.any():
        peer_at = {round(t, 3): p for t, p in zip(peer[0], peer[1], strict=True)}
        pb = np.array([peer_at.get(round(t, 3), np.full(3, np.nan)) for t in ours.t[drive]])
        result["drive_ours_minus_peer"] = difference(ours.pos_ecef_m[drive], pb, x0)
        ok = warm & np.isfinite(ours.pos_ecef_m[:, 0])
        pa = np.array([peer_at.get(round(t, 3), np.full(3, np.nan)) for t in ours.t[ok]])
        result["all_ours_minus_peer"] = difference(ours.pos_ecef_m[ok], pa, x0)
        sb = np.array([peer_at.get(round(t, 3), np.full(3, np.nan)) for t in snap[0][drive]])
        result["drive_ours_wls_minus_peer"] = difference(snap[1][drive], sb, x0)
    hp, vp = ours.hpl_m[warm], ours.vpl_m[warm]
    result["mhss"] = {
        "epochs_with_pl": int(np.isfinite(hp).sum()),
        "hpl_median_m": float(np.nanmedian(hp)),
        "hpl_p95_m": float(np.nanpercentile(hp, 95)),
        "hpl_max_m": float(np.nanmax(hp)),
        "vpl_median_m": float(np.nanmedian(vp)),
        "vpl_p95_m": float(np.nanpercentile(vp, 95)),
        "vpl_max_m": float(np.nanmax(vp)),
        "alarms": ours.alarms,
        "detections": ours.detections,
        "excluded_epochs": ours.excluded_epochs,
    }
    result["peer"] = "gnss-lib-py 1.1.0 solve_wls" if peer is not None else None
    return result


def format_result(r: dict) -> str:
    lines = [
        f"{r['data']}: {r['epochs']} epochs, {r['observations']} observations (dropped {r['dropped']}); "
        f"broadcast Klobuchar in the nav file: {'yes' if r['klobuchar_in_nav'] else 'no'}",
        f"static start {r['static_start_s'][0]:.0f}-{r['static_start_s'][1]:.0f} s, "
        f"static end {r['static_end_s'][0]:.0f}-{r['static_end_s'][1]:.0f} s (from the first epoch)",
        "",
        "| part | solution | E std m | N std m | U std m | H m | epochs |",
        "|---|---|---|---|---|---|---|",
    ]
    for key in ("static_start", "static_end"):
        for who in ("ours", "ours_wls", "peer"):
            v = r.get(f"{who}_{key}")
            if v is None:
                lines.append(f"| {key} | {who} | - | - | - | - | - |")
            else:
                cells = f"{v['E']:.2f} | {v['N']:.2f} | {v['U']:.2f} | {v['H']:.2f}"
                lines.append(f"| {key} | {who} | {cells} | {v['n']} |")
    diffs = (
        ("drive_ours_minus_peer", "drive: ours - peer"),
        ("drive_ours_wls_minus_peer", "drive: ours_wls - peer"),
        ("all_ours_minus_peer", "all after 60 s: ours - peer"),
    )
    for key, title in diffs:
        d = r.get(key)
        if d is not None:
            lines.append(
                f"| {title} | rms | {d['E']:.2f} | {d['N']:.2f} | {d['U']:.2f} | {d['H']:.2f} "
                f"(max {d['H_max']:.2f}) | {d['n']} |"
            )
    if r["peer"] is None:
        lines.append("peer skipped: gnss-lib-py not installed (pip install -e '.[peer]')")
    m = r["mhss"]
    lines += [
        "",
        f"MHSS ({m['epochs_with_pl']} epochs): HPL median {m['hpl_median_m']:.1f} m, "
        f"p95 {m['hpl_p95_m']:.1f}, "
        f"max {m['hpl_max_m']:.1f}; VPL median {m['vpl_median_m']:.1f} m, p95 {m['vpl_p95_m']:.1f}, "
        f"max {m['vpl_max_m']:.1f}; alarms {m['alarms']}, detections {m['detections']}, "
        f"epochs with an excluded satellite {m['excluded_epochs']}",
    ]
    return "\n".join(lines)


def rinex2raw(obs: str, nav: list[str], out: str, systems: str) -> int:
    stats = ConversionStats()
    with open(out, "w") as f:
        for _, msg in iter_gnss_raw(obs, nav, systems=tuple(systems), stats=stats):
            f.write(msg.model_dump_json() + "\n")
    print(f"{out}: {stats.epochs} epochs, {stats.observations} observations, dropped {stats.dropped}")
    return 0


def cli(argv: list[str]) -> int:
    ap = argparse.ArgumentParser(prog="fednav-sim")
    sub = ap.add_subparsers(dest="cmd", required=True)
    c = sub.add_parser("rinex2raw", help="RINEX 2/3 observation + navigation -> GnssRaw JSON lines")
    c.add_argument("obs")
    c.add_argument("nav", nargs="+")
    c.add_argument("--out", required=True)
    c.add_argument("--systems", default="GEC", help="system letters (default GEC)")
    e = sub.add_parser("eval-rinex", help="tightly coupled (GNSS-only mode) vs gnss-lib-py WLS on real RINEX")
    e.add_argument("folder")
    e.add_argument("--json", action="store_true")
    e.add_argument("--no-exclusion", action="store_true", help="MHSS detects and reports, excludes nothing")
    a = ap.parse_args(argv)
    if a.cmd == "rinex2raw":
        return rinex2raw(a.obs, a.nav, a.out, a.systems)
    r = evaluate_rinex(a.folder, **({"exclusion": False, "sub_sub_filters": False} if a.no_exclusion else {}))
    print(json.dumps(r, indent=2) if a.json else format_result(r))
    return 0


RINEX_COMMANDS = ("rinex2raw", "eval-rinex")

if __name__ == "__main__":
    sys.exit(cli(sys.argv[1:]))
