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

from service import keys
from service.messages import MAX_DT_S, GnssFix, ImuSample, WireModel


class Event(NamedTuple):
    t_gps_s: float
    key_suffix: str
    msg: WireModel


def key_suffix(kind: str, sensor_id: str) -> str:
    """``sensor/imu/<id>``, ``sensor/gnss/<id>/fix``, ... (service.keys builds it)."""
    return keys.sensor("v", kind, sensor_id, prefix="p").split("/", 2)[2]


def merge(streams: Iterable[Iterable[Event]]) -> Iterator[Event]:
    """All streams in time order (stable: equal stamps keep the order the streams were listed)."""
    return heapq.merge(*streams, key=lambda e: e.t_gps_s)


class ImuBuilder:
    """Source IMU samples (already in GPS time) -> ImuSample increments in fednav's RFU body frame.

    Rate form: the interval (t_{k-1}, t_k] gets the trapezoid of the two rates times dt (the first
    sample only opens the first interval). Increment form: the sample is the increment over the
    interval ending at t_k, its length from the source's dt or from the previous stamp. Intervals
    with dt <= 0 (stamps not increasing) or dt > MAX_DT_S (a gap) are not published: counted in
    ``skipped`` by reason (the checks name them before publishing)."""

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
        prev, self._prev = self._prev, (t, w, f)
        if self.form == "rate":
            if prev is None:
                return None
            dt = t - prev[0]
            dtheta, dvel = 0.5 * (prev[1] + w) * dt, 0.5 * (prev[2] + f) * dt
        else:
            if dt is None:
                if prev is None:
                    return None
                dt = t - prev[0]
            dtheta, dvel = w, f
        if dt <= 0.0:
            self._skip("stamp_not_increasing")
            return None
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
    vel_enu_mps,
    pos_std_enu_m,
    vel_std_enu_mps,
    num_sats: int = 0,
    constellation: str = "GPS",
) -> GnssFix:
    """The current GnssFix (3-D velocity with sigmas): NAV-PVT and NavSatFix + Twist have all of it."""
    return GnssFix(
        t=t,
        lat_deg=lat_deg,
        lon_deg=lon_deg,
        height_m=height_m,
        vel_enu_mps=tuple(float(x) for x in vel_enu_mps),
        pos_std_enu_m=tuple(float(x) for x in pos_std_enu_m),
        vel_std_enu_mps=tuple(float(x) for x in vel_std_enu_mps),
        constellation=constellation,
        num_sats=int(min(max(num_sats, 0), 200)),
    )


# Where an NMEA log has no velocity at an epoch (no RMC/VTG), or for the vertical (NMEA has none),
# the current GnssFix still needs a value: zero with these sigmas, i.e. "unknown" to the filter.
NMEA_NO_VERTICAL_VEL_STD_MPS = 5.0
NMEA_NO_VEL_STD_MPS = 100.0


def nmea_fix_to_wire(
    t: float,
    lat_deg: float,
    lon_deg: float,
    height_m: float,
    speed_mps: float | None,
    course_deg: float | None,
    pos_std_enu_m,
    horizontal_vel_std_mps: float,
    num_sats: int = 0,
) -> GnssFix:
    """An NMEA epoch (position; horizontal speed and course over ground when RMC/VTG gave them).

    THE ONE PLACE TO CHANGE AT THE MERGE OF THE GnssFix VARIANTS: the current GnssFix forces a 3-D
    velocity, so the vertical velocity is published as 0 with a wide sigma
    (NMEA_NO_VERTICAL_VEL_STD_MPS) and a missing speed/course as 0 with NMEA_NO_VEL_STD_MPS.
    With the speed + course variant (and the position-only variant when speed is None), this
    function returns that message instead and nothing else in replay/ changes."""
    if speed_mps is None or course_deg is None:
        vel = (0.0, 0.0, 0.0)
        vel_std = (NMEA_NO_VEL_STD_MPS, NMEA_NO_VEL_STD_MPS, NMEA_NO_VEL_STD_MPS)
    else:
        c = np.radians(course_deg)
        vel = (speed_mps * np.sin(c), speed_mps * np.cos(c), 0.0)
        vel_std = (horizontal_vel_std_mps, horizontal_vel_std_mps, NMEA_NO_VERTICAL_VEL_STD_MPS)
    return gnss_fix_to_wire(t, lat_deg, lon_deg, height_m, vel, pos_std_enu_m, vel_std, num_sats)
