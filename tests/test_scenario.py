"""Scenario files (loading, validation) and the message stream of a run."""

from __future__ import annotations

import math
import time
from collections import Counter

import numpy as np
import pytest

from fednav.service import earth, keys
from fednav.service.messages import GnssFix, ImuSample, InitialNav, StarAttitude, Truth
from fednav.simulators.scenario import SCENARIO_DIR, ScenarioError, load_scenario, parse_scenario
from fednav.simulators.stream import simulate

MIN_SCENARIO = {
    "name": "t",
    "duration_s": 20.0,
    "start": {"lat_deg": 30.0, "lon_deg": 100.0, "height_m": 50.0, "heading_deg": 90.0, "speed_mps": 50.0},
    "segments": [{"kind": "turn", "duration_s": 10.0, "turn_rate_dps": 3.0, "ramp_s": 2.0}],
    "gnss": {"pos_std_enu_m": [5.0, 5.0, 8.0], "vel_std_enu_mps": [0.1, 0.1, 0.1]},
    "star": {"std_arcsec": [10.0, 10.0, 10.0], "rate_hz": 2.0},
}


def _with(**kw) -> dict:
    d = {k: (dict(v) if isinstance(v, dict) else v) for k, v in MIN_SCENARIO.items()}
    d.update(kw)
    return d


@pytest.fixture(scope="module")
def demo():
    sc = load_scenario("demo_aircraft")
    return sc, sc.build_trajectory()


@pytest.fixture(scope="module")
def faulty():
    sc = load_scenario("seed000_faults")
    return sc, sc.build_trajectory()


# --- loading --------------------------------------------------------------------------------------
def test_shipped_scenarios_load():
    names = sorted(p.stem for p in SCENARIO_DIR.glob("*.toml"))
    assert {"demo_aircraft", "seed000_fault_free", "seed000_faults"} <= set(names)
    for n in names:
        sc = load_scenario(n)
        assert sc.name == n
    demo = load_scenario(SCENARIO_DIR / "demo_aircraft.toml")
    assert demo.service["pipelines"] == [{"name": "lc", "kind": "loosely_coupled"}]
    for n in ("demo_aircraft", "seed000_fault_free", "seed000_faults"):
        sc = load_scenario(n)  # the filter's process model is the simulated IMU grade
        imu = sc.service["imu"]
        assert imu["gyro_bias_dph"] == sc.imu.gyro_bias_dph[0]
        assert imu["accel_bias_ug"] == sc.imu.accel_bias_ug[0]
        assert imu["arw_dpsh"] == sc.imu.arw_dpsh and imu["vrw_ugpsHz"] == sc.imu.vrw_ugpsHz
    assert demo.imu.gyro_bias_dph == (0.01,) * 3 and demo.imu.arw_dpsh == 0.001
    assert demo.imu.accel_bias_ug == (50.0,) * 3 and demo.imu.vrw_ugpsHz == 5.0
    assert demo.gnss.pos_std_enu_m == (10.0,) * 3 and demo.gnss.vel_std_enu_mps == (0.1,) * 3


def test_seed000_scenarios_carry_the_paper_parameters():
    ff, fa = load_scenario("seed000_fault_free"), load_scenario("seed000_faults")
    for sc in (ff, fa):
        assert (sc.start.lat_deg, sc.start.lon_deg, sc.start.height_m) == (40.10021, 118.60212, 100.0)
        assert sc.duration_s == 800.0 and sc.imu.rate_hz == 100.0 and sc.imu.bias_mode == "random"
        assert sc.imu.gyro_bias_dph == (0.01,) * 3 and sc.imu.accel_bias_ug == (100.0,) * 3
        assert sc.star.std_arcsec == (10.0,) * 3 and sc.star.rate_hz == 1.0
        assert sc.gnss.constellation == "BDS" and sc.gnss.pos_std_enu_m == (10.0,) * 3
        assert sc.gnss.vel_std_enu_mps == (0.1,) * 3 and sc.gnss.rate_hz == 1.0
        ie = sc.initial_errors
        assert (
            ie.pos_enu_m == (9.0, 6.0, 1.0) and ie.vel_enu_mps == (0.05,) * 3 and ie.rpy_arcsec == (10.0,) * 3
        )
        names = [p["name"] for p in sc.service["pipelines"]]
        assert names[:5] == ["fed_fixed", "fed_scalar", "fed_vector", "fed_vector_sysiso", "centralized"]
        assert names[5:] == ["fed_vector_perstate", "fed_vector_cons"]  # comparison variants
        sharing = {p["name"]: p.get("sharing") for p in sc.service["pipelines"]}
        assert sharing["fed_vector"] == sharing["fed_vector_sysiso"] == "vector_eigen"
        assert sharing["fed_vector_perstate"] == "vector"
    assert ff.faults == []
    sched = [(f.start_s, f.duration_s, dict(zip(f.channels, f.magnitude, strict=True))) for f in fa.faults]
    assert sched == [
        (
            300.0,
            10.0,
            {"pos_n": 100.0, "pos_e": 95.0, "pos_u": 90.0, "vel_e": 2.5, "vel_n": 2.0, "vel_u": 2.3},
        ),
        (450.0, 50.0, {"vel_e": 3.0, "vel_n": 3.0, "vel_u": 3.0}),
        (
            600.0,
            20.0,
            {"pos_n": 110.0, "pos_e": 100.0, "pos_u": 110.0, "vel_e": 3.0, "vel_n": 3.2, "vel_u": 2.8},
        ),
    ]
    assert all(f.sensor == "gnss" and f.kind == "step" for f in fa.faults)


