"""Federated (seed 000/002/004) and centralised INS pipelines on the federated core.

Both own ONE INS and ONE ``InsFilterBank`` around it (all members share the INS linearisation
point, closed loop) driven by ``service.estimation.federated.core.FederatedCore``:

* ``Federated``: one local filter per configured subsystem (e.g. INS/BDS on ``gnss_fix``,
  INS/CNS on ``star``), plus a master member when ``master_share`` > 0. Each aiding message
  updates only its subsystem's local (fault-tested by the configured plug-in). ``apply``
  returns a ``Faults`` message per aiding message: the tested subsystem's per-observation
  statistics, thresholds, flags and isolation, and every local's 15 sharing coefficients as in
  effect for this update (set by the previous fusion; they define the prior that was tested).
* Fusion timing (seed 000 algorithm 2: locals update, then the master fuses and resets): once
  per aiding EPOCH, i.e. after all messages with the same time (a GNSS fix and a star
  attitude at the same t are one epoch, as in the paper's 1 s filter period). The fusion runs
  when time moves on (next IMU data) or when an aiding message of a later time arrives; an
  output requested meanwhile gets a pure view of the fused estimate (``_epoch_view``), so
  outputs never change the filter. For scalar shares the timing changes nothing (exact);
  for per-state shares it matters: every fusion-reset of diagonal shares adds spurious
  information, so fusing after each message would double it.
* ``Centralized``: the comparator, a single filter (bank of one) on every supported sensor's
  rows with optional fault handling (one test per sensor kind); it returns ``Faults`` only when
  fault handling is on.

Solutions come from the fused estimate: ``Estimate(nav = INS state, P9 = P_g[NAV, NAV])`` (after
the feedback the fused error state is zero with fusion-reset, ~zero with no_reset).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from fednav.service.config import CentralizedConfig, FederatedConfig, ImuModel
from fednav.service.estimation import measurements
from fednav.service.estimation.federated.core import FederatedCore
from fednav.service.estimation.federated.fault_tests import FaultTest, make_fault_test
from fednav.service.estimation.federated.sharing import get_strategy
from fednav.service.estimation.ins_filter import InsFilterBank
from fednav.service.estimation.measurements import MeasurementModel
from fednav.service.ins import error_model as em
from fednav.service.ins.mechanisation import Ins, NavState
from fednav.service.messages import Faults, ObservationFault, SubsystemFaults, WireModel
from fednav.service.pipelines.base import (
    Estimate,
    InitStd,
    Pipeline,
    initial_covariance,
    model_options,
    sensor_option_errors,
)


@dataclass
class _Channel:
    """Where one sensor kind goes: its measurement model, the owning local, the report name and
    its fault test."""

    model: MeasurementModel
    owner: int
    name: str
    test: FaultTest


class _CorePipeline(Pipeline):
    """Shared machinery of Federated and Centralized (one core, two configurations)."""

    restores_members = True  # a restart from a checkpoint: each local as it was
    bias_test = True  # innovations off centre: degraded (Pipeline.bias_test)
    #: a kind accepted before whose rows the fault test keeps flagging (Pipeline.refused_long):
    #: all of them, or one position row, for 30 s. Longer than the loosely coupled gate's 10 s
    #: and 20 s: the paper's fault test isolates a faulty receiver and carries on (its per-row
    #: test flags the demo's 15 s step whole, and seed 000's faults last up to 20 s). (The
    #: underwater pipeline keeps None: its USBL excluded by chi2_reconfig stays excluded, the
    #: paper's reconfiguration.)
    refusal_recovery_s: float | None = 30.0
    row_refusal_factor = 1.0

    @classmethod
    def sensor_kinds(cls) -> frozenset[str]:
        """Every registered model without private states (the locals share the 15 INS states;
        private states per local are not implemented yet)."""
        return measurements.plain_kinds()

    def __init__(
        self,
        name: str,
        imu: ImuModel,
        major_interval_s: float,
        *,
        subsystems: list[tuple[str, list[str]]],
        sharing: str,
        fault_handling: str,
        false_alarm_prob: float,
        reset: str = "fusion_reset",
        master_share: float = 0.0,
        floor_share: float = 0.05,
        report_faults: bool = True,
        model_options: dict[str, dict] | None = None,
        doubt_prob: float | None = None,
    ):
        super().__init__(name, imu, major_interval_s)
        self.local_names = [s for s, _ in subsystems]
        self.strategy = get_strategy(sharing)
        self.reset_mode = reset
        self.master_share = float(master_share)
        self.floor_share = float(floor_share)
        #: the soft edge of the fault tests (FederatedCore, "Doubtful updates"; None: hard gates)
        self.doubt_prob = doubt_prob
        self.report_faults = report_faults
        self.channels: dict[str, _Channel] = {}
        for i, (sub_name, kinds) in enumerate(subsystems):
            for kind in kinds:
                if kind not in self.sensor_kinds():
                    raise ValueError(
                        f"pipeline {name!r}: no measurement model for sensor kind {kind!r} "
                        f"(subsystem {sub_name!r}); supported: {sorted(self.sensor_kinds())}"
                    )
                if kind in self.channels:
                    raise ValueError(
                        f"pipeline {name!r}: sensor kind {kind!r} is in two subsystems "
                        f"({self.channels[kind].name!r}, {sub_name!r}); it would be counted twice"
                    )
                self.channels[kind] = _Channel(
                    measurements.make(kind, **(model_options or {}).get(kind, {})),
                    i,
                    sub_name,
                    make_fault_test(fault_handling, false_alarm_prob),
                )
        self.core: FederatedCore | None = None
        self._version = 0
        self._epoch_t: float | None = None  # time of an aiding epoch whose fusion is pending
        self._fused_key: tuple | None = None
        self._fused_P: np.ndarray | None = None
        self._view_key: int | None = None
        self._view: Estimate | None = None
        self._fused_view: tuple[np.ndarray, np.ndarray] | None = None

    # --- Pipeline interface ---------------------------------------------------------------------
    def consumed_kinds(self) -> frozenset[str]:
        return frozenset(self.channels)

    def private_states(self) -> tuple:
        """Private-state blocks every member carries after the 15 common states (never fused):
        those of the configured models (e.g. the correlated GNSS error of ``gnss_fix``), each
        observed and fed back by the local that owns its sensor (``_feedback_private``)."""
        return tuple(b for ch in self.channels.values() for b in ch.model.private_states)

    def _feedback_private(self) -> None:
        """Each owning local's estimate of its model's private blocks into their references
        (closed loop, like the INS; seed 004's DVL block is fed back the same way)."""
        bank = self.bank
        for ch in self.channels.values():
            for block in ch.model.private_states:
                cols = bank.columns.get(block.name)
                if cols is None:
                    continue
                part = bank.x[ch.owner, cols]
                if np.all(np.isfinite(part)) and np.any(part):
                    dx = np.zeros(bank.n - em.N_STATES)
                    dx[cols.start - em.N_STATES : cols.stop - em.N_STATES] = part
                    bank.feedback_private(dx)

    def initialise(self, nav: NavState, std: InitStd) -> None:
        n_locals = len(self.local_names)
        private = self.private_states()
        self._P0 = initial_covariance(std, self.imu, private)
        self.bank = InsFilterBank(
            nav,
            self._P0,
            self.imu.noise(),
            bank_size=FederatedCore.bank_size(n_locals, self.master_share),
            major_interval_s=self.major_interval_s,
            private=private,
        )
        self.core = FederatedCore(
            self.bank,
            n_locals,
            self.strategy,
            reset=self.reset_mode,
            master_share=self.master_share,
            floor_share=self.floor_share,
            doubt_prob=self.doubt_prob,
        )
        self.core.start()
        self._epoch_t = None
        for ch in self.channels.values():
            ch.test.reset()
        self._version += 1

    def push_imu(self, dtheta_rad, dvel_mps, dt_s: float, t_end: float | None = None) -> None:
        if self._epoch_t is not None:
            self._end_epoch()  # time moves on: the aiding epoch is complete
        self.bank.push_imu(dtheta_rad, dvel_mps, dt_s, t_end)

    def advance(self, pre) -> None:
        if self._epoch_t is not None:
            self._end_epoch()  # time moves on: the aiding epoch is complete
        self.bank.advance(pre)

    def _end_epoch(self) -> None:
        """Seed 000 algorithm 2 once per aiding epoch: master fusion, reset, feedback.

        Runs outside the engine's ``apply`` guard (from push_imu / estimate), so a covariance
        that lost positive definiteness is recovered here (docs/DESIGN.md reliability rules).
        """
        self._epoch_t = None
        fused = self._fused_view if self._view_key == self._version else None  # reuse the view's
        self._version += 1
        try:
            self.core.fuse_and_reset(fused)
        except np.linalg.LinAlgError:
            self.recover_covariance()
            return
        self._feedback_private()

    def recover_covariance(self) -> None:
        """Numerical-health recovery: keep the INS, restart every member from the initial
        covariance (re-divided by the sharing strategy), zero error states, flag it."""
        bank = self.bank
        bank.x[:] = 0.0
        for ref in bank.reference.values():  # private references restart with the covariance
            ref[:] = 0.0
        bank.P = np.broadcast_to(self._P0, bank.P.shape).copy()
        bank.q_scale = np.ones_like(bank.q_scale)
        self.core.start()
        self._epoch_t = None
        self._version += 1
        self.restarted()

    def apply(self, kind: str, sensor_id: str, msg: WireModel, dt_late_s: float = 0.0) -> list[WireModel]:
        ch = self.channels.get(kind)
        if ch is None:
            return []
        bank, core = self.bank, self.core
        if self._epoch_t is not None and bank.t != self._epoch_t:
            self._end_epoch()
        meas = ch.model(bank.nav(), msg, bank.context(dt_late_s))
        if meas is None:
            return []
        key = f"{kind}/{sensor_id}"
        meas, claimed = self.floors.apply(key, meas)  # no claim below what the stream's history supports
        if meas.floored:
            self.screened["sigma_floor"] += meas.floored
        x0, P0 = bank.x[ch.owner].copy(), bank.P[ch.owner].copy()
        held = self.held_on_return(key, bank.t, meas, x0, P0, ch.test.refuses)
        if held is not None:  # back after a gap: its first messages must agree with the filter first
            if held.all():
                return []
            meas, claimed = measurements.rows_of(meas, ~held), claimed[~held]
        self._version += 1
        upd = core.update(ch.owner, meas.z, meas.H, meas.R, ch.test, self.source_groups(key, meas))
        self.end_source_episode(key, bool(upd.decision.flagged.any()))
        self.record_prior_rows(key, meas, claimed, x0, P0, upd.decision.passed, upd.decision.used)
        # the state further off than its covariance says (a test that refuses nothing, the paper's
        # unscreened comparators, is the paper's plain filter: its status says so, no inflation)
        flagged = bool(upd.decision.flagged.any())
        if ch.test.refuses and not flagged and self.bias_test and self.bias.is_failing(key):
            S_diag = np.einsum("ij,jk,ik->i", meas.H, P0, meas.H) + np.diagonal(meas.R)
            inflated = self.inflate_for_bias(key, meas, S_diag, bank.P, self.fused_covariance())
            if inflated is not None:
                bank.P = inflated
                self._version += 1
        self._epoch_t = bank.t  # fused when the epoch ends (next IMU data or a later aiding time)
        # rows its test keeps refusing: the filter may be the one wrong (a test that refuses
        # nothing, the paper's unscreened comparators, takes its faults: never)
        if ch.test.refuses and self.refused_long(kind, bank.t, meas, upd.decision.flagged, key):
            self.report(self.refusal_event(kind, bank.t))  # the lifecycle checks the state
        if upd.rows_used:
            self._trusted.add(kind)
            self.mark_aided(bank.t, meas.H, upd.decision.used)
        # the stream's cadence for the return check counts every message its fault test judged:
        # a stream isolated by the test and back is the test's to re-admit (the paper's method,
        # its per-observation flags published throughout); one back after silence is checked
        self.note_used(key, bank.t)
        if upd.doubt > 0.0:  # (core: "Doubtful updates")
            self.screened["doubted_update"] += 1
        isolated = int(np.count_nonzero(upd.decision.isolated))
        if isolated:
            self.mark_screened(bank.t, "fault_test", isolated)
        if not self.report_faults:
            return []
        d = upd.decision
        obs = [
            ObservationFault(
                label=label,
                statistic=float(d.statistic[j]),
                threshold=float(d.threshold[j]),
                flagged=bool(d.flagged[j]),
                isolated=bool(d.isolated[j]),
            )
            for j, label in enumerate(meas.labels)
        ]
        return [
            Faults(
                t=float(bank.t),
                pipeline=self.name,
                subsystems=[SubsystemFaults(name=ch.name, isolated=d.subsystem_isolated, observations=obs)],
                sharing=self.sharing_report(),
            )
        ]

    def estimate(self) -> Estimate:
        if self._epoch_t is not None:
            return self._epoch_view()
        return Estimate(self.bank.nav(), self.fused_covariance()[em.NAV, em.NAV])

    def _epoch_view(self) -> Estimate:
        """The fused estimate while an epoch's fusion is pending (more aiding at this time may
        follow), as a pure view: x_g applied to a COPY of the INS state, and P_g. Requesting an
        output never changes the filter, so results do not depend on outputs or truth being
        present; the real fusion-reset later applies the identical correction."""
        if self._view_key != self._version:
            try:
                x_g, P_g = self._fused_view = self.core.fuse()
            except np.linalg.LinAlgError:
                self.recover_covariance()
                return self.estimate()
            ins = Ins(self.bank.nav(), self.major_interval_s)
            ins.correct(x_g[em.POS], x_g[em.VEL], x_g[em.ATT], x_g[em.GYRO], x_g[em.ACC])
            self._view = Estimate(ins.state, P_g[em.NAV, em.NAV])
            self._view_key = self._version
        return self._view

    # --- federated outputs ------------------------------------------------------------------------
    def fused_covariance(self) -> np.ndarray:
        """(15, 15) master-fused covariance of the current bank (cached per state change)."""
        key = (self.bank.ins.state.t, self._version)
        if key != self._fused_key:
            try:
                self._fused_P = self.core.fused_covariance()
            except np.linalg.LinAlgError:
                self.recover_covariance()
                self._fused_P = self.core.fused_covariance()
            self._fused_key = (self.bank.ins.state.t, self._version)
        return self._fused_P

    def sharing_report(self) -> dict[str, list[float]]:
        """{local name: its 15 common-state shares} (+ "master" when it keeps a share)."""
        G = self.core.shares
        out = {name: [float(g) for g in G[i]] for i, name in enumerate(self.local_names)}
        if G.shape[0] > len(self.local_names):
            out["master"] = [float(g) for g in G[-1]]
        return out


class Federated(_CorePipeline):
    """Federated filter: one local per ``FederatedConfig.subsystems`` entry (see module doc)."""

    @classmethod
    def config_errors(cls, cfg: FederatedConfig) -> list[tuple[str, str]]:
        out, owner = [], {}
        for i, sub in enumerate(cfg.subsystems):
            for j, kind in enumerate(sub.sensors):
                loc = f"subsystems.{i}.sensors.{j}"
                if kind not in cls.sensor_kinds():
                    out.append(
                        (
                            loc,
                            f"sensor kind {kind!r} is not implemented in a federated pipeline "
                            f"(implemented: {', '.join(sorted(cls.sensor_kinds()))})",
                        )
                    )
                elif kind in owner:
                    out.append((loc, f"sensor kind {kind!r} is already in subsystem {owner[kind]!r}"))
                else:
                    owner[kind] = sub.name
        return out + sensor_option_errors(cfg, set(owner))

    def __init__(self, cfg: FederatedConfig, imu: ImuModel, major_interval_s: float):
        super().__init__(
            cfg.name,
            imu,
            major_interval_s,
            subsystems=[(s.name, list(s.sensors)) for s in cfg.subsystems],
            sharing=cfg.sharing,
            fault_handling=cfg.fault_handling,
            false_alarm_prob=cfg.false_alarm_prob,
            reset=cfg.reset,
            master_share=cfg.master_share,
            floor_share=cfg.floor_share,
            report_faults=True,
            model_options=model_options(cfg),
            doubt_prob=cfg.soft_gate_prob,
        )
        self.cfg = cfg


def central_kinds(cfg: CentralizedConfig) -> list[str]:
    """The kinds of the centralised comparator: ``sensors``, else every registered kind whose
    default model needs no states of its own."""
    if cfg.sensors is not None:
        return list(dict.fromkeys(cfg.sensors))
    return sorted(k for k in measurements.plain_kinds() if not measurements.make(k).private_states)


class Centralized(_CorePipeline):
    """Centralised comparator: one filter on all supported sensors (one fault test per kind).

    Family "loosely_coupled" for dashboards: a single INS/GNSS(/CNS) filter, no sharing.
    """

    def __init__(self, cfg: CentralizedConfig, imu: ImuModel, major_interval_s: float):
        super().__init__(
            cfg.name,
            imu,
            major_interval_s,
            subsystems=[("central", central_kinds(cfg))],
            sharing="fixed",
            fault_handling=cfg.fault_handling,
            false_alarm_prob=cfg.false_alarm_prob,
            report_faults=cfg.fault_handling != "none",
            model_options=model_options(cfg),
            doubt_prob=cfg.soft_gate_prob,
        )
        self.cfg = cfg
        # report per sensor kind (one test each), all owned by the single filter
        for kind, ch in self.channels.items():
            ch.name = kind

    @classmethod
    def config_errors(cls, cfg: CentralizedConfig) -> list[tuple[str, str]]:
        kinds = central_kinds(cfg)
        out = [
            (f"sensors.{i}", f"sensor kind {k!r} is not implemented in a centralised pipeline")
            for i, k in enumerate(kinds)
            if k not in cls.sensor_kinds()
        ]
        return out + sensor_option_errors(cfg, set(kinds))

    def sharing_report(self) -> dict[str, list[float]]:
        return {}


__all__ = ["Federated", "Centralized"]
