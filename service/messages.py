"""Wire contract: pydantic models of every message fednav sends or receives over Zenoh.

Every payload is JSON produced and validated by these models. Validation is strict (no type
coercion except int -> float), extra keys are errors, NaN/Inf are errors, and physically absurd
magnitudes are errors (limits below, chosen generously above any vehicle fednav targets). The
Zenoh encoding of a payload is ``application/json;fednav.<Type>/<SCHEMA_VERSION>``.

Units are in the field names (``_m``, ``_mps``, ``_rad``, ``_deg``, ``_s``); frames too
(``vel_enu_mps`` east/north/up, ``*_b_*`` body right/forward/up). Time ``t`` is sensor time in
seconds of GPS time (since 1980-01-06), float64. Attitude ``rpy_deg`` = [roll, pitch, heading]
with heading clockwise from true north in [0, 360).

Every frame and angle convention is stated once, in the README section "Conventions (one place)".

``python -m fednav.service.messages --write docs/schemas`` regenerates the JSON Schemas shipped in docs/.
"""

from __future__ import annotations

import argparse
import json
import math
from pathlib import Path
from typing import Annotated, Literal

import msgspec
from pydantic import BaseModel, ConfigDict, Field, model_validator

SCHEMA_VERSION = 1

# Plausibility limits (absurd-magnitude rejection). A value beyond these is a corrupt message.
MAX_RATE_RPS = 50.0  # ~2900 deg/s, above any tactical gyro range
MAX_SPECIFIC_FORCE_MPS2 = 50.0 * 9.81  # 50 g
MAX_SPEED_MPS = 3000.0
MAX_DT_S = 1.0
MIN_HEIGHT_M = -12000.0  # ocean trenches (underwater vehicles)
MAX_HEIGHT_M = 1.0e5
MAX_RANGE_M = 1.0e8  # pseudoranges (GEO ~ 4e7 m)
T_MAX_S = 1.0e10  # GPS seconds; ~300 years


class WireModel(BaseModel):
    """Base of all wire messages: strict, closed, immutable, finite."""

    model_config = ConfigDict(
        strict=True, extra="forbid", frozen=True, allow_inf_nan=False, use_attribute_docstrings=True
    )

    @classmethod
    def encoding(cls) -> str:
        return f"application/json;fednav.{cls.__name__}/{SCHEMA_VERSION}"

    def to_json(self) -> bytes:
        return self.model_dump_json().encode()


Time = Annotated[float, Field(ge=0.0, le=T_MAX_S, description="Sensor time, s of GPS time")]
Vec3 = tuple[float, float, float]
PosStd3 = tuple[
    Annotated[float, Field(gt=0.0, le=1e7)],
    Annotated[float, Field(gt=0.0, le=1e7)],
    Annotated[float, Field(gt=0.0, le=1e7)],
]
Lat = Annotated[float, Field(ge=-90.0, le=90.0, description="Geodetic latitude, deg")]
Lon = Annotated[float, Field(ge=-180.0, le=180.0, description="Longitude, deg")]
Height = Annotated[float, Field(ge=MIN_HEIGHT_M, le=MAX_HEIGHT_M, description="Ellipsoidal height, m")]


def _norm(v) -> float:
    if len(v) == 3:  # every IMU sample's two checks: the same sum, without a generator
        x, y, z = v
        return math.sqrt(x * x + y * y + z * z)
    return math.sqrt(sum(x * x for x in v))


def _check_speed(v, name: str) -> None:
    if _norm(v) > MAX_SPEED_MPS:
        raise ValueError(f"{name} magnitude {_norm(v):.1f} m/s exceeds {MAX_SPEED_MPS} m/s")


def _check_rpy(rpy) -> None:
    if not (-180.0 <= rpy[0] <= 180.0 and -90.0 <= rpy[1] <= 90.0 and -360.0 <= rpy[2] <= 360.0):
        raise ValueError("rpy_deg out of range: roll [-180,180], pitch [-90,90], heading [-360,360]")


# --- sensors ----------------------------------------------------------------------------------------
class ImuSample(WireModel):
    """One IMU interval ending at ``t``: angle and velocity increments in the body frame (RFU:
    x right, y forward, z up; README "Conventions (one place)")."""

    t: Time
    dt_s: float = Field(gt=0.0, le=MAX_DT_S, description="Interval length, s")
    dtheta_rad: Vec3 = Field(description="Angle increment over dt_s, body frame, rad")
    dvel_mps: Vec3 = Field(description="Velocity (specific force) increment over dt_s, body frame, m/s")

    @model_validator(mode="after")
    def _plausible(self):
        if _norm(self.dtheta_rad) > MAX_RATE_RPS * self.dt_s:
            raise ValueError("dtheta_rad implies an angular rate above the plausibility limit")
        if _norm(self.dvel_mps) > MAX_SPECIFIC_FORCE_MPS2 * self.dt_s:
            raise ValueError("dvel_mps implies a specific force above the plausibility limit")
        return self


class ImuJson(msgspec.Struct, forbid_unknown_fields=True, frozen=True):
    """A JSON ImuSample decoded on the hot path (:func:`decode_imu_json`): the same attributes,
    no pydantic object. Only what :class:`ImuSample` accepts gets here, with the same values."""

    t: Annotated[float, msgspec.Meta(ge=0.0, le=T_MAX_S)]
    dt_s: Annotated[float, msgspec.Meta(gt=0.0, le=MAX_DT_S)]
    dtheta_rad: tuple[float, float, float]
    dvel_mps: tuple[float, float, float]


