"""Rendezvous assignment (service/fleet.py) and local shards (fednav-service --shards, service/shards.py)."""

from __future__ import annotations

import json
import signal
import subprocess
import sys
import threading
from collections import Counter

import pytest

from fednav.service import fleet
from fednav.simulators.fleet import vehicle_names

from .scenario_utils import wait_until


def test_rendezvous_is_balanced_over_1000_vehicles():
    names = vehicle_names(1000)
    for k in (2, 3, 4, 8):
        members = [fleet.shard_name(i) for i in range(k)]
        load = Counter(fleet.owner(v, members) for v in names)
        mean = 1000 / k
        assert set(load) == set(members)
        # a binomial count's spread: max/mean stays within ~4 sigma of 1 for these sizes
        assert max(load.values()) / mean < 1.0 + 4.0 * ((k - 1) / 1000) ** 0.5, (k, load)


def test_rendezvous_moves_only_the_dead_or_new_members_share():
    names = vehicle_names(1000)
    members = ["svc-a", "svc-b", "svc-c"]
    before = {v: fleet.owner(v, members) for v in names}
    after = {v: fleet.owner(v, ["svc-a", "svc-c"]) for v in names}  # svc-b died
    moved = {v for v in names if before[v] != after[v]}
    assert moved == {v for v in names if before[v] == "svc-b"}
    joined = {v: fleet.owner(v, [*members, "svc-d"]) for v in names}  # svc-d joined
    moved = {v for v in names if before[v] != joined[v]}
    assert moved and all(joined[v] == "svc-d" for v in moved)
    assert 150 < len(moved) < 350  # about a quarter of the fleet
    # every instance computes the same owner whatever the order of its member list
    assert all(fleet.owner(v, list(reversed(members))) == before[v] for v in names)
    assert fleet.owner("v1", []) is None


def _fleet_of(names: list[str], caps: dict[str, int]) -> dict[str, set[str]]:
    """Three services' views of one fleet driven as the service drives them: each takes the
    vehicles its view says are its own, in arrival order, until it is full; a full one declares
    what it holds, then ``full``, and the others hear both. Returns each service's vehicles."""
    held: dict[str, set[str]] = {m: set() for m in caps}
    views = {m: fleet.FleetView(m, holds_me=held[m].__contains__) for m in caps}
    for view in views.values():
        view.active = True
        for other in caps:
            view.update(other, True)
    for v in names:  # every vehicle's first input reaches every service
        owners = {m: view.owner(v) for m, view in views.items()}
        assert len(set(owners.values())) == 1, (v, owners)  # every view names the same owner
        m = owners["a"]
        if len(held[m]) < caps[m]:
            held[m].add(v)
            if len(held[m]) == caps[m]:  # full: holds first, then the full token
                views[m].set_me_full(True)
                for other, view in views.items():
                    if other != m:
                        for h in held[m]:
                            view.set_holds(m, h, True)
                        assert view.set_full(m, True)
    return held


def test_a_full_member_keeps_its_vehicles_and_the_rest_go_to_the_next_with_room():
    names = vehicle_names(60)
    plain = {v: fleet.owner(v, ["a", "b", "c"]) for v in names}
    held = _fleet_of(names, {"a": 5, "b": 1000, "c": 1000})
    assert len(held["a"]) == 5 and sum(map(len, held.values())) == 60  # every vehicle served once
    assert not (held["a"] & held["b"]) and not (held["b"] & held["c"]) and not (held["a"] & held["c"])
    spilled = {v for v in names if plain[v] == "a"} - held["a"]
    assert spilled  # a's share was above 5: the rest went to each vehicle's next member
    for v in spilled:
        nxt = fleet.ranked(v, ["a", "b", "c"])[1]
        assert v in held[nxt], (v, nxt)
    for v in set(names) - spilled:  # nothing else moved
        assert v in held[plain[v]]
    # every member full: the first one owns (and refuses: counted as vehicle_limit)
    small = _fleet_of(names, {"a": 5, "b": 5, "c": 5})
    assert sum(map(len, small.values())) == 15
    view = fleet.FleetView("c", holds_me=small["c"].__contains__)
    view.active = True
    for m in ("a", "b"):
        view.update(m, True)
        for h in small[m]:
            view.set_holds(m, h, True)
        view.set_full(m, True)
    view.set_me_full(True)
    for v in names:
        held_by = [m for m in small if v in small[m]]
        assert view.owner(v) == (held_by[0] if held_by else plain[v]), v
    # a full member that is no longer full gets its vehicles back; its holdings are forgotten
    assert view.set_full("a", False) and view.full_members() == ["b", "c"]
    assert all(view.owner(v) == "a" for v in names if plain[v] == "a")


