"""Wing IMU nodes for transfer alignment (Zhu, Ma, Wang, Chen 2022, section 2.1 and Table 1).

The master IMU sits on the fuselage (the scenario's trajectory and [imu]); each slave IMU sits on
the wing at a lever arm r_nom + dr0 (dr0 the lever-arm error, drawn per run) and is rotated from
the master by mu(t) = rho0 + d_delta + theta(t) + v(t):

- rho0: installation angle, d_delta: coupling angle (constants drawn per run);
- theta(t): wing flexure per axis, second-order Gauss-Markov theta_ddot = -2 beta theta_dot -
  beta^2 theta + w (stationary, var(theta) = q / (4 beta^3)), simulated by its exact discrete
  transition; the flexure also displaces the node: r(t) = r_nom + dr0 + M theta(t),
  M = -kappa [r_nom x] (a beam of constant curvature: kappa = 1/2);
- v(t): wing vibration per axis, a lightly damped resonator (second-order, frequency
  ``vibration_hz``, damping ``vibration_damping``) of rms ``vibration_arcmin`` scaled by a gain
  that rises to ``turbulence_gain`` inside the turbulence windows (smooth 2 s ramps): not
  modelled by the filter (it is the time-varying measurement noise that adaptation is for).

Exact kinematics: the slave's rotation increment over (t_k-1, t_k] is
rotvec(C_ms(k-1)' exp(dtheta_m) C_ms(k)) (exact given the master's), and its specific force
f_s = C_sm (f_m + omega_dot x r + omega x (omega x r) + 2 omega x r_dot + r_ddot) (gravity is
common; its gradient over 3 m is negligible), integrated by the trapezoid rule for the smooth
terms and exactly for r_ddot (M times the increment of theta_dot). The slave IMU errors (Table 1
grades) are then applied by :func:`simulators.imu.apply_imu_errors`.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from pydantic import BaseModel, ConfigDict, Field
from scipy.linalg import expm
from scipy.signal import lfilter

from fednav.service import earth
from fednav.service.estimation.transfer_alignment import flexure_displacement_matrix, flexure_q, rot, rotvec
from fednav.simulators.imu import ImuErrorTruth, ImuSpec, apply_imu_errors

Vec3 = tuple[float, float, float]


class _M(BaseModel):
    model_config = ConfigDict(extra="forbid", frozen=True)


class WingNodeSpec(_M):
    id: str = Field(pattern=r"^[A-Za-z0-9_\-.]+$", description="Node id (IMU sensor id), e.g. wing1")
    lever_arm_m: Vec3 = Field(description="Nominal lever arm from the master, master axes (RFU), m")
    flexure_arcmin: Vec3 = Field(description="Flexure angle rms per axis, arcmin")
    flexure_beta_rps: Vec3 = Field(description="Flexure Gauss-Markov beta per axis, rad/s")


class WingSpec(_M):
    """Slave nodes, their IMU grade (Table 1) and the wing's motion."""

    nodes: list[WingNodeSpec] = Field(min_length=1)
    gyro_bias_dph: float = Field(0.05, ge=0, description="Slave gyro constant drift 1-sigma, deg/h")
    arw_dpsh: float = Field(0.025, ge=0, description="Slave angle random walk, deg/sqrt(h)")
    accel_bias_ug: float = Field(150.0, ge=0, description="Slave accelerometer bias 1-sigma, ug")
    vrw_ugpsHz: float = Field(50.0, ge=0, description="Slave velocity random walk, ug/sqrt(Hz)")
    install_arcmin: float = Field(0.5, ge=0, description="Installation angle 1-sigma per axis, arcmin")
    coupling_arcmin: float = Field(10.0, ge=0, description="Coupling angle 1-sigma per axis, arcmin")
    lever_arm_error_m: Vec3 = Field((0.2, 0.1, 0.1), description="Lever-arm error 1-sigma per axis, m")
    kappa: float = Field(0.5, ge=0, description="Flexure displacement factor (M = -kappa [r x])")
    vibration_arcmin: Vec3 = Field((0.3, 0.3, 0.3), description="Vibration rms per axis (calm), arcmin")
    vibration_hz: float = Field(6.0, gt=0, description="Vibration resonance, Hz")
    vibration_damping: float = Field(0.3, gt=0, lt=1, description="Vibration damping ratio")
    turbulence: list[tuple[float, float]] = Field(
        default_factory=list, description="Turbulence windows [start_s, end_s] (relative time)"
    )
    turbulence_gain: float = Field(4.0, ge=1, description="Vibration gain inside turbulence windows")
    vibration_displacement: bool = Field(
        False, description="The vibration bends the wing like the flexure: the node moves by M v(t) too"
    )
    turbulence_flexure_gain: float = Field(
        1.0, ge=1, description="Flexure (angle and rate) gain inside turbulence windows (gust loads)"
    )


