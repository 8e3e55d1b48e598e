"""Process wiring of fednav-service: Zenoh intake -> per-vehicle workers -> Zenoh + Rerun.

Threads: the Zenoh intake thread (reads the subscriber FIFO, routes by vehicle), one worker per
vehicle (validates, runs the engine in sensor-time order, publishes), the query server. Signals
(SIGINT/SIGTERM) set a stop event; ``stop()`` then stops intake, lets each worker drain its queue,
emits the last solutions and health, closes the recording (complete, readable) and the session.
"""

from __future__ import annotations

import json
import logging
import queue
import threading
import time
from collections import Counter, deque
from datetime import datetime
from pathlib import Path

import numpy as np
from pydantic import ValidationError

from service import earth, keys
from service.config import ServiceConfig
from service.engine import VehicleEngine
from service.messages import (
    SENSOR_MESSAGES,
    Faults,
    Health,
    ImmModels,
    Integrity,
    PipelineHealth,
    Solution,
    Truth,
    WireModel,
)
from service.pipelines.base import error_dict

log = logging.getLogger("fednav.service")

MAX_PAYLOAD_BYTES = 1 << 20
_RANGE_ERRORS = {"greater_than", "greater_than_equal", "less_than", "less_than_equal"}


def classify(err: ValidationError) -> str:
    """Rejection reason of a pydantic validation error (counted in Health)."""
    types = {e["type"] for e in err.errors()}
    if "json_invalid" in types or "json_type" in types:
        return "malformed_json"
    if "finite_number" in types:
        return "non_finite"
    if "value_error" in types:
        return "absurd_value"
    if types & _RANGE_ERRORS:
        return "out_of_range"
    return "schema"


def _blueprint_plugin(pipelines: dict[str, str]):
    """A blueprint factory from the ``fednav.blueprints`` entry point (dashboards registers one).

    Discovered by entry point so the service never imports dashboards (dependency direction);
    without the plugin the recording is still complete, only without an embedded layout.
    """
    from importlib.metadata import entry_points

    for ep in entry_points(group="fednav.blueprints"):
        try:
            return ep.load()(pipelines)
        except Exception as exc:  # a broken plugin must not stop the service
            log.warning("blueprint plugin %s failed: %s", ep.name, exc)
    return None


class _RateLimitedLog:
    def __init__(self, period_s: float = 5.0):
        self.period_s = period_s
        self._last: dict[str, float] = {}

    def warn(self, reason: str, text: str) -> None:
        now = time.monotonic()
        if now - self._last.get(reason, -1e9) >= self.period_s:
            self._last[reason] = now
            log.warning("%s: %s", reason, text)


class OutputSink:
    """Engine sink of the service: publish on Zenoh, record to Rerun."""

    def __init__(self, prefix: str, publishers, rerun_sink):
        self.prefix = prefix
        self.pubs = publishers
        self.rr = rerun_sink
        self.last_solution: dict[tuple[str, str], Solution] = {}

    def on_solution(self, vehicle: str, sol: Solution, err9, P9) -> None:
        self.pubs.publish(keys.nav(vehicle, sol.pipeline, "solution", self.prefix), sol)
        self.last_solution[(vehicle, sol.pipeline)] = sol
        if self.rr is not None:
            self.rr.log_solution(vehicle, sol)
            if err9 is not None:
                e = error_dict(err9)
                sd = np.sqrt(np.clip(np.diagonal(P9), 0.0, None))
                errors = {
                    "east_m": e["lon_m"],
                    "north_m": e["lat_m"],
                    "up_m": e["h_m"],
                    "ve_mps": e["ve_mps"],
                    "vn_mps": e["vn_mps"],
                    "vu_mps": e["vu_mps"],
                    "phi_e_arcsec": e["phi_e_arcsec"],
                    "phi_n_arcsec": e["phi_n_arcsec"],
                    "phi_u_arcsec": e["phi_u_arcsec"],
                }
                scale = np.r_[np.ones(6), np.full(3, 1.0 / earth.ARCSEC)]  # phi in arcsec
                bounds = {n: float(3.0 * sd[i] * scale[i]) for i, n in enumerate(errors)}
                self.rr.log_errors(vehicle, sol.pipeline, sol.t, errors, bounds)

    def on_output(self, vehicle: str, msg: WireModel, err9=None) -> None:
        what = "faults" if isinstance(msg, Faults) else "integrity" if isinstance(msg, Integrity) else None
        if isinstance(msg, ImmModels):
            what = "models"
        if what is None:
            return
        self.pubs.publish(keys.nav(vehicle, msg.pipeline, what, self.prefix), msg)
        if self.rr is not None:
            if what == "models":
                self.rr.log_imm(vehicle, msg)
            elif what == "faults":
                self.rr.log_faults(vehicle, msg)
            else:
                h_err = float(np.hypot(err9[0], err9[1])) if err9 is not None else None
                v_err = float(abs(err9[2])) if err9 is not None else None
                self.rr.log_integrity(vehicle, msg, h_error_m=h_err, v_error_m=v_err)

    def on_truth(self, vehicle: str, truth: Truth) -> None:
        if self.rr is not None:
            self.rr.log_truth(vehicle, truth)


