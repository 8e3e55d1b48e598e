"""Batched Kalman core: banks of B filters of dimension n as arrays.

A bank is ``x`` (B, n) and ``P`` (B, n, n). :func:`predict` and :func:`update` are single numpy
calls over the bank (matmul broadcasting), never Python loops over filter objects. Federated
local filters, IMM models and MHSS sub/sub-sub filters are all banks of this core.

Row exclusion (MHSS, isolation): ``mask`` (B, m) selects the rows each member uses. An excluded
row has its H row zeroed, its innovation zeroed and R set to identity on that row/column, so the
gain column is exactly zero and the row contributes nothing (same shapes for every member).

Numerics: S = H P H' + R is factorised by Cholesky (S = L L'); the gain is solved from the factor
(never ``inv(S)``); covariance by the Joseph form P = (I - K H) P (I - K H)' + K R K', then
symmetrised. Every update returns the whitened innovations w = L^-1 r, the standardised
innovations r_j / sqrt(S_jj) and NIS = r' S^-1 r = |w|^2, which fault tests consume.

A bank of one member (the loosely coupled filter, every vehicle's fix update) takes the same
steps on (n, n) arrays with LAPACK's potrf/trtrs (:func:`_gain_one`): the batched row-by-row
substitution costs ~5 numpy calls per row, 200 us for 6 rows against 60 us; the results equal the
batched path's to rounding (tests/test_kalman.py).
"""

from __future__ import annotations

import functools
import math
from dataclasses import dataclass

import numpy as np
from scipy.linalg import blas as _blas  # BLAS trsm: the one-member path's triangular solves
from scipy.linalg import lapack as _lapack  # LAPACK's potrf: the one-member path, ~1-3 us a call


@dataclass(frozen=True)
class UpdateResult:
    """Per-member innovation statistics of one update.

    innovation (B, m): r = z - H x (zero on excluded rows); S (B, m, m); whitened (B, m): L^-1 r;
    standardised (B, m): r_j / sqrt(S_jj); nis (B,): r' S^-1 r; dof (B,): rows used; K (B, n, m).
    """

    innovation: np.ndarray
    S: np.ndarray
    whitened: np.ndarray
    standardised: np.ndarray
    nis: np.ndarray
    dof: np.ndarray
    K: np.ndarray


class NotPositiveDefinite(np.linalg.LinAlgError):
    """A covariance (or innovation covariance) lost positive definiteness."""


@functools.lru_cache(maxsize=64)
def _eye(n: int) -> np.ndarray:
    """The (n, n) identity, made once per size (read-only: the hot path asks for it per update)."""
    eye = np.eye(n)
    eye.setflags(write=False)
    return eye


def symmetrise(P: np.ndarray) -> np.ndarray:
    # the array's own swapaxes: np.swapaxes's Python wrapper costs as much as the sum at 15 x 15
    P = np.asanyarray(P)
    return 0.5 * (P + P.swapaxes(-1, -2))


