"""The pipeline contract: a configured chain sensors -> measurement models -> filter bank -> outputs.

Each pipeline owns its INS inside its filter bank (``self.bank``, an
:class:`~service.estimation.ins_filter.InsFilterBank` or a subclass; closed loop makes references
differ per pipeline), so several run side by side on one input stream. A family is one module
under ``service/pipelines/`` with one class per configuration ``kind`` (registered in
``service/pipelines/__init__.py``). The engine calls, in sensor-time order:

  ``start(nav, std, after_loss)``  once, and again on re-initialisation (calls ``initialise``);
  ``advance(pre)``                 the vehicle's shared preintegrated IMU interval at every major
                                   update (``push_imu`` is the per-pipeline equivalent);
  ``sync()``                       before reading the state at an aiding or output epoch;
  ``apply(kind, sensor_id, msg, dt_late_s)``  per aiding message -> extra outputs (Faults, ...);
  ``estimate()`` / ``solution()``  at output epochs; ``recover_covariance()`` after a
                                   numerical failure (the engine catches ``LinAlgError``).

A subclass implements ``initialise`` (build ``self.bank``), ``apply`` (measurement models from
:mod:`service.estimation.measurements`, one update on the bank) and ``estimate``; the base class
provides the time path, status and Solution. The pipeline owns its status (``status``,
``updates``, ``reinitialisations``); nobody else writes them.
"""

from __future__ import annotations

import math
from abc import ABC, abstractmethod
from collections import Counter, deque
from dataclasses import dataclass
from functools import lru_cache

import numpy as np

# at import, not at the first quantile: a lazy import of scipy.stats (~0.4 s) would stall the
# service's intake, and every vehicle with it, at the first epoch of its first tightly coupled
# vehicle (the other families import it through their gates and fault tests anyway)
from scipy.stats import chi2

from fednav.service import earth
from fednav.service.config import ImuModel
from fednav.service.estimation.consistency import InnovationBias, InnovationConsistency
from fednav.service.estimation.ins_filter import InsFilterBank
from fednav.service.estimation.measurements.base import SigmaFloors
from fednav.service.estimation.measurements.gnss_fix import BLOCK as GNSS_ERROR_BLOCK
from fednav.service.estimation.measurements.gnss_fix import white_std
from fednav.service.ins import error_model as em
from fednav.service.ins.alignment import InitStd
from fednav.service.ins.mechanisation import NavState
from fednav.service.messages import Solution, WireModel


def initial_covariance(std: InitStd, imu: ImuModel, private=()) -> np.ndarray:
    """Diagonal prior of the 15 INS error states (initial sigmas, the IMU's bias sigmas), then of
    each private-state block of ``private`` (its ``initial_std``), in bank column order."""
    sg, sa = imu.bias_sigmas()
    d = np.concatenate(
        [
            std.pos_enu_m,
            std.vel_enu_mps,
            std.att_rad,
            np.full(3, max(sg, 1e-12)),
            np.full(3, max(sa, 1e-12)),
            *[np.asarray(b.initial_std, dtype=float) for b in private],
        ]
    )
    P = np.diag(np.square(d))
    if getattr(std, "pos_from_fix", False):
        # a position taken from a fix carries the receiver's correlated error b: dp = b + n, and
        # the model's error state is db = -b (gnss_fix.py), so Cov(dp, db) = -P_b (independent,
        # the first fixes' b would count twice: consistent only after a correlation time).
        # Var(dp) = P_b + Var(n), with n the fix's white part as its update takes it
        # (gnss_fix.white_std): a fix that claims less than the configured correlated error
        # (a receiver's sigma below the configuration's) must not start the position more certain
        # than b itself, or the fixes then pin b and the filter is overconfident from its start
        col = em.N_STATES
        for block in private:
            if block.name == GNSS_ERROR_BLOCK:
                sd_b = np.asarray(block.initial_std, dtype=float)
                sd_p = np.asarray(std.pos_enu_m, dtype=float)
                i, j = np.arange(3), col + np.arange(3)
                P[i, i] = np.maximum(P[i, i], np.square(sd_b) + np.square(white_std(sd_p, sd_b)))
                cross = -np.minimum(np.square(sd_b), 0.99 * sd_b * np.sqrt(P[i, i]))
                P[i, j] = P[j, i] = cross
            col += block.size
    cov = getattr(std, "cov", None)
    if cov is not None:  # a restart that keeps the correlations of the state it restores
        cov = 0.5 * (np.asarray(cov, dtype=float) + np.asarray(cov, dtype=float).T)
        if cov.shape == P.shape:
            P = cov
        else:
            P[:9, :9] = cov[:9, :9]
    return P


def model_options(cfg) -> dict[str, dict]:
    """Keyword options of the measurement models of a pipeline configuration, by sensor kind: the
    GNSS fix's dedicated fields (lever arm, correlated error) and each ``sensor_options`` table,
    validated by its registry entry's options model (:func:`sensor_option_errors` at load)."""
    from fednav.service import sensors
    from fednav.service.estimation.measurements.gnss_fix import gnss_fix_options

    out: dict[str, dict] = {}
    if hasattr(cfg, "gnss_lever_arm_b_m"):
        out["gnss_fix"] = gnss_fix_options(cfg)
    for kind, opts in getattr(cfg, "sensor_options", {}).items():
        entry = sensors.get(kind)
        validated = entry.options.model_validate(opts).model_dump() if entry.options else dict(opts)
        out[kind] = out.get(kind, {}) | validated
    return out


