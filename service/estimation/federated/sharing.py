"""Information-sharing strategies of the federated filter: local covariances -> per-state shares.

Interface (docs/STYLE.md 2): ``SharingStrategy.shares(P_locals, context) -> G``

    P_locals : (N, c, c)  the N local filters' covariances over the c common states, taken after
                          their measurement updates and before the master fusion;
    G        : (N, c)     G[i, j] = beta_{j,i}, the share of common state j given to local i,
                          i.e. G_i = diag(G[i]).

Invariants (tested): every share is > 0 (the reset divides by it) and, for every state j,
``sum_i G[i, j] + master_share = 1`` (information conservation, seed 000 eq (12); docs/DESIGN.md).
The federated core (``federated.py``) then resets local i to

    P_i = G_i^-1/2 P_g G_i^-1/2,   Q_i = G_i^-1/2 Q G_i^-1/2        seed 000 eq (14)-(15), (25)-(26)

Theory every user of this module should know (docs/PAPERS.md, seed 000 "warning from theory"):

* Scalar shares (G_i = beta_i I): with fusion and reset every cycle and Q_i = Q / beta_i, the
  fused information is sum_i beta_i P_g^-1 = P_g^-1 exactly, so *any* scalar beta reproduces the
  centralised Kalman filter (Carlson 1990). Fault-free differences between fixed, trace, EDOP,
  norm-weighted, eigen-trace (either direction) cannot come from beta under a consistent model;
  beta only changes each local's own prior (its innovation covariance, hence its fault tests'
  sensitivity, and its linearisation in nonlinear models).
* Diagonal (per-state, "vector") shares are *not* information preserving when P_g has
  cross-correlations: the fused information becomes Y_g o C with C_jk = sum_i sqrt(g_ij g_ik) <= 1
  (Cauchy-Schwarz, equality iff the share columns j and k are proportional), so off-diagonal
  information is lost while diagonal information is kept. In an INS the lost terms are the
  strong correlations (velocity-attitude-accelerometer bias) whose cancellation keeps weakly
  observable combinations uncertain, so each reset creates spurious information there and
  the filter becomes overconfident, then under-weights new measurements (measured in
  tests/test_federated.py).
* Per-DIRECTION shares along the eigenvectors of P_g (``vector_eigen``, the eigendecomposition of
  seed 000 eq 11) are information preserving: G_i = V diag(beta_i) V^-1 commutes with P_g, so
  sum_i P_i^-1 = P_g^-1 exactly; with the process noise split by scalars the federated filter is
  then conservative (never overconfident) and, fault free, within ~0.2 % of the centralised
  filter's error variance. This is the recommended vector strategy (and the default).

The eq (22) floor (``floor_share``) trades information for test sensitivity: a floored local's
prior of those states is ~1/floor times wider, so its NEXT fault test on them is blunter. With
10 m fixes and ~1 m position variance, a floor of 1e-3 gives a prior sigma of ~33 m and the
paper's 100 m position step passes at ~3 sigma (measured: NEES 20, height RMS 2 m in
seed000_faults); floors from 0.05 to 0.49 give identical, consistent results. Default 0.05.

Units: trace- and norm-based strategies add variances of different units (m^2, (m/s)^2, rad^2,
(rad/s)^2); in the 15-state INS model the position block dominates them. That is how the papers
define them; the per-state strategies (vector, diagonal, vector_conservative) are unit-free.

Strategies (registry names = ``service.config.SharingName``):
  fixed, trace (seed 000 eq 36), vector (seed 000 eq 13 per state, read per docs/PAPERS.md + eq 22
  floor), vector_eigen (seed 000 eq 11-15, 22 along the eigen-directions of P_g; recommended),
  vector_conservative (ours: scalar mean of the per-state shares), eigen_trace (seed 004 5.1 as
  printed), eigen_trace_inverse, diagonal (seed 004 5.2 as printed), edop (seed 004 5.3),
  norm_weighted (seed 002 eq 18-21).
"""

from __future__ import annotations

from abc import ABC, abstractmethod
from dataclasses import dataclass
from typing import ClassVar

