"""Real-time factor of the seed-000 pipelines side by side (in-process, one core).

The paper's five pipelines (fed_fixed, fed_scalar, fed_vector, fed_vector_sysiso, centralized)
on the 800 s scenario at a 100 Hz IMU, and, for reference, all seven configured ones and a single
loosely coupled pipeline on the same scenario. Usage: .venv/bin/python benchmarks/federated.py
"""

from __future__ import annotations

import json
import os

os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")

from fednav.simulators.evaluate import evaluate  # noqa: E402
from fednav.simulators.scenario import load_scenario  # noqa: E402

PAPER = ["fed_fixed", "fed_scalar", "fed_vector", "fed_vector_sysiso", "centralized"]


def with_pipelines(sc, pipelines):
    service = dict(sc.service)
    service["pipelines"] = pipelines
    return sc.model_copy(update={"service": service})


def main() -> int:
    sc = load_scenario("seed000_faults")
    all_p = sc.service["pipelines"]
    cases = {
        "paper_five": [p for p in all_p if p["name"] in PAPER],
        "all_seven": all_p,
        "single_lc": [{"name": "lc", "kind": "loosely_coupled"}],
    }
    out = {}
    for name, pipes in cases.items():
        r = evaluate(with_pipelines(sc, pipes), runs=1, seed=7)
        out[name] = {
            "pipelines": len(pipes),
            "realtime_factor": round(r["timing"]["realtime_factor"], 1),
            "wall_s": round(r["timing"]["wall_s"], 2),
        }
        print(json.dumps({name: out[name]}), flush=True)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
