"""Transfer alignment family (Zhu, Ma, Wang, Chen 2022): wing IMU nodes aligned to the master.

The vehicle's INS (the master IMU stream, aided by GNSS when present) runs as a loosely coupled
pipeline, so the pipeline's Solution is the master's navigation. On top, every configured slave
node has a 27-state local filter, one member of a :class:`TransferAlignmentBank`, fed by the
master's and the nodes' raw IMU samples (the engine routes node IMU ids to
:meth:`push_node_imu`, docs/seed002.md). Each filter epoch produces an
:class:`~service.messages.Alignment` per node (misalignment, lever arm, flexure with sigmas,
adaptive R and fading factors), published at the output epochs.
"""

from __future__ import annotations

from collections import deque

import numpy as np

from fednav.service import earth
from fednav.service.config import ImuModel, LooselyCoupledConfig, TransferAlignmentConfig
from fednav.service.estimation import transfer_alignment as ta
from fednav.service.messages import Alignment, ImuSample, WireModel
from fednav.service.pipelines.loosely_coupled import LooselyCoupled


def params_from_config(cfg: TransferAlignmentConfig) -> ta.TAParams:
    """The filter's assumptions (TAParams) from a pipeline configuration."""
    r_att = (cfg.r_att_arcmin * earth.ARCMIN) ** 2
    r_vel = cfg.r_vel_mps**2
    r_rate = (cfg.r_rate_dps * earth.DEG) ** 2
    lever = np.array([n.lever_arm_m for n in cfg.nodes])
    R0 = np.tile(np.array([r_att] * 3 + [r_vel] * 3 + [r_rate] * 3), (len(cfg.nodes), 1))
    if cfg.r_vel_vibration:  # the vibration rate moves the node: diag(M r_rate M'), M = -kappa [r x]
        M = ta.flexure_displacement_matrix(lever, cfg.kappa)
        R0[:, 3:6] += r_rate * np.einsum("bij,bij->bi", M, M)
    return ta.TAParams(
        lever_arm_m=lever,
        flex_beta_rps=np.array([n.flexure_beta_rps for n in cfg.nodes]),
        flex_sigma_rad=np.array([n.flexure_arcmin for n in cfg.nodes]) * earth.ARCMIN,
        arw_rad_psqrts=cfg.arw_dpsh * earth.DEG / 60.0,
        vrw_mps_psqrts=cfg.vrw_ugpsHz * earth.UG,
        gyro_bias_rps=cfg.gyro_bias_dph * earth.DPH,
        accel_bias_mps2=cfg.accel_bias_ug * earth.UG,
        R0=R0,
        phi0_rad=cfg.initial_attitude_arcmin * earth.ARCMIN,
        dw0_mps=cfg.initial_velocity_mps,
        install_rad=cfg.install_arcmin * earth.ARCMIN,
        coupling_rad=cfg.coupling_arcmin * earth.ARCMIN,
        lever_arm_err_m=tuple(cfg.lever_arm_error_m),
        kappa=cfg.kappa,
    )


def bank_from_config(cfg: TransferAlignmentConfig, t0: float = 0.0) -> ta.TransferAlignmentBank:
    return ta.TransferAlignmentBank(
        params_from_config(cfg),
        mode=cfg.filter,
        fusion=cfg.fusion,
        filter_period_s=cfg.filter_period_s,
        forgetting=cfg.forgetting_factor,
        restart=cfg.restart,
        fading=cfg.fading,
        order=cfg.adaptive_order,
        p_fa=cfg.p_fa,
        fading_form=cfg.fading_form,
        r_floor=cfg.r_floor,
        t0=t0,
    )


#: samples a node or the master may wait for the other (4 s at 100 Hz)
_MAX_WAITING = 400


def _tkey(t: float) -> int:
    return int(round(t * 1e6))


