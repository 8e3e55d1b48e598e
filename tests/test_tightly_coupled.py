"""Tightly coupled INS/GNSS with MHSS integrity: range model, rows, clock, pipeline scenarios.

Scenario: the simulators' trajectory (exact IMU increments) and raw GNSS sensor (nominal BDS,
10 Hz, 3 m / 0.05 m/s noise, random-walk receiver clock); the pipeline is driven directly (and
once through the engine). Faults are applied to the published messages.
"""

from __future__ import annotations

import math

import numpy as np
import pytest

from fednav.service import earth
from fednav.service.config import ClockModel, ImuModel, TightlyCoupledConfig
from fednav.service.estimation.measurements import gnss_raw as gm
from fednav.service.evaluation import nav_errors
from fednav.service.ins.mechanisation import NavState
from fednav.service.messages import GnssRaw, ImuSample
from fednav.service.pipelines.base import InitStd
from fednav.service.pipelines.tightly_coupled import TightlyCoupled
from fednav.simulators.gnss.orbits import NominalConstellation
from fednav.simulators.gnss.orbits import range_geometry as sim_range_geometry
from fednav.simulators.gnss.raw_sensor import GnssRawSensor, GnssRawSpec
from fednav.simulators.gnss.raw_sensor import clock_transition as sim_clock_transition
from fednav.simulators.trajectory import StartSpec, StraightSegment, TurnSegment, build_trajectory

from .scenario_utils import initial_nav_message

T0 = 1_300_000_000.0
DUR_S = 60.0
START = StartSpec(lat_deg=40.1, lon_deg=118.6, height_m=1000.0, heading_deg=45.0, speed_mps=100.0)


# --- range model and rows ------------------------------------------------------------------------------
def test_range_model_equals_the_simulators():
    src = NominalConstellation(("BDS", "GPS"))
    st = src.states(src.satellite_ids(), T0)
    rng = np.random.default_rng(0)
    for _ in range(5):
        llh = np.array([rng.uniform(-1.2, 1.2), rng.uniform(-3, 3), rng.uniform(0, 1e4)])
        rx, v = earth.llh_to_ecef(llh), rng.normal(0, 200, 3)
        a = gm.range_geometry(rx, st.pos_ecef_m, v, st.vel_ecef_mps)
        b = sim_range_geometry(rx, st.pos_ecef_m, v, st.vel_ecef_mps)
        np.testing.assert_allclose(a.range_m, b.range_m, atol=1e-9, rtol=0)
        np.testing.assert_allclose(a.range_rate_mps, b.range_rate_mps, atol=1e-12, rtol=0)
        np.testing.assert_allclose(a.los_ecef, b.los_ecef, atol=1e-15)
        np.testing.assert_allclose(a.doppler_factor, b.doppler_factor, atol=1e-15)
    # first-order Sagnac reading: |r_s - r_r| + (omega/c)(x_s y_r - y_s x_r), to a few mm
    rx = earth.llh_to_ecef(np.array([0.7, 2.0, 100.0]))
    g = gm.range_geometry(rx, st.pos_ecef_m)
    approx = np.linalg.norm(st.pos_ecef_m - rx, axis=1) + earth.OMEGA_IE_RPS / earth.C_MPS * (
        st.pos_ecef_m[:, 0] * rx[1] - st.pos_ecef_m[:, 1] * rx[0]
    )
    assert np.max(np.abs(g.range_m - approx)) < 0.05


def test_clock_transition_equals_the_simulators():
    c = ClockModel(bias_psd_m2ps=0.2, drift_psd_m2ps3=0.03, correlation_time_s=300.0)
    for T in (0.01, 0.1, 1.0):
        a = gm.clock_transition(T, c.correlation_time_s, c.bias_psd_m2ps, c.drift_psd_m2ps3)
        b = sim_clock_transition(T, c.correlation_time_s, c.bias_psd_m2ps, c.drift_psd_m2ps3)
        np.testing.assert_allclose(a[0], b[0], rtol=1e-14, atol=1e-16)
        np.testing.assert_allclose(a[1], b[1], rtol=1e-12, atol=1e-18)


