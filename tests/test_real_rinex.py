"""Tightly coupled raw-GNSS pipeline on the real Wuhan 2015 RINEX data (docs/real_rinex.md).

Skips without ../shared/data. One evaluation (about 20-30 s) checks:
- the static scatter of ours (the pipeline in GNSS-only mode, filtered) is within 1.5x of the
  gnss-lib-py WLS peer's (measured: 0.62 vs 0.89 m and 0.31 vs 0.46 m horizontal) -- or, without
  gnss-lib-py installed, below 1.5x the peer's measured values (1.3 m and 0.7 m horizontal);
- our epoch-wise least squares with the service's corrections equals the peer to < 0.3 m RMS in the
  drive (measured 0.05 m): the same orbits, clocks, group delay, Sagnac, troposphere size, weights;
- ours minus peer in the drive: horizontal RMS < 2.5 m (measured 1.96 m with MHSS exclusion, 1.27 m
  without; the filter smooths the metre-level epoch noise of the snapshot solutions, and where a
  low satellite (G25) pulls the snapshot solutions by ~10 m while the car stands MHSS excludes it
  and the peer keeps it, see the docs);
- MHSS protection levels are reported on every epoch after the first minute and are finite and
  larger than the static scatter (HPL median 10.9 m).
"""

from __future__ import annotations

import importlib.util

import pytest

from fednav.simulators.rinex_eval import evaluate_rinex

from .real_data import WUHAN

HAVE_PEER = importlib.util.find_spec("gnss_lib_py") is not None
PEER_MEASURED_H_M = {"static_start": 0.89, "static_end": 0.46}


@pytest.fixture(scope="module")
def result():
    if not (WUHAN / "01.15o").exists():
        pytest.skip(f"real data {WUHAN} absent (../shared/data not available here)")
    return evaluate_rinex(WUHAN)


def test_segments_and_conversion(result):
    assert result["epochs"] == 2285 and not result["dropped"]
    a0, a1 = result["static_start_s"]
    b0, b1 = result["static_end_s"]
    assert a0 == 0.0 and 550.0 < a1 < 700.0  # ~10 min static
    assert 1500.0 < b0 < 1800.0 and b1 == 2284.0  # ~16 min drive, static end


@pytest.mark.parametrize("part", ["static_start", "static_end"])
def test_static_scatter_against_the_peer(result, part):
    ours = result[f"ours_{part}"]
    assert ours is not None and ours["n"] > 500
    if HAVE_PEER:
        peer = result[f"peer_{part}"]
        assert ours["H"] <= 1.5 * peer["H"]
        assert ours["U"] <= 1.5 * peer["U"]
    else:
        assert ours["H"] <= 1.5 * PEER_MEASURED_H_M[part]


@pytest.mark.skipif(not HAVE_PEER, reason="gnss-lib-py not installed (pip install -e '.[peer]')")
def test_drive_difference_to_the_peer(result):
    assert result["drive_ours_wls_minus_peer"]["H"] < 0.3
    assert result["drive_ours_wls_minus_peer"]["U"] < 0.5
    assert result["drive_ours_minus_peer"]["H"] < 2.5
    assert result["drive_ours_minus_peer"]["n"] > 900


def test_mhss_protection_levels(result):
    m = result["mhss"]
    assert m["epochs_with_pl"] == result["epochs"] - 60
    assert 0.0 < m["hpl_median_m"] < m["hpl_max_m"] < 100.0
    assert 0.0 < m["vpl_median_m"] < m["vpl_max_m"] < 100.0
    assert m["hpl_median_m"] > 3.0 * result["ours_static_start"]["H"]
