"""``--zenoh-config FILE`` is overlaid on fednav's safe defaults (issue 9, security by default).

The resulting session config is read back with ``zenoh.Config.get_json`` (what Zenoh will use).
"""

import json

import pytest
import zenoh

from fednav.service.config import ZenohConfig
from fednav.service.transport.zenoh_io import make_config


def _get(c: zenoh.Config, key: str):
    return json.loads(c.get_json(key))


def _write(tmp_path, text: str) -> str:
    p = tmp_path / "zenoh.json5"
    p.write_text(text)
    return str(p)


def test_no_file_is_loopback_and_discovery_off():
    c = make_config(ZenohConfig())
    assert _get(c, "mode") == "peer"
    assert _get(c, "listen/endpoints") == ["tcp/127.0.0.1:7447"]
    assert _get(c, "connect/endpoints") == []
    assert _get(c, "scouting/multicast/enabled") is False
    assert _get(c, "scouting/gossip/enabled") is False


def test_file_with_mode_and_listen_keeps_multicast_and_gossip_off(tmp_path):
    # JSON5 as people write it: comments, unquoted keys, single quotes, trailing commas
    path = _write(
        tmp_path,
        """{
          // only mode and listen
          mode: 'peer',
          listen: { endpoints: ["tcp/127.0.0.1:17447"], },
        }""",
    )
    # what Zenoh alone would do with the file: multicast and gossip unset, i.e. Zenoh's default (on)
    bare = zenoh.Config.from_file(path)
    assert _get(bare, "scouting/multicast/enabled") is None
    c = make_config(ZenohConfig(), config_file=path)
    assert _get(c, "mode") == "peer"
    assert _get(c, "listen/endpoints") == ["tcp/127.0.0.1:17447"]
    assert _get(c, "connect/endpoints") == []
    assert _get(c, "scouting/multicast/enabled") is False
    assert _get(c, "scouting/gossip/enabled") is False


def test_file_without_endpoints_gets_loopback_not_all_interfaces(tmp_path):
    path = _write(tmp_path, "{ transport: { link: { tx: { lease: 12000 } } } }")
    bare = zenoh.Config.from_file(path)
    assert _get(bare, "listen/endpoints") != ["tcp/127.0.0.1:7447"]  # Zenoh's own: tcp/[::]:0
    c = make_config(ZenohConfig(mode="client", listen=[], connect=["tcp/127.0.0.1:7999"]), config_file=path)
    assert _get(c, "mode") == "client"
    assert _get(c, "listen/endpoints") == []
    assert _get(c, "connect/endpoints") == ["tcp/127.0.0.1:7999"]
    assert _get(c, "transport/link/tx/lease") == 12000  # the rest of the file is kept
    assert _get(c, "scouting/multicast/enabled") is False


def test_explicit_settings_in_the_file_are_honoured(tmp_path):
    path = _write(
        tmp_path,
        """{
          mode: "client",
          connect: { endpoints: ["tcp/127.0.0.1:7999"] },
          scouting: { multicast: { enabled: true }, gossip: { enabled: true } },
        }""",
    )
    c = make_config(ZenohConfig(), config_file=path)
    assert _get(c, "mode") == "client"
    assert _get(c, "connect/endpoints") == ["tcp/127.0.0.1:7999"]
    assert _get(c, "scouting/multicast/enabled") is True
    assert _get(c, "scouting/gossip/enabled") is True
    assert _get(c, "listen/endpoints") == ["tcp/127.0.0.1:7447"]  # not in the file: fednav's


def test_command_line_endpoints_replace_the_files(tmp_path):
    path = _write(tmp_path, '{ listen: { endpoints: ["tls/127.0.0.1:7447"] } }')
    c = make_config(ZenohConfig(), listen=["tls/127.0.0.1:17000"], connect=[], config_file=path)
    assert _get(c, "listen/endpoints") == ["tls/127.0.0.1:17000"]
    # the [zenoh] table's config_file is used when no file is given explicitly
    c = make_config(ZenohConfig(config_file=path))
    assert _get(c, "listen/endpoints") == ["tls/127.0.0.1:7447"]
    assert _get(c, "scouting/multicast/enabled") is False