def test_rows_are_the_jacobian_of_predicted_minus_measured():
    """z = predicted(INS) - measured with the INS off by +dx (computed minus true): z = H dx.
    Pseudorange rows: -u_enu on position (range grows moving away from the satellite), +1 on the
    clock bias; range-rate rows: -f u_enu on velocity, +1 on the drift (finite differences)."""
    src = NominalConstellation(("BDS",))
    st = src.states(src.satellite_ids(), T0)
    true_llh = np.array([math.radians(40.1), math.radians(118.6), 1000.0])
    true_vel = np.array([70.0, 70.0, 2.0])
    c_en = earth.mat_en(true_llh[0], true_llh[1])
    rx_true = gm.Receiver(earth.llh_to_ecef(true_llh), c_en @ true_vel, c_en, 120.0, 3.0)
    sats_all = gm.SatArrays(
        tuple(f"C{i:02d}" for i in range(len(st.pos_ecef_m))),
        np.zeros(len(st.pos_ecef_m)),
        np.zeros(len(st.pos_ecef_m)),
        np.ones(len(st.pos_ecef_m)),
        np.ones(len(st.pos_ecef_m)),
        st.pos_ecef_m,
        st.vel_ecef_mps,
        np.zeros(len(st.pos_ecef_m)),
        np.zeros(len(st.pos_ecef_m)),
    )
    p_true = gm.predict(rx_true, sats_all)
    vis = np.flatnonzero(p_true.elevation_rad > 0.1)
    meas = sats_all.take(vis)
    meas = gm.SatArrays(
        meas.ids,
        p_true.pseudorange_m[vis],
        p_true.range_rate_mps[vis],
        meas.pseudorange_sigma_m,
        meas.range_rate_sigma_mps,
        meas.sat_pos_ecef_m,
        meas.sat_vel_ecef_mps,
        meas.sat_clock_m,
        meas.sat_clock_drift_mps,
    )
    dx = np.zeros(17)
    dx[0:3] = [3.0, -2.0, 4.0]  # ENU m
    dx[3:6] = [0.2, -0.1, 0.3]
    dx[15], dx[16] = 5.0, -0.4
    llh_ins = true_llh + earth.enu_m_to_llh_delta(dx[0:3], true_llh[0], true_llh[2])
    nav = NavState(T0, llh_ins[0], llh_ins[1], llh_ins[2], true_vel + dx[3:6], np.array([1.0, 0, 0, 0]))
    rx_ins = gm.receiver_from_nav(nav, 120.0 + dx[15], 3.0 + dx[16])
    pred = gm.predict(rx_ins, meas)
    rows = gm.raw_rows(pred, meas, use_range_rate=True)
    n = len(vis)
    np.testing.assert_allclose(rows.z[:n], rows.H[:n] @ dx, atol=2e-5)  # second order: |dp|^2 / rho
    # range rate: the neglected position dependence of the line of sight is ~|v_s| |dp| / rho
    np.testing.assert_allclose(rows.z[n:], rows.H[n:] @ dx, atol=3e-3)
    assert np.all(rows.H[:n, 2] < 0)  # up error: the satellites are above, the ranges shrink
    assert rows.labels[0].endswith(".pr") and rows.labels[n].endswith(".rr")


# --- scenario ------------------------------------------------------------------------------------------
@pytest.fixture(scope="module")
def scenario():
    traj = build_trajectory(
        START,
        [
            StraightSegment(kind="straight", duration_s=20.0),
            TurnSegment(kind="turn", duration_s=20.0, turn_rate_dps=3.0, ramp_s=5.0),
        ],
        100.0,
        T0,
        duration_s=DUR_S,
    )
    spec = GnssRawSpec(
        rate_hz=10.0, pseudorange_sigma_m=3.0, range_rate_sigma_mps=0.05, elevation_mask_deg=5.0
    )
    sensor = GnssRawSensor(spec, seed=1)
    epochs = {}
    for k in range(0, len(traj.t_s), 10):
        s = traj.state_at(traj.t_s[k])
        c_en = earth.mat_en(s.llh[0], s.llh[1])
        epochs[k] = sensor.measure(traj.t_s[k], earth.llh_to_ecef(s.llh), c_en @ s.vel_enu_mps)
    return traj, epochs


