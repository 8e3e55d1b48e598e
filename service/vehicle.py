"""One vehicle's loop: decode and validate an input, run the engine, count, report health.

The one per-vehicle loop of fednav: the service's worker pool (:mod:`service.app`), the
in-process recorder (``fednav-record``) and the evaluator (``fednav-sim eval``) all feed their
events through :meth:`VehicleLoop.process`, so a message is judged, counted and used the same way
on every route. An input is one of

- JSON bytes of a sensor message (validated by its pydantic model, refusals classified),
- an ImuBatch payload (:mod:`service.imu_batch`: refused whole, or record by record),
- a wire message already validated (in-process simulators, the ROS 2 bridge's decoded CDR),
- a rejection decided before (``kind`` None: ``sensor_id`` is the reason, the payload its text).

No thread here: the caller owns scheduling (the service's pool runs many vehicles per worker).
"""

from __future__ import annotations

import array
import logging
import time
from collections import Counter

import numpy as np
from pydantic import ValidationError

from fednav.service import imu_batch, sensors
from fednav.service.config import ServiceConfig
from fednav.service.engine import VehicleEngine
from fednav.service.messages import Health, ImuSample, PipelineHealth, WireModel, decode_imu_json

log = logging.getLogger("fednav.service")

MAX_PAYLOAD_BYTES = 1 << 20
#: wall seconds without a message from a stream after which Health calls it stale
STALE_WALL_S = 2.0
from fednav.service.validation_errors import classify, reason_and_text  # noqa: E402  (one set of rules)


class RateLimitedLog:
    def __init__(self, period_s: float = 5.0):
        self.period_s = period_s
        self._last: dict[str, float] = {}

    def warn(self, reason: str, text: str) -> None:
        now = time.monotonic()
        if now - self._last.get(reason, -1e9) >= self.period_s:
            self._last[reason] = now
            log.warning("%s: %s", reason, text)


def tune_gc() -> None:
    """The collector settings of a process that runs vehicles (the service, after its start; the
    benchmarks that measure its per-vehicle loop): the long-lived objects of the start (modules,
    configuration, sessions) leave the collector's generations (a full collection does not walk
    them), and young collections run less often (the hot path allocates many small arrays and
    tuples). For one vehicle's steady state it makes no difference to the instructions it takes
    (``benchmarks/instructions.py``: 30.83 against 30.84 M per vehicle-second)."""
    import gc

    gc.freeze()
    gc.set_threshold(50_000, 50, 100)


#: the messages over which a vehicle's Health latency percentiles are taken (the most recent)
LATENCY_WINDOW = 2000


class LatencyWindow:
    """The latencies (s) of a vehicle's most recent ``size`` messages, in a ring of floats, and
    their p50 / p99 / max for Health. One Health a second per vehicle: the percentiles by one
    partial sort of the window (:meth:`percentiles_ms`, numpy's default linear interpolation,
    the same values as ``np.percentile``) cost ~30 us against ~250 us for a deque read into an
    array and ``np.percentile`` (200 vehicles: 6 % of a core for Health alone before)."""

    __slots__ = ("_buf", "_i", "_n")

    def __init__(self, size: int = LATENCY_WINDOW):
        self._buf = array.array("d", bytes(8 * size))  # read by numpy without a conversion
        self._i = 0  # next slot
        self._n = 0  # slots filled

    def __len__(self) -> int:
        return self._n

    def append(self, value: float) -> None:
        buf, i = self._buf, self._i
        buf[i] = value
        i += 1
        self._i = 0 if i == len(buf) else i
        if self._n < len(buf):
            self._n += 1

    def extend(self, values) -> None:
        for v in values:
            self.append(v)

    def percentiles_ms(self) -> tuple[float, float, float]:
        """(p50, p99, max) of the window, ms ((0, 0, 0) when empty)."""
        n = self._n
        if n == 0:
            return 0.0, 0.0, 0.0
        a = np.frombuffer(self._buf, float, n) * 1e3  # (the filled slots are the first n until full)
        ranks = [(n - 1) * 0.5, (n - 1) * 0.99]
        kth = sorted({int(r) for r in ranks} | {min(int(r) + 1, n - 1) for r in ranks} | {n - 1})
        a.partition(kth)
        out = []
        for r in ranks:
            lo = int(r)
            t = r - lo
            x0, x1 = float(a[lo]), float(a[min(lo + 1, n - 1)])
            d = x1 - x0  # numpy's _lerp: from the nearer end
            out.append(x1 - d * (1.0 - t) if t >= 0.5 else x0 + d * t)
        return out[0], out[1], float(a[n - 1])


