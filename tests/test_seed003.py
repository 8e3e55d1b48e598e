"""Seed 003 (He, Nie, Wu 2011): outlier injection, the IMM pipeline against the tightly coupled KF
on the same stream, and a short outlier run of the paper's experiment (docs/seed003.md)."""

from __future__ import annotations

import numpy as np
import pytest

from service import config as config_mod
from simulators.evaluate import run_once
from simulators.scenario import parse_scenario
from simulators.stream import Simulation

from .scenario_utils import shortened

T0 = 1_300_000_000.0


def test_outlier_windows_hit_about_15_percent_of_epochs_on_published_satellites_and_show_in_truth():
    sc = shortened("seed003_outliers.toml", 140.0)  # window 1 (100-300 s) cut to 100-140 s
    sim = Simulation(sc, seed=3)
    truths = [(m.t, m.faults) for k, m in sim if k.endswith("/truth")]
    hits = {round(t - T0, 6): f for t, f in truths if f}
    raw = {round(r.t_gps_s - T0, 6): r for r in sim.truth.gnss_raw}
    in_window = [t for t in raw if 100.0 <= t < 140.0]
    assert len(in_window) == 400
    assert all(100.0 <= t < 140.0 for t in hits)  # nothing outside the window
    frac = len(hits) / len(in_window)
    assert 0.10 <= frac <= 0.20, frac  # 15 % per epoch, 400 epochs: sd 1.8 %
    sizes = set()
    for t, faults in hits.items():
        (f,) = faults
        assert f.kind == "outliers" and f.sensor == "gnss_raw" and len(f.channels) == 1
        sat = f.channels[0].removesuffix(".pseudorange")
        r = raw[t]
        assert sat in r.ids  # a published satellite
        i = r.ids.index(sat)
        sizes.add(round(abs(r.pseudorange_fault_m[i]) / 5.0, 9))
        others = np.delete(r.pseudorange_fault_m, i)
        assert not others.any() and not r.range_rate_fault_mps.any()
    assert sizes == {3.0, 5.0, 8.0}
    # every epoch without a hit is clean
    assert all(not r.pseudorange_fault_m.any() for t, r in raw.items() if t not in hits)
    # seeded: the same run again gives the same outliers
    again = [(m.t, m.faults) for k, m in Simulation(sc, seed=3) if k.endswith("/truth")]
    assert again == truths


def test_outlier_fault_validation():
    sc = shortened("seed003_outliers.toml", 140.0)
    data = sc.model_dump(mode="json")
    data["faults"][0]["channels"] = ["*.clock"]
    with pytest.raises(ValueError, match="channel patterns"):
        parse_scenario(data)
    data["faults"][0]["channels"] = ["*.pseudorange"]
    data["faults"][0]["fraction"] = 1.5
    with pytest.raises(ValueError, match="fraction"):
        parse_scenario(data)


def test_imm_with_one_model_equals_the_tightly_coupled_kf_on_the_same_stream():
    sc = shortened("seed003_outliers.toml", 130.0)
    cfg = config_mod.from_dict(
        {
            **sc.service,
            "pipelines": [
                {"name": "tc", "kind": "tightly_coupled", "integrity": False, "elevation_mask_deg": 5.0},
                {"name": "kf1", "kind": "imm_tightly_coupled", "models": ["normal"]},
            ],
        }
    )
    sink, _ = run_once(sc, 3, cfg)
    a, b = np.array(sink.records["tc"].err), np.array(sink.records["kf1"].err)
    assert a.shape == b.shape and len(a) > 1000
    assert np.abs(a - b).max() < 1e-10  # metres, m/s, rad
    np.testing.assert_allclose(sink.records["tc"].nees, sink.records["kf1"].nees, rtol=1e-8)
