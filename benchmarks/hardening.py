"""Hardening figures: single hostile messages (issue 9) and transient corruption (issue 22),
in-process through the service's engine (the same code as the service).

    .venv/bin/python benchmarks/hardening.py                 # both parts, seed 7
    .venv/bin/python benchmarks/hardening.py --part transient --runs 3 --markdown docs/hardening.md
    .venv/bin/python benchmarks/hardening.py --part single --runs 3

Single messages (``--part single``): the demo stream once clean and once with every attack of
tests/test_hostile.py injected at 100 s (one IMU sample 1e6 s ahead, an InitialNav 1000 s ahead,
a current InitialNav 11 km off, the receiver's next fix at lat 0 / lon 0 / h -12 km and the one
after claiming 1e-9 m, 50 IMU samples slipped between genuine ones, 5 star-tracker messages under
new ids): horizontal RMS and max error, with the innovation gate (default) and without it, and
the real-time factor of the clean run with and without the gate.

Transient corruption (``--part transient``), per pipeline family, each class of corruption once
into a clean stream (seeds S, S+1, ...), against the same stream clean:

- ``imu_burst``: 50 forged IMU samples (20 rad/s about x) slipped between the genuine ones, as a
  second publisher under the IMU's key delivers them at the demo's pace ``1x`` (each lands between
  two genuine samples), ``10x`` (arrival jitter +-10 ms of stream time: some arrive before the
  genuine sample they follow) and ``max`` (all at once, as fast as possible);
- ``imu_close``: forged samples close to the genuine ones (each the genuine sample's increments
  with more yaw rate), at 10x: ``0.2`` (50 samples, 0.2 rad/s more) and ``0.05x500`` (500 samples,
  5 s, 0.05 rad/s more); plausible, and the fixes agree with the state they leave for a while;
- ``imu_race``: a forger racing the IMU on its own time stamps: before each genuine sample, a copy
  on the same time stamp with the previous sample's increments and more yaw rate (``0.05x500``:
  0.05 rad/s, 500 samples, 5 s), as ``benchmarks/process_probe.py``'s ``race`` arrives in real
  time: the forged copy of each slot taken, the genuine one refused ``duplicate``;
- ``init_burst``: 500 InitialNav in 2.5 s, the true state moved 5, 20 or 100 m north, claiming
  1 cm / 0.01 m/s / 0.01 deg;
- ``drift``: a forged fix stream under the receiver's own key (between its fixes) drifting 0.1 to
  2 m/s for 30 s, claiming 1 m (the genuine receiver 10 m) and a velocity with the drift
  (underwater: the same with the USBL);
- ``drift_stamped``: the same forged stream on the receiver's own time stamps, each forged fix
  delivered just before the genuine one (a spoofer racing the receiver), 0.5 and 2 m/s;
- ``outage``: no GNSS for 60 s (fixes and raw epochs), then 5 s of fixes 50 m off: the
  receiver's solution jumps on return, its pseudoranges return as they are (underwater: the
  USBL, its relative vector 50 m off).

Per case and pipeline: the peak horizontal error from the corruption's start; the time from its
end until the error is back under the clean run's 95th percentile (``recovered``: the first epoch
after the end at which the error is under that percentile and from which on, to the end of the
run, the 95th percentile of the error is within 5 % of it, i.e. the run is as good as the clean
one again; ``never``: not before the last 10 s of the run); the same time like with like
(``like clean``: the rest of the run's 95th percentile within 5 % of the clean run's own over the
same span, so that a clean run scored against itself gives 0 s where its own late error sits above
its whole-run percentile, which the first figure counts against it); the RMS over the last 60 s
(clean in brackets); the epochs reported ``aided`` while the horizontal error exceeded 3x the reported
horizontal sigma or the height error 3x the vertical sigma (clean in brackets, same span); the
status timeline from the start (s after it).
"""

from __future__ import annotations

import argparse
import math
import sys
import time
import tomllib
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from fednav.service import earth, keys  # noqa: E402
from fednav.service.engine import VehicleEngine  # noqa: E402
from fednav.service.messages import (  # noqa: E402
    GnssFix,
    GnssRaw,
    ImuSample,
    InitialNav,
    StarAttitude,
    UsblFix,
)
from fednav.simulators.evaluate import CollectingSink, service_config  # noqa: E402
from fednav.simulators.scenario import load_scenario, parse_scenario  # noqa: E402
from fednav.simulators.stream import Simulation  # noqa: E402

