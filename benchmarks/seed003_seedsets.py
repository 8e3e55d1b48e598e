"""Seed 003 over several seed sets: ``fednav-sim eval --seeds`` with extra pipeline variants.

The same evaluation as ``fednav-sim eval SCENARIO --seeds 3,103,203 --runs 10 --json`` (the
scenario's pipelines, the same streams and figures: :func:`simulators.evaluate.evaluate`), with
variants appended to the scenario's [service] pipelines so that the "before" of a change runs on
the same streams as the "after":

    tc_imm_sel_fixed   tc_imm_sel with the paper's fixed Markov matrix (learn_transition_s = None:
                       the recommended IMM before the learned transition; the marginal residuals)
    tc_imm_sel_marginal  tc_imm_sel choosing and weighing rows by the marginal v_i (the recommended
                       IMM before the conditional residuals, 2026-12-02)

``--pipelines`` picks pipelines (the scenario's and the variants, by name). Writes
``{"seed_sets": across_seed_sets(...), "sets": [...]}`` (the JSON of ``fednav-sim eval --seeds``)
to ``--out``, rewritten after every seed set (a cut-short run keeps the finished sets).

``--table CLEAN.json OUTLIERS.json`` prints the markdown table of docs/seed003.md from two such
files: per pipeline, the 3-D position RMS (whole run) and NEES on each scenario and the change
against the KF on clean data of the same seed set, as the mean over the sets [min - max].

Usage: OPENBLAS_NUM_THREADS=1 nice -n 5 .venv/bin/python benchmarks/seed003_seedsets.py
       seed003_outliers --seeds 3,103,203 --runs 10 --pipelines tc,tc_imm_sel,tc_imm_sel_fixed,tc_gate
       --out docs/seed003_seedsets_outliers.json
       .venv/bin/python benchmarks/seed003_seedsets.py --table CLEAN.json OUTLIERS.json
"""

from __future__ import annotations

import argparse
import json
import sys

import numpy as np
from seed003_remedies import pin_clock

from fednav.simulators import evaluate as ev
from fednav.simulators.scenario import load_scenario

VARIANTS = {
    "tc_imm_sel_fixed": {
        "kind": "imm_tightly_coupled",
        "likelihood": "gaussian",
        "selection_correction": True,
        "learn_transition_s": None,
        "residuals": "marginal",
    },
    "tc_imm_sel_marginal": {
        "kind": "imm_tightly_coupled",
        "likelihood": "gaussian",
        "selection_correction": True,
        "residuals": "marginal",
    },
}


def _spread(values: list[float], fmt: str) -> str:
    return f"{np.mean(values):{fmt}} [{min(values):{fmt}} - {max(values):{fmt}}]"


def table(clean_path: str, outliers_path: str) -> str:
    """Markdown: mean over the seed sets [min - max] per pipeline and scenario."""
    runs = {"clean": json.load(open(clean_path))["sets"], "outliers": json.load(open(outliers_path))["sets"]}
    seeds = [r["seed"] for r in runs["clean"]]
    if seeds != [r["seed"] for r in runs["outliers"]]:
        raise SystemExit("the two files have different seed sets")
    kf = [r["pipelines"]["tc"]["pos_rms_m"] for r in runs["clean"]]
    names = list(runs["clean"][0]["pipelines"])
    head = (
        "| pipeline | clean: RMS (m) | vs KF clean | NEES | outliers: RMS (m) | vs KF clean | NEES |\n"
        "|---|---|---|---|---|---|---|"
    )
    lines = [head]
    for n in names:
        cells = []
        for sc in ("clean", "outliers"):
            sets = [r["pipelines"].get(n) for r in runs[sc]]
            if any(e is None for e in sets):
                cells += ["-", "-", "-"]
                continue
            rms = [e["pos_rms_m"] for e in sets]
            pct = [100.0 * (v / k - 1.0) for v, k in zip(rms, kf, strict=True)]
            cells += [
                _spread(rms, ".4f"),
                _spread(pct, "+.2f") + " %",
                _spread([e["nees"]["mean"] for e in sets], ".2f"),
            ]
        lines.append(f"| `{n}` | " + " | ".join(cells) + " |")
    per_set = ", ".join(str(s) for s in seeds)
    return (
        f"seed sets {per_set} ({runs['clean'][0]['runs']} runs each): mean [min - max] over the sets\n\n"
        + "\n".join(lines)
    )


def main() -> int:
    if len(sys.argv) == 4 and sys.argv[1] == "--table":
        print(table(sys.argv[2], sys.argv[3]))
        return 0
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("scenario")
    ap.add_argument("--seeds", default="3,103,203")
    ap.add_argument("--runs", type=int, default=10)
    ap.add_argument("--pipelines", help="comma-separated names (default: the scenario's and the variants)")
    ap.add_argument("--out", required=True)
    args = ap.parse_args()
    sc = load_scenario(args.scenario)
    service = dict(sc.service)
    service["pipelines"] = list(service["pipelines"]) + pin_clock(
        [dict(v, name=n) for n, v in VARIANTS.items()]
    )
    sc = sc.model_copy(update={"service": service})
    names = args.pipelines.split(",") if args.pipelines else None
    sets = []
    for seed in (int(s) for s in args.seeds.split(",")):
        sets.append(ev.evaluate(sc, runs=args.runs, seed=seed, pipelines=names))
        with open(args.out, "w") as fh:
            json.dump({"seed_sets": ev.across_seed_sets(sets), "sets": sets}, fh, indent=2)
        wall = sets[-1]["timing"]["wall_s"]
        print(f"{args.scenario}: seed set {seed} done ({wall:.0f} s)", file=sys.stderr, flush=True)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
