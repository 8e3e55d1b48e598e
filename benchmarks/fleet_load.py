"""Fleet load: one process publishes N vehicles, fednav-service (its own process) serves them all.

Each case starts a service serving every vehicle (``vehicles = ['*']``, one loosely coupled
pipeline, solutions at 10 Hz), then ``fednav-sim fleet`` (its own process: N vehicles of the demo
aircraft at 200 Hz IMU + 10 Hz fixes, phase-shifted, paced in real time) and a plain Zenoh
subscriber of every Solution in this process. Printed per case:

- latency: from the publication of the message that completes a solution epoch (the IMU batch or
  sample whose last sample reaches the epoch's time) to that Solution's arrival at the subscriber,
  p50 / p99 / max (monotonic clock shared by the processes of this machine); it contains the
  service's work and both Zenoh hops, so it bounds the service's own share from above;
- real time: solutions received / expected, the publisher's wall time vs the scenario time (a
  service that falls behind back-pressures the reliable publisher and stretches it);
- service CPU (cores, from /proc over the publishing window), CPU per vehicle, RSS and RSS per
  vehicle (RSS at the end minus RSS of the idle service).

Usage: .venv/bin/python benchmarks/fleet_load.py [--vehicles 50 100 200] [--duration 30] [--option LINE]
           [--intake-option LINE]
           [--modes batch json] [--imu-batch 10] [--record off on] [--workers 2] [--shards 1] [--json]
"""

from __future__ import annotations

import argparse
import json
import os
import signal
import sys
import tempfile
import threading
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
CLK_TCK = os.sysconf("SC_CLK_TCK")


def cpu_s(pid: int) -> float:
    with open(f"/proc/{pid}/stat") as f:
        parts = f.read().rsplit(")", 1)[1].split()
    return (int(parts[11]) + int(parts[12])) / CLK_TCK  # utime + stime


def thread_cpu_s(pid: int) -> dict[str, float]:
    """CPU seconds per thread name (``comm``) of a process: Python's own threads are named after
    the interpreter, Zenoh's runtime threads after their pools."""
    out: dict[str, float] = {}
    for tid in os.listdir(f"/proc/{pid}/task"):
        try:
            with open(f"/proc/{pid}/task/{tid}/comm") as f:
                name = f.read().strip()
            with open(f"/proc/{pid}/task/{tid}/stat") as f:
                parts = f.read().rsplit(")", 1)[1].split()
        except OSError:
            continue
        out[name] = out.get(name, 0.0) + (int(parts[11]) + int(parts[12])) / CLK_TCK
    return out


def rss_mb(pid: int) -> float:
    with open(f"/proc/{pid}/status") as f:
        for line in f:
            if line.startswith("VmRSS:"):
                return int(line.split()[1]) / 1024.0
    return float("nan")


def service_config(tmp: Path, workers: int | None, record: bool, extra: str = "", intake: str = "") -> Path:
    p = tmp / "fleet_service.toml"
    p.write_text(
        'vehicles = ["*"]\n'
        'pipelines = [{ name = "lc", kind = "loosely_coupled" }]\n'
        + ("rrd_vehicle_interval_s = 1.0\n" if record else "")
        + f"{extra}"
        "[intake]\n"
        + (f"workers = {workers}\n" if workers is not None else "")
        + "max_vehicles = 1000\n"
        + intake
    )
    return p


