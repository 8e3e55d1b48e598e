"""IMU samples (and the readings of sensor registry kinds with a CSV hook, e.g. ``baro``) from a CSV
file (read with the standard library's csv module).

Format (a header row names the columns; lines starting with '#' are comments; order free):

    rate form       t, gyro_x, gyro_y, gyro_z, accel_x, accel_y, accel_z
    increment form  t, dtheta_x, dtheta_y, dtheta_z, dvel_x, dvel_y, dvel_z [, dt]

``t``: the sample's stamp (end of the interval in increment form) in the stream's ``time_base``;
axes x, y, z of the source frame named by ``axes``; gyro in ``gyro_unit`` (rad/s or deg/s; in
increment form rad or deg), accelerometer in ``accel_unit`` (m/s^2 or g; increment form m/s or
g*s). Without a ``dt`` column the interval is the difference of consecutive stamps.
"""

from __future__ import annotations

import csv
from collections.abc import Iterator
from pathlib import Path

from .events import Event, ImuBuilder, key_suffix
from .mapping import ReplayMapping, StreamMapping, to_gps_s

RATE_COLUMNS = ("t", "gyro_x", "gyro_y", "gyro_z", "accel_x", "accel_y", "accel_z")
INCREMENT_COLUMNS = ("t", "dtheta_x", "dtheta_y", "dtheta_z", "dvel_x", "dvel_y", "dvel_z")


class SourceError(ValueError):
    pass


def events(
    stream: StreamMapping, base: Path, mapping: ReplayMapping, stats: dict | None = None
) -> Iterator[Event]:
    if stream.kind != "imu":
        yield from registry_events(stream, base, mapping)
        return
    path = base / stream.source
    cols = RATE_COLUMNS if stream.form == "rate" else INCREMENT_COLUMNS
    b = ImuBuilder(stream.matrix(), stream.gyro_scale(), stream.accel_scale(), stream.form, stats=stats)
    suffix = key_suffix(stream.kind, stream.sensor_id)
    try:
        f = path.open(newline="")
    except OSError as exc:
        raise SourceError(f"{path}: {exc}") from None
    with f:
        reader = csv.DictReader(line for line in f if not line.lstrip().startswith("#"))
        names = [n.strip() for n in (reader.fieldnames or [])]
        missing = [c for c in cols if c not in names]
        if missing:
            raise SourceError(
                f"{path}: {stream.form} form needs columns {', '.join(cols)}; missing {', '.join(missing)}"
            )
        has_dt = stream.form == "increment" and "dt" in names
        for line, row in enumerate(reader, start=2):
            row = {k.strip(): v for k, v in row.items() if k is not None}
            try:
                v = [float(row[c]) for c in cols]
                dt = float(row["dt"]) if has_dt else None
            except (TypeError, ValueError):
                raise SourceError(f"{path} line {line}: a value is not a number") from None
            t = to_gps_s(v[0], stream, mapping.leap_seconds)
            s = b.push(t, v[1:4], v[4:7], dt=dt)
            if s is not None:
                yield Event(t, suffix, s)


def registry_events(stream: StreamMapping, base: Path, mapping: ReplayMapping) -> Iterator[Event]:
    """A CSV stream of a sensor registry kind (e.g. ``baro``: t, altitude_m[, std_m]): the columns
    and the message come from the kind's entry (``csv_columns``, ``from_csv``); ``t`` in the
    stream's time base."""
    from fednav.service import sensors

    entry = sensors.get(stream.kind)
    path = base / stream.source
    suffix = key_suffix(stream.kind, stream.sensor_id)
    try:
        f = path.open(newline="")
    except OSError as exc:
        raise SourceError(f"{path}: {exc}") from None
    with f:
        reader = csv.DictReader(line for line in f if not line.lstrip().startswith("#"))
        names = [n.strip() for n in (reader.fieldnames or [])]
        missing = [c for c in entry.csv_columns if c not in names and c not in entry.csv_optional]
        if missing:
            raise SourceError(
                f"{path}: a {stream.kind} CSV needs columns {', '.join(entry.csv_columns)} "
                f"({', '.join(entry.csv_optional) or 'none'} optional); missing {', '.join(missing)}"
            )
        for line, row in enumerate(reader, start=2):
            row = {k.strip(): v for k, v in row.items() if k is not None}
            try:
                values = {
                    c: (float(row[c]) if row.get(c) not in (None, "") else None) for c in entry.csv_columns
                }
            except (TypeError, ValueError):
                raise SourceError(f"{path} line {line}: a value is not a number") from None
            if values["t"] is None:
                raise SourceError(f"{path} line {line}: no time")
            values["t"] = to_gps_s(values["t"], stream, mapping.leap_seconds)
            try:
                msg = entry.from_csv(values, stream.sensor_id)
            except ValueError as exc:
                raise SourceError(f"{path} line {line}: {str(exc).splitlines()[0]}") from None
            yield Event(values["t"], suffix, msg)