def test_a_joining_service_is_named_owner_of_what_a_full_member_passes_on():
    """joiner_owner (where a member's handover states of a vehicle go besides its heir) applies
    capacity as owner() does: a vehicle whose first member is full and does not hold it goes to
    the next in its order, which may be the joining service."""
    names = vehicle_names(300)
    view = fleet.FleetView("a", holds_me=lambda v: True)
    view.active = True
    view.update("b", True)
    view.set_joining("j", True)
    plain = {v: fleet.owner(v, ["a", "b", "j"]) for v in names}
    assert {v for v in names if plain[v] == "j"} == {v for v in names if view.joiner_owner(v) == "j"}
    view.set_full("b", True)  # b full, holding nothing: its share goes down each vehicle's order
    passed = [v for v in names if fleet.ranked(v, ["a", "b", "j"])[:2] == ["b", "j"]]
    assert passed
    for v in names:
        order = [m for m in fleet.ranked(v, ["a", "b", "j"]) if m != "b"]
        assert view.joiner_owner(v) == ("j" if order[0] == "j" else None), v
    view.set_holds("b", passed[0], True)  # what a full member holds stays with it
    assert view.joiner_owner(passed[0]) is None


def test_shard_of_is_stable_and_covers_every_shard():
    names = vehicle_names(200)
    got = [fleet.shard_of(v, 4) for v in names]
    assert set(got) == {0, 1, 2, 3}
    assert got == [fleet.shard_of(v, 4) for v in names]
    assert all(fleet.shard_of(v, 1) == 0 for v in names)


