"""``fednav-inspect FILE.rrd [--json]``: headless summary of a fednav recording.

Reads the recording back with Rerun's own reader (``rerun.chunk.RrdReader``, rerun-sdk 0.41) and
summarises it from the entity layout of ``service.transport.rerun_paths``: recording id, time span,
vehicles and pipelines; per pipeline the number of solutions, RMS / max of each error against truth
(and the horizontal error sqrt(e^2 + n^2)), the share of epochs outside the ±3σ bound and the final
status; fault tests (flagged observations per label); integrity (HPL/VPL statistics, alarms,
detections, exclusions, HMI epochs, Stanford-diagram regions); the last health counters.

A real run has no truth: per pipeline inspect also gives the status timeline (time in each status,
re-initialisations), solution gaps, the median 1-sigma once aided, the recorded Faults per
subsystem and row against their expected rate (gate refusals against the fixes received), the
consistency of the claimed sigma from the recording alone (update jumps x fix residuals, whose
expectation is the claimed posterior variance: :func:`_fix_residual_consistency`) with the
innovations' whiteness, and one verdict line. The final status is the last recorded one; when
the recording's last Health rows repeat the same sensor time, the input had stopped and the
service's Health said coasting: both are said (``input_stopped``). ``--config SERVICE.toml``: the
run's configuration (lever arm, correlated-error states) refines the consistency check.

``inspect_rrd(path) -> dict`` is the library entry point (the ``--json`` output). Result keys for
pipelines are the pipeline name when the file holds one vehicle, else ``"{vehicle}/{pipeline}"``.
Exit codes: 0 ok, 2 file missing, unreadable, or holding no fednav recording.
"""

from __future__ import annotations

import argparse
import json
import math
import shutil
import struct
import sys
import tempfile
import warnings
from collections import defaultdict
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import pyarrow as pa
import pyarrow.compute as pc

from fednav.dashboards import quiet_closed_stdout
from fednav.service.transport import rerun_paths as paths

_COMPONENTS = ("Scalars:scalars", "StateChange:state", "TextLog:text", "Points2D:positions")


class InspectError(Exception):
    """The file is missing, unreadable, or not a fednav recording."""


@dataclass
class Series:
    """One entity's rows sorted by sensor time: ``t_ns`` int64; ``values`` float array, (N, 2) float
    array (2-D points: the ENU views, x = east, y = -north) or list of str."""

    t_ns: np.ndarray
    values: Any

    def __len__(self) -> int:
        return len(self.t_ns)


# --- reading ---------------------------------------------------------------------------------------
def read_series(path: str | Path, timeline: str = paths.TIMELINE) -> tuple[dict[str, Any], dict[str, Series]]:
    """Read the first recording of an .rrd: (store info, entity path -> Series on ``timeline``).

    Scalars keep their first instance (the +3σ series of bounds); StateChange / TextLog their text.
    """
    from rerun.chunk import RrdReader

    p = Path(path)
    if not p.is_file():
        raise InspectError(f"{p}: no such file")
    truncated = None
    try:
        with warnings.catch_warnings(record=True) as caught:
            warnings.simplefilter("always")
            reader = RrdReader(p)
            recordings = reader.recordings()
            blueprints = reader.blueprints()
        if any("no footer" in str(w.message) for w in caught):
            truncated = {"read_bytes": p.stat().st_size, "lost_bytes": 0}  # not closed by its writer
    except Exception as exc:
        cut = whole_messages(p)
        if cut is None:
            raise InspectError(f"{p}: not a readable Rerun recording ({exc})") from exc
        # a recording whose writer died mid-message (SIGKILL, power loss, a full disk): its whole
        # messages are read from a copy, and the summary says what was lost
        read_bytes, size = cut
        with tempfile.NamedTemporaryFile(suffix=".rrd", delete=False) as f:
            with open(p, "rb") as src:
                shutil.copyfileobj(_limited(src, read_bytes), f)
        copy = Path(f.name)
        try:
            lost = {"read_bytes": read_bytes, "lost_bytes": size - read_bytes}
            return _read_series_of(copy, timeline, lost)
        finally:
            copy.unlink(missing_ok=True)
    return _read_reader(p, reader, recordings, blueprints, timeline, truncated)


#: the framing of an .rrd (rerun-sdk 0.41, ``re_log_encoding``): a 12-byte file header (``RRF2``,
#: version, options), then messages of a little-endian u64 kind and u64 length and that many
#: bytes; kind 0 ends the stream (its footer follows)
_RRD_MAGIC = b"RRF2"
_RRD_HEADER = 12
_RRD_KIND_MAX = 64


def whole_messages(path: Path) -> tuple[int, int] | None:
    """(bytes of the file's whole messages, file size) when the file is an .rrd whose last message
    runs past its end (the writer died mid-write), else None (not that kind of file, or a message
    header that is not one: corruption this does not repair)."""
    size = path.stat().st_size
    with open(path, "rb") as f:
        if f.read(4) != _RRD_MAGIC:
            return None
        pos = _RRD_HEADER
        while pos + 16 <= size:
            f.seek(pos)
            kind, length = struct.unpack("<QQ", f.read(16))
            if kind > _RRD_KIND_MAX:
                return None
            if kind == 0 or pos + 16 + length > size:
                break
            pos += 16 + length
    return (pos, size) if pos < size and pos > _RRD_HEADER else None


def _limited(src, n: int):
    """A reader of the first ``n`` bytes of ``src``."""

    class _Head:
        left = n

        def read(self, k: int = -1) -> bytes:
            k = self.left if k < 0 else min(k, self.left)
            data = src.read(k)
            self.left -= len(data)
            return data

    return _Head()


def _read_series_of(p: Path, timeline: str, truncated: dict | None):
    from rerun.chunk import RrdReader

    try:
        with warnings.catch_warnings():  # "no footer": said by the summary (the copy has none)
            warnings.simplefilter("ignore")
            reader = RrdReader(p)
            recordings = reader.recordings()
            blueprints = reader.blueprints()
    except Exception as exc:
        raise InspectError(f"{p}: not a readable Rerun recording ({exc})") from exc
    return _read_reader(p, reader, recordings, blueprints, timeline, truncated)


