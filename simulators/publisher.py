"""``fednav-sim run``: publish a scenario's sensor stream and truth over Zenoh.

Reliable delivery with blocking congestion control (a fast publisher slows down instead of
dropping); the first message waits for a matched subscriber. ``speed`` paces publication in
wall-clock time (2 = twice real time); 0 publishes as fast as the receiver keeps up.

Nothing is lost at the end: before the session closes, :func:`drain` waits until the service
has received what was put (see there); closing with messages still queued in Zenoh's
transmission queue or the socket loses them.
"""

from __future__ import annotations

import sys
import time
from collections.abc import Iterable

import zenoh

from fednav.service import imu_batch as imu_batch_codec
from fednav.service import keys as fkeys
from fednav.service.config import ZenohConfig
from fednav.service.messages import ImuSample, InitialNav, WireModel
from fednav.service.transport.zenoh_io import PUBLISHER_BLOCK_WAIT_S, make_config
from fednav.simulators.scenario import duration_arg

#: IMU samples per published ImuBatch by default (``--imu-batch``; 1 = one JSON ImuSample each)
DEFAULT_IMU_BATCH = 10


#: longest wait (s) at the end of a stream for the receiver to take what is still queued
DRAIN_TIMEOUT_S = 300.0


class MatchTimeout(RuntimeError):
    pass


def session_args_problem(connect: list[str] | None, zenoh_config: str | None) -> str | None:
    """What is wrong with a publisher's ``--connect`` endpoints or ``--zenoh-config`` file (one
    line for the command to print before it exits 2), or None."""
    from pathlib import Path

    from fednav.service.transport.zenoh_io import endpoint_error

    for ep in connect or []:
        if endpoint_error(ep):
            return endpoint_error(ep)
    if zenoh_config and not Path(zenoh_config).is_file():
        return f"--zenoh-config {zenoh_config}: no such file"
    return None


#: ``--match-timeout S`` of the publishers: a finite number of seconds > 0 (the same rule as a
#: scenario's ``--duration``)
timeout_arg = duration_arg


class MatchWatch:
    """Whether a publisher's subscribers went away after it matched (a link closed, the service
    stopped): a put then returns as usual and reaches nobody, which the put does not say. Watches
    one publisher (a stream's first) from its first match on, through Zenoh's matching listener."""

    def __init__(self, publisher: zenoh.Publisher):
        self._publisher = publisher
        #: the publisher is a vehicle's InitialNav probe that a fednav service matched (set by the user)
        self.served = False
        self._unmatched: list[bool] = []
        self._listener = publisher.declare_matching_listener(
            lambda status: None if status.matching else self._unmatched.append(True)
        )

    def lost(self) -> bool:
        """The subscribers went away at some point (and may be back), or are gone now."""
        return bool(self._unmatched) or not self._publisher.matching_status.matching

    def close(self) -> None:
        self._listener.undeclare()


def vehicle_probe_key(key: str) -> str:
    """The InitialNav key of the vehicle of ``key`` (``{prefix}/{vehicle}/...``): what a publisher
    waits on and watches for a service (:func:`publish_stream`, ``fednav-sim fleet``)."""
    prefix, vehicle = key.split("/", 2)[:2]
    return fkeys.init(vehicle, prefix)


#: how long a publisher waits, once a fednav service is there, for a subscription to its vehicle's
#: inputs (a fleet member that subscribes per vehicle it owns declares it when the vehicle's
#: announcement reaches it; any other service has one already); past it the stream starts anyway
ANNOUNCE_WAIT_S = 3.0


class Announcement:
    """A vehicle announced while its sensors are published: the ``keys.sensors_alive`` liveliness
    token, and a publisher on the same key (never put on) whose matching says that a subscription
    covering the vehicle's inputs exists. A fleet member that subscribes per vehicle it owns
    (``[intake] subscribe = 'owned'``) subscribes to an announced vehicle of its own before its
    first message, so the IMU published before the first InitialNav or aiding message reaches it
    (a ground start's static alignment starts with the IMU, not with the first fix)."""

    def __init__(self, session: zenoh.Session, vehicle_key: str):
        prefix, vehicle = vehicle_key.split("/", 2)[:2]
        key = fkeys.sensors_alive(vehicle, prefix)
        self.vehicle = vehicle
        self._token = session.liveliness().declare_token(key)
        self._pub = session.declare_publisher(key)

    @property
    def heard(self) -> bool:
        """A subscription covers the vehicle's inputs (its owner's, or a service's of every vehicle)."""
        return self._pub.matching_status.matching

    def close(self) -> None:
        for d in (self._pub, self._token):
            try:
                d.undeclare()
            except zenoh.ZError:
                pass


