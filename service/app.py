"""Process wiring of fednav-service: Zenoh intake -> per-vehicle workers -> Zenoh + Rerun.

Threads: the Zenoh intake thread (reads the subscriber FIFO, routes by vehicle), a bounded pool
of workers (``[intake] workers``), each owning many vehicles (a vehicle lives on one worker, so its
events keep their order; each runs the vehicle's loop, :mod:`service.vehicle`: validates, runs
the engine in sensor-time order, publishes), the query server. Where the GIL is the limit, a
fleet is split over processes (``--shard I/K``, :mod:`service.shards`). Signals
(SIGINT/SIGTERM) set a stop event; ``stop()`` then stops intake, lets each worker drain its queue,
emits the last solutions and health, closes the recording (complete, readable) and the session.
"""

from __future__ import annotations

import functools
import itertools
import logging
import math
import queue
import threading
import time
import zlib
from collections import Counter
from datetime import datetime
from pathlib import Path

import numpy as np
from pydantic import ValidationError

from fednav.service import fleet, imu_batch, keys
from fednav.service.config import ServiceConfig, recording_kinds
from fednav.service.engine import EstimateOutput
from fednav.service.evaluation import recording_errors
from fednav.service.messages import (
    Alignment,
    Faults,
    HandoverState,
    Health,
    ImmModels,
    Integrity,
    ServiceHealth,
    Solution,
    Status,
    Truth,
    WireModel,
)
from fednav.service.transport import rerun_paths as paths
from fednav.service.vehicle import MAX_PAYLOAD_BYTES, RateLimitedLog, VehicleLoop
from fednav.service.vehicle import classify as classify  # re-exported (tests, ROS 2 bridge)

log = logging.getLogger("fednav.service")

#: at shutdown the vehicles' queues drain for at most this long together (then the rest is
#: counted in the log and the recording is closed: SIGTERM returns within seconds)
_SHUTDOWN_DRAIN_S = 5.0
#: control item of a pool worker: the vehicle moved to another service of the fleet
RETIRE = "__retire__"
#: vehicle names whose refused messages ServiceHealth counts one by one (unserved_vehicles)
_MAX_LOGGED_NAMES = 100
#: (reason, vehicle name) pairs the log names (then one line says it names no more): another
#: application publishing under 300 names of the prefix wrote 100 warnings in one burst
_MAX_LOGGED_REFUSALS = 10
#: a vehicle of a '*' service that has accepted no message yet (only refused ones: another
#: client's data under a vehicle's sensor keys) is released after this long without input, not
#: [intake] vehicle_idle_s: foreign names must not hold max_vehicles slots for minutes
NEVER_ACCEPTED_IDLE_S = 10.0
#: Service.stopping while the recording is closed (the one stage of a stop that may take long:
#: a large recording's optimisation; the shutdown watchdog of __main__ does not count it)
RECORDING_STAGE = "recording"
#: ServiceHealth.refusing_vehicles: the vehicles refused for vehicle_limit this recently
REFUSING_WINDOW_S = 10.0
#: vehicles announced by their publishers (keys.sensors_alive) a fleet member remembers at most
ANNOUNCED_MAX = 100_000
#: encodings of the queryables' JSON replies (the samples carry application/json;fednav.<Type>/1)
STATUS_ENCODING = Status.encoding()
CONFIG_ENCODING = "application/json;fednav.ServiceConfig/1"


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


class OutputSink:
    """Engine sink of the service: publish on Zenoh, record to Rerun."""

    def __init__(self, prefix: str, publishers, rerun_sink, extra=(), vehicle_interval_s: float = 0.0):
        self.prefix = prefix
        self.pubs = publishers
        self.rr = rerun_sink
        #: per-vehicle recording decimation (``rrd_vehicle_interval_s``): last recorded sensor time
        #: and status per (vehicle, stream)
        self.vehicle_interval_s = vehicle_interval_s
        self._recorded: dict[tuple[str, str], tuple[float, str]] = {}
        self.extra = list(extra)  # more sinks (the ROS 2 bridge); their failures are logged, not raised
        self.last_solution: dict[tuple[str, str], Solution] = {}
        self._rlog = RateLimitedLog()

    def _forward(self, method: str, *args) -> None:
        for s in self.extra:
            try:
                getattr(s, method)(*args)
            except Exception as exc:
                self._rlog.warn("output_sink_error", f"{type(s).__name__}.{method}: {exc!r}")

    def on_health(self, vehicle: str, health: Health) -> None:
        self._forward("on_health", vehicle, health)

    def forget(self, vehicle: str) -> None:
        """A vehicle the service released idle: what is kept per vehicle goes (its last Solutions,
        the decimation's book, the recording's and the other sinks' own)."""
        for d in (self.last_solution, self._recorded):  # (other workers' threads write them too)
            for k in list(d):
                if k[0] == vehicle:
                    d.pop(k, None)
        if self.rr is not None:
            self.rr.forget(vehicle)
        for s in self.extra:
            forget = getattr(s, "forget", None)
            if forget is not None:
                try:
                    forget(vehicle)
                except Exception as exc:
                    self._rlog.warn("output_sink_error", f"{type(s).__name__}.forget: {exc!r}")

    def on_estimate(self, vehicle: str, out: EstimateOutput) -> None:
        sol = out.solution()
        self.pubs.publish(keys.nav(vehicle, sol.pipeline, "solution", self.prefix), sol)
        self.last_solution[(vehicle, sol.pipeline)] = sol
        innovations = out.pipeline.innovations
        if self.rr is not None and innovations:
            while innovations:
                t, sensor, labels, r, used = innovations.popleft()
                self.rr.log_innovations(vehicle, sol.pipeline, t, sensor, labels, r, used)
        if self.rr is not None and self.record_due(vehicle, sol.pipeline, sol.t, sol.status):
            self.rr.log_solution(vehicle, sol)
            if out.err9 is not None:
                errors, bounds = recording_errors(out.err9, out.P9)
                self.rr.log_errors(vehicle, sol.pipeline, sol.t, errors, bounds)
        self._forward("on_estimate", vehicle, out)

    def record_due(self, vehicle: str, stream: str, t: float, state: str = "") -> bool:
        """Per-vehicle recording decimation: True when a row of ``stream`` at sensor time ``t`` is
        to be recorded (always when ``state``, e.g. a status, changed or time went back)."""
        if self.vehicle_interval_s <= 0.0:
            return True
        key = (vehicle, stream)
        last = self._recorded.get(key)
        if last is None or t - last[0] >= self.vehicle_interval_s - 1e-9 or t < last[0] or state != last[1]:
            self._recorded[key] = (t, state)
            return True
        return False

    def log_fix(self, vehicle: str, sensor_id: str, fix) -> None:
        """A raw GNSS fix on the recording's trajectory view (decimated per vehicle)."""
        if self.rr is not None and self.record_due(vehicle, "fix/" + sensor_id, fix.t):
            self.rr.log_fix(vehicle, sensor_id, fix)

    def log_health(self, vehicle: str, health: Health) -> None:
        if self.rr is not None and (health.t is None or self.record_due(vehicle, "health", health.t)):
            self.rr.log_health(vehicle, health)

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


def health_phase(vehicle: str) -> float:
    """A vehicle's phase in [0, 1) of the Health period: a stable hash of its name, so that the
    vehicles of a fleet that started at once publish their Health spread over the period."""
    return (zlib.crc32(vehicle.encode()) & 0xFFFF) / 65536.0


def next_due(due: float, now: float, period: float) -> float:
    """The first time after ``now`` on the grid ``due + k period`` (a periodic task that keeps its
    phase, also after a scan that came late)."""
    due += period
    if due <= now:
        due = now + period - (now - due) % period
    return due


