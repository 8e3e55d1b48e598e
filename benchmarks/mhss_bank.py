"""MHSS bank benchmark (seed 001): 12 satellites with sub-sub filters, 10 Hz GNSS, 100 Hz IMU.

1. Real-time factor of the tightly coupled pipeline with integrity on one core: 12 satellites
   (BDS + GPS, the 12 highest), main + 12 sub-filters + 66 sub-sub filters = 79 members of 17
   states plus 12 + 132 cross-covariance blocks, 100 Hz IMU, 10 Hz pseudoranges and range rates
   (24 rows), MHSS tests, the satellite residual test and exclusion search every epoch. The
   pipeline is driven directly (no engine, no message decoding): the filter's own cost (a
   service's worker spends about a quarter more on the same vehicle: 6.). Goal (issue 21):
   >= 100x real time. Timed after an untimed 20 s run in the same process (the steady state: a
   process's first epoch pays imports and first calls once).
2. The bank's arithmetic per GNSS epoch, counted from the shapes (:func:`bank_flops`: every
   matrix product 2 m k n, Cholesky n^3 / 3, inverse 2 n^3; elementwise work not counted), the
   GFLOP/s it achieves (per epoch of the whole pipeline and per second spent in the bank's
   predict + update) and the fraction of one core's peak, measured here as the best of a few
   1000 x 1000 @ 1000 x 1000 float64 products on one thread.
3. ``--baseline REV``: the same pipeline run from another revision (``git archive REV``, e.g. the
   commit before issue 21), alternating with this tree in fresh processes, ``--repeat`` times
   each: the before/after ratio measured on the same machine at the same time (the machine is
   shared; the median of the ratios of neighbouring runs is reported).
4. The same bank (predict at 10 Hz + one update per epoch, members and cross blocks) against a
   loop of independent filter objects doing the same arithmetic one member / one block at a time
   (numpy per object, the usual way of writing MHSS), on identical inputs; both results agree to
   rounding and the speed-up ratio is measured in the same run.

5. The bank with its cross blocks tied (mhss.py, "Tied cross blocks": the members only) against
   the same pipeline computing every block (its cost after an exclusion), epochs in turn in one
   process (:func:`bench_lockstep`): the ratio of their per-epoch medians, which the machine's
   minute-to-minute speed does not move as it moves separate runs.

6. The same data through the service's per-vehicle loop (:func:`bench_service_loop`:
   ``VehicleLoop.process`` with an InitialNav, ImuBatch payloads of 10 and JSON GnssRaw, the
   engine's rules and shared minor loop, every output built and serialised; no Zenoh) against the
   pipeline driven as in 1., epochs in turn in one process: what a service's worker really spends
   on an MHSS vehicle. Both run the same filter (final positions within 1e-7 m,
   tests/test_mhss_service_loop.py).

Usage: OPENBLAS_NUM_THREADS=1 .venv/bin/python benchmarks/mhss_bank.py [--duration 60] [--epochs 100]
       [--baseline REV [--repeat 3]] [--json]
"""

from __future__ import annotations

import argparse
import itertools
import json
import os
import statistics
import subprocess
import sys
import tempfile
import time

os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")

import numpy as np  # noqa: E402

from fednav.service import earth  # noqa: E402
from fednav.service.config import ImuModel, TightlyCoupledConfig  # noqa: E402
from fednav.service.estimation.integrity.mhss import MhssBank, cross_update  # noqa: E402
from fednav.service.ins.mechanisation import NavState  # noqa: E402
from fednav.service.pipelines.base import InitStd  # noqa: E402
from fednav.service.pipelines.tightly_coupled import TightlyCoupled  # noqa: E402
from fednav.simulators.gnss.raw_sensor import GnssRawSensor, GnssRawSpec  # noqa: E402
from fednav.simulators.trajectory import (  # noqa: E402
    StartSpec,
    StraightSegment,
    TurnSegment,
    build_trajectory,
)

T0 = 1_300_000_000.0
N_SAT = 12
#: sensor seconds of the untimed warm-up run before each timed one
WARMUP_S = 20.0


