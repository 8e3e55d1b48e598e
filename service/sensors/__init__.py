"""The sensor registry: everything fednav knows about a kind of sensor, in one entry.

Per kind (``imu``, ``gnss_fix``, ``gnss_raw``, ``star``, ``dvl``, ``usbl``, ``baro``): its wire
message model, its key chunk under ``{prefix}/{vehicle}/sensor/``, its decoders (JSON through the
message model; a binary batch for the IMU; ROS 2 message types decoded straight into the message
model), its measurement model (what pipelines use), and its hooks for the simulators (a scenario
table ``[sensors.<kind>]``) and for fednav-replay (CSV columns). Everything else asks this
registry: key building and parsing (:mod:`service.keys`), the service's decoder choice
(:mod:`service.vehicle`), the models pipelines build (:mod:`service.estimation.measurements`), the
configuration's sensor lists, the simulators' extra sensors, fednav-replay's CSV streams and the
ROS 2 bridge's extra inputs.

Adding a sensor is one file (its message, model and hooks, e.g. :mod:`service.sensors.baro`) and
one entry in :data:`REGISTRY` (docs/ARCHITECTURE.md "How to add a sensor").
"""

from __future__ import annotations

from collections.abc import Callable, Mapping
from dataclasses import dataclass, field
from typing import Any

from fednav.service.messages import WireModel

ID = "{id}"


@dataclass(frozen=True)
class SensorKind:
    """One kind of sensor.

    kind
        Its name in configurations, Health and the engine (``gnss_fix``).
    message
        The wire model of one measurement (validated on arrival).
    key
        Its key chunks under ``{prefix}/{vehicle}/sensor/``, with ``{id}`` for the sensor id,
        e.g. ``("gnss", "{id}", "fix")``.
    model
        Measurement model factory (keyword options from the pipeline's configuration, see
        :mod:`service.estimation.measurements.base`); None for the IMU, which drives time.
    options
        A pydantic model of the model's options in a pipeline's ``sensor_options`` table (None:
        the model takes none there).
    batch
        A decoder of a binary batch payload, ``(payload) -> rows`` (the IMU's ImuBatch).
    ros2
        ROS 2 message type -> ``decode(msg, t, sensor_id) -> WireModel | None``: the message
        decoded straight into the wire model (``t``: its header stamp in GPS seconds).
    simulate
        ``(spec, trajectory, rng) -> [(imu_index, message), ...]`` for a scenario's
        ``[sensors.<kind>]`` table, ``spec`` validated by ``simulate_spec``.
    csv_columns / csv_optional / from_csv
        fednav-replay CSV streams of this kind: the columns (time first; those in ``csv_optional``
        may be absent) and ``(row: dict[str, float | None], sensor_id) -> WireModel`` (time
        already in GPS seconds).
    discovery
        Whether its messages announce a vehicle to the members of a fleet that subscribe per
        vehicle they own (``[intake] subscribe = 'owned'``): every member subscribes to these keys
        of every vehicle, so keep it for low-rate kinds (a few tens of messages a second at
        most); the IMU, which drives time at hundreds of hertz, is heard only by its owner.
    """

    kind: str
    message: type[WireModel]
    key: tuple[str, ...]
    model: Callable[..., Any] | None = None
    options: type | None = None
    batch: Callable[[bytes], Any] | None = None
    ros2: Mapping[str, Callable[..., WireModel | None]] = field(default_factory=dict)
    simulate: Callable[..., list] | None = None
    simulate_spec: type | None = None
    csv_columns: tuple[str, ...] = ()
    csv_optional: tuple[str, ...] = ()
    from_csv: Callable[..., WireModel] | None = None
    doc: str = ""
    discovery: bool = True

    def key_suffix(self, sensor_id: str) -> str:
        """Key chunks after ``{vehicle}/sensor/`` for ``sensor_id``."""
        return "/".join(sensor_id if c == ID else c for c in self.key)


