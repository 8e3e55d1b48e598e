"""Satellite orbits (nominal constellations), GNSS time helpers and the shared ranging model.

Conventions
-----------
- Time ``t_gps_s`` is GPS time in seconds since 1980-01-06 00:00:00 (the project's sensor time).
  BeiDou time (BDT = GPST - 14 s) never appears: every orbit source here is evaluated in GPST.
- Satellite states are ECEF (WGS-84 axes; CGCS2000 and IGb14 agree with them at the centimetre
  level, far below anything modelled here), metres and metres per second, *in the ECEF frame of
  the epoch they are evaluated at*. Velocities are ECEF-relative (they include the -omega x r
  earth-rotation term).
- Satellite clock ``clock_s`` is the offset of satellite time from GPST (s); a pseudorange carries
  ``- c * clock_s``. ``SatObservation.sat_clock_m`` is ``c * clock_s``.

Every orbit source (:class:`NominalConstellation` here, ``sp3.Sp3Orbits``,
``rinex.BroadcastEphemeris``) answers the :class:`OrbitSource` protocol:
``satellite_ids()`` and ``states(ids, t_gps_s) -> SatStates`` with one time per satellite, so a
receiver model can evaluate each satellite at its own transmit time in one vectorised call.

Ranging model (shared by the simulator and the service's filter)
-----------------------------------------------------------------
The section "ranging model" at the end of this module is self-contained (numpy and
``service.earth`` only) so the service can move it to ``service/`` unchanged.
The published satellite state is the state at the signal's transmit time ``t_t`` in the ECEF frame
*of the transmit time* (what an ephemeris gives at ``t_t``). The earth rotates by ``omega * tau``
during the light time ``tau = t_r - t_t``, so in the ECEF frame of the receive time the satellite is
at ``R3(omega tau) r_sat`` (exact rotation, not the first-order Sagnac formula), and the geometric
range solves ``rho = |R3(omega rho / c) r_sat - r_rx|`` (a fixed point, three iterations reach
machine precision). The range rate is the exact time derivative ``d rho / d t_r`` of that model,
including the light-time factor (see :func:`range_geometry`). The simulator produces its truth
with these very functions, so a filter that uses them inverts the simulator exactly.

References: IS-GPS-200N section 20.3.3.4.3 (user algorithm for ephemeris); BeiDou ICD B1C/B2a
(2017), section 7 (BDS-3 constellation: 3 GEO, 3 IGSO, 24 MEO); Walker, J. Br. Interplanet. Soc.
1984 (Walker-delta notation T/P/F); Groves, *Principles of GNSS, Inertial, and Multisensor
Integrated Navigation Systems*, 2nd ed., sections 8.5.3 (Sagnac) and 9.4.
"""

from __future__ import annotations

import datetime as _dt
import math
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Literal, Protocol, runtime_checkable

import numpy as np

from fednav.service.earth import A_M, GM_M3PS2, OMEGA_IE_RPS

# The ranging model is the receiver's (service.estimation.measurements.gnss_raw), re-exported here: one copy
# shared by the simulator and the filter, so simulated and predicted pseudoranges agree exactly.
from fednav.service.estimation.measurements.gnss_raw import (  # noqa: F401
    RangeGeometry,
    earth_rotation_matrices,
    range_geometry,
)

# --- time -----------------------------------------------------------------------------------------
GPS_EPOCH = _dt.datetime(1980, 1, 6)
SECONDS_PER_WEEK = 604800.0
BDT_MINUS_GPST_S = -14.0  # BDT = GPST - 14 s (BDS ICD); for reference, nothing here runs in BDT


def gps_seconds(
    year: int, month: int, day: int, hour: int = 0, minute: int = 0, second: float = 0.0
) -> float:
    """Calendar date/time *already in the GPS time scale* -> seconds since 1980-01-06 (no leap seconds)."""
    days = (_dt.datetime(year, month, day) - GPS_EPOCH).days
    return days * 86400.0 + hour * 3600.0 + minute * 60.0 + float(second)


