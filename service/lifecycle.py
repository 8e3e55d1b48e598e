"""One vehicle's life: how its pipelines start, are verified, fall under suspicion and are reset.

Every start, check and reset of a vehicle's navigation goes through :class:`VehicleLife` (the
engine owns one per vehicle and calls it at the points below); the maths of an initial state is
in :mod:`service.ins.alignment`, the status a pipeline reports is the pipeline's own
(:meth:`service.pipelines.base.Pipeline.current_status`).

Stages of each pipeline (``Life.stage``) and the events that move it (``TRANSITIONS``; every
transition is recorded in ``VehicleLife.history``)::

    initialising --start------------> aligned        first InitialNav, coarse alignment, restart
    initialising --hand_over--------> aligned        another service's last state (unverified)
    initialising --recover----------> aligned        the INS lost for a moment (IMU gap, a run of
                                                     samples behind it): each pipeline's last
                                                     verified state carried over the gap
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
vehicle's own aiding wins over what it was told). A reference is a fix its stream confirms (it
agrees with one of the two fixes before it) with its sigmas floored by what the stream claimed
before: a forged fix between genuine ones, or one claiming 1e-9 m, never resets anything.

Suspicion (evidence that a running state may be wrong): a contested IMU key
(:data:`CONTESTED_IMU` refusals: a second publisher's samples may have been taken), a contested
aiding key (two different messages for one epoch: neither publisher's used for
:data:`CONTESTED_AIDING_HOLD_S`, :meth:`VehicleLife.on_aiding_contested`), aiding the
pipeline refuses wholesale (its own screening: ``Pipeline.report("aiding_refused")``; refused
again, ``aiding_still_refused``: reset at the next reference whatever the check says). A suspect
pipeline is ``degraded`` and checked like an unverified one. Suspect for a contested key, at a
reference epoch: if the INS took intervals other than the verified stream's, the pipeline is
replayed from its checkpoint at once, whether or not the reference disagrees yet (forged samples
close to the genuine ones leave a state the fixes agree with for a while:
:meth:`VehicleLife._replay_forged`).

Reset: the whole state, with an honest covariance (:meth:`VehicleLife._fix_state`): velocity from
the reference, attitude from gravity and the GNSS track, position from the pipeline's last
verified estimate (a checkpoint kept at output epochs) carried to now when the moment of the
corruption is known, else the reference's; the biases and the sensors' own states (receiver
clock, DVL offset and scale, ...) kept. After a contested IMU key (the moment of the corruption
known): the last verified state restarted whole and run forward with the verified stream's own
IMU intervals and the aiding between them (:meth:`VehicleLife._replayed`: the engine keeps what
reached a verdict, taken or refused), when they are there whole and the reference agrees;
else that state carried over the gap, whole (velocity, attitude, biases, clock and their
correlations), when the reference agrees with it; else as above with the attitude of that
carried state (the INS's last interval may hold a forged sample). Without GNSS the carried
checkpoint is the reference. An INS lost for a moment restarts the same way (replayed, else
carried). A tightly coupled pipeline's satellite exclusions survive the reset
(a satellite is re-admitted only after its health tests pass against the new filter for
``readmit_after_s``: ``MhssMonitor.restart_windows``). Every transition is said on the pipeline's
Faults (subsystem ``lifecycle``) and counted in Health notes.

Reset requests (an InitialNav on a running vehicle, a hand-over): rate-limited, floored, checked
against the latest fix and the verified estimate, then weighed against each verified pipeline's
state (:func:`fuse`) instead of replacing it.

Hand-over (fleet scale-out): :meth:`VehicleLife.hand_over` starts every pipeline from another
service's last state, or, on a running vehicle, is a reset request checked like an InitialNav.
"""

from __future__ import annotations

import copy
import logging
import math
from collections import deque
from dataclasses import dataclass
from typing import TYPE_CHECKING

import numpy as np

from fednav.service import earth
from fednav.service.estimation import snapshot
from fednav.service.estimation.ins_filter import InsFilterBank
from fednav.service.estimation.integrity.ins_bank import MhssInsBank
from fednav.service.estimation.integrity.mhss import BankState, MhssBank
from fednav.service.ins import alignment
from fednav.service.ins import error_model as em
from fednav.service.ins.alignment import InitStd
from fednav.service.ins.mechanisation import Ins, NavState
from fednav.service.messages import Faults, GnssFix, GnssRaw, InitialNav, ObservationFault, SubsystemFaults

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
    (INITIALISING, "recover"): ALIGNED,
    (ALIGNED, "aided"): AIDED,
    (ALIGNED, "verified"): AIDED,
    (AIDED, "suspect"): SUSPECT,
    (ALIGNED, "suspect"): SUSPECT,
    (SUSPECT, "suspect"): SUSPECT,
    (SUSPECT, "verified"): AIDED,
    **{(s, e): ALIGNED for s in _RUNNING for e in ("start", "reset", "init_reset", "hand_over", "restart")},
    **{(s, "lost"): INITIALISING for s in STAGES},
}

#: restarts of a running pipeline that keep its sensors' own states (clock, DVL offsets, ...)
_KEEPS_SENSOR_STATES = frozenset({"reset", "recover", "init_reset", "hand_over"})
#: transitions said on the pipeline's Faults (subsystem ``lifecycle``)
_SAID = frozenset({"suspect", "reset", "recover", "init_reset", "hand_over", "verified"})
#: consecutive agreeing reference epochs (or clean aiding updates) that verify a state
VERIFY_EPOCHS = 3
#: the unverified reason of a hand-over whose old owner's screening was refusing aiding
HAND_OVER_SCREENING = "hand_over_screening"
#: unverified states whose disagreement with a fix is judged by the pipeline's own screening, not
#: a reset onto the fix: a recovery from a checkpoint, a hand-over during a fault
_OWN_SCREENING_JUDGES = frozenset({"recover", HAND_OVER_SCREENING})
#: IMU refusals that mean a second publisher under the INS's key: samples slipped between the
#: genuine ones or replayed (some of them may have been taken: the INS is suspect)
CONTESTED_IMU = frozenset({"overlap", "time_backwards", "duplicate"})
#: InitialNav reset requests of a running vehicle taken at most once per this interval (s)
INIT_RESET_INTERVAL_S = 10.0
#: InitialNav sigmas kept as the host's history (their median floors a reset request's sigmas)
INIT_HISTORY = 16
#: a pipeline's verified estimates kept (at output epochs) for a reset that needs the last good
#: position: at most this old when used (s)
CHECKPOINT_MAX_AGE_S = 5.0
#: a restart carried over the gap during a contested IMU is kept as a checkpoint (carried again by
#: the next reset) while the verified checkpoint it descends from is at most this old (s): the
#: carry's turn-rate allowance is learnt from the vehicle's recent motion and does not hold for
#: long (a 30 s race through the gnss family's turns, carried throughout: 15.6 m, 'aided' beyond
#: 3 sigma at 569 epochs against 290 clean; docs/hardening.md, "A forger racing the IMU in real time")
CARRY_CHAIN_MAX_S = 10.0
#: two publishers on the IMU's own time stamps (:meth:`VehicleLife._referee_contest`): a candidate
#: stream agrees with the last verified state carried over the contest when its attitude is within
#: this chi-square(3) quantile of the carry's (1e-6)
CONTEST_AGREE_CHI2_3DOF = 30.66
#: ... and the differences it absorbs into the covariance along a chain of such restarts, at most
#: (attitude deg, velocity m/s, position m): beyond, the small-angle error model no longer holds
CONTEST_ABSORB_MAX = (5.0, 2.0, 20.0)
CHECKPOINTS = 8
#: ... one kept at most every this often (s; the cost of a copy of the filter at output epochs)
CHECKPOINT_PERIOD_S = 0.1
#: older than the newest ``CHECKPOINTS``, one kept per this long, up to ``CHECKPOINT_MAX_AGE_S``
#: behind the newest (:func:`_thin`): a contest noticed late (a second publisher's copies 1.4 s
#: behind the IMU) drops the checkpoints since its first copy, and the newest eight span 0.8 s
CHECKPOINT_OLD_SPACING_S = 1.0
#: an aiding key on which two publishers said different things for one epoch (a duplicate that
#: differs from the message taken) is used again only after this long without such a pair (s)
CONTESTED_AIDING_HOLD_S = 10.0
#: checkpoints this close before a contested IMU sample are not trusted (s)
CONTESTED_GUARD_S = 0.1
#: a carried checkpoint moves on with the acceleration and turn rate its INS had then; what the
#: vehicle may have changed of them over the gap is the RMS change between consecutive
#: checkpoints in the last ``CARRY_HISTORY_S`` of verified navigation (its own dynamics, with
#: its IMU's noise), never less than these floors (1-sigma; m/s^2 and deg/s). The largest change
#: instead was tried (docs/hardening.md, "New seeds 70 and 80"): the gnss family's tightly coupled
#: filter recovered faster after a burst at a roll-out's end, the demo's MHSS filter slower.
CARRY_ACC_FLOOR_MPS2 = 0.02
CARRY_TURN_FLOOR_DPS = 0.02
CARRY_HISTORY_S = 60.0
#: ... and before any history: (m/s^2, deg/s)
CARRY_ACC_DEFAULT_MPS2 = 0.5
CARRY_TURN_STD_DPS = 3.0
#: a GNSS fix is this epoch's reference when at most this far from it in time (s): an older one
#: carried forward says nothing reliable about the velocity of an accelerating vehicle
REFERENCE_MAX_AGE_S = 0.05
#: a GNSS stream's fixes confirm each other when at most this far apart (s)
REFERENCE_CHAIN_MAX_S = 2.0
#: acceleration change two consecutive fixes may hide (m/s^2): a manoeuvring vehicle's fixes
#: still confirm each other, a forged one hundreds of metres away does not
REFERENCE_CHAIN_ACC_MPS2 = 10.0
#: ... and motion between two position-only fixes (m/s)
REFERENCE_CHAIN_SPEED_MPS = 100.0
#: a checkpoint's carried position and a fix disagree beyond this chi-square(3) quantile (1e-6)
POSITION_CHI2_3DOF = 30.66
#: chi-square of 4 degrees of freedom at 1e-6 (velocity and heading: :meth:`VehicleLife._own_motion`)
VEL_HEADING_CHI2_4DOF = 33.38
#: acceleration the trapezoid of two velocities may miss when a checkpoint's position is
#: carried to the reset time (m/s^2): the position sigma grows by 1/2 this x dt^2
CARRY_ACC_STD_MPS2 = 0.5
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
    checked_t: float | None = None  # time of the last check (one per aiding epoch)
    force_reset: bool = False  # its aiding keeps being refused: reset at the next reference
    started_t: float | None = None  # time of the last start of the pipeline
    #: suspect since a moment that is known (a contested IMU key, the first epoch of a run of
    #: wholesale refusals): its checkpoints from before it are good states to carry over the gap
    moment_known: bool = False
    #: the time of the verified checkpoint its newest checkpoint was carried from, when that one is
    #: a carried restart kept during a contested IMU (:meth:`VehicleLife._reset_from_reference`)
    carried_root_t: float | None = None
    #: (time of its newest checkpoint, the differences absorbed since the verified one it descends
    #: from, (9,)) when that checkpoint is an absorbed contest (:meth:`VehicleLife._referee_contest`)
    absorbed: tuple[float, np.ndarray] | None = None


def floored_std(std: InitStd) -> InitStd:
    """Initial sigmas raised to the absolute floors (no source pins the state to a millimetre)."""
    return InitStd(
        np.maximum(np.asarray(std.pos_enu_m, dtype=float), ABS_FLOOR_POS_M),
        np.maximum(np.asarray(std.vel_enu_mps, dtype=float), ABS_FLOOR_VEL_MPS),
        np.maximum(np.asarray(std.att_rad, dtype=float), ABS_FLOOR_ATT_RAD),
    )


