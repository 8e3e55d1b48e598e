"""Loosely coupled INS/GNSS: 15-state closed-loop error-state EKF, position + velocity aiding
(and star-tracker attitude when configured and present).

Optional states beyond the 15 (each a private block after them; docs/own_data.md "Unknown antenna
offset / IMU scale factors"):

* the sensors' own (correlated GNSS error, barometer offset, ...), declared by their models;
* ``estimate_gnss_lever_arm``: the GNSS antenna lever arm (block ``gnss_lever_arm``, body axes,
  prior ``gnss_lever_arm_b_m`` +- ``gnss_lever_arm_std_m``), observed in turns;
* ``estimate_imu_scale_factors``: the gyro and accelerometer scale-factor errors (block
  ``imu_scale``, coupled into the INS error dynamics by the filter bank), observed in turns and
  speed changes.

The estimated lever arm and scale factors are published (at most once per
``STATES_PERIOD_S`` of fix updates) as ``Faults.states`` of subsystem ``gnss_fix`` with their
1-sigma: names ``gnss_lever_arm_{x,y,z}_m`` (the whole lever arm, configured plus estimated) and
``{gyro,accel}_scale_{x,y,z}_ppm``.
"""

from __future__ import annotations

from collections import deque

import numpy as np

from fednav.service.config import ImuModel, LooselyCoupledConfig
from fednav.service.estimation import kalman, measurements
from fednav.service.estimation.ins_filter import InsFilterBank, imu_scale_block
from fednav.service.estimation.measurements import MeasurementModel
from fednav.service.estimation.measurements.gnss_fix import LEVER_BLOCK
from fednav.service.ins import error_model as em
from fednav.service.ins.mechanisation import NavState
from fednav.service.messages import Faults, ObservationFault, StateEstimate, SubsystemFaults, WireModel
from fednav.service.pipelines.base import (
    Estimate,
    InitStd,
    Pipeline,
    initial_covariance,
    model_options,
    sensor_option_errors,
)


def configured_kinds(cfg: LooselyCoupledConfig) -> list[str]:
    """The sensor kinds a loosely coupled configuration fuses (``sensors``; default gnss_fix, and
    star when ``use_star``)."""
    if cfg.sensors is not None:
        return list(dict.fromkeys(cfg.sensors))
    return ["gnss_fix"] + (["star"] if cfg.use_star else [])


#: the estimated lever arm / scale factors are published at most this often (s of sensor time)
STATES_PERIOD_S = 1.0