def _read_reader(p: Path, reader, recordings, blueprints, timeline: str, truncated: dict | None):
    if not recordings:
        raise InspectError(f"{p}: the file holds no recording")
    store = recordings[0]
    info = {
        "recording_id": store.recording_id,
        "application_id": store.application_id,
        "blueprints": len(blueprints),
        "recordings": len(recordings),
        "unfinished": truncated,
    }

    t_parts: dict[str, list[np.ndarray]] = defaultdict(list)
    v_parts: dict[str, list[Any]] = defaultdict(list)
    kind: dict[str, str] = {}
    try:
        stream = reader.stream(store=store).filter(has_timeline=timeline, components=list(_COMPONENTS))
        for chunk in stream:
            batch: pa.RecordBatch = chunk.to_record_batch()
            names = batch.schema.names
            if timeline not in names:
                continue
            t = pc.cast(batch.column(timeline), pa.int64()).to_numpy(zero_copy_only=False)
            for comp in _COMPONENTS:
                if comp not in names:
                    continue
                col = batch.column(comp)
                first = pc.list_element(col, 0)
                if comp == "Scalars:scalars":
                    vals = first.to_numpy(zero_copy_only=False).astype(np.float64)
                    kind[chunk.entity_path] = "scalar"
                elif comp == "Points2D:positions":
                    flat = pc.list_flatten(first).to_numpy(zero_copy_only=False).astype(np.float64)
                    vals = flat.reshape(-1, 2)
                    kind[chunk.entity_path] = "points"
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
        if kind[ent] in ("scalar", "points"):
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


def _flag_counts(flag: Series, stat: Series | None, thr: Series | None) -> tuple[int, int]:
    """(rows that failed their own test, rows isolated) of one recorded observation. A row can be
    isolated without failing its test (with its subsystem, or as the rest of a failing row's
    source: ``per_source`` and the loosely coupled gate): failed is statistic > threshold where
    both were recorded with the state, else any state but ``ok``."""
    states = np.asarray(flag.values, dtype=object)
    isolated = int(np.count_nonzero(states == "isolated"))
    bad = states != "ok"
    if stat is not None and thr is not None:
        st, th = _align(flag, stat), _align(flag, thr)
        known = np.isfinite(st) & np.isfinite(th)
        bad = np.where(known, st > th, bad)
    return int(np.count_nonzero(bad)), isolated


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
    res["truth_verdict"] = _truth_verdict(outside)
    res["h_rms_m"] = rms.get("horizontal_m")
    res["h_max_m"] = mx.get("horizontal_m")
    return res


#: share of position errors beyond the reported 3 sigma, per axis: a consistent filter (Gaussian
#: errors) has 0.27 %; up to CONSISTENT_3SIGMA it is called consistent against the truth
CONSISTENT_3SIGMA = 0.01
OVERCONFIDENT_3SIGMA = 0.05


def _truth_verdict(outside: dict[str, float | None]) -> str | None:
    """What the truth says of the reported position sigma: the share of errors beyond 3 sigma."""
    pos = {k: outside.get(k) for k in ("east_m", "north_m", "up_m")}
    pos = {k: v for k, v in pos.items() if v is not None}
    if not pos:
        return None
    worst = max(pos, key=lambda k: pos[k])
    shares = "/".join(f"{100 * v:.1f}" for v in pos.values())
    text = f"position errors beyond 3 sigma E/N/U {shares} % (a consistent filter: 0.3 %)"
    if pos[worst] <= CONSISTENT_3SIGMA:
        return f"consistent: {text}"
    kind = "overconfident" if pos[worst] > OVERCONFIDENT_3SIGMA else "somewhat overconfident"
    return f"{kind} in {worst[:-2]}: {text}"


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
            flagged, isolated = _flag_counts(
                s, stat, data.get(paths.faults(v, p, rest[0], rest[1], "threshold"))
            )
            obs[key] = {
                "tests": len(s),
                "flagged": flagged,
                "isolated": isolated,
                "max_statistic": _f(np.max(stat.values)) if stat is not None and len(stat) else None,
            }
    sharing_root = paths.sharing(v, p) + "/"
    sharing: dict[str, dict[str, float | None]] = defaultdict(dict)
    for ent, s in data.items():
        if ent.startswith(sharing_root) and len(s):
            local, _, state = ent[len(sharing_root) :].partition("/")
            sharing[local][state] = _f(s.values[-1])
    # the private filter states a pipeline reports on Faults (estimated lever arm, scale factors,
    # DVL offset): the last value and 1-sigma of each
    states_root = paths.filter_state(v, p) + "/"
    states: dict[str, dict[str, float | None]] = defaultdict(dict)
    for ent, s in data.items():
        if ent.startswith(states_root) and len(s):
            name, _, leaf = ent[len(states_root) :].partition("/")
            if leaf in ("value", "std"):
                states[name][leaf] = _f(s.values[-1])
    if not obs and not sub_iso and not sharing and not states:
        return None
    return {
        "vehicle": v,
        "states_last": {k: dict(sorted(d.items(), reverse=True)) for k, d in sorted(states.items())},
        "observations": dict(sorted(obs.items())),
        "flagged": {k: o["flagged"] for k, o in sorted(obs.items())},
        "subsystem_isolated_epochs": dict(sorted(sub_iso.items())),
        "sharing_last": {
            k: dict(sorted(d.items(), key=lambda kv: (len(kv[0]), kv[0]))) for k, d in sorted(sharing.items())
        },
    }


def _health_summary(v: str, data: dict[str, Series]) -> dict[str, Any] | None:
    out: dict[str, Any] = {}
    for name in paths.HEALTH_SCALARS:
        s = data.get(paths.health(v, name))
        if s is not None and len(s):
            out[name] = _f(s.values[-1])
    root = paths.health_rejected(v, "_")[:-1]
    reasons = {e[len(root) :]: _f(x.values[-1]) for e, x in data.items() if e.startswith(root) and len(x)}
    if reasons:
        out["rejected"] = dict(sorted(reasons.items(), key=lambda kv: -kv[1]))
    return out or None


# --- a real run without truth: consistency, screening, status -----------------------------------------
#: A pipeline's claimed sigma is called off when the evidence puts the real error this many times
#: above or below it (and the figure's own uncertainty does not reach back to 1)
CONSISTENT_FACTOR = 1.5
SETTLE_S = 10.0  # the first seconds after a pipeline is first aided are not judged
#: lag-1 autocorrelation of the fix innovations above which they are not white (and at least 4
#: standard errors, 1/sqrt(n)): measured on the simulated drives, white fixes 0.07 at most, fixes
#: with a 30 s Gauss-Markov error twice their white part 0.33-0.49
LAG1_CORRELATED = 0.2
CHI2_1_MEDIAN = 0.454936  # median of chi-square with one degree of freedom
#: Health rows at the same sensor time after the input stopped: the service reports once a second
#: (output.health_period_s), and calls a pipeline coasting when no input came for 2 s of wall time
#: (service.vehicle.STALE_WALL_S): three such rows mean its Health said coasting.
STOPPED_HEALTH_ROWS = 3


