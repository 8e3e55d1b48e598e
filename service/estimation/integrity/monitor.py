"""The integrity monitor around an MHSS bank: one call per GNSS epoch (:class:`MhssMonitor`).

It owns everything integrity does with an epoch's rows: re-admission tests of excluded
satellites, the used satellite set (bank rebuild), the batched update of every member and cross
block, the satellite residual windows, the separation tests, exclusion, protection levels and the
verdict; the pipeline only builds the rows (measurement hook) and turns the result into a message.
Also here: alert limits per flight phase, alarm and availability, exclusion memory and
re-admission.

Alert limits (docs/PAPERS.md seed 001, ICAO Annex 10 as commonly tabulated)
--------------------------------------------------------------------
    phase       HAL        VAL      TTA
    en_route    3704 m     -        300 s   (2 NM; 5 min; PANS-OPS receivers use 30 s)
    terminal    1852 m     -        15 s    (1 NM; some tables 10 s)
    npa          556 m     -        10 s    (0.3 NM, NPA/LNAV)
    lpv           40 m     50 m     10 s    (APV-I)
    lpv200        40 m     35 m      6 s

Per GNSS epoch (:func:`assess`)
-------------------------------
    available = HPL <= HAL and (no VAL or VPL <= VAL)
    alarm     = not available, or a detection that exclusion did not resolve
An alarm is raised at the epoch itself (no waiting inside the TTA); the TTA is what an evaluation
measures from fault onset to the alarm or exclusion. Vertical tests join detection (and VPL is
compared with VAL) only in phases that have a VAL; the false-alarm budget is then split evenly
between the horizontal and vertical test families (``n_families``).

Satellite residual test (:class:`ResidualWindows`, detection in addition to solution separation)
-------------------------------------------------------------------------------------------------
Each epoch, satellite n's pseudorange residual against the sub-filter F0n that excludes it,
e_n = z_n - H_n x_0n (after the update), has mean = the fault on n and variance
hph_n + r_n (hph_n = H_n P_0n H_n'), its noise v_n independent of F0n's error (F0n never used n).
Over the last W epochs (W in ``windows``; fewer right after a (re)start) the mean residual
m = sum(e)/W is tested against

    sigma_W^2 = (sum sqrt(hph_k) / W)^2 + sum r_k / W^2

which bounds var(m) for ANY correlation of F0n's errors across the window (the standard
deviation of a sum is at most the sum of the standard deviations) with white measurement noise.
A window of one epoch is the snapshot residual test; longer windows average the noise down and
detect ramps (the idea of AIME's averaged innovations, Diesel & Dunn 1995, on the excluded
satellite). Flag: |m| > K sigma_W. Each window is one family of N tests sharing the per-epoch
false-alarm budget with the separation tests (``n_families`` in the pipeline).
The windows restart (are emptied) for a satellite that enters the bank and for every satellite
after an exclusion (their past residuals were taken against sub-filters that used the excluded
satellite), and on re-initialisation.

Re-admission (:class:`ExclusionBook`)
------------------------------------
An excluded satellite is re-admitted after ``readmit_after_s`` of continuous health: every epoch
it is observed, its rows are tested against the current main filter (standardised innovation of
each row within the single-test multiplier); a failure, or an epoch with the satellite missing,
restarts the clock. Re-admitted satellites enter the bank like rising satellites.
"""

from __future__ import annotations

import functools
from collections.abc import Sequence
from dataclasses import dataclass, field

import numpy as np

from fednav.service.estimation.integrity.mhss import (
    BankUpdate,
    SeparationTests,
    k_fa,
    k_fa_horizontal,
    k_md,
    residual_test,
)
from fednav.service.estimation.kalman import NotPositiveDefinite
from fednav.service.estimation.measurements.base import Measurement

PhaseName = str


@dataclass(frozen=True)
class PhaseLimits:
    """Alert limits of one flight phase: HAL (m), VAL (m, None where there is none), TTA (s)."""

    hal_m: float
    val_m: float | None
    tta_s: float