SCENARIOS = ROOT / "simulators" / "scenarios"

# --- part 1: single hostile messages (issue 9) ----------------------------------------------------
ATTACK_AT_S = 100.0


def attacks(imu: ImuSample, fix: GnssFix, init: InitialNav) -> list[tuple[str, object]]:
    t = imu.t
    return [
        ("imu", imu.model_copy(update={"t": t + 1e6})),
        ("init", init.model_copy(update={"t": t + 1000.0})),
        ("init", init.model_copy(update={"t": t, "lat_deg": init.lat_deg + 0.1})),
    ] + [
        ("star", StarAttitude(t=t + 0.01 * i, rpy_deg=(20.0, -15.0, 55.0), rpy_std_deg=(0.001,) * 3))
        for i in range(5)
    ]


def replaced_fix(fix: GnssFix, n: int) -> GnssFix:
    """The receiver's n-th fix from the attack on, as the fix attacks send it in its place (a fix
    between the receiver's own is refused off_cadence before any filter sees it): the first at
    lat 0 / lon 0 / h -12 km, the second claiming 1e-9 m."""
    if n == 0:
        return fix.model_copy(update={"lat_deg": 0.0, "lon_deg": 0.0, "height_m": -11999.0})
    if n == 1:
        return fix.model_copy(update={"pos_std_enu_m": (1e-9,) * 3, "vel_std_enu_mps": (1e-9,) * 3})
    return fix


def run_single(sc, seed: int, gate: bool, attack: bool) -> tuple[float, float, float]:
    cfg = service_config(sc)
    if not gate:
        cfg = cfg.model_copy(
            update={
                "pipelines": [p.model_copy(update={"innovation_gate_sigma": None}) for p in cfg.pipelines]
            }
        )
    sink = CollectingSink()
    eng = VehicleEngine("v1", cfg, sink)
    init = fix = None
    done = False
    extra = replaced = 0
    t0 = time.perf_counter()
    for key, msg in Simulation(sc, seed=seed):
        pk = keys.parse_input(key)
        if attack and isinstance(msg, GnssFix) and msg.t - sc.t0_gps_s > ATTACK_AT_S:
            msg = replaced_fix(msg, replaced)
            replaced += 1
        eng.handle(pk.kind, pk.sensor_id, msg)
        init = msg if isinstance(msg, InitialNav) else init
        fix = msg if isinstance(msg, GnssFix) else fix
        if not attack or not isinstance(msg, ImuSample) or msg.t - sc.t0_gps_s < ATTACK_AT_S:
            continue
        if extra < 50:
            extra += 1
            eng.handle(
                "imu", "main", msg.model_copy(update={"t": msg.t + 0.005, "dvel_mps": (1.0, 1.0, 1.0)})
            )
        if not done:
            done = True
            for i, (kind, m) in enumerate(attacks(msg, fix, init)):
                eng.handle(kind, f"spoof{i}" if kind == "star" else ("main" if kind != "init" else ""), m)
    wall = time.perf_counter() - t0
    err = np.array(sink.records["lc"].err)
    h = np.hypot(err[:, 0], err[:, 1])
    return float(math.sqrt(np.mean(h * h))), float(h.max()), sc.duration_s / wall


def single_part(runs: int, seed: int) -> None:
    sc = load_scenario("demo_aircraft")
    rows = {}
    for gate in (True, False):
        for attack in (False, True):
            res = [run_single(sc, seed + i, gate, attack) for i in range(runs)]
            rows[(gate, attack)] = (
                float(np.sqrt(np.mean([r[0] ** 2 for r in res]))),
                max(r[1] for r in res),
                float(np.median([r[2] for r in res])),
            )
    print(f"demo, {runs} run(s) from seed {seed}, {sc.duration_s:.0f} s, attacks at {ATTACK_AT_S:.0f} s")
    print(f"{'gate':>6}{'input':>10}{'h RMS m':>10}{'h max m':>10}{'x real time':>13}")
    for (gate, attack), (rms, mx, rtf) in rows.items():
        label = f"{'on' if gate else 'off':>6}{'attacked' if attack else 'clean':>10}"
        print(f"{label}{rms:10.2f}{mx:10.2f}{rtf:13.0f}")
    on, off = rows[(True, False)][2], rows[(False, False)][2]
    print(f"cost of screening (clean run): {on:.0f}x real time with the gate, {off:.0f}x without")


