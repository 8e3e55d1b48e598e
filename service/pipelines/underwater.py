"""Underwater INS/USBL/DVL family (Xu et al. 2017, "INS/USBL/DVL information fusion and
fault-tolerant verification for underwater vehicles"), on the federated core.

``architecture = "federated"`` (the paper's Fig. 3): two local filters on ONE INS and one
batched bank (``InsFilterBank`` + ``FederatedCore``):

* local 0, INS/USBL: the 15 INS error states, USBL body vector rows (``UsblModel``, eq 21-25),
  tested by ``usbl_fault_handling`` (default ``chi2_reconfig``: the paper's chi2 residual test;
  a failing local is excluded, i.e. the system is reconfigured to INS/DVL only, and rejoins
  when its test passes again);
* local 1, INS/DVL: 15 + 6 states, the DVL offset and scale factor as the model's private block
  (``DvlModel``, eq 26-27);
* master fusion and reset once per aiding epoch with the configured sharing (section 5:
  ``eigen_trace`` 5.1 as printed, ``eigen_trace_inverse``, ``diagonal`` 5.2, ``edop`` 5.3, or
  any registered strategy).

Every member of the bank has the 21 states (one array shape for the batched calls); the DVL
block is private: never fused or rescaled (the core keeps each member's p | c conditional at a
reset), observed only by the INS/DVL local, whose estimate of it is fed back into the block's
reference after each fusion (closed loop, like the INS). In the other members the block stays
at its prior, uncorrelated with the common states, so it changes nothing there.

``architecture = "centralized"``: the comparator on the same data, one 21-state filter on the
USBL and DVL rows (default: no screening, the paper's divergence case under the USBL fault).

Outputs per aiding message: ``Faults`` with the tested rows, the sharing coefficients, the
reconfiguration events (``excluded``/``rejoined``), the currently excluded subsystems and, for
DVL messages, the DVL offset/scale estimates with their sigmas.
"""

from __future__ import annotations

import math

import numpy as np

from fednav.service.config import ImuModel, UnderwaterConfig
from fednav.service.estimation.federated.fault_tests import make_fault_test
from fednav.service.estimation.measurements.dvl import BLOCK as DVL_BLOCK
from fednav.service.estimation.measurements.dvl import DvlModel
from fednav.service.estimation.measurements.usbl import UsblModel
from fednav.service.ins import error_model as em
from fednav.service.messages import Faults, Reconfiguration, StateEstimate, WireModel
from fednav.service.pipelines.federated import _CorePipeline

USBL_LOCAL, DVL_LOCAL = "INS/USBL", "INS/DVL"


def usbl_model(cfg: UnderwaterConfig) -> UsblModel:
    tp = cfg.transponder
    return UsblModel(
        transponder_llh_deg_m=None if tp is None else (tp.lat_deg, tp.lon_deg, tp.height_m),
        lever_arm_b_m=cfg.usbl.lever_arm_b_m,
        base_std_m=cfg.usbl.base_std_m,
        range_fraction=cfg.usbl.range_fraction,
        angle_std_deg=cfg.usbl.angle_std_deg,
    )


def dvl_model(cfg: UnderwaterConfig) -> DvlModel:
    d = cfg.dvl
    return DvlModel(
        offset_std_mps=d.offset_std_mps,
        scale_std=d.scale_std,
        offset_rw_mps_per_sqrt_s=d.offset_rw_mps_per_sqrt_s,
        scale_rw_per_sqrt_s=d.scale_rw_per_sqrt_s,
        lever_arm_b_m=d.lever_arm_b_m,
    )


