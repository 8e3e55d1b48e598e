"""The engine's acceptance rules (service/intake_rules.py) and pipeline status ownership: the
pipelines set their own status and re-initialisation count; the engine only tells them what
happened (``start(..., after_loss=)``, ``mark_lost()``)."""

import ast
import logging
import re
import sys
from pathlib import Path

import numpy as np
import pytest

from fednav.service import keys
from fednav.service.config import IntakeConfig, LooselyCoupledConfig
from fednav.service.engine import VehicleEngine
from fednav.service.ins.alignment import InitStd
from fednav.service.ins.mechanisation import NavState
from fednav.service.intake_rules import AcceptanceRules
from fednav.service.messages import GnssFix, ImuSample, InitialNav, StarAttitude, Truth
from fednav.service.pipelines.base import Pipeline
from fednav.service.pipelines.loosely_coupled import LooselyCoupled
from fednav.simulators.evaluate import CollectingSink, service_config
from fednav.simulators.stream import Simulation

from .scenario_utils import shortened

T0 = 1000.0
INTAKE = IntakeConfig(
    late_tolerance_s=0.5, max_lead_s=5.0, max_imu_gap_s=0.5, sensor_ids={"gnss_fix": ["a", "b"]}
)


def _imu(t, dt=0.01):
    return ImuSample(t=t, dt_s=dt, dtheta_rad=(0.0, 0.0, 0.0), dvel_mps=(0.0, 0.0, 0.098))


def _fix(t):
    return GnssFix(
        t=t,
        lat_deg=40.0,
        lon_deg=10.0,
        height_m=0.0,
        vel_enu_mps=(0.0, 0.0, 0.0),
        pos_std_enu_m=(1.0, 1.0, 1.0),
        vel_std_enu_mps=(0.1, 0.1, 0.1),
    )


# --- acceptance rules --------------------------------------------------------------------------------
def test_imu_rules_against_the_ins_time():
    r = AcceptanceRules(INTAKE)
    assert r.decide("imu", "0", _imu(T0), None, False).accepted  # the first sample
    assert r.decide("imu", "0", _imu(T0), T0, True).reason == "duplicate"
    assert r.decide("imu", "0", _imu(T0 - 0.01), T0, True).reason == "time_backwards"
    assert r.decide("imu", "0", _imu(T0 + 0.01), T0, True).accepted
    assert r.decide("imu", "0", _imu(T0 + 0.4), T0, True).accepted  # short gap: stretched over it
    gap = r.decide("imu", "0", _imu(T0 + 0.52), T0, True)  # 0.52 - 0.01 > 0.5
    assert gap.reason == "imu_gap" and not gap.accepted
    assert r.decide("imu", "0", _imu(T0 + 0.52), T0, False).reason == "imu_gap"  # also before init
    assert r.last_t == {}  # IMU order is the INS time's, not a per-key record


def test_aiding_rules_order_and_records():
    r = AcceptanceRules(INTAKE)
    t_ins = T0
    assert r.decide("gnss_fix", "a", _fix(T0), t_ins, True).accepted
    assert r.last_t[("gnss_fix", "a")] == T0
    assert r.decide("gnss_fix", "a", _fix(T0), t_ins, True).reason == "duplicate"
    # older than the sensor's previous AND than the INS by more than the tolerance: "late" first
    assert r.decide("gnss_fix", "a", _fix(T0 - 1.0), t_ins, True).reason == "late"
    assert r.decide("gnss_fix", "a", _fix(T0 - 0.2), t_ins, True).reason == "time_backwards"
    assert r.decide("gnss_fix", "b", _fix(T0 - 0.2), t_ins, True).accepted  # another sensor: late-tolerated
    early = r.decide("gnss_fix", "a", _fix(T0 + 5.5), t_ins, True)
    assert early.reason == "early" and early.in_sequence
    assert r.last_t[("gnss_fix", "a")] == T0  # refused: not recorded
    assert r.decide("gnss_fix", "a", _fix(T0 + 4.9), t_ins, True).accepted  # queued by the engine
    assert r.last_t[("gnss_fix", "a")] == T0 + 4.9
    # out of sequence (stale): the engine does not even keep such a fix for alignment
    assert not r.decide("gnss_fix", "a", _fix(T0 - 9.0), t_ins, True).in_sequence
    assert not r.decide("gnss_fix", "a", _fix(T0 + 4.9), t_ins, True).in_sequence  # duplicate


