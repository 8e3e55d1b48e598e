"""The one interface of every input format: an iterator of events ``(t_gps_s, key_suffix, message)``.

``key_suffix`` is the key below ``{prefix}/{vehicle}/`` (``sensor/imu/imu1``,
``sensor/gnss/rx/fix``); ``message`` is the wire model of service/messages.py, exactly what a live
sensor publishes. Streams are merged in time order with ``heapq.merge`` (each stream is already in
its own time order; a stream that is not is reported by the checks, and stays in file order).
"""

from __future__ import annotations

import heapq
from collections.abc import Iterable, Iterator
from typing import NamedTuple

import numpy as np

from fednav.service import keys
from fednav.service.messages import MAX_DT_S, T_MAX_S, GnssFix, ImuSample, WireModel


class Event(NamedTuple):
    t_gps_s: float
    key_suffix: str
    msg: WireModel


def key_suffix(kind: str, sensor_id: str) -> str:
    """``sensor/imu/<id>``, ``sensor/gnss/<id>/fix``, ... (service.keys builds it)."""
    return keys.sensor("v", kind, sensor_id, prefix="p").split("/", 2)[2]


def count(stats: dict | None, key: str, n: int = 1) -> None:
    """Count ``key`` in a source's ``stats`` (skip reasons; ``sigma_pos:<origin>`` and
    ``sigma_vel:<origin>``: where each fix's sigmas came from, for the checks' summary)."""
    if stats is not None:
        stats[key] = stats.get(key, 0) + n


def note(stats: dict | None, key: str, value) -> None:
    """Keep the first ``value`` under an information key (``_`` prefix: not a count)."""
    if stats is not None and key not in stats:
        stats[key] = value


def merge(streams: Iterable[Iterable[Event]]) -> Iterator[Event]:
    """All streams in time order (stable: equal stamps keep the order the streams were listed)."""
    return heapq.merge(*streams, key=lambda e: e.t_gps_s)


class ImuBuilder:
    """Source IMU samples (already in GPS time) -> ImuSample increments in fednav's RFU body frame.

    Rate form: the interval (t_{k-1}, t_k] gets the trapezoid of the two rates times dt (the first
    sample only opens the first interval). Increment form: the sample is the increment over the
    interval ending at t_k, its length from the source's dt or from the previous stamp. Intervals
    with dt <= 0 (stamps not increasing) or dt > MAX_DT_S (a gap) are not published: counted in
    ``skipped`` by reason (the checks name them before publishing). A stamp that converts to no
    GPS time a message can carry (before 1980, or absurdly late) is ``bad_time``, the first such
    converted time kept under ``_bad_time_t`` (the checks say what the stamps look like)."""

    def __init__(
        self, matrix: np.ndarray, gyro_scale: float, accel_scale: float, form: str, stats: dict | None = None
    ):
        self.m = np.asarray(matrix, float)
        self.gs, self.as_ = gyro_scale, accel_scale
        self.form = form
        self._prev: tuple[float, np.ndarray, np.ndarray] | None = None
        self.skipped: dict[str, int] = {} if stats is None else stats

    def _skip(self, why: str) -> None:
        self.skipped[why] = self.skipped.get(why, 0) + 1

    def push(self, t: float, gyro, accel, dt: float | None = None) -> ImuSample | None:
        w = self.m @ (np.asarray(gyro, float) * self.gs)
        f = self.m @ (np.asarray(accel, float) * self.as_)
        if not (np.all(np.isfinite(w)) and np.all(np.isfinite(f)) and np.isfinite(t)):
            self._skip("not_finite")
            return None
        if not 0.0 <= t <= T_MAX_S:
            self._skip("bad_time")
            note(self.skipped, "_bad_time_t", float(t))
            return None
        prev = self._prev
        if prev is None and (self.form == "rate" or dt is None):
            self._prev = (t, w, f)  # the first sample only opens the first interval
            return None
        if self.form == "rate":
            dt = t - prev[0]
            dtheta, dvel = 0.5 * (prev[1] + w) * dt, 0.5 * (prev[2] + f) * dt
        else:
            if dt is None:
                dt = t - prev[0]
            dtheta, dvel = w, f
        if dt <= 0.0:
            # a repeated or swapped row: skipped, and the next interval starts at the last sample
            # taken (from this one it would overlap the interval already published)
            self._skip("stamp_not_increasing")
            return None
        self._prev = (t, w, f)
        if dt > MAX_DT_S:
            self._skip("gap")
            return None
        try:
            return ImuSample(t=t, dt_s=dt, dtheta_rad=tuple(dtheta.tolist()), dvel_mps=tuple(dvel.tolist()))
        except ValueError:
            self._skip("implausible")
            return None


