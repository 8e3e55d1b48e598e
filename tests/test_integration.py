"""Real processes over loopback Zenoh: fednav-service and fednav-sim as subprocesses on a free port.

A plain Zenoh subscriber (no fednav import for decoding: raw JSON) receives Solution and Health;
the recording is read back with Rerun's own reader; the in-process eval gives the same solutions;
bad input is rejected and counted; SIGTERM leaves a complete recording.
"""

from __future__ import annotations

import json
import math
import signal
import subprocess
import sys
import threading
import time
from pathlib import Path

import numpy as np
import pytest
import zenoh

from fednav.simulators.processes import free_port, start_service, start_sim, wait_idle

from .plain_zenoh import client as zenoh_client

pytestmark = pytest.mark.integration
ROOT = Path(__file__).resolve().parents[1]
DEMO = ROOT / "simulators" / "scenarios" / "demo_aircraft.toml"
RERUN = Path(sys.executable).with_name("rerun")


class Collector:
    def __init__(self, session: zenoh.Session, expr: str):
        self.items: list[tuple[str, dict]] = []
        self._lock = threading.Lock()
        self.sub = session.declare_subscriber(expr, self._cb)

    def _cb(self, sample: zenoh.Sample) -> None:
        with self._lock:
            self.items.append((str(sample.key_expr), json.loads(sample.payload.to_bytes())))

    def of(self, suffix: str) -> list[dict]:
        with self._lock:
            return [d for k, d in self.items if k.endswith(suffix)]


def _truth_by_t(collector: Collector) -> dict[float, dict]:
    return {round(d["t"], 6): d for d in collector.of("/truth")}


def _h_err_m(sol: dict, truth: dict) -> float:
    lat = math.radians(truth["lat_deg"])
    dn = math.radians(sol["lat_deg"] - truth["lat_deg"]) * 6356752.0
    de = math.radians(sol["lon_deg"] - truth["lon_deg"]) * 6378137.0 * math.cos(lat)
    return math.hypot(dn, de)


@pytest.fixture(scope="module")
def demo_run(tmp_path_factory):
    """One accelerated demo run shared by the checks below."""
    tmp = tmp_path_factory.mktemp("demo")
    port = free_port()
    rrd = tmp / "demo.rrd"
    svc = start_service(port, config=DEMO, table="service", rrd=rrd)
    client = zenoh_client(port)
    col = Collector(client, "fednav/v1/**")
    try:
        sim = start_sim(port, DEMO, speed=0.0, seed=3)
        assert sim.wait(timeout=300) == 0, sim.output()
        status = wait_idle(port)
        assert status is not None, "service did not become idle"
    finally:
        svc.signal(signal.SIGINT)
        rc = svc.wait(timeout=60)
    time.sleep(0.2)
    client.close()
    return {"rrd": rrd, "collector": col, "status": status, "service_rc": rc, "service_out": svc.output()}


def test_service_publishes_solutions_and_health(demo_run):
    col = demo_run["collector"]
    sols = col.of("/nav/lc/solution")
    assert len(sols) > 2500, f"only {len(sols)} solutions"  # 10 Hz over 300 s
    s = sols[-1]
    for field in ("t", "lat_deg", "lon_deg", "height_m", "vel_enu_mps", "rpy_deg", "pos_std_enu_m", "status"):
        assert field in s
    health = col.of("/service/health")
    assert health, "no Health received"
    assert health[-1]["received"] >= health[-1]["accepted"] > 30000
    assert demo_run["service_rc"] == 0, demo_run["service_out"]


def test_horizontal_error_against_truth_below_5m(demo_run):
    col = demo_run["collector"]
    truth = _truth_by_t(col)
    errs = [
        _h_err_m(s, truth[round(s["t"], 6)]) for s in col.of("/nav/lc/solution") if round(s["t"], 6) in truth
    ]
    assert len(errs) > 2500
    rms = math.sqrt(np.mean(np.square(errs)))
    assert rms < 5.0, f"horizontal RMS {rms:.2f} m"


def test_recording_verifies_and_reads_back(demo_run):
    rrd = demo_run["rrd"]
    res = subprocess.run([str(RERUN), "rrd", "verify", str(rrd)], capture_output=True, text=True, timeout=120)
    assert res.returncode == 0, res.stderr
    from rerun.chunk import RrdReader

    paths = {ch.entity_path for ch in RrdReader(str(rrd)).stream()}
    assert any(p.startswith("/v1/lc/solution") for p in paths), sorted(paths)[:20]
    assert any(p.startswith("/v1/truth") for p in paths)
    from fednav.dashboards.inspect import inspect_rrd

    summary = inspect_rrd(rrd)
    assert "lc" in summary["pipelines"]
    assert summary["duration_s"] > 250
    # truth and sensors arrive in order on one channel: errors against truth at every solution
    lc = summary["pipelines"]["lc"]
    assert lc["error_epochs"] >= lc["solutions"] - 2, (lc["error_epochs"], lc["solutions"])
    assert lc["h_rms_m"] < 5.0


def test_in_process_eval_equals_over_zenoh(demo_run):
    """The same seeded scenario in-process gives the same solutions as over Zenoh."""
    from fednav.simulators.evaluate import run_once
    from fednav.simulators.scenario import load_scenario

    sink, _ = run_once(load_scenario(DEMO), seed=3, keep_solutions=True)
    local = {round(s.t, 6): s for s in sink.records["lc"].solutions}
    remote = {round(d["t"], 6): d for d in demo_run["collector"].of("/nav/lc/solution")}
    common = sorted(set(local) & set(remote))
    assert len(common) >= 0.99 * len(local)
    worst = 0.0
    for t in common:
        a, b = local[t], remote[t]
        worst = max(
            worst,
            abs(a.lat_deg - b["lat_deg"]),
            abs(a.lon_deg - b["lon_deg"]),
            abs(a.height_m - b["height_m"]) * 1e-5,
            *(abs(x - y) for x, y in zip(a.vel_enu_mps, b["vel_enu_mps"], strict=True)),
        )
    assert worst < 1e-9, worst