# --- part 2: transient corruption (issue 22) ------------------------------------------------------
#: (family label, scenario builder, pipelines reported, corruption start s)
CASES = [
    ("imu_burst", "1x"),
    ("imu_burst", "10x"),
    ("imu_burst", "max"),
    ("imu_close", "0.2"),
    ("imu_close", "0.05x500"),
    ("imu_race", "0.05x500"),
    ("init_burst", 5.0),
    ("init_burst", 20.0),
    ("init_burst", 100.0),
    ("drift", 0.1),
    ("drift", 0.5),
    ("drift", 2.0),
    ("drift_stamped", 0.5),
    ("drift_stamped", 2.0),
    ("outage", 60.0),
]
#: the pace of a second publisher's samples: arrival jitter in stream seconds (None: all at once)
PACE_JITTER_S = {"1x": 0.001, "10x": 0.010, "max": None}
RECOVERY_HOLD_S = 10.0
RECOVERY_MARGIN = 1.05
#: the outage's jump also on the raw pseudoranges (a consistent 50 m shift of every range: a
#: displacement, or every satellite spoofed, not a receiver's transient; off by default)
RAW_JUMP = False


def _toml(name: str) -> dict:
    return tomllib.loads((SCENARIOS / f"{name}.toml").read_text())


def gnss_scenario(duration_s: float = 300.0, keep: tuple[str, ...] | None = None):
    """The demo aircraft with its fixes plus raw GNSS and a star tracker (demo_product's), and one
    pipeline of each GNSS family (``keep``: only these of them)."""
    d = _toml("demo_aircraft")
    p = _toml("demo_product")
    d["gnss_raw"], d["star"], d["duration_s"] = p["gnss_raw"], p["star"], duration_s
    d["service"]["pipelines"] = [
        {"name": "lc", "kind": "loosely_coupled"},
        {
            "name": "fed",
            "kind": "federated",
            "sharing": "vector_eigen",
            "fault_handling": "per_source",
            "subsystems": [
                {"name": "INS/GNSS", "sensors": ["gnss_fix"]},
                {"name": "INS/CNS", "sensors": ["star"]},
            ],
        },
        {"name": "central", "kind": "centralized", "fault_handling": "per_source"},
        {"name": "tc", "kind": "tightly_coupled", "integrity": True, "phase": "npa"},
        {"name": "imm", "kind": "imm_tightly_coupled", "likelihood": "paper", "selection_correction": False},
        {
            "name": "imm_sel",
            "kind": "imm_tightly_coupled",
            "likelihood": "gaussian",
            "selection_correction": True,
        },
    ]
    if keep is not None:
        d["service"]["pipelines"] = [q for q in d["service"]["pipelines"] if q["name"] in keep]
    return parse_scenario(d, "hardening: demo aircraft with raw GNSS and a star tracker")


def demo_scenario(duration_s: float = 300.0):
    """The main job's scenario as it is (``make demo``: demo_product, its three pipelines and its
    own faults: the 40-55 s GNSS step, the 30-110 s GEO3 ramp, in the clean run too), run for
    ``duration_s`` (straight on after its last turn): what a probe of the running demo sees."""
    d = _toml("demo_product")
    d["duration_s"] = duration_s
    return parse_scenario(d, f"hardening: demo_product, {duration_s:.0f} s")


def ta_scenario():
    d = _toml("seed002_wing")
    d["service"]["pipelines"] = [p for p in d["service"]["pipelines"] if p["name"] == "ta_akf"]
    return parse_scenario(d, "hardening: seed002_wing, ta_akf")


def underwater_scenario(duration_s: float = 400.0):
    d = _toml("seed004_nominal")
    d["duration_s"] = duration_s
    keep = ("fed_edop", "centralized")
    d["service"]["pipelines"] = [p for p in d["service"]["pipelines"] if p["name"] in keep]
    for p in d["service"]["pipelines"]:
        if p["name"] == "centralized":
            p["name"], p["usbl_fault_handling"] = "centralized_chi2", "chi2_reconfig"
    return parse_scenario(d, "hardening: seed004_nominal, 400 s")