def test_segments_are_padded_to_the_duration(demo):
    sc, tr = demo
    assert sum(s.duration_s for s in sc.segments) < sc.duration_s
    assert tr.t_s.size == 30_001 and tr.duration_s == pytest.approx(300.0, abs=1e-12)
    # after the last turn (ends at 286 s): straight and level
    tail = tr.kinematics(np.arange(286.0, 300.0, 0.5))
    assert np.abs(tail["rpy_dot"]).max() < 1e-15 and np.abs(tail["acc"]).max() < 1e-12


@pytest.mark.parametrize(
    "change, message",
    [
        ({"gnss": {"pos_std_enu_m": [5.0, 5.0], "vel_std_enu_mps": [0.1] * 3}}, r"gnss\.pos_std_enu_m"),
        (
            {"gnss": {"pos_std_enu_m": [5.0] * 3, "vel_std_enu_mps": [0.1] * 3, "rate": 1}},
            r"gnss\.rate: unknown field",
        ),
        ({"duration_s": -1.0}, r"duration_s: Input should be greater than 0"),
        (
            {"segments": [{"kind": "turn", "duration_s": 10.001, "turn_rate_dps": 1.0}]},
            r"segments\[0\] \(turn\)\.duration_s = 10.001 s is not a multiple",
        ),
        (
            {"segments": [{"kind": "loop", "duration_s": 10.0}]},
            r"segments\.0: unknown kind 'loop'",
        ),
        (
            {"segments": [{"kind": "climb", "duration_s": 10.0, "climb_rate_mps": "fast"}]},
            r"segments\.0\.climb\.climb_rate_mps",
        ),
        ({"segments": [{"kind": "straight", "duration_s": 30.0}]}, r"longer than duration_s"),
        (
            {"star": {"std_arcsec": [10.0] * 3, "rate_hz": 3.0}},
            r"star\.rate_hz = 3.0 Hz must divide the IMU rate",
        ),
        ({"truth_rate_hz": 7.0}, r"truth_rate_hz = 7.0 Hz must divide"),
        (
            {
                "faults": [
                    {
                        "sensor": "dvl",
                        "kind": "step",
                        "start_s": 1.0,
                        "duration_s": 1.0,
                        "channels": ["v"],
                        "magnitude": [1.0],
                    }
                ]
            },
            r"faults\[0\]\.sensor = 'dvl': no such sensor",
        ),
        (
            {
                "faults": [
                    {
                        "sensor": "gnss",
                        "kind": "step",
                        "start_s": 1.0,
                        "duration_s": 1.0,
                        "channels": ["pos_x"],
                        "magnitude": [1.0],
                    }
                ]
            },
            r"faults\[0\]\.channels: \['pos_x'\] unknown for gnss",
        ),
        (
            {
                "faults": [
                    {
                        "sensor": "star",
                        "kind": "step",
                        "start_s": 1.0,
                        "duration_s": 1.0,
                        "channels": ["roll"],
                        "magnitude": [1.0, 2.0],
                    }
                ]
            },
            r"faults\.0\.step: .*magnitude has 2 values",
        ),
        (
            {"initial_errors": {"mode": "random", "pos_enu_m": [1.0, -1.0, 1.0]}},
            r"initial_errors\.pos_enu_m: sigmas must be >= 0",
        ),
        (
            {"imu": {"rate_hz": 100.0, "vrw_ug": 3.0}},
            r"imu\.vrw_ug: unknown field \(did you mean 'vrw_ugpsHz'\?\)",
        ),
    ],
)
def test_validation_errors_name_the_field(change, message):
    with pytest.raises(ScenarioError, match=message):
        parse_scenario(_with(**change))


