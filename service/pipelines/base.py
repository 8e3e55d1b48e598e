"""The pipeline contract: a configured chain sensors -> measurement models -> filter bank -> outputs.

Each pipeline owns its INS inside its filter bank (``self.bank``, an
:class:`~service.estimation.ins_filter.InsFilterBank` or a subclass; closed loop makes references
differ per pipeline), so several run side by side on one input stream. A family is one module
under ``service/pipelines/`` with one class per configuration ``kind`` (registered in
``service/pipelines/__init__.py``). The engine calls, in sensor-time order:

  ``start(nav, std, after_loss)``  once, and again on re-initialisation (calls ``initialise``);
  ``advance(pre)``                 the vehicle's shared preintegrated IMU interval at every major
                                   update (``push_imu`` is the per-pipeline equivalent);
  ``sync()``                       before reading the state at an aiding or output epoch;
  ``apply(kind, sensor_id, msg, dt_late_s)``  per aiding message -> extra outputs (Faults, ...);
  ``estimate()`` / ``solution()``  at output epochs; ``recover_covariance()`` after a
                                   numerical failure (the engine catches ``LinAlgError``).

A subclass implements ``initialise`` (build ``self.bank``), ``apply`` (measurement models from
:mod:`service.estimation.measurements`, one update on the bank) and ``estimate``; the base class
provides the time path, status and Solution. The pipeline owns its status (``status``,
``updates``, ``reinitialisations``); nobody else writes them.
"""

from __future__ import annotations

import math
from abc import ABC, abstractmethod
from dataclasses import dataclass

import numpy as np

from service import earth
from service.config import ImuModel
from service.estimation.ins_filter import InsFilterBank
from service.ins import error_model as em
from service.ins.alignment import InitStd
from service.ins.mechanisation import NavState
from service.messages import Solution, WireModel


def initial_covariance(std: InitStd, imu: ImuModel) -> np.ndarray:
    sg, sa = imu.bias_sigmas()
    d = np.concatenate(
        [
            std.pos_enu_m,
            std.vel_enu_mps,
            std.att_rad,
            np.full(3, max(sg, 1e-12)),
            np.full(3, max(sa, 1e-12)),
        ]
    )
    return np.diag(np.square(d))


@dataclass
class Estimate:
    """What evaluation needs: the navigation state and the 9x9 covariance of (dp, dv, phi)."""

    nav: NavState
    P9: np.ndarray


class Pipeline(ABC):
    def __init__(self, name: str, imu: ImuModel, major_interval_s: float):
        self.bank: InsFilterBank | None = None  # built by ``initialise``
        self.name = name
        self.imu = imu
        self.major_interval_s = major_interval_s
        self.status = "initialising"
        self.updates = 0
        self.reinitialisations = 0
        self.last_aiding_t: float | None = None

    #: without aiding for longer than this, an aided pipeline reports ``ins_only``
    ins_only_after_s: float = 3.0

    def mark_aided(self, t: float) -> None:
        self.last_aiding_t = t
        self.updates += 1
        self.status = "aided"

    def current_status(self, t: float) -> str:
        if (
            self.status == "aided"
            and self.last_aiding_t is not None
            and t - self.last_aiding_t > self.ins_only_after_s
        ):
            return "ins_only"
        return self.status

    def start(self, nav: NavState, std: InitStd, *, after_loss: bool = False) -> None:
        """(Re-)initialise from an initial state (``initialise`` builds the filter). A start of a
        pipeline that had been initialised before counts one re-initialisation. Status
        ``reinitialised`` when the start follows a loss of the INS (:meth:`mark_lost`), else
        ``aligned``."""
        restart = self.bank is not None
        self.initialise(nav, std)
        if restart:
            self.reinitialisations += 1
        self.status = "reinitialised" if after_loss else "aligned"

    def mark_lost(self) -> None:
        """The INS is lost (IMU gap): no navigation until the next start; status ``ins_only``."""
        self.status = "ins_only"

    @classmethod
    def sensor_kinds(cls) -> frozenset[str]:
        """Sensor kinds this pipeline kind can consume (its configuration is checked against it)."""
        return frozenset()

    @classmethod
    def config_errors(cls, cfg) -> list[tuple[str, str]]:
        """(field inside the pipeline's config, message) for options this kind does not
        implement; checked when the configuration is loaded (``service.pipelines.config_errors``)."""
        return []

    @abstractmethod
    def initialise(self, nav: NavState, std: InitStd) -> None: ...

    def push_imu(self, dtheta_rad, dvel_mps, dt_s: float, t_end: float | None = None) -> None:
        """One IMU interval through the pipeline's own minor loop (tests and single pipelines)."""
        self.bank.push_imu(dtheta_rad, dvel_mps, dt_s, t_end)

    def advance(self, pre) -> None:
        """Apply a preintegrated IMU interval shared by all pipelines of the vehicle (the
        engine's path; ``push_imu`` is the per-pipeline equivalent)."""
        self.bank.advance(pre)

    def sync(self) -> None:
        """Bring the filter to the INS time (pending minor-loop increments, propagation)."""
        self.bank.sync()

    @abstractmethod
    def apply(self, kind: str, sensor_id: str, msg: WireModel, dt_late_s: float = 0.0) -> list[WireModel]:
        """Apply an aiding measurement at the current INS time; return extra output messages."""

    @abstractmethod
    def estimate(self) -> Estimate: ...

    # --- several IMU nodes (transfer alignment, seed 002); defaults: one IMU stream ---------------
    def node_imu_ids(self) -> frozenset[str]:
        """IMU sensor ids this pipeline consumes as nodes: the engine routes their samples to
        :meth:`push_node_imu` and never to the vehicle's INS."""
        return frozenset()

    #: True: the engine also hands every accepted INS-driving IMU sample to :meth:`push_imu_sample`
    wants_imu_samples: bool = False

    def push_node_imu(self, sensor_id: str, msg) -> None:
        """A node IMU sample (accepted by the engine's rules for its key)."""
        return None

    def push_imu_sample(self, msg) -> None:
        """An INS-driving IMU sample, after the vehicle's INS took it."""
        return None

    def epoch_outputs(self) -> list[WireModel]:
        """Extra messages at an output epoch (published by the engine's sink)."""
        return []

    def recover_covariance(self) -> None:
        """Numerical-health recovery after a covariance lost positive definiteness.

        Pipelines reset their covariances to the initial ones (keeping the INS) and set the
        status ``reinitialised``; this default only flags the fault.
        """
        self.status = "fault"

    def solution(self, est: Estimate | None = None) -> Solution:
        est = est or self.estimate()
        nav, P = est.nav, est.P9
        sd = np.sqrt(np.clip(np.diagonal(P), 0.0, None))
        rpy = nav.rpy_rad
        # attitude sigma: roll/pitch/heading from the misalignment sigmas (small-angle reading)
        rpy_std = np.degrees(np.array([max(sd[6], sd[7]), max(sd[6], sd[7]), sd[8]]))
        return Solution(
            t=nav.t,
            pipeline=self.name,
            lat_deg=math.degrees(nav.lat_rad),
            lon_deg=(math.degrees(nav.lon_rad) + 180.0) % 360.0 - 180.0,
            height_m=nav.h_m,
            vel_enu_mps=tuple(float(v) for v in nav.vel_enu_mps),
            rpy_deg=tuple(earth.rpy_msg_deg(rpy)),
            pos_std_enu_m=tuple(float(v) for v in sd[0:3]),
            vel_std_enu_mps=tuple(float(v) for v in sd[3:6]),
            rpy_std_deg=tuple(float(v) for v in rpy_std),
            gyro_bias_dph=tuple(float(v) for v in nav.gyro_bias_rps / earth.DPH),
            accel_bias_ug=tuple(float(v) for v in nav.accel_bias_mps2 / earth.UG),
            status=self.current_status(nav.t),
        )


