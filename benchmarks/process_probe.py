"""Transient corruption through real processes, as an outside probe sees it.

``benchmarks/hardening.py`` injects its attacks into the engine in-process, in one stream order.
Here fednav-service runs as its own process on ``make demo``'s scenario (``demo_product``: its
three pipelines and its own faults) and four vehicles are published at ``--pace`` x real time,
each from its own plain Zenoh session, with the attacks from a second session of their own:

- ``clean``: the stream as it is (the reference: its 95th percentile of the horizontal error);
- ``burst``: 50 forged IMU samples (20 rad/s about x) slipped between the genuine ones at 70 s;
- ``inits``: 500 InitialNav in 2.5 s from 70 s, 20 m north, claiming 1 cm / 0.01 m/s / 0.01 deg,
  stamped at the newest Solution the attacker sees on the bus (current from the service's view);
- ``drift``: a forged fix stream under the receiver's key, half a period after each genuine fix,
  drifting 1 m/s north for 30 s from 70 s and claiming 1 m;
- ``close``: forged IMU samples close to the genuine ones: the attacker reads the genuine samples
  on the bus and publishes for each, as it sees it, its increments with 0.2 rad/s more yaw rate
  stamped half a period later, 50 from 70 s;
- ``close500``: the same with 0.05 rad/s more, 500 samples (5 s);
- ``race``: for each genuine sample it sees, the next one predicted on its own time stamp (the
  same increments, 0.05 rad/s more yaw rate), 500 from 70 s: one copy of each slot is taken, the
  other refused ``duplicate``, whichever arrives first;
- ``stamped``: the ``drift`` stream on the receiver's own time stamps: the attacker learns the
  fixes' cadence on the bus and publishes each forged fix when it sees the IMU sample two
  periods before the next genuine fix (a spoofer racing the receiver; usually ahead of it).
- ``outage``: no GNSS for 60 s from 70 s (fixes and raw epochs withheld by the vehicle's own
  publisher), then 5 s of fixes 50 m north (the receiver's solution jumping on return; its
  pseudoranges return as they are), as ``benchmarks/hardening.py``'s ``outage``. With it the
  scenario runs 200 s instead of 120 (straight on after its last turn) for every vehicle, so
  that 65 s follow the jump.

The ``close`` and ``stamped`` attackers key on what they see on the bus, so their messages reach
the service where they are meant to however far it runs behind the sensors (the others are
timed from the sensors' own stream).

``--attacks`` chooses the attacked vehicles (all by default; ``clean`` always runs).

Two sessions reach the service in an order no in-process run reproduces (the sensors' session is
busier than the forger's: its messages can arrive seconds of stream time later), so runs differ;
``--runs`` repeats the probe. Printed per run and pipeline: the peak horizontal error after the
attack, the time after its end until the error is back under the clean vehicle's 95th percentile
and stays under 1.5 times it, the epochs reported ``aided`` while the horizontal error exceeds 3x
its sigma or the height error 3x its own, and the vehicle's refusal counts.

Usage: .venv/bin/python benchmarks/process_probe.py [--runs 3] [--seed 5] [--pace 10]
"""

from __future__ import annotations

import argparse
import json
import math
import queue
import signal
import sys
import tempfile
import threading
import time
from pathlib import Path

import numpy as np
import zenoh

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(Path(__file__).resolve().parent))

from hardening import _shift_fix, demo_scenario, forged_init  # noqa: E402  (the attacks' messages)

from fednav.service import earth, keys  # noqa: E402
from fednav.service.messages import GnssFix, GnssRaw, ImuSample  # noqa: E402
from fednav.service.transport.zenoh_io import PUBLISHER_BLOCK_WAIT_S  # noqa: E402
from fednav.simulators.processes import free_port, query_status, start_service, wait_idle  # noqa: E402
from fednav.simulators.publisher import drain  # noqa: E402
from fednav.simulators.scenario import load_scenario  # noqa: E402
from fednav.simulators.stream import Simulation  # noqa: E402
from tests.plain_zenoh import client  # noqa: E402  (the tests' plain client: no fednav code)
from tests.test_hostile import Publisher  # noqa: E402  (reliable, blocking, waits for the subscriber)

