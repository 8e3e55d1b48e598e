"""Zenoh behind one module: session config, publishers, the intake subscriber and queryables.

The rest of the service sees plain data: (wall_time, key, payload bytes) from intake, and
``publish(key, model)`` for outputs. Nothing here blocks inside a Zenoh callback: intake uses a
bounded Zenoh FIFO channel (a full channel back-pressures reliable, blocking publishers instead
of dropping) read by our own thread; queryables are served from a thread too.
"""

from __future__ import annotations

import json
import logging
import re
import threading
import time
from collections.abc import Callable

import zenoh

from fednav.service.config import ZenohConfig
from fednav.service.messages import WireModel

log = logging.getLogger("fednav.service")
#: Keys of fednav's safe defaults, overlaid on a ``--zenoh-config`` file unless the file sets them
#: itself (values in :func:`make_config`). Zenoh's own defaults listen on every interface
#: (``tcp/[::]:0``) and discover peers by UDP multicast (224.0.0.224:7446) and gossip.
SAFE_KEYS = (
    "mode",
    "listen/endpoints",
    "connect/endpoints",
    "scouting/multicast/enabled",
    "scouting/gossip/enabled",
)


def _file_keys(path: str) -> tuple[zenoh.Config, dict]:
    """The file loaded by Zenoh, and the file's own content as plain JSON (parsed by Zenoh's JSON5
    parser through the free-form ``metadata`` field, so comments, unquoted keys and trailing
    commas read exactly as Zenoh reads them). A file that is not JSON5 (Zenoh also reads YAML)
    gives no content: its keys are then judged by their resolved values alone (:func:`_explicit`)."""
    loaded = zenoh.Config.from_file(path)
    with open(path, encoding="utf-8") as f:
        text = f.read()
    raw = zenoh.Config()
    try:
        raw.insert_json5("metadata", text)
        content = json.loads(raw.get_json("metadata"))
    except zenoh.ZError:
        content = {}
    return loaded, content if isinstance(content, dict) else {}


def _explicit(content: dict, loaded: zenoh.Config, key: str) -> bool:
    """True when the file sets ``key``: written in the file, or (through an included file) resolved to
    a value other than Zenoh's built-in default."""
    node = content
    for part in key.split("/"):
        if not isinstance(node, dict) or part not in node:
            break
        node = node[part]
    else:
        return True
    return json.loads(loaded.get_json(key)) != json.loads(zenoh.Config().get_json(key))


#: the Zenoh config key of how long one put with blocking congestion control may wait for room in
#: the transmission queue before Zenoh closes the link (microseconds; Zenoh's default is 5 s)
BLOCK_WAIT_KEY = "transport/link/tx/queue/congestion_control/block/wait_before_close"
#: that wait for fednav's input publishers (``fednav-sim``, ``fednav-replay``, the fleet simulator,
#: the ROS 2 publisher), seconds: their back-pressure is meant to be lossless, and with Zenoh's
#: 5 s a service that read nothing from one of its links for 5 s (a backlog shared by several
#: publishers) had the publisher's link closed and every later put dropped without an error
#: (measured: four ``fednav-sim run --speed 0 --imu-batch 1`` of a 300 s demo against one service
#: delivered 3.7-10.3 k of their 35.1 k messages each, and exited 0). The same bound as the
#: end-of-stream drain (``simulators.publisher.DRAIN_TIMEOUT_S``); a peer that died is still
#: found by the session lease (10 s), not by this wait.
PUBLISHER_BLOCK_WAIT_S = 300.0


#: Zenoh link protocols that reach another machine or user (the outputs guard applies to them)
NETWORK_LINK_PROTOCOLS = ("tcp", "tls", "udp", "quic", "ws", "serial", "unixpipe", "vsock")


def egress_drop_rules() -> list[dict]:
    """Zenoh QoS overwrite (``qos/network``) for the service's session: every put it sends over a
    network link (:data:`NETWORK_LINK_PROTOCOLS`) goes with congestion control DROP, whatever the
    publisher asked. A blocking put waits for room in each matching link's queue, its own outputs
    and the sensor data it routes to other clients alike, so one subscriber that stops reading held
    every other client and the service's own intake: measured with a client whose callback never
    returns, subscribed to ``fednav/**``, 20 fleet vehicles at 1x: no Solution reached another
    client for 15 s, and 1,760 of 12,020 never did. With this rule a reader that cannot keep up
    loses its own samples once its link's queue is full (Zenoh's ``wait_before_drop``), and only
    its own. Not on the service's local unix socket (its ``--shards`` processes, whose inputs are
    routed through it and must stay lossless), and not on its own subscribers: the intake still
    back-pressures the sensor publishers (:class:`Intake`)."""
    return [
        {
            "id": "readers-never-hold-the-service",
            "messages": ["put", "delete"],
            "flows": ["egress"],
            "link_protocols": list(NETWORK_LINK_PROTOCOLS),
            "overwrite": {"congestion_control": "drop"},
        }
    ]


