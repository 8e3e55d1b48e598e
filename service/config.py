"""Service configuration: typed, documented, validated whole at load (errors name the field).

A TOML file (``fednav-service --config service.toml``) or a ``[service]`` table of a scenario
(used by ``fednav-sim eval``). Unknown keys are errors; nothing is silently "fixed".
"""

from __future__ import annotations

import tomllib
from collections.abc import Sequence
from pathlib import Path
from typing import Annotated, Any, Literal

from pydantic import BaseModel, ConfigDict, Field, ValidationError, field_validator, model_validator

from fednav.service import earth
from fednav.service.ins.error_model import ImuNoise
from fednav.service.ros2_config import Ros2Config


class Model(BaseModel):
    model_config = ConfigDict(extra="forbid", frozen=True)


class ImuModel(Model):
    """The IMU grade the filters assume (process model), in datasheet units.

    ``grade`` fills every field not given from a preset (docs/imu_grades.md); explicit numbers
    override. Without a grade the defaults are the navigation-grade preset."""

    grade: Literal["navigation", "tactical", "industrial_mems", "consumer_mems"] | None = Field(
        None,
        description="IMU class preset (docs/imu_grades.md): navigation, tactical, industrial_mems, "
        "consumer_mems (a phone); fields given explicitly override the preset",
    )

    gyro_bias_dph: float = Field(0.01, ge=0, description="Gyro bias 1-sigma (initial uncertainty), deg/h")
    accel_bias_ug: float = Field(50.0, ge=0, description="Accelerometer bias 1-sigma, micro-g")
    arw_dpsh: float = Field(0.001, gt=0, description="Angle random walk, deg/sqrt(h)")
    vrw_ugpsHz: float = Field(5.0, gt=0, description="Velocity random walk, micro-g/sqrt(Hz)")
    gyro_bias_rw_dphpsh: float = Field(0.0, ge=0, description="Gyro bias random walk, deg/h/sqrt(h)")
    accel_bias_rw_ugpsh: float = Field(0.0, ge=0, description="Accel bias random walk, micro-g/sqrt(h)")

    @model_validator(mode="before")
    @classmethod
    def _preset(cls, data):
        if isinstance(data, dict) and data.get("grade") is not None:
            from fednav.service.ins.imu_grades import PRESETS

            preset = PRESETS.get(data["grade"])
            if preset is not None:  # an unknown grade is refused by the Literal, naming it
                data = {**preset.config_fields(), **data}
        return data

    def noise(self) -> ImuNoise:
        return ImuNoise(
            arw=self.arw_dpsh * earth.DEG / 60.0,
            vrw=self.vrw_ugpsHz * earth.UG,
            gyro_bias_rw=self.gyro_bias_rw_dphpsh * earth.DPH / 60.0,
            accel_bias_rw=self.accel_bias_rw_ugpsh * earth.UG / 60.0,
        )

    def bias_sigmas(self) -> tuple[float, float]:
        return self.gyro_bias_dph * earth.DPH, self.accel_bias_ug * earth.UG


class GnssCorrelatedError(Model):
    """First-order Gauss-Markov receiver position error as filter states (docs/own_data.md)."""

    sigma_enu_m: tuple[float, float, float] = Field(
        description="1-sigma of the correlated part of the fix error, east/north/up, m (the fix's own "
        "sigma is its total error: the white part is what remains)"
    )
    correlation_time_s: float = Field(60.0, gt=0, description="Correlation time, s")

    @model_validator(mode="after")
    def _positive(self):
        if min(self.sigma_enu_m) <= 0:
            raise ValueError("sigma_enu_m: every component must be > 0")
        return self


#: GNSS antenna position relative to the IMU, shared by the pipelines that take GNSS fixes
GnssLeverArm = Annotated[
    tuple[float, float, float],
    Field(
        description="GNSS antenna position relative to the IMU in body axes (right, forward, up), m "
        "(README 'Conventions (one place)')"
    ),
]
GnssCorrelatedErrorOption = Annotated[
    GnssCorrelatedError | None,
    Field(description="Estimate a time-correlated receiver position error (None: fixes independent)"),
]


SensorKindName = Annotated[str, Field(pattern=r"^[a-z][a-z0-9_]*$")]
#: options of the sensors' measurement models in a pipeline, by kind (the registry entry's
#: ``options`` model validates them when the configuration is loaded)
SensorOptions = Annotated[
    dict[SensorKindName, dict[str, Any]],
    Field(
        default_factory=dict,
        description="Options of the measurement models by sensor kind, e.g. {baro = {offset_std_m = 20}} "
        "(each kind's options: its entry in the sensor registry, service/sensors)",
    ),
]


