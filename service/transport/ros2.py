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

Decoding builds the fednav wire models (ImuSample, GnssFix) straight from the CDR values, validated
by the models as any JSON input is (no JSON in between); the service hands them to the same intake
path (acceptance rules, counters). CDR that does not decode (``bad_cdr``) and values the models
refuse (``non_finite``, ``absurd_value``, ``out_of_range``, ``schema``, as the service's own
classification) are counted rejections, never an exception out of :meth:`RosInput.decode` other
than :class:`RosDecodeError`.
"""

from __future__ import annotations

import functools
import math
import struct
import threading
import time
from collections import Counter
from dataclasses import dataclass, field

import numpy as np
from pydantic import ValidationError

from fednav.service import earth
from fednav.service.messages import GnssFix, ImuSample, WireModel
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
#: decoded samples whose exact header.stamp the bridge remembers for its outputs (per bridge)
STAMP_MEMORY = 1 << 14
#: what RosInput.counters counts (notes, not rejections: the messages still go on):
#: a NavSatFix sent position-only because its Twist did not come within ``twist_wait_s``, and a
#: Twist dropped because no NavSatFix of its epoch came
COUNTER_NAMES = ("fix_without_velocity", "twist_without_fix")

TYPES_OUT = {
    "odometry": "nav_msgs/msg/Odometry",
    "navsatfix": "sensor_msgs/msg/NavSatFix",
    "diagnostics": "diagnostic_msgs/msg/DiagnosticArray",
    "tf": "tf2_msgs/msg/TFMessage",
}

_NS = 1_000_000_000


class RosUnavailable(RuntimeError):
    pass


def _why(err, where: str) -> tuple[str, str]:
    """(reason, text) of a validation error, the text the error's that gave the reason."""
    reason, text = reason_and_text(err)
    return reason, f"{where}{text}"


class RosDecodeError(ValueError):
    def __init__(self, reason: str, text: str):
        super().__init__(text)
        self.reason = reason


from fednav.service.validation_errors import classify as classify  # noqa: E402  (one set of rules)
from fednav.service.validation_errors import reason_and_text  # noqa: E402


def _wire(model: type[WireModel], data: dict, what: str) -> WireModel:
    """A wire model built (and validated) from decoded values; a refusal is a RosDecodeError with
    the reason the service gives the same message in JSON."""
    try:
        return model.model_validate(data)
    except ValidationError as err:
        raise RosDecodeError(*_why(err, f"{what}: ")) from None


@functools.cache
def typestore(distro: str = "jazzy"):
    """rosbags' type store of a ROS 2 distribution (message definitions, CDR (de)serialisers)."""
    try:
        from rosbags.typesys import Stores, get_typestore
    except ImportError as exc:
        raise RosUnavailable(INSTALL_HINT) from exc
    return get_typestore({"humble": Stores.ROS2_HUMBLE, "jazzy": Stores.ROS2_JAZZY}[distro])


# --- time -------------------------------------------------------------------------------------------
# fednav's time is float64 seconds of GPS time (~1.4e9 s): its resolution there is 2**-22 s
# (238 ns) until 2048, so a nanosecond stamp does not survive a float in general. Two things make
# output stamps exact: the conversion stamp -> t rounds once (to the nearest float), and t -> stamp
# inverts it, returning the coarsest decimal stamp (1 s, 0.1 s, ... 1 ns) that converts back to t
# (exact for stamps of microsecond resolution); and the bridge remembers the exact stamp of every
# sample it decoded (:class:`StampMemory`), so outputs at an input's time carry its stamp to the ns.
def _offset_ns(base: str, leap_seconds: int) -> int:
    """header.stamp minus fednav time, ns: 0 for GPS stamps, (unix - GPS) for UTC (ROS time)."""
    return 0 if base == "gps" else (GPS_EPOCH_UNIX_S - leap_seconds) * _NS


def _round_div(a: int, b: int) -> int:
    """a / b (b > 0) rounded to the nearest integer, ties to even."""
    q, r = divmod(a, b)
    if 2 * r > b or (2 * r == b and q & 1):
        q += 1
    return q


def stamp_ns_to_t(stamp_ns: int, base: str = "utc", leap_seconds: int = 18) -> float:
    """header.stamp as integer ns -> fednav sensor time (GPS seconds): the float nearest to the exact
    value (one rounding: an integer division)."""
    return (stamp_ns - _offset_ns(base, leap_seconds)) / _NS


def stamp_to_t(sec: int, nanosec: int, base: str = "utc", leap_seconds: int = 18) -> float:
    """header.stamp -> fednav sensor time (GPS seconds)."""
    return stamp_ns_to_t(sec * _NS + nanosec, base, leap_seconds)


_STEPS = tuple(10**k for k in range(9, -1, -1))


def t_to_stamp_ns(t: float, base: str = "utc", leap_seconds: int = 18) -> int:
    """fednav sensor time -> header.stamp in ns, the inverse of :func:`stamp_ns_to_t`: of the stamps
    that convert to ``t``, the one of coarsest decimal resolution (1 s, 0.1 s, ..., 1 ns), found like
    the shortest decimal that reads back as a float; else the nearest ns to ``t``'s exact value. A
    stamp of 1 us resolution comes back exactly while the float spacing is below 1 us (GPS time
    below 2**32 s, year 2116); a finer one within one float spacing (238 ns until 2048)."""
    num, den = float(t).as_integer_ratio()
    off = _offset_ns(base, leap_seconds)
    for step in _STEPS:
        cand = _round_div(num * _NS, den * step) * step
        if cand / _NS == t:
            return cand + off
    return _round_div(num * _NS, den) + off


