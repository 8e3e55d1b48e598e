"""Issue 24: the antenna lever arm and the IMU scale factors as estimated states (loosely coupled).

Unit checks: the fix model's lever-arm columns against finite differences of its reference; the
scale-factor compensation of the INS (own minor loop and a shared preintegrator) and its F
columns against two INSes run apart; the estimates kept through a restart; the configuration.

Simulated drive (``lever_arm_drive``: a car with a 1.03 m antenna offset the service is not told,
IMU scale-factor errors of 3000 ppm 1-sigma, turns both ways and speed changes), seeds 1-3, the
epochs after ``SKIP_S``:
(a) the lever arm converges to the truth (horizontal within ``LEVER_TOL_M``, every axis within
    3 sigma of the full model) once the turns are driven;
(b) the fused horizontal error beats the receiver's and the same pipeline without estimation;
(c) the scale factors move toward the truth (gyro z) and stay consistent; heading and position are
    not worse with them estimated.
"""

from __future__ import annotations

import math

import numpy as np
import pytest

from fednav.service import config as config_mod
from fednav.service import earth, keys
from fednav.service.engine import VehicleEngine
from fednav.service.estimation.ins_filter import InsFilterBank, imu_scale_block
from fednav.service.estimation.measurements import ModelContext, private_layout
from fednav.service.estimation.measurements.gnss_fix import LEVER_BLOCK, GnssFixModel, lever_arm_block
from fednav.service.ins import error_model as em
from fednav.service.ins.alignment import InitStd
from fednav.service.ins.mechanisation import NavState, Preintegrator
from fednav.service.messages import Faults, GnssFix
from fednav.simulators.evaluate import service_config
from fednav.simulators.own_data_eval import fix_errors
from fednav.simulators.scenario import load_scenario
from fednav.simulators.stream import Simulation

SEEDS = (1, 2, 3)
SKIP_S = 60.0  # the first turn (20-35 s) and what follows it: convergence left out
LEVER_TOL_M = 0.15


def nav0() -> NavState:
    rpy = np.array([0.04, -0.02, 0.9])
    return NavState(
        t=100.0,
        lat_rad=math.radians(48.1),
        lon_rad=math.radians(11.5),
        h_m=520.0,
        vel_enu_mps=np.array([7.0, -4.0, 0.2]),
        q_nb=earth.mat_to_quat(earth.rpy_to_mat_nb(rpy)),
    )


# --- the fix model's lever-arm columns ------------------------------------------------------------
@pytest.mark.parametrize(
    "msg",
    [
        GnssFix(t=100.0, lat_deg=48.10001, lon_deg=11.50002, height_m=521.0, vel_enu_mps=(7.1, -3.9, 0.1)),
        GnssFix(t=100.0, lat_deg=48.10001, lon_deg=11.50002, height_m=521.0, speed_mps=8.0, course_deg=118.0),
    ],
    ids=["velocity", "speed_course"],
)
def test_lever_arm_columns_match_finite_differences_of_the_reference(msg):
    """dl = l_ref - l (computed minus true): H[:, lever] = dz / d(reference)."""
    prior = np.array([0.2, 0.5, 0.1])
    model = GnssFixModel(lever_arm_b_m=prior, estimate_lever_arm=True, lever_arm_std_m=1.0)
    blocks = model.private_states
    assert [b.name for b in blocks] == [LEVER_BLOCK]
    cols = private_layout(blocks)
    n = em.N_STATES + 3
    w = np.array([0.03, -0.02, 0.25])
    ref = np.array([0.1, -0.3, 0.2])

    def z(r):
        ctx = ModelContext(n_states=n, columns=cols, reference={LEVER_BLOCK: r}, wib_b_rps=w)
        return model(nav0(), msg, ctx)

    m0 = z(ref)
    # the model uses the configured lever arm plus the reference: the same z as a known lever arm
    known = GnssFixModel(lever_arm_b_m=prior + ref)(nav0(), msg, ModelContext(wib_b_rps=w))
    np.testing.assert_allclose(m0.z, known.z, atol=1e-9)
    np.testing.assert_allclose(m0.H[:, : em.N_STATES], known.H, atol=1e-12)
    for j in range(3):
        e = np.zeros(3)
        e[j] = 1e-3
        fd = (z(ref + e).z - z(ref - e).z) / 2e-3
        np.testing.assert_allclose(m0.H[:, em.N_STATES + j], fd, atol=1e-7, err_msg=f"axis {j}")
    assert np.abs(m0.H[:3, em.N_STATES :]).max() > 0.5  # C_nb: really there
    with pytest.raises(ValueError, match="gnss_lever_arm"):
        model(nav0(), msg, ModelContext())