@pytest.mark.integration
def test_two_shards_serve_each_vehicle_exactly_once(tmp_path):
    """Real processes: fednav-service --shards 2 (two processes) and the fleet simulator with 8
    vehicles: every vehicle gets solutions from exactly one shard (no duplicate solution times),
    status answers once per vehicle, and each shard writes its own complete recording."""
    import zenoh

    from fednav.simulators.processes import Proc, free_port, query_status, start_service, wait_idle

    from .plain_zenoh import client as zenoh_client

    cfg = tmp_path / "fleet.toml"
    cfg.write_text('vehicles = ["*"]\npipelines = [{ name = "lc", kind = "loosely_coupled" }]\n')
    port = free_port()
    rrd = tmp_path / "run.rrd"
    svc = start_service(port, config=cfg, rrd=rrd, extra=["--shards", "2"])
    session = zenoh_client(port)
    sols: dict[str, list[float]] = {}
    lock = threading.Lock()

    def on_sol(sample: zenoh.Sample) -> None:
        v = str(sample.key_expr).split("/")[1]
        with lock:
            sols.setdefault(v, []).append(json.loads(sample.payload.to_bytes())["t"])

    sub = session.declare_subscriber("fednav/*/nav/lc/solution", on_sol)
    health: dict[str, dict] = {}  # the latest ServiceHealth per shard (Zenoh id)

    def on_health(sample: zenoh.Sample) -> None:
        with lock:
            health[str(sample.key_expr).split("/")[2]] = json.loads(sample.payload.to_bytes())

    hsub = session.declare_subscriber("fednav/_services/*/health", on_health)
    n = 8
    names = vehicle_names(n)
    try:
        gen = Proc(
            [
                sys.executable,
                "-m",
                "fednav.simulators",
                "fleet",
                "--vehicles",
                str(n),
                "--duration",
                "20",
                "--speed",
                "4",
                "--connect",
                f"tcp/127.0.0.1:{port}",
            ],
            "fleet",
        )
        assert gen.wait(timeout=120) == 0, gen.output()
        for v in names:  # every vehicle's messages run (a slow machine's service lags its input)
            wait_idle(port, vehicle=v, timeout_s=60)
        replies = {}
        for v in names:
            replies[v] = []
            for reply in session.get(f"fednav/{v}/service/status", timeout=5.0):
                if reply.ok is not None:
                    replies[v].append(json.loads(reply.ok.payload.to_bytes()))
        st = query_status(port, names[0])
        assert st is not None
        # shard 0 alone receives the inputs: it hands shard 1 its vehicles' (none lost), and no
        # shard receives another's vehicles' inputs to drop them
        assert wait_until(
            lambda: len(health) == 2
            and sorted(h["inputs_forwarded"] > 1000 for h in health.values()) == [0, 1],
            10.0,
        ), health
        for h in health.values():
            assert h["inputs_forward_lost"] == 0, h
            assert h["inputs_served_elsewhere"] == 0, h
    finally:
        hsub.undeclare()
        sub.undeclare()
        session.close()
        svc.signal(signal.SIGTERM)
        rc = svc.wait(timeout=90)
    assert rc == 0, svc.output()
    owners = {v: fleet.shard_of(v, 2) for v in names}
    assert set(owners.values()) == {0, 1}, owners  # both shards have vehicles
    for v in names:
        t = sols.get(v, [])
        assert len(t) > 150, (v, len(t))
        assert len(t) == len(set(t)), f"{v}: {len(t) - len(set(t))} solutions published twice"
        assert len(replies[v]) == 1, (v, replies[v])
        h = replies[v][0]["health"]
        assert h["pipelines"]["lc"]["status"] in ("aided", "coasting"), h
    # each shard's own recording, readable by Rerun's reader, holding only its vehicles
    from fednav.dashboards.inspect import read_series

    for i, path in enumerate((rrd, tmp_path / "run.shard1.rrd")):
        assert path.is_file(), path
        _, series = read_series(path)
        ents = set(series)
        mine = {v for v in names if owners[v] == i}
        assert all(any(e.startswith(f"/{v}/") for e in ents) for v in mine), (path, sorted(ents)[:20])
        assert not any(e.startswith(f"/{v}/") for v in set(names) - mine for e in ents), path


def test_a_shard_whose_shard_0_is_killed_stops_cleanly_with_its_recording(tmp_path):
    """Shard 0 killed outright (SIGKILL: no supervisor left to stop the others): the end of the
    shard's feed stops it like a signal, and its recording is complete."""
    import os
    import time

    from fednav.dashboards.inspect import read_series
    from fednav.simulators.processes import Proc, free_port, start_service

    cfg = tmp_path / "fleet.toml"
    cfg.write_text('vehicles = ["*"]\npipelines = [{ name = "lc", kind = "loosely_coupled" }]\n')
    port = free_port()
    rrd = tmp_path / "run.rrd"
    svc = start_service(port, config=cfg, rrd=rrd, extra=["--shards", "2"])
    with open(f"/proc/{svc.p.pid}/task/{svc.p.pid}/children") as f:
        (child,) = (int(x) for x in f.read().split())
    names = [v for v in vehicle_names(8) if fleet.shard_of(v, 2) == 1]
    assert names
    gen = Proc(
        [sys.executable, "-m", "fednav.simulators", "fleet", "--vehicles", "8", "--duration", "6"]
        + ["--speed", "4", "--connect", f"tcp/127.0.0.1:{port}"],
        "fleet",
    )
    assert gen.wait(timeout=120) == 0, gen.output()
    svc.p.kill()
    svc.wait(timeout=30)
    end = time.monotonic() + 60
    while time.monotonic() < end and os.path.exists(f"/proc/{child}") and _state(child) != "Z":
        time.sleep(0.2)
    assert not os.path.exists(f"/proc/{child}") or _state(child) == "Z", "the shard outlived shard 0"
    _, series = read_series(tmp_path / "run.shard1.rrd")
    assert any(e.startswith(f"/{names[0]}/") for e in series), sorted(series)[:10]


