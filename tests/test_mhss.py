"""MHSS on a Kalman filter bank (seed 001, docs/DESIGN.md): recursion, bank, tests, exclusion.

Linear model used throughout: states [east, north, up, clock] (random walk), satellites as
line-of-sight rows h = [-cos(el) sin(az), -cos(el) cos(az), -sin(el), 1] (the tightly coupled
pseudorange row without the INS). Monte Carlo runs use the bank's own (data-independent) gains
applied to many runs at once; one run is checked against the bank's own state update.
"""

from __future__ import annotations

import itertools
import math

import numpy as np
import pytest

from fednav.service.estimation import kalman
from fednav.service.estimation.integrity.mhss import (
    MhssBank,
    cross_predict,
    cross_update,
    horizontal_false_alarm_probability,
    k_fa,
    k_fa_horizontal,
    k_md,
    lambda_max_2x2,
    q_inv,
    residual_test,
    solution_separation,
)

N_X = 4
H_IDX, V_IDX = (0, 1), 2
AZ_EL_DEG = [(10, 70), (80, 35), (150, 20), (200, 55), (260, 15), (320, 40), (40, 25), (110, 60)]
IDS = [f"S{i}" for i in range(len(AZ_EL_DEG))]
PHI = np.eye(N_X)
PHI[3, 3] = 0.98  # a decaying "clock" keeps the model non-trivial
Q = np.diag([0.3, 0.3, 0.2, 1.0]) ** 2
P0 = np.diag([10.0, 10.0, 15.0, 30.0]) ** 2
SIGMA = 1.0


def h_row(sat: str) -> np.ndarray:
    az, el = (math.radians(a) for a in AZ_EL_DEG[IDS.index(sat)])
    return np.array([-math.cos(el) * math.sin(az), -math.cos(el) * math.cos(az), -math.sin(el), 1.0])


def rows(sats) -> np.ndarray:
    return np.array([h_row(s) for s in sats])


def z_score(
    sample: np.ndarray, expected: np.ndarray, runs: int, truth: np.ndarray | None = None
) -> np.ndarray:
    """Elementwise (S - expected) / sd(S) for zero-mean Gaussian sample covariances (n, n); the
    estimator's sd comes from ``truth`` (default: ``expected``)."""
    ref = expected if truth is None else truth
    d = np.diagonal(ref, axis1=-2, axis2=-1)
    sd = np.sqrt((d[..., :, None] * d[..., None, :] + ref**2) / runs)
    return (sample - expected) / sd


def run_mc(
    runs: int,
    steps: int,
    schedule: dict,
    sats0,
    seed: int,
    r_true=None,
    q_true=None,
    depth=2,
    fault=None,
    record=None,
):
    """Seeded Monte Carlo of the bank on the linear model.

    schedule: step -> ("rise", id) | ("set", id) | ("purge", id), applied after the prediction.
    r_true (per id) / q_true: truth noise (default = the filters' model). fault: (id, start, bias).
    Returns (bank, X (runs, B, n) member estimates, truth (runs, n), true_blocks, steps_log).
    """
    rng = np.random.default_rng(seed)
    q_true = Q if q_true is None else q_true
    bank = MhssBank.initial(np.zeros(N_X), P0, sats0, depth=depth, h_idx=H_IDX, v_idx=V_IDX)
    true_blocks = bank.blocks.copy()
    truth = rng.multivariate_normal(np.zeros(N_X), P0, size=runs)
    X = np.zeros((runs, bank.B, N_X))
    log = []
    for k in range(steps):
        bank.predict(PHI, Q)
        true_blocks = cross_predict(true_blocks, PHI, q_true)
        X = X @ PHI.T
        truth = truth @ PHI.T + rng.multivariate_normal(np.zeros(N_X), q_true, size=runs)
        if k in schedule:
            what, sid = schedule[k]
            sats = list(bank.sats)
            if what == "rise":
                sats.append(sid)
            else:
                sats.remove(sid)
            purge = [sid] if what == "purge" else []
            new = bank.rebuild(sats, purge=purge)
            # the true blocks follow the same mapping
            true_blocks = (
                MhssBank(bank.sats, bank.x, true_blocks, bank.depth, H_IDX, V_IDX).rebuild(sats, purge).blocks
            )
            X = X[:, new.sources]
            bank = new
        H = rows(bank.sats)
        m = len(bank.sats)
        r_model = np.full(m, SIGMA**2)
        rt = r_model if r_true is None else np.array([r_true[s] for s in bank.sats])
        upd = bank.update(np.zeros(m), H, r_model, np.arange(m))
        true_blocks = cross_update(
            true_blocks, upd.IKH[bank.pa], upd.IKH[bank.pb], upd.K[bank.pa], upd.K[bank.pb], rt
        )
        z = truth @ H.T + rng.standard_normal((runs, m)) * np.sqrt(rt)
        if fault is not None and fault[0] in bank.sats and k >= fault[1]:
            z[:, bank.sats.index(fault[0])] += fault[2]
        keep = ~bank.excl
        innov = (z[:, None, :] - X @ H.T) * keep[None]
        X = X + np.einsum("bij,rbj->rbi", upd.K, innov)
        if record is not None:
            log.append(record(bank, X, truth))
    return bank, X, truth, true_blocks, log


