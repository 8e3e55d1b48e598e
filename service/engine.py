"""Per-vehicle engine: consumes validated events in sensor-time order and drives the pipelines.

The same code runs inside the service (events from Zenoh) and in ``fednav-sim eval`` (events
generated in-process), so both give the same solutions for the same input stream.

Time handling (DESIGN.md "The service's inner loop"):
- The IMU stream drives time. An aiding measurement at t_m is queued until the INS reaches t_m;
  the IMU interval containing t_m is split there (constant-rate assumption), the pipelines
  update at exactly t_m, and propagation resumes.
- Aiding older than the INS time by at most ``late_tolerance_s`` is applied at the INS time (a
  GNSS fix is carried forward with its own velocity); older is rejected as ``late``. Aiding
  ahead by more than ``max_lead_s`` is rejected as ``early``. Same key and same t: ``duplicate``.
- IMU time going backwards is rejected (``time_backwards``; equal time: ``duplicate``). A gap
  longer than ``max_imu_gap_s`` marks the INS lost: pipelines are re-initialised from the next
  GNSS fix (status ``reinitialised``).
- These acceptance rules are :class:`service.intake_rules.AcceptanceRules` (one verdict per event).

Initialisation (``[init] mode``):
- ``message``: from an InitialNav (position, velocity, attitude and their sigmas, as a host
  system hands over; the simulators send truth with the scenario's initial errors applied).
- ``auto`` (default): InitialNav whenever one arrives (also re-initialises); otherwise, once
  ``align_time_s`` of IMU data is in: if the vehicle was static (specific-force and rate
  scatter small), static coarse alignment (levelling + gyrocompassing) at the latest GNSS fix
  position; else, in motion with a GNSS fix faster than ``min_speed_mps``: position and
  velocity from the fix, heading and pitch from the velocity track, roll 0, wide sigmas.
- ``static`` / ``gnss_motion`` force the respective fallback.
The alignment maths and its thresholds are in :mod:`service.ins.alignment`.
"""

from __future__ import annotations

import math
from collections import Counter
from typing import Protocol

import numpy as np

from service import earth
from service.config import LooselyCoupledConfig, ServiceConfig
from service.ins import alignment
from service.ins.mechanisation import NavState, Preintegrator
from service.intake_rules import AcceptanceRules, Verdict
from service.messages import GnssFix, ImuSample, InitialNav, Solution, Truth, WireModel
from service.pipelines.base import InitStd, Pipeline, nav_errors


class EngineSink(Protocol):
    """Where the engine's outputs go (the service publishes/records; eval collects)."""

    def on_solution(self, vehicle: str, sol: Solution, err9: np.ndarray | None, P9: np.ndarray) -> None: ...

    def on_output(self, vehicle: str, msg: WireModel, err9: np.ndarray | None = None) -> None: ...

    def on_truth(self, vehicle: str, truth: Truth) -> None: ...

    # A sink may set ``wants_solutions = False`` and implement
    # ``on_estimate(vehicle, pipeline, t, err9, P9)`` instead of receiving Solution messages.


def build_pipeline(cfg, config: ServiceConfig) -> Pipeline:
    """Instantiate a pipeline from its config (the registry of pipeline kinds)."""
    if isinstance(cfg, LooselyCoupledConfig):
        from service.pipelines.loosely_coupled import LooselyCoupled

        return LooselyCoupled(cfg, config.imu, config.major_interval_s)
    if cfg.kind in ("federated", "centralized"):
        from service.pipelines.federated import Centralized, Federated

        cls = Federated if cfg.kind == "federated" else Centralized
        return cls(cfg, config.imu, config.major_interval_s)
    if cfg.kind == "tightly_coupled":
        from service.pipelines.tightly_coupled import TightlyCoupled

        return TightlyCoupled(cfg, config.imu, config.major_interval_s)
    from service.pipelines import build_pipeline as from_registry  # every other registered kind

    return from_registry(cfg, config)


