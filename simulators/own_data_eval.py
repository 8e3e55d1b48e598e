"""The issue-10 outside check on a simulated drive: is the fused solution better than the receiver?

``python -m fednav.simulators.own_data_eval --runs 10`` runs a scenario (default ``own_data_phone_car``)
in process, seeded (runs ``seed .. seed + runs - 1``), and prints per pipeline, pooled over runs
and over the epochs after ``--skip-s`` seconds (initial convergence):

* horizontal error (median, RMS, max) of the solution beside the fixes' own (fix minus the true
  antenna position), vertical RMS/max beside the fixes';
* horizontal velocity RMS beside the fixes' (speed/course turned into east/north);
* heading RMS beside the receiver's course over ground as a heading (speeds above 2 m/s);
* sigma ratios: RMS horizontal error / RMS reported horizontal sigma (and vertical), and the
  mean position NEES / 3 (1 = consistent; the outside check asks for a factor within 1.5);
* observations refused by screening (innovation gate / fault tests) per run.
"""

from __future__ import annotations

import argparse
import json
import math
import sys
from dataclasses import dataclass, field

import numpy as np

from fednav.service import keys
from fednav.service.engine import VehicleEngine
from fednav.service.messages import Faults, GnssFix
from fednav.simulators.evaluate import service_config
from fednav.simulators.scenario import Scenario, load_scenario, scenario_path
from fednav.simulators.stream import Simulation
from fednav.simulators.trajectory import mat_nb_vec, radii_vec


@dataclass
class _Rec:
    t: list = field(default_factory=list)
    err: list = field(default_factory=list)
    P: list = field(default_factory=list)
    refused: int = 0


class _Sink:
    def __init__(self):
        self.records: dict[str, _Rec] = {}

    def on_estimate(self, vehicle, out) -> None:
        if out.err9 is None:
            return
        r = self.records.setdefault(out.name, _Rec())
        r.t.append(out.t)
        r.err.append(out.err9)
        r.P.append(out.P9[:3, :3].copy())

    def on_output(self, vehicle, msg, err9=None) -> None:
        if isinstance(msg, Faults):
            r = self.records.setdefault(msg.pipeline, _Rec())
            r.refused += sum(o.isolated for s in msg.subsystems for o in s.observations)

    def on_truth(self, vehicle, truth) -> None:
        pass


def fix_errors(sim: Simulation, lever_b_m: np.ndarray) -> dict[str, np.ndarray]:
    """Each fix against the true antenna: t, ENU position error (m), horizontal velocity error
    (m/s; NaN for position-only fixes) and course minus true heading (deg; NaN below 2 m/s)."""
    traj = sim.truth.trajectory
    fixes = [(k, m) for k, m in sim._gnss if isinstance(m, GnssFix)]
    ks = np.array([k for k, _ in fixes])
    c_nb = mat_nb_vec(traj.rpy_rad[ks])
    w_b, _ = traj.body_rates(ks / traj.imu_rate_hz)
    ant_p = np.einsum("pij,j->pi", c_nb, lever_b_m)
    ant_v = traj.vel_enu_mps[ks] + np.einsum("pij,pj->pi", c_nb, np.cross(w_b, lever_b_m))
    lat, lon, h = traj.llh[ks].T
    r_m, r_n = radii_vec(lat)
    out_p, out_v, out_c = [], [], []
    for i, (_, m) in enumerate(fixes):
        dlat = math.radians(m.lat_deg) - lat[i]
        dlon = (math.radians(m.lon_deg) - lon[i] + math.pi) % (2 * math.pi) - math.pi
        p = np.array([dlon * (r_n[i] + h[i]) * math.cos(lat[i]), dlat * (r_m[i] + h[i]), m.height_m - h[i]])
        out_p.append(p - ant_p[i])
        v = m.velocity()
        out_v.append(np.full(2, np.nan) if v is None else np.asarray(v[:2]) - ant_v[i, :2])
        speed = float(np.hypot(*ant_v[i, :2]))
        if v is None or speed < 2.0:
            out_c.append(np.nan)
        else:
            course = math.degrees(math.atan2(v[0], v[1]))
            heading = -math.degrees(traj.rpy_rad[ks[i], 2])
            out_c.append((course - heading + 180.0) % 360.0 - 180.0)
    return {
        "t": traj.t_s[ks],
        "pos": np.array(out_p),
        "vel_h": np.array(out_v),
        "course_minus_heading_deg": np.array(out_c),
    }


def run_once(scenario: Scenario, seed: int, cfg, traj) -> tuple[_Sink, dict]:
    sink = _Sink()
    engine = VehicleEngine("v1", cfg, sink)
    sim = Simulation(scenario, seed=seed, trajectory=traj, prefix=cfg.prefix)
    for key, msg in sim:
        pk = keys.parse_input(key, cfg.prefix)
        engine.handle(pk.kind, pk.sensor_id, msg)
    lever = np.asarray(scenario.gnss.lever_arm_b_m, dtype=float)
    return sink, fix_errors(sim, lever)


def _h(e: np.ndarray) -> np.ndarray:
    return np.hypot(e[:, 0], e[:, 1])


def _rms(x: np.ndarray) -> float:
    x = x[np.isfinite(x)]
    return float(math.sqrt(np.mean(x * x))) if x.size else float("nan")


