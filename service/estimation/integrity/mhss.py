"""MHSS: multiple-hypothesis solution separation on ONE Kalman filter bank (seed 001, docs/DESIGN.md).

Members (one bank, B = 1 + N + N(N-1)/2 at depth 2)
---------------------------------------------------
Each member is identified by the tuple of satellite indices it excludes: ``()`` the main filter
F00, ``(n,)`` sub-filter F0n, ``(n, m)`` (n < m) sub-sub filter Fnm. All members share the
linearisation point (the main filter's INS), one Phi, one Q and one R model; exclusion is the row
mask of the batched update (an excluded row gets exactly zero gain). Layout: index 0 main,
1..N subs, then the pairs in lexicographic order.

Cross-covariances (what MHSS needs, and nothing more)
-----------------------------------------------------
Detection compares the main with every sub: needs P_0n (N blocks). Exclusion of satellite r
compares sub r with its sub-subs (r, m): needs P_{r,(r,m)} for every ordered (r, m), m != r
(N(N-1) blocks; each sub-sub appears under both of its satellites). The bank stores member
covariances and these cross blocks together as ``blocks`` (B + C, n, n) with pair indices
(pa, pb): block k = Cov(e_pa[k], e_pb[k]), members being the pairs (a, a). One recursion serves
all of them (docs/DESIGN.md "MHSS on a Kalman filter bank"):

    predict:  P_ab <- Phi P_ab Phi' + Q                 full Q: the same process noise drives both
    update:   P_ab <- (I - K_a H) P_ab (I - K_b H)' + K_a R K_b'
    init:     P_ab = P(0) for members started from the same prior

For a = b this is the Joseph form. K_b is member b's gain with zero columns on its masked rows, so
full H and the true (unsubstituted) R are used in the recursion. The shortcut
dP = P_nn - P_00 holds only when every member is optimal for the truth model (then P_0n = P_00 by
orthogonality); tests show the recursion matches Monte Carlo where the shortcut does not.

How it is computed (issue 21, bank speed; the equations above unchanged): the gains in the s
states the rows observe (position, velocity, clock: s = 8 for m = 2N rows) by the push-through
identity H_a' S^-1 = E' (I + J C)^-1 G_a' R^-1 (:func:`_masked_gain`), so K = L G_a' R^-1 with
L = P E' (I + J C)^-1 (n x s), K H = L J E and K_a R K_b' = L_a J_b L_b'; then the Joseph product
of every block with (n, s) x (s, n) products only (:meth:`MhssBank._joseph_observed`):
T = P_ab - (L_a J_a)(E P_ab), P_ab <- T + (L_a - T E') J_b L_b'. A bank of one filter
(integrity off) and banks with a member whose C is not positive definite take the general path:
``kalman.gain`` (Cholesky of S, explicit gains, as every other pipeline) and the Joseph product
of the explicit factors.

Tied cross blocks (issue 21, bank speed)
----------------------------------------
The recursion above runs with the very R and Q the gains use, so it is the filters' own model,
and every member's gain is the optimal one for its own covariance. Then for a parent a and a
child b (b uses a subset of a's rows, now and in its whole history, and a is optimal for its
rows), e_a is orthogonal to everything b's estimate is made of, and Cov(e_a, e_b) = P_aa:
P_0n = P_00 and P_{n,(n,m)} = P_nn, exactly (the predict keeps it: Phi P Phi' + Q on both; the
update keeps it: P_aa^+ H' = K_a R on the rows b uses). A bank started from one prior
(:meth:`MhssBank.initial`) therefore computes its members only (79 of 223 blocks for 12
satellites) and reads each cross block as its reference member's covariance (``tied``). A rebuild
without a purge keeps the tie (each new cross block is an old one stored in its orientation); an
exclusion breaks it, because the restarted sub-subs are copies of the new main, which used the
satellites they now exclude: from then on the bank runs the whole recursion. Under a model that
differs from the truth the tie holds for the model's covariances, not the true ones (what the
recursion of ``cross_update`` with the true R shows in tests/test_mhss.py); the bank never knows
the truth, so nothing it computed changes but the rounding.

Closed loop: only the main filter's correction dx_0 is fed back; every member shifts by it,
x_i <- x_i - dx_0 (covariances unchanged), so after feedback x_0 = 0 and dx_0n = -x_n.

Tests and protection levels (seed 001 eq 27-32, read per docs/PAPERS.md)
-------------------------------------------------------------------
    dx_0n = x_0 - x_n;   dP_0n = P_00 - P_0n - P_0n' + P_nn                       (eq 27)
    horizontal: d_n = |dx_0n[h]|,  T_n = K_fa sqrt(lambda_max(dP_0n[h, h]))         (eq 28-29)
                a_n = K_md sqrt(lambda_max(P_nn[h, h])),   HPL = max_n (T_n + a_n)  (eq 30-32)
    vertical:   the same with the up component (1-D, no eigenvalue): VPL = max_n (T_v,n + a_v,n)
    K_fa = Q^-1(P_FA / (2 N)),  K_md = Q^-1(P_MD)    (standard two-sided form, not the paper's erfinv)
A fault-free term K_md sqrt(lambda_max(P_00[h, h])) also enters the max; it never binds while
P_nn >= P_00 but gives a protection level when N = 0.
Note: for the 2-D statistic the per-test false-alarm probability P(|d| > K sqrt(lambda_max)) lies
between 2 Q(K) = P_FA/N (one dominant axis) and exp(-K^2/2) (circular dP); the seed's horizontal
test can therefore exceed P_FA by up to that ratio. :func:`horizontal_false_alarm_probability`
gives the exact value for a given dP, and the tests compare against it.

Exclusion (Brenner / Vanderwerf solution-separation FDE)
---------------------------------------------------------
On a detection, sub-filter r is a candidate when its own main-level test failed (d_0r > T_0r) and
all its sub-sub tests (r vs (r, m), threshold with K_fa = Q^-1(P_FA / (2 (N - 1)))) pass. A unique
candidate is excluded; among several, the one with the largest normalised main-level statistic
d_0r / T_0r. No candidate: the detection is unresolved (an alarm for the integrity logic).

Rebuilding the bank (satellite set changes and exclusions): :meth:`MhssBank.rebuild`
-----------------------------------------------------------------------------------
Each new member E' (excluded set) takes the state, covariance and cross-covariances of an old
member ("source"): (E' U X) restricted to the old satellites, X being the satellites purged by
an exclusion; if that member does not exist (its set would need three exclusions, or sub-subs are
off), the source is X itself (the old sub-filter of the excluded satellite = the new main), else
the old main. Every needed new block then maps to an old block (or a member covariance), so:
- rising satellites (X empty) are EXACT: the new sub j IS the old main (P_0j = P_00 at entry:
  identical estimates), sub-sub (n, j) IS the old sub n, and all blocks are old blocks;
- setting satellites (X empty) are EXACT: every member continues, the set just loses a row;
- an exclusion of r is exact for the main (old sub r) and the subs (old sub-subs (r, n)); the new
  sub-subs restart as copies of the new main (their own separation history restarts at zero:
  the approximation, consistent in covariance since the blocks are the exact ones of the copies).
"""

