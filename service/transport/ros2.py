"""ROS 2 bridge over Zenoh: CDR in (sensor_msgs/Imu, NavSatFix, TwistWithCovarianceStamped) -> fednav
sensors; solutions and health out as nav_msgs/Odometry, sensor_msgs/NavSatFix,
diagnostic_msgs/DiagnosticArray and optionally tf2_msgs/TFMessage, in CDR.

Two carriers (key formats), selected by ``[ros2] carrier``:

- ``rmw_zenoh`` (ROS 2's Zenoh middleware): ``<domain_id>/<topic>/<pkg>::msg::dds_::<Type>_/<type hash>``,
  the topic without its leading '/', the type hash ``RIHS01_<sha256>`` (Jazzy and later) or
  ``TypeHashNotSupported`` (Humble). Inputs are subscribed with ``*`` in place of the hash (a
  publisher of either distro matches). Published samples carry rmw_zenoh's attachment (sequence
  number, source timestamp, GID).
- ``ros2dds`` (zenoh-bridge-ros2dds): ``[<namespace>/]<topic>``, the topic without its leading '/'.

Conventions (docs/ros2.md): ROS body axes are REP 103 forward-left-up (FLU), fednav's are
right-forward-up (RFU): ``v_rfu = FLU_TO_RFU @ v_flu``. World frames are ENU in both. ROS time
(header.stamp) is UTC (unix seconds); fednav's ``t`` is GPS seconds: ``t = unix - 315964800 +
leap_seconds``. An Imu message carries rates; fednav's ImuSample carries increments over the interval
since the previous sample: the first Imu of a stream only opens the interval.

Decoding produces the same JSON wire messages a fednav publisher sends; the service hands them to
the same intake path (validation, acceptance rules, counters). CDR that does not decode is a counted
rejection (``bad_cdr``), never an exception out of :meth:`RosInput.decode`.
"""

from __future__ import annotations

import functools
import json
import math
import struct
import time
from dataclasses import dataclass, field

import numpy as np

from fednav.service import earth
from fednav.service.ros2_config import Ros2Config, Ros2Input

INSTALL_HINT = "the ROS 2 bridge needs rosbags: install fednav[ros] (pip install -e '.[ros]')"

#: unix time of the GPS epoch 1980-01-06T00:00:00 UTC
GPS_EPOCH_UNIX_S = 315_964_800
#: REP 103 body forward-left-up -> fednav body right-forward-up (v_rfu = FLU_TO_RFU @ v_flu)
FLU_TO_RFU = np.array([[0.0, -1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, 1.0]])
NED_TO_ENU = np.array([[0.0, 1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, -1.0]])
#: twist.angular is not estimated: its variance in Odometry says so
UNKNOWN_VARIANCE = 1.0e6
#: NavSatFix / Twist messages kept per sensor while waiting for their partner
PAIR_BUFFER = 16
#: rmw_zenoh's GID storage (RMW_GID_STORAGE_SIZE since Jazzy)
GID_SIZE = 16

TYPES_OUT = {
    "odometry": "nav_msgs/msg/Odometry",
    "navsatfix": "sensor_msgs/msg/NavSatFix",
    "diagnostics": "diagnostic_msgs/msg/DiagnosticArray",
    "tf": "tf2_msgs/msg/TFMessage",
}


class RosUnavailable(RuntimeError):
    pass


class RosDecodeError(ValueError):
    def __init__(self, reason: str, text: str):
        super().__init__(text)
        self.reason = reason


@functools.cache
def typestore(distro: str = "jazzy"):
    """rosbags' type store of a ROS 2 distribution (message definitions, CDR (de)serialisers)."""
    try:
        from rosbags.typesys import Stores, get_typestore
    except ImportError as exc:
        raise RosUnavailable(INSTALL_HINT) from exc
    return get_typestore({"humble": Stores.ROS2_HUMBLE, "jazzy": Stores.ROS2_JAZZY}[distro])


