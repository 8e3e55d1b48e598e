"""Raw GNSS sensor: spec validation, measurement model (inverted by single-point LS), noise statistics,
receiver clock, DOP and selection rules, fault hook, wire messages, and a real-data check
(RINEX 2.10 from Wuhan 2015, ../shared/data/real/psins_wuhan_2015)."""

from __future__ import annotations

import itertools
import math
from pathlib import Path

import numpy as np
import pytest
from pydantic import ValidationError
from scipy import stats
from scipy.optimize import least_squares

from fednav.service.earth import C_MPS, ecef_to_enu, ecef_to_llh, llh_to_ecef, mat_en
from fednav.service.estimation.snapshot import solve_position, solve_velocity
from fednav.service.messages import GnssRaw
from fednav.simulators.gnss.constellation import az_el, dop, dop_batch, los_enu, select_satellites
from fednav.simulators.gnss.orbits import (
    NOMINAL_EPOCH_GPS_S,
    NominalConstellation,
    gps_seconds,
    range_geometry,
)
from fednav.simulators.gnss.raw_sensor import (
    GnssRawSensor,
    GnssRawSpec,
    ReceiverClock,
    ReceiverClockSpec,
    clock_transition,
    iono_obliquity,
    tropo_delay_m,
    tropo_mapping,
)
from fednav.simulators.gnss.rinex import C_L1_M, BroadcastEphemeris, read_rinex2_obs

from .real_data import BRDC_2021, SP3_FILE, WUHAN

LLH0 = np.array([math.radians(40.10021), math.radians(118.60212), 100.0])  # seed 000's start point
T0 = NOMINAL_EPOCH_GPS_S + 1800.0  # 2021-04-28 18:30 GPST, inside the real SP3 file too


def _need(path: Path) -> Path:
    if not path.exists():
        pytest.skip(f"real data {path} absent (../shared/data not available here)")
    return path


def _trajectory(k: float):
    """Straight climbing flight: ENU velocity (200, 50, 3) m/s from LLH0; ECEF position, velocity."""
    m = mat_en(LLH0[0], LLH0[1])
    v = m @ np.array([200.0, 50.0, 3.0])
    return llh_to_ecef(LLH0) + v * k, v


def _arrays(msg: GnssRaw):
    s = msg.sats
    return (
        np.array([o.pseudorange_m for o in s]),
        np.array([o.range_rate_mps for o in s]),
        np.array([o.sat_pos_ecef_m for o in s]),
        np.array([o.sat_vel_ecef_mps for o in s]),
        np.array([o.sat_clock_m for o in s]),
        np.array([o.sat_clock_drift_mps for o in s]),
    )


# --- spec -----------------------------------------------------------------------------------------
@pytest.mark.parametrize(
    ("kwargs", "field"),
    [
        ({"rate_hz": 0.0}, "rate_hz"),
        ({"selection": "max_gdop"}, "selection_count"),
        ({"selection": "best", "selection_count": 6}, "selection"),
        ({"selection": "max_gdop", "selection_count": 3}, "selection_count"),
        ({"orbit_source": "/nonexistent/file.sp3"}, "orbit_source"),
        ({"constellations": ()}, "constellations"),
        ({"constellations": ("BDS", "BDS")}, "constellations"),
        ({"constellations": ("GAL",)}, "constellations"),
        ({"required_satellites": ("G05",)}, "required_satellites"),
        ({"required_satellites": ("XYZ",)}, "required_satellites"),
        ({"pseudorange_sigma_m": -1.0}, "pseudorange_sigma_m"),
        ({"elevation_mask_deg": 95.0}, "elevation_mask_deg"),
        ({"clock": {"drift_correlation_time_s": 0.0}}, "drift_correlation_time_s"),
        ({"unknown_key": 1}, "unknown_key"),
    ],
)
def test_spec_errors_name_the_field(kwargs, field):
    with pytest.raises(ValidationError) as e:
        GnssRawSpec(**kwargs)
    assert field in str(e.value)