def gps_week_seconds(week: int, sow_s: float) -> float:
    """GPS week (continuous, not modulo 1024) and seconds of week -> seconds since the GPS epoch."""
    return week * SECONDS_PER_WEEK + float(sow_s)


# --- orbit source protocol ---------------------------------------------------------------------------
Constellation = Literal["GPS", "BDS"]
PREFIX_TO_CONSTELLATION = {"G": "GPS", "C": "BDS", "E": "GAL", "R": "GLO", "J": "QZS"}


def constellation_of(sat_id: str) -> str:
    """``"C03"`` -> ``"BDS"``; ``"G12"`` -> ``"GPS"`` (message constellation names)."""
    return PREFIX_TO_CONSTELLATION[sat_id[0]]


@dataclass(frozen=True)
class SatStates:
    """States of N satellites, each at its own epoch (see the module conventions).

    Attributes
    ----------
    ids : tuple of N str
    pos_ecef_m, vel_ecef_mps : (N, 3) arrays; NaN rows where the source has no valid state.
    clock_s : (N,) satellite clock offset from GPST, s (0 where the source has no clock model).
    clock_drift_sps : (N,) its rate, s/s.
    """

    ids: tuple[str, ...]
    pos_ecef_m: np.ndarray
    vel_ecef_mps: np.ndarray
    clock_s: np.ndarray
    clock_drift_sps: np.ndarray

    @property
    def valid(self) -> np.ndarray:
        """(N,) bool: position, velocity and clock all finite."""
        return (
            np.all(np.isfinite(self.pos_ecef_m), axis=1)
            & np.all(np.isfinite(self.vel_ecef_mps), axis=1)
            & np.isfinite(self.clock_s)
            & np.isfinite(self.clock_drift_sps)
        )

    def subset(self, index: np.ndarray | Sequence[int]) -> SatStates:
        idx = np.asarray(index, dtype=int)
        return SatStates(
            tuple(self.ids[i] for i in idx),
            self.pos_ecef_m[idx],
            self.vel_ecef_mps[idx],
            self.clock_s[idx],
            self.clock_drift_sps[idx],
        )


@runtime_checkable
class OrbitSource(Protocol):
    """Anything that gives satellite states: nominal elements, SP3 precise orbits, broadcast ephemeris."""

    def satellite_ids(self) -> list[str]:
        """All satellite ids this source knows (RINEX style, e.g. ``C03``), sorted."""
        ...

    def states(self, ids: Sequence[str], t_gps_s: float | np.ndarray) -> SatStates:
        """States of ``ids`` at ``t_gps_s`` (scalar, or (N,) one time per satellite)."""
        ...


def _times_for(ids: Sequence[str], t_gps_s: float | np.ndarray) -> np.ndarray:
    t = np.asarray(t_gps_s, dtype=float)
    if t.ndim == 0:
        return np.full(len(ids), float(t))
    if t.shape != (len(ids),):
        raise ValueError(f"t_gps_s must be a scalar or shape ({len(ids)},), got {t.shape}")
    return t


# --- nominal constellations ---------------------------------------------------------------------------
NOMINAL_EPOCH_GPS_S = gps_seconds(2021, 4, 28, 18)
"""Reference epoch of the nominal elements (2021-04-28 18:00:00 GPST, the first epoch of the
project's real SP3 file). The inertial frame of the nominal model is the ECEF frame at this epoch.
The BDS MEO Walker phase is fitted to the real constellation at this epoch (see
:data:`BDS_MEO_PLANES`); far from it the nominal geometry drifts from the real one (no J2 nodal
regression, no along-track drift), which does not matter for a nominal constellation."""

GEOSYNC_A_M = (GM_M3PS2 / OMEGA_IE_RPS**2) ** (1.0 / 3.0)  # 42,164.17 km: mean motion = earth rate
BDS_MEO_A_M = A_M + 21_528_000.0  # 27,906.1 km (BDS ICD: MEO altitude 21,528 km)
GPS_A_M = 26_559_700.0  # GPS nominal semi-major axis (SPS PS 2020, table 3.2-1)