def test_aiding_before_initialisation():
    r = AcceptanceRules(INTAKE)
    v = r.decide("gnss_fix", "a", _fix(T0), None, False)  # no IMU yet
    assert v.reason == "not_initialised" and v.in_sequence
    assert r.last_t[("gnss_fix", "a")] == T0  # recorded: the newest fix of the sensor
    # not initialised: no late/early checks, but the sensor's own order still holds
    assert r.decide("gnss_fix", "a", _fix(T0 - 30.0), T0 + 60.0, False).reason == "time_backwards"
    assert r.decide("gnss_fix", "a", _fix(T0 + 30.0), T0, False).reason == "not_initialised"


def test_truth_and_init_rules():
    r = AcceptanceRules(INTAKE)
    truth = Truth.model_construct(t=T0)
    assert r.decide("truth", "0", truth, None, False).accepted  # truth is kept before initialisation
    assert r.decide("truth", "0", truth, None, False).reason == "duplicate"
    assert (
        r.decide("truth", "0", Truth.model_construct(t=T0 - 1.0), T0 + 100.0, True).reason == "time_backwards"
    )
    init = InitialNav.model_construct(t=T0)
    assert r.decide("init", "0", init, None, False).accepted  # before any IMU: taken
    assert r.decide("init", "0", init, T0, True).reason == "duplicate"
    # a (re-)initialisation must be current: within future_window_s of the running time
    assert r.decide("init", "0", InitialNav.model_construct(t=T0 + 1.5), T0, True).accepted
    assert r.decide("init", "0", InitialNav.model_construct(t=T0 - 5.0), T0 + 100.0, True).reason == "late"
    assert r.decide("init", "0", InitialNav.model_construct(t=T0 + 1000.0), T0, True).reason == "future"
    star = StarAttitude.model_construct(t=T0)
    assert r.decide("star", "st1", star, T0, True).accepted


# --- pipeline status ownership ------------------------------------------------------------------------
def _nav(t=0.0):
    return NavState(
        t=t, lat_rad=0.7, lon_rad=0.2, h_m=0.0, vel_enu_mps=np.zeros(3), q_nb=np.array([1.0, 0, 0, 0])
    )


STD = InitStd(np.full(3, 5.0), np.full(3, 0.1), np.radians([0.1, 0.1, 0.5]))


def test_pipeline_start_counts_a_restart_once_and_sets_status():
    p = LooselyCoupled(
        LooselyCoupledConfig(name="lc"), service_config(shortened("demo_aircraft.toml", 5.0)).imu, 0.1
    )
    assert p.status == "initialising"
    p.start(_nav(), STD, after_loss=False)
    assert (p.status, p.reinitialisations) == ("unaided", 0)
    p.mark_aided(0.0)
    assert p.status == "aided"
    p.start(_nav(1.0), STD, after_loss=False)  # a second InitialNav
    assert (p.status, p.reinitialisations) == ("unaided", 1)
    p.mark_lost()
    assert p.status == "initialising"
    p.start(_nav(2.0), STD, after_loss=True)
    assert (p.status, p.reinitialisations) == ("unaided", 2)
    p.mark_failed()
    assert p.status == "failed"


def test_status_follows_aiding_coasting_and_screening():
    """aided within three aiding intervals (at least 1 s), then coasting; degraded while
    screening refused aiding within that window."""
    p = LooselyCoupled(
        LooselyCoupledConfig(name="lc"), service_config(shortened("demo_aircraft.toml", 5.0)).imu, 0.1
    )
    p.start(_nav(), STD)
    for t in (1.0, 2.0, 3.0):
        p.mark_aided(t)
    assert p.coast_after_s() == 3.0
    assert p.current_status(5.9) == "aided" and p.current_status(6.1) == "coasting"
    p.mark_screened(6.5, "innovation_gate", 3)
    assert p.current_status(7.0) == "degraded" and p.current_status(9.6) == "coasting"
    assert p.screened == {"innovation_gate": 3}


def test_gate_faults_clear_after_a_refusal():
    """The loosely coupled gate publishes Faults while it refuses rows and once more, all rows in
    use, at the first fix it passes whole; nothing while nothing was refused."""
    p = LooselyCoupled(
        LooselyCoupledConfig(name="lc"), service_config(shortened("demo_aircraft.toml", 5.0)).imu, 0.1
    )
    nav = _nav()
    p.start(nav, STD)
    lat, lon = np.degrees(nav.lat_rad), np.degrees(nav.lon_rad)

    def fix(t, dlat_deg=0.0):
        return GnssFix(t=t, lat_deg=lat + dlat_deg, lon_deg=lon, height_m=0.0, vel_enu_mps=(0.0, 0.0, 0.0))

    assert p.apply("gnss_fix", "g", fix(0.1)) == []
    (refused,) = p.apply("gnss_fix", "g", fix(0.2, dlat_deg=0.01))  # 1.1 km north: refused
    assert [o.label for o in refused.subsystems[0].observations if o.isolated] == ["pos_n"]
    assert abs(np.degrees(p.bank.nav().lat_rad) - lat) < 1e-9  # the refused row moved nothing
    (clear,) = p.apply("gnss_fix", "g", fix(0.3))
    assert not clear.subsystems[0].isolated
    assert not any(o.flagged or o.isolated for o in clear.subsystems[0].observations)
    assert p.apply("gnss_fix", "g", fix(0.4)) == []