class VehicleWorker:
    """One vehicle inside a pool worker: its :class:`~service.vehicle.VehicleLoop` and what the
    service adds (health publication, the raw-fix recording hook, its share of the queue)."""

    def __init__(self, vehicle: str, config: ServiceConfig, sink: OutputSink, publishers, rr, pool_worker):
        self.vehicle = vehicle
        self.config = config
        self.sink = sink
        self.pubs = publishers
        self.rr = rr
        self.pool_worker = pool_worker
        on_fix = sink.log_fix if rr is not None else None  # raw fixes on the ENU trajectory view
        self.loop = VehicleLoop(vehicle, config, sink, on_fix=on_fix)
        self.engine = self.loop.engine
        self.counters = self.loop.counters
        self.queued = 0  # items of this vehicle waiting in its pool worker's queue
        self.retired = False  # moved to another service of the fleet, or released idle
        self.on_retired = None  # (VehicleWorker) -> None, set by the service
        #: [intake] vehicle_idle_s for a vehicle of a '*' service (0: never released), the
        #: monotonic arrival of its latest input, and the service's hooks for a released vehicle:
        #: on_released(worker) when it goes, reroute(worker, item) -> its new worker (or None,
        #: refused and counted) for an input routed to it just before
        self.idle_s = 0.0
        self.last_input = time.monotonic()
        self.released = False
        self.on_released = None
        self.reroute = None
        self.next_state = time.monotonic() + config.fleet.handover_period_s
        #: a fleet member's view of the other members' handover states of this vehicle (() -> {pipeline:
        #: payload}) and its own id: a vehicle lost here (an IMU gap: this service stopped, SIGSTOP,
        #: while another took the vehicle) resumes from the other's fresher state (resume_from_fleet)
        self.fleet_states_of = None
        self.fleet_me = ""
        #: a rendezvous fleet member's: (vehicle) -> the members its handover states go to
        self.state_to = None
        self._resume_seen: tuple = ()
        self.notes = None  # () -> counted non-refusal events (the ROS 2 bridge's), for Health
        # each vehicle's Health at its own phase of the period (a stable hash of its name): a fleet
        # started at once does not publish every vehicle's Health in the same scan (a burst that
        # holds the intake for ~0.3 ms per vehicle, the latency tail of every vehicle behind it)
        self.next_health = time.monotonic() + config.output.health_period_s * health_phase(vehicle)

    def accepted_any(self) -> bool:
        """Whether the vehicle has taken any message (else only refused ones)."""
        return self.loop.accepted > 0

    @property
    def received(self) -> int:
        return self.loop.received

    @received.setter
    def received(self, n: int) -> None:
        self.loop.received = n

    @property
    def dropped(self) -> int:
        return self.loop.dropped

    def submit(self, wall: float, kind: str | None, sensor_id: str, payload) -> None:
        self.pool_worker.submit(self, (wall, kind, sensor_id, payload))

    def submit_rejection(self, wall: float, reason: str, text: str) -> None:
        """A message refused before it became a wire message (e.g. ROS 2 CDR that does not decode):
        counted by the vehicle like every other rejection."""
        self.submit(wall, None, reason, text.encode())

    def reject(self, reason: str, text: str = "") -> None:
        self.loop.reject(reason, text)

    def health(self) -> Health:
        return self.loop.health(queue_depth=self.queued, notes=self.notes() if self.notes else None)

    def publish_health(self) -> None:
        h = self.health()
        self.pubs.publish(keys.service(self.vehicle, "health", self.config.prefix), h)
        self.sink.on_health(self.vehicle, h)
        self.sink.log_health(self.vehicle, h)

    # --- fleet handover ([fleet] sharding = "rendezvous") ---------------------------------------
    def handover_states(self, service: str) -> list[HandoverState]:
        """Each running pipeline's state for the service that may take the vehicle over."""
        engine = self.engine
        if not engine.initialised:
            return []
        out = []
        for p in engine.pipelines:
            status = p.current_status(engine.last_t)
            if status in ("initialising", "failed") or p.bank is None:
                continue
            p.sync()
            est = p.estimate()
            nav = est.nav
            if not engine._usable(est):
                continue
            Pb = np.clip(np.diagonal(p.bank.P[0])[9:15], 0.0, None)
            monitor = getattr(p, "monitor", None)  # MHSS integrity: its satellite exclusions
            ins = getattr(p.bank, "ins", None)  # its motion: a state carried through a turn
            acc = ins.last_acc_enu_mps2 if ins is not None else np.zeros(3)
            rate = ins.last_wib_b_rps if ins is not None else np.zeros(3)
            if not (np.isfinite(acc).all() and np.isfinite(rate).all()):
                acc, rate = np.zeros(3), np.zeros(3)
            # its gate refusing aiding now (the window of its 'degraded' for screening)
            screening = p.last_screened_t is not None and nav.t - p.last_screened_t <= p.coast_after_s()
            out.append(
                HandoverState(
                    t=nav.t,
                    vehicle=self.vehicle,
                    pipeline=p.name,
                    service=service,
                    lat_deg=math.degrees(nav.lat_rad),
                    lon_deg=(math.degrees(nav.lon_rad) + 180.0) % 360.0 - 180.0,
                    height_m=nav.h_m,
                    vel_enu_mps=tuple(float(v) for v in nav.vel_enu_mps),
                    q_nb=tuple(float(v) for v in nav.q_nb / np.linalg.norm(nav.q_nb)),
                    P9=[float(v) for v in est.P9.ravel()],
                    gyro_bias_rps=tuple(float(v) for v in nav.gyro_bias_rps),
                    accel_bias_mps2=tuple(float(v) for v in nav.accel_bias_mps2),
                    acc_enu_mps2=tuple(float(v) for v in acc),
                    rate_body_rps=tuple(float(v) for v in rate),
                    screening=bool(screening),
                    stream_records=dict(list(p.stream_verdicts().items())[:32]),
                    bias_std=tuple(float(v) for v in np.sqrt(Pb)),
                    status=status,
                    excluded=monitor.book.healthy_for(nav.t) if monitor is not None else {},
                )
            )
        return out

    def publish_states(self, group: str, service: str) -> None:
        """The vehicle's handover states: in a rendezvous fleet to the members ``state_to`` names
        (its heir, a joining service that will own it, or its new owner when it moves; nothing
        without another member), from a local shard to shard 0 (which keeps every shard's)."""
        prefix = self.config.prefix
        if self.state_to is None:  # a local shard: shard 0 subscribes to its group's states
            for st in self.handover_states(service):
                self.pubs.publish(keys.fleet_state(group, self.vehicle, st.pipeline, prefix), st)
            return
        to = self.state_to(self.vehicle)
        if not to:
            return  # no other member: nobody to take the vehicle over
        for st in self.handover_states(service):
            for member in to:
                self.pubs.publish(keys.fleet_state_to(group, member, self.vehicle, st.pipeline, prefix), st)

    def take_over(self, payloads: dict[str, bytes], t_start: float) -> bool:
        """Start the vehicle from the last handover state another service published (called once,
        before its first IMU sample: ``t_start`` is that sample's start; or by
        :meth:`resume_from_fleet`); a state older than ``[fleet] handover_max_age_s`` (or
        unreadable) is not used: the vehicle aligns itself. True when the state was taken."""
        states = []
        for payload in payloads.values():
            try:
                states.append(HandoverState.model_validate_json(payload))
            except ValidationError:
                self.loop.reject("bad_handover_state", "a handover state that does not validate")
        rank = {"aided": 0, "degraded": 1, "coasting": 2, "unaided": 3}
        states.sort(key=lambda st: (rank.get(st.status, 9), -st.t))
        max_age = self.config.fleet.handover_max_age_s
        usable = [st for st in states if -1.0 <= t_start - st.t <= max_age]
        if not usable:
            if states:
                self.engine.notes["handover_state_too_old"] += 1
            return False
        st = usable[0]
        nav, std = fleet.handover_nav(st, t_start)
        hand_over = getattr(self.engine, "hand_over", None)
        if hand_over is not None:
            if not hand_over(nav, std, st.service, screening=any(s.screening for s in usable)):
                log.warning(
                    "vehicle %s: the handover state of service %s refused (counted in Health rejected); "
                    "the vehicle starts from its own sensors",
                    self.vehicle,
                    st.service,
                )
                return False
        else:  # the engine's lifecycle without a handover transition: a plain start
            self.engine._start(nav, std)
        self.engine.notes[f"handed_over_from:{st.service}"] += 1
        # each integrity monitor keeps the satellites its pipeline's last state excluded (a faulty
        # satellite must not come back with the service that takes the vehicle over)
        for p in self.engine.pipelines:
            monitor = getattr(p, "monitor", None)
            own = [s for s in usable if s.pipeline == p.name]
            if own:  # the old owner's verdicts on the streams' innovations (Pipeline.source_groups)
                p.consistency.adopt(own[0].stream_records)
            excluded = own[0].excluded if own and monitor is not None else {}
            if excluded:
                monitor.book.restore(excluded, t_start)
                self.engine.notes["handover_exclusions"] += len(excluded)
        log.info(
            "vehicle %s handed over from service %s (state %.2f s old, status %s; degraded until its own "
            "aiding agrees)",
            self.vehicle,
            st.service,
            t_start - st.t,
            st.status,
        )
        if self.rr is not None:
            self.rr.log_event(self.vehicle, t_start, f"handed over from {st.service} ({st.status} state)")
        return True

    def resume_from_fleet(self) -> bool:
        """A vehicle this service had lost (``life.lost``: an IMU gap, e.g. the service was stopped
        longer than its lease while another member served the vehicle) is started from another
        member's handover state newer than the loss, when one within ``handover_max_age_s`` of the
        vehicle's time is there, instead of aligning anew. The same, as a reset request
        (``VehicleLifecycle.hand_over`` on a running vehicle), for a vehicle that started itself
        again after the loss (its own alignment: a fix in the drain that confirmed the loss, before
        the other member's state came; the CI saw that once) within ``handover_max_age_s`` of that
        start. Called by the pool worker's scan (off the per-message path); parses the states only
        when they changed, or while one is ahead of the vehicle's time (more than 1 s: this
        service's stream of the vehicle lags the other's, as after it resumed with a backlog; the
        other sends its last state once as it lets the vehicle go). True when it took one."""
        eng = self.engine
        life = eng.life
        if eng.lost_after_t is None or eng.last_imu_t is None or self.fleet_states_of is None:
            return False
        if not life.lost and not life.started_itself_after_loss(self.config.fleet.handover_max_age_s):
            return False
        payloads = self.fleet_states_of()
        key = tuple(sorted((n, len(b), hash(b)) for n, b in payloads.items()))
        if not payloads or key == self._resume_seen:
            return False
        t, max_age = eng.last_imu_t, self.config.fleet.handover_max_age_s
        others, ahead = {}, False
        for name, payload in payloads.items():
            try:
                st = HandoverState.model_validate_json(payload)
            except ValidationError:
                continue
            if st.service == self.fleet_me or st.t <= eng.lost_after_t:  # (not served there after the loss)
                continue
            if t - st.t < -1.0:
                ahead = True  # usable once the vehicle's time comes near it
            elif t - st.t <= max_age:
                others[name] = payload
        if not ahead:
            self._resume_seen = key
        if not others or not self.take_over(others, t) or life.lost:
            return False
        eng.notes["resumed_from_fleet_state"] += 1
        return True

    def final_outputs(self) -> None:
        """The vehicle's last Solutions (at its last IMU time) and Health, as it leaves this service
        (stopped, released idle); not a Solution already published at that time (a stream whose
        last IMU sample fell on the output grid), which would reach readers twice under one ``t``."""
        try:
            eng = self.engine
            if eng.initialised and not self._published_at(eng.last_imu_t):
                eng.emit_solutions()
            self.publish_health()
        except Exception:
            log.exception("vehicle %s: final outputs failed", self.vehicle)

    def _published_at(self, t: float | None) -> bool:
        """Whether every running pipeline's last published Solution is at ``t`` or later."""
        if t is None:
            return False
        last = self.sink.last_solution
        for p in self.engine.pipelines:
            sol = None if p.failed else last.get((self.vehicle, p.name))
            if not p.failed and (sol is None or sol.t < t - 1e-6):
                return False
        return True


