"""Rerun blueprints (viewer layouts) of fednav recordings, per vehicle and pipeline family.

Entity paths come from ``service.transport.rerun_paths`` (dependency direction: dashboards ->
service). The service embeds a blueprint in each recording through ``blueprint_factory``::

    sink = RerunSink(path, blueprint=blueprint_factory({"fed": "federated", "mhss": "integrity"}))

so that ``rerun file.rrd`` opens ready to read, on the ``mission_time`` timeline, every time
series showing the whole run. One tab per question, pipelines compared inside a tab:

* Overview (opening tab): ENU trajectory, east error of every pipeline, subsystem isolation lanes,
  HPL vs horizontal error, pipeline status;
* Trajectory: offline 2D ENU view (truth, solutions, raw fixes, 3-sigma ellipses, fault / isolation /
  alarm markers) beside the map (online tiles) and the injected-faults log;
* Errors: all pipelines compared (3x3), then per pipeline with ±3σ bounds;
* Integrity (MHSS): HPL / VPL with the true error on their own axes, HAL / VAL, availability and
  alarm lanes, per-satellite statistic / threshold, log-log Stanford diagrams, events;
* Faults & sharing: isolation lanes of every fault-tolerant pipeline, injected faults; per pipeline
  normalised test statistics, flags per observation, named sharing coefficients;
* family tabs: IMM (seed 003), alignment (seed 002), underwater (seed 004);
* States & covariance: truth vs solutions, 1σ, biases;
* Health: status lanes, queue depth, latency, message counters.

Rerun view filters take ``/**`` only at the end of a path: every panel's data has its own root.
Built with the rerun-sdk 0.41 ``rerun.blueprint`` API.
"""

from __future__ import annotations

import logging
from collections.abc import Callable, Mapping, Sequence

import rerun as rr
import rerun.blueprint as rrb
import rerun.encodings as rre

from fednav.service.transport import rerun_paths as paths

log = logging.getLogger(__name__)

FAMILIES = ("loosely_coupled", "federated", "integrity", "imm", "transfer_alignment", "underwater", "plain")
#: "plain": an estimator that publishes no fault tests (e.g. a centralised comparator without fault
#: handling, ``config.recording_kinds``): errors, states and health, no Faults panels.
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


def features_of(kind: str) -> tuple[str, ...]:
    """The dashboard details a kind carries after a colon (``config.recording_kinds``), in order:
    underwater features (``"underwater:centralized,untested"`` -> ("centralized", "untested")),
    the node ids of a transfer-alignment pipeline (``"transfer_alignment:wing1,wing2"``)."""
    _, _, rest = kind.partition(":")
    return tuple(f for f in rest.split(",") if f)


def family_of(kind: str) -> str:
    """Dashboard family of a pipeline family or configuration kind (``FAMILY_ALIASES``); the
    features after a colon (``features_of``) do not change the family.

    An unknown kind gets the loosely-coupled dashboards (errors, faults) and a logged warning: a
    new pipeline kind must not stop the service from recording.
    """
    kind = kind.partition(":")[0]
    if kind in FAMILIES:
        return kind
    if kind in FAMILY_ALIASES:
        return FAMILY_ALIASES[kind]
    log.warning("blueprint: unknown pipeline family %r, using the loosely_coupled dashboards", kind)
    return "loosely_coupled"


def _check(pipelines: Mapping[str, str]) -> None:
    for name in pipelines:
        paths.pipeline_root("v", name)  # raises on reserved names (truth, service)


#: Every time series and 2D history opens on the whole run, on each of the three timelines.
WHOLE_RUN = [
    rrb.VisibleTimeRange(tl, start=rrb.TimeRangeBoundary.infinite(), end=rrb.TimeRangeBoundary.infinite())
    for tl in (paths.MISSION_TIMELINE, paths.TIMELINE, paths.UTC_TIMELINE)
]
#: The time axis of every plot spans the whole run (not a window around the time cursor).
WHOLE_RUN_AXIS = rrb.TimeAxis(
    link="Independent",
    view_range=rre.TimeRange(start=rrb.TimeRangeBoundary.infinite(), end=rrb.TimeRangeBoundary.infinite()),
)
#: Histories drawn in 2D views (trajectory, Stanford points): everything up to the time cursor.
UP_TO_CURSOR = [
    rrb.VisibleTimeRange(
        tl, start=rrb.TimeRangeBoundary.infinite(), end=rrb.TimeRangeBoundary.cursor_relative()
    )
    for tl in (paths.MISSION_TIMELINE, paths.TIMELINE, paths.UTC_TIMELINE)
]


