"""Assignment of vehicles to service instances: rendezvous (highest-random-weight) hashing.

Every instance computes the same owner for a vehicle from the same member list, without a
coordinator: the owner is the member with the highest weight ``hash(vehicle, member)``. When a
member leaves, only its vehicles move (each to the member with its next highest weight); when
one joins, it takes only the vehicles for which it now has the highest weight. Used by the
service's local shards (``--shards K``: members ``shard0..shardK-1``) and by services sharing a
fleet (``[fleet] sharding = 'rendezvous'``: members = the Zenoh ids of the live services of the
group, from their liveliness tokens; :class:`FleetView`).
"""

from __future__ import annotations

import hashlib
from collections.abc import Iterable


def weight(vehicle: str, member: str) -> int:
    """The rendezvous weight of ``member`` for ``vehicle`` (64 bits of BLAKE2b: stable across
    processes, machines and Python versions, unlike ``hash()``)."""
    h = hashlib.blake2b(f"{member}\x00{vehicle}".encode(), digest_size=8)
    return int.from_bytes(h.digest(), "little")


def owner(vehicle: str, members: Iterable[str]) -> str | None:
    """The member that serves ``vehicle`` (None without members). Ties (64-bit) go to the
    smaller member name, so every instance agrees."""
    best, best_w = None, -1
    for m in members:
        w = weight(vehicle, m)
        if w > best_w or (w == best_w and best is not None and m < best):
            best, best_w = m, w
    return best


def ranked(vehicle: str, members: Iterable[str]) -> list[str]:
    """The members in ``vehicle``'s rendezvous order: highest weight first (ties: the smaller
    name first, as :func:`owner`)."""
    return sorted(members, key=lambda m: (-weight(vehicle, m), m))


def shard_name(index: int) -> str:
    return f"shard{index}"


def shard_of(vehicle: str, shards: int) -> int:
    """The local shard (0..shards-1) that serves ``vehicle``."""
    return int(owner(vehicle, [shard_name(i) for i in range(shards)])[len("shard") :])