def outputs_guard(prefix: str) -> dict:
    """Zenoh access control that refuses, from every remote session, publications, queryables and
    liveliness tokens under the service's output keys (``{prefix}/*/nav/**``,
    ``{prefix}/*/service/**``) over any network link (:data:`NETWORK_LINK_PROTOCOLS`; the service's
    own shards connect over a private unix socket and publish their vehicles' outputs through it):
    only the service itself publishes solutions and health, answers status and declares the
    ``{vehicle}/service/alive`` tokens, so a client on the bus cannot spoof them to the other
    clients routed through the service. Everything else is allowed (``_services`` and ``_fleet``
    keys included: the services of a fleet exchange them through each other's sessions)."""
    outputs = [f"{prefix}/*/nav/**", f"{prefix}/*/service/**"]
    return {
        "enabled": True,
        "default_permission": "allow",
        "rules": [
            {
                "id": "no-spoofed-outputs",
                "permission": "deny",
                "flows": ["ingress"],
                # liveliness tokens too: ``{prefix}/{vehicle}/service/alive`` says which vehicles
                # a service serves, and a client's token there announced a vehicle nobody served
                "messages": ["put", "delete", "declare_queryable", "reply", "liveliness_token"],
                "key_exprs": outputs,
            }
        ],
        # every network link; a session over a local unix socket (the service's own shard
        # processes, ``--shards``: the socket lives in a directory only the service's user can
        # open) is the service itself
        "subjects": [{"id": "every-remote-session", "link_protocols": list(NETWORK_LINK_PROTOCOLS)}],
        "policies": [
            {
                "id": "outputs-are-the-services",
                "rules": ["no-spoofed-outputs"],
                "subjects": ["every-remote-session"],
            }
        ],
    }


def make_config(
    zc: ZenohConfig | None = None,
    listen: list[str] | None = None,
    connect: list[str] | None = None,
    config_file: str | None = None,
    outputs_prefix: str | None = None,
    block_wait_s: float | None = None,
    own_id: bool = True,
) -> zenoh.Config:
    """The session config: fednav's safe defaults, a json5 file overlaid on them, explicit endpoints.

    Safe defaults (``SAFE_KEYS``), from ``zc``: its mode, loopback listen endpoints, its connect
    endpoints, multicast scouting and gossip off (both follow ``zc.multicast_scouting``). A config
    file (``config_file``, else ``zc.config_file``) is loaded by Zenoh as written (TLS, access control,
    anything else); only the safe keys the file does not set itself keep fednav's values, so a file
    with only mode and listen does not turn multicast scouting on. ``listen``/``connect`` (the
    command line's ``--listen``/``--connect``; None: not given) replace the endpoints of both.
    ``outputs_prefix`` (the service's prefix) adds :func:`outputs_guard` as access control unless the
    file configures ``access_control`` itself, and :func:`egress_drop_rules` as ``qos/network``
    unless the file configures that. ``block_wait_s`` (an input publisher's
    :data:`PUBLISHER_BLOCK_WAIT_S`) sets how long a blocking put may wait before Zenoh closes the
    link (:data:`BLOCK_WAIT_KEY`) unless the file sets it; None keeps Zenoh's 5 s (the service,
    whose puts over network links do not block: :func:`egress_drop_rules`). ``own_id`` False: the
    file's ``id`` is not used and Zenoh draws one (the local shards 1..K-1 of ``--shards K``, which
    run with shard 0's command line: two sessions under one id do not connect, and a shard's
    vehicles went unserved without a word).
    """
    zc = zc or ZenohConfig()
    path = config_file or (str(zc.config_file) if zc.config_file else None)
    if path:
        c, content = _file_keys(path)
    else:
        c, content = zenoh.Config(), {}
    discovery = "true" if zc.multicast_scouting else "false"
    safe = {
        "mode": json.dumps(zc.mode),
        "listen/endpoints": json.dumps(zc.listen),
        "connect/endpoints": json.dumps(zc.connect),
        "scouting/multicast/enabled": discovery,
        "scouting/gossip/enabled": discovery,
    }
    for key in SAFE_KEYS:
        if not (path and _explicit(content, c, key)):
            c.insert_json5(key, safe[key])
    if outputs_prefix is not None and not (path and _explicit(content, c, "access_control")):
        c.insert_json5("access_control", json.dumps(outputs_guard(outputs_prefix)))
    if outputs_prefix is not None and not (path and _explicit(content, c, "qos/network")):
        c.insert_json5("qos/network", json.dumps(egress_drop_rules()))
    if outputs_prefix is not None and not (path and _explicit(content, c, "timestamping")):
        # the service's runtime stamps every sample that arrives without a timestamp, at ingress
        # (before any queue): Health's latency starts there (``Intake``)
        c.insert_json5("timestamping/enabled", "{ router: true, peer: true, client: true }")
    if block_wait_s is not None and not (path and _explicit(content, c, BLOCK_WAIT_KEY)):
        c.insert_json5(BLOCK_WAIT_KEY, str(int(block_wait_s * 1e6)))
    if not own_id and path and _explicit(content, c, "id"):
        c.insert_json5("id", "null")
    if listen is not None:
        c.insert_json5("listen/endpoints", json.dumps(listen))
    if connect is not None:
        c.insert_json5("connect/endpoints", json.dumps(connect))
    return c


