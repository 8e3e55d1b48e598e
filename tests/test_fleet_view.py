"""``fednav-fleet status`` and ``fednav-fleet record`` (issue 23) on real processes: fednav-router,
fednav-service(s) in client mode behind it, the fleet simulator (one process, five vehicles), and
the two commands as processes of their own, all over loopback with multicast scouting off.

- one service serving ``*`` and five vehicles: ``status --json`` lists the five vehicles, each
  answered by that service (its Zenoh id, as its ServiceHealth key names it) with the pipeline
  'aided' while the simulator publishes, and nothing flagged; ``record`` writes one .rrd that
  Rerun's reader reads back with every vehicle's track (map and ENU), status lane and the
  service's load;
- two services answering for the same vehicle with different pipeline settings, and a third
  under another prefix: ``status`` flags the vehicle served twice, names the differing
  configuration and the other prefix, and exits 1.
"""

from __future__ import annotations

import json
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pyarrow as pa
import pyarrow.compute as pc
import pytest
import zenoh

from fednav.dashboards import fleet as fleet_mod
from fednav.dashboards.fleet import config_difference
from fednav.simulators.processes import Proc, free_port

pytestmark = pytest.mark.integration
ROOT = Path(__file__).resolve().parents[1]
FLEET = ROOT / "service" / "configs" / "fleet"
VEHICLES = [f"veh{i:03d}" for i in range(5)]


def _router(port: int) -> Proc:
    router = Proc(
        [sys.executable, "-m", "fednav.service.router", "--listen", f"tcp/127.0.0.1:{port}"], "fednav-router"
    )
    assert router.wait_for("fednav-router ready", timeout=30), router.output()
    return router


def _service(port: int, *args: str) -> Proc:
    svc = Proc(
        [sys.executable, "-m", "fednav.service", "--zenoh-config", str(FLEET / "service.json5")]
        + ["--connect", f"tcp/127.0.0.1:{port}", "--no-record", *args],
        "fednav-service",
    )
    assert svc.wait_for("fednav-service ready", timeout=60), svc.output()
    return svc


def _fleet(*args: str, port: int) -> subprocess.Popen:
    return subprocess.Popen(
        [sys.executable, "-m", "fednav.dashboards.fleet", *args, "--connect", f"tcp/127.0.0.1:{port}"],
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
    )


def _fleet_sim(port: int, vehicles: int, duration_s: float, *extra: str) -> Proc:
    """``fednav-sim fleet`` of ``vehicles`` through the router on ``port``, once publishing."""
    sim = Proc(
        [sys.executable, "-m", "fednav.simulators", "fleet", "--vehicles", str(vehicles)]
        + ["--duration", str(duration_s), *extra, "--connect", f"tcp/127.0.0.1:{port}"],
        "fednav-sim fleet",
    )
    if not sim.wait_for("publishing", timeout=60):
        sim.kill()
        raise AssertionError(sim.output())
    return sim


def _client(port: int) -> zenoh.Session:
    c = zenoh.Config.from_file(str(FLEET / "reader.json5"))
    c.insert_json5("connect/endpoints", json.dumps([f"tcp/127.0.0.1:{port}"]))
    return zenoh.open(c)


def _stop(*procs: Proc) -> list[int]:
    for p in procs:
        p.signal(signal.SIGTERM)
    return [p.wait(timeout=60) for p in procs]


def _read(rrd: Path) -> tuple[dict[str, int], dict[str, list], dict[str, list[float]], int]:
    """Rows per entity (temporal), StateChange states per entity, Scalars per entity, blueprints."""
    from rerun.chunk import RrdReader

    reader = RrdReader(rrd)
    store = reader.recordings()[0]
    rows: dict[str, int] = {}
    states: dict[str, list] = {}
    scalars: dict[str, list[float]] = {}
    for ch in reader.stream(store=store):
        if ch.is_static:
            continue
        batch: pa.RecordBatch = ch.to_record_batch()
        rows[ch.entity_path] = rows.get(ch.entity_path, 0) + ch.num_rows
        if "StateChange:state" in batch.schema.names:
            states.setdefault(ch.entity_path, []).extend(
                pc.list_element(batch.column("StateChange:state"), 0).to_pylist()
            )
        if "Scalars:scalars" in batch.schema.names:
            scalars.setdefault(ch.entity_path, []).extend(
                pc.list_element(batch.column("Scalars:scalars"), 0).to_numpy(zero_copy_only=False).tolist()
            )
    return rows, states, scalars, len(reader.blueprints())


