"""Receiver-side atmosphere models of the raw-GNSS measurement model (single frequency).

- :func:`klobuchar_gps_s`: GPS broadcast ionosphere, IS-GPS-200N 20.3.3.5.2.5 (Figure 20-4): the
  L1 slant delay in seconds from the eight broadcast coefficients, the user's geodetic latitude/
  longitude, the satellite's elevation/azimuth and GPS time. Angles of the ICD are semicircles.
- :func:`klobuchar_bds_s`: BeiDou broadcast ionosphere, BDS-SIS-ICD-B1I (v3.0) 5.2.4.7: the B1I
  slant delay; the pierce point on a 375 km shell (geographic latitude/longitude), BDT, the
  period clamped to [72000, 172800] s and the obliquity ``1 / sqrt(1 - (R cos E / (R + h))^2)``.
- :func:`saastamoinen_zenith_m`: Saastamoinen (1972) hydrostatic + wet zenith delay with a
  standard atmosphere (pressure/temperature from height, 70 % relative humidity): ~2.3 m hydro +
  ~0.1-0.2 m wet at sea level.
- :func:`tropo_mapping`: RTCA DO-229 mapping ``1.001 / sqrt(0.002001 + sin^2 E)`` (1.000 at the
  zenith, ~10 at 5 deg).

The ionosphere scales as 1/f^2: a delay modelled for one carrier is multiplied by
``(f_model / f_signal)^2`` for another (BeiDou B1I from GPS coefficients, Galileo E1 = GPS L1).
"""

from __future__ import annotations

import math

import numpy as np

from fednav.service import earth

C_MPS = earth.C_MPS  # one definition of the speed of light (service.earth)
GPS_L1_HZ = 1575.42e6
BDS_B1I_HZ = 1561.098e6


def klobuchar_gps_s(
    alpha: np.ndarray,
    beta: np.ndarray,
    lat_rad: float,
    lon_rad: float,
    el_rad: np.ndarray,
    az_rad: np.ndarray,
    t_gps_s: float,
) -> np.ndarray:
    """GPS L1 ionospheric slant delay (s), IS-GPS-200N 20.3.3.5.2.5, vectorised over satellites."""
    el = np.asarray(el_rad, dtype=float) / math.pi  # semicircles
    az = np.asarray(az_rad, dtype=float)
    phi_u, lam_u = lat_rad / math.pi, lon_rad / math.pi
    psi = 0.0137 / (el + 0.11) - 0.022  # earth-centred angle, semicircles
    phi_i = np.clip(phi_u + psi * np.cos(az), -0.416, 0.416)
    lam_i = lam_u + psi * np.sin(az) / np.cos(phi_i * math.pi)
    phi_m = phi_i + 0.064 * np.cos((lam_i - 1.617) * math.pi)  # geomagnetic latitude, semicircles
    t = np.mod(4.32e4 * lam_i + t_gps_s, 86400.0)
    f = 1.0 + 16.0 * (0.53 - el) ** 3  # obliquity
    a = np.asarray(alpha, dtype=float)
    b = np.asarray(beta, dtype=float)
    amp = np.maximum(a[0] + phi_m * (a[1] + phi_m * (a[2] + phi_m * a[3])), 0.0)
    per = np.maximum(b[0] + phi_m * (b[1] + phi_m * (b[2] + phi_m * b[3])), 72000.0)
    x = 2.0 * math.pi * (t - 50400.0) / per
    day = 5.0e-9 + amp * (1.0 - x**2 / 2.0 + x**4 / 24.0)
    return f * np.where(np.abs(x) < 1.57, day, 5.0e-9)


BDS_SHELL_M = 375e3
BDS_EARTH_R_M = 6378e3


def klobuchar_bds_s(
    alpha: np.ndarray,
    beta: np.ndarray,
    lat_rad: float,
    lon_rad: float,
    el_rad: np.ndarray,
    az_rad: np.ndarray,
    t_gps_s: float,
) -> np.ndarray:
    """BeiDou B1I ionospheric slant delay (s), BDS-SIS-ICD-B1I 5.2.4.7 (time converted to BDT)."""
    el = np.asarray(el_rad, dtype=float)
    az = np.asarray(az_rad, dtype=float)
    k = BDS_EARTH_R_M / (BDS_EARTH_R_M + BDS_SHELL_M) * np.cos(el)
    psi = math.pi / 2.0 - el - np.arcsin(k)  # earth-centred angle, rad
    phi_m = np.arcsin(math.sin(lat_rad) * np.cos(psi) + math.cos(lat_rad) * np.sin(psi) * np.cos(az))
    lam_m = lon_rad + np.arcsin(np.sin(psi) * np.sin(az) / np.cos(phi_m))
    t_bdt = t_gps_s - 14.0
    t = np.mod(t_bdt + lam_m * 43200.0 / math.pi, 86400.0)
    x = np.abs(phi_m / math.pi)
    a = np.asarray(alpha, dtype=float)
    b = np.asarray(beta, dtype=float)
    a2 = np.maximum(a[0] + x * (a[1] + x * (a[2] + x * a[3])), 0.0)
    a4 = np.clip(b[0] + x * (b[1] + x * (b[2] + x * b[3])), 72000.0, 172800.0)
    dt = t - 50400.0
    iz = np.where(np.abs(dt) < a4 / 4.0, 5.0e-9 + a2 * np.cos(2.0 * math.pi * dt / a4), 5.0e-9)
    return iz / np.sqrt(1.0 - k * k)


def saastamoinen_zenith_m(lat_rad: float, height_m: float, rel_humidity: float = 0.7) -> float:
    """Saastamoinen zenith delay (hydrostatic + wet), m, standard atmosphere at ``height_m``
    (pressure 1013.25 hPa, 15 C at sea level, lapse 6.5 K/km; Saastamoinen 1972 with the
    Davis et al. 1985 gravity term). Heights are clamped to [0, 10 km] (outside: the model's
    standard atmosphere does not apply)."""
    h = min(max(height_m, 0.0), 1.0e4)
    pres_hpa = 1013.25 * (1.0 - 2.2557e-5 * h) ** 5.2568
    temp_k = 15.0 - 6.5e-3 * h + 273.16
    e_hpa = 6.108 * rel_humidity * math.exp((17.15 * temp_k - 4684.0) / (temp_k - 38.45))
    hydro = 0.0022768 * pres_hpa / (1.0 - 0.00266 * math.cos(2.0 * lat_rad) - 0.00028 * h / 1e3)
    wet = 0.002277 * (1255.0 / temp_k + 0.05) * e_hpa
    return hydro + wet


def tropo_mapping(el_rad: np.ndarray) -> np.ndarray:
    """RTCA DO-229 troposphere mapping function ``1.001 / sqrt(0.002001 + sin^2 E)``."""
    s = np.sin(np.asarray(el_rad, dtype=float))
    return 1.001 / np.sqrt(0.002001 + s * s)


__all__ = [
    "BDS_B1I_HZ",
    "GPS_L1_HZ",
    "klobuchar_bds_s",
    "klobuchar_gps_s",
    "saastamoinen_zenith_m",
    "tropo_mapping",
]
