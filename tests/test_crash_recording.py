"""kill -9 of fednav-service loses at most about the last second of the recording (issue 9).

Real processes over loopback Zenoh: fednav-service records the demo scenario published in real time
(speed 1, so sensor seconds are wall seconds); a plain Zenoh client notes every solution the service
published; the service is killed with SIGKILL mid-run. The .rrd, left without its footer, is read
back with Rerun's own reader and compared with what was published; then recovered with
``rerun rrd merge --continue-on-error`` into a file that ``rerun rrd verify`` accepts.
"""

from __future__ import annotations

import json
import subprocess
import sys
import threading
import time
import warnings
from pathlib import Path

import pytest
import zenoh

from fednav.dashboards.inspect import InspectError, inspect_rrd, read_series
from fednav.service.messages import Truth
from fednav.service.transport.rerun_sink import RerunSink
from fednav.simulators.processes import free_port, start_service, start_sim

from .plain_zenoh import client as zenoh_client

pytestmark = pytest.mark.integration
ROOT = Path(__file__).resolve().parents[1]
DEMO = ROOT / "simulators" / "scenarios" / "demo_aircraft.toml"
RERUN = Path(sys.executable).with_name("rerun")

FLUSH_INTERVAL_S = 1.0  # RerunSink's default
#: what kill -9 may lose, in seconds of a real-time run: the flush interval, one solution period
#: (0.1 s) and scheduling slack on a loaded 2-core machine
MAX_LOSS_S = FLUSH_INTERVAL_S + 0.5


def _truth(t: float) -> Truth:
    return Truth(t=t, lat_deg=40.0, lon_deg=118.0, height_m=100.0, vel_enu_mps=(1, 2, 0), rpy_deg=(0, 0, 45))


def test_rows_reach_the_file_without_further_logging(tmp_path):
    """The sink's background flusher sends rows older than the flush interval even when no logging
    call follows (input stopped): the open, footer-less file holds them."""
    rrd = tmp_path / "open.rrd"
    sink = RerunSink(rrd, flush_interval_s=0.2)
    try:
        for k in range(5):
            sink.log_truth("v1", _truth(1000.0 + 0.1 * k))
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            deadline = time.monotonic() + 10.0
            n = 0
            while time.monotonic() < deadline:
                time.sleep(0.2)
                try:
                    n = len(read_series(rrd)[1].get("/v1/truth/lat_deg", []))
                except InspectError:
                    n = 0
                if n == 5:
                    break
        assert n == 5
        assert not sink.closed
    finally:
        sink.close()
    # a sink without the flusher keeps them in memory until the next call (what kill -9 would lose)
    rrd2 = tmp_path / "held.rrd"
    held = RerunSink(rrd2, flush_interval_s=0.2, background_flush=False)
    try:
        for k in range(5):
            held.log_truth("v1", _truth(1000.0 + 0.1 * k))
        time.sleep(1.0)
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            try:
                n = len(read_series(rrd2)[1].get("/v1/truth/lat_deg", []))
            except InspectError:
                n = 0
        assert n == 0
    finally:
        held.close()


def test_kill_9_loses_at_most_about_the_last_second(tmp_path):
    rrd = tmp_path / "crash.rrd"
    port = free_port()
    svc = start_service(port, config=DEMO, table="service", rrd=rrd)
    session = zenoh_client(port)
    published: list[tuple[float, float]] = []  # (wall time received, solution t)
    lock = threading.Lock()

    def cb(sample: zenoh.Sample) -> None:
        with lock:
            published.append((time.monotonic(), json.loads(sample.payload.to_bytes())["t"]))

    sub = session.declare_subscriber("fednav/v1/nav/lc/solution", cb)
    sim = start_sim(port, DEMO, speed=1.0, seed=5)
    try:
        deadline = time.monotonic() + 60.0
        while time.monotonic() < deadline:
            with lock:
                if len(published) >= 120:  # 12 s of solutions at 10 Hz
                    break
            time.sleep(0.1)
        t_kill = time.monotonic()
        svc.p.kill()  # SIGKILL: no handler, no close(), no footer
        svc.p.wait(timeout=10)
    finally:
        sim.kill()
        svc.kill()
        sub.undeclare()
        session.close()
    with lock:
        before = [t for w, t in published if w <= t_kill]
    assert len(before) >= 120, "the service did not publish solutions"

    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # RrdReader warns about the missing footer and scans the file
        _, data = read_series(rrd)
    recorded = data["/v1/lc/solution/lat_deg"].t_ns / 1e9
    loss_s = before[-1] - recorded[-1]
    n_lost = sum(1 for t in before if t > recorded[-1])
    print(
        f"kill -9 after {len(before)} published solutions: {len(recorded)} recorded, "
        f"last recorded {loss_s:.2f} s before the last published ({n_lost} solutions lost)"
    )
    assert 0.0 <= loss_s <= MAX_LOSS_S
    # everything recorded is what was published (no gap in the middle)
    assert set(round(t, 3) for t in recorded) <= set(round(t, 3) for t in before)
    assert len(recorded) == len(before) - n_lost

    # the file as left: no footer (rerun rrd verify rejects it), data verifies without the footer check
    res = subprocess.run([str(RERUN), "rrd", "verify", str(rrd)], capture_output=True, text=True, timeout=120)
    assert res.returncode != 0 and "footer" in (res.stderr + res.stdout).lower()
    res = subprocess.run(
        [str(RERUN), "rrd", "verify", "--check-footers", "false", str(rrd)],
        capture_output=True,
        text=True,
        timeout=120,
    )
    assert res.returncode == 0, res.stderr
    # recovery documented in the README
    fixed = tmp_path / "recovered.rrd"
    res = subprocess.run(
        [str(RERUN), "rrd", "merge", "--continue-on-error", str(rrd), "-o", str(fixed)],
        capture_output=True,
        text=True,
        timeout=120,
    )
    assert res.returncode == 0, res.stderr
    res = subprocess.run(
        [str(RERUN), "rrd", "verify", str(fixed)], capture_output=True, text=True, timeout=120
    )
    assert res.returncode == 0, res.stderr
    summary = inspect_rrd(fixed)
    assert summary["pipelines"]["lc"]["solutions"] == len(recorded)
