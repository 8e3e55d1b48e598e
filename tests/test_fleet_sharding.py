"""Services sharing a fleet behind a Zenoh router ([fleet] sharding = "rendezvous"): every vehicle
served once, failover after kill -9 with the state handed over, a joining service takes its share
back (real processes: fednav-router, fednav-service x3, fednav-sim fleet, a plain Zenoh client)."""

from __future__ import annotations

import functools
import json
import math
import signal
import sys
import time

import numpy as np
import pytest

from fednav.service import fleet
from fednav.simulators.fleet import vehicle_names
from fednav.simulators.fleet_watch import FleetWatch
from fednav.simulators.processes import Proc, free_port, stop_all

from .scenario_utils import fleet_status, split_zids, wait_until

#: the services are polled every 0.2 s
_wait = functools.partial(wait_until, poll_s=0.2)

pytestmark = pytest.mark.integration

N = 6


def _router(port: int) -> Proc:
    r = Proc([sys.executable, "-m", "fednav.service.router", "--listen", f"tcp/127.0.0.1:{port}"], "router")
    assert r.wait_for("fednav-router ready", timeout=30), r.output()
    return r


def _service(port: int, cfg, zid: str, tmp_path) -> Proc:
    """A service in client mode behind the router (no listener of its own), under Zenoh id ``zid``."""
    zc = tmp_path / f"zenoh-{zid}.json5"
    zc.write_text(f'{{ id: "{zid}" }}\n')
    args = [
        sys.executable,
        "-m",
        "fednav.service",
        "--config",
        str(cfg),
        "--no-record",
        "--zenoh-config",
        str(zc),
    ]
    p = Proc(args + ["--connect", f"tcp/127.0.0.1:{port}"], "fednav-service")
    assert p.wait_for("fednav-service ready", timeout=60), p.output()
    return p


def _fleet_sim(port: int, *args: str) -> Proc:
    """``fednav-sim fleet`` of N vehicles at 1 Hz fixes for 120 s (``args`` added), once publishing."""
    gen = Proc(
        [sys.executable, "-m", "fednav.simulators", "fleet", "--vehicles", str(N), "--duration", "120"]
        + ["--fix-rate", "1", *args, "--connect", f"tcp/127.0.0.1:{port}"],
        "fleet",
    )
    if not gen.wait_for("publishing", timeout=60):
        gen.kill()
        raise AssertionError(gen.output())
    return gen


def _zid(proc: Proc) -> str:
    """The Zenoh id a service logs when it starts."""
    return proc.output().split("fednav-service up: zid=", 1)[1].split()[0]


