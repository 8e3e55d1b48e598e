"""``fednav-fleet``: the whole fleet on one bus, from liveliness and the services' queryables.

``fednav-fleet status --connect ENDPOINT [--prefix fednav] [--json]`` lists every vehicle with the
service serving it, the status of each of its pipelines and the age of its last solution;
``fednav-fleet record --connect ENDPOINT -o fleet.rrd [--duration S] [--rate 1]`` writes one Rerun
recording of the whole fleet at a low rate (tracks on a map and in ENU, a status lane per vehicle,
the load of each service). No daemon: both are plain Zenoh clients (a router's or a service's
endpoint) that ask what every fednav service already offers (docs/fleet.md):

* liveliness tokens ``{prefix}/_services/{zid}`` (one per running service),
  ``{prefix}/{vehicle}/service/alive`` (one per served vehicle) and
  ``{prefix}/{vehicle}/sensor/alive`` (a vehicle its publisher announces while publishing: one no
  service serves is flagged);
* queryables ``{prefix}/{vehicle}/service/status`` (health per pipeline), ``.../service/config``
  and ``{prefix}/{vehicle}/nav/{pipeline}/solution`` (the latest Solution). Every reply names the
  Zenoh session that sent it (``Reply.replier_id``): that is the service of the vehicle when that
  session holds a service token (a replier without one, e.g. a Zenoh storage keeping ``fednav/**``,
  is named under ``other_repliers``, not counted). Queries ask every queryable
  (``QueryTarget.ALL``) and keep every reply (``ConsolidationMode.NONE``), so a vehicle two
  services answer for is seen twice and flagged;
* ServiceHealth on ``{prefix}/_services/{zid}/health`` (record only: a subscription; a service
  whose token is gone or whose ServiceHealth is older than ``HEALTH_STALE_S`` leaves the load plot).

A service whose configuration differs from the others' (other pipelines or pipeline settings) is
named, as is a service under another prefix (found by its ``*/_services/*`` token), instead of
being mixed in silently. Age of a solution: this machine's clock (as GPS time) minus the
solution's ``t`` when the vehicle runs on live time; simulated or replayed data carry another time,
so the age is then left out and the lag behind the vehicle's latest input (``health.t - t``) says
how current the solution is. Exit codes: 0 nothing to flag, 1 something flagged (a vehicle served
twice or by no answering service, a published vehicle no service serves, a differing
configuration, another prefix, no service at all),
2 bad arguments or no Zenoh session.
"""

from __future__ import annotations

import argparse
import json
import math
import signal
import subprocess
import sys
import threading
import time
import uuid
from collections import Counter
from pathlib import Path
from typing import Any

from fednav.dashboards import quiet_closed_stdout
from fednav.service import keys
from fednav.service.config import navigation_settings
from fednav.service.transport.rerun_paths import GPS_EPOCH_UNIX_S, gps_minus_utc_s

DEFAULT_CONNECT = "tcp/127.0.0.1:7447"
#: ``fednav-fleet record``: how long it waits at its start for the router (a recorder started with
#: its router, or before it, by a process manager)
RECORD_WAIT_S = 30.0
#: ``fednav-fleet record``: a service whose last ServiceHealth (1 Hz) is older than this has left
HEALTH_STALE_S = 3.0
#: an announced vehicle that no service serves is looked at again this much later before it is
#: flagged (a fleet member serves an announced vehicle at its first message, milliseconds on)
ANNOUNCED_RECHECK_S = 0.5
#: a solution whose time is further than this from this machine's clock is not on live time
LIVE_WINDOW_S = 86_400.0
#: worst first: the status a vehicle's lane shows when its pipelines disagree
STATUS_RANK = ("failed", "degraded", "coasting", "unaided", "initialising", "aided")
#: lane states beside the pipelines' own: no service answered; two services answered
NO_ANSWER, SERVED_TWICE = "no answer", "served twice"


# --- Zenoh ------------------------------------------------------------------------------------------
def session_config(connect: list[str] | None = None, zenoh_config: str | None = None):
    """A client of the router (or of a service), listening on nothing, no discovery: fednav's safe
    defaults (``zenoh_io.make_config``) with ``zenoh_config`` overlaid; ``connect`` replaces the
    file's endpoints."""
    from fednav.service.config import ZenohConfig
    from fednav.service.transport.zenoh_io import make_config

    return make_config(
        ZenohConfig(mode="client", listen=[], connect=[DEFAULT_CONNECT]),
        connect=connect or None,
        config_file=zenoh_config,
    )


def _get(session, selector: str, timeout_s: float) -> list[tuple[str, str | None, bytes]]:
    """Every reply of every queryable matching ``selector``: (key, replier zid, payload)."""
    import zenoh

    out = []
    for reply in session.get(
        selector,
        timeout=timeout_s,
        target=zenoh.QueryTarget.ALL,
        consolidation=zenoh.ConsolidationMode.NONE,
    ):
        if reply.ok is None:
            continue
        rid = reply.replier_id
        out.append(
            (str(reply.ok.key_expr), str(rid.zid) if rid is not None else None, reply.ok.payload.to_bytes())
        )
    return out


def _tokens(session, selector: str, timeout_s: float) -> list[str]:
    return sorted({str(r.ok.key_expr) for r in session.liveliness().get(selector, timeout=timeout_s) if r.ok})


