"""IMU samples (and the readings of sensor registry kinds with a CSV hook, e.g. ``baro``) from a CSV
file (read with the standard library's csv module).

Format (a header row names the columns; lines starting with '#' are comments; order free):

    rate form       t, gyro_x, gyro_y, gyro_z, accel_x, accel_y, accel_z
    increment form  t, dtheta_x, dtheta_y, dtheta_z, dvel_x, dvel_y, dvel_z [, dt]

``t``: the sample's stamp (end of the interval in increment form) in the stream's ``time_base``;
axes x, y, z of the source frame named by ``axes``; gyro in ``gyro_unit`` (rad/s or deg/s; in
increment form rad or deg), accelerometer in ``accel_unit`` (m/s^2 or g; increment form m/s or
g*s). Without a ``dt`` column the interval is the difference of consecutive stamps. ``t`` and
``dt`` are in seconds, or in ticks of ``tick_s`` seconds when the stream sets it (``tick_s =
0.001``: milliseconds; the same option as UBX ESF-RAW's time tags).

Reading: UTF-8 (a byte order mark, as Excel writes, is dropped); columns separated by ',', or by
';' or tab when the header line has no ','; column names matched ignoring case and surrounding
spaces (a unit in a name, ``gyro_x [deg/s]``, is refused with a hint: units belong in the
mapping); blank and whitespace-only lines are ignored. Line numbers in messages are the file's
physical lines (1-based, counting the header, comments and blank lines). A row with an empty value
is skipped and counted (``empty_field``) like a ``nan``/``inf`` one (``not_finite``); an
incomplete last row (a logger stopped mid-write: fewer fields than it needs, a value cut into no
number, NUL padding, or an unterminated line shorter than the row before it ending in a used value)
is skipped and counted (``truncated_last_row``); any other malformed row is an error. The physical
line of the first sample skipped for each reason is kept under ``_first_line_<reason>`` in the
stats. Stamps whose spacing looks like milliseconds (or us, ns) of a 50-1000 Hz IMU are refused
naming ``tick_s`` unless it is set.
"""

from __future__ import annotations

import csv
import math
import re
import statistics
from collections.abc import Iterable, Iterator
from itertools import chain, islice, pairwise
from pathlib import Path
from typing import IO

from .events import Event, ImuBuilder, count, key_suffix, note
from .mapping import ReplayMapping, StreamMapping, to_gps_s

RATE_COLUMNS = ("t", "gyro_x", "gyro_y", "gyro_z", "accel_x", "accel_y", "accel_z")
INCREMENT_COLUMNS = ("t", "dtheta_x", "dtheta_y", "dtheta_z", "dvel_x", "dvel_y", "dvel_z")
#: column separators, in the order tried on the header line (',' whenever the header has one)
DELIMITERS = (",", ";", "\t")
#: stamp units recognised from the spacing of the first rows: a 50-1000 Hz IMU in that unit
STAMP_UNITS = (("milliseconds", 1e-3), ("microseconds", 1e-6), ("nanoseconds", 1e-9))
IMU_RATES_HZ = (50.0, 1000.0)
UNIT_CHECK_ROWS = 64  # rows whose stamps are looked at before any sample is converted
UNIT_CHECK_MIN_STEPS = 5  # increasing stamp steps needed among them to tell a unit
#: a header name with a unit: ``gyro_x [deg/s]``, ``gyro_x (deg/s)``
_UNIT_IN_NAME = re.compile(r"^(.*?)\s*(\[[^\]]*\]|\([^)]*\))$")
_UNIT_FIELD = {"gyro": "gyro_unit", "dtheta": "gyro_unit", "accel": "accel_unit", "dvel": "accel_unit"}


class SourceError(ValueError):
    pass


class _Builder(ImuBuilder):
    """ImuBuilder that keeps the physical line of the first sample skipped for each reason."""

    line = 0

    def _skip(self, why: str) -> None:
        super()._skip(why)
        note(self.skipped, f"_first_line_{why}", self.line)


def _skip(stats: dict | None, why: str, line: int) -> None:
    count(stats, why)
    note(stats, f"_first_line_{why}", line)