#: family -> (scenario builder, {pipeline: family label}, corruption start s, position aiding kind)
FAMILIES = {
    "gnss": (
        gnss_scenario,
        {
            "lc": "loosely_coupled",
            "fed": "federated",
            "central": "centralized",
            "tc": "tightly_coupled",
            "imm": "imm_tightly_coupled (the paper's likelihood)",
            "imm_sel": "imm_tightly_coupled (recommended: log-Gaussian, selection correction)",
        },
        100.0,
        "gnss_fix",
    ),
    "demo": (
        demo_scenario,
        {"lc": "demo: loosely_coupled", "fed": "demo: federated", "tc_mhss": "demo: tightly_coupled (MHSS)"},
        140.0,
        "gnss_fix",
    ),
    "ta": (ta_scenario, {"ta_akf": "transfer_alignment"}, 100.0, "gnss_fix"),
    "underwater": (
        underwater_scenario,
        {"fed_edop": "underwater (federated)", "centralized_chi2": "underwater (centralised)"},
        150.0,
        "usbl",
    ),
}


class StatusSink:
    """Per pipeline: time, errors, sigmas and status at every output epoch."""

    def __init__(self):
        self.rec: dict[str, tuple[list, list, list, list]] = {}

    def on_estimate(self, vehicle, out) -> None:
        if out.err9 is None:
            return
        r = self.rec.setdefault(out.name, ([], [], [], []))
        r[0].append(out.t)
        r[1].append(out.err9)
        r[2].append(np.sqrt(np.clip(np.diagonal(out.P9), 0.0, None)))
        r[3].append(out.pipeline.current_status(out.t))

    def on_output(self, vehicle, msg, err9=None) -> None:
        pass

    def on_truth(self, vehicle, truth) -> None:
        pass


def _moved(lat_rad: float, lon_rad: float, h: float, north_m: float, east_m: float = 0.0):
    r_m, r_n = earth.radii(lat_rad)
    return lat_rad + north_m / (r_m + h), lon_rad + east_m / ((r_n + h) * math.cos(lat_rad))


def forged_init(traj, t: float, north_m: float) -> InitialNav:
    """The InitialNav of an ``init_burst``: the true state at ``t`` moved ``north_m`` north,
    claiming 1 cm / 0.01 m/s / 0.01 deg."""
    s = traj.state_at(t)
    lat, lon = _moved(s.llh[0], s.llh[1], s.llh[2], north_m)
    return InitialNav(
        t=t,
        lat_deg=math.degrees(lat),
        lon_deg=math.degrees(lon),
        height_m=float(s.llh[2]),
        vel_enu_mps=tuple(float(v) for v in s.vel_enu_mps),
        rpy_deg=tuple(earth.rpy_msg_deg(s.rpy_rad)),
        pos_std_enu_m=(0.01,) * 3,
        vel_std_enu_mps=(0.01,) * 3,
        rpy_std_deg=(0.01,) * 3,
    )


def _shift_fix(msg: GnssFix, north_m: float) -> GnssFix:
    lat, lon = _moved(math.radians(msg.lat_deg), math.radians(msg.lon_deg), msg.height_m, north_m)
    return msg.model_copy(update={"lat_deg": math.degrees(lat), "lon_deg": math.degrees(lon)})


def _shift_raw(msg: GnssRaw, traj, north_m: float) -> GnssRaw:
    """Pseudoranges of a receiver ``north_m`` further north (line-of-sight projection)."""
    s = traj.state_at(msg.t)
    llh = np.asarray(s.llh, dtype=float)
    r = earth.llh_to_ecef(llh)
    d = earth.enu_to_ecef(np.array([0.0, north_m, 0.0]), llh) - r
    sats = []
    for o in msg.sats:
        u = np.asarray(o.sat_pos_ecef_m) - r
        u /= np.linalg.norm(u)
        sats.append(o.model_copy(update={"pseudorange_m": o.pseudorange_m - float(u @ d)}))
    return msg.model_copy(update={"sats": sats})