def gps_now_s(unix_s: float | None = None) -> float:
    """This machine's clock as GPS seconds (since 1980-01-06, leap seconds added)."""
    t = (time.time() if unix_s is None else unix_s) - GPS_EPOCH_UNIX_S
    return t + gps_minus_utc_s(t + 18.0)


# --- one look at the fleet -------------------------------------------------------------------------
def _json(payload: bytes) -> dict | None:
    try:
        d = json.loads(payload)
    except ValueError:
        return None
    return d if isinstance(d, dict) else None


def _pipelines_text(cfg: dict) -> str:
    return ", ".join(f"{p.get('name')} ({p.get('kind')})" for p in cfg.get("pipelines", [])) or "none"


def config_difference(cfg: dict, ref: dict) -> str:
    """How a service's configuration differs from the reference one (prefix, pipelines), in words."""
    if cfg.get("prefix") != ref.get("prefix"):
        return f"prefix {cfg.get('prefix')!r} vs {ref.get('prefix')!r}"
    mine = {p.get("name"): p for p in cfg.get("pipelines", [])}
    theirs = {p.get("name"): p for p in ref.get("pipelines", [])}
    if [(n, p.get("kind")) for n, p in mine.items()] != [(n, p.get("kind")) for n, p in theirs.items()]:
        return f"pipelines {_pipelines_text(cfg)} vs {_pipelines_text(ref)}"
    changed = sorted(n for n in mine if mine[n] != theirs[n])
    words = [f"settings of pipeline(s) {', '.join(changed)} differ"] if changed else []
    # the rest of what changes a vehicle's navigation (and the fleet group's digest): IMU model,
    # initialisation, solution rate, major interval, the intake's acceptance rules
    nav, nav_ref = navigation_settings(cfg), navigation_settings(ref)
    others = [k for k in nav if k not in ("prefix", "pipelines") and nav[k] != nav_ref[k]]
    if others:
        words.append(f"{', '.join(others)} differ")
    return "; ".join(words)


def _signature(cfg: dict) -> str:
    """What services sharing a fleet must agree on (config.navigation_settings: until 2026-12-01
    only the prefix and the pipelines, and a service with another IMU grade and solution rate,
    in a fleet group of its own, was shown with the configuration "same")."""
    return json.dumps(navigation_settings(cfg), sort_keys=True)


def _pipeline_row(health: dict | None, sol: dict | None, name: str, now_gps: float) -> dict:
    ph = ((health or {}).get("pipelines") or {}).get(name) or {}
    t = sol.get("t") if sol else None
    row: dict[str, Any] = {"status": ph.get("status") or (sol or {}).get("status"), "t": t}
    age = now_gps - t if t is not None else None
    live = age is not None and abs(age) <= LIVE_WINDOW_S
    row["age_s"] = round(age, 3) if live else None
    ht = (health or {}).get("t")
    row["lag_s"] = round(ht - t, 3) if t is not None and ht is not None else None
    row["live_time"] = live
    row["position"] = [sol["lat_deg"], sol["lon_deg"], sol["height_m"]] if sol else None
    return row