def _ts(name: str, contents: list[str] | str, origin: str = "/", legend: bool = True) -> rrb.TimeSeriesView:
    return rrb.TimeSeriesView(
        name=name,
        origin=origin,
        contents=contents,
        time_ranges=WHOLE_RUN,
        axis_x=WHOLE_RUN_AXIS,
        plot_legend=rrb.PlotLegend(corner="LeftTop", visible=legend),
    )


def _named(name: str, series: Mapping[str, str]) -> rrb.TimeSeriesView:
    """A time series view whose lines are named here (path -> label, one colour per line), not by
    the recording's pipeline style."""
    overrides = {
        path: rr.SeriesLines.from_fields(names=[label], colors=[paths.AXIS_COLOURS[i % 3]])
        for i, (path, label) in enumerate(series.items())
    }
    return rrb.TimeSeriesView(
        name=name,
        origin="/",
        contents=list(series),
        overrides=overrides,
        time_ranges=WHOLE_RUN,
        axis_x=WHOLE_RUN_AXIS,
        plot_legend=rrb.PlotLegend(corner="LeftTop", visible=True),
    )


def _states(name: str, origin: str, contents: list[str] | str) -> rrb.StateTimelineView:
    return rrb.StateTimelineView(name=name, origin=origin, contents=contents, time_view=WHOLE_RUN_AXIS)


def _map_view(v: str, pipelines: Sequence[str]) -> rrb.MapView:
    contents = [paths.truth(v, "position"), paths.truth(v, "track")]
    for p in pipelines:
        contents += [paths.solution(v, p, "position"), paths.solution(v, p, "track")]
    return rrb.MapView(name="Map (online tiles)", origin=paths.vehicle_root(v), contents=contents)


def _enu_view(
    v: str, pipelines: Sequence[str], name: str = "Trajectory, ENU (m): x east, y = -north"
) -> rrb.Spatial2DView:
    contents = [
        paths.enu(v, paths.TRUTH),
        paths.enu_markers(v, paths.TRUTH),
        f"/{paths.part(v)}/service/inputs/**",
    ]
    for p in pipelines:
        contents += [paths.enu(v, p), paths.enu_ellipse(v, p), paths.enu_markers(v, p)]
    return rrb.Spatial2DView(
        name=name, origin=paths.vehicle_root(v), contents=contents, time_ranges=UP_TO_CURSOR
    )


def _trajectory_tab(v: str, pipelines: Sequence[str]) -> rrb.Horizontal:
    """Offline ENU view (truth black, solutions in pipeline colours, raw fixes grey, 3-sigma
    ellipses, fault / isolation / alarm markers) beside the map and the injected-fault log."""
    side = rrb.Vertical(
        _map_view(v, pipelines),
        rrb.TextLogView(
            name="injected faults (truth)", origin=paths.vehicle_root(v), contents=[paths.truth(v, "faults")]
        ),
        row_shares=[3, 1],
    )
    return rrb.Horizontal(_enu_view(v, pipelines), side, column_shares=[3, 2], name="Trajectory")


def _error_grid(v: str, pipelines: Sequence[str], with_bounds: bool) -> rrb.Grid:
    views = []
    for title, (names, labels) in _AXES.items():
        what = title.split()[0].lower()
        for n, lab in zip(names, labels, strict=True):
            contents = [paths.error(v, p, n) for p in pipelines]
            if with_bounds:
                contents += [paths.bound(v, p, n) for p in pipelines]
            views.append(_ts(f"{what} {lab}{' ±3σ' if with_bounds else ''}", contents))
    return rrb.Grid(*views, grid_columns=3)


def _errors_tab(v: str, pipelines: Sequence[str]) -> rrb.Tabs:
    """Errors against truth: every pipeline compared, then each pipeline with its ±3σ bounds."""
    inner: list[rrb.Container] = []
    if len(pipelines) > 1:
        inner.append(rrb.Vertical(_error_grid(v, pipelines, False), name="all pipelines"))
    for p in pipelines:
        inner.append(rrb.Vertical(_error_grid(v, [p], True), name=f"{p} ±3σ"))
    return rrb.Tabs(*inner, name="Errors", active_tab=0)


