"""``fednav-inspect FILE.rrd [--json]``: headless summary of a fednav recording.

Reads the recording back with Rerun's own reader (``rerun.chunk.RrdReader``, rerun-sdk 0.41) and
summarises it from the entity layout of ``service.transport.rerun_paths``: recording id, time span,
vehicles and pipelines; per pipeline the number of solutions, RMS / max of each error against truth
(and the horizontal error sqrt(e^2 + n^2)), the share of epochs outside the ±3σ bound and the final
status; fault tests (flagged observations per label); integrity (HPL/VPL statistics, alarms,
detections, exclusions, HMI epochs, Stanford-diagram regions); the last health counters.

``inspect_rrd(path) -> dict`` is the library entry point (the ``--json`` output). Result keys for
pipelines are the pipeline name when the file holds one vehicle, else ``"{vehicle}/{pipeline}"``.
Exit codes: 0 ok, 2 file missing, unreadable, or holding no fednav recording.
"""

from __future__ import annotations

import argparse
import json
import math
import sys
from collections import defaultdict
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import pyarrow as pa
import pyarrow.compute as pc

from fednav.service.transport import rerun_paths as paths

_COMPONENTS = ("Scalars:scalars", "StateChange:state", "TextLog:text")


class InspectError(Exception):
    """The file is missing, unreadable, or not a fednav recording."""


@dataclass
class Series:
    """One entity's rows sorted by sensor time: ``t_ns`` int64; ``values`` float array or list of str."""

    t_ns: np.ndarray
    values: Any

    def __len__(self) -> int:
        return len(self.t_ns)


# --- reading ---------------------------------------------------------------------------------------
def read_series(path: str | Path) -> tuple[dict[str, Any], dict[str, Series]]:
    """Read the first recording of an .rrd: (store info, entity path -> Series).

    Scalars keep their first instance (the +3σ series of bounds); StateChange / TextLog their text.
    """
    from rerun.chunk import RrdReader

    p = Path(path)
    if not p.is_file():
        raise InspectError(f"{p}: no such file")
    try:
        reader = RrdReader(p)
        recordings = reader.recordings()
        blueprints = reader.blueprints()
    except Exception as exc:
        raise InspectError(f"{p}: not a readable Rerun recording ({exc})") from exc
    if not recordings:
        raise InspectError(f"{p}: the file holds no recording")
    store = recordings[0]
    info = {
        "recording_id": store.recording_id,
        "application_id": store.application_id,
        "blueprints": len(blueprints),
        "recordings": len(recordings),
    }

    t_parts: dict[str, list[np.ndarray]] = defaultdict(list)
    v_parts: dict[str, list[Any]] = defaultdict(list)
    kind: dict[str, str] = {}
    try:
        stream = reader.stream(store=store).filter(has_timeline=paths.TIMELINE, components=list(_COMPONENTS))
        for chunk in stream:
            batch: pa.RecordBatch = chunk.to_record_batch()
            names = batch.schema.names
            if paths.TIMELINE not in names:
                continue
            t = pc.cast(batch.column(paths.TIMELINE), pa.int64()).to_numpy(zero_copy_only=False)
            for comp in _COMPONENTS:
                if comp not in names:
                    continue
                col = batch.column(comp)
                first = pc.list_element(col, 0)
                if comp == "Scalars:scalars":
                    vals = first.to_numpy(zero_copy_only=False).astype(np.float64)
                    kind[chunk.entity_path] = "scalar"
                else:
                    vals = first.to_pylist()
                    kind[chunk.entity_path] = "text"
                t_parts[chunk.entity_path].append(t)
                v_parts[chunk.entity_path].append(vals)
    except InspectError:
        raise
    except Exception as exc:
        raise InspectError(f"{p}: failed while reading chunks ({exc})") from exc

    out: dict[str, Series] = {}
    for ent, ts in t_parts.items():
        t = np.concatenate(ts)
        order = np.argsort(t, kind="stable")
        if kind[ent] == "scalar":
            vals = np.concatenate(v_parts[ent])[order]
        else:
            flat = [x for part in v_parts[ent] for x in part]
            vals = [flat[i] for i in order]
        out[ent] = Series(t[order], vals)
    return info, out


# --- statistics ------------------------------------------------------------------------------------
def _f(x: float | None) -> float | None:
    """JSON-safe float (NaN/inf -> None)."""
    if x is None:
        return None
    x = float(x)
    return x if math.isfinite(x) else None


