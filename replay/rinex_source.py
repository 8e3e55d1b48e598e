"""RINEX observation + navigation files -> GnssRaw events.

The RINEX readers and the satellite models live in ``simulators/gnss/`` (docs/real_rinex.md):
``simulators.gnss.rinex_raw.iter_gnss_raw(obs_path, nav_paths, **options)`` yields
``(t_gps_s, GnssRaw)`` per observation epoch and this module only calls it, with the mapping's
``rinex_nav`` files and the stream's ``rinex_options`` table as keyword arguments (systems,
pseudorange_sigma_m, range_rate_sigma_mps, start_gps_s, stop_gps_s, max_age_s: checked when the
mapping is read, ``mapping.RinexOptions``). In a build
without that module (a trimmed install), a ``rinex`` stream is refused with a plain message
before anything is published. End to end over Zenoh: tests/test_replay_rinex_zenoh.py.
"""

from __future__ import annotations

from collections.abc import Iterator
from pathlib import Path

from .events import Event, key_suffix
from .mapping import ReplayMapping, StreamMapping


class SourceError(ValueError):
    pass


def available() -> bool:
    try:
        import fednav.simulators.gnss.rinex_raw  # noqa: F401
    except ImportError:
        return False
    return True


NOT_AVAILABLE = (
    "RINEX replay is not available in this build: it needs simulators.gnss.rinex_raw.iter_gnss_raw "
    "(the RINEX -> GnssRaw conversion), which is not installed"
)


def events(
    stream: StreamMapping, base: Path, mapping: ReplayMapping, stats: dict | None = None
) -> Iterator[Event]:
    if not available():
        raise SourceError(NOT_AVAILABLE)
    from fednav.simulators.gnss.rinex_raw import iter_gnss_raw

    if not mapping.rinex_nav:
        raise SourceError("a rinex stream needs 'rinex_nav' (navigation files) in the mapping")
    suffix = key_suffix(stream.kind, stream.sensor_id)
    nav = [base / p for p in mapping.rinex_nav]
    for t, raw in iter_gnss_raw(base / stream.source, nav, **stream.rinex_options.kwargs()):
        yield Event(float(t) + stream.time_offset_s, suffix, raw)
