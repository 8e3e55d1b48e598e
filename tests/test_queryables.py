"""Late joiners over real processes: liveliness tokens, the latest-solution queryable, and queries
with wildcards answered under concrete keys with typed encodings (a plain Zenoh client)."""

from __future__ import annotations

import json
import signal

import pytest

from fednav.simulators.processes import free_port, start_service, start_sim, wait_idle

from .plain_zenoh import client as zenoh_client
from .scenario_utils import SCENARIOS

pytestmark = pytest.mark.integration


def _get(session, selector: str) -> list[tuple[str, str, dict]]:
    out = []
    for reply in session.get(selector, timeout=5.0):
        assert reply.ok is not None, reply.err.payload.to_string()
        out.append((str(reply.ok.key_expr), str(reply.ok.encoding), json.loads(reply.ok.payload.to_bytes())))
    return sorted(out, key=lambda r: r[0])


def test_late_joiner_finds_the_service_and_the_latest_solution(tmp_path):
    port = free_port()
    svc = start_service(port, config=SCENARIOS / "demo_aircraft.toml", table="service")
    session = zenoh_client(port)
    samples: list[tuple[str, bytes]] = []  # every sample on the bus: (encoding, payload)
    session.declare_subscriber("fednav/**", lambda s: samples.append((str(s.encoding), s.payload.to_bytes())))
    try:
        sim = start_sim(port, SCENARIOS / "demo_aircraft.toml", speed=0.0, seed=3)
        assert sim.wait(timeout=120) == 0, sim.output()
        status = wait_idle(port)
        assert status is not None
        alive = sorted(str(r.ok.key_expr) for r in session.liveliness().get("fednav/**", timeout=5.0))
        assert "fednav/v1/service/alive" in alive
        assert any(k.startswith("fednav/_services/") for k in alive), alive
        # wildcard queries: one reply per resource, each under its concrete key, typed
        replies = _get(session, "fednav/**/status")
        assert [(k, e) for k, e, _ in replies] == [
            ("fednav/v1/service/status", "application/json;fednav.Status/1")
        ]
        assert replies[0][2]["vehicle"] == "v1" and replies[0][2]["health"]["accepted"] > 0
        keys_ = [k for k, _, _ in _get(session, "fednav/*/service/*")]
        assert keys_ == ["fednav/v1/service/config", "fednav/v1/service/status"]
        sols = _get(session, "fednav/v1/nav/**")
        assert [(k, e) for k, e, _ in sols] == [
            ("fednav/v1/nav/lc/solution", "application/json;fednav.Solution/1")
        ]
        last = sols[0][2]
        assert last["pipeline"] == "lc" and last["t"] == pytest.approx(status["health"]["t"], abs=0.1)
        assert _get(session, "fednav/v2/**") == []  # a vehicle the service does not serve: no reply
    finally:
        svc.signal(signal.SIGTERM)
        rc = svc.wait(timeout=30)
        session.close()
    assert rc == 0
    _validate_against_shipped_schemas(samples)


def _validate_against_shipped_schemas(samples) -> None:
    """Every live sample validates, with a standard 2020-12 validator, against the shipped schema
    its encoding names (application/json;fednav.<Type>/<version>); the simulator's binary ImuBatch
    (application/octet-stream;fednav.ImuBatch/1) decodes by its declared layout."""
    from pathlib import Path

    from jsonschema import Draft202012Validator

    folder = Path(__file__).resolve().parents[1] / "docs" / "schemas"
    validators = {}
    seen: dict[str, int] = {}
    for encoding, payload in samples:
        kind = encoding.split(";fednav.")[1].split("/")[0]
        if encoding.startswith("application/octet-stream;"):  # the binary ImuBatch: its declared layout
            from fednav.service import imu_batch

            assert encoding == imu_batch.ENCODING
            seen[kind] = seen.get(kind, 0) + len(imu_batch.decode(payload))
            continue
        if kind not in validators:
            validators[kind] = Draft202012Validator(json.loads((folder / f"{kind}.schema.json").read_text()))
        validators[kind].validate(json.loads(payload))
        seen[kind] = seen.get(kind, 0) + 1
    assert {"ImuBatch", "GnssFix", "InitialNav", "Truth", "Solution", "Health"} <= set(seen), seen
    assert sum(seen.values()) > 30000