def _states_tab(v: str, pipelines: Sequence[str]) -> rrb.Tabs:
    """Truth vs solutions (9 states) and each state's 1-sigma (named series), biases."""
    nav = rrb.Grid(
        *[
            _ts(title, [paths.truth(v, n)] + [paths.solution(v, p, n) for p in pipelines])
            for n, title in zip(paths.SOLUTION_SCALARS, _STATE_TITLES, strict=True)
        ],
        grid_columns=3,
        name="navigation states",
    )
    cov = rrb.Vertical(
        rrb.Grid(
            *[
                _ts(title, [paths.solution_std(v, p, n) for p in pipelines])
                for n, title in zip(paths.STD_SCALARS, _STD_TITLES, strict=True)
            ],
            grid_columns=3,
        ),
        rrb.Horizontal(
            _ts("gyro bias (deg/h)", [paths.solution(v, p, "gyro_bias_dph") for p in pipelines]),
            _ts("accelerometer bias (µg)", [paths.solution(v, p, "accel_bias_ug") for p in pipelines]),
        ),
        row_shares=[3, 1],
        name="covariance (1σ) and biases",
    )
    return rrb.Tabs(nav, cov, name="States & covariance", active_tab=0)


def _isolation_view(v: str, fault_pipes: Sequence[str]) -> rrb.StateTimelineView:
    return _states(
        "subsystem in use / isolated, per pipeline",
        paths.vehicle_root(v),
        [f"{paths.isolation(v, p)}/**" for p in fault_pipes],
    )


def _has_sharing(kind: str) -> bool:
    """Federated pipelines publish sharing coefficients; a centralised underwater one does not."""
    return family_of(kind) in ("federated", "underwater") and "centralized" not in features_of(kind)


def _reconfiguration_log(v: str, p: str) -> rrb.TextLogView:
    """Seed 004: locals (or the centralised filter's sensor rows) leaving and rejoining the fusion,
    beside the injected faults (truth) that should cause them."""
    return rrb.TextLogView(
        name=f"{p}: reconfiguration, injected faults (truth)",
        origin=paths.vehicle_root(v),
        contents=[paths.reconfiguration(v, p), paths.truth(v, "faults")],
    )


def _faults_detail(v: str, p: str, kind: str) -> rrb.Grid:
    views: list[rrb.View] = [
        _ts(f"{p}: test statistic / threshold (flag above 1)", f"{paths.fault_test(v, p)}/**"),
        _states(f"{p}: flags per observation (ok / flagged / isolated)", paths.faults(v, p), "$origin/**"),
    ]
    if _has_sharing(kind):
        views.append(_ts(f"{p}: sharing coefficients (local state)", f"{paths.sharing(v, p)}/**"))
    if family_of(kind) == "underwater" and "untested" not in features_of(kind):
        views.append(_reconfiguration_log(v, p))
    return rrb.Grid(*views, grid_columns=2, name=p)


def _faults_tab(v: str, fault_pipes: Mapping[str, str]) -> rrb.Vertical:
    """Faults and sharing: the isolation timeline of every fault-tolerant pipeline compared, the
    injected faults (truth), then per pipeline the normalised test statistics, flags per
    observation and sharing coefficients."""
    top = rrb.Horizontal(
        _isolation_view(v, list(fault_pipes)),
        rrb.Vertical(
            _ts("injected fault channels (truth)", [paths.truth(v, "fault_channels")], legend=False),
            rrb.TextLogView(
                name="injected faults (truth)",
                origin=paths.vehicle_root(v),
                contents=[paths.truth(v, "faults")],
            ),
        ),
        column_shares=[2, 1],
    )
    detail = rrb.Tabs(*[_faults_detail(v, p, kind) for p, kind in fault_pipes.items()], active_tab=0)
    return rrb.Vertical(top, detail, row_shares=[1, 2], name="Faults & sharing")


