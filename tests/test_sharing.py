"""Sharing strategies: conservation, positivity, the papers' formulas, and the information algebra.

Closed-form references (the printed formulas of seeds 000, 002, 004) and invariants on random
SPD covariances. The filter-level consequences (scalar sharing == centralised, vector sharing
overconfident) are in tests/test_federated.py.
"""

import typing

import numpy as np
import pytest

from fednav.service.config import SharingName
from fednav.service.estimation.federated import sharing
from fednav.service.estimation.federated.sharing import MIN_SHARE, SharingContext, get_strategy
from fednav.service.estimation.kalman import information_fusion

ALL = sorted(sharing.STRATEGIES)


def _random_spd(rng, n, scales=None):
    A = rng.normal(size=(n, n))
    P = A @ A.T + 0.1 * np.eye(n)
    if scales is not None:  # INS-like: wildly different units per state
        P = P * np.outer(scales, scales)
    return P


def _ins_like_scales(rng):
    return np.concatenate(
        [np.full(3, 5.0), np.full(3, 0.05), np.full(3, 5e-5), np.full(3, 5e-8), np.full(3, 1e-3)]
    ) * rng.uniform(0.5, 2.0, 15)


def test_registry_matches_config_names():
    assert set(sharing.STRATEGIES) == set(typing.get_args(SharingName))
    for name in ALL:
        assert get_strategy(name).name == name
    with pytest.raises(ValueError, match="unknown sharing strategy"):
        get_strategy("nope")


@pytest.mark.parametrize("name", ALL)
@pytest.mark.parametrize("N", [2, 3, 4])
@pytest.mark.parametrize("master_share", [0.0, 0.25])
def test_conservation_and_positivity_on_random_spd(name, N, master_share):
    """Every strategy: sum over locals + master share = 1 for every state (1e-12), every share > 0."""
    rng = np.random.default_rng(100 + N)
    strat = get_strategy(name)
    for trial in range(20):
        scales = _ins_like_scales(rng) if trial % 2 else None
        P = np.stack([_random_spd(rng, 15, scales) for _ in range(N)])
        fl = rng.random((N, 15)) < 0.2 if trial % 3 == 0 else None
        ctx = SharingContext(flagged_only=fl, floor_share=1e-3, master_share=master_share)
        G = strat.shares(P, ctx)
        assert G.shape == (N, 15)
        assert np.all(np.isfinite(G))
        assert np.all(G > 0.0)
        np.testing.assert_allclose(G.sum(axis=0) + master_share, 1.0, rtol=0, atol=1e-12)
        if strat.scalar:  # one share per local for all states
            np.testing.assert_allclose(G, G[:, :1] * np.ones((1, 15)), rtol=1e-12, atol=0)


@pytest.mark.parametrize("name", ALL)
def test_never_zero_under_extreme_covariances(name):
    """A local 1e15 times more (or less) accurate still leaves every share >= MIN_SHARE / 2."""
    rng = np.random.default_rng(3)
    P1 = _random_spd(rng, 15)
    P = np.stack([P1, 1e15 * P1, 1e-15 * P1])
    G = get_strategy(name).shares(P)
    assert np.all(G >= 0.5 * MIN_SHARE)
    np.testing.assert_allclose(G.sum(axis=0), 1.0, atol=1e-12)


def test_single_local_gets_everything_but_the_master_share():
    P = np.eye(15)[None]
    for name in ALL:
        G = get_strategy(name).shares(P, SharingContext(master_share=0.2))
        np.testing.assert_allclose(G, 0.8, atol=1e-15)


# --- the papers' formulas ----------------------------------------------------------------------
def _two_locals(rng):
    return np.stack([_random_spd(rng, 15, _ins_like_scales(rng)) for _ in range(2)])


def test_fixed_is_one_over_n():
    rng = np.random.default_rng(1)
    P = np.stack([_random_spd(rng, 15) for _ in range(3)])
    np.testing.assert_allclose(get_strategy("fixed").shares(P), 1.0 / 3.0, atol=1e-15)


