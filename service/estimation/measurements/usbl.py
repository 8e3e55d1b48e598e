"""USBL (ultra-short baseline) fix: the body-frame vector from the vehicle's acoustic array to a
transponder at a known earth-fixed position (Xu et al. 2017, "INS/USBL/DVL information fusion and
fault-tolerant verification for underwater vehicles", eq (9)-(25)).

Measurement (eq 12): B_r = R' (s - p) + n_r, R = C_b^e; here in the local ENU frame at the INS
position, with the array at lever arm l_b from the IMU (body frame, metres):

    r_b = C_nb' d_n - l_b,        d_n = C_en' (s_e - p_e)   (transponder minus IMU, ENU metres)

INS-predicted minus measured, linearised about the INS (computed C_nb = (I - [phi x]) C_nb,
computed position p + dp):

    z = r_b(INS) - r_b(USBL) = -C_nb' (I - [d_n x] M) dp - C_nb' [d_n x] phi + n_r       eq (21)-(22)

i.e. H = [-C_nb' (I - [d_n x] M), 0, -C_nb' [d_n x], 0, 0]: eq (24)-(25) with the position
error in ENU metres instead of (dL, dlon, dh) (A and C_e^n are absorbed), -[B_r x] R' phi =
-R' [d x] phi since B_r = R' d, and the sign of the whole row ours (z is INS minus sensor).
M dp is the turn of the local ENU frame when the position moves by dp (a term the paper's ECEF
form leaves inside its attitude error; ~4e-4 per metre at 2.6 km, checked by finite differences).

Noise (the paper's USBL error, Table 2 and section 6): a floor of ``base_std_m`` on every axis,
``range_fraction`` of the slant range along the line of sight and ``angle_std_deg`` of bearing
across it:

    R = base^2 I + (range_fraction l)^2 u u' + (l angle)^2 (I - u u'),   u = r / l, l = |r|

evaluated at the INS-predicted vector (so a corrupted measurement cannot shrink its own noise).
Without noise parameters the message's per-axis ``rel_std_m`` is used (diagonal R).

The transponder position comes from the pipeline's configuration when given (the surveyed
position), else from the message.
"""

from __future__ import annotations

import math

import numpy as np

from fednav.service import earth
from fednav.service.estimation.measurements.base import Measurement, ModelContext
from fednav.service.ins import error_model as em
from fednav.service.ins.mechanisation import NavState
from fednav.service.messages import UsblFix

LABELS = ("r_x", "r_y", "r_z")


def usbl_noise(
    r_b_m: np.ndarray, base_std_m: float, range_fraction: float, angle_std_deg: float
) -> np.ndarray:
    """R (3, 3) of a USBL vector r_b (see module docstring)."""
    r = np.asarray(r_b_m, dtype=float)
    slant = float(np.linalg.norm(r))
    R = np.eye(3) * base_std_m**2
    if slant > 0.0:
        u = r / slant
        uu = np.outer(u, u)
        R += (range_fraction * slant) ** 2 * uu + (slant * math.radians(angle_std_deg)) ** 2 * (
            np.eye(3) - uu
        )
    return R


def predicted_vector(
    nav: NavState, transponder_ecef_m: np.ndarray, lever_arm_b_m: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """(r_b, d_n): the INS-predicted body vector array -> transponder and the ENU vector
    IMU -> transponder at the INS position (eq 16)."""
    p_e = earth.llh_to_ecef(np.array([nav.lat_rad, nav.lon_rad, nav.h_m]))
    d_n = earth.mat_en(nav.lat_rad, nav.lon_rad).T @ (transponder_ecef_m - p_e)
    r_b = nav.mat_nb.T @ d_n - lever_arm_b_m
    return r_b, d_n


class UsblModel:
    """USBL body-frame vector to a known transponder (module docstring)."""

    kind = "usbl"
    private_states = ()

    def __init__(
        self,
        transponder_llh_deg_m: tuple[float, float, float] | None = None,
        lever_arm_b_m: tuple[float, float, float] = (0.0, 0.0, 0.0),
        base_std_m: float | None = None,
        range_fraction: float = 0.0,
        angle_std_deg: float = 0.0,
    ):
        self.transponder = transponder_llh_deg_m
        self._s_e = None if transponder_llh_deg_m is None else self._ecef(*transponder_llh_deg_m)
        self.lever_arm_b_m = np.asarray(lever_arm_b_m, dtype=float)
        self.base_std_m = base_std_m
        self.range_fraction = float(range_fraction)
        self.angle_std_deg = float(angle_std_deg)

    @staticmethod
    def _ecef(lat_deg: float, lon_deg: float, h_m: float) -> np.ndarray:
        return earth.llh_to_ecef(np.array([math.radians(lat_deg), math.radians(lon_deg), h_m]))

    def transponder_ecef(self, msg: UsblFix) -> np.ndarray:
        if self._s_e is not None:
            return self._s_e
        return self._ecef(msg.transponder_lat_deg, msg.transponder_lon_deg, msg.transponder_height_m)

    def __call__(self, nav: NavState, msg: UsblFix, ctx: ModelContext) -> Measurement | None:
        r_hat, d_n = predicted_vector(nav, self.transponder_ecef(msg), self.lever_arm_b_m)
        if ctx.dt_late_s > 0.0:
            # late fix: the vector changed by -C_nb' v dt since it was measured (vehicle moved)
            r_hat = r_hat + nav.mat_nb.T @ (np.asarray(nav.vel_enu_mps) * ctx.dt_late_s)
        z = r_hat - np.asarray(msg.rel_b_m, dtype=float)
        if not np.all(np.isfinite(z)):
            return None
        c_bn = nav.mat_nb.T
        H = np.zeros((3, ctx.n_states))
        # eq (24): position block (ENU metres), plus the turn of the local ENU frame with the
        # position (d_n is resolved at the INS position): d_n(p + dp) = (I - [dtheta x]) (d_n - dp),
        # dtheta = M dp -> -C_nb' dp + C_nb' [d_n x] M dp (4e-4 per metre at 2.6 km: kept exact)
        r_m, r_n = earth.radii(nav.lat_rad)
        M = np.zeros((3, 3))
        M[0, 1] = -1.0 / (r_m + nav.h_m)
        M[1, 0] = 1.0 / (r_n + nav.h_m)
        M[2, 0] = math.tan(nav.lat_rad) / (r_n + nav.h_m)
        skew_d = earth.skew(d_n)
        H[:, em.POS] = -c_bn + c_bn @ skew_d @ M
        H[:, em.ATT] = -c_bn @ skew_d  # eq (25): -[B_r x] R' phi = -R' [d x] phi
        if self.base_std_m is None:
            R = np.diag(np.square(msg.rel_std_m))
        else:
            R = usbl_noise(r_hat, self.base_std_m, self.range_fraction, self.angle_std_deg)
        return Measurement(z, H, R, LABELS)
