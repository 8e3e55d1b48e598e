"""The extension hooks of docs/ARCHITECTURE.md, each exercised the way its how-to says.

Each test adds something new through the public hook only (a registry line, done here with
``monkeypatch`` so the registries are restored), then runs it in the real code path:
- a sensor: a measurement model + one entry in the sensor registry (``service.sensors``),
  configured in a federated pipeline through the service configuration (the barometer,
  tests/test_baro.py, is a whole sensor added that way: one file + one registry line);
- private states: a model that declares its own states, estimated closed loop by a filter bank;
- a pipeline family: a ``Pipeline`` subclass registered by kind;
- a sharing strategy and a fault test: a class + one registry line each.
"""

from __future__ import annotations

import math

import numpy as np
import pytest
from scipy.stats import chi2

from fednav.service import config, earth, pipelines, sensors
from fednav.service.estimation import kalman, measurements
from fednav.service.estimation.federated import fault_tests, sharing
from fednav.service.estimation.federated.core import FederatedCore, LinearBank
from fednav.service.estimation.federated.fault_tests import FaultDecision, FaultTest, make_fault_test
from fednav.service.estimation.federated.sharing import SharingStrategy, get_strategy
from fednav.service.estimation.ins_filter import InsFilterBank
from fednav.service.estimation.measurements import Measurement, ModelContext, PrivateStates
from fednav.service.ins import error_model as em
from fednav.service.messages import DvlVelocity, Faults, GnssFix
from fednav.service.pipelines.base import Estimate, Pipeline, initial_covariance
from fednav.service.sensors import SensorKind

from .test_federated import IMU, drive, mini_ins, run_linear, static_stream
from .test_federated import H as STATIC_H


# --- how to add a sensor ----------------------------------------------------------------------------
class DvlBodyVelocity:
    """Example sensor model: body-frame velocity (a DVL without scale factor or offset).

    v_b(computed) = C_nb(computed)' v_n = v_b - C_nb' [v_n x] phi + C_nb' dv_n (small angles), so
    z = C_nb' v_ins - v_dvl, H_vel = C_nb', H_att = -C_nb' [v_n x].
    """

    kind = "dvl"
    private_states = ()

    def __call__(self, nav, msg: DvlVelocity, ctx: ModelContext) -> Measurement:
        c_bn = nav.mat_nb.T
        v = np.asarray(nav.vel_enu_mps, dtype=float)
        z = c_bn @ v - np.asarray(msg.vel_b_mps, dtype=float)
        H = np.zeros((3, ctx.n_states))
        H[:, em.VEL] = c_bn
        H[:, em.ATT] = -c_bn @ earth.skew(v)
        return Measurement(z, H, np.diag(np.square(msg.vel_std_mps)), ("vb_x", "vb_y", "vb_z"))


def _with_dvl(events, sigma_mps=0.01):
    """Add a zero body velocity (the vehicle is static) at every GNSS epoch of a static stream."""
    out = []
    for ev in events:
        out.append(ev)
        if ev[0] == "gnss_fix":
            out.append(
                ("dvl", ev[1], DvlVelocity(t=ev[1], vel_b_mps=(0, 0, 0), vel_std_mps=(sigma_mps,) * 3))
            )
    return out


def _federated_config(sensors_of_second_local):
    return {
        "imu": IMU.model_dump(),
        "pipelines": [
            {
                "kind": "federated",
                "name": "fed",
                "fault_handling": "per_observation",
                "subsystems": [
                    {"name": "INS/GNSS", "sensors": ["gnss_fix"]},
                    {"name": "INS/DVL", "sensors": sensors_of_second_local},
                ],
            }
        ],
    }