def separations(bank: MhssBank, X: np.ndarray):
    """Main-level (runs, N, n) and sub-level (runs, N, N-1, n) separations with their dP."""
    N = bank.N
    subs = 1 + np.arange(N)
    d_main = X[:, :1] - X[:, subs]
    P = bank.P
    Pc = bank.blocks[bank.main_blocks]
    dP_main = P[0][None] - Pc - np.swapaxes(Pc, 1, 2) + P[subs]
    mem = bank.subsub_members
    d_sub = X[:, subs][:, :, None] - X[:, mem]
    Ps = bank.blocks[bank.sub_blocks]
    dP_sub = P[subs][:, None] - Ps - np.swapaxes(Ps, -1, -2) + P[mem]
    return d_main, dP_main, d_sub, dP_sub


SCHEDULE = {4: ("rise", "S6"), 7: ("set", "S1"), 9: ("purge", "S2")}
RUNS = 20000


@pytest.fixture(scope="module")
def matched_mc():
    def record(bank, X, truth):
        t = bank.main_tests(k_fa(1e-3, bank.N), k_md(1e-3))
        e = X[:, 0] - truth
        return (t.hpl, t.vpl, np.linalg.norm(e[:, :2], axis=1).max(), np.abs(e[:, 2]).max())

    bank, X, truth, true_blocks, log = run_mc(RUNS, 12, SCHEDULE, IDS[:6], seed=1, record=record)
    return bank, X, truth, true_blocks, log


# --- multipliers and small helpers -------------------------------------------------------------------
def test_multipliers_are_the_standard_two_sided_gaussian_ones():
    assert q_inv(0.025) == pytest.approx(1.959963984540054, abs=1e-12)
    assert k_md(1e-3) == pytest.approx(3.090232306167813, abs=1e-12)
    # K_fa = Q^-1(P_FA / (2N)) = sqrt(2) erfinv(1 - P_FA / N)
    from scipy.special import erfinv

    assert k_fa(1e-4, 6) == pytest.approx(math.sqrt(2.0) * erfinv(1.0 - 1e-4 / 6), rel=1e-9)
    rng = np.random.default_rng(3)
    A = rng.standard_normal((50, 2, 2))
    M = A @ np.swapaxes(A, 1, 2)
    np.testing.assert_allclose(lambda_max_2x2(M), np.linalg.eigvalsh(M)[:, 1], rtol=1e-12)


def test_horizontal_false_alarm_probability_limits():
    k = 2.5
    assert horizontal_false_alarm_probability(np.diag([1.0, 1e-12]), k) == pytest.approx(
        2 * 0.0062096653, rel=1e-6
    )
    assert horizontal_false_alarm_probability(np.eye(2) * 4.0, k) == pytest.approx(
        math.exp(-k * k / 2), rel=1e-6
    )


# --- the recursion against Monte Carlo ------------------------------------------------------------------
def test_monte_carlo_run_equals_the_bank_state_update():
    """The vectorised Monte Carlo applies exactly the bank's update (one run re-done with the bank)."""
    rng = np.random.default_rng(7)
    bank = MhssBank.initial(np.zeros(N_X), P0, IDS[:6], depth=2, h_idx=H_IDX, v_idx=V_IDX)
    X = np.zeros((bank.B, N_X))
    truth = rng.multivariate_normal(np.zeros(N_X), P0)
    for _ in range(6):
        bank.predict(PHI, Q)
        X = X @ PHI.T
        truth = PHI @ truth + rng.multivariate_normal(np.zeros(N_X), Q)
        H = rows(bank.sats)
        z = H @ truth + rng.standard_normal(len(H))
        x_before = bank.x.copy()
        upd = bank.update(z, H, np.ones(len(H)), np.arange(len(H)))
        innov = (z[None] - X @ H.T) * ~bank.excl
        X = X + np.einsum("bij,bj->bi", upd.K, innov)
        np.testing.assert_allclose(x_before, X - np.einsum("bij,bj->bi", upd.K, innov), atol=1e-12)
    np.testing.assert_allclose(bank.x, X, atol=1e-10)


def test_cross_covariance_recursion_matches_monte_carlo(matched_mc):
    """Sample covariance of x_0 - x_n (and x_n - x_nm) over 20000 seeded runs, through a rising,
    a setting and an exclusion rebuild, agrees with dP = P00 - P0n - P0n' + Pnn elementwise
    within 5 sigma of the sample-covariance estimator."""
    bank, X, _, _, _ = matched_mc
    d_main, dP_main, d_sub, dP_sub = separations(bank, X)
    S_main = np.einsum("rni,rnj->nij", d_main, d_main) / RUNS
    S_sub = np.einsum("rnmi,rnmj->nmij", d_sub, d_sub) / RUNS
    zm = z_score(S_main, dP_main, RUNS)
    zs = z_score(S_sub, dP_sub, RUNS)
    assert np.max(np.abs(zm)) < 5.0, np.max(np.abs(zm))
    assert np.max(np.abs(zs)) < 5.0, np.max(np.abs(zs))
    # means are zero too (3-sigma... 5 over many components)
    mean_z = d_main.mean(0) / np.sqrt(np.diagonal(dP_main, axis1=1, axis2=2) / RUNS)
    assert np.max(np.abs(mean_z)) < 5.0
    # model matches truth: the filters are optimal, P_0n = P_00 and the shortcut is right here
    Pc = bank.blocks[bank.main_blocks]
    np.testing.assert_allclose(Pc, np.broadcast_to(bank.P[0], Pc.shape), rtol=1e-8, atol=1e-8)