def initial_nav(traj) -> tuple[NavState, InitStd]:
    s = traj.state_at(T0)
    d = earth.enu_m_to_llh_delta(np.array([4.0, -3.0, 2.0]), s.llh[0], s.llh[2])
    rpy = s.rpy_rad + np.radians([0.02, -0.02, 0.1])
    nav = NavState(
        T0,
        s.llh[0] + d[0],
        s.llh[1] + d[1],
        s.llh[2] + d[2],
        s.vel_enu_mps + [0.1, -0.1, 0.05],
        earth.mat_to_quat(earth.rpy_to_mat_nb(rpy)),
    )
    return nav, InitStd(np.full(3, 10.0), np.full(3, 0.3), np.radians([0.1, 0.1, 0.3]))


def with_faults(msg: GnssRaw, t_rel: float, faults) -> GnssRaw:
    """faults: list of (sat_id, fn(t_rel) -> pseudorange offset m); drop: sat_id -> None."""
    sats = []
    for o in msg.sats:
        off = 0.0
        drop = False
        for sid, fn in faults:
            if sid == o.id:
                v = fn(t_rel)
                if v is None:
                    drop = True
                else:
                    off += v
        if not drop:
            sats.append(o.model_copy(update={"pseudorange_m": o.pseudorange_m + off}) if off else o)
    return GnssRaw(t=msg.t, sats=sats)


def run(traj, epochs, cfg: TightlyCoupledConfig, faults=(), hook=None):
    p = TightlyCoupled(cfg, ImuModel(), 0.1)
    p.initialise(*initial_nav(traj))
    log = []
    for k in range(1, len(traj.t_s)):
        if hook is not None:
            hook(k, p)
        p.push_imu(traj.dtheta_rad[k], traj.dvel_mps[k], traj.dt_s, float(traj.t_s[k]))
        if k in epochs:
            p.sync()
            msg = with_faults(epochs[k].message, traj.t_s[k] - T0, faults)
            out = p.apply("gnss_raw", "gnss0", msg, 0.0)
            s = traj.state_at(traj.t_s[k])
            e = nav_errors(p.bank.nav(), s.llh, s.vel_enu_mps, earth.rpy_to_mat_nb(s.rpy_rad))
            log.append((traj.t_s[k] - T0, out[0] if out else None, e, p.last, epochs[k].truth))
    return p, log


@pytest.fixture(scope="module")
def fault_free(scenario):
    traj, epochs = scenario
    return run(traj, epochs, TightlyCoupledConfig(name="tc"))


def test_fault_free_accuracy_clock_and_bank_shape(fault_free, scenario):
    p, log = fault_free
    N = p.bank.mhss.N
    assert N >= 8
    assert p.bank.mhss.B == 1 + N + N * (N - 1) // 2
    assert len(p.bank.mhss.blocks) == p.bank.mhss.B + N * N  # members + P_0n + P_n,nm
    late = np.array([e for t, _, e, _, _ in log if t > 20.0])
    assert np.sqrt(np.mean(late[:, :3] ** 2, axis=0)).max() < 1.0  # m
    assert np.sqrt(np.mean(late[:, 3:6] ** 2, axis=0)).max() < 0.03  # m/s
    truth = log[-1][4]
    assert abs(p.bank.reference["clock"][0] - truth.rx_clock_bias_m) < 2.0
    assert abs(p.bank.reference["clock"][1] - truth.rx_clock_drift_mps) < 0.05
    assert p.status == "aided"