class Fleet:
    """Looks at the fleet under one prefix through one Zenoh session (status and record).

    The configuration of each service is asked once (one vehicle's ``service/config``, the reply
    from that service) and kept; :meth:`snapshot` asks the rest every time."""

    def __init__(self, session, prefix: str = keys.DEFAULT_PREFIX, timeout_s: float = 3.0):
        self.session = session
        self.prefix = prefix
        self.timeout_s = timeout_s
        self.configs: dict[str, dict] = {}

    def _config_of(self, zid: str, vehicle: str) -> dict | None:
        cfg = self.configs.get(zid)
        if cfg is None:
            for _, rid, payload in _get(
                self.session, f"{self.prefix}/{vehicle}/service/config", self.timeout_s
            ):
                got = _json(payload)
                if got is not None and rid is not None:
                    self.configs.setdefault(rid, got)
            cfg = self.configs.get(zid)
        return cfg

    def snapshot(self, now_gps: float | None = None) -> dict:
        """The fleet now: services, vehicles (service, pipelines with status and age) and problems."""
        p = self.prefix
        now_gps = gps_now_s() if now_gps is None else now_gps
        # narrow selectors: an access control (secure/router.json5) allows a liveliness query only
        # inside the key expressions it lists
        service_tokens = self._service_zids()
        alive = {k.split("/")[1] for k in _tokens(self.session, f"{p}/*/service/alive", self.timeout_s)}
        # the vehicles whose publishers announce them (keys.sensors_alive): published right now
        announced = {k.split("/")[1] for k in _tokens(self.session, f"{p}/*/sensor/alive", self.timeout_s)}
        others = []
        for k in _tokens(self.session, "**/_services/*", self.timeout_s):
            other = k.rsplit("/_services/", 1)[0]
            if other != p:
                others.append({"zid": k.rsplit("/", 1)[-1], "prefix": other})

        sol_replies = _get(self.session, f"{p}/*/nav/*/solution", self.timeout_s)
        # a '*' service answers for its ServiceHealth: its max_vehicles, whether it is full and
        # the vehicles it refused for that lately (a fixed-list service has no such limit)
        health_replies = _get(self.session, f"{p}/_services/*/health", self.timeout_s)
        status_replies = _get(self.session, f"{p}/*/service/status", self.timeout_s)
        repliers = {zid or "?" for _, zid, _ in sol_replies + status_replies + health_replies}
        if repliers - service_tokens:  # a service declares its queryables just before its token
            service_tokens |= self._service_zids()
        # a replier without a service token (a Zenoh storage keeping fednav/**, a recorder's
        # replay, ...) is no fednav service: named once, its replies are not counted as a service's
        other_repliers = sorted(repliers - service_tokens)

        solutions: dict[tuple[str, str], dict[str, dict]] = {}  # (vehicle, zid) -> pipeline -> Solution
        for key, zid, payload in sol_replies:
            d = _json(payload)
            if d is not None and (zid or "?") in service_tokens:
                parts = key.split("/")
                solutions.setdefault((parts[1], zid or "?"), {})[parts[3]] = d

        status: dict[str, dict[str, dict]] = {}  # vehicle -> zid -> status JSON
        for key, zid, payload in status_replies:
            d = _json(payload)
            if d is not None and (zid or "?") in service_tokens:
                status.setdefault(key.split("/")[1], {})[zid or "?"] = d
        capacity: dict[str, dict] = {}  # zid -> its ServiceHealth's capacity fields
        for key, zid, payload in health_replies:
            d = _json(payload)
            if d is not None and (zid or "?") in service_tokens and key.split("/")[-2] == zid:
                capacity[zid] = {
                    "max_vehicles": d.get("max_vehicles"),
                    "full": bool(d.get("full")),
                    "refusing": list(d.get("refusing_vehicles") or []),
                    # a fleet member subscribing per vehicle it serves ([intake] subscribe =
                    # 'owned'): how many it subscribes to (None: every vehicle's inputs)
                    "subscribed": d.get("subscribed_vehicles"),
                    "active": len(d.get("active_vehicles") or []),
                    # a fleet member's group ([fleet] group, or its digest): None for others
                    "fleet_group": d.get("fleet_group"),
                }
        services: dict[str, dict] = {
            z: {"zid": z, "alive": True, "vehicles": [], "pipelines": [], "received": 0}
            for z in sorted(service_tokens)
        }
        vehicles: dict[str, dict] = {}
        problems: list[str] = []
        for v in sorted(set(status) | alive | {v for v, _ in solutions}):
            by_service = {}
            for zid in sorted(set(status.get(v, {})) | {z for (vv, z) in solutions if vv == v}):
                st = status.get(v, {}).get(zid) or {}
                health = st.get("health")
                sols = solutions.get((v, zid), {})
                names = list(st.get("pipelines") or []) or sorted(sols)
                by_service[zid] = {
                    "pipelines": {n: _pipeline_row(health, sols.get(n), n, now_gps) for n in names},
                    "received": (health or {}).get("received"),
                    "queue_depth": (health or {}).get("queue_depth"),
                    "stale": (health or {}).get("stale", []),
                }
                svc = services.setdefault(
                    zid, {"zid": zid, "alive": False, "vehicles": [], "pipelines": [], "received": 0}
                )
                svc["vehicles"].append(v)
                svc["pipelines"] = svc["pipelines"] or names
                svc["received"] += (health or {}).get("received") or 0
            zids = list(by_service)
            vehicles[v] = {
                "vehicle": v,
                "alive": v in alive,
                "service": zids[0] if len(zids) == 1 else None,
                "services": zids,
                "served_twice": len(zids) > 1,
                "pipelines": by_service[zids[0]]["pipelines"] if zids else {},
                "by_service": by_service,
            }
            if len(zids) > 1:
                problems.append(f"vehicle {v} is served by {len(zids)} services: {', '.join(zids)}")
            elif not zids:
                problems.append(f"vehicle {v} has a liveliness token but no service answers for it")

        # capacity: a service at max_vehicles is named; a vehicle it refused that no service serves
        # is a vehicle, unserved, and a problem (the fleet, or that service, needs more room)
        refused: dict[str, list[str]] = {}
        for zid, c in capacity.items():
            svc = services.get(zid)
            if svc is not None:
                svc.update(c)
                if c["subscribed"] is not None and c["subscribed"] < c["active"]:  # (one reply's figures)
                    problems.append(
                        f"service {zid} serves {c['active']} vehicles but subscribes to "
                        f"{c['subscribed']}: the others receive no IMU there"
                    )
            for v in c["refusing"]:
                refused.setdefault(v, []).append(zid)
        for v, zids in sorted(refused.items()):
            if vehicles.get(v, {}).get("services"):
                continue  # another service has it (spilled over in a fleet group)
            vehicles[v] = _unserved(v, v in alive, refused_by=zids)
            limits = ", ".join(f"{z} (max_vehicles {capacity[z]['max_vehicles']})" for z in zids)
            problems.append(f"vehicle {v} is not served: refused by a service at its limit: {limits}")
        # a vehicle its publisher announces that no service serves (nor refused: named above):
        # its data reach no fednav service (no service of that name, another prefix, a policy).
        # Looked at again after a moment: a vehicle announced an instant before its owner's first
        # message (a fleet member subscribes, then serves at the first message) is not flagged
        unserved = announced - set(vehicles)
        if unserved:
            time.sleep(ANNOUNCED_RECHECK_S)
            unserved -= {
                k.split("/")[1] for k in _tokens(self.session, f"{p}/*/service/alive", self.timeout_s)
            }
        for v in sorted(unserved):
            vehicles[v] = _unserved(v, v in alive)
            problems.append(f"vehicle {v} is published (its publisher announces it) but no service serves it")
        for v, d in vehicles.items():
            d["announced"] = v in announced
        vehicles = dict(sorted(vehicles.items()))

        # configurations: the one most services share is the reference; the others are named
        for zid, svc in services.items():
            cfg = self._config_of(zid, svc["vehicles"][0]) if svc["vehicles"] else None
            svc["config"] = (
                {
                    "prefix": cfg.get("prefix"),
                    "pipelines": {q.get("name"): q.get("kind") for q in cfg.get("pipelines", [])},
                }
                if cfg
                else None
            )
            svc["config_differs"] = None
        with_cfg = [z for z in services if z in self.configs]
        sigs = Counter(_signature(self.configs[z]) for z in with_cfg)
        if len(sigs) > 1:  # the reference: the configuration most services share (then the first)
            ref = max(with_cfg, key=lambda z: (sigs[_signature(self.configs[z])], -with_cfg.index(z)))
            for zid in with_cfg:
                if _signature(self.configs[zid]) != _signature(self.configs[ref]):
                    why = config_difference(self.configs[zid], self.configs[ref]) or "configuration differs"
                    services[zid]["config_differs"] = why
                    problems.append(f"service {zid}: configuration differs from service {ref}'s: {why}")
        # fleet members of different groups share nothing: each serves every vehicle it hears
        # (a typo in [fleet] group, or navigation settings that differ: the default group digests them)
        groups: dict[str, list[str]] = {}
        for zid, svc in services.items():
            if svc.setdefault("fleet_group", None):
                groups.setdefault(svc["fleet_group"], []).append(zid)
        if len(groups) > 1:
            named = "; ".join(f"{g}: {', '.join(zs)}" for g, zs in sorted(groups.items()))
            problems.append(
                f"services in {len(groups)} fleet groups do not share the fleet (each serves every "
                f"vehicle it hears; [fleet] group, or the navigation settings it digests): {named}"
            )
        for o in others:
            problems.append(f"service {o['zid']} runs under another prefix {o['prefix']!r} (not listed here)")
        if not services:
            problems.append(f"no fednav service found under prefix {p!r}")
        return {
            "prefix": p,
            "routers": [str(z) for z in self.session.info.routers_zid()],
            "services": list(services.values()),
            "vehicles": list(vehicles.values()),
            "other_prefixes": others,
            "other_repliers": other_repliers,
            "problems": problems,
        }

    def _service_zids(self) -> set[str]:
        """The zids holding a ``{prefix}/_services/{zid}`` liveliness token: the running services."""
        return {k.split("/")[-1] for k in _tokens(self.session, f"{self.prefix}/_services/*", self.timeout_s)}


