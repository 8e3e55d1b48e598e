"""The integrity evaluation counts exclusions of satellites no fault touched (service/evaluation.py
``integrity_metrics``: ``healthy_exclusions``): the paper's classes hide them, since an epoch with the
faulty satellite excluded counts as ``detected`` whatever else is excluded (found on
``seed001_ramp --seed 1001``: C01 excluded 5.5 s into a C03 ramp, docs/seed001.md)."""

from __future__ import annotations

import numpy as np

from fednav.service.evaluation import FaultWindow, integrity_metrics
from fednav.service.messages import Integrity

T0 = 1_000_000.0


def _epoch(t_rel: float, excluded: list[str], detected: bool = False) -> tuple[Integrity, np.ndarray]:
    msg = Integrity(
        t=T0 + t_rel,
        pipeline="tc",
        phase="npa",
        hpl_m=10.0,
        vpl_m=12.0,
        hal_m=556.0,
        val_m=None,
        alarm=False,
        available=True,
        detected=detected,
        excluded=excluded,
        satellites=[],
    )
    return msg, np.zeros(3)


def test_exclusions_of_healthy_satellites_are_listed_and_the_faulty_ones_are_not():
    ramp = FaultWindow(start_s=10.0, end_s=40.0, satellites=frozenset({"C03"}))
    run = [_epoch(t, []) for t in (8.0, 9.0)]
    run += [_epoch(11.0, ["C03"], detected=True)]  # the faulty satellite: not counted
    run += [_epoch(t, ["C03"]) for t in (12.0, 13.0)]
    run += [_epoch(14.0, ["C03", "C01"], detected=True)]  # a healthy one during the fault: counted
    run += [_epoch(t, ["C03", "C01"]) for t in (15.0, 16.0)]  # still out: not a new exclusion
    run += [_epoch(45.0, ["C01"])]  # C03 re-admitted
    run += [_epoch(46.0, ["C01", "C03"])]  # C03 again within TTA (10 s) of its fault's end: not counted
    run += [_epoch(47.0, ["C03"])]
    run += [_epoch(48.0, ["C03", "C01"])]  # C01 out a second time: counted again
    g = integrity_metrics([ramp], T0, 100.0, [run, [_epoch(5.0, ["C28"])]])
    assert g["healthy_exclusions"] == [
        {"run": 0, "t_s": 14.0, "satellite": "C01"},
        {"run": 0, "t_s": 48.0, "satellite": "C01"},
        {"run": 1, "t_s": 5.0, "satellite": "C28"},
    ]
    assert g["healthy_exclusion_count"] == 3
    # the classes are as before: the fault epochs with C03 excluded count as detected
    assert g["counts"]["detected"] == 6 and g["counts"]["missed"] == 0


def test_a_faulty_satellite_excluded_after_its_fault_beyond_tta_is_healthy_again():
    fault = FaultWindow(start_s=10.0, end_s=20.0, satellites=frozenset({"C03"}))
    g = integrity_metrics([fault], T0, 100.0, [[_epoch(29.0, ["C03"])], [_epoch(31.0, ["C03"])]])
    assert g["healthy_exclusions"] == [{"run": 1, "t_s": 31.0, "satellite": "C03"}]
