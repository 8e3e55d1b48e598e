"""Instructions per vehicle-second of the per-vehicle loop, counted by valgrind: a figure that the
machine's noise does not move (on the project's shared 2-core machine the CPU time of the same run
varies by 2x from one minute to the next, and it has no hardware counters for ``perf stat``).

The messages ``fednav-sim fleet`` publishes for one vehicle (the demo aircraft, 200 Hz IMU, 10 Hz
fixes; as ``benchmarks/vehicle_cost.py``) go through ``VehicleLoop.process`` with every output
serialised, under ``valgrind --tool=callgrind``, for two scenario lengths; the difference of the
two instruction counts divided by the difference of the lengths is what one vehicle-second costs
(the start -- imports, the loop's construction -- cancels out). The two runs go side by side
(instruction counts do not depend on the load). The collector is set as the service sets it after
its start (``service.vehicle.tune_gc``; ``FEDNAV_BENCH_GC=default`` keeps Python's defaults).
Printed with the outputs' digest of the longer run, so that a change can show both that its
outputs are identical and what it saved. ``PYTHONHASHSEED`` is fixed; repeated runs of one tree
agreed to within 0.05 % (30.83-30.84 M per vehicle-second).

Needs valgrind (``apt-get install valgrind``); a run takes ~1.5 min on the project's machine.

Usage: .venv/bin/python benchmarks/instructions.py [--seconds 2 12] [--imu-batch 10]
Before/after: run it once with PYTHONPATH pointing at the other tree's package.
"""

from __future__ import annotations

import argparse
import hashlib
import os
import pickle
import re
import shutil
import subprocess
import sys
import tempfile
from pathlib import Path


def make_inputs(path: Path, seconds: float, imu_batch: int) -> None:
    from vehicle_cost import vehicle_inputs  # benchmarks/, beside this script

    path.write_bytes(pickle.dumps(vehicle_inputs(seconds, imu_batch)))


def run_loop(path: Path, seconds: float) -> None:
    """The measured process: the loop over the first ``seconds`` of the inputs."""
    from fednav.service import keys
    from fednav.service.app import OutputSink
    from fednav.service.config import ServiceConfig
    from fednav.service.vehicle import VehicleLoop, tune_gc

    inputs = pickle.loads(path.read_bytes())
    if os.environ.get("FEDNAV_BENCH_GC") != "default":
        tune_gc()  # as the service after its start
    digest = hashlib.sha256()
    n = [0]

    class Publishers:
        def publish(self, key: str, msg) -> None:
            digest.update(key.encode())
            digest.update(msg.to_json())
            n[0] += 1

    config = ServiceConfig.model_validate(
        {"vehicles": ["*"], "pipelines": [{"name": "lc", "kind": "loosely_coupled"}]}
    )
    loop = VehicleLoop("veh000", config, OutputSink(keys.DEFAULT_PREFIX, Publishers(), None))
    t0 = inputs[0][0]
    for t, kind, sensor_id, payload in inputs:
        if t - t0 > seconds:
            break
        loop.process(kind, sensor_id, payload)
    print(f"outputs {n[0]} digest {digest.hexdigest()[:16]}", flush=True)


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--seconds", type=float, nargs=2, default=(2.0, 12.0), help="the two scenario lengths")
    ap.add_argument("--imu-batch", type=int, default=10, help="samples per ImuBatch, 1 = JSON (default 10)")
    ap.add_argument("--_run", nargs=2, help=argparse.SUPPRESS)  # internal: INPUTS SECONDS
    args = ap.parse_args()
    if args._run:
        run_loop(Path(args._run[0]), float(args._run[1]))
        return 0
    valgrind = shutil.which("valgrind")
    if valgrind is None:
        print("valgrind not found (apt-get install valgrind)", file=sys.stderr)
        return 2
    short, long_ = sorted(args.seconds)
    with tempfile.TemporaryDirectory(prefix="instructions_") as tmp:
        inputs = Path(tmp) / "inputs.pkl"
        make_inputs(inputs, long_ + 1.0, args.imu_batch)
        env = dict(os.environ, PYTHONHASHSEED="0", OPENBLAS_NUM_THREADS="1")
        procs = [
            subprocess.Popen(
                [valgrind, "--tool=callgrind", "--callgrind-out-file=/dev/null", sys.executable, __file__]
                + ["--_run", str(inputs), str(s)],
                env=env,
                stdout=subprocess.PIPE,
                stderr=subprocess.PIPE,
                text=True,
            )
            for s in (short, long_)
        ]
        outs = [p.communicate() for p in procs]
    counts = []
    for (_, err), p in zip(outs, procs, strict=True):
        m = re.search(r"Collected : (\d+)", err)
        if p.returncode != 0 or m is None:
            print(f"valgrind run failed ({p.returncode}):\n{err[-2000:]}", file=sys.stderr)
            return 1
        counts.append(int(m.group(1)))
    per_s = (counts[1] - counts[0]) / (long_ - short)
    inputs_text = f"ImuBatch of {args.imu_batch}" if args.imu_batch > 1 else "JSON"
    print(
        f"one vehicle, {inputs_text}: {per_s / 1e6:.2f} M instructions per vehicle-second "
        f"({counts[0]:,} at {short:g} s, {counts[1]:,} at {long_:g} s); {outs[1][0].strip()}"
    )
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
