"""Trajectory generator: exact increments, consistent truth, segment outcomes, validation."""

from __future__ import annotations

import math
import time

import numpy as np
import pytest
from scipy.integrate import quad

from fednav.service import earth
from fednav.simulators.scenario import load_scenario
from fednav.simulators.trajectory import (
    AccelerateSegment,
    ClimbSegment,
    StartSpec,
    StaticSegment,
    StraightSegment,
    TurnSegment,
    build_trajectory,
    gravity_vec,
    mat_nb_vec,
    radii_vec,
)

T0 = 1_300_000_000.0
START = StartSpec(lat_deg=40.10021, lon_deg=118.60212, height_m=100.0, heading_deg=45.0, speed_mps=120.0)


@pytest.fixture(scope="module")
def demo():
    return load_scenario("demo_aircraft").build_trajectory()


def test_vectorised_earth_matches_scalar_earth():
    rng = np.random.default_rng(0)
    lat = rng.uniform(-1.4, 1.4, 50)
    h = rng.uniform(-100.0, 20000.0, 50)
    rpy = rng.uniform(-3.0, 3.0, (50, 3))
    r_m, r_n = radii_vec(lat)
    g = gravity_vec(lat, h)
    m = mat_nb_vec(rpy)
    for i in range(50):
        rm_i, rn_i = earth.radii(lat[i])
        assert r_m[i] == pytest.approx(rm_i, rel=1e-15)
        assert r_n[i] == pytest.approx(rn_i, rel=1e-15)
        assert g[i] == pytest.approx(earth.gravity_normal(lat[i], h[i]), rel=1e-15)
        np.testing.assert_allclose(m[i], earth.rpy_to_mat_nb(rpy[i]), atol=1e-15)


def test_increments_equal_adaptive_quadrature_of_the_rates(demo):
    """dtheta/dvel rows are the integrals of omega_ib^b / f^b (checked with scipy quad, to 1e-11)."""
    dt = demo.dt_s
    # intervals in straight flight, in ramps, right after ramp ends (kinks at 20 s, 25 s, 65 s, 95 s)
    rows = [1, 1000, 2001, 2050, 2499, 2500, 2501, 6500, 6501, 8000, 9501, 15000, 29999, 30000]
    for k in rows:
        a, b = (k - 1) * dt, k * dt
        for axis in range(3):
            w_ref = quad(
                lambda t, i=axis: demo.body_rates(np.array([t]))[0][0, i], a, b, epsabs=1e-17, epsrel=1e-13
            )[0]
            f_ref = quad(
                lambda t, i=axis: demo.body_rates(np.array([t]))[1][0, i], a, b, epsabs=1e-15, epsrel=1e-13
            )[0]
            assert abs(demo.dtheta_rad[k, axis] - w_ref) <= 1e-11 * abs(w_ref) + 1e-17, (k, axis)
            assert abs(demo.dvel_mps[k, axis] - f_ref) <= 1e-11 * abs(f_ref) + 1e-15, (k, axis)
    assert np.all(demo.dtheta_rad[0] == 0.0) and np.all(demo.dvel_mps[0] == 0.0)