# --- status ----------------------------------------------------------------------------------------
def _unserved(vehicle: str, alive: bool, **extra) -> dict:
    """A snapshot's entry of a vehicle no service serves (refused, or only announced)."""
    return {
        "vehicle": vehicle,
        "alive": alive,
        "service": None,
        "services": [],
        "served_twice": False,
        "pipelines": {},
        "by_service": {},
        **extra,
    }


def _fmt(x: float | None, unit: str = " s") -> str:
    return "-" if x is None else f"{x:.1f}{unit}"


def format_status(snap: dict) -> str:
    """The snapshot as tables: services, then one line per vehicle and pipeline, then problems."""
    lines = [
        f"fednav fleet, prefix {snap['prefix']!r}: {len(snap['services'])} service(s), "
        f"{len(snap['vehicles'])} vehicle(s)"
        + (f", router {', '.join(z[:8] for z in snap['routers'])}" if snap["routers"] else "")
    ]
    rows = [("SERVICE", "VEHICLES", "PIPELINES", "MESSAGES", "CONFIG")]
    for s in snap["services"]:
        cfg = "differs: " + s["config_differs"] if s["config_differs"] else ("same" if s["config"] else "-")
        count = str(len(s["vehicles"])) + (f" (full: max {s['max_vehicles']})" if s.get("full") else "")
        if s.get("subscribed") is not None:  # a fleet member subscribing per vehicle it serves
            count += f", subscribed {s['subscribed']}"
        rows.append((s["zid"], count, ",".join(s["pipelines"]) or "-", str(s["received"]), cfg))
    lines += _table(rows)
    if snap.get("other_repliers"):
        lines.append(
            f"other repliers (answer on {snap['prefix']}/** without a service token; not services): "
            + ", ".join(snap["other_repliers"])
        )
    rows = [("VEHICLE", "SERVICE", "PIPELINE", "STATUS", "LAST T (GPS s)", "AGE", "LAG")]
    for v in snap["vehicles"]:
        if not v["services"]:
            why = (
                "refused (service full)"
                if v.get("refused_by")
                else "published, not served"
                if v.get("announced") and not v["alive"]
                else NO_ANSWER
            )
            rows.append((v["vehicle"], "-", "-", why, "-", "-", "-"))
        for zid, info in v["by_service"].items():
            name = zid[:8] + (" (twice!)" if v["served_twice"] else "")
            for pname, r in info["pipelines"].items():
                t = "-" if r["t"] is None else f"{r['t']:.1f}"
                rows.append(
                    (v["vehicle"], name, pname, r["status"] or "-", t, _fmt(r["age_s"]), _fmt(r["lag_s"]))
                )
    lines += [""] + _table(rows)
    if any(
        r["t"] is not None and not r["live_time"] for v in snap["vehicles"] for r in v["pipelines"].values()
    ):
        lines.append(
            "AGE is left out where the solution's time is not this machine's (simulated or replayed data); "
            "LAG: behind the vehicle's latest input"
        )
    if snap["problems"]:
        lines += ["", "problems:"] + [f"  - {p}" for p in snap["problems"]]
    return "\n".join(lines)