def test_fault_free_integrity_messages_bound_the_error(fault_free):
    """Every epoch: an Integrity message; HPL/VPL above the true errors; no detection, exclusion
    or alarm (NPA: HAL 556 m)."""
    _, log = fault_free
    assert all(out is not None for _, out, _, _, _ in log)
    for _, out, e, _, _ in log:
        assert out.hal_m == 556.0 and out.val_m is None and out.phase == "npa"
        assert math.hypot(e[0], e[1]) < out.hpl_m
        assert abs(e[2]) < out.vpl_m
        assert not out.detected and not out.alarm and out.available and out.excluded == []
        assert len(out.satellites) >= 8
        assert all(s.statistic_m <= s.threshold_m for s in out.satellites)


def test_ramp_fault_is_detected_and_only_the_faulty_satellite_excluded(scenario):
    """A 5 m/s pseudorange ramp on one satellite from 20 s: detected within 5 s, that satellite
    (and no other) excluded, no alarm; HPL bounds the true horizontal error at every epoch."""
    traj, epochs = scenario
    faulty = "C23"
    assert any(o.id == faulty for o in epochs[0].message.sats)
    ramp = [(faulty, lambda t: 5.0 * (t - 20.0) if t >= 20.0 else 0.0)]
    p, log = run(traj, epochs, TightlyCoupledConfig(name="tc"), ramp)
    t_det = next(t for t, out, _, _, _ in log if out.detected)
    assert 20.0 < t_det <= 25.0
    exclusions = [last.excluded_now for _, _, _, last, _ in log if last.excluded_now]
    assert exclusions == [faulty]
    for t, out, e, last, _ in log:
        assert not out.alarm
        assert math.hypot(e[0], e[1]) < out.hpl_m
        if t > t_det:
            assert out.excluded == [faulty] and faulty not in last.used
    assert np.linalg.norm(log[-1][2][:3]) < 2.0


def test_excluded_satellite_is_readmitted_after_the_fault_ends(scenario):
    """A 60 m step on one satellite for 20-30 s; readmit_after_s = 5: excluded at onset,
    re-admitted once its residuals have been healthy for 5 s, then used without further alarms."""
    traj, epochs = scenario
    faulty = "C25"
    step = [(faulty, lambda t: 60.0 if 20.0 <= t < 30.0 else 0.0)]
    p, log = run(traj, epochs, TightlyCoupledConfig(name="tc", readmit_after_s=5.0), step)
    excl_t = [t for t, _, _, last, _ in log if last.excluded_now == faulty]
    back_t = [t for t, _, _, last, _ in log if faulty in last.readmitted]
    assert len(excl_t) == 1 and 20.0 <= excl_t[0] <= 20.5
    # 5 s of healthy residuals after the fault ends at 30 s (a noisy failure restarts the clock)
    assert len(back_t) == 1 and 35.0 - 1e-6 <= back_t[0] <= 40.0
    assert faulty in p.bank.mhss.sats
    assert not any(out.alarm for _, out, _, _, _ in log)
    assert all(last.excluded_now in (None, faulty) for _, _, _, last, _ in log)


