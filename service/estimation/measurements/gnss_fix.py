"""GNSS position + velocity fix (loosely coupled), antenna at the IMU.

z = [p_INS - p_fix (ENU m), v_INS - v_fix (ENU m/s)], H = [I 0 0 0 0; 0 I 0 0 0],
R = diag(position and velocity variances of the fix), each sigma at least ``MIN_POS_STD_M`` /
``MIN_VEL_STD_MPS`` (below any receiver's real precision, RTK included). Late aiding
(``ctx.dt_late_s`` > 0, the fix older than the INS time): the fix position is carried forward
with its own velocity.
"""

from __future__ import annotations

import math

import numpy as np

from service import earth
from service.estimation.measurements.base import Measurement, ModelContext, floored_variances
from service.ins import error_model as em
from service.ins.mechanisation import NavState
from service.messages import GnssFix

LABELS = ("pos_e", "pos_n", "pos_u", "vel_e", "vel_n", "vel_u")
MIN_POS_STD_M = 0.005
MIN_VEL_STD_MPS = 0.001


class GnssFixModel:
    kind = "gnss_fix"
    private_states = ()

    def __call__(self, nav: NavState, msg: GnssFix, ctx: ModelContext) -> Measurement:
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
            - vel * ctx.dt_late_s
        )
        z = np.concatenate([dp, nav.vel_enu_mps - vel])
        H = np.zeros((6, ctx.n_states))
        H[0:3, em.POS] = np.eye(3)
        H[3:6, em.VEL] = np.eye(3)
        var, floored = floored_variances(
            np.concatenate([msg.pos_std_enu_m, msg.vel_std_enu_mps]),
            np.r_[np.full(3, MIN_POS_STD_M), np.full(3, MIN_VEL_STD_MPS)],
        )
        return Measurement(z, H, np.diag(var), LABELS, floored=floored)
