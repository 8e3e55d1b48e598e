"""Orbits: SP3 interpolation, GPS broadcast ephemeris, nominal BDS-3 geometry, the shared ranging model.

Real data (../shared/data/real, see its README): CODE MGEX final SP3 of 2021-04-28 (the stored
file holds 18:00-24:00 GPST, 73 epochs at 5 min), the same day's GPS broadcast file, and the
2015 Wuhan broadcast file. Tests that need them skip when the folder is absent.
"""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest

from fednav.service.earth import C_MPS, OMEGA_IE_RPS, llh_to_ecef, mat_en
from fednav.simulators.gnss.orbits import (
    BDS_GEO_LON_DEG,
    BDS_IGSO_IDS,
    BDS_MEO_A_M,
    BDS_MEO_IDS,
    GEOSYNC_A_M,
    NOMINAL_EPOCH_GPS_S,
    NominalConstellation,
    earth_rotation_matrices,
    gps_seconds,
    inertial_orbit_geometry,
    light_time_states,
    predicted_range,
    range_geometry,
    resolve_sat_id,
)
from fednav.simulators.gnss.rinex import BroadcastEphemeris, read_rinex2_nav
from fednav.simulators.gnss.sp3 import Sp3Data, Sp3Orbits, lagrange_weights

from .real_data import BRDC_2015, BRDC_2021, SP3_FILE


def _need(path: Path) -> Path:
    if not path.is_file():
        pytest.skip(f"real data file {path} absent (../shared/data not available here)")
    return path


@pytest.fixture(scope="module")
def sp3() -> Sp3Orbits:
    return Sp3Orbits.from_file(_need(SP3_FILE))


# --- time ------------------------------------------------------------------------------------------------
def test_gps_seconds_matches_sp3_header_week():
    assert gps_seconds(1980, 1, 6) == 0.0
    # SP3 header "## 2155 259200.0" is 2021-04-28 00:00 GPST
    assert gps_seconds(2021, 4, 28) == 2155 * 604800 + 259200


# --- SP3 ------------------------------------------------------------------------------------------------
def test_lagrange_weights_exact_on_polynomials():
    """Closed form: a degree-9 polynomial is reproduced exactly by 10-node interpolation, and so is
    its derivative, at and between nodes."""
    rng = np.random.default_rng(3)
    coef = rng.normal(size=10)
    nodes = np.arange(-4.0, 6.0)[None, :].repeat(5, axis=0)
    x = np.array([-4.0, 0.0, 0.37, 0.5, 5.0])
    w, dw = lagrange_weights(x, nodes)
    f = np.polynomial.polynomial.polyval(nodes[0], coef)
    np.testing.assert_allclose(w @ f, np.polynomial.polynomial.polyval(x, coef), rtol=1e-11, atol=1e-9)
    dcoef = np.polynomial.polynomial.polyder(coef)
    np.testing.assert_allclose(dw @ f, np.polynomial.polynomial.polyval(x, dcoef), rtol=1e-10, atol=1e-8)


def test_sp3_reader(sp3: Sp3Orbits):
    d = sp3.data
    assert d.t_gps_s.shape == (73,)  # the stored file is cut to 18:00-24:00 although its header says 289
    assert np.all(np.diff(d.t_gps_s) == 300.0)
    assert {"G01", "C19", "C38", "E01", "R01"} <= set(d.ids)
    assert d.time_system == "GPS"
    assert np.isnan(d.clock_s).any()  # 999999.999999 clocks read as missing
    k = d.ids.index("G01")
    np.testing.assert_allclose(d.pos_ecef_m[0, k], [13287682.546, -15491926.575, 16545690.647], atol=1e-3)
    assert d.clock_s[0, k] == pytest.approx(703.963460e-6)


def test_sp3_interpolation_at_nodes_equals_nodes(sp3: Sp3Orbits):
    ids = sp3.satellite_ids()
    for e in (0, 1, 36, 71, 72):  # the ends use shifted windows
        pos, vel = sp3.interpolate(ids, sp3.data.t_gps_s[e])
        ok = np.isfinite(sp3.data.pos_ecef_m[e, :, 0]) & np.isfinite(pos[:, 0])
        assert ok.sum() > 100
        np.testing.assert_allclose(pos[ok], sp3.data.pos_ecef_m[e, ok], rtol=0, atol=1e-6)


