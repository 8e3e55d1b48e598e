"""Tightly coupled INS/GNSS with MHSS integrity (seed 001).

Filter: 17-state closed-loop error-state EKF on :class:`InsFilterBank`: the 15 INS error states
(``service.ins.error_model`` order, position error in ENU metres) plus the receiver clock bias
(m) and drift (m/s) as private states with seed 001's model

    d(b)/dt = d + w_b,   d(d)/dt = -beta d + w_d    (first-order Markov drift, beta = 1/tau)

discretised exactly (Van Loan). The clock's linearisation point ``clock_ref`` (bias, drift) lives
next to the INS; the main filter's clock correction is fed back into it like the INS states, so
the whole 17-state correction is closed loop. Measurement rows per satellite: pseudorange and
(``use_range_rate``) range rate, z = predicted - measured, from
:mod:`service.estimation.measurements.gnss_raw`. At the first epoch the clock reference is the mean
residual of the visible satellites (the clock prior keeps ``ClockModel.init_*_std``).

Integrity (``integrity = true``): the bank is an :class:`~service.estimation.integrity.mhss.MhssBank` --
main + one sub-filter per satellite (+ sub-sub filters with ``sub_sub_filters``), one batched
bank sharing the INS; only the main correction is fed back and every member shifts by it. The
cross-covariances are propagated together with the member covariances in the bank's own time
update (this class overrides :meth:`InsFilterBank.propagate`). Per epoch:

1. satellites below the elevation mask (seen from the INS) and excluded satellites are not used;
   excluded satellites are tested against the main for re-admission
   (:class:`~service.estimation.integrity.monitor.ExclusionBook`);
2. a change of the used set rebuilds the bank (:meth:`MhssBank.rebuild`: exact for rising and
   setting satellites);
3. batched update of all members and cross blocks, feedback of the main correction;
4. main-vs-sub tests (horizontal; + vertical in phases with a VAL) and the satellite residual
   tests (each satellite's pseudorange against the sub-filter that excludes it, over windows of
   ``RESIDUAL_WINDOWS`` epochs: :class:`~service.estimation.integrity.monitor.ResidualWindows`) ->
   detection; on detection the exclusion search (sub-sub tests; residual-flagged satellites are
   candidates too); an excluded satellite is purged (new main = its sub-filter, whose correction
   is fed back at once) and the tests/PLs are recomputed on the new bank;
5. an :class:`~service.messages.Integrity` message (HPL/VPL against the phase's HAL/VAL, alarm,
   availability, per-satellite statistics and thresholds).

False-alarm budget: ``p_fa`` per epoch is split evenly over the test families -- horizontal
separation (+ vertical with a VAL) and one family per residual window -- each of N two-sided
tests: K = Q^-1(p_fa / (2 N n_families)). The protection levels use the separation K (the
residual tests only add detections, so the PLs stay valid). Why the residual test (seed 001's
ramp, docs/seed001.md): the sub-filter that excludes the faulty satellite has not absorbed any of
its ramp, and with range rates and the INS its prediction of that satellite's range is good to
~0.15 m, so the averaged residual shows a 0.63 m/s ramp about twice as fast as the separation
(whose main filter absorbs part of the ramp into position and clock).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import scipy.linalg

from service.config import ClockModel, ImuModel, TightlyCoupledConfig
from service.estimation.ins_filter import InsFilterBank
from service.estimation.integrity import monitor as integrity
from service.estimation.integrity.mhss import (
    BankUpdate,
    MhssBank,
    SeparationTests,
    k_fa,
    k_fa_horizontal,
    k_md,
    residual_test,
)
from service.estimation.kalman import is_positive_definite
from service.estimation.measurements import gnss_raw as gm
from service.ins import error_model as em
from service.ins.mechanisation import NavState
from service.messages import GnssRaw, Integrity, SatelliteTest, WireModel
from service.pipelines.base import Estimate, InitStd, Pipeline, initial_covariance

N_STATES = gm.N_STATES_TC


def clock_transition(T: float, clock: ClockModel) -> tuple[np.ndarray, np.ndarray]:
    """Exact discrete clock model over T: (Phi (2, 2), Qd (2, 2)) for x = [bias_m, drift_mps].

    F = [[0, 1], [0, -beta]], Qc = diag(S_b, S_d); Van Loan: expm([[-F, Qc], [0, F']] T).
    """
    beta = 1.0 / clock.correlation_time_s
    F = np.array([[0.0, 1.0], [0.0, -beta]])
    M = np.zeros((4, 4))
    M[:2, :2] = -F
    M[:2, 2:] = np.diag([clock.bias_psd_m2ps, clock.drift_psd_m2ps3])
    M[2:, 2:] = F.T
    E = scipy.linalg.expm(M * T)
    Phi = E[2:, 2:].T
    Qd = Phi @ E[:2, 2:]
    return Phi, 0.5 * (Qd + Qd.T)


class TightInsBank(InsFilterBank):
    """INS + an :class:`MhssBank` of 17-state members (clock as private states), closed loop.

    ``x`` and ``P`` are the MHSS bank's members (so the base class's feedback shifts all of them);
    :meth:`propagate` predicts members and cross blocks in one call; :meth:`feedback` also
    corrects the clock reference.
    """

    def __init__(
        self,
        nav: NavState,
        P0: np.ndarray,
        noise: em.ImuNoise,
        clock: ClockModel,
        major_interval_s: float = 0.1,
        depth: int = 2,
    ):
        self.mhss = MhssBank.initial(np.zeros(N_STATES), P0, (), depth)
        self.clock = clock
        self.clock_ref = np.zeros(2)  # [bias_m, drift_mps]: the clock's linearisation point
        self._clock_cache: dict[float, tuple[np.ndarray, np.ndarray]] = {}
        super().__init__(
            nav, P0, noise, bank_size=1, major_interval_s=major_interval_s, private_model=self.clock_model
        )

    # the members live in the MHSS bank (the base class assigns x/P once in __init__: ignored)
    @property
    def x(self) -> np.ndarray:
        return self.mhss.x

    @x.setter
    def x(self, value: np.ndarray) -> None:
        if np.any(value):
            raise ValueError("TightInsBank members are set through the MHSS bank")

    @property
    def P(self) -> np.ndarray:
        return self.mhss.P

    @P.setter
    def P(self, value: np.ndarray) -> None:
        pass

    @property
    def B(self) -> int:
        return self.mhss.B

    @B.setter
    def B(self, value: int) -> None:
        pass

    def clock_model(self, T: float) -> tuple[np.ndarray, np.ndarray]:
        key = round(T, 12)
        out = self._clock_cache.get(key)
        if out is None:
            if len(self._clock_cache) > 32:
                self._clock_cache.clear()
            out = self._clock_cache[key] = clock_transition(T, self.clock)
        return out

    def propagate(self, T: float) -> None:
        # the bank's transition (15 INS states + clock block), then one batched prediction of
        # members and cross-covariances (full Q for every block)
        Phi, Qd = self.transition(T)
        Phi_pp = Phi[15:, 15:]
        self.last_Phi = Phi
        self.mhss.predict(Phi, Qd)
        self.clock_ref = Phi_pp @ self.clock_ref

    def feedback(self, dx: np.ndarray) -> None:
        """Feed the main correction back: INS (15 states), clock reference (2); shift every member."""
        dx = np.asarray(dx, dtype=float)
        super().feedback(dx)  # INS + x[:, :15] -= dx[:15]
        self.clock_ref = self.clock_ref - dx[gm.CLOCK]
        self.mhss.x[:, gm.CLOCK] -= dx[gm.CLOCK]


@dataclass(frozen=True)
class EpochResult:
    """Diagnostics of the last GNSS epoch (for tests, evaluation and dashboards)."""

    t: float
    used: tuple[str, ...]
    update: BankUpdate | None
    tests: SeparationTests | None
    detected: bool
    excluded_now: str | None
    resolved: bool
    readmitted: tuple[str, ...]
    residual: integrity.ResidualTests | None = None
    detected_by: str = ""  # "separation", "residual", "separation+residual" or "" (no detection)


class TightlyCoupled(Pipeline):
    family = "tightly_coupled"

    RESIDUAL_WINDOWS: tuple[int, ...] = (1, 10)
    """Windows (epochs) of the satellite residual test; () turns the test off (separation only)."""

    def __init__(self, cfg: TightlyCoupledConfig, imu: ImuModel, major_interval_s: float):
        super().__init__(cfg.name, imu, major_interval_s)
        self.cfg = cfg
        self.depth = 0 if not cfg.integrity else (2 if cfg.sub_sub_filters else 1)
        self.limits = integrity.limits(cfg.phase)
        self.use_vertical = integrity.uses_vertical(cfg.phase)
        self.residual = integrity.ResidualWindows(self.RESIDUAL_WINDOWS)
        self.n_families = integrity.n_families(cfg.phase) + self.residual.n_families
        self.kmd = k_md(cfg.p_md)
        self.k_single = k_fa(cfg.p_fa, 1)  # one two-sided test (re-admission residuals)
        self.book = integrity.ExclusionBook(cfg.readmit_after_s)
        self.bank: TightInsBank | None = None
        self.clock_initialised = False
        self.last: EpochResult | None = None

    # --- pipeline interface ------------------------------------------------------------------------
    def initialise(self, nav: NavState, std: InitStd) -> None:
        if self.bank is not None:
            self.reinitialisations += 1
        P0 = np.zeros((N_STATES, N_STATES))
        P0[:15, :15] = initial_covariance(std, self.imu)
        P0[gm.CLK_BIAS, gm.CLK_BIAS] = self.cfg.clock.init_bias_std_m**2
        P0[gm.CLK_DRIFT, gm.CLK_DRIFT] = self.cfg.clock.init_drift_std_mps**2
        self._P0 = P0
        self.bank = TightInsBank(nav, P0, self.imu.noise(), self.cfg.clock, self.major_interval_s, self.depth)
        self.book.clear()
        self.residual.clear()
        self.clock_initialised = False
        self.last = None
        self.status = "aligned"

    def recover_covariance(self) -> None:
        """Lost positive definiteness: keep the INS, the clock reference and the exclusions; restart
        every member and cross block from the initial covariance (all states zero)."""
        mh = self.bank.mhss
        self.bank.mhss = MhssBank.initial(np.zeros(N_STATES), self._P0, mh.sats, mh.depth)
        self.residual.clear()
        self.reinitialisations += 1
        self.status = "reinitialised"

    def push_imu(self, dtheta_rad, dvel_mps, dt_s: float, t_end: float | None = None) -> None:
        self.bank.push_imu(dtheta_rad, dvel_mps, dt_s, t_end)

    def sync(self) -> None:
        self.bank.sync()

    def estimate(self) -> Estimate:
        return Estimate(self.bank.nav(), self.bank.P[0, :9, :9])

    def apply(self, kind: str, sensor_id: str, msg: WireModel, dt_late_s: float = 0.0) -> list[WireModel]:
        if kind != "gnss_raw" or not isinstance(msg, GnssRaw):
            return []
        return self._gnss_epoch(msg, dt_late_s)

    # --- one GNSS epoch -------------------------------------------------------------------------------
    def _gnss_epoch(self, msg: GnssRaw, dt_late_s: float) -> list[WireModel]:
        bank, cfg = self.bank, self.cfg
        bank.sync()
        sats = gm.sat_arrays(msg)
        nav = bank.nav()
        if not self.clock_initialised and sats.ids:
            rx0 = gm.receiver_from_nav(nav, 0.0, 0.0, dt_late_s)
            vis0 = gm.elevation_mask(gm.predict(rx0, sats), cfg.elevation_mask_deg)
            if np.any(vis0):
                bank.clock_ref = np.array(gm.clock_from_residuals(rx0, sats.take(np.flatnonzero(vis0))))
                self.clock_initialised = True
        rx = gm.receiver_from_nav(nav, bank.clock_ref[0], bank.clock_ref[1], dt_late_s)
        pred = gm.predict(rx, sats)
        visible = gm.elevation_mask(pred, cfg.elevation_mask_deg)
        rows = gm.raw_rows(pred, sats, cfg.use_range_rate)

        # re-admission tests of excluded satellites against the current main filter
        health: dict[str, bool] = {}
        mh = bank.mhss
        for i, sid in enumerate(sats.ids):
            if sid in self.book and visible[i]:
                sel = rows.row_sat == i
                std = residual_test(mh.x[0], mh.P[0], rows.z[sel], rows.H[sel], rows.r_var[sel])
                health[sid] = bool(np.all(np.abs(std) <= self.k_single))
        readmitted = tuple(self.book.observe(msg.t, health))

        # a satellite listed twice in one message: only its first observation is used
        first = {sid: i for i, sid in reversed(list(enumerate(sats.ids)))}
        used = tuple(
            sid for i, sid in enumerate(sats.ids) if visible[i] and sid not in self.book and first[sid] == i
        )
        if set(used) != set(mh.sats):
            mh = bank.mhss = mh.rebuild(used)
            self.residual.retain(mh.sats)
        upd = None
        if used:
            col = {sid: j for j, sid in enumerate(mh.sats)}
            sat_col = np.array(
                [col.get(sid, -1) if first[sid] == i else -1 for i, sid in enumerate(sats.ids)]
            )
            sel = sat_col[rows.row_sat] >= 0
            z, H, r_var, rcol = rows.z[sel], rows.H[sel], rows.r_var[sel], sat_col[rows.row_sat[sel]]
            upd = mh.update(z, H, r_var, rcol)
            if not is_positive_definite(mh.P[:1])[0]:
                # numerical health: never continue on a broken P (DESIGN reliability rules)
                self.recover_covariance()
                return []
            if self.depth >= 1 and self.residual.windows:
                # the pseudorange row of each bank column (one per used satellite)
                is_pr = np.flatnonzero(rows.H[sel][:, gm.CLK_BIAS] == 1.0)
                pr_row = np.full(mh.N, -1)
                pr_row[rcol[is_pr]] = is_pr
                if np.all(pr_row >= 0):
                    self.residual.push(mh.sats, *mh.excluded_residuals(z, H, r_var, pr_row))
            bank.feedback(mh.x[0].copy())
            self.mark_aided(nav.t)
        if self.depth == 0:
            self.last = EpochResult(msg.t, used, upd, None, False, None, True, readmitted)
            return []

        # MHSS tests, exclusion, protection levels
        p_fa, nf, usev = cfg.p_fa, self.n_families, self.use_vertical
        kfa = k_fa(p_fa, mh.N * nf)
        hmode = cfg.horizontal_threshold
        tests = mh.main_tests(kfa, self.kmd, k_fa_horizontal(p_fa, mh.N * nf, hmode))
        res = self.residual.tests(mh.sats, kfa)
        ss_detected = bool(np.any(tests.flagged(usev)))
        res_detected = bool(np.any(res.flagged))
        detected = ss_detected or res_detected
        resolved, excluded_now = not detected, None
        if detected and cfg.exclusion:
            r = mh.find_exclusion(tests, p_fa, self.kmd, usev, nf, res.flagged, res.normalised, hmode)
            if r is not None:
                excluded_now = mh.sats[r]
                mh = bank.mhss = mh.rebuild([s for s in mh.sats if s != excluded_now], purge=[excluded_now])
                bank.feedback(mh.x[0].copy())  # the new main (old sub-filter r) becomes the solution
                self.book.exclude(excluded_now, msg.t)
                self.residual.clear()  # past residuals were taken against filters that used it
                tests = mh.main_tests(
                    k_fa(p_fa, mh.N * nf), self.kmd, k_fa_horizontal(p_fa, mh.N * nf, hmode)
                )
                resolved = not bool(np.any(tests.flagged(usev)))
        verdict = integrity.assess(tests.hpl, tests.vpl, cfg.phase, detected, resolved)
        self.last = EpochResult(
            msg.t,
            mh.sats,
            upd,
            tests,
            detected,
            excluded_now,
            resolved,
            readmitted,
            res,
            ("separation" if ss_detected else "")
            + ("+" if ss_detected and res_detected else "")
            + ("residual" if res_detected else ""),
        )
        # residual test of each satellite: the window with the largest statistic/threshold ratio
        resid = {}
        if res.statistic.size:
            ratio = res.statistic / np.maximum(res.threshold, 1e-300)
            for j, sid in enumerate(res.sats):
                w = int(np.argmax(ratio[j]))
                resid[sid] = (float(res.statistic[j, w]), float(res.threshold[j, w]))
        sat_tests = (
            [
                SatelliteTest(
                    id=sid,
                    statistic_m=float(tests.d_h[j]),
                    threshold_m=float(tests.T_h[j]),
                    vertical_statistic_m=float(tests.d_v[j]),
                    vertical_threshold_m=float(tests.T_v[j]),
                    residual_statistic_m=resid.get(sid, (0.0, 0.0))[0],
                    residual_threshold_m=resid.get(sid, (0.0, 0.0))[1],
                )
                for j, sid in enumerate(mh.sats)
            ]
            if len(tests.d_h)
            else []
        )
        return [
            Integrity(
                t=msg.t,
                pipeline=self.name,
                phase=cfg.phase,
                hpl_m=float(tests.hpl),
                vpl_m=float(tests.vpl),
                hal_m=self.limits.hal_m,
                val_m=self.limits.val_m,
                alarm=verdict.alarm,
                available=verdict.available,
                detected=detected,
                excluded=self.book.ids,
                satellites=sat_tests,
                detected_by=self.last.detected_by,
            )
        ]


__all__ = ["EpochResult", "TightInsBank", "TightlyCoupled", "clock_transition"]
