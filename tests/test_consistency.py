"""Statistical consistency of the loosely coupled filter over seeded Monte Carlo runs.

Per epoch, the NEES of the 9 navigation errors (position, velocity, misalignment) averaged over
N runs is chi2(9N)/N distributed for a consistent filter; likewise the NIS of the 6-row GNSS
update (chi2(6N)/N). We check that the run-averaged statistics stay inside the two-sided 99 %
bounds at (nearly) all epochs and that their time averages are near the dof. The Monte Carlo
uses a 100 s cut of the demo scenario (N = 6 seeds) to stay fast.
"""

import numpy as np
from scipy.stats import chi2

from fednav.service import keys
from fednav.service.engine import VehicleEngine
from fednav.simulators.evaluate import CollectingSink, service_config
from fednav.simulators.stream import Simulation

from .scenario_utils import shortened

N_RUNS = 6


def _run(sc, seed, traj):
    cfg = service_config(sc)
    sink = CollectingSink()
    eng = VehicleEngine("v1", cfg, sink)
    for key, msg in Simulation(sc, seed=seed, trajectory=traj):
        pk = keys.parse_input(key)
        eng.handle(pk.kind, pk.sensor_id, msg)
    nis = [(t, v) for t, kind, v, dof in eng.pipelines[0].nis_history if kind == "gnss_fix"]
    return np.array(sink.records["lc"].nees), np.array([v for _, v in nis])


def test_nees_and_nis_within_chi2_bounds():
    sc = shortened("demo_aircraft.toml", 100.0)
    traj = sc.build_trajectory()
    runs = [_run(sc, 100 + i, traj) for i in range(N_RUNS)]
    nees = np.mean([r[0] for r in runs], axis=0)
    nis = np.mean([r[1] for r in runs], axis=0)
    lo9, hi9 = chi2.ppf([0.005, 0.995], 9 * N_RUNS) / N_RUNS
    lo6, hi6 = chi2.ppf([0.005, 0.995], 6 * N_RUNS) / N_RUNS
    inside_nees = np.mean((nees > lo9) & (nees < hi9))
    inside_nis = np.mean((nis > lo6) & (nis < hi6))
    assert inside_nis > 0.95, f"NIS inside bounds at {inside_nis:.1%} of epochs (mean {nis.mean():.2f}/6)"
    assert inside_nees > 0.9, f"NEES inside bounds at {inside_nees:.1%} of epochs (mean {nees.mean():.2f}/9)"
    assert 6.5 < nees.mean() < 11.5, nees.mean()
    assert 4.8 < nis.mean() < 7.2, nis.mean()