def _status_timeline(status: Series | None, t_end: float | None) -> dict[str, Any]:
    """Status changes, time per status, re-initialisations: back to ``initialising`` (the INS
    lost) or to ``unaided`` (a restart: a pipeline is unaided from its start until aided) from
    another status after the first (a restart straight to unaided, e.g. after a time jump whose
    alignment took less than a solution period, used to go uncounted)."""
    if status is None or len(status) == 0:
        return {"changes": [], "time_in_s": {}, "reinitialisations": 0}
    t = status.t_ns / 1e9
    vals = list(status.values)
    end = max(t_end if t_end is not None else t[-1], t[-1])
    dur: dict[str, float] = defaultdict(float)
    for i, v in enumerate(vals):
        dur[v] += (t[i + 1] if i + 1 < len(vals) else end) - t[i]
    fresh = ("initialising", "unaided")
    reinit = sum(1 for i, v in enumerate(vals) if i > 0 and v in fresh and vals[i - 1] not in fresh)
    changes = [{"t": float(a), "status": v} for a, v in zip(t, vals, strict=True)]
    return {
        "changes": changes,
        "time_in_s": {k: float(v) for k, v in dur.items()},
        "reinitialisations": reinit,
    }


def _gaps(t_ns: np.ndarray, min_gap_s: float = 1.0) -> list[dict[str, float]]:
    """Intervals between rows longer than max(3 x the median step, ``min_gap_s``)."""
    if len(t_ns) < 3:
        return []
    t = t_ns / 1e9
    d = np.diff(t)
    lim = max(3.0 * float(np.median(d)), min_gap_s)
    return [{"t": float(t[i]), "length_s": float(d[i])} for i in np.flatnonzero(d > lim)]


def _sigma_levels(v: str, p: str, data: dict[str, Series], t_from: float | None) -> dict[str, Any]:
    """Median and last reported 1-sigma per solution component (after ``t_from``)."""
    out: dict[str, Any] = {}
    for name in paths.STD_SCALARS:
        sd = data.get(paths.solution_std(v, p, name))
        if sd is None or len(sd) == 0:
            continue
        x = np.asarray(sd.values)
        if t_from is not None:
            keep = sd.t_ns / 1e9 >= t_from
            x = x[keep] if keep.any() else x
        out[name] = {"median": _f(np.median(x)), "last": _f(sd.values[-1])}
    return out


def _enu_ref(
    lat_deg: np.ndarray, lon_deg: np.ndarray, h: np.ndarray, pts: np.ndarray
) -> tuple[float, float, float]:
    """The recording's ENU reference (the sink's first position of the vehicle) from solution rows
    and their recorded ENU points: solved at the row nearest to it (float32 points are exact there)."""
    from fednav.service import earth

    i = int(np.argmin(np.hypot(pts[:, 0], pts[:, 1])))
    lat_ref, lon_ref, h_ref = math.radians(lat_deg[i]), math.radians(lon_deg[i]), float(h[i])
    e, n = pts[i, 0], -pts[i, 1]
    for _ in range(3):
        r_m, r_n = earth.radii(lat_ref)
        lat_ref = math.radians(lat_deg[i]) - n / (r_m + h_ref)
        lon_ref = math.radians(lon_deg[i]) - e / ((r_n + h_ref) * math.cos(lat_ref))
    return lat_ref, lon_ref, h_ref