def test_fleet_status_and_record_of_five_vehicles(tmp_path):
    port = free_port()
    router = _router(port)
    procs = [router]
    watcher = _client(port)
    zids: set[str] = set()
    watcher.declare_subscriber("fednav/_services/*/health", lambda s: zids.add(str(s.key_expr).split("/")[2]))
    rrd = tmp_path / "out" / "fleet.rrd"
    try:
        procs.insert(0, _service(port, "--vehicle", "*"))
        sim = _fleet_sim(port, 5, 40, "--speed", "4")
        procs.insert(0, sim)
        record = _fleet("record", "-o", str(rrd), "--duration", "6", "--rate", "2", port=port)
        # status while the simulator publishes (10 s of it): every vehicle aided
        snap, deadline = None, time.monotonic() + 9
        while time.monotonic() < deadline:
            status = _fleet("status", "--json", port=port)
            out, err = status.communicate(timeout=60)
            snap = json.loads(out)
            statuses = [v["pipelines"].get("lc", {}).get("status") for v in snap["vehicles"]]
            if len(snap["vehicles"]) == 5 and statuses == ["aided"] * 5:
                break
            time.sleep(0.5)
        rec_out, rec_err = record.communicate(timeout=60)
        assert sim.wait(timeout=60) == 0, sim.output()
    finally:
        rcs = _stop(*procs)
        watcher.close()
    assert rcs == [0] * len(procs), [p.output() for p in procs]
    print(json.dumps({k: snap[k] for k in ("routers", "services", "problems")}, indent=1))
    assert status.returncode == 0, out + err
    assert len(zids) == 1, zids
    (zid,) = zids
    assert [v["vehicle"] for v in snap["vehicles"]] == VEHICLES
    for v in snap["vehicles"]:
        assert v["service"] == zid and v["services"] == [zid] and not v["served_twice"] and v["alive"], v
        lc = v["pipelines"]["lc"]
        assert lc["status"] == "aided", v
        assert lc["lag_s"] is not None and 0.0 <= lc["lag_s"] < 2.0, lc
        assert lc["age_s"] is None and lc["live_time"] is False  # simulated time, not this clock's
        assert lc["position"] is not None and abs(lc["position"][0] - 40.1) < 0.5
    assert [s["zid"] for s in snap["services"]] == [zid]
    assert snap["services"][0]["vehicles"] == VEHICLES and snap["services"][0]["alive"]
    assert snap["services"][0]["config"] == {"prefix": "fednav", "pipelines": {"lc": "loosely_coupled"}}
    assert snap["problems"] == [] and snap["other_prefixes"] == []
    assert len(snap["routers"]) == 1 and snap["routers"][0] != zid

    # the recording, read back with Rerun's reader: every vehicle, its track, its lane, the load
    assert record.returncode == 0, rec_out + rec_err
    assert "5 vehicle(s), 1 service(s)" in rec_out, rec_out
    assert "optimized from" in rec_out, rec_out  # compacted at the end (and read back below)
    rows, states, scalars, blueprints = _read(rrd)
    assert blueprints == 2  # the default at the start, then again with the ENU view framing every track
    for v in VEHICLES:
        assert rows.get(f"/fleet/{v}/position", 0) >= 8, (v, rows)  # 2 Hz for 6 s
        assert rows.get(f"/enu/{v}", 0) >= 8
        assert rows.get(f"/fleet/{v}/track", 0) >= 1
        assert "aided" in states[f"/status/{v}"], states
    assert set(states) == {f"/status/{v}" for v in VEHICLES}
    assert max(scalars[f"/load/vehicles/{zid}"]) == 5.0
    rates = np.array(scalars[f"/load/messages_per_s/{zid}"])
    # five vehicles at 4x real time: 200 Hz IMU in batches of 10, 10 Hz fixes -> ~600 messages/s
    assert rates.max() > 300, rates


