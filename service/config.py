"""Service configuration: typed, documented, validated whole at load (errors name the field).

A TOML file (``fednav-service --config service.toml``) or a ``[service]`` table of a scenario
(used by ``fednav-sim eval``). Unknown keys are errors; nothing is silently "fixed".
"""

from __future__ import annotations

import tomllib
from pathlib import Path
from typing import Annotated, Literal

from pydantic import BaseModel, ConfigDict, Field, ValidationError, model_validator

from service import earth
from service.ins.error_model import ImuNoise


class Model(BaseModel):
    model_config = ConfigDict(extra="forbid", frozen=True)


class ImuModel(Model):
    """The IMU grade the filters assume (process model), in datasheet units."""

    gyro_bias_dph: float = Field(0.01, ge=0, description="Gyro bias 1-sigma (initial uncertainty), deg/h")
    accel_bias_ug: float = Field(50.0, ge=0, description="Accelerometer bias 1-sigma, micro-g")
    arw_dpsh: float = Field(0.001, gt=0, description="Angle random walk, deg/sqrt(h)")
    vrw_ugpsHz: float = Field(5.0, gt=0, description="Velocity random walk, micro-g/sqrt(Hz)")
    gyro_bias_rw_dphpsh: float = Field(0.0, ge=0, description="Gyro bias random walk, deg/h/sqrt(h)")
    accel_bias_rw_ugpsh: float = Field(0.0, ge=0, description="Accel bias random walk, micro-g/sqrt(h)")

    def noise(self) -> ImuNoise:
        return ImuNoise(
            arw=self.arw_dpsh * earth.DEG / 60.0,
            vrw=self.vrw_ugpsHz * earth.UG,
            gyro_bias_rw=self.gyro_bias_rw_dphpsh * earth.DPH / 60.0,
            accel_bias_rw=self.accel_bias_rw_ugpsh * earth.UG / 60.0,
        )

    def bias_sigmas(self) -> tuple[float, float]:
        return self.gyro_bias_dph * earth.DPH, self.accel_bias_ug * earth.UG


class LooselyCoupledConfig(Model):
    kind: Literal["loosely_coupled"] = "loosely_coupled"
    name: str = Field(pattern=r"^[A-Za-z0-9_\-]+$")
    use_star: bool = Field(True, description="Use star-tracker attitude when present")
    innovation_gate_sigma: float | None = Field(
        None, gt=0, description="Reject a fix whose standardised innovation exceeds this (None: no gate)"
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
FaultHandlingName = Literal["none", "per_observation", "subsystem", "chi2_reconfig"]


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


class FederatedConfig(Model):
    """Federated filter (seed 000/002/004): local filters on the common 15 INS error states."""

    kind: Literal["federated"] = "federated"
    name: str = Field(pattern=r"^[A-Za-z0-9_\-]+$")
    subsystems: list[SubsystemConfig] = Field(default_factory=_default_subsystems, min_length=1)
    sharing: SharingName = Field("vector_eigen", description="Information-sharing strategy")
    fault_handling: FaultHandlingName = Field("per_observation", description="Fault handling plug-in")
    reset: Literal["fusion_reset", "no_reset"] = Field("fusion_reset", description="Master reset mode")
    false_alarm_prob: float = Field(0.001, gt=0, lt=0.5, description="Per-test false-alarm probability")
    floor_share: float = Field(
        0.05,
        gt=0,
        lt=0.5,
        description="Share floor of a state seen only by a flagged row (docs/seed000.md: not below ~0.01)",
    )
    master_share: float = Field(0.0, ge=0, lt=1, description="Share kept by the master (0: none)")


class CentralizedConfig(Model):
    """Centralised Kalman filter on all measurements (comparator)."""

    kind: Literal["centralized"] = "centralized"
    name: str = Field(pattern=r"^[A-Za-z0-9_\-]+$")
    fault_handling: FaultHandlingName = "none"
    false_alarm_prob: float = Field(0.001, gt=0, lt=0.5)


class ClockModel(Model):
    """Receiver clock (seed 001): d(b)/dt = d + w_b, d(d)/dt = -beta d + w_d (b in m, d in m/s)."""

    bias_psd_m2ps: float = Field(0.1, gt=0, description="White-noise PSD driving the bias, m^2/s")
    drift_psd_m2ps3: float = Field(0.01, gt=0, description="White-noise PSD driving the drift, m^2/s^3")
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
        "paper", description="'paper': Lambda = 1/(V' P^-1 V) (eq 11); 'gaussian': N(r; 0, S) in log space"
    )
    h_percent: float = Field(
        100.0, gt=0, le=100, description="p of eq (14): H-row scale of suspected rows, %"
    )
    c: float = Field(1.5, gt=0, description="c of eq (16): standardised-residual threshold")
    big: float = Field(100.0, ge=1, description="C of eq (16): R multiplier of a row with |v| > c")
    gate_p_fa: float | None = Field(
        None, gt=0, lt=0.5, description="Chi-square innovation gate with row rejection (None: off)"
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
        return self

    def resolved_transition(self) -> list[list[float]] | None:
        if self.transition is not None:
            return [list(r) for r in self.transition]
        if tuple(self.models) == IMM_PAPER_MODELS:
            return [list(r) for r in IMM_PAPER_TRANSITION]
        if len(self.models) == 1:
            return [[1.0]]
        return None

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
    | ImmTightlyCoupledConfig,
    Field(discriminator="kind"),
]