import numpy as np

from fednav.service.estimation.kalman import information_fusion

# Smallest share any strategy may hand out (numerical guard, not a modelling choice): the reset
# divides by the share, so it must never be 0.
MIN_SHARE = 1e-9


@dataclass(frozen=True)
class SharingContext:
    """What a strategy may use besides the covariances.

    flagged_only : (N, c) bool, optional
        True where common state j of local i was directly observed this epoch only through
        observations its fault test flagged (no used row of local i observed it). Used by the
        seed 000 eq (22) reading (vector strategies).
    floor_share : float
        The share such a state gets in that local (fraction of the locals' total).
    master_share : float
        Share kept by the master filter; the locals' shares sum to ``1 - master_share``.
    """

    flagged_only: np.ndarray | None = None
    floor_share: float = 0.05
    master_share: float = 0.0


_DEFAULT_CONTEXT = SharingContext()


@dataclass(frozen=True)
class ResetPlan:
    """How the federated core resets the N locals from the fused (x_g, P_g): seed 000 eq (14)-(15).

    shares : (N, c)
        beta_{j,i}. With ``directions`` None they are per STATE: G_i = diag(shares[i]) and
            P_i = G_i^-1/2 P_g G_i^-1/2,   Q_i = G_i^-1/2 Q G_i^-1/2.
        Otherwise per DIRECTION: G_i = V diag(shares[i]) V^-1 with V = diag(scale) directions,
        the directions chosen so that V^-1 P_g V^-T = diag(lam) (seed 000 eq 11), and
            P_i = G_i^-1/2 P_g G_i^-T/2 = V diag(lam / shares[i]) V'.
    q_shares : (N,) or None
        Scalar process-noise shares, Q_i = Q / q_shares[i] (they sum to the locals' total); None
        means the per-state form above.
    """

    shares: np.ndarray
    directions: np.ndarray | None = None  # U (c, c), orthonormal columns
    scale: np.ndarray | None = None  # (c,) V = diag(scale) U
    lam: np.ndarray | None = None  # (c,) V^-1 P_g V^-T = diag(lam)
    q_shares: np.ndarray | None = None

    def state_shares(self) -> np.ndarray:
        """(N, c) the diagonal of every G_i in state coordinates (per-state shares for display;
        columns still sum to the locals' total because the diagonal of sum_i G_i = I is 1)."""
        if self.directions is None:
            return self.shares
        return self.shares @ (self.directions**2).T  # diag(U diag(b) U') = (U o U) b

    def covariances(self, P_g: np.ndarray) -> np.ndarray:
        """(N, c, c) the reset covariances P_i of the locals' common states."""
        if self.directions is None:
            inv_sqrt = 1.0 / np.sqrt(self.shares)  # G_i^-1/2
            return inv_sqrt[:, :, None] * P_g[None] * inv_sqrt[:, None, :]  # seed 000 eq (14)
        V = self.scale[:, None] * self.directions
        return np.einsum("jk,ik,lk->ijl", V, self.lam[None] / self.shares, V)  # V diag(lam/b_i) V'

    def q_scales(self) -> np.ndarray:
        """(N, c) per-state process-noise scales of the bank (Q_i = S^1/2 Q S^1/2, S = diag)."""
        if self.q_shares is None:
            return 1.0 / self.shares  # seed 000 eq (15)
        return np.broadcast_to(1.0 / self.q_shares[:, None], self.shares.shape).copy()


