"""``fednav-sim fleet``: one process publishing N vehicles (a fleet load, a fleet test).

Each vehicle flies a scenario (default: the demo aircraft at 200 Hz IMU and 10 Hz fixes) with its
own start heading and noise seed, drawn from ``--variants`` distinct runs (vehicles sharing a
variant publish the same sensor values under their own keys: generating 1000 vehicles' streams
would cost more than publishing them). Vehicles are phase-shifted in wall time (vehicle i starts
i/N of a batch period later), as independent vehicles are; each vehicle's messages keep their own
order and pacing.

IMU samples go out as ImuBatch payloads of ``--imu-batch`` samples (1: one JSON ImuSample each);
fixes, the InitialNav and (``--truth``) truth as JSON. ``--log FILE`` writes, for every IMU
publication, (vehicle index, sensor time of its last sample, monotonic wall time of the put): the
fleet benchmark's latency reference.
"""

from __future__ import annotations

import heapq
import math
import time
from dataclasses import dataclass

import numpy as np

from fednav.service import imu_batch as imu_batch_codec
from fednav.service import keys
from fednav.service.messages import ImuSample, InitialNav, Truth

#: the fleet's default scenario: the demo aircraft at fleet rates
DEFAULT_SCENARIO = "demo_aircraft"


@dataclass
class Item:
    t: float  # sensor time of the message (of its last sample for a batch)
    suffix: str  # the key after {prefix}/{vehicle}/
    payload: bytes
    encoding: str
    imu: bool


def variant_items(
    scenario, seed: int, heading_deg: float, imu_batch: int, truth: bool, prefix: str
) -> tuple[list[Item], float]:
    """One variant's publication items in order, and its first sensor time."""
    from fednav.simulators.scenario import parse_scenario
    from fednav.simulators.stream import Simulation

    data = dict(scenario)
    data["start"] = dict(data["start"], heading_deg=heading_deg)
    sc = parse_scenario(data, f"{data.get('name', 'fleet')} heading {heading_deg:.0f}")
    head = f"{prefix}/_v_/"
    items: list[Item] = []
    pending: list[ImuSample] = []
    t0 = None
    for key, msg in Simulation(sc, seed=seed, vehicle="_v_", prefix=prefix):
        t0 = msg.t if t0 is None else t0
        suffix = key[len(head) :]
        if isinstance(msg, ImuSample):
            if imu_batch > 1:
                pending.append(msg)
                if len(pending) == imu_batch:
                    items.append(
                        Item(
                            msg.t,
                            suffix,
                            imu_batch_codec.encode_samples(pending),
                            imu_batch_codec.ENCODING,
                            True,
                        )
                    )
                    pending = []
                continue
            items.append(Item(msg.t, suffix, msg.to_json(), msg.encoding(), True))
            continue
        if isinstance(msg, Truth) and not truth:
            continue
        items.append(Item(msg.t, suffix, msg.to_json(), msg.encoding(), False))
    return items, t0


def fleet_scenario(name: str, imu_rate_hz: float, fix_rate_hz: float, duration_s: float) -> dict:
    """The scenario mapping of a fleet vehicle: ``name`` at the given rates and length."""
    import tomllib

    from fednav.simulators.scenario import scenario_path

    data = tomllib.loads(scenario_path(name).read_text())
    data["duration_s"] = float(duration_s)
    data["imu"] = dict(data["imu"], rate_hz=float(imu_rate_hz))
    if "gnss" in data:
        data["gnss"] = dict(data["gnss"], rate_hz=float(fix_rate_hz))
    data["truth_rate_hz"] = float(fix_rate_hz)
    segs, total = [], 0.0
    for s in data.get("segments", []):
        if total + s["duration_s"] > duration_s:
            break
        segs.append(s)
        total += s["duration_s"]
    data["segments"] = segs
    data["faults"] = [f for f in data.get("faults", []) if f["start_s"] < duration_s]
    return data


def vehicle_names(n: int, stem: str = "veh") -> list[str]:
    width = max(3, len(str(n - 1)))
    return [f"{stem}{i:0{width}d}" for i in range(n)]