from __future__ import annotations

import functools
import itertools
import math
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
from scipy import integrate, special

from fednav.service.estimation import kalman
from fednav.service.estimation.kalman import symmetrise

H_IDX = (0, 1)  # east, north position error (ENU metres) in the INS error state
V_IDX = 2  # up


# --- multipliers ------------------------------------------------------------------------------------
@functools.lru_cache(maxsize=256)
def q_inv(p: float) -> float:
    """Q^-1(p): the upper-tail standard normal quantile (Q(k) = P(z > k)); cached (the monitor asks
    for the same few every epoch)."""
    return float(-special.ndtri(p))


def k_fa(p_fa: float, n_tests: int) -> float:
    """K_fa = Q^-1(P_FA / (2 N)): two-sided multiplier of each of N tests (seed 001 eq 29, standard form)."""
    return q_inv(p_fa / (2.0 * max(n_tests, 1)))


def k_fa_horizontal(p_fa: float, n_tests: int, mode: str = "gaussian") -> float:
    """Multiplier of each horizontal separation test, T = K sqrt(lambda_max(dP_h)).

    "gaussian": K_fa = Q^-1(P_FA / (2 N)) as seed 001 eq 29 (in the standard form). On the 2-D
        statistic |dx_h| it gives a per-test false-alarm probability between P_FA/N (a flat
        separation ellipse) and exp(-K^2/2), up to ~6x P_FA/N for a round one.
    "chi2": K = sqrt(-2 ln(P_FA / N)), the chi-square(2) quantile: since |d|^2 <= lambda_max d' dP^-1 d,
        P(|d| > K sqrt(lambda_max)) <= P(chi2_2 > K^2) = P_FA / N for ANY ellipse, so the budget
        holds exactly for round ellipses and conservatively otherwise (thresholds ~7-9 % larger).
    """
    if mode == "gaussian":
        return k_fa(p_fa, n_tests)
    if mode == "chi2":
        return math.sqrt(-2.0 * math.log(p_fa / max(n_tests, 1)))
    raise ValueError(f"unknown horizontal threshold mode {mode!r}")


def k_md(p_md: float) -> float:
    """K_md = Q^-1(P_MD) (seed 001 eq 31)."""
    return q_inv(p_md)


def lambda_max_2x2(M: np.ndarray) -> np.ndarray:
    """Largest eigenvalue of symmetric 2x2 matrices (..., 2, 2), closed form."""
    a, b, c = M[..., 0, 0], 0.5 * (M[..., 0, 1] + M[..., 1, 0]), M[..., 1, 1]
    return 0.5 * (a + c) + np.sqrt(0.25 * (a - c) ** 2 + b * b)


def horizontal_false_alarm_probability(dP_h: np.ndarray, k: float) -> float:
    """Exact P(|d| > k sqrt(lambda_max)) for d ~ N(0, dP_h), dP_h (2, 2): the false-alarm
    probability of one horizontal solution-separation test (generalised chi-square, by quadrature)."""
    lam = np.linalg.eigvalsh(0.5 * (dP_h + dP_h.T))
    rho = max(lam[0], 0.0) / lam[1]

    def f(z2: float) -> float:
        rest = k * k - rho * z2 * z2
        return (
            math.exp(-0.5 * z2 * z2)
            / math.sqrt(2.0 * math.pi)
            * (2.0 * special.ndtr(-math.sqrt(rest)) if rest > 0 else 1.0)
        )

    val, _ = integrate.quad(f, -np.inf, np.inf, limit=200, epsabs=1e-13)
    return float(val)


# --- the recursion ----------------------------------------------------------------------------------------
def cross_predict(blocks: np.ndarray, Phi: np.ndarray, Qd: np.ndarray) -> np.ndarray:
    """P_ab <- Phi P_ab Phi' + Q for blocks (K, n, n) (full Q: one process noise drives all members)."""
    return Phi @ blocks @ Phi.T + Qd


def cross_update(
    P_ab: np.ndarray,
    IKH_a: np.ndarray,
    IKH_b: np.ndarray,
    K_a: np.ndarray,
    K_b: np.ndarray,
    r_var: np.ndarray,
) -> np.ndarray:
    """P_ab <- (I - K_a H) P_ab (I - K_b H)' + K_a R K_b' with R = diag(r_var) (the true noise).

    Shapes: P_ab (..., n, n); IKH_* (..., n, n); K_* (..., n, m); r_var (m,).
    """
    return IKH_a @ P_ab @ np.swapaxes(IKH_b, -1, -2) + (K_a * r_var[..., None, :]) @ np.swapaxes(K_b, -1, -2)


