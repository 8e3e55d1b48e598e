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

Initialisation (``[init] mode``):
- ``message``: from an InitialNav (position, velocity, attitude and their sigmas, as a host
  system hands over; the simulators send truth with the scenario's initial errors applied).
- ``auto`` (default): InitialNav whenever one arrives (also re-initialises); otherwise, once
  ``align_time_s`` of IMU data is in: if the vehicle was static (specific-force and rate
  scatter small), static coarse alignment (levelling + gyrocompassing) at the latest GNSS fix
  position; else, in motion with a GNSS fix faster than ``min_speed_mps``: position and
  velocity from the fix, heading and pitch from the velocity track, roll 0, wide sigmas.
- ``static`` / ``gnss_motion`` force the respective fallback.
"""

from __future__ import annotations

import math
from collections import Counter
from dataclasses import dataclass, field
from typing import Protocol

import numpy as np

from service import earth
from service.config import LooselyCoupledConfig, ServiceConfig
from service.ins.mechanisation import NavState, Preintegrator
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
    raise ValueError(f"unknown pipeline kind {cfg.kind!r}")  # unreachable: config validates kinds


@dataclass
class _Align:
    t_start: float | None = None
    n: int = 0
    sum_w: np.ndarray = field(default_factory=lambda: np.zeros(3))
    sum_f: np.ndarray = field(default_factory=lambda: np.zeros(3))
    sum_f2: np.ndarray = field(default_factory=lambda: np.zeros(3))


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
        self._last_t_by_key: dict[tuple[str, str], float] = {}
        self._truth: dict[int, Truth] = {}
        self._last_fix: GnssFix | None = None
        self._align = _Align()
        self._last_out_k = -1
        self._lost = False
        self.last_t: float | None = None

    # --- entry point ----------------------------------------------------------------------------
    def handle(self, kind: str, sensor_id: str, msg: WireModel) -> bool:
        """Process one validated event. Returns False when it was rejected (reason counted)."""
        key = (kind, sensor_id)
        if kind != "imu":
            prev = self._last_t_by_key.get(key)
            if prev is not None and msg.t == prev:
                return self._reject("duplicate")
        if kind == "imu":
            return self._on_imu(msg)
        if kind == "init":
            self._last_t_by_key[key] = msg.t
            self._initialise_from_message(msg)
            return True
        if kind == "truth":
            if prev is not None and msg.t < prev:
                return self._reject("time_backwards")
            self._last_t_by_key[key] = msg.t
            self._truth[self._tkey(msg.t)] = msg
            if len(self._truth) > 256:
                for k in sorted(self._truth)[:128]:
                    del self._truth[k]
            self.sink.on_truth(self.vehicle, msg)
            return True
        # aiding: older than the INS by more than the tolerance is "late" (checked first: it is
        # the more useful reason); older than the same sensor's previous message is "time_backwards"
        if self.initialised and msg.t < self.last_imu_t - self.config.intake.late_tolerance_s:
            return self._reject("late")
        if prev is not None and msg.t < prev:
            return self._reject("time_backwards")
        if kind == "gnss_fix":
            self._last_fix = msg
        if not self.initialised:
            self._last_t_by_key[key] = msg.t
            self._try_initialise_from_aiding()
            return self._reject("not_initialised") if not self.initialised else True
        t_ins = self.last_imu_t
        if msg.t > t_ins + self.config.intake.max_lead_s:
            return self._reject("early")
        if msg.t < t_ins - self.config.intake.late_tolerance_s:
            return self._reject("late")
        self._last_t_by_key[key] = msg.t
        if msg.t > t_ins + 1e-9:
            self.pending.append((msg.t, kind, sensor_id, msg))
            self.pending.sort(key=lambda e: e[0])
        else:
            self._apply(kind, sensor_id, msg, dt_late=t_ins - msg.t)
        return True

    def _reject(self, reason: str) -> bool:
        self.rejected[reason] += 1
        return False

    @staticmethod
    def _tkey(t: float) -> int:
        return int(round(t * 1e6))

    # --- IMU ------------------------------------------------------------------------------------
    def _on_imu(self, msg: ImuSample) -> bool:
        t, dt = msg.t, msg.dt_s
        if self.last_imu_t is not None:
            if t == self.last_imu_t:
                return self._reject("duplicate")
            if t < self.last_imu_t:
                return self._reject("time_backwards")
            span = t - self.last_imu_t
            if span - dt > self.config.intake.max_imu_gap_s:
                self._imu_gap(t)
                return True
        if not self.initialised:
            self._align_accumulate(msg)
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
        self._align = _Align()
        for p in self.pipelines:
            p.status = "ins_only"

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
            p.initialise(nav, std)
            if self._lost:
                p.status = "reinitialised"
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
        rpy = earth.rpy_from_msg_deg(msg.rpy_deg)
        nav = NavState(
            t=msg.t,
            lat_rad=math.radians(msg.lat_deg),
            lon_rad=math.radians(msg.lon_deg),
            h_m=msg.height_m,
            vel_enu_mps=np.array(msg.vel_enu_mps, dtype=float),
            q_nb=earth.mat_to_quat(earth.rpy_to_mat_nb(rpy)),
        )
        rs = np.radians(msg.rpy_std_deg)
        std = InitStd(
            np.array(msg.pos_std_enu_m), np.array(msg.vel_std_enu_mps), np.array([rs[1], rs[0], rs[2]])
        )
        if self.initialised:
            for p in self.pipelines:
                p.reinitialisations += 1
        self._start(nav, std)

    def _align_accumulate(self, msg: ImuSample) -> None:
        a = self._align
        if a.t_start is None:
            a.t_start = msg.t - msg.dt_s
        w = np.asarray(msg.dtheta_rad) / msg.dt_s
        f = np.asarray(msg.dvel_mps) / msg.dt_s
        a.n += 1
        a.sum_w += w
        a.sum_f += f
        a.sum_f2 += f * f

    def _try_initialise_from_aiding(self) -> None:
        mode = self.config.init.mode
        if self.initialised or mode == "message" or self.last_imu_t is None:
            return
        fix = self._last_fix
        if fix is None or abs(fix.t - self.last_imu_t) > 1.0:
            return
        a = self._align
        speed = float(np.linalg.norm(fix.vel_enu_mps))
        if mode in ("auto", "gnss_motion") and speed >= self.config.init.min_speed_mps:
            ve, vn, vu = fix.vel_enu_mps
            heading = math.degrees(math.atan2(ve, vn))
            pitch = math.atan2(vu, math.hypot(ve, vn))
            rpy = np.array([0.0, pitch, earth.yaw_from_heading_deg(heading)])
            std = InitStd(
                np.array(fix.pos_std_enu_m), np.array(fix.vel_std_enu_mps), np.radians([2.0, 2.0, 5.0])
            )
            self._start(self._nav_at_fix(fix, rpy), std)
            return
        if (
            mode in ("auto", "static")
            and a.n > 0
            and a.t_start is not None
            and self.last_imu_t - a.t_start >= self.config.init.align_time_s
            and speed < 0.5
        ):
            f = a.sum_f / a.n
            var_f = np.maximum(a.sum_f2 / a.n - f * f, 0.0)
            if float(np.sqrt(var_f.sum())) > 0.5:  # not static: wait for motion initialisation
                return
            w = a.sum_w / a.n
            g = float(np.linalg.norm(f))
            pitch = math.asin(max(-1.0, min(1.0, f[1] / g)))
            roll = math.atan2(-f[0], f[2])
            c_lev = earth.rpy_to_mat_nb(np.array([roll, pitch, 0.0]))
            w_l = c_lev @ w
            yaw = math.atan2(w_l[0], w_l[1])
            sg, sa = self.config.imu.bias_sigmas()
            lat = math.radians(fix.lat_deg)
            att_std = np.array(
                [
                    max(sa / g, 1e-4),
                    max(sa / g, 1e-4),
                    max(sg / (earth.OMEGA_IE_RPS * math.cos(lat)), math.radians(0.5)),
                ]
            )
            std = InitStd(np.array(fix.pos_std_enu_m), np.array([0.05, 0.05, 0.05]), att_std)
            nav = self._nav_at_fix(fix, np.array([roll, pitch, yaw]))
            nav.vel_enu_mps = np.zeros(3)
            self._start(nav, std)

    def _nav_at_fix(self, fix: GnssFix, rpy: np.ndarray) -> NavState:
        """State at the INS time from a fix, carried back/forward with the fix's velocity."""
        vel = np.array(fix.vel_enu_mps, dtype=float)
        llh = np.array([math.radians(fix.lat_deg), math.radians(fix.lon_deg), fix.height_m])
        dllh = earth.enu_m_to_llh_delta(vel * (self.last_imu_t - fix.t), llh[0], llh[2])
        return NavState(
            t=self.last_imu_t,
            lat_rad=float(llh[0] + dllh[0]),
            lon_rad=float(llh[1] + dllh[1]),
            h_m=float(llh[2] + dllh[2]),
            vel_enu_mps=vel,
            q_nb=earth.mat_to_quat(earth.rpy_to_mat_nb(rpy)),
        )

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
