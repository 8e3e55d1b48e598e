"""Star-tracker attitude: z = phi with C_ins = (I - [phi x]) C_star, H = [0 0 I 0 0].

The tracker's roll/pitch/heading sigmas are applied per navigation axis (small-angle reading),
each at least ``MIN_ATT_STD_RAD`` (0.1 arcsec, below any star tracker's real precision).

Late aiding (``ctx.dt_late_s`` = dt > 0): the INS attitude is taken back to the measurement's
time, ``C_nb(t - dt) = exp(+[w_in dt x]) C_nb(t) exp(-[w_ib dt x])`` with the INS's last body rate
``ctx.wib_b_rps`` and the navigation frame's rate (earth rate plus transport rate) at the INS
state. (Until 2026-12-01 a late attitude was compared with the INS's at the later time: 0.1 s
late on the demo aircraft, the yaw error went from 0.7 to 1.3 arcsec RMS.)
"""

from __future__ import annotations

import numpy as np

from fednav.service import earth
from fednav.service.estimation.measurements.base import Measurement, ModelContext, floored_variances
from fednav.service.ins import error_model as em
from fednav.service.ins.mechanisation import NavState
from fednav.service.messages import StarAttitude

LABELS = ("roll", "pitch", "yaw")
MIN_ATT_STD_RAD = 0.1 * earth.ARCSEC


class StarAttitudeModel:
    kind = "star"
    private_states = ()

    def __call__(self, nav: NavState, msg: StarAttitude, ctx: ModelContext) -> Measurement:
        c_star = earth.rpy_to_mat_nb(earth.rpy_from_msg_deg(msg.rpy_deg))
        c_ins = nav.mat_nb
        dt = ctx.dt_late_s
        if dt > 0.0:  # late: the INS attitude at the measurement's time (module docstring)
            w_in = earth.earth_rate_n(nav.lat_rad) + earth.transport_rate_n(
                nav.lat_rad, nav.h_m, np.asarray(nav.vel_enu_mps, dtype=float)
            )
            body = earth.quat_to_mat(earth.rotvec_to_quat(-np.asarray(ctx.wib_b_rps, dtype=float) * dt))
            frame = earth.quat_to_mat(earth.rotvec_to_quat(w_in * dt))
            c_ins = frame @ c_ins @ body
        # I - C_ins C_star' = [phi x]  ->  phi = rotation vector of C_star C_ins'
        z = earth.quat_to_rotvec(earth.mat_to_quat(c_star @ c_ins.T))
        H = np.zeros((3, ctx.n_states))
        H[:, em.ATT] = np.eye(3)
        var, floored = floored_variances(np.radians(msg.rpy_std_deg), MIN_ATT_STD_RAD)
        return Measurement(z, H, np.diag(var), LABELS, floored=floored)
