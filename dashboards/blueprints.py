"""Rerun blueprints (viewer layouts) of fednav recordings, per vehicle and pipeline family.

Entity paths come from ``service.transport.rerun_paths`` (dependency direction: dashboards ->
service). The service embeds a blueprint in each recording through ``blueprint_factory``::

    sink = RerunSink(path, blueprint=blueprint_factory({"fed": "federated", "mhss": "integrity"}))

so that ``rerun file.rrd`` opens ready to read. Tabs of one vehicle:

* Map: truth and every solution (points and decimated tracks) on a map;
* Position / Velocity / Attitude error: all pipelines compared, then per pipeline E/N/U (or about
  E/N/U) errors with their ±3σ covariance bounds;
* Navigation: truth vs solutions (9 states), status lanes, injected faults log;
* Covariance: 1σ of each state per pipeline, estimated sensor biases;
* per family: federated / loosely coupled -> fault test statistics vs thresholds, flags per
  observation, sharing coefficients; integrity -> HPL/VPL vs HAL/VAL vs true error, alarms, per
  satellite statistics vs thresholds, events log, Stanford diagrams; imm -> model probabilities;
  transfer alignment -> lever arm and misalignment; underwater -> DVL/USBL states;
* Health: queue depth, latency, message counters.

Built with the rerun-sdk 0.41 ``rerun.blueprint`` API.
"""

from __future__ import annotations

import logging
from collections.abc import Callable, Mapping, Sequence

import rerun.blueprint as rrb

from service.transport import rerun_paths as paths

log = logging.getLogger(__name__)

FAMILIES = ("loosely_coupled", "federated", "integrity", "imm", "transfer_alignment", "underwater")
#: Pipeline kinds of the service configuration that map onto a family's dashboard.
FAMILY_ALIASES = {
    "centralized": "loosely_coupled",
    "tightly_coupled": "integrity",
    "imm_tightly_coupled": "imm",
}

_AXES = {
    "Position error": (paths.POSITION_ERRORS, ("east (m)", "north (m)", "up (m)")),
    "Velocity error": (paths.VELOCITY_ERRORS, ("east (m/s)", "north (m/s)", "up (m/s)")),
    "Attitude error": (
        paths.ATTITUDE_ERRORS,
        ("about east (arcsec)", "about north (arcsec)", "about up (arcsec)"),
    ),
}
_STATE_TITLES = (
    "latitude (deg)",
    "longitude (deg)",
    "height (m)",
    "velocity east (m/s)",
    "velocity north (m/s)",
    "velocity up (m/s)",
    "roll (deg)",
    "pitch (deg)",
    "heading (deg)",
)
_STD_TITLES = (
    "1σ east (m)",
    "1σ north (m)",
    "1σ up (m)",
    "1σ v east (m/s)",
    "1σ v north (m/s)",
    "1σ v up (m/s)",
    "1σ roll (deg)",
    "1σ pitch (deg)",
    "1σ heading (deg)",
)
_GROUP_OF_FAMILY = {
    "imm": ("imm", "IMM model probabilities"),
    "transfer_alignment": ("alignment", "lever arm and misalignment"),
    "underwater": ("underwater", "DVL / USBL states"),
}


def family_of(kind: str) -> str:
    """Dashboard family of a pipeline family or configuration kind (``FAMILY_ALIASES``).

    An unknown kind gets the loosely-coupled dashboards (errors, faults) and a logged warning: a
    new pipeline kind must not stop the service from recording.
    """
    if kind in FAMILIES:
        return kind
    if kind in FAMILY_ALIASES:
        return FAMILY_ALIASES[kind]
    log.warning("blueprint: unknown pipeline family %r, using the loosely_coupled dashboards", kind)
    return "loosely_coupled"


def _check(pipelines: Mapping[str, str]) -> None:
    for name in pipelines:
        paths.pipeline_root("v", name)  # raises on reserved names (truth, service)