def test_shortcut_is_wrong_when_the_filters_model_mismatches_the_truth():
    """Filters assume sigma = 1 m on every satellite; the truth has 0.5 to 4 m and 3x the process
    noise. The recursion run with the true noise (and the filters' gains) still matches Monte Carlo;
    the shortcut P_nn - P_00 is far off, whether from the filters' covariances or the true ones."""
    r_true = {s: v**2 for s, v in zip(IDS, [1.0, 4.0, 0.5, 3.0, 1.0, 2.0, 1.0, 1.0], strict=True)}
    runs = 20000
    bank, X, _, tb, _ = run_mc(runs, 8, {}, IDS[:6], seed=2, r_true=r_true, q_true=9.0 * Q, depth=1)
    subs = 1 + np.arange(bank.N)
    d = X[:, :1] - X[:, subs]
    S = np.einsum("rni,rnj->nij", d, d) / runs
    Pc_t = tb[bank.main_blocks]
    dP_rec = tb[0][None] - Pc_t - np.swapaxes(Pc_t, 1, 2) + tb[subs]
    dP_short_model = bank.P[subs] - bank.P[0][None]
    dP_short_true = tb[subs] - tb[0][None]
    assert np.max(np.abs(z_score(S, dP_rec, runs))) < 5.0
    # horizontal/vertical blocks of the shortcut are many sigmas off
    hv = np.ix_(range(bank.N), [0, 1, 2], [0, 1, 2])
    assert np.max(np.abs(z_score(S, dP_short_model, runs, dP_rec)[hv])) > 30.0
    assert np.max(np.abs(z_score(S, dP_short_true, runs, dP_rec)[hv])) > 30.0
    # and the cross-covariance is genuinely not P_00 under mismatch
    assert np.max(np.abs(Pc_t - tb[0][None])) > 0.05 * np.max(np.abs(tb[0][:3, :3]))


# --- bank vs separate filters ---------------------------------------------------------------------------
def test_bank_equals_separate_filters_closed_loop_with_rising_and_setting():
    """Every member of the bank (closed loop: main fed back, members shifted) equals a separate
    open-loop Kalman filter (kalman.update, rows deleted) using the available satellites minus
    its excluded ones, to 1e-10 -- through a rising and a setting satellite."""
    rng = np.random.default_rng(11)
    avail = (
        {k: IDS[:6] for k in range(5)}
        | {k: IDS[:7] for k in range(5, 9)}
        | {k: [s for s in IDS[:7] if s != "S1"] for k in range(9, 14)}
    )
    bank = MhssBank.initial(np.zeros(N_X), P0, avail[0], depth=2, h_idx=H_IDX, v_idx=V_IDX)
    ref = np.zeros(N_X)  # closed-loop reference ("the INS"): absorbs the main corrections
    sep: dict[tuple, tuple[np.ndarray, np.ndarray]] = {}
    truth = rng.multivariate_normal(np.zeros(N_X), P0)
    all_ids = IDS[:7]
    for E in [()] + [(s,) for s in all_ids] + [tuple(sorted(p)) for p in itertools.combinations(all_ids, 2)]:
        sep[E] = (np.zeros(N_X), P0.copy())
    for k in range(14):
        bank.predict(PHI, Q)
        ref = PHI @ ref
        truth = PHI @ truth + rng.multivariate_normal(np.zeros(N_X), Q)
        for E, (x, P) in sep.items():
            x1, P1 = kalman.predict(x[None], P[None], PHI, Q)
            sep[E] = (x1[0], P1[0])
        if tuple(bank.sats) != tuple(avail[k]):
            bank = bank.rebuild(avail[k])
        H_all = rows(bank.sats)
        y = H_all @ truth + SIGMA * rng.standard_normal(len(bank.sats))
        bank.update(y - H_all @ ref, H_all, np.full(len(y), SIGMA**2), np.arange(len(y)))
        dx0 = bank.x[0].copy()
        bank.shift(dx0)
        ref = ref + dx0
        for E, (x, P) in sep.items():
            use = [i for i, s in enumerate(bank.sats) if s not in E]
            if not use:
                continue
            x1, P1, _ = kalman.update(x[None], P[None], y[use], H_all[use], np.eye(len(use)) * SIGMA**2)
            sep[E] = (x1[0], P1[0])
        for i, excl in enumerate(bank.members):
            E = tuple(sorted(bank.sats[j] for j in excl))
            x_sep, P_sep = sep[E]
            np.testing.assert_allclose(bank.x[i] + ref, x_sep, atol=1e-10, rtol=0)
            np.testing.assert_allclose(bank.P[i], P_sep, atol=1e-10 * np.max(np.abs(P_sep)), rtol=0)