class Publishers:
    """Declared publishers per key (reliable; blocking or dropping congestion control). In the
    service, blocking holds for its local subscribers and shard sockets only: its session sends
    every put over a network link with DROP (:func:`egress_drop_rules`)."""

    def __init__(self, session: zenoh.Session, block: bool = True):
        self.session = session
        self.cc = zenoh.CongestionControl.BLOCK if block else zenoh.CongestionControl.DROP
        self._pubs: dict[str, zenoh.Publisher] = {}
        self._lock = threading.Lock()

    def publisher(self, key: str, msg_type: type[WireModel]) -> zenoh.Publisher:
        with self._lock:
            pub = self._pubs.get(key)
            if pub is None:
                pub = self.session.declare_publisher(
                    key,
                    encoding=zenoh.Encoding(msg_type.encoding()),
                    congestion_control=self.cc,
                    reliability=zenoh.Reliability.RELIABLE,
                )
                self._pubs[key] = pub
            return pub

    def publish(self, key: str, msg: WireModel) -> None:
        self.publisher(key, type(msg)).put(msg.to_json())

    def put_bytes(self, key: str, payload: bytes, attachment: bytes | None = None) -> None:
        """Publish bytes of another encoding (the ROS 2 bridge's CDR) with an optional attachment."""
        with self._lock:
            pub = self._pubs.get(key)
            if pub is None:
                pub = self.session.declare_publisher(
                    key, congestion_control=self.cc, reliability=zenoh.Reliability.RELIABLE
                )
                self._pubs[key] = pub
        pub.put(payload, attachment=attachment)

    def forget(self, vehicle: str, prefix: str) -> None:
        """Undeclare a vehicle's publishers (its outputs ``{prefix}/{vehicle}/...`` and its fleet
        handover states ``.../state/{vehicle}/...``): a vehicle released by the service."""
        own, state = f"{prefix}/{vehicle}/", f"/state/{vehicle}/"
        with self._lock:
            gone = [k for k in self._pubs if k.startswith(own) or (state in k and "/_fleet/" in k)]
            pubs = [self._pubs.pop(k) for k in gone]
        for p in pubs:
            try:
                p.undeclare()
            except zenoh.ZError:
                pass

    def undeclare_all(self) -> None:
        with self._lock:
            for p in self._pubs.values():
                try:
                    p.undeclare()
                except zenoh.ZError:
                    pass
            self._pubs.clear()


#: most messages one drain of the intake hands on together (``deliver_many``)
DRAIN_MAX = 256
#: after the shutdown drain's deadline, the drain in progress is let finish for at least this
#: long (s): it is not interrupted, and DRAIN_MAX messages of a slow consumer (2 ms each: 0.5 s)
#: outlast a short ``drain_s``
ABANDON_GRACE_S = 2.0


