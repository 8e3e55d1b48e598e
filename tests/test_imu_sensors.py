"""IMU error model and aiding sensors (GNSS fix, star tracker): statistics, timing, faults."""

from __future__ import annotations

import math

import numpy as np
import pytest
from pydantic import ValidationError

from fednav.service import earth
from fednav.simulators.faults import FaultSet
from fednav.simulators.imu import ImuSpec, apply_imu_errors
from fednav.simulators.sensors import GnssSpec, StarSpec, simulate_gnss_fixes, simulate_star
from fednav.simulators.trajectory import StartSpec, StraightSegment, TurnSegment, build_trajectory

T0 = 1_300_000_000.0


@pytest.fixture(scope="module")
def traj():
    start = StartSpec(lat_deg=40.1, lon_deg=118.6, height_m=500.0, heading_deg=10.0, speed_mps=100.0)
    segs = [
        StraightSegment(kind="straight", duration_s=50.0),
        TurnSegment(kind="turn", duration_s=100.0, turn_rate_dps=2.0, ramp_s=5.0),
    ]
    return build_trajectory(start, segs, 100.0, T0, duration_s=200.0)


# --- IMU ------------------------------------------------------------------------------------------
def test_perfect_imu_passes_increments_through(traj):
    dth, dv, truth = apply_imu_errors(ImuSpec(), traj.dtheta_rad, traj.dvel_mps, np.random.default_rng(1))
    assert np.array_equal(dth, traj.dtheta_rad) and np.array_equal(dv, traj.dvel_mps)
    assert np.all(truth.gyro_bias_rps == 0.0) and np.all(truth.accel_markov_mps2 == 0.0)


def test_fixed_bias_and_scale_factor_are_applied_exactly(traj):
    spec = ImuSpec(
        bias_mode="fixed",
        gyro_bias_dph=(0.01, -0.02, 0.03),
        accel_bias_ug=(100.0, -50.0, 20.0),
        gyro_scale_ppm=(100.0, 0.0, -50.0),
        accel_scale_ppm=(0.0, 200.0, 0.0),
    )
    dth, dv, truth = apply_imu_errors(spec, traj.dtheta_rad, traj.dvel_mps, np.random.default_rng(1))
    dt = 0.01
    b_g = np.array([0.01, -0.02, 0.03]) * earth.DPH
    b_a = np.array([100.0, -50.0, 20.0]) * earth.UG
    np.testing.assert_allclose(
        dth[1:], traj.dtheta_rad[1:] * (1 + np.array([1e-4, 0, -5e-5])) + b_g * dt, rtol=0, atol=1e-18
    )
    np.testing.assert_allclose(
        dv[1:], traj.dvel_mps[1:] * (1 + np.array([0, 2e-4, 0])) + b_a * dt, rtol=0, atol=1e-15
    )
    np.testing.assert_allclose(truth.gyro_bias_dph, [0.01, -0.02, 0.03], rtol=1e-12)
    np.testing.assert_allclose(truth.accel_bias_ug, [100.0, -50.0, 20.0], rtol=1e-12)
    assert np.all(dth[0] == 0.0) and np.all(dv[0] == 0.0)


def test_random_biases_have_the_stated_sigma():
    spec = ImuSpec(gyro_bias_dph=(0.01, 0.02, 0.03), accel_bias_ug=(100.0, 100.0, 50.0))
    z = np.zeros((2, 3))
    rng = np.random.default_rng(7)
    draws = [apply_imu_errors(spec, z, z, rng)[2] for _ in range(4000)]
    g = np.array([d.gyro_bias_dph for d in draws])
    a = np.array([d.accel_bias_ug for d in draws])
    # std of a sample std over 4000 draws: 1.1 %; 5 % tolerance
    np.testing.assert_allclose(g.std(axis=0), [0.01, 0.02, 0.03], rtol=0.05)
    np.testing.assert_allclose(a.std(axis=0), [100.0, 100.0, 50.0], rtol=0.05)
    np.testing.assert_allclose(g.mean(axis=0) / [0.01, 0.02, 0.03], 0.0, atol=0.06)  # 4 sigma of the mean


def test_random_walks_have_the_stated_density():
    spec = ImuSpec(arw_dpsh=0.001, vrw_ugpsHz=5.0, rate_hz=100.0)
    n = 40_000
    z = np.zeros((n, 3))
    dth, dv, _ = apply_imu_errors(spec, z, z, np.random.default_rng(3))
    # increments' std = density * sqrt(dt); sample std over 120k numbers: 0.2 % error; 2 % tolerance
    assert dth[1:].std() == pytest.approx(0.001 * earth.DEG / 60.0 * math.sqrt(0.01), rel=0.02)
    assert dv[1:].std() == pytest.approx(5.0 * earth.UG * math.sqrt(0.01), rel=0.02)
    assert abs(dth[1:].mean()) < 4 * dth[1:].std() / math.sqrt(3 * n)


