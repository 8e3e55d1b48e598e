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

``--mhss``: the same count for the tightly coupled pipeline with MHSS integrity of
``benchmarks/mhss_bank.py`` (12 satellites, 79 filters, 100 Hz IMU, 10 Hz pseudoranges and range
rates), driven directly as that benchmark drives it: instructions per second of data, with the
digest of every Integrity message and of the final state and covariance.

Usage: .venv/bin/python benchmarks/instructions.py [--seconds 2 12] [--imu-batch 10] [--imu-hz 200]
           [--without KIND ...] [--mhss [--untied]]
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


def make_inputs(
    path: Path, seconds: float, imu_batch: int, without: tuple[str, ...] = (), imu_hz: float = 200.0
) -> None:
    from vehicle_cost import vehicle_inputs  # benchmarks/, beside this script

    inputs = [m for m in vehicle_inputs(seconds, imu_batch, imu_hz) if m[1] not in without]
    path.write_bytes(pickle.dumps(inputs))


def make_mhss_inputs(path: Path, seconds: float) -> None:
    import mhss_bank  # benchmarks/, beside this script

    traj, msgs = mhss_bank.make_inputs(seconds)
    path.write_bytes(pickle.dumps((traj, msgs)))


def run_mhss(path: Path, seconds: float, untied: bool = False) -> None:
    """The measured process for ``--mhss``: ``mhss_bank.bench_pipeline``'s loop over the first
    ``seconds`` of the inputs, every Integrity message and the final state digested."""
    import mhss_bank as mb
    import numpy as np

    traj, msgs = pickle.loads(path.read_bytes())
    p = mb.make_pipeline(traj)
    if untied:  # every cross block computed (the bank after an exclusion; mhss_bank.bench_pipeline)
        p.bank.mhss.tied = False
    dth = [tuple(r) for r in traj.dtheta_rad]
    dv = [tuple(r) for r in traj.dvel_mps]
    digest = hashlib.sha256()
    n = 0
    for k in range(1, len(traj.t_s)):
        if traj.t_s[k] - mb.T0 > seconds:
            break
        p.push_imu(dth[k], dv[k], traj.dt_s, float(traj.t_s[k]))
        if k in msgs:
            p.sync()
            for out in p.apply("gnss_raw", "main", msgs[k], 0.0):
                digest.update(out.to_json())
                n += 1
    est = p.estimate()
    digest.update(np.asarray(est.P9).tobytes())
    nav = est.nav
    digest.update(
        np.hstack(
            [
                [nav.t, nav.lat_rad, nav.lon_rad, nav.h_m],
                nav.vel_enu_mps,
                nav.q_nb,
                nav.gyro_bias_rps,
                nav.accel_bias_mps2,
            ]
        ).tobytes()
    )
    print(f"outputs {n} digest {digest.hexdigest()[:16]}", flush=True)


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
    ap.add_argument("--mhss", action="store_true", help="the tightly coupled MHSS pipeline of mhss_bank.py")
    ap.add_argument(
        "--untied", action="store_true", help="with --mhss: every cross block computed (after an exclusion)"
    )
    ap.add_argument("--imu-hz", type=float, default=200.0, help="IMU rate (default 200)")
    ap.add_argument(
        "--without",
        nargs="+",
        default=(),
        metavar="KIND",
        help="leave these input kinds out (e.g. gnss_fix: what the fix epochs cost is the difference)",
    )
    ap.add_argument("--_run", nargs=2, help=argparse.SUPPRESS)  # internal: INPUTS SECONDS
    args = ap.parse_args()
    if args._run:
        if args.mhss:
            run_mhss(Path(args._run[0]), float(args._run[1]), args.untied)
        else:
            run_loop(Path(args._run[0]), float(args._run[1]))
        return 0
    valgrind = shutil.which("valgrind")
    if valgrind is None:
        print("valgrind not found (apt-get install valgrind)", file=sys.stderr)
        return 2
    short, long_ = sorted(args.seconds)
    with tempfile.TemporaryDirectory(prefix="instructions_") as tmp:
        inputs = Path(tmp) / "inputs.pkl"
        if args.mhss:
            make_mhss_inputs(inputs, max(long_ + 1.0, 20.0))
        else:
            make_inputs(inputs, long_ + 1.0, args.imu_batch, tuple(args.without), args.imu_hz)
        env = dict(os.environ, PYTHONHASHSEED="0", OPENBLAS_NUM_THREADS="1")
        procs = [
            subprocess.Popen(
                [valgrind, "--tool=callgrind", "--callgrind-out-file=/dev/null", sys.executable, __file__]
                + ["--_run", str(inputs), str(s)]
                + (["--mhss"] if args.mhss else [])
                + (["--untied"] if args.untied else []),
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
    if args.mhss:
        what = "tightly coupled + MHSS (12 satellites, 79 filters" + (
            ", every cross block computed)" if args.untied else ")"
        )
    else:
        what = "one vehicle, " + (f"ImuBatch of {args.imu_batch}" if args.imu_batch > 1 else "JSON")
        if args.imu_hz != 200.0:
            what += f", IMU at {args.imu_hz:g} Hz"
        if args.without:
            what += ", without " + ", ".join(args.without)
    print(
        f"{what}: {per_s / 1e6:.2f} M instructions per vehicle-second "
        f"({counts[0]:,} at {short:g} s, {counts[1]:,} at {long_:g} s); {outs[1][0].strip()}"
    )
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
