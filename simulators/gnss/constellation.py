"""Satellite visibility, azimuth/elevation, dilution of precision and satellite selection rules.

- :func:`az_el` gives azimuth (clockwise from north, [0, 2 pi)) and elevation of satellites seen
  from a receiver, in the receiver's local ENU frame (geodetic vertical).
- :func:`dop` / :func:`dop_batch` give GDOP, PDOP, HDOP, VDOP, TDOP from the unit line-of-sight
  geometry with one receiver clock: rows ``[-e, -n, -u, 1]``, ``Q = (G' G)^-1`` (ENU + clock),
  ``GDOP = sqrt(tr Q)``, ``PDOP = sqrt(Q_ee + Q_nn + Q_uu)``, ``HDOP = sqrt(Q_ee + Q_nn)``,
  ``VDOP = sqrt(Q_uu)``, ``TDOP = sqrt(Q_tt)``. A singular (or numerically singular) geometry has
  infinite DOPs.
- :func:`select_satellites` picks satellites by a rule named in :data:`SELECTION_RULES`:
  ``"all"``, ``"max_gdop"`` (seed 001: the subset of ``count`` visible satellites with the
  LARGEST finite GDOP, searched exhaustively), ``"min_gdop"`` (exhaustive), ``"highest_elevation"``.

Reference: Misra & Enge, *Global Positioning System*, 2nd ed., section 6.1 (DOP).
"""

from __future__ import annotations

import itertools
import math
from collections.abc import Callable, Sequence
from dataclasses import dataclass

import numpy as np

from fednav.service.earth import ecef_to_llh, mat_en

# A geometry whose normal matrix G'G has eigenvalues spread by more than this is singular for our
# purposes (its DOP would be > ~1e6, i.e. meaningless); its DOPs are reported as infinite.
SINGULAR_EIG_RATIO = 1e-12
MAX_COMBINATIONS = 2_000_000  # exhaustive search guard


