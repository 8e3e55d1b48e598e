"""15-state INS error model (phi-angle form, ENU) and its discretisation.

State order (the papers' layout, seed 000):
    x = [dp_e, dp_n, dp_u, dv_e, dv_n, dv_u, phi_e, phi_n, phi_u, eps_x, eps_y, eps_z, nab_x, nab_y, nab_z]
    dp   position error, ENU metres (computed minus true). The papers use (dLat, dLon, dh) in
         radians; metres are the same model under the constant scaling diag((R_N+h)cos L, R_M+h, 1)
         and are far better conditioned numerically. Eval reports lat_m/lon_m/h_m from it.
    dv   velocity error, ENU m/s.
    phi  platform misalignment, rad: C_nb(computed) = (I - [phi x]) C_nb(true).
    eps  gyro bias residual (true minus estimated), body rad/s.
    nab  accelerometer bias residual, body m/s^2.

Continuous dynamics (Yan Gongmin's PSINS ``etm``; Groves 2nd ed. 14.2):
    phi'  = -w_in x phi + d(w_in) - C_nb eps
    dv'   = f^n x phi + C_nb nab - (2 w_ie + w_en) x dv + v x (2 d(w_ie) + d(w_en)) + dg
    dL'   = dv_n/(R_M+h) - v_n dh/(R_M+h)^2        (then converted to metres)
    dlon' = dv_e sec L/(R_N+h) + v_e sec L tan L dL/(R_N+h) - v_e sec L dh/(R_N+h)^2
    dh'   = dv_u
Biases: random constants plus an optional random walk (bias instability as its long-term drift).

Discretisation over T (accurate for ||F|| T << 1, i.e. any T up to a few seconds here, so IMU
rates of 1-200 Hz or covariance steps of 0.005-1 s all qualify):
    Phi = I + F T + (F T)^2/2 + (F T)^3/6
    Qd  = Qc T + (F Qc + Qc F') T^2/2 + (F^2 Qc + 2 F Qc F' + Qc F'^2) T^3/6   (Van Loan series)
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from service import earth

N_STATES = 15
POS, VEL, ATT, GYRO, ACC = slice(0, 3), slice(3, 6), slice(6, 9), slice(9, 12), slice(12, 15)
STATE_LABELS = (
    "dp_e",
    "dp_n",
    "dp_u",
    "dv_e",
    "dv_n",
    "dv_u",
    "phi_e",
    "phi_n",
    "phi_u",
    "eps_x",
    "eps_y",
    "eps_z",
    "nab_x",
    "nab_y",
    "nab_z",
)


@dataclass(frozen=True)
class ImuNoise:
    """Continuous-time IMU noise densities used by the filter's process model (SI units).

    arw: angle random walk, rad/sqrt(s); vrw: velocity random walk, m/s/sqrt(s);
    gyro_bias_rw: gyro bias random walk, rad/s/sqrt(s); accel_bias_rw: m/s^2/sqrt(s).
    """

    arw: float
    vrw: float
    gyro_bias_rw: float = 0.0
    accel_bias_rw: float = 0.0


def continuous_F(
    lat_rad: float, h_m: float, vel_enu_mps: np.ndarray, mat_nb: np.ndarray, f_n_mps2: np.ndarray
) -> np.ndarray:
    """Continuous-time error dynamics matrix F (15x15) in the state order of this module."""
    sl, cl = math.sin(lat_rad), math.cos(lat_rad)
    tl, secl = sl / cl, 1.0 / cl
    r_m, r_n = earth.radii(lat_rad)
    rmh, rnh = r_m + h_m, r_n + h_m
    ve, vn, vu = (float(x) for x in vel_enu_mps)
    w = earth.OMEGA_IE_RPS
    wie = np.array([0.0, w * cl, w * sl])
    wen = np.array([-vn / rmh, ve / rnh, ve * tl / rnh])
    win = wie + wen

    # PSINS etm blocks with position states (dL, dlon, dh) in radians
    Mp1 = np.array([[0.0, 0.0, 0.0], [-wie[2], 0.0, 0.0], [wie[1], 0.0, 0.0]])
    Mp2 = np.array(
        [
            [0.0, 0.0, vn / rmh**2],
            [0.0, 0.0, -ve / rnh**2],
            [ve * secl**2 / rnh, 0.0, -ve * tl / rnh**2],
        ]
    )
    Maa = -earth.skew(win)
    Mav = np.array([[0.0, -1.0 / rmh, 0.0], [1.0 / rnh, 0.0, 0.0], [tl / rnh, 0.0, 0.0]])
    Map = Mp1 + Mp2
    Mva = earth.skew(f_n_mps2)
    Avn = earth.skew(vel_enu_mps)
    Mvv = Avn @ Mav - earth.skew(2.0 * wie + wen)
    Mvp = Avn @ (Mp1 + Map)
    # gravity variation with latitude and height (normal gravity gradient)
    g0 = earth.G_EQUATOR_MPS2
    Mvp[2, 0] -= g0 * (5.27094e-3 * 2.0 * sl * cl + 2.32718e-5 * 4.0 * sl * sl * sl * cl)
    Mvp[2, 2] += 3.086e-6
    Mpv = np.array([[0.0, 1.0 / rmh, 0.0], [secl / rnh, 0.0, 0.0], [0.0, 0.0, 1.0]])
    Mpp = np.array(
        [[0.0, 0.0, -vn / rmh**2], [ve * secl * tl / rnh, 0.0, -ve * secl / rnh**2], [0.0, 0.0, 0.0]]
    )

    # Convert position blocks to ENU metres: dp = D dllh, D = [[0, rnh cl, 0], [rmh, 0, 0], [0, 0, 1]]
    D = np.array([[0.0, rnh * cl, 0.0], [rmh, 0.0, 0.0], [0.0, 0.0, 1.0]])
    Di = np.array([[0.0, 1.0 / rmh, 0.0], [1.0 / (rnh * cl), 0.0, 0.0], [0.0, 0.0, 1.0]])

    F = np.zeros((N_STATES, N_STATES))
    F[POS, POS] = D @ Mpp @ Di
    F[POS, VEL] = D @ Mpv
    F[VEL, POS] = Mvp @ Di
    F[VEL, VEL] = Mvv
    F[VEL, ATT] = Mva
    F[VEL, ACC] = mat_nb
    F[ATT, POS] = Map @ Di
    F[ATT, VEL] = Mav
    F[ATT, ATT] = Maa
    F[ATT, GYRO] = -mat_nb
    return F


def continuous_Q(noise: ImuNoise, mat_nb: np.ndarray) -> np.ndarray:
    """Continuous process noise spectral density Qc = G q G' (isotropic sensor noise)."""
    Q = np.zeros((N_STATES, N_STATES))
    Q[VEL, VEL] = noise.vrw**2 * np.eye(3)  # C_nb (s^2 I) C_nb' = s^2 I
    Q[ATT, ATT] = noise.arw**2 * np.eye(3)
    Q[GYRO, GYRO] = noise.gyro_bias_rw**2 * np.eye(3)
    Q[ACC, ACC] = noise.accel_bias_rw**2 * np.eye(3)
    return Q


def discretise(F: np.ndarray, Qc: np.ndarray, T: float) -> tuple[np.ndarray, np.ndarray]:
    """Transition matrix and discrete process noise over T (third-order series, Van Loan)."""
    FT = F * T
    FT2 = FT @ FT
    Phi = np.eye(F.shape[0]) + FT + FT2 / 2.0 + FT2 @ FT / 6.0
    FQ = F @ Qc
    FQFt = FQ @ F.T
    Qd = Qc * T + (FQ + FQ.T) * (T * T / 2.0) + (F @ FQ + 2.0 * FQFt + (F @ FQ).T) * (T**3 / 6.0)
    Qd = 0.5 * (Qd + Qd.T)
    return Phi, Qd
