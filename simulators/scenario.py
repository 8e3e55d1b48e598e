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
    [gnss_raw]         GnssRawScenarioSpec (optional): raw pseudoranges/range rates (seed 001)
    [usbl], [dvl]      UsblSpec, DvlSpec (optional): underwater acoustic aiding (seed 004)
    [initial_errors]   mode, pos_enu_m, vel_enu_mps, rpy_arcsec
    [[faults]]         sensor, kind, start_s, duration_s, channels, per-channel parameters
    [fault_schedule]   FaultScheduleSpec (optional): random faults expanded into [[faults]] at load
    [service]          free-form, passed untouched to the service configuration

Segments shorter than ``duration_s`` in total are padded with straight flight.

Raw GNSS faults (sensor ``"gnss_raw"``) name channels ``"<sat>.pseudorange"`` (m) and
``"<sat>.range_rate"`` (m/s); ``<sat>`` is an id (``C03``) or a role name (``GEO3``), resolved at
load. Unless ``gnss_raw.selection = "all"``, a faulted satellite must be one of
``gnss_raw.required_satellites`` (so the selection publishes it while it is visible).

Fault schedule (``[fault_schedule]``, seed 001's Monte Carlo): :func:`expand_fault_schedule`
turns it into explicit ``[[faults]]`` at load, deterministically from ``seed``. See
:class:`FaultScheduleSpec` for the draw.
"""

from __future__ import annotations

import math
import re
import tomllib
from pathlib import Path
from typing import Any, Literal

import numpy as np
from pydantic import BaseModel, ConfigDict, Field, ValidationError, model_validator

from fednav.service.validation_errors import format_errors, suggest
from fednav.simulators.acoustic import DVL_CHANNELS, DVL_SENSOR, USBL_CHANNELS, USBL_SENSOR, DvlSpec, UsblSpec
from fednav.simulators.faults import FaultSpec
from fednav.simulators.gnss.orbits import resolve_sat_id
from fednav.simulators.gnss.raw_sensor import GnssRawSpec
from fednav.simulators.imu import ImuSpec
from fednav.simulators.sensors import (
    GNSS_CHANNELS,
    GNSS_SENSOR,
    STAR_CHANNELS,
    STAR_SENSOR,
    GnssSpec,
    StarSpec,
    epoch_step,
)
from fednav.simulators.trajectory import Segment, StartSpec, Trajectory, build_trajectory, check_segments
from fednav.simulators.wing import WingSpec

SCENARIO_DIR = Path(__file__).resolve().parent / "scenarios"
Vec3 = tuple[float, float, float]

GNSS_RAW_SENSOR = "gnss_raw"
GNSS_RAW_CHANNEL = re.compile(r"^([GCERJ]\d{2})\.(pseudorange|range_rate)$")
#: outlier faults (He, Nie, Wu 2011) pick among published satellites: '*' stands for any
GNSS_RAW_PATTERN = re.compile(r"^(\*|[GCERJ]\d{2})\.(pseudorange|range_rate)$")
FAULT_KINDS = ("step", "ramp", "noise", "random_walk", "oscillation")
Range = tuple[float, float]


class GnssRawScenarioSpec(GnssRawSpec):
    """A raw GNSS sensor of a scenario: :class:`GnssRawSpec` plus the sensor id of its key."""

    id: str = Field(default="main", pattern=r"^[A-Za-z0-9_\-.]+$", description="Sensor id in the key")


class FaultScheduleSpec(BaseModel):
    """Random single-satellite faults at a fixed period (seed 001's Monte Carlo, "a fault injected
    at a random satellite every 120 epochs"), expanded into explicit faults at load.

    Draw (``rng = default_rng(SeedSequence([seed, 1]))``, in this order per fault ``i``)::

        onset      = first_onset_s + i * period_epochs / rate   (rate: gnss_raw.rate_hz), while
                     onset + the longest duration fits before duration_s
        satellite  ~ uniform over ``satellites`` (default: gnss_raw.required_satellites)
        kind       ~ uniform over ``kinds``
        duration   ~ uniform integer in [duration_epochs[0], duration_epochs[1]] epochs
        sign       ~ +-1 with probability 1/2 (step magnitude, ramp rate, noise mean)
        size       ~ uniform over the kind's range:
          step         magnitude = sign * U(step_m)
          ramp         rate_per_s = sign * U(ramp_mps)
          noise        mean = sign * U(noise_mean_m), std = U(noise_std_m)
          random_walk  sigma_per_sqrt_s = U(random_walk_m_per_sqrt_s)
          oscillation  amplitude = U(oscillation_m), freq_hz = U(oscillation_hz), phase ~ U(0, 2 pi)

    Every fault acts on the ``<sat>.pseudorange`` channel of sensor ``gnss_raw``. The epochs
    between the end of one fault and the next onset are fault-free. ``expanded`` is set by the
    loader once the faults are in ``faults`` (a dumped scenario re-loads without duplicating).
    """

    model_config = ConfigDict(extra="forbid", frozen=True)

    period_epochs: int = Field(120, ge=2, description="Epochs between fault onsets")
    first_onset_s: float = Field(60.0, ge=0.0, description="Onset of the first fault, s after the start")
    duration_epochs: tuple[int, int] = Field((30, 60), description="Fault length range, epochs (inclusive)")
    satellites: tuple[str, ...] = Field((), description="Candidates (ids or role names); default: required")
    kinds: tuple[Literal["step", "ramp", "noise", "random_walk", "oscillation"], ...] = Field(
        FAULT_KINDS, min_length=1, description="Fault kinds drawn uniformly"
    )
    step_m: Range = Field((5.0, 100.0), description="|step| range, m")
    ramp_mps: Range = Field((0.2, 5.0), description="|ramp rate| range, m/s")
    noise_mean_m: Range = Field((0.0, 20.0), description="|noise mean| range, m")
    noise_std_m: Range = Field((2.0, 30.0), description="noise std range, m")
    random_walk_m_per_sqrt_s: Range = Field((1.0, 10.0), description="random-walk intensity range, m/sqrt(s)")
    oscillation_m: Range = Field((5.0, 50.0), description="oscillation amplitude range, m")
    oscillation_hz: Range = Field((0.01, 0.2), description="oscillation frequency range, Hz")
    expanded: bool = Field(False, description="Set by the loader: faults already in [[faults]]")

    @model_validator(mode="after")
    def _ranges(self):
        lo, hi = self.duration_epochs
        if not 1 <= lo <= hi:
            raise ValueError(f"duration_epochs = {list(self.duration_epochs)}: need 1 <= min <= max")
        if hi >= self.period_epochs:
            raise ValueError("duration_epochs: the longest fault must be shorter than period_epochs")
        for name in (
            "step_m",
            "ramp_mps",
            "noise_mean_m",
            "noise_std_m",
            "random_walk_m_per_sqrt_s",
            "oscillation_m",
            "oscillation_hz",
        ):
            a, b = getattr(self, name)
            if not 0.0 <= a <= b:
                raise ValueError(f"{name} = {[a, b]}: need 0 <= min <= max")
        return self


def expand_fault_schedule(
    sched: FaultScheduleSpec, seed: int, rate_hz: float, duration_s: float, satellites: list[str]
) -> list[dict]:
    """The explicit fault tables of a schedule (see :class:`FaultScheduleSpec`)."""
    if not satellites:
        raise ValueError("fault_schedule: no candidate satellites (give satellites or required_satellites)")
    rng = np.random.default_rng(np.random.SeedSequence([int(seed), 1]))
    out: list[dict] = []
    period = sched.period_epochs / rate_hz
    longest = sched.duration_epochs[1] / rate_hz
    i = 0
    while True:
        onset = sched.first_onset_s + i * period
        if onset + longest > duration_s + 1e-9:
            break
        sat = satellites[int(rng.integers(len(satellites)))]
        kind = sched.kinds[int(rng.integers(len(sched.kinds)))]
        n_ep = int(rng.integers(sched.duration_epochs[0], sched.duration_epochs[1] + 1))
        sign = 1.0 if rng.random() < 0.5 else -1.0
        f: dict[str, Any] = {
            "sensor": GNSS_RAW_SENSOR,
            "kind": kind,
            "start_s": round(onset, 9),
            "duration_s": n_ep / rate_hz,
            "channels": [f"{sat}.pseudorange"],
        }
        u = lambda r: float(rng.uniform(r[0], r[1]))  # noqa: E731
        if kind == "step":
            f["magnitude"] = [sign * u(sched.step_m)]
        elif kind == "ramp":
            f["rate_per_s"] = [sign * u(sched.ramp_mps)]
        elif kind == "noise":
            f["mean"] = [sign * u(sched.noise_mean_m)]
            f["std"] = [u(sched.noise_std_m)]
        elif kind == "random_walk":
            f["sigma_per_sqrt_s"] = [u(sched.random_walk_m_per_sqrt_s)]
        else:
            f["amplitude"] = [u(sched.oscillation_m)]
            f["freq_hz"] = [u(sched.oscillation_hz)]
            f["phase_rad"] = [float(rng.uniform(0.0, 2.0 * math.pi))]
        out.append(f)
        i += 1
    return out


def _resolve_raw_channels(data: dict) -> dict:
    """Role names in raw-GNSS fault channels (``GEO3.pseudorange`` -> ``C03.pseudorange``)."""
    faults = data.get("faults")
    if not isinstance(faults, list):
        return data
    new = []
    for f in faults:
        if isinstance(f, dict) and f.get("sensor") == GNSS_RAW_SENSOR and isinstance(f.get("channels"), list):
            ch = []
            for c in f["channels"]:
                if isinstance(c, str) and "." in c:
                    sat, _, q = c.partition(".")
                    c = f"{resolve_sat_id(sat)}.{q}"
                ch.append(c)
            f = {**f, "channels": ch}
        new.append(f)
    return {**data, "faults": new}


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
    gnss_raw: GnssRawScenarioSpec | None = Field(
        default=None, description="Raw GNSS pseudoranges/range rates (optional)"
    )
    fault_schedule: FaultScheduleSpec | None = Field(
        default=None, description="Random raw-GNSS faults expanded into faults at load (optional)"
    )
    usbl: UsblSpec | None = Field(default=None, description="USBL vectors to a transponder (optional)")
    dvl: DvlSpec | None = Field(default=None, description="DVL body velocities (optional)")
    initial_errors: InitialErrorsSpec = Field(
        default_factory=InitialErrorsSpec, description="Initial-state errors"
    )
    truth_rate_hz: float = Field(
        default=10.0, gt=0.0, description="Truth message rate, Hz (divides the IMU rate)"
    )
    faults: list[FaultSpec] = Field(default_factory=list, description="Injected sensor faults")
    wing: WingSpec | None = Field(
        default=None, description="Wing IMU nodes for transfer alignment (seed 002, optional)"
    )
    service: dict[str, Any] = Field(
        default_factory=dict, description="Passed untouched to the service config"
    )
    sensors: dict[str, dict[str, Any]] = Field(
        default_factory=dict,
        description="Further sensors of the sensor registry by kind, each with its simulation options "
        "(e.g. [sensors.baro] rate_hz = 10): a kind whose registry entry has a simulator hook",
    )

    @model_validator(mode="after")
    def _registry_sensors(self):
        from fednav.service import sensors as registry

        for kind, spec in self.sensors.items():
            entry = registry.registry().get(kind)
            if entry is None or entry.simulate is None:
                hooks = sorted(k for k, e in registry.registry().items() if e.simulate is not None)
                raise ValueError(
                    f"sensors.{kind}: no simulator for sensor kind {kind!r} (simulated: {hooks})"
                )
            try:
                entry.simulate_spec.model_validate(spec)
            except ValidationError as e:
                first = e.errors()[0]
                loc = ".".join(str(p) for p in ("sensors", kind, *first["loc"]))
                raise ValueError(f"{loc}: {first['msg']}") from None
        return self

    def registry_sensor_specs(self) -> dict[str, Any]:
        """The validated specs of the ``[sensors.<kind>]`` tables."""
        from fednav.service import sensors as registry

        return {k: registry.get(k).simulate_spec.model_validate(v) for k, v in self.sensors.items()}

    @model_validator(mode="before")
    @classmethod
    def _expand(cls, data: Any) -> Any:
        if not isinstance(data, dict):
            return data
        data = _resolve_raw_channels(data)
        sched, raw = data.get("fault_schedule"), data.get("gnss_raw")
        if sched is None:
            return data
        if isinstance(sched, FaultScheduleSpec):
            sched = sched.model_dump()
        try:
            sched = FaultScheduleSpec.model_validate(sched)
        except ValidationError as e:
            first = e.errors()[0]
            loc = ".".join(str(p) for p in ("fault_schedule", *first["loc"]))
            raise ValueError(f"{loc}: {first['msg']}") from None
        if sched.expanded:
            return data
        if not isinstance(raw, dict | GnssRawSpec):
            raise ValueError("fault_schedule needs a [gnss_raw] sensor")
        if isinstance(raw, dict):
            try:
                raw = GnssRawScenarioSpec.model_validate(raw)
            except ValidationError:
                return data  # the gnss_raw field's own validation reports it
        if "duration_s" not in data:
            return data
        sats = [resolve_sat_id(s) for s in sched.satellites] or list(raw.required_satellites)
        faults = list(data.get("faults") or [])
        faults += expand_fault_schedule(
            sched, int(data.get("seed", 1)), raw.rate_hz, float(data["duration_s"]), sats
        )
        sched = sched.model_copy(update={"satellites": tuple(sats), "expanded": True})
        return {**data, "faults": faults, "fault_schedule": sched.model_dump()}

    @model_validator(mode="after")
    def _consistent(self):
        rate = self.imu.rate_hz
        check_segments(self.start, self.segments, rate, self.duration_s)  # messages name the segment
        for what, r in (
            ("truth_rate_hz", self.truth_rate_hz),
            ("gnss.rate_hz", self.gnss.rate_hz if self.gnss else None),
            ("star.rate_hz", self.star.rate_hz if self.star else None),
            ("gnss_raw.rate_hz", self.gnss_raw.rate_hz if self.gnss_raw else None),
            ("usbl.rate_hz", self.usbl.rate_hz if self.usbl else None),
            ("dvl.rate_hz", self.dvl.rate_hz if self.dvl else None),
        ):
            if r is not None:
                epoch_step(rate, r, what)
        channels = {}
        if self.gnss is not None:
            channels[GNSS_SENSOR] = GNSS_CHANNELS
        if self.star is not None:
            channels[STAR_SENSOR] = STAR_CHANNELS
        if self.usbl is not None:
            channels[USBL_SENSOR] = USBL_CHANNELS
        if self.dvl is not None:
            channels[DVL_SENSOR] = DVL_CHANNELS
        raw = self.gnss_raw
        if raw is not None:
            channels[GNSS_RAW_SENSOR] = None  # "<sat>.pseudorange" / "<sat>.range_rate", checked below
        for i, f in enumerate(self.faults):
            if f.sensor == GNSS_RAW_SENSOR and raw is not None and f.kind == "outliers":
                bad = [c for c in f.channels if not GNSS_RAW_PATTERN.match(c)]
                if bad:
                    raise ValueError(
                        f"faults[{i}].channels: {bad} are not raw GNSS channel patterns "
                        "('*.pseudorange', '*.range_rate' or '<sat>.<quantity>')"
                    )
            elif f.sensor == GNSS_RAW_SENSOR and raw is not None:
                bad = [c for c in f.channels if not GNSS_RAW_CHANNEL.match(c)]
                if bad:
                    raise ValueError(
                        f"faults[{i}].channels: {bad} are not raw GNSS channels "
                        "('<sat>.pseudorange' or '<sat>.range_rate', sat an id like C03 or a role like GEO3)"
                    )
                sats = {c.split(".")[0] for c in f.channels}
                systems = {"G": "GPS", "C": "BDS"}
                off = sorted(s for s in sats if systems.get(s[0]) not in raw.constellations)
                if off:
                    raise ValueError(f"faults[{i}].channels: {off} not in gnss_raw.constellations")
                if raw.selection != "all":
                    unsure = sorted(sats - set(raw.required_satellites))
                    if unsure:
                        raise ValueError(
                            f"faults[{i}].channels: {unsure} must be in gnss_raw.required_satellites "
                            f"(selection {raw.selection!r} might not publish them)"
                        )
            if f.sensor not in channels:
                raise ValueError(
                    f"faults[{i}].sensor = {f.sensor!r}: no such sensor in this scenario "
                    f"(have {sorted(channels)})"
                )
            bad = [c for c in f.channels if channels[f.sensor] is not None and c not in channels[f.sensor]]
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
    shipped = sorted(f.stem for f in SCENARIO_DIR.glob("*.toml"))
    raise ScenarioError(
        f"no scenario {str(name_or_path)!r}{suggest(p.stem, shipped)}: not a file, and not one of the "
        f"shipped scenarios ({', '.join(shipped)})"
    )


def parse_scenario(data: dict, source: str = "<dict>") -> Scenario:
    """Validate a scenario mapping (raises ScenarioError naming the fields)."""
    try:
        return Scenario.model_validate(data)
    except ValidationError as e:
        raise ScenarioError(format_errors(e, Scenario, f"invalid scenario {source}:"), e.errors()) from None


def load_scenario(path: str | Path) -> Scenario:
    """Read and validate a scenario TOML (a path, or a name under ``simulators/scenarios``)."""
    p = scenario_path(path)
    try:
        data = tomllib.loads(p.read_text())
    except tomllib.TOMLDecodeError as e:
        raise ScenarioError(f"invalid TOML in {p}: {e}") from e
    return parse_scenario(data, str(p))


def load_scenario_cli(path: str | Path, prog: str) -> Scenario | None:
    """:func:`load_scenario` for a command line: a :class:`ScenarioError` is printed as one line
    ``prog: message`` on stderr, no traceback; None then (the command exits 2)."""
    import sys

    try:
        return load_scenario(path)
    except ScenarioError as exc:
        print(f"{prog}: {exc}", file=sys.stderr)
        return None


def duration_arg(text: str) -> float:
    """``--duration S`` of scenario time on a command line (and the publishers' ``--match-timeout``,
    ``publisher.timeout_arg``): a finite number of seconds > 0."""
    import argparse

    try:
        s = float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"not a number: {text!r}") from None
    if not (math.isfinite(s) and s > 0):
        raise argparse.ArgumentTypeError(f"{text}: use a finite number of seconds > 0")
    return s
