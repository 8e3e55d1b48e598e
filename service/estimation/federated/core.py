"""Federated filter core: a bank of local filters, master fusion and reset (sensor independent).

The N local filters and the master are ONE batched bank (``kalman``'s arrays): ``x`` (B, n),
``P`` (B, n, n), ``q_scale`` (B, n), with B = N + 1 (N = 1 without a master share: B = 1, the
centralised filter). The master member keeps ``master_share`` of the information and is fused
like a local, or, with no share, holds no information and only carries the fused solution
through its own time update between fusions (outputs then need no fusion; see
``FederatedCore.fused_covariance``). All members share one linearisation point (the
pipeline's single INS) and the closed loop: the fused correction is fed back once and every
member shifts by it (``bank.feedback``). The first ``n_common`` states (15 INS error states)
are common and fused; states beyond them are private to each member and never fused or
rescaled.

One aiding epoch (seed 000 algorithm 2):

1. ``update(owner, z, H, R, test)``: ONE ``kalman.update`` call on the bank of locals with a
   per-member row mask (locals other than the owner have every row masked out, so their gain
   is exactly zero); the owner's predicted innovation statistics it returns are tested
   (fault_tests); only when the test isolates rows is the call repeated without them (seed 000
   eq (8)-(10): a faulty row gets infinite noise, i.e. is dropped).
2. ``fuse_and_reset()``: master fusion over the common states
           P_g = (sum_i P_i^-1)^-1,  x_g = P_g sum_i P_i^-1 x_i          seed 000 Algorithm 2
   (``information_fusion``: pairwise covariance form, Cholesky solves, after a diagonal scaling
   that makes INS covariances, whose raw condition numbers reach 1e17, well conditioned).
   ``fusion_reset``: shares G_i = diag(g_i) from the sharing strategy, then
       P_i = G_i^-1/2 P_g G_i^-1/2,  Q_i = G_i^-1/2 Q G_i^-1/2 (q_scale = 1/g_i),  x_i = x_g
                                                                  seed 000 eq (14)-(15), (25)-(27)
   and x_g is fed back into the INS, which shifts every x_i to 0.
   ``no_reset``: the locals keep their own P_i, Q_i (set once at ``start`` from the strategy's
   initial division, Carlson's no-reset mode); the fusion is for output and for the closed
   loop: x_g is fed back into the shared INS and every local shifts by it (x_i <- x_i - x_g),
   which re-references the locals without changing any local's own estimate (a master without
   a share is still reset to (x_g, P_g) for outputs).

Doubtful updates (the soft edge of the gate). A test that refuses rows (every test but ``none``)
draws a hard line: an innovation just inside its threshold moved the state all the way and shrank
the covariance as if the rows were certainly good, one just outside changed nothing. Found on the
underwater family after a 60 s USBL outage (docs/hardening.md): the first three fixes of a 50 m
jump had NIS 14.5, 16.2 and 12.7 against the test's 16.3, were taken in full, left the solution
13-16 m off at a claimed 2.7 m, and it was reported ``aided`` beyond 3 sigma for 13 s. Between
the chi-square quantile of the used rows' NIS at ``doubt_prob`` (1e-2: one clean update in a
hundred) and the test's own threshold (its false-alarm probability; the refusal of a
whole-innovation test), the update is the mixture of two hypotheses with the weight p of "the
rows were a fault" rising linearly from 0 to 1:

    x = x+ - p d,   P = (1 - p) P+ + p P- + p (1 - p) d d'        d = x+ - x- (the full correction)

(the first two moments of {take the rows: x+, P+; refuse them: x-, P-}). It is continuous at
both ends: p = 0 is the Kalman update, p = 1 the refusal. p reaches 1 only under a per-row test
(rows that pass one by one while their NIS together reaches the whole-innovation threshold): the
rows are then refused and the decision says so (isolated). The covariance never grows beyond what
a refusal keeps plus a quarter of the correction's outer product, so a jump cannot ratchet
itself in (a first version that kept x+ and added p d d' let each doubted fix widen the gate for
the next: the same jump walked the solution 42 m). The owner's covariance only; counted per
pipeline as ``screened["doubted_update"]``. A test that refuses nothing (``none``) takes every
row by design (the papers' unscreened comparators) and is left exactly as it was. On by default
in the underwater family only (``soft_gate_prob``): over 12 clean seeds it changed the underwater
RMS by -0.2 % (fewer epochs beyond 3 sigma), the GNSS federated and centralised ones by +0.8 to
+1.3 % (docs/hardening.md, "The soft edge of the gate").

Private states (n > n_common) at a reset: each member keeps its conditional p | c
(A = P_pc P_cc^-1) and follows the new common marginal: x_p += A (x_c' - x_c),
P_pc' = A P_cc', P_pp' = P_pp + A (P_cc' - P_cc) A'. Their own (conditional) uncertainty is
neither fused nor rescaled, and P stays positive definite.

Scalar shares with ``fusion_reset`` reproduce the centralised filter exactly (Carlson 1990; see
``sharing``); tests/test_federated.py checks it on a linear model and end to end.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass
from typing import Literal, Protocol

import numpy as np

from fednav.service.estimation import kalman
from fednav.service.estimation.federated.fault_tests import FaultDecision, FaultTest, chi2_threshold
from fednav.service.estimation.federated.sharing import SharingContext, SharingStrategy
from fednav.service.estimation.kalman import information_fusion

ResetMode = Literal["fusion_reset", "no_reset"]
#: the false-alarm level above which a passed update is doubted (module docstring; the underwater
#: family's default ``soft_gate_prob``; the core's own default is None: the papers' hard gates)
DOUBT_PROB = 1e-2


class FilterBank(Protocol):
    """What the core needs of a bank (``InsFilterBank`` and ``LinearBank`` provide it)."""

    x: np.ndarray  # (B, n) error states
    P: np.ndarray  # (B, n, n) covariances
    q_scale: np.ndarray  # (B, n) per-member, per-state process-noise scale: Q_i = S^1/2 Q S^1/2

    def feedback(self, dx: np.ndarray) -> None:
        """Absorb the common correction dx (n_common,) into the reference; x[:, :c] -= dx."""


class LinearBank:
    """A sensor-free bank with the ``FilterBank`` protocol, for linear models and tests.

    The estimate of member i is ``ref + x[i]``: ``ref`` plays the INS (the shared reference),
    ``x`` the error states. Measurements must be given relative to the reference
    (z - H ref, like the INS-minus-sensor form). ``feedback(dx)`` moves dx of the common states
    into ``ref`` and shifts every member by -dx.
    """

    def __init__(self, P0: np.ndarray, bank_size: int):
        P0 = np.asarray(P0, dtype=float)
        self.n = P0.shape[-1]
        self.B = bank_size
        self.P = np.broadcast_to(P0, (bank_size, self.n, self.n)).copy()
        self.x = np.zeros((bank_size, self.n))
        self.q_scale = np.ones((bank_size, self.n))
        self.ref = np.zeros(self.n)

    def predict(self, Phi: np.ndarray, Qd: np.ndarray) -> None:
        """x <- Phi x, ref <- Phi ref, P_i <- Phi P_i Phi' + S_i^1/2 Qd S_i^1/2."""
        s_half = np.sqrt(self.q_scale)
        Qb = s_half[:, :, None] * np.asarray(Qd)[None] * s_half[:, None, :]
        self.ref = Phi @ self.ref
        self.x, self.P = kalman.predict(self.x, self.P, Phi, Qb)

    def feedback(self, dx: np.ndarray) -> None:
        dx = np.asarray(dx, dtype=float)
        c = dx.shape[0]
        self.ref[:c] += dx
        self.x[:, :c] -= dx

    def estimate(self, member: int) -> np.ndarray:
        return self.ref + self.x[member]


