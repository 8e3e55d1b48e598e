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

from fednav.service import earth


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


def _floats3(v) -> list[float]:
    """A 3-vector's components as Python floats (a float64 array's by tolist, the same values as
    float() of each element, without iterating over numpy scalars)."""
    if isinstance(v, np.ndarray) and v.dtype == np.float64:
        return v.tolist()
    return [float(a) for a in v]


def _cross(a0, a1, a2, b0, b1, b2):
    return a1 * b2 - a2 * b1, a2 * b0 - a0 * b2, a0 * b1 - a1 * b0


class Preintegrator:
    """Minor loop over *raw* IMU increments (Savage's second-order coning and sculling).

    Bias-independent, so one instance serves every INS of a vehicle (all pipelines): each INS
    applies its own bias estimate at its major update with the exact algebra below. Between two
    major updates an INS's bias estimate is constant (corrections happen only after a major
    update), and with b the gyro and a the accelerometer bias:
        alpha = alpha~ - b T,  nu = nu~ - a T
        beta  = beta~ - 1/2 (S1 - S2) x b
        scul  = scul~ - 1/2 [(S1 - S2) x a + (S4 - S3) x b]
    where S1 = sum (alpha~_(m-1) + dth~_(m-1)/6) dt_m, S2 = sum tau_m dth~_m, S3 = sum tau_m dv~_m,
    S4 = sum (nu~_(m-1) + dv~_(m-1)/6) dt_m, tau_m = t_(m-1) + dt_(m-1)/6 (time from the start of
    the interval); the b x b and a x b terms cancel exactly. The only approximation: the previous
    increment carried across a major boundary is corrected with the current bias.
    """

    __slots__ = ("v", "T", "t_end", "_prev")

    # layout of v: alpha(0:3) beta(3:6) nu(6:9) scul(9:12) S1(12:15) S2(15:18) S3(18:21) S4(21:24)
    def __init__(self) -> None:
        self._prev = (0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0)  # dth(3), dv(3), dt of the last increment
        self.reset(0.0)

    def reset(self, t: float) -> None:
        self.v = [0.0] * 24
        self.T = 0.0
        self.t_end = t

    def push(self, dth, dv, dt: float, t_end: float) -> None:
        self.push6(
            float(dth[0]), float(dth[1]), float(dth[2]), float(dv[0]), float(dv[1]), float(dv[2]), dt, t_end
        )

    def push6(
        self, th0: float, th1: float, th2: float, v0: float, v1: float, v2: float, dt: float, t_end: float
    ) -> None:
        """:meth:`push` of one interval given as six floats (the engine's batch records): the
        state in locals and written back once (every sum in the same order as element by element,
        so the results are the same to the last bit)."""
        (al0, al1, al2, be0, be1, be2, nu0, nu1, nu2, sc0, sc1, sc2,
         S10, S11, S12, S20, S21, S22, S30, S31, S32, S40, S41, S42) = self.v  # fmt: skip
        p0, p1, p2, q0, q1, q2, pdt = self._prev
        # A = alpha_(m-1) + dth_(m-1)/6, N = nu_(m-1) + dv_(m-1)/6, tau = t_(m-1) + dt_(m-1)/6
        A0, A1, A2 = al0 + p0 / 6.0, al1 + p1 / 6.0, al2 + p2 / 6.0
        N0, N1, N2 = nu0 + q0 / 6.0, nu1 + q1 / 6.0, nu2 + q2 / 6.0
        tau = self.T + pdt / 6.0
        # coning A x dth; sculling A x dv + N x dth
        self.v = [
            al0 + th0,
            al1 + th1,
            al2 + th2,
            be0 + 0.5 * (A1 * th2 - A2 * th1),
            be1 + 0.5 * (A2 * th0 - A0 * th2),
            be2 + 0.5 * (A0 * th1 - A1 * th0),
            nu0 + v0,
            nu1 + v1,
            nu2 + v2,
            sc0 + 0.5 * ((A1 * v2 - A2 * v1) + (N1 * th2 - N2 * th1)),
            sc1 + 0.5 * ((A2 * v0 - A0 * v2) + (N2 * th0 - N0 * th2)),
            sc2 + 0.5 * ((A0 * v1 - A1 * v0) + (N0 * th1 - N1 * th0)),
            S10 + A0 * dt,
            S11 + A1 * dt,
            S12 + A2 * dt,
            S20 + tau * th0,
            S21 + tau * th1,
            S22 + tau * th2,
            S30 + tau * v0,
            S31 + tau * v1,
            S32 + tau * v2,
            S40 + N0 * dt,
            S41 + N1 * dt,
            S42 + N2 * dt,
        ]
        self._prev = (th0, th1, th2, v0, v1, v2, dt)
        self.T += dt
        self.t_end = t_end

    def push_steps(self, steps, t_end: float) -> None:
        """:meth:`push6` of several intervals in order, ``steps`` (th0, th1, th2, v0, v1, v2, dt)
        each, the last ending at ``t_end`` (the engine's usual records of a batch between two
        major updates): the 24 sums stay in locals from the first interval to the last instead of
        going through the state's list at every one (the same operations in the same order as
        push6 of each, so the same values to the last bit: tests/test_mechanisation.py; ~4 k of
        push6's ~14 k instructions an interval were that list and the call). Keep it alike to
        :meth:`push6`."""
        (al0, al1, al2, be0, be1, be2, nu0, nu1, nu2, sc0, sc1, sc2,
         S10, S11, S12, S20, S21, S22, S30, S31, S32, S40, S41, S42) = self.v  # fmt: skip
        p0, p1, p2, q0, q1, q2, pdt = self._prev
        T = self.T
        for th0, th1, th2, v0, v1, v2, dt in steps:
            A0, A1, A2 = al0 + p0 / 6.0, al1 + p1 / 6.0, al2 + p2 / 6.0
            N0, N1, N2 = nu0 + q0 / 6.0, nu1 + q1 / 6.0, nu2 + q2 / 6.0
            tau = T + pdt / 6.0
            al0, al1, al2 = al0 + th0, al1 + th1, al2 + th2
            be0 = be0 + 0.5 * (A1 * th2 - A2 * th1)
            be1 = be1 + 0.5 * (A2 * th0 - A0 * th2)
            be2 = be2 + 0.5 * (A0 * th1 - A1 * th0)
            nu0, nu1, nu2 = nu0 + v0, nu1 + v1, nu2 + v2
            sc0 = sc0 + 0.5 * ((A1 * v2 - A2 * v1) + (N1 * th2 - N2 * th1))
            sc1 = sc1 + 0.5 * ((A2 * v0 - A0 * v2) + (N2 * th0 - N0 * th2))
            sc2 = sc2 + 0.5 * ((A0 * v1 - A1 * v0) + (N0 * th1 - N1 * th0))
            S10, S11, S12 = S10 + A0 * dt, S11 + A1 * dt, S12 + A2 * dt
            S20, S21, S22 = S20 + tau * th0, S21 + tau * th1, S22 + tau * th2
            S30, S31, S32 = S30 + tau * v0, S31 + tau * v1, S32 + tau * v2
            S40, S41, S42 = S40 + N0 * dt, S41 + N1 * dt, S42 + N2 * dt
            p0, p1, p2, q0, q1, q2, pdt = th0, th1, th2, v0, v1, v2, dt
            T += dt
        self.v = [al0, al1, al2, be0, be1, be2, nu0, nu1, nu2, sc0, sc1, sc2,
                  S10, S11, S12, S20, S21, S22, S30, S31, S32, S40, S41, S42]  # fmt: skip
        self._prev = (p0, p1, p2, q0, q1, q2, pdt)
        self.T = T
        self.t_end = t_end

    def corrected(self, gyro_bias_rps: np.ndarray, accel_bias_mps2: np.ndarray):
        """(alpha, beta, nu, scul) with the biases removed (class docstring)."""
        return tuple(np.array(v) for v in self.corrected_f(gyro_bias_rps, accel_bias_mps2))

    def corrected_f(self, gyro_bias_rps: np.ndarray, accel_bias_mps2: np.ndarray):
        """:meth:`corrected` as four 3-tuples of Python floats: the same elementwise operations in
        the same order (so the same values), without ~20 numpy calls on 3-vectors (the major
        update reads them as floats; it runs at every epoch of every vehicle)."""
        (al0, al1, al2, be0, be1, be2, nu0, nu1, nu2, sc0, sc1, sc2,
         S10, S11, S12, S20, S21, S22, S30, S31, S32, S40, S41, S42) = self.v  # fmt: skip
        b0, b1, b2 = gyro_bias_rps.tolist()
        a0, a1, a2 = accel_bias_mps2.tolist()
        T = self.T
        s0, s1, s2 = S10 - S20, S11 - S21, S12 - S22  # S1 - S2
        t0, t1, t2 = S40 - S30, S41 - S31, S42 - S32  # S4 - S3
        c0, c1, c2 = _cross(s0, s1, s2, b0, b1, b2)
        d0, d1, d2 = _cross(s0, s1, s2, a0, a1, a2)
        e0, e1, e2 = _cross(t0, t1, t2, b0, b1, b2)
        return (
            (al0 - b0 * T, al1 - b1 * T, al2 - b2 * T),
            (be0 - 0.5 * c0, be1 - 0.5 * c1, be2 - 0.5 * c2),
            (nu0 - a0 * T, nu1 - a1 * T, nu2 - a2 * T),
            (sc0 - 0.5 * (d0 + e0), sc1 - 0.5 * (d1 + e1), sc2 - 0.5 * (d2 + e2)),
        )