def test_lever_arm_block_and_options():
    b = lever_arm_block(0.5, rw_m_per_sqrt_h=0.06)
    Phi, Qd = b.transition(10.0)
    np.testing.assert_array_equal(Phi, np.eye(3))
    np.testing.assert_allclose(np.diagonal(Qd), 0.06**2 / 3600.0 * 10.0)
    assert b.initial_std == (0.5, 0.5, 0.5)
    # off by default: no private state, the known-lever-arm model as before
    assert GnssFixModel(lever_arm_b_m=(0.1, 0.2, 0.3)).private_states == ()
    with pytest.raises(config_mod.ConfigError, match="estimate_gnss_lever_arm"):
        config_mod.from_dict(
            {
                "pipelines": [
                    {
                        "name": "a",
                        "kind": "loosely_coupled",
                        "sensors": ["baro"],
                        "estimate_gnss_lever_arm": True,
                    }
                ]
            }
        )
    with pytest.raises(config_mod.ConfigError, match="gnss_lever_arm_std_m"):
        config_mod.from_dict(
            {"pipelines": [{"name": "a", "kind": "loosely_coupled", "gnss_lever_arm_std_m": 0}]}
        )


# --- the scale factors in the INS -----------------------------------------------------------------
def _bank(scale_ref=None) -> InsFilterBank:
    blocks = () if scale_ref is None else (imu_scale_block(5e-3, 5e-3),)
    n = em.N_STATES + sum(b.size for b in blocks)
    bank = InsFilterBank(nav0(), np.eye(n) * 1e-4, em.ImuNoise(1e-4, 1e-3), private=blocks)
    if scale_ref is not None:
        bank.reference[em.SCALE_BLOCK][:] = scale_ref
    return bank


W_B = np.array([0.02, -0.03, 0.2])  # rad/s
F_B = np.array([0.3, 0.8, 9.9])  # m/s^2
DT = 0.01


def test_scale_estimate_is_removed_from_the_increments_own_and_shared():
    """IMU increments (1 + s) x true, a bank whose scale reference is s: the same navigation as a
    bank without scale states fed the true increments (own minor loop and shared preintegrator)."""
    s = np.array([3e-3, -2e-3, 4e-3, -3e-3, 2.5e-3, 1.5e-3])
    plain, own, shared = _bank(), _bank(s), _bank(s)
    pre = Preintegrator()
    pre.reset(plain.t)
    t = plain.t
    for k in range(300):
        th, dv = W_B * DT, F_B * DT
        t += DT
        plain.push_imu(th, dv, DT, t)
        own.push_imu(th * (1 + s[:3]), dv * (1 + s[3:]), DT, t)
        pre.push(th * (1 + s[:3]), dv * (1 + s[3:]), DT, t)
        if (k + 1) % 10 == 0:
            shared.advance(pre)
            pre.reset(t)
    for b in (own, shared):
        nb, np_ = b.nav(), plain.nav()
        assert nb.t == pytest.approx(np_.t)
        np.testing.assert_allclose(nb.vel_enu_mps, np_.vel_enu_mps, atol=1e-9)
        np.testing.assert_allclose(nb.q_nb, np_.q_nb, atol=1e-12)
        np.testing.assert_allclose(nb.llh, np_.llh, atol=1e-12)
    # without the compensation they would differ (the test can fail): 0.4 % of 0.2 rad/s over 3 s
    raw = _bank()
    t = raw.t
    for _ in range(300):
        t += DT
        raw.push_imu(W_B * DT * (1 + s[:3]), F_B * DT * (1 + s[3:]), DT, t)
    assert np.abs(raw.nav().q_nb - plain.nav().q_nb).max() > 1e-4


