"""Chi-square innovation gate with row rejection (the simple standard against outliers).

Given one filter's prior (x, P) and rows z = H x + v, v ~ N(0, diag(r_var)): while the
normalised innovation squared NIS = r' S^-1 r of the kept rows exceeds the chi-square quantile
chi2_{1 - p_fa}(dof), reject the kept row with the largest |standardised innovation|
r_i / sqrt(S_ii) and test again (at least ``min_rows`` rows are kept). The comparator of the
outlier IMM (docs/seed003.md): one filter, no model set, rejection instead of down-weighting.
"""

from __future__ import annotations

import numpy as np
from scipy.stats import chi2


def gate_rows(
    x: np.ndarray,
    P: np.ndarray,
    z: np.ndarray,
    H: np.ndarray,
    r_var: np.ndarray,
    p_fa: float,
    min_rows: int = 1,
) -> np.ndarray:
    """(m,) bool: rows kept by the gate (module docstring)."""
    m = z.shape[0]
    keep = np.ones(m, dtype=bool)
    if m == 0:
        return keep
    r = z - H @ x
    S = H @ P @ H.T + np.diag(r_var)
    std = r / np.sqrt(np.diagonal(S))
    while keep.sum() > min_rows:
        idx = np.flatnonzero(keep)
        Sk = S[np.ix_(idx, idx)]
        rk = r[idx]
        nis = float(rk @ np.linalg.solve(Sk, rk))
        if nis <= chi2.ppf(1.0 - p_fa, idx.size):
            break
        keep[idx[int(np.argmax(np.abs(std[idx])))]] = False
    return keep


__all__ = ["gate_rows"]