def _table(rows: list[tuple[str, ...]]) -> list[str]:
    widths = [max(len(r[i]) for r in rows) for i in range(len(rows[0]))]
    return ["  ".join(c.ljust(w) for c, w in zip(r, widths, strict=True)).rstrip() for r in rows]


# --- record ----------------------------------------------------------------------------------------
WALL_TIMELINE = "wall_time"
_PALETTE = (
    0x1F77B4FF, 0xFF7F0EFF, 0x2CA02CFF, 0xD62728FF, 0x9467BDFF,
    0x8C564BFF, 0xE377C2FF, 0x7F7F7FFF, 0xBCBD22FF, 0x17BECFFF,
)  # fmt: skip
#: points kept in a vehicle's map track (thinned by two when full)
TRACK_POINTS = 1000


def fleet_blueprint(
    enu_bounds: tuple[float, float, float, float] | None = None, time_panel: str = "expanded"
):
    """Map and ENU view of every vehicle, a status lane per vehicle, the load of each service; the
    time cursor follows the latest snapshot and the plots span the whole recording.
    ``enu_bounds`` (x0, x1, y0, y1): what the ENU view shows (default: the viewer's choice)."""
    import rerun.blueprint as rrb
    import rerun.blueprint.components as rrc
    import rerun.encodings as rre

    def window(end):
        return [rrb.VisibleTimeRange(WALL_TIMELINE, start=rrb.TimeRangeBoundary.infinite(), end=end)]

    whole_axis = rrb.TimeAxis(
        link="Independent",
        view_range=rre.TimeRange(
            start=rrb.TimeRangeBoundary.infinite(), end=rrb.TimeRangeBoundary.infinite()
        ),
    )

    def series(name: str, origin: str) -> rrb.TimeSeriesView:
        return rrb.TimeSeriesView(
            name=name,
            origin=origin,
            time_ranges=window(rrb.TimeRangeBoundary.infinite()),
            axis_x=whole_axis,
            plot_legend=rrb.PlotLegend(corner="LeftTop", visible=True),
        )

    return rrb.Blueprint(
        rrb.Horizontal(
            rrb.Vertical(
                rrb.MapView(name="Fleet map (online tiles)", origin="/fleet"),
                rrb.Spatial2DView(
                    name="Fleet, ENU from the first vehicle (m): x east, y = -north",
                    origin="/enu",
                    time_ranges=window(rrb.TimeRangeBoundary.cursor_relative()),
                    visual_bounds=(
                        rrb.VisualBounds2D(x_range=enu_bounds[:2], y_range=enu_bounds[2:])
                        if enu_bounds
                        else None
                    ),
                ),
                row_shares=[1, 1],
            ),
            rrb.Vertical(
                rrb.StateTimelineView(name="Status per vehicle", origin="/status", time_view=whole_axis),
                series("Vehicles per service", "/load/vehicles"),
                series("Messages per second per service", "/load/messages_per_s"),
                row_shares=[2, 1, 1],
            ),
            column_shares=[3, 2],
        ),
        rrb.TimePanel(timeline=WALL_TIMELINE, play_state=rrc.PlayState.Following, state=time_panel),
        rrb.BlueprintPanel(state="collapsed"),
        rrb.SelectionPanel(state="collapsed"),
    )


def enu_view_bounds(b: tuple[float, float, float, float], margin: float = 0.08) -> tuple[float, ...]:
    """ENU extents (x0, x1, y0, y1) with a margin, at least 100 m wide."""
    x0, x1, y0, y1 = b
    m = max(x1 - x0, y1 - y0, 100.0) * margin
    return (x0 - m, x1 + m, y0 - m, y1 + m)


def _worst(states: list[str]) -> str:
    ranked = [s for s in STATUS_RANK if s in states]
    return ranked[0] if ranked else (states[0] if states else NO_ANSWER)