def test_add_a_sensor_model_one_registry_line(monkeypatch):
    # not registered: the configuration is refused at load, naming the field
    with pytest.raises(
        config.ConfigError, match=r"pipelines\.0\.subsystems\.1\.sensors\.0: sensor kind 'dvl'"
    ):
        config.from_dict(_federated_config(["dvl"]))
    # the one registry entry (here replacing the DVL's own entry, whose model has private states)
    monkeypatch.setitem(
        sensors.registry(), "dvl", SensorKind("dvl", DvlVelocity, ("dvl", "{id}"), DvlBodyVelocity)
    )
    cfg = config.from_dict(_federated_config(["dvl"]))
    fed = pipelines.build_pipeline(cfg.pipelines[0], cfg)
    ref = pipelines.build_pipeline(
        config.from_dict(_federated_config(["star"])).pipelines[0], cfg
    )  # same GNSS, no DVL
    init, std, events = static_stream(3, 30)
    events = [e for e in events if e[0] != "star"]
    out = drive([fed, ref], _with_dvl(events), init, std)
    faults = [m for m in out["fed"] if isinstance(m, Faults) and m.subsystems[0].name == "INS/DVL"]
    assert len(faults) == 30  # one Faults message per DVL message, rows labelled by the model
    assert [o.label for o in faults[-1].subsystems[0].observations] == ["vb_x", "vb_y", "vb_z"]
    assert fed.status == "aided"
    # 1 cm/s body velocity beats 0.1 m/s GNSS velocity: the fused velocity sigma shows it
    sd_fed = np.sqrt(np.diag(fed.estimate().P9))[3:6]
    sd_ref = np.sqrt(np.diag(ref.estimate().P9))[3:6]
    assert np.all(sd_fed < 0.5 * sd_ref)
    truth_vel_err = np.abs(fed.estimate().nav.vel_enu_mps)  # static truth: the velocity is the error
    assert np.all(truth_vel_err < 4.0 * sd_fed)


# --- how to give a model states of its own ----------------------------------------------------------
BARO_BIAS_M = 5.0


class BaroHeight:
    """Example model with a private state: barometric height with an unknown constant bias b.

    h_baro = h + b + v  ->  z = h_ins + b_ref - h_baro = dp_u + db + v (b_ref: the bias reference,
    closed loop); the bias is a random constant (a tiny random walk keeps it adaptable)."""

    kind = "baro"

    def __init__(self):
        def transition(T):
            return np.eye(1), np.array([[1e-6 * T]])

        self.private_states = (PrivateStates("baro", ("baro_bias_m",), transition, (20.0,)),)

    def __call__(self, nav, h_baro: float, ctx: ModelContext) -> Measurement:
        cols = ctx.columns["baro"]
        H = np.zeros((1, ctx.n_states))
        H[0, em.POS.start + 2] = 1.0
        H[0, cols] = 1.0
        z = np.array([nav.h_m + ctx.reference["baro"][0] - h_baro])
        return Measurement(z, H, np.array([[0.5**2]]), ("baro_h",))


def test_private_states_are_estimated_closed_loop():
    """GNSS height (10 m sigma) and a biased barometer (0.5 m): the filter bank carries the
    model's private bias state and its reference; after 60 s the bias reference is within
    3 sigma of the true 5 m bias and its sigma is well below the 20 m prior."""
    init, std, events = static_stream(4, 60)
    gnss_model, baro = measurements.make("gnss_fix"), BaroHeight()
    n = 15 + 1
    P0 = np.zeros((n, n))
    P0[:15, :15] = initial_covariance(std, IMU)
    P0[15, 15] = baro.private_states[0].initial_std[0] ** 2
    bank = InsFilterBank(init, P0, IMU.noise(), private=baro.private_states)
    assert bank.columns == {"baro": slice(15, 16)}
    rng = np.random.default_rng(0)
    for ev in events:
        if ev[0] == "imu":
            bank.push_imu(ev[2], ev[3], ev[4])
            continue
        if ev[0] != "gnss_fix":
            continue
        bank.sync()
        h_baro = STATIC_H + BARO_BIAS_M + rng.normal(0.0, 0.5)
        for meas in (gnss_model(bank.nav(), ev[2], bank.context()), baro(bank.nav(), h_baro, bank.context())):
            bank.x, bank.P, _ = kalman.update(bank.x, bank.P, meas.z, meas.H, meas.R)
            bank.feedback(bank.x[0].copy())
    sigma = math.sqrt(bank.P[0, 15, 15])
    assert sigma < 5.0  # from the 20 m prior: the bias is observed (GNSS height vs barometer)
    assert abs(bank.reference["baro"][0] - BARO_BIAS_M) < 3.0 * sigma


# --- how to add a pipeline family -------------------------------------------------------------------
class PositionOnly(Pipeline):
    """Example family: an INS aided by GNSS position only (velocity rows dropped)."""

    @classmethod
    def sensor_kinds(cls):
        return frozenset({"gnss_fix"})

    def __init__(self, cfg, imu, major_interval_s):
        super().__init__(cfg.name, imu, major_interval_s)
        self.model = measurements.make("gnss_fix")

    def initialise(self, nav, std):
        self.bank = InsFilterBank(nav, initial_covariance(std, self.imu), self.imu.noise())

    def apply(self, kind, sensor_id, msg, dt_late_s=0.0):
        if kind != "gnss_fix":
            return []
        m = self.model(self.bank.nav(), msg, self.bank.context(dt_late_s))
        b = self.bank
        b.x, b.P, _ = kalman.update(b.x, b.P, m.z[:3], m.H[:3], m.R[:3, :3])
        b.feedback(b.x[0].copy())
        self.mark_aided(b.t)
        return []

    def estimate(self):
        return Estimate(self.bank.nav(), self.bank.P[0, :9, :9])