def _mechanise_rk4(traj, h_s: float):
    """Continuous-time strapdown (quaternion, velocity, llh) driven by the true rates, RK4 at h_s.

    Returns max attitude (rad), velocity (m/s) and position (m) differences to the truth samples.
    """
    n_step = int(round(traj.duration_s / h_s))
    w_all, f_all = traj.body_rates(np.arange(2 * n_step + 1) * (0.5 * h_s))

    def deriv(q, v, llh, w_b, f_b):
        lat, hgt = llh[0], llh[2]
        r_m, r_n = earth.radii(lat)
        w_ie = earth.earth_rate_n(lat)
        w_en = earth.transport_rate_n(lat, hgt, v)
        # q_nb' = q_nb (x) w_ib^b / 2 - w_in^n (x) q_nb / 2
        q_dot = 0.5 * (
            earth.quat_mul(q, np.array([0.0, *w_b])) - earth.quat_mul(np.array([0.0, *(w_ie + w_en)]), q)
        )
        v_dot = (
            earth.quat_to_mat(q) @ f_b
            + np.array([0.0, 0.0, -earth.gravity_normal(lat, hgt)])
            - np.cross(2.0 * w_ie + w_en, v)
        )
        llh_dot = np.array([v[1] / (r_m + hgt), v[0] / ((r_n + hgt) * math.cos(lat)), v[2]])
        return q_dot, v_dot, llh_dot

    q = earth.mat_to_quat(earth.rpy_to_mat_nb(traj.rpy_rad[0]))
    v = traj.vel_enu_mps[0].copy()
    llh = traj.llh[0].copy()
    every = int(round(traj.imu_rate_hz * h_s))
    err_att = err_vel = err_pos = 0.0
    for i in range(n_step):
        j = 2 * i
        k1 = deriv(q, v, llh, w_all[j], f_all[j])
        k2 = deriv(
            q + 0.5 * h_s * k1[0], v + 0.5 * h_s * k1[1], llh + 0.5 * h_s * k1[2], w_all[j + 1], f_all[j + 1]
        )
        k3 = deriv(
            q + 0.5 * h_s * k2[0], v + 0.5 * h_s * k2[1], llh + 0.5 * h_s * k2[2], w_all[j + 1], f_all[j + 1]
        )
        k4 = deriv(q + h_s * k3[0], v + h_s * k3[1], llh + h_s * k3[2], w_all[j + 2], f_all[j + 2])
        q = q + h_s / 6.0 * (k1[0] + 2 * k2[0] + 2 * k3[0] + k4[0])
        q = q / np.linalg.norm(q)
        v = v + h_s / 6.0 * (k1[1] + 2 * k2[1] + 2 * k3[1] + k4[1])
        llh = llh + h_s / 6.0 * (k1[2] + 2 * k2[2] + 2 * k3[2] + k4[2])
        if (i + 1) % 25 == 0:
            k = (i + 1) * every
            d = earth.quat_to_mat(q) @ earth.rpy_to_mat_nb(traj.rpy_rad[k]).T
            err_att = max(err_att, float(np.abs(earth.quat_to_rotvec(earth.mat_to_quat(d))).max()))
            err_vel = max(err_vel, float(np.abs(v - traj.vel_enu_mps[k]).max()))
            dpos = earth.llh_delta_to_enu_m(llh - traj.llh[k], llh[0], llh[2])
            err_pos = max(err_pos, float(np.abs(dpos).max()))
    return err_att, err_vel, err_pos


def test_reintegrating_the_rates_reproduces_the_truth(demo):
    """Fine-step strapdown from omega_ib^b and f^b over the 300 s demo reproduces the truth.

    Expected sizes (RK4 at 20 ms, rounding): attitude ~1e-11 rad, velocity ~3e-8 m/s, position ~3e-6 m.
    """
    err_att, err_vel, err_pos = _mechanise_rk4(demo, 0.02)
    assert err_att < 1e-8
    assert err_vel < 1e-6
    assert err_pos < 1e-4


def test_coordinated_turn_and_level_flight_specific_force(demo):
    kin = demo.kinematics(np.array([10.0, 80.0]))  # straight, mid-turn (3 deg/s)
    w, f = demo.body_rates(np.array([10.0, 80.0]))
    g = earth.gravity_normal(demo.llh[1000, 0], demo.llh[1000, 2])
    # straight and level: f^b = [0, 0, g] up to Coriolis/transport terms (< 0.03 m/s^2)
    np.testing.assert_allclose(f[0], [0.0, 0.0, g], atol=0.03)
    # coordinated turn: no lateral specific force (an uncoordinated turn would have v*omega = 6.3 m/s^2)
    speed = float(np.linalg.norm(kin["vel"][1]))
    omega = math.radians(3.0)
    assert kin["rpy"][1, 0] == pytest.approx(
        math.atan(speed * omega / earth.gravity_normal(START.lat_deg * earth.DEG, 100.0)), abs=1e-3
    )
    assert abs(f[1, 0]) < 0.03
    assert f[1, 2] == pytest.approx(g / math.cos(kin["rpy"][1, 0]), rel=5e-3)
    # heading rate = turn rate (yaw west positive decreases in a right turn)
    assert kin["rpy_dot"][1, 2] == pytest.approx(-omega, rel=1e-12)


