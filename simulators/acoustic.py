"""Underwater aiding sensors (seed 004, Xu et al. 2017): USBL body vectors to a transponder and DVL
body velocities, on the IMU grid like :mod:`simulators.sensors`.

Fault channels (see :mod:`simulators.faults`):

========  ==========================  =====================================================
sensor    channels                    quantity the channel carries (``scale`` multiplies it)
========  ==========================  =====================================================
usbl      rel_x, rel_y, rel_z         measured body vector array -> transponder, m (the
                                      paper's multipath fault: ``scale`` with factor 0.1)
dvl       vel_x, vel_y, vel_z         measured body velocity, m/s
dvl       lock                        bottom lock, 1 = locked; below 0.5 no message is sent
                                      (bottom-lock loss: ``scale`` with factor 0)
========  ==========================  =====================================================
"""

from __future__ import annotations

import math
from typing import Literal

import numpy as np
from pydantic import BaseModel, ConfigDict, Field

from fednav.service import earth
from fednav.service.messages import DvlVelocity, UsblFix
from fednav.simulators.faults import FaultSet
from fednav.simulators.sensors import epoch_step
from fednav.simulators.trajectory import Trajectory, mat_nb_vec

USBL_SENSOR = "usbl"
DVL_SENSOR = "dvl"
USBL_CHANNELS = ("rel_x", "rel_y", "rel_z")
DVL_CHANNELS = ("vel_x", "vel_y", "vel_z", "lock")

Vec3 = tuple[float, float, float]


class _Spec(BaseModel):
    model_config = ConfigDict(extra="forbid", frozen=True)


class UsblSpec(_Spec):
    """USBL on the vehicle and its transponder: noise floor, slant-range and bearing errors."""

    id: str = Field(default="main", pattern=r"^[A-Za-z0-9_\-.]+$", description="Sensor id in the key")
    rate_hz: float = Field(default=1.0, gt=0.0, description="Fix rate, Hz (must divide the IMU rate)")
    transponder_lat_deg: float = Field(ge=-90.0, le=90.0)
    transponder_lon_deg: float = Field(ge=-180.0, le=180.0)
    transponder_height_m: float = Field(ge=-12000.0, le=1000.0, description="Ellipsoidal height, m")
    base_std_m: float = Field(default=5.0, gt=0.0, description="Noise floor on every axis, m")
    range_fraction: float = Field(default=0.005, ge=0.0, lt=1.0, description="Slant-range noise / range")
    angle_std_deg: float = Field(default=0.1, ge=0.0, lt=10.0, description="Bearing noise, deg")
    lever_arm_b_m: Vec3 = Field(default=(0.0, 0.0, 0.0), description="Array in body axes from the IMU, m")


class DvlSpec(_Spec):
    """DVL: per-axis offset and scale-factor error (drawn per run or fixed), white noise."""

    id: str = Field(default="main", pattern=r"^[A-Za-z0-9_\-.]+$", description="Sensor id in the key")
    rate_hz: float = Field(default=1.0, gt=0.0, description="Output rate, Hz (must divide the IMU rate)")
    error_mode: Literal["random", "fixed"] = Field(
        default="random", description="random: offset/scale are 1-sigma, drawn per run; fixed: applied"
    )
    offset_mps: Vec3 = Field(default=(0.4, 0.4, 0.4), description="Velocity offset per body axis, m/s")
    scale: Vec3 = Field(default=(1e-3, 1e-3, 1e-3), description="Scale-factor error per axis (1e-3 = 0.1 %)")
    noise_std_mps: float = Field(default=0.016, gt=0.0, description="White noise per axis, m/s")
    lever_arm_b_m: Vec3 = Field(default=(0.0, 0.0, 0.0), description="DVL in body axes from the IMU, m")


def transponder_ecef(spec: UsblSpec) -> np.ndarray:
    return earth.llh_to_ecef(
        np.array(
            [
                math.radians(spec.transponder_lat_deg),
                math.radians(spec.transponder_lon_deg),
                spec.transponder_height_m,
            ]
        )
    )


def true_usbl_vectors(spec: UsblSpec, traj: Trajectory, ks: np.ndarray) -> np.ndarray:
    """(P, 3) true body vectors array -> transponder at IMU samples ``ks``."""
    llh = traj.llh[ks]
    d_e = transponder_ecef(spec)[None, :] - earth.llh_to_ecef(llh)
    lat, lon = llh[:, 0], llh[:, 1]
    sl, cl, so, co = np.sin(lat), np.cos(lat), np.sin(lon), np.cos(lon)
    d_n = np.stack(
        [
            -so * d_e[:, 0] + co * d_e[:, 1],
            -sl * co * d_e[:, 0] - sl * so * d_e[:, 1] + cl * d_e[:, 2],
            cl * co * d_e[:, 0] + cl * so * d_e[:, 1] + sl * d_e[:, 2],
        ],
        axis=-1,
    )
    c_nb = mat_nb_vec(traj.rpy_rad[ks])
    return np.einsum("pji,pj->pi", c_nb, d_n) - np.asarray(spec.lever_arm_b_m)[None, :]


