"""Seed 003: what any outlier treatment can reach, per outlier window (a calculation, no run).

One pseudorange row as a location measurement with unit noise, contaminated as in
seed003_outliers: 15 % of the epochs carry one outlier on one of the ~10 published pseudoranges
(1.5 % of the pseudorange rows), of k sigma with random sign, k from the window's sizes (0-200 s:
3, 5, 8; 200-400 s: 3; 500-700 s: 5). Printed per window, as the standard deviation of the
estimate relative to clean data (1 = no loss):

    KF        every row used in full (the least-squares / Kalman weight)
    bound     1 / sqrt(Fisher information) of the contaminated density: no estimator, however it
              treats the rows (gate, IMM, robust weights), does better asymptotically, even one
              that knows the outliers' rate and sizes
    hard T    rows with |v| > T down-weighted by C = 100 (what a threshold test or the IMM's
              fault models do; the IMM's effective threshold is about 4 with the seed-003 priors)

The fraction of the KF's excess variance that the bound leaves, (bound^2 - 1) / (KF^2 - 1), is
what at least remains of the outlier-induced error in that window (docs/seed003.md).

Usage: .venv/bin/python benchmarks/seed003_bound.py
"""

from __future__ import annotations

import numpy as np

X = np.linspace(-25.0, 25.0, 500001)
DX = X[1] - X[0]
WINDOWS = {
    "0-200 s (3/5/8 sigma)": (3.0, 5.0, 8.0),
    "200-400 s (3 sigma)": (3.0,),
    "500-700 s (5 sigma)": (5.0,),
}
EPS = 0.015  # outlier probability per pseudorange row


def phi(u: np.ndarray) -> np.ndarray:
    return np.exp(-0.5 * u * u) / np.sqrt(2.0 * np.pi)


def density(eps: float, sizes: tuple[float, ...]) -> np.ndarray:
    d = (1.0 - eps) * phi(X)
    for k in sizes:
        d += eps / len(sizes) * 0.5 * (phi(X - k) + phi(X + k))
    return d


def m_estimate_std(psi: np.ndarray, d: np.ndarray) -> float:
    """Asymptotic std of the M-estimator with influence psi: sqrt(E psi^2) / E psi'."""
    return float(np.sqrt(np.sum(psi * psi * d) * DX) / (np.sum(np.gradient(psi, DX) * d) * DX))


def fisher_bound(d: np.ndarray) -> float:
    dd = np.gradient(d, DX)
    return float(1.0 / np.sqrt(np.sum(dd * dd / np.maximum(d, 1e-300)) * DX))


def main() -> int:
    print(f"outlier probability per pseudorange row {EPS}; std relative to clean data")
    print(
        f"{'window':24s} {'KF':>7s} {'bound':>7s} {'left':>6s}"
        + "".join(f" {'hard ' + str(t):>8s}" for t in (3, 4, 5))
    )
    for name, sizes in WINDOWS.items():
        d = density(EPS, sizes)
        kf = m_estimate_std(X, d)
        b = fisher_bound(d)
        hard = [m_estimate_std(np.where(np.abs(X) > t, X / 100.0, X), d) for t in (3.0, 4.0, 5.0)]
        left = (b * b - 1.0) / (kf * kf - 1.0)
        print(f"{name:24s} {kf:7.4f} {b:7.4f} {left:6.2f}" + "".join(f" {h:8.4f}" for h in hard))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
