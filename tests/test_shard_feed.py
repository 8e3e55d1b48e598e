"""The pipe from shard 0 to a local shard (service/transport/shard_feed.py): messages arrive whole
and in order, nothing waits for a dead or missing shard, and every message not handed over is
counted."""

from __future__ import annotations

import os
import struct
import threading
import time

from fednav.service.transport.shard_feed import FeedIntake, ShardFeed


def _wait(cond, timeout_s: float = 5.0) -> bool:
    end = time.monotonic() + timeout_s
    while time.monotonic() < end:
        if cond():
            return True
        time.sleep(0.01)
    return cond()


def test_messages_cross_whole_and_in_order_and_the_pipes_end_stops_the_shard():
    r, w = os.pipe()
    feed = ShardFeed(1)
    feed.attach(w)
    got: list[tuple[float, str, bytes]] = []
    drains: list[int] = []
    ended = threading.Event()

    def many(items):
        drains.append(len(items))
        got.extend((wall, key, payload) for wall, key, payload in items)

    intake = FeedIntake(r, lambda *a: None, deliver_many=many, on_end=ended.set)
    sent = []
    ends = set()  # where each drain's frame ends, counted in messages
    for d in range(50):  # 50 drains of 1..40 messages, payloads up to 200 kB
        for j in range(1 + d % 40):
            item = (1000.0 + d + j * 1e-3, f"fednav/veh{d % 7}/sensor/imu/a", os.urandom(j * 5000 + 1))
            feed.add(*item)
            sent.append(item)
        feed.flush()
        ends.add(len(sent))
    feed.flush()  # nothing added: no empty frame
    assert _wait(lambda: len(got) == len(sent)), (len(got), len(sent))
    assert got == sent
    # whole frames only: what arrived together is handed on together, never a part of a frame
    assert {sum(drains[: i + 1]) for i in range(len(drains))} <= ends
    assert feed.forwarded == len(sent) and feed.lost == 0
    assert not ended.is_set()
    feed.close()  # shard 0 stops: the shard reads to the end of the pipe, then stops itself
    assert ended.wait(5.0)
    intake._thread.join(2.0)
    assert not intake._thread.is_alive() and intake.received == len(sent) and intake.bad_frames == 0
    os.close(r)


def test_a_missing_or_dead_shard_costs_shard_0_nothing_and_is_counted():
    feed = ShardFeed(1)
    feed.add(1.0, "fednav/v/sensor/imu/a", b"{}")
    feed.flush()  # no shard attached yet (not started, or restarting)
    assert feed.lost == 1 and feed.forwarded == 0
    r, w = os.pipe()
    feed.attach(w)
    os.close(r)  # the shard died: EPIPE
    for _ in range(3):
        feed.add(2.0, "fednav/v/sensor/imu/a", b"{}")
        feed.add(2.1, "fednav/v/sensor/imu/a", b"{}")
        t0 = time.monotonic()
        feed.flush()
        assert time.monotonic() - t0 < 0.5  # never waits for the shard
    assert _wait(lambda: feed.lost == 7), feed.lost
    assert feed.forwarded == 0
    r2, w2 = os.pipe()  # restarted: the next frames reach the new shard
    feed.attach(w2)
    got = []
    intake = FeedIntake(r2, lambda *a: got.append(a))
    feed.add(3.0, "fednav/v/sensor/imu/a", b"x")
    feed.flush()
    assert _wait(lambda: got == [(3.0, "fednav/v/sensor/imu/a", b"x")]), got
    assert feed.forwarded == 1 and feed.lost == 7
    intake.stop(0.5)
    feed.close()
    os.close(r2)


def test_a_stalled_shard_fills_a_bounded_queue_then_frames_are_dropped_and_counted(monkeypatch):
    from fednav.service.transport import shard_feed

    monkeypatch.setattr(shard_feed, "MAX_QUEUED_BYTES", 200_000)
    r, w = os.pipe()  # nobody reads: the pipe (widened to 1 MiB where allowed) fills, then the queue
    feed = ShardFeed(1)
    feed.attach(w)
    t0 = time.monotonic()
    for _ in range(400):
        feed.add(1.0, "fednav/v/sensor/gnss/a/fix", b"z" * 10_000)
        feed.flush()
    assert time.monotonic() - t0 < 1.0  # shard 0's intake never blocked
    assert _wait(lambda: feed.lost > 100), feed.lost  # 4 MB sent into 1.2 MB of room
    assert feed.lost + feed.forwarded <= 400
    os.close(r)
    feed.close()
    assert feed.lost + feed.forwarded == 400  # every message either handed over or counted


def test_a_frame_that_is_not_messagepack_is_counted_and_the_feed_goes_on():
    r, w = os.pipe()
    got = []
    intake = FeedIntake(r, lambda *a: got.append(a))
    bad = b"\xc1\xc1\xc1"  # 0xc1: never used in MessagePack
    os.write(w, struct.pack("<I", len(bad)) + bad)
    feed = ShardFeed(1)
    feed.attach(w)
    feed.add(5.0, "fednav/v/sensor/imu/a", b"ok")
    feed.flush()
    assert _wait(lambda: got == [(5.0, "fednav/v/sensor/imu/a", b"ok")]), got
    assert intake.bad_frames == 1
    intake.stop(0.5)
    feed.close()
    os.close(r)


def test_closing_the_feed_of_a_stalled_shard_does_not_hang_and_counts_everything(monkeypatch):
    """Shard 0 stopping while a shard reads nothing: close() returns after its timeout, the frame
    being written is given up, and every message is either handed over or counted as lost."""
    from fednav.service.transport import shard_feed

    monkeypatch.setattr(shard_feed, "MAX_QUEUED_BYTES", 200_000)
    r, w = os.pipe()  # a shard alive but never reading
    feed = ShardFeed(1)
    feed.attach(w)
    for _ in range(300):
        feed.add(1.0, "fednav/v/sensor/gnss/a/fix", b"z" * 10_000)
        feed.flush()
    t0 = time.monotonic()
    feed.close(timeout_s=1.0)
    assert time.monotonic() - t0 < 3.0
    assert _wait(lambda: feed.lost + feed.forwarded == 300), (feed.lost, feed.forwarded)
    assert not feed._thread.is_alive()
    os.close(r)
