"""``fednav-record SCENARIO -o FILE.rrd``: record a scenario in-process, faster than real time.

The same engine, pipelines, output sink and Rerun sink as ``fednav-service`` (no Zenoh): the
simulator's message stream goes straight into :class:`service.engine.VehicleEngine` and every
output into :class:`service.transport.rerun_sink.RerunSink` with the blueprint the service embeds.
Used by ``make screenshots`` and ``benchmarks/recording_size.py``.

Chunking as the live service: the sink's flush clock is the *sensor* time of the stream, so rows
are sent every ``rrd_flush_interval_s`` of scenario time, exactly as a service fed in real time
sends them every ``rrd_flush_interval_s`` of wall time (same chunk count, same file size).

Health rows are those of the in-process run: message counters from the engine, latency = the
processing time of each message in this process (no queue, no network), queue depth 0.
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import numpy as np

from fednav.service import keys
from fednav.service.app import OutputSink
from fednav.service.blas import one_blas_thread
from fednav.service.config import ServiceConfig, recording_kinds
from fednav.service.transport.rerun_sink import RerunSink
from fednav.service.vehicle import VehicleLoop
from fednav.simulators.evaluate import service_config
from fednav.simulators.scenario import Scenario, duration_arg, load_scenario, load_scenario_cli


class _NoPublish:
    """Publishers stand-in: the recorder records, it does not publish."""

    def publish(self, key: str, msg) -> None:
        return None


def record(
    scenario: Scenario | str,
    out: str | Path,
    *,
    seed: int | None = None,
    vehicle: str = "v1",
    cfg: ServiceConfig | None = None,
    optimize: bool | None = None,
    duration_s: float | None = None,
) -> dict:
    """Record ``scenario`` to ``out``; returns figures (messages, wall time, file size).

    ``cfg``: the service configuration (default: the scenario's ``[service]`` table), whose
    ``rrd_*`` fields set the sink (flush interval, decimation, optimize on close). ``optimize``
    overrides ``cfg.rrd_optimize``. ``duration_s``: stop after this much scenario time.
    """
    from fednav.dashboards.blueprints import blueprint_factory

    sc = load_scenario(scenario) if isinstance(scenario, str) else scenario
    cfg = cfg or service_config(sc)
    out = Path(out)
    clock = [0.0]
    sink = RerunSink(
        out,
        blueprint=blueprint_factory(recording_kinds(cfg.pipelines)),
        recording_name=f"{sc.name} (fednav-record)",
        flush_interval_s=cfg.rrd_flush_interval_s,
        clock=lambda: clock[0],
        background_flush=False,
        decimation=cfg.rrd_decimation,
        slow_flush_interval_s=cfg.rrd_slow_flush_interval_s,
        optimize_on_close=cfg.rrd_optimize if optimize is None else optimize,
    )
    outputs = OutputSink(cfg.prefix, _NoPublish(), sink, vehicle_interval_s=cfg.rrd_vehicle_interval_s)
    # the service's per-vehicle loop: the same judging, counting and raw-fix recording
    loop = VehicleLoop(vehicle, cfg, outputs, on_fix=outputs.log_fix)
    if sc.wing is not None:  # transfer alignment (seed 002): wing nodes too
        from fednav.simulators.wing import WingSimulation

        sim = WingSimulation(sc, seed=seed, vehicle=vehicle, prefix=cfg.prefix)
    else:
        from fednav.simulators.stream import Simulation

        sim = Simulation(sc, seed=seed, vehicle=vehicle, prefix=cfg.prefix)
    wall0 = time.perf_counter()
    t_first: float | None = None
    next_health = -np.inf
    engine = loop.engine
    for key, msg in sim:
        pk = keys.parse_input(key, cfg.prefix)
        t = getattr(msg, "t", None)
        if t is not None:
            clock[0] = float(t)
            t_first = float(t) if t_first is None else t_first
            if duration_s is not None and t - t_first > duration_s:
                break
        loop.process(pk.kind, pk.sensor_id, msg)
        if engine.last_t is not None and engine.last_t >= next_health:
            next_health = engine.last_t + cfg.output.health_period_s
            outputs.log_health(vehicle, loop.health())
    sink.close()
    t_span = 0.0 if t_first is None else clock[0] - t_first
    return {
        "scenario": sc.name,
        "rrd": str(out),
        "messages": loop.received,
        "scenario_s": t_span,
        "wall_s": time.perf_counter() - wall0,
        "bytes": out.stat().st_size if out.is_file() else 0,
    }


def main(argv: list[str] | None = None) -> int:
    one_blas_thread()
    ap = argparse.ArgumentParser(prog="fednav-record", description=__doc__.split("\n\n")[0].replace("``", ""))
    ap.add_argument("scenario", help="a scenario file or the name of a shipped one (e.g. seed000_faults)")
    ap.add_argument("-o", "--out", type=Path, required=True, help="the .rrd to write")
    ap.add_argument("--seed", type=int, help="noise seed (default: the scenario's)")
    ap.add_argument("--duration", type=duration_arg, help="stop after this many seconds of scenario time")
    ap.add_argument(
        "--optimize", action=argparse.BooleanOptionalAction, default=None, help="compact the file at the end"
    )
    args = ap.parse_args(argv)
    scenario = load_scenario_cli(args.scenario, "fednav-record")
    if scenario is None:
        return 2
    r = record(scenario, args.out, seed=args.seed, optimize=args.optimize, duration_s=args.duration)
    print(
        f"{r['rrd']}: {r['bytes'] / 1e6:.1f} MB, {r['scenario_s']:.0f} s of {r['scenario']}, "
        f"{r['messages']} messages in {r['wall_s']:.1f} s",
        file=sys.stderr,
    )
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
