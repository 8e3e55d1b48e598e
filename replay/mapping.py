"""The replay mapping file (TOML): which recorded stream becomes which fednav sensor, and how.

fednav's conventions (docs/DESIGN.md, service/messages.py): body frame right-forward-up (RFU),
navigation frame ENU, time ``t`` in seconds of GPS time since 1980-01-06, angles in rad on the
IMU wire (increments), specific force in m/s (increments). A stream states how its source
differs: body axes, units, rate or increment form, time base and leap seconds.

Axes: three letters naming where the source's x, y, z axes point on the vehicle, each one of
F(orward)/B(ack), R(ight)/L(eft), U(p)/D(own): ``FLU`` (ROS REP-103), ``FRD`` (aerospace,
u-blox), ``RFU`` (fednav itself); or a 3x3 matrix ``M`` with ``v_rfu = M @ v_source``.

Time bases (``t_gps = convert(stamp) + time_offset_s``):
- ``gps``: seconds since the GPS epoch 1980-01-06, GPS time scale (no leap seconds);
- ``unix``: POSIX seconds since 1970-01-01 in UTC (ROS header stamps, most loggers):
  ``t_gps = stamp - 315964800 + leap_seconds``;
- ``utc``: calendar UTC (NMEA's date and time of day); numeric stamps are read as POSIX UTC;
- ``boot``: seconds since the device booted; ``boot_offset_s`` is the GPS time of boot zero, or
  ``"auto"``: derived before the checks (replay/checks.py ``resolve_boot_offsets``) from a stream
  that carries both clocks (a ROS bag's receive times beside the header stamps; NMEA lines that
  start with the logger's own stamp), else from the first fix, then refined by the IMU's yaw rate
  against the GNSS course rate; the derived value is printed so that it can be written in.

Formats from the source's name (``format`` overrides): ``.nmea``, ``.ubx``, ``.csv``; ``.obs``,
``.rnx``, ``.YYo`` RINEX; ``.bag``, ``.mcap``, ``.db3`` and a name without an extension (a ROS 2 bag
directory) ROS. Any other extension is refused, asking for ``format``; a ``.gz`` file is refused
whatever the format (no reader decompresses: gunzip it first).

Misplaced fields are named as such: in TOML every key after a ``[[streams]]`` header belongs to
that stream, so ``leap_seconds`` written there is told to move above the first ``[[streams]]``.
"""

from __future__ import annotations

import re
import tomllib
import typing
from pathlib import Path
from typing import Literal

import numpy as np
from pydantic import BaseModel, ConfigDict, Field, ValidationError, field_validator, model_validator

from fednav.service.validation_errors import format_errors, suggest

GPS_EPOCH_UNIX_S = 315964800.0  # 1980-01-06T00:00:00Z as POSIX seconds
LEAP_SECONDS_NOW = 18  # GPS - UTC since 2017-01-01 (IERS Bulletin C); older logs need their value
G0_MPS2 = 9.80665  # standard gravity, the "g" of accelerometer datasheets

_AXIS = {
    "R": (1.0, 0.0, 0.0),
    "L": (-1.0, 0.0, 0.0),
    "F": (0.0, 1.0, 0.0),
    "B": (0.0, -1.0, 0.0),
    "U": (0.0, 0.0, 1.0),
    "D": (0.0, 0.0, -1.0),
}

Format = Literal["ros", "nmea", "ubx", "csv", "rinex"]
TimeBase = Literal["gps", "unix", "utc", "boot"]
#: a source's extension -> its format (a name without an extension: a ROS 2 bag directory)
EXTENSIONS: dict[str, Format] = {
    ".nmea": "nmea",
    ".ubx": "ubx",
    ".csv": "csv",
    ".bag": "ros",
    ".mcap": "ros",
    ".db3": "ros",
    ".obs": "rinex",
    ".rnx": "rinex",
}
_RINEX2_OBS = re.compile(r"\.\d\d[o]")  # RINEX 2 observation file: .19o
#: Zenoh endpoint ``<protocol>/<address>`` (tcp/127.0.0.1:7447, udp/..., tls/..., unixsock-stream/...)
ENDPOINT_RE = r"^[a-z][a-z0-9\-]*/\S+$"
#: receive stamps written in front of NMEA lines: their unit
RECEIVE_UNITS = {"s": 1.0, "ms": 1e-3, "us": 1e-6, "ns": 1e-9}