def usbl_covariance(r: np.ndarray, spec: UsblSpec) -> np.ndarray:
    """(P, 3, 3) noise covariance of vectors r (P, 3): floor + slant range along + bearing across."""
    slant = np.linalg.norm(r, axis=1)
    u = r / np.maximum(slant, 1e-9)[:, None]
    uu = u[:, :, None] * u[:, None, :]
    eye = np.eye(3)[None]
    return (
        spec.base_std_m**2 * eye
        + ((spec.range_fraction * slant) ** 2)[:, None, None] * uu
        + ((slant * math.radians(spec.angle_std_deg)) ** 2)[:, None, None] * (eye - uu)
    )


def simulate_usbl(
    spec: UsblSpec, traj: Trajectory, rng: np.random.Generator, faults: FaultSet | None = None
) -> list[tuple[int, UsblFix]]:
    """USBL fixes as ``(imu_sample_index, message)`` pairs; noise ~ N(0, usbl_covariance)."""
    step = epoch_step(traj.imu_rate_hz, spec.rate_hz, "usbl.rate_hz")
    ks = np.arange(step, traj.t_s.size, step)
    r_true = true_usbl_vectors(spec, traj, ks)
    cov = usbl_covariance(r_true, spec)
    L = np.linalg.cholesky(cov)
    meas = r_true + np.einsum("pij,pj->pi", L, rng.standard_normal((ks.size, 3)))
    std = np.sqrt(np.diagonal(cov, axis1=1, axis2=2))
    out = []
    for i, k in enumerate(ks.tolist()):
        r = meas[i]
        if faults is not None:
            vals = faults.apply(
                USBL_SENSOR, k / traj.imu_rate_hz, dict(zip(USBL_CHANNELS, r.tolist(), strict=True))
            )
            r = np.array([vals[c] for c in USBL_CHANNELS])
        msg = UsblFix(
            t=float(traj.t_s[k]),
            rel_b_m=tuple(float(x) for x in r),
            transponder_lat_deg=spec.transponder_lat_deg,
            transponder_lon_deg=spec.transponder_lon_deg,
            transponder_height_m=spec.transponder_height_m,
            rel_std_m=tuple(float(x) for x in std[i]),
        )
        out.append((k, msg))
    return out


def draw_dvl_errors(spec: DvlSpec, rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray]:
    """(offset_mps (3,), scale (3,)) of one run."""
    off, sc = np.asarray(spec.offset_mps, float), np.asarray(spec.scale, float)
    if spec.error_mode == "random":
        z = rng.standard_normal(6)
        return z[:3] * off, z[3:] * sc
    return off.copy(), sc.copy()


def simulate_dvl(
    spec: DvlSpec,
    traj: Trajectory,
    rng: np.random.Generator,
    offset_mps: np.ndarray,
    scale: np.ndarray,
    faults: FaultSet | None = None,
) -> list[tuple[int, DvlVelocity]]:
    """DVL velocities as ``(imu_sample_index, message)`` pairs:
    v = (1 + scale) o (C_nb' v_n + w_ib x l_b) + offset + n (w from the IMU increments)."""
    step = epoch_step(traj.imu_rate_hz, spec.rate_hz, "dvl.rate_hz")
    ks = np.arange(step, traj.t_s.size, step)
    c_nb = mat_nb_vec(traj.rpy_rad[ks])
    u = np.einsum("pji,pj->pi", c_nb, traj.vel_enu_mps[ks])
    w = traj.dtheta_rad[ks] * traj.imu_rate_hz
    u = u + np.cross(w, np.asarray(spec.lever_arm_b_m)[None, :])
    meas = (
        (1.0 + scale)[None, :] * u
        + offset_mps[None, :]
        + spec.noise_std_mps * rng.standard_normal((ks.size, 3))
    )
    out = []
    for i, k in enumerate(ks.tolist()):
        v = meas[i]
        if faults is not None:
            vals = faults.apply(
                DVL_SENSOR, k / traj.imu_rate_hz, dict(zip(DVL_CHANNELS, [*v.tolist(), 1.0], strict=True))
            )
            if vals["lock"] < 0.5:
                continue  # bottom lock lost: no velocity output
            v = np.array([vals[c] for c in DVL_CHANNELS[:3]])
        msg = DvlVelocity(
            t=float(traj.t_s[k]),
            vel_b_mps=tuple(float(x) for x in v),
            vel_std_mps=(spec.noise_std_mps,) * 3,
        )
        out.append((k, msg))
    return out
