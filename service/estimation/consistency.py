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

import numpy as np

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

    def records(self) -> dict[str, bool]:
        """Each stream's verdict now (its tested window's, else its record): what a service taking
        the vehicle over adopts (HandoverState.stream_records)."""
        out = dict(self._record)
        for key, w in self._streams.items():
            if w.dof >= self.min_dof:
                out[key] = not w.failing
        return out

    def adopt(self, records: dict[str, bool]) -> None:
        """Another service's verdicts (a hand-over) for the streams this one has no record of: a
        fault episode that begins before this service has tested a stream then takes the rule of
        a stream known to be as good as it claims (Pipeline.source_groups), as the old owner did."""
        for key, ok in records.items():
            if key not in self._record and key not in self._streams:
                self._record[key] = bool(ok)

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


#: the window of one stream's updates the bias test averages over, s (longer than the variance
#: test's: a bias is a slow thing, and a fix at 1 Hz gives 30 rows)
BIAS_WINDOW_S = 30.0
#: updates of a row a window needs before it is tested
BIAS_MIN_N = 10
#: ... its mean standardised innovation must be at least this (half the claimed spread) ...
BIAS_MIN_MEAN = 0.5
#: ... by this many of its own standard deviations (1 / sqrt(n)): material beyond its noise
BIAS_MARGIN_SD = 3.0
#: ... and significant at this two-sided false-alarm probability for white innovations
BIAS_P_FA = 1e-6
#: the window's latest span tested on its own too, s (a bias that began within the window is
#: diluted in the whole window's mean by the centred innovations before it)
BIAS_RECENT_S = 10.0


#: the bins the bias test sums in, s (its windows hold whole bins; tested when a bin closes)
BIAS_BIN_S = 1.0


class _StreamBias:
    """One stream's bias windows: per row, sums and counts of its standardised innovations in
    ``BIAS_BIN_S`` bins (the current one open), the closed bins of the window, their totals
    (lists of Python floats: a handful of rows, added one by one faster than numpy's calls)."""

    __slots__ = (
        "labels",
        "index",
        "bin",
        "cur_sum",
        "cur_n",
        "bins",
        "tot_sum",
        "tot_n",
        "last_t",
        "failing",
    )

    def __init__(self, labels: tuple) -> None:
        self.labels = labels
        self.index = {label: i for i, label in enumerate(labels)}
        self.bin: int | None = None
        m = len(labels)
        self.cur_sum, self.cur_n = [0.0] * m, [0] * m
        self.bins: deque = deque()  # (bin number, sums, counts), oldest first
        self.tot_sum, self.tot_n = [0.0] * m, [0] * m
        self.last_t: float | None = None
        self.failing: list[str] = []

    def rows_of(self, labels) -> list[int]:
        """The row indices of ``labels``, new labels appended to every list."""
        index = self.index
        for label in labels:
            if label not in index:
                index[label] = len(self.labels)
                self.labels = (*self.labels, label)
                for lst in (self.cur_sum, self.tot_sum):
                    lst.append(0.0)
                for lst in (self.cur_n, self.tot_n):
                    lst.append(0)
                for _, su, n in self.bins:
                    su.append(0.0)
                    n.append(0)
        return [index[label] for label in labels]