def _close(arg: str) -> tuple[float, int]:
    """An ``imu_close`` case's (extra yaw rate rad/s, number of samples): "0.2" or "0.05x500"."""
    rate, _, n = arg.partition("x")
    return float(rate), int(n or 50)


@dataclass
class Injector:
    """One corruption injected into a scenario's stream (module docstring)."""

    kind: str | None
    arg: object
    start_s: float
    aiding: str
    rng: np.random.Generator
    end_s: float = 0.0
    queue: list = field(default_factory=list)
    drift_last: float = -1.0
    race_prev: object = None

    def __post_init__(self):
        self.end_s = self.start_s
        if self.kind == "init_burst":
            self.end_s = self.start_s + 2.5
        elif self.kind in ("drift", "drift_stamped"):
            self.end_s = self.start_s + 30.0
        elif self.kind == "outage":
            self.end_s = self.start_s + float(self.arg) + 5.0
        elif self.kind == "imu_burst":
            self.end_s = self.start_s + 0.5
        elif self.kind in ("imu_close", "imu_race"):
            self.end_s = self.start_s + 0.01 * _close(self.arg)[1]

    def filter(self, pk, msg, t_rel: float, traj):
        """The genuine message as delivered (None: dropped)."""
        if self.kind != "outage" or pk.kind not in ("gnss_fix", "gnss_raw", "usbl"):
            return msg
        if pk.kind != self.aiding and not (self.aiding == "gnss_fix" and pk.kind == "gnss_raw"):
            return msg
        t_back = self.start_s + float(self.arg)
        if self.start_s <= t_rel < t_back:
            return None
        if t_back <= t_rel < t_back + 5.0:  # the jump on return (of the receiver's solution: the
            if isinstance(msg, GnssFix):  # pseudoranges themselves return as they are)
                return _shift_fix(msg, 50.0)
            if isinstance(msg, GnssRaw) and RAW_JUMP:
                return _shift_raw(msg, traj, 50.0)
            if isinstance(msg, UsblFix):
                rel = list(msg.rel_b_m)
                rel[1] += 50.0
                return msg.model_copy(update={"rel_b_m": tuple(rel)})
        return msg

    def after(self, pk, msg, t_rel: float, traj, last: dict) -> list[tuple[str, str, object]]:
        """Forged messages delivered after the genuine ``msg`` (kind, sensor id, message)."""
        out = []
        if self.kind in ("imu_burst", "imu_close") and pk.kind == "imu":
            if abs(t_rel - self.start_s) < 0.5 * msg.dt_s and not self.queue and not last.get("burst"):
                last["burst"] = True
                if self.kind == "imu_burst":
                    jitter, n, dtheta = PACE_JITTER_S[self.arg], 50, (0.2, 0.0, 0.0)
                else:  # the genuine increments, more yaw rate
                    (rate, n), a = _close(self.arg), msg.dtheta_rad
                    jitter, dtheta = PACE_JITTER_S["10x"], (a[0], a[1], a[2] + rate * msg.dt_s)
                items = []
                for k in range(n):
                    f = msg.model_copy(
                        update={"t": msg.t + 0.5 * msg.dt_s + k * msg.dt_s, "dtheta_rad": dtheta}
                    )
                    arrival = msg.t + 1e-7 * k if jitter is None else f.t + self.rng.uniform(-jitter, jitter)
                    items.append((arrival, k, f))
                self.queue = sorted(items)
                while self.queue and self.queue[0][0] <= msg.t + 1e-9:
                    _, _, m = self.queue.pop(0)
                    out.append(("imu", pk.sensor_id, m))
        if self.kind == "init_burst" and pk.kind == "imu" and self.start_s <= t_rel < self.start_s + 2.5:
            for j in range(2):  # two per 10 ms sample: 500 in 2.5 s at 100 Hz
                ti = msg.t + 0.5 * msg.dt_s * j
                out.append(("init", "", forged_init(traj, ti, float(self.arg))))
        if self.kind == "drift" and pk.kind == self.aiding and self.start_s <= t_rel < self.end_s:
            last["forge"] = (msg, t_rel)
        forge = last.get("forge")
        if self.kind == "drift" and pk.kind == "imu" and forge is not None:
            g, t_g = forge
            if t_rel >= t_g + 0.5 - 0.5 * msg.dt_s:  # half-way to the next genuine message
                last["forge"] = None
                out.append((self.aiding, "main", self._forged(g, msg.t, t_rel, traj)))
        return out

    def before(self, pk, msg, t_rel: float = 0.0, traj=None) -> list[tuple[str, str, object]]:
        """Forged messages that arrive before the genuine ``msg``: IMU samples of a burst, or
        the forged fix on the genuine one's time stamp."""
        if self.kind == "drift_stamped" and pk.kind == self.aiding and self.start_s <= t_rel < self.end_s:
            return [(self.aiding, pk.sensor_id, self._forged(msg, msg.t, t_rel, traj))]
        if self.kind == "imu_race" and pk.kind == "imu":
            prev, self.race_prev = self.race_prev, msg
            if prev is not None and self.start_s - 0.5 * msg.dt_s <= t_rel < self.end_s - 0.5 * msg.dt_s:
                # the previous sample's increments with more yaw rate, on this one's time stamp
                a = prev.dtheta_rad
                rate = _close(self.arg)[0]
                forged = msg.model_copy(
                    update={"dtheta_rad": (a[0], a[1], a[2] + rate * msg.dt_s), "dvel_mps": prev.dvel_mps}
                )
                return [("imu", pk.sensor_id, forged)]
            return []
        out = []
        if self.kind in ("imu_burst", "imu_close") and pk.kind == "imu":
            while self.queue and self.queue[0][0] < msg.t:
                _, _, m = self.queue.pop(0)
                out.append(("imu", pk.sensor_id, m))
        return out

    def _forged(self, genuine, t: float, t_rel: float, traj):
        rate = float(self.arg)
        drift = rate * (t_rel - self.start_s)
        s = traj.state_at(t)
        if isinstance(genuine, GnssFix):
            lat, lon = _moved(s.llh[0], s.llh[1], s.llh[2], drift / math.sqrt(2), drift / math.sqrt(2))
            v = np.asarray(s.vel_enu_mps) + np.array([rate, rate, 0.0]) / math.sqrt(2)
            return GnssFix(
                t=t,
                lat_deg=math.degrees(lat),
                lon_deg=math.degrees(lon),
                height_m=float(s.llh[2]),
                vel_enu_mps=tuple(float(x) for x in v),
                pos_std_enu_m=(1.0, 1.0, 1.0),
                vel_std_enu_mps=(0.1, 0.1, 0.1),
            )
        rel = list(genuine.rel_b_m)
        rel[1] += drift
        return genuine.model_copy(update={"t": t, "rel_b_m": tuple(rel), "rel_std_m": (0.5, 0.5, 0.5)})


