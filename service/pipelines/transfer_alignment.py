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

import numpy as np

from service import earth
from service.config import TransferAlignmentConfig
from service.estimation import transfer_alignment as ta


def params_from_config(cfg: TransferAlignmentConfig) -> ta.TAParams:
    """The filter's assumptions (TAParams) from a pipeline configuration."""
    r_att = (cfg.r_att_arcmin * earth.ARCMIN) ** 2
    r_vel = cfg.r_vel_mps**2
    r_rate = (cfg.r_rate_dps * earth.DEG) ** 2
    return ta.TAParams(
        lever_arm_m=np.array([n.lever_arm_m for n in cfg.nodes]),
        flex_beta_rps=np.array([n.flexure_beta_rps for n in cfg.nodes]),
        flex_sigma_rad=np.array([n.flexure_arcmin for n in cfg.nodes]) * earth.ARCMIN,
        arw_rad_psqrts=cfg.arw_dpsh * earth.DEG / 60.0,
        vrw_mps_psqrts=cfg.vrw_ugpsHz * earth.UG,
        gyro_bias_rps=cfg.gyro_bias_dph * earth.DPH,
        accel_bias_mps2=cfg.accel_bias_ug * earth.UG,
        R0=np.array([r_att] * 3 + [r_vel] * 3 + [r_rate] * 3),
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
        p_fa=cfg.p_fa,
        t0=t0,
    )