class LooselyCoupledConfig(Model):
    kind: Literal["loosely_coupled"] = "loosely_coupled"
    name: str = Field(pattern=r"^[A-Za-z0-9_\-]+$")
    sensors: list[SensorKindName] | None = Field(
        None,
        description="Sensor kinds this pipeline fuses (any kind of the sensor registry with a measurement "
        "model, e.g. ['gnss_fix', 'baro']); default: gnss_fix, and star when use_star",
    )
    sensor_options: SensorOptions
    gnss_lever_arm_b_m: GnssLeverArm = (0.0, 0.0, 0.0)
    gnss_correlated_error: GnssCorrelatedErrorOption = None
    estimate_gnss_lever_arm: bool = Field(
        False,
        description="Estimate the GNSS antenna lever arm as filter states (gnss_lever_arm_b_m is then its "
        "prior mean); observed in turns (docs/own_data.md 'Unknown antenna offset / IMU scale factors')",
    )
    gnss_lever_arm_std_m: float = Field(
        1.0, gt=0, le=100.0, description="Prior 1-sigma of the estimated lever arm per body axis, m"
    )
    gnss_lever_arm_rw_m_per_sqrt_h: float = Field(
        0.0, ge=0, le=10.0, description="Random walk of the estimated lever arm, m/sqrt(h) (0: constant)"
    )
    estimate_imu_scale_factors: bool = Field(
        False,
        description="Estimate the gyro and accelerometer scale-factor errors (3 + 3 states); observed in "
        "turns (gyro) and speed changes (accelerometer)",
    )
    gyro_scale_factor_std_ppm: float = Field(
        5000.0, gt=0, le=1e5, description="Prior 1-sigma of each gyro scale-factor error, ppm"
    )
    accel_scale_factor_std_ppm: float = Field(
        5000.0, gt=0, le=1e5, description="Prior 1-sigma of each accelerometer scale-factor error, ppm"
    )
    use_star: bool = Field(True, description="Use star-tracker attitude when present")
    innovation_gate_sigma: float | None = Field(
        5.0,
        gt=0,
        description="Innovation gate: an observation (row) whose standardised innovation |r_j|/sqrt(S_jj) "
        "exceeds this is refused, the other rows of its source (a fix's position solution) are used only "
        "within 2 sigma, the other sources' rows are used (5: a false refusal per row about 6e-7 "
        "under the model; None: no gate, not recommended)",
    )
    gate_recovery_s: float = Field(
        10.0,
        gt=0,
        description="After every row of a sensor kind has been refused for this long, the filter's "
        "covariance is restarted (INS kept) and the sensor trusted again (recovery from divergence)",
    )


SharingName = Literal[
    "fixed",
    "trace",
    "vector",
    "vector_eigen",
    "vector_conservative",
    "eigen_trace",
    "eigen_trace_inverse",
    "diagonal",
    "edop",
    "norm_weighted",
]
FaultHandlingName = Literal["none", "per_observation", "per_source", "subsystem", "chi2_reconfig"]


class SubsystemConfig(Model):
    """A local filter of a federated pipeline: the sensor kinds it uses."""

    name: str = Field(pattern=r"^[A-Za-z0-9_\-/]+$")
    sensors: list[Annotated[str, Field(pattern=r"^[a-z][a-z0-9_]*$")]] = Field(
        min_length=1,
        description="Sensor kinds of this local (e.g. gnss_fix, star); checked at load against the "
        "measurement models a federated pipeline implements",
    )


def _default_subsystems() -> list[SubsystemConfig]:
    return [
        SubsystemConfig(name="INS/BDS", sensors=["gnss_fix"]),
        SubsystemConfig(name="INS/CNS", sensors=["star"]),
    ]


def _soft_gate(default: float | None):
    """The ``soft_gate_prob`` field of the families on the federated core (the same meaning in each)."""
    return Field(
        default,
        gt=0,
        lt=0.5,
        description="The soft edge of the fault tests (docs/DESIGN-NOTES.md): an update whose NIS lies "
        "between the chi-square quantile at this probability and the test's own threshold is taken as the "
        "mixture of taking and refusing it; None: the papers' hard gates (the default of the federated "
        "and centralised families: on their clean GNSS runs it cost ~1 % of RMS; 0.01 in the "
        "underwater one)",
    )


class FederatedConfig(Model):
    """Federated filter (seed 000/002/004): local filters on the common 15 INS error states."""

    kind: Literal["federated"] = "federated"
    name: str = Field(pattern=r"^[A-Za-z0-9_\-]+$")
    subsystems: list[SubsystemConfig] = Field(default_factory=_default_subsystems, min_length=1)
    sharing: SharingName = Field("vector_eigen", description="Information-sharing strategy")
    fault_handling: FaultHandlingName = Field(
        "per_source",
        description="Fault handling plug-in (service/estimation/federated/fault_tests.py): per_source drops "
        "a failing row and the rows of its source (a fix's position solution, its velocity) beyond 2 sigma; "
        "per_observation (seed 000's eq 5-10) drops only the failing rows",
    )
    reset: Literal["fusion_reset", "no_reset"] = Field("fusion_reset", description="Master reset mode")
    false_alarm_prob: float = Field(0.001, gt=0, lt=0.5, description="Per-test false-alarm probability")
    floor_share: float = Field(
        0.05,
        gt=0,
        lt=0.5,
        description="Share floor of a state seen only by a flagged row (docs/seed000.md: not below ~0.01)",
    )
    master_share: float = Field(0.0, ge=0, lt=1, description="Share kept by the master (0: none)")
    soft_gate_prob: float | None = _soft_gate(None)
    sensor_options: SensorOptions
    gnss_lever_arm_b_m: GnssLeverArm = (0.0, 0.0, 0.0)
    gnss_correlated_error: GnssCorrelatedErrorOption = None


class CentralizedConfig(Model):
    """Centralised Kalman filter on all measurements (comparator)."""

    kind: Literal["centralized"] = "centralized"
    name: str = Field(pattern=r"^[A-Za-z0-9_\-]+$")
    fault_handling: FaultHandlingName = "none"
    false_alarm_prob: float = Field(0.001, gt=0, lt=0.5)
    soft_gate_prob: float | None = _soft_gate(None)
    sensors: list[SensorKindName] | None = Field(
        None,
        description="Sensor kinds fused (default: every registered kind whose model needs no states of "
        "its own: gnss_fix, star, usbl)",
    )
    sensor_options: SensorOptions
    gnss_lever_arm_b_m: GnssLeverArm = (0.0, 0.0, 0.0)
    gnss_correlated_error: GnssCorrelatedErrorOption = None


