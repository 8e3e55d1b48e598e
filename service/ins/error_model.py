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

Optional IMU scale factors (a filter's private block :data:`SCALE_BLOCK`, 3 gyro + 3 accel,
dimensionless; ``service/estimation/ins_filter.py`` builds and feeds it back). The IMU measures
w~ = (I + diag(s_g)) w + b_g and f~ = (I + diag(s_a)) f + b_a; the INS uses
w = (w~ - b_g^) / (1 + s_g^) (per axis, likewise f). With the private blocks' closed-loop
convention the states are ds = s^ - s (computed minus true), so the computed rate's error is
eps - diag(w_b) ds_g and the specific force's nab - diag(f_b) ds_a (first order):
    phi' += C_nb diag(w_b) ds_g,    dv' -= C_nb diag(f_b) ds_a          (:func:`scale_coupling`)

Discretisation over T (accurate for ||F|| T << 1, i.e. any T up to a few seconds here, so IMU
rates of 1-200 Hz or covariance steps of 0.005-1 s all qualify):
    Phi = I + F T + (F T)^2/2 + (F T)^3/6 + (F T)^4/24
    Qd  = sum_k A_k T^(k+1)/(k+1)!, A_0 = Qc, A_(k+1) = F A_k + A_k F', k < 5   (Van Loan series)