class FleetRecorder:
    """Logs fleet snapshots to one ``.rrd`` (Rerun, timeline ``wall_time``).

    Entities: ``/fleet/{vehicle}/position`` (GeoPoints) and ``/fleet/{vehicle}/track``
    (GeoLineStrings, thinned), ``/enu/{vehicle}`` (Points2D: east, -north from the first vehicle's
    first position), ``/status/{vehicle}`` (StateChange: the worst status of its pipelines, or
    "no answer" / "served twice"; per pipeline under ``/status/{vehicle}/{pipeline}`` when it has
    several), ``/load/vehicles/{zid}`` and ``/load/messages_per_s/{zid}`` (Scalars) of each
    service holding its token (and whose ServiceHealth is not stale)."""

    def __init__(self, path: str | Path, track_every: int = 5):
        import rerun as rr

        from fednav.service.transport.rerun_sink import STATE_COLORS

        self.rr = rr
        self.rec = rr.RecordingStream("fednav-fleet", recording_id=str(uuid.uuid4()))
        Path(path).parent.mkdir(parents=True, exist_ok=True)
        self.rec.save(str(path), default_blueprint=fleet_blueprint())
        self.state_colors = dict(STATE_COLORS, **{NO_ANSWER: 0x7F7F7FFF, SERVED_TWICE: 0xD62728FF})
        self.track_every = track_every
        self.origin = None  # (lat_rad, lon_rad, h_m) of the first vehicle's first solution
        self.colors: dict[str, int] = {}
        self.tracks: dict[str, list[tuple[float, float]]] = {}
        self.states: dict[str, str] = {}
        self.counts: dict[tuple[str, str], int] = {}  # (zid, vehicle) -> received, last look
        self.counts_wall: float | None = None
        self.ticks = 0
        self.vehicles_seen: set[str] = set()
        self.services_seen: set[str] = set()
        self.services_named: set[str] = set()
        self.services_live: set[str] = set()  # the services whose load the last snapshot logged
        self.enu_bounds = (math.inf, -math.inf, math.inf, -math.inf)  # x (east), y (-north)

    def _color(self, v: str) -> int:
        if v not in self.colors:
            self.colors[v] = _PALETTE[len(self.colors) % len(_PALETTE)]
            rr = self.rr
            self.rec.log(
                f"/fleet/{v}/position",
                rr.GeoPoints.from_fields(colors=[self.colors[v]], radii=rr.Radius.ui_points(6.0)),
                static=True,
            )
            self.rec.log(
                f"/fleet/{v}/track",
                rr.GeoLineStrings.from_fields(colors=[self.colors[v]], radii=rr.Radius.ui_points(1.5)),
                static=True,
            )
            self.rec.log(
                f"/enu/{v}",
                rr.Points2D.from_fields(colors=[self.colors[v]], radii=rr.Radius.ui_points(3.0)),
                static=True,
            )
        return self.colors[v]

    def _state(self, path: str, state: str) -> None:
        if self.states.get(path) == state:
            return
        if path not in self.states:
            c = self.state_colors
            self.rec.log(
                path, self.rr.StateConfiguration(values=list(c), colors=list(c.values())), static=True
            )
        self.states[path] = state
        self.rec.log(path, self.rr.StateChange(state=state))

    def log(
        self,
        snap: dict,
        service_health: dict[str, dict],
        wall: float,
        stale_health: frozenset[str] | set[str] = frozenset(),
    ) -> None:
        """One snapshot. ``service_health``: the latest ServiceHealth per zid (current ones);
        ``stale_health``: the zids whose ServiceHealth stopped (older than ``HEALTH_STALE_S``)."""
        import numpy as np

        from fednav.service import earth
        from fednav.service.transport.rerun_paths import part

        rr = self.rr
        self.rec.set_time(WALL_TIMELINE, timestamp=wall)
        self.ticks += 1
        for veh in snap["vehicles"]:
            v = part(veh["vehicle"])
            self.vehicles_seen.add(veh["vehicle"])
            self._color(v)
            rows = veh["pipelines"]
            if veh["served_twice"]:
                self._state(f"/status/{v}", SERVED_TWICE)
            elif not veh["services"]:
                self._state(f"/status/{v}", NO_ANSWER)
            else:
                self._state(f"/status/{v}", _worst([r["status"] for r in rows.values() if r["status"]]))
            if len(rows) > 1:
                for name, r in rows.items():
                    self._state(f"/status/{v}/{part(name)}", r["status"] or NO_ANSWER)
            # the track: the first pipeline with a solution (in the service's order)
            pos = next((r["position"] for r in rows.values() if r.get("position")), None)
            if pos is None:
                continue
            lat, lon, h = pos
            self.rec.log(f"/fleet/{v}/position", rr.GeoPoints(lat_lon=[[lat, lon]]))
            llh = np.array([math.radians(lat), math.radians(lon), h])
            if self.origin is None:
                self.origin = llh
            e, n, _ = earth.ecef_to_enu(earth.llh_to_ecef(llh), self.origin)
            self.rec.log(f"/enu/{v}", rr.Points2D(positions=[[e, -n]]))
            b = self.enu_bounds
            self.enu_bounds = (min(b[0], e), max(b[1], e), min(b[2], -n), max(b[3], -n))
            track = self.tracks.setdefault(v, [])
            if not track or track[-1] != (lat, lon):
                track.append((lat, lon))
            if len(track) > TRACK_POINTS:
                track[:] = track[::2]
            if len(track) > 1 and self.ticks % self.track_every == 0:
                self.rec.log(f"/fleet/{v}/track", rr.GeoLineStrings(lat_lon=[track]))
        # load per service: vehicles (ServiceHealth's active vehicles, else the vehicles it answers
        # for) and messages per second (the growth of its vehicles' received counts since the last
        # look; a vehicle that moved to another service counts from its second look there)
        counts = {
            (zid, veh["vehicle"]): info["received"]
            for veh in snap["vehicles"]
            for zid, info in veh["by_service"].items()
            if isinstance(info.get("received"), int)
        }
        answering = {s["zid"]: len(s["vehicles"]) for s in snap["services"]}
        prev_wall, self.counts_wall = self.counts_wall, wall
        # a service counts while it holds its token and its ServiceHealth (if it sent any) is
        # current: a killed service's last ServiceHealth must not count its vehicles forever
        live = {s["zid"] for s in snap["services"] if s.get("alive", True)} - set(stale_health)
        for zid in sorted(self.services_live - live):
            # a departed service's series end with one 0: a line that simply stops would read (and
            # answer Rerun's latest-at queries, e.g. on hover) as its last load to the end of the
            # recording; the drop to 0 shows where it left and the sum over services stays the
            # fleet; nothing after it (no flat 0 for the rest of the recording). It comes back as
            # the same series if its token and ServiceHealth do.
            for what in ("vehicles", "messages_per_s"):
                self.rec.log(f"/load/{what}/{zid}", rr.Scalars(0.0))
        self.services_live = live
        for zid in sorted(live):
            self.services_seen.add(zid)
            sh = service_health.get(zid)
            n_veh = len(sh.get("active_vehicles", [])) if sh else answering.get(zid, 0)
            if zid not in self.services_named:  # the legend: the zid's first 8 characters
                self.services_named.add(zid)
                for what in ("vehicles", "messages_per_s"):
                    self.rec.log(
                        f"/load/{what}/{zid}",
                        rr.SeriesLines.from_fields(
                            names=[f"service {zid[:8]}"],
                            colors=[_PALETTE[(len(self.services_named) - 1) % len(_PALETTE)]],
                        ),
                        static=True,
                    )
            self.rec.log(f"/load/vehicles/{zid}", rr.Scalars(float(n_veh)))
            if prev_wall is None or wall <= prev_wall:
                continue
            grown = [n - self.counts[k] for k, n in counts.items() if k[0] == zid and k in self.counts]
            if grown or answering.get(zid):
                rate = sum(max(0, g) for g in grown) / (wall - prev_wall)
                self.rec.log(f"/load/messages_per_s/{zid}", rr.Scalars(float(rate)))
        self.counts = counts

    def close(self) -> None:
        for v, track in self.tracks.items():  # the whole track at the end
            if len(track) > 1:
                self.rec.log(f"/fleet/{v}/track", self.rr.GeoLineStrings(lat_lon=[track]))
        x0, x1, y0, y1 = self.enu_bounds
        if x0 <= x1:  # the blueprint again, its ENU view framing every track
            self.rec.send_blueprint(fleet_blueprint(enu_view_bounds(self.enu_bounds)), make_default=True)
        self.rec.flush(timeout_sec=10.0)
        self.rec.disconnect()


