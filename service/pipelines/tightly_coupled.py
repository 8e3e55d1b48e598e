"""Tightly coupled INS/GNSS with MHSS integrity (seed 001).

Filter: 17-state closed-loop error-state EKF: the 15 INS error states (``service.ins.error_model``
order, position error in ENU metres) plus the receiver clock bias (m) and drift (m/s), the
private states the raw-GNSS measurement model declares
(:class:`~service.estimation.measurements.gnss_raw.GnssRawModel`: first-order Markov drift,
discretised exactly). The clock's linearisation point is the bank's ``reference["clock"]``, fed
back like the INS, so the whole 17-state correction is closed loop. At the first epoch the clock
reference is the mean residual of the visible satellites (the clock prior keeps
``ClockModel.init_*_std``).

Integrity (``integrity = true``): the bank is an
:class:`~service.estimation.integrity.ins_bank.MhssInsBank` -- main + one sub-filter per
satellite (+ sub-sub filters with ``sub_sub_filters``), one batched bank sharing the INS; only
the main correction is fed back and every member shifts by it. Each epoch the pipeline builds the
rows through the measurement hook and hands them to the
:class:`~service.estimation.integrity.monitor.MhssMonitor` (re-admission, used set, update,
residual windows, separation tests, exclusion, protection levels, verdict); it turns the result
into an :class:`~service.messages.Integrity` message. Without integrity the same monitor runs
at depth 0 (main filter only, no tests, no message).

Why the satellite residual test (seed 001's ramp, docs/seed001.md): the sub-filter that excludes
the faulty satellite has not absorbed any of its ramp, and with range rates and the INS its
prediction of that satellite's range is good to ~0.15 m, so the averaged residual shows a
0.63 m/s ramp about twice as fast as the separation (whose main filter absorbs part of the ramp
into position and clock).
"""

from __future__ import annotations

import numpy as np

from fednav.service.config import ImuModel, TightlyCoupledConfig
from fednav.service.estimation import measurements
from fednav.service.estimation.integrity.ins_bank import MhssInsBank
from fednav.service.estimation.integrity.mhss import MhssBank
from fednav.service.estimation.integrity.monitor import EpochResult, MhssMonitor, MonitorSettings
from fednav.service.estimation.kalman import NotPositiveDefinite
from fednav.service.estimation.measurements.gnss_raw import GnssRawModel
from fednav.service.ins import error_model as em
from fednav.service.ins.mechanisation import NavState
from fednav.service.messages import GnssRaw, Integrity, WireModel
from fednav.service.pipelines.base import Estimate, InitStd, Pipeline, initial_covariance


def raw_gnss_model(cfg) -> GnssRawModel:
    """The raw-GNSS measurement model of a tightly coupled configuration (its receiver clock model,
    elevation mask and range-rate option): the tightly coupled families share it."""
    c = cfg.clock
    return measurements.make(
        "gnss_raw",
        correlation_time_s=c.correlation_time_s,
        bias_psd_m2ps=c.bias_psd_m2ps,
        drift_psd_m2ps3=c.drift_psd_m2ps3,
        init_bias_std_m=c.init_bias_std_m,
        init_drift_std_mps=c.init_drift_std_mps,
        elevation_mask_deg=cfg.elevation_mask_deg,
        use_range_rate=cfg.use_range_rate,
        troposphere=getattr(cfg, "troposphere", False),
        ionosphere=getattr(cfg, "ionosphere", False),
        elevation_weighting=getattr(cfg, "elevation_weighting", False),
        isb_constellations=tuple(getattr(cfg, "isb_constellations", ())),
        isb_psd_m2ps=getattr(cfg, "isb_psd_m2ps", 1e-4),
        init_isb_std_m=getattr(cfg, "init_isb_std_m", 1000.0),
    )