class MappingError(ValueError):
    pass


def gzipped(name: str) -> str:
    """The message refusing a ``.gz`` file (no reader decompresses)."""
    return f"{name} is compressed with gzip: decompress it first (gunzip {name})"


def axes_matrix(axes: str | list[list[float]]) -> np.ndarray:
    """Rotation ``M`` with ``v_rfu = M @ v_source`` from a three-letter name or a 3x3 matrix.

    Raises ValueError naming what is wrong (unknown letter, an axis twice, left-handed)."""
    if isinstance(axes, str):
        name = axes.upper()
        if len(name) != 3 or any(c not in _AXIS for c in name):
            raise ValueError(
                f"axes {axes!r}: use three letters from F/B, R/L, U/D (e.g. FLU, FRD) or a matrix"
            )
        m = np.array([_AXIS[c] for c in name]).T  # column i: where source axis i points in RFU
        if abs(abs(np.linalg.det(m)) - 1.0) > 1e-9:
            raise ValueError(f"axes {axes!r}: each of forward/back, right/left, up/down must appear once")
    else:
        m = np.asarray(axes, dtype=float)
        if m.shape != (3, 3) or not np.all(np.isfinite(m)):
            raise ValueError("axes matrix must be 3x3 and finite")
        if np.max(np.abs(m @ m.T - np.eye(3))) > 1e-6:
            raise ValueError("axes matrix is not orthonormal (rows/columns must be unit and orthogonal)")
    if np.linalg.det(m) < 0:
        raise ValueError(f"axes {axes!r} form a left-handed frame: one axis sign is wrong")
    return m


def axes_name(m: np.ndarray) -> str | None:
    """The three-letter name of an axis-permutation matrix, None for a general rotation."""
    out = []
    for i in range(3):
        col = tuple(float(x) for x in np.round(m[:, i], 9))
        hit = [k for k, v in _AXIS.items() if v == col]
        if not hit:
            return None
        out.append(hit[0])
    return "".join(out)


class _Model(BaseModel):
    model_config = ConfigDict(extra="forbid", frozen=True)


class RinexOptions(_Model):
    """A RINEX stream's ``rinex_options``: the keyword options of
    ``simulators.gnss.rinex_raw.iter_gnss_raw`` (its documentation; tests/test_replay_mapping_user.py
    holds these to its signature). An option left out keeps iter_gnss_raw's default."""

    systems: list[Literal["G", "E", "C"]] | None = Field(
        None, min_length=1, description="System letters converted: G GPS, E Galileo, C BeiDou (G, E, C)"
    )
    pseudorange_sigma_m: float | None = Field(
        None, gt=0, allow_inf_nan=False, description="Zenith 1-sigma pseudorange noise, m (3.0)"
    )
    range_rate_sigma_mps: float | None = Field(
        None, gt=0, allow_inf_nan=False, description="Zenith 1-sigma range-rate noise, m/s (0.1)"
    )
    start_gps_s: float | None = Field(None, allow_inf_nan=False, description="First epoch converted, GPS s")
    stop_gps_s: float | None = Field(None, allow_inf_nan=False, description="Last epoch converted, GPS s")
    max_age_s: float | None = Field(
        None, gt=0, allow_inf_nan=False, description="Oldest ephemeris used, s from its reference time"
    )

    @model_validator(mode="before")
    @classmethod
    def _known(cls, data):
        if isinstance(data, dict):
            for k in data:
                if k not in cls.model_fields:
                    raise ValueError(
                        f"unknown option {k!r}{suggest(k, cls.model_fields)}; the options are "
                        f"{', '.join(cls.model_fields)}"
                    )
        return data

    def kwargs(self) -> dict:
        """The options set, as iter_gnss_raw's keyword arguments."""
        return self.model_dump(exclude_none=True)


