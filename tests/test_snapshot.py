"""Snapshot least-squares fixes from raw GNSS epochs, and a raw-only vehicle that aligns on them."""

import math

import numpy as np
import pytest

from fednav.service import earth, keys
from fednav.service.engine import VehicleEngine
from fednav.service.estimation import snapshot
from fednav.service.messages import GnssFix, GnssRaw, InitialNav
from fednav.simulators.evaluate import CollectingSink, service_config
from fednav.simulators.stream import Simulation

from .scenario_utils import shortened


@pytest.fixture(scope="module")
def raw_epochs():
    """(raw message, truth) pairs of the seed 001 aircraft (GPS+BDS, 10 Hz) for 30 s."""
    sc = shortened("seed001_ramp.toml", 30.0, faults=[])
    out, truth = [], {}
    for _key, msg in Simulation(sc, seed=3):
        if type(msg).__name__ == "Truth":
            truth[round(msg.t, 3)] = msg
        elif isinstance(msg, GnssRaw):
            out.append(msg)
    return [(m, truth[round(m.t, 3)]) for m in out if round(m.t, 3) in truth]


def _enu_error(fix: GnssFix, truth) -> np.ndarray:
    ref = np.radians([truth.lat_deg, truth.lon_deg])
    d = earth.llh_delta_to_enu_m(
        np.array([math.radians(fix.lat_deg) - ref[0], math.radians(fix.lon_deg) - ref[1], 0.0]),
        ref[0],
        truth.height_m,
    )
    d[2] = fix.height_m - truth.height_m
    return d


def test_snapshot_fix_is_near_the_truth_and_its_sigmas_cover_the_error(raw_epochs):
    errs, z = [], []
    for raw, truth in raw_epochs[:100]:
        fix = snapshot.snapshot_fix(raw)
        assert fix is not None
        e = _enu_error(fix, truth)
        errs.append(e)
        z.append(e / np.array(fix.pos_std_enu_m))
        v = np.array(fix.vel_enu_mps) - np.array(truth.vel_enu_mps)
        assert np.all(np.abs(v) < 5 * np.array(fix.vel_std_enu_mps)), v
    errs = np.array(errs)
    # six BeiDou satellites (GEO/IGSO geometry) and the simulator's atmosphere, which the snapshot
    # does not model: tens of metres at worst, enough to align on, and covered by the fix's sigmas
    print("horizontal RMS", np.sqrt(np.mean(np.sum(errs[:, :2] ** 2, axis=1))), "max |z|", np.max(np.abs(z)))
    assert np.sqrt(np.mean(np.sum(errs[:, :2] ** 2, axis=1))) < 30.0
    assert np.max(np.abs(np.array(z))) < 4.0


def test_snapshot_fix_refuses_too_few_satellites_and_a_gross_outlier(raw_epochs):
    raw = raw_epochs[0][0]
    one_system = max(
        {o.constellation for o in raw.sats}, key=lambda c: sum(o.constellation == c for o in raw.sats)
    )
    few = [o for o in raw.sats if o.constellation == one_system][: snapshot.MIN_SATS - 1]
    assert snapshot.snapshot_fix(GnssRaw(t=raw.t, sats=few)) is None
    sats = list(raw.sats)
    i = next(k for k, o in enumerate(sats) if o.constellation == one_system)
    sats[i] = sats[i].model_copy(update={"pseudorange_m": sats[i].pseudorange_m + 5000.0})
    assert snapshot.snapshot_fix(GnssRaw(t=raw.t, sats=sats)) is None


def test_raw_only_vehicle_aligns_in_motion_without_initial_nav_or_fix():
    """No InitialNav and no GnssFix: the tightly coupled pipeline starts from snapshot fixes of the
    raw epochs (the aircraft flies at 80 m/s: motion alignment) and converges."""
    sc = shortened("seed001_ramp.toml", 90.0, faults=[])
    cfg = service_config(sc)
    sink = CollectingSink(keep_solutions=True)
    eng = VehicleEngine("v1", cfg, sink)
    for key, msg in Simulation(sc, seed=5):
        if isinstance(msg, InitialNav | GnssFix):
            continue
        pk = keys.parse_input(key)
        eng.handle(pk.kind, pk.sensor_id, msg)
    assert eng.initialised
    name = cfg.pipelines[0].name
    err = np.array(sink.records[name].err)
    assert len(err) > 500
    late = err[-200:]
    assert np.sqrt(np.mean(late[:, 0] ** 2 + late[:, 1] ** 2)) < 5.0
    assert np.max(np.abs(late[:, 3:6])) < 0.3