def test_spec_resolves_role_names_and_checks_orbit_files():
    s = GnssRawSpec(selection="max_gdop", selection_count=6, required_satellites=("GEO3",))
    assert s.required_satellites == ("C03",)
    assert GnssRawSpec.model_validate_json(s.model_dump_json()) == s
    if BRDC_2021.is_file():
        with pytest.raises(ValidationError, match="constellations"):
            GnssRawSpec(orbit_source=str(BRDC_2021), constellations=("BDS",))
        assert GnssRawSpec(orbit_source=str(BRDC_2021), constellations=("GPS",)).orbit_source == str(
            BRDC_2021
        )


# --- measurement model, noise free ----------------------------------------------------------------
def _noise_free_spec(**kw) -> GnssRawSpec:
    return GnssRawSpec(
        pseudorange_sigma_m=1e-9,
        range_rate_sigma_mps=1e-9,
        clock=ReceiverClockSpec(initial_bias_m=12345.6, initial_drift_mps=-3.2),
        **kw,
    )


@pytest.mark.parametrize("source", ["nominal", "sp3", "broadcast"])
def test_noise_free_spp_recovers_truth(source):
    """The filter-side model (solve_position / solve_velocity on range_geometry) inverts the simulator:
    position < 1 mm, clock bias < 1 mm, velocity and drift < 1e-6 m/s, moving receiver, with real
    satellite clocks for SP3 and broadcast orbits."""
    if source == "nominal":
        spec = _noise_free_spec(constellations=("BDS", "GPS"))
    elif source == "sp3":
        spec = _noise_free_spec(constellations=("BDS", "GPS"), orbit_source=str(_need(SP3_FILE)))
    else:
        spec = _noise_free_spec(constellations=("GPS",), orbit_source=str(_need(BRDC_2021)))
    sensor = GnssRawSensor(spec, seed=1)
    for k in (0.0, 1.0, 2.0, 60.0):
        rx, v = _trajectory(k)
        ep = sensor.measure(T0 + k, rx, v)
        pr, rr, sp, sv, sc, sd = _arrays(ep.message)
        assert len(pr) >= 8
        if source != "nominal":
            assert np.all(np.abs(sc) > 1.0)  # real satellite clocks are in play
        sol = solve_position(pr, sp, sc)
        assert sol.converged
        assert np.linalg.norm(sol.pos_ecef_m - rx) < 1e-3
        assert abs(sol.clock_bias_m - ep.truth.rx_clock_bias_m) < 1e-3
        assert np.max(np.abs(sol.residuals_m)) < 1e-4
        vs = solve_velocity(rr, sol.pos_ecef_m, sp, sv, sd)
        assert np.linalg.norm(vs.vel_ecef_mps - v) < 1e-6
        assert abs(vs.clock_drift_mps - ep.truth.rx_clock_drift_mps) < 1e-6


def test_published_state_is_transmit_time_state():
    spec = _noise_free_spec()
    sensor = GnssRawSensor(spec, seed=2)
    rx, v = _trajectory(0.0)
    ep = sensor.measure(T0, rx, v)
    ids = list(ep.truth.ids)
    tau = ep.truth.range_m / C_MPS
    st = sensor.source.states(ids, T0 - tau)
    _, _, sp, sv, _, _ = _arrays(ep.message)
    np.testing.assert_allclose(sp, st.pos_ecef_m, atol=1e-6)
    np.testing.assert_allclose(sv, st.vel_ecef_mps, atol=1e-9)
    # the message validates as a wire message and round-trips through JSON
    again = GnssRaw.model_validate_json(ep.message.to_json())
    assert again == ep.message
    assert all(o.constellation == "BDS" and o.id[0] == "C" for o in again.sats)
    el = np.array([o.elevation_deg for o in again.sats])
    assert np.all(el >= spec.elevation_mask_deg)
    # all visible BDS satellites are there (rule "all")
    assert set(ep.truth.ids) == set(ep.truth.visible_ids)


