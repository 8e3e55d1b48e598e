"""Seed 002 (Zhu, Ma, Wang, Chen 2022) paper conditions and speed paths: the vibration displaces
the node (velocity-difference noise, matched by the nominal R of ``r_vel_vibration``), gusts scale
the flexure, and the hot-path helpers equal the generic ones bit for bit."""

from __future__ import annotations

import numpy as np

from fednav.service.config import TransferAlignmentConfig
from fednav.service.estimation import transfer_alignment as ta
from fednav.service.pipelines.transfer_alignment import bank_from_config, params_from_config
from fednav.simulators.wing import WingSimulation, turbulence_gain
from tests.test_seed002 import TURN, _true_w, short


def test_hot_path_helpers_are_bit_identical_to_the_generic_ones():
    rng = np.random.default_rng(7)
    for _ in range(50):
        v = rng.standard_normal(3) * 10.0 ** rng.integers(-8, 2)
        vb = rng.standard_normal((4, 3)) * 10.0 ** rng.integers(-8, 2)
        assert np.array_equal(ta._skew3(v), ta.skew(v))
        assert np.array_equal(ta._skew_b(vb), ta.skew(vb))
        assert np.array_equal(ta._cross_b(v, vb), np.cross(v, vb))


def test_vibration_displacement_noise_matches_the_nominal_velocity_R():
    """With only vibration (no IMU errors, calm air), the velocity-difference residual z_v - H x_true
    is the node's vibration velocity M v_dot: its rms per axis matches sqrt(R0) of r_vel_vibration
    (diag(M r_rate M'), the same calm-air rate rms) where that is above 1 mm/s."""
    sc = short(40.0, TURN + [{"kind": "straight", "duration_s": 10.0}], vibration_displacement=True)
    d = sc.model_dump()
    d["wing"] |= {"gyro_bias_dph": 0.0, "accel_bias_ug": 0.0, "arw_dpsh": 0.0, "vrw_ugpsHz": 0.0}
    d["imu"] |= {"gyro_bias_dph": (0, 0, 0), "accel_bias_ug": (0, 0, 0), "arw_dpsh": 0.0, "vrw_ugpsHz": 0.0}
    from fednav.simulators.scenario import parse_scenario

    sc = parse_scenario(d)
    sim = WingSimulation(sc, seed=3)
    cfg = TransferAlignmentConfig(name="x", r_vel_vibration=True)
    p = params_from_config(cfg)
    bank = bank_from_config(cfg)
    bank.T = 1e9
    bank.C_ms = np.stack([n.C_ms[0] for n in sim.nodes])
    bank.V = _true_w(sim, 0) + np.stack([p.M[j] @ _vib_rate(n, 0) for j, n in enumerate(sim.nodes)])
    dth_m, dv_m = sim.master._dth, sim.master._dv
    res = []
    for k in range(1, dth_m.shape[0]):
        bank.push(
            dth_m[k],
            dv_m[k],
            [n.dtheta_rad[k] for n in sim.nodes],
            [n.dvel_mps[k] for n in sim.nodes],
            0.01,
            k / 100,
        )
        if k % 10 != 5:
            continue
        x = np.zeros((3, ta.N_STATES))
        for j, n in enumerate(sim.nodes):
            x[j, ta.THD] = n.theta_dot_rps[k]
            x[j, ta.DR] = n.lever_arm_m[k] - n.lever_arm_nom_m
        H = ta.measurement_matrix(bank._last_rates[2], p)
        res.append((bank.measurements() - np.einsum("bij,bj->bi", H, x))[:, 3:6])
    rms = np.sqrt(np.mean(np.square(res), axis=0))  # (B, 3)
    sig = np.sqrt(p.R0[:, 3:6])
    big = sig > 1e-3
    assert big.sum() >= 6
    ratio = rms[big] / sig[big]
    assert np.all((ratio > 0.75) & (ratio < 1.3)), ratio
    # without the displacement the same flight has no such noise (the old simulator)
    assert np.all(
        sig[big] > 5 * np.sqrt(params_from_config(TransferAlignmentConfig(name="y")).R0[:, 3:6])[big]
    )


def _vib_rate(n, k: int) -> np.ndarray:
    """Vibration angle rate of a node at sample k (central difference of the simulated angle)."""
    return (n.vibration_rad[k + 1] - n.vibration_rad[k]) / 0.01


def test_turbulence_scales_the_flexure_by_its_gain():
    sc = short(120.0, [{"kind": "straight", "duration_s": 120.0}], turbulence=[(60.0, 120.0)])
    d = sc.model_dump()
    d["wing"] |= {"turbulence_flexure_gain": 2.0}
    from fednav.simulators.scenario import parse_scenario

    sc = parse_scenario(d)
    g = turbulence_gain(np.arange(12001) * 0.01, sc.wing, gain=2.0)
    assert g[0] == 1.0 and g[9000] == 2.0
    ratios = []
    for seed in (1, 2):
        for n in WingSimulation(sc, seed=seed).nodes:
            calm = n.theta_rad[500:5800].std(axis=0)
            gust = n.theta_rad[6300:11900].std(axis=0)
            ratios.append(gust / calm)
    assert 1.6 < np.mean(ratios) < 2.5, np.mean(ratios)