def test_a_restart_keeps_the_exclusions_until_their_health_check_passes(scenario):
    """A 60 m step on one satellite from 20 s to the end; the pipeline restarted at 30 s (a reset
    on a running vehicle, as recovery does), readmit_after_s = 5: the satellite stays excluded
    through the restart and after it (its fault goes on), excluded once, never used again. Before
    the fix the restart cleared the exclusions: the faulty satellite was back in the next epoch."""
    traj, epochs = scenario
    faulty = "C25"
    cfg = TightlyCoupledConfig(name="tc", readmit_after_s=5.0)
    step = [(faulty, lambda t: 60.0 if t >= 20.0 else 0.0)]
    p, log = run(traj, epochs, cfg, step, hook=_reset_at(traj, 30.0))
    assert p.reinitialisations == 1
    excl_t = [t for t, _, _, last, _ in log if last.excluded_now == faulty]
    assert len(excl_t) == 1 and 20.0 <= excl_t[0] <= 20.5
    after = [(t, out, last) for t, out, _, last, _ in log if t > excl_t[0]]
    assert any(t > 30.0 for t, _, _ in after)
    for t, out, last in after:
        assert faulty not in last.used, f"{faulty} used again at {t:.1f} s"
        assert out.excluded == [faulty]
        assert not last.readmitted
    # a fault that ended (20-30 s) and a restart at 33 s, while its health clock runs: re-admitted
    # when its 5 s of health are complete (35-40 s, as without the restart), not at the restart
    step = [(faulty, lambda t: 60.0 if 20.0 <= t < 30.0 else 0.0)]
    p, log = run(traj, epochs, cfg, step, hook=_reset_at(traj, 33.0))
    assert p.reinitialisations == 1
    back_t = [t for t, _, _, last, _ in log if faulty in last.readmitted]
    assert len(back_t) == 1 and 35.0 - 1e-6 <= back_t[0] <= 40.0
    assert all(faulty not in last.used for t, _, _, last, _ in log if 20.5 <= t < back_t[0])


def test_a_suspect_state_does_not_judge_an_excluded_satellites_health(scenario):
    """A 60 m step on one satellite for 20-30 s (readmit_after_s = 5); from 31 to 32 s the INS is
    300 m off and the pipeline unverified (as while suspect), then restarted from the truth: the
    health tests against the wrong state do not restart the satellite's health clock, so it is
    re-admitted as without the episode (before 37 s), not 5 s after it."""
    traj, epochs = scenario
    faulty = "C25"
    cfg = TightlyCoupledConfig(name="tc", readmit_after_s=5.0)
    step = [(faulty, lambda t: 60.0 if 20.0 <= t < 30.0 else 0.0)]
    _, log0 = run(traj, epochs, cfg, step)
    back0 = [t for t, _, _, last, _ in log0 if faulty in last.readmitted]
    assert len(back0) == 1 and back0[0] < 36.0
    reset = _reset_at(traj, 32.0)
    state = {}

    def suspect_episode(k, p):
        t = float(traj.t_s[k]) - T0
        if t >= 31.0 and "off" not in state:
            p.bank.ins.state.lat_rad += 300.0 / 6.4e6
            p.mark_unverified("imu_contested")
            state["off"] = t
        reset(k, p)
        if t >= 32.0 and "back" not in state:
            p.mark_verified()
            state["back"] = t

    p, log = run(traj, epochs, cfg, step, hook=suspect_episode)
    assert p.reinitialisations == 1
    back = [t for t, _, _, last, _ in log if faulty in last.readmitted]
    assert len(back) == 1 and back[0] < 36.0, back


def _reset_at(traj, t_rel: float):
    """A hook of :func:`run` that restarts the pipeline from the true state at ``t_rel`` (a reset
    on a running vehicle, as recovery does)."""
    done = []

    def hook(k, p):
        t = float(traj.t_s[k])
        if not done and t - T0 >= t_rel:
            s = traj.state_at(t)
            nav = NavState(t, *s.llh, s.vel_enu_mps.copy(), earth.mat_to_quat(earth.rpy_to_mat_nb(s.rpy_rad)))
            p.start(nav, InitStd(np.full(3, 5.0), np.full(3, 0.1), np.radians([0.05, 0.05, 0.2])))
            done.append(t)

    return hook


def test_setting_and_rising_satellites_rebuild_the_bank(scenario):
    """A satellite disappears at 30 s and comes back at 40 s (as when setting/rising): the bank
    shrinks and grows (exact rebuilds), no detection, PLs still bound the error."""
    traj, epochs = scenario
    gone = "C28"
    outage = [(gone, lambda t: None if 30.0 <= t < 40.0 else 0.0)]
    p, log = run(traj, epochs, TightlyCoupledConfig(name="tc"), outage)
    n_all = len(epochs[0].message.sats)
    for t, out, e, last, _ in log:
        assert len(last.used) == (n_all - 1 if 30.0 <= t < 40.0 else n_all)
        assert not out.detected and not out.alarm
        assert math.hypot(e[0], e[1]) < out.hpl_m
    assert gone in p.bank.mhss.sats