def test_scale_columns_of_F_match_two_INSes_run_apart():
    """An INS with scale estimate d against one with none (the truth, s = 0): after T the attitude
    and velocity differences are Phi[:, scale] d (first order)."""
    d = np.array([2e-3, -3e-3, 4e-3, 3e-3, -2e-3, 5e-3])
    truth, est = _bank(np.zeros(6)), _bank(d)
    t = truth.t
    Phi = np.eye(truth.n)
    for _ in range(100):
        t += DT
        for b in (truth, est):
            b.push_imu(W_B * DT, F_B * DT, DT, t)
        if truth.ins.pending_s == 0.0:
            Phi = truth.last_Phi @ Phi
    cols = truth.columns[em.SCALE_BLOCK]
    pred = Phi[:, cols] @ d
    a, b = est.nav(), truth.nav()
    phi = earth.quat_to_rotvec(earth.mat_to_quat(b.mat_nb @ a.mat_nb.T))  # C_est = (I - [phi x]) C
    dv = a.vel_enu_mps - b.vel_enu_mps
    np.testing.assert_allclose(phi, pred[em.ATT], rtol=0.03, atol=1e-8)
    np.testing.assert_allclose(dv, pred[em.VEL], rtol=0.03, atol=1e-6)
    assert np.abs(dv).max() > 1e-3 and np.abs(phi).max() > 1e-4


def test_lever_arm_and_scale_estimates_survive_a_restart():
    """keep_private_states (the lifecycle's resets): the blocks' references, states and
    covariance carried over; the navigation restarted."""
    cfg = config_mod.from_dict(
        {
            "pipelines": [
                {
                    "name": "lc",
                    "kind": "loosely_coupled",
                    "estimate_gnss_lever_arm": True,
                    "estimate_imu_scale_factors": True,
                }
            ]
        }
    )
    from fednav.service.pipelines import build_pipeline

    p = build_pipeline(cfg.pipelines[0], cfg)
    std = InitStd(np.full(3, 1.0), np.full(3, 0.1), np.full(3, 0.01))
    p.start(nav0(), std)
    assert p.bank.n == em.N_STATES + 3 + 6
    lever, scale = p.bank.columns[LEVER_BLOCK], p.bank.columns[em.SCALE_BLOCK]
    p.bank.reference[LEVER_BLOCK][:] = [0.4, 0.9, 0.3]
    p.bank.reference[em.SCALE_BLOCK][:] = 1e-3
    p.bank.P[0, lever, lever] = np.eye(3) * 0.01**2
    old = p.bank
    p.start(nav0(), std)
    assert not p.bank.reference[LEVER_BLOCK].any()  # the prior, before keeping
    p.keep_private_states(old)
    np.testing.assert_array_equal(p.bank.reference[LEVER_BLOCK], [0.4, 0.9, 0.3])
    np.testing.assert_array_equal(p.bank.scale_estimate(), np.full(6, 1e-3))
    np.testing.assert_allclose(p.bank.P[0, lever, lever], np.eye(3) * 1e-4)
    states = {s.name: s for s in p.private_state_estimates()}
    assert states["gnss_lever_arm_y_m"].value == pytest.approx(0.9)
    assert states["gyro_scale_z_ppm"].value == pytest.approx(1000.0)
    assert states["gyro_scale_z_ppm"].std == pytest.approx(5000.0)
    assert scale.stop == p.bank.n


# --- the simulated drive --------------------------------------------------------------------------
class _Sink:
    def __init__(self):
        self.t: dict[str, list] = {}
        self.err: dict[str, list] = {}
        self.states: dict[str, list] = {}

    def on_estimate(self, vehicle, out) -> None:
        if out.err9 is not None:
            self.t.setdefault(out.name, []).append(out.t)
            self.err.setdefault(out.name, []).append(out.err9)

    def on_output(self, vehicle, msg, err9=None) -> None:
        if isinstance(msg, Faults) and msg.states:
            self.states.setdefault(msg.pipeline, []).append(
                (msg.t, {s.name: (s.value, s.std) for s in msg.states})
            )

    def on_truth(self, vehicle, truth) -> None:
        pass


def _rms(x) -> float:
    return float(math.sqrt(np.mean(np.square(x))))