def _fix_residual_consistency(
    v: str, p: str, data: dict[str, Series], t_from: float | None, lever_arm=None
) -> dict[str, Any] | None:
    """Consistency of the claimed horizontal sigma from the recorded fixes and solutions, without
    truth and without the fixes' sigmas.

    At a fix, the update moves the solution by D = K nu (nu: the innovation) and leaves it at the
    residual d = fix - solution = (I - H K) nu; their product has expectation
    E[D d'] = H K S (I - H K)' = H P+ H' (the update's own identity: S = H P- H' + R,
    P+ = (I - K H) P-). So mean(D_e d_e) / mean(P+_ee), per horizontal axis, is the ratio of the
    actual innovation variance to the one the filter claims: 1 consistent, k^2 when the real errors
    are k times the claimed ones. D is the solution just after the fix minus the one before it
    carried forward to the fix time with its velocity and acceleration; d uses the fixes recorded
    on the ENU view (``service/inputs``); P+ the recorded 1-sigma (interpolated, 1 Hz). Holds for
    fixes fused as independent; an antenna lever arm only adds scatter (it is the same at D's both
    ends); with ``gnss_correlated_error`` part of d is the estimated receiver error, not recorded:
    the ratio reads low (the caller says so)."""
    from fednav.service import earth

    lat, lon = data.get(paths.solution(v, p, "lat_deg")), data.get(paths.solution(v, p, "lon_deg"))
    h = data.get(paths.solution(v, p, "height_m"))
    ve, vn = data.get(paths.solution(v, p, "ve_mps")), data.get(paths.solution(v, p, "vn_mps"))
    pts = data.get(paths.enu(v, p))
    sd_e, sd_n = data.get(paths.solution_std(v, p, "pos_e_m")), data.get(paths.solution_std(v, p, "pos_n_m"))
    series = (lat, lon, h, ve, vn, pts, sd_e, sd_n)
    if any(x is None or len(x) < 10 for x in series):
        return None
    if not all(len(x) == len(lat) and np.array_equal(x.t_ns, lat.t_ns) for x in (lon, h, ve, vn, pts)):
        return None
    # one row per output time: the service's last solutions at shutdown repeat the latest time
    last = np.append(np.diff(lat.t_ns) > 0, True)
    if not last.all():
        lat, lon, h, ve, vn, pts = (
            Series(x.t_ns[last], np.asarray(x.values)[last]) for x in (lat, lon, h, ve, vn, pts)
        )
    ts = lat.t_ns / 1e9
    lat_ref, lon_ref, h_ref = _enu_ref(
        np.asarray(lat.values), np.asarray(lon.values), np.asarray(h.values), np.asarray(pts.values)
    )
    r_m, r_n = earth.radii(lat_ref)
    e = np.radians(np.asarray(lon.values)) - lon_ref
    e = e * (r_n + h_ref) * math.cos(lat_ref)
    n = (np.radians(np.asarray(lat.values)) - lat_ref) * (r_m + h_ref)
    pos = np.stack([e, n], axis=1)
    vel = np.stack([np.asarray(ve.values), np.asarray(vn.values)], axis=1)
    if lever_arm is not None and any(lever_arm):
        hd = np.radians(np.asarray(data[paths.solution(v, p, "heading_deg")].values))
        lr, lf = lever_arm[0], lever_arm[1]  # body right/forward -> east/north at the heading
        pos = pos + np.stack([lr * np.cos(hd) + lf * np.sin(hd), -lr * np.sin(hd) + lf * np.cos(hd)], axis=1)
    root = f"/{paths.part(v)}/{paths.SERVICE}/inputs/"
    out: dict[str, Any] = {}
    for ent, fx in data.items():
        if not (ent.startswith(root) and ent.endswith("/enu")) or len(fx) < 10:
            continue
        sensor = ent[len(root) : -len("/enu")]
        tf = fx.t_ns / 1e9
        f_en = np.stack([fx.values[:, 0], -fx.values[:, 1]], axis=1)
        # the rows around the update: the last one before the fix and the first one half an output
        # period after it (a row at the fix's own time may come before or after the update,
        # depending on which message reached the engine first)
        step = float(np.median(np.diff(ts)))
        a = np.searchsorted(ts, tf - 1e-4) - 1  # last row before the fix
        b = np.searchsorted(ts, tf + 0.5 * step)  # first row clearly after it
        ok = (a >= 1) & (b < len(ts) - 1)
        a, b = np.clip(a, 1, len(ts) - 2), np.clip(b, 1, len(ts) - 2)
        ok &= (tf - ts[a] <= 2.5 * step) & (ts[b] - tf <= 2.5 * step)
        if t_from is not None:
            ok &= tf >= t_from
        if ok.sum() < 20:
            continue
        a, b, tf, f_en = a[ok], b[ok], tf[ok], f_en[ok]
        tau, dlt = (tf - ts[a])[:, None], (ts[b] - tf)[:, None]
        acc_a = (vel[a] - vel[a - 1]) / (ts[a] - ts[a - 1])[:, None]  # accelerations away from the update
        acc_b = (vel[b + 1] - vel[b]) / (ts[b + 1] - ts[b])[:, None]
        before = pos[a] + vel[a] * tau + 0.5 * acc_a * tau**2
        after = pos[b] - vel[b] * dlt + 0.5 * acc_b * dlt**2
        jump, resid = after - before, f_en - after
        var = np.stack(
            [
                np.interp(tf, sd_e.t_ns / 1e9, np.square(sd_e.values)),
                np.interp(tf, sd_n.t_ns / 1e9, np.square(sd_n.values)),
            ],
            axis=1,
        )
        prod = jump * resid
        good = np.isfinite(prod).all(axis=1) & np.isfinite(var).all(axis=1)
        prod, var, resid = prod[good], var[good], resid[good]
        if len(prod) < 20:
            continue
        # the innovations' whiteness: fix minus the prediction, consecutive fixes (a consistent
        # filter's innovations are white; fixes whose error is slow give correlated ones)
        nu = (f_en - before)[good]
        tg = tf[good]
        # a fault episode (fixes tens of metres off for a while, refused by the gate) is not the
        # receiver's usual slow error: innovations beyond OUTLIER_MADS robust sigmas are left out
        # of the whiteness (a demo's injected GNSS fault read as "the fixes' error is slow")
        dev = np.abs(nu - np.median(nu, axis=0))
        inlier = (dev <= OUTLIER_MADS * np.maximum(1.4826 * np.median(dev, axis=0), 1e-9)).all(axis=1)
        consecutive = (np.diff(tg) <= 1.5 * float(np.median(np.diff(tg)))) & inlier[1:] & inlier[:-1]
        axes = {}
        for k, name in enumerate(("east", "north")):
            ratio = float(prod[:, k].mean() / var[:, k].mean())
            se = float(prod[:, k].std() / math.sqrt(len(prod)) / var[:, k].mean())
            x = np.where(inlier, nu[:, k] - nu[inlier, k].mean(), 0.0)
            lag1 = float((x[1:] * x[:-1])[consecutive].sum() / max((x * x).sum(), 1e-30))
            axes[name] = {"ratio": ratio, "ratio_se": se, "factor": math.sqrt(max(ratio, 0.0)), "lag1": lag1}
        out[sensor] = {
            "epochs": int(len(prod)),
            "outliers": int((~inlier).sum()),
            "axes": axes,
            "residual_rms_m": [float(x) for x in np.sqrt(np.mean(resid**2, axis=0))],
            "sigma_rms_m": [float(x) for x in np.sqrt(var.mean(axis=0))],
        }
    return out or None


def _is_sensor_kind(name: str) -> bool:
    try:
        from fednav.service.estimation import measurements

        return name in measurements.REGISTRY
    except ImportError:  # a trimmed install
        return name in ("gnss_fix", "star")


def _screening(v: str, p: str, data: dict[str, Series], n_fixes: int) -> dict[str, Any]:
    """Per subsystem and row of the recorded Faults: tests, refusals and their expected rate.

    A subsystem named after a sensor kind is the loosely coupled innovation gate (statistic
    |r|/sqrt(S) against k sigma, recorded only when it refuses a row and once when it clears:
    the tests are the fixes received); any other is a federated local's per-row chi-square test
    (statistic r^2/S, recorded every few seconds and whenever it flags: its median against
    chi-square(1)'s, 0.455, is the NIS per degree of freedom)."""
    from scipy.stats import chi2, norm

    root = paths.faults(v, p) + "/"
    rows: dict[str, Any] = {}
    for ent, flag in data.items():
        if not ent.startswith(root) or not ent.endswith("/flagged"):
            continue
        sub, label = ent[len(root) :].split("/")[:2]
        stat = data.get(paths.faults(v, p, sub, label, "statistic"))
        thr = data.get(paths.faults(v, p, sub, label, "threshold"))
        flagged, refused = _flag_counts(flag, stat, thr)
        threshold = float(np.median(thr.values)) if thr is not None and len(thr) else None
        r: dict[str, Any] = {
            "recorded": len(flag),
            "flagged": flagged,
            "refused": refused,
            "threshold": threshold,
        }
        if _is_sensor_kind(sub):
            r["test"] = "innovation gate |r|/sqrt(S)"
            tests = n_fixes if sub == "gnss_fix" and n_fixes else None
            r["tests"] = tests
            if threshold is not None:
                r["expected_rate"] = float(2.0 * norm.sf(threshold))
            if tests:  # the rows beyond the gate on their own (not those refused with them)
                rate = flagged / tests
                r["rate"] = rate
                if flagged >= 3 and threshold is not None and rate < 1.0:
                    # |N(0, k^2)| > g with probability rate: k = g / z(1 - rate/2)
                    r["implied_factor"] = float(threshold / norm.isf(rate / 2.0))
        else:
            r["test"] = "chi-square(1) per row r^2/S"
            if threshold is not None:
                r["expected_rate"] = float(chi2.sf(threshold, 1))
            if stat is not None and len(stat) >= 20:
                med = float(np.median(stat.values))
                r["median_statistic"] = med
                r["implied_factor"] = math.sqrt(med / CHI2_1_MEDIAN)
        rows[f"{sub}/{label}"] = r
    return rows


#: fix innovations further than this many robust sigmas (1.4826 MAD) from their median are a fault
#: episode, left out of the whiteness test
OUTLIER_MADS = 6.0