def test_status_flags_a_vehicle_served_twice_a_differing_config_and_another_prefix(tmp_path):
    """... and a vehicle its publisher announces (``fednav/ghost/sensor/alive``, a plain client's
    token here) that no service serves."""
    lc = '[[pipelines]]\nkind = "loosely_coupled"\nname = "lc"\n'
    (tmp_path / "a.toml").write_text('vehicles = ["v1", "v2"]\n' + lc)
    (tmp_path / "b.toml").write_text('vehicles = ["v1"]\n' + lc + "innovation_gate_sigma = 4.0\n")
    (tmp_path / "c.toml").write_text('prefix = "other"\nvehicles = ["v9"]\n' + lc)
    port = free_port()
    router = _router(port)
    procs = [router]
    try:
        for name in ("a", "b", "c"):
            procs.insert(0, _service(port, "--config", str(tmp_path / f"{name}.toml")))
        publisher = _client(port)
        token = publisher.liveliness().declare_token("fednav/ghost/sensor/alive")  # noqa: F841 (kept)
        status = _fleet("status", "--json", port=port)
        out, err = status.communicate(timeout=60)
        table = _fleet("status", port=port)
        text, _ = table.communicate(timeout=60)
        publisher.close()
    finally:
        rcs = _stop(*procs)
    assert rcs == [0] * len(procs)
    print(text)
    assert status.returncode == 1 and table.returncode == 1, out + err
    snap = json.loads(out)
    by_name = {v["vehicle"]: v for v in snap["vehicles"]}
    assert sorted(by_name) == ["ghost", "v1", "v2"]  # v9 is under the other prefix
    assert by_name["ghost"]["announced"] and not by_name["ghost"]["services"]
    assert not by_name["v1"]["announced"]  # (nothing publishes v1 and v2 here)
    assert by_name["v1"]["served_twice"] and len(by_name["v1"]["services"]) == 2
    assert by_name["v1"]["service"] is None
    assert not by_name["v2"]["served_twice"] and by_name["v2"]["service"] is not None
    a = by_name["v2"]["service"]
    (b,) = set(by_name["v1"]["services"]) - {a}
    services = {s["zid"]: s for s in snap["services"]}
    assert set(services) == {a, b}
    assert services[a]["vehicles"] == ["v1", "v2"] and services[b]["vehicles"] == ["v1"]
    # two services, two configurations: the first one listed is the reference, the other is named
    differs = [s for s in snap["services"] if s["config_differs"]]
    assert len(differs) == 1 and differs[0]["config_differs"] == "settings of pipeline(s) lc differ"
    assert len(snap["other_prefixes"]) == 1 and snap["other_prefixes"][0]["prefix"] == "other"
    problems = "\n".join(snap["problems"])
    assert f"vehicle v1 is served by 2 services: {', '.join(sorted((a, b)))}" in problems
    assert "configuration differs" in problems
    assert "another prefix 'other'" in problems
    assert "vehicle ghost is published (its publisher announces it) but no service serves it" in problems
    assert "published, not served" in text
    assert "(twice!)" in text and "problems:" in text


def test_config_difference_in_words():
    lc = {"name": "lc", "kind": "loosely_coupled", "innovation_gate_sigma": 5.0}
    tc = {"name": "tc", "kind": "tightly_coupled"}
    ref = {"prefix": "fednav", "pipelines": [lc]}
    assert config_difference(ref, ref) == ""
    assert config_difference({"prefix": "x", "pipelines": [lc]}, ref) == "prefix 'x' vs 'fednav'"
    assert (
        config_difference({"prefix": "fednav", "pipelines": [lc, tc]}, ref)
        == "pipelines lc (loosely_coupled), tc (tightly_coupled) vs lc (loosely_coupled)"
    )
    changed = dict(lc, innovation_gate_sigma=4.0)
    assert config_difference({"prefix": "fednav", "pipelines": [changed]}, ref) == (
        "settings of pipeline(s) lc differ"
    )


