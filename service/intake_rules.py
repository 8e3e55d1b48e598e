"""Acceptance rules of one vehicle's event stream (docs/DESIGN.md "The service's inner loop").

One decision per event. The running time of a vehicle is the time of its INS (the last accepted
IMU sample). A single message, however valid it looks, must not move that time: samples far from
it are refused, and only a run of samples that agree with each other re-bases it.

- Sensor ids: a kind listed in ``[intake] sensor_ids`` accepts those ids; any other kind takes
  the first id it sees and refuses others as ``unexpected_sensor`` (a second star tracker or
  receiver is fused only when configured). InitialNav and Truth have no id.
- IMU (against the running time): equal time ``duplicate``; earlier ``time_backwards``; further
  ahead than ``future_window_s`` beyond its own interval ``future``; a sample whose interval
  starts more than a quarter interval before the previous sample's end ``overlap`` (samples
  slipped between genuine ones); a gap (span minus the sample's interval) longer than ``max_imu_gap_s``
  but inside the window: ``imu_gap`` (taken; the INS is lost and re-initialised). Refused samples
  more than ``future_window_s`` behind or ahead of the running time are candidates of a time jump
  (samples behind it by less are ``time_backwards`` and never move it: a second publisher lagging
  the sensor by a fraction of a second, whose samples reach the service in runs of twenty and
  more, would otherwise re-base the INS on its own stream): ``time_jump_samples`` consecutive
  candidates, each following the previous one by at most its interval plus ``max_imu_gap_s``,
  with no accepted sample between them, give ``time_jump`` (the last one is taken: the INS is
  re-initialised on the new time base and every per-key record is forgotten).
- InitialNav: further than ``future_window_s`` from the running time ``future`` (ahead) or
  ``late`` (behind: a re-initialisation must be current); else same time as the previous one
  ``duplicate``.
  Whether a re-initialisation is consistent with the navigation is the engine's check.
- Truth: ``duplicate``; older than the previous one ``time_backwards``.
- Aiding (everything else): ``duplicate``; once initialised, older than the INS time by more than
  ``late_tolerance_s`` ``late`` (checked before ``time_backwards``: the more useful reason); older
  than the same sensor's previous message ``time_backwards``; before initialisation
  ``not_initialised`` (the message may still complete an alignment); ahead of the INS by more
  than ``max_lead_s`` ``early``; off its stream's established cadence ``off_cadence`` (below).
- Cadence: a sensor stream that has kept a period (``CADENCE_ESTABLISH`` messages in a row with
  intervals within ``CADENCE_TOLERANCE`` of each other) has a phase: a message further than
  ``CADENCE_TOLERANCE`` periods from it is a second publisher interleaving with the sensor under
  its key (a forged stream between the genuine fixes) and is refused ``off_cadence``, as long as
  the sensor keeps its phase; a phase silent for ``CADENCE_RELEARN_PERIODS`` periods is learnt
  again from the new messages (a receiver restarted on another timing, a rate change). Silent
  means the INS moved on that long without an on-phase message, not a message stamped that far
  ahead: a second publisher whose messages reach the service seconds before the sensor's own
  (another session, less loaded) would otherwise restart the learning with its own message and
  take the key, the sensor's then refused ``time_backwards``.

Messages accepted (and aiding refused only as ``not_initialised``) become their key's latest time.
"""

from __future__ import annotations

from dataclasses import dataclass

from fednav.service.config import IntakeConfig
from fednav.service.messages import WireModel

#: reasons for which a message is out of sequence for its key or the INS (it is not used at all);
#: other refusals (``not_initialised``, ``early``) still leave it the newest of its sensor
OUT_OF_SEQUENCE = frozenset(
    {"duplicate", "time_backwards", "late", "future", "overlap", "unexpected_sensor", "off_cadence"}
)
#: an IMU sample whose interval starts this fraction of itself before the previous sample's end
#: overlaps it (timestamp jitter of genuine samples is far smaller)
OVERLAP_FRACTION = 0.25
#: kinds without a sensor id
_NO_ID = frozenset({"init", "truth", "imu_node"})  # node ids: declared by their pipelines
#: kinds whose messages keep no cadence (not sensors, or judged by their own rules)
_NO_CADENCE = frozenset({"init", "truth", "imu_node", "alignment_truth"})
#: a stream's intervals agree (and a message is on its phase) within this fraction of its period
CADENCE_TOLERANCE = 0.25
#: consecutive agreeing intervals that establish a stream's period and phase
CADENCE_ESTABLISH = 4
#: an established phase without a message for this many periods is learnt again
CADENCE_RELEARN_PERIODS = 3.0
#: streams faster than this (s) keep no cadence (a phase to a millisecond says nothing)
CADENCE_MIN_PERIOD_S = 0.02


