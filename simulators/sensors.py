"""Aiding sensor models: GNSS position/velocity fixes and a star tracker.

Epochs fall exactly on IMU sample times: a sensor at ``rate_hz`` samples every
``imu_rate_hz / rate_hz`` IMU steps (an integer), starting one sensor period after the start, and
its message time is the trajectory's ``t_s[k]`` bit for bit.

Fault channels (see :mod:`simulators.faults`):

========  ==========================  =====================================================
sensor    channels                    quantity the channel carries (``scale`` multiplies it)
========  ==========================  =====================================================
gnss      pos_e, pos_n, pos_u         position error, measured minus true, ENU metres
gnss      vel_e, vel_n, vel_u         measured velocity, ENU m/s
star      roll, pitch, yaw            attitude error, measured minus true Euler angle, arcsec
                                      (yaw west positive: a +yaw error is a -heading error)
========  ==========================  =====================================================
"""

from __future__ import annotations

from typing import Literal

import numpy as np
from pydantic import BaseModel, ConfigDict, Field, field_validator
from scipy.signal import lfilter

from fednav.service import earth
from fednav.service.estimation.measurements.gnss_fix import LABELS as GNSS_FIX_LABELS
from fednav.service.messages import GnssFix, StarAttitude
from fednav.simulators.faults import FaultSet
from fednav.simulators.trajectory import Trajectory, mat_nb_vec, radii_vec

GNSS_SENSOR = "gnss"
STAR_SENSOR = "star"
#: fault channels of a GNSS fix = the rows of the service's fix model (Faults labels)
GNSS_CHANNELS = GNSS_FIX_LABELS
STAR_CHANNELS = ("roll", "pitch", "yaw")

Vec3 = tuple[float, float, float]


def _positive3(v: tuple[float, float, float], name: str) -> tuple[float, float, float]:
    if min(v) <= 0.0:
        raise ValueError(f"{name}: every component must be > 0 (got {list(v)})")
    return v


class GnssSpec(BaseModel):
    """GNSS receiver producing position/velocity fixes with white noise."""

    model_config = ConfigDict(extra="forbid", frozen=True)

    id: str = Field(default="main", pattern=r"^[A-Za-z0-9_\-.]+$", description="Sensor id in the key")
    rate_hz: float = Field(default=1.0, gt=0.0, description="Fix rate, Hz (must divide the IMU rate)")
    pos_std_enu_m: Vec3 = Field(description="1-sigma position noise east/north/up, m")
    vel_std_enu_mps: Vec3 = Field(description="1-sigma velocity noise east/north/up, m/s")
    constellation: Literal["GPS", "BDS"] = Field(default="GPS", description="Constellation in the message")
    num_sats: int = Field(default=10, ge=0, le=200, description="Satellite count reported in the message")
    outages: list[tuple[float, float]] = Field(
        default_factory=list, description="No fixes for start_s <= t < end_s (s after the scenario start)"
    )
    variant: Literal["velocity", "speed_course", "position"] = Field(
        default="velocity",
        description="What the fix carries: 3-D velocity, horizontal speed + course (NMEA/Android), or "
        "position only",
    )
    vertical_rate: bool = Field(default=False, description="speed_course: also report the vertical rate")
    lever_arm_b_m: Vec3 = Field(
        default=(0.0, 0.0, 0.0), description="Antenna position from the IMU, body right/forward/up, m"
    )
    correlated_pos_std_enu_m: Vec3 = Field(
        default=(0.0, 0.0, 0.0),
        description="1-sigma of a first-order Gauss-Markov position error added to the white noise, "
        "east/north/up, m (0: none). The message reports the total sigma sqrt(white^2 + correlated^2)",
    )
    correlation_time_s: float = Field(default=60.0, gt=0.0, description="Its correlation time, s")

    @field_validator("pos_std_enu_m")
    @classmethod
    def _pos_pos(cls, v):
        return _positive3(v, "pos_std_enu_m")

    @field_validator("vel_std_enu_mps")
    @classmethod
    def _vel_pos(cls, v):
        return _positive3(v, "vel_std_enu_mps")

    @field_validator("outages")
    @classmethod
    def _outages_ordered(cls, v):
        for i, (a, b) in enumerate(v):
            if not (0.0 <= a < b):
                raise ValueError(f"outages[{i}] = [{a}, {b}]: need 0 <= start_s < end_s")
        return v


