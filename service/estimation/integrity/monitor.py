"""Integrity bookkeeping around MHSS: alert limits per flight phase, alarm and availability,
exclusion memory and re-admission.

Alert limits (SEEDS.md seed 001, ICAO Annex 10 as commonly tabulated)
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

from collections import deque
from collections.abc import Sequence
from dataclasses import dataclass, field

import numpy as np

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
            if e.healthy_since is None:
                e.healthy_since = t
            if t - e.healthy_since >= self.readmit_after_s - 1e-9:
                ready.append(sid)
        for sid in ready:
            del self.entries[sid]
        return ready

    def clear(self) -> None:
        self.entries.clear()


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
        return np.any(self.statistic > self.threshold, axis=1)

    @property
    def normalised(self) -> np.ndarray:
        """(N,) largest statistic / threshold over the windows."""
        if self.statistic.size == 0:
            return np.zeros(len(self.sats))
        return np.max(self.statistic / np.maximum(self.threshold, 1e-300), axis=1)


@dataclass
class ResidualWindows:
    """Per-satellite buffers of the satellite residual test (module docstring)."""

    windows: tuple[int, ...] = (1, 10)
    _buf: dict[str, deque] = field(default_factory=dict)

    def __post_init__(self) -> None:
        if any(int(w) < 1 for w in self.windows):
            raise ValueError(f"residual windows must be >= 1 epoch, got {self.windows}")
        self.windows = tuple(int(w) for w in self.windows)

    @property
    def n_families(self) -> int:
        return len(self.windows)

    def retain(self, sats: Sequence[str]) -> None:
        """Forget satellites no longer in the bank (one that comes back starts empty)."""
        keep = set(sats)
        for sid in [s for s in self._buf if s not in keep]:
            del self._buf[sid]

    def clear(self) -> None:
        self._buf.clear()

    def push(self, sats: Sequence[str], e: np.ndarray, hph: np.ndarray, r: np.ndarray) -> None:
        depth = max(self.windows, default=1)
        for j, sid in enumerate(sats):
            b = self._buf.get(sid)
            if b is None:
                b = self._buf[sid] = deque(maxlen=depth)
            b.append((float(e[j]), float(np.sqrt(hph[j])), float(r[j])))

    def tests(self, sats: Sequence[str], k: float) -> ResidualTests:
        """Statistics and thresholds (multiplier ``k``) of every window for ``sats``."""
        nw = len(self.windows)
        stat, thr, cnt = (
            np.zeros((len(sats), nw)),
            np.full((len(sats), nw), np.inf),
            np.zeros((len(sats), nw)),
        )
        for j, sid in enumerate(sats):
            b = self._buf.get(sid)
            if not b:
                continue
            arr = np.array(b)
            for i, w in enumerate(self.windows):
                a = arr[-w:]
                n = len(a)
                stat[j, i] = abs(a[:, 0].sum()) / n
                thr[j, i] = k * np.sqrt((a[:, 1].sum() / n) ** 2 + a[:, 2].sum() / (n * n))
                cnt[j, i] = n
        return ResidualTests(tuple(sats), self.windows, stat, thr, cnt)


__all__ = [
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