def make_inputs(duration_s: float):
    start = StartSpec(lat_deg=40.1, lon_deg=118.6, height_m=1000.0, heading_deg=45.0, speed_mps=100.0)
    traj = build_trajectory(
        start,
        [
            StraightSegment(kind="straight", duration_s=min(30.0, duration_s / 2)),
            TurnSegment(
                kind="turn",
                duration_s=min(30.0, duration_s / 2),
                turn_rate_dps=3.0,
                ramp_s=min(5.0, duration_s / 4),  # (a run shorter than 20 s: a shorter ramp)
            ),
        ],
        100.0,
        T0,
        duration_s=duration_s,
    )
    spec = GnssRawSpec(
        rate_hz=10.0,
        constellations=("BDS", "GPS"),
        selection="highest_elevation",
        selection_count=N_SAT,
        elevation_mask_deg=5.0,
        pseudorange_sigma_m=0.4,
    )
    sensor = GnssRawSensor(spec, seed=1)
    msgs = {}
    for k in range(10, len(traj.t_s), 10):
        st = traj.state_at(traj.t_s[k])
        c_en = earth.mat_en(st.llh[0], st.llh[1])
        msgs[k] = sensor.measure(traj.t_s[k], earth.llh_to_ecef(st.llh), c_en @ st.vel_enu_mps).message
    return traj, msgs


def make_pipeline(traj) -> TightlyCoupled:
    """The measured pipeline, initialised at the trajectory's true start (also
    ``benchmarks/instructions.py --mhss``)."""
    p = TightlyCoupled(TightlyCoupledConfig(name="tc"), ImuModel(), 0.1)
    s0 = traj.state_at(T0)
    nav = NavState(
        T0,
        s0.llh[0],
        s0.llh[1],
        s0.llh[2],
        s0.vel_enu_mps.copy(),
        earth.mat_to_quat(earth.rpy_to_mat_nb(s0.rpy_rad)),
    )
    p.initialise(nav, InitStd(np.full(3, 5.0), np.full(3, 0.2), np.radians([0.05, 0.05, 0.2])))
    return p


def bench_pipeline(duration_s: float, time_bank: bool = True) -> dict:
    """Run the pipeline over ``duration_s`` of data; ``time_bank`` also times the bank's own
    predict and update calls (``bank_s``)."""
    traj, msgs = make_inputs(duration_s)
    p = make_pipeline(traj)
    dth = [tuple(r) for r in traj.dtheta_rad]
    dv = [tuple(r) for r in traj.dvel_mps]
    dt = traj.dt_s
    bank_s = [0.0]
    originals = {name: getattr(MhssBank, name) for name in ("predict", "update")}

    def timed(f):
        def g(*args, **kwargs):
            t = time.perf_counter()
            try:
                return f(*args, **kwargs)
            finally:
                bank_s[0] += time.perf_counter() - t

        return g

    if time_bank:
        for name, f in originals.items():
            setattr(MhssBank, name, timed(f))
    try:
        wall0, cpu0 = time.perf_counter(), time.process_time()
        detections = epochs = 0
        for k in range(1, len(traj.t_s)):
            p.push_imu(dth[k], dv[k], dt, float(traj.t_s[k]))
            if k in msgs:
                p.sync()
                p.apply("gnss_raw", "main", msgs[k], 0.0)
                detections += p.last.detected
                epochs += 1
        wall, cpu = time.perf_counter() - wall0, time.process_time() - cpu0
    finally:
        for name, f in originals.items():
            setattr(MhssBank, name, f)
    mh = p.bank.mhss
    return {
        "satellites": mh.N,
        "members": mh.B,
        "blocks": len(mh.blocks),
        "tied": mh.tied,
        "imu_hz": 100,
        "gnss_hz": 10,
        "sensor_s": duration_s,
        "wall_s": wall,
        "cpu_s": cpu,
        "realtime_factor": duration_s / wall,
        "realtime_factor_cpu": duration_s / cpu,
        "gnss_epochs": epochs,
        "bank_s": bank_s[0] if time_bank else None,
        "detections": detections,
    }


