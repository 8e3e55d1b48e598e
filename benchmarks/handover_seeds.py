"""A fleet handover in a turn and during a receiver fault, over seeds (in-process: the old owner's
HandoverState through JSON to a second VehicleWorker, 0.7 s later; the demo aircraft, loosely
coupled pipeline; the scenario of tests/test_handover_motion.py).

Per seed: the first Solution's velocity error after the takeover, the worst horizontal error over
the 8 s after it and the restarts of the pipeline, for
- turn: handed over 12 s into the 3 deg/s turn, with the state's motion / without it (``turn0``);
- step: handed over 4 s into the receiver's 60 m step (40-55 s), with the screening flag and the
  stream records / without the flag (``step_nos``) / without the records (``step_norec``).

Usage: .venv/bin/python benchmarks/handover_seeds.py [--seeds 1-8]
"""

from __future__ import annotations

import argparse
import logging
import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

import tests.test_handover_motion as probe  # noqa: E402

CASES = {
    "turn": {"with_motion": True},
    "turn0": {"with_motion": False},
    "step": {"with_motion": True, "at_s": 44.0},
    "step_nos": {"with_motion": True, "at_s": 44.0, "update": {"screening": False}},
    "step_norec": {"with_motion": True, "at_s": 44.0, "update": {"stream_records": {}}},
}


def main() -> int:
    ap = argparse.ArgumentParser()
    ap.add_argument("--seeds", default="1-8", help="first-last (inclusive)")
    args = ap.parse_args()
    first, last = (int(x) for x in args.seeds.split("-"))
    logging.disable(logging.WARNING)
    worst: dict[str, list[float]] = {c: [] for c in CASES}
    for seed in range(first, last + 1):
        probe.SEED = seed
        cells = []
        for name, kw in CASES.items():
            rows, notes, _ = probe._hand_over_in_the_turn(**kw)
            h = max(e for _, e, _ in rows)
            worst[name].append(h)
            cells.append(
                f"{name}: dv0 {rows[0][2]:.2f} m/s, max h {h:.1f} m, resets {notes.get('reset:lc', 0)}"
            )
        print(f"seed {seed}: " + " | ".join(cells), flush=True)
    for name, hs in worst.items():
        print(f"{name}: worst horizontal error over seeds {min(hs):.1f}-{max(hs):.1f} m")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