# --- time -------------------------------------------------------------------------------------------
def stamp_to_t(sec: int, nanosec: int, base: str = "utc", leap_seconds: int = 18) -> float:
    """header.stamp -> fednav sensor time (GPS seconds)."""
    unix = sec + nanosec * 1e-9
    return unix if base == "gps" else unix - GPS_EPOCH_UNIX_S + leap_seconds


def t_to_stamp(t: float, base: str = "utc", leap_seconds: int = 18) -> tuple[int, int]:
    """fednav sensor time (GPS seconds) -> header.stamp (sec, nanosec), rounded to the nanosecond."""
    unix = t if base == "gps" else t + GPS_EPOCH_UNIX_S - leap_seconds
    sec = math.floor(unix)
    ns = round((unix - sec) * 1e9)
    if ns >= 1_000_000_000:
        sec, ns = sec + 1, ns - 1_000_000_000
    return int(sec), int(ns)


# --- keys -------------------------------------------------------------------------------------------
def dds_type_name(msgtype: str) -> str:
    """``sensor_msgs/msg/Imu`` -> ``sensor_msgs::msg::dds_::Imu_`` (the type chunk of rmw_zenoh keys)."""
    pkg, kind, name = msgtype.split("/")
    return f"{pkg}::{kind}::dds_::{name}_"


@functools.cache
def type_hash(msgtype: str, distro: str = "jazzy") -> str:
    """The type-hash chunk of rmw_zenoh keys: ``RIHS01_<sha256 hex>`` (REP 2011), Humble has none."""
    if distro == "humble":
        return "TypeHashNotSupported"
    return typestore(distro).hash_rihs01(msgtype)


def topic_key(cfg: Ros2Config, topic: str, msgtype: str, *, any_hash: bool = False) -> str:
    """Zenoh key of a ROS 2 topic under the configured carrier (``any_hash``: ``*`` for the hash)."""
    name = topic.lstrip("/")
    if cfg.carrier == "ros2dds":
        return f"{cfg.namespace}/{name}" if cfg.namespace else name
    h = "*" if any_hash else type_hash(msgtype, cfg.distro)
    return f"{cfg.domain_id}/{name}/{dds_type_name(msgtype)}/{h}"


def output_topic(template: str, vehicle: str, pipeline: str = "") -> str:
    return template.replace("{vehicle}", vehicle).replace("{pipeline}", pipeline)


# --- rmw_zenoh attachment -----------------------------------------------------------------------------
def _leb128(n: int) -> bytes:
    out = bytearray()
    while True:
        b = n & 0x7F
        n >>= 7
        out.append(b | (0x80 if n else 0))
        if not n:
            return bytes(out)


def _zstr(s: str) -> bytes:
    b = s.encode()
    return _leb128(len(b)) + b


def rmw_attachment(sequence_number: int, source_timestamp_ns: int, gid: bytes, keyed: bool = False) -> bytes:
    """rmw_zenoh's sample attachment, serialised like Zenoh's serializer does (int64 little-endian;
    strings and sequences prefixed with their LEB128 length; a std::array is a sequence):
    sequence number, source timestamp (ns), GID (16 bytes). ``keyed``: the earlier rmw_zenoh layout
    with the strings "sequence_number", "source_timestamp", "source_gid" before the values."""
    if len(gid) != GID_SIZE:
        raise ValueError(f"gid must be {GID_SIZE} bytes")
    seq, ts = struct.pack("<q", sequence_number), struct.pack("<q", source_timestamp_ns)
    g = _leb128(GID_SIZE) + gid
    if keyed:
        return _zstr("sequence_number") + seq + _zstr("source_timestamp") + ts + _zstr("source_gid") + g
    return seq + ts + g


# --- rmw_zenoh graph (liveliness) tokens -----------------------------------------------------------------
#: QoS chunk of a token for rmw_zenoh's default profile (reliable, volatile, keep last 10): every
#: field equal to the default is left empty
DEFAULT_QOS_CHUNK = "::,:,:,:,,"


def _mangle(name: str) -> str:
    return name.replace("/", "%")