#: the rows of a sensor's innovations as the verdict names them
ROW_AXES = {
    "pos_e": "east",
    "pos_n": "north",
    "pos_u": "up",
    "vel_e": "east velocity",
    "vel_n": "north velocity",
    "vel_u": "up velocity",
    "vel_along": "along-track velocity",
    "vel_cross": "cross-track velocity",
}
NIS_MIN_EPOCHS = 20  # fewer used rows than this: no figure
#: a row of a sensor with at least this many other rows, far off while they are consistent, is a
#: fault in that row's data (one satellite's pseudorange), not the filter's overconfidence
FAULT_PEERS = 3


def _innovation_consistency(v: str, p: str, data: dict[str, Series], t_from: float | None) -> dict | None:
    """Per sensor stream and row, the recorded innovation windows (``RerunSink.log_innovations``)
    pooled: the NIS per row, mean of r^2 = nu^2 / S over the rows used after ``t_from``, against
    chi-square(1) (mean 1 for a consistent filter, whatever the states behind S: correlated
    receiver error, lever arm, ...), with the 95 % interval of the mean of that many independent
    chi-square(1) values (chi2(N) / N: a consistent filter's innovations are white);
    factor = sqrt(NIS), the real over the claimed innovation spread; the gate's refusals."""
    from scipy.stats import chi2

    root = paths.innovations(v, p) + "/"
    out: dict[str, Any] = {}
    for ent, m in data.items():
        if not ent.startswith(root) or not ent.endswith("/r2_mean") or len(m) == 0:
            continue
        parts = ent[len(root) :].split("/")
        if len(parts) != 4:
            continue
        sensor, label = f"{parts[0]}/{parts[1]}", parts[2]
        n = _align(m, data.get(paths.innovations(v, p, sensor, label, "count")))
        x = np.asarray(m.values, dtype=np.float64)
        keep = np.isfinite(n) & np.isfinite(x) & (n > 0)
        if t_from is not None:
            keep &= m.t_ns / 1e9 >= t_from
        epochs = int(n[keep].sum())
        if epochs < NIS_MIN_EPOCHS:
            continue
        nis = float((x[keep] * n[keep]).sum() / epochs)
        lo, hi = float(chi2.ppf(0.025, epochs) / epochs), float(chi2.ppf(0.975, epochs) / epochs)
        entry = out.setdefault(sensor, {"rows": {}})
        entry["rows"][label] = {
            "epochs": epochs,
            "windows": int(keep.sum()),
            "nis": nis,
            "interval95": [lo, hi],
            "factor": math.sqrt(max(nis, 0.0)),
        }
    for sensor, entry in out.items():
        ref = data.get(paths.innovations(v, p, sensor, paths.INNOVATIONS_REFUSED))
        if ref is not None and len(ref):
            keep = np.ones(len(ref), bool) if t_from is None else ref.t_ns / 1e9 >= t_from
            entry["refused"] = int(np.asarray(ref.values)[keep].sum())
        order = {lab: i for i, lab in enumerate(ROW_AXES)}
        entry["rows"] = dict(sorted(entry["rows"].items(), key=lambda kv: (order.get(kv[0], 99), kv[0])))
    return out or None


def _verdict(
    fixres: dict | None, screening: dict, correlated: bool | None, innov: dict | None = None
) -> tuple[str, list[dict]]:
    """One line from the evidence: the largest significant over- or underconfidence, else
    consistent, else not decidable."""
    ev: list[dict] = []
    slow: list[tuple[str, str, float]] = []  # innovations correlated in time: (sensor, axis, lag-1)
    if fixres and correlated is not True:
        for sensor, r in fixres.items():
            for axis, a in r["axes"].items():
                if a["lag1"] > max(LAG1_CORRELATED, 4.0 / math.sqrt(r["epochs"])):
                    slow.append((sensor, axis, a["lag1"]))
                lo = max(a["ratio"] - 2 * a["ratio_se"], 1e-9)
                hi = a["ratio"] + 2 * a["ratio_se"]
                # the innovations' NIS, where recorded, is the better evidence (it holds whatever
                # the filter fuses: pseudoranges of a tightly coupled pipeline, correlated-error
                # states): the fix residuals are then shown, not judged on
                judged = not innov
                ev.append(
                    {
                        "source": f"fix residuals ({sensor})",
                        "axis": axis,
                        "factor": a["factor"],
                        "over": judged and a["factor"] > CONSISTENT_FACTOR and lo > 1.0,
                        "under": judged and a["factor"] < 1 / CONSISTENT_FACTOR and hi < 1.0,
                    }
                )
    faults: list[str] = []  # rows whose data, not the filter, is off (named, not called overconfidence)
    innov_over: set[str] = set()  # sensors whose used innovations show overconfidence
    for sensor, r in (innov or {}).items():
        rows = r["rows"]
        for label, a in rows.items():
            lo, hi = a["interval95"]
            over = a["nis"] > hi and a["factor"] > CONSISTENT_FACTOR
            others = [b["factor"] for k, b in rows.items() if k != label]
            fault = over and len(others) >= FAULT_PEERS and float(np.median(others)) < CONSISTENT_FACTOR
            if fault:
                # one row far off while the sensor's other rows are consistent (a satellite's
                # pseudorange with a fault): that row's data, not the filter's covariance
                faults.append(f"{sensor} {label} (NIS {a['nis']:.3g} while its other rows are consistent)")
                over = False
            if over:
                innov_over.add(sensor)
            ev.append(
                {
                    "source": f"innovations ({sensor}: NIS {a['nis']:.2f} over {a['epochs']} epochs, "
                    f"chi-square(1) 95 % interval {lo:.2f}-{hi:.2f})",
                    "axis": ROW_AXES.get(label, label),
                    "factor": a["factor"],
                    "fault": fault,
                    "over": over,
                    "under": a["nis"] < lo and a["factor"] < 1 / CONSISTENT_FACTOR,
                }
            )
    innov_kinds = {s.split("/")[0] for s in (innov or {})}
    over_kinds = {s.split("/")[0] for s in innov_over}
    for label, r in screening.items():
        k = r.get("implied_factor")
        if k is None:
            continue
        gate = r["test"].startswith("innovation gate")
        # a federated local's per-row test statistic speaks of that local filter; with the
        # innovations' NIS recorded, that (the better evidence) judges, the statistic is shown
        over = k > CONSISTENT_FACTOR and (gate or not innov)
        kind = label.split("/")[0]
        if gate and over and kind in innov_kinds and kind not in over_kinds:
            # refusals the used innovations do not explain (they are consistent): the gate
            # refused faulty data, as it should; not a claim the filter makes too small
            faults.append(
                f"{label} ({r['refused']} rows refused by the gate, the used innovations consistent)"
            )
            over = False
        ev.append(
            {
                "source": f"{'gate refusals' if gate else 'fault-test statistics'} ({label})",
                "axis": ROW_AXES.get(label.split("/")[-1], label.split("/")[-1]),
                "factor": k,
                "over": over,
                # refusals cannot show underconfidence: a gate that refuses nothing says nothing
                "under": (not gate)
                and not innov
                and k < 1 / CONSISTENT_FACTOR
                and r.get("median_statistic") is not None,
            }
        )
    over = [e for e in ev if e["over"]]
    under = [e for e in ev if e["under"]]
    faulty = f"; faulty data, not overconfidence: {'; '.join(faults)}" if faults else ""
    # without the configuration, fix residuals assume fixes fused as independent
    caveat = (
        " [fix residuals assume fixes fused as independent: give --config if the pipeline has "
        "gnss_correlated_error]"
        if correlated is None and fixres
        else ""
    )
    if over:
        worst = max(over, key=lambda e: e["factor"])
        return f"overconfident in {worst['axis']} by {worst['factor']:.1f}x ({worst['source']}){faulty}", ev
    if slow:
        lags = ", ".join(f"{axis} {lag:.2f}" for _, axis, lag in slow)
        return (
            f"fix innovations correlated in time (lag-1 autocorrelation {lags}; white: 0): the fixes' error "
            "is slow. Fused as independent, the filter's error against the truth exceeds its sigma even "
            "where its innovations look small (set gnss_correlated_error: fednav-replay --suggest-config); "
            "if it is set, give --config. Underconfidence cannot be told from these residuals",
            ev,
        )
    if under:
        worst = min(under, key=lambda e: e["factor"])
        tail = caveat if worst["source"].startswith("fix residuals") else ""
        return (
            f"underconfident in {worst['axis']} by "
            + (f"{1 / worst['factor']:.1f}x" if worst["factor"] > 0.1 else "more than 10x")
            + f" ({worst['source']}){tail}{faulty}",
            ev,
        )
    nis = [e for e in ev if e["source"].startswith("innovations") and not e.get("fault")]
    if nis:  # the innovations' NIS: the evidence that holds whatever states the filter carries
        figures = ", ".join(f"{e['axis']} {e['factor']:.2f}" for e in nis)
        return (
            f"consistent (innovations: real / claimed spread within {CONSISTENT_FACTOR}x: {figures}){faulty}",
            ev,
        )
    if any(e["source"].startswith(("fix residuals", "fault-test")) for e in ev):
        figures = ", ".join(f"{e['axis']} {e['factor']:.2f}" for e in ev if "factor" in e)
        return f"consistent (real / claimed error within {CONSISTENT_FACTOR}x: {figures}){caveat}{faulty}", ev
    why = (
        "gnss_correlated_error holds part of the fix error as states the recording does not hold, "
        "and it holds no innovation windows"
        if correlated
        else "no fix residuals or innovation tests in the recording"
    )
    tail = "; no gate refusals beyond their expected rate" if screening else ""
    return f"not decidable from this recording ({why}){tail}", ev