def _align(base: Series, other: Series | None) -> np.ndarray:
    """Values of ``other`` at the exact times of ``base`` (NaN where absent)."""
    out = np.full(len(base), np.nan)
    if other is None or len(other) == 0:
        return out
    idx = np.searchsorted(other.t_ns, base.t_ns, side="right") - 1  # last row at or before t
    ok = idx >= 0
    ok[ok] = other.t_ns[idx[ok]] == base.t_ns[ok]
    out[ok] = np.asarray(other.values, dtype=np.float64)[idx[ok]]
    return out


def _rms(x: np.ndarray) -> float:
    return float(np.sqrt(np.mean(np.square(x)))) if len(x) else math.nan


def _pipeline_summary(v: str, p: str, data: dict[str, Series]) -> dict[str, Any]:
    lat = data.get(paths.solution(v, p, "lat_deg"))
    status = data.get(paths.solution(v, p, "status"))
    res: dict[str, Any] = {"vehicle": v, "solutions": len(lat) if lat is not None else 0}
    if lat is not None and len(lat):
        res["t_start"], res["t_end"] = lat.t_ns[0] / 1e9, lat.t_ns[-1] / 1e9
    res["final_status"] = status.values[-1] if status is not None and len(status) else None
    res["status_changes"] = len(status) if status is not None else 0
    rms: dict[str, float | None] = {}
    mx: dict[str, float | None] = {}
    mean: dict[str, float | None] = {}
    outside: dict[str, float | None] = {}
    for name in paths.ERROR_NAMES:
        s = data.get(paths.error(v, p, name))
        if s is None or len(s) == 0:
            continue
        x = np.asarray(s.values)
        rms[name], mx[name], mean[name] = _f(_rms(x)), _f(np.max(np.abs(x))), _f(np.mean(x))
        b = _align(s, data.get(paths.bound(v, p, name)))
        has = np.isfinite(b)
        if has.any():
            outside[name] = _f(np.mean(np.abs(x[has]) > b[has]))
    east, north = data.get(paths.error(v, p, "east_m")), data.get(paths.error(v, p, "north_m"))
    if east is not None and north is not None and len(east):
        n_at = _align(east, north)
        ok = np.isfinite(n_at)
        h = np.hypot(np.asarray(east.values)[ok], n_at[ok])
        if len(h):
            rms["horizontal_m"], mx["horizontal_m"] = _f(_rms(h)), _f(np.max(h))
    res["error_epochs"] = len(data[paths.error(v, p, "east_m")]) if east is not None else 0
    res["rms"], res["max"], res["mean"], res["outside_3sigma"] = rms, mx, mean, outside
    res["h_rms_m"] = rms.get("horizontal_m")
    res["h_max_m"] = mx.get("horizontal_m")
    return res


def _stanford_counts(
    err: Series | None, pl: Series | None, al: Series | None, alarm: Series | None
) -> dict[str, int] | None:
    if err is None or pl is None or len(err) == 0:
        return None
    e = np.abs(np.asarray(err.values))
    pl_v, al_v, alarm_v = _align(err, pl), _align(err, al), _align(err, alarm)
    counts = dict.fromkeys(paths.STANFORD_REGIONS, 0)
    for ei, pli, ali, ai in zip(e, pl_v, al_v, alarm_v, strict=True):
        if not math.isfinite(pli):
            continue
        region = paths.stanford_region(
            ei, pli, ali if math.isfinite(ali) else None, bool(ai > 0.5) if math.isfinite(ai) else False
        )
        counts[region] += 1
    counts["total"] = sum(counts.values())
    return counts


def _integrity_summary(v: str, p: str, data: dict[str, Series]) -> dict[str, Any] | None:
    def s(leaf: str) -> Series | None:
        return data.get(paths.integrity(v, p, leaf))

    hpl = s("hpl_m")
    if hpl is None or len(hpl) == 0:
        return None
    vpl, alarm, avail, det = s("vpl_m"), s("alarm"), s("available"), s("detected")
    herr, verr = s("h_error_m"), s("v_error_m")
    hpl_v = np.asarray(hpl.values)
    res: dict[str, Any] = {
        "vehicle": v,
        "epochs": len(hpl),
        "hpl_median_m": _f(np.median(hpl_v)),
        "hpl_max_m": _f(np.max(hpl_v)),
    }
    if vpl is not None and len(vpl):
        res["vpl_median_m"], res["vpl_max_m"] = _f(np.median(vpl.values)), _f(np.max(vpl.values))
    for leaf in ("hal_m", "val_m"):
        x = s(leaf)
        res[leaf] = _f(x.values[-1]) if x is not None and len(x) else None

    def count(x: Series | None, want: bool = True) -> int:
        if x is None:
            return 0
        return int(np.sum((np.asarray(x.values) > 0.5) == want))

    res["alarm_epochs"] = count(alarm)
    res["unavailable_epochs"] = count(avail, want=False)
    res["detected_epochs"] = count(det)
    events = data.get(paths.integrity_events(v, p))
    texts = list(events.values) if events is not None else []
    res["detection_events"] = sum(1 for x in texts if x.startswith("detection"))
    res["alarm_events"] = sum(1 for x in texts if x.startswith("alarm"))
    excl = [x for x in texts if x.startswith("exclusion: ")]
    res["exclusion_events"] = len(excl)
    res["excluded_sats"] = sorted({sat for x in excl for sat in x[len("exclusion: ") :].split(",") if sat})
    if herr is not None and len(herr):
        e = np.abs(np.asarray(herr.values))
        pl_at, alarm_at = _align(herr, hpl), _align(herr, alarm)
        no_alarm = ~(alarm_at > 0.5)
        res["hmi_epochs"] = int(np.sum((e > pl_at) & no_alarm))  # error above HPL without alarm
        res["h_error_rms_m"], res["h_error_max_m"] = _f(_rms(e)), _f(np.max(e))
    else:
        res["hmi_epochs"] = None
    res["stanford_h"] = _stanford_counts(herr, hpl, s("hal_m"), alarm)
    res["stanford_v"] = _stanford_counts(verr, vpl, s("val_m"), alarm) if s("val_m") is not None else None
    return res


