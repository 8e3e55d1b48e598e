"""ROS 1 bags, ROS 2 bags (sqlite3 or MCAP storage) and bare MCAP files, read with ``rosbags``
(its AnyReader picks the container, its type store decodes the messages: no ROS install).

Topics: sensor_msgs/Imu (rates: angular_velocity rad/s, linear_acceleration m/s^2, in the frame
the mapping's ``axes`` names; REP-103 says FLU), sensor_msgs/NavSatFix (latitude/longitude deg,
altitude m above the WGS-84 ellipsoid, position_covariance ENU m^2) paired with
geometry_msgs/TwistWithCovarianceStamped on ``twist_topic`` (linear velocity in ``twist_frame``,
ENU or NED) when there is one within 0.05 s: a 3-D velocity fix; a NavSatFix without a Twist
(no ``twist_topic``, or none near its stamp: counted as ``no_velocity``) is published as a
position-only fix, never with an invented velocity. Stamps are the message headers' (sensor
time), not the bag's receive time; an IMU stamped in ``boot`` time keeps (header stamp, receive
time as GPS seconds) pairs in ``stats["_clock_pairs"]`` (every 10th message), from which the
checks derive ``boot_offset_s = "auto"``. Where each fix's sigmas came from is counted in
``stats`` (``sigma_pos:covariance|mapping|default``, ``sigma_vel:...``). An Imu marked as carrying
no angular velocity or no acceleration (element 0 of that covariance -1: an orientation-only
driver) is skipped and counted ``no_rates``.
"""

from __future__ import annotations

from collections.abc import Iterator
from pathlib import Path

import numpy as np

from .events import Event, ImuBuilder, count, gnss_fix_to_wire, key_suffix
from .mapping import GPS_EPOCH_UNIX_S, ReplayMapping, StreamMapping, to_gps_s

IMU_TYPES = ("sensor_msgs/msg/Imu",)
FIX_TYPES = ("sensor_msgs/msg/NavSatFix",)
TWIST_TYPES = ("geometry_msgs/msg/TwistWithCovarianceStamped",)
TWIST_MATCH_S = 0.05  # a twist is paired with a fix whose stamp is within this, s
#: NavSatStatus.status -> GnssFix.fix_type (STATUS_FIX 0, STATUS_SBAS_FIX 1, STATUS_GBAS_FIX 2)
NAVSAT_FIX_TYPE = {0: "single", 1: "sbas", 2: "dgnss"}


#: what rosbags reads: a ROS 1 bag, a ROS 2 storage file, or a ROS 2 bag directory (metadata.yaml)
BAG_SUFFIXES = (".bag", ".db3", ".mcap")
#: first bytes that name another format, for the message refusing a file that is no bag
MAGIC = (
    (b"$", "NMEA text (it starts with '$'): set format = 'nmea'"),
    (b"\xb5\x62", "u-blox UBX (it starts with b5 62): set format = 'ubx'"),
)


class SourceError(ValueError):
    pass


def _not_a_bag(path: Path) -> str | None:
    """Why ``path`` is no ROS bag rosbags reads, or None."""
    if path.is_dir():
        if (path / "metadata.yaml").exists():
            return None
        return f"{path}: a directory without metadata.yaml, so no ROS 2 bag"
    if path.suffix.lower() in BAG_SUFFIXES:
        return None
    with path.open("rb") as f:
        head = f.read(2)
    hint = next((h for magic, h in MAGIC if head.startswith(magic)), "set the stream's format")
    return f"{path}: not a ROS bag (a bag directory with metadata.yaml, or a .bag, .db3, .mcap file): {hint}"


def no_rates(msg) -> bool:
    """An Imu whose driver marks its rates or accelerations "no estimate" (element 0 of the
    covariance -1, sensor_msgs/Imu's convention): an orientation-only message, its zeros no data."""
    return (
        float(msg.angular_velocity_covariance[0]) == -1.0
        or float(msg.linear_acceleration_covariance[0]) == -1.0
    )


def _stamp(msg) -> float:
    return msg.header.stamp.sec + msg.header.stamp.nanosec * 1e-9


def _read(path: Path, topic: str):
    from rosbags.highlevel import AnyReader
    from rosbags.typesys import Stores, get_typestore

    with AnyReader([path], default_typestore=get_typestore(Stores.ROS2_HUMBLE)) as reader:
        conns = [c for c in reader.connections if c.topic == topic]
        if not conns:
            have = sorted({f"{c.topic} ({c.msgtype})" for c in reader.connections})
            raise SourceError(f"{path}: no topic {topic!r}; the file has: {', '.join(have) or 'nothing'}")
        for con, t_ns, raw in reader.messages(connections=conns):
            yield con.msgtype, reader.deserialize(raw, con.msgtype), t_ns


