"""Coarse alignment maths (service/ins/alignment.py) against hand-computed cases."""

import math

import numpy as np
import pytest

from fednav.service import earth
from fednav.service.ins import alignment as al
from fednav.service.messages import GnssFix, InitialNav

LAT_DEG = 45.0
LAT = math.radians(LAT_DEG)
G = 9.80
W_IE_N = earth.OMEGA_IE_RPS * math.cos(LAT)  # horizontal (north) earth rate
W_IE_U = earth.OMEGA_IE_RPS * math.sin(LAT)  # vertical earth rate
DT = 0.01


def _fix(t=100.0, vel=(0.0, 0.0, 0.0), lat=LAT_DEG, h=50.0):
    return GnssFix(
        t=t,
        lat_deg=lat,
        lon_deg=10.0,
        height_m=h,
        vel_enu_mps=vel,
        pos_std_enu_m=(1.0, 2.0, 3.0),
        vel_std_enu_mps=(0.1, 0.2, 0.3),
    )


def _accumulate(f_b, w_b, n=100, t0=40.0, f_jitter=0.0):
    acc = al.ImuAccumulator()
    for k in range(n):
        f = np.asarray(f_b, dtype=float) + (f_jitter if k % 2 else -f_jitter)
        acc.add(t0 + (k + 1) * DT, DT, np.asarray(w_b) * DT, f * DT)
    return acc


def _level_body_rate(heading_deg):
    """Earth rate seen by a level body (right-forward-up) heading ``heading_deg`` from north:
    forward = (sin h, cos h, 0) and right = (cos h, -sin h, 0) in ENU, earth rate (0, W_N, W_U)."""
    h = math.radians(heading_deg)
    return np.array([-math.sin(h) * W_IE_N, math.cos(h) * W_IE_N, W_IE_U])


# --- accumulator ------------------------------------------------------------------------------------
def test_accumulator_means_scatter_and_span():
    acc = _accumulate([0.1, 0.2, G], [1e-5, 2e-5, 3e-5], n=4, t0=10.0, f_jitter=0.3)
    assert acc.n == 4 and acc.t_start == pytest.approx(10.0)
    assert acc.mean_specific_force() == pytest.approx([0.1, 0.2, G])
    assert acc.mean_rate() == pytest.approx([1e-5, 2e-5, 3e-5])
    # every axis alternates by +-0.3: per-axis std 0.3, RSS over three axes 0.3 sqrt(3)
    assert acc.specific_force_scatter() == pytest.approx(0.3 * math.sqrt(3.0), rel=1e-9)
    assert acc.covers(10.05, 0.04) and not acc.covers(10.03, 0.04)
    assert not al.ImuAccumulator().covers(1e9, 0.0)  # no data: never covers


# --- static alignment -------------------------------------------------------------------------------
@pytest.mark.parametrize("heading_deg", [0.0, 30.0, 90.0, 200.0, 315.0])
def test_level_static_imu_gives_zero_tilt_and_its_heading(heading_deg):
    rpy = al.level_and_gyrocompass(np.array([0.0, 0.0, G]), _level_body_rate(heading_deg))
    assert rpy[0] == pytest.approx(0.0, abs=1e-12)
    assert rpy[1] == pytest.approx(0.0, abs=1e-12)
    assert earth.heading_deg_from_yaw(rpy[2]) == pytest.approx(heading_deg, abs=1e-9)


def test_level_static_imu_facing_east_by_hand():
    # facing east: right = south, forward = east -> w_b = (-W_N, 0, W_U); yaw -90 deg (west-positive)
    rpy = al.level_and_gyrocompass(np.array([0.0, 0.0, G]), np.array([-W_IE_N, 0.0, W_IE_U]))
    assert rpy == pytest.approx([0.0, 0.0, -math.pi / 2], abs=1e-12)


def test_tilted_static_imu():
    roll, pitch, heading = math.radians(2.0), math.radians(-3.0), 120.0
    # f_b = C_bn (0, 0, g): the third row of C_nb = Rz Rx(pitch) Ry(roll)
    f_b = G * np.array([-math.cos(pitch) * math.sin(roll), math.sin(pitch), math.cos(pitch) * math.cos(roll)])
    c_nb = earth.rpy_to_mat_nb(np.array([roll, pitch, earth.yaw_from_heading_deg(heading)]))
    w_b = c_nb.T @ np.array([0.0, W_IE_N, W_IE_U])
    rpy = al.level_and_gyrocompass(f_b, w_b)
    assert rpy[0] == pytest.approx(roll, abs=1e-12)
    assert rpy[1] == pytest.approx(pitch, abs=1e-12)
    assert earth.heading_deg_from_yaw(rpy[2]) == pytest.approx(heading, abs=1e-9)


