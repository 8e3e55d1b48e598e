"""Vehicle trajectories from flight segments: consistent truth and exact IMU increments.

Model
-----
A trajectory is a sequence of segments (static, straight, turn, climb, accelerate) flown one after
the other. Every change of a kinematic channel is a raised-cosine ramp
``S(u) = (1 - cos(pi u)) / 2`` over ``ramp_s`` seconds, so angular rates and accelerations are
continuous. The channels are analytic functions of time:

- roll (coordinated turn: ``roll = atan(v omega / g)``, ramped with the turn rate),
- pitch (= flight-path angle; no angle of attack),
- heading rate (clockwise from north; yaw = -heading, west positive, per :mod:`service.earth`),
- along-track acceleration (speed = its integral).

The velocity is along the body forward axis (no sideslip):
``v_enu = speed [sin(hdg) cos(p), cos(hdg) cos(p), sin(p)] = speed * mat_nb[:, 1]``.
The geodetic position integrates ``dlat/dt = vn / (R_M + h)``, ``dlon/dt = ve / ((R_N + h) cos lat)``,
``dh/dt = vu`` with 5-point Gauss-Legendre quadrature per IMU interval (height exactly, latitude
by Picard iteration, which contracts by ~1e-4 per pass), accurate to ~1e-12 relative.

IMU increments over ``(t_{k-1}, t_k]`` are Gauss-Legendre integrals of

- ``omega_ib^b = omega_nb^b + C_bn (omega_ie^n + omega_en^n)``,
- ``f^b = C_bn (dv^n/dt - g^n + (2 omega_ie^n + omega_en^n) x v^n)``, ``g^n = [0, 0, -gamma(lat, h)]``,

with ``omega_nb^b`` the exact body rate of the Euler-angle rates for ``mat_nb = Rz(y) Rx(p) Ry(r)``:
``omega_nb^b = [cr p' - sr cp y', r' + sp y', sr p' + cr cp y']``. Segment boundaries and ramp
ends must fall on IMU sample times (multiples of the IMU step), so that every interval's integrand
is smooth and the quadrature is exact to rounding.

References: Groves (2013) ch. 5 (ENU mechanisation, eqs 5.44-5.54 in local-navigation form);
PSINS ``trjsimu`` for the segment idea.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Annotated, Literal

import numpy as np
from pydantic import BaseModel, ConfigDict, Field, model_validator

from fednav.service import earth

_GL_X, _GL_W = np.polynomial.legendre.leggauss(5)  # nodes on [-1, 1], weights (sum 2)
_STEP_TOL = 1e-6  # tolerance (in IMU steps) for "is a multiple of the IMU step"


# --- specification models -----------------------------------------------------------------------
class _Spec(BaseModel):
    model_config = ConfigDict(extra="forbid", frozen=True)


class StartSpec(_Spec):
    """Initial state of a trajectory: level attitude, velocity along the heading."""

    lat_deg: float = Field(ge=-85.0, le=85.0, description="Geodetic latitude, deg")
    lon_deg: float = Field(ge=-180.0, le=180.0, description="Longitude, deg")
    height_m: float = Field(ge=-1000.0, le=50000.0, description="Ellipsoidal height, m")
    heading_deg: float = Field(ge=0.0, lt=360.0, description="Heading clockwise from north, deg")
    speed_mps: float = Field(ge=0.0, le=1000.0, description="Speed along the body forward axis, m/s")


class _SegmentBase(_Spec):
    duration_s: float = Field(
        gt=0.0, le=1.0e6, description="Segment duration, s (a multiple of the IMU step)"
    )


class StaticSegment(_SegmentBase):
    """Vehicle at rest (speed must be zero when the segment starts)."""

    kind: Literal["static"]


class StraightSegment(_SegmentBase):
    """Constant velocity, level, wings level."""

    kind: Literal["straight"]


class _RampedSegment(_SegmentBase):
    ramp_s: float = Field(default=5.0, gt=0.0, description="Raised-cosine transition length at each end, s")

    @model_validator(mode="after")
    def _ramps_fit(self):
        if 2.0 * self.ramp_s > self.duration_s + 1e-9:
            raise ValueError(f"ramp_s ({self.ramp_s}) must be at most half of duration_s ({self.duration_s})")
        return self


class TurnSegment(_RampedSegment):
    """Level turn; positive turn rate = heading increasing (right turn, right wing down)."""

    kind: Literal["turn"]
    turn_rate_dps: float = Field(ge=-30.0, le=30.0, description="Heading rate when fully rolled in, deg/s")
    bank: Literal["coordinated", "level"] = Field(
        "coordinated",
        description="'coordinated': rolled into the turn (tan(roll) = v omega / g, an aircraft); "
        "'level': no roll, the centripetal force on the body's lateral axis (a car, a ship)",
    )


class ClimbSegment(_RampedSegment):
    """Climb (or descent): pitch = flight-path angle, ramped in and out; level again at the end."""

    kind: Literal["climb"]
    climb_rate_mps: float | None = Field(
        default=None,
        ge=-300.0,
        le=300.0,
        description="Vertical speed when fully pitched, m/s (needs speed > 0)",
    )
    flight_path_deg: float | None = Field(
        default=None, ge=-60.0, le=60.0, description="Flight-path (= pitch) angle when fully pitched, deg"
    )

    @model_validator(mode="after")
    def _one_of(self):
        if (self.climb_rate_mps is None) == (self.flight_path_deg is None):
            raise ValueError("give exactly one of climb_rate_mps and flight_path_deg")
        return self


class AccelerateSegment(_RampedSegment):
    """Along-track acceleration (negative = deceleration), ramped in and out; level, wings level."""

    kind: Literal["accelerate"]
    accel_mps2: float = Field(ge=-50.0, le=50.0, description="Along-track acceleration when ramped in, m/s^2")


Segment = Annotated[
    StaticSegment | StraightSegment | TurnSegment | ClimbSegment | AccelerateSegment,
    Field(discriminator="kind"),
]


# --- analytic channels ----------------------------------------------------------------------------
@dataclass(frozen=True)
class _Ramp:
    t_start_s: float  # relative to the trajectory start
    ramp_s: float
    delta: float  # change of the channel value over the ramp


class _Channel:
    """``c(t) = base + sum_i delta_i S((t - a_i) / T_i)`` with its derivative and its integral from 0."""

    def __init__(self, base: float, ramps: list[_Ramp]):
        self.base = base
        self.ramps = ramps

    def eval(self, t_rel_s: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Value, time derivative and integral from 0, at sorted relative times (P,)."""
        t = t_rel_s
        val = np.full(t.shape, self.base)
        der = np.zeros(t.shape)
        itg = self.base * t
        for r in self.ramps:
            a, T, d = r.t_start_s, r.ramp_s, r.delta
            i0 = int(np.searchsorted(t, a, side="left"))
            i1 = int(np.searchsorted(t, a + T, side="right"))
            if i1 > i0:
                u = (t[i0:i1] - a) / T
                val[i0:i1] += d * 0.5 * (1.0 - np.cos(np.pi * u))
                der[i0:i1] += d * 0.5 * np.pi / T * np.sin(np.pi * u)
                itg[i0:i1] += d * T * (0.5 * u - np.sin(np.pi * u) / (2.0 * np.pi))
            if i1 < t.size:
                val[i1:] += d
                itg[i1:] += d * (t[i1:] - a - 0.5 * T)
        return val, der, itg


