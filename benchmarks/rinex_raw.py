"""RINEX -> GnssRaw conversion and the GNSS-only tightly coupled run on the Wuhan 2015 data.

Prints: conversion throughput (epochs/s and observations/s of ``iter_gnss_raw``, reading included)
and the real-time factor of the pipeline in GNSS-only mode (10 Hz stationary IMU, full MHSS with
sub-sub filters and exclusion; docs/real_rinex.md) over the 2285 s of data.

Usage: OPENBLAS_NUM_THREADS=1 .venv/bin/python benchmarks/rinex_raw.py [DATA_DIR] [--json]
"""

from __future__ import annotations

import argparse
import json
import os
import sys
import time
from pathlib import Path

os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")

from fednav.simulators.gnss.rinex_raw import ConversionStats, iter_gnss_raw  # noqa: E402
from fednav.simulators.rinex_eval import find_files, run_ours, spp  # noqa: E402

DEFAULT = Path(__file__).resolve().parents[2] / "shared" / "data" / "real" / "psins_wuhan_2015"


def main() -> int:
    ap = argparse.ArgumentParser()
    ap.add_argument("folder", nargs="?", default=str(DEFAULT))
    ap.add_argument("--json", action="store_true")
    a = ap.parse_args()
    folder = Path(a.folder)
    if not folder.exists():
        print(f"skipped: {folder} absent")
        return 0
    obs, nav = find_files(folder)
    stats = ConversionStats()
    t0 = time.perf_counter()
    msgs = [m for _, m in iter_gnss_raw(obs, nav, stats=stats)]
    conv_s = time.perf_counter() - t0
    x0 = spp(msgs[:1]).pos_ecef_m[0]
    t0 = time.perf_counter()
    run_ours(msgs, x0)
    run_s = time.perf_counter() - t0
    span = msgs[-1].t - msgs[0].t
    r = {
        "epochs": stats.epochs,
        "observations": stats.observations,
        "convert_epochs_per_s": stats.epochs / conv_s,
        "convert_observations_per_s": stats.observations / conv_s,
        "pipeline_real_time_factor": span / run_s,
        "data_span_s": span,
    }
    if a.json:
        print(json.dumps(r, indent=2))
    else:
        print(
            f"conversion: {r['convert_epochs_per_s']:.0f} epochs/s, "
            f"{r['convert_observations_per_s']:.0f} obs/s"
            f" ({stats.epochs} epochs, {stats.observations} observations)"
        )
        print(
            f"GNSS-only tightly coupled + MHSS: {r['pipeline_real_time_factor']:.0f}x real time "
            f"over {span:.0f} s"
        )
    return 0


if __name__ == "__main__":
    sys.exit(main())