AT_S = 70.0
#: the attacked vehicles and the end of each one's attack (s of the scenario)
ENDS = {
    "burst": AT_S + 0.6,
    "inits": AT_S + 2.5,
    "drift": AT_S + 30.0,
    "close": AT_S + 0.5,
    "close500": AT_S + 5.0,
    "race": AT_S + 5.0,
    "stamped": AT_S + 30.0,
    "outage": AT_S + 65.0,
}
#: the outage: GNSS withheld for OUTAGE_S, then JUMP_S of fixes JUMP_M north
OUTAGE_S, JUMP_S, JUMP_M = 60.0, 5.0, 50.0
#: ``close`` attacks: (extra yaw rate, rad/s; samples; on the next sample's own stamp)
CLOSE = {"close": (0.2, 50, False), "close500": (0.05, 500, False), "race": (0.05, 500, True)}
PIPELINES = ("lc", "fed", "tc_mhss")


def _moved(traj, t: float, north_m: float, dvn: float = 0.0):
    s = traj.state_at(t)
    r_m, _ = earth.radii(s.llh[0])
    return s, math.degrees(s.llh[0] + north_m / (r_m + s.llh[2])), s.vel_enu_mps + np.array([0.0, dvn, 0.0])


def _forged_fix(traj, t: float, t_rel: float) -> GnssFix:
    """The drifting fix at ``t`` (``t_rel`` s of the scenario): 1 m/s north from AT_S, claiming 1 m."""
    s, lat, vel = _moved(traj, t, 1.0 * (t_rel - AT_S), 1.0)
    return GnssFix(
        t=t,
        lat_deg=lat,
        lon_deg=math.degrees(s.llh[1]),
        height_m=float(s.llh[2]),
        vel_enu_mps=tuple(float(v) for v in vel),
        pos_std_enu_m=(1.0, 1.0, 1.0),
        vel_std_enu_mps=(0.1, 0.1, 0.1),
    )