class _Table:
    """A CSV file's header and data rows, with each row's physical line number (1-based: the
    header, comments and blank lines counted) and whether the line ends with a line break."""

    def __init__(self, f: IO[str], path: Path):
        self.path = path
        self.line = 0  # physical line of the last data line read
        self.terminated = True
        self.read = 0  # physical lines read so far
        lines = self._lines(f)
        first = next(lines, None)
        self.header_line = first or ""
        self.delimiter = next((d for d in DELIMITERS if d in self.header_line), ",")
        self.header = next(self._parsed(csv.reader([self.header_line], delimiter=self.delimiter)), [])
        self._reader = self._parsed(csv.reader(lines, delimiter=self.delimiter))

    def _lines(self, f: IO[str]) -> Iterator[str]:
        try:
            for n, line in enumerate(f, start=1):
                self.read = n
                if "\0" in line:  # a crashed logger's file can end in a run of NUL bytes (no newline)
                    line = line.rstrip("\0")
                s = line.strip()
                if not s or s.startswith("#"):
                    continue
                self.line, self.terminated = n, line.endswith(("\n", "\r"))
                yield line
        except UnicodeDecodeError:
            if _gzip(self.path):
                raise SourceError(
                    f"{self.path}: compressed with gzip (it starts with gzip's bytes 1f 8b), not text: "
                    f"decompress it first (gunzip -c {self.path.name} > unpacked.csv)"
                ) from None
            raise SourceError(
                f"{self.path}: not UTF-8 text (a byte at or after line {self.read + 1} is no UTF-8): "
                "save the file as UTF-8"
            ) from None

    def _parsed(self, reader: Iterator[list[str]]) -> Iterator[list[str]]:
        while True:
            try:
                row = next(reader)
            except StopIteration:
                return
            except csv.Error as exc:  # e.g. NUL bytes inside a line: not a ValueError
                raise SourceError(f"{self.path} line {self.line}: {exc}") from None
            yield row

    def rows(self) -> Iterator[tuple[int, list[str], bool, bool]]:
        """(line, fields, terminated, last): each data row, ``last`` True for the file's last one."""
        prev = None
        for row in self._reader:
            if prev is not None:
                yield (*prev, False)
            prev = (self.line, row, self.terminated)
        if prev is not None:
            yield (*prev, True)

    def columns(self, wanted: Iterable[str]) -> dict[str, int]:
        """The index of each wanted column that the header has: its exact name (surrounding spaces
        ignored; the last of equal names), else the one name equal to it ignoring case."""
        names = [h.strip() for h in self.header]
        exact = {n: i for i, n in enumerate(names)}
        folded: dict[str, list[int]] = {}
        for i, n in enumerate(names):
            folded.setdefault(n.lower(), []).append(i)
        out = {}
        for c in wanted:
            if c in exact:
                out[c] = exact[c]
            elif c in folded:
                hits = folded[c]
                if len({names[i] for i in hits}) > 1:
                    raise SourceError(
                        f"{self.path}: columns {', '.join(repr(names[i]) for i in hits)} all read as "
                        f"{c!r} (names are matched ignoring case): keep one"
                    )
                out[c] = hits[-1]
        return out

    def missing_hints(self, missing: list[str], other_form: tuple[str, tuple[str, ...]] | None = None) -> str:
        """Why required columns may be missing: units written in the names, another separator,
        the other IMU form's columns."""
        hints = []
        if not self.header:
            hints.append("the file has no header line (every line is blank or a '#' comment)")
        united = []  # (name as written, the column it looks like)
        for h in self.header:
            m = _UNIT_IN_NAME.match(h.strip())
            if m and m.group(1).strip().lower() in missing:
                united.append((h.strip(), m.group(1).strip().lower()))
        if united:
            fields = sorted(
                {_UNIT_FIELD[b.split("_")[0]] for _, b in united if b.split("_")[0] in _UNIT_FIELD}
            )
            where = [
                *fields,
                *(["tick_s for stamps not in seconds"] if {"t", "dt"} & {b for _, b in united} else []),
            ]
            hints.append(
                "column names carry units ("
                + ", ".join(f"{h!r} looks like {b}" for h, b in united)
                + "): units belong in the mapping"
                + (f" ({', '.join(where)})" if where else "")
                + f", not in the header: name the columns {', '.join(b for _, b in united)}"
            )
        if len(self.header) == 1 and " " in self.header_line.strip():
            hints.append(
                "the header has a single column: the reader expects the columns separated by ',' "
                "(or ';' or a tab), not spaces"
            )
        if other_form is not None:
            form, cols = other_form
            if all(c in self.columns(cols) for c in cols):
                hints.append(f"the header has the {form} form's columns: set form = '{form}' in the stream")
        return "".join(f"; {h}" for h in hints)

    def not_a_number(self, line: int, column: str, value: str) -> SourceError:
        hint = ""
        if self.delimiter != "," and "," in value:
            hint = ": a decimal comma? the reader expects '.' as the decimal mark"
        return SourceError(f"{self.path} line {line}: {column} = {value.strip()!r} is not a number{hint}")