class VehicleWorker:
    """One vehicle: a bounded queue and a thread running its engine in arrival (= sensor) order."""

    def __init__(self, vehicle: str, config: ServiceConfig, sink: OutputSink, publishers, rr):
        self.vehicle = vehicle
        self.config = config
        self.sink = sink
        self.pubs = publishers
        self.rr = rr
        self.counters: Counter = Counter()
        self.received = 0
        self.accepted = 0
        self.dropped = 0
        self.engine = VehicleEngine(vehicle, config, sink, self.counters)
        self.q: queue.Queue = queue.Queue(maxsize=config.intake.queue_size)
        self.latency_s: deque = deque(maxlen=2000)
        self.started = time.monotonic()
        self._rlog = _RateLimitedLog()
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, name=f"fednav-{vehicle}", daemon=True)
        self._thread.start()

    def submit(self, wall: float, kind: str, sensor_id: str, payload: bytes) -> None:
        item = (wall, kind, sensor_id, payload)
        if self.config.intake.overload == "block":
            self.q.put(item)
        else:
            try:
                self.q.put_nowait(item)
            except queue.Full:
                self.dropped += 1

    def reject(self, reason: str, text: str = "") -> None:
        self.counters[reason] += 1
        self._rlog.warn(reason, f"{self.vehicle}: {text}")

    def _process(self, item) -> None:
        wall, kind, sensor_id, payload = item
        self.received += 1
        if len(payload) > MAX_PAYLOAD_BYTES:
            self.reject("oversize", f"{kind} payload of {len(payload)} bytes")
            return
        try:
            msg = SENSOR_MESSAGES[kind].model_validate_json(payload)
        except ValidationError as err:
            reason = classify(err)
            self.reject(reason, f"{kind}/{sensor_id}: {err.errors()[0]['msg']}")
            return
        try:
            ok = self.engine.handle(kind, sensor_id, msg)
        except Exception:  # never let a pipeline bug kill the vehicle worker
            log.exception("engine failure on %s/%s", kind, sensor_id)
            self.counters["internal_error"] += 1
            return
        if ok:
            self.accepted += 1
        self.latency_s.append(time.monotonic() - wall)

    def _run(self) -> None:
        period = self.config.output.health_period_s
        next_health = time.monotonic() + period
        while True:
            try:
                item = self.q.get(timeout=0.05)
            except queue.Empty:
                item = None
            if item is not None:
                self._process(item)
            now = time.monotonic()
            if now >= next_health:
                self.publish_health()
                next_health = now + period
            if item is None and self._stop.is_set():
                break

    def health(self) -> Health:
        lat = np.array(self.latency_s) * 1e3 if self.latency_s else np.zeros(1)
        states = self.engine.pipeline_states()
        return Health(
            t=self.engine.last_t,
            uptime_s=time.monotonic() - self.started,
            received=self.received,
            accepted=self.accepted,
            rejected=dict(self.counters),
            dropped_overload=self.dropped,
            queue_depth=self.q.qsize(),
            latency_ms={
                "p50": float(np.percentile(lat, 50)),
                "p99": float(np.percentile(lat, 99)),
                "max": float(lat.max()),
            },
            pipelines={k: PipelineHealth(**v) for k, v in states.items()},
        )

    def publish_health(self) -> None:
        h = self.health()
        self.pubs.publish(keys.service(self.vehicle, "health", self.config.prefix), h)
        if self.rr is not None:
            self.rr.log_health(self.vehicle, h)

    def stop(self) -> None:
        """Drain the queue, emit the last solutions and health."""
        self._stop.set()
        self._thread.join(timeout=60.0)
        if self.engine.initialised:
            self.engine.emit_solutions()
        self.publish_health()