def graph_tokens(cfg: Ros2Config, zid: str, publishers, subscriptions) -> list[str]:
    """rmw_zenoh liveliness tokens of the bridge: one node (NN), one per publisher (MP) and per
    subscription (MS), ``@ros2_lv/<domain>/<zid>/<node id>/<entity id>/<kind>/<enclave>/<namespace>/
    <node>[/<topic>/<type>/<type hash>/<qos>]`` with '/' inside names written '%' (rmw_zenoh's
    liveliness_utils). ``publishers``/``subscriptions``: (topic, message type) pairs."""
    base = f"@ros2_lv/{cfg.domain_id}/{zid}/0"
    node = f"%/%/{cfg.node_name}"
    out = [f"{base}/0/NN/{node}"]
    entities = [("MP", t, m) for t, m in publishers] + [("MS", t, m) for t, m in subscriptions]
    for n, (kind, topic, msgtype) in enumerate(entities, start=1):
        t = "/" + topic.lstrip("/")
        h = type_hash(msgtype, cfg.distro)
        out.append(f"{base}/{n}/{kind}/{node}/{_mangle(t)}/{dds_type_name(msgtype)}/{h}/{DEFAULT_QOS_CHUNK}")
    return out


def header_stamp_s(payload: bytes) -> float:
    """header.stamp (s) of a CDR message whose first field is a std_msgs/Header (Imu, NavSatFix,
    TwistWithCovarianceStamped): int32 sec and uint32 nanosec after the 4-byte encapsulation header,
    in the byte order it names. 0 when the payload is too short (it is refused later)."""
    if len(payload) < 12:
        return 0.0
    sec, ns = struct.unpack_from("<iI" if payload[1] & 1 else ">iI", payload, 4)
    return sec + ns * 1e-9


# --- conversions in ------------------------------------------------------------------------------------
def _diag_std(cov, idx: tuple[int, int, int], default: float) -> list[float]:
    """1-sigma from covariance diagonal entries; a non-positive or non-finite one -> default."""
    out = []
    for i in idx:
        v = float(cov[i])
        out.append(math.sqrt(v) if math.isfinite(v) and v > 0.0 else default)
    return out


def gnss_fix_from_ros(fix: dict, twist: dict | None) -> dict | None:
    """The one place a NavSatFix (and the Twist paired with it) becomes a fednav GnssFix (JSON dict).

    ``fix``: t, lat_deg, lon_deg, height_m, pos_std_enu_m (optional fix_type, constellation);
    ``twist``: t, vel_enu_mps, vel_std_enu_mps. With a Twist: the 3-D velocity variant; without
    one (``twist is None``): the position-only variant, no velocity invented.
    """
    out = {
        "t": fix["t"],
        "lat_deg": fix["lat_deg"],
        "lon_deg": fix["lon_deg"],
        "height_m": fix["height_m"],
        "pos_std_enu_m": fix["pos_std_enu_m"],
        "fix_type": fix.get("fix_type", "single"),
        "constellation": fix.get("constellation", "GPS"),
    }
    if twist is not None:
        out["vel_enu_mps"] = twist["vel_enu_mps"]
        out["vel_std_enu_mps"] = twist["vel_std_enu_mps"]
    return out


_SERVICE_CONSTELLATION = {1: "GPS", 2: "GLO", 4: "BDS", 8: "GAL"}
#: NavSatStatus.status -> GnssFix.fix_type (STATUS_FIX 0, STATUS_SBAS_FIX 1, STATUS_GBAS_FIX 2)
_NAVSAT_FIX_TYPE = {0: "single", 1: "sbas", 2: "dgnss"}


@dataclass
class _ImuState:
    stamp_ns: int
    rate_flu_rps: np.ndarray
    accel_flu_mps2: np.ndarray