class FleetView:
    """The live members of a fleet group (from their liveliness tokens) and who owns a vehicle.

    ``mine(vehicle)`` is cached per membership version; ``update(key, alive)`` is called from a
    Zenoh callback (cheap, under a lock) and bumps the version when the member set changes.

    Capacity: a member at its ``max_vehicles`` is *full* (its ``{prefix}/_services/{zid}/full``
    token; it also holds a ``.../holds/{vehicle}`` token for each vehicle it serves meanwhile). A
    full member keeps the vehicles it holds and owns no other: the owner of a vehicle is the first
    member in its rendezvous order that is not full or holds it (the vehicles a full member would
    have had go to their next member, not unserved); only when every member is full is the owner
    the first one, which refuses the vehicle and counts it (``vehicle_limit``). When a member is no
    longer full its vehicles come back to it (handed over like any move).
    """

    def __init__(self, me: str, holds_me=None):
        import threading

        self.me = me
        self._members: set[str] = {me}
        self._lock = threading.Lock()
        self._owner: dict[str, str] = {}
        self.version = 0
        self.changes = 0  # membership changes seen (Health of the service)
        #: False until this service has joined (its token declared): it owns nothing before, so a
        #: joining service first hears the members and their handover states, then takes its share
        self.active = False
        #: the other members that are full, and the vehicles each of them holds
        self._full: set[str] = set()
        self._holds: dict[str, set[str]] = {}
        #: services about to join (their ``joining`` tokens): not members yet
        self._joining: set[str] = set()
        #: this service is full (it owns only what ``holds_me(vehicle)`` says it holds)
        self.me_full = False
        self._holds_me = holds_me or (lambda vehicle: False)

    def _changed(self) -> None:
        self._owner = {}
        self.version += 1

    def set_full(self, member: str, full: bool) -> bool:
        """Another member's ``full`` token appeared or vanished; True when that changed anything."""
        with self._lock:
            if (member in self._full) == full or member == self.me:
                return False
            if full:
                self._full.add(member)
            else:
                self._full.discard(member)
                self._holds.pop(member, None)
            self._changed()
            return True

    def set_holds(self, member: str, vehicle: str, held: bool) -> bool:
        """A ``holds`` token of another member appeared or vanished; True when ownership may change
        (only a full member's holdings matter: until its ``full`` token, they change nothing)."""
        with self._lock:
            if member == self.me:
                return False
            d = self._holds.setdefault(member, set())
            if (vehicle in d) == held:
                return False
            if held:
                d.add(vehicle)
            else:
                d.discard(vehicle)
            if member in self._full:
                self._changed()
                return True
            return False

    def set_me_full(self, full: bool) -> bool:
        with self._lock:
            if self.me_full == full:
                return False
            self.me_full = full
            self._changed()
            return True

    def full_members(self) -> list[str]:
        with self._lock:
            return sorted(self._full & self._members | ({self.me} if self.me_full else set()))

    def _eligible(self, member: str, vehicle: str) -> bool:
        if member == self.me:
            return not self.me_full or self._holds_me(vehicle)
        return member not in self._full or vehicle in self._holds.get(member, ())

    def update(self, member: str, alive: bool) -> bool:
        """A member's token appeared (``alive``) or vanished; True when the set changed."""
        with self._lock:
            before = set(self._members)
            if alive:
                self._members.add(member)
            elif member != self.me:
                self._members.discard(member)
            if self._members == before:
                return False
            self._changed()
            self.changes += 1
            return True

    def members(self) -> list[str]:
        with self._lock:
            return sorted(self._members)

    def owner(self, vehicle: str) -> str:
        with self._lock:
            o = self._owner.get(vehicle)
            if o is None:
                if len(self._owner) > 200_000:
                    self._owner.clear()
                o = owner(vehicle, self._members)
                if self._full or self.me_full:  # capacity: the first member that can take it
                    order = ranked(vehicle, self._members)
                    o = next((m for m in order if self._eligible(m, vehicle)), order[0])
                self._owner[vehicle] = o
            return o

    def mine(self, vehicle: str) -> bool:
        return self.active and self.owner(vehicle) == self.me

    def set_joining(self, member: str, joining: bool) -> bool:
        """A service's ``joining`` token appeared or vanished; True when that changed the set."""
        with self._lock:
            if member == self.me or (member in self._joining) == joining:
                return False
            if joining:
                self._joining.add(member)
            else:
                self._joining.discard(member)
            return True

    def joiner_owner(self, vehicle: str) -> str | None:
        """The joining service that will own ``vehicle`` once it joins (rendezvous over the members
        and the joining services, with capacity as :meth:`owner` applies it: a full member that
        does not hold the vehicle is passed over, so the vehicle may fall to a joiner further down
        its order), or None (a member keeps it)."""
        with self._lock:
            if not self._joining - self._members:
                return None
            everyone = self._members | self._joining
            if self._full or self.me_full:  # a joining service is never full (not a member yet)
                order = ranked(vehicle, everyone)
                o = next((m for m in order if self._eligible(m, vehicle)), order[0])
            else:
                o = owner(vehicle, everyone)
            return o if o in self._joining and o not in self._members else None

    def heir(self, vehicle: str) -> str | None:
        """The member that owns ``vehicle`` when this one goes (the first other member in its
        rendezvous order that can take it; when every other is full, the first other, which
        refuses it), None without another member: where this member's handover states of the
        vehicle go (``keys.fleet_state_to``)."""
        with self._lock:
            order = [m for m in ranked(vehicle, self._members) if m != self.me]
            if not order:
                return None
            return next((m for m in order if self._eligible(m, vehicle)), order[0])


