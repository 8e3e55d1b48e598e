"""Atmosphere, weighting and inter-system biases of the raw-GNSS measurement model.

Closed forms: Saastamoinen hydrostatic zenith delay at sea level (2.3 m), the mapping function at
the zenith (1) and at 5 deg, the Klobuchar models at night (5 ns x obliquity), at the 14:00 local
peak (5 ns + alpha_0) and their obliquity factors (IS-GPS-200N 20.3.3.5.2.5: F = 1 + 16 (0.53 - E)^3;
BDS-SIS-ICD-B1I 5.2.4.7: 1 / sqrt(1 - (R cos E / (R + h))^2)). Model: rows with atmosphere and ISB
are zero at the truth, ISB columns, elevation weights, defaults unchanged; a short tightly coupled
run with a BeiDou inter-system bias."""

from __future__ import annotations

import math

import numpy as np
import pytest

from fednav.service import earth
from fednav.service.config import ImuModel, TightlyCoupledConfig
from fednav.service.estimation.measurements import atmosphere as atm
from fednav.service.estimation.measurements import gnss_raw as gm
from fednav.service.estimation.measurements.base import ModelContext
from fednav.service.evaluation import nav_errors
from fednav.service.ins.mechanisation import NavState
from fednav.service.messages import GnssRaw, IonoKlobuchar, SatObservation
from fednav.service.pipelines.base import InitStd
from fednav.service.pipelines.tightly_coupled import TightlyCoupled
from fednav.simulators.gnss.orbits import NominalConstellation
from fednav.simulators.gnss.raw_sensor import GnssRawSensor, GnssRawSpec
from fednav.simulators.gnss.raw_sensor import tropo_delay_m as sim_tropo_delay_m
from fednav.simulators.trajectory import StartSpec, StraightSegment, TurnSegment, build_trajectory

T0 = 1_300_000_000.0


# --- closed forms -----------------------------------------------------------------------------------------
def test_saastamoinen_zenith_and_mapping():
    # hydrostatic: 0.0022768 * 1013.25 hPa / (1 - 0.00266 cos 2phi) = 2.3070 m at 45 deg, sea level
    assert atm.saastamoinen_zenith_m(math.radians(45.0), 0.0, rel_humidity=0.0) == pytest.approx(
        2.3070, abs=5e-4
    )
    total = atm.saastamoinen_zenith_m(math.radians(45.0), 0.0)
    assert 2.35 < total < 2.6  # + wet delay of a standard atmosphere at 70 % humidity (~0.1-0.2 m)
    assert atm.saastamoinen_zenith_m(0.5, 2000.0) < 0.8 * total  # pressure falls with height
    # the simulator's Saastamoinen (1/cos z mapping) agrees at the zenith
    assert sim_tropo_delay_m(np.array([math.pi / 2]), 0.5, 100.0)[0] == pytest.approx(
        atm.saastamoinen_zenith_m(0.5, 100.0), rel=1e-6
    )
    assert atm.tropo_mapping(np.array([math.pi / 2]))[0] == pytest.approx(1.0, abs=1e-6)
    assert atm.tropo_mapping(np.array([math.radians(5.0)]))[0] == pytest.approx(
        1.001 / math.sqrt(0.002001 + math.sin(math.radians(5.0)) ** 2), rel=1e-12
    )
    assert 10.0 < atm.tropo_mapping(np.array([math.radians(5.0)]))[0] < 10.5


ALPHA = (1.0e-8, 0.0, 0.0, 0.0)
BETA = (86400.0, 0.0, 0.0, 0.0)