def test_bad_file_raises(tmp_path):
    with pytest.raises(zenoh.ZError):
        make_config(ZenohConfig(), config_file=_write(tmp_path, "{ mode: 'nonsense' }"))


@pytest.mark.integration
@pytest.mark.parametrize("multicast", [None, True])
def test_service_process_with_a_minimal_file_opens_no_multicast_socket(tmp_path, multicast):
    """fednav-service with a file of mode + listen only: its sockets are the loopback TCP listener
    (and its connections), no UDP scouting socket; the same file with multicast explicitly on opens
    the scouting sockets (so the check can see them)."""
    import psutil  # installed with rerun-sdk (its dependency)

    from fednav.simulators.processes import Proc, free_port

    port = free_port()
    scouting = "" if multicast is None else "scouting: { multicast: { enabled: true } },"
    path = _write(
        tmp_path, f'{{ mode: "peer", {scouting} listen: {{ endpoints: ["tcp/127.0.0.1:{port}"] }} }}'
    )
    import sys

    proc = Proc(
        [sys.executable, "-m", "fednav.service", "--zenoh-config", path, "--no-record"], "fednav-service"
    )
    try:
        assert proc.wait_for("fednav-service ready", timeout=60.0), proc.output()
        conns = psutil.Process(proc.p.pid).net_connections(kind="inet")
    finally:
        proc.kill()
    udp = [c for c in conns if c.type == 2]  # SOCK_DGRAM
    listening = [c.laddr for c in conns if c.status == psutil.CONN_LISTEN]
    if multicast is None:
        assert udp == [], udp
        assert listening == [("127.0.0.1", port)], listening
    else:
        assert any(c.laddr[1] == 7446 for c in udp), udp


@pytest.mark.integration
def test_default_service_refuses_spoofed_outputs():
    """fednav-service with its defaults (no config file): a client on the bus cannot publish
    solutions or health, nor answer status queries, to the other clients routed through the
    service; what is not an output (a sensor key) is still routed."""
    import signal
    import threading
    import time

    from fednav.simulators.processes import free_port, start_service

    from .plain_zenoh import client

    port = free_port()
    svc = start_service(port)
    spoofer, reader = client(port), client(port)
    got: list[tuple[str, str]] = []
    lock = threading.Lock()

    def cb(sample: zenoh.Sample) -> None:
        with lock:
            got.append((str(sample.key_expr), sample.payload.to_string()))

    try:
        reader.declare_subscriber("fednav/**", cb)
        rogue = spoofer.declare_queryable(
            "fednav/v1/service/status", lambda q: q.reply(q.key_expr, '{"spoofed": true}')
        )
        time.sleep(0.5)
        for _ in range(10):
            spoofer.put("fednav/v1/nav/lc/solution", '{"spoofed": true}')
            spoofer.put("fednav/v1/service/health", '{"spoofed": true}')
            spoofer.put("fednav/v2/sensor/imu/x", "routed")  # not served by the service: a plain route
        time.sleep(0.5)
        replies = [
            r.ok.payload.to_string() for r in reader.get("fednav/v1/service/status", timeout=3.0) if r.ok
        ]
        rogue.undeclare()
    finally:
        svc.signal(signal.SIGTERM)
        svc.wait(timeout=30)
        spoofer.close()
        reader.close()
    with lock:
        keys = [k for k, _ in got]
    assert keys.count("fednav/v2/sensor/imu/x") == 10  # routing through the service works
    assert not any("spoofed" in p for _, p in got), got
    assert len(replies) == 1 and "spoofed" not in replies[0], replies  # the service's own answer


