"""One vehicle's life: how its pipelines start, are verified, fall under suspicion and are reset.

Every start, check and reset of a vehicle's navigation goes through :class:`VehicleLife` (the
engine owns one per vehicle and calls it at the points below); the maths of an initial state is
in :mod:`service.ins.alignment`, the status a pipeline reports is the pipeline's own
(:meth:`service.pipelines.base.Pipeline.current_status`).

Stages of each pipeline (``Life.stage``) and the events that move it (``TRANSITIONS``; every
transition is recorded in ``VehicleLife.history``)::

    initialising --start------------> aligned        first InitialNav, coarse alignment, restart
    initialising --hand_over--------> aligned        another service's last state (unverified)
    aligned      --aided------------> aided          first accepted aiding of a verified start
    aligned      --verified---------> aided          an unverified start agreed with own aiding
    aligned      --reset------------> aligned        an unverified start disagreed: own reference
    aided        --suspect----------> suspect        evidence that the state may be wrong
    suspect      --verified---------> aided          own aiding agrees again
    suspect      --reset------------> aligned        own aiding disagrees: restart from it
    aligned|aided|suspect --init_reset|hand_over-->  aligned (unverified): a checked reset request
    aligned|aided|suspect --restart-> aligned        failed pipeline restarted (sibling or fix)
    any          --lost-------------> initialising   IMU gap, time jump: the INS is lost

``aided`` covers the statuses aided and coasting (the pipeline's timing decides which).

Verification. A start from the vehicle's own sensors (an alignment, a restart from its own fix,
the first InitialNav confirmed by the first fix) is verified. A start from a source the service
cannot check at that moment (a hand-over from another service, an InitialNav that resets a
running vehicle) is *unverified*: the pipeline reports ``degraded`` until its own aiding agrees
with it: :data:`VERIFY_EPOCHS` consecutive reference epochs (a GNSS fix, or the snapshot fix of a
raw epoch) at which the estimate and the reference agree (chi-square of position and velocity,
:func:`service.ins.alignment.plausible`) and the pipeline's own aiding was accepted; without a
reference (no GNSS), :data:`VERIFY_EPOCHS` accepted aiding updates in a row without screening.
A reference that disagrees with an unverified state resets the pipeline from the reference (the
vehicle's own aiding wins over what it was told).

Hand-over (fleet scale-out): :meth:`VehicleLife.hand_over` starts every pipeline from another
service's last state, or, on a running vehicle, is a reset request checked like an InitialNav.
"""

from __future__ import annotations

import logging
import math
from collections import deque
from dataclasses import dataclass
from typing import TYPE_CHECKING

import numpy as np

from fednav.service.estimation import snapshot
from fednav.service.ins import alignment
from fednav.service.ins.alignment import InitStd
from fednav.service.ins.mechanisation import NavState
from fednav.service.messages import GnssFix, GnssRaw, InitialNav

if TYPE_CHECKING:  # the engine imports this module
    from fednav.service.engine import VehicleEngine
    from fednav.service.pipelines.base import Pipeline

log = logging.getLogger("fednav.service")

INITIALISING, ALIGNED, AIDED, SUSPECT = "initialising", "aligned", "aided", "suspect"
STAGES = (INITIALISING, ALIGNED, AIDED, SUSPECT)
_RUNNING = (ALIGNED, AIDED, SUSPECT)

#: (stage, event) -> next stage: every transition a pipeline's life can make
TRANSITIONS: dict[tuple[str, str], str] = {
    (INITIALISING, "start"): ALIGNED,
    (INITIALISING, "hand_over"): ALIGNED,
    (INITIALISING, "restart"): ALIGNED,
    (ALIGNED, "aided"): AIDED,
    (ALIGNED, "verified"): AIDED,
    (AIDED, "suspect"): SUSPECT,
    (ALIGNED, "suspect"): SUSPECT,
    (SUSPECT, "suspect"): SUSPECT,
    (SUSPECT, "verified"): AIDED,
    **{(s, e): ALIGNED for s in _RUNNING for e in ("start", "reset", "init_reset", "hand_over", "restart")},
    **{(s, "lost"): INITIALISING for s in STAGES},
}

