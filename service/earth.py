"""WGS-84 earth model, frames and rotations.

Conventions (the whole project follows these)
---------------------------------------------
- Navigation frame ``n`` = local-level ENU (east, north, up); body frame ``b`` = right, forward, up.
- Geodetic position ``llh`` = (lat_rad, lon_rad, h_m); ECEF in metres.
- ``mat_ab`` maps a vector expressed in frame b into frame a (``v_a = mat_ab @ v_b``).
- Attitude as roll, pitch, yaw (``rpy_rad``) with ENU/RFU: yaw is measured from north towards
  **west** positive (the PSINS convention, right-handed about up); heading (clockwise from north,
  used in messages) is ``-yaw`` wrapped to [0, 360) deg. ``mat_nb = Rz(yaw) @ Rx(pitch) @ Ry(roll)``.
- Quaternions are scalar-first ``[w, x, y, z]`` (Hamilton), ``q_nb`` rotates body vectors into nav.

References: NIMA TR8350.2 (WGS-84); Groves, *Principles of GNSS, Inertial, and Multisensor
Integrated Navigation Systems*, 2nd ed., ch. 2; Yan Gongmin, PSINS toolbox conventions.
"""

from __future__ import annotations

import math

import numpy as np

# --- WGS-84 defining and derived constants (NIMA TR8350.2) ---------------------------------------
A_M = 6378137.0  # semi-major axis
F = 1.0 / 298.257223563  # flattening
E2 = F * (2.0 - F)  # first eccentricity squared
B_M = A_M * (1.0 - F)  # semi-minor axis
OMEGA_IE_RPS = 7.292115e-5  # earth rotation rate
GM_M3PS2 = 3.986004418e14  # gravitational constant
G_EQUATOR_MPS2 = 9.7803253359  # normal gravity at the equator (Somigliana)
G_POLE_MPS2 = 9.8321849378  # normal gravity at the poles
K_SOMIGLIANA = (B_M * G_POLE_MPS2) / (A_M * G_EQUATOR_MPS2) - 1.0
M_GRAV = OMEGA_IE_RPS**2 * A_M**2 * B_M / GM_M3PS2
C_MPS = 299792458.0  # speed of light

DEG = math.pi / 180.0
ARCSEC = DEG / 3600.0
ARCMIN = DEG / 60.0
DPH = DEG / 3600.0  # deg/h in rad/s
UG = 9.7803253359e-6  # micro-g in m/s^2 (g of the equator, a common convention)


# --- radii, rates, gravity ------------------------------------------------------------------------
def radii(lat_rad: float) -> tuple[float, float]:
    """Meridian (R_M, north-south) and transverse (R_N, prime vertical) radii of curvature, metres."""
    s2 = math.sin(lat_rad) ** 2
    w = math.sqrt(1.0 - E2 * s2)
    r_n = A_M / w
    r_m = A_M * (1.0 - E2) / (w * w * w)
    return r_m, r_n


def gravity_normal(lat_rad: float, h_m: float) -> float:
    """Normal gravity magnitude (m/s^2) at latitude and height (Somigliana + free-air, TR8350.2 4-1/4-3)."""
    s2 = math.sin(lat_rad) ** 2
    g0 = G_EQUATOR_MPS2 * (1.0 + K_SOMIGLIANA * s2) / math.sqrt(1.0 - E2 * s2)
    # Second-order height correction (TR8350.2 eq 4-3).
    return g0 * (1.0 - 2.0 / A_M * (1.0 + F + M_GRAV - 2.0 * F * s2) * h_m + 3.0 / A_M**2 * h_m**2)


def earth_rate_n(lat_rad: float) -> np.ndarray:
    """Earth rotation rate in ENU, omega_ie^n (rad/s)."""
    return np.array([0.0, OMEGA_IE_RPS * math.cos(lat_rad), OMEGA_IE_RPS * math.sin(lat_rad)])


