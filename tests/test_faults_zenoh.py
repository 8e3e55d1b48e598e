"""Seed 000 fault handling over real processes: fednav-service and fednav-sim on loopback Zenoh.

A compressed seed000_faults variant (70 s straight cruise; the paper's position+velocity step at
20-25 s and its velocity-only step at 40-50 s, same magnitudes) is written to tmp_path; the
service runs fed_vector (per-observation isolation, "method 2") and fed_vector_sysiso (whole
subsystem, "method 1") side by side and records to an .rrd. A plain Zenoh client (raw JSON, no
fednav decoding) collects the Faults messages; the recording is read back with Rerun's reader.
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
FAULTS = ROOT / "simulators" / "scenarios" / "seed000_faults.toml"
RERUN = Path(sys.executable).with_name("rerun")
T0 = 1_300_000_000.0
DURATION_S = 70.0
BOTH = (20.0, 25.0)  # position AND velocity step
VEL = (40.0, 50.0)  # velocity-only step
POS_LABELS = {"pos_e", "pos_n", "pos_u"}
VEL_LABELS = {"vel_e", "vel_n", "vel_u"}


def compressed_faults(tmp_path: Path) -> Path:
    text = FAULTS.read_text()
    text = re.sub(r"(?m)^duration_s = 800\.0$", f"duration_s = {DURATION_S}", text, count=1)
    text = re.sub(r"(?s)\[\[segments\]\].*?(?=\n\[)", "", text)  # straight cruise
    text = text.replace('name = "seed000_faults"', 'name = "seed000_faults_compressed"')
    blocks = text.split("\n[[faults]]")
    assert len(blocks) == 4, "the shipped scenario has three fault blocks"
    both = (
        blocks[1]
        .replace("start_s = 300.0", f"start_s = {BOTH[0]}")
        .replace("duration_s = 10.0", f"duration_s = {BOTH[1] - BOTH[0]}")
    )
    vel = (
        blocks[2]
        .replace("start_s = 450.0", f"start_s = {VEL[0]}")
        .replace("duration_s = 50.0", f"duration_s = {VEL[1] - VEL[0]}")
    )
    text = "\n[[faults]]".join([blocks[0], both, vel])
    keep = ("fed_vector", "fed_vector_sysiso")
    text = re.sub(r'(?m)^  \{ name = "(\w+)".*\n', lambda m: m.group(0) if m.group(1) in keep else "", text)
    p = tmp_path / "seed000_faults_compressed.toml"
    p.write_text(text)
    return p


@pytest.fixture(scope="module")
def faults_run(tmp_path_factory):
    tmp = tmp_path_factory.mktemp("seed000")
    scenario = compressed_faults(tmp)
    from fednav.simulators.scenario import load_scenario

    sc = load_scenario(scenario)  # the variant is a valid scenario
    assert [(f.start_s, f.duration_s) for f in sc.faults] == [(BOTH[0], 5.0), (VEL[0], 10.0)]
    assert [p["name"] for p in sc.service["pipelines"]] == ["fed_vector", "fed_vector_sysiso"]
    rrd = tmp / "faults.rrd"
    return run_and_collect(scenario, "fednav/**/faults", seed=3, rrd=rrd) | {"rrd": rrd}


def _bds(msgs, pipeline, t0, t1):
    """(t, INS/BDS subsystem report) of ``pipeline`` for aiding epochs with t0 <= t - T0 < t1."""
    out = []
    for d in msgs:
        if d["pipeline"] != pipeline or not t0 <= d["t"] - T0 < t1:
            continue
        for s in d["subsystems"]:
            if s["name"] == "INS/BDS":
                out.append((d["t"] - T0, s))
    return out


def test_faults_messages_arrive_per_pipeline_with_shares(faults_run):
    assert faults_run["rc"] == 0, faults_run["out"]
    items = faults_run["items"]
    keys = {k for k, _ in items}
    assert keys == {"fednav/v1/nav/fed_vector/faults", "fednav/v1/nav/fed_vector_sysiso/faults"}
    msgs = [d for _, d in items]
    for name in ("fed_vector", "fed_vector_sysiso"):
        mine = [d for d in msgs if d["pipeline"] == name]
        # one report per aiding message: BDS fix and star attitude at 1 Hz each
        assert len(mine) >= 2 * (DURATION_S - 2), (name, len(mine))
        bds = _bds(msgs, name, 0.0, DURATION_S)
        assert len(bds) >= DURATION_S - 2
        assert {o["label"] for o in bds[0][1]["observations"]} == POS_LABELS | VEL_LABELS
        for d in mine:
            shares = np.array(list(d["sharing"].values()))
            assert shares.shape == (2, 15)
            assert np.all(shares > 0.0)
            np.testing.assert_allclose(shares.sum(axis=0), 1.0, atol=1e-9)  # conservation per state


def test_position_and_velocity_step_is_isolated_by_both_methods(faults_run):
    msgs = [d for _, d in faults_run["items"]]
    for name in ("fed_vector", "fed_vector_sysiso"):
        inside = _bds(msgs, name, *BOTH)
        assert len(inside) >= 4
        for _, s in inside:
            assert all(o["flagged"] and o["isolated"] for o in s["observations"]), (name, s)
    # the subsystem-level method reports the whole subsystem isolated
    assert all(s["isolated"] for _, s in _bds(msgs, "fed_vector_sysiso", *BOTH))


def test_velocity_only_step_keeps_the_healthy_position_rows_in_method_2(faults_run):
    msgs = [d for _, d in faults_run["items"]]
    m2 = _bds(msgs, "fed_vector", *VEL)
    m1 = _bds(msgs, "fed_vector_sysiso", *VEL)
    assert len(m2) >= 9 and len(m1) >= 9
    for _, s in m2:  # per-observation isolation: only the faulty velocity rows go
        obs = {o["label"]: o for o in s["observations"]}
        assert all(obs[k]["isolated"] for k in VEL_LABELS), s
        assert not any(obs[k]["isolated"] for k in POS_LABELS), s
        assert not s["isolated"]
    for _, s in m1:  # subsystem isolation: everything goes
        assert s["isolated"] and all(o["isolated"] for o in s["observations"]), s
    # outside the fault windows healthy fixes are used (alpha 1e-3 per test: at most a stray flag)
    quiet = [s for _, s in _bds(msgs, "fed_vector", 30.0, 40.0) + _bds(msgs, "fed_vector", 55.0, DURATION_S)]
    flagged = sum(o["flagged"] for s in quiet for o in s["observations"])
    assert len(quiet) >= 20 and flagged <= 2


def test_recording_holds_the_fault_tests_and_shares(faults_run):
    rrd = faults_run["rrd"]
    res = subprocess.run([str(RERUN), "rrd", "verify", str(rrd)], capture_output=True, text=True, timeout=120)
    assert res.returncode == 0, res.stderr
    from fednav.dashboards.inspect import inspect_rrd

    summary = inspect_rrd(rrd)
    m2 = summary["faults"]["fed_vector"]  # (one vehicle: keyed by pipeline; paths sanitise "/")
    m1 = summary["faults"]["fed_vector_sysiso"]
    # velocity rows isolated in both windows (5 + 10 epochs), position rows only in the first (5)
    for lab in VEL_LABELS:
        assert 14 <= m2["observations"][f"INS_BDS/{lab}"]["isolated"] <= 17, m2["observations"]
    for lab in POS_LABELS:
        assert 4 <= m2["observations"][f"INS_BDS/{lab}"]["isolated"] <= 7, m2["observations"]
    assert 14 <= m1["subsystem_isolated_epochs"]["INS_BDS"] <= 17
    assert 4 <= m2["subsystem_isolated_epochs"]["INS_BDS"] <= 7  # only while every row is faulty
    assert m1["subsystem_isolated_epochs"]["INS_CNS"] == m2["subsystem_isolated_epochs"]["INS_CNS"] == 0
    for shares in (m1["sharing_last"], m2["sharing_last"]):
        assert set(shares) == {"INS_BDS", "INS_CNS"}
        for j in map(str, range(15)):
            assert abs(shares["INS_BDS"][j] + shares["INS_CNS"][j] - 1.0) < 1e-9