@dataclass(frozen=True)
class _Profile:
    """Analytic roll, pitch, yaw and speed as functions of relative time."""

    lat0_rad: float
    lon0_rad: float
    h0_m: float
    yaw0_rad: float
    speed0_mps: float
    roll: _Channel
    pitch: _Channel
    heading_rate: _Channel  # rad/s, clockwise
    accel: _Channel  # m/s^2 along track
    duration_s: float

    def kinematics(self, t_rel_s: np.ndarray) -> dict[str, np.ndarray]:
        """Attitude, attitude rates, velocity and its derivative at relative times (P,)."""
        t = np.asarray(t_rel_s, dtype=float)
        order = None
        if t.size > 1 and np.any(np.diff(t) < 0):
            order = np.argsort(t, kind="stable")
            t = t[order]
        r, rd, _ = self.roll.eval(t)
        p, pd, _ = self.pitch.eval(t)
        hr, _, hi = self.heading_rate.eval(t)
        a, _, ai = self.accel.eval(t)
        y = self.yaw0_rad - hi
        yd = -hr
        s = self.speed0_mps + ai
        sd = a
        sy, cy, sp, cp = np.sin(y), np.cos(y), np.sin(p), np.cos(p)
        u = np.stack([-sy * cp, cy * cp, sp], axis=-1)  # body forward axis in ENU = mat_nb[:, 1]
        du = np.stack([-cy * cp * yd + sy * sp * pd, -sy * cp * yd - cy * sp * pd, cp * pd], axis=-1)
        vel = s[:, None] * u
        acc = sd[:, None] * u + s[:, None] * du
        out = {
            "rpy": np.stack([r, p, y], axis=-1),
            "rpy_dot": np.stack([rd, pd, yd], axis=-1),
            "vel": vel,
            "acc": acc,
        }
        if order is not None:
            inv = np.empty_like(order)
            inv[order] = np.arange(order.size)
            out = {k: v[inv] for k, v in out.items()}
        return out