def json_imu_runs(routed: list) -> list:
    """A drain's routed inputs ((vehicle worker, (wall, kind, sensor_id, payload)), in arrival
    order) as (worker, items) in the order each vehicle's first item came, with the JSON IMU
    samples of one stream that follow each other among that vehicle's inputs (no other input of
    the vehicle between them) in one list: each vehicle's own order is kept, and its samples
    are run together (:meth:`VehicleLoop.process_imu_json`). Vehicles are independent, so a
    sample taken ahead of another vehicle's input that arrived before it changes no result.
    Under light load a drain holds one sample per vehicle and nothing changes; a loaded service
    (drains of many messages) spends less per sample the further behind it falls."""
    out: list = []
    open_runs: dict = {}  # worker -> its open run (a list in ``out``)
    for w, item in routed:
        payload = item[3]
        if item[1] == "imu" and isinstance(payload, bytes) and payload[:4] != imu_batch.MAGIC:
            run = open_runs.get(w)
            if run is not None and run[0][2] == item[2]:
                run.append(item)
                continue
            run = open_runs[w] = [item]
        else:
            open_runs.pop(w, None)
            run = [item]
        out.append((w, run))
    return out


class PoolWorker:
    """A thread that owns many vehicles: one bounded queue of (vehicle, item), consumed in
    arrival order (a vehicle's events keep their order: a vehicle always lives on one worker).

    ``inline`` (``[intake] workers = 0``): no queue; the thread that receives a message (the
    intake) runs it at once, under this worker's lock, and this worker's own thread only scans the
    vehicles for Health and handover states every 50 ms. No hand-over between threads: on a busy
    process the fastest (docs/SCALING.md, "Idle between messages, and the inline intake"); the
    Zenoh channel back-pressures the publishers when the service falls behind, and one vehicle's
    long epoch delays the others."""

    def __init__(
        self, index: int, config: ServiceConfig, fleet: tuple[str, str] | None = None, inline: bool = False
    ):
        self.index = index
        self.config = config
        self.fleet = fleet  # (group, this service's id) when sharing a fleet: handover states out
        self.inline = inline
        self.vehicles: list[VehicleWorker] = []
        self.q: queue.Queue = queue.Queue(maxsize=config.intake.queue_size)
        self._lock = threading.Lock()  # inline: one message or one scan at a time
        self._stop = threading.Event()
        self._next_scan = 0.0
        target = self._run_scans if inline else self._run
        self._thread = threading.Thread(target=target, name=f"fednav-worker-{index}", daemon=True)
        self._thread.start()

    def submit(self, vw: VehicleWorker, item) -> None:
        if self.inline:
            with self._lock:
                try:  # nothing a message or a sink does may end the intake
                    if not vw.released:
                        self._one(vw, item)
                        return
                except Exception:
                    log.exception("worker %d: error", self.index)
                    vw.counters["internal_error"] += 1
                    return
            self._rerouted(vw, item)  # released idle since it was routed: to its new worker
            return
        if self.config.intake.overload == "block":
            self.q.put((vw, item))
        else:
            try:
                self.q.put_nowait((vw, item))
            except queue.Full:
                vw.loop.dropped += 1
                return
        vw.queued += 1

    def submit_imu_json(self, vw: VehicleWorker, items: list) -> None:
        """A run of one vehicle's JSON IMU samples of one stream (:func:`json_imu_runs`): taken
        together when inline (:meth:`VehicleLoop.process_imu_json`), else queued one by one."""
        if not self.inline:
            for item in items:
                self.submit(vw, item)
            return
        with self._lock:
            try:
                if not vw.retired:
                    vw.loop.process_imu_json(items[0][2], items)
                    return
            except Exception:
                log.exception("worker %d: error", self.index)
                vw.counters["internal_error"] += 1
                return
        if vw.released:
            for item in items:
                self._rerouted(vw, item)

    def _one(self, vw: VehicleWorker, item) -> None:
        """One item of one vehicle (an input, a rejection, or the order to retire it)."""
        wall, kind, sensor_id, payload = item
        if kind is None and sensor_id == RETIRE:
            self._retire(vw)
        elif not vw.retired:
            vw.loop.process(kind, sensor_id, payload, wall)
        elif vw.released:
            self._rerouted(vw, item)

    def _rerouted(self, vw: VehicleWorker, item) -> None:
        """An input routed to a vehicle just before it was released idle: to the vehicle's new
        worker (this thread runs it when that worker is on this pool worker and queued: a
        thread never waits for room in its own queue)."""
        nw = vw.reroute(vw, item) if vw.reroute is not None else None
        if nw is None:
            return
        if nw.pool_worker is self and not self.inline:
            self._one(nw, item)
        else:
            nw.pool_worker.submit(nw, item)

    def _scan(self) -> None:
        """Health (and handover states) of the vehicles that are due: every 50 ms, not per event."""
        now = time.monotonic()
        if now < self._next_scan:
            return
        self._next_scan = now + 0.05
        for v in list(self.vehicles):
            idle = v.idle_s if v.accepted_any() else min(v.idle_s, NEVER_ACCEPTED_IDLE_S)
            if idle and now - v.last_input >= idle and not v.queued:
                self._release(v, now)
                continue
            if now >= v.next_health:
                v.next_health = next_due(v.next_health, now, self.config.output.health_period_s)
                v.publish_health()
            if self.fleet is not None:
                if now >= v.next_state:
                    v.next_state = now + self.config.fleet.handover_period_s
                    v.publish_states(*self.fleet)
                if v.fleet_states_of is not None:  # (a fleet member's, not a local shard's)
                    v.resume_from_fleet()

    def _run(self) -> None:
        while True:
            try:
                vw, item = self.q.get(timeout=0.05)
            except queue.Empty:
                vw = item = None
            try:  # nothing a message or a sink does may end this worker
                if item is not None:
                    vw.queued -= 1
                    self._one(vw, item)
                self._scan()
            except Exception:
                log.exception("worker %d: error", self.index)
                if vw is not None:
                    vw.counters["internal_error"] += 1
            if item is None and self._stop.is_set():
                break

    def _run_scans(self) -> None:
        while not self._stop.wait(0.05):
            try:
                with self._lock:
                    self._scan()
            except Exception:
                log.exception("worker %d: health scan failed", self.index)

    def _retire(self, vw: VehicleWorker) -> None:
        """The vehicle moved to another service: its last state out (the new owner starts from
        it), then it is dropped here."""
        if vw.retired:
            return
        vw.retired = True
        try:
            if self.fleet is not None:
                vw.publish_states(*self.fleet)
        except Exception:
            log.exception("vehicle %s: last handover state failed", vw.vehicle)
        self._drop(vw, vw.on_retired)

    def _drop(self, vw: VehicleWorker, hook) -> None:
        """A retired or released vehicle leaves this worker; then the service's ``hook``."""
        if vw in self.vehicles:
            self.vehicles.remove(vw)
        if hook is not None:
            hook(vw)

    def _release(self, vw: VehicleWorker, now: float) -> None:
        """A vehicle that sent nothing for ``[intake] vehicle_idle_s``: its last solutions and
        Health out, a note in the recording, then dropped (the service frees its slot)."""
        vw.final_outputs()
        vw.retired = vw.released = True
        if vw.rr is not None:
            try:
                t = vw.engine.last_t
                if t is not None and math.isfinite(t):
                    vw.rr.log_event(vw.vehicle, t, f"released: no input for {now - vw.last_input:.0f} s")
            except Exception:
                log.exception("vehicle %s: release note failed", vw.vehicle)
        self._drop(vw, vw.on_released)

    def request_stop(self) -> None:
        """Ask the thread to finish: it drains its queue, then ends."""
        self._stop.set()

    def stop(self, deadline: float | None = None) -> None:
        """Drain the queue (until ``deadline``, monotonic seconds), emit the vehicles' last
        solutions and health."""
        self._stop.set()
        self._thread.join(timeout=None if deadline is None else max(0.0, deadline - time.monotonic()))
        if self._thread.is_alive():
            log.warning("worker %d: %d events not processed at shutdown", self.index, self.q.qsize())
            return
        with self._lock:
            for v in self.vehicles:
                v.final_outputs()
                if self.fleet is not None:  # the freshest state for the member that takes it over
                    try:
                        v.publish_states(*self.fleet)
                    except Exception:
                        log.exception("vehicle %s: last handover state failed", v.vehicle)


