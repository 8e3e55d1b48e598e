"""CPU cost of the IMM's conditional residuals (``residuals = "conditional"``, docs/seed003.md "Set
1001 per run") against the marginal ones: ``tc_imm_sel`` of seed003_outliers (seed 3, the first
200 s, 10 Hz GNSS epochs of ~20 pseudoranges and range rates) through the engine, the two runs
alternated three times in one process; the minimum of each.

Usage: OPENBLAS_NUM_THREADS=1 .venv/bin/python benchmarks/imm_residuals_cost.py
"""

from __future__ import annotations

import os
import time

os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")

from fednav.service import keys  # noqa: E402
from fednav.service.engine import VehicleEngine  # noqa: E402
from fednav.simulators.evaluate import service_config  # noqa: E402
from fednav.simulators.scenario import load_scenario  # noqa: E402
from fednav.simulators.stream import Simulation  # noqa: E402

DURATION_S = 200.0


class Sink:
    def on_estimate(self, *a) -> None:
        pass

    def on_output(self, *a, **k) -> None:
        pass

    def on_truth(self, *a) -> None:
        pass


def main() -> None:
    sc = load_scenario("seed003_outliers")
    msgs = []
    for key, msg in Simulation(sc, seed=3):
        if msg.t - sc.t0_gps_s > DURATION_S:
            break
        pk = keys.parse_input(key)
        msgs.append((pk.kind, pk.sensor_id, msg))
    base = service_config(sc)
    imm = next(p for p in base.pipelines if p.name == "tc_imm_sel")
    cpu: dict[str, list[float]] = {"marginal": [], "conditional": []}
    for _ in range(3):
        for name in cpu:
            cfg = base.model_copy(update={"pipelines": [imm.model_copy(update={"residuals": name})]})
            eng = VehicleEngine("v1", cfg, Sink())
            t0 = time.process_time()
            for kind, sid, msg in msgs:
                eng.handle(kind, sid, msg)
            cpu[name].append(time.process_time() - t0)
    epochs = sum(1 for kind, _, _ in msgs if kind == "gnss_raw")
    for name, v in cpu.items():
        print(
            f"{name:12s} CPU s per {DURATION_S:.0f} s of data {[round(x, 2) for x in v]}, "
            f"min {min(v):.2f}: {1000.0 * min(v) / epochs:.3f} ms per GNSS epoch ({epochs} epochs)"
        )
    print(f"conditional / marginal: {min(cpu['conditional']) / min(cpu['marginal']):.3f}")


if __name__ == "__main__":
    main()