class Intake:
    """Subscribes to input keys and hands (arrival time, key, payload) to ``deliver`` from a thread.

    Samples wait in bounded Zenoh FIFO channels (filled by Zenoh's own threads, without Python's
    lock: a full channel back-pressures reliable, blocking publishers instead of dropping) and are
    read by our thread. The arrival time (monotonic seconds, the start of the latency the service
    reports) is the sample's Zenoh timestamp, which the service's runtime puts on each sample at
    ingress (``timestamping`` in :func:`make_config`); a sample without one (a user's config that
    turns timestamping off) or with an implausible one (a remote clock) counts from its reading.
    """

    def __init__(
        self,
        session: zenoh.Session,
        key_exprs: list[str],
        deliver: Callable[[float, str, bytes], None],
        capacity: int = 4096,
        order_key: Callable[[bytes], float] | None = None,
        deliver_many: Callable[[list[tuple[float, str, bytes]]], None] | None = None,
        wanted: Callable[[str], bool] | None = None,
        forward: Callable[[str], object | None] | None = None,
    ):
        self._subs = [
            session.declare_subscriber(
                k, zenoh.handlers.FifoChannel(capacity), allowed_origin=zenoh.Locality.REMOTE
            )
            for k in key_exprs
        ]
        self._deliver = deliver
        self._deliver_many = deliver_many
        # wanted(key) False: a message this process is known not to serve (another shard's or
        # fleet member's vehicle), dropped before its arrival time and payload are read
        self._wanted = wanted
        self.unwanted = 0
        # forward(key): the ShardFeed (service.transport.shard_feed) of the local shard that serves
        # the key's vehicle, or None to deliver it here; each feed gets one frame per drain
        self._forward = forward
        self._feeds: set = set()
        self._order_key = order_key
        # one subscription, no reordering (the service's own intake): the thread blocks in the
        # channel's recv (Zenoh releases the GIL while it waits) instead of polling; stop()
        # closes the channel by undeclaring it, and what had arrived is still delivered first
        self._blocking = len(self._subs) == 1 and order_key is None
        self._handlers = [s.handler for s in self._subs]
        self._stop = threading.Event()
        self._abandon = threading.Event()  # set by stop() when its drain outlasts the deadline
        self._left = 0  # messages not run at shutdown (counted when abandoned)
        self._thread = threading.Thread(target=self._run, name="fednav-intake", daemon=True)
        self._thread.start()

    @staticmethod
    def arrival(sample: zenoh.Sample) -> float:
        """Monotonic time of the sample's arrival in the process (see the class docstring)."""
        now = time.monotonic()
        ts = sample.timestamp
        if ts is None:
            return now
        # the timestamp's NTP64 seconds (since the UNIX epoch), not get_time(), whose datetime
        # costs ~1.5 us of every message
        age = time.time() - ts.get_time_as_ntp64().as_secs_f64()
        return now - age if 0.0 <= age < 60.0 else now

    def _drain(self) -> bool:
        if self._order_key is not None:
            return self._drain_ordered()
        got = False
        wanted = self._wanted
        forward = self._forward
        for s in self._subs:
            sample = s.try_recv()
            while sample is not None:
                got = True
                key = str(sample.key_expr)
                if wanted is not None and not wanted(key):
                    self.unwanted += 1
                elif forward is not None and (feed := forward(key)) is not None:
                    feed.add(self.arrival(sample), key, sample.payload.to_bytes())
                    self._feeds.add(feed)
                else:
                    self._deliver_one(self.arrival(sample), key, sample.payload.to_bytes())
                sample = s.try_recv()
        self._flush_feeds()
        return got

    def _flush_feeds(self) -> None:
        if self._feeds:
            for feed in self._feeds:
                feed.flush()
            self._feeds.clear()

    def _deliver_one(self, wall: float, key: str, payload: bytes) -> None:
        try:
            self._deliver(wall, key, payload)
        except Exception:  # routing must survive any one message
            log.exception("intake: delivery of %s failed", key[:200])

    def _drain_ordered(self) -> bool:
        """Everything waiting in every subscription, delivered in ``order_key`` (sensor time) order.

        Separate subscriptions (one per ROS 2 topic) lose the order across topics; samples of one
        publisher reach the FIFOs in publication order, so whatever one drain finds is complete up
        to its newest sample per topic, and sorting it restores the time order across topics."""
        batch = []
        for s in self._subs:
            sample = s.try_recv()
            while sample is not None:
                batch.append((self.arrival(sample), str(sample.key_expr), sample.payload.to_bytes()))
                sample = s.try_recv()
        if len(self._subs) > 1:
            batch.sort(key=lambda item: self._order_key(item[2]))
        for item in batch:
            self._deliver_one(*item)
        return bool(batch)

    def _run(self) -> None:
        if self._blocking:
            self._run_blocking()
            return
        while not self._stop.is_set():
            if not self._drain():
                self._stop.wait(0.0005)
        self._drain()  # what already arrived

    def _run_blocking(self) -> None:
        handler = self._handlers[0]
        many = self._deliver_many
        wanted = self._wanted
        forward = self._forward
        while True:
            if self._abandon.is_set():  # stop()'s deadline passed: what is left is not run
                self._left = self._count_left(handler)
                return
            try:
                sample = handler.recv()
            except zenoh.ZError:  # "channel is empty and closed": undeclared by stop()
                return
            if many is None and forward is None:
                key = str(sample.key_expr)
                if wanted is not None and not wanted(key):
                    self.unwanted += 1
                else:
                    self._deliver_one(self.arrival(sample), key, sample.payload.to_bytes())
                continue
            # this sample and what else has arrived (at most DRAIN_MAX): ours handed on together
            # (deliver_many) or one by one, each local shard's as one frame of its feed
            batch = []
            for i in range(DRAIN_MAX):
                if i:
                    try:
                        sample = handler.try_recv()
                    except zenoh.ZError:
                        break
                    if sample is None:
                        break
                key = str(sample.key_expr)
                if wanted is not None and not wanted(key):
                    self.unwanted += 1
                elif forward is not None and (feed := forward(key)) is not None:
                    feed.add(self.arrival(sample), key, sample.payload.to_bytes())
                    self._feeds.add(feed)
                else:
                    batch.append((self.arrival(sample), key, sample.payload.to_bytes()))
            self._flush_feeds()
            if not batch:
                continue
            if many is None:
                for item in batch:
                    self._deliver_one(*item)
                continue
            try:
                many(batch)
            except Exception:  # routing must survive any one drain
                log.exception("intake: delivery of %d messages failed", len(batch))

    @staticmethod
    def _count_left(handler) -> int:
        n = 0
        while True:
            try:
                if handler.try_recv() is None:
                    return n
            except zenoh.ZError:
                return n
            n += 1

    def stop(self, drain_s: float = 5.0) -> None:
        """Stop receiving; what had arrived is still delivered for at most ``drain_s`` (the inline
        intake runs it: the service's shutdown drain), the rest is counted in the log."""
        self._stop.set()
        if not self._blocking:
            self._thread.join(timeout=drain_s)
        for s in self._subs:  # closes the channels: a blocked recv returns what is left, then ends
            try:
                s.undeclare()
            except zenoh.ZError:
                pass
        if self._blocking:
            self._thread.join(timeout=drain_s)
            if self._thread.is_alive():  # still running what had arrived: stop after this drain
                self._abandon.set()
                grace = max(drain_s, ABANDON_GRACE_S)
                self._thread.join(timeout=grace)
                if self._thread.is_alive():
                    log.warning("intake: still running a drain %.1f s after shutdown began", drain_s + grace)
                else:
                    log.warning("intake: %d messages not run at shutdown (after %.1f s)", self._left, drain_s)