def test_sp3_leave_one_out_sub_centimetre(sp3: Sp3Orbits):
    """Interpolate across a node removed from the grid (a 10 min gap, worse than normal use) for every
    satellite of every system: measured max 4.5 mm (SP3 positions are rounded to 1 mm)."""
    d = sp3.data
    ids = list(d.ids)
    errs = []
    for e in range(8, 65, 4):
        keep = np.r_[0:e, e + 1 : len(d.t_gps_s)]
        sub = Sp3Orbits(Sp3Data(d.t_gps_s[keep], d.ids, d.pos_ecef_m[keep], d.clock_s[keep], "GPS"))
        pos, _ = sub.interpolate(ids, d.t_gps_s[e])
        errs.append(np.linalg.norm(pos - d.pos_ecef_m[e], axis=1))
    errs = np.array(errs)
    assert np.nanmax(errs) < 0.02
    assert np.nanmedian(errs) < 0.005


def test_sp3_velocity_is_derivative_of_position(sp3: Sp3Orbits):
    ids = [s for s in sp3.satellite_ids() if s[0] in "GC"]
    t = sp3.data.t_gps_s[30] + 123.0
    p1, _ = sp3.interpolate(ids, t + 0.5)
    p0, _ = sp3.interpolate(ids, t - 0.5)
    _, v = sp3.interpolate(ids, t)
    np.testing.assert_allclose(p1 - p0, v, atol=1e-4)
    # outside the file: NaN, not extrapolation
    pos, _ = sp3.interpolate(ids[:2], sp3.time_span_gps_s[1] + 1.0)
    assert np.all(np.isnan(pos))


def test_sp3_against_gps_broadcast(sp3: Sp3Orbits):
    """Two independent orbit products for the same satellites: CODE final (centre of mass) vs the
    broadcast ephemeris (antenna phase centre, ~1 m apart by itself). Data README: ~1.5 m median.
    Measured: median 1.55 m, max 5.3 m (G14), velocity max 1.5 mm/s."""
    brdc = BroadcastEphemeris.from_file(_need(BRDC_2021), with_tgd=False)
    ids = [s for s in brdc.satellite_ids() if s in sp3.satellite_ids()]
    assert len(ids) >= 30
    errs, verrs = [], []
    for t in sp3.data.t_gps_s:
        a, b = sp3.states(ids, t), brdc.states(ids, t)
        errs.append(np.linalg.norm(a.pos_ecef_m - b.pos_ecef_m, axis=1))
        verrs.append(np.linalg.norm(a.vel_ecef_mps - b.vel_ecef_mps, axis=1))
    errs, verrs = np.array(errs), np.array(verrs)
    assert not np.isnan(errs).any()
    assert np.median(errs) < 3.0
    assert np.max(errs) < 10.0
    assert np.max(verrs) < 0.01


# --- broadcast ephemeris --------------------------------------------------------------------------------
def test_broadcast_reader_and_radius_2015():
    eph = read_rinex2_nav(_need(BRDC_2015))
    assert len(eph) == 64
    assert set(eph.params["week"]) == {1829.0}
    brdc = BroadcastEphemeris(eph)
    ids = brdc.satellite_ids()
    t = gps_seconds(2015, 1, 28, 6, 10)
    st = brdc.states(ids, t)
    assert st.valid.all()
    r = np.linalg.norm(st.pos_ecef_m, axis=1)
    a = eph.params["sqrt_a"] ** 2
    assert np.all(np.abs(a - 26_560e3) < 50e3)  # semi-major axes
    assert np.all(np.abs(r - 26_560e3) < 600e3)  # radii (e < 0.02)
    speed_inertial = np.linalg.norm(
        st.vel_ecef_mps + OMEGA_IE_RPS * np.stack([-st.pos_ecef_m[:, 1], st.pos_ecef_m[:, 0], 0 * r], axis=1),
        axis=1,
    )
    np.testing.assert_allclose(speed_inertial, 3874.0, atol=80.0)
    # clocks: broadcast af0 is up to ~1 ms
    assert np.all(np.abs(st.clock_s) < 1e-3)
    # out of validity (4 h from any toe): NaN
    assert not brdc.states(ids, t + 86400.0).valid.any()


def test_broadcast_velocity_and_clock_drift_are_derivatives():
    brdc = BroadcastEphemeris.from_file(_need(BRDC_2021))
    ids = brdc.satellite_ids()
    t = gps_seconds(2021, 4, 28, 19, 7, 3.0)
    s0, s1, s = brdc.states(ids, t - 0.5), brdc.states(ids, t + 0.5), brdc.states(ids, t)
    np.testing.assert_allclose(s1.pos_ecef_m - s0.pos_ecef_m, s.vel_ecef_mps, atol=1e-4)
    np.testing.assert_allclose(s1.clock_s - s0.clock_s, s.clock_drift_sps, atol=1e-17)