def collect(scenario: Scenario, runs: int, seed: int) -> dict:
    """The raw per-run figures of ``runs`` seeded runs (seeds seed, seed + 1, ...)."""
    cfg = service_config(scenario)
    traj = scenario.build_trajectory()
    t0 = float(traj.t_s[0])
    out: dict = {"scenario": scenario.name, "runs": runs, "seed": seed, "fixes": [], "pipelines": {}}
    for i in range(runs):
        sink, fe = run_once(scenario, seed + i, cfg, traj)
        out["fixes"].append({**fe, "t": fe["t"] - t0})
        for name, rec in sink.records.items():
            if rec.err:
                out["pipelines"].setdefault(name, []).append(
                    (np.asarray(rec.t) - t0, np.asarray(rec.err), np.asarray(rec.P), rec.refused)
                )
    return out


def summarise(raw: dict, skip_s: float) -> dict:
    """The outside check's figures over the epochs after ``skip_s`` (module docstring)."""
    sel = [f["t"] >= skip_s for f in raw["fixes"]]
    fp = np.concatenate([f["pos"][s] for f, s in zip(raw["fixes"], sel, strict=True)])
    fv = np.concatenate([f["vel_h"][s] for f, s in zip(raw["fixes"], sel, strict=True)])
    fc = np.concatenate([f["course_minus_heading_deg"][s] for f, s in zip(raw["fixes"], sel, strict=True)])
    out = {
        "scenario": raw["scenario"],
        "runs": raw["runs"],
        "seed": raw["seed"],
        "skip_s": skip_s,
        "receiver": {
            "h_median_m": float(np.median(_h(fp))),
            "h_rms_m": _rms(_h(fp)),
            "h_max_m": float(np.max(_h(fp))),
            "v_rms_m": _rms(fp[:, 2]),
            "v_max_m": float(np.max(np.abs(fp[:, 2]))),
            "hvel_rms_mps": _rms(np.hypot(fv[:, 0], fv[:, 1])),
            "heading_rms_deg": _rms(fc),
        },
        "pipelines": {},
    }
    for name, per_run in raw["pipelines"].items():
        e = np.concatenate([err[t >= skip_s] for t, err, _, _ in per_run])
        P = np.concatenate([cov[t >= skip_s] for t, _, cov, _ in per_run])
        he = _h(e)
        sig_h2 = P[:, 0, 0] + P[:, 1, 1]
        nees3 = np.einsum("pi,pi->p", e[:, :3], np.linalg.solve(P, e[:, :3][..., None])[..., 0])
        out["pipelines"][name] = {
            "h_median_m": float(np.median(he)),
            "h_rms_m": _rms(he),
            "h_max_m": float(np.max(he)),
            "v_rms_m": _rms(e[:, 2]),
            "v_max_m": float(np.max(np.abs(e[:, 2]))),
            "hvel_rms_mps": _rms(np.hypot(e[:, 3], e[:, 4])),
            "heading_rms_deg": math.degrees(_rms(e[:, 8])),
            "h_sigma_ratio": _rms(he) / math.sqrt(float(np.mean(sig_h2))),
            "v_sigma_ratio": _rms(e[:, 2]) / math.sqrt(float(np.mean(P[:, 2, 2]))),
            "pos_nees_per_dof": float(np.mean(nees3)) / 3.0,
            "refused_rows_per_run": float(np.mean([r for *_, r in per_run])),
        }
    return out


def evaluate(scenario: Scenario, runs: int, seed: int, skip_s: float) -> dict:
    """:func:`collect` then :func:`summarise` after ``skip_s``."""
    return summarise(collect(scenario, runs, seed), skip_s)


def format_table(res: dict) -> str:
    cols = [
        ("h_median_m", "h med m"),
        ("h_rms_m", "h RMS m"),
        ("h_max_m", "h max m"),
        ("v_rms_m", "v RMS m"),
        ("v_max_m", "v max m"),
        ("hvel_rms_mps", "hvel RMS m/s"),
        ("heading_rms_deg", "hdg RMS deg"),
        ("h_sigma_ratio", "h err/sigma"),
        ("v_sigma_ratio", "v err/sigma"),
        ("pos_nees_per_dof", "NEES/3"),
        ("refused_rows_per_run", "refused/run"),
    ]
    lines = [
        f"{res['scenario']}: {res['runs']} runs from seed {res['seed']}, epochs after {res['skip_s']:g} s",
        "| solution | " + " | ".join(c[1] for c in cols) + " |",
        "|---" * (len(cols) + 1) + "|",
    ]
    rows = [("receiver (fixes)", res["receiver"])] + list(res["pipelines"].items())
    for name, r in rows:
        cells = [f"{r[k]:.3f}" if k in r and np.isfinite(r[k]) else "-" for k, _ in cols]
        lines.append(f"| {name} | " + " | ".join(cells) + " |")
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("scenario", nargs="?", default="own_data_phone_car")
    ap.add_argument("--runs", type=int, default=3)
    ap.add_argument("--seed", type=int, default=None)
    ap.add_argument(
        "--skip-s",
        type=float,
        nargs="+",
        default=[30.0],
        help="initial convergence left out, s (one table each)",
    )
    ap.add_argument("--json", type=str, default=None, help="also write the figures to this file")
    ap.add_argument(
        "--imu-grade",
        default=None,
        help="override the filters' [service.imu] with this grade (e.g. navigation)",
    )
    args = ap.parse_args(argv)
    sc = load_scenario(scenario_path(args.scenario))
    if args.imu_grade:
        sc = sc.model_copy(update={"service": {**dict(sc.service), "imu": {"grade": args.imu_grade}}})
    raw = collect(sc, args.runs, sc.seed if args.seed is None else args.seed)
    results = [summarise(raw, s) for s in args.skip_s]
    for res in results:
        print(format_table(res))
        print()
    if args.json:
        with open(args.json, "w") as f:
            json.dump(results, f, indent=2)
    return 0


if __name__ == "__main__":
    sys.exit(main())
