"""RINEX 2/3 observation + broadcast navigation files -> ``GnssRaw`` epochs (tightly coupled aiding).

:func:`iter_gnss_raw` is the one entry point (``fednav-replay`` and ``fednav-sim rinex2raw`` call
it). Per epoch and satellite it forms what ``service.estimation.measurements.gnss_raw`` expects:

- pseudorange (GPS L1 C/A ``C1``/``C1C``, Galileo E1 ``C1C``/``C1X``, BeiDou B1I ``C2I``/``C1I``)
  and range rate ``-lambda * Doppler`` (m/s);
- transmission time ``t_tx = t_rx - P / c - dt_sv(t_tx)`` iterated (IS-GPS-200N 20.3.3.3.3.1: the
  pseudorange gives the satellite's own clock reading, the clock correction turns it into system
  time; two passes converge to < 1 ps);
- satellite position/velocity at ``t_tx`` in the ECEF frame *of the transmission time* (the
  Earth-rotation (Sagnac) rotation to the reception frame is applied by the service's ranging
  model, exactly, from the geometric range: ``R3(omega_e rho / c)``), from the broadcast
  ephemeris: GPS LNAV (IS-GPS-200N Table 20-IV), Galileo (OS SIS ICD 5.1.1, same Keplerian
  algorithm with mu = 3.986004418e14), BeiDou D1/D2 (BDS-SIS-ICD-B1I 5.2.4.12: MEO/IGSO as GPS
  with the CGCS2000 constants, GEO with the extra -5 deg x-rotation and z-rotation by omega_e tk);
- satellite clock ``af0 + af1 dt + af2 dt^2 + F e sqrt(A) sin E`` (relativistic term) minus the
  single-frequency group delay: GPS ``T_GD`` (L1 C/A), BeiDou ``T_GD1`` (B1I), Galileo
  ``BGD(E1, E5b)`` (E1, I/NAV). BeiDou times (BDT = GPST - 14 s, week + 1356) are converted to
  GPS seconds;
- the broadcast ionosphere coefficients of the navigation headers (GPS and BeiDou Klobuchar) in
  ``GnssRaw.iono``; the service applies ionosphere, troposphere, elevation mask and weights
  (docs/real_rinex.md explains why the corrections live in the service).

Observation epochs are receiver time (the file's time system; BDT files are shifted to GPST).
Satellites without the selected code or Doppler, without a usable ephemeris, or whose values fail
the wire model's checks are dropped and counted in :class:`ConversionStats`.
"""

from __future__ import annotations

import math
from collections.abc import Iterator, Sequence
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
from pydantic import ValidationError

from fednav.service.messages import GnssRaw, IonoKlobuchar, SatObservation
from fednav.simulators.gnss.orbits import SECONDS_PER_WEEK, gps_seconds, gps_week_seconds
from fednav.simulators.gnss.rinex import (
    _NAV_FIELDS,
    GpsEphemerides,
    RinexObs,
    _float,
    gps_broadcast_states,
    read_rinex2_nav,
    read_rinex2_obs,
)

C_MPS = 299792458.0
BDT_WEEK_OFFSET = 1356  # BDT week 0 starts at GPS week 1356 (2006-01-01)
BDT_MINUS_GPST_S = -14.0
CGCS2000_MU_M3PS2 = 3.986004418e14
CGCS2000_OMEGA_E_RPS = 7.2921150e-5
GAL_MU_M3PS2 = 3.986004418e14
GAL_OMEGA_E_RPS = 7.2921151467e-5

FREQ_HZ = {"G": 1575.42e6, "E": 1575.42e6, "C": 1561.098e6}
CONSTELLATION = {"G": "GPS", "E": "GAL", "C": "BDS"}
#: observation codes tried in order per system (RINEX 3); RINEX 2 uses C1/P1 and D1
PSEUDORANGE_CODES = {"G": ("C1C", "C1W", "C1P", "C1X"), "E": ("C1C", "C1X", "C1B"), "C": ("C2I", "C1I")}
DOPPLER_CODES = {"G": ("D1C", "D1W", "D1P", "D1X"), "E": ("D1C", "D1X", "D1B"), "C": ("D2I", "D1I")}
NAV_LINES = {"G": 8, "E": 8, "C": 8, "J": 8, "I": 8, "R": 4, "S": 4}
#: BeiDou GEO satellites (BDS-2 C01-C05, BDS-3 C59-C63): the ICD's GEO algorithm
BDS_GEO = frozenset({1, 2, 3, 4, 5, 59, 60, 61, 62, 63})


