"""An INS with a bank of error-state filters around it (closed loop).

All members of the bank share the INS as their linearisation point and the same transition
matrix; each member may have its own process-noise scale (federated sharing: Q_i = Q / beta_i).
After a correction the INS absorbs the chosen error estimate and every member's state shifts by
the same amount (x_i <- x_i - dx), which keeps the bank consistent (docs/DESIGN.md "MHSS").

Private states (declared by measurement models, :class:`~service.estimation.measurements.base.
PrivateStates`) follow the 15 INS states, block diagonal in the process model. They are closed
loop too: each block has a linearisation point ``reference[name]`` that propagates with the
block's transition and absorbs the block's part of every feedback, like the INS.

IMU scale factors (:func:`imu_scale_block`, the private block ``em.SCALE_BLOCK``) are the one
private block that is not block diagonal: they drive the attitude and velocity errors
(:func:`~service.ins.error_model.scale_coupling`), so the bank discretises the 15 INS states and
that block together; and their reference (the scale estimate) is what the INS divides the
bias-corrected increments by at every major update (:class:`_ScaledIncrements`), its own minor
loop's and a shared preintegrator's alike.
"""

from __future__ import annotations

import numpy as np

from fednav.service import earth
from fednav.service.estimation import kalman
from fednav.service.estimation.measurements.base import (
    ModelContext,
    PrivateStates,
    private_layout,
    private_transition,
)
from fednav.service.ins import error_model as em
from fednav.service.ins.mechanisation import Ins, NavState, Preintegrator


def imu_scale_block(gyro_std: float, accel_std: float) -> PrivateStates:
    """The IMU scale-factor errors (dimensionless; 3 gyro then 3 accelerometer axes) as random
    constants with prior sigmas ``gyro_std`` and ``accel_std`` (e.g. 5e-3 for 5000 ppm)."""

    def transition(T: float) -> tuple[np.ndarray, np.ndarray]:
        return np.eye(6), np.zeros((6, 6))

    std = (float(gyro_std),) * 3 + (float(accel_std),) * 3
    return PrivateStates(em.SCALE_BLOCK, em.SCALE_NAMES, transition, std)


def remove_scale(increments, scale: np.ndarray):
    """(alpha, beta, nu, scul) of bias-corrected increments divided by (1 + s) per axis (s: gyro
    then accelerometer scale estimate). Coning (a cross product of two scaled rotation increments)
    exactly: (D a) x (D b) = det(D) D^-1 (a x b); sculling by the accelerometer scale (its error: a
    scale error times the sculling term)."""
    alpha, beta, nu, scul = increments
    dg = 1.0 / (1.0 + scale[0:3])
    da = 1.0 / (1.0 + scale[3:6])
    return alpha * dg, beta * (dg[0] * dg[1] * dg[2] / dg), nu * da, scul * da


class _ScaledIncrements:
    """A shared :class:`Preintegrator`'s increments seen through a bank's scale estimate (what
    ``Ins.major_update`` reads of a preintegrator: ``T``, ``t_end``, ``corrected``)."""

    __slots__ = ("pre", "scale")

    def __init__(self, pre, scale):
        self.pre, self.scale = pre, scale

    @property
    def T(self) -> float:
        return self.pre.T

    @property
    def t_end(self) -> float:
        return self.pre.t_end

    def corrected(self, gyro_bias_rps, accel_bias_mps2):
        return remove_scale(self.pre.corrected(gyro_bias_rps, accel_bias_mps2), self.scale())