def sensor_option_errors(cfg, used: set[str]) -> list[tuple[str, str]]:
    """(field, message) for ``sensor_options`` of kinds the pipeline does not use, of kinds whose
    model takes no options there, or that their options model refuses."""
    from pydantic import ValidationError

    from fednav.service import sensors

    out = []
    for kind, opts in getattr(cfg, "sensor_options", {}).items():
        loc = f"sensor_options.{kind}"
        if kind not in used:
            out.append((loc, f"sensor kind {kind!r} is not among this pipeline's sensors {sorted(used)}"))
            continue
        entry = sensors.registry().get(kind)
        if entry is None or entry.options is None:
            out.append((loc, f"the {kind!r} model takes no options here"))
            continue
        try:
            entry.options.model_validate(opts)
        except ValidationError as exc:
            e = exc.errors()[0]
            where = ".".join(str(x) for x in e["loc"])
            out.append((f"{loc}.{where}" if where else loc, e["msg"]))
    return out


@lru_cache(maxsize=16)
def _all_rows(m: int) -> np.ndarray:
    """(m,) True: the rows of an update that used every row (read-only, shared: the innovations
    kept for the recording carry it, and np.ones costs more than the rest of their entry)."""
    a = np.ones(m, dtype=bool)
    a.flags.writeable = False
    return a


@lru_cache(maxsize=256)
def _chi2_quantile(dof: int, p: float) -> float:
    return float(chi2.isf(p, dof))


@dataclass
class Estimate:
    """What evaluation needs: the navigation state and the 9x9 covariance of (dp, dv, phi)."""

    nav: NavState
    P9: np.ndarray


def observes_horizontal(H: np.ndarray, used: np.ndarray | None = None) -> bool:
    """Whether an update's rows (``used`` of them) observe horizontal position or velocity: what
    keeps a horizontal solution from being free-inertial (a star tracker's rows do not)."""
    Hh = np.asarray(H)
    if Hh.ndim != 2:
        Hh = Hh.reshape(-1, Hh.shape[-1])
    if used is not None:
        u = np.asarray(used, dtype=bool).reshape(-1)
        if not u.all():
            Hh = Hh[u]
    # error-state columns 0, 1 (east, north position) and 3, 4 (east, north velocity:
    # service/ins/error_model.py), as basic slices and count_nonzero: 2-5 us a call against 12-16
    # with fancy indexing and np.any (every update)
    return bool(np.count_nonzero(Hh[:, 0:2]) or np.count_nonzero(Hh[:, 3:5]))


