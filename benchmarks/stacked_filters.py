"""What stacking the loosely coupled filters of many vehicles into one array would buy: an upper
bound measured before writing the array-over-vehicles engine that issue 21's 200 vehicles need.

Two figures, measured in one process, side by side:

1. The share of one fleet vehicle's CPU that is the filter's numerics -- the calls that an
   engine holding every vehicle's state in one (vehicles, n, n) array would run once for many
   vehicles: ``error_model.continuous_F`` / ``continuous_Q`` / ``discretise``, ``kalman.predict``,
   ``kalman.update``, ``kalman.is_positive_definite``. The service's own per-vehicle loop
   (``VehicleLoop.process``, the messages of ``benchmarks/vehicle_cost.py``: the demo aircraft,
   200 Hz IMU in ImuBatches, 10 Hz fixes, every output serialised) runs with those functions
   wrapped by timers; the wrappers' own cost (measured on an empty function) is taken off.
2. The same numerics per vehicle-epoch, one vehicle at a time (the engine's calls on the shapes
   the vehicle used) against K vehicles stacked (the bank forms of the same functions over a
   (K, 15, 15) array: the discretisation's series on stacked F, one ``kalman.predict``, one
   ``kalman.update`` of K members with their own H and R).

What is left of a vehicle's CPU if the numerics cost their stacked price is the bound that
stacking alone can reach; the rest (the IMU samples' preintegration and checks, the rules, the
records, the outputs) is per-message Python that an array engine would also have to take over.

Usage: OPENBLAS_NUM_THREADS=1 .venv/bin/python benchmarks/stacked_filters.py [--duration 60]
           [--stack 1 5 10 20 50 200] [--json]
"""

from __future__ import annotations

import argparse
import functools
import json
import time

import numpy as np

WRAPPED = (
    ("error_model", "continuous_F"),
    ("error_model", "continuous_Q"),
    ("error_model", "discretise"),
    ("kalman", "predict"),
    ("kalman", "update"),
    ("kalman", "is_positive_definite"),
)


def _wrap(mod, name: str, acc: dict, calls: dict, shapes: dict):
    fn = getattr(mod, name)
    clock = time.perf_counter

    @functools.wraps(fn)
    def timed(*a, **k):
        t0 = clock()
        out = fn(*a, **k)
        acc[name] += clock() - t0
        calls[name] += 1
        if name not in shapes:
            shapes[name] = a
        return out

    setattr(mod, name, timed)
    return fn


def wrapper_overhead_s(n: int = 200_000) -> float:
    """Seconds one timing wrapper adds to a call (an empty function wrapped, against it bare)."""
    acc, calls, shapes = {"f": 0.0}, {"f": 0}, {}

    class M:
        @staticmethod
        def f(*a):
            return a

    bare = M.f
    t0 = time.perf_counter()
    for _ in range(n):
        bare(1)
    t_bare = time.perf_counter() - t0
    _wrap(M, "f", acc, calls, shapes)
    t0 = time.perf_counter()
    for _ in range(n):
        M.f(1)
    return max(0.0, (time.perf_counter() - t0 - t_bare) / n)


def vehicle_share(duration_s: float) -> dict:
    """One vehicle through the service's loop with the numerics timed."""
    from vehicle_cost import vehicle_inputs  # benchmarks/, beside this script

    from fednav.service import keys
    from fednav.service.app import OutputSink
    from fednav.service.config import ServiceConfig
    from fednav.service.estimation import kalman
    from fednav.service.ins import error_model
    from fednav.service.vehicle import VehicleLoop, tune_gc

    mods = {"error_model": error_model, "kalman": kalman}
    inputs = vehicle_inputs(duration_s, 10)
    config = ServiceConfig.model_validate(
        {"vehicles": ["*"], "pipelines": [{"name": "lc", "kind": "loosely_coupled"}]}
    )

    class Publishers:
        n = 0

        def publish(self, key: str, msg) -> None:
            msg.to_json()
            Publishers.n += 1

    def run(timed: bool) -> tuple[float, dict, dict]:
        acc = {name: 0.0 for _, name in WRAPPED}
        calls = {name: 0 for _, name in WRAPPED}
        shapes: dict = {}
        originals = []
        if timed:
            originals = [(mods[m], n, _wrap(mods[m], n, acc, calls, shapes)) for m, n in WRAPPED]
        try:
            loop = VehicleLoop("veh000", config, OutputSink(keys.DEFAULT_PREFIX, Publishers(), None))
            c0 = time.thread_time()
            for _t, kind, sensor_id, payload in inputs:
                loop.process(kind, sensor_id, payload)
            cpu = time.thread_time() - c0
        finally:
            for mod, name, fn in originals:
                setattr(mod, name, fn)
        return cpu, {"s": acc, "calls": calls}, shapes

    tune_gc()
    run(False)  # warm-up
    cpu_bare, _, _ = run(False)
    cpu_timed, t, shapes = run(True)
    over = wrapper_overhead_s()
    numerics = {n: max(0.0, t["s"][n] - over * t["calls"][n]) for n in t["s"]}
    return {
        "duration_s": duration_s,
        "cpu_ms_per_vehicle_s": 1e3 * cpu_bare / duration_s,
        "cpu_ms_per_vehicle_s_timed": 1e3 * cpu_timed / duration_s,
        "wrapper_us": over * 1e6,
        "numerics_ms_per_vehicle_s": {n: 1e3 * s / duration_s for n, s in numerics.items()},
        "calls_per_vehicle_s": {n: c / duration_s for n, c in t["calls"].items()},
        "numerics_share": sum(numerics.values()) / cpu_bare,
        "shapes": shapes,
    }


