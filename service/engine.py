"""Per-vehicle engine: consumes validated events in sensor-time order and drives the pipelines.

The same code runs inside the service (events from Zenoh) and in ``fednav-sim eval`` (events
generated in-process), so both give the same solutions for the same input stream.

Time handling (docs/DESIGN.md "The service's inner loop"):
- The IMU stream drives time. An aiding measurement at t_m is queued until the INS reaches t_m;
  the IMU interval containing t_m is split there (constant-rate assumption), the pipelines
  update at exactly t_m, and propagation resumes.
- Aiding older than the INS time by at most ``late_tolerance_s`` is applied at the INS time (a
  GNSS fix is carried forward with its own velocity); older is rejected as ``late``. Aiding
  ahead by more than ``max_lead_s`` is rejected as ``early``. Same key and same t: ``duplicate``.
- IMU time going backwards is rejected (``time_backwards``; equal time: ``duplicate``), so is a
  sample further ahead than ``future_window_s`` (``future``): one message never moves the running
  time. A run of ``time_jump_samples`` such samples that agree with each other is a new time base
  (a restarted sensor or clock step, ``time_jump``). A gap longer than ``max_imu_gap_s`` (inside
  the window) or a time jump marks the INS lost: pipelines restart from a current InitialNav (also
  one refused earlier for its time) or the next alignment (status ``initialising``, then
  ``unaided`` until aided).
- An InitialNav on a running vehicle is a reset request (rate-limited, floored, checked against the
  latest fix and the verified estimate: otherwise ``implausible_init``, weighed against the
  verified state); a first start is checked against the first fix. Starting, verifying,
  suspecting and resetting pipelines is :mod:`service.lifecycle`'s (``self.life``).
- An estimate a Solution cannot carry (non-finite, outside the wire limits) fails its pipeline
  (``pipeline_failed``, status ``failed``); it restarts from a running sibling or the next fix.
- These acceptance rules are :class:`service.intake_rules.AcceptanceRules` (one verdict per event).

Initialisation (``[init] mode``):
- ``message``: from an InitialNav (position, velocity, attitude and their sigmas, as a host
  system hands over; the simulators send truth with the scenario's initial errors applied).
- ``auto`` (default): InitialNav whenever one arrives (also re-initialises); otherwise, once
  ``align_time_s`` of IMU data is in: if the vehicle was static (specific-force and rate
  scatter small), static coarse alignment (levelling + gyrocompassing) at the latest GNSS fix
  position; else, in motion with a GNSS fix faster than ``min_speed_mps``: position and
  velocity from the fix, heading and pitch from the velocity track, roll 0, wide sigmas.
  A vehicle with a raw receiver and no fix stream uses the snapshot least-squares fix of each raw
  epoch instead (:func:`service.estimation.snapshot.snapshot_fix`), also to confirm an InitialNav
  start and to restart failed pipelines.
- ``static`` / ``gnss_motion`` force the respective fallback.
The alignment maths and its thresholds are in :mod:`service.ins.alignment`.
"""

from __future__ import annotations

import logging
import math
import struct
import time
from collections import Counter, deque
from dataclasses import dataclass
from typing import Protocol

import numpy as np

from fednav.service.config import ServiceConfig
from fednav.service.evaluation import errors_against_truth
from fednav.service.imu_batch import ImuRow
from fednav.service.ins.mechanisation import NavState, Preintegrator
from fednav.service.intake_rules import AcceptanceRules, Verdict
from fednav.service.lifecycle import CONTESTED_IMU, VehicleLife
from fednav.service.messages import (
    MAX_HEIGHT_M,
    MAX_SPEED_MPS,
    MIN_HEIGHT_M,
    ImuSample,
    Solution,
    Truth,
    WireModel,
)
from fednav.service.pipelines import build_pipeline
from fednav.service.pipelines.base import Estimate, InitStd, Pipeline


@dataclass
class EstimateOutput:
    """One pipeline's estimate at an output epoch, as the engine hands it to its sink.

    ``est``: navigation state and its 9x9 covariance; ``err9``: errors against truth at the same
    epoch (:func:`service.evaluation.nav_errors`; None without truth). :meth:`solution` builds the
    wire message on demand (evaluation that keeps no messages never builds one)."""

    pipeline: Pipeline
    est: Estimate
    err9: np.ndarray | None

    @property
    def name(self) -> str:
        return self.pipeline.name

    @property
    def t(self) -> float:
        return self.est.nav.t

    @property
    def P9(self) -> np.ndarray:
        return self.est.P9

    def solution(self) -> Solution:
        return self.pipeline.solution(self.est)


class EngineSink(Protocol):
    """Where the engine's outputs go (the service publishes and records; evaluation collects)."""

    def on_estimate(self, vehicle: str, out: EstimateOutput) -> None:
        """Every pipeline's estimate at every output epoch."""

    def on_output(self, vehicle: str, msg: WireModel, err9: np.ndarray | None = None) -> None:
        """Extra outputs of an aiding update (Faults, Integrity, ...), with the errors at its time."""

    def on_truth(self, vehicle: str, truth: Truth) -> None:
        """A Truth message (simulators only), accepted in sensor-time order."""


log = logging.getLogger("fednav.service")
#: a stream refused this many times in a row is reported once in the log, with the likely cause
WHOLESALE_REFUSALS = 100
#: aiding refused ``not_initialised`` is reported only once its streak has lasted longer than a
#: static alignment ([init] align_time_s) and this much more: a vehicle aligning as configured
#: refuses every fix until it is aligned (a 10 Hz receiver's 100th came at 10 s of a 60 s alignment)
ALIGNMENT_WARNING_MARGIN_S = 10.0
#: a stream further than this from the running time is reported as a time base mismatch
TIME_BASE_MISMATCH_S = 60.0
#: wall seconds between two log warnings of a vehicle's INS lost to an IMU gap or a time jump
IMU_LOST_LOG_PERIOD_S = 30.0
#: a pipeline never aided this long after its start is reported once in the log
UNAIDED_WARNING_S = 30.0


#: IMU intervals kept for a replay (:meth:`VehicleEngine.verified_imu`): 2.5 s of a 200 Hz IMU
#: with a second publisher's as many again (a reset comes at the first aiding epoch after the
#: contest; its checkpoint is at most ~0.2 s before it); a replay that does not reach back to its
#: checkpoint falls back to the carry
IMU_LOG_LEN = 1024
#: a confirmed time jump back into the span the IMU ring holds: late copies (:meth:`VehicleEngine._late_copy`)
LATE_COPY = Verdict("time_backwards")
#: aiding messages kept for the same replay: those of the last AIDING_LOG_S of INS time, at most
#: AIDING_LOG_LEN (the messages themselves: a fix ~1.9 kB, a raw GNSS epoch of 12 satellites ~16 kB)
AIDING_LOG_S = 5.0
AIDING_LOG_LEN = 256
#: one row of the IMU ring (t, dt, dtheta xyz, dvel xyz), little-endian doubles as numpy reads them
_PACK_ROW = struct.Struct("=8d").pack_into


