"""Strapdown mechanisation in ENU with a right-forward-up body, quaternion attitude.

Two-speed scheme (Savage, *Strapdown Analytics*, ch. 7; Savage 1998 JGCD 21(1-2)):

- minor loop, at the IMU rate: bias-corrected increments are accumulated into the rotation
  vector ``alpha + beta`` (coning, beta) and the velocity increment ``nu + 1/2 alpha x nu +
  dv_scul`` (rotation compensation and sculling), with the second-order (previous-increment)
  algorithms of Savage eq. 7.1.1.1-11 and 7.2.2.2.2-17;
- major loop, at ``major_interval_s`` (default 0.1 s) and whenever the navigation state is
  needed (an aiding epoch, an output epoch): attitude ``q_nb <- q(-zeta) q_nb q(phi)`` with
  ``zeta = omega_in^n T`` the nav-frame rotation; velocity ``v += [I - 1/2 zeta x] C_nb dv_sf^b
  + (g^n - (2 omega_ie^n + omega_en^n) x v) T`` with mid-interval (extrapolated) earth terms;
  position by trapezoidal integration of velocity over the ellipsoid.

This is exact for constant angular rate and specific force over an IMU interval and second-order
accurate (coning/sculling) for linearly varying ones; the noise-free round-trip test states the
bounds reached on the demo trajectory. The minor loop is plain Python floats (a few microseconds
per sample); the major loop costs ~50 us, so several pipelines each with its own INS run far
faster than real time.

An IMU interval can be split at an aiding epoch inside it: :meth:`Ins.push` takes a fraction of
the increments (constant-rate assumption over the interval).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

from service import earth


@dataclass
class NavState:
    """Navigation state: geodetic position, ENU velocity, attitude quaternion q_nb, biases."""

    t: float
    lat_rad: float
    lon_rad: float
    h_m: float
    vel_enu_mps: np.ndarray
    q_nb: np.ndarray
    gyro_bias_rps: np.ndarray = field(default_factory=lambda: np.zeros(3))
    accel_bias_mps2: np.ndarray = field(default_factory=lambda: np.zeros(3))

    @property
    def mat_nb(self) -> np.ndarray:
        return earth.quat_to_mat(self.q_nb)

    @property
    def rpy_rad(self) -> np.ndarray:
        return earth.mat_nb_to_rpy(self.mat_nb)

    @property
    def llh(self) -> np.ndarray:
        return np.array([self.lat_rad, self.lon_rad, self.h_m])

    def copy(self) -> NavState:
        return NavState(
            self.t,
            self.lat_rad,
            self.lon_rad,
            self.h_m,
            self.vel_enu_mps.copy(),
            self.q_nb.copy(),
            self.gyro_bias_rps.copy(),
            self.accel_bias_mps2.copy(),
        )


def _cross(a0, a1, a2, b0, b1, b2):
    return a1 * b2 - a2 * b1, a2 * b0 - a0 * b2, a0 * b1 - a1 * b0


def _cross3(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """3-vector cross product without np.cross's per-call overhead (~40 us)."""
    return np.array([a[1] * b[2] - a[2] * b[1], a[2] * b[0] - a[0] * b[2], a[0] * b[1] - a[1] * b[0]])