def t_to_stamp(t: float, base: str = "utc", leap_seconds: int = 18) -> tuple[int, int]:
    """fednav sensor time (GPS seconds) -> header.stamp (sec, nanosec): :func:`t_to_stamp_ns` split."""
    sec, ns = divmod(t_to_stamp_ns(t, base, leap_seconds), _NS)
    return int(sec), int(ns)


class StampMemory:
    """fednav time -> the exact header.stamp (ns) a decoded sample had, for the last ``size`` samples
    (written by the input thread, read by the output sink's). An output at an input's time gets that
    input's stamp to the nanosecond; any other time falls back to :func:`t_to_stamp_ns`."""

    def __init__(self, size: int = STAMP_MEMORY):
        self.size = size
        self._d: dict[float, int] = {}
        self._lock = threading.Lock()

    def remember(self, t: float, stamp_ns: int, *, replace: bool = True) -> None:
        """``replace`` False: keep a stamp already remembered for ``t`` (IMU stamps win over fixes':
        the outputs are at IMU times)."""
        with self._lock:
            if t in self._d:
                if not replace:
                    return
                del self._d[t]
            self._d[t] = stamp_ns
            if len(self._d) > self.size:
                del self._d[next(iter(self._d))]

    def stamp_ns(self, t: float) -> int | None:
        with self._lock:
            return self._d.get(t)


@dataclass
class BridgeState:
    """What the bridge's input side, output side and graph tokens share for one ``[ros2]``
    configuration (the service builds RosInput, RosSink and the tokens from the same object):
    the exact input stamps and the GIDs of the declared graph entities."""

    cfg: Ros2Config
    stamps: StampMemory = field(default_factory=StampMemory)
    #: (MP or MS, topic, message type) -> GID of the entity's graph token
    gids: dict[tuple[str, str, str], bytes] = field(default_factory=dict)


_STATES: dict[int, BridgeState] = {}
_STATES_LOCK = threading.Lock()
_MAX_STATES = 64


def bridge_state(cfg: Ros2Config) -> BridgeState:
    """The shared state of ``cfg`` (this very object: keyed by identity, the entry holds it)."""
    with _STATES_LOCK:
        st = _STATES.get(id(cfg))
        if st is None or st.cfg is not cfg:
            st = _STATES[id(cfg)] = BridgeState(cfg)
            while len(_STATES) > _MAX_STATES:
                del _STATES[next(iter(_STATES))]
        return st


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


# --- rmw_zenoh graph (liveliness) tokens and GIDs ----------------------------------------------------------
#: QoS enum values of rmw/types.h used in the tokens
QOS_RELIABLE, QOS_BEST_EFFORT = 1, 2
QOS_TRANSIENT_LOCAL, QOS_VOLATILE = 1, 2
QOS_KEEP_LAST, QOS_KEEP_ALL = 1, 2
#: rmw_zenoh's default profile (rmw_zenoh_cpp/src/detail/qos.cpp): reliable, volatile, keep last,
#: depth 42; deadline, lifespan and liveliness lease infinite, liveliness automatic
RMW_ZENOH_DEFAULT_QOS = {
    "reliability": QOS_RELIABLE,
    "durability": QOS_VOLATILE,
    "history": QOS_KEEP_LAST,
    "depth": 42,
}
#: depth the bridge declares for its publishers and subscriptions: 10, the depth of ROS 2's default
#: profile (rmw_qos_profile_default: reliable, volatile, keep last 10)
QOS_DEPTH = 10


def qos_keyexpr(
    reliability: int = QOS_RELIABLE,
    durability: int = QOS_VOLATILE,
    history: int = QOS_KEEP_LAST,
    depth: int = QOS_DEPTH,
) -> str:
    """The QoS chunk of a token as rmw_zenoh's ``qos_to_keyexpr`` writes it:
    ``<reliability>:<durability>:<history>,<depth>:<deadline s>,<ns>:<lifespan s>,<ns>:<liveliness>,
    <lease s>,<lease ns>`` (rmw/types.h enum values), each field left empty when it equals rmw_zenoh's
    default (:data:`RMW_ZENOH_DEFAULT_QOS`). Deadline, lifespan and liveliness are the defaults here
    (empty). Reliable, volatile, keep last 10 -> ``::,10:,:,:,,``; ``::,:,:,:,,`` would be depth 42."""
    d = RMW_ZENOH_DEFAULT_QOS

    def f(name: str, v: int) -> str:
        return "" if v == d[name] else str(v)

    return (
        f"{f('reliability', reliability)}:{f('durability', durability)}:"
        f"{f('history', history)},{f('depth', depth)}:,:,:,,"
    )


#: the QoS chunk of the bridge's tokens (reliable, volatile, keep last 10)
QOS_CHUNK = qos_keyexpr()


# --- XXH3-128 (rmw_zenoh's entity GIDs) --------------------------------------------------------------------
# rmw_zenoh hashes each entity's liveliness key expression with XXH3-128 (its
# simplified_xxhash3.cpp: the portable xxHash 0.8 code, default secret, seed 0) and stores
# low64 then high64, each in host (little-endian) order, as the entity's 16-byte GID. The port
# below follows that code path by path; tests check it against the reference implementation.
_M64 = (1 << 64) - 1
_P32_1, _P32_2, _P32_3 = 0x9E3779B1, 0x85EBCA77, 0xC2B2AE3D
_P64_1, _P64_2, _P64_3 = 0x9E3779B185EBCA87, 0xC2B2AE3D27D4EB4F, 0x165667B19E3779F9
_P64_4, _P64_5 = 0x85EBCA77C2B2AE63, 0x27D4EB2F165667C5
_PRIME_MX1, _PRIME_MX2 = 0x165667919E3779F9, 0x9FB21C651E98DF25
_SECRET = bytes.fromhex(
    "b8fe6c3923a44bbe7c01812cf721ad1cded46de9839097db7240a4a4b7b3671f"
    "cb79e64eccc0e578825ad07dccff7221b8084674f743248ee03590e6813a264c"
    "3c2852bb91c300cb88d0658b1b532ea371644897a20df94e3819ef46a9deacd8"
    "a8fa763fe39c343ff9dcbbc7c70b4f1d8a51e04bcdb45931c89f7ec9d9787364"
    "eac5ac8334d3ebc3c581a0fffa1363eb170ddd51b7f0da49d316552629d4689e"
    "2b16be587d47a1fc8ff8b8d17ad031ce45cb3a8f95160428afd7fbcabb4b407e"
)


