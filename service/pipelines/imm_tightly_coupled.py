"""Tightly coupled INS/GNSS as an IMM bank of outlier models (He, Nie, Wu 2011).

Filter: the 17-state closed-loop error-state EKF of :mod:`service.pipelines.tightly_coupled`
(15 INS error states + receiver clock bias/drift, the private states of
:class:`~service.estimation.measurements.gnss_raw.GnssRawModel`), here as an
:class:`~service.estimation.ins_filter.InsFilterBank` of one member per model. All members share
the INS and the clock reference (their linearisation point), the transition matrix and the
process noise. At each GNSS epoch the rows come from the measurement hook and
:func:`service.estimation.imm.core.step` runs one IMM cycle (mixing, the models' down-weighted
rows in one batched update, model probabilities, combined output, eq (4)-(16)); the combined
correction is fed back to the INS and the clock, and every member shifts by it (closed loop:
mixing and combining only use differences of members, which the shift leaves unchanged).

Options: ``models = ["normal"]`` is the plain tightly coupled KF (one member, mu = 1);
``gate_p_fa`` puts a chi-square innovation gate with row rejection in front of the update
(:mod:`service.estimation.innovation_gate`, against the combined prior), the simple standard the
IMM is compared with in docs/seed003.md.

Each epoch publishes an :class:`~service.messages.ImmModels` message (probabilities, per-row
factors, gate rejections) on ``fednav/{vehicle}/nav/{pipeline}/models``.
"""

from __future__ import annotations

import numpy as np

from fednav.service.config import ImmTightlyCoupledConfig, ImuModel
from fednav.service.estimation import kalman
from fednav.service.estimation.imm import core
from fednav.service.estimation.imm.models import DownWeighting
from fednav.service.estimation.innovation_gate import gate_rows
from fednav.service.estimation.ins_filter import InsFilterBank
from fednav.service.estimation.kalman import NotPositiveDefinite
from fednav.service.ins import error_model as em
from fednav.service.ins.mechanisation import NavState
from fednav.service.messages import GnssRaw, ImmModels, WireModel
from fednav.service.pipelines.base import Estimate, InitStd, Pipeline, initial_covariance
from fednav.service.pipelines.tightly_coupled import raw_gnss_model


