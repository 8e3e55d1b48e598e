"""Process wiring of fednav-service: Zenoh intake -> per-vehicle workers -> Zenoh + Rerun.

Threads: the Zenoh intake thread (reads the subscriber FIFO, routes by vehicle), one worker per
vehicle (validates, runs the engine in sensor-time order, publishes), the query server. Signals
(SIGINT/SIGTERM) set a stop event; ``stop()`` then stops intake, lets each worker drain its queue,
emits the last solutions and health, closes the recording (complete, readable) and the session.
"""

from __future__ import annotations

import functools
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

from fednav.service import keys
from fednav.service.config import ServiceConfig, recording_kinds
from fednav.service.engine import EstimateOutput, VehicleEngine
from fednav.service.evaluation import recording_errors
from fednav.service.messages import (
    SENSOR_MESSAGES,
    Alignment,
    Faults,
    Health,
    ImmModels,
    Integrity,
    PipelineHealth,
    ServiceHealth,
    Solution,
    Truth,
    WireModel,
)
from fednav.service.transport import rerun_paths as paths

log = logging.getLogger("fednav.service")

MAX_PAYLOAD_BYTES = 1 << 20
#: at shutdown the vehicles' queues drain for at most this long together (then the rest is
#: counted in the log and the recording is closed: SIGTERM returns within seconds)
_SHUTDOWN_DRAIN_S = 5.0
_MAX_LOGGED_NAMES = 100
#: encodings of the queryables' JSON replies (the samples carry application/json;fednav.<Type>/1)
STATUS_ENCODING = "application/json;fednav.Status/1"
CONFIG_ENCODING = "application/json;fednav.ServiceConfig/1"
#: wall seconds without a message from a stream after which Health calls it stale
STALE_WALL_S = 2.0
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


@functools.lru_cache(maxsize=256)
def alignment_styles(node: str) -> dict[str, tuple[str, int]]:
    """Legend labels and colours of one node's error series (``alignment_error`` group): the
    error per axis in its axis colour, the +-3 sigma bounds in the same colour."""
    out = {}
    for quantity in ("misalignment", "flexure", "lever"):
        for a, colour in zip("xyz", paths.AXIS_COLOURS, strict=True):
            key = f"{node}.{quantity}_{a}"
            out[key] = (f"{a} error", colour)
            out[key + "_p3s"] = (f"{a} +3σ", colour)
            out[key + "_m3s"] = (f"{a} −3σ", colour)
    return out


