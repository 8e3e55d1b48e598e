"""Bad input into a running service, and SIGTERM mid-run (real processes over loopback Zenoh).

Bad input: malformed JSON, wrong schema, NaN, absurd magnitudes, time going backwards,
duplicates, late aiding, unknown keys. Each must be counted by reason in Health, the service
must not crash, solutions must keep flowing, and nothing may reach the filter: the solutions
equal those of the clean stream run in-process.
"""

from __future__ import annotations

import json
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest
import zenoh

from fednav.service import keys
from fednav.service.messages import GnssFix, ImuSample
from fednav.simulators.evaluate import run_once
from fednav.simulators.processes import free_port, start_service, start_sim, wait_idle
from fednav.simulators.stream import Simulation

from .plain_zenoh import client as zenoh_client
from .scenario_utils import SCENARIOS, shortened

pytestmark = pytest.mark.integration
RERUN = Path(sys.executable).with_name("rerun")


def test_bad_input_is_counted_and_never_reaches_the_filter(tmp_path):
    sc = shortened("demo_aircraft.toml", 40.0)
    cfg_path = tmp_path / "scenario.toml"
    cfg_path.write_text((SCENARIOS / "demo_aircraft.toml").read_text())
    port = free_port()
    svc = start_service(port, config=cfg_path, table="service")
    session = zenoh_client(port)
    sols: list[dict] = []
    session.declare_subscriber(
        "fednav/v1/nav/lc/solution", lambda s: sols.append(json.loads(s.payload.to_bytes()))
    )
    pubs: dict[str, zenoh.Publisher] = {}

    def put(key: str, payload: bytes | str) -> None:
        p = pubs.get(key)
        if p is None:
            p = pubs[key] = session.declare_publisher(
                key, congestion_control=zenoh.CongestionControl.BLOCK, reliability=zenoh.Reliability.RELIABLE
            )
            deadline = time.monotonic() + 10
            while not p.matching_status.matching and time.monotonic() < deadline:
                time.sleep(0.01)
        p.put(payload)

    imu_key = keys.sensor("v1", "imu", "main")
    gnss_key = keys.sensor("v1", "gnss_fix", "main")
    expected = {
        "malformed_json": 0,
        "schema": 0,
        "non_finite": 0,
        "absurd_value": 0,
        "time_backwards": 0,
        "duplicate": 0,
        "late": 0,
        "unknown_key": 0,
    }
    try:
        last_imu = last_fix = None
        for key, msg in Simulation(sc, seed=5):
            put(key, msg.to_json())
            if isinstance(msg, ImuSample):
                last_imu = msg
            if isinstance(msg, GnssFix):
                last_fix = msg
            if isinstance(msg, ImuSample) and last_fix is not None and abs(msg.t - last_fix.t) < 1e-9:
                # right after the IMU reaches a GNSS epoch: a burst of bad input
                t = msg.t
                put(imu_key, b"{not json")
                expected["malformed_json"] += 1
                put(imu_key, json.dumps({"t": t, "dt_s": 0.01, "dtheta_rad": [0, 0], "dvel_mps": [0, 0, 0]}))
                expected["schema"] += 1
                put(gnss_key, last_fix.to_json().replace(b'"height_m":', b'"height_m":NaN,"x":'))
                expected["non_finite"] += 1  # NaN plus an unknown field: NaN is the reason given
                put(
                    imu_key,
                    json.dumps(
                        {
                            "t": t + 0.001,
                            "dt_s": 0.01,
                            "dtheta_rad": [float("nan"), 0, 0],
                            "dvel_mps": [0, 0, 0],
                        }
                    ),
                )
                expected["non_finite"] += 1
                put(
                    imu_key,
                    json.dumps(
                        {"t": t + 0.001, "dt_s": 0.01, "dtheta_rad": [0, 0, 0], "dvel_mps": [1e6, 0, 0]}
                    ),
                )
                expected["absurd_value"] += 1
                put(imu_key, last_imu.model_copy(update={"t": t - 0.5}).to_json())
                expected["time_backwards"] += 1
                put(imu_key, last_imu.to_json())
                expected["duplicate"] += 1
                put(gnss_key, last_fix.to_json())
                expected["duplicate"] += 1
                put(gnss_key, last_fix.model_copy(update={"t": t - 3.0}).to_json())
                expected["late"] += 1
                put("fednav/v1/sensor/bogus/x", b"{}")
                expected["unknown_key"] += 1
        status = wait_idle(port)
        assert status is not None
        rejected = status["health"]["rejected"]
        for reason, n in expected.items():
            assert rejected.get(reason, 0) == n, f"{reason}: {json.dumps(rejected)}"
        assert svc.p.poll() is None, "service died"
    finally:
        svc.signal(signal.SIGINT)
        svc.wait(timeout=60)
        session.close()
    assert expected["late"] >= 30
    # nothing reached the filter: the solutions equal the clean stream's, in-process
    sink, _ = run_once(sc, seed=5, keep_solutions=True)
    clean = {round(s.t, 6): s for s in sink.records["lc"].solutions}
    got = {round(d["t"], 6): d for d in sols}
    assert len(got) >= len(clean) - 1 and len(clean) > 350
    worst = max(
        max(abs(clean[t].lat_deg - got[t]["lat_deg"]), abs(clean[t].lon_deg - got[t]["lon_deg"]))
        for t in clean
        if t in got
    )
    assert worst < 1e-12, worst


def test_sigterm_mid_run_leaves_a_complete_recording(tmp_path):
    port = free_port()
    rrd = tmp_path / "term.rrd"
    demo = SCENARIOS / "demo_aircraft.toml"
    svc = start_service(port, config=demo, table="service", rrd=rrd)
    session = zenoh_client(port)
    sols: list[float] = []
    session.declare_subscriber(
        "fednav/v1/nav/lc/solution", lambda s: sols.append(json.loads(s.payload.to_bytes())["t"])
    )
    sim = start_sim(port, demo, speed=20.0)
    try:
        deadline = time.monotonic() + 60
        while len(sols) < 300 and time.monotonic() < deadline:  # ~30 s of sensor time in
            time.sleep(0.05)
        assert len(sols) >= 300
        t_kill = time.monotonic()
        svc.signal(signal.SIGTERM)
        rc = svc.wait(timeout=30)
        took = time.monotonic() - t_kill
    finally:
        sim.kill()
        time.sleep(0.2)
        session.close()
    assert rc == 0, svc.output()
    assert took < 10.0, f"shutdown took {took:.1f} s"
    res = subprocess.run([str(RERUN), "rrd", "verify", str(rrd)], capture_output=True, text=True, timeout=120)
    assert res.returncode == 0, res.stderr
    from fednav.dashboards.inspect import inspect_rrd

    summary = inspect_rrd(rrd)
    last_published = max(sols)
    assert summary["t_end"] >= last_published - 1e-6, (summary["t_end"], last_published)
    assert summary["pipelines"]["lc"]["solutions"] >= len(sols)