@dataclass
class RosInput:
    """Decodes ROS 2 samples of the configured topics into fednav wire messages (JSON bytes).

    Keeps what a stream needs across samples (the previous Imu of each sensor, a NavSatFix or Twist
    waiting for its partner). Use from one thread."""

    cfg: Ros2Config
    _by_key: dict[str, Ros2Input] = field(default_factory=dict)
    _imu: dict[str, _ImuState] = field(default_factory=dict)
    _fix: dict[str, list[dict]] = field(default_factory=dict)  # waiting for their Twist, per sensor
    _twist: dict[str, list[dict]] = field(default_factory=dict)  # waiting for their NavSatFix

    def __post_init__(self):
        self.store = typestore(self.cfg.distro)
        self._with_twist = {
            i.sensor_id for i in self.cfg.inputs if i.type == "geometry_msgs/msg/TwistWithCovarianceStamped"
        }
        for i in self.cfg.inputs:
            self._by_key[self._match_key(topic_key(self.cfg, i.topic, i.type, any_hash=True))] = i

    def _match_key(self, key: str) -> str:
        """The part of a key that names the input (rmw_zenoh: without the type hash)."""
        return key.rsplit("/", 1)[0] if self.cfg.carrier == "rmw_zenoh" else key

    def key_exprs(self) -> list[str]:
        return [topic_key(self.cfg, i.topic, i.type, any_hash=True) for i in self.cfg.inputs]

    def input_of(self, key: str) -> Ros2Input | None:
        return self._by_key.get(self._match_key(key))

    def _t(self, header) -> float:
        return stamp_to_t(
            header.stamp.sec, header.stamp.nanosec, self.cfg.stamp_time_base, self.cfg.leap_seconds
        )

    def decode(self, key: str, payload: bytes) -> list[tuple[str, str, bytes]]:
        """(kind, sensor_id, JSON payload) for the intake; raises RosDecodeError (reason, text)."""
        inp = self.input_of(key)
        if inp is None:
            raise RosDecodeError("unknown_key", f"no [ros2] input for {key[:120]}")
        try:
            msg = self.store.deserialize_cdr(payload, inp.type)
        except Exception as exc:  # rosbags raises several types on truncated or garbled CDR
            raise RosDecodeError("bad_cdr", f"{inp.topic}: {type(exc).__name__}: {str(exc)[:80]}") from None
        try:
            if inp.type == "sensor_msgs/msg/Imu":
                return self._imu_in(inp, msg)
            if inp.type == "sensor_msgs/msg/NavSatFix":
                return self._fix_in(inp, msg)
            return self._twist_in(inp, msg)
        except RosDecodeError:
            raise
        except (TypeError, ValueError, AttributeError, IndexError) as exc:
            raise RosDecodeError("bad_cdr", f"{inp.topic}: {exc}") from None

    # Imu: rates (FLU) -> increments (RFU) over the interval since the previous stamp
    def _imu_in(self, inp: Ros2Input, msg) -> list[tuple[str, str, bytes]]:
        t = self._t(msg.header)
        stamp_ns = msg.header.stamp.sec * 1_000_000_000 + msg.header.stamp.nanosec
        w = np.array([msg.angular_velocity.x, msg.angular_velocity.y, msg.angular_velocity.z], dtype=float)
        a = np.array(
            [msg.linear_acceleration.x, msg.linear_acceleration.y, msg.linear_acceleration.z], dtype=float
        )
        prev = self._imu.get(inp.sensor_id)
        if prev is not None and stamp_ns == prev.stamp_ns:
            raise RosDecodeError("duplicate", f"{inp.topic}: Imu stamp repeated")
        self._imu[inp.sensor_id] = _ImuState(stamp_ns, w, a)
        if prev is None:
            return []
        if stamp_ns < prev.stamp_ns:
            # the interval reopens at this sample: a sensor restart or clock step backwards goes
            # on to the intake on its new time base (its rules recognise a time jump)
            raise RosDecodeError("time_backwards", f"{inp.topic}: Imu stamp went back; interval reopened")
        dt_s = (stamp_ns - prev.stamp_ns) * 1e-9  # exact from the integer stamps
        sample = imu_sample_from_rates(
            t, dt_s, w, a, prev.rate_flu_rps, prev.accel_flu_mps2, self.cfg.imu_integration
        )
        return [("imu", inp.sensor_id, _dumps(sample))]

    def _fix_in(self, inp: Ros2Input, msg) -> list[tuple[str, str, bytes]]:
        if msg.status.status < 0:
            raise RosDecodeError("ros_no_fix", f"{inp.topic}: NavSatFix status NO_FIX")
        cov_known = msg.position_covariance_type != 0
        std = (
            _diag_std(msg.position_covariance, (0, 4, 8), self.cfg.fix_std_m)
            if cov_known
            else [self.cfg.fix_std_m] * 3
        )
        fix = {
            "t": self._t(msg.header),
            "lat_deg": float(msg.latitude),
            "lon_deg": float(msg.longitude),
            "height_m": float(msg.altitude),
            "pos_std_enu_m": std,
            "fix_type": _NAVSAT_FIX_TYPE.get(int(msg.status.status), "single"),
            "constellation": _SERVICE_CONSTELLATION.get(int(msg.status.service), "MULTI"),
        }
        if inp.sensor_id not in self._with_twist:  # no Twist topic for this receiver: position only
            return [("gnss_fix", inp.sensor_id, _dumps(gnss_fix_from_ros(fix, None)))]
        return self._pair(inp.sensor_id, fix, self._fix, self._twist, fix_first=True)

    def _twist_in(self, inp: Ros2Input, msg) -> list[tuple[str, str, bytes]]:
        lin = msg.twist.twist.linear
        v = np.array([lin.x, lin.y, lin.z], dtype=float)
        std = _diag_std(msg.twist.covariance, (0, 7, 14), self.cfg.vel_std_mps)
        if inp.velocity_frame == "ned":
            v = NED_TO_ENU @ v
            std = [std[1], std[0], std[2]]
        tw = {"t": self._t(msg.header), "vel_enu_mps": [float(x) for x in v], "vel_std_enu_mps": std}
        return self._pair(inp.sensor_id, tw, self._twist, self._fix, fix_first=False)

    def _pair(self, sid: str, item: dict, mine: dict, theirs: dict, fix_first: bool):
        """Pair ``item`` with the waiting partner closest in time (within pair_tolerance_s), else
        keep it waiting (at most PAIR_BUFFER per sensor; the oldest unpaired one is dropped)."""
        waiting = theirs.get(sid, [])
        best = min(waiting, key=lambda o: abs(o["t"] - item["t"]), default=None)
        if best is not None and abs(best["t"] - item["t"]) < self.cfg.pair_tolerance_s:
            waiting.remove(best)
            fix, tw = (item, best) if fix_first else (best, item)
            return self._emit(sid, fix, tw)
        q = mine.setdefault(sid, [])
        q.append(item)
        del q[:-PAIR_BUFFER]
        return []

    def _emit(self, sensor_id: str, fix: dict, twist: dict) -> list[tuple[str, str, bytes]]:
        out = gnss_fix_from_ros(fix, twist)
        return [] if out is None else [("gnss_fix", sensor_id, _dumps(out))]