def record(fleet: Fleet, out: Path, duration_s: float | None, rate_hz: float, stop: threading.Event) -> dict:
    """Snapshots at ``rate_hz`` into ``out`` until ``duration_s`` (None: until ``stop``)."""
    health: dict[str, tuple[float, dict]] = {}  # zid -> (time.monotonic() of arrival, ServiceHealth)
    lock = threading.Lock()

    def on_health(sample) -> None:
        d = _json(sample.payload.to_bytes())
        if d is not None:
            with lock:
                health[str(sample.key_expr).split("/")[-2]] = (time.monotonic(), d)

    sub = fleet.session.declare_subscriber(f"{fleet.prefix}/_services/*/health", on_health)
    recorder = FleetRecorder(out)
    period = 1.0 / rate_hz
    t0 = time.monotonic()
    runs = ProblemRuns()
    try:
        k = 0
        while not stop.is_set():
            snap = fleet.snapshot()
            runs.see(snap["problems"], time.monotonic())
            now = time.monotonic()
            with lock:
                sh = {z: d for z, (t, d) in health.items() if now - t <= HEALTH_STALE_S}
                stale = set(health) - set(sh)
            recorder.log(snap, sh, time.time(), stale)
            k += 1
            if duration_s is not None and time.monotonic() - t0 >= duration_s:
                break
            stop.wait(max(0.0, t0 + k * period - time.monotonic()))
    finally:
        sub.undeclare()
        recorder.close()
    return {
        "rrd": str(out),
        "snapshots": recorder.ticks,
        "vehicles": sorted(recorder.vehicles_seen),
        "services": sorted(recorder.services_seen),
        "problems": runs.lasting(),
        "transient": runs.transient(),
    }


#: a problem ``fednav-fleet record`` saw for less than this (its longest run of consecutive
#: snapshots) is a transient one, not an exit 1: a vehicle "published but not served" in the
#: snapshot taken while its killed service's heir takes it over (a failover: ~0.1-1 s)
TRANSIENT_PROBLEM_S = 3.0


class ProblemRuns:
    """The problems of successive snapshots and how long each lasted (its longest run)."""

    def __init__(self) -> None:
        self._since: dict[str, float] = {}  # problem -> start of its current run
        self._last: dict[str, float] = {}  # problem -> last time seen in the current run
        self.longest: dict[str, float] = {}

    def see(self, problems, now: float) -> None:
        for p in list(self._since):
            if p not in problems:  # its run ended at the snapshot before this one
                del self._since[p]
        for p in problems:
            start = self._since.setdefault(p, now)
            self._last[p] = now
            self.longest[p] = max(self.longest.get(p, 0.0), now - start)

    def lasting(self) -> list[str]:
        return sorted(p for p, d in self.longest.items() if d >= TRANSIENT_PROBLEM_S or p in self._since)

    def transient(self) -> list[str]:
        return sorted(set(self.longest) - set(self.lasting()))


def _compact(out: Path, optimize: bool) -> str:
    """The finished recording compacted (``rerun rrd optimize``: the recorder writes many small
    chunks, a 10-minute fleet recording of 20 MB became ~1 MB), unless asked not to; its size."""
    before = out.stat().st_size if out.is_file() else 0
    if not optimize or before == 0:
        return f"{before / 1e6:.1f} MB"
    from fednav.service.transport.rerun_sink import optimize_rrd

    try:
        optimize_rrd(out)
    except (RuntimeError, OSError, subprocess.TimeoutExpired) as exc:
        print(f"fednav-fleet record: {out} left as written (not optimized): {exc}", file=sys.stderr)
        return f"{before / 1e6:.1f} MB"
    return f"{out.stat().st_size / 1e6:.1f} MB, optimized from {before / 1e6:.1f} MB"