def test_static_alignment_state_and_sigmas():
    acc = _accumulate([0.0, 0.0, G], _level_body_rate(30.0))
    fix = _fix(t=41.0, vel=(0.1, -0.2, 0.0))
    sg, sa = 1.0 * earth.DPH, 1000.0 * earth.UG  # a poor IMU: sigmas above their floors
    nav, std = al.static_alignment(acc, fix, 41.5, sg, sa)
    assert nav.t == 41.5
    assert earth.heading_deg_from_yaw(nav.rpy_rad[2]) == pytest.approx(30.0, abs=1e-9)
    assert np.all(nav.vel_enu_mps == 0.0)  # static: zero velocity ...
    r_m, _ = earth.radii(LAT)
    assert nav.lat_rad == pytest.approx(LAT + (-0.2 * 0.5) / (r_m + 50.0), abs=1e-15)  # ... fix carried
    assert list(std.pos_enu_m) == [1.0, 2.0, 3.0]
    assert list(std.vel_enu_mps) == [0.05, 0.05, 0.05]
    tilt = 1000e-6 * 9.7803253359 / G  # accel bias / g
    heading_sigma = 1.0 / 3600.0 * math.pi / 180.0 / (7.292115e-5 * math.cos(LAT))  # gyro bias / (w cos L)
    assert std.att_rad == pytest.approx([tilt, tilt, heading_sigma], rel=1e-12)


def test_static_alignment_sigma_floors():
    acc = _accumulate([0.0, 0.0, G], _level_body_rate(0.0))
    _, std = al.static_alignment(acc, _fix(t=41.0), 41.0, 0.01 * earth.DPH, 50.0 * earth.UG)
    # 50 ug / g = 5e-5 rad < 1e-4; 0.01 deg/h / (w cos 45) = 0.054 deg < 0.5 deg
    assert std.att_rad == pytest.approx([1e-4, 1e-4, math.radians(0.5)])
    assert al.LEVELLING_STD_FLOOR_RAD == 1e-4 and al.HEADING_STD_FLOOR_RAD == math.radians(0.5)


def test_static_alignment_refuses_a_moving_imu():
    sg, sa = 0.01 * earth.DPH, 50.0 * earth.UG
    shaking = _accumulate([0.0, 0.0, G], _level_body_rate(0.0), f_jitter=0.3)  # scatter 0.52 m/s^2
    assert shaking.specific_force_scatter() > al.STATIC_MAX_SCATTER_MPS2
    assert al.static_alignment(shaking, _fix(t=41.0), 41.0, sg, sa) is None
    calm = _accumulate([0.0, 0.0, G], _level_body_rate(0.0), f_jitter=0.2)  # scatter 0.35 m/s^2
    assert al.static_alignment(calm, _fix(t=41.0), 41.0, sg, sa) is not None


# --- in motion ----------------------------------------------------------------------------------------
@pytest.mark.parametrize(
    ("vel", "heading_deg", "pitch_deg"),
    [
        ((3.0, 4.0, 0.0), math.degrees(math.atan2(3.0, 4.0)), 0.0),  # 36.87 deg
        ((0.0, -10.0, 10.0), 180.0, 45.0),
        ((-20.0, 0.0, -20.0 / math.sqrt(3.0)), 270.0, -30.0),
    ],
)
def test_attitude_from_velocity_track(vel, heading_deg, pitch_deg):
    rpy = al.attitude_from_velocity(vel)
    assert rpy[0] == 0.0
    assert rpy[1] == pytest.approx(math.radians(pitch_deg), abs=1e-12)
    assert earth.heading_deg_from_yaw(rpy[2]) == pytest.approx(heading_deg, abs=1e-9)


def test_motion_alignment_from_a_fix():
    fix = _fix(t=100.0, vel=(30.0, 40.0, 0.0))
    nav, std = al.motion_alignment(fix, 100.2)
    assert nav.t == 100.2
    assert list(nav.vel_enu_mps) == [30.0, 40.0, 0.0]
    rpy = nav.rpy_rad
    assert rpy[0] == pytest.approx(0.0, abs=1e-12) and rpy[1] == pytest.approx(0.0, abs=1e-12)
    assert earth.heading_deg_from_yaw(rpy[2]) == pytest.approx(math.degrees(math.atan2(30.0, 40.0)))
    assert list(std.pos_enu_m) == [1.0, 2.0, 3.0] and list(std.vel_enu_mps) == [0.1, 0.2, 0.3]
    assert std.att_rad == pytest.approx(np.radians([2.0, 2.0, 5.0]))


def test_nav_at_fix_carries_position_with_the_fix_velocity():
    fix = _fix(t=100.0, vel=(0.0, 10.0, 1.0))
    r_m, _ = earth.radii(LAT)
    ahead = al.nav_at_fix(fix, np.zeros(3), 100.5)  # 5 m north, 0.5 m up
    assert ahead.lat_rad == pytest.approx(LAT + 5.0 / (r_m + 50.0), abs=1e-15)
    assert ahead.lon_rad == pytest.approx(math.radians(10.0), abs=1e-15)
    assert ahead.h_m == pytest.approx(50.5)
    back = al.nav_at_fix(fix, np.zeros(3), 99.0)  # 10 m south, 1 m down
    assert back.lat_rad == pytest.approx(LAT - 10.0 / (r_m + 50.0), abs=1e-15)
    assert back.h_m == pytest.approx(49.0)


