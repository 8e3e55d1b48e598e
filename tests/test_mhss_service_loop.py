"""``benchmarks/mhss_bank.py``'s service-loop figure compares like with like: the MHSS pipeline
driven directly and the same data through the service's per-vehicle loop (ImuBatch and JSON
GnssRaw payloads, the engine, every output serialised) run the same filter: their final
positions agree to well under a millimetre, nothing is refused, and every epoch's Solution and
Integrity come out. (The figures themselves are the benchmark's, not asserted here.)"""

from __future__ import annotations

import sys
from pathlib import Path


def test_the_service_loop_runs_the_benchmarks_filter_on_the_same_data():
    sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "benchmarks"))
    import mhss_bank as mb

    r = mb.bench_service_loop(8.0, skip_epochs=5)
    assert r["refused"] == {}, r
    assert r["position_difference_m"] < 1e-6, r
    assert r["outputs"] >= 2 * 80, r  # a Solution and an Integrity per 10 Hz epoch (80 epochs, 8 s)
    assert r["epochs"] == 80 - 5 and r["service_loop_ms_per_epoch"] > 0.0, r