def _dumps(d: dict) -> bytes:
    # NaN/Inf are written as JSON's NaN/Infinity tokens: the wire model refuses them ('non_finite')
    return json.dumps(d).encode()


def imu_sample_from_rates(
    t: float,
    dt_s: float,
    rate_flu_rps: np.ndarray,
    accel_flu_mps2: np.ndarray,
    prev_rate_flu_rps: np.ndarray,
    prev_accel_flu_mps2: np.ndarray,
    integration: str = "trapezoid",
) -> dict:
    """ImuSample (JSON dict) for the interval (t - dt_s, t] from two Imu samples' rates (FLU)."""
    if integration == "trapezoid":
        w = 0.5 * (rate_flu_rps + prev_rate_flu_rps)
        a = 0.5 * (accel_flu_mps2 + prev_accel_flu_mps2)
    else:
        w, a = rate_flu_rps, accel_flu_mps2
    return {
        "t": t,
        "dt_s": dt_s,
        "dtheta_rad": [float(x) for x in FLU_TO_RFU @ w * dt_s],
        "dvel_mps": [float(x) for x in FLU_TO_RFU @ a * dt_s],
    }


# --- conversions out -----------------------------------------------------------------------------------
def quat_enu_flu(mat_nb: np.ndarray) -> np.ndarray:
    """Orientation for ROS (x, y, z, w): body FLU -> ENU, from fednav's mat_nb (body RFU -> ENU)."""
    w, x, y, z = earth.mat_to_quat(mat_nb @ FLU_TO_RFU)
    return np.array([x, y, z, w])