@dataclass(frozen=True)
class LocalUpdate:
    """One local measurement update: the owner, its test decision and innovation statistics.

    standardised (m,): r_j / sqrt(S_jj) of the owner's prior; nis: r' S^-1 r;
    flagged_only (c,): common states observed only through flagged rows (seed 000 eq 22 input).
    """

    owner: int
    decision: FaultDecision
    standardised: np.ndarray
    nis: float
    flagged_only: np.ndarray
    #: the weight p of the fault hypothesis in the update (0: the Kalman update; 1: refused;
    #: ``FederatedCore`` module docstring, "Doubtful updates")
    doubt: float = 0.0

    @property
    def rows_used(self) -> int:
        return int(np.count_nonzero(self.decision.used))


class FederatedCore:
    """Local-filter bank + master fusion + reset (see module docstring).

    Bank members: 0 .. n_locals-1 are the local filters; member n_locals (when n_locals > 1 or
    ``master_share`` > 0) is the MASTER: with ``master_share`` > 0 it keeps that information
    share and takes part in the fusion; with ``master_share`` = 0 it holds no information, is not
    fused, and only carries the master's own time update for outputs (it is reset to the fused
    (x_g, P_g) at every fusion and propagated with the full Q in the same batched call). The
    master never owns measurement rows.

    Parameters
    ----------
    bank : FilterBank with B = ``bank_size(n_locals, master_share)`` members
    n_locals : int
    strategy : SharingStrategy
    reset : "fusion_reset" | "no_reset"
    master_share : float in [0, 1)
    floor_share : float
        Seed 000 eq (22) floor for states seen only through flagged rows (vector strategies).
    n_common : int
        Number of common (fused) states; 15 for the INS error model.
    doubt_prob : float or None
        The soft edge of the fault tests (module docstring, "Doubtful updates"); None: the papers'
        hard gates (the default; the pipelines' ``soft_gate_prob``).
    """

    def __init__(
        self,
        bank: FilterBank,
        n_locals: int,
        strategy: SharingStrategy,
        reset: ResetMode = "fusion_reset",
        master_share: float = 0.0,
        floor_share: float = 0.05,
        n_common: int = 15,
        doubt_prob: float | None = None,
    ):
        if n_locals < 1:
            raise ValueError("n_locals must be >= 1")
        if not 0.0 <= master_share < 1.0:
            raise ValueError(f"master_share must be in [0, 1), got {master_share}")
        if reset not in ("fusion_reset", "no_reset"):
            raise ValueError(f"unknown reset mode {reset!r}")
        B = self.bank_size(n_locals, master_share)
        if bank.x.shape[0] != B:
            raise ValueError(
                f"bank has {bank.x.shape[0]} members, need {B} ({n_locals} locals"
                f"{' + master' if B > n_locals else ''})"
            )
        n = bank.x.shape[1]
        if not 0 < n_common <= n:
            raise ValueError(f"n_common must be in (0, {n}], got {n_common}")
        self.bank = bank
        self.n_locals = n_locals
        self.strategy = strategy
        self.reset_mode: ResetMode = reset
        self.master_share = float(master_share)
        self.floor_share = float(floor_share)
        if doubt_prob is not None and not 0.0 < doubt_prob < 0.5:
            raise ValueError(f"doubt_prob must be in (0, 0.5) or None, got {doubt_prob}")
        self.doubt_prob = doubt_prob
        self.c = n_common
        self.B = B
        self.master = n_locals if B > n_locals else None  # index of the master member
        self.n_fused = n_locals + (1 if master_share > 0.0 else 0)  # members entering the fusion
        # last information shares (locals, then the master's when it keeps one): (n_fused, c)
        self.shares = np.full((self.n_fused, n_common), 1.0 / self.n_fused)
        self._dirty = False  # a local was updated since the last fusion
        self._flagged_only = np.zeros((n_locals, n_common), dtype=bool)

    @staticmethod
    def bank_size(n_locals: int, master_share: float = 0.0) -> int:
        """Members needed: the locals, plus the master when there is anything to fuse or keep."""
        return n_locals + (1 if (n_locals > 1 or master_share > 0.0) else 0)

    # --- start --------------------------------------------------------------------------------
    def start(self) -> None:
        """Initial division of the common prior (all members start from the same P0, x0):
        P_i = G_i^-1/2 P0 G_i^-1/2, Q_i = Q / G_i, for both reset modes."""
        if self.B == 1:
            return
        b = self.bank
        x0, P0 = b.x[0, : self.c].copy(), b.P[0, : self.c, : self.c].copy()
        self._reset_all(x0, P0)
        self._dirty = False

    # --- local update -------------------------------------------------------------------------
    def update(
        self, owner: int, z: np.ndarray, H: np.ndarray, R: np.ndarray, test: FaultTest, groups=None
    ) -> LocalUpdate:
        """Test and apply one measurement of local ``owner`` (one bank call; others unchanged).

        z (m,), H (m, n), R (m, m); ``groups`` (m,) the rows' sources, for the test. Raises
        ``kalman.NotPositiveDefinite`` before changing any state when S or the updated covariance
        is not positive definite.
        """
        if not 0 <= owner < self.n_locals:
            raise ValueError(f"owner {owner} is not a local filter (0..{self.n_locals - 1})")
        b = self.bank
        z = np.asarray(z, dtype=float)
        H = np.asarray(H, dtype=float)
        R = np.asarray(R, dtype=float)
        m, n = H.shape
        if n != b.x.shape[1]:
            raise ValueError(f"H has {n} columns, the bank has {b.x.shape[1]} states")
        # one call on the bank of locals with every row of the owner (other locals fully masked:
        # zero gain; the master is not a local and is left out); its innovation statistics are
        # the owner's predicted ones (seed 000 eq 5: S = H P H' + R)
        N = self.n_locals
        mask = np.zeros((N, m), dtype=bool)
        mask[owner] = True
        xl, Pl = b.x[:N], b.P[:N]
        x_new, P_new, res = kalman.update(xl, Pl, z, H, R, mask)
        std, nis = res.standardised[owner], float(res.nis[owner])
        decision = test.decide(std, res.S[owner], nis, groups)
        used = decision.used
        doubt = self._doubt(test, std, res.S[owner], nis, used) if np.any(used) else 0.0
        if doubt >= 1.0:  # rows passed one by one, together as improbable as a refusal: refused
            decision = dataclasses.replace(decision, isolated=np.ones(m, dtype=bool))
            used = decision.used
        if not np.all(used):  # redo without the isolated rows (rare: only when a test fails)
            mask[owner] = used  # seed 000 eq (8)-(10): a faulty row gets infinite noise = dropped
            if np.any(used):
                x_new, P_new, _ = kalman.update(xl, Pl, z, H, R, mask)
        if np.any(decision.flagged):
            # seed 000 eq (22) reading: common states seen by a flagged row and by no used row
            Hc = H[:, : self.c] != 0.0
            flagged_only = np.any(Hc[decision.flagged], axis=0) & ~np.any(Hc[used], axis=0)
            self._flagged_only[owner] |= flagged_only
        else:
            flagged_only = np.zeros(self.c, dtype=bool)
        if np.any(used):
            if doubt > 0.0:  # the update may have been a fault: the two hypotheses' moments
                delta = x_new[owner] - xl[owner]
                x_new, P_new = x_new.copy(), P_new.copy()
                x_new[owner] -= doubt * delta
                P_o = P_new[owner] + doubt * (Pl[owner] - P_new[owner])
                P_o += doubt * (1.0 - doubt) * np.outer(delta, delta)
                P_new[owner] = 0.5 * (P_o + P_o.T)
            P_owner = P_new[owner]
            if not np.isfinite(P_owner).all():
                raise kalman.NotPositiveDefinite("updated local covariance is not finite")
            kalman.cholesky(P_owner, "updated local covariance")  # PD check (cheaper than eigenvalues)
            if N == self.B:
                b.x, b.P = x_new, P_new
            else:
                x_all, P_all = b.x.copy(), b.P.copy()
                x_all[:N], P_all[:N] = x_new, P_new
                b.x, b.P = x_all, P_all
            self._dirty = True
        return LocalUpdate(owner, decision, std, nis, flagged_only, doubt)

    def _doubt(self, test: FaultTest, std: np.ndarray, S: np.ndarray, nis: float, used: np.ndarray) -> float:
        """The weight p of the hypothesis that an update the test passed was a fault (module
        docstring, "Doubtful updates"): 0 below the chi-square quantile at ``doubt_prob`` of the
        used rows' NIS, rising linearly to 1 at the quantile at the test's own false-alarm
        probability (where a whole-innovation test refuses). 0 for a test that refuses nothing
        (it takes every row by design) or with ``doubt_prob`` None."""
        if self.doubt_prob is None or not test.refuses:
            return 0.0
        k = int(np.count_nonzero(used))
        lo = chi2_threshold(self.doubt_prob, k)
        hi = chi2_threshold(test.false_alarm_prob, k)
        if hi <= lo:
            return 0.0
        if k == used.shape[0]:
            q = nis
        else:  # the NIS of the used rows alone (their prior innovations and covariance)
            sd = np.sqrt(np.diagonal(S))
            r = (std * sd)[used]
            q = float(r @ np.linalg.solve(S[np.ix_(used, used)], r))
        if not q > lo:
            return 0.0
        return min(1.0, (q - lo) / (hi - lo))

    # --- master -------------------------------------------------------------------------------
    def fuse(self) -> tuple[np.ndarray, np.ndarray]:
        """Master fusion of the current bank over the common states: (x_g (c,), P_g (c, c))."""
        b, c = self.bank, self.c
        if self.n_fused == 1:
            return b.x[0, :c].copy(), b.P[0, :c, :c].copy()
        return information_fusion(b.x[: self.n_fused, :c], b.P[: self.n_fused, :c, :c])

    def fused_covariance(self) -> np.ndarray:
        """P_g (c, c) for outputs, without a fusion where none is needed.

        With no local update since the last fusion, the master member carries the fused
        covariance through its own time update (P_m <- Phi P_m Phi' + Q, Carlson's master time
        update): its P (times its share when it keeps one) is the output. With scalar shares this
        equals a fresh fusion of the locals exactly (Carlson); with per-state shares a fresh
        fusion would also carry the reset's spurious information (sharing.py), which enters at
        the next fusion instead. With a local update pending, or in no_reset mode with a master
        share (the master then keeps its own information), ``fuse()``.
        """
        c = self.c
        if self.B == 1:
            return self.bank.P[0, :c, :c].copy()
        if not self._dirty and self.master is not None:
            if self.master_share == 0.0:
                return self.bank.P[self.master, :c, :c].copy()
            if self.reset_mode == "fusion_reset":
                return self.master_share * self.bank.P[self.master, :c, :c]
        return self.fuse()[1]

    def fused_covariance_of(self, P: np.ndarray) -> np.ndarray:
        """P_g (c, c) of a bank whose members' covariances are ``P`` (B, n, n) right after a
        fusion-reset (a checkpoint): the output-only master's own, the master's times its share,
        else the information fusion of the fused members' common blocks."""
        c = self.c
        if self.B == 1:
            return P[0, :c, :c].copy()
        if self.master is not None and self.reset_mode == "fusion_reset":
            m = self.master_share if self.master_share > 0.0 else 1.0
            return m * P[self.master, :c, :c]
        info = sum(np.linalg.inv(P[i, :c, :c]) for i in range(self.n_fused))
        return kalman.symmetrise(np.linalg.inv(info))

    def carry_private(self, P_old: np.ndarray, P_new: np.ndarray, T: np.ndarray, keep: np.ndarray) -> None:
        """Re-condition every member's private states (``P_new`` (B, n, n), in place) after the
        common states were carried over a gap: c' = T c + w, w independent of everything, added to
        the members' common blocks (``P_new[:, :c, :c]``), ``keep`` (c,) False for common states
        replaced outright (no correlation with anything before).

        A member keeps its private states as a conditional on the common ones (p | c, module
        docstring); kept as they are, a carry that widens the fused common covariance would widen
        the private marginals with it (A P_g A') although nothing happened to them: a DVL offset
        known to 1 cm would be 'known' only as well as the carried velocity, and its local would
        re-learn it like a new start. The true marginal and cross-covariance survive the carry
        (Cov(p, c') = Cov(p, c) T'), so each member's conditional is rebuilt from them against
        the new fused covariance."""
        c = self.c
        if P_new.shape[-1] <= c or self.B == 1:
            return
        Pg_old = self.fused_covariance_of(P_old)
        Pg_new = self.fused_covariance_of(P_new)
        for m in range(P_new.shape[0]):
            Pcc, Pcp, Ppp = P_old[m, :c, :c], P_old[m, :c, c:], P_old[m, c:, c:]
            if not np.any(Pcp):
                continue
            At = np.linalg.solve(Pcc, Pcp)  # P_cc^-1 P_cp = A'
            marg = Ppp - Pcp.T @ At + At.T @ Pg_old @ At  # p's marginal given the fused commons
            cross = (At.T @ Pg_old @ T.T) * keep[None, :]  # Cov(p, c')
            A_new = np.linalg.solve(Pg_new, cross.T).T  # Cov(p, c') P_g'^-1
            cond = kalman.symmetrise(marg - A_new @ Pg_new @ A_new.T)
            Pcc_m = P_new[m, :c, :c]
            P_new[m, c:, :c] = A_new @ Pcc_m
            P_new[m, :c, c:] = P_new[m, c:, :c].T
            P_new[m, c:, c:] = kalman.symmetrise(cond + A_new @ Pcc_m @ A_new.T)

    def fuse_and_reset(
        self, fused: tuple[np.ndarray, np.ndarray] | None = None
    ) -> tuple[np.ndarray, np.ndarray]:
        """Seed 000 algorithm 2, after an aiding epoch: fuse, reset (per mode), feed x_g back.

        ``fused``: the result of ``fuse()`` on the current bank if the caller already has it
        (saves recomputing it). Returns the fused (x_g, P_g) before feedback (after it, the fused
        error state is ~0: exactly 0 with ``fusion_reset``).
        """
        x_g, P_g = self.fuse() if fused is None else fused
        if self.B > 1:
            if self.reset_mode == "fusion_reset":
                self._reset_all(x_g, P_g)
            elif self.master_share == 0.0:  # no_reset: only the output-only master follows P_g
                self._reset(x_g, np.array([self.master]), P_g[None], np.ones((1, self.c)))
        self._flagged_only[:] = False
        self.bank.feedback(x_g)
        if self.reset_mode == "fusion_reset":
            self.bank.x[:, : self.c] = 0.0  # x_i = x_g - x_g (exact zero, no rounding residue)
        self._dirty = self.reset_mode == "no_reset" and self.master_share > 0.0
        return x_g, P_g

    def _reset_all(self, x_g: np.ndarray, P_g: np.ndarray) -> None:
        """Reset every member from the fusion: the locals by the strategy's ``ResetPlan``, the
        master by its constant share (or to P_g itself for the output-only master)."""
        c = self.c
        ctx = SharingContext(
            flagged_only=self._flagged_only, floor_share=self.floor_share, master_share=self.master_share
        )
        try:
            plan = self.strategy.plan(self.bank.P[: self.n_locals, :c, :c], P_g, ctx)
            Pcc = plan.covariances(P_g)
        except (ValueError, np.linalg.LinAlgError) as exc:  # invalid shares come from broken covariances
            raise kalman.NotPositiveDefinite(f"sharing failed: {exc}") from exc
        qs = plan.q_scales()
        shares = plan.state_shares()
        if self.master is not None:
            m = self.master_share if self.master_share > 0.0 else 1.0
            Pcc = np.concatenate([Pcc, (P_g / m)[None]])
            qs = np.vstack([qs, np.full((1, c), 1.0 / m)])
            shares = np.vstack([shares, np.full((1, c), m)])
        self._reset(x_g, np.arange(self.B), Pcc, qs)
        self.shares = shares[: self.n_fused]

    def _reset(
        self, x_g: np.ndarray, members: np.ndarray, Pcc_new: np.ndarray, q_scale_new: np.ndarray
    ) -> None:
        """Reset ``members`` (index array) to x_g with common covariances Pcc_new (members, c, c)
        and process-noise scales q_scale_new (members, c)."""
        b, c = self.bank, self.c
        P = b.P.copy()
        x = b.x.copy()
        Pm, xm = P[members], x[members]
        if P.shape[1] > c:  # private states: keep p | c, follow the new common marginal
            Pcc_old = Pm[:, :c, :c]
            Pcp = Pm[:, :c, c:]
            kalman.cholesky(Pcc_old, "local common covariance")  # positive-definite check
            # A' = P_cc^-1 P_cp after the diagonal scaling D = diag(P_cc)^1/2 (INS covariances are
            # badly scaled); numpy's batched solve (scipy's batched solve_triangular costs ~10 ms)
            d = np.sqrt(np.diagonal(Pcc_old, axis1=1, axis2=2))
            Cs = Pcc_old / (d[:, :, None] * d[:, None, :])
            At = np.linalg.solve(Cs, Pcp / d[:, :, None]) / d[:, :, None]
            A = np.swapaxes(At, 1, 2)  # A = P_pc P_cc^-1   (members, p, c)
            xm[:, c:] += np.einsum("bpc,bc->bp", A, x_g[None] - xm[:, :c])
            Pm[:, c:, :c] = A @ Pcc_new
            Pm[:, :c, c:] = np.swapaxes(Pm[:, c:, :c], 1, 2)
            Pm[:, c:, c:] = Pm[:, c:, c:] + A @ (Pcc_new - Pcc_old) @ At
        Pm[:, :c, :c] = Pcc_new
        xm[:, :c] = x_g  # seed 000 eq (27)
        P[members] = Pm
        x[members] = xm
        b.P = kalman.symmetrise(P)
        b.x = x
        q_scale = b.q_scale.copy()
        q_scale[members, :c] = q_scale_new  # seed 000 eq (15)/(26) (see sharing.ResetPlan)
        b.q_scale = q_scale


__all__ = ["FederatedCore", "FilterBank", "LinearBank", "LocalUpdate", "information_fusion", "ResetMode"]