@pytest.fixture
def attribute_writers(monkeypatch):
    """(attribute, writing module) for every write of a pipeline's status bookkeeping."""
    writes: list[tuple[str, str]] = []

    def spy(self, name, value):
        if name in ("status", "reinitialisations", "updates"):
            writes.append((name, sys._getframe(1).f_globals.get("__name__")))
        object.__setattr__(self, name, value)

    monkeypatch.setattr(Pipeline, "__setattr__", spy)
    return writes


def test_engine_reinitialisation_and_imu_gap_statuses(attribute_writers, caplog):
    """A second InitialNav consistent with the GNSS fix is a reset request: weighed against the
    verified solution (here it agrees: no restart), counted (``init_reset``), ``degraded`` until
    the vehicle's own fixes agree again (a stale one, the start position 8 s later, is refused
    ``implausible_init``). An
    IMU gap loses the INS for a moment: every pipeline restarts at once from its last verified
    state carried over the gap (one more count), ``degraded`` until verified; the engine writes
    none of the pipelines' bookkeeping. The lost INS is said in the log, once, with the gap and
    what the vehicle does about it."""
    caplog.set_level(logging.WARNING, logger="fednav.service")
    sc = shortened("demo_aircraft.toml", 30.0)
    cfg = service_config(sc)
    eng = VehicleEngine("v1", cfg, CollectingSink(keep_solutions=True))
    p = eng.pipelines[0]
    init = truth = None
    seen = []  # (t - t0, status, reinitialisations) at every change
    for key, msg in Simulation(sc, seed=4):
        pk = keys.parse_input(key)
        t = msg.t - sc.t0_gps_s
        if pk.kind == "init":
            init = msg
        if pk.kind == "truth":
            truth = msg
        if pk.kind == "imu" and 15.0 <= t < 16.0:
            continue  # a 1 s IMU gap (> max_imu_gap_s)
        eng.handle(pk.kind, pk.sensor_id, msg)
        if pk.kind == "imu" and init is not None and abs(t - 8.0) < 0.005:
            assert not eng.handle("init", "0", init.model_copy(update={"t": msg.t}))  # stale position
            assert eng.rejected["implausible_init"] == 1
            here = {
                k: getattr(truth, k) for k in ("lat_deg", "lon_deg", "height_m", "vel_enu_mps", "rpy_deg")
            }
            assert eng.handle("init", "0", init.model_copy(update={"t": msg.t, **here}))  # re-initialise
        state = (p.status, p.reinitialisations)
        if not seen or seen[-1][1:] != state:
            seen.append((round(t, 2), *state))
    statuses = [s[1:] for s in seen]
    # the second InitialNav agrees with the verified solution: taken (counted), nothing to
    # restart; degraded until three fixes agree again
    assert statuses[:4] == [("unaided", 0), ("aided", 0), ("degraded", 0), ("aided", 0)]
    assert eng.notes["init_reset"] == 1 and 10.0 <= seen[3][0] <= 11.1
    i_lost = statuses.index(("degraded", 1))
    assert 16.0 <= seen[i_lost][0] < 16.1  # the first sample after the gap: restarted at once
    assert eng.rejected["imu_gap"] == 1 and eng.notes["recovered_from_checkpoint"] == 1
    assert statuses[-1] == ("aided", 1)
    lost = [r.getMessage() for r in caplog.records if "INS lost" in r.getMessage()]
    assert len(lost) == 1 and "vehicle v1" in lost[0] and "carried over the gap" in lost[0]
    assert re.search(r"IMU gap of 1\.0\d s", lost[0]), lost[0]
    writers = {m for _, m in attribute_writers}
    assert writers and "fednav.service.engine" not in writers
    assert writers <= {"fednav.service.pipelines.base", "fednav.service.pipelines.loosely_coupled"}


def test_engine_source_never_assigns_pipeline_bookkeeping():
    tree = ast.parse(Path(sys.modules[VehicleEngine.__module__].__file__).read_text())
    targets = [
        t.attr
        for node in ast.walk(tree)
        if isinstance(node, ast.Assign | ast.AugAssign)
        for t in (node.targets if isinstance(node, ast.Assign) else [node.target])
        if isinstance(t, ast.Attribute)
    ]
    assert not {"status", "reinitialisations", "updates"} & set(targets)