def run_case(
    n: int,
    mode: str,
    record: bool,
    duration: float,
    workers: int | None,
    shards: int,
    tmp: Path,
    options: str = "",
    intake_options: str = "",
    imu_batch: int = 10,
) -> dict:
    import zenoh

    from fednav.service.config import ZenohConfig
    from fednav.service.transport.zenoh_io import make_config
    from fednav.simulators.fleet import vehicle_names
    from fednav.simulators.processes import Proc, free_port, start_service

    port = free_port()
    cfg = service_config(tmp, workers, record, options, intake_options)
    rrd = tmp / f"fleet_{n}_{mode}.rrd" if record else None
    extra = ["--shards", str(shards)] if shards > 1 else []
    svc = start_service(port, config=cfg, rrd=rrd, extra=extra)
    pids = [svc.p.pid] + _children(svc.p.pid)
    time.sleep(1.0)
    rss0 = sum(rss_mb(p) for p in pids)
    s = zenoh.open(make_config(ZenohConfig(mode="client"), listen=[], connect=[f"tcp/127.0.0.1:{port}"]))
    names = vehicle_names(n)
    index = {v: i for i, v in enumerate(names)}
    got: list[tuple[int, float, float]] = []
    lock = threading.Lock()

    def on_sol(sample):
        now = time.monotonic()
        v = str(sample.key_expr).split("/")[1]
        t = json.loads(sample.payload.to_bytes())["t"]
        with lock:
            got.append((index.get(v, -1), t, now))

    sub = s.declare_subscriber("fednav/*/nav/lc/solution", on_sol)
    log = tmp / "fleet_log.npy"
    batch = imu_batch if mode == "batch" else 1
    gen = Proc(
        [
            sys.executable,
            "-m",
            "fednav.simulators",
            "fleet",
            "--vehicles",
            str(n),
            "--duration",
            str(duration),
            "--imu-batch",
            str(batch),
            "--connect",
            f"tcp/127.0.0.1:{port}",
            "--log",
            str(log),
        ],
        "fednav-sim fleet",
    )
    try:
        if not gen.wait_for("publishing", timeout=600):
            raise RuntimeError(gen.output())
        c0 = sum(cpu_s(p) for p in pids)
        th0 = thread_cpu_s(svc.p.pid)
        ths0 = {p: thread_cpu_s(p) for p in pids}
        w0 = time.monotonic()
        assert gen.wait(timeout=duration * 20 + 120) == 0, gen.output()
        w1 = time.monotonic()
        c1 = sum(cpu_s(p) for p in pids)
        th1 = thread_cpu_s(svc.p.pid)
        ths1 = {p: thread_cpu_s(p) for p in pids}
        rss1 = sum(rss_mb(p) for p in pids)
        time.sleep(1.0)
    finally:
        sub.undeclare()
        s.close()
        svc.signal(signal.SIGTERM)
        svc.wait(timeout=120)
    pub = np.load(log)
    lat = _latencies(pub, np.array(got, dtype=float).reshape(-1, 3), n)
    wall_pub = float(gen.output().split(" in ")[-1].split(" s")[0]) if " in " in gen.output() else w1 - w0
    expected = n * duration * 10
    out = {
        "vehicles": n,
        "mode": mode,
        "imu_batch": batch,
        "record": record,
        "workers": workers,
        "shards": shards,
        "solutions_received": len(got),
        "solutions_expected": int(expected),
        "publisher_wall_s": round(wall_pub, 2),
        "scenario_s": duration,
        "latency_ms": {k: round(float(v), 2) for k, v in lat.items()},
        "service_cpu_cores": round((c1 - c0) / (w1 - w0), 3),
        "cpu_ms_per_vehicle_s": round((c1 - c0) / (w1 - w0) / n * 1e3, 3),
        "shard0_threads_cores": {
            k: round((th1.get(k, 0.0) - th0.get(k, 0.0)) / (w1 - w0), 3)
            for k in sorted(th1, key=lambda k: th0.get(k, 0.0) - th1[k])[:6]
        },
        # every process of the service (shard 0 first): Python's threads against Zenoh's
        "shards_cores": [_split_threads(ths0[p], ths1[p], w1 - w0) for p in pids],
        "rss_mb": round(rss1, 1),
        "rss_mb_per_vehicle": round((rss1 - rss0) / n, 3),
    }
    if rrd is not None:
        files = list(tmp.glob(f"fleet_{n}_{mode}*.rrd"))
        size = sum(f.stat().st_size for f in files)
        out["rrd_mb"] = round(size / 1e6, 2)
        out["rrd_kb_per_vehicle_min"] = round(size / 1e3 / n / (duration / 60.0), 1)
        for f in files:
            f.unlink()
    return out


def _split_threads(before: dict[str, float], after: dict[str, float], wall_s: float) -> dict[str, float]:
    """One process's cores over ``wall_s``: in total, in Python's threads (named after the
    interpreter) and in the rest (Zenoh's runtime: rx-*, tx-*, acc-*, net-*, ...)."""
    d = {k: (v - before.get(k, 0.0)) / wall_s for k, v in after.items()}
    py = sum(v for k, v in d.items() if k.startswith("python"))
    total = sum(d.values())
    return {"total": round(total, 3), "python": round(py, 3), "other": round(total - py, 3)}


