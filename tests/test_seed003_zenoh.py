"""Seed 003 over real processes: fednav-service and fednav-sim on loopback Zenoh.

A shortened seed003_outliers scenario (20 s straight drive, outliers on 15 % of the epochs from
5 s) is written to tmp_path, with the KF and the IMM (paper likelihood); a plain Zenoh client
(client mode, multicast off, raw JSON) subscribed to ``fednav/**/models`` receives the ImmModels
messages; the recording verifies and reads back with Rerun's reader (probabilities per model).
"""

from __future__ import annotations

import re
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from .plain_zenoh import run_and_collect

pytestmark = pytest.mark.integration
ROOT = Path(__file__).resolve().parents[1]
SCENARIO = ROOT / "simulators" / "scenarios" / "seed003_outliers.toml"
RERUN = Path(sys.executable).with_name("rerun")
T0 = 1_300_000_000.0
DURATION_S = 20.0
MODELS = ["normal", "largest", "two_largest", "above_c"]


def short_outliers(tmp_path: Path) -> Path:
    text = SCENARIO.read_text()
    text = re.sub(r"(?m)^duration_s = \d+(\.\d*)?$", f"duration_s = {DURATION_S}", text, count=1)
    text = re.sub(r"(?s)\[\[segments\]\].*?(?=\n\[)", "", text)
    # keep the first outlier window only, from 5 s to the end
    text = re.sub(r"(?s)\[\[faults\]\].*?(?=\n\[service\])", "", text)
    text = text.replace(
        "[service]\n",
        '[[faults]]\nsensor = "gnss_raw"\nkind = "outliers"\nstart_s = 5.0\nduration_s = 15.0\n'
        'channels = ["*.pseudorange"]\nsigma = 5.0\nmultiples = [3.0, 5.0, 8.0]\nfraction = 0.15\n\n'
        "[service]\n",
        1,
    )
    text = re.sub(
        r"(?s)pipelines = \[.*?\n\]",
        "pipelines = [\n"
        '  { name = "tc", kind = "tightly_coupled", integrity = false, elevation_mask_deg = 5.0 },\n'
        '  { name = "tc_imm", kind = "imm_tightly_coupled", likelihood = "paper",'
        " selection_correction = false },\n]",
        text,
        count=1,
    )
    text = text.replace('name = "seed003_outliers"', 'name = "seed003_outliers_short"')
    p = tmp_path / "seed003_outliers_short.toml"
    p.write_text(text)
    return p


@pytest.fixture(scope="module")
def imm_run(tmp_path_factory):
    tmp = tmp_path_factory.mktemp("seed003")
    scenario = short_outliers(tmp)
    from fednav.simulators.scenario import load_scenario

    sc = load_scenario(scenario)  # the variant is a valid scenario
    assert sc.duration_s == DURATION_S and [f.kind for f in sc.faults] == ["outliers"]
    rrd = tmp / "seed003.rrd"
    out = run_and_collect(scenario, "fednav/**/models", seed=3, rrd=rrd)
    out["rrd"] = rrd
    return out


def test_models_topic_reaches_a_plain_zenoh_client(imm_run):
    items = imm_run["items"]
    assert imm_run["rc"] == 0, imm_run["out"]
    assert {k for k, _ in items} == {"fednav/v1/nav/tc_imm/models"}  # the KF publishes none
    msgs = [d for _, d in items]
    assert len(msgs) >= 0.95 * DURATION_S * 10, f"only {len(msgs)} ImmModels messages (10 Hz GNSS)"
    ts = [d["t"] for d in msgs]
    assert ts == sorted(ts)
    for d in msgs:
        assert d["models"] == MODELS and d["likelihood"] == "paper"
        assert abs(sum(d["probabilities"]) - 1.0) < 1e-9 and min(d["probabilities"]) >= 0.0
        m = len(d["rows"])
        assert m >= 8 and len(d["standardised_residual"]) == m
        assert len(d["r_scale"]) == len(d["h_scale"]) == 4
        assert all(len(r) == m for r in d["r_scale"])
        assert all(f == 1.0 for f in d["r_scale"][0])  # the normal model never down-weights
        assert sum(f != 1.0 for f in d["r_scale"][1]) == 1  # "largest" touches one row
        assert all(re.fullmatch(r"[GC]\d\d\.(pr|rr)", lab) for lab in d["rows"])
    # an 8-sigma outlier (40 m) stands out: some epoch down-weights a row by C = 100
    assert any(100.0 in d["r_scale"][3] for d in msgs if d["t"] - T0 >= 5.0)


def test_recording_reads_back_with_model_probabilities(imm_run):
    rrd = imm_run["rrd"]
    res = subprocess.run([str(RERUN), "rrd", "verify", str(rrd)], capture_output=True, text=True, timeout=120)
    assert res.returncode == 0, res.stderr
    from fednav.dashboards.inspect import read_series

    info, data = read_series(rrd)
    assert info["blueprints"] >= 1
    probs = {m: data[f"/v1/tc_imm/imm/prob/{m}"] for m in MODELS}
    n = len(probs["normal"])
    assert n >= 0.95 * DURATION_S * 10
    total = sum(np.asarray(s.values) for s in probs.values())
    np.testing.assert_allclose(total, 1.0, atol=1e-9)
    assert "/v1/tc_imm/imm/downweighted/largest" in data and "/v1/tc_imm/imm/rejected_rows" in data
    # the injected outliers are in the recording too (truth)
    assert np.asarray(data["/v1/truth/fault_channels"].values).max() == 1.0
