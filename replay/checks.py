"""Checks of a replay before anything is published, each stated in plain words.

- gravity: in the IMU's first second (when at rest) the mapped specific force must point up
  (+9.8 m/s^2 on fednav's z, body right-forward-up); else the axes or units are named as wrong
  ("IMU z axis reads -9.8 m/s^2 at rest: axes look like FRD, mapping says FLU");
- stamp alignment: streams whose first stamps are more than a minute apart have different
  time bases ("time bases differ: ...");
- monotonic stamps: stamps going backwards or repeating, per stream;
- rates: an empty stream, an IMU below 50 Hz or with gaps the service treats as IMU loss, the
  rate of each stream.
Errors stop the replay (``--force`` publishes anyway); warnings are printed.
"""

from __future__ import annotations

import datetime as dt
import itertools
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from .mapping import GPS_EPOCH_UNIX_S, ReplayMapping, StreamMapping, axes_matrix, axes_name
from .sources import SourceError, stream_events

STATIC_WINDOW_S = 1.0  # the first second of the IMU is tested for rest and gravity
REST_ACCEL_STD_MPS2 = 0.3  # at rest: specific-force scatter below this (phone MEMS noise ~0.05)
REST_RATE_RPS = 0.05  # at rest: mean rotation rate below this (about 3 deg/s)
GRAVITY_RANGE_MPS2 = (9.5, 10.1)  # |g| anywhere on Earth is 9.76-9.84; allow for bias and noise
TIME_BASES_DIFFER_S = 60.0
MIN_IMU_RATE_HZ = 50.0
IMU_GAP_S = 0.5  # the service's default [intake] max_imu_gap_s
COMMON_AXES = ("FLU", "FRD", "RFU")
SKIP_HINTS = {
    "implausible": ": rates or specific forces beyond the wire limits (50 rad/s, 50 g): check gyro_unit "
    "(deg/s data declared rad/s?) and accel_unit",
    "no_velocity": ": no twist within 0.05 s of the fix (published as position-only fixes)",
}


@dataclass
class StreamReport:
    name: str
    kind: str
    count: int = 0
    t_first: float | None = None
    t_last: float | None = None
    rate_hz: float | None = None
    backwards: int = 0
    repeated: int = 0
    gaps: int = 0
    skipped: dict = field(default_factory=dict)

    def as_dict(self) -> dict:
        return dict(self.__dict__)


@dataclass
class Report:
    streams: list[StreamReport] = field(default_factory=list)
    errors: list[str] = field(default_factory=list)
    warnings: list[str] = field(default_factory=list)

    @property
    def total(self) -> int:
        return sum(s.count for s in self.streams)

    def as_dict(self) -> dict:
        return {
            "streams": [s.as_dict() for s in self.streams],
            "errors": self.errors,
            "warnings": self.warnings,
            "messages": self.total,
        }

    def text(self) -> str:
        lines = []
        for s in self.streams:
            span = f"{s.t_last - s.t_first:.1f} s" if s.count else "-"
            rate = f"{s.rate_hz:.1f} Hz" if s.rate_hz else "rate unknown"
            lines.append(f"  {s.name}: {s.count} messages, {span}, {rate}, starts {gps_str(s.t_first)}")
        lines += [f"ERROR: {e}" for e in self.errors]
        lines += [f"warning: {w}" for w in self.warnings]
        lines.append(
            "checks passed" if not self.errors else f"{len(self.errors)} error(s): nothing published"
        )
        return "\n".join(lines)


def gps_str(t: float | None) -> str:
    """GPS seconds as a readable GPS-scale date (no leap seconds applied), for messages."""
    if t is None:
        return "-"
    try:
        when = dt.datetime.fromtimestamp(t + GPS_EPOCH_UNIX_S, dt.UTC)
    except (OverflowError, OSError, ValueError):
        return f"t={t:.3f}"
    return f"{when:%Y-%m-%d %H:%M:%S} GPS (t={t:.3f})"