class SharingStrategy(ABC):
    """Base: subclasses return un-normalised weights; the base normalises, guards and scales.

    ``scalar`` is True when the strategy gives one share per local for all states (and hence, with
    fusion-reset every cycle, reproduces the centralised filter exactly).
    """

    name: ClassVar[str]
    scalar: ClassVar[bool]

    def shares(self, P_locals: np.ndarray, context: SharingContext | None = None) -> np.ndarray:
        """Per-state shares G (N, c) of the N locals; columns sum to ``1 - master_share``."""
        P = np.asarray(P_locals, dtype=float)
        if P.ndim != 3 or P.shape[1] != P.shape[2]:
            raise ValueError(f"P_locals must be (N, c, c), got {P.shape}")
        ctx = context if context is not None else _DEFAULT_CONTEXT
        N, c, _ = P.shape
        if N == 1:
            return np.full((1, c), 1.0 - ctx.master_share)
        w = np.asarray(self._weights(P, ctx), dtype=float).reshape(N, -1)
        if not (np.isfinite(w).all() and (w >= 0.0).all()):
            raise ValueError(f"sharing strategy {self.name!r} produced invalid weights")
        w = _normalise(w)  # (N, 1) for scalar strategies, (N, c) per state
        return (1.0 - ctx.master_share) * np.broadcast_to(w, (N, c))

    def plan(
        self, P_locals: np.ndarray, P_fused: np.ndarray, context: SharingContext | None = None
    ) -> ResetPlan:
        """The reset of the locals after a fusion (``ResetPlan``); per-state strategies return
        their ``shares`` (diagonal G_i). ``P_fused`` is the master's fused P_g (c, c)."""
        return ResetPlan(self.shares(P_locals, context))

    @abstractmethod
    def _weights(self, P: np.ndarray, ctx: SharingContext) -> np.ndarray:
        """(N,) scalar or (N, c) per-state non-negative weights (normalised by the base)."""


def _normalise(w: np.ndarray) -> np.ndarray:
    """Columns to sum 1, then lift anything below MIN_SHARE and renormalise (never 0)."""
    w = w / np.sum(w, axis=0, keepdims=True)
    w = np.maximum(w, MIN_SHARE)
    return w / np.sum(w, axis=0, keepdims=True)


def _diag(P: np.ndarray) -> np.ndarray:
    return np.diagonal(P, axis1=1, axis2=2)


def _trace(P: np.ndarray) -> np.ndarray:
    return np.trace(P, axis1=1, axis2=2)


def _frobenius(P: np.ndarray) -> np.ndarray:
    # sqrt(tr(P P')) = sqrt(tr(P^2)) for symmetric P = Frobenius norm
    return np.sqrt(np.einsum("bij,bij->b", P, P))


# --- scalar strategies -----------------------------------------------------------------------------
class Fixed(SharingStrategy):
    """Fixed equal shares beta_i = 1/N (seed 000's "1:1" comparator for N = 2)."""

    name = "fixed"
    scalar = True

    def _weights(self, P, ctx):
        return np.ones(P.shape[0])


class Trace(SharingStrategy):
    """Adaptive scalar sharing, seed 000 eq (36): beta_i = (1/tr P_i) / sum_k (1/tr P_k)."""

    name = "trace"
    scalar = True

    def _weights(self, P, ctx):
        return 1.0 / _trace(P)  # seed 000 eq (36)


class EigenTrace(SharingStrategy):
    """Seed 004 section 5.1 AS PRINTED: beta_i = tr(Lambda_i) / sum_k tr(Lambda_k).

    Lambda_i = eigenvalues of P_i, so tr(Lambda_i) = tr(P_i). WARNING (flagged per docs/PAPERS.md): as
    printed this gives MORE share (smaller reset covariance P_g / beta_i) to the LESS accurate
    local filter, the opposite of the usual intent. Kept as printed for reproduction; see
    ``eigen_trace_inverse``. Being scalar, with fusion-reset every cycle it still reproduces the
    centralised filter (docs/PAPERS.md warning), so the inversion shows only in fault-test sensitivity.
    """

    name = "eigen_trace"
    scalar = True

    def _weights(self, P, ctx):
        return _trace(P)  # tr(Lambda_i) = tr(P_i); seed 004 5.1 as printed


class EigenTraceInverse(SharingStrategy):
    """Seed 004 section 5.1 inverted: beta_i = (1/tr Lambda_i) / sum_k (1/tr Lambda_k).

    Since tr(Lambda_i) = tr(P_i) this is numerically the same as ``trace`` (seed 000 eq 36); it is
    kept as its own name so seed 004 configurations read as the paper's method family.
    """

    name = "eigen_trace_inverse"
    scalar = True

    def _weights(self, P, ctx):
        return 1.0 / _trace(P)