def _input_stopped(v: str, data: dict[str, Series]) -> dict[str, Any] | None:
    """The service's Health after its input stopped: rows at the same sensor time, one per health
    period of wall time; from the third on (2 s without input) its Health reported coasting."""
    rec = data.get(paths.health(v, "received"))
    if rec is None or len(rec) < STOPPED_HEALTH_ROWS:
        return None
    t = rec.t_ns
    n = 1
    while n < len(t) and t[-1 - n] == t[-1] and rec.values[-1 - n] == rec.values[-1]:
        n += 1
    if n < STOPPED_HEALTH_ROWS:
        return None
    return {"t": float(t[-1] / 1e9), "health_reports_after": n - 1}


def _fix_counts(v: str, data: dict[str, Series]) -> dict[str, Any]:
    root = f"/{paths.part(v)}/{paths.SERVICE}/inputs/"
    out = {}
    for ent, s in data.items():
        if ent.startswith(root) and ent.endswith("/enu"):
            out[ent[len(root) : -len("/enu")]] = {"fixes": len(s), "gaps": _gaps(s.t_ns, 2.0)}
    return out


def real_run_summary(
    v: str, p: str, data: dict[str, Series], res: dict[str, Any], pipeline_cfg=None
) -> dict[str, Any]:
    """What a run without truth says about pipeline ``p``: status timeline, re-initialisations,
    gaps, sigma levels, screening, consistency and one verdict. ``pipeline_cfg``: its service
    configuration (lever arm, correlated error) when known."""
    status = data.get(paths.solution(v, p, "status"))
    timeline = _status_timeline(status, res.get("t_end"))
    aided_from = next((c["t"] for c in timeline["changes"] if c["status"] in ("aided", "degraded")), None)
    t_from = None if aided_from is None else aided_from + SETTLE_S
    lat = data.get(paths.solution(v, p, "lat_deg"))
    inputs = _fix_counts(v, data)
    n_fixes = sum(x["fixes"] for x in inputs.values())
    correlated = (
        None if pipeline_cfg is None else getattr(pipeline_cfg, "gnss_correlated_error", None) is not None
    )
    lever = None if pipeline_cfg is None else getattr(pipeline_cfg, "gnss_lever_arm_b_m", None)
    fixres = _fix_residual_consistency(v, p, data, t_from, lever)
    screening = _screening(v, p, data, n_fixes)
    innov = _innovation_consistency(v, p, data, t_from)
    verdict, evidence = _verdict(fixres, screening, correlated, innov)
    return {
        "status": timeline,
        "solution_gaps": _gaps(lat.t_ns) if lat is not None else [],
        # solutions at a time already recorded: two runs over the same times in one recording (a
        # log replayed twice into one running service), whose rows the reader interleaves by time
        "repeated_times": int(len(lat.t_ns) - len(np.unique(lat.t_ns))) if lat is not None else 0,
        "sigma": _sigma_levels(v, p, data, t_from),
        "fix_residuals": fixres,
        "fix_residuals_apply": correlated is not True,
        "screening": screening,
        "innovations": innov,
        "evidence": evidence,
        "verdict": verdict,
    }


def summarize(info: dict[str, Any], data: dict[str, Series], file: str, config=None) -> dict[str, Any]:
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
        "unfinished": info.get("unfinished"),
        "t_start": t_min / 1e9 if vehicles else None,
        "t_end": t_max / 1e9 if vehicles else None,
        "duration_s": (t_max - t_min) / 1e9 if vehicles else 0.0,
        "vehicles": vehicles,
        "pipelines": {},
        "integrity": {},
        "faults": {},
        "health": {},
        "inputs": {},
        "input_stopped": {},
    }
    for v in vehicles:
        stopped = _input_stopped(v, data)
        result["inputs"][v] = _fix_counts(v, data)
        if stopped is not None:
            result["input_stopped"][v] = stopped
        for p in sorted(layout[v]):
            key = p if single else f"{v}/{p}"
            res = _pipeline_summary(v, p, data)
            pcfg = None
            if config is not None:
                pcfg = next((c for c in config.pipelines if paths.part(c.name) == p), None)
            res.update(real_run_summary(v, p, data, res, pcfg))
            if stopped is not None and res["final_status"] in ("aided", "degraded", "unaided"):
                res["health_final_status"] = "coasting"
            result["pipelines"][key] = res
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