_IMU_JSON = msgspec.json.Decoder(ImuJson)


def decode_imu_json(payload: bytes) -> ImuJson | None:
    """The ImuSample in a JSON payload, decoded by msgspec (0.6 us against pydantic's 3.7), or
    None when anything is wrong with it: the caller then validates it with :class:`ImuSample`,
    which stays the contract and gives the exact error and counted reason. msgspec's rules here
    are at least as strict as the model's (closed object, exact types with int -> float, no
    NaN/Inf, the same bounds; tests/test_imu_json.py), and the model's plausibility check is
    repeated (NaN or Inf anywhere fails it too)."""
    try:
        m = _IMU_JSON.decode(payload)
    except msgspec.MsgspecError:
        return None
    # _norm's arithmetic inline (two calls fewer on every JSON IMU sample)
    (a0, a1, a2), (v0, v1, v2), dt = m.dtheta_rad, m.dvel_mps, m.dt_s
    if (
        math.sqrt(a0 * a0 + a1 * a1 + a2 * a2) <= MAX_RATE_RPS * dt
        and math.sqrt(v0 * v0 + v1 * v1 + v2 * v2) <= MAX_SPECIFIC_FORCE_MPS2 * dt
    ):
        return m
    return None


#: Default 1-sigma of a fix that carries no sigmas (docs: README "GNSS fixes"): horizontal
#: per-axis position sigma by fix type at HDOP 1 (scaled by ``hdop`` when given), vertical =
#: VERTICAL_TO_HORIZONTAL x horizontal; speed and vertical-rate sigmas.
DEFAULT_H_STD_M = {"single": 2.5, "sbas": 1.5, "dgnss": 0.8, "float": 0.3, "fixed": 0.03}
VERTICAL_TO_HORIZONTAL = 1.7
DEFAULT_SPEED_STD_MPS = {"single": 0.15, "sbas": 0.1, "dgnss": 0.1, "float": 0.05, "fixed": 0.03}
DEFAULT_VERTICAL_RATE_STD_MPS = 0.3


class GnssFix(WireModel):
    """Receiver position (and optionally velocity) solution for loosely coupled aiding.

    Variants, by the fields present: position only (no velocity fields); horizontal speed and
    course (``speed_mps`` + ``course_deg``, e.g. NMEA RMC/VTG or Android; optional
    ``vertical_rate_mps``); full 3-D velocity (``vel_enu_mps``). Sigmas are optional: missing ones
    take the documented defaults from ``fix_type`` and ``hdop`` (README "GNSS fixes"). Angle
    conventions: README "Conventions (one place)"."""

    t: Time
    lat_deg: Lat
    lon_deg: Lon
    height_m: Height
    vel_enu_mps: Vec3 | None = None
    """Velocity, east/north/up, m/s (None: not reported; use speed/course or position only)"""
    pos_std_enu_m: PosStd3 | None = Field(
        None, description="1-sigma position noise, east/north/up, m (None: default from fix_type/hdop)"
    )
    vel_std_enu_mps: PosStd3 | None = Field(
        None, description="1-sigma velocity noise, east/north/up, m/s (with vel_enu_mps; None: default)"
    )
    speed_mps: float | None = Field(None, ge=0.0, le=MAX_SPEED_MPS)
    """Horizontal speed over ground, m/s (with course_deg; not with vel_enu_mps)"""
    course_deg: float | None = Field(None, ge=-360.0, le=360.0)
    """Course over ground, deg clockwise from true north (direction of the horizontal velocity)"""
    vertical_rate_mps: float | None = Field(None, ge=-MAX_SPEED_MPS, le=MAX_SPEED_MPS)
    """Vertical velocity, up positive, m/s (optional, with speed_mps/course_deg)"""
    speed_std_mps: float | None = Field(None, gt=0.0, le=1e3)
    """1-sigma of speed_mps, m/s (None: default from fix_type)"""
    course_std_deg: float | None = Field(None, gt=0.0, le=360.0)
    """1-sigma of course_deg, deg (None: speed_std_mps / speed, i.e. isotropic horizontal velocity)"""
    vertical_rate_std_mps: float | None = Field(None, gt=0.0, le=1e3)
    """1-sigma of vertical_rate_mps, m/s (None: default)"""
    fix_type: Literal["single", "sbas", "dgnss", "float", "fixed"] = "single"
    """Solution type (sets default sigmas): single point, SBAS, DGNSS, RTK float, RTK fixed"""
    hdop: float | None = Field(None, gt=0.0, le=100.0)
    """Horizontal dilution of precision (scales the default position sigmas; None: 1)"""
    constellation: Literal["GPS", "BDS", "GAL", "GLO", "MULTI"] = "GPS"
    """Constellation(s) of the solution"""
    num_sats: int = Field(default=0, ge=0, le=200)
    """Satellites used in the solution (0: not reported)"""

    @model_validator(mode="after")
    def _plausible(self):
        if self.vel_enu_mps is not None:
            _check_speed(self.vel_enu_mps, "vel_enu_mps")
            if (
                self.speed_mps is not None
                or self.course_deg is not None
                or self.vertical_rate_mps is not None
            ):
                raise ValueError("give either vel_enu_mps or speed_mps/course_deg, not both")
        elif self.vel_std_enu_mps is not None:
            raise ValueError("vel_std_enu_mps given without vel_enu_mps")
        if (self.speed_mps is None) != (self.course_deg is None):
            raise ValueError("speed_mps and course_deg come together (horizontal speed and course)")
        if self.vertical_rate_mps is not None and self.speed_mps is None:
            raise ValueError("vertical_rate_mps needs speed_mps and course_deg")
        return self

    @property
    def variant(self) -> Literal["position", "speed_course", "velocity"]:
        """Which rows the fix carries: position only, speed + course, or 3-D velocity."""
        if self.vel_enu_mps is not None:
            return "velocity"
        return "speed_course" if self.speed_mps is not None else "position"

    def pos_std(self) -> tuple[float, float, float]:
        """Position 1-sigma east/north/up, m: the message's, else the fix-type/HDOP default."""
        if self.pos_std_enu_m is not None:
            return self.pos_std_enu_m
        h = DEFAULT_H_STD_M[self.fix_type] * (self.hdop if self.hdop is not None else 1.0)
        return (h, h, VERTICAL_TO_HORIZONTAL * h)

    def speed_std(self) -> float:
        """Horizontal speed (per-axis velocity) 1-sigma, m/s: the message's, else the default."""
        if self.speed_std_mps is not None:
            return self.speed_std_mps
        return DEFAULT_SPEED_STD_MPS[self.fix_type]

    def velocity(self) -> tuple[float, float, float] | None:
        """ENU velocity, m/s: vel_enu_mps, or east/north from speed and course (up from the
        vertical rate, else 0); None for a position-only fix."""
        if self.vel_enu_mps is not None:
            return self.vel_enu_mps
        if self.speed_mps is None:
            return None
        c = math.radians(self.course_deg)
        vu = self.vertical_rate_mps if self.vertical_rate_mps is not None else 0.0
        return (self.speed_mps * math.sin(c), self.speed_mps * math.cos(c), vu)

    def vel_std(self) -> tuple[float, float, float] | None:
        """ENU velocity 1-sigma for initialisation (isotropic horizontal from speed_std; up from
        the vertical rate's sigma, else the vertical-rate default x 3 as nothing measures it)."""
        if self.vel_enu_mps is not None:
            if self.vel_std_enu_mps is not None:
                return self.vel_std_enu_mps
            s = self.speed_std()
            return (s, s, DEFAULT_VERTICAL_RATE_STD_MPS)
        if self.speed_mps is None:
            return None
        s = self.speed_std()
        if self.vertical_rate_mps is not None:
            vs = self.vertical_rate_std_mps or DEFAULT_VERTICAL_RATE_STD_MPS
        else:
            vs = 3.0 * DEFAULT_VERTICAL_RATE_STD_MPS
        return (s, s, vs)


