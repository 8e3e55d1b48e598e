"""The service's vehicle workers (service/app.py ``PoolWorker``), in both modes: inline (the
default, ``[intake] workers = 0``: the submitting thread runs the message under the worker's lock)
and a worker thread with its queue. Either way: every item is run once, a vehicle's items in
order, never two at once, a failing item is counted and the next one still runs, idle vehicles
still publish Health, and stopping drains and emits the last outputs."""

from __future__ import annotations

import threading
import time
from collections import Counter

import pytest

from fednav.service.app import PoolWorker
from fednav.service.config import ServiceConfig

from .scenario_utils import wait_until


class _Loop:
    def __init__(self, log: list, busy: list):
        self.log = log
        self.busy = busy

    def process(self, kind, sensor_id, payload, wall):
        if self.busy[0]:
            raise AssertionError("two items run at once")
        self.busy[0] = True
        try:
            if payload == b"boom":
                raise RuntimeError("a pipeline bug")
            time.sleep(0.0002)
            self.log.append(payload)
        finally:
            self.busy[0] = False


class _Vehicle:
    """What PoolWorker needs of a VehicleWorker."""

    def __init__(self, name: str, busy: list):
        self.vehicle = name
        self.log: list = []
        self.loop = _Loop(self.log, busy)
        self.counters: Counter = Counter()
        self.queued = 0
        self.retired = False
        self.on_retired = None
        self.next_health = 0.0
        self.next_state = float("inf")
        self.health_published = 0
        self.finals = 0
        self.idle_s = 0.0
        self.last_input = time.monotonic()
        self.released = False
        self.on_released = None
        self.reroute = None
        self.rr = None
        self.took_any = True

    def accepted_any(self) -> bool:
        return self.took_any

    def publish_health(self) -> None:
        self.health_published += 1

    def final_outputs(self) -> None:
        self.finals += 1


def _config(workers: int) -> ServiceConfig:
    return ServiceConfig.model_validate({"intake": {"workers": workers}, "output": {"health_period_s": 0.1}})


def test_inline_is_the_default():
    assert ServiceConfig().intake.workers == 0


@pytest.mark.parametrize("inline", [True, False], ids=["inline", "worker_thread"])
def test_items_run_once_in_order_never_two_at_once(inline):
    busy = [False]
    pw = PoolWorker(0, _config(0 if inline else 1), None, inline)
    a, b = _Vehicle("a", busy), _Vehicle("b", busy)
    pw.vehicles += [a, b]
    n = 300

    def feed(v: _Vehicle) -> None:  # two submitting threads (the intake and the ROS 2 intake)
        for i in range(n):
            payload = b"boom" if i == 100 else f"{v.vehicle}{i}".encode()
            pw.submit(v, (time.monotonic(), "imu", "", payload))

    threads = [threading.Thread(target=feed, args=(v,)) for v in (a, b)]
    for t in threads:
        t.start()
    for t in threads:
        t.join()
    assert wait_until(lambda: len(a.log) == len(b.log) == n - 1)
    for v in (a, b):
        assert v.log == [f"{v.vehicle}{i}".encode() for i in range(n) if i != 100]
        assert v.counters["internal_error"] == 1  # the failing item, counted; the next ones ran
    # idle vehicles still publish Health (every health_period_s, from the worker's own scan)
    before = a.health_published
    assert wait_until(lambda: a.health_published >= before + 2, timeout=5.0)
    pw.request_stop()
    pw.stop(time.monotonic() + 5.0)
    assert a.finals == b.finals == 1
    assert a.queued == b.queued == 0


@pytest.mark.parametrize("inline", [True, False], ids=["inline", "worker_thread"])
def test_an_idle_vehicle_is_released_and_what_reached_it_late_goes_to_its_successor(inline):
    """``[intake] vehicle_idle_s``: a vehicle with no input for that long is released by the
    worker's scan (its last outputs, then the service's hook); an input routed to it just before
    (the intake looked it up, then the scan released it) is handed to the vehicle's new worker,
    not lost, and the new worker runs it in its place."""
    busy = [False]
    pw = PoolWorker(0, _config(0 if inline else 1), None, inline)
    old, new, busy_one = _Vehicle("a", busy), _Vehicle("a", busy), _Vehicle("b", busy)
    released: list = []
    for v in (old, busy_one):
        v.idle_s = 0.3
        v.on_released = released.append
        v.reroute = lambda vw, item: new
    new.pool_worker = pw
    pw.vehicles += [old, busy_one]
    deadline = time.monotonic() + 1.0
    while time.monotonic() < deadline:  # b keeps sending; a does not
        pw.submit(busy_one, (time.monotonic(), "imu", "", b"b"))
        busy_one.last_input = time.monotonic()
        time.sleep(0.02)
    assert released == [old] and old.released and old.retired and old.finals == 1
    assert pw.vehicles == [busy_one] and not busy_one.released
    pw.submit(old, (time.monotonic(), "imu", "", b"late"))  # routed to the old one before its release
    assert wait_until(lambda: new.log == [b"late"])
    assert old.log == []
    pw.request_stop()
    pw.stop(time.monotonic() + 5.0)


