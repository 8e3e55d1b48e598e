"""The CPU cost of one fleet vehicle in-process: what a service's pool worker spends per vehicle.

The same messages ``fednav-sim fleet`` publishes for one vehicle (the demo aircraft at 200 Hz IMU
and 10 Hz fixes, ImuBatch payloads of ``--imu-batch`` samples or JSON per sample) go through the
service's own per-vehicle loop (``VehicleLoop.process``: decoding, validation, the engine, one
loosely coupled pipeline, the output sink with every message serialised) without Zenoh and without
threads. Printed: CPU per vehicle-second (process time / scenario time; ``benchmarks/fleet_load.py``
gives the same figure for a whole service, Zenoh and threads included, so the difference is the
transport's and the scheduling's share) and a digest of every serialised output, so that a change
of the hot path can show its outputs are byte-identical.

With ``--record``, the output sink also records to a Rerun file as the service does (its default
recording options, ``rrd_vehicle_interval_s`` 1 s as a fleet is advised to record), its flushes due
by scenario time (in-process the messages come faster than real time; a wall clock would batch many
seconds into one flush) and sent in the loop's thread: the CPU is then the process's
(``time.process_time``: Rerun's own threads included), and the figure with recording minus the one
without is what recording a vehicle costs.

With ``--pace-ms``, the thread sleeps after every ``--burst`` messages, as a service's worker idles
between arrivals: its own CPU for the same work (``time.thread_time``) shows what idling costs.

Usage: .venv/bin/python benchmarks/vehicle_cost.py [--duration 120] [--imu-batch 10] [--repeat 3]
           [--vehicles 1] [--pace-ms 0 --burst 1] [--record] [--profile]
"""

from __future__ import annotations

import argparse
import cProfile
import hashlib
import pstats
import tempfile
import time
from pathlib import Path


class _Publishers:
    """The service's publishers without Zenoh: every message serialised as it would be sent."""

    def __init__(self) -> None:
        self.digest = hashlib.sha256()
        self.n = 0

    def publish(self, key: str, msg) -> None:
        self.digest.update(key.encode())
        self.digest.update(msg.to_json())
        self.n += 1


def vehicle_inputs(
    duration_s: float, imu_batch: int, imu_hz: float = 200.0, fix_hz: float = 10.0
) -> list[tuple[float, str, str, bytes]]:
    """(sensor time, kind, sensor id, payload) of every message ``fednav-sim fleet`` publishes for
    one vehicle over ``duration_s``: the demo aircraft, 200 Hz IMU (ImuBatches of ``imu_batch``
    samples, or JSON per sample when 1), 10 Hz fixes (other rates: ``imu_hz``, ``fix_hz``)."""
    from fednav.service import keys
    from fednav.simulators.fleet import fleet_scenario, variant_items

    data = fleet_scenario("demo_aircraft", imu_hz, fix_hz, duration_s)
    items, _ = variant_items(data, 1, 0.0, imu_batch, False, keys.DEFAULT_PREFIX)
    inputs = []
    for it in items:
        parsed = keys.parse_input(f"{keys.DEFAULT_PREFIX}/veh000/{it.suffix}")
        inputs.append((it.t, parsed.kind, parsed.sensor_id, it.payload))
    return inputs