#: the application id of ``fednav-fleet record``'s recordings (dashboards/fleet.py), on its own timeline
FLEET_APPLICATION = "fednav-fleet"
FLEET_TIMELINE = "wall_time"


def summarize_fleet(info: dict[str, Any], data: dict[str, Series], file: str) -> dict[str, Any]:
    """Summary of a ``fednav-fleet record`` file (its ``wall_time`` timeline): the snapshots, each
    vehicle's status changes (``/status/{vehicle}``, "no answer" while no service answered for it)
    and positions, each service's vehicles (``/load/vehicles/{zid}``; a last 0: it left)."""
    times = sorted({int(t) for s in data.values() for t in s.t_ns})
    vehicles: dict[str, dict[str, Any]] = {}
    services: dict[str, dict[str, Any]] = {}
    for ent, s in sorted(data.items()):
        parts = [p for p in ent.strip("/").split("/") if p]
        if len(parts) == 2 and parts[0] == "status" and len(s):
            states = [str(x) for x in s.values]
            changes = [x for i, x in enumerate(states) if i == 0 or x != states[i - 1]]
            vehicles.setdefault(parts[1], {}).update(final_status=states[-1], statuses=changes)
        elif len(parts) == 2 and parts[0] == "enu":
            vehicles.setdefault(parts[1], {})["positions"] = len(s)
        elif len(parts) == 3 and parts[:2] == ["load", "vehicles"] and len(s):
            vals = np.asarray(s.values, dtype=float)
            services[parts[2]] = {
                "final_vehicles": int(vals[-1]),
                "max_vehicles": int(vals.max()),
                "left": bool(vals[-1] == 0 and len(vals) > 1),
            }
    for v in vehicles.values():
        v.setdefault("positions", 0)
        v.setdefault("final_status", None)
        v.setdefault("statuses", [])
    return {
        "file": file,
        "kind": "fleet",
        "recording_id": info["recording_id"],
        "application_id": info["application_id"],
        "has_blueprint": info["blueprints"] > 0,
        "unfinished": info.get("unfinished"),
        "snapshots": len(times),
        "wall_start": times[0] / 1e9 if times else None,
        "wall_end": times[-1] / 1e9 if times else None,
        "duration_s": (times[-1] - times[0]) / 1e9 if times else 0.0,
        "vehicles": vehicles,
        "services": services,
    }


def render_fleet_text(s: dict[str, Any]) -> str:
    from datetime import UTC, datetime

    lines = [
        f"file: {s['file']}",
        f"recording: {s['recording_id']} (application {s['application_id']}), "
        f"blueprint embedded: {'yes' if s['has_blueprint'] else 'no'}",
    ]
    lines += _unfinished_lines(s)
    if not s["snapshots"]:
        lines.append("fleet recording (fednav-fleet record): no snapshot")
        return "\n".join(lines)

    def iso(t: float) -> str:
        return datetime.fromtimestamp(t, UTC).strftime("%Y-%m-%d %H:%M:%S UTC")

    lines.append(
        f"fleet recording (fednav-fleet record): {s['snapshots']} snapshots, wall time "
        f"{iso(s['wall_start'])} .. {iso(s['wall_end'])} ({s['duration_s']:.1f} s)"
    )
    lines.append(f"vehicles ({len(s['vehicles'])}):")
    width = max(len(v) for v in s["vehicles"]) if s["vehicles"] else 0
    for v, d in sorted(s["vehicles"].items()):
        lines.append(
            f"  {v:<{width}}  final {d['final_status'] or '-'}; "
            f"statuses {' -> '.join(d['statuses']) or '-'}; {d['positions']} positions"
        )
    lines.append(f"services ({len(s['services'])}):")
    for z, d in sorted(s["services"].items()):
        left = " (left)" if d["left"] else ""
        lines.append(f"  {z}  vehicles at the end {d['final_vehicles']}{left}, at most {d['max_vehicles']}")
    return "\n".join(lines)


def inspect_rrd(path: str | Path, config=None) -> dict[str, Any]:
    """Summary of a fednav .rrd (see the module docstring): a service's recording, or a
    ``fednav-fleet record`` file (:func:`summarize_fleet`). ``config``: the service configuration
    of the run (a ServiceConfig), when known. Raises :class:`InspectError`."""
    info, data = read_series(path)
    if info["application_id"] == FLEET_APPLICATION and not data:
        info, data = read_series(path, FLEET_TIMELINE)
        return summarize_fleet(info, data, str(path))
    return summarize(info, data, str(path), config)


# --- text rendering --------------------------------------------------------------------------------
def _fmt(x: float | None, spec: str = ".4g") -> str:
    return "-" if x is None else format(x, spec)


def _unfinished_lines(s: dict[str, Any]) -> list[str]:
    u = s.get("unfinished")
    if not u:
        return []
    if u.get("lost_bytes"):
        return [
            f"WARNING: the recording ends inside a message (its writer died mid-write: killed, power "
            f"lost, disk full?): read its first {u['read_bytes']} bytes, the last {u['lost_bytes']} "
            "are an unfinished message"
        ]
    return ["WARNING: the recording was not closed (no footer: its writer did not stop cleanly)"]