def transport_rate_n(lat_rad: float, h_m: float, vel_enu_mps: np.ndarray) -> np.ndarray:
    """Transport rate omega_en^n (rad/s) of the ENU frame over the ellipsoid."""
    r_m, r_n = radii(lat_rad)
    ve, vn = float(vel_enu_mps[0]), float(vel_enu_mps[1])
    return np.array([-vn / (r_m + h_m), ve / (r_n + h_m), ve * math.tan(lat_rad) / (r_n + h_m)])


# --- positions --------------------------------------------------------------------------------------
def llh_to_ecef(llh: np.ndarray) -> np.ndarray:
    """Geodetic (lat_rad, lon_rad, h_m) -> ECEF metres. Accepts (..., 3)."""
    llh = np.asarray(llh, dtype=float)
    lat, lon, h = llh[..., 0], llh[..., 1], llh[..., 2]
    sl, cl = np.sin(lat), np.cos(lat)
    r_n = A_M / np.sqrt(1.0 - E2 * sl * sl)
    return np.stack(
        [(r_n + h) * cl * np.cos(lon), (r_n + h) * cl * np.sin(lon), (r_n * (1.0 - E2) + h) * sl], axis=-1
    )


def llh_to_ecef_f(lat_rad: float, lon_rad: float, h_m: float) -> np.ndarray:
    """:func:`llh_to_ecef` of one point given as floats: the same expressions in the same order
    on Python floats (``math``'s sine and cosine give numpy's values), without the arrays of a
    batch (a tightly coupled filter needs its receiver's position at every GNSS epoch)."""
    sl, cl = math.sin(lat_rad), math.cos(lat_rad)
    r_n = A_M / math.sqrt(1.0 - E2 * sl * sl)
    x = (r_n + h_m) * cl * math.cos(lon_rad)
    y = (r_n + h_m) * cl * math.sin(lon_rad)
    return np.array([x, y, (r_n * (1.0 - E2) + h_m) * sl])


def ecef_to_llh(xyz: np.ndarray) -> np.ndarray:
    """ECEF metres -> geodetic (lat_rad, lon_rad, h_m), iterative (converges to < 1e-12 rad)."""
    xyz = np.asarray(xyz, dtype=float)
    x, y, z = xyz[..., 0], xyz[..., 1], xyz[..., 2]
    lon = np.arctan2(y, x)
    p = np.hypot(x, y)
    lat = np.arctan2(z, p * (1.0 - E2))
    h = np.zeros_like(p)
    for _ in range(8):
        sl = np.sin(lat)
        r_n = A_M / np.sqrt(1.0 - E2 * sl * sl)
        h = np.where(np.abs(np.cos(lat)) > 1e-9, p / np.cos(lat) - r_n, np.abs(z) - B_M)
        lat = np.arctan2(z, p * (1.0 - E2 * r_n / (r_n + h)))
    return np.stack([lat, lon, h], axis=-1)


def mat_en(lat_rad: float, lon_rad: float) -> np.ndarray:
    """Rotation ENU -> ECEF (columns are the east, north, up unit vectors in ECEF)."""
    sl, cl = math.sin(lat_rad), math.cos(lat_rad)
    so, co = math.sin(lon_rad), math.cos(lon_rad)
    return np.array([[-so, -sl * co, cl * co], [co, -sl * so, cl * so], [0.0, cl, sl]])


def ecef_to_enu(xyz: np.ndarray, ref_llh: np.ndarray) -> np.ndarray:
    """ECEF points (..., 3) to ENU metres about a reference geodetic position."""
    d = np.asarray(xyz, dtype=float) - llh_to_ecef(ref_llh)
    return d @ mat_en(ref_llh[0], ref_llh[1])


def enu_to_ecef(enu: np.ndarray, ref_llh: np.ndarray) -> np.ndarray:
    return np.asarray(enu, dtype=float) @ mat_en(ref_llh[0], ref_llh[1]).T + llh_to_ecef(ref_llh)


