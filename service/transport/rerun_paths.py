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
    /{vehicle}/{pipeline}/integrity/{hpl_m, ...}            Scalars (INTEGRITY_SCALARS; flags as 0/1)
    /{vehicle}/{pipeline}/integrity/excluded_count          Scalars
    /{vehicle}/{pipeline}/integrity/sat/{id}/{statistic_m, threshold_m}       Scalars
    /{vehicle}/{pipeline}/integrity/sat_v/{id}/{statistic_m, threshold_m}     Scalars (vertical, if used)
    /{vehicle}/{pipeline}/integrity/events                  TextLog (detection, alarm, exclusion, ...)
    /{vehicle}/{pipeline}/integrity/stanford/{h, v}         Points2D (x = error, y = -PL), /frame static
    /{vehicle}/{pipeline}/{group}/{name}                    Scalars from ``log_scalars`` (GROUPS)
    /{vehicle}/{pipeline}/imm/{prob, downweighted}/{model}, /rejected_rows     Scalars (IMM)
    /{vehicle}/service/health/{queue_depth, ...}            Scalars (HEALTH_SCALARS)

Timeline ``sensor_time``: a duration timeline holding ``t`` (seconds of GPS time) in nanoseconds.
Path parts are restricted to ``[A-Za-z0-9_.-]`` (the Zenoh key chunk alphabet of ``keys.py``); any
other character is replaced by ``_`` so that every path parses the same way in the reader.
"""

from __future__ import annotations

import math
import re
from dataclasses import dataclass
from functools import lru_cache

from service.ins.error_model import NAV_ERRORS

TIMELINE = "sensor_time"

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