def pose_covariance(P9: np.ndarray, mat_datum_here: np.ndarray | None = None) -> np.ndarray:
    """ROS pose covariance (6x6: x, y, z, rotation about fixed X, Y, Z of the world frame) from
    fednav's 9x9 (dp_enu, dv_enu, phi_enu).

    fednav's phi is defined by C_nb(computed) = (I - [phi x]) C_nb(true): the computed attitude
    is the true one rotated by -phi in world axes, so the attitude error estimate-minus-truth is
    -phi (and dp is estimate minus truth): J = blockdiag(R, -R), R rotating the vehicle's ENU to
    the map frame's (identity at the datum)."""
    R = np.eye(3) if mat_datum_here is None else mat_datum_here
    idx = np.r_[0:3, 6:9]
    J = np.zeros((6, 6))
    J[:3, :3], J[3:, 3:] = R, -R
    C = J @ P9[np.ix_(idx, idx)] @ J.T
    return 0.5 * (C + C.T)


def twist_covariance(P9: np.ndarray, mat_nb: np.ndarray) -> np.ndarray:
    """ROS twist covariance in the child frame (FLU): linear from P_vv rotated to the body, angular
    not estimated (UNKNOWN_VARIANCE on its diagonal)."""
    C_bn = (mat_nb @ FLU_TO_RFU).T
    out = np.zeros((6, 6))
    out[:3, :3] = C_bn @ P9[3:6, 3:6] @ C_bn.T
    out[3:, 3:] = np.eye(3) * UNKNOWN_VARIANCE
    return 0.5 * (out + out.T)


def mat_datum_from_here(datum_llh_rad: np.ndarray, llh_rad: np.ndarray) -> np.ndarray:
    """Rotation of ENU vectors at ``llh`` into the ENU frame at the datum."""
    return earth.mat_en(datum_llh_rad[0], datum_llh_rad[1]).T @ earth.mat_en(llh_rad[0], llh_rad[1])


#: fednav pipeline status -> DiagnosticStatus level (OK 0, WARN 1, ERROR 2, STALE 3)
PIPELINE_LEVEL = {"aided": 0, "unaided": 1, "coasting": 1, "degraded": 1, "failed": 2, "initialising": 3}
#: fednav pipeline status -> NavSatStatus.status (FIX 0, NO_FIX -1)
NAVSAT_STATUS = {"initialising": -1, "failed": -1}


