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

from service import config as config_mod
from service import keys
from service.engine import VehicleEngine
from service.messages import Integrity, Solution, Truth, WireModel
from service.pipelines.base import ERROR_KEYS, error_dict, nees
from simulators.papers import reference
from simulators.scenario import Scenario
from simulators.stream import Simulation


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

    @property
    def wants_solutions(self) -> bool:
        return self.keep

    def on_solution(self, vehicle, sol: Solution, err9, P9) -> None:
        self._rec(sol.pipeline).solutions.append(sol)
        self.on_estimate(vehicle, sol.pipeline, sol.t, err9, P9)

    def on_estimate(self, vehicle, pipeline: str, t: float, err9, P9) -> None:
        r = self._rec(pipeline)
        if err9 is not None:
            r.t.append(t)
            r.err.append(err9)
            try:
                r.nees.append(nees(err9, P9))
            except np.linalg.LinAlgError:
                r.nees.append(float("nan"))

    def on_output(self, vehicle, msg, err9=None) -> None:
        r = self._rec(msg.pipeline)
        r.outputs.append(msg)
        r.output_errors.append(err9)

    def on_truth(self, vehicle, truth: Truth) -> None:
        pass


def service_config(scenario: Scenario) -> config_mod.ServiceConfig:
    """The service configuration a scenario asks for (its ``[service]`` table)."""
    return config_mod.from_dict(dict(scenario.service), f"scenario {scenario.name} [service]")


def run_once(
    scenario: Scenario,
    seed: int,
    cfg: config_mod.ServiceConfig | None = None,
    trajectory=None,
    keep_solutions: bool = False,
    vehicle: str = "v1",
) -> tuple[CollectingSink, Simulation]:
    cfg = cfg or service_config(scenario)
    sink = CollectingSink(keep_solutions)
    engine = VehicleEngine(vehicle, cfg, sink)
    sim = Simulation(scenario, seed=seed, vehicle=vehicle, trajectory=trajectory, prefix=cfg.prefix)
    for key, msg in sim:
        pk = keys.parse_input(key, cfg.prefix)
        engine.handle(pk.kind, pk.sensor_id, msg)
    return sink, sim


def _stats(err: np.ndarray) -> tuple[dict, dict]:
    named = [error_dict(e) for e in err]
    rms = {k: float(math.sqrt(np.mean([d[k] ** 2 for d in named]))) for k in ERROR_KEYS}
    mx = {k: float(np.max([abs(d[k]) for d in named])) for k in ERROR_KEYS}
    return rms, mx


def evaluate(
    scenario: Scenario, runs: int = 1, seed: int | None = None, window: tuple[float, float] | None = None
) -> dict:
    """Monte Carlo evaluation; returns the JSON-ready result dict."""
    seed = scenario.seed if seed is None else seed
    cfg = service_config(scenario)
    traj = scenario.build_trajectory()
    t0 = float(traj.t_s[0])
    pooled: dict[str, dict[str, list]] = {}
    wall0 = time.perf_counter()
    integ_runs: dict[str, list] = {}
    for i in range(runs):
        sink, _ = run_once(scenario, seed + i, cfg, trajectory=traj)
        collect_integrity(integ_runs, sink)
        for name, rec in sink.records.items():
            p = pooled.setdefault(name, {"t": [], "err": [], "nees": []})
            p["t"] += [t - t0 for t in rec.t]
            p["err"] += rec.err
            p["nees"] += rec.nees
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
        rms, mx = _stats(err)
        nees_arr = np.array(p["nees"])
        entry = {
            "rms": rms,
            "max": mx,
            "epochs": len(err),
            "h_rms_m": float(math.sqrt(np.mean(err[:, 0] ** 2 + err[:, 1] ** 2))),
            "pos_rms_m": float(math.sqrt(np.mean(np.sum(err[:, 0:3] ** 2, axis=1)))),
            "nees": {"mean": float(np.nanmean(nees_arr)), "dof": 9},
        }
        fw = _fault_window_max_vel(scenario, np.array(p["t"]), err)
        if fw is not None:
            entry["fault_windows_max_vel_err_mps"] = fw
        if window is not None:
            t = np.array(p["t"])
            sel = (t >= window[0]) & (t <= window[1])
            if sel.any():
                wr, wm = _stats(err[sel])
                entry["window"] = {"t0": window[0], "t1": window[1], "rms": wr, "max": wm}
        out["pipelines"][name] = entry
    add_integrity(out, scenario, integ_runs)
    return out