class SatObservation(WireModel):
    """One satellite's raw measurement with the broadcast (or precise) satellite state."""

    id: str = Field(pattern=r"^[GCERJ]\d{2}$", description="RINEX-style id, e.g. C03, G12")
    constellation: Literal["GPS", "BDS", "GAL", "GLO", "QZS"]
    """Constellation of the satellite"""
    pseudorange_m: float = Field(gt=1.0e6, lt=MAX_RANGE_M)
    """Pseudorange, m"""
    range_rate_mps: float = Field(ge=-2.0e4, le=2.0e4)
    """Pseudorange rate (Doppler x -wavelength), m/s"""
    pseudorange_sigma_m: float = Field(gt=0.0, le=1.0e4)
    """1-sigma pseudorange noise, m"""
    range_rate_sigma_mps: float = Field(gt=0.0, le=1.0e3)
    """1-sigma range-rate noise, m/s"""
    sat_pos_ecef_m: Vec3
    """Satellite position at transmission time, in the ECEF frame of that time (NOT rotated to reception:
    the service applies the Earth-rotation correction itself), m"""
    sat_vel_ecef_mps: Vec3
    """Satellite velocity, ECEF, m/s"""
    sat_clock_m: float = Field(default=0.0, ge=-1.0e7, le=1.0e7, description="Satellite clock bias x c, m")
    sat_clock_drift_mps: float = Field(default=0.0, ge=-1.0e3, le=1.0e3)
    """Satellite clock drift x c, m/s"""
    elevation_deg: float | None = Field(default=None, ge=-90.0, le=90.0)
    """Elevation seen from the receiver, deg (None: not reported)"""

    @model_validator(mode="after")
    def _plausible(self):
        if not (6.0e6 < _norm(self.sat_pos_ecef_m) < 6.0e7):
            raise ValueError("sat_pos_ecef_m radius is not a plausible satellite orbit")
        if _norm(self.sat_vel_ecef_mps) > 1.0e4:
            raise ValueError("sat_vel_ecef_mps magnitude above 10 km/s")
        return self


class IonoKlobuchar(WireModel):
    """Broadcast Klobuchar ionosphere coefficients of one constellation (GPS: IS-GPS-200 20.3.3.5.1.7;
    BDS: BDS-SIS-ICD-B1I 5.2.4.7), as in the navigation message (seconds, semicircle powers)."""

    constellation: Literal["GPS", "BDS"]
    """Constellation whose navigation message broadcast the coefficients"""
    alpha: tuple[float, float, float, float]
    """alpha_0..3: amplitude polynomial, s/semicircle^n"""
    beta: tuple[float, float, float, float]
    """beta_0..3: period polynomial, s/semicircle^n"""


