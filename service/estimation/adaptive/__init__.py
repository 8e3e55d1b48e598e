"""Adaptive pieces usable by any Kalman bank (arrays (B, n), (B, n, n)).

- :mod:`.sage_husa`: Sage-Husa measurement-noise (R) adaptation with a forgetting factor, a
  positive-definite fallback and the restart rule of Zhu, Ma, Wang, Chen 2022 (eq 7).
- :mod:`.fading`: chi-square triggered per-state fading factors on the predicted covariance
  (Zhu, Ma, Wang, Chen 2022, eq 8-17, after Geng & Wang 2008).
"""

from fednav.service.estimation.adaptive.fading import (
    FadingResult,
    chi2_threshold,
    faded_covariance,
    fading_factors,
)
from fednav.service.estimation.adaptive.sage_husa import SageHusaR, sage_husa_weight

__all__ = [
    "FadingResult",
    "SageHusaR",
    "chi2_threshold",
    "faded_covariance",
    "fading_factors",
    "sage_husa_weight",
]