def _state(pid: int) -> str:
    try:
        with open(f"/proc/{pid}/stat") as f:
            return f.read().rsplit(")", 1)[1].split()[0]
    except OSError:
        return "gone"


def test_a_killed_shard_is_restarted_and_fed_again(tmp_path):
    """Shard 1 killed outright mid-run: shard 0 restarts it on a new pipe, counts what it could
    not hand over meanwhile, and the shard's vehicles get solutions again."""
    import os
    import time

    import zenoh

    from fednav.simulators.processes import Proc, free_port, start_service

    from .plain_zenoh import client as zenoh_client

    cfg = tmp_path / "fleet.toml"
    cfg.write_text('vehicles = ["*"]\npipelines = [{ name = "lc", kind = "loosely_coupled" }]\n')
    port = free_port()
    svc = start_service(port, config=cfg, extra=["--shards", "2"])
    with open(f"/proc/{svc.p.pid}/task/{svc.p.pid}/children") as f:
        (child,) = (int(x) for x in f.read().split())
    names = vehicle_names(6)
    theirs = [v for v in names if fleet.shard_of(v, 2) == 1]
    assert theirs
    session = zenoh_client(port)
    sols: dict[str, list[float]] = {}
    health: dict[str, dict] = {}
    lock = threading.Lock()

    def on_sol(sample: zenoh.Sample) -> None:
        with lock:
            sols.setdefault(str(sample.key_expr).split("/")[1], []).append(time.monotonic())

    def on_health(sample: zenoh.Sample) -> None:
        with lock:
            health[str(sample.key_expr).split("/")[2]] = json.loads(sample.payload.to_bytes())

    notes: dict[str, dict] = {}  # the latest Health notes per vehicle

    def on_vehicle_health(sample: zenoh.Sample) -> None:
        with lock:
            notes[str(sample.key_expr).split("/")[1]] = json.loads(sample.payload.to_bytes())["notes"]

    states: set[str] = set()  # vehicles whose handover state shard 1 has published

    def on_state(sample: zenoh.Sample) -> None:
        with lock:
            states.add(str(sample.key_expr).split("/")[4])

    subs = [
        session.declare_subscriber("fednav/*/nav/lc/solution", on_sol),
        session.declare_subscriber("fednav/_services/*/health", on_health),
        session.declare_subscriber("fednav/*/service/health", on_vehicle_health),
        session.declare_subscriber("fednav/_fleet/*/state/**", on_state),
    ]
    try:
        # 200 s at 2x: inputs still flow when the shard is killed, however slowly the machine ran
        # the steps before (with 30 s, and again with 60 s on a loaded machine, a fresh-clone CI
        # run reached the kill after the last input: nothing to lose, inputs_forward_lost stayed
        # 0); stopped once the test has seen enough, so a quick machine pays nothing for it
        gen = Proc(
            [sys.executable, "-m", "fednav.simulators", "fleet", "--vehicles", "6", "--duration", "200"]
            + ["--speed", "2", "--connect", f"tcp/127.0.0.1:{port}"],
            "fleet",
        )
        assert wait_until(lambda: all(len(sols.get(v, [])) > 20 for v in theirs), 60.0), sols.keys()
        assert wait_until(lambda: states >= set(theirs), 20.0), states  # each state published once
        assert states <= set(theirs)  # by shard 1, for its own vehicles only
        assert gen.p.poll() is None, "the fleet generator ended before the kill: nothing to lose"
        os.kill(child, signal.SIGKILL)
        killed = time.monotonic()
        lost = lambda: any(h.get("inputs_forward_lost", 0) > 0 for h in health.values())  # noqa: E731
        assert wait_until(lost, 20.0), health
        # restarted: its vehicles are served again, each from the last state the dead shard
        # published (handed to the new shard by shard 0 before any input), not aligned anew
        assert wait_until(
            lambda: all(any(t > killed + 1.0 for t in sols.get(v, [])) for v in theirs), 60.0
        ), {v: len(sols.get(v, [])) for v in theirs}
        assert wait_until(
            lambda: all(notes.get(v, {}).get("handed_over_from:shard1", 0) == 1 for v in theirs), 10.0
        ), {v: notes.get(v) for v in theirs}
        gen.signal(signal.SIGINT)  # stopped: exit 130 with a one-line message, no traceback
        # (a fresh-clone CI run, 2026-12-01, saw no exit within 60 s of the SIGINT: the suite had
        # been started with SIGINT ignored, which Python kept; service/stop_signals.py since)
        try:
            rc = gen.wait(timeout=60)
        except subprocess.TimeoutExpired:
            gen.signal(signal.SIGUSR1)  # (simulators/__main__.py: faulthandler prints every stack)
            time.sleep(2.0)
            gen.signal(signal.SIGKILL)
            gen.wait(timeout=30)
            raise AssertionError(f"the fleet generator did not stop on SIGINT:\n{gen.output()}") from None
        assert rc in (0, 130) and "Traceback" not in gen.output(), gen.output()
    finally:
        for sub in subs:
            sub.undeclare()
        session.close()
        svc.signal(signal.SIGTERM)
        rc = svc.wait(timeout=90)
    assert rc == 0, svc.output()
    assert "restarting it" in svc.output()