def _builtin() -> dict[str, SensorKind]:
    from fednav.service import imu_batch
    from fednav.service.estimation.measurements.dvl import DvlModel
    from fednav.service.estimation.measurements.gnss_fix import GnssFixModel
    from fednav.service.estimation.measurements.gnss_raw import GnssRawModel
    from fednav.service.estimation.measurements.star import StarAttitudeModel
    from fednav.service.estimation.measurements.usbl import UsblModel
    from fednav.service.messages import DvlVelocity, GnssFix, GnssRaw, ImuSample, StarAttitude, UsblFix

    return {
        "imu": SensorKind(
            "imu",
            ImuSample,
            ("imu", ID),
            batch=imu_batch.decode,
            doc="angle/velocity increments",
            discovery=False,
        ),
        "gnss_fix": SensorKind("gnss_fix", GnssFix, ("gnss", ID, "fix"), GnssFixModel, doc="GNSS fixes"),
        "gnss_raw": SensorKind("gnss_raw", GnssRaw, ("gnss", ID, "raw"), GnssRawModel, doc="pseudoranges"),
        "star": SensorKind("star", StarAttitude, ("star", ID), StarAttitudeModel, doc="star tracker"),
        "dvl": SensorKind("dvl", DvlVelocity, ("dvl", ID), DvlModel, doc="Doppler velocity log"),
        "usbl": SensorKind("usbl", UsblFix, ("usbl", ID), UsblModel, doc="USBL acoustic fixes"),
        # a sensor in a file of its own: its module's SENSOR
        "baro": entry("baro"),
    }


def entry(module: str) -> SensorKind:
    """The ``SENSOR`` of ``service/sensors/<module>.py`` (a sensor defined in one file)."""
    import importlib

    return importlib.import_module(f"fednav.service.sensors.{module}").SENSOR


#: kind -> its entry (built on first use: the entries import the measurement models)
REGISTRY: dict[str, SensorKind] = {}


def registry() -> dict[str, SensorKind]:
    if not REGISTRY:
        REGISTRY.update(_builtin())
    return REGISTRY


def get(kind: str) -> SensorKind:
    """The entry of ``kind`` (``KeyError`` naming the known kinds)."""
    reg = registry()
    try:
        return reg[kind]
    except KeyError:
        raise KeyError(f"unknown sensor kind {kind!r}; known: {sorted(reg)}") from None


def kinds() -> list[str]:
    return list(registry())


def model_kinds() -> list[str]:
    """Kinds with a measurement model (what pipelines can be configured with)."""
    return [k for k, s in registry().items() if s.model is not None]


def discovery_keys() -> list[str]:
    """Key chunks after ``{vehicle}/sensor/`` of every kind that announces a vehicle
    (``discovery``), sensor ids as ``*``."""
    return ["/".join("*" if c == ID else c for c in s.key) for s in registry().values() if s.discovery]


def parse_key(chunks: list[str]) -> tuple[str, str] | None:
    """(kind, sensor id) of the key chunks after ``{vehicle}/sensor/``; None when no kind matches."""
    for s in registry().values():
        if len(s.key) != len(chunks):
            continue
        sid = None
        for pat, c in zip(s.key, chunks, strict=True):
            if pat == ID:
                sid = c
            elif pat != c:
                break
        else:
            if sid is not None:
                return s.kind, sid
    return None


def input_message(kind: str) -> type[WireModel] | None:
    """The wire model of an input kind: a sensor, or ``init``/``truth``/``alignment_truth``."""
    s = REGISTRY.get(kind) or registry().get(kind)  # (every message asks: no import per call)
    if s is not None:
        return s.message
    from fednav.service.messages import CONTROL_MESSAGES

    return CONTROL_MESSAGES.get(kind)


def csv_kinds() -> list[str]:
    """Kinds fednav-replay reads from a CSV file through their registry hook (beyond the IMU's)."""
    return [k for k, s in registry().items() if s.from_csv is not None]


def ros2_decoder(msgtype: str) -> tuple[str, Callable] | None:
    """(kind, decoder) of a ROS 2 message type an entry decodes (beyond the bridge's own Imu,
    NavSatFix and Twist), else None."""
    for s in registry().values():
        if msgtype in s.ros2:
            return s.kind, s.ros2[msgtype]
    return None


__all__ = [
    "REGISTRY",
    "SensorKind",
    "get",
    "input_message",
    "kinds",
    "model_kinds",
    "parse_key",
    "registry",
    "ros2_decoder",
]