def _fault_window_max_vel(scenario: Scenario, t_rel: np.ndarray, err: np.ndarray) -> float | None:
    """Largest velocity-error norm inside the fault windows, after the first filter cycle of each.

    The filter cycle is the aiding period of the faulted sensor (1 s for the seed-000 BDS fixes).
    """
    if not scenario.faults:
        return None
    rate = {
        "gnss": scenario.gnss.rate_hz if scenario.gnss else 1.0,
        "star": scenario.star.rate_hz if scenario.star else 1.0,
    }
    vnorm = np.linalg.norm(err[:, 3:6], axis=1)
    worst = 0.0
    for f in scenario.faults:
        cycle = 1.0 / rate.get(f.sensor, 1.0)
        sel = (t_rel >= f.start_s + cycle - 1e-6) & (t_rel < f.start_s + f.duration_s)
        if sel.any():
            worst = max(worst, float(vnorm[sel].max()))
    return worst


def format_table(result: dict) -> str:
    cols = ERROR_KEYS
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
    lines += format_seed003(result)
    for name, e in result["pipelines"].items():
        if "fault_windows_max_vel_err_mps" in e:
            lines.append(
                f"{name}: max velocity error in fault windows {e['fault_windows_max_vel_err_mps']:.3f} m/s"
            )
    lines += format_integrity(result)
    lines.append("units: lat_m/lon_m/h_m metres (north/east/up), v m/s, phi arcsec")
    return "\n".join(lines)


def format_seed003(result: dict) -> list[str]:
    """Seed 003: the paper's four position RMS figures (Table 1) beside ours (3-D position RMS)."""
    ref = reference(result["scenario"])
    table = ref.get("seed003_table1")
    if not table:
        return []
    lines = ["paper (He, Nie, Wu 2011, Table 1), position RMS (m):"]
    schemes = ref.get("seed003_schemes", {})
    ours = {scheme: name for name, scheme in schemes.items()}
    for scheme, vals in table.items():
        name = ours.get(scheme)
        e = result["pipelines"].get(name, {}) if name else {}
        mine = f"ours ({name}) {e['pos_rms_m']:.3f}" if e else "ours: other scenario"
        lines.append(f"  {scheme:<14}{vals['pos_m']:8.3f}   {mine}")
    for name, e in result["pipelines"].items():
        if "pos_rms_m" in e:
            lines.append(f"  {name:<22}position RMS {e['pos_rms_m']:.3f} m, NEES/9 {e['nees']['mean']:.2f}")
    return lines


# --- integrity (seed 001): per-epoch classes of the paper's Table 1 --------------------------------
INTEGRITY_CLASSES = ("normal", "detected", "missed", "false_alarm", "undetected")


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
        entry["integrity"] = integrity_metrics(scenario, runs)


def _raw_faults(scenario: Scenario) -> list[tuple[float, float, set[str]]]:
    """(start_s, end_s, satellites) of the raw-GNSS faults, in onset order."""
    out = []
    for f in scenario.faults:
        if f.sensor == "gnss_raw":
            out.append((f.start_s, f.start_s + f.duration_s, {c.split(".")[0] for c in f.channels}))
    return sorted(out, key=lambda x: x[0])