class VehicleEngine:
    """Drives all configured pipelines of one vehicle from a time-ordered event stream."""

    def __init__(
        self, vehicle: str, config: ServiceConfig, sink: EngineSink, counters: Counter | None = None
    ):
        self.vehicle = vehicle
        self.config = config
        self.sink = sink
        self.rejected: Counter = counters if counters is not None else Counter()
        self.pipelines: list[Pipeline] = [build_pipeline(p, config) for p in config.pipelines]
        self.initialised = False
        self.pre = Preintegrator()  # the vehicle's one minor loop, shared by every pipeline
        self.last_imu_t: float | None = None
        self.pending: list[tuple[float, str, str, WireModel]] = []
        self.rules = AcceptanceRules(config.intake)
        self._truth: dict[int, Truth] = {}
        self._last_fix: GnssFix | None = None
        self._align = alignment.ImuAccumulator()
        self._last_out_k = -1
        self._lost = False
        self.last_t: float | None = None

    # --- entry point ----------------------------------------------------------------------------
    def handle(self, kind: str, sensor_id: str, msg: WireModel) -> bool:
        """Process one validated event. Returns False when it was rejected (reason counted)."""
        verdict = self.rules.decide(kind, sensor_id, msg, self.last_imu_t, self.initialised)
        if kind == "imu":
            return self._on_imu(msg, verdict)
        if kind == "gnss_fix" and verdict.in_sequence:
            self._last_fix = msg  # the newest fix, also when not applied (alignment uses it)
        if verdict.reason == "not_initialised":
            self._try_initialise_from_aiding()  # this message may complete an alignment
            if self.initialised:
                return True
        if not verdict.accepted:
            return self._reject(verdict.reason)
        if kind == "init":
            self._initialise_from_message(msg)
        elif kind == "truth":
            self._keep_truth(msg)
        else:
            self._schedule(kind, sensor_id, msg)
        return True

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

    @staticmethod
    def _tkey(t: float) -> int:
        return int(round(t * 1e6))

    # --- IMU ------------------------------------------------------------------------------------
    def _on_imu(self, msg: ImuSample, verdict: Verdict) -> bool:
        t, dt = msg.t, msg.dt_s
        if verdict.reason == "imu_gap":
            self._imu_gap(t)
            return True
        if not verdict.accepted:
            return self._reject(verdict.reason)
        if not self.initialised:
            self._align.add(t, dt, msg.dtheta_rad, msg.dvel_mps)
            self.last_imu_t = t
            self._try_initialise_from_aiding()
            return True
        span = t - self.last_imu_t
        scale = span / dt  # a short gap (< max_imu_gap_s) stretches the sample over it
        dth = [v * scale for v in msg.dtheta_rad]
        dv = [v * scale for v in msg.dvel_mps]
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
        self.last_imu_t = t
        self.last_t = t
        self._maybe_output(t)
        return True

    def _push(self, dth, dv, dt, t_end) -> None:
        """One minor-loop step for every pipeline at once (shared preintegration)."""
        pre = self.pre
        pre.push(dth, dv, dt, t_end)
        if pre.T >= self.config.major_interval_s - 1e-9:
            self._advance_all()

    def _advance_all(self) -> None:
        """Bring every pipeline's INS to the engine's time (major update from the shared loop)."""
        pre = self.pre
        if pre.T > 0.0:
            for p in self.pipelines:
                p.advance(pre)
            pre.reset(pre.t_end)

    def _imu_gap(self, t: float) -> None:
        self.rejected["imu_gap"] += 1
        self._lost = True
        self.initialised = False
        self.pending.clear()
        self.last_imu_t = t
        self._align = alignment.ImuAccumulator()
        for p in self.pipelines:
            p.mark_lost()

    # --- aiding ---------------------------------------------------------------------------------
    def _apply(self, kind: str, sensor_id: str, msg: WireModel, dt_late: float) -> None:
        self._advance_all()
        for p in self.pipelines:
            p.sync()
            try:
                outputs = p.apply(kind, sensor_id, msg, dt_late)
            except np.linalg.LinAlgError:
                self.rejected["numerical"] += 1
                p.recover_covariance()
                continue
            err9 = self._errors(p, msg.t) if outputs else None
            for out in outputs:
                self.sink.on_output(self.vehicle, out, err9)

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
        wants = getattr(self.sink, "wants_solutions", True)
        self._advance_all()
        for p in self.pipelines:
            p.sync()
            est = p.estimate()
            err9 = self._errors(p, est.nav.t, est)
            if wants:
                self.sink.on_solution(self.vehicle, p.solution(est), err9, est.P9)
            else:  # evaluation without solution messages: skip building them
                self.sink.on_estimate(self.vehicle, p.name, est.nav.t, err9, est.P9)

    def _errors(self, p: Pipeline, t: float, est=None) -> np.ndarray | None:
        """Errors of a pipeline's estimate against truth at t (None without truth at t)."""
        truth = self._truth.get(self._tkey(t))
        if truth is None:
            return None
        est = est or p.estimate()
        llh = np.array([math.radians(truth.lat_deg), math.radians(truth.lon_deg), truth.height_m])
        c_nb = earth.rpy_to_mat_nb(earth.rpy_from_msg_deg(truth.rpy_deg))
        return nav_errors(est.nav, llh, np.asarray(truth.vel_enu_mps), c_nb)

    # --- initialisation ---------------------------------------------------------------------------
    def _start(self, nav: NavState, std: InitStd) -> None:
        for p in self.pipelines:
            p.start(nav, std, after_loss=self._lost)
        self.pre = Preintegrator()
        self.pre.reset(nav.t)
        self.initialised = True
        self._lost = False
        self.last_imu_t = nav.t
        self.last_t = nav.t
        self._last_out_k = -1
        self.pending.clear()

    def _initialise_from_message(self, msg: InitialNav) -> None:
        if self.config.init.mode not in ("auto", "message"):
            return
        self._start(*alignment.from_initial_nav(msg))

    def _try_initialise_from_aiding(self) -> None:
        """Coarse alignment from the latest GNSS fix and the IMU data so far, when ``[init] mode``
        allows it: in motion (fix speed >= ``min_speed_mps``), or static after ``align_time_s``."""
        mode = self.config.init.mode
        t = self.last_imu_t
        if self.initialised or mode == "message" or t is None:
            return
        fix = self._last_fix
        if fix is None or not alignment.fix_is_current(fix, t):
            return
        speed = alignment.fix_speed(fix)
        if mode in ("auto", "gnss_motion") and speed >= self.config.init.min_speed_mps:
            self._start(*alignment.motion_alignment(fix, t))
            return
        if (
            mode in ("auto", "static")
            and self._align.covers(t, self.config.init.align_time_s)
            and speed < alignment.STATIC_MAX_SPEED_MPS
        ):
            sg, sa = self.config.imu.bias_sigmas()
            aligned = alignment.static_alignment(self._align, fix, t, sg, sa)
            if aligned is not None:  # else not static: wait for motion initialisation
                self._start(*aligned)

    # --- state for health ---------------------------------------------------------------------------
    def pipeline_states(self) -> dict[str, dict]:
        return {
            p.name: {
                "status": p.status,
                "last_t": self.last_t,
                "updates": p.updates,
                "reinitialisations": p.reinitialisations,
            }
            for p in self.pipelines
        }