def _ts(name: str, contents: list[str] | str, origin: str = "/") -> rrb.TimeSeriesView:
    return rrb.TimeSeriesView(name=name, origin=origin, contents=contents)


def _map_tab(v: str, pipelines: Sequence[str]) -> rrb.MapView:
    contents = [paths.truth(v, "position"), paths.truth(v, "track")]
    for p in pipelines:
        contents += [paths.solution(v, p, "position"), paths.solution(v, p, "track")]
    return rrb.MapView(name="Map", origin=paths.vehicle_root(v), contents=contents)


def _error_tab(v: str, pipelines: Sequence[str], title: str) -> rrb.Horizontal:
    names, labels = _AXES[title]
    columns: list[rrb.Vertical] = []
    if len(pipelines) > 1:
        columns.append(
            rrb.Vertical(
                *[
                    _ts(f"all: {lab}", [paths.error(v, p, n) for p in pipelines])
                    for n, lab in zip(names, labels, strict=True)
                ],
                name="all pipelines",
            )
        )
    for p in pipelines:
        columns.append(
            rrb.Vertical(
                *[
                    _ts(f"{p}: {lab} ±3σ", [paths.error(v, p, n), paths.bound(v, p, n)])
                    for n, lab in zip(names, labels, strict=True)
                ],
                name=p,
            )
        )
    return rrb.Horizontal(*columns, name=title)


def _navigation_tab(v: str, pipelines: Sequence[str]) -> rrb.Vertical:
    grid = rrb.Grid(
        *[
            _ts(title, [paths.truth(v, n)] + [paths.solution(v, p, n) for p in pipelines])
            for n, title in zip(paths.SOLUTION_SCALARS, _STATE_TITLES, strict=True)
        ],
        grid_columns=3,
    )
    status = rrb.StateTimelineView(
        name="status",
        origin=paths.vehicle_root(v),
        contents=[paths.solution(v, p, "status") for p in pipelines],
    )
    truth_faults = rrb.TextLogView(
        name="injected faults (truth)", origin=paths.vehicle_root(v), contents=[paths.truth(v, "faults")]
    )
    return rrb.Vertical(grid, rrb.Horizontal(status, truth_faults), row_shares=[4, 1], name="Navigation")


def _covariance_tab(v: str, pipelines: Sequence[str]) -> rrb.Vertical:
    grid = rrb.Grid(
        *[
            _ts(title, [paths.solution_std(v, p, n) for p in pipelines])
            for n, title in zip(paths.STD_SCALARS, _STD_TITLES, strict=True)
        ],
        grid_columns=3,
    )
    biases = rrb.Horizontal(
        _ts("gyro bias (deg/h)", [paths.solution(v, p, "gyro_bias_dph") for p in pipelines]),
        _ts("accelerometer bias (µg)", [paths.solution(v, p, "accel_bias_ug") for p in pipelines]),
    )
    return rrb.Vertical(grid, biases, row_shares=[3, 1], name="Covariance")


def _faults_tab(v: str, p: str, with_sharing: bool) -> rrb.Vertical:
    views: list[rrb.View] = [
        _ts(f"{p}: test statistics vs thresholds", f"{paths.faults(v, p)}/**"),
        rrb.StateTimelineView(
            name=f"{p}: fault flags per observation", origin=paths.faults(v, p), contents="$origin/**"
        ),
    ]
    if with_sharing:
        views.append(_ts(f"{p}: sharing coefficients", f"{paths.sharing(v, p)}/**"))
    return rrb.Vertical(*views, name=f"{p}: faults")


