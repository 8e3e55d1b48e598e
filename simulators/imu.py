"""IMU error model applied to exact increments.

Measured increment over an interval of length ``dt`` (per axis, body frame)::

    dtheta_meas = (1 + s_g) dtheta + (b_g + m_g) dt + arw * sqrt(dt) * n
    dvel_meas   = (1 + s_a) dvel   + (b_a + m_a) dt + vrw * sqrt(dt) * n

with ``b`` the constant (turn-on) bias, ``m`` the bias instability (first-order Gauss-Markov,
stationary, ``m_k = exp(-dt/tau) m_{k-1} + sigma sqrt(1 - exp(-2 dt/tau)) w``, sampled at the end
of each interval), ``s`` the scale-factor error and ``n ~ N(0, 1)``.

Units of the specification: deg/h (gyro bias), ug (accel bias; 1 ug = :data:`service.earth.UG`),
deg/sqrt(h) (angle random walk; ``arw_rad_per_sqrt_s = arw_dpsh * DEG / 60``), ug/sqrt(Hz)
(velocity random walk; ``vrw_mps_per_sqrt_s = vrw * UG``), ppm (scale factor).

References: IEEE Std 952-1997 (random walk and bias instability terms); Groves (2013) sec. 4.4.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Literal

import numpy as np
from pydantic import BaseModel, ConfigDict, Field, model_validator
from scipy.signal import lfilter

from fednav.service import earth

Vec3 = tuple[float, float, float]


class ImuSpec(BaseModel):
    """IMU grade and identity.

    ``bias_mode = "random"``: ``gyro_bias_dph``, ``accel_bias_ug``, ``gyro_scale_ppm`` and
    ``accel_scale_ppm`` are 1-sigma values, each axis drawn per run as N(0, sigma).
    ``bias_mode = "fixed"``: they are the values applied (any sign).
    """

    model_config = ConfigDict(extra="forbid", frozen=True)

    id: str = Field(default="main", pattern=r"^[A-Za-z0-9_\-.]+$", description="Sensor id in the key")
    rate_hz: float = Field(default=100.0, gt=0.0, le=10000.0, description="Sample rate, Hz")
    bias_mode: Literal["random", "fixed"] = Field(
        default="random", description="Draw biases and scale factors per run (sigmas) or apply them as given"
    )
    gyro_bias_dph: Vec3 = Field(default=(0.0, 0.0, 0.0), description="Gyro constant bias per axis, deg/h")
    accel_bias_ug: Vec3 = Field(
        default=(0.0, 0.0, 0.0), description="Accelerometer constant bias per axis, ug"
    )
    gyro_scale_ppm: Vec3 = Field(default=(0.0, 0.0, 0.0), description="Gyro scale-factor error per axis, ppm")
    accel_scale_ppm: Vec3 = Field(
        default=(0.0, 0.0, 0.0), description="Accel scale-factor error per axis, ppm"
    )
    arw_dpsh: float = Field(default=0.0, ge=0.0, description="Angle random walk, deg/sqrt(h)")
    vrw_ugpsHz: float = Field(default=0.0, ge=0.0, description="Velocity random walk, ug/sqrt(Hz)")
    gyro_bias_instability_dph: float = Field(
        default=0.0, ge=0.0, description="Gyro bias instability (Gauss-Markov sigma), deg/h"
    )
    gyro_bias_tau_s: float = Field(
        default=3600.0, gt=0.0, description="Gyro Gauss-Markov correlation time, s"
    )
    accel_bias_instability_ug: float = Field(
        default=0.0, ge=0.0, description="Accel bias instability (Gauss-Markov sigma), ug"
    )
    accel_bias_tau_s: float = Field(
        default=3600.0, gt=0.0, description="Accel Gauss-Markov correlation time, s"
    )

    @model_validator(mode="after")
    def _sigmas_nonnegative(self):
        if self.bias_mode == "random":
            for name in ("gyro_bias_dph", "accel_bias_ug", "gyro_scale_ppm", "accel_scale_ppm"):
                if min(getattr(self, name)) < 0.0:
                    raise ValueError(f"{name}: sigmas must be >= 0 when bias_mode = 'random'")
        return self


@dataclass
class ImuErrorTruth:
    """The errors one run actually applied (for evaluation; never given to filters).

    Attributes
    ----------
    gyro_bias_rps, accel_bias_mps2 : (3,) constant biases (rad/s, m/s^2).
    gyro_scale, accel_scale : (3,) scale-factor errors (dimensionless).
    gyro_markov_rps, accel_markov_mps2 : (N, 3) bias-instability state at each sample (row 0 = initial).
    """

    gyro_bias_rps: np.ndarray
    accel_bias_mps2: np.ndarray
    gyro_scale: np.ndarray
    accel_scale: np.ndarray
    gyro_markov_rps: np.ndarray
    accel_markov_mps2: np.ndarray

    @property
    def gyro_bias_dph(self) -> np.ndarray:
        return self.gyro_bias_rps / earth.DPH

    @property
    def accel_bias_ug(self) -> np.ndarray:
        return self.accel_bias_mps2 / earth.UG


def _gauss_markov(n: int, sigma: float, tau_s: float, dt_s: float, rng: np.random.Generator) -> np.ndarray:
    """Stationary first-order Gauss-Markov sequence (n, 3) with std ``sigma``."""
    w = rng.standard_normal((n, 3))
    if sigma == 0.0:
        return np.zeros((n, 3))
    phi = np.exp(-dt_s / tau_s)
    drive = sigma * np.sqrt(1.0 - phi * phi)
    x = np.empty((n, 3))
    x[0] = sigma * w[0]
    # x_k = phi x_{k-1} + drive w_k, via a one-pole filter seeded with x_0
    x[1:] = lfilter([drive], [1.0, -phi], w[1:], axis=0, zi=(phi * x[0])[None, :])[0]
    return x


def apply_imu_errors(
    spec: ImuSpec, dtheta_rad: np.ndarray, dvel_mps: np.ndarray, rng: np.random.Generator
) -> tuple[np.ndarray, np.ndarray, ImuErrorTruth]:
    """Corrupt exact increments with the errors of ``spec``.

    Parameters
    ----------
    spec : ImuSpec
    dtheta_rad, dvel_mps : (N, 3)
        Exact increments at ``spec.rate_hz``; row 0 (no interval) is left at zero.
    rng : numpy.random.Generator
        Seeded generator; the draw order is fixed, so a seed reproduces a run.

    Returns
    -------
    dtheta_meas_rad, dvel_meas_mps : (N, 3)
    truth : ImuErrorTruth
    """
    n = dtheta_rad.shape[0]
    dt = 1.0 / spec.rate_hz

    def draw(v) -> np.ndarray:
        v = np.asarray(v, dtype=float)
        z = rng.standard_normal(3)
        return v * z if spec.bias_mode == "random" else v.copy()

    b_g = draw(spec.gyro_bias_dph) * earth.DPH
    b_a = draw(spec.accel_bias_ug) * earth.UG
    s_g = draw(spec.gyro_scale_ppm) * 1e-6
    s_a = draw(spec.accel_scale_ppm) * 1e-6
    m_g = _gauss_markov(n, spec.gyro_bias_instability_dph * earth.DPH, spec.gyro_bias_tau_s, dt, rng)
    m_a = _gauss_markov(n, spec.accel_bias_instability_ug * earth.UG, spec.accel_bias_tau_s, dt, rng)
    arw = spec.arw_dpsh * earth.DEG / 60.0  # rad/sqrt(s)
    vrw = spec.vrw_ugpsHz * earth.UG  # (m/s^2)/sqrt(Hz) = (m/s)/sqrt(s)
    n_g = rng.standard_normal((n, 3)) * (arw * np.sqrt(dt))
    n_a = rng.standard_normal((n, 3)) * (vrw * np.sqrt(dt))

    dth = (1.0 + s_g) * dtheta_rad + (b_g + m_g) * dt + n_g
    dv = (1.0 + s_a) * dvel_mps + (b_a + m_a) * dt + n_a
    dth[0] = 0.0
    dv[0] = 0.0
    return dth, dv, ImuErrorTruth(b_g, b_a, s_g, s_a, m_g, m_a)
