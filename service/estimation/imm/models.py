"""Fault models of the outlier IMM (He, Nie, Wu 2011, section 4, eq (14)-(16)): plug-ins.

Each model of the set names the rows it *suspects* from the standardised predicted residuals
``v_i = r_i / sqrt(S_ii)`` (r = z - H x, S = H P H' + R, with that model's mixed prior and the
normal rows), and the suspected rows are down-weighted as in eq (14)-(16):

    H_j(i, :) = H(i, :) * p %                                               (14)
    R_j(i, i) = R(i, i) * C0,   C0 = C                  if |v_i| > c        (15)
                                C0 = 1 / exp(1 - (v_i / c)^2)   otherwise   (16)

(c = 1.5, C = 100 in the paper; p is not given there: default 100 %, i.e. H unchanged -- a row
scaled below 100 % models a gain loss, which for an additive outlier biases the model; see
docs/seed003.md). Rows that are not suspected keep H and R. The paper's experiment has four
models: normal, one outlier, two outliers, several outliers; our reading of which rows each
suspects:

    normal        none
    largest       the row with the largest |v_i|
    two_largest   the two rows with the largest |v_i|
    above_c       every row with |v_i| > c

Adding a model: a function ``(v (B, m), c) -> suspected (B, m) bool`` and one ``SUSPECTS`` line.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import numpy as np


def _none(v: np.ndarray, c: float) -> np.ndarray:
    return np.zeros(v.shape, dtype=bool)


def _largest_k(k: int) -> Callable[[np.ndarray, float], np.ndarray]:
    def suspects(v: np.ndarray, c: float) -> np.ndarray:
        out = np.zeros(v.shape, dtype=bool)
        m = v.shape[-1]
        if m == 0:
            return out
        kk = min(k, m)
        idx = np.argsort(-np.abs(v), axis=-1, kind="stable")[..., :kk]
        np.put_along_axis(out, idx, True, axis=-1)
        return out

    return suspects


def _above_c(v: np.ndarray, c: float) -> np.ndarray:
    return np.abs(v) > c


#: model name -> which rows it suspects, from v (B, m) and c
SUSPECTS: dict[str, Callable[[np.ndarray, float], np.ndarray]] = {
    "normal": _none,
    "largest": _largest_k(1),
    "two_largest": _largest_k(2),
    "above_c": _above_c,
}
MODEL_NAMES = tuple(SUSPECTS)


@dataclass(frozen=True)
class DownWeighting:
    """Parameters of eq (14)-(16): h_percent = p, c, big = C."""

    h_percent: float = 100.0
    c: float = 1.5
    big: float = 100.0

    def factors(self, v: np.ndarray, suspected: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """(h_scale, r_scale), shapes of ``v``: the H-row and R_ii multipliers of eq (14)-(16)."""
        a = np.abs(v)  # (clipped inside exp: no overflow where big is taken anyway)
        c0 = np.where(a > self.c, self.big, np.exp(np.square(np.minimum(a, self.c) / self.c) - 1.0))
        r_scale = np.where(suspected, c0, 1.0)
        h_scale = np.where(suspected, self.h_percent / 100.0, 1.0)
        return h_scale, r_scale


def suspects(names: tuple[str, ...], v: np.ndarray, c: float) -> np.ndarray:
    """(B, m) bool: suspected rows of each model (row b of ``v`` belongs to model ``names[b]``)."""
    out = np.zeros(v.shape, dtype=bool)
    for b, name in enumerate(names):
        out[b] = SUSPECTS[name](v[b : b + 1], c)[0]
    return out


__all__ = ["DownWeighting", "MODEL_NAMES", "SUSPECTS", "suspects"]