def publish(sc, vehicle: str, port: int, t_wall0: float, seed: int, pace: float) -> int:
    # sessions that wait as fednav's own publishers do (PUBLISHER_BLOCK_WAIT_S): with Zenoh's 5 s,
    # a service busy with the other vehicles' backlog had the link of a vehicle's session closed
    # and the rest of its stream dropped (the "stall" of three or more attacked vehicles)
    genuine, attacker = client(port, PUBLISHER_BLOCK_WAIT_S), client(port, PUBLISHER_BLOCK_WAIT_S)
    pub, forged = Publisher(genuine), Publisher(attacker)
    k_imu, k_fix = keys.sensor(vehicle, "imu", "main"), keys.sensor(vehicle, "gnss_fix", "main")
    sim = Simulation(sc, seed=seed, vehicle=vehicle)
    traj = sim.truth.trajectory
    burst: list[ImuSample] = []
    sent = 0
    # the InitialNav attacker watches the vehicle's Solutions on the bus and stamps its messages
    # at their times: current from the service's view, however far the service runs behind the
    # sensors' session (stamped from the sensors' stream instead, they arrived tens of seconds
    # of stream time ahead of the IMU the service had reached, all refused `future`: the attack
    # never reached the filter)
    seen = queue.Queue()
    watch = attack = None  # (the subscriber kept: an undeclared subscriber's callback stops)
    if vehicle in CLOSE or vehicle == "stamped":
        watch, attack, sent_bus = _bus_forger(sc, vehicle, attacker, forged, traj)
    if vehicle == "inits":
        watch = attacker.declare_subscriber(
            keys.nav(vehicle, "lc", "solution"),
            lambda sample: seen.put(json.loads(sample.payload.to_bytes())["t"]),
        )
        sent_inits = [0]

        def attack_inits() -> None:
            """At each Solution seen in [AT_S, AT_S + 2.5 s) of the vehicle's time, the 20
            InitialNav (5 ms apart) up to the next one: 500 in 2.5 s, as the vehicle sees them."""
            deadline = time.monotonic() + 600.0
            while sent_inits[0] < 500 and time.monotonic() < deadline:
                try:
                    t = seen.get(timeout=1.0)
                except queue.Empty:
                    continue
                if t - sc.t0_gps_s >= AT_S + 2.5:
                    break
                if t - sc.t0_gps_s >= AT_S:
                    for j in range(20):
                        forged.put(keys.init(vehicle), forged_init(traj, t + 0.005 * j, 20.0).to_json())
                        sent_inits[0] += 1

        attack = threading.Thread(target=attack_inits, daemon=True)
        attack.start()
    try:
        for key, msg in sim:
            t_rel = msg.t - sc.t0_gps_s
            if isinstance(msg, ImuSample):
                delay = t_wall0 + t_rel / pace - time.monotonic()
                if delay > 0:
                    time.sleep(delay)
                if vehicle == "burst" and abs(t_rel - AT_S) < 0.005:
                    burst = [
                        msg.model_copy(update={"t": msg.t + 0.005 + 0.01 * k, "dtheta_rad": (0.2, 0.0, 0.0)})
                        for k in range(1, 51)
                    ]
                if burst and burst[0].t < msg.t + msg.dt_s:  # just before the genuine sample
                    forged.put(k_imu, burst.pop(0).to_json())
                    sent += 1
            if vehicle == "outage" and isinstance(msg, (GnssFix, GnssRaw)):
                if AT_S <= t_rel < AT_S + OUTAGE_S:
                    continue  # withheld
                if isinstance(msg, GnssFix) and AT_S + OUTAGE_S <= t_rel < AT_S + OUTAGE_S + JUMP_S:
                    msg = _shift_fix(msg, JUMP_M)
            pub.put(key, msg.to_json())
            if vehicle == "drift" and isinstance(msg, GnssFix) and AT_S <= t_rel < AT_S + 30.0:
                forged.put(k_fix, _forged_fix(traj, msg.t + 0.5, t_rel + 0.5).to_json())
                sent += 1
        if attack is not None:  # the service may reach the attack's time only after the stream
            if vehicle == "inits":
                attack.join()
                sent += sent_inits[0]
            else:
                drain(genuine, [keys.service(vehicle, "status")])  # the attacker has seen it all
                time.sleep(1.0)
                sent_bus[1].put(None)
                attack.join(timeout=60)
                sent += sent_bus[0][0]
            watch.undeclare()
        for session in (genuine, attacker):  # what is still queued reaches the service first
            drain(session, [keys.service(vehicle, "status")])
    finally:
        genuine.close()
        attacker.close()
    return sent


