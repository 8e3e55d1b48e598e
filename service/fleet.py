"""Assignment of vehicles to service instances: rendezvous (highest-random-weight) hashing.

Every instance computes the same owner for a vehicle from the same member list, without a
coordinator: the owner is the member with the highest weight ``hash(vehicle, member)``. When a
member leaves, only its vehicles move (each to the member with its next highest weight); when
one joins, it takes only the vehicles for which it now has the highest weight. Used by the
service's local shards (``--shards K``: members ``shard0..shardK-1``).
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


def shard_name(index: int) -> str:
    return f"shard{index}"


def shard_of(vehicle: str, shards: int) -> int:
    """The local shard (0..shards-1) that serves ``vehicle``."""
    return int(owner(vehicle, [shard_name(i) for i in range(shards)])[len("shard") :])


__all__ = ["owner", "shard_name", "shard_of", "weight"]
