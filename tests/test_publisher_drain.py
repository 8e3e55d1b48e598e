"""The publisher's end of stream: nothing still queued is lost when its session closes.

A receiver slower than a ``--speed 0`` publisher leaves the stream's tail in Zenoh's transmission
queue and the sockets when the publisher is done; ``publish_stream`` waits for the service's
status queryable to see a query sent behind that tail (``publisher.drain``) before it closes.
The receiver here is a plain Zenoh peer with a small channel read slowly, and a status queryable.
"""

import subprocess
import sys
import threading
import time
from pathlib import Path

import pytest
import zenoh

from fednav.service.config import ZenohConfig
from fednav.service.messages import ImuSample
from fednav.service.transport.zenoh_io import make_config
from fednav.simulators.processes import free_port, start_service
from fednav.simulators.publisher import publish_stream, status_keys

N = 3000
DEMO = Path(__file__).resolve().parents[1] / "simulators" / "scenarios" / "demo_aircraft.toml"


def imu_stream(vehicle: str = "v1", n: int = N):
    for k in range(n):
        yield (
            f"fednav/{vehicle}/sensors/imu/imu0",
            ImuSample(
                t=1000.0 + 0.005 * k, dt_s=0.005, dtheta_rad=(0.0, 0.0, 0.0), dvel_mps=(0.0, 0.0, 0.049)
            ),
        )


class SlowReceiver:
    """A peer listening on ``port``: its subscriber's channel holds 16 samples and is read at
    ~0.3 ms a sample (far slower than the publisher), its status queryable answers at once."""

    def __init__(
        self,
        port: int,
        answer: bool = True,
        serve_status: bool = True,
        pause_s: float = 0.0,
        read_s: float = 0.0003,
        close_after: int | None = None,
        key_expr: str = "fednav/v1/sensors/**",
    ):
        self.pause_s, self.read_s, self.close_after = pause_s, read_s, close_after
        self.session = zenoh.open(make_config(ZenohConfig(mode="peer"), listen=[f"tcp/127.0.0.1:{port}"]))
        self.sub = self.session.declare_subscriber(key_expr, zenoh.handlers.FifoChannel(16))
        self.queries = 0
        self.held: list[zenoh.Query] = []  # a stuck service: queries kept, never answered
        if serve_status:
            self.qbl = self.session.declare_queryable("fednav/v1/service/status", self._status)
        self._answer = answer
        self.got = 0
        self._stop = threading.Event()
        self._t = threading.Thread(target=self._read, daemon=True)
        self._t.start()

    def _status(self, query: zenoh.Query) -> None:
        self.queries += 1
        if self._answer:
            query.reply(query.key_expr, b"{}")
        else:  # (a query dropped unanswered ends at once, without a reply)
            self.held.append(query)

    def _read(self) -> None:
        # ``pause_s``: nothing read at first (a service busy elsewhere), the channel and the
        # sockets filling; ``close_after``: the session closed after that many (a service stopped)
        self._stop.wait(self.pause_s)
        while not self._stop.is_set():
            s = self.sub.handler.try_recv()
            if s is None:
                time.sleep(0.001)
                continue
            self.got += 1
            if self.close_after is not None and self.got >= self.close_after:
                try:
                    self.session.close()
                except zenoh.ZError:  # Zenoh's close timed out on a loaded CI machine (once):
                    pass  # whether the publisher saw it go is what the tests assert
                return
            if self.read_s:
                time.sleep(self.read_s)

    def count_when_quiet(self, quiet_s: float = 1.0, timeout_s: float = 60.0) -> int:
        last, since = -1, time.monotonic()
        deadline = time.monotonic() + timeout_s
        while time.monotonic() < deadline:
            if self.got != last:
                last, since = self.got, time.monotonic()
            elif time.monotonic() - since > quiet_s:
                break
            time.sleep(0.05)
        return self.got

    def close(self) -> None:
        self._stop.set()
        self._t.join(timeout=5)
        self.held.clear()
        self.session.close()


def publish_to(rx_options: dict, n: int = N, **options) -> tuple[dict, float, SlowReceiver]:
    """Publish ``n`` samples at full speed (or ``speed``) to a SlowReceiver(**rx_options); the
    publisher's result, how long it took, and how many the receiver had when it returned."""
    port = free_port()
    rx = SlowReceiver(port, **rx_options)
    options.setdefault("speed", 0.0)
    try:
        t0 = time.monotonic()
        out = publish_stream(imu_stream(n=n), connect=[f"tcp/127.0.0.1:{port}"], imu_batch=1, **options)
        took = time.monotonic() - t0
        got_at_return = rx.got
        rx.count_when_quiet()
        return out, took, got_at_return
    finally:
        rx.close()


