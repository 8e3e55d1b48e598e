"""``benchmarks/stacked_filters.py`` compares like with like: its stacked discretisation and bank
update give each member what the engine's per-vehicle calls give, and its vehicle run times the
engine's own calls (one of each per 10 Hz epoch)."""

import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "benchmarks"))

import stacked_filters  # noqa: E402

from fednav.service.estimation import kalman  # noqa: E402
from fednav.service.ins import error_model as em  # noqa: E402


def test_the_stacked_numerics_equal_the_per_vehicle_calls():
    rng = np.random.default_rng(5)
    K, n, m = 4, em.N_STATES, 6
    F = rng.normal(size=(K, n, n)) * 0.05
    Qc = np.stack([np.diag(rng.uniform(1e-6, 1e-3, n)) for _ in range(K)])
    A = rng.normal(size=(K, n, n))
    P = A @ A.swapaxes(1, 2) + n * np.eye(n)
    x = rng.normal(size=(K, n))
    H = rng.normal(size=(K, m, n))
    R = np.stack([np.diag(rng.uniform(0.5, 2.0, m)) for _ in range(K)])
    z = rng.normal(size=(K, m))
    Phi_s, Qd_s = stacked_filters._stacked_discretise(F, Qc, 0.1)
    xs, Ps = kalman.predict(x, P, Phi_s, Qd_s)
    xs, Ps, _ = kalman.update(xs, Ps, z, H, R)
    for b in range(K):
        Phi, Qd = em.discretise(F[b], Qc[b], 0.1)
        np.testing.assert_allclose(Phi_s[b], Phi, rtol=1e-12, atol=1e-15)
        np.testing.assert_allclose(Qd_s[b], Qd, rtol=1e-12, atol=1e-18)
        xb, Pb = kalman.predict(x[b : b + 1], P[b : b + 1], Phi, Qd)
        xb, Pb, _ = kalman.update(xb, Pb, z[b], H[b], R[b])
        np.testing.assert_allclose(xs[b], xb[0], rtol=1e-9, atol=1e-12)
        np.testing.assert_allclose(Ps[b], Pb[0], rtol=1e-9, atol=1e-12)


def test_the_vehicle_run_times_the_engines_own_calls():
    share = stacked_filters.vehicle_share(3.0)
    calls = share["calls_per_vehicle_s"]
    # one propagation and one fix update per 10 Hz epoch (the first second aligns: fewer updates)
    assert 9.0 <= calls["discretise"] <= 11.0, calls
    assert 6.0 <= calls["update"] <= 11.0, calls
    assert 0.0 < share["numerics_share"] < 1.0, share["numerics_share"]
    for name in ("discretise", "predict", "update", "is_positive_definite"):
        assert share["numerics_ms_per_vehicle_s"][name] > 0.0, name
    # the shapes the epoch benchmark replays are the engine's (15 states, 6 fix rows)
    F, Qc, T = share["shapes"]["discretise"][:3]
    assert F.shape == (em.N_STATES, em.N_STATES) and 0.0 < T <= 0.2
    costs = stacked_filters.epoch_costs(share["shapes"], [1, 3], reps_total=30)
    assert [c["K"] for c in costs] == [1, 3] and all(c["stacked_us"] > 0 for c in costs)
