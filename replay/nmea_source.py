"""NMEA 0183 logs (GGA, RMC, GST, VTG), each line parsed and checksum-checked by ``pynmea2``.

Sentences are grouped into epochs by their UTC time of day (VTG has none: it joins the epoch of
the sentence before it). An epoch with a valid GGA becomes one GnssFix: position from GGA
(ellipsoidal height = altitude above mean sea level + geoid separation), fix type (quality
indicator) and HDOP from GGA, position sigmas from GST (else the mapping's ``pos_std_m``, else
the documented defaults from fix type and HDOP), the date from RMC (else the mapping's ``date``).
The variant is what the log gives: speed + course over ground (RMC or VTG) when both are there,
position only when not; NMEA has no vertical velocity and none is invented. Lines that are not
NMEA or fail their checksum are counted in ``stats`` and skipped (``bad_sentence``); a sentence
without a ``*hh`` checksum is refused too, counted as ``no_checksum`` (a log written without
checksums: every sentence refused, and the checks say why). The message itself is built by
``events.nmea_fix_to_wire``.

A logger's own receive stamp in front of a line (``12345.678,$GPGGA,...``, or separated by a
space, tab or ';'; unit ``receive_unit``) is kept: each epoch's (receive stamp, fix GPS time)
pair goes to ``stats["_clock_pairs"]``, from which the checks derive the boot offset of an IMU
stamped by the same logger (``boot_offset_s = "auto"``). Where each fix's sigmas came from is
counted in ``stats`` (``sigma_pos:GST``, ``sigma_pos:mapping``, ``sigma_pos:default``,
``sigma_vel:...``).
"""

from __future__ import annotations

import datetime as dt
from collections.abc import Iterator
from pathlib import Path

from .events import GGA_FIX_TYPE, Event, count, key_suffix, nmea_fix_to_wire
from .mapping import RECEIVE_UNITS, ReplayMapping, StreamMapping, to_gps_s

KNOT_MPS = 1852.0 / 3600.0


class SourceError(ValueError):
    pass


def split_receive_stamp(line: str) -> tuple[float | None, str]:
    """``'12345.678,$GPGGA,...'`` -> (12345.678, ``'$GPGGA,...'``); a line without a numeric prefix
    keeps None (a line that is not NMEA comes back as it is)."""
    i = line.find("$")
    if i <= 0:
        return None, line
    head = line[:i].strip().rstrip(",;").strip()
    try:
        return float(head), line[i:]
    except ValueError:
        return None, line[i:]


def _epochs(path: Path, wanted: set[str], stats: dict):
    """Yield dicts {time, receive, GGA, RMC, GST, VTG} in file order, one per UTC time of day
    (``receive``: the logger's stamp in front of the epoch's first line, or None)."""
    import pynmea2

    cur: dict | None = None
    with path.open(errors="replace") as f:
        for line in f:
            recv, line = split_receive_stamp(line.strip())
            if not line.startswith("$"):
                continue
            try:
                m = pynmea2.parse(line, check=True)
            except (pynmea2.ParseError, ValueError, AttributeError):
                why = "no_checksum" if "*" not in line else "bad_sentence"
                stats[why] = stats.get(why, 0) + 1
                continue
            typ = m.sentence_type
            if typ not in wanted:
                continue
            ts = getattr(m, "timestamp", None)
            if typ != "VTG" and ts is not None and (cur is None or cur["time"] != ts):
                if cur is not None:
                    yield cur
                cur = {"time": ts, "receive": recv}
            if cur is not None:
                cur[typ] = m
    if cur is not None:
        yield cur


def _float(x) -> float | None:
    try:
        v = float(x)
    except (TypeError, ValueError):
        return None
    return v


def events(
    stream: StreamMapping, base: Path, mapping: ReplayMapping, stats: dict | None = None
) -> Iterator[Event]:
    path = base / stream.source
    if not path.exists():
        raise SourceError(f"{path}: no such file")
    stats = {} if stats is None else stats
    suffix = key_suffix(stream.kind, stream.sensor_id)
    date = dt.date.fromisoformat(stream.date) if stream.date else None
    last_tod = None
    for ep in _epochs(path, set(stream.sentences), stats):
        rmc, gga = ep.get("RMC"), ep.get("GGA")
        if rmc is not None and getattr(rmc, "datestamp", None):
            date = rmc.datestamp
        elif date is not None and last_tod is not None and ep["time"] < last_tod:
            date = date + dt.timedelta(days=1)  # midnight passed without an RMC
        last_tod = ep["time"]
        qual = int(_float(gga.gps_qual) or 0) if gga is not None else 0
        if qual not in GGA_FIX_TYPE:  # 0 invalid, 6-8 dead reckoning / manual / simulator
            stats["no_fix"] = stats.get("no_fix", 0) + 1
            continue
        fix_type = GGA_FIX_TYPE[qual]
        if date is None:
            raise SourceError(
                f"{path}: no RMC sentence gives the date: set 'date' (YYYY-MM-DD) in the mapping"
            )
        when = dt.datetime.combine(date, ep["time"]).replace(tzinfo=dt.UTC)
        t = to_gps_s(when.timestamp(), stream, mapping.leap_seconds)
        alt, sep = _float(gga.altitude), _float(gga.geo_sep)
        if alt is None:
            continue
        height = alt + (sep or 0.0)
        gst = ep.get("GST")
        pstd = stream.pos_std_m
        origin = "mapping" if pstd is not None else "default"
        if gst is not None:
            s = (_float(gst.std_dev_longitude), _float(gst.std_dev_latitude), _float(gst.std_dev_altitude))
            if all(x is not None and x > 0 for x in s):
                pstd, origin = s, "GST"
        speed = course = None
        if rmc is not None and rmc.status == "A":
            speed, course = _float(rmc.spd_over_grnd), _float(rmc.true_course)
            speed = None if speed is None else speed * KNOT_MPS
        vtg = ep.get("VTG")
        if (speed is None or course is None) and vtg is not None:
            kmh, course = _float(vtg.spd_over_grnd_kmph), _float(vtg.true_track)
            speed = None if kmh is None else kmh / 3.6
        if speed is not None and course is None and speed < 0.1:
            course = 0.0  # receivers leave the course empty at rest
        hdop = _float(gga.horizontal_dil)
        try:
            fix = nmea_fix_to_wire(
                t,
                gga.latitude,
                gga.longitude,
                height,
                speed,
                course,
                pstd,
                None if stream.vel_std_mps is None else stream.vel_std_mps[0],
                num_sats=int(_float(gga.num_sats) or 0),
                fix_type=fix_type,
                hdop=hdop if hdop is not None and 0.0 < hdop <= 100.0 else None,
            )
        except ValueError:
            stats["implausible"] = stats.get("implausible", 0) + 1
            continue
        count(stats, f"sigma_pos:{origin}")
        if fix.speed_mps is not None:
            count(stats, "sigma_vel:mapping" if stream.vel_std_mps is not None else "sigma_vel:default")
        if ep.get("receive") is not None:
            stats.setdefault("_clock_pairs", []).append(
                (ep["receive"] * RECEIVE_UNITS[stream.receive_unit], t)
            )
        yield Event(t, suffix, fix)
