"""Rerun recording schema: entity paths, the timeline, and the integrity region classifier.

Pure Python (no ``rerun`` import), so the service's sink and ``dashboards/`` (blueprints, inspector)
share one definition. Paths mirror the Zenoh keys of ``service/keys.py`` without the prefix and the
``nav/`` level::

    /{vehicle}/truth/position                               GeoPoints (map)
    /{vehicle}/truth/track                                  GeoLineStrings (decimated track, ~10 s)
    /{vehicle}/truth/{lat_deg, ..., heading_deg}            Scalars (SOLUTION_SCALARS)
    /{vehicle}/truth/faults                                 TextLog (injected faults, on change)
    /{vehicle}/truth/fault_channels                         Scalars (channels under an injected fault)
    /{vehicle}/{pipeline}/solution/position, /track         GeoPoints, GeoLineStrings
    /{vehicle}/{pipeline}/solution/{lat_deg, ...}           Scalars (SOLUTION_SCALARS)
    /{vehicle}/{pipeline}/solution/std/{pos_e_m, ...}       Scalars, 1 sigma (STD_SCALARS)
    /{vehicle}/{pipeline}/solution/gyro_bias_dph            Scalars, 3 series x/y/z (when non-zero)
    /{vehicle}/{pipeline}/solution/accel_bias_ug            Scalars, 3 series x/y/z (when non-zero)
    /{vehicle}/{pipeline}/solution/status                   StateChange (on change)
    /{vehicle}/{pipeline}/error/{east_m, ...}               Scalars, solution - truth (ERROR_NAMES)
    /{vehicle}/{pipeline}/bound/{east_m, ...}               Scalars, 2 series [+3 sigma, -3 sigma]
    /{vehicle}/{pipeline}/faults/{subsystem}/{label}/statistic, /threshold    Scalars
    /{vehicle}/{pipeline}/faults/{subsystem}/{label}/flagged                  StateChange ok|flagged|isolated
    /{vehicle}/{pipeline}/faults/{subsystem}/subsystem_isolated               StateChange in use|isolated
    /{vehicle}/{pipeline}/sharing/{local_filter}/{state_index}                Scalars
    /{vehicle}/{pipeline}/innovations/{kind}/{sensor_id}/{label}/{r2_mean, count}   Scalars (windows)
    /{vehicle}/{pipeline}/innovations/{kind}/{sensor_id}/refused                    Scalars (windows)
    /{vehicle}/{pipeline}/integrity/{hpl_m, ...}            Scalars (INTEGRITY_SCALARS; flags as 0/1)
    /{vehicle}/{pipeline}/integrity/excluded_count          Scalars
    /{vehicle}/{pipeline}/integrity/sat/{id}/{statistic_m, threshold_m}       Scalars
    /{vehicle}/{pipeline}/integrity/sat_v/{id}/{statistic_m, threshold_m}     Scalars (vertical, if used)
    /{vehicle}/{pipeline}/integrity/events                  TextLog (detection, alarm, exclusion, ...)
    /{vehicle}/{pipeline}/integrity/stanford/{h, v}         Points2D (x = error, y = -PL), /frame static
    /{vehicle}/{pipeline}/{group}/{name}                    Scalars from ``log_scalars`` (GROUPS)
    /{vehicle}/{pipeline}/imm/{prob, downweighted}/{model}, /rejected_rows     Scalars (IMM)
    /{vehicle}/service/health/{queue_depth, ...}            Scalars (HEALTH_SCALARS)
    /{vehicle}/truth/enu, /{vehicle}/{pipeline}/solution/enu  Points2D (x = east, y = -north, m)
    /{vehicle}/{pipeline}/solution/ellipse                  LineStrips2D (3-sigma horizontal, decimated)
    /{vehicle}/{truth|pipeline}/markers                     Points2D + labels (fault onset, isolation, alarm)
    /{vehicle}/service/inputs/{sensor}/enu                  Points2D (raw GNSS fixes received)
    /{vehicle}/{pipeline}/integrity/{availability, alarm_state}   StateChange (on every epoch)
    /{vehicle}/{pipeline}/fault_tests/{subsystem}/{label}   Scalars, statistic / threshold (1 = threshold)
    /{vehicle}/{pipeline}/isolation/{subsystem}             StateChange in use|isolated (on change)
    /{vehicle}/{pipeline}/integrity/sat_ratio/{id}          Scalars, statistic / threshold (1 = threshold)
    /{vehicle}/{pipeline}/integrity/stanford/labels_{h, v}  Points2D labels (ticks, regions), static

Timelines (every entity carries all three):

* ``sensor_time``: a duration timeline holding ``t`` (seconds of GPS time) in nanoseconds: the
  exact key readers join on (``dashboards/inspect.py``);
* ``mission_time``: a duration timeline, seconds since the first message of the recording (the
  blueprints open on it: "+2m 13s" instead of "+15046d 7h");
* ``utc``: a timestamp timeline, GPS time converted to UTC with the leap seconds of
  :data:`LEAP_SECONDS` (:func:`gps_to_utc_ns`), so the viewer shows wall-clock dates.

Path parts are restricted to ``[A-Za-z0-9_.-]`` (the Zenoh key chunk alphabet of ``keys.py``); any
other character is replaced by ``_`` so that every path parses the same way in the reader.
"""