def test_trace_is_seed000_eq36_and_equals_eigen_trace_inverse():
    rng = np.random.default_rng(2)
    P = np.stack([_random_spd(rng, 15, _ins_like_scales(rng)) for _ in range(3)])
    inv_tr = 1.0 / np.array([np.trace(p) for p in P])
    expect = inv_tr / inv_tr.sum()  # seed 000 eq (36)
    np.testing.assert_allclose(get_strategy("trace").shares(P)[:, 0], expect, rtol=1e-12)
    # seed 004 5.1 via eigenvalues: tr(Lambda) = tr(P)
    inv_lam = 1.0 / np.array([np.linalg.eigvalsh(p).sum() for p in P])
    np.testing.assert_allclose(
        get_strategy("eigen_trace_inverse").shares(P)[:, 0], inv_lam / inv_lam.sum(), rtol=1e-9
    )


def test_eigen_trace_as_printed_favours_the_less_accurate_local():
    """Seed 004 5.1 as printed: beta_i = tr(Lambda_i)/sum; flagged in the docstring."""
    rng = np.random.default_rng(4)
    P1 = _random_spd(rng, 15)
    P = np.stack([P1, 4.0 * P1])  # local 2 is less accurate
    G = get_strategy("eigen_trace").shares(P)
    np.testing.assert_allclose(G[:, 0], [0.2, 0.8], rtol=1e-12)


def test_diagonal_as_printed_seed004():
    rng = np.random.default_rng(5)
    P = _two_locals(rng)
    d1, d2 = np.diag(P[0]), np.diag(P[1])
    G = get_strategy("diagonal").shares(P)
    np.testing.assert_allclose(G[0], d1 / (d1 + d2), rtol=1e-12)  # a_i = P1_ii / (P1_ii + P2_ii)
    np.testing.assert_allclose(G[1], d2 / (d1 + d2), rtol=1e-12)


def test_edop_matches_the_printed_two_local_formula():
    rng = np.random.default_rng(6)
    P = _two_locals(rng)
    e1, e2 = (np.sqrt(np.trace(p @ p.T)) for p in P)  # EDOP_i = sqrt(tr(P_i P_i'))
    G = get_strategy("edop").shares(P)
    np.testing.assert_allclose(G[:, 0], [e2 / (e1 + e2), e1 / (e1 + e2)], rtol=1e-12)


def test_norm_weighted_matches_seed002_for_three_locals():
    """Seed 002 eq (18)-(21) prints alpha_j = sum_{i != j} A_i / (2 sum_i A_i) for N = 3."""
    rng = np.random.default_rng(7)
    P = np.stack([_random_spd(rng, 15) * s for s in (1.0, 3.0, 10.0)])
    A = np.array([np.sqrt(np.trace(p @ p)) for p in P])
    expect = np.array([(A.sum() - a) / (2.0 * A.sum()) for a in A])
    np.testing.assert_allclose(get_strategy("norm_weighted").shares(P)[:, 0], expect, rtol=1e-12)
    assert np.argmax(expect) == 0  # the most accurate local gets the largest share


def test_vector_is_eq13_normalised_over_locals():
    rng = np.random.default_rng(8)
    P = np.stack([_random_spd(rng, 15, _ins_like_scales(rng)) for _ in range(3)])
    inv = 1.0 / np.diagonal(P, axis1=1, axis2=2)
    expect = inv / inv.sum(axis=0)  # seed 000 eq (13) as read in docs/PAPERS.md (over subsystems k)
    np.testing.assert_allclose(get_strategy("vector").shares(P), expect, rtol=1e-12)
    # vector_conservative: the mean over states of those shares, as one scalar per local
    np.testing.assert_allclose(
        get_strategy("vector_conservative").shares(P)[:, 0], expect.mean(axis=1), rtol=1e-12
    )