"""

from __future__ import annotations

import functools
import math
from dataclasses import dataclass

import numpy as np

from fednav.service import earth

N_STATES = 15
POS, VEL, ATT, GYRO, ACC = slice(0, 3), slice(3, 6), slice(6, 9), slice(9, 12), slice(12, 15)
#: the navigation errors (position, velocity, attitude): what solutions, evaluation and the
#: recording report; ``P[NAV, NAV]`` is their covariance
NAV = slice(0, 9)
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
class NavErrorName:
    """The public names of one navigation error (one row of :data:`NAV_ERRORS`).

    ``state``: the error-state label above; ``report``: ``fednav-sim eval`` JSON and the paper
    tables (the papers' dLat/dLon/dh read as north/east/up metres); ``recording``: the Rerun
    entities ``error/<name>`` and ``bound/<name>``; ``std``: the Solution sigma entity
    ``solution/std/<name>`` (attitude sigmas are roll/pitch/heading there); ``per_si``: reported
    units per SI unit (metres, m/s; attitude in arcsec).
    """

    state: str
    report: str
    recording: str
    std: str
    per_si: float


#: the private block of IMU scale-factor errors (module docstring): its name and state names
SCALE_BLOCK = "imu_scale"
SCALE_NAMES = tuple(f"{s}_scale_{a}" for s in ("gyro", "accel") for a in "xyz")


_ARCSEC_PER_RAD = 180.0 * 3600.0 / math.pi
#: The one table of names of the 9 navigation errors, in error-state order.
NAV_ERRORS = (
    NavErrorName("dp_e", "lon_m", "east_m", "pos_e_m", 1.0),
    NavErrorName("dp_n", "lat_m", "north_m", "pos_n_m", 1.0),
    NavErrorName("dp_u", "h_m", "up_m", "pos_u_m", 1.0),
    NavErrorName("dv_e", "ve_mps", "ve_mps", "ve_mps", 1.0),
    NavErrorName("dv_n", "vn_mps", "vn_mps", "vn_mps", 1.0),
    NavErrorName("dv_u", "vu_mps", "vu_mps", "vu_mps", 1.0),
    NavErrorName("phi_e", "phi_e_arcsec", "phi_e_arcsec", "roll_deg", _ARCSEC_PER_RAD),
    NavErrorName("phi_n", "phi_n_arcsec", "phi_n_arcsec", "pitch_deg", _ARCSEC_PER_RAD),
    NavErrorName("phi_u", "phi_u_arcsec", "phi_u_arcsec", "heading_deg", _ARCSEC_PER_RAD),
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


#: the non-zero entries of F (:func:`continuous_F`) in the order of its values list: flat indices
#: for one ``ndarray.put`` (50 item assignments cost ~3x as much, at every major update)
_F_ENTRIES = (
    [(0, 1), (0, 2), (1, 2), (0, 3), (1, 4), (2, 5)]
    + [(3, 1), (4, 1), (5, 1), (3, 2), (4, 2), (5, 2)]
    + [(3, 3), (3, 4), (3, 5), (4, 3), (4, 4), (4, 5), (5, 3), (5, 4)]
    + [(3, 7), (3, 8), (4, 6), (4, 8), (5, 6), (5, 7)]
    + [(3 + i, 12 + j) for i in range(3) for j in range(3)]
    + [(6, 2), (7, 1), (7, 2), (8, 1), (8, 2)]
    + [(6, 4), (7, 3), (8, 3)]
    + [(6, 7), (6, 8), (7, 6), (7, 8), (8, 6), (8, 7)]
    + [(6 + i, 9 + j) for i in range(3) for j in range(3)]
)
_F_INDEX = np.array([i * N_STATES + j for i, j in _F_ENTRIES], dtype=np.intp)
_F_INDEX.setflags(write=False)


def continuous_F(
    lat_rad: float, h_m: float, vel_enu_mps: np.ndarray, mat_nb: np.ndarray, f_n_mps2: np.ndarray
) -> np.ndarray:
    """Continuous-time error dynamics matrix F (15x15) in the state order of this module.

    The PSINS ``etm`` blocks (position in dL, dlon, dh) converted to ENU metres with the frozen
    scaling dp = D dllh, written out element by element (this runs at every major update of every
    pipeline; tests/test_error_model.py checks it against the block-matrix form), the entries
    placed by one ``put`` (:data:`_F_ENTRIES`).
    """
    sl, cl = math.sin(lat_rad), math.cos(lat_rad)
    tl, secl = sl / cl, 1.0 / cl
    r_m, r_n = earth.radii(lat_rad)
    rmh, rnh = r_m + h_m, r_n + h_m
    ve, vn, vu = np.asarray(vel_enu_mps, dtype=float).tolist()
    fe, fn, fu = np.asarray(f_n_mps2, dtype=float).tolist()
    # (C_nb as an array, or as rows of floats: earth.quat_to_mat_f)
    rows = mat_nb.tolist() if isinstance(mat_nb, np.ndarray) else mat_nb
    (m00, m01, m02), (m10, m11, m12), (m20, m21, m22) = rows
    W = earth.OMEGA_IE_RPS
    # velocity <- position: Avn (2 Mp1 + Mp2) D^-1 plus the normal-gravity gradient
    c1, c2 = -2.0 * W * sl, 2.0 * W * cl + ve * secl * secl / rnh  # column dL
    h0, h1, h2 = vn / rmh**2, -ve / rnh**2, -ve * tl / rnh**2  # column dh
    g_lat = earth.G_EQUATOR_MPS2 * (5.27094e-3 * 2.0 * sl * cl + 2.32718e-5 * 4.0 * sl * sl * sl * cl)
    # velocity <- velocity: Avn Mav - [(2 w_ie + w_en) x]
    a0, a1, a2 = -vn / rmh, 2.0 * W * cl + ve / rnh, 2.0 * W * sl + ve * tl / rnh
    # attitude <- attitude: -[w_in x]
    w0, w1, w2 = -vn / rmh, W * cl + ve / rnh, W * sl + ve * tl / rnh
    values = [
        # position <- position, velocity
        ve * tl / rmh, -ve / rnh, -vn / rmh, 1.0, 1.0, 1.0,
        # velocity <- position
        (-vu * c1 + vn * c2) / rmh, (-ve * c2) / rmh, (ve * c1 - g_lat) / rmh,
        -vu * h1 + vn * h2, vu * h0 - ve * h2, -vn * h0 + ve * h1 + 3.086e-6,
        # velocity <- velocity
        (vn * tl - vu) / rnh, a2, -a1, -ve * tl / rnh - a2, -vu / rmh, a0, ve / rnh + a1, vn / rmh - a0,
        # velocity <- attitude: [f^n x]
        -fu, fn, fu, -fe, -fn, fe,
        # velocity <- accel bias: C_nb
        m00, m01, m02, m10, m11, m12, m20, m21, m22,
        # attitude <- position: Map D^-1
        vn / rmh**2, -W * sl / rmh, -ve / rnh**2, (W * cl + ve * secl * secl / rnh) / rmh, -ve * tl / rnh**2,
        # attitude <- velocity: Mav
        -1.0 / rmh, 1.0 / rnh, tl / rnh,
        # attitude <- attitude
        w2, -w1, -w2, w0, w1, -w0,
        # attitude <- gyro bias: -C_nb
        -m00, -m01, -m02, -m10, -m11, -m12, -m20, -m21, -m22,
    ]  # fmt: skip
    F = np.zeros((N_STATES, N_STATES))
    F.put(_F_INDEX, values)
    return F


def scale_coupling(mat_nb: np.ndarray, f_b_mps2: np.ndarray, w_b_rps: np.ndarray) -> np.ndarray:
    """Columns of F (15 x 6) for the scale-factor errors [ds_g, ds_a] (computed minus true):
    attitude <- gyro scale C_nb diag(w_b), velocity <- accel scale -C_nb diag(f_b)."""
    G = np.zeros((N_STATES, 6))
    G[ATT, 0:3] = mat_nb * np.asarray(w_b_rps, dtype=float)[None, :]
    G[VEL, 3:6] = -mat_nb * np.asarray(f_b_mps2, dtype=float)[None, :]
    return G


def continuous_Q(noise: ImuNoise, mat_nb: np.ndarray | None = None) -> np.ndarray:
    """Continuous process noise spectral density Qc = G q G' (read-only, cached per noise model).

    The sensor noises are isotropic, so C_nb (s^2 I) C_nb' = s^2 I: Qc does not depend on the
    attitude (``mat_nb`` is accepted for interface symmetry and ignored).
    """
    return _qc(noise)


@functools.lru_cache(maxsize=64)
def _qc(noise: ImuNoise) -> np.ndarray:
    d = np.zeros(N_STATES)
    d[VEL] = noise.vrw**2
    d[ATT] = noise.arw**2
    d[GYRO] = noise.gyro_bias_rw**2
    d[ACC] = noise.accel_bias_rw**2
    Q = np.diag(d)
    Q.setflags(write=False)
    return Q


_I15 = np.eye(N_STATES)
_I15.setflags(write=False)


def discretise(F: np.ndarray, Qc: np.ndarray, T: float) -> tuple[np.ndarray, np.ndarray]:
    """Transition matrix (fourth-order series) and discrete process noise (Van Loan series) over T.

    The fourth-order term matters for small entries built from cancelling paths (e.g. height
    error from gyro bias: 0.1 % at T = 0.1 s with a third-order series).
    """
    # the same operations in the same order as the expressions in the comments, into buffers
    # (numpy's out=): fewer 15 x 15 allocations, the same values (every major update)
    FT = F * T
    FT2 = FT @ FT
    # Phi = ((I + FT) + FT2 / 2) + FT2 @ (FT / 6 + FT2 / 24)
    Phi = (_I15 if F.shape[0] == N_STATES else np.eye(F.shape[0])) + FT
    tmp = FT2 / 2.0
    Phi += tmp
    poly = FT / 6.0
    np.divide(FT2, 24.0, out=tmp)
    poly += tmp
    np.matmul(FT2, poly, out=tmp)
    Phi += tmp
    # Qd = sum_k A_k T^(k+1)/(k+1)!, A_0 = Qc, A_(k+1) = F A_k + A_k F' (the Lyapunov series of
    # Van Loan's integral). Five terms: position variance driven by attitude noise through
    # gravity enters at T^5 (g^2 arw^2 T^5/20), 0.14 % of it at T = 0.1 s with three terms.
    # Per term: FA = F @ A; A = FA + FA'; Qd = Qd + A * coef.
    Qd = Qc * T
    coef = T
    FA = np.matmul(F, Qc)
    A = FA + FA.T
    for k in range(1, 5):
        if k > 1:
            np.matmul(F, A, out=FA)
            np.add(FA, FA.T, out=A)
        coef *= T / (k + 1)
        np.multiply(A, coef, out=tmp)
        Qd += tmp
    Qd = 0.5 * (Qd + Qd.T)
    return Phi, Qd