#: The drift PSD a receiver clock model took by default before 2026-11-27 (m^2/s^3): 3.5x below a
#: TCXO's, which left the range-rate innovations of a TCXO receiver about twice their claimed
#: variance (docs/hardening.md, "Innovation consistency"). The seed 003 reproduction keeps it
#: (simulators/scenarios/seed003_*.toml, benchmarks/seed003_*.py), so that its documented figures
#: stand; docs/seed003.md says so.
SEED003_DRIFT_PSD_M2PS3 = 0.01
#: The default drift PSD: a TCXO's, 2 pi^2 h_-2 c^2 with h_-2 = 2e-20 (Brown & Hwang's TCXO; the
#: simulators' receiver clock). A better oscillator makes it conservative, a worse one needs more.
TCXO_DRIFT_PSD_M2PS3 = 0.0355


class ClockModel(Model):
    """Receiver clock (seed 001): d(b)/dt = d + w_b, d(d)/dt = -beta d + w_d (b in m, d in m/s).

    Defaults: the drift PSD of a TCXO (:data:`TCXO_DRIFT_PSD_M2PS3`); the bias PSD about ten times
    a TCXO's white frequency noise (h_0 = 2e-19: 0.009 m^2/s), a margin for receivers' clock steps."""

    bias_psd_m2ps: float = Field(0.1, gt=0, description="White-noise PSD driving the bias, m^2/s")
    drift_psd_m2ps3: float = Field(
        TCXO_DRIFT_PSD_M2PS3, gt=0, description="White-noise PSD driving the drift, m^2/s^3 (a TCXO's)"
    )
    correlation_time_s: float = Field(600.0, gt=0, description="Drift correlation time 1/beta, s")
    init_bias_std_m: float = Field(1.0e5, gt=0)
    init_drift_std_mps: float = Field(100.0, gt=0)


class TightlyCoupledConfig(Model):
    """Tightly coupled INS/GNSS (17 states: 15 INS + clock bias/drift) with optional MHSS integrity."""

    kind: Literal["tightly_coupled"] = "tightly_coupled"
    name: str = Field(pattern=r"^[A-Za-z0-9_\-]+$")
    clock: ClockModel = ClockModel()
    use_range_rate: bool = True
    integrity: bool = Field(True, description="Run MHSS (main + sub-filters) with protection levels")
    sub_sub_filters: bool = Field(True, description="Sub-sub filters for exclusion")
    phase: Literal["en_route", "terminal", "npa", "lpv", "lpv200"] = "npa"
    p_fa: float = Field(1e-4, gt=0, lt=0.5, description="Total false-alarm probability per epoch")
    p_md: float = Field(1e-3, gt=0, lt=0.5, description="Missed-detection probability")
    horizontal_threshold: Literal["gaussian", "chi2"] = Field(
        "gaussian",
        description="Horizontal separation multiplier: 'gaussian' K = Q^-1(P_FA/2N) (seed 001 eq 29);"
        " 'chi2' K = sqrt(-2 ln(P_FA/N)), which bounds each 2-D test's false alarms by its share",
    )
    exclusion: bool = True
    readmit_after_s: float = Field(
        60.0, gt=0, description="Healthy time before an excluded satellite returns"
    )
    elevation_mask_deg: float = Field(5.0, ge=0, lt=90)
    # Real receivers (docs/real_rinex.md); all off by default (the simulator's scenarios add none).
    troposphere: bool = Field(False, description="Saastamoinen zenith delay x DO-229 mapping")
    ionosphere: bool = Field(False, description="Broadcast Klobuchar of GnssRaw.iono (GPS; BeiDou)")
    elevation_weighting: bool = Field(False, description="Pseudorange/range-rate variance / sin^2(el)")
    isb_constellations: tuple[Literal["BDS", "GAL", "GLO", "QZS"], ...] = Field(
        (), description="One inter-system bias state (m, random walk) per listed constellation"
    )
    isb_psd_m2ps: float = Field(1e-4, gt=0, description="ISB random-walk PSD, m^2/s")
    init_isb_std_m: float = Field(1000.0, gt=0, description="ISB prior 1-sigma, m")


Vec3 = tuple[float, float, float]


class AlignmentNodeConfig(Model):
    """A slave IMU node of transfer alignment (seed 002): its IMU id and the filter's model of it."""

    id: str = Field(pattern=r"^[A-Za-z0-9_\-.]+$", description="IMU sensor id of the node (key id)")
    lever_arm_m: Vec3 = Field(description="Nominal lever arm from the master, master axes (RFU), m")
    flexure_arcmin: tuple[
        Annotated[float, Field(gt=0)], Annotated[float, Field(gt=0)], Annotated[float, Field(gt=0)]
    ] = Field(description="Flexure angle rms per axis the filter assumes, arcmin")
    flexure_beta_rps: tuple[
        Annotated[float, Field(gt=0)], Annotated[float, Field(gt=0)], Annotated[float, Field(gt=0)]
    ] = Field(description="Flexure second-order Gauss-Markov beta per axis, rad/s")


def _paper_nodes() -> list[AlignmentNodeConfig]:
    """The three slaves of Zhu, Ma, Wang, Chen 2022 (Table 1 lever arms; our flexure model)."""
    arms = ((0.85, 0.15, 0.25), (2.0, 0.15, 0.28), (2.65, 0.15, 0.31))
    flex = ((1.0, 2.0, 0.5), (2.0, 4.0, 1.0), (3.0, 6.0, 1.5))
    return [
        AlignmentNodeConfig(
            id=f"wing{i + 1}", lever_arm_m=a, flexure_arcmin=f, flexure_beta_rps=(1.0, 0.8, 1.2)
        )
        for i, (a, f) in enumerate(zip(arms, flex, strict=True))
    ]