def test_rebuild_for_rising_satellite_copies_exact_blocks():
    bank = MhssBank.initial(np.zeros(N_X), P0, IDS[:4], depth=2, h_idx=H_IDX, v_idx=V_IDX)
    rng = np.random.default_rng(5)
    for _ in range(3):
        bank.predict(PHI, Q)
        H = rows(bank.sats)
        bank.update(H @ rng.standard_normal(N_X), H, np.ones(4), np.arange(4))
    new = bank.rebuild(IDS[:5])
    j = new.sats.index("S4")
    np.testing.assert_array_equal(new.P[1 + j], bank.P[0])  # sub j IS the old main
    np.testing.assert_array_equal(new.blocks[new.main_blocks[j]], bank.P[0])  # P_0j = P_00 at entry
    for n in range(4):  # sub n continues; P_0n continues; sub-sub (n, j) IS the old sub n
        np.testing.assert_array_equal(new.blocks[new.main_blocks[n]], bank.blocks[bank.main_blocks[n]])
        np.testing.assert_array_equal(new.P[new.index[(n, j)]], bank.P[1 + n])
    # exclusion: the new main is the old sub-filter of the purged satellite, subs its sub-subs
    purged = bank.rebuild([s for s in bank.sats if s != "S2"], purge=["S2"])
    np.testing.assert_array_equal(purged.x[0], bank.x[1 + 2])
    np.testing.assert_array_equal(purged.P[0], bank.P[1 + 2])
    for n, sid in enumerate(purged.sats):
        old_n = bank.sats.index(sid)
        np.testing.assert_array_equal(purged.P[1 + n], bank.P[bank.index[tuple(sorted((2, old_n)))]])
    # the sub-subs restart as copies of the new main
    np.testing.assert_array_equal(purged.P[purged.index[(0, 1)]], purged.P[0])


# --- detection: false alarms and protection levels --------------------------------------------------------
def test_false_alarm_rate_matches_p_fa(matched_mc):
    """P_FA = 0.05: each vertical test fires with probability exactly P_FA / N (two-sided
    Gaussian); their sum is P_FA; each horizontal test at the exact 2-D rate given dP (between
    P_FA/N and exp(-K^2/2)). Checked on 20000 independent runs at the last epoch, 4.5 sigma."""
    bank, X, _, _, _ = matched_mc
    p_fa, N = 0.05, bank.N
    t = solution_separation(
        np.zeros(N_X),
        bank.P[0],
        np.zeros((N, N_X)),
        bank.P[1 : 1 + N],
        bank.blocks[bank.main_blocks],
        k_fa(p_fa, N),
        k_md(1e-3),
        H_IDX,
        V_IDX,
    )
    d_main, dP_main, _, _ = separations(bank, X)
    fired_v = np.abs(d_main[:, :, V_IDX]) > t.T_v[None]
    fired_h = np.linalg.norm(d_main[:, :, :2], axis=2) > t.T_h[None]

    def within(count, p, n):
        return abs(count - n * p) < 4.5 * math.sqrt(n * p * (1 - p))

    for j in range(N):
        assert within(fired_v[:, j].sum(), p_fa / N, RUNS), (j, fired_v[:, j].sum())
        p_h = horizontal_false_alarm_probability(dP_main[j][:2, :2], t.k_fa)
        assert p_fa / N * 0.999 <= p_h <= math.exp(-(t.k_fa**2) / 2) * 1.001
        assert within(fired_h[:, j].sum(), p_h, RUNS), (j, fired_h[:, j].sum(), p_h * RUNS)
    assert within(fired_v.sum(), p_fa, RUNS)  # sum of the N per-test counts: expectation P_FA
    any_v = fired_v.any(axis=1).mean()
    assert any_v <= p_fa + 4.5 * math.sqrt(p_fa / RUNS)  # union bound