def test_segment_outcomes_and_smoothness():
    segs = [
        StraightSegment(kind="straight", duration_s=10.0),
        ClimbSegment(kind="climb", duration_s=30.0, climb_rate_mps=10.0, ramp_s=4.0),
        TurnSegment(kind="turn", duration_s=40.0, turn_rate_dps=3.0, ramp_s=5.0),
        AccelerateSegment(kind="accelerate", duration_s=20.0, accel_mps2=-1.5, ramp_s=2.0),
        ClimbSegment(kind="climb", duration_s=20.0, flight_path_deg=-3.0, ramp_s=3.0),
    ]
    tr = build_trajectory(START, segs, 100.0, T0, duration_s=130.0)
    assert tr.t_s.size == 13001 and tr.t_s[0] == T0 and tr.t_s[-1] == T0 + 130.0
    k = lambda t: int(round(t * 100))  # noqa: E731

    def climb_m(speed_mps, gamma_rad, dur_s, ramp_s):
        # pitch ramps as gamma * S(u): dh = v [sin(gamma) (D - 2T) + 2 int_0^T sin(gamma S(t/T)) dt]
        ramp = quad(
            lambda t: math.sin(gamma_rad * 0.5 * (1 - math.cos(math.pi * t / ramp_s))),
            0,
            ramp_s,
            epsabs=1e-14,
        )[0]
        return speed_mps * (math.sin(gamma_rad) * (dur_s - 2 * ramp_s) + 2 * ramp)

    # climb: 10 m/s at 120 m/s (about 10 m/s * (30 - 4) s = 260 m)
    assert tr.llh[k(40), 2] - tr.llh[k(10), 2] == pytest.approx(
        climb_m(120, math.asin(10 / 120), 30, 4), abs=1e-6
    )
    # turn: heading +3 deg/s for (40 - 5) s, yaw west positive
    assert tr.rpy_rad[k(80), 2] - tr.rpy_rad[k(40), 2] == pytest.approx(-math.radians(105.0), abs=1e-12)
    # accelerate: -1.5 m/s^2 for (20 - 2) s
    speed = np.linalg.norm(tr.vel_enu_mps, axis=1)
    assert speed[k(100)] - speed[k(80)] == pytest.approx(-27.0, abs=1e-9)
    # flight-path descent at -3 deg and 93 m/s, then level and padded straight
    assert tr.llh[k(120), 2] - tr.llh[k(100), 2] == pytest.approx(
        climb_m(93, math.radians(-3), 20, 3), abs=1e-6
    )
    assert np.all(np.abs(tr.rpy_rad[k(120) :, :2]) < 1e-15)
    assert np.all(np.abs(tr.vel_enu_mps[k(120) :, 2]) < 1e-12)
    # rates are continuous: consecutive increments differ by at most (peak angular acceleration, 0.12
    # rad/s^2 rolling in over 5 s) * dt^2 = 1.2e-5 rad, far below a 3 deg/s rate step (5.2e-4 rad);
    # likewise for dvel against a 1.5 m/s^2 acceleration step (0.015 m/s)
    assert np.abs(np.diff(tr.dtheta_rad[1:], axis=0)).max() < 2e-5
    assert np.abs(np.diff(tr.dvel_mps[1:], axis=0)).max() < 1e-3
    # horizontal position follows the velocity: mean velocity over 10 s of straight flight
    d_n = (tr.llh[k(10), 0] - tr.llh[0, 0]) * (earth.radii(tr.llh[0, 0])[0] + 100.0)
    assert d_n == pytest.approx(120.0 * math.cos(math.radians(45.0)) * 10.0, rel=1e-6)


