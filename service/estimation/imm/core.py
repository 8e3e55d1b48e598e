"""Interacting multiple model (IMM) cycle on a batched bank (He, Nie, Wu 2011, section 3).

The bank holds one filter per model: ``x`` (M, n), ``P`` (M, n, n), model probabilities ``mu``
(M,) and the Markov transition matrix ``Pi`` (M, M) with ``Pi[i, j] = P(model j at k | model i
at k-1)`` (rows sum to one). One cycle at a measurement epoch:

1. Mixing, eq (4)-(6):  c_j = sum_i Pi_ij mu_i,  mu_{i|j} = Pi_ij mu_i / c_j,
       x0_j = sum_i mu_{i|j} x_i,
       P0_j = sum_i mu_{i|j} (P_i + (x_i - x0_j)(x_i - x0_j)')        (spread-of-means term).
   All members share the transition matrix and process noise, so mixing the predicted members
   at the epoch equals mixing before the prediction (the prediction is linear and sum mu = 1).
2. Per-model update: the rows of model j (its H and R, :mod:`.models`) in ONE batched masked
   update of the bank (:func:`service.estimation.kalman.update`).
3. Probability update, eq (7): mu_j = Lambda_j c_j / sum_i Lambda_i c_i, computed in log space
   (log-sum-exp) with either likelihood:
     ``"paper"``:    Lambda_j = 1 / (V' P0_j^-1 V),  V = x_pred - x_upd  (eq 11, the paper's form;
                     V = K r, so V' P0^-1 V = a' (S - R) a with a = S^-1 r: no P inverse)
     ``"gaussian"``: Lambda_j = N(r_j; 0, S_j)  (eq 8), as log N = -(NIS + log|S| + m log 2 pi) / 2,
                     which never underflows (the reason the paper gives for eq 11).
4. Combined output, eq (12)-(13): x = sum_j mu_j x_j, P = sum_j mu_j (P_j + (x_j - x)(x_j - x)').

Selection correction (option ``selection=True``, not in the paper): a fault model picks its k
suspected rows AFTER seeing the residuals (the largest |v_i|), so its likelihood is the best of
C(m, k) row sets, not the likelihood of a hypothesis fixed before the data. With a uniform prior
over which k of the m rows are outlying, the model's likelihood is the mixture
sum_sets N(r; 0, S_set) / C(m, k); keeping the paper's single (best) set, its max-term
approximation is Lambda_j / C(m, k): log Lambda_j -= log C(m, k). Without it, on clean data
the `largest` model out-scores the normal model whenever max |v_i| > 2.15 (about half of the
epochs with 20 rows) and a good row is down-weighted (docs/seed003.md).

Conditional residuals (option ``residuals="conditional"``, not in the paper): the fault models
choose and weigh their rows by v_i = r_i / sqrt(S_ii), the row's innovation against its marginal
variance. S_ii holds the row's share of every common uncertainty of the prior (the receiver clock
bias, the position), which the other rows determine: at the first epoch of a tightly coupled
filter the clock bias has a sigma of 1e5 m, every |v_i| is below 1e-2 and a 40 m outlier cannot
be told from a good row (docs/seed003.md, "Set 1001 per run": seed 1002). The conditional form
w_i = (S^-1 r)_i / sqrt((S^-1)_ii) is the innovation of row i given all the other rows,
standardised (Baarda's w-test for one outlier in row i under the full S): N(0, 1) on clean data
as v_i is, and its mean under an outlier b on row i is b sqrt((S^-1)_ii) >= b / sqrt(S_ii). With
S near diagonal (R dominant: in the seed 003 scenario from the second epoch on) the two agree.

Learned transition matrix (option, not in the paper): the paper's Pi is a fixed guess of how
often and how persistently outliers occur (2-5 % of the epochs leave the normal model, a fault
model persists with 0.9). :class:`TransitionLearner` estimates Pi online by expectation-
maximisation on the IMM's own quantities: the joint posterior of (model i at k-1, model j at k),
xi_ij = mu_i(k-1) Pi_ij Lambda_j / sum, is accumulated with exponential forgetting (time
constant tau) into counts N_ij, and Pi_ij = (N_ij + n0 Pi0_ij) / (sum_j N_ij + n0): the prior
matrix Pi0 keeps the weight of n0 epochs per row (a model seldom visited keeps the prior's row).
Outliers at a rate and persistence other than the prior's are then met with the rate the data
show (and on clean data the fault models' entries shrink to the false-alarm rate).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from fednav.service.estimation import kalman
from fednav.service.estimation.imm.models import DownWeighting, suspects

LIKELIHOODS = ("paper", "gaussian")
RESIDUALS = ("marginal", "conditional")
_TINY = np.finfo(float).tiny


def mix(
    x: np.ndarray, P: np.ndarray, mu: np.ndarray, Pi: np.ndarray
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Mixing step, eq (4)-(6). Returns (x0 (M, n), P0 (M, n, n), c (M,) predicted probabilities)."""
    c = mu @ Pi  # c_j = sum_i Pi_ij mu_i
    W = Pi * mu[:, None] / np.maximum(c, _TINY)[None, :]  # W[i, j] = mu_{i|j}
    x0 = W.T @ x  # (M, n)
    d = x[None, :, :] - x0[:, None, :]  # d[j, i] = x_i - x0_j
    P0 = np.einsum("ij,ikl->jkl", W, P) + np.einsum("ij,jik,jil->jkl", W, d, d)
    return x0, kalman.symmetrise(P0), c