#: the polling intake's period (s): a drain at most every first figure while messages come (what
#: arrived meanwhile is taken together; a drain that ran longer is followed at once), the period
#: doubled per empty poll up to the second figure while nothing comes
OWNED_POLL_PERIOD_S = (0.001, 0.004)
#: discovery messages of a vehicle held until its new subscription's first sample (more are run
#: at once), and the longest they wait for it (s)
OWNED_EARLY_MAX = 256
OWNED_HOLD_MAX_S = 0.5


class _VehicleSub:
    """One owned vehicle's subscription (``{prefix}/{vehicle}/**``) and, until its own channel
    delivers, the messages its discovery keys received of the vehicle (``held``): a message that
    arrived before the subscription reaches only the discovery keys, one after it reaches both
    channels. At the channel's first sample the held messages older than it (Zenoh timestamps:
    the same sample carries the same one on both channels) are run before it, in order, and the
    others are its own messages' copies, dropped."""

    __slots__ = ("vehicle", "sub", "handler", "started", "held", "held_since", "ts0")

    def __init__(self, vehicle: str, sub) -> None:
        self.vehicle = vehicle
        self.sub = sub
        self.handler = sub.handler
        self.started = False
        self.held: list[tuple[object, tuple[float, str, bytes]]] = []
        self.held_since = 0.0
        self.ts0 = None  # timestamp of the channel's first sample