class TransferAlignmentConfig(Model):
    """Transfer alignment of wing IMUs to the master (seed 002): a 27-state local filter per slave
    node on one bank, plain KF or adaptive (Sage-Husa R + chi2 fading on P), optional fusion."""

    kind: Literal["transfer_alignment"] = "transfer_alignment"
    name: str = Field(pattern=r"^[A-Za-z0-9_\-]+$")
    nodes: list[AlignmentNodeConfig] = Field(default_factory=_paper_nodes, min_length=1)
    filter: Literal["kf", "akf"] = Field("akf", description="kf: plain Kalman; akf: adaptive R and P")
    fusion: Literal["none", "paper"] = Field(
        "none", description="none: locals only; paper: eq 18-21 on all 27 states (docs/seed002.md)"
    )
    filter_period_s: float = Field(0.1, gt=0, le=1.0, description="Filter (measurement) period, s")
    forgetting_factor: float = Field(0.97, ge=0.95, le=0.99, description="Sage-Husa forgetting factor")
    restart: bool = Field(True, description="Sage-Husa restart rule (the paper's)")
    fading: bool = Field(
        False,
        description="akf: chi2-triggered fading factors on P (eq 8-17). Off by default: on seed002_wing "
        "(10 runs) fading costs heading (-21.8 % vs +11.4 % with R adaptation only), docs/seed002.md",
    )
    adaptive_order: Literal["r_then_p", "p_then_r"] = Field(
        "r_then_p", description="akf: Sage-Husa R before the chi2 fading test (section 1.2 order) or after"
    )
    p_fa: float = Field(0.01, gt=0, lt=0.5, description="Fading chi2 test false-alarm probability")
    fading_form: Literal["scaled", "added"] = Field(
        "added",
        description="akf: P = J + T J T' + Q, T = sqrt(S^2 - I) (consistent) or S J S' + Q (eq 8 literal)",
    )
    r_floor: float = Field(
        1.0, gt=0, le=1, description="Adapted R_ii never below this fraction of the nominal (docs/seed002.md)"
    )
    gyro_bias_dph: float = Field(0.05, gt=0, description="Slave gyro bias 1-sigma, deg/h")
    arw_dpsh: float = Field(0.025, gt=0, description="Slave angle random walk, deg/sqrt(h)")
    accel_bias_ug: float = Field(150.0, gt=0, description="Slave accel bias 1-sigma, ug")
    vrw_ugpsHz: float = Field(50.0, gt=0, description="Slave velocity random walk, ug/sqrt(Hz)")
    install_arcmin: float = Field(0.5, gt=0, description="Installation angle prior 1-sigma, arcmin")
    coupling_arcmin: float = Field(10.0, gt=0, description="Coupling angle prior 1-sigma, arcmin")
    lever_arm_error_m: Vec3 = Field((0.2, 0.1, 0.1), description="Lever-arm error prior 1-sigma, m")
    initial_attitude_arcmin: float = Field(30.0, gt=0, description="Misalignment prior 1-sigma, arcmin")
    initial_velocity_mps: float = Field(0.1, gt=0, description="Velocity-difference prior 1-sigma, m/s")
    kappa: float = Field(0.5, ge=0, description="Flexure lever-arm displacement factor")
    r_att_arcmin: float = Field(0.3, gt=0, description="Nominal attitude-difference noise, arcmin")
    r_vel_mps: float = Field(2.0e-4, gt=0, description="Nominal velocity-difference noise, m/s")
    r_rate_dps: float = Field(0.19, gt=0, description="Nominal angular-rate-difference noise, deg/s")
    r_vel_vibration: bool = Field(
        False,
        description="Velocity rows' R adds the node's vibration velocity diag(M r_rate M') (docs/seed002.md)",
    )


class TransponderConfig(Model):
    """Surveyed position of a USBL transponder (seed 004)."""

    lat_deg: float = Field(ge=-90, le=90)
    lon_deg: float = Field(ge=-180, le=180)
    height_m: float = Field(ge=-12000, le=1000, description="Ellipsoidal height (negative under water), m")


class UsblModelConfig(Model):
    """USBL measurement model (seed 004): noise from slant range and angle, lever arm."""

    base_std_m: float = Field(5.0, gt=0, description="Noise floor on every axis, m")
    range_fraction: float = Field(0.005, ge=0, lt=1, description="Along-line-of-sight noise / slant range")
    angle_std_deg: float = Field(0.1, ge=0, lt=10, description="Bearing noise across the line of sight, deg")
    lever_arm_b_m: tuple[float, float, float] = Field((0.0, 0.0, 0.0), description="Array in body axes, m")


class DvlModelConfig(Model):
    """DVL measurement model (seed 004): priors of its private offset and scale states, lever arm."""

    offset_std_mps: float = Field(0.4, gt=0, description="Prior 1-sigma of the velocity offset, m/s")
    scale_std: float = Field(
        1e-3, gt=0, description="Prior 1-sigma of the scale-factor error (0.001 = 0.1 %)"
    )
    offset_rw_mps_per_sqrt_s: float = Field(1e-5, ge=0, description="Offset random walk, m/s/sqrt(s)")
    scale_rw_per_sqrt_s: float = Field(1e-7, ge=0, description="Scale-factor random walk, 1/sqrt(s)")
    lever_arm_b_m: tuple[float, float, float] = Field((0.0, 0.0, 0.0), description="DVL in body axes, m")


class UnderwaterConfig(Model):
    """Seed 004 INS/USBL/DVL: federated (INS/USBL + INS/DVL locals) or its centralised comparator."""

    kind: Literal["underwater"] = "underwater"
    name: str = Field(pattern=r"^[A-Za-z0-9_\-]+$")
    architecture: Literal["federated", "centralized"] = Field(
        "federated", description="Two locals and a master, or one filter on every row (comparator)"
    )
    sharing: SharingName = Field("edop", description="Information sharing of the federated filter")
    reset: Literal["fusion_reset", "no_reset"] = Field("fusion_reset", description="Master reset mode")
    master_share: float = Field(0.0, ge=0, lt=1, description="Share kept by the master (0: none)")
    usbl_fault_handling: FaultHandlingName = Field(
        "chi2_reconfig", description="Test of the USBL rows (chi2_reconfig: exclude, rejoin on a pass)"
    )
    dvl_fault_handling: FaultHandlingName = Field("none", description="Test of the DVL rows")
    false_alarm_prob: float = Field(0.001, gt=0, lt=0.5, description="Per-test false-alarm probability")
    soft_gate_prob: float | None = _soft_gate(0.01)
    transponder: TransponderConfig | None = Field(
        None, description="Surveyed transponder position (None: the one each UsblFix carries)"
    )
    usbl: UsblModelConfig = UsblModelConfig()
    dvl: DvlModelConfig = DvlModelConfig()