class GnssRaw(WireModel):
    """Raw pseudoranges and range rates of one epoch (tightly coupled aiding)."""

    t: Time
    sats: list[SatObservation] = Field(max_length=128)
    """One entry per tracked satellite"""
    iono: list[IonoKlobuchar] = Field(default_factory=list, max_length=2)
    """Optional broadcast ionosphere coefficients (the service applies them when configured to)"""


class StarAttitude(WireModel):
    """Star tracker attitude solution, expressed as the body attitude in the navigation frame
    (ENU; angle signs: README "Conventions (one place)")."""

    t: Time
    rpy_deg: Vec3
    """Body attitude: roll (right wing down +), pitch (nose up +), heading (clockwise from north), deg"""
    rpy_std_deg: PosStd3
    """1-sigma roll, pitch, heading noise, deg"""

    @model_validator(mode="after")
    def _plausible(self):
        _check_rpy(self.rpy_deg)
        return self


class DvlVelocity(WireModel):
    """Doppler velocity log: vehicle velocity over ground in the body frame."""

    t: Time
    vel_b_mps: Vec3
    """Velocity over ground in the body frame (right, forward, up), m/s"""
    vel_std_mps: PosStd3
    """1-sigma velocity noise per body axis, m/s"""

    @model_validator(mode="after")
    def _plausible(self):
        _check_speed(self.vel_b_mps, "vel_b_mps")
        return self


class UsblFix(WireModel):
    """USBL: body-frame vector from the vehicle array to a transponder at a known position."""

    t: Time
    rel_b_m: Vec3
    """Vector from the vehicle's array to the transponder in the body frame (right, forward, up), m"""
    transponder_lat_deg: Lat
    transponder_lon_deg: Lon
    transponder_height_m: Height
    rel_std_m: PosStd3
    """1-sigma noise per body axis, m"""

    @model_validator(mode="after")
    def _plausible(self):
        if _norm(self.rel_b_m) > 5.0e4:
            raise ValueError("rel_b_m beyond 50 km acoustic range")
        return self


class InitialNav(WireModel):
    """Initial navigation state handed over by a host system (or by a simulator). Frames and
    angle signs: README "Conventions (one place)"."""

    t: Time
    lat_deg: Lat
    lon_deg: Lon
    height_m: Height
    vel_enu_mps: Vec3
    """Velocity, east/north/up, m/s"""
    rpy_deg: Vec3
    """Attitude: roll (right wing down +), pitch (nose up +), heading (clockwise from north), deg"""
    pos_std_enu_m: PosStd3
    """1-sigma position uncertainty, east/north/up, m"""
    vel_std_enu_mps: PosStd3
    """1-sigma velocity uncertainty, east/north/up, m/s"""
    rpy_std_deg: PosStd3
    """1-sigma roll, pitch, heading uncertainty, deg"""

    @model_validator(mode="after")
    def _plausible(self):
        _check_speed(self.vel_enu_mps, "vel_enu_mps")
        _check_rpy(self.rpy_deg)
        return self


class ActiveFault(WireModel):
    """A fault the simulator is injecting at this instant (truth side only)."""

    sensor: str
    """Faulted sensor kind (gnss, gnss_raw, star, ...)"""
    kind: Literal["step", "ramp", "noise", "random_walk", "oscillation", "scale", "outliers"]
    """Fault type"""
    channels: list[str]
    """Faulted channels (e.g. pos_e, C03.pseudorange)"""


class Truth(WireModel):
    """Simulator truth (never used for filtering; for errors, dashboards and evaluation)."""

    t: Time
    lat_deg: Lat
    lon_deg: Lon
    height_m: Height
    vel_enu_mps: Vec3
    """True velocity, east/north/up, m/s"""
    rpy_deg: Vec3
    """True roll, pitch, heading (clockwise from north), deg"""
    faults: list[ActiveFault] = Field(default_factory=list)
    """Faults the simulator is injecting at this instant"""


# --- service outputs ------------------------------------------------------------------------------
#: initialising: no navigation yet (or the INS was lost and waits to be re-initialised);
#: unaided: initialised, no aiding applied since the start; aided: aiding applied within the
#: coasting window (three aiding intervals, at least 1 s); coasting: aided before, no aiding for
#: longer than that; degraded: screening (innovation gate, fault test, satellite exclusion)
#: refused aiding within that window; failed: no usable estimate until the pipeline restarts
NavStatus = Literal["initialising", "unaided", "aided", "coasting", "degraded", "failed"]


class Solution(WireModel):
    """Navigation solution of one pipeline (position of the IMU, not the antenna). Frames and
    angle signs: README "Conventions (one place)"."""

    t: Time
    pipeline: str
    """Pipeline name (as configured)"""
    lat_deg: Lat
    lon_deg: Lon
    height_m: Height
    vel_enu_mps: Vec3
    """Velocity, east/north/up, m/s"""
    rpy_deg: Vec3
    """Roll (right wing down +), pitch (nose up +), heading (clockwise from north), deg"""
    pos_std_enu_m: Vec3
    """1-sigma position, east/north/up, m (the filter's own covariance)"""
    vel_std_enu_mps: Vec3
    """1-sigma velocity, east/north/up, m/s"""
    rpy_std_deg: Vec3
    """1-sigma roll, pitch, heading, deg"""
    gyro_bias_dph: Vec3 = (0.0, 0.0, 0.0)
    """Estimated gyro bias per body axis, deg/h"""
    accel_bias_ug: Vec3 = (0.0, 0.0, 0.0)
    """Estimated accelerometer bias per body axis, micro-g"""
    status: NavStatus
    """initialising, unaided, aided, coasting, degraded or failed (see the README)"""