def wait_heard(announcements: Iterable[Announcement], timeout_s: float = ANNOUNCE_WAIT_S) -> list[str]:
    """Wait (at most ``timeout_s``) until a subscription covers every announced vehicle's inputs;
    the vehicles still unheard then (no fleet member with room owns them, or the router's access
    control drops the announcement: their streams start anyway, and a member finds each at its
    first InitialNav or aiding message), logged on stderr."""
    waiting = list(announcements)
    deadline = time.monotonic() + timeout_s
    while waiting:
        waiting = [a for a in waiting if not a.heard]
        if not waiting or time.monotonic() > deadline:
            break
        time.sleep(0.01)
    if waiting:
        names = ", ".join(a.vehicle for a in waiting[:5]) + (" ..." if len(waiting) > 5 else "")
        print(
            f"fednav publisher: {len(waiting)} vehicle(s) not subscribed by a service {timeout_s:g} s after "
            f"their announcement ({names}): published anyway; a fleet member finds each at its first "
            "InitialNav or aiding message",
            file=sys.stderr,
            flush=True,
        )
    return [a.vehicle for a in waiting]


def status_keys(published: Iterable[str]) -> list[str]:
    """The service status queryables (``{prefix}/{vehicle}/service/status``) of the vehicles whose
    keys were published: the keys :func:`drain` queries."""
    out = {}
    for key in published:
        chunks = key.split("/", 2)
        if len(chunks) == 3 and fkeys.valid_name(chunks[1]):
            out[fkeys.service(chunks[1], "status", chunks[0])] = None
    return list(out)


def drain(session: zenoh.Session, keys: list[str], timeout_s: float = DRAIN_TIMEOUT_S) -> bool | None:
    """Wait until everything this session put has reached the service(s) serving ``keys``.

    A put returns once its message is queued in this process; a receiver that is behind leaves
    messages in Zenoh's transmission queue and the sockets, and closing the session then loses
    them (a simulator at ``--speed 0`` against a loaded service lost half its stream). Zenoh has no
    flush, so each key is queried at the data's own priority with blocking congestion control: the
    query travels the same links in the same queue behind the data, and the service's status
    queryable can only see it once every message before it has been read off the link (into the
    service's intake channel). (A querier's matching status cannot tell beforehand whether a
    service serves the key: its declaration waits behind the same backlog.) True: every service
    answered; False: one did not answer in ``timeout_s``; None: every query ended without a reply
    (no fednav service serves the keys: nothing to wait for)."""
    deadline = time.monotonic() + timeout_s
    answered = unanswered = 0
    for key in keys:  # the first waits for the backlog; the others then answer at once
        left = deadline - time.monotonic()
        if left <= 0:
            unanswered += 1
            continue
        t0 = time.monotonic()
        replies = session.get(
            key, timeout=left, congestion_control=zenoh.CongestionControl.BLOCK, priority=zenoh.Priority.DATA
        )
        if any(reply.ok is not None for reply in replies):
            answered += 1
        elif time.monotonic() - t0 >= left - 0.05:  # no reply before the timeout: a service is stuck
            unanswered += 1
        # else: finished without a reply, nobody serves the key (no fednav service for it)
    if answered + unanswered == 0:
        return None
    return unanswered == 0


def services_visible(session: zenoh.Session, prefixes: Iterable[str], timeout_s: float = 1.0) -> bool:
    """Whether any fednav service's liveliness token (``{prefix}/_services/*``) is visible to this
    session: with :func:`drain` answered by none, it tells "no service serves these vehicles" (a
    service is there) from "this client may not ask" (a router's access control lets a simulator
    neither query status nor see the tokens)."""
    for prefix in prefixes:
        if any(
            r.ok is not None for r in session.liveliness().get(f"{prefix}/_services/*", timeout=timeout_s)
        ):
            return True
    return False