def _r64(b: bytes, i: int) -> int:
    return int.from_bytes(b[i : i + 8], "little")


def _r32(b: bytes, i: int) -> int:
    return int.from_bytes(b[i : i + 4], "little")


def _fold64(a: int, b: int) -> int:
    p = a * b
    return (p & _M64) ^ (p >> 64)


def _avalanche(h: int) -> int:
    h ^= h >> 37
    h = (h * _PRIME_MX1) & _M64
    return h ^ (h >> 32)


def _avalanche64(h: int) -> int:
    h ^= h >> 33
    h = (h * _P64_2) & _M64
    h ^= h >> 29
    h = (h * _P64_3) & _M64
    return h ^ (h >> 32)


def _mix16(d: bytes, i: int, s: int) -> int:
    return _fold64(_r64(d, i) ^ _r64(_SECRET, s), _r64(d, i + 8) ^ _r64(_SECRET, s + 8))


def _mix32(lo: int, hi: int, d: bytes, i1: int, i2: int, s: int) -> tuple[int, int]:
    lo = (lo + _mix16(d, i1, s)) & _M64
    lo ^= (_r64(d, i2) + _r64(d, i2 + 8)) & _M64
    hi = (hi + _mix16(d, i2, s + 16)) & _M64
    hi ^= (_r64(d, i1) + _r64(d, i1 + 8)) & _M64
    return lo, hi


def _xxh3_mid_end(lo: int, hi: int, n: int) -> tuple[int, int]:
    h_lo = (lo + hi) & _M64
    h_hi = (lo * _P64_1 + hi * _P64_4 + n * _P64_2) & _M64
    return _avalanche(h_lo), (-_avalanche(h_hi)) & _M64