def test_fleet_shared_by_rendezvous_with_failover_handover_and_rejoin(tmp_path):
    cfg = tmp_path / "svc.toml"
    cfg.write_text(
        'vehicles = ["*"]\npipelines = [{ name = "lc", kind = "loosely_coupled" }]\n'
        '[zenoh]\nmode = "client"\n[fleet]\nsharding = "rendezvous"\nhandover_period_s = 0.5\n'
    )
    port = free_port()
    router = _router(port)
    procs = [router]
    bus = FleetWatch(port)
    names = vehicle_names(N)
    try:
        ids = split_zids(vehicle_names(N), 3)
        a, b = _service(port, cfg, ids[0], tmp_path), _service(port, cfg, ids[1], tmp_path)
        procs += [a, b]
        gen = Proc(
            [
                sys.executable,
                "-m",
                "fednav.simulators",
                "fleet",
                "--vehicles",
                str(N),
                "--duration",
                "120",
                "--speed",
                "2",
                "--truth",
                "--fix-rate",
                "1",
                "--connect",
                f"tcp/127.0.0.1:{port}",
            ],
            "fleet",
        )
        procs.append(gen)
        assert gen.wait_for("publishing", timeout=60), gen.output()
        # settled: two services, each vehicle on exactly one of them
        t_settle = time.monotonic() + 4.0
        assert _wait(lambda: len(bus.assignment(t_settle)) == 2 and time.monotonic() > t_settle + 1.5, 20)
        asg = bus.assignment(t_settle)
        served = sorted(v for vs in asg.values() for v in vs)
        assert served == names, asg
        members = sorted(asg)
        assert members == sorted(ids[:2]), asg  # the ids set in their Zenoh configs
        for z, vs in asg.items():  # the assignment is the rendezvous one over the live services
            assert sorted(vs) == sorted(v for v in names if fleet.owner(v, members) == z), asg
        wall_settled = time.monotonic()
        time.sleep(3.0)
        for v in names:
            assert bus.duplicates(v, wall_settled) == 0, v
        clean = np.concatenate([bus.h_errors(v, 0, math.inf) for v in names])
        assert clean.size > 50
        bound = max(3.0 * float(np.percentile(clean, 95)), 5.0)
        # kill -9 the service holding the most vehicles: its vehicles come back from the other
        victim_zid = max(asg, key=lambda z: len(asg[z]))
        moved = asg[victim_zid]
        victim = a if victim_zid in a.output() else b
        assert victim_zid in victim.output()
        victim.kill()
        t_kill = time.monotonic()
        last = {v: bus.last_t(v) for v in moved}
        assert _wait(lambda: all(bus.last_t(v) > last[v] + 0.5 for v in moved), 10), (
            "no solutions after failover"
        )
        gap = time.monotonic() - t_kill
        assert gap < 5.0, gap
        # handed over, not cold: errors stay under the nominal bound from the first solution on
        assert _wait(lambda: all(bus.last_t(v) > last[v] + 4.0 for v in moved), 10)
        survivor = b if victim is a else a
        for v in moved:
            assert f"vehicle {v} handed over from service {victim_zid}" in survivor.output(), v
            e = bus.h_errors(v, last[v], math.inf)
            assert e.size >= 2, (v, e)
            assert e.max() < bound, (v, e.max(), bound)
        # a new service joins and takes its share back, again handed over
        c = _service(port, cfg, ids[2], tmp_path)
        procs.append(c)
        t_join = time.monotonic()
        # joined: it listens 1.5 handover periods before its token, then serves its share (its
        # Health names its vehicles); on a loaded machine its start alone can take seconds
        assert _wait(
            lambda: (len(asg := bus.assignment(t_join + 2.0)) == 2 and all(asg.values()))
            and time.monotonic() > t_join + 4.0,
            30,
        ), bus.assignment(t_join + 2.0)
        asg2 = bus.assignment(t_join + 2.0)
        assert sorted(v for vs in asg2.values() for v in vs) == names, asg2
        assert all(asg2.values()), asg2  # both services have vehicles
        time.sleep(2.0)
        for v in names:
            assert bus.duplicates(v, t_join + 4.0) == 0, v
            e = bus.h_errors(v, bus.last_t(v) - 5.0, math.inf)
            assert e.size >= 2, (v, e)
            assert e.max() < bound, (v, e.max(), bound)
        taken = [v for v in names if v in asg2.get(_zid(c), [])]
        assert taken, asg2
        for v in taken:  # the joining service started them from the survivor's states
            assert f"vehicle {v} handed over from service {_zid(survivor)}" in c.output(), v
    finally:
        stop_all(procs)
        bus.close()


def _status(port: int) -> tuple[int, dict]:
    import json

    p = fleet_status(port)
    return p.returncode, json.loads(p.stdout)