class StarSpec(BaseModel):
    """Star tracker: attitude with white noise, a small body-frame rotation of the true attitude."""

    model_config = ConfigDict(extra="forbid", frozen=True)

    id: str = Field(default="main", pattern=r"^[A-Za-z0-9_\-.]+$", description="Sensor id in the key")
    rate_hz: float = Field(default=1.0, gt=0.0, description="Output rate, Hz (must divide the IMU rate)")
    std_arcsec: Vec3 = Field(description="1-sigma noise about roll, pitch, yaw, arcsec")

    @field_validator("std_arcsec")
    @classmethod
    def _std_pos(cls, v):
        return _positive3(v, "std_arcsec")


def epoch_step(imu_rate_hz: float, rate_hz: float, what: str = "rate_hz") -> int:
    """IMU steps per sensor epoch; ValueError unless ``imu_rate_hz / rate_hz`` is an integer >= 1."""
    r = imu_rate_hz / rate_hz
    if abs(r - round(r)) > 1e-9 or round(r) < 1:
        raise ValueError(f"{what} = {rate_hz} Hz must divide the IMU rate {imu_rate_hz} Hz")
    return int(round(r))


def _epochs(traj: Trajectory, rate_hz: float, what: str) -> np.ndarray:
    step = epoch_step(traj.imu_rate_hz, rate_hz, what)
    return np.arange(step, traj.t_s.size, step)


def gauss_markov_sequence(
    rng: np.random.Generator, n: int, dt_s: float, tau_s: float, sigma: np.ndarray
) -> np.ndarray:
    """(n, len(sigma)) stationary first-order Gauss-Markov samples every dt_s:
    b_0 ~ N(0, sigma^2), b_k = a b_(k-1) + sigma sqrt(1 - a^2) w_k, a = exp(-dt/tau)."""
    a = float(np.exp(-dt_s / tau_s))
    w = rng.standard_normal((n, sigma.size))
    w[1:] *= np.sqrt(1.0 - a * a)
    out = lfilter([1.0], [1.0, -a], w, axis=0)
    return out * sigma


def simulate_gnss_fixes(
    spec: GnssSpec, traj: Trajectory, rng: np.random.Generator, faults: FaultSet | None = None
) -> list[tuple[int, GnssFix]]:
    """GNSS fixes as ``(imu_sample_index, message)`` pairs, in time order.

    Noise is drawn for every nominal epoch (outages included), so an outage does not change the
    noise of the other epochs. Position noise is generated in ENU metres and converted to
    latitude/longitude/height at the true position.
    """
    ks = _epochs(traj, spec.rate_hz, "gnss.rate_hz")
    t_rel = ks / traj.imu_rate_hz
    pos_err = rng.standard_normal((ks.size, 3)) * np.asarray(spec.pos_std_enu_m)
    vel_meas = traj.vel_enu_mps[ks] + rng.standard_normal((ks.size, 3)) * np.asarray(spec.vel_std_enu_mps)
    gm_std = np.asarray(spec.correlated_pos_std_enu_m, dtype=float)
    if np.any(gm_std > 0.0):  # drawn after the white noise: scenarios without it are unchanged
        pos_err = pos_err + gauss_markov_sequence(
            rng, ks.size, 1.0 / spec.rate_hz, spec.correlation_time_s, gm_std
        )
    lever = np.asarray(spec.lever_arm_b_m, dtype=float)
    if np.any(lever != 0.0):  # antenna offsets C_nb l and C_nb (w_ib x l)
        c_nb = mat_nb_vec(traj.rpy_rad[ks])
        w_b, _ = traj.body_rates(t_rel)
        ant_pos = np.einsum("pij,j->pi", c_nb, lever)
        ant_vel = np.einsum("pij,pj->pi", c_nb, np.cross(w_b, lever))
    else:
        ant_pos = ant_vel = np.zeros((ks.size, 3))
    pos_std_msg = tuple(float(x) for x in np.hypot(np.asarray(spec.pos_std_enu_m), gm_std))
    keep = np.ones(ks.size, dtype=bool)
    for a, b in spec.outages:
        keep &= ~((t_rel >= a) & (t_rel < b))
    out = []
    for i in np.flatnonzero(keep):
        k = int(ks[i])
        pe, vm = pos_err[i], vel_meas[i]
        if faults is not None:
            vals = dict(zip(GNSS_CHANNELS, [*pe.tolist(), *vm.tolist()], strict=True))
            vals = faults.apply(GNSS_SENSOR, float(t_rel[i]), vals)
            pe = np.array([vals[c] for c in GNSS_CHANNELS[:3]])
            vm = np.array([vals[c] for c in GNSS_CHANNELS[3:]])
        lat, lon, h = traj.llh[k]
        r_m, r_n = radii_vec(lat)
        pe = pe + ant_pos[i]
        vm = vm + ant_vel[i]
        lat_m = lat + pe[1] / (r_m + h)
        lon_m = lon + pe[0] / ((r_n + h) * np.cos(lat))
        vel_fields: dict = {}
        if spec.variant == "velocity":
            vel_fields = {
                "vel_enu_mps": tuple(float(x) for x in vm),
                "vel_std_enu_mps": tuple(float(x) for x in spec.vel_std_enu_mps),
            }
        elif spec.variant == "speed_course":
            vel_fields = {
                "speed_mps": float(np.hypot(vm[0], vm[1])),
                "course_deg": float(np.degrees(np.arctan2(vm[0], vm[1])) % 360.0),
                "speed_std_mps": float(spec.vel_std_enu_mps[0]),
            }
            if spec.vertical_rate:
                vel_fields["vertical_rate_mps"] = float(vm[2])
                vel_fields["vertical_rate_std_mps"] = float(spec.vel_std_enu_mps[2])
        msg = GnssFix(
            t=float(traj.t_s[k]),
            lat_deg=float(np.degrees(lat_m)),
            lon_deg=float(np.degrees(earth.wrap_pi(lon_m))),
            height_m=float(h + pe[2]),
            pos_std_enu_m=pos_std_msg,
            constellation=spec.constellation,
            num_sats=spec.num_sats,
            **vel_fields,
        )
        out.append((k, msg))
    return out