def test_state_at_hits_samples_exactly_and_agrees_with_a_finer_build(demo):
    k = 12_300
    s = demo.state_at(float(demo.t_s[k]))
    assert np.array_equal(s.llh, demo.llh[k]) and np.array_equal(s.rpy_rad, demo.rpy_rad[k])
    assert np.array_equal(s.vel_enu_mps, demo.vel_enu_mps[k]) and s.t_s == demo.t_s[k]
    assert demo.index_of(T0 + 123.0) == k
    # half-step times: compare with the same trajectory built at 200 Hz (exact samples there). Relative
    # time: an absolute GPS time near 1.3e9 s only resolves 2.4e-7 s (~3e-5 m at 120 m/s).
    sc = load_scenario("demo_aircraft")
    fine = build_trajectory(sc.start, sc.segments, 200.0, T0, sc.duration_s)
    for j in (1, 4001, 13_001, 40_001, 59_999):
        st = demo.state_at_rel(j / 200.0)
        np.testing.assert_allclose(st.rpy_rad, fine.rpy_rad[j], atol=1e-12)
        np.testing.assert_allclose(st.vel_enu_mps, fine.vel_enu_mps[j], atol=1e-9)
        d = earth.llh_delta_to_enu_m(st.llh - fine.llh[j], fine.llh[j, 0], fine.llh[j, 2])
        assert np.abs(d).max() < 1e-6
    with pytest.raises(ValueError, match="outside the trajectory"):
        demo.state_at(T0 + 400.0)


def test_invalid_segments_are_rejected_with_the_segment_named():
    with pytest.raises(ValueError, match=r"segments\[1\] \(turn\)\.duration_s = 10.005 s is not a multiple"):
        build_trajectory(
            START,
            [
                StraightSegment(kind="straight", duration_s=10.0),
                TurnSegment(kind="turn", duration_s=10.005, turn_rate_dps=1.0, ramp_s=2.0),
            ],
            100.0,
            T0,
        )
    with pytest.raises(ValueError, match=r"segments\[0\] \(static\).*needs 0"):
        build_trajectory(START, [StaticSegment(kind="static", duration_s=10.0)], 100.0, T0)
    with pytest.raises(ValueError, match="longer than duration_s"):
        build_trajectory(
            START, [StraightSegment(kind="straight", duration_s=10.0)], 100.0, T0, duration_s=5.0
        )
    with pytest.raises(ValueError, match="at most half"):
        TurnSegment(kind="turn", duration_s=10.0, turn_rate_dps=1.0, ramp_s=6.0)
    with pytest.raises(ValueError, match="exactly one"):
        ClimbSegment(kind="climb", duration_s=10.0)
    # a vehicle at rest can turn on the spot, accelerate, then stop and rest again
    rest = StartSpec(lat_deg=0.0, lon_deg=0.0, height_m=0.0, heading_deg=0.0, speed_mps=0.0)
    tr = build_trajectory(
        rest,
        [
            StaticSegment(kind="static", duration_s=5.0),
            AccelerateSegment(kind="accelerate", duration_s=10.0, accel_mps2=1.0, ramp_s=5.0),
            AccelerateSegment(kind="accelerate", duration_s=10.0, accel_mps2=-1.0, ramp_s=5.0),
            StaticSegment(kind="static", duration_s=5.0),
        ],
        100.0,
        T0,
    )
    assert np.abs(tr.vel_enu_mps[-500:]).max() < 1e-12
    assert np.abs(tr.vel_enu_mps[:501]).max() == 0.0


def test_build_800_s_at_100_hz_is_fast():
    sc = load_scenario("seed000_fault_free")
    t = time.perf_counter()
    tr = sc.build_trajectory()
    elapsed = time.perf_counter() - t
    assert tr.t_s.size == 80_001
    assert elapsed < 5.0, f"build took {elapsed:.2f} s"


def test_builds_at_different_rates_agree(demo):
    """Two routes: 4 increments at 400 Hz sum to one at 100 Hz; positions agree to nanometres."""
    sc = load_scenario("demo_aircraft")
    fine = build_trajectory(sc.start, sc.segments, 400.0, T0, sc.duration_s)
    np.testing.assert_allclose(
        fine.dtheta_rad[1:].reshape(-1, 4, 3).sum(axis=1), demo.dtheta_rad[1:], atol=1e-15
    )
    np.testing.assert_allclose(fine.dvel_mps[1:].reshape(-1, 4, 3).sum(axis=1), demo.dvel_mps[1:], atol=1e-13)
    d_enu = earth.llh_delta_to_enu_m(fine.llh[::4] - demo.llh, demo.llh[0, 0], 0.0)
    assert np.abs(d_enu).max() < 1e-7  # measured ~4e-9 m over 800 s for seed000
    np.testing.assert_array_equal(fine.t_s[::4], demo.t_s)
