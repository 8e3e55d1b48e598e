"""The shipped mutual-TLS + access-control example (service/configs/secure/, docs/SECURITY.md) with
real processes (issue 9, security by default).

A throwaway CA and certificates are made at test time by the shipped ``make-certs.sh`` (openssl CLI);
fednav-service and fednav-sim run with the shipped json5 files, unchanged, over tls/127.0.0.1 on a
free port (``--listen``/``--connect`` give the port; the processes run in a folder holding
``certs/``, as the configs' relative paths expect). Plain eclipse-zenoh clients then show:

- an authorised reader (CN=fednav-reader) receives solutions and health; the service processed
  every sample the simulator (CN=fednav-simulator) published and nothing else;
- a client without a certificate, and one whose certificate comes from another CA, cannot open a
  session at all; a plain TCP client neither;
- a client with a valid certificate but no policy (CN=fednav-intruder) receives nothing, and what
  it publishes (a spoofed solution, a spoofed GNSS fix) reaches no one: not the readers, not the
  service (its received count equals the simulator's message count);
- the authorised reader is refused what its policy does not list: publishing a spoofed solution or
  sensor sample, subscribing to sensor keys or to everything; the simulator's certificate cannot
  read solutions.
"""

from __future__ import annotations

import json
import os
import shutil
import signal
import subprocess
import sys
import threading
import time
from pathlib import Path

import pytest
import zenoh

from fednav.service.messages import GnssFix
from fednav.simulators.processes import Proc, free_port

pytestmark = [
    pytest.mark.integration,
    pytest.mark.skipif(shutil.which("openssl") is None, reason="needs the openssl command line tool"),
]
ROOT = Path(__file__).resolve().parents[1]
SECURE = ROOT / "service" / "configs" / "secure"
DEMO = ROOT / "simulators" / "scenarios" / "demo_aircraft.toml"
SPOOF_LAT_DEG = 1.2345  # a solution with this latitude can only come from a spoofer


def _make_certs(folder: Path) -> None:
    def run(*args: str) -> None:
        subprocess.run(
            ["sh", str(SECURE / "make-certs.sh"), *args], check=True, capture_output=True, timeout=60
        )

    run(str(folder / "certs"))  # ca, service, simulator, reader
    run(str(folder / "certs"), "intruder=fednav-intruder")  # right CA, no policy
    run(str(folder / "rogue"), "reader=fednav-reader")  # the reader's name, another CA


def _config(endpoint: str, tls: dict | None) -> zenoh.Config:
    """A client config: the shipped reader.json5 with TLS keys replaced, or a plain one (tls None).
    Paths are relative to the working directory (the test's folder)."""
    if tls is None:
        c = zenoh.Config()
        c.insert_json5("mode", '"client"')
        c.insert_json5("scouting/multicast/enabled", "false")
    else:
        c = zenoh.Config.from_file(str(SECURE / "reader.json5"))
        for k, v in tls.items():
            c.insert_json5(f"transport/link/tls/{k}", json.dumps(v))
    c.insert_json5("connect/endpoints", json.dumps([endpoint]))
    return c


class Sink:
    """Samples received by one subscription: (key, payload bytes)."""

    def __init__(self, session: zenoh.Session, expr: str):
        self.items: list[tuple[str, bytes]] = []
        self._lock = threading.Lock()
        self.sub = session.declare_subscriber(expr, self._cb)

    def _cb(self, s: zenoh.Sample) -> None:
        with self._lock:
            self.items.append((str(s.key_expr), s.payload.to_bytes()))

    def json(self, suffix: str = "") -> list[dict]:
        with self._lock:
            return [json.loads(p) for k, p in self.items if k.endswith(suffix)]

    def __len__(self) -> int:
        with self._lock:
            return len(self.items)


def _spoof(session: zenoh.Session, solution: dict, n: int = 20) -> None:
    """Publish n spoofed solutions and n schema-valid GNSS fixes (lat 0, lon 0, h -12 km) under the
    simulator's sensor key: accepted, either would hijack navigation."""
    sol = json.dumps(dict(solution, lat_deg=SPOOF_LAT_DEG))
    fix = GnssFix(
        t=solution["t"] + 0.05,
        lat_deg=0.0,
        lon_deg=0.0,
        height_m=-12_000.0,
        vel_enu_mps=(0.0, 0.0, 0.0),
        pos_std_enu_m=(1.0, 1.0, 1.0),
        vel_std_enu_mps=(0.1, 0.1, 0.1),
    ).to_json()
    for _ in range(n):
        session.put("fednav/v1/nav/lc/solution", sol)
        session.put("fednav/v1/sensor/gnss/main/fix", fix)
        time.sleep(0.01)


