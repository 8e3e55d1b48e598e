"""Rerun sink: the only module of ``service/`` that calls the Rerun SDK (``rr.*``).

The service hands plain wire messages (``service.messages``) to a :class:`RerunSink`; the sink
records them to an ``.rrd`` file and/or streams them to a live viewer, under the entity paths of
``service.transport.rerun_paths`` on three timelines: ``sensor_time`` (duration, ``t`` in seconds
of GPS time, stored in nanoseconds), ``mission_time`` (duration since the first message of the
recording) and ``utc`` (timestamp: GPS time converted to UTC with leap seconds).

Efficiency: rows are accumulated per entity in memory and sent column-wise with
``RecordingStream.send_columns`` when ``flush_interval_s`` of wall time has passed since the last
send or ``max_buffered_rows`` rows are waiting, and on :meth:`RerunSink.flush` / :meth:`RerunSink.close`.
Each send makes one Rerun chunk per entity, and a chunk costs ~1.1 kB of file and ~0.1 ms of CPU
whatever its row count. Measured with 3 pipelines at 10 Hz (federated with 3 subsystems, integrity
with 10 satellites: ~235 entities) in real time: 1 s flushes -> ~1 GB/h of file, ~3.5 % of a core;
5 s flushes -> ~270 MB/h, ~1 %. The default is 1 s, file or viewer: what sits in memory is what a
crash (kill -9, power loss) loses, so a background thread also sends rows older than the interval
when no logging call comes, and each periodic send starts an SDK flush to the file. Measured by
tests/test_crash_recording.py (demo, real time, kill -9): the last ~1 s of solutions lost (5 s
before). The price is chunk count, five times that of 5 s flushes: file size (demo, one pipeline:
~1.2 MB per 16 s at 1 s, ~0.5 MB at 5 s) and, with ``write_footer``, the footer's per-chunk
metadata held in memory until close (~210 B per chunk measured: 400,000 chunks of 200 entities ->
+154 MB RSS with the footer, +71 MB without; ~180 MB/h for the ~235-entity case above at 1 s).
The service's ``rrd_flush_interval_s`` (default 1 s) sets the trade: 5 s for long runs that
may lose 5 s. ``optimize_rrd`` (``rerun rrd
optimize``) compacts a finished file ~10x (``optimize_on_close=True`` runs it in
:meth:`RerunSink.close`, ~5 s per 10 min of such a recording). A file cut by a crash has no footer
(``rerun rrd verify`` rejects it; Rerun's reader and viewer read it by scanning):
``rerun rrd merge --continue-on-error cut.rrd -o fixed.rrd`` rewrites it complete.

Threading: the logging calls come from one worker thread; :meth:`close` may come from another
(signal handling). A re-entrant lock guards the buffers, so ``close()`` sends every row that was
accepted before it and nothing is lost on SIGTERM. After ``close()`` the logging calls are no-ops.

Rerun's own failures (viewer unreachable, disk full) are logged, never raised into the service.
Bad arguments from the caller (unknown error names, reserved pipeline names) raise ``ValueError``.

Pinned to rerun-sdk 0.41 (its API changes between minor versions).
"""

from __future__ import annotations

import logging
import math
import os
import subprocess
import sys
import threading
import time
import uuid
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import rerun as rr

from fednav.service import earth
from fednav.service.messages import Faults, GnssFix, Health, ImmModels, Integrity, Solution, Truth
from fednav.service.transport import rerun_paths as paths

log = logging.getLogger(__name__)
#: vehicles that get tabs of their own in the embedded blueprint (a fleet's others are recorded
#: too, and reachable in the viewer's entity tree; fednav-fleet record gives the fleet's view)
BLUEPRINT_VEHICLES = 8
#: wall seconds between two blueprints sent for new vehicles (the last one is sent at close)
BLUEPRINT_INTERVAL_S = 10.0

#: A blueprint object, or a callable that builds one from the vehicles recorded so far.
BlueprintSource = Any | Callable[[Sequence[str]], Any]

# RGBA (0xRRGGBBAA): tab10 palette for pipelines, black for truth.
_PALETTE = (
    0x1F77B4FF,
    0xFF7F0EFF,
    0x2CA02CFF,
    0xD62728FF,
    0x9467BDFF,
    0x8C564BFF,
    0xE377C2FF,
    0x7F7F7FFF,
    0xBCBD22FF,
    0x17BECFFF,
)
_TRUTH_COLOR = 0x000000FF
_REGION_COLOR = {
    "normal": 0x2CA02CFF,
    "mi": 0xFFBF00FF,
    "hmi": 0xD62728FF,
    "alarm": 0x1F77B4FF,
    "unavailable": 0x7F7F7FFF,
    "unavailable_mi": 0x9467BDFF,
}
#: Colours of every state lane (StateConfiguration): the same meaning in every panel. Neutral for
#: "working as intended", amber for "watch", red for "isolated / failed / alarm".
_NEUTRAL, _AMBER, _RED, _GREY = 0xB8C4D0FF, 0xFFBF00FF, 0xD62728FF, 0x7F7F7FFF
STATE_COLORS = {
    "ok": _NEUTRAL,
    "in use": _NEUTRAL,
    "aided": _NEUTRAL,
    "available": _NEUTRAL,
    "no alarm": _NEUTRAL,
    "flagged": _AMBER,
    "degraded": _AMBER,
    "coasting": _AMBER,
    "unaided": _AMBER,
    "initialising": _GREY,
    "detection": _AMBER,
    "isolated": _RED,
    "failed": _RED,
    "alarm": _RED,
    "unavailable": _GREY,
}
_STATUS_LEVEL = {"failed": "ERROR", "coasting": "WARN", "degraded": "WARN", "unaided": "WARN"}


def seconds_to_ns(t_s: float) -> int:
    """Sensor time in seconds (float64 GPS seconds) -> integer nanoseconds, without float overflow.

    Splits whole and fractional seconds so the fraction is rounded at nanosecond resolution.
    """
    whole = math.floor(t_s)
    return int(whole) * 1_000_000_000 + round((t_s - whole) * 1e9)


_GPS_EPOCH_UNIX_NS = paths.GPS_EPOCH_UNIX_S * 1_000_000_000
#: GPS nanoseconds at which each leap second takes effect (offset = number of entries passed).
_LEAP_STARTS_NS = np.array([seconds_to_ns(t) for t, _ in paths.LEAP_SECONDS], dtype=np.int64)


def time_columns(t_ns: np.ndarray, t0_ns: int) -> list[rr.TimeColumn]:
    """The three timelines of rows stamped ``t_ns`` (GPS nanoseconds): sensor time, mission time
    (since ``t0_ns``) and UTC (``rerun_paths.gps_to_utc_ns``, vectorised)."""
    t_ns = np.asarray(t_ns, dtype=np.int64)
    leap_ns = np.searchsorted(_LEAP_STARTS_NS, t_ns, side="right").astype(np.int64) * 1_000_000_000
    utc_ns = t_ns + _GPS_EPOCH_UNIX_NS - leap_ns
    return [
        rr.TimeColumn(paths.TIMELINE, duration=t_ns.astype("timedelta64[ns]")),
        rr.TimeColumn(paths.MISSION_TIMELINE, duration=(t_ns - t0_ns).astype("timedelta64[ns]")),
        rr.TimeColumn(paths.UTC_TIMELINE, timestamp=utc_ns.astype("datetime64[ns]")),
    ]