def _integrity_tab(v: str, p: str) -> rrb.Grid:
    def i(leaf: str) -> str:
        return paths.integrity(v, p, leaf)

    everything = rrb.VisibleTimeRange(
        paths.TIMELINE, start=rrb.TimeRangeBoundary.infinite(), end=rrb.TimeRangeBoundary.cursor_relative()
    )
    return rrb.Grid(
        _ts(f"{p}: HPL vs HAL vs horizontal error (m)", [i("hpl_m"), i("hal_m"), i("h_error_m")]),
        _ts(f"{p}: VPL vs VAL vs vertical error (m)", [i("vpl_m"), i("val_m"), i("v_error_m")]),
        _ts(
            f"{p}: alarm / available / detected / excluded",
            [i("alarm"), i("available"), i("detected"), i("excluded_count")],
        ),
        _ts(
            f"{p}: per-satellite statistic vs threshold (m)",
            [f"{paths.integrity_sat(v, p)}/**", f"{paths.integrity_sat(v, p, vertical=True)}/**"],
        ),
        rrb.TextLogView(
            name=f"{p}: integrity events",
            origin=paths.integrity(v, p),
            contents=[paths.integrity_events(v, p)],
        ),
        rrb.Spatial2DView(
            name=f"{p}: Stanford (x: |error|, y: -HPL)",
            origin=paths.stanford(v, p),
            contents=[paths.stanford(v, p, "h"), paths.stanford(v, p, "frame_h")],
            time_ranges=everything,
        ),
        rrb.Spatial2DView(
            name=f"{p}: Stanford (x: |error|, y: -VPL)",
            origin=paths.stanford(v, p),
            contents=[paths.stanford(v, p, "v"), paths.stanford(v, p, "frame_v")],
            time_ranges=everything,
        ),
        grid_columns=2,
        name=f"{p}: integrity",
    )


def _underwater_tab(v: str, p: str) -> rrb.Grid:
    """Seed 004: USBL/DVL tests vs thresholds and flags, reconfiguration events, sharing
    coefficients, DVL offset and scale-factor estimates with their 1-sigma."""

    def st(prefix: str) -> list[str]:
        return [f"{paths.filter_state(v, p)}/{prefix}_{a}/**" for a in "xyz"]

    return rrb.Grid(
        _ts(f"{p}: USBL / DVL test statistics vs thresholds", f"{paths.faults(v, p)}/**"),
        rrb.StateTimelineView(
            name=f"{p}: rows in use / flagged", origin=paths.faults(v, p), contents="$origin/**"
        ),
        rrb.TextLogView(
            name=f"{p}: reconfiguration",
            origin=paths.pipeline_root(v, p),
            contents=[paths.reconfiguration(v, p)],
        ),
        _ts(f"{p}: sharing coefficients", f"{paths.sharing(v, p)}/**"),
        _ts(f"{p}: DVL offset (m/s) and 1σ", st("dvl_offset")),
        _ts(f"{p}: DVL scale factor and 1σ", st("dvl_scale")),
        grid_columns=2,
        name=f"{p}: underwater",
    )


def _imm_tab(v: str, p: str) -> rrb.Grid:
    """IMM (He, Nie, Wu 2011): model probabilities beside the position error and the injected
    faults (truth), and the rows each model down-weights."""
    imm = paths.group(v, p, "imm")
    return rrb.Grid(
        _ts(f"{p}: model probabilities", f"{imm}/prob/**"),
        _ts(f"{p}: position error (m)", [paths.error(v, p, n) for n in paths.POSITION_ERRORS]),
        _ts(
            f"{p}: down-weighted rows per model / gate rejections",
            [f"{imm}/downweighted/**", f"{imm}/rejected_rows"],
        ),
        rrb.Vertical(
            _ts("injected fault channels (truth)", [paths.truth(v, "fault_channels")]),
            rrb.TextLogView(
                name="injected faults (truth)",
                origin=paths.vehicle_root(v),
                contents=[paths.truth(v, "faults")],
            ),
        ),
        grid_columns=2,
        name=f"{p}: IMM",
    )


def _group_tab(v: str, p: str, family: str) -> rrb.TimeSeriesView:
    group, title = _GROUP_OF_FAMILY[family]
    return _ts(f"{p}: {title}", f"{paths.group(v, p, group)}/**")