def bench_lockstep(duration_s: float, skip_epochs: int = 50) -> dict:
    """The pipeline with tied cross blocks against the same pipeline computing every block (its
    cost after an exclusion), in one process, epoch by epoch in turn (which goes first alternates):
    both see the same minute of the machine, so the ratio of their per-epoch times holds where
    separate runs do not. Per epoch: its 10 IMU samples and the GNSS epoch; the first
    ``skip_epochs`` are left out (first calls)."""
    traj, msgs = make_inputs(duration_s)
    pipes = {"tied": make_pipeline(traj), "untied": make_pipeline(traj)}
    pipes["untied"].bank.mhss.tied = False
    dth = [tuple(r) for r in traj.dtheta_rad]
    dv = [tuple(r) for r in traj.dvel_mps]
    per_epoch: dict[str, list[float]] = {k: [] for k in pipes}
    cur = dict.fromkeys(pipes, 0.0)
    for k in range(1, len(traj.t_s)):
        for name in ("tied", "untied") if k % 2 else ("untied", "tied"):
            p = pipes[name]
            t0 = time.perf_counter()
            p.push_imu(dth[k], dv[k], traj.dt_s, float(traj.t_s[k]))
            if k in msgs:
                p.sync()
                p.apply("gnss_raw", "main", msgs[k], 0.0)
            cur[name] += time.perf_counter() - t0
            if k in msgs:
                per_epoch[name].append(cur[name])
                cur[name] = 0.0
    tied = np.array(per_epoch["tied"][skip_epochs:])
    untied = np.array(per_epoch["untied"][skip_epochs:])
    return {
        "epochs": len(tied),
        "tied_ms_median": 1e3 * float(np.median(tied)),
        "untied_ms_median": 1e3 * float(np.median(untied)),
        "ratio_median": float(np.median(untied / tied)),
        "still_tied": pipes["tied"].bank.mhss.tied,
    }


class _Digest:
    """The service's publisher stand-in: every output serialised (as the service does), counted."""

    def __init__(self) -> None:
        self.n = 0

    def publish(self, key: str, msg) -> None:
        msg.to_json()
        self.n += 1


def service_loop_inputs(traj, msgs, imu_batch: int = 10) -> list[tuple[str, str, bytes]]:
    """The same data as the wire carries it to a service: an InitialNav at the true start (the
    pipeline's own initial sigmas), ImuBatch payloads of ``imu_batch`` samples (cut at each GNSS
    epoch), each GnssRaw as its JSON document; (kind, sensor id, payload) for ``VehicleLoop.process``."""
    from fednav.service import imu_batch as ib
    from fednav.service.messages import InitialNav

    s0 = traj.state_at(T0)
    init = InitialNav(
        t=T0,
        lat_deg=float(np.degrees(s0.llh[0])),
        lon_deg=float(np.degrees(s0.llh[1])),
        height_m=float(s0.llh[2]),
        vel_enu_mps=tuple(float(x) for x in s0.vel_enu_mps),
        rpy_deg=tuple(earth.rpy_msg_deg(s0.rpy_rad)),
        pos_std_enu_m=(5.0, 5.0, 5.0),
        vel_std_enu_mps=(0.2, 0.2, 0.2),
        rpy_std_deg=(0.05, 0.05, 0.2),
    )
    out = [("init", "", init.model_dump_json().encode())]
    rows: list[tuple] = []
    for k in range(1, len(traj.t_s)):
        rows.append((float(traj.t_s[k]), traj.dt_s, *traj.dtheta_rad[k], *traj.dvel_mps[k]))
        if len(rows) == imu_batch or k in msgs:
            out.append(("imu", "main", ib.encode(np.array(rows))))
            rows = []
        if k in msgs:
            out.append(("gnss_raw", "main", msgs[k].model_dump_json().encode()))
    return out


