"""The element-wise error model equals the PSINS block-matrix form; discretisation checks."""

import math

import numpy as np
from scipy.linalg import expm

from fednav.service import earth
from fednav.service.ins import error_model as em


def _reference_F(lat_rad, h_m, vel_enu_mps, mat_nb, f_n_mps2):
    """PSINS ``etm`` blocks (dL, dlon, dh) converted to ENU metres by D F D^-1 (block form)."""
    sl, cl = math.sin(lat_rad), math.cos(lat_rad)
    tl, secl = sl / cl, 1.0 / cl
    r_m, r_n = earth.radii(lat_rad)
    rmh, rnh = r_m + h_m, r_n + h_m
    ve, vn, vu = vel_enu_mps
    w = earth.OMEGA_IE_RPS
    wie = np.array([0.0, w * cl, w * sl])
    wen = np.array([-vn / rmh, ve / rnh, ve * tl / rnh])
    Mp1 = np.array([[0.0, 0.0, 0.0], [-wie[2], 0.0, 0.0], [wie[1], 0.0, 0.0]])
    Mp2 = np.array(
        [[0.0, 0.0, vn / rmh**2], [0.0, 0.0, -ve / rnh**2], [ve * secl**2 / rnh, 0.0, -ve * tl / rnh**2]]
    )
    Mav = np.array([[0.0, -1.0 / rmh, 0.0], [1.0 / rnh, 0.0, 0.0], [tl / rnh, 0.0, 0.0]])
    Map = Mp1 + Mp2
    Avn = earth.skew(vel_enu_mps)
    Mvv = Avn @ Mav - earth.skew(2.0 * wie + wen)
    Mvp = Avn @ (Mp1 + Map)
    Mvp[2, 0] -= earth.G_EQUATOR_MPS2 * (5.27094e-3 * 2.0 * sl * cl + 2.32718e-5 * 4.0 * sl**3 * cl)
    Mvp[2, 2] += 3.086e-6
    Mpv = np.array([[0.0, 1.0 / rmh, 0.0], [secl / rnh, 0.0, 0.0], [0.0, 0.0, 1.0]])
    Mpp = np.array(
        [[0.0, 0.0, -vn / rmh**2], [ve * secl * tl / rnh, 0.0, -ve * secl / rnh**2], [0.0, 0.0, 0.0]]
    )
    D = np.array([[0.0, rnh * cl, 0.0], [rmh, 0.0, 0.0], [0.0, 0.0, 1.0]])
    Di = np.linalg.inv(D)
    F = np.zeros((15, 15))
    F[0:3, 0:3] = D @ Mpp @ Di
    F[0:3, 3:6] = D @ Mpv
    F[3:6, 0:3] = Mvp @ Di
    F[3:6, 3:6] = Mvv
    F[3:6, 6:9] = earth.skew(f_n_mps2)
    F[3:6, 12:15] = mat_nb
    F[6:9, 0:3] = Map @ Di
    F[6:9, 3:6] = Mav
    F[6:9, 6:9] = -earth.skew(wie + wen)
    F[6:9, 9:12] = -mat_nb
    return F


def test_elementwise_F_equals_block_form():
    rng = np.random.default_rng(4)
    for _ in range(50):
        lat = rng.uniform(-1.3, 1.3)
        h = rng.uniform(-100.0, 12000.0)
        v = rng.normal(size=3) * 150.0
        c = earth.rpy_to_mat_nb(rng.uniform(-1, 1, 3))
        f = np.array([0.0, 0.0, 9.8]) + rng.normal(size=3)
        ref = _reference_F(lat, h, v, c, f)
        got = em.continuous_F(lat, h, v, c, f)
        np.testing.assert_allclose(got, ref, rtol=1e-12, atol=1e-18)


def test_discretisation_against_matrix_exponential():
    rng = np.random.default_rng(5)
    F = em.continuous_F(
        0.7,
        1000.0,
        np.array([100.0, 50.0, 5.0]),
        earth.rpy_to_mat_nb([0.1, 0.05, 1.0]),
        np.array([0.5, -0.3, 9.8]),
    )
    noise = em.ImuNoise(arw=1e-5, vrw=1e-4, gyro_bias_rw=1e-9, accel_bias_rw=1e-7)
    Qc = em.continuous_Q(noise, np.eye(3))
    for T in (0.005, 0.1, 1.0):
        Phi, Qd = em.discretise(F, Qc, T)
        # Van Loan's exact discretisation
        n = 15
        M = np.zeros((2 * n, 2 * n))
        M[:n, :n], M[:n, n:], M[n:, n:] = -F, Qc, F.T
        E = expm(M * T)
        Phi_ref = E[n:, n:].T
        Qd_ref = Phi_ref @ E[:n, n:]
        # fourth-order series: neglected terms below 1e-6 of each entry (plus a T^5-scaled floor)
        np.testing.assert_allclose(Phi, Phi_ref, rtol=1e-6, atol=1e-9 * T**5 + 1e-16)
        # series truncation error O((F T)^3 Qc T) relative to the largest entry
        # measured: < 1e-7 relative at T <= 0.1 s (the 10 Hz major rate), ~8e-4 at T = 1 s
        rtol = 1e-6 if T <= 0.1 else 2e-3
        np.testing.assert_allclose(Qd, Qd_ref, rtol=rtol, atol=1e-9 * np.abs(Qd_ref).max())
    del rng


def test_one_table_of_navigation_error_names():
    """The 9 navigation errors have one table of public names; evaluation, the recording and the
    error-state labels all read it (no second vocabulary)."""
    from fednav.service import evaluation
    from fednav.service.transport import rerun_paths

    assert tuple(n.state for n in em.NAV_ERRORS) == em.STATE_LABELS[em.NAV]
    assert rerun_paths.ERROR_NAMES == tuple(n.recording for n in em.NAV_ERRORS)
    assert rerun_paths.STD_SCALARS == tuple(n.std for n in em.NAV_ERRORS)
    e9 = np.array([1.0, 2.0, 3.0, 0.1, 0.2, 0.3, earth.ARCSEC, 2 * earth.ARCSEC, 3 * earth.ARCSEC])
    rep = evaluation.report_errors(e9)
    assert list(rep) == list(evaluation.REPORT_KEYS)
    assert (rep["lon_m"], rep["lat_m"], rep["h_m"]) == (1.0, 2.0, 3.0)  # lat_m is north, lon_m east
    assert np.allclose([rep["phi_e_arcsec"], rep["phi_n_arcsec"], rep["phi_u_arcsec"]], [1, 2, 3])
    errors, bounds = evaluation.recording_errors(e9, np.diag(np.r_[np.ones(6), np.full(3, earth.ARCSEC**2)]))
    assert (errors["east_m"], errors["north_m"], errors["up_m"]) == (1.0, 2.0, 3.0)
    assert np.allclose([bounds["east_m"], bounds["phi_u_arcsec"]], [3.0, 3.0])
    rms, mx = evaluation.error_stats(np.vstack([e9, -2 * e9]))
    assert np.isclose(rms["lat_m"], np.sqrt((4 + 16) / 2)) and np.isclose(mx["lon_m"], 2.0)