def test_config_difference_names_the_navigation_settings_beyond_the_pipelines():
    """The settings that put services in different fleet groups (config.navigation_settings: the IMU
    model, the solution rate, ...) are a difference too: a service with another IMU grade and 1 Hz
    solutions was shown with the configuration "same" (and its vehicles "served twice")."""
    lc = {"name": "lc", "kind": "loosely_coupled"}
    ref = {
        "prefix": "fednav",
        "pipelines": [lc],
        "imu": {"grade": "tactical"},
        "output": {"solution_rate_hz": 10},
    }
    other = dict(ref, imu={"grade": "consumer"}, output={"solution_rate_hz": 1})
    assert config_difference(other, ref) == "imu, solution_rate_hz differ"
    assert config_difference(dict(ref, vehicles=["x"], zenoh={"mode": "peer"}), ref) == ""  # not navigation
    assert fleet_mod._signature(other) != fleet_mod._signature(ref)


def test_status_names_services_of_different_fleet_groups(tmp_path):
    """Two fleet members whose ``[fleet] group`` differs (a typo) do not share the fleet: each serves
    every vehicle. fednav-fleet status names the groups (not only each vehicle "served twice", with
    both configurations "same")."""
    member = 'vehicles = ["*"]\n[zenoh]\nmode = "client"\n[fleet]\nsharding = "rendezvous"\n'
    (tmp_path / "a.toml").write_text(member)
    (tmp_path / "b.toml").write_text(member + 'group = "fleet-typo"\n')
    port = free_port()
    procs = [_router(port)]
    try:
        for name in ("a", "b"):
            procs.insert(0, _service(port, "--config", str(tmp_path / f"{name}.toml")))
        status = _fleet("status", "--json", port=port)
        out, err = status.communicate(timeout=60)
    finally:
        rcs = _stop(*procs)
    assert rcs == [0] * len(procs)
    assert status.returncode == 1, out + err
    snap = json.loads(out)
    groups = {s["zid"]: s["fleet_group"] for s in snap["services"]}
    assert len(groups) == 2 and "fleet-typo" in groups.values(), groups
    (problem,) = [p for p in snap["problems"] if "fleet groups" in p]
    assert "fleet-typo" in problem and all(z in problem for z in groups), problem


def test_command_line_errors():
    for args, text in (
        (["status", "--connect", "tcp:127.0.0.1:1"], "invalid Zenoh endpoint"),
        (["record", "-o", "x.rrd", "--rate", "0"], "--rate 0.0"),
        (["status", "--zenoh-config", "/nonexistent.json5"], "no such file"),
        (["record", "-o", "x.rrd", "--wait", "-1"], "--wait -1.0"),
    ):
        r = subprocess.run(
            [sys.executable, "-m", "fednav.dashboards.fleet", *args],
            capture_output=True,
            text=True,
            timeout=60,
        )
        assert r.returncode == 2 and text in r.stderr, (args, r.stderr)


def test_no_service_is_flagged():
    port = free_port()
    router = _router(port)
    try:
        r = _fleet("status", "--json", "--timeout", "1", port=port)
        out, _ = r.communicate(timeout=60)
    finally:
        _stop(router)
    snap = json.loads(out)
    assert r.returncode == 1
    assert snap["vehicles"] == [] and snap["services"] == []
    assert snap["problems"] == ["no fednav service found under prefix 'fednav'"]


