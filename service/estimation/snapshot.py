"""Snapshot (single-epoch) least-squares GNSS solutions, and a GNSS fix made from one raw epoch.

- :func:`solve_position`: Gauss-Newton single-point position and receiver clock from pseudoranges
  (the shared ranging model of :mod:`service.estimation.measurements.gnss_raw`: exact Earth
  rotation during the signal's flight, satellites given at transmission time).
- :func:`solve_velocity`: receiver velocity and clock drift from range rates at a known position
  (linear least squares).
- :func:`snapshot_fix`: a :class:`~service.messages.GnssFix` from one :class:`GnssRaw` epoch, so a
  vehicle with a raw receiver and no fix stream can align (static or in motion) and restart like
  one with a receiver solution. It uses the largest single constellation (one receiver clock), the
  message's own pseudorange/range-rate sigmas as weights, and inflates the position sigmas for the
  atmosphere it does not model (``ATMOSPHERE_STD_M``); an epoch whose residuals are far beyond their
  sigmas (an outlier the snapshot cannot isolate) gives no fix.

References: Groves, Principles of GNSS, Inertial, and Multisensor Integrated Navigation Systems,
2nd ed., sections 9.4.1 (single-epoch navigation solution) and 9.4.1.2 (velocity).
"""

from __future__ import annotations

import math
from collections import Counter
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

from fednav.service import earth
from fednav.service.earth import ecef_to_llh
from fednav.service.estimation.measurements.gnss_raw import range_geometry
from fednav.service.messages import GnssFix, GnssRaw

#: 1-sigma position error added in quadrature for the unmodelled ionosphere and troposphere (a
#: snapshot fix serves alignment only; the filters model the ranging themselves), m
ATMOSPHERE_STD_M = 8.0
#: velocity 1-sigma floor of a snapshot fix, m/s
VEL_STD_FLOOR_MPS = 0.05
#: an epoch whose weighted residual RMS exceeds this many sigmas gives no fix
MAX_NORMALISED_RESIDUAL = 5.0
#: satellites needed (4 unknowns + 1 for the residual check)
MIN_SATS = 5


@dataclass(frozen=True)
class PositionSolution:
    """Least-squares single-point solution. ``residuals_m`` (N,) = measured - predicted at the solution."""

    pos_ecef_m: np.ndarray
    clock_bias_m: float
    residuals_m: np.ndarray
    iterations: int
    converged: bool
    cov: np.ndarray  # (4, 4) (G' W G)^-1: x, y, z, clock (unit weights: in units of the ranging variance)

    @property
    def llh(self) -> np.ndarray:
        return ecef_to_llh(self.pos_ecef_m)


def solve_position(
    pseudorange_m: np.ndarray,
    sat_pos_ecef_m: np.ndarray,
    sat_clock_m: np.ndarray | None = None,
    x0_ecef_m: np.ndarray | None = None,
    weights: np.ndarray | None = None,
    delay_fn: Callable[[np.ndarray, np.ndarray], np.ndarray] | None = None,
    max_iter: int = 15,
    tol_m: float = 1e-7,
) -> PositionSolution:
    """Gauss-Newton single-point positioning with the shared ranging model.

    Model: ``pseudorange = range_geometry(x, sat).range_m + b - sat_clock_m + delay_fn(x, sat_rx_frame)``.

    Parameters
    ----------
    pseudorange_m : (N,), N >= 4.
    sat_pos_ecef_m : (N, 3) satellite positions at transmit time (ECEF of the transmit time).
    sat_clock_m : (N,) satellite clocks x c (default zero).
    x0_ecef_m : (3,) initial position (default the earth's centre).
    weights : (N,) inverse variances (default ones).
    delay_fn : optional ``(rx_ecef (3,), sat_rx_frame (N, 3)) -> (N,)`` extra modelled delay (e.g. tropo).
    """
    pr = np.asarray(pseudorange_m, dtype=float)
    sat = np.asarray(sat_pos_ecef_m, dtype=float)
    n = len(pr)
    if n < 4:
        raise ValueError(f"solve_position needs >= 4 satellites, got {n}")
    clk = np.zeros(n) if sat_clock_m is None else np.asarray(sat_clock_m, dtype=float)
    w = np.ones(n) if weights is None else np.asarray(weights, dtype=float)
    x = np.zeros(4)
    if x0_ecef_m is not None:
        x[:3] = x0_ecef_m
    sw = np.sqrt(w)
    converged = False
    iterations = 0
    for iterations in range(1, max_iter + 1):  # noqa: B007 - the count is reported
        g = range_geometry(x[:3], sat)
        pred = g.range_m + x[3] - clk
        if delay_fn is not None:
            pred = pred + delay_fn(x[:3], g.sat_pos_rx_frame_m)
        res = pr - pred
        h = np.concatenate([-g.los_ecef, np.ones((n, 1))], axis=1)
        dx, *_ = np.linalg.lstsq(h * sw[:, None], res * sw, rcond=None)
        x = x + dx
        if np.linalg.norm(dx) < tol_m:
            converged = True
            break
    g = range_geometry(x[:3], sat)
    pred = g.range_m + x[3] - clk
    if delay_fn is not None:
        pred = pred + delay_fn(x[:3], g.sat_pos_rx_frame_m)
    h = np.concatenate([-g.los_ecef, np.ones((n, 1))], axis=1)
    cov = np.linalg.inv(h.T @ (h * w[:, None]))
    return PositionSolution(x[:3].copy(), float(x[3]), pr - pred, iterations, converged, cov)


