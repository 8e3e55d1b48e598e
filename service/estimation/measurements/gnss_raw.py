"""Receiver-side GNSS ranging model and the tightly coupled measurement rows (seed 001).

Ranging model (must equal the simulator's ``simulators/gnss/orbits.range_geometry``; the service
does not import simulators, so the model is written out here and a test compares the two)
--------------------------------------------------------------------------------------------
A ``SatObservation`` carries the satellite position/velocity at its *transmit* time, expressed in
the ECEF frame *of the transmit time* (as an ephemeris gives it), and the message time ``t`` is
the GPS time of reception. The geometric range solves

    rho = | R3(omega_e rho / c) r_s - r_r |                          (exact earth rotation, Sagnac)

by fixed-point iteration from ``rho_0 = |r_s - r_r|`` (``RANGE_ITERATIONS`` passes; to first order
this is ``|r_s - r_r| + (omega_e / c)(x_s y_r - y_s x_r)``). With ``u`` the unit line of sight
from the receiver to the rotated satellite position (ECEF of the receive time), the range rate is
the exact receive-time derivative

    rho_dot = u . (R3 v_s - v_r) / (1 + u . R3 (v_s + omega_e x r_s) / c)

(the denominator is the light-time "Doppler factor", 1 +- 1e-5). Predicted observables:

    pseudorange = rho + b - sat_clock_m                    b: receiver clock bias, m
    range_rate  = rho_dot + d - sat_clock_drift_mps        d: receiver clock drift, m/s

No lever arm (antenna at the IMU). Optional (``GnssRawModel`` options, all off by default so the
simulator's scenarios keep their model): the broadcast Klobuchar ionosphere of the message
(``GnssRaw.iono``; GPS IS-GPS-200N 20.3.3.5.2.5, BeiDou BDS-SIS-ICD-B1I 5.2.4.7) and the
Saastamoinen troposphere with the DO-229 mapping function are added to the predicted pseudorange
(:mod:`~service.estimation.measurements.atmosphere`); elevation weighting divides the message's
zenith variances by ``sin^2 E`` (E floored at 5 deg); one inter-system bias (ISB, m) per listed
extra constellation is a private random-walk state added to its satellites' pseudoranges (the
receiver clock is that of every other constellation, GPS first).

Measurement rows (z = INS-predicted minus measured, error state x = computed minus true)
-------------------------------------------------------------------------------------
State order: the 15 INS error states of :mod:`service.ins.error_model` (position error in ENU
metres), then the clock bias error (m) and drift error (m/s) at indices 15, 16.

    d rho / d r_r = -u (ECEF)  and  dp_ecef = C_en dp_enu   =>   H_pos = -(C_ne u)' = -u_enu'

i.e. rho grows when the receiver moves away from the satellite (dp along -u). The clock error
enters with +1. Range rate: ``d rho_dot / d v_r = -f u`` (f the Doppler factor) so
``H_vel = -f u_enu'`` and +1 on the drift error. The dependence of rho_dot on the receiver
*position* (through u; ~|v_s - v_r| / rho ~ 1e-4 per metre) and the frame error of C_en due to
the INS position error (~|v| |dp| / R) are neglected, as in seed 001 and the standard form.

Late aiding (``dt_late_s`` > 0, INS ahead of the measurement): the receiver position and clock
bias are carried back to the measurement time with the INS velocity and the clock drift, and the
velocity (and the position, to second order) with the INS's acceleration (``ctx.acc_enu_mps2``).
"""

from __future__ import annotations

import functools
import math
from dataclasses import dataclass

import numpy as np
import scipy.linalg

from fednav.service import earth
from fednav.service.estimation.measurements import atmosphere
from fednav.service.estimation.measurements.base import Measurement, ModelContext, PrivateStates
from fednav.service.ins import error_model as em
from fednav.service.messages import GnssRaw

RANGE_ITERATIONS = 3  # light-time fixed point; each pass shrinks the error by ~omega r / c ~ 1e-5
CLK_BIAS, CLK_DRIFT = 15, 16
N_STATES_TC = 17
CLOCK = slice(15, 17)