# --- noise statistics -----------------------------------------------------------------------------
def test_residuals_match_configured_sigma():
    """Sum of squared LS residuals / sigma^2 over many epochs ~ chi2(sum (N - 4)); checked against the
    0.1 % and 99.9 % quantiles, for pseudoranges and range rates (seeded)."""
    sig_pr, sig_rr = 3.0, 0.05
    spec = GnssRawSpec(constellations=("BDS",), pseudorange_sigma_m=sig_pr, range_rate_sigma_mps=sig_rr)
    sensor = GnssRawSensor(spec, seed=42)
    ss_pr = ss_rr = 0.0
    dof = 0
    errs = []
    for k in range(200):
        rx, v = _trajectory(float(k))
        ep = sensor.measure(T0 + k, rx, v)
        pr, rr, sp, sv, sc, sd = _arrays(ep.message)
        sol = solve_position(pr, sp, sc, x0_ecef_m=rx + 100.0)
        vs = solve_velocity(rr, sol.pos_ecef_m, sp, sv, sd)
        ss_pr += np.sum(sol.residuals_m**2) / sig_pr**2
        ss_rr += np.sum(vs.residuals_mps**2) / sig_rr**2
        dof += len(pr) - 4
        errs.append(np.linalg.norm(sol.pos_ecef_m - rx))
    lo, hi = stats.chi2.ppf([0.001, 0.999], dof)
    assert lo < ss_pr < hi, (ss_pr, dof)
    assert lo < ss_rr < hi, (ss_rr, dof)
    assert np.sqrt(ss_pr / dof) == pytest.approx(1.0, abs=0.06)
    assert np.median(errs) < 10.0  # PDOP ~2 x 3 m


# --- receiver clock -------------------------------------------------------------------------------
def test_clock_transition_closed_form():
    tc, sb, sd, dt = 600.0, 9e-3, 3.5e-2, 0.7
    phi, q = clock_transition(dt, tc, sb, sd)
    beta = 1.0 / tc
    e1, e2 = math.exp(-beta * dt), math.exp(-2.0 * beta * dt)
    np.testing.assert_allclose(phi, [[1.0, (1.0 - e1) / beta], [0.0, e1]], rtol=1e-12)
    q11 = sb * dt + sd / beta**2 * (dt - 2.0 * (1.0 - e1) / beta + (1.0 - e2) / (2.0 * beta))
    q12 = sd / beta * ((1.0 - e1) / beta - (1.0 - e2) / (2.0 * beta))
    q22 = sd * (1.0 - e2) / (2.0 * beta)
    np.testing.assert_allclose(q, [[q11, q12], [q12, q22]], rtol=1e-6)


def test_clock_simulation_statistics():
    """Innovations of the simulated clock against its own transition have covariance Qd (seeded;
    chi2 bounds on each variance) and the drift decorrelates with the configured time constant."""
    spec = ReceiverClockSpec(initial_bias_m=0.0, initial_drift_mps=5.0, drift_correlation_time_s=50.0)
    clock = ReceiverClock(spec, np.random.default_rng(7))
    dt, n = 1.0, 20000
    phi, q = clock_transition(dt, spec.drift_correlation_time_s, spec.bias_psd_m2ps, spec.drift_psd_m2ps3)
    xs = np.empty((n + 1, 2))
    xs[0] = clock.state
    for k in range(n):
        clock.step(dt)
        xs[k + 1] = clock.state
    w = xs[1:] - xs[:-1] @ phi.T
    lo, hi = stats.chi2.ppf([0.001, 0.999], n) / n
    for i in range(2):
        assert lo < np.mean(w[:, i] ** 2) / q[i, i] < hi
    # steady-state drift variance S_d T_c / 2
    assert np.var(xs[2000:, 1]) == pytest.approx(spec.drift_psd_m2ps3 * 50.0 / 2.0, rel=0.3)
    with pytest.raises(ValueError):
        clock.step(0.0)


# --- DOP and selection ----------------------------------------------------------------------------
def _brute_gdop(az, el):
    u = los_enu(az, el)
    g = np.c_[-u, np.ones(len(az))]
    try:
        return math.sqrt(np.trace(np.linalg.inv(g.T @ g)))
    except np.linalg.LinAlgError:
        return math.inf


