"""Checks of a replay before anything is published, each stated in plain words.

Every stream is read once, as it will be published (the decoded events: one implementation for
CSV, NMEA, UBX and ROS bags alike), and checked:

- units and gravity: in the IMU's first second when it is at rest, else over the whole log
  (a land vehicle's accelerations average out), the mapped specific force must be about
  9.8 m/s^2 (an accelerometer in g declared m/s^2 reads about 1) and point up on fednav's z
  (body right-forward-up); else the axes are named ("IMU z axis reads -9.8 m/s^2 at rest:
  axes look like FRD, mapping says FLU");
- motion against the GNSS (logs that start in motion as well as at rest): over windows of about
  a second in motion, the acceleration and course rate derived from the fixes, rotated into the
  vehicle's axes (heading = course), against the IMU's mean specific force and rate over the same
  windows: the horizontal axes and their signs (forward/right swapped, mounted backwards, one
  sign mirrored), the gyro's yaw axis, sign and unit (yaw rate against course rate), and the
  time offset between the IMU's and the GNSS's stamps (the lag that best aligns the IMU's
  rotation with the course's: a wrong boot offset, leap seconds, a receiver's output latency).
  A wrong mapping is named with the one that fits ("the IMU's axes look like FLU, not FRD:
  set axes = 'FLU'");
- stamps: converted stamps that are no plausible GPS time (what the stamps look like: seconds
  since boot, milliseconds, POSIX), a log that starts after the present (POSIX seconds declared
  as GPS time land in the 2030s), streams whose first stamps are more than a minute apart,
  stamps going backwards or repeating;
- rates: an empty stream, an IMU below 50 Hz or with gaps the service treats as IMU loss;
- sigmas: per GNSS stream, the sigma its fixes carry and where it came from (the receiver's
  GST / covariance / accuracy fields, the mapping, or GnssFix's default for the fix type and HDOP).

Errors stop the replay (``--force`` publishes anyway, except a stream whose ``"auto"`` boot offset
could not be derived); warnings and notes are printed.
``resolve_boot_offsets`` turns ``boot_offset_s = "auto"`` into a number before the checks.
"""

from __future__ import annotations

import datetime as dt
import itertools
import math
import time
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from fednav.service import earth
from fednav.service.messages import DEFAULT_H_STD_M, DEFAULT_SPEED_STD_MPS, GnssFix, ImuSample

from .mapping import (
    G0_MPS2,
    GPS_EPOCH_UNIX_S,
    ReplayMapping,
    StreamMapping,
    axes_matrix,
    axes_name,
    from_gps_s,
    with_stream,
)
from .sources import SourceError, stream_events

STATIC_WINDOW_S = 1.0  # the first second of the IMU is tested for rest and gravity
REST_ACCEL_STD_MPS2 = 0.3  # at rest: specific-force scatter below this (phone MEMS noise ~0.05)
REST_RATE_RPS = 0.05  # at rest: mean rotation rate below this (about 3 deg/s)
GRAVITY_RANGE_MPS2 = (9.5, 10.1)  # |g| anywhere on Earth is 9.76-9.84; allow for bias and noise
#: in motion the median |specific force| is sqrt(g^2 + a^2) with vehicle accelerations a
MOTION_GRAVITY_RANGE_MPS2 = (9.0, 11.5)
TIME_BASES_DIFFER_S = 60.0
#: a converted first stamp outside 1989..2059 (GPS seconds) is not a plausible GPS time of a log
PLAUSIBLE_GPS_S = (3.0e8, 2.5e9)
#: a log cannot start after the present: a first stamp later than now (the system clock) plus this
#: margin is an error (POSIX seconds of 2024 declared as GPS time start in 2034)
FUTURE_MARGIN_S = 86400.0
MIN_IMU_RATE_HZ = 50.0
IMU_GAP_S = 0.5  # the service's default [intake] max_imu_gap_s
COMMON_AXES = ("FLU", "FRD", "RFU")
SKIP_HINTS = {
    "implausible": ": rates or specific forces beyond the wire limits (50 rad/s, 50 g): check gyro_unit "
    "(deg/s data declared rad/s?) and accel_unit",
    "no_velocity": ": no twist within 0.05 s of the fix (published as position-only fixes)",
    "no_rates": ": Imu messages whose angular_velocity_covariance[0] or linear_acceleration_covariance[0] "
    "is -1 (ROS's 'no estimate': an orientation-only driver) carry no rates: map the raw IMU topic "
    "(e.g. /imu/data_raw)",
    "no_checksum": ": NMEA sentences without a '*hh' checksum are refused (it guards against corrupted "
    "lines): log them with checksums",
}

# --- motion against the GNSS --------------------------------------------------------------------
MIN_SPEED_MPS = 3.0  # course and course rate are used above this speed
WINDOW_S = 1.0  # acceleration / course-rate windows (rounded to whole fix intervals)
MIN_MOTION_EPOCHS = 20  # windows in motion needed to compare the IMU with the GNSS
TURN_RATE_RPS = math.radians(2.0)  # a window turning faster than this counts as a turn
MIN_TURN_EPOCHS = 8  # turning windows needed for the yaw and time-offset checks
MIN_HORIZONTAL_ACCEL_MPS2 = 0.3  # RMS horizontal acceleration needed to check forward/right
LAG_ERROR_S = 0.05  # IMU vs GNSS stamps: an error above this (1.5 m along track at 30 m/s)
LAG_WARN_S = 0.02
#: a lag found counts as a misalignment only this many of its own standard errors from zero: on a
#: short drive with one turn the course's noise moves the best lag by about LAG_ERROR_S (40 s
#: drives with one banked turn, 5 Hz fixes, seeds 1-20, correctly stamped: lags spread 0.030 s,
#: at most 2.65 of their sigmas, 0.026 s on average, from zero)
LAG_SIGNIFICANT = 3.0
LAG_MIN_CORRELATION = 0.8  # below this the lag found does not confirm (nor correct) the stamps
#: lags searched, both ways: the 18 leap seconds, and a receiver's time to first fix (a cold start:
#: 30-60 s) when boot_offset_s = "auto" puts the IMU's first sample at the first fix. Bounded also
#: by the data: at least half the fixes' windows in motion must lie inside the IMU's log
#: stamps going backwards or repeating that the reader skipped: above this share of a stream's
#: samples the stamps themselves are wrong (an error), below a logger's few bad rows (a warning)
MAX_SKIPPED_BACK_FRACTION = 0.01
MAX_LAG_S = 120.0
LAG_COARSE_STEP_S = 0.1  # the whole range at this step (1 s windows: the peak is seconds wide) ...
LAG_MEDIUM_STEP_S = 0.02  # ... its best peaks at this step, then the best to the millisecond
LAG_PEAKS = 3  # coarse peaks examined
LAG_DISTINCT_S = 1.0  # peaks at least this far apart are different offsets
LAG_EDGE_S = 0.5  # a best lag this close to an end of the lags searched may lie beyond it
LAG_AMBIGUOUS = 0.02  # another peak scoring within this of the best: the lag is not determined
#: not confirmed, but a strong signal that the stamps are wrong (an error, with the number to set):
#: the best lag's correlation at least this, and this much better than the stamps' as they are
LAG_STRONG_CORRELATION = 0.5
LAG_CLEARLY_BETTER = 0.3
GYRO_SCALE_OK = (0.8, 1.25)  # yaw rate / course rate
DEG_PER_RAD = 180.0 / math.pi


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
    sigma: dict | None = None  # GNSS fixes: the sigmas they carry and where they came from

    def as_dict(self) -> dict:
        return dict(self.__dict__)


@dataclass
class Report:
    streams: list[StreamReport] = field(default_factory=list)
    errors: list[str] = field(default_factory=list)
    warnings: list[str] = field(default_factory=list)
    notes: list[str] = field(default_factory=list)  # what was found (motion check, derived values)
    motion: dict = field(default_factory=dict)  # per IMU: the motion check's figures
    #: decoded data by stream index (not serialised): ImuData / FixData for suggest and tests
    data: dict = field(default_factory=dict, repr=False)

    @property
    def total(self) -> int:
        return sum(s.count for s in self.streams)

    def as_dict(self) -> dict:
        return {
            "streams": [s.as_dict() for s in self.streams],
            "errors": self.errors,
            "warnings": self.warnings,
            "notes": self.notes,
            "motion": self.motion,
            "messages": self.total,
        }

    def text(self, forced: bool = False) -> str:
        """The summary; ``forced``: the caller publishes despite the errors (``--force``)."""
        lines = []
        for s in self.streams:
            span = f"{s.t_last - s.t_first:.1f} s" if s.count else "-"
            rate = f"{s.rate_hz:.1f} Hz" if s.rate_hz else "rate unknown"
            lines.append(f"  {s.name}: {s.count} messages, {span}, {rate}, starts {gps_str(s.t_first)}")
            if s.sigma:
                lines.append(f"    sigmas: {s.sigma['text']}")
        lines += [f"  {n}" for n in self.notes]
        lines += [f"ERROR: {e}" for e in self.errors]
        lines += [f"warning: {w}" for w in self.warnings]
        if self.errors:
            lines.append(
                f"{len(self.errors)} error(s): publishing anyway (--force)"
                if forced
                else f"{len(self.errors)} error(s): nothing published"
            )
        elif self.warnings:
            lines.append(f"checks passed with {len(self.warnings)} warning(s): read them before publishing")
        else:
            lines.append("checks passed")
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