#: consecutive agreeing reference epochs (or clean aiding updates) that verify a state
VERIFY_EPOCHS = 3
#: an InitialNav or hand-over state never claims less than this (ENU m, ENU m/s, rad)
ABS_FLOOR_POS_M = 0.1
ABS_FLOOR_VEL_MPS = 0.01
ABS_FLOOR_ATT_RAD = math.radians(0.005)


@dataclass
class Life:
    """One pipeline's stage, where its last start came from and whether it is verified."""

    stage: str = INITIALISING
    source: str = ""
    verified: bool = True
    reason: str | None = None  # why suspect / unverified
    since: float | None = None  # time of the last transition
    agreeing: int = 0  # consecutive agreeing checks since the last start or suspicion


def floored_std(std: InitStd) -> InitStd:
    """Initial sigmas raised to the absolute floors (no source pins the state to a millimetre)."""
    return InitStd(
        np.maximum(np.asarray(std.pos_enu_m, dtype=float), ABS_FLOOR_POS_M),
        np.maximum(np.asarray(std.vel_enu_mps, dtype=float), ABS_FLOOR_VEL_MPS),
        np.maximum(np.asarray(std.att_rad, dtype=float), ABS_FLOOR_ATT_RAD),
    )


def honest_std(std: InitStd, nav: NavState, ref: NavState | None) -> InitStd:
    """Sigmas of a reset state that cover its disagreement with the state it replaces: per axis
    at least the position and velocity difference (neither can be told right yet)."""
    if ref is None:
        return std
    d = np.abs(alignment.pos_vel_difference(nav, ref))
    return InitStd(np.maximum(std.pos_enu_m, d[:3]), np.maximum(std.vel_enu_mps, d[3:]), std.att_rad)