def test_bias_instability_is_a_stationary_gauss_markov_process():
    spec = ImuSpec(
        gyro_bias_instability_dph=0.05,
        gyro_bias_tau_s=0.2,
        accel_bias_instability_ug=30.0,
        accel_bias_tau_s=0.2,
    )
    n = 100_000
    z = np.zeros((n, 3))
    _, dv, truth = apply_imu_errors(spec, z, z, np.random.default_rng(11))
    m = truth.gyro_markov_rps / earth.DPH
    # ~ n dt / (2 tau) = 2500 independent samples per axis: std error ~1.5 %; 6 % tolerance
    np.testing.assert_allclose(m.std(axis=0), 0.05, rtol=0.06)
    lag1 = np.mean(m[1:] * m[:-1], axis=0) / np.mean(m * m, axis=0)
    np.testing.assert_allclose(lag1, math.exp(-0.01 / 0.2), atol=0.01)
    # the accelerometer increments carry the Markov bias times dt
    np.testing.assert_allclose(dv[1:], truth.accel_markov_mps2[1:] * 0.01, atol=1e-18)


def test_imu_errors_are_reproducible_per_seed(traj):
    spec = ImuSpec(gyro_bias_dph=(0.01,) * 3, accel_bias_ug=(50.0,) * 3, arw_dpsh=0.001, vrw_ugpsHz=5.0)
    a = apply_imu_errors(spec, traj.dtheta_rad, traj.dvel_mps, np.random.default_rng(5))
    b = apply_imu_errors(spec, traj.dtheta_rad, traj.dvel_mps, np.random.default_rng(5))
    c = apply_imu_errors(spec, traj.dtheta_rad, traj.dvel_mps, np.random.default_rng(6))
    assert np.array_equal(a[0], b[0]) and np.array_equal(a[1], b[1])
    assert not np.array_equal(a[0], c[0])


def test_imu_spec_validation_names_the_field():
    with pytest.raises(ValidationError, match="gyro_bias_dph: sigmas must be >= 0"):
        ImuSpec(gyro_bias_dph=(-0.01, 0.0, 0.0))
    ImuSpec(bias_mode="fixed", gyro_bias_dph=(-0.01, 0.0, 0.0))  # a fixed bias may be negative
    with pytest.raises(ValidationError, match="arw_dpsh"):
        ImuSpec(arw_dpsh=-1.0)
    with pytest.raises(ValidationError, match="accel_bias_ug"):
        ImuSpec(accel_bias_ug=(1.0, 2.0))
    with pytest.raises(ValidationError, match="extra_forbidden"):
        ImuSpec(gyro_bias=0.1)


# --- GNSS -----------------------------------------------------------------------------------------
def _enu_error(traj, k: int, msg) -> np.ndarray:
    lat, lon, h = traj.llh[k]
    d = np.array(
        [math.radians(msg.lat_deg) - lat, earth.wrap_pi(math.radians(msg.lon_deg) - lon), msg.height_m - h]
    )
    return earth.llh_delta_to_enu_m(d, lat, h)


def test_gnss_epochs_coincide_with_imu_samples_and_respect_outages(traj):
    spec = GnssSpec(
        rate_hz=1.0,
        pos_std_enu_m=(3.0, 3.0, 5.0),
        vel_std_enu_mps=(0.1, 0.1, 0.2),
        constellation="BDS",
        outages=[(20.0, 30.5), (100.0, 101.0)],
    )
    fixes = simulate_gnss_fixes(spec, traj, np.random.default_rng(2))
    ks = [k for k, _ in fixes]
    t_rel = [k / 100 for k in ks]
    assert t_rel == [float(t) for t in range(1, 201) if not (20 <= t < 30.5 or 100 <= t < 101)]
    for k, m in fixes:
        assert m.t == traj.t_s[k] and traj.index_of(m.t) == k  # bit-identical sample times
        assert m.constellation == "BDS" and m.pos_std_enu_m == (3.0, 3.0, 5.0)
    # an outage does not change the other epochs' noise
    no_out = dict(
        simulate_gnss_fixes(spec.model_copy(update={"outages": []}), traj, np.random.default_rng(2))
    )
    assert all(no_out[k] == m for k, m in fixes)


def test_gnss_noise_statistics(traj):
    spec = GnssSpec(rate_hz=20.0, pos_std_enu_m=(3.0, 4.0, 6.0), vel_std_enu_mps=(0.1, 0.05, 0.2))
    fixes = simulate_gnss_fixes(spec, traj, np.random.default_rng(4))
    assert len(fixes) == 4000
    pos = np.array([_enu_error(traj, k, m) for k, m in fixes])
    vel = np.array([np.subtract(m.vel_enu_mps, traj.vel_enu_mps[k]) for k, m in fixes])
    # 4000 samples: std error 1.1 %, mean error 1.6 % of sigma; tolerances 5 % and 6.5 %
    np.testing.assert_allclose(pos.std(axis=0), [3.0, 4.0, 6.0], rtol=0.05)
    np.testing.assert_allclose(vel.std(axis=0), [0.1, 0.05, 0.2], rtol=0.05)
    np.testing.assert_allclose(pos.mean(axis=0) / [3.0, 4.0, 6.0], 0.0, atol=0.065)
    np.testing.assert_allclose(vel.mean(axis=0) / [0.1, 0.05, 0.2], 0.0, atol=0.065)