def gps_now(leap_seconds: int) -> float:
    """The present (the system clock) in GPS seconds."""
    return time.time() - GPS_EPOCH_UNIX_S + leap_seconds


# --- decoded data -----------------------------------------------------------------------------------
@dataclass
class ImuData:
    """An IMU stream as published: interval ends ``t``, lengths ``dt``, increments in fednav's
    RFU body axes (the mapping's axes and units applied)."""

    t: np.ndarray
    dt: np.ndarray
    dtheta: np.ndarray  # (N, 3) rad
    dvel: np.ndarray  # (N, 3) m/s

    @classmethod
    def from_samples(cls, samples: list[ImuSample]) -> ImuData:
        n = len(samples)
        t = np.fromiter((s.t for s in samples), float, n)
        d = np.fromiter((s.dt_s for s in samples), float, n)
        th = np.array([s.dtheta_rad for s in samples], float).reshape(n, 3)
        dv = np.array([s.dvel_mps for s in samples], float).reshape(n, 3)
        return cls(t, d, th, dv)

    def __len__(self) -> int:
        return len(self.t)

    def rates(self) -> tuple[np.ndarray, np.ndarray]:
        """(angular rate rad/s, specific force m/s^2), (N, 3) each."""
        return self.dtheta / self.dt[:, None], self.dvel / self.dt[:, None]

    def cumulative(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Times (N+1: the first interval's start, then every end) and the running integrals of
        angle and velocity increments at them."""
        tc = np.concatenate([[self.t[0] - self.dt[0]], self.t])
        th = np.vstack([np.zeros(3), np.cumsum(self.dtheta, axis=0)])
        dv = np.vstack([np.zeros(3), np.cumsum(self.dvel, axis=0)])
        return tc, th, dv

    def gap_times(self, factor: float = 3.0) -> np.ndarray:
        """Ends of intervals that follow a gap (stamp step above ``factor`` x the median step)."""
        if len(self.t) < 3:
            return np.zeros(0)
        step = np.diff(self.t)
        return self.t[1:][step > factor * float(np.median(step))]


@dataclass
class FixData:
    """A GNSS fix stream: times, positions, ENU velocity (NaN rows where the fix has none)."""

    t: np.ndarray
    lat_deg: np.ndarray
    lon_deg: np.ndarray
    h_m: np.ndarray
    vel: np.ndarray  # (N, 3); vertical NaN for speed + course fixes without a vertical rate
    msgs: list[GnssFix]

    @classmethod
    def from_fixes(cls, fixes: list[GnssFix]) -> FixData:
        vel = np.full((len(fixes), 3), np.nan)
        for i, f in enumerate(fixes):
            if f.vel_enu_mps is not None:
                vel[i] = f.vel_enu_mps
            elif f.speed_mps is not None and f.course_deg is not None:
                c = math.radians(f.course_deg)
                vel[i, :2] = (f.speed_mps * math.sin(c), f.speed_mps * math.cos(c))
                if f.vertical_rate_mps is not None:
                    vel[i, 2] = f.vertical_rate_mps
        return cls(
            np.array([f.t for f in fixes], float),
            np.array([f.lat_deg for f in fixes], float),
            np.array([f.lon_deg for f in fixes], float),
            np.array([f.height_m for f in fixes], float),
            vel,
            fixes,
        )

    def __len__(self) -> int:
        return len(self.t)

    def enu(self) -> np.ndarray:
        """(N, 3) positions in a local tangent plane at the first fix, m."""
        lat0, h0 = math.radians(self.lat_deg[0]), float(self.h_m[0])
        r_m, r_n = earth.radii(lat0)
        e = np.radians(self.lon_deg - self.lon_deg[0]) * (r_n + h0) * math.cos(lat0)
        n = np.radians(self.lat_deg - self.lat_deg[0]) * (r_m + h0)
        return np.stack([e, n, self.h_m - h0], axis=1)

    def velocity(self) -> np.ndarray:
        """ENU velocity at every fix: the fix's own where it has one, else central differences of
        the positions (the vertical from heights when the fix gives none)."""
        v = self.vel.copy()
        if len(self.t) < 3:
            return v
        p = self.enu()
        dp = np.gradient(p, self.t, axis=0)
        missing = np.isnan(v)
        v[missing] = dp[missing]
        return v


#: a file's first bytes, what they are, and the format they need (``content_hint``)
_CONTENT = (
    (b"\x1f\x8b", "gzip", "it is compressed with gzip: decompress it first (gunzip)"),
    (b"$", "nmea", "it holds NMEA text (it starts with '$'): set format = 'nmea'"),
    (b"\xb5\x62", "ubx", "it holds u-blox UBX (it starts with b5 62): set format = 'ubx'"),
)


def content_hint(path: Path, fmt: str) -> str:
    """Why a file of format ``fmt`` gave no message, when its first bytes say it is something
    else (gzip, NMEA, UBX): ": ..." to append to the error, or ""."""
    try:
        with path.open("rb") as f:
            head = f.read(4)
    except OSError:
        return ""
    head = head.removeprefix(b"\xef\xbb\xbf")  # a UTF-8 BOM before NMEA text
    return next((f": {hint}" for magic, what, hint in _CONTENT if head.startswith(magic) and what != fmt), "")


#: the fixes' velocities are judged against their positions' track (differences over about
#: VELOCITY_SPAN_S) when at least VELOCITY_CHECK_FIXES fixes in motion carry one: a frame mistake
#: is named when east and north exchanged fit at least VELOCITY_FRAME_RATIO times better
VELOCITY_CHECK_FIXES = 20
VELOCITY_SPAN_S = 1.0
VELOCITY_FRAME_RATIO = 3.0


def velocity_check(stream: StreamMapping, fx: FixData, report: Report) -> FixData | None:
    """The fixes' own velocities against the track of their positions in motion. When east and
    north look exchanged (a Twist in ENU mapped as NED or the reverse: ``twist_frame``), an error
    that says so, and the fixes with their velocities in the other frame (what the IMU's motion
    is then checked against); else None. Before this, velocities in the wrong frame were blamed on
    the IMU ("the data are mirrored", "the gyro's axes or rate signs differ from the
    accelerometer's")."""
    w = _half_window(fx, VELOCITY_SPAN_S, 3)
    if w is None:
        return None
    k, n = w[0], len(fx)
    p = fx.enu()
    i = np.arange(k, n - k)
    dp = (p[i + k, :2] - p[i - k, :2]) / (fx.t[i + k] - fx.t[i - k])[:, None]
    v = fx.vel[i, :2]
    ok = np.isfinite(v).all(axis=1) & np.isfinite(dp).all(axis=1) & (np.hypot(*dp.T) >= MIN_SPEED_MPS)
    if ok.sum() < VELOCITY_CHECK_FIXES:
        return None
    v, dp = v[ok], dp[ok]
    as_is = math.sqrt(float(np.mean(np.sum((v - dp) ** 2, axis=1))))
    swapped = math.sqrt(float(np.mean(np.sum((v[:, ::-1] - dp) ** 2, axis=1))))
    if swapped * VELOCITY_FRAME_RATIO > as_is:
        return None
    frame = getattr(stream, "twist_frame", None)
    if getattr(stream, "twist_topic", None) and frame in ("ENU", "NED"):
        other = "NED" if frame == "ENU" else "ENU"
        what = (
            f"the Twist's velocities look {other}, the mapping says twist_frame = {frame!r}: "
            f"set twist_frame = {other!r}"
        )
    else:
        what = "its velocities' east and north look exchanged (a NED velocity read as ENU, or the reverse)"
    report.errors.append(
        f"gnss_fix {stream.sensor_id!r}: {what} (RMS misfit against the track of its positions {as_is:.2f} "
        f"m/s over {int(ok.sum())} fixes in motion, {swapped:.2f} m/s with east and north exchanged); the "
        "IMU is checked against the velocities in the other frame"
    )
    vel = fx.vel[:, [1, 0, 2]] * np.array([1.0, 1.0, -1.0])
    return FixData(fx.t, fx.lat_deg, fx.lon_deg, fx.h_m, vel, fx.msgs)


# --- gravity and units -------------------------------------------------------------------------------
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


def _declared(stream: StreamMapping) -> str | None:
    return stream.axes.upper() if isinstance(stream.axes, str) else axes_name(stream.matrix())


def at_rest(samples: list[ImuSample]) -> bool | None:
    """Whether the IMU is at rest over ``samples`` (None: too few to tell)."""
    if len(samples) < 5:
        return None
    dts = np.array([s.dt_s for s in samples])
    f = np.array([s.dvel_mps for s in samples]) / dts[:, None]
    w = np.array([s.dtheta_rad for s in samples]) / dts[:, None]
    return bool(
        f.std(axis=0).max() <= REST_ACCEL_STD_MPS2 and np.linalg.norm(w.mean(axis=0)) <= REST_RATE_RPS
    )


def gravity_check(
    stream: StreamMapping,
    imu: ImuData,
    report: Report,
    first: list[ImuSample],
    speed_mps: float | None = None,
) -> bool:
    """Units and the up axis from the mean specific force: over the IMU's first second when it is
    steady there (``first``: its samples; at rest, or at constant velocity: ``speed_mps`` from the
    fixes), else over the whole log (``imu``). Returns True when the units and the up axis look
    right (or cannot be told), False after naming an error."""
    name = f"IMU {stream.sensor_id!r}"
    rest = at_rest(first)
    if rest:
        dts = np.array([s.dt_s for s in first])
        f_mean = (np.array([s.dvel_mps for s in first]) / dts[:, None]).mean(axis=0)
        g_typ = float(np.linalg.norm(f_mean))
        where, (lo, hi) = "at rest", GRAVITY_RANGE_MPS2
        if speed_mps is not None and speed_mps > 1.0:
            where = f"in its steady first second (moving at {speed_mps:.1f} m/s)"
    else:
        if len(imu) < 5:
            report.warnings.append(f"{name}: too few samples to check gravity")
            return True
        _, f = imu.rates()
        g_typ = float(np.median(np.linalg.norm(f, axis=1)))
        f_mean = imu.dvel.sum(axis=0) / imu.dt.sum()
        where, (lo, hi) = "on average over the log (in motion)", MOTION_GRAVITY_RANGE_MPS2
    m = stream.matrix()
    unit = stream.accel_unit
    if 0.8 < g_typ < 1.3 and unit == "m/s^2":
        report.errors.append(
            f"{name} reads {g_typ:.2f} m/s^2 {where} (gravity is 9.8): the accelerometer looks like it is "
            "in g, mapping says accel_unit = 'm/s^2': set accel_unit = 'g'"
        )
        return False
    if 78.0 < g_typ < 128.0 and unit == "g":
        report.errors.append(
            f"{name} reads {g_typ / G0_MPS2:.1f} g {where}: the accelerometer looks like it is in m/s^2, "
            "mapping says accel_unit = 'g': set accel_unit = 'm/s^2'"
        )
        return False
    if not lo < g_typ < hi:
        report.errors.append(
            f"{name} reads |f| = {g_typ:.2f} m/s^2 {where}, expected about 9.8: "
            "check accel_unit and the scale of the data"
        )
        return False
    g = float(np.linalg.norm(f_mean))
    if not rest and not 0.85 * g_typ < g < 1.15 * g_typ:
        report.warnings.append(
            f"{name}: its mean specific force over the log ({g:.1f} m/s^2) is not gravity's: the up axis "
            "is not checked (not a land vehicle?)"
        )
        return True
    if f_mean[2] > 0.9 * g:
        return True  # gravity reaction on fednav's up axis: the axes agree
    f_src = m.T @ f_mean / stream.accel_scale()  # in the source's axes and unit
    j = int(np.argmax(np.abs(f_src)))
    if abs(f_src[j]) * stream.accel_scale() < 0.9 * g:
        report.warnings.append(
            f"{name}: the mean specific force {where} points between the axes (fednav right/forward/up "
            f"{np.round(f_mean, 2).tolist()} m/s^2): a tilted mount? A 3x3 axes matrix can state it"
        )
        return True
    axis = "xyz"[j]
    read = f"{f_src[j]:+.1f} {unit}"
    declared = _declared(stream)
    if declared:
        hint = suggest_axes(declared, j, f_src[j] > 0)
        report.errors.append(
            f"{name} {axis} axis reads {read} {where}: axes look like {hint}, mapping says {declared}"
        )
    else:
        report.errors.append(
            f"{name} {axis} axis reads {read} {where}, so it points {'up' if f_src[j] > 0 else 'down'}; "
            f"the axes matrix sends it to fednav {np.round(m[:, j], 3).tolist()} (right, forward, up): "
            "check the matrix"
        )
    return False


# --- motion against the GNSS ---------------------------------------------------------------------------
@dataclass
class Kinematics:
    """What the fixes say the IMU should read, per window [ta, tb] in motion (GNSS time):
    mean specific force in the vehicle's right/forward/up axes with heading = course, the rate
    about up (counter-clockwise positive: minus the course rate) and the course change."""

    ta: np.ndarray
    tb: np.ndarray
    f_exp: np.ndarray  # (M, 3) m/s^2
    w_up: np.ndarray  # (M,) rad/s
    turn: np.ndarray  # (M,) |course change| over the window, rad
    speed: np.ndarray  # (M,) m/s

    def __len__(self) -> int:
        return len(self.ta)


def _half_window(fx: FixData, span_s: float, min_fixes: int) -> tuple[int, float] | None:
    """(the fixes on each side of a window of about ``span_s`` in whole fix intervals, the median
    interval), or None for a stream shorter than ``min_fixes`` or than one window, or whose stamps
    do not advance."""
    n = len(fx)
    if n < min_fixes:
        return None
    step = float(np.median(np.diff(fx.t)))
    if not step > 0:
        return None
    k = max(1, int(round(0.5 * span_s / step)))
    return (k, step) if n >= 2 * k + 1 else None


def fix_kinematics(fx: FixData, window_s: float = WINDOW_S) -> Kinematics | None:
    """Windows of about ``window_s`` (whole fix intervals) between fixes in motion."""
    w = _half_window(fx, window_s, 5)
    if w is None:
        return None
    (k, step), n = w, len(fx)
    v = fx.velocity()
    i = np.arange(k, n - k)
    a_i, b_i = i - k, i + k
    ta, tb = fx.t[a_i], fx.t[b_i]
    span = tb - ta
    ok = np.abs(span - 2 * k * step) < 0.5 * step  # no missing fix inside
    va, vb = v[a_i], v[b_i]
    sa, sb = np.hypot(va[:, 0], va[:, 1]), np.hypot(vb[:, 0], vb[:, 1])
    ok &= (sa >= MIN_SPEED_MPS) & (sb >= MIN_SPEED_MPS) & np.isfinite(sa) & np.isfinite(sb)
    if ok.sum() < MIN_MOTION_EPOCHS:
        return None
    ta, tb, va, vb, span, speed = ta[ok], tb[ok], va[ok], vb[ok], span[ok], 0.5 * (sa + sb)[ok]
    acc = (vb - va) / span[:, None]
    acc[:, 2] = np.where(np.isfinite(fx.vel[a_i[ok], 2]) & np.isfinite(fx.vel[b_i[ok], 2]), acc[:, 2], 0.0)
    course_a, course_b = np.arctan2(va[:, 0], va[:, 1]), np.arctan2(vb[:, 0], vb[:, 1])
    dcourse = (course_b - course_a + np.pi) % (2 * np.pi) - np.pi  # clockwise positive
    vm = va + vb
    c = np.arctan2(vm[:, 0], vm[:, 1])
    right = acc[:, 0] * np.cos(c) - acc[:, 1] * np.sin(c)
    fwd = acc[:, 0] * np.sin(c) + acc[:, 1] * np.cos(c)
    g = earth.gravity_normal(math.radians(float(fx.lat_deg[0])), float(fx.h_m[0]))
    f_exp = np.stack([right, fwd, g + acc[:, 2]], axis=1)
    return Kinematics(ta, tb, f_exp, -dcourse / span, np.abs(dcourse), speed)


def _at(tc: np.ndarray, cum: np.ndarray, t: np.ndarray) -> np.ndarray:
    """Running integrals (columns of ``cum``) interpolated at times ``t`` (any shape) -> (*t.shape, 3)."""
    return np.stack([np.interp(t, tc, cum[:, j]) for j in range(cum.shape[1])], axis=-1)


def imu_means(imu: ImuData, ta: np.ndarray, tb: np.ndarray, lag: float = 0.0):
    """Mean angular rate and specific force of the IMU over [ta + lag, tb + lag] (RFU), and which
    windows the IMU covers without a gap."""
    tc, th, dv = imu.cumulative()
    a, b = ta + lag, tb + lag
    valid = (a >= tc[0]) & (b <= tc[-1])
    gaps = imu.gap_times()
    if len(gaps):
        valid &= np.searchsorted(gaps, a, "right") == np.searchsorted(gaps, b, "right")
    span = (b - a)[:, None]
    return (_at(tc, th, b) - _at(tc, th, a)) / span, (_at(tc, dv, b) - _at(tc, dv, a)) / span, valid


def _corr(x: np.ndarray, y: np.ndarray) -> float:
    x, y = x - x.mean(), y - y.mean()
    d = math.sqrt(float((x * x).sum() * (y * y).sum()))
    return float((x * y).sum() / d) if d > 0 else 0.0


#: the specific force that says where up is, averaged over this long around each IMU interval
UP_WINDOW_S = 1.0


def _angle_about_up(tc: np.ndarray, th: np.ndarray, dv: np.ndarray) -> np.ndarray:
    """The IMU's running angle about its own up, (N+1,) at times ``tc`` (:meth:`ImuData.cumulative`):
    each interval's angle increment projected on the specific force averaged over ``UP_WINDOW_S``
    around it (up in whatever axes the IMU reads: no mapping needed); the increment's magnitude
    where that force is not gravity's (an IMU that outputs gravity removed, free fall).

    The course turns about the vertical: a vehicle that rolls into its turns (a car on its
    suspension, an aircraft banking) adds roll rate at the start and end of each turn, the very
    windows that tell the lag, and the rotation's magnitude counted it (a simulated drive with one
    banked turn: 0.106 rad over a 0.8 s window where the course changed 0.032). Roll is about the
    forward axis, square to the specific force in a turn at constant speed. One running angle:
    a window's rotation is then two interpolations, at every lag searched."""
    tm = 0.5 * (tc[:-1] + tc[1:])
    h = 0.5 * UP_WINDOW_S
    lo, hi = np.maximum(tm - h, tc[0]), np.minimum(tm + h, tc[-1])
    f = np.stack([np.interp(hi, tc, dv[:, j]) - np.interp(lo, tc, dv[:, j]) for j in range(3)], axis=-1)
    f /= np.maximum(hi - lo, 1e-9)[:, None]
    fn = np.linalg.norm(f, axis=-1)
    d = np.diff(th, axis=0)
    about_up = (d * f).sum(axis=-1) / np.where(fn > 0, fn, 1.0)
    inc = np.where((fn > 5.0) & (fn < 15.0), about_up, np.linalg.norm(d, axis=-1))
    return np.concatenate([[0.0], np.cumsum(inc)])


def _turning(tc: np.ndarray, up: np.ndarray, a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """The IMU's rotation about its up over each window [a, b] (any shape), rad, >= 0, from the
    running angle ``up`` of :func:`_angle_about_up`."""
    return np.abs(np.interp(b, tc, up) - np.interp(a, tc, up))


def estimate_lag(imu: ImuData, kin: Kinematics, max_lag_s: float = MAX_LAG_S) -> dict:
    """How late the IMU's stamps are against the GNSS's (s): the lag L maximising the correlation
    of the IMU's rotation over [ta + L, tb + L] (about the window's specific force,
    :func:`_turning`: whatever the axes) with the course change over [ta, tb]. The IMU's event at
    true time T is stamped T + L: subtract L from its stamps (``time_offset_s -= L``).

    Lags within +-``max_lag_s`` where at least half the windows lie inside the IMU's log are
    searched: every ``LAG_COARSE_STEP_S``, then the best ``LAG_PEAKS`` peaks (ranked by the
    correlation times the share of the course's turning inside the IMU's log: a lag that leaves
    half the turns outside explains only half) every ``LAG_MEDIUM_STEP_S``, then the best to the
    millisecond. Returns ``lag_s`` (None when there is none, with ``reason``), ``correlation``,
    ``zero_correlation`` (at the stamps as they are; None when they do not overlap),
    ``turn_windows``, ``searched_s`` (the range), ``at_edge`` (the best lag at an end of it),
    ``sigma_s`` (the lag's standard error, :func:`_lag_sigma`; None when it cannot be told) and
    ``runner_up`` (the best other peak, at least ``LAG_DISTINCT_S`` away, or None)."""
    turning = kin.turn / (kin.tb - kin.ta) > TURN_RATE_RPS
    n_turn = int(turning.sum())
    out: dict = {"lag_s": None, "turn_windows": n_turn}
    if n_turn < MIN_TURN_EPOCHS:
        out["reason"] = (
            f"too few turns: {n_turn} windows turning faster than {math.degrees(TURN_RATE_RPS):.0f} deg/s, "
            f"{MIN_TURN_EPOCHS} needed"
        )
        return out
    sel = np.flatnonzero(turning | (np.arange(len(kin)) % max(1, len(kin) // 1500) == 0))[:4000]
    ta, tb, g = kin.ta[sel], kin.tb[sel], kin.turn[sel]
    tc, th, dv = imu.cumulative()
    cum = _angle_about_up(tc, th, dv)
    gaps = imu.gap_times()
    need = max(MIN_TURN_EPOCHS, 0.5 * len(g))
    g_total = float(g.sum())
    # at least half the windows inside the IMU's log: a <= ta + L and tb + L <= b for the median
    lo = max(-max_lag_s, float(tc[0] - np.median(ta)))
    hi = min(max_lag_s, float(tc[-1] - np.median(tb)))
    out["searched_s"] = [lo, hi]
    no_overlap = (
        f"the IMU's log does not hold half the fixes' windows in motion at any lag within +-{max_lag_s:.0f} s"
    )
    if lo > hi:
        out["reason"] = no_overlap
        return out

    def inside(a: np.ndarray, b: np.ndarray) -> np.ndarray:
        """Which windows [a, b] the IMU's log covers without a gap."""
        valid = (a >= tc[0]) & (b <= tc[-1])
        if len(gaps):
            valid &= np.searchsorted(gaps, a, "right") == np.searchsorted(gaps, b, "right")
        return valid

    def scan(lags: np.ndarray, same: bool = False) -> tuple[np.ndarray, np.ndarray]:
        """Correlation at each lag (-inf where too few windows are inside the IMU's log) and the
        share of the course's turning those windows hold. ``same``: every lag over the same windows
        (those inside the log at every lag of ``lags``): a refinement near a peak must not see a
        window leave the set between two neighbouring lags, a step in the correlation that pulled
        the lags found towards the side where the set stays whole (the last window, ending with
        the IMU's log, left it at any positive lag: correctly stamped drives came out 0.03-0.2 s
        early)."""
        corr = np.full(len(lags), -np.inf)
        cover = np.zeros(len(lags))
        fixed = inside(ta + lags.min(), tb + lags.max()) if same else None
        for c0 in range(0, len(lags), 128):
            L = lags[c0 : c0 + 128, None]
            a, b = ta[None, :] + L, tb[None, :] + L
            rot = _turning(tc, cum, a, b)
            valid = np.broadcast_to(fixed, a.shape) if fixed is not None else inside(a, b)
            ok = (valid.sum(axis=1) >= need) & (valid & (g > 0)).any(axis=1)
            w = valid.astype(float)
            n = np.maximum(w.sum(axis=1), 1e-300)
            dx = rot - ((rot * w).sum(axis=1) / n)[:, None]
            dy = g[None, :] - ((g * w).sum(axis=1) / n)[:, None]
            den = np.sqrt((w * dx * dx).sum(axis=1) * (w * dy * dy).sum(axis=1))
            c = np.divide((w * dx * dy).sum(axis=1), den, out=np.zeros(len(L)), where=den > 0)
            corr[c0 : c0 + len(L)] = np.where(ok, c, -np.inf)
            cover[c0 : c0 + len(L)] = (valid * g).sum(axis=1) / g_total if g_total > 0 else 1.0
        return corr, cover

    step = LAG_COARSE_STEP_S
    grid = np.arange(math.ceil(lo / step), math.floor(hi / step) + 1) * step
    lags = np.unique(np.concatenate([grid, [lo, hi]]))
    corr, cover = scan(lags)
    if not np.isfinite(corr).any():
        out["reason"] = no_overlap
        return out
    score = np.where(np.isfinite(corr), corr * cover, -np.inf)
    # the coarse peaks (local maxima, not a better peak's shoulders), best first, each at least
    # LAG_DISTINCT_S from a better one
    padded = np.concatenate([[-np.inf], score, [-np.inf]])
    local = np.isfinite(score) & (score >= padded[:-2]) & (score >= padded[2:])
    peaks: list[float] = []
    for k in np.flatnonzero(local)[np.argsort(-score[local], kind="stable")]:
        if len(peaks) == LAG_PEAKS:
            break
        if all(abs(lags[k] - p) >= LAG_DISTINCT_S for p in peaks):
            peaks.append(float(lags[k]))
    cands = []  # (score, lag, correlation) at the medium step around each peak
    for p in peaks:
        m = np.clip(p + np.arange(-step, step + 1e-9, LAG_MEDIUM_STEP_S), lo, hi)
        cm, vm = scan(m, same=True)
        sm = np.where(np.isfinite(cm), cm * vm, -np.inf)
        j = int(np.argmax(sm))
        cands.append((float(sm[j]), float(m[j]), float(cm[j])))
    cands.sort(key=lambda c: -c[0])
    best = cands[0][1]
    fine = np.arange(best - 2 * LAG_MEDIUM_STEP_S, best + 2 * LAG_MEDIUM_STEP_S + 1e-4, 0.001)
    fine = fine[(fine >= lo) & (fine <= hi)]
    sf, _ = scan(fine, same=True)
    j = int(np.argmax(sf))
    lag = float(fine[j])
    if 0 < j < len(fine) - 1 and np.all(np.isfinite(sf[j - 1 : j + 2])):
        y0, y1, y2 = sf[j - 1], sf[j], sf[j + 1]
        den = y0 - 2 * y1 + y2
        if den < 0:
            lag += 0.001 * 0.5 * (y0 - y2) / den
    c_zero = float(scan(np.zeros(1))[0][0])
    others = [c for c in cands[1:] if abs(c[1] - lag) >= LAG_DISTINCT_S]
    out.update(
        lag_s=lag,
        sigma_s=_lag_sigma(tc, cum, ta, tb, g, gaps, lag),
        correlation=float(sf[j]),
        zero_correlation=c_zero if math.isfinite(c_zero) else None,
        at_edge=bool(lag - lo < LAG_EDGE_S or hi - lag < LAG_EDGE_S),
        score=cands[0][0],
        runner_up=(
            {"lag_s": others[0][1], "correlation": others[0][2], "score": others[0][0]} if others else None
        ),
    )
    return out


#: the lag's standard error: a parametric bootstrap over this many replicates, lags this far either
#: side of the lag found at this step (fixed seed: a check says the same of the same log)
LAG_BOOT_N = 200
LAG_BOOT_SPAN_S = 0.5
LAG_BOOT_STEP_S = 0.004


def _lag_sigma(tc, cum, ta, tb, g, gaps, lag: float) -> float | None:
    """The standard error of a lag found by :func:`estimate_lag`, s (None when it cannot be told),
    from its arrays (IMU times ``tc``, running angle about up ``cum``, windows
    ``ta``-``tb`` between two fixes, their course changes ``g``, gap ends).

    A parametric bootstrap: the course changes regressed on the IMU's rotation over the windows at
    ``lag``; each fix's course error drawn afresh (its variance from the residuals: a window's is
    the difference of its two fixes', hence half their variance) and entered, with opposite signs,
    into the windows that start and end at that fix; the lag that correlates best found again for
    each replicate, on a grid within +-``LAG_BOOT_SPAN_S``; the spread of those lags. Checked on
    the 40 s one-turn drive of tests/replay_files.py: 0.026 s said, against 0.026 s spread by 40
    draws of fresh velocity noise on one drive and 0.030 s over seeds 1-20. (With the rotation's
    magnitude, before the rotation about up, a linearised formula, the residuals through
    d rot / d lag, had said 0.050 s against a spread of 0.088 s: that correlation was not smooth
    at the scale of its noise, and only replicates see such a curve.)"""
    span = LAG_BOOT_SPAN_S
    a, b = ta + lag - span, tb + lag + span
    v = (a >= tc[0]) & (b <= tc[-1])
    if len(gaps):
        v &= np.searchsorted(gaps, a, "right") == np.searchsorted(gaps, b, "right")
    if v.sum() < MIN_TURN_EPOCHS:
        return None
    ta, tb, y = ta[v], tb[v], g[v]
    lags = lag + np.arange(-span, span + 1e-9, LAG_BOOT_STEP_S)
    X = _turning(tc, cum, ta[None, :] + lags[:, None], tb[None, :] + lags[:, None])
    x = _turning(tc, cum, ta + lag, tb + lag)
    xm = x - x.mean()
    sxx = float(xm @ xm)
    if not sxx > 0:
        return None
    k = float(xm @ (y - y.mean())) / sxx
    fit = y.mean() + k * xm
    r = y - fit
    var_e = 0.5 * float(r @ r) / max(1, len(r) - 2)
    fixes, idx = np.unique(np.concatenate([ta, tb]), return_inverse=True)
    ia, ib = idx[: len(ta)], idx[len(ta) :]
    e = np.random.default_rng(0).normal(0.0, math.sqrt(var_e), (LAG_BOOT_N, len(fixes)))
    Y = fit[None, :] + e[:, ib] - e[:, ia]
    Xc = X - X.mean(axis=1, keepdims=True)
    Yc = Y - Y.mean(axis=1, keepdims=True)
    nx = np.linalg.norm(Xc, axis=1)
    ny = np.linalg.norm(Yc, axis=1)
    if not (np.all(nx > 0) and np.all(ny > 0)):
        return None
    corr = (Yc / ny[:, None]) @ (Xc / nx[:, None]).T
    found = lags[np.argmax(corr, axis=1)]
    sigma = float(np.std(found))
    return sigma if math.isfinite(sigma) else None


def lag_doubt(lag: dict) -> str | None:
    """Why the lag :func:`estimate_lag` found does not confirm the alignment of the stamps (None:
    it does). Another peak scoring almost as well (a drive that repeats itself: laps) casts doubt
    only when it is nearer zero, the stamps as they are, than the best."""
    if lag.get("lag_s") is None:
        return lag.get("reason", "no lag found")
    why = []
    L = lag["lag_s"]
    if lag["correlation"] < LAG_MIN_CORRELATION:
        why.append(
            f"the IMU's rotation follows the course with a correlation of {lag['correlation']:.2f} at best "
            f"(at a lag of {L:+.3f} s), {LAG_MIN_CORRELATION} needed"
        )
    if lag["at_edge"]:
        lo, hi = lag["searched_s"]
        why.append(
            f"the best lag, {L:+.3f} s, is at an end of the lags searched ({lo:+.1f} to {hi:+.1f} s): "
            "the offset may lie beyond"
        )
    ru = lag["runner_up"]
    if ru is not None and abs(ru["lag_s"]) < abs(L) and ru["score"] >= lag["score"] - LAG_AMBIGUOUS:
        why.append(
            f"another lag, {ru['lag_s']:+.2f} s (correlation {ru['correlation']:.2f}), fits almost as well "
            f"as {L:+.3f} s (a drive that repeats itself?)"
        )
    return "; ".join(why) or None


#: horizontal signed 2x2 maps (fednav right/forward from the mapped x/y): what each one means
_HORIZONTAL = [
    (np.array([[1, 0], [0, 1]]), "agree"),
    (np.array([[-1, 0], [0, -1]]), "forward and right both read reversed (mounted backwards)"),
    (np.array([[0, 1], [-1, 0]]), "forward and right are exchanged (turned 90 degrees)"),
    (np.array([[0, -1], [1, 0]]), "forward and right are exchanged (turned 90 degrees)"),
    (np.array([[1, 0], [0, -1]]), "forward reads reversed while right does not: the data are mirrored"),
    (np.array([[-1, 0], [0, 1]]), "right reads reversed while forward does not: the data are mirrored"),
    (np.array([[0, 1], [1, 0]]), "forward and right are exchanged and mirrored"),
    (np.array([[0, -1], [-1, 0]]), "forward and right are exchanged and mirrored"),
]


def _horizontal_misfit(x: np.ndarray, y: np.ndarray) -> float:
    """Mean squared misfit of measured (right, forward) ``x`` against expected ``y``, the lateral
    part scaled by the factor in [0, 1] that fits best (banking vehicles read less of it)."""
    den = float((y[:, 0] ** 2).sum())
    gain = min(max(float((x[:, 0] * y[:, 0]).sum()) / den, 0.0), 1.0) if den > 0 else 1.0
    return float(np.mean((x[:, 0] - gain * y[:, 0]) ** 2 + (x[:, 1] - y[:, 1]) ** 2))


def _alignment_advice(stream: StreamMapping, derived: bool) -> str:
    """What to do when the IMU's stamps cannot be aligned with the GNSS's."""
    if stream.time_base == "boot" and derived:
        return (
            "boot_offset_s = 'auto' without a stream carrying both clocks assumes the IMU's and the GNSS's "
            "logs started together (a receiver's first fix often comes 30 s or more after power-on): write "
            "boot_offset_s (the GPS time of the device's boot) in the mapping, or check that both logs "
            "started together"
        )
    if stream.time_base == "boot":
        return (
            "check boot_offset_s (the GPS time of the device's boot) and that both logs cover the same drive"
        )
    return (
        "check the stream's time_base, time_offset_s and leap_seconds, and that both logs cover the same "
        "drive"
    )


def motion_check(
    stream: StreamMapping,
    imu: ImuData,
    kin: Kinematics,
    report: Report,
    fix_label: str,
    leap: int,
    derived: bool = False,
    warned: bool = False,
) -> dict:
    """Axes, signs, gyro unit and time offset of an IMU against the GNSS's motion (module doc).
    Appends errors / warnings / a note to ``report``; returns the figures. ``derived``: the
    stream's boot offset came from ``"auto"``; ``warned``: its derivation was already warned of
    as unconfirmed (the same doubt is not said twice; errors still are)."""
    name = f"IMU {stream.sensor_id!r}"
    out: dict = {"against": fix_label, "windows": len(kin)}
    lag = estimate_lag(imu, kin)
    shift = 0.0
    doubt = lag_doubt(lag)
    if lag["lag_s"] is None:
        if not warned:
            report.notes.append(f"{name}: time offset against {fix_label} not checked: {doubt}")
    else:
        out["time_offset"] = lag
        L, c, c0 = lag["lag_s"], lag["correlation"], lag["zero_correlation"]
        fix_hint = (
            f"boot_offset_s = {float(stream.boot_offset_s) - L:.3f}"
            if stream.time_base == "boot"
            else f"time_offset_s = {stream.time_offset_s - L:+.3f}"
        )
        why = ""
        if abs(abs(L) - leap) < 0.5:
            why = " (the leap seconds: is one stream in UTC and the other in GPS time? check time_base)"
        at_zero = f"{c0:.2f}" if c0 is not None else "none: the logs do not overlap"
        pm = f", 1 sigma {lag['sigma_s']:.3f} s" if lag.get("sigma_s") is not None else ""
        text = (
            f"{name}: its stamps are {abs(L):.3f} s {'late' if L > 0 else 'early'} against those of "
            f"{fix_label} (the IMU's rotation against the course over {lag['turn_windows']} turning windows, "
            f"correlation {c:.2f}{pm}){why}: set {fix_hint} in stream {stream.sensor_id!r}"
        )
        sigma = lag.get("sigma_s")
        significant = sigma is None or abs(L) > LAG_SIGNIFICANT * sigma
        if doubt is None and not significant and abs(L) > LAG_WARN_S:
            # inside the lag's own noise: neither refused nor shifted, but said
            report.notes.append(
                f"{name}: time offset against {fix_label} {L:+.3f} s +- {sigma:.3f} s (1 sigma; the IMU's "
                f"rotation against the course over {lag['turn_windows']} turning windows, correlation "
                f"{c:.2f}): within {LAG_SIGNIFICANT:g} sigma of the stamps as they are, not a misalignment "
                "this drive can show (a longer one, with more turns, tells the offset more finely)"
            )
        elif doubt is None:
            if abs(L) > LAG_ERROR_S:
                report.errors.append(text)
                shift = L
            elif abs(L) > LAG_WARN_S:
                report.warnings.append(text)
                shift = L
        elif (
            abs(L) > LAG_ERROR_S
            and significant
            and c >= LAG_STRONG_CORRELATION
            and (c0 is None or c - c0 >= LAG_CLEARLY_BETTER)
        ):
            # not confirmed, yet the stamps as they are fit clearly worse: the service would refuse
            # the fixes (its innovation gate) and coast
            report.errors.append(
                f"{name}: its stamps look {abs(L):.3f} s {'late' if L > 0 else 'early'} against those of "
                f"{fix_label}: at that lag the IMU's rotation follows the course with a correlation of "
                f"{c:.2f} over {lag['turn_windows']} turning windows, at the stamps as they are "
                f"{at_zero}{why} (not confirmed: {doubt}): set {fix_hint} in stream {stream.sensor_id!r} and "
                f"run --check again; {_alignment_advice(stream, derived)}"
            )
            shift = L
        elif not warned:
            report.warnings.append(
                f"TIME ALIGNMENT NOT CONFIRMED: the stamps of {name} against those of {fix_label}: {doubt}; "
                f"correlation at the stamps as they are {at_zero}. The service may refuse the fixes and "
                f"coast if they are off: {_alignment_advice(stream, derived)}"
            )
    w_bar, f_bar, valid = imu_means(imu, kin.ta, kin.tb, shift)
    if valid.sum() < MIN_MOTION_EPOCHS:
        report.warnings.append(f"{name}: too little IMU data beside the fixes in motion to check its axes")
        return out
    f_bar, w_bar, f_exp, w_up = f_bar[valid], w_bar[valid], kin.f_exp[valid], kin.w_up[valid]
    turning = (kin.turn / (kin.tb - kin.ta) > TURN_RATE_RPS)[valid]
    declared = _declared(stream)
    problems = []
    # horizontal accelerometer axes: the signed map of mapped x/y onto fednav right/forward that
    # fits the acceleration from the fixes best. In a turn a car's IMU reads the centripetal
    # acceleration sideways; a banking vehicle (aircraft, motorbike, the simulator's coordinated
    # turns) reads less of it: the lateral part is fitted with a factor in [0, 1].
    rms_h = float(np.sqrt(np.mean(np.sum(f_exp[:, :2] ** 2, axis=1))))
    out["rms_horizontal_accel_mps2"] = rms_h
    if rms_h >= MIN_HORIZONTAL_ACCEL_MPS2:
        res = [_horizontal_misfit(f_bar[:, :2] @ S.T, f_exp[:, :2]) for S, _ in _HORIZONTAL]
        b = int(np.argmin(res))
        out["horizontal_fit_rms_mps2"] = {"declared": math.sqrt(res[0]), "best": math.sqrt(res[b])}
        if b != 0 and res[0] > 2.5 * res[b] and res[0] - res[b] > 0.05:
            S, meaning = _HORIZONTAL[b]
            P = np.eye(3)
            P[:2, :2] = S
            evidence = (
                f"its specific force against the acceleration from the fixes over {len(f_exp)} windows "
                f"in motion: RMS misfit {math.sqrt(res[0]):.2f} m/s^2 as declared, {math.sqrt(res[b]):.2f} "
                "with the fix"
            )
            if np.linalg.det(S) > 0:
                right = axes_name(P @ stream.matrix())
                fix = (
                    f"set axes = '{right}'"
                    if right
                    else f"use the axes matrix {np.round(P @ stream.matrix(), 6).tolist()}"
                )
                problems.append(
                    f"{name}: the IMU's axes look like {right or 'a rotation of them'}, not {declared}: "
                    f"{meaning}; {fix} ({evidence})"
                )
                out["axes_suggested"] = right
            else:
                problems.append(
                    f"{name}: {meaning} (no right-handed axes fit: one axis' sign is reversed in the log; "
                    f"{evidence})"
                )
    else:
        report.notes.append(
            f"{name}: too little manoeuvring to check forward/right (RMS horizontal acceleration "
            f"{rms_h:.2f} m/s^2, {MIN_HORIZONTAL_ACCEL_MPS2} needed): speed changes and turns check them"
        )
    # gyro: which mapped axis carries the yaw rate, its sign and scale
    if turning.sum() >= MIN_TURN_EPOCHS:
        r = [_corr(w_bar[:, j], w_up) for j in range(3)]
        j = int(np.argmax(np.abs(r)))
        sign = 1.0 if r[j] > 0 else -1.0
        x = sign * w_bar[:, j]
        k = float((x * w_up).sum() / max((x * x).sum(), 1e-30))
        out["yaw"] = {"axis": "xyz"[j], "sign": sign, "correlation": r[j], "course_rate_over_yaw_rate": k}
        if abs(r[j]) < 0.7:
            report.warnings.append(
                f"{name}: its rates do not follow the course rate (best correlation {abs(r[j]):.2f}): "
                "the gyro is not checked"
            )
        elif j != 2 or sign < 0:
            where = (
                "fednav's up axis with the opposite sign"
                if j == 2
                else f"fednav's {('right', 'forward')[j]} axis"
            )
            problems.append(
                f"{name}: its yaw rate appears on {where} (correlation {r[j]:+.2f} with minus the course "
                f"rate over {int(turning.sum())} turning windows) while the mapping puts gravity right: "
                "the gyro's axes or rate signs differ from the accelerometer's in the log"
            )
        elif abs(k / DEG_PER_RAD - 1.0) < 0.15 and stream.gyro_unit == "deg/s":
            problems.append(
                f"{name}: its yaw rate is {1 / k:.4f} x the course rate: the gyro looks like it is in rad/s, "
                "mapping says gyro_unit = 'deg/s': set gyro_unit = 'rad/s'"
            )
        elif abs(k * DEG_PER_RAD - 1.0) < 0.15 and stream.gyro_unit == "rad/s":
            problems.append(
                f"{name}: its yaw rate is {1 / k:.1f} x the course rate: the gyro looks like it is in deg/s, "
                "mapping says gyro_unit = 'rad/s': set gyro_unit = 'deg/s'"
            )
        elif not GYRO_SCALE_OK[0] < k < GYRO_SCALE_OK[1]:
            problems.append(
                f"{name}: its yaw rate is {1 / k:.3f} x the course rate: check gyro_unit and the data's scale"
            )
    else:
        report.notes.append(f"{name}: too few turns to check the gyro's yaw axis, sign and unit")
    report.errors.extend(problems)
    if not problems:
        lag_txt = ""
        if "time_offset" in out:
            lag_txt = (
                f", time offset {out['time_offset']['lag_s']:+.3f} s (correlation "
                f"{out['time_offset']['correlation']:.2f}{', NOT confirmed' if doubt else ''})"
            )
        report.notes.append(
            f"motion: {name} against {fix_label} over {len(f_exp)} windows in motion: axes "
            f"{declared or 'matrix'} fit{lag_txt}"
        )
    return out


# --- sigmas -----------------------------------------------------------------------------------------
_POS_ORIGIN = {
    "GST": "the log's GST sentences",
    "covariance": "the NavSatFix position covariance",
    "receiver": "the receiver's accuracy estimate (NAV-PVT hAcc/vAcc)",
    "mapping": "the mapping's pos_std_m",
}
_VEL_ORIGIN = {
    "covariance": "the Twist covariance",
    "receiver": "the receiver's speed accuracy (NAV-PVT sAcc)",
    "mapping": "the mapping's vel_std_mps",
}


def sigma_summary(stream: StreamMapping, fx: FixData, stats: dict) -> dict:
    """The sigmas a GNSS stream's fixes carry and where they came from (``stats``: the source's
    ``sigma_pos:<origin>`` / ``sigma_vel:<origin>`` counts)."""
    msgs = fx.msgs
    pos = np.array([f.pos_std() for f in msgs])
    med = np.median(pos, axis=0)
    ftypes = sorted({f.fix_type for f in msgs})
    hdops = [f.hdop for f in msgs if f.hdop is not None]
    out: dict = {"pos_std_enu_m_median": med.tolist(), "pos_origin": {}, "vel_origin": {}}
    parts = []
    for key, n in sorted(stats.items()):
        if key.startswith("sigma_pos:"):
            origin = key.split(":", 1)[1]
            out["pos_origin"][origin] = n
            if origin == "default":
                ft = ftypes[0] if len(ftypes) == 1 else "/".join(ftypes)
                base_h = DEFAULT_H_STD_M.get(ftypes[0], 2.5)
                hd = f" x HDOP (median {np.median(hdops):.2f})" if hdops else " (no HDOP: x 1)"
                why = (
                    f"GnssFix's default for fix type '{ft}' ({base_h} m per horizontal axis{hd}, vertical "
                    "1.7 x): the log gives no sigma (NMEA without GST, a fix without covariance); set "
                    "pos_std_m in the stream if you know better"
                )
            else:
                why = _POS_ORIGIN.get(origin, origin)
            parts.append(f"{why} ({n} of {len(msgs)} fixes)")
    text = f"position E/N/U {med[0]:.2f}/{med[1]:.2f}/{med[2]:.2f} m (median) from " + "; ".join(
        parts or ["-"]
    )
    vel_msgs = [f for f in msgs if f.variant != "position"]
    if vel_msgs:
        if all(f.variant == "speed_course" for f in vel_msgs):
            v = float(np.median([f.speed_std() for f in vel_msgs]))
            vtxt = f"speed {v:.3f} m/s (median)"
            out["speed_std_mps_median"] = v
        else:
            vs = np.median(np.array([f.vel_std() for f in vel_msgs]), axis=0)
            vtxt = f"velocity E/N/U {vs[0]:.3f}/{vs[1]:.3f}/{vs[2]:.3f} m/s (median)"
            out["vel_std_enu_mps_median"] = vs.tolist()
        vparts = []
        for key, n in sorted(stats.items()):
            if key.startswith("sigma_vel:"):
                origin = key.split(":", 1)[1]
                out["vel_origin"][origin] = n
                if origin == "default":
                    ft = ftypes[0]
                    src = " (RMC/VTG carry no speed sigma)" if stream.resolved_format() == "nmea" else ""
                    dflt = DEFAULT_SPEED_STD_MPS.get(ft, 0.15)
                    why = f"GnssFix's default for fix type '{ft}' ({dflt} m/s){src}"
                else:
                    why = _VEL_ORIGIN.get(origin, origin)
                vparts.append(f"{why} ({n} fixes)")
        text += f"; {vtxt} from " + "; ".join(vparts or ["-"])
    else:
        text += "; no velocity (position-only fixes)"
    out["text"] = text
    return out


# --- stamps -------------------------------------------------------------------------------------------
def stamp_looks_like(raw: float, stream: StreamMapping) -> str:
    """What a raw stamp (as written in the source) looks like, for messages."""
    a = abs(raw)
    if raw == 0.0:  # a stamp never set: no clock at all, no time base reads it
        return (
            "unset, 0 (a ROS driver that leaves header.stamp empty; the bag's receive "
            "times carry the transport's delays, fednav does not take them for the sensor's time): "
            "fix the driver's stamps, no time_base reads them"
        )
    if a < 1.0e7:
        tow = (
            " (or GPS seconds of the week, 0-604800: set time_offset_s = the week's start, "
            "GPS week x 604800, with time_base = 'gps')"
            if a < 604800.0
            else ""
        )
        return "seconds since the device booted: set time_base = 'boot' with boot_offset_s (or 'auto')" + tow
    scalable = stream.source.lower().endswith((".csv", ".ubx"))  # tick_s scales CSV and UBX stamps
    for lo, unit, tick in (
        (1.0e11, "milliseconds", "0.001"),
        (1.0e14, "microseconds", "1e-6"),
        (1.0e17, "nanoseconds", "1e-9"),
    ):
        if lo < a < lo * 100.0:
            return f"{unit}: " + (
                f"set tick_s = {tick} in the stream" if scalable else "convert the stamps to seconds"
            )
    if 1.0e9 < a < 2.5e9 and stream.time_base == "gps":
        return "POSIX seconds (UTC): set time_base = 'unix'"
    if 3.0e8 < a < 1.0e9 and stream.time_base in ("unix", "utc"):
        return "GPS seconds: set time_base = 'gps'"
    return f"something else: check time_base ('{stream.time_base}'), boot_offset_s and time_offset_s"


# --- the checks ------------------------------------------------------------------------------------------
def _read(stream: StreamMapping, base: Path, mapping: ReplayMapping, stats: dict, sr: StreamReport | None):
    """Read a stream: (IMU rows (t, dt, 6 increments) or fix messages, first-second IMU samples)."""
    rows: list = []
    first: list = []
    prev = None
    dts = []
    for ev in stream_events(stream, base, mapping, stats=stats):
        t = ev.t_gps_s
        m = ev.msg
        if stream.kind == "imu":
            rows.append((t, m.dt_s, *m.dtheta_rad, *m.dvel_mps))
            if not first or t - first[0].t <= STATIC_WINDOW_S:
                first.append(m)
        elif isinstance(m, GnssFix):
            rows.append(m)
        if sr is not None:
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
    return rows, first, dts


def _speed_near(fixes: list, t: float) -> float | None:
    """Horizontal speed of the first fix within 1.5 s of ``t`` (any GNSS stream), None if none."""
    for _, fx in fixes:
        v = fx.velocity()
        near = np.flatnonzero(np.abs(fx.t - t) <= 1.5)
        for i in near:
            if np.isfinite(v[i, :2]).all():
                return float(np.hypot(v[i, 0], v[i, 1]))
    return None


def _imu_data(rows: list) -> ImuData:
    a = np.array(rows, float).reshape(len(rows), 8)
    return ImuData(a[:, 0], a[:, 1], a[:, 2:5], a[:, 5:8])


def run_checks(mapping: ReplayMapping, base: Path) -> Report:
    """Read every stream once (as it will be published) and check it. ``boot_offset_s = 'auto'``
    is resolved first (:func:`resolve_boot_offsets`); ``report.mapping`` is the mapping to publish.
    A stream whose offset could not be derived is not read (the resolution's errors say why, after
    the streams' own: a GNSS file's problem first, then what it left underived)."""
    report = Report()
    derived = {s.sensor_id for s in mapping.streams if s.boot_offset_s == "auto"}
    mapping, notes, errors, doubted = _resolve_boot_offsets(mapping, base)
    report.mapping = mapping
    report.notes += notes
    report.warnings += list(doubted.values())
    imu_streams = [s for s in mapping.streams if s.kind == "imu"]
    if not imu_streams:
        report.errors.append("no IMU stream: the service needs an IMU to navigate")
    if not any(s.kind in ("gnss_fix", "gnss_raw") for s in mapping.streams):
        report.warnings.append("no GNSS stream: the service cannot align or aid the INS without one")
    pending: list[tuple[StreamMapping, ImuData, list]] = []
    fixes: list[tuple[StreamMapping, FixData]] = []
    for idx, stream in enumerate(mapping.streams):
        sr = StreamReport(name=f"{stream.kind} {stream.sensor_id!r} ({stream.source})", kind=stream.kind)
        report.streams.append(sr)
        stats: dict = {}
        label = f"{stream.kind} {stream.sensor_id!r}"
        if stream.boot_offset_s == "auto":
            continue  # not derived: its stamps convert to no time (the resolution's errors say why)
        try:
            rows, first, dts = _read(stream, base, mapping, stats, sr)
        except SourceError as exc:
            if not any(str(exc) in e for e in errors):  # said once: resolving the offsets read it
                report.errors.append(str(exc))
            continue
        finally:
            sr.skipped = {k: v for k, v in stats.items() if not k.startswith(("_", "sigma_"))}
        bad_t = stats.get("_bad_time_t")
        if sr.count == 0:
            if bad_t is not None:
                raw = from_gps_s(bad_t, stream, mapping.leap_seconds)
                report.errors.append(
                    f"{label}: no messages read from {stream.source}: all {stats.get('bad_time', 0)} stamps "
                    f"convert to no GPS time (the first, {raw:.3f} read as time_base '{stream.time_base}', "
                    f"gives t = {bad_t:.1f} s): the stamps look like {stamp_looks_like(raw, stream)}"
                )
            else:
                skipped = ", ".join(f"{n} {k.replace('_', ' ')}" for k, n in sorted(sr.skipped.items()))
                hints = "".join(SKIP_HINTS.get(k, "") for k in sorted(sr.skipped))
                report.errors.append(
                    f"{label}: no messages read from {stream.source}"
                    + (f" (skipped: {skipped}){hints}" if skipped else "")
                    + content_hint(base / stream.source, stream.resolved_format())
                )
            continue
        now = gps_now(mapping.leap_seconds)
        if not PLAUSIBLE_GPS_S[0] <= sr.t_first <= PLAUSIBLE_GPS_S[1]:
            raw = from_gps_s(sr.t_first, stream, mapping.leap_seconds)
            report.errors.append(
                f"{label}: first stamp {sr.t_first:.1f} s ({gps_str(sr.t_first)}) is not a plausible "
                "GPS time "
                f"of a log: its stamps ({raw:.3f} as written) look like {stamp_looks_like(raw, stream)}"
            )
        elif sr.t_first > now + FUTURE_MARGIN_S:
            raw = from_gps_s(sr.t_first, stream, mapping.leap_seconds)
            cause = (
                "POSIX (UTC) seconds declared as GPS time: set time_base = 'unix'"
                if stream.time_base == "gps" and 1.0e9 < raw < 2.5e9
                else f"check time_base ('{stream.time_base}'), boot_offset_s and time_offset_s"
            )
            report.errors.append(
                f"{label}: the log starts {gps_str(sr.t_first)}, after the present "
                f"({gps_str(now)[:10]}): a log cannot start in the future: its stamps ({raw:.3f} as "
                f"written) look like {cause}"
            )
        elif bad_t is not None:
            report.warnings.append(
                f"{label}: {stats.get('bad_time', 0)} stamp(s) convert to no GPS time (t = {bad_t:.1f}): "
                "skipped"
            )
        if dts:
            sr.rate_hz = 1.0 / float(np.median(dts))
        else:
            report.warnings.append(f"{label}: rate unknown (a single message)")
        skipped_back = sr.skipped.get("stamp_not_increasing", 0)
        back = sr.backwards + skipped_back
        line = stats.get("_first_line_stamp_not_increasing")
        where = f" (the first at line {line})" if line else ""
        if sr.backwards or skipped_back > MAX_SKIPPED_BACK_FRACTION * (sr.count + skipped_back):
            report.errors.append(
                f"{label}: {back} stamp(s) go backwards or repeat{where}: the stamps are not monotonic "
                "(wrong stamp field, or files concatenated out of order)"
            )
        elif skipped_back:
            # a logger's few duplicated or swapped rows: the reader dropped them (each interval
            # starts at the last sample taken), the rest is sound
            report.warnings.append(
                f"{label}: {skipped_back} stamp(s) go backwards or repeat{where}: those samples are "
                "skipped (a logger's repeated or swapped rows)"
            )
        if sr.repeated:
            report.warnings.append(f"{label}: {sr.repeated} repeated stamp(s) (same time twice)")
        if stream.kind == "imu":
            sr.gaps = int(sum(d > IMU_GAP_S for d in dts)) + sr.skipped.get("gap", 0)
            if sr.gaps:
                report.warnings.append(
                    f"{label}: {sr.gaps} gap(s) longer than {IMU_GAP_S} s: the service treats them as "
                    "IMU loss"
                )
            if sr.rate_hz and sr.rate_hz < MIN_IMU_RATE_HZ:
                report.warnings.append(
                    f"{label}: IMU at {sr.rate_hz:.1f} Hz, below {MIN_IMU_RATE_HZ:.0f} Hz: rates are missing "
                    "or the log is decimated"
                )
            imu = _imu_data(rows)
            report.data[idx] = imu
            pending.append((stream, imu, first))
        elif stream.kind == "gnss_fix" and rows:
            fx = FixData.from_fixes(rows)
            report.data[idx] = fx
            sr.sigma = sigma_summary(stream, fx, stats)
            fx = velocity_check(stream, fx, report) or fx  # (a frame mistake: the other frame's)
            fixes.append((stream, fx))
        for why in sorted(set(sr.skipped) - {"stamp_not_increasing", "gap"}):
            if sr.skipped.get(why):
                hint = SKIP_HINTS.get(why, "")
                report.warnings.append(
                    f"{label}: {sr.skipped[why]} sample(s) skipped ({why.replace('_', ' ')}){hint}"
                )
    report.errors += errors  # the offsets' resolution: after the problems of the streams it read
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
    # units and gravity (the speed of the first fixes says whether a steady start is a rest)
    imus: list[tuple[StreamMapping, ImuData]] = []
    for stream, imu, first in pending:
        speed = _speed_near(fixes, float(imu.t[0]))
        if gravity_check(stream, imu, report, first, speed):
            imus.append((stream, imu))
    # motion: every IMU whose units and up axis are right, against the first GNSS stream in motion
    ref = next(((s, fx, k) for s, fx in fixes if (k := fix_kinematics(fx)) is not None), None)
    for stream, imu in imus:
        if ref is None:
            if fixes:
                report.notes.append(
                    f"IMU {stream.sensor_id!r}: the fixes show too little motion (above {MIN_SPEED_MPS} m/s) "
                    "to check its axes and time offset against the GNSS"
                )
            continue
        fs, _, kin = ref
        report.motion[stream.sensor_id] = motion_check(
            stream,
            imu,
            kin,
            report,
            f"gnss_fix {fs.sensor_id!r}",
            mapping.leap_seconds,
            derived=stream.sensor_id in derived,
            warned=stream.sensor_id in doubted,
        )
    return report


# --- boot offsets -----------------------------------------------------------------------------------------
def resolve_boot_offsets(
    mapping: ReplayMapping, base: Path, warnings: list[str] | None = None
) -> tuple[ReplayMapping, list[str], list[str]]:
    """``boot_offset_s = "auto"`` -> a number: from a stream that carries both clocks (a ROS bag's
    receive times beside an IMU's boot-time header stamps; NMEA lines led by the logger's stamp),
    else the first fix minus the stream's first stamp (both logs started together); an IMU's
    offset is then refined by the lag of its rotation against the GNSS course (turns needed; from
    the first fix searched over +-``MAX_LAG_S``: a late first fix is found). An offset the motion
    does not confirm is used as derived, with a warning saying why (appended to ``warnings``).
    Returns (mapping with numbers, notes saying how each was derived, errors)."""
    mapping, notes, errors, doubted = _resolve_boot_offsets(mapping, base)
    if warnings is not None:
        warnings.extend(doubted.values())
    return mapping, notes, errors


def _resolve_boot_offsets(
    mapping: ReplayMapping, base: Path
) -> tuple[ReplayMapping, list[str], list[str], dict[str, str]]:
    """:func:`resolve_boot_offsets`, the warnings by the stream's sensor_id."""
    notes: list[str] = []
    errors: list[str] = []
    doubted: dict[str, str] = {}
    for i, s in enumerate(mapping.streams):
        if s.boot_offset_s != "auto":
            continue
        m0 = with_stream(mapping, i, boot_offset_s=0.0)
        stats: dict = {}
        try:
            rows, _, _ = _read(m0.streams[i], base, m0, stats, None)
        except SourceError as exc:
            errors.append(str(exc))  # the file's own problem, said as that (it names the stream)
            continue
        if not rows:  # the stream's own problem, said as the checks say it of any stream
            skipped = ", ".join(f"{n} {k.replace('_', ' ')}" for k, n in sorted(stats.items()) if k[0] != "_")
            errors.append(
                f"{s.kind} {s.sensor_id!r}: no messages read from {s.source}"
                + (f" (skipped: {skipped})" if skipped else "")
                + content_hint(base / s.source, s.resolved_format())
            )
            continue
        # the stream's first stamp: for an IMU the start of its first interval (a rate-form
        # source's first sample only opens it: the first row's end is one sample later)
        raw_first = rows[0][0] - rows[0][1] if s.kind == "imu" else rows[0].t
        how = None
        pairs = stats.get("_clock_pairs")
        if pairs:
            d = np.array([g - r for r, g in pairs])
            off, how = (
                float(np.median(d)),
                f"its bag's receive times against its stamps ({len(d)} pairs, median)",
            )
        fix_streams = [fs for fs in mapping.streams if fs.kind == "gnss_fix" and fs.boot_offset_s != "auto"]
        fx = None
        for fs in fix_streams:
            fstats: dict = {}
            try:
                frows, _, _ = _read(fs, base, mapping, fstats, None)
            except SourceError as exc:
                if str(exc) not in errors:  # the fix stream's own problem, said once
                    errors.append(str(exc))
                continue
            if not frows:
                continue
            fx = fx or FixData.from_fixes(frows)
            fp = fstats.get("_clock_pairs")
            if how is None and fp:
                d = np.array([g - r for r, g in fp])
                off = float(np.median(d))
                how = (
                    f"the logger's receive stamps on {len(d)} epochs of {fs.resolved_format().upper()} "
                    f"stream {fs.sensor_id!r} (median fix GPS time - receive stamp; includes the receiver's "
                    "output latency)"
                )
        if how is None and fx is not None:
            off = float(fx.t[0]) - raw_first
            how = (
                "the first fix's GPS time minus the stream's first stamp (assumes both logs started together)"
            )
        if how is None and fix_streams:
            # the fix streams' own problem is said as that (here, or when the checks read them)
            names = " or ".join(f"gnss_fix {fs.sensor_id!r}" for fs in fix_streams)
            errors.append(
                f"boot_offset_s = 'auto' for stream {s.sensor_id!r} needs fixes from {names}, which gave "
                f"none: not derived, stream {s.sensor_id!r} not checked"
            )
            continue
        if how is None:
            errors.append(
                f"boot_offset_s = 'auto' for stream {s.sensor_id!r}: no GNSS fix stream to derive it from: "
                "set boot_offset_s (the GPS time of the device's boot zero)"
            )
            continue
        refine = ""
        if s.kind == "imu" and fx is not None:
            imu = _imu_data(rows)
            imu.t = imu.t + off
            kin = fix_kinematics(fx)
            coarse = "first fix" in how
            if kin is None:
                lag = {
                    "lag_s": None,
                    "reason": f"the fixes show too little motion (above {MIN_SPEED_MPS} m/s) to align the "
                    "IMU's rotation with the course",
                }
            else:
                lag = estimate_lag(imu, kin, MAX_LAG_S if coarse else 2.0)
            doubt = lag_doubt(lag)
            sigma = lag.get("sigma_s")
            if (
                doubt is None
                and not coarse
                and sigma is not None
                and abs(lag["lag_s"]) <= LAG_SIGNIFICANT * sigma
            ):
                # the receive stamps' offset stands: the motion's correction is inside its own noise
                refine = (
                    f", not refined by the motion: its {-lag['lag_s']:+.3f} s is within "
                    f"{LAG_SIGNIFICANT:g} of its sigmas ({sigma:.3f} s) of zero"
                )
            elif doubt is None:
                L = lag["lag_s"]
                off -= L
                late = ""
                if coarse and abs(L) > 1.0:
                    late = (
                        f": the first fix came {L:.1f} s after the IMU's first sample (a receiver's time to "
                        "first fix?)"
                        if L > 0
                        else f": the IMU's log started {-L:.1f} s after the first fix"
                    )
                refine = (
                    f", then {-L:+.3f} s from its rotation against the course of the fixes "
                    f"({lag['turn_windows']} turning windows, correlation {lag['correlation']:.2f}){late}"
                )
            else:
                refine = f", NOT refined by the motion ({doubt})"
                c0 = lag.get("zero_correlation")
                doubted[s.sensor_id] = (
                    f"TIME ALIGNMENT NOT CONFIRMED: boot_offset_s = 'auto' of stream {s.sensor_id!r} gives "
                    f"{off:.3f} s from {how}, which the motion does not confirm: {doubt}"
                    + (f"; correlation at the derived offset {c0:.2f}" if c0 is not None else "")
                    + (
                        ". Its receive stamps include the receiver's output latency (typically 20-100 ms): "
                        "write boot_offset_s in the mapping if you know it better"
                        if not coarse
                        else ". It assumes the IMU's and the GNSS's logs started together (a receiver's "
                        "first fix often comes 30 s or more after power-on): write boot_offset_s (the GPS "
                        "time of the device's boot) in the mapping, or check that both logs started together"
                    )
                )
        mapping = with_stream(mapping, i, boot_offset_s=round(off, 6))
        notes.append(
            f"boot_offset_s of stream {s.sensor_id!r} derived: {off:.3f} s, from {how}{refine}; write "
            f"boot_offset_s = {off:.3f} in the mapping to use it as it is"
        )
    return mapping, notes, errors, doubted