def integrity_metrics(scenario: Scenario, runs: list[list[tuple[Integrity, np.ndarray | None]]]) -> dict:
    """Integrity figures of one pipeline over runs of ``scenario`` (JSON-ready).

    Epochs are the pipeline's Integrity messages (one per GNSS epoch); ``t_rel`` is the message
    time from the scenario start on the IMU grid. A raw-GNSS fault of ``scenario.faults`` is
    *active* at ``start_s <= t_rel < start_s + duration_s``. Per fault, the epoch is *flagged*
    when the message has ``detected`` or ``alarm``, or lists one of the fault's satellites in
    ``excluded``; the fault is *detected in time* when its first flagged epoch inside its window
    comes at most TTA (the phase's time to alert) after its onset. herr = true horizontal error
    of the solution at the epoch (|dp_east, dp_north|); hazardous = herr > HPL or herr > HAL.

    Classes (each epoch exactly one; the paper's Table 1 plus "undetected"):
      normal       no fault active, neither detected nor alarm
      false_alarm  no fault active, detected or alarm (exclusions kept from earlier faults do not
                   count; a detection caused by the filter's recovery right after a fault ends does)
      detected     fault active, flagged, and that fault was detected in time
      missed       fault active and either flagged only after TTA, or not flagged while hazardous
                   and that fault was not detected in time (never, or late)
      undetected   fault active, not flagged, not hazardous -- or hazardous while a detection in
                   time is still to come (then also counted in hmi_epochs if herr > HPL)
    Overlay (not a class): hmi_epochs = herr > HPL with no alarm, at any epoch; also reported as
    ``counts["hmi"]``. The classes (all counts but "hmi") sum to ``epochs``.
    p_fa = false_alarm / (normal + false_alarm) (per fault-free epoch; the paper's 1.25e-4 is
    1 / 8000 over all epochs), p_md = missed / (detected + missed +
    undetected) (per fault epoch). detection_latency_s: first epoch flagged (detected, alarm or an
    exclusion listed) at or after the first fault's onset, minus that onset; with several runs the
    worst run (per-run values in ``detection_latency_runs_s``). ``excluded_satellites``: every
    satellite excluded at some epoch. Epochs without truth are counted in ``epochs_without_truth``
    and classified without the error criteria (never hazardous, never HMI).
    """
    from service.estimation.integrity.monitor import limits

    faults = _raw_faults(scenario)
    rate = scenario.imu.rate_hz
    t0 = scenario.t0_gps_s
    counts = dict.fromkeys(INTEGRITY_CLASSES, 0)
    hpl, vpl, latencies = [], [], []
    hmi = alarms = no_truth = n_ep = 0
    excluded: set[str] = set()
    fault_latency: list[float | None] = []
    for pairs in runs:
        t_rel = [round((m.t - t0) * rate) / rate for m, _ in pairs]
        # first flagged epoch of each fault inside its window
        first_flag: list[float | None] = []
        for s0, s1, sats in faults:
            first_flag.append(
                next(
                    (
                        t
                        for t, (m, _) in zip(t_rel, pairs, strict=True)
                        if s0 <= t < s1 and (m.detected or m.alarm or sats & set(m.excluded))
                    ),
                    None,
                )
            )
        fault_latency += [
            None if f is None else f - s0 for f, (s0, _, _) in zip(first_flag, faults, strict=True)
        ]
        if faults:
            on = faults[0][0]
            det = next(
                (t for t, (m, _) in zip(t_rel, pairs, strict=True) if t >= on and (m.detected or m.alarm)),
                None,
            )
            latencies.append(None if det is None else det - on)
        for t, (m, e) in zip(t_rel, pairs, strict=True):
            n_ep += 1
            tta = limits(m.phase).tta_s
            hpl.append(m.hpl_m)
            vpl.append(m.vpl_m)
            alarms += bool(m.alarm)
            excluded |= set(m.excluded)
            herr = None if e is None else math.hypot(float(e[0]), float(e[1]))
            no_truth += herr is None
            hazardous = herr is not None and (herr > m.hpl_m or herr > m.hal_m)
            if herr is not None and herr > m.hpl_m and not m.alarm:
                hmi += 1
            active = [i for i, (s0, s1, _) in enumerate(faults) if s0 <= t < s1]
            if not active:
                counts["false_alarm" if (m.detected or m.alarm) else "normal"] += 1
                continue
            i = active[0]
            sats = set().union(*(faults[j][2] for j in active))
            in_time = first_flag[i] is not None and first_flag[i] - faults[i][0] <= tta + 1e-9
            if m.detected or m.alarm or sats & set(m.excluded):
                counts["detected" if in_time else "missed"] += 1
            elif hazardous and not in_time:
                counts["missed"] += 1
            else:
                counts["undetected"] += 1
    fault_free = counts["normal"] + counts["false_alarm"]
    faulty = counts["detected"] + counts["missed"] + counts["undetected"]
    counts["hmi"] = hmi  # the paper's HMI column: an overlay on the classes, not summed with them
    lat_known = [x for x in latencies if x is not None]

    def stats(v: list[float]) -> dict:
        return (
            {"median": float(np.median(v)), "max": float(np.max(v))} if v else {"median": None, "max": None}
        )

    return {
        "epochs": n_ep,
        "detection_latency_s": (max(lat_known) if len(lat_known) == len(latencies) else None)
        if latencies
        else None,
        "detection_latency_runs_s": latencies,
        "hpl_m": stats(hpl),
        "vpl_m": stats(vpl),
        "hmi_epochs": hmi,
        "alarms": alarms,
        "counts": counts,
        "p_fa": counts["false_alarm"] / fault_free if fault_free else None,
        "p_md": counts["missed"] / faulty if faulty else None,
        "faults": len(faults) * len(runs),
        "faults_detected_in_time": sum(1 for x in fault_latency if x is not None and x <= _tta(runs) + 1e-9),
        "fault_latency_s": stats([x for x in fault_latency if x is not None]),
        "excluded_satellites": sorted(excluded),
        "epochs_without_truth": no_truth,
    }


def _tta(runs: list) -> float:
    from service.estimation.integrity.monitor import limits

    for pairs in runs:
        for m, _ in pairs:
            return limits(m.phase).tta_s
    return math.inf


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