def test_chi2_horizontal_threshold_keeps_every_test_within_its_share(matched_mc):
    """horizontal_threshold = "chi2": K = sqrt(-2 ln(P_FA/N)) bounds the exact false-alarm
    probability of each 2-D test by P_FA/N for any separation ellipse (equality for a round one),
    where the Gaussian K can exceed it (up to exp(-K^2/2)). Exact probabilities by quadrature on
    the Monte Carlo's dP and on synthetic round/flat ellipses, and the MC counts (4.5 sigma)."""
    bank, X, _, _, _ = matched_mc
    p_fa, N = 0.05, bank.N
    k2 = k_fa_horizontal(p_fa, N, "chi2")
    assert k2 == pytest.approx(math.sqrt(-2.0 * math.log(p_fa / N)))
    assert k_fa_horizontal(p_fa, N, "gaussian") == k_fa(p_fa, N)
    with pytest.raises(ValueError):
        k_fa_horizontal(p_fa, N, "nope")
    share = p_fa / N
    for ratio in (1.0, 0.5, 0.1, 1e-3):  # eigenvalue ratio of the separation ellipse
        dP = np.diag([1.0, ratio])
        assert horizontal_false_alarm_probability(dP, k2) <= share * 1.001
    assert horizontal_false_alarm_probability(np.eye(2), k2) == pytest.approx(share, rel=1e-3)
    assert horizontal_false_alarm_probability(np.eye(2), k_fa(p_fa, N)) > 2.0 * share  # the defect
    t = bank.main_tests(k_fa(p_fa, N), k_md(1e-3), k2)
    np.testing.assert_allclose(t.T_v, bank.main_tests(k_fa(p_fa, N), k_md(1e-3)).T_v)  # vertical unchanged
    d_main, dP_main, _, _ = separations(bank, X)
    fired_h = np.linalg.norm(d_main[:, :, :2], axis=2) > t.T_h[None]  # thresholds use covariances only
    for j in range(N):
        p_h = horizontal_false_alarm_probability(dP_main[j][:2, :2], k2)
        assert p_h <= share * 1.001
        n = fired_h[:, j].sum()
        assert abs(n - RUNS * p_h) < 4.5 * math.sqrt(RUNS * p_h * (1 - p_h)), (j, n, RUNS * p_h)


def test_hpl_and_vpl_bound_the_true_error_fault_free(matched_mc):
    """Over 20000 runs x 12 epochs (P_FA = P_MD = 1e-3) no error exceeds its protection level."""
    _, _, _, _, log = matched_mc
    for hpl, vpl, herr_max, verr_max in log:
        assert herr_max < hpl
        assert verr_max < vpl


# --- snapshot special case ---------------------------------------------------------------------------------
def test_snapshot_case_reproduces_least_squares_solution_separation():
    """One update from a flat prior is weighted least squares: the bank's thresholds and PLs equal
    the closed-form snapshot solution-separation ones (dP_0n = P_n - P_0, S matrices), rel 1e-6.
    (The WG-C ARAIM ADD v3.0 Appendix D example could not be reconstructed: its ISM parameters and
    geometry table are not available here, and its PL is ARAIM's iterative allocation with nominal
    biases, not seed 001's max(T + a).)"""
    sats = IDS[:7]
    H = rows(sats)
    sig = np.array([0.8, 1.0, 1.5, 0.9, 2.0, 1.2, 1.1])
    W = np.diag(1.0 / sig**2)
    y = np.random.default_rng(4).standard_normal(7) * sig
    big = np.eye(N_X) * 1e8
    bank = MhssBank.initial(np.zeros(N_X), big, sats, depth=1, h_idx=H_IDX, v_idx=V_IDX)
    bank.update(y, H, sig**2, np.arange(7))
    kf, km = k_fa(1e-3, 7), k_md(1e-3)
    t = bank.main_tests(kf, km)
    P_0 = np.linalg.inv(H.T @ W @ H)
    x_0 = P_0 @ H.T @ W @ y
    for n in range(7):
        keep = np.arange(7) != n
        Hn, Wn = H[keep], W[np.ix_(keep, keep)]
        P_n = np.linalg.inv(Hn.T @ Wn @ Hn)
        x_n = P_n @ Hn.T @ Wn @ y[keep]
        dP = P_n - P_0
        assert t.T_h[n] == pytest.approx(kf * math.sqrt(np.linalg.eigvalsh(dP[:2, :2])[1]), rel=1e-6)
        assert t.a_h[n] == pytest.approx(km * math.sqrt(np.linalg.eigvalsh(P_n[:2, :2])[1]), rel=1e-6)
        assert t.T_v[n] == pytest.approx(kf * math.sqrt(dP[2, 2]), rel=1e-6)
        assert t.d_h[n] == pytest.approx(np.linalg.norm((x_0 - x_n)[:2]), rel=1e-5, abs=1e-7)
    assert t.hpl == pytest.approx(np.max(t.T_h + t.a_h), rel=1e-12)
    assert t.vpl == pytest.approx(np.max(t.T_v + t.a_v), rel=1e-12)