def _xxh3_long(d: bytes) -> tuple[int, int]:
    n = len(d)
    acc = [_P32_3, _P64_1, _P64_2, _P64_3, _P64_4, _P32_2, _P64_5, _P32_1]

    def stripe(i: int, s: int) -> None:
        for lane in range(8):
            v = _r64(d, i + 8 * lane)
            k = v ^ _r64(_SECRET, s + 8 * lane)
            acc[lane ^ 1] = (acc[lane ^ 1] + v) & _M64
            acc[lane] = (acc[lane] + (k & 0xFFFFFFFF) * (k >> 32)) & _M64

    per_block = (len(_SECRET) - 64) // 8
    block = 64 * per_block
    blocks = (n - 1) // block
    for b in range(blocks):
        for j in range(per_block):
            stripe(b * block + 64 * j, 8 * j)
        for lane in range(8):
            a = acc[lane]
            a ^= a >> 47
            a ^= _r64(_SECRET, len(_SECRET) - 64 + 8 * lane)
            acc[lane] = (a * _P32_1) & _M64
    for j in range(((n - 1) - block * blocks) // 64):
        stripe(blocks * block + 64 * j, 8 * j)
    stripe(n - 64, len(_SECRET) - 64 - 7)

    def merge(s: int, start: int) -> int:
        r = start
        for i in range(4):
            k = s + 16 * i
            r += _fold64(acc[2 * i] ^ _r64(_SECRET, k), acc[2 * i + 1] ^ _r64(_SECRET, k + 8))
        return _avalanche(r & _M64)

    return merge(11, (n * _P64_1) & _M64), merge(len(_SECRET) - 64 - 11, ~(n * _P64_2) & _M64)


def xxh3_128(data: bytes) -> tuple[int, int]:
    """XXH3-128 of ``data`` (seed 0, default secret) as (low64, high64)."""
    d, n = bytes(data), len(data)
    if n == 0:
        return (
            _avalanche64(_r64(_SECRET, 64) ^ _r64(_SECRET, 72)),
            _avalanche64(_r64(_SECRET, 80) ^ _r64(_SECRET, 88)),
        )
    if n <= 3:
        lo32 = (d[0] << 16) | (d[n >> 1] << 24) | d[n - 1] | (n << 8)
        sw = int.from_bytes(lo32.to_bytes(4, "little"), "big")
        hi32 = ((sw << 13) | (sw >> 19)) & 0xFFFFFFFF
        return (
            _avalanche64(lo32 ^ (_r32(_SECRET, 0) ^ _r32(_SECRET, 4))),
            _avalanche64(hi32 ^ (_r32(_SECRET, 8) ^ _r32(_SECRET, 12))),
        )
    if n <= 8:
        keyed = (_r32(d, 0) + (_r32(d, n - 4) << 32)) ^ (_r64(_SECRET, 16) ^ _r64(_SECRET, 24))
        p = keyed * ((_P64_1 + (n << 2)) & _M64)
        lo, hi = p & _M64, p >> 64
        hi = (hi + (lo << 1)) & _M64
        lo ^= hi >> 3
        lo ^= lo >> 35
        lo = (lo * _PRIME_MX2) & _M64
        lo ^= lo >> 28
        return lo, _avalanche(hi)
    if n <= 16:
        in_lo, in_hi = _r64(d, 0), _r64(d, n - 8)
        p = (in_lo ^ in_hi ^ (_r64(_SECRET, 32) ^ _r64(_SECRET, 40))) * _P64_1
        m_lo, m_hi = (p & _M64) + ((n - 1) << 54), p >> 64
        m_lo &= _M64
        in_hi ^= _r64(_SECRET, 48) ^ _r64(_SECRET, 56)
        m_hi = (m_hi + in_hi + (in_hi & 0xFFFFFFFF) * (_P32_2 - 1)) & _M64
        m_lo ^= int.from_bytes(m_hi.to_bytes(8, "little"), "big")
        p = m_lo * _P64_2
        h_lo, h_hi = p & _M64, ((p >> 64) + m_hi * _P64_2) & _M64
        return _avalanche(h_lo), _avalanche(h_hi)
    if n <= 128:
        lo, hi = (n * _P64_1) & _M64, 0
        if n > 32:
            if n > 64:
                if n > 96:
                    lo, hi = _mix32(lo, hi, d, 48, n - 64, 96)
                lo, hi = _mix32(lo, hi, d, 32, n - 48, 64)
            lo, hi = _mix32(lo, hi, d, 16, n - 32, 32)
        lo, hi = _mix32(lo, hi, d, 0, n - 16, 0)
        return _xxh3_mid_end(lo, hi, n)
    if n <= 240:
        lo, hi = (n * _P64_1) & _M64, 0
        for i in range(32, 160, 32):
            lo, hi = _mix32(lo, hi, d, i - 32, i - 16, i - 32)
        lo, hi = _avalanche(lo), _avalanche(hi)
        for i in range(160, n + 1, 32):
            lo, hi = _mix32(lo, hi, d, i - 32, i - 16, 3 + i - 160)
        lo, hi = _mix32(lo, hi, d, n - 16, n - 32, 136 - 17 - 16)
        return _xxh3_mid_end(lo, hi, n)
    return _xxh3_long(d)


def entity_gid(token: str) -> bytes:
    """An entity's GID as rmw_zenoh computes it (liveliness_utils.cpp, ``Entity::Entity``): XXH3-128
    of the entity's liveliness key expression, low 64 bits then high 64 bits, little-endian."""
    lo, hi = xxh3_128(token.encode())
    return lo.to_bytes(8, "little") + hi.to_bytes(8, "little")


def derived_gid(base_gid: bytes, topic: str, msgtype: str) -> bytes:
    """A publisher's GID when no graph token names it (``liveliness = false``, or no token declared
    for that topic): XXH3-128 (as :func:`entity_gid`) of ``<base gid hex>/<topic>/<dds type name>``,
    so each publisher has its own, stable for a session."""
    return entity_gid(f"{base_gid.hex()}/{'/' + topic.lstrip('/')}/{dds_type_name(msgtype)}")


def _mangle(name: str) -> str:
    return name.replace("/", "%")


@dataclass(frozen=True)
class GraphEntity:
    """One rmw_zenoh graph entity of the bridge: its kind (NN node, MP publisher, MS subscription),
    entity id, topic and type (None for the node), liveliness token and GID."""

    kind: str
    entity_id: int
    topic: str | None
    msgtype: str | None
    token: str

    @property
    def gid(self) -> bytes:
        return entity_gid(self.token)


def graph_entities(cfg: Ros2Config, zid: str, publishers, subscriptions) -> list[GraphEntity]:
    """The bridge's graph entities as rmw_zenoh declares them: one node (NN, entity id 0), then one
    per publisher (MP) and per subscription (MS), ids 1, 2, ... in that order (rmw_zenoh numbers a
    context's node and entities from one counter); tokens
    ``@ros2_lv/<domain>/<zid>/<node id>/<entity id>/<kind>/<enclave>/<namespace>/<node>[/<topic>/
    <type>/<type hash>/<qos>]`` with '/' inside names written '%' (liveliness_utils.cpp), enclave
    and namespace '/', the QoS chunk :data:`QOS_CHUNK`. ``publishers``/``subscriptions``: (topic,
    message type) pairs."""
    base = f"@ros2_lv/{cfg.domain_id}/{zid}/0"
    node = f"%/%/{cfg.node_name}"
    out = [GraphEntity("NN", 0, None, None, f"{base}/0/NN/{node}")]
    entities = [("MP", t, m) for t, m in publishers] + [("MS", t, m) for t, m in subscriptions]
    for n, (kind, topic, msgtype) in enumerate(entities, start=1):
        t = "/" + topic.lstrip("/")
        h = type_hash(msgtype, cfg.distro)
        token = f"{base}/{n}/{kind}/{node}/{_mangle(t)}/{dds_type_name(msgtype)}/{h}/{QOS_CHUNK}"
        out.append(GraphEntity(kind, n, t, msgtype, token))
    return out


def graph_tokens(cfg: Ros2Config, zid: str, publishers, subscriptions) -> list[str]:
    """The liveliness tokens of :func:`graph_entities`. Their GIDs are recorded for ``cfg``
    (:func:`bridge_state`): the :class:`RosSink` of the same configuration puts each publisher's
    GID in its samples' attachment, so a ROS 2 node can match ``publisher_gid`` to the graph."""
    ents = graph_entities(cfg, zid, publishers, subscriptions)
    gids = bridge_state(cfg).gids
    for e in ents:
        if e.topic is not None:
            gids[(e.kind, e.topic, e.msgtype)] = e.gid
    return [e.token for e in ents]


def header_stamp_s(payload: bytes) -> float:
    """header.stamp (s) of a CDR message whose first field is a std_msgs/Header (Imu, NavSatFix,
    TwistWithCovarianceStamped): int32 sec and uint32 nanosec after the 4-byte encapsulation header,
    in the byte order it names. 0 when the payload is too short (it is refused later)."""
    if len(payload) < 12:
        return 0.0
    sec, ns = struct.unpack_from("<iI" if payload[1] & 1 else ">iI", payload, 4)
    return sec + ns * 1e-9


# --- conversions in ------------------------------------------------------------------------------------
def _diag_std(cov, idx: tuple[int, int, int], default: float) -> tuple[float, float, float]:
    """1-sigma from covariance diagonal entries; a non-positive or non-finite one -> default."""
    out = []
    for i in idx:
        v = float(cov[i])
        out.append(math.sqrt(v) if math.isfinite(v) and v > 0.0 else default)
    return (out[0], out[1], out[2])


def _vec3(v) -> tuple[float, float, float]:
    return (float(v[0]), float(v[1]), float(v[2]))


def gnss_fix_from_ros(fix: dict, twist: dict | None) -> GnssFix:
    """The one place a NavSatFix (and the Twist paired with it) becomes a fednav GnssFix, built and
    validated by the wire model (a refusal raises pydantic's ValidationError).

    ``fix``: t, lat_deg, lon_deg, height_m, pos_std_enu_m (optional fix_type, constellation);
    ``twist``: t, vel_enu_mps, vel_std_enu_mps. With a Twist: the 3-D velocity variant; without
    one (``twist is None``): the position-only variant, no velocity invented.
    """
    out = {
        "t": fix["t"],
        "lat_deg": fix["lat_deg"],
        "lon_deg": fix["lon_deg"],
        "height_m": fix["height_m"],
        "pos_std_enu_m": _vec3(fix["pos_std_enu_m"]),
        "fix_type": fix.get("fix_type", "single"),
        "constellation": fix.get("constellation", "GPS"),
    }
    if twist is not None:
        out["vel_enu_mps"] = _vec3(twist["vel_enu_mps"])
        out["vel_std_enu_mps"] = _vec3(twist["vel_std_enu_mps"])
    return GnssFix.model_validate(out)


_SERVICE_CONSTELLATION = {1: "GPS", 2: "GLO", 4: "BDS", 8: "GAL"}
#: NavSatStatus.status -> GnssFix.fix_type (STATUS_FIX 0, STATUS_SBAS_FIX 1, STATUS_GBAS_FIX 2)
_NAVSAT_FIX_TYPE = {0: "single", 1: "sbas", 2: "dgnss"}


@dataclass
class _ImuState:
    stamp_ns: int
    rate_flu_rps: np.ndarray
    accel_flu_mps2: np.ndarray


@dataclass
class _WaitingFix:
    stamp_ns: int
    fix: dict  # gnss_fix_from_ros's ``fix``
    position: GnssFix  # the position-only fix, already validated


@dataclass
class _WaitingTwist:
    stamp_ns: int
    twist: dict  # gnss_fix_from_ros's ``twist`` (its velocity already validated)


def _stamp_ns(header) -> int:
    return int(header.stamp.sec) * _NS + int(header.stamp.nanosec)


@dataclass
class RosInput:
    """Decodes ROS 2 samples of the configured topics into fednav wire models (ImuSample, GnssFix).

    Keeps what a stream needs across samples (the previous Imu of each sensor, a NavSatFix or Twist
    waiting for its partner). A NavSatFix whose Twist has not come once the bridge's stamp time
    (the newest header.stamp decoded) is ``twist_wait_s`` past it, or when the receiver's next fix
    arrives, goes on as a position-only fix, counted in :attr:`counters` (``fix_without_velocity``);
    a Twist without its fix after the same wait is dropped (``twist_without_fix``). The exact
    stamps of the decoded samples go to the configuration's :class:`StampMemory` (outputs at those
    times carry them). Use from one thread; :attr:`counters` may be read from another (its keys are
    all present from the start)."""

    cfg: Ros2Config
    counters: Counter = field(default_factory=lambda: Counter(dict.fromkeys(COUNTER_NAMES, 0)))
    _by_key: dict[str, Ros2Input] = field(default_factory=dict)
    _imu: dict[str, _ImuState] = field(default_factory=dict)
    _fix: dict[str, list[_WaitingFix]] = field(default_factory=dict)  # waiting for their Twist, per sensor
    _twist: dict[str, list[_WaitingTwist]] = field(default_factory=dict)  # waiting for their NavSatFix
    _ready: list = field(default_factory=list)  # position-only fixes given up on, for the next decode
    _clock_ns: int | None = None  # the bridge's stamp time: the newest header.stamp decoded
    #: samples received per configured topic (decoded or not), and the first stamp decoded
    received: Counter = field(default_factory=Counter)
    _first_ns: int | None = None
    _silent_said: set = field(default_factory=set)

    #: a configured topic without a single sample while the others have run this long (stamp time)
    #: is named once (:meth:`newly_silent`): a typo in a topic or a type shows as nothing else
    SILENT_AFTER_S = 5.0

    def __post_init__(self):
        self.store = typestore(self.cfg.distro)
        self.stamps = bridge_state(self.cfg).stamps
        self._with_twist = {
            i.sensor_id for i in self.cfg.inputs if i.type == "geometry_msgs/msg/TwistWithCovarianceStamped"
        }
        self._tol_ns = round(self.cfg.pair_tolerance_s * _NS)
        self._wait_ns = round(self.cfg.twist_wait_s * _NS)
        for i in self.cfg.inputs:
            self._by_key[self._match_key(topic_key(self.cfg, i.topic, i.type, any_hash=True))] = i

    def _match_key(self, key: str) -> str:
        """The part of a key that names the input (rmw_zenoh: without the type hash)."""
        return key.rsplit("/", 1)[0] if self.cfg.carrier == "rmw_zenoh" else key

    def key_exprs(self) -> list[str]:
        return [topic_key(self.cfg, i.topic, i.type, any_hash=True) for i in self.cfg.inputs]

    def input_of(self, key: str) -> Ros2Input | None:
        return self._by_key.get(self._match_key(key))

    def _t(self, stamp_ns: int) -> float:
        return stamp_ns_to_t(stamp_ns, self.cfg.stamp_time_base, self.cfg.leap_seconds)

    def decode(self, key: str, payload: bytes) -> list[tuple[str, str, WireModel]]:
        """(kind, sensor_id, wire model) for the intake, oldest first; raises RosDecodeError
        (reason, text). The models are validated: the intake takes them as they are."""
        inp = self.input_of(key)
        if inp is None:
            raise RosDecodeError("unknown_key", f"no [ros2] input for {key[:120]}")
        self.received[inp.topic] += 1
        try:
            msg = self.store.deserialize_cdr(payload, inp.type)
            stamp_ns = _stamp_ns(msg.header)
        except Exception as exc:  # rosbags raises several types on truncated or garbled CDR
            raise RosDecodeError("bad_cdr", f"{inp.topic}: {type(exc).__name__}: {str(exc)[:80]}") from None
        if stamp_ns == 0:  # the service's reason for a time before GPS time 0, said in ROS's words
            raise RosDecodeError("out_of_range", f"{inp.topic}: header.stamp is 0: the driver does not stamp")
        try:
            if inp.type == "sensor_msgs/msg/Imu":
                items = self._imu_in(inp, msg, stamp_ns)
            elif inp.type == "sensor_msgs/msg/NavSatFix":
                items = self._fix_in(inp, msg, stamp_ns)
            elif inp.type == "geometry_msgs/msg/TwistWithCovarianceStamped":
                items = self._twist_in(inp, msg, stamp_ns)
            else:  # a type of the sensor registry (e.g. FluidPressure: the barometer)
                items = self._registry_in(inp, msg, stamp_ns)
        except RosDecodeError:
            raise
        except (TypeError, ValueError, AttributeError, IndexError) as exc:
            raise RosDecodeError("bad_cdr", f"{inp.topic}: {exc}") from None
        finally:
            self._advance(stamp_ns)
        out, self._ready = self._ready + items, []
        return out

    def newly_silent(self) -> list[str]:
        """Texts naming each configured topic that has had no sample while the others' stamps span
        :data:`SILENT_AFTER_S`, once per topic (a topic that starts later is not named again)."""
        if self._first_ns is None or self._clock_ns is None:
            return []
        if self._clock_ns - self._first_ns < self.SILENT_AFTER_S * _NS:
            return []
        out = []
        others = sum(self.received.values())
        for i in self.cfg.inputs:
            if self.received[i.topic] or i.topic in self._silent_said:
                continue
            self._silent_said.add(i.topic)
            out.append(
                f"ROS 2 bridge: no sample on {i.topic} ({i.type}, key "
                f"{topic_key(self.cfg, i.topic, i.type, any_hash=True)}) in {self.SILENT_AFTER_S:g} s of "
                f"the robot's time, while {others} arrived on the other topics: check the topic's name and "
                "type against the robot's (ros2 topic list -t, or a Zenoh subscriber on its keys), or "
                "take it out of [ros2] inputs"
            )
        return out

    def silent_topics(self) -> list[str]:
        """The configured topics named by :meth:`newly_silent` that still have no sample."""
        return sorted(t for t in self._silent_said if not self.received[t])

    def _registry_in(self, inp, msg, stamp_ns: int) -> list[tuple[str, str, WireModel]]:
        """A message of a type a sensor registry entry decodes, straight into its wire model."""
        from pydantic import ValidationError

        from fednav.service import sensors

        kind, decode = sensors.ros2_decoder(inp.type)
        try:
            m = decode(msg, self._t(stamp_ns), inp.sensor_id)
        except ValidationError as err:
            raise RosDecodeError(*_why(err, f"{kind}/{inp.sensor_id}: ")) from None
        except ValueError as exc:
            raise RosDecodeError("absurd_value", f"{kind}/{inp.sensor_id}: {exc}") from None
        return [] if m is None else [(kind, inp.sensor_id, m)]

    def flush(self) -> list[tuple[str, str, WireModel]]:
        """Every fix still waiting for its Twist, position-only (end of a stream)."""
        for sid, waiting in self._fix.items():
            for w in waiting:
                self._give_up(sid, w)
            waiting.clear()
        out, self._ready = self._ready, []
        return out

    # waiting fixes and twists against the stamp time
    def _advance(self, stamp_ns: int) -> None:
        if self._first_ns is None:
            self._first_ns = stamp_ns
        if self._clock_ns is None or stamp_ns > self._clock_ns:
            self._clock_ns = stamp_ns
        now = self._clock_ns
        for sid, waiting in self._fix.items():
            old = [w for w in waiting if now - w.stamp_ns > self._wait_ns]
            for w in old:
                waiting.remove(w)
                self._give_up(sid, w)
        for waiting in self._twist.values():
            old = [w for w in waiting if now - w.stamp_ns > self._wait_ns]
            for w in old:
                waiting.remove(w)
                self.counters["twist_without_fix"] += 1

    def _give_up(self, sid: str, w: _WaitingFix) -> None:
        """A fix whose Twist did not come: on as position only (never dropped), counted."""
        self.counters["fix_without_velocity"] += 1
        self._ready.append(("gnss_fix", sid, w.position))

    # Imu: rates (FLU) -> increments (RFU) over the interval since the previous stamp
    def _imu_in(self, inp: Ros2Input, msg, stamp_ns: int) -> list[tuple[str, str, WireModel]]:
        w = np.array([msg.angular_velocity.x, msg.angular_velocity.y, msg.angular_velocity.z], dtype=float)
        a = np.array(
            [msg.linear_acceleration.x, msg.linear_acceleration.y, msg.linear_acceleration.z], dtype=float
        )
        missing = imu_without_rates(msg)
        if missing:  # an orientation-only driver (e.g. an AHRS's filter output): no rates to integrate
            raise RosDecodeError(
                "ros_no_rates",
                f"{inp.topic}: Imu without {missing} ({missing}_covariance[0] = -1, ROS's 'no estimate'): "
                "fednav integrates the rates; publish the raw IMU topic (e.g. /imu/data_raw)",
            )
        prev = self._imu.get(inp.sensor_id)
        if prev is not None and stamp_ns == prev.stamp_ns:
            raise RosDecodeError("duplicate", f"{inp.topic}: Imu stamp repeated")
        self._imu[inp.sensor_id] = _ImuState(stamp_ns, w, a)
        if prev is None:
            return []
        if stamp_ns < prev.stamp_ns:
            # the interval reopens at this sample: a sensor restart or clock step backwards goes
            # on to the intake on its new time base (its rules recognise a time jump); the stamp
            # time restarts there too
            self._clock_ns = stamp_ns
            raise RosDecodeError("time_backwards", f"{inp.topic}: Imu stamp went back; interval reopened")
        t = self._t(stamp_ns)
        dt_s = (stamp_ns - prev.stamp_ns) / _NS  # from the integer stamps, one rounding
        try:
            sample = imu_sample_from_rates(
                t, dt_s, w, a, prev.rate_flu_rps, prev.accel_flu_mps2, self.cfg.imu_integration
            )
        except ValidationError as err:
            raise RosDecodeError(*_why(err, f"imu/{inp.sensor_id}: ")) from None
        self.stamps.remember(t, stamp_ns)
        return [("imu", inp.sensor_id, sample)]

    def _fix_in(self, inp: Ros2Input, msg, stamp_ns: int) -> list[tuple[str, str, WireModel]]:
        sid = inp.sensor_id
        if msg.status.status < 0:  # NO_FIX (-1), or STATUS_UNKNOWN (-2, since Jazzy)
            name = {-1: "NO_FIX", -2: "STATUS_UNKNOWN"}.get(msg.status.status, str(msg.status.status))
            raise RosDecodeError("ros_no_fix", f"{inp.topic}: NavSatFix status {name}: no fix to use")
        cov_known = msg.position_covariance_type != 0
        std = (
            _diag_std(msg.position_covariance, (0, 4, 8), self.cfg.fix_std_m)
            if cov_known
            else (self.cfg.fix_std_m,) * 3
        )
        t = self._t(stamp_ns)
        fix = {
            "t": t,
            "lat_deg": float(msg.latitude),
            "lon_deg": float(msg.longitude),
            "height_m": float(msg.altitude),
            "pos_std_enu_m": std,
            "fix_type": _NAVSAT_FIX_TYPE.get(int(msg.status.status), "single"),
            "constellation": _SERVICE_CONSTELLATION.get(int(msg.status.service), "MULTI"),
        }
        try:  # the fix is checked alone first: with or without a Twist, a bad one goes no further
            position = gnss_fix_from_ros(fix, None)
        except ValidationError as err:
            raise RosDecodeError(*_why(err, f"gnss_fix/{sid}: ")) from None
        self.stamps.remember(t, stamp_ns, replace=False)
        if sid not in self._with_twist:  # no Twist topic for this receiver: position only
            return [("gnss_fix", sid, position)]
        # the receiver's next fix: a fix of another epoch still waiting gets no Twist any more
        waiting = self._fix.setdefault(sid, [])
        for w in [w for w in waiting if abs(w.stamp_ns - stamp_ns) >= self._tol_ns]:
            waiting.remove(w)
            self._give_up(sid, w)
        twists = self._twist.get(sid, [])
        best = min(twists, key=lambda o: abs(o.stamp_ns - stamp_ns), default=None)
        if best is not None and abs(best.stamp_ns - stamp_ns) < self._tol_ns:
            twists.remove(best)
            return [("gnss_fix", sid, self._paired(sid, fix, best.twist))]
        waiting.append(_WaitingFix(stamp_ns, fix, position))
        while len(waiting) > PAIR_BUFFER:
            self._give_up(sid, waiting.pop(0))
        return []

    def _twist_in(self, inp: Ros2Input, msg, stamp_ns: int) -> list[tuple[str, str, WireModel]]:
        sid = inp.sensor_id
        lin = msg.twist.twist.linear
        v = np.array([lin.x, lin.y, lin.z], dtype=float)
        std = _diag_std(msg.twist.covariance, (0, 7, 14), self.cfg.vel_std_mps)
        if inp.velocity_frame == "ned":
            v = NED_TO_ENU @ v
            std = (std[1], std[0], std[2])
        t = self._t(stamp_ns)
        tw = {"t": t, "vel_enu_mps": _vec3(v), "vel_std_enu_mps": std}
        # the velocity checked alone first: a bad Twist never spoils or holds back its fix
        probe = {"t": t, "lat_deg": 0.0, "lon_deg": 0.0, "height_m": 0.0, "pos_std_enu_m": (1.0,) * 3}
        try:
            gnss_fix_from_ros(probe, tw)
        except ValidationError as err:
            raise RosDecodeError(*_why(err, f"gnss_fix/{sid}: Twist: ")) from None
        fixes = self._fix.get(sid, [])
        best = min(fixes, key=lambda o: abs(o.stamp_ns - stamp_ns), default=None)
        if best is not None and abs(best.stamp_ns - stamp_ns) < self._tol_ns:
            fixes.remove(best)
            return [("gnss_fix", sid, self._paired(sid, best.fix, tw))]
        waiting = self._twist.setdefault(sid, [])
        waiting.append(_WaitingTwist(stamp_ns, tw))
        while len(waiting) > PAIR_BUFFER:
            waiting.pop(0)
            self.counters["twist_without_fix"] += 1
        return []

    @staticmethod
    def _paired(sid: str, fix: dict, twist: dict) -> GnssFix:
        try:  # both halves were validated on arrival
            return gnss_fix_from_ros(fix, twist)
        except ValidationError as err:
            raise RosDecodeError(*_why(err, f"gnss_fix/{sid}: ")) from None


def imu_without_rates(msg) -> str | None:
    """The part of a sensor_msgs/Imu its driver says it does not carry (``angular_velocity`` or
    ``linear_acceleration``: element 0 of its covariance is -1, the message's own convention for
    "no estimate of this data element"), or None. Such a message's zeros are no measurement."""
    for name in ("angular_velocity", "linear_acceleration"):
        if float(getattr(msg, f"{name}_covariance")[0]) == -1.0:
            return name
    return None


def imu_sample_from_rates(
    t: float,
    dt_s: float,
    rate_flu_rps: np.ndarray,
    accel_flu_mps2: np.ndarray,
    prev_rate_flu_rps: np.ndarray,
    prev_accel_flu_mps2: np.ndarray,
    integration: str = "trapezoid",
) -> ImuSample:
    """ImuSample for the interval (t - dt_s, t] from two Imu samples' rates (FLU), built and validated
    by the wire model (a refusal raises pydantic's ValidationError)."""
    if integration == "trapezoid":
        w = 0.5 * (rate_flu_rps + prev_rate_flu_rps)
        a = 0.5 * (accel_flu_mps2 + prev_accel_flu_mps2)
    else:
        w, a = rate_flu_rps, accel_flu_mps2
    return ImuSample.model_validate(
        {
            "t": t,
            "dt_s": dt_s,
            "dtheta_rad": _vec3(FLU_TO_RFU @ w * dt_s),
            "dvel_mps": _vec3(FLU_TO_RFU @ a * dt_s),
        }
    )


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
        self.stamps = bridge_state(cfg).stamps
        self.datum: dict[str, np.ndarray] = {}  # pipeline -> datum llh (rad)
        if cfg.outputs.datum is not None:
            lat, lon, h = cfg.outputs.datum
            self._fixed_datum = np.array([math.radians(lat), math.radians(lon), h])
        else:
            self._fixed_datum = None

    def stamp(self, t: float | None) -> tuple[int, int]:
        """header.stamp of a fednav time: the exact stamp of the input decoded at that time when the
        bridge remembers one, else :func:`t_to_stamp`; (0, 0) for None."""
        if t is None:
            return 0, 0
        ns = self.stamps.stamp_ns(t)
        if ns is None:
            ns = t_to_stamp_ns(t, self.cfg.stamp_time_base, self.cfg.leap_seconds)
        sec, nsec = divmod(ns, _NS)
        return int(sec), int(nsec)

    def _header(self, t: float | None, frame_id: str):
        sec, ns = self.stamp(t)
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

    ``put(key, payload, attachment)`` is the transport (Zenoh lives in zenoh_io/app). ``gid``: the
    session's base GID (16 bytes). Each publisher's attachment carries its own GID
    (:meth:`gid_of`): the GID of its graph token when :func:`graph_tokens` declared one for this
    configuration (rmw_zenoh's XXH3-128 of the token), else :func:`derived_gid` of the base GID."""

    def __init__(self, cfg: Ros2Config, pipelines: list[str], put, gid: bytes | None = None):
        self.cfg = cfg
        self.enc = RosEncoder(cfg)
        self.put = put
        o = cfg.outputs
        self.pipelines = list(o.pipelines) or list(pipelines)
        self.tf_pipeline = o.tf_pipeline or (self.pipelines[0] if self.pipelines else None)
        self.gid = gid if gid is not None else bytes(GID_SIZE)
        self.seq: dict[str, int] = {}
        self._state = bridge_state(cfg)
        self._gids: dict[tuple[str, str], bytes] = {}  # GIDs taken from graph tokens

    def gid_of(self, topic: str, msgtype: str) -> bytes:
        """The GID of this bridge's publisher of ``topic`` (see the class docstring)."""
        t = "/" + topic.lstrip("/")
        g = self._gids.get((t, msgtype))
        if g is None:
            g = self._state.gids.get(("MP", t, msgtype))
            if g is None:  # no token (yet): not cached, a token declared later still wins
                return derived_gid(self.gid, t, msgtype)
            self._gids[(t, msgtype)] = g
        return g

    def _send(self, topic: str, msg) -> None:
        if not topic:
            return
        key = topic_key(self.cfg, topic, msg.__msgtype__)
        att = None
        if self.cfg.carrier == "rmw_zenoh" and self.cfg.attachment != "none":
            n = self.seq[key] = self.seq.get(key, 0) + 1
            att = rmw_attachment(
                n,
                time.time_ns(),
                self.gid_of(topic, msg.__msgtype__),
                keyed=self.cfg.attachment == "rmw_zenoh_keyed",
            )
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