class ZenohConfig(Model):
    mode: Literal["peer", "client", "router"] = "peer"
    listen: list[str] = Field(default_factory=lambda: ["tcp/127.0.0.1:7447"])
    connect: list[str] = Field(default_factory=list)
    multicast_scouting: bool = False
    config_file: Path | None = Field(None, description="A full Zenoh json5 config (overrides the above)")


class IntakeConfig(Model):
    queue_size: int = Field(100_000, ge=16, description="Bounded intake queue per vehicle (events)")
    overload: Literal["block", "drop"] = Field(
        "block", description="Full queue: block (back-pressure to reliable publishers) or drop (counted)"
    )
    late_tolerance_s: float = Field(0.5, ge=0, description="Aiding older than INS time by more is rejected")
    max_lead_s: float = Field(5.0, gt=0, description="Aiding ahead of the INS by more is rejected")
    max_imu_gap_s: float = Field(0.5, gt=0, description="IMU gap that marks the INS as lost")


class InitConfig(Model):
    mode: Literal["auto", "message", "static", "gnss_motion"] = Field(
        "auto", description="auto: InitialNav if received, else static coarse alignment or GNSS in motion"
    )
    align_time_s: float = Field(60.0, gt=0, description="Static coarse-alignment averaging time")
    min_speed_mps: float = Field(5.0, gt=0, description="GNSS speed needed for in-motion initialisation")


class OutputConfig(Model):
    solution_rate_hz: float = Field(10.0, gt=0, le=1000)
    health_period_s: float = Field(1.0, gt=0)


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
    viewer: str | None = Field(None, description="Also stream live to a Rerun viewer at this URL")


class ConfigError(ValueError):
    pass


def _format(err: ValidationError, source: str) -> str:
    lines = [f"invalid configuration in {source}:"]
    for e in err.errors():
        loc = ".".join(str(p) for p in e["loc"])
        lines.append(f"  {loc}: {e['msg']}")
    return "\n".join(lines)


def from_dict(data: dict, source: str = "<dict>") -> ServiceConfig:
    """Validate a configuration whole: the schema, then what is implemented (every pipeline is
    built once, so an option no code runs is refused here, naming the field, not at the first
    message)."""
    try:
        cfg = ServiceConfig.model_validate(data)
    except ValidationError as err:
        raise ConfigError(_format(err, source)) from None
    from service.pipelines import config_errors  # the pipelines import this module

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