def combine(x: np.ndarray, P: np.ndarray, mu: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Combined output, eq (12)-(13)."""
    xc = mu @ x
    d = x - xc
    Pc = np.einsum("j,jkl->kl", mu, P) + np.einsum("j,jk,jl->kl", mu, d, d)
    return xc, kalman.symmetrise(Pc)


def log_likelihood_gaussian(res: kalman.UpdateResult) -> np.ndarray:
    """(M,) log N(r; 0, S) of each member's innovation (eq 8 in log space)."""
    _, logdet = np.linalg.slogdet(res.S)
    return -0.5 * (res.nis + logdet + res.dof * math.log(2.0 * math.pi))


def log_likelihood_paper(res: kalman.UpdateResult, R: np.ndarray) -> np.ndarray:
    """(M,) log Lambda_j of eq (11): -log(V' P0^-1 V), V = K r the state correction.

    V' P0^-1 V = r' S^-1 H P0 H' S^-1 r = a' (S - R) a with a = S^-1 r (exact; R as used)."""
    a = np.linalg.solve(res.S, res.innovation[:, :, None])[:, :, 0]
    q = np.einsum("bi,bij,bj->b", a, res.S - R, a)
    return -np.log(np.maximum(q, _TINY))


def log_row_sets(k: np.ndarray, m: int) -> np.ndarray:
    """(M,) log C(m, k): how many sets of k suspected rows a model chose from among m rows."""
    k = np.asarray(k, dtype=float)
    return math.lgamma(m + 1.0) - np.array([math.lgamma(kk + 1.0) + math.lgamma(m - kk + 1.0) for kk in k])


def probabilities(log_lik: np.ndarray, c: np.ndarray) -> np.ndarray:
    """eq (7) in log space: mu_j proportional to Lambda_j c_j (falls back to c if nothing is finite)."""
    lg = log_lik + np.log(np.maximum(c, _TINY))
    ok = np.isfinite(lg)
    if not ok.any():
        return c / c.sum()
    lg = np.where(ok, lg, -np.inf)
    w = np.exp(lg - lg.max())
    return w / w.sum()


class TransitionLearner:
    """Online EM estimate of the Markov matrix (module docstring): ``Pi0`` (M, M) the prior
    matrix, ``prior_epochs`` = n0 its weight per row in epochs, ``tau_s`` the forgetting time
    constant of the counts."""

    def __init__(self, Pi0: np.ndarray, tau_s: float, prior_epochs: float = 50.0):
        self.Pi0 = np.asarray(Pi0, dtype=float)
        self.tau_s = float(tau_s)
        self.n0 = float(prior_epochs)
        self.N = np.zeros_like(self.Pi0)
        self.t_last: float | None = None

    @property
    def Pi(self) -> np.ndarray:
        num = self.N + self.n0 * self.Pi0
        return num / num.sum(axis=1, keepdims=True)

    def update(self, t: float, mu_prev: np.ndarray, Pi: np.ndarray, log_lik: np.ndarray) -> np.ndarray:
        """Add one epoch's joint posterior xi (given the probabilities before the epoch, the
        matrix used and the models' log-likelihoods); returns the matrix for the next epoch."""
        lg = np.log(np.maximum(mu_prev, _TINY))[:, None] + np.log(np.maximum(Pi, _TINY)) + log_lik[None, :]
        if np.isfinite(lg).any():
            lg = np.where(np.isfinite(lg), lg, -np.inf)
            xi = np.exp(lg - lg.max())
            forget = 1.0 if self.t_last is None else math.exp(-max(t - self.t_last, 0.0) / self.tau_s)
            self.N = forget * self.N + xi / xi.sum()
            self.t_last = t
        return self.Pi


@dataclass(frozen=True)
class ImmStep:
    """One IMM cycle's results.

    x, P: updated members; mu (M,); c (M,) predicted probabilities; log_lik (M,);
    x_comb (n,), P_comb (n, n): combined output; v (M, m) the residual statistic of each model's
    mixed prior with the normal rows (``residuals``: v_i or w_i), by which the suspected rows were
    chosen and weighed; h_scale, r_scale (M, m): the rows' eq (14)-(16) factors; result: the
    bank's innovation statistics.
    """

    x: np.ndarray
    P: np.ndarray
    mu: np.ndarray
    c: np.ndarray
    log_lik: np.ndarray
    x_comb: np.ndarray
    P_comb: np.ndarray
    v: np.ndarray
    h_scale: np.ndarray
    r_scale: np.ndarray
    result: kalman.UpdateResult


def standardised_residuals(
    x: np.ndarray, P: np.ndarray, z: np.ndarray, H: np.ndarray, r_var: np.ndarray, mask: np.ndarray | None
) -> np.ndarray:
    """(B, m) v_i = r_i / sqrt(S_ii) for each member (zero on masked rows)."""
    r = z[None, :] - x @ H.T
    s = np.einsum("ij,bjk,ik->bi", H, P, H) + r_var[None, :]
    v = r / np.sqrt(s)
    return v if mask is None else np.where(mask, v, 0.0)


def conditional_residuals(
    x: np.ndarray, P: np.ndarray, z: np.ndarray, H: np.ndarray, r_var: np.ndarray, mask: np.ndarray | None
) -> np.ndarray:
    """(B, m) w_i = (S^-1 r)_i / sqrt((S^-1)_ii) for each member, S = H P H' + R over the kept rows:
    row i's innovation given every other kept row, standardised (module docstring; zero on masked
    rows, which take no part in S)."""
    r = z[None, :] - x @ H.T
    S = H @ P @ H.T + np.diag(r_var)  # (B, m, m)
    if mask is not None:  # masked rows: a unit block of their own, no coupling to the kept rows
        keep = np.broadcast_to(np.asarray(mask, dtype=bool), r.shape)
        eye = np.eye(r.shape[1], dtype=bool)[None]
        S = np.where(keep[:, :, None] & keep[:, None, :], S, eye.astype(float))
        r = np.where(keep, r, 0.0)
    Si = np.linalg.inv(S)
    w = np.einsum("bij,bj->bi", Si, r) / np.sqrt(np.einsum("bii->bi", Si))
    return w if mask is None else np.where(keep, w, 0.0)


def step(
    x: np.ndarray,
    P: np.ndarray,
    mu: np.ndarray,
    Pi: np.ndarray,
    z: np.ndarray,
    H: np.ndarray,
    r_var: np.ndarray,
    models: tuple[str, ...],
    weighting: DownWeighting | None = None,
    likelihood: str = "paper",
    mask: np.ndarray | None = None,
    selection: bool = False,
    residuals: str = "marginal",
) -> ImmStep:
    """One IMM cycle (module docstring) on members ``x`` (M, n), ``P`` (M, n, n) with the normal
    rows z (m,), H (m, n), R = diag(r_var); ``mask`` (m,) bool drops rows for every model;
    ``weighting`` the eq (14)-(16) parameters (default: the paper's); ``selection`` divides each
    model's likelihood by the number of row sets it chose from; ``residuals`` the statistic the
    fault models choose and weigh their rows by: ``"marginal"`` v_i (the paper's) or
    ``"conditional"`` w_i (module docstring)."""
    weighting = weighting or DownWeighting()
    if likelihood not in LIKELIHOODS:
        raise ValueError(f"likelihood {likelihood!r}: choose from {LIKELIHOODS}")
    if residuals not in RESIDUALS:
        raise ValueError(f"residuals {residuals!r}: choose from {RESIDUALS}")
    M, m = x.shape[0], z.shape[0]
    x0, P0, c = mix(x, P, mu, Pi)
    keep = None if mask is None else np.broadcast_to(np.asarray(mask, dtype=bool), (M, m))
    statistic = conditional_residuals if residuals == "conditional" else standardised_residuals
    v = statistic(x0, P0, z, H, r_var, keep)
    sus = suspects(models, v, weighting.c)
    if keep is not None:
        sus &= keep
    h_scale, r_scale = weighting.factors(v, sus)
    Hb = H[None, :, :] * h_scale[:, :, None]
    Rb = (r_var[None, :] * r_scale)[:, :, None] * np.eye(m)
    xu, Pu, res = kalman.update(x0, P0, z, Hb, Rb, keep)
    if likelihood == "paper":
        R_used = Rb if keep is None else Rb * (keep[:, :, None] & keep[:, None, :])
        log_lik = log_likelihood_paper(res, R_used)
    else:
        log_lik = log_likelihood_gaussian(res)
    if selection:
        m_used = m if keep is None else int(keep[0].sum())
        log_lik = log_lik - log_row_sets(sus.sum(axis=1), m_used)
    new_mu = probabilities(log_lik, c) if M > 1 else np.ones(1)
    xc, Pc = combine(xu, Pu, new_mu)
    return ImmStep(xu, Pu, new_mu, c, log_lik, xc, Pc, v, h_scale, r_scale, res)


__all__ = [
    "ImmStep",
    "LIKELIHOODS",
    "RESIDUALS",
    "TransitionLearner",
    "combine",
    "conditional_residuals",
    "log_likelihood_gaussian",
    "log_likelihood_paper",
    "log_row_sets",
    "mix",
    "probabilities",
    "standardised_residuals",
    "step",
]