def test_simulator_config_is_overlaid_the_same_way(tmp_path):
    from fednav.simulators.publisher import session_config

    c = session_config()
    assert _get(c, "mode") == "client"
    assert _get(c, "connect/endpoints") == ["tcp/127.0.0.1:7447"]
    assert _get(c, "listen/endpoints") == []
    assert _get(c, "scouting/multicast/enabled") is False
    path = _write(tmp_path, '{ transport: { link: { tls: { root_ca_certificate: "ca.pem" } } } }')
    c = session_config(zenoh_config=path)
    assert _get(c, "mode") == "client"
    assert _get(c, "connect/endpoints") == ["tcp/127.0.0.1:7447"]
    assert _get(c, "listen/endpoints") == []
    assert _get(c, "scouting/multicast/enabled") is False
    assert _get(c, "scouting/gossip/enabled") is False
    assert _get(c, "transport/link/tls/root_ca_certificate") == "ca.pem"
    c = session_config(connect=["tls/127.0.0.1:7000"], zenoh_config=path)
    assert _get(c, "connect/endpoints") == ["tls/127.0.0.1:7000"]


def test_yaml_file_is_overlaid_by_resolved_values(tmp_path):
    p = tmp_path / "zenoh.yaml"
    p.write_text('mode: "peer"\nlisten:\n  endpoints: ["tcp/127.0.0.1:17447"]\n')
    c = make_config(ZenohConfig(), config_file=str(p))
    assert _get(c, "listen/endpoints") == ["tcp/127.0.0.1:17447"]
    assert _get(c, "scouting/multicast/enabled") is False
    p.write_text('mode: "peer"\nscouting:\n  multicast:\n    enabled: true\n')
    c = make_config(ZenohConfig(), config_file=str(p))
    assert _get(c, "scouting/multicast/enabled") is True
    assert _get(c, "listen/endpoints") == ["tcp/127.0.0.1:7447"]


def test_output_guard_unless_the_file_sets_access_control(tmp_path):
    c = make_config(ZenohConfig(), outputs_prefix="fleet")
    acl = _get(c, "access_control")
    assert acl["enabled"] is True and acl["default_permission"] == "allow"
    assert acl["rules"][0]["key_exprs"] == ["fleet/*/nav/**", "fleet/*/service/**"]
    assert acl["rules"][0]["permission"] == "deny" and acl["rules"][0]["flows"] == ["ingress"]
    assert _get(make_config(ZenohConfig()), "access_control")["enabled"] is False  # simulators, clients
    path = _write(tmp_path, "{ access_control: { enabled: false } }")
    assert (
        _get(make_config(ZenohConfig(), config_file=path, outputs_prefix="fleet"), "access_control")[
            "enabled"
        ]
        is False
    )


def test_arrival_time_is_the_ingress_timestamp():
    """Health's latency starts at the sample's ingress timestamp (queue time included); without a
    timestamp, or with an implausible one, at its reading."""
    import time
    from datetime import UTC, datetime, timedelta
    from types import SimpleNamespace

    from fednav.service.transport.zenoh_io import Intake, make_config

    class Ts:
        def __init__(self, age_s):
            self.t = datetime.now(UTC) - timedelta(seconds=age_s)

        def get_time_as_ntp64(self):
            return SimpleNamespace(as_secs_f64=self.t.timestamp)

    now = time.monotonic()
    assert abs((now - Intake.arrival(SimpleNamespace(timestamp=Ts(0.25)))) - 0.25) < 0.05
    assert abs(Intake.arrival(SimpleNamespace(timestamp=None)) - time.monotonic()) < 0.05
    assert abs(Intake.arrival(SimpleNamespace(timestamp=Ts(-5.0))) - time.monotonic()) < 0.05  # clock ahead
    # a real Zenoh timestamp: its NTP64 seconds are the UNIX time its datetime gives
    import zenoh

    real = zenoh.Timestamp.parse_rfc3339("2026-11-28T12:00:00.250000000Z/ea5965af401ccd66e2833a89035a3cb8")
    assert real.get_time_as_ntp64().as_secs_f64() == pytest.approx(real.get_time().timestamp(), abs=1e-6)
    cfg = make_config(outputs_prefix="fednav")  # the service's session stamps samples at ingress
    assert json.loads(cfg.get_json("timestamping/enabled")) == {"router": True, "peer": True, "client": True}