def test_a_full_member_passes_new_vehicles_on_and_status_names_what_nobody_takes(tmp_path):
    """Two services of a fleet group, one with ``max_vehicles = 2`` and a rendezvous share of four
    of six vehicles: it serves two, the other service the four others (each vehicle once), and
    ``fednav-fleet status`` shows it full with no problem. With the roomy service gone, the full one
    keeps its two and refuses the rest: status lists each refused vehicle as not served, exit 1."""
    names = vehicle_names(N)
    small, big = next(
        (a, b)
        for i in range(1, 10_000)
        for a, b in [(f"fed{i:029x}", f"fee{i:029x}")]
        if sum(fleet.owner(v, [a, b]) == a for v in names) >= 4
    )
    base = '[zenoh]\nmode = "client"\n[fleet]\nsharding = "rendezvous"\nhandover_period_s = 0.5\n'
    head = 'vehicles = ["*"]\npipelines = [{ name = "lc", kind = "loosely_coupled" }]\n'
    cfg_small, cfg_big = tmp_path / "small.toml", tmp_path / "big.toml"
    cfg_small.write_text(head + "[intake]\nmax_vehicles = 2\n" + base)
    cfg_big.write_text(head + base)
    port = free_port()
    router = _router(port)
    procs = [router]
    bus = FleetWatch(port)
    try:
        a = _service(port, cfg_small, small, tmp_path)
        b = _service(port, cfg_big, big, tmp_path)
        procs += [a, b]
        procs.append(_fleet_sim(port))

        def settled() -> bool:
            asg = bus.assignment(time.monotonic() - 1.5)
            return len(asg.get(small, [])) == 2 and sorted(asg.get(small, []) + asg.get(big, [])) == names

        assert _wait(settled, 30), bus.assignment(0.0)
        t_settled = time.monotonic()
        time.sleep(3.0)
        assert settled(), bus.assignment(0.0)
        for v in names:
            assert bus.duplicates(v, t_settled) == 0, v
        assert "at max_vehicles (2): new vehicles are refused unless another service" in a.output()
        rc, snap = _status(port)
        assert rc == 0, snap["problems"]
        by_zid = {s["zid"]: s for s in snap["services"]}
        assert by_zid[small]["full"] and by_zid[small]["max_vehicles"] == 2, by_zid[small]
        assert not by_zid[big]["full"] and by_zid[big]["max_vehicles"] == 1000, by_zid[big]
        assert sorted(v["vehicle"] for v in snap["vehicles"] if v["services"]) == names
        kept = sorted(bus.assignment(time.monotonic() - 1.5)[small])
        # the roomy service stops: the full one keeps its two, the others are refused, named
        b.signal(signal.SIGTERM)
        assert b.wait(timeout=60) == 0, b.output()
        refused = sorted(set(names) - set(kept))

        def named() -> bool:
            rc, snap = _status(port)
            out = [v["vehicle"] for v in snap["vehicles"] if v.get("refused_by") == [small]]
            return rc == 1 and sorted(out) == refused

        assert _wait(named, 20), _status(port)
        rc, snap = _status(port)
        for v in refused:
            assert any(
                p.startswith(f"vehicle {v} is not served: refused by a service at its limit")
                for p in snap["problems"]
            )
        assert sorted(bus.assignment(time.monotonic() - 1.5)[small]) == kept
    finally:
        stop_all(procs)
        bus.close()


def _two_members(tmp_path, handover_period_s: float, *sim_args: str, intake: str = ""):
    """A router, a bus watcher, two fleet members (Zenoh ids from ``split_zids``, each serving some of
    the N vehicles) and ``fednav-sim fleet`` of N vehicles at 1 Hz fixes, publishing: (procs, bus,
    ids, a, b). ``intake``: the members' ``[intake]`` table's lines. The caller stops ``procs`` and
    closes ``bus``."""
    cfg = tmp_path / "svc.toml"
    cfg.write_text(
        'vehicles = ["*"]\npipelines = [{ name = "lc", kind = "loosely_coupled" }]\n'
        '[zenoh]\nmode = "client"\n[fleet]\nsharding = "rendezvous"\n'
        f"handover_period_s = {handover_period_s}\n[intake]\n{intake}\n"
    )
    port = free_port()
    procs = [_router(port)]
    bus = FleetWatch(port)
    bus.port = port  # (for fednav-fleet status)
    try:
        ids = split_zids(vehicle_names(N), 2)
        a, b = _service(port, cfg, ids[0], tmp_path), _service(port, cfg, ids[1], tmp_path)
        procs += [a, b]
        procs.append(_fleet_sim(port, *sim_args))
        assert _wait(lambda: len(bus.assignment(time.monotonic() - 1.5)) == 2, 30), bus.assignment(0.0)
    except BaseException:
        stop_all(procs)
        bus.close()
        raise
    return procs, bus, ids, a, b


def test_a_service_stopped_with_sigterm_hands_its_vehicles_over_from_their_last_state(tmp_path):
    """A member that stops (SIGTERM) publishes each vehicle's state as it goes: the survivor starts
    them from states a moment old, not from the last periodic one (``handover_period_s = 4`` here:
    up to 4 s old, carried over the gap with growing sigmas)."""
    import re

    names = vehicle_names(N)
    procs, bus, ids, a, b = _two_members(tmp_path, 4.0)
    try:
        time.sleep(8.0)  # past the joining period: every vehicle served, states published
        asg = bus.assignment(time.monotonic() - 1.5)
        moved = asg[ids[0]]
        assert moved and sorted(moved + asg[ids[1]]) == names, asg
        a.signal(signal.SIGTERM)
        assert a.wait(timeout=60) == 0, a.output()
        assert _wait(lambda: all(f"vehicle {v} handed over from service" in b.output() for v in moved), 15), (
            b.output()[-3000:]
        )
        ages = {
            m.group(1): float(m.group(2))
            for m in re.finditer(
                r"vehicle (\S+) handed over from service \S+ \(state (\S+) s old", b.output()
            )
        }
        assert set(moved) <= set(ages), ages
        assert all(ages[v] < 0.5 for v in moved), ages  # their states as the service stopped
    finally:
        stop_all(procs)
        bus.close()


