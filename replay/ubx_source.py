"""u-blox UBX logs, parsed and checksum-checked by ``pyubx2``: NAV-PVT -> GnssFix, ESF-RAW -> IMU.

NAV-PVT: time from the GPS time of week ``iTOW`` (ms) with the week taken from the UTC date
fields (UTC + leap seconds, rounded to the nearest week start: exact to the ms), position
(``lat``/``lon`` deg, ``height`` mm above the ellipsoid), velocity ``velN/velE/velD`` (mm/s),
sigmas from ``hAcc`` (the horizontal accuracy, split over east and north as hAcc/sqrt(2)),
``vAcc`` (vertical) and ``sAcc`` (speed: east and north each; the vertical velocity's scaled by
the geometry's vertical-to-horizontal ratio vAcc / (hAcc/sqrt(2)), at least 1: Doppler velocity
has the position's dilution of precision, and a receiver's vertical velocity is noisier than its
horizontal one; the same sAcc on the vertical claimed a half of the simulated receiver's noise and
the filter's innovation consistency test called it). Epochs without ``gnssFixOk`` or with
fixType < 3 (no 3-D fix) are skipped.

ESF-RAW: each block is a 24-bit signed value and a data type (u-blox interface description):
14/13/5 gyro x/y/z in 2^-12 deg/s, 16/17/18 accelerometer x/y/z in 2^-10 m/s^2, in the sensor's
frame (named by the mapping's ``axes``), stamped with a sensor time tag in ticks of ``tick_s``
counted from boot (``time_base = "boot"``). The mapping's units do not apply (the format fixes
them). A sample is published when all six axes of one time tag have arrived.
"""

from __future__ import annotations

import datetime as dt
import math
from collections.abc import Iterator
from pathlib import Path

import numpy as np

from .events import Event, ImuBuilder, count, gnss_fix_to_wire, key_suffix
from .mapping import GPS_EPOCH_UNIX_S, ReplayMapping, StreamMapping, to_gps_s

WEEK_S = 604800.0
GYRO_TYPES = {14: 0, 13: 1, 5: 2}
ACCEL_TYPES = {16: 0, 17: 1, 18: 2}
GYRO_LSB_DPS = 2.0**-12
ACCEL_LSB_MPS2 = 2.0**-10


class SourceError(ValueError):
    pass


def _messages(path: Path, identity: str):
    from pyubx2 import UBX_PROTOCOL, UBXReader

    with path.open("rb") as f:
        for _raw, msg in UBXReader(f, protfilter=UBX_PROTOCOL, quitonerror=0):
            if msg is not None and msg.identity == identity:
                yield msg


def nav_pvt_gps_s(msg, leap_seconds: int) -> float:
    """GPS seconds of a NAV-PVT epoch: week from the UTC date fields, time of week from iTOW."""
    utc = dt.datetime(msg.year, msg.month, msg.day, msg.hour, msg.min, msg.second, tzinfo=dt.UTC)
    approx = utc.timestamp() + msg.nano * 1e-9 - GPS_EPOCH_UNIX_S + leap_seconds
    tow = msg.iTOW / 1000.0
    week = round((approx - tow) / WEEK_S)
    return week * WEEK_S + tow


def _i24(b: bytes) -> tuple[int, int]:
    word = int.from_bytes(b, "little")
    val = word & 0xFFFFFF
    if val & 0x800000:
        val -= 1 << 24
    return val, word >> 24


def events(
    stream: StreamMapping, base: Path, mapping: ReplayMapping, stats: dict | None = None
) -> Iterator[Event]:
    path = base / stream.source
    if not path.exists():
        raise SourceError(f"{path}: no such file")
    suffix = key_suffix(stream.kind, stream.sensor_id)
    if stream.kind == "gnss_fix":
        for m in _messages(path, "NAV-PVT"):
            if not m.gnssFixOk or m.fixType < 3 or m.invalidLlh:
                if stats is not None:
                    stats["no_3d_fix"] = stats.get("no_3d_fix", 0) + 1
                continue
            t = nav_pvt_gps_s(m, mapping.leap_seconds) + stream.time_offset_s
            h_std = max(m.hAcc * 1e-3 / math.sqrt(2.0), 1e-3)
            pstd = (h_std, h_std, max(m.vAcc * 1e-3, 1e-3))
            s_std = max(m.sAcc * 1e-3, 1e-3)
            s_up = s_std * max(1.0, pstd[2] / h_std)  # vertical: the geometry's ratio (docstring)
            vel = (m.velE * 1e-3, m.velN * 1e-3, -m.velD * 1e-3)
            # the 3-D velocity is the receiver's own (velD is measured, not invented); fix type
            # from the carrier-phase and differential flags (only labels it: the sigmas are given)
            carr = int(getattr(m, "carrSoln", 0) or 0)
            ftype = {1: "float", 2: "fixed"}.get(carr, "dgnss" if getattr(m, "diffSoln", 0) else "single")
            fix = gnss_fix_to_wire(
                t, m.lat, m.lon, m.height * 1e-3, vel, pstd, (s_std, s_std, s_up), m.numSV, fix_type=ftype
            )
            count(stats, "sigma_pos:receiver")
            count(stats, "sigma_vel:receiver")
            yield Event(t, suffix, fix)
        return
    if stream.tick_s is None:
        raise SourceError(
            "ESF-RAW needs 'tick_s' (seconds per sensor time-tag tick, from the receiver manual)"
        )
    b = ImuBuilder(stream.matrix(), 1.0, 1.0, "rate", stats=stats)
    pending: dict[int, dict] = {}
    for m in _messages(path, "ESF-RAW"):
        i = 1
        while hasattr(m, f"data_{i:02d}"):
            val, typ = _i24(getattr(m, f"data_{i:02d}"))
            tag = int.from_bytes(getattr(m, f"sTag_{i:02d}"), "little")
            i += 1
            slot = pending.setdefault(tag, {"g": [None] * 3, "a": [None] * 3})
            if typ in GYRO_TYPES:
                slot["g"][GYRO_TYPES[typ]] = val * GYRO_LSB_DPS * np.pi / 180.0
            elif typ in ACCEL_TYPES:
                slot["a"][ACCEL_TYPES[typ]] = val * ACCEL_LSB_MPS2
        for tag in sorted(pending):
            slot = pending[tag]
            if None in slot["g"] or None in slot["a"]:
                continue
            del pending[tag]
            t = to_gps_s(tag * stream.tick_s, stream, mapping.leap_seconds)
            s = b.push(t, slot["g"], slot["a"])
            if s is not None:
                yield Event(t, suffix, s)