# --- exclusion --------------------------------------------------------------------------------
@pytest.mark.parametrize("faulty", IDS[:6])
def test_exclusion_removes_the_faulty_satellite_and_not_another(faulty):
    """A 25 m step on one satellite (sigma 1 m): detected, the sub-sub tests single out the
    faulty satellite, and the rebuilt bank (new main = its sub-filter) passes its tests."""
    rng = np.random.default_rng(21)
    bank = MhssBank.initial(np.zeros(N_X), P0, IDS[:6], depth=2, h_idx=H_IDX, v_idx=V_IDX)
    truth = rng.multivariate_normal(np.zeros(N_X), P0)
    p_fa, kmd = 1e-3, k_md(1e-3)
    excluded = None
    for k in range(10):
        bank.predict(PHI, Q)
        truth = PHI @ truth + rng.multivariate_normal(np.zeros(N_X), Q)
        H = rows(bank.sats)
        z = H @ truth + rng.standard_normal(len(H))
        if k >= 6 and faulty in bank.sats:
            z[bank.sats.index(faulty)] += 25.0
        bank.update(z, H, np.ones(len(H)), np.arange(len(H)))
        t = bank.main_tests(k_fa(p_fa, bank.N), kmd)
        if np.any(t.flagged(True)):
            assert k >= 6, "false alarm before the fault"
            r = bank.find_exclusion(t, p_fa, kmd, use_vertical=True)
            assert r is not None
            excluded = bank.sats[r]
            old_sub = bank.x[1 + r].copy()
            bank = bank.rebuild([s for s in bank.sats if s != excluded], purge=[excluded])
            np.testing.assert_array_equal(bank.x[0], old_sub)
            assert not np.any(bank.main_tests(k_fa(p_fa, bank.N), kmd).flagged(True))
            break
    assert excluded == faulty


def test_residual_test_flags_a_faulty_row():
    bank = MhssBank.initial(np.zeros(N_X), np.eye(N_X), IDS[:5], depth=0)
    H = rows(IDS[:2])
    std = residual_test(bank.x[0], bank.P[0], np.array([0.1, 30.0]), H, np.ones(2))
    assert abs(std[0]) < 1.0 and abs(std[1]) > 10.0


# --- the bank's arithmetic (issue 21) against the general masked update --------------------------------
def tc_bank_and_rows(N: int = 6, seed: int = 7):
    """A 17-state bank (depth 2) after one update and two predictions, and tightly coupled rows:
    pseudoranges on position + clock bias, range rates on velocity + clock drift."""
    rng = np.random.default_rng(seed)
    n = 17
    A = rng.normal(size=(n, n))
    bank = MhssBank.initial(np.zeros(n), A @ A.T / n + np.eye(n), [f"S{i}" for i in range(N)], depth=2)
    Phi = np.eye(n) + 0.05 * rng.normal(size=(n, n))
    Qd = 0.01 * np.eye(n)
    u = rng.normal(size=(N, 3))
    u /= np.linalg.norm(u, axis=1)[:, None]
    H = np.zeros((2 * N, n))
    H[:N, 0:3], H[:N, 15], H[N:, 3:6], H[N:, 16] = -u, 1.0, -1.0001 * u, 1.0
    r_var = np.r_[np.full(N, 0.16), np.full(N, 0.0025)]
    row_sat = np.r_[np.arange(N), np.arange(N)]
    bank.predict(Phi, Qd)
    bank.update(rng.normal(size=2 * N), H, r_var, row_sat)
    bank.predict(Phi, Qd)
    return bank, rng.normal(size=2 * N), H, r_var, row_sat


def general_update(bank: MhssBank, z, H, r_var, row_sat):
    """kalman.gain on every member with its row mask, cross_update on every block."""
    keep = ~bank.excl[:, row_sat]
    ref = kalman.gain(bank.x, bank.P, z, H, r_var, keep)
    pa, pb = bank.pa, bank.pb
    blocks = cross_update(bank.blocks, ref.IKH[pa], ref.IKH[pb], ref.K[pa], ref.K[pb], r_var)
    return ref, blocks


def untied(bank: MhssBank) -> MhssBank:
    """The same bank running the whole recursion (every cross block computed)."""
    return MhssBank(bank.sats, bank.x, bank.blocks, bank.depth, bank.h_idx, bank.v_idx, tied=False)


@pytest.mark.parametrize("tied", [True, False])
@pytest.mark.parametrize("general_path", [False, True])
def test_bank_update_equals_the_general_masked_update(general_path, tied, monkeypatch):
    """Gains in the observed states and the low-rank Joseph products give the general update
    (Cholesky of each member's S, explicit gains, Joseph of every block) to rounding; so does the
    general path the bank takes when a member's covariance is not positive definite (forced);
    with the cross blocks tied (members only) and with the whole recursion."""
    from fednav.service.estimation.integrity import mhss

    if general_path:
        monkeypatch.setattr(mhss, "_masked_gain", lambda *args: None)
    bank, z, H, r_var, row_sat = tc_bank_and_rows()
    assert bank.tied
    if not tied:
        bank = untied(bank)
    ref, blocks = general_update(bank, z, H, r_var, row_sat)
    upd = bank.update(z, H, r_var, row_sat)
    scale = np.abs(blocks).max(axis=(1, 2))[:, None, None]
    np.testing.assert_allclose(bank.x, ref.x, rtol=1e-9, atol=1e-12)
    np.testing.assert_allclose(bank.blocks / scale, blocks / scale, rtol=0, atol=1e-12)
    np.testing.assert_array_equal(bank.P, np.swapaxes(bank.P, 1, 2))  # members symmetrised
    np.testing.assert_allclose(upd.K, ref.K, rtol=1e-9, atol=1e-12)
    np.testing.assert_allclose(upd.IKH, ref.IKH, rtol=1e-9, atol=1e-12)
    np.testing.assert_allclose(upd.whitened, ref.result.whitened, rtol=1e-9, atol=1e-12)
    np.testing.assert_allclose(upd.nis, ref.result.nis, rtol=1e-9)
    np.testing.assert_array_equal(upd.innovation == 0.0, ref.result.innovation == 0.0)