def test_a_service_stopped_past_its_lease_resumes_its_vehicles_from_the_others_states(tmp_path):
    """A member stopped (SIGSTOP) longer than its Zenoh lease: the other member takes its vehicles
    (from scratch: the stopped one's states are too old by then) and, 10 s later, aids them. When
    it resumes (SIGCONT), the
    fleet gives the vehicles back to it, and its workers, lost after the IMU gap, start from the
    other member's fresher states (``VehicleWorker.resume_from_fleet``) instead of aligning anew
    (an operator's audit saw up to 27.7 m that way): the log says so for each, and the errors stay
    under three times the settled run's 95th percentile (one run: 1.5-3.9 m against a bound of
    12.7 m; aligning anew, the same run without the resume gave 6.8-16.4 m)."""
    names = vehicle_names(N)
    procs, bus, ids, a, b = _two_members(tmp_path, 0.5, "--truth")
    try:
        time.sleep(4.0)
        settled = {v: bus.last_t(v) for v in names}
        time.sleep(6.0)
        # the settled run's errors (after the vehicles' own alignment)
        clean = np.concatenate([bus.h_errors(v, settled[v], math.inf) for v in names])
        bound = max(3.0 * float(np.percentile(clean, 95)), 3.0)
        mine = bus.assignment(time.monotonic() - 1.5)[ids[0]]
        assert mine, bus.assignment(0.0)
        a.signal(signal.SIGSTOP)
        # past the 10 s lease: the other member serves every vehicle
        assert _wait(lambda: sorted(bus.assignment(time.monotonic() - 1.5).get(ids[1], [])) == names, 25), (
            bus.assignment(0.0)
        )
        time.sleep(10.0)  # the other member aligns them from scratch and aids them
        a.signal(signal.SIGCONT)
        t_resume = {v: bus.last_t(v) for v in mine}
        assert _wait(
            lambda: all(f"vehicle {v} handed over from service {ids[1]}" in a.output() for v in mine), 20
        ), a.output()[-3000:]
        time.sleep(6.0)
        for v in mine:
            e = bus.h_errors(v, t_resume[v], math.inf)
            assert e.size >= 3, (v, e)
            assert e.max() < bound, (v, e.max(), bound)
    finally:
        stop_all(procs)  # (continues a stopped process first)
        bus.close()