class StreamMapping(_Model):
    """One recorded stream -> one fednav sensor."""

    source: str = Field(
        description="File (path relative to the mapping file): bag dir/.bag/.mcap/.db3, .nmea, .ubx, .csv, "
        "RINEX .obs/.rnx/.YYo"
    )
    format: Format | None = Field(None, description="Parser; None: from the file name (module doc)")
    kind: str = Field(
        description="fednav sensor kind it becomes: imu, gnss_fix, gnss_raw, or a kind of the sensor "
        "registry with a CSV hook (e.g. baro: columns t, altitude_m[, std_m])"
    )
    sensor_id: str = Field(pattern=r"^[A-Za-z0-9_\-.]+$", description="Sensor id in the key")
    topic: str | None = Field(None, description="ROS: topic of sensor_msgs/Imu or sensor_msgs/NavSatFix")
    twist_topic: str | None = Field(
        None, description="ROS: geometry_msgs/TwistWithCovarianceStamped topic giving the fix velocity"
    )
    twist_frame: Literal["ENU", "NED"] = Field("ENU", description="Frame of the twist's linear velocity")
    sentences: list[Literal["GGA", "RMC", "GST", "VTG"]] = Field(
        default_factory=lambda: ["GGA", "RMC", "GST", "VTG"], description="NMEA sentence types used"
    )
    date: str | None = Field(None, description="NMEA: UTC date YYYY-MM-DD when the log has no RMC")
    axes: str | list[list[float]] = Field(
        "FLU", description="Source body axes (letters) or 3x3 matrix to RFU"
    )
    gyro_unit: Literal["rad/s", "deg/s"] = Field(
        "rad/s", description="Gyro unit (increment form: rad or deg)"
    )
    accel_unit: Literal["m/s^2", "g"] = Field(
        "m/s^2", description="Accelerometer unit (increment: m/s or g*s)"
    )
    form: Literal["rate", "increment"] = Field("rate", description="Rates (rad/s, m/s^2) or increments")
    time_base: TimeBase = Field("unix", description="gps | unix | utc | boot (see module doc)")
    boot_offset_s: float | Literal["auto"] | None = Field(
        None,
        description="boot: GPS time (s) of the device's boot zero, or 'auto' (derived from the log and "
        "printed: a stream carrying both clocks, else the first fix; refined by the motion)",
    )
    receive_unit: Literal["s", "ms", "us", "ns"] = Field(
        "s",
        description="NMEA: unit of the logger's receive stamp written in front of each line "
        "('12345.678,$GPGGA,...'), in the clock of the IMU stamped in 'boot' time",
    )
    time_offset_s: float = Field(0.0, description="Added to every converted stamp, s")
    tick_s: float | None = Field(
        None,
        gt=0,
        allow_inf_nan=False,
        description="Seconds per unit of the source's stamps: UBX ESF-RAW, one sensor time-tag tick "
        "(receiver manual); a CSV, its t and dt column's unit (0.001 for milliseconds)",
    )
    rinex_options: RinexOptions = Field(
        default_factory=RinexOptions, description="RINEX: keyword options passed to iter_gnss_raw"
    )
    pos_std_m: tuple[float, float, float] | None = Field(
        None,
        description="Fix position 1-sigma E/N/U, m, where the source gives none "
        "(None: GnssFix's documented defaults from fix type and HDOP)",
    )
    vel_std_mps: tuple[float, float, float] | None = Field(
        None,
        description="Fix velocity 1-sigma E/N/U, m/s, where the source gives none (NMEA: the first "
        "value is the speed sigma; None: GnssFix's documented default for the fix type)",
    )

    @field_validator("axes")
    @classmethod
    def _axes(cls, v):
        axes_matrix(v)
        return v

    @field_validator("pos_std_m", "vel_std_mps")
    @classmethod
    def _positive(cls, v):
        if v is not None and not all(x > 0 for x in v):
            raise ValueError("every sigma must be > 0")
        return v

    @model_validator(mode="after")
    def _consistent(self):
        if self.source.lower().endswith(".gz"):
            raise ValueError(gzipped(self.source))
        fmt = self.resolved_format()
        if self.time_base == "boot" and self.boot_offset_s is None:
            raise ValueError(
                "time_base 'boot' needs boot_offset_s: the GPS time of the device's boot zero, or 'auto' "
                "to derive it from the log (printed by the checks)"
            )
        if self.time_base != "boot" and self.boot_offset_s is not None:
            raise ValueError(
                f"boot_offset_s applies to time_base 'boot' only (this stream's is {self.time_base!r}): "
                "remove it, or set time_base = 'boot'"
            )
        if fmt == "ros" and not self.topic:
            taken = ""
            if not self.format and not Path(self.source).suffix:
                taken = (
                    f" ({self.source} has no extension: it is read as a ROS 2 bag directory; if it is not "
                    "one, set format)"
                )
            raise ValueError(f"a ROS bag/MCAP stream needs 'topic'{taken}")
        if fmt == "nmea" and self.kind != "gnss_fix":
            raise ValueError("NMEA gives GNSS fixes: kind must be 'gnss_fix'")
        if fmt == "nmea" and self.time_base != "utc":
            raise ValueError("NMEA time is UTC: time_base must be 'utc'")
        from fednav.service import sensors

        csv_kinds = ["imu", *sensors.csv_kinds()]
        if self.kind not in ("imu", "gnss_fix", "gnss_raw", *csv_kinds):
            raise ValueError(
                f"kind {self.kind!r} is not one fednav-replay reads: imu, gnss_fix, gnss_raw, or (CSV) "
                f"{', '.join(sensors.csv_kinds())}"
            )
        if fmt == "csv" and self.kind not in csv_kinds:
            raise ValueError(f"the CSV format is for these kinds: {', '.join(csv_kinds)}")
        if fmt != "csv" and self.kind in sensors.csv_kinds():
            raise ValueError(f"kind {self.kind!r} comes from a CSV file (format 'csv')")
        if fmt == "rinex" and self.kind != "gnss_raw":
            raise ValueError("RINEX gives raw GNSS: kind must be 'gnss_raw'")
        if self.kind == "gnss_raw" and fmt != "rinex":
            raise ValueError("kind 'gnss_raw' comes from RINEX (format 'rinex')")
        return self

    def resolved_format(self) -> Format:
        """``format``, else the one the source's extension names (ValueError for an unknown one)."""
        if self.format:
            return self.format
        suffix = Path(self.source.lower()).suffix
        if suffix in EXTENSIONS:
            return EXTENSIONS[suffix]
        if _RINEX2_OBS.fullmatch(suffix):
            return "rinex"
        if not suffix:
            return "ros"  # a ROS 2 bag directory
        formats = ", ".join(repr(f) for f in typing.get_args(Format))
        raise ValueError(
            f"cannot tell the format of {self.source} from its extension: set format = one of {formats} "
            f"(known extensions: {', '.join(EXTENSIONS)}, .YYo; no extension: a ROS 2 bag directory)"
        )

    def matrix(self) -> np.ndarray:
        return axes_matrix(self.axes)

    def gyro_scale(self) -> float:
        return np.pi / 180.0 if self.gyro_unit == "deg/s" else 1.0

    def accel_scale(self) -> float:
        return G0_MPS2 if self.accel_unit == "g" else 1.0


