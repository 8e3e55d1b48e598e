"""A client on the bus that stops reading holds nobody (real processes over loopback).

The service routes the sensor data it receives to every other matching subscriber and publishes its
outputs to them; with blocking congestion control each put waits for room in every matching link's
queue, so one subscriber that stopped reading once held every other client and the service's own
intake (measured: 20 fleet vehicles at 1x, no Solution reached another client for 15 s, and 1,760
of 12,020 never did). The service's session now sends every put over a network link with DROP
(``zenoh_io.egress_drop_rules``): the stuck client loses its own samples, nobody else's.
"""

import signal
import sys
import threading
import time

import pytest

from fednav.simulators.processes import Proc, free_port, start_service
from tests.plain_zenoh import client

VEHICLES, DURATION_S, SPEED = 10, 30.0, 2.0


@pytest.mark.integration
def test_a_subscriber_that_never_returns_holds_no_other_client(tmp_path):
    cfg = tmp_path / "service.toml"
    cfg.write_text('[service]\nvehicles = ["*"]\n')
    port = free_port()
    svc = start_service(port, config=cfg, table="service")
    sessions = []
    sim = None
    release = threading.Event()
    try:
        good = client(port)
        sessions.append(good)
        arrivals: list[float] = []
        good.declare_subscriber("fednav/*/nav/*/solution", lambda s: arrivals.append(time.monotonic()))
        stuck = client(port)
        sessions.append(stuck)
        held = []
        # a callback that does not return until the test ends: this client reads nothing more,
        # its socket and its link's queue in the service fill with what is routed to it
        stuck.declare_subscriber("fednav/**", lambda s: held.append(1) or release.wait(600))
        time.sleep(0.5)
        sim = Proc(
            [sys.executable, "-m", "fednav.simulators", "fleet", "--vehicles", str(VEHICLES)]
            + ["--duration", str(DURATION_S), "--speed", str(SPEED), "--connect", f"tcp/127.0.0.1:{port}"],
            "fednav-sim fleet",
        )
        assert sim.wait(timeout=300) == 0, sim.output()
        time.sleep(2.0)
        assert held, "the stuck client never got a sample: the test shows nothing"
        gaps = [b - a for a, b in zip(arrivals[:-1], arrivals[1:], strict=True)]
        # ten vehicles' Solutions at 10 Hz x 2: one every 5 ms; a held service stops them for
        # Zenoh's wait_before_close (5 s) or more
        assert max(gaps) < 2.0, f"Solutions stopped for {max(gaps):.1f} s"
        expected = VEHICLES * int(DURATION_S * 10)
        assert len(arrivals) >= 0.98 * expected, (len(arrivals), expected)
    finally:
        release.set()
        if sim is not None and sim.p.poll() is None:
            sim.signal(signal.SIGTERM)
            sim.wait(timeout=30)
        svc.signal(signal.SIGTERM)
        rc = svc.wait(timeout=60)
        for s in sessions:
            try:
                s.close()
            except Exception:
                pass
    assert rc == 0, svc.output()