def _rotvec_to_mat_vec(rv: np.ndarray) -> np.ndarray:
    """Rodrigues formula, (P, 3) -> (P, 3, 3)."""
    a = np.linalg.norm(rv, axis=1)
    small = a < 1e-8
    a_safe = np.where(small, 1.0, a)
    s = np.where(small, 1.0 - a * a / 6.0, np.sin(a) / a_safe)
    c = np.where(small, 0.5 - a * a / 24.0, (1.0 - np.cos(a)) / (a_safe * a_safe))
    k = np.zeros(rv.shape[:1] + (3, 3))
    k[:, 0, 1], k[:, 0, 2] = -rv[:, 2], rv[:, 1]
    k[:, 1, 0], k[:, 1, 2] = rv[:, 2], -rv[:, 0]
    k[:, 2, 0], k[:, 2, 1] = -rv[:, 1], rv[:, 0]
    return np.eye(3) + s[:, None, None] * k + c[:, None, None] * (k @ k)


def _mat_nb_to_rpy_vec(m: np.ndarray) -> np.ndarray:
    pitch = np.arcsin(np.clip(m[:, 2, 1], -1.0, 1.0))
    roll = np.arctan2(-m[:, 2, 0], m[:, 2, 2])
    yaw = np.arctan2(-m[:, 0, 1], m[:, 1, 1])
    return np.stack([roll, pitch, yaw], axis=-1)


def simulate_star(
    spec: StarSpec, traj: Trajectory, rng: np.random.Generator, faults: FaultSet | None = None
) -> list[tuple[int, StarAttitude]]:
    """Star-tracker attitudes as ``(imu_sample_index, message)`` pairs, in time order.

    Noise: ``mat_nb_meas = mat_nb @ Rot(delta_b)``, ``delta_b`` about body right (pitch), forward
    (roll), up (yaw) with the stds of ``std_arcsec`` = [roll, pitch, yaw].
    """
    ks = _epochs(traj, spec.rate_hz, "star.rate_hz")
    t_rel = ks / traj.imu_rate_hz
    std_rad = np.asarray(spec.std_arcsec) * earth.ARCSEC
    z = rng.standard_normal((ks.size, 3)) * std_rad  # roll, pitch, yaw
    delta_b = np.stack([z[:, 1], z[:, 0], z[:, 2]], axis=-1)  # about right, forward, up
    rpy_true = traj.rpy_rad[ks]
    rpy_noisy = _mat_nb_to_rpy_vec(mat_nb_vec(rpy_true) @ _rotvec_to_mat_vec(delta_b))
    err_arcsec = earth.wrap_pi(rpy_noisy - rpy_true) / earth.ARCSEC
    std_deg = tuple(float(s) / 3600.0 for s in spec.std_arcsec)
    out = []
    for i, k in enumerate(ks.tolist()):
        e = err_arcsec[i]
        if faults is not None:
            vals = faults.apply(
                STAR_SENSOR, float(t_rel[i]), dict(zip(STAR_CHANNELS, e.tolist(), strict=True))
            )
            e = np.array([vals[c] for c in STAR_CHANNELS])
        rpy = rpy_true[i] + e * earth.ARCSEC
        roll = float(np.degrees(earth.wrap_pi(rpy[0])))
        msg = StarAttitude(
            t=float(traj.t_s[k]),
            rpy_deg=(roll, float(np.degrees(rpy[1])), earth.heading_deg_from_yaw(float(rpy[2]))),
            rpy_std_deg=std_deg,
        )
        out.append((k, msg))
    return out