class RosEncoder:
    """Builds the output messages (rosbags objects) and their CDR bytes."""

    def __init__(self, cfg: Ros2Config):
        self.cfg = cfg
        self.store = typestore(cfg.distro)
        self.T = self.store.types
        self.datum: dict[str, np.ndarray] = {}  # pipeline -> datum llh (rad)
        if cfg.outputs.datum is not None:
            lat, lon, h = cfg.outputs.datum
            self._fixed_datum = np.array([math.radians(lat), math.radians(lon), h])
        else:
            self._fixed_datum = None

    def _header(self, t: float | None, frame_id: str):
        sec, ns = (0, 0) if t is None else t_to_stamp(t, self.cfg.stamp_time_base, self.cfg.leap_seconds)
        return self.T["std_msgs/msg/Header"](
            stamp=self.T["builtin_interfaces/msg/Time"](sec=sec, nanosec=ns), frame_id=frame_id
        )

    def datum_of(self, pipeline: str, llh: np.ndarray) -> np.ndarray:
        if self._fixed_datum is not None:
            return self._fixed_datum
        return self.datum.setdefault(pipeline, np.array(llh, dtype=float))

    def pose(self, pipeline: str, nav) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """(position in the map frame, quaternion xyzw FLU->map, R vehicle ENU -> map ENU)."""
        llh = nav.llh
        datum = self.datum_of(pipeline, llh)
        pos = earth.ecef_to_enu(earth.llh_to_ecef(llh), datum)
        R = mat_datum_from_here(datum, llh)
        return pos, quat_enu_flu(R @ nav.mat_nb), R

    def odometry(self, pipeline: str, nav, P9: np.ndarray):
        T, o = self.T, self.cfg.outputs
        pos, q, R = self.pose(pipeline, nav)
        v_flu = (nav.mat_nb @ FLU_TO_RFU).T @ np.asarray(nav.vel_enu_mps, dtype=float)
        vec3, point = T["geometry_msgs/msg/Vector3"], T["geometry_msgs/msg/Point"]
        pose = T["geometry_msgs/msg/PoseWithCovariance"](
            pose=T["geometry_msgs/msg/Pose"](
                position=point(x=float(pos[0]), y=float(pos[1]), z=float(pos[2])),
                orientation=T["geometry_msgs/msg/Quaternion"](x=q[0], y=q[1], z=q[2], w=q[3]),
            ),
            covariance=pose_covariance(P9, R).reshape(36),
        )
        twist = T["geometry_msgs/msg/TwistWithCovariance"](
            twist=T["geometry_msgs/msg/Twist"](
                linear=vec3(x=float(v_flu[0]), y=float(v_flu[1]), z=float(v_flu[2])),
                angular=vec3(x=0.0, y=0.0, z=0.0),
            ),
            covariance=twist_covariance(P9, nav.mat_nb).reshape(36),
        )
        return T["nav_msgs/msg/Odometry"](
            header=self._header(nav.t, o.map_frame), child_frame_id=o.base_frame, pose=pose, twist=twist
        )

    def navsatfix(self, nav, P9: np.ndarray, status: str):
        T = self.T
        return T["sensor_msgs/msg/NavSatFix"](
            header=self._header(nav.t, self.cfg.outputs.navsat_frame),
            status=T["sensor_msgs/msg/NavSatStatus"](status=NAVSAT_STATUS.get(status, 0), service=1),
            latitude=math.degrees(nav.lat_rad),
            longitude=math.degrees(nav.lon_rad),
            altitude=float(nav.h_m),
            position_covariance=np.ascontiguousarray(0.5 * (P9[:3, :3] + P9[:3, :3].T)).reshape(9),
            position_covariance_type=3,  # COVARIANCE_TYPE_KNOWN
        )

    def tf(self, pipeline: str, nav):
        T, o = self.T, self.cfg.outputs
        pos, q, _ = self.pose(pipeline, nav)
        ts = T["geometry_msgs/msg/TransformStamped"](
            header=self._header(nav.t, o.map_frame),
            child_frame_id=o.base_frame,
            transform=T["geometry_msgs/msg/Transform"](
                translation=T["geometry_msgs/msg/Vector3"](x=float(pos[0]), y=float(pos[1]), z=float(pos[2])),
                rotation=T["geometry_msgs/msg/Quaternion"](x=q[0], y=q[1], z=q[2], w=q[3]),
            ),
        )
        return T["tf2_msgs/msg/TFMessage"](transforms=[ts])

    def diagnostics(self, vehicle: str, health):
        """DiagnosticArray of a Health message: one status for the vehicle's service, one per
        pipeline (levels from PIPELINE_LEVEL)."""
        T = self.T
        kv = T["diagnostic_msgs/msg/KeyValue"]
        status = T["diagnostic_msgs/msg/DiagnosticStatus"]
        if health.t is None:
            level, text = 3, "no data yet"
        elif health.stale or health.dropped_overload:
            level = 1
            text = (
                f"stale: {', '.join(health.stale)}" if health.stale else "intake overload: messages dropped"
            )
        else:
            level, text = 0, "running"
        values = [
            kv(key="received", value=str(health.received)),
            kv(key="accepted", value=str(health.accepted)),
            kv(key="dropped_overload", value=str(health.dropped_overload)),
            kv(key="queue_depth", value=str(health.queue_depth)),
        ]
        values += [kv(key=f"latency_ms.{k}", value=f"{v:.3f}") for k, v in health.latency_ms.items()]
        values += [kv(key=f"rejected.{k}", value=str(v)) for k, v in sorted(health.rejected.items())]
        out = [
            status(
                level=level,
                name=f"fednav/{vehicle}/service",
                message=text,
                hardware_id=vehicle,
                values=values,
            )
        ]
        for name, p in health.pipelines.items():
            pv = [
                kv(key="status", value=p.status),
                kv(key="updates", value=str(p.updates)),
                kv(key="reinitialisations", value=str(p.reinitialisations)),
                kv(key="last_t", value="" if p.last_t is None else f"{p.last_t:.6f}"),
            ] + [kv(key=f"screened.{k}", value=str(v)) for k, v in sorted(p.screened.items())]
            out.append(
                status(
                    level=PIPELINE_LEVEL[p.status],
                    name=f"fednav/{vehicle}/{name}",
                    message=p.status,
                    hardware_id=vehicle,
                    values=pv,
                )
            )
        return T["diagnostic_msgs/msg/DiagnosticArray"](header=self._header(health.t, ""), status=out)

    def cdr(self, msg) -> bytes:
        return bytes(self.store.serialize_cdr(msg, msg.__msgtype__))