# --- navigation ------------------------------------------------------------------------------------------
@dataclass
class Navigation:
    """Broadcast records per system (``"G"``, ``"E"``, ``"C"``; times in GPS seconds) and the
    Klobuchar coefficients found in the headers (``{"GPS": (alpha4, beta4), "BDS": ...}``)."""

    eph: dict[str, GpsEphemerides] = field(default_factory=dict)
    klobuchar: dict[str, tuple[tuple[float, ...], tuple[float, ...]]] = field(default_factory=dict)

    def add(self, system: str, eph: GpsEphemerides) -> None:
        old = self.eph.get(system)
        if old is None:
            self.eph[system] = eph
            return
        self.eph[system] = GpsEphemerides(
            np.concatenate([old.prn, eph.prn]),
            np.concatenate([old.toc_gps_s, eph.toc_gps_s]),
            np.concatenate([old.toe_gps_s, eph.toe_gps_s]),
            {k: np.concatenate([old.params[k], eph.params[k]]) for k in old.params},
            old.header,
        )


def _rinex_version(path: Path) -> float:
    with open(path, errors="replace") as f:
        return float(f.readline()[:9])


def read_rinex3_nav(path: str | Path) -> Navigation:
    """Read a RINEX 3.0x navigation file (mixed or single system). GPS, Galileo and BeiDou records
    are kept (other systems' records are skipped by their line count); header IONOSPHERIC CORR
    GPSA/GPSB and BDSA/BDSB become Klobuchar coefficients."""
    path = Path(path)
    lines = path.read_text(errors="replace").splitlines()
    if not lines or not lines[0][:9].strip().startswith("3") or lines[0][20:21].upper() != "N":
        raise ValueError(f"{path}: not a RINEX 3 navigation file")
    nav = Navigation()
    iono: dict[str, list[float]] = {}
    k = 0
    while k < len(lines):
        ln = lines[k]
        label = ln[60:].strip()
        if label == "IONOSPHERIC CORR":
            iono[ln[0:4].strip()] = [_float(ln[5 + 12 * j : 17 + 12 * j]) for j in range(4)]
        k += 1
        if label == "END OF HEADER":
            break
    else:
        raise ValueError(f"{path}: no END OF HEADER")
    for name, (a, b) in {"GPS": ("GPSA", "GPSB"), "BDS": ("BDSA", "BDSB")}.items():
        if a in iono and b in iono:
            nav.klobuchar[name] = (tuple(iono[a]), tuple(iono[b]))
    recs: dict[str, tuple[list[int], list[float], list[list[float]]]] = {}
    while k < len(lines):
        head = lines[k]
        if not head.strip():
            k += 1
            continue
        sys_ = head[0]
        n_lines = NAV_LINES.get(sys_)
        if n_lines is None:
            raise ValueError(f"{path}: line {k + 1}: unknown system in navigation record {head!r}")
        block = lines[k : k + n_lines]
        k += n_lines
        if sys_ not in FREQ_HZ:
            continue
        try:
            prn = int(head[1:3])
            yy, mo, dd, hh, mi, ss = (int(head[4:8]),) + tuple(
                int(head[9 + 3 * j : 11 + 3 * j]) for j in range(5)
            )
            vals = [_float(head[23 + 19 * j : 42 + 19 * j]) for j in range(3)]
            for ln in block[1:]:
                vals += [_float(ln[4 + 19 * j : 23 + 19 * j]) for j in range(4)]
        except (ValueError, IndexError) as e:
            raise ValueError(f"{path}: bad navigation record starting {head!r}") from e
        toc = gps_seconds(yy, mo, dd, hh, mi, float(ss))
        if sys_ == "C":
            toc -= BDT_MINUS_GPST_S
        r = recs.setdefault(sys_, ([], [], []))
        r[0].append(prn)
        r[1].append(toc)
        r[2].append((vals + [0.0] * len(_NAV_FIELDS))[: len(_NAV_FIELDS)])
    for sys_, (prns, tocs, rows) in recs.items():
        arr = np.array(rows, dtype=float).reshape(len(rows), len(_NAV_FIELDS))
        params = {name: arr[:, j].copy() for j, name in enumerate(_NAV_FIELDS)}
        week = params["week"].astype(int)
        if sys_ == "C":  # BDT week and seconds of week -> GPS seconds
            toe = np.array(
                [
                    gps_week_seconds(w + BDT_WEEK_OFFSET, s)
                    for w, s in zip(week, params["toe_sow"], strict=True)
                ]
            )
            toe = toe - BDT_MINUS_GPST_S
        else:  # GPS week; the Galileo week in RINEX 3 is aligned to the GPS week
            toe = np.array([gps_week_seconds(w, s) for w, s in zip(week, params["toe_sow"], strict=True)])
        if sys_ == "E":  # E1 single-frequency (I/NAV) group delay: BGD(E1, E5b), 6th orbit line, 4th field
            params["tgd"] = params["iodc"].copy()
        toe = toe + np.round((np.asarray(tocs) - toe) / SECONDS_PER_WEEK) * SECONDS_PER_WEEK
        nav.eph[sys_] = GpsEphemerides(np.array(prns, dtype=int), np.asarray(tocs), toe, params)
    return nav