def _plan(start: StartSpec, segments: list, imu_rate_hz: float, duration_s: float | None) -> _Profile:
    """Turn segments into analytic channels; raise ValueError naming the offending segment."""
    dt = 1.0 / imu_rate_hz
    lat0 = math.radians(start.lat_deg)
    g0 = earth.gravity_normal(lat0, start.height_m)

    def _on_grid(x: float, what: str) -> None:
        n = x * imu_rate_hz
        if abs(n - round(n)) > _STEP_TOL:
            raise ValueError(f"{what} = {x} s is not a multiple of the IMU step {dt} s")

    segs = list(segments)
    total = sum(s.duration_s for s in segs)
    if duration_s is not None:
        _on_grid(duration_s, "duration_s")
        if total > duration_s + 1e-9:
            raise ValueError(f"segments last {total} s, longer than duration_s = {duration_s} s")
        if duration_s - total > 0.5 * dt:
            segs.append(StraightSegment(kind="straight", duration_s=duration_s - total))
        total = duration_s
    if not segs:
        raise ValueError("no segments and no duration_s")

    roll, pitch, hrate, accel = [], [], [], []
    t = 0.0
    speed = start.speed_mps
    for i, seg in enumerate(segs):
        name = f"segments[{i}] ({seg.kind})"
        _on_grid(seg.duration_s, f"{name}.duration_s")
        ramp = getattr(seg, "ramp_s", None)
        if ramp is not None:
            _on_grid(ramp, f"{name}.ramp_s")
        end_ramp = t + seg.duration_s - (ramp or 0.0)
        if seg.kind == "static":
            if abs(speed) > 1e-9:
                raise ValueError(
                    f"{name}: speed is {speed:.3f} m/s, a static segment needs 0 (decelerate first)"
                )
        elif seg.kind == "turn":
            w = math.radians(seg.turn_rate_dps)
            hrate += [_Ramp(t, ramp, w), _Ramp(end_ramp, ramp, -w)]
            if seg.bank == "coordinated":
                phi = math.atan(speed * w / g0)  # coordinated: tan(roll) = v omega / g
                roll += [_Ramp(t, ramp, phi), _Ramp(end_ramp, ramp, -phi)]
        elif seg.kind == "climb":
            if seg.climb_rate_mps is not None:
                if speed <= abs(seg.climb_rate_mps):
                    raise ValueError(
                        f"{name}.climb_rate_mps = {seg.climb_rate_mps} needs a speed above it "
                        f"(speed {speed:.3f} m/s)"
                    )
                gamma = math.asin(seg.climb_rate_mps / speed)
            else:
                gamma = math.radians(seg.flight_path_deg)
            pitch += [_Ramp(t, ramp, gamma), _Ramp(end_ramp, ramp, -gamma)]
        elif seg.kind == "accelerate":
            new_speed = speed + seg.accel_mps2 * (seg.duration_s - ramp)
            if new_speed < -1e-9:
                raise ValueError(f"{name}: speed would become negative ({new_speed:.3f} m/s)")
            accel += [_Ramp(t, ramp, seg.accel_mps2), _Ramp(end_ramp, ramp, -seg.accel_mps2)]
            speed = new_speed
        t += seg.duration_s
    return _Profile(
        lat0_rad=lat0,
        lon0_rad=math.radians(start.lon_deg),
        h0_m=start.height_m,
        yaw0_rad=earth.yaw_from_heading_deg(start.heading_deg),
        speed0_mps=start.speed_mps,
        roll=_Channel(0.0, roll),
        pitch=_Channel(0.0, pitch),
        heading_rate=_Channel(0.0, hrate),
        accel=_Channel(0.0, accel),
        duration_s=total,
    )