# --- results ----------------------------------------------------------------------------------------------
class BankUpdate:
    """Per-member statistics of one bank update.

    innovation (B, m) r = z - H x (zero on masked rows); whitened (B, m) L^-1 r; nis (B,);
    dof (B,) rows used; K (B, n, m) gains; IKH (B, n, n) = I - K H.

    The bank's update works with the factors of the gains (:func:`_masked_gain`) and never forms
    K, I - K H as returned here nor the Cholesky factor of each S: those are computed on first
    access (the integrity logic reads none of them).
    """

    __slots__ = ("innovation", "dof", "_K", "_IKH", "_whitened", "_nis", "_gain")

    def __init__(
        self,
        innovation: np.ndarray,
        dof: np.ndarray,
        K: np.ndarray | None = None,
        IKH: np.ndarray | None = None,
        whitened: np.ndarray | None = None,
        nis: np.ndarray | None = None,
        gain: _Gain | None = None,
    ):
        self.innovation, self.dof = innovation, dof
        self._K, self._IKH, self._whitened, self._nis, self._gain = K, IKH, whitened, nis, gain

    @property
    def K(self) -> np.ndarray:
        if self._K is None:
            self._K = self._gain.K()
        return self._K

    @property
    def IKH(self) -> np.ndarray:
        if self._IKH is None:
            self._IKH = self._gain.IKH()
        return self._IKH

    @property
    def whitened(self) -> np.ndarray:
        if self._whitened is None:
            self._whitened, self._nis = self._gain.whitened()
        return self._whitened

    @property
    def nis(self) -> np.ndarray:
        if self._nis is None:
            self._whitened, self._nis = self._gain.whitened()
        return self._nis


@dataclass(frozen=True)
class _Gain:
    """The gains of one bank update in factored form (:func:`_masked_gain`).

    x (B, n) updated states; L = P E' (I + J C)^-1 (B, n, s), so that K = L G_a' R^-1 and
    K H = L J E; J = G_a' R^-1 G_a (B, s, s); C = E P E' (B, s, s); sel (s,) the observed states;
    G = H[:, sel]; keep (B, m) rows used; r_var (m,); innovation (B, m); dof (B,).
    """

    x: np.ndarray
    L: np.ndarray
    J: np.ndarray
    C: np.ndarray
    sel: np.ndarray
    G: np.ndarray
    keep: np.ndarray
    r_var: np.ndarray
    innovation: np.ndarray
    dof: np.ndarray

    def K(self) -> np.ndarray:
        return self.L @ (self.G.T[None] * (self.keep / self.r_var)[:, None, :])

    def IKH(self) -> np.ndarray:
        B, n = self.x.shape
        out = np.broadcast_to(np.eye(n), (B, n, n)).copy()
        out[:, :, self.sel] -= self.L @ self.J
        return out

    def whitened(self) -> tuple[np.ndarray, np.ndarray]:
        """L^-1 r and r' S^-1 r with S = H_a P H_a' + R (R = identity on masked rows) = L L'."""
        Ga = self.G * self.keep[:, :, None]
        S = Ga @ self.C @ np.swapaxes(Ga, 1, 2)
        m = S.shape[-1]
        S.reshape(len(S), -1)[:, :: m + 1] += np.where(self.keep, self.r_var, 1.0)
        L = np.linalg.cholesky(0.5 * (S + np.swapaxes(S, 1, 2)))
        w = np.linalg.solve(L, self.innovation[:, :, None])[:, :, 0]
        return w, np.einsum("bi,bi->b", w, w)


def _masked_gain(
    x: np.ndarray, P: np.ndarray, z: np.ndarray, H: np.ndarray, r_var: np.ndarray, keep: np.ndarray
) -> _Gain | None:
    """Gains of a bank whose members share H and a diagonal R and differ by row masks.

    The same gains as :func:`~service.estimation.kalman.gain` (K = P H_a' S^-1, S = H_a P H_a' + R,
    zero gain on masked rows), solved in the space of the s states that H observes instead of the
    m rows: with E selecting those states (H = G E, G (m, s)), C = E P E', G_a = G with masked
    rows zero and J = G_a' R^-1 G_a, the push-through identity (exact, no approximation) gives

        H_a' S^-1 = E' (I + J C)^-1 G_a' R^-1,   so   K = L G_a' R^-1,   L = P E' (I + J C)^-1,

    K H = L J E and K r = L G_a' R^-1 r: one s x s inverse per member (s = 8 for pseudoranges and
    range rates: position, velocity, clock) instead of an m x m Cholesky factor and two triangular
    solves (m = 24 for 12 satellites). J is summed from the rows' g_i g_i' / r_i. Returns None when
    a member's C is not positive definite or a noise variance is not positive (then S may not be:
    the caller takes the general path, which raises NotPositiveDefinite exactly when S is not
    positive definite).
    """
    B, n = x.shape
    # (array methods: the values of np.any / np.all / np.take / np.swapaxes without their Python
    # wrappers; the bank's update runs at every GNSS epoch)
    sel = np.flatnonzero(H.any(axis=0))
    s = len(sel)
    if s == 0 or not (r_var > 0.0).all():
        return None
    kf = keep.astype(float)
    r = (z - x @ H.T) * kf  # innovations, zero on masked rows
    G = H[:, sel]
    U = P[:, :, sel]  # P E' (B, n, s)
    C = U[:, sel, :]  # E P E' (B, s, s)
    try:
        np.linalg.cholesky(C)
    except np.linalg.LinAlgError:
        return None
    Gw = G / r_var[:, None]  # R^-1 G
    J = (kf @ (Gw[:, :, None] * G[:, None, :]).reshape(len(G), s * s)).reshape(B, s, s)
    M = J @ C
    M.reshape(B, -1)[:, :: s + 1] += 1.0
    L = U @ np.linalg.inv(M)
    x_new = x + (L @ ((r @ Gw)[:, :, None]))[:, :, 0]
    return _Gain(x_new, L, J, C, sel, G, keep, r_var, r, keep.sum(axis=1))