# Nominal satellite naming for BDS-3 (ours, documented; the fault schedules of seed 001 name "GEO3").
# GEOs are numbered west to east: GEO1 = C01 at 80 E, GEO2 = C02 at 110.5 E, GEO3 = C03 at 140 E.
# (The real BDS-2 PRNs differ: C01 140 E, C02 80 E, C03 110.5 E. This is a nominal simulation
# naming so that "GEO3" and "C03" are the same satellite.)
BDS_GEO_LON_DEG = {"C01": 80.0, "C02": 110.5, "C03": 140.0}
# IGSO: three planes 120 deg apart in right ascension, phased 120 deg apart in argument of latitude so
# that all three follow one figure-eight ground track whose equator crossings are at 118 E.
BDS_IGSO_IDS = ("C38", "C39", "C40")
BDS_IGSO_NODE_LON_DEG = 118.0
BDS_INCLINATION_DEG = 55.0
# MEO: Walker 24/3/1 (i = 55 deg, 21,528 km). Planes A, B, C at right ascension raan0 + 0, 120, 240
# deg; slot j of plane p at argument of latitude u0 + 45 j + 15 p. The PRNs are the real BDS-3 MEO
# satellites in their real planes and slot order, and raan0, u0 are fitted to the CODE SP3 orbits of
# 2021-04-28 18:00 GPST: every real satellite is within 1.3 deg (node) and 2 deg (argument of
# latitude) of its nominal slot there (tests/test_gnss_orbits.py checks this).
BDS_MEO_PLANES = (
    ("C21", "C22", "C19", "C20", "C32", "C41", "C33", "C42"),  # plane A
    ("C46", "C37", "C23", "C25", "C24", "C26", "C45", "C36"),  # plane B
    ("C43", "C34", "C44", "C35", "C29", "C30", "C27", "C28"),  # plane C
)
BDS_MEO_IDS = tuple(s for plane in BDS_MEO_PLANES for s in plane)
BDS_MEO_RAAN0_DEG = -1.29  # plane A node, from the ECEF x axis at NOMINAL_EPOCH_GPS_S
BDS_MEO_U0_DEG = 38.05  # plane A slot 0 argument of latitude at NOMINAL_EPOCH_GPS_S
GPS_NOMINAL_IDS = tuple(f"G{n:02d}" for n in range(1, 25))  # Walker 24/6/2, planes A-F, 4 slots each

NOMINAL_ALIASES: dict[str, str] = {
    "GEO1": "C01",
    "GEO2": "C02",
    "GEO3": "C03",
    "IGSO1": "C38",
    "IGSO2": "C39",
    "IGSO3": "C40",
}
"""Role names used in papers and scenarios -> nominal satellite ids (e.g. ``"GEO3" -> "C03"``)."""


def resolve_sat_id(name: str) -> str:
    """A role name (``"GEO3"``, ``"igso1"``; any case) or an id (``"C03"``) -> the satellite id."""
    return NOMINAL_ALIASES.get(name.upper(), name)


@dataclass(frozen=True)
class CircularElements:
    """Circular-orbit elements of N satellites at :data:`NOMINAL_EPOCH_GPS_S`.

    ``raan_rad`` is the right ascension of the ascending node in the nominal inertial frame (= the
    ECEF frame at the reference epoch, so it is also the node's longitude at that instant);
    ``arg_lat_rad`` is the argument of latitude at the reference epoch.
    """

    ids: tuple[str, ...]
    a_m: np.ndarray
    inc_rad: np.ndarray
    raan_rad: np.ndarray
    arg_lat_rad: np.ndarray

    @property
    def mean_motion_rps(self) -> np.ndarray:
        return np.sqrt(GM_M3PS2 / self.a_m**3)