class Pipeline(ABC):
    def __init__(self, name: str, imu: ImuModel, major_interval_s: float):
        self.bank: InsFilterBank | None = None  # built by ``initialise``
        self.name = name
        self.imu = imu
        self.major_interval_s = major_interval_s
        self.updates = 0
        self.reinitialisations = 0
        self.screened: Counter = Counter()  # observations refused by screening, by reason
        self.last_aiding_t: float | None = None  # any aiding update
        #: the last update that observed horizontal position or velocity (:meth:`mark_aided`)
        self.last_nav_aiding_t: float | None = None
        self.last_screened_t: float | None = None
        self.aiding_period_s: float | None = None  # the interval between the last two aidings
        self.aided_since_start = False
        self.failed = False
        self.lost = False
        #: why the running state is not verified by the vehicle's own aiding (None: verified);
        #: set by the vehicle's lifecycle (:mod:`service.lifecycle`), reported ``degraded``
        self.unverified: str | None = None
        #: the state may be corrupt and its covariance does not say so (lifecycle ``suspect``: a
        #: contested IMU, refused aiding), until it is verified or reset
        self.suspect = False
        #: lifecycle events of the pipeline's own screening, for the vehicle's lifecycle (e.g.
        #: ``aiding_refused``: a trusted sensor refused so long that the state is suspect)
        self._events: list[str] = []
        #: (t, stream key, row labels, standardised innovations, rows used) of the latest updates
        #: (the service's recording drains them at output epochs)
        self.innovations: deque = deque(maxlen=64)
        self._refused_from: float | None = None  # first epoch of a run of wholesale refusals
        #: ... the run's first epoch, kept over its reports (None: no run under way): the state
        #: went wrong before it (a sudden corruption) and its estimates since are no checkpoints
        self.refusal_began: float | None = None
        self._refused_reports = 0
        #: sigma floors from each stream's own history (measurements.base.SigmaFloors)
        self.floors = SigmaFloors()
        #: are the innovations as small as the filter claims (estimation/consistency.py)? the
        #: last time a stream's window failed: ``degraded`` for a coasting window after it
        self.consistency = InnovationConsistency()
        #: ... and centred (the same module), for the pipelines with ``bias_test``
        self.bias = InnovationBias()
        self._inflated_at: dict[tuple[str, str], float | None] = {}  # (stream, row) -> t (inflate_for_bias)
        self.last_inconsistent_t: float | None = None
        #: per stream, in an episode of updates with failing rows: whether the rest of a failing
        #: row's source is suspect (:meth:`source_groups`)
        self._source_episode: dict[str, bool] = {}
        #: per stream: (time of its last update, its usual interval) and, after a gap, the
        #: innovations of the messages held since its return (:meth:`held_on_return`)
        self._used_at: dict[str, tuple[float, float | None]] = {}
        self._returning: dict[str, tuple[float, deque, set]] = {}  # (since, window, sources released)
        #: (kind, row label) -> the first of the consecutive updates that flagged that row on its
        #: own (beyond the gate or the fault test's threshold, not only by its source)
        self._refused_since: dict[tuple[str, str], float] = {}
        self._trusted: set[str] = set()  # kinds with at least one accepted update since the start
        self._recovered_at: dict[str, float] = {}  # kind -> time of its last refusal recovery

    #: without aiding for longer than this many aiding periods (at least ``min_coast_after_s``)
    #: an aided pipeline reports ``coasting``; screening within that time reports ``degraded``
    coast_after_periods: float = 3.0
    min_coast_after_s: float = 1.0
    default_coast_after_s: float = 3.0

    # --- status: the pipeline's own, derived from what happened to it ------------------------------
    def mark_aided(self, t: float, H: np.ndarray | None = None, used: np.ndarray | None = None) -> None:
        """An aiding update was applied at t. ``H`` (rows x error states, the navigation error
        states first: service/ins/error_model.py) and ``used`` (its rows the update took), when
        given: an update that observes neither horizontal position nor horizontal velocity (a star
        tracker's attitude, a height alone) counts as an update, but the horizontal solution stays
        free-inertial, so it does not make the pipeline ``aided`` nor keep it from ``coasting``
        (:meth:`current_status`)."""
        self.last_aiding_t = t
        self.updates += 1
        if H is not None and not observes_horizontal(H, used):
            return
        if self.last_nav_aiding_t is not None and t > self.last_nav_aiding_t:
            self.aiding_period_s = t - self.last_nav_aiding_t
        self.last_nav_aiding_t = t
        self.aided_since_start = True

    def mark_screened(self, t: float, reason: str, rows: int = 1) -> None:
        """Screening refused ``rows`` observations at t (an innovation gate, a fault test)."""
        self.screened[reason] += rows
        self.last_screened_t = t

    def mark_failed(self) -> None:
        """No usable estimate (numerical failure, or an estimate outside the wire model's limits):
        ``failed`` until the next start."""
        self.failed = True

    def mark_lost(self) -> None:
        """The INS is lost (IMU gap, time jump): no navigation until the next start."""
        self.lost = True

    def mark_unverified(self, reason: str, suspect: bool = False) -> None:
        """The running state came from a source the vehicle's own aiding has not confirmed (a
        hand-over, a reset request: its covariance says how far it may be off) or is ``suspect``
        (it may be corrupt and its covariance does not say so): ``degraded`` until
        :meth:`mark_verified`, or a restart that replaces the suspect state."""
        self.unverified = reason
        self.suspect = suspect

    def mark_verified(self) -> None:
        """The vehicle's own aiding agrees with the running state again."""
        self.unverified = None
        self.suspect = False

    #: a restart from a checkpoint restores every member of the bank as it was (federated locals:
    #: each local's covariance with its private blocks); False: the members restart from the
    #: restored navigation covariance (an IMM's models, whose probabilities restart too)
    restores_members: bool = False

    #: an epoch's rows refused wholesale (:meth:`epoch_refusal`) for this long (s): the filter,
    #: not the sensor, is wrong
    refused_after_s: float = 2.0
    #: ... at this false-alarm probability per epoch of the trimmed NIS test
    REFUSED_P_FA = 1e-6

    def note_refusal(self, t: float, refused: bool) -> None:
        """An aiding epoch whose rows the filter's state refused wholesale (``refused``) or not:
        refused for ``refused_after_s`` reports ``aiding_refused`` to the vehicle's lifecycle,
        which checks the state against the vehicle's own reference; ``aiding_still_refused``
        every ``refused_after_s`` after that while the refusals go on: the state is reset."""
        if not refused:
            self._refused_from = self.refusal_began = None
            return
        if self._refused_from is None:
            self._refused_from, self._refused_reports = t, 0
        if self.refusal_began is None:
            self.refusal_began = t
        if t - self._refused_from >= self.refused_after_s:
            self._refused_from = t  # again after as long if the refusals go on
            self._refused_reports += 1
            self.report("aiding_refused" if self._refused_reports == 1 else "aiding_still_refused")

    #: a kind accepted before whose rows keep being refused this long (s): the filter, not the
    #: sensor, is wrong (:meth:`refused_long`; None: never, the fault test's exclusion stands)
    refusal_recovery_s: float | None = None
    #: ... one position row alone: this many times as long
    row_refusal_factor: float = 2.0

    def refused_long(self, kind: str, t: float, meas, flagged: np.ndarray, key: str) -> bool:
        """Whether ``kind``'s refusals say the filter, not the sensor, is wrong: every row of its
        messages beyond the gate (or the fault test's threshold) on its own at every update for
        ``refusal_recovery_s``, or one row that observes position for ``row_refusal_factor``
        times that. Only a run of such updates counts, and only for a kind accepted before (a
        sensor never accepted is never trusted by recovery).

        The row rule: a position corrupted along one axis while the rest of the fix agrees is
        refused row by row, the whole fix never fails together, and the filter stayed off for
        good (docs/hardening.md, "A silent corruption of the state"). It waits longer (the rest
        of the fix agreeing is weaker evidence against the filter, and a receiver's transient
        fault must not restart the filter onto it: the demo's step lasts 15 s, seed 000's up to
        20 s), and it takes position rows only: a filter whose velocity were wrong would soon
        disagree with the fixes' positions too, so velocity rows refused while the positions
        agree are the receiver's fault (seed 000's 50 s velocity step). And it holds only in a
        stream (``key``) whose innovations were consistent when its failing rows began
        (:meth:`source_groups`'s episode): a receiver claiming a fifth of its noise has rows
        refused for as long as it runs, which says nothing against the filter, and restarting
        the filter onto it hid the overconfidence the consistency test names (found by
        tests/test_inspect_real.py's 5x case)."""
        since = self._refused_since
        if not flagged.any():  # the usual update: nothing refused, every run of refusals ends
            if since:
                for k in [k for k in since if k[0] == kind]:
                    del since[k]
            return False
        labels = meas.labels
        for label, f in zip(labels, flagged, strict=True):
            if f:
                since.setdefault((kind, label), t)
            else:
                since.pop((kind, label), None)
        limit = self.refusal_recovery_s
        if limit is None or kind not in self._trusted:
            return False
        first = [since.get((kind, label), t) for label in labels]  # (t: not flagged now)
        if flagged.all() and t - max(first) >= limit:
            return True
        long = np.array([t - t0 >= self.row_refusal_factor * limit for t0 in first]) & flagged
        if not (long.any() and np.any(meas.H[long][:, em.POS] != 0.0)):
            return False
        episode = self._source_episode.get(key)
        return bool(self.consistency.is_consistent(key) if episode is None else episode)

    def refusal_event(self, kind: str, t: float) -> str:
        """Count a recovery :meth:`refused_long` called for and name the lifecycle's event:
        ``aiding_refused`` (the state is suspect: checked against the vehicle's own reference),
        or ``aiding_still_refused`` within three recovery times of the last one (the recovery did
        not help: the whole state is reset)."""
        self.screened["gate_recovery"] += 1
        last = self._recovered_at.get(kind)
        again = last is not None and t - last <= 3.0 * float(self.refusal_recovery_s or 0.0)
        self._recovered_at[kind] = t
        return "aiding_still_refused" if again else "aiding_refused"

    @staticmethod
    def prior_rows(meas, x: np.ndarray, P: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """(innovations z - H x, diagonal of S = H P H' + R) of an epoch's rows against the prior
        (x, P): what :meth:`epoch_refusal` tests and :meth:`record_rows` records, computed once
        by a pipeline that does both on the same prior."""
        return meas.z - meas.H @ x, np.einsum("ij,jk,ik->i", meas.H, P, meas.H) + np.diagonal(meas.R)

    def epoch_refusal(self, meas, x: np.ndarray, P: np.ndarray, prior=None) -> tuple[bool, float]:
        """(whether the prior (x, P) refuses an epoch's rows as a whole, the typical source's
        disagreement). Refused: the NIS of the rows without the worst source (``meas.groups``,
        e.g. a satellite; else the worst row) above its chi-square quantile at ``REFUSED_P_FA``.
        One failing source never makes it true; a state that disagrees with most sources does (a
        jump it took, a corrupted INS). The disagreement: the median over the sources but the
        worst of each one's RMS standardised innovation, in sigmas (0 when not refused).
        ``prior``: :meth:`prior_rows` of (meas, x, P) when the caller has them."""
        z, H = meas.z, meas.H
        m = len(z)
        if m < 3 or not (np.isfinite(z).all() and np.isfinite(H).all()):
            return False, 0.0
        r, s = self.prior_rows(meas, x, P) if prior is None else prior
        q = np.square(r) / np.maximum(s, 1e-30)
        if meas.groups is not None and len(meas.groups) == m:
            per = np.bincount(meas.groups, weights=q)
            worst = int(np.argmax(per))
            keep = meas.groups != worst
        else:
            per, worst = q, int(np.argmax(q))
            keep = np.ones(m, bool)
            keep[worst] = False
        dof = int(np.count_nonzero(keep))
        if not (dof >= 2 and float(q[keep].sum()) > _chi2_quantile(dof, self.REFUSED_P_FA)):
            return False, 0.0
        rows = np.bincount(meas.groups) if per is not q else np.ones(m)
        others = np.delete(np.arange(len(per)), worst)
        others = others[rows[others] > 0]
        return True, float(np.sqrt(np.median(per[others] / rows[others])))

    #: an epoch refused wholesale whose typical source is this far out (sigmas, :meth:`epoch_refusal`)
    #: takes no update (:meth:`refused_wholesale`); a refusal nearer than that is a prior somewhat
    #: too sure of itself (seed 003's clean runs, seeds 1-2: 1.8-2.3 sigma at 15-28 epochs; seed
    #: 001's ramp, seeds 1-3: 2.1-2.4 sigma, the main filter having absorbed part of the ramp),
    #: which the update is there to correct
    GROSS_REFUSAL_SIGMA = 5.0

    def refused_wholesale(self, t: float, meas, x: np.ndarray, P: np.ndarray, prior=None) -> bool:
        """Note whether the prior (x, P) refuses this epoch's rows as a whole (:meth:`note_refusal`:
        for ``refused_after_s`` the lifecycle checks the state, then resets it), and whether the
        refusal is gross (the typical source beyond ``GROSS_REFUSAL_SIGMA``): then the epoch takes
        no update (counted ``epoch_refused``). For a pipeline without a gate of its own (the
        tightly coupled families' pseudoranges): an update with every satellite 200 m out dragged
        the biases and the receiver clock along with a corrupted position, and let the MHSS monitor
        exclude good satellites against it, which the reset kept (docs/hardening.md, "A silent
        corruption of the state")."""
        refused, typical = self.epoch_refusal(meas, x, P, prior)
        self.note_refusal(t, refused)
        if refused and typical > self.GROSS_REFUSAL_SIGMA:
            self.mark_screened(t, "epoch_refused", len(meas.z))
            return True
        return False

    #: rows whose innovation is further out than this (standardised) are not the sensor's
    #: spread but a fault, and stay out of its history
    HISTORY_MAX_SIGMA = 5.0

    #: whether a stream's innovations off centre (estimation/consistency.py ``InnovationBias``)
    #: make the pipeline ``degraded`` too: the pipelines whose small gains leave a state a few
    #: aiding sigmas off for minutes (loosely coupled, federated, centralised); the tightly
    #: coupled families refuse such a state wholesale (:meth:`refused_wholesale`), and a biased
    #: satellite is their integrity monitor's business
    bias_test: bool = False

    #: the lifecycle is replaying epochs the pipeline had applied before (``VehicleLife.
    #: _start_replayed``): their rows are not recorded again in the streams' sigma histories nor in
    #: the recording's innovation windows (they were, once, when they came; each epoch counted
    #: once); the restarted consistency windows take them (they were cleared by the restart)
    replaying: bool = False

    def record_rows(self, key: str, meas, claimed, innovation, S_diag, used=None, taken=None) -> None:
        """The rows of an update that passed its screening, into the stream's sigma history and
        its innovation consistency window (innovations ``z - H x`` of the prior and the diagonal
        of their covariance S = H P H' + R; ``used``: the rows the screening passed, those the
        update took and those left out only as suspects of a faulty source (:meth:`source_groups`:
        their innovations are the stream's spread all the same); ``taken``: the rows the update
        took, the only ones the bias test averages (a suspect of a faulty source shares its
        source's fault: averaged, it made the covariance grow towards the fault, and the grown
        covariance let the fault in as a suspect within SUSPECT_SIGMA; tests/test_fix_groups.py);
        default ``used``).

        The rows on Python floats (a handful per update: sqrt, max, abs, the comparison and the
        division give numpy's values, a NaN as numpy treats it), with numpy only for the sum of
        squares (its dot product, whose rounding a Python sum need not share) and the arrays the
        recording keeps: some 25 numpy calls fewer per fix epoch."""
        inn = np.asarray(innovation, dtype=float).tolist()
        S_l = np.asarray(S_diag, dtype=float).tolist()
        R_l = np.asanyarray(meas.R).diagonal().tolist()
        use = None if used is None else np.asarray(used, dtype=bool).tolist()
        lim = self.HISTORY_MAX_SIGMA
        sd = [math.sqrt(max(v, 1e-300)) for v in S_l]  # max(NaN, 1e-300) is NaN, as np.maximum's
        ok = [abs(v) <= lim * d for v, d in zip(inn, sd, strict=True)]
        if use is not None:
            ok = [a and b for a, b in zip(ok, use, strict=True)]
        hph = [v - rv for v, rv in zip(S_l, R_l, strict=True)]
        if not self.replaying:
            claims = np.asarray(claimed, dtype=float).tolist()
            self.floors.record_floats(key, meas.labels, claims, inn, hph, ok)
        ins = getattr(self.bank, "ins", None)
        t = ins.state.t if ins is not None else getattr(self.bank, "t", None)
        used_rows = _all_rows(len(inn)) if used is None else np.asarray(used, dtype=bool)
        r_l = [v / d for v, d in zip(inn, sd, strict=True)]
        r = np.array(r_l, dtype=float)
        if ins is not None and not self.replaying:  # the recording's innovation windows (NIS per row)
            self.innovations.append((t, key, meas.labels, r, used_rows))
        if t is None:
            return
        ru = r if use is None else r[used_rows]
        was = self.consistency.is_failing(key)
        if self.consistency.add(key, t, float(ru @ ru), int(ru.size)):
            self.last_inconsistent_t = t
            if not was:  # counted once per episode, in Health's screened counts
                self.screened["innovations_inconsistent"] += 1
        if self.bias_test:
            was = self.bias.is_failing(key)
            if taken is not None:
                took = np.asarray(taken, dtype=bool).tolist()
            else:
                took = [True] * len(r_l) if use is None else use
            if self.bias.add(key, t, meas.labels, r_l, took):
                self.last_inconsistent_t = t
                if not was:
                    self.screened["innovations_biased"] += 1

    def inflate_for_bias(
        self, key: str, meas, S_diag, P: np.ndarray, P_ref: np.ndarray | None = None
    ) -> np.ndarray | None:
        """The prior covariances ``P`` (members x n x n) inflated where stream ``key``'s rows are
        off centre (:class:`InnovationBias`, after :meth:`record_rows` of this update), or None.

        The mean innovation b of a failing row (the larger of its window's mean and its latest
        span's, ``InnovationBias.recent_s``, standardised, times the row's sqrt(S)) says the
        state is about b off along that row, while its covariance claims v = h P h'. Each member's covariance
        grows by b^2 along the row alone, P + b^2 g g' with g = h' / (h h'): the row's variance
        becomes v + b^2 and nothing else is assumed about where the error came from (growing P
        along P h', the filter's own correlations, moved a velocity that was right with a
        position corrupted alone). The update that follows takes the aiding with the gain the
        evidence supports instead of pulling the state back over minutes (docs/hardening.md,
        "A smaller corruption"). Once per row per bias window (``InnovationBias.window_s``): a
        row still off centre a whole window after its inflation is inflated again. The callers
        inflate only in an update whose screening flagged no row: a stream with a failing row is
        suspect, and growing the covariance towards it would let its fault in. ``P_ref``: the
        covariance the pipeline reports, when its members share it (a federated bank's locals
        hold the fused covariance divided by their shares): member i then grows by b^2 times
        its variance along g over the reference's, so that the fused variance grows by b^2."""
        rows = self.bias.failing().get(key)
        if not rows:
            return None
        t = self._bias_clock()
        labels = list(meas.labels)
        out = None
        for label in rows:
            last = self._inflated_at.get((key, label))
            if last is not None and t is not None and t - last < self.bias.window_s:
                continue
            if label not in labels:  # a row this update does not carry (held, or not sent)
                continue
            j = labels.index(label)
            h = np.asarray(meas.H[j], dtype=float)
            hh = float(h @ h)
            m = max(abs(self.bias.mean(key, label) or 0.0), abs(self.bias.recent_mean(key, label) or 0.0))
            b2 = m * m * float(S_diag[j])
            if not (hh > 0.0 and math.isfinite(b2)):
                continue
            scale = np.ones(P.shape[0])
            if P_ref is not None:
                ref = float(h @ P_ref @ h)
                scale = np.array([float(h @ Pi @ h) / ref if ref > 0.0 else 1.0 for Pi in P])
            out = (P if out is None else out) + (b2 / (hh * hh)) * scale[:, None, None] * np.outer(h, h)[None]
            self._inflated_at[(key, label)] = t
            self.screened["bias_inflation"] += 1
        return out

    def _bias_clock(self) -> float | None:
        ins = getattr(self.bank, "ins", None)
        return ins.state.t if ins is not None else getattr(self.bank, "t", None)

    def record_prior_rows(
        self, key: str, meas, claimed, x: np.ndarray, P: np.ndarray, used=None, taken=None
    ) -> None:
        """:meth:`record_rows` from the prior (x, P) the rows were tested against."""
        r, S = self.prior_rows(meas, x, P)
        self.record_rows(key, meas, claimed, r, S, used, taken)

    #: a stream that fed no update for this long (and for RETURN_GAP_PERIODS of its own
    #: interval) is checked on its return (:meth:`held_on_return`)
    RETURN_GAP_S = 5.0
    RETURN_GAP_PERIODS = 5.0
    #: the returning messages averaged: about RETURN_SPAN_S of them, 2 to 5
    RETURN_SPAN_S = 0.5
    #: after this long held, the stream goes to the gate alone (and its recovery rules)
    RETURN_MAX_S = 10.0
    #: the mean's test: every row of a source within this many sigmas (3: a sound source held
    #: one message longer about once in 370 rows; the per-row gate stays 5)
    RETURN_SIGMA = 3.0

    def held_on_return(
        self, key: str, t: float, meas, x: np.ndarray, P: np.ndarray, screening: bool
    ) -> np.ndarray | None:
        """The rows of an aiding message held, not used, because their stream is back after a
        gap and the mean of its first messages must agree with the filter first (None: none held).

        After an outage the filter's position sigma has grown, and one message of a receiver
        that claims 10 m may be 50 m off (its solution jumping on return) and still pass the
        per-row gate at 4.9 sigma; the filter then takes the jump and keeps part of it for
        minutes (docs/hardening.md, "The jump on return"). One message cannot tell the jump
        from noise; the mean of k of them can: its innovation has the variance H P H' + R / k
        (the filter's error is common to them, the sensor's noise averages). So from the first
        message after the gap, each source of the stream (``meas.groups``: a fix's position
        solution, its velocity) is held until the mean innovation of its rows over the last k
        messages (k ~ RETURN_SPAN_S of the stream's interval, 2 to 5) agrees with the filter
        within RETURN_SIGMA on every row; from then on that source's rows go on to the gate as usual
        (a jumped position does not hold back the receiver's sound velocity). Held rows are
        counted in ``screened["return_check"]`` (the status is ``degraded`` meanwhile). After
        RETURN_MAX_S of holding, the gate and its recovery decide alone. The first message of a
        stream, and every message of a stream at its cadence, are never held; nor is any of a
        pipeline whose screening is off (``screening`` False: no gate, or a fault test that
        refuses nothing, as the paper's unscreened centralised filter). ``x``, ``P``: the prior
        the message is tested against (a federated pipeline's: the owning local filter's).
        The loosely coupled pipeline (so the transfer alignment master) and the federated,
        centralised and underwater ones check; the tightly coupled ones do not (a jump common to
        every pseudorange is a clock step to them, and a single satellite's is their own
        tests')."""
        state = self._returning.get(key)  # a check under way goes on (its sound sources are used)
        if state is None:
            last = self._used_at.get(key)
            if not screening or last is None:
                return None
            if t - last[0] <= max(self.RETURN_GAP_S, self.RETURN_GAP_PERIODS * (last[1] or 0.0)):
                return None
            k = int(min(5, max(2, round(self.RETURN_SPAN_S / last[1]) if last[1] else 2)))
            state = self._returning[key] = (t, deque(maxlen=k), set())
        started, window, released = state
        if not 0.0 <= t - started <= self.RETURN_MAX_S:
            del self._returning[key]
            return None
        H = meas.H
        r = meas.z - H @ x
        groups = meas.groups if meas.groups is not None else np.zeros(len(r), dtype=int)
        if window and window[-1][0].shape != r.shape:  # other rows (a fix without its velocity)
            window.clear()
            released.clear()
        window.append((r, np.diagonal(meas.R).copy()))
        if len(window) == window.maxlen:
            n = len(window)
            mean = sum(w[0] for w in window) / n
            var = np.einsum("ij,jk,ik->i", H, P, H) + sum(w[1] for w in window) / (n * n)
            agree = np.abs(mean) <= self.RETURN_SIGMA * np.sqrt(np.maximum(var, 1e-300))
            released.update(int(g) for g in np.unique(groups) if agree[groups == g].all())
        held = ~np.isin(groups, list(released))
        if not held.any():
            self._returning.pop(key, None)
            return None
        self.mark_screened(t, "return_check", int(held.sum()))
        return held

    def note_used(self, key: str, t: float) -> None:
        """A stream's message fed an update at ``t`` (its cadence, for :meth:`held_on_return`).
        The federated pipelines note every message their fault test judged, used or isolated:
        for them only a stream back after silence is checked."""
        last = self._used_at.get(key)
        interval = last[1] if last is not None else None
        if last is not None and 0.0 < t - last[0] <= self.RETURN_GAP_S:
            interval = t - last[0]
        self._used_at[key] = (t, interval)

    def source_groups(self, key: str, meas) -> np.ndarray | None:
        """The rows' sources (``meas.groups``) for a screening that makes the rest of a failing
        row's source suspect (measurements.base.refused_with_source), or None: the rule of the
        stream's episode of updates with failing rows, set when it began (call
        :meth:`end_source_episode` after the screening). A failing row is evidence of a fault in
        its source only in a stream whose rows are otherwise as good as they claim: the rule
        holds for an episode that began while the stream's innovations had been tested
        consistent (estimation/consistency.py), not otherwise. In a stream whose sigmas are too
        optimistic throughout (a receiver claiming a fifth of its error) failing rows are the
        rule, and refusing the rest of every such fix starved the filter (it diverged on the 5x
        case of tests/test_inspect_nis.py); within a fault episode the suspects' own innovations
        make the window fail, which must not end the rule (the demo's step would be taken through
        its height after a few seconds). The episode is the stream's, not the filter's: a restart
        of the filter keeps it, and a new episode after a restart, before the new window has
        enough rows to be tested, takes the stream's verdict from before the restart
        (``InnovationConsistency.is_consistent``). Found with a forged IMU burst that made the
        pipelines restart from their checkpoint just before or during the demo's receiver step:
        the untested window switched the rule off, the step's height rows were taken, and the
        loosely coupled solution was reported ``aided`` 3-5 vertical sigmas off for 50-60 s."""
        if meas.groups is None:
            return None
        rule = self._source_episode.get(key)
        if rule is None:
            rule = self._source_episode[key] = self.consistency.is_consistent(key)
        return meas.groups if rule else None

    def stream_verdicts(self) -> dict[str, bool]:
        """Per aiding stream, whether its failing rows make the rest of their source suspect now:
        the rule of its fault episode under way (set when the episode began: within the episode the
        suspects' own innovations make the window fail), else its innovation test's verdict. What a
        service taking the vehicle over starts from (HandoverState.stream_records)."""
        out = self.consistency.records()
        out.update({k: bool(v) for k, v in self._source_episode.items() if v is not None})
        return out

    def end_source_episode(self, key: str, flagged_any: bool) -> None:
        """After a screening: an update without failing rows ends the stream's episode."""
        if not flagged_any:
            self._source_episode.pop(key, None)

    def report(self, event: str) -> None:
        """Tell the vehicle's lifecycle what the pipeline's own screening concluded."""
        self._events.append(event)

    def take_events(self) -> list[str]:
        """The events reported since the last call (the lifecycle drains them after an aiding)."""
        if not self._events:
            return self._events
        out, self._events = self._events, []
        return out

    def restarted(self) -> None:
        """The filter was restarted in place (covariance recovery): counts a re-initialisation;
        ``unaided`` until the next aiding."""
        self.reinitialisations += 1
        self.aided_since_start = False
        self.failed = False
        self.consistency.clear()  # the restarted covariance's innovations start a new history
        self.bias.clear()
        self._inflated_at.clear()
        # (a stream's fault episode and its rule stay: the sensor's fault did not end with the
        # filter's restart, :meth:`source_groups`)
        self.last_inconsistent_t = None

    def coast_after_s(self) -> float:
        if self.aiding_period_s is None:
            return self.default_coast_after_s
        return max(self.coast_after_periods * self.aiding_period_s, self.min_coast_after_s)

    def current_status(self, t: float | None) -> str:
        """``initialising`` (no filter, or the INS lost), ``failed``, ``degraded`` (the state is not
        verified by the vehicle's own aiding, or screening refused aiding recently, or a stream's
        innovations were larger than the filter claims recently: estimation/consistency.py), ``unaided``
        (never aided since the start), ``coasting`` (aided before, nothing for longer than
        :meth:`coast_after_s`), ``aided``; "aided" means by an update that observed horizontal
        position or velocity (:meth:`mark_aided`: a star tracker alone leaves the position
        free-inertial)."""
        if self.bank is None or self.lost:
            return "initialising"
        if self.failed:
            return "failed"
        if self.unverified is not None:
            return "degraded"
        t = self.bank.t if t is None else t
        window = self.coast_after_s()
        if self.last_screened_t is not None and t - self.last_screened_t <= window:
            return "degraded"
        if self.last_inconsistent_t is not None and t - self.last_inconsistent_t <= window:
            return "degraded"  # innovations larger than the filter claims: its sigmas understate
        if not self.aided_since_start:
            return "unaided"
        if self.last_nav_aiding_t is None or t - self.last_nav_aiding_t > window:
            return "coasting"
        return "aided"

    @property
    def status(self) -> str:
        return self.current_status(None)

    def start(self, nav: NavState, std: InitStd, *, after_loss: bool = False) -> None:
        """(Re-)initialise from an initial state (``initialise`` builds the filter). A start of a
        pipeline that had been initialised before counts one re-initialisation; ``after_loss``
        says the start follows a loss of the INS (:meth:`mark_lost`). ``unaided`` until aided."""
        restart = self.bank is not None
        self.initialise(nav, std)
        if restart:
            self.reinitialisations += 1
        self.aided_since_start = False
        self.failed = self.lost = False
        self.last_aiding_t = self.last_nav_aiding_t = self.last_screened_t = self.last_inconsistent_t = None
        self._refused_since.clear()  # a new state: its refusals start again
        self.consistency.clear()  # (the streams' fault episodes stay, as in :meth:`restarted`)
        self.bias.clear()
        self._inflated_at.clear()
        self._refused_from = self.refusal_began = None

    def restore_references(self, refs: dict[str, np.ndarray]) -> None:
        """After a restart from a full state (``InitStd.cov`` of every state), the linearisation
        points of its private blocks (receiver clock, ...) as they were."""
        for name, ref in refs.items():
            if name in self.bank.reference and np.shape(self.bank.reference[name]) == np.shape(ref):
                self.bank.reference[name] = np.array(ref, dtype=float, copy=True)

    def keep_private_states(self, old: InsFilterBank | None) -> None:
        """After a restart of the navigation states, the sensors' own states of the bank it
        replaced (receiver clock, DVL offset and scale, correlated GNSS error, ...: estimates,
        references and their covariance block): what corrupted the INS did not touch them. Banks
        of another layout (or an MHSS bank, whose members and cross blocks restart) keep the
        model's prior."""
        new = self.bank
        if old is None or new is None or type(old) is not InsFilterBank or type(new) is not InsFilterBank:
            return
        if old.n != new.n or old.B != new.B or new.n == em.N_STATES:
            return
        k = em.N_STATES
        Pp = old.P[:, k:, k:]
        if not np.all(np.isfinite(Pp)) or not np.all(np.isfinite(old.x[:, k:])):
            return
        for name, ref in old.reference.items():
            new.reference[name] = np.array(ref, dtype=float, copy=True)
        new.x[:, k:] = old.x[:, k:]
        new.P[:, k:, k:] = Pp
        new.P[:, :k, k:] = 0.0
        new.P[:, k:, :k] = 0.0

    @classmethod
    def sensor_kinds(cls) -> frozenset[str]:
        """Sensor kinds this pipeline kind can consume (its configuration is checked against it)."""
        return frozenset()

    def consumed_kinds(self) -> frozenset[str]:
        """Sensor kinds this configured pipeline uses (the engine counts and warns once about a
        kind that reaches a pipeline not using it); default: every kind its family can consume."""
        return self.sensor_kinds()

    @classmethod
    def config_errors(cls, cfg) -> list[tuple[str, str]]:
        """(field inside the pipeline's config, message) for options this kind does not
        implement; checked when the configuration is loaded (``service.pipelines.config_errors``)."""
        return []

    @abstractmethod
    def initialise(self, nav: NavState, std: InitStd) -> None: ...

    def push_imu(self, dtheta_rad, dvel_mps, dt_s: float, t_end: float | None = None) -> None:
        """One IMU interval through the pipeline's own minor loop (tests and single pipelines)."""
        self.bank.push_imu(dtheta_rad, dvel_mps, dt_s, t_end)

    def advance(self, pre) -> None:
        """Apply a preintegrated IMU interval shared by all pipelines of the vehicle (the
        engine's path; ``push_imu`` is the per-pipeline equivalent)."""
        self.bank.advance(pre)

    def sync(self) -> None:
        """Bring the filter to the INS time (pending minor-loop increments, propagation)."""
        self.bank.sync()

    @abstractmethod
    def apply(self, kind: str, sensor_id: str, msg: WireModel, dt_late_s: float = 0.0) -> list[WireModel]:
        """Apply an aiding measurement at the current INS time; return extra output messages."""

    @abstractmethod
    def estimate(self) -> Estimate: ...

    # --- several IMU nodes (transfer alignment, seed 002); defaults: one IMU stream ---------------
    def node_imu_ids(self) -> frozenset[str]:
        """IMU sensor ids this pipeline consumes as nodes: the engine routes their samples to
        :meth:`push_node_imu` and never to the vehicle's INS."""
        return frozenset()

    #: True: the engine also hands every accepted INS-driving IMU sample to :meth:`push_imu_sample`
    wants_imu_samples: bool = False

    def push_node_imu(self, sensor_id: str, msg) -> None:
        """A node IMU sample (accepted by the engine's rules for its key)."""
        return None

    def push_imu_sample(self, msg) -> None:
        """An INS-driving IMU sample, after the vehicle's INS took it."""
        return None

    def epoch_outputs(self) -> list[WireModel]:
        """Extra messages at an output epoch (published by the engine's sink)."""
        return []

    def recover_covariance(self) -> None:
        """Numerical-health recovery after a covariance lost positive definiteness.

        Pipelines reset their covariances to the initial ones (keeping the INS) and call
        :meth:`restarted`; this default marks the pipeline failed.
        """
        self.mark_failed()

    def solution(self, est: Estimate | None = None) -> Solution:
        est = est or self.estimate()
        nav, P = est.nav, est.P9
        # Python floats, as float(v) gives; np.maximum is what np.clip(d, 0.0, None) calls, without
        # its Python wrappers (every output epoch of every vehicle)
        sd = np.sqrt(np.maximum(np.asanyarray(P).diagonal(), 0.0)).tolist()
        # roll, pitch, heading: earth.mat_nb_to_rpy of the entries of earth.quat_to_mat it reads
        # (the same arithmetic on floats, without the matrix)
        w, x, y, z = nav.q_nb.tolist()
        c21, c20, c22 = 2 * (y * z + w * x), 2 * (x * z - w * y), 1 - 2 * (x * x + y * y)
        c01, c11 = 2 * (x * y - w * z), 1 - 2 * (x * x + z * z)
        rpy = (math.atan2(-c20, c22), math.asin(max(-1.0, min(1.0, c21))), math.atan2(-c01, c11))
        # attitude sigma: roll/pitch/heading from the misalignment sigmas (small-angle reading)
        level = math.degrees(max(sd[6], sd[7]))
        return Solution(
            t=nav.t,
            pipeline=self.name,
            lat_deg=math.degrees(nav.lat_rad),
            lon_deg=(math.degrees(nav.lon_rad) + 180.0) % 360.0 - 180.0,
            height_m=nav.h_m,
            vel_enu_mps=tuple(nav.vel_enu_mps.tolist()),
            rpy_deg=tuple(earth.rpy_msg_deg(rpy)),
            pos_std_enu_m=tuple(sd[0:3]),
            vel_std_enu_mps=tuple(sd[3:6]),
            rpy_std_deg=(level, level, math.degrees(sd[8])),
            # (the divisions on floats: the same elementwise operation as numpy's)
            gyro_bias_dph=tuple([v / earth.DPH for v in np.asarray(nav.gyro_bias_rps, float).tolist()]),
            accel_bias_ug=tuple([v / earth.UG for v in np.asarray(nav.accel_bias_mps2, float).tolist()]),
            status=self.current_status(nav.t),
        )


__all__ = ["Estimate", "InitStd", "Pipeline", "initial_covariance"]