def _integrity_grid(v: str, p: str, name: str | None = None) -> rrb.Vertical:
    def i(leaf: str) -> str:
        return paths.integrity(v, p, leaf)

    stanford = [
        rrb.Spatial2DView(
            name=f"{p}: Stanford, {axis_name} (log-log, m)",
            origin=paths.stanford(v, p),
            contents=[
                paths.stanford(v, p, a),
                paths.stanford(v, p, f"frame_{a}"),
                paths.stanford(v, p, f"labels_{a}"),
            ],
            time_ranges=UP_TO_CURSOR,
        )
        for a, axis_name in (("h", "horizontal"), ("v", "vertical"))
    ]
    return rrb.Vertical(
        rrb.Horizontal(
            _ts(f"{p}: HPL and horizontal error (m)", [i("hpl_m"), i("h_error_m")]),
            _ts(f"{p}: VPL and vertical error (m)", [i("vpl_m"), i("v_error_m")]),
        ),
        rrb.Horizontal(
            rrb.Vertical(
                _states(
                    f"{p}: availability / alarm",
                    paths.integrity(v, p),
                    ["$origin/availability", "$origin/alarm_state"],
                ),
                _ts(
                    f"{p}: HAL / VAL (m), excluded satellites", [i("hal_m"), i("val_m"), i("excluded_count")]
                ),
                row_shares=[3, 2],  # both lanes visible
            ),
            _ts(f"{p}: per-satellite statistic / threshold", f"{paths.integrity_sat_ratio(v, p)}/**"),
        ),
        rrb.Horizontal(
            *stanford,
            rrb.TextLogView(
                name=f"{p}: integrity events",
                origin=paths.integrity(v, p),
                contents=[paths.integrity_events(v, p)],
            ),
            column_shares=[2, 2, 1],
        ),
        row_shares=[2, 2, 3],
        name=name or f"{p}: integrity",
    )


def _integrity_tab(v: str, pipes: Sequence[str]) -> rrb.Container:
    """HPL / VPL against the true error on their own axes, the alert limits in a small panel with
    the availability and alarm lanes, per-satellite tests normalised by their thresholds, the
    Stanford diagrams (log-log) and the events log; one sub-tab per pipeline when several."""
    if len(pipes) == 1:
        return _integrity_grid(v, pipes[0], name="Integrity")
    return rrb.Tabs(*[_integrity_grid(v, p) for p in pipes], name="Integrity", active_tab=0)


def _overview_tab(
    v: str, pipelines: Sequence[str], fault_pipes: Sequence[str], integ_pipes: Sequence[str]
) -> rrb.Grid:
    """What a first look needs: trajectory, horizontal error of every pipeline, the fault
    isolation timeline and the protection level against the error."""
    views: list[rrb.View] = [
        _enu_view(v, pipelines, name="Trajectory, ENU (m)"),
        _ts(
            "position error east (m), all pipelines",
            [paths.error(v, p, paths.POSITION_ERRORS[0]) for p in pipelines],
        ),
    ]
    if fault_pipes:
        views.append(_isolation_view(v, fault_pipes))
    if integ_pipes:
        p = integ_pipes[0]
        views.append(
            _ts(
                f"{p}: HPL and horizontal error (m)",
                [paths.integrity(v, p, "hpl_m"), paths.integrity(v, p, "h_error_m")],
            )
        )
    views.append(
        _states("pipeline status", paths.vehicle_root(v), [paths.solution(v, p, "status") for p in pipelines])
    )
    return rrb.Grid(*views, grid_columns=2, name="Overview")


def _underwater_tab(v: str, p: str, kind: str = "underwater") -> rrb.Grid:
    """Seed 004: USBL/DVL tests vs thresholds and flags, reconfiguration events (unless nothing is
    tested), sharing coefficients (federated only), DVL offset and scale-factor estimates with
    their 1-sigma (state names as ``measurements.dvl.STATE_NAMES``)."""

    def st(prefix: str, suffix: str = "") -> list[str]:
        return [f"{paths.filter_state(v, p)}/{prefix}_{a}{suffix}/**" for a in "xyz"]

    views: list[rrb.View] = [
        _ts(f"{p}: USBL / DVL test statistics vs thresholds", f"{paths.faults(v, p)}/**"),
        rrb.StateTimelineView(
            name=f"{p}: rows in use / flagged", origin=paths.faults(v, p), contents="$origin/**"
        ),
    ]
    if "untested" not in features_of(kind):
        views.append(_reconfiguration_log(v, p))
    if _has_sharing(kind):
        views.append(_ts(f"{p}: sharing coefficients", f"{paths.sharing(v, p)}/**"))
    views += [
        _ts(f"{p}: DVL offset (m/s) and 1σ", st("dvl_offset", "_mps")),
        _ts(f"{p}: DVL scale factor and 1σ", st("dvl_scale")),
    ]
    return rrb.Grid(*views, grid_columns=2, name=f"{p}: underwater")