def earth_rotation_matrices(angle_rad: np.ndarray) -> np.ndarray:
    """R3(angle) for (N,) angles -> (N, 3, 3): coordinates of an inertially fixed point in an ECEF
    frame that has turned by ``angle`` since are ``R3 @ r``."""
    c, s = np.cos(angle_rad), np.sin(angle_rad)
    out = np.zeros(np.shape(c) + (3, 3))
    out[..., 0, 0] = c
    out[..., 0, 1] = s
    out[..., 1, 0] = -s
    out[..., 1, 1] = c
    out[..., 2, 2] = 1.0
    return out


@dataclass(frozen=True)
class RangeGeometry:
    """Geometry of N receiver-satellite links (module docstring).

    range_m (N,); los_ecef (N, 3) unit vectors receiver -> satellite at receive time
    (``d rho / d r_r = -los_ecef``); sat_pos_rx_frame_m (N, 3); light_time_s (N,);
    range_rate_mps (N,) or None; doppler_factor (N,) or None.
    """

    range_m: np.ndarray
    los_ecef: np.ndarray
    sat_pos_rx_frame_m: np.ndarray
    light_time_s: np.ndarray
    range_rate_mps: np.ndarray | None = None
    doppler_factor: np.ndarray | None = None


def _row_norms(d: np.ndarray) -> np.ndarray:
    """``np.linalg.norm(d, axis=1)`` of real (N, 3) rows, bit for bit, without its checks."""
    return np.sqrt(np.add.reduce(d * d, axis=1))


def _rotate(c: np.ndarray, s: np.ndarray, v: np.ndarray) -> np.ndarray:
    """Rows of ``v`` (N, 3) rotated by R3 (cosines ``c``, sines ``s``): what
    ``einsum("nij,nj->ni", earth_rotation_matrices(angle), v)`` gives, bit for bit, without the
    3x3 matrices."""
    out = np.empty_like(v)
    v0, v1 = v[:, 0], v[:, 1]
    np.add(c * v0, s * v1, out=out[:, 0])
    np.add((-s) * v0, c * v1, out=out[:, 1])
    out[:, 2] = v[:, 2]
    return out


def range_geometry(
    rx_pos_ecef_m: np.ndarray,
    sat_pos_ecef_m: np.ndarray,
    rx_vel_ecef_mps: np.ndarray | None = None,
    sat_vel_ecef_mps: np.ndarray | None = None,
) -> RangeGeometry:
    """Geometric range (and range rate) to satellites given at their transmit time (module docstring).

    Parameters
    ----------
    rx_pos_ecef_m : (3,) receiver position at receive time, ECEF.
    sat_pos_ecef_m : (N, 3) satellite positions at transmit time, ECEF of the transmit time.
    rx_vel_ecef_mps : (3,) receiver ECEF velocity (optional).
    sat_vel_ecef_mps : (N, 3) satellite ECEF velocities at transmit time (optional).
    """
    r_rx = np.asarray(rx_pos_ecef_m, dtype=float).reshape(3)
    r_s = np.atleast_2d(np.asarray(sat_pos_ecef_m, dtype=float))
    d = r_s - r_rx
    rho = _row_norms(d)
    r_rot = r_s
    if not RANGE_ITERATIONS:
        c, s = np.ones(len(r_s)), np.zeros(len(r_s))  # R3 of the earth rotation angle: cos, sin
    for _ in range(RANGE_ITERATIONS):
        angle = earth.OMEGA_IE_RPS * rho / earth.C_MPS
        c, s = np.cos(angle), np.sin(angle)
        r_rot = _rotate(c, s, r_s)
        d = r_rot - r_rx
        rho = _row_norms(d)
    los = d / rho[:, None]
    rate = factor = None
    if rx_vel_ecef_mps is not None and sat_vel_ecef_mps is not None:
        v_rx = np.asarray(rx_vel_ecef_mps, dtype=float).reshape(3)
        v_s = np.atleast_2d(np.asarray(sat_vel_ecef_mps, dtype=float))
        # inertial velocity of the satellite (ECEF velocity + omega x r), then rotated like r
        w = np.zeros_like(r_s)
        w[:, 0], w[:, 1] = -r_s[:, 1], r_s[:, 0]
        v_in = v_s + earth.OMEGA_IE_RPS * w
        v_rot = _rotate(c, s, v_s)
        v_in_rot = _rotate(c, s, v_in)
        # np.add.reduce: what np.sum calls, without its Python wrappers
        factor = 1.0 / (1.0 + np.add.reduce(los * v_in_rot, axis=1) / earth.C_MPS)
        rate = np.add.reduce(los * (v_rot - v_rx), axis=1) * factor
    return RangeGeometry(rho, los, r_rot, rho / earth.C_MPS, rate, factor)