@pytest.mark.integration
def test_the_tail_reaches_a_slow_receiver():
    out, took, got_at_return = publish_to({})
    assert out["messages"] == N and out["drained"] is True
    # the publisher returned only once the receiver had taken (nearly) all: it closes after the
    # query, which waits behind the data; at most its channel's 16 were still unread
    assert got_at_return >= N - 16 - 1, (got_at_return, took)


@pytest.mark.integration
def test_all_is_received_and_asked_once():
    port = free_port()
    rx = SlowReceiver(port)
    try:
        publish_stream(imu_stream(), speed=0.0, connect=[f"tcp/127.0.0.1:{port}"], imu_batch=1)
        assert rx.count_when_quiet() == N
        assert rx.queries == 1
    finally:
        rx.close()


@pytest.mark.integration
def test_a_receiver_without_a_status_queryable_is_not_waited_for():
    out, _, _ = publish_to({"serve_status": False})
    assert out["drained"] is None  # nobody to ask: the old linger, no claim


@pytest.mark.integration
def test_a_service_that_does_not_answer_is_reported():
    out, took, _ = publish_to({"answer": False}, drain_timeout_s=2.0)
    assert out["drained"] is False
    assert 2.0 <= took < 30.0


#: samples enough to fill the publisher's transmission queue and both sockets (~4 MB: a put then
#: blocks; measured 19,600 of 200 B)
BACKLOG_N = 40_000


@pytest.mark.integration
def test_a_receiver_that_reads_nothing_for_longer_than_zenohs_block_limit_loses_nothing():
    """Zenoh closes a link after one blocking put waited ``wait_before_close`` (5 s by default)
    and drops every later put without an error: four simulators at ``--speed 0`` against one
    service lost 70-90 % of their streams. The simulators' sessions wait ``PUBLISHER_BLOCK_WAIT_S``;
    here the receiver reads nothing for 7 s, then everything."""
    out, took, got_at_return = publish_to({"pause_s": 7.0, "read_s": 0.0}, n=BACKLOG_N)
    assert took >= 7.0  # the publisher was held back (else the test shows nothing)
    assert out["messages"] == BACKLOG_N
    assert out["drained"] is True and not out["subscriber_lost"], out
    assert got_at_return >= BACKLOG_N - 16, got_at_return  # at most the channel still unread


@pytest.mark.integration
def test_a_publisher_whose_subscribers_go_away_says_so():
    """The service stops after 500 samples of a paced stream: what follows reaches nobody, and the
    result says so (the command line exits 4 with a message) instead of 'published N'."""
    out, _, got = publish_to({"close_after": 500, "read_s": 0.0}, speed=20.0)
    assert got == 500
    assert out["subscriber_lost"] is True and out["drained"] is False, out


@pytest.mark.integration
@pytest.mark.parametrize(
    "command, vehicle, prog",
    [
        (["run", str(DEMO), "--speed", "60", "--imu-batch", "1"], "v1", "fednav-sim"),
        (
            ["fleet", "--vehicles", "1", "--stem", "v", "--duration", "20", "--speed", "20"]
            + ["--imu-batch", "1", "--variants", "1"],
            "v000",
            "fednav-sim fleet",
        ),
    ],
    ids=["run", "fleet"],
)
def test_fednav_sim_exits_4_when_its_subscribers_go_away(command, vehicle, prog):
    """The command line says it: exit 4 and a message, not 'published N' and 0 (the receiver stands
    for a service stopped a few hundred messages into the stream); ``fednav-sim fleet`` too (its
    own publishing loop, one watch on its first key)."""
    port = free_port()
    rx = SlowReceiver(port, serve_status=False, read_s=0.0, close_after=300, key_expr=f"fednav/{vehicle}/**")
    try:
        sim = subprocess.run(
            [sys.executable, "-m", "fednav.simulators", *command, "--connect", f"tcp/127.0.0.1:{port}"],
            capture_output=True,
            text=True,
            timeout=120,
        )
    finally:
        rx.close()
    assert rx.got == 300
    assert sim.returncode == 4, (sim.returncode, sim.stdout, sim.stderr)
    assert f"{prog}: the subscribers went away during the stream" in sim.stderr


def _run_car1(port: int) -> subprocess.CompletedProcess:
    """``fednav-sim run`` of the demo as fast as taken, under the name car1."""
    return subprocess.run(
        [sys.executable, "-m", "fednav.simulators", "run", str(DEMO), "--speed", "0", "--imu-batch", "10"]
        + ["--vehicle", "car1", "--connect", f"tcp/127.0.0.1:{port}"],
        capture_output=True,
        text=True,
        timeout=120,
    )


