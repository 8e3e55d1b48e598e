"""GNSS fix (loosely coupled): the rows the fix carries, antenna lever arm, correlated error.

Rows, by the fix's variant (``GnssFix.variant``); z = INS-predicted minus measured:

* position (always): ``pos_e, pos_n, pos_u`` (ENU m), the antenna position
  p_a = p + C_nb l_b (l_b: antenna lever arm from the IMU, body RFU axes, m);
* 3-D velocity: ``vel_e, vel_n, vel_u``, the antenna velocity v_a = v + C_nb (w_ib x l_b);
* speed + course: two rows along and across the reported course,
  ``vel_along = u_a . v_a,h - s`` and ``vel_cross = u_c . v_a,h`` with u_a = (sin c, cos c),
  u_c = (cos c, -sin c) (c the course, clockwise from north); plus ``vel_u`` when the fix has a
  vertical rate. This is the speed/course pair converted to an east/north velocity
  v_f = s u_a with its first-order covariance J diag(s_s^2, s_c^2) J' (J = d v_f / d(s, c) =
  [u_a, s u_c]) rotated into the (u_a, u_c) frame, where it is diagonal:
  R = diag(s_s^2, s^2 s_c^2). Row-independent, so every per-row gate and fault test applies.
  Without a course sigma s_c = s_s / s (isotropic horizontal velocity, R = s_s^2 I); with one,
  the cross-track sigma s s_c is kept at least s_s (at low speed a course says nothing).
  docs/own_data.md derives it.

Lever arm (attitude error convention of ``Ins.correct``: C_nb(computed) = (I - [phi x]) C_nb):
C_nb,c l = C_nb l + [(C_nb l) x] phi, so H_pos,att = [(C_nb l) x]; likewise
H_vel,att = [(C_nb (w x l)) x]. The Earth-rate part of the antenna velocity (w_ie x C_nb l,
< 1e-4 m/s per metre of lever arm) and the gyro-bias error's effect on w x l (10 deg/h gives
5e-5 m/s per metre) are below any receiver's velocity noise and left out (tests check H against
finite differences of this model).

Time-correlated receiver error (``correlated_sigma_enu_m``): a first-order Gauss-Markov
position error b per ENU axis as the private block ``gnss_error`` (Groves 2013, "Principles of
GNSS, Inertial and Multisensor Integrated Navigation Systems", ch. 14: correlated GNSS
position errors as additional states), fix = p_a + b + n, b_k+1 = e^(-T/tau) b_k + w,
Qd = sigma^2 (1 - e^(-2T/tau)). Closed loop like the INS: the model predicts p_a + b_ref and
H_pos,b = I (error db = b_ref - b). The fix's sigma is read as its TOTAL error: the white part
used in R is sqrt(sigma_fix^2 - sigma_gm^2), at least ``MIN_WHITE_FRACTION`` of sigma_fix.

Estimated lever arm (``estimate_lever_arm``; docs/own_data.md "Unknown antenna offset / IMU
scale factors"): the lever arm as the private block ``gnss_lever_arm`` (3 states, body RFU axes,
m; a random constant with an optional random walk ``lever_arm_rw_m_per_sqrt_h``, prior sigma
``lever_arm_std_m`` per axis about the configured ``lever_arm_b_m``). Closed loop like the INS:
the model uses l_ref = lever_arm_b_m + reference (the reference absorbs the block's feedback)
and the error state is dl = l_ref - l (computed minus true), so H_pos,l = C_nb and
H_vel,l = C_nb [w x] (from p_a = p + C_nb l and v_a = v + C_nb (w x l)). The horizontal
components are observed when the heading changes (turns: C_nb l rotates against a position
error that does not; w x l is non-zero only while turning); the vertical one only through
roll/pitch (on a level road it stays near its prior, indistinguishable from a height error).

Sigmas: each at least ``MIN_POS_STD_M`` / ``MIN_VEL_STD_MPS`` (below any receiver's real
precision). Late aiding (``ctx.dt_late_s`` = dt > 0, the fix older than the INS): the fix
position is carried forward to the INS time with its own velocity and the INS's acceleration a
(``ctx.acc_enu_mps2``), ``p_fix + v_fix dt + a dt^2 / 2``, a position-only fix's with the INS's
velocity, ``p_fix + v_ins dt - a dt^2 / 2``; and its velocity is compared with the INS's taken
back to the fix's time, ``v_ins - a dt``. (Until 2026-12-01 a position-only fix was not carried,
and a fix's velocity was compared with the INS's at the later time: fixes 40 ms late, as a
robot's receiver delivers them, took a drive's horizontal error from 0.09 to 0.29 m RMS.)
"""