class ObservationFault(WireModel):
    label: str
    """Observation (row) label, e.g. pos_e, vel_n, yaw"""
    statistic: float
    """Test statistic of the row (its standardised innovation, squared or not as the test defines)"""
    threshold: float
    """Threshold the statistic is compared with"""
    flagged: bool
    """The statistic exceeded the threshold"""
    isolated: bool
    """The row was not used in the update"""


class SubsystemFaults(WireModel):
    name: str
    """Local filter or sensor kind"""
    isolated: bool
    """The whole subsystem was isolated at this epoch"""
    observations: list[ObservationFault]
    """Per observation row"""


class Reconfiguration(WireModel):
    """A subsystem leaving or rejoining the fusion (seed 004: chi2 test on the USBL local)."""

    subsystem: str
    """Local filter (subsystem) name"""
    action: Literal["excluded", "rejoined"]
    """Whether it left (excluded) or rejoined the fusion at this epoch"""
    statistic: float = Field(description="Test statistic of the epoch that changed it (NIS)")
    threshold: float
    """Threshold of that test"""


class StateEstimate(WireModel):
    """A filter state outside the navigation solution (e.g. a DVL offset) with its 1-sigma."""

    name: str
    """State name with its unit (e.g. dvl_offset_x_mps, dvl_scale_x)"""
    value: float
    """Estimate"""
    std: float
    """1-sigma"""


class Faults(WireModel):
    """Per-subsystem, per-observation fault tests of one pipeline at one aiding epoch."""

    t: Time
    pipeline: str
    """Pipeline name"""
    subsystems: list[SubsystemFaults]
    """One entry per local filter (subsystem) or sensor kind that was tested"""
    sharing: dict[str, list[float]] = Field(
        default_factory=dict, description="Per local filter, its sharing coefficient per common state"
    )
    reconfiguration: list[Reconfiguration] = Field(
        default_factory=list, description="Subsystems excluded from or rejoining the fusion at this epoch"
    )
    excluded: list[str] = Field(default_factory=list, description="Subsystems excluded after this epoch")
    states: list[StateEstimate] = Field(
        default_factory=list, description="Private states of the tested subsystem (estimate and 1-sigma)"
    )


class SatelliteTest(WireModel):
    """Per-satellite tests: solution separation (horizontal, vertical) and the windowed residual."""

    id: str
    """Satellite id, e.g. C03"""
    statistic_m: float = Field(description="Horizontal separation |dx_0n|, m")
    threshold_m: float = Field(description="Horizontal separation threshold T_n, m")
    vertical_statistic_m: float = 0.0
    """Vertical separation |dx_0n,up|, m"""
    vertical_threshold_m: float = 0.0
    """Vertical separation threshold, m"""
    residual_statistic_m: float = Field(0.0, description="Windowed mean residual vs the sub-filter, m")
    residual_threshold_m: float = Field(
        0.0, description="Its threshold (the window with the largest ratio), m"
    )


class Integrity(WireModel):
    """MHSS integrity of one pipeline at one GNSS epoch."""

    t: Time
    pipeline: str
    """Pipeline name"""
    phase: str
    """Flight phase whose alert limits apply (e.g. npa, lpv200)"""
    hpl_m: float
    """Horizontal protection level, m"""
    vpl_m: float
    """Vertical protection level, m"""
    hal_m: float
    """Horizontal alert limit of the phase, m"""
    val_m: float | None
    """Vertical alert limit of the phase, m (None: the phase has none)"""
    alarm: bool
    """Protection level above the alert limit, or a fault detected and not excluded"""
    available: bool
    """Protection levels within the alert limits"""
    detected: bool
    """A separation or residual test failed at this epoch"""
    excluded: list[str]
    """Satellites excluded (by this or an earlier epoch)"""
    satellites: list[SatelliteTest]
    """Per satellite in use: its tests"""
    detected_by: str = Field(
        "",
        description="'separation', 'residual', 'separation+residual', 'epoch_refused' (the "
        "pipeline's state refused the epoch wholesale: no update, an alarm) or ''",
    )


class Alignment(WireModel):
    """Transfer alignment of one slave IMU node (seed 002), per filter epoch at the output rate.

    Angles in master body axes (right-forward-up). ``mount_deg``: the estimated rotation of the
    slave from the master (installation + coupling + flexure), whose error is the misalignment
    with 1-sigma ``misalignment_std_deg``; ``lever_arm_m`` the estimated lever arm (nominal +
    error estimate); ``flexure_deg`` the dynamic flexure angle. ``r_std`` the square roots of the
    measurement-noise variances in use (attitude deg, velocity m/s, rate deg/s); ``fading`` the
    largest fading factor of the epoch (1: not engaged); ``share`` the fusion weight alpha_j (eq
    19) when the pipeline fuses, else None.
    """

    t: Time
    pipeline: str
    """Pipeline name"""
    node: str
    """Slave IMU node id (e.g. wing1)"""
    mount_deg: Vec3
    """Rotation of the slave from the master (installation + coupling + flexure), master axes, deg"""
    misalignment_std_deg: Vec3
    """1-sigma of the misalignment (the error of mount_deg), deg"""
    installation_deg: Vec3 = Field(description="Installation + coupling angle estimate, deg")
    installation_std_deg: Vec3
    """1-sigma of installation_deg, deg"""
    flexure_deg: Vec3
    """Dynamic flexure angle estimate, deg"""
    flexure_std_deg: Vec3
    """1-sigma of flexure_deg, deg"""
    lever_arm_m: Vec3
    """Lever arm estimate (nominal + error estimate), master body axes, m"""
    lever_arm_std_m: Vec3
    """1-sigma of lever_arm_m, m"""
    gyro_bias_dph: Vec3
    """Slave gyro bias estimate, deg/h"""
    accel_bias_ug: Vec3
    """Slave accelerometer bias estimate, micro-g"""
    r_std: tuple[float, float, float, float, float, float, float, float, float]
    """Square roots of the measurement-noise variances in use (attitude deg, velocity m/s, rate deg/s)"""
    fading: float
    """Largest fading factor of the epoch (1: not engaged)"""
    nis: float
    """Normalised innovation squared of the epoch"""
    share: float | None = None
    """Fusion weight alpha_j (eq 19) when the pipeline fuses, else None"""