def test_an_unusable_estimate_fails_the_pipeline_and_it_restarts():
    """An estimate a Solution cannot carry (here a height below the wire limit) is never an
    exception nor a message: the pipeline is ``failed`` (counted ``pipeline_failed``) and restarts
    from the next GNSS fix."""
    sc = shortened("demo_aircraft.toml", 20.0)
    sink = CollectingSink(keep_solutions=True)
    eng = VehicleEngine("v1", service_config(sc), sink)
    p = eng.pipelines[0]
    broken_at = None
    for key, msg in Simulation(sc, seed=4):
        pk = keys.parse_input(key)
        eng.handle(pk.kind, pk.sensor_id, msg)
        if pk.kind == "imu" and broken_at is None and msg.t - sc.t0_gps_s >= 8.05:
            p.bank.ins.state.h_m = -1e6  # what a diverged filter could produce
            broken_at = msg.t
            eng.emit_solutions()
            assert p.status == "failed" and eng.rejected["pipeline_failed"] == 1
    sols = sink.records["lc"].solutions
    assert all(s.height_m > -1e4 for s in sols)
    gap = [s.t for s in sols if s.t > broken_at]
    assert gap and gap[0] - broken_at <= 1.0 + 1e-6  # a solution again after the next fix (1 Hz)
    assert p.reinitialisations == 1 and sols[-1].status == "aided"


def test_warnings_name_a_time_base_mismatch_and_a_pipeline_without_input(caplog):
    """A GNSS stream stamped 1000 s away from the IMU is refused wholesale: one log line names the
    time base mismatch. A tightly coupled pipeline on a stream without raw GNSS: one log line says
    it has no input and what it consumes. Each once."""
    import logging

    from fednav.service.config import ServiceConfig, TightlyCoupledConfig

    sc = shortened("demo_aircraft.toml", 40.0)
    cfg = ServiceConfig(pipelines=[LooselyCoupledConfig(name="lc"), TightlyCoupledConfig(name="tc")])
    eng = VehicleEngine("v1", cfg, CollectingSink())
    with caplog.at_level(logging.WARNING, logger="fednav.service"):
        for key, msg in Simulation(sc, seed=4):
            pk = keys.parse_input(key)
            if pk.kind == "gnss_fix" and msg.t - sc.t0_gps_s > 5.0:
                msg = msg.model_copy(update={"t": msg.t + 1000.0})  # boot time vs GPS time, say
            eng.handle(pk.kind, pk.sensor_id, msg)
        for t in range(200):  # and 200 more of them
            eng.handle("gnss_fix", "main", _fix(sc.t0_gps_s + 2000.0 + t))
    lines = [r.getMessage() for r in caplog.records]
    mismatch = [m for m in lines if "time base mismatch" in m]
    assert len(mismatch) == 1 and "gnss_fix/main" in mismatch[0] and "+" in mismatch[0], lines
    unaided = [m for m in lines if "pipeline tc has had no aiding" in m]
    assert len(unaided) == 1 and "gnss_raw" in unaided[0], lines
    assert eng.pipelines[1].status == "unaided"


def test_attitude_or_height_alone_is_not_aided():
    """An update observing neither horizontal position nor velocity (a star tracker's attitude
    rows, a height alone) counts, but neither makes the pipeline aided nor keeps it from coasting."""
    from fednav.service.pipelines.base import observes_horizontal

    p = LooselyCoupled(
        LooselyCoupledConfig(name="lc"), service_config(shortened("demo_aircraft.toml", 5.0)).imu, 0.1
    )
    p.start(_nav(), STD)
    n = 15
    attitude = np.zeros((3, n))
    attitude[:, 6:9] = np.eye(3)
    height = np.zeros((1, n))
    height[0, 2] = 1.0
    fix = np.zeros((6, n))
    fix[:, 0:6] = np.eye(6)
    assert not observes_horizontal(attitude) and not observes_horizontal(height)
    assert observes_horizontal(fix)
    assert not observes_horizontal(fix, [False, False, True, False, False, True])  # only the up rows
    p.mark_aided(1.0, attitude)
    p.mark_aided(1.5, height)
    assert p.status == "unaided" and p.updates == 2
    for t in (2.0, 3.0, 4.0):
        p.mark_aided(t, fix)
    for t in np.arange(4.1, 12.0, 0.1):  # attitude at 10 Hz after the last fix: coasting at 7 s
        p.mark_aided(float(t), attitude)
    assert p.current_status(6.9) == "aided" and p.current_status(7.1) == "coasting"