def test_dop_closed_form_and_singular():
    # zenith + three at 0 deg elevation 120 deg apart: G'G = diag(1.5, 1.5, 1, 4) with cross term
    az = np.radians([0.0, 0.0, 120.0, 240.0])
    el = np.radians([90.0, 0.0, 0.0, 0.0])
    d = dop(az, el)
    u = los_enu(az, el)
    g = np.c_[-u, np.ones(4)]
    q = np.linalg.inv(g.T @ g)
    assert float(d.gdop) == pytest.approx(math.sqrt(np.trace(q)))
    assert float(d.hdop) == pytest.approx(math.sqrt(q[0, 0] + q[1, 1]))
    assert float(d.hdop) == pytest.approx(math.sqrt(4.0 / 3.0))
    assert float(d.vdop) == pytest.approx(math.sqrt(q[2, 2]))
    assert float(d.tdop) == pytest.approx(math.sqrt(q[3, 3]))
    # all at one elevation: vertical and clock inseparable -> singular
    assert math.isinf(float(dop(np.radians([0, 90, 180, 270.0]), np.radians([30, 30, 30, 30.0])).gdop))
    assert math.isinf(float(dop(az[:3], el[:3]).gdop))


def test_selection_rules_against_brute_force():
    nc = NominalConstellation(("BDS",))
    ids = nc.satellite_ids()
    rx, _ = _trajectory(0.0)
    st = nc.states(ids, T0)
    az, el = az_el(rx, st.pos_ecef_m)
    vis = np.flatnonzero(el >= math.radians(10.0))
    az, el = az[vis], el[vis]
    assert len(vis) >= 10
    brute = {c: _brute_gdop(az[list(c)], el[list(c)]) for c in itertools.combinations(range(len(az)), 6)}
    finite = {c: g for c, g in brute.items() if math.isfinite(g)}
    sel = select_satellites(az, el, "max_gdop", 6)
    assert len(sel) == 6
    assert float(dop(az[sel], el[sel]).gdop) == pytest.approx(max(finite.values()), rel=1e-9)
    sel = select_satellites(az, el, "min_gdop", 6)
    assert float(dop(az[sel], el[sel]).gdop) == pytest.approx(min(finite.values()), rel=1e-9)
    with_req = {c: g for c, g in finite.items() if 0 in c}
    sel = select_satellites(az, el, "max_gdop", 6, required=[0])
    assert 0 in sel and float(dop(az[sel], el[sel]).gdop) == pytest.approx(max(with_req.values()), rel=1e-9)
    capped = {c: g for c, g in finite.items() if g <= 8.0}
    sel = select_satellites(az, el, "max_gdop", 6, gdop_limit=8.0)
    assert float(dop(az[sel], el[sel]).gdop) == pytest.approx(max(capped.values()), rel=1e-9)
    sel = select_satellites(az, el, "highest_elevation", 5)
    assert set(sel) == set(np.argsort(-el)[:5])
    assert len(select_satellites(az, el, "all")) == len(az)
    with pytest.raises(ValueError, match="rule"):
        select_satellites(az, el, "nope", 6)
    # batch DOP equals the one-by-one route
    combos = np.array(list(brute)[:50])
    np.testing.assert_allclose(
        dop_batch(los_enu(az[combos], el[combos])).gdop, [brute[tuple(c)] for c in combos], rtol=1e-9
    )