#: He, Nie, Wu 2011, section 5: the model set, the Markov transition matrix and initial probabilities
IMM_PAPER_MODELS = ("normal", "largest", "two_largest", "above_c")
IMM_PAPER_TRANSITION = (
    (0.95, 0.02, 0.02, 0.01),
    (0.045, 0.9, 0.045, 0.01),
    (0.045, 0.045, 0.9, 0.01),
    (0.05, 0.025, 0.025, 0.9),
)
IMM_PAPER_MU0 = (9 / 16, 3 / 16, 3 / 16, 1 / 16)


class ImmTightlyCoupledConfig(Model):
    """Tightly coupled INS/GNSS (17 states) as an IMM bank of outlier models (He, Nie, Wu 2011).

    ``models = ["normal"]`` is the plain tightly coupled KF; with ``gate_p_fa`` a chi-square
    innovation gate rejects rows before the update (the comparator of docs/seed003.md)."""

    kind: Literal["imm_tightly_coupled"] = "imm_tightly_coupled"
    name: str = Field(pattern=r"^[A-Za-z0-9_\-]+$")
    clock: ClockModel = ClockModel()
    use_range_rate: bool = True
    elevation_mask_deg: float = Field(5.0, ge=0, lt=90)
    models: list[Literal["normal", "largest", "two_largest", "above_c"]] = Field(
        default_factory=lambda: list(IMM_PAPER_MODELS),
        min_length=1,
        description="Model set (service/estimation/imm/models.py); the paper's four by default",
    )
    transition: list[list[Annotated[float, Field(ge=0, le=1)]]] | None = Field(
        None,
        description="Markov matrix Pi[i][j] = P(j | i), rows sum to 1 (None: the paper's for its four "
        "models, [[1]] for one model)",
    )
    initial_probabilities: list[Annotated[float, Field(gt=0, le=1)]] | None = Field(
        None,
        description="mu0, sums to 1 (None: the paper's [9, 3, 3, 1]/16 for its four models, else uniform)",
    )
    likelihood: Literal["paper", "gaussian"] = Field(
        "gaussian",
        description="'gaussian' (default): N(r; 0, S) in log space; 'paper': Lambda = 1/(V' P^-1 V) (eq 11, "
        "the paper's IMM with selection_correction = false: overconfident, docs/seed003.md)",
    )
    h_percent: float = Field(
        100.0, gt=0, le=100, description="p of eq (14): H-row scale of suspected rows, %"
    )
    c: float = Field(1.5, gt=0, description="c of eq (16): standardised-residual threshold")
    big: float = Field(100.0, ge=1, description="C of eq (16): R multiplier of a row with |v| > c")
    gate_p_fa: float | None = Field(
        None, gt=0, lt=0.5, description="Chi-square innovation gate with row rejection (None: off)"
    )
    selection_correction: bool = Field(
        True,
        description="Divide a fault model's likelihood by C(m, k), the number of k-row sets it chose its "
        "suspected rows from (not in the paper; on by default: the recommended IMM; docs/seed003.md)",
    )
    output: Literal["combined", "map"] = Field(
        "combined",
        description="'combined': eq (12)-(13) fed back and published; 'map': the most probable model's",
    )
    residuals: Literal["auto", "marginal", "conditional"] = Field(
        "auto",
        description="Statistic the fault models choose and weigh their rows by: 'marginal' v_i = r_i / "
        "sqrt(S_ii) (the paper's reading), 'conditional' w_i = (S^-1 r)_i / sqrt((S^-1)_ii), the row's "
        "innovation given the other rows (Baarda's w-test: a common clock or position uncertainty no "
        "longer hides an outlier; not in the paper; docs/seed003.md); 'auto': conditional with the "
        "selection correction (the recommended IMM), else marginal (the paper's IMM)",
    )
    learn_transition_s: float | Literal["auto"] | None = Field(
        "auto",
        description="Learn the Markov matrix online (EM with forgetting of this time constant, s; the "
        "resolved transition as prior; not in the paper; docs/seed003.md). None: the fixed matrix; 'auto': "
        "60 s with the selection correction (the recommended IMM), else fixed (the paper's IMM)",
    )

    @model_validator(mode="after")
    def _markov(self):
        M = len(self.models)
        if len(set(self.models)) != M:
            raise ValueError(f"models has duplicates: {self.models}")
        Pi = self.resolved_transition()
        if Pi is None:
            raise ValueError("transition: required for a model set other than the paper's four")
        if len(Pi) != M or any(len(row) != M for row in Pi):
            raise ValueError(f"transition: must be {M}x{M} (one row and column per model)")
        for i, row in enumerate(Pi):
            if abs(sum(row) - 1.0) > 1e-9:
                raise ValueError(f"transition row {i} sums to {sum(row)}, not 1")
        mu0 = self.resolved_mu0()
        if len(mu0) != M or abs(sum(mu0) - 1.0) > 1e-9:
            raise ValueError(f"initial_probabilities: need {M} values summing to 1")
        tau = self.learn_transition_s
        if tau is not None and tau != "auto" and not 0 < tau < float("inf"):
            raise ValueError(f"learn_transition_s: {tau} (a time constant > 0 s, 'auto' or None)")
        return self

    def resolved_transition(self) -> list[list[float]] | None:
        if self.transition is not None:
            return [list(r) for r in self.transition]
        if tuple(self.models) == IMM_PAPER_MODELS:
            return [list(r) for r in IMM_PAPER_TRANSITION]
        if len(self.models) == 1:
            return [[1.0]]
        return None

    def resolved_learn_transition_s(self) -> float | None:
        if self.learn_transition_s == "auto":
            return 60.0 if self.selection_correction else None
        return self.learn_transition_s

    def resolved_residuals(self) -> str:
        if self.residuals == "auto":
            return "conditional" if self.selection_correction else "marginal"
        return self.residuals

    def resolved_mu0(self) -> list[float]:
        if self.initial_probabilities is not None:
            return list(self.initial_probabilities)
        if tuple(self.models) == IMM_PAPER_MODELS:
            return list(IMM_PAPER_MU0)
        return [1.0 / len(self.models)] * len(self.models)