class AlignmentTruth(WireModel):
    """Truth of one wing node (simulators only; the service uses it only to log errors)."""

    t: Time
    node: str
    """Slave IMU node id"""
    mount_deg: Vec3 = Field(description="True rotation of the slave from the master (incl. vibration), deg")
    installation_deg: Vec3 = Field(description="True installation + coupling angle, deg")
    flexure_deg: Vec3
    """True dynamic flexure angle, deg"""
    lever_arm_m: Vec3
    """True lever arm, master body axes, m"""


class ImmModels(WireModel):
    """Outlier IMM (He, Nie, Wu 2011) of one pipeline at one GNSS epoch: model probabilities after
    the update and each row's down-weighting per model (eq 14-16)."""

    t: Time
    pipeline: str
    """Pipeline name"""
    likelihood: Literal["paper", "gaussian"]
    """Model likelihood in use: the paper's 1/(V' Sigma^-1 V) (eq 11) or the Gaussian (log space)"""
    models: list[str] = Field(description="Model names, in bank order")
    probabilities: list[float] = Field(description="mu_j after the update, one per model (sum 1)")
    rows: list[str] = Field(description="Row labels, e.g. 'G05.pr', 'C03.rr'")
    standardised_residual: list[float] = Field(
        description="v_i of each row (normal rows; w_i, the row's residual given the other rows, with "
        "conditional residuals), averaged over the models with their predicted probabilities"
    )
    h_scale: list[list[float]] = Field(description="Per model, per row: H-row factor (eq 14; 1 = untouched)")
    r_scale: list[list[float]] = Field(
        description="Per model, per row: R_ii factor C0 (eq 15-16; 1 = untouched)"
    )
    rejected: list[str] = Field(default_factory=list, description="Rows rejected by the innovation gate")

    @model_validator(mode="after")
    def _shapes(self):
        M, m = len(self.models), len(self.rows)
        if len(self.probabilities) != M or len(self.h_scale) != M or len(self.r_scale) != M:
            raise ValueError("probabilities, h_scale and r_scale need one entry per model")
        if len(self.standardised_residual) != m or any(len(r) != m for r in self.h_scale + self.r_scale):
            raise ValueError("standardised_residual and every h_scale/r_scale row need one value per row")
        return self


class PipelineHealth(WireModel):
    status: NavStatus
    """initialising, unaided, aided, coasting, degraded or failed"""
    last_t: float | None
    """Latest sensor time processed"""
    updates: int
    """Aiding updates applied"""
    reinitialisations: int = 0
    """Restarts of the filter (InitialNav, INS loss, numerical recovery)"""
    screened: dict[str, int] = Field(
        default_factory=dict,
        description="Observations refused (or sigmas raised) by screening, by reason: innovation_gate, "
        "fault_test, excluded_satellite, gate_recovery, sigma_floor; doubted_update: updates taken between "
        "the doubt level and the fault test's threshold, weighed as possibly faulty (federated and "
        "underwater families: the covariance widened, the correction scaled down); and "
        "innovations_inconsistent: the times a stream's innovations turned larger than the filter claims "
        "(status degraded meanwhile); innovations_biased: the times a stream's innovations turned off "
        "centre (status degraded meanwhile), and bias_inflation: the rows whose bias grew the "
        "covariance (loosely coupled, federated and centralised families)",
    )


class Health(WireModel):
    """Service health, once a second."""

    t: float | None = Field(description="Latest sensor time processed (None before any)")
    uptime_s: float
    """Seconds since the vehicle's worker started"""
    received: int
    """Messages received for this vehicle"""
    accepted: int
    """Messages accepted"""
    rejected: dict[str, int] = Field(description="Rejections by reason")
    dropped_overload: int
    """Messages dropped because the intake queue was full (overload = drop)"""
    queue_depth: int
    """Messages waiting in the vehicle's queue"""
    latency_ms: dict[str, float] = Field(
        description="Latency percentiles (p50, p99, max) from a message's arrival in the service process "
        "(Zenoh callback), queue time included, to the end of its processing (outputs published)"
    )
    pipelines: dict[str, PipelineHealth]
    """Per pipeline: status, screening and counts"""
    sensors: dict[str, float] = Field(
        default_factory=dict, description="Last accepted sensor time per stream ('kind/id' -> t)"
    )
    stale: list[str] = Field(
        default_factory=list,
        description="Streams silent for more than three of their own intervals (at least 1 s)",
    )
    time_base_mismatch: dict[str, float] = Field(
        default_factory=dict,
        description="Streams ('kind/id') whose latest time is more than 60 s from the vehicle's IMU time, "
        "with that offset, s: a time base mismatch (every stream must carry GPS seconds)",
    )
    notes: dict[str, int] = Field(
        default_factory=dict,
        description="Counted events that are not refusals, by name: e.g. fix_without_velocity (a ROS 2 "
        "NavSatFix used position-only because its Twist did not come), twist_without_fix",
    )


