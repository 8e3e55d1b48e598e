"""Star-tracker attitude: z = phi with C_ins = (I - [phi x]) C_star, H = [0 0 I 0 0].

The tracker's roll/pitch/heading sigmas are applied per navigation axis (small-angle reading),
each at least ``MIN_ATT_STD_RAD`` (0.1 arcsec, below any star tracker's real precision).
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
        # I - C_ins C_star' = [phi x]  ->  phi = rotation vector of C_star C_ins'
        z = earth.quat_to_rotvec(earth.mat_to_quat(c_star @ nav.mat_nb.T))
        H = np.zeros((3, ctx.n_states))
        H[:, em.ATT] = np.eye(3)
        var, floored = floored_variances(np.radians(msg.rpy_std_deg), MIN_ATT_STD_RAD)
        return Measurement(z, H, np.diag(var), LABELS, floored=floored)