@dataclass(frozen=True)
class SatArrays:
    """One GnssRaw epoch as arrays, in message order. Shapes (N,) or (N, 3)."""

    ids: tuple[str, ...]
    pseudorange_m: np.ndarray
    range_rate_mps: np.ndarray
    pseudorange_sigma_m: np.ndarray
    range_rate_sigma_mps: np.ndarray
    sat_pos_ecef_m: np.ndarray
    sat_vel_ecef_mps: np.ndarray
    sat_clock_m: np.ndarray
    sat_clock_drift_mps: np.ndarray

    def take(self, idx) -> SatArrays:
        idx = np.asarray(idx, dtype=int)
        return SatArrays(
            tuple(self.ids[i] for i in idx),
            self.pseudorange_m[idx],
            self.range_rate_mps[idx],
            self.pseudorange_sigma_m[idx],
            self.range_rate_sigma_mps[idx],
            self.sat_pos_ecef_m[idx].reshape(-1, 3),
            self.sat_vel_ecef_mps[idx].reshape(-1, 3),
            self.sat_clock_m[idx],
            self.sat_clock_drift_mps[idx],
        )


def sat_arrays(msg: GnssRaw) -> SatArrays:
    s = msg.sats
    # one pass over the observations, one array: columns pseudorange, range rate, their sigmas,
    # satellite clock and drift, position (3), velocity (3)
    a = np.array(
        [
            (
                o.pseudorange_m,
                o.range_rate_mps,
                o.pseudorange_sigma_m,
                o.range_rate_sigma_mps,
                o.sat_clock_m,
                o.sat_clock_drift_mps,
                *o.sat_pos_ecef_m,
                *o.sat_vel_ecef_mps,
            )
            for o in s
        ],
        dtype=float,
    ).reshape(-1, 12)
    c = a.T.copy()  # one copy: each scalar column a contiguous row of its own
    return SatArrays(
        tuple(o.id for o in s),
        c[0],
        c[1],
        c[2],
        c[3],
        a[:, 6:9].copy(),
        a[:, 9:12].copy(),
        c[4],
        c[5],
    )


@dataclass(frozen=True)
class Receiver:
    """Receiver state the rows are linearised about (INS position/velocity + clock reference)."""

    pos_ecef_m: np.ndarray  # (3,)
    vel_ecef_mps: np.ndarray  # (3,)
    mat_en: np.ndarray  # (3, 3) ENU -> ECEF at the INS position
    clock_bias_m: float
    clock_drift_mps: float


def receiver_from_nav(
    nav, clock_bias_m: float, clock_drift_mps: float, dt_late_s: float = 0.0, acc_enu_mps2=None
) -> Receiver:
    """Receiver at the measurement time ``nav.t - dt_late_s`` from an INS NavState; with the INS's
    acceleration (``acc_enu_mps2``, ENU) its velocity is taken back to that time too and its
    position to second order (until 2026-12-01 the range rates of a late epoch were predicted
    from the velocity at the INS time: acceleration x lateness on every row)."""
    c_en = earth.mat_en(nav.lat_rad, nav.lon_rad)
    pos = earth.llh_to_ecef_f(float(nav.lat_rad), float(nav.lon_rad), float(nav.h_m))
    vel = c_en @ np.asarray(nav.vel_enu_mps, dtype=float)
    if dt_late_s:
        pos = pos - vel * dt_late_s
        if acc_enu_mps2 is not None:
            acc = c_en @ np.asarray(acc_enu_mps2, dtype=float)
            pos = pos + acc * (0.5 * dt_late_s * dt_late_s)
            vel = vel - acc * dt_late_s
        clock_bias_m = clock_bias_m - clock_drift_mps * dt_late_s
    return Receiver(pos, vel, c_en, float(clock_bias_m), float(clock_drift_mps))