class OwnedIntake:
    """The intake of a fleet member that subscribes per vehicle it serves (``[intake] subscribe
    = 'owned'``): one subscription per owned vehicle (everything under ``{prefix}/{vehicle}/``,
    one channel, in arrival order) and, for every vehicle, its low-rate inputs (the discovery
    keys: InitialNav, fixes and the other aiding kinds of the sensor registry, not the IMU), from
    which the service finds new vehicles that are its own.

    With every member subscribed to every vehicle's inputs, each of S members received the whole
    fleet's messages to keep 1/S of them; now it receives its own vehicles' and the rest's
    discovery keys (with JSON IMU samples at 200 Hz and fixes at 10 Hz, a twentieth of a foreign
    vehicle's messages; no other member's outputs at all). Zenoh's routers then carry each
    vehicle's IMU stream to one member only.

    A discovery key's message of a vehicle with its own subscription is dropped (counted in
    ``discovery_copies``); until that subscription's first sample it is held, and the ones older
    than that sample (Zenoh timestamps) are run before it, in order (:class:`_VehicleSub`), so a
    vehicle's order is kept across the moment it is subscribed, even in a burst.
    Several channels cannot be waited on together, so the thread polls them (``try_recv``,
    ~0.3 us each when empty) once per period (``OWNED_POLL_PERIOD_S``: each wake-up takes what
    arrived since, which costs less per message than waking for each). Drains
    are handed on as :class:`Intake`'s are (``deliver_many``, at most ``DRAIN_MAX`` messages).
    :meth:`watch` and :meth:`unwatch` are called from any thread except Zenoh's callbacks (a
    declaration waits for the session).
    """

    def __init__(
        self,
        session: zenoh.Session,
        prefix: str,
        discovery_exprs: list[str],
        deliver_many: Callable[[list[tuple[float, str, bytes]]], None],
        wanted: Callable[[str], bool] | None = None,
        capacity: int = 4096,
        vehicle_capacity: int = 1024,
    ):
        self._session = session
        self._prefix = prefix
        self._capacity = vehicle_capacity
        self._disc = [
            session.declare_subscriber(
                k, zenoh.handlers.FifoChannel(capacity), allowed_origin=zenoh.Locality.REMOTE
            )
            for k in discovery_exprs
        ]
        self._disc_handlers = tuple(s.handler for s in self._disc)
        self._deliver_many = deliver_many
        self._wanted = wanted
        self.unwanted = 0
        self.discovery_copies = 0
        self._lock = threading.Lock()
        self._vsubs: dict[str, _VehicleSub] = {}
        self._polled: tuple[_VehicleSub, ...] = ()
        self._turn = 0
        self._more = False
        self._closing: list = []  # undeclared subscriptions whose channels are read to the end
        self._stop = threading.Event()
        self._abandon = threading.Event()
        self._left = 0
        self._thread = threading.Thread(target=self._run, name="fednav-intake", daemon=True)
        self._thread.start()

    # --- the vehicles subscribed -------------------------------------------------------------
    def vehicles(self) -> set[str]:
        return set(self._vsubs)

    @property
    def watched(self):
        """The vehicles subscribed (a live view: for membership tests only)."""
        return self._vsubs.keys()

    def watch(self, vehicle: str) -> bool:
        """Subscribe to ``vehicle``'s keys (nothing if already); False when the service is stopping."""
        if vehicle in self._vsubs:
            return True
        with self._lock:
            if vehicle in self._vsubs:
                return True
            if self._stop.is_set():
                return False
            from fednav.service import keys

            sub = self._session.declare_subscriber(
                keys.vehicle_inputs_selector(vehicle, self._prefix),
                zenoh.handlers.FifoChannel(self._capacity),
                allowed_origin=zenoh.Locality.REMOTE,
            )
            vs = _VehicleSub(vehicle, sub)
            self._vsubs[vehicle] = vs
            self._polled = (*self._polled, vs)
        return True

    def unwatch(self, vehicle: str) -> None:
        """Drop ``vehicle``'s subscription (what its channel holds is still delivered)."""
        with self._lock:
            vs = self._vsubs.pop(vehicle, None)
            if vs is None:
                return
            self._polled = tuple(v for v in self._polled if v is not vs)
            self._closing.append(vs)
        try:
            vs.sub.undeclare()
        except zenoh.ZError:
            pass

    def set_vehicles(self, vehicles: set[str]) -> None:
        """Subscribe to exactly ``vehicles``."""
        for v in set(self._vsubs) - vehicles:
            self.unwatch(v)
        for v in vehicles:
            self.watch(v)

    # --- the thread ----------------------------------------------------------------------------
    def _drain(self) -> list[tuple[float, str, bytes]]:
        batch: list[tuple[float, str, bytes]] = []
        arrival = Intake.arrival
        wanted = self._wanted
        vsubs = self._vsubs
        # the discovery keys first: a message published before a vehicle's subscription was
        # declared reaches only them, and is run before that subscription's first delivery; at
        # most half a drain of them, so that a flood of other vehicles' fixes cannot starve the
        # vehicles' own channels
        for h in self._disc_handlers:
            while len(batch) < DRAIN_MAX // 2:
                try:
                    sample = h.try_recv()
                except zenoh.ZError:
                    break
                if sample is None:
                    break
                key = str(sample.key_expr)
                parts = key.split("/", 2)
                vs = vsubs.get(parts[1]) if len(parts) > 1 else None
                if vs is not None:
                    ts = sample.timestamp
                    if vs.started:  # a copy of what its channel delivers, unless from before it
                        if ts is None or vs.ts0 is None or not ts < vs.ts0:
                            self.discovery_copies += 1
                            continue
                    elif ts is not None and len(vs.held) < OWNED_EARLY_MAX:
                        if not vs.held:
                            vs.held_since = time.monotonic()
                        vs.held.append((ts, (arrival(sample), key, sample.payload.to_bytes())))
                        continue
                if wanted is not None and not wanted(key):
                    self.unwanted += 1
                    continue
                batch.append((arrival(sample), key, sample.payload.to_bytes()))
        self._more = len(batch) >= DRAIN_MAX // 2  # discovery keys left: drain again at once
        if self._closing:
            with self._lock:
                closing, self._closing = self._closing, []
            for vs in closing:  # an undeclared subscription: what it had received, then gone
                self._read(vs, batch, DRAIN_MAX * 4)
        polled = self._polled
        now = None
        for vs in polled:
            if vs.held:  # its channel delivered nothing since: what was held goes on alone
                now = now or time.monotonic()
                if now - vs.held_since > OWNED_HOLD_MAX_S:
                    batch.extend(item for _, item in vs.held)
                    vs.held = []
        if polled:  # from a rotating start: a full drain does not always serve the same vehicles
            self._turn = k = (self._turn + 1) % len(polled)
            for vs in polled[k:] + polled[:k]:
                if len(batch) >= DRAIN_MAX:
                    break
                self._read(vs, batch, DRAIN_MAX)
        return batch

    def _read(self, vs: _VehicleSub, batch: list, limit: int) -> None:
        h = vs.handler
        arrival = Intake.arrival
        while len(batch) < limit:
            try:
                sample = h.try_recv()
            except zenoh.ZError:  # closed and empty: undeclared
                return
            if sample is None:
                return
            if not vs.started:
                vs.started = True
                vs.ts0 = ts0 = sample.timestamp
                for ts, item in vs.held:  # from before the subscription: run first, in order
                    if ts0 is None or ts < ts0:
                        batch.append(item)
                    else:
                        self.discovery_copies += 1  # (this channel delivers it)
                vs.held = []
            batch.append((arrival(sample), str(sample.key_expr), sample.payload.to_bytes()))

    def _run(self) -> None:
        short, long = OWNED_POLL_PERIOD_S
        period = short
        while True:
            if self._abandon.is_set():
                return
            t0 = time.monotonic()
            batch = self._drain()
            if batch:
                period = short
                try:
                    self._deliver_many(batch)
                except Exception:  # routing must survive any one drain
                    log.exception("intake: delivery of %d messages failed", len(batch))
                if len(batch) >= DRAIN_MAX or self._more:
                    continue  # more is waiting
            elif self._stop.is_set():
                return  # stopped and everything that had arrived delivered
            else:
                period = min(long, period * 2.0)
            rest = period - (time.monotonic() - t0)
            if rest > 0.0:
                time.sleep(rest)

    def stop(self, drain_s: float = 5.0) -> None:
        """Stop receiving (subscriptions undeclared); what had arrived is still delivered for at
        most ``drain_s``, then the drain in progress is let finish."""
        with self._lock:
            self._stop.set()
            subs = [vs.sub for vs in self._vsubs.values()] + self._disc
        for s in subs:
            try:
                s.undeclare()
            except zenoh.ZError:
                pass
        self._thread.join(timeout=drain_s)
        if self._thread.is_alive():
            self._abandon.set()
            self._thread.join(timeout=max(drain_s, ABANDON_GRACE_S))
            if self._thread.is_alive():
                log.warning("intake: still running a drain %.1f s after shutdown began", drain_s)
            else:
                log.warning("intake: messages not run at shutdown (after %.1f s)", drain_s)