def llh_delta_to_enu_m(dllh: np.ndarray, lat_rad: float, h_m: float) -> np.ndarray:
    """Small geodetic differences (dlat_rad, dlon_rad, dh_m), shape (..., 3) -> ENU metres."""
    r_m, r_n = radii(lat_rad)
    d = np.asarray(dllh, dtype=float)
    return np.stack(
        [d[..., 1] * (r_n + h_m) * math.cos(lat_rad), d[..., 0] * (r_m + h_m), d[..., 2]], axis=-1
    )


def enu_m_to_llh_delta(enu: np.ndarray, lat_rad: float, h_m: float) -> np.ndarray:
    r_m, r_n = radii(lat_rad)
    e = np.asarray(enu, dtype=float)
    return np.stack(
        [e[..., 1] / (r_m + h_m), e[..., 0] / ((r_n + h_m) * math.cos(lat_rad)), e[..., 2]], axis=-1
    )


# --- rotations --------------------------------------------------------------------------------------
def skew(v: np.ndarray) -> np.ndarray:
    """Cross-product matrix [v x] such that skew(a) @ b = a x b."""
    x, y, z = float(v[0]), float(v[1]), float(v[2])
    return np.array([[0.0, -z, y], [z, 0.0, -x], [-y, x, 0.0]])


def rpy_to_mat_nb(rpy_rad: np.ndarray) -> np.ndarray:
    """Roll, pitch, yaw (rad; ENU/RFU, yaw west-positive) -> mat_nb = Rz(yaw) Rx(pitch) Ry(roll)."""
    r, p, y = (float(a) for a in rpy_rad)
    sr, cr, sp, cp, sy, cy = math.sin(r), math.cos(r), math.sin(p), math.cos(p), math.sin(y), math.cos(y)
    return np.array(
        [
            [cy * cr - sy * sp * sr, -sy * cp, cy * sr + sy * sp * cr],
            [sy * cr + cy * sp * sr, cy * cp, sy * sr - cy * sp * cr],
            [-cp * sr, sp, cp * cr],
        ]
    )


def mat_nb_to_rpy(mat_nb: np.ndarray) -> np.ndarray:
    """Inverse of :func:`rpy_to_mat_nb`; pitch in [-90, 90] deg."""
    c = mat_nb
    pitch = math.asin(max(-1.0, min(1.0, c[2, 1])))
    roll = math.atan2(-c[2, 0], c[2, 2])
    yaw = math.atan2(-c[0, 1], c[1, 1])
    return np.array([roll, pitch, yaw])


def heading_deg_from_yaw(yaw_rad: float) -> float:
    """Heading clockwise from north (deg, [0, 360)) from the west-positive yaw."""
    return (-math.degrees(yaw_rad)) % 360.0


def yaw_from_heading_deg(heading_deg: float) -> float:
    y = -math.radians(heading_deg)
    return (y + math.pi) % (2.0 * math.pi) - math.pi


def rpy_msg_deg(rpy_rad: np.ndarray) -> list[float]:
    """Message form of attitude: [roll_deg, pitch_deg, heading_deg (clockwise from north)]."""
    return [math.degrees(rpy_rad[0]), math.degrees(rpy_rad[1]), heading_deg_from_yaw(rpy_rad[2])]


def rpy_from_msg_deg(rpy_deg) -> np.ndarray:
    return np.array([math.radians(rpy_deg[0]), math.radians(rpy_deg[1]), yaw_from_heading_deg(rpy_deg[2])])


def quat_mul(p: np.ndarray, q: np.ndarray) -> np.ndarray:
    """Hamilton product p (x) q, scalar first."""
    return np.array(quat_mul_f(p, q))


def quat_mul_f(p, q) -> tuple[float, float, float, float]:
    """:func:`quat_mul` of any two 4-sequences, a tuple (the INS's major update on floats)."""
    pw, px, py, pz = p
    qw, qx, qy, qz = q
    return (
        pw * qw - px * qx - py * qy - pz * qz,
        pw * qx + px * qw + py * qz - pz * qy,
        pw * qy - px * qz + py * qw + pz * qx,
        pw * qz + px * qy - py * qx + pz * qw,
    )