def run_case(sc, seed: int, kind, arg, start_s: float, aiding: str):
    cfg = service_config(sc)
    sink = StatusSink()
    eng = VehicleEngine("v1", cfg, sink)
    sim = Simulation(sc, seed=seed)
    traj = sim.truth.trajectory
    inj = Injector(kind, arg, start_s, aiding, np.random.default_rng(seed + 1000))
    last: dict = {}
    for key, msg in sim:
        pk = keys.parse_input(key)
        t_rel = msg.t - sc.t0_gps_s
        for k, sid, fm in inj.before(pk, msg, t_rel, traj):
            eng.handle(k, sid, fm)
        m = inj.filter(pk, msg, t_rel, traj)
        if m is not None:
            eng.handle(pk.kind, pk.sensor_id, m)
        for k, sid, fm in inj.after(pk, msg, t_rel, traj, last):
            eng.handle(k, sid, fm)
    out = {}
    for name, (t, err, sd, st) in sink.rec.items():
        out[name] = (np.array(t) - sc.t0_gps_s, np.array(err), np.array(sd), st)
    return out, eng, inj


@dataclass
class Row:
    peak: float
    recovered: float | None
    recovered_like: float | None
    rms_end: float
    rms_end_clean: float
    lies: int
    lies_clean: int
    timeline: list


def _h(err, sd):
    return np.hypot(err[:, 0], err[:, 1]), np.hypot(sd[:, 0], sd[:, 1])