class InnovationBias:
    """Per stream and row, are the innovations centred? The test the variance ratio cannot make.

    A filter whose state is right sees innovations of mean zero; for an optimal filter they are
    white, so the mean m of the n standardised innovations r_j / sqrt(S_jj) of one row over the
    last ``window_s`` has the standard deviation 1 / sqrt(n). A row *fails* when its window holds
    at least ``min_n`` updates and |m| is both material (beyond ``min_mean``, a bias of half
    the claimed spread, by ``BIAS_MARGIN_SD`` of its own standard deviations: a bias of a third
    of the spread at 10 Hz is not called material by its noise) and significant (|m| sqrt(n)
    beyond the normal quantile at ``p_fa``, two-sided), or when the window's latest ``recent_s``
    passes the same test on its own (a bias that began within the window is diluted by the
    centred innovations before it). Why it is needed: a state corrupted by a few times the
    aiding's claimed sigma (a position 20 m off against fixes claiming 5-10 m) is pulled back
    slowly by small gains; the stream's innovations are then larger than claimed only at first,
    and the variance test (:class:`InnovationConsistency`) passes again while the state is still
    several of its own sigmas off: 'aided' while wrong (docs/hardening.md, "A smaller
    corruption"). The mean of the innovations keeps saying so until the state is right. A sensor
    whose errors are correlated in time beyond what the filter models fails it too: the filter's
    covariance then understates its error, and ``degraded`` is the truthful status for that too.

    Cheap on the hot path: an update adds its rows into the stream's open ``BIAS_BIN_S`` bin
    (a loop over Python floats); the windows are sums of whole bins, tested when a bin closes
    (at most once a second per stream), and a stream's verdict holds until the next test.
    Measured on every shipped scenario (docs/hardening.md, "A smaller corruption: innovations off
    centre"): no screened filter with a sound model fails it; the two that do are a filter not
    told its antenna's lever arm (``lever_arm_drive``'s ``lc_unknown``) and seed 000's diverging
    per-state federated reading."""

    def __init__(
        self,
        window_s: float = BIAS_WINDOW_S,
        min_n: int = BIAS_MIN_N,
        min_mean: float = BIAS_MIN_MEAN,
        p_fa: float = BIAS_P_FA,
        recent_s: float = BIAS_RECENT_S,
        bin_s: float = BIAS_BIN_S,
    ):
        self.window_s = window_s
        self.recent_s = recent_s
        self.bin_s = bin_s
        self.min_n = min_n
        self.min_mean = min_mean
        self._z = NormalDist().inv_cdf(1.0 - p_fa / 2.0)
        self._bins = max(1, round(window_s / bin_s))  # closed bins a window holds
        self._recent_bins = max(1, round(recent_s / bin_s))
        self._streams: dict[str, _StreamBias] = {}

    def clear(self) -> None:
        """Forget every window (a filter restarted: its new innovations start a new history)."""
        self._streams.clear()

    def add(self, key: str, t: float, labels, r, used) -> bool:
        """One update of stream ``key`` at ``t``: its rows' ``labels``, standardised innovations
        ``r`` and which of them the update ``used`` (only those, and finite ones, are averaged;
        arrays, or lists of Python floats and bools as a pipeline's record_rows has them).
        Returns whether a row of the stream failed its latest test."""
        st = self._streams.get(key)
        if st is None:
            st = self._streams[key] = _StreamBias(tuple(labels))
        elif st.last_t is not None and t < st.last_t:  # time went back (the stream restarted)
            st = self._streams[key] = _StreamBias(tuple(labels))
        st.last_t = t
        b = math.floor(t / self.bin_s)
        if b != st.bin:
            if st.bin is not None:
                self._close(st, b)
            st.bin = b
        cur_sum, cur_n = st.cur_sum, st.cur_n
        rows = range(len(cur_sum)) if (labels is st.labels or labels == st.labels) else st.rows_of(labels)
        r = r.tolist() if isinstance(r, np.ndarray) else r
        used = used.tolist() if isinstance(used, np.ndarray) else used
        for i, x, u in zip(rows, r, used, strict=True):
            if u and x - x == 0.0:  # (used and finite)
                cur_sum[i] += x
                cur_n[i] += 1
        return bool(st.failing)

    def _close(self, st: _StreamBias, now_bin: int) -> None:
        """The open bin joins the window; bins older than the window leave it; the test."""
        bins = st.bins
        m = len(st.labels)
        cur_sum, cur_n, tot_sum, tot_n = st.cur_sum, st.cur_n, st.tot_sum, st.tot_n
        bins.append((st.bin, cur_sum, cur_n))
        for i in range(m):
            tot_sum[i] += cur_sum[i]
            tot_n[i] += cur_n[i]
        st.cur_sum, st.cur_n = [0.0] * m, [0] * m
        while bins and bins[0][0] <= now_bin - 1 - self._bins:
            _, su, n = bins.popleft()
            for i in range(m):
                tot_sum[i] -= su[i]
                tot_n[i] -= n[i]
        first_recent = now_bin - 1 - self._recent_bins
        rec_sum, rec_n = [0.0] * m, [0] * m
        for bn, su, n in reversed(bins):
            if bn <= first_recent:
                break
            for i in range(m):
                rec_sum[i] += su[i]
                rec_n[i] += n[i]
        st.failing = [
            st.labels[i]
            for i in range(m)
            if self._off_centre(tot_sum[i], tot_n[i]) or self._off_centre(rec_sum[i], rec_n[i])
        ]

    def _off_centre(self, total: float, n: int) -> bool:
        """n standardised innovations summing to ``total`` off centre: at least min_n of them, and
        |m| sqrt(n) = |total| / sqrt(n) beyond both the quantile and min_mean sqrt(n) plus the
        margin."""
        if n < self.min_n:
            return False
        root = math.sqrt(n)
        return abs(total) / root >= max(self._z, self.min_mean * root + BIAS_MARGIN_SD)

    def _window(self, key: str, label: str, recent: bool) -> float | None:
        st = self._streams.get(key)
        i = st.index.get(label) if st is not None else None
        if i is None:
            return None
        total, n = st.cur_sum[i], st.cur_n[i]  # the open bin
        if recent:
            first = st.bin - self._recent_bins
            for bn, su, cnt in reversed(st.bins):
                if bn < first:
                    break
                total += su[i]
                n += cnt[i]
        else:
            total, n = total + st.tot_sum[i], n + st.tot_n[i]
        return total / n if n > 0 else None

    def mean(self, key: str, label: str) -> float | None:
        """The window's mean standardised innovation of one row, the open bin included (None
        before it has updates)."""
        return self._window(key, label, False)

    def recent_mean(self, key: str, label: str) -> float | None:
        """The same over the window's latest ``recent_s`` (None without updates there)."""
        return self._window(key, label, True)

    def is_failing(self, key: str) -> bool:
        """Whether stream ``key``'s latest test failed."""
        st = self._streams.get(key)
        return st is not None and bool(st.failing)

    def failing(self) -> dict[str, list[str]]:
        """The streams whose latest test failed, with their failing rows."""
        return {k: list(st.failing) for k, st in sorted(self._streams.items()) if st.failing}


__all__ = ["InnovationBias", "InnovationConsistency", "chi2_upper"]
