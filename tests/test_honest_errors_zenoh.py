"""Honest errors over real processes: data under a vehicle name the service does not serve is
counted in the service-level ServiceHealth (a plain Zenoh client receives it) and logged once per
name with a hint; a time base mismatch is named in the vehicle's Health and the log."""

from __future__ import annotations

import json
import signal
import threading
import time

import pytest

from fednav.service import keys
from fednav.service.messages import ServiceHealth
from fednav.simulators.processes import free_port, start_service
from fednav.simulators.stream import Simulation

from .plain_zenoh import client as zenoh_client
from .scenario_utils import SCENARIOS, shortened
from .test_hostile import Publisher

pytestmark = pytest.mark.integration


@pytest.mark.parametrize("subscribe", ["all", "served"])
def test_unserved_vehicle_is_counted_and_named(tmp_path, subscribe):
    """subscribe = "all" (default): counted and named; "served" (services sharing a fleet): the
    service never receives the other vehicle's data, so nothing is counted or logged."""
    text = (SCENARIOS / "demo_aircraft.toml").read_text()
    line = f'vehicles = ["v1"]\nintake = {{ subscribe = "{subscribe}" }}\n'
    text = text.replace("[service]\n", "[service]\n" + line, 1)
    cfg = tmp_path / "service.toml"
    cfg.write_text(text)
    port = free_port()
    svc = start_service(port, config=cfg, table="service")
    session = zenoh_client(port)
    got: list[dict] = []
    lock = threading.Lock()

    def cb(sample) -> None:
        with lock:
            got.append(json.loads(sample.payload.to_bytes()))

    sub = session.declare_subscriber("fednav/_services/*/health", cb)
    # "served": nobody subscribes to this vehicle's keys (the point of the test), so waiting
    # for a match (10 s for each of its four keys) would only wait
    pub = Publisher(session, match_wait_s=0.0 if subscribe == "served" else 10.0)
    sc = shortened("demo_aircraft.toml", 1.0)
    sent = 0
    try:
        for key, msg in Simulation(sc, seed=3, vehicle="car"):
            pub.put(key, msg.to_json())
            sent += 1
        deadline = time.monotonic() + 20.0
        while time.monotonic() < deadline:
            with lock:
                last = got[-1] if got else None
            if last and last.get("unserved_vehicles", {}).get("car", 0) >= sent:
                break
            if subscribe == "served" and len(got) >= 3:  # health keeps coming, nothing counted
                break
            time.sleep(0.2)
    finally:
        sub.undeclare()
        svc.signal(signal.SIGTERM)
        rc = svc.wait(timeout=30)
        session.close()
    assert rc == 0
    assert last is not None, "no ServiceHealth received"
    h = ServiceHealth.model_validate(last)  # the wire contract
    out = svc.output()
    if subscribe == "served":
        assert h.unserved_vehicles == {} and h.refused_before_routing.get("unserved_vehicle", 0) == 0
        assert "unserved_vehicle" not in out
        return
    assert h.unserved_vehicles == {"car": sent}
    assert h.refused_before_routing["unserved_vehicle"] == sent
    assert h.vehicles == ["v1"] and h.active_vehicles == []
    assert out.count("unserved_vehicle: data for vehicle 'car' refused") == 1, out[-2000:]
    assert keys.is_output("fednav/_services/abc/health")