def test_a_recorder_waits_for_its_router_and_the_fleet_survives_a_router_restart(tmp_path):
    """``fednav-fleet record`` started before its router waits for it (``--wait``). The router
    then stops for 3 s while a vehicle is served and starts again on the same endpoint: the
    service, the fleet simulator, a plain reader and the recorder are Zenoh clients of it and
    reconnect by themselves; Solutions reach the reader again, 'aided' once the vehicle's fixes
    verify its new start, the service says in its log that the vehicle's INS was lost to the gap,
    the simulator exits 4 (what it published meanwhile reached nobody), every other process 0."""
    port = free_port()
    rrd = tmp_path / "fleet.rrd"
    record = _fleet("record", "-o", str(rrd), "--duration", "30", "--rate", "2", "--wait", "30", port=port)
    time.sleep(1.0)  # the recorder is waiting for a router that is not there yet
    assert record.poll() is None
    router = _router(port)
    procs: list[Proc] = [router]
    arrivals: list[float] = []
    watcher = None
    try:
        procs.insert(0, _service(port, "--vehicle", "*"))
        watcher = _client(port)
        statuses: list[tuple[float, str]] = []

        def on_solution(sample) -> None:
            arrivals.append(time.monotonic())
            statuses.append((arrivals[-1], json.loads(sample.payload.to_bytes())["status"]))

        watcher.declare_subscriber("fednav/*/nav/lc/solution", on_solution)
        sim = _fleet_sim(port, 1, 20)
        procs.insert(0, sim)
        deadline = time.monotonic() + 30
        while len(arrivals) < 30 and time.monotonic() < deadline:  # 3 s of Solutions at 10 Hz
            time.sleep(0.2)
        assert len(arrivals) >= 30, procs[1].output()
        assert router.p.poll() is None
        router.signal(signal.SIGTERM)
        assert router.wait(timeout=30) == 0, router.output()
        down = time.monotonic()
        time.sleep(3.0)
        router = _router(port)
        procs[-1] = router
        up = time.monotonic()
        deadline = up + 30
        while not any(t > up and st == "aided" for t, st in statuses) and time.monotonic() < deadline:
            time.sleep(0.2)
        back = [t for t in arrivals if t > up]
        assert back, "no Solution after the router restarted"
        assert procs[1].wait_for("INS lost", timeout=30), procs[1].output()
        sim_rc = sim.wait(timeout=60)  # to the end of its 20 s
        procs.remove(sim)
    finally:
        rcs = _stop(*procs)
        if watcher is not None:
            watcher.close()
        record.send_signal(signal.SIGINT)
        rec_out, rec_err = record.communicate(timeout=60)
    assert rcs == [0] * len(procs), [p.output() for p in procs]
    # what it published while the router was down reached nobody, and it says so
    assert sim_rc == 4 and "the subscribers went away" in sim.output(), sim.output()
    aided = [t for t, st in statuses if t > up and st == "aided"]
    print(
        f"router down {up - down:.1f} s; Solutions again {back[0] - up:.2f} s and 'aided' again "
        f"{aided[0] - up:.2f} s after it came back; after it: {[st for t, st in statuses if t > up][:5]}"
    )
    assert aided and aided[0] - up < 20.0
    lost = [ln for ln in procs[0].output().splitlines() if "INS lost" in ln]
    # a gap longer than [intake] future_window_s (2 s): the stream resumed that far ahead
    assert lost and "vehicle veh000" in lost[0] and "the IMU stream resumed" in lost[0], lost
    # it saw the fleet empty before the service started and while the router was down: flagged
    assert record.returncode == 1, rec_out + rec_err
    assert "1 vehicle(s), 1 service(s)" in rec_out, rec_out
    # ... and, when the simulator's session came back before the service's, its vehicle
    # published (announced) with no service serving it: true for that moment, and nothing else
    seen = [ln.split("problem seen: ", 1)[1] for ln in rec_out.splitlines() if "problem seen: " in ln]
    assert any("no fednav service found" in p for p in seen), rec_out
    assert all(
        "no fednav service found" in p
        or p == "vehicle veh000 is published (its publisher announces it) but no service serves it"
        for p in seen
    ), rec_out
    rows, _, _, _ = _read(rrd)
    assert rows.get("/fleet/veh000/position", 0) >= 4, rows