def run(
    duration_s: float,
    imu_batch: int,
    profile: bool = False,
    vehicles: int = 1,
    pace_s: float = 0.0,
    burst: int = 1,
    record: bool = False,
) -> dict:
    from fednav.service import keys
    from fednav.service.app import OutputSink
    from fednav.service.config import ServiceConfig
    from fednav.service.vehicle import VehicleLoop, tune_gc

    inputs = vehicle_inputs(duration_s, imu_batch)
    config = ServiceConfig.model_validate(
        {"vehicles": ["*"], "pipelines": [{"name": "lc", "kind": "loosely_coupled"}]}
    )
    tune_gc()  # as the service after its start
    pubs = _Publishers()
    now = [inputs[0][0] if inputs else 0.0]  # the scenario time of the message being processed
    rr = tmp = None
    if record:
        from fednav.service.transport.rerun_sink import RerunSink

        tmp = tempfile.TemporaryDirectory(prefix="vehicle_cost_")
        c = config
        rr = RerunSink(
            str(Path(tmp.name) / "cost.rrd"),
            flush_interval_s=c.rrd_flush_interval_s,
            decimation=c.rrd_decimation,
            slow_flush_interval_s=c.rrd_slow_flush_interval_s,
            clock=lambda: now[0],
            background_flush=False,
        )
    sink = OutputSink(keys.DEFAULT_PREFIX, pubs, rr, vehicle_interval_s=1.0 if record else 0.0)
    on_fix = sink.log_fix if rr is not None else None
    loops = [VehicleLoop(f"veh{i:03d}", config, sink, on_fix=on_fix) for i in range(vehicles)]
    # recording: the process's CPU (the background flusher and Rerun's threads are part of the cost)
    clock = time.process_time if record else time.thread_time
    prof = cProfile.Profile() if profile else None
    if prof is not None:
        prof.enable()
    cpu = 0.0
    c0 = clock()
    n = 0
    for t, kind, sensor_id, payload in inputs:  # vehicles interleaved message by message, as in a fleet
        now[0] = t
        for loop in loops:
            loop.process(kind, sensor_id, payload)
            n += 1
            if pace_s > 0.0 and n % burst == 0:  # idle between bursts, as a paced service is
                cpu += clock() - c0
                time.sleep(pace_s)
                c0 = clock()
    if rr is not None:
        rr.close()  # what is still buffered is sent and written: part of the cost
    cpu += clock() - c0
    rrd_bytes = 0
    if tmp is not None:
        rrd_bytes = sum(f.stat().st_size for f in Path(tmp.name).iterdir())
        tmp.cleanup()
    loop = loops[0]
    if prof is not None:
        prof.disable()
        pstats.Stats(prof).sort_stats("tottime").print_stats(30)
    return {
        "messages": len(inputs),
        "accepted_samples": loop.accepted,
        "refused": dict(loop.counters),
        "outputs": pubs.n,
        "cpu_ms_per_vehicle_s": 1e3 * cpu / duration_s / vehicles,
        "digest": pubs.digest.hexdigest()[:16],
        "rrd_kb_per_vehicle_min": rrd_bytes / 1e3 / vehicles / (duration_s / 60.0),
    }


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--duration", type=float, default=120.0, help="scenario seconds (default 120)")
    ap.add_argument("--imu-batch", type=int, default=10, help="samples per ImuBatch, 1 = JSON (default 10)")
    ap.add_argument("--repeat", type=int, default=3, help="runs; the minimum CPU is printed (default 3)")
    ap.add_argument(
        "--vehicles", type=int, default=1, help="vehicles served side by side, interleaved (default 1)"
    )
    ap.add_argument(
        "--pace-ms",
        type=float,
        default=0.0,
        help="sleep this long after every --burst messages (the thread's own CPU is still what is "
        "counted): the cost of the same work done by a thread that idles between messages",
    )
    ap.add_argument("--burst", type=int, default=1, help="messages between two --pace-ms sleeps")
    ap.add_argument(
        "--record", action="store_true", help="also record to a Rerun file as a fleet service does"
    )
    ap.add_argument("--profile", action="store_true", help="one run under cProfile, its top functions")
    args = ap.parse_args()
    if args.profile:
        run(args.duration, args.imu_batch, profile=True, vehicles=args.vehicles, record=args.record)
        return 0
    run(
        min(args.duration, 10.0), args.imu_batch, record=args.record
    )  # warm-up: lazy imports, schema builds, caches
    pace = {"pace_s": args.pace_ms * 1e-3, "burst": args.burst}
    runs = [
        run(args.duration, args.imu_batch, vehicles=args.vehicles, record=args.record, **pace)
        for _ in range(max(1, args.repeat))
    ]
    best = min(r["cpu_ms_per_vehicle_s"] for r in runs)
    r = runs[0]
    digests = {x["digest"] for x in runs}
    inputs = f"ImuBatch of {args.imu_batch}" if args.imu_batch > 1 else "JSON"
    if args.record:
        inputs += f", recorded ({r['rrd_kb_per_vehicle_min']:.0f} kB per vehicle-minute)"
    if args.pace_ms > 0.0:
        inputs += f", idle {args.pace_ms:g} ms after every {args.burst} message(s)"
    print(
        f"{args.vehicles} vehicle(s), {args.duration:.0f} s, {inputs}: "
        f"{r['messages']} messages, {r['accepted_samples']} samples accepted, {r['outputs']} outputs, "
        f"refused {r['refused'] or 'none'}"
    )
    print(
        f"CPU per vehicle-second: {best:.2f} ms (min of {len(runs)}; all: "
        + ", ".join(f"{x['cpu_ms_per_vehicle_s']:.2f}" for x in runs)
        + f"); output digest {'/'.join(sorted(digests))}"
    )
    return 0 if len(digests) == 1 else 1


if __name__ == "__main__":
    raise SystemExit(main())