class ReplayMapping(_Model):
    """A replay: the vehicle, the key prefix, leap seconds, the service's endpoint and the streams."""

    vehicle: str = Field("v1", pattern=r"^[A-Za-z0-9_\-.]+$", description="Vehicle name in the keys")
    prefix: str = Field("fednav", description="Key prefix (the service's 'prefix')")
    endpoint: str | None = Field(
        None,
        pattern=ENDPOINT_RE,
        description="Zenoh endpoint of the service to connect to, e.g. 'tcp/127.0.0.1:7447' (--connect "
        "overrides it; None: the publisher's default, tcp/127.0.0.1:7447)",
    )
    leap_seconds: int = Field(LEAP_SECONDS_NOW, ge=0, le=60, description="GPS - UTC at the log's date, s")
    rinex_nav: list[str] = Field(default_factory=list, description="RINEX navigation files (gnss_raw)")
    streams: list[StreamMapping] = Field(min_length=1)

    @field_validator("rinex_nav")
    @classmethod
    def _not_gzip(cls, v):
        for p in v:
            if p.lower().endswith(".gz"):
                raise ValueError(gzipped(p))
        return v

    @model_validator(mode="after")
    def _unique(self):
        seen = set()
        for s in self.streams:
            k = (s.kind, s.sensor_id)
            if k in seen:
                raise ValueError(
                    f"two streams publish {s.kind} sensor {s.sensor_id!r}: give them different ids"
                )
            seen.add(k)
        return self


