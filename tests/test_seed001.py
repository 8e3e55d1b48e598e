"""Seed 001 (BDS/SINS tightly coupled MHSS integrity): scenarios, raw-GNSS stream, eval integrity.

Short variants of ``seed001_ramp`` / ``seed001_montecarlo`` run through ``fednav-sim eval``'s
in-process path (``simulators.evaluate.evaluate``). Figures of the full scenarios are in
docs/seed001.md (they take minutes; see the commands there).
"""

from __future__ import annotations

import math
from collections import Counter

import numpy as np
import pytest
from scipy import stats

from fednav.service import keys
from fednav.service.estimation.integrity.mhss import MhssBank
from fednav.service.estimation.integrity.monitor import ResidualWindows
from fednav.service.messages import GnssRaw, ImuSample, Truth
from fednav.simulators.evaluate import INTEGRITY_CLASSES, evaluate, format_table
from fednav.simulators.papers import SEED001_TABLE1, reference
from fednav.simulators.scenario import ScenarioError, load_scenario, parse_scenario
from fednav.simulators.stream import Simulation

from .scenario_utils import cut_to

ONSET_S, RAMP_MPS = 11.0, 0.63
LATENCY_BOUND_S = 2.0  # the paper's 13 s flag of the 11 s onset


def variant(name: str = "seed001_ramp", duration_s: float | None = None, **changes):
    """A validated copy of a shipped scenario: shorter (segments that fit, faults clipped) and/or changed."""
    d = load_scenario(name).model_dump()
    if duration_s is not None:
        d = cut_to(d, duration_s)
    for k, v in changes.items():
        if isinstance(v, dict) and isinstance(d.get(k), dict):
            d[k] = {**d[k], **v}
        else:
            d[k] = v
    return parse_scenario(d, f"{name} (test variant)")


# --- scenarios --------------------------------------------------------------------------------------
def test_seed001_scenarios_carry_the_paper_setup():
    ramp = load_scenario("seed001_ramp")
    raw = ramp.gnss_raw
    assert raw.selection == "max_gdop" and raw.selection_count == 6 and raw.required_satellites == ("C03",)
    assert raw.id == "main" and raw.rate_hz >= 1.0
    (f,) = ramp.faults
    assert (f.sensor, f.kind, f.channels, f.rate_per_s) == ("gnss_raw", "ramp", ["C03.pseudorange"], [0.63])
    assert (f.start_s, f.duration_s) == (11.0, 129.0)
    (tc,) = ramp.service["pipelines"]
    assert tc["kind"] == "tightly_coupled" and tc["integrity"] and tc["phase"] == "npa"
    assert ramp.service["imu"]["gyro_bias_dph"] == ramp.imu.gyro_bias_dph[0]
    assert ramp.service["imu"]["accel_bias_ug"] == ramp.imu.accel_bias_ug[0]
    assert ramp.service["imu"]["arw_dpsh"] == ramp.imu.arw_dpsh
    assert ramp.service["imu"]["vrw_ugpsHz"] == ramp.imu.vrw_ugpsHz
    mc = load_scenario("seed001_montecarlo")
    assert mc.seed == 11 and mc.duration_s * mc.gnss_raw.rate_hz >= 8000
    assert set(mc.gnss_raw.required_satellites) == {"C01", "C03", "C25", "C28", "C38", "C39"}


def test_fault_schedule_is_deterministic_and_follows_its_distribution():
    mc = load_scenario("seed001_montecarlo")
    sch = mc.fault_schedule
    assert sch.expanded and sch.satellites == mc.gnss_raw.required_satellites
    faults = mc.faults
    rate = mc.gnss_raw.rate_hz
    assert len(faults) == 66
    for i, f in enumerate(faults):
        assert f.sensor == "gnss_raw" and len(f.channels) == 1
        sat, q = f.channels[0].split(".")
        assert q == "pseudorange" and sat in sch.satellites
        assert f.start_s == pytest.approx(sch.first_onset_s + i * sch.period_epochs / rate)
        n_ep = round(f.duration_s * rate)
        assert sch.duration_epochs[0] <= n_ep <= sch.duration_epochs[1]
        assert f.start_s + f.duration_s <= mc.duration_s
        size = {
            "step": lambda f: (abs(f.magnitude[0]), sch.step_m),
            "ramp": lambda f: (abs(f.rate_per_s[0]), sch.ramp_mps),
            "noise": lambda f: (f.std[0], sch.noise_std_m),
            "random_walk": lambda f: (f.sigma_per_sqrt_s[0], sch.random_walk_m_per_sqrt_s),
            "oscillation": lambda f: (f.amplitude[0], sch.oscillation_m),
        }[f.kind](f)
        assert size[1][0] <= size[0] <= size[1][1]
    kinds = Counter(f.kind for f in faults)
    assert set(kinds) == set(sch.kinds)
    # reproducible from the seed; a dumped scenario re-validates without expanding again
    assert load_scenario("seed001_montecarlo").faults == faults
    assert parse_scenario(mc.model_dump()).faults == faults
    d = mc.model_dump()
    d["fault_schedule"]["expanded"] = False
    d["faults"] = []
    d["seed"] = 12
    other = parse_scenario(d).faults
    assert len(other) == 66 and other != faults


