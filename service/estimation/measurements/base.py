"""The measurement hook: one interface for every sensor model.

A measurement model turns one aiding message into the rows of an error-state Kalman update for
the navigation state it is linearised about:

    model(nav, msg, ctx) -> Measurement(z, H, R, labels[, groups]) or None (nothing usable)

z is the INS-predicted quantity minus the sensor's ("INS minus sensor"), so with the error state
x (computed minus true) the model is z = H x + v, v ~ N(0, R). H has ``ctx.n_states`` columns:
the 15 INS error states of :mod:`service.ins.error_model` first, then the filter's private
states. A model that needs states of its own (receiver clock, DVL scale factor and offset, lever
arm, flexure angles) DECLARES them as :class:`PrivateStates` blocks; the pipeline appends the
blocks to its filter's state vector (block-diagonal process model from ``transition``) and tells
the model where they are (``ctx.columns[name]``) and their linearisation point
(``ctx.reference[name]``, closed loop like the INS).

Rows may carry ``groups``: the index, into ``group_ids``, of the source each row belongs to
(e.g. a satellite for pseudorange and range-rate rows), for per-source exclusion (MHSS) and
fault isolation. Registering a model: one line in ``service/estimation/measurements/__init__.py``.
"""

from __future__ import annotations

import math
from collections import deque
from collections.abc import Callable, Mapping
from dataclasses import dataclass, field, replace
from typing import Protocol

import numpy as np

from fednav.service.ins import error_model as em
from fednav.service.ins.mechanisation import NavState
from fednav.service.messages import WireModel


@dataclass(frozen=True)
class Measurement:
    """Rows of one update: z (m,), H (m, n_states), R (m, m), one label per row.

    ``groups`` (m,) int, optional: source index of each row into ``group_ids``. ``floored``: how
    many rows had their sigma raised to the model's minimum (a message claiming more precision
    than any such sensor has; counted by the pipeline as screening ``sigma_floor``).
    """

    z: np.ndarray
    H: np.ndarray
    R: np.ndarray
    labels: tuple[str, ...]
    groups: np.ndarray | None = None
    group_ids: tuple[str, ...] = ()
    floored: int = 0

    @property
    def r_var(self) -> np.ndarray:
        """Diagonal of R (models with independent rows)."""
        return np.diagonal(self.R).copy()


@dataclass(frozen=True)
class PrivateStates:
    """A block of states a measurement model adds to its filter.

    names: one per state (with units); transition(T) -> (Phi (k, k), Qd (k, k)) over T seconds;
    initial_std (k,): prior 1-sigma of the block's error states.
    """

    name: str
    names: tuple[str, ...]
    transition: Callable[[float], tuple[np.ndarray, np.ndarray]]
    initial_std: tuple[float, ...]

    @property
    def size(self) -> int:
        return len(self.names)


@dataclass(frozen=True)
class ModelContext:
    """Where the model's rows go: filter size, its private blocks' columns and references.

    dt_late_s > 0: the message is older than the INS time (late aiding inside the tolerance).
    wib_b_rps: the INS's last body angular rate (lever-arm velocities, e.g. a DVL's).
    acc_enu_mps2: with late aiding, the INS's acceleration (ENU, dv/dt over its last major
    interval): what takes its velocity back to the message's time (None when not late).
    """

    n_states: int = em.N_STATES
    dt_late_s: float = 0.0
    columns: Mapping[str, slice] = field(default_factory=dict)
    reference: Mapping[str, np.ndarray] = field(default_factory=dict)
    wib_b_rps: np.ndarray = field(default_factory=lambda: np.zeros(3))
    acc_enu_mps2: np.ndarray | None = None


class MeasurementModel(Protocol):
    """The hook every aiding sensor implements (module docstring)."""

    #: the sensor kind (intake key family) whose messages it consumes
    kind: str
    #: private-state blocks the model needs in its filter (empty for most sensors)
    private_states: tuple[PrivateStates, ...]

    def __call__(self, nav: NavState, msg: WireModel, ctx: ModelContext) -> Measurement | None: ...


def private_layout(blocks: tuple[PrivateStates, ...]) -> dict[str, slice]:
    """Columns of each private block appended after the 15 INS states, in order."""
    out, k = {}, em.N_STATES
    for b in blocks:
        out[b.name] = slice(k, k + b.size)
        k += b.size
    return out


