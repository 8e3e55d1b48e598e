"""One service instance serving several vehicles by key expression (``--vehicle '*'``)."""

import json
import signal
import threading

import pytest

from fednav.simulators.processes import free_port, query_status, start_service, start_sim, wait_idle

from .plain_zenoh import client as zenoh_client
from .scenario_utils import SCENARIOS

pytestmark = pytest.mark.integration


@pytest.mark.parametrize("workers", [None, 2], ids=["inline", "two_worker_threads"])
def test_two_vehicles_one_service(tmp_path, workers):
    demo = SCENARIOS / "demo_aircraft.toml"
    if workers is not None:  # the same scenario, its service with a pool of worker threads
        cfg = tmp_path / "demo_workers.toml"
        cfg.write_text(demo.read_text() + f"\n[service.intake]\nworkers = {workers}\n")
        demo = cfg
    port = free_port()
    svc = start_service(port, config=demo, table="service", extra=["--vehicle", "*"])
    session = zenoh_client(port)
    seen: dict[str, int] = {}
    lock = threading.Lock()

    def on_sol(sample):
        vehicle = str(sample.key_expr).split("/")[1]
        json.loads(sample.payload.to_bytes())
        with lock:
            seen[vehicle] = seen.get(vehicle, 0) + 1

    session.declare_subscriber("fednav/*/nav/lc/solution", on_sol)
    try:
        sims = [start_sim(port, demo, speed=0.0, seed=s, vehicle=v) for s, v in ((1, "alpha"), (2, "bravo"))]
        for sim in sims:
            assert sim.wait(timeout=300) == 0, sim.output()
        for v in ("alpha", "bravo"):
            st = wait_idle(port, vehicle=v)
            assert st is not None and st["health"]["accepted"] == st["health"]["received"] > 30000
        assert query_status(port, "charlie") is None  # a vehicle never seen: no worker, no reply
    finally:
        svc.signal(signal.SIGINT)
        svc.wait(timeout=60)
        session.close()
    assert seen.get("alpha", 0) > 2900 and seen.get("bravo", 0) > 2900, seen