from __future__ import annotations

import math
import re
from dataclasses import dataclass
from functools import lru_cache

from fednav.service.ins.error_model import NAV_ERRORS, STATE_LABELS

TIMELINE = "sensor_time"
MISSION_TIMELINE = "mission_time"
UTC_TIMELINE = "utc"

#: Unix time (s) of the GPS epoch 1980-01-06T00:00:00 UTC.
GPS_EPOCH_UNIX_S = 315_964_800
#: (GPS seconds at which it takes effect, GPS - UTC in s): IERS Bulletin C leap seconds since 1980.
#: The GPS second of a leap second inserted at the end of UTC day D is D+1 00:00:00 UTC converted
#: with the previous offset.
_LEAP_DATES_UTC = (
    (1981, 7, 1), (1982, 7, 1), (1983, 7, 1), (1985, 7, 1), (1988, 1, 1), (1990, 1, 1),
    (1991, 1, 1), (1992, 7, 1), (1993, 7, 1), (1994, 7, 1), (1996, 1, 1), (1997, 7, 1),
    (1999, 1, 1), (2006, 1, 1), (2009, 1, 1), (2012, 7, 1), (2015, 7, 1), (2017, 1, 1),
)  # fmt: skip


def _leap_table() -> tuple[tuple[float, int], ...]:
    import calendar

    table = []
    for n, (y, m, d) in enumerate(_LEAP_DATES_UTC, start=1):
        unix = calendar.timegm((y, m, d, 0, 0, 0))
        table.append((float(unix - GPS_EPOCH_UNIX_S + n), n))
    return tuple(table)


LEAP_SECONDS = _leap_table()


def gps_minus_utc_s(t_gps_s: float) -> int:
    """GPS - UTC (leap seconds, whole s) at GPS time ``t_gps_s``: 0 before mid-1981, 18 since 2017."""
    off = 0
    for start, n in LEAP_SECONDS:
        if t_gps_s >= start:
            off = n
        else:
            break
    return off


def gps_to_utc_ns(t_gps_s: float) -> int:
    """GPS seconds (since 1980-01-06) -> UTC as integer nanoseconds since the Unix epoch."""
    whole = math.floor(t_gps_s)
    frac_ns = round((t_gps_s - whole) * 1e9)
    return (int(whole) + GPS_EPOCH_UNIX_S - gps_minus_utc_s(t_gps_s)) * 1_000_000_000 + frac_ns


TRUTH = "truth"
SERVICE = "service"
#: Second-level path parts that are not pipelines.
RESERVED_PIPELINE_NAMES = frozenset({TRUTH, SERVICE})

