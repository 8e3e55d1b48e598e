"""A vehicle handed over between services sharing a fleet ([fleet] sharding = "rendezvous") during
a live satellite fault keeps the satellite the old service's MHSS monitor had excluded (real
processes: fednav-router, two fednav-service, fednav-sim on the demo_product scenario, a plain
Zenoh client).

The process version of tests/test_lifecycle.py::test_a_hand_over_keeps_the_satellites_integrity_excluded:
the demo's GEO3 pseudorange ramp (30-110 s) is excluded by service A's tc_mhss monitor; at ~95 s
the simulator is paused (SIGSTOP), A is killed with kill -9 once it has processed everything,
service B sees A's fleet token vanish, then the simulator resumes: B takes the vehicle over from
A's last HandoverState (received over Zenoh) and must keep the satellite out from its first
epoch on. The pause only makes the split of the Integrity stream between A and B exact (both
publish on the same key); the handover itself is the live one (token gone, state from the bus).
"""

from __future__ import annotations

import json
import signal
import sys
import threading
import time
import tomllib

import pytest

from fednav.service import fleet
from fednav.simulators.processes import Proc, free_port, stop_all

from .scenario_utils import SCENARIOS
from .test_fleet_sharding import _router, _service, _zid

pytestmark = pytest.mark.integration

VEHICLE = "v1"
PIPELINE = "tc_mhss"
SEED = 4  # the seed of the in-process test
PACE = 8.0  # x real time: ~95 s of scenario in ~12 s
T_PAUSE_S = 95.0  # scenario time at which A is stopped (the GEO3 ramp runs 30-110 s)
FAULT_START_S, FAULT_END_S = 30.0, 110.0
_DEMO = tomllib.loads((SCENARIOS / "demo_product.toml").read_text())
T0 = float(_DEMO["t0_gps_s"])


def _toml(v) -> str:
    """A TOML value (inline tables for dicts) of a parsed scenario's service settings."""
    if isinstance(v, bool):
        return "true" if v else "false"
    if isinstance(v, int | float):
        return repr(v)
    if isinstance(v, str):
        return json.dumps(v)
    if isinstance(v, list):
        return "[" + ", ".join(_toml(x) for x in v) + "]"
    if isinstance(v, dict):
        return "{ " + ", ".join(f"{k} = {_toml(x)}" for k, x in v.items()) + " }"
    raise TypeError(f"no TOML for {v!r}")


def _service_config(tmp_path):
    """The demo's tc_mhss pipeline and IMU model, every vehicle, shared by rendezvous (states
    published every 0.25 s of wall time)."""
    svc = _DEMO["service"]
    tc = next(p for p in svc["pipelines"] if p["name"] == PIPELINE)
    imu = "\n".join(f"{k} = {_toml(v)}" for k, v in svc["imu"].items())
    cfg = tmp_path / "svc.toml"
    cfg.write_text(
        f'vehicles = ["*"]\npipelines = [{_toml(tc)}]\n[imu]\n{imu}\n'
        '[zenoh]\nmode = "client"\n[fleet]\nsharding = "rendezvous"\nhandover_period_s = 0.25\n'
    )
    return cfg


def _ids() -> tuple[str, str]:
    """Two Zenoh ids (hex, as in split_zids); the first owns VEHICLE when both are up."""
    a, b = f"fed{1:029x}", f"fed{2:029x}"
    return (a, b) if fleet.owner(VEHICLE, [a, b]) == a else (b, a)


class _Bus:
    """A plain Zenoh client: the vehicle's Integrity of PIPELINE and Health, every ServiceHealth."""

    def __init__(self, port: int):
        import zenoh

        from fednav.service.config import ZenohConfig
        from fednav.service.transport.zenoh_io import make_config

        self.s = zenoh.open(
            make_config(ZenohConfig(mode="client"), listen=[], connect=[f"tcp/127.0.0.1:{port}"])
        )
        self.lock = threading.Lock()
        self.integrity: list[dict] = []
        self.health: list[tuple[float, dict]] = []  # (wall, Health)
        self.services: list[tuple[float, str, dict]] = []  # (wall, zid, ServiceHealth)
        self.s.declare_subscriber(f"fednav/{VEHICLE}/nav/{PIPELINE}/integrity", self._integrity)
        self.s.declare_subscriber(f"fednav/{VEHICLE}/service/health", self._health)
        self.s.declare_subscriber("fednav/_services/*/health", self._service)

    def _integrity(self, sample) -> None:
        m = json.loads(sample.payload.to_bytes())
        with self.lock:
            self.integrity.append(m)

    def _health(self, sample) -> None:
        m = json.loads(sample.payload.to_bytes())
        with self.lock:
            self.health.append((time.monotonic(), m))

    def _service(self, sample) -> None:
        zid = str(sample.key_expr).split("/")[2]
        m = json.loads(sample.payload.to_bytes())
        with self.lock:
            self.services.append((time.monotonic(), zid, m))

    def messages(self) -> list[dict]:
        with self.lock:
            return list(self.integrity)

    def members(self, zid: str, since: float) -> list[str] | None:
        """The fleet members in ``zid``'s latest ServiceHealth received after ``since``."""
        with self.lock:
            got = [m for w, z, m in self.services if z == zid and w >= since]
        return sorted(got[-1]["fleet_members"]) if got else None

    def healths(self, since: float) -> list[dict]:
        with self.lock:
            return [m for w, m in self.health if w >= since]

    def close(self) -> None:
        self.s.close()