def session_config(
    connect: list[str] | None = None,
    listen: list[str] | None = None,
    zenoh_config: str | None = None,
) -> zenoh.Config:
    """The simulator's Zenoh config: a client of the service on loopback, no discovery.

    Client mode: the service (a peer) routes our samples to its other clients (dashboards,
    subscribers); two peers connected only through the service would not see each other. A
    ``--zenoh-config`` file is overlaid on these safe defaults (``make_config``); explicit
    ``--connect`` endpoints replace the file's. A put blocked by a receiver that is behind waits
    up to ``PUBLISHER_BLOCK_WAIT_S`` (unless the file says otherwise), not Zenoh's 5 s after which
    the link is closed and the rest of the stream silently dropped."""
    return make_config(
        ZenohConfig(mode="client", listen=[], connect=["tcp/127.0.0.1:7447"]),
        listen=listen or None,
        connect=connect or None,
        config_file=zenoh_config,
        block_wait_s=PUBLISHER_BLOCK_WAIT_S,
    )


def open_session(config: zenoh.Config, wait_s: float) -> zenoh.Session:
    """Open a publisher's client session, waiting up to ``wait_s`` for its service (or router) to
    answer (:func:`zenoh_io.open_waiting`: a publisher started a moment before its service waits
    for it). :class:`MatchTimeout` when nothing answered in that time (a command line says so and
    exits 3, not a traceback)."""
    from fednav.service.transport.zenoh_io import NoAnswer, open_waiting

    try:
        return open_waiting(config, wait_s)
    except NoAnswer as exc:
        raise MatchTimeout(str(exc)) from exc


def report_end(result: dict, prog: str, vehicles: list[str] | None = None) -> int:
    """What a command line says after :func:`publish_stream` (``result``), on stderr, and its exit
    code: 4 when the subscribers went away during the stream (what was published meanwhile reached
    nobody); 5 when no fednav service serves the vehicle(s) (``vehicles``; the end-of-stream
    status queries had no reply, :func:`drain`, while a service is visible,
    :func:`services_visible`: the messages reached other subscribers only, e.g. a service serving
    other vehicles, which counts them as ``unserved_vehicle``); a warning and 0 when no service is
    visible at all (none on the bus, or access control) or the service did not confirm the end in
    time; else nothing, 0."""
    if result.get("drained") is None and result.get("messages") and not result.get("subscriber_lost"):
        vs = list(vehicles or [])
        names = ", ".join(repr(v) for v in vs[:3]) + (f" and {len(vs) - 3} more" if len(vs) > 3 else "")
        names = names or "the published vehicle(s)"
        if result.get("services_seen"):
            print(
                f"{prog}: no fednav service serves vehicle {names}: the messages reached other "
                "subscribers only (a service serving other vehicles refuses them as unserved_vehicle); "
                'start the service with --vehicle (or vehicles = [...] / ["*"] in its config) for this '
                "name, or publish under the name it serves",
                file=sys.stderr,
            )
            return 5
        # no service visible: none on the bus (other subscribers only), or a router's access
        # control that lets this client neither ask a status nor see the services: not an error
        print(
            f"{prog}: warning: no fednav service confirmed vehicle {names} (none answered its status "
            "at the end of the stream and none is visible: no service on the bus, or this client may "
            "not ask, e.g. behind a router's access control)",
            file=sys.stderr,
        )
    if result.get("subscriber_lost"):
        print(
            f"{prog}: the subscribers went away during the stream (a link closed or the "
            "service stopped): messages published meanwhile reached nobody",
            file=sys.stderr,
        )
        return 4
    if result.get("drained") is False:
        print(
            f"{prog}: the service did not confirm the end of the stream in time: "
            "the last messages may not have reached it",
            file=sys.stderr,
        )
    return 0