def test_gnss_faults_offset_the_named_channels(traj):
    spec = GnssSpec(pos_std_enu_m=(1e-6,) * 3, vel_std_enu_mps=(1e-6,) * 3)
    faults = FaultSet(
        [
            dict(
                sensor="gnss",
                kind="step",
                start_s=10.0,
                duration_s=5.0,
                channels=["pos_n", "vel_u"],
                magnitude=[100.0, 2.0],
            ),
            dict(sensor="gnss", kind="scale", start_s=12.0, duration_s=1.0, channels=["vel_e"], factor=[1.5]),
        ],
        np.random.default_rng(0),
    )
    fixes = dict(simulate_gnss_fixes(spec, traj, np.random.default_rng(1), faults))
    for t in range(1, 30):
        k = t * 100
        e = _enu_error(traj, k, fixes[k])
        dv = np.subtract(fixes[k].vel_enu_mps, traj.vel_enu_mps[k])
        on = 10 <= t < 15
        np.testing.assert_allclose(e, [0.0, 100.0 if on else 0.0, 0.0], atol=1e-5)
        expect_ve = traj.vel_enu_mps[k, 0] * (0.5 if t == 12 else 0.0)
        np.testing.assert_allclose(dv, [expect_ve, 0.0, 2.0 if on else 0.0], atol=1e-5)


def test_gnss_spec_validation():
    with pytest.raises(ValidationError, match=r"pos_std_enu_m: every component must be > 0"):
        GnssSpec(pos_std_enu_m=(1.0, 0.0, 1.0), vel_std_enu_mps=(0.1, 0.1, 0.1))
    with pytest.raises(ValidationError, match=r"outages\[0\]"):
        GnssSpec(pos_std_enu_m=(1.0,) * 3, vel_std_enu_mps=(0.1,) * 3, outages=[(5.0, 4.0)])
    with pytest.raises(ValidationError, match="constellation"):
        GnssSpec(pos_std_enu_m=(1.0,) * 3, vel_std_enu_mps=(0.1,) * 3, constellation="GAL")


def test_sensor_rate_must_divide_the_imu_rate(traj):
    spec = GnssSpec(rate_hz=3.0, pos_std_enu_m=(1.0,) * 3, vel_std_enu_mps=(0.1,) * 3)
    with pytest.raises(ValueError, match="must divide the IMU rate"):
        simulate_gnss_fixes(spec, traj, np.random.default_rng(0))


# --- star tracker ---------------------------------------------------------------------------------
def test_star_noise_statistics_and_heading_convention(traj):
    fixes = simulate_star(
        StarSpec(rate_hz=20.0, std_arcsec=(10.0, 20.0, 30.0)), traj, np.random.default_rng(9)
    )
    assert len(fixes) == 4000
    err = []
    for k, m in fixes:
        assert m.t == traj.t_s[k] and m.rpy_std_deg == pytest.approx((10 / 3600, 20 / 3600, 30 / 3600))
        true_deg = earth.rpy_msg_deg(traj.rpy_rad[k])
        d = np.subtract(m.rpy_deg, true_deg)
        d[2] = (d[2] + 180.0) % 360.0 - 180.0
        err.append(d * 3600.0)
    err = np.array(err)
    # small body rotations: Euler errors have the stated stds (4000 samples: 1.1 %; 5 % tolerance)
    np.testing.assert_allclose(err.std(axis=0), [10.0, 20.0, 30.0], rtol=0.05)
    np.testing.assert_allclose(err.mean(axis=0) / [10.0, 20.0, 30.0], 0.0, atol=0.065)


def test_star_faults_are_in_arcsec_and_yaw_is_west_positive(traj):
    faults = FaultSet(
        [
            dict(
                sensor="star",
                kind="step",
                start_s=5.0,
                duration_s=3.0,
                channels=["roll", "yaw"],
                magnitude=[36.0, 72.0],
            )
        ],
        np.random.default_rng(0),
    )
    fixes = dict(simulate_star(StarSpec(std_arcsec=(1e-6,) * 3), traj, np.random.default_rng(1), faults))
    for t in (4, 5, 7, 8):
        k = t * 100
        true_deg = earth.rpy_msg_deg(traj.rpy_rad[k])
        d = np.subtract(fixes[k].rpy_deg, true_deg)
        on = 5 <= t < 8
        # +36" roll -> +0.01 deg roll; +72" yaw (west positive) -> -0.02 deg heading
        np.testing.assert_allclose(d, [0.01 if on else 0.0, 0.0, -0.02 if on else 0.0], atol=1e-8)