@dataclass
class _Series:
    """Rows waiting to be sent for one entity: ``kind`` selects the archetype."""

    kind: str  # scalar | multi | geo | state | text | point2d | xy | strip | marker
    rows: list[tuple[int, Any]] = field(default_factory=list)  # (t_ns, value); append is atomic
    slow: bool = False  # a diagnostic stream sent every ``slow_flush_interval_s``
    since: float = 0.0  # sink clock when its oldest waiting row came


@dataclass
class _Track:
    """Decimated (lat, lon) history of one source, logged as GeoLineStrings now and then."""

    path: str
    points: list[tuple[float, float]] = field(default_factory=list)
    last_kept_t: float = -math.inf
    min_dt_s: float = 1.0
    last_logged_t: float = -math.inf
    head: tuple[float, float] | None = None
    head_t: float = 0.0


def _columns(kind: str, values: list[Any]):
    """Column bundle of one entity's buffered rows (one instance per row, multi: k per row)."""
    if kind == "scalar" or kind == "multi":
        return rr.Scalars.columns(scalars=np.asarray(values, dtype=np.float64))
    if kind == "geo":
        return rr.GeoPoints.columns(positions=np.asarray(values, dtype=np.float64))
    if kind == "state":
        return rr.StateChange.columns(state=list(values))
    if kind == "text":
        texts, levels = zip(*values, strict=True)
        return rr.TextLog.columns(text=list(texts), level=list(levels))
    if kind == "point2d":
        pos, colors = zip(*values, strict=True)
        return rr.Points2D.columns(
            positions=np.asarray(pos, dtype=np.float64), colors=np.asarray(colors, dtype=np.uint32)
        )
    if kind == "xy":  # one 2-D point per row, style (colour, radius) logged static
        return rr.Points2D.columns(positions=np.asarray(values, dtype=np.float64))
    if kind == "strip":  # one closed line strip (an ellipse) per row
        return rr.LineStrips2D.columns(strips=[np.asarray(v, dtype=np.float64) for v in values])
    if kind == "marker":  # one labelled point per row
        pos, labels, colors = zip(*values, strict=True)
        return rr.Points2D.columns(
            positions=np.asarray(pos, dtype=np.float64),
            labels=list(labels),
            colors=np.asarray(colors, dtype=np.uint32),
        )
    raise ValueError(f"unknown series kind {kind!r}")


