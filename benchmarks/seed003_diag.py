"""Seed 003: where the outlier IMM loses (a diagnostic, not a speed test).

Per seed, seed003_clean and seed003_outliers (the same noise: the outliers draw from the fault's
own stream) with the KF and IMM variants on the same stream. Printed per variant and pooled over
the seeds: the 3-D position RMS over the whole run and its change against the KF on clean data,
the outlier-induced error (RMS of error with outliers - error without, paired on the same noise)
per span of the run (the three outlier windows, split at 10 s and 50 s for the convergence), and
for every injected outlier (its window, size in sigmas, the filter's standardised residual at
that epoch) how much weight the combined filter still gave the hit row: its effective R factor
1 / sum_j mu_j / R_factor_j (1: used in full; >= 10: down-weighted; the gate's rejections count
as removed), with the normal model's probability after the update.

Usage: OPENBLAS_NUM_THREADS=1 .venv/bin/python benchmarks/seed003_diag.py --seeds 103,104,105
       [--variants tc,sel] [--json PATH]
"""

from __future__ import annotations

import argparse
import json
import math
from collections import defaultdict

import numpy as np
from seed003_remedies import GATE, pin_clock

from fednav.service import config as config_mod
from fednav.service.messages import ImmModels
from fednav.simulators import evaluate as ev
from fednav.simulators import faults as faults_mod
from fednav.simulators.scenario import load_scenario

GAUSS = {"kind": "imm_tightly_coupled", "likelihood": "gaussian", "selection_correction": False}
SEL = dict(GAUSS, selection_correction=True, residuals="marginal")
VARIANTS: dict[str, dict] = {
    "tc": {"kind": "tightly_coupled", "integrity": False, "elevation_mask_deg": 5.0},
    # the variants of the figures in docs/seed003.md chose and weighed rows by the marginal v_i
    "sel": dict(SEL, learn_transition_s=None),  # tc_imm_sel before the learning
    "learn": dict(SEL, learn_transition_s=60.0),  # tc_imm_sel before the conditional residuals
    "learn20": dict(SEL, learn_transition_s=20.0),
    "learn_c16": dict(SEL, learn_transition_s=60.0, big=16.0),
    "sel_c16": dict(SEL, learn_transition_s=None, big=16.0),
    "sel_gate": dict(SEL, learn_transition_s=None, gate_p_fa=0.001),
    "cond": dict(SEL, learn_transition_s=60.0, residuals="conditional"),  # = tc_imm_sel now
    "gauss": GAUSS,  # = tc_imm_gauss
    "gate": GATE,  # = tc_gate
}
SPANS = ((0, 10), (10, 50), (50, 200), (200, 400), (400, 500), (500, 700))

HITS: list[tuple[float, str, float]] = []  # (t from start, channel, signed size in sigmas)
_orig_outliers = faults_mod.FaultSet._outliers


def _recording_outliers(self, i, f, t_rel_s, out, published):
    before = dict(out)
    _orig_outliers(self, i, f, t_rel_s, out, published)
    for c, v in out.items():
        if v != before[c]:
            HITS.append((float(t_rel_s), c, (v - before[c]) / f.sigma))


faults_mod.FaultSet._outliers = _recording_outliers


def run(scenario: str, seed: int, names: list[str]) -> tuple[dict, list, float]:
    sc = load_scenario(scenario)
    service = dict(sc.service)
    service["pipelines"] = pin_clock([dict(VARIANTS[n], name=n) for n in names])
    cfg = config_mod.from_dict(service, "seed003_diag")
    traj = sc.build_trajectory()
    HITS.clear()
    sink, _ = ev.run_once(sc, seed, cfg, trajectory=traj)
    return sink.records, list(HITS), float(traj.t_s[0])