from __future__ import annotations

import logging
import math
from functools import lru_cache

import numpy as np

from fednav.service import earth
from fednav.service.estimation.measurements.base import (
    Measurement,
    ModelContext,
    PrivateStates,
    floored_variances,
)
from fednav.service.ins import error_model as em
from fednav.service.ins.mechanisation import NavState
from fednav.service.messages import DEFAULT_VERTICAL_RATE_STD_MPS, GnssFix

#: rows of a full fix (also the simulator's fault channels)
LABELS = ("pos_e", "pos_n", "pos_u", "vel_e", "vel_n", "vel_u")
SPEED_COURSE_LABELS = ("vel_along", "vel_cross")
#: the sources of a fix's rows (``Measurement.groups``): the position rows are one least-squares
#: solution of the receiver, the velocity rows (velocity, speed and course, vertical rate)
#: another, from its Dopplers: a fault large enough to fail one row of a solution is in its
#: other rows too, only smaller (measurements.base.refused_with_source)
FIX_GROUPS = ("position", "velocity")


def _late_carry(nav: NavState, vel_fix, dt: float, acc) -> tuple[tuple[float, float, float], tuple]:
    """A fix ``dt`` s older than the INS (module docstring): (what carries its position to the INS
    time, what takes the INS velocity back to the fix's time), ENU. ``acc``: the INS's acceleration
    (None: taken as zero)."""
    a0, a1, a2 = (0.0, 0.0, 0.0) if acc is None else (float(x) for x in acc)
    h = 0.5 * dt * dt
    if vel_fix is None:  # a position-only fix: the INS's velocity, now, carries it
        v0, v1, v2 = nav.vel_enu_mps.tolist()
        carry = (v0 * dt - a0 * h, v1 * dt - a1 * h, v2 * dt - a2 * h)
    else:
        v0, v1, v2 = (float(x) for x in vel_fix)
        carry = (v0 * dt + a0 * h, v1 * dt + a1 * h, v2 * dt + a2 * h)
    return carry, (a0 * dt, a1 * dt, a2 * dt)