class RerunSink:
    """Record fednav outputs to an ``.rrd`` file and/or a live Rerun viewer.

    Parameters
    ----------
    rrd_path
        File to write (overwritten; parent folders are created). None: no file.
    application_id
        Rerun application id; blueprints apply to recordings of the same id.
    recording_id
        Rerun recording id; a fresh UUID when None.
    viewer_addr
        Rerun gRPC URL of a running viewer for live streaming in addition to the file, e.g.
        ``rerun+http://127.0.0.1:9876/proxy``. None: no live stream.
    blueprint
        A Rerun blueprint object (sent once, embedded in the file), or a callable
        ``f(vehicles: list[str]) -> blueprint`` called again whenever a new vehicle first appears
        (``dashboards.blueprints.blueprint_factory`` builds one). The sink never imports dashboards.
    recording_name
        Optional human-readable recording name shown by the viewer.
    flush_interval_s, max_buffered_rows
        Send buffered rows when this much wall time has passed since the last send, or when this
        many rows are waiting (None: 1 s). Bounds what a crash loses (see the module docstring).
    track_interval_s, max_track_points
        Sensor-time interval between logs of the decimated map tracks, and their size limit.
    write_footer
        Write the RRD footer (chunk manifest) at close; keeps per-chunk metadata in memory.
    optimize_on_close
        Compact the file with :func:`optimize_rrd` at the end of :meth:`close` (slower shutdown).
    flush_timeout_s
        Longest wait for the SDK to write out data in :meth:`flush` / :meth:`close`.
    clock
        Wall clock for the flush cadence (monotonic seconds); injectable for tests.
    background_flush
        Run the thread that sends rows older than ``flush_interval_s`` without a logging call.
    decimation
        Per diagnostic stream, the shortest sensor-time interval (s) between recorded rows
        (``service.config.RRD_DECIMATION_DEFAULTS`` names the streams; absent or 0: every row).
        Fault statistics, sharing coefficients and per-satellite statistics keep every row while
        a test flags or isolates something; state changes are always recorded.
    slow_flush_interval_s
        Diagnostic streams (fault tests, sharing coefficients, per-satellite statistics, 1-sigma,
        health: ``rerun_paths.is_slow_stream``) are sent this often instead of every
        ``flush_interval_s`` (None: same as ``flush_interval_s``). Each send is one chunk per entity,
        so this divides their chunk count (file size) by the ratio; what a crash loses of them
        grows to this interval.

    With neither ``rrd_path`` nor ``viewer_addr`` the sink is disabled: every call is a cheap no-op.
    """

    def __init__(
        self,
        rrd_path: str | Path | None,
        application_id: str = "fednav",
        recording_id: str | None = None,
        viewer_addr: str | None = None,
        blueprint: BlueprintSource | None = None,
        *,
        recording_name: str | None = None,
        flush_interval_s: float | None = None,
        max_buffered_rows: int = 50_000,
        track_interval_s: float = 10.0,
        max_track_points: int = 2000,
        write_footer: bool = True,
        optimize_on_close: bool = False,
        flush_timeout_s: float = 5.0,
        clock: Callable[[], float] = time.monotonic,
        background_flush: bool = True,
        decimation: Mapping[str, float] | None = None,
        slow_flush_interval_s: float | None = None,
    ) -> None:
        if flush_interval_s is None:
            flush_interval_s = 1.0
        if flush_interval_s < 0 or max_buffered_rows < 1 or track_interval_s <= 0 or max_track_points < 2:
            raise ValueError(
                "flush_interval_s >= 0, max_buffered_rows >= 1, track_interval_s > 0, "
                "max_track_points >= 2 required"
            )
        self.rrd_path = None if rrd_path is None else Path(rrd_path)
        self.viewer_addr = viewer_addr
        self.application_id = application_id
        self.recording_id = recording_id or str(uuid.uuid4())
        self.enabled = self.rrd_path is not None or viewer_addr is not None
        self._flush_interval_s = flush_interval_s
        self._slow_interval_s = max(flush_interval_s, slow_flush_interval_s or 0.0)
        self._max_rows = max_buffered_rows
        self._track_interval_s = track_interval_s
        self._max_track_points = max_track_points
        self._flush_timeout_s = flush_timeout_s
        self._optimize_on_close = optimize_on_close
        self._clock = clock
        self._lock = threading.RLock()
        self._send_lock = threading.Lock()  # one send at a time, in the order the rows were taken
        self._flush_wake: threading.Event | None = None  # set when a background flusher runs
        self._flush_everything = False
        self._closed = not self.enabled
        self._series: dict[str, _Series] = {}
        self._rows = 0
        self._last_flush = clock()
        self._styled: set[str] = set()
        self._tracks: dict[str, _Track] = {}
        self._status: dict[tuple[str, str], str] = {}
        self._truth_faults: dict[str, str] = {}
        self._integ_prev: dict[tuple[str, str], tuple[bool, bool, bool, frozenset[str]]] = {}
        self._frames: dict[str, tuple[float, float]] = {}
        self._colors: dict[tuple[str, str], int] = {}
        self._last_t: dict[str, float] = {}
        self._t0_ns: int | None = None
        self._decimation = {k: float(v) for k, v in (decimation or {}).items() if v and v > 0}
        self._last_kept: dict[tuple[str, str, str], float] = {}
        self._enu_ref: dict[str, tuple[float, float, float]] = {}  # vehicle -> (lat_rad, lon_rad, h_m)
        self._enu_last: dict[tuple[str, str], tuple[float, float]] = {}  # (vehicle, source) -> (e, n)
        self._state_last: dict[str, str] = {}
        #: (vehicle, pipeline, sensor) -> the innovation window being accumulated (log_innovations)
        self._innov: dict[tuple[str, str, str], dict] = {}
        self._marker_last: dict[tuple[str, str], int] = {}
        self._vehicles: list[str] = []
        self._bp_more = 0  # vehicles beyond BLUEPRINT_VEHICLES (recorded, without tabs of their own)
        self._bp_pending = False  # a new vehicle's blueprint waits for BLUEPRINT_INTERVAL_S
        self._bp_sent_at = -math.inf
        # A Rerun blueprint (Blueprint, Container or View) has to_blueprint(); anything else callable
        # is a factory of the vehicles seen so far.
        self._bp_object = blueprint if hasattr(blueprint, "to_blueprint") else None
        self._bp_factory = blueprint if self._bp_object is None and callable(blueprint) else None
        if blueprint is not None and self._bp_object is None and self._bp_factory is None:
            raise ValueError("blueprint must be a rerun blueprint or a callable(vehicles) -> blueprint")
        self._rec: rr.RecordingStream | None = None
        if not self.enabled:
            return

        self._rec = rr.RecordingStream(application_id, recording_id=self.recording_id)
        sinks: list[Any] = []
        if self.rrd_path is not None:
            self.rrd_path.parent.mkdir(parents=True, exist_ok=True)
            sinks.append(rr.FileSink(str(self.rrd_path), write_footer=write_footer))
        if viewer_addr is not None:
            sinks.append(rr.GrpcSink(viewer_addr))
        self._rec.set_sinks(*sinks)
        self._stop_flusher = threading.Event()
        if background_flush and flush_interval_s > 0:
            self._flush_wake = threading.Event()
            threading.Thread(target=self._flusher, name="fednav-rerun-flush", daemon=True).start()
        if recording_name:
            self._rec.send_recording_name(recording_name)
        if self._bp_object is not None:
            self.send_blueprint(self._bp_object)

    # --- public API ---------------------------------------------------------------------------------
    def send_blueprint(self, blueprint: Any) -> None:
        """Send (and embed) a blueprint, making it the active and default one of the application."""
        with self._lock:
            if self._closed or self._rec is None:
                return
            try:
                self._rec.send_blueprint(blueprint, make_active=True, make_default=True)
            except Exception as exc:  # a bad blueprint must not stop the recording
                log.warning("rerun sink: could not send blueprint: %s", exc)

    def log_solution(self, vehicle: str, sol: Solution) -> None:
        """Navigation solution of one pipeline: map point, scalars, 1-sigma, biases, status."""
        if self._closed:
            return
        p = sol.pipeline
        with self._lock:
            if self._closed:
                return
            tn = self._time(vehicle, sol.t)
            key = (vehicle, p)
            if self._status.get(key) != sol.status:
                self._status[key] = sol.status
                self._add(paths.solution(vehicle, p, "status"), "state", tn, sol.status)
            self._track(
                paths.solution(vehicle, p, "track"), sol.t, sol.lat_deg, sol.lon_deg, self._color(vehicle, p)
            )
            en = self._enu(vehicle, p, sol.lat_deg, sol.lon_deg, sol.height_m)
            if self._due("ellipses", vehicle, p, sol.t):
                self._ellipse(vehicle, p, tn, en, sol.pos_std_enu_m[0], sol.pos_std_enu_m[1])
            if not self._due("navigation", vehicle, p, sol.t):
                self._maybe_flush()
                return
            self._xy(paths.enu(vehicle, p), tn, en, self._color(vehicle, p), 1.5)
            self._geo(
                paths.solution(vehicle, p, "position"), tn, sol.lat_deg, sol.lon_deg, self._color(vehicle, p)
            )
            self._state_scalars(
                lambda n: paths.solution(vehicle, p, n),
                tn,
                sol.lat_deg,
                sol.lon_deg,
                sol.height_m,
                sol.vel_enu_mps,
                sol.rpy_deg,
            )
            if not self._due("std", vehicle, p, sol.t):
                self._maybe_flush()
                return
            std = (*sol.pos_std_enu_m, *sol.vel_std_enu_mps, *sol.rpy_std_deg)
            for name, v in zip(paths.STD_SCALARS, std, strict=True):
                path = paths.solution_std(vehicle, p, name)
                self._style_series(path, [f"{p} {paths.STD_LABELS[name]}"], [self._color(vehicle, p)])
                self._add(path, "scalar", tn, v)
            for leaf, bias in (("gyro_bias_dph", sol.gyro_bias_dph), ("accel_bias_ug", sol.accel_bias_ug)):
                path = paths.solution(vehicle, p, leaf)
                if any(bias) or path in self._styled:
                    self._style_series(path, [f"{p} {a}" for a in paths.BIAS_SERIES])
                    self._add(path, "multi", tn, tuple(bias))
            self._maybe_flush()

    def log_truth(self, vehicle: str, truth: Truth) -> None:
        """Simulator truth: map point, scalars, and the active injected faults (on change)."""
        if self._closed:
            return
        with self._lock:
            if self._closed:
                return
            tn = self._time(vehicle, truth.t)
            en = self._enu(vehicle, paths.TRUTH, truth.lat_deg, truth.lon_deg, truth.height_m)
            desc = "; ".join(f"{f.sensor} {f.kind} [{','.join(f.channels)}]" for f in truth.faults)
            desc = desc or "no active faults"
            before = self._truth_faults.get(vehicle)  # None: this vehicle's first truth
            changed = before != desc
            if changed:  # the first state too, so the log says "no active faults" from the start
                self._truth_faults[vehicle] = desc
                level = "WARN" if truth.faults else "INFO"
                self._add(paths.truth(vehicle, "faults"), "text", tn, (desc, level))
                if truth.faults or before is not None:
                    label = f"fault: {desc}" if truth.faults else "faults end"
                    self._marker(paths.enu_markers(vehicle, paths.TRUTH), tn, en, label, _AMBER)
            self._track(paths.truth(vehicle, "track"), truth.t, truth.lat_deg, truth.lon_deg, _TRUTH_COLOR)
            if not self._due("navigation", vehicle, paths.TRUTH, truth.t, force=changed):
                self._maybe_flush()
                return
            self._xy(paths.enu(vehicle, paths.TRUTH), tn, en, _TRUTH_COLOR, 1.0)
            self._geo(paths.truth(vehicle, "position"), tn, truth.lat_deg, truth.lon_deg, _TRUTH_COLOR)
            self._state_scalars(
                lambda n: paths.truth(vehicle, n),
                tn,
                truth.lat_deg,
                truth.lon_deg,
                truth.height_m,
                truth.vel_enu_mps,
                truth.rpy_deg,
            )
            n_ch = float(sum(len(f.channels) for f in truth.faults))
            self._add(paths.truth(vehicle, "fault_channels"), "scalar", tn, n_ch)
            self._maybe_flush()

    def log_fix(self, vehicle: str, sensor_id: str, fix: GnssFix) -> None:
        """A raw GNSS position fix (service input) on the ENU trajectory view (decimated as
        ``navigation``)."""
        if self._closed:
            return
        with self._lock:
            if self._closed:
                return
            tn = self._time(vehicle, fix.t)
            if not self._due("navigation", vehicle, f"fix/{sensor_id}", fix.t):
                return
            en = self._enu(vehicle, f"fix/{sensor_id}", fix.lat_deg, fix.lon_deg, fix.height_m)
            self._xy(paths.input_fix(vehicle, sensor_id), tn, en, 0x9E9E9E99, 1.0)
            self._maybe_flush()

    def log_errors(
        self,
        vehicle: str,
        pipeline: str,
        t: float,
        errors: Mapping[str, float],
        bounds: Mapping[str, float] | None = None,
    ) -> None:
        """Errors of a solution against truth and their 3-sigma covariance bounds.

        Parameters
        ----------
        errors
            Solution minus truth, keys from ``rerun_paths.ERROR_NAMES`` (east_m, north_m, up_m,
            ve_mps, vn_mps, vu_mps, phi_e_arcsec, phi_n_arcsec, phi_u_arcsec); any subset.
        bounds
            Positive 3-sigma bounds with the same keys; recorded as two series (+3σ, -3σ).
            Non-finite values are skipped.
        """
        if self._closed:
            return
        bounds = bounds or {}
        unknown = (set(errors) | set(bounds)) - set(paths.ERROR_NAMES)
        if unknown:
            raise ValueError(f"unknown error names {sorted(unknown)}; expected {paths.ERROR_NAMES}")
        with self._lock:
            if self._closed:
                return
            tn = self._time(vehicle, t)
            if not self._due("errors", vehicle, pipeline, t):
                return
            color = self._color(vehicle, pipeline)
            for name, v in errors.items():
                if math.isfinite(v):
                    path = paths.error(vehicle, pipeline, name)
                    self._style_series(path, [pipeline], [color])
                    self._add(path, "scalar", tn, float(v))
            for name, b in bounds.items():
                if math.isfinite(b):
                    path = paths.bound(vehicle, pipeline, name)
                    faint = (color & 0xFFFFFF00) | 0x80
                    self._style_series(path, [f"{pipeline} {s}" for s in paths.BOUND_SERIES], [faint, faint])
                    self._add(path, "multi", tn, (abs(float(b)), -abs(float(b))))
            self._maybe_flush()

    def log_faults(self, vehicle: str, faults: Faults) -> None:
        """Per-observation fault tests (statistic, threshold, flag) and sharing coefficients."""
        if self._closed:
            return
        p = faults.pipeline
        with self._lock:
            if self._closed:
                return
            tn = self._time(vehicle, faults.t)
            busy = any(
                sub.isolated or any(o.flagged or o.isolated for o in sub.observations)
                for sub in faults.subsystems
            )
            iso = frozenset(s.name for s in faults.subsystems if s.isolated)
            key = (vehicle, p, "isolated")
            prev = self._integ_prev.get(key, frozenset())
            self._integ_prev[key] = iso
            changed = iso != prev or bool(faults.reconfiguration)
            if iso - prev:
                at = self._enu_last.get((vehicle, p))
                if at is not None:
                    label = f"{p}: isolated {','.join(sorted(iso - prev))}"
                    self._marker(paths.enu_markers(vehicle, p), tn, at, label, _RED)
            # decimated per set of subsystems: subsystems reported in separate messages (different
            # rates) each keep their rows
            subs = p + "|" + ",".join(sub.name for sub in faults.subsystems)
            flags = tuple(
                (sub.isolated, tuple((o.flagged, o.isolated) for o in sub.observations))
                for sub in faults.subsystems
            )
            fkey = (vehicle, subs, "flags")
            flags_changed = self._integ_prev.get(fkey) != flags  # a flag clearing is kept too
            self._integ_prev[fkey] = flags
            keep_faults = self._due("faults", vehicle, subs, faults.t, force=busy or changed or flags_changed)
            keep_sharing = self._due("sharing", vehicle, p, faults.t, force=busy or changed)
            for sub in faults.subsystems:  # isolation lanes: every change, never decimated
                state = "isolated" if sub.isolated else "in use"
                path = paths.isolation(vehicle, p, sub.name)
                if self._state_last.get(path) != state:
                    self._state_last[path] = state
                    self._add(path, "state", tn, state)
            for sub in faults.subsystems if keep_faults else ():
                self._add(
                    paths.faults(vehicle, p, sub.name, "subsystem_isolated"),
                    "state",
                    tn,
                    "isolated" if sub.isolated else "in use",
                )
                for obs in sub.observations:
                    self._add(
                        paths.faults(vehicle, p, sub.name, obs.label, "statistic"),
                        "scalar",
                        tn,
                        obs.statistic,
                    )
                    self._add(
                        paths.faults(vehicle, p, sub.name, obs.label, "threshold"),
                        "scalar",
                        tn,
                        obs.threshold,
                    )
                    if obs.threshold > 0 and math.isfinite(obs.statistic):
                        path = paths.fault_test(vehicle, p, sub.name, obs.label)
                        self._style_series(path, [f"{sub.name}/{obs.label}"])
                        self._add(path, "scalar", tn, obs.statistic / obs.threshold)
                    state = "isolated" if obs.isolated else ("flagged" if obs.flagged else "ok")
                    self._add(paths.faults(vehicle, p, sub.name, obs.label, "flagged"), "state", tn, state)
            for local, coeffs in faults.sharing.items() if keep_sharing else ():
                for i, c in enumerate(coeffs):
                    path = paths.sharing(vehicle, p, local, i)
                    self._style_series(path, [f"{local} {paths.state_name(i, len(coeffs))}"])
                    self._add(path, "scalar", tn, c)
            for ev in faults.reconfiguration:  # seed 004: a local leaving or rejoining the fusion
                stat = f"statistic {ev.statistic:.1f}, threshold {ev.threshold:.1f}"
                text = f"{ev.action}: {ev.subsystem} ({stat})"
                self._add(
                    paths.reconfiguration(vehicle, p),
                    "text",
                    tn,
                    (text, "WARN" if ev.action == "excluded" else "INFO"),
                )
            for st in faults.states:
                self._add(paths.filter_state(vehicle, p, st.name, "value"), "scalar", tn, st.value)
                self._add(paths.filter_state(vehicle, p, st.name, "std"), "scalar", tn, st.std)
            self._maybe_flush()

    def log_innovations(
        self,
        vehicle: str,
        pipeline: str,
        t: float,
        sensor: str,
        labels: Sequence[str],
        standardised: Sequence[float],
        used: Sequence[bool] | None = None,
    ) -> None:
        """One aiding epoch's standardised innovations r_j = nu_j / sqrt(S_jj) of a pipeline's
        sensor stream (``sensor``: ``kind/sensor_id``; the prior innovation per row and the diagonal
        of its covariance S = H P- H' + R, private states such as the correlated receiver error
        included), ``used``: the rows the update used (the gate's refusals are counted apart).

        Cheap by construction (a fleet records many vehicles): the rows are accumulated per row
        label and recorded as windows, at most one per ``faults`` decimation interval (every epoch
        when not decimated): the mean of r^2 over the window's used rows and their count (two
        scalars per row label) and the rows refused in it. ``fednav-inspect`` pools the windows into
        the NIS per row against chi-square(1) (dashboards/inspect.py)."""
        if self._closed:
            return
        r = np.asarray(standardised, dtype=float)
        ok = np.isfinite(r) if used is None else np.isfinite(r) & np.asarray(used, dtype=bool)
        with self._lock:
            if self._closed:
                return
            key = (vehicle, pipeline, sensor)
            acc = self._innov.get(key)
            if acc is None:
                acc = self._innov[key] = {"rows": {}, "refused": 0, "t": t}
            rows = acc["rows"]
            for lab, x, good in zip(labels, r.tolist(), ok.tolist(), strict=True):
                if good:
                    cell = rows.get(lab)
                    if cell is None:
                        rows[lab] = [x * x, 1]
                    else:
                        cell[0] += x * x
                        cell[1] += 1
            acc["refused"] += int(len(r) - int(ok.sum()))
            acc["t"] = t
            if self._due("faults", vehicle, f"{pipeline}#innovations#{sensor}", t):
                self._innovation_window(key, acc)
            self._maybe_flush()

    def _innovation_window(self, key: tuple[str, str, str], acc: dict) -> None:
        """Record and reset one accumulated innovation window (lock held)."""
        vehicle, pipeline, sensor = key
        if not acc["rows"] and not acc["refused"]:
            return
        tn = self._time(vehicle, acc["t"])
        for lab, (s2, n) in acc["rows"].items():
            self._add(paths.innovations(vehicle, pipeline, sensor, lab, "r2_mean"), "scalar", tn, s2 / n)
            self._add(paths.innovations(vehicle, pipeline, sensor, lab, "count"), "scalar", tn, float(n))
        self._add(
            paths.innovations(vehicle, pipeline, sensor, paths.INNOVATIONS_REFUSED),
            "scalar",
            tn,
            float(acc["refused"]),
        )
        acc["rows"], acc["refused"] = {}, 0

    def log_integrity(
        self, vehicle: str, integ: Integrity, h_error_m: float | None = None, v_error_m: float | None = None
    ) -> None:
        """MHSS integrity: protection levels vs alert limits vs true error, per-satellite tests,
        events (detection, alarm, exclusion, availability) and Stanford-diagram points.

        ``h_error_m`` / ``v_error_m``: true horizontal / vertical position error (truth present).
        """
        if self._closed:
            return
        p = integ.pipeline
        with self._lock:
            if self._closed:
                return
            tn = self._time(vehicle, integ.t)
            values = {
                "hpl_m": integ.hpl_m,
                "vpl_m": integ.vpl_m,
                "hal_m": integ.hal_m,
                "val_m": integ.val_m,
                "alarm": float(integ.alarm),
                "available": float(integ.available),
                "detected": float(integ.detected),
                "h_error_m": h_error_m,
                "v_error_m": v_error_m,
                "excluded_count": float(len(integ.excluded)),
            }
            for name, v in values.items():
                if v is not None and math.isfinite(v):
                    path = paths.integrity(vehicle, p, name)
                    if name in paths.INTEGRITY_LABELS:
                        self._style_series(
                            path, [paths.INTEGRITY_LABELS[name]], [paths.INTEGRITY_COLORS[name]]
                        )
                    self._add(path, "scalar", tn, float(v))
            self._add(
                paths.integrity(vehicle, p, "availability"),
                "state",
                tn,
                "available" if integ.available else "unavailable",
            )
            alarm_state = "alarm" if integ.alarm else ("detection" if integ.detected else "no alarm")
            self._add(paths.integrity(vehicle, p, "alarm_state"), "state", tn, alarm_state)
            if integ.alarm and not self._integ_prev.get((vehicle, p), (False, False))[1]:
                at = self._enu_last.get((vehicle, p))
                if at is not None:
                    self._marker(paths.enu_markers(vehicle, p), tn, at, f"{p}: integrity alarm", _RED)
            busy = integ.detected or integ.alarm or bool(integ.excluded)
            keep_sats = self._due("integrity_sat", vehicle, p, integ.t, force=busy)
            for sat in integ.satellites if keep_sats else ():
                if sat.threshold_m > 0 and math.isfinite(sat.statistic_m):
                    path = paths.integrity_sat_ratio(vehicle, p, sat.id)
                    self._style_series(path, [sat.id])
                    self._add(path, "scalar", tn, sat.statistic_m / sat.threshold_m)
                self._add(
                    paths.integrity_sat(vehicle, p, sat.id, "statistic_m"), "scalar", tn, sat.statistic_m
                )
                self._add(
                    paths.integrity_sat(vehicle, p, sat.id, "threshold_m"), "scalar", tn, sat.threshold_m
                )
                if sat.vertical_statistic_m or sat.vertical_threshold_m:
                    self._add(
                        paths.integrity_sat(vehicle, p, sat.id, "statistic_m", vertical=True),
                        "scalar",
                        tn,
                        sat.vertical_statistic_m,
                    )
                    self._add(
                        paths.integrity_sat(vehicle, p, sat.id, "threshold_m", vertical=True),
                        "scalar",
                        tn,
                        sat.vertical_threshold_m,
                    )
            self._integrity_events(vehicle, p, tn, integ)
            if h_error_m is not None and math.isfinite(h_error_m):
                self._stanford(vehicle, p, "h", tn, h_error_m, integ.hpl_m, integ.hal_m, integ.alarm)
            if v_error_m is not None and math.isfinite(v_error_m) and math.isfinite(integ.vpl_m):
                self._stanford(vehicle, p, "v", tn, v_error_m, integ.vpl_m, integ.val_m, integ.alarm)
            self._maybe_flush()

    def log_health(self, vehicle: str, health: Health) -> None:
        """Service health counters. Stamped with ``health.t``, else the vehicle's latest sensor time;
        skipped when neither exists (nothing processed yet)."""
        if self._closed:
            return
        with self._lock:
            if self._closed:
                return
            t = health.t if health.t is not None else self._last_t.get(vehicle)
            if t is None:
                return
            tn = self._time(vehicle, t)
            values = {
                "queue_depth": health.queue_depth,
                "latency_p50_ms": health.latency_ms.get("p50"),
                "latency_p99_ms": health.latency_ms.get("p99"),
                "received": health.received,
                "accepted": health.accepted,
                "rejected_total": sum(health.rejected.values()),
                "dropped_overload": health.dropped_overload,
            }
            for name, v in values.items():
                if v is not None:
                    self._add(paths.health(vehicle, name), "scalar", tn, float(v))
            for reason, n in health.rejected.items():  # what was refused and why (its total above)
                if n:
                    self._add(paths.health_rejected(vehicle, reason), "scalar", tn, float(n))
            self._maybe_flush()

    def log_event(self, vehicle: str, t: float, text: str, level: str = "INFO") -> None:
        """A service event of a vehicle (e.g. "handed over from <service>"), as a text log row
        under the vehicle's health entity ``events``."""
        if self._closed:
            return
        with self._lock:
            if self._closed:
                return
            self._add(paths.health(vehicle, "events"), "text", self._time(vehicle, t), (text, level))
            self._maybe_flush()

    def forget(self, vehicle: str) -> None:
        """A vehicle the service released (``[intake] vehicle_idle_s``): its buffered rows and its
        tracks' last points are written, then every per-vehicle book is dropped, so that a fleet
        whose names come and go does not grow the sink (an innovation window still accumulating
        is not written). Its time origin, ENU reference and place in the blueprint stay: a vehicle
        that comes back keeps them."""
        if self._closed:
            return
        root = paths.vehicle_root(vehicle) + "/"
        with self._lock:
            if self._closed:
                return
            for path in [p for p in self._tracks if p.startswith(root)]:
                self._send_track(self._tracks.pop(path))
            series = {p: self._series.pop(p) for p in list(self._series) if p.startswith(root)}
            self._rows -= sum(len(s.rows) for s in series.values())
            with self._send_lock:
                self._send(series)
            self._styled = {p for p in self._styled if not p.startswith(root)}
            for d in (self._frames, self._state_last):
                for k in [k for k in d if k.startswith(root)]:
                    del d[k]
            for d in (self._status, self._integ_prev, self._colors, self._enu_last, self._innov):
                for k in [k for k in d if k[0] == vehicle]:
                    del d[k]
            for k in [k for k in self._last_kept if k[1] == vehicle]:
                del self._last_kept[k]
            for k in [k for k in self._marker_last if k[0].startswith(root)]:
                del self._marker_last[k]
            self._truth_faults.pop(vehicle, None)

    def log_imm(self, vehicle: str, msg: ImmModels) -> None:
        """IMM model probabilities (``imm/prob/{model}``), the number of down-weighted rows per
        model (``imm/downweighted/{model}``: R_ii factor above 1) and gate rejections
        (``imm/rejected_rows``)."""
        if self._closed:
            return
        base = paths.group(vehicle, msg.pipeline, "imm")
        with self._lock:
            if self._closed:
                return
            tn = self._time(vehicle, msg.t)
            for i, (m, pr, rs) in enumerate(zip(msg.models, msg.probabilities, msg.r_scale, strict=True)):
                colour = _PALETTE[i % len(_PALETTE)]  # one colour per model, the same in both panels
                prob, down = f"{base}/prob/{paths.part(m)}", f"{base}/downweighted/{paths.part(m)}"
                self._style_series(prob, [m], [colour])
                self._style_series(down, [m], [colour])
                self._add(prob, "scalar", tn, float(pr))
                self._add(down, "scalar", tn, float(sum(r > 1.0 for r in rs)))
            self._add(f"{base}/rejected_rows", "scalar", tn, float(len(msg.rejected)))
            self._maybe_flush()

    def log_scalars(
        self,
        vehicle: str,
        pipeline: str,
        t: float,
        group: str,
        values: Mapping[str, float],
        styles: Mapping[str, tuple[str, int]] | None = None,
    ) -> None:
        """Family-specific scalars at ``/{vehicle}/{pipeline}/{group}/{name}``.

        Groups the blueprints show: ``rerun_paths.GROUPS`` (imm, alignment, underwater).
        ``styles`` (name -> (legend label, RGBA colour)) styles a series once, the first time.
        """
        if self._closed:
            return
        if group in ("solution", "error", "bound", "faults", "sharing", "integrity"):
            raise ValueError(f"group {group!r} is used by the fixed layout")
        with self._lock:
            if self._closed:
                return
            tn = self._time(vehicle, t)
            for name, v in values.items():
                if math.isfinite(v):
                    path = paths.group(vehicle, pipeline, group, name)
                    if styles and name in styles:
                        label, colour = styles[name]
                        self._style_series(path, [label], [colour])
                    self._add(path, "scalar", tn, float(v))
            self._maybe_flush()

    def flush(self) -> None:
        """Send every buffered row and wait (up to ``flush_timeout_s``) until the SDK wrote it."""
        with self._lock:
            if self._closed or self._rec is None:
                return
            self._flush_locked()
            self._sdk_flush()

    def close(self) -> None:
        """Send everything (final map tracks included), flush and disconnect. Idempotent."""
        with self._lock:
            if self._closed or self._rec is None:
                self._closed = True
                return
            try:
                if self._bp_pending:
                    self._send_vehicle_blueprint()
                for track in self._tracks.values():
                    self._send_track(track)
                for key, acc in self._innov.items():  # the last (partial) innovation windows
                    self._innovation_window(key, acc)
                self._flush_locked()
                self._sdk_flush()
            finally:
                self._closed = True
                self._stop_flusher.set()
                if self._flush_wake is not None:
                    self._flush_wake.set()
                try:
                    self._rec.disconnect()
                except Exception as exc:
                    log.warning("rerun sink: disconnect failed: %s", exc)
            if self._optimize_on_close and self.rrd_path is not None:
                try:
                    optimize_rrd(self.rrd_path)
                except (OSError, RuntimeError, subprocess.SubprocessError) as exc:
                    log.warning("rerun sink: %s left as written (not optimized): %s", self.rrd_path, exc)

    @property
    def closed(self) -> bool:
        return self._closed

    def __enter__(self) -> RerunSink:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    # --- internals (lock held) ----------------------------------------------------------------------
    def _time(self, vehicle: str, t: float) -> int:
        if self._t0_ns is None:  # mission time counts from the recording's first message
            self._t0_ns = seconds_to_ns(t)
        if vehicle not in self._last_t:
            self._new_vehicle(vehicle)
        if t > self._last_t.get(vehicle, -math.inf):
            self._last_t[vehicle] = t
        return seconds_to_ns(t)

    def _new_vehicle(self, vehicle: str) -> None:
        self._last_t[vehicle] = -math.inf
        self._vehicles.append(vehicle)
        if self._bp_factory is None:
            return
        if len(self._vehicles) <= BLUEPRINT_VEHICLES:
            # the first at once; later ones at most every BLUEPRINT_INTERVAL_S (and at close):
            # each blueprint is the whole layout again (MBs for a few vehicles)
            if len(self._vehicles) == 1 or self._clock() - self._bp_sent_at >= BLUEPRINT_INTERVAL_S:
                self._send_vehicle_blueprint()
            else:
                self._bp_pending = True
        else:  # a fleet: the per-vehicle tabs stay those of the first vehicles (each blueprint is
            # the whole layout again: one per new vehicle would grow the file with the square of
            # the fleet); the recording still holds every vehicle's entities
            self._bp_more += 1

    def _send_vehicle_blueprint(self) -> None:
        self._bp_pending = False
        self._bp_sent_at = self._clock()
        vehicles = self._vehicles[:BLUEPRINT_VEHICLES]
        try:
            bp = self._bp_factory(list(vehicles))
        except Exception as exc:
            log.warning("rerun sink: blueprint factory failed for %s: %s", vehicles, exc)
            return
        self.send_blueprint(bp)

    def _due(self, stream: str, vehicle: str, pipeline: str, t: float, force: bool = False) -> bool:
        """Decimation: True when a row of ``stream`` at ``t`` is to be recorded (``force``: always)."""
        dt = self._decimation.get(stream)
        if dt is None:
            return True
        key = (stream, vehicle, pipeline)
        if force or t - self._last_kept.get(key, -math.inf) >= dt - 1e-9 or t < self._last_kept.get(key, t):
            self._last_kept[key] = t
            return True
        return False

    def _color(self, vehicle: str, pipeline: str) -> int:
        key = (vehicle, pipeline)
        c = self._colors.get(key)
        if c is None:
            n = sum(1 for v, _ in self._colors if v == vehicle)
            c = self._colors[key] = _PALETTE[n % len(_PALETTE)]
        return c

    def _add(self, path: str, kind: str, t_ns: int, value: Any) -> None:
        if kind == "state" and path not in self._styled:
            self._styled.add(path)
            self._static(
                path,
                rr.StateConfiguration(values=list(STATE_COLORS), colors=list(STATE_COLORS.values())),
            )
        s = self._series.get(path)
        if s is None:
            s = self._series[path] = _Series(kind, slow=paths.is_slow_stream(path))
        if not s.rows:
            s.since = self._clock()
        s.rows.append((t_ns, value))
        self._rows += 1

    def _state_scalars(
        self,
        path_of: Callable[[str], str],
        tn: int,
        lat: float,
        lon: float,
        h: float,
        vel: Sequence[float],
        rpy: Sequence[float],
    ) -> None:
        vals = (lat, lon, h, *vel, *rpy)
        for name, v in zip(paths.SOLUTION_SCALARS, vals, strict=True):
            self._add(path_of(name), "scalar", tn, v)

    def _geo(self, path: str, tn: int, lat: float, lon: float, color: int) -> None:
        if path not in self._styled:
            self._styled.add(path)
            self._static(path, rr.GeoPoints.from_fields(colors=[color], radii=rr.Radius.ui_points(4.0)))
        self._add(path, "geo", tn, (lat, lon))

    def _style_series(self, path: str, names: list[str], colors: list[int] | None = None) -> None:
        if path in self._styled:
            return
        self._styled.add(path)
        self._static(path, rr.SeriesLines.from_fields(names=names, colors=colors))

    def _static(self, path: str, archetype: Any) -> None:
        try:
            self._rec.log(path, archetype, static=True)
        except Exception as exc:
            log.warning("rerun sink: static log to %s failed: %s", path, exc)

    def _track(self, path: str, t: float, lat: float, lon: float, color: int) -> None:
        tr = self._tracks.get(path)
        if tr is None:
            tr = self._tracks[path] = _Track(path)
            self._static(path, rr.GeoLineStrings.from_fields(colors=[color], radii=rr.Radius.ui_points(1.5)))
        tr.head, tr.head_t = (lat, lon), t
        if t - tr.last_kept_t >= tr.min_dt_s:
            tr.points.append((lat, lon))
            tr.last_kept_t = t
            if len(tr.points) > self._max_track_points:
                tr.points = tr.points[::2]  # decimate, and keep half as many points from now on
                tr.min_dt_s *= 2.0
        if t - tr.last_logged_t >= self._track_interval_s:
            self._send_track(tr)

    def _send_track(self, tr: _Track) -> None:
        if tr.head is None:
            return
        line = tr.points if tr.points and tr.points[-1] == tr.head else [*tr.points, tr.head]
        if len(line) < 2:
            return
        tr.last_logged_t = tr.head_t
        t = np.array([seconds_to_ns(tr.head_t)], dtype=np.int64)
        try:
            self._rec.send_columns(
                tr.path,
                indexes=time_columns(t, self._t0_ns),
                columns=rr.GeoLineStrings.columns(line_strings=[np.asarray(line)]),
            )
        except Exception as exc:
            log.warning("rerun sink: track %s not sent: %s", tr.path, exc)

    def _integrity_events(self, vehicle: str, p: str, tn: int, integ: Integrity) -> None:
        key = (vehicle, p)
        excluded = frozenset(integ.excluded)
        prev_det, prev_alarm, prev_avail, prev_excl = self._integ_prev.get(
            key, (False, False, True, frozenset())
        )
        self._integ_prev[key] = (integ.detected, integ.alarm, integ.available, excluded)
        path = paths.integrity_events(vehicle, p)
        if integ.detected and not prev_det:
            self._add(path, "text", tn, (f"detection (phase {integ.phase})", "WARN"))
        if integ.alarm and not prev_alarm:
            self._add(path, "text", tn, (f"alarm: HPL {integ.hpl_m:.2f} m, HAL {integ.hal_m:.2f} m", "ERROR"))
        if integ.available != prev_avail:
            text = "available" if integ.available else f"unavailable: HPL {integ.hpl_m:.2f} m > HAL"
            self._add(path, "text", tn, (text, "INFO" if integ.available else "WARN"))
        if excluded - prev_excl:
            self._add(path, "text", tn, ("exclusion: " + ",".join(sorted(excluded - prev_excl)), "WARN"))
        if prev_excl - excluded:
            self._add(path, "text", tn, ("readmitted: " + ",".join(sorted(prev_excl - excluded)), "INFO"))

    def _stanford(
        self, vehicle: str, p: str, axis: str, tn: int, err: float, pl: float, al: float | None, alarm: bool
    ) -> None:
        # Stanford diagram in a 2D view, both axes log10 of metres so that errors of 1 m and an alert
        # limit of 500 m are both readable: x = log10|error|, y = -log10 PL (2D views point y down,
        # so PL grows upwards); per-epoch points coloured by region. A static frame (decade grid,
        # PL = error diagonal, alert-limit lines, tick and region labels) follows the data's range.
        err = abs(err)
        region = paths.stanford_region(err, pl, al, alarm)
        key = paths.stanford(vehicle, p, f"frame_{axis}")
        lo_prev, hi_prev = self._frames.get(key, (math.inf, -math.inf))
        lo = min(lo_prev, math.floor(math.log10(max(min(err, pl), paths.STANFORD_FLOOR_M))))
        top = max(err, pl, al if al is not None else 0.0)
        hi = max(
            hi_prev, math.ceil(math.log10(max(top, paths.STANFORD_FLOOR_M))) + (1 if al is not None else 0)
        )
        hi = max(hi, lo + 1)
        x, y = paths.stanford_xy(err, pl)
        self._add(paths.stanford(vehicle, p, axis), "point2d", tn, ((x, y), _REGION_COLOR[region]))
        if (lo, hi) != (lo_prev, hi_prev) or al != self._frames.get(key + "#al"):
            self._frames[key] = (lo, hi)
            self._frames[key + "#al"] = al
            name = ("HAL" if axis == "h" else "VAL") if al is not None else None
            strips, colors, labels = paths.stanford_frame(lo, hi, al, name)
            self._static(key, rr.LineStrips2D(strips, colors=np.asarray(colors, dtype=np.uint32)))
            pos, texts, tcolors = labels
            self._static(
                paths.stanford(vehicle, p, f"labels_{axis}"),
                rr.Points2D(
                    pos,
                    labels=texts,
                    colors=np.asarray(tcolors, dtype=np.uint32),
                    radii=rr.Radius.ui_points(0.5),
                    show_labels=True,
                ),
            )

    # --- ENU trajectory view --------------------------------------------------------------------------
    def _enu(
        self, vehicle: str, source: str, lat_deg: float, lon_deg: float, h_m: float
    ) -> tuple[float, float]:
        """(east, north) m from the vehicle's first recorded position (local tangent plane)."""
        ref = self._enu_ref.get(vehicle)
        lat, lon = math.radians(lat_deg), math.radians(lon_deg)
        if ref is None:
            ref = self._enu_ref[vehicle] = (lat, lon, h_m)
        d = earth.llh_delta_to_enu_m(np.array([lat - ref[0], lon - ref[1], h_m - ref[2]]), ref[0], ref[2])
        en = (float(d[0]), float(d[1]))
        self._enu_last[(vehicle, source)] = en
        return en

    def _xy(self, path: str, tn: int, en: tuple[float, float], color: int, radius_ui: float) -> None:
        if path not in self._styled:
            self._styled.add(path)
            self._static(path, rr.Points2D.from_fields(colors=[color], radii=rr.Radius.ui_points(radius_ui)))
        self._add(path, "xy", tn, (en[0], -en[1]))  # 2D views point y down: y = -north

    def _ellipse(
        self, vehicle: str, p: str, tn: int, en: tuple[float, float], sd_e: float, sd_n: float
    ) -> None:
        """3-sigma horizontal ellipse from the solution's east / north 1-sigma (the Solution message
        carries the diagonal, so the ellipse is axis-aligned)."""
        path = paths.enu_ellipse(vehicle, p)
        if path not in self._styled:
            self._styled.add(path)
            faint = (self._color(vehicle, p) & 0xFFFFFF00) | 0x90
            self._static(path, rr.LineStrips2D.from_fields(colors=[faint], radii=rr.Radius.ui_points(0.75)))
        a = np.linspace(0.0, 2.0 * math.pi, 33)
        pts = np.stack([en[0] + 3.0 * sd_e * np.cos(a), -(en[1] + 3.0 * sd_n * np.sin(a))], axis=1)
        self._add(path, "strip", tn, pts)

    def _marker(self, path: str, tn: int, en: tuple[float, float], label: str, color: int) -> None:
        # one marker per label and 30 s at most: an isolation that toggles each epoch is one label
        key = (path, label)
        if tn - self._marker_last.get(key, -(10**20)) < 30_000_000_000:
            return
        self._marker_last[key] = tn
        self._add(path, "marker", tn, ((en[0], -en[1]), label, color))

    def _maybe_flush(self) -> None:
        if self._bp_pending and self._clock() - self._bp_sent_at >= BLUEPRINT_INTERVAL_S:
            self._send_vehicle_blueprint()
        everything = self._rows >= self._max_rows
        if not everything and self._clock() - self._last_flush < self._flush_interval_s:
            return
        if self._flush_wake is not None:
            # a background flusher sends, not the logging thread (the service's intake): a fleet's
            # flush (one chunk per entity: thousands) would hold every vehicle's next message
            self._flush_everything |= everything
            self._flush_wake.set()
            return
        self._flush_locked(everything=everything)
        self._sdk_flush_start()

    def _flusher(self) -> None:
        # Rows wait in memory at most ~flush_interval_s even when no logging call comes (input stopped):
        # what a kill -9 can lose. Woken early by a logging call when a flush is due. The rows are
        # taken under the sink's lock and sent outside it (under the send lock, taken before the
        # sink's lock is released, so that close() sends its rows after these). Ends at close().
        wake = self._flush_wake
        while not self._stop_flusher.is_set():
            wake.wait(self._flush_interval_s / 4)
            wake.clear()
            with self._lock:
                if self._closed:
                    return
                everything, self._flush_everything = self._flush_everything, False
                if not self._rows or (
                    not everything and self._clock() - self._last_flush < self._flush_interval_s
                ):
                    continue
                series = self._take_locked(everything)
                self._send_lock.acquire()
            try:
                self._send(series)
                self._sdk_flush_start()
            finally:
                self._send_lock.release()

    def _sdk_flush_start(self) -> None:
        """Start writing what the SDK holds to the file (not waited for): kill -9 then loses at most
        the rows of the last flush interval, not the SDK's batches."""
        try:
            self._rec.flush(timeout_sec=0.0)
        except Exception as exc:
            log.warning("rerun sink: flush not started: %s", exc)

    def _flush_locked(self, everything: bool = True) -> None:
        """Send the buffered rows: all of them, or (``everything`` False) those of the fast streams
        and of the slow streams whose oldest row waited ``slow_flush_interval_s``."""
        series = self._take_locked(everything)
        with self._send_lock:
            self._send(series)

    def _take_locked(self, everything: bool) -> dict:
        """The rows :meth:`_flush_locked` sends, taken out of the buffer (lock held)."""
        now = self._clock()
        if everything or self._slow_interval_s <= self._flush_interval_s:
            series, self._series = self._series, {}
            self._rows = 0
        else:
            series = {}
            for path, s in list(self._series.items()):
                if s.rows and (not s.slow or now - s.since >= self._slow_interval_s):
                    series[path] = self._series.pop(path)
                    self._rows -= len(s.rows)
        self._last_flush = now
        return series

    def _send(self, series: dict) -> None:
        # the time columns of a row set are made once per flush: a decimated vehicle's entities
        # (14 of them, one row each per flush) share their rows' times, and making the three
        # columns costs about as much as the entity's own values (~100 of ~250 us a call)
        indexes: dict[tuple, list] = {}
        for path, s in series.items():
            rows = s.rows
            if not rows:
                continue
            times = tuple(r[0] for r in rows)
            try:
                idx = indexes.get(times)
                if idx is None:
                    idx = indexes[times] = time_columns(np.array(times, dtype=np.int64), self._t0_ns)
                self._rec.send_columns(path, indexes=idx, columns=_columns(s.kind, [r[1] for r in rows]))
            except Exception as exc:
                log.warning("rerun sink: %d rows for %s not sent: %s", len(rows), path, exc)

    def _sdk_flush(self) -> None:
        try:
            self._rec.flush(timeout_sec=self._flush_timeout_s)
        except Exception as exc:  # e.g. viewer unreachable: the file sink is still written
            log.warning("rerun sink: flush incomplete: %s", exc)


def optimize_rrd(path: str | Path, out: str | Path | None = None, timeout_s: float = 600.0) -> Path:
    """Compact a finished recording (``rerun rrd optimize``): merges the many small chunks of a live
    recording (~10x smaller, faster to open). Writes ``out`` or replaces ``path`` atomically."""
    src = Path(path)
    dst = Path(out) if out is not None else src
    exe = Path(sys.executable).parent / ("rerun.exe" if os.name == "nt" else "rerun")
    cmd = [str(exe)] if exe.is_file() else [sys.executable, "-m", "rerun_cli"]
    tmp = dst.with_name(dst.name + ".optimizing")
    proc = subprocess.run(
        [*cmd, "rrd", "optimize", str(src), "-o", str(tmp)],
        capture_output=True,
        text=True,
        timeout=timeout_s,
        check=False,
    )
    if proc.returncode != 0 or not tmp.is_file():
        tmp.unlink(missing_ok=True)
        raise RuntimeError(f"rerun rrd optimize failed ({proc.returncode}): {proc.stderr.strip()[-500:]}")
    os.replace(tmp, dst)
    return dst