def imu_candidates(log, t0: float, t1: float) -> tuple[list[tuple], list[tuple], int, int] | None:
    """The IMU intervals (rows of :attr:`VehicleEngine.imu_log`, ``log``) of the stream the INS
    followed at ``t0``, as :meth:`VehicleEngine.verified_imu` gives them, also when slots of the
    cadence are held by two different intervals (two publishers on the same time stamps): (the
    first interval logged for each slot, the last different one for each slot (the first where
    there is no other), the number of such slots, how many intervals up to the last of them), or
    None when the slots do not cover the span whole. The first logged is the one the INS took (a
    second copy is refused ``duplicate``, or ``time_backwards`` once the INS has passed it), so
    the first list is the stream the INS followed and the second the other candidate wherever
    the two differ (:meth:`VehicleLife._referee_contest`)."""
    slots: dict[int, tuple] = {}
    other: dict[int, tuple] = {}
    for rec in log:
        rec = tuple(rec)
        t, dt = rec[0], rec[1]
        if t <= t0 + 1e-9 or not dt > 0.0 or t - dt >= t1 - 1e-9:
            continue  # before the checkpoint, or beginning at or after t1
        k = round((t - t0) / dt)
        if k < 1 or abs(t - t0 - k * dt) > 0.01 * dt:
            continue  # off the verified stream's cadence
        prev = slots.get(k)
        if prev is None:
            slots[k] = rec
        elif prev != rec:
            other[k] = rec
    if not slots or len(slots) != max(slots):
        return None
    n = len(slots)
    out = []
    for chosen in (slots, {**slots, **other}):
        rows = [chosen[k] for k in range(1, n + 1)]
        end = t0
        for r in rows:
            if abs(r[0] - r[1] - end) > 0.01 * r[1]:
                return None
            end = r[0]
        last = rows[-1]
        if abs(last[0] - t1) > 1e-6:
            if last[0] < t1:
                return None  # the interval that reaches t1 is not there
            start = rows[-2][0] if len(rows) > 1 else t0
            f = (t1 - start) / (last[0] - start)
            rows[-1] = (t1, t1 - start, *(x * f for x in last[2:]))
        out.append(rows)
    return out[0], out[1], len(other), max(other, default=0)


