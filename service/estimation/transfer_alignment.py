"""Transfer alignment of slave IMUs to a master IMU: relative mechanisation and the 27-state
error model of Zhu, Ma, Wang, Chen 2022 (eq 1-6), one bank member per slave.

Frames: m master body (right-forward-up), s slave body, i inertial. The slave's mounting
relative to the master is C_ms (slave -> master) = exp([mu x]), mu = rho0 + theta + d_delta (+
unmodelled vibration); the lever arm is r = r_nom + dr in m axes. Every quantity is relative, so
neither the Earth model nor the master's navigation enters (gravity is common to both IMUs; its
gradient over 3 m is ~1e-5 m/s^2, below the slave accelerometer bias).

Mechanisation per IMU sample (dtheta, dvel raw increments of the master and of each slave):
    C_im <- C_im exp(dtheta_m)                     (master inertial attitude, from I at start)
    C_ms^ <- exp(-dtheta_m) C_ms^ exp(dtheta_s)    (relative attitude, exact for exact increments)
    V <- V + C_im(mid) (C_ms^(mid) dvel_s - dvel_m)   (inertial relative velocity v_s - v_m)
and w^ = C_mi V is the slave-minus-master velocity in master axes (true: w = omega x r + r_dot).

Error state X (27) = [phi, dw, eps, nabla, rho0, theta, theta_dot, dr, d_delta] (eq 1) with
C_ms^ = (I - [phi x]) C_ms, dw = w^ - w, eps / nabla the slave gyro / accel biases, theta the
flexure angle (second-order Gauss-Markov per axis: theta_ddot = -2 beta theta_dot - beta^2 theta
+ w), dr the lever-arm error (constant part plus the flexure displacement M theta), d_delta the
coupling angle. Continuous model (derivation in docs/seed002.md):
    phi_dot = -[omega_m x] phi - C_ms eps                (paper eq 2 row 1, omega_in -> omega_im)
    dw_dot  = [f_s^m x] phi - [omega_m x] dw + C_ms nabla   (row 2; the paper omits f x phi)
    theta_dot' = -beta^2 theta - 2 beta theta_dot + w;  dr_dot = M theta_dot
Measurements every filter period (eq 3-4, small-angle reading):
    z_a = rotvec(C_ms^)               = mu - phi                     H_a = [-I 0 0 0 I I 0 0 I]
    z_v = w^ - omega_m x r_nom        = dw + [omega_m x] dr + M theta_dot
                                      (omega_m: the last sample's mean rate extrapolated to its end)
    z_w = omega_s~ - omega_m~         = [omega_m x](rho0 + theta + d_delta) + theta_dot + eps
rho0 and d_delta enter every row through the same columns (the paper's extra K(omega_theta)
term of H_w1 is undefined in the paper): only their sum is observable; the filter keeps both
states and splits the sum by their priors.
"""

from __future__ import annotations

from dataclasses import dataclass, field, replace

import numpy as np

from fednav.service.estimation import kalman
from fednav.service.estimation.adaptive import SageHusaR, chi2_threshold, faded_covariance, fading_factors

N_STATES = 27
N_MEAS = 9
PHI, DW, EPS, NAB, RHO, TH, THD, DR, DD = (slice(3 * i, 3 * i + 3) for i in range(9))
_I3 = np.eye(3)

#: states that may fade (eq 16-17 "only observable states"): those every epoch measures directly
#: whatever the manoeuvre -- misalignment, velocity difference, flexure angle and rate. Not the
#: constants: rho0 and d_delta are observable only as their sum (fading both inflates their
#: unobservable difference without bound: measured, docs/seed002.md), and biases and lever arm
#: only through manoeuvres (fading them in straight flight inflates P with nothing to reduce it).
FADING_STATES = np.zeros(27, dtype=bool)
FADING_STATES[np.r_[0:6, 15:21]] = True