@dataclass(frozen=True)
class Predicted:
    """Predicted observables and line-of-sight data of N satellites."""

    pseudorange_m: np.ndarray  # (N,)
    range_rate_mps: np.ndarray  # (N,)
    los_enu: np.ndarray  # (N, 3) receiver -> satellite, ENU at the receiver
    doppler_factor: np.ndarray  # (N,)
    elevation_rad: np.ndarray  # (N,)


def predict(rx: Receiver, sats: SatArrays) -> Predicted:
    g = range_geometry(rx.pos_ecef_m, sats.sat_pos_ecef_m, rx.vel_ecef_mps, sats.sat_vel_ecef_mps)
    los_enu = g.los_ecef @ rx.mat_en  # C_ne u  (rows)
    pr = g.range_m + rx.clock_bias_m - sats.sat_clock_m
    rr = g.range_rate_mps + rx.clock_drift_mps - sats.sat_clock_drift_mps
    el = np.arcsin(np.minimum(np.maximum(los_enu[:, 2], -1.0), 1.0))  # np.clip's values, without its wrappers
    return Predicted(pr, rr, los_enu, g.doppler_factor, el)


@dataclass(frozen=True)
class RawRows:
    """Tightly coupled rows of N satellites: z = H x + v, R = diag(r_var).

    z (m,); H (m, n_states); r_var (m,); row_sat (m,) satellite index of each row (into ``ids``);
    labels (m,) like ``"C03.pr"``/``"C03.rr"``. Pseudorange rows first, then range-rate rows.
    """

    z: np.ndarray
    H: np.ndarray
    r_var: np.ndarray
    row_sat: np.ndarray
    labels: tuple[str, ...]
    ids: tuple[str, ...]


def raw_rows(
    pred: Predicted,
    sats: SatArrays,
    use_range_rate: bool = True,
    n_states: int = N_STATES_TC,
    clock: slice = CLOCK,
) -> RawRows:
    """Rows of the tightly coupled EKF (module docstring for the derivation and signs); ``clock``
    the filter columns of the clock bias and drift errors."""
    n = len(sats.ids)
    clk_bias, clk_drift = clock.start, clock.start + 1
    H_pr = np.zeros((n, n_states))
    H_pr[:, em.POS] = -pred.los_enu
    H_pr[:, clk_bias] = 1.0
    z = [pred.pseudorange_m - sats.pseudorange_m]
    H = [H_pr]
    r = [np.square(sats.pseudorange_sigma_m)]
    row_sat = [np.arange(n)]
    labels = _row_labels(sats.ids, use_range_rate)
    if use_range_rate:
        H_rr = np.zeros((n, n_states))
        H_rr[:, em.VEL] = -pred.doppler_factor[:, None] * pred.los_enu
        H_rr[:, clk_drift] = 1.0
        z.append(pred.range_rate_mps - sats.range_rate_mps)
        H.append(H_rr)
        r.append(np.square(sats.range_rate_sigma_mps))
        row_sat.append(np.arange(n))
    return RawRows(
        np.concatenate(z),
        np.concatenate(H),
        np.concatenate(r),
        np.concatenate(row_sat),
        labels,
        sats.ids,
    )


@functools.lru_cache(maxsize=256)
def _row_labels(ids: tuple[str, ...], range_rate: bool) -> tuple[str, ...]:
    """The rows' labels of satellites ``ids`` (a receiver's set repeats from epoch to epoch)."""
    return tuple(f"{s}.pr" for s in ids) + (tuple(f"{s}.rr" for s in ids) if range_rate else ())


CONSTELLATION_OF_PREFIX = {"G": "GPS", "C": "BDS", "E": "GAL", "R": "GLO", "J": "QZS"}


def azimuth(pred: Predicted) -> np.ndarray:
    """(N,) azimuth (rad, clockwise from north) of the lines of sight."""
    return np.arctan2(pred.los_enu[:, 0], pred.los_enu[:, 1])


