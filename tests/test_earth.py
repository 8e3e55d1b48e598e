"""Earth model against closed-form WGS-84 values; rotations against scipy.spatial.transform."""

import math

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from fednav.service import earth


def test_gravity_closed_form():
    # Somigliana at the equator and the poles (NIMA TR8350.2 table 3.4), sea level
    assert earth.gravity_normal(0.0, 0.0) == pytest.approx(9.7803253359, abs=1e-10)
    assert earth.gravity_normal(math.pi / 2, 0.0) == pytest.approx(9.8321849378, abs=1e-9)
    # free-air gradient ~ -3.086e-6 s^-2 at the equator
    dg = earth.gravity_normal(0.0, 1000.0) - earth.gravity_normal(0.0, 0.0)
    assert dg == pytest.approx(-3.086e-3, rel=2e-3)


def test_radii_closed_form():
    r_m, r_n = earth.radii(0.0)
    assert r_n == pytest.approx(earth.A_M, abs=1e-6)
    assert r_m == pytest.approx(earth.A_M * (1 - earth.E2), abs=1e-6)  # 6335439.327 m
    assert r_m == pytest.approx(6335439.327, abs=1e-3)
    r_m, r_n = earth.radii(math.pi / 2)
    assert r_m == pytest.approx(r_n, abs=1e-6)
    assert r_n == pytest.approx(earth.A_M**2 / earth.B_M, abs=1e-6)  # 6399593.626 m


def test_llh_ecef_round_trip_and_known_points():
    np.testing.assert_allclose(earth.llh_to_ecef([0.0, 0.0, 0.0]), [earth.A_M, 0, 0], atol=1e-9)
    np.testing.assert_allclose(earth.llh_to_ecef([math.pi / 2, 0.0, 0.0]), [0, 0, earth.B_M], atol=1e-6)
    rng = np.random.default_rng(1)
    llh = np.column_stack(
        [rng.uniform(-1.5, 1.5, 200), rng.uniform(-3.1, 3.1, 200), rng.uniform(-5e3, 5e4, 200)]
    )
    back = earth.ecef_to_llh(earth.llh_to_ecef(llh))
    np.testing.assert_allclose(back[:, :2], llh[:, :2], atol=1e-12)
    np.testing.assert_allclose(back[:, 2], llh[:, 2], atol=1e-6)


def test_enu_frame():
    ref = np.array([math.radians(40.1), math.radians(118.6), 100.0])
    up = earth.enu_to_ecef([0.0, 0.0, 10.0], ref) - earth.llh_to_ecef(ref)
    np.testing.assert_allclose(up / 10.0, earth.mat_en(ref[0], ref[1])[:, 2], atol=1e-12)
    p = earth.enu_to_ecef([12.0, -7.0, 3.0], ref)
    np.testing.assert_allclose(earth.ecef_to_enu(p, ref), [12.0, -7.0, 3.0], atol=1e-8)


def test_earth_and_transport_rate():
    lat = math.radians(40.0)
    w = earth.earth_rate_n(lat)
    assert np.linalg.norm(w) == pytest.approx(7.292115e-5, rel=1e-12)
    r_m, r_n = earth.radii(lat)
    wen = earth.transport_rate_n(lat, 0.0, np.array([0.0, 100.0, 0.0]))
    assert wen[0] == pytest.approx(-100.0 / r_m)


def test_rpy_matrix_against_scipy():
    rng = np.random.default_rng(2)
    for _ in range(200):
        r, p, y = rng.uniform(-3, 3), rng.uniform(-1.5, 1.5), rng.uniform(-3, 3)
        # mat_nb = Rz(yaw) Rx(pitch) Ry(roll): intrinsic z-x'-y'' = scipy "ZXY"
        ref = Rotation.from_euler("ZXY", [y, p, r]).as_matrix()
        m = earth.rpy_to_mat_nb([r, p, y])
        np.testing.assert_allclose(m, ref, atol=1e-14)
        np.testing.assert_allclose(earth.mat_nb_to_rpy(m), [r, p, y], atol=1e-12)


def test_quaternions_against_scipy():
    rng = np.random.default_rng(3)
    for _ in range(200):
        rv = rng.normal(size=3) * rng.uniform(1e-9, 3.0)
        q = earth.rotvec_to_quat(rv)
        ref = Rotation.from_rotvec(rv)
        x, y, z, w = ref.as_quat()
        np.testing.assert_allclose(q * np.sign(q[0]), np.array([w, x, y, z]) * np.sign(w), atol=1e-14)
        np.testing.assert_allclose(earth.quat_to_mat(q), ref.as_matrix(), atol=1e-14)
        np.testing.assert_allclose(earth.quat_to_rotvec(q), ref.as_rotvec(), atol=1e-12)
        np.testing.assert_allclose(earth.mat_to_quat(ref.as_matrix()), q * np.sign(q[0]), atol=1e-12)
        rv2 = rng.normal(size=3)
        prod = earth.quat_mul(q, earth.rotvec_to_quat(rv2))
        np.testing.assert_allclose(
            earth.quat_to_mat(prod), (ref * Rotation.from_rotvec(rv2)).as_matrix(), atol=1e-13
        )
    np.testing.assert_allclose(earth.skew([1, 2, 3]) @ [4, 5, 6], np.cross([1, 2, 3], [4, 5, 6]))


def test_heading_convention():
    assert earth.heading_deg_from_yaw(math.radians(-90.0)) == pytest.approx(90.0)  # east
    assert earth.yaw_from_heading_deg(270.0) == pytest.approx(math.radians(90.0))
    # body forward axis of heading 90 deg points east
    c = earth.rpy_to_mat_nb([0.0, 0.0, earth.yaw_from_heading_deg(90.0)])
    np.testing.assert_allclose(c @ [0, 1, 0], [1, 0, 0], atol=1e-15)


def test_message_angle_signs_as_the_readme_states():
    """roll + : right wing (body x) down; pitch + : nose (body y) up; heading 90: nose east."""
    import numpy as np

    def axis_up(rpy, axis):
        return (earth.rpy_to_mat_nb(earth.rpy_from_msg_deg(rpy)) @ axis)[2]

    assert axis_up((10.0, 0.0, 0.0), [1.0, 0.0, 0.0]) < -0.17
    assert axis_up((0.0, 10.0, 0.0), [0.0, 1.0, 0.0]) > 0.17
    nose = earth.rpy_to_mat_nb(earth.rpy_from_msg_deg((0.0, 0.0, 90.0))) @ [0.0, 1.0, 0.0]
    assert np.allclose(nose, [1.0, 0.0, 0.0], atol=1e-12)