def skew(v: np.ndarray) -> np.ndarray:
    """(..., 3) -> (..., 3, 3) cross-product matrices."""
    v = np.asarray(v, dtype=float)
    K = np.zeros(v.shape[:-1] + (3, 3))
    K[..., 0, 1] = -v[..., 2]
    K[..., 0, 2] = v[..., 1]
    K[..., 1, 0] = v[..., 2]
    K[..., 1, 2] = -v[..., 0]
    K[..., 2, 0] = -v[..., 1]
    K[..., 2, 1] = v[..., 0]
    return K


def _skew3(v: np.ndarray) -> np.ndarray:
    """skew() of one vector (3,), built directly (the same entries; the per-sample hot path)."""
    x, y, z = v.tolist()
    return np.array(((0.0, -z, y), (z, 0.0, -x), (-y, x, 0.0)))


_SKEW_AT = np.array([1, 2, 3, 5, 6, 7])  # flat entries (0,1) (0,2) (1,0) (1,2) (2,0) (2,1)
_SKEW_FROM = np.array([5, 1, 2, 3, 4, 0])  # of [x, y, z, -x, -y, -z]: -z, y, z, -x, -y, x


def _skew_b(v: np.ndarray) -> np.ndarray:
    """skew() of a bank of vectors (B, 3) with one gather and one scatter (the same entries)."""
    B = v.shape[0]
    K = np.zeros((B, 9))
    K[:, _SKEW_AT] = np.concatenate((v, -v), axis=1)[:, _SKEW_FROM]
    return K.reshape(B, 3, 3)