@pytest.mark.parametrize("subscribe", ["auto", "all"])
def test_a_member_hears_its_own_vehicles_and_only_the_low_rate_inputs_of_the_others(tmp_path, subscribe):
    """A fleet member subscribes per vehicle it serves (``[intake] subscribe = 'owned'``, what
    ``'auto'`` gives a member that is one process) and to every vehicle's low-rate inputs (fixes,
    InitialNav) to find its new ones: the IMU stream of a vehicle another member serves never
    reaches it (JSON IMU samples here: 200 a second per vehicle against one fix). With
    ``subscribe = 'all'`` every member receives every vehicle's inputs and drops the others'."""
    t0 = time.monotonic()
    procs, bus, ids, a, b = _two_members(
        tmp_path, 2.0, "--imu-batch", "1", intake=f'subscribe = "{subscribe}"'
    )
    try:
        time.sleep(6.0)  # past the joining period: every vehicle served by one member
        since = time.monotonic() - 1.5
        assert _wait(lambda: sorted(sum(bus.assignment(since).values(), [])) == vehicle_names(N), 20), (
            bus.assignment(0.0)
        )
        time.sleep(2.0)  # one more ServiceHealth of each member (1 s period)
        elapsed = time.monotonic() - t0
        asg = bus.assignment(time.monotonic() - 1.5)
        with bus.lock:
            health = {z: dict(bus.health[z]) for z in ids}
        for zid in ids:
            h, foreign = health[zid], N - len(asg[zid])
            assert foreign > 0, asg  # (split_zids gives each member some of the vehicles)
            elsewhere = h["inputs_served_elsewhere"]
            if subscribe == "auto":
                assert h["subscribed_vehicles"] == len(asg[zid]), (h, asg)
                # a foreign vehicle's fixes (1 Hz) and InitialNav, and what a subscription handed
                # over held in the moment of a membership change: no IMU stream
                assert elsewhere <= foreign * (elapsed + 60), (zid, elsewhere, foreign, elapsed)
            else:
                assert h["subscribed_vehicles"] is None, h
                assert elsewhere > foreign * 100 * 4, (zid, elapsed, elsewhere)  # their IMU samples
        for v in vehicle_names(N):  # every vehicle still solved, at its fixes' rate or faster
            with bus.lock:
                recent = [s for s in bus.sols.get(v, []) if s[0] >= time.monotonic() - 3.0]
            assert len(recent) >= 3, (v, len(recent))
        st = fleet_status(bus.port)  # fednav-fleet status names each member's subscriptions
        assert st.returncode == 0, st.stdout + st.stderr
        snap = json.loads(st.stdout)
        subscribed = {s["zid"]: s.get("subscribed") for s in snap["services"]}
        want = {z: (len(asg[z]) if subscribe == "auto" else None) for z in ids}
        assert subscribed == want, (subscribed, asg)
        if subscribe == "auto":  # a member goes: the other subscribes to its vehicles and serves them
            a.signal(signal.SIGTERM)
            assert a.wait(timeout=60) == 0, a.output()

            def b_has_all() -> bool:
                with bus.lock:
                    h = dict(bus.health[ids[1]])
                return h["subscribed_vehicles"] == N and sorted(h["active_vehicles"]) == vehicle_names(N)

            assert _wait(b_has_all, 20), bus.health[ids[1]]
            time.sleep(2.0)
            for v in vehicle_names(N):
                with bus.lock:
                    recent = [s for s in bus.sols.get(v, []) if s[0] >= time.monotonic() - 2.0]
                assert len(recent) >= 2, (v, len(recent))
    finally:
        stop_all(procs)
        bus.close()


_IMU_ONLY_PUBLISHER = """
import sys
from fednav.service.messages import ImuSample
from fednav.simulators.publisher import publish_stream

vehicle, port, n = sys.argv[1], sys.argv[2], int(sys.argv[3])
stream = (
    (
        f"fednav/{vehicle}/sensor/imu/imu0",
        ImuSample(t=1000.0 + 0.005 * k, dt_s=0.005, dtheta_rad=(0.0, 0.0, 0.0), dvel_mps=(0.0, 0.0, 0.049)),
    )
    for k in range(n)
)
out = publish_stream(stream, connect=[f"tcp/127.0.0.1:{port}"], imu_batch=1)
print("published", out["messages"], "drained", out["drained"], flush=True)
"""


def test_a_member_hears_an_announced_vehicle_from_its_first_imu_sample(tmp_path):
    """A vehicle that publishes only its IMU (no InitialNav, no fix: a ground start before its
    receiver's first fix) reaches its owner in a fleet whose members subscribe per vehicle they own
    (``subscribe = 'auto'``): fednav's publishers announce the vehicle (``keys.sensors_alive``), the
    owner subscribes to it, and the publisher waits for that subscription before its first sample.
    Every sample reaches the owner (none before its subscription is lost), none the other member.
    Without the announcement the vehicle is never heard: its IMU is no discovery key."""
    from fednav.service import keys

    cfg = tmp_path / "svc.toml"
    cfg.write_text(
        'vehicles = ["*"]\npipelines = [{ name = "lc", kind = "loosely_coupled" }]\n'
        '[zenoh]\nmode = "client"\n[fleet]\nsharding = "rendezvous"\nhandover_period_s = 1.0\n'
    )
    port, n = free_port(), 400
    procs = [_router(port)]
    bus = FleetWatch(port)
    health: list[dict] = []
    sub = None
    try:
        ids = split_zids(vehicle_names(N), 2)
        owner = fleet.owner("solo", ids)
        procs += [_service(port, cfg, z, tmp_path) for z in ids]
        assert _wait(lambda: all(z in bus.health for z in ids), 20), dict(bus.health)
        time.sleep(2.0)  # past the joining period (1.5 handover periods): both members own vehicles
        sub = bus.s.declare_subscriber(
            keys.service("solo", "health"), lambda s: health.append(json.loads(s.payload.to_bytes()))
        )
        pub = Proc([sys.executable, "-c", _IMU_ONLY_PUBLISHER, "solo", str(port), str(n)], "imu-only")
        procs.append(pub)
        assert pub.wait(timeout=60) == 0, pub.output()
        assert f"published {n} drained True" in pub.output(), pub.output()
        assert _wait(lambda: bool(health) and health[-1]["received"] == n, 10), health[-1:]
        h = health[-1]
        assert h["accepted"] == n and not h["rejected"], h  # every sample, from the first on
        with bus.lock:
            served = {z: list(bus.health[z]["active_vehicles"]) for z in ids}
        assert "solo" in served[owner], served
        other = next(z for z in ids if z != owner)
        assert "solo" not in served[other], served
    finally:
        if sub is not None:
            sub.undeclare()
        stop_all(procs)
        bus.close()


