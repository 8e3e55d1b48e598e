"""``fednav-sim eval``: run a scenario through the service's own engine in-process.

The same :class:`service.engine.VehicleEngine` and pipelines as the service, fed the same
message stream the simulator publishes over Zenoh (so both routes give the same solutions),
faster than real time. Metrics per pipeline over seeded Monte Carlo runs (seed, seed+1, ...):
RMS and max of position (lat_m = north, lon_m = east, h_m), velocity (ENU) and misalignment
(phi_e/n/u, arcsec) errors against truth at every solution epoch, pooled over the runs; mean
NEES of the 9 navigation errors against the filter's own covariance (dof 9).
"""

from __future__ import annotations

import math
import time
from dataclasses import dataclass, field

import numpy as np

from fednav.service import config as config_mod
from fednav.service import keys
from fednav.service.engine import EstimateOutput
from fednav.service.evaluation import (
    INTEGRITY_CLASSES,
    REPORT_KEYS,
    FaultWindow,
    dvl_state_summary,
    end_errors,
    error_stats,
    fault_window_max_vel,
    integrity_metrics,
    nees,
)
from fednav.service.messages import Faults, Integrity, Solution, Truth, WireModel
from fednav.service.vehicle import VehicleLoop
from fednav.simulators.papers import reference
from fednav.simulators.scenario import Scenario
from fednav.simulators.stream import Simulation


@dataclass
class RunRecord:
    """What one pipeline produced in one run."""

    t: list[float] = field(default_factory=list)
    err: list[np.ndarray] = field(default_factory=list)
    nees: list[float] = field(default_factory=list)
    solutions: list[Solution] = field(default_factory=list)
    outputs: list[WireModel] = field(default_factory=list)
    output_errors: list = field(default_factory=list)  # err9 at each output's time (None: no truth)


class CollectingSink:
    def __init__(self, keep_solutions: bool = False):
        self.keep = keep_solutions
        self.records: dict[str, RunRecord] = {}
        self.truths: list[Truth] = []

    def _rec(self, name: str) -> RunRecord:
        return self.records.setdefault(name, RunRecord())

    def on_estimate(self, vehicle, out: EstimateOutput) -> None:
        r = self._rec(out.name)
        if self.keep:
            r.solutions.append(out.solution())
        if out.err9 is not None:
            r.t.append(out.t)
            r.err.append(out.err9)
            try:
                r.nees.append(nees(out.err9, out.P9))
            except np.linalg.LinAlgError:
                r.nees.append(float("nan"))

    def on_output(self, vehicle, msg, err9=None) -> None:
        r = self._rec(msg.pipeline)
        r.outputs.append(msg)
        r.output_errors.append(err9)

    def on_truth(self, vehicle, truth: Truth) -> None:
        pass


def service_config(scenario: Scenario, pipelines: list[str] | None = None) -> config_mod.ServiceConfig:
    """The service configuration a scenario asks for (its ``[service]`` table); ``pipelines``:
    only the pipelines of these names (in the scenario's order; an unknown name is an error)."""
    service = dict(scenario.service)
    if pipelines is not None:
        listed = [p.get("name") for p in service.get("pipelines", [])]
        unknown = sorted(set(pipelines) - set(listed))
        if unknown:
            have, missing = ", ".join(map(str, listed)), ", ".join(unknown)
            raise config_mod.ConfigError(f"scenario {scenario.name}: no pipeline {missing} (it has {have})")
        service["pipelines"] = [p for p in service["pipelines"] if p.get("name") in pipelines]
    return config_mod.from_dict(service, f"scenario {scenario.name} [service]")


def run_once(
    scenario: Scenario,
    seed: int,
    cfg: config_mod.ServiceConfig | None = None,
    trajectory=None,
    keep_solutions: bool = False,
    vehicle: str = "v1",
    on_time=None,
) -> tuple[CollectingSink, Simulation]:
    """One seeded run. ``on_time(t_s)``: called with the sensor time about once a second of
    scenario time (progress bars)."""
    cfg = cfg or service_config(scenario)
    sink = CollectingSink(keep_solutions)
    loop = VehicleLoop(vehicle, cfg, sink)  # the service's per-vehicle loop, in-process
    engine = loop.engine
    sim = Simulation(scenario, seed=seed, vehicle=vehicle, trajectory=trajectory, prefix=cfg.prefix)
    next_tick = -math.inf
    for key, msg in sim:
        pk = keys.parse_input(key, cfg.prefix)
        loop.process(pk.kind, pk.sensor_id, msg)
        if on_time is not None and engine.last_t is not None and engine.last_t >= next_tick:
            next_tick = engine.last_t + 1.0
            on_time(engine.last_t)
    return sink, sim