def suggest_axes(declared: str, axis: int, up: bool) -> str | None:
    """The right-handed three-letter name closest to ``declared`` whose source axis ``axis``
    points up (``up``) or down."""
    want = "U" if up else "D"
    best = None
    for pairs in itertools.permutations(("RL", "FB", "UD")):
        for signs in itertools.product((0, 1), repeat=3):
            name = "".join(pair[k] for pair, k in zip(pairs, signs, strict=True))
            if name[axis] != want:
                continue
            try:
                axes_matrix(name)
            except ValueError:
                continue
            score = (sum(a == b for a, b in zip(name, declared, strict=True)), name in COMMON_AXES)
            if best is None or score > best[0]:
                best = (score, name)
    return best[1] if best else None


def gravity_check(stream: StreamMapping, samples: list, report: Report) -> None:
    """``samples``: the ImuSample messages of the IMU's first STATIC_WINDOW_S (already mapped)."""
    name = f"IMU {stream.sensor_id!r}"
    if len(samples) < 5:
        report.warnings.append(f"{name}: too few samples in its first second to check gravity")
        return
    dts = np.array([s.dt_s for s in samples])
    f = np.array([s.dvel_mps for s in samples]) / dts[:, None]
    w = np.array([s.dtheta_rad for s in samples]) / dts[:, None]
    f_mean, w_mean = f.mean(axis=0), np.linalg.norm(w.mean(axis=0))
    if f.std(axis=0).max() > REST_ACCEL_STD_MPS2 or w_mean > REST_RATE_RPS:
        report.warnings.append(
            f"{name} is not at rest in its first second (specific-force scatter "
            f"{f.std(axis=0).max():.2f} m/s^2, rate {np.degrees(w_mean):.1f} deg/s): "
            "gravity direction not checked"
        )
        return
    g = float(np.linalg.norm(f_mean))
    m = stream.matrix()
    f_src = m.T @ f_mean / stream.accel_scale()  # in the source's axes and unit
    j = int(np.argmax(np.abs(f_src)))
    axis = "xyz"[j]
    unit = stream.accel_unit
    if 0.9 < g < 1.1 and stream.accel_unit == "m/s^2":
        report.errors.append(
            f"{name} reads {g:.2f} m/s^2 at rest (gravity is 9.8): the accelerometer looks like it is in g, "
            "mapping says accel_unit = 'm/s^2'"
        )
        return
    if 85.0 < g < 110.0 and stream.accel_unit == "g":
        report.errors.append(
            f"{name} reads {g / 9.80665:.1f} g at rest: the accelerometer looks like it is in m/s^2, "
            "mapping says accel_unit = 'g'"
        )
        return
    if not GRAVITY_RANGE_MPS2[0] < g < GRAVITY_RANGE_MPS2[1]:
        report.errors.append(
            f"{name} reads |f| = {g:.2f} m/s^2 at rest, expected about 9.8: "
            "check accel_unit and the scale of the data"
        )
        return
    if f_mean[2] > 0.9 * g:
        return  # gravity reaction on fednav's up axis: the axes agree
    declared = stream.axes if isinstance(stream.axes, str) else axes_name(m)
    read = f"{f_src[j]:+.1f} {unit}"
    if declared:
        hint = suggest_axes(declared.upper(), j, f_src[j] > 0)
        report.errors.append(
            f"{name} {axis} axis reads {read} at rest: axes look like {hint}, mapping says {declared.upper()}"
        )
    else:
        report.errors.append(
            f"{name} {axis} axis reads {read} at rest, so it points {'up' if f_src[j] > 0 else 'down'}; "
            f"the axes matrix sends it to fednav {np.round(m[:, j], 3).tolist()} (right, forward, up): "
            "check the matrix"
        )