class Service:
    #: set in __init__ (a class default for a service assembled without it, as unit tests do)
    _resubscribe_due: threading.Event | None = None
    _owned_intake = False

    def __init__(
        self,
        config: ServiceConfig,
        rrd: Path | None = None,
        viewer: str | None = None,
        listen: list[str] | None = None,
        connect: list[str] | None = None,
        zenoh_config_file: str | None = None,
        record: bool = True,
        shard: tuple[int, int] | None = None,
        feeds: dict | None = None,
        feed_fd: int | None = None,
        on_feed_end=None,
        shard_group: str | None = None,
    ):
        self.config = config
        #: shard 0 of local shards: the ShardFeed of each other shard (by index), to which the
        #: intake hands those shards' vehicles' inputs (service.transport.shard_feed)
        self.feeds = feeds or {}
        self._feed_of: dict[str, object | None] = {}
        #: shard 0 of local shards in a fleet group: each shard's Zenoh id -> its index (the
        #: supervisor's ShardSupervisor.by_zid, kept up to date as shards start and restart)
        self.shard_members: dict[str, int] = {}
        #: a shard 1..K-1: its inputs come from shard 0 through this file descriptor, not Zenoh
        self.feed_fd = feed_fd
        self._on_feed_end = on_feed_end
        #: local shards: the private group under which shards 1..K-1 publish their vehicles' handover
        #: states; shard 0 keeps the latest and hands a restarted shard its vehicles' states first
        self.shard_group = shard_group if shard is not None and shard[1] > 1 else None
        self.fleet_states: fleet.StateCache | None = None
        #: (index, count): this process serves only the vehicles that rendezvous hashing gives its
        #: shard (``--shards``, :mod:`service.shards`); None: every served vehicle
        self.shard = shard if shard is not None and shard[1] > 1 else None
        self._shard_cache: dict[str, bool] = {}
        #: vehicles another shard or fleet member serves, as _route found them: their inputs are
        #: dropped by the intake before their payload is read (_wanted). Emptied when the fleet's
        #: membership changes; _foreign_gen keeps a verdict of the old membership out of it
        self._foreign: set[str] = set()
        self._foreign_gen = 0
        self._foreign_lock = threading.Lock()
        self.fleet_view = None
        self._rebalance_due = threading.Event()
        #: [intake] subscribe = 'owned': ownership may have changed, the vehicles subscribed are
        #: brought up to date by the health loop (_resubscribe)
        self._resubscribe_due = threading.Event()
        self._owned_intake = False
        #: ... and the vehicles whose publishers announce them (keys.sensors_alive tokens): the
        #: ones it owns are subscribed before their first message (set by a Zenoh callback)
        self._announced: set[str] = set()
        self.retired_vehicles = 0
        self.released_vehicles = 0
        self.rrd_path = rrd or config.rrd or Path("recordings") / f"fednav-{datetime.now():%Y%m%d-%H%M%S}.rrd"
        self.viewer = viewer or config.viewer
        self.listen, self.connect, self.zenoh_config_file = listen, connect, zenoh_config_file
        self.record = record
        self.workers: dict[str, VehicleWorker] = {}
        self.pool: list[PoolWorker] = []
        self.unrouted = Counter()  # data refused before any vehicle: by reason
        self.unserved = Counter()  # messages per vehicle name not served (first _MAX_LOGGED_NAMES)
        #: vehicle -> when its input was last refused for vehicle_limit (ServiceHealth)
        self._limit_refused: dict[str, float] = {}
        #: a '*' service at max_vehicles: its 'full' token (and in a fleet group its 'holds'
        #: tokens) are declared; see _capacity
        self._full_declared = False
        self._full_grace: threading.Timer | None = None
        self.started = time.monotonic()
        self._health_stop = threading.Event()
        self._logged: set[tuple[str, str]] = set()
        self._lock = threading.Lock()
        self.session = None
        #: the stage stop() is in (None: running), for the shutdown watchdog's message
        self.stopping: str | None = None

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
                cfg.zenoh,
                self.listen,
                self.connect,
                self.zenoh_config_file,
                outputs_prefix=cfg.prefix,
                own_id=self.shard is None or self.shard[0] == 0,  # shards 1..K-1: an id of their own
            )
        )
        self.pubs = zenoh_io.Publishers(self.session, block=True)
        zid = str(self.session.zid())
        self.fleet_view = None
        fleet_id = None
        if cfg.fleet.sharding == "rendezvous":
            self.fleet_group = cfg.fleet_group()
            self.fleet_view = fleet.FleetView(zid, holds_me=self.workers.__contains__)
            self.fleet_states = fleet.StateCache(cfg.intake.max_vehicles * 10)
            fleet_id = (self.fleet_group, zid)
        elif self.shard_group is not None:
            self.fleet_states = fleet.StateCache(cfg.intake.max_vehicles * 10)
            if self.feed_fd is not None:  # shards 1..K-1 publish their vehicles' states
                fleet_id = (self.shard_group, fleet.shard_name(self.shard[0]))
        # a bounded pool of worker threads, each owning many vehicles (no thread per vehicle)
        # (workers = 0: one inline worker, run by the intake thread itself)
        inline = cfg.intake.workers == 0
        self.pool = [PoolWorker(i, cfg, fleet_id, inline) for i in range(max(1, cfg.intake.workers))]
        self._watches = []
        if self.fleet_view is not None:
            base = f"{cfg.prefix}/_fleet/{self.fleet_group}"
            services = f"{cfg.prefix}/_services/*"
            self._watches = [
                # the states addressed to this member: of the vehicles it takes over if their owner
                # goes, and of those handed to it (not every vehicle's: a state reaches one member)
                zenoh_io.Watch(
                    self.session, keys.fleet_states_for(self.fleet_group, zid, cfg.prefix), self._on_state
                ),
                zenoh_io.Watch(self.session, f"{base}/member/*", self._on_member, liveliness=True),
                zenoh_io.Watch(self.session, f"{base}/joining/*", self._on_joining, liveliness=True),
                # capacity: the members at their max_vehicles and what each of them holds
                zenoh_io.Watch(self.session, f"{services}/holds/*", self._on_holds, liveliness=True),
                zenoh_io.Watch(self.session, f"{services}/full", self._on_full, liveliness=True),
            ]
            self._fleet_token = keys.fleet_member(self.fleet_group, zid, cfg.prefix)
        elif self.shard_group is not None and self.feeds:  # shard 0 hears the other shards' states
            base = f"{cfg.prefix}/_fleet/{self.shard_group}"
            self._watches = [zenoh_io.Watch(self.session, f"{base}/state/**", self._on_state)]
        self.liveliness = zenoh_io.Liveliness(self.session)
        self.ros_in = None
        extra = [self._start_ros2()] if cfg.ros2 is not None else []
        self.sink = OutputSink(cfg.prefix, self.pubs, self.rr, extra, cfg.rrd_vehicle_interval_s)
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
        many = self._deliver_many if inline else None  # inline: drains handed over whole
        local = self.shard is not None and not self.feeds and self.feed_fd is None
        wanted = self._wanted if local or self.fleet_view is not None else None
        one_process = self.shard is None and not self.feeds and self.feed_fd is None
        mode = cfg.intake.subscribe
        if mode == "owned" and not one_process:
            log.warning(
                "[intake] subscribe = 'owned' needs a fleet member that is one process (not --shards): "
                "subscribing to every vehicle's inputs"
            )
        self._owned_intake = (
            self.fleet_view is not None and one_process and mode in ("owned", "auto") and sel is not None
        )
        if self.feed_fd is not None:  # a local shard: shard 0 hands it its vehicles' inputs
            from fednav.service.transport.shard_feed import FeedIntake

            self.intake = FeedIntake(self.feed_fd, self._deliver, deliver_many=many, on_end=self._on_feed_end)
        elif self._owned_intake:
            self.intake = zenoh_io.OwnedIntake(
                self.session,
                cfg.prefix,
                keys.discovery_selectors(cfg.prefix),
                many or self._deliver_each,
                wanted=wanted,
            )
        else:
            forward = self._forward if self.feeds else None
            self.intake = zenoh_io.Intake(
                self.session, selectors, self._deliver, deliver_many=many, wanted=wanted, forward=forward
            )
        if self._owned_intake:  # publishers that announce their vehicles: subscribed before they speak
            self._watches.append(
                zenoh_io.Watch(
                    self.session, keys.sensors_alive_selector(cfg.prefix), self._on_announced, liveliness=True
                )
            )
        self.ros_intake = None
        if self.ros_in is not None and self.ros_in.key_exprs():
            from fednav.service.transport.ros2 import header_stamp_s

            self.ros_intake = zenoh_io.Intake(
                self.session, self.ros_in.key_exprs(), self._deliver_ros, order_key=header_stamp_s
            )
        # one queryable per vehicle selector: status, config and each pipeline's latest solution
        # (a '*' service's {prefix}/*/** also answers for its ServiceHealth: fednav-fleet status
        # reads which services are full and what they refuse)
        self._health_key = keys.service_health(str(self.session.zid()), cfg.prefix)
        qexprs = [f"{cfg.prefix}/{v}/**" for v in ([sel] if sel else cfg.vehicles)]
        if not sel:  # the named vehicles' queryables do not cover the ServiceHealth's own key
            qexprs.append(self._health_key)
        self.queries = zenoh_io.QueryServer(self.session, qexprs, self._answer)
        self.liveliness.declare(keys.service_token(str(self.session.zid()), cfg.prefix))
        if self.fleet_view is not None:
            # hear the members and their handover states for a while, then join: the members see
            # this token and hand this service its share (each publishing its last states);
            # meanwhile its ``joining`` token has the members address it the states of its share
            self.liveliness.declare(keys.fleet_joining(self.fleet_group, zid, cfg.prefix))
            threading.Timer(1.5 * cfg.fleet.handover_period_s, self._join_fleet).start()
        for v in [] if sel else self._served_list():
            self.liveliness.declare(keys.service(v, "alive", cfg.prefix))
        self._health_thread = threading.Thread(
            target=self._health_loop, name="fednav-service-health", daemon=True
        )
        self._health_thread.start()
        log.info(
            "fednav-service up: zid=%s vehicles=%s pipelines=%s rrd=%s",
            str(self.session.zid()),
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
        w.last_input = wall
        if len(payload) > MAX_PAYLOAD_BYTES:
            return w.submit_rejection(wall, "oversize", f"ROS 2 payload of {len(payload)} bytes")
        try:
            items = self.ros_in.decode(key, payload)
        except RosDecodeError as exc:
            return w.submit_rejection(wall, exc.reason, str(exc))
        finally:
            for text in self.ros_in.newly_silent():
                log.warning("%s", text)
        for kind, sensor_id, data in items:
            w.submit(wall, kind, sensor_id, data)

    def _worker(self, vehicle: str) -> VehicleWorker:
        w = self.workers.get(vehicle)
        if w is None:
            with self._lock:
                w = self.workers.get(vehicle)
                if w is None:
                    pw = min(self.pool, key=lambda p: len(p.vehicles))  # the least loaded worker
                    w = VehicleWorker(vehicle, self.config, self.sink, self.pubs, self.rr, pw)
                    pw.vehicles.append(w)
                    if self.ros_in is not None and vehicle == self.config.ros2.vehicle:
                        w.notes = lambda: dict(self.ros_in.counters) | {
                            f"silent_topic:{t}": 1 for t in self.ros_in.silent_topics()
                        }
                    if self.fleet_view is not None:
                        w.on_retired = self._retired
                        w.fleet_states_of = functools.partial(self.fleet_states.get, vehicle)
                        w.engine.life.resume_from_fleet = w.resume_from_fleet
                        w.fleet_me = self.fleet_view.me
                        w.state_to = self._state_to
                        states = self.fleet_states.get(vehicle)
                        if states:  # another service served it: start from its last state
                            w.loop.starter = lambda t, w=w, states=states: w.take_over(states, t)
                    elif self.fleet_states is not None and self.feed_fd is not None:
                        states = self.fleet_states.get(vehicle)
                        if states:  # a restarted shard: the vehicle goes on from its last state
                            w.loop.starter = lambda t, w=w, states=states: w.take_over(states, t)
                    if "*" in self.config.vehicles:
                        w.idle_s = self.config.intake.vehicle_idle_s
                        w.on_released, w.reroute = self._released, self._reroute
                    self.workers[vehicle] = w
                    self.liveliness.declare(keys.service(vehicle, "alive", self.config.prefix))
                    self._capacity()
                    if self._owned_intake and (intake := getattr(self, "intake", None)) is not None:
                        intake.watch(vehicle)  # (found by its discovery keys: all of it from now on)
        return w

    def _deliver_each(self, batch: list[tuple[float, str, bytes]]) -> None:
        """A drain of the owned-vehicles intake handed to a pool of worker threads one by one."""
        for item in batch:
            try:
                self._deliver(*item)
            except Exception:  # routing must survive any one message
                log.exception("intake: delivery of %s failed", item[1][:200])

    def _resubscribe(self) -> None:
        """[intake] subscribe = 'owned': subscribe to the vehicles this member serves and to those
        it owns now by the fleet's membership and of which a handover state arrived lately (a
        member that left or died: its vehicles, to be taken over from their states), at most
        max_vehicles; drop the rest. New vehicles are found by their discovery keys (_worker).
        Under the service's lock: a vehicle made meanwhile by the intake (_worker, which subscribes
        to it) is not unsubscribed by a list made before it."""
        horizon = 3.0 * self.config.fleet.handover_period_s + 30.0
        recent = self.fleet_states.recent(horizon) if self.fleet_view.active else []
        with self._lock:
            want = set(self.workers)
            room = self.config.intake.max_vehicles - len(want)
            # then the vehicles announced by their publishers (keys.sensors_alive), most of
            # them not served yet: their IMU heard from the start
            announced = list(self._announced) if self.fleet_view.active else []
            for v in itertools.chain(recent, announced):
                if room <= 0:
                    break
                if v not in want and self.fleet_view.mine(v):
                    want.add(v)
                    room -= 1
            self.intake.set_vehicles(want)

    def _capacity(self) -> None:
        """A '*' service reaching its max_vehicles declares itself full (a fleet member first one
        ``holds`` token per vehicle it keeps, then the ``full`` token: a member that sees it full
        always knows what it holds), and withdraws that when a vehicle leaves (the ``full`` token
        first). A fleet member then takes new vehicles only after 1.5 handover periods, as when it
        joins: the members that took its vehicles meanwhile hand them back with their last states.
        Called under ``self._lock``."""
        if "*" not in self.config.vehicles or self.session is None:
            return
        prefix, zid = self.config.prefix, str(self.session.zid())
        full = len(self.workers) >= self.config.intake.max_vehicles
        if full == self._full_declared:
            return
        self._full_declared = full
        if full:
            if self._full_grace is not None:
                self._full_grace.cancel()
                self._full_grace = None
            if self.fleet_view is not None:
                for v in list(self.workers):
                    self.liveliness.declare(keys.service_holds(zid, v, prefix))
                if self.fleet_view.set_me_full(True):
                    self._forget_foreign()
            self.liveliness.declare(keys.service_full(zid, prefix))
            log.warning(
                "at max_vehicles (%d): new vehicles are refused%s",
                self.config.intake.max_vehicles,
                " unless another service of the fleet group has room" if self.fleet_view is not None else "",
            )
            return
        self.liveliness.undeclare(keys.service_full(zid, prefix))
        if self.fleet_view is not None:
            for key in self.liveliness.keys(f"{keys.service_token(zid, prefix)}/holds/"):
                self.liveliness.undeclare(key)
            t = threading.Timer(1.5 * self.config.fleet.handover_period_s, self._not_full)
            t.daemon = True
            self._full_grace = t
            t.start()
        log.info("below max_vehicles again (%d vehicles): new vehicles are taken", len(self.workers))

    def _not_full(self) -> None:
        with self._lock:
            if self._full_declared or self.session is None:
                return
            self._full_grace = None
            if self.fleet_view.set_me_full(False):
                self._forget_foreign()

    def service_health(self) -> ServiceHealth:
        return ServiceHealth(
            uptime_s=time.monotonic() - self.started,
            vehicles=list(self.config.vehicles),
            active_vehicles=sorted(self.workers),
            refused_before_routing=dict(self.unrouted)
            | (
                {"bad_shard_frame": bad}
                if (bad := getattr(getattr(self, "intake", None), "bad_frames", 0))
                else {}
            ),
            unserved_vehicles=dict(self.unserved),
            messages_received=sum(w.received for w in list(self.workers.values())),
            fleet_group=self.fleet_group if self.fleet_view is not None else None,
            fleet_members=self.fleet_view.members() if self.fleet_view is not None else [],
            vehicles_moved_away=self.retired_vehicles,
            vehicles_released_idle=self.released_vehicles,
            inputs_served_elsewhere=getattr(getattr(self, "intake", None), "unwanted", 0),
            subscribed_vehicles=(
                len(self.intake.vehicles()) if self._owned_intake and hasattr(self, "intake") else None
            ),
            inputs_discovery_copies=getattr(getattr(self, "intake", None), "discovery_copies", 0),
            inputs_forwarded=sum(f.forwarded for f in self.feeds.values()),
            inputs_forward_lost=sum(f.lost for f in self.feeds.values()),
            max_vehicles=self.config.intake.max_vehicles if "*" in self.config.vehicles else None,
            full=self._full_declared,
            refusing_vehicles=self._refusing(),
        )

    def _refusing(self) -> list[str]:
        """The vehicles refused for vehicle_limit in the last REFUSING_WINDOW_S (the rest forgotten)."""
        since = time.monotonic() - REFUSING_WINDOW_S
        for v, t in list(self._limit_refused.items()):
            if t < since:
                self._limit_refused.pop(v, None)
        return sorted(self._limit_refused)[:100]

    def _health_loop(self) -> None:
        period = self.config.output.health_period_s
        next_health = time.monotonic() + period
        while not self._health_stop.wait(0.05):
            if self._rebalance_due.is_set():
                self._rebalance_due.clear()
                try:
                    self._rebalance()
                except Exception:
                    log.exception("fleet rebalance failed")
            if self._owned_intake and self._resubscribe_due.is_set():
                self._resubscribe_due.clear()
                try:
                    self._resubscribe()
                except Exception:
                    log.exception("fleet resubscription failed")
            if time.monotonic() < next_health:
                continue
            next_health = time.monotonic() + period
            if self._owned_intake:  # a vehicle made before the intake was there: subscribed now
                try:
                    for v in set(self.workers) - self.intake.vehicles():
                        self.intake.watch(v)
                except Exception:
                    log.exception("vehicle subscription failed")
            try:
                self.pubs.publish(self._health_key, self.service_health())
            except Exception:  # a publication failure must not end the loop
                log.exception("service health publication failed")

    def _refuse(self, reason: str, vehicle: str) -> None:
        """Data the service does not take for any vehicle: counted (ServiceHealth, status
        queryable) and logged once per vehicle name and reason (at most ``_MAX_LOGGED_REFUSALS``
        of them, then one line that says the log names no more)."""
        self.unrouted[reason] += 1
        if reason == "vehicle_limit" and (
            vehicle in self._limit_refused or len(self._limit_refused) < _MAX_LOGGED_NAMES
        ):
            self._limit_refused[vehicle] = time.monotonic()
        if reason == "unserved_vehicle" and (
            vehicle in self.unserved or len(self.unserved) < _MAX_LOGGED_NAMES
        ):
            self.unserved[vehicle] += 1
        if (reason, vehicle) not in self._logged and len(self._logged) <= _MAX_LOGGED_REFUSALS:
            self._logged.add((reason, vehicle))
            if len(self._logged) > _MAX_LOGGED_REFUSALS:
                log.warning(
                    "further refused vehicle names are not logged (%d named); ServiceHealth counts "
                    "them (refused_before_routing, unserved_vehicles): %s",
                    _MAX_LOGGED_REFUSALS,
                    getattr(self, "_health_key", f"{self.config.prefix}/_services/*/health"),
                )
                return
            served = self.config.vehicles
            hint = (
                " (publish under a served name, or add it to 'vehicles' in the configuration)"
                if reason == "unserved_vehicle"
                else ""
            )
            log.warning("%s: data for vehicle %r refused (served: %s)%s", reason, vehicle[:80], served, hint)

    def _deliver(self, wall: float, key: str, payload: bytes) -> None:
        routed = self._route(wall, key, payload)
        if routed is not None:
            w, item = routed
            w.pool_worker.submit(w, item)

    def _deliver_many(self, items: list[tuple[float, str, bytes]]) -> None:
        """The inline intake's drain of its channel: routed first, so that each vehicle's Health
        ``queue_depth`` counts what of it still waits, then run in order, a vehicle's consecutive
        JSON IMU samples of one stream together (:func:`json_imu_runs`)."""
        routed = []
        for wall, key, payload in items:
            try:
                r = self._route(wall, key, payload)
            except Exception:  # routing must survive any one message
                log.exception("intake: delivery of %s failed", key[:200])
                continue
            if r is not None:
                r[0].queued += 1
                routed.append(r)
        for w, run in json_imu_runs(routed):
            w.queued -= len(run)
            if len(run) == 1:
                w.pool_worker.submit(w, run[0])
            else:
                w.pool_worker.submit_imu_json(w, run)

    def _route(self, wall: float, key: str, payload: bytes) -> tuple[VehicleWorker, tuple] | None:
        """The vehicle an input is for and its item, or None (refused and counted, or not ours)."""
        pk = keys.parse_input(key, self.config.prefix)
        if pk is None and keys.is_output(key, self.config.prefix):
            if self.feed_fd is not None and self.fleet_states is not None:
                self._on_state(key, payload)  # from shard 0's feed: this restarted shard's states
            return None  # another fednav service's outputs share the prefix: not input, not an error
        parts = key.split("/")
        vehicle = parts[1] if len(parts) > 1 else ""
        if not keys.valid_name(vehicle):
            return self._refuse("bad_vehicle_name", vehicle)
        if self.fleet_view is not None:
            gen = self._foreign_gen  # read before the verdict (see _forget_foreign)
            if not self.fleet_view.mine(vehicle):
                if self.fleet_view.active:
                    self._note_foreign(vehicle, gen)
                return None  # another service of the fleet serves it (validated name first)
        elif self.shard is not None and not self._mine(vehicle):
            if not self.feeds:  # shard 0 hands its intake's such inputs on instead (_forward)
                self._note_foreign(vehicle, self._foreign_gen)
            return None  # another shard of this service serves it (validated name first)
        serve_all = "*" in self.config.vehicles
        if not serve_all and vehicle not in self.config.vehicles:
            return self._refuse("unserved_vehicle", vehicle)
        if pk is None and vehicle not in self.workers:
            # a key that is no sensor input (another client's data under the prefix): counted for
            # the service, no vehicle made of it (150 foreign names made 150 vehicles, each with
            # its token, Health and a max_vehicles slot for [intake] vehicle_idle_s)
            return self._refuse("unknown_key", vehicle)
        if serve_all and vehicle not in self.workers and len(self.workers) >= self.config.intake.max_vehicles:
            return self._refuse("vehicle_limit", vehicle)
        w = self._worker(vehicle)
        w.last_input = wall
        if pk is None:
            w.received += 1
            w.reject("unknown_key", key)
            return None
        return w, (wall, pk.kind, pk.sensor_id, payload)

    def _wanted(self, key: str) -> bool:
        """The intake's early filter: False only for an input of a vehicle :meth:`_route` found to be
        another shard's or fleet member's (every other key is routed as before). With S services
        or shards each receives the whole fleet's inputs to keep 1/S of them; this drops the rest
        for a key split and a set lookup, before the arrival time, the payload copy and the
        key's parsing."""
        parts = key.split("/", 2)
        return len(parts) < 2 or parts[1] not in self._foreign

    def _forward(self, key: str):
        """Shard 0's intake: the feed of the local shard that serves the key's vehicle, or None
        (this shard's, or a name :meth:`_route` refuses and counts here)."""
        parts = key.split("/", 3)
        if len(parts) < 3 or parts[2] in ("nav", "service"):
            return None  # outputs (the prefix's own, other shards' included): _route ignores them
        vehicle = parts[1]
        if self.fleet_view is not None:
            # in a fleet group each local shard is a member under its own Zenoh id: a vehicle goes
            # to the shard the fleet gives it (the local hash would send some of them to a shard
            # that does not own them, while their owner never hears them); not cached: ownership
            # changes with the members
            index = self.shard_members.get(self.fleet_view.owner(vehicle))
            if index is None or not keys.valid_name(vehicle) or vehicle in ("_services", "_fleet"):
                return None  # this shard's (or another member's, or a name _route refuses)
            return self.feeds.get(index)
        try:
            return self._feed_of[vehicle]
        except KeyError:
            pass
        feed = None
        if keys.valid_name(vehicle) and vehicle not in ("_services", "_fleet"):
            feed = self.feeds.get(fleet.shard_of(vehicle, self.shard[1]))
        if len(self._feed_of) > 100_000:
            self._feed_of.clear()
        self._feed_of[vehicle] = feed
        return feed

    def shard_states(self, index: int) -> list[list]:
        """Shard 0: the latest handover states of local shard ``index``'s vehicles, as feed items
        (the first frame of a restarted shard's new pipe)."""
        if self.fleet_states is None or self.shard_group is None or self.fleet_view is not None:
            return []  # (in a fleet group a restarted shard is a new member: the fleet hands it states)
        now, k, prefix = time.monotonic(), self.shard[1], self.config.prefix
        return [
            [now, keys.fleet_state(self.shard_group, vehicle, pipeline, prefix), payload]
            for vehicle, d in self.fleet_states.snapshot().items()
            if fleet.shard_of(vehicle, k) == index
            for pipeline, payload in d.items()
        ]

    def _note_foreign(self, vehicle: str, gen: int) -> None:
        with self._foreign_lock:
            if gen == self._foreign_gen:  # no membership change since the verdict was made
                if len(self._foreign) > 200_000:
                    self._foreign.clear()
                self._foreign.add(vehicle)

    def _forget_foreign(self) -> None:
        """Ownership changed (a member came or went, this service joined): every verdict goes."""
        with self._foreign_lock:
            self._foreign_gen += 1
            self._foreign.clear()
        if self._resubscribe_due is not None:
            self._resubscribe_due.set()

    # --- fleet sharing ([fleet] sharding = "rendezvous") -----------------------------------------
    def _on_member(self, key: str, payload: bytes | None) -> None:
        """A fleet member's token appeared or vanished (Zenoh callback: record, never block)."""
        if self.fleet_view.update(key.rsplit("/", 1)[-1], payload is not None):
            self._forget_foreign()
            self._rebalance_due.set()

    def _on_full(self, key: str, payload: bytes | None) -> None:
        """A service's ``full`` token appeared or vanished (Zenoh callback)."""
        if self.fleet_view.set_full(key.split("/")[-2], payload is not None):
            self._forget_foreign()
            self._rebalance_due.set()

    def _on_holds(self, key: str, payload: bytes | None) -> None:
        """A ``holds`` token of a service appeared or vanished (Zenoh callback)."""
        parts = key.split("/")
        if len(parts) >= 4 and self.fleet_view.set_holds(parts[-3], parts[-1], payload is not None):
            self._forget_foreign()
            self._rebalance_due.set()

    def _state_to(self, vehicle: str) -> list[str]:
        """Where a served vehicle's handover states go (VehicleWorker.publish_states): while it is
        this member's, its heir (the member that owns it if this one goes: stopped, killed or past
        its lease) and a joining service that will own it (which then starts it from its state);
        once it is not, its new owner (it moves: the last state as it goes)."""
        view = self.fleet_view
        if view.mine(vehicle):
            to = [m for m in (view.heir(vehicle), view.joiner_owner(vehicle)) if m is not None]
            return to if len(to) < 2 or to[0] != to[1] else to[:1]
        owner = view.owner(vehicle)
        return [] if owner == view.me else [owner]

    def _on_joining(self, key: str, payload: bytes | None) -> None:
        """A service's ``joining`` token appeared or vanished (Zenoh callback: record only)."""
        self.fleet_view.set_joining(key.rsplit("/", 1)[-1], payload is not None)

    def _on_state(self, key: str, payload: bytes | None) -> None:
        """A handover state: ``{prefix}/_fleet/{group}/to/{me}/state/{vehicle}/{pipeline}`` (a
        fleet member's) or ``.../state/{vehicle}/{pipeline}`` (a local shard's, for shard 0)."""
        parts = key.split("/")
        if len(parts) == 8 and parts[3] == "to":
            parts = parts[:3] + parts[5:]
        if payload is not None and len(parts) == 6 and len(payload) <= MAX_PAYLOAD_BYTES:
            self.fleet_states.put(parts[4], parts[5], payload)
            # a vehicle handed to this member (the state its old owner published as it let it go)
            # and not subscribed yet: subscribed now, not at its next discovery message
            intake = getattr(self, "intake", None) if self._owned_intake else None
            if intake is not None and parts[4] not in intake.watched and self.fleet_view.mine(parts[4]):
                self._resubscribe_due.set()

    def _on_announced(self, key: str, payload: bytes | None) -> None:
        """A publisher's announcement of a vehicle (keys.sensors_alive) appeared or vanished
        (Zenoh callback: record, never block): an owned one not subscribed yet is subscribed by
        the health loop (_resubscribe), before the vehicle's first message."""
        parts = key[len(self.config.prefix) + 1 :].split("/")
        if len(parts) != 3 or not keys.valid_name(parts[0]):
            return
        vehicle = parts[0]
        if payload is None:
            self._announced.discard(vehicle)
            return
        if vehicle in self._announced or len(self._announced) >= ANNOUNCED_MAX:
            return
        self._announced.add(vehicle)
        intake = getattr(self, "intake", None)
        if intake is not None and vehicle not in intake.watched and self.fleet_view.mine(vehicle):
            self._resubscribe_due.set()

    def _join_fleet(self) -> None:
        if self.session is None:
            return
        self.liveliness.declare(self._fleet_token)
        self.fleet_view.active = True
        self._forget_foreign()
        self.liveliness.undeclare(
            keys.fleet_joining(self.fleet_group, str(self.session.zid()), self.config.prefix)
        )
        log.info("joined fleet group %s: members %s", self.fleet_group, self.fleet_view.members())

    def _rebalance(self) -> None:
        """After a membership change: every served vehicle that hashes to another service now is
        retired (its last state published for the new owner, then dropped here)."""
        for vehicle, w in list(self.workers.items()):
            if not self.fleet_view.mine(vehicle) and not w.retired:
                w.pool_worker.submit(w, (time.monotonic(), None, RETIRE, b""))

    def _retired(self, w: VehicleWorker) -> None:
        with self._lock:
            if self.workers.get(w.vehicle) is w:
                del self.workers[w.vehicle]
            self._capacity()
        self.liveliness.undeclare(keys.service(w.vehicle, "alive", self.config.prefix))
        self.retired_vehicles += 1
        if self._owned_intake:  # its subscription goes to its new owner (_resubscribe)
            self._resubscribe_due.set()
        log.info("vehicle %s moved to service %s", w.vehicle, self.fleet_view.owner(w.vehicle))

    def _released(self, w: VehicleWorker) -> None:
        """A vehicle released idle (PoolWorker._release): its slot, token and outputs' state freed."""
        with self._lock:  # (under the lock: a new worker of the name is not made meanwhile)
            self.released_vehicles += 1
            if self.workers.get(w.vehicle) is not w:
                return
            del self.workers[w.vehicle]
            self.liveliness.undeclare(keys.service(w.vehicle, "alive", self.config.prefix))
            self.sink.forget(w.vehicle)
            self.pubs.forget(w.vehicle, self.config.prefix)
            self._capacity()
        log.info(
            "vehicle %s released: no input for %.0f s ([intake] vehicle_idle_s)",
            w.vehicle,
            time.monotonic() - w.last_input,
        )

    def _reroute(self, old: VehicleWorker, item) -> VehicleWorker | None:
        """The worker for an input that reached ``old`` after its release: the vehicle's new one,
        or None (refused and counted: the service is at max_vehicles)."""
        vehicle = old.vehicle
        if vehicle not in self.workers and len(self.workers) >= self.config.intake.max_vehicles:
            self._refuse("vehicle_limit", vehicle)
            return None
        w = self._worker(vehicle)
        w.last_input = max(w.last_input, item[0])
        return w

    def _served_list(self) -> list[str]:
        """The configured vehicle names this process serves (its shard's share)."""
        return [v for v in self.config.vehicles if self.shard is None or self._mine(v)]

    def _mine(self, vehicle: str) -> bool:
        mine = self._shard_cache.get(vehicle)
        if mine is None:
            if len(self._shard_cache) > 100_000:
                self._shard_cache.clear()
            mine = self._shard_cache[vehicle] = fleet.shard_of(vehicle, self.shard[1]) == self.shard[0]
        return mine

    def _answer(self, query_ke) -> list[tuple[str, bytes, str]]:
        """Replies to a query: for each vehicle (served, or seen with ``*``) its status, its
        configuration and each pipeline's latest Solution whose key intersects the query."""
        from fednav.service.transport.zenoh_io import intersects

        prefix = self.config.prefix
        vehicles = sorted(self.workers) if "*" in self.config.vehicles else self._served_list()
        latest = list(self.sink.last_solution.items())
        out = []
        if intersects(self._health_key, query_ke):
            h = self.service_health()
            out.append((self._health_key, h.model_dump_json().encode(), h.encoding()))
        for v in vehicles:
            resources = {
                keys.service(v, "status", prefix): (lambda v=v: self._status(v), STATUS_ENCODING),
                keys.service(v, "config", prefix): (self._effective_config_json, CONFIG_ENCODING),
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

    def _effective_config_json(self) -> str:
        """The configuration reply: the service's configuration with the Zenoh endpoints and
        config file it really uses (a command line's ``--listen``, ``--connect`` and
        ``--zenoh-config`` replace the file's; the reply used to show the file's)."""
        z: dict = {}
        if self.listen is not None:
            z["listen"] = list(self.listen)
        if self.connect is not None:
            z["connect"] = list(self.connect)
        if self.zenoh_config_file is not None:
            z["config_file"] = Path(self.zenoh_config_file)
        cfg = self.config
        if z:
            cfg = cfg.model_copy(update={"zenoh": cfg.zenoh.model_copy(update=z)})
        return cfg.model_dump_json()

    def _status(self, vehicle: str) -> str:
        """The status reply (docs/schemas/Status.schema.json)."""
        w = self.workers.get(vehicle)
        return Status(
            vehicle=vehicle,
            running=True,
            pipelines=[p.name for p in self.config.pipelines],
            health=w.health() if w else None,
            refused_before_routing=dict(self.unrouted),
        ).model_dump_json()

    def stop(self) -> None:
        if self.session is None:
            return
        self.stopping = "health"
        self._health_stop.set()
        self._health_thread.join(timeout=5.0)
        self.stopping = "intake"
        self.intake.stop()
        if self.intake.unwanted:
            log.info("intake: %d inputs of vehicles served elsewhere dropped unread", self.intake.unwanted)
        self.stopping = "watches"
        for watch in self._watches:
            watch.stop()
        if self.ros_intake is not None:
            self.ros_intake.stop()
        self.stopping = "workers"
        for pw in self.pool:
            pw.request_stop()
        deadline = time.monotonic() + _SHUTDOWN_DRAIN_S
        for pw in self.pool:
            pw.stop(deadline)
        self.stopping = "queries"
        self.queries.stop()
        self.stopping = "liveliness"
        self.liveliness.undeclare_all()
        if self.rr is not None:
            self.stopping = RECORDING_STAGE
            self.rr.close()
        self.stopping = "publishers"
        self.pubs.undeclare_all()
        self.stopping = "session"
        self.session.close()
        self.session = None
        self.stopping = "done"
        log.info("fednav-service stopped; recording %s", self.rrd_path if self.record else None)