def az_el(rx_pos_ecef_m: np.ndarray, sat_pos_ecef_m: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Azimuth and elevation (N,) rad of satellites (N, 3) from a receiver (3,), both ECEF.

    Azimuth is clockwise from north in [0, 2 pi); elevation in [-pi/2, pi/2] above the ellipsoid's
    tangent plane. (Satellite transmit-time vs receive-time frames differ by < 2e-5 rad here: pass
    either.)
    """
    rx = np.asarray(rx_pos_ecef_m, dtype=float).reshape(3)
    llh = ecef_to_llh(rx)
    enu = (np.atleast_2d(np.asarray(sat_pos_ecef_m, dtype=float)) - rx) @ mat_en(llh[0], llh[1])
    az = np.mod(np.arctan2(enu[:, 0], enu[:, 1]), 2.0 * np.pi)
    el = np.arctan2(enu[:, 2], np.hypot(enu[:, 0], enu[:, 1]))
    return az, el


def los_enu(az_rad: np.ndarray, el_rad: np.ndarray) -> np.ndarray:
    """Unit line-of-sight vectors (..., 3) in ENU from azimuth/elevation (...)."""
    az, el = np.asarray(az_rad, dtype=float), np.asarray(el_rad, dtype=float)
    ce = np.cos(el)
    return np.stack([ce * np.sin(az), ce * np.cos(az), np.sin(el)], axis=-1)


def visible(el_rad: np.ndarray, mask_deg: float) -> np.ndarray:
    """(N,) bool: elevation at or above the mask."""
    return np.asarray(el_rad) >= math.radians(mask_deg)


@dataclass(frozen=True)
class Dop:
    """Dilution of precision; arrays of the batch shape (scalars for one geometry)."""

    gdop: np.ndarray
    pdop: np.ndarray
    hdop: np.ndarray
    vdop: np.ndarray
    tdop: np.ndarray


def dop_batch(los_enu_unit: np.ndarray) -> Dop:
    """DOPs of a batch of geometries.

    Parameters
    ----------
    los_enu_unit : (..., k, 3) unit receiver-to-satellite vectors (ENU) of k satellites each.

    Returns
    -------
    Dop with arrays of shape (...); ``inf`` where k < 4 or G'G is (numerically) singular.
    """
    u = np.asarray(los_enu_unit, dtype=float)
    g = np.concatenate([-u, np.ones(u.shape[:-1] + (1,))], axis=-1)  # (..., k, 4)
    ngm = np.einsum("...ki,...kj->...ij", g, g)  # G'G (..., 4, 4)
    lam, vec = np.linalg.eigh(ngm)
    singular = lam[..., 0] <= SINGULAR_EIG_RATIO * lam[..., -1]
    inv_lam = np.where(singular[..., None], 0.0, 1.0 / np.where(lam > 0, lam, 1.0))
    qdiag = np.einsum("...ik,...k->...i", vec**2, inv_lam)  # diag of V diag(1/lam) V'
    inf = np.where(singular, np.inf, 0.0)
    return Dop(
        gdop=np.sqrt(np.sum(qdiag, axis=-1)) + inf,
        pdop=np.sqrt(np.sum(qdiag[..., :3], axis=-1)) + inf,
        hdop=np.sqrt(qdiag[..., 0] + qdiag[..., 1]) + inf,
        vdop=np.sqrt(qdiag[..., 2]) + inf,
        tdop=np.sqrt(qdiag[..., 3]) + inf,
    )


def dop(az_rad: np.ndarray, el_rad: np.ndarray) -> Dop:
    """DOPs (scalars) of one set of satellites given by azimuth/elevation (N,) rad."""
    az = np.asarray(az_rad, dtype=float)
    if az.size < 4:
        inf = np.float64(np.inf)
        return Dop(inf, inf, inf, inf, inf)
    return dop_batch(los_enu(az, el_rad))


# --- selection rules ----------------------------------------------------------------------------------
SelectionRule = Callable[[np.ndarray, np.ndarray, int, np.ndarray, float], np.ndarray]
"""``rule(az_rad (N,), el_rad (N,), count, required (N,) bool, gdop_limit) -> sorted indices``
over the satellites given (already visible)."""


def _combinations_gdop(
    az: np.ndarray, el: np.ndarray, count: int, required: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    n = len(az)
    req = np.flatnonzero(required)
    free = np.flatnonzero(~required)
    k_free = count - len(req)
    if k_free < 0:
        raise ValueError(f"{len(req)} required satellites exceed the selection count {count}")
    n_comb = math.comb(len(free), k_free)
    if n_comb > MAX_COMBINATIONS:
        raise ValueError(
            f"exhaustive selection of {count} of {n} satellites needs {n_comb} subsets (> {MAX_COMBINATIONS})"
        )
    if k_free == 0:  # every selected satellite is required: the one subset is the required set
        combos = np.zeros((1, 0), dtype=int)
    else:
        combos = np.array(list(itertools.combinations(free, k_free)), dtype=int).reshape(-1, k_free)
    subsets = np.concatenate([np.broadcast_to(req, (len(combos), len(req))), combos], axis=1)
    subsets.sort(axis=1)
    g = dop_batch(los_enu(az[subsets], el[subsets])).gdop
    return subsets, g


def _rule_all(az, el, count, required, gdop_limit):
    return np.arange(len(az))


def _rule_gdop(largest: bool):
    def rule(az, el, count, required, gdop_limit):
        if len(az) <= count:
            return np.arange(len(az))
        subsets, g = _combinations_gdop(az, el, count, required)
        ok = np.isfinite(g) & (g <= gdop_limit)
        if not np.any(ok):
            raise ValueError(f"no subset of {count} satellites has a finite GDOP <= {gdop_limit}")
        g = np.where(ok, g, -np.inf if largest else np.inf)
        best = int(np.argmax(g) if largest else np.argmin(g))  # first one wins ties: deterministic
        return subsets[best]

    return rule


def _rule_highest_elevation(az, el, count, required, gdop_limit):
    # required first, then by decreasing elevation (stable on ties)
    order = np.lexsort((-np.asarray(el), ~np.asarray(required)))
    return np.sort(order[:count])


SELECTION_RULES: dict[str, SelectionRule] = {
    "all": _rule_all,
    "max_gdop": _rule_gdop(largest=True),
    "min_gdop": _rule_gdop(largest=False),
    "highest_elevation": _rule_highest_elevation,
}


def select_satellites(
    az_rad: np.ndarray,
    el_rad: np.ndarray,
    rule: str = "all",
    count: int | None = None,
    required: Sequence[int] | np.ndarray = (),
    gdop_limit: float = math.inf,
) -> np.ndarray:
    """Indices (sorted) of the selected satellites among those given (pass only visible ones).

    Parameters
    ----------
    az_rad, el_rad : (N,) azimuth and elevation of the candidate satellites.
    rule : a key of :data:`SELECTION_RULES`.
    count : number to select (ignored by ``"all"``; required >= 4 otherwise). With ``count >= N``
        every candidate is returned (the rule cannot choose).
    required : indices that every selected subset must contain (e.g. the satellite a fault
        scenario targets).
    gdop_limit : ``max_gdop``/``min_gdop`` consider only subsets with ``GDOP <= gdop_limit``
        (besides finiteness), so "largest GDOP" can exclude near-degenerate subsets.
    """
    if rule not in SELECTION_RULES:
        raise ValueError(f"rule: unknown selection rule {rule!r}; choose from {sorted(SELECTION_RULES)}")
    az = np.asarray(az_rad, dtype=float)
    el = np.asarray(el_rad, dtype=float)
    if rule != "all" and (count is None or count < 4):
        raise ValueError(f"count: rule {rule!r} needs a count >= 4, got {count}")
    req = np.zeros(len(az), dtype=bool)
    req[np.asarray(required, dtype=int)] = True
    return np.asarray(SELECTION_RULES[rule](az, el, int(count or 0), req, gdop_limit), dtype=int)