def run_checks(mapping: ReplayMapping, base: Path) -> Report:
    """Read every stream once (as it will be published) and check it."""
    report = Report()
    imu_streams = [s for s in mapping.streams if s.kind == "imu"]
    if not imu_streams:
        report.errors.append("no IMU stream: the service needs an IMU to navigate")
    if not any(s.kind in ("gnss_fix", "gnss_raw") for s in mapping.streams):
        report.warnings.append("no GNSS stream: the service cannot align or aid the INS without one")
    for stream in mapping.streams:
        sr = StreamReport(name=f"{stream.kind} {stream.sensor_id!r} ({stream.source})", kind=stream.kind)
        report.streams.append(sr)
        first: list = []
        prev = None
        dts: list[float] = []
        try:
            for ev in stream_events(stream, base, mapping, stats=sr.skipped):
                t = ev.t_gps_s
                sr.count += 1
                if sr.t_first is None:
                    sr.t_first = t
                sr.t_last = t if sr.t_last is None else max(sr.t_last, t)
                if prev is not None:
                    if t < prev:
                        sr.backwards += 1
                    elif t == prev:
                        sr.repeated += 1
                    else:
                        dts.append(t - prev)
                prev = t
                if stream.kind == "imu" and t - sr.t_first <= STATIC_WINDOW_S:
                    first.append(ev.msg)
        except SourceError as exc:
            report.errors.append(str(exc))
            continue
        label = f"{stream.kind} {stream.sensor_id!r}"
        if sr.count == 0:
            report.errors.append(f"{label}: no messages read from {stream.source}")
            continue
        if sr.t_first < 0 or sr.t_first > 3.0e9:
            report.errors.append(
                f"{label}: first stamp {sr.t_first:.1f} s is not a plausible GPS time: check time_base "
                f"('{stream.time_base}') and boot_offset_s"
            )
        if dts:
            sr.rate_hz = 1.0 / float(np.median(dts))
        else:
            report.warnings.append(f"{label}: rate unknown (a single message)")
        back = sr.backwards + sr.skipped.get("stamp_not_increasing", 0)
        if back:
            report.errors.append(
                f"{label}: {back} stamp(s) go backwards or repeat: the stamps are not monotonic "
                "(wrong stamp field, or files concatenated out of order)"
            )
        if sr.repeated:
            report.warnings.append(f"{label}: {sr.repeated} repeated stamp(s) (same time twice)")
        if stream.kind == "imu":
            sr.gaps = int(sum(d > IMU_GAP_S for d in dts)) + sr.skipped.get("gap", 0)
            if sr.gaps:
                report.warnings.append(
                    f"{label}: {sr.gaps} gap(s) longer than {IMU_GAP_S} s: "
                    "the service treats them as IMU loss"
                )
            if sr.rate_hz and sr.rate_hz < MIN_IMU_RATE_HZ:
                report.warnings.append(
                    f"{label}: IMU at {sr.rate_hz:.1f} Hz, below {MIN_IMU_RATE_HZ:.0f} Hz: rates are missing "
                    "or the log is decimated"
                )
            gravity_check(stream, first, report)
        for why in sorted(set(sr.skipped) - {"stamp_not_increasing", "gap"}):
            if sr.skipped.get(why):
                hint = SKIP_HINTS.get(why, "")
                report.warnings.append(
                    f"{label}: {sr.skipped[why]} sample(s) skipped ({why.replace('_', ' ')}){hint}"
                )
    # A time-base mistake shifts a whole stream: its start AND its end. A GNSS that starts later
    # (cold start) still ends with the IMU, so only both ends apart count.
    spans = [s for s in report.streams if s.t_first is not None]
    for a, b in itertools.combinations(spans, 2):
        d_start, d_end = b.t_first - a.t_first, b.t_last - a.t_last
        shift = d_start if abs(d_start) < abs(d_end) else d_end
        if min(abs(d_start), abs(d_end)) > TIME_BASES_DIFFER_S:
            report.errors.append(
                f"time bases differ: {a.name} starts at {gps_str(a.t_first)} but {b.name} at "
                f"{gps_str(b.t_first)}, {d_start:+.1f} s (and ends {d_end:+.1f} s) apart; "
                "check each stream's time_base ('gps', 'unix', 'utc', 'boot' + boot_offset_s), "
                "time_offset_s and leap_seconds"
            )
        elif 1.0 < abs(shift) and abs(abs(shift) - mapping.leap_seconds) < 0.5:
            report.warnings.append(
                f"{a.name} and {b.name} are {abs(shift):.1f} s apart, the leap seconds (GPS - UTC): "
                "is one stream in UTC and the other in GPS time?"
            )
        elif abs(d_start) > TIME_BASES_DIFFER_S:
            report.warnings.append(
                f"{b.name} starts {d_start:+.1f} s after {a.name} (they end together: a late first fix?)"
            )
    return report