def private_transition(blocks: tuple[PrivateStates, ...]):
    """(T) -> (Phi, Qd) of all private blocks, block diagonal (the bank's ``private_model``)."""
    if not blocks:
        return None
    n = sum(b.size for b in blocks)

    def model(T: float) -> tuple[np.ndarray, np.ndarray]:
        Phi, Qd = np.eye(n), np.zeros((n, n))
        k = 0
        for b in blocks:
            s = slice(k, k + b.size)
            Phi[s, s], Qd[s, s] = b.transition(T)
            k += b.size
        return Phi, Qd

    return model


__all__ = [
    "CLAIM_FRACTION",
    "SPREAD_FRACTION",
    "SigmaFloors",
    "Measurement",
    "MeasurementModel",
    "ModelContext",
    "PrivateStates",
    "private_layout",
    "private_transition",
]


#: a row whose source (``Measurement.groups``) has a row refused as faulty is suspect: it is used
#: only when its standardised innovation is within this (a fault large enough to fail one axis
#: of a receiver's solution is in its other axes too, smaller: under a 5-sigma gate it would be
#: taken at full weight; a clean row of that source passes with 95 % probability)
SUSPECT_SIGMA = 2.0


def rows_of(meas: Measurement, rows: np.ndarray) -> Measurement:
    """The measurement with only ``rows`` ((m,) bool), everything else as it was."""
    idx = np.flatnonzero(rows)
    return replace(
        meas,
        z=meas.z[idx],
        H=meas.H[idx],
        R=meas.R[np.ix_(idx, idx)],
        labels=tuple(meas.labels[i] for i in idx),
        groups=None if meas.groups is None else meas.groups[idx],
    )


def refused_with_source(
    standardised: np.ndarray, refused: np.ndarray, groups: np.ndarray | None
) -> np.ndarray:
    """(m,) bool: the ``refused`` rows, and the rows of a refused row's source (``groups``) whose
    ``|standardised|`` exceeds :data:`SUSPECT_SIGMA`. Without sources: ``refused``."""
    refused = np.asarray(refused, dtype=bool)
    if groups is None or not refused.any() or len(groups) != len(refused):
        return refused
    groups = np.asarray(groups)
    hit = np.isin(groups, groups[refused])
    return refused | (hit & (np.abs(np.asarray(standardised, dtype=float)) > SUSPECT_SIGMA))


def floored_variances(std: np.ndarray, minimum: np.ndarray | float) -> tuple[np.ndarray, int]:
    """Variances of the given sigmas, each sigma raised to at least ``minimum``; and how many were
    raised. A sensor message cannot claim more precision than the model admits (one fix with a
    1e-9 m sigma must not pin the filter)."""
    std = np.asarray(std, dtype=float)
    lo = np.asarray(minimum, dtype=float)  # a scalar or std's shape: numpy broadcasts it
    return np.square(np.maximum(std, lo)), int(np.count_nonzero(std < lo))


#: a claimed sigma is raised to at least this fraction of the median of what the same stream (and
#: row) claimed before: a sensor that claimed 10 m for minutes does not become a 1 m sensor in
#: one message (what its own history supports)
CLAIM_FRACTION = 0.5
#: ... and to at least this fraction of the sensor noise its innovations show (their robust
#: spread less the filter's own share H P H'): a stream claiming 1 m whose fixes scatter by 10 m
SPREAD_FRACTION = 0.1
#: messages of a stream remembered per row (its recent history)
HISTORY_WINDOW = 120
#: rows of history before the history floors apply (before: the model's absolute floor only)
HISTORY_MIN_SAMPLES = 20
#: median of chi-square(1): median(r^2) / this estimates the variance of r
_MEDIAN_CHI2_1 = 0.45493642311957184


def _median(values) -> float:
    """The median of a short sequence of finite floats, as ``np.median`` computes it (the mean of
    the two middle values of an even count), without the array round trip (the sigma floors'
    histories are updated at every aiding epoch of every vehicle)."""
    s = sorted(values)
    n = len(s)
    m = n // 2
    return float(s[m]) if n % 2 else (s[m - 1] + s[m]) / 2.0


