"""The innovation consistency test (service/estimation/consistency.py) and the status it drives:
a pipeline whose innovations are materially and significantly larger than it claims reports
``degraded``, counted in its screened counts; honest innovations never trip it."""

import logging
import math

import numpy as np
import pytest
from scipy.stats import chi2

from fednav.service import earth, keys
from fednav.service.config import ImuModel, LooselyCoupledConfig
from fednav.service.engine import VehicleEngine
from fednav.service.estimation.consistency import InnovationBias, InnovationConsistency, chi2_upper
from fednav.service.ins.alignment import InitStd
from fednav.service.ins.mechanisation import NavState
from fednav.service.messages import GnssFix
from fednav.service.pipelines.loosely_coupled import LooselyCoupled
from fednav.simulators.evaluate import CollectingSink, service_config
from fednav.simulators.stream import Simulation

from .scenario_utils import shortened

T0 = 1000.0
KEY = "gnss_fix/main"


@pytest.mark.parametrize("dof", [20, 60, 600, 2400])
def test_the_quantile_formula_is_the_chi_square_one_and_never_below_it(dof):
    z = 4.753424308822899  # the standard normal quantile at 1 - 1e-6
    exact = chi2.isf(1e-6, dof)
    assert exact <= chi2_upper(dof, z) <= 1.012 * exact


def _feed(c: InnovationConsistency, rng, sigma: float, seconds: float, rows: int = 6, rate_hz: float = 1.0):
    """Standardised innovations of ``rows`` rows per update whose real spread is ``sigma`` times the
    claimed one; the verdicts of every update."""
    out = []
    for k in range(int(seconds * rate_hz)):
        r = sigma * rng.standard_normal(rows)
        out.append(c.add("gnss_fix/main", T0 + k / rate_hz, float(r @ r), rows))
    return out


def test_honest_innovations_never_fail_over_a_long_run():
    c = InnovationConsistency()
    verdicts = _feed(c, np.random.default_rng(1), 1.0, 20_000.0, rows=6, rate_hz=1.0)
    assert verdicts[:3] == [None, None, None]  # 6, 12, 18 rows: fewer than MIN_DOF, not tested
    assert verdicts[3] is False
    assert not any(v for v in verdicts)
    # also at 10 Hz with many rows (the tightly coupled case: a large window, a tight quantile)
    c = InnovationConsistency()
    assert not any(_feed(c, np.random.default_rng(2), 1.0, 2_000.0, rows=24, rate_hz=10.0))


def test_innovations_twice_the_claimed_spread_fail_and_recover_after_the_window():
    c = InnovationConsistency()
    rng = np.random.default_rng(3)
    assert not any(_feed(c, rng, 1.0, 60.0))
    bad = [
        c.add("gnss_fix/main", T0 + 60.0 + k, float(np.sum((2.0 * rng.standard_normal(6)) ** 2)), 6)
        for k in range(10)
    ]
    assert bad[-1] is True and c.is_failing("gnss_fix/main") and c.failing() == ["gnss_fix/main"]
    assert 3.0 < c.ratio("gnss_fix/main") < 5.5
    # honest again: once the bad updates have left the 10 s window, the stream passes
    after = [
        c.add("gnss_fix/main", T0 + 70.0 + k, float(np.sum(rng.standard_normal(6) ** 2)), 6)
        for k in range(12)
    ]
    assert after[-1] is False and not c.is_failing("gnss_fix/main")