class Service:
    def __init__(
        self,
        config: ServiceConfig,
        rrd: Path | None = None,
        viewer: str | None = None,
        listen: list[str] | None = None,
        connect: list[str] | None = None,
        zenoh_config_file: str | None = None,
        record: bool = True,
    ):
        self.config = config
        self.rrd_path = rrd or config.rrd or Path("recordings") / f"fednav-{datetime.now():%Y%m%d-%H%M%S}.rrd"
        self.viewer = viewer or config.viewer
        self.listen, self.connect, self.zenoh_config_file = listen, connect, zenoh_config_file
        self.record = record
        self.workers: dict[str, VehicleWorker] = {}
        self.unrouted = Counter()
        self._lock = threading.Lock()
        self.session = None

    # --- lifecycle ------------------------------------------------------------------------------
    def start(self) -> None:
        import zenoh

        from service.transport import zenoh_io

        cfg = self.config
        self.rr = None
        if self.record:
            from service.transport.rerun_sink import RerunSink

            Path(self.rrd_path).parent.mkdir(parents=True, exist_ok=True)
            blueprint = _blueprint_plugin({p.name: p.kind for p in cfg.pipelines})
            self.rr = RerunSink(self.rrd_path, viewer_addr=self.viewer, blueprint=blueprint)
        self.session = zenoh.open(
            zenoh_io.make_config(cfg.zenoh, self.listen, self.connect, self.zenoh_config_file)
        )
        self.pubs = zenoh_io.Publishers(self.session, block=True)
        self.sink = OutputSink(cfg.prefix, self.pubs, self.rr)
        sel = "*" if "*" in cfg.vehicles else None
        exprs = []
        for v in [sel] if sel else cfg.vehicles:
            exprs += keys.inputs_selector(v, cfg.prefix)
        self.intake = zenoh_io.Intake(self.session, exprs, self._deliver)
        qexprs = [f"{cfg.prefix}/{v}/service/status" for v in ([sel] if sel else cfg.vehicles)]
        qexprs += [f"{cfg.prefix}/{v}/service/config" for v in ([sel] if sel else cfg.vehicles)]
        self.queries = zenoh_io.QueryServer(self.session, qexprs, self._answer)
        log.info(
            "fednav-service up: vehicles=%s pipelines=%s rrd=%s",
            cfg.vehicles,
            [p.name for p in cfg.pipelines],
            self.rrd_path if self.record else None,
        )

    def _worker(self, vehicle: str) -> VehicleWorker:
        w = self.workers.get(vehicle)
        if w is None:
            with self._lock:
                w = self.workers.get(vehicle)
                if w is None:
                    w = VehicleWorker(vehicle, self.config, self.sink, self.pubs, self.rr)
                    self.workers[vehicle] = w
        return w

    def _deliver(self, wall: float, key: str, payload: bytes) -> None:
        pk = keys.parse_input(key, self.config.prefix)
        if pk is None and keys.is_output(key, self.config.prefix):
            return  # another fednav service's outputs share the prefix: not input, not an error
        parts = key.split("/")
        vehicle = parts[1] if len(parts) > 1 else ""
        if "*" not in self.config.vehicles and vehicle not in self.config.vehicles:
            return
        w = self._worker(vehicle) if vehicle else None
        if pk is None:
            if w is not None:
                w.received += 1
                w.reject("unknown_key", key)
            else:
                self.unrouted["unknown_key"] += 1
            return
        w.submit(wall, pk.kind, pk.sensor_id, payload)

    def _answer(self, key: str) -> bytes:
        parts = key.split("/")
        vehicle = parts[1] if len(parts) > 1 else ""
        if key.endswith("/config"):
            return self.config.model_dump_json().encode()
        w = self.workers.get(vehicle)
        state = {
            "vehicle": vehicle,
            "running": True,
            "pipelines": [p.name for p in self.config.pipelines],
            "health": json.loads(w.health().model_dump_json()) if w else None,
        }
        return json.dumps(state).encode()

    def stop(self) -> None:
        if self.session is None:
            return
        self.intake.stop()
        for w in list(self.workers.values()):
            w.stop()
        self.queries.stop()
        if self.rr is not None:
            self.rr.close()
        self.pubs.undeclare_all()
        self.session.close()
        self.session = None
        log.info("fednav-service stopped; recording %s", self.rrd_path if self.record else None)