def _imm_tab(v: str, p: str) -> rrb.Grid:
    """IMM (He, Nie, Wu 2011): model probabilities beside the position error and the injected
    faults (truth), and the rows each model down-weights."""
    imm = paths.group(v, p, "imm")
    return rrb.Grid(
        _ts(f"{p}: model probabilities", f"{imm}/prob/**"),
        _named(
            f"{p}: position error (m)",
            {
                paths.error(v, p, n): axis
                for n, axis in zip(paths.POSITION_ERRORS, ("east", "north", "up"), strict=True)
            },
        ),
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


def _error_bounds_view(title: str, group: str, node: str, quantity: str) -> rrb.TimeSeriesView:
    """One quantity's error per axis with its +-3 sigma bounds, in the axis colours the service
    gives the series (``service.app.alignment_styles``)."""
    suffixes = ("", "_p3s", "_m3s")
    return _ts(title, [f"{group}/{node}.{quantity}_{a}{s}" for a in "xyz" for s in suffixes])


def _alignment_node(v: str, p: str, node: str) -> rrb.Grid:
    err, est = paths.group(v, p, "alignment_error"), paths.group(v, p, "alignment")
    return rrb.Grid(
        _error_bounds_view(f"{node}: misalignment error ±3σ (arcmin)", err, node, "misalignment"),
        _error_bounds_view(f"{node}: flexure error ±3σ (arcmin)", err, node, "flexure"),
        _error_bounds_view(f"{node}: lever-arm error ±3σ (m)", err, node, "lever"),
        _ts(f"{node}: lever-arm estimate (m)", [f"{est}/{node}.lever_{a}_m" for a in "xyz"]),
        grid_columns=2,
        name=node,
    )


def _alignment_adaptation(v: str, p: str, nodes: Sequence[str]) -> rrb.Grid:
    """Per node: NIS (the fading trigger's statistic), the fading factor (1: not engaged) and the
    measurement-noise 1-sigma in use (adaptive R), by row kind."""
    ad = paths.group(v, p, "alignment_adaptive")

    def rows(first: int) -> list[str]:
        return [f"{ad}/{n}.r_std_{i}" for n in nodes for i in range(first, first + 3)]

    return rrb.Grid(
        _ts(f"{p}: NIS per node", [f"{ad}/{n}.nis" for n in nodes]),
        _ts(f"{p}: fading factor per node (1: not engaged)", [f"{ad}/{n}.fading" for n in nodes]),
        _ts(f"{p}: R 1σ, attitude rows (deg)", rows(0)),
        _ts(f"{p}: R 1σ, velocity rows (m/s)", rows(3)),
        _ts(f"{p}: R 1σ, angular-rate rows (deg/s)", rows(6)),
        grid_columns=2,
        name="adaptive R, fading",
    )


def _alignment_tab(v: str, p: str, kind: str = "transfer_alignment") -> rrb.Container:
    """Transfer alignment (seed 002): per node (ids from ``features_of(kind)``), the errors against
    truth with +-3 sigma bounds (misalignment and flexure in arcmin, lever arm in m, one colour per
    axis) and the lever-arm estimate; then the adaptive R, fading factor and NIS per node.
    Without node ids: three panels with every node."""
    nodes = features_of(kind)
    if not nodes:
        return rrb.Grid(
            _ts(f"{p}: errors vs truth, ±3σ", f"{paths.group(v, p, 'alignment_error')}/**"),
            _ts(f"{p}: lever arm, flexure, mount estimates", f"{paths.group(v, p, 'alignment')}/**"),
            _ts(f"{p}: adaptive R (1σ), fading factor, NIS", f"{paths.group(v, p, 'alignment_adaptive')}/**"),
            grid_columns=2,
            name=f"{p}: alignment",
        )
    return rrb.Tabs(
        *[_alignment_node(v, p, n) for n in nodes],
        _alignment_adaptation(v, p, nodes),
        name=f"{p}: alignment",
        active_tab=0,
    )


def _health_tab(v: str, pipelines: Sequence[str]) -> rrb.Vertical:
    def h(leaf: str) -> str:
        return paths.health(v, leaf)

    grid = rrb.Grid(
        _ts("queue depth", [h("queue_depth")]),
        _ts("latency intake -> publish (ms)", [h("latency_p50_ms"), h("latency_p99_ms")]),
        _ts("messages received / accepted", [h("received"), h("accepted")]),
        _ts(
            "messages rejected (total, by reason) / dropped (overload)",
            [h("rejected_total"), f"{h('rejected')}/**", h("dropped_overload")],
        ),
        grid_columns=2,
    )
    status = _states(
        "pipeline status", paths.vehicle_root(v), [paths.solution(v, p, "status") for p in pipelines]
    )
    return rrb.Vertical(status, grid, row_shares=[1, 4], name="Health")


def _family_tab(v: str, pipes: Mapping[str, str], family: str) -> rrb.Container:
    """The family's tab; ``pipes`` maps each pipeline to its kind (with features)."""
    if family in ("underwater", "transfer_alignment"):
        by_kind = {"underwater": _underwater_tab, "transfer_alignment": _alignment_tab}[family]

        def make(v: str, p: str) -> rrb.Container:
            return by_kind(v, p, pipes[p])

    else:
        make = {"imm": _imm_tab}.get(family)
    if make is None:
        views = [_group_tab(v, p, family) for p in pipes]
        title = _GROUP_OF_FAMILY.get(family, (family, family))[0]
        return rrb.Tabs(*views, name=title, active_tab=0) if len(views) > 1 else views[0]
    if len(pipes) == 1:
        return make(v, next(iter(pipes)))
    title = {"imm": "IMM", "transfer_alignment": "Alignment", "underwater": "Underwater"}[family]
    return rrb.Tabs(*[make(v, p) for p in pipes], name=title, active_tab=0)


def vehicle_tabs(vehicle: str, pipelines: Mapping[str, str]) -> rrb.Tabs:
    """The tab container of one vehicle: one tab per question, pipelines compared inside a tab.

    Overview (opening tab), Trajectory, Errors, Integrity (MHSS pipelines), Faults & sharing
    (federated / loosely coupled / underwater), the family tabs (IMM, alignment, underwater states),
    States & covariance, Health.
    """
    _check(pipelines)
    names = list(pipelines)
    fam = {p: family_of(k) for p, k in pipelines.items()}
    integ = [p for p in names if fam[p] == "integrity"]
    faults = {p: pipelines[p] for p in names if fam[p] in ("federated", "loosely_coupled", "underwater")}
    tabs: list[rrb.Container | rrb.View] = [
        _overview_tab(vehicle, names, list(faults), integ),
        _trajectory_tab(vehicle, names),
        _errors_tab(vehicle, names),
    ]
    if integ:
        tabs.append(_integrity_tab(vehicle, integ))
    if faults:
        tabs.append(_faults_tab(vehicle, faults))
    for family in ("imm", "transfer_alignment", "underwater"):
        pipes = {p: pipelines[p] for p in names if fam[p] == family}
        if pipes:
            tabs.append(_family_tab(vehicle, pipes, family))
    tabs += [_states_tab(vehicle, names), _health_tab(vehicle, names)]
    return rrb.Tabs(*tabs, name=vehicle, active_tab=0)


def _blueprint(*parts) -> rrb.Blueprint:
    return rrb.Blueprint(
        *parts,
        rrb.TimePanel(timeline=paths.MISSION_TIMELINE),
        auto_views=False,
        auto_layout=False,
        collapse_panels=False,
    )


def build_blueprint(vehicle: str, pipelines: Mapping[str, str]) -> rrb.Blueprint:
    """Blueprint of one vehicle.

    Parameters
    ----------
    vehicle
        Vehicle name (as in the Zenoh keys).
    pipelines
        Pipeline name -> family, one of ``FAMILIES`` (or a configuration kind of ``FAMILY_ALIASES``).
    """
    return _blueprint(vehicle_tabs(vehicle, pipelines))


def build_fleet_blueprint(vehicles: Sequence[str], pipelines: Mapping[str, str]) -> rrb.Blueprint:
    """Blueprint of several vehicles running the same pipelines: one top-level tab per vehicle."""
    if not vehicles:
        _check(pipelines)
        return rrb.Blueprint(auto_views=True, auto_layout=True)
    if len(vehicles) == 1:
        return build_blueprint(vehicles[0], pipelines)
    return _blueprint(rrb.Tabs(*[vehicle_tabs(v, pipelines) for v in vehicles], active_tab=0))


def blueprint_factory(pipelines: Mapping[str, str]) -> Callable[[Sequence[str]], rrb.Blueprint]:
    """The callable to pass as ``RerunSink(blueprint=...)``: vehicles seen so far -> blueprint.

    The pipeline families are checked now, so a bad configuration fails at start-up.
    """
    frozen = dict(pipelines)
    _check(frozen)

    def factory(vehicles: Sequence[str]) -> rrb.Blueprint:
        return build_fleet_blueprint(list(vehicles), frozen)

    return factory