#: one reply: (concrete key, payload, encoding)
Reply = tuple[str, bytes, str]


class QueryServer:
    """Answers queries from a thread with ``answer(query key expression) -> [Reply, ...]``: every
    resource whose concrete key intersects the query's key expression, each under its own key and
    typed encoding (a wildcard query gets one reply per vehicle and resource). Each queryable
    replies only with the resources under its own key expression: a query that reaches several of
    them (``fednav/**`` and the queryables of vehicles ``v1``, ``v2`` and the service's health)
    gets each resource once, not once per queryable."""

    def __init__(
        self, session: zenoh.Session, key_exprs: list[str], answer: Callable[[zenoh.KeyExpr], list[Reply]]
    ):
        self._qs = [session.declare_queryable(k, zenoh.handlers.FifoChannel(64)) for k in key_exprs]
        self._scopes = [zenoh.KeyExpr(k) for k in key_exprs]
        self._answer = answer
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, name="fednav-queries", daemon=True)
        self._thread.start()

    def _reply(self, query, scope: zenoh.KeyExpr | None = None) -> None:
        try:
            for key, payload, encoding in self._answer(query.key_expr):
                if scope is not None and not zenoh.KeyExpr(key).intersects(scope):
                    continue  # another of the service's queryables answers it
                query.reply(key, payload, encoding=zenoh.Encoding(encoding))
        except Exception as exc:  # a bad query must not kill the server
            try:
                query.reply_err(str(exc))
            except zenoh.ZError:
                pass
        finally:
            query.drop()

    def _run(self) -> None:
        if len(self._qs) == 1:  # one queryable (a '*' service): blocked in its channel, no polling
            handler = self._qs[0].handler
            while True:
                try:
                    query = handler.recv()
                except zenoh.ZError:  # closed: undeclared by stop()
                    return
                self._reply(query)
        while not self._stop.is_set():
            got = False
            for q, scope in zip(self._qs, self._scopes, strict=True):
                query = q.try_recv()
                while query is not None:
                    got = True
                    self._reply(query, scope)
                    query = q.try_recv()
            if not got:
                self._stop.wait(0.01)

    def stop(self) -> None:
        self._stop.set()
        if len(self._qs) > 1:
            self._thread.join(timeout=5.0)
        for q in self._qs:  # closes the channels: a blocked recv ends
            try:
                q.undeclare()
            except zenoh.ZError:
                pass
        self._thread.join(timeout=5.0)


