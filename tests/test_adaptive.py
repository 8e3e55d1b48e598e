"""Sage-Husa R adaptation and chi2-triggered fading factors (service/estimation/adaptive)."""

from __future__ import annotations

import numpy as np
import pytest

from fednav.service.estimation import kalman
from fednav.service.estimation.adaptive import (
    SageHusaR,
    chi2_threshold,
    faded_covariance,
    fading_factors,
    sage_husa_weight,
)


def test_weight_sequence_hand_computed():
    a = 0.97
    assert sage_husa_weight(0, a) == pytest.approx(1.0)
    assert sage_husa_weight(1, a) == pytest.approx(0.03 / (1 - 0.97**2))
    assert sage_husa_weight(10_000, a) == pytest.approx(1 - a)


def test_two_steps_hand_computed():
    sh = SageHusaR(np.array([[2.0]]), B=1, a=0.97, restart=False)
    R = sh.update(np.array([[3.0]]), np.array([[[1.0]]]))  # d_0 = 1: R = 9 - 1
    assert R[0, 0, 0] == pytest.approx(8.0)
    d1 = 0.03 / (1 - 0.97**2)
    R = sh.update(np.array([[1.0]]), np.array([[[1.0]]]))  # sample 1 - 1 = 0
    assert R[0, 0, 0] == pytest.approx((1 - d1) * 8.0)
    assert sh.fallbacks[0] == 0


def test_fallback_keeps_previous_R_when_not_positive_definite():
    R0 = np.diag([2.0, 3.0])
    sh = SageHusaR(R0, B=2, a=0.95, restart=False)
    r = np.array([[0.0, 0.0], [2.0, 2.0]])
    HPHt = np.broadcast_to(np.eye(2) * 5.0, (2, 2, 2))
    R = sh.update(r, HPHt)  # member 0: sample -5 I (not PD) -> keeps R0; member 1: [[-1, 4],[4,-1]]
    np.testing.assert_allclose(R[0], R0)
    np.testing.assert_allclose(R[1], R0)
    assert list(sh.fallbacks) == [1, 1]
    assert list(sh.k) == [1, 1]


def test_mask_leaves_unmeasured_rows():
    sh = SageHusaR(np.diag([2.0, 3.0]), B=1, a=0.95, restart=False)
    sh.k[:] = 5
    d = sage_husa_weight(5, 0.95)
    R = sh.update(np.array([[2.0, 100.0]]), np.diag([1.0, 1.0])[None], mask=np.array([[True, False]]))
    assert R[0, 0, 0] == pytest.approx((1 - d) * 2.0 + d * 3.0)
    assert R[0, 1, 1] == 3.0 and R[0, 0, 1] == 0.0


def test_restart_rule_resets_count_when_weight_converged():
    sh = SageHusaR(np.eye(1), B=1, a=0.95, restart=True, restart_tol=1e-2)
    ks = []
    for _ in range(200):
        sh.update(np.array([[1.0]]), np.zeros((1, 1, 1)) + 0.5)
        ks.append(int(sh.k[0]))
    # d_k - 0.05 < 5e-4  <=>  0.95^(k+1) < ~0.0099  <=>  k + 1 >= 90
    assert sh.restarts[0] >= 2
    assert max(ks) <= 90 and 0 in ks


@pytest.mark.parametrize("restart", [False, True])
def test_adaptive_R_converges_to_true_R_on_stationary_case(restart):
    """A static 2-state bank measured directly with correlated noise: R starts 10x too large and
    converges to the true R (fading-memory average; with restarts the time average)."""
    rng = np.random.default_rng(7)
    R_true = np.array([[0.04, 0.01], [0.01, 0.09]])
    Lr = np.linalg.cholesky(R_true)
    B, n = 4, 2
    x_true = rng.standard_normal((B, n))
    x = np.zeros((B, n))
    P = np.broadcast_to(np.eye(n) * 100.0, (B, n, n)).copy()
    Q = np.eye(n) * 1e-8
    H = np.eye(n)
    sh = SageHusaR(10.0 * R_true, B=B, a=0.98, restart=restart)
    hist = []
    for k in range(3000):
        x, P = kalman.predict(x, P, np.eye(n), Q)
        z = x_true + (Lr @ rng.standard_normal((B, n, 1)))[:, :, 0]
        r = z - x
        R = sh.update(r, P).copy()
        x, P, _ = kalman.update(x, P, z, H, R)
        if k >= 1000:
            hist.append(R)
    R_mean = np.mean(hist, axis=(0, 1))
    np.testing.assert_allclose(R_mean, R_true, rtol=0.1, atol=0.004)