class VehicleLife:
    """The lifecycle of one vehicle's pipelines (module docstring): the engine calls
    :meth:`on_initial_nav`, :meth:`on_fix`, :meth:`on_raw`, :meth:`try_align`,
    :meth:`before_aiding`, :meth:`after_aiding`, :meth:`on_imu_lost` and :meth:`hand_over`."""

    def __init__(self, engine: VehicleEngine):
        self.engine = engine
        self.config = engine.config
        self.initialised = False
        self.lost = False  # the INS was lost (IMU gap, time jump): the next start follows a loss
        self.align = alignment.ImuAccumulator()
        self.last_fix: GnssFix | None = None
        self.fix_from_raw = False  # last_fix is a snapshot solution of a raw epoch (snapshot.py)
        self.pending_init: InitialNav | None = None  # refused for its time: kept for a time jump
        self.check_first_fix = False  # an InitialNav start not yet confirmed by a GNSS fix
        self.start_t: float | None = None
        self.lives: dict[str, Life] = {p.name: Life() for p in engine.pipelines}
        #: (t, pipeline, from stage, event, to stage) of the latest transitions
        self.history: deque = deque(maxlen=512)

    # --- transitions -------------------------------------------------------------------------------
    def go(self, p: Pipeline, event: str, t: float | None, reason: str | None = None) -> str:
        """Move ``p`` by ``event`` (``TRANSITIONS``); an event its stage does not take is a bug."""
        life = self.lives[p.name]
        to = TRANSITIONS.get((life.stage, event))
        if to is None:
            raise ValueError(f"pipeline {p.name}: no transition from {life.stage!r} on {event!r}")
        self.history.append((t, p.name, life.stage, event, to))
        life.stage, life.since = to, t
        if event in ("start", "hand_over", "init_reset", "reset", "restart", "lost", "suspect"):
            life.agreeing = 0
        if event == "suspect":
            life.reason = reason
        return to

    def _start_one(self, p: Pipeline, nav: NavState, std: InitStd, event: str, verified: bool, reason=None):
        p.start(nav.copy(), std, after_loss=self.lost)
        life = self.lives[p.name]
        self.go(p, event, nav.t, reason)
        life.source, life.verified, life.reason = event, verified, (None if verified else reason or event)
        if verified:
            p.mark_verified()
        else:
            p.mark_unverified(life.reason)

    def start_all(self, nav: NavState, std: InitStd, event: str = "start", verified: bool = True) -> None:
        """Every pipeline starts from ``nav``: the vehicle's clock moves to ``nav.t``."""
        for p in self.engine.pipelines:
            self._start_one(p, nav, std, event, verified)
        self.engine._restart_clock(nav.t)
        self.initialised = True
        self.start_t = nav.t
        self.lost = False

    # --- InitialNav, hand-over ------------------------------------------------------------------------
    def on_initial_nav(self, msg: InitialNav) -> bool:
        """Start (or re-start) from an InitialNav. A re-initialisation of a running vehicle must
        agree with the sensors: with the latest GNSS fix when current, else with the running
        estimate (``alignment.plausible``); otherwise it is refused ``implausible_init``. A first
        start is checked against the first GNSS fix instead (:meth:`_confirm_start`)."""
        if self.config.init.mode not in ("auto", "message"):
            return True
        nav, std = alignment.from_initial_nav(msg)
        if self.initialised:
            ref = self.reference_state(nav.t)
            if ref is not None and not alignment.plausible(nav, ref[0], alignment.std_cov6(std) + ref[1])[0]:
                self.engine.rejected["implausible_init"] += 1
                return False
        self.start_all(nav, std)
        self.check_first_fix = True
        return True

    def hand_over(self, nav: NavState, std: InitStd, source: str) -> bool:
        """Start or restart every pipeline from another service's last state (fleet hand-over).

        ``nav`` at the time the vehicle resumes (before its first IMU sample: that sample's start;
        on a running vehicle within ``[intake] future_window_s`` of its time), ``std`` its 1-sigma
        (position ENU m, velocity ENU m/s, attitude nav-frame rad; raised to the absolute floors),
        ``source`` who sent it (e.g. the other service's id).

        Not initialised: every pipeline starts from it (transition ``hand_over``), unverified:
        its status is ``degraded`` until the vehicle's own aiding agrees with it
        (``VERIFY_EPOCHS`` agreeing reference epochs); a reference that disagrees resets it from
        the vehicle's own sensors. Running: a reset request, checked like an InitialNav against
        the latest fix (else the running estimate); refused (``implausible_handover`` counted,
        False) when they disagree, else every pipeline restarts from it with sigmas that cover the
        difference, unverified as above. Counted in Health notes (``handed_over``); returns
        whether the state was taken."""
        eng = self.engine
        if not (np.all(np.isfinite(nav.llh)) and np.all(np.isfinite(nav.vel_enu_mps))):
            eng.rejected["implausible_handover"] += 1
            return False
        std = floored_std(std)
        if self.initialised:
            t_ins = eng.last_imu_t
            if t_ins is not None and abs(nav.t - t_ins) > self.config.intake.future_window_s:
                eng.rejected["stale_handover"] += 1
                return False
            ref = self.reference_state(nav.t)
            if ref is not None:
                if not alignment.plausible(nav, ref[0], alignment.std_cov6(std) + ref[1])[0]:
                    eng.rejected["implausible_handover"] += 1
                    return False
                std = honest_std(std, nav, ref[0])
            nav = nav.copy()
            nav.t = t_ins if t_ins is not None else nav.t
        self.start_all(nav, std, "hand_over", verified=False)
        self.check_first_fix = False
        eng.notes["handed_over"] += 1
        log.info(
            "vehicle %s: navigation handed over from %s (unverified until its own aiding agrees)",
            eng.vehicle,
            source,
        )
        return True

    # --- the vehicle's own references -----------------------------------------------------------------
    def on_fix(self, fix: GnssFix) -> None:
        """The newest in-sequence GNSS fix (also when not applied: alignment uses it)."""
        self.last_fix = fix
        self.fix_from_raw = False

    def on_raw(self, raw: GnssRaw) -> GnssFix | None:
        """The snapshot least-squares fix of a raw epoch (``snapshot.snapshot_fix``) as the latest
        fix, unless a receiver's own fix is current (that one is better: it models the atmosphere)."""
        own = self.last_fix
        if own is not None and not self.fix_from_raw and alignment.fix_is_current(own, raw.t):
            return None
        fix = snapshot.snapshot_fix(raw)
        if fix is not None:
            self.last_fix, self.fix_from_raw = fix, True
        return fix

    def reference_state(self, t: float) -> tuple[NavState, np.ndarray] | None:
        """An independent position/velocity at ``t`` and its 6x6 covariance: the latest GNSS fix if
        current, else the first running pipeline's estimate."""
        fix = self.last_fix
        if fix is not None and alignment.fix_is_current(fix, t):
            nav, std = alignment.motion_alignment(fix, t)
            return nav, alignment.std_cov6(std)
        p = self.running_pipeline(t)
        if p is None:
            return None
        p.sync()
        est = p.estimate()
        return est.nav, est.P9[:6, :6]

    def running_pipeline(self, t: float) -> Pipeline | None:
        """The first pipeline with a usable estimate (not initialising, not failed)."""
        usable = (p for p in self.engine.pipelines if p.current_status(t) not in ("initialising", "failed"))
        return next(usable, None)

    # --- alignment ------------------------------------------------------------------------------------
    def try_align(self) -> None:
        """Coarse alignment from the latest GNSS fix and the IMU data so far, when ``[init] mode``
        allows it: in motion (fix speed >= ``min_speed_mps``), or static after ``align_time_s``."""
        mode = self.config.init.mode
        t = self.engine.last_imu_t
        if self.initialised or mode == "message" or t is None:
            return
        fix = self.last_fix
        if fix is None or not alignment.fix_is_current(fix, t):
            return
        speed = alignment.fix_speed(fix)
        if mode in ("auto", "gnss_motion") and speed >= self.config.init.min_speed_mps:
            self.start_all(*alignment.motion_alignment(fix, t))
            return
        if (
            mode in ("auto", "static")
            and self.align.covers(t, self.config.init.align_time_s)
            and speed < alignment.STATIC_MAX_SPEED_MPS
        ):
            sg, sa = self.config.imu.bias_sigmas()
            aligned = alignment.static_alignment(self.align, fix, t, sg, sa)
            if aligned is not None:  # else not static: wait for motion initialisation
                self.start_all(*aligned)

    # --- around an aiding epoch ---------------------------------------------------------------------------
    def before_aiding(self, kind: str, msg) -> None:
        """At an aiding epoch, before the pipelines take the message: the first fix confirms an
        InitialNav start; failed pipelines restart."""
        if kind == "gnss_fix":
            if self.check_first_fix:
                self._confirm_start(msg)
            self._restart_failed(msg)
        elif kind == "gnss_raw" and (self.check_first_fix or any(p.failed for p in self.engine.pipelines)):
            fix = self.on_raw(msg)
            if fix is not None:
                if self.check_first_fix:
                    self._confirm_start(fix)
                self._restart_failed(fix)

    def after_aiding(self, kind: str, msg, t: float) -> None:
        """After the pipelines took an aiding message at the INS time ``t``: stage moves (first
        aiding, verification of an unverified state against the vehicle's own reference, reset
        when they disagree)."""
        ref = None
        for p in self.engine.pipelines:
            life = self.lives[p.name]
            if life.stage == ALIGNED and life.verified:
                if p.aided_since_start:
                    self.go(p, "aided", t)
                continue
            if life.stage not in (ALIGNED, SUSPECT) or p.failed or p.lost:
                continue
            if ref is None:
                ref = self._epoch_reference(kind, msg, t)
            self._check(p, life, ref, t)

    def _epoch_reference(self, kind: str, msg, t: float):
        """(NavState, 6x6 covariance) of this aiding epoch's own GNSS reference, or False."""
        fix = None
        if kind == "gnss_fix":
            fix = msg
        elif kind == "gnss_raw":
            last = self.last_fix
            fix = last if self.fix_from_raw and last is not None and last.t == msg.t else self.on_raw(msg)
            fix = fix or self.last_fix  # a receiver's own current fix
        if fix is None or not alignment.fix_is_current(fix, t):
            return False
        nav, std = alignment.motion_alignment(fix, t)
        return nav, alignment.std_cov6(std), fix

    def _check(self, p: Pipeline, life: Life, ref, t: float) -> None:
        """An unverified or suspect pipeline against this epoch's reference (``ref`` False: none)."""
        if ref is False:  # no GNSS here: the pipeline's own screening is the check
            if p.last_aiding_t == t and p.last_screened_t != t:
                life.agreeing += 1
            elif p.last_screened_t == t:
                life.agreeing = 0
        else:
            p.sync()
            est = p.estimate()
            ok, _ = alignment.plausible(est.nav, ref[0], est.P9[:6, :6] + ref[1])
            if not ok:
                self._reset_from_reference(p, ref[2], t)
                return
            if p.last_aiding_t == t:
                life.agreeing += 1
        if life.agreeing >= VERIFY_EPOCHS:
            life.verified, life.reason = True, None
            p.mark_verified()
            self.go(p, "verified", t)

    def _reset_from_reference(self, p: Pipeline, fix: GnssFix, t: float) -> None:
        """Restart ``p`` from the vehicle's own fix (in-motion alignment; static: attitude kept)."""
        nav, std = self._fix_state(p, fix, t)
        self.engine.notes[f"reset:{p.name}"] += 1
        self._start_one(p, nav, std, "reset", verified=True)

    def _fix_state(self, p: Pipeline, fix: GnssFix, t: float) -> tuple[NavState, InitStd]:
        if alignment.fix_speed(fix) >= self.config.init.min_speed_mps:
            return alignment.motion_alignment(fix, t)
        est = p.estimate()
        nav, std = alignment.motion_alignment(fix, t)
        att_std = np.sqrt(np.clip(np.diagonal(est.P9)[6:9], 0.0, None))
        return alignment.nav_at_fix(fix, est.nav.rpy_rad, t), InitStd(std.pos_enu_m, std.vel_enu_mps, att_std)

    def _confirm_start(self, fix: GnssFix) -> None:
        """The first GNSS fix after an InitialNav start: an InitialNav that disagrees with it
        (``alignment.plausible`` against the estimate) is counted ``implausible_init`` and the
        pipelines restart from the fix (in motion: its velocity track; else the attitude kept)."""
        self.check_first_fix = False
        p = self.running_pipeline(fix.t)
        if p is None:
            return
        p.sync()
        est = p.estimate()
        nav_fix, std_fix = alignment.motion_alignment(fix, est.nav.t)
        ok, _ = alignment.plausible(est.nav, nav_fix, est.P9[:6, :6] + alignment.std_cov6(std_fix))
        if ok:
            return
        self.engine.rejected["implausible_init"] += 1
        if alignment.fix_speed(fix) < self.config.init.min_speed_mps:  # keep the attitude
            nav_fix = alignment.nav_at_fix(fix, est.nav.rpy_rad, est.nav.t)
            att_std = np.sqrt(np.clip(np.diagonal(est.P9)[6:9], 0.0, None))
            std_fix = InitStd(std_fix.pos_enu_m, std_fix.vel_enu_mps, att_std)
        self.lost = False
        self.start_all(nav_fix, std_fix)
        self.check_first_fix = False

    def _restart_failed(self, fix: GnssFix) -> None:
        """Failed pipelines restart from a running sibling's estimate, else (in motion) from the fix."""
        failed = [p for p in self.engine.pipelines if p.failed]
        if not failed:
            return
        ref = self.running_pipeline(fix.t)
        if ref is not None:
            ref.sync()
            est = ref.estimate()
            sd = np.sqrt(np.clip(np.diagonal(est.P9), 0.0, None))
            nav, std = est.nav.copy(), InitStd(sd[0:3], sd[3:6], sd[6:9])
        elif alignment.fix_speed(fix) >= self.config.init.min_speed_mps:
            nav, std = alignment.motion_alignment(fix, self.engine.last_imu_t)
        else:
            return
        for p in failed:
            p.start(nav.copy(), std, after_loss=True)
            life = self.lives[p.name]
            self.go(p, "restart", nav.t)
            life.source, life.verified, life.reason = "restart", True, None
            p.mark_verified()

    # --- loss of the INS ---------------------------------------------------------------------------
    def on_imu_lost(self, t: float, reason: str) -> None:
        """An IMU gap or a confirmed time jump: the INS is lost; re-initialised from a current
        InitialNav (one refused for its time is kept for this) or the next alignment."""
        self.lost = True
        self.initialised = False
        self.align = alignment.ImuAccumulator()
        for p in self.engine.pipelines:
            p.mark_lost()
            self.go(p, "lost", t)
        if reason == "time_jump":  # a new time base: nothing of the old one applies
            self.last_fix = None
        init, self.pending_init = self.pending_init, None
        if init is not None and abs(init.t - t) <= self.config.intake.future_window_s:
            self.on_initial_nav(init)


__all__ = [
    "ABS_FLOOR_ATT_RAD",
    "ABS_FLOOR_POS_M",
    "ABS_FLOOR_VEL_MPS",
    "AIDED",
    "ALIGNED",
    "INITIALISING",
    "STAGES",
    "SUSPECT",
    "TRANSITIONS",
    "VERIFY_EPOCHS",
    "Life",
    "VehicleLife",
    "floored_std",
    "honest_std",
]