def _bus_forger(sc, vehicle: str, attacker: zenoh.Session, forged, traj):
    """The ``close`` / ``stamped`` attacker: a subscription to the vehicle's genuine IMU samples
    (and fixes) on the bus and a thread publishing the forged messages as it sees them. Returns
    (the subscriber, the thread, ([forged sent], its queue))."""
    k_imu, k_fix = keys.sensor(vehicle, "imu", "main"), keys.sensor(vehicle, "gnss_fix", "main")
    todo: queue.Queue = queue.Queue()
    sent = [0]
    fixes: list[float] = []  # the genuine fixes' times seen
    forged_at: set[float] = set()

    def on_sample(sample: zenoh.Sample) -> None:
        key = str(sample.key_expr)
        d = json.loads(sample.payload.to_bytes())
        if key == k_fix:
            fixes.append(d["t"])
            return
        if key != k_imu:
            return
        t, dt = d["t"], d["dt_s"]
        t_rel = t - sc.t0_gps_s
        if vehicle in CLOSE:
            rate, n, own_stamp = CLOSE[vehicle]
            if AT_S - 0.5 * dt <= t_rel < AT_S + (n - 0.5) * dt:
                a = d["dtheta_rad"]
                d.update(t=t + (dt if own_stamp else 0.5 * dt), dtheta_rad=[a[0], a[1], a[2] + rate * dt])
                todo.put((k_imu, json.dumps(d).encode()))
            return
        if len(fixes) < 2:  # stamped: the next fix from the cadence seen
            return
        t_next = fixes[-1] + (fixes[-1] - fixes[-2])
        rel = t_next - sc.t0_gps_s
        if AT_S <= rel < AT_S + 30.0 and t_next - 2.0 * dt <= t < t_next and t_next not in forged_at:
            forged_at.add(t_next)
            todo.put((k_fix, _forged_fix(traj, t_next, rel).to_json()))

    def run() -> None:
        while (item := todo.get()) is not None:
            forged.put(*item)
            sent[0] += 1

    subs = [
        attacker.declare_subscriber(k, on_sample, allowed_origin=zenoh.Locality.REMOTE)
        for k in (k_imu, k_fix)
    ]
    th = threading.Thread(target=run, daemon=True)
    th.start()
    return _Subs(subs), th, (sent, todo)


class _Subs:
    def __init__(self, subs):
        self.subs = subs

    def undeclare(self) -> None:
        for s in self.subs:
            s.undeclare()