def _wait(cond, timeout: float, poll_s: float = 0.05) -> bool:
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        if cond():
            return True
        time.sleep(poll_s)
    return bool(cond())


def _used(m: dict) -> set[str]:
    return {s["id"] for s in m["satellites"]}


def test_a_process_handover_during_a_satellite_fault_keeps_the_satellite_excluded(tmp_path):
    cfg = _service_config(tmp_path)
    id_a, id_b = _ids()
    port = free_port()
    router = _router(port)
    procs = [router]
    bus = _Bus(port)
    sim = None
    try:
        a = _service(port, cfg, id_a, tmp_path)
        procs.append(a)
        b = _service(port, cfg, id_b, tmp_path)
        procs.append(b)
        assert (_zid(a), _zid(b)) == (id_a, id_b)
        # settled: each service has joined and counts both members (then A owns the vehicle)
        t_up = time.monotonic()
        both = sorted([id_a, id_b])
        assert _wait(lambda: bus.members(id_a, t_up) == both and bus.members(id_b, t_up) == both, 30), (
            a.output(),
            b.output(),
        )
        assert "joined fleet group" in a.output() and "joined fleet group" in b.output()
        sim = Proc(
            [sys.executable, "-m", "fednav.simulators", "run", "demo_product", "--speed", str(PACE)]
            + ["--seed", str(SEED), "--vehicle", VEHICLE, "--connect", f"tcp/127.0.0.1:{port}"],
            "fednav-sim",
        )
        procs.append(sim)

        def excluded_late() -> bool:
            ms = bus.messages()
            return bool(ms) and ms[-1]["t"] - T0 >= T_PAUSE_S and bool(ms[-1]["excluded"])

        assert _wait(excluded_late, 90), (bus.messages()[-1:], sim.output(), a.output())
        sim.signal(signal.SIGSTOP)  # the fault still live; A finishes what it has received
        t_stop = time.monotonic()

        def drained() -> bool:  # A's Health after the pause: nothing left in its queue
            hs = bus.healths(t_stop + 0.2)
            return bool(hs) and hs[-1]["queue_depth"] == 0

        assert _wait(drained, 15), bus.healths(t_stop)[-1:]
        n = -1
        while n != len(bus.messages()):  # and no Integrity for 0.8 s: A has processed everything
            n = len(bus.messages())
            time.sleep(0.8)
        msgs_a = bus.messages()
        last_a = msgs_a[-1]
        assert FAULT_START_S < last_a["t"] - T0 < FAULT_END_S - 10.0, last_a["t"] - T0
        excluded = set(last_a["excluded"])
        # control, A (the old service): the satellite was used before its fault, its fault
        # detected, then excluded: the hand-over below has something to carry
        before = [m for m in msgs_a if m["t"] - T0 < FAULT_START_S]
        assert len(before) >= 50, len(before)
        assert all(excluded <= _used(m) and not m["excluded"] for m in before)
        detections = [m for m in msgs_a if m["detected"]]
        assert detections and detections[0]["t"] - T0 > FAULT_START_S, detections[:1]
        assert not (excluded & _used(last_a)) and not last_a["alarm"], last_a
        assert "handed over" not in a.output() + b.output()

        a.kill()  # kill -9 during the fault
        t_kill = time.monotonic()
        assert _wait(lambda: bus.members(id_b, t_kill + 0.1) == [id_b], 15), b.output()
        assert len(bus.messages()) == len(msgs_a)  # nothing from B yet: the stream is paused
        sim.signal(signal.SIGCONT)
        t_resume = time.monotonic()

        def b_went_past_the_fault() -> bool:
            ms = bus.messages()[len(msgs_a) :]
            return bool(ms) and ms[-1]["t"] - T0 >= FAULT_END_S

        assert _wait(b_went_past_the_fault, 30), (bus.messages()[-1:], b.output())
        assert f"vehicle {VEHICLE} handed over from service {id_a}" in b.output(), b.output()
        msgs_b = bus.messages()[len(msgs_a) :]
        live = [m for m in msgs_b if m["t"] - T0 < FAULT_END_S]
        # B started from A's state at once (no alignment of its own): its first epoch follows A's last
        assert 0.0 < msgs_b[0]["t"] - last_a["t"] < 1.0, (last_a["t"], msgs_b[0]["t"])
        assert len(live) >= 25, len(live)
        # the faulty satellite stays out from B's first epoch on: nothing to detect. (Without the
        # carried exclusions B's first epoch detects it anew and excludes it at once: that epoch's
        # `excluded` and `satellites` look the same, its `detected` does not.)
        for m in live:
            assert excluded <= set(m["excluded"]), (m["t"] - T0, m["excluded"], _used(m))
            assert not (excluded & _used(m)), (m["t"] - T0, _used(m))
            assert not m["detected"] and not m["alarm"], (m["t"] - T0, m["detected_by"], m["alarm"])

        def noted() -> list[dict]:
            return [h for h in bus.healths(t_resume) if h["notes"].get(f"handed_over_from:{id_a}") == 1]

        assert _wait(lambda: bool(noted()), 10), bus.healths(t_resume)[-1:]
        assert noted()[-1]["notes"].get("handover_exclusions") == len(excluded), noted()[-1]["notes"]
    finally:
        stop_all(procs)  # the simulator continued first if it is stopped
        bus.close()