# --- command line ----------------------------------------------------------------------------------
EXAMPLES = """examples:
  fednav-fleet status --connect tcp/127.0.0.1:7447
  fednav-fleet status --connect tcp/127.0.0.1:7447 --json
  fednav-fleet record --connect tcp/127.0.0.1:7447 -o recordings/fleet.rrd --duration 600 --rate 1
  fednav-fleet status --zenoh-config service/configs/fleet/secure/ops.json5
exit codes: 0 nothing flagged, 1 something flagged (listed), 2 bad arguments or no Zenoh session.
docs/fleet.md: topology, configs per role, example output."""


def parse_args(argv: list[str] | None = None) -> argparse.Namespace:
    ap = argparse.ArgumentParser(
        prog="fednav-fleet",
        description="every vehicle of the fleet with its service, status and last solution "
        "(from liveliness and the services' queryables)",
        epilog=EXAMPLES,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    sub = ap.add_subparsers(dest="cmd", required=True)
    common = argparse.ArgumentParser(add_help=False)
    common.add_argument(
        "--connect",
        action="append",
        help=f"Zenoh endpoint: the router or a service (default {DEFAULT_CONNECT})",
    )
    common.add_argument("--zenoh-config", help="a Zenoh json5 config file (TLS: secure/ops.json5)")
    common.add_argument("--prefix", default=keys.DEFAULT_PREFIX, help="key prefix (default fednav)")
    common.add_argument("--timeout", type=float, default=3.0, help="seconds to wait for replies (default 3)")
    s = sub.add_parser("status", parents=[common], help="list the fleet now")
    s.add_argument("--json", action="store_true", help="print the snapshot as JSON")
    s.add_argument(
        "--wait", type=float, default=0.0, help="seconds to wait for the router (default 0: fail at once)"
    )
    r = sub.add_parser("record", parents=[common], help="record the fleet to one .rrd at a low rate")
    r.add_argument(
        "--wait",
        type=float,
        default=RECORD_WAIT_S,
        help=f"seconds to wait for the router to answer at the start (default {RECORD_WAIT_S:g})",
    )
    r.add_argument("-o", "--out", type=Path, required=True, help="the .rrd to write")
    r.add_argument("--duration", type=float, help="seconds to record (default: until Ctrl-C)")
    r.add_argument("--rate", type=float, default=1.0, help="snapshots per second (default 1)")
    r.add_argument(
        "--no-optimize",
        action="store_true",
        help="leave the file as written (by default it is compacted at the end, 'rerun rrd optimize': "
        "about 20x smaller, a few seconds)",
    )
    return ap.parse_args(argv)


@quiet_closed_stdout
def main(argv: list[str] | None = None) -> int:
    args = parse_args(argv)
    from fednav.service.transport.zenoh_io import endpoint_error

    problem = next((e for e in map(endpoint_error, args.connect or []) if e), None)
    if args.zenoh_config and not Path(args.zenoh_config).is_file():
        problem = f"--zenoh-config {args.zenoh_config}: no such file"
    if args.cmd == "record" and not (0 < args.rate <= 50):
        problem = f"--rate {args.rate}: use a rate in (0, 50] snapshots per second"
    if args.cmd == "record" and args.duration is not None and args.duration <= 0:
        problem = f"--duration {args.duration}: use a positive number of seconds"
    if args.timeout <= 0:
        problem = f"--timeout {args.timeout}: use a positive number of seconds"
    if not 0 <= args.wait < math.inf:
        problem = f"--wait {args.wait}: use a number of seconds >= 0"
    if problem:
        print(f"fednav-fleet: {problem}", file=sys.stderr)
        return 2
    import zenoh

    from fednav.service.__main__ import zenoh_error_text
    from fednav.service.transport.zenoh_io import NoAnswer, open_waiting

    config = session_config(args.connect, args.zenoh_config)
    try:
        session = open_waiting(config, args.wait) if args.wait > 0 else zenoh.open(config)
    except NoAnswer as exc:
        print(f"fednav-fleet: {exc}", file=sys.stderr)
        return 2
    except zenoh.ZError as exc:
        print(f"fednav-fleet: cannot open the Zenoh session ({zenoh_error_text(exc)})", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        return 130
    try:
        fleet = Fleet(session, args.prefix, timeout_s=args.timeout)
        if args.cmd == "status":
            snap = fleet.snapshot()
            print(json.dumps(snap, indent=2) if args.json else format_status(snap), flush=True)
            return 1 if snap["problems"] else 0
        stop = threading.Event()
        signal.signal(signal.SIGINT, lambda *_: stop.set())
        signal.signal(signal.SIGTERM, lambda *_: stop.set())
        res = record(fleet, args.out, args.duration, args.rate, stop)
        size = _compact(args.out, not args.no_optimize)
        print(
            f"fednav-fleet record: {res['snapshots']} snapshots, {len(res['vehicles'])} vehicle(s), "
            f"{len(res['services'])} service(s) -> {res['rrd']} ({size})",
            flush=True,
        )
        for p in res["problems"]:
            print(f"  problem seen: {p}", flush=True)
        for p in res["transient"]:  # e.g. the snapshot taken during a failover
            print(f"  transient (under {TRANSIENT_PROBLEM_S:g} s, not an error): {p}", flush=True)
        return 1 if res["problems"] else 0
    finally:
        session.close()


if __name__ == "__main__":
    raise SystemExit(main())