def evaluate(
    scenario: Scenario,
    runs: int = 1,
    seed: int | None = None,
    window: tuple[float, float] | None = None,
    progress=None,
    on_time=None,
    pipelines: list[str] | None = None,
) -> dict:
    """Monte Carlo evaluation; returns the JSON-ready result dict. ``progress(i, runs, wall_s)``
    is called after each run; ``on_time(run_index, t_s)`` about once a second of scenario time
    (the command line's progress bar); ``pipelines``: run only these of the scenario's pipelines."""
    seed = scenario.seed if seed is None else seed
    cfg = service_config(scenario, pipelines)
    traj = scenario.build_trajectory()
    t0 = float(traj.t_s[0])
    pooled: dict[str, dict[str, list]] = {}
    wall0 = time.perf_counter()
    integ_runs: dict[str, list] = {}
    for i in range(runs):
        tick = None if on_time is None else (lambda t, i=i: on_time(i, t))
        sink, sim = run_once(scenario, seed + i, cfg, trajectory=traj, on_time=tick)
        if progress is not None:
            progress(i + 1, runs, time.perf_counter() - wall0)
        collect_integrity(integ_runs, sink)
        for name, rec in sink.records.items():
            p = pooled.setdefault(name, {"t": [], "err": [], "nees": [], "end": []})
            p["t"] += [t - t0 for t in rec.t]
            p["err"] += rec.err
            p["nees"] += rec.nees
            if rec.err:
                p["end"].append(rec.err[-1])
            dvl = dvl_state_errors(rec, sim.truth)
            if dvl:
                p.setdefault("dvl", []).append(dvl)
            shares = [m.sharing for m in rec.outputs if isinstance(m, Faults) and m.sharing]
            if shares:  # time-mean share of each local over this run (mean over the 15 states)
                p.setdefault("sharing", []).append(
                    {k: float(np.mean([np.mean(s[k]) for s in shares if k in s])) for k in shares[-1]}
                )
    wall = time.perf_counter() - wall0
    out = {
        "scenario": scenario.name,
        "runs": runs,
        "seed": seed,
        "pipelines": {},
        "timing": {"wall_s": wall, "realtime_factor": runs * scenario.duration_s / wall},
    }
    for name, p in pooled.items():
        if not p["err"]:
            continue
        err = np.array(p["err"])
        rms, mx = error_stats(err)
        nees_arr = np.array(p["nees"])
        entry = {
            "rms": rms,
            "max": mx,
            "epochs": len(err),
            "h_rms_m": float(math.sqrt(np.mean(err[:, 0] ** 2 + err[:, 1] ** 2))),
            "pos_rms_m": float(math.sqrt(np.mean(np.sum(err[:, 0:3] ** 2, axis=1)))),
            "nees": {"mean": float(np.nanmean(nees_arr)), "dof": 9},
        }
        entry.update(end_errors(p["end"]))
        if p.get("dvl"):
            entry["dvl_states"] = dvl_state_summary(p["dvl"])
        if p.get("sharing"):
            entry["sharing_mean"] = {k: float(np.mean([r[k] for r in p["sharing"]])) for k in p["sharing"][0]}
        onset = min((f.start_s for f in scenario.faults), default=None)
        if onset is not None:
            t = np.array(p["t"])
            sel = t >= onset
            if sel.any():
                entry["after_fault"] = {"t0": onset, "rms": error_stats(err[sel])[0]}
        fw = fault_window_max_vel(fault_windows(scenario), np.array(p["t"]), err)
        if fw is not None:
            entry["fault_windows_max_vel_err_mps"] = fw
        if window is not None:
            t = np.array(p["t"])
            sel = (t >= window[0]) & (t <= window[1])
            if sel.any():
                wr, wm = error_stats(err[sel])
                entry["window"] = {"t0": window[0], "t1": window[1], "rms": wr, "max": wm}
        out["pipelines"][name] = entry
    add_integrity(out, scenario, integ_runs)
    return out


