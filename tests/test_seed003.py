"""Seed 003 (He, Nie, Wu 2011): outlier injection, the IMM pipeline against the tightly coupled KF
on the same stream, and a short outlier run of the paper's experiment (docs/seed003.md)."""

from __future__ import annotations

import numpy as np
import pytest

from fednav.service import config as config_mod
from fednav.simulators.evaluate import run_once
from fednav.simulators.scenario import parse_scenario
from fednav.simulators.stream import Simulation

from .scenario_utils import shortened

T0 = 1_300_000_000.0


def test_outlier_windows_hit_about_15_percent_of_epochs_on_published_satellites_and_show_in_truth():
    sc = shortened("seed003_outliers.toml", 40.0)  # window 1 (3/5/8 sigma) moved to 0-40 s
    data = sc.model_dump(mode="json")
    data["faults"] = [dict(load_outlier_window("seed003_outliers.toml"), start_s=0.0, duration_s=40.0)]
    sc = parse_scenario(data, "seed003_outliers (short)")
    sim = Simulation(sc, seed=3)
    truths = [(m.t, m.faults) for k, m in sim if k.endswith("/truth")]
    hits = {round(t - T0, 6): f for t, f in truths if f}
    raw = {round(r.t_gps_s - T0, 6): r for r in sim.truth.gnss_raw}
    assert len(raw) == 400
    frac = len(hits) / len(raw)
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
    sc = shortened("seed003_outliers.toml", 40.0)
    data = sc.model_dump(mode="json")
    data["faults"] = [load_outlier_window("seed003_outliers.toml")]
    data["faults"][0]["channels"] = ["*.clock"]
    with pytest.raises(ValueError, match="channel patterns"):
        parse_scenario(data)
    data["faults"][0]["channels"] = ["*.pseudorange"]
    data["faults"][0]["fraction"] = 1.5
    with pytest.raises(ValueError, match="fraction"):
        parse_scenario(data)


def test_imm_with_one_model_equals_the_tightly_coupled_kf_on_the_same_stream():
    sc = shortened("seed003_outliers.toml", 60.0)
    data = sc.model_dump(mode="json")
    data["faults"] = [dict(load_outlier_window("seed003_outliers.toml"), start_s=20.0, duration_s=40.0)]
    sc = parse_scenario(data, "seed003_outliers (short)")
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
    assert a.shape == b.shape and len(a) > 500
    assert np.abs(a - b).max() < 1e-10  # metres, m/s, rad
    np.testing.assert_allclose(sink.records["tc"].nees, sink.records["kf1"].nees, rtol=1e-8)


def test_imm_pipelines_get_the_imm_dashboard():
    from fednav.dashboards.blueprints import build_blueprint, family_of, vehicle_tabs

    assert family_of("imm_tightly_coupled") == "imm"
    tabs = vehicle_tabs("v1", {"tc": "tightly_coupled", "tc_imm": "imm_tightly_coupled"})
    names = [getattr(t, "name", None) for t in tabs.contents]
    assert "tc_imm: IMM" in names and "Integrity" in names
    build_blueprint("v1", {"tc_imm": "imm_tightly_coupled"})


def short_outlier_run(seed: int, duration_s: float = 45.0, outliers: bool = True):
    """seed003_outliers_obs cut to ``duration_s`` with its first window (3/5/8 sigma, 15 % of the
    pseudoranges) moved to 15 s - end (``outliers = False``: no window, same noise); KF, IMM
    (both likelihoods) and the chi-square gate."""
    sc = shortened("seed003_outliers_obs.toml", duration_s)
    data = sc.model_dump(mode="json")
    first = load_outlier_window()
    data["faults"] = [dict(first, start_s=15.0, duration_s=duration_s - 15.0)] if outliers else []
    sc = parse_scenario(data, "seed003_outliers_obs (short)")
    sink, sim = run_once(sc, seed)
    return sc, sink, sim