def test_lpv_phase_uses_vertical_limits_and_integrity_off_emits_nothing(scenario):
    traj, epochs = scenario
    short = {k: v for k, v in epochs.items() if k <= 1000}
    p, log = run(traj, short, TightlyCoupledConfig(name="tc", phase="lpv200", sub_sub_filters=False))
    out = log[-1][1]
    assert (out.hal_m, out.val_m) == (40.0, 35.0)
    assert out.available == (out.hpl_m <= 40.0 and out.vpl_m <= 35.0)
    assert p.bank.mhss.B == 1 + p.bank.mhss.N
    p0, log0 = run(traj, short, TightlyCoupledConfig(name="tc", integrity=False))
    assert all(out is None for _, out, _, _, _ in log0)
    assert p0.bank.mhss.B == 1
    assert np.linalg.norm(log0[-1][2][:3]) < 3.0


def test_covariance_recovery_restarts_the_bank_and_keeps_navigating(scenario):
    """recover_covariance (lost positive definiteness): members and cross blocks restart from
    the initial covariance, the INS and clock are kept, the next epochs aid again."""
    traj, epochs = scenario
    short = {k: v for k, v in epochs.items() if k <= 2000}
    seen = {}

    def hook(k, p):
        if k == 1001:
            p.recover_covariance()
            seen["status"], seen["B"] = p.status, p.bank.mhss.B
            seen["P"] = p.bank.mhss.blocks.copy()

    p, log = run(traj, short, TightlyCoupledConfig(name="tc"), hook=hook)
    assert seen["status"] == "unaided" and seen["B"] == p.bank.mhss.B
    np.testing.assert_array_equal(seen["P"], np.broadcast_to(p._P0, seen["P"].shape))
    # aided again after the restart (the run goes on past the last GNSS epoch kept: coasting there)
    assert p.current_status(p.last_aiding_t) == "aided" and p.reinitialisations == 1
    for _, out, e, _, _ in log:
        assert not out.alarm and math.hypot(e[0], e[1]) < out.hpl_m
    assert np.linalg.norm(log[-1][2][:3]) < 3.0


def test_runs_through_the_engine(scenario):
    """InitialNav + ImuSample + GnssRaw through VehicleEngine: Integrity messages come out."""
    from fednav.service.config import ServiceConfig
    from fednav.service.engine import VehicleEngine

    traj, epochs = scenario
    outs = []

    class Sink:  # tolerant of extra arguments (the sink protocol may grow)
        def on_estimate(self, *args, **kwargs):
            pass

        def on_output(self, vehicle, msg, *args, **kwargs):
            outs.append(msg)

        def on_truth(self, *args, **kwargs):
            pass

    cfg = ServiceConfig(pipelines=[TightlyCoupledConfig(name="tc")])
    eng = VehicleEngine("v1", cfg, Sink())
    nav, std = initial_nav(traj)
    eng.handle("init", "init", initial_nav_message(T0, nav, (10.0,) * 3, (0.3,) * 3, (0.1, 0.1, 0.3)))
    for k in range(1, 501):
        if k in epochs:
            assert eng.handle("gnss_raw", "gnss0", epochs[k].message)
        assert eng.handle(
            "imu",
            "imu0",
            ImuSample(
                t=float(traj.t_s[k]),
                dt_s=traj.dt_s,
                dtheta_rad=tuple(float(v) for v in traj.dtheta_rad[k]),
                dvel_mps=tuple(float(v) for v in traj.dvel_mps[k]),
            ),
        )
    integ = [o for o in outs if type(o).__name__ == "Integrity"]
    assert len(integ) >= 45
    assert not any(o.alarm for o in integ)