def dvl_state_errors(rec: RunRecord, truth) -> dict[str, tuple[float, float]]:
    """{state: (estimate - truth, 1-sigma)} of the last DVL states a pipeline reported in one
    run (seed 004: ``Faults.states``), else {}."""
    if getattr(truth, "dvl_offset_mps", None) is None:
        return {}
    last = next((m.states for m in reversed(rec.outputs) if isinstance(m, Faults) and m.states), None)
    if not last:
        return {}
    true = dict(zip(("x", "y", "z"), zip(truth.dvl_offset_mps, truth.dvl_scale, strict=True), strict=True))
    out = {}
    for st in last:
        axis = st.name.split("_")[2]  # dvl_offset_x_mps, dvl_scale_x
        t = true[axis][0 if "offset" in st.name else 1]
        out[st.name] = (st.value - float(t), st.std)
    return out


def format_table(result: dict) -> str:
    cols = REPORT_KEYS
    head = f"{'pipeline':<22}{'':6}" + "".join(f"{c:>13}" for c in cols) + f"{'NEES/9':>9}"
    lines = [
        f"scenario {result['scenario']}: {result['runs']} run(s), seed {result['seed']}, "
        f"{result['timing']['realtime_factor']:.0f}x real time",
        head,
        "-" * len(head),
    ]
    for name, e in result["pipelines"].items():
        for stat in ("rms", "max"):
            nees_s = f"{e['nees']['mean']:9.2f}" if stat == "rms" else ""
            lines.append(f"{name:<22}{stat:6}" + "".join(f"{e[stat][c]:13.4f}" for c in cols) + nees_s)
        if "window" in e:
            w = e["window"]
            for stat in ("rms", "max"):
                lines.append(
                    f"{'  window ' + str(w['t0']) + '-' + str(w['t1']):<22}{stat:6}"
                    + "".join(f"{w[stat][c]:13.4f}" for c in cols)
                )
    ref = reference(result["scenario"])
    if ref and "table1" in ref:
        table = "table2" if any("window" in e for e in result["pipelines"].values()) else "table1"
        lines.append(f"paper ({table}, RMS):")
        for name, vals in ref[table].items():
            ours = result["pipelines"].get(name, {})
            ours = ours.get("window", ours).get("rms", {}) if ours else {}
            cells = "  ".join(f"{k} {v:.3f} (ours {ours.get(k, float('nan')):.3f})" for k, v in vals.items())
            lines.append(f"  {name:<20}{cells}")
    lines += format_end_errors(result)
    lines += format_seed003(result)
    for name, e in result["pipelines"].items():
        if "fault_windows_max_vel_err_mps" in e:
            lines.append(
                f"{name}: max velocity error in fault windows {e['fault_windows_max_vel_err_mps']:.3f} m/s"
            )
    lines += format_integrity(result)
    lines.append("units: lat_m/lon_m/h_m metres (north/east/up), v m/s, phi arcsec")
    return "\n".join(lines)


def format_end_errors(result: dict) -> list[str]:
    """End errors (and RMS after the first fault) per pipeline; the paper's figures beside them
    where the scenario reproduces one (seed 004)."""
    ref = reference(result["scenario"])
    lines = []
    ends = {n: e for n, e in result["pipelines"].items() if "end_pos_m" in e}
    if not ends:
        return lines
    lines.append(
        f"{'end of run':<28}{'pos m':>9}{'(max)':>9}{'vel m/s':>9}{'(max)':>9}"
        f"{'east m':>10}{'north m':>10}{'ve m/s':>9}{'vn m/s':>9}"
    )
    for name, e in ends.items():
        c = e["end"]
        lines.append(
            f"  {name:<26}{e['end_pos_m']:9.2f}{e['end_pos_m_max']:9.2f}{e['end_vel_mps']:9.3f}"
            f"{e['end_vel_mps_max']:9.3f}{c['east_m']:10.2f}{c['north_m']:10.2f}{c['ve_mps']:9.3f}{c['vn_mps']:9.3f}"
        )
    for name, e in ends.items():
        if "after_fault" in e:
            r = e["after_fault"]["rms"]
            vel = f"ve {r['ve_mps']:.3f} m/s, vn {r['vn_mps']:.3f} m/s"
            lines.append(
                f"  {name}: RMS after the fault (t >= {e['after_fault']['t0']:g} s): "
                f"east {r['lon_m']:.2f} m, north {r['lat_m']:.2f} m, {vel}"
            )
    for name, e in ends.items():
        if "dvl_states" in e:
            cells = ", ".join(
                f"{k.removeprefix('dvl_')} {v['rms_error']:.2g}/{v['sigma']:.2g}/{v['nees']:.2f}"
                for k, v in e["dvl_states"].items()
            )
            lines.append(f"  {name}: DVL states at the end, RMS error/sigma/NEES: {cells}")
    for name, e in ends.items():
        if "sharing_mean" in e:
            cells = ", ".join(f"{k} {v:.3f}" for k, v in e["sharing_mean"].items())
            lines.append(f"  {name}: mean sharing coefficients {cells}")
    for key, label in (("nominal", "paper, fault free"), ("usbl_fault", "paper, USBL fault (Table 3)")):
        if key in ref:
            for pname, vals in ref[key].items():
                cells = ", ".join(f"{k} {v:g}" for k, v in vals.items())
                lines.append(f"  {label}: {pname}: {cells}")
    return lines


