"""A plain Zenoh client watching a fleet: Solutions and Truth per vehicle, each service's active
vehicles (ServiceHealth); errors, gaps and duplicates from them (tests and fleet benchmarks)."""

from __future__ import annotations

import json
import math
import threading
import time

import numpy as np


class FleetWatch:
    """Subscribes (client mode, loopback ``port``) to every vehicle's Solutions of ``pipeline``,
    Truth and every service's ServiceHealth."""

    def __init__(self, port: int, pipeline: str = "lc", prefix: str = "fednav"):
        import zenoh

        from fednav.service.config import ZenohConfig
        from fednav.service.transport.zenoh_io import make_config

        self.s = zenoh.open(
            make_config(ZenohConfig(mode="client"), listen=[], connect=[f"tcp/127.0.0.1:{port}"])
        )
        self.lock = threading.Lock()
        self.sols: dict[str, list[tuple[float, float, dict]]] = {}  # vehicle -> (wall, t, solution)
        self.truth: dict[tuple[str, int], dict] = {}
        self.services: dict[str, tuple[float, list[str]]] = {}  # zid -> (wall, active vehicles)
        self.health: dict[str, dict] = {}  # zid -> its latest ServiceHealth
        self.s.declare_subscriber(f"{prefix}/*/nav/{pipeline}/solution", self._sol)
        self.s.declare_subscriber(f"{prefix}/*/truth", self._truth)
        self.s.declare_subscriber(f"{prefix}/_services/*/health", self._health)

    def close(self) -> None:
        self.s.close()

    def _sol(self, sample):
        v = str(sample.key_expr).split("/")[1]
        m = json.loads(sample.payload.to_bytes())
        with self.lock:
            self.sols.setdefault(v, []).append((time.monotonic(), m["t"], m))

    def _truth(self, sample):
        v = str(sample.key_expr).split("/")[1]
        m = json.loads(sample.payload.to_bytes())
        with self.lock:
            self.truth[(v, round(m["t"] * 1e6))] = m

    def _health(self, sample):
        zid = str(sample.key_expr).split("/")[2]
        m = json.loads(sample.payload.to_bytes())
        with self.lock:
            self.services[zid] = (time.monotonic(), m["active_vehicles"])
            self.health[zid] = m

    def assignment(self, since: float) -> dict[str, list[str]]:
        with self.lock:
            return {z: list(v) for z, (w, v) in self.services.items() if w >= since}

    def h_errors(self, vehicle: str, t_from: float, t_to: float) -> np.ndarray:
        """Horizontal errors (m) of the vehicle's Solutions with sensor time in [t_from, t_to)."""
        out = []
        with self.lock:
            for _, t, m in self.sols.get(vehicle, []):
                tr = self.truth.get((vehicle, round(t * 1e6)))
                if tr is None or not t_from <= t < t_to:
                    continue
                dn = math.radians(m["lat_deg"] - tr["lat_deg"]) * 6.371e6
                de = (
                    math.radians(m["lon_deg"] - tr["lon_deg"])
                    * 6.371e6
                    * math.cos(math.radians(tr["lat_deg"]))
                )
                out.append(math.hypot(de, dn))
        return np.array(out)

    def last_t(self, vehicle: str) -> float:
        with self.lock:
            return max((t for _, t, _ in self.sols.get(vehicle, [])), default=-math.inf)

    def duplicates(self, vehicle: str, after_wall: float) -> int:
        with self.lock:
            ts = [t for w, t, _ in self.sols.get(vehicle, []) if w >= after_wall]
        return len(ts) - len(set(ts))