@dataclass
class _Cadence:
    """A stream's learnt period and phase: ``period`` None while learning (``count`` intervals
    agree so far); ``anchor`` the time of its last on-phase message."""

    period: float | None = None
    count: int = 0
    anchor: float | None = None
    established: bool = False

    def judge(self, t: float, t_ins: float | None = None) -> bool:
        """Whether ``t`` fits the stream (learning, or on its phase); learns from it if so.
        ``t_ins``: the INS time (the last IMU time), the clock silence is measured on."""
        a = self.anchor
        if a is None:
            self.anchor = t
            return True
        dt = t - a
        if self.established:
            n = round(dt / self.period)
            if n >= 1 and abs(dt - n * self.period) <= CADENCE_TOLERANCE * self.period:
                self.anchor = t
                return True
            silent = CADENCE_RELEARN_PERIODS * self.period
            if dt > silent and (t_ins is None or t_ins - a > silent):  # its phase went silent
                self.period, self.count, self.anchor, self.established = None, 0, t, False
                return True
            return False
        if dt <= 0.0:
            return True
        if self.period is not None and abs(dt - self.period) <= CADENCE_TOLERANCE * self.period:
            self.count += 1
        else:
            self.period, self.count = dt, 1
        self.anchor = t
        if self.count >= CADENCE_ESTABLISH and self.period >= CADENCE_MIN_PERIOD_S:
            self.established = True
        return True


@dataclass(frozen=True)
class Verdict:
    """The decision on one event: ``reason`` None to accept, else why it was refused -- except
    ``imu_gap`` and ``time_jump``, IMU samples that are taken but mark the INS lost (counted
    under those names)."""

    reason: str | None = None

    @property
    def accepted(self) -> bool:
        return self.reason is None

    @property
    def in_sequence(self) -> bool:
        """Not stale for its key or the INS (a GNSS fix may then serve an alignment)."""
        return self.reason not in OUT_OF_SEQUENCE


ACCEPT = Verdict()


@dataclass
class _JumpCandidate:
    last_t: float
    count: int