def test_klobuchar_gps_closed_forms():
    """User at lat 0, lon 0, satellite at the zenith (E = 0.5 semicircles): psi = 0.0137/0.61 -
    0.022, the pierce point is the user (A = 0 moves it north by psi), local time = GPS time of day,
    F = 1 + 16 (0.03)^3. With alpha = (a0, 0, 0, 0): 14:00 local -> F (5 ns + a0); night -> F 5 ns."""
    f = 1.0 + 16.0 * 0.03**3
    el, az = np.array([math.pi / 2]), np.array([0.0])
    peak = atm.klobuchar_gps_s(ALPHA, BETA, 0.0, 0.0, el, az, 50400.0)[0]
    assert peak == pytest.approx(f * (5e-9 + 1e-8), rel=1e-12)
    night = atm.klobuchar_gps_s(ALPHA, BETA, 0.0, 0.0, el, az, 10000.0)[0]
    assert night == pytest.approx(f * 5e-9, rel=1e-12)
    # a quarter period after the peak the cosine series is x = pi/2 - not below 1.57: night value
    q = atm.klobuchar_gps_s(ALPHA, BETA, 0.0, 0.0, el, az, 50400.0 + 86400.0 / 4 + 10.0)[0]
    assert q == pytest.approx(f * 5e-9, rel=1e-12)
    # the series 1 - x^2/2 + x^4/24 at x = 1
    t = 50400.0 + 86400.0 / (2 * math.pi)
    one = atm.klobuchar_gps_s(ALPHA, BETA, 0.0, 0.0, el, az, t)[0]
    assert one == pytest.approx(f * (5e-9 + 1e-8 * (1 - 0.5 + 1 / 24)), rel=1e-9)
    # low elevation: obliquity F = 1 + 16 (0.53 - E)^3 at E = 5 deg
    e5 = math.radians(5.0)
    low = atm.klobuchar_gps_s(ALPHA, BETA, 0.0, 0.0, np.array([e5]), az, 10000.0)[0]
    assert low == pytest.approx((1 + 16 * (0.53 - e5 / math.pi) ** 3) * 5e-9, rel=1e-12)
    # negative amplitude polynomial is clamped to zero; period below 72000 s clamped
    neg = atm.klobuchar_gps_s((-1e-8, 0, 0, 0), (1000.0, 0, 0, 0), 0.0, 0.0, el, az, 50400.0)[0]
    assert neg == pytest.approx(f * 5e-9, rel=1e-12)
    # a broadcast set (GPS, typical) gives metres: 1-30 m in daytime at mid latitude
    a = (1.1176e-08, 7.4506e-09, -5.9605e-08, -5.9605e-08)
    b = (9.0112e04, 1.6384e04, -1.9661e05, -6.5536e04)
    d = atm.C_MPS * atm.klobuchar_gps_s(a, b, math.radians(30.0), math.radians(114.0), el, az, 6 * 3600.0)[0]
    assert 1.0 < d < 30.0


def test_klobuchar_bds_closed_forms():
    """Zenith: psi = 0, pierce point = user, obliquity 1; local time = BDT + lon/15deg h.
    With alpha = (a0, 0, 0, 0), beta0 = 86400: 14:00 -> 5 ns + a0; night -> 5 ns."""
    el, az = np.array([math.pi / 2]), np.array([0.0])
    peak = atm.klobuchar_bds_s(ALPHA, BETA, 0.3, 0.0, el, az, 50400.0 + 14.0)[0]  # GPST = BDT + 14 s
    assert peak == pytest.approx(5e-9 + 1e-8, rel=1e-12)
    assert atm.klobuchar_bds_s(ALPHA, BETA, 0.3, 0.0, el, az, 10014.0)[0] == pytest.approx(5e-9, rel=1e-12)
    # 90 deg east: local noon is 6 h earlier in BDT
    east = atm.klobuchar_bds_s(ALPHA, BETA, 0.3, math.pi / 2, el, az, 50400.0 - 21600.0 + 14.0)[0]
    assert east == pytest.approx(5e-9 + 1e-8, rel=1e-9)
    # period clamped to [72000, 172800]: at dt = -(172800/4 - 10 s) with beta0 = 1e6 still daytime
    day = atm.klobuchar_bds_s(ALPHA, (1e6, 0, 0, 0), 0.3, 0.0, el, az, 50400.0 - 43190.0 + 14.0)[0]
    assert day > 5e-9
    # obliquity at 10 deg: 1 / sqrt(1 - (R cos E / (R + h))^2), night value
    e10 = math.radians(10.0)
    k = 6378e3 / (6378e3 + 375e3) * math.cos(e10)
    low = atm.klobuchar_bds_s(ALPHA, BETA, 0.3, 0.0, np.array([e10]), az, 10014.0)[0]
    assert low == pytest.approx(5e-9 / math.sqrt(1 - k * k), rel=1e-12)


# --- the measurement model ------------------------------------------------------------------------------
LLH = np.array([math.radians(30.5), math.radians(114.3), 50.0])
ISB_BDS_M = 37.0
CLOCK_M = 120.0