def publish_stream(
    stream: Iterable[tuple[str, WireModel]],
    *,
    speed: float = 1.0,
    connect: list[str] | None = None,
    listen: list[str] | None = None,
    zenoh_config: str | None = None,
    match_timeout_s: float = 30.0,
    linger_s: float = 0.5,
    imu_batch: int = DEFAULT_IMU_BATCH,
    drain_timeout_s: float = DRAIN_TIMEOUT_S,
) -> dict:
    """Publish (key, message) pairs in order; returns counts and timing.

    ``imu_batch`` N > 1: consecutive IMU samples of a key go out as one ImuBatch of N samples
    (:mod:`service.imu_batch`, binary, encoding ``application/octet-stream;fednav.ImuBatch/1``),
    published when its last sample is due; every other message goes out at its own time, so an
    aiding message still precedes the IMU samples after it. N = 1: one JSON ImuSample each.

    At the end, :func:`drain` waits (at most ``drain_timeout_s``) for the service(s) to take what
    is still queued; with no fednav service on the keys, a ``linger_s`` pause instead. The result's
    ``drained``: True, False (a service did not answer in time, or the subscribers went away
    during the stream: the tail may be lost) or None; ``subscriber_lost``: the first key's
    subscribers went away at some point after it matched (a link closed, the service stopped):
    what was put then reached nobody."""
    session = open_session(
        session_config(connect=connect, listen=listen, zenoh_config=zenoh_config),
        match_timeout_s,
    )
    pubs: dict[str, zenoh.Publisher] = {}
    batches: dict[str, list[ImuSample]] = {}

    def pub_for(key: str, encoding: str) -> zenoh.Publisher:
        p = pubs.get(key)
        if p is None:
            p = session.declare_publisher(
                key,
                encoding=zenoh.Encoding(encoding),
                congestion_control=zenoh.CongestionControl.BLOCK,
                reliability=zenoh.Reliability.RELIABLE,
            )
            pubs[key] = p
        return p

    n = 0
    t_first = None
    wall0 = None
    watch: MatchWatch | None = None  # the first publisher's matching, from its first match on
    announced: dict[str, Announcement] = {}  # vehicle -> its announcement, while it is published
    try:
        for key, msg in stream:
            batched = imu_batch > 1 and isinstance(msg, ImuSample)
            p = pub_for(key, imu_batch_codec.ENCODING if batched else type(msg).encoding())
            vehicle = key.split("/", 2)[1]
            if vehicle not in announced:
                announced[vehicle] = a = Announcement(session, key)
                if t_first is not None and watch is not None and watch.served:
                    wait_heard([a])  # a vehicle that starts later in the stream
            if t_first is None:
                # a service is there when it subscribes to the vehicle's InitialNav key: every
                # service does (a fleet member that subscribes per vehicle it owns hears every
                # vehicle's InitialNav and fixes, but its IMU only once the vehicle is its own)
                # (or, for a receiver of one's own, when it subscribes to the first key)
                probe = pub_for(vehicle_probe_key(key), InitialNav.encoding())
                deadline = time.monotonic() + match_timeout_s
                while not (probe.matching_status.matching or p.matching_status.matching):
                    if time.monotonic() > deadline:
                        raise MatchTimeout(f"no subscriber matched {key} within {match_timeout_s} s")
                    time.sleep(0.01)
                watch = MatchWatch(probe if probe.matching_status.matching else p)
                watch.served = probe.matching_status.matching
                if watch.served:  # a fednav service: the vehicle's owner subscribes to it
                    wait_heard(announced.values())
                t_first = msg.t
                wall0 = time.monotonic()
            if batched:
                pending = batches.setdefault(key, [])
                pending.append(msg)
                n += 1
                if len(pending) < imu_batch:
                    continue
            if speed > 0:
                delay = wall0 + (msg.t - t_first) / speed - time.monotonic()
                if delay > 0:
                    time.sleep(delay)
            if batched:
                p.put(imu_batch_codec.encode_samples(batches.pop(key)))
            else:
                p.put(msg.to_json())
                n += 1
        for key, pending in batches.items():  # the last, partial batches
            if pending:
                pubs[key].put(imu_batch_codec.encode_samples(pending))
        wall = time.monotonic() - (wall0 or time.monotonic())
        drained = drain(session, status_keys(pubs), drain_timeout_s) if pubs else None
        seen = None
        if drained is None:  # no fednav service answered: let the transmission queues empty a little
            time.sleep(linger_s)
            seen = services_visible(session, {k.split("/", 1)[0] for k in pubs})
        lost = watch is not None and watch.lost()
        if lost:
            drained = False
    finally:
        if watch is not None:
            watch.close()
        for p in pubs.values():
            p.undeclare()
        for a in announced.values():
            a.close()
        session.close()
    return {"messages": n, "wall_s": wall, "drained": drained, "subscriber_lost": lost, "services_seen": seen}