@pytest.mark.parametrize(
    "fault, message",
    [
        ({"channels": ["C05.pseudorange"]}, r"\['C05'\] must be in gnss_raw.required_satellites"),
        ({"channels": ["C03.phase"]}, r"are not raw GNSS channels"),
        ({"channels": ["G05.pseudorange"]}, r"not in gnss_raw.constellations"),
    ],
)
def test_raw_gnss_fault_validation_names_the_problem(fault, message):
    d = load_scenario("seed001_ramp").model_dump()
    d["faults"][0].update(fault)
    with pytest.raises(ScenarioError, match=message):
        parse_scenario(d)


def test_fault_schedule_needs_raw_gnss():
    d = load_scenario("seed001_montecarlo").model_dump()
    d["fault_schedule"]["expanded"] = False
    d["faults"] = []
    d["gnss_raw"] = None
    with pytest.raises(ScenarioError, match="fault_schedule needs a \\[gnss_raw\\] sensor"):
        parse_scenario(d)


# --- stream -----------------------------------------------------------------------------------------
def test_stream_publishes_raw_gnss_at_its_rate_with_the_ramp_on_c03_only():
    sc = variant(duration_s=15.0)
    sim = Simulation(sc, seed=2, vehicle="v9")
    msgs = list(sim)
    raw = [(k, m) for k, m in msgs if isinstance(m, GnssRaw)]
    rate = sc.gnss_raw.rate_hz
    assert len(raw) == round(sc.duration_s * rate)
    assert {k for k, _ in raw} == {keys.sensor("v9", "gnss_raw", "main")}
    t0 = sc.t0_gps_s
    assert raw[0][1].t == pytest.approx(t0 + 1.0 / rate, abs=1e-6)
    # per instant: Truth, then the aiding, then the IMU sample ending there
    for i, (_, m) in enumerate(msgs):
        if isinstance(m, GnssRaw):
            before = [x for _, x in msgs[max(i - 3, 0) : i]]
            assert isinstance(msgs[i + 1][1], ImuSample) and msgs[i + 1][1].t == m.t
            assert any(isinstance(x, Truth) and x.t == m.t for x in before)
    # the published set: six satellites including C03; the fault on C03's pseudorange only
    truths = sim.truth.gnss_raw
    assert len(truths) == len(raw)
    for tr, (_, m) in zip(truths, raw, strict=True):
        t_rel = round((m.t - t0) * sc.imu.rate_hz) / sc.imu.rate_hz
        assert len(m.sats) == 6 and "C03" in tr.ids
        ramp = RAMP_MPS * (t_rel - ONSET_S) if sc.faults[0].is_active(t_rel) else 0.0
        expect = np.where(np.array(tr.ids) == "C03", ramp, 0.0)
        np.testing.assert_allclose(tr.pseudorange_fault_m, expect, atol=1e-9)
        assert not np.any(tr.range_rate_fault_mps)
    active = {m.t: m.faults for _, m in msgs if isinstance(m, Truth)}
    assert all(not f for t, f in active.items() if t - t0 < ONSET_S - 1e-6)
    late = [f for t, f in active.items() if ONSET_S + 1e-6 < t - t0 < sc.faults[0].end_s - 1e-6]
    assert late and all(
        [(a.sensor, a.kind, a.channels) for a in f] == [("gnss_raw", "ramp", ["C03.pseudorange"])]
        for f in late
    )
    # adding raw GNSS does not change the other streams' noise
    d = sc.model_dump()
    d["gnss_raw"], d["faults"] = None, []
    imu_a = [m for m in Simulation(parse_scenario(d), seed=2, vehicle="v9") if isinstance(m[1], ImuSample)]
    imu_b = [(k, m) for k, m in msgs if isinstance(m, ImuSample)]
    assert imu_a == imu_b


# --- integrity through the eval path --------------------------------------------------------------------
@pytest.fixture(scope="module")
def ramp_result():
    return evaluate(variant(duration_s=30.0), runs=1, seed=1)


def test_short_ramp_detected_within_2_s_and_only_c03_excluded(ramp_result):
    g = ramp_result["pipelines"]["tc_mhss"]["integrity"]
    lat = g["detection_latency_s"]
    assert lat is not None and 0.0 < lat <= LATENCY_BOUND_S + 1e-9, f"latency {lat}"
    assert g["excluded_satellites"] == ["C03"]
    assert g["hmi_epochs"] == 0 and g["alarms"] == 0
    c = g["counts"]
    assert c["missed"] == 0 and c["false_alarm"] == 0
    assert c["normal"] == round((ONSET_S - 0.1) * 10) + 1  # fault-free epochs 0.1 .. 11.0 s (10 Hz)
    assert c["detected"] > 0 and g["faults_detected_in_time"] == g["faults"] == 1