def test_sensor_max_gdop_six_with_geo3_kept():
    """Seed 001 set-up: six satellites, the largest-GDOP set of six visible, GEO3 (C03) required so the
    fault scenario has its target; the set is kept while all six stay visible (reselect on loss)."""
    spec = GnssRawSpec(selection="max_gdop", selection_count=6, required_satellites=("GEO3",))
    sensor = GnssRawSensor(spec, seed=3)
    rx, v = _trajectory(0.0)
    ep = sensor.measure(T0, rx, v)
    ids = ep.truth.ids
    assert len(ids) == 6 and "C03" in ids
    # brute force over the visible set
    vis = list(ep.truth.visible_ids)
    st = sensor.source.states(vis, T0 - 0.075)
    az, el = az_el(rx, st.pos_ecef_m)
    best = max(
        (_brute_gdop(az[list(c)], el[list(c)]), c)
        for c in itertools.combinations(range(len(vis)), 6)
        if vis.index("C03") in c and math.isfinite(_brute_gdop(az[list(c)], el[list(c)]))
    )
    assert {vis[i] for i in best[1]} == set(ids)
    assert ep.truth.gdop == pytest.approx(best[0], rel=1e-3)
    for k in range(1, 20):
        rx, v = _trajectory(float(k))
        assert sensor.measure(T0 + k, rx, v).truth.ids == ids


# --- faults and atmosphere ------------------------------------------------------------------------
class _FakeFaultSet:
    """Stand-in for simulators.faults.FaultSet: apply(sensor, t_rel_s, values) -> values."""

    def __init__(self):
        self.calls = []

    def apply(self, sensor: str, t_rel_s: float, values: dict[str, float]) -> dict[str, float]:
        self.calls.append((sensor, t_rel_s, sorted(values)))
        out = dict(values)
        if t_rel_s >= 11.0:  # seed 001: ramp 0.63 m/s on GEO3 from 11 s
            out["C03.pseudorange"] += 0.63 * (t_rel_s - 11.0)
            out["C03.range_rate"] += 0.63
        return out


def test_fault_hook_ramp_on_geo3():
    faults = _FakeFaultSet()
    spec = _noise_free_spec(selection="max_gdop", selection_count=6, required_satellites=("GEO3",))
    sensor = GnssRawSensor(spec, seed=4, fault_fn=lambda t, v: faults.apply("gnss", t, v))
    clean = GnssRawSensor(spec, seed=4)
    for k in range(0, 16):
        rx, v = _trajectory(float(k))
        ep, ref = sensor.measure(T0 + k, rx, v), clean.measure(T0 + k, rx, v)
        i = ep.truth.ids.index("C03")
        pr, rr, *_ = _arrays(ep.message)
        pr0, rr0, *_ = _arrays(ref.message)
        expect = 0.63 * max(0.0, k - 11.0)
        assert pr[i] - pr0[i] == pytest.approx(expect, abs=1e-6)
        assert ep.truth.pseudorange_fault_m[i] == pytest.approx(expect, abs=1e-6)
        assert rr[i] - rr0[i] == pytest.approx(0.63 if k >= 11 else 0.0, abs=1e-6)
        others = np.arange(len(pr)) != i
        np.testing.assert_allclose(pr[others], pr0[others], atol=1e-6)
    assert faults.calls[0][0] == "gnss" and faults.calls[0][1] == 0.0 and faults.calls[-1][1] == 15.0
    assert "C03.pseudorange" in faults.calls[0][2] and "C03.range_rate" in faults.calls[0][2]
    assert set(sensor.channels(["C03"])) == {"C03.pseudorange", "C03.range_rate"}
    bad = GnssRawSensor(spec, seed=4, fault_fn=lambda t, v: {**v, "C99.pseudorange": 1.0})
    with pytest.raises(KeyError, match="C99"):
        bad.measure(T0, *_trajectory(0.0))


