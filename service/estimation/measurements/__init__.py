"""Measurement models: each answers ``matrices(nav, msg) -> Measurement`` (z, H, R, labels).

z is the INS-predicted quantity minus the sensor's (the papers' "INS minus sensor" form), so
with the error state x (computed minus true) the model is z = H x + v.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from service import earth
from service.ins import error_model as em
from service.ins.mechanisation import NavState
from service.messages import GnssFix, StarAttitude


@dataclass(frozen=True)
class Measurement:
    z: np.ndarray  # (m,)
    H: np.ndarray  # (m, 15)
    R: np.ndarray  # (m, m)
    labels: tuple[str, ...]


GNSS_LABELS = ("pos_e", "pos_n", "pos_u", "vel_e", "vel_n", "vel_u")
STAR_LABELS = ("roll", "pitch", "yaw")


def gnss_fix(nav: NavState, msg: GnssFix, n_states: int = em.N_STATES, dt_late_s: float = 0.0) -> Measurement:
    """Loosely coupled position + velocity (antenna at the IMU).

    ``dt_late_s`` > 0 when the fix is older than the INS time (late aiding inside the tolerance):
    the fix position is carried forward with its own velocity to the INS time.
    """
    lat, lon = math.radians(msg.lat_deg), math.radians(msg.lon_deg)
    r_m, r_n = earth.radii(nav.lat_rad)
    vel = np.asarray(msg.vel_enu_mps, dtype=float)
    dp = (
        np.array(
            [
                (nav.lon_rad - lon) * (r_n + nav.h_m) * math.cos(nav.lat_rad),
                (nav.lat_rad - lat) * (r_m + nav.h_m),
                nav.h_m - msg.height_m,
            ]
        )
        - vel * dt_late_s
    )
    z = np.concatenate([dp, nav.vel_enu_mps - vel])
    H = np.zeros((6, n_states))
    H[0:3, em.POS] = np.eye(3)
    H[3:6, em.VEL] = np.eye(3)
    R = np.diag(np.concatenate([np.square(msg.pos_std_enu_m), np.square(msg.vel_std_enu_mps)]))
    return Measurement(z, H, R, GNSS_LABELS)


def star_attitude(nav: NavState, msg: StarAttitude, n_states: int = em.N_STATES) -> Measurement:
    """Star tracker attitude: z = phi with C_ins = (I - [phi x]) C_star, H = [0 0 I 0 0].

    The tracker's roll/pitch/heading sigmas are applied per nav axis (small-angle reading).
    """
    c_star = earth.rpy_to_mat_nb(earth.rpy_from_msg_deg(msg.rpy_deg))
    c_ins = nav.mat_nb
    # I - C_ins C_star' = [phi x]  ->  phi = rotation vector of C_star C_ins'
    z = earth.quat_to_rotvec(earth.mat_to_quat(c_star @ c_ins.T))
    H = np.zeros((3, n_states))
    H[:, em.ATT] = np.eye(3)
    R = np.diag(np.square(np.radians(msg.rpy_std_deg)))
    return Measurement(z, H, R, STAR_LABELS)
