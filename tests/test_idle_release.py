"""A '*' service releases a vehicle that sent nothing for ``[intake] vehicle_idle_s``.

A fleet whose names come and go (vehicles retired, renamed, replayed under new names) must not
fill ``max_vehicles`` and memory for good. Real processes over loopback: one service serving every
vehicle with room for two; a plain Zenoh client publishes two vehicles, then a third (refused:
no room), waits, and publishes the third and the first again (both served: the idle two were
released). The recording is read back with Rerun's own reader for the release note.
"""

from __future__ import annotations

import json
import signal
import threading
import time

import pytest

from fednav.service.messages import ServiceHealth
from fednav.simulators.processes import free_port, query_status, start_service, wait_idle
from fednav.simulators.stream import Simulation

from .plain_zenoh import client as zenoh_client
from .scenario_utils import SCENARIOS, shortened
from .test_hostile import Publisher

pytestmark = pytest.mark.integration

IDLE_S = 3.0


def _config(tmp_path, idle_s: float) -> str:
    text = (SCENARIOS / "demo_aircraft.toml").read_text()
    extra = f'vehicles = ["*"]\nintake = {{ max_vehicles = 2, vehicle_idle_s = {idle_s} }}\n'
    path = tmp_path / "service.toml"
    path.write_text(text.replace("[service]\n", "[service]\n" + extra, 1))
    return path


def _publish(pub: Publisher, vehicle: str, seconds: float, seed: int = 5) -> int:
    n = 0
    for key, msg in Simulation(shortened("demo_aircraft.toml", seconds), seed=seed, vehicle=vehicle):
        pub.put(key, msg.to_json())
        n += 1
    return n


def _alive(session, vehicle: str) -> bool:
    replies = session.liveliness().get(f"fednav/{vehicle}/service/alive", timeout=3.0)
    return any(r.ok is not None for r in replies)


def test_idle_vehicles_are_released_and_come_back_fresh(tmp_path):
    port = free_port()
    rrd = tmp_path / "idle.rrd"
    svc = start_service(port, config=_config(tmp_path, IDLE_S), table="service", rrd=rrd)
    session = zenoh_client(port)
    healths: list[dict] = []
    lock = threading.Lock()

    def on_health(sample) -> None:
        with lock:
            healths.append(json.loads(sample.payload.to_bytes()))

    sub = session.declare_subscriber("fednav/_services/*/health", on_health)
    pub = Publisher(session)

    def latest() -> ServiceHealth | None:
        with lock:
            return ServiceHealth.model_validate(healths[-1]) if healths else None

    try:
        for v in ("a1", "a2"):
            _publish(pub, v, 2.0)
        assert wait_idle(port, vehicle="a1") and wait_idle(port, vehicle="a2")
        assert _alive(session, "a1")
        _publish(pub, "a3", 0.5)  # no room: both slots held
        deadline = time.monotonic() + 10.0
        while time.monotonic() < deadline:
            h = latest()
            if h is not None and h.refused_before_routing.get("vehicle_limit", 0) > 0:
                break
            time.sleep(0.2)
        assert h is not None and h.refused_before_routing.get("vehicle_limit", 0) > 0, h
        assert sorted(h.active_vehicles) == ["a1", "a2"] and h.vehicles_released_idle == 0
        # nothing for a1 and a2 from here on: both are released after IDLE_S
        deadline = time.monotonic() + IDLE_S + 15.0
        while time.monotonic() < deadline:
            h = latest()
            if h is not None and h.vehicles_released_idle == 2:
                break
            time.sleep(0.2)
        assert h.vehicles_released_idle == 2 and h.active_vehicles == [], h
        assert not _alive(session, "a1") and query_status(port, "a1", timeout_s=2.0) is None
        # the freed slots serve a new name and the old one again, from scratch
        sent3 = _publish(pub, "a3", 2.0)
        sent1 = _publish(pub, "a1", 2.0, seed=6)
        st3, st1 = wait_idle(port, vehicle="a3"), wait_idle(port, vehicle="a1")
        assert st3 and st1, (st3, st1)
        assert st3["health"]["received"] == sent3
        assert st1["health"]["received"] == sent1  # a new worker: the old counts went with the old
        statuses = {k: p["status"] for k, p in st1["health"]["pipelines"].items()}
        assert statuses and all(s in ("aided", "degraded") for s in statuses.values()), statuses
        assert _alive(session, "a1")
    finally:
        sub.undeclare()
        svc.signal(signal.SIGTERM)
        rc = svc.wait(timeout=30)
        session.close()
    assert rc == 0
    out = svc.output()
    assert "vehicle a1 released: no input for" in out and "vehicle a2 released" in out, out[-3000:]
    # the release is in the recording, under each vehicle's events
    from rerun.chunk import RrdReader

    reader = RrdReader(rrd)
    texts: dict[str, list[str]] = {}
    for ch in reader.stream(store=reader.recordings()[0]):
        if ch.is_static or not ch.entity_path.endswith("/service/health/events"):
            continue
        batch = ch.to_record_batch()
        if "TextLog:text" in batch.schema.names:
            for row in batch.column("TextLog:text").to_pylist():
                texts.setdefault(ch.entity_path, []).extend(row or [])
    for v in ("a1", "a2"):
        got = texts.get(f"/{v}/service/health/events", [])
        assert sum("released: no input for" in t for t in got) == 1, texts