class RosSink:
    """Engine sink (plus ``on_health``) that republishes one vehicle's outputs as ROS 2 messages.

    ``put(key, payload, attachment)`` is the transport (Zenoh lives in zenoh_io/app)."""

    def __init__(self, cfg: Ros2Config, pipelines: list[str], put, gid: bytes | None = None):
        self.cfg = cfg
        self.enc = RosEncoder(cfg)
        self.put = put
        o = cfg.outputs
        self.pipelines = list(o.pipelines) or list(pipelines)
        self.tf_pipeline = o.tf_pipeline or (self.pipelines[0] if self.pipelines else None)
        self.gid = gid if gid is not None else bytes(GID_SIZE)
        self.seq: dict[str, int] = {}

    def _send(self, topic: str, msg) -> None:
        if not topic:
            return
        key = topic_key(self.cfg, topic, msg.__msgtype__)
        att = None
        if self.cfg.carrier == "rmw_zenoh" and self.cfg.attachment != "none":
            n = self.seq[key] = self.seq.get(key, 0) + 1
            att = rmw_attachment(n, time.time_ns(), self.gid, keyed=self.cfg.attachment == "rmw_zenoh_keyed")
        self.put(key, self.enc.cdr(msg), att)

    def topics(self) -> list[tuple[str, str]]:
        """(topic, message type) of every output this sink can publish."""
        o, v = self.cfg.outputs, self.cfg.vehicle
        out = []
        for p in self.pipelines:
            out += [(output_topic(o.odometry_topic, v, p), TYPES_OUT["odometry"])]
            out += [(output_topic(o.navsatfix_topic, v, p), TYPES_OUT["navsatfix"])]
        if o.tf and self.tf_pipeline:
            out.append((output_topic(o.tf_topic, v, self.tf_pipeline), TYPES_OUT["tf"]))
        out.append((output_topic(o.diagnostics_topic, v), TYPES_OUT["diagnostics"]))
        return [(t, m) for t, m in dict.fromkeys(out) if t]

    def on_estimate(self, vehicle: str, out) -> None:
        if vehicle != self.cfg.vehicle or out.name not in self.pipelines:
            return
        o, nav, P9 = self.cfg.outputs, out.est.nav, out.P9
        self._send(output_topic(o.odometry_topic, vehicle, out.name), self.enc.odometry(out.name, nav, P9))
        status = out.pipeline.current_status(nav.t)
        self._send(output_topic(o.navsatfix_topic, vehicle, out.name), self.enc.navsatfix(nav, P9, status))
        if o.tf and out.name == self.tf_pipeline:
            self._send(output_topic(o.tf_topic, vehicle, out.name), self.enc.tf(out.name, nav))

    def on_output(self, vehicle: str, msg, err9=None) -> None:
        return None

    def on_truth(self, vehicle: str, truth) -> None:
        return None

    def on_health(self, vehicle: str, health) -> None:
        if vehicle == self.cfg.vehicle:
            self._send(
                output_topic(self.cfg.outputs.diagnostics_topic, vehicle),
                self.enc.diagnostics(vehicle, health),
            )