def check_segments(
    start: StartSpec, segments: list, imu_rate_hz: float, duration_s: float | None = None
) -> None:
    """Validate a segment list against a start state and IMU rate (raises ValueError naming the segment)."""
    _plan(start, segments, imu_rate_hz, duration_s)


# --- vectorised earth model -----------------------------------------------------------------------
def radii_vec(lat_rad: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Vectorised :func:`service.earth.radii`: (R_M, R_N) in metres, shape of ``lat_rad``."""
    s2 = np.sin(lat_rad) ** 2
    w = np.sqrt(1.0 - earth.E2 * s2)
    return earth.A_M * (1.0 - earth.E2) / (w * w * w), earth.A_M / w


def gravity_vec(lat_rad: np.ndarray, h_m: np.ndarray) -> np.ndarray:
    """Vectorised :func:`service.earth.gravity_normal` (m/s^2)."""
    s2 = np.sin(lat_rad) ** 2
    g0 = earth.G_EQUATOR_MPS2 * (1.0 + earth.K_SOMIGLIANA * s2) / np.sqrt(1.0 - earth.E2 * s2)
    a, f, m = earth.A_M, earth.F, earth.M_GRAV
    return g0 * (1.0 - 2.0 / a * (1.0 + f + m - 2.0 * f * s2) * h_m + 3.0 / a**2 * h_m**2)


def mat_nb_vec(rpy_rad: np.ndarray) -> np.ndarray:
    """Vectorised :func:`service.earth.rpy_to_mat_nb`: (P, 3) -> (P, 3, 3)."""
    r, p, y = rpy_rad[:, 0], rpy_rad[:, 1], rpy_rad[:, 2]
    sr, cr, sp, cp, sy, cy = np.sin(r), np.cos(r), np.sin(p), np.cos(p), np.sin(y), np.cos(y)
    m = np.empty(rpy_rad.shape[:1] + (3, 3))
    m[:, 0, 0] = cy * cr - sy * sp * sr
    m[:, 0, 1] = -sy * cp
    m[:, 0, 2] = cy * sr + sy * sp * cr
    m[:, 1, 0] = sy * cr + cy * sp * sr
    m[:, 1, 1] = cy * cp
    m[:, 1, 2] = sy * sr - cy * sp * cr
    m[:, 2, 0] = -cp * sr
    m[:, 2, 1] = sp
    m[:, 2, 2] = cp * cr
    return m


def _llh_rate(llh: np.ndarray, vel: np.ndarray) -> np.ndarray:
    r_m, r_n = radii_vec(llh[:, 0])
    h = llh[:, 2]
    return np.stack([vel[:, 1] / (r_m + h), vel[:, 0] / ((r_n + h) * np.cos(llh[:, 0])), vel[:, 2]], axis=-1)


def _imu_rates(kin: dict[str, np.ndarray], llh: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """omega_ib^b (rad/s) and f^b (m/s^2), each (P, 3), from kinematics and positions (P, 3)."""
    rpy, rpy_dot, vel, acc = kin["rpy"], kin["rpy_dot"], kin["vel"], kin["acc"]
    r, p = rpy[:, 0], rpy[:, 1]
    rd, pd, yd = rpy_dot[:, 0], rpy_dot[:, 1], rpy_dot[:, 2]
    sr, cr, sp, cp = np.sin(r), np.cos(r), np.sin(p), np.cos(p)
    # omega_nb^b of mat_nb = Rz(y) Rx(p) Ry(r): Ry(r)' (Rx(p)' [0,0,y'] + [p',0,0]) + [0,r',0]
    w_nb_b = np.stack([cr * pd - sr * cp * yd, rd + sp * yd, sr * pd + cr * cp * yd], axis=-1)
    lat, h = llh[:, 0], llh[:, 2]
    r_m, r_n = radii_vec(lat)
    w_ie = np.stack(
        [np.zeros_like(lat), earth.OMEGA_IE_RPS * np.cos(lat), earth.OMEGA_IE_RPS * np.sin(lat)], -1
    )
    ve, vn = vel[:, 0], vel[:, 1]
    w_en = np.stack([-vn / (r_m + h), ve / (r_n + h), ve * np.tan(lat) / (r_n + h)], axis=-1)
    g_n = np.zeros_like(vel)
    g_n[:, 2] = -gravity_vec(lat, h)
    f_n = acc - g_n + np.cross(2.0 * w_ie + w_en, vel)
    c_nb = mat_nb_vec(rpy)
    w_ib_b = w_nb_b + np.einsum("pji,pj->pi", c_nb, w_ie + w_en)  # C_bn = C_nb'
    f_b = np.einsum("pji,pj->pi", c_nb, f_n)
    return w_ib_b, f_b


def _hermite(y0, y1, d0, d1, s, dt):
    """Cubic Hermite between two samples (values y, derivatives d) at fraction s in [0, 1]."""
    s2, s3 = s * s, s * s * s
    return (
        (2 * s3 - 3 * s2 + 1) * y0
        + (s3 - 2 * s2 + s) * dt * d0
        + (-2 * s3 + 3 * s2) * y1
        + (s3 - s2) * dt * d1
    )


# --- trajectory -----------------------------------------------------------------------------------
@dataclass
class TruthState:
    """True state at one instant."""

    t_s: float
    llh: np.ndarray  # (3,) lat_rad, lon_rad, h_m
    vel_enu_mps: np.ndarray  # (3,)
    rpy_rad: np.ndarray  # (3,) roll, pitch, yaw (west positive, wrapped to [-pi, pi))


@dataclass
class Trajectory:
    """Truth samples at the IMU rate and exact (error-free) IMU increments.

    Attributes
    ----------
    t_s : (N,) GPS time of each sample, ``t0_gps_s + k / imu_rate_hz``.
    llh : (N, 3) geodetic latitude (rad), longitude (rad, continuous: not wrapped), height (m).
    vel_enu_mps : (N, 3) ground velocity, east/north/up.
    rpy_rad : (N, 3) roll, pitch, yaw (west positive, wrapped to [-pi, pi)).
    dtheta_rad : (N, 3) body angle increments over ``(t_{k-1}, t_k]``; row 0 is zeros.
    dvel_mps : (N, 3) body velocity (specific-force) increments over ``(t_{k-1}, t_k]``; row 0 zeros.
    """

    t_s: np.ndarray
    llh: np.ndarray
    vel_enu_mps: np.ndarray
    rpy_rad: np.ndarray
    dtheta_rad: np.ndarray
    dvel_mps: np.ndarray
    imu_rate_hz: float
    t0_gps_s: float
    _profile: _Profile = field(repr=False)
    _llh_dot: np.ndarray = field(repr=False)

    @property
    def dt_s(self) -> float:
        return 1.0 / self.imu_rate_hz

    @property
    def duration_s(self) -> float:
        return (self.t_s.size - 1) / self.imu_rate_hz

    def index_of(self, t_s: float) -> int | None:
        """Sample index whose time is ``t_s`` (within 1 us), else None."""
        k = int(round((t_s - self.t0_gps_s) * self.imu_rate_hz))
        if 0 <= k < self.t_s.size and abs(t_s - self.t_s[k]) < 1e-6:
            return k
        return None

    def _llh_rel(self, t_rel_s: np.ndarray) -> np.ndarray:
        """Positions at relative times by cubic Hermite on the samples and their exact rates."""
        t = np.asarray(t_rel_s, dtype=float)
        x = t * self.imu_rate_hz
        k = np.clip(np.floor(x).astype(int), 0, self.t_s.size - 2)
        s = (x - k)[:, None]
        y = _hermite(self.llh[k], self.llh[k + 1], self._llh_dot[k], self._llh_dot[k + 1], s, self.dt_s)
        exact = np.abs(x - np.round(x)) < 1e-9
        if np.any(exact):
            y[exact] = self.llh[np.clip(np.round(x[exact]).astype(int), 0, self.t_s.size - 1)]
        return y

    def state_at(self, t_s: float) -> TruthState:
        """True state at GPS time ``t_s`` (exact sample when ``t_s`` is a sample time).

        Between samples, attitude and velocity are evaluated analytically and the position by cubic
        Hermite interpolation (error ~1e-12 relative at 100 Hz). Note that a GPS time near 1.3e9 s
        resolves only ~2.4e-7 s; use :meth:`state_at_rel` for full resolution between samples.
        """
        k = self.index_of(t_s)
        if k is not None:
            return TruthState(
                float(self.t_s[k]), self.llh[k].copy(), self.vel_enu_mps[k].copy(), self.rpy_rad[k].copy()
            )
        return self.state_at_rel(t_s - self.t0_gps_s)

    def state_at_rel(self, t_rel_s: float) -> TruthState:
        """True state at ``t_rel_s`` seconds after the start (full time resolution; see :meth:`state_at`)."""
        t_rel = float(t_rel_s)
        if not (-1e-9 <= t_rel <= self.duration_s + 1e-9):
            raise ValueError(f"t_rel_s = {t_rel} is outside the trajectory [0, {self.duration_s}]")
        kin = self._profile.kinematics(np.array([t_rel]))
        rpy = kin["rpy"][0].copy()
        rpy[2] = float(earth.wrap_pi(rpy[2]))
        return TruthState(self.t0_gps_s + t_rel, self._llh_rel(np.array([t_rel]))[0], kin["vel"][0], rpy)

    def body_rates(self, t_rel_s: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """True ``omega_ib^b`` (rad/s) and ``f^b`` (m/s^2), each (P, 3), at relative times (P,) in s."""
        t = np.atleast_1d(np.asarray(t_rel_s, dtype=float))
        return _imu_rates(self._profile.kinematics(t), self._llh_rel(t))

    def kinematics(self, t_rel_s: np.ndarray) -> dict[str, np.ndarray]:
        """Analytic ``rpy``, ``rpy_dot``, ``vel``, ``acc`` (each (P, 3)) at relative times (P,) in s."""
        return self._profile.kinematics(np.atleast_1d(np.asarray(t_rel_s, dtype=float)))


def build_trajectory(
    start: StartSpec,
    segments: list,
    imu_rate_hz: float,
    t0_gps_s: float,
    duration_s: float | None = None,
) -> Trajectory:
    """Build truth and exact IMU increments.

    Parameters
    ----------
    start : StartSpec
        Initial position, heading and speed (level attitude).
    segments : list of Segment
        Flown in order. Durations and ramps must be multiples of ``1 / imu_rate_hz``.
    imu_rate_hz : float
        Sample rate of truth and increments.
    t0_gps_s : float
        GPS time of the first sample.
    duration_s : float, optional
        Total duration; the segments are padded with straight flight up to it (they must not exceed it).

    Returns
    -------
    Trajectory
    """
    if not imu_rate_hz > 0:
        raise ValueError("imu_rate_hz must be > 0")
    prof = _plan(start, segments, imu_rate_hz, duration_s)
    n = int(round(prof.duration_s * imu_rate_hz)) + 1
    dt = 1.0 / imu_rate_hz
    k = np.arange(n)
    t_rel = k / imu_rate_hz
    # Gauss-Legendre nodes of every interval (t_{k-1}, t_k], flattened (sorted).
    frac = 0.5 * (1.0 + _GL_X)  # (5,)
    t_nodes = (t_rel[:-1, None] + dt * frac[None, :]).ravel()
    w_half = 0.5 * dt * _GL_W  # weights on an interval of length dt

    kin_g = prof.kinematics(t_rel)
    kin_n = prof.kinematics(t_nodes)
    vel_g, vel_n = kin_g["vel"], kin_n["vel"]
    m = n - 1

    def quad(vals_nodes: np.ndarray) -> np.ndarray:
        """Per-interval integrals (m, ...) of values at the nodes (m*5, ...)."""
        return np.tensordot(vals_nodes.reshape((m, 5) + vals_nodes.shape[1:]), w_half, axes=([1], [0]))

    def cum(vals_nodes: np.ndarray, x0: float) -> np.ndarray:
        return np.concatenate([[x0], x0 + np.cumsum(quad(vals_nodes))])

    def at_nodes(y_g: np.ndarray, d_g: np.ndarray) -> np.ndarray:
        s = np.broadcast_to(frac, (m, 5))
        return _hermite(y_g[:-1, None], y_g[1:, None], d_g[:-1, None], d_g[1:, None], s, dt).ravel()

    # Height: exact cumulative quadrature of vu.
    h_g = cum(vel_n[:, 2], prof.h0_m)
    h_n = at_nodes(h_g, vel_g[:, 2])
    # Latitude: Picard iteration of dlat/dt = vn / (R_M(lat) + h).
    lat_g = np.full(n, prof.lat0_rad)
    for _ in range(4):
        r_m_g, _ = radii_vec(lat_g)
        dlat_g = vel_g[:, 1] / (r_m_g + h_g)
        lat_n = at_nodes(lat_g, dlat_g)
        r_m_n, _ = radii_vec(lat_n)
        lat_g = cum(vel_n[:, 1] / (r_m_n + h_n), prof.lat0_rad)
    r_m_g, r_n_g = radii_vec(lat_g)
    dlat_g = vel_g[:, 1] / (r_m_g + h_g)
    lat_n = at_nodes(lat_g, dlat_g)
    _, r_n_n = radii_vec(lat_n)
    lon_g = cum(vel_n[:, 0] / ((r_n_n + h_n) * np.cos(lat_n)), prof.lon0_rad)
    llh_g = np.stack([lat_g, lon_g, h_g], axis=-1)
    llh_n = np.stack([lat_n, np.zeros_like(lat_n), h_n], axis=-1)  # longitude does not enter the rates

    w_ib_b, f_b = _imu_rates(kin_n, llh_n)
    dtheta = np.zeros((n, 3))
    dvel = np.zeros((n, 3))
    dtheta[1:] = quad(w_ib_b)
    dvel[1:] = quad(f_b)

    rpy = kin_g["rpy"].copy()
    rpy[:, 2] = earth.wrap_pi(rpy[:, 2])
    return Trajectory(
        t_s=t0_gps_s + t_rel,
        llh=llh_g,  # longitude not wrapped (continuous); wrap when formatting messages
        vel_enu_mps=vel_g,
        rpy_rad=rpy,
        dtheta_rad=dtheta,
        dvel_mps=dvel,
        imu_rate_hz=float(imu_rate_hz),
        t0_gps_s=float(t0_gps_s),
        _profile=prof,
        _llh_dot=_llh_rate(llh_g, vel_g),
    )