class ImmTightlyCoupled(Pipeline):
    @classmethod
    def sensor_kinds(cls) -> frozenset[str]:
        return frozenset({"gnss_raw"})

    def __init__(self, cfg: ImmTightlyCoupledConfig, imu: ImuModel, major_interval_s: float):
        super().__init__(cfg.name, imu, major_interval_s)
        self.cfg = cfg
        self.model = raw_gnss_model(cfg)
        self.models = tuple(cfg.models)
        self.Pi = np.array(cfg.resolved_transition(), dtype=float)
        self.mu0 = np.array(cfg.resolved_mu0(), dtype=float)
        self.weighting = DownWeighting(cfg.h_percent, cfg.c, cfg.big)
        self.bank: InsFilterBank | None = None
        self.mu = self.mu0.copy()
        self.clock_initialised = False
        self.last: core.ImmStep | None = None
        self.rejected_rows = 0
        self.learner = self._new_learner()

    def _new_learner(self) -> core.TransitionLearner | None:
        tau = self.cfg.resolved_learn_transition_s()
        if tau is None or len(self.models) < 2:
            return None
        return core.TransitionLearner(np.array(self.cfg.resolved_transition(), dtype=float), tau)

    # --- pipeline interface ------------------------------------------------------------------------
    def initialise(self, nav: NavState, std: InitStd) -> None:
        private = self.model.private_states
        self._P0 = P0 = initial_covariance(std, self.imu, private)
        self.bank = InsFilterBank(nav, P0, self.imu.noise(), len(self.models), self.major_interval_s, private)
        self.mu = self.mu0.copy()
        self.clock_initialised = False
        self.last = None
        self.learner = self._new_learner()
        if self.learner is not None:
            self.Pi = self.learner.Pi

    def restore_references(self, refs) -> None:
        super().restore_references(refs)
        self.clock_initialised = "clock" in refs  # the clock as it was: not set again from residuals

    def keep_private_states(self, old) -> None:
        super().keep_private_states(old)
        if old is not None and self.bank.n == old.n and "clock" in old.reference:
            self.clock_initialised = True  # the clock as it was: not set again from residuals

    def recover_covariance(self) -> None:
        """Lost positive definiteness: keep the INS and the clock reference; restart every member
        from the initial covariance (states zero) and the probabilities from mu0."""
        self.bank.x = np.zeros_like(self.bank.x)
        self.bank.P = np.broadcast_to(self._P0, self.bank.P.shape).copy()
        self.mu = self.mu0.copy()
        self.restarted()

    def combined(self) -> tuple[np.ndarray, np.ndarray]:
        """The bank's output now: combined state and covariance (eq 12-13), or with
        ``output = "map"`` the most probable model's."""
        if self.cfg.output == "map":
            j = int(np.argmax(self.mu))
            return self.bank.x[j].copy(), self.bank.P[j].copy()
        return core.combine(self.bank.x, self.bank.P, self.mu)

    def estimate(self) -> Estimate:
        _, P = self.combined()
        return Estimate(self.bank.nav(), P[em.NAV, em.NAV])

    def apply(self, kind: str, sensor_id: str, msg: WireModel, dt_late_s: float = 0.0) -> list[WireModel]:
        if kind != "gnss_raw" or not isinstance(msg, GnssRaw):
            return []
        bank = self.bank
        bank.sync()
        nav = bank.nav()
        if not self.clock_initialised:
            ref = self.model.initial_clock(nav, msg, dt_late_s)
            if ref is None:
                return []
            bank.reference["clock"] = ref
            self.clock_initialised = True
        meas = self.model(nav, msg, bank.context(dt_late_s))
        m = meas.z.shape[0]
        if m == 0 or not (np.all(np.isfinite(meas.z)) and np.all(np.isfinite(meas.H))):
            return []
        key = f"{kind}/{sensor_id}"
        meas, claimed = self.floors.apply(key, meas)  # no claim below what the stream's history supports
        if meas.floored:
            self.screened["sigma_floor"] += meas.floored
        r_var = meas.r_var
        x0, P0 = bank.x[0].copy(), bank.P[0].copy()
        if self.refused_wholesale(nav.t, meas, x0, P0):
            return []
        mask = None
        rejected: list[str] = []
        if self.cfg.gate_p_fa is not None:
            xc, Pc = self.combined()
            keep = gate_rows(xc, Pc, meas.z, meas.H, r_var, self.cfg.gate_p_fa)
            if not keep.all():
                mask = keep
                rejected = [lab for lab, k in zip(meas.labels, keep, strict=True) if not k]
                self.rejected_rows += len(rejected)
                self.mark_screened(nav.t, "innovation_gate", len(rejected))
        try:
            st = core.step(
                bank.x,
                bank.P,
                self.mu,
                self.Pi,
                meas.z,
                meas.H,
                r_var,
                self.models,
                self.weighting,
                self.cfg.likelihood,
                mask,
                self.cfg.selection_correction,
                self.cfg.resolved_residuals(),
            )
            if not kalman.is_positive_definite(st.P).all():
                raise NotPositiveDefinite("IMM member covariance after the update")
        except NotPositiveDefinite:
            self.recover_covariance()
            return []
        if self.learner is not None:
            self.Pi = self.learner.update(float(nav.t), self.mu, self.Pi, st.log_lik)
        bank.x, bank.P, self.mu, self.last = st.x, st.P, st.mu, st
        bank.feedback(self.combined()[0])
        self.mark_aided(nav.t)
        self.record_prior_rows(key, meas, claimed, x0, P0, mask)
        xc_prior = self.mu_prior_residual(st)
        return [
            ImmModels(
                t=msg.t,
                pipeline=self.name,
                likelihood=self.cfg.likelihood,
                models=list(self.models),
                probabilities=[float(p) for p in st.mu],
                rows=list(meas.labels),
                standardised_residual=[float(v) for v in xc_prior],
                h_scale=st.h_scale.tolist(),
                r_scale=st.r_scale.tolist(),
                rejected=rejected,
            )
        ]

    @staticmethod
    def mu_prior_residual(st: core.ImmStep) -> np.ndarray:
        """Standardised residuals of the rows weighted over the predicted probabilities c."""
        return st.c @ st.v


__all__ = ["ImmTightlyCoupled"]