class Edop(SharingStrategy):
    """Seed 004 section 5.3: EDOP_i = sqrt(tr(P_i P_i')), beta_1 = EDOP_2 / (EDOP_1 + EDOP_2).

    Generalised to N locals as beta_i = (1/EDOP_i) / sum_k (1/EDOP_k), which is exactly the
    printed formula for N = 2 (EDOP_2 / (EDOP_1 + EDOP_2) = (1/EDOP_1) / (1/EDOP_1 + 1/EDOP_2)).
    EDOP is the Frobenius norm of P_i (dominated by the largest-variance states).
    """

    name = "edop"
    scalar = True

    def _weights(self, P, ctx):
        return 1.0 / _frobenius(P)


class NormWeighted(SharingStrategy):
    """Seed 002 eq (18)-(21): A_j = sqrt(tr(P_j^2)), alpha_j = sum_{i != j} A_i / ((N-1) sum_i A_i).

    The paper prints the denominator as ``2 sum_i A_i`` for its N = 3 wing IMUs; 2 = N - 1, which
    is what makes the shares sum to 1: sum_j (S - A_j) = (N - 1) S. We use N - 1 for any N >= 2.
    A larger norm (less accurate local) gives a smaller share.
    """

    name = "norm_weighted"
    scalar = True

    def _weights(self, P, ctx):
        A = _frobenius(P)  # seed 002 eq (18)
        S = A.sum()
        return (S - A) / ((P.shape[0] - 1) * S)  # seed 002 eq (19)-(21), generalised to N


# --- per-state (vector) strategies ---------------------------------------------------------------
def vector_shares(P: np.ndarray, ctx: SharingContext) -> np.ndarray:
    """Seed 000 eq (13) read per docs/PAPERS.md, plus the eq (22) floor; (N, c), columns sum to 1.

    beta_{j,i} = (1/P_i,jj) / sum_k (1/P_k,jj)   (normalised over locals k, not states)
    Eq (22) reading: where ``ctx.flagged_only[i, j]``, local i gets exactly ``floor_share`` of
    state j and the other locals share the rest in proportion to their eq (13) weights.
    """
    return _eq13_with_floor(_diag(P), ctx.flagged_only, ctx.floor_share)


def _eq13_with_floor(lam: np.ndarray, flagged: np.ndarray | None, floor_share: float) -> np.ndarray:
    """beta_{j,i} = (1/lam_{j,i}) / sum_k (1/lam_{j,k}) for variances lam (N, c) (seed 000 eq 13 read
    per docs/PAPERS.md), then the eq (22) floor where ``flagged[i, j]``; columns sum to 1."""
    inv = 1.0 / lam  # 1/lambda_{j,i}
    w = inv / inv.sum(axis=0, keepdims=True)  # seed 000 eq (13), read per docs/PAPERS.md
    fl = flagged
    if fl is None or not np.any(fl):
        return w
    fl = np.asarray(fl, dtype=bool)
    N = w.shape[0]
    n_fl = fl.sum(axis=0)  # (c,) how many locals have state j flagged-only
    cols = (n_fl > 0) & (n_fl < N)  # if every local is flagged there is nothing to prefer
    if not np.any(cols):
        return w
    floor = np.minimum(floor_share, 0.5 / np.maximum(n_fl, 1))  # keep the healthy rest > 0
    rest = np.where(fl, 0.0, w)
    rest_sum = rest.sum(axis=0)
    healthy = rest * ((1.0 - n_fl * floor) / np.where(rest_sum > 0.0, rest_sum, 1.0))
    floored = np.where(fl, floor, healthy)  # seed 000 eq (22), read per docs/PAPERS.md
    return np.where(cols, floored, w)


