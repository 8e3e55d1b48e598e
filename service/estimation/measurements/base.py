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

from collections.abc import Callable, Mapping
from dataclasses import dataclass, field
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
    """

    n_states: int = em.N_STATES
    dt_late_s: float = 0.0
    columns: Mapping[str, slice] = field(default_factory=dict)
    reference: Mapping[str, np.ndarray] = field(default_factory=dict)
    wib_b_rps: np.ndarray = field(default_factory=lambda: np.zeros(3))


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
    "Measurement",
    "MeasurementModel",
    "ModelContext",
    "PrivateStates",
    "private_layout",
    "private_transition",
]


def floored_variances(std: np.ndarray, minimum: np.ndarray | float) -> tuple[np.ndarray, int]:
    """Variances of the given sigmas, each sigma raised to at least ``minimum``; and how many were
    raised. A sensor message cannot claim more precision than the model admits (one fix with a
    1e-9 m sigma must not pin the filter)."""
    std = np.asarray(std, dtype=float)
    lo = np.broadcast_to(np.asarray(minimum, dtype=float), std.shape)
    return np.square(np.maximum(std, lo)), int(np.count_nonzero(std < lo))