def test_a_fleets_health_is_spread_over_the_period():
    """Vehicles that start at once publish Health at their own phase of the period (a stable
    hash of the name), not all in one scan (a burst of ~0.3 ms per vehicle that holds the intake);
    a vehicle keeps its phase, also after a late scan."""
    from fednav.service.app import health_phase, next_due

    names = [f"veh{i:03d}" for i in range(200)]
    phases = [health_phase(v) for v in names]
    assert all(0.0 <= p < 1.0 for p in phases)
    assert health_phase("veh007") == health_phase("veh007")
    per_scan = Counter(int(p / 0.05) for p in phases)  # 20 scans of 50 ms in a 1 s period
    assert len(per_scan) == 20 and max(per_scan.values()) <= 3 * 200 / 20
    # on time, late by less than a period, late by several: the next due time is on the grid
    assert next_due(10.3, 10.31, 1.0) == pytest.approx(11.3)
    assert next_due(10.3, 11.5, 1.0) == pytest.approx(12.3)
    assert next_due(10.3, 14.3, 1.0) == pytest.approx(15.3)


def test_health_latency_figures_are_the_windows_percentiles():
    """Health reads the latency window once and both percentiles in one call: the same figures as
    numpy's percentile of the window (the median and the 99th, linear interpolation)."""
    import numpy as np

    from fednav.service.vehicle import VehicleLoop

    class Sink:
        def on_estimate(self, *a):
            pass

        def on_output(self, *a, **k):
            pass

        def on_truth(self, *a):
            pass

    loop = VehicleLoop("v1", ServiceConfig(), Sink(), latency_window=500)
    assert loop.health().latency_ms == {"p50": 0.0, "p99": 0.0, "max": 0.0}  # nothing yet
    rng = np.random.default_rng(3)
    values = rng.exponential(0.004, 700)
    for v in values:
        loop.latency_s.append(float(v))
    window = values[-500:] * 1e3
    lat = loop.health().latency_ms
    assert lat["p50"] == float(np.percentile(window, 50))
    assert lat["p99"] == float(np.percentile(window, 99))
    assert lat["max"] == float(window.max())


@pytest.mark.parametrize(
    "size,count", [(500, 1), (500, 2), (500, 3), (500, 499), (500, 500), (7, 1000), (2000, 2345)]
)
def test_latency_window_percentiles_are_numpys(size, count):
    """The ring of latencies (service/vehicle.py ``LatencyWindow``): the most recent ``size``
    values, whatever the count (before the ring fills, at its edge, wrapped many times); p50 /
    p99 / max equal to numpy's of the same values, to the bit."""
    import numpy as np

    from fednav.service.vehicle import LatencyWindow

    w = LatencyWindow(size)
    rng = np.random.default_rng(size + count)
    values = rng.lognormal(-5.0, 1.0, count)
    w.extend(values[: count // 3].tolist())
    for v in values[count // 3 :].tolist():
        w.append(v)
    window = values[-size:] * 1e3
    assert len(w) == len(window)
    p50, p99, mx = w.percentiles_ms()
    assert (p50, p99, mx) == (
        float(np.percentile(window, 50)),
        float(np.percentile(window, 99)),
        float(window.max()),
    )


def test_a_vehicle_that_took_nothing_is_released_after_a_short_silence(monkeypatch):
    """Another client's data under a vehicle's sensor keys, all refused: that name made a vehicle
    that held a max_vehicles slot for [intake] vehicle_idle_s (600 s); with nothing ever accepted
    it goes after NEVER_ACCEPTED_IDLE_S of silence, a vehicle that took data keeps its idle time."""
    from fednav.service import app

    monkeypatch.setattr(app, "NEVER_ACCEPTED_IDLE_S", 0.2)
    busy = [False]
    pw = PoolWorker(0, _config(0), None, True)
    ghost, real = _Vehicle("ghost", busy), _Vehicle("real", busy)
    ghost.took_any = False
    released: list = []
    for v in (ghost, real):
        v.idle_s = 600.0
        v.on_released = released.append
        v.last_input = time.monotonic()
    pw.vehicles += [ghost, real]
    deadline = time.monotonic() + 2.0
    while time.monotonic() < deadline and not released:  # the real one keeps sending (the scans run)
        pw.submit(real, (time.monotonic(), "imu", "", b"x"))
        real.last_input = time.monotonic()
        time.sleep(0.02)
    assert released == [ghost] and ghost.released
    assert pw.vehicles == [real] and not real.released
    pw.request_stop()
    pw.stop(time.monotonic() + 5.0)