def test_vector_floor_for_states_seen_only_through_flagged_rows():
    """Seed 000 eq (22) reading: flagged-only state j of local i gets exactly the floor in i; the
    other locals share the rest in proportion to their eq (13) weights; other states untouched."""
    rng = np.random.default_rng(9)
    P = np.stack([_random_spd(rng, 15, _ins_like_scales(rng)) for _ in range(3)])
    fl = np.zeros((3, 15), dtype=bool)
    fl[0, 3:6] = True  # local 0: velocity rows flagged (GNSS velocity fault)
    fl[:, 14] = True  # every local flagged on one state: nothing to prefer, eq (13) unchanged
    floor = 1e-3
    base = get_strategy("vector").shares(P)
    G = get_strategy("vector").shares(P, SharingContext(flagged_only=fl, floor_share=floor))
    np.testing.assert_allclose(G[0, 3:6], floor, rtol=1e-9)
    ratio = base[1, 3:6] / base[2, 3:6]
    np.testing.assert_allclose(G[1, 3:6] / G[2, 3:6], ratio, rtol=1e-9)
    np.testing.assert_allclose(G[1:, 3:6].sum(axis=0), 1.0 - floor, rtol=1e-12)
    untouched = np.r_[0:3, 6:15]
    np.testing.assert_allclose(G[:, untouched], base[:, untouched], rtol=1e-12)
    # with a master share the floor is a fraction of the locals' total
    Gm = get_strategy("vector").shares(
        P, SharingContext(flagged_only=fl, floor_share=floor, master_share=0.5)
    )
    np.testing.assert_allclose(Gm[0, 3:6], 0.5 * floor, rtol=1e-9)


def test_vector_conservative_lowers_a_flagged_local_share():
    rng = np.random.default_rng(10)
    P1 = _random_spd(rng, 15)
    P = np.stack([P1, P1])
    fl = np.zeros((2, 15), dtype=bool)
    fl[0, 3:6] = True
    G = get_strategy("vector_conservative").shares(P, SharingContext(flagged_only=fl, floor_share=1e-3))
    assert G[0, 0] < 0.5 < G[1, 0]
    np.testing.assert_allclose(G[0, 0], (12 * 0.5 + 3 * 1e-3) / 15, rtol=1e-12)


# --- information algebra of the reset ------------------------------------------------------------
def _reset_information(P_g, G):
    """sum_i (G_i^-1/2 P_g G_i^-1/2)^-1: the information the master gets back after a reset."""
    Y = np.zeros_like(P_g)
    for g in G:
        s = 1.0 / np.sqrt(g)
        Y += np.linalg.inv(s[:, None] * P_g * s[None, :])
    return Y


@pytest.mark.parametrize("name", [n for n in ALL if get_strategy(n).scalar])
def test_scalar_reset_preserves_information_exactly(name):
    """Scalar shares: sum_i (P_g / beta_i)^-1 = P_g^-1 (Carlson), to 1e-10 relative."""
    rng = np.random.default_rng(11)
    P_g = _random_spd(rng, 15)
    P_locals = np.stack([_random_spd(rng, 15) for _ in range(3)])
    G = get_strategy(name).shares(P_locals)
    Y = _reset_information(P_g, G)
    Yg = np.linalg.inv(P_g)
    np.testing.assert_allclose(Y, Yg, rtol=0, atol=1e-10 * np.abs(Yg).max())


def test_vector_reset_loses_off_diagonal_information_by_the_hadamard_factor():
    """Per-state shares: the returned information is Y_g o C, C_jk = sum_i sqrt(g_ij g_ik) <= 1
    (diagonal kept exactly, off-diagonals shrunk), i.e. NOT P_g^-1 for a correlated P_g."""
    rng = np.random.default_rng(12)
    P_g = _random_spd(rng, 15)
    P_locals = np.stack([_random_spd(rng, 15, _ins_like_scales(rng)) for _ in range(2)])
    G = get_strategy("vector").shares(P_locals)
    s = np.sqrt(G)
    C = s.T @ s  # C_jk = sum_i sqrt(g_ij g_ik)
    assert np.all(C <= 1.0 + 1e-12)
    np.testing.assert_allclose(np.diag(C), 1.0, atol=1e-12)
    Yg = np.linalg.inv(P_g)
    Y = _reset_information(P_g, G)
    np.testing.assert_allclose(Y, Yg * C, rtol=1e-8, atol=1e-10 * np.abs(Yg).max())
    assert np.abs(Y - Yg).max() > 1e-3 * np.abs(Yg).max()  # measurably different


# --- vector sharing along the eigen-directions of P_g (seed 000 eq 11) ------------------------------
def _eigen_case(rng, N=2, scales=None):
    P_locals = np.stack([_random_spd(rng, 15, scales) for _ in range(N)])
    return P_locals, information_fusion(np.zeros(P_locals.shape[:2]), P_locals)[1]