PipelineConfig = Annotated[
    LooselyCoupledConfig
    | FederatedConfig
    | CentralizedConfig
    | TightlyCoupledConfig
    | TransferAlignmentConfig
    | UnderwaterConfig
    | ImmTightlyCoupledConfig,
    Field(discriminator="kind"),
]


class ZenohConfig(Model):
    mode: Literal["peer", "client", "router"] = "peer"
    listen: list[str] = Field(default_factory=lambda: ["tcp/127.0.0.1:7447"])
    connect: list[str] = Field(default_factory=list)
    multicast_scouting: bool = False
    config_file: Path | None = Field(
        None,
        description="A Zenoh json5 config (TLS, access control...) overlaid on the safe values above: "
        "mode, endpoints and discovery keep these unless the file sets them",
    )


class IntakeConfig(Model):
    queue_size: int = Field(100_000, ge=16, description="Bounded intake queue per vehicle (events)")
    overload: Literal["block", "drop"] = Field(
        "block",
        description="Full queue (workers >= 1): block (back-pressure to reliable publishers) or drop "
        "(counted); with workers = 0 there is no queue and the intake always back-pressures",
    )
    late_tolerance_s: float = Field(0.5, ge=0, description="Aiding older than INS time by more is rejected")
    max_lead_s: float = Field(5.0, gt=0, description="Aiding ahead of the INS by more is rejected")
    max_imu_gap_s: float = Field(0.5, gt=0, description="IMU gap that marks the INS as lost")
    future_window_s: float = Field(
        2.0,
        gt=0,
        description="An IMU sample or InitialNav further ahead of the running (IMU) time than this is "
        "rejected as 'future', not adopted (a gap up to it marks the INS lost and re-initialises)",
    )
    time_jump_samples: int = Field(
        20,
        ge=2,
        description="Consecutive IMU samples outside the running time (ahead of the window or behind it) "
        "that agree with each other and confirm a time jump (sensor restart, clock step): the INS is "
        "re-initialised on the new time base",
    )
    subscribe: Literal["auto", "all", "served", "owned"] = Field(
        "auto",
        description="'all': subscribe to every vehicle's inputs, so data under a name this service does "
        "not serve is counted and named (a typo shows); 'served': only the listed vehicles' keys (several "
        "services sharing a fleet on one bus: none receives or counts the others' vehicles); 'owned' (a "
        "fleet member, [fleet] sharding = 'rendezvous'): one subscription per vehicle it serves, and "
        "every vehicle's low-rate inputs (InitialNav, fixes, other aiding; not the IMU) to find its own "
        "new vehicles, so each vehicle's IMU stream reaches its owner only; 'auto' (default): 'owned' "
        "for a fleet member that is one process, 'all' otherwise",
    )
    vehicle_idle_s: float = Field(
        600.0,
        ge=0,
        description="With vehicles = ['*']: a vehicle that sent nothing for this long (wall-clock seconds) "
        "is released: its last Health published, its worker, state and slot of max_vehicles freed, "
        "counted in ServiceHealth.vehicles_released_idle; data under its name later starts it anew. "
        "0: never (a fleet whose names come and go would otherwise fill max_vehicles for good)",
    )
    workers: int = Field(
        0,
        ge=0,
        le=64,
        description="0 (default): the intake thread runs each message itself, no hand-over between "
        "threads (the fastest: with the GIL, threads add no parallelism, only hand-overs; "
        "docs/SCALING.md); N: N worker threads, each owning many vehicles (a vehicle lives on one "
        "worker, so its events keep their order), so that one vehicle's long epoch (an MHSS bank) "
        "does not hold the others; more processes: fednav-service --shards",
    )
    max_vehicles: int = Field(
        1000,
        ge=1,
        description="With vehicles = ['*']: at most this many vehicles get a worker; data for more is "
        "refused and counted ('vehicle_limit')",
    )
    sensor_ids: dict[str, list[str]] = Field(
        default_factory=dict,
        description="Sensor ids accepted per kind (e.g. {star = ['st1', 'st2']}); a kind not listed takes "
        "the first id it sees and refuses others as 'unexpected_sensor' (a second sensor of a kind is "
        "fused only when configured)",
    )


class InitConfig(Model):
    mode: Literal["auto", "message", "static", "gnss_motion"] = Field(
        "auto", description="auto: InitialNav if received, else static coarse alignment or GNSS in motion"
    )
    align_time_s: float = Field(60.0, gt=0, description="Static coarse-alignment averaging time")
    min_speed_mps: float = Field(5.0, gt=0, description="GNSS speed needed for in-motion initialisation")