def test_integrity_json_keys_are_consistent(ramp_result):
    g = ramp_result["pipelines"]["tc_mhss"]["integrity"]
    for key in ("detection_latency_s", "hpl_m", "vpl_m", "hmi_epochs", "alarms", "counts", "p_fa", "p_md"):
        assert key in g
    assert set(g["counts"]) == set(INTEGRITY_CLASSES) | {"hmi"}
    assert set(INTEGRITY_CLASSES) >= {"normal", "detected", "missed", "false_alarm"}
    assert g["counts"]["hmi"] == g["hmi_epochs"]
    assert sum(g["counts"][k] for k in INTEGRITY_CLASSES) == g["epochs"] == 300  # 30 s at 10 Hz
    for pl in ("hpl_m", "vpl_m"):
        assert 0.0 < g[pl]["median"] <= g[pl]["max"] < 556.0
    c = g["counts"]
    assert g["p_fa"] == c["false_alarm"] / (c["normal"] + c["false_alarm"])
    assert g["p_md"] == c["missed"] / (c["detected"] + c["missed"] + c["undetected"])
    text = format_table(ramp_result)
    assert "paper Table 1" in text and "flagged at 13.0 s" in text
    assert reference("seed001_montecarlo")["integrity_table1"] == SEED001_TABLE1


def test_fault_free_false_alarms_are_consistent_with_p_fa():
    """Fault-free 60 s runs (600 epochs each). At the configured P_FA = 1e-4 no false alarm is
    expected (P(>= 2) < 2e-3 for a rate at P_FA); at P_FA = 0.02 the rate is measurable: the count
    must not exceed the binomial 99.9 % quantile at P_FA (the tests are conservative, so fewer)."""
    base = variant(name="seed001_montecarlo", duration_s=60.0, fault_schedule=None, faults=[])
    g = evaluate(base, runs=1, seed=5)["pipelines"]["tc_mhss"]["integrity"]
    assert g["counts"]["false_alarm"] <= 1 and g["hmi_epochs"] == 0
    tc = dict(base.service["pipelines"][0], p_fa=0.02, exclusion=False)
    loose = variant(
        name="seed001_montecarlo",
        duration_s=60.0,
        fault_schedule=None,
        faults=[],
        service={"pipelines": [tc]},
    )
    g = evaluate(loose, runs=1, seed=5)["pipelines"]["tc_mhss"]["integrity"]
    n = g["counts"]["normal"] + g["counts"]["false_alarm"]
    assert n == g["epochs"] == 600
    assert g["counts"]["false_alarm"] <= stats.binom.ppf(0.999, n, 0.02)


# --- the satellite residual test --------------------------------------------------------------------
def test_excluded_residuals_use_the_sub_filter_that_excludes_the_satellite():
    rng = np.random.default_rng(0)
    n, sats = 5, ["A", "B", "C", "D"]
    A = rng.normal(size=(n, n))
    bank = MhssBank.initial(np.zeros(n), A @ A.T + np.eye(n), sats, depth=1, h_idx=(0, 1), v_idx=2)
    H = rng.normal(size=(4, n))
    z = rng.normal(size=4)
    bank.update(z, H, np.full(4, 0.25), np.arange(4))
    e, hph, r = bank.excluded_residuals(z, H, np.full(4, 0.25), np.arange(4))
    for j in range(4):
        x, P = bank.x[1 + j], bank.P[1 + j]
        assert e[j] == pytest.approx(z[j] - H[j] @ x)
        assert hph[j] == pytest.approx(H[j] @ P @ H[j])
    np.testing.assert_array_equal(r, 0.25)


def test_residual_windows_bound_the_mean_for_any_correlation():
    """sigma_W^2 = (mean sqrt(hph))^2 + sum r / W^2 bounds var(mean e) even when the state part
    is constant over the window (fully correlated, the worst case); window statistics restart
    for new satellites and after clear()."""
    w = ResidualWindows((1, 4))
    k = 3.0
    rng = np.random.default_rng(1)
    runs, flags = 4000, 0
    for _ in range(runs):
        c = rng.normal(0.0, 0.5)  # sub-filter error along the line of sight, the same for 4 epochs
        w.clear()
        for _ in range(4):
            w.push(["X"], np.array([c + rng.normal(0.0, 0.3)]), np.array([0.25]), np.array([0.09]))
        t = w.tests(["X"], k)
        flags += bool(t.statistic[0, 1] > t.threshold[0, 1])
        assert t.count[0].tolist() == [1, 4]
    p = 2 * stats.norm.sf(k)  # exact rate of this worst case would be 2 Q(k sigma_W / sd) <= 2 Q(k)
    assert flags / runs <= p + 4 * math.sqrt(p / runs)
    t = w.tests(["X", "Y"], k)
    assert t.threshold[1].tolist() == [math.inf, math.inf] and not t.flagged[1]
    mean = t.statistic[0, 1]
    assert t.threshold[0, 1] == pytest.approx(k * math.sqrt(0.5**2 + 4 * 0.09 / 16))
    assert mean >= 0.0
    w.retain(["Y"])
    assert w.tests(["X"], k).count[0].tolist() == [0, 0]