class Vector(SharingStrategy):
    """Vector information sharing, seed 000 eq (11)-(15), (22), as read in docs/PAPERS.md.

    Per state j: beta_{j,i} = (1/P_i,jj) / sum_k (1/P_k,jj); a state of local i observed this
    epoch only through flagged observations gets the floor share (``SharingContext``).

    Known defect (docs/PAPERS.md; measured in tests/test_federated.py): with the reset
    P_i = G_i^-1/2 P_g G_i^-1/2 the fused information loses off-diagonal terms (factor
    sum_i sqrt(g_ij g_ik) <= 1) while keeping the diagonal, which makes the federated filter
    overconfident. Found: one-axis INS linear model, expected NEES ~40 against 5 and a true
    position error variance ~20x the centralised one; static INS/GNSS/CNS scenario, NEES ~80
    against 9; seed 000 flight scenario (fednav-sim eval, seed 1), NEES ~9400 against 9 and
    ~37 m north RMS against ~1 m for the centralised filter (which it matches with
    ``vector_conservative``, and is consistent with ``vector_eigen``). Also note the floor makes
    local i's prior of that state ~1/floor times wider, so its next fault test on that state is
    less sensitive.
    """

    name = "vector"
    scalar = False

    def _weights(self, P, ctx):
        return vector_shares(P, ctx)


class VectorConservative(SharingStrategy):
    """A simple fix for ``vector``: one scalar share per local, from the vector shares.

    beta_i = mean_j beta_{j,i} over the c common states, with beta_{j,i} the ``vector`` shares
    (eq (13) as read, eq (22) floor included). The mean of columns that each sum to 1 again sums to
    1, so conservation holds; and because the share is a scalar, the reset
    P_i = P_g / beta_i, Q_i = Q / beta_i is information-consistent: sum_i P_i^-1 = P_g^-1 exactly,
    so fault free it reproduces the centralised filter (Carlson 1990) and cannot be overconfident.
    What it keeps from ``vector``: the weighting is unit-free (each state compares like with
    like, unlike tr P which is dominated by position variances) and a local with flagged states
    gets a smaller share.

    Alternative considered and not chosen: keep diagonal G and inflate the reset covariances by
    kappa = lambda_max(Y_g^-1/2 (Y_g o C) Y_g^-1/2) >= 1 (covariance-intersection style). It is
    consistent but conservative: the shares then sum to 1/kappa < 1, i.e. information is thrown
    away every cycle, and it costs a generalised eigenproblem per epoch; under fusion-reset every
    cycle per-state shares buy nothing in fused accuracy anyway.
    """

    name = "vector_conservative"
    scalar = True

    def _weights(self, P, ctx):
        return vector_shares(P, ctx).mean(axis=1)