def intersects(key: str, key_expr: zenoh.KeyExpr) -> bool:
    """Whether a concrete key matches a (wildcard) key expression of a query."""
    return zenoh.KeyExpr(key).intersects(key_expr)


class Liveliness:
    """Liveliness tokens (``liveliness get`` / subscribers see them appear and vanish)."""

    def __init__(self, session: zenoh.Session):
        self.session = session
        self._tokens: dict[str, object] = {}
        self._lock = threading.Lock()

    def declare(self, key: str) -> None:
        with self._lock:
            if key not in self._tokens:
                self._tokens[key] = self.session.liveliness().declare_token(key)

    def undeclare(self, key: str) -> None:
        with self._lock:
            t = self._tokens.pop(key, None)
        if t is not None:
            try:
                t.undeclare()
            except zenoh.ZError:
                pass

    def keys(self, prefix: str) -> list[str]:
        """The declared tokens whose key starts with ``prefix``."""
        with self._lock:
            return [k for k in self._tokens if k.startswith(prefix)]

    def undeclare_all(self) -> None:
        with self._lock:
            for t in self._tokens.values():
                try:
                    t.undeclare()
                except zenoh.ZError:
                    pass
            self._tokens.clear()


class Watch:
    """A subscriber whose callback only hands (key, payload or None) to ``on_sample`` (None: a
    liveliness token vanished). ``liveliness=True`` watches tokens (with the ones already alive)."""

    def __init__(self, session: zenoh.Session, key_expr: str, on_sample, liveliness: bool = False):
        def cb(sample: zenoh.Sample) -> None:
            try:
                gone = sample.kind == zenoh.SampleKind.DELETE
                on_sample(str(sample.key_expr), None if gone else sample.payload.to_bytes())
            except Exception:  # a callback must never raise into Zenoh
                log.exception("watch %s: callback failed", key_expr)

        if liveliness:
            self._sub = session.liveliness().declare_subscriber(key_expr, cb, history=True)
        else:
            self._sub = session.declare_subscriber(key_expr, cb)

    def stop(self) -> None:
        try:
            self._sub.undeclare()
        except zenoh.ZError:
            pass


_ENDPOINT = re.compile(r"^(tcp|udp|tls|quic|ws|unixsock-stream|unixpipe|serial|vsock)/(.+)$")
_HOST_PORT = re.compile(r"^(\[[0-9A-Fa-f:.]+\]|[A-Za-z0-9_.\-]+):([0-9]{1,5})$")


class NoAnswer(RuntimeError):
    """:func:`open_waiting`: nothing answered on the session's endpoints in the time given."""


def open_waiting(config: zenoh.Config, wait_s: float) -> zenoh.Session:
    """Open a client session, waiting up to ``wait_s`` for something (a router, a service) to
    answer on its endpoints: a process started a moment before its router or service waits for it
    (a Zenoh client fails at once by default). :class:`NoAnswer` when nothing answered in that
    time. Tried in attempts of at most 0.5 s (Zenoh's open holds the interpreter until it returns,
    so Ctrl-C is seen between attempts). A config that sets ``connect/timeout_ms`` itself (a
    ``--zenoh-config`` file) gets one open with its own timeout."""
    own = json.loads(config.get_json("connect/timeout_ms")) is not None
    deadline = time.monotonic() + wait_s
    while True:
        left = deadline - time.monotonic()
        if not own:
            config.insert_json5("connect/timeout_ms", str(max(1, int(min(0.5, left) * 1000))))
        try:
            return zenoh.open(config)
        except zenoh.ZError as exc:
            if own or time.monotonic() >= deadline:
                endpoints = json.loads(config.get_json("connect/endpoints"))
                raise NoAnswer(
                    f"no fednav service or Zenoh router answered on "
                    f"{', '.join(endpoints) or 'its endpoints'} within {wait_s:g} s "
                    f"({str(exc).split(' at ')[0]})"
                ) from exc
            time.sleep(0.05)


def endpoint_error(endpoint: str) -> str | None:
    """Why a Zenoh endpoint string is not one (None if it looks right): ``PROTOCOL/HOST:PORT``."""
    m = _ENDPOINT.match(endpoint)
    if m is None:
        guess = endpoint.split("://")[-1].replace("tcp:", "")
        return (
            f"invalid Zenoh endpoint {endpoint!r}: expected PROTOCOL/HOST:PORT, "
            f"e.g. tcp/{guess if _HOST_PORT.match(guess) else '127.0.0.1:7447'}"
        )
    proto, rest = m.groups()
    if proto in ("tcp", "udp", "tls", "quic", "ws"):
        hp = _HOST_PORT.match(rest.split("#")[0])
        if hp is None or not 0 < int(hp.group(2)) < 65536:
            return f"invalid Zenoh endpoint {endpoint!r}: expected {proto}/HOST:PORT with a port 1-65535"
    return None