def format_seed003(result: dict) -> list[str]:
    """Seed 003: the paper's four position RMS figures (Table 1) beside ours (3-D position RMS)."""
    ref = reference(result["scenario"])
    table = ref.get("seed003_table1")
    if not table:
        return []
    lines = ["paper (He, Nie, Wu 2011, Table 1), position RMS (m):"]
    schemes = ref.get("seed003_schemes", {})
    for scheme, vals in table.items():
        mine = [
            f"{name} {result['pipelines'][name]['pos_rms_m']:.3f}"
            for name, s in schemes.items()
            if s == scheme and "pos_rms_m" in result["pipelines"].get(name, {})
        ]
        lines.append(
            f"  {scheme:<14}{vals['pos_m']:8.3f}   "
            + ("ours: " + ", ".join(mine) if mine else "ours: other scenario")
        )
    for name, e in result["pipelines"].items():
        if "pos_rms_m" in e:
            lines.append(f"  {name:<22}position RMS {e['pos_rms_m']:.3f} m, NEES/9 {e['nees']['mean']:.2f}")
    return lines


# --- integrity (seed 001): per-epoch classes of the paper's Table 1 --------------------------------
def collect_integrity(acc: dict[str, list], sink: CollectingSink) -> None:
    """Keep each pipeline's Integrity outputs (and their errors) of one run: acc[name] += [(msgs, errs)]."""
    for name, rec in sink.records.items():
        pairs = [
            (m, e) for m, e in zip(rec.outputs, rec.output_errors, strict=True) if isinstance(m, Integrity)
        ]
        if pairs:
            acc.setdefault(name, []).append(pairs)


def add_integrity(result: dict, scenario: Scenario, acc: dict[str, list]) -> None:
    """Add ``result["pipelines"][name]["integrity"]`` for every pipeline that produced Integrity."""
    for name, runs in acc.items():
        entry = result["pipelines"].setdefault(name, {})
        entry["integrity"] = integrity_metrics(
            fault_windows(scenario, "gnss_raw"), scenario.t0_gps_s, scenario.imu.rate_hz, runs
        )


def fault_windows(scenario: Scenario, sensor: str | None = None) -> list[FaultWindow]:
    """The scenario's injected faults as plain windows (seconds from the start), in onset order;
    ``sensor`` keeps one sensor's (``gnss_raw`` faults carry their satellites)."""
    rate = {
        "gnss": scenario.gnss.rate_hz if scenario.gnss else 1.0,
        "star": scenario.star.rate_hz if scenario.star else 1.0,
    }
    out = [
        FaultWindow(
            f.start_s,
            f.start_s + f.duration_s,
            f.sensor,
            1.0 / rate.get(f.sensor, 1.0),
            frozenset(c.split(".")[0] for c in f.channels) if f.sensor == "gnss_raw" else frozenset(),
        )
        for f in scenario.faults
        if sensor is None or f.sensor == sensor
    ]
    return sorted(out, key=lambda w: w.start_s)