def bench_service_loop(duration_s: float, imu_batch: int = 10, skip_epochs: int = 50) -> dict:
    """The pipeline as :func:`bench_pipeline` drives it against the same data through the
    service's per-vehicle loop (``VehicleLoop.process``: ImuBatch and JSON decoding, validation, the
    engine's rules and shared minor loop, the pipeline, every output built and serialised; no
    Zenoh), epoch by epoch in turn in one process (which goes first alternates), thread CPU time:
    what a service's worker spends on an MHSS vehicle, and how much more than the pipeline alone.
    The first ``skip_epochs`` are left out (first calls)."""
    from fednav.service.app import OutputSink
    from fednav.service.config import ServiceConfig
    from fednav.service.vehicle import VehicleLoop, tune_gc

    traj, msgs = make_inputs(duration_s)
    p = make_pipeline(traj)
    dth = [tuple(r) for r in traj.dtheta_rad]
    dv = [tuple(r) for r in traj.dvel_mps]
    inputs = service_loop_inputs(traj, msgs, imu_batch)
    config = ServiceConfig.model_validate(
        {
            "vehicles": ["*"],
            "init": {"mode": "message"},
            "pipelines": [{"name": "tc", "kind": "tightly_coupled"}],
        }
    )
    tune_gc()
    pubs = _Digest()
    loop = VehicleLoop("v1", config, OutputSink("fednav", pubs, None, vehicle_interval_s=0.0))
    loop.process(*inputs[0])  # the InitialNav
    j = 1
    k = 1
    direct, served = [], []
    for epoch in range(len(msgs)):
        k_end = sorted(msgs)[epoch]
        j_end = j
        while inputs[j_end][0] != "gnss_raw":
            j_end += 1
        for first in ("direct", "loop") if epoch % 2 else ("loop", "direct"):
            c0 = time.thread_time()
            if first == "direct":
                for i in range(k, k_end + 1):
                    p.push_imu(dth[i], dv[i], traj.dt_s, float(traj.t_s[i]))
                p.sync()
                p.apply("gnss_raw", "main", msgs[k_end], 0.0)
                direct.append(time.thread_time() - c0)
            else:
                for kind, sid, payload in inputs[j : j_end + 1]:
                    loop.process(kind, sid, payload)
                served.append(time.thread_time() - c0)
        k, j = k_end + 1, j_end + 1
    d = np.array(direct[skip_epochs:])
    v = np.array(served[skip_epochs:])
    epoch_s = 1.0 / 10.0
    return {
        "epochs": len(d),
        "imu_batch": imu_batch,
        "pipeline_ms_per_epoch": 1e3 * float(d.mean()),
        "service_loop_ms_per_epoch": 1e3 * float(v.mean()),
        "pipeline_realtime_factor": epoch_s / float(d.mean()),
        "service_loop_realtime_factor": epoch_s / float(v.mean()),
        "ratio_median": float(np.median(v / d)),
        "outputs": pubs.n,
        "refused": dict(loop.counters),
        # the two ran the same filter on the same data: their final positions, m apart
        "position_difference_m": float(
            np.linalg.norm(
                earth.llh_to_ecef(loop.engine.pipelines[0].estimate().nav.llh)
                - earth.llh_to_ecef(p.estimate().nav.llh)
            )
        ),
    }


# --- arithmetic per epoch -----------------------------------------------------------------------------
def _mm(m: int, k: int, n: int) -> int:
    """FLOPs of an (m, k) @ (k, n) product."""
    return 2 * m * k * n


def bank_flops(N: int = N_SAT, n: int = 17, s: int = 8, rows_per_sat: int = 2, tied: bool = True) -> dict:
    """FLOPs of one GNSS epoch of the bank (one predict + one update, depth 2), from the shapes of
    the products in ``service/estimation/integrity/mhss.py`` (``MhssBank.predict``,
    ``_masked_gain``, ``MhssBank._joseph_observed``): N satellites, n states, s states the
    rows observe (position, velocity, clock), m = rows_per_sat N rows. Also the same epoch as the
    bank computed it before issue 21 (``kalman.gain``: m x m Cholesky and triangular solves on
    the dense H; Joseph as (I - K_a H) P (I - K_b H)' + K_a R K_b'), for comparison. ``tied``: the
    cross blocks are their reference members' covariances and only the B members are computed
    (mhss.py, "Tied cross blocks"); False: every block, as after an exclusion."""
    m = rows_per_sat * N
    B = 1 + N + N * (N - 1) // 2
    K = B + N + N * (N - 1)  # member covariances + main-sub + sub-subsub cross blocks
    computed = B if tied else K
    predict = computed * 2 * _mm(n, n, n)
    gain = B * (
        _mm(1, n, m)  # innovations z - H x
        + _mm(1, m, s * s)  # J = G_a' R^-1 G_a from the rows' g g' / r
        + _mm(s, s, s)  # J C
        + s**3 // 3  # Cholesky of C (the positive-definiteness check)
        + 2 * s**3  # (I + J C)^-1
        + _mm(n, s, s)  # L = P E' (I + J C)^-1
        + _mm(1, m, s)
        + _mm(n, s, 1)  # x update L G_a' R^-1 r
    )
    # per member L J and W = J L'; per block T = P - (L_a J_a)(E P), P <- T + (L_a - T E') W_b
    joseph = B * (_mm(n, s, s) + _mm(s, s, n)) + computed * 2 * _mm(n, s, n)
    ref_gain = B * (
        _mm(n, n, m)  # P H'
        + _mm(m, n, m)  # H P H'
        + m**3 // 3  # Cholesky of S
        + m * m * (n + 1)  # forward substitution, n + 1 right-hand sides
        + m * m * n  # back substitution
        + _mm(n, m, 1)
        + _mm(n, m, n)  # K H
    )
    ref_joseph = K * (2 * _mm(n, n, n) + _mm(n, m, n))
    return {
        "satellites": N,
        "members": B,
        "blocks": K,
        "computed_blocks": computed,
        "rows": m,
        "predict": predict,
        "gain": gain,
        "joseph": joseph,
        "total": predict + gain + joseph,
        "before_issue_21": K * 2 * _mm(n, n, n) + ref_gain + ref_joseph,
    }