SOLUTION_SCALARS = (
    "lat_deg",
    "lon_deg",
    "height_m",
    "ve_mps",
    "vn_mps",
    "vu_mps",
    "roll_deg",
    "pitch_deg",
    "heading_deg",
)
#: 1-sigma of a Solution (names from the one table of navigation-error names)
STD_SCALARS = tuple(n.std for n in NAV_ERRORS)
#: Errors of a solution against truth: position ENU (m), velocity ENU (m/s), attitude error angles
#: about E/N/U (arcsec).
ERROR_NAMES = tuple(n.recording for n in NAV_ERRORS)
#: Line colours (RGBA) of x / y / z (east / north / up) where one panel shows the three axes.
AXIS_COLOURS = (0xD62728FF, 0x2CA02CFF, 0x1F77B4FF)
POSITION_ERRORS = ERROR_NAMES[0:3]
VELOCITY_ERRORS = ERROR_NAMES[3:6]
ATTITUDE_ERRORS = ERROR_NAMES[6:9]
INTEGRITY_SCALARS = (
    "hpl_m",
    "vpl_m",
    "hal_m",
    "val_m",
    "alarm",
    "available",
    "detected",
    "h_error_m",
    "v_error_m",
)
HEALTH_SCALARS = (
    "queue_depth",
    "latency_p50_ms",
    "latency_p99_ms",
    "received",
    "accepted",
    "rejected_total",
    "dropped_overload",
)
BOUND_SERIES = ("+3σ", "-3σ")
BIAS_SERIES = ("x", "y", "z")
FLAG_STATES = ("ok", "flagged", "isolated")
#: Groups for family-specific scalars (``RerunSink.log_scalars``) that the blueprints know about.
GROUPS = {
    "imm": "model probabilities and mode-conditioned quantities (IMM)",
    "alignment": "lever arm and misalignment estimates (transfer alignment)",
    "underwater": "DVL / USBL states (scale factor, misalignment, offsets)",
}

_BAD = re.compile(r"[^A-Za-z0-9_.\-]")


@lru_cache(maxsize=65536)
def part(name: str) -> str:
    """One path part: characters outside ``[A-Za-z0-9_.-]`` become ``_``; never empty."""
    s = _BAD.sub("_", str(name))
    return s if s else "_"


@lru_cache(maxsize=4096)
def _pipeline(pipeline: str) -> str:
    p = part(pipeline)
    if p in RESERVED_PIPELINE_NAMES:
        raise ValueError(f"pipeline name {pipeline!r} is reserved in the recording layout")
    return p


def vehicle_root(vehicle: str) -> str:
    return f"/{part(vehicle)}"


def truth(vehicle: str, leaf: str | None = None) -> str:
    base = f"/{part(vehicle)}/{TRUTH}"
    return base if leaf is None else f"{base}/{part(leaf)}"


def pipeline_root(vehicle: str, pipeline: str) -> str:
    return f"/{part(vehicle)}/{_pipeline(pipeline)}"


def solution(vehicle: str, pipeline: str, leaf: str | None = None) -> str:
    base = f"{pipeline_root(vehicle, pipeline)}/solution"
    return base if leaf is None else f"{base}/{part(leaf)}"


def solution_std(vehicle: str, pipeline: str, name: str | None = None) -> str:
    base = f"{solution(vehicle, pipeline)}/std"
    return base if name is None else f"{base}/{part(name)}"


def error(vehicle: str, pipeline: str, name: str | None = None) -> str:
    base = f"{pipeline_root(vehicle, pipeline)}/error"
    return base if name is None else f"{base}/{part(name)}"


def bound(vehicle: str, pipeline: str, name: str | None = None) -> str:
    base = f"{pipeline_root(vehicle, pipeline)}/bound"
    return base if name is None else f"{base}/{part(name)}"


def faults(
    vehicle: str,
    pipeline: str,
    subsystem: str | None = None,
    label: str | None = None,
    leaf: str | None = None,
) -> str:
    """``.../faults[/{subsystem}[/{label}[/{leaf}]]]``; leaf is statistic, threshold or flagged."""
    p = f"{pipeline_root(vehicle, pipeline)}/faults"
    for x in (subsystem, label, leaf):
        if x is None:
            break
        p = f"{p}/{part(x)}"
    return p


#: leaves of an innovation window (``RerunSink.log_innovations``): the mean of the squared
#: standardised innovations r^2 = nu^2 / S (chi-square(1) per row, mean 1 for a consistent filter)
#: over the rows used since the last recorded window, and their number; per sensor, the rows the
#: gate refused in the window
INNOVATION_LEAVES = ("r2_mean", "count")
INNOVATIONS_REFUSED = "refused"