def shifted(nav: NavState, d_enu_m: np.ndarray, rot_nav: np.ndarray | None = None) -> NavState:
    """``nav`` moved by an ENU offset (m) and turned by a nav-frame rotation vector (rad)."""
    out = nav.copy()
    dllh = earth.enu_m_to_llh_delta(np.asarray(d_enu_m, dtype=float), nav.lat_rad, nav.h_m)
    out.lat_rad, out.lon_rad, out.h_m = nav.lat_rad + dllh[0], nav.lon_rad + dllh[1], nav.h_m + dllh[2]
    if rot_nav is not None:
        c = earth.quat_to_mat(earth.rotvec_to_quat(rot_nav)) @ nav.mat_nb
        out.q_nb = earth.mat_to_quat(c)
    return out


def attitude_difference(a: NavState, b: NavState) -> np.ndarray:
    """The nav-frame rotation vector (rad) that turns b's attitude into a's."""
    return earth.quat_to_rotvec(earth.mat_to_quat(a.mat_nb @ b.mat_nb.T))


def fuse(est: NavState, P: np.ndarray, refs: dict, req: NavState, req_std: InitStd):
    """A reset request weighed against a verified running solution instead of replacing it (no
    claimed certainty pins the state): one Kalman update of the running filter's whole state
    (covariance ``P``: 9x9 of the navigation errors, or every state of a one-member bank with
    its private ``refs``) with the request as a measurement of position, velocity and attitude
    (independent, diagonal ``req_std``). Returns (corrected state, its sigmas with the updated
    covariance ``cov``, corrected private references)."""
    z = np.concatenate([alignment.pos_vel_difference(est, req), attitude_difference(req, est)])
    R = np.diag(np.square(np.concatenate([req_std.pos_enu_m, req_std.vel_enu_mps, req_std.att_rad])))
    P = 0.5 * (P + P.T)
    S = P[:9, :9] + R
    K = np.linalg.solve(S, P[:9, :]).T  # P H' S^-1, H = [I9 0]
    x = K @ z  # estimated errors (computed minus true)
    Pn = P - K @ P[:9, :]
    Pn = 0.5 * (Pn + Pn.T)
    ins = Ins(est, 1.0)
    xi = np.zeros(em.N_STATES)
    xi[: min(em.N_STATES, len(x))] = x[: em.N_STATES]
    ins.correct(xi[em.POS], xi[em.VEL], xi[em.ATT], xi[em.GYRO], xi[em.ACC])
    out_refs = {}
    k = em.N_STATES
    for name, ref in refs.items():  # private blocks in column order after the 15 INS states
        n = np.size(ref)
        out_refs[name] = np.asarray(ref, dtype=float) - x[k : k + n]
        k += n
    sd = np.sqrt(np.clip(np.diagonal(Pn), 0.0, None))
    return ins.state.copy(), InitStd(sd[0:3], sd[3:6], sd[6:9], cov=Pn), out_refs


def publisher_streams(first: list[tuple], other: list[tuple], last: int) -> tuple[list[tuple], list[tuple]]:
    """The two candidate streams of :func:`imu_candidates`' first ``last`` intervals sorted by
    publisher rather than by arrival: of two publishers on the same time stamps, either may be
    first on any slot (a forger racing the genuine IMU is first wherever it catches up), so the
    first-logged copies mix both. What one publisher's copies have in common against the
    other's is the direction of their difference (a forger that moves the state adds a
    systematic offset to what it copies: a zero-mean one averages out): each slot's difference
    is signed by its projection on the slots' principal direction (of the angle or of the
    velocity increments' differences, whichever that direction explains the larger share of),
    and the copies on one side of it form one stream, those on the other side the other.
    Returned with the stream that shares more slots with ``first`` first (the streams are
    ``first`` and ``other`` themselves when no slot's copies swap). :func:`imu_candidates` is
    in ``service.engine``.

    Why: the probe's race on the demo, seed 38 at 10x, through processes: the forger was first on
    the last slot held by two copies at three resets; the referee's choice, the first-logged
    stream against the other publisher's whole stream, kept that forged interval each time
    (0.5 mrad of heading), and the MHSS filter (five satellites) drifted 2.9 m from it
    (docs/hardening.md, "Sorted by publisher")."""
    pairs = [k for k in range(last) if first[k] != other[k]]
    if len(pairs) < 2:
        return first[:last], other[:last]
    D = np.array([np.subtract(first[k][2:8], other[k][2:8]) for k in pairs], dtype=float)
    if not np.all(np.isfinite(D)):
        return first[:last], other[:last]
    best = None
    for blk in (D[:, :3], D[:, 3:]):  # angle and velocity increments: each in its own units
        w, V = np.linalg.eigh(blk.T @ blk)
        share = float(w[-1] / w.sum()) if w.sum() > 0.0 else 0.0
        if best is None or share > best[0]:
            best = (share, blk @ V[:, -1])
    side = best[1] >= 0.0
    if 2 * int(np.count_nonzero(side)) < len(pairs):  # the side that shares more with ``first``
        side = ~side
    a, b = list(first[:last]), list(other[:last])
    for k, keep in zip(pairs, side.tolist(), strict=True):
        if not keep:
            a[k], b[k] = other[k], first[k]
    return a, b


def full_state(p: Pipeline) -> tuple[np.ndarray, dict, np.ndarray | BankState | None] | None:
    """What a full restart of ``p`` restores besides its navigation state: (covariance of every
    state: (n, n) of a one-filter bank (loosely coupled, tightly coupled's MHSS main member), or
    (B, n, n) of each member of a bank (federated locals, IMM models); the private references;
    the members' private error states (B, n - 15), None for a one-filter bank, or the whole MHSS
    bank (:class:`BankState`: every sub-filter's state and covariance, restored around the
    restart's main covariance by :meth:`MhssBank.restored`))."""
    bank = p.bank
    if bank is None:
        return None
    refs = {name: np.array(r, dtype=float, copy=True) for name, r in bank.reference.items()}
    if isinstance(bank, MhssInsBank) or (type(bank) is InsFilterBank and bank.B == 1):
        if np.count_nonzero(bank.x[0]):  # errors not fed back: not a restartable state (as .any())
            return None
        members = bank.mhss.state() if isinstance(bank, MhssInsBank) and bank.mhss.B > 1 else None
        return bank.P[0].copy(), refs, members
    if type(bank) is InsFilterBank and p.restores_members:
        return bank.P.copy(), refs, bank.x[:, em.N_STATES :].copy()
    combined = getattr(p, "combined", None)
    if type(bank) is InsFilterBank and combined is not None:  # an IMM: its combined state, every
        return combined()[1].copy(), refs, None  # model restarting from it (its errors fed back)
    return None


def consistent_fixes(a: GnssFix, b: GnssFix) -> bool:
    """Whether fix ``b`` agrees with the earlier fix ``a`` carried to it by the trapezoid of their
    velocities (``REFERENCE_CHAIN_ACC_MPS2`` of unknown acceleration change; position-only fixes:
    ``REFERENCE_CHAIN_SPEED_MPS`` of unknown motion), chi-square at 1e-6 with their own sigmas."""
    dt = b.t - a.t
    va, vb = a.velocity(), b.velocity()
    na, _ = alignment.motion_alignment(a, a.t)
    nb, _ = alignment.motion_alignment(b, b.t)
    sa, sb = np.square(a.pos_std()), np.square(b.pos_std())
    if va is None or vb is None:
        d = alignment.pos_vel_difference(nb, na)[:3]
        var = sa + sb + (REFERENCE_CHAIN_SPEED_MPS * dt) ** 2
        return float(np.sum(d * d / var)) <= POSITION_CHI2_3DOF
    va, vb = np.asarray(va, dtype=float), np.asarray(vb, dtype=float)
    moved = shifted(na, 0.5 * (va + vb) * dt)
    d = alignment.pos_vel_difference(nb, moved)
    d[3:] = vb - va
    acc = REFERENCE_CHAIN_ACC_MPS2
    var_p = sa + sb + (0.5 * acc * dt * dt) ** 2
    var_v = np.square(a.vel_std()) + np.square(b.vel_std()) + (acc * dt) ** 2
    return float(np.sum(d[:3] ** 2 / var_p) + np.sum(d[3:] ** 2 / var_v)) <= alignment.PLAUSIBILITY_CHI2_6DOF


def _imu_of(p: Pipeline) -> tuple[np.ndarray, np.ndarray] | None:
    """(specific force ENU m/s^2, body rate w_ib rad/s) of ``p``'s INS over its last interval
    (copies), or None without one: kept with a checkpoint, turned into motion only when carried."""
    ins = getattr(p.bank, "ins", None) if p.bank is not None else None
    if ins is None:
        return None
    return np.array(ins.last_fn_mps2, dtype=float), np.array(ins.last_wib_b_rps, dtype=float)


def _motion(imu: tuple[np.ndarray, np.ndarray], nav: NavState) -> tuple[np.ndarray, np.ndarray] | None:
    """(acceleration ENU m/s^2, body turn rate relative to the navigation frame rad/s) of a state
    ``nav`` whose INS measured ``imu`` (:func:`_imu_of`), or None when not finite."""
    f_n, w_ib = imu
    if not (np.all(np.isfinite(f_n)) and np.all(np.isfinite(w_ib))):
        return None
    g = earth.gravity_normal(nav.lat_rad, nav.h_m)
    w_nb = w_ib - nav.mat_nb.T @ earth.earth_rate_n(nav.lat_rad)
    return f_n - np.array([0.0, 0.0, g]), w_nb


def _private_over(p: Pipeline, refs, P: np.ndarray, dt: float):
    """A checkpoint's private states (receiver clock, correlated GNSS error, DVL offset, ...)
    carried over ``dt`` by their own model: references x_ref <- Phi x_ref (a clock's bias moves on
    by its drift: a checkpoint half a second old is tens of metres off in range otherwise), the
    members' private error states likewise, covariance Phi P Phi' + Qd. (refs, P)."""
    bank = p.bank
    if refs is None or bank is None or dt <= 0.0 or P.shape[-1] != bank.n or bank.n == em.N_STATES:
        return refs, P
    refs, privx = refs if isinstance(refs, tuple) else (refs, None)
    Phi_p, Qd_p = bank.private_model(dt)
    Phi = np.eye(bank.n)
    Phi[em.N_STATES :, em.N_STATES :] = Phi_p
    refs = {
        name: (Phi[bank.columns[name], bank.columns[name]] @ r if name in bank.columns else r)
        for name, r in refs.items()
    }
    if isinstance(privx, np.ndarray):  # (an MHSS bank's members: restored around the main's)
        privx = privx @ Phi_p.T
    P = Phi @ P @ Phi.T
    P[..., em.N_STATES :, em.N_STATES :] += Qd_p
    return (refs, privx), P


def _thin(cps: deque) -> None:
    """After a checkpoint is appended to ``cps``: the newest ``CHECKPOINTS`` kept as they come,
    older ones one per ``CHECKPOINT_OLD_SPACING_S``, none more than ``CHECKPOINT_MAX_AGE_S``
    behind the newest (and at most twice as many as that spacing allows, whatever the times).

    Why: the probe's race at 10x through processes (the demo, seed 38): the forger's copies
    reached the loaded service 1.4 s behind the IMU; its first copy dropped every checkpoint
    since its own stamp (:meth:`VehicleLife.on_imu_contested`), the eight newest 0.8 s, so none
    was left to replay or carry: `tc_mhss` reset from the snapshot fix, 4.6 m off, back after
    84 s (docs/hardening.md, "A lagging copy is not a new time base")."""
    k = len(cps) - CHECKPOINTS - 1  # the one that just left the newest eight
    if k >= 1 and cps[k][0] - cps[k - 1][0] < CHECKPOINT_OLD_SPACING_S:
        del cps[k]
    newest = cps[-1][0]
    while cps and newest - cps[0][0] > CHECKPOINT_MAX_AGE_S:
        cps.popleft()
    while len(cps) > CHECKPOINTS + 2 * int(CHECKPOINT_MAX_AGE_S / CHECKPOINT_OLD_SPACING_S):
        cps.popleft()