#: Recording streams that can be decimated (``ServiceConfig.rrd_decimation``) and their default
#: shortest interval in seconds of sensor time: ``navigation`` (solution and truth states, map and
#: ENU points, raw fixes: every solution by default, it is the product), ``std`` (solution 1-sigma
#: and biases), ``errors`` (errors against truth and 3-sigma bounds), ``faults`` (test statistics,
#: thresholds, flags), ``sharing`` (sharing coefficients), ``integrity_sat`` (per-satellite
#: statistics), ``ellipses`` (covariance ellipses of the ENU trajectory view). A long evaluation
#: recording (seed000_faults) raises ``navigation`` and ``errors`` in its ``[service]`` table.
RRD_DECIMATION_DEFAULTS: dict[str, float] = {
    "navigation": 0.0,
    "std": 1.0,
    "errors": 0.0,
    "faults": 2.0,
    "sharing": 5.0,
    "integrity_sat": 2.0,
    "ellipses": 10.0,
}


class OutputConfig(Model):
    solution_rate_hz: float = Field(10.0, gt=0, le=1000)
    health_period_s: float = Field(1.0, gt=0)


class FleetConfig(Model):
    """Several services sharing one fleet (docs/SCALING.md)."""

    sharding: Literal["static", "rendezvous"] = Field(
        "static",
        description="static: this service serves its 'vehicles' list (or every vehicle with '*'); "
        "rendezvous: with vehicles = ['*'], the live services of the same group split the fleet by "
        "rendezvous hashing of the vehicle name over their liveliness tokens (no coordinator); a vehicle "
        "whose service vanishes moves to another, which starts it from the last handover state",
    )
    group: str | None = Field(
        None,
        pattern=r"^[A-Za-z0-9_\-.]{1,64}$",
        description="Services of one group share vehicles (default: derived from the prefix and the "
        "pipelines' configuration, so services configured differently never split a fleet between them)",
    )
    handover_period_s: float = Field(
        1.0, gt=0, le=60, description="Each served vehicle's state is published this often for a handover"
    )
    handover_max_age_s: float = Field(
        5.0,
        gt=0,
        le=600,
        description="A handover state older than this (sensor time) at the new service's first IMU sample "
        "is not used: the vehicle starts from its own alignment",
    )


#: the settings of a service configuration that change what a vehicle's solutions are (the rest:
#: transport, recording, capacity, scheduling): services that share a fleet must agree on these
NAVIGATION_INTAKE = (
    "late_tolerance_s",
    "max_lead_s",
    "max_imu_gap_s",
    "future_window_s",
    "time_jump_samples",
    "sensor_ids",
)


def navigation_settings(cfg: dict) -> dict:
    """What of a service configuration (as ``model_dump(mode="json")``, or the ``service/config``
    queryable's JSON) changes a vehicle's navigation: prefix, pipelines, IMU model,
    initialisation, solution rate, major interval and the intake's acceptance rules. Until
    2026-12-01 the fleet group digested only the prefix and the pipelines: a service with another
    IMU grade and 1 Hz solutions split a fleet with the others, and fednav-fleet status called
    its configuration "same"."""
    intake = cfg.get("intake") or {}
    return {
        "prefix": cfg.get("prefix"),
        "pipelines": cfg.get("pipelines"),
        "imu": cfg.get("imu"),
        "init": cfg.get("init"),
        "solution_rate_hz": (cfg.get("output") or {}).get("solution_rate_hz"),
        "major_interval_s": cfg.get("major_interval_s"),
        "intake": {k: intake.get(k) for k in NAVIGATION_INTAKE},
    }


