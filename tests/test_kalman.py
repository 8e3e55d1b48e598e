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


@pytest.mark.parametrize("r_shape", ["diag", "matrix", "bank"])
@pytest.mark.parametrize("masked", [False, True])
def test_one_member_path_equals_the_bank_path(r_shape, masked):
    """A bank of one (loosely coupled, transfer alignment) takes its own (n, n) path with LAPACK's
    solves: every output equals the batched path's for the same member (a bank of two identical
    members takes the batched path) to rounding."""
    rng = np.random.default_rng(11)
    n, m = 15, 6
    x = rng.normal(size=(1, n))
    P = _random_spd(rng, n, 0.1)[None]
    H = rng.normal(size=(m, n))
    Rm = _random_spd(rng, m, 0.5)
    R = {"diag": np.diag(Rm).copy(), "matrix": Rm, "bank": Rm[None]}[r_shape]
    z = rng.normal(size=m)
    mask = np.array([[True, True, False, True, True, False]]) if masked else None
    x1, P1, r1 = kalman.update(x, P, z, H, R) if mask is None else kalman.update(x, P, z, H, R, mask=mask)
    R2 = R if r_shape != "bank" else np.concatenate([R, R])
    mask2 = None if mask is None else np.concatenate([mask, mask])
    x2, P2, r2 = kalman.update(np.concatenate([x, x]), np.concatenate([P, P]), z, H, R2, mask=mask2)
    np.testing.assert_allclose(x1[0], x2[0], rtol=1e-12, atol=1e-14)
    np.testing.assert_allclose(P1[0], P2[0], rtol=1e-12, atol=1e-14)
    for name in ("innovation", "S", "whitened", "standardised", "nis", "K"):
        np.testing.assert_allclose(getattr(r1, name)[0], getattr(r2, name)[0], rtol=1e-12, atol=1e-14)
    assert r1.dof[0] == r2.dof[0] == (4 if masked else 6)
    assert x1.shape == (1, n) and P1.shape == (1, n, n) and r1.S.shape == (1, m, m)
    if masked:
        np.testing.assert_array_equal(r1.K[0][:, ~mask[0]], 0.0)


def test_one_member_path_refuses_what_the_bank_path_refuses():
    P = np.eye(3)[None]
    H = np.ones((1, 3))
    with pytest.raises(kalman.NotPositiveDefinite):
        kalman.update(np.zeros((1, 3)), P, np.zeros(1), H, -10.0 * np.eye(1))
    # a NaN noise is not caught here, as on the bank path (callers screen their inputs): the
    # result is not finite, never a number that looks usable
    for B in (1, 2):
        nan_R = np.full((1, 1), np.nan)
        x, _, res = kalman.update(np.zeros((B, 3)), np.repeat(P, B, 0), np.zeros(1), H, nan_R)
        assert not np.isfinite(x).any() and not np.isfinite(res.nis).any()
    np.testing.assert_array_equal(kalman.is_positive_definite(-np.eye(3)[None]), [False])
    np.testing.assert_array_equal(kalman.is_positive_definite(np.full((1, 3, 3), np.nan)), [False])
    np.testing.assert_array_equal(kalman.is_positive_definite(np.eye(3)[None]), [True])
