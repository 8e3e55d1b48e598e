"""Seed 001 integrity over real processes: fednav-service and fednav-sim on loopback Zenoh.

A shortened seed001_ramp scenario (25 s, ramp 0.63 m/s on GEO3 = C03 from 11 s) is written to
tmp_path; the service runs its [service] table (tightly coupled + MHSS, NPA); a plain Zenoh client
(mode client, multicast scouting off, raw JSON: no fednav decoding) subscribed to
``fednav/**/integrity`` receives the Integrity messages.
"""

from __future__ import annotations

import re
from pathlib import Path

import pytest

from .plain_zenoh import run_and_collect

pytestmark = pytest.mark.integration
ROOT = Path(__file__).resolve().parents[1]
RAMP = ROOT / "simulators" / "scenarios" / "seed001_ramp.toml"
T0 = 1_300_000_000.0
DURATION_S = 25.0


def short_ramp(tmp_path: Path) -> Path:
    """seed001_ramp.toml with duration 25 s (straight flight) and the ramp ending with the run."""
    text = RAMP.read_text()
    text = re.sub(r"(?m)^duration_s = 180\.0$", f"duration_s = {DURATION_S}", text, count=1)
    text = re.sub(r"(?s)\[\[segments\]\].*?(?=\n\[)", "", text)
    text = re.sub(r"(?m)^duration_s = 129\.0$", f"duration_s = {DURATION_S - 11.0}", text)
    text = text.replace('name = "seed001_ramp"', 'name = "seed001_ramp_short"')
    p = tmp_path / "seed001_ramp_short.toml"
    p.write_text(text)
    return p


@pytest.fixture(scope="module")
def integrity_run(tmp_path_factory):
    tmp = tmp_path_factory.mktemp("seed001")
    scenario = short_ramp(tmp)
    from fednav.simulators.scenario import load_scenario

    sc = load_scenario(scenario)  # the variant is a valid scenario
    assert sc.duration_s == DURATION_S and sc.faults[0].channels == ["C03.pseudorange"]
    return run_and_collect(scenario, "fednav/**/integrity", seed=1)


def test_integrity_messages_arrive_with_protection_levels_and_satellite_tests(integrity_run):
    items = integrity_run["items"]
    assert integrity_run["rc"] == 0, integrity_run["out"]
    assert {k for k, _ in items} == {"fednav/v1/nav/tc_mhss/integrity"}
    msgs = [d for _, d in items]
    assert len(msgs) >= 0.95 * DURATION_S * 10, f"only {len(msgs)} Integrity messages (10 Hz GNSS)"
    ts = [d["t"] for d in msgs]
    assert ts == sorted(ts)
    for d in msgs:
        for key in ("hpl_m", "vpl_m", "hal_m", "alarm", "available", "detected", "excluded", "satellites"):
            assert key in d, key
        assert d["phase"] == "npa" and d["hal_m"] == 556.0
        assert 0.0 < d["hpl_m"] < d["hal_m"] and d["vpl_m"] > 0.0
        assert isinstance(d["alarm"], bool) and not d["alarm"]
        assert len(d["satellites"]) >= 5
        for s in d["satellites"]:
            assert re.fullmatch(r"C\d\d", s["id"]) and s["threshold_m"] > 0.0 and s["statistic_m"] >= 0.0
    assert {s["id"] for s in msgs[0]["satellites"]} >= {"C03"}


def test_ramp_on_c03_is_detected_within_2_s_and_c03_excluded(integrity_run):
    msgs = [d for _, d in integrity_run["items"]]
    before = [d for d in msgs if d["t"] - T0 < 11.0 - 1e-6]
    assert before and not any(d["detected"] or d["excluded"] for d in before)
    first = next(d for d in msgs if d["detected"])
    latency = first["t"] - T0 - 11.0
    assert 0.0 < latency <= 2.0 + 1e-6, f"detected {latency:.2f} s after the onset"
    assert first["excluded"] == ["C03"]
    after = [d for d in msgs if d["t"] > first["t"]]
    assert after and all(d["excluded"] == ["C03"] for d in after)
    assert all("C03" not in {s["id"] for s in d["satellites"]} for d in after)