def to_gps_s(stamp: float, stream: StreamMapping, leap_seconds: int) -> float:
    """A source stamp (seconds in the stream's time base) -> GPS seconds since 1980-01-06."""
    if stream.time_base == "gps":
        t = stamp
    elif stream.time_base in ("unix", "utc"):
        t = stamp - GPS_EPOCH_UNIX_S + leap_seconds
    else:  # boot
        if not isinstance(stream.boot_offset_s, float | int):
            raise ValueError(
                f"stream {stream.sensor_id!r}: boot_offset_s = 'auto' is resolved by the checks "
                "(replay.checks.resolve_boot_offsets) before the stream is read"
            )
        t = stamp + float(stream.boot_offset_s)
    return t + stream.time_offset_s


def from_gps_s(t_gps: float, stream: StreamMapping, leap_seconds: int) -> float:
    """The inverse of :func:`to_gps_s`: the stamp as written in the source (for messages)."""
    t = t_gps - stream.time_offset_s
    if stream.time_base in ("unix", "utc"):
        return t + GPS_EPOCH_UNIX_S - leap_seconds
    if stream.time_base == "boot" and isinstance(stream.boot_offset_s, float | int):
        return t - float(stream.boot_offset_s)
    return t


def with_stream(mapping: ReplayMapping, index: int, **changes) -> ReplayMapping:
    """A copy of the mapping with stream ``index`` changed (validated again)."""
    streams = list(mapping.streams)
    streams[index] = StreamMapping.model_validate({**streams[index].model_dump(), **changes})
    return ReplayMapping.model_validate(
        {**mapping.model_dump(), "streams": [s.model_dump() for s in streams]}
    )


def load_mapping(path: Path | str) -> tuple[ReplayMapping, Path]:
    """Read and validate a mapping file; returns it and its directory (sources are relative to it)."""
    path = Path(path)
    try:
        data = tomllib.loads(path.read_text())
    except (OSError, tomllib.TOMLDecodeError) as exc:
        raise MappingError(f"cannot read {path}: {exc}") from None
    return from_dict(data, str(path)), path.resolve().parent


def misplaced_fields(data: dict) -> list[str]:
    """Lines naming fields written at the wrong level: a top-level field inside a stream (in TOML
    every key after a ``[[streams]]`` header belongs to that stream) or a stream field at the top."""
    top = set(ReplayMapping.model_fields) - {"streams"}
    per_stream = set(StreamMapping.model_fields)
    out = []
    streams = data.get("streams")
    for i, st in enumerate(streams if isinstance(streams, list) else []):
        if not isinstance(st, dict):
            continue
        for k in st:
            if k in top and k not in per_stream:
                out.append(
                    f"  streams.{i}.{k}: '{k}' is a top-level field of the mapping (it applies to every "
                    f"stream), not a stream's: move the line '{k} = ...' above the first [[streams]] "
                    "(in TOML every key after a [[streams]] header belongs to that stream)"
                )
    for k in data:
        if k in per_stream and k not in top:
            out.append(
                f"  {k}: '{k}' is a field of a stream: move it into the [[streams]] table it describes"
            )
    return out


def from_dict(data: dict, source: str = "<dict>") -> ReplayMapping:
    heading = f"invalid mapping in {source}:"
    misplaced = misplaced_fields(data) if isinstance(data, dict) else []
    if misplaced:
        raise MappingError("\n".join([heading, *misplaced]))
    try:
        return ReplayMapping.model_validate(data)
    except ValidationError as err:
        raise MappingError(format_errors(err, ReplayMapping, heading)) from None
