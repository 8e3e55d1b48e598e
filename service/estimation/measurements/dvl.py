"""DVL (Doppler velocity log): vehicle velocity over ground in the body frame, with an offset and
a scale-factor error per axis as PRIVATE states of the filter that uses it (Xu et al. 2017,
"INS/USBL/DVL information fusion and fault-tolerant verification for underwater vehicles",
section 4, eq (26)-(27): X_DVL = [dV_Dx, dV_Dy, dV_Dz, dK_Dx, dK_Dy, dK_Dz]).

Sensor (per body axis j, DVL at lever arm l_b from the IMU):

    v_dvl_j = (1 + k_j) u_j + b_j + n_j,     u = C_nb' v_n + w_ib x l_b

(the Earth rate's part of w x l is below 1e-4 m/s for any lever arm here and is ignored).
The filter's private block ``dvl`` holds the errors of its references (closed loop, like the
INS): db = b_ref - b, dk = k_ref - k. INS-predicted minus measured, linearised
(computed C_nb = (I - [phi x]) C_nb, computed v_n = v_n + dv):

    z = (1 + k_ref) o (C_nb' v_n(INS) + w x l) + b_ref - v_dvl
      = D C_nb' dv - D C_nb' [v_n x] phi + db + diag(u) dk + n,      D = diag(1 + k_ref)

so H = [0, D C_nb', -D C_nb' [v_n x], 0, 0 | I, diag(u)] (the paper's H_INS and H_DVL of eq 27).
Offset and scale are random constants; ``offset_rw`` and ``scale_rw`` (per sqrt(s)) keep them
adaptable. R = diag(vel_std_mps^2) from the message.
"""

from __future__ import annotations

import numpy as np

from fednav.service import earth
from fednav.service.estimation.measurements.base import Measurement, ModelContext, PrivateStates
from fednav.service.ins import error_model as em
from fednav.service.ins.mechanisation import NavState
from fednav.service.messages import DvlVelocity

LABELS = ("vb_x", "vb_y", "vb_z")
BLOCK = "dvl"
STATE_NAMES = (
    "dvl_offset_x_mps",
    "dvl_offset_y_mps",
    "dvl_offset_z_mps",
    "dvl_scale_x",
    "dvl_scale_y",
    "dvl_scale_z",
)
OFFSET, SCALE = slice(0, 3), slice(3, 6)


class DvlModel:
    """DVL body velocity with private offset (3) and scale-factor (3) states (module docstring)."""

    kind = "dvl"
    # the class declares that it has private states (so plain 15-state filters refuse it);
    # instances carry the configured block
    private_states: tuple[PrivateStates, ...] = (
        PrivateStates(BLOCK, STATE_NAMES, lambda T: (np.eye(6), np.zeros((6, 6))), (0.4,) * 3 + (1e-3,) * 3),
    )

    def __init__(
        self,
        offset_std_mps: float = 0.4,
        scale_std: float = 1e-3,
        offset_rw_mps_per_sqrt_s: float = 1e-5,
        scale_rw_per_sqrt_s: float = 1e-7,
        lever_arm_b_m: tuple[float, float, float] = (0.0, 0.0, 0.0),
    ):
        q = np.array([offset_rw_mps_per_sqrt_s] * 3 + [scale_rw_per_sqrt_s] * 3) ** 2

        def transition(T: float) -> tuple[np.ndarray, np.ndarray]:
            return np.eye(6), np.diag(q * T)  # random constants + random walk

        self.private_states = (
            PrivateStates(BLOCK, STATE_NAMES, transition, (offset_std_mps,) * 3 + (scale_std,) * 3),
        )
        self.lever_arm_b_m = np.asarray(lever_arm_b_m, dtype=float)

    def body_velocity(self, nav: NavState, wib_b_rps: np.ndarray) -> np.ndarray:
        """u = C_nb' v_n + w_ib x l_b: the INS velocity of the DVL in body axes."""
        return nav.mat_nb.T @ np.asarray(nav.vel_enu_mps, dtype=float) + np.cross(
            wib_b_rps, self.lever_arm_b_m
        )

    def __call__(self, nav: NavState, msg: DvlVelocity, ctx: ModelContext) -> Measurement | None:
        cols = ctx.columns.get(BLOCK)
        if cols is None:
            raise ValueError("the DVL model needs a filter with its private 'dvl' block")
        ref = np.asarray(ctx.reference[BLOCK], dtype=float)
        b_ref, k_ref = ref[OFFSET], ref[SCALE]
        u = self.body_velocity(nav, np.asarray(ctx.wib_b_rps, dtype=float))
        z = (1.0 + k_ref) * u + b_ref - np.asarray(msg.vel_b_mps, dtype=float)
        if not np.all(np.isfinite(z)):
            return None
        c_bn = nav.mat_nb.T
        D = np.diag(1.0 + k_ref)
        H = np.zeros((3, ctx.n_states))
        H[:, em.VEL] = D @ c_bn
        H[:, em.ATT] = -D @ c_bn @ earth.skew(np.asarray(nav.vel_enu_mps, dtype=float))
        p = np.arange(cols.start, cols.stop)
        H[:, p[OFFSET]] = np.eye(3)
        H[:, p[SCALE]] = np.diag(u)
        return Measurement(z, H, np.diag(np.square(msg.vel_std_mps)), LABELS)
