"""Fault tests of a local filter's innovation: which observation rows to drop this epoch.

Interface (docs/STYLE.md 2): ``FaultTest.flags(standardised, S, nis) -> FaultDecision``; a test that
also looks at the rows' sources overrides ``decide(standardised, S, nis, groups)`` (what the
federated core calls; by default ``flags``)

    standardised : (m,)   r_j / sqrt(S_jj), the standardised predicted innovations
    S            : (m, m) innovation covariance H P H' + R of the local filter being tested
    nis          : float  r' S^-1 r (normalised innovation squared, chi2(m) when fault free)
    groups       : (m,) int or None  the source of each row (``Measurement.groups``: a fix's
                          position solution, its velocity; a satellite)

``FaultDecision`` carries, per row, the statistic and threshold (for display), whether the row
failed its test (``flagged``) and whether it is dropped from the update (``isolated``). Dropping a
row is the exact equivalent of seed 000 eq (8)-(10) (R_jj -> infinity for a faulty row).

Tests (registry names = ``service.config.FaultHandlingName``):
  per_observation  seed 000 eq (5)-(7): f_jj = r_j^2 / S_jj against chi2_1(1 - alpha); only the
                   failing rows are dropped, healthy rows of the same subsystem are still used.
  per_source       the same per-row test; a failing row makes the rest of its source suspect (a
                   receiver's position solution: a fault large enough to fail one axis is in the
                   others, merely smaller; per_observation would take them at full weight): they
                   are kept only within SUSPECT_SIGMA (2). Rows without sources: per_observation.
  subsystem        seed 000 "method 1": the same per-row tests, but if any row fails the whole
                   subsystem is isolated this epoch.
  chi2_reconfig    seed 004: NIS against chi2_m(1 - alpha); on failure the subsystem is excluded
                   (reconfiguration to the remaining locals) until its test passes again.
  none             the per-row statistics are computed and flagged for display; nothing dropped.

Instances may hold state (``chi2_reconfig``): make one per subsystem (``make_fault_test``).
"""

from __future__ import annotations

from abc import ABC, abstractmethod
from dataclasses import dataclass
from functools import lru_cache
from typing import ClassVar

import numpy as np
from scipy.stats import chi2

from fednav.service.estimation.measurements.base import refused_with_source


@lru_cache(maxsize=256)
def chi2_threshold(false_alarm_prob: float, dof: int) -> float:
    """chi2_dof quantile at 1 - false_alarm_prob (cached: scipy's ppf is slow per call)."""
    return float(chi2.ppf(1.0 - false_alarm_prob, dof))


@dataclass(frozen=True)
class FaultDecision:
    """Outcome of one test of an m-row innovation.

    statistic, threshold : (m,) float   what was compared, per row (for display)
    flagged : (m,) bool                 the row (or the subsystem test covering it) failed
    isolated : (m,) bool                the row is dropped from this epoch's update
    """

    statistic: np.ndarray
    threshold: np.ndarray
    flagged: np.ndarray
    isolated: np.ndarray
    #: (m,) bool or None: rows isolated only as the rest of a failing row's source (``per_source``)
    suspect: np.ndarray | None = None

    @property
    def used(self) -> np.ndarray:
        """(m,) bool: rows that update the filter."""
        return ~self.isolated

    @property
    def passed(self) -> np.ndarray:
        """(m,) bool: rows used or isolated only as suspects (their innovations are the stream's
        spread: its sigma history and consistency window take them)."""
        return self.used if self.suspect is None else self.used | self.suspect

    @property
    def subsystem_isolated(self) -> bool:
        return bool(np.all(self.isolated))