def read_navigation(paths: str | Path | Sequence[str | Path]) -> Navigation:
    """Read and merge RINEX 2 (GPS) and RINEX 3 navigation files."""
    if isinstance(paths, str | Path):
        paths = [paths]
    nav = Navigation()
    for p in paths:
        p = Path(p)
        if _rinex_version(p) < 3.0:
            e = read_rinex2_nav(p)
            nav.add("G", e)
            if "ION ALPHA" in e.header and "ION BETA" in e.header:
                nav.klobuchar.setdefault("GPS", (tuple(e.header["ION ALPHA"]), tuple(e.header["ION BETA"])))
        else:
            n3 = read_rinex3_nav(p)
            for s, e in n3.eph.items():
                nav.add(s, e)
            for c, v in n3.klobuchar.items():
                nav.klobuchar.setdefault(c, v)
    if not nav.eph:
        raise ValueError(f"no GPS, Galileo or BeiDou navigation records in {[str(p) for p in paths]}")
    return nav


class MultiBroadcast:
    """Broadcast-ephemeris orbit source for GPS, Galileo and BeiDou (record nearest in toe, healthy,
    within ``max_age_s``)."""

    def __init__(self, nav: Navigation, max_age_s: float = 14400.0, use_unhealthy: bool = False):
        self.nav = nav
        self.max_age_s = max_age_s
        self._by_sat: dict[str, tuple[str, np.ndarray]] = {}
        for s, eph in nav.eph.items():
            ok = np.ones(len(eph), dtype=bool) if use_unhealthy else (eph.params["health"] == 0)
            groups: dict[str, list[int]] = {}
            for r in np.flatnonzero(ok):
                groups.setdefault(f"{s}{eph.prn[r]:02d}", []).append(int(r))
            for sid, rs in groups.items():
                self._by_sat[sid] = (s, np.asarray(rs, dtype=int))

    def satellite_ids(self) -> list[str]:
        return sorted(self._by_sat)

    def record(self, sid: str, t_gps_s: float) -> int:
        entry = self._by_sat.get(sid)
        if entry is None:
            return -1
        s, recs = entry
        age = np.abs(t_gps_s - self.nav.eph[s].toe_gps_s[recs])
        best = int(np.argmin(age))
        return int(recs[best]) if age[best] <= self.max_age_s else -1

    def state(self, sid: str, rec: int, t_gps_s: float) -> tuple[np.ndarray, np.ndarray, float, float]:
        """Position (3,) m, velocity (3,) m/s (ECEF of ``t_gps_s``), clock s (with relativistic
        term and group delay), clock drift s/s at GPS time ``t_gps_s``."""
        s = sid[0]
        eph = self.nav.eph[s]
        r = np.array([rec])
        t = np.array([t_gps_s])
        if s == "G":
            p, v, c, d = gps_broadcast_states(eph, r, t)
        elif s == "E":
            p, v, c, d = gps_broadcast_states(eph, r, t, True, GAL_MU_M3PS2, GAL_OMEGA_E_RPS)
        elif int(sid[1:]) in BDS_GEO:
            return _bds_geo_state(eph, rec, t_gps_s)
        else:
            p, v, c, d = gps_broadcast_states(eph, r, t, True, CGCS2000_MU_M3PS2, CGCS2000_OMEGA_E_RPS)
        return p[0], v[0], float(c[0]), float(d[0])


