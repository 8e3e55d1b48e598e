"""Key expressions of the wire contract (docs/DESIGN.md): builders and a parser.

{prefix}/{vehicle}/sensor/imu/{id}            ImuSample
{prefix}/{vehicle}/sensor/gnss/{id}/fix       GnssFix
{prefix}/{vehicle}/sensor/gnss/{id}/raw       GnssRaw
{prefix}/{vehicle}/sensor/star/{id}           StarAttitude
{prefix}/{vehicle}/sensor/dvl/{id}            DvlVelocity
{prefix}/{vehicle}/sensor/usbl/{id}           UsblFix
{prefix}/{vehicle}/sensor/init                InitialNav
{prefix}/{vehicle}/truth                      Truth
{prefix}/{vehicle}/truth/alignment/{node}     AlignmentTruth (seed 002 simulators)
{prefix}/{vehicle}/nav/{pipeline}/solution    Solution
{prefix}/{vehicle}/nav/{pipeline}/faults      Faults
{prefix}/{vehicle}/nav/{pipeline}/integrity   Integrity
{prefix}/{vehicle}/nav/{pipeline}/alignment/{node}  Alignment (transfer alignment, seed 002)
{prefix}/{vehicle}/nav/{pipeline}/models      ImmModels
{prefix}/{vehicle}/service/health             Health
{prefix}/{vehicle}/service/status             queryable (and .../service/config)
{prefix}/{vehicle}/nav/{pipeline}/solution    also a queryable: the latest Solution
{prefix}/{vehicle}/service/alive              liveliness token of each served vehicle
{prefix}/_services/{zenoh id}                 liveliness token of each running service
{prefix}/_services/{zenoh id}/health          ServiceHealth (refused before routing, unserved names)
"""

from __future__ import annotations

import re
from dataclasses import dataclass

DEFAULT_PREFIX = "fednav"
_CHUNK = re.compile(r"^[A-Za-z0-9_\-.]+$")


MAX_NAME_LEN = 64


def valid_name(name: str) -> bool:
    """A vehicle, sensor or pipeline name usable as one key chunk and one recording path part."""
    return 0 < len(name) <= MAX_NAME_LEN and bool(_CHUNK.match(name))


def _chunk(name: str, what: str) -> str:
    if not _CHUNK.match(name):
        raise ValueError(f"invalid {what} {name!r}: use letters, digits, '_', '-', '.'")
    return name


def sensor(vehicle: str, kind: str, sensor_id: str, prefix: str = DEFAULT_PREFIX) -> str:
    """Key of a sensor stream. ``kind`` is one of imu, gnss_fix, gnss_raw, star, dvl, usbl."""
    v, s = _chunk(vehicle, "vehicle"), _chunk(sensor_id, "sensor id")
    if kind == "gnss_fix":
        return f"{prefix}/{v}/sensor/gnss/{s}/fix"
    if kind == "gnss_raw":
        return f"{prefix}/{v}/sensor/gnss/{s}/raw"
    if kind in ("imu", "star", "dvl", "usbl"):
        return f"{prefix}/{v}/sensor/{kind}/{s}"
    raise ValueError(f"unknown sensor kind {kind!r}")


def init(vehicle: str, prefix: str = DEFAULT_PREFIX) -> str:
    return f"{prefix}/{_chunk(vehicle, 'vehicle')}/sensor/init"


def truth(vehicle: str, prefix: str = DEFAULT_PREFIX) -> str:
    return f"{prefix}/{_chunk(vehicle, 'vehicle')}/truth"


def alignment_truth(vehicle: str, node: str, prefix: str = DEFAULT_PREFIX) -> str:
    return f"{prefix}/{_chunk(vehicle, 'vehicle')}/truth/alignment/{_chunk(node, 'node')}"


def nav(vehicle: str, pipeline: str, what: str, prefix: str = DEFAULT_PREFIX) -> str:
    if what not in ("solution", "faults", "integrity", "models"):
        raise ValueError(f"unknown nav output {what!r}")
    return f"{prefix}/{_chunk(vehicle, 'vehicle')}/nav/{_chunk(pipeline, 'pipeline')}/{what}"


def alignment(vehicle: str, pipeline: str, node: str, prefix: str = DEFAULT_PREFIX) -> str:
    """Key of a transfer-alignment node output (seed 002)."""
    v, p, n = _chunk(vehicle, "vehicle"), _chunk(pipeline, "pipeline"), _chunk(node, "node")
    return f"{prefix}/{v}/nav/{p}/alignment/{n}"


def service(vehicle: str, what: str, prefix: str = DEFAULT_PREFIX) -> str:
    if what not in ("health", "status", "config", "alive"):
        raise ValueError(f"unknown service key {what!r}")
    return f"{prefix}/{_chunk(vehicle, 'vehicle')}/service/{what}"


def service_token(instance: str, prefix: str = DEFAULT_PREFIX) -> str:
    """Liveliness token of one running service instance (its Zenoh id)."""
    return f"{prefix}/_services/{_chunk(instance, 'service instance')}"


def service_health(instance: str, prefix: str = DEFAULT_PREFIX) -> str:
    """Key of one running service's ServiceHealth."""
    return f"{service_token(instance, prefix)}/health"


def inputs_selector(vehicles: str = "*", prefix: str = DEFAULT_PREFIX) -> list[str]:
    """Key expression the service subscribes to for a vehicle selector (``*`` = all vehicles).

    One expression per vehicle selector, so one Zenoh channel keeps the arrival order of a
    vehicle's sensors *and* truth (two subscriptions would be two channels, drained in turn).
    Outputs under the same prefix (``nav/``, ``service/``) are recognised by :func:`is_output`.
    """
    return [f"{prefix}/{vehicles}/**"]


def is_output(key: str, prefix: str = DEFAULT_PREFIX) -> bool:
    """True for keys a fednav service publishes (nav/..., service/...), not inputs."""
    parts = key.split("/")
    if len(parts) >= 2 and parts[0] == prefix and parts[1] == "_services":
        return True  # service tokens and ServiceHealth
    return len(parts) >= 3 and parts[0] == prefix and parts[2] in ("nav", "service")


@dataclass(frozen=True)
class ParsedKey:
    vehicle: str
    kind: str  # imu, gnss_fix, gnss_raw, star, dvl, usbl, init, truth, alignment_truth
    sensor_id: str  # "" for init/truth


def parse_input(key: str, prefix: str = DEFAULT_PREFIX) -> ParsedKey | None:
    """Parse an input key; None when it is not a known input key (counted as ``unknown_key``)."""
    parts = key.split("/")
    if len(parts) < 3 or parts[0] != prefix:
        return None
    vehicle, rest = parts[1], parts[2:]
    if rest == ["truth"]:
        return ParsedKey(vehicle, "truth", "")
    if len(rest) == 3 and rest[:2] == ["truth", "alignment"]:
        return ParsedKey(vehicle, "alignment_truth", rest[2])
    if not rest or rest[0] != "sensor":
        return None
    rest = rest[1:]
    if rest == ["init"]:
        return ParsedKey(vehicle, "init", "")
    if len(rest) == 2 and rest[0] in ("imu", "star", "dvl", "usbl"):
        return ParsedKey(vehicle, rest[0], rest[1])
    if len(rest) == 3 and rest[0] == "gnss" and rest[2] in ("fix", "raw"):
        return ParsedKey(vehicle, "gnss_" + rest[2], rest[1])
    return None