@dataclass
class NodeTruth:
    """One node's truth at every IMU sample (relative time t_rel_s (N,))."""

    id: str
    lever_arm_nom_m: np.ndarray  # (3,)
    rho0_rad: np.ndarray  # (3,)
    coupling_rad: np.ndarray  # (3,)
    dr0_m: np.ndarray  # (3,)
    theta_rad: np.ndarray  # (N, 3)
    theta_dot_rps: np.ndarray  # (N, 3)
    vibration_rad: np.ndarray  # (N, 3)
    lever_arm_m: np.ndarray  # (N, 3) true lever arm r(t)
    C_ms: np.ndarray  # (N, 3, 3)
    imu: ImuErrorTruth
    dtheta_rad: np.ndarray  # (N, 3) measured increments
    dvel_mps: np.ndarray  # (N, 3)

    @property
    def mu_rad(self) -> np.ndarray:
        return rotvec(self.C_ms)


def _lti2(Phi: np.ndarray, w: np.ndarray, x0: np.ndarray) -> np.ndarray:
    """x_k = Phi x_(k-1) + w_k (k >= 1), x_0 = x0, for a 2x2 Phi, as one IIR filter: by
    Cayley-Hamilton (I - Phi z^-1)^-1 = (I - z^-1 (tr I - Phi)) / (1 - tr z^-1 + det z^-2)."""
    u = np.array(w, dtype=float)
    u[0] = x0
    tr, det = float(np.trace(Phi)), float(np.linalg.det(Phi))
    u[1:] -= u[:-1] @ (tr * np.eye(2) - Phi).T
    return lfilter([1.0], [1.0, -tr, det], u, axis=0)


def _gm2(n: int, dt: float, beta: np.ndarray, sigma: np.ndarray, rng: np.random.Generator):
    """Stationary second-order Gauss-Markov (N, 3) angle and rate per axis by the exact transition."""
    th = np.zeros((n, 3))
    thd = np.zeros((n, 3))
    for ax in range(3):
        b, s = float(beta[ax]), float(sigma[ax])
        if s == 0.0:
            continue
        A = np.array([[0.0, 1.0], [-b * b, -2.0 * b]])
        q = float(flexure_q(b, s))
        Phi = expm(A * dt)
        # Van Loan: Qd from expm of [[-A, G q G'], [0, A']]
        Mv = np.zeros((4, 4))
        Mv[:2, :2] = -A
        Mv[:2, 2:] = np.array([[0.0, 0.0], [0.0, q]])
        Mv[2:, 2:] = A.T
        E = expm(Mv * dt)
        Qd = E[2:, 2:].T @ E[:2, 2:]
        Qd = 0.5 * (Qd + Qd.T)
        Lq = np.linalg.cholesky(Qd + 1e-30 * np.eye(2))
        P0 = np.diag([s * s, (b * s) ** 2])  # stationary covariance (theta, theta_dot uncorrelated)
        x0 = np.linalg.cholesky(P0) @ rng.standard_normal(2)
        out = _lti2(Phi, rng.standard_normal((n, 2)) @ Lq.T, x0)
        th[:, ax], thd[:, ax] = out[:, 0], out[:, 1]
    return th, thd


def _resonator(n: int, dt: float, f_hz: float, zeta: float, rms: np.ndarray, rng: np.random.Generator):
    """Band-limited vibration: x_ddot = -2 zeta w0 x_dot - w0^2 x + w, unit rms scaled by ``rms``;
    returns the angle and its rate (N, 3)."""
    w0 = 2.0 * np.pi * f_hz
    A = np.array([[0.0, 1.0], [-w0 * w0, -2.0 * zeta * w0]])
    q = 4.0 * zeta * w0**3  # var(x) = q / (4 zeta w0^3) = 1
    Mv = np.zeros((4, 4))
    Mv[:2, :2] = -A
    Mv[:2, 2:] = np.array([[0.0, 0.0], [0.0, q]])
    Mv[2:, 2:] = A.T
    E = expm(Mv * dt)
    Qd = E[2:, 2:].T @ E[:2, 2:]
    Lq = np.linalg.cholesky(0.5 * (Qd + Qd.T))
    Phi = expm(A * dt)
    x = np.zeros((n, 3))
    xd = np.zeros((n, 3))
    for ax in range(3):
        x0 = np.array([rng.standard_normal(), w0 * rng.standard_normal()])
        xa = _lti2(Phi, rng.standard_normal((n, 2)) @ Lq.T, x0)
        x[:, ax], xd[:, ax] = xa[:, 0], xa[:, 1]
    return x * np.asarray(rms), xd * np.asarray(rms)