def test_tied_bank_equals_the_whole_recursion_until_an_exclusion_unties_it():
    """A bank started from one prior computes its members only (module docstring "Tied cross
    blocks"); its cross blocks, read as the reference members' covariances, equal the whole
    recursion's to rounding through predictions, updates, a rising and a setting satellite. An
    exclusion unties it: its restarted sub-subs make the blocks differ from the tie, and from then
    on it runs the whole recursion, still equal to the untied bank's."""
    rng = np.random.default_rng(5)
    tied = MhssBank.initial(np.zeros(N_X), P0, IDS[:6], depth=2, h_idx=H_IDX, v_idx=V_IDX)
    full = untied(tied)
    truth = rng.multivariate_normal(np.zeros(N_X), P0)
    schedule = {3: ("rise", "S6"), 6: ("set", "S1"), 9: ("purge", "S3"), 12: ("rise", "S7")}
    for k in range(16):
        for b in (tied, full):
            b.predict(PHI, Q)
        truth = PHI @ truth + rng.multivariate_normal(np.zeros(N_X), Q)
        if k in schedule:
            what, sid = schedule[k]
            sats = list(tied.sats) + [sid] if what == "rise" else [s for s in tied.sats if s != sid]
            purge = [sid] if what == "purge" else []
            if what == "purge":  # the blocks the tie would claim for the restarted sub-subs are wrong
                naive = tied.rebuild(sats, purge=purge)
                naive.tied = True
                lie = naive.blocks[naive.sub_blocks].copy()
            tied, full = tied.rebuild(sats, purge=purge), full.rebuild(sats, purge=purge)
            assert tied.tied == (what != "purge" and k < 9) and not full.tied
            if what == "purge":
                assert np.max(np.abs(lie - tied.blocks[tied.sub_blocks])) > 0.1
        H = rows(tied.sats)
        z = H @ truth + SIGMA * rng.standard_normal(len(H))
        for b in (tied, full):
            b.update(z, H, np.full(len(H), SIGMA**2), np.arange(len(H)))
            b.shift(b.x[0].copy())
        np.testing.assert_allclose(tied.x, full.x, rtol=0, atol=1e-9)
        np.testing.assert_allclose(tied.blocks, full.blocks, rtol=1e-9, atol=1e-9)
        t_tied, t_full = tied.main_tests(3.0, 3.0), full.main_tests(3.0, 3.0)
        np.testing.assert_allclose(t_tied.T_h, t_full.T_h, rtol=1e-6)
        np.testing.assert_allclose(t_tied.hpl, t_full.hpl, rtol=1e-9)
        for r in range(tied.N):
            np.testing.assert_allclose(
                tied.sub_tests(r, 3.0, 3.0).T_v, full.sub_tests(r, 3.0, 3.0).T_v, rtol=1e-6
            )
    assert not tied.tied  # a rising satellite after the exclusion does not tie it again


def test_bank_update_raises_when_an_innovation_covariance_is_not_positive_definite():
    bank, z, H, r_var, row_sat = tc_bank_and_rows()
    bank.blocks[5] = -np.eye(bank.n)  # a sub-filter whose covariance went negative
    with pytest.raises(kalman.NotPositiveDefinite):
        bank.update(z, H, r_var, row_sat)


def test_bank_arrays_stay_valid_until_the_second_update_after():
    """predict/update alternate between two arrays: a view taken now keeps its values through one
    more step (the documented contract); the estimate copies what it keeps."""
    bank, z, H, r_var, row_sat = tc_bank_and_rows()
    P0 = bank.P[0]
    kept = P0.copy()
    bank.update(z, H, r_var, row_sat)
    np.testing.assert_array_equal(P0, kept)


def test_exclusion_book_health_clock_restarts_when_time_goes_back():
    """A satellite's run of healthy epochs is measured on the vehicle's time: a new time base
    (time going back) restarts it instead of keeping the satellite out until the old time returns."""
    from fednav.service.estimation.integrity.monitor import ExclusionBook

    book = ExclusionBook(readmit_after_s=5.0)
    book.exclude("C03", 100.0)
    assert book.observe(101.0, {"C03": True}) == []
    assert book.observe(10.0, {"C03": True}) == []  # a new time base: the clock restarts at 10 s
    assert book.observe(14.0, {"C03": True}) == []
    assert book.observe(15.0, {"C03": True}) == ["C03"]
    assert "C03" not in book