def test_atmosphere_residual_is_elevation_dependent_and_off_by_default():
    base = _noise_free_spec()
    assert base.atmosphere is False
    atm = _noise_free_spec(atmosphere=True, tropo_zenith_residual_m=0.2, iono_zenith_residual_m=1.5)
    rx, v = _trajectory(0.0)
    e0 = GnssRawSensor(base, seed=5).measure(T0, rx, v)
    e1 = GnssRawSensor(atm, seed=5).measure(T0, rx, v)
    assert np.all(e0.truth.atmosphere_m == 0.0)
    el = np.radians(e1.truth.elevation_deg)
    expect = 0.2 * tropo_mapping(el) + 1.5 * iono_obliquity(el)
    pr0, *_ = _arrays(e0.message)
    pr1, *_ = _arrays(e1.message)
    np.testing.assert_allclose(pr1 - pr0, expect, atol=1e-6)
    assert np.all(expect >= 1.7 - 1e-9) and np.max(expect) < 0.2 * 10.2 + 1.5 * 3.1
    lo = int(np.argmin(el))
    assert expect[lo] == pytest.approx(np.max(expect))
    # Saastamoinen: ~2.4 m at zenith at sea level
    assert float(tropo_delay_m(np.array([math.pi / 2]), math.radians(45.0), 0.0)[0]) == pytest.approx(
        2.4, abs=0.1
    )


def test_time_must_increase_and_epoch_grid():
    sensor = GnssRawSensor(GnssRawSpec(rate_hz=10.0), seed=6)
    rx, v = _trajectory(0.0)
    sensor.measure(T0, rx, v)
    with pytest.raises(ValueError):
        sensor.measure(T0, rx, v)
    grid = sensor.epoch_times(T0, T0 + 1.0)
    assert len(grid) == 11 and grid[-1] == pytest.approx(T0 + 1.0)


# --- real data: Wuhan 2015, RINEX 2.10 ------------------------------------------------------------
@pytest.fixture(scope="module")
def wuhan():
    obs = read_rinex2_obs(_need(WUHAN / "01.15o"), ["C1", "D1"])
    nav = BroadcastEphemeris.from_file(_need(WUHAN / "01.15n"))
    return obs, nav


def _real_epoch(obs, nav, e, x0):
    t = obs.t_gps_s[e]
    c1, d1 = obs.obs("C1")[e], obs.obs("D1")[e]
    m = np.isfinite(c1) & np.isfinite(d1)
    ids = [s for s, k in zip(obs.ids, m, strict=True) if k]
    pr = c1[m]
    # transmit time: t_sv = t_rx - P/c (receiver clock cancels), t = t_sv - dt_sv (IS-GPS-200 20.3.3.3.3.1)
    st = nav.states(ids, t - pr / C_MPS)
    st = nav.states(ids, t - pr / C_MPS - st.clock_s)

    def tropo(x, sat_rx_frame):
        llh = ecef_to_llh(x)
        if not -500.0 < llh[2] < 9000.0:
            return np.zeros(len(sat_rx_frame))
        return tropo_delay_m(az_el(x, sat_rx_frame)[1], llh[0], llh[2])

    sol = solve_position(pr, st.pos_ecef_m, C_MPS * st.clock_s, x0_ecef_m=x0, delay_fn=tropo)
    vel = solve_velocity(
        -d1[m] * C_L1_M, sol.pos_ecef_m, st.pos_ecef_m, st.vel_ecef_mps, C_MPS * st.clock_drift_sps
    )
    return sol, vel