def innovations(
    vehicle: str,
    pipeline: str,
    sensor: str | None = None,
    label: str | None = None,
    leaf: str | None = None,
) -> str:
    """``.../innovations[/{kind}/{sensor_id}[/{label}[/{leaf}]]]``; ``sensor`` is the stream key
    ``kind/sensor_id`` (e.g. ``gnss_fix/rx``, two path parts), label a row (pos_e, vel_u, ...),
    leaf r2_mean or count; ``label`` ``refused`` (no leaf): the rows refused in the window."""
    p = f"{pipeline_root(vehicle, pipeline)}/innovations"
    if sensor is None:
        return p
    kind, _, sid = sensor.partition("/")
    p = f"{p}/{part(kind)}/{part(sid or '_')}"
    for x in (label, leaf):
        if x is None:
            break
        p = f"{p}/{part(x)}"
    return p


def reconfiguration(vehicle: str, pipeline: str) -> str:
    """``.../faults/reconfiguration``: text events "excluded: <subsystem>" / "rejoined: <subsystem>"."""
    return f"{pipeline_root(vehicle, pipeline)}/faults/reconfiguration"


def filter_state(vehicle: str, pipeline: str, name: str | None = None, leaf: str | None = None) -> str:
    """``.../states[/{name}[/{value|std}]]``: private filter states (DVL offset, scale factor)."""
    p = f"{pipeline_root(vehicle, pipeline)}/states"
    if name is not None:
        p = f"{p}/{part(name)}"
        if leaf is not None:
            p = f"{p}/{part(leaf)}"
    return p


def sharing(vehicle: str, pipeline: str, local: str | None = None, state: int | str | None = None) -> str:
    p = f"{pipeline_root(vehicle, pipeline)}/sharing"
    if local is not None:
        p = f"{p}/{part(local)}"
        if state is not None:
            p = f"{p}/{part(str(state))}"
    return p


def integrity(vehicle: str, pipeline: str, leaf: str | None = None) -> str:
    base = f"{pipeline_root(vehicle, pipeline)}/integrity"
    return base if leaf is None else f"{base}/{part(leaf)}"


def integrity_sat(
    vehicle: str, pipeline: str, sat_id: str | None = None, leaf: str | None = None, vertical: bool = False
) -> str:
    p = f"{integrity(vehicle, pipeline)}/{'sat_v' if vertical else 'sat'}"
    if sat_id is not None:
        p = f"{p}/{part(sat_id)}"
        if leaf is not None:
            p = f"{p}/{part(leaf)}"
    return p


def integrity_events(vehicle: str, pipeline: str) -> str:
    return integrity(vehicle, pipeline, "events")


def stanford(vehicle: str, pipeline: str, axis: str | None = None) -> str:
    """``.../integrity/stanford[/{h|v|frame_h|frame_v}]``."""
    base = integrity(vehicle, pipeline, "stanford")
    return base if axis is None else f"{base}/{part(axis)}"


def group(vehicle: str, pipeline: str, group_name: str, name: str | None = None) -> str:
    base = f"{pipeline_root(vehicle, pipeline)}/{part(group_name)}"
    return base if name is None else f"{base}/{part(name)}"


def health(vehicle: str, leaf: str | None = None) -> str:
    base = f"/{part(vehicle)}/{SERVICE}/health"
    return base if leaf is None else f"{base}/{part(leaf)}"


def health_rejected(vehicle: str, reason: str) -> str:
    """The count of a vehicle's inputs refused for ``reason`` (Health ``rejected``)."""
    return f"{health(vehicle, 'rejected')}/{part(reason)}"


@dataclass(frozen=True)
class ParsedPath:
    """An entity path split into its layout parts.

    ``source`` is ``"truth"``, ``"service"`` or a pipeline name; ``rest`` the remaining parts.
    """

    vehicle: str
    source: str
    rest: tuple[str, ...]

    @property
    def is_pipeline(self) -> bool:
        return self.source not in RESERVED_PIPELINE_NAMES


def parse(entity_path: str) -> ParsedPath | None:
    """Split an entity path of this layout; None for paths outside it (``/__properties``...)."""
    parts = [p for p in entity_path.strip("/").split("/") if p]
    if len(parts) < 2 or parts[0].startswith("__"):
        return None
    return ParsedPath(parts[0], parts[1], tuple(parts[2:]))


def enu(vehicle: str, source: str) -> str:
    """ENU trajectory points of ``truth`` or a pipeline's solution (2D view, y = -north)."""
    return truth(vehicle, "enu") if source == TRUTH else solution(vehicle, source, "enu")