def _alignment_tab(v: str, p: str) -> rrb.Grid:
    """Transfer alignment (seed 002): per-node errors against truth with +-3 sigma bounds
    (misalignment and flexure in arcmin, lever arm in m), estimates, adaptive R and fading."""
    return rrb.Grid(
        _ts(f"{p}: errors vs truth, ±3σ", f"{paths.group(v, p, 'alignment_error')}/**"),
        _ts(f"{p}: lever arm, flexure, mount estimates", f"{paths.group(v, p, 'alignment')}/**"),
        _ts(f"{p}: adaptive R (1σ), fading factor, NIS", f"{paths.group(v, p, 'alignment_adaptive')}/**"),
        grid_columns=2,
        name=f"{p}: alignment",
    )


def _health_tab(v: str) -> rrb.Grid:
    def h(leaf: str) -> str:
        return paths.health(v, leaf)

    return rrb.Grid(
        _ts("queue depth", [h("queue_depth")]),
        _ts("latency intake -> publish (ms)", [h("latency_p50_ms"), h("latency_p99_ms")]),
        _ts("messages received / accepted", [h("received"), h("accepted")]),
        _ts("messages rejected / dropped (overload)", [h("rejected_total"), h("dropped_overload")]),
        grid_columns=2,
        name="Health",
    )


def vehicle_tabs(vehicle: str, pipelines: Mapping[str, str]) -> rrb.Tabs:
    """The tab container of one vehicle (see the module docstring for the tabs)."""
    _check(pipelines)
    names = list(pipelines)
    tabs: list[rrb.Container | rrb.View] = [_map_tab(vehicle, names)]
    tabs += [_error_tab(vehicle, names, title) for title in _AXES]
    tabs += [_navigation_tab(vehicle, names), _covariance_tab(vehicle, names)]
    for p, kind in pipelines.items():
        family = family_of(kind)
        if family in ("federated", "loosely_coupled"):
            tabs.append(_faults_tab(vehicle, p, with_sharing=family == "federated"))
        elif family == "integrity":
            tabs.append(_integrity_tab(vehicle, p))
        elif family == "transfer_alignment":
            tabs.append(_alignment_tab(vehicle, p))
        elif family == "underwater":
            tabs.append(_underwater_tab(vehicle, p))
        elif family == "imm":
            tabs.append(_imm_tab(vehicle, p))
        else:
            tabs.append(_group_tab(vehicle, p, family))
    tabs.append(_health_tab(vehicle))
    return rrb.Tabs(*tabs, name=vehicle, active_tab=0)


def build_blueprint(vehicle: str, pipelines: Mapping[str, str]) -> rrb.Blueprint:
    """Blueprint of one vehicle.

    Parameters
    ----------
    vehicle
        Vehicle name (as in the Zenoh keys).
    pipelines
        Pipeline name -> family, one of ``FAMILIES`` (or a configuration kind of ``FAMILY_ALIASES``).
    """
    return rrb.Blueprint(vehicle_tabs(vehicle, pipelines), auto_views=False, auto_layout=False)


def build_fleet_blueprint(vehicles: Sequence[str], pipelines: Mapping[str, str]) -> rrb.Blueprint:
    """Blueprint of several vehicles running the same pipelines: one top-level tab per vehicle."""
    if not vehicles:
        _check(pipelines)
        return rrb.Blueprint(auto_views=True, auto_layout=True)
    if len(vehicles) == 1:
        return build_blueprint(vehicles[0], pipelines)
    return rrb.Blueprint(
        rrb.Tabs(*[vehicle_tabs(v, pipelines) for v in vehicles], active_tab=0),
        auto_views=False,
        auto_layout=False,
    )


def blueprint_factory(pipelines: Mapping[str, str]) -> Callable[[Sequence[str]], rrb.Blueprint]:
    """The callable to pass as ``RerunSink(blueprint=...)``: vehicles seen so far -> blueprint.

    The pipeline families are checked now, so a bad configuration fails at start-up.
    """
    frozen = dict(pipelines)
    _check(frozen)

    def factory(vehicles: Sequence[str]) -> rrb.Blueprint:
        return build_fleet_blueprint(list(vehicles), frozen)

    return factory