class ServiceConfig(Model):
    prefix: str = "fednav"
    vehicles: list[str] = Field(default_factory=lambda: ["v1"], description="Vehicles served ('*' = all)")
    zenoh: ZenohConfig = ZenohConfig()
    intake: IntakeConfig = IntakeConfig()
    init: InitConfig = InitConfig()
    output: OutputConfig = OutputConfig()
    imu: ImuModel = ImuModel()
    major_interval_s: float = Field(0.1, gt=0, le=1.0, description="INS major-update interval")
    pipelines: list[PipelineConfig] = Field(
        default_factory=lambda: [LooselyCoupledConfig(name="lc")], min_length=1
    )
    rrd: Path | None = Field(None, description="Recording path (.rrd); None: recordings/<time>.rrd")
    rrd_flush_interval_s: float = Field(
        1.0,
        gt=0,
        le=60,
        description="Recording rows are sent to the file this often: about what a crash (kill -9) loses. "
        "Each send is one chunk per entity: shorter means a bigger file and more memory for its footer",
    )
    rrd_decimation: dict[str, float] = Field(
        default_factory=lambda: dict(RRD_DECIMATION_DEFAULTS),
        description="Recording: shortest sensor-time interval (s) between two recorded rows of each "
        "diagnostic stream (0 = every row). Streams: " + ", ".join(RRD_DECIMATION_DEFAULTS) + ". Fault "
        "tests keep every row while something is flagged; state changes are always recorded",
    )
    rrd_slow_flush_interval_s: float = Field(
        10.0,
        gt=0,
        le=300,
        description="Diagnostic recording streams (fault tests, sharing, 1-sigma, health, per-satellite "
        "tests) are sent this often (at least rrd_flush_interval_s): fewer chunks, a smaller file; "
        "a crash loses up to this much of them",
    )
    rrd_vehicle_interval_s: float = Field(
        0.0,
        ge=0,
        le=3600,
        description="Recording a fleet: each vehicle's solutions, raw fixes and health are recorded at "
        "most once per this many seconds of sensor time (0: every one). A pipeline's status change is "
        "always recorded; Zenoh outputs are never decimated. A fleet: 1.0 with rrd_flush_interval_s = 5 "
        "(what it costs per vehicle: docs/SCALING.md)",
    )
    rrd_optimize: bool = Field(
        False, description="Compact the recording when the service stops (rerun rrd optimize, ~10x smaller)"
    )
    viewer: str | None = Field(None, description="Also stream live to a Rerun viewer at this URL")
    ros2: Ros2Config | None = Field(None, description="ROS 2 bridge over Zenoh (docs/ros2.md); None: off")
    fleet: FleetConfig = FleetConfig()

    @model_validator(mode="after")
    def _fleet_vehicles(self):
        if self.fleet.sharding == "rendezvous" and "*" not in self.vehicles:
            raise ValueError(
                "fleet.sharding = 'rendezvous' shares vehicles = ['*'] (a list is static sharding)"
            )
        if self.intake.subscribe == "owned" and self.fleet.sharding != "rendezvous":
            raise ValueError(
                "intake.subscribe = 'owned' is for a fleet member (fleet.sharding = 'rendezvous'): "
                "a service that is not one knows no owner of a vehicle; use 'all' or 'served'"
            )
        return self

    def fleet_group(self) -> str:
        """The fleet group (``fleet.group``, else a digest of :func:`navigation_settings`: services
        that would navigate a vehicle differently never split a fleet)."""
        if self.fleet.group:
            return self.fleet.group
        import hashlib
        import json

        text = json.dumps(navigation_settings(self.model_dump(mode="json")), sort_keys=True)
        return "g" + hashlib.blake2b(text.encode(), digest_size=6).hexdigest()

    @model_validator(mode="after")
    def _ros2_vehicle(self):
        if self.ros2 is not None and "*" not in self.vehicles and self.ros2.vehicle not in self.vehicles:
            raise ValueError(f"ros2.vehicle {self.ros2.vehicle!r} is not a served vehicle {self.vehicles}")
        names = {p.name for p in self.pipelines}
        out = self.ros2.outputs if self.ros2 is not None else None
        for name in out.pipelines if out is not None else []:
            if name not in names:
                raise ValueError(
                    f"ros2.outputs.pipelines: {name!r} is not a configured pipeline {sorted(names)}"
                )
        if (
            out is not None
            and out.tf_pipeline is not None
            and out.tf_pipeline not in (out.pipelines or names)
        ):
            raise ValueError(f"ros2.outputs.tf_pipeline: {out.tf_pipeline!r} is not a republished pipeline")
        return self

    @field_validator("rrd_decimation")
    @classmethod
    def _known_streams(cls, v: dict[str, float]) -> dict[str, float]:
        bad = sorted(set(v) - set(RRD_DECIMATION_DEFAULTS))
        if bad:
            raise ValueError(f"unknown recording streams {bad}; known: {sorted(RRD_DECIMATION_DEFAULTS)}")
        if any(not (x >= 0.0 and x < 3600.0) for x in v.values()):
            raise ValueError("decimation intervals must be in [0, 3600) s")
        return {**RRD_DECIMATION_DEFAULTS, **v}


class ConfigError(ValueError):
    pass


def _format(err: ValidationError, source: str) -> str:
    from fednav.service.validation_errors import format_errors

    return format_errors(err, ServiceConfig, f"invalid configuration in {source}:")


def from_dict(data: dict, source: str = "<dict>") -> ServiceConfig:
    """Validate a configuration whole: the schema, then what is implemented (every pipeline is
    built once, so an option no code runs is refused here, naming the field, not at the first
    message)."""
    try:
        cfg = ServiceConfig.model_validate(data)
    except ValidationError as err:
        raise ConfigError(_format(err, source)) from None
    from fednav.service.pipelines import config_errors  # the pipelines import this module

    errors = config_errors(cfg)
    if errors:
        lines = [f"invalid configuration in {source}:"] + [f"  {loc}: {msg}" for loc, msg in errors]
        raise ConfigError("\n".join(lines))
    return cfg


def load(path: Path | str, table: str | None = None) -> ServiceConfig:
    """Load a TOML config; ``table`` selects a sub-table (e.g. a scenario's ``[service]``)."""
    path = Path(path)
    try:
        data = tomllib.loads(path.read_text())
    except (OSError, tomllib.TOMLDecodeError) as exc:
        raise ConfigError(f"cannot read {path}: {exc}") from None
    source = str(path)
    if table:
        if not isinstance(data.get(table), dict):
            raise ConfigError(f"{path} has no [{table}] table")
        data, source = data[table], f"{path} [{table}]"
    return from_dict(data, source)


def recording_kinds(pipelines: Sequence[PipelineConfig]) -> dict[str, str]:
    """Pipeline name -> the kind its dashboards are built for: its ``kind``, or ``"plain"`` for a
    pipeline that publishes neither fault tests nor integrity (a centralised comparator with
    ``fault_handling = "none"``, a tightly coupled filter with ``integrity = false``), so the
    recording's blueprint has no empty Faults or Integrity panels for it. An underwater pipeline
    carries its dashboard features after a colon: ``underwater:centralized`` (no sharing
    coefficients), ``underwater:untested`` (no USBL/DVL test: no reconfiguration log), or both; a
    transfer-alignment pipeline its node ids (``transfer_alignment:wing1,wing2,wing3``)."""

    def plain(p) -> bool:
        if p.kind == "centralized":
            return getattr(p, "fault_handling", "none") == "none"
        return p.kind == "tightly_coupled" and not getattr(p, "integrity", True)

    def kind(p) -> str:
        if plain(p):
            return "plain"
        if p.kind == "underwater":  # dashboard features after the colon (dashboards.blueprints)
            features = []
            if p.architecture == "centralized":
                features.append("centralized")  # one filter: no sharing coefficients
            if p.usbl_fault_handling == "none" and p.dvl_fault_handling == "none":
                features.append("untested")  # nothing is ever excluded: no reconfiguration log
            return "underwater:" + ",".join(features) if features else "underwater"
        if p.kind == "transfer_alignment":  # one dashboard tab per wing node
            return "transfer_alignment:" + ",".join(n.id for n in p.nodes)
        return p.kind

    return {p.name: kind(p) for p in pipelines}
