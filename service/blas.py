"""One BLAS thread per process.

Every matrix of the filters is small (at most a few dozen rows), and OpenBLAS hands some routines
to its thread pool whatever their size: LAPACK's ``dtrtrs`` on a 6 x 16 system ran on two threads,
and the pool's second thread then spins for a while after each call, waiting for the next. On a
2-core machine that doubled a fleet service's CPU (40 vehicles: 1.66 cores against 0.76) and took
the core the load and the other processes need. Parallelism in fednav comes from processes
(``fednav-service --shards K``), never from BLAS, so each entry point (the service and its shards,
the simulators and the evaluator, fednav-replay, fednav-record) runs BLAS on one thread.

A user who sets ``OPENBLAS_NUM_THREADS``, ``OMP_NUM_THREADS`` or ``MKL_NUM_THREADS`` keeps their
choice: it is left alone.
"""

from __future__ import annotations

import os

_USER_VARS = ("OPENBLAS_NUM_THREADS", "OMP_NUM_THREADS", "MKL_NUM_THREADS")


def one_blas_thread() -> bool:
    """Limit every loaded BLAS library (numpy's and scipy's OpenBLAS) to one thread, unless the
    user chose a thread count in the environment. Returns whether the limit was applied."""
    if any(os.environ.get(v) for v in _USER_VARS):
        return False
    import numpy  # noqa: F401  (load the BLAS libraries so that the limit reaches them)
    import scipy.linalg  # noqa: F401
    from threadpoolctl import threadpool_limits

    threadpool_limits(limits=1, user_api="blas")
    return True