def _bds_geo_position(eph: GpsEphemerides, rec: int, t_gps_s: float) -> tuple[np.ndarray, float, float]:
    """BDS-SIS-ICD-B1I 5.2.4.12 GEO: Omega_k = Omega_0 + Omega_dot tk - omega_e toe in the
    inertial-like frame, then R_Z(omega_e tk) R_X(-5 deg). Reuses the Keplerian code with omega_e = 0
    and Omega_0 shifted by -omega_e toe."""
    params = {k: v[[rec]].copy() for k, v in eph.params.items()}
    params["omega0"] = params["omega0"] - CGCS2000_OMEGA_E_RPS * params["toe_sow"]
    one = GpsEphemerides(eph.prn[[rec]], eph.toc_gps_s[[rec]], eph.toe_gps_s[[rec]], params)
    p, _, c, d = gps_broadcast_states(one, np.array([0]), np.array([t_gps_s]), True, CGCS2000_MU_M3PS2, 0.0)
    tk = t_gps_s - eph.toe_gps_s[rec]
    a = math.radians(-5.0)
    rx = np.array([[1.0, 0.0, 0.0], [0.0, math.cos(a), math.sin(a)], [0.0, -math.sin(a), math.cos(a)]])
    z = CGCS2000_OMEGA_E_RPS * tk
    rz = np.array([[math.cos(z), math.sin(z), 0.0], [-math.sin(z), math.cos(z), 0.0], [0.0, 0.0, 1.0]])
    return rz @ rx @ p[0], float(c[0]), float(d[0])


def _bds_geo_state(
    eph: GpsEphemerides, rec: int, t_gps_s: float
) -> tuple[np.ndarray, np.ndarray, float, float]:
    p, c, d = _bds_geo_position(eph, rec, t_gps_s)
    h = 0.5  # central difference: error ~ |a| h^2 / 6 ~ 1e-2 mm/s for a GEO
    vel = (_bds_geo_position(eph, rec, t_gps_s + h)[0] - _bds_geo_position(eph, rec, t_gps_s - h)[0]) / (
        2 * h
    )
    return p, vel, c, d