PHASES: dict[PhaseName, PhaseLimits] = {
    "en_route": PhaseLimits(3704.0, None, 300.0),
    "terminal": PhaseLimits(1852.0, None, 15.0),
    "npa": PhaseLimits(556.0, None, 10.0),
    "lpv": PhaseLimits(40.0, 50.0, 10.0),
    "lpv200": PhaseLimits(40.0, 35.0, 6.0),
}


def limits(phase: PhaseName) -> PhaseLimits:
    try:
        return PHASES[phase]
    except KeyError:
        raise ValueError(f"unknown flight phase {phase!r}; choose from {sorted(PHASES)}") from None


def uses_vertical(phase: PhaseName) -> bool:
    """Vertical tests and VPL join the alarm logic only in phases with a VAL."""
    return limits(phase).val_m is not None


def n_families(phase: PhaseName) -> int:
    """Number of test families sharing the false-alarm budget (horizontal, + vertical with a VAL)."""
    return 2 if uses_vertical(phase) else 1


@dataclass(frozen=True)
class Assessment:
    available: bool
    alarm: bool


def assess(hpl_m: float, vpl_m: float, phase: PhaseName, detected: bool, resolved: bool) -> Assessment:
    """Availability and alarm of one epoch (module docstring)."""
    lim = limits(phase)
    available = hpl_m <= lim.hal_m and (lim.val_m is None or vpl_m <= lim.val_m)
    alarm = (not available) or (detected and not resolved)
    return Assessment(available, alarm)


@dataclass
class _Excluded:
    t_excluded: float
    healthy_since: float | None = None


@dataclass
class ExclusionBook:
    """Excluded satellites and their re-admission clocks."""

    readmit_after_s: float
    entries: dict[str, _Excluded] = field(default_factory=dict)

    @property
    def ids(self) -> list[str]:
        return sorted(self.entries)

    def __contains__(self, sat_id: str) -> bool:
        return sat_id in self.entries

    def exclude(self, sat_id: str, t: float) -> None:
        self.entries[sat_id] = _Excluded(t)

    def observe(self, t: float, health: dict[str, bool]) -> list[str]:
        """Record this epoch's health of the excluded satellites (``health``: id -> passed, for
        those observed) and return the ones to re-admit now (removed from the book)."""
        ready = []
        for sid, e in self.entries.items():
            ok = health.get(sid)
            if not ok:
                e.healthy_since = None
                continue
            if e.healthy_since is None or t < e.healthy_since:  # (a new time base restarts it)
                e.healthy_since = t
            if t - e.healthy_since >= self.readmit_after_s - 1e-9:
                ready.append(sid)
        for sid in ready:
            del self.entries[sid]
        return ready

    def clear(self) -> None:
        self.entries.clear()

    def healthy_for(self, t: float) -> dict[str, float]:
        """Each excluded satellite with the seconds its health tests have passed at ``t`` (0 while
        failing): what another service needs to keep it out as long as this one would."""
        return {
            sid: 0.0 if e.healthy_since is None else max(0.0, t - e.healthy_since)
            for sid, e in self.entries.items()
        }

    def restore(self, healthy_for: dict[str, float], t: float) -> None:
        """Exclude the satellites of :meth:`healthy_for` (another service's book) at ``t``, their
        health clocks as far along as they were there (a satellite already excluded here keeps the
        clock of whichever has passed less)."""
        for sid, h in healthy_for.items():
            since = t - h if h > 0.0 else None
            e = self.entries.get(sid)
            if e is None:
                self.entries[sid] = _Excluded(t, since)
            elif since is None or (e.healthy_since is not None and since > e.healthy_since):
                e.healthy_since = since


