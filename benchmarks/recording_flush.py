"""The CPU of one flush of a fleet's recording: the rows a decimated fleet buffers in one flush
interval (per vehicle: 12 scalar entities, a geo point and a status, one row each, as a loosely
coupled vehicle recorded at ``rrd_vehicle_interval_s`` = 1 s with ``rrd_flush_interval_s`` = 1 s),
sent by ``RerunSink._send`` to a file. Printed: ms of CPU per flush (the first flush, which
creates the entities, apart) and per entity.

Usage: .venv/bin/python benchmarks/recording_flush.py [--vehicles 40] [--flushes 8]
"""

from __future__ import annotations

import argparse
import statistics
import tempfile
import time
from pathlib import Path

T0_NS = 1_400_000_000_000_000_000


def main() -> int:
    from fednav.service.transport.rerun_sink import RerunSink, _Series

    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--vehicles", type=int, default=40)
    ap.add_argument("--flushes", type=int, default=8)
    args = ap.parse_args()
    with tempfile.TemporaryDirectory(prefix="recording_flush_") as tmp:
        sink = RerunSink(str(Path(tmp) / "flush.rrd"), background_flush=False)
        sink._t0_ns = T0_NS  # as set by the first logged row

        def rows(k: int) -> dict:
            series = {}
            for v in range(args.vehicles):
                t = T0_NS + k * 1_000_000_000 + v * 1_000_000  # each vehicle its own phase
                for e in range(12):
                    series[f"/veh{v:03d}/lc/solution/s{e}"] = _Series("scalar", [(t, float(e + k))])
                series[f"/veh{v:03d}/lc/solution/position"] = _Series("geo", [(t, (40.0, 116.0 + k * 1e-4))])
                series[f"/veh{v:03d}/lc/status"] = _Series("state", [(t, "aided")])
            return series

        cpu = []
        for k in range(args.flushes + 1):
            s = rows(k)
            c0 = time.thread_time()
            sink._send(s)
            cpu.append(1e3 * (time.thread_time() - c0))
        sink.close()
    entities = 14 * args.vehicles
    rest = cpu[1:]
    print(
        f"{args.vehicles} vehicles, {entities} entities of one row: first flush {cpu[0]:.0f} ms CPU, "
        f"then median {statistics.median(rest):.1f} ms (min {min(rest):.1f}), "
        f"{1e3 * statistics.median(rest) / entities:.0f} us per entity"
    )
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
