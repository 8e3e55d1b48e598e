"""Seed 004 reconfiguration over real processes: fednav-service and fednav-sim on loopback Zenoh.

A compressed seed004_usbl_fault variant (60 s straight, USBL multipath 20-40 s) is written to
tmp_path; the service runs fed_edop (federated INS/USBL + INS/DVL, chi2 reconfiguration, alpha
1e-6) beside the unscreened centralised comparator and records to an .rrd. A plain Zenoh client
(raw JSON, no fednav decoding) collects the Faults messages; the recording is read back with
Rerun's reader.
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
SCENARIO = ROOT / "simulators" / "scenarios" / "seed004_usbl_fault.toml"
RERUN = Path(sys.executable).with_name("rerun")
T0 = 1_300_000_000.0
DURATION_S = 60.0
FAULT = (20.0, 40.0)


def compressed(tmp_path: Path) -> Path:
    text = SCENARIO.read_text()
    text = re.sub(r"(?m)^duration_s = 1000\.0$", f"duration_s = {DURATION_S}", text, count=1)
    text = text.replace('name = "seed004_usbl_fault"', 'name = "seed004_usbl_fault_compressed"')
    text = text.replace(
        "start_s = 500.0\nduration_s = 500.0", f"start_s = {FAULT[0]}\nduration_s = {FAULT[1] - FAULT[0]}"
    )
    keep = ("fed_edop", "centralized")
    text = re.sub(r'(?m)^  \{ name = "(\w+)".*\n', lambda m: m.group(0) if m.group(1) in keep else "", text)
    text = text.replace('sharing = "edop",', 'sharing = "edop", false_alarm_prob = 1e-6,')
    p = tmp_path / "seed004_usbl_fault_compressed.toml"
    p.write_text(text)
    return p


@pytest.fixture(scope="module")
def uw_run(tmp_path_factory):
    tmp = tmp_path_factory.mktemp("seed004")
    scenario = compressed(tmp)
    from fednav.simulators.scenario import load_scenario

    sc = load_scenario(scenario)  # the variant is a valid scenario
    assert [(f.start_s, f.duration_s) for f in sc.faults] == [(FAULT[0], FAULT[1] - FAULT[0])]
    assert [p["name"] for p in sc.service["pipelines"]] == ["fed_edop", "centralized"]
    rrd = tmp / "uw.rrd"
    return run_and_collect(scenario, "fednav/**/faults", seed=4, rrd=rrd) | {"rrd": rrd}


def test_a_plain_client_sees_the_reconfiguration_on_faults(uw_run):
    assert uw_run["rc"] == 0, uw_run["out"]
    items = uw_run["items"]
    assert {k for k, _ in items} == {"fednav/v1/nav/fed_edop/faults", "fednav/v1/nav/centralized/faults"}
    fed = [d for k, d in items if d["pipeline"] == "fed_edop"]
    assert len(fed) >= 2 * (DURATION_S - 2)  # one report per USBL and per DVL message
    events = [(round(d["t"] - T0, 3), e["subsystem"], e["action"]) for d in fed for e in d["reconfiguration"]]
    assert events == [(FAULT[0], "INS/USBL", "excluded"), (FAULT[1], "INS/USBL", "rejoined")]
    for d in fed:
        inside = FAULT[0] <= d["t"] - T0 < FAULT[1]
        assert d["excluded"] == (["INS/USBL"] if inside else [])
        assert set(d["sharing"]) == {"INS/USBL", "INS/DVL"}
        sub = d["subsystems"][0]
        if sub["name"] == "INS/DVL":
            assert [s["name"] for s in d["states"]][:3] == [
                "dvl_offset_x_mps",
                "dvl_offset_y_mps",
                "dvl_offset_z_mps",
            ]
            assert not sub["isolated"]
        else:
            assert sub["isolated"] == inside
    # the unscreened comparator uses every faulty fix (no test, no reconfiguration)
    cen = [d for k, d in items if d["pipeline"] == "centralized"]
    assert cen and all(d["reconfiguration"] == [] and d["sharing"] == {} for d in cen)
    assert not any(s["isolated"] for d in cen for s in d["subsystems"])


def test_recording_holds_the_reconfiguration_and_dvl_states(uw_run):
    rrd = uw_run["rrd"]
    res = subprocess.run([str(RERUN), "rrd", "verify", str(rrd)], capture_output=True, text=True, timeout=120)
    assert res.returncode == 0, res.stderr
    from fednav.dashboards.inspect import read_series
    from fednav.service.transport import rerun_paths as paths

    info, data = read_series(rrd)
    assert info["blueprints"] >= 1
    rec = data[paths.reconfiguration("v1", "fed_edop")]
    assert [t.split(" (")[0] for t in rec.values] == ["excluded: INS/USBL", "rejoined: INS/USBL"]
    assert [round(t / 1e9 - T0, 3) for t in rec.t_ns.tolist()] == [FAULT[0], FAULT[1]]
    std = data[paths.filter_state("v1", "fed_edop", "dvl_offset_y_mps", "std")]
    assert len(std) >= DURATION_S - 2
    assert std.values[-1] < std.values[0] < 0.2 * 0.4  # from the 0.4 m/s prior, shrinking
    assert paths.reconfiguration("v1", "centralized") not in data
