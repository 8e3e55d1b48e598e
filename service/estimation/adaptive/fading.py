"""Chi-square triggered per-state fading factors on the predicted covariance (Zhu, Ma, Wang,
Chen 2022, eq 8-17, after Geng & Wang 2008, "Adaptive estimation of multiple fading factors").

With J = F P F' (eq 12), B = H Q H' + R (eq 11) and the innovation r = z - H x_k|k-1, the test
statistic with S = I is gamma = r' (H J H' + B)^-1 r ~ chi2(m) (eq 9). Only when gamma exceeds
the chi2(m) threshold, per measurement row i:

    s_i^2 = r_i^2 / (lambda_i^2 j_ii eps_i) - b_ii / j_ii     (eq 15-16),  s_i = max(1, sqrt(.))

where the bracket is positive, else s_i = 1; eps_i is the chi2(1) threshold of the row.

Reading taken (the paper mixes measurement and state indices: a_ii in eq 13 is a measurement
diagonal, j_ii in eq 14 a state diagonal, lambda_i is not defined): for a row that measures one
state x_j with coefficient lambda (H row = lambda e_j'), (H J H')_ii = lambda^2 j_jj, so we use
lambda_i^2 j_ii := (H J H')_ii, the row's predicted variance; the factor then makes that row's
statistic r_i^2 / (s_i^2 (H J H')_ii + b_ii) equal to eps_i (the smallest inflation that passes
the row test). Row factors go to the states the row observes (nonzero H column); a state seen by
several rows takes the largest; states no row observes keep 1 (eq 17 "unobservable states keep
1"). Then P_k|k-1 = S J S' + Q with S = diag(s) (eq 8).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.stats import chi2


def chi2_threshold(dof: int, p_fa: float) -> float:
    """Upper chi2(dof) quantile with false-alarm probability ``p_fa``."""
    return float(chi2.isf(p_fa, dof))


@dataclass(frozen=True)
class FadingResult:
    """s (B, n) per-state factors (1 where not engaged); gamma (B,) the statistic with S = I;
    triggered (B,) gamma above the threshold; row_factors (B, m)."""

    s: np.ndarray
    gamma: np.ndarray
    triggered: np.ndarray
    row_factors: np.ndarray


def fading_factors(
    r: np.ndarray,
    H: np.ndarray,
    J: np.ndarray,
    Bk: np.ndarray,
    threshold: float,
    row_threshold: float,
    observable: np.ndarray | None = None,
    HJHt: np.ndarray | None = None,
) -> FadingResult:
    """Per-state fading factors of a bank (eq 9-17).

    r (B, m) innovations; H (B, m, n) or (m, n); J (B, n, n) = F P F'; Bk (B, m, m) = H Q H' + R;
    threshold: chi2(m) quantile of the whole test; row_threshold: eps_i (chi2(1) quantile);
    observable (n,) or (B, n) bool: states allowed to fade (default: those with a nonzero H column).
    HJHt: H J H' when the caller has it already.
    """
    if HJHt is None:
        HJ = H @ J
        HJHt = HJ @ np.swapaxes(H, -1, -2) if H.ndim == 3 else HJ @ H.T
    S = HJHt + Bk
    L = np.linalg.cholesky(0.5 * (S + np.swapaxes(S, -1, -2)))
    w = np.linalg.solve(L, r[:, :, None])[:, :, 0]
    gamma = np.einsum("bi,bi->b", w, w)
    triggered = gamma > threshold
    if not triggered.any():  # the usual epoch: every factor is 1 (the same result, without the work)
        return FadingResult(np.ones((r.shape[0], J.shape[-1])), gamma, triggered, np.ones_like(r))
    a = np.diagonal(HJHt, axis1=1, axis2=2)
    b = np.diagonal(Bk, axis1=1, axis2=2)
    with np.errstate(divide="ignore", invalid="ignore"):
        bracket = (r**2 / row_threshold - b) / a
    bracket = np.where(np.isfinite(bracket) & (a > 0.0), bracket, 0.0)
    rows = np.where(bracket > 0.0, np.sqrt(np.maximum(bracket, 0.0)), 1.0)
    rows = np.maximum(rows, 1.0)
    rows = np.where(triggered[:, None], rows, 1.0)
    Hb = np.broadcast_to(H, (r.shape[0],) + H.shape[-2:])
    seen = np.abs(Hb) > 0.0  # (B, m, n): row i observes state j
    s = np.max(np.where(seen, rows[:, :, None], 1.0), axis=1)
    if observable is None:
        observable = np.any(seen, axis=1)
    s = np.where(np.broadcast_to(observable, s.shape), s, 1.0)
    return FadingResult(s, gamma, triggered, rows)


def faded_covariance(J: np.ndarray, s: np.ndarray, Qd: np.ndarray, form: str = "scaled") -> np.ndarray:
    """Predicted covariance with per-state fading factors s (B, n) on J (B, n, n).

    ``form="scaled"``: P = S J S' + Q with S = diag(s) (eq 8, literal). With factors that differ
    between correlated states, S J S' - J is indefinite: S J S' is *smaller* than J along some
    directions (e.g. J = [[1, 1], [1, 1]], s = (2, 1): v = (1, -3) gives v'(SJS' - J)v = -3), so
    the literal form can make the filter overconfident about a combination of states (here the
    lever arm against the flexure angle, the misalignment against the mounting angles).
    ``form="added"``: P = J + T J T' + Q with T = diag(sqrt(s^2 - 1)): the same diagonal as eq 8
    (s_i^2 J_ii), the added term is positive semi-definite (a congruence of J), so P >= J + Q in
    every direction: fading only ever adds uncertainty.
    """
    if form == "scaled":
        P = s[:, :, None] * J * s[:, None, :] + Qd
    elif form == "added":
        t = np.sqrt(np.maximum(s * s - 1.0, 0.0))
        P = J + t[:, :, None] * J * t[:, None, :] + Qd
    else:
        raise ValueError(f"fading form {form!r}: use 'scaled' or 'added'")
    return 0.5 * (P + np.swapaxes(P, -1, -2))


__all__ = ["FadingResult", "chi2_threshold", "faded_covariance", "fading_factors"]