def peak_gflops(size: int = 1000, repeat: int = 5) -> float:
    """One core's float64 matrix-product rate: best of ``repeat`` (size x size) @ (size x size)."""
    rng = np.random.default_rng(0)
    a, b = rng.normal(size=(size, size)), rng.normal(size=(size, size))
    a @ b
    best = min(_timed(lambda: a @ b) for _ in range(repeat))
    return _mm(size, size, size) / best / 1e9


def _timed(f) -> float:
    t = time.perf_counter()
    f()
    return time.perf_counter() - t


# --- before / after on the same machine ------------------------------------------------------------------
_RUN = "import json, sys; sys.path.insert(0, sys.argv[1]); import mhss_bank as mb; "
_RUN += "kw = {} if sys.argv[3] == 'old' else {'time_bank': False}; "
_RUN += f"mb.bench_pipeline({WARMUP_S}, **kw); "  # first-use costs out of the timed run (see main)
_RUN += "r = mb.bench_pipeline(float(sys.argv[2]), **kw); "
_RUN += "print(json.dumps({k: r[k] for k in ('realtime_factor', 'realtime_factor_cpu', 'wall_s')}))"


def _run_tree(bench_dir: str, duration_s: float, pythonpath: str | None, kind: str) -> dict:
    env = dict(os.environ, OPENBLAS_NUM_THREADS=os.environ.get("OPENBLAS_NUM_THREADS", "1"))
    if pythonpath:
        env["PYTHONPATH"] = pythonpath + os.pathsep + env.get("PYTHONPATH", "")
    out = subprocess.run(
        [sys.executable, "-c", _RUN, bench_dir, str(duration_s), kind],
        env=env,
        check=True,
        capture_output=True,
        text=True,
    ).stdout
    return json.loads(out.strip().splitlines()[-1])