def predict(x: np.ndarray, P: np.ndarray, Phi: np.ndarray, Qd: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Time update of a bank: x <- Phi x, P <- Phi P Phi' + Qd.

    Phi and Qd may be shared (n, n) or per member (B, n, n).
    """
    x = np.einsum("...ij,...j->...i", Phi, x) if Phi.ndim == 3 else x @ Phi.T
    P = Phi @ P @ Phi.swapaxes(-1, -2) + Qd
    return x, symmetrise(P)


def _solve_lower(L: np.ndarray, Y: np.ndarray, inv_diag: np.ndarray) -> np.ndarray:
    """X = L^-1 Y for lower-triangular L (B, m, m), Y (B, m, k): forward substitution vectorised
    over the bank (numpy has no batched triangular solve; this beats a batched LU by ~3x and,
    unlike LU with pivoting, is exact substitution)."""
    m = L.shape[1]
    X = np.empty_like(Y)
    X[:, 0] = Y[:, 0] * inv_diag[:, 0, None]
    for i in range(1, m):
        X[:, i] = (Y[:, i] - (L[:, i, None, :i] @ X[:, :i])[:, 0]) * inv_diag[:, i, None]
    return X


def _solve_upper_from_lower(L: np.ndarray, Y: np.ndarray, inv_diag: np.ndarray) -> np.ndarray:
    """X = L'^-1 Y (back substitution with the transpose of lower-triangular L)."""
    m = L.shape[1]
    X = np.empty_like(Y)
    X[:, m - 1] = Y[:, m - 1] * inv_diag[:, m - 1, None]
    for i in range(m - 2, -1, -1):
        X[:, i] = (Y[:, i] - (L[:, None, i + 1 :, i] @ X[:, i + 1 :])[:, 0]) * inv_diag[:, i, None]
    return X


@dataclass(frozen=True)
class Gain:
    """The gain step of a masked batched update (:func:`gain`), before any covariance update.

    x (B, n) updated states; K (B, n, m) gains (zero columns on masked rows); IKH (B, n, n) = I - K H;
    R (B, m, m) noise as used (identity on masked rows); result: the innovation statistics.
    """

    x: np.ndarray
    K: np.ndarray
    IKH: np.ndarray
    R: np.ndarray
    result: UpdateResult


def gain(
    x: np.ndarray,
    P: np.ndarray,
    z: np.ndarray,
    H: np.ndarray,
    R: np.ndarray,
    mask: np.ndarray | None = None,
) -> Gain:
    """Innovations, Cholesky-solved gains and updated states of a bank (the one masked batched
    update every bank uses: :func:`update` adds the Joseph covariance, the MHSS bank its cross
    blocks). Shapes as :func:`update`; ``R`` may also be (m,), a diagonal."""
    B, n = x.shape
    if B == 1:
        x_new, K, IKH, R0, res = _gain_one(x, P, z, H, R, mask)
        return Gain(x_new, K[None], IKH[None], R0[None], res)
    m = H.shape[-2]
    shared_H = H.ndim == 2
    R = np.asarray(R, dtype=float)
    if R.ndim == 1:
        R = R[:, None] * _eye(m)
    R = np.broadcast_to(R, (B, m, m))
    z = np.broadcast_to(z, (B, m))
    if mask is not None:
        keep_b = np.asarray(mask, dtype=bool)
        keep = keep_b.astype(float)
        PHt = (P @ np.swapaxes(H, -1, -2)) * keep[:, None, :]  # P H_b' (masked rows' columns zero)
        HPHt = H @ PHt * keep[:, :, None]
        R = R * (keep[:, :, None] * keep[:, None, :]) + _eye(m) * (1.0 - keep)[:, :, None]
        r = (z - np.einsum("...ij,...j->...i", H, x) if not shared_H else z - x @ H.T) * keep
        dof = keep_b.sum(axis=1)
    else:
        PHt = P @ np.swapaxes(H, -1, -2)  # (B, n, m)
        HPHt = H @ PHt
        r = z - (np.einsum("bij,bj->bi", H, x) if not shared_H else x @ H.T)
        dof = np.full(B, m)
    S = symmetrise(HPHt + R)
    try:
        L = np.linalg.cholesky(S)
    except np.linalg.LinAlgError as exc:
        raise NotPositiveDefinite("innovation covariance S is not positive definite") from exc
    inv_d = 1.0 / np.diagonal(L, axis1=1, axis2=2)
    # [L^-1 H P | L^-1 r] by one forward substitution, then K' = L'^-1 (L^-1 H P)
    W = _solve_lower(L, np.concatenate([np.swapaxes(PHt, 1, 2), r[:, :, None]], axis=2), inv_d)
    Kt = _solve_upper_from_lower(L, W[:, :, :n], inv_d)
    w = W[:, :, n]  # whitened innovation L^-1 r
    K = np.swapaxes(Kt, 1, 2)  # (B, n, m)
    x_new = x + np.einsum("bij,bj->bi", K, r)
    IKH = _eye(n) - K @ H
    std = r / np.sqrt(np.diagonal(S, axis1=1, axis2=2))
    res = UpdateResult(r, S, w, std, np.einsum("bi,bi->b", w, w), dof, K)
    return Gain(x_new, K, IKH, R, res)


def _gain_one(x, P, z, H, R, mask) -> tuple:
    """:func:`gain` of a bank of one (a loosely coupled filter, transfer alignment): the same
    steps on (n, n) arrays with LAPACK's Cholesky and triangular solves, without the bank's
    broadcasting and its row-by-row substitution (a quarter of the batched path's cost for one
    member; the same results to rounding). Returns :class:`Gain`'s fields (x, K, IKH, R, result),
    :func:`update` reads them without the wrapper."""
    n = x.shape[1]
    H0 = H if H.ndim == 2 else H[0]
    m = H0.shape[0]
    R0 = np.asarray(R, dtype=float)
    if R0.ndim == 1:
        R0 = np.diag(R0)
    elif R0.ndim == 3:
        R0 = R0[0]
    z0 = np.asarray(z, dtype=float)
    z0 = z0 if z0.ndim == 1 else z0[0]
    x0 = x[0]
    PHt = P[0] @ H0.T  # (n, m)
    r = z0 - H0 @ x0
    if mask is not None:
        keep_b = np.asarray(mask, dtype=bool).reshape(-1, m)[0]
        keep = keep_b.astype(float)
        PHt = PHt * keep[None, :]
        HPHt = (H0 @ PHt) * keep[:, None]
        R0 = R0 * (keep[:, None] * keep[None, :]) + _eye(m) * (1.0 - keep)[:, None]
        r = r * keep
        dof = np.array([keep_b.sum()])
    else:
        HPHt = H0 @ PHt
        dof = np.array([m])
    S = HPHt + R0
    S = 0.5 * (S + S.T)
    L, info = _lapack.dpotrf(S, lower=1, clean=1)
    if info != 0:
        raise NotPositiveDefinite("innovation covariance S is not positive definite")
    # [L^-1 H P | L^-1 r] by one forward solve, then K' = L'^-1 (L^-1 H P). BLAS's dtrsm, not
    # LAPACK's dtrtrs: OpenBLAS runs every dtrtrs on its thread pool whatever its size (a 6 x 16
    # solve kept a second core spinning for ~14 us a call, which doubled a fleet service's CPU),
    # and dtrtrs's only other work, the test for a zero on L's diagonal, cannot fail after a
    # successful dpotrf (whose pivots are all > 0). The right-hand side is built in Fortran order
    # and solved in place (the wrapper would copy a C-ordered one; np.column_stack's Python
    # wrapper cost as much as the solve): the same values, the same solve.
    Y = np.empty((m, n + 1), order="F")
    Y[:, :n] = PHt.T
    Y[:, n] = r
    W = _blas.dtrsm(1.0, L, Y, lower=1, overwrite_b=1)
    Kt = _blas.dtrsm(1.0, L, W[:, :n], lower=1, trans_a=1)
    w = W[:, n]
    K = Kt.T  # (n, m)
    x_new = x0 + K @ r
    IKH = _eye(n) - K @ H0
    std = r / np.sqrt(S.diagonal())
    res = UpdateResult(r[None], S[None], w[None], std[None], np.array([w @ w]), dof, K[None])
    return x_new[None], K, IKH, R0, res


def update(
    x: np.ndarray,
    P: np.ndarray,
    z: np.ndarray,
    H: np.ndarray,
    R: np.ndarray,
    mask: np.ndarray | None = None,
) -> tuple[np.ndarray, np.ndarray, UpdateResult]:
    """Measurement update of a bank of B filters (Joseph form, Cholesky solves).

    Parameters
    ----------
    x : (B, n) states; P : (B, n, n) covariances.
    z : (B, m) or (m,) measurements; H : (B, m, n) or (m, n); R : (B, m, m), (m, m) or (m,) diagonal.
    mask : (B, m) bool, optional. False excludes that row for that member.

    Returns
    -------
    x, P : updated bank (new arrays).
    UpdateResult : innovation statistics per member.
    """
    if x.shape[0] == 1:  # one member: (n, n) products
        x_new, K, IKH, R0, result = _gain_one(x, P, z, H, R, mask)
        P_new = IKH @ P[0] @ IKH.T + K @ R0 @ K.T
        return x_new, (0.5 * (P_new + P_new.T))[None], result
    g = gain(x, P, z, H, R, mask)
    Kt = np.swapaxes(g.K, 1, 2)
    P_new = g.IKH @ P @ np.swapaxes(g.IKH, 1, 2) + g.K @ g.R @ Kt
    return g.x, symmetrise(P_new), g.result


def is_positive_definite(P: np.ndarray) -> np.ndarray:
    """(B,) bool: which members' covariances are finite, symmetric (to 1e-9 relative) and positive
    definite (LAPACK's Cholesky succeeds, or the smallest eigenvalue of the symmetric part > 0)."""
    if P.ndim == 2:
        P = P[None]
    # the usual case first: every member finite and exactly symmetric (banks symmetrise their
    # covariances), and LAPACK's Cholesky succeeds on all of them (a fifth of the eigenvalues' cost)
    if P.shape[0] == 1:
        # one member (a loosely coupled filter's every update): finite, as its sum is (a NaN or an
        # infinity makes the sum one; an overflowing sum of finite entries only sends P to the
        # tests below), and symmetric, as its bytes equal its transpose's (equal bytes are equal
        # values; -0.0 against 0.0 goes to the tests below): one C call each instead of numpy's
        # isfinite/compare and two Python-level all()s (~25 us of a fix epoch's 200)
        P0 = P[0]
        quick = math.isfinite(np.add.reduce(P0, axis=None)) and P0.tobytes() == P0.T.tobytes()
    else:
        quick = False
    if quick:
        if _lapack.dpotrf(P0, lower=1, overwrite_a=0)[1] == 0:
            return np.array([True])
    elif np.isfinite(P).all() and (P == np.swapaxes(P, 1, 2)).all():
        if P.shape[0] == 1:  # one member: LAPACK's potrf directly (a tenth of numpy's wrapper)
            if _lapack.dpotrf(P[0], lower=1, overwrite_a=0)[1] == 0:
                return np.ones(1, dtype=bool)
        else:
            try:
                np.linalg.cholesky(P)
                return np.ones(P.shape[0], dtype=bool)
            except np.linalg.LinAlgError:
                pass  # some member is not: the tests below say which
    finite = np.all(np.isfinite(P), axis=(1, 2))
    Ps = np.where(finite[:, None, None], P, 0.0)
    sym = np.all(np.abs(Ps - np.swapaxes(Ps, 1, 2)) <= 1e-9 * (1.0 + np.abs(Ps)), axis=(1, 2))
    return finite & sym & (np.linalg.eigvalsh(symmetrise(Ps)).min(axis=-1) > 0.0)


def cholesky(A: np.ndarray, what: str) -> np.ndarray:
    """Lower Cholesky factor(s) of A, or ``NotPositiveDefinite`` naming ``what``."""
    try:
        return np.linalg.cholesky(A)
    except np.linalg.LinAlgError as exc:
        raise NotPositiveDefinite(f"{what} is not positive definite") from exc


def information_fusion(x: np.ndarray, P: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """P_g = (sum_i P_i^-1)^-1, x_g = P_g sum_i P_i^-1 x_i for x (B, c), P (B, c, c) (the federated
    master fusion; also used by sharing strategies that need P_g).

    Computed without inverting any P_i, by sequential pairwise fusion in covariance form
    (information adds, so the order does not matter):
        (P_a^-1 + P_b^-1)^-1 = P_a (P_a + P_b)^-1 P_b,
        x = x_a + P_a (P_a + P_b)^-1 (x_b - x_a),
    with one Cholesky factorisation of P_a + P_b per pair, on D^-1 P D^-1 with
    D = diag(sqrt(mean_i P_i,jj)) (exact: fusion commutes with a common change of variables;
    raw INS covariances have condition numbers up to ~1e17). B - 1 small solves: this runs at
    every solution output, so it is kept cheap (~30 us per pair).
    """
    B, c = x.shape
    diag = np.diagonal(P, axis1=1, axis2=2)
    if not (np.isfinite(P).all() and np.isfinite(x).all() and (diag > 0.0).all()):
        raise NotPositiveDefinite("local covariances to fuse are not finite / positive")
    d = np.sqrt(np.mean(diag, axis=0))  # (c,) scaling
    dd = np.outer(d, d)
    Ps = P / dd
    xs = x / d
    Pg, xg = Ps[0], xs[0]
    for i in range(1, B):
        L = cholesky(Pg + Ps[i], "sum of local covariances")  # P_a + P_b = L L'
        rhs = np.concatenate([Ps[i], (xs[i] - xg)[:, None]], axis=1)
        M = np.linalg.solve(L.T, np.linalg.solve(L, rhs))  # (P_a + P_b)^-1 [P_b, x_b - x_a]
        xg = xg + Pg @ M[:, c]  # x_a + P_a (P_a + P_b)^-1 (x_b - x_a)
        Pg = symmetrise(Pg @ M[:, :c])  # P_a (P_a + P_b)^-1 P_b
    return xg * d, Pg * dd