def test_a_recorder_without_its_router_gives_up_after_its_wait():
    port = free_port()
    t0 = time.monotonic()
    r = subprocess.run(
        [sys.executable, "-m", "fednav.dashboards.fleet", "record", "-o", "x.rrd", "--wait", "1.5"]
        + ["--connect", f"tcp/127.0.0.1:{port}"],
        capture_output=True,
        text=True,
        timeout=60,
    )
    assert r.returncode == 2, r.stderr
    assert "answered on tcp/127.0.0.1" in r.stderr and "within 1.5 s" in r.stderr, r.stderr
    assert time.monotonic() - t0 >= 1.5


def _series_times(rrd: Path, entity: str) -> list[tuple[float, float]]:
    """(wall_time as Unix seconds, value) of each temporal row of one Scalars entity, in time order."""
    from rerun.chunk import RrdReader

    reader = RrdReader(rrd)
    out: list[tuple[float, float]] = []
    for ch in reader.stream(store=reader.recordings()[0]):
        if ch.is_static or ch.entity_path != entity:
            continue
        batch: pa.RecordBatch = ch.to_record_batch()
        ns = batch.column("wall_time").cast(pa.int64()).to_pylist()
        values = pc.list_element(batch.column("Scalars:scalars"), 0).to_pylist()
        out += [(t / 1e9, v) for t, v in zip(ns, values, strict=True)]
    return sorted(out)


def test_a_killed_service_leaves_the_recorded_load(tmp_path):
    """Two services serving ``*`` (each serves both vehicles: no sharding), ``record --rate 2``
    running; one service is killed (SIGKILL: no goodbye). Its ``/load/vehicles/{zid}`` series
    ends within a few seconds (a 0 where it left, nothing after), the other service's goes on."""
    port = free_port()
    router = _router(port)
    procs = [router]
    watcher = _client(port)
    zids: list[str] = []

    def on_health(sample) -> None:
        z = str(sample.key_expr).split("/")[2]
        if z not in zids:
            zids.append(z)

    sub = watcher.declare_subscriber("fednav/_services/*/health", on_health)
    rrd = tmp_path / "fleet.rrd"
    doomed = None

    def wait_zids(n: int) -> None:
        deadline = time.monotonic() + 20
        while len(zids) < n and time.monotonic() < deadline:
            time.sleep(0.1)
        assert len(zids) == n, zids

    try:
        procs.insert(0, _service(port, "--vehicle", "*"))
        wait_zids(1)
        doomed = _service(port, "--vehicle", "*")
        wait_zids(2)
        kept_zid, doomed_zid = zids
        sim = _fleet_sim(port, 2, 40)
        procs.insert(0, sim)
        record = _fleet("record", "-o", str(rrd), "--duration", "14", "--rate", "2", port=port)
        time.sleep(6.0)  # a few snapshots with both services
        assert record.poll() is None
        doomed.p.kill()
        doomed.wait(timeout=30)
        killed = time.time()
        rec_out, rec_err = record.communicate(timeout=60)
    finally:
        if doomed is not None:
            doomed.kill()  # only if a failure left it running
        sub.undeclare()
        watcher.close()
        rcs = _stop(*procs)
    assert rcs[1:] == [0, 0], [p.output() for p in procs]  # the kept service and the router
    assert record.returncode in (0, 1), rec_out + rec_err  # 1: every vehicle served twice
    rows, _, scalars, _ = _read(rrd)
    gone = _series_times(rrd, f"/load/vehicles/{doomed_zid}")
    kept = _series_times(rrd, f"/load/vehicles/{kept_zid}")
    print(
        f"killed at {killed:.1f}; its load: {[(round(t - killed, 1), v) for t, v in gone]}; "
        f"the other's last row {kept[-1][0] - killed:.1f} s after"
    )
    assert rows[f"/load/vehicles/{doomed_zid}"] == len(gone)
    assert [v for t, v in gone if t < killed - 0.5][-2:] == [2.0, 2.0], gone  # it was counted
    # its series ends: a 0 where it left (its token went with its link; or 3 s without
    # ServiceHealth), nothing after it
    assert gone[-1][0] <= killed + 4.0, gone
    assert gone[-1][1] == 0.0 and scalars[f"/load/vehicles/{doomed_zid}"][-1] == 0.0
    assert [v for t, v in gone if t > killed] in ([0.0], [2.0, 0.0], [2.0, 2.0, 0.0]), gone
    # the recording goes on with the other service alone: the load adds up to the fleet's 2
    assert kept[-1][0] > killed + 6.0, kept
    assert all(v == 2.0 for t, v in kept if t > killed + 1.0), kept