def _faults_summary(v: str, p: str, data: dict[str, Series]) -> dict[str, Any] | None:
    root = paths.faults(v, p) + "/"
    obs: dict[str, dict[str, Any]] = {}
    sub_iso: dict[str, int] = {}
    for ent, s in data.items():
        if not ent.startswith(root):
            continue
        rest = ent[len(root) :].split("/")
        if len(rest) == 2 and rest[1] == "subsystem_isolated":
            sub_iso[rest[0]] = sum(1 for x in s.values if x == "isolated")
        elif len(rest) == 3 and rest[2] == "flagged":
            key = f"{rest[0]}/{rest[1]}"
            stat = data.get(paths.faults(v, p, rest[0], rest[1], "statistic"))
            obs[key] = {
                "tests": len(s),
                "flagged": sum(1 for x in s.values if x != "ok"),
                "isolated": sum(1 for x in s.values if x == "isolated"),
                "max_statistic": _f(np.max(stat.values)) if stat is not None and len(stat) else None,
            }
    sharing_root = paths.sharing(v, p) + "/"
    sharing: dict[str, dict[str, float | None]] = defaultdict(dict)
    for ent, s in data.items():
        if ent.startswith(sharing_root) and len(s):
            local, _, state = ent[len(sharing_root) :].partition("/")
            sharing[local][state] = _f(s.values[-1])
    if not obs and not sub_iso and not sharing:
        return None
    return {
        "vehicle": v,
        "observations": dict(sorted(obs.items())),
        "flagged": {k: o["flagged"] for k, o in sorted(obs.items())},
        "subsystem_isolated_epochs": dict(sorted(sub_iso.items())),
        "sharing_last": {
            k: dict(sorted(d.items(), key=lambda kv: (len(kv[0]), kv[0]))) for k, d in sorted(sharing.items())
        },
    }


def _health_summary(v: str, data: dict[str, Series]) -> dict[str, Any] | None:
    out = {}
    for name in paths.HEALTH_SCALARS:
        s = data.get(paths.health(v, name))
        if s is not None and len(s):
            out[name] = _f(s.values[-1])
    return out or None


def summarize(info: dict[str, Any], data: dict[str, Series], file: str) -> dict[str, Any]:
    """Summary dict (the ``--json`` document) of series read by :func:`read_series`."""
    layout: dict[str, set[str]] = defaultdict(set)
    t_min, t_max = math.inf, -math.inf
    for ent, s in data.items():
        parsed = paths.parse(ent)
        if parsed is None or len(s) == 0:
            continue
        pipelines = layout[parsed.vehicle]  # registers the vehicle
        if parsed.is_pipeline:
            pipelines.add(parsed.source)
        t_min, t_max = min(t_min, s.t_ns[0]), max(t_max, s.t_ns[-1])
    vehicles = sorted(layout)
    single = len(vehicles) == 1
    result: dict[str, Any] = {
        "file": file,
        "recording_id": info["recording_id"],
        "application_id": info["application_id"],
        "has_blueprint": info["blueprints"] > 0,
        "t_start": t_min / 1e9 if vehicles else None,
        "t_end": t_max / 1e9 if vehicles else None,
        "duration_s": (t_max - t_min) / 1e9 if vehicles else 0.0,
        "vehicles": vehicles,
        "pipelines": {},
        "integrity": {},
        "faults": {},
        "health": {},
    }
    for v in vehicles:
        for p in sorted(layout[v]):
            key = p if single else f"{v}/{p}"
            result["pipelines"][key] = _pipeline_summary(v, p, data)
            integ = _integrity_summary(v, p, data)
            if integ is not None:
                result["integrity"][key] = integ
            flt = _faults_summary(v, p, data)
            if flt is not None:
                result["faults"][key] = flt
        h = _health_summary(v, data)
        if h is not None:
            result["health"][v] = h
    return result