def eigen_directions(P_g: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(scale, U, lam): P_g = diag(scale) U diag(lam) U' diag(scale), the eigendecomposition of
    seed 000 eq (11) taken on the correlation matrix of P_g (unit-free: raw INS covariances mix
    m^2 with rad^2, and their eigenvectors would just be the states sorted by unit)."""
    scale = np.sqrt(np.diagonal(P_g))
    C = P_g / np.outer(scale, scale)
    lam, U = np.linalg.eigh(0.5 * (C + C.T))
    return scale, U, np.maximum(lam, np.finfo(float).tiny)


class VectorEigen(SharingStrategy):
    """Vector information sharing along the eigen-directions of P_g: seed 000 eq (11)-(15), (22).

    The paper builds its shares from an eigendecomposition (eq 11: P = D L D', beta from the
    eigenvalues) and claims sum_i G_i = I conserves information; with a DIAGONAL G in state
    coordinates it does not (``vector``, module docstring). Here G_i is diagonal in the
    eigenbasis of the fused covariance, which makes eq (14) exactly information-preserving:

        P_g = V diag(lam) V'               V = diag(sqrt(P_g,jj)) U, U' C U = diag(lam)  (eq 11)
        lam_{j,i} = (V^-1 P_i V^-T)_jj      variance of local i along direction j
        beta_{j,i} = (1/lam_{j,i}) / sum_k (1/lam_{j,k})                                  (eq 13)
        G_i = V diag(beta_i) V^-1,  sum_i G_i = I                                         (eq 12)
        P_i = G_i^-1/2 P_g G_i^-T/2 = V diag(lam / beta_i) V'                             (eq 14)

    so sum_i P_i^-1 = V^-T diag(sum_i beta_i / lam) V^-1 = P_g^-1 exactly, for any shares.
    Each local is told precisely as much as it contributes along each direction, and the
    correlations (tilt-velocity-bias) survive the reset. Eq (15) with a non-commuting G_i would
    again lose information, so the process noise is split with one scalar per local,
    Q_i = Q / q_i, q_i = mean_j beta_{j,i}, which conserves it (sum_i Q_i^-1 = Q^-1): the fused
    predicted information can then only be smaller than the centralised filter's (the parallel
    sum is superadditive), i.e. in the linear model the filter is conservative, never overconfident.
    Eq (22) floor: a direction whose weight sum_k U_kj^2 lies mostly (> 1/2) on states local i
    saw only through flagged rows gets the floor share in local i.
    """

    name = "vector_eigen"
    scalar = False

    def _weights(self, P, ctx):  # per-state view (display, ``shares``): the diagonal of each G_i
        return self.plan(P, information_fusion(np.zeros(P.shape[:2]), P)[1], ctx).state_shares()

    def plan(self, P_locals, P_fused, context=None):
        P = np.asarray(P_locals, dtype=float)
        ctx = context if context is not None else _DEFAULT_CONTEXT
        N, c, _ = P.shape
        total = 1.0 - ctx.master_share
        scale, U, lam = eigen_directions(np.asarray(P_fused, dtype=float))
        if N == 1:
            return ResetPlan(np.full((1, c), total), U, scale, lam, np.full(1, total))
        Vinv = U.T / scale[None, :]  # V^-1 = U' diag(1/scale)
        lam_i = np.einsum("jk,ikl,jl->ij", Vinv, P, Vinv)  # (V^-1 P_i V^-T)_jj
        if not (np.isfinite(lam_i).all() and (lam_i > 0.0).all()):
            raise ValueError(f"sharing strategy {self.name!r}: local covariances are not positive definite")
        fl = ctx.flagged_only
        if fl is not None and np.any(fl):  # eq (22) floor, per direction
            fl = (np.asarray(fl, dtype=float) @ U**2) > 0.5
        b = _normalise(_eq13_with_floor(lam_i, fl, ctx.floor_share))
        return ResetPlan(total * b, U, scale, lam, total * b.mean(axis=1))


class Diagonal(SharingStrategy):
    """Seed 004 section 5.2 AS PRINTED: a_j = P1_jj / (P1_jj + P2_jj), beta_1 = diag(a), beta_2 =
    diag(b), b_j = P2_jj / (P1_jj + P2_jj); generalised to N as beta_{j,i} = P_i,jj / sum_k P_k,jj.

    WARNING (flagged per docs/PAPERS.md): as printed, the local with the LARGER variance of state j gets
    the LARGER share of it (the opposite of ``vector``). Per-state, so it has the same
    information-loss defect as ``vector`` (see module docstring).
    """

    name = "diagonal"
    scalar = False

    def _weights(self, P, ctx):
        d = _diag(P)
        return d / d.sum(axis=0, keepdims=True)  # seed 004 5.2 as printed


STRATEGIES: dict[str, type[SharingStrategy]] = {
    cls.name: cls
    for cls in (
        Fixed,
        Trace,
        Vector,
        VectorEigen,
        VectorConservative,
        EigenTrace,
        EigenTraceInverse,
        Diagonal,
        Edop,
        NormWeighted,
    )
}


def get_strategy(name: str) -> SharingStrategy:
    """Registry: a strategy instance by its config name (``service.config.SharingName``)."""
    try:
        return STRATEGIES[name]()
    except KeyError:
        raise ValueError(f"unknown sharing strategy {name!r}; known: {sorted(STRATEGIES)}") from None


__all__ = [
    "SharingStrategy",
    "SharingContext",
    "ResetPlan",
    "eigen_directions",
    "STRATEGIES",
    "get_strategy",
    "vector_shares",
    "MIN_SHARE",
]