# --- nominal constellation ------------------------------------------------------------------------------
def test_nominal_bds_closed_form_geometry():
    nc = NominalConstellation(("BDS",))
    ids = nc.satellite_ids()
    assert len(ids) == 30
    assert (
        resolve_sat_id("GEO3") == "C03" and resolve_sat_id("geo1") == "C01" and resolve_sat_id("C07") == "C07"
    )
    t = NOMINAL_EPOCH_GPS_S + 12345.6
    st = nc.states(ids, t)
    g = inertial_orbit_geometry(st.pos_ecef_m, st.vel_ecef_mps)
    k = {s: i for i, s in enumerate(ids)}
    for sid, lon in BDS_GEO_LON_DEG.items():  # GEO1 80 E, GEO2 110.5 E, GEO3 = C03 140 E
        assert g["lon_deg"][k[sid]] == pytest.approx(lon, abs=1e-9)
        assert g["radius_m"][k[sid]] == pytest.approx(42_164.17e3, abs=10.0)
        assert np.linalg.norm(st.vel_ecef_mps[k[sid]]) < 1e-6
        assert abs(st.pos_ecef_m[k[sid], 2]) < 1e-3
    assert BDS_GEO_LON_DEG["C03"] == 140.0
    igso = [k[s] for s in BDS_IGSO_IDS]
    np.testing.assert_allclose(g["inclination_deg"][igso], 55.0, atol=1e-9)
    np.testing.assert_allclose(g["node_lon_deg"][igso], 118.0, atol=1e-6)
    np.testing.assert_allclose(g["radius_m"][igso], GEOSYNC_A_M, atol=1e-3)
    meo = [k[s] for s in BDS_MEO_IDS]
    np.testing.assert_allclose(g["radius_m"][meo], 27_906.137e3, atol=1e-3)
    np.testing.assert_allclose(g["inclination_deg"][meo], 55.0, atol=1e-9)
    # Walker 24/3/1: three planes 120 deg apart, eight per plane
    raan = g["raan_ecef_deg"][meo]
    lattice = np.degrees(np.angle(np.mean(np.exp(3j * np.radians(raan))))) / 3.0
    dev = (raan - lattice + 60.0) % 120.0 - 60.0
    assert np.max(np.abs(dev)) < 1e-9
    assert sorted(np.bincount((np.round(((raan - lattice) % 360.0) / 120.0) % 3).astype(int))) == [8, 8, 8]
    # orbital period of the MEO: 12 h 53 min
    period = 2 * math.pi * math.sqrt(BDS_MEO_A_M**3 / 3.986004418e14)
    assert period == pytest.approx(12 * 3600 + 53 * 60, abs=60)


def test_nominal_velocity_is_derivative_of_position():
    nc = NominalConstellation(("BDS", "GPS"))
    ids = nc.satellite_ids()
    assert len(ids) == 54
    t = NOMINAL_EPOCH_GPS_S + 5000.0
    p1, p0 = nc.states(ids, t + 0.5).pos_ecef_m, nc.states(ids, t - 0.5).pos_ecef_m
    np.testing.assert_allclose(p1 - p0, nc.states(ids, t).vel_ecef_mps, atol=2e-4)


def test_nominal_bds_against_real_sp3(sp3: Sp3Orbits):
    """The nominal BDS-3 model against the real constellation (CODE SP3, 2021-04-28 18-24 h).

    The SP3 holds no BDS GEO (CODE MGEX did not process them in 2021), so the GEO longitudes
    are checked on the nominal model only (above). IGSO: the BDS-2 IGSO C06-C08 cross the equator
    at ~118-120 E (the nominal 118 E); BDS-3 C38-C40 cross at ~104-112 E (so the nominal IGSO
    node is the BDS-2 one, as the brief asks). Inclinations 51-60 deg (BDS-2 IGSO drift).
    MEO: radius and inclination, the Walker 24/3/1 plane structure, and the nominal slots
    (fitted at 18:00) within 3 deg of the real satellites over the six hours (measured 2.5 deg).
    """
    ids = [s for s in sp3.satellite_ids() if s[0] == "C"]
    assert not {"C01", "C02", "C03", "C04", "C05"} & set(ids)
    nc = NominalConstellation(("BDS",))
    meo = list(BDS_MEO_IDS)
    igso = [s for s in ("C06", "C07", "C08", "C09", "C10", "C13", "C16", "C38", "C39", "C40")]
    for t in sp3.data.t_gps_s[[0, 36, 72]]:
        st = sp3.states(ids, t)
        g = inertial_orbit_geometry(st.pos_ecef_m, st.vel_ecef_mps)
        k = {s: i for i, s in enumerate(ids)}
        gi = {key: v[[k[s] for s in igso]] for key, v in g.items()}
        gm = {key: v[[k[s] for s in meo]] for key, v in g.items()}
        assert abs(np.mean(gi["radius_m"]) - GEOSYNC_A_M) < 150e3
        assert np.all(np.abs(gi["inclination_deg"] - 55.0) < 5.0)
        assert abs(np.mean(gi["inclination_deg"]) - 55.0) < 2.0
        np.testing.assert_allclose(gi["node_lon_deg"][:3], 118.0, atol=3.0)  # C06-C08
        assert abs(np.mean(gm["radius_m"]) - BDS_MEO_A_M) < 30e3
        assert np.all(np.abs(gm["radius_m"] - BDS_MEO_A_M) < 100e3)
        assert np.all(np.abs(gm["inclination_deg"] - 55.0) < 2.0)
        # real Walker structure: nodes within 2 deg of a 120-deg lattice, 8 per plane
        raan = gm["raan_ecef_deg"]
        lattice = np.degrees(np.angle(np.mean(np.exp(3j * np.radians(raan))))) / 3.0
        assert np.max(np.abs((raan - lattice + 60.0) % 120.0 - 60.0)) < 2.0
        # nominal slots vs real satellites, angle seen from the earth's centre
        a, b = st.pos_ecef_m[[k[s] for s in meo]], nc.states(meo, t).pos_ecef_m
        ang = np.degrees(np.arccos(np.sum(a * b, 1) / np.linalg.norm(a, axis=1) / np.linalg.norm(b, axis=1)))
        assert np.max(ang) < 3.0