def test_shards_run_under_their_own_zenoh_ids_when_the_config_file_sets_one(tmp_path):
    """Real processes: ``--shards 2`` with a Zenoh config file that sets ``id`` (every shard gets
    shard 0's command line). Before, shard 1 opened its session under shard 0's id, its session to
    shard 0 never connected, and its vehicles' Solutions reached nobody without a word."""
    import zenoh

    from fednav.simulators.processes import Proc, free_port, start_service

    from .plain_zenoh import client as zenoh_client

    cfg = tmp_path / "fleet.toml"
    cfg.write_text('vehicles = ["*"]\npipelines = [{ name = "lc", kind = "loosely_coupled" }]\n')
    zcfg = tmp_path / "zenoh.json5"
    zcfg.write_text('{ id: "a1b2c3d4" }\n')
    port = free_port()
    svc = start_service(port, config=cfg, extra=["--shards", "2", "--zenoh-config", str(zcfg)])
    session = zenoh_client(port)
    seen: Counter = Counter()
    lock = threading.Lock()

    def on_sol(sample: zenoh.Sample) -> None:
        with lock:
            seen[str(sample.key_expr).split("/")[1]] += 1

    sub = session.declare_subscriber("fednav/*/nav/lc/solution", on_sol)
    names = vehicle_names(4)
    try:
        gen = Proc(
            [sys.executable, "-m", "fednav.simulators", "fleet", "--vehicles", "4", "--duration", "10"]
            + ["--speed", "4", "--connect", f"tcp/127.0.0.1:{port}"],
            "fleet",
        )
        assert gen.wait(timeout=120) == 0, gen.output()
        assert wait_until(lambda: all(seen[v] > 50 for v in names), 30.0), dict(seen)
    finally:
        sub.undeclare()
        session.close()
        svc.signal(signal.SIGTERM)
        rc = svc.wait(timeout=90)
    assert rc == 0, svc.output()
    owners = {v: fleet.shard_of(v, 2) for v in names}
    assert set(owners.values()) == {0, 1}, owners  # both shards have vehicles
    out = svc.output()
    assert "zid=a1b2c3d4" in out and out.count("zid=a1b2c3d4") < out.count("zid="), out[-2000:]