@dataclass(frozen=True)
class ResidualTests:
    """Windowed satellite residual tests of one epoch, arrays (N, n_windows) in bank order.

    statistic: |mean residual| (m); threshold: K sigma_W (m); count: samples in each window.
    """

    sats: tuple[str, ...]
    windows: tuple[int, ...]
    statistic: np.ndarray
    threshold: np.ndarray
    count: np.ndarray

    @property
    def flagged(self) -> np.ndarray:
        """(N,) any window of the satellite above its threshold."""
        if self.statistic.size == 0:
            return np.zeros(len(self.sats), dtype=bool)
        return (self.statistic > self.threshold).any(axis=1)

    @property
    def normalised(self) -> np.ndarray:
        """(N,) largest statistic / threshold over the windows."""
        if self.statistic.size == 0:
            return np.zeros(len(self.sats))
        return np.maximum.reduce(self.statistic / np.maximum(self.threshold, 1e-300), axis=1)


class ResidualWindows:
    """Per-satellite buffers of the satellite residual test (module docstring).

    Each satellite in the buffers owns a row of ``_hist`` (3, rows, depth): the channels e,
    sqrt(hph), r of its last ``depth`` epochs, oldest first, zeros before its first sample.
    """

    def __init__(self, windows: Sequence[int] = (1, 10)):
        if any(int(w) < 1 for w in windows):
            raise ValueError(f"residual windows must be >= 1 epoch, got {tuple(windows)}")
        self.windows: tuple[int, ...] = tuple(int(w) for w in windows)
        self._depth = max(self.windows, default=1)
        self._row: dict[str, int] = {}
        self._free: list[int] = []
        self._hist = np.zeros((3, 0, self._depth))
        self._count = np.zeros(0, dtype=int)

    @property
    def n_families(self) -> int:
        return len(self.windows)

    def retain(self, sats: Sequence[str]) -> None:
        """Forget satellites no longer in the bank (one that comes back starts empty)."""
        keep = set(sats)
        for sid in [s for s in self._row if s not in keep]:
            self._free.append(self._row.pop(sid))

    def clear(self) -> None:
        self._row.clear()
        self._free.clear()
        self._hist = np.zeros((3, 0, self._depth))
        self._count = np.zeros(0, dtype=int)

    def _rows_for(self, sats: Sequence[str]) -> np.ndarray:
        """Rows of ``sats``, new (empty) rows for satellites not in the buffers."""
        rows = []
        for sid in sats:
            row = self._row.get(sid)
            if row is None:
                if not self._free:
                    n = self._hist.shape[1]
                    grow = max(n, 16)
                    self._hist = np.concatenate([self._hist, np.zeros((3, grow, self._depth))], axis=1)
                    self._count = np.concatenate([self._count, np.zeros(grow, dtype=int)])
                    self._free.extend(range(n + grow - 1, n - 1, -1))
                row = self._row[sid] = self._free.pop()
                self._hist[:, row] = 0.0
                self._count[row] = 0
            rows.append(row)
        return np.array(rows, dtype=int)

    def push(self, sats: Sequence[str], e: np.ndarray, hph: np.ndarray, r: np.ndarray) -> None:
        if not len(sats):
            return
        rows = self._rows_for(sats)
        h = self._hist
        h[:, rows, :-1] = h[:, rows, 1:]
        h[0, rows, -1] = e
        h[1, rows, -1] = np.sqrt(hph)
        h[2, rows, -1] = r
        self._count[rows] = np.minimum(self._count[rows] + 1, self._depth)

    def tests(self, sats: Sequence[str], k: float) -> ResidualTests:
        """Statistics and thresholds (multiplier ``k``) of every window for ``sats``."""
        nw = len(self.windows)
        stat, thr, cnt = (
            np.zeros((len(sats), nw)),
            np.full((len(sats), nw), np.inf),
            np.zeros((len(sats), nw)),
        )
        idx = [(j, self._row[sid]) for j, sid in enumerate(sats) if sid in self._row]
        if idx and nw:
            j, rows = (np.array(v, dtype=int) for v in zip(*idx, strict=True))
            has = self._count[rows] > 0
            j, rows = j[has], rows[has]
            h = self._hist[:, rows]  # (3, len(rows), depth)
            for i, w in enumerate(self.windows):
                n = np.minimum(self._count[rows], w).astype(float)
                sums = np.add.reduce(h[:, :, self._depth - w :], axis=2)  # zeros before the first sample
                stat[j, i] = np.abs(sums[0]) / n
                thr[j, i] = k * np.sqrt((sums[1] / n) ** 2 + sums[2] / (n * n))
                cnt[j, i] = n
        return ResidualTests(tuple(sats), self.windows, stat, thr, cnt)