SatId = Annotated[str, Field(min_length=1, max_length=16)]


class Status(WireModel):
    """Reply of the queryable ``{prefix}/{vehicle}/service/status``: the vehicle's state now."""

    vehicle: str
    """The vehicle the reply is about"""
    running: bool
    """True: the service that answers is running"""
    pipelines: list[str]
    """The service's configured pipelines (each publishes under ``{prefix}/{vehicle}/nav/{pipeline}/...``)"""
    health: Health | None = None
    """The vehicle's Health as it stands (null before the vehicle's first message)"""
    refused_before_routing: dict[str, int] = Field(
        default_factory=dict,
        description="Messages the service refused before any vehicle, by reason (as in ServiceHealth)",
    )


class HandoverState(WireModel):
    """A served vehicle's pipeline state for another service of its fleet (``[fleet] sharding =
    'rendezvous'``, key ``{prefix}/_fleet/{group}/to/{member}/state/{vehicle}/{pipeline}``, about
    1 Hz, to the member that takes the vehicle over; a local shard's
    ``{prefix}/_fleet/{group}/state/{vehicle}/{pipeline}``): what the service that takes the
    vehicle over starts from instead of a cold start. Carries the
    navigation state, its 9x9 covariance and the IMU bias estimates with their sigmas."""

    t: Time
    vehicle: str = Field(min_length=1, max_length=64, description="Vehicle name")
    pipeline: str = Field(min_length=1, max_length=64, description="Pipeline whose state this is")
    service: str = Field(min_length=1, max_length=64, description="Zenoh id of the publishing service")
    lat_deg: Lat
    lon_deg: Lon
    height_m: Height
    vel_enu_mps: Vec3 = Field(description="Velocity east/north/up, m/s")
    q_nb: tuple[float, float, float, float] = Field(
        description="Attitude quaternion body -> ENU (w, x, y, z)"
    )
    P9: list[float] = Field(
        min_length=81, max_length=81, description="Covariance of (dp_enu, dv_enu, phi_enu), row-major"
    )
    gyro_bias_rps: Vec3 = Field(description="Gyro bias estimate, body, rad/s")
    accel_bias_mps2: Vec3 = Field(description="Accelerometer bias estimate, body, m/s^2")
    acc_enu_mps2: Vec3 = Field(
        (0.0, 0.0, 0.0),
        description="The vehicle's acceleration east/north/up over the INS's last major interval, "
        "m/s^2: the taking service carries velocity and position over the gap with it (a turn)",
    )
    rate_body_rps: Vec3 = Field(
        (0.0, 0.0, 0.0),
        description="Body angular rate (bias corrected) over the INS's last major interval, rad/s: "
        "the taking service turns the attitude over the gap with it",
    )
    stream_records: dict[Annotated[str, Field(max_length=64)], bool] = Field(
        default_factory=dict,
        max_length=32,
        description="Per aiding stream (kind/sensor id), whether the pipeline's innovation test found it as "
        "good as it claims: the taking service starts from these verdicts (a fix whose position fails "
        "its gate then makes the rest of that fix suspect from the first epoch, as it did here)",
    )
    screening: bool = Field(
        False,
        description="The pipeline's own screening refused aiding within its coast window (a fault under "
        "way: a GNSS step its gate refuses): the taking service lets its own screening judge a fix that "
        "disagrees with this state instead of restarting from that fix",
    )
    bias_std: tuple[float, float, float, float, float, float] = Field(
        description="1-sigma of the gyro (rad/s) and accelerometer (m/s^2) bias estimates"
    )
    status: str = Field(max_length=32, description="The pipeline's status when published")
    excluded: dict[SatId, Annotated[float, Field(ge=0.0)]] = Field(
        default_factory=dict,
        max_length=64,
        description="Satellites the pipeline's integrity monitor excludes as faulty (MHSS), each with "
        "the seconds its health tests have passed so far (0: failing): the service taking the "
        "vehicle over keeps them out until they have passed for the monitor's re-admission time",
    )

    @model_validator(mode="after")
    def _plausible(self):
        _check_speed(self.vel_enu_mps, "vel_enu_mps")
        if abs(_norm(self.q_nb) - 1.0) > 1e-6:
            raise ValueError("q_nb is not a unit quaternion")
        if any(self.P9[9 * i + i] < 0.0 for i in range(9)) or min(self.bias_std) < 0.0:
            raise ValueError("negative variance or sigma")
        return self