def events(
    stream: StreamMapping, base: Path, mapping: ReplayMapping, stats: dict | None = None
) -> Iterator[Event]:
    path = base / stream.source
    if not path.exists():
        raise SourceError(f"{path}: no such file or bag directory")
    why = _not_a_bag(path)
    if why:
        raise SourceError(why)
    suffix = key_suffix(stream.kind, stream.sensor_id)
    leap = mapping.leap_seconds
    if stream.kind == "imu":
        b = ImuBuilder(stream.matrix(), stream.gyro_scale(), stream.accel_scale(), stream.form, stats=stats)
        pairs = None
        if stats is not None and stream.time_base == "boot":
            pairs = stats.setdefault("_clock_pairs", [])
        for k, (msgtype, m, t_bag_ns) in enumerate(_read(path, stream.topic)):
            if msgtype not in IMU_TYPES:
                raise SourceError(f"{path} {stream.topic}: {msgtype} is not sensor_msgs/Imu")
            if no_rates(m):  # orientation-only (covariance[0] = -1: no estimate): no measurement
                count(stats, "no_rates")
                continue
            w, a = m.angular_velocity, m.linear_acceleration
            if pairs is not None and k % 10 == 0:  # the bag's receive clock is POSIX (UTC)
                pairs.append((_stamp(m), t_bag_ns * 1e-9 - GPS_EPOCH_UNIX_S + leap))
            t = to_gps_s(_stamp(m), stream, leap)
            s = b.push(t, (w.x, w.y, w.z), (a.x, a.y, a.z))
            if s is not None:
                yield Event(t, suffix, s)
        return
    # gnss_fix: NavSatFix + the nearest twist (both decoded once; fixes are small streams)
    twists: list[tuple[float, np.ndarray, np.ndarray]] = []
    if stream.twist_topic:
        for msgtype, m, _ in _read(path, stream.twist_topic):
            if msgtype not in TWIST_TYPES:
                raise SourceError(f"{path} {stream.twist_topic}: {msgtype} is not TwistWithCovarianceStamped")
            v = np.array([m.twist.twist.linear.x, m.twist.twist.linear.y, m.twist.twist.linear.z])
            cov = np.asarray(m.twist.covariance, float).reshape(6, 6)[:3, :3]
            std = np.sqrt(np.clip(np.diag(cov), 0.0, None))
            if stream.twist_frame == "NED":
                v, std = np.array([v[1], v[0], -v[2]]), std[[1, 0, 2]]
            twists.append((_stamp(m), v, std))
    twists.sort(key=lambda x: x[0])
    tw_t = np.array([x[0] for x in twists])
    for msgtype, m, _ in _read(path, stream.topic):
        if msgtype not in FIX_TYPES:
            raise SourceError(f"{path} {stream.topic}: {msgtype} is not sensor_msgs/NavSatFix")
        if m.status.status < 0:  # STATUS_NO_FIX
            if stats is not None:
                stats["no_fix"] = stats.get("no_fix", 0) + 1
            continue
        ts = _stamp(m)
        cov = np.asarray(m.position_covariance, float).reshape(3, 3)
        known = m.position_covariance_type > 0 and np.all(np.diag(cov) > 0)
        pstd = np.sqrt(np.diag(cov)) if known else stream.pos_std_m  # None: GnssFix's defaults
        p_origin = "covariance" if known else ("mapping" if stream.pos_std_m is not None else "default")
        v_origin = None
        ftype = NAVSAT_FIX_TYPE.get(int(m.status.status), "single")
        t = to_gps_s(ts, stream, leap)
        vel = vstd = None
        if twists:
            i = int(np.argmin(np.abs(tw_t - ts)))
            if abs(tw_t[i] - ts) <= TWIST_MATCH_S:
                _, vel, vstd = twists[i]
                v_origin = "covariance"
                if not np.all(vstd > 0):
                    vstd = stream.vel_std_mps  # None: GnssFix's default for the fix type
                    v_origin = "mapping" if vstd is not None else "default"
            elif stats is not None:  # published as position only
                stats["no_velocity"] = stats.get("no_velocity", 0) + 1
        try:
            fix = gnss_fix_to_wire(t, m.latitude, m.longitude, m.altitude, vel, pstd, vstd, fix_type=ftype)
        except ValueError:
            if stats is not None:
                stats["implausible"] = stats.get("implausible", 0) + 1
            continue
        count(stats, f"sigma_pos:{p_origin}")
        if v_origin is not None:
            count(stats, f"sigma_vel:{v_origin}")
        yield Event(t, suffix, fix)