def hit_weights(rec, hits, t0: float) -> list[dict]:
    """Per injected outlier: the combined filter's effective R factor on the hit row."""
    msgs = {round(m.t - t0, 3): m for m in rec.outputs if isinstance(m, ImmModels)}
    out = []
    for t, ch, k in hits:
        m = msgs.get(round(t, 3))
        row = ch.replace(".pseudorange", ".pr")
        if m is None or row not in m.rows:
            continue
        i = m.rows.index(row)
        if row in m.rejected:
            eff = math.inf
        else:
            mu = np.array(m.probabilities)
            rs = np.array(m.r_scale)[:, i]
            eff = 1.0 / float(np.sum(mu / rs))
        p_normal = m.probabilities[m.models.index("normal")] if "normal" in m.models else 1.0
        out.append({"t": t, "k": k, "v": m.standardised_residual[i], "eff_r": eff, "p_normal": p_normal})
    return out


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--seeds", default="103,104,105")
    ap.add_argument("--variants", default="tc,sel")
    ap.add_argument("--json", help="write the figures here")
    args = ap.parse_args()
    seeds = [int(s) for s in args.seeds.split(",")]
    names = args.variants.split(",")
    if "tc" not in names:
        names = ["tc", *names]
    ss = defaultdict(lambda: defaultdict(float))  # (variant, scen) -> span -> sum sq
    nn = defaultdict(lambda: defaultdict(int))
    ind = defaultdict(lambda: defaultdict(float))  # variant -> span -> induced sum sq
    hitw = defaultdict(list)
    per_seed = []
    for seed in seeds:
        errs = {}
        for scen in ("seed003_clean", "seed003_outliers"):
            recs, hits, t0 = run(scen, seed, names)
            for n in names:
                r = recs[n]
                t = np.array(r.t) - t0
                e = np.linalg.norm(np.array(r.err)[:, 0:3], axis=1)
                errs[(n, scen)] = (t, np.array(r.err)[:, 0:3])
                for a, b in SPANS:
                    sel = (t >= a) & (t < b)
                    ss[(n, scen)][(a, b)] += float(np.sum(e[sel] ** 2))
                    nn[(n, scen)][(a, b)] += int(sel.sum())
                if scen == "seed003_outliers" and n != "tc":
                    hitw[n] += hit_weights(r, hits, t0)
        row = {"seed": seed}
        for n in names:
            tc_, ec = errs[(n, "seed003_clean")]
            to, eo = errs[(n, "seed003_outliers")]
            k = min(len(tc_), len(to))
            d = np.linalg.norm(eo[:k] - ec[:k], axis=1) ** 2
            for a, b in SPANS:
                sel = (to[:k] >= a) & (to[:k] < b)
                ind[n][(a, b)] += float(np.sum(d[sel]))
            row[n] = {
                s: math.sqrt(float(np.mean(np.sum(errs[(n, s)][1] ** 2, axis=1))))
                for s in ("seed003_clean", "seed003_outliers")
            }
        base = row["tc"]["seed003_clean"]
        print(
            f"seed {seed}: "
            + "  ".join(
                f"{n} clean {100 * (row[n]['seed003_clean'] / base - 1):+.2f}% out "
                f"{100 * (row[n]['seed003_outliers'] / base - 1):+.2f}%"
                for n in names
            ),
            flush=True,
        )
        per_seed.append(row)

    def tot(n, scen):
        return math.sqrt(sum(ss[(n, scen)].values()) / sum(nn[(n, scen)].values()))

    base = tot("tc", "seed003_clean")
    fig = {"seeds": seeds, "per_seed": per_seed, "variants": {}}
    print(f"\npooled over seeds {seeds}: 3-D position RMS, whole run (vs KF clean)")
    for n in names:
        c, o = tot(n, "seed003_clean"), tot(n, "seed003_outliers")
        v = {
            "clean": c,
            "outliers": o,
            "clean_pct": 100 * (c / base - 1),
            "outliers_pct": 100 * (o / base - 1),
        }
        # share of the whole-run sum of squares (outliers minus KF clean) by span
        tot_n = sum(nn[("tc", "seed003_clean")].values())
        v["excess_ms_by_span"] = {
            f"{a}-{b}": (ss[(n, "seed003_outliers")][(a, b)] - ss[("tc", "seed003_clean")][(a, b)]) / tot_n
            for a, b in SPANS
        }
        v["induced_rms_by_span"] = {
            f"{a}-{b}": math.sqrt(ind[n][(a, b)] / max(nn[(n, "seed003_outliers")][(a, b)], 1))
            for a, b in SPANS
        }
        print(
            f"  {n:10s} clean {c:.4f} ({v['clean_pct']:+.2f} %)  outliers {o:.4f} ({v['outliers_pct']:+.2f}%)"
        )
        print(
            "    excess mean square vs KF clean by span (m^2, sums to the total): "
            + " ".join(f"{k}: {x:+.4f}" for k, x in v["excess_ms_by_span"].items())
        )
        print(
            "    outlier-induced RMS by span (m): "
            + " ".join(f"{k}: {x:.3f}" for k, x in v["induced_rms_by_span"].items())
        )
        hw = hitw.get(n, [])
        if hw:
            tab = {}
            for a, b in ((0, 200), (200, 400), (500, 700)):
                for k in (3.0, 5.0, 8.0):
                    hs = [h for h in hw if a <= h["t"] < b and abs(abs(h["k"]) - k) < 1e-6]
                    if not hs:
                        continue
                    eff = np.array([h["eff_r"] for h in hs])
                    tab[f"{a}-{b} {k:g}s"] = {
                        "n": len(hs),
                        "used_full": float(np.mean(eff < 2)),
                        "partial": float(np.mean((eff >= 2) & (eff < 10))),
                        "downweighted": float(np.mean(eff >= 10)),
                        "median_abs_v": float(np.median([abs(h["v"]) for h in hs])),
                        "mean_p_normal": float(np.mean([h["p_normal"] for h in hs])),
                        "early_10s": sum(h["t"] < 10 for h in hs),
                    }
            v["hits"] = tab
            print(
                "    hits: window size: n, used in full (R factor < 2) / partly (2-10) / "
                "down-weighted (>= 10), median |v|, mean P(normal)"
            )
            for key, h in tab.items():
                print(
                    f"      {key:12s} n {h['n']:4d}  {h['used_full']:.2f} / {h['partial']:.2f} / "
                    f"{h['downweighted']:.2f}  |v| {h['median_abs_v']:.2f}  P(n) {h['mean_p_normal']:.2f}"
                )
        fig["variants"][n] = v
    if args.json:
        with open(args.json, "w") as fh:
            json.dump(fig, fh, indent=2)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