def test_fading_hand_computed_and_engages_only_above_threshold():
    H = np.array([[1.0, 0.0]])
    J = np.diag([1.0, 4.0])[None]
    Bk = np.array([[[1.0]]])
    thr = chi2_threshold(1, 0.05)
    assert thr == pytest.approx(3.841458820694124)
    res = fading_factors(np.array([[4.0]]), H, J, Bk, thr, thr)  # gamma = 16 / 2 = 8 > 3.84
    assert res.gamma[0] == pytest.approx(8.0)
    assert res.triggered[0]
    s0 = np.sqrt(16.0 / thr - 1.0)
    np.testing.assert_allclose(res.s[0], [s0, 1.0])  # state 1 is not observed: keeps 1
    # the faded row passes its test exactly: r^2 / (s^2 j + b) = eps
    assert 16.0 / (s0**2 * 1.0 + 1.0) == pytest.approx(thr)
    Q = np.diag([0.1, 0.2])[None]
    np.testing.assert_allclose(faded_covariance(J, res.s, Q)[0], np.diag([s0**2 + 0.1, 4.2]))
    below = fading_factors(np.array([[2.0]]), H, J, Bk, thr, thr)  # gamma = 2 < 3.84
    assert not below.triggered[0]
    np.testing.assert_allclose(below.s[0], [1.0, 1.0])


def test_fading_row_below_its_own_threshold_keeps_one_and_shared_state_takes_max():
    # two rows, both observing state 0; row 1 also state 1
    H = np.array([[1.0, 0.0], [1.0, 1.0]])
    J = np.eye(2)[None]
    Bk = np.eye(2)[None] * 0.5
    thr = chi2_threshold(2, 0.01)
    eps = chi2_threshold(1, 0.01)
    r = np.array([[0.1, 10.0]])
    res = fading_factors(r, H, J, Bk, thr, eps)
    assert res.triggered[0]
    assert res.row_factors[0, 0] == 1.0
    s1 = np.sqrt((100.0 / eps - 0.5) / 2.0)  # (H J H')_11 = 2
    np.testing.assert_allclose(res.s[0], [s1, s1])


def test_fading_statistic_is_chi2_distributed_when_consistent():
    """With a consistent model the trigger rate equals the false-alarm probability."""
    rng = np.random.default_rng(3)
    B, n, m = 20000, 3, 2
    H = np.array([[1.0, 0.0, 1.0], [0.0, 1.0, 0.0]])
    J = np.broadcast_to(np.diag([1.0, 2.0, 0.5]), (B, n, n))
    Bk = np.broadcast_to(np.diag([0.3, 0.4]), (B, m, m))
    S = H @ J[0] @ H.T + Bk[0]
    r = rng.standard_normal((B, m)) @ np.linalg.cholesky(S).T
    res = fading_factors(r, H, J, Bk, chi2_threshold(m, 0.05), chi2_threshold(1, 0.05))
    assert res.triggered.mean() == pytest.approx(0.05, abs=0.006)
    assert np.all(res.s[~res.triggered] == 1.0)


def test_scaled_fading_shrinks_a_correlated_direction_added_form_never_does():
    """Eq 8 literal (S J S') with factors that differ between correlated states is smaller than J
    along some direction (the hand case J = [[1, 1], [1, 1]], s = (2, 1), v = (1, -3): v'(SJS' -
    J)v = -3); the added form J + T J T', T = sqrt(S^2 - I), keeps the same diagonal and is >= J."""
    J = np.array([[[1.0, 1.0], [1.0, 1.0]]])
    s = np.array([[2.0, 1.0]])
    Q = np.zeros_like(J)
    v = np.array([1.0, -3.0])
    scaled = faded_covariance(J, s, Q, "scaled")[0]
    added = faded_covariance(J, s, Q, "added")[0]
    assert v @ (scaled - J[0]) @ v == pytest.approx(-3.0)
    np.testing.assert_allclose(added, [[4.0, 1.0], [1.0, 1.0]])
    np.testing.assert_allclose(np.diag(added), np.diag(scaled))
    # random correlated covariances and factors: the added form dominates J, the scaled form not
    rng = np.random.default_rng(5)
    A = rng.standard_normal((200, 6, 6))
    Jr = A @ np.swapaxes(A, 1, 2) + 1e-6 * np.eye(6)
    sr = np.where(rng.random((200, 6)) < 0.5, 1.0, 1.0 + 2.0 * rng.random((200, 6)))
    Qr = np.zeros_like(Jr)
    d_add = np.linalg.eigvalsh(faded_covariance(Jr, sr, Qr, "added") - Jr).min(axis=1)
    d_sca = np.linalg.eigvalsh(faded_covariance(Jr, sr, Qr, "scaled") - Jr).min(axis=1)
    assert np.all(d_add > -1e-9)
    assert np.mean(d_sca < -1e-6) > 0.5
    np.testing.assert_allclose(
        np.diagonal(faded_covariance(Jr, sr, Qr, "added"), axis1=1, axis2=2),
        np.diagonal(faded_covariance(Jr, sr, Qr, "scaled"), axis1=1, axis2=2),
    )
    with pytest.raises(ValueError):
        faded_covariance(J, s, Q, "other")
