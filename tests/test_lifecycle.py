"""The vehicle lifecycle (service/lifecycle.py): its transition table, the stages a run goes
through, and the hand-over from another service (the transition the fleet scale-out uses)."""

from __future__ import annotations

import math

import numpy as np
import pytest

from fednav.service import earth, keys, lifecycle
from fednav.service.engine import VehicleEngine
from fednav.service.ins.alignment import InitStd
from fednav.service.ins.mechanisation import NavState
from fednav.service.lifecycle import AIDED, ALIGNED, INITIALISING, STAGES, SUSPECT, TRANSITIONS
from fednav.simulators.evaluate import CollectingSink, service_config
from fednav.simulators.stream import Simulation

from .scenario_utils import shortened

SEED = 4


def _truth_nav(sim, t: float, north_m: float = 0.0) -> NavState:
    s = sim.truth.trajectory.state_at(t)
    lat, lon, h = s.llh
    return NavState(
        t=t,
        lat_rad=float(lat + north_m / earth.radii(lat)[0]),
        lon_rad=float(lon),
        h_m=float(h),
        vel_enu_mps=np.array(s.vel_enu_mps, dtype=float),
        q_nb=earth.mat_to_quat(earth.rpy_to_mat_nb(s.rpy_rad)),
    )


STD = InitStd(np.full(3, 2.0), np.full(3, 0.05), np.radians([0.02, 0.02, 0.1]))


def test_transition_table_reaches_every_stage_and_refuses_the_rest():
    targets = set(TRANSITIONS.values())
    assert targets == set(STAGES)
    for stage in STAGES:  # every stage can be left (the INS can always be lost)
        assert (stage, "lost") in TRANSITIONS
    assert (INITIALISING, "verified") not in TRANSITIONS  # nothing to verify without navigation
    assert (INITIALISING, "reset") not in TRANSITIONS  # a reset needs a running state
    assert TRANSITIONS[(SUSPECT, "reset")] == ALIGNED and TRANSITIONS[(SUSPECT, "verified")] == AIDED
    sc = shortened("demo_aircraft.toml", 5.0)
    eng = VehicleEngine("v1", service_config(sc), CollectingSink())
    with pytest.raises(ValueError, match="no transition"):
        eng.life.go(eng.pipelines[0], "verified", 0.0)


def _run(sc, eng, sim, on_imu=None, skip_init=False):
    for key, msg in sim:
        pk = keys.parse_input(key)
        if skip_init and pk.kind == "init":
            continue
        if on_imu is not None and pk.kind == "imu":
            on_imu(msg)
        eng.handle(pk.kind, pk.sensor_id, msg)


def test_a_run_goes_initialising_aligned_aided():
    sc = shortened("demo_aircraft.toml", 10.0)
    eng = VehicleEngine("v1", service_config(sc), CollectingSink())
    _run(sc, eng, Simulation(sc, seed=SEED))
    events = [(stage_from, event, to) for _, name, stage_from, event, to in eng.life.history]
    assert events == [(INITIALISING, "start", ALIGNED), (ALIGNED, "aided", AIDED)]
    assert eng.pipelines[0].status == "aided"


def test_hand_over_before_the_first_sample_is_degraded_until_own_aiding_agrees():
    """A hand-over (no InitialNav: the vehicle continues another service's navigation) starts
    every pipeline at the first IMU sample's start; ``degraded`` until VERIFY_EPOCHS GNSS fixes
    agree, then ``aided``; counted ``handed_over``."""
    sc = shortened("demo_aircraft.toml", 12.0)
    eng = VehicleEngine("v1", service_config(sc), CollectingSink())
    sim = Simulation(sc, seed=SEED)
    p = eng.pipelines[0]
    seen = []

    def on_imu(msg):
        if not eng.initialised:
            assert eng.hand_over(_truth_nav(sim, msg.t - msg.dt_s), STD, "svc-a")
            assert p.status == "degraded" and eng.notes["handed_over"] == 1
        if not seen or seen[-1][1] != p.status:
            seen.append((round(msg.t - sc.t0_gps_s, 2), p.status))

    _run(sc, eng, sim, on_imu, skip_init=True)
    assert [s for _, s in seen] == ["degraded", "aided"]
    assert 2.0 <= seen[1][0] <= lifecycle.VERIFY_EPOCHS + 1.1  # three fixes at 1 Hz
    assert [e for *_, e, _ in eng.life.history] == ["hand_over", "verified"]
    assert p.reinitialisations == 0 and eng.rejected.get("implausible_init", 0) == 0