def test_toml_file_errors_name_the_file(tmp_path):
    p = tmp_path / "bad.toml"
    p.write_text('name = "x"\nduration_s = 10\n')
    with pytest.raises(ScenarioError, match=r"bad\.toml:\n  start: Field required"):
        load_scenario(p)
    p.write_text("name = \n")
    with pytest.raises(ScenarioError, match="invalid TOML"):
        load_scenario(p)


# --- stream ---------------------------------------------------------------------------------------
def test_demo_stream_order_keys_and_messages(demo):
    sc, tr = demo
    t = time.perf_counter()
    sim = simulate(sc, 3, vehicle="v7", trajectory=tr)
    msgs = list(sim)
    elapsed = time.perf_counter() - t
    assert elapsed < 10.0, f"stream took {elapsed:.2f} s"
    kinds = Counter(type(m).__name__ for _, m in msgs)
    assert kinds == {"InitialNav": 1, "Truth": 3001, "ImuSample": 30_000, "GnssFix": 300}
    assert isinstance(msgs[0][1], InitialNav) and msgs[0][0] == keys.init("v7")
    assert isinstance(msgs[1][1], Truth) and msgs[1][1].t == sc.t0_gps_s
    expected_key = {
        ImuSample: keys.sensor("v7", "imu", "main"),
        GnssFix: keys.sensor("v7", "gnss_fix", "main"),
        Truth: keys.truth("v7"),
        InitialNav: keys.init("v7"),
    }
    last_t = -1.0
    prev = None
    for key, m in msgs:
        assert key == expected_key[type(m)]
        assert m.t >= last_t
        if m.t > last_t and last_t > sc.t0_gps_s:  # each instant after t0 ends with its IMU sample
            assert isinstance(prev, ImuSample) and prev.t == last_t
        last_t = m.t
        prev = m
    # every message round-trips through JSON validation; fields are plain floats
    for _, m in msgs[:50] + msgs[-50:]:
        assert type(m).model_validate_json(m.to_json()) == m
        assert all(type(x) is float for x in getattr(m, "dtheta_rad", ()) + getattr(m, "vel_enu_mps", ()))
        assert type(m.t) is float
    imu = [m for _, m in msgs if isinstance(m, ImuSample)]
    assert imu[0].dt_s == 0.01 and imu[-1].t == tr.t_s[-1]
    assert [m.t for m in imu] == tr.t_s[1:].tolist()
    gnss_t = [m.t for _, m in msgs if isinstance(m, GnssFix)]
    assert gnss_t == tr.t_s[100::100].tolist()
    assert sim.truth.imu_errors.gyro_bias_dph.shape == (3,) and sim.truth.seed == 3


def test_noise_free_stream_carries_the_exact_increments_and_truth():
    sc = parse_scenario(_with(imu={"rate_hz": 100.0}, truth_rate_hz=100.0))
    sim = simulate(sc, 1)
    tr = sim.trajectory
    imu = [m for _, m in sim if isinstance(m, ImuSample)]
    np.testing.assert_array_equal(np.array([m.dtheta_rad for m in imu]), tr.dtheta_rad[1:])
    np.testing.assert_array_equal(np.array([m.dvel_mps for m in imu]), tr.dvel_mps[1:])
    truth = [m for _, m in simulate(sc, 1) if isinstance(m, Truth)]
    assert len(truth) == tr.t_s.size
    k = 1234
    assert truth[k].lat_deg == math.degrees(tr.llh[k, 0]) and truth[k].height_m == tr.llh[k, 2]
    np.testing.assert_allclose(truth[k].rpy_deg, earth.rpy_msg_deg(tr.rpy_rad[k]), atol=1e-12)
    star = [m for _, m in simulate(sc, 1) if isinstance(m, StarAttitude)]
    assert len(star) == 40 and star[0].t == tr.t_s[50]