# --- observations ----------------------------------------------------------------------------------------
def read_rinex3_obs(path: str | Path) -> RinexObs:
    """Read a RINEX 3.0x observation file (single receiver, any systems). ``types`` of the result
    are ``"<sys><code>"`` (e.g. ``"GC1C"``, ``"CD2I"``); values NaN where absent or zero. Event
    epochs (flags 2-5) are skipped; BDT-stamped files are shifted to GPS time."""
    path = Path(path)
    lines = path.read_text(errors="replace").splitlines()
    if not lines or not lines[0][:9].strip().startswith("3") or "OBSERVATION" not in lines[0][20:40].upper():
        raise ValueError(f"{path}: not a RINEX 3 observation file")
    sys_types: dict[str, list[str]] = {}
    approx = np.full(3, np.nan)
    interval = math.nan
    time_shift = 0.0
    k = 0
    cur = ""
    while k < len(lines):
        ln = lines[k]
        label = ln[60:].strip()
        if label == "SYS / # / OBS TYPES":
            if ln[0] != " ":
                cur = ln[0]
                sys_types[cur] = []
            sys_types[cur] += ln[7:60].split()
        elif label == "APPROX POSITION XYZ":
            approx = np.array([float(ln[0:14]), float(ln[14:28]), float(ln[28:42])])
        elif label == "INTERVAL":
            interval = float(ln[0:10])
        elif label == "TIME OF FIRST OBS" and ln[48:51].strip() == "BDT":
            time_shift = -BDT_MINUS_GPST_S
        k += 1
        if label == "END OF HEADER":
            break
    else:
        raise ValueError(f"{path}: no END OF HEADER")
    all_types = tuple(f"{s}{c}" for s in sorted(sys_types) for c in sys_types[s])
    col = {t: j for j, t in enumerate(all_types)}
    times: list[float] = []
    flags: list[int] = []
    epochs: list[dict[str, dict[int, float]]] = []
    while k < len(lines):
        ln = lines[k]
        if not ln.startswith(">"):
            k += 1
            continue
        flag = int(ln[31:32]) if ln[31:32].strip() else 0
        nsat = int(ln[32:35])
        k += 1
        if flag > 1:
            k += nsat
            continue
        yy, mo, dd, hh, mi = int(ln[2:6]), int(ln[7:9]), int(ln[10:12]), int(ln[13:15]), int(ln[16:18])
        ss = float(ln[18:29])
        rec: dict[str, dict[int, float]] = {}
        for ln_s in lines[k : k + nsat]:
            sid = ln_s[0:3].replace(" ", "0")
            codes = sys_types.get(sid[0])
            if codes is None:
                continue
            vals = {}
            for j, code in enumerate(codes):
                f = ln_s[3 + 16 * j : 17 + 16 * j]
                if f.strip():
                    v = float(f)
                    if v != 0.0:
                        vals[col[f"{sid[0]}{code}"]] = v
            rec[sid] = vals
        k += nsat
        times.append(gps_seconds(yy, mo, dd, hh, mi, ss) + time_shift)
        flags.append(flag)
        epochs.append(rec)
    ids = tuple(sorted({s for rec in epochs for s in rec}))
    sidx = {s: j for j, s in enumerate(ids)}
    values = np.full((len(epochs), len(ids), len(all_types)), np.nan)
    for e, rec in enumerate(epochs):
        for s, vals in rec.items():
            for c, v in vals.items():
                values[e, sidx[s], c] = v
    return RinexObs(np.asarray(times), ids, all_types, values, approx, interval, np.asarray(flags, dtype=int))


def read_observations(path: str | Path) -> RinexObs:
    """RINEX 2 or 3 observations; RINEX 2 types are renamed ``"G" + type`` (GPS only is used)."""
    path = Path(path)
    if _rinex_version(path) >= 3.0:
        return read_rinex3_obs(path)
    o = read_rinex2_obs(path)
    return RinexObs(
        o.t_gps_s,
        o.ids,
        tuple("G" + t for t in o.types),
        o.values,
        o.approx_pos_ecef_m,
        o.interval_s,
        o.epoch_flags,
    )


def _pick(obs: RinexObs, system: str, prefs: Sequence[str]) -> np.ndarray:
    """(E, S) values of the first preferred code present for ``system`` (NaN where none)."""
    out = np.full(obs.values.shape[:2], np.nan)
    for code in prefs:
        name = system + code
        if name in obs.types:
            v = obs.values[:, :, obs.types.index(name)]
            out = np.where(np.isnan(out), v, out)
    return out


# --- conversion ------------------------------------------------------------------------------------------
@dataclass
class ConversionStats:
    """Counts of one conversion: epochs yielded, observations kept and dropped per reason."""

    epochs: int = 0
    observations: int = 0
    dropped: dict[str, int] = field(default_factory=dict)

    def drop(self, reason: str, n: int = 1) -> None:
        self.dropped[reason] = self.dropped.get(reason, 0) + n