def atmosphere_delay_m(
    nav, pred: Predicted, sats: SatArrays, msg: GnssRaw, troposphere: bool, ionosphere: bool
) -> np.ndarray:
    """(N,) modelled pseudorange delays (m) at the INS position: troposphere (Saastamoinen zenith x
    DO-229 mapping) and broadcast Klobuchar ionosphere. The signal is taken as GPS L1 / Galileo E1
    / BeiDou B1I (what ``simulators.gnss.rinex_raw`` writes). GPS coefficients serve Galileo E1
    (same carrier; NeQuick-G is not implemented) and, scaled by (f_L1 / f_B1I)^2, BeiDou when the
    message has no BeiDou coefficients; satellites with no coefficients get no ionosphere."""
    n = len(sats.ids)
    delay = np.zeros(n)
    if n == 0:
        return delay
    el = np.maximum(pred.elevation_rad, 0.0)
    if troposphere:
        delay += atmosphere.saastamoinen_zenith_m(nav.lat_rad, nav.h_m) * atmosphere.tropo_mapping(el)
    if ionosphere and msg.iono:
        coef = {k.constellation: k for k in msg.iono}
        az = azimuth(pred)
        pre = np.array([sid[0] for sid in sats.ids])
        args = (nav.lat_rad, nav.lon_rad, el, az, msg.t)
        if "GPS" in coef:
            k = coef["GPS"]
            gps = atmosphere.C_MPS * atmosphere.klobuchar_gps_s(k.alpha, k.beta, *args)
            use = np.isin(pre, ("G", "E", "J"))
            delay[use] += gps[use]
            if "BDS" not in coef:
                ratio = (atmosphere.GPS_L1_HZ / atmosphere.BDS_B1I_HZ) ** 2
                delay[pre == "C"] += ratio * gps[pre == "C"]
        if "BDS" in coef:
            k = coef["BDS"]
            bds = atmosphere.C_MPS * atmosphere.klobuchar_bds_s(k.alpha, k.beta, *args)
            delay[pre == "C"] += bds[pre == "C"]
    return delay


def clock_from_residuals(rx: Receiver, sats: SatArrays) -> tuple[float, float]:
    """Receiver clock bias (m) and drift (m/s) as the mean residual of all satellites with the
    receiver clock set to zero (first-epoch initialisation; the INS position/velocity errors and
    any fault go into it, which the clock prior's sigma must cover)."""
    rx0 = Receiver(rx.pos_ecef_m, rx.vel_ecef_mps, rx.mat_en, 0.0, 0.0)
    p = predict(rx0, sats)
    return float(np.mean(sats.pseudorange_m - p.pseudorange_m)), float(
        np.mean(sats.range_rate_mps - p.range_rate_mps)
    )


def elevation_mask(pred: Predicted, mask_deg: float) -> np.ndarray:
    """(N,) bool: satellites at or above the elevation mask seen from the INS position."""
    return pred.elevation_rad >= math.radians(mask_deg) - 1e-12


# --- the measurement model (the hook) -----------------------------------------------------------------
def clock_transition(
    T: float, correlation_time_s: float, bias_psd_m2ps: float, drift_psd_m2ps3: float
) -> tuple[np.ndarray, np.ndarray]:
    """Exact discrete receiver-clock model over T: (Phi (2, 2), Qd (2, 2)) for x = [bias_m, drift_mps]

        d(b)/dt = d + w_b,   d(d)/dt = -beta d + w_d    (first-order Markov drift, beta = 1/tau)

    F = [[0, 1], [0, -beta]], Qc = diag(S_b, S_d); Van Loan: expm([[-F, Qc], [0, F']] T).
    """
    beta = 1.0 / correlation_time_s
    F = np.array([[0.0, 1.0], [0.0, -beta]])
    M = np.zeros((4, 4))
    M[:2, :2] = -F
    M[:2, 2:] = np.diag([bias_psd_m2ps, drift_psd_m2ps3])
    M[2:, 2:] = F.T
    E = scipy.linalg.expm(M * T)
    Phi = E[2:, 2:].T
    Qd = Phi @ E[:2, 2:]
    return Phi, 0.5 * (Qd + Qd.T)


