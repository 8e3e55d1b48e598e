"""A plain eclipse-zenoh client for the tests: ``client`` uses no fednav code (what any other client
would do); ``run_and_collect`` starts the fednav processes around such a client."""

import json

import zenoh


def client(port: int, block_wait_s: float | None = None) -> zenoh.Session:
    """Client-mode session to the service on loopback, multicast scouting off. ``block_wait_s``:
    how long one blocking put may wait before Zenoh closes the link (its default 5 s: a
    publisher faster than a busy service then loses its link and every later put)."""
    c = zenoh.Config()
    if block_wait_s is not None:
        c.insert_json5(
            "transport/link/tx/queue/congestion_control/block/wait_before_close", str(int(block_wait_s * 1e6))
        )
    c.insert_json5("mode", '"client"')
    c.insert_json5("scouting/multicast/enabled", "false")
    c.insert_json5("listen/endpoints", "[]")
    c.insert_json5("connect/endpoints", json.dumps([f"tcp/127.0.0.1:{port}"]))
    return zenoh.open(c)


def run_and_collect(scenario, key_expr: str, *, seed: int, rrd=None, sim_timeout_s: float = 180.0) -> dict:
    """Start fednav-service on the scenario's [service] table (optionally recording to ``rrd``),
    subscribe ``key_expr`` with a plain client, publish the scenario as fast as the service takes
    it, wait until the service is idle, stop it with SIGTERM. Returns the received
    (key, JSON) items, the service's exit code and output."""
    import signal
    import threading
    import time

    from fednav.simulators.processes import free_port, start_service, start_sim, wait_idle

    port = free_port()
    svc = start_service(port, config=scenario, table="service", rrd=rrd)
    session = client(port)
    got: list[tuple[str, dict]] = []
    lock = threading.Lock()

    def cb(sample: zenoh.Sample) -> None:
        with lock:
            got.append((str(sample.key_expr), json.loads(sample.payload.to_bytes())))

    sub = session.declare_subscriber(key_expr, cb)
    try:
        sim = start_sim(port, scenario, speed=0.0, seed=seed)
        assert sim.wait(timeout=sim_timeout_s) == 0, sim.output()
        assert wait_idle(port, timeout_s=120) is not None, "service did not become idle"
        time.sleep(0.3)
    finally:
        svc.signal(signal.SIGTERM)
        rc = svc.wait(timeout=60)
        sub.undeclare()
        session.close()
    with lock:
        items = list(got)
    return {"items": items, "rc": rc, "out": svc.output()}