def alignment_scalars(msg: Alignment, truth=None) -> dict[str, dict[str, float]]:
    """Recording groups of one node's alignment (``/{vehicle}/{pipeline}/{group}/{node}.{name}``):
    estimates, and with the node's truth the errors and their 3-sigma bounds (misalignment and
    flexure in arcmin, lever arm in m), adaptive R (1 sigma) and the fading factor."""
    n = msg.node
    ax = "xyz"
    est = {f"{n}.lever_{ax[i]}_m": msg.lever_arm_m[i] for i in range(3)}
    est |= {f"{n}.flexure_{ax[i]}_deg": msg.flexure_deg[i] for i in range(3)}
    est |= {f"{n}.mount_{ax[i]}_deg": msg.mount_deg[i] for i in range(3)}
    adaptive = {f"{n}.r_std_{i}": v for i, v in enumerate(msg.r_std)} | {
        f"{n}.fading": msg.fading,
        f"{n}.nis": msg.nis,
    }
    out = {"alignment": est, "alignment_adaptive": adaptive}
    if truth is not None:
        err, bnd = {}, {}
        for i in range(3):
            for name, e, s, scale in (
                ("misalignment", msg.mount_deg[i] - truth.mount_deg[i], msg.misalignment_std_deg[i], 60.0),
                ("flexure", msg.flexure_deg[i] - truth.flexure_deg[i], msg.flexure_std_deg[i], 60.0),
                ("lever", msg.lever_arm_m[i] - truth.lever_arm_m[i], msg.lever_arm_std_m[i], 1.0),
            ):
                key = f"{n}.{name}_{ax[i]}"
                err[key] = e * scale
                bnd[key + "_p3s"] = 3.0 * s * scale
                bnd[key + "_m3s"] = -3.0 * s * scale
        out["alignment_error"] = err | bnd
    return out


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

    def __init__(self, prefix: str, publishers, rerun_sink, extra=()):
        self.prefix = prefix
        self.pubs = publishers
        self.rr = rerun_sink
        self.extra = list(extra)  # more sinks (the ROS 2 bridge); their failures are logged, not raised
        self.last_solution: dict[tuple[str, str], Solution] = {}
        self._rlog = _RateLimitedLog()

    def _forward(self, method: str, *args) -> None:
        for s in self.extra:
            try:
                getattr(s, method)(*args)
            except Exception as exc:
                self._rlog.warn("output_sink_error", f"{type(s).__name__}.{method}: {exc!r}")

    def on_health(self, vehicle: str, health: Health) -> None:
        self._forward("on_health", vehicle, health)

    def on_estimate(self, vehicle: str, out: EstimateOutput) -> None:
        sol = out.solution()
        self.pubs.publish(keys.nav(vehicle, sol.pipeline, "solution", self.prefix), sol)
        self.last_solution[(vehicle, sol.pipeline)] = sol
        if self.rr is not None:
            self.rr.log_solution(vehicle, sol)
            if out.err9 is not None:
                errors, bounds = recording_errors(out.err9, out.P9)
                self.rr.log_errors(vehicle, sol.pipeline, sol.t, errors, bounds)
        self._forward("on_estimate", vehicle, out)

    def on_output(self, vehicle: str, msg: WireModel, err9=None) -> None:
        self._forward("on_output", vehicle, msg, err9)
        if isinstance(msg, Alignment):  # transfer alignment (seed 002); err9: the node's truth
            self.pubs.publish(keys.alignment(vehicle, msg.pipeline, msg.node, self.prefix), msg)
            if self.rr is not None:
                styles = alignment_styles(msg.node)
                for group, values in alignment_scalars(msg, err9).items():
                    self.rr.log_scalars(vehicle, msg.pipeline, msg.t, group, values, styles)
            return
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
        self.arrivals: dict[str, float] = {}  # stream -> monotonic arrival time of its last message
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

    def submit_rejection(self, wall: float, reason: str, text: str) -> None:
        """A message refused before it became a wire message (e.g. ROS 2 CDR that does not decode):
        counted by the worker like every other rejection."""
        self.submit(wall, None, reason, text.encode())

    def reject(self, reason: str, text: str = "") -> None:
        self.counters[reason] += 1
        self._rlog.warn(reason, f"{self.vehicle}: {text}")

    def _process(self, item) -> None:
        wall, kind, sensor_id, payload = item
        self.received += 1
        if kind is None:  # submit_rejection: sensor_id is the reason
            self.reject(sensor_id, payload.decode())
            return
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
            self.arrivals[f"{kind}/{sensor_id}" if sensor_id else kind] = wall
            if kind == "gnss_fix" and self.rr is not None:  # raw fixes on the ENU trajectory view
                self.rr.log_fix(self.vehicle, sensor_id, msg)
        self.latency_s.append(time.monotonic() - wall)

    def _run(self) -> None:
        period = self.config.output.health_period_s
        next_health = time.monotonic() + period
        while True:
            try:
                item = self.q.get(timeout=0.05)
            except queue.Empty:
                item = None
            try:  # nothing a message or a sink does may end this vehicle's thread
                if item is not None:
                    self._process(item)
                now = time.monotonic()
                if now >= next_health:
                    next_health = now + period
                    self.publish_health()
            except Exception:
                log.exception("vehicle %s: worker error", self.vehicle)
                self.counters["internal_error"] += 1
            if item is None and self._stop.is_set():
                break

    def health(self) -> Health:
        lat = np.array(self.latency_s) * 1e3 if self.latency_s else np.zeros(1)
        states = self.engine.pipeline_states()
        # the sensor-time view cannot see a stream that stopped arriving: streams silent for
        # STALE_WALL_S of wall time are stale, and no pipeline is aided while its input is silent
        now = time.monotonic()
        silent = {
            k for k, w in self.arrivals.items() if now - w > STALE_WALL_S and k not in ("truth", "init")
        }
        stale = sorted(set(self.engine.stale_streams()) | silent)
        if self.arrivals and now - max(self.arrivals.values()) > STALE_WALL_S:
            for st in states.values():
                if st["status"] in ("aided", "degraded", "unaided"):
                    st["status"] = "coasting"
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
            sensors={k: t for k, (t, _) in self.engine.streams.items()},
            stale=stale,
            time_base_mismatch=dict(self.engine.time_base_mismatch),
        )

    def publish_health(self) -> None:
        h = self.health()
        self.pubs.publish(keys.service(self.vehicle, "health", self.config.prefix), h)
        self.sink.on_health(self.vehicle, h)
        if self.rr is not None:
            self.rr.log_health(self.vehicle, h)

    def request_stop(self) -> None:
        """Ask the thread to finish: it drains its queue, then ends."""
        self._stop.set()

    def stop(self, deadline: float | None = None) -> None:
        """Drain the queue (until ``deadline``, monotonic seconds), emit the last solutions and
        health."""
        self._stop.set()
        self._thread.join(timeout=None if deadline is None else max(0.0, deadline - time.monotonic()))
        if self._thread.is_alive():
            log.warning("vehicle %s: %d events not processed at shutdown", self.vehicle, self.q.qsize())
            return
        try:
            if self.engine.initialised:
                self.engine.emit_solutions()
            self.publish_health()
        except Exception:
            log.exception("vehicle %s: final outputs failed", self.vehicle)


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
        self.unrouted = Counter()  # data refused before any vehicle: by reason
        self.unserved = Counter()  # messages per vehicle name not served (first _MAX_LOGGED_NAMES)
        self.started = time.monotonic()
        self._health_stop = threading.Event()
        self._logged: set[tuple[str, str]] = set()
        self._lock = threading.Lock()
        self.session = None

    # --- lifecycle ------------------------------------------------------------------------------
    def start(self) -> None:
        import zenoh

        from fednav.service.transport import zenoh_io

        cfg = self.config
        self.rr = None
        if self.record:
            from fednav.service.transport.rerun_sink import RerunSink

            Path(self.rrd_path).parent.mkdir(parents=True, exist_ok=True)
            blueprint = _blueprint_plugin(recording_kinds(cfg.pipelines))
            self.rr = RerunSink(
                self.rrd_path,
                viewer_addr=self.viewer,
                blueprint=blueprint,
                flush_interval_s=cfg.rrd_flush_interval_s,
                decimation=cfg.rrd_decimation,
                slow_flush_interval_s=cfg.rrd_slow_flush_interval_s,
                optimize_on_close=cfg.rrd_optimize,
            )
        self.session = zenoh.open(
            zenoh_io.make_config(
                cfg.zenoh, self.listen, self.connect, self.zenoh_config_file, outputs_prefix=cfg.prefix
            )
        )
        self.pubs = zenoh_io.Publishers(self.session, block=True)
        self.liveliness = zenoh_io.Liveliness(self.session)
        self.ros_in = None
        extra = [self._start_ros2()] if cfg.ros2 is not None else []
        self.sink = OutputSink(cfg.prefix, self.pubs, self.rr, extra)
        sel = "*" if "*" in cfg.vehicles else None
        # by default every vehicle's inputs, served or not: data under a name the service does not
        # serve is counted (ServiceHealth) and logged once per name instead of meeting silence;
        # intake.subscribe = "served": only the served vehicles' keys (services sharing a fleet)
        served_only = cfg.intake.subscribe == "served" and sel is None
        selectors = (
            [e for v in cfg.vehicles for e in keys.inputs_selector(v, cfg.prefix)]
            if served_only
            else keys.inputs_selector("*", cfg.prefix)
        )
        self.intake = zenoh_io.Intake(self.session, selectors, self._deliver)
        self.ros_intake = None
        if self.ros_in is not None and self.ros_in.key_exprs():
            from fednav.service.transport.ros2 import header_stamp_s

            self.ros_intake = zenoh_io.Intake(
                self.session, self.ros_in.key_exprs(), self._deliver_ros, order_key=header_stamp_s
            )
        # one queryable per vehicle selector: status, config and each pipeline's latest solution
        qexprs = [f"{cfg.prefix}/{v}/**" for v in ([sel] if sel else cfg.vehicles)]
        self.queries = zenoh_io.QueryServer(self.session, qexprs, self._answer)
        self.liveliness.declare(keys.service_token(str(self.session.zid()), cfg.prefix))
        for v in [] if sel else cfg.vehicles:
            self.liveliness.declare(keys.service(v, "alive", cfg.prefix))
        self._health_key = keys.service_health(str(self.session.zid()), cfg.prefix)
        self._health_thread = threading.Thread(
            target=self._health_loop, name="fednav-service-health", daemon=True
        )
        self._health_thread.start()
        log.info(
            "fednav-service up: vehicles=%s pipelines=%s rrd=%s",
            cfg.vehicles,
            [p.name for p in cfg.pipelines],
            self.rrd_path if self.record else None,
        )

    def _start_ros2(self):
        """The ROS 2 bridge (docs/ros2.md): its input decoder and its output sink."""
        import hashlib

        from fednav.service.transport import ros2

        cfg = self.config.ros2
        if "*" not in self.config.vehicles and cfg.vehicle not in self.config.vehicles:
            log.warning(
                "[ros2] vehicle %r is not among the served vehicles %s", cfg.vehicle, self.config.vehicles
            )
        self.ros_in = ros2.RosInput(cfg)
        gid = hashlib.md5(str(self.session.zid()).encode()).digest()  # 16 bytes, stable per session
        sink = ros2.RosSink(cfg, [p.name for p in self.config.pipelines], self.pubs.put_bytes, gid)
        if cfg.carrier == "rmw_zenoh" and cfg.liveliness:
            subs = [(i.topic, i.type) for i in cfg.inputs]
            for token in ros2.graph_tokens(cfg, str(self.session.zid()), sink.topics(), subs):
                self.liveliness.declare(token)
        log.info("ROS 2 bridge (%s): inputs %s", cfg.carrier, self.ros_in.key_exprs())
        return sink

    def _deliver_ros(self, wall: float, key: str, payload: bytes) -> None:
        """A ROS 2 sample: decoded into fednav wire messages and handed to the same intake path."""
        from fednav.service.transport.ros2 import RosDecodeError

        w = self._worker(self.config.ros2.vehicle)
        if len(payload) > MAX_PAYLOAD_BYTES:
            return w.submit_rejection(wall, "oversize", f"ROS 2 payload of {len(payload)} bytes")
        try:
            items = self.ros_in.decode(key, payload)
        except RosDecodeError as exc:
            return w.submit_rejection(wall, exc.reason, str(exc))
        for kind, sensor_id, data in items:
            w.submit(wall, kind, sensor_id, data)

    def _worker(self, vehicle: str) -> VehicleWorker:
        w = self.workers.get(vehicle)
        if w is None:
            with self._lock:
                w = self.workers.get(vehicle)
                if w is None:
                    w = VehicleWorker(vehicle, self.config, self.sink, self.pubs, self.rr)
                    self.workers[vehicle] = w
                    self.liveliness.declare(keys.service(vehicle, "alive", self.config.prefix))
        return w

    def service_health(self) -> ServiceHealth:
        return ServiceHealth(
            uptime_s=time.monotonic() - self.started,
            vehicles=list(self.config.vehicles),
            active_vehicles=sorted(self.workers),
            refused_before_routing=dict(self.unrouted),
            unserved_vehicles=dict(self.unserved),
        )

    def _health_loop(self) -> None:
        period = self.config.output.health_period_s
        while not self._health_stop.wait(period):
            try:
                self.pubs.publish(self._health_key, self.service_health())
            except Exception:  # a publication failure must not end the loop
                log.exception("service health publication failed")

    def _refuse(self, reason: str, vehicle: str) -> None:
        """Data the service does not take for any vehicle: counted (ServiceHealth, status
        queryable) and logged once per vehicle name and reason (at most ``_MAX_LOGGED_NAMES``
        names)."""
        self.unrouted[reason] += 1
        if reason == "unserved_vehicle" and (
            vehicle in self.unserved or len(self.unserved) < _MAX_LOGGED_NAMES
        ):
            self.unserved[vehicle] += 1
        if len(self._logged) < _MAX_LOGGED_NAMES and (reason, vehicle) not in self._logged:
            self._logged.add((reason, vehicle))
            served = self.config.vehicles
            hint = (
                " (publish under a served name, or add it to 'vehicles' in the configuration)"
                if reason == "unserved_vehicle"
                else ""
            )
            log.warning("%s: data for vehicle %r refused (served: %s)%s", reason, vehicle[:80], served, hint)

    def _deliver(self, wall: float, key: str, payload: bytes) -> None:
        pk = keys.parse_input(key, self.config.prefix)
        if pk is None and keys.is_output(key, self.config.prefix):
            return  # another fednav service's outputs share the prefix: not input, not an error
        parts = key.split("/")
        vehicle = parts[1] if len(parts) > 1 else ""
        if not keys.valid_name(vehicle):
            return self._refuse("bad_vehicle_name", vehicle)
        serve_all = "*" in self.config.vehicles
        if not serve_all and vehicle not in self.config.vehicles:
            return self._refuse("unserved_vehicle", vehicle)
        if serve_all and vehicle not in self.workers and len(self.workers) >= self.config.intake.max_vehicles:
            return self._refuse("vehicle_limit", vehicle)
        w = self._worker(vehicle)
        if pk is None:
            w.received += 1
            w.reject("unknown_key", key)
            return
        w.submit(wall, pk.kind, pk.sensor_id, payload)

    def _answer(self, query_ke) -> list[tuple[str, bytes, str]]:
        """Replies to a query: for each vehicle (served, or seen with ``*``) its status, its
        configuration and each pipeline's latest Solution whose key intersects the query."""
        from fednav.service.transport.zenoh_io import intersects

        prefix = self.config.prefix
        vehicles = sorted(self.workers) if "*" in self.config.vehicles else self.config.vehicles
        latest = list(self.sink.last_solution.items())
        out = []
        for v in vehicles:
            resources = {
                keys.service(v, "status", prefix): (lambda v=v: self._status(v), STATUS_ENCODING),
                keys.service(v, "config", prefix): (self.config.model_dump_json, CONFIG_ENCODING),
            }
            for (vehicle, pipeline), sol in latest:
                if vehicle == v:
                    resources[keys.nav(v, pipeline, "solution", prefix)] = (
                        sol.model_dump_json,
                        sol.encoding(),
                    )
            for key, (payload, encoding) in resources.items():
                if intersects(key, query_ke):
                    out.append((key, payload().encode(), encoding))
        return out

    def _status(self, vehicle: str) -> str:
        w = self.workers.get(vehicle)
        return json.dumps(
            {
                "vehicle": vehicle,
                "running": True,
                "pipelines": [p.name for p in self.config.pipelines],
                "health": json.loads(w.health().model_dump_json()) if w else None,
                "refused_before_routing": dict(self.unrouted),
            }
        )

    def stop(self) -> None:
        if self.session is None:
            return
        self._health_stop.set()
        self._health_thread.join(timeout=5.0)
        self.intake.stop()
        if self.ros_intake is not None:
            self.ros_intake.stop()
        workers = list(self.workers.values())
        for w in workers:
            w.request_stop()
        deadline = time.monotonic() + _SHUTDOWN_DRAIN_S
        for w in workers:
            w.stop(deadline)
        self.queries.stop()
        self.liveliness.undeclare_all()
        if self.rr is not None:
            self.rr.close()
        self.pubs.undeclare_all()
        self.session.close()
        self.session = None
        log.info("fednav-service stopped; recording %s", self.rrd_path if self.record else None)