class StateCache:
    """The latest handover-state payload per (vehicle, pipeline), kept as bytes (parsed only
    when a vehicle is taken over)."""

    def __init__(self, max_vehicles: int = 100_000):
        import threading

        self._latest: dict[str, dict[str, bytes]] = {}
        self._at: dict[str, float] = {}  # vehicle -> monotonic time of its latest state
        self._lock = threading.Lock()
        self.max_vehicles = max_vehicles

    def put(self, vehicle: str, pipeline: str, payload: bytes) -> None:
        import time

        with self._lock:
            d = self._latest.get(vehicle)
            if d is None:
                if len(self._latest) >= self.max_vehicles:
                    return
                d = self._latest[vehicle] = {}
            d[pipeline] = payload
            self._at[vehicle] = time.monotonic()

    def recent(self, max_age_s: float) -> list[str]:
        """The vehicles whose latest state arrived within ``max_age_s``: the ones some member
        served lately (a member that died stopped publishing its vehicles' states at its death),
        newest first."""
        import time

        now = time.monotonic()
        with self._lock:
            at = [(t, v) for v, t in self._at.items() if now - t <= max_age_s]
        return [v for _, v in sorted(at, reverse=True)]

    def get(self, vehicle: str) -> dict[str, bytes]:
        with self._lock:
            return dict(self._latest.get(vehicle, {}))

    def snapshot(self) -> dict[str, dict[str, bytes]]:
        with self._lock:
            return {v: dict(d) for v, d in self._latest.items()}


#: what a handed-over state cannot know about the gap it is carried over: a change of the
#: vehicle's acceleration (the manoeuvre it can fly unseen, m/s^2) and of its turn rate (rad/s)
HANDOVER_ACC_CHANGE_MPS2 = 0.5
HANDOVER_RATE_CHANGE_RPS = 0.01


def handover_nav(st, t_start: float):
    """(NavState, InitStd) at ``t_start`` from a HandoverState at ``st.t``: carried over the gap
    with the state's motion (position and velocity with its acceleration, the attitude turned by its
    body rate: a vehicle in a 3 deg/s turn at 115 m/s accelerates 6 m/s^2, which a constant
    velocity would miss by 3.8 m/s after 0.65 s), the sigmas grown by the velocity sigma over the
    gap and by what the state cannot know (a change of acceleration, HANDOVER_ACC_CHANGE_MPS2, and
    of turn rate, HANDOVER_RATE_CHANGE_RPS, during the gap); the bias estimates kept (their sigmas
    are the service's own IMU prior). A state ahead of ``t_start`` (a taking service whose stream
    of the vehicle lags the giver's; up to 1 s is taken) is carried back the same way: held, an
    aircraft's state 1 s ahead was 117 m off and refused by the vehicle's own fix."""
    import math

    import numpy as np

    from fednav.service import earth
    from fednav.service.ins.alignment import InitStd
    from fednav.service.ins.mechanisation import NavState

    gap = t_start - st.t  # (negative: carried back)
    lat, lon = math.radians(st.lat_deg), math.radians(st.lon_deg)
    r_m, r_n = earth.radii(lat)
    v = np.asarray(st.vel_enu_mps, dtype=float)
    a = np.asarray(st.acc_enu_mps2, dtype=float)
    d = v * gap + 0.5 * a * gap * gap  # ENU displacement over the gap
    lat += d[1] / (r_m + st.height_m)
    lon += d[0] / ((r_n + st.height_m) * math.cos(lat))
    q = np.asarray(st.q_nb, dtype=float)
    q = earth.quat_mul(q, earth.rotvec_to_quat(np.asarray(st.rate_body_rps, dtype=float) * gap))
    P = np.asarray(st.P9, dtype=float).reshape(9, 9)
    sd = np.sqrt(np.clip(np.diagonal(P), 0.0, None))
    acc = HANDOVER_ACC_CHANGE_MPS2
    span = abs(gap)
    vel_sd = np.hypot(sd[3:6], acc * span)
    pos_sd = np.sqrt(sd[0:3] ** 2 + (sd[3:6] * span) ** 2 + (0.5 * acc * span * span) ** 2)
    att_sd = np.hypot(sd[6:9], HANDOVER_RATE_CHANGE_RPS * span)
    nav = NavState(
        t=float(t_start),
        lat_rad=lat,
        lon_rad=lon,
        h_m=st.height_m + d[2],
        vel_enu_mps=v + a * gap,
        q_nb=q / np.linalg.norm(q),
        gyro_bias_rps=np.asarray(st.gyro_bias_rps, dtype=float),
        accel_bias_mps2=np.asarray(st.accel_bias_mps2, dtype=float),
    )
    return nav, InitStd(pos_sd, vel_sd, att_sd)


__all__ = ["FleetView", "StateCache", "handover_nav", "owner", "ranked", "shard_name", "shard_of", "weight"]