def rotvec_to_quat(rv: np.ndarray) -> np.ndarray:
    """Rotation vector (rad) -> unit quaternion, series-safe near zero."""
    return np.array(rotvec_to_quat_f(float(rv[0]), float(rv[1]), float(rv[2])))


def rotvec_to_quat_f(x: float, y: float, z: float) -> tuple[float, float, float, float]:
    """:func:`rotvec_to_quat` of a rotation vector's components, a tuple."""
    a2 = x * x + y * y + z * z
    if a2 < 1e-16:
        # cos(a/2) and sin(a/2)/a to fourth order
        c = 1.0 - a2 / 8.0 + a2 * a2 / 384.0
        s = 0.5 - a2 / 48.0 + a2 * a2 / 3840.0
    else:
        a = math.sqrt(a2)
        c = math.cos(0.5 * a)
        s = math.sin(0.5 * a) / a
    return (c, s * x, s * y, s * z)


def quat_to_rotvec(q: np.ndarray) -> np.ndarray:
    q = q if q[0] >= 0 else -q
    v = q[1:]
    n = float(np.linalg.norm(v))
    if n < 1e-15:
        return 2.0 * v
    return 2.0 * math.atan2(n, q[0]) / n * v


def quat_to_mat(q: np.ndarray) -> np.ndarray:
    # the components as Python floats (the same IEEE operations as on numpy's float64 scalars, at
    # a third of their cost: every major update and fix epoch reads the matrix)
    f64 = isinstance(q, np.ndarray) and q.dtype == np.float64
    return np.array(quat_to_mat_f(*(q.tolist() if f64 else q)))


def quat_to_mat_f(w: float, x: float, y: float, z: float) -> tuple[tuple[float, float, float], ...]:
    """:func:`quat_to_mat` of a quaternion's components, as rows of floats."""
    return (
        (1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)),
        (2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)),
        (2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)),
    )


def mat_to_quat(m: np.ndarray) -> np.ndarray:
    """Rotation matrix -> unit quaternion (Shepperd's method), scalar first, w >= 0."""
    tr = m[0, 0] + m[1, 1] + m[2, 2]
    if tr > 0:
        s = 2.0 * math.sqrt(tr + 1.0)
        q = np.array([0.25 * s, (m[2, 1] - m[1, 2]) / s, (m[0, 2] - m[2, 0]) / s, (m[1, 0] - m[0, 1]) / s])
    elif m[0, 0] > m[1, 1] and m[0, 0] > m[2, 2]:
        s = 2.0 * math.sqrt(1.0 + m[0, 0] - m[1, 1] - m[2, 2])
        q = np.array([(m[2, 1] - m[1, 2]) / s, 0.25 * s, (m[0, 1] + m[1, 0]) / s, (m[0, 2] + m[2, 0]) / s])
    elif m[1, 1] > m[2, 2]:
        s = 2.0 * math.sqrt(1.0 + m[1, 1] - m[0, 0] - m[2, 2])
        q = np.array([(m[0, 2] - m[2, 0]) / s, (m[0, 1] + m[1, 0]) / s, 0.25 * s, (m[1, 2] + m[2, 1]) / s])
    else:
        s = 2.0 * math.sqrt(1.0 + m[2, 2] - m[0, 0] - m[1, 1])
        q = np.array([(m[1, 0] - m[0, 1]) / s, (m[0, 2] + m[2, 0]) / s, (m[1, 2] + m[2, 1]) / s, 0.25 * s])
    q = q / np.linalg.norm(q)
    return q if q[0] >= 0 else -q


def wrap_pi(a):
    return (np.asarray(a) + np.pi) % (2.0 * np.pi) - np.pi


def wrap_pi_f(a: float) -> float:
    """:func:`wrap_pi` of one float: Python's float modulo is numpy's (fmod, then the divisor's
    sign), so the same value without three numpy scalar operations (every fix epoch)."""
    return (a + math.pi) % (2.0 * math.pi) - math.pi