def walker_elements(
    ids: Sequence[str],
    a_m: float,
    inc_deg: float,
    planes: int,
    phasing: int,
    raan0_deg: float = 0.0,
    u0_deg: float = 0.0,
) -> CircularElements:
    """Walker-delta T/P/F constellation (T = len(ids)): planes ``360/P`` apart, slots ``360/S`` apart in
    a plane (S = T/P), and slot phase offset ``F * 360 / T`` from one plane to the next; plane 0 slot 0
    at node ``raan0_deg`` and argument of latitude ``u0_deg``. Satellites are listed plane by plane."""
    total = len(ids)
    if total % planes:
        raise ValueError(f"Walker: {total} satellites do not divide into {planes} planes")
    per_plane = total // planes
    p = np.repeat(np.arange(planes), per_plane)
    j = np.tile(np.arange(per_plane), planes)
    raan = np.radians(raan0_deg + p * 360.0 / planes)
    u = np.radians(u0_deg + j * 360.0 / per_plane + p * phasing * 360.0 / total)
    n = len(ids)
    return CircularElements(tuple(ids), np.full(n, a_m), np.full(n, math.radians(inc_deg)), raan, u)


def bds3_elements(
    include: Sequence[Literal["GEO", "IGSO", "MEO"]] = ("GEO", "IGSO", "MEO"),
) -> CircularElements:
    """Nominal BDS-3: 3 GEO (80, 110.5, 140 E), 3 IGSO (55 deg, 118 E crossing), 24 MEO Walker 24/3/1."""
    parts: list[CircularElements] = []
    if "GEO" in include:
        ids = tuple(BDS_GEO_LON_DEG)
        lon = np.radians([BDS_GEO_LON_DEG[s] for s in ids])
        parts.append(CircularElements(ids, np.full(3, GEOSYNC_A_M), np.zeros(3), lon, np.zeros(3)))
    if "IGSO" in include:
        k = np.arange(3)
        # node longitude = raan + arg_lat (mean motion = earth rate) stays 118 E for all three
        raan = np.radians(BDS_IGSO_NODE_LON_DEG + 120.0 * k)
        u = np.radians(-120.0 * k)
        parts.append(
            CircularElements(
                BDS_IGSO_IDS, np.full(3, GEOSYNC_A_M), np.full(3, math.radians(BDS_INCLINATION_DEG)), raan, u
            )
        )
    if "MEO" in include:
        parts.append(
            walker_elements(
                BDS_MEO_IDS,
                BDS_MEO_A_M,
                BDS_INCLINATION_DEG,
                planes=3,
                phasing=1,
                raan0_deg=BDS_MEO_RAAN0_DEG,
                u0_deg=BDS_MEO_U0_DEG,
            )
        )
    return _concat(parts)


def gps_nominal_elements() -> CircularElements:
    """Nominal GPS as a Walker 24/6/2 at 26,559.7 km, 55 deg (an approximation of the 24-slot
    baseline of the SPS Performance Standard, whose slots are unevenly spaced; not the slot table)."""
    return walker_elements(GPS_NOMINAL_IDS, GPS_A_M, 55.0, planes=6, phasing=2)


def _concat(parts: Sequence[CircularElements]) -> CircularElements:
    return CircularElements(
        tuple(s for p in parts for s in p.ids),
        np.concatenate([p.a_m for p in parts]),
        np.concatenate([p.inc_rad for p in parts]),
        np.concatenate([p.raan_rad for p in parts]),
        np.concatenate([p.arg_lat_rad for p in parts]),
    )