def turbulence_gain(
    t_rel_s: np.ndarray, spec: WingSpec, ramp_s: float = 2.0, gain: float | None = None
) -> np.ndarray:
    """Vibration gain (N,): 1 outside the windows, ``turbulence_gain`` (or ``gain``) inside,
    cosine ramps."""
    top = spec.turbulence_gain if gain is None else float(gain)
    g = np.ones_like(t_rel_s)
    for t0, t1 in spec.turbulence:
        up = np.clip((t_rel_s - t0) / ramp_s, 0.0, 1.0)
        down = np.clip((t1 - t_rel_s) / ramp_s, 0.0, 1.0)
        shape = 0.5 - 0.5 * np.cos(np.pi * np.minimum(up, down))
        g = np.maximum(g, 1.0 + (top - 1.0) * shape)
    return g


def simulate_wing(spec: WingSpec, traj, rng: np.random.Generator, imu_rate_hz: float) -> list[NodeTruth]:
    """Slave IMU increments and truth for every node over the trajectory (master exact increments
    ``traj.dtheta_rad``/``traj.dvel_mps``, rates from ``traj.body_rates``)."""
    n = traj.t_s.size
    dt = 1.0 / imu_rate_hz
    t_rel = np.arange(n) * dt
    omega, _f = traj.body_rates(t_rel)
    omega_dot = np.gradient(omega, dt, axis=0)
    dCm = rot(traj.dtheta_rad)
    gain = turbulence_gain(t_rel, spec)
    gain_dot = np.gradient(gain, dt)
    fgain = turbulence_gain(t_rel, spec, gain=spec.turbulence_flexure_gain)
    fgain_dot = np.gradient(fgain, dt)
    out = []
    for node in spec.nodes:
        r_nom = np.asarray(node.lever_arm_m, float)
        rho0 = rng.standard_normal(3) * spec.install_arcmin * earth.ARCMIN
        dd = rng.standard_normal(3) * spec.coupling_arcmin * earth.ARCMIN
        dr0 = rng.standard_normal(3) * np.asarray(spec.lever_arm_error_m)
        beta = np.asarray(node.flexure_beta_rps, float)
        th, thd = _gm2(n, dt, beta, np.asarray(node.flexure_arcmin) * earth.ARCMIN, rng)
        if spec.turbulence_flexure_gain != 1.0:  # gust loads: theta g(t), rate theta_dot g + theta g'
            th, thd = th * fgain[:, None], thd * fgain[:, None] + th * fgain_dot[:, None]
        vib, vib_dot = _resonator(
            n,
            dt,
            spec.vibration_hz,
            spec.vibration_damping,
            np.asarray(spec.vibration_arcmin) * earth.ARCMIN,
            rng,
        )
        vib, vib_dot = vib * gain[:, None], vib_dot * gain[:, None] + vib * gain_dot[:, None]
        M = flexure_displacement_matrix(r_nom, spec.kappa)
        r = r_nom + dr0 + th @ M.T  # the scored lever arm: nominal + error + quasi-static flexure
        rdot = thd @ M.T
        r_lever = r
        if spec.vibration_displacement:  # the node's position also vibrates (noise, not scored)
            r = r + vib @ M.T
            rdot = rdot + vib_dot @ M.T
        C_ms = rot(rho0 + dd + th + vib)
        # gyro: exact relative rotation increments
        dth = np.zeros((n, 3))
        dth[1:] = rotvec(np.swapaxes(C_ms[:-1], 1, 2) @ dCm[1:] @ C_ms[1:])
        # accelerometer: f_s^m = f_m + omega_dot x r + omega x (omega x r) + 2 omega x r_dot + r_ddot
        a_rel = np.cross(omega_dot, r) + np.cross(omega, np.cross(omega, r)) + 2.0 * np.cross(omega, rdot)
        dv_m = traj.dvel_mps[1:] + 0.5 * (a_rel[:-1] + a_rel[1:]) * dt + (thd[1:] - thd[:-1]) @ M.T
        if spec.vibration_displacement:
            dv_m = dv_m + (vib_dot[1:] - vib_dot[:-1]) @ M.T
        C_mid = rot(0.5 * (rotvec(C_ms[:-1]) + rotvec(C_ms[1:])))
        dv = np.zeros((n, 3))
        dv[1:] = np.einsum("kji,kj->ki", C_mid, dv_m)  # C_sm = C_ms'
        ispec = ImuSpec(
            id=node.id,
            rate_hz=imu_rate_hz,
            bias_mode="random",
            gyro_bias_dph=(spec.gyro_bias_dph,) * 3,
            accel_bias_ug=(spec.accel_bias_ug,) * 3,
            arw_dpsh=spec.arw_dpsh,
            vrw_ugpsHz=spec.vrw_ugpsHz,
        )
        dth_meas, dv_meas, imu_truth = apply_imu_errors(ispec, dth, dv, rng)
        out.append(
            NodeTruth(
                node.id, r_nom, rho0, dd, dr0, th, thd, vib, r_lever, C_ms, imu_truth, dth_meas, dv_meas
            )
        )
    return out