def publish_fleet(
    vehicles: list[str],
    variants: list[tuple[list[Item], float]],
    *,
    session,
    speed: float = 1.0,
    prefix: str = keys.DEFAULT_PREFIX,
    batch_period_s: float = 0.05,
    log: list | None = None,
    match_timeout_s: float = 30.0,
    stop=None,
) -> dict:
    """Publish every vehicle's items paced at ``speed`` (> 0) with per-vehicle phase offsets."""
    import zenoh

    pubs: dict[str, object] = {}

    def pub(key: str, encoding: str):
        p = pubs.get(key)
        if p is None:
            p = pubs[key] = session.declare_publisher(
                key,
                encoding=zenoh.Encoding(encoding),
                congestion_control=zenoh.CongestionControl.BLOCK,
                reliability=zenoh.Reliability.RELIABLE,
            )
        return p

    n = len(vehicles)
    # declare every publisher first and wait for the service's subscriber
    for i, v in enumerate(vehicles):
        items, _ = variants[i % len(variants)]
        for it in items[:200]:
            pub(f"{prefix}/{v}/{it.suffix}", it.encoding)
    from fednav.simulators.publisher import (
        Announcement,
        MatchTimeout,
        MatchWatch,
        vehicle_probe_key,
        wait_heard,
    )

    # each vehicle announced (a fleet member that subscribes per vehicle it owns subscribes to its
    # own now, and hears their IMU from the first sample)
    announced = [Announcement(session, f"{prefix}/{v}/") for v in vehicles]

    # a service subscribes to every vehicle's InitialNav key (a fleet member that subscribes per
    # vehicle it owns too: its IMU keys only once the vehicle is its own); a receiver of one's
    # own may subscribe to the first key only
    first = next(iter(pubs.values()))
    probe = pub(vehicle_probe_key(f"{prefix}/{vehicles[0]}/"), InitialNav.encoding())
    deadline = time.monotonic() + match_timeout_s
    while not (probe.matching_status.matching or first.matching_status.matching):
        if time.monotonic() > deadline:
            raise MatchTimeout(f"no subscriber matched the fleet's keys within {match_timeout_s:g} s")
        time.sleep(0.01)

    watch = MatchWatch(probe if probe.matching_status.matching else first)
    if probe.matching_status.matching:  # a fednav service: each vehicle's owner subscribes to it
        wait_heard(announced)
    heap = []
    for i in range(n):
        items, t0 = variants[i % len(variants)]
        phase = batch_period_s * i / n
        heap.append((items[0].t - t0 + phase, i, 0))
    heapq.heapify(heap)
    wall0 = time.monotonic() + 0.1
    sent = 0
    while heap:
        due, i, k = heap[0]
        if stop is not None and stop.is_set():
            break
        items, t0 = variants[i % len(variants)]
        it = items[k]
        delay = wall0 + due / speed - time.monotonic()
        if delay > 0:
            time.sleep(delay)
        pub(f"{prefix}/{vehicles[i]}/{it.suffix}", it.encoding).put(it.payload)
        if log is not None and it.imu:
            log.append((i, it.t, time.monotonic()))
        sent += 1
        if k + 1 < len(items):
            phase = batch_period_s * i / n
            heapq.heapreplace(heap, (items[k + 1].t - t0 + phase, i, k + 1))
        else:
            heapq.heappop(heap)
    wall = time.monotonic() - wall0
    return {
        "messages": sent,
        "wall_s": wall,
        "vehicles": n,
        "pubs": pubs,
        "watch": watch,
        "announced": announced,
    }


def end_fleet(session, stats: dict, drain_keys: list[str]) -> dict:
    """After :func:`publish_fleet`: wait for the services to take what is queued (``drain``), then
    say whether the subscribers went away meanwhile (``subscriber_lost``), and undeclare. The
    result as :func:`fednav.simulators.publisher.publish_stream`'s, for ``report_end``."""
    from fednav.simulators.publisher import drain, services_visible

    drained = drain(session, drain_keys)
    seen = None
    if drained is None:
        time.sleep(0.5)  # no fednav service answers: let the transmission queues empty a little
        seen = services_visible(session, {k.split("/", 1)[0] for k in drain_keys})
    watch = stats.pop("watch")
    lost = watch.lost()
    watch.close()
    for p in stats.pop("pubs").values():
        p.undeclare()
    for a in stats.pop("announced"):
        a.close()
    return {**stats, "drained": False if lost else drained, "subscriber_lost": lost, "services_seen": seen}