def gnss_fix_to_wire(
    t: float,
    lat_deg: float,
    lon_deg: float,
    height_m: float,
    vel_enu_mps=None,
    pos_std_enu_m=None,
    vel_std_enu_mps=None,
    num_sats: int = 0,
    constellation: str = "GPS",
    fix_type: str = "single",
    hdop: float | None = None,
) -> GnssFix:
    """A GnssFix with what the source really gives: 3-D velocity (UBX NAV-PVT, NavSatFix + Twist)
    or none (position only, ``vel_enu_mps=None``). Sigmas left None take the documented defaults
    from ``fix_type`` and ``hdop`` (service.messages.GnssFix.pos_std / speed_std)."""

    def _tup(x):
        return None if x is None else tuple(float(v) for v in x)

    return GnssFix(
        t=t,
        lat_deg=lat_deg,
        lon_deg=lon_deg,
        height_m=height_m,
        vel_enu_mps=_tup(vel_enu_mps),
        pos_std_enu_m=_tup(pos_std_enu_m),
        vel_std_enu_mps=_tup(vel_std_enu_mps) if vel_enu_mps is not None else None,
        constellation=constellation,
        num_sats=int(min(max(num_sats, 0), 200)),
        fix_type=fix_type,
        hdop=hdop,
    )


#: NMEA GGA quality indicator -> GnssFix.fix_type (NMEA 0183 v4.10 GGA field 6: 1 GPS SPS, 2 DGPS,
#: 3 PPS, 4 RTK fixed, 5 RTK float, 6 dead reckoning, 7 manual, 8 simulator; 9 SBAS on u-blox and
#: others). Qualities that are not a GNSS solution (6-8) are not published as fixes.
GGA_FIX_TYPE = {1: "single", 2: "dgnss", 3: "single", 4: "fixed", 5: "float", 9: "sbas"}


def nmea_fix_to_wire(
    t: float,
    lat_deg: float,
    lon_deg: float,
    height_m: float,
    speed_mps: float | None,
    course_deg: float | None,
    pos_std_enu_m=None,
    speed_std_mps: float | None = None,
    num_sats: int = 0,
    fix_type: str = "single",
    hdop: float | None = None,
) -> GnssFix:
    """An NMEA epoch as the GnssFix variant it really is: horizontal speed + course when RMC/VTG
    gave both, position only when not. Nothing is invented: NMEA has no vertical velocity, so
    none is sent. Position sigmas: GST's (``pos_std_enu_m``) when present, else None, i.e. the
    documented defaults from ``fix_type`` and ``hdop`` (from GGA); ``speed_std_mps`` None: the
    fix type's default; the course sigma is left to GnssFix (speed sigma / speed: isotropic)."""
    has_vel = speed_mps is not None and course_deg is not None
    return GnssFix(
        t=t,
        lat_deg=lat_deg,
        lon_deg=lon_deg,
        height_m=height_m,
        pos_std_enu_m=None if pos_std_enu_m is None else tuple(float(x) for x in pos_std_enu_m),
        speed_mps=float(speed_mps) if has_vel else None,
        course_deg=float(course_deg) if has_vel else None,
        speed_std_mps=float(speed_std_mps) if has_vel and speed_std_mps is not None else None,
        fix_type=fix_type,
        hdop=hdop,
        num_sats=int(min(max(num_sats, 0), 200)),
    )