def format_integrity(result: dict) -> list[str]:
    """Integrity lines of the table form, with the paper's figures beside ours where they exist."""
    ref = reference(result["scenario"])
    lines = []
    for name, e in result["pipelines"].items():
        g = e.get("integrity")
        if not g:
            continue
        c = g["counts"]
        lat = g["detection_latency_s"]
        lines.append(
            f"{name}: integrity over {g['epochs']} epochs: HPL median {g['hpl_m']['median']:.1f} m "
            f"max {g['hpl_m']['max']:.1f} m, VPL median {g['vpl_m']['median']:.1f} m, alarms {g['alarms']}, "
            f"HMI epochs {g['hmi_epochs']}, excluded {g['excluded_satellites']}"
            + (
                f" (healthy satellites excluded {g['healthy_exclusion_count']}: "
                + ", ".join(f"{e['satellite']} at {e['t_s']:.1f} s" for e in g["healthy_exclusions"][:5])
                + (", ..." if len(g["healthy_exclusions"]) > 5 else "")
                + ")"
                if g.get("healthy_exclusions")
                else ""
            )
        )
        lines.append(
            f"  first detection {'never' if lat is None else f'{lat:.2f} s'} after the first fault onset; "
            f"faults detected in time {g['faults_detected_in_time']}/{g['faults']}"
        )
        t1 = ref.get("integrity_table1")
        head = f"  {'':14}" + "".join(f"{k:>13}" for k in INTEGRITY_CLASSES) + f"{'P_FA':>11}{'P_MD':>9}"
        lines.append(head)
        pfa = "-" if g["p_fa"] is None else f"{g['p_fa']:.2e}"
        pmd = "-" if g["p_md"] is None else f"{g['p_md']:.2e}"
        lines.append(
            f"  {'ours':14}" + "".join(f"{c[k]:>13}" for k in INTEGRITY_CLASSES) + f"{pfa:>11}{pmd:>9}"
        )
        if t1:
            lines.append(
                f"  {'paper Table 1':14}"
                + "".join(f"{t1.get(k, '-'):>13}" for k in INTEGRITY_CLASSES)
                + f"{t1['false_alarm_rate']:>11.2e}{t1['missed_rate']:>9.1f}"
            )
        ramp = ref.get("ramp")
        if ramp:
            lines.append(
                f"  paper: ramp {ramp['rate_mps']} m/s on {ramp['satellite']} from {ramp['onset_s']} s "
                f"flagged at {ramp['flagged_at_s']} s (latency {ramp['latency_s']} s); ours "
                f"{'never' if lat is None else f'{lat:.2f} s'}"
            )
    return lines


#: lists of events in a result, not figures: left out of the statistics across seed sets (their
#: counts are figures of their own)
EVENT_LISTS = ("healthy_exclusions",)


def across_seed_sets(sets: list[dict]) -> dict:
    """Every numeric figure of several evaluations (one per seed set, the same scenario and runs):
    its mean over the sets, min, max and the values, by the same path (``pipelines.tc.pos_rms_m``).
    Timing is left out; figures missing from a set are left out of that figure's statistics."""
    leaves: dict[str, list[float]] = {}

    def walk(node, path: str) -> None:
        if isinstance(node, dict):
            for k, v in node.items():
                if (path == "" and k in ("timing", "seed", "runs")) or k in EVENT_LISTS:
                    continue
                walk(v, f"{path}.{k}" if path else k)
        elif isinstance(node, list):
            for i, v in enumerate(node):
                walk(v, f"{path}[{i}]")
        elif isinstance(node, (int, float)) and not isinstance(node, bool) and math.isfinite(node):
            leaves.setdefault(path, []).append(float(node))

    for r in sets:
        walk(r, "")
    return {
        "seeds": [r.get("seed") for r in sets],
        "runs_per_set": sets[0].get("runs"),
        "figures": {
            p: {"mean": float(np.mean(v)), "min": float(min(v)), "max": float(max(v)), "values": v}
            for p, v in leaves.items()
        },
    }


#: the figures the seed-set table shows per pipeline (every figure is in the JSON)
SEED_SET_COLUMNS = ("pos_rms_m", "h_rms_m", "nees.mean")


def format_seed_sets(summary: dict) -> str:
    """The main figures per pipeline: mean over the seed sets [min - max]."""
    figs = summary["figures"]
    names = sorted({p.split(".")[1] for p in figs if p.startswith("pipelines.")})
    lines = [
        f"seed sets {summary['seeds']}, {summary['runs_per_set']} runs each: mean over the sets [min - max]",
        f"{'pipeline':24s}" + "".join(f"{c:>30s}" for c in SEED_SET_COLUMNS),
    ]
    for n in names:
        cells = []
        for c in SEED_SET_COLUMNS:
            f = figs.get(f"pipelines.{n}.{c}")
            cells.append(f"{f['mean']:.4g} [{f['min']:.4g} - {f['max']:.4g}]" if f else "-")
        lines.append(f"{n:24s}" + "".join(f"{c:>30s}" for c in cells))
    return "\n".join(lines)