def main(argv: list[str] | None = None) -> int:
    import argparse
    import sys

    from fednav.service.imu_batch import batch_size_arg
    from fednav.simulators.publisher import timeout_arg
    from fednav.simulators.scenario import ScenarioError, duration_arg

    ap = argparse.ArgumentParser(
        prog="fednav-sim fleet", description=__doc__.split("\n\n")[0].replace("``", "")
    )
    ap.add_argument("--vehicles", type=int, default=10, help="number of vehicles (default 10)")
    ap.add_argument("--stem", default="veh", help="vehicle names: <stem>000, <stem>001, ...")
    ap.add_argument("--scenario", default=DEFAULT_SCENARIO, help="scenario (default demo_aircraft)")
    ap.add_argument("--imu-rate", type=float, default=200.0, help="IMU rate, Hz (default 200)")
    ap.add_argument("--fix-rate", type=float, default=10.0, help="GNSS fix rate, Hz (default 10)")
    ap.add_argument("--duration", type=duration_arg, default=60.0, help="scenario seconds (default 60)")
    ap.add_argument("--speed", type=float, default=1.0, help="pacing, x real time (default 1)")
    ap.add_argument("--imu-batch", type=batch_size_arg, default=10, help="IMU samples per ImuBatch (1: JSON)")
    ap.add_argument(
        "--variants", type=int, default=4, help="distinct runs (headings, seeds) shared round-robin"
    )
    ap.add_argument("--seed", type=int, default=1, help="first noise seed (variant j: seed + j)")
    ap.add_argument("--truth", action="store_true", help="also publish truth (errors in the recording)")
    ap.add_argument("--connect", action="append", help="Zenoh endpoint (default tcp/127.0.0.1:7447)")
    ap.add_argument("--zenoh-config", help="a Zenoh json5 config file (TLS, access control)")
    ap.add_argument("--prefix", default=keys.DEFAULT_PREFIX)
    ap.add_argument("--log", help="write the IMU publication log (npy: vehicle, t, wall) here")
    ap.add_argument(
        "--match-timeout", type=timeout_arg, default=30.0, help="seconds to wait for a service (default 30)"
    )
    args = ap.parse_args(argv)
    if args.vehicles < 1 or not (math.isfinite(args.speed) and args.speed > 0):
        print("fednav-sim fleet: --vehicles >= 1 and --speed > 0", file=sys.stderr)
        return 2
    from fednav.simulators.publisher import MatchTimeout, open_session, session_args_problem, session_config

    problem = session_args_problem(args.connect, args.zenoh_config)
    if problem:
        print(f"fednav-sim fleet: {problem}", file=sys.stderr)
        return 2

    n_var = max(1, min(args.variants, args.vehicles))
    t_build = time.monotonic()
    try:
        data = fleet_scenario(args.scenario, args.imu_rate, args.fix_rate, args.duration)
        variants = [
            variant_items(
                data,
                args.seed + j,
                (data["start"]["heading_deg"] + 360.0 * j / n_var) % 360.0,
                args.imu_batch,
                args.truth,
                args.prefix,
            )
            for j in range(n_var)
        ]
    except ScenarioError as exc:
        print(f"fednav-sim fleet: {exc}", file=sys.stderr)
        return 2
    print(f"fednav-sim fleet: {n_var} variants built in {time.monotonic() - t_build:.1f} s", flush=True)
    log: list | None = [] if args.log else None
    period = args.imu_batch / args.imu_rate
    wait = args.match_timeout
    try:
        session = open_session(session_config(connect=args.connect, zenoh_config=args.zenoh_config), wait)
        with session:
            print("fednav-sim fleet: publishing", flush=True)
            stats = publish_fleet(
                vehicle_names(args.vehicles, args.stem),
                variants,
                session=session,
                speed=args.speed,
                prefix=args.prefix,
                batch_period_s=max(period, 1.0 / args.fix_rate) if math.isfinite(period) else 0.1,
                log=log,
                match_timeout_s=wait,
            )
            names = vehicle_names(args.vehicles, args.stem)
            stats = end_fleet(session, stats, [keys.service(v, "status", args.prefix) for v in names])
    except MatchTimeout as exc:
        print(f"fednav-sim fleet: {exc}: is fednav-service running on the endpoint?", file=sys.stderr)
        return 3
    if args.log:
        np.save(args.log, np.array(log, dtype=float).reshape(-1, 3))
    print(
        f"fednav-sim fleet: published {stats['messages']} messages for {stats['vehicles']} vehicles "
        f"in {stats['wall_s']:.1f} s",
        flush=True,
    )
    from fednav.simulators.publisher import report_end

    return report_end(stats, "fednav-sim fleet", vehicle_names(args.vehicles, args.stem))


if __name__ == "__main__":
    raise SystemExit(main())