def bench_baseline(rev: str, duration_s: float, repeat: int) -> dict:
    """Real-time factors of revision ``rev`` and of this tree, alternating in fresh processes.

    ``rev`` is exported with ``git archive`` and imported as ``fednav`` ahead of the installed
    (editable) package through a throw-away namespace folder of links; this tree's runs import
    ``fednav`` as this process does (PYTHONPATH inherited)."""
    here = os.path.dirname(os.path.abspath(__file__))
    for where in (here, os.getcwd()):  # this tree, or (run from an exported tree) the current folder
        top = subprocess.run(
            ["git", "-C", where, "rev-parse", "--show-toplevel"], capture_output=True, text=True
        )
        if top.returncode == 0:
            repo = top.stdout.strip()
            break
    else:
        raise SystemExit("--baseline needs a git repository (this tree or the current folder)")
    commit = subprocess.run(
        ["git", "-C", repo, "rev-parse", "--short", rev], check=True, capture_output=True, text=True
    ).stdout.strip()
    with tempfile.TemporaryDirectory(prefix="mhss_baseline_") as tmp:
        tree = os.path.join(tmp, "tree")
        os.makedirs(tree)
        archive = subprocess.run(
            ["git", "-C", repo, "archive", commit], check=True, capture_output=True
        ).stdout
        subprocess.run(["tar", "-x", "-C", tree], input=archive, check=True)
        shim = os.path.join(tmp, "shim", "fednav")
        os.makedirs(shim)
        for d in ("service", "simulators", "dashboards", "replay"):
            if os.path.isdir(os.path.join(tree, d)):
                os.symlink(os.path.join(tree, d), os.path.join(shim, d))
        before, after = [], []
        for _ in range(repeat):
            before.append(
                _run_tree(os.path.join(tree, "benchmarks"), duration_s, os.path.dirname(shim), "old")
            )
            after.append(_run_tree(here, duration_s, None, "new"))
    ratios = [a["realtime_factor"] / b["realtime_factor"] for a, b in zip(after, before, strict=True)]
    ratios_cpu = [
        a["realtime_factor_cpu"] / b["realtime_factor_cpu"] for a, b in zip(after, before, strict=True)
    ]
    return {
        "baseline": commit,
        "repeat": repeat,
        "before_realtime_factor": [r["realtime_factor"] for r in before],
        "after_realtime_factor": [r["realtime_factor"] for r in after],
        "before_realtime_factor_cpu": [r["realtime_factor_cpu"] for r in before],
        "after_realtime_factor_cpu": [r["realtime_factor_cpu"] for r in after],
        "speedup_median": statistics.median(ratios),
        "speedup_cpu_median": statistics.median(ratios_cpu),
    }


# --- loop of independent filter objects -----------------------------------------------------------
class Filter:
    """One Kalman filter (17 states) that ignores the rows of its excluded satellites."""

    def __init__(self, x, P, excluded):
        self.x, self.P, self.excluded = x.copy(), P.copy(), set(excluded)
        self.K = self.IKH = None

    def predict(self, Phi, Qd):
        self.x = Phi @ self.x
        self.P = Phi @ self.P @ Phi.T + Qd

    def update(self, z, H, r_var, row_sat):
        keep = np.array([s not in self.excluded for s in row_sat])
        Hk, zk, rk = H[keep], z[keep], r_var[keep]
        S = Hk @ self.P @ Hk.T + np.diag(rk)
        L = np.linalg.cholesky(S)
        Kk = np.linalg.solve(L.T, np.linalg.solve(L, Hk @ self.P)).T
        K = np.zeros((len(self.x), len(z)))
        K[:, keep] = Kk
        self.x = self.x + Kk @ (zk - Hk @ self.x)
        IKH = np.eye(len(self.x)) - K @ H
        self.P = IKH @ self.P @ IKH.T + (K * r_var) @ K.T
        self.K, self.IKH = K, IKH


class Cross:
    """Cross-covariance of two filter objects, P_ab."""

    def __init__(self, a: Filter, b: Filter, P):
        self.a, self.b, self.P = a, b, P.copy()

    def predict(self, Phi, Qd):
        self.P = Phi @ self.P @ Phi.T + Qd

    def update(self, r_var):
        self.P = cross_update(self.P, self.a.IKH, self.b.IKH, self.a.K, self.b.K, r_var)