def _stacked_discretise(F: np.ndarray, Qc: np.ndarray, T: float) -> tuple[np.ndarray, np.ndarray]:
    """``error_model.discretise``'s series on a stack of F (K, n, n): the same terms."""
    n = F.shape[-1]
    FT = F * T
    FT2 = FT @ FT
    Phi = np.eye(n) + FT + FT2 / 2.0 + FT2 @ (FT / 6.0 + FT2 / 24.0)
    Qd = Qc * T
    coef = T
    FA = F @ Qc
    A = FA + FA.swapaxes(-1, -2)
    for k in range(1, 5):
        if k > 1:
            FA = F @ A
            A = FA + FA.swapaxes(-1, -2)
        coef *= T / (k + 1)
        Qd = Qd + A * coef
    return Phi, 0.5 * (Qd + Qd.swapaxes(-1, -2))


def epoch_costs(shapes: dict, stacks: list[int], reps_total: int = 4000) -> list[dict]:
    """us per vehicle-epoch of discretise, predict, update and the positive-definite test on the
    vehicle's own first arguments (F, Qc, T, P, z, H, R as the engine passed them), one vehicle at a
    time against ``K`` copies stacked."""
    from fednav.service.estimation import kalman
    from fednav.service.ins import error_model as em

    F1, Qc1, T = shapes["discretise"][:3]
    x1, P1 = shapes["predict"][:2]
    z1, H1, R1 = shapes["update"][2:5]
    n, m = F1.shape[0], np.shape(H1)[-2]
    R1 = np.asarray(R1, dtype=float)
    R1m = np.diag(R1) if R1.ndim == 1 else R1.reshape(m, m)
    out = []
    for K in stacks:
        F = np.broadcast_to(F1, (K, n, n)).copy()
        Qc = np.broadcast_to(Qc1, (K, n, n)).copy()
        P = np.broadcast_to(P1.reshape(n, n), (K, n, n)).copy()
        x = np.broadcast_to(x1.reshape(n), (K, n)).copy()
        z = np.broadcast_to(np.reshape(z1, m), (K, m)).copy()
        H = np.broadcast_to(np.reshape(H1, (m, n)), (K, m, n)).copy()
        R = np.broadcast_to(R1m, (K, m, m)).copy()
        reps = max(10, reps_total // K)
        t0 = time.perf_counter()
        for _ in range(reps):
            for b in range(K):
                Phi, Qd = em.discretise(F[b], Qc[b], T)
                xb, Pb = kalman.predict(x[b : b + 1], P[b : b + 1], Phi, Qd)
                xb, Pb, _res = kalman.update(xb, Pb, z[b], H[b], R[b])
                kalman.is_positive_definite(Pb)
        one = (time.perf_counter() - t0) / reps / K
        t0 = time.perf_counter()
        for _ in range(reps):
            Phi, Qd = _stacked_discretise(F, Qc, T)
            xs, Ps = kalman.predict(x, P, Phi, Qd)
            xs, Ps, _res = kalman.update(xs, Ps, z, H, R)
            kalman.is_positive_definite(Ps)
        stacked = (time.perf_counter() - t0) / reps / K
        out.append({"K": K, "one_at_a_time_us": one * 1e6, "stacked_us": stacked * 1e6})
    return out


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--duration", type=float, default=60.0, help="scenario seconds of the vehicle")
    ap.add_argument("--stack", type=int, nargs="+", default=[1, 5, 10, 20, 50, 200])
    ap.add_argument("--json", action="store_true")
    args = ap.parse_args()
    share = vehicle_share(args.duration)
    costs = epoch_costs(share["shapes"], args.stack)
    epochs_per_s = share["calls_per_vehicle_s"]["discretise"]
    res = {"vehicle": {k: v for k, v in share.items() if k != "shapes"}, "epochs": costs}
    if args.json:
        print(json.dumps(res, indent=2))
        return 0
    cpu = share["cpu_ms_per_vehicle_s"]
    num = share["numerics_ms_per_vehicle_s"]
    print(
        f"one vehicle through VehicleLoop ({args.duration:.0f} s, ImuBatch of 10, 10 Hz fixes): "
        f"{cpu:.2f} ms CPU per vehicle-second ({share['cpu_ms_per_vehicle_s_timed']:.2f} timed; "
        f"wrapper {share['wrapper_us']:.2f} us a call, taken off)"
    )
    for name, ms in num.items():
        calls = share["calls_per_vehicle_s"][name]
        each = 1e3 * ms / max(calls, 1)
        print(f"  {name:22s} {ms:6.3f} ms per vehicle-second ({calls:5.1f} calls, {each:6.1f} us each)")
    total = sum(num.values())
    print(f"  the numerics: {total:.2f} ms, {100 * share['numerics_share']:.1f} % of the vehicle")
    print(
        "per vehicle-epoch, the vehicle's own first arguments (discretise + predict + update + PD "
        f"test), {epochs_per_s:.1f} epochs a second:"
    )
    # the vehicle's own numerics of the epoch (F and Qc excluded), scaled by what stacking saved
    # on the same calls in the loop above: the ratio, not the difference of two noisy times
    own = sum(num[k] for k in ("discretise", "predict", "update", "is_positive_definite"))
    for c in costs:
        saved = own * (1.0 - c["stacked_us"] / c["one_at_a_time_us"])  # ms per vehicle-second
        c["vehicle_ms_bound"] = cpu - saved
        print(
            f"  K = {c['K']:4d}: one at a time {c['one_at_a_time_us']:6.1f} us, stacked "
            f"{c['stacked_us']:6.1f} us -> the vehicle at best {cpu - saved:.2f} ms per vehicle-second "
            f"({100 * saved / cpu:.0f} % saved, {cpu / (cpu - saved):.2f}x)"
        )
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