def _gzip(path: Path) -> bool:
    """Whether the file starts with gzip's magic bytes (a ``.gz`` renamed ``.csv``)."""
    try:
        with path.open("rb") as f:
            return f.read(2) == b"\x1f\x8b"
    except OSError:
        return False


def _open(path: Path) -> IO[str]:
    try:
        return path.open(newline="", encoding="utf-8-sig")
    except OSError as exc:
        raise SourceError(f"{path}: {exc}") from None


def _unresolved(stream: StreamMapping) -> bool:
    """A boot-time stream whose ``boot_offset_s = 'auto'`` has not been derived (the checks'
    resolve_boot_offsets failed, or a caller skipped it): the file is read in full first, so that a
    problem of the file itself is the one reported, then mapping.to_gps_s says what is missing."""
    return stream.time_base == "boot" and not isinstance(stream.boot_offset_s, float | int)


def check_stamp_unit(path: Path, stamps: list[float]) -> None:
    """Refuse stamps that look like milliseconds (microseconds, nanoseconds): the median step of
    the first rows, read in that unit, is a 50-1000 Hz IMU (in seconds it would be one below 2 Hz)."""
    steps = [b - a for a, b in pairwise(x for x in stamps if math.isfinite(x)) if b > a]
    if len(steps) < UNIT_CHECK_MIN_STEPS:
        return
    med = statistics.median(steps)
    if med <= 0.5:
        return
    lo, hi = IMU_RATES_HZ
    for unit, scale in STAMP_UNITS:
        rate = 1.0 / (med * scale)
        if 0.99 * lo <= rate <= 1.01 * hi:
            raise SourceError(
                f"{path}: the stamps (column t) look like {unit}: the first rows are {med:g} apart, a "
                f"{rate:.0f} Hz IMU in {unit} but {1.0 / med:.2g} Hz in seconds: set tick_s = {scale:g} in "
                "the stream (seconds per unit of the t and dt columns)"
            )


def events(
    stream: StreamMapping, base: Path, mapping: ReplayMapping, stats: dict | None = None
) -> Iterator[Event]:
    if stream.kind != "imu":
        yield from registry_events(stream, base, mapping, stats)
        return
    path = base / stream.source
    cols = RATE_COLUMNS if stream.form == "rate" else INCREMENT_COLUMNS
    other = ("increment", INCREMENT_COLUMNS) if stream.form == "rate" else ("rate", RATE_COLUMNS)
    tick = stream.tick_s  # (the mapping refuses one that is not a finite number > 0)
    b = _Builder(stream.matrix(), stream.gyro_scale(), stream.accel_scale(), stream.form, stats=stats)
    suffix = key_suffix(stream.kind, stream.sensor_id)
    with _open(path) as f:
        table = _Table(f, path)
        idx = table.columns((*cols, "dt"))
        missing = [c for c in cols if c not in idx]
        if missing:
            raise SourceError(
                f"{path}: {stream.form} form needs columns {', '.join(cols)}; missing {', '.join(missing)}"
                + table.missing_hints(missing, other)
            )
        if stream.form == "increment" and "dt" in idx:
            cols = (*cols, "dt")
        rows = _imu_rows(table, [(c, idx[c]) for c in cols], b.skipped)
        head = list(islice(rows, UNIT_CHECK_ROWS))
        if tick is None:
            check_stamp_unit(path, [r[1][0] for r in head])
        if _unresolved(stream):
            for _ in rows:  # the whole file read first: its own problems are the ones to report
                pass
            to_gps_s(0.0, stream, mapping.leap_seconds)  # raises: boot_offset_s 'auto' not derived
        has_dt = len(cols) == 8
        for line, v in chain(head, rows):
            dt = v[7] if has_dt else None
            if tick is not None:
                v[0] *= tick
                dt = None if dt is None else dt * tick
            t = to_gps_s(v[0], stream, mapping.leap_seconds)
            b.line = line
            s = b.push(t, v[1:4], v[4:7], dt=dt)
            if s is not None:
                yield Event(t, suffix, s)