class TransferAlignment(LooselyCoupled):
    """Master navigation as a loosely coupled pipeline plus the slave nodes' transfer alignment."""

    wants_imu_samples = True

    def __init__(self, cfg: TransferAlignmentConfig, imu: ImuModel, major_interval_s: float):
        super().__init__(LooselyCoupledConfig(name=cfg.name), imu, major_interval_s)
        self.ta_cfg = cfg
        self.node_ids = [n.id for n in cfg.nodes]
        self.ta: ta.TransferAlignmentBank | None = None
        #: node samples waiting for the master sample of their instant, per node, by time (us)
        self._pending: dict[str, dict[int, ImuSample]] = {}
        #: master samples waiting for their nodes' samples (batches of the nodes may arrive after
        #: the master's: the join is by time, not by arrival order)
        self._masters: deque = deque()
        self._t_prev: float | None = None
        self.node_resets = 0
        self._out: list[WireModel] = []

    @classmethod
    def config_errors(cls, cfg) -> list[tuple[str, str]]:
        ids = [n.id for n in cfg.nodes]
        if len(set(ids)) != len(ids):
            return [("nodes", f"node ids must be unique, got {ids}")]
        return []

    def node_imu_ids(self) -> frozenset[str]:
        return frozenset(self.node_ids)

    def initialise(self, nav, std) -> None:
        super().initialise(nav, std)
        self.ta = bank_from_config(self.ta_cfg, t0=nav.t)  # the node filters start with the INS
        self._pending.clear()
        self._masters.clear()

    def push_node_imu(self, sensor_id: str, msg: ImuSample) -> None:
        pending = self._pending.setdefault(sensor_id, {})
        pending[_tkey(msg.t)] = msg
        if len(pending) > _MAX_WAITING:  # a node far ahead of the master: keep the newest
            for k in sorted(pending)[: len(pending) - _MAX_WAITING]:
                del pending[k]
        self._join()

    def push_imu_sample(self, msg: ImuSample) -> None:
        """A master sample at t: queued until every node's sample ending at t is in (or a node
        has passed t without one), then the node filters step (:meth:`_step`)."""
        self._masters.append(msg)
        if len(self._masters) > _MAX_WAITING:  # nodes silent: the oldest master cannot be joined
            self._step(self._masters.popleft(), None)
        self._join()

    def _join(self) -> None:
        """Step the node filters for every queued master sample whose nodes are decided."""
        while self._masters:
            msg = self._masters[0]
            k = _tkey(msg.t)
            got, waiting = [], False
            for i in self.node_ids:
                pending = self._pending.get(i, {})
                m = pending.get(k)
                if m is None and not any(kk > k for kk in pending):
                    waiting = True  # this node has not reached t yet
                    break
                got.append(m)
            if waiting:
                return
            self._masters.popleft()
            for i in self.node_ids:  # what is at or before t is used or missing now
                pending = self._pending.get(i, {})
                for kk in [kk for kk in pending if kk <= k]:
                    del pending[kk]
            self._step(msg, got)

    def _step(self, msg: ImuSample, got: list | None) -> None:
        """A master sample at t with the nodes' samples ending at t (None: missing). A node
        missing at t (lost or late) restarts the node filters at the next complete set (the
        relative mechanisation needs every interval of every node; counted in ``node_resets``)."""
        complete = got is not None and all(
            m is not None and abs(m.t - msg.t) < 1e-6 and abs(m.dt_s - msg.dt_s) < 1e-9 for m in got
        )
        if not complete:
            if self.ta is not None:
                self.ta = None
                self.node_resets += 1
            return
        if self.ta is None:
            self.ta = bank_from_config(self.ta_cfg, t0=msg.t)
            return  # the filters start at this instant; the next interval is the first one
        info = self.ta.push(
            msg.dtheta_rad,
            msg.dvel_mps,
            np.array([m.dtheta_rad for m in got]),
            np.array([m.dvel_mps for m in got]),
            msg.dt_s,
            msg.t,
        )
        if info is not None:
            self._out = self._alignment_messages(info)

    def epoch_outputs(self) -> list[WireModel]:
        out, self._out = self._out, []
        return out

    def _alignment_messages(self, info: ta.StepInfo) -> list[Alignment]:
        """One Alignment per node, every field computed for all nodes at once (array arithmetic
        then ``tolist``: the same float64 values as element-wise Python arithmetic)."""
        bank = self.ta
        sd = bank.sigmas()
        deg = 1.0 / earth.DEG
        R = np.sqrt(info.R_diag)
        R[:, [0, 1, 2, 6, 7, 8]] *= deg
        x, P = bank.x, bank.P
        inst_var = (
            np.diagonal(P[:, ta.RHO, ta.RHO], axis1=1, axis2=2)
            + np.diagonal(P[:, ta.DD, ta.DD], axis1=1, axis2=2)
            + 2 * np.diagonal(P[:, ta.RHO, ta.DD], axis1=1, axis2=2)
        )
        fields = {
            "mount_deg": ta.rotvec(bank.C_ms) * deg,
            "misalignment_std_deg": sd[:, ta.PHI] * deg,
            "installation_deg": (x[:, ta.RHO] + x[:, ta.DD]) * deg,
            "installation_std_deg": np.sqrt(np.clip(inst_var, 0.0, None)) * deg,
            "flexure_deg": x[:, ta.TH] * deg,
            "flexure_std_deg": sd[:, ta.TH] * deg,
            "lever_arm_m": bank.lever_arm_m(),
            "lever_arm_std_m": sd[:, ta.DR],
            "gyro_bias_dph": x[:, ta.EPS] * (1.0 / earth.DPH),
            "accel_bias_ug": x[:, ta.NAB] * (1.0 / earth.UG),
            "r_std": R,
        }
        rows = {k: v.tolist() for k, v in fields.items()}
        fading = info.fading_s.max(axis=1).tolist()
        nis = info.nis.tolist()
        share = [None] * len(self.node_ids) if info.alpha is None else info.alpha.tolist()
        t = float(info.t)
        msgs = []
        for b, node in enumerate(self.node_ids):
            msgs.append(
                Alignment(
                    t=t,
                    pipeline=self.name,
                    node=node,
                    **{k: tuple(v[b]) for k, v in rows.items()},
                    fading=fading[b],
                    nis=nis[b],
                    share=share[b],
                )
            )
        return msgs