@pytest.mark.parametrize("age_s", [0.3, 0.9, -0.6])
def test_a_fix_as_a_reference_is_carried_along_the_turn_its_fixes_show(age_s):
    """alignment.fix_reference: the demo aircraft's 3 deg/s turn at 120 m/s (6.3 m/s^2 centripetal),
    fixes 1 s apart: the last fix carried over its age with the two fixes' acceleration covers the
    true state at the INS time (chi-square of 6 within its 99.9 % quantile, 22.5), where the fix as
    it was (motion_alignment: its velocity held, its sigmas kept) is 1.9-5.7 m/s off against 0.1 m/s;
    without the previous fix its sigmas grow by the unknown acceleration instead."""
    omega, speed = math.radians(3.0), 120.0
    r_m, r_n = earth.radii(LAT)

    def truth(t):  # a circle east/north about the origin of the turn, heading north at t=0
        th = omega * t
        e, n = (speed / omega) * (1.0 - math.cos(th)), (speed / omega) * math.sin(th)
        return (
            np.array([e, n, 0.0]),
            np.array([speed * math.sin(th), speed * math.cos(th), 0.0]),
        )

    def fix_at(t):
        p, v = truth(t)
        return GnssFix(
            t=t,
            lat_deg=LAT_DEG + math.degrees(p[1] / (r_m + 50.0)),
            lon_deg=10.0 + math.degrees(p[0] / ((r_n + 50.0) * math.cos(LAT))),
            height_m=50.0,
            vel_enu_mps=tuple(v),
            pos_std_enu_m=(1.0, 1.0, 2.0),
            vel_std_enu_mps=(0.1, 0.1, 0.1),
        )

    prev, fix = fix_at(9.0), fix_at(10.0)
    t = 10.0 + age_s
    p_true, v_true = truth(t)
    true_nav = al.nav_at_fix(fix_at(t), np.zeros(3), t)
    nav, cov = al.fix_reference(fix, t, prev)
    d = al.pos_vel_difference(nav, true_nav)
    assert float(d @ np.linalg.solve(cov, d)) < 22.5, (d, np.sqrt(np.diag(cov)))
    assert np.all(np.sqrt(np.diag(cov))[3:5] < 0.6)  # the acceleration known: still a tight reference
    held, held_std = al.motion_alignment(fix, t)
    dv = al.pos_vel_difference(held, true_nav)[3:]
    assert np.linalg.norm(dv) > 1.5 and np.all(np.asarray(held_std.vel_enu_mps) <= 0.1)  # the old reference
    alone_nav, alone_cov = al.fix_reference(fix, t)  # no previous fix: the acceleration unknown
    d = al.pos_vel_difference(alone_nav, true_nav)
    assert float(d @ np.linalg.solve(alone_cov, d)) < 22.5
    assert np.all(np.sqrt(np.diag(alone_cov))[3:5] >= al.REF_ACC_UNKNOWN_MPS2 * abs(age_s) * 0.99)
    assert np.allclose(al.fix_reference(fix, 10.0, prev)[1], al.std_cov6(al.motion_alignment(fix, 10.0)[1]))


def test_fix_age_and_speed():
    fix = _fix(t=100.0, vel=(3.0, 4.0, 0.0))
    assert al.fix_is_current(fix, 101.0) and al.fix_is_current(fix, 99.0)
    assert not al.fix_is_current(fix, 101.001)
    assert al.fix_speed(fix) == pytest.approx(5.0)


def test_from_initial_nav():
    msg = InitialNav(
        t=5.0,
        lat_deg=LAT_DEG,
        lon_deg=-20.0,
        height_m=100.0,
        vel_enu_mps=(1.0, 2.0, 3.0),
        rpy_deg=(1.0, -2.0, 30.0),
        pos_std_enu_m=(1.0, 1.0, 2.0),
        vel_std_enu_mps=(0.1, 0.1, 0.2),
        rpy_std_deg=(0.1, 0.2, 0.5),
    )
    nav, std = al.from_initial_nav(msg)
    assert (nav.t, nav.h_m) == (5.0, 100.0)
    assert nav.lat_rad == math.radians(LAT_DEG) and nav.lon_rad == math.radians(-20.0)
    assert earth.rpy_msg_deg(nav.rpy_rad) == pytest.approx([1.0, -2.0, 30.0])
    # roll/pitch sigmas -> nav-frame tilts: east tilt ~ pitch (rotation about x), north ~ roll
    assert std.att_rad == pytest.approx(np.radians([0.2, 0.1, 0.5]))
    assert list(std.pos_enu_m) == [1.0, 1.0, 2.0] and list(std.vel_enu_mps) == [0.1, 0.1, 0.2]


def test_init_std_is_reexported_by_the_pipeline_contract():
    from fednav.service.pipelines.base import InitStd

    assert InitStd is al.InitStd