def test_ros2_input_keeps_its_vehicle_from_being_released():
    """The ROS 2 intake routes to its vehicle's worker without ``_route``: it stamps the arrival
    too, so a vehicle fed only by ROS 2 (even refused samples) is not released while they come."""
    from fednav.service.app import OutputSink, PoolWorker, Service
    from fednav.service.config import ServiceConfig
    from fednav.service.transport import ros2

    cfg = ServiceConfig.model_validate(
        {
            "vehicles": ["*"],
            "pipelines": [{"name": "lc", "kind": "loosely_coupled"}],
            "intake": {"vehicle_idle_s": 1.0},
            "ros2": {
                "vehicle": "rosv",
                "inputs": [{"topic": "/imu/data", "type": "sensor_msgs/msg/Imu", "sensor_id": "main"}],
            },
        }
    )

    class _Nothing:
        def __getattr__(self, name):
            return lambda *a, **k: None

    svc = Service(cfg, record=False)
    svc.pool = [PoolWorker(0, cfg, None, inline=True)]
    svc.pubs = svc.liveliness = _Nothing()
    svc.rr = None
    svc.sink = OutputSink(cfg.prefix, svc.pubs, None)
    svc.ros_in = ros2.RosInput(cfg.ros2)
    key = ros2.topic_key(cfg.ros2, "/imu/data", "sensor_msgs/msg/Imu")
    try:
        svc._deliver_ros(time.monotonic(), key, b"\x00\x01\x00\x00not cdr")
        w = svc.workers["rosv"]
        assert w.idle_s == 1.0 and w.counters  # the refusal counted
        for _ in range(8):  # 2 s of ROS 2 samples every 0.25 s: never 1 s without one
            time.sleep(0.25)
            wall = time.monotonic()
            svc._deliver_ros(wall, key, b"\x00\x01\x00\x00not cdr")
            assert w.last_input == wall
        assert svc.workers.get("rosv") is w and not w.released and svc.released_vehicles == 0
        time.sleep(1.5)  # then silence: released
        assert w.released and "rosv" not in svc.workers and svc.released_vehicles == 1
    finally:
        svc.pool[0].request_stop()
        svc.pool[0].stop(time.monotonic() + 2.0)


def test_another_clients_keys_under_the_prefix_make_no_vehicle(tmp_path):
    """Keys that are no sensor input under a vehicle-like name (a dashboard's commands, a
    diagnostics blob: another client on the bus) are counted for the service (ServiceHealth
    ``unknown_key``), not made vehicles with a token, Health and a max_vehicles slot."""
    port = free_port()
    svc = start_service(port, config=_config(tmp_path, 600.0), table="service")
    session = zenoh_client(port)
    healths: list[dict] = []
    sub = session.declare_subscriber(
        "fednav/_services/*/health", lambda s: healths.append(json.loads(s.payload.to_bytes()))
    )
    try:
        for k in range(5):
            session.put(f"fednav/ghost{k}/cmd/zoom", b"2")
            session.put(f"fednav/diag{k}/blob", b"\x00" * 100)
        deadline = time.monotonic() + 10.0
        while time.monotonic() < deadline:
            h = ServiceHealth.model_validate(healths[-1]) if healths else None
            if h is not None and h.refused_before_routing.get("unknown_key", 0) >= 10:
                break
            time.sleep(0.2)
        assert h is not None and h.refused_before_routing.get("unknown_key", 0) == 10, h
        assert h.active_vehicles == [] and not _alive(session, "ghost0")
        # a real vehicle still gets its slot (max_vehicles = 2)
        _publish(Publisher(session), "real1", 1.0)
        assert wait_idle(port, vehicle="real1")
    finally:
        sub.undeclare()
        svc.signal(signal.SIGTERM)
        rc = svc.wait(timeout=30)
        session.close()
    assert rc == 0