class ServiceHealth(WireModel):
    """Service-level health, once a second (key ``{prefix}/_services/{zenoh id}/health``): what
    the service refused before any vehicle, e.g. data under a vehicle name it does not serve."""

    uptime_s: float
    """Seconds since the service started"""
    vehicles: list[str]
    """Vehicles served as configured ('*': all)"""
    active_vehicles: list[str]
    """Vehicles with data so far (a worker running)"""
    refused_before_routing: dict[str, int] = Field(
        default_factory=dict,
        description="Messages refused before any vehicle, by reason: unserved_vehicle (a name not in "
        "'vehicles'), vehicle_limit (more than intake.max_vehicles with '*'), bad_vehicle_name, "
        "bad_shard_frame (a local shard: a frame of shard 0's feed that did not decode)",
    )
    unserved_vehicles: dict[str, int] = Field(
        default_factory=dict,
        description="Messages per vehicle name the service does not serve (the first 100 names)",
    )
    messages_received: int = Field(
        0,
        ge=0,
        description="Messages received for the vehicles it serves now (an ImuBatch counts its samples)",
    )
    fleet_group: str | None = Field(
        None, description="Fleet group it shares vehicles in ([fleet] sharding = 'rendezvous'), else None"
    )
    fleet_members: list[str] = Field(
        default_factory=list, description="The live services of its fleet group (Zenoh ids), itself included"
    )
    vehicles_moved_away: int = Field(
        0, ge=0, description="Vehicles handed to another service of the fleet since the start"
    )
    vehicles_released_idle: int = Field(
        0,
        ge=0,
        description="Vehicles released after [intake] vehicle_idle_s without any input, since the start",
    )
    inputs_served_elsewhere: int = Field(
        0,
        ge=0,
        description="Inputs of vehicles another shard or fleet member serves, dropped unread by the "
        "intake since the start (every service of a fleet receives every vehicle's inputs, or with "
        "[intake] subscribe = 'owned' their low-rate discovery inputs)",
    )
    subscribed_vehicles: int | None = Field(
        None,
        ge=0,
        description="A fleet member subscribing per vehicle it serves ([intake] subscribe = 'owned'): the "
        "vehicles it subscribes to now (of the others it hears only their low-rate discovery inputs); "
        "None when it subscribes to every vehicle's inputs",
    )
    inputs_discovery_copies: int = Field(
        0,
        ge=0,
        description="[intake] subscribe = 'owned': low-rate inputs of a vehicle with its own subscription "
        "that reached the service through the discovery keys as well, dropped there since the start",
    )
    inputs_forwarded: int = Field(
        0,
        ge=0,
        description="Shard 0 of local shards (fednav-service --shards): inputs handed to the other "
        "shards (each serves the vehicles rendezvous hashing gives it) since the start",
    )
    inputs_forward_lost: int = Field(
        0,
        ge=0,
        description="Shard 0: inputs for another shard dropped (that shard dead, restarting or not "
        "keeping up: its queue full) since the start",
    )
    max_vehicles: int | None = Field(
        None, ge=1, description="[intake] max_vehicles of a '*' service (None: it serves a fixed list)"
    )
    full: bool = Field(
        False,
        description="A '*' service at max_vehicles: it takes no new vehicle (in a fleet group, the "
        "vehicles it would have had go to the next member with room)",
    )
    refusing_vehicles: list[str] = Field(
        default_factory=list,
        max_length=100,
        description="Vehicles whose inputs it refused for vehicle_limit in the last "
        "REFUSING_WINDOW_S (10 s): unserved unless another service takes them (the first 100)",
    )


#: input messages that are not sensors: the initial state, truth (simulators), alignment truth;
#: the sensors' messages are in the sensor registry (``service.sensors``)
CONTROL_MESSAGES: dict[str, type[WireModel]] = {
    "init": InitialNav,
    "truth": Truth,
    "alignment_truth": AlignmentTruth,
}

ALL_MESSAGES: list[type[WireModel]] = [
    ImuSample,
    GnssFix,
    GnssRaw,
    StarAttitude,
    DvlVelocity,
    UsblFix,
    InitialNav,
    Truth,
    Solution,
    Faults,
    Integrity,
    ImmModels,
    Health,
    Alignment,
    AlignmentTruth,
    ServiceHealth,
    Status,
    HandoverState,
]


def schema_id(name: str) -> str:
    """The schema's URI (a URN: it names the message type and version, it is not fetched); the
    samples' encoding ``application/json;fednav.<name>/<version>`` names the same pair."""
    return f"urn:fednav:schema:{name}:{SCHEMA_VERSION}"


def all_messages() -> list[type[WireModel]]:
    """Every wire message: the ones above and those of the sensor registry's kinds."""
    from fednav.service import sensors

    extra = [s.message for s in sensors.registry().values() if s.message not in ALL_MESSAGES]
    return ALL_MESSAGES + extra


def json_schemas() -> dict[str, dict]:
    """JSON Schema (draft 2020-12, pydantic's validation mode) of every wire message."""
    out = {}
    for m in all_messages():
        s = {"$schema": "https://json-schema.org/draft/2020-12/schema", **m.model_json_schema()}
        s["$id"] = schema_id(m.__name__)
        out[m.__name__] = s
    return out


def write_schemas(folder: Path) -> list[Path]:
    folder.mkdir(parents=True, exist_ok=True)
    paths = []
    for name, schema in json_schemas().items():
        p = folder / f"{name}.schema.json"
        p.write_text(json.dumps(schema, indent=2, sort_keys=True) + "\n")
        paths.append(p)
    return paths


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description="Write the JSON Schemas of fednav's wire messages")
    ap.add_argument("--write", type=Path, required=True, help="output folder (docs/schemas)")
    args = ap.parse_args(argv)
    for p in write_schemas(args.write):
        print(p)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