class Underwater(_CorePipeline):
    """Seed 004 pipeline: federated INS/USBL + INS/DVL, or the centralised comparator."""

    #: a USBL its test keeps excluding stays excluded (the paper's reconfiguration: seed 004's
    #: multipath fault lasts 500 s); a corrupted position the USBL keeps refusing looks the same
    #: and is not recovered (docs/hardening.md, "A silent corruption of the state")
    refusal_recovery_s = None

    @classmethod
    def sensor_kinds(cls) -> frozenset[str]:
        return frozenset({"usbl", "dvl"})

    def __init__(self, cfg: UnderwaterConfig, imu: ImuModel, major_interval_s: float):
        federated = cfg.architecture == "federated"
        subsystems = (
            [(USBL_LOCAL, ["usbl"]), (DVL_LOCAL, ["dvl"])] if federated else [("central", ["usbl", "dvl"])]
        )
        super().__init__(
            cfg.name,
            imu,
            major_interval_s,
            subsystems=subsystems,
            sharing=cfg.sharing if federated else "fixed",
            fault_handling=cfg.usbl_fault_handling,
            false_alarm_prob=cfg.false_alarm_prob,
            reset=cfg.reset,
            master_share=cfg.master_share if federated else 0.0,
            report_faults=True,
            doubt_prob=cfg.soft_gate_prob,
        )
        self.cfg = cfg
        self.federated = federated
        usbl, dvl = self.channels["usbl"], self.channels["dvl"]
        usbl.model, dvl.model = usbl_model(cfg), dvl_model(cfg)
        dvl.test = make_fault_test(cfg.dvl_fault_handling, cfg.false_alarm_prob)
        if not federated:  # one filter, one test per sensor kind (reported by kind)
            usbl.name, dvl.name = "usbl", "dvl"
        self.dvl_owner = dvl.owner
        #: (t, subsystem, "excluded" | "rejoined") in time order
        self.events: list[tuple[float, str, str]] = []

    # --- filter ------------------------------------------------------------------------------------
    def private_states(self) -> tuple:
        return self.channels["dvl"].model.private_states  # the INS/DVL local's offset and scale

    def _end_epoch(self) -> None:
        """Fusion, reset and common feedback (the core), then the DVL local's private estimate
        into the DVL block's reference (closed loop)."""
        super()._end_epoch()
        cols = self.bank.columns[DVL_BLOCK]
        dx = self.bank.x[self.dvl_owner, em.N_STATES :].copy()
        if np.all(np.isfinite(dx)) and np.any(dx[cols.start - em.N_STATES : cols.stop - em.N_STATES]):
            self.bank.feedback_private(dx)

    # --- aiding ------------------------------------------------------------------------------------
    def apply(self, kind: str, sensor_id: str, msg: WireModel, dt_late_s: float = 0.0) -> list[WireModel]:
        ch = self.channels.get(kind)
        if ch is None:
            return []
        was_excluded = bool(getattr(ch.test, "excluded", False))
        out = super().apply(kind, sensor_id, msg, dt_late_s)
        if not out:
            return out
        faults: Faults = out[0]
        now_excluded = bool(getattr(ch.test, "excluded", False))
        events = []
        if now_excluded != was_excluded:
            action = "excluded" if now_excluded else "rejoined"
            obs = faults.subsystems[0].observations
            events.append(
                Reconfiguration(
                    subsystem=ch.name,
                    action=action,
                    statistic=obs[0].statistic if obs else math.nan,
                    threshold=obs[0].threshold if obs else math.nan,
                )
            )
            self.events.append((float(faults.t), ch.name, action))
        excluded = sorted({c.name for c in self.channels.values() if getattr(c.test, "excluded", False)})
        states = self.dvl_states() if kind == "dvl" else []
        return [faults.model_copy(update={"reconfiguration": events, "excluded": excluded, "states": states})]

    def dvl_states(self) -> list[StateEstimate]:
        """The DVL offset/scale estimates (reference minus the owner's error state) and sigmas.

        The sigma is the DVL block's marginal given the FUSED common states: the owner's
        conditional P_pp|c plus A P_g A' (A = P_pc P_cc^-1 of the owner). The owner's own P_pp is
        larger by A (P_g / beta - P_g) A' after a fusion-reset (its common prior is the fused one
        inflated by 1/beta, and the core keeps p | c); for the centralised filter both agree."""
        b = self.bank
        cols = b.columns[DVL_BLOCK]
        names = self.channels["dvl"].model.private_states[0].names
        est = b.reference[DVL_BLOCK] - b.x[self.dvl_owner, cols]
        P = b.P[self.dvl_owner]
        c = em.N_STATES
        Pcc, Pcp, Ppp = P[:c, :c], P[:c, cols], P[cols, cols]
        d = np.sqrt(np.diagonal(Pcc))
        At = np.linalg.solve(Pcc / np.outer(d, d), Pcp / d[:, None]) / d[:, None]  # P_cc^-1 P_cp
        P_g = self.fused_covariance() if self.federated else Pcc
        var = np.diagonal(Ppp - Pcp.T @ At + At.T @ P_g @ At)
        sd = np.sqrt(np.clip(var, 0.0, None))
        return [
            StateEstimate(name=n, value=float(v), std=float(s))
            for n, v, s in zip(names, est, sd, strict=True)
        ]

    def dvl_estimate(self) -> tuple[np.ndarray, np.ndarray]:
        """(estimate (6,), sigma (6,)) of [offset_xyz_mps, scale_xyz]."""
        s = self.dvl_states()
        return np.array([e.value for e in s]), np.array([e.std for e in s])

    def sharing_report(self) -> dict[str, list[float]]:
        return super().sharing_report() if self.federated else {}


__all__ = ["Underwater", "USBL_LOCAL", "DVL_LOCAL"]