def _imu_rows(table: _Table, cols: list[tuple[str, int]], stats: dict) -> Iterator[tuple[int, list[float]]]:
    """(line, values of ``cols``) per data row; rows with an empty value and an incomplete last
    row are skipped and counted, any other malformed row is an error."""
    used = {i for _, i in cols}
    full = len(table.header)  # fields of a whole row: the previous row's count (else the header's)
    for line, row, terminated, last in table.rows():
        values: list[float] = []
        empty = cut = False
        for name, i in cols:
            if i >= len(row):
                if last:
                    cut = True
                    break
                raise SourceError(
                    f"{table.path} line {line}: {len(row)} field(s) where the header has "
                    f"{len(table.header)}: no {name}"
                )
            text = row[i]
            if not text.strip():
                empty = True
                continue
            try:
                values.append(float(text))
            except ValueError:
                if last:
                    cut = True
                    break
                raise table.not_a_number(line, name, text) from None
        # an unterminated last line shorter than the row before it: its last value may be cut
        if last and not terminated and len(row) < full and len(row) - 1 in used:
            cut = True
        full = len(row)
        if cut or (empty and last and not terminated):
            _skip(stats, "truncated_last_row", line)
        elif empty:
            _skip(stats, "empty_field", line)
        else:
            yield line, values


def registry_events(
    stream: StreamMapping, base: Path, mapping: ReplayMapping, stats: dict | None = None
) -> Iterator[Event]:
    """A CSV stream of a sensor registry kind (e.g. ``baro``: t, altitude_m[, std_m]): the columns
    and the message come from the kind's entry (``csv_columns``, ``from_csv``); ``t`` in the
    stream's time base (ticks of ``tick_s`` when set). Empty values are None (an optional column's
    default); an incomplete last row is skipped and counted (``truncated_last_row``)."""
    from fednav.service import sensors

    entry = sensors.get(stream.kind)
    path = base / stream.source
    suffix = key_suffix(stream.kind, stream.sensor_id)
    tick = stream.tick_s  # (the mapping refuses one that is not a finite number > 0)
    unresolved = _unresolved(stream)
    with _open(path) as f:
        table = _Table(f, path)
        idx = table.columns(entry.csv_columns)
        missing = [c for c in entry.csv_columns if c not in idx and c not in entry.csv_optional]
        if missing:
            raise SourceError(
                f"{path}: a {stream.kind} CSV needs columns {', '.join(entry.csv_columns)} "
                f"({', '.join(entry.csv_optional) or 'none'} optional); missing {', '.join(missing)}"
                + table.missing_hints(missing)
            )
        full = len(table.header)  # fields of a whole row: the previous row's count (else the header's)
        for line, row, terminated, last in table.rows():
            values: dict[str, float | None] = {}
            try:
                for c in entry.csv_columns:
                    i = idx.get(c)
                    text = row[i] if i is not None and i < len(row) else ""
                    values[c] = float(text) if text.strip() else None
            except ValueError:
                if last:
                    _skip(stats, "truncated_last_row", line)
                    continue
                raise table.not_a_number(line, c, text) from None
            if last and not terminated and len(row) < full and len(row) - 1 in idx.values():
                _skip(stats, "truncated_last_row", line)
                continue
            full = len(row)
            if values["t"] is None:
                raise SourceError(f"{path} line {line}: no time")
            if unresolved:
                continue
            if tick is not None:
                values["t"] *= tick
            values["t"] = to_gps_s(values["t"], stream, mapping.leap_seconds)
            try:
                msg = entry.from_csv(values, stream.sensor_id)
            except ValueError as exc:
                raise SourceError(f"{path} line {line}: {str(exc).splitlines()[0]}") from None
            yield Event(values["t"], suffix, msg)
    if unresolved:
        to_gps_s(0.0, stream, mapping.leap_seconds)  # raises: boot_offset_s 'auto' not derived