def _children(pid: int) -> list[int]:
    try:
        with open(f"/proc/{pid}/task/{pid}/children") as f:
            return [int(x) for x in f.read().split()]
    except OSError:
        return []


def _latencies(pub: np.ndarray, sol: np.ndarray, n: int) -> dict:
    """Per solution: its arrival minus the publication of the first IMU message of its vehicle
    whose last sample reaches the solution's time."""
    out = []
    for i in range(n):
        p = pub[pub[:, 0] == i]
        s = sol[sol[:, 0] == i]
        if not len(p) or not len(s):
            continue
        order = np.argsort(p[:, 1])
        tp, wp = p[order, 1], p[order, 2]
        k = np.searchsorted(tp, s[:, 1] - 1e-9)
        ok = k < len(tp)
        out.append(s[ok, 2] - wp[k[ok]])
    a = np.concatenate(out) * 1e3 if out else np.zeros(1)
    return {"p50": np.percentile(a, 50), "p99": np.percentile(a, 99), "max": a.max(), "n": a.size}


def main() -> int:
    ap = argparse.ArgumentParser()
    ap.add_argument("--vehicles", type=int, nargs="+", default=[50, 100, 200])
    ap.add_argument("--duration", type=float, default=30.0)
    ap.add_argument("--modes", nargs="+", default=["batch", "json"], choices=["batch", "json"])
    ap.add_argument("--record", nargs="+", default=["off"], choices=["off", "on"])
    ap.add_argument(
        "--workers", type=int, default=None, help="[intake] workers (default: the service's, 0 = inline)"
    )
    ap.add_argument("--shards", type=int, default=1)
    ap.add_argument(
        "--option",
        action="append",
        default=[],
        help="a top-level line of the service's TOML configuration, repeatable "
        "(e.g. --option 'rrd_flush_interval_s = 5.0')",
    )
    ap.add_argument(
        "--intake-option",
        action="append",
        default=[],
        help="a line of the service's [intake] table, repeatable (e.g. 'subscribe = \"all\"')",
    )
    ap.add_argument(
        "--imu-batch",
        type=int,
        default=10,
        help="samples per ImuBatch in the batch mode (default 10: 20 messages a second at 200 Hz; "
        "20: one per 10 Hz solution epoch)",
    )
    ap.add_argument("--json", action="store_true")
    args = ap.parse_args()
    if args.imu_batch < 2:
        ap.error("--imu-batch: at least 2 (one sample per message is the json mode)")
    results = []
    with tempfile.TemporaryDirectory() as d:
        for mode in args.modes:
            for rec in args.record:
                for n in args.vehicles:
                    r = run_case(
                        n,
                        mode,
                        rec == "on",
                        args.duration,
                        args.workers,
                        args.shards,
                        Path(d),
                        "".join(o + "\n" for o in args.option),
                        "".join(o + "\n" for o in args.intake_option),
                        args.imu_batch,
                    )
                    results.append(r)
                    if not args.json:
                        lat = r["latency_ms"]
                        print(
                            f"{n:5d} vehicles {mode:5s} rec {rec:3s}: latency p50 {lat['p50']:.1f} p99 "
                            f"{lat['p99']:.1f} max {lat['max']:.1f} ms | solutions {r['solutions_received']}/"
                            f"{r['solutions_expected']} | publisher {r['publisher_wall_s']} s for "
                            f"{r['scenario_s']:.0f} s | service {r['service_cpu_cores']:.2f} cores, "
                            f"{r['cpu_ms_per_vehicle_s']:.2f} ms CPU per vehicle-second | RSS "
                            f"{r['rss_mb']:.0f} MB, {r['rss_mb_per_vehicle']:.2f} MB/vehicle"
                            + (
                                f" | rrd {r['rrd_kb_per_vehicle_min']} kB/vehicle/min"
                                if "rrd_mb" in r
                                else ""
                            )
                            + (
                                " | per process, cores (Python + Zenoh's threads): "
                                + ", ".join(
                                    f"{c['total']:.2f} ({c['python']:.2f} + {c['other']:.2f})"
                                    for c in r["shards_cores"]
                                )
                                if len(r["shards_cores"]) > 1
                                else ""
                            ),
                            flush=True,
                        )
    if args.json:
        print(json.dumps(results, indent=2))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