def one_run(seed: int, pace: float, workdir: Path, attacks: tuple[str, ...] = tuple(ENDS)) -> dict:
    # the outage needs time after its jump: the demo run on, straight after its last turn
    sc = demo_scenario(200.0) if "outage" in attacks else load_scenario("demo_product")
    text = (ROOT / "simulators" / "scenarios" / "demo_product.toml").read_text()
    text = text.replace("[service]\n", '[service]\nvehicles = ["*"]\n', 1)
    cfg = workdir / "service.toml"
    cfg.write_text(text)
    port = free_port()
    svc = start_service(port, config=cfg, table="service", rrd=workdir / "probe.rrd")
    session = client(port)
    sols: dict[tuple[str, str], list[dict]] = {}
    lock = threading.Lock()

    def on_solution(sample: zenoh.Sample) -> None:
        d = json.loads(sample.payload.to_bytes())
        parts = str(sample.key_expr).split("/")
        with lock:
            sols.setdefault((parts[1], parts[3]), []).append(d)

    session.declare_subscriber("fednav/*/nav/*/solution", on_solution)
    sent: dict[str, int] = {}
    vehicles = ("clean", *attacks)
    try:
        t_wall0 = time.monotonic() + 1.0
        threads = [
            threading.Thread(
                target=lambda v=v: sent.__setitem__(v, publish(sc, v, port, t_wall0, seed, pace))
            )
            for v in vehicles
        ]
        for th in threads:
            th.start()
        for th in threads:
            th.join(timeout=600)
        # the service may still work through a backlog (four demo vehicles at 10x load it):
        # wait until every vehicle's Health time reached the end of the scenario
        end_t = sc.t0_gps_s + sc.duration_s - 0.5
        deadline = time.monotonic() + 300.0
        for v in vehicles:
            while time.monotonic() < deadline:
                h = ((query_status(port, v) or {}).get("health")) or {}
                if (h.get("t") or 0.0) >= end_t:
                    break
                time.sleep(0.5)
        status = {v: wait_idle(port, vehicle=v) for v in vehicles}
        # and until this process's subscriber has taken every Solution in flight (its callback
        # thread lags behind when the publishing threads hold the GIL)
        count, still = -1, 0
        while still < 3 and time.monotonic() < deadline:
            with lock:
                n = sum(len(x) for x in sols.values())
            still = still + 1 if n == count else 0
            count = n
            time.sleep(1.0)
        alive = svc.p.poll() is None
    finally:
        svc.signal(signal.SIGTERM)
        rc = svc.wait(timeout=60)
        session.close()
    traj = Simulation(sc, seed=seed).truth.trajectory

    def errors(v: str, p: str) -> list[tuple]:
        out = []
        for d in sorted(sols.get((v, p), []), key=lambda d: d["t"]):
            s = traj.state_at(d["t"])
            r_m, r_n = earth.radii(s.llh[0])
            dn = (math.radians(d["lat_deg"]) - s.llh[0]) * (r_m + s.llh[2])
            de = earth.wrap_pi(math.radians(d["lon_deg"]) - s.llh[1]) * (r_n + s.llh[2]) * math.cos(s.llh[0])
            sd = d["pos_std_enu_m"]
            out.append(
                (d["t"] - sc.t0_gps_s, math.hypot(de, dn), math.hypot(sd[0], sd[1]), d["status"],
                 abs(d["height_m"] - s.llh[2]), sd[2])
            )  # fmt: skip
        return out

    def lies(e) -> int:
        return sum(1 for _, h, s, st, u, su in e if st == "aided" and (h > 3 * s or u > 3 * su))

    result = {"alive": alive, "rc": rc, "sent": sent, "pipelines": {}}
    for p in PIPELINES:
        clean = errors("clean", p)
        if not clean:
            result["pipelines"][p] = None
            continue
        p95 = float(np.percentile([e[1] for e in clean], 95))
        row = {"clean_p95": p95, "clean_lies": lies(clean)}
        for v in attacks:
            end = ENDS[v]
            e = errors(v, p)
            if not e:
                row[v] = None
                continue
            rec = None
            for i, x in enumerate(e):
                if x[0] >= end and x[1] <= p95 and all(y[1] <= 1.5 * p95 for y in e[i:]):
                    rec = x[0] - end
                    break
            after = [x[1] for x in e if x[0] >= AT_S]
            peak = max(after) if after else None  # None: its solutions stopped before the attack
            row[v] = {"peak": peak, "recovered": rec, "lies": lies(e), "last": e[-1][0]}
        result["pipelines"][p] = row
    result["refused"] = {v: ((status.get(v) or {}).get("health") or {}).get("rejected") for v in attacks}
    return result


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--runs", type=int, default=3)
    ap.add_argument("--seed", type=int, default=5)
    ap.add_argument("--pace", type=float, default=10.0, help="x real time (default 10, the probes')")
    ap.add_argument("--attacks", default=",".join(ENDS), help=f"attacked vehicles, of {','.join(ENDS)}")
    ap.add_argument("--json", action="store_true")
    a = ap.parse_args()
    attacks = tuple(x for x in a.attacks.split(",") if x)
    unknown = [x for x in attacks if x not in ENDS]
    if unknown:
        ap.error(f"unknown attacks {unknown}; known: {', '.join(ENDS)}")
    results = []
    for r in range(a.runs):
        with tempfile.TemporaryDirectory(prefix="fednav_probe_") as tmp:
            res = one_run(a.seed, a.pace, Path(tmp), attacks)
        results.append(res)
        if a.json:
            continue
        print(f"run {r + 1}: service alive {res['alive']}, exit {res['rc']}, forged messages {res['sent']}")
        for p, row in res["pipelines"].items():
            if row is None:
                print(f"  {p}: no solutions")
                continue
            cells = []
            for v in attacks:
                x = row[v]
                if x is None:
                    cells.append(f"{v}: no solutions")
                    continue
                if x["peak"] is None:
                    cells.append(f"{v}: solutions stopped at {x['last']:.0f} s")
                    continue
                rec = "never" if x["recovered"] is None else f"{x['recovered']:.1f} s"
                cells.append(
                    f"{v}: peak {x['peak']:.1f} m, back {rec}, aided>3sigma {x['lies']}, "
                    f"last {x['last']:.0f} s"
                )
            print(
                f"  {p:8s} clean p95 {row['clean_p95']:.2f} m (aided>3sigma {row['clean_lies']}) | "
                + " | ".join(cells)
            )
        print("  refused:", res["refused"], flush=True)
    if a.json:
        print(json.dumps(results, indent=2))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