class NominalConstellation:
    """Keplerian circular orbits (no perturbations) in the nominal inertial frame, rotated to ECEF.

    Position ``r_e = R3(omega_e dt) R3(-raan) R1(-i) [a cos u, a sin u, 0]`` with ``u = u0 + n dt`` and
    ``dt = t - NOMINAL_EPOCH_GPS_S``; ECEF velocity ``v_e = R3(omega_e dt) v_i - omega_e x r_e``.
    GEOs (i = 0, n = omega_e) are fixed in ECEF. Satellite clocks are ideal (zero) unless
    ``clock_s`` gives constant offsets per satellite.

    Parameters
    ----------
    constellations : "BDS" and/or "GPS".
    clock_s : optional {id: constant clock offset, s}.
    """

    def __init__(
        self, constellations: Sequence[Constellation] = ("BDS",), clock_s: dict[str, float] | None = None
    ):
        parts = []
        for c in constellations:
            if c == "BDS":
                parts.append(bds3_elements())
            elif c == "GPS":
                parts.append(gps_nominal_elements())
            else:
                raise ValueError(f"constellations: unknown constellation {c!r} (use 'BDS' or 'GPS')")
        self.elements = _concat(parts)
        self._index = {s: k for k, s in enumerate(self.elements.ids)}
        self._clock = np.array([(clock_s or {}).get(s, 0.0) for s in self.elements.ids])

    def satellite_ids(self) -> list[str]:
        return sorted(self.elements.ids)

    def states(self, ids: Sequence[str], t_gps_s: float | np.ndarray) -> SatStates:
        t = _times_for(ids, t_gps_s)
        try:
            k = np.array([self._index[s] for s in ids], dtype=int)
        except KeyError as e:
            raise KeyError(f"satellite {e.args[0]} is not in the nominal constellation") from None
        el = self.elements
        a, inc, raan, u0 = el.a_m[k], el.inc_rad[k], el.raan_rad[k], el.arg_lat_rad[k]
        n = el.mean_motion_rps[k]
        dt = t - NOMINAL_EPOCH_GPS_S
        u = u0 + n * dt
        cu, su, ci, si = np.cos(u), np.sin(u), np.cos(inc), np.sin(inc)
        # In-plane position and inertial velocity, then R3(-raan) R1(-i).
        xp, yp = a * cu, a * su
        vxp, vyp = -a * n * su, a * n * cu
        theta = raan - OMEGA_IE_RPS * dt  # node longitude in the ECEF frame at t
        co, so = np.cos(theta), np.sin(theta)
        pos = np.stack([xp * co - yp * ci * so, xp * so + yp * ci * co, yp * si], axis=-1)
        vel_i = np.stack([vxp * co - vyp * ci * so, vxp * so + vyp * ci * co, vyp * si], axis=-1)
        # v_ecef = R v_inertial - omega x r_ecef (R already folded into theta)
        vel = vel_i + OMEGA_IE_RPS * np.stack([pos[:, 1], -pos[:, 0], np.zeros(len(k))], axis=-1)
        zeros = np.zeros(len(k))
        return SatStates(tuple(ids), pos, vel, self._clock[k].copy(), zeros)


