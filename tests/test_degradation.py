"""Missing sensors degrade, they do not stop; numerical faults are flagged and recovered."""

import numpy as np

from fednav.service import keys
from fednav.service.engine import VehicleEngine
from fednav.service.estimation import kalman
from fednav.simulators.evaluate import CollectingSink, service_config
from fednav.simulators.stream import Simulation

from .scenario_utils import shortened


def _run(sc, seed=2):
    cfg = service_config(sc)
    sink = CollectingSink(keep_solutions=True)
    eng = VehicleEngine("v1", cfg, sink)
    for key, msg in Simulation(sc, seed=seed):
        pk = keys.parse_input(key)
        eng.handle(pk.kind, pk.sensor_id, msg)
    return eng, sink.records["lc"].solutions


def test_gnss_outage_gives_coasting_with_growing_covariance():
    base = shortened("demo_aircraft.toml", 150.0)
    gnss = dict(base.gnss.model_dump())
    gnss["outages"] = [[60.0, 100.0]]
    sc = base.model_copy(update={"gnss": type(base.gnss).model_validate(gnss)})
    eng, sols = _run(sc)
    t0 = sc.t0_gps_s
    during = [s for s in sols if 70.0 <= s.t - t0 <= 99.0]
    after = [s for s in sols if 110.0 <= s.t - t0]
    assert during and all(s.status == "coasting" for s in during)
    assert all(s.status == "aided" for s in after)
    std = np.array([np.hypot(*s.pos_std_enu_m[:2]) for s in during])
    assert np.all(np.diff(std) >= -1e-9) and std[-1] > std[0]
    assert np.hypot(*after[-1].pos_std_enu_m[:2]) < std[-1]


def test_lost_positive_definiteness_is_recovered(monkeypatch):
    sc = shortened("demo_aircraft.toml", 40.0)
    calls = {"n": 0}
    real = kalman.is_positive_definite

    def flaky(P):
        calls["n"] += 1
        ok = real(P)
        return ok & False if calls["n"] == 10 else ok  # the 10th check reports a broken P

    monkeypatch.setattr(kalman, "is_positive_definite", flaky)
    eng, sols = _run(sc)
    p = eng.pipelines[0]
    assert p.reinitialisations == 1
    first_aided = next(i for i, s in enumerate(sols) if s.status == "aided")
    assert any(s.status == "unaided" for s in sols[first_aided:])  # restarted: unaided until aided
    assert sols[-1].status == "aided"  # and the filter went on


def test_a_star_tracker_alone_does_not_keep_a_gnss_outage_aided():
    """During a GNSS outage the star tracker still aids the attitude, but the position is
    free-inertial: the loosely coupled and federated solutions say ``coasting``, not ``aided``
    (before: ``aided`` for the whole outage, its star updates counted as aiding)."""
    base = shortened("demo_product.toml", 120.0)
    gnss = dict(base.gnss.model_dump())
    gnss["outages"] = [[65.0, 95.0]]
    sc = base.model_copy(update={"gnss": type(base.gnss).model_validate(gnss)})
    cfg = service_config(sc)
    sink = CollectingSink(keep_solutions=True)
    eng = VehicleEngine("v1", cfg, sink)
    for key, msg in Simulation(sc, seed=2):
        pk = keys.parse_input(key)
        eng.handle(pk.kind, pk.sensor_id, msg)
    t0 = sc.t0_gps_s
    for name in ("lc", "fed"):
        sols = sink.records[name].solutions
        during = [s.status for s in sols if 70.0 <= s.t - t0 <= 94.0]
        after = [s.status for s in sols if 100.0 <= s.t - t0]
        assert during and set(during) == {"coasting"}, (name, sorted(set(during)))
        assert "aided" in after, (name, sorted(set(after)))
    assert eng.pipelines[0].updates > 0  # the star updates still counted as updates