def bench_bank_vs_loop(epochs: int, n_states: int = 17, steps_per_epoch: int = 1) -> dict:
    rng = np.random.default_rng(3)
    sats = [f"S{i:02d}" for i in range(N_SAT)]
    A = rng.normal(size=(n_states, n_states))
    P0 = A @ A.T / n_states + np.eye(n_states)
    Phi = np.eye(n_states) + 0.01 * rng.normal(size=(n_states, n_states))
    Qd = 1e-3 * np.eye(n_states)
    H = np.zeros((2 * N_SAT, n_states))
    H[:N_SAT, :3] = rng.normal(size=(N_SAT, 3))
    H[:N_SAT, 15] = 1.0
    H[N_SAT:, 3:6] = rng.normal(size=(N_SAT, 3))
    H[N_SAT:, 16] = 1.0
    row_sat = np.concatenate([np.arange(N_SAT), np.arange(N_SAT)])
    r_var = np.concatenate([np.full(N_SAT, 0.16), np.full(N_SAT, 0.0025)])
    zs = [rng.normal(size=2 * N_SAT) for _ in range(epochs)]

    bank = MhssBank.initial(np.zeros(n_states), P0, sats, depth=2)
    filters = [Filter(np.zeros(n_states), P0, [sats[i] for i in e]) for e in bank.members]
    crosses = [
        Cross(filters[a], filters[b], P0) for a, b in zip(bank.pa[bank.B :], bank.pb[bank.B :], strict=True)
    ]
    row_ids = [sats[i] for i in row_sat]

    def run_bank():
        for z in zs:
            for _ in range(steps_per_epoch):
                bank.predict(Phi, Qd)
            bank.update(z, H, r_var, row_sat)

    def run_loop():
        for z in zs:
            for _ in range(steps_per_epoch):
                for f in filters:
                    f.predict(Phi, Qd)
                for c in crosses:
                    c.predict(Phi, Qd)
            for f in filters:
                f.update(z, H, r_var, row_ids)
            for c in crosses:
                c.update(r_var)

    t = time.perf_counter()
    run_bank()
    t_bank = time.perf_counter() - t
    t = time.perf_counter()
    run_loop()
    t_loop = time.perf_counter() - t
    x_loop = np.array([f.x for f in filters])
    P_loop = np.array([f.P for f in filters] + [c.P for c in crosses])
    agree = bool(
        np.allclose(bank.x, x_loop, rtol=1e-7, atol=1e-9)
        and np.allclose(bank.blocks, P_loop, rtol=1e-7, atol=1e-9)
    )
    return {
        "members": bank.B,
        "cross_blocks": len(crosses),
        "epochs": epochs,
        "predicts_per_epoch": steps_per_epoch,
        "bank_ms_per_epoch": 1e3 * t_bank / epochs,
        "loop_ms_per_epoch": 1e3 * t_loop / epochs,
        "speedup": t_loop / t_bank,
        "results_agree": agree,
    }


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description="MHSS bank benchmark (seed 001)")
    ap.add_argument("--duration", type=float, default=60.0, help="pipeline run, sensor seconds")
    ap.add_argument("--epochs", type=int, default=100, help="epochs of the bank-vs-loop comparison")
    ap.add_argument("--baseline", help="also run this git revision (e.g. the commit before issue 21)")
    ap.add_argument("--repeat", type=int, default=3, help="alternating runs of each with --baseline")
    ap.add_argument("--json", action="store_true")
    a = ap.parse_args(argv)
    # a warm-up run first: what a process pays once (imports, LAPACK and scipy first calls, the
    # quantile caches) is a service's start-up, not the per-epoch cost this measures
    bench_pipeline(WARMUP_S, time_bank=False)
    pipe = bench_pipeline(a.duration)
    lock = bench_lockstep(a.duration)
    served = bench_service_loop(a.duration)
    flops = bank_flops(pipe["satellites"], tied=pipe["tied"])
    untied = bank_flops(pipe["satellites"], tied=False)
    peak = peak_gflops()
    epoch_s = pipe["wall_s"] / pipe["gnss_epochs"]
    bank_epoch_s = pipe["bank_s"] / pipe["gnss_epochs"]
    perf = {
        "flops_per_epoch": flops["total"],
        "gflops_per_pipeline_second": flops["total"] / epoch_s / 1e9,
        "gflops_per_bank_second": flops["total"] / bank_epoch_s / 1e9,
        "peak_gflops_one_core": peak,
        "bank_ms_per_epoch": 1e3 * bank_epoch_s,
        "pipeline_ms_per_epoch": 1e3 * epoch_s,
    }
    perf["fraction_of_peak_pipeline"] = perf["gflops_per_pipeline_second"] / peak
    perf["fraction_of_peak_bank"] = perf["gflops_per_bank_second"] / peak
    base = bench_baseline(a.baseline, a.duration, a.repeat) if a.baseline else None
    cmp_ = bench_bank_vs_loop(a.epochs)
    if a.json:
        out = {
            "pipeline": pipe,
            "tied_vs_untied": lock,
            "service_loop": served,
            "flops": flops,
            "flops_untied": untied,
            "performance": perf,
            "bank_vs_loop": cmp_,
        }
        if base:
            out["baseline"] = base
        print(json.dumps(out, indent=2))
        return 0
    print(
        f"tightly coupled + MHSS, {pipe['satellites']} satellites, {pipe['members']} filters "
        f"({len(list(itertools.combinations(range(pipe['satellites']), 2)))} sub-sub), "
        f"{pipe['blocks']} covariance blocks, IMU {pipe['imu_hz']} Hz, GNSS {pipe['gnss_hz']} Hz "
        f"(OPENBLAS_NUM_THREADS={os.environ.get('OPENBLAS_NUM_THREADS')}):"
    )
    print(
        f"  {pipe['sensor_s']:.0f} s of data in {pipe['wall_s']:.2f} s wall ({pipe['cpu_s']:.2f} s cpu): "
        f"{pipe['realtime_factor']:.1f}x real time (cpu {pipe['realtime_factor_cpu']:.1f}x; goal >= 100x); "
        f"{perf['pipeline_ms_per_epoch']:.2f} ms per GNSS epoch, of which the bank's predict + update "
        f"{perf['bank_ms_per_epoch']:.2f} ms"
    )
    print(
        f"  through the service's per-vehicle loop (ImuBatch of {served['imu_batch']}, JSON GnssRaw, "
        f"the engine, every output serialised; epochs in turn in one process, thread CPU): "
        f"{served['service_loop_ms_per_epoch']:.2f} ms per epoch, "
        f"{served['service_loop_realtime_factor']:.1f}x real time, against the pipeline alone "
        f"{served['pipeline_ms_per_epoch']:.2f} ms, "
        f"{served['pipeline_realtime_factor']:.1f}x (median ratio {served['ratio_median']:.2f})"
    )
    print(
        f"  tied cross blocks against every block computed (the cost after an exclusion), epochs in "
        f"turn in one process: {lock['tied_ms_median']:.2f} / {lock['untied_ms_median']:.2f} ms per "
        f"epoch (medians of {lock['epochs']}), every block computed {lock['ratio_median']:.2f}x slower"
    )
    print(
        f"  bank arithmetic per epoch: {flops['total'] / 1e6:.2f} MFLOP "
        f"(predict {flops['predict'] / 1e6:.2f}, "
        f"gains {flops['gain'] / 1e6:.2f}, "
        f"Joseph of {flops['computed_blocks']} blocks {flops['joseph'] / 1e6:.2f}"
        f"{' (tied cross blocks: the members only)' if pipe['tied'] else ''}; "
        f"{untied['total'] / 1e6:.2f} MFLOP with every block computed (after an exclusion); "
        f"{flops['before_issue_21'] / 1e6:.2f} MFLOP as computed before issue 21)"
    )
    print(
        f"  {perf['gflops_per_pipeline_second']:.1f} GFLOP/s over the whole epoch, "
        f"{perf['gflops_per_bank_second']:.1f} GFLOP/s over the bank's own time; one-core peak "
        f"(1000 x 1000 matmul) {peak:.1f} GFLOP/s: {100 * perf['fraction_of_peak_pipeline']:.1f} % / "
        f"{100 * perf['fraction_of_peak_bank']:.1f} % of it"
    )
    if base:
        print(
            f"  same machine, alternating fresh processes, {base['repeat']} each: {base['baseline']} "
            + " ".join(f"{v:.1f}x" for v in base["before_realtime_factor"])
            + " | this tree "
            + " ".join(f"{v:.1f}x" for v in base["after_realtime_factor"])
            + f" -> speed-up {base['speedup_median']:.2f}x wall, {base['speedup_cpu_median']:.2f}x cpu "
            "(medians over neighbouring pairs)"
        )
    print(
        f"bank vs a loop of {cmp_['members']} filter objects + {cmp_['cross_blocks']} cross blocks, "
        f"{cmp_['epochs']} epochs (predict + update): bank {cmp_['bank_ms_per_epoch']:.2f} ms/epoch, "
        f"loop {cmp_['loop_ms_per_epoch']:.2f} ms/epoch -> speed-up {cmp_['speedup']:.1f}x "
        f"(results agree: {cmp_['results_agree']})"
    )
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