class VehicleLoop:
    """A vehicle's engine with its counters (Health): ``received`` counts samples (an ImuBatch of
    N records is N received), ``accepted`` those the engine took, ``counters`` every refusal by
    reason. ``on_fix(vehicle, sensor_id, fix)`` is called for every accepted GNSS fix (the
    recording's raw-fix layer)."""

    def __init__(
        self, vehicle: str, config: ServiceConfig, sink, on_fix=None, latency_window: int = LATENCY_WINDOW
    ):
        self.vehicle = vehicle
        self.config = config
        self.counters: Counter = Counter()
        self.received = 0
        self.accepted = 0
        self.dropped = 0
        self.engine = VehicleEngine(vehicle, config, sink, self.counters)
        self.on_fix = on_fix
        self.latency_s = LatencyWindow(latency_window)
        self.arrivals: dict[str, float] = {}  # stream -> monotonic arrival time of its last message
        self.started = time.monotonic()
        self._rlog = RateLimitedLog()
        #: called once with the start time of the vehicle's first IMU sample, before it is used
        #: (a fleet handover starts the engine there); None: nothing to do
        self.starter = None

    def reject(self, reason: str, text: str = "", n: int = 1) -> None:
        self.counters[reason] += n
        self._rlog.warn(reason, f"{self.vehicle}: {text}")

    def process(self, kind: str | None, sensor_id: str, payload, wall: float | None = None) -> None:
        """One input (module docstring); ``wall``: its arrival, monotonic seconds (latency)."""
        wall = time.monotonic() if wall is None else wall
        if kind is None:  # a rejection decided before: sensor_id is the reason
            self.received += 1
            self.reject(sensor_id, payload.decode() if isinstance(payload, bytes) else str(payload))
            return
        # bytes (every message off the wire) skip the models' isinstance: pydantic's metaclass is an
        # ABCMeta, whose check took ~4x a type test in a micro-benchmark (with the other changes of
        # its commit, JSON IMU samples: 25.28 -> 24.25 M instructions per vehicle-second)
        if type(payload) is not bytes and isinstance(payload, WireModel):
            self.received += 1
            self._handle(kind, sensor_id, payload, wall)
            return
        entry = sensors.REGISTRY.get(kind) or sensors.registry().get(kind)
        if entry is not None and entry.batch is not None and imu_batch.is_batch(payload):
            self._batch(sensor_id, payload, wall)
            return
        self.received += 1
        if len(payload) > MAX_PAYLOAD_BYTES:
            self.reject("oversize", f"{kind} payload of {len(payload)} bytes")
            return
        model = entry.message if entry is not None else sensors.input_message(kind)
        if model is None:
            self.reject("unknown_key", f"no message model for kind {kind!r}")
            return
        if model is ImuSample:  # the commonest message: msgspec, pydantic only for what it refuses
            msg = decode_imu_json(payload)
            if msg is not None:
                self._handle(kind, sensor_id, msg, wall)
                return
        try:
            msg = model.model_validate_json(payload)
        except ValidationError as err:
            reason, text = reason_and_text(err)
            self.reject(reason, f"{kind}/{sensor_id}: {text}")
            return
        self._handle(kind, sensor_id, msg, wall)

    def process_imu_json(self, sensor_id: str, items) -> None:
        """A run of JSON IMU samples of one stream, consecutive among the vehicle's arrivals
        (``items``: the (wall, kind, sensor_id, payload) of each, in order): what
        :meth:`process` does to each, with the samples that decode taken together as the
        records of one ImuBatch (the engine judges and uses each record exactly as the same
        sample alone: tests/test_imu_batch.py), without a dispatch per sample. A sample that does
        not decode (or is too large) goes through :meth:`process` alone, in its place, for its
        exact refusal and counted reason. Each sample's latency is counted from its own arrival.
        The service's inline intake hands over such runs when one drain holds several samples of
        a vehicle (docs/SCALING.md, "JSON samples of one drain taken together")."""
        rows: list[tuple] = []
        walls: list[float] = []
        for wall, _kind, _sid, payload in items:
            msg = decode_imu_json(payload) if len(payload) <= MAX_PAYLOAD_BYTES else None
            if msg is None:
                if rows:
                    self._imu_rows(sensor_id, rows, walls)
                    rows, walls = [], []
                self.process("imu", sensor_id, payload, wall)
                continue
            (a0, a1, a2), (v0, v1, v2) = msg.dtheta_rad, msg.dvel_mps
            rows.append((msg.t, msg.dt_s, a0, a1, a2, v0, v1, v2))
            walls.append(wall)
        if rows:
            self._imu_rows(sensor_id, rows, walls)

    def _imu_rows(self, sensor_id: str, rows: list[tuple], walls: list[float]) -> None:
        """Valid IMU samples (as records) of one stream into the engine, counted per sample."""
        self.received += len(rows)
        self._imu_records(sensor_id, rows, walls)

    def _imu_records(self, sensor_id: str, rows, walls: list[float], records=None) -> None:
        """Validated IMU records ((N, 8) array or 8-tuples) of one stream into the engine, from the
        messages that arrived at ``walls`` (a latency each): the start hook, the engine, the
        counts of what it took. ``records``: the array's rows as lists of floats, when read."""
        if self.starter is not None and not self.engine.initialised:
            self._start_at(float(rows[0][0] - rows[0][1]))
        try:
            n = self.engine.handle_imu_batch(sensor_id, rows, records)
        except Exception:
            log.exception("engine failure on IMU records of imu/%s", sensor_id)
            self.counters["internal_error"] += 1
            return
        self.accepted += n
        if n:
            self.arrivals[f"imu/{sensor_id}" if sensor_id else "imu"] = walls[-1]
        now = time.monotonic()
        self.latency_s.extend([now - w for w in walls])

    def _start_at(self, t_start: float) -> None:
        starter, self.starter = self.starter, None
        try:
            starter(t_start)
        except Exception:
            log.exception("vehicle %s: start hook failed", self.vehicle)
            self.counters["internal_error"] += 1

    def _handle(self, kind: str, sensor_id: str, msg: WireModel, wall: float) -> None:
        if self.starter is not None and kind == "imu" and not self.engine.initialised:
            self._start_at(msg.t - msg.dt_s)
        try:
            ok = self.engine.handle(kind, sensor_id, msg)
        except Exception:  # never let a pipeline bug end the vehicle
            log.exception("engine failure on %s/%s", kind, sensor_id)
            self.counters["internal_error"] += 1
            return
        if ok:
            self.accepted += 1
            self.arrivals[f"{kind}/{sensor_id}" if sensor_id else kind] = wall
            if kind == "gnss_fix" and self.on_fix is not None:
                self.on_fix(self.vehicle, sensor_id, msg)
        self.latency_s.append(time.monotonic() - wall)

    def _batch(self, sensor_id: str, payload, wall: float) -> None:
        if len(payload) > MAX_PAYLOAD_BYTES:
            self.received += 1
            self.reject("oversize", f"imu/{sensor_id}: ImuBatch of {len(payload)} bytes")
            return
        try:
            rows = imu_batch.decode(payload)
        except imu_batch.BatchError as exc:
            self.received += 1
            self.reject(exc.reason, f"imu/{sensor_id}: {exc}")
            return
        self.received += len(rows)
        # the usual batch (small, every record good): its floats read once, for the check and
        # the engine, and no mask
        records = imu_batch.usual_records(rows)
        if records is None:
            ok, bad = imu_batch.validate(rows)
            for reason, n in bad.items():
                self.reject(reason, f"imu/{sensor_id}: {n} of {len(rows)} records of an ImuBatch", n)
            if bad:
                rows = rows[ok]
            if len(rows) == 0:
                return
        self._imu_records(sensor_id, rows, [wall], records)

    def health(self, queue_depth: int = 0, notes: dict[str, int] | None = None) -> Health:
        # one pass over the window and one percentile call (a health a second per vehicle: 195 ->
        # 119 us with 2,000 latencies; the same values)
        p50, p99, lat_max = self.latency_s.percentiles_ms()
        engine = self.engine
        states = engine.pipeline_states()
        # the sensor-time view cannot see a stream that stopped arriving: streams silent for
        # STALE_WALL_S of wall time are stale, and no pipeline is aided while its input is silent
        now = time.monotonic()
        silent = {
            k for k, w in self.arrivals.items() if now - w > STALE_WALL_S and k not in ("truth", "init")
        }
        stale = sorted(set(engine.stale_streams()) | silent)
        if self.arrivals and now - max(self.arrivals.values()) > STALE_WALL_S:
            for st in states.values():
                if st["status"] in ("aided", "degraded", "unaided"):
                    st["status"] = "coasting"
        return Health(
            t=engine.last_t,
            uptime_s=now - self.started,
            received=self.received,
            accepted=self.accepted,
            rejected=dict(self.counters),
            dropped_overload=self.dropped,
            queue_depth=queue_depth,
            latency_ms={"p50": p50, "p99": p99, "max": lat_max},
            pipelines={k: PipelineHealth(**v) for k, v in states.items()},
            sensors={k: t for k, (t, _) in engine.streams.items()},
            stale=stale,
            time_base_mismatch=dict(engine.time_base_mismatch),
            notes={k: int(v) for k, v in (dict(engine.notes) | dict(notes or {})).items() if v},
        )


__all__ = ["MAX_PAYLOAD_BYTES", "STALE_WALL_S", "RateLimitedLog", "VehicleLoop", "classify"]