@pytest.mark.parametrize("N", [2, 3])
@pytest.mark.parametrize("master_share", [0.0, 0.3])
def test_vector_eigen_reset_preserves_information_exactly(N, master_share):
    """G_i = V diag(beta_i) V^-1 with V^-1 P_g V^-T diagonal: sum_i G_i = (1 - m) I as MATRICES, and
    the reset covariances return exactly the fused information, sum_i P_i^-1 = (1 - m) P_g^-1,
    also on INS-like scales (1e-8 .. 5) and with flagged states."""
    rng = np.random.default_rng(21 + N)
    strat = get_strategy("vector_eigen")
    for trial in range(6):
        scales = _ins_like_scales(rng) if trial % 2 else None
        P_locals, P_g = _eigen_case(rng, N, scales)
        fl = rng.random((N, 15)) < 0.3 if trial >= 3 else None
        plan = strat.plan(P_locals, P_g, SharingContext(flagged_only=fl, master_share=master_share))
        V = plan.scale[:, None] * plan.directions
        Vinv = np.linalg.inv(V)
        np.testing.assert_allclose(Vinv @ P_g @ Vinv.T, np.diag(plan.lam), atol=1e-9 * plan.lam.max())
        G = np.stack([V @ np.diag(b) @ Vinv for b in plan.shares])
        Gs = G * plan.scale[None, None, :] / plan.scale[None, :, None]  # diag(s)^-1 G diag(s): O(1)
        np.testing.assert_allclose(Gs.sum(axis=0), (1.0 - master_share) * np.eye(15), atol=1e-12)
        np.testing.assert_allclose(np.diagonal(G, axis1=1, axis2=2), plan.state_shares(), atol=1e-12)
        Pi = plan.covariances(P_g)
        d = np.sqrt(np.diag(P_g))  # compare in correlation units (raw information spans 1e16)
        Y = sum(np.linalg.inv(p / np.outer(d, d)) for p in Pi)
        Yg = np.linalg.inv(P_g / np.outer(d, d))
        np.testing.assert_allclose(Y, (1.0 - master_share) * Yg, rtol=0, atol=1e-8 * np.abs(Yg).max())
        # process noise: one scalar per local, summing to the locals' total (conserves Q^-1 too)
        assert plan.q_shares is not None and np.all(plan.q_shares > 0)
        np.testing.assert_allclose(plan.q_shares.sum(), 1.0 - master_share, atol=1e-12)


def test_vector_eigen_is_unit_free_and_prefers_the_accurate_local():
    """Rescaling the states (metres -> millimetres, rad -> arcsec) changes no share; along a
    direction where local 0 is 100x more accurate it gets ~100/101 of the information."""
    rng = np.random.default_rng(5)
    P0 = _random_spd(rng, 15)
    P1 = 100.0 * P0  # local 1 is 100x worse along every direction
    P_locals = np.stack([P0, P1])
    P_g = information_fusion(np.zeros(P_locals.shape[:2]), P_locals)[1]
    strat = get_strategy("vector_eigen")
    b = strat.plan(P_locals, P_g).shares
    np.testing.assert_allclose(b[0], 100.0 / 101.0, rtol=1e-9)
    D = np.diag(10.0 ** rng.uniform(-6, 6, 15))
    b_scaled = strat.plan(D @ P_locals @ D, D @ P_g @ D).shares
    np.testing.assert_allclose(b_scaled, b, rtol=1e-9)


def test_vector_eigen_floor_applies_to_directions_on_flagged_states():
    """Eq (22) per direction: with P_g diagonal the directions are the states, so a state local 0
    saw only through flagged rows gets exactly the floor share there, the others are untouched."""
    P_locals = np.stack([np.diag(np.linspace(1.0, 2.0, 15)), np.diag(np.linspace(3.0, 1.0, 15))])
    P_g = information_fusion(np.zeros(P_locals.shape[:2]), P_locals)[1]
    fl = np.zeros((2, 15), dtype=bool)
    fl[0, 3:6] = True
    strat = get_strategy("vector_eigen")
    base = strat.plan(P_locals, P_g).state_shares()
    G = strat.plan(P_locals, P_g, SharingContext(flagged_only=fl, floor_share=0.05)).state_shares()
    np.testing.assert_allclose(G[0, 3:6], 0.05, rtol=1e-9)
    np.testing.assert_allclose(G[1, 3:6], 0.95, rtol=1e-9)
    keep = np.r_[0:3, 6:15]
    np.testing.assert_allclose(G[:, keep], base[:, keep], rtol=1e-12)