def _message(iono=True, isb=ISB_BDS_M):
    """A GnssRaw epoch of nominal GPS + BDS at the truth: range + clock + ISB (BDS) + modelled
    troposphere and Klobuchar delays (the model's own functions)."""
    src = NominalConstellation(("BDS", "GPS"))
    ids = src.satellite_ids()
    st = src.states(ids, T0)
    rx = earth.llh_to_ecef(LLH)
    c_en = earth.mat_en(LLH[0], LLH[1])
    g = gm.range_geometry(rx, st.pos_ecef_m)
    los_enu = g.los_ecef @ c_en
    el = np.arcsin(los_enu[:, 2])
    az = np.arctan2(los_enu[:, 0], los_enu[:, 1])
    keep = el > math.radians(12.0)
    a = (1.1176e-08, 7.4506e-09, -5.9605e-08, -5.9605e-08)
    b = (9.0112e04, 1.6384e04, -1.9661e05, -6.5536e04)
    a_c = (1.0245e-08, 2.2352e-08, -5.9605e-08, -1.1921e-07)
    b_c = (1.1469e05, 1.6384e05, -2.6214e05, -1.9661e05)
    tropo = atm.saastamoinen_zenith_m(LLH[0], LLH[2]) * atm.tropo_mapping(el)
    ion_g = atm.C_MPS * atm.klobuchar_gps_s(a, b, LLH[0], LLH[1], el, az, T0)
    ion_c = atm.C_MPS * atm.klobuchar_bds_s(a_c, b_c, LLH[0], LLH[1], el, az, T0)
    sats = []
    for j in np.flatnonzero(keep):
        sid = ids[j]
        bds = sid[0] == "C"
        pr = g.range_m[j] + CLOCK_M + tropo[j] + (ion_c[j] + isb if bds else ion_g[j])
        sats.append(
            SatObservation(
                id=sid,
                constellation="BDS" if bds else "GPS",
                pseudorange_m=float(pr),
                range_rate_mps=0.0,
                pseudorange_sigma_m=2.0,
                range_rate_sigma_mps=0.1,
                sat_pos_ecef_m=tuple(st.pos_ecef_m[j]),
                sat_vel_ecef_mps=(0.0, 0.0, 0.0),
            )
        )
    kl = [
        IonoKlobuchar(constellation="GPS", alpha=a, beta=b),
        IonoKlobuchar(constellation="BDS", alpha=a_c, beta=b_c),
    ]
    return GnssRaw(t=T0, sats=sats, iono=kl if iono else []), el[keep]


def _nav():
    return NavState(T0, LLH[0], LLH[1], LLH[2], np.zeros(3), np.array([1.0, 0.0, 0.0, 0.0]))


def _ctx(model, clock, isb=None):
    n = 15
    cols, ref = {}, {}
    for blk in model.private_states:
        cols[blk.name] = slice(n, n + blk.size)
        n += blk.size
    ref["clock"] = np.array(clock)
    if isb is not None:
        ref["isb"] = np.array(isb)
    return ModelContext(n, 0.0, cols, ref)


def _model(**kw):
    base = dict(
        correlation_time_s=600.0,
        bias_psd_m2ps=0.1,
        drift_psd_m2ps3=0.01,
        init_bias_std_m=100.0,
        init_drift_std_mps=1.0,
        elevation_mask_deg=10.0,
        use_range_rate=False,
    )
    base.update(kw)
    return gm.GnssRawModel(**base)


def test_rows_vanish_at_the_truth_with_atmosphere_and_isb():
    msg, el = _message()
    m = _model(troposphere=True, ionosphere=True, isb_constellations=("BDS",))
    assert [b.name for b in m.private_states] == ["clock", "isb"]
    nav = _nav()
    clock = m.initial_clock(nav, msg)
    assert clock[0] == pytest.approx(CLOCK_M, abs=1e-6)  # GPS only: the clock excludes the ISB system
    isb = m.initial_isb(nav, msg, clock)
    assert isb == pytest.approx([ISB_BDS_M], abs=1e-6)
    meas = m(nav, msg, _ctx(m, [CLOCK_M, 0.0], [ISB_BDS_M]))
    np.testing.assert_allclose(meas.z, 0.0, atol=1e-6)
    bds_rows = np.array([lab.startswith("C") for lab in meas.labels])
    assert bds_rows.any() and (~bds_rows).any()
    np.testing.assert_array_equal(meas.H[:, 17], bds_rows.astype(float))  # ISB column after the clock
    np.testing.assert_array_equal(meas.H[:, 15], 1.0)
    # without the corrections the residuals are the delays (metres, larger at low elevation)
    plain = _model(isb_constellations=("BDS",))
    z = plain(nav, msg, _ctx(plain, [CLOCK_M, 0.0], [ISB_BDS_M])).z
    assert np.all(z < -2.0)  # predicted - measured: the measured ranges carry > 2 m of delay