@dataclass(frozen=True)
class SeparationTests:
    """Solution-separation tests of one reference filter against its N children, all (N,).

    d_h / T_h / a_h: horizontal statistic, threshold, missed-detection term; d_v / T_v / a_v the
    vertical ones; hpl / vpl the protection levels; k_fa / k_md the multipliers used.
    """

    d_h: np.ndarray
    T_h: np.ndarray
    a_h: np.ndarray
    d_v: np.ndarray
    T_v: np.ndarray
    a_v: np.ndarray
    hpl: float
    vpl: float
    k_fa: float
    k_md: float

    @property
    def flagged_h(self) -> np.ndarray:
        return self.d_h > self.T_h

    @property
    def flagged_v(self) -> np.ndarray:
        return self.d_v > self.T_v

    def flagged(self, use_vertical: bool) -> np.ndarray:
        return self.flagged_h | self.flagged_v if use_vertical else self.flagged_h

    def normalised(self, use_vertical: bool) -> np.ndarray:
        r = self.d_h / np.maximum(self.T_h, 1e-300)
        if use_vertical:
            r = np.maximum(r, self.d_v / np.maximum(self.T_v, 1e-300))
        return r


def solution_separation(
    x_ref: np.ndarray,
    P_ref: np.ndarray,
    x_sub: np.ndarray,
    P_sub: np.ndarray,
    P_cross: np.ndarray,
    kfa: float,
    kmd: float,
    h_idx: Sequence[int] = H_IDX,
    v_idx: int = V_IDX,
    kfa_h: float | None = None,
) -> SeparationTests:
    """Tests of a reference filter against N children (seed 001 eq 27-32).

    x_ref (n,), P_ref (n, n); x_sub (N, n), P_sub (N, n, n); P_cross (N, n, n) = Cov(e_ref, e_sub).
    ``kfa`` multiplies the vertical thresholds, ``kfa_h`` (default ``kfa``) the horizontal ones
    (``k_fa_horizontal``).
    """
    kh = kfa if kfa_h is None else kfa_h
    # only the horizontal and vertical rows/columns of the covariances enter the tests
    h, hh, ix = _separation_index(tuple(h_idx), v_idx)
    dx = x_ref[None, :] - x_sub
    Pc, Ps = P_cross[ix], P_sub[ix]
    dP = P_ref[ix[1:]][None] - Pc - Pc.swapaxes(1, 2) + Ps  # eq 27, (N, 3, 3)
    dxh = dx[:, h]
    d_h = np.sqrt(np.add.reduce(dxh * dxh, axis=1))  # eq 28 (np.linalg.norm's values, without its checks)
    T_h = kh * np.sqrt(np.maximum(lambda_max_2x2(dP[:, :2, :2]), 0.0))  # eq 29
    a_h = kmd * np.sqrt(np.maximum(lambda_max_2x2(Ps[:, :2, :2]), 0.0))  # eq 31
    d_v = np.abs(dx[:, v_idx])
    T_v = kfa * np.sqrt(np.maximum(dP[:, 2, 2], 0.0))
    a_v = kmd * np.sqrt(np.maximum(Ps[:, 2, 2], 0.0))
    # fault-free term (binds only when N = 0 or a child is better than the reference)
    hpl0 = kmd * math.sqrt(max(float(lambda_max_2x2(P_ref[hh])), 0.0))
    vpl0 = kmd * math.sqrt(max(float(P_ref[v_idx, v_idx]), 0.0))
    # np.maximum.reduce: np.max's values (NaN included) without its wrappers
    hpl = max(hpl0, float(np.maximum.reduce(T_h + a_h))) if len(T_h) else hpl0  # eq 32
    vpl = max(vpl0, float(np.maximum.reduce(T_v + a_v))) if len(T_v) else vpl0
    return SeparationTests(d_h, T_h, a_h, d_v, T_v, a_v, hpl, vpl, kfa, kmd)


@functools.lru_cache(maxsize=16)
def _separation_index(h_idx: tuple[int, ...], v_idx: int):
    """(the horizontal indices, their (2, 2) block's index, the (N, 3, 3) horizontal + vertical
    block's index) of :func:`solution_separation`, read-only."""
    h = np.asarray(h_idx)
    hv = np.append(h, v_idx)
    for a in (h, hv):
        a.setflags(write=False)
    return h, (h[:, None], h[None, :]), (slice(None), hv[:, None], hv[None, :])


# --- the bank ---------------------------------------------------------------------------------------------
class _Work:
    """Arrays reused from epoch to epoch (no allocation, warm caches): scratch arrays and the two
    covariance arrays the updates alternate between."""

    def __init__(self) -> None:
        self._arrays: dict[str, np.ndarray] = {}

    def get(self, name: str, shape: tuple[int, ...]) -> np.ndarray:
        a = self._arrays.get(name)
        if a is None or a.shape != shape:
            a = self._arrays[name] = np.empty(shape)
        return a