class AcceptanceRules:
    """Accept/refuse decisions of one vehicle's events; keeps each (kind, sensor) key's last time,
    the sensor id adopted per kind and the run of time-jump candidates."""

    def __init__(self, intake: IntakeConfig):
        self.intake = intake
        self.last_t: dict[tuple[str, str], float] = {}
        self.sensor_of: dict[str, str] = {}  # kind -> the id adopted (kinds not in sensor_ids)
        self.imu_t: float | None = None  # end of the last accepted IMU sample
        self._jump: _JumpCandidate | None = None
        self._cadence: dict[tuple[str, str], _Cadence] = {}

    def forget_times(self) -> None:
        """A new time base (confirmed time jump): per-key records and the IMU time are forgotten;
        adopted sensor ids are kept."""
        self.last_t.clear()
        self.imu_t = None
        self._jump = None
        self._cadence.clear()

    def withdraw(self, kind: str, sensor_id: str, previous: float | None) -> None:
        """A message the rules took was refused later (an implausible InitialNav): its key's time
        goes back to ``previous``, so a corrected message with the same time is not a duplicate."""
        if previous is None:
            self.last_t.pop((kind, sensor_id), None)
        else:
            self.last_t[(kind, sensor_id)] = previous

    def decide(
        self, kind: str, sensor_id: str, msg: WireModel, t_ins: float | None, initialised: bool
    ) -> Verdict:
        """The verdict on one event given the INS time (the last IMU time; None before any IMU)
        and whether the INS is initialised. Records the key's time when the message is taken."""
        if kind not in _NO_ID and not self._known_sensor(kind, sensor_id):
            return Verdict("unexpected_sensor")
        if kind == "imu":
            return self.decide_imu(msg.t, msg.dt_s, t_ins)
        key = (kind, sensor_id)
        verdict = self._other(kind, msg.t, self.last_t.get(key), t_ins, initialised)
        if (verdict.accepted or verdict.reason == "not_initialised") and kind not in _NO_CADENCE:
            c = self._cadence.get(key)
            if c is None:
                c = self._cadence[key] = _Cadence()
            if not c.judge(msg.t, t_ins):
                return Verdict("off_cadence")
        if verdict.accepted or verdict.reason == "not_initialised":
            self.last_t[key] = msg.t
        return verdict

    def decide_imu(self, t: float, dt_s: float, t_ins: float | None) -> Verdict:
        """The verdict on one IMU interval of an id already known (:meth:`known_sensor`): a
        sample, or one record of a batch (the same rules, no message object)."""
        verdict = self._imu(t, dt_s, t_ins)
        if verdict.reason in (None, "imu_gap", "time_jump"):
            self.imu_t = t
        return verdict

    def take_imu_in_sequence(self, t: float, dt_s: float, t_ins: float) -> bool:
        """Whether an IMU interval of a known id is accepted in sequence after the INS time
        ``t_ins`` (:meth:`decide_imu` would return ACCEPT): if so, recorded exactly as
        :meth:`decide_imu` records it and True; otherwise False and nothing recorded (the caller
        then asks :meth:`decide_imu` for the verdict). The fast path of a batch's records."""
        gap = (t - t_ins) - dt_s
        intake = self.intake
        if (
            t > t_ins
            and gap <= intake.future_window_s
            and gap <= intake.max_imu_gap_s
            and not (self.imu_t == t_ins and t - dt_s < t_ins - OVERLAP_FRACTION * dt_s)
        ):
            self._jump = None
            self.imu_t = t
            return True
        return False

    def known_sensor(self, kind: str, sensor_id: str) -> bool:
        """Whether ``sensor_id`` is accepted for ``kind`` (adopts the first id of an unlisted kind)."""
        return kind in _NO_ID or self._known_sensor(kind, sensor_id)

    def _known_sensor(self, kind: str, sensor_id: str) -> bool:
        allowed = self.intake.sensor_ids.get(kind)
        if allowed is not None:
            return sensor_id in allowed
        return self.sensor_of.setdefault(kind, sensor_id) == sensor_id

    def _imu(self, t: float, dt_s: float, t_ins: float | None) -> Verdict:
        if t_ins is None:
            return ACCEPT
        if t == t_ins:
            return Verdict("duplicate")
        if t < t_ins:
            if t_ins - t <= self.intake.future_window_s:
                # inside the window the INS has just run through: a second publisher lagging
                # behind the sensor (or the sensor's own stream behind a forged run ahead), never
                # a new time base; a restart this close behind catches up within the window
                return Verdict("time_backwards")
            return self._jump_candidate(t, dt_s, "time_backwards")
        gap = (t - t_ins) - dt_s
        if gap > self.intake.future_window_s:
            return self._jump_candidate(t, dt_s, "future")
        self._jump = None  # a sample in sequence: whatever came out of it was not a new time base
        if self.imu_t == t_ins and t - dt_s < t_ins - OVERLAP_FRACTION * dt_s:
            return Verdict("overlap")  # starts inside the previous sample (not after a start's time)
        if gap > self.intake.max_imu_gap_s:
            return Verdict("imu_gap")
        return ACCEPT

    def _jump_candidate(self, t: float, dt_s: float, reason: str) -> Verdict:
        c = self._jump
        if c is not None and c.last_t < t <= c.last_t + dt_s + self.intake.max_imu_gap_s:
            c.count += 1
            c.last_t = t
        else:
            c = self._jump = _JumpCandidate(t, 1)
        if c.count >= self.intake.time_jump_samples:
            self._jump = None
            return Verdict("time_jump")
        return Verdict(reason)

    def _other(
        self, kind: str, t: float, prev: float | None, t_ins: float | None, initialised: bool
    ) -> Verdict:
        if kind == "init":  # the window first: a restarted host's InitialNav is kept as pending
            if t_ins is not None and t > t_ins + self.intake.future_window_s:
                return Verdict("future")
            if t_ins is not None and t < t_ins - self.intake.future_window_s:
                return Verdict("late")
            return Verdict("duplicate") if prev is not None and t == prev else ACCEPT
        if prev is not None and t == prev:
            return Verdict("duplicate")
        if kind == "truth":
            return Verdict("time_backwards") if prev is not None and t < prev else ACCEPT
        # aiding
        if initialised and t < t_ins - self.intake.late_tolerance_s:
            return Verdict("late")
        if prev is not None and t < prev:
            return Verdict("time_backwards")
        if not initialised:
            return Verdict("not_initialised")
        if t > t_ins + self.intake.max_lead_s:
            return Verdict("early")
        return ACCEPT


__all__ = ["ACCEPT", "OUT_OF_SEQUENCE", "AcceptanceRules", "Verdict"]
