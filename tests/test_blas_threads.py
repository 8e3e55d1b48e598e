"""One BLAS thread per process (service/blas.py), and the one-member update without LAPACK's
threaded dtrtrs."""

from __future__ import annotations

import json
import os
import subprocess
import sys

import numpy as np

from fednav.service.estimation import kalman

PROBE = """
import json
from fednav.service.blas import one_blas_thread
applied = one_blas_thread()
from threadpoolctl import threadpool_info
print(json.dumps({"applied": applied,
                  "threads": [d["num_threads"] for d in threadpool_info() if d["user_api"] == "blas"]}))
"""


def _probe(**env_over: str) -> dict:
    env = {
        k: v
        for k, v in os.environ.items()
        if k not in ("OPENBLAS_NUM_THREADS", "OMP_NUM_THREADS", "MKL_NUM_THREADS")
    }
    env.update(env_over)
    out = subprocess.run(
        [sys.executable, "-c", PROBE], env=env, capture_output=True, text=True, timeout=60, check=True
    )
    return json.loads(out.stdout)


def test_every_blas_library_runs_one_thread():
    got = _probe()
    assert got["applied"] is True
    # numpy's and scipy's OpenBLAS are both loaded and both limited
    assert len(got["threads"]) >= 1
    assert got["threads"] == [1] * len(got["threads"])


def test_a_users_thread_count_is_left_alone():
    got = _probe(OPENBLAS_NUM_THREADS="2")
    assert got["applied"] is False


def test_one_member_update_matches_the_bank_path():
    """The one-member path (dpotrf + dtrsm) against the general bank path on the same inputs."""
    rng = np.random.default_rng(3)
    n, m = 15, 6
    A = rng.standard_normal((n, n))
    P = (A @ A.T + n * np.eye(n))[None]
    x = rng.standard_normal((1, n))
    H = rng.standard_normal((m, n))
    R = np.abs(rng.standard_normal(m)) + 0.5
    z = rng.standard_normal(m)
    x1, P1, res1 = kalman.update(x, P, z, H, R)
    x2, P2, res2 = kalman.update(np.repeat(x, 2, 0), np.repeat(P, 2, 0), z, H, R)
    np.testing.assert_allclose(x1[0], x2[0], rtol=1e-10, atol=1e-12)
    np.testing.assert_allclose(P1[0], P2[0], rtol=1e-9, atol=1e-12)
    np.testing.assert_allclose(res1.whitened[0], res2.whitened[0], rtol=1e-9, atol=1e-12)