def carried(nav: NavState, std: InitStd, t: float) -> tuple[NavState, InitStd]:
    """A state moved to time ``t`` with its own velocity, its position sigma grown over the gap."""
    dt = t - nav.t
    if dt == 0.0:
        return nav, std
    out = shifted(nav, np.asarray(nav.vel_enu_mps, dtype=float) * dt)
    out.t = t
    grow = np.square(std.vel_enu_mps * dt) + (0.5 * CARRY_ACC_STD_MPS2 * dt * dt) ** 2
    return out, InitStd(np.sqrt(np.square(std.pos_enu_m) + grow), std.vel_enu_mps, std.att_rad)


def covering(std: InitStd, moved: np.ndarray) -> InitStd:
    """``std`` (with its full ``cov``) widened so that it also covers ``moved``, the shift of
    position, velocity and attitude that a reset request weighed into a verified state made:
    nothing has verified that shift yet, so its square is added to the variances (a request 20 m
    off that the fusion took 0.5 m of otherwise leaves the restarted filter more certain than it
    was and 3 sigma off later: docs/hardening.md, "An InitialNav weighed in")."""
    cov = np.array(std.cov, dtype=float, copy=True)
    i = np.arange(9)
    cov[i, i] += np.square(moved)
    sd = np.sqrt(np.clip(np.diagonal(cov), 0.0, None))
    return InitStd(sd[0:3], sd[3:6], sd[6:9], cov=cov)


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

    #: a fleet member's hook, () -> bool (app.VehicleWorker.resume_from_fleet, set on the instance):
    #: at a loss its checkpoints cannot carry, a state another member served meanwhile is taken at
    #: once, before the next message (a fix in the same drain started the vehicle from its own
    #: alignment first, 14.8 m off in a fleet test, and the state came as a reset request after)
    resume_from_fleet = None
    #: whether the log said the vehicle would re-initialise after a loss
    #: (``VehicleEngine._log_imu_lost``) and not yet that it did (:meth:`start_all` says it)
    restart_untold = False

    def __init__(self, engine: VehicleEngine):
        self.engine = engine
        self.config = engine.config
        self.initialised = False
        self.lost = False  # the INS was lost (IMU gap, time jump): the next start follows a loss
        self.align = alignment.ImuAccumulator()
        self.last_fix: GnssFix | None = None
        self.prev_fix: GnssFix | None = None  # the fix before ``last_fix`` (GNSS acceleration)
        self.fix_from_raw = False  # last_fix is a snapshot solution of a raw epoch (snapshot.py)
        self.pending_init: InitialNav | None = None  # refused for its time: kept for a time jump
        self.check_first_fix = False  # an InitialNav start not yet confirmed by a GNSS fix
        self.start_t: float | None = None
        self.lives: dict[str, Life] = {p.name: Life() for p in engine.pipelines}
        #: (t, pipeline, from stage, event, to stage) of the latest transitions
        self.history: deque = deque(maxlen=512)
        #: sigmas (InitStd) the host's InitialNavs claimed when taken: a reset request's floor
        self.init_sigmas: deque = deque(maxlen=INIT_HISTORY)
        self._recent: dict[str, deque] = {}  # stream -> its latest fixes (references' confirmation)
        self.last_init_reset_t: float | None = None
        #: per pipeline, its latest verified estimates (t, NavState, P9, full state, dynamics) at
        #: output epochs; dynamics: (acceleration ENU m/s^2, body turn rate w_nb rad/s) of its INS
        self.checkpoints: dict[str, deque] = {p.name: deque() for p in engine.pipelines}  # (_thin)
        #: per pipeline, the checkpoint its last replay under a contest left (the verified
        #: stream's alone: a later contested sample does not drop it, :meth:`on_imu_contested`)
        self.replayed_checkpoint: dict[str, tuple] = {}
        #: running (INS) time of the IMU key's last ambiguous refusal: a duplicate that differs
        #: from the sample taken for its time (:meth:`on_imu_contested`)
        self.imu_ambiguous_t: float | None = None
        #: aiding key ("kind/id") -> time of its last contested epoch (:meth:`on_aiding_contested`)
        self.contested_aiding: dict[str, float] = {}
        #: per pipeline, (t, |acceleration change|, |turn rate change|) between its checkpoints
        self.dyn_changes: dict[str, deque] = {p.name: deque() for p in engine.pipelines}

    # --- transitions -------------------------------------------------------------------------------
    def go(self, p: Pipeline, event: str, t: float | None, reason: str | None = None) -> str:
        """Move ``p`` by ``event`` (``TRANSITIONS``); an event its stage does not take is a bug."""
        life = self.lives[p.name]
        to = TRANSITIONS.get((life.stage, event))
        if to is None:
            raise ValueError(f"pipeline {p.name}: no transition from {life.stage!r} on {event!r}")
        self.history.append((t, p.name, life.stage, event, to))
        said = event in _SAID and (event != "suspect" or life.stage != SUSPECT)
        life.stage, life.since = to, t
        if event in ("start", "hand_over", "init_reset", "reset", "restart", "lost", "suspect"):
            life.agreeing = 0
        if to == ALIGNED and event != "verified":
            life.started_t = t
        if event == "suspect":
            life.reason = reason
        if said and t is not None:
            self._say(
                p, t, event if reason is None or event == reason else f"{event}:{reason}", event != "verified"
            )
        return to

    def _say(self, p: Pipeline, t: float, label: str, in_doubt: bool) -> None:
        """The transition on the pipeline's Faults (subsystem ``lifecycle``: isolated while its
        state is in doubt or was replaced, in use again once verified) for subscribers and the
        recording's isolation lanes."""
        row = ObservationFault(label=label, statistic=0.0, threshold=0.0, flagged=in_doubt, isolated=in_doubt)
        msg = Faults(
            t=t,
            pipeline=p.name,
            subsystems=[SubsystemFaults(name="lifecycle", isolated=in_doubt, observations=[row])],
        )
        eng = self.engine
        eng.sink.on_output(eng.vehicle, msg, eng._errors(p, t) if p.bank is not None else None)

    def _start_one(
        self,
        p: Pipeline,
        nav: NavState,
        std: InitStd,
        event: str,
        verified: bool,
        reason=None,
        refs=None,
        event_t: float | None = None,
    ):
        """Restart ``p`` from ``nav`` (``std``) and move it by ``event`` (at ``event_t``, default
        ``nav.t``). With ``refs`` (private references, and the members' private error states for a
        bank of several) and a full ``std.cov`` (every state; per member for a bank of several):
        the whole filter state."""
        self._restore(p, nav, std, event, refs)
        life = self.lives[p.name]
        self.go(p, event, nav.t if event_t is None else event_t, reason)
        life.source, life.verified, life.reason = event, verified, (None if verified else reason or event)
        if verified:
            p.mark_verified()
        else:
            p.mark_unverified(life.reason)

    def _restore(self, p: Pipeline, nav: NavState, std: InitStd, event: str, refs=None) -> None:
        """:meth:`_start_one`'s restart of the filter, without the lifecycle's stage move."""
        old = p.bank
        cov = std.cov
        members = cov is not None and cov.ndim == 3
        p.start(
            nav.copy(),
            InitStd(std.pos_enu_m, std.vel_enu_mps, std.att_rad, cov[0]) if members else std,
            after_loss=self.lost,
        )
        bank = p.bank
        if refs is not None and cov is not None and cov.shape[-1] == bank.n:
            refs, privx = refs if isinstance(refs, tuple) else (refs, None)
            if members and cov.shape[0] == bank.B:  # each member as it was (after the bank's own start)
                bank.P = np.array(cov, dtype=float, copy=True)
                if isinstance(privx, np.ndarray) and privx.shape == bank.x[:, em.N_STATES :].shape:
                    bank.x[:, em.N_STATES :] = privx
            p.restore_references(refs)
            if isinstance(privx, BankState) and isinstance(bank, MhssInsBank) and not members:
                # every sub-filter as it was, around the restart's main covariance (else each
                # starts as a copy of the main: the protection levels fell from 16.4 to 7.0 m at
                # such restarts, docs/hardening.md "The MHSS bank restored whole")
                mh = MhssBank.restored(privx, bank.P[0])
                if mh is not None:
                    bank.mhss = mh
                else:
                    self.engine.notes[f"bank_not_restored:{p.name}"] += 1
        elif event in _KEEPS_SENSOR_STATES:
            p.keep_private_states(old)

    def start_all(
        self,
        nav: NavState,
        std: InitStd,
        event: str = "start",
        verified: bool = True,
        per_pipeline=None,
        source: str = "its own alignment",
    ) -> None:
        """Every pipeline starts from ``nav`` (or ``per_pipeline(p) -> (nav, std, refs)``): the
        vehicle's clock moves to ``nav.t``. After a loss the log said it would re-initialise
        (``VehicleEngine._log_imu_lost``), the log says it did, from ``source``."""
        eng = self.engine
        for p in eng.pipelines:
            p_nav, p_std, refs = (nav, std, None) if per_pipeline is None else per_pipeline(p)
            self._start_one(p, p_nav, p_std, event, verified, refs=refs)
        eng._restart_clock(nav.t)
        self.initialised = True
        self.start_t = nav.t
        self.lost = False
        if self.restart_untold:
            self.restart_untold = False
            if event != "hand_over":  # (the service logs a hand-over itself: app.take_over)
                log.info(
                    "vehicle %s: INS re-initialised at t=%.3f from %s%s",
                    eng.vehicle,
                    nav.t,
                    source,
                    "" if verified else "; degraded until its own aiding verifies it",
                )

    def started_itself_after_loss(self, within_s: float) -> bool:
        """Whether the vehicle runs from its own start after its latest loss (alignment, an
        InitialNav; not a hand-over, a checkpoint carry), begun within ``within_s`` of its time."""
        eng = self.engine
        return (
            self.initialised
            and eng.lost_after_t is not None
            and self.start_t is not None
            and self.start_t > eng.lost_after_t
            and eng.last_imu_t - self.start_t <= within_s
            and all(lf.source == "start" for lf in self.lives.values())
        )

    def how_restarted(self) -> str:
        """What the vehicle went on from at a loss (for the loss's log line)."""
        if not self.initialised:
            return "re-initialising (an InitialNav, or alignment)"
        sources = {lf.source for lf in self.lives.values()}
        if sources == {"hand_over"}:
            return "resumed from another fleet member's state (above), degraded until the aiding verifies it"
        if sources == {"recover"}:
            return "carried over the gap from the last checkpoint, degraded until the aiding verifies it"
        return "restarted from an InitialNav that came meanwhile"

    # --- InitialNav, hand-over ------------------------------------------------------------------------
    def on_initial_nav(self, msg: InitialNav) -> bool:
        """Start from an InitialNav, or on a running vehicle treat it as a reset request
        (:meth:`_init_reset`). A first start is checked against the first GNSS fix
        (:meth:`_confirm_start`)."""
        if self.config.init.mode not in ("auto", "message"):
            return True
        nav, std = alignment.from_initial_nav(msg)
        if self.initialised:
            return self._init_reset(nav, std)
        self.start_all(nav, std, source="an InitialNav")
        self.init_sigmas.append(std)
        self.check_first_fix = True
        return True

    def _init_reset(self, nav: NavState, std: InitStd) -> bool:
        """An InitialNav on a running vehicle: a reset request, never a pin. Taken at most once
        per ``INIT_RESET_INTERVAL_S`` (else ``init_rate_limited``); its sigmas raised to the
        absolute floors and to the median of what the host claimed before (its own history);
        it must agree with the latest GNSS fix when current and with the running estimate
        (``alignment.plausible``, else ``implausible_init``); taken, every pipeline restarts
        from it with sigmas that also cover its difference from the running estimate, unverified
        (``degraded``) until the vehicle's own aiding agrees (``init_reset`` counted in notes)."""
        eng = self.engine
        last = self.last_init_reset_t
        if last is not None and abs(nav.t - last) < INIT_RESET_INTERVAL_S:
            eng.rejected["init_rate_limited"] += 1
            return False
        std = floored_std(std)
        if self.init_sigmas:
            past = self.init_sigmas
            std = InitStd(
                np.maximum(std.pos_enu_m, np.median([s.pos_enu_m for s in past], axis=0)),
                np.maximum(std.vel_enu_mps, np.median([s.vel_enu_mps for s in past], axis=0)),
                np.maximum(std.att_rad, np.median([s.att_rad for s in past], axis=0)),
            )
        if not self._reset_request(nav, std, "init_reset", "implausible_init"):
            return False
        self.last_init_reset_t = nav.t
        self.init_sigmas.append(std)
        eng.notes["init_reset"] += 1
        return True

    def _reset_request(self, nav: NavState, std: InitStd, event: str, refusal: str) -> bool:
        """A state another party asks a running vehicle to take (an InitialNav, a hand-over),
        carried to the INS time with its own velocity. Refused (``refusal`` counted) unless it
        agrees with the latest fix when current and with the running verified estimate. Taken:
        each pipeline whose own state is verified weighs the request against it (:func:`fuse`);
        any other restarts from the request with sigmas that also cover its difference from the
        best reference. Every pipeline is then unverified (``degraded``) until its own aiding
        agrees."""
        eng = self.engine
        eng._advance_all()
        t = eng.last_imu_t
        nav, std = carried(nav, std, t)
        refs = self.references(t)
        for ref_nav, ref_cov in refs:
            if not alignment.plausible(nav, ref_nav, alignment.std_cov6(std) + ref_cov)[0]:
                eng.rejected[refusal] += 1
                return False
        wide = honest_std(std, nav, refs[-1][0]) if refs else std
        for p in eng.pipelines:
            life = self.lives[p.name]
            refs = None
            if life.stage == AIDED and life.verified and not (p.failed or p.lost):
                p.sync()
                est = p.estimate()
                full = full_state(p)
                members = None
                if full is not None and full[0].ndim == 2:
                    P, refs, members = full
                else:
                    P, refs = est.P9, {}
                p_nav, p_std, refs = fuse(est.nav.copy(), P, refs, nav, std)
                if isinstance(members, BankState):
                    # the MHSS bank's sub-filters kept around the restart's main covariance (as at a
                    # restart from a checkpoint), not started as copies of the main: their excess
                    # over it is what the protection levels are made of
                    refs = (refs, members)
                elif not refs:
                    refs = None
                moved = np.concatenate(
                    [alignment.pos_vel_difference(p_nav, est.nav), attitude_difference(p_nav, est.nav)]
                )
                if np.all(np.abs(moved) <= np.sqrt(np.clip(np.diagonal(est.P9), 0.0, None))):
                    # the request agrees with the verified state: nothing to restore, no restart;
                    # degraded until the vehicle's own aiding agrees again (checked like any reset)
                    self.go(p, event, t)
                    life.verified, life.reason = False, event
                    p.mark_unverified(event)
                    continue
                p_std = covering(p_std, moved)  # restarted: unverified, its shift in its sigmas
            else:
                p_nav, p_std = nav, wide
            self._start_one(p, p_nav, p_std, event, verified=False, refs=refs)
        return True

    def hand_over(self, nav: NavState, std: InitStd, source: str, screening: bool = False) -> bool:
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
        whether the state was taken.

        ``screening``: the old owner's screening was refusing aiding when it sent the state (a
        fault under way, ``HandoverState.screening``). A fix that disagrees with the state is then
        as likely that fault as the state is wrong: as after a recovery from a checkpoint, the
        pipelines' own screening judges it (their gates refuse it; a refusal that persists
        wholesale resets them at the next reference) instead of a reset onto it. Why: the demo
        aircraft handed over 4 s into its receiver's 60 m step (refused by the old owner's gate,
        which coasted on its star tracker 1.4 m off through the 15 s) was reset onto the stepped
        fixes and then 'aided' 60-85 m off until the step ended."""
        eng = self.engine
        if not (np.all(np.isfinite(nav.llh)) and np.all(np.isfinite(nav.vel_enu_mps))):
            eng.rejected["implausible_handover"] += 1
            return False
        std = floored_std(std)
        if self.initialised:
            if abs(nav.t - eng.last_imu_t) > self.config.intake.future_window_s:
                eng.rejected["stale_handover"] += 1
                return False
            if not self._reset_request(nav, std, "hand_over", "implausible_handover"):
                return False
        else:
            self.start_all(nav, std, "hand_over", verified=False)
        if screening:
            for p in self.engine.pipelines:
                life = self.lives[p.name]
                if not life.verified:
                    life.reason = HAND_OVER_SCREENING
                    p.mark_unverified(HAND_OVER_SCREENING)
        self.check_first_fix = False
        eng.notes["handed_over"] += 1
        # (the service logs the hand-over once, with the state's age and status: app.take_over)
        log.debug("vehicle %s: navigation handed over from %s (unverified)", eng.vehicle, source)
        return True

    # --- the vehicle's own references -----------------------------------------------------------------
    def on_fix(self, fix: GnssFix, key: str = "gnss_fix") -> None:
        """The newest in-sequence GNSS fix (also when not applied: alignment uses it)."""
        self._new_fix(fix)
        self.fix_from_raw = False
        self._remember(key, fix)

    def _new_fix(self, fix: GnssFix) -> None:
        last = self.last_fix
        if last is not None and fix.t > last.t:
            self.prev_fix = last
        self.last_fix = fix

    def _confirmed_by_stream(self, key: str, fix: GnssFix) -> bool:
        """Whether ``fix`` agrees with one of the two fixes before it on its stream (at most
        ``REFERENCE_CHAIN_MAX_S`` earlier, carried with their velocities: :func:`consistent_fixes`).
        Only such a fix may reset a pipeline: a forged fix between genuine ones (a hostile storm)
        never does. Evaluated only when a reference is needed (nothing in a clean run)."""
        before = [f for f in self._recent.get(key, ()) if 0.0 < fix.t - f.t <= REFERENCE_CHAIN_MAX_S]
        return any(consistent_fixes(f, fix) for f in before[-2:])

    def _floored(self, key: str, fix: GnssFix) -> GnssFix:
        """``fix`` with its sigmas raised to the absolute floors and to half the median of what
        its stream's recent fixes claimed (a reference claiming 1e-9 m must not pin a reset)."""
        recent = [f for f in self._recent.get(key, ()) if f is not fix] or [fix]
        pos = np.maximum(
            np.maximum(np.asarray(fix.pos_std(), dtype=float), ABS_FLOOR_POS_M),
            0.5 * np.median([f.pos_std() for f in recent], axis=0),
        )
        update = {"pos_std_enu_m": tuple(float(v) for v in pos)}
        if fix.velocity() is not None:
            vel = np.maximum(
                np.maximum(np.asarray(fix.vel_std(), dtype=float), ABS_FLOOR_VEL_MPS),
                0.5
                * np.median(
                    [f.vel_std() for f in recent if f.vel_std() is not None] or [fix.vel_std()], axis=0
                ),
            )
            update["vel_enu_mps"] = tuple(float(v) for v in fix.velocity())
            update["vel_std_enu_mps"] = tuple(float(v) for v in vel)
        return fix.model_copy(update=update)

    def _remember(self, key: str, fix: GnssFix) -> None:
        recent = self._recent.get(key)
        if recent is None:
            recent = self._recent[key] = deque(maxlen=4)
        if not recent or fix.t > recent[-1].t:
            recent.append(fix)

    def on_raw(self, raw: GnssRaw) -> GnssFix | None:
        """The snapshot least-squares fix of a raw epoch (``snapshot.snapshot_fix``) as the latest
        fix, unless a receiver's own fix is current (that one is better: it models the atmosphere)."""
        own = self.last_fix
        if own is not None and not self.fix_from_raw and alignment.fix_is_current(own, raw.t):
            return None
        fix = snapshot.snapshot_fix(raw)
        if fix is not None:
            self._new_fix(fix)
            self.fix_from_raw = True
            self._remember("snapshot", fix)
        return fix

    def references(self, t: float) -> list[tuple[NavState, np.ndarray]]:
        """Independent positions/velocities at ``t`` with their 6x6 covariances: the latest GNSS
        fix when current (carried to ``t``: :func:`alignment.fix_reference`), then the estimate
        of the first running pipeline that is verified."""
        out = []
        fix = self.last_fix
        if fix is not None and alignment.fix_is_current(fix, t):
            out.append(alignment.fix_reference(fix, t, self.prev_fix))
        for p in self.engine.pipelines:
            if self.lives[p.name].stage == AIDED and p.current_status(t) not in ("initialising", "failed"):
                p.sync()
                est = p.estimate()
                out.append((est.nav, est.P9[:6, :6]))
                break
        return out

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
            if self.lost and self.align.n:  # a re-alignment: attitude from gravity, last good position
                f_b = self.align.mean_specific_force()
                nav, std = alignment.moving_alignment(fix, t, f_b, self.prev_fix)
                self.start_all(
                    nav,
                    std,
                    per_pipeline=lambda p: self._from_checkpoint(p, nav, std, t),
                    source="its own alignment in motion (a fix, gravity; the last checkpoint's biases)",
                )
            else:
                self.start_all(*alignment.motion_alignment(fix, t), source="a fix's velocity track")
            return
        if (
            mode in ("auto", "static")
            and self.align.covers(t, self.config.init.align_time_s)
            and speed < alignment.STATIC_MAX_SPEED_MPS
        ):
            sg, sa = self.config.imu.bias_sigmas()
            aligned = alignment.static_alignment(self.align, fix, t, sg, sa)
            if aligned is not None:  # else not static: wait for motion initialisation
                self.start_all(*aligned, source="a static alignment")

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

    def after_aiding(self, kind: str, msg, t: float, sensor_id: str = "") -> None:
        """After the pipelines took an aiding message at the INS time ``t``: stage moves (first
        aiding, verification of an unverified state against the vehicle's own reference, reset
        when they disagree)."""
        ref = None
        for p in self.engine.pipelines:
            life = self.lives[p.name]
            for event in p.take_events():  # the pipeline's own screening gave up on its state
                if life.stage in _RUNNING and not (p.failed or p.lost):
                    # (a contested IMU key first: its samples may be in the INS, whose own motion
                    # then dates nothing; the reset starts from the fix's state, as before)
                    dated = p.refusal_began is not None and not (
                        life.stage == SUSPECT and life.reason == "imu_contested"
                    )
                    began = p.refusal_began
                    if not (life.stage == SUSPECT and life.reason == "imu_contested"):
                        # (under a contest the refusal is the contest's: the replay judges it)
                        self.suspect(p, t, "aiding_refused")
                    life.force_reset = event == "aiding_still_refused"
                    if dated and event == "aiding_refused":
                        self._corrupt_since(p, began)
            if life.stage == ALIGNED and life.verified:
                if p.aided_since_start:
                    self.go(p, "aided", t)
                continue
            if life.stage not in (ALIGNED, SUSPECT) or p.failed or p.lost:
                continue
            if ref is None:
                ref = self._epoch_reference(kind, sensor_id, msg, t)
            self._check(p, life, ref, t)

    def _epoch_reference(self, kind: str, sensor_id: str, msg, t: float):
        """(NavState, 6x6 covariance) of this aiding epoch's own GNSS reference, or False."""
        fix, key = None, f"gnss_fix/{sensor_id}"
        if kind == "gnss_fix":
            fix = msg if self._confirmed_by_stream(key, msg) else None
        elif kind == "gnss_raw":
            key = "snapshot"
            fix = snapshot.snapshot_fix(msg)
            if fix is not None:
                self._remember(key, fix)
                if not self._confirmed_by_stream(key, fix):
                    fix = None
        if fix is None or abs(fix.t - t) > REFERENCE_MAX_AGE_S:
            return False
        fix = self._floored(key, fix)
        nav, std = alignment.motion_alignment(fix, t)
        return nav, alignment.std_cov6(std), fix

    def _check(self, p: Pipeline, life: Life, ref, t: float) -> None:
        """An unverified or suspect pipeline against this epoch's reference (``ref`` False: none)."""
        counted = life.checked_t == t  # a second message of this epoch: agreement counted once
        life.checked_t = t
        if ref is False and life.stage == SUSPECT and life.reason == "imu_contested":
            ref = self._carried_checkpoint(p, t)  # no GNSS: the last good state carried over the gap
        if ref is False or ref is None:
            if counted:
                return  # no reference here: the pipeline's own screening is the check
            if p.last_nav_aiding_t == t and p.last_screened_t != t:
                life.agreeing += 1  # (an attitude or a height alone verifies no position)
            elif p.last_screened_t == t:
                life.agreeing = 0
        else:
            if self._replay_forged(p, life, ref, t):
                return
            p.sync()
            est = p.estimate()
            ok, _ = alignment.plausible(est.nav, ref[0], est.P9[:6, :6] + ref[1])
            if not ok and not life.force_reset and life.reason in _OWN_SCREENING_JUDGES:
                # a state recovered from a checkpoint carried over a moment's loss of the IMU: its
                # covariance is honest, and a fix that disagrees beyond it is as likely the faulty
                # one (the demo's receiver step arrived 1.4 s after such a recovery, and a reset
                # onto it was then "verified" by the stepped fixes: 'aided' 84-90 m off). Its own
                # screening decides: rows refused by its gate; a refusal that persists reports
                # aiding_refused (suspect: reset at the next reference). Unverified meanwhile.
                life.agreeing = 0
                return
            if not ok or life.force_reset:
                life.force_reset = False
                if isinstance(ref[2], InitStd):  # the carried checkpoint is the state itself
                    self.engine.notes[f"reset:{p.name}"] += 1
                    plan = self._replay_plan(p, t) if life.reason == "imu_contested" else None
                    if plan is not None:  # with the verified stream's IMU over the gap
                        self._start_replayed(p, *plan, "reset", t)
                    else:
                        self._start_one(
                            p, ref[0], ref[2], "reset", verified=False, reason="reset", refs=ref[3]
                        )
                else:
                    self._reset_from_reference(p, ref[2], t)
                return
            if p.last_nav_aiding_t == t and not counted:
                life.agreeing += 1
        if life.agreeing >= VERIFY_EPOCHS:
            life.verified, life.reason = True, None
            p.mark_verified()
            self.go(p, "verified", t)

    def suspect(self, p: Pipeline, t: float | None, reason: str) -> None:
        """Evidence that ``p``'s state may be wrong: ``degraded`` and checked against the vehicle's
        own reference at every aiding epoch until it agrees (verified) or is reset from it."""
        life = self.lives[p.name]
        if life.stage != SUSPECT:
            self.engine.notes[f"suspect:{p.name}:{reason}"] += 1
        self.go(p, "suspect", t, reason)
        life.verified = False
        life.moment_known = reason == "imu_contested"
        p.mark_unverified(reason, suspect=True)

    def _corrupt_since(self, p: Pipeline, began: float) -> None:
        """``p``'s aiding refused wholesale since ``began`` (its first refused epoch): the state
        went wrong after the aiding epoch before it (a sudden corruption; a slow one passed the
        refusal test until then), so the checkpoints up to that epoch are good states, and a reset
        carries the last of them over the gap, whole, when the fix agrees with it
        (:meth:`_carried_state`), as after a contested IMU key. No checkpoint is kept while a run
        of refusals is under way (:meth:`note_estimate`); the later ones are dropped here.

        Why: a tightly coupled pipeline reset from a snapshot fix of six BeiDou satellites took
        88-100 s to get back under its clean run's 95th percentile (north, up and the receiver
        clock weakly observed: docs/hardening.md, "A silent corruption of the state")."""
        period = p.aiding_period_s or 0.0
        cps = self.checkpoints[p.name]
        while cps and cps[-1][0] > began - period + 1e-6:
            cps.pop()
        self.lives[p.name].moment_known = True

    def on_imu_contested(self, t: float, reason: str, ambiguous: bool = False) -> None:
        """An IMU sample refused as a second publisher's (``CONTESTED_IMU``): samples of that
        publisher may have been taken, every running pipeline is suspect. Its checkpoints of the
        last ``CONTESTED_GUARD_S`` are dropped: a forged sample may have been taken just before the
        first refusal (a jittered second publisher), and a checkpoint after it is not a good state.
        ``ambiguous``: a duplicate that differs from the sample taken for its time (two publishers
        on the same time stamps: :meth:`_reset_after_long_contest`).

        A sample refused further behind the INS than ``future_window_s`` (a time-jump candidate:
        a stale stream, or a second session delivering its samples tens of seconds late) cannot
        have displaced any interval the INS took, so it drops nothing: guarding from its own stamp
        dropped every checkpoint since then (43 s of them when a forged burst reached a loaded
        service that late), and the jump back to the genuine stream then found none to restart
        from (docs/hardening.md, "A forged burst delivered 43 s late")."""
        t_ins = self.engine.last_imu_t
        if ambiguous:
            self.imu_ambiguous_t = t_ins if t_ins is not None else t
        stale = t_ins is not None and t < t_ins - self.config.intake.future_window_s
        for p in self.engine.pipelines:
            cps = self.checkpoints[p.name]
            clean = self.replayed_checkpoint.get(p.name)
            while not stale and cps and cps[-1][0] > t - CONTESTED_GUARD_S and cps[-1] is not clean:
                cps.pop()
            if self.lives[p.name].stage in _RUNNING and not (p.failed or p.lost):
                self.suspect(p, t, "imu_contested")

    def on_aiding_contested(self, kind: str, sensor_id: str, t: float) -> None:
        """Two different messages for the epoch ``t`` under one aiding key (a second publisher:
        a spoofer racing the sensor on its own time stamps; which one is genuine is not known).
        The key is refused ``aiding_contested`` until ``CONTESTED_AIDING_HOLD_S`` has passed
        without such a pair (:meth:`aiding_contested`), and every running pipeline that uses the
        kind is suspect (``aiding_contested``: ``degraded``, verified again by the vehicle's other
        references or, after the hold, by the key's own; a disagreement then resets it).

        Why: forged fixes on the receiver's own time stamps, delivered just before the genuine
        ones and claiming 1 m against the receiver's 10 m, were taken and the genuine refused as
        duplicates; the filters followed the forged drift 'aided' while beyond 3 sigma for
        160-380 epochs (docs/hardening.md, "Forged fixes on the receiver's own time stamps")."""
        key = f"{kind}/{sensor_id}" if sensor_id else kind
        last = self.contested_aiding.get(key)
        self.contested_aiding[key] = t
        first = last is None or abs(t - last) > CONTESTED_AIDING_HOLD_S
        if first:
            log.warning(
                "vehicle %s: two publishers under %s: different messages for the epoch %.3f; the key is "
                "not used until %.0f s pass without such a pair (Health rejected aiding_contested, "
                "notes contested:%s)",
                self.engine.vehicle,
                key,
                t,
                CONTESTED_AIDING_HOLD_S,
                key,
            )
        for p in self.engine.pipelines:
            running = self.lives[p.name].stage in _RUNNING and not (p.failed or p.lost)
            if not (running and kind in p.consumed_kinds()):
                continue
            self.suspect(p, t, "aiding_contested")
            if first:
                self._undo_contested(p, kind, sensor_id, t)

    def _undo_contested(self, p: Pipeline, kind: str, sensor_id: str, t: float) -> None:
        """The first contested epoch's message was applied before its rival arrived: restart ``p``
        from its last checkpoint before ``t`` and replay the IMU and the aiding since, without the
        key's messages from ``t`` on (:meth:`_start_replayed`); the checkpoints from ``t`` on are
        dropped (they may hold that message). Nothing when the replay cannot be made."""
        cps = self.checkpoints[p.name]
        while cps and cps[-1][0] > t - 1e-6:
            cps.pop()
        if self.engine.last_imu_t is None:
            return
        self.engine._advance_all()  # (every pipeline at the engine's time: nothing left to push)
        t_now = self.engine.pre.t_end
        plan = self._replay_plan(p, t_now)
        if plan is None:
            return
        self.engine.notes[f"reset:{p.name}"] += 1
        self._start_replayed(p, *plan, "reset", t_now, skip=(kind, sensor_id, t))
        life = self.lives[p.name]
        life.verified, life.reason = False, "aiding_contested"

    def aiding_contested(self, kind: str, sensor_id: str, t: float) -> bool:
        """Whether the aiding key is held after a contested epoch (:meth:`on_aiding_contested`)."""
        if not self.contested_aiding:
            return False
        last = self.contested_aiding.get(f"{kind}/{sensor_id}" if sensor_id else kind)
        return last is not None and abs(t - last) <= CONTESTED_AIDING_HOLD_S

    def _reset_from_reference(self, p: Pipeline, fix: GnssFix, t: float) -> None:
        """Restart ``p`` from the vehicle's own fix (:meth:`_fix_state`), or after a contested IMU
        key from its last verified state with the verified stream's IMU since then
        (:meth:`_replayed`); unverified (``degraded``) until its aiding agrees."""
        self.engine.notes[f"reset:{p.name}"] += 1
        if self._replayed(p, fix, t):
            return
        life = self.lives[p.name]
        # what a carry starts from, when the verified stream cannot restore the state instead: a
        # contest whose slots hold two different samples (a race), or a pipeline whose stream is
        # not replayed. Not otherwise: a contest that can be replayed replays from the verified
        # checkpoint, which a kept carry would hide (the gnss family's tc after imu_close
        # 0.05x500, seed 33: 2.1 m and back in 24 s against 1.9 m and 0.1 s)
        cp = self._checkpoint(p, t) if life.reason == "imu_contested" else None
        raced = self.imu_ambiguous_t is not None and cp is not None and self.imu_ambiguous_t >= cp[0]
        if not (raced or p.wants_imu_samples or p.node_imu_ids()):
            cp = None
        carried = self._carried_state(p, fix, t)
        nav, std, refs = carried if carried is not None else self._fix_state(p, fix, t)
        self._start_one(p, nav, std, "reset", verified=False, reason="reset", refs=refs)
        if carried is not None and cp is not None:
            # the last verified state carried over the gap holds no sample of the contest: kept
            # as the newest checkpoint, the next reset of a contest that goes on carries it again,
            # for at most CARRY_CHAIN_MAX_S from the verified one it descends from. Without it a
            # forger racing the IMU on its own time stamps (each slot's first copy taken, which is
            # genuine unknown) aged the checkpoint out, and the first fix after the contest
            # restarted every pipeline from the fix alone: the gnss family's 10 m fixes, seed 33,
            # a 5 s race: 0.4 m off before that reset, 10-12 m after, not back under the clean run's
            # 95th percentile in the 195 s left (docs/hardening.md, "A forger racing the IMU in
            # real time")
            kept = self.replayed_checkpoint.get(p.name)
            chained = life.carried_root_t is not None and kept is not None and kept[0] == cp[0]
            root = life.carried_root_t if chained else cp[0]
            if t - root <= CARRY_CHAIN_MAX_S:
                self._keep_clean_checkpoint(p)
                life.carried_root_t = root

    def _replayed(self, p: Pipeline, fix: GnssFix, t: float) -> bool:
        """After a contested IMU key: restart ``p`` from its last verified checkpoint, whole, and run
        the IMU intervals of the stream it followed then (:meth:`VehicleEngine.verified_imu`: the
        intervals that continue its cadence end to end, taken or refused) through it to ``t``,
        when they cover the span unambiguously and the state they give agrees with the vehicle's
        fix (``alignment.plausible``). Returns whether it did; else the reset carries the
        checkpoint over the gap (:meth:`_carried_state`), as before.

        Why: a second publisher between the genuine samples leaves the genuine stream in the
        intervals the rules took or refused, and the carry over the gap throws away what the
        IMU measured there. The demo, seed 102, an IMU burst at 10x: the carry restarted
        ``tc_mhss`` 0.9 s after its checkpoint with 928 arcsec of attitude and 0.1 m/s of velocity
        sigma (the checkpoint's: 4-6 arcsec, 0.007-0.02 m/s); re-learning them from six
        satellites left its error above the clean run's for 67 s and 'aided' beyond 3 sigma for
        26 epochs (docs/hardening.md, "Replaying the verified IMU stream"). Not for pipelines that
        take IMU sample objects or node IMUs (their own streams are not replayed)."""
        life = self.lives[p.name]
        if not (life.stage == SUSPECT and life.reason == "imu_contested" and life.moment_known):
            return False
        plan = self._replay_plan(p, t)
        if plan is None or not self._replay_agrees(p, plan, fix, t):
            return False
        self._start_replayed(p, *plan, "reset", t)
        return True

    def _replay_agrees(self, p: Pipeline, plan, fix: GnssFix, t: float) -> bool:
        """Whether the navigation the verified stream's IMU gives from the plan's checkpoint to
        ``t`` (without aiding, its position sigma grown by the checkpoint's velocity sigma over the
        span) agrees with the vehicle's fix (``alignment.plausible``)."""
        c, rows = plan
        t_cp, cp, P9 = c[0], c[1], c[2]
        ins = Ins(cp, p.bank.ins.major_interval_s)  # the replayed navigation, to check it first
        for r in rows:
            ins.push(r[2:5], r[5:8], r[1], r[0])
        ins.major_update()
        T9 = np.eye(9)
        T9[:3, 3:6] = (t - t_cp) * np.eye(3)
        P6 = (T9 @ P9 @ T9.T)[:6, :6]
        ref_nav, ref_std = alignment.motion_alignment(fix, t)
        return bool(alignment.plausible(ins.state, ref_nav, P6 + alignment.std_cov6(ref_std))[0])

    def _replay_forged(self, p: Pipeline, life: Life, ref, t: float) -> bool:
        """While the IMU key is contested, at a reference epoch: when the INS took intervals that
        are not the verified stream's (:meth:`VehicleEngine.imu_took_forged`: a second
        publisher's sample between the genuine ones taken, or a genuine one refused for it), restart
        ``p`` from its last verified checkpoint with the verified stream's IMU and the aiding since
        (:meth:`_start_replayed`), whether or not its state disagrees with the reference yet, and
        keep the replayed state as a checkpoint (built from the verified stream alone: a contest
        that goes on replays from it). With a fix as the reference, only when the replayed
        navigation agrees with it (:meth:`_replay_agrees`). A stream held on its own time stamps by
        two publishers is refereed (:meth:`_referee_contest`); a pipeline whose stream is not
        replayed (node IMUs), or that the referee cannot settle, is reset from its checkpoint
        carried over the gap instead (:meth:`_reset_from_reference`). Returns whether it did.

        Why: a forged sample close to the genuine ones (the genuine increments with 0.2 rad/s more
        yaw rate) leaves a state that still agrees with the fixes, so no reset came; the heading
        error it left grew into the position. The gnss family, seed 401: the federated filter
        892 m off at the end of the run, the loosely coupled 233 m at its peak
        (docs/hardening.md, "Forged samples close to the genuine ones")."""
        if not (life.stage == SUSPECT and life.reason == "imu_contested" and life.moment_known):
            return False
        plan = self._replay_plan(p, t)
        c = plan[0] if plan is not None else self._checkpoint(p, t)
        fix = ref[2] if isinstance(ref[2], GnssFix) else None
        if c is None:  # a contest longer than the checkpoints last (CHECKPOINT_MAX_AGE_S)
            return self._reset_after_long_contest(p, life, fix, t)
        if not self.engine.imu_took_forged(c[0], t):
            return False
        if plan is None:  # a stream that is not replayed (node IMUs) or not unambiguously
            if self._referee_contest(p, c, ref, t):
                return True
            if fix is None:
                if isinstance(ref[2], InitStd) and not self._gnss_streams():
                    # a vehicle without GNSS: the checkpoint carried over the gap is its only
                    # reference, and it holds no sample of the contest: restart from it, as a
                    # fix restarts a GNSS vehicle's pipeline (a state that merely passed
                    # plausibility against it kept the forged samples: the underwater federated
                    # filter, seed 23, 6.3 deg of heading and 270 m, 'degraded' for the rest of
                    # the run once the checkpoint had expired with no reference left)
                    self.engine.notes[f"reset:{p.name}"] += 1
                    self._start_one(p, ref[0], ref[2], "reset", verified=False, reason="reset", refs=ref[3])
                    # kept as the reference past CHECKPOINT_MAX_AGE_S: a contest that outlasted
                    # the last verified checkpoint left the pipeline with no reference at all,
                    # its screening refusing the USBL and DVL at every epoch, 'degraded' and
                    # drifting for the rest of the run (seed 31, 40 m; docs/hardening.md)
                    self._keep_clean_checkpoint(p)
                    return True
                return False  # (no fix: the pipeline's own screening decides, as before)
            self._reset_from_reference(p, fix, t)  # the checkpoint carried over the gap
            return True
        if fix is not None and not self._replay_agrees(p, plan, fix, t):
            return False
        self.engine.notes[f"reset:{p.name}"] += 1
        self._start_replayed(p, *plan, "reset", t)
        self._keep_clean_checkpoint(p)
        return True

    def _referee_contest(self, p: Pipeline, c, ref, t: float) -> bool:
        """Two publishers on the IMU's own time stamps (which one is genuine is not known from the
        samples), checkpoint ``c`` before the contest: the two candidate streams
        (:meth:`VehicleEngine.candidate_imu`: the copies the INS took, and the others) are each
        run on a copy of ``p`` from ``c`` with the aiding since, to the end of the last slot held
        by two copies, and their attitudes compared with ``c`` carried there with its own turn
        rate (:meth:`_carried_checkpoint`): the referee a forged turn rate cannot pass. What
        tells them apart is the turn over the span, so the yardstick is the carry's growth alone
        (``carry_sigmas``), not ``c``'s own attitude sigma, which all three share. The likelier
        candidate (within ``CONTEST_AGREE_CHI2_3DOF`` of the carry; neither: None) is the stream
        ``p`` restarts from, at ``c``, with its position, velocity and attitude variances grown by
        the other's probability times the squares of their differences (the second moment of the
        two-hypothesis mixture: nothing when the referee is clear, half the square when it cannot
        tell), kept as the newest checkpoint at that slot's end, and run on to ``t`` with the
        copies taken (slots whose second copy may still come are judged by the next reset). Nothing
        the aiding since ``c`` said is lost, as it is in a carry. The state must still agree with
        this epoch's reference ``ref``; unverified; counted ``absorbed:<pipeline>``. Along a
        chain of such restarts the grown sigmas add up (``Life.absorbed``: a drift that passes
        grows the variance with its square, not a piece at a time) to ``CONTEST_ABSORB_MAX``.
        Returns whether it did (else the reset carries ``c`` over the gap, as before).

        Why: a forger's copies delivered ~1 s behind the IMU, four of them ahead of the genuine
        samples (refused ``duplicate``): the demo, seed 38, through real processes at 10x: the
        MHSS filter (five BeiDou satellites) restarted from its checkpoint carried over 3 s at
        three fixes, 4.6 m off 15 s later against 1.2 m clean, not back in the 45 s left; the
        copies it had taken had moved its heading by ~2 mrad. The copies taken trusted without a
        referee lost the race the forger won: the gnss family's loosely coupled filters back after
        33 s or never, an underwater filter 234 m off (docs/hardening.md, "A race lost by the
        forger")."""
        if c is None or p.wants_imu_samples or p.node_imu_ids() or p.bank is None:
            return False
        if not self.engine.aiding_logged_since(c[0]):
            return False
        cands = self.engine.candidate_imu(c[0], t)
        if cands is None or not cands[2]:
            return False
        taken, other, _, last = cands
        t_last = taken[last - 1][0]
        carry = self._carried_checkpoint(p, t_last, level=False)
        if carry is None:
            return False
        streams = publisher_streams(taken, other, last)  # (each publisher's copies, not the first)
        navs = []
        for rows in streams:  # each candidate on a copy (its screening's records stay there)
            q = copy.deepcopy(p)
            self._start_replayed(q, c, rows, "reset", t_last + 1e-6, quiet=True)
            navs.append(q.estimate().nav)
        sd = max(self.carry_sigmas(p)[1] * abs(t_last - c[0]), 1e-6)
        m_taken, m_other = (float(np.sum(np.square(attitude_difference(n, carry[0]) / sd))) for n in navs)
        if min(m_taken, m_other) > CONTEST_AGREE_CHI2_3DOF:
            return False  # neither agrees with the carry (a manoeuvre it did not foresee)
        rows = streams[0] if m_taken <= m_other else streams[1]
        p_other = 1.0 / (1.0 + math.exp(min(0.5 * abs(m_taken - m_other), 700.0)))
        diff = np.concatenate(
            [alignment.pos_vel_difference(navs[0], navs[1]), attitude_difference(navs[0], navs[1])]
        )
        life = self.lives[p.name]
        chain = life.absorbed
        before = chain[1] if chain is not None and chain[0] == c[0] else np.zeros(9)
        total = before + math.sqrt(p_other) * np.abs(diff)
        att, vel, pos = CONTEST_ABSORB_MAX
        if not (
            np.all(np.isfinite(total))
            and float(total[6:9].max()) <= math.radians(att)
            and float(total[3:6].max()) <= vel
            and float(total[0:3].max()) <= pos
        ):
            return False
        t_cp, cp, P9, P, refs, dyn = c
        grow = total * total - before * before
        P9 = P9.copy()
        P = P.copy()
        for j in range(9):
            if P9[j, j] > 0.0:
                P[..., j, j] += grow[j] * P[..., j, j] / P9[j, j]  # members by their share
            P9[j, j] += grow[j]
        # kept at the last slot held by two copies: the slots after it may yet get their second
        # copy (the forger's, or the genuine one behind it), which the next reset judges. (Kept
        # at this epoch instead, the copy taken of the slot holding it leaked into the chain at
        # every reset: a forger first on every slot moved the heading 0.7 deg in 5 s under a
        # sigma of 0.0005 deg)
        self._start_replayed(p, (t_cp, cp, P9, P, refs, dyn), rows, "reset", t_last + 1e-6, quiet=True)
        # (carried on with c's motion, the last verified one: the INS's last interval may be a
        # short one holding copies of the contest, and the next referee's carry would follow it)
        self._keep_clean_checkpoint(p, dyn)
        kept = self.checkpoints[p.name][-1]
        self._start_replayed(p, self._checkpoint(p, t), taken[last:], "reset", t)
        p.sync()
        est = p.estimate()
        if not alignment.plausible(est.nav, ref[0], est.P9[:6, :6] + ref[1])[0]:
            self.checkpoints[p.name].remove(kept)  # (not a state to go on from)
            self.replayed_checkpoint.pop(p.name, None)
            if isinstance(ref[2], GnssFix):
                self._reset_from_reference(p, ref[2], t)
            else:  # (no fix: the last verified state carried over the gap, as before)
                self._start_one(p, ref[0], ref[2], "reset", verified=False, reason="reset", refs=ref[3])
            return True
        self.engine.notes[f"absorbed:{p.name}"] += 1
        life.absorbed = (kept[0], total)
        return True

    def _keep_clean_checkpoint(self, p: Pipeline, dyn=None) -> None:
        """The state ``p`` just restarted from (replayed with the verified stream, or the last
        verified checkpoint carried over the gap: no sample of the contest in it) kept as its
        newest checkpoint, which the contest's guard (:meth:`on_imu_contested`) does not drop.
        ``dyn``: the motion a carry of it goes on with (default: its INS's last interval)."""
        p.sync()
        est = p.estimate()
        cp = (est.nav.t, est.nav.copy(), est.P9.copy(), full_state(p), _imu_of(p) if dyn is None else dyn)
        self.checkpoints[p.name].append(cp)
        _thin(self.checkpoints[p.name])
        self.replayed_checkpoint[p.name] = cp
        self.lives[p.name].carried_root_t = None  # (a carried restart sets it after this)

    def _gnss_streams(self) -> bool:
        """Whether the vehicle has a GNSS stream (fixes or raw epochs): its reference after a
        contest (:meth:`_reset_after_long_contest`)."""
        return any(k.startswith(("gnss_fix", "gnss_raw")) for k in self.engine.streams)

    def _reset_after_long_contest(self, p: Pipeline, life: Life, fix: GnssFix | None, t: float) -> bool:
        """While the IMU key is contested with no checkpoint left to replay or carry (the contest
        outlasted ``CHECKPOINT_MAX_AGE_S``): at a fix, when a duplicate that differs from the
        sample taken for its time was refused since the pipeline's last start (the samples it took
        since then may be a second publisher's on the genuine time stamps, and nothing tells which),
        restart it from the fix (:meth:`_reset_from_reference`: velocity from the fix, attitude
        from gravity and the GNSS track with their own sigmas, no IMU sample of the contest in
        them), at every fix while the contest goes on and once after it. Returns whether it did.

        Why: a second publisher racing the IMU on its own time stamps (a forged copy of each
        sample delivered first, the genuine one refused ``duplicate``) cannot be replayed out:
        which copy is genuine is not known. The reset at each fix carried the checkpoint from
        before the contest over the gap, until that checkpoint was too old; the forged samples
        taken after the last such reset then stayed in the state. The demo, seed 5, 500 such
        samples with 0.05 rad/s more yaw rate: the federated filter 2.9 deg off in heading with a
        sigma of a few hundredths of a degree, its fault test isolating the star tracker (the
        sensor that could correct it), 23.6 m off 31 s after the contest; 1,500 samples: 184 m
        (docs/hardening.md, "A forger racing the IMU on its own time stamps")."""
        last = self.imu_ambiguous_t
        if fix is None or last is None or life.started_t is None or last < life.started_t:
            return False
        self._reset_from_reference(p, fix, t)
        return True

    def _replay_plan(self, p: Pipeline, t: float):
        """(checkpoint as :meth:`_checkpoint` gives it, the verified stream's IMU intervals from
        it to ``t``) for :meth:`_start_replayed`, or None: no checkpoint, intervals that do not
        cover the span unambiguously (:meth:`VehicleEngine.verified_imu`), or a pipeline that
        takes IMU sample objects or node IMUs (their own streams are not replayed)."""
        if p.wants_imu_samples or p.node_imu_ids() or p.bank is None:
            return None
        c = self._checkpoint(p, t)
        if c is None or not self.engine.aiding_logged_since(c[0]):
            return None  # (the aiding since the checkpoint no longer all in the log)
        rows = self.engine.verified_imu(c[0], t)
        return None if rows is None else (c, rows)

    def _start_replayed(
        self, p: Pipeline, c, rows, event: str, t: float, skip=None, quiet: bool = False
    ) -> None:
        """Restart ``p`` from checkpoint ``c``, whole, then run the IMU intervals ``rows`` through
        it to ``t`` (the filter's own propagation: navigation, covariance, private states), with
        the aiding messages the engine handed it in between applied again at their epochs (the
        interval holding one cut there, as the engine cuts it; the pipeline's own screening judges
        them again; their outputs were sent the first time and are not sent again); unverified.
        Counted ``replayed:<pipeline>``. ``skip``: (kind, sensor id, t0), that key's messages from
        ``t0`` on are not applied again (a contested aiding key). ``quiet``: the filter only (a
        copy of ``p`` run to see where a stream takes it): no stage move, not counted."""
        t_cp, cp, P9, P, refs, _ = c
        sd = np.sqrt(np.clip(np.diagonal(P9), 0.0, None))
        std = InitStd(sd[0:3], sd[3:6], sd[6:9], cov=P)
        if quiet:
            self._restore(p, cp, std, event, refs)
        else:
            self._start_one(p, cp, std, event, verified=False, reason=event, refs=refs, event_t=t)
        kinds = p.consumed_kinds()
        aids = [
            a
            for a in self.engine.aiding_log
            if t_cp + 1e-9 < a[0] < t - 1e-9
            and a[1] in kinds
            and not (skip is not None and a[1:3] == skip[:2] and a[3].t >= skip[2] - 1e-9)
        ]
        screened = p.screened.copy()  # (each message's screening counted once, when it came)
        p.replaying = True
        try:
            self._replay_rows(p, rows, aids, t_cp)
        finally:
            p.replaying = False
            p.screened.clear()
            p.screened.update(screened)
        p.sync()
        p.take_events()  # (what the replayed epochs' screening said is about epochs already judged)
        if not quiet:
            self.engine.notes[f"replayed:{p.name}"] += 1

    @staticmethod
    def _replay_rows(p: Pipeline, rows, aids, t_cp: float) -> None:
        """:meth:`_start_replayed`'s loop: the IMU intervals ``rows`` through ``p`` from ``t_cp``
        with the aiding messages ``aids`` applied at their epochs (the interval holding one cut
        there, as the engine cuts it)."""
        i, cur = 0, t_cp
        for r in rows:
            end = r[0]
            dth, dv = list(r[2:5]), list(r[5:8])
            while i < len(aids) and aids[i][0] <= end + 1e-9:
                t_a, kind, sensor_id, msg, dt_late = aids[i]
                i += 1
                f = min(max((t_a - cur) / (end - cur), 0.0), 1.0) if end > cur else 1.0
                if f > 0.0:
                    p.push_imu([a * f for a in dth], [a * f for a in dv], t_a - cur, t_a)
                    dth = [a * (1.0 - f) for a in dth]
                    dv = [a * (1.0 - f) for a in dv]
                    cur = t_a
                p.sync()
                try:
                    p.apply(kind, sensor_id, msg, dt_late)
                except np.linalg.LinAlgError:
                    p.recover_covariance()
            if end - cur > 1e-12:
                p.push_imu(dth, dv, end - cur, end)
            cur = end

    def _fix_state(self, p: Pipeline, fix: GnssFix, t: float):
        """(NavState, InitStd, private references or None) a reset restarts ``p`` from: velocity
        from the fix, attitude from gravity and the GNSS track (in motion; static: the attitude
        kept, its sigmas widened), position from the pipeline's last verified estimate carried to
        ``t`` (:meth:`_from_checkpoint`), else the fix's; bias estimates kept. (While the IMU key is
        contested, :meth:`_reset_from_reference` restarts from the last verified state carried over
        the gap instead, :meth:`_carried_state`, when the fix agrees with it.)"""
        est = p.estimate()
        if alignment.fix_speed(fix) >= self.config.init.min_speed_mps:
            ins = p.bank.ins
            f_b = est.nav.mat_nb.T @ ins.last_fn_mps2
            nav, std = alignment.moving_alignment(fix, t, f_b, self.prev_fix)
        else:
            _, std = alignment.motion_alignment(fix, t)
            att = np.sqrt(np.clip(np.diagonal(est.P9)[6:9], 0.0, None))
            att = np.maximum(att, np.radians(alignment.MOTION_ATT_STD_DEG))
            nav = alignment.nav_at_fix(fix, est.nav.rpy_rad, t)
            std = InitStd(std.pos_enu_m, std.vel_enu_mps, att)
        life = self.lives[p.name]
        if life.stage == SUSPECT and life.reason == "imu_contested":
            # the INS's input was contested: its last interval (the specific force the tilts come
            # from above) may hold a forged sample. The last verified state before the contest,
            # carried to now with its turn rate and its attitude sigmas grown over the gap, is the
            # attitude to restart from (found on the demo, seed 12: a reset 0.1 s after a burst of
            # forged samples levelled from such an interval was 6.6 deg off in roll against a 2 deg
            # sigma; the federated filter's fault test then refused the star tracker, the one
            # sensor that could correct it, to the end of the run)
            carried = self._carried_checkpoint(p, t, level=False)
            if carried is not None:
                nav.q_nb = carried[0].q_nb.copy()
                std = InitStd(
                    std.pos_enu_m, std.vel_enu_mps, carried[2].att_rad, pos_from_fix=std.pos_from_fix
                )
        if np.all(np.isfinite(est.nav.gyro_bias_rps)) and np.all(np.isfinite(est.nav.accel_bias_mps2)):
            nav.gyro_bias_rps = est.nav.gyro_bias_rps.copy()
            nav.accel_bias_mps2 = est.nav.accel_bias_mps2.copy()
        return self._from_checkpoint(p, nav, std, t)

    def _carried_state(self, p: Pipeline, fix: GnssFix, t: float):
        """After a contested IMU key: ``p``'s last verified estimate carried over the gap with its
        whole covariance (:meth:`_carried_checkpoint`: velocity, attitude, biases, receiver clock
        and their correlations, grown by the vehicle's own dynamics) as (NavState, InitStd,
        private references), when the vehicle's fix agrees with it (position and velocity,
        ``alignment.plausible``); else None (the fix's state, :meth:`_fix_state`). The same state
        a vehicle without GNSS resets to, and one whose INS was lost for a moment recovers from.

        Why not the fix's velocity: the carried checkpoint knows it better. A raw-only pipeline's
        fix is a snapshot solution (the demo's six BeiDou satellites: 0.3 / 1.3 / 1.2 m/s, against
        ~0.1 m/s for a checkpoint carried 0.9 s), and the position was carried with the trapezoid
        of both velocities: the demo, seed 12, an IMU burst at 10x, reset ``tc_mhss`` with its
        velocity 0.76 m/s off in north and its position moved 0.34 m (``lc``, whose receiver fix
        was not current at its second reset, 2.2 m/s off). The tightly coupled filter's
        pseudoranges observe north, up and the receiver clock together so weakly that about half
        of such an offset is still there 150 s later (issue 22). Velocity and attitude replaced
        with no correlations also lost what the checkpoint knew of them with the biases."""
        life = self.lives[p.name]
        if not (life.stage == SUSPECT and life.moment_known):
            return None
        c = self._carried_checkpoint(p, t, level=False, own_motion=life.reason != "imu_contested")
        if c is None:
            return None
        nav, P6, std, refs = c
        ref_nav, ref_std = alignment.motion_alignment(fix, t)
        if not alignment.plausible(nav, ref_nav, P6 + alignment.std_cov6(ref_std))[0]:
            return None
        return nav, std, refs

    def note_estimate(self, p: Pipeline, est) -> None:
        """A pipeline's estimate at an output epoch: kept while the pipeline is verified (the last
        good state a reset may start from), not while its aiding is refused wholesale (the state
        may have gone wrong: :meth:`_corrupt_since`)."""
        life = self.lives[p.name]
        if life.stage != AIDED or not life.verified or p.refusal_began is not None:
            return
        cps = self.checkpoints[p.name]
        if cps and 0.0 <= est.nav.t - cps[-1][0] < CHECKPOINT_PERIOD_S:
            return
        dyn = _imu_of(p)  # the changes of specific force and body rate: those of motion
        recent = cps and est.nav.t - cps[-1][0] <= 2 * CHECKPOINT_PERIOD_S
        if recent and dyn is not None and cps[-1][4] is not None:
            a0, w0 = cps[-1][4]
            changes = self.dyn_changes[p.name]
            da, dw = math.hypot(*(dyn[0] - a0)), math.hypot(*(dyn[1] - w0))
            if math.isfinite(da) and math.isfinite(dw):
                changes.append((est.nav.t, da, dw))
            while changes and changes[0][0] < est.nav.t - CARRY_HISTORY_S:
                changes.popleft()
        cps.append((est.nav.t, est.nav.copy(), est.P9.copy(), full_state(p), dyn))
        _thin(cps)

    def carry_sigmas(self, p: Pipeline) -> tuple[float, float]:
        """(acceleration m/s^2, turn rate rad/s) a carried checkpoint of ``p`` may miss, 1-sigma:
        the RMS change between its consecutive checkpoints lately (floored), or the defaults
        before there is a history."""
        changes = self.dyn_changes[p.name]
        if len(changes) < 4:
            return CARRY_ACC_DEFAULT_MPS2, math.radians(CARRY_TURN_STD_DPS)
        n = len(changes)
        acc = max(CARRY_ACC_FLOOR_MPS2, math.sqrt(sum(c[1] ** 2 for c in changes) / n))
        turn = max(math.radians(CARRY_TURN_FLOOR_DPS), math.sqrt(sum(c[2] ** 2 for c in changes) / n))
        return acc, turn

    def _checkpoint(self, p: Pipeline, t: float):
        """``p``'s last verified estimate if at most ``CHECKPOINT_MAX_AGE_S`` from ``t``: (time,
        NavState, its 9x9 covariance, covariance of the restart (:func:`full_state`'s, else the
        9x9), (references, members' private states) or None)."""
        cps = self.checkpoints[p.name]
        if not cps:
            return None
        t_cp, cp, P9, full, dyn = cps[-1]
        if abs(t - t_cp) > CHECKPOINT_MAX_AGE_S:
            return None
        bank = p.bank
        if full is not None and bank is not None and full[0].shape[-1] == bank.n:
            if full[0].ndim == 2 or full[0].shape[0] == bank.B:
                return t_cp, cp, P9, full[0].copy(), (full[1], full[2]), dyn
        return t_cp, cp, P9, P9.copy(), None, dyn

    def _carried_checkpoint(self, p: Pipeline, t: float, level: bool = True, own_motion: bool = False):
        """(NavState, 6x6 position/velocity covariance, InitStd with the full ``cov``, private
        references or None) of ``p``'s last verified estimate carried to ``t`` with its own
        velocity (``CARRY_ACC_STD_MPS2`` of unknown acceleration over the gap); attitude levelled
        again from the specific force of its INS's last interval, heading kept (``level``), or the
        checkpoint's, grown by ``CARRY_TURN_STD_DPS``. None without a checkpoint at most
        ``CHECKPOINT_MAX_AGE_S`` old. The reference of a vehicle without GNSS whose INS input was
        contested, and the state of a vehicle whose INS was lost for a moment.

        ``own_motion`` (the INS's input sound: a refusal run, not a contested key): when the INS's
        own velocity and heading now agree with the carried ones (chi-square of 4 at 1e-6 under
        the carried covariance: :meth:`_own_motion`), its velocity and attitude are taken, with
        the checkpoint's covariance carried without the unknown-motion growth (the IMU measured
        the motion over the gap: its biases' share is added), and the position is carried with
        the trapezoid of both velocities. The carry's
        growth alone left a tightly coupled pipeline reset 2.5 s after its checkpoint with 0.72 deg
        of attitude and 0.27 m/s of velocity sigma while its INS was within 0.003 deg and 0.04 m/s
        of them; re-learning them from pseudoranges took it 2 m off for 30 s (the demo, seed 7:
        docs/hardening.md, "A silent corruption of the state")."""
        c = self._checkpoint(p, t)
        if c is None:
            return None
        t_cp, cp, P9, P, refs, dyn = c
        dt = t - t_cp
        refs, P = _private_over(p, refs, P, dt)
        P_old = P.copy()
        v0 = np.asarray(cp.vel_enu_mps, dtype=float)
        acc_std, turn_std = self.carry_sigmas(p)
        motion = None if dyn is None else _motion(dyn, cp)
        if motion is None:
            nav = shifted(cp, v0 * dt)
        else:  # on with its acceleration and turn rate of then
            a, w = motion
            nav = shifted(cp, v0 * dt + 0.5 * a * dt * dt)
            nav.vel_enu_mps = v0 + a * dt
            nav.q_nb = earth.quat_mul(np.asarray(cp.q_nb, dtype=float), earth.rotvec_to_quat(w * dt))
        nav.t = t
        T = np.eye(P.shape[-1])
        T[:3, 3:6] = dt * np.eye(3)
        P = T @ P @ T.T
        T9 = np.eye(9)
        T9[:3, 3:6] = dt * np.eye(3)
        P9 = T9 @ P9 @ T9.T
        before_growth = (P.copy(), P9.copy()) if own_motion else None
        dt_signed, dt = dt, abs(dt)
        acc = acc_std
        grow = np.diag([(0.5 * acc * dt * dt) ** 2] * 3 + [(acc * dt) ** 2] * 3)
        P[..., :6, :6] += grow
        P9[:6, :6] += grow
        sd = np.sqrt(np.clip(np.diagonal(P9), 0.0, None))
        turn = turn_std * dt
        att = np.sqrt(np.square(sd[6:9]) + turn * turn)
        levelled = False
        if level and p.bank is not None and math.atan2(acc, 9.8) < float(np.max(att[:2])):
            est = p.estimate()
            f_b = est.nav.mat_nb.T @ p.bank.ins.last_fn_mps2
            g = float(np.linalg.norm(f_b))
            if g > 1.0:
                pitch = math.asin(max(-1.0, min(1.0, f_b[1] / g)))
                roll = math.atan2(-f_b[0], f_b[2])
                nav.q_nb = earth.mat_to_quat(earth.rpy_to_mat_nb(np.array([roll, pitch, cp.rpy_rad[2]])))
                att[:2] = math.atan2(acc, 9.8)
                P[..., 6:8, :] = 0.0  # levelled again: the tilts owe nothing to the old state
                P[..., :, 6:8] = 0.0
                levelled = True
        # what the gap adds to each member's attitude variance (a member of a federated bank keeps
        # its own share of the information: added, never set to the fused value)
        i = np.arange(8, 9) if levelled else np.arange(6, 9)
        P[..., i, i] += turn * turn
        if levelled:
            P[..., [6, 7], [6, 7]] = np.square(att[:2])
        if own_motion and p.bank is not None:
            carried6 = P9[3:9, 3:9].copy()  # velocity and attitude as carried (the turn's growth too)
            carried6[3:, 3:] += np.eye(3) * turn * turn
            taken = self._own_motion(p, nav, cp, carried6, *before_growth, dt_signed)
            if taken is not None:
                nav, P, P9 = taken
                sd = np.sqrt(np.clip(np.diagonal(P9), 0.0, None))
                att = sd[6:9]
                levelled = False
        core = getattr(p, "core", None)
        if core is not None and P.ndim == 3:  # federated members: their private states' conditionals
            keep = np.ones(em.N_STATES, dtype=bool)
            keep[6:8] = not levelled
            core.carry_private(P_old, P, T[: em.N_STATES, : em.N_STATES], keep)
        return nav, P9[:6, :6], InitStd(sd[0:3], sd[3:6], att, cov=P), refs

    def _own_motion(self, p: Pipeline, nav: NavState, cp: NavState, C: np.ndarray, P, P9, dt: float):
        """(nav, P, P9) of :meth:`_carried_checkpoint` with the INS's own velocity and attitude
        when its velocity and heading agree with the carried ones under ``C`` (their carried 6x6
        velocity and attitude covariance; chi-square of 4 at 1e-6); P and P9 the checkpoint's
        carried without the motion's growth, plus what the IMU's bias sigmas add over ``dt``. None
        when they disagree (the carry stands).

        Why not the tilts: the carry turns the checkpoint's attitude at its body rate of then, and
        a roll-out within the gap leaves it degrees off the INS, which measured it (the gnss family
        of docs/hardening.md, seed 7: 5.3 deg of roll 2.5 s after the checkpoint, at the end of a
        turn). A tilt corrupted before the refusals began (at least ``refused_after_s`` before the
        reset) would show in the velocity (g x tilt x that time: 0.34 m/s per degree in 2 s)."""
        p.sync()
        own = p.bank.nav()
        datt = attitude_difference(own, nav)
        d = np.concatenate([np.asarray(own.vel_enu_mps) - nav.vel_enu_mps, datt[2:3]])
        k = [0, 1, 2, 5]
        try:
            d2 = float(d @ np.linalg.solve(C[np.ix_(k, k)], d))
        except np.linalg.LinAlgError:
            return None
        if not (math.isfinite(d2) and d2 <= VEL_HEADING_CHI2_4DOF):
            return None
        v0, v1 = np.asarray(cp.vel_enu_mps, dtype=float), np.asarray(own.vel_enu_mps, dtype=float)
        out = shifted(cp, 0.5 * (v0 + v1) * dt)
        out.t = nav.t
        out.vel_enu_mps = v1.copy()
        out.q_nb = np.array(own.q_nb, dtype=float, copy=True)
        sg, sa = p.imu.bias_sigmas()
        a = abs(dt)
        add = np.array([(0.5 * sa * a * a) ** 2] * 3 + [(sa * a) ** 2] * 3 + [(sg * a) ** 2] * 3)
        i = np.arange(9)
        P[..., i, i] += add
        P9 = P9.copy()
        P9[i, i] += add
        return out, P, P9

    def _from_checkpoint(self, p: Pipeline, nav: NavState, std: InitStd, t: float):
        """(``nav`` with the position of ``p``'s last verified estimate carried to ``t`` by the
        trapezoid of its velocity and the fix's, its sigmas, private references) when the
        checkpoint is at most ``CHECKPOINT_MAX_AGE_S`` old and agrees with the fix; else
        (``nav``, ``std``, None). Only where the moment of the corruption is known (a contested IMU
        stream, a loss of the INS): a state that went wrong unseen (its aiding refused later) may
        have been wrong at its last checkpoint already. The position keeps its correlations with
        the filter's other states (biases, receiver clock); velocity and attitude, replaced, none."""
        life = self.lives[p.name]
        if life.stage == SUSPECT and not life.moment_known:
            return nav, std, None
        c = self._checkpoint(p, t)
        if c is None or t < c[0]:
            return nav, std, None
        t_cp, cp, P9, P, refs, _ = c
        dt = t - t_cp
        refs, P = _private_over(p, refs, P, dt)
        v_mean = 0.5 * (np.asarray(cp.vel_enu_mps) + np.asarray(nav.vel_enu_mps))
        pos = shifted(cp, v_mean * dt)
        sd_v = np.sqrt(np.clip(np.diagonal(P9)[3:6], 0.0, None))
        grow = np.square(0.5 * (sd_v + std.vel_enu_mps) * dt) + (0.5 * CARRY_ACC_STD_MPS2 * dt * dt) ** 2
        var = np.diagonal(P9)[:3] + grow
        d = alignment.pos_vel_difference(pos, nav)[:3]
        if float(np.sum(d * d / (var + np.square(std.pos_enu_m)))) > POSITION_CHI2_3DOF:
            return nav, std, None  # the checkpoint disagrees with the fix: the fix's position
        out = nav.copy()
        out.lat_rad, out.lon_rad, out.h_m = pos.lat_rad, pos.lon_rad, pos.h_m
        out.gyro_bias_rps, out.accel_bias_mps2 = cp.gyro_bias_rps.copy(), cp.accel_bias_mps2.copy()
        C = P
        C[..., 3:9, :] = 0.0
        C[..., :, 3:9] = 0.0
        C[..., :3, :3] += np.diag(grow)
        i = np.arange(3, 9)
        C[..., i, i] = np.square(np.concatenate([std.vel_enu_mps, std.att_rad]))
        return out, InitStd(np.sqrt(var), std.vel_enu_mps, std.att_rad, cov=C), refs

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
        ref_nav, ref_cov = alignment.fix_reference(fix, est.nav.t, self.prev_fix)  # (carried to the INS time)
        ok, _ = alignment.plausible(est.nav, ref_nav, est.P9[:6, :6] + ref_cov)
        if ok:
            return
        self.engine.rejected["implausible_init"] += 1
        nav_fix, std_fix = alignment.motion_alignment(fix, est.nav.t)
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
            self.last_fix = self.prev_fix = None
            self.imu_ambiguous_t = None
        init, self.pending_init = self.pending_init, None
        if init is not None and abs(init.t - t) <= self.config.intake.future_window_s:
            self.on_initial_nav(init)
            return
        carried = {p.name: self._carried_checkpoint(p, t, level=False) for p in self.engine.pipelines}
        if all(c is not None for c in carried.values()):  # lost for a moment: the last good states
            for p in self.engine.pipelines:
                # with the verified stream's IMU since the checkpoint when it is there whole (a
                # second publisher's burst confirmed a time jump forward, the genuine stream the
                # jump back: its samples were refused, not lost), else carried over the gap
                plan = self._replay_plan(p, t)
                if plan is not None:
                    self._start_replayed(p, *plan, "recover", t)
                    continue
                nav, _, std, refs = carried[p.name]
                self._start_one(p, nav, std, "recover", verified=False, reason="recover", refs=refs)
            self.engine._restart_clock(t)
            self.initialised, self.start_t, self.lost = True, t, False
            self.engine.notes["recovered_from_checkpoint"] += 1
            return
        if self.resume_from_fleet is not None:
            self.resume_from_fleet()


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
    "CONTESTED_IMU",
    "INIT_HISTORY",
    "INIT_RESET_INTERVAL_S",
    "VERIFY_EPOCHS",
    "Life",
    "VehicleLife",
    "floored_std",
    "honest_std",
]