def load_outlier_window(name: str = "seed003_outliers_obs.toml") -> dict:
    """The first [[faults]] table (3/5/8 sigma window) of a seed 003 scenario file."""
    import tomllib

    from .scenario_utils import SCENARIOS

    return tomllib.loads((SCENARIOS / name).read_text())["faults"][0]


def test_short_outlier_run_imm_and_gate_resist_outliers_the_kf_does_not():
    """One seeded short run with and without outliers, same noise (the Monte Carlo figures are
    docs/seed003.md's). The outlier-induced error of a pipeline is the RMS of its position with
    outliers minus its position without, from 20 s (paired: convergence cancels). Measured on
    seeds 1/2/3, as a share of the KF's: IMM paper likelihood 0.18/0.12/0.25, IMM Gaussian
    0.37/0.27/0.70, IMM Gaussian with the selection correction 0.20/0.22/0.29, gate 0.48/0.59/0.41.
    Tolerances: every 8-sigma outlier is down-weighted by C = 100 in a fault model (97 % rejected
    by the gate); each share at most 0.85; the normal model's probability (Gaussian likelihood) at
    outlier epochs below half of that at clean epochs (measured 0.009 vs 0.38). Clean run, from
    20 s: the normal model's mean probability is 0.58 with the Gaussian likelihood (the fault
    models pick their rows after seeing the residuals) and 0.996 with the selection correction
    (seed 1); bounds 0.8 and 0.95."""
    from fednav.service.messages import ImmModels

    sc, clean, _ = short_outlier_run(seed=1, duration_s=40.0, outliers=False)
    sc, sink, sim = short_outlier_run(seed=1, duration_s=40.0)
    T0 = sc.t0_gps_s
    hits: dict[float, list[tuple[str, float]]] = {}
    for r in sim.truth.gnss_raw:
        for i, sid in enumerate(r.ids):
            if r.pseudorange_fault_m[i] != 0.0:
                hits.setdefault(round(r.t_gps_s, 3), []).append((f"{sid}.pr", r.pseudorange_fault_m[i]))
    assert len(hits) > 100

    def induced(name: str) -> float:
        t = np.array(sink.records[name].t) - T0
        assert np.array_equal(t, np.array(clean.records[name].t) - T0)
        d = (np.array(sink.records[name].err) - np.array(clean.records[name].err))[t >= 20.0, :3]
        return float(np.sqrt(np.mean(np.sum(d**2, axis=1))))

    kf = induced("tc")
    assert kf > 0.3  # metres: the KF follows the outliers
    for name in ("tc_imm", "tc_imm_gauss", "tc_imm_sel", "tc_gate"):
        assert induced(name) <= 0.85 * kf, name
        msgs = [m for m in sink.records[name].outputs if isinstance(m, ImmModels)]
        caught = []
        for m in msgs:
            for lab, f in hits.get(round(m.t, 3), []):
                if lab in m.rows and abs(f) >= 39.0:
                    j = m.rows.index(lab)
                    caught.append(max(rs[j] for rs in m.r_scale) == 100.0 or lab in m.rejected)
        # the gate tests the whole innovation vector: an 8-sigma row partly absorbed by the clock
        # can pass it (measured 1 of 118 on seed 1, 1 of 122 on seed 2)
        assert len(caught) > 30 and np.mean(caught) >= (0.97 if name == "tc_gate" else 1.0), name
    gauss = [m for m in sink.records["tc_imm_gauss"].outputs if isinstance(m, ImmModels)]
    hit_mu = np.mean([m.probabilities[0] for m in gauss if round(m.t, 3) in hits])
    clean_mu = np.mean([m.probabilities[0] for m in gauss if round(m.t, 3) not in hits])
    assert hit_mu < 0.5 * clean_mu

    def normal_mu_clean(name: str) -> float:
        msgs = [m for m in clean.records[name].outputs if isinstance(m, ImmModels) and m.t - T0 >= 20.0]
        return float(np.mean([m.probabilities[0] for m in msgs]))

    assert normal_mu_clean("tc_imm_gauss") < 0.8 < 0.95 < normal_mu_clean("tc_imm_sel")