def _layout(N: int, depth: int):
    members: list[tuple[int, ...]] = [()]
    if depth >= 1:
        members += [(n,) for n in range(N)]
    if depth >= 2:
        members += list(itertools.combinations(range(N), 2))
    index = {e: i for i, e in enumerate(members)}
    B = len(members)
    pa, pb = list(range(B)), list(range(B))
    main_blocks = np.zeros(0, dtype=int)
    sub_blocks = np.zeros((N, max(N - 1, 0)), dtype=int)
    subsub_members = np.zeros((N, max(N - 1, 0)), dtype=int)
    if depth >= 1:
        main_blocks = np.arange(B, B + N)
        pa += [0] * N
        pb += [1 + n for n in range(N)]
    if depth >= 2:
        k = B + N
        for n in range(N):
            for j, m in enumerate(x for x in range(N) if x != n):
                pa.append(1 + n)
                pb.append(index[(min(n, m), max(n, m))])
                sub_blocks[n, j] = k
                subsub_members[n, j] = index[(min(n, m), max(n, m))]
                k += 1
    excl = np.zeros((B, N), dtype=bool)
    for i, e in enumerate(members):
        excl[i, list(e)] = True
    return members, index, np.array(pa), np.array(pb), main_blocks, sub_blocks, subsub_members, excl


@dataclass(frozen=True, eq=False)
class BankState:
    """What a lifecycle checkpoint keeps of an :class:`MhssBank` (:meth:`MhssBank.state`): its
    satellites, the members' states (B, n) and its blocks (the members only when tied: the cross
    blocks are then their reference members' covariances). Copies: the bank's arrays are reused
    from update to update."""

    sats: tuple[str, ...]
    depth: int
    x: np.ndarray
    blocks: np.ndarray
    tied: bool
    h_idx: tuple[int, ...]
    v_idx: int