def enu_ellipse(vehicle: str, pipeline: str) -> str:
    return solution(vehicle, pipeline, "ellipse")


def enu_markers(vehicle: str, source: str) -> str:
    """Labelled markers on the ENU view: injected fault changes (truth), isolations and alarms."""
    return truth(vehicle, "markers") if source == TRUTH else f"{pipeline_root(vehicle, source)}/markers"


def input_fix(vehicle: str, sensor_id: str) -> str:
    """Raw GNSS fixes the service received, on the ENU view."""
    return f"/{part(vehicle)}/{SERVICE}/inputs/{part(sensor_id)}/enu"


_SLOW = re.compile(
    r"/(faults|fault_tests|innovations|sharing|std|health|states|imm|alignment\w*|underwater)/|/integrity/sat"
)


def is_slow_stream(entity_path: str) -> bool:
    """Diagnostic streams the sink may send less often (``slow_flush_interval_s``): fault tests,
    innovation windows, sharing coefficients, 1-sigma, health, private states, family groups,
    per-satellite tests."""
    return _SLOW.search(entity_path) is not None


#: Series names of the solution 1-sigma entities (legend: "<pipeline> 1σ east").
STD_LABELS = dict(
    zip(
        STD_SCALARS,
        (
            "1σ east",
            "1σ north",
            "1σ up",
            "1σ v east",
            "1σ v north",
            "1σ v up",
            "1σ roll",
            "1σ pitch",
            "1σ heading",
        ),
        strict=True,
    )
)
#: Legend names and colours (RGBA) of the integrity scalars: PL solid blue, error orange, limits red.
INTEGRITY_LABELS = {
    "hpl_m": "HPL",
    "vpl_m": "VPL",
    "hal_m": "HAL",
    "val_m": "VAL",
    "h_error_m": "horizontal error",
    "v_error_m": "vertical error",
    "excluded_count": "excluded satellites",
}
INTEGRITY_COLORS = {
    "hpl_m": 0x1F77B4FF,
    "vpl_m": 0x1F77B4FF,
    "hal_m": 0xD62728FF,
    "val_m": 0xD62728FF,
    "h_error_m": 0xFF7F0EFF,
    "v_error_m": 0xFF7F0EFF,
    "excluded_count": 0x7F7F7FFF,
}


def fault_test(vehicle: str, pipeline: str, subsystem: str | None = None, label: str | None = None) -> str:
    """``.../fault_tests[/{subsystem}/{label}]``: test statistic / threshold (Rerun view filters
    only take ``/**`` at the end, so the normalised tests have their own root)."""
    base = f"{pipeline_root(vehicle, pipeline)}/fault_tests"
    return base if subsystem is None else f"{base}/{part(subsystem)}/{part(label or '_')}"


def isolation(vehicle: str, pipeline: str, subsystem: str | None = None) -> str:
    """``.../isolation[/{subsystem}]``: in use / isolated lanes, one row per change."""
    base = f"{pipeline_root(vehicle, pipeline)}/isolation"
    return base if subsystem is None else f"{base}/{part(subsystem)}"


def integrity_sat_ratio(vehicle: str, pipeline: str, sat_id: str | None = None) -> str:
    base = integrity(vehicle, pipeline, "sat_ratio")
    return base if sat_id is None else f"{base}/{part(sat_id)}"


def state_name(index: int, n: int) -> str:
    """Name of entry ``index`` of an ``n``-long sharing / covariance vector: the INS error-state
    labels (dp_e ... nab_z) for the 15 common states, ``x<index>`` beyond."""
    return STATE_LABELS[index] if index < len(STATE_LABELS) else f"x{index}"


# --- Stanford-diagram regions (integrity) ---------------------------------------------------------
STANFORD_REGIONS = ("normal", "mi", "hmi", "alarm", "unavailable", "unavailable_mi")


def stanford_region(error_m: float, pl_m: float, al_m: float | None, alarm: bool) -> str:
    """Classify one epoch on the Stanford diagram (error on x, protection level on y).

    * ``unavailable``: PL > AL (the operation is not available); ``unavailable_mi`` if also err > PL;
    * ``normal``: err <= PL <= AL;
    * ``mi`` (misleading information): PL < err <= AL;
    * ``hmi`` (hazardously misleading): PL <= AL < err and no alarm was raised;
    * ``alarm``: PL <= AL < err with an alarm raised (a detected, hence not hazardous, failure).

    Without an alert limit (``al_m`` None, e.g. no VAL) only normal / mi are distinguishable.
    """
    al = math.inf if al_m is None else al_m
    if pl_m > al:
        return "unavailable_mi" if error_m > pl_m else "unavailable"
    if error_m <= pl_m:
        return "normal"
    if error_m <= al:
        return "mi"
    return "alarm" if alarm else "hmi"


