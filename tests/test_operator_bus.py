"""An operator's shared bus (real processes, plain eclipse-zenoh clients, no fednav code in them):
other applications' keys and tokens next to the service, the service's own health asked by its
documented key, and a run stopped with SIGTERM read back by a client and by fednav-inspect."""

from __future__ import annotations

import json
import signal
import time

import pytest

from fednav.simulators.processes import free_port, start_service, start_sim, wait_idle

from .plain_zenoh import client as zenoh_client
from .scenario_utils import SCENARIOS

pytestmark = pytest.mark.integration


@pytest.fixture(scope="module")
def service():
    """One service (vehicle v1, no recording) and its port; stopped with SIGTERM at the end."""
    port = free_port()
    svc = start_service(port, config=SCENARIOS / "demo_aircraft.toml", table="service")
    yield svc, port
    svc.signal(signal.SIGTERM)
    assert svc.wait(timeout=30) == 0, svc.output()[-3000:]


def test_a_run_stopped_after_its_end_publishes_each_solution_once(tmp_path):
    """A client reading Solutions and the recording of a finished run stopped with SIGTERM: every
    Solution time once (the shutdown's last outputs republished the last epoch's Solution under the
    same time, which fednav-inspect then called two runs interleaved in one recording)."""
    from fednav.dashboards.inspect import inspect_rrd

    port = free_port()
    rrd = tmp_path / "run.rrd"
    demo = SCENARIOS / "demo_aircraft.toml"
    svc = start_service(port, config=demo, table="service", rrd=rrd)
    times: list[float] = []
    health: list[dict] = []
    try:
        with zenoh_client(port) as s:
            s.declare_subscriber(
                "fednav/v1/nav/lc/solution", lambda x: times.append(json.loads(x.payload.to_bytes())["t"])
            )
            s.declare_subscriber(
                "fednav/v1/service/health", lambda x: health.append(json.loads(x.payload.to_bytes()))
            )
            sim = start_sim(port, demo, speed=0.0, seed=5)
            assert sim.wait(timeout=120) == 0, sim.output()
            assert wait_idle(port) is not None
            time.sleep(0.5)
            n_health = len(health)
            svc.signal(signal.SIGTERM)
            assert svc.wait(timeout=30) == 0, svc.output()[-3000:]
            time.sleep(0.5)
    finally:
        svc.kill()
    assert len(times) > 2900
    assert len(times) == len(set(times)), sorted(t for t in set(times) if times.count(t) > 1)
    assert len(health) > n_health  # the last Health still goes out at shutdown
    summary = inspect_rrd(rrd)
    assert summary["pipelines"]["lc"]["repeated_times"] == 0
    assert summary["pipelines"]["lc"]["solutions"] == len(times)