def test_handover_states_go_to_the_member_that_takes_the_vehicle_over(tmp_path):
    """Three members: each vehicle's handover states go to its heir only (the next member in its
    rendezvous order, ``keys.fleet_state_to``), not to every member; when a member stops
    (SIGTERM), each of its vehicles is handed over by its heir from its last state."""
    import re

    from fednav.service.config import ZenohConfig
    from fednav.service.transport.zenoh_io import make_config

    names = vehicle_names(N)
    cfg = tmp_path / "svc.toml"
    cfg.write_text(
        'vehicles = ["*"]\npipelines = [{ name = "lc", kind = "loosely_coupled" }]\n'
        '[zenoh]\nmode = "client"\n[fleet]\nsharding = "rendezvous"\nhandover_period_s = 1.0\n'
    )
    port = free_port()
    procs = [_router(port)]
    bus = FleetWatch(port)
    seen: list[tuple[str, str, str]] = []  # (addressee, vehicle, publishing service)
    broadcast: list[str] = []
    import zenoh

    spy = zenoh.open(make_config(ZenohConfig(mode="client"), listen=[], connect=[f"tcp/127.0.0.1:{port}"]))

    def on_to(sample) -> None:
        parts = str(sample.key_expr).split("/")
        seen.append((parts[4], parts[6], json.loads(sample.payload.to_bytes())["service"]))

    subs = [
        spy.declare_subscriber("fednav/_fleet/*/to/*/state/**", on_to),
        spy.declare_subscriber("fednav/_fleet/*/state/**", lambda s: broadcast.append(str(s.key_expr))),
    ]
    try:
        ids = split_zids(names, 3)
        members = [_service(port, cfg, z, tmp_path) for z in ids]
        procs += members
        procs.append(_fleet_sim(port))
        assert _wait(lambda: sorted(sum(bus.assignment(time.monotonic() - 1.5).values(), [])) == names, 30)
        time.sleep(4.0)  # settled: several periodic states of every vehicle
        since = len(seen)
        time.sleep(3.0)
        recent = seen[since:]
        assert {v for _, v, _ in recent} == set(names), recent
        for to, v, by in recent:
            order = fleet.ranked(v, ids)
            assert (by, to) == (order[0], order[1]), (v, by, to, order)  # owner -> heir, nobody else
        for z in ids:  # a member hears the states of the vehicles it is heir of, not all of them
            assert {v for to, v, _ in recent if to == z} < set(names), (z, recent)
        assert not broadcast, broadcast[:5]  # (the shared key of local shards: unused by a fleet)
        # a member stops: its heirs take its vehicles over from the states it published as it went
        gone = members[0]
        theirs = [v for v in names if fleet.ranked(v, ids)[0] == ids[0]]
        assert theirs, ids
        gone.signal(signal.SIGTERM)
        assert gone.wait(timeout=60) == 0, gone.output()
        heirs = {v: members[ids.index(fleet.ranked(v, ids)[1])] for v in theirs}
        assert _wait(
            lambda: all(
                f"vehicle {v} handed over from service {ids[0]}" in heirs[v].output() for v in theirs
            ),
            20,
        ), [m.output()[-2000:] for m in members[1:]]
        for v in theirs:
            m = re.search(rf"vehicle {v} handed over from service \S+ \(state (\S+) s old", heirs[v].output())
            assert m and float(m.group(1)) < 0.5, (v, m and m.group(0))
    finally:
        for s in subs:
            s.undeclare()
        spy.close()
        stop_all(procs)
        bus.close()


