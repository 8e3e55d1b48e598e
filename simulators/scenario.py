"""Scenario files: typed TOML describing a trajectory, its sensors, initial errors and faults.

A scenario is validated whole at load; every error names its field (``segments[2].duration_s``,
``gnss.pos_std_enu_m``, ``faults.0.step.magnitude``...). Nothing is silently corrected.

Layout (see ``simulators/scenarios/*.toml``)::

    name, duration_s, t0_gps_s, seed, truth_rate_hz
    [start]            lat_deg, lon_deg, height_m, heading_deg, speed_mps
    [[segments]]       kind = static | straight | turn | climb | accelerate, duration_s, ...
    [imu]              ImuSpec
    [gnss]             GnssSpec (optional)
    [star]             StarSpec (optional)
    [initial_errors]   mode, pos_enu_m, vel_enu_mps, rpy_arcsec
    [[faults]]         sensor, kind, start_s, duration_s, channels, per-channel parameters
    [service]          free-form, passed untouched to the service configuration

Segments shorter than ``duration_s`` in total are padded with straight flight.
"""

from __future__ import annotations

import tomllib
from pathlib import Path
from typing import Any, Literal

from pydantic import BaseModel, ConfigDict, Field, ValidationError, model_validator

from simulators.faults import FaultSpec
from simulators.imu import ImuSpec
from simulators.sensors import (
    GNSS_CHANNELS,
    GNSS_SENSOR,
    STAR_CHANNELS,
    STAR_SENSOR,
    GnssSpec,
    StarSpec,
    epoch_step,
)
from simulators.trajectory import Segment, StartSpec, Trajectory, build_trajectory, check_segments

SCENARIO_DIR = Path(__file__).resolve().parent / "scenarios"
Vec3 = tuple[float, float, float]


class InitialErrorsSpec(BaseModel):
    """Errors of the initial navigation state handed to the service.

    ``mode = "random"``: the values are 1-sigma, each component drawn per run as N(0, sigma).
    ``mode = "fixed"``: the values are applied exactly (any sign). Attitude errors are added to the
    Euler angles (roll, pitch, yaw; yaw west positive, so +yaw error = -heading error).
    """

    model_config = ConfigDict(extra="forbid", frozen=True)

    mode: Literal["random", "fixed"] = Field(default="random", description="Draw per run or apply as given")
    pos_enu_m: Vec3 = Field(default=(0.0, 0.0, 0.0), description="Position error east/north/up, m")
    vel_enu_mps: Vec3 = Field(default=(0.0, 0.0, 0.0), description="Velocity error east/north/up, m/s")
    rpy_arcsec: Vec3 = Field(default=(0.0, 0.0, 0.0), description="Attitude error roll/pitch/yaw, arcsec")

    @model_validator(mode="after")
    def _sigmas_nonnegative(self):
        if self.mode == "random":
            for name in ("pos_enu_m", "vel_enu_mps", "rpy_arcsec"):
                if min(getattr(self, name)) < 0.0:
                    raise ValueError(f"initial_errors.{name}: sigmas must be >= 0 when mode = 'random'")
        return self


class Scenario(BaseModel):
    """One simulated run: trajectory, sensors, initial errors, faults and service settings."""

    model_config = ConfigDict(extra="forbid", frozen=True)

    name: str = Field(min_length=1, description="Scenario name")
    description: str = Field(default="", description="Free text")
    duration_s: float = Field(gt=0.0, le=1.0e6, description="Length of the run, s (multiple of the IMU step)")
    t0_gps_s: float = Field(
        default=1_300_000_000.0, ge=0.0, le=1.0e10, description="GPS time of the start, s"
    )
    seed: int = Field(default=1, ge=0, description="Default random seed of a run")
    start: StartSpec = Field(description="Initial position, heading and speed")
    segments: list[Segment] = Field(default_factory=list, description="Flight segments, flown in order")
    imu: ImuSpec = Field(default_factory=ImuSpec, description="IMU grade and rate")
    gnss: GnssSpec | None = Field(default=None, description="GNSS position/velocity fixes (optional)")
    star: StarSpec | None = Field(default=None, description="Star tracker (optional)")
    initial_errors: InitialErrorsSpec = Field(
        default_factory=InitialErrorsSpec, description="Initial-state errors"
    )
    truth_rate_hz: float = Field(
        default=10.0, gt=0.0, description="Truth message rate, Hz (divides the IMU rate)"
    )
    faults: list[FaultSpec] = Field(default_factory=list, description="Injected sensor faults")
    service: dict[str, Any] = Field(
        default_factory=dict, description="Passed untouched to the service config"
    )

    @model_validator(mode="after")
    def _consistent(self):
        rate = self.imu.rate_hz
        check_segments(self.start, self.segments, rate, self.duration_s)  # messages name the segment
        for what, r in (
            ("truth_rate_hz", self.truth_rate_hz),
            ("gnss.rate_hz", self.gnss.rate_hz if self.gnss else None),
            ("star.rate_hz", self.star.rate_hz if self.star else None),
        ):
            if r is not None:
                epoch_step(rate, r, what)
        channels = {}
        if self.gnss is not None:
            channels[GNSS_SENSOR] = GNSS_CHANNELS
        if self.star is not None:
            channels[STAR_SENSOR] = STAR_CHANNELS
        for i, f in enumerate(self.faults):
            if f.sensor not in channels:
                raise ValueError(
                    f"faults[{i}].sensor = {f.sensor!r}: no such sensor in this scenario "
                    f"(have {sorted(channels)})"
                )
            bad = [c for c in f.channels if c not in channels[f.sensor]]
            if bad:
                raise ValueError(
                    f"faults[{i}].channels: {bad} unknown for {f.sensor} (known: {list(channels[f.sensor])})"
                )
            if f.start_s >= self.duration_s:
                raise ValueError(
                    f"faults[{i}].start_s = {f.start_s} is not before duration_s = {self.duration_s}"
                )
        return self

    def build_trajectory(self) -> Trajectory:
        """The scenario's trajectory at the IMU rate (build once, reuse across Monte Carlo runs)."""
        return build_trajectory(self.start, self.segments, self.imu.rate_hz, self.t0_gps_s, self.duration_s)


class ScenarioError(ValueError):
    """A scenario file that does not parse or validate; ``errors`` holds pydantic's error list."""

    def __init__(self, message: str, errors: list | None = None):
        super().__init__(message)
        self.errors = errors or []


def scenario_path(name_or_path: str | Path) -> Path:
    """A path as given if it exists, else ``simulators/scenarios/<name>.toml``."""
    p = Path(name_or_path)
    if p.exists():
        return p
    q = SCENARIO_DIR / (p.name if p.suffix == ".toml" else f"{p.name}.toml")
    if q.exists():
        return q
    raise FileNotFoundError(f"no scenario {name_or_path!r} (looked at {p} and {q})")


def parse_scenario(data: dict, source: str = "<dict>") -> Scenario:
    """Validate a scenario mapping (raises ScenarioError naming the fields)."""
    try:
        return Scenario.model_validate(data)
    except ValidationError as e:
        raise ScenarioError(f"invalid scenario {source}:\n{e}", e.errors()) from e


def load_scenario(path: str | Path) -> Scenario:
    """Read and validate a scenario TOML (a path, or a name under ``simulators/scenarios``)."""
    p = scenario_path(path)
    try:
        data = tomllib.loads(p.read_text())
    except tomllib.TOMLDecodeError as e:
        raise ScenarioError(f"invalid TOML in {p}: {e}") from e
    return parse_scenario(data, str(p))