def assess(rec, clean, start: float, end: float) -> Row:
    t, err, sd, st = rec
    tc, errc, sdc, stc = clean
    h, hs = _h(err, sd)
    hc, hsc = _h(errc, sdc)
    p95 = float(np.percentile(hc, 95))
    after = t >= start
    recovered = recovered_like = None
    idx = np.nonzero(t >= end)[0]
    for i in idx[:: max(1, len(idx) // 400)]:
        if t[-1] - t[i] < RECOVERY_HOLD_S:
            break
        if h[i] > p95:
            continue
        rest = np.percentile(h[i:], 95)
        if recovered_like is None:
            same_span = hc[tc >= t[i]]
            clean_rest = np.percentile(same_span, 95) if same_span.size else p95
            if rest <= max(p95, clean_rest) * RECOVERY_MARGIN:
                recovered_like = max(0.0, float(t[i] - end))
        if rest <= p95 * RECOVERY_MARGIN:
            recovered = max(0.0, float(t[i] - end))
            break
    st = np.array(st)
    # 'aided' with the horizontal error beyond 3x its sigma or the height beyond 3 vertical sigmas
    lies = int(np.sum(after & (st == "aided") & ((h > 3.0 * hs) | (np.abs(err[:, 2]) > 3.0 * sd[:, 2]))))
    beyond_c = (hc > 3.0 * hsc) | (np.abs(errc[:, 2]) > 3.0 * sdc[:, 2])
    lies_clean = int(np.sum((tc >= start) & (np.array(stc) == "aided") & beyond_c))
    last = t > t[-1] - 60.0
    lastc = tc > tc[-1] - 60.0
    timeline, prev = [], None
    for ti, s in zip(t[after], st[after], strict=True):
        if s != prev:
            timeline.append((round(float(ti - start), 1), str(s)))
            prev = s
    return Row(
        peak=float(h[after].max()),
        recovered=recovered,
        recovered_like=recovered_like,
        rms_end=float(np.sqrt(np.mean(h[last] ** 2))),
        rms_end_clean=float(np.sqrt(np.mean(hc[lastc] ** 2))),
        lies=lies,
        lies_clean=lies_clean,
        timeline=timeline,
    )


def choose_cases(cases: list[str] | None) -> list[tuple[str, object]]:
    """The cases ``--cases`` names: a kind alone (its rows of :data:`CASES`) or ``kind:arg`` with
    any argument of that kind, on the grid or off it (``drift:5``, ``outage:120``,
    ``imu_close:0.01x3000``, ``imu_burst:10x``)."""
    if cases is None:
        return list(CASES)
    kinds = {k for k, _ in CASES}
    chosen: list[tuple[str, object]] = []
    for c in cases:
        kind, sep, arg = c.partition(":")
        if kind not in kinds:
            raise SystemExit(f"--cases: unknown kind {kind!r}; one of {sorted(kinds)}")
        if not sep:
            chosen += [row for row in CASES if row[0] == kind]
            continue
        if kind == "imu_burst":
            if arg not in PACE_JITTER_S:
                raise SystemExit(f"--cases: imu_burst takes one of {sorted(PACE_JITTER_S)}, not {arg!r}")
            value: object = arg
        elif kind in ("imu_close", "imu_race"):
            try:
                _close(arg)
            except ValueError:
                why = f"--cases: {kind} takes RATE or RATExN (0.2, 0.05x500), not {arg!r}"
                raise SystemExit(why) from None
            value = arg
        else:
            try:
                value = float(arg)
            except ValueError:
                raise SystemExit(f"--cases: {kind} takes a number, not {arg!r}") from None
            if not math.isfinite(value) or value <= 0.0:
                raise SystemExit(f"--cases: {kind} takes a positive number, not {arg!r}")
        chosen.append((kind, value))
    return chosen


def transient_part(
    runs: int, seed: int, families: list[str], markdown: Path | None, cases: list[str] | None = None
) -> None:
    chosen = choose_cases(cases)
    lines = []
    for fam in families:
        build, labels, start, aiding = FAMILIES[fam]
        sc = build()
        table: dict[tuple[str, object, str], list[Row]] = {}
        notes: dict[tuple[str, object], dict] = {}
        p95s: dict[str, list[float]] = {}
        for r in range(runs):
            clean, _, _ = run_case(sc, seed + r, None, None, start, aiding)
            for name in labels:
                p95s.setdefault(name, []).append(
                    float(np.percentile(_h(clean[name][1], clean[name][2])[0], 95))
                )
            for kind, arg in chosen:
                t0 = time.perf_counter()
                rec, eng, inj = run_case(sc, seed + r, kind, arg, start, aiding)
                for name in labels:
                    table.setdefault((kind, arg, name), []).append(
                        assess(rec[name], clean[name], start, inj.end_s)
                    )
                counted = {k: v for k, v in eng.rejected.items()}
                counted |= {k: v for k, v in eng.notes.items() if not k.startswith("unused")}
                notes[(kind, arg)] = counted
                print(
                    f"{fam} seed {seed + r} {kind} {arg}: {time.perf_counter() - t0:.1f} s {counted}",
                    file=sys.stderr,
                )
        lines.append(f"\n### {fam}: {sc.name}, corruption at {start:.0f} s, {runs} run(s) from seed {seed}\n")
        for name, label in labels.items():
            lines.append(
                f"\n**{label}** (`{name}`): clean 95th percentile of the horizontal error "
                f"{' / '.join(f'{v:.2f}' for v in p95s[name])} m (per run)\n"
            )
            lines.append(
                "| case | peak m | recovered s | like clean s | last 60 s RMS m (clean) "
                "| aided > 3 sigma, h or up (clean) | status from the start (s) |"
            )
            lines.append("|---|---|---|---|---|---|---|")
            for kind, arg in chosen:
                rows = table[(kind, arg, name)]
                recs = [x.recovered for x in rows]
                rec_txt = "never" if any(x is None for x in recs) else f"{max(recs):.1f}"
                likes = [x.recovered_like for x in rows]
                like_txt = "never" if any(x is None for x in likes) else f"{max(likes):.1f}"
                tl = rows[0].timeline
                tl_txt = ", ".join(f"{a:g} {s}" for a, s in tl[:6]) + (" ..." if len(tl) > 6 else "")
                lines.append(
                    f"| {kind} {arg} | {max(x.peak for x in rows):.1f} | {rec_txt} | {like_txt} | "
                    f"{max(x.rms_end for x in rows):.2f} ({max(x.rms_end_clean for x in rows):.2f}) | "
                    f"{sum(x.lies for x in rows)} ({sum(x.lies_clean for x in rows)}) | {tl_txt} |"
                )
        lines.append(
            "\nCounted (first run): "
            + "; ".join(
                f"{k} {a}: " + ", ".join(f"{n} {v}" for n, v in sorted(c.items()))
                for (k, a), c in notes.items()
            )
        )
    text = "\n".join(lines)
    print(text)
    if markdown is not None:
        intro = __doc__.split("Transient corruption (``--part transient``), ")[1]
        head = (
            "# Hardening: transient corruption (issue 22)\n\n"
            "Written by `.venv/bin/python benchmarks/hardening.py --part transient "
            f"--runs {runs} --seed {seed} --markdown {markdown}` (in-process, the service's engine). "
            'Measurements and what they mean: docs/DESIGN-NOTES.md, "Recovery".\n\n'
            + "Per "
            + intro.replace("``", "`").removeprefix("per ")
        )
        markdown.write_text(head + "\n" + text + "\n")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--part", choices=("single", "transient", "both"), default="both")
    ap.add_argument("--runs", type=int, default=1)
    ap.add_argument("--seed", type=int, default=7)
    ap.add_argument("--families", default=",".join(FAMILIES), help=f"of {', '.join(FAMILIES)}")
    ap.add_argument("--markdown", type=Path, help="also write the transient tables to this file")
    ap.add_argument(
        "--cases",
        help="only these transient cases, comma-separated kinds or kind:arg, the arg on the grid or off it "
        "(e.g. imu_burst:max,outage,drift:5,imu_close:0.01x3000)",
    )
    a = ap.parse_args()
    if a.part in ("single", "both"):
        single_part(a.runs, a.seed)
    if a.part in ("transient", "both"):
        cases = a.cases.split(",") if a.cases else None
        transient_part(a.runs, a.seed, a.families.split(","), a.markdown, cases)


if __name__ == "__main__":
    main()