@functools.lru_cache(maxsize=256)
def _pseudorange_rows(labels: tuple[str, ...]) -> np.ndarray:
    """Which rows are pseudoranges (``<id>.pr``), read-only: a receiver's labels repeat from epoch
    to epoch."""
    out = np.array([lab.endswith(".pr") for lab in labels], dtype=bool)
    out.setflags(write=False)
    return out


def _positive_definite(P: np.ndarray) -> bool:
    """:func:`~service.estimation.kalman.is_positive_definite` of one matrix: finite, symmetric
    (to 1e-9 relative) and positive definite (smallest eigenvalue of its symmetric part > 0)."""
    if not np.isfinite(P).all():
        return False
    if (P == P.T).all():  # the bank symmetrises its members: then 0.5 (P + P') is P itself
        try:  # LAPACK's Cholesky: a fifth of the eigenvalues' cost; its failure is checked below
            np.linalg.cholesky(P)
            return True
        except np.linalg.LinAlgError:
            return bool(np.linalg.eigvalsh(P)[0] > 0.0)
    if not (np.abs(P - P.T) <= 1e-9 * (1.0 + np.abs(P))).all():
        return False
    return bool(np.linalg.eigvalsh(0.5 * (P + P.T))[0] > 0.0)


# --- the monitor ---------------------------------------------------------------------------------------
@dataclass(frozen=True)
class MonitorSettings:
    """What the monitor needs from a pipeline's configuration (see TightlyCoupledConfig)."""

    phase: PhaseName = "npa"
    p_fa: float = 1e-4
    p_md: float = 1e-3
    depth: int = 2  # 0 main only (no integrity), 1 + sub-filters, 2 + sub-sub filters (exclusion search)
    exclusion: bool = True
    readmit_after_s: float = 60.0
    horizontal_threshold: str = "gaussian"
    residual_windows: tuple[int, ...] = (1, 10)


@dataclass(frozen=True)
class EpochResult:
    """Diagnostics of one GNSS epoch (tests, evaluation, dashboards and the Integrity message).

    ``tests`` is None when the monitor runs without integrity (depth 0); ``detected_by`` is
    "separation", "residual", "separation+residual", "epoch_refused" (the state refused the
    epoch wholesale: :meth:`MhssMonitor.refused_epoch`) or "" (no detection); ``residual_by_sat``:
    per satellite the (statistic, threshold) of its window with the largest ratio.
    """

    t: float
    used: tuple[str, ...]
    update: BankUpdate | None
    tests: SeparationTests | None
    detected: bool
    excluded_now: str | None
    resolved: bool
    readmitted: tuple[str, ...]
    residual: ResidualTests | None = None
    detected_by: str = ""
    assessment: Assessment | None = None
    excluded: tuple[str, ...] = ()
    residual_by_sat: dict[str, tuple[float, float]] = field(default_factory=dict)