class LooselyCoupled(Pipeline):
    bias_test = True  # innovations off centre: degraded (Pipeline.bias_test)

    @classmethod
    def sensor_kinds(cls) -> frozenset[str]:
        """Every kind of the sensor registry with a measurement model (private states included:
        the bank is built with them)."""
        return frozenset(measurements.REGISTRY)

    @classmethod
    def config_errors(cls, cfg: LooselyCoupledConfig) -> list[tuple[str, str]]:
        kinds = configured_kinds(cfg)
        out = [
            (
                f"sensors.{i}",
                f"sensor kind {k!r} has no measurement model (known: {sorted(cls.sensor_kinds())})",
            )
            for i, k in enumerate(kinds)
            if k not in cls.sensor_kinds()
        ]
        if cfg.estimate_gnss_lever_arm and "gnss_fix" not in kinds:
            out.append(("estimate_gnss_lever_arm", f"needs gnss_fix among the pipeline's sensors {kinds}"))
        return out + sensor_option_errors(cfg, set(kinds))

    def __init__(self, cfg: LooselyCoupledConfig, imu: ImuModel, major_interval_s: float):
        super().__init__(cfg.name, imu, major_interval_s)
        self.cfg = cfg
        options = model_options(cfg)
        self.models: dict[str, MeasurementModel] = {
            k: measurements.make(k, **options.get(k, {})) for k in configured_kinds(cfg)
        }
        self.private = tuple(b for m in self.models.values() for b in m.private_states)
        if cfg.estimate_imu_scale_factors:
            self.private += (
                imu_scale_block(cfg.gyro_scale_factor_std_ppm * 1e-6, cfg.accel_scale_factor_std_ppm * 1e-6),
            )
        #: private blocks published as Faults.states (the lever arm, the scale factors)
        self._reported = tuple(b.name for b in self.private if b.name in (LEVER_BLOCK, em.SCALE_BLOCK))
        self._states_t: float | None = None  # time of the last published states
        self.last_nis: float | None = None
        #: (t, kind, NIS, dof) of the latest updates, for consistency checks
        self.nis_history: deque = deque(maxlen=2048)
        self.refusal_recovery_s = cfg.gate_recovery_s
        self._gate_reported: set[str] = set()  # kinds whose last published Faults refused rows

    def consumed_kinds(self) -> frozenset[str]:
        return frozenset(self.models)

    def initialise(self, nav: NavState, std: InitStd) -> None:
        self._gate_reported.clear()
        self._P0 = initial_covariance(std, self.imu, self.private)
        self.bank = InsFilterBank(
            nav, self._P0, self.imu.noise(), major_interval_s=self.major_interval_s, private=self.private
        )

    def apply(self, kind: str, sensor_id: str, msg: WireModel, dt_late_s: float = 0.0) -> list[WireModel]:
        model = self.models.get(kind)
        if model is None:
            return []
        bank = self.bank
        nav = bank.nav()
        meas = model(nav, msg, bank.context(dt_late_s))
        if meas is None:
            return []
        key = f"{kind}/{sensor_id}"
        meas, claimed = self.floors.apply(key, meas)  # no claim below what the stream's history supports
        if meas.floored:
            self.screened["sigma_floor"] += meas.floored
        screening = self.cfg.innovation_gate_sigma is not None
        held = self.held_on_return(key, nav.t, meas, bank.x[0], bank.P[0], screening)
        if held is not None:  # back after a gap: its first messages must agree with the filter first
            if held.all():
                return []
            meas, claimed = measurements.rows_of(meas, ~held), claimed[~held]
        x, P, res = kalman.update(bank.x, bank.P, meas.z, meas.H, meas.R)
        prior = res
        gate = self.cfg.innovation_gate_sigma
        std0 = res.standardised[0]
        # the gate on floats first (|r| > gate as numpy compares it; a NaN is never beyond it): the
        # usual update flags no row, and then builds none of the row masks (flagged, refused None:
        # every row within the gate, or no gate; ~10 numpy calls fewer per fix epoch)
        any_flagged = gate is not None and any(abs(v) > gate for v in std0.tolist())
        if any_flagged:  # the rest of a failing row's source is suspect (Pipeline.source_groups)
            flagged = np.abs(std0) > gate
            groups = self.source_groups(key, meas)
            refused = measurements.refused_with_source(std0, flagged, groups)
        else:
            flagged = refused = None
            self.end_source_episode(key, False)
        outputs: list[WireModel] = []
        due = (any_flagged or bool(self._refused_since)) and self.refused_long(
            kind, nav.t, meas, flagged if any_flagged else np.zeros(len(meas.z), bool), key
        )
        if any_flagged:  # (refused: the flagged rows and the suspects of their sources)
            self.mark_screened(nav.t, "innovation_gate", int(refused.sum()))
            outputs.append(self._gate_faults(nav.t, kind, meas.labels, res.standardised[0], flagged, refused))
            self._gate_reported.add(kind)
            if flagged.all() and not due:  # every row beyond the gate on its own (not by its group)
                return outputs
            if due:
                # a sensor accepted before, every row refused for gate_recovery_s, or one of
                # its position rows for twice that (Pipeline.refused_long): the filter, not the
                # sensor, is wrong
                event = self.refusal_event(kind, nav.t)
                self.recover_covariance()
                # and its state is suspect (service/lifecycle.py); refused again soon after the
                # covariance restart: the restart did not help, the whole state is reset
                self.report(event)
                x, P, res = kalman.update(bank.x, bank.P, meas.z, meas.H, meas.R)
                refused = np.zeros_like(refused)
            else:
                x, P, res = kalman.update(bank.x, bank.P, meas.z, meas.H, meas.R, mask=~refused[None, :])
        elif kind in self._gate_reported:  # the first update the gate passes whole: say it is clear
            self._gate_reported.discard(kind)
            clear = np.zeros(len(meas.z), bool)
            outputs.append(self._gate_faults(nav.t, kind, meas.labels, std0, clear, clear))
        # the rows within the gate (the suspects of a faulty source too; None: every row)
        used = None if flagged is None else ~flagged
        taken = None if refused is None else ~refused
        S_diag = prior.S[0].diagonal()
        self.record_rows(key, meas, claimed, prior.innovation[0], S_diag, used, taken)
        if refused is not None and refused.size and refused.all():
            return outputs  # the flagged rows and the rest of their sources: nothing left to take
        # the state further off than its covariance says: the update again (a filter without a
        # gate takes whatever comes, as configured: its status says so, no inflation)
        biased = screening and not any_flagged and self.bias_test and self.bias.is_failing(key)
        inflated = self.inflate_for_bias(key, meas, S_diag, bank.P) if biased else None
        if inflated is not None:
            bank.P = inflated
            mask = np.ones((1, len(meas.z)), bool) if taken is None else taken[None, :]
            x, P, res = kalman.update(bank.x, bank.P, meas.z, meas.H, meas.R, mask=mask)
        self._trusted.add(kind)
        if not kalman.is_positive_definite(P)[0]:
            # numerical health: never continue on a broken P; keep the INS, re-initialise the
            # covariance to the initial one and flag it
            self.recover_covariance()
            return outputs
        bank.x, bank.P = x, P
        bank.feedback(bank.x[0].copy())
        self.note_used(key, nav.t)
        self.last_nis = float(res.nis[0])
        self.nis_history.append((nav.t, kind, self.last_nis, int(res.dof[0])))
        self.mark_aided(nav.t, meas.H, taken)
        if self._reported and kind == "gnss_fix":
            self._add_states(nav.t, outputs)
        return outputs

    def _add_states(self, t: float, outputs: list[WireModel]) -> None:
        """The estimated lever arm / scale factors onto this update's Faults (a new one when the
        gate refused nothing), at most once per ``STATES_PERIOD_S``."""
        if self._states_t is not None and 0.0 <= t - self._states_t < STATES_PERIOD_S:
            return
        self._states_t = t
        states = self.private_state_estimates()
        for i, msg in enumerate(outputs):
            if isinstance(msg, Faults) and msg.subsystems and msg.subsystems[0].name == "gnss_fix":
                outputs[i] = msg.model_copy(update={"states": states})
                return
        sub = SubsystemFaults(name="gnss_fix", isolated=False, observations=[])
        outputs.append(Faults(t=t, pipeline=self.name, subsystems=[sub], states=states))

    def private_state_estimates(self) -> list[StateEstimate]:
        """The estimated lever arm (configured plus estimated, m) and scale factors (ppm) with
        their 1-sigma."""
        bank = self.bank
        out = []
        for name in self._reported:
            cols = bank.columns[name]
            est = bank.reference[name] - bank.x[0, cols]
            sd = np.sqrt(np.clip(np.diagonal(bank.P[0])[cols], 0.0, None))
            if name == LEVER_BLOCK:
                est = est + self.models["gnss_fix"].lever_arm_b_m
                names = [n for b in self.private if b.name == name for n in b.names]
            else:
                est, sd = est * 1e6, sd * 1e6
                names = [f"{n}_ppm" for n in em.SCALE_NAMES]
            rows = zip(names, est, sd, strict=True)
            out += [StateEstimate(name=n, value=float(v), std=float(s)) for n, v, s in rows]
        return out

    def _gate_faults(self, t: float, kind: str, labels, standardised, flagged, refused) -> Faults:
        """The gate's decision on Faults (published when it refuses a row, and once more at the
        first update it passes whole, so that a subscriber's isolation state clears): per row
        |r|/sqrt(S) against the gate; rows beyond it are flagged, flagged rows and the suspect
        rows of their source (measurements.refused_with_source) isolated."""
        gate = float(self.cfg.innovation_gate_sigma)
        rows = [
            ObservationFault(
                label=label, statistic=float(abs(v)), threshold=gate, flagged=bool(f), isolated=bool(r)
            )
            for label, v, f, r in zip(labels, standardised, flagged, refused, strict=True)
        ]
        return Faults(
            t=t,
            pipeline=self.name,
            subsystems=[SubsystemFaults(name=kind, isolated=bool(refused.all()), observations=rows)],
        )

    def recover_covariance(self) -> None:
        self.bank.x[:] = 0.0
        for name in self.bank.reference:  # private references (correlated GNSS error) restart too
            self.bank.reference[name][:] = 0.0
        self.bank.P[:] = self._P0
        self.restarted()

    def estimate(self) -> Estimate:
        return Estimate(self.bank.nav(), self.bank.P[0, em.NAV, em.NAV])