class _RowHistory:
    __slots__ = ("claimed", "r2", "hph", "floor", "stale")

    def __init__(self) -> None:
        self.claimed: deque = deque(maxlen=HISTORY_WINDOW)
        self.r2: deque = deque(maxlen=HISTORY_WINDOW)
        self.hph: deque = deque(maxlen=HISTORY_WINDOW)
        self.floor = 0.0
        self.stale = 0

    def update_floor(self) -> None:
        if len(self.claimed) < HISTORY_MIN_SAMPLES:
            self.floor = 0.0
            return
        f = CLAIM_FRACTION * _median(self.claimed)
        if len(self.r2) >= HISTORY_MIN_SAMPLES:
            var = _median(self.r2) / _MEDIAN_CHI2_1 - _median(self.hph)
            f = max(f, SPREAD_FRACTION * math.sqrt(max(var, 0.0)))
        self.floor = f
        self.stale = 0


class SigmaFloors:
    """Sigma floors from each stream's own history (per ``kind/sensor`` key and row label): a new
    claim is raised to at least :data:`CLAIM_FRACTION` x the median of the stream's recent claims
    and :data:`SPREAD_FRACTION` x the sensor noise its recent innovations show. The model's
    absolute floor (:func:`floored_variances`) still applies before any history exists. A
    pipeline calls :meth:`apply` before an update and :meth:`record` after an update that used
    the rows (refused rows teach nothing)."""

    #: label tuples remembered per stream (:meth:`_histories`) before the memo starts afresh
    MEMO_SIZE = 64

    def __init__(self) -> None:
        self._rows: dict[tuple[str, str], _RowHistory] = {}
        # (key, labels) -> the rows' histories in label order: a stream's messages repeat their
        # labels (a receiver's satellites change every few minutes), so each epoch looks them up
        # once instead of once per row
        self._memo: dict[tuple[str, tuple[str, ...]], list[_RowHistory]] = {}

    def _histories(self, key: str, labels: tuple[str, ...]) -> list[_RowHistory]:
        k = (key, labels)
        hs = self._memo.get(k)
        if hs is None:
            if len(self._memo) >= self.MEMO_SIZE:
                self._memo.clear()
            hs = self._memo[k] = [self._row(key, lab) for lab in labels]
        return hs

    def apply(self, key: str, meas: Measurement) -> tuple[Measurement, np.ndarray]:
        """(meas with its R raised where the history says so, the claimed sigmas before)."""
        # np.maximum is what np.clip(d, 0.0, None) calls, without its Python wrappers (~20 us a call)
        sd = np.sqrt(np.maximum(np.asanyarray(meas.R).diagonal(), 0.0))
        floors = [h.floor for h in self._histories(key, tuple(meas.labels))]
        if not any(f > 0.0 for f in floors) or all(a >= f for a, f in zip(sd.tolist(), floors, strict=True)):
            return meas, sd  # (the usual epoch: no history floor, or every claim above it)
        floor = np.array(floors)
        low = sd < floor
        if not low.any():  # (NaN sigmas: never below a floor)
            return meas, sd
        scale = np.where(low, floor / np.maximum(sd, 1e-300), 1.0)
        R = meas.R * np.outer(scale, scale)
        return replace(meas, R=R, floored=max(meas.floored, int(low.sum()))), sd

    def record(self, key: str, meas: Measurement, claimed: np.ndarray, innovation, hph, used=None) -> None:
        """Rows of an update that used them: the claimed sigmas, the innovations (z - H x) and
        the filter's share of their variance (diagonal of H P H')."""
        # Python floats once (the same values as float() of each element)
        claimed, innovation, hph = (np.asarray(a, dtype=float).tolist() for a in (claimed, innovation, hph))
        used = None if used is None else np.asarray(used, dtype=bool).tolist()
        self.record_floats(key, meas.labels, claimed, innovation, hph, used)

    def record_floats(self, key: str, labels, claimed: list, innovation: list, hph: list, used) -> None:
        """:meth:`record` of rows given as lists of Python floats (``used``: a list of bools or
        None), as the pipelines' :meth:`~service.pipelines.base.Pipeline.record_rows` has them."""
        for j, h in enumerate(self._histories(key, tuple(labels))):
            if used is not None and not used[j]:
                continue
            h.claimed.append(claimed[j])
            h.r2.append(innovation[j] ** 2)
            h.hph.append(hph[j])
            h.stale += 1
            if h.stale >= 10 or len(h.claimed) == HISTORY_MIN_SAMPLES:
                h.update_floor()

    def _row(self, key: str, label: str) -> _RowHistory:
        h = self._rows.get((key, label))
        if h is None:
            h = self._rows[(key, label)] = _RowHistory()
        return h

    def floor(self, key: str, label: str) -> float:
        """The current history floor of a row (0 before enough history)."""
        return self._row(key, label).floor
