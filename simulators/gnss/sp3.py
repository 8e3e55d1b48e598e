"""SP3-c/d precise orbit reader and per-satellite Lagrange interpolation.

Positions are interpolated with a Lagrange polynomial through ``order + 1`` consecutive grid nodes
(default 10 nodes, i.e. order 9, on the usual 5 or 15 min grid) centred on the query time and
shifted inwards at the file's ends; velocity is the analytic derivative of that same polynomial,
so position and velocity are mutually consistent. The interpolation is done on ECEF coordinates
directly (at 5 min spacing this is good to well below a millimetre for GPS; see the tests' leave-
one-out check). Clocks are interpolated linearly between the two bracketing nodes (SP3 clocks are
not smooth enough for high-order polynomials) and the drift is that segment's slope.

Missing values follow SP3: a position of 0.000000 km or a clock of 999999.999999 us is "bad or
absent" and becomes NaN; an interpolation window containing NaN yields NaN.

SP3 orbits are satellite centre of mass in the IGS realisation of ITRF (IGb14 here), which is
WGS-84 to centimetres. SP3 clocks do not contain the periodic relativistic correction
``-2 r.v / c^2``; :class:`Sp3Orbits` adds it by default (``relativistic_clock=True``) so that its
``clock_s`` has the same meaning as a broadcast clock (the apparent clock a receiver must remove).

Reference: Hilla, "The Extended Standard Product 3 Orbit Format (SP3-d)", IGS/NGS, 2016.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from fednav.service.earth import C_MPS, GM_M3PS2, OMEGA_IE_RPS
from fednav.simulators.gnss.orbits import SatStates, _times_for, gps_seconds

SP3_BAD_CLOCK_US = 999999.0  # values >= this are "no clock"


@dataclass(frozen=True)
class Sp3Data:
    """Contents of an SP3 file.

    Attributes
    ----------
    t_gps_s : (E,) epoch times, s of GPS time.
    ids : tuple of S satellite ids (``G01``, ``C19``, ...).
    pos_ecef_m : (E, S, 3) positions, NaN where absent.
    clock_s : (E, S) clocks, s, NaN where absent.
    time_system : the file's time system (``GPS``).
    """

    t_gps_s: np.ndarray
    ids: tuple[str, ...]
    pos_ecef_m: np.ndarray
    clock_s: np.ndarray
    time_system: str


def read_sp3(path: str | Path) -> Sp3Data:
    """Read an SP3-c or SP3-d file (position records; velocity and correlation records are skipped).

    Only the GPS time scale is accepted (the file's ``%c`` line); other scales raise ``ValueError``.
    The epochs actually present are used (the header's epoch count may disagree, e.g. in a cut file).
    """
    path = Path(path)
    lines = path.read_text(errors="replace").splitlines()
    if not lines or not lines[0].startswith("#") or lines[0][1] not in "cd":
        raise ValueError(f"{path}: not an SP3-c/d file (first line {lines[0][:10] if lines else ''!r})")
    time_system = "GPS"
    first_c = next((ln for ln in lines if ln.startswith("%c")), None)
    if first_c is not None and len(first_c) >= 12 and first_c[9:12].strip() not in ("", "ccc"):
        time_system = first_c[9:12].strip()
    if time_system != "GPS":
        raise ValueError(f"{path}: time system {time_system!r} not supported (GPS only)")

    epochs: list[float] = []
    records: dict[str, dict[int, tuple[float, float, float, float]]] = {}
    for ln in lines:
        if ln.startswith("*"):
            f = ln[1:].split()
            epochs.append(gps_seconds(int(f[0]), int(f[1]), int(f[2]), int(f[3]), int(f[4]), float(f[5])))
        elif ln.startswith("P") and epochs:
            sid = ln[1:4].replace(" ", "0")
            try:
                x, y, z = float(ln[4:18]), float(ln[18:32]), float(ln[32:46])
                clk = float(ln[46:60]) if len(ln) >= 47 and ln[46:60].strip() else SP3_BAD_CLOCK_US
            except ValueError as e:
                raise ValueError(f"{path}: bad position record {ln!r}") from e
            records.setdefault(sid, {})[len(epochs) - 1] = (x, y, z, clk)
        elif ln.startswith("EOF"):
            break
    if not epochs:
        raise ValueError(f"{path}: no epochs")
    ids = tuple(sorted(records))
    n_e, n_s = len(epochs), len(ids)
    pos = np.full((n_e, n_s, 3), np.nan)
    clk = np.full((n_e, n_s), np.nan)
    for j, sid in enumerate(ids):
        for e, (x, y, z, c) in records[sid].items():
            if not (x == 0.0 and y == 0.0 and z == 0.0):
                pos[e, j] = (x * 1e3, y * 1e3, z * 1e3)
            if abs(c) < SP3_BAD_CLOCK_US:
                clk[e, j] = c * 1e-6
    t = np.asarray(epochs)
    if np.any(np.diff(t) <= 0):
        raise ValueError(f"{path}: epochs are not strictly increasing")
    return Sp3Data(t, ids, pos, clk, time_system)


def lagrange_weights(x: np.ndarray, nodes: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Lagrange basis values and derivatives.

    Parameters
    ----------
    x : (Q,) query abscissae.
    nodes : (Q, n) node abscissae per query (distinct).

    Returns
    -------
    w, dw : (Q, n) with ``p(x) = sum_j w_j f_j`` and ``p'(x) = sum_j dw_j f_j``.
        Exact at the nodes too (no division by ``x - x_j``).
    """
    x = np.asarray(x, dtype=float)
    nodes = np.asarray(nodes, dtype=float)
    n = nodes.shape[1]
    eye = np.eye(n, dtype=bool)
    diff = x[:, None] - nodes  # (Q, n): x - x_m
    denom = nodes[:, :, None] - nodes[:, None, :]  # (Q, j, m): x_j - x_m
    denom = np.where(eye, 1.0, denom)
    terms = np.where(eye, 1.0, diff[:, None, :] / denom)  # (Q, j, m): (x - x_m)/(x_j - x_m), 1 at m == j
    w = np.prod(terms, axis=2)
    # L_j'(x) = sum_{k != j} 1/(x_j - x_k) prod_{m != j, k} (x - x_m)/(x_j - x_m)
    excl = eye[None, None, :, :] | eye[None, :, None, :]  # (1, j, k, m): m == k or m == j
    t4 = np.where(excl, 1.0, terms[:, :, None, :])  # (Q, j, k, m)
    partial = np.prod(t4, axis=3)  # (Q, j, k)
    dw = np.sum(np.where(eye, 0.0, partial / denom), axis=2)
    return w, dw


class Sp3Orbits:
    """Orbit source from an SP3 file (see the module docstring).

    Parameters
    ----------
    data : parsed file (or use :meth:`from_file`).
    order : interpolation polynomial order (``order + 1`` nodes), default 9.
    relativistic_clock : add ``-2 r.v / c^2`` to the SP3 clock (default True).
    """

    def __init__(self, data: Sp3Data, order: int = 9, relativistic_clock: bool = True):
        if order < 1 or order + 1 > len(data.t_gps_s):
            raise ValueError(f"order: {order} needs {order + 1} epochs, file has {len(data.t_gps_s)}")
        self.data = data
        self.order = order
        self.relativistic_clock = relativistic_clock
        self._index = {s: k for k, s in enumerate(data.ids)}
        self._t = data.t_gps_s
        self._h = float(np.median(np.diff(self._t)))

    @classmethod
    def from_file(cls, path: str | Path, order: int = 9, relativistic_clock: bool = True) -> Sp3Orbits:
        return cls(read_sp3(path), order=order, relativistic_clock=relativistic_clock)

    @property
    def time_span_gps_s(self) -> tuple[float, float]:
        return float(self._t[0]), float(self._t[-1])

    def satellite_ids(self) -> list[str]:
        return list(self.data.ids)

    def _sat_index(self, ids: Sequence[str]) -> np.ndarray:
        try:
            return np.array([self._index[s] for s in ids], dtype=int)
        except KeyError as e:
            raise KeyError(f"satellite {e.args[0]} is not in the SP3 file") from None

    def interpolate(self, ids: Sequence[str], t_gps_s: float | np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Position (N, 3) and velocity (N, 3) of ``ids`` at ``t_gps_s`` (scalar or (N,)); NaN outside
        the file's span or where the window holds a missing node."""
        t = _times_for(ids, t_gps_s)
        k = self._sat_index(ids)
        tt, n_nodes = self._t, self.order + 1
        inside = (t >= tt[0]) & (t <= tt[-1])
        seg = np.clip(np.searchsorted(tt, t, side="right") - 1, 0, len(tt) - 2)  # tt[seg] <= t < tt[seg+1]
        start = np.clip(seg - (n_nodes // 2 - 1), 0, len(tt) - n_nodes)
        win = start[:, None] + np.arange(n_nodes)  # (N, n)
        x = (t - tt[seg]) / self._h
        nodes = (tt[win] - tt[seg][:, None]) / self._h
        w, dw = lagrange_weights(x, nodes)
        f = self.data.pos_ecef_m[win, k[:, None], :]  # (N, n, 3)
        pos = np.einsum("nj,njc->nc", w, f)
        vel = np.einsum("nj,njc->nc", dw, f) / self._h
        pos[~inside] = np.nan
        vel[~inside] = np.nan
        return pos, vel

    def clock(self, ids: Sequence[str], t_gps_s: float | np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """SP3 clock (N,) s and drift (N,) s/s by linear interpolation (no relativistic term)."""
        t = _times_for(ids, t_gps_s)
        k = self._sat_index(ids)
        tt = self._t
        seg = np.clip(np.searchsorted(tt, t, side="right") - 1, 0, len(tt) - 2)
        c0, c1 = self.data.clock_s[seg, k], self.data.clock_s[seg + 1, k]
        dt = tt[seg + 1] - tt[seg]
        drift = (c1 - c0) / dt
        clk = c0 + drift * (t - tt[seg])
        out = (t < tt[0]) | (t > tt[-1])
        clk[out] = np.nan
        drift[out] = np.nan
        return clk, drift

    def states(self, ids: Sequence[str], t_gps_s: float | np.ndarray) -> SatStates:
        pos, vel = self.interpolate(ids, t_gps_s)
        clk, drift = self.clock(ids, t_gps_s)
        if self.relativistic_clock:
            # dt_rel = -2 r.v / c^2 (IS-GPS-200 20.3.3.3.3.1 in vector form; same for BDS MEO/IGSO);
            # its rate uses |v|^2 + r.a with two-body a = -GM r / |r|^3.
            # r.v is frame independent (r . (omega x r) = 0); |v|^2 needs the inertial velocity.
            v_in = vel + OMEGA_IE_RPS * np.stack([-pos[:, 1], pos[:, 0], np.zeros(len(pos))], axis=-1)
            r = np.linalg.norm(pos, axis=1)
            clk = clk - 2.0 * np.sum(pos * vel, axis=1) / C_MPS**2
            drift = drift - 2.0 * (np.sum(v_in * v_in, axis=1) - GM_M3PS2 / r) / C_MPS**2
        return SatStates(tuple(ids), pos, vel, clk, drift)

    def available(self, t_gps_s: float) -> list[str]:
        """Ids with a valid position and clock at ``t_gps_s``."""
        ids = list(self.data.ids)
        st = self.states(ids, t_gps_s)
        return [s for s, ok in zip(ids, st.valid, strict=True) if ok]
