"""Sage-Husa measurement-noise adaptation for a Kalman bank (Zhu, Ma, Wang, Chen 2022, eq 7).

With forgetting factor ``a`` in [0.95, 0.99] and the innovation r_k = z_k - H x_k|k-1 of each
member, whose predicted covariance is H P_k|k-1 H' + R:

    d_k = (1 - a) / (1 - a^(k+1))                                   (eq 7, k counted from 0)
    R_k = (1 - d_k) R_(k-1) + d_k (r_k r_k' - H P_k|k-1 H')

d_0 = 1, then d_k decreases to (1 - a): a fading-memory mean of r r' - H P H' (E[r r'] = H P H'
+ R, so the estimate is unbiased for a stationary R). Readings taken:

- Positive-definite fallback: r r' - H P H' is indefinite for a single sample, and R_k may lose
  positive definiteness (e.g. right after a restart). A member whose R_k is not symmetric
  positive definite with eigenvalues above ``min_eig`` keeps R_(k-1) (the R before this step;
  counted in ``fallbacks``).
- Restart rule (the paper, section 1.2): once d_k has converged to (1 - a) -- here within a
  relative ``restart_tol`` -- the count k restarts at 0, so recent innovations again dominate.
  ``restart=False`` keeps the plain fading-memory estimator.
- ``diagonal=True``: the per-row form (R diagonal, each R_ii adapted from r_i^2 - (H P H')_ii,
  each row falling back on its own). With a 9-row measurement whose H P H' is far above R in some
  direction while P is large, the full-matrix form stays indefinite (and frozen by the fallback)
  for hundreds of epochs; the per-row form adapts each row as soon as its own variance allows.
  ``floor`` (m,) optionally bounds each R_ii from below (a row whose true noise is near zero
  would otherwise drive R_ii, and the filter's conditioning, to zero).
- Rows excluded by a mask (a member without that measurement) are left unchanged.
"""

from __future__ import annotations

import numpy as np


def sage_husa_weight(k: np.ndarray | int, a: float) -> np.ndarray:
    """d_k = (1 - a) / (1 - a^(k+1)) (eq 7 with k counted from 0: d_0 = 1)."""
    k = np.asarray(k, dtype=float)
    return (1.0 - a) / (1.0 - a ** (k + 1.0))


class SageHusaR:
    """Adaptive R of a bank of B members with m measurement rows.

    Parameters
    ----------
    R0 : (m, m) or (B, m, m) prior R (initial value of the recursion).
    B : members.
    a : forgetting factor in [0.95, 0.99].
    restart : apply the paper's restart rule.
    restart_tol : d_k counts as converged when d_k - (1 - a) < restart_tol (1 - a).
    min_eig : smallest eigenvalue an adapted R may have (fallback below it).
    """

    def __init__(
        self,
        R0: np.ndarray,
        B: int,
        a: float = 0.97,
        *,
        restart: bool = True,
        restart_tol: float = 1e-3,
        min_eig: float = 0.0,
        diagonal: bool = False,
        floor: np.ndarray | None = None,
    ):
        if not 0.0 < a < 1.0:
            raise ValueError("forgetting factor a must be in (0, 1)")
        R0 = np.asarray(R0, dtype=float)
        m = R0.shape[-1]
        self.R = np.array(np.broadcast_to(R0, (B, m, m)))
        self.R_prior = self.R.copy()
        self.a = float(a)
        self.k = np.zeros(B, dtype=int)
        self.restart = restart
        self.restart_tol = float(restart_tol)
        self.min_eig = float(min_eig)
        self.diagonal = bool(diagonal)
        self.floor = None if floor is None else np.asarray(floor, dtype=float)
        self.fallbacks = np.zeros(B, dtype=int)
        self.restarts = np.zeros(B, dtype=int)

    @property
    def d(self) -> np.ndarray:
        """(B,) the weight the next update will use."""
        return sage_husa_weight(self.k, self.a)

    def update(self, r: np.ndarray, HPHt: np.ndarray, mask: np.ndarray | None = None) -> np.ndarray:
        """One step from the innovations r (B, m) and predicted H P H' (B, m, m); returns R_k.

        ``mask`` (B, m) bool: rows a member did not measure keep their R entries.
        """
        d = self.d[:, None, None]
        if self.diagonal:
            return self._update_diagonal(r, HPHt, mask)
        sample = r[:, :, None] * r[:, None, :] - HPHt
        R_new = (1.0 - d) * self.R + d * sample
        if mask is not None:
            keep = np.asarray(mask, dtype=bool)
            both = keep[:, :, None] & keep[:, None, :]
            R_new = np.where(both, R_new, self.R)
        R_new = 0.5 * (R_new + np.swapaxes(R_new, 1, 2))
        finite = np.all(np.isfinite(R_new), axis=(1, 2))
        safe = np.where(finite[:, None, None], R_new, self.R)
        ok = finite & (np.linalg.eigvalsh(safe).min(axis=-1) > self.min_eig)
        self.fallbacks += ~ok
        self.R = np.where(ok[:, None, None], safe, self.R)
        self._advance()
        return self.R

    def _update_diagonal(self, r: np.ndarray, HPHt: np.ndarray, mask: np.ndarray | None) -> np.ndarray:
        """Per-row variant: R_ii = (1 - d) R_ii + d (r_i^2 - (H P H')_ii), R diagonal; a row whose
        new value is not above ``min_eig`` keeps its previous value (counted once per member)."""
        d = self.d[:, None]
        Rd = np.diagonal(self.R, axis1=1, axis2=2)
        new = (1.0 - d) * Rd + d * (r * r - np.diagonal(HPHt, axis1=1, axis2=2))
        ok = np.isfinite(new) & (new > self.min_eig)
        if mask is not None:
            ok &= np.asarray(mask, dtype=bool)
        self.fallbacks += (
            np.any(~ok, axis=1) if mask is None else np.any(~ok & np.asarray(mask, bool), axis=1)
        )
        Rd = np.where(ok, new, Rd)
        if self.floor is not None:
            Rd = np.maximum(Rd, self.floor)
        R = np.zeros_like(self.R)
        m = Rd.shape[1]
        R[:, np.arange(m), np.arange(m)] = Rd  # diag(Rd): the same values as Rd[:, :, None] * I
        self.R = R
        self._advance()
        return self.R

    def _advance(self) -> None:
        d_now = self.d
        self.k += 1
        if self.restart:
            converged = d_now - (1.0 - self.a) < self.restart_tol * (1.0 - self.a)
            self.k[converged] = 0
            self.restarts += converged


__all__ = ["SageHusaR", "sage_husa_weight"]