class _ScaledPreintegrator(Preintegrator):
    """The INS's own minor loop with the bank's scale estimate removed at its major updates."""

    __slots__ = ("scale",)

    def corrected(self, gyro_bias_rps, accel_bias_mps2):
        return remove_scale(super().corrected(gyro_bias_rps, accel_bias_mps2), self.scale())


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
        #: columns of the 15 INS states and the scale-factor block (None: not estimated)
        self._scaled = None
        if em.SCALE_BLOCK in self.columns:
            cols = self.columns[em.SCALE_BLOCK]
            self._scaled = np.r_[0 : em.N_STATES, cols.start : cols.stop]
            own = _ScaledPreintegrator()
            own.scale = self.scale_estimate
            own.reset(self.ins.state.t)
            self.ins._pre = own
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
            if self._scaled is not None:
                pre = _ScaledIncrements(pre, self.scale_estimate)
            self.ins.major_update(pre)
            self.propagate(T)

    def scale_estimate(self) -> np.ndarray:
        """The IMU scale-factor estimate (6,) the INS applies (the block's reference)."""
        return self.reference[em.SCALE_BLOCK]

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
        if self._scaled is not None:
            c_nb = s.mat_nb
            F = em.continuous_F(s.lat_rad, s.h_m, s.vel_enu_mps, c_nb, self.ins.last_fn_mps2)
            return self._scaled_transition(F, c_nb, T)
        # C_nb as rows of floats (the same entries as the array of NavState.mat_nb, which
        # continuous_F would read back as floats)
        q = s.q_nb
        f64 = isinstance(q, np.ndarray) and q.dtype == np.float64
        c_nb = earth.quat_to_mat_f(*q.tolist()) if f64 else s.mat_nb
        F = em.continuous_F(s.lat_rad, s.h_m, s.vel_enu_mps, c_nb, self.ins.last_fn_mps2)
        Phi15, Qd15 = em.discretise(F, em.continuous_Q(self.noise), T)
        if self.n == em.N_STATES:
            return Phi15, Qd15
        Phi = np.eye(self.n)
        Qd = np.zeros((self.n, self.n))
        Phi[:15, :15], Qd[:15, :15] = Phi15, Qd15
        Phi[15:, 15:], Qd[15:, 15:] = self.private_model(T)
        return Phi, Qd

    def _scaled_transition(self, F15: np.ndarray, c_nb: np.ndarray, T: float):
        """(Phi, Qd) with the scale-factor block: it and the 15 INS states discretised together
        (F with the scale coupling), the other private blocks block diagonal as usual."""
        Phi = np.eye(self.n)
        Qd = np.zeros((self.n, self.n))
        Phi[15:, 15:], Qd[15:, 15:] = self.private_model(T)
        k = em.N_STATES
        F = np.zeros((k + 6, k + 6))
        F[:k, :k] = F15
        f_b = c_nb.T @ self.ins.last_fn_mps2
        F[:k, k:] = em.scale_coupling(c_nb, f_b, self.ins.last_wib_b_rps)
        Qc = np.zeros((k + 6, k + 6))
        Qc[:k, :k] = em.continuous_Q(self.noise)
        Phi_a, Qd_a = em.discretise(F, Qc, T)
        idx = self._scaled
        Qd_a[k:, k:] += Qd[np.ix_(idx[k:], idx[k:])]  # the block's own process noise
        Phi[np.ix_(idx, idx)] = Phi_a
        Qd[np.ix_(idx, idx)] = Qd_a
        return Phi, Qd

    def propagate(self, T: float) -> None:
        Phi, Qd = self.transition(T)
        self.last_Phi = Phi
        self.predict_members(Phi, Qd)
        self._propagate_reference(Phi)

    def predict_members(self, Phi: np.ndarray, Qd: np.ndarray) -> None:
        """Time update of the members (banks with more to propagate override this)."""
        # every scale 1 (a NaN counts as a scale): count_nonzero, not ndarray.all, whose Python
        # wrapper costs twice the test (every propagation)
        if not np.count_nonzero(self.q_scale != 1.0):
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
        if dt_late_s > 0.0:  # late aiding: the INS's acceleration takes its velocity back
            acc = self.ins.last_acc_enu_mps2
            return ModelContext(self.n, dt_late_s, self.columns, self.reference, self.ins.last_wib_b_rps, acc)
        return ModelContext(self.n, dt_late_s, self.columns, self.reference, self.ins.last_wib_b_rps)