def inspect_rrd(path: str | Path) -> dict[str, Any]:
    """Summary of a fednav .rrd (see the module docstring). Raises :class:`InspectError`."""
    info, data = read_series(path)
    return summarize(info, data, str(path))


# --- text rendering --------------------------------------------------------------------------------
def _fmt(x: float | None, spec: str = ".4g") -> str:
    return "-" if x is None else format(x, spec)


def render_text(s: dict[str, Any]) -> str:
    lines = [
        f"file: {s['file']}",
        f"recording: {s['recording_id']} (application {s['application_id']}), "
        f"blueprint embedded: {'yes' if s['has_blueprint'] else 'no'}",
    ]
    if s["t_start"] is None:
        lines.append("no data on the sensor_time timeline")
        return "\n".join(lines)
    lines.append(f"sensor time: {s['t_start']:.3f} .. {s['t_end']:.3f} s  (duration {s['duration_s']:.3f} s)")
    lines.append(f"vehicles: {', '.join(s['vehicles'])}")
    for key, p in s["pipelines"].items():
        lines.append(
            f"pipeline {key}: {p['solutions']} solutions, final status {p['final_status']}, "
            f"{p['error_epochs']} epochs with errors vs truth"
        )
        if p["rms"]:
            lines.append(f"    {'error':<14}{'RMS':>12}{'max':>12}{'mean':>12}{'>3σ':>9}")
            for name in (*paths.ERROR_NAMES, "horizontal_m"):
                if name in p["rms"]:
                    out = p["outside_3sigma"].get(name)
                    lines.append(
                        f"    {name:<14}{_fmt(p['rms'][name]):>12}{_fmt(p['max'][name]):>12}"
                        f"{_fmt(p['mean'].get(name)):>12}"
                        f"{'-' if out is None else format(100 * out, '.1f') + '%':>9}"
                    )
    for key, f in s["faults"].items():
        lines.append(f"faults {key}:")
        for label, o in f["observations"].items():
            lines.append(
                f"    {label:<24} flagged {o['flagged']}/{o['tests']} (isolated {o['isolated']}), "
                f"max statistic {_fmt(o['max_statistic'])}"
            )
        for sub, n in f["subsystem_isolated_epochs"].items():
            if n:
                lines.append(f"    subsystem {sub} isolated in {n} epochs")
    for key, i in s["integrity"].items():
        lines.append(
            f"integrity {key}: {i['epochs']} epochs, HPL median {_fmt(i['hpl_median_m'])} m "
            f"max {_fmt(i['hpl_max_m'])} m (HAL {_fmt(i['hal_m'])} m), VPL median "
            f"{_fmt(i.get('vpl_median_m'))} m max {_fmt(i.get('vpl_max_m'))} m "
            f"(VAL {_fmt(i['val_m'])} m)"
        )
        lines.append(
            f"    alarms {i['alarm_epochs']} epochs ({i['alarm_events']} events), detections "
            f"{i['detected_epochs']} epochs ({i['detection_events']} events), exclusions "
            f"{i['exclusion_events']} {i['excluded_sats']}, unavailable {i['unavailable_epochs']} "
            f"epochs, HMI epochs (error > HPL, no alarm) {_fmt(i['hmi_epochs'], 'd')}"
        )
        for axis in ("h", "v"):
            st = i[f"stanford_{axis}"]
            if st:
                lines.append(
                    f"    Stanford ({'horizontal' if axis == 'h' else 'vertical'}): "
                    + ", ".join(f"{k} {v}" for k, v in st.items())
                )
    for v, h in s["health"].items():
        lines.append(f"health {v} (last): " + ", ".join(f"{k} {_fmt(x, 'g')}" for k, x in h.items()))
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(
        prog="fednav-inspect", description="Summarise a fednav Rerun recording (.rrd) without a viewer"
    )
    ap.add_argument("file", type=Path, help="recording to read")
    ap.add_argument("--json", action="store_true", help="print one JSON object instead of text")
    args = ap.parse_args(argv)
    try:
        summary = inspect_rrd(args.file)
    except InspectError as exc:
        print(f"fednav-inspect: error: {exc}", file=sys.stderr)
        return 2
    if args.json:
        print(json.dumps(summary, indent=2, allow_nan=False))
    else:
        print(render_text(summary))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