# --- ranging model ------------------------------------------------------------------------------------------
def _receiver():
    llh = np.array([math.radians(40.1), math.radians(118.6), 100.0])
    return llh_to_ecef(llh), mat_en(llh[0], llh[1]) @ np.array([200.0, 50.0, 3.0])


def test_range_matches_inertial_light_time_solution():
    """Two routes: (1) light_time_states + range_geometry in ECEF with the earth-rotation correction;
    (2) an independent light-time solution in the nominal model's inertial frame."""
    nc = NominalConstellation(("BDS", "GPS"))
    ids = nc.satellite_ids()
    rx, _ = _receiver()
    t_r = NOMINAL_EPOCH_GPS_S + 4321.0
    st, geo = light_time_states(nc, ids, t_r, rx)

    def to_inertial(r_e, t):  # ECEF at t -> inertial frame (= ECEF at the nominal epoch)
        ang = -OMEGA_IE_RPS * (np.atleast_1d(t) - NOMINAL_EPOCH_GPS_S)
        return np.einsum("nij,nj->ni", earth_rotation_matrices(np.broadcast_to(ang, (len(r_e),))), r_e)

    rx_i = to_inertial(rx[None, :], t_r)[0]
    tau = np.zeros(len(ids))
    for _ in range(6):
        sat_i = to_inertial(nc.states(ids, t_r - tau).pos_ecef_m, t_r - tau)
        rho = np.linalg.norm(sat_i - rx_i, axis=1)
        tau = rho / C_MPS
    # float64 GPS seconds (~1.3e9 s) resolve 2.4e-7 s: ~1e-4 m of satellite motion or earth rotation
    np.testing.assert_allclose(geo.range_m, rho, rtol=0, atol=1e-4)
    np.testing.assert_allclose(predicted_range(rx, st.pos_ecef_m), rho, rtol=0, atol=1e-4)
    # the earth-rotation (Sagnac) effect is tens of metres, so this is a real check
    assert np.max(np.abs(np.linalg.norm(st.pos_ecef_m - rx, axis=1) - rho)) > 10.0


def test_range_rate_is_exact_receive_time_derivative():
    """Closed-form range rate vs a 4th-order central difference of the range over receive time
    (h = 30 s, truncation ~1e-7 m/s). The light-time factor it includes is ~1.5 mm/s."""
    nc = NominalConstellation(("BDS", "GPS"))
    ids = nc.satellite_ids()
    rx, v = _receiver()
    t0 = NOMINAL_EPOCH_GPS_S + 777.0
    _, geo = light_time_states(nc, ids, t0, rx, v)

    def rho(t):
        return light_time_states(nc, ids, t, rx + v * (t - t0))[1].range_m

    h = 30.0
    num = (8.0 * (rho(t0 + h) - rho(t0 - h)) - (rho(t0 + 2 * h) - rho(t0 - 2 * h))) / (12.0 * h)
    np.testing.assert_allclose(geo.range_rate_mps, num, rtol=0, atol=2e-5)
    assert np.max(np.abs(geo.range_rate_mps / geo.doppler_factor - geo.range_rate_mps)) > 5e-4
    # range_geometry alone (published states) gives the same rate
    st, _ = light_time_states(nc, ids, t0, rx, v)
    g2 = range_geometry(rx, st.pos_ecef_m, v, st.vel_ecef_mps)
    np.testing.assert_allclose(g2.range_rate_mps, geo.range_rate_mps, atol=1e-9)
