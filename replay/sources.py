"""One module per input format, all behind one function: ``events(stream, base_dir, mapping, stats)``
-> iterator of ``Event(t_gps_s, key_suffix, message)`` in the stream's own order."""

from __future__ import annotations

import importlib
from collections.abc import Iterator
from pathlib import Path

from .events import Event, merge
from .mapping import ReplayMapping, StreamMapping

MODULES = {
    "ros": "fednav.replay.ros_source",
    "nmea": "fednav.replay.nmea_source",
    "ubx": "fednav.replay.ubx_source",
    "csv": "fednav.replay.csv_source",
    "rinex": "fednav.replay.rinex_source",
}


class SourceError(ValueError):
    pass


def stream_events(
    stream: StreamMapping, base: Path, mapping: ReplayMapping, stats: dict | None = None
) -> Iterator[Event]:
    """The events of one stream; every parser's own error comes out as SourceError, with the stream named."""
    mod = importlib.import_module(MODULES[stream.resolved_format()])
    it = mod.events(stream, base, mapping, stats=stats)
    try:
        yield from it
    except (ValueError, OSError, KeyError, EOFError) as exc:  # the parsers' errors: say which stream
        raise SourceError(f"stream {stream.kind} {stream.sensor_id!r} ({stream.source}): {exc}") from None


def all_events(mapping: ReplayMapping, base: Path) -> Iterator[Event]:
    """Every stream of the mapping, merged in time order."""
    return merge(stream_events(s, base, mapping) for s in mapping.streams)