def test_a_zenoh_storage_on_the_fleets_keys_is_no_service():
    """A plain Zenoh storage (the latest sample of every key under ``fednav/**``, answering
    queries there) replies to ``fednav-fleet status``'s solution queries beside the service: it
    holds no ``fednav/_services/{zid}`` token, so it is no service. Nothing is served twice, it
    is named once under ``other_repliers`` (and on one line of the table), exit 0."""
    import threading

    port = free_port()
    router = _router(port)
    procs = [router]
    storage = _client(port)
    latest: dict[str, bytes] = {}
    lock = threading.Lock()

    def keep(sample) -> None:
        with lock:
            latest[str(sample.key_expr)] = sample.payload.to_bytes()

    def answer(query) -> None:
        with lock:
            items = list(latest.items())
        for key, payload in items:
            if zenoh.KeyExpr(key).intersects(query.key_expr):
                query.reply(key, payload)

    sub = storage.declare_subscriber("fednav/**", keep)
    qbl = storage.declare_queryable("fednav/**", answer)
    storage_zid = str(storage.zid())
    solutions = ["fednav/veh000/nav/lc/solution", "fednav/veh001/nav/lc/solution"]
    try:
        procs.insert(0, _service(port, "--vehicle", "*"))
        sim = _fleet_sim(port, 2, 40)
        procs.insert(0, sim)
        deadline = time.monotonic() + 30
        while not all(k in latest for k in solutions) and time.monotonic() < deadline:
            time.sleep(0.2)
        assert all(k in latest for k in solutions), sorted(latest)[:20]
        # the storage does answer a solution query of another client, with its own zid
        asker = _client(port)
        try:
            replies = [
                str(r.replier_id.zid)
                for r in asker.get(
                    "fednav/*/nav/*/solution",
                    timeout=3.0,
                    target=zenoh.QueryTarget.ALL,
                    consolidation=zenoh.ConsolidationMode.NONE,
                )
                if r.ok is not None and r.replier_id is not None
            ]
        finally:
            asker.close()
        assert replies.count(storage_zid) == 2, replies
        snap, deadline = None, time.monotonic() + 20
        while time.monotonic() < deadline:  # until the service answers for both vehicles
            status = _fleet("status", "--json", port=port)
            out, err = status.communicate(timeout=60)
            snap = json.loads(out)
            if len(snap["vehicles"]) == 2 and all(v["services"] for v in snap["vehicles"]):
                break
            time.sleep(0.5)
        table = _fleet("status", port=port)
        text, text_err = table.communicate(timeout=60)
    finally:
        sub.undeclare()
        qbl.undeclare()
        storage.close()
        # one after the other, the router last (this test is about status, not shutdown: once in
        # four CI runs the service, SIGTERMed together with the router and the simulator under
        # load, had not exited 60 s later; noted in docs/fleet.md, not understood yet)
        rcs = [rc for p in procs for rc in _stop(p)]
    assert rcs[1:] == [0, 0], [p.output() for p in procs]
    print(text)
    assert status.returncode == 0, out + err
    assert table.returncode == 0, text + text_err
    assert [v["vehicle"] for v in snap["vehicles"]] == ["veh000", "veh001"]
    (service,) = snap["services"]
    assert service["zid"] != storage_zid and service["vehicles"] == ["veh000", "veh001"]
    for v in snap["vehicles"]:
        assert not v["served_twice"] and v["services"] == [service["zid"]], v
        assert list(v["by_service"]) == [service["zid"]]
    assert snap["other_repliers"] == [storage_zid]
    assert snap["problems"] == []
    lines = [ln for ln in text.splitlines() if storage_zid in ln]
    assert len(lines) == 1 and lines[0].startswith("other repliers"), text
    assert "(twice!)" not in text