class Ins:
    """A strapdown INS; one instance per pipeline (closed loop makes references differ).

    Parameters
    ----------
    state : NavState
        Initial navigation state (the INS owns a copy).
    major_interval_s : float
        Longest interval between major (attitude/velocity/position) updates.

    Either push IMU intervals one by one (:meth:`push`, with the INS's own minor loop) or hand
    it a shared :class:`Preintegrator` at each major update (:meth:`major_update`).
    """

    def __init__(self, state: NavState, major_interval_s: float = 0.1):
        self.state = state.copy()
        self.major_interval_s = major_interval_s
        # last full-interval major increments: specific force dv^n and the interval, for F/Q
        self.last_fn_mps2 = np.array([0.0, 0.0, earth.gravity_normal(state.lat_rad, state.h_m)])
        self.last_wib_b_rps = np.zeros(3)
        self._dv_prev_n = np.zeros(3)
        self._pre = Preintegrator()
        self._pre.reset(self.state.t)

    @property
    def pending_s(self) -> float:
        """Time accumulated in the own minor loop, not yet applied to the state."""
        return self._pre.T

    @property
    def time(self) -> float:
        """Time the INS has reached (end of the last pushed interval)."""
        return self._pre.t_end if self._pre.T > 0.0 else self.state.t

    def push(self, dtheta_rad, dvel_mps, dt_s: float, t_end: float | None = None) -> None:
        """Accumulate one (possibly partial) IMU interval; runs a major update when due.

        ``t_end`` is the sensor time at the end of the interval: absolute GPS seconds (~1e9)
        cannot be accumulated from increments without losing microseconds, so the caller's
        time stamps are kept exactly.
        """
        pre = self._pre
        pre.push(dtheta_rad, dvel_mps, dt_s, t_end if t_end is not None else self.state.t + pre.T + dt_s)
        if pre.T >= self.major_interval_s - 1e-9:
            self.major_update()

    # --- major loop --------------------------------------------------------------------------
    def major_update(self, pre: Preintegrator | None = None) -> None:
        """Apply minor-loop increments (the own ones, or a shared preintegrator's) to the state."""
        own = pre is None
        pre = self._pre if own else pre
        T = pre.T
        if T <= 0.0:
            return
        s = self.state
        # the algebra below on Python floats (3-vectors as scalars: a tenth of numpy's per-call
        # cost at this size; the same operations in the same order, equal to rounding); a plain
        # preintegrator's increments as floats directly (a scaled one's through its arrays)
        if type(pre) is Preintegrator:
            (a0, a1, a2), (b0, b1, b2), (n0, n1, n2), (k0, k1, k2) = pre.corrected_f(
                s.gyro_bias_rps, s.accel_bias_mps2
            )
        else:
            a, beta, nu, scul = pre.corrected(s.gyro_bias_rps, s.accel_bias_mps2)
            a0, a1, a2 = a.tolist()
            b0, b1, b2 = beta.tolist()
            n0, n1, n2 = nu.tolist()
            k0, k1, k2 = scul.tolist()
        phi_b = (a0 + b0, a1 + b1, a2 + b2)  # body rotation vector over the interval
        # rotation compensation to third order (Savage eq. 7.2.2.2-22): the 1/6 a x (a x nu) term
        # matters in sustained turns at 10 Hz major rates (~1e-5 m/s per update otherwise)
        x0, x1, x2 = _cross(a0, a1, a2, n0, n1, n2)
        y0, y1, y2 = _cross(a0, a1, a2, x0, x1, x2)
        d0 = n0 + 0.5 * x0 + y0 / 6.0 + k0
        d1 = n1 + 0.5 * x1 + y1 / 6.0 + k1
        d2 = n2 + 0.5 * x2 + y2 / 6.0 + k2

        # mid-interval extrapolation of position and velocity for the earth terms
        ve, vn, vu = s.vel_enu_mps.tolist()
        p0, p1, p2 = self._dv_prev_n.tolist()
        k = T / max(self._prev_T, 1e-12)
        m0, m1, m2 = ve + 0.5 * p0 * k, vn + 0.5 * p1 * k, vu + 0.5 * p2 * k
        lat, h = s.lat_rad, s.h_m
        r_m, r_n = earth.radii(lat)
        lat_mid = lat + 0.5 * m1 * T / (r_m + h)
        h_mid = h + 0.5 * m2 * T
        W = earth.OMEGA_IE_RPS
        ie1, ie2 = W * math.cos(lat_mid), W * math.sin(lat_mid)  # earth_rate_n (east term 0)
        rm_mid, rn_mid = earth.radii(lat_mid)  # transport_rate_n
        en0 = -m1 / (rm_mid + h_mid)
        en1 = m0 / (rn_mid + h_mid)
        en2 = m0 * math.tan(lat_mid) / (rn_mid + h_mid)
        z0, z1, z2 = (0.0 + en0) * T, (ie1 + en1) * T, (ie2 + en2) * T

        q_nb = s.q_nb.tolist()
        c_nb = earth.quat_to_mat_f(*q_nb)
        f0 = c_nb[0][0] * d0 + c_nb[0][1] * d1 + c_nb[0][2] * d2
        f1 = c_nb[1][0] * d0 + c_nb[1][1] * d1 + c_nb[1][2] * d2
        f2 = c_nb[2][0] * d0 + c_nb[2][1] * d1 + c_nb[2][2] * d2
        c0, c1, c2 = _cross(z0, z1, z2, f0, f1, f2)
        g = earth.gravity_normal(lat_mid, h_mid)
        w0, w1, w2 = 2.0 * 0.0 + en0, 2.0 * ie1 + en1, 2.0 * ie2 + en2
        o0, o1, o2 = _cross(w0, w1, w2, m0, m1, m2)
        dv0 = (f0 - 0.5 * c0) + (0.0 - o0) * T
        dv1 = (f1 - 0.5 * c1) + (0.0 - o1) * T
        dv2 = (f2 - 0.5 * c2) + (-g - o2) * T

        u0, u1, u2 = ve + dv0, vn + dv1, vu + dv2
        # position: trapezoid over the ellipsoid
        h_new = h + 0.5 * (vu + u2) * T
        h_avg = 0.5 * (h + h_new)
        lat_new = lat + 0.5 * (vn + u1) * T / (r_m + h_avg)
        lat_avg = 0.5 * (lat + lat_new)
        r_m2, r_n2 = earth.radii(lat_avg)
        lon_new = s.lon_rad + 0.5 * (ve + u0) * T / ((r_n2 + h_avg) * math.cos(lat_avg))

        qz = earth.rotvec_to_quat_f(-z0, -z1, -z2)
        qb = earth.rotvec_to_quat_f(*phi_b)
        q0, q1, q2, q3 = earth.quat_mul_f(earth.quat_mul_f(qz, q_nb), qb)
        qn = math.sqrt(q0 * q0 + q1 * q1 + q2 * q2 + q3 * q3)
        s.q_nb = np.array([q0 / qn, q1 / qn, q2 / qn, q3 / qn])
        s.vel_enu_mps = np.array([u0, u1, u2])
        s.lat_rad, s.lon_rad, s.h_m = lat_new, lon_new, h_new
        s.t = pre.t_end

        self._dv_prev_n = np.array([dv0, dv1, dv2])
        self._prev_T = T
        self.last_fn_mps2 = np.array([f0 / T, f1 / T, f2 / T])
        self.last_wib_b_rps = np.array([a0 / T, a1 / T, a2 / T])
        if own:
            pre.reset(s.t)

    _prev_T = 0.1

    @property
    def last_acc_enu_mps2(self) -> np.ndarray:
        """The acceleration (ENU, gravity and Coriolis included: dv/dt) over the last major interval."""
        return self._dv_prev_n / self._prev_T

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
        if self._pre.T > 0.0:
            self.major_update()
        s = self.state
        r_m, r_n = earth.radii(s.lat_rad)
        # on Python floats (a fix epoch's feedback: the same operations, the same results)
        p0, p1, p2 = _floats3(dp_enu_m)
        s.lat_rad = float(s.lat_rad - p1 / (r_m + s.h_m))
        s.lon_rad = float(s.lon_rad - p0 / ((r_n + s.h_m) * math.cos(s.lat_rad)))
        s.h_m = float(s.h_m - p2)
        s.vel_enu_mps = s.vel_enu_mps - dv_enu_mps
        a0, a1, a2 = _floats3(phi_rad)
        q = np.array(earth.quat_mul_f(earth.rotvec_to_quat_f(a0, a1, a2), s.q_nb.tolist()))
        s.q_nb = q / math.sqrt(float(q @ q))
        # bias states are "remaining bias" (true - estimated): add them to the estimate
        s.gyro_bias_rps = s.gyro_bias_rps + d_gyro_bias_rps
        s.accel_bias_mps2 = s.accel_bias_mps2 + d_accel_bias_mps2