@lru_cache(maxsize=8)
def _groups(rows: int) -> np.ndarray:
    """The source of each of a fix's ``rows`` rows: three position rows first (read-only, shared)."""
    g = np.minimum(np.arange(rows) // 3, 1)
    g.flags.writeable = False
    return g


@lru_cache(maxsize=16)
def _plain_rows(n_states: int, rows: int) -> tuple[np.ndarray, tuple[float, ...]]:
    """(H, sigma floors) of a fix's ``rows`` rows (3: position, 6: and velocity) with the antenna
    at the IMU, as the general path builds them (the attitude columns hold the skew of a zero
    offset); read-only, shared."""
    H = np.zeros((rows, n_states))
    H[:3, em.POS] = np.eye(3)
    H[:3, em.ATT] = earth.skew(np.zeros(3))
    mins = [MIN_POS_STD_M] * 3
    if rows == 6:
        H[3:, em.VEL] = np.eye(3)
        H[3:, em.ATT] = earth.skew(np.zeros(3))
        mins += [MIN_VEL_STD_MPS] * 3
    H.flags.writeable = False
    return H, tuple(mins)


MIN_POS_STD_M = 0.005
MIN_VEL_STD_MPS = 0.001
MIN_WHITE_FRACTION = 0.2
log = logging.getLogger("fednav.service")
BLOCK = "gnss_error"
BLOCK_NAMES = ("gnss_err_e_m", "gnss_err_n_m", "gnss_err_u_m")
LEVER_BLOCK = "gnss_lever_arm"
LEVER_NAMES = ("gnss_lever_arm_x_m", "gnss_lever_arm_y_m", "gnss_lever_arm_z_m")


def white_std(pos_std_m, gm_sigma_m) -> np.ndarray:
    """The white part of a fix's position error per axis when its correlated part is a state of
    ``gm_sigma_m``: the fix's claimed 1-sigma is the total, so sqrt(claimed^2 - gm^2), and at
    least ``MIN_WHITE_FRACTION`` of the claim (a fix claiming less than the configured correlated
    error: the configuration does not fit the receiver's sigmas)."""
    c = np.asarray(pos_std_m, dtype=float)
    return np.sqrt(np.maximum(c**2 - np.square(gm_sigma_m), (MIN_WHITE_FRACTION * c) ** 2))


def gauss_markov_block(tau_s: float, sigma_enu_m) -> PrivateStates:
    """First-order Gauss-Markov ENU position error of the receiver (stationary, exact
    discretisation): Phi = e^(-T/tau) I, Qd = sigma^2 (1 - e^(-2T/tau))."""
    var = np.square(np.asarray(sigma_enu_m, dtype=float))

    def transition(T: float) -> tuple[np.ndarray, np.ndarray]:
        a = math.exp(-T / tau_s)
        return a * np.eye(3), np.diag(var * (1.0 - a * a))

    return PrivateStates(BLOCK, BLOCK_NAMES, transition, tuple(float(s) for s in sigma_enu_m))


def lever_arm_block(std_m, rw_m_per_sqrt_h: float = 0.0) -> PrivateStates:
    """The antenna lever arm (body axes, m) as a random constant with an optional random walk:
    Phi = I, Qd = (rw^2 / 3600) T I; prior sigma ``std_m`` per axis (a number or three)."""
    std = np.broadcast_to(np.asarray(std_m, dtype=float), (3,))
    q = float(rw_m_per_sqrt_h) ** 2 / 3600.0

    def transition(T: float) -> tuple[np.ndarray, np.ndarray]:
        return np.eye(3), np.eye(3) * (q * T)

    return PrivateStates(LEVER_BLOCK, LEVER_NAMES, transition, tuple(float(s) for s in std))


def gnss_fix_options(cfg) -> dict:
    """The model's options from a pipeline configuration with ``gnss_lever_arm_b_m`` and
    ``gnss_correlated_error`` (loosely coupled, federated, centralised), and the lever-arm
    estimation options where the configuration has them (loosely coupled)."""
    gm = cfg.gnss_correlated_error
    out = {
        "lever_arm_b_m": cfg.gnss_lever_arm_b_m,
        "correlated_sigma_enu_m": None if gm is None else gm.sigma_enu_m,
        "correlation_time_s": 60.0 if gm is None else gm.correlation_time_s,
    }
    if getattr(cfg, "estimate_gnss_lever_arm", False):
        out["estimate_lever_arm"] = True
        out["lever_arm_std_m"] = cfg.gnss_lever_arm_std_m
        out["lever_arm_rw_m_per_sqrt_h"] = cfg.gnss_lever_arm_rw_m_per_sqrt_h
    return out


class GnssFixModel:
    kind = "gnss_fix"
    # the class has no private states (usable by every 15-state filter); an instance with a
    # correlated-error or lever-arm block declares it (the loosely coupled family builds its
    # bank with it)
    private_states: tuple[PrivateStates, ...] = ()

    def __init__(
        self,
        lever_arm_b_m=(0.0, 0.0, 0.0),
        correlated_sigma_enu_m=None,
        correlation_time_s: float = 60.0,
        estimate_lever_arm: bool = False,
        lever_arm_std_m=1.0,
        lever_arm_rw_m_per_sqrt_h: float = 0.0,
    ):
        self.lever_arm_b_m = np.asarray(lever_arm_b_m, dtype=float)
        self.gm_sigma = None if correlated_sigma_enu_m is None else np.asarray(correlated_sigma_enu_m, float)
        self.estimate_lever_arm = bool(estimate_lever_arm)
        blocks = []
        if self.gm_sigma is not None:
            blocks.append(gauss_markov_block(correlation_time_s, self.gm_sigma))
        if self.estimate_lever_arm:
            blocks.append(lever_arm_block(lever_arm_std_m, lever_arm_rw_m_per_sqrt_h))
        if blocks:
            self.private_states = tuple(blocks)
        self._warned_below_gm = False

    def _warn_below_gm(self, pos_std: np.ndarray) -> None:
        """Log once that the fixes claim less than the configured correlated error."""
        self._warned_below_gm = True
        log.warning(
            "GNSS fixes claim a position sigma (E/N/U %s m) below the configured gnss_correlated_error "
            "sigma_enu_m (%s m): the configuration does not fit this receiver's sigmas (it was made for "
            "fixes claiming more, e.g. without GST or in another fix mode); their white part is taken as "
            "%.0f %% of the claim and the position starts no more certain than the correlated error; "
            "re-run fednav-replay --suggest-config on a log with these sigmas",
            "/".join(f"{v:.2f}" for v in pos_std),
            "/".join(f"{v:.2f}" for v in self.gm_sigma),
            100 * MIN_WHITE_FRACTION,
        )

    # --- the antenna ------------------------------------------------------------------------------
    def lever_arm(self, ctx: ModelContext | None = None) -> np.ndarray:
        """The lever arm the model uses: the configured one, plus the estimated block's reference
        when the lever arm is estimated."""
        if not self.estimate_lever_arm or ctx is None:
            return self.lever_arm_b_m
        ref = ctx.reference.get(LEVER_BLOCK)
        if ref is None:
            raise ValueError("the estimated lever arm needs a filter with the 'gnss_lever_arm' block")
        return self.lever_arm_b_m + np.asarray(ref, dtype=float)

    def antenna_offsets(self, nav: NavState, wib_b_rps, lever_b_m=None) -> tuple[np.ndarray, np.ndarray]:
        """(C_nb l, C_nb (w x l)): the antenna's position and velocity offsets from the IMU, ENU."""
        l_b = self.lever_arm_b_m if lever_b_m is None else lever_b_m
        if not l_b.any():  # the antenna at the IMU: no offsets (the same zeros, without the algebra)
            return np.zeros(3), np.zeros(3)
        c_nb = nav.mat_nb
        return c_nb @ l_b, c_nb @ np.cross(np.asarray(wib_b_rps, dtype=float), l_b)

    def __call__(self, nav: NavState, msg: GnssFix, ctx: ModelContext) -> Measurement | None:
        if (
            self.gm_sigma is None
            and not self.estimate_lever_arm
            and msg.speed_mps is None
            and not np.count_nonzero(self.lever_arm_b_m)  # (as .any(), without its Python wrapper)
        ):
            return self._at_imu(nav, msg, ctx)
        lat, lon = math.radians(msg.lat_deg), math.radians(msg.lon_deg)
        r_m, r_n = earth.radii(nav.lat_rad)
        dl_pos, dl_vel = self.antenna_offsets(nav, ctx.wib_b_rps, self.lever_arm(ctx))
        vel_fix = msg.velocity()
        dt = ctx.dt_late_s
        if dt > 0.0:
            carry, back = _late_carry(nav, vel_fix, dt, ctx.acc_enu_mps2)
            carry = np.array(carry)
        else:
            carry = np.zeros(3) if vel_fix is None else np.asarray(vel_fix, dtype=float) * dt
            back = None
        dp = (
            np.array(
                [
                    earth.wrap_pi(nav.lon_rad - lon) * (r_n + nav.h_m) * math.cos(nav.lat_rad),
                    (nav.lat_rad - lat) * (r_m + nav.h_m),
                    nav.h_m - msg.height_m,
                ]
            )
            + dl_pos
            - carry
        )
        pos_std = np.asarray(msg.pos_std(), dtype=float)
        H_pos = np.zeros((3, ctx.n_states))
        H_pos[:, em.POS] = np.eye(3)
        H_pos[:, em.ATT] = earth.skew(dl_pos)
        if self.gm_sigma is not None:
            cols = ctx.columns.get(BLOCK)
            if cols is None:
                raise ValueError("the correlated GNSS error needs a filter with the 'gnss_error' block")
            dp = dp + np.asarray(ctx.reference[BLOCK], dtype=float)
            H_pos[:, cols] = np.eye(3)
            if not self._warned_below_gm and np.any(pos_std < self.gm_sigma):
                self._warn_below_gm(pos_std)
            pos_std = white_std(pos_std, self.gm_sigma)
        v_a = np.asarray(nav.vel_enu_mps, dtype=float) + dl_vel
        if back is not None:  # late: the INS velocity at the fix's time
            v_a = v_a - np.array(back)
        H_vel = np.zeros((3, ctx.n_states))
        H_vel[:, em.VEL] = np.eye(3)
        H_vel[:, em.ATT] = earth.skew(dl_vel)
        if self.estimate_lever_arm:
            cols = ctx.columns[LEVER_BLOCK]
            c_nb = nav.mat_nb
            H_pos[:, cols] = c_nb
            H_vel[:, cols] = c_nb @ earth.skew(np.asarray(ctx.wib_b_rps, dtype=float))
        zs, Hs, stds, mins, labels = [dp], [H_pos], [pos_std], [np.full(3, MIN_POS_STD_M)], list(LABELS[:3])
        variant = msg.variant
        if variant == "velocity":
            vel_std = msg.vel_std()
            zs.append(v_a - np.asarray(msg.vel_enu_mps, dtype=float))
            Hs.append(H_vel)
            stds.append(np.asarray(vel_std, dtype=float))
            mins.append(np.full(3, MIN_VEL_STD_MPS))
            labels += LABELS[3:]
        elif variant == "speed_course":
            s = float(msg.speed_mps)
            c = math.radians(msg.course_deg)
            U = np.array([[math.sin(c), math.cos(c)], [math.cos(c), -math.sin(c)]])  # along, cross
            s_s = msg.speed_std()
            cross = s_s if msg.course_std_deg is None else max(s * math.radians(msg.course_std_deg), s_s)
            zs.append(U @ v_a[:2] - np.array([s, 0.0]))
            Hs.append(U @ H_vel[:2])
            stds.append(np.array([s_s, cross]))
            mins.append(np.full(2, MIN_VEL_STD_MPS))
            labels += SPEED_COURSE_LABELS
            if msg.vertical_rate_mps is not None:
                zs.append(np.array([v_a[2] - msg.vertical_rate_mps]))
                Hs.append(H_vel[2:3])
                stds.append(np.array([msg.vertical_rate_std_mps or DEFAULT_VERTICAL_RATE_STD_MPS]))
                mins.append(np.array([MIN_VEL_STD_MPS]))
                labels.append(LABELS[5])
        z = np.concatenate(zs)
        if not np.all(np.isfinite(z)):
            return None
        var, floored = floored_variances(np.concatenate(stds), np.concatenate(mins))
        H, R = np.vstack(Hs), np.diag(var)
        groups = _groups(len(z))
        return Measurement(z, H, R, tuple(labels), groups=groups, group_ids=FIX_GROUPS, floored=floored)

    def _at_imu(self, nav: NavState, msg: GnssFix, ctx: ModelContext) -> Measurement | None:
        """:meth:`__call__` of a position or 3-D velocity fix with the antenna at the IMU and no
        private block (every fix of a plain configuration): the same rows and the same arithmetic
        (the zero lever-arm offsets added as the general path adds them, the same H), without the
        general path's array building."""
        lat, lon = math.radians(msg.lat_deg), math.radians(msg.lon_deg)
        r_m, r_n = earth.radii(nav.lat_rad)
        h = nav.h_m
        vel_fix = msg.vel_enu_mps
        dt = ctx.dt_late_s
        back = None
        if dt > 0.0:
            (c0, c1, c2), back = _late_carry(nav, vel_fix, dt, ctx.acc_enu_mps2)
        else:
            c0, c1, c2 = (0.0, 0.0, 0.0) if vel_fix is None else (v * dt for v in vel_fix)
        z = [
            (earth.wrap_pi_f(nav.lon_rad - lon) * (r_n + h) * math.cos(nav.lat_rad) + 0.0) - c0,
            ((nav.lat_rad - lat) * (r_m + h) + 0.0) - c1,
            ((h - msg.height_m) + 0.0) - c2,
        ]
        std = msg.pos_std()
        if vel_fix is not None:
            ve, vn, vu = nav.vel_enu_mps.tolist()
            if back is not None:  # late: the INS velocity at the fix's time
                ve, vn, vu = ve - back[0], vn - back[1], vu - back[2]
            fe, fn, fu = vel_fix
            z += [(ve + 0.0) - fe, (vn + 0.0) - fn, (vu + 0.0) - fu]
            std = (*std, *msg.vel_std())
        if not all(map(math.isfinite, z)):
            return None
        m = len(z)
        H, mins = _plain_rows(ctx.n_states, m)
        # floored_variances on floats (max then square, NaN kept, as np.maximum and np.square) and
        # R as np.diag builds it (zeros, the diagonal set), without their Python wrappers
        var, floored = [], 0
        for s, lo in zip(map(float, std), mins, strict=True):
            floored += s < lo
            s = lo if lo > s else s
            var.append(s * s)
        R = np.zeros((m, m))
        R.ravel()[:: m + 1] = var
        return Measurement(
            np.array(z), H, R, LABELS[:m], groups=_groups(m), group_ids=FIX_GROUPS, floored=floored
        )
