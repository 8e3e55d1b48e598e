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

Re-admission (:class:`ExclusionBook`)
------------------------------------
An excluded satellite is re-admitted after ``readmit_after_s`` of continuous health: every epoch
it is observed, its rows are tested against the current main filter (standardised innovation of
each row within the single-test multiplier); a failure, or an epoch with the satellite missing,
restarts the clock. Re-admitted satellites enter the bank like rising satellites.
"""

from __future__ import annotations

from dataclasses import dataclass, field

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


__all__ = [
    "PHASES",
    "Assessment",
    "ExclusionBook",
    "PhaseLimits",
    "assess",
    "limits",
    "n_families",
    "uses_vertical",
]