ERROR_KEYS = (
    "lat_m",
    "lon_m",
    "h_m",
    "ve_mps",
    "vn_mps",
    "vu_mps",
    "phi_e_arcsec",
    "phi_n_arcsec",
    "phi_u_arcsec",
)


def nav_errors(
    nav: NavState, truth_llh: np.ndarray, truth_vel: np.ndarray, truth_mat_nb: np.ndarray
) -> np.ndarray:
    """Errors (computed minus true) in the error-state convention: [dp_enu_m, dv_enu, phi_rad].

    phi from C_computed = (I - [phi x]) C_true, i.e. phi = rotation vector of C_true C_computed'.
    """
    r_m, r_n = earth.radii(truth_llh[0])
    dp = np.array(
        [
            earth.wrap_pi(nav.lon_rad - truth_llh[1]) * (r_n + truth_llh[2]) * math.cos(truth_llh[0]),
            (nav.lat_rad - truth_llh[0]) * (r_m + truth_llh[2]),
            nav.h_m - truth_llh[2],
        ]
    )
    dv = nav.vel_enu_mps - truth_vel
    phi = earth.quat_to_rotvec(earth.mat_to_quat(truth_mat_nb @ nav.mat_nb.T))
    return np.concatenate([dp, dv, phi])


def error_dict(e9: np.ndarray) -> dict[str, float]:
    """Named errors for reports: lat_m (north), lon_m (east), h_m, velocities, phi in arcsec."""
    return {
        "lat_m": float(e9[1]),
        "lon_m": float(e9[0]),
        "h_m": float(e9[2]),
        "ve_mps": float(e9[3]),
        "vn_mps": float(e9[4]),
        "vu_mps": float(e9[5]),
        "phi_e_arcsec": float(e9[6] / earth.ARCSEC),
        "phi_n_arcsec": float(e9[7] / earth.ARCSEC),
        "phi_u_arcsec": float(e9[8] / earth.ARCSEC),
    }


def nees(e9: np.ndarray, P9: np.ndarray) -> float:
    """Normalised estimation error squared e' P^-1 e (Cholesky solve)."""
    L = np.linalg.cholesky(P9)
    w = np.linalg.solve(L, e9)
    return float(w @ w)


def p15_to_p9(P: np.ndarray) -> np.ndarray:
    return P[:9, :9]


__all__ = [
    "Pipeline",
    "InitStd",
    "Estimate",
    "initial_covariance",
    "nav_errors",
    "error_dict",
    "nees",
    "ERROR_KEYS",
    "em",
]