# --- Stanford-diagram drawing (log10 axes, metres) --------------------------------------------------
#: Smallest error / PL drawn (m): smaller values sit on the diagram's lower edge.
STANFORD_FLOOR_M = 0.01
_GRID, _DIAG, _LIMIT, _TEXT = 0xD0D0D0FF, 0x555555FF, 0xD62728FF, 0x333333FF


def stanford_xy(error_m: float, pl_m: float) -> tuple[float, float]:
    """Point of one epoch: x = log10 |error|, y = -log10 PL (2D views point y down: PL grows up)."""
    x = math.log10(max(abs(error_m), STANFORD_FLOOR_M))
    y = -math.log10(max(pl_m, STANFORD_FLOOR_M))
    return x, y


def _metres(decade: int) -> str:
    """Short tick label of a decade of metres: 1cm, 10cm, 1m, 10m, 100m, 1km, 10km."""
    if decade >= 3:
        return f"{10 ** (decade - 3)}km"
    v = 10.0**decade
    return f"{v:g}m" if v >= 1 else f"{v * 100:g}cm"


def stanford_frame(
    lo: int, hi: int, al_m: float | None, al_name: str | None
) -> tuple[list, list[int], tuple[list, list[str], list[int]]]:
    """Static frame of a log-log Stanford diagram spanning decades ``lo..hi``: (strips, colours,
    (label positions, label texts, label colours)). Grid lines at each decade, the PL = error
    diagonal, the alert-limit lines and the region names (normal / MI / HMI / unavailable)."""
    strips: list[list[list[float]]] = []
    colors: list[int] = []
    pos: list[list[float]] = []
    texts: list[str] = []
    tcol: list[int] = []
    # tick labels: every decade up to 5 of them, every other one beyond (narrow panels); the x
    # axis starts one decade in, where the y axis's lowest label would otherwise overlap it
    step = 1 if hi - lo <= 5 else 2
    for d in range(lo, hi + 1):
        strips += [[[d, -lo], [d, -hi]], [[lo, -d], [hi, -d]]]
        colors += [_GRID, _GRID]
        if (d - lo) % step == 0 or d == hi:
            if d > lo:
                pos.append([d, -lo + 0.12])
                texts.append(_metres(d))
                tcol.append(_TEXT)
            pos.append([lo - 0.12, -d])
            texts.append(_metres(d))
            tcol.append(_TEXT)
    strips.append([[lo, -lo], [hi, -hi]])
    colors.append(_DIAG)
    pos.append([(lo + hi) / 2 + 0.35, -(lo + hi) / 2 + 0.35])
    texts.append("PL = error")
    tcol.append(_DIAG)
    a = None if al_m is None or al_m <= 0 else math.log10(al_m)
    top = hi if a is None else a
    pos += [
        [lo + 0.25 * (top - lo), -(lo + 0.75 * (top - lo))],
        [lo + 0.75 * (top - lo), -(lo + 0.25 * (top - lo))],
    ]
    texts += ["normal", "MI (error > PL)"]
    tcol += [0x2CA02CFF, 0xB8860BFF]
    if a is not None and a < hi:
        strips += [[[a, -lo], [a, -hi]], [[lo, -a], [hi, -a]]]
        colors += [_LIMIT, _LIMIT]
        pos += [[a, -hi - 0.1], [hi + 0.1, -a]]
        texts += [f"{al_name} {al_m:.0f} m", f"{al_name}"]
        tcol += [_LIMIT, _LIMIT]
        pos += [[(a + hi) / 2, -(lo + 0.5 * (a - lo))], [lo + 0.35 * (a - lo), -(a + hi) / 2]]
        texts += ["HMI (error > AL, no alarm)", "unavailable (PL > AL)"]
        tcol += [_LIMIT, 0x7F7F7FFF]
    return strips, colors, (pos, texts, tcol)
