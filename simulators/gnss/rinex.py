"""RINEX 2 readers (GPS navigation message, observations) and the IS-GPS-200 ephemeris algorithm.

- :func:`read_rinex2_nav` reads a RINEX 2.x GPS navigation file into :class:`GpsEphemerides`
  (one array per broadcast parameter, one row per record).
- :class:`BroadcastEphemeris` is an orbit source (``orbits.OrbitSource``): for each satellite it
  takes the healthy record whose ``toe`` is nearest the query time (within ``max_age_s``) and
  evaluates IS-GPS-200N Table 20-IV (position), its analytic time derivative (velocity) and the
  clock polynomial with the relativistic term (20.3.3.3.3.1) and, optionally, the L1 group delay
  ``T_GD`` (single-frequency L1 C/A users subtract it, 20.3.3.3.3.2).
- :func:`read_rinex2_obs` reads RINEX 2.10/2.11 observation files (any subset of observation
  types) into an (epochs x satellites x types) array.

Times are GPS seconds since 1980-01-06 (``orbits.gps_seconds``). RINEX 2 nav epochs (``toc``) are
GPS time; the ``toe`` week in RINEX 2 is the continuous GPS week.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from fednav.simulators.gnss.orbits import (
    SECONDS_PER_WEEK,
    SatStates,
    _times_for,
    gps_seconds,
    gps_week_seconds,
)

# IS-GPS-200 constants (must be used with broadcast parameters, not the WGS-84 ones).
GPS_MU_M3PS2 = 3.986005e14
GPS_OMEGA_E_RPS = 7.2921151467e-5
GPS_F_REL = -4.442807633e-10  # s / sqrt(m), relativistic clock constant F = -2 sqrt(mu) / c^2
GPS_L1_HZ = 1575.42e6
GPS_L2_HZ = 1227.60e6
C_L1_M = 299792458.0 / GPS_L1_HZ  # L1 wavelength, 0.1903 m

_NAV_FIELDS = (
    # line 0 after PRN/epoch
    "af0",
    "af1",
    "af2",
    # broadcast orbit 1..7 (4 fields each)
    "iode",
    "crs",
    "delta_n",
    "m0",
    "cuc",
    "e",
    "cus",
    "sqrt_a",
    "toe_sow",
    "cic",
    "omega0",
    "cis",
    "i0",
    "crc",
    "omega",
    "omega_dot",
    "idot",
    "l2_codes",
    "week",
    "l2p_flag",
    "sv_accuracy",
    "health",
    "tgd",
    "iodc",
    "transmit_sow",
    "fit_interval",
    "spare1",
    "spare2",
)


def _float(s: str) -> float:
    s = s.strip().replace("D", "E").replace("d", "e")
    return float(s) if s else 0.0


@dataclass(frozen=True)
class GpsEphemerides:
    """Broadcast records: ``prn`` (R,) ints, ``toc_gps_s`` and ``toe_gps_s`` (R,) full GPS seconds and one
    (R,) array per parameter in ``params`` (names as in :data:`_NAV_FIELDS`; angles rad, SI units)."""

    prn: np.ndarray
    toc_gps_s: np.ndarray
    toe_gps_s: np.ndarray
    params: dict[str, np.ndarray]
    header: dict[str, list[float]] = field(default_factory=dict)

    def __len__(self) -> int:
        return len(self.prn)


def read_rinex2_nav(path: str | Path) -> GpsEphemerides:
    """Read a RINEX 2.x GPS navigation message file (header ION/DELTA-UTC lines kept as numbers)."""
    path = Path(path)
    lines = path.read_text(errors="replace").splitlines()
    if not lines or not lines[0][:9].strip().startswith("2") or lines[0][20:21].upper() != "N":
        raise ValueError(f"{path}: not a RINEX 2 GPS navigation file")
    header: dict[str, list[float]] = {}
    k = 0
    while k < len(lines):
        ln = lines[k]
        label = ln[60:].strip()
        if label in ("ION ALPHA", "ION BETA"):
            header[label] = [_float(ln[2 + 12 * j : 14 + 12 * j]) for j in range(4)]
        k += 1
        if label == "END OF HEADER":
            break
    else:
        raise ValueError(f"{path}: no END OF HEADER")
    prns, tocs, rows = [], [], []
    body = [ln for ln in lines[k:] if ln.strip()]
    if len(body) % 8:
        raise ValueError(f"{path}: {len(body)} data lines is not a whole number of 8-line records")
    for r in range(0, len(body), 8):
        rec = body[r : r + 8]
        head = rec[0]
        try:
            prn = int(head[0:2])
            yy, mo, dd, hh, mi = (int(head[3 + 3 * j : 5 + 3 * j]) for j in range(5))
            ss = float(head[17:22])
            vals = [_float(head[22 + 19 * j : 41 + 19 * j]) for j in range(3)]
            for ln in rec[1:]:
                vals += [_float(ln[3 + 19 * j : 22 + 19 * j]) for j in range(4)]
        except ValueError as e:
            raise ValueError(f"{path}: bad navigation record starting {head!r}") from e
        year = yy + (1900 if yy >= 80 else 2000)
        prns.append(prn)
        tocs.append(gps_seconds(year, mo, dd, hh, mi, ss))
        rows.append(vals)
    arr = np.array(rows, dtype=float).reshape(len(rows), len(_NAV_FIELDS))
    params = {name: arr[:, j] for j, name in enumerate(_NAV_FIELDS)}
    toe = np.array(
        [gps_week_seconds(int(w), s) for w, s in zip(params["week"], params["toe_sow"], strict=True)]
    )
    # The RINEX 2 week goes with toe; guard against writers that put the transmission week there
    # (toe in the next week at a rollover): toc and toe must be within half a week of each other.
    toe = toe + np.round((np.asarray(tocs) - toe) / SECONDS_PER_WEEK) * SECONDS_PER_WEEK
    return GpsEphemerides(np.array(prns, dtype=int), np.asarray(tocs), toe, params, header)


def gps_broadcast_states(
    eph: GpsEphemerides,
    rec: np.ndarray,
    t_gps_s: np.ndarray,
    with_tgd: bool = True,
    mu_m3ps2: float = GPS_MU_M3PS2,
    omega_e_rps: float = GPS_OMEGA_E_RPS,
    tgd_field: str = "tgd",
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """IS-GPS-200N Table 20-IV user algorithm, vectorised over records ``rec`` (N,) at times (N,).

    Returns position (N, 3) m and velocity (N, 3) m/s in ECEF at ``t_gps_s`` (velocity: analytic
    derivative of the same equations, ECEF-relative), clock (N,) s and clock drift (N,) s/s
    (``af0 + af1 dt + af2 dt^2 + F e sqrt(A) sin E [- T_GD]``). The same Keplerian algorithm serves
    Galileo (OS SIS ICD 5.1.1) and BeiDou MEO/IGSO (BDS-SIS-ICD-B1I 5.2.4.12) with their own
    ``mu_m3ps2``/``omega_e_rps`` (F = -2 sqrt(mu) / c^2) and group-delay field ``tgd_field``.
    """
    p = {k: v[rec] for k, v in eph.params.items()}
    t = np.asarray(t_gps_s, dtype=float)
    a = p["sqrt_a"] ** 2
    e = p["e"]
    n0 = np.sqrt(mu_m3ps2 / a**3)
    f_rel = -2.0 * math.sqrt(mu_m3ps2) / 299792458.0**2
    tk = t - eph.toe_gps_s[rec]
    n = n0 + p["delta_n"]
    mk = p["m0"] + n * tk
    ek = mk.copy()
    for _ in range(30):  # Kepler's equation, Newton
        d = (ek - e * np.sin(ek) - mk) / (1.0 - e * np.cos(ek))
        ek = ek - d
        if np.all(np.abs(d) < 1e-15):
            break
    se, ce = np.sin(ek), np.cos(ek)
    one_m_ecos = 1.0 - e * ce
    nu = np.arctan2(np.sqrt(1.0 - e * e) * se, ce - e)
    phi = nu + p["omega"]
    s2, c2 = np.sin(2.0 * phi), np.cos(2.0 * phi)
    du = p["cus"] * s2 + p["cuc"] * c2
    dr = p["crs"] * s2 + p["crc"] * c2
    di = p["cis"] * s2 + p["cic"] * c2
    u = phi + du
    r = a * one_m_ecos + dr
    inc = p["i0"] + di + p["idot"] * tk
    xp, yp = r * np.cos(u), r * np.sin(u)
    omega_k = p["omega0"] + (p["omega_dot"] - omega_e_rps) * tk - omega_e_rps * eph.params["toe_sow"][rec]
    co, so, ci, si = np.cos(omega_k), np.sin(omega_k), np.cos(inc), np.sin(inc)
    x = xp * co - yp * ci * so
    y = xp * so + yp * ci * co
    z = yp * si
    # Velocity (IS-GPS-200N Table 20-IV, second part).
    ek_dot = n / one_m_ecos
    nu_dot = ek_dot * np.sqrt(1.0 - e * e) / one_m_ecos
    inc_dot = p["idot"] + 2.0 * nu_dot * (p["cis"] * c2 - p["cic"] * s2)
    u_dot = nu_dot + 2.0 * nu_dot * (p["cus"] * c2 - p["cuc"] * s2)
    r_dot = e * a * ek_dot * se + 2.0 * nu_dot * (p["crs"] * c2 - p["crc"] * s2)
    omega_k_dot = p["omega_dot"] - omega_e_rps
    xp_dot = r_dot * np.cos(u) - r * u_dot * np.sin(u)
    yp_dot = r_dot * np.sin(u) + r * u_dot * np.cos(u)
    vx = (
        -xp * omega_k_dot * so
        + xp_dot * co
        - yp_dot * so * ci
        - yp * (omega_k_dot * co * ci - inc_dot * so * si)
    )
    vy = (
        xp * omega_k_dot * co
        + xp_dot * so
        + yp_dot * co * ci
        - yp * (omega_k_dot * so * ci + inc_dot * co * si)
    )
    vz = yp_dot * si + yp * inc_dot * ci
    # Clock (20.3.3.3.3.1): dt_sv = af0 + af1 (t - toc) + af2 (t - toc)^2 + dt_r, dt_r = F e sqrt(A) sin E.
    tc = t - eph.toc_gps_s[rec]
    clk = p["af0"] + p["af1"] * tc + p["af2"] * tc**2 + f_rel * e * p["sqrt_a"] * se
    drift = p["af1"] + 2.0 * p["af2"] * tc + f_rel * e * p["sqrt_a"] * ce * ek_dot
    if with_tgd:
        clk = clk - p[tgd_field]
    return np.stack([x, y, z], -1), np.stack([vx, vy, vz], -1), clk, drift


class BroadcastEphemeris:
    """Orbit source from GPS broadcast ephemerides (RINEX 2 nav).

    Parameters
    ----------
    eph : records (or use :meth:`from_file`).
    max_age_s : a record is usable while ``|t - toe| <= max_age_s`` (default 4 h: the 4-hour fit
        interval is centred on toe, so 2 h is the nominal limit; 4 h keeps a satellite usable across
        a missing upload with metre-level degradation).
    with_tgd : subtract the L1 group delay T_GD from the clock (L1 C/A single-frequency user).
    use_unhealthy : allow records with a non-zero health word.
    """

    def __init__(
        self,
        eph: GpsEphemerides,
        max_age_s: float = 14400.0,
        with_tgd: bool = True,
        use_unhealthy: bool = False,
    ):
        self.eph = eph
        self.max_age_s = max_age_s
        self.with_tgd = with_tgd
        ok = np.ones(len(eph), dtype=bool) if use_unhealthy else (eph.params["health"] == 0)
        self._by_sat: dict[str, np.ndarray] = {}
        for r in np.flatnonzero(ok):
            self._by_sat.setdefault(f"G{eph.prn[r]:02d}", []).append(r)  # type: ignore[arg-type]
        self._by_sat = {s: np.asarray(v, dtype=int) for s, v in self._by_sat.items()}

    @classmethod
    def from_file(cls, path: str | Path, **kwargs) -> BroadcastEphemeris:
        return cls(read_rinex2_nav(path), **kwargs)

    def satellite_ids(self) -> list[str]:
        return sorted(self._by_sat)

    def select_records(self, ids: Sequence[str], t_gps_s: np.ndarray) -> np.ndarray:
        """Record index per satellite (N,), -1 where none is within ``max_age_s``."""
        out = np.full(len(ids), -1, dtype=int)
        for j, s in enumerate(ids):
            recs = self._by_sat.get(s)
            if recs is None or len(recs) == 0:
                continue
            age = np.abs(t_gps_s[j] - self.eph.toe_gps_s[recs])
            best = int(np.argmin(age))
            if age[best] <= self.max_age_s:
                out[j] = recs[best]
        return out

    def states(self, ids: Sequence[str], t_gps_s: float | np.ndarray) -> SatStates:
        t = _times_for(ids, t_gps_s)
        rec = self.select_records(ids, t)
        ok = rec >= 0
        n = len(ids)
        pos, vel = np.full((n, 3), np.nan), np.full((n, 3), np.nan)
        clk, drift = np.full(n, np.nan), np.full(n, np.nan)
        if np.any(ok):
            p, v, c, d = gps_broadcast_states(self.eph, rec[ok], t[ok], with_tgd=self.with_tgd)
            pos[ok], vel[ok], clk[ok], drift[ok] = p, v, c, d
        return SatStates(tuple(ids), pos, vel, clk, drift)


# --- observations ---------------------------------------------------------------------------------------
@dataclass(frozen=True)
class RinexObs:
    """RINEX 2 observations.

    Attributes
    ----------
    t_gps_s : (E,) receiver epoch times (GPS time as written in the file).
    ids : tuple of S satellite ids.
    types : tuple of K observation types read (subset of the file's, e.g. ``("C1", "D1")``).
    values : (E, S, K) observations in the file's units (m, cycles, Hz); NaN where absent or 0.
    approx_pos_ecef_m : (3,) header APPROX POSITION XYZ.
    interval_s : header INTERVAL (NaN if absent).
    epoch_flags : (E,) epoch flags (0 OK, 1 power failure; event epochs 2-5 are skipped).
    """

    t_gps_s: np.ndarray
    ids: tuple[str, ...]
    types: tuple[str, ...]
    values: np.ndarray
    approx_pos_ecef_m: np.ndarray
    interval_s: float
    epoch_flags: np.ndarray

    def obs(self, obs_type: str) -> np.ndarray:
        """(E, S) array of one observation type."""
        return self.values[:, :, self.types.index(obs_type)]


def read_rinex2_obs(path: str | Path, types: Sequence[str] | None = None) -> RinexObs:
    """Read a RINEX 2.10/2.11 observation file (single receiver). ``types=None`` reads all types.

    Handles satellite lists longer than 12 (continuation lines), more than 5 observation types
    (continuation lines per satellite), blank and zero values (NaN), and skips event records
    (epoch flags 2-5 with their header lines). Satellite ids with a blank system letter are GPS.
    """
    path = Path(path)
    lines = path.read_text(errors="replace").splitlines()
    if not lines or not lines[0][:9].strip().startswith("2") or "OBSERVATION" not in lines[0][20:40].upper():
        raise ValueError(f"{path}: not a RINEX 2 observation file")
    file_types: list[str] = []
    approx = np.full(3, np.nan)
    interval = math.nan
    k = 0
    n_types = 0
    while k < len(lines):
        ln = lines[k]
        label = ln[60:].strip()
        if label == "# / TYPES OF OBSERV":
            if not file_types:
                n_types = int(ln[0:6])
            file_types += ln[6:60].split()
        elif label == "APPROX POSITION XYZ":
            approx = np.array([float(ln[0:14]), float(ln[14:28]), float(ln[28:42])])
        elif label == "INTERVAL":
            interval = float(ln[0:10])
        k += 1
        if label == "END OF HEADER":
            break
    if len(file_types) != n_types:
        raise ValueError(f"{path}: header announces {n_types} observation types, lists {len(file_types)}")
    want = tuple(file_types if types is None else types)
    missing = [t for t in want if t not in file_types]
    if missing:
        raise ValueError(f"{path}: observation types {missing} not in file (has {file_types})")
    cols = [file_types.index(t) for t in want]
    lines_per_sat = (n_types + 4) // 5

    times: list[float] = []
    flags: list[int] = []
    epochs: list[dict[str, list[float]]] = []
    while k < len(lines):
        ln = lines[k]
        if not ln.strip():
            k += 1
            continue
        flag = int(ln[26:29]) if ln[26:29].strip() else 0
        nsat = int(ln[29:32])
        if flag > 1:  # event: nsat header lines follow
            k += 1 + nsat
            continue
        yy, mo, dd, hh, mi = (int(ln[3 * j : 3 * j + 3]) for j in range(5))
        ss = float(ln[15:26])
        sats = []
        sat_line, pos = ln, 32
        while len(sats) < nsat:
            if pos >= 68:
                k += 1
                sat_line, pos = lines[k], 32
            sid = sat_line[pos : pos + 3]
            sats.append(("G" + sid[1:] if sid[0] == " " else sid).replace(" ", "0"))
            pos += 3
        k += 1
        rec: dict[str, list[float]] = {}
        for sid in sats:
            text = "".join(lines[k + j].ljust(80)[:80] for j in range(lines_per_sat))
            k += lines_per_sat
            vals = []
            for c in cols:
                line_j, pos_j = divmod(c, 5)  # 5 fields of F14.3 + LLI + SSI per 80-column line
                f = text[80 * line_j + 16 * pos_j : 80 * line_j + 16 * pos_j + 14]
                v = float(f) if f.strip() else math.nan
                vals.append(math.nan if v == 0.0 else v)
            rec[sid] = vals
        year = yy + (1900 if yy >= 80 else 2000)
        times.append(gps_seconds(year, mo, dd, hh, mi, ss))
        flags.append(flag)
        epochs.append(rec)
    ids = tuple(sorted({s for rec in epochs for s in rec}))
    col = {s: j for j, s in enumerate(ids)}
    values = np.full((len(epochs), len(ids), len(want)), np.nan)
    for e, rec in enumerate(epochs):
        for s, v in rec.items():
            values[e, col[s]] = v
    return RinexObs(np.asarray(times), ids, want, values, approx, interval, np.asarray(flags, dtype=int))