def test_add_a_pipeline_family(monkeypatch):
    monkeypatch.setitem(pipelines._KINDS, "position_only", f"{__name__}:PositionOnly")
    cls = pipelines.pipeline_class("position_only")
    assert cls is PositionOnly
    cfg = config.from_dict({"imu": IMU.model_dump()})
    p = cls(cfg.pipelines[0], cfg.imu, cfg.major_interval_s)
    init, std, events = static_stream(5, 60)
    drive([p], [e for e in events if e[0] != "star"], init, std)
    assert p.status == "aided" and p.updates == 60
    sol = p.solution()
    assert max(sol.pos_std_enu_m) < 10.0  # 10 m fixes, averaged
    assert sol.status == "aided"


# --- how to add a sharing strategy -------------------------------------------------------------------
class InverseTrace(SharingStrategy):
    """Example scalar strategy: shares proportional to 1 / trace(P_i)."""

    name = "inverse_trace"
    scalar = True

    def _weights(self, P, ctx):
        return 1.0 / np.trace(P, axis1=1, axis2=2)


def test_add_a_sharing_strategy(monkeypatch):
    monkeypatch.setitem(sharing.STRATEGIES, "inverse_trace", InverseTrace)
    G = get_strategy("inverse_trace").shares(np.stack([np.eye(3), 4.0 * np.eye(3)]))
    np.testing.assert_allclose(G.sum(axis=0), 1.0)  # conserves information, state by state
    np.testing.assert_allclose(G[:, 0], [0.8, 0.2])
    # any scalar share with fusion-reset reproduces the centralised filter (Carlson 1990)
    xc, Pc, _ = run_linear("fixed", 1, 100, seed=8)
    xf, Pf, _ = run_linear("inverse_trace", 2, 100, seed=8)
    sd = np.sqrt(np.diagonal(Pc, axis1=1, axis2=2))
    assert np.max(np.abs(xf - xc) / sd) < 1e-9


# --- how to add a fault test -------------------------------------------------------------------------
class NisGate(FaultTest):
    """Example fault test: drop the whole update when its NIS exceeds the chi-square quantile."""

    name = "nis_gate"

    def flags(self, standardised, S, nis):
        m = len(standardised)
        thr = chi2.isf(self.false_alarm_prob, m)
        bad = np.full(m, nis > thr)
        return FaultDecision(np.full(m, nis), np.full(m, thr), bad, bad.copy())


def test_add_a_fault_test(monkeypatch):
    monkeypatch.setitem(fault_tests.FAULT_TESTS, "nis_gate", NisGate)
    test = make_fault_test("nis_gate", 1e-3)
    Phi, Q, subs, P0 = mini_ins()
    bank = LinearBank(P0, FederatedCore.bank_size(2))
    core = FederatedCore(bank, 2, get_strategy("fixed"), n_common=5)
    core.start()
    H, R = subs[0]
    healthy = core.update(0, np.array([1.0, 0.01]), H, R, test)
    assert healthy.rows_used == 2 and not healthy.decision.subsystem_isolated
    x_before = bank.x.copy()
    faulty = core.update(0, np.array([500.0, 0.01]), H, R, test)  # a 500 m position step
    assert faulty.rows_used == 0 and faulty.decision.subsystem_isolated
    np.testing.assert_array_equal(bank.x, x_before)  # isolated: the state is untouched


def test_gnss_fix_model_is_the_registered_hook():
    """The built-in models are reached through the registry with the same call as any other."""
    nav = static_stream(1, 1)[0]
    fix = GnssFix(
        t=nav.t,
        lat_deg=math.degrees(nav.lat_rad),
        lon_deg=math.degrees(nav.lon_rad),
        height_m=nav.h_m - 2.0,
        vel_enu_mps=(0.0, 0.0, 0.0),
        pos_std_enu_m=(1.0, 1.0, 1.0),
        vel_std_enu_mps=(0.1, 0.1, 0.1),
    )
    m = measurements.make("gnss_fix")(nav, fix, ModelContext(n_states=17))
    assert m.H.shape == (6, 17) and m.labels[2] == "pos_u"
    np.testing.assert_allclose(m.z[2], 2.0, atol=1e-9)  # INS minus sensor
