"""Innovation consistency: are a stream's innovations as small as the filter claims?

A filter whose covariance is right sees innovations r (prior: z - H x) with E[r_j^2] = S_jj, the
diagonal of S = H P H' + R, whatever the correlations between rows. Over a window of the last
``window_s`` of one stream (a sensor key), the sum of the standardised squares

    q = sum_j r_j^2 / S_jj    over the rows the updates used (refused rows are the gates' business)

has the mean d (the rows counted) and, for uncorrelated rows, the chi-square distribution with d
degrees of freedom. A window *fails* when q / d exceeds ``min_ratio`` AND q exceeds the chi-square
upper quantile at ``p_fa`` (Wilson-Hilferty's approximation; rows correlated within an epoch widen
the spread, which ``min_ratio`` and the small ``p_fa`` absorb): the innovations are materially and
significantly larger than claimed, so the filter's sigmas understate its error (an overconfident
sensor claim, a process model too optimistic for the real clock or IMU, a forged stream). The
pipeline then reports ``degraded`` instead of ``aided`` (issue 22: "'aided' only while the aiding
is accepted and consistent"); smaller innovations than claimed (an underconfident model) are not
a failure. Measured on the clean runs of every family (docs/hardening.md, "Innovation
consistency"): no window fails.

Cheap on the hot path: running sums per stream, one quantile formula per update, no scipy.
"""

from __future__ import annotations

import math
from collections import deque
from statistics import NormalDist

#: the window of one stream's updates the test sums over, s
WINDOW_S = 10.0
#: rows a window needs before it is tested (a 1 Hz fix of 3 rows: 7 s; one scalar at 1 Hz: never)
MIN_DOF = 20
#: false-alarm probability of one window's test (it runs at every update of the stream)
P_FA = 1e-6
#: ... and the variance ratio the innovations must exceed too (claimed sigmas 22 % too small)
MIN_RATIO = 1.5


def chi2_upper(dof: float, z: float) -> float:
    """Upper quantile of chi-square(dof) at the standard normal quantile ``z`` (Wilson-Hilferty: at
    1e-6, 1.1 % above the exact one at 20 degrees of freedom, 0.3 % at 60, 0.01 % at 600)."""
    c = 2.0 / (9.0 * dof)
    return dof * (1.0 - c + z * math.sqrt(c)) ** 3


class _Window:
    __slots__ = ("rows", "q", "dof", "failing")

    def __init__(self) -> None:
        self.rows: deque = deque()
        self.q = 0.0
        self.dof = 0
        self.failing = False


class InnovationConsistency:
    """Per stream (sensor key), the innovation test of the module docstring over a sliding window."""

    def __init__(
        self,
        window_s: float = WINDOW_S,
        p_fa: float = P_FA,
        min_dof: int = MIN_DOF,
        min_ratio: float = MIN_RATIO,
    ):
        self.window_s = window_s
        self.min_dof = min_dof
        self.min_ratio = min_ratio
        self._z = NormalDist().inv_cdf(1.0 - p_fa)
        self._streams: dict[str, _Window] = {}
        #: per stream, the verdict of its last tested window (True: consistent), kept over
        #: :meth:`clear`: whether a sensor's rows are as good as they claim is the sensor's
        #: record, which a restart of the filter does not change
        self._record: dict[str, bool] = {}

    def clear(self) -> None:
        """Forget every window (a filter restarted: its new innovations start a new history); each
        stream's record (its last tested verdict) stays."""
        for key, w in self._streams.items():
            if w.dof >= self.min_dof:
                self._record[key] = not w.failing
        self._streams.clear()

    def add(self, key: str, t: float, q: float, dof: int) -> bool | None:
        """One update of stream ``key`` at ``t``: ``q`` the sum of r_j^2 / S_jj over its ``dof``
        used rows. Returns True when the stream's window now fails, False when it passes, None
        while it has fewer than ``min_dof`` rows (not tested)."""
        w = self._streams.get(key)
        if w is None:
            w = self._streams[key] = _Window()
        rows = w.rows
        if rows and t < rows[-1][0]:  # time went back (a restart of the stream): a new window
            rows.clear()
            w.q, w.dof = 0.0, 0
        if dof > 0 and math.isfinite(q):
            rows.append((t, q, dof))
            w.q += q
            w.dof += dof
        while rows and rows[0][0] <= t - self.window_s:
            _, q0, d0 = rows.popleft()
            w.q -= q0
            w.dof -= d0
        if w.dof < self.min_dof:
            w.failing = False
            return None
        w.failing = w.q > self.min_ratio * w.dof and w.q > chi2_upper(w.dof, self._z)
        return w.failing

    def ratio(self, key: str) -> float | None:
        """The window's q / d of a stream (None before it has rows): 1.0 when consistent."""
        w = self._streams.get(key)
        return w.q / w.dof if w is not None and w.dof > 0 else None

    def is_failing(self, key: str) -> bool:
        """Whether the latest test of stream ``key`` failed."""
        w = self._streams.get(key)
        return w is not None and w.failing

    def is_consistent(self, key: str) -> bool:
        """Whether stream ``key``'s window has been tested (enough rows) and passed; while the
        window is too short to be tested (after a restart of the filter), whether its last tested
        window before the restart passed (False for a stream never tested)."""
        w = self._streams.get(key)
        if w is not None and w.dof >= self.min_dof:
            return not w.failing
        return self._record.get(key, False)

    def failing(self) -> list[str]:
        """The streams whose latest test failed."""
        return sorted(k for k, w in self._streams.items() if w.failing)


__all__ = ["InnovationConsistency", "chi2_upper"]