def test_a_member_with_local_shards_serves_its_share_once(tmp_path):
    """A fleet member run with ``--shards 2`` (SCALING.md: machines of 8 cores with ``--shards 8``,
    all in one fleet group) beside a plain member: every vehicle is served, once. Each shard is a
    member of the group under its own Zenoh id; shard 0, which alone receives the inputs, hands a
    vehicle's to the shard the fleet gives it. Before, shard 0 handed them by the local hash
    instead, and a vehicle whose two hashes disagreed reached a shard that did not own it (about
    a third of the fleet unserved, each "published, not served" in ``fednav-fleet status``). When
    the plain member stops, the shards take its vehicles, again once each."""
    n = 12
    names = vehicle_names(n)
    cfg = tmp_path / "svc.toml"
    cfg.write_text(
        'vehicles = ["*"]\npipelines = [{ name = "lc", kind = "loosely_coupled" }]\n'
        '[zenoh]\nmode = "client"\n[fleet]\nsharding = "rendezvous"\nhandover_period_s = 0.5\n'
    )
    port = free_port()
    procs = [_router(port)]
    bus = FleetWatch(port)

    def served() -> list[str]:
        return sorted(sum(bus.assignment(time.monotonic() - 1.5).values(), []))

    try:
        plain = _service(port, cfg, split_zids(names, 1)[0], tmp_path)
        procs.append(plain)
        sharded = Proc(
            [sys.executable, "-m", "fednav.service", "--config", str(cfg), "--no-record", "--shards", "2"]
            + ["--connect", f"tcp/127.0.0.1:{port}"],
            "fednav-service --shards 2",
        )
        procs.append(sharded)
        assert sharded.wait_for("fednav-service ready", timeout=60), sharded.output()
        procs.append(_fleet_sim(port, "--vehicles", str(n)))
        assert _wait(lambda: served() == names and len(bus.assignment(time.monotonic() - 1.5)) == 3, 30), (
            bus.assignment(time.monotonic() - 1.5),
            sharded.output()[-3000:],
        )
        code, snap = _status(port)
        assert code == 0, snap["problems"]
        assert sorted(v["vehicle"] for v in snap["vehicles"] if v["service"]) == names, snap["vehicles"]
        # the plain member stops: the two shards serve the whole fleet, each vehicle once
        plain.signal(signal.SIGTERM)
        assert plain.wait(timeout=60) == 0, plain.output()
        assert _wait(lambda: served() == names and len(bus.assignment(time.monotonic() - 1.5)) == 2, 20), (
            bus.assignment(time.monotonic() - 1.5)
        )
        t0 = {v: bus.last_t(v) for v in names}
        assert _wait(lambda: all(bus.last_t(v) > t0[v] + 1.0 for v in names), 10), {
            v: bus.last_t(v) - t0[v] for v in names
        }
        code, snap = _status(port)
        assert code == 0, snap["problems"]
    finally:
        stop_all(procs)
        bus.close()


def test_a_member_stopped_with_sigterm_publishes_no_solution_twice(tmp_path):
    """A member stopped with SIGTERM publishes its vehicles' last Solutions as it goes (README: "last
    solutions published"), but not one it has already published: with ImuBatches of 10 at 100 Hz
    every batch ends on the 10 Hz output grid, and the stop republished the Solution of the last
    batch's end under the same ``t``, one duplicate per moved vehicle on the bus."""
    names = vehicle_names(N)
    procs, bus, ids, a, b = _two_members(tmp_path, 0.5, "--imu-rate", "100")
    try:
        time.sleep(5.0)  # past the joining period: every vehicle served, Solutions flowing
        asg = bus.assignment(time.monotonic() - 1.5)
        moved = asg[ids[0]]
        assert moved and sorted(moved + asg[ids[1]]) == names, asg
        a.signal(signal.SIGTERM)
        assert a.wait(timeout=60) == 0, a.output()
        assert _wait(lambda: all(f"vehicle {v} handed over from service" in b.output() for v in moved), 15), (
            b.output()[-3000:]
        )
        t0 = {v: bus.last_t(v) for v in moved}
        assert _wait(lambda: all(bus.last_t(v) > t0[v] + 1.0 for v in moved), 10)
        assert {v: bus.duplicates(v, 0.0) for v in names} == dict.fromkeys(names, 0)
    finally:
        stop_all(procs)
        bus.close()