def test_exclusion_book_carried_to_another_book_keeps_each_health_clock():
    """What a hand-over carries (HandoverState.excluded): each excluded satellite with the seconds
    its health tests have passed; the book that takes them needs only the rest of the
    re-admission time, and a satellite failing at the hand-over (0 s) the whole of it."""
    from fednav.service.estimation.integrity.monitor import ExclusionBook

    old = ExclusionBook(readmit_after_s=60.0)
    old.exclude("C03", 100.0)
    old.exclude("G07", 100.0)
    old.observe(110.0, {"C03": True, "G07": False})
    old.observe(140.0, {"C03": True, "G07": False})
    carried = old.healthy_for(150.0)
    assert carried == {"C03": 40.0, "G07": 0.0}
    new = ExclusionBook(readmit_after_s=60.0)
    new.restore(carried, 500.0)  # another service, its own time of the hand-over
    assert new.ids == ["C03", "G07"]
    assert new.observe(510.0, {"C03": True, "G07": True}) == []
    assert new.observe(520.0, {"C03": True, "G07": True}) == ["C03"]  # 40 s there + 20 s here
    assert new.observe(569.0, {"G07": True}) == []
    assert new.observe(570.0, {"G07": True}) == ["G07"]  # its own 60 s, from 510 s
    # a satellite excluded here already keeps the clock that has passed less
    both = ExclusionBook(readmit_after_s=60.0)
    both.exclude("C03", 480.0)
    both.observe(490.0, {"C03": True})  # healthy since 490 s here: 10 s at 500 s
    both.restore({"C03": 40.0}, 500.0)
    assert both.healthy_for(500.0) == {"C03": 10.0}
    both.restore({"C03": 0.0}, 500.0)
    assert both.healthy_for(500.0) == {"C03": 0.0}


@pytest.mark.parametrize("purge", [False, True], ids=["tied", "untied"])
def test_a_bank_restored_from_its_state_keeps_every_member_around_the_new_main(purge):
    """A lifecycle checkpoint keeps the whole bank (``MhssBank.state``); a restart rebuilds it
    around the restart's main covariance (``MhssBank.restored``): the main's change is common to
    every block, each member keeps its excess over the main and its state, so the separations'
    covariances and thresholds are the checkpoint's (a restart that started every member as a copy
    of the main made the demo's HPL fall from 16.4 to 7.0 m). Restored at the same covariance the
    bank equals the original and runs on identically; a member that would not be positive definite
    gives None (the caller starts a new bank)."""
    rng = np.random.default_rng(3)
    bank = MhssBank.initial(np.zeros(N_X), P0, IDS[:6], depth=2, h_idx=H_IDX, v_idx=V_IDX)
    truth = rng.multivariate_normal(np.zeros(N_X), P0)
    for k in range(8):
        bank.predict(PHI, Q)
        truth = PHI @ truth + rng.multivariate_normal(np.zeros(N_X), Q)
        if purge and k == 4:
            bank = bank.rebuild([s for s in bank.sats if s != "S2"], purge=["S2"])
        H = rows(bank.sats)
        z = H @ truth + SIGMA * rng.standard_normal(len(H))
        bank.update(z, H, np.full(len(H), SIGMA**2), np.arange(len(H)))
        bank.shift(bank.x[0].copy())
    assert bank.tied == (not purge)
    s = bank.state()
    assert len(s.blocks) == (bank.B if bank.tied else len(bank.pa))
    same = MhssBank.restored(s, bank.P[0])
    np.testing.assert_allclose(same.blocks, bank.blocks, rtol=0, atol=1e-12)
    np.testing.assert_array_equal(same.x, bank.x)
    assert same.tied == bank.tied and same.sats == bank.sats
    H = rows(bank.sats)
    z = H @ truth
    for b in (bank, same):
        b.predict(PHI, Q)
        b.update(z, H, np.full(len(H), SIGMA**2), np.arange(len(H)))
    np.testing.assert_allclose(same.blocks, bank.blocks, rtol=1e-12, atol=1e-12)
    np.testing.assert_allclose(same.x, bank.x, rtol=1e-12, atol=1e-12)
    grown = bank.P[0] + np.diag([4.0, 4.0, 1.0, 9.0])  # a carry over a gap: a common error
    s = bank.state()
    out = MhssBank.restored(s, grown)
    np.testing.assert_allclose(
        out.blocks - bank.blocks, np.broadcast_to(grown - bank.P[0], bank.blocks.shape), atol=1e-9
    )
    kfa, kmd = k_fa(1e-3, bank.N), k_md(1e-3)
    d_before = bank.P[1:] - bank.P[0]
    np.testing.assert_allclose(out.P[1:] - out.P[0], d_before, atol=1e-9)  # the separations' covariances
    assert out.main_tests(kfa, kmd).hpl > bank.main_tests(kfa, kmd).hpl  # the common error in a_n
    fresh = MhssBank.initial(np.zeros(N_X), grown, bank.sats, depth=2, h_idx=H_IDX, v_idx=V_IDX)
    assert out.main_tests(kfa, kmd).hpl > fresh.main_tests(kfa, kmd).hpl + 1.0  # copies of the main: no T_n
    # a shrink no member's excess covers leaves members not positive definite: refused
    assert MhssBank.restored(s, bank.P[0] - 50.0 * np.eye(N_X)) is None
    assert MhssBank.restored(s, np.eye(N_X + 1)) is None