class GnssRawModel:
    """Pseudorange (+ range rate) rows of every usable satellite, receiver clock as private states.

    Usable: at or above the elevation mask seen from the INS, first observation of its id in the
    message. Rows are grouped by satellite (``groups`` / ``group_ids``), pseudorange rows first,
    then range-rate rows, satellites in message order. The clock's linearisation point is
    ``ctx.reference["clock"]`` = [bias_m, drift_mps] (closed loop, kept by the filter bank).
    """

    kind = "gnss_raw"

    def __init__(
        self,
        *,
        correlation_time_s: float,
        bias_psd_m2ps: float,
        drift_psd_m2ps3: float,
        init_bias_std_m: float,
        init_drift_std_mps: float,
        elevation_mask_deg: float = 5.0,
        use_range_rate: bool = True,
        troposphere: bool = False,
        ionosphere: bool = False,
        elevation_weighting: bool = False,
        isb_constellations: tuple[str, ...] = (),
        isb_psd_m2ps: float = 1e-4,
        init_isb_std_m: float = 1000.0,
    ):
        self.elevation_mask_deg = float(elevation_mask_deg)
        self.use_range_rate = bool(use_range_rate)
        self.troposphere = bool(troposphere)
        self.ionosphere = bool(ionosphere)
        self.elevation_weighting = bool(elevation_weighting)
        self.isb_constellations = tuple(isb_constellations)
        params = (correlation_time_s, bias_psd_m2ps, drift_psd_m2ps3)
        cache: dict[float, tuple[np.ndarray, np.ndarray]] = {}

        def transition(T: float) -> tuple[np.ndarray, np.ndarray]:
            key = round(T, 12)
            out = cache.get(key)
            if out is None:
                if len(cache) > 32:
                    cache.clear()
                out = cache[key] = clock_transition(T, *params)
            return out

        blocks = [
            PrivateStates(
                "clock", ("clk_bias_m", "clk_drift_mps"), transition, (init_bias_std_m, init_drift_std_mps)
            )
        ]
        if self.isb_constellations:
            k = len(self.isb_constellations)

            def isb_transition(T: float) -> tuple[np.ndarray, np.ndarray]:
                return np.eye(k), np.eye(k) * isb_psd_m2ps * abs(T)  # random walk

            blocks.append(
                PrivateStates(
                    "isb",
                    tuple(f"isb_{c}_m" for c in self.isb_constellations),
                    isb_transition,
                    (init_isb_std_m,) * k,
                )
            )
        self.private_states = tuple(blocks)

    def _isb_index(self, sats: SatArrays) -> np.ndarray:
        """(N,) index into ``isb_constellations`` of each satellite, -1 for the clock's own."""
        idx = {c: j for j, c in enumerate(self.isb_constellations)}
        return np.array([idx.get(CONSTELLATION_OF_PREFIX.get(sid[0], ""), -1) for sid in sats.ids], dtype=int)

    def _predict(
        self, nav, rx: Receiver, sats: SatArrays, msg: GnssRaw, isb_m: np.ndarray | None
    ) -> Predicted:
        """Predicted observables with the configured atmosphere and inter-system biases."""
        pred = predict(rx, sats)
        extra = atmosphere_delay_m(nav, pred, sats, msg, self.troposphere, self.ionosphere)
        if isb_m is not None and len(sats.ids):
            j = self._isb_index(sats)
            extra = extra + np.where(j >= 0, np.asarray(isb_m)[np.maximum(j, 0)], 0.0)
        if not extra.any():
            return pred
        return Predicted(
            pred.pseudorange_m + extra,
            pred.range_rate_mps,
            pred.los_enu,
            pred.doppler_factor,
            pred.elevation_rad,
        )

    def initial_isb(
        self, nav, msg: GnssRaw, clock_ref: np.ndarray, dt_late_s: float = 0.0
    ) -> np.ndarray | None:
        """First-epoch ISB references (m): per listed constellation, the mean pseudorange residual of
        its satellites above the mask minus the clock bias (0 where none is seen); None without ISB."""
        if not self.isb_constellations:
            return None
        sats = sat_arrays(msg)
        out = np.zeros(len(self.isb_constellations))
        if not sats.ids:
            return out
        rx = receiver_from_nav(nav, clock_ref[0], clock_ref[1], dt_late_s)
        pred = self._predict(nav, rx, sats, msg, None)
        vis = elevation_mask(pred, self.elevation_mask_deg)
        j = self._isb_index(sats)
        res = sats.pseudorange_m - pred.pseudorange_m
        for c in range(len(out)):
            sel = vis & (j == c)
            if np.any(sel):
                out[c] = float(np.mean(res[sel]))
        return out

    def initial_clock(self, nav, msg: GnssRaw, dt_late_s: float = 0.0) -> np.ndarray | None:
        """First-epoch clock reference [bias_m, drift_mps]: the mean residual of the satellites
        above the mask with the receiver clock at zero; None when none is usable."""
        sats = sat_arrays(msg)
        if not sats.ids:
            return None
        rx0 = receiver_from_nav(nav, 0.0, 0.0, dt_late_s)
        pred0 = self._predict(nav, rx0, sats, msg, None)
        vis0 = elevation_mask(pred0, self.elevation_mask_deg)
        if self.isb_constellations and np.any(vis0 & (self._isb_index(sats) < 0)):
            vis0 = vis0 & (self._isb_index(sats) < 0)  # the clock is that of the non-ISB systems
        if not np.any(vis0):
            return None
        use = np.flatnonzero(vis0)
        return np.array(
            [
                float(np.mean(sats.pseudorange_m[use] - pred0.pseudorange_m[use])),
                float(np.mean(sats.range_rate_mps[use] - pred0.range_rate_mps[use])),
            ]
        )

    def __call__(self, nav, msg: GnssRaw, ctx: ModelContext) -> Measurement:
        """Rows of the usable satellites (none usable: zero rows -- an epoch without satellites
        is still an integrity epoch)."""
        sats = sat_arrays(msg)
        ref = ctx.reference["clock"]
        rx = receiver_from_nav(nav, ref[0], ref[1], ctx.dt_late_s, ctx.acc_enu_mps2)
        isb_ref = ctx.reference["isb"] if self.isb_constellations else None
        pred = self._predict(nav, rx, sats, msg, isb_ref)
        visible = elevation_mask(pred, self.elevation_mask_deg)
        rows = raw_rows(pred, sats, self.use_range_rate, ctx.n_states, ctx.columns["clock"])
        if self.elevation_weighting and len(sats.ids):
            sin_el = np.sin(np.clip(pred.elevation_rad, math.radians(5.0), math.pi / 2))
            rows = RawRows(
                rows.z, rows.H, rows.r_var / sin_el[rows.row_sat] ** 2, rows.row_sat, rows.labels, rows.ids
            )
        if isb_ref is not None and len(sats.ids):
            j = self._isb_index(sats)[rows.row_sat]
            pr_row = np.array([lab.endswith(".pr") for lab in rows.labels])
            cols = ctx.columns["isb"]
            for c in range(len(self.isb_constellations)):
                rows.H[pr_row & (j == c), cols.start + c] = 1.0
        first = {sid: i for i, sid in reversed(list(enumerate(sats.ids)))}
        usable = [i for i, sid in enumerate(sats.ids) if visible[i] and first[sid] == i]
        col = np.full(len(sats.ids), -1)
        col[usable] = np.arange(len(usable))
        if len(usable) == len(sats.ids):  # every satellite usable (the usual epoch): every row
            return Measurement(
                rows.z, rows.H, np.diag(rows.r_var), rows.labels, col[rows.row_sat], tuple(sats.ids)
            )
        sel = col[rows.row_sat] >= 0
        return Measurement(
            rows.z[sel],
            rows.H[sel],
            np.diag(rows.r_var[sel]),
            tuple(lab for lab, s in zip(rows.labels, sel, strict=True) if s),
            col[rows.row_sat[sel]],
            tuple(sats.ids[i] for i in usable),
        )


__all__ = [
    "GnssRawModel",
    "clock_transition",
    "CLK_BIAS",
    "CLK_DRIFT",
    "CLOCK",
    "N_STATES_TC",
    "RANGE_ITERATIONS",
    "Predicted",
    "RangeGeometry",
    "RawRows",
    "Receiver",
    "SatArrays",
    "atmosphere_delay_m",
    "azimuth",
    "clock_from_residuals",
    "earth_rotation_matrices",
    "elevation_mask",
    "predict",
    "range_geometry",
    "raw_rows",
    "receiver_from_nav",
    "sat_arrays",
]