def test_a_streams_record_outlives_a_restart_of_the_filter():
    """After ``clear`` (the filter restarted), a stream whose new window is too short to be tested
    is as consistent as its last tested window was; a stream never tested is not; a window tested
    after the restart decides again."""
    c = InnovationConsistency()
    rng = np.random.default_rng(6)
    assert c.is_consistent("gnss_fix/main") is False  # never tested
    _feed(c, rng, 1.0, 30.0)
    for k in range(10):  # a second stream, overconfident: failing when the filter restarts
        c.add("gnss_fix/aux", T0 + 20.0 + k, float(np.sum((3.0 * rng.standard_normal(6)) ** 2)), 6)
    assert c.is_consistent("gnss_fix/main") and c.is_failing("gnss_fix/aux")
    c.clear()
    assert c.add("gnss_fix/main", T0 + 31.0, 60.0, 6) is None  # 6 rows, untested: its record
    assert c.is_consistent("gnss_fix/main") and not c.is_failing("gnss_fix/main")
    assert c.is_consistent("gnss_fix/aux") is False and c.is_consistent("star/main") is False
    for k in range(4):  # tested again: the new window decides (60 / 6 = 10x the claimed variance)
        c.add("gnss_fix/main", T0 + 32.0 + k, 60.0, 6)
    assert c.is_failing("gnss_fix/main") and not c.is_consistent("gnss_fix/main")


def test_a_small_excess_is_not_a_failure_however_many_rows():
    """Significant but not material (sigmas 10 % too small, 24 rows at 10 Hz): not a failure."""
    c = InnovationConsistency()
    assert not any(_feed(c, np.random.default_rng(4), 1.1, 300.0, rows=24, rate_hz=10.0))


def test_one_large_innovation_does_not_fail_a_window_and_time_going_back_starts_a_new_one():
    c = InnovationConsistency()
    rng = np.random.default_rng(5)
    _feed(c, rng, 1.0, 30.0)
    assert c.add("gnss_fix/main", T0 + 30.0, 24.0 + float(np.sum(rng.standard_normal(5) ** 2)), 6) is False
    assert c.add("gnss_fix/main", T0 - 100.0, 1e6, 6) is None  # a restarted stream: 6 rows, untested
    assert c.ratio("gnss_fix/main") == pytest.approx(1e6 / 6)
    c.clear()
    assert c.ratio("gnss_fix/main") is None and c.failing() == []


def _feed_bias(
    b: InnovationBias,
    rng,
    seconds: float,
    t0: float = T0,
    rows: int = 6,
    rate_hz: float = 1.0,
    bias=None,
    used=None,
):
    """Standardised innovations (``bias``: added per row) into the bias test; its verdicts."""
    labels = tuple(f"r{j}" for j in range(rows))
    offset = np.zeros(rows) if bias is None else np.asarray(bias, float)
    use = np.ones(rows, bool) if used is None else np.asarray(used, bool)
    return [
        b.add(KEY, t0 + k / rate_hz, labels, rng.standard_normal(rows) + offset, use)
        for k in range(int(seconds * rate_hz))
    ]


@pytest.mark.parametrize(("rows", "rate_hz", "seconds"), [(6, 1.0, 5_000.0), (24, 10.0, 500.0)])
def test_centred_innovations_are_almost_never_called_biased(rows, rate_hz, seconds):
    """White, centred innovations: the bias test's two means (the window's, its latest span's) at
    1e-6 each fail at most a handful of updates in thousands (a threshold at 2 sigma would fail
    ~5 % of them)."""
    verdicts = _feed_bias(InnovationBias(), np.random.default_rng(7), seconds, rows=rows, rate_hz=rate_hz)
    assert sum(verdicts) <= 1e-3 * len(verdicts), sum(verdicts)


def test_a_row_off_centre_is_found_within_its_recent_span_and_named():
    """One row 2 sigma off centre from t = 60 s (1 Hz): failing within the latest span's 10 s,
    only that row named, its recent mean near 2 while the whole window's is diluted; centred
    again, it passes once the biased updates have left the 30 s window."""
    b = InnovationBias()
    rng = np.random.default_rng(8)
    assert not any(_feed_bias(b, rng, 60.0))
    off = _feed_bias(b, rng, 15.0, t0=T0 + 60.0, bias=[2.0, 0, 0, 0, 0, 0])
    first = off.index(True)
    assert 5 <= first <= 10, off
    assert b.failing() == {KEY: ["r0"]}
    assert b.recent_mean(KEY, "r0") == pytest.approx(2.0, abs=0.8)
    assert abs(b.mean(KEY, "r0")) < abs(b.recent_mean(KEY, "r0"))
    after = _feed_bias(b, rng, 40.0, t0=T0 + 75.0)
    assert after[-1] is False and b.failing() == {}
    b.clear()
    assert b.mean(KEY, "r0") is None and b.failing() == {}