def test_mtls_and_access_control(tmp_path, monkeypatch):
    _make_certs(tmp_path)
    monkeypatch.chdir(tmp_path)  # the clients below read certs/... as the shipped configs say
    port = free_port()
    ep = f"tls/127.0.0.1:{port}"
    svc = Proc(
        [sys.executable, "-m", "fednav.service", "--config", str(DEMO), "--config-table", "service"]
        + ["--zenoh-config", str(SECURE / "service.json5"), "--listen", ep, "--no-record"],
        "fednav-service",
        cwd=tmp_path,
    )
    sessions: list[zenoh.Session] = []
    try:
        assert svc.wait_for("fednav-service ready", timeout=60.0), svc.output()

        def open_(tls: dict | None, endpoint: str = ep) -> zenoh.Session:
            s = zenoh.open(_config(endpoint, tls))
            sessions.append(s)
            return s

        # One session per probe: a session hands a sample it receives (or publishes) to all its own
        # matching subscribers, so a denied subscription must not share a session with an allowed one.
        reader = open_({})  # the shipped reader.json5 as is
        nav = Sink(reader, "fednav/v1/nav/**")
        health = Sink(reader, "fednav/v1/service/health")
        reader_probe = open_({})
        reader_sensors = Sink(reader_probe, "fednav/v1/sensor/**")
        reader_all = Sink(reader_probe, "fednav/**")

        # no certificate, another CA's certificate (with the reader's name), plain TCP: no session
        no_cert = {
            "root_ca_certificate": "certs/ca.pem",
            "enable_mtls": False,
            "connect_certificate": None,
            "connect_private_key": None,
        }
        # control: the same certificate-less client does open a session with a TLS listener of the
        # same server certificate that does not ask for client certificates (so below, it is mTLS
        # that refuses it)
        ctl_ep = f"tls/127.0.0.1:{free_port()}"
        ctl = zenoh.Config()
        ctl.insert_json5("scouting/multicast/enabled", "false")
        ctl.insert_json5("listen/endpoints", json.dumps([ctl_ep]))
        for k, v in {
            "root_ca_certificate": "certs/ca.pem",
            "listen_certificate": "certs/service.pem",
            "listen_private_key": "certs/service-key.pem",
        }.items():
            ctl.insert_json5(f"transport/link/tls/{k}", json.dumps(v))
        with zenoh.open(ctl):
            zenoh.open(_config(ctl_ep, no_cert)).close()
        refused = {}
        for name, tls, endpoint in (
            ("no certificate", no_cert, ep),
            (
                "wrong CA",
                {
                    "root_ca_certificate": "certs/ca.pem",
                    "connect_certificate": "rogue/reader.pem",
                    "connect_private_key": "rogue/reader-key.pem",
                },
                ep,
            ),
            ("plain tcp", None, f"tcp/127.0.0.1:{port}"),
        ):
            t0 = time.monotonic()
            with pytest.raises(zenoh.ZError) as err:
                open_(tls, endpoint)
            refused[name] = time.monotonic() - t0
            assert "Unable to connect" in str(err.value), err.value  # refused, not a config error

        intruder_tls = {
            "root_ca_certificate": "certs/ca.pem",
            "connect_certificate": "certs/intruder.pem",
            "connect_private_key": "certs/intruder-key.pem",
        }
        intruder = open_(intruder_tls)
        intruder_nav = Sink(intruder, "fednav/v1/nav/**")
        intruder_all = Sink(intruder, "fednav/**")
        sim_cert = open_(
            {
                "root_ca_certificate": "certs/ca.pem",
                "connect_certificate": "certs/simulator.pem",
                "connect_private_key": "certs/simulator-key.pem",
            }
        )
        sim_cert_nav = Sink(sim_cert, "fednav/v1/nav/**")
        time.sleep(0.5)  # subscriptions declared

        sim = Proc(
            [sys.executable, "-m", "fednav.simulators", "run", str(DEMO), "--speed", "0", "--seed", "4"]
            + ["--zenoh-config", str(SECURE / "simulator.json5"), "--connect", ep],
            "fednav-sim",
            cwd=tmp_path,
        )
        assert sim.wait(timeout=300) == 0, sim.output()
        published = int(sim.output().split("published ")[1].split()[0])

        # spoofs once solutions flow, from the intruder and from the authorised reader
        deadline = time.monotonic() + 120
        while len(nav.json("/solution")) < 100 and time.monotonic() < deadline:
            time.sleep(0.1)
        genuine = nav.json("/solution")[-1]
        for spoofer in (open_(intruder_tls), open_({})):
            _spoof(spoofer, genuine)

        # the status and config queryables answer no reader
        status_replies = [
            r for k in ("status", "config") for r in reader_probe.get(f"fednav/v1/service/{k}", timeout=2.0)
        ]

        # wait until the service is idle: health's received count stops moving
        last, deadline = None, time.monotonic() + 180
        while time.monotonic() < deadline:
            time.sleep(1.2)
            h = health.json()
            cur = (h[-1]["received"], h[-1]["queue_depth"]) if h else None
            if cur is not None and cur == last and cur[1] == 0:
                break
            last = cur
        time.sleep(0.5)
    finally:
        svc.signal(signal.SIGTERM)
        rc = svc.wait(timeout=60)
        for s in sessions:
            s.close()

    solutions = nav.json("/solution")
    h = health.json()
    print(
        f"simulator published {published}; service received {h[-1]['received'] if h else None}; "
        f"reader: {len(solutions)} solutions, {len(h)} health; intruder {len(intruder_nav)}+"
        f"{len(intruder_all)}; reader on sensor/** {len(reader_sensors)}, on fednav/** {len(reader_all)}; "
        f"simulator certificate on nav/** {len(sim_cert_nav)}; status/config replies {len(status_replies)}; "
        "refused in " + ", ".join(f"{k} {v:.1f} s" for k, v in refused.items())
    )
    assert rc == 0, svc.output()
    # the authorised reader gets the solutions (demo: 300 s at 10 Hz) and health
    assert len(solutions) >= 2900
    assert h and h[-1]["t"] is not None
    # nothing in: the service processed exactly what the simulator published, no spoofed sample
    assert h[-1]["received"] == published, (h[-1], published)
    assert all(s["lat_deg"] != SPOOF_LAT_DEG for s in solutions)
    # nothing out: no policy, no data; the reader gets only what its policy lists
    assert len(intruder_nav) == 0 and len(intruder_all) == 0
    assert len(reader_sensors) == 0 and len(reader_all) == 0
    assert len(sim_cert_nav) == 0
    assert status_replies == []
    assert os.path.exists(tmp_path / "certs" / "ca-key.pem")  # made by the shipped script
