"""Recording size per minute of scenario, before and after decimation / slow flushes / compaction.

Records a scenario in-process with ``fednav-record`` (the service's engine, output sink and Rerun
sink; the sink's flush clock is the sensor time, so chunking is that of a service fed in real
time) under three settings and prints the file size, MB per minute of scenario and the entity
count (every panel intact: the decimated files must hold the same entities as the full one):

* ``every row``: no decimation, every stream sent each ``rrd_flush_interval_s`` (1 s), not
  compacted (the behaviour before ``rrd_decimation`` / ``rrd_slow_flush_interval_s``);
* ``decimated``: the scenario's ``rrd_decimation`` and ``rrd_slow_flush_interval_s``, not compacted;
* ``decimated + optimize``: the same, compacted at close (``rerun rrd optimize``, ``rrd_optimize``).

    .venv/bin/python benchmarks/recording_size.py                       # seed000_faults, 800 s
    .venv/bin/python benchmarks/recording_size.py demo_product --duration 60
"""

from __future__ import annotations

import argparse
import tempfile
import time
from pathlib import Path

from fednav.dashboards.record import record
from fednav.simulators.evaluate import service_config
from fednav.simulators.scenario import load_scenario


def entities(path: Path) -> set[str]:
    from rerun.chunk import RrdReader

    r = RrdReader(path)
    return {ch.entity_path for ch in r.stream(store=r.recordings()[0])}


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("scenario", nargs="?", default="seed000_faults")
    ap.add_argument("--duration", type=float, help="record only this many seconds of scenario time")
    ap.add_argument("--keep", type=Path, help="keep the recordings in this folder")
    ap.add_argument("--skip-full", action="store_true", help="skip the slow 'every row' recording")
    args = ap.parse_args(argv)
    sc = load_scenario(args.scenario)
    cfg = service_config(sc)
    variants = []
    if not args.skip_full:
        full = cfg.model_copy(
            update={
                "rrd_decimation": {k: 0.0 for k in cfg.rrd_decimation},
                "rrd_slow_flush_interval_s": cfg.rrd_flush_interval_s,
                "rrd_optimize": False,
            }
        )
        variants.append(("every row, 1 s flushes", full))
    variants.append(("decimated + slow flushes", cfg.model_copy(update={"rrd_optimize": False})))
    variants.append(("decimated + optimize", cfg.model_copy(update={"rrd_optimize": True})))
    out_dir = args.keep or Path(tempfile.mkdtemp(prefix="fednav-rrd-size-"))
    out_dir.mkdir(parents=True, exist_ok=True)
    print(f"scenario {sc.name}: {len(cfg.pipelines)} pipelines, flush {cfg.rrd_flush_interval_s} s")
    print(f"decimation (s): {cfg.rrd_decimation}, slow flush {cfg.rrd_slow_flush_interval_s} s")
    print(f"{'setting':<28} {'MB':>9} {'MB/min':>8} {'entities':>9} {'record s':>9}")
    ref: set[str] | None = None
    for i, (label, c) in enumerate(variants):
        path = out_dir / f"{sc.name}-{i}.rrd"
        w = time.perf_counter()
        r = record(sc, path, cfg=c, duration_s=args.duration)
        wall = time.perf_counter() - w
        ents = entities(path)
        ref = ents if ref is None else ref
        missing = sorted(ref - ents)
        minutes = max(r["scenario_s"], 1e-9) / 60.0
        print(
            f"{label:<28} {r['bytes'] / 1e6:9.1f} {r['bytes'] / 1e6 / minutes:8.2f} "
            f"{len(ents):9d} {wall:9.1f}" + (f"   MISSING {len(missing)}: {missing[:5]}" if missing else ""),
            flush=True,
        )
        if not args.keep and i < len(variants) - 1:
            path.unlink(missing_ok=True)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