def test_a_small_bias_or_rows_not_used_are_not_a_failure():
    """A bias of 0.3 sigma at 10 Hz is significant but not material (below half the claimed
    spread): no failure. Rows the update did not use (refused by the gate) are not averaged."""
    assert not any(
        _feed_bias(InnovationBias(), np.random.default_rng(9), 300.0, rate_hz=10.0, bias=[0.3] * 6)
    )
    used = [False, True, True, True, True, True]
    assert not any(
        _feed_bias(InnovationBias(), np.random.default_rng(10), 60.0, bias=[5.0, 0, 0, 0, 0, 0], used=used)
    )


def test_rows_are_followed_by_label_whatever_their_order_and_non_finite_ones_are_skipped():
    b = InnovationBias()
    b.add(KEY, T0, ("a", "b"), np.array([1.0, 2.0]), np.ones(2, bool))
    b.add(KEY, T0 + 0.5, ("b", "a", "c"), np.array([4.0, 3.0, np.nan]), np.ones(3, bool))
    b.add(KEY, T0 + 1.2, ("a",), np.array([5.0]), np.zeros(1, bool))  # not used: not averaged
    assert b.mean(KEY, "a") == 2.0 and b.mean(KEY, "b") == 3.0 and b.mean(KEY, "c") is None
    assert b.recent_mean(KEY, "a") == 2.0 and b.mean("star/main", "a") is None


def test_an_inflation_skips_a_failing_row_the_update_does_not_carry():
    """The rows of a stream that fail its bias test may be missing from the update at hand (held
    on return, not sent): the inflation grows what the update carries and never fails on the rest."""
    p = LooselyCoupled(LooselyCoupledConfig(name="lc"), ImuModel(), 0.1)
    rng = np.random.default_rng(11)
    labels = ("pos_e", "pos_n")
    for k in range(40):
        p.bias.add(KEY, T0 + k, labels, rng.standard_normal(2) + np.array([0.0, 3.0]), np.ones(2, bool))
    assert p.bias.failing() == {KEY: ["pos_n"]}

    class Meas:  # an update carrying pos_e alone
        labels = ("pos_e",)
        H = np.eye(1, 15)

    P = np.eye(15)[None]
    assert p.inflate_for_bias(KEY, Meas, np.array([4.0]), P) is None

    class Both:
        labels = ("pos_e", "pos_n")
        H = np.eye(2, 15)

    grown = p.inflate_for_bias(KEY, Both, np.array([4.0, 4.0]), P)
    m = p.bias.recent_mean(KEY, "pos_n")
    assert grown[0, 1, 1] == pytest.approx(1.0 + m * m * 4.0) and grown[0, 0, 0] == 1.0
    assert p.screened["bias_inflation"] == 1


def _lc(claimed_std_m: float, real_std_m: float, seconds: float = 90.0):
    """A static, level loosely coupled filter (no innovation gate) fed 1 Hz fixes at the truth plus
    N(0, real) noise claiming ``claimed``; its status and counts after ``seconds``."""
    # no innovation gate: the consistency test alone can make it degraded
    p = LooselyCoupled(LooselyCoupledConfig(name="lc", innovation_gate_sigma=None), ImuModel(), 0.1)
    lat, lon = math.radians(40.0), math.radians(10.0)
    nav = NavState(T0, lat, lon, 100.0, np.zeros(3), earth.mat_to_quat(np.eye(3)))
    p.start(nav, InitStd(np.full(3, 2.0), np.full(3, 0.1), np.radians([0.1, 0.1, 0.5])))
    g = earth.gravity_normal(lat, 100.0)
    w = earth.OMEGA_IE_RPS * 0.01  # the earth's rotation, sensed by the gyros of a vehicle at rest (ENU body)
    dth = (0.0, w * math.cos(lat), w * math.sin(lat))
    rng = np.random.default_rng(6)
    r_m, r_n = earth.radii(lat)
    t = T0
    for k in range(int(seconds * 100)):
        t = T0 + (k + 1) * 0.01
        p.push_imu(dth, (0.0, 0.0, g * 0.01), 0.01, t)
        if (k + 1) % 100 == 0:
            p.sync()
            e, n, u = real_std_m * rng.standard_normal(3)
            fix = GnssFix(
                t=t,
                lat_deg=math.degrees(lat + n / (r_m + 100.0)),
                lon_deg=math.degrees(lon + e / ((r_n + 100.0) * math.cos(lat))),
                height_m=100.0 + u,
                vel_enu_mps=tuple(0.05 * real_std_m * rng.standard_normal(3)),
                pos_std_enu_m=(claimed_std_m,) * 3,
                vel_std_enu_mps=(0.05 * claimed_std_m,) * 3,
            )
            p.apply("gnss_fix", "main", fix)
    return p.current_status(t), p.screened