def test_elevation_weights_and_defaults_unchanged():
    msg, el = _message(isb=0.0)
    nav = _nav()
    plain = _model()
    weighted = _model(elevation_weighting=True)
    a = plain(nav, msg, _ctx(plain, [CLOCK_M, 0.0]))
    b = weighted(nav, msg, _ctx(weighted, [CLOCK_M, 0.0]))
    np.testing.assert_allclose(np.diag(a.R), 4.0)
    np.testing.assert_allclose(np.diag(b.R), 4.0 / np.sin(el) ** 2, rtol=1e-9)
    np.testing.assert_array_equal(a.z, b.z)
    assert len(plain.private_states) == 1 and a.H.shape[1] == 17
    # ionosphere requested but the message carries no coefficients: no ionosphere term
    no_iono, _ = _message(iono=False, isb=0.0)
    m = _model(ionosphere=True)
    np.testing.assert_array_equal(
        m(nav, no_iono, _ctx(m, [CLOCK_M, 0.0])).z,
        a.z * 0 + plain(nav, no_iono, _ctx(plain, [CLOCK_M, 0.0])).z,
    )


def test_config_rejects_unknown_isb_constellation():
    with pytest.raises(ValueError):
        TightlyCoupledConfig(name="tc", isb_constellations=("XYZ",))
    assert TightlyCoupledConfig(name="tc").isb_constellations == ()


def test_tightly_coupled_run_estimates_a_bds_inter_system_bias():
    """GPS + BDS simulated with one receiver clock, BDS pseudoranges shifted by 37 m: with an ISB
    state the pipeline converges (position < 3 m, ISB within 2 m); sharing one clock it is biased."""
    start = StartSpec(lat_deg=30.5, lon_deg=114.3, height_m=50.0, heading_deg=45.0, speed_mps=20.0)
    traj = build_trajectory(
        start,
        [
            StraightSegment(kind="straight", duration_s=20.0),
            TurnSegment(kind="turn", duration_s=20.0, turn_rate_dps=3.0, ramp_s=5.0),
        ],
        100.0,
        T0,
        duration_s=40.0,
    )
    spec = GnssRawSpec(
        rate_hz=2.0, constellations=("BDS", "GPS"), pseudorange_sigma_m=1.0, range_rate_sigma_mps=0.05
    )
    sensor = GnssRawSensor(spec, seed=5)
    s0 = traj.state_at(T0)

    def run(isb: tuple[str, ...]):
        p = TightlyCoupled(
            TightlyCoupledConfig(name="tc", integrity=False, isb_constellations=isb), ImuModel(), 0.1
        )
        nav = NavState(T0, *s0.llh, s0.vel_enu_mps.copy(), earth.mat_to_quat(earth.rpy_to_mat_nb(s0.rpy_rad)))
        p.initialise(nav, InitStd(np.full(3, 5.0), np.full(3, 0.3), np.radians([0.1, 0.1, 0.3])))
        errs = []
        for k in range(1, len(traj.t_s)):
            p.push_imu(traj.dtheta_rad[k], traj.dvel_mps[k], traj.dt_s, float(traj.t_s[k]))
            if k % 50 == 0:
                p.sync()
                s = traj.state_at(traj.t_s[k])
                c_en = earth.mat_en(s.llh[0], s.llh[1])
                ep = epochs.get(k)
                if ep is None:
                    ep = epochs[k] = sensor.measure(
                        traj.t_s[k], earth.llh_to_ecef(s.llh), c_en @ s.vel_enu_mps
                    )
                msg = GnssRaw(
                    t=ep.message.t,
                    sats=[
                        o.model_copy(update={"pseudorange_m": o.pseudorange_m + ISB_BDS_M})
                        if o.id[0] == "C"
                        else o
                        for o in ep.message.sats
                    ],
                )
                p.apply("gnss_raw", "g", msg)
                e = nav_errors(p.bank.nav(), s.llh, s.vel_enu_mps, earth.rpy_to_mat_nb(s.rpy_rad))
                errs.append(e)
        return p, errs

    epochs: dict = {}
    p_isb, e_isb = run(("BDS",))
    p_one, e_one = run(())
    pos_isb = np.array([np.linalg.norm(e[0:3]) for e in e_isb])
    pos_one = np.array([np.linalg.norm(e[0:3]) for e in e_one])
    assert p_isb.bank.reference["isb"][0] == pytest.approx(ISB_BDS_M, abs=2.0)
    assert np.max(pos_isb[len(pos_isb) // 2 :]) < 3.0
    assert np.mean(pos_one[len(pos_one) // 2 :]) > 2.0 * np.mean(pos_isb[len(pos_isb) // 2 :])
