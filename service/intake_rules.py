"""Acceptance rules of one vehicle's event stream (docs/DESIGN.md "The service's inner loop").

One decision per event, in this order of checks:

- IMU (against the INS time): equal time ``duplicate``; earlier ``time_backwards``; a gap (span
  minus the sample's own interval) longer than ``max_imu_gap_s``: ``imu_gap`` (the sample is
  taken, the INS is lost and re-initialised).
- InitialNav: same time as the previous one ``duplicate``.
- Truth: ``duplicate``; older than the previous one ``time_backwards``.
- Aiding (everything else): ``duplicate``; once initialised, older than the INS time by more than
  ``late_tolerance_s`` ``late`` (checked before ``time_backwards``: the more useful reason); older
  than the same sensor's previous message ``time_backwards``; before initialisation
  ``not_initialised`` (the message may still complete an alignment); ahead of the INS by more
  than ``max_lead_s`` ``early``.

Messages accepted (and aiding refused only as ``not_initialised``) become their key's latest time.
"""

from __future__ import annotations

from dataclasses import dataclass

from service.config import IntakeConfig
from service.messages import WireModel

#: reasons for which a message is out of sequence for its key or the INS (it is not used at all);
#: other refusals (``not_initialised``, ``early``) still leave it the newest of its sensor
OUT_OF_SEQUENCE = frozenset({"duplicate", "time_backwards", "late"})


@dataclass(frozen=True)
class Verdict:
    """The decision on one event: ``reason`` None to accept, else why it was refused -- except
    ``imu_gap``, an IMU sample that is taken but marks the INS lost (counted under that name)."""

    reason: str | None = None

    @property
    def accepted(self) -> bool:
        return self.reason is None

    @property
    def in_sequence(self) -> bool:
        """Not stale for its key or the INS (a GNSS fix may then serve an alignment)."""
        return self.reason not in OUT_OF_SEQUENCE


ACCEPT = Verdict()


class AcceptanceRules:
    """Accept/refuse decisions of one vehicle's events; keeps each (kind, sensor) key's last time."""

    def __init__(self, intake: IntakeConfig):
        self.intake = intake
        self.last_t: dict[tuple[str, str], float] = {}

    def decide(
        self, kind: str, sensor_id: str, msg: WireModel, t_ins: float | None, initialised: bool
    ) -> Verdict:
        """The verdict on one event given the INS time (the last IMU time; None before any IMU)
        and whether the INS is initialised. Records the key's time when the message is taken."""
        if kind == "imu":
            return self._imu(msg.t, msg.dt_s, t_ins)
        key = (kind, sensor_id)
        verdict = self._other(kind, msg.t, self.last_t.get(key), t_ins, initialised)
        if verdict.accepted or verdict.reason == "not_initialised":
            self.last_t[key] = msg.t
        return verdict

    def _imu(self, t: float, dt_s: float, t_ins: float | None) -> Verdict:
        if t_ins is not None:
            if t == t_ins:
                return Verdict("duplicate")
            if t < t_ins:
                return Verdict("time_backwards")
            if (t - t_ins) - dt_s > self.intake.max_imu_gap_s:
                return Verdict("imu_gap")
        return ACCEPT

    def _other(
        self, kind: str, t: float, prev: float | None, t_ins: float | None, initialised: bool
    ) -> Verdict:
        if prev is not None and t == prev:
            return Verdict("duplicate")
        if kind == "init":
            return ACCEPT
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
