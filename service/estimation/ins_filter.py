"""An INS with a bank of error-state filters around it (closed loop).

All members of the bank share the INS as their linearisation point and the same transition
matrix; each member may have its own process-noise scale (federated sharing: Q_i = Q / beta_i).
After a correction the INS absorbs the chosen error estimate and every member's state shifts by
the same amount (x_i <- x_i - dx), which keeps the bank consistent (docs/DESIGN.md "MHSS").

Private states (declared by measurement models, :class:`~service.estimation.measurements.base.
PrivateStates`) follow the 15 INS states, block diagonal in the process model. They are closed
loop too: each block has a linearisation point ``reference[name]`` that propagates with the
block's transition and absorbs the block's part of every feedback, like the INS.
"""

from __future__ import annotations

import numpy as np

from fednav.service.estimation import kalman
from fednav.service.estimation.measurements.base import (
    ModelContext,
    PrivateStates,
    private_layout,
    private_transition,
)
from fednav.service.ins import error_model as em
from fednav.service.ins.mechanisation import Ins, NavState


class InsFilterBank:
    """INS + bank of B filters on the 15 common error states (plus optional private states).

    Parameters
    ----------
    nav : NavState
        Initial navigation state.
    P0 : (n, n) or (B, n, n)
        Initial covariance (n = 15 + private states).
    noise : ImuNoise
        Process model of the IMU.
    bank_size : int
        Number of filters B.
    private : PrivateStates blocks after the 15 INS states (their columns: ``columns``).
    """

    def __init__(
        self,
        nav: NavState,
        P0: np.ndarray,
        noise: em.ImuNoise,
        bank_size: int = 1,
        major_interval_s: float = 0.1,
        private: tuple[PrivateStates, ...] = (),
    ):
        self.ins = Ins(nav, major_interval_s)
        self.noise = noise
        P0 = np.asarray(P0, dtype=float)
        self.n = P0.shape[-1]
        self.private = tuple(private)
        self.columns = private_layout(self.private)
        if self.n != em.N_STATES + sum(b.size for b in self.private):
            raise ValueError(f"P0 is {self.n} states; the INS and private blocks need a different size")
        self.private_model = private_transition(self.private)
        self.reference = {b.name: np.zeros(b.size) for b in self.private}
        self.B = bank_size
        self.P = np.broadcast_to(P0, (bank_size, self.n, self.n)).copy()
        self.x = np.zeros((bank_size, self.n))
        self.q_scale = np.ones((bank_size, self.n))  # per-member, per-state process-noise scale
        self.last_Phi = np.eye(self.n)

    # --- time ---------------------------------------------------------------------------------
    @property
    def t(self) -> float:
        return self.ins.time

    def push_imu(self, dtheta_rad, dvel_mps, dt_s: float, t_end: float | None = None) -> None:
        T = self.ins.pending_s + dt_s
        t_before = self.ins.state.t
        self.ins.push(dtheta_rad, dvel_mps, dt_s, t_end)
        if self.ins.state.t != t_before:
            self.propagate(T)

    def advance(self, pre) -> None:
        """Major update from a shared :class:`~service.ins.mechanisation.Preintegrator`, then
        propagate the bank over its interval (the engine's path: one minor loop per vehicle)."""
        T = pre.T
        if T > 0.0:
            if self.ins.pending_s > 0.0:
                self.sync()
            self.ins.major_update(pre)
            self.propagate(T)

    def sync(self) -> None:
        """Bring the state to the INS time (apply pending minor-loop increments and propagate)."""
        T = self.ins.pending_s
        if T > 0.0:
            self.ins.major_update()
            self.propagate(T)

    def transition(self, T: float) -> tuple[np.ndarray, np.ndarray]:
        """(Phi, Qd) over T at the current INS state: the 15 INS error states, block-diagonal
        with the private states' model."""
        s = self.ins.state
        c_nb = s.mat_nb
        F = em.continuous_F(s.lat_rad, s.h_m, s.vel_enu_mps, c_nb, self.ins.last_fn_mps2)
        Phi15, Qd15 = em.discretise(F, em.continuous_Q(self.noise), T)
        if self.n == em.N_STATES:
            return Phi15, Qd15
        Phi = np.eye(self.n)
        Qd = np.zeros((self.n, self.n))
        Phi[:15, :15], Qd[:15, :15] = Phi15, Qd15
        Phi[15:, 15:], Qd[15:, 15:] = self.private_model(T)
        return Phi, Qd

    def propagate(self, T: float) -> None:
        Phi, Qd = self.transition(T)
        self.last_Phi = Phi
        self.predict_members(Phi, Qd)
        self._propagate_reference(Phi)

    def predict_members(self, Phi: np.ndarray, Qd: np.ndarray) -> None:
        """Time update of the members (banks with more to propagate override this)."""
        if np.all(self.q_scale == 1.0):
            Qb = Qd
        else:
            # Q_i = S_i^1/2 Q S_i^1/2 with S_i = diag(q_scale_i) (scalar sharing: Q / beta_i)
            s_half = np.sqrt(self.q_scale)
            Qb = s_half[:, :, None] * Qd[None] * s_half[:, None, :]
        self.x, self.P = kalman.predict(self.x, self.P, Phi, Qb)

    def _propagate_reference(self, Phi: np.ndarray) -> None:
        for name, cols in self.columns.items():
            self.reference[name] = Phi[cols, cols] @ self.reference[name]

    # --- feedback -----------------------------------------------------------------------------
    def feedback(self, dx: np.ndarray) -> None:
        """Feed ``dx`` back: the 15 INS error states into the INS, each private block into its
        reference; every member shifts by the fed-back amount. A ``dx`` of the 15 INS states
        only (the federated master's common correction) leaves the private blocks alone
        (``feedback_private`` feeds them)."""
        dx = np.asarray(dx, dtype=float)
        self.ins.correct(dx[em.POS], dx[em.VEL], dx[em.ATT], dx[em.GYRO], dx[em.ACC])
        self.x[:, :15] -= dx[:15]
        if dx.shape[0] > em.N_STATES:
            self.feedback_private(dx[em.N_STATES :])

    def feedback_private(self, dx_private: np.ndarray) -> None:
        """Feed the private states' correction (n - 15,) into their references; every member
        shifts by it (a federated local owning a private block feeds its estimate back)."""
        dx = np.asarray(dx_private, dtype=float)
        for name, cols in self.columns.items():
            d = dx[cols.start - em.N_STATES : cols.stop - em.N_STATES]
            self.reference[name] = self.reference[name] - d
            self.x[:, cols] -= d

    # --- outputs --------------------------------------------------------------------------------
    def nav(self) -> NavState:
        return self.ins.state

    def context(self, dt_late_s: float = 0.0) -> ModelContext:
        """Where a measurement model's rows go in this bank (the hook's context)."""
        return ModelContext(self.n, dt_late_s, self.columns, self.reference, self.ins.last_wib_b_rps)