class FaultTest(ABC):
    """Base of fault tests; ``false_alarm_prob`` is the per-test false-alarm probability alpha."""

    name: ClassVar[str]
    #: the test refuses rows (False: it only flags them for display, every row is taken)
    refuses: ClassVar[bool] = True

    def __init__(self, false_alarm_prob: float = 1e-3):
        if not 0.0 < false_alarm_prob < 0.5:
            raise ValueError(f"false_alarm_prob must be in (0, 0.5), got {false_alarm_prob}")
        self.false_alarm_prob = float(false_alarm_prob)

    @abstractmethod
    def flags(self, standardised: np.ndarray, S: np.ndarray, nis: float) -> FaultDecision:
        """Decide which rows are faulty and which are dropped this epoch."""

    def decide(self, standardised: np.ndarray, S: np.ndarray, nis: float, groups=None) -> FaultDecision:
        """:meth:`flags`, given also each row's source (``Measurement.groups`` or None); tests
        that use the sources override this."""
        return self.flags(standardised, S, nis)

    def reset(self) -> None:  # noqa: B027 (optional hook: stateless tests keep nothing)
        """Forget any state (re-initialisation)."""

    def _per_row(self, standardised: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        std = np.asarray(standardised, dtype=float)
        f = std * std  # seed 000 eq (5)-(6): diagonal f_jj = r_j^2 / S_jj ~ chi2(1) fault free
        thr = np.full(f.shape, chi2_threshold(self.false_alarm_prob, 1))
        return f, thr, f > thr  # seed 000 eq (7)


class NoFaultHandling(FaultTest):
    """No isolation; the per-observation chi2(1) flags are still computed for display."""

    name = "none"
    refuses = False

    def flags(self, standardised, S, nis):
        f, thr, bad = self._per_row(standardised)
        return FaultDecision(f, thr, bad, np.zeros_like(bad))


class PerObservation(FaultTest):
    """Seed 000 eq (5)-(10): per-row chi2(1) test; failing rows dropped, healthy rows kept."""

    name = "per_observation"

    def flags(self, standardised, S, nis):
        f, thr, bad = self._per_row(standardised)
        return FaultDecision(f, thr, bad, bad.copy())  # eq (8)-(10): faulty row -> R infinite


class PerSource(FaultTest):
    """Per-row chi2(1) test as :class:`PerObservation`; a failing row also isolates the rows of its
    source (``groups``) beyond ``SUSPECT_SIGMA`` this epoch (measurements.base.refused_with_source);
    the other sources' rows are kept."""

    name = "per_source"

    def flags(self, standardised, S, nis):
        return self.decide(standardised, S, nis)

    def decide(self, standardised, S, nis, groups=None):
        f, thr, bad = self._per_row(standardised)
        isolated = refused_with_source(standardised, bad, groups)
        return FaultDecision(f, thr, bad, isolated, isolated & ~bad)


class SubsystemIsolation(FaultTest):
    """Seed 000 "method 1": any failing row isolates the whole subsystem this epoch."""

    name = "subsystem"

    def flags(self, standardised, S, nis):
        f, thr, bad = self._per_row(standardised)
        return FaultDecision(f, thr, bad, np.full(bad.shape, bool(np.any(bad))))


class Chi2Reconfig(FaultTest):
    """Seed 004: whole-innovation chi2(m) test; a failing subsystem is excluded until it passes.

    Every row reports the subsystem statistic (NIS) and threshold chi2_m(1 - alpha). The test is
    evaluated at every epoch of the subsystem, excluded or not (the local is reset from the fused
    solution, so its innovation stays meaningful); it rejoins after ``readmit_passes``
    consecutive passes (default 1: at the first pass, seed 004's "rejoin when the test passes
    again"). ``excluded`` is the current state.
    """

    name = "chi2_reconfig"

    def __init__(self, false_alarm_prob: float = 1e-3, readmit_passes: int = 1):
        super().__init__(false_alarm_prob)
        if readmit_passes < 1:
            raise ValueError("readmit_passes must be >= 1")
        self.readmit_passes = int(readmit_passes)
        self.excluded = False
        self._passes = 0

    def reset(self) -> None:
        self.excluded = False
        self._passes = 0

    def flags(self, standardised, S, nis):
        m = np.asarray(standardised).shape[0]
        thr = chi2_threshold(self.false_alarm_prob, m)
        failed = float(nis) > thr  # seed 004: chi2 residual test of the whole innovation
        if failed:
            self.excluded = True
            self._passes = 0
        elif self.excluded:
            self._passes += 1
            if self._passes >= self.readmit_passes:
                self.excluded = False
        return FaultDecision(
            np.full(m, float(nis)), np.full(m, thr), np.full(m, failed), np.full(m, self.excluded)
        )


FAULT_TESTS: dict[str, type[FaultTest]] = {
    cls.name: cls for cls in (NoFaultHandling, PerObservation, PerSource, SubsystemIsolation, Chi2Reconfig)
}


def make_fault_test(name: str, false_alarm_prob: float = 1e-3) -> FaultTest:
    """Registry: a new (possibly stateful) test by its config name."""
    try:
        return FAULT_TESTS[name](false_alarm_prob)
    except KeyError:
        raise ValueError(f"unknown fault handling {name!r}; known: {sorted(FAULT_TESTS)}") from None


__all__ = ["FaultTest", "FaultDecision", "FAULT_TESTS", "make_fault_test", "chi2_threshold"]
