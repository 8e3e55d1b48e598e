"""Batched Kalman bank against independent textbook single filters."""

import numpy as np
import pytest

from fednav.service.estimation import kalman


def _random_spd(rng, n, scale=1.0):
    A = rng.normal(size=(n, n))
    return scale * (A @ A.T + n * np.eye(n))


def _single_filter_step(x, P, Phi, Q, z, H, R):
    """Textbook reference: explicit inverse, Joseph form (what the bank must reproduce)."""
    x = Phi @ x
    P = Phi @ P @ Phi.T + Q
    S = H @ P @ H.T + R
    K = P @ H.T @ np.linalg.inv(S)
    r = z - H @ x
    x = x + K @ r
    IKH = np.eye(len(x)) - K @ H
    P = IKH @ P @ IKH.T + K @ R @ K.T
    return x, P, float(r @ np.linalg.inv(S) @ r)


def test_bank_equals_independent_filters():
    rng = np.random.default_rng(7)
    B, n, m = 6, 15, 6
    x = rng.normal(size=(B, n))
    P = np.stack([_random_spd(rng, n, 0.1) for _ in range(B)])
    xs, Ps = x.copy(), P.copy()
    for _ in range(25):
        Phi = np.eye(n) + 0.01 * rng.normal(size=(n, n))
        Q = np.stack([_random_spd(rng, n, 1e-3) for _ in range(B)])
        H = rng.normal(size=(B, m, n))
        R = np.stack([_random_spd(rng, m, 0.5) for _ in range(B)])
        z = rng.normal(size=(B, m))
        x, P = kalman.predict(x, P, Phi, Q)
        x, P, res = kalman.update(x, P, z, H, R)
        for b in range(B):
            xs[b], Ps[b], nis = _single_filter_step(xs[b], Ps[b], Phi, Q[b], z[b], H[b], R[b])
            assert res.nis[b] == pytest.approx(nis, rel=1e-9)
        np.testing.assert_allclose(x, xs, atol=1e-10, rtol=0)
        np.testing.assert_allclose(P, Ps, atol=1e-10, rtol=0)


def test_mask_equals_dropping_rows():
    rng = np.random.default_rng(8)
    n, m = 9, 5
    x = rng.normal(size=(1, n))
    P = _random_spd(rng, n)[None]
    H = rng.normal(size=(m, n))
    R = np.diag(rng.uniform(0.5, 2.0, m))
    z = rng.normal(size=m)
    mask = np.array([[True, False, True, True, False]])
    xm, Pm, res = kalman.update(x, P, z, H, R, mask=mask)
    keep = mask[0]
    xr, Pr, resr = kalman.update(x, P, z[keep], H[keep], R[np.ix_(keep, keep)])
    np.testing.assert_allclose(xm, xr, atol=1e-12)
    np.testing.assert_allclose(Pm, Pr, atol=1e-12)
    assert res.nis[0] == pytest.approx(resr.nis[0], rel=1e-12)
    assert res.dof[0] == 3
    np.testing.assert_array_equal(res.K[0][:, ~keep], 0.0)  # excluded gain columns exactly zero


def test_whitened_and_standardised_innovations():
    rng = np.random.default_rng(9)
    n, m = 4, 3
    P = _random_spd(rng, n)[None]
    H = rng.normal(size=(m, n))
    R = _random_spd(rng, m)
    z = rng.normal(size=m)
    _, _, res = kalman.update(np.zeros((1, n)), P, z, H, R)
    S = H @ P[0] @ H.T + R
    assert res.nis[0] == pytest.approx(z @ np.linalg.solve(S, z), rel=1e-12)
    np.testing.assert_allclose(res.standardised[0], z / np.sqrt(np.diag(S)), rtol=1e-12)
    np.testing.assert_allclose(np.linalg.cholesky(S) @ res.whitened[0], z, atol=1e-12)


def test_non_positive_definite_detected():
    P = np.stack([np.eye(3), np.diag([1.0, -1.0, 1.0]), np.full((3, 3), np.nan)])
    np.testing.assert_array_equal(kalman.is_positive_definite(P), [True, False, False])
    with pytest.raises(kalman.NotPositiveDefinite):
        kalman.update(np.zeros((1, 3)), -np.eye(3)[None], np.zeros(1), np.ones((1, 3)), -10 * np.eye(1))