class MhssBank:
    """Main + sub + sub-sub filters over one satellite set, with the cross-covariances MHSS needs.

    Parameters
    ----------
    sats : satellite ids, in the order of the exclusion columns.
    x : (B, n) member states; blocks : (B + C, n, n) member covariances then cross blocks
        (layout in the module docstring); use :meth:`initial` or :meth:`rebuild` to make one.
    depth : 0 main only, 1 + sub-filters, 2 + sub-sub filters.
    h_idx, v_idx : horizontal (2) and vertical state indices of the tests.
    tied : the cross blocks are their reference members' covariances and only the members are
        computed (module docstring "Tied cross blocks"; :meth:`initial` and :meth:`rebuild` set
        it). Its cross blocks are then stale until ``blocks`` is read: to run the whole recursion
        from a tied bank, build a new bank from its ``blocks`` (turning ``tied`` off in place is
        right only while every block still equals the prior, as right after :meth:`initial`).

    Speed (issue 21, ``benchmarks/mhss_bank.py``): :meth:`predict` and :meth:`update` write into
    two arrays they alternate between (and reuse their scratch arrays), so ``blocks``, ``P`` and
    :meth:`cross` are views that stay valid until the second update after: copy what must outlive
    that.
    """

    def __init__(
        self,
        sats: Sequence[str],
        x: np.ndarray,
        blocks: np.ndarray,
        depth: int,
        h_idx: Sequence[int] = H_IDX,
        v_idx: int = V_IDX,
        tied: bool = False,
    ):
        self.sats = tuple(sats)
        self.depth = int(depth)
        self.h_idx = tuple(h_idx)
        self.v_idx = int(v_idx)
        N = len(self.sats)
        (
            self.members,
            self.index,
            self.pa,
            self.pb,
            self.main_blocks,
            self.sub_blocks,
            self.subsub_members,
            self.excl,
        ) = _layout(N, self.depth if N > 0 else 0)
        B = len(self.members)
        if x.shape[0] != B or blocks.shape[0] != len(self.pa):
            raise ValueError(
                f"bank of {N} satellites at depth {depth} needs {B} members and {len(self.pa)} blocks"
            )
        self.x = np.array(x, dtype=float)
        self._blocks = np.array(blocks, dtype=float)
        self.tied = bool(tied)
        self.n = self.x.shape[1]
        self.sources: np.ndarray | None = None  # after rebuild: old member index of each member
        self._work = _Work()

    # --- construction -----------------------------------------------------------------------------
    @classmethod
    def initial(
        cls,
        x0: np.ndarray,
        P0: np.ndarray,
        sats: Sequence[str] = (),
        depth: int = 2,
        h_idx: Sequence[int] = H_IDX,
        v_idx: int = V_IDX,
    ) -> MhssBank:
        """Every member starts from the same prior (x0, P0): all blocks = P0 (DESIGN init)."""
        N = len(sats)
        members, _, pa, *_ = _layout(N, depth if N > 0 else 0)
        x = np.broadcast_to(np.asarray(x0, dtype=float), (len(members), len(x0))).copy()
        blocks = np.broadcast_to(np.asarray(P0, dtype=float), (len(pa),) + np.shape(P0)).copy()
        return cls(sats, x, blocks, depth, h_idx, v_idx, tied=True)

    @property
    def N(self) -> int:
        return len(self.sats)

    @property
    def B(self) -> int:
        return len(self.members)

    @property
    def P(self) -> np.ndarray:
        """(B, n, n) member covariances (a view of ``blocks``)."""
        return self._blocks[: self.B]

    @property
    def blocks(self) -> np.ndarray:
        """(B + C, n, n) member covariances then cross blocks (module docstring). A tied bank
        (module docstring "Tied cross blocks") keeps only its members: reading ``blocks`` writes
        each cross block as its reference member's covariance first (what the recursion would
        give, to rounding)."""
        if self.tied and len(self._blocks) > self.B:
            B = self.B
            np.take(self._blocks, self.pa[B:], axis=0, out=self._blocks[B:])
        return self._blocks

    def _cross_blocks(self, idx: np.ndarray) -> np.ndarray:
        """Cross blocks ``idx`` (indices into ``blocks``); a tied bank's are read as their reference
        members' covariances, without materialising the others."""
        return self._blocks[self.pa[idx] if self.tied else idx]

    def member(self, excluded_ids: Sequence[str]) -> int:
        """Index of the member that excludes exactly these satellites."""
        pos = {s: i for i, s in enumerate(self.sats)}
        return self.index[tuple(sorted(pos[s] for s in excluded_ids))]

    def cross(self, a: int, b: int) -> np.ndarray:
        """Cov(e_a, e_b) for a stored pair (either orientation) or a member (a == b)."""
        for k in range(len(self.pa)):
            if self.pa[k] == a and self.pb[k] == b:
                return self.blocks[k]
            if self.pa[k] == b and self.pb[k] == a:
                return self.blocks[k].T
        raise KeyError(f"cross-covariance ({a}, {b}) is not kept by the bank")

    def rebuild(self, new_sats: Sequence[str], purge: Sequence[str] = ()) -> MhssBank:
        """The bank over ``new_sats`` (module docstring "Rebuilding the bank").

        ``purge``: satellites removed because they are faulty (exclusion); their contamination is
        removed by taking the members that never used them. Other satellites absent from
        ``new_sats`` simply stop being used; satellites new to the bank enter as copies.
        """
        new_sats = tuple(new_sats)
        if set(purge) & set(new_sats):
            raise ValueError("a purged satellite cannot stay in the bank")
        old_pos = {s: i for i, s in enumerate(self.sats)}
        X = tuple(sorted(old_pos[s] for s in purge if s in old_pos))
        x_fallback = self.index.get(X, 0)
        members, _, pa, pb, *_ = _layout(len(new_sats), self.depth if new_sats else 0)

        def source(excluded: tuple[int, ...]) -> int:
            cand = tuple(sorted({old_pos[new_sats[i]] for i in excluded if new_sats[i] in old_pos} | set(X)))
            return self.index.get(cand, x_fallback)

        src = np.array([source(e) for e in members], dtype=int)
        lookup = {(int(a), int(b)): k for k, (a, b) in enumerate(zip(self.pa, self.pb, strict=True))}
        idx = np.empty(len(pa), dtype=int)
        trans = np.zeros(len(pa), dtype=bool)
        for k, (a, b) in enumerate(zip(src[pa], src[pb], strict=True)):
            key = (int(a), int(b))
            if key in lookup:
                idx[k] = lookup[key]
            elif key[::-1] in lookup:
                idx[k], trans[k] = lookup[key[::-1]], True
            else:  # cannot happen with the source rule above; keep the failure loud
                raise RuntimeError(f"rebuild: no cross-covariance for old members {key}")
        blocks = self.blocks[idx]
        blocks[trans] = np.swapaxes(blocks[trans], 1, 2)
        # the tie survives a rebuild without a purge: every new cross block is then an old block
        # stored in its orientation (or a member's covariance), i.e. its reference member's
        # covariance; the exclusion's restarted sub-subs (copies of the new main) break it
        tied = self.tied and not X and not np.any(trans & (src[pa] != src[pb]))
        out = type(self)(new_sats, self.x[src], blocks, self.depth, self.h_idx, self.v_idx, tied=tied)
        out.sources = src
        return out

    # --- filtering ---------------------------------------------------------------------------------
    def _next_blocks(self) -> np.ndarray:
        """The scratch array the next time or measurement update writes: of two, the one that is not
        ``blocks`` (views of ``blocks`` stay valid until the second update after)."""
        a = self._work.get("blocks_a", self._blocks.shape)
        return self._work.get("blocks_b", self._blocks.shape) if a is self._blocks else a

    def _computed(self) -> int:
        """How many of the first blocks the recursion computes: the members only when tied."""
        return self.B if self.tied else len(self._blocks)

    def predict(self, Phi: np.ndarray, Qd: np.ndarray) -> None:
        """Time update of every member and cross block: two batched products, P <- (Phi P) Phi' + Q
        (the members only when tied)."""
        Phi = np.asarray(Phi, dtype=float)
        self.x = self.x @ Phi.T
        nb = self._computed()
        tmp = self._work.get("phi_p", (nb,) + self._blocks.shape[1:])
        np.matmul(Phi, self._blocks[:nb], out=tmp)
        out = self._next_blocks()
        np.matmul(tmp, np.ascontiguousarray(Phi.T), out=out[:nb])
        out[:nb] += Qd
        self._symmetrise_members(out)
        self._blocks = out

    def _symmetrise_members(self, blocks: np.ndarray) -> None:
        """P <- (P + P') / 2 in place for the member covariances (the first B blocks)."""
        P = blocks[: self.B]
        t = self._work.get("sym", P.shape)
        np.add(P, P.swapaxes(1, 2), out=t)
        np.multiply(t, 0.5, out=P)

    def update(self, z: np.ndarray, H: np.ndarray, r_var: np.ndarray, row_sat: np.ndarray) -> BankUpdate:
        """Measurement update of every member (row mask per member) and every cross block.

        Parameters
        ----------
        z : (m,) measurements; H : (m, n); r_var : (m,) noise variances (R diagonal);
        row_sat : (m,) index into ``sats`` of each row's satellite.
        """
        B = self.B
        z = np.asarray(z, dtype=float)
        H = np.asarray(H, dtype=float)
        r_var = np.asarray(r_var, dtype=float)
        m = len(z)
        keep_b = ~self.excl[:, np.asarray(row_sat, dtype=int)] if self.N else np.ones((B, m), dtype=bool)
        # a bank of one filter (integrity off) takes the plain update of every other pipeline
        g = _masked_gain(self.x, self._blocks[:B], z, H, r_var, keep_b) if B > 1 else None
        if g is None:  # general path (raises NotPositiveDefinite when an S is not positive definite)
            ref = kalman.gain(self.x, self._blocks[:B], z, H, r_var, keep_b)
            self.x = ref.x
            self._blocks = self._joseph_all(ref.IKH, ref.K, r_var)
            res = ref.result
            return BankUpdate(res.innovation, res.dof, ref.K, ref.IKH, res.whitened, res.nis)
        blocks = self._joseph_observed(g)
        self.x = g.x
        self._blocks = blocks
        return BankUpdate(g.innovation, g.dof, gain=g)

    def _joseph_observed(self, g: _Gain) -> np.ndarray:
        """:func:`cross_update` of every block from the factored gains (:func:`_masked_gain`).

        With K = L G_a' R^-1: K H = L J E, and K_a R K_b' = L_a (G_a' R^-1 G_b) L_b' = L_a J_b L_b'
        (the rows b uses are rows a uses: every block pairs a filter with itself or one of its
        children), so with W_b = J_b L_b' (s, n) the product form reads

            T = (I - K_a H) P_ab = P_ab - (L_a J_a) (E P_ab)
            T (I - K_b H)' + K_a R K_b' = T + (L_a - T E') W_b

        two (n, s) x (s, n) products per block instead of n x n ones, for all blocks at once (the
        factors of a and b gathered per block; a tied bank's members only, nothing gathered)."""
        n, Wk = self.n, self._work
        nb = self._computed()
        sel, blocks = g.sel, self._blocks[:nb]
        s = len(sel)
        LJ = g.L @ g.J  # K H on the observed columns (B, n, s)
        Wb = g.J @ g.L.swapaxes(1, 2)  # (B, s, n)
        Ps = blocks.take(sel, axis=1, out=Wk.get("p_s", (nb, s, n)), mode="clip")  # E P
        T = Wk.get("t", blocks.shape)
        X = Wk.get("x", (nb, n, s))
        out = self._next_blocks()

        if self.tied:  # members: a = b, the factors as they are
            LJa, La, Wbb = LJ, g.L, Wb
        else:
            pa, pb = self.pa, self.pb
            LJa = LJ.take(pa, axis=0, out=Wk.get("lj_a", (nb, n, s)), mode="clip")
            La = g.L.take(pa, axis=0, out=Wk.get("l_a", (nb, n, s)), mode="clip")
            Wbb = Wb.take(pb, axis=0, out=Wk.get("w_b", (nb, s, n)), mode="clip")
        np.matmul(LJa, Ps, out=T)
        np.subtract(blocks, T, out=T)
        T.take(sel, axis=-1, out=X, mode="clip")
        np.subtract(La, X, out=X)
        np.matmul(X, Wbb, out=out[:nb])
        out[:nb] += T
        self._symmetrise_members(out)
        return out

    def _joseph_all(self, IKH: np.ndarray, K: np.ndarray, r_var: np.ndarray) -> np.ndarray:
        """:func:`cross_update` of every block with explicit gains (the general path), by segment:
        members (a = b), main-sub (a = 0, broadcast), sub-subsub (a = sub n, broadcast over its
        N-1 sub-subs; b gathered). Right factors are pre-transposed into contiguous arrays."""
        B, N, n = self.B, self.N, self.n
        IKHt = np.ascontiguousarray(np.swapaxes(IKH, 1, 2))
        Kt = np.ascontiguousarray(np.swapaxes(K, 1, 2))
        KR = K * r_var
        out = np.empty_like(self._blocks)
        out[:B] = symmetrise(IKH @ self._blocks[:B] @ IKHt + KR @ Kt)
        if self.depth >= 1 and N and not self.tied:
            subs = slice(1, 1 + N)
            out[B : B + N] = IKH[0] @ self._blocks[B : B + N] @ IKHt[subs] + KR[0] @ Kt[subs]
            if self.depth >= 2 and N > 1:
                mem = self.subsub_members
                blk = self._blocks[B + N :].reshape(N, N - 1, n, n)
                a, ka = IKH[subs][:, None], KR[subs][:, None]
                out[B + N :] = (a @ blk @ IKHt[mem] + ka @ Kt[mem]).reshape(-1, n, n)
        return out

    def shift(self, dx: np.ndarray) -> None:
        """Closed-loop feedback of the main correction: every member x_i <- x_i - dx."""
        self.x -= np.asarray(dx, dtype=float)[None, :]

    # --- checkpoints ------------------------------------------------------------------------------
    def state(self) -> BankState:
        """A copy of the bank's whole state (:class:`BankState`), for a lifecycle checkpoint: about
        B n^2 doubles when tied (79 members of 17 states for 12 satellites: 180 kB), every block
        otherwise (223 blocks: 520 kB)."""
        blocks = self._blocks[: self.B] if self.tied else self._blocks
        return BankState(
            self.sats, self.depth, self.x.copy(), blocks.copy(), self.tied, self.h_idx, self.v_idx
        )

    @classmethod
    def restored(cls, s: BankState, P_main: np.ndarray) -> MhssBank | None:
        """The bank of checkpoint ``s`` restarted with main covariance ``P_main``: what the restart
        changed of the main's covariance (the carry's growth, a reset's new sigmas) is an error
        common to every member, so ``P_main - P_00`` is added to every block, and every member
        keeps its own excess over the main (P_nn - P_00, what the separations, their thresholds
        and the protection levels are made of) and its state. Each member's covariance stays
        positive definite when the restart's and the excess are (a sub-filter uses a subset of the
        main's rows: P_nn >= P_00); None when the shapes disagree or a member is not (the
        caller then starts every member from the main, as a new bank)."""
        P_main = np.asarray(P_main, dtype=float)
        if s.blocks.ndim != 3 or P_main.shape != s.blocks.shape[1:]:
            return None
        members, _, pa, *_ = _layout(len(s.sats), s.depth if s.sats else 0)
        B, C = len(members), len(pa)
        if s.x.shape[0] != B or len(s.blocks) not in (B, C):
            return None
        blocks = np.empty((C,) + P_main.shape)
        np.add(s.blocks, P_main - s.blocks[0], out=blocks[: len(s.blocks)])
        blocks[0] = P_main
        if len(s.blocks) < C:  # tied: the cross blocks are read from their reference members
            np.take(blocks, pa[B:], axis=0, out=blocks[B:])
        P = blocks[:B]
        P += P.swapaxes(1, 2)
        P *= 0.5
        try:
            np.linalg.cholesky(P)
        except np.linalg.LinAlgError:
            return None
        return cls(s.sats, s.x, blocks, s.depth, s.h_idx, s.v_idx, tied=s.tied and len(s.blocks) == B)

    # --- tests ----------------------------------------------------------------------------------------
    def main_tests(self, kfa: float, kmd: float, kfa_h: float | None = None) -> SeparationTests:
        """Main filter against every sub-filter (detection and protection levels)."""
        if self.depth < 1 or self.N == 0:
            none = np.zeros((0, self.n, self.n))
            return solution_separation(
                self.x[0],
                self.P[0],
                np.zeros((0, self.n)),
                none,
                none,
                kfa,
                kmd,
                self.h_idx,
                self.v_idx,
                kfa_h,
            )
        N = self.N
        return solution_separation(
            self.x[0],
            self.P[0],
            self.x[1 : 1 + N],  # sub-filters: members 1..N; their main blocks: B..B+N-1
            self.P[1 : 1 + N],
            self._cross_blocks(self.main_blocks),
            kfa,
            kmd,
            self.h_idx,
            self.v_idx,
            kfa_h,
        )

    def sub_tests(self, r: int, kfa: float, kmd: float, kfa_h: float | None = None) -> SeparationTests:
        """Sub-filter r against its sub-sub filters (r, m), m != r (in satellite order, skipping r)."""
        if self.depth < 2:
            raise ValueError("sub-sub filters are off (depth < 2)")
        s = 1 + r
        mem = self.subsub_members[r]
        return solution_separation(
            self.x[s],
            self.P[s],
            self.x[mem],
            self.P[mem],
            self._cross_blocks(self.sub_blocks[r]),
            kfa,
            kmd,
            self.h_idx,
            self.v_idx,
            kfa_h,
        )

    def find_exclusion(
        self,
        tests: SeparationTests,
        p_fa: float,
        kmd: float,
        use_vertical: bool,
        n_families: int = 1,
        extra_flagged: np.ndarray | None = None,
        extra_score: np.ndarray | None = None,
        horizontal_threshold: str = "gaussian",
    ) -> int | None:
        """Satellite index to exclude after a detection, or None (module docstring "Exclusion").

        ``extra_flagged`` / ``extra_score`` (N,): satellites flagged by another detector (the
        satellite residual test) and their normalised statistics; they join the candidates and
        the ranking (a candidate's sub-sub separation tests must still all pass).
        """
        if self.depth < 2 or self.N < 2:
            return None
        kfa_sub = k_fa(p_fa, (self.N - 1) * n_families)
        kfa_sub_h = k_fa_horizontal(p_fa, (self.N - 1) * n_families, horizontal_threshold)
        flagged = tests.flagged(use_vertical)
        score = tests.normalised(use_vertical)
        if extra_flagged is not None:
            flagged = flagged | np.asarray(extra_flagged, dtype=bool)
        if extra_score is not None:
            score = np.maximum(score, np.asarray(extra_score, dtype=float))
        failed = np.flatnonzero(flagged)
        cands = [
            int(r)
            for r in failed
            if not np.any(self.sub_tests(int(r), kfa_sub, kmd, kfa_sub_h).flagged(use_vertical))
        ]
        if not cands:
            return None
        return max(cands, key=lambda r: score[r])

    def excluded_residuals(
        self, z: np.ndarray, H: np.ndarray, r_var: np.ndarray, rows: np.ndarray
    ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Residual of each satellite against the sub-filter that excludes it (after the update).

        ``rows`` (N,): for satellite n (bank order) the index of its row in (z, H, r_var). Returns
        ``e`` (N,) = z_n - H_n x_0n, ``hph`` (N,) = H_n P_0n H_n' and ``r`` (N,) = R_n. Sub-filter
        F0n never used satellite n, so e_n = H_n (error of F0n) + v_n with v_n independent of
        F0n: E e_n = fault of n, var e_n = hph_n + r_n (the "satellite residual test").
        """
        if self.depth < 1 or self.N == 0:
            z0 = np.zeros(0)
            return z0, z0, z0
        rows = np.asarray(rows, dtype=int)
        Hn = H[rows]
        subs = slice(1, 1 + self.N)
        e = z[rows] - np.einsum("ij,ij->i", Hn, self.x[subs])
        hph = np.einsum("ij,ijk,ik->i", Hn, self.P[subs], Hn)
        return e, np.maximum(hph, 0.0), np.asarray(r_var, dtype=float)[rows]


def residual_test(
    x: np.ndarray, P: np.ndarray, z: np.ndarray, H: np.ndarray, r_var: np.ndarray
) -> np.ndarray:
    """Standardised innovations (m,) of rows (z, H, r_var) against a filter (x, P):
    (z - H x) / sqrt(H P H' + r), one per row (used to re-admit an excluded satellite)."""
    s = np.einsum("ij,jk,ik->i", H, P, H) + r_var
    return (z - H @ x) / np.sqrt(s)


__all__ = [
    "BankState",
    "BankUpdate",
    "H_IDX",
    "MhssBank",
    "SeparationTests",
    "V_IDX",
    "cross_predict",
    "cross_update",
    "horizontal_false_alarm_probability",
    "k_fa",
    "k_fa_horizontal",
    "k_md",
    "lambda_max_2x2",
    "q_inv",
    "residual_test",
    "solution_separation",
]