class MhssMonitor:
    """Integrity monitoring of one MHSS bank, epoch by epoch (module docstring).

    False-alarm budget: ``p_fa`` per epoch is split evenly over the test families -- horizontal
    separation (+ vertical with a VAL) and one family per residual window -- each of N two-sided
    tests: K = Q^-1(p_fa / (2 N n_families)). The protection levels use the separation K (the
    residual tests only add detections, so the PLs stay valid).
    """

    def __init__(self, settings: MonitorSettings):
        self.settings = s = settings
        self.limits = limits(s.phase)
        self.use_vertical = uses_vertical(s.phase)
        self.residual = ResidualWindows(s.residual_windows)
        self.n_families = n_families(s.phase) + self.residual.n_families
        self.kmd = k_md(s.p_md)
        self.k_single = k_fa(s.p_fa, 1)  # one two-sided test (re-admission residuals)
        self.book = ExclusionBook(s.readmit_after_s)

    def reset(self) -> None:
        """Forget exclusions and residual windows (re-initialisation)."""
        self.book.clear()
        self.residual.clear()

    def restart_windows(self) -> None:
        """A restart of the filter on a running vehicle (a covariance recovery, a reset, a
        re-initialisation): the residual windows restart (they were taken against the old filter)
        and the exclusions are kept with their health clocks: a satellite is re-admitted only
        once its health tests have passed for ``readmit_after_s``, the tests after the restart
        taken against the new filter (a failed one restarts its clock, as always), and none while
        the new state is not verified (``epoch(judge_health=False)``). A satellite's fault does
        not depend on the navigation state: clearing the book at a reset let an excluded
        satellite back in at the next epoch without its check (the demo's C03 at a reset 30 s
        after its ramp fault ended; during a live fault it would have been the faulty one)."""
        self.residual.clear()

    def refused_epoch(self, bank, t: float) -> EpochResult:
        """An epoch the pipeline's state refused wholesale (``Pipeline.refused_wholesale``: most
        satellites disagree with it, so no update and no satellite's fault to find): the
        protection levels of the bank as it stands, reported ``detected`` and unresolved
        (``detected_by`` ``"epoch_refused"``), hence an alarm. No exclusion, no health judged."""
        cfg, mh = self.settings, bank.mhss
        if mh.depth == 0 or mh.N == 0:
            return EpochResult(t, mh.sats, None, None, False, None, True, ())
        p_fa, nf = cfg.p_fa, self.n_families
        kfa = k_fa(p_fa, mh.N * nf)
        tests = mh.main_tests(kfa, self.kmd, k_fa_horizontal(p_fa, mh.N * nf, cfg.horizontal_threshold))
        verdict = assess(tests.hpl, tests.vpl, cfg.phase, True, False)
        return EpochResult(
            t,
            mh.sats,
            None,
            tests,
            True,
            None,
            False,
            (),
            None,
            "epoch_refused",
            verdict,
            tuple(self.book.ids),
        )

    def epoch(
        self, bank, meas: Measurement, t: float, judge_health: bool = True, may_exclude: bool = True
    ) -> EpochResult:
        """One GNSS epoch on ``bank`` (an :class:`~service.estimation.integrity.ins_bank.MhssInsBank`).

        ``meas``: rows of the usable satellites grouped by satellite (``groups``/``group_ids``),
        pseudorange rows labelled ``<id>.pr``. Updates the bank, feeds the main correction back,
        excludes a faulty satellite when it can. Raises ``NotPositiveDefinite`` (bank unchanged
        since the update) when the main covariance lost positive definiteness.

        ``judge_health`` False (the pipeline's state is suspect or not yet verified: tests against
        it say nothing of a satellite): the excluded satellites' health is not judged at this
        epoch, their clocks neither advanced by a pass nor restarted by a failure, and none is
        re-admitted.

        ``may_exclude`` False (the pipeline's state is suspect: it may be corrupt, e.g. by a
        contested IMU, and its covariance does not say so): a detection excludes no satellite.
        Every test is then taken against an error the satellites do not have; excluding the
        satellite that best "resolves" it removed good satellites one per epoch (the demo on seed
        16, an IMU burst at 10x: three in 0.4 s, two left, the solution 5.7 m off for a minute).
        The detection is reported (``detected``, unresolved: an alarm); the lifecycle verifies the
        state against the vehicle's own reference or resets it.
        """
        cfg = self.settings
        mh = bank.mhss
        ids, groups = meas.group_ids, meas.groups
        r_var = meas.r_var
        # 1. re-admission tests of excluded satellites against the current main filter
        readmitted: tuple[str, ...] = ()
        if judge_health:
            health: dict[str, bool] = {}
            for g, sid in enumerate(ids):
                if sid in self.book:
                    sel = groups == g
                    std = residual_test(mh.x[0], mh.P[0], meas.z[sel], meas.H[sel], r_var[sel])
                    health[sid] = bool(np.all(np.abs(std) <= self.k_single))
            readmitted = tuple(self.book.observe(t, health))
        # 2. the used set; a change rebuilds the bank
        used = tuple(sid for sid in ids if sid not in self.book)
        if set(used) != set(mh.sats):
            mh = bank.mhss = mh.rebuild(used)
            self.residual.retain(mh.sats)
        # 3. batched update of members and cross blocks, residual windows, feedback
        upd = None
        if used:
            col = {sid: j for j, sid in enumerate(mh.sats)}
            sat_col = np.array([col.get(sid, -1) for sid in ids])
            sel = sat_col[groups] >= 0
            z, H, rv, rcol = meas.z[sel], meas.H[sel], r_var[sel], sat_col[groups[sel]]
            upd = mh.update(z, H, rv, rcol)
            if not _positive_definite(mh.P[0]):
                raise NotPositiveDefinite("main filter covariance after the MHSS update")
            if mh.depth >= 1 and self.residual.windows:
                # the pseudorange row of each bank column (one per used satellite)
                is_pr = _pseudorange_rows(tuple(meas.labels))[sel]
                pr_idx = np.flatnonzero(is_pr)
                pr_row = np.full(mh.N, -1)
                pr_row[rcol[pr_idx]] = pr_idx
                if (pr_row >= 0).all():
                    self.residual.push(mh.sats, *mh.excluded_residuals(z, H, rv, pr_row))
            bank.feedback(mh.x[0].copy())
        if mh.depth == 0:
            return EpochResult(t, used, upd, None, False, None, True, readmitted)
        # 4. separation and residual tests -> detection -> exclusion
        p_fa, nf, usev, hmode = cfg.p_fa, self.n_families, self.use_vertical, cfg.horizontal_threshold
        kfa = k_fa(p_fa, mh.N * nf)
        tests = mh.main_tests(kfa, self.kmd, k_fa_horizontal(p_fa, mh.N * nf, hmode))
        res = self.residual.tests(mh.sats, kfa)
        ss_detected = bool(tests.flagged(usev).any())
        res_detected = bool(res.flagged.any())
        detected = ss_detected or res_detected
        resolved, excluded_now = not detected, None
        if detected and cfg.exclusion and may_exclude:
            r = mh.find_exclusion(tests, p_fa, self.kmd, usev, nf, res.flagged, res.normalised, hmode)
            if r is not None:
                excluded_now = mh.sats[r]
                mh = bank.mhss = mh.rebuild([s for s in mh.sats if s != excluded_now], purge=[excluded_now])
                bank.feedback(mh.x[0].copy())  # the new main (old sub-filter r) becomes the solution
                self.book.exclude(excluded_now, t)
                self.residual.clear()  # past residuals were taken against filters that used it
                tests = mh.main_tests(
                    k_fa(p_fa, mh.N * nf), self.kmd, k_fa_horizontal(p_fa, mh.N * nf, hmode)
                )
                resolved = not bool(np.any(tests.flagged(usev)))
        # 5. protection levels against the alert limits
        verdict = assess(tests.hpl, tests.vpl, cfg.phase, detected, resolved)
        by_sat = {}
        if res.statistic.size:
            ratio = res.statistic / np.maximum(res.threshold, 1e-300)
            rows = np.arange(len(res.sats))
            w = np.argmax(ratio, axis=1)
            st, th = res.statistic[rows, w].tolist(), res.threshold[rows, w].tolist()
            by_sat = {sid: (st[j], th[j]) for j, sid in enumerate(res.sats)}
        detected_by = (
            ("separation" if ss_detected else "")
            + ("+" if ss_detected and res_detected else "")
            + ("residual" if res_detected else "")
        )
        return EpochResult(
            t,
            mh.sats,
            upd,
            tests,
            detected,
            excluded_now,
            resolved,
            readmitted,
            res,
            detected_by,
            verdict,
            tuple(self.book.ids),
            by_sat,
        )


__all__ = [
    "EpochResult",
    "MhssMonitor",
    "MonitorSettings",
    "PHASES",
    "Assessment",
    "ExclusionBook",
    "PhaseLimits",
    "ResidualTests",
    "ResidualWindows",
    "assess",
    "limits",
    "n_families",
    "uses_vertical",
]
