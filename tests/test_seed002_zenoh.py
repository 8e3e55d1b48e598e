"""Seed 002 over real processes: fednav-service and fednav-sim on loopback Zenoh.

A shortened seed002_wing scenario (20 s straight flight, one adaptive pipeline) is written to
tmp_path. The simulator publishes four IMU nodes (``master``, ``wing1``..``wing3``) into one
vehicle, GNSS, init and truth (also the nodes' AlignmentTruth); a plain Zenoh client (client mode,
multicast off, raw JSON: no fednav decoding) receives the per-node Alignment messages on
``fednav/v1/nav/{pipeline}/alignment/{node}``; the recording verifies and reads back.
"""

from __future__ import annotations

import re
import subprocess
import sys
from pathlib import Path

import pytest

from .plain_zenoh import run_and_collect

pytestmark = pytest.mark.integration
ROOT = Path(__file__).resolve().parents[1]
WING = ROOT / "simulators" / "scenarios" / "seed002_wing.toml"
RERUN = Path(sys.executable).with_name("rerun")
DURATION_S = 20.0


def short_wing(tmp_path: Path) -> Path:
    text = WING.read_text()
    text = re.sub(r"(?m)^duration_s = 300\.0$", f"duration_s = {DURATION_S}", text, count=1)
    text = re.sub(r"(?s)\[\[segments\]\].*?(?=\n\[imu\])", "", text)
    text = re.sub(r"(?m)^turbulence = .*$", "turbulence = []", text)
    text = re.sub(
        r"(?s)pipelines = \[.*?\n\]",
        'pipelines = [{ name = "ta", kind = "transfer_alignment", filter = "akf", fading = true }]',
        text,
    )
    text = text.replace('name = "seed002_wing"', 'name = "seed002_wing_short"')
    p = tmp_path / "seed002_wing_short.toml"
    p.write_text(text)
    return p


@pytest.fixture(scope="module")
def wing_run(tmp_path_factory):
    tmp = tmp_path_factory.mktemp("seed002")
    scenario = short_wing(tmp)
    from fednav.simulators.scenario import load_scenario

    sc = load_scenario(scenario)
    assert sc.duration_s == DURATION_S and sc.wing is not None and len(sc.wing.nodes) == 3
    rrd = tmp / "wing.rrd"
    return run_and_collect(scenario, "fednav/*/nav/*/alignment/*", seed=2, rrd=rrd) | {"rrd": rrd}


def test_alignment_messages_per_node_arrive_over_zenoh(wing_run):
    items = wing_run["items"]
    assert wing_run["rc"] == 0, wing_run["out"]
    keys = {k for k, _ in items}
    assert keys == {f"fednav/v1/nav/ta/alignment/wing{i}" for i in (1, 2, 3)}, keys
    for node in ("wing1", "wing2", "wing3"):
        msgs = [d for k, d in items if k.endswith("/" + node)]
        assert len(msgs) >= 0.9 * DURATION_S * 10, f"{node}: only {len(msgs)} messages (10 Hz)"
        ts = [d["t"] for d in msgs]
        assert ts == sorted(ts)
        last = msgs[-1]
        assert last["node"] == node and last["pipeline"] == "ta"
        for key in ("mount_deg", "misalignment_std_deg", "lever_arm_m", "lever_arm_std_m", "flexure_deg"):
            assert len(last[key]) == 3, key
        # 20 s of straight flight: the level misalignment converges from 30 arcmin (velocity
        # matching under gravity); the heading one and the lever arm stay near their priors
        # (separable from the mounting angle only by manoeuvres: honest sigmas, no fake convergence)
        sx, sy, sz = (v * 60.0 for v in last["misalignment_std_deg"])
        assert sx < 1.0 and sy < 1.0 and sz > 5.0
        assert 0.05 < last["lever_arm_std_m"][0] <= 0.2 + 1e-9
        assert len(last["r_std"]) == 9 and last["fading"] >= 1.0


def test_recording_holds_alignment_errors_with_bounds(wing_run):
    rrd = wing_run["rrd"]
    res = subprocess.run([str(RERUN), "rrd", "verify", str(rrd)], capture_output=True, text=True, timeout=120)
    assert res.returncode == 0, res.stderr
    from fednav.dashboards.inspect import read_series

    _, data = read_series(rrd)
    err = [p for p in data if "/ta/alignment_error/" in p]
    assert any(p.endswith("wing3.lever_x") for p in err), err[:10]
    assert any(p.endswith("wing1.misalignment_z_p3s") for p in err)
    assert any("/ta/alignment_adaptive/wing2.r_std_0" in p for p in data)
    s = data[next(p for p in err if p.endswith("wing2.misalignment_x"))]
    b = data[next(p for p in err if p.endswith("wing2.misalignment_x_p3s"))]
    assert len(s.values) >= 0.9 * DURATION_S * 10 and len(b.values) == len(s.values)