class Ins:
    """A strapdown INS; one instance per pipeline (closed loop makes references differ).

    Parameters
    ----------
    state : NavState
        Initial navigation state (the INS owns a copy).
    major_interval_s : float
        Longest interval between major (attitude/velocity/position) updates.
    """

    def __init__(self, state: NavState, major_interval_s: float = 0.1):
        self.state = state.copy()
        self.major_interval_s = major_interval_s
        # last full-interval major increments: specific force dv^n and the interval, for F/Q
        self.last_fn_mps2 = np.array([0.0, 0.0, earth.gravity_normal(state.lat_rad, state.h_m)])
        self.last_wib_b_rps = np.zeros(3)
        self._dv_prev_n = np.zeros(3)
        self._prev_dth = (0.0, 0.0, 0.0)
        self._prev_dv = (0.0, 0.0, 0.0)
        self._reset_minor()

    # --- minor loop --------------------------------------------------------------------------
    def _reset_minor(self) -> None:
        self._a = [0.0, 0.0, 0.0]  # alpha: sum of angle increments
        self._b = [0.0, 0.0, 0.0]  # beta: coning
        self._nu = [0.0, 0.0, 0.0]  # sum of velocity increments
        self._scul = [0.0, 0.0, 0.0]  # sculling
        self._T = 0.0
        self._t_end = self.state.t

    @property
    def pending_s(self) -> float:
        """Time accumulated in the minor loop, not yet applied to the state."""
        return self._T

    @property
    def time(self) -> float:
        """Time the INS has reached (end of the last pushed interval)."""
        return self._t_end

    def push(self, dtheta_rad, dvel_mps, dt_s: float, t_end: float | None = None) -> None:
        """Accumulate one (possibly partial) IMU interval; runs a major update when due.

        ``t_end`` is the sensor time at the end of the interval: absolute GPS seconds (~1e9)
        cannot be accumulated from increments without losing microseconds, so the caller's
        time stamps are kept exactly.
        """
        bg, ba = self.state.gyro_bias_rps, self.state.accel_bias_mps2
        th0 = dtheta_rad[0] - bg[0] * dt_s
        th1 = dtheta_rad[1] - bg[1] * dt_s
        th2 = dtheta_rad[2] - bg[2] * dt_s
        v0 = dvel_mps[0] - ba[0] * dt_s
        v1 = dvel_mps[1] - ba[1] * dt_s
        v2 = dvel_mps[2] - ba[2] * dt_s
        a, nu = self._a, self._nu
        p0, p1, p2 = self._prev_dth
        q0, q1, q2 = self._prev_dv
        # (alpha_{m-1} + dtheta_{m-1}/6) and (nu_{m-1} + dv_{m-1}/6)
        ae0, ae1, ae2 = a[0] + p0 / 6.0, a[1] + p1 / 6.0, a[2] + p2 / 6.0
        ne0, ne1, ne2 = nu[0] + q0 / 6.0, nu[1] + q1 / 6.0, nu[2] + q2 / 6.0
        c0, c1, c2 = _cross(ae0, ae1, ae2, th0, th1, th2)  # coning increment x2
        self._b[0] += 0.5 * c0
        self._b[1] += 0.5 * c1
        self._b[2] += 0.5 * c2
        s0, s1, s2 = _cross(ae0, ae1, ae2, v0, v1, v2)
        r0, r1, r2 = _cross(ne0, ne1, ne2, th0, th1, th2)
        self._scul[0] += 0.5 * (s0 + r0)
        self._scul[1] += 0.5 * (s1 + r1)
        self._scul[2] += 0.5 * (s2 + r2)
        a[0] += th0
        a[1] += th1
        a[2] += th2
        nu[0] += v0
        nu[1] += v1
        nu[2] += v2
        self._prev_dth = (th0, th1, th2)
        self._prev_dv = (v0, v1, v2)
        self._T += dt_s
        self._t_end = t_end if t_end is not None else self.state.t + self._T
        if self._T >= self.major_interval_s - 1e-9:
            self.major_update()

    # --- major loop --------------------------------------------------------------------------
    def major_update(self) -> None:
        """Apply the accumulated minor-loop increments to attitude, velocity and position."""
        T = self._T
        if T <= 0.0:
            return
        s = self.state
        a = np.array(self._a)
        phi_b = a + np.array(self._b)  # body rotation vector over the interval
        nu = np.array(self._nu)
        # rotation compensation to third order (Savage eq. 7.2.2.2-22): the 1/6 a x (a x nu) term
        # matters in sustained turns at 10 Hz major rates (~1e-5 m/s per update otherwise)
        a_x_nu = _cross3(a, nu)
        dv_sf_b = nu + 0.5 * a_x_nu + _cross3(a, a_x_nu) / 6.0 + np.array(self._scul)

        # mid-interval extrapolation of position and velocity for the earth terms
        v_mid = s.vel_enu_mps + 0.5 * self._dv_prev_n * (T / max(self._prev_T, 1e-12))
        r_m, r_n = earth.radii(s.lat_rad)
        lat_mid = s.lat_rad + 0.5 * v_mid[1] * T / (r_m + s.h_m)
        h_mid = s.h_m + 0.5 * v_mid[2] * T
        w_ie = earth.earth_rate_n(lat_mid)
        w_en = earth.transport_rate_n(lat_mid, h_mid, v_mid)
        zeta = (w_ie + w_en) * T

        c_nb = earth.quat_to_mat(s.q_nb)
        f_n = c_nb @ dv_sf_b
        dv_sf_n = f_n - 0.5 * _cross3(zeta, f_n)
        g_n = np.array([0.0, 0.0, -earth.gravity_normal(lat_mid, h_mid)])
        dv_n = dv_sf_n + (g_n - _cross3(2.0 * w_ie + w_en, v_mid)) * T

        v_old = s.vel_enu_mps
        v_new = v_old + dv_n
        # position: trapezoid over the ellipsoid
        vm = 0.5 * (v_old + v_new)
        h_new = s.h_m + vm[2] * T
        h_avg = 0.5 * (s.h_m + h_new)
        lat_new = s.lat_rad + vm[1] * T / (r_m + h_avg)
        r_m2, r_n2 = earth.radii(0.5 * (s.lat_rad + lat_new))
        lon_new = s.lon_rad + vm[0] * T / ((r_n2 + h_avg) * math.cos(0.5 * (s.lat_rad + lat_new)))

        q = earth.quat_mul(earth.quat_mul(earth.rotvec_to_quat(-zeta), s.q_nb), earth.rotvec_to_quat(phi_b))
        s.q_nb = q / math.sqrt(float(q @ q))
        s.vel_enu_mps = v_new
        s.lat_rad, s.lon_rad, s.h_m = lat_new, lon_new, h_new
        s.t = self._t_end

        self._dv_prev_n = dv_n
        self._prev_T = T
        self.last_fn_mps2 = f_n / T
        self.last_wib_b_rps = a / T
        self._reset_minor()

    _prev_T = 0.1

    # --- closed-loop feedback ----------------------------------------------------------------
    def correct(
        self,
        dp_enu_m: np.ndarray,
        dv_enu_mps: np.ndarray,
        phi_rad: np.ndarray,
        d_gyro_bias_rps: np.ndarray,
        d_accel_bias_mps2: np.ndarray,
    ) -> None:
        """Absorb estimated errors (computed minus true) into the state.

        Must be called with no pending minor-loop time (call :meth:`major_update` first).
        Attitude error convention: C_nb(computed) = (I - [phi x]) C_nb(true), so the corrected
        attitude is C_nb <- exp([phi x]) C_nb.
        """
        if self._T > 0.0:
            self.major_update()
        s = self.state
        r_m, r_n = earth.radii(s.lat_rad)
        s.lat_rad -= dp_enu_m[1] / (r_m + s.h_m)
        s.lon_rad -= dp_enu_m[0] / ((r_n + s.h_m) * math.cos(s.lat_rad))
        s.h_m -= dp_enu_m[2]
        s.vel_enu_mps = s.vel_enu_mps - dv_enu_mps
        q = earth.quat_mul(earth.rotvec_to_quat(phi_rad), s.q_nb)
        s.q_nb = q / math.sqrt(float(q @ q))
        # bias states are "remaining bias" (true - estimated): add them to the estimate
        s.gyro_bias_rps = s.gyro_bias_rps + d_gyro_bias_rps
        s.accel_bias_mps2 = s.accel_bias_mps2 + d_accel_bias_mps2
