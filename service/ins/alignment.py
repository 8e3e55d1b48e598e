"""Coarse alignment: an initial navigation state and its uncertainty without a host's InitialNav.

Pure functions (no engine state); the engine decides *when* to align (``[init] mode``,
``align_time_s``, ``min_speed_mps``) and these decide *how*:

- :func:`static_alignment`: levelling and gyrocompassing from the mean specific force and angular
  rate of a static IMU (:class:`ImuAccumulator`), at a GNSS fix's position. Roll and pitch from
  the direction of the specific force (gravity reaction), yaw from the horizontal earth rate seen
  in the levelled frame. Attitude sigmas from the IMU bias sigmas: levelling to
  ``accel_bias / g``, gyrocompassing to ``gyro_bias / (omega_ie cos L)`` (with floors).
- :func:`motion_alignment`: in motion, position and velocity from a GNSS fix, heading and pitch
  from its velocity track, roll 0, wide attitude sigmas.
- :func:`nav_at_fix`: a fix's position carried to the INS time with the fix's own velocity.
- :func:`from_initial_nav`: the state and sigmas of a host's InitialNav message.

Frames as everywhere in the service: ENU navigation frame, right-forward-up body, yaw
west-positive (``earth.rpy_to_mat_nb``), headings clockwise from north.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

from fednav.service import earth
from fednav.service.ins.mechanisation import NavState
from fednav.service.messages import GnssFix, InitialNav

#: a GNSS fix further than this from the INS time is not used to initialise (s)
FIX_MAX_AGE_S = 1.0
#: static alignment needs the GNSS speed below this (m/s)
STATIC_MAX_SPEED_MPS = 0.5
#: static alignment needs the specific-force scatter (RSS of the per-axis standard deviations)
#: below this (m/s^2); above, the vehicle is moving and in-motion initialisation is awaited
STATIC_MAX_SCATTER_MPS2 = 0.5
#: 1-sigma attitude uncertainty of an in-motion alignment, nav frame (east, north, up), deg:
#: roll is assumed 0 and heading/pitch follow the velocity track (sideslip, angle of attack)
MOTION_ATT_STD_DEG = (2.0, 2.0, 5.0)
#: floor of the levelling (east/north tilt) sigma of a static alignment (rad)
LEVELLING_STD_FLOOR_RAD = 1e-4
#: floor of the gyrocompassing (heading) sigma of a static alignment (rad)
HEADING_STD_FLOOR_RAD = math.radians(0.5)
#: 1-sigma velocity uncertainty of a static alignment (velocity set to zero), each ENU axis (m/s)
STATIC_VEL_STD_MPS = 0.05


@dataclass(frozen=True)
class InitStd:
    """1-sigma uncertainties of an initial state: ENU m, ENU m/s, nav-frame rad; ``cov``, when
    given, a full covariance they are part of: 9x9 of (dp, dv, phi), or of every state of the
    filter it restarts (its columns: the 15 INS error states, then its private blocks), so that a
    restart keeps what the running filter knew of the correlations. ``pos_from_fix``: the position
    is a GNSS fix's (its error is the receiver's, correlated part included)."""

    pos_enu_m: np.ndarray
    vel_enu_mps: np.ndarray
    att_rad: np.ndarray
    cov: np.ndarray | None = None
    pos_from_fix: bool = False


@dataclass
class ImuAccumulator:
    """Running sums of IMU rate and specific force (body frame) over the alignment window."""

    t_start: float | None = None  # start of the first accumulated interval
    n: int = 0
    sum_w: np.ndarray = field(default_factory=lambda: np.zeros(3))
    sum_f: np.ndarray = field(default_factory=lambda: np.zeros(3))
    sum_f2: np.ndarray = field(default_factory=lambda: np.zeros(3))

    def add(self, t: float, dt_s: float, dtheta_rad, dvel_mps) -> None:
        """One IMU interval (increments over ``dt_s`` ending at ``t``)."""
        if self.t_start is None:
            self.t_start = t - dt_s
        w = np.asarray(dtheta_rad) / dt_s
        f = np.asarray(dvel_mps) / dt_s
        self.n += 1
        self.sum_w += w
        self.sum_f += f
        self.sum_f2 += f * f

    def covers(self, t: float, duration_s: float) -> bool:
        """True when the accumulated data spans at least ``duration_s`` up to ``t``."""
        return self.n > 0 and self.t_start is not None and t - self.t_start >= duration_s

    def mean_specific_force(self) -> np.ndarray:
        return self.sum_f / self.n

    def mean_rate(self) -> np.ndarray:
        return self.sum_w / self.n

    def specific_force_scatter(self) -> float:
        """RSS of the per-axis standard deviations of the specific force (m/s^2)."""
        f = self.sum_f / self.n
        var_f = np.maximum(self.sum_f2 / self.n - f * f, 0.0)
        return float(np.sqrt(var_f.sum()))


#: velocity 1-sigma of a position-only fix used as a reference state (uninformative)
UNKNOWN_VEL_STD_MPS = 100.0


def fix_is_current(fix: GnssFix, t: float) -> bool:
    """Whether a fix is close enough to the INS time ``t`` to initialise from."""
    return abs(fix.t - t) <= FIX_MAX_AGE_S


def fix_speed(fix: GnssFix) -> float:
    """Speed of a fix (3-D or from speed/course); 0 for a position-only fix (no motion start)."""
    vel = fix.velocity()
    return 0.0 if vel is None else float(np.linalg.norm(vel))


def level_and_gyrocompass(f_b: np.ndarray, w_b: np.ndarray) -> np.ndarray:
    """Roll, pitch, yaw (rad) of a static body from its mean specific force ``f_b`` (m/s^2) and
    angular rate ``w_b`` (rad/s): f_b = C_bn [0, 0, g] gives roll and pitch; the rate rotated into
    the levelled frame is the horizontal earth rate [0, w cos L] turned by -yaw."""
    g = float(np.linalg.norm(f_b))
    pitch = math.asin(max(-1.0, min(1.0, f_b[1] / g)))
    roll = math.atan2(-f_b[0], f_b[2])
    c_lev = earth.rpy_to_mat_nb(np.array([roll, pitch, 0.0]))
    w_l = c_lev @ w_b
    yaw = math.atan2(w_l[0], w_l[1])
    return np.array([roll, pitch, yaw])


def static_attitude_std(
    g: float, lat_rad: float, gyro_bias_sigma: float, accel_bias_sigma: float
) -> np.ndarray:
    """Nav-frame attitude sigmas (rad) of a static alignment: tilts ``accel_bias / g``, heading
    ``gyro_bias / (omega_ie cos L)``, each with its floor."""
    return np.array(
        [
            max(accel_bias_sigma / g, LEVELLING_STD_FLOOR_RAD),
            max(accel_bias_sigma / g, LEVELLING_STD_FLOOR_RAD),
            max(gyro_bias_sigma / (earth.OMEGA_IE_RPS * math.cos(lat_rad)), HEADING_STD_FLOOR_RAD),
        ]
    )


def static_alignment(
    acc: ImuAccumulator, fix: GnssFix, t: float, gyro_bias_sigma: float, accel_bias_sigma: float
) -> tuple[NavState, InitStd] | None:
    """Static coarse alignment at the INS time ``t``: attitude from the accumulated IMU data,
    position from the fix (carried to ``t``), velocity zero. None when the specific force
    scattered too much for a static vehicle."""
    if acc.specific_force_scatter() > STATIC_MAX_SCATTER_MPS2:
        return None
    f = acc.mean_specific_force()
    rpy = level_and_gyrocompass(f, acc.mean_rate())
    att_std = static_attitude_std(
        float(np.linalg.norm(f)), math.radians(fix.lat_deg), gyro_bias_sigma, accel_bias_sigma
    )
    std = InitStd(np.array(fix.pos_std()), np.full(3, STATIC_VEL_STD_MPS), att_std, pos_from_fix=True)
    nav = nav_at_fix(fix, rpy, t)
    nav.vel_enu_mps = np.zeros(3)
    return nav, std


def attitude_from_velocity(vel_enu_mps) -> np.ndarray:
    """Roll 0, pitch and yaw (rad) of a body moving along its velocity (heading atan2(ve, vn))."""
    ve, vn, vu = vel_enu_mps
    heading = math.degrees(math.atan2(ve, vn))
    pitch = math.atan2(vu, math.hypot(ve, vn))
    return np.array([0.0, pitch, earth.yaw_from_heading_deg(heading)])


def motion_alignment(fix: GnssFix, t: float) -> tuple[NavState, InitStd]:
    """In-motion initialisation at the INS time ``t`` from a fix: position (carried to ``t``) and
    velocity from the fix, attitude from its velocity track, wide attitude sigmas."""
    vel, vel_std = fix.velocity(), fix.vel_std()
    if vel is None:  # position-only fix: velocity unknown (as a reference, only position counts)
        vel, vel_std = (0.0, 0.0, 0.0), (UNKNOWN_VEL_STD_MPS,) * 3
    att = np.radians(list(MOTION_ATT_STD_DEG))
    std = InitStd(np.array(fix.pos_std()), np.array(vel_std), att, pos_from_fix=True)
    return nav_at_fix(fix, attitude_from_velocity(vel), t), std


#: 1-sigma tilt (east, north) of an in-motion alignment whose specific force was matched with a
#: GNSS acceleration (rad): the acceleration from two fixes' velocities and the timing of the
#: specific force against it leave about a degree
TRIAD_TILT_STD_RAD = math.radians(2.0)
#: ... and without a GNSS acceleration (the vehicle assumed unaccelerated; rad)
TRIAD_TILT_STD_UNACCELERATED_RAD = math.radians(10.0)
#: the GNSS acceleration is taken from two fixes at most this far apart (s)
TRIAD_MAX_FIX_INTERVAL_S = 2.0


def gravity_attitude(f_b: np.ndarray, vel_n: np.ndarray, acc_n: np.ndarray, g: float) -> np.ndarray | None:
    """Attitude matrix C_nb of a moving body from its specific force (body, the accelerometers:
    ``f_b``) and its velocity and acceleration (nav ENU, GNSS: ``vel_n``, ``acc_n``): the
    specific force in the nav frame is ``acc_n + [0, 0, g]`` (gravity's reaction), which fixes
    roll and pitch; the body's forward axis lies in the plane of that force and the velocity,
    which fixes the heading (TRIAD, the force primary). None when the two directions are too
    close to tell a heading (moving along the specific force)."""
    f_n = np.asarray(acc_n, dtype=float) + np.array([0.0, 0.0, g])
    f_b = np.asarray(f_b, dtype=float)
    v = np.asarray(vel_n, dtype=float)
    nf, nb, nv = np.linalg.norm(f_n), np.linalg.norm(f_b), np.linalg.norm(v)
    if nf < 1e-6 or nb < 1e-6 or nv < 1e-6:
        return None
    n1, b1 = f_n / nf, f_b / nb
    n2, b2 = np.cross(n1, v / nv), np.cross(b1, np.array([0.0, 1.0, 0.0]))
    if np.linalg.norm(n2) < 0.1 or np.linalg.norm(b2) < 0.1:
        return None
    n2, b2 = n2 / np.linalg.norm(n2), b2 / np.linalg.norm(b2)
    N = np.column_stack([n1, n2, np.cross(n1, n2)])
    B = np.column_stack([b1, b2, np.cross(b1, b2)])
    return N @ B.T


def moving_alignment(
    fix: GnssFix, t: float, f_b: np.ndarray | None, previous: GnssFix | None = None
) -> tuple[NavState, InitStd]:
    """In-motion alignment at the INS time ``t`` from the vehicle's own sensors: position and
    velocity from the fix (as :func:`motion_alignment`), attitude from the specific force
    ``f_b`` (body, m/s^2, e.g. the last major interval of the IMU) and the fix's velocity and
    acceleration (from the ``previous`` fix's velocity when at most
    ``TRIAD_MAX_FIX_INTERVAL_S`` before; else assumed zero, with wider tilt sigmas):
    :func:`gravity_attitude`. Falls back to :func:`motion_alignment` (heading and pitch from
    the track, roll 0) without a usable specific force. Sigmas: the fix's, tilt
    ``TRIAD_TILT_STD_RAD`` (``TRIAD_TILT_STD_UNACCELERATED_RAD``), heading that of
    ``MOTION_ATT_STD_DEG`` (sideslip)."""
    nav, std = motion_alignment(fix, t)
    vel = fix.velocity()
    if f_b is None or vel is None or not np.all(np.isfinite(f_b)):
        return nav, std
    acc, tilt = np.zeros(3), TRIAD_TILT_STD_UNACCELERATED_RAD
    pv = previous.velocity() if previous is not None else None
    if pv is not None and 0.0 < fix.t - previous.t <= TRIAD_MAX_FIX_INTERVAL_S:
        acc = (np.asarray(vel) - np.asarray(pv)) / (fix.t - previous.t)
        tilt = TRIAD_TILT_STD_RAD
    c_nb = gravity_attitude(f_b, np.asarray(vel), acc, earth.gravity_normal(nav.lat_rad, nav.h_m))
    if c_nb is None:
        return nav, std
    nav.q_nb = earth.mat_to_quat(c_nb)
    att = np.array([tilt, tilt, math.radians(MOTION_ATT_STD_DEG[2])])
    return nav, InitStd(std.pos_enu_m, std.vel_enu_mps, att, pos_from_fix=std.pos_from_fix)


#: the latest fix as a reference at the INS time (:func:`fix_reference`) is carried over its age
#: with the acceleration of the last two fixes' velocities; what it cannot know: a change of that
#: acceleration over the age (m/s^2, 1-sigma), and without a previous fix the acceleration itself
#: (an aircraft in a 3 deg/s turn at 120 m/s accelerates 6.3 m/s^2)
REF_ACC_CHANGE_MPS2 = 0.5
REF_ACC_UNKNOWN_MPS2 = 5.0


def fix_reference(fix: GnssFix, t: float, previous: GnssFix | None = None) -> tuple[NavState, np.ndarray]:
    """The fix as an independent position and velocity at the INS time ``t`` (up to
    ``FIX_MAX_AGE_S`` from the fix) with its 6x6 covariance: carried over the age with the
    acceleration from the ``previous`` fix's velocity (at most ``TRIAD_MAX_FIX_INTERVAL_S``
    before), its covariance grown by what the carry cannot know (the velocity's sigma over the
    age, the acceleration's: its estimate's and ``REF_ACC_CHANGE_MPS2``, else
    ``REF_ACC_UNKNOWN_MPS2``; a position-only fix's unknown velocity). Why: a fix 0.5 s old in
    the demo aircraft's turn has a velocity 3 m/s off against its 0.1 m/s sigma, and a current
    state checked against it (a hand-over, an InitialNav) was refused as implausible."""
    nav, std = motion_alignment(fix, t)
    cov = std_cov6(std)
    age = t - fix.t
    if age == 0.0:
        return nav, cov
    vel = fix.velocity()
    var = np.diagonal(cov).copy()
    if vel is None:  # position only: held still, its sigma grown by the unknown velocity
        var[:3] += (UNKNOWN_VEL_STD_MPS * age) ** 2
        return nav, np.diag(var)
    acc, var_acc = np.zeros(3), np.full(3, REF_ACC_UNKNOWN_MPS2**2)
    pv = previous.velocity() if previous is not None else None
    if pv is not None and 0.0 < fix.t - previous.t <= TRIAD_MAX_FIX_INTERVAL_S:
        dt = fix.t - previous.t
        acc = (np.asarray(vel, dtype=float) - np.asarray(pv, dtype=float)) / dt
        pvs = previous.vel_std() or (UNKNOWN_VEL_STD_MPS,) * 3
        var_acc = (np.square(std.vel_enu_mps) + np.square(pvs)) / dt**2
        var_acc = var_acc + REF_ACC_CHANGE_MPS2**2
    nav.vel_enu_mps = nav.vel_enu_mps + acc * age
    dllh = earth.enu_m_to_llh_delta(0.5 * acc * age * age, nav.lat_rad, nav.h_m)
    nav.lat_rad, nav.lon_rad, nav.h_m = (
        float(nav.lat_rad + dllh[0]),
        float(nav.lon_rad + dllh[1]),
        float(nav.h_m + dllh[2]),
    )
    var[3:] += var_acc * age**2
    var[:3] += np.square(std.vel_enu_mps) * age**2 + var_acc * (0.5 * age * age) ** 2
    return nav, np.diag(var)


def nav_at_fix(fix: GnssFix, rpy_rad: np.ndarray, t: float) -> NavState:
    """State at time ``t`` from a fix, carried back/forward with the fix's velocity."""
    v = fix.velocity()
    vel = np.zeros(3) if v is None else np.array(v, dtype=float)
    llh = np.array([math.radians(fix.lat_deg), math.radians(fix.lon_deg), fix.height_m])
    dllh = earth.enu_m_to_llh_delta(vel * (t - fix.t), llh[0], llh[2])
    return NavState(
        t=t,
        lat_rad=float(llh[0] + dllh[0]),
        lon_rad=float(llh[1] + dllh[1]),
        h_m=float(llh[2] + dllh[2]),
        vel_enu_mps=vel,
        q_nb=earth.mat_to_quat(earth.rpy_to_mat_nb(rpy_rad)),
    )


#: an initial state (InitialNav) is implausible when its position and velocity differ from an
#: independent one (the latest GNSS fix, or the running estimate) by more than this chi-square(6)
#: quantile of their combined covariance: a false refusal once in a million consistent starts
PLAUSIBILITY_CHI2_6DOF = 38.26


def pos_vel_difference(a: NavState, b: NavState) -> np.ndarray:
    """a minus b: ENU position (m) and velocity (m/s) differences, (6,)."""
    r_m, r_n = earth.radii(b.lat_rad)
    dp = [
        earth.wrap_pi(a.lon_rad - b.lon_rad) * (r_n + b.h_m) * math.cos(b.lat_rad),
        (a.lat_rad - b.lat_rad) * (r_m + b.h_m),
        a.h_m - b.h_m,
    ]
    return np.concatenate([dp, np.asarray(a.vel_enu_mps) - np.asarray(b.vel_enu_mps)])


def plausible(a: NavState, b: NavState, cov6: np.ndarray) -> tuple[bool, float]:
    """Whether two independent position/velocity states agree within ``cov6`` (the sum of their
    6x6 covariances): (verdict, chi-square statistic)."""
    d = pos_vel_difference(a, b)
    try:
        L = np.linalg.cholesky(cov6)
    except np.linalg.LinAlgError:
        return False, math.inf
    w = np.linalg.solve(L, d)
    d2 = float(w @ w)
    return d2 <= PLAUSIBILITY_CHI2_6DOF, d2


def std_cov6(std: InitStd) -> np.ndarray:
    """The 6x6 position/velocity covariance of initial sigmas."""
    return np.diag(np.square(np.concatenate([std.pos_enu_m, std.vel_enu_mps])))


def from_initial_nav(msg: InitialNav) -> tuple[NavState, InitStd]:
    """State and sigmas of a host's InitialNav (roll/pitch sigmas -> nav-frame north/east tilts)."""
    rpy = earth.rpy_from_msg_deg(msg.rpy_deg)
    nav = NavState(
        t=msg.t,
        lat_rad=math.radians(msg.lat_deg),
        lon_rad=math.radians(msg.lon_deg),
        h_m=msg.height_m,
        vel_enu_mps=np.array(msg.vel_enu_mps, dtype=float),
        q_nb=earth.mat_to_quat(earth.rpy_to_mat_nb(rpy)),
    )
    rs = np.radians(msg.rpy_std_deg)
    std = InitStd(np.array(msg.pos_std_enu_m), np.array(msg.vel_std_enu_mps), np.array([rs[1], rs[0], rs[2]]))
    return nav, std


__all__ = [
    "PLAUSIBILITY_CHI2_6DOF",
    "plausible",
    "pos_vel_difference",
    "std_cov6",
    "FIX_MAX_AGE_S",
    "HEADING_STD_FLOOR_RAD",
    "LEVELLING_STD_FLOOR_RAD",
    "MOTION_ATT_STD_DEG",
    "STATIC_MAX_SCATTER_MPS2",
    "STATIC_MAX_SPEED_MPS",
    "STATIC_VEL_STD_MPS",
    "ImuAccumulator",
    "InitStd",
    "attitude_from_velocity",
    "fix_is_current",
    "fix_reference",
    "REF_ACC_CHANGE_MPS2",
    "REF_ACC_UNKNOWN_MPS2",
    "fix_speed",
    "from_initial_nav",
    "level_and_gyrocompass",
    "TRIAD_MAX_FIX_INTERVAL_S",
    "TRIAD_TILT_STD_RAD",
    "TRIAD_TILT_STD_UNACCELERATED_RAD",
    "gravity_attitude",
    "motion_alignment",
    "moving_alignment",
    "nav_at_fix",
    "static_alignment",
    "static_attitude_std",
]