def test_initial_nav_fixed_and_random_errors():
    ie = {
        "mode": "fixed",
        "pos_enu_m": [3.0, -4.0, 2.0],
        "vel_enu_mps": [0.1, 0.0, -0.2],
        "rpy_arcsec": [36.0, -72.0, 360.0],
    }
    sc = parse_scenario(_with(initial_errors=ie))
    sim = simulate(sc, 1)
    init, tr = sim.initial_nav, sim.trajectory
    d = np.array(
        [
            math.radians(init.lat_deg) - tr.llh[0, 0],
            math.radians(init.lon_deg) - tr.llh[0, 1],
            init.height_m - tr.llh[0, 2],
        ]
    )
    np.testing.assert_allclose(
        earth.llh_delta_to_enu_m(d, tr.llh[0, 0], tr.llh[0, 2]), [3.0, -4.0, 2.0], atol=1e-6
    )
    np.testing.assert_allclose(np.subtract(init.vel_enu_mps, tr.vel_enu_mps[0]), [0.1, 0.0, -0.2], atol=1e-12)
    # roll +0.01 deg, pitch -0.02 deg, yaw +0.1 deg (west positive) -> heading -0.1 deg
    np.testing.assert_allclose(
        np.subtract(init.rpy_deg, earth.rpy_msg_deg(tr.rpy_rad[0])), [0.01, -0.02, -0.1], atol=1e-10
    )
    assert init.pos_std_enu_m == (3.0, 4.0, 2.0)
    assert init.vel_std_enu_mps == (0.1, 1e-3, 0.2)  # zero sigma -> 1e-3 floor
    np.testing.assert_allclose(init.rpy_std_deg, [0.01, 0.02, 0.1], rtol=1e-12)
    # random mode: per-run draws with the stated sigmas, recorded in the truth
    sc = parse_scenario(
        _with(
            initial_errors={
                "mode": "random",
                "pos_enu_m": [9.0, 6.0, 1.0],
                "vel_enu_mps": [0.05] * 3,
                "rpy_arcsec": [10.0] * 3,
            }
        )
    )
    tr = sc.build_trajectory()
    errs = np.array([simulate(sc, s, trajectory=tr).truth.initial_pos_error_enu_m for s in range(400)])
    np.testing.assert_allclose(errs.std(axis=0), [9.0, 6.0, 1.0], rtol=0.12)  # 400 draws: 3.5 % std error
    s0 = simulate(sc, 0, trajectory=tr)
    assert s0.initial_nav.pos_std_enu_m == (9.0, 6.0, 1.0)
    assert s0.initial_nav.rpy_std_deg == pytest.approx((10 / 3600,) * 3)


def test_runs_are_reproducible_and_share_a_trajectory(demo):
    sc, tr = demo
    head = lambda sim: [m for _, m in zip(range(3000), sim, strict=False)]  # noqa: E731
    a, b = head(simulate(sc, 11, trajectory=tr)), head(simulate(sc, 11))
    assert a == b
    assert head(simulate(sc, 12, trajectory=tr)) != a
    other = load_scenario("seed000_fault_free").build_trajectory()
    with pytest.raises(ValueError, match="does not match the scenario"):
        simulate(sc, 1, trajectory=other)


def test_seed000_faults_reach_the_gnss_fixes_and_the_truth(faulty):
    sc, tr = faulty
    sim = simulate(sc, 5, trajectory=tr)
    gnss, truth = {}, {}
    for _, m in sim:
        if isinstance(m, GnssFix):
            gnss[round(m.t - sc.t0_gps_s, 6)] = m
        elif isinstance(m, Truth):
            truth[round(m.t - sc.t0_gps_s, 6)] = m
    assert len(gnss) == 800 and len(truth) == 8001

    def errors(t_rel: float):
        k = int(round(t_rel * 100))
        m = gnss[t_rel]
        d = np.array(
            [
                math.radians(m.lat_deg) - tr.llh[k, 0],
                math.radians(m.lon_deg) - tr.llh[k, 1],
                m.height_m - tr.llh[k, 2],
            ]
        )
        return earth.llh_delta_to_enu_m(d, tr.llh[k, 0], tr.llh[k, 2]), np.subtract(
            m.vel_enu_mps, tr.vel_enu_mps[k]
        )

    windows = [
        (300, 310, [95.0, 100.0, 90.0], [2.5, 2.0, 2.3]),
        (450, 500, [0.0] * 3, [3.0] * 3),
        (600, 620, [100.0, 110.0, 110.0], [3.0, 3.2, 2.8]),
    ]
    for t in range(1, 801):
        pos_off, vel_off = [0.0] * 3, [0.0] * 3
        for a, b, p, v in windows:
            if a <= t < b:
                pos_off, vel_off = p, v
        dp, dv = errors(float(t))
        # 5-sigma bounds on the noise (10 m, 0.1 m/s) around the scheduled offsets (E, N, U)
        assert np.all(np.abs(dp - pos_off) < 50.0), t
        assert np.all(np.abs(dv - vel_off) < 0.5), t
        active = truth[float(t)].faults
        assert (len(active) == 1) == any(a <= t < b for a, b, _, _ in windows), t
    assert truth[455.0].faults[0].channels == ["vel_e", "vel_n", "vel_u"]
    assert truth[449.9].faults == [] and truth[500.0].faults == []
