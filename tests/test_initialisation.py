"""Initialisation without an InitialNav: static coarse alignment and GNSS in motion."""

import logging
import math

import numpy as np

from fednav.service import keys
from fednav.service.engine import VehicleEngine
from fednav.service.messages import InitialNav
from fednav.simulators.evaluate import CollectingSink, service_config
from fednav.simulators.scenario import parse_scenario
from fednav.simulators.stream import Simulation

from .scenario_utils import SCENARIOS, shortened


def _run_without_init(sc, seed=1):
    cfg = service_config(sc)
    sink = CollectingSink(keep_solutions=True)
    eng = VehicleEngine("v1", cfg, sink)
    for key, msg in Simulation(sc, seed=seed):
        if isinstance(msg, InitialNav):
            continue
        pk = keys.parse_input(key)
        eng.handle(pk.kind, pk.sensor_id, msg)
    return eng, sink.records["lc"]


def test_in_motion_initialisation_from_gnss_converges():
    sc = shortened("demo_aircraft.toml", 150.0)
    eng, rec = _run_without_init(sc)
    err = np.array(rec.err)
    assert len(err) > 1400
    late = err[-300:]  # the last 30 s
    h = np.hypot(late[:, 0], late[:, 1])
    assert np.sqrt(np.mean(h**2)) < 5.0
    assert np.max(np.abs(late[:, 3:6])) < 0.3
    assert np.max(np.abs(late[:, 8])) < math.radians(0.5)  # heading converged within 0.5 deg


def test_static_coarse_alignment(caplog):
    import tomllib

    data = tomllib.loads((SCENARIOS / "demo_aircraft.toml").read_text())
    data.update(duration_s=90.0, segments=[{"kind": "static", "duration_s": 90.0}])
    data["start"]["speed_mps"] = 0.0
    data["start"]["heading_deg"] = 30.0
    data["service"]["init"] = {"mode": "auto", "align_time_s": 60.0}
    data["gnss"]["rate_hz"] = 10.0  # a 10 Hz receiver: its 100th fix refused at 10 s of the alignment
    sc = parse_scenario(data, "static")
    with caplog.at_level(logging.WARNING, logger="fednav.service"):
        eng, rec = _run_without_init(sc)
    err = np.array(rec.err)
    assert len(err) > 200  # aligned after ~60 s, solutions from then on
    # the fixes refused while it aligned as configured (600 at 10 Hz) are no cause for a warning
    assert eng.rejected["not_initialised"] >= 500
    assert not [r for r in caplog.records if "not_initialised" in r.getMessage()]
    first = err[0]
    # levelling to ~accel bias / g (50 ug -> 10 arcsec), gyrocompassing to ~bias / (w_ie cos L)
    assert abs(first[6]) < math.radians(0.02) and abs(first[7]) < math.radians(0.02)
    assert abs(first[8]) < math.radians(1.0)
    assert np.max(np.abs(err[:, 3:6])) < 0.5


def test_a_vehicle_that_cannot_initialise_is_reported_once_an_alignment_would_have_ended(caplog):
    """Aiding refused ``not_initialised`` is logged (with the likely cause) once its streak outlasts
    [init] align_time_s and a margin, not at the 100th refusal: here no InitialNav ever comes
    (mode "message"), so the fixes are refused for good and the warning comes once, after ~30 s."""
    import tomllib

    from fednav.service.engine import ALIGNMENT_WARNING_MARGIN_S

    data = tomllib.loads((SCENARIOS / "demo_aircraft.toml").read_text())
    data.update(duration_s=45.0, segments=[{"kind": "static", "duration_s": 45.0}])
    data["start"]["speed_mps"] = 0.0
    data["gnss"]["rate_hz"] = 10.0
    data["service"]["init"] = {"mode": "message", "align_time_s": 20.0}
    sc = parse_scenario(data, "never initialised")
    times = []

    class At(logging.Handler):
        def emit(self, record):
            if "not_initialised" in record.getMessage():
                times.append(eng_t[0])

    eng_t = [0.0]
    cfg = service_config(sc)
    eng = VehicleEngine("v1", cfg, CollectingSink())
    handler = At(level=logging.WARNING)
    logging.getLogger("fednav.service").addHandler(handler)
    try:
        for key, msg in Simulation(sc, seed=1):
            if isinstance(msg, InitialNav):
                continue
            pk = keys.parse_input(key)
            eng_t[0] = msg.t - sc.t0_gps_s
            eng.handle(pk.kind, pk.sensor_id, msg)
    finally:
        logging.getLogger("fednav.service").removeHandler(handler)
    assert not eng.initialised and eng.rejected["not_initialised"] > 300
    assert len(times) == 1  # once
    assert 20.0 + ALIGNMENT_WARNING_MARGIN_S - 1.0 <= times[0] <= 20.0 + ALIGNMENT_WARNING_MARGIN_S + 2.0