def test_a_wrong_hand_over_is_reset_by_the_vehicles_own_fix():
    """A handed-over state 300 m off claiming 2 m: the first GNSS fix disagrees, the pipeline
    restarts from the fix (``reset``), is verified by the next fixes, and ends within metres."""
    sc = shortened("demo_aircraft.toml", 20.0)
    sink = CollectingSink()
    eng = VehicleEngine("v1", service_config(sc), sink)
    sim = Simulation(sc, seed=SEED)

    def on_imu(msg):
        if not eng.initialised:
            assert eng.hand_over(_truth_nav(sim, msg.t - msg.dt_s, north_m=300.0), STD, "svc-a")

    _run(sc, eng, sim, on_imu, skip_init=True)
    events = [e for *_, e, _ in eng.life.history]
    assert events[:3] == ["hand_over", "reset", "verified"], events  # the reset is verified too
    assert eng.notes["reset:lc"] == 1
    err = np.array(sink.records["lc"].err)
    assert math.hypot(*err[-1, :2]) < 10.0


def test_hand_over_on_a_running_vehicle_is_a_checked_reset_request():
    sc = shortened("demo_aircraft.toml", 25.0)
    eng = VehicleEngine("v1", service_config(sc), CollectingSink())
    sim = Simulation(sc, seed=SEED)
    p = eng.pipelines[0]
    done = {}

    def on_imu(msg):
        t = msg.t - sc.t0_gps_s
        if abs(t - 10.0) < 0.005 and not done:
            t_ins = eng.last_imu_t
            far = _truth_nav(sim, t_ins, north_m=2000.0)
            done["far"] = eng.hand_over(far, STD, "svc-b")
            assert eng.rejected["implausible_handover"] == 1
            assert p.status == "aided"
            done["near"] = eng.hand_over(_truth_nav(sim, t_ins, north_m=3.0), STD, "svc-b")
            assert p.status == "degraded" and p.reinitialisations == 1

    _run(sc, eng, sim, on_imu)
    assert done == {"far": False, "near": True}
    assert eng.notes["handed_over"] == 1 and p.status == "aided"
    assert [e for *_, e, _ in eng.life.history][-2:] == ["hand_over", "verified"]


class _Pubs:
    """The service's publishers without Zenoh: the Integrity messages kept."""

    def __init__(self):
        self.integrity = []

    def publish(self, key: str, msg) -> None:
        if type(msg).__name__ == "Integrity":
            self.integrity.append(msg)


def _worker(cfg):
    from fednav.service.app import OutputSink, VehicleWorker

    pubs = _Pubs()
    return VehicleWorker("v1", cfg, OutputSink(keys.DEFAULT_PREFIX, pubs, None), pubs, None, None), pubs


@pytest.mark.parametrize("carried", [True, False], ids=["exclusions_carried", "control_without"])
def test_a_hand_over_keeps_the_satellites_integrity_excluded(carried):
    """A vehicle handed over to another service of its fleet (app.VehicleWorker.take_over) during
    a live satellite fault: the MHSS monitor there keeps the satellite the old service's monitor
    had excluded (HandoverState.excluded, with its health clock), instead of taking the faulty
    satellite back at its first epoch. The control, the same hand-over without the exclusions,
    shows what the test guards: the faulty satellite used again at the first epoch, its fault
    detected anew (here at once: 70 s into its ramp; a smaller fault would stay in longer)."""
    sc = shortened("demo_product.toml", 125.0)  # its GEO3 ramp fault: 30-110 s
    cfg = service_config(sc)
    t_cut = sc.t0_gps_s + 100.0
    a, _ = _worker(cfg)
    b, pubs_b = _worker(cfg)
    states = None
    for key, msg in Simulation(sc, seed=SEED):
        pk = keys.parse_input(key)
        if msg.t <= t_cut:
            a.loop.process(pk.kind, pk.sensor_id, msg)
            continue
        if states is None:  # the old service's last states, through the wire
            states = {s.pipeline: s for s in a.handover_states("service-a")}
            book = next(p for p in a.engine.pipelines if getattr(p, "monitor", None)).monitor.book
            assert book.ids and states["tc_mhss"].excluded.keys() == set(book.ids)
            excluded = set(book.ids)
            if not carried:
                states = {n: s.model_copy(update={"excluded": {}}) for n, s in states.items()}
            payloads = {n: s.to_json() for n, s in states.items()}
            b.loop.starter = lambda t, payloads=payloads: b.take_over(payloads, t)
        if pk.kind == "truth" or msg.t > t_cut + 5.0:
            continue
        b.loop.process(pk.kind, pk.sensor_id, msg)
    assert b.engine.initialised and b.engine.notes["handed_over_from:service-a"] == 1
    after = [m for m in pubs_b.integrity if m.pipeline == "tc_mhss"]
    assert len(after) >= 4
    in_use = [{s.id for s in m.satellites} for m in after]
    if carried:
        assert b.engine.notes["handover_exclusions"] == len(excluded)
        for m, used in zip(after, in_use, strict=True):
            assert excluded <= set(m.excluded) and not (excluded & used), (m.t, m.excluded, used)
            assert not m.detected and not m.alarm, m.t  # nothing to detect: the fault never came in
    else:
        # the faulty satellite taken back in: the first epoch's filters used it, its fault had to
        # be detected again (a detection the hand-over caused) and it was excluded again
        first = after[0]
        assert first.detected and excluded <= set(first.excluded), first