# --- orbit diagnostics ----------------------------------------------------------------------------------
def inertial_orbit_geometry(pos_ecef_m: np.ndarray, vel_ecef_mps: np.ndarray) -> dict[str, np.ndarray]:
    """Radius, inclination and node longitude from ECEF states (N, 3) (two-body, circular approx.).

    Works in the inertial frame aligned with ECEF at the state's epoch: ``v_i = v_e + omega x r``,
    ``h = r x v_i``. Node longitude (longitude of the ascending equator crossing, as it happens)
    is ``raan_ecef + omega_e * u / n`` with ``u`` the argument of latitude and ``n`` the mean motion
    (for a geosynchronous orbit ``raan_ecef + u``): the earth turned that much since the crossing.

    Returns dict of (N,) arrays: ``radius_m``, ``inclination_deg``, ``raan_ecef_deg`` (node direction
    from the ECEF x axis at the state's epoch), ``arg_lat_deg``, ``node_lon_deg``, ``lon_deg``
    (sub-satellite longitude); angles in (-180, 180].
    """
    r = np.asarray(pos_ecef_m, dtype=float)
    v = np.asarray(vel_ecef_mps, dtype=float)
    v_i = v + OMEGA_IE_RPS * np.stack([-r[:, 1], r[:, 0], np.zeros(len(r))], axis=-1)
    h = np.cross(r, v_i)
    hn = np.linalg.norm(h, axis=1)
    inc = np.arccos(np.clip(h[:, 2] / hn, -1.0, 1.0))
    node = np.stack([-h[:, 1], h[:, 0], np.zeros(len(r))], axis=-1)  # z x h
    raan = np.arctan2(node[:, 1], node[:, 0])
    rn = np.linalg.norm(r, axis=1)
    nn = np.maximum(np.linalg.norm(node, axis=1), 1e-300)
    cos_u = np.sum(node * r, axis=1) / (nn * rn)
    sin_u = r[:, 2] / (rn * np.maximum(np.sin(inc), 1e-300))
    u = np.arctan2(sin_u, cos_u)  # argument of latitude (only meaningful for inclined orbits)
    mean_motion = np.sqrt(GM_M3PS2 / rn**3)
    node_lon = raan + OMEGA_IE_RPS * u / mean_motion
    return {
        "radius_m": rn,
        "inclination_deg": np.degrees(inc),
        "raan_ecef_deg": np.degrees(raan),
        "arg_lat_deg": np.degrees(u),
        "node_lon_deg": np.degrees(np.arctan2(np.sin(node_lon), np.cos(node_lon))),
        "lon_deg": np.degrees(np.arctan2(r[:, 1], r[:, 0])),
    }


# ======================================================================================================
# Ranging model (shared with the service; depends only on numpy and service.earth)
# ======================================================================================================
RANGE_ITERATIONS = 3  # light-time fixed point: each iteration shrinks the error by ~omega r / c ~ 1e-5


def predicted_range(rx_pos_ecef_m: np.ndarray, sat_pos_ecef_m: np.ndarray) -> np.ndarray:
    """Geometric range (N,) in metres; see :func:`range_geometry`. A pseudorange is predicted as
    ``predicted_range + rx_clock_bias_m - sat_clock_m (+ atmosphere)``."""
    return range_geometry(rx_pos_ecef_m, sat_pos_ecef_m).range_m


def predicted_range_rate(
    rx_pos_ecef_m: np.ndarray,
    rx_vel_ecef_mps: np.ndarray,
    sat_pos_ecef_m: np.ndarray,
    sat_vel_ecef_mps: np.ndarray,
) -> np.ndarray:
    """Geometric range rate (N,) in m/s; a pseudorange rate is predicted as
    ``predicted_range_rate + rx_clock_drift_mps - sat_clock_drift_mps``."""
    g = range_geometry(rx_pos_ecef_m, sat_pos_ecef_m, rx_vel_ecef_mps, sat_vel_ecef_mps)
    assert g.range_rate_mps is not None
    return g.range_rate_mps


def light_time_states(
    source: OrbitSource,
    ids: Sequence[str],
    t_rx_gps_s: float,
    rx_pos_ecef_m: np.ndarray,
    rx_vel_ecef_mps: np.ndarray | None = None,
) -> tuple[SatStates, RangeGeometry]:
    """Satellite states at their transmit times ``t_t = t_r - rho/c`` for a receiver at ``rx_pos_ecef_m``.

    Iterates the light time (geometric; satellite clocks do not enter the geometry) until the
    transmit time is consistent with the range to machine precision (four passes; the last pass's
    geometry is that of the returned states). With ``rx_vel_ecef_mps`` the geometry includes the
    range rate.
    """
    rx = np.asarray(rx_pos_ecef_m, dtype=float).reshape(3)
    tau = np.full(len(ids), 0.075)
    for _ in range(4):
        st = source.states(ids, t_rx_gps_s - tau)
        geo = range_geometry(
            rx, st.pos_ecef_m, rx_vel_ecef_mps, st.vel_ecef_mps if rx_vel_ecef_mps is not None else None
        )
        tau = geo.light_time_s
    return st, geo