def test_real_spp_and_doppler_static_wuhan(wuhan):
    """SPP (C1 only, broadcast clocks with T_GD and relativity, Saastamoinen troposphere, no ionosphere
    model: the file has no Klobuchar coefficients) and Doppler velocity over the first 10 min (static).

    Measured: residual RMS median 2.0 m (max 3.1 m); static scatter ~1-2 m horizontal, 3.5 m
    vertical; Doppler residual RMS ~7 mm/s and |v| ~2 cm/s.

    The header APPROX POSITION is NOT the antenna position: the SPP lies 714 m from it (697 m west,
    147 m north, height within 2 m). Two independent routes say the offset is in the header, not in
    the solution: a Doppler-only static fix (no pseudoranges at all; Doppler positioning is good to
    a few tens of metres here) lands within 60 m of the SPP and > 600 m from the header, and Doppler
    residuals are 3x smaller at the SPP position than at the header position. The reference is
    therefore the SPP mean itself (scatter), plus the documented header offset.
    """
    obs, nav = wuhan
    assert obs.t_gps_s[0] == gps_seconds(2015, 1, 28, 5, 54, 14.0)
    ref = obs.approx_pos_ecef_m
    ref_llh = ecef_to_llh(ref)
    pos, rms, vel, vres, vres_header = [], [], [], [], []
    for e in range(0, 600, 4):
        sol, v = _real_epoch(obs, nav, e, ref)
        assert sol.converged and len(sol.residuals_m) >= 6
        pos.append(sol.pos_ecef_m)
        rms.append(np.sqrt(np.mean(sol.residuals_m**2)))
        vel.append(v.vel_ecef_mps)
        vres.append(np.sqrt(np.mean(v.residuals_mps**2)))
        if e % 40 == 0:
            t = obs.t_gps_s[e]
            c1, d1 = obs.obs("C1")[e], obs.obs("D1")[e]
            m = np.isfinite(c1) & np.isfinite(d1)
            ids = [s for s, k in zip(obs.ids, m, strict=True) if k]
            st = nav.states(ids, t - c1[m] / C_MPS)
            st = nav.states(ids, t - c1[m] / C_MPS - st.clock_s)
            vh = solve_velocity(
                -d1[m] * C_L1_M, ref, st.pos_ecef_m, st.vel_ecef_mps, C_MPS * st.clock_drift_sps
            )
            vres_header.append(np.sqrt(np.mean(vh.residuals_mps**2)))
    rms = np.array(rms)
    assert 1.0 < np.median(rms) < 5.0  # the data README's 1-5 m
    assert np.max(rms) < 10.0
    enu = ecef_to_enu(np.array(pos), ref_llh)
    mean = enu.mean(axis=0)
    scatter = enu - mean
    assert np.max(np.hypot(scatter[:, 0], scatter[:, 1])) < 15.0
    assert np.max(np.abs(scatter[:, 2])) < 25.0
    # documented header offset (see docstring): ~714 m horizontally, height agrees
    assert 680.0 < math.hypot(mean[0], mean[1]) < 750.0
    assert abs(mean[2]) < 10.0
    # Doppler: static receiver, range_rate = -D1 * lambda_L1
    speed = np.linalg.norm(np.array(vel), axis=1)
    assert np.median(speed) < 0.05 and np.max(speed) < 0.5
    assert np.median(vres) < 0.03
    assert np.median(vres_header) > 2.0 * np.median(vres)

    # Doppler-only static position: unknowns position + one clock drift per epoch (eliminated)
    c1_all, d1_all = obs.obs("C1"), obs.obs("D1")
    epochs = []
    for e in range(0, 600, 5):
        m = np.isfinite(c1_all[e]) & np.isfinite(d1_all[e])
        ids = [s for s, k in zip(obs.ids, m, strict=True) if k]
        t_tx = obs.t_gps_s[e] - c1_all[e, m] / C_MPS
        st = nav.states(ids, t_tx - nav.states(ids, t_tx).clock_s)
        epochs.append((st, -d1_all[e, m] * C_L1_M + C_MPS * st.clock_drift_sps))

    def doppler_residuals(x):
        out = []
        for st, rr in epochs:
            r = rr - range_geometry(x, st.pos_ecef_m, np.zeros(3), st.vel_ecef_mps).range_rate_mps
            out.append(r - r.mean())
        return np.concatenate(out)

    fix = least_squares(doppler_residuals, ref, x_scale=100.0).x
    spp_mean = np.mean(np.array(pos), axis=0)
    assert np.linalg.norm(fix - spp_mean) < 60.0
    assert np.linalg.norm(fix - ref) > 600.0


def test_gdop_rules_when_every_selected_satellite_is_required():
    from fednav.simulators.gnss.constellation import select_satellites

    az = np.radians([0.0, 90.0, 180.0, 270.0, 45.0, 135.0])
    el = np.radians([20.0, 30.0, 40.0, 50.0, 60.0, 70.0])
    for rule in ("max_gdop", "min_gdop"):
        sel = select_satellites(az, el, rule, 4, required=[0, 2, 3, 5])
        np.testing.assert_array_equal(sel, [0, 2, 3, 5])