def test_an_honest_receiver_keeps_the_filter_aided():
    status, screened = _lc(1.0, 1.0)
    assert status == "aided" and screened["innovations_inconsistent"] == 0


def test_a_receiver_claiming_a_third_of_its_noise_makes_the_filter_degraded():
    status, screened = _lc(1.0, 3.0)
    assert status == "degraded" and screened["innovations_inconsistent"] >= 1


def _demo_run(claim_scale: float, caplog):
    """The demo aircraft for 60 s through the engine, its fixes claiming ``claim_scale`` times
    their simulated sigmas; the loosely coupled pipeline's statuses (t from the start) and the
    warnings about inconsistent innovations."""
    sc = shortened("demo_aircraft.toml", 60.0)
    eng = VehicleEngine("v1", service_config(sc), CollectingSink(keep_solutions=True))
    with caplog.at_level(logging.WARNING, logger="fednav.service"):
        for key, msg in Simulation(sc, seed=5):
            pk = keys.parse_input(key)
            if pk.kind == "gnss_fix":
                msg = msg.model_copy(
                    update={
                        "pos_std_enu_m": tuple(claim_scale * s for s in msg.pos_std_enu_m),
                        "vel_std_enu_mps": tuple(claim_scale * s for s in msg.vel_std_enu_mps),
                    }
                )
            eng.handle(pk.kind, pk.sensor_id, msg)
    p = eng.pipelines[0]
    warnings = [r.getMessage() for r in caplog.records if "innovations larger than" in r.getMessage()]
    return p, eng.pipeline_states()["lc"], warnings


def test_the_engine_names_the_inconsistent_stream_once_and_health_counts_it(caplog):
    p, state, warnings = _demo_run(1.0 / 3.0, caplog)
    assert state["screened"].get("innovations_inconsistent", 0) >= 1
    assert len(warnings) == 1 and "pipeline lc" in warnings[0] and "gnss_fix/main" in warnings[0]
    caplog.clear()
    p, state, warnings = _demo_run(1.0, caplog)
    assert "innovations_inconsistent" not in state["screened"] and warnings == []
    assert state["status"] == "aided"


def test_the_clock_default_is_a_tcxo_and_seed003_keeps_its_own():
    """The default drift PSD is a TCXO's (the simulators' receiver clock); the seed 003 scenarios
    name the value their documented figures were measured with, on every tightly coupled filter."""
    from fednav.service.config import SEED003_DRIFT_PSD_M2PS3, ClockModel, from_dict
    from fednav.simulators.gnss.raw_sensor import TCXO_DRIFT_PSD_M2PS3
    from fednav.simulators.scenario import load_scenario

    assert ClockModel().drift_psd_m2ps3 == pytest.approx(TCXO_DRIFT_PSD_M2PS3, rel=1e-3)
    for name in ("seed003_clean", "seed003_outliers", "seed003_outliers_obs"):
        cfg = from_dict(load_scenario(name).service, name)
        clocks = [p.clock.drift_psd_m2ps3 for p in cfg.pipelines if hasattr(p, "clock")]
        assert len(clocks) == 5 and all(c == SEED003_DRIFT_PSD_M2PS3 for c in clocks)