class VehicleEngine:
    """Drives all configured pipelines of one vehicle from a time-ordered event stream."""

    #: :meth:`_log_imu_lost`'s last warning (monotonic s) and the losses since: class defaults,
    #: set on the instance at a vehicle's first loss only (two more instance attributes in
    #: ``__init__`` took the engine past CPython's 30 shared keys, +0.8 % instructions per
    #: vehicle-second on every attribute read: benchmarks/instructions.py)
    _lost_logged_at = -math.inf
    _lost_unlogged = 0
    #: the last IMU time before the latest loss (a class default likewise): a fleet member's state
    #: newer than this is what a vehicle lost here may resume from (app.VehicleWorker.resume_from_fleet)
    lost_after_t: float | None = None

    def __init__(
        self, vehicle: str, config: ServiceConfig, sink: EngineSink, counters: Counter | None = None
    ):
        self.vehicle = vehicle
        self.config = config
        self.sink = sink
        self.rejected: Counter = counters if counters is not None else Counter()
        self.notes: Counter = Counter()  # counted events that are not refusals (Health notes)
        self.pipelines: list[Pipeline] = [build_pipeline(p, config) for p in config.pipelines]
        self.pre = Preintegrator()  # the vehicle's one minor loop, shared by every pipeline
        self.last_imu_t: float | None = None
        self.pending: list[tuple[float, str, str, WireModel]] = []
        #: the last IMU_LOG_LEN intervals of the INS's key that reached a verdict, taken or
        #: refused, rows of (t, dt, dtheta xyz, dvel xyz) in a ring (64 kB, whatever the rate):
        #: what a reset after a contested key replays from its last verified checkpoint
        #: (:attr:`imu_log`, :meth:`verified_imu`)
        self._imu_buf = bytearray(IMU_LOG_LEN * 64)
        self._imu_ring = np.frombuffer(self._imu_buf, dtype=float).reshape(IMU_LOG_LEN, 8)
        self._imu_n = 0  # rows written, ever
        #: the aiding messages handed to the pipelines lately, as (INS time, kind, sensor id,
        #: message, lateness): what that replay applies again between its IMU intervals
        self.aiding_log: deque = deque(maxlen=AIDING_LOG_LEN)
        #: the INS time of the last aiding message that left the log (a replay from a checkpoint
        #: before it would miss aiding): :meth:`aiding_logged_since`
        self._aiding_dropped_t = -math.inf
        #: the end times of the INS key's intervals the rules refused (the rare path: under
        #: contest), to tell the stream the INS took from the verified one (:meth:`imu_took_forged`)
        self._imu_refused: deque = deque(maxlen=IMU_LOG_LEN)
        #: per aiding key, its last message refused while the key is contested
        self._held: dict[tuple[str, str], WireModel] = {}
        self.rules = AcceptanceRules(config.intake)
        self._truth: dict[int, Truth] = {}
        self._last_out_k = -1
        self.last_t: float | None = None
        self.streams: dict[str, tuple[float, float | None]] = {}  # "kind/id" -> (last t, interval)
        #: stream -> (consecutive refusals, time of the streak's first); no attribute of its own for
        #: the time: one more attribute of this object cost 0.5 % of a vehicle's instructions
        #: (CPython's attribute layout), though no usual record reads it
        self._refusals: dict[str, tuple[int, float]] = {}
        self._warned: set[tuple[str, str]] = set()
        #: streams whose time is more than TIME_BASE_MISMATCH_S from the IMU time: offset, s (Health)
        self.time_base_mismatch: dict[str, float] = {}
        # IMU nodes (transfer alignment): ids routed to pipelines, never to the vehicle's INS
        self._node_imus: dict[str, list[Pipeline]] = {}
        for p in self.pipelines:
            for sid in p.node_imu_ids():
                self._node_imus.setdefault(sid, []).append(p)
        self._sample_pipes = [p for p in self.pipelines if p.wants_imu_samples]
        self._node_truth: dict[tuple[str, int], WireModel] = {}
        #: IMU sensor id -> its stream key ("imu/<id>"), for the ids the rules know (an id adopted
        #: or listed stays known: the rules are not asked again per sample)
        self._imu_keys: dict[str, str] = {}
        #: the vehicle's life: starts, verification, suspicion, resets (service/lifecycle.py)
        self.life = VehicleLife(self)

    @property
    def initialised(self) -> bool:
        return self.life.initialised

    # --- entry point ----------------------------------------------------------------------------
    def handle(self, kind: str, sensor_id: str, msg: WireModel) -> bool:
        """Process one validated event. Returns False when it was rejected (reason counted)."""
        if kind == "imu":
            if sensor_id in self._node_imus:
                return self._on_node_imu(sensor_id, msg)
            return self._imu_sample(sensor_id, msg)
        if kind == "alignment_truth":  # kept for error logging only, like Truth
            self._node_truth[(sensor_id, self._tkey(msg.t))] = msg
            if len(self._node_truth) > 1024:
                for k in sorted(self._node_truth, key=lambda k: k[1])[:512]:
                    del self._node_truth[k]
            return True
        previous_t = self.rules.last_t.get((kind, sensor_id))
        self._watch_time_base(kind, sensor_id, msg.t)
        verdict = self.rules.decide(kind, sensor_id, msg, self.last_imu_t, self.initialised)
        if verdict.accepted or verdict.reason in ("not_initialised", "imu_gap", "time_jump"):
            self._note_stream(kind, sensor_id, msg.t)
        life = self.life
        if kind not in ("init", "truth"):
            if verdict.reason == "duplicate":
                self._watch_contest(kind, sensor_id, msg)
            elif verdict.accepted and life.aiding_contested(kind, sensor_id, msg.t):
                verdict = Verdict("aiding_contested")  # neither publisher's, for now (lifecycle)
                self._held[(kind, sensor_id)] = msg  # (its duplicate still tells the contest on)
        self._watch_refusals(kind, sensor_id, msg.t, verdict.reason)
        if kind == "gnss_fix" and verdict.in_sequence and verdict.reason != "aiding_contested":
            life.on_fix(msg, f"gnss_fix/{sensor_id}")  # the newest fix, also when not applied (alignment)
        elif kind == "gnss_raw" and verdict.in_sequence and not life.initialised:
            life.on_raw(msg)  # a raw receiver without a fix stream aligns like one with it
        if verdict.reason == "not_initialised":
            life.try_align()  # this message may complete an alignment
            if life.initialised:
                return True
        if kind == "init" and verdict.reason in ("future", "late"):
            life.pending_init = msg  # usable if the IMU time base moves to it (restart)
        if not verdict.accepted:
            return self._reject(verdict.reason)
        if kind == "init":
            if not life.on_initial_nav(msg):
                self.rules.withdraw(kind, sensor_id, previous_t)
                return False
        elif kind == "truth":
            self._keep_truth(msg)
        else:
            self._schedule(kind, sensor_id, msg)
        return True

    def _imu_sample(self, sensor_id: str, msg: ImuSample) -> bool:
        """:meth:`handle` of an IMU sample (every message of a JSON IMU stream): the same steps
        (no time-base watch, which skips the IMU), with the stream's key made once."""
        key = self._imu_keys.get(sensor_id)  # only ids the rules know (known once, known for good)
        if key is None and self.rules.known_sensor("imu", sensor_id):
            key = self._imu_keys[sensor_id] = f"imu/{sensor_id}" if sensor_id else "imu"
        if key is not None:
            (a0, a1, a2), (v0, v1, v2) = msg.dtheta_rad, msg.dvel_mps
            n = self._imu_n  # the row into the ring (struct's pack_into: a numpy row cost 4 %)
            _PACK_ROW(self._imu_buf, (n % IMU_LOG_LEN) * 64, msg.t, msg.dt_s, a0, a1, a2, v0, v1, v2)
            self._imu_n = n + 1
            if not self._sample_pipes and self._usual_imu(key, msg.t, msg.dt_s, a0, a1, a2, v0, v1, v2):
                return True
        else:
            key = f"imu/{sensor_id}" if sensor_id else "imu"
        verdict = self.rules.decide("imu", sensor_id, msg, self.last_imu_t, self.life.initialised)
        reason = verdict.reason
        if reason is None or reason in ("not_initialised", "imu_gap", "time_jump"):
            self._note_key(key, msg.t)
        if reason is None or reason in ("imu_gap", "time_jump"):
            self._refusals.pop(key, None)  # _watch_refusals of a sample taken
        else:
            self._watch_refusals("imu", sensor_id, msg.t, reason)
        return self._imu_values(msg.t, msg.dt_s, msg.dtheta_rad, msg.dvel_mps, verdict, msg)

    def handle_imu_batch(self, sensor_id: str, rows, records=None) -> int:
        """The records of an ImuBatch (:mod:`service.imu_batch`; already validated record by record),
        in order, each judged and used exactly as an ImuSample with the same values would be
        (:meth:`handle`), without a message object per record. ``rows``: an (N, 8) array or a
        list of 8-tuples (t, dt_s, dtheta_rad, dvel_mps); ``records``: an array's ``tolist()``
        when the caller has it already. Returns the number accepted."""
        if sensor_id in self._node_imus:
            return sum(self._on_node_imu(sensor_id, ImuRow(r)) for r in rows)
        key = self._imu_keys.get(sensor_id)  # (as _imu_sample)
        if key is None:
            if not self.rules.known_sensor("imu", sensor_id):
                for r in rows:
                    self._watch_refusals("imu", sensor_id, float(r[0]), "unexpected_sensor")
                self.rejected["unexpected_sensor"] += len(rows)
                return 0
            key = self._imu_keys[sensor_id] = f"imu/{sensor_id}" if sensor_id else "imu"
        self._log_imu_rows(rows if isinstance(rows, np.ndarray) else np.asarray(rows, dtype=float))
        decide = self.rules.decide_imu
        refusals = self._refusals
        usual = not self._sample_pipes
        if records is None:
            records = rows.tolist() if isinstance(rows, np.ndarray) else rows
        n = len(records)
        accepted = i = 0
        while i < n:
            if usual:  # the usual records from i on, then one by the general path
                k = self._usual_run(key, records[i:] if i else records)
                accepted += k
                i += k
                if i == n:
                    break
            t, dt, a0, a1, a2, v0, v1, v2 = records[i]
            i += 1
            verdict = decide(t, dt, self.last_imu_t)
            reason = verdict.reason
            if reason is None or reason in ("imu_gap", "time_jump"):
                self._note_key(key, t)  # _note_stream, the key made once per batch
                refusals.pop(key, None)  # _watch_refusals of an accepted record
            else:
                self._watch_refusals("imu", sensor_id, t, reason)
            accepted += self._imu_values(t, dt, (a0, a1, a2), (v0, v1, v2), verdict)
        return accepted

    def _usual_imu(
        self, key: str, t: float, dt: float, a0: float, a1: float, a2: float, v0: float, v1: float, v2: float
    ) -> bool:
        """The usual IMU interval of a known id (a JSON sample or a batch's record), in one step:
        an initialised INS, no aiding due before the interval's end, and in sequence by the rules
        (:meth:`AcceptanceRules.take_imu_in_sequence`). Taken exactly as :meth:`_imu_sample` /
        :meth:`handle_imu_batch` with decide_imu and :meth:`_imu_values` take it (the same
        bookkeeping, the same floats; tests/test_imu_batch.py checks both paths on an irregular
        stream), without the rules' verdict chain, the pending-aiding loop and the stretch as
        lists: a third of a fleet vehicle's cost was its 200 intervals a second (docs/SCALING.md).
        Returns False, having changed nothing, when the interval needs the general path
        (the caller then asks the rules for its verdict). Not for pipelines that take IMU sample
        objects (``_sample_pipes``): the caller checks. A batch's records take
        :meth:`_usual_run`, the same steps for a run of them (keep the two alike)."""
        t_ins = self.last_imu_t
        if (
            t_ins is None
            or not self.life.initialised
            or (self.pending and self.pending[0][0] <= t + 1e-9)
            or not self.rules.take_imu_in_sequence(t, dt, t_ins)
        ):
            return False
        # _note_key, _push6 and _maybe_output inline (three calls fewer an interval): the same steps
        streams = self.streams
        prev = streams.get(key)
        if prev is not None and t > prev[0]:
            streams[key] = (t, t - prev[0])
        else:
            streams[key] = (t, prev[1] if prev else None)
        if self._refusals:
            self._refusals.pop(key, None)  # _watch_refusals of a sample taken
        config = self.config
        span = t - t_ins
        if span > 1e-12:
            # a short gap stretches the interval over it (_imu_values: the span over the
            # interval's own length, at GPS-second magnitudes rarely exactly 1)
            scale = span / dt
            if scale != 1.0:
                a0, a1, a2 = a0 * scale, a1 * scale, a2 * scale
                v0, v1, v2 = v0 * scale, v1 * scale, v2 * scale
            pre = self.pre
            pre.push6(a0, a1, a2, v0, v1, v2, span, t)
            if pre.T >= config.major_interval_s - 1e-9:
                self._advance_all()
        self.last_imu_t = self.last_t = t
        k = math.floor(t * config.output.solution_rate_hz + 1e-3)
        if k > self._last_out_k:
            self._last_out_k = k
            self.emit_solutions()
        return True

    def _usual_run(self, key: str, records) -> int:
        """How many of ``records`` (8-sequences t, dt, dtheta xyz, dvel xyz of a known id, from the
        first: a JSON sample's one, or a batch's) are usual IMU intervals, each taken in one step:
        an initialised INS, no aiding due before the interval's end, and in sequence by the rules
        (:meth:`AcceptanceRules.take_imu_in_sequence`). Taken exactly as :meth:`_imu_sample` /
        :meth:`handle_imu_batch` with decide_imu and :meth:`_imu_values` take it (the same
        bookkeeping, the same floats; tests/test_imu_batch.py checks both paths on an irregular
        stream), without the rules' verdict chain, the pending-aiding loop and the stretch as
        lists: a third of a fleet vehicle's cost was its 200 intervals a second (docs/SCALING.md).
        Stops, having changed nothing for it, at the first interval that needs the general path
        (the caller then asks the rules for its verdict). Not for pipelines that take IMU sample
        objects (``_sample_pipes``): the caller checks. A batch's records in one call, the
        lookups that no interval changes made once (a call and ~15 lookups per record fewer:
        -0.37 M instructions per vehicle-second with ImuBatches of 10). A JSON sample takes
        :meth:`_usual_imu`, the same steps for one interval (as a run of one it cost +0.38 M).

        The intervals are checked one by one and preintegrated together: a stretch of them up to
        the first that completes a major interval or reaches an output epoch (what must then
        happen after it) in one :meth:`Preintegrator.push_steps` call, and the stream's
        bookkeeping (its last time and interval, the refusal streak) once per stretch, with the
        values the steps one by one would leave."""
        life, pending, rules, streams, config = self.life, self.pending, self.rules, self.streams, self.config
        major_s = config.major_interval_s - 1e-9
        rate_hz = config.output.solution_rate_hz
        n = len(records)
        taken = 0
        while taken < n:
            t_ins = self.last_imu_t
            if t_ins is None or not life.initialised:
                return taken
            pre = self.pre  # (a restart in the outputs below makes a new one)
            T = pre.T  # the preintegrator's time after each step, as push6 sums it
            steps: list[tuple] = []
            t_end = t_prev = t_ins  # the end of the last step pushed; the time before the last interval
            major = out = False
            j = taken
            while j < n:
                t, dt, a0, a1, a2, v0, v1, v2 = records[j]
                if (pending and pending[0][0] <= t + 1e-9) or not rules.take_imu_in_sequence(t, dt, t_ins):
                    break
                j += 1
                span = t - t_ins
                if span > 1e-12:
                    # a short gap stretches the interval over it (_imu_values: the span over the
                    # interval's own length, at GPS-second magnitudes rarely exactly 1)
                    scale = span / dt
                    if scale != 1.0:
                        a0, a1, a2 = a0 * scale, a1 * scale, a2 * scale
                        v0, v1, v2 = v0 * scale, v1 * scale, v2 * scale
                    steps.append((a0, a1, a2, v0, v1, v2, span))
                    t_end = t
                    T += span
                    major = T >= major_s
                t_prev, t_ins = t_ins, t
                k = math.floor(t * rate_hz + 1e-3)
                out = k > self._last_out_k
                if major or out:
                    break
            if j == taken:
                return taken
            # _note_key of each interval: their times increase (the rules took each after the one
            # before), so what stays is the last one's time and its interval from the one before
            if j - taken > 1:
                streams[key] = (t_ins, t_ins - t_prev)
            else:
                prev = streams.get(key)
                if prev is not None and t_ins > prev[0]:
                    streams[key] = (t_ins, t_ins - prev[0])
                else:
                    streams[key] = (t_ins, prev[1] if prev else None)
            if self._refusals:
                self._refusals.pop(key, None)  # _watch_refusals of a sample taken
            if steps:
                pre.push_steps(steps, t_end)
                if major:
                    self._advance_all()
            self.last_imu_t = self.last_t = t_ins
            if out:
                self._last_out_k = k
                self.emit_solutions()
            taken = j
        return taken

    def _keep_truth(self, msg: Truth) -> None:
        self._truth[self._tkey(msg.t)] = msg
        if len(self._truth) > 256:
            for k in sorted(self._truth)[:128]:
                del self._truth[k]
        self.sink.on_truth(self.vehicle, msg)

    def _schedule(self, kind: str, sensor_id: str, msg: WireModel) -> None:
        """An accepted aiding message: queued until the INS reaches it, or applied now (late)."""
        t_ins = self.last_imu_t
        if msg.t > t_ins + 1e-9:
            self.pending.append((msg.t, kind, sensor_id, msg))
            self.pending.sort(key=lambda e: e[0])
        else:
            self._apply(kind, sensor_id, msg, dt_late=t_ins - msg.t)

    def _reject(self, reason: str) -> bool:
        self.rejected[reason] += 1
        return False

    def _note_stream(self, kind: str, sensor_id: str, t: float) -> None:
        self._note_key(f"{kind}/{sensor_id}" if sensor_id else kind, t)

    def _note_key(self, key: str, t: float) -> None:
        prev = self.streams.get(key)
        self.streams[key] = (t, (t - prev[0]) if prev and t > prev[0] else (prev[1] if prev else None))

    def _watch_time_base(self, kind: str, sensor_id: str, t: float) -> None:
        """Streams (not the IMU) more than TIME_BASE_MISMATCH_S from the IMU time, named in Health
        (``time_base_mismatch``); the once-only warning of ``_watch_refusals`` names the cause."""
        if kind in ("imu", "truth", "alignment_truth") or self.last_imu_t is None:
            return
        key = f"{kind}/{sensor_id}" if sensor_id else kind
        dt = t - self.last_imu_t
        if abs(dt) > TIME_BASE_MISMATCH_S:
            self.time_base_mismatch[key] = dt
        else:
            self.time_base_mismatch.pop(key, None)

    def _watch_refusals(self, kind: str, sensor_id: str, t: float, reason: str | None) -> None:
        """Log once, with the likely cause, when a stream is refused wholesale."""
        key = f"{kind}/{sensor_id}" if sensor_id else kind
        if reason is None or reason in ("imu_gap", "time_jump"):
            self._refusals.pop(key, None)
            return
        n, t0 = self._refusals.get(key, (0, t))
        n += 1
        self._refusals[key] = (n, t0)
        if n < WHOLESALE_REFUSALS or ("refused", key) in self._warned:
            return
        dt = t - self.last_imu_t if self.last_imu_t is not None else 0.0
        if (
            reason == "not_initialised"
            and abs(dt) <= TIME_BASE_MISMATCH_S
            and t - t0 < self.config.init.align_time_s + ALIGNMENT_WARNING_MARGIN_S
        ):
            return  # still within what an alignment takes: the vehicle may be aligning as configured
        self._warned.add(("refused", key))
        if (
            reason in ("late", "time_backwards", "future", "early", "not_initialised")
            and abs(dt) > TIME_BASE_MISMATCH_S
        ):
            cause = (
                f"its time is {dt:+.0f} s from the vehicle's running (IMU) time: a time base mismatch "
                "(e.g. the IMU stamped in boot time, GNSS in GPS time)? every stream must carry GPS seconds"
            )
        elif reason in ("late", "time_backwards", "future", "early", "duplicate"):
            cause = "a sender restarted, or two senders publish under this key?"
        elif reason == "not_initialised":
            cause = (
                "the vehicle is not initialised: publish an InitialNav, or let it align (static for "
                "[init] align_time_s with a GNSS fix, or moving faster than [init] min_speed_mps)"
            )
        elif reason == "unexpected_sensor":
            cause = "another sensor of this kind was adopted first: list both ids in [intake] sensor_ids"
        else:
            cause = "see the Health counts"
        log.warning(
            "vehicle %s: %d consecutive %s messages refused (%s): %s", self.vehicle, n, key, reason, cause
        )

    def _watch_inputs(self, p: Pipeline, t: float) -> None:
        """Log once when a pipeline has had no aiding for ``UNAIDED_WARNING_S`` since its start."""
        start_t = self.life.lives[p.name].started_t
        if p.aided_since_start or start_t is None or t - start_t < UNAIDED_WARNING_S:
            return
        if ("unaided", p.name) in self._warned:
            return
        self._warned.add(("unaided", p.name))
        log.warning(
            "vehicle %s: pipeline %s has had no aiding for %.0f s since its start (status unaided): it "
            "consumes %s; this vehicle's streams: %s",
            self.vehicle,
            p.name,
            t - start_t,
            sorted(p.sensor_kinds()),
            sorted(self.streams),
        )

    def stale_streams(self, t: float | None = None) -> list[str]:
        """Sensor streams silent for longer than three of their own intervals (at least 1 s) at the
        running time (Truth and InitialNav are not streams)."""
        t = self.last_t if t is None else t
        if t is None:
            return []
        return sorted(
            k
            for k, (last, period) in self.streams.items()
            if k not in ("truth", "init") and t - last > max(3.0 * (period or 1.0), 1.0)
        )

    @staticmethod
    def _tkey(t: float) -> int:
        return int(round(t * 1e6))

    # --- IMU ------------------------------------------------------------------------------------
    def _log_imu_rows(self, rows: np.ndarray) -> None:
        """Rows (n, 8) of the INS's key into the IMU ring, in order."""
        n = len(rows)
        if n == 0:
            return
        if n > IMU_LOG_LEN:
            self._imu_n += n - IMU_LOG_LEN
            rows, n = rows[-IMU_LOG_LEN:], IMU_LOG_LEN
        i = self._imu_n % IMU_LOG_LEN
        first = min(n, IMU_LOG_LEN - i)
        self._imu_ring[i : i + first] = rows[:first]
        if first < n:
            self._imu_ring[: n - first] = rows[first:]
        self._imu_n += n

    @property
    def imu_log(self) -> list[list[float]]:
        """The IMU ring's rows, oldest first: (t, dt, dtheta xyz, dvel xyz) of the last
        IMU_LOG_LEN intervals of the INS's key that reached a verdict, taken or refused."""
        n = min(self._imu_n, IMU_LOG_LEN)
        idx = (self._imu_n - n + np.arange(n)) % IMU_LOG_LEN
        return self._imu_ring[idx].tolist()

    def _imu_values(self, t: float, dt: float, dtheta, dvel, verdict: Verdict, msg=None) -> bool:
        """One IMU interval (a sample, or a record of a batch: ``msg`` None) after its verdict."""
        if verdict.reason in ("imu_gap", "time_jump"):
            if verdict.reason == "time_jump" and self._late_copy(t, dt):
                verdict = LATE_COPY
            else:
                self._imu_lost(t, verdict.reason)
                return True
        if not verdict.accepted:
            self._imu_refused.append(t)
            if verdict.reason in CONTESTED_IMU and self.life.initialised:
                ambiguous = verdict.reason == "duplicate" and self._duplicate_differs(t)
                self.life.on_imu_contested(t, verdict.reason, ambiguous)
            return self._reject(verdict.reason)
        if not self.life.initialised:
            self.life.align.add(t, dt, dtheta, dvel)
            self.last_imu_t = t
            self.life.try_align()
            return True
        span = t - self.last_imu_t
        scale = span / dt  # a short gap (< max_imu_gap_s) stretches the sample over it
        if scale == 1.0:  # the usual case: the values as they are (v * 1.0 == v)
            dth, dv = dtheta, dvel
        else:
            dth = [v * scale for v in dtheta]
            dv = [v * scale for v in dvel]
        cur = self.last_imu_t
        while self.pending and self.pending[0][0] <= t + 1e-9:
            t_m, kind, sid, amsg = self.pending.pop(0)
            f = min(max((t_m - cur) / (t - cur), 0.0), 1.0) if t > cur else 1.0
            if f > 0.0:
                self._push([a * f for a in dth], [a * f for a in dv], (t_m - cur), t_m)
                dth = [a * (1.0 - f) for a in dth]
                dv = [a * (1.0 - f) for a in dv]
                cur = t_m
            self._apply(kind, sid, amsg, dt_late=0.0)
        if t - cur > 1e-12:
            self._push(dth, dv, t - cur, t)
        if self._sample_pipes:
            sample = msg if msg is not None else ImuRow((t, dt, *dtheta, *dvel))
            for p in self._sample_pipes:
                p.push_imu_sample(sample)
        self.last_imu_t = t
        self.last_t = t
        self._maybe_output(t)
        return True

    def _late_copy(self, t: float, dt: float) -> bool:
        """Whether a time jump back to ``t`` the rules confirmed is a run of late copies of the
        stream the IMU ring holds (a second publisher lagging it by more than ``future_window_s``,
        its samples reaching the service in runs of ``time_jump_samples`` and more): besides the
        sample's own, an interval of the ring covers ``t`` (ends at it, to 1 % of ``dt``, or spans
        it: copies stamped between the slots). A new time base (a sensor restarted, its clock
        stepped) does not land inside the old one's last seconds, nor does one that stepped
        further back than the ring holds; taken for one, the INS was re-based on the forger's
        stream and lost twice (the probe's race at 10x through processes, seed 38: copies 3.3 s
        late in runs of 100, `tc_mhss` 4.5 m, back after 77 s; docs/hardening.md, "A lagging copy
        is not a new time base")."""
        if self.last_imu_t is None or t >= self.last_imu_t:
            return False
        n = min(self._imu_n, IMU_LOG_LEN)
        ends, spans = self._imu_ring[:n, 0], self._imu_ring[:n, 1]
        tol = 0.01 * dt
        return int(np.count_nonzero((ends - spans < t - tol) & (t <= ends + tol))) >= 2

    def _duplicate_differs(self, t: float, look_back: int = 64) -> bool:
        """Whether the IMU ring's latest ``look_back`` rows hold two different intervals for the
        time ``t`` (a duplicate that says something else than the sample taken: two publishers on
        the same time stamps, which one is genuine not known), not a copy of it."""
        n = min(self._imu_n, IMU_LOG_LEN, look_back)
        ring = self._imu_ring
        first = None
        for i in range(self._imu_n - n, self._imu_n):
            row = ring[i % IMU_LOG_LEN]
            if row[0] == t:
                if first is None:
                    first = row
                elif not np.array_equal(row, first):
                    return True
        return False

    def verified_imu(self, t0: float, t1: float) -> list[tuple] | None:
        """The IMU intervals of the stream the INS followed at ``t0`` (a verified checkpoint's time:
        the end of one of its intervals), from ``t0`` to ``t1``, from :attr:`imu_log`, taken or
        refused: the intervals that continue it end to end (each begins where the one before
        ended, to 1 % of its length); the one holding ``t1`` cut there as the engine cuts an
        interval at an aiding epoch (its share of the increments). None unless they cover the
        span whole and unambiguously: a slot of that cadence missing, or held by two different
        intervals (a second publisher on the verified stream's own time stamps: which one is
        genuine is not known: :meth:`candidate_imu`). A second publisher between the verified
        stream's samples (the forged bursts of docs/hardening.md) is off its cadence and left out."""
        cands = imu_candidates(self.imu_log, t0, t1)
        return None if cands is None or cands[2] else cands[0]

    def candidate_imu(self, t0: float, t1: float) -> tuple[list[tuple], list[tuple], int, int] | None:
        """:func:`imu_candidates` of :attr:`imu_log` (:meth:`VehicleLife._referee_contest`)."""
        return imu_candidates(self.imu_log, t0, t1)

    def _watch_contest(self, kind: str, sensor_id: str, msg: WireModel) -> None:
        """A duplicate aiding message (the time of one already taken): when it says something else
        than the one taken (pending, or in :attr:`aiding_log`; or the last one held while the key
        is contested), two publishers share the key and which one is genuine is not known:
        counted ``contested:<kind>/<id>`` and handed to the lifecycle
        (:meth:`VehicleLife.on_aiding_contested`); a pending copy is dropped. A copy of the same
        message (a retransmission, a replayed log) is only a duplicate."""
        t = msg.t
        held = self._held.get((kind, sensor_id))
        taken = held if held is not None and held.t == t else None
        for e in self.pending if taken is None else ():
            if e[1] == kind and e[2] == sensor_id and e[3].t == t:
                taken = e[3]
                if taken != msg:
                    self.pending.remove(e)  # not applied yet: neither copy will be
                    self._held[(kind, sensor_id)] = taken
                break
        for e in reversed(self.aiding_log) if taken is None else ():
            if e[1] == kind and e[2] == sensor_id and e[3].t == t:
                taken = e[3]
                break
        if taken is None or taken == msg:
            return
        self.notes[f"contested:{kind}/{sensor_id}" if sensor_id else f"contested:{kind}"] += 1
        self.life.on_aiding_contested(kind, sensor_id, t)

    def imu_took_forged(self, t0: float, t1: float) -> bool:
        """Whether the intervals the INS took from ``t0`` (a verified checkpoint's time) to ``t1``
        differ from the verified stream's (:meth:`verified_imu`): an interval off its cadence taken
        (a second publisher's, slipped between the genuine samples), or one on it refused (a
        genuine sample refused as overlapping a forged one taken before it). Read from
        :attr:`imu_log` and the refusals' times; a duplicate of a sample taken counts as refused,
        the sample itself as taken."""
        refused = Counter(t for t in self._imu_refused if t > t0 + 1e-9)
        for rec in self.imu_log:
            t, dt = rec[0], rec[1]
            if t <= t0 + 1e-9 or not dt > 0.0 or t - dt >= t1 - 1e-9:
                continue
            k = round((t - t0) / dt)
            on_cadence = k >= 1 and abs(t - t0 - k * dt) <= 0.01 * dt
            took = refused[t] == 0
            if not took:
                refused[t] -= 1
            if took != on_cadence:
                return True
        return False

    def aiding_logged_since(self, t0: float) -> bool:
        """Whether :attr:`aiding_log` still holds every aiding message applied after ``t0``."""
        return self._aiding_dropped_t <= t0 + 1e-9

    def _on_node_imu(self, sensor_id: str, msg: ImuSample) -> bool:
        """A node IMU sample: judged by the aiding rules of its own key (duplicate, late,
        time_backwards, not_initialised, early), then handed to the pipelines that consume it."""
        verdict = self.rules.decide("imu_node", sensor_id, msg, self.last_imu_t, self.initialised)
        if not verdict.accepted:
            return self._reject(verdict.reason)
        for p in self._node_imus[sensor_id]:
            p.push_node_imu(sensor_id, msg)
        return True

    def _push(self, dth, dv, dt, t_end) -> None:
        """One minor-loop step for every pipeline at once (shared preintegration)."""
        self._push6(
            float(dth[0]), float(dth[1]), float(dth[2]), float(dv[0]), float(dv[1]), float(dv[2]), dt, t_end
        )

    def _push6(self, a0, a1, a2, v0, v1, v2, dt, t_end) -> None:
        """:meth:`_push` of an interval given as six floats."""
        pre = self.pre
        pre.push6(a0, a1, a2, v0, v1, v2, dt, t_end)
        if pre.T >= self.config.major_interval_s - 1e-9:
            self._advance_all()

    def _advance_all(self) -> None:
        """Bring every pipeline's INS to the engine's time (major update from the shared loop)."""
        pre = self.pre
        if pre.T > 0.0:
            for p in self.pipelines:
                p.advance(pre)
            pre.reset(pre.t_end)

    def _imu_lost(self, t: float, reason: str) -> None:
        """An IMU gap or a confirmed time jump: the INS is lost; re-initialised from a current
        InitialNav (one refused for its time is kept for this) or the next alignment."""
        self.rejected[reason] += 1
        self.pending.clear()
        gap = t - self.last_imu_t if self.last_imu_t is not None else None
        self.lost_after_t = self.last_imu_t
        was_running = self.life.initialised
        self.last_imu_t = self.last_t = t
        if reason == "time_jump":  # a new time base: nothing of the old one applies
            self.rules.forget_times()
            self.rules.imu_t = t
            self.streams.clear()
        self.life.on_imu_lost(t, reason)
        if was_running:
            self._log_imu_lost(t, reason, gap)

    def _log_imu_lost(self, t: float, reason: str, gap: float | None) -> None:
        """Say in the log that a running vehicle's INS was lost and what happens now (at most
        once per ``IMU_LOST_LOG_PERIOD_S`` of wall time, with the count of the ones not logged):
        a link that dropped the vehicle's messages for a moment (a router restarted, a network
        outage) shows in the service's log, not only in Health counts and the recording."""
        now = time.monotonic()
        self._lost_unlogged += 1
        if now - self._lost_logged_at < IMU_LOST_LOG_PERIOD_S:
            return
        n, self._lost_unlogged, self._lost_logged_at = self._lost_unlogged, 0, now
        intake = self.config.intake
        if gap is None:
            what = f"the IMU stream moved to a new time base at {t:.3f}"
        elif reason == "imu_gap":
            what = f"an IMU gap of {gap:.2f} s (over [intake] max_imu_gap_s {intake.max_imu_gap_s:g} s)"
        elif gap > 0.0:
            what = (
                f"the IMU stream resumed {gap:.2f} s after its last sample (beyond [intake] "
                f"future_window_s {intake.future_window_s:g} s: a link outage, or a clock step)"
            )
        else:
            what = f"the IMU stream went {-gap:.2f} s back (a sensor restarted, or a clock step)"
        then = self.life.how_restarted()
        more = f" ({n - 1} more since the last such warning)" if n > 1 else ""
        self.life.restart_untold = not self.life.initialised
        log.warning(
            "vehicle %s: INS lost at t=%.3f: %s; %s (Health rejected %s)%s",
            self.vehicle,
            t,
            what,
            then,
            reason,
            more,
        )

    # --- aiding ---------------------------------------------------------------------------------
    def _apply(self, kind: str, sensor_id: str, msg: WireModel, dt_late: float) -> None:
        self._advance_all()
        log, t_ins = self.aiding_log, self.pre.t_end
        if len(log) == AIDING_LOG_LEN:
            self._aiding_dropped_t = log[0][0]
        log.append((t_ins, kind, sensor_id, msg, dt_late))
        while log[0][0] < t_ins - AIDING_LOG_S:
            self._aiding_dropped_t = log.popleft()[0]
        self.life.before_aiding(kind, msg)
        for p in self.pipelines:
            p.sync()  # every pipeline at the aiding epoch (the same propagation steps as before)
            if kind not in p.consumed_kinds():
                self._unused(p, kind)
                continue
            try:
                outputs = p.apply(kind, sensor_id, msg, dt_late)
            except np.linalg.LinAlgError:
                self.rejected["numerical"] += 1
                p.recover_covariance()
                continue
            err9 = self._errors(p, msg.t) if outputs else None
            for out in outputs:
                self.sink.on_output(self.vehicle, out, err9)
            if p.screened.get("innovations_inconsistent") and ("inconsistent", p.name) not in self._warned:
                self._warn_inconsistent(p)
            if p.screened.get("innovations_biased") and ("biased", p.name) not in self._warned:
                self._warn_biased(p)
        self.life.after_aiding(kind, msg, self.pre.t_end, sensor_id)

    def _warn_inconsistent(self, p: Pipeline) -> None:
        """Log once per pipeline when a stream's innovations first turn larger than it claims."""
        self._warned.add(("inconsistent", p.name))
        streams = ", ".join(f"{k} {p.consistency.ratio(k):.1f}x" for k in p.consistency.failing())
        log.warning(
            "vehicle %s: pipeline %s: innovations larger than the filter claims over the last %.0f s "
            "(%s the claimed variance): its sigmas understate the error, status degraded meanwhile; "
            "a sensor's sigmas or the filter's process noise (IMU grade, receiver clock) are too "
            "optimistic (Health screened innovations_inconsistent counts the episodes)",
            self.vehicle,
            p.name,
            p.consistency.window_s,
            streams or "a stream",
        )

    def _warn_biased(self, p: Pipeline) -> None:
        """Log once per pipeline when a stream's innovations first turn off centre."""
        self._warned.add(("biased", p.name))
        rows = ", ".join(
            f"{k} {label} {p.bias.mean(k, label):+.1f} sigma"
            for k, labels in p.bias.failing().items()
            for label in labels
        )
        log.warning(
            "vehicle %s: pipeline %s: innovations off centre over the last %.0f s (%s on average): the "
            "state is further off than its sigmas say (a corruption the aiding pulls back slowly), or "
            "a sensor's errors are biased or correlated beyond its model; status degraded meanwhile "
            "(Health screened innovations_biased counts the episodes)",
            self.vehicle,
            p.name,
            p.bias.window_s,
            rows or "a stream",
        )

    def _unused(self, p: Pipeline, kind: str) -> None:
        """A sensor kind reached a pipeline that is not configured to use it: counted (Health
        notes ``unused:<pipeline>:<kind>``) and logged once."""
        self.notes[f"unused:{p.name}:{kind}"] += 1
        if ("unused", p.name, kind) in self._warned:
            return
        self._warned.add(("unused", p.name, kind))
        log.warning(
            "vehicle %s: pipeline %s does not use sensor kind %r (it uses %s): its messages are counted "
            "in Health notes, not fused by it; to fuse them, add %r to the pipeline's sensors",
            self.vehicle,
            p.name,
            kind,
            sorted(p.consumed_kinds()),
            kind,
        )

    @staticmethod
    def _usable(est: Estimate) -> bool:
        """An estimate a Solution can carry: finite, inside the wire model's limits."""
        nav = est.nav
        # the 3- and 4-vectors as Python floats (every output epoch: numpy's calls cost more than
        # the tests; math.isfinite and math.hypot take the same values either way)
        vel = np.asarray(nav.vel_enu_mps, dtype=float).tolist()
        scalars = (nav.lat_rad, nav.lon_rad, nav.h_m, *vel, *np.asarray(nav.q_nb, dtype=float).tolist())
        # P9 finite: its sum is (a NaN or an infinity makes the sum one; a sum of finite entries
        # that overflows asks the elementwise test), one C call instead of isfinite and all()
        P9 = est.P9
        return bool(
            all(math.isfinite(v) for v in scalars)
            and (math.isfinite(np.add.reduce(P9, axis=None)) or np.isfinite(P9).all())
            and abs(nav.lat_rad) <= math.pi / 2
            and MIN_HEIGHT_M <= nav.h_m <= MAX_HEIGHT_M
            and math.hypot(*vel) <= MAX_SPEED_MPS
        )

    # --- outputs --------------------------------------------------------------------------------
    def _maybe_output(self, t: float) -> None:
        # output epochs on absolute multiples of the output period (aligned with truth and other
        # services); the 1e-3 period tolerance absorbs float resolution at GPS-second magnitudes
        k = math.floor(t * self.config.output.solution_rate_hz + 1e-3)
        if k <= self._last_out_k:
            return
        self._last_out_k = k
        self.emit_solutions()

    def emit_solutions(self) -> None:
        self._advance_all()
        for p in self.pipelines:
            if p.failed:
                continue
            p.sync()
            est = p.estimate()
            self._watch_inputs(p, est.nav.t)
            if not self._usable(est):  # never an exception, never a wrong message: the pipeline failed
                p.mark_failed()
                self.rejected["pipeline_failed"] += 1
                continue
            self.life.note_estimate(p, est)
            self.sink.on_estimate(self.vehicle, EstimateOutput(p, est, self._errors(p, est.nav.t, est)))
            for out in p.epoch_outputs():  # per-node outputs, with the node's truth when present
                node = getattr(out, "node", None)
                truth = self._node_truth.get((node, self._tkey(out.t))) if node else None
                self.sink.on_output(self.vehicle, out, truth)

    def _errors(self, p: Pipeline, t: float, est: Estimate | None = None) -> np.ndarray | None:
        """Errors of a pipeline's estimate against truth at t (None without truth at t)."""
        truth = self._truth.get(self._tkey(t))
        if truth is None:
            return None
        return errors_against_truth((est or p.estimate()).nav, truth)

    # --- initialisation (the transitions themselves: service/lifecycle.py) ---------------------------
    def _restart_clock(self, t: float) -> None:
        """Every pipeline (re)started at ``t``: the vehicle's clock and outputs restart there."""
        self.pre = Preintegrator()
        self.pre.reset(t)
        self.last_imu_t = t
        self.last_t = t
        self._last_out_k = -1
        self.pending.clear()

    def _start(self, nav: NavState, std: InitStd) -> None:
        """Every pipeline starts from ``nav`` (a verified start: :meth:`VehicleLife.start_all`)."""
        self.life.start_all(nav, std)

    def hand_over(self, nav: NavState, std: InitStd, source: str, screening: bool = False) -> bool:
        """Start or restart every pipeline from another service's last state (fleet scale-out).

        ``nav``: the navigation state at the time the vehicle resumes here (before its first IMU
        sample: that sample's start time; on a running vehicle: within ``[intake]
        future_window_s`` of its running time), biases included; ``std``: its 1-sigma (position
        ENU m, velocity ENU m/s, attitude nav-frame rad), raised to the lifecycle's absolute
        floors; ``source``: who handed it over (the other service's id, for the log).

        A vehicle not yet initialised starts every pipeline from it (lifecycle transition
        ``hand_over``). A running vehicle treats it as a reset request: it must agree with the
        latest GNSS fix (else the running estimate) like a re-initialising InitialNav, or it is
        refused (``implausible_handover``, or ``stale_handover`` out of the time window, counted
        in Health ``rejected``) and False is returned; taken, every pipeline restarts from it with
        sigmas that cover its difference from that reference. Either way the state is
        *unverified*: every pipeline reports ``degraded`` until the vehicle's own aiding agrees
        with it (``lifecycle.VERIFY_EPOCHS`` agreeing GNSS epochs), and a GNSS reference that
        disagrees with it restarts the pipeline from the vehicle's own fix. Counted in Health
        ``notes`` as ``handed_over``. Returns whether the state was taken. ``screening``: the
        old owner's screening was refusing aiding (``HandoverState.screening``): a fix that
        disagrees with the state is then judged by the pipelines' own screening, not a reset."""
        return self.life.hand_over(nav, std, source, screening)

    # --- state for health ---------------------------------------------------------------------------
    def pipeline_states(self) -> dict[str, dict]:
        return {
            p.name: {
                "status": p.current_status(self.last_t) if self.initialised or p.failed else "initialising",
                "screened": dict(p.screened),
                "last_t": self.last_t,
                "updates": p.updates,
                "reinitialisations": p.reinitialisations,
            }
            for p in self.pipelines
        }