__all__ = ["NodeTruth", "WingNodeSpec", "WingSpec", "simulate_wing", "turbulence_gain"]


def wing_rng(seed: int) -> np.random.Generator:
    """The wing nodes' generator of a run (independent of the master stream's generators)."""
    return np.random.default_rng(np.random.SeedSequence([seed, 2]).spawn(2)[1])


class WingSimulation:
    """The scenario's message stream (:class:`simulators.stream.Simulation`: master IMU, GNSS,
    init, truth) with every wing node's ImuSample inserted before the master sample of the same
    instant (``fednav/{vehicle}/sensor/imu/{node}``), so a service steps the nodes with the master.
    ``nodes`` holds the nodes' truth; ``master`` the wrapped Simulation."""

    def __init__(
        self, scenario, seed: int | None = None, vehicle: str = "v1", trajectory=None, prefix: str = "fednav"
    ):
        from fednav.service import keys
        from fednav.simulators.stream import Simulation

        if scenario.wing is None:
            raise ValueError("scenario has no [wing] section")
        seed = scenario.seed if seed is None else int(seed)
        self.master = Simulation(scenario, seed=seed, vehicle=vehicle, trajectory=trajectory, prefix=prefix)
        traj = self.master.trajectory
        self.nodes = simulate_wing(scenario.wing, traj, wing_rng(seed), scenario.imu.rate_hz)
        self._master_key = keys.sensor(vehicle, "imu", scenario.imu.id, prefix)
        self._truth_key = keys.truth(vehicle, prefix)
        self._node_truth_keys = [keys.alignment_truth(vehicle, n.id, prefix) for n in self.nodes]
        self._keys = [keys.sensor(vehicle, "imu", n.id, prefix) for n in self.nodes]
        self._t0 = traj.t0_gps_s
        self._rate = scenario.imu.rate_hz
        self._gen = self._messages()

    def __iter__(self):
        return self

    def node_truth(self, j: int, k: int, t: float):
        from fednav.service.messages import AlignmentTruth

        n = self.nodes[j]
        deg = 1.0 / earth.DEG
        return AlignmentTruth(
            t=t,
            node=n.id,
            mount_deg=tuple(float(v) for v in rotvec(n.C_ms[k]) * deg),
            installation_deg=tuple(float(v) for v in (n.rho0_rad + n.coupling_rad) * deg),
            flexure_deg=tuple(float(v) for v in n.theta_rad[k] * deg),
            lever_arm_m=tuple(float(v) for v in n.lever_arm_m[k]),
        )

    def __next__(self):
        return next(self._gen)

    def _messages(self):
        from fednav.service.messages import ImuSample

        dt = 1.0 / self._rate
        dth = [n.dtheta_rad.tolist() for n in self.nodes]
        dv = [n.dvel_mps.tolist() for n in self.nodes]
        for key, msg in self.master:
            if key == self._truth_key:
                yield key, msg
                k = int(round((msg.t - self._t0) * self._rate))
                for j, tkey in enumerate(self._node_truth_keys):
                    yield tkey, self.node_truth(j, k, msg.t)
                continue
            if key == self._master_key:
                k = int(round((msg.t - self._t0) * self._rate))
                for j, nkey in enumerate(self._keys):
                    yield (
                        nkey,
                        ImuSample.model_construct(
                            t=msg.t, dt_s=dt, dtheta_rad=tuple(dth[j][k]), dvel_mps=tuple(dv[j][k])
                        ),
                    )
            yield key, msg
