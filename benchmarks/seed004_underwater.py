"""Real-time factor of the seed-004 ``underwater`` family at a 100 Hz IMU (in-process, one core).

The seed004_nominal stream (1000 s, IMU 100 Hz, USBL and DVL 1 Hz) is generated once into a list;
then each case is timed through the service's engine alone (acceptance rules, INS, filter bank,
fusion and reset, Faults/Solution outputs to an in-memory sink), so the figure is the family's
cost, not the simulator's. Both wall-clock and process CPU time are printed: on a shared
machine the CPU figure is the one-core cost. Cases: one federated pipeline per sharing method
(5.1 as printed, 5.2, 5.3), the centralised comparator, and the six pipelines of the scenario
side by side. The
figure of the whole ``fednav-sim eval`` path (simulation included) is printed last.

Usage: .venv/bin/python benchmarks/seed004_underwater.py [--duration 1000]
"""

from __future__ import annotations

import argparse
import json
import os
import time

os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")
os.environ.setdefault("OMP_NUM_THREADS", "1")

from fednav.service import config as config_mod  # noqa: E402
from fednav.service import keys  # noqa: E402
from fednav.service.engine import VehicleEngine  # noqa: E402
from fednav.simulators.evaluate import CollectingSink, evaluate  # noqa: E402
from fednav.simulators.scenario import load_scenario, parse_scenario  # noqa: E402
from fednav.simulators.stream import Simulation  # noqa: E402


def scenario(duration_s: float):
    d = load_scenario("seed004_nominal").model_dump()
    d["duration_s"] = duration_s
    return parse_scenario(d)


def time_engine(sc, pipelines: list[dict], events: list) -> dict:
    cfg = config_mod.from_dict({**sc.service, "pipelines": pipelines})
    sink = CollectingSink()
    engine = VehicleEngine("v1", cfg, sink)
    t0, c0 = time.perf_counter(), time.process_time()
    for kind, sid, msg in events:
        engine.handle(kind, sid, msg)
    wall, cpu = time.perf_counter() - t0, time.process_time() - c0
    return {
        "pipelines": len(pipelines),
        "wall_s": round(wall, 3),
        "realtime_factor": round(sc.duration_s / wall, 1),
        "cpu_s": round(cpu, 3),
        "realtime_factor_cpu": round(sc.duration_s / cpu, 1),
    }


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--duration", type=float, default=1000.0, help="scenario length, s")
    args = ap.parse_args(argv)
    sc = scenario(args.duration)
    prefix = keys.DEFAULT_PREFIX
    t0 = time.perf_counter()
    events = []
    for key, msg in Simulation(sc, seed=4):
        pk = keys.parse_input(key, prefix)
        events.append((pk.kind, pk.sensor_id, msg))
    print(json.dumps({"stream": {"events": len(events), "generate_s": round(time.perf_counter() - t0, 2)}}))
    by_name = {p["name"]: p for p in sc.service["pipelines"]}
    cases = {
        "fed_eigen_trace (5.1)": [by_name["fed_eigen_trace"]],
        "fed_diagonal (5.2)": [by_name["fed_diagonal"]],
        "fed_edop (5.3)": [by_name["fed_edop"]],
        "centralized": [by_name["centralized"]],
        "all six": list(sc.service["pipelines"]),
    }
    time_engine(sc, cases["fed_edop (5.3)"], events[: len(events) // 10])  # warm-up
    for name, pipes in cases.items():
        print(json.dumps({name: time_engine(sc, pipes, events)}), flush=True)
    one = sc.model_copy(update={"service": {**sc.service, "pipelines": cases["fed_edop (5.3)"]}})
    r = evaluate(one, runs=1, seed=4)
    print(
        json.dumps(
            {
                "eval fed_edop (simulation included)": {
                    "realtime_factor": round(r["timing"]["realtime_factor"], 1)
                }
            }
        )
    )
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