def render_text(s: dict[str, Any]) -> str:
    lines = [
        f"file: {s['file']}",
        f"recording: {s['recording_id']} (application {s['application_id']}), "
        f"blueprint embedded: {'yes' if s['has_blueprint'] else 'no'}",
    ]
    lines += _unfinished_lines(s)
    if s["t_start"] is None:
        lines.append("no data on the sensor_time timeline")
        return "\n".join(lines)
    lines.append(f"sensor time: {s['t_start']:.3f} .. {s['t_end']:.3f} s  (duration {s['duration_s']:.3f} s)")
    lines.append(f"vehicles: {', '.join(s['vehicles'])}")
    t0 = s["t_start"]
    for key, p in s["pipelines"].items():
        final = f"final status {p['final_status']} (the last recorded)"
        v = p["vehicle"]
        stop = s.get("input_stopped", {}).get(v)
        if stop is not None:
            final += (
                f"; input stopped at +{stop['t'] - t0:.1f} s: the service's "
                f"{stop['health_reports_after']} Health "
                "reports after it said "
                + (
                    "coasting (no input for 2 s of wall time)"
                    if p.get("health_final_status")
                    else p["final_status"]
                )
            )
        truth = f"{p['error_epochs']} epochs with errors vs truth" if p["error_epochs"] else "no truth"
        lines.append(f"pipeline {key}: {p['solutions']} solutions, {final}, {truth}")
        lines += _render_real_run(p, t0)
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
            if p.get("truth_verdict"):
                lines.append(f"    verdict against the truth: {p['truth_verdict']}")
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
        for name, st in f.get("states_last", {}).items():
            lines.append(f"    state {name:<18} {_fmt(st.get('value'))} +- {_fmt(st.get('std'))} (last)")
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
        why = h.get("rejected") or {}
        reasons = " (" + ", ".join(f"{k} {_fmt(x, 'g')}" for k, x in why.items()) + ")" if why else ""
        text = ", ".join(
            f"{k} {_fmt(x, 'g')}" + (reasons if k == "rejected_total" else "")
            for k, x in h.items()
            if k != "rejected"
        )
        lines.append(f"health {v} (last): " + text)
    for v, ins in s.get("inputs", {}).items():
        for sensor, x in ins.items():
            gaps = f", {len(x['gaps'])} gap(s) over 2 s" if x["gaps"] else ""
            lines.append(f"inputs {v}: {x['fixes']} GNSS fixes from {sensor}{gaps}")
    return "\n".join(lines)


def _render_real_run(p: dict[str, Any], t0: float) -> list[str]:
    """The lines of :func:`real_run_summary`'s figures."""
    out = []
    st = p.get("status") or {}
    if st.get("changes"):
        tl = " -> ".join(f"{c['status']} at +{c['t'] - t0:.1f} s" for c in st["changes"][:8])
        more = f" (+{len(st['changes']) - 8} more)" if len(st["changes"]) > 8 else ""
        times = ", ".join(f"{k} {v:.1f} s" for k, v in st["time_in_s"].items())
        out.append(
            f"    status: {tl}{more}; time in each: {times}; re-initialisations {st['reinitialisations']}"
        )
    if p.get("repeated_times"):
        out.append(
            f"    WARNING: {p['repeated_times']} solutions share their time with an earlier one: the "
            "recording holds more than one run over the same times, interleaved (the same log replayed "
            "twice into one running service?); the figures below mix them: give each replay its own "
            "service or recording"
        )
    gaps = p.get("solution_gaps") or []
    if gaps:
        g = ", ".join(f"{x['length_s']:.1f} s at +{x['t'] - t0:.1f} s" for x in gaps[:5])
        out.append(f"    solution gaps: {len(gaps)} ({g})")
    sig = p.get("sigma") or {}
    if sig:

        def m(*names):
            return "/".join(_fmt((sig.get(n) or {}).get("median"), ".2f") for n in names)

        out.append(
            f"    1-sigma (median once aided): position E/N/U {m('pos_e_m', 'pos_n_m', 'pos_u_m')} m, "
            f"velocity {m('ve_mps', 'vn_mps', 'vu_mps')} m/s, roll/pitch/heading "
            f"{m('roll_deg', 'pitch_deg', 'heading_deg')} deg"
        )
    fr = p.get("fix_residuals")
    if fr:
        for sensor, r in fr.items():
            ax = ", ".join(
                f"{a} {x['factor']:.2f} (ratio {x['ratio']:.2f} +- {x['ratio_se']:.2f})"
                for a, x in r["axes"].items()
            )
            note = (
                "" if p.get("fix_residuals_apply", True) else " [not used: gnss_correlated_error configured]"
            )
            out.append(
                f"    fixes {sensor}: real/claimed error (update jumps x fix residuals, {r['epochs']} "
                f"fixes): {ax}; fix residual RMS E/N {_fmt(r['residual_rms_m'][0], '.2f')}/"
                f"{_fmt(r['residual_rms_m'][1], '.2f')} m{note}"
            )
    for sensor, r in (p.get("innovations") or {}).items():
        rows = ", ".join(
            f"{ROW_AXES.get(label, label)} {a['nis']:.2f} "
            f"({a['interval95'][0]:.2f}-{a['interval95'][1]:.2f}, x{a['factor']:.2f})"
            for label, a in r["rows"].items()
        )
        n = max((a["epochs"] for a in r["rows"].values()), default=0)
        ref = f"; {r['refused']} rows refused by the gate" if r.get("refused") else ""
        out.append(
            f"    innovations {sensor} ({n} epochs): NIS per row against chi-square(1) (95 % interval, "
            f"real/claimed spread): {rows}{ref}"
        )
    for label, r in (p.get("screening") or {}).items():
        tests = r.get("tests")
        rate = (
            f" of {tests} tests ({100 * r['rate']:.2g} % failing)"
            if tests
            else f" ({r['recorded']} rows recorded)"
        )
        exp = f", expected {r['expected_rate']:.1g} per test" if r.get("expected_rate") is not None else ""
        k = f", implied real/claimed {r['implied_factor']:.2f}" if r.get("implied_factor") is not None else ""
        med = (
            f", median statistic {r['median_statistic']:.2f} (chi2(1): 0.45)"
            if "median_statistic" in r
            else ""
        )
        own = (
            f" ({r['flagged']} beyond it on their own)"
            if r.get("flagged", r["refused"]) != r["refused"]
            else ""
        )
        out.append(f"    {r['test']} {label}: refused {r['refused']}{own}{rate}{exp}{med}{k}")
    if p.get("verdict"):
        # with truth in the recording, the truth's verdict leads (below the error table); the
        # recording's own evidence is what a run without truth would be judged on
        who = "without truth, the recording's own evidence says" if p.get("truth_verdict") else "verdict"
        out.append(f"    {who}: {p['verdict']}")
    return out


@quiet_closed_stdout
def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(
        prog="fednav-inspect", description="Summarise a fednav Rerun recording (.rrd) without a viewer"
    )
    ap.add_argument("file", type=Path, help="recording to read")
    ap.add_argument("--json", action="store_true", help="print one JSON object instead of text")
    ap.add_argument(
        "--config",
        type=Path,
        default=None,
        help="the service configuration of the run (its pipelines' lever arm and correlated-error states "
        "refine the consistency check)",
    )
    args = ap.parse_args(argv)
    config = None
    if args.config is not None:
        from fednav.service.config import ConfigError, load

        try:
            config = load(args.config)
        except ConfigError as exc:
            print(f"fednav-inspect: error: {exc}", file=sys.stderr)
            return 2
    try:
        summary = inspect_rrd(args.file, config)
    except InspectError as exc:
        print(f"fednav-inspect: error: {exc}", file=sys.stderr)
        return 2
    if args.json:
        print(json.dumps(summary, indent=2, allow_nan=False))
    else:
        print(render_fleet_text(summary) if summary.get("kind") == "fleet" else render_text(summary))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