def iter_gnss_raw(
    obs_path: str | Path,
    nav_paths: str | Path | Sequence[str | Path],
    *,
    systems: Sequence[str] = ("G", "E", "C"),
    pseudorange_sigma_m: float = 3.0,
    range_rate_sigma_mps: float = 0.1,
    start_gps_s: float | None = None,
    stop_gps_s: float | None = None,
    max_age_s: float = 14400.0,
    stats: ConversionStats | None = None,
) -> Iterator[tuple[float, GnssRaw]]:
    """Yield ``(t_gps_s, GnssRaw)`` per observation epoch (module docstring for the model).

    Parameters
    ----------
    obs_path : RINEX 2.10/2.11 or 3.0x observation file.
    nav_paths : one or more RINEX 2 (GPS) / 3 (mixed) navigation files.
    systems : system letters to convert (G GPS, E Galileo, C BeiDou).
    pseudorange_sigma_m, range_rate_sigma_mps : zenith 1-sigma noise written into each observation
        (the service scales them with elevation when configured).
    start_gps_s, stop_gps_s : optional time window (inclusive).
    stats : optional :class:`ConversionStats` filled while iterating.
    """
    st = stats if stats is not None else ConversionStats()
    obs = read_observations(obs_path)
    nav = read_navigation(nav_paths)
    src = MultiBroadcast(nav, max_age_s=max_age_s)
    iono = [IonoKlobuchar(constellation=c, alpha=a, beta=b) for c, (a, b) in sorted(nav.klobuchar.items())]
    use = [j for j, s in enumerate(obs.ids) if s[0] in systems and s[0] in FREQ_HZ]
    pr_all = np.full(obs.values.shape[:2], np.nan)
    dop_all = np.full(obs.values.shape[:2], np.nan)
    for s in {obs.ids[j][0] for j in use}:
        cols = [j for j in use if obs.ids[j][0] == s]
        pr_codes = PSEUDORANGE_CODES[s] + (("C1", "P1") if s == "G" else ())
        dop_codes = DOPPLER_CODES[s] + (("D1",) if s == "G" else ())
        pr_all[:, cols] = _pick(obs, s, pr_codes)[:, cols]
        dop_all[:, cols] = _pick(obs, s, dop_codes)[:, cols]
    for e, t_rx in enumerate(obs.t_gps_s):
        t_rx = float(t_rx)
        if (start_gps_s is not None and t_rx < start_gps_s) or (stop_gps_s is not None and t_rx > stop_gps_s):
            continue
        sats = []
        for j in use:
            sid = obs.ids[j]
            pr, dop = pr_all[e, j], dop_all[e, j]
            if not np.isfinite(pr):
                continue
            if not np.isfinite(dop):
                st.drop("no_doppler")
                continue
            rec = src.record(sid, t_rx)
            if rec < 0:
                st.drop("no_ephemeris")
                continue
            t_tx = t_rx - pr / C_MPS  # satellite clock reading at transmission
            clk = 0.0
            for _ in range(2):  # t_tx(system) = t_sv - dt_sv(t_tx)
                _, _, clk, _ = src.state(sid, rec, t_tx - clk)
            t_tx = t_tx - clk
            pos, vel, clk, drift = src.state(sid, rec, t_tx)
            try:
                sats.append(
                    SatObservation(
                        id=sid,
                        constellation=CONSTELLATION[sid[0]],  # type: ignore[arg-type]
                        pseudorange_m=float(pr),
                        range_rate_mps=float(-dop * C_MPS / FREQ_HZ[sid[0]]),
                        pseudorange_sigma_m=pseudorange_sigma_m,
                        range_rate_sigma_mps=range_rate_sigma_mps,
                        sat_pos_ecef_m=tuple(float(x) for x in pos),
                        sat_vel_ecef_mps=tuple(float(x) for x in vel),
                        sat_clock_m=float(C_MPS * clk),
                        sat_clock_drift_mps=float(C_MPS * drift),
                    )
                )
            except ValidationError:
                st.drop("invalid")
                continue
        st.epochs += 1
        st.observations += len(sats)
        yield t_rx, GnssRaw(t=t_rx, sats=sats, iono=iono)


__all__ = [
    "ConversionStats",
    "MultiBroadcast",
    "Navigation",
    "iter_gnss_raw",
    "read_navigation",
    "read_observations",
    "read_rinex3_nav",
    "read_rinex3_obs",
]