@dataclass(frozen=True)
class VelocitySolution:
    """Least-squares receiver velocity. ``cov`` (4, 4) = (G' W G)^-1 (velocity, clock drift)."""

    vel_ecef_mps: np.ndarray
    clock_drift_mps: float
    residuals_mps: np.ndarray
    cov: np.ndarray


def solve_velocity(
    range_rate_mps: np.ndarray,
    rx_pos_ecef_m: np.ndarray,
    sat_pos_ecef_m: np.ndarray,
    sat_vel_ecef_mps: np.ndarray,
    sat_clock_drift_mps: np.ndarray | None = None,
    weights: np.ndarray | None = None,
) -> VelocitySolution:
    """Receiver ECEF velocity and clock drift from range rates at a known position (exact linear LS:
    the model of ``range_geometry`` is linear in the receiver velocity)."""
    rr = np.asarray(range_rate_mps, dtype=float)
    n = len(rr)
    if n < 4:
        raise ValueError(f"solve_velocity needs >= 4 satellites, got {n}")
    drift_s = np.zeros(n) if sat_clock_drift_mps is None else np.asarray(sat_clock_drift_mps, dtype=float)
    w = np.ones(n) if weights is None else np.asarray(weights, dtype=float)
    g = range_geometry(rx_pos_ecef_m, sat_pos_ecef_m, np.zeros(3), sat_vel_ecef_mps)
    assert g.range_rate_mps is not None and g.doppler_factor is not None
    r0 = g.range_rate_mps  # range rate of a receiver at rest
    h = np.concatenate([-g.los_ecef * g.doppler_factor[:, None], np.ones((n, 1))], axis=1)
    sw = np.sqrt(w)
    x, *_ = np.linalg.lstsq(h * sw[:, None], (rr - r0 + drift_s) * sw, rcond=None)
    res = rr - (r0 + h @ x - drift_s)
    cov = np.linalg.inv(h.T @ (h * w[:, None]))
    return VelocitySolution(x[:3], float(x[3]), res, cov)


def _tuple3(v: np.ndarray) -> tuple[float, float, float]:
    return (float(v[0]), float(v[1]), float(v[2]))


def snapshot_fix(raw: GnssRaw) -> GnssFix | None:
    """A fix (position, 3-D velocity, per-axis sigmas) from one raw epoch, or None (fewer than
    ``MIN_SATS`` satellites of one constellation, no convergence, residuals beyond their sigmas)."""
    if not raw.sats:
        return None
    system, count = Counter(o.constellation for o in raw.sats).most_common(1)[0]
    sats = [o for o in raw.sats if o.constellation == system]
    if count < MIN_SATS:
        return None
    pr = np.array([o.pseudorange_m for o in sats])
    sig = np.array([o.pseudorange_sigma_m for o in sats])
    pos = np.array([o.sat_pos_ecef_m for o in sats])
    clk = np.array([o.sat_clock_m for o in sats])
    try:
        sol = solve_position(pr, pos, clk, weights=1.0 / sig**2, tol_m=1e-3)
    except np.linalg.LinAlgError:
        return None
    chi = float(np.sqrt(np.mean((sol.residuals_m / sig) ** 2)))
    if not sol.converged or not np.all(np.isfinite(sol.pos_ecef_m)) or chi > MAX_NORMALISED_RESIDUAL:
        return None
    llh = ecef_to_llh(sol.pos_ecef_m)
    c_en = earth.mat_en(llh[0], llh[1]).T  # ECEF -> ENU rotation at the solution
    pos_var = np.diagonal(c_en @ sol.cov[:3, :3] @ c_en.T) * max(chi, 1.0) ** 2
    pos_std = np.sqrt(pos_var + ATMOSPHERE_STD_M**2)
    vel = vel_std = None
    rr_sig = np.array([o.range_rate_sigma_mps for o in sats])
    try:
        v = solve_velocity(
            np.array([o.range_rate_mps for o in sats]),
            sol.pos_ecef_m,
            pos,
            np.array([o.sat_vel_ecef_mps for o in sats]),
            np.array([o.sat_clock_drift_mps for o in sats]),
            weights=1.0 / rr_sig**2,
        )
        chi_v = float(np.sqrt(np.mean((v.residuals_mps / rr_sig) ** 2)))
        if chi_v <= MAX_NORMALISED_RESIDUAL and np.all(np.isfinite(v.vel_ecef_mps)):
            vel = c_en @ v.vel_ecef_mps
            vel_var = np.diagonal(c_en @ v.cov[:3, :3] @ c_en.T) * max(chi_v, 1.0) ** 2
            vel_std = np.sqrt(vel_var + VEL_STD_FLOOR_MPS**2)
    except np.linalg.LinAlgError:
        pass
    try:
        return GnssFix(
            t=raw.t,
            lat_deg=math.degrees(llh[0]),
            lon_deg=math.degrees(llh[1]),
            height_m=float(llh[2]),
            vel_enu_mps=None if vel is None else _tuple3(vel),
            pos_std_enu_m=_tuple3(pos_std),
            vel_std_enu_mps=None if vel_std is None else _tuple3(vel_std),
            constellation=system if system in ("GPS", "BDS", "GAL", "GLO") else "MULTI",
            num_sats=count,
        )
    except ValueError:  # outside the wire model's limits (implausible solution)
        return None
