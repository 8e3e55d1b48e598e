"""What each member of a fleet spends on the vehicles it does not serve: ``[intake] subscribe =
"all"`` (every member receives every vehicle's inputs and drops the others') against ``"owned"``
(one subscription per vehicle a member serves, and every vehicle's low-rate discovery inputs).

One case: a ``fednav-router``, ``--members`` services sharing the fleet (``[fleet] sharding =
"rendezvous"``, one loosely coupled pipeline, client mode behind the router) and ``fednav-sim
fleet`` of ``--vehicles`` vehicles (200 Hz IMU as JSON samples or ImuBatches of 10, 10 Hz fixes),
paced in real time. After the members have settled (every vehicle served by one), over
``--window`` seconds: each member's CPU (cores), its vehicles, the inputs it dropped as another
member's (``ServiceHealth.inputs_served_elsewhere``, per second) and the router's CPU; then every
vehicle's Solutions counted (each vehicle solved at 10 Hz by exactly one member). The two modes
run alternately, ``--rounds`` times, on the same machine: compare them within a round.

Usage: .venv/bin/python benchmarks/fleet_members.py [--vehicles 30] [--members 3] [--modes json batch]
           [--window 20] [--rounds 2] [--json]
"""

from __future__ import annotations

import argparse
import json
import sys
import tempfile
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))

from fleet_failover import _service, _zid  # noqa: E402
from fleet_load import cpu_s  # noqa: E402

from fednav.simulators.fleet import vehicle_names  # noqa: E402
from fednav.simulators.fleet_watch import FleetWatch  # noqa: E402
from fednav.simulators.processes import Proc, free_port, stop_all  # noqa: E402


def run_case(n: int, members: int, mode: str, subscribe: str, window: float, tmp: Path) -> dict:
    cfg = tmp / f"member_{subscribe}.toml"
    cfg.write_text(
        'vehicles = ["*"]\npipelines = [{ name = "lc", kind = "loosely_coupled" }]\n'
        '[zenoh]\nmode = "client"\n[fleet]\nsharding = "rendezvous"\n'
        f'[intake]\nsubscribe = "{subscribe}"\nmax_vehicles = 1000\n'
    )
    port = free_port()
    router = Proc(
        [sys.executable, "-m", "fednav.service.router", "--listen", f"tcp/127.0.0.1:{port}"], "router"
    )
    if not router.wait_for("fednav-router ready", timeout=30):
        raise RuntimeError(router.output())
    procs = [router]
    watch = FleetWatch(port)
    names = vehicle_names(n)
    try:
        svcs = [_service(port, cfg) for _ in range(members)]
        procs += svcs
        zids = [_zid(s) for s in svcs]
        gen = Proc(
            [sys.executable, "-m", "fednav.simulators", "fleet", "--vehicles", str(n)]
            + ["--duration", str(window + 60), "--imu-batch", "1" if mode == "json" else "10"]
            + ["--connect", f"tcp/127.0.0.1:{port}"],
            "fednav-sim fleet",
        )
        procs.append(gen)
        if not gen.wait_for("publishing", timeout=120):
            raise RuntimeError(gen.output())
        deadline = time.monotonic() + 60.0
        while time.monotonic() < deadline:  # settled: every vehicle served by one member
            asg = watch.assignment(time.monotonic() - 1.5)
            served = sorted(sum(asg.values(), []))
            if served == names and len(asg) == members:
                break
            time.sleep(0.5)
        time.sleep(5.0)
        with watch.lock:
            h0 = {z: dict(watch.health.get(z, {})) for z in zids}
        c0 = [cpu_s(p.p.pid) for p in procs[: members + 1]]
        w0 = time.monotonic()
        time.sleep(window)
        w1 = time.monotonic()
        c1 = [cpu_s(p.p.pid) for p in procs[: members + 1]]
        time.sleep(1.2)  # the members' next ServiceHealth
        with watch.lock:
            h1 = {z: dict(watch.health.get(z, {})) for z in zids}
            sols = {v: [s for s in watch.sols.get(v, []) if w0 <= s[0] <= w1] for v in names}
        asg = watch.assignment(w1 - 1.5)
    finally:
        stop_all(procs)
        watch.close()
    wall = w1 - w0
    per = []
    for i, z in enumerate(zids):
        dropped = h1[z].get("inputs_served_elsewhere", 0) - h0[z].get("inputs_served_elsewhere", 0)
        per.append(
            {
                "vehicles": len(asg.get(z, [])),
                "cores": round((c1[i + 1] - c0[i + 1]) / wall, 3),
                "dropped_per_s": round(dropped / wall, 1),
                "subscribed_vehicles": h1[z].get("subscribed_vehicles"),
            }
        )
    counts = [len(sols[v]) for v in names]
    return {
        "vehicles": n,
        "members": members,
        "mode": mode,
        "subscribe": subscribe,
        "window_s": round(wall, 1),
        "members_cores": round(sum(p["cores"] for p in per), 3),
        "router_cores": round((c1[0] - c0[0]) / wall, 3),
        "per_member": per,
        "solutions_per_vehicle_s": [round(min(counts) / wall, 2), round(max(counts) / wall, 2)],
    }


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--vehicles", type=int, default=30)
    ap.add_argument("--members", type=int, default=3)
    ap.add_argument("--modes", nargs="+", default=["json", "batch"], choices=["json", "batch"])
    ap.add_argument("--window", type=float, default=20.0, help="measured seconds (default 20)")
    ap.add_argument("--rounds", type=int, default=2)
    ap.add_argument("--json", action="store_true")
    args = ap.parse_args()
    out = []
    with tempfile.TemporaryDirectory() as d:
        for r in range(args.rounds):
            for mode in args.modes:
                for sub in ("all", "owned"):
                    res = run_case(args.vehicles, args.members, mode, sub, args.window, Path(d))
                    res["round"] = r + 1
                    out.append(res)
                    if not args.json:
                        per = "; ".join(
                            f"{p['vehicles']} veh {p['cores']:.2f} cores, drops {p['dropped_per_s']:.0f}/s"
                            for p in res["per_member"]
                        )
                        print(
                            f"round {r + 1} {mode:5s} subscribe {sub:5s}: members {res['members_cores']:.2f} "
                            f"cores ({per}) | router {res['router_cores']:.2f} cores | Solutions per "
                            "vehicle-second {}-{}".format(*res["solutions_per_vehicle_s"]),
                            flush=True,
                        )
    if args.json:
        print(json.dumps(out, indent=1))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