def _cross_b(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """np.cross(a (3,), b (B, 3)) with the same products and differences, without its overhead."""
    a0, a1, a2 = a.tolist()
    b0, b1, b2 = b[:, 0], b[:, 1], b[:, 2]
    return np.stack((a1 * b2 - a2 * b1, a2 * b0 - a0 * b2, a0 * b1 - a1 * b0), axis=-1)


def rot(rv: np.ndarray) -> np.ndarray:
    """Rotation matrices exp([rv x]) of rotation vectors (..., 3) (Rodrigues, series near 0)."""
    rv = np.asarray(rv, dtype=float)
    a2 = np.sum(rv * rv, axis=-1)[..., None, None]
    a = np.sqrt(a2)
    small = a2 < 1e-12
    s = np.where(small, 1.0 - a2 / 6.0, np.sin(a) / np.where(small, 1.0, a))
    c = np.where(small, 0.5 - a2 / 24.0, (1.0 - np.cos(a)) / np.where(small, 1.0, a2))
    K = skew(rv)
    return np.eye(3) + s * K + c * (K @ K)


def rotvec(C: np.ndarray) -> np.ndarray:
    """Rotation vectors (..., 3) of rotation matrices (..., 3, 3) (angles below pi)."""
    v = 0.5 * np.stack(
        [C[..., 2, 1] - C[..., 1, 2], C[..., 0, 2] - C[..., 2, 0], C[..., 1, 0] - C[..., 0, 1]], -1
    )
    s = np.linalg.norm(v, axis=-1)
    c = 0.5 * (np.trace(C, axis1=-2, axis2=-1) - 1.0)
    ang = np.arctan2(s, c)
    scale = np.where(s > 1e-12, ang / np.where(s > 1e-12, s, 1.0), 1.0 + s * s / 6.0)
    return v * scale[..., None]


def flexure_displacement_matrix(lever_arm_m: np.ndarray, kappa: float = 0.5) -> np.ndarray:
    """M with dr_flex = M theta: a beam of constant curvature bent by the angle theta at the node
    is displaced by kappa theta x r_nom (kappa = 1/2 for constant curvature)."""
    return -kappa * skew(lever_arm_m)


def flexure_q(beta_rps: np.ndarray, sigma_rad: np.ndarray) -> np.ndarray:
    """White-noise PSD of theta_ddot = -2 beta theta_dot - beta^2 theta + w giving var(theta) =
    sigma^2: var = q / (4 beta^3)."""
    return 4.0 * np.asarray(beta_rps) ** 3 * np.asarray(sigma_rad) ** 2


@dataclass
class TAParams:
    """The filter's assumptions, per member (B = number of slaves).

    lever_arm_m (B, 3) nominal lever arms in master axes; flex_beta_rps, flex_sigma_rad (B, 3);
    kappa: flexure displacement factor (M = -kappa [r_nom x]); noise densities of the slave IMU;
    prior sigmas; R0 (9,) or (B, 9) nominal measurement variances [att rad^2, vel (m/s)^2, rate (rad/s)^2].
    """

    lever_arm_m: np.ndarray
    flex_beta_rps: np.ndarray
    flex_sigma_rad: np.ndarray
    arw_rad_psqrts: float
    vrw_mps_psqrts: float
    gyro_bias_rps: float
    accel_bias_mps2: float
    R0: np.ndarray
    phi0_rad: float = 30.0 * np.pi / (180 * 60)
    dw0_mps: float = 0.1
    install_rad: float = 0.5 * np.pi / (180 * 60)
    coupling_rad: float = 10.0 * np.pi / (180 * 60)
    lever_arm_err_m: tuple[float, float, float] = (0.2, 0.1, 0.1)
    kappa: float = 0.5
    M: np.ndarray = field(init=False)

    def __post_init__(self):
        self.lever_arm_m = np.atleast_2d(np.asarray(self.lever_arm_m, dtype=float))
        B = self.lever_arm_m.shape[0]
        self.flex_beta_rps = np.broadcast_to(np.asarray(self.flex_beta_rps, float), (B, 3)).copy()
        self.flex_sigma_rad = np.broadcast_to(np.asarray(self.flex_sigma_rad, float), (B, 3)).copy()
        self.R0 = np.asarray(self.R0, dtype=float)  # (9,) or per member (B, 9)
        self.M = flexure_displacement_matrix(self.lever_arm_m, self.kappa)

    @property
    def B(self) -> int:
        return self.lever_arm_m.shape[0]

    def initial_covariance(self) -> np.ndarray:
        B = self.B
        d = np.zeros((B, N_STATES))
        d[:, PHI] = self.phi0_rad
        d[:, DW] = self.dw0_mps
        d[:, EPS] = self.gyro_bias_rps
        d[:, NAB] = self.accel_bias_mps2
        d[:, RHO] = self.install_rad
        d[:, TH] = self.flex_sigma_rad
        d[:, THD] = self.flex_sigma_rad * self.flex_beta_rps  # stationary: std(theta_dot) = beta sigma
        d[:, DD] = self.coupling_rad
        P = np.zeros((B, N_STATES, N_STATES))
        idx = np.arange(N_STATES)
        P[:, idx, idx] = d**2
        # dr = dr0 + M theta: the flexure part is correlated with theta
        Pth = np.einsum("bi,ij->bij", self.flex_sigma_rad**2, _I3)
        P[:, DR, DR] = np.diag(np.square(self.lever_arm_err_m)) + self.M @ Pth @ np.swapaxes(self.M, 1, 2)
        P[:, DR, TH] = self.M @ Pth
        P[:, TH, DR] = np.swapaxes(P[:, DR, TH], 1, 2)
        return P


_D3 = np.arange(3)


def continuous_model(
    omega_m: np.ndarray, f_sm: np.ndarray, C_ms: np.ndarray, p: TAParams
) -> tuple[np.ndarray, np.ndarray]:
    """F (B, 27, 27) and Qc (B, 27, 27) of the error model at master rate omega_m (3,),
    slave specific force in master axes f_sm (B, 3) and relative attitude C_ms (B, 3, 3)."""
    B = p.B
    W = skew(omega_m)
    F = np.zeros((B, N_STATES, N_STATES))
    F[:, PHI, PHI] = -W
    F[:, PHI, EPS] = -C_ms
    F[:, DW, PHI] = skew(f_sm)
    F[:, DW, DW] = -W
    F[:, DW, NAB] = C_ms
    F[:, 15 + _D3, 18 + _D3] = 1.0  # theta' = theta_dot
    beta = p.flex_beta_rps
    F[:, 18 + _D3, 15 + _D3] = -(beta**2)
    F[:, 18 + _D3, 18 + _D3] = -2.0 * beta
    F[:, DR, THD] = p.M
    Qc = np.zeros((B, N_STATES, N_STATES))
    Qc[:, _D3, _D3] = p.arw_rad_psqrts**2
    Qc[:, 3 + _D3, 3 + _D3] = p.vrw_mps_psqrts**2
    Qc[:, 18 + _D3, 18 + _D3] = flexure_q(beta, p.flex_sigma_rad)
    return F, Qc


def discretise(F: np.ndarray, Qc: np.ndarray, T: float) -> tuple[np.ndarray, np.ndarray]:
    """Batched fourth-order transition and Van Loan series for Qd (as service.ins.error_model)."""
    FT = F * T
    FT2 = FT @ FT
    Phi = np.eye(F.shape[-1]) + FT + FT2 / 2.0 + FT2 @ (FT / 6.0 + FT2 / 24.0)
    A = Qc
    Qd = Qc * T
    coef = T
    for k in range(1, 5):
        FA = F @ A
        A = FA + np.swapaxes(FA, -1, -2)
        coef *= T / (k + 1)
        Qd = Qd + A * coef
    return Phi, kalman.symmetrise(Qd)


def _h_template() -> np.ndarray:
    H = np.zeros((N_MEAS, N_STATES))
    H[_D3, _D3] = -1.0  # attitude: -phi
    for c in (12, 15, 24):  # + rho0 + theta + d_delta
        H[_D3, c + _D3] = 1.0
    H[3 + _D3, 3 + _D3] = 1.0  # velocity: dw
    H[6 + _D3, 6 + _D3] = 1.0  # rate: eps
    H[6 + _D3, 18 + _D3] = 1.0  # rate: theta_dot
    return H


_H0 = _h_template()


def measurement_matrix(omega_m: np.ndarray, p: TAParams) -> np.ndarray:
    """H (B, 9, 27) (eq 4, small-angle reading; see the module docstring) at the master rate (3,)."""
    W = skew(omega_m)
    H = np.repeat(_H0[None], p.B, axis=0)
    H[:, 3:6, THD] = p.M
    H[:, 3:6, DR] = W
    H[:, 6:9, RHO] = W
    H[:, 6:9, TH] = W
    H[:, 6:9, DD] = W
    return H


def norm_weights(P: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """A_j = sqrt(tr(P_j^2)) (eq 18) and alpha_j = sum_{i != j} A_i / (2 sum_i A_i) (eq 19; the
    shares sum to (B - 1) / 2, i.e. 1 for the paper's three slaves)."""
    A = np.sqrt(np.einsum("bij,bji->b", P, P))
    alpha = (A.sum() - A) / (2.0 * A.sum())
    return A, alpha


@dataclass
class StepInfo:
    """What one filter epoch did, per member (for outputs and evaluation)."""

    t: float
    nis: np.ndarray
    gamma: np.ndarray
    fading_s: np.ndarray
    fading_triggered: np.ndarray
    R_diag: np.ndarray
    alpha: np.ndarray | None


class TransferAlignmentBank:
    """Relative mechanisation and the 27-state filter of B slaves (one bank member each).

    ``mode``: "kf" (plain Kalman filter with the nominal R) or "akf" (Sage-Husa R and chi2
    fading factors on P; an adapted R_ii never goes below ``r_floor`` times the nominal).
    ``fading_form``: "added" (P = J + T J T' + Q, T = sqrt(S^2 - I): fading only adds
    uncertainty; default) or "scaled" (eq 8 literally, S J S' + Q, which shrinks P along
    combinations of faded and unfaded correlated states and made the filter overconfident:
    :func:`service.estimation.adaptive.faded_covariance`, docs/seed002.md).
    ``lever_follows_flexure`` (with "added", default on): the uncertainty fading adds to the
    flexure angle moves the lever arm's flexure part M theta with it (:meth:`_faded`).
    ``fusion``: "none" (local filters only; the honest reading, docs/seed002.md) or "paper"
    (eq 18-21 applied to all 27 states as if they were common).
    """

    def __init__(
        self,
        p: TAParams,
        *,
        mode: str = "akf",
        fusion: str = "none",
        filter_period_s: float = 0.1,
        forgetting: float = 0.97,
        restart: bool = True,
        p_fa: float = 0.01,
        r_floor: float = 0.1,
        fading: bool = True,
        order: str = "r_then_p",
        fading_form: str = "added",
        lever_follows_flexure: bool = True,
        t0: float = 0.0,
    ):
        if mode not in ("kf", "akf"):
            raise ValueError(f"mode {mode!r}: use 'kf' or 'akf'")
        if fusion not in ("none", "paper"):
            raise ValueError(f"fusion {fusion!r}: use 'none' or 'paper'")
        self.p = p
        self.mode, self.fusion = mode, fusion
        self.fading = fading
        if order not in ("r_then_p", "p_then_r"):
            raise ValueError(f"order {order!r}: use 'r_then_p' or 'p_then_r'")
        self.order = order
        if fading_form not in ("scaled", "added"):
            raise ValueError(f"fading_form {fading_form!r}: use 'scaled' or 'added'")
        self.fading_form = fading_form
        self.lever_follows_flexure = bool(lever_follows_flexure)
        self.T = float(filter_period_s)
        B = p.B
        self.x = np.zeros((B, N_STATES))
        self.P = p.initial_covariance()
        self.R0 = p.R0[..., :, None] * np.eye(N_MEAS)  # (9, 9) or (B, 9, 9)
        self.sh = (
            SageHusaR(self.R0, B, forgetting, restart=restart, diagonal=True, floor=r_floor * p.R0)
            if mode == "akf"
            else None
        )
        self.thr = chi2_threshold(N_MEAS, p_fa)
        self.row_thr = chi2_threshold(1, p_fa)
        self.C_im = np.eye(3)
        self.C_ms = np.broadcast_to(np.eye(3), (B, 3, 3)).copy()
        self.V = None  # set at the first sample (needs the master rate)
        self.t = t0
        self._acc_T = 0.0
        self._w_prev: np.ndarray | None = None
        self._acc_w = np.zeros(3)
        self._acc_f = np.zeros((B, 3))
        self.epochs = 0
        self.last: StepInfo | None = None

    # --- mechanisation ------------------------------------------------------------------------
    def push(self, dth_m, dv_m, dth_s, dv_s, dt: float, t_end: float) -> StepInfo | None:
        """One IMU interval of the master (3,) and of every slave (B, 3); runs a filter epoch when
        a filter period is complete and returns its StepInfo (else None)."""
        dth_m = np.asarray(dth_m, float)
        dv_m = np.asarray(dv_m, float)
        dth_s = np.asarray(dth_s, float)
        dv_s = np.asarray(dv_s, float)
        w_m = dth_m / dt
        if self.V is None:
            self.V = np.cross(w_m, self.p.lever_arm_m)  # nominal lever-arm velocity, C_im = I
        # second-order exponentials of the sample increments (|dtheta| < 0.05 rad: error < 2e-5
        # of the increment, orthonormality restored at every epoch)
        Km = _skew3(dth_m)
        dCm = _I3 + Km + 0.5 * (Km @ Km)
        Ks = _skew_b(dth_s)
        C_new = dCm.T @ self.C_ms @ (_I3 + Ks + 0.5 * (Ks @ Ks))
        C_mid = 0.5 * (self.C_ms + C_new)  # mid-interval relative attitude (error O(dmu^2) ~ 1e-8)
        f_sm = np.einsum("bij,bj->bi", C_mid, dv_s)
        self.V = self.V + (f_sm - dv_m) @ (self.C_im + 0.5 * (self.C_im @ Km)).T
        self.C_ms = C_new
        self.C_im = self.C_im @ dCm
        self._acc_T += dt
        self._acc_w += dth_m
        self._acc_f += f_sm
        self.t = t_end
        # master rate at the end of the sample: the sample means are rates at mid-sample; linear
        # extrapolation by half a sample (matters in roll/turn entries: omega_dot x r ~ 1e-3 m/s)
        # (evaluated at the epoch only: _last_rates)
        self._last = (w_m, self._w_prev, dth_s, dt)
        self._w_prev = w_m
        if self._acc_T >= self.T - 1e-9:
            return self._epoch()
        return None

    @property
    def _last_rates(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """(master rate, slave rates, master rate extrapolated to the end) of the last sample."""
        w_m, w_prev, dth_s, dt = self._last
        w_end = w_m if w_prev is None else 1.5 * w_m - 0.5 * w_prev
        return w_m, dth_s / dt, w_end

    def w_hat(self) -> np.ndarray:
        """(B, 3) slave-minus-master velocity in master axes."""
        return self.V @ self.C_im

    def measurements(self) -> np.ndarray:
        w_m, w_s, w_end = self._last_rates
        z_a = rotvec(self.C_ms)
        z_v = self.w_hat() - _cross_b(w_end, self.p.lever_arm_m)
        z_w = w_s - w_m
        return np.concatenate([z_a, z_v, z_w], axis=1)

    # --- filter -------------------------------------------------------------------------------
    def _epoch(self) -> StepInfo:
        # one Newton step of the polar decomposition keeps the attitudes orthonormal
        self.C_ms = 0.5 * self.C_ms @ (3.0 * _I3 - np.swapaxes(self.C_ms, 1, 2) @ self.C_ms)
        self.C_im = 0.5 * self.C_im @ (3.0 * _I3 - self.C_im.T @ self.C_im)
        T = self._acc_T
        w_avg = self._acc_w / T
        f_avg = self._acc_f / T
        self._acc_T, self._acc_w, self._acc_f = 0.0, np.zeros(3), np.zeros_like(self._acc_f)
        F, Qc = continuous_model(w_avg, f_avg, self.C_ms, self.p)
        Phi, Qd = discretise(F, Qc, T)
        x_pred = np.einsum("bij,bj->bi", Phi, self.x)
        J = kalman.symmetrise(Phi @ self.P @ np.swapaxes(Phi, 1, 2))
        H = measurement_matrix(self._last_rates[2], self.p)
        z = self.measurements()
        r = z - np.einsum("bij,bj->bi", H, x_pred)
        Ht = np.swapaxes(H, 1, 2)
        B = self.p.B
        if self.mode == "akf" and self.order == "p_then_r":
            fad = fading_factors(r, H, J, H @ Qd @ Ht + self.sh.R, self.thr, self.row_thr, FADING_STATES)
            if not self.fading:  # Sage-Husa R only: the statistic is still reported
                fad = replace(fad, s=np.ones_like(fad.s), triggered=np.zeros_like(fad.triggered))
            P_pred = self._faded(J, fad.s, Qd)
            R = self.sh.update(r, H @ P_pred @ Ht).copy()
            s, gamma, trig = fad.s, fad.gamma, fad.triggered
        elif self.mode == "akf":  # R first (section 1.2 order): the chi2 test sees the adapted R
            HJHt = H @ J @ Ht
            HQHt = H @ Qd @ Ht
            R = self.sh.update(r, HJHt + HQHt).copy()
            fad = fading_factors(r, H, J, HQHt + R, self.thr, self.row_thr, FADING_STATES, HJHt=HJHt)
            if not self.fading:
                fad = replace(fad, s=np.ones_like(fad.s), triggered=np.zeros_like(fad.triggered))
            P_pred = self._faded(J, fad.s, Qd)
            s, gamma, trig = fad.s, fad.gamma, fad.triggered
        else:
            P_pred = kalman.symmetrise(J + Qd)
            R = np.broadcast_to(self.R0, (B, N_MEAS, N_MEAS))
            s, gamma, trig = np.ones((B, N_STATES)), np.full(B, np.nan), np.zeros(B, bool)
        x, P, res = kalman.update(x_pred, P_pred, z, H, R)
        alpha = None
        if self.fusion == "paper":
            x, P, alpha = _paper_fusion(x, P)
        self.x, self.P = x, P
        self._feedback()
        self.epochs += 1
        self.last = StepInfo(self.t, res.nis, gamma, s, trig, np.diagonal(R, axis1=1, axis2=2).copy(), alpha)
        return self.last

    def _faded(self, J: np.ndarray, s: np.ndarray, Qd: np.ndarray) -> np.ndarray:
        """Faded prediction covariance. ``"added"`` with ``lever_follows_flexure`` (default): the
        uncertainty added to the flexure angle theta also moves the lever arm by M times it (the
        lever arm is r_nom + dr0 + M theta: T = diag(t) plus the block T[dr, theta] = M diag(t_theta)),
        so fading keeps dr = dr0 + M theta; without it, each trigger made the flexure more uncertain
        than the lever arm's flexure part and the lever arm stopped converging (docs/seed002.md,
        issue 25: over 60 min the adaptive filter's lever arm stalled at 5-6 mm)."""
        P = faded_covariance(J, s, Qd, self.fading_form)
        if self.fading_form != "added" or not self.lever_follows_flexure:
            return P
        t_th = np.sqrt(np.maximum(s[:, TH] ** 2 - 1.0, 0.0))  # (B, 3)
        b = np.flatnonzero(np.any(t_th > 0.0, axis=1))
        if b.size == 0:
            return P
        t = np.sqrt(np.maximum(s[b] ** 2 - 1.0, 0.0))
        T = t[:, :, None] * np.eye(N_STATES)
        T[:, DR, TH] = self.p.M[b] * t_th[b][:, None, :]
        P = P.copy()
        # the coherent term T J T' replaces the diagonal one diag(t) J diag(t) of the "added" form
        P[b] += T @ J[b] @ np.swapaxes(T, 1, 2) - t[:, :, None] * J[b] * t[:, None, :]
        return kalman.symmetrise(P)

    def _feedback(self) -> None:
        """Closed loop: the relative attitude and velocity absorb phi and dw (states reset to 0)."""
        phi = self.x[:, PHI]
        self.C_ms = rot(phi) @ self.C_ms  # C_ms = exp([phi x]) C_ms^
        self.V = self.V - self.x[:, DW] @ self.C_im.T
        self.x[:, PHI] = 0.0
        self.x[:, DW] = 0.0

    # --- outputs ------------------------------------------------------------------------------
    def lever_arm_m(self) -> np.ndarray:
        return self.p.lever_arm_m + self.x[:, DR]

    def sigmas(self) -> np.ndarray:
        return np.sqrt(np.clip(np.diagonal(self.P, axis1=1, axis2=2), 0.0, None))


def _paper_fusion(x: np.ndarray, P: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Eq 18-21 on whole state vectors: x_g, P_g by information fusion, then P_j = alpha_j^-1 P_g,
    x_j = x_g. Treats every slave's 27 states as the same quantities (the literal reading)."""
    _, alpha = norm_weights(P)
    xg, Pg = kalman.information_fusion(x, P)
    return np.broadcast_to(xg, x.shape).copy(), Pg[None] / alpha[:, None, None], alpha


__all__ = [
    "N_STATES",
    "N_MEAS",
    "PHI",
    "DW",
    "EPS",
    "NAB",
    "RHO",
    "TH",
    "THD",
    "DR",
    "DD",
    "TAParams",
    "TransferAlignmentBank",
    "StepInfo",
    "continuous_model",
    "discretise",
    "measurement_matrix",
    "norm_weights",
    "flexure_q",
    "flexure_displacement_matrix",
    "rot",
    "rotvec",
    "skew",
]