class TightlyCoupled(Pipeline):
    @classmethod
    def sensor_kinds(cls) -> frozenset[str]:
        return frozenset({"gnss_raw"})

    RESIDUAL_WINDOWS: tuple[int, ...] = (1, 10)
    """Windows (epochs) of the satellite residual test; () turns the test off (separation only)."""

    def __init__(self, cfg: TightlyCoupledConfig, imu: ImuModel, major_interval_s: float):
        super().__init__(cfg.name, imu, major_interval_s)
        self.cfg = cfg
        self.depth = 0 if not cfg.integrity else (2 if cfg.sub_sub_filters else 1)
        self.model = raw_gnss_model(cfg)
        self.monitor = MhssMonitor(
            MonitorSettings(
                phase=cfg.phase,
                p_fa=cfg.p_fa,
                p_md=cfg.p_md,
                depth=self.depth,
                exclusion=cfg.exclusion,
                readmit_after_s=cfg.readmit_after_s,
                horizontal_threshold=cfg.horizontal_threshold,
                residual_windows=self.RESIDUAL_WINDOWS,
            )
        )
        self.bank: MhssInsBank | None = None
        self.clock_initialised = False
        self.last: EpochResult | None = None

    # --- pipeline interface ------------------------------------------------------------------------
    def initialise(self, nav: NavState, std: InitStd) -> None:
        private = self.model.private_states
        self._P0 = P0 = initial_covariance(std, self.imu, private)
        restart = self.bank is not None
        self.bank = MhssInsBank(nav, P0, self.imu.noise(), self.major_interval_s, private, self.depth)
        if restart:  # a reset on a running vehicle: the exclusions stay (restart_windows)
            self.monitor.restart_windows()
        else:
            self.monitor.reset()
        self.clock_initialised = False
        self.last = None

    def restore_references(self, refs) -> None:
        super().restore_references(refs)
        self.clock_initialised = "clock" in refs  # the clock as it was: not set again from residuals

    def recover_covariance(self) -> None:
        """Lost positive definiteness: keep the INS, the clock reference and the exclusions; restart
        every member and cross block from the initial covariance (all states zero)."""
        mh = self.bank.mhss
        self.bank.mhss = MhssBank.initial(np.zeros(mh.n), self._P0, mh.sats, mh.depth)
        self.monitor.restart_windows()
        self.restarted()

    def estimate(self) -> Estimate:
        # a copy: the MHSS bank reuses its covariance arrays from update to update
        return Estimate(self.bank.nav(), self.bank.P[0, em.NAV, em.NAV].copy())

    def apply(self, kind: str, sensor_id: str, msg: WireModel, dt_late_s: float = 0.0) -> list[WireModel]:
        if kind != "gnss_raw" or not isinstance(msg, GnssRaw):
            return []
        bank = self.bank
        bank.sync()
        nav = bank.nav()
        if not self.clock_initialised:
            ref = self.model.initial_clock(nav, msg, dt_late_s)
            if ref is not None:
                bank.reference["clock"] = ref
                isb = self.model.initial_isb(nav, msg, ref, dt_late_s)
                if isb is not None:
                    bank.reference["isb"] = isb
                self.clock_initialised = True
        meas = self.model(nav, msg, bank.context(dt_late_s))
        key = f"{kind}/{sensor_id}"
        meas, claimed = self.floors.apply(key, meas)  # no claim below what the stream's history supports
        if meas.floored:
            self.screened["sigma_floor"] += meas.floored
        x0, P0 = bank.x[0].copy(), bank.P[0].copy()
        prior = self.prior_rows(meas, x0, P0)  # (tested here, recorded after the update)
        if self.refused_wholesale(nav.t, meas, x0, P0, prior):  # no update; integrity: an alarm
            res = self.last = self.monitor.refused_epoch(bank, msg.t)
            return [] if res.tests is None else [self.integrity_message(res)]
        try:
            # an unverified or suspect state cannot judge an excluded satellite's health, and a
            # suspect one (possibly corrupt, its covariance not saying so) no satellite's fault
            res = self.last = self.monitor.epoch(
                bank, meas, msg.t, judge_health=self.unverified is None, may_exclude=not self.suspect
            )
        except NotPositiveDefinite:
            # numerical health: never continue on a broken P (docs/DESIGN.md reliability rules)
            self.recover_covariance()
            return []
        if res.update is not None:
            self.mark_aided(nav.t)
            self.record_rows(key, meas, claimed, *prior)
        if res.excluded:
            self.mark_screened(nav.t, "excluded_satellite", len(res.excluded))
        if res.tests is None:
            return []
        return [self.integrity_message(res)]

    def integrity_message(self, res: EpochResult) -> Integrity:
        """The epoch's Integrity message, validated in one call (pydantic builds the nested
        SatelliteTests from their fields: the same message as constructing each, without a
        Python-level model construction per satellite at every epoch)."""
        tests, lim = res.tests, self.monitor.limits
        by_sat = res.residual_by_sat
        sat_tests = (
            [
                {
                    "id": sid,
                    "statistic_m": dh,
                    "threshold_m": th,
                    "vertical_statistic_m": dv,
                    "vertical_threshold_m": tv,
                    "residual_statistic_m": by_sat.get(sid, (0.0, 0.0))[0],
                    "residual_threshold_m": by_sat.get(sid, (0.0, 0.0))[1],
                }
                for sid, dh, th, dv, tv in zip(
                    res.used,
                    tests.d_h.tolist(),
                    tests.T_h.tolist(),
                    tests.d_v.tolist(),
                    tests.T_v.tolist(),
                    strict=False,
                )
            ]
            if len(tests.d_h)
            else []
        )
        return Integrity.model_validate(
            {
                "t": res.t,
                "pipeline": self.name,
                "phase": self.cfg.phase,
                "hpl_m": float(tests.hpl),
                "vpl_m": float(tests.vpl),
                "hal_m": lim.hal_m,
                "val_m": lim.val_m,
                "alarm": res.assessment.alarm,
                "available": res.assessment.available,
                "detected": res.detected,
                "excluded": list(res.excluded),
                "satellites": sat_tests,
                "detected_by": res.detected_by,
            }
        )


__all__ = ["EpochResult", "TightlyCoupled"]