@pytest.fixture(scope="module")
def drive():
    """Per seed: the receiver's and each pipeline's horizontal RMS and heading RMS after SKIP_S,
    the last published states, the true lever arm and scale factors."""
    sc = load_scenario("lever_arm_drive")
    cfg = service_config(sc)
    traj = sc.build_trajectory()
    t0 = float(traj.t_s[0])
    runs = []
    for seed in SEEDS:
        sink = _Sink()
        engine = VehicleEngine("v1", cfg, sink)
        sim = Simulation(sc, seed=seed, trajectory=traj, prefix=cfg.prefix)
        for key, msg in sim:
            pk = keys.parse_input(key, cfg.prefix)
            engine.handle(pk.kind, pk.sensor_id, msg)
        fe = fix_errors(sim, np.asarray(sc.gnss.lever_arm_b_m))
        sel = fe["t"] - t0 >= SKIP_S
        run = {
            "receiver_h": _rms(np.hypot(fe["pos"][sel, 0], fe["pos"][sel, 1])),
            "h": {},
            "heading_deg": {},
            "states": {p: s for p, s in sink.states.items()},
            "lever": np.asarray(sc.gnss.lever_arm_b_m),
            "scale_ppm": np.concatenate([sim.truth.imu_errors.gyro_scale, sim.truth.imu_errors.accel_scale])
            * 1e6,
        }
        for name, err in sink.err.items():
            e, t = np.asarray(err), np.asarray(sink.t[name]) - t0
            m = t >= SKIP_S
            run["h"][name] = _rms(np.hypot(e[m, 0], e[m, 1]))
            run["heading_deg"][name] = math.degrees(_rms(e[m, 8]))
        runs.append(run)
    return runs


def _last(run, pipeline):
    return run["states"][pipeline][-1][1]


@pytest.mark.parametrize("pipeline", ["lc_lever", "lc_lever_sf"])
def test_lever_arm_converges_to_the_unknown_offset(drive, pipeline):
    for seed, run in zip(SEEDS, drive, strict=True):
        st = _last(run, pipeline)
        est = np.array([st[f"gnss_lever_arm_{a}_m"][0] for a in "xyz"])
        sd = np.array([st[f"gnss_lever_arm_{a}_m"][1] for a in "xyz"])
        err = est - run["lever"]
        msg = f"seed {seed} {pipeline}: estimate {est.round(3)} +- {sd.round(3)}, truth {run['lever']}"
        assert np.all(np.abs(err[:2]) < LEVER_TOL_M), msg
        assert np.all(sd[:2] < 0.1), msg  # observed (prior 1 m)
        # consistent: horizontal always; every axis in the full model (the scale errors modelled)
        axes = 3 if pipeline == "lc_lever_sf" else 2
        assert np.all(np.abs(err[:axes]) < 3.0 * sd[:axes]), msg
        # published through the run, not only at its end: the first (before the turns) is the prior
        first = run["states"][pipeline][0][1]
        assert first["gnss_lever_arm_x_m"][1] > 0.5, msg


def test_fused_horizontal_error_beats_the_receiver_and_no_estimation(drive):
    for seed, run in zip(SEEDS, drive, strict=True):
        h = run["h"]
        msg = f"seed {seed}: receiver {run['receiver_h']:.3f} m, pipelines {h}"
        # the user's situation: ~1 m off, worse than the receiver
        assert h["lc_unknown"] > 0.8, msg
        for name in ("lc_lever", "lc_lever_sf"):
            assert h[name] < 0.5 * run["receiver_h"], msg
            assert h[name] < 0.5 * h["lc_unknown"], msg
            assert h[name] < 2.0 * h["lc_known"], msg


def test_scale_factors_converge_and_do_not_hurt(drive):
    gz_err, gz_true = [], []
    for seed, run in zip(SEEDS, drive, strict=True):
        st = _last(run, "lc_lever_sf")
        names = [f"{s}_scale_{a}_ppm" for s in ("gyro", "accel") for a in "xyz"]
        est = np.array([st[n][0] for n in names])
        sd = np.array([st[n][1] for n in names])
        err = est - run["scale_ppm"]
        msg = f"seed {seed}: estimate {est.round(0)} +- {sd.round(0)} ppm, truth {run['scale_ppm'].round(0)}"
        assert np.all(np.abs(err) < 3.0 * sd), msg
        assert sd[2] < 0.4 * 5000.0, msg  # gyro z observed in the turns
        gz_err.append(err[2])
        gz_true.append(run["scale_ppm"][2])
    # gyro z: the estimate moved toward the truth (its prior mean 0 has the truth's error)
    assert _rms(gz_err) < 0.5 * _rms(gz_true), (gz_err, gz_true)
    heading = {n: _rms([r["heading_deg"][n] for r in drive]) for n in ("lc_lever", "lc_lever_sf")}
    h = {n: _rms([r["h"][n] for r in drive]) for n in ("lc_lever", "lc_lever_sf")}
    assert heading["lc_lever_sf"] < heading["lc_lever"], heading
    assert h["lc_lever_sf"] < 1.1 * h["lc_lever"], h