@pytest.mark.integration
def test_fednav_sim_exits_5_when_no_service_serves_its_vehicle():
    """A fednav service serving v1 takes a stream under another name (counted unserved_vehicle) and
    answers no status for it: exit 5 naming the vehicle, not 0 (a mapping's vehicle that differs
    from the service's is an easy first-hour mistake). A receiver that is no fednav service (no
    service visible: none on the bus, or a router's access control that lets a simulator neither
    ask a status nor see the services): a warning, exit 0."""
    port = free_port()
    svc = start_service(port, extra=["--vehicle", "v1"])
    try:
        sim = _run_car1(port)
    finally:
        svc.signal()
        assert svc.wait(timeout=60) == 0, svc.output()
    assert sim.returncode == 5, (sim.returncode, sim.stdout, sim.stderr[-2000:])
    assert "fednav-sim: no fednav service serves vehicle 'car1'" in sim.stderr, sim.stderr
    assert "unserved_vehicle" in svc.output()
    port = free_port()
    rx = SlowReceiver(port, serve_status=False, read_s=0.0, key_expr="fednav/car1/**")
    try:
        sim = _run_car1(port)
    finally:
        rx.close()
    assert rx.got > 1000
    assert sim.returncode == 0, (sim.returncode, sim.stderr[-2000:])
    assert "fednav-sim: warning: no fednav service confirmed vehicle 'car1'" in sim.stderr, sim.stderr


@pytest.mark.integration
def test_fednav_sim_fleet_says_when_no_service_answers_and_refuses_bad_endpoints():
    """No subscriber on the endpoint: exit 3 and a message (not a traceback); an endpoint that is
    not one: exit 2 before anything is built."""
    port = free_port()
    base = [sys.executable, "-m", "fednav.simulators", "fleet", "--vehicles", "1", "--duration", "2"]
    alone = subprocess.run(
        base + ["--match-timeout", "1", "--connect", f"tcp/127.0.0.1:{port}"],
        capture_output=True,
        text=True,
        timeout=120,
    )
    assert alone.returncode == 3, (alone.returncode, alone.stderr[-2000:])
    assert f"no fednav service or Zenoh router answered on tcp/127.0.0.1:{port} within 1 s" in alone.stderr
    assert "Traceback" not in alone.stderr
    bad = subprocess.run(base + ["--connect", "nonsense"], capture_output=True, text=True, timeout=60)
    assert bad.returncode == 2 and "fednav-sim fleet:" in bad.stderr, bad.stderr


@pytest.mark.integration
def test_a_simulator_started_before_its_service_waits_for_it():
    """Started first (a script that starts both at once), ``fednav-sim run`` waits for the service
    (up to its match timeout) instead of failing at once with Zenoh's error."""
    port = free_port()
    sim = subprocess.Popen(
        [sys.executable, "-m", "fednav.simulators", "run", str(DEMO), "--speed", "100"]
        + ["--connect", f"tcp/127.0.0.1:{port}"],
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
    )
    time.sleep(3.0)
    assert sim.poll() is None, sim.communicate()
    rx = SlowReceiver(port, read_s=0.0, key_expr="fednav/v1/**")
    try:
        out, err = sim.communicate(timeout=120)
    finally:
        rx.close()
    assert sim.returncode == 0, (sim.returncode, err[-2000:])
    assert "published" in out and rx.got > 1000, (out, rx.got)


@pytest.mark.integration
def test_ctrl_c_ends_the_wait_for_a_service():
    """Waiting for its service, the simulator still stops at once on Ctrl-C (SIGINT): exit 130."""
    import signal

    sim = subprocess.Popen(
        [
            sys.executable,
            "-m",
            "fednav.simulators",
            "run",
            str(DEMO),
            "--connect",
            f"tcp/127.0.0.1:{free_port()}",
        ],
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
        # a terminal's Ctrl-C: the test runner's workers ignore SIGINT, and a child inherits that
        # (Python then installs no KeyboardInterrupt handler: the command rightly ignores it too)
        preexec_fn=lambda: signal.signal(signal.SIGINT, signal.SIG_DFL),
    )
    time.sleep(3.0)  # (imports, the scenario, then the wait)
    assert sim.poll() is None
    t0 = time.monotonic()
    sim.send_signal(signal.SIGINT)
    _, err = sim.communicate(timeout=30)
    assert sim.returncode == 130 and "interrupted" in err, (sim.returncode, err[-2000:])
    assert time.monotonic() - t0 < 10.0  # (attempts of 0.5 s; the wait itself would be 30 s)


def test_status_keys_one_per_vehicle_in_order():
    keys = ["fednav/a/sensors/imu/x", "fednav/b/sensors/gnss/y", "fednav/a/init", "odd"]
    assert status_keys(keys) == ["fednav/a/service/status", "fednav/b/service/status"]
