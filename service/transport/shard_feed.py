"""The inputs of a local shard's vehicles, handed from shard 0 to the shard over a pipe.

``fednav-service --shards K`` (:mod:`service.shards`): shard 0 alone subscribes to the fleet's
inputs on Zenoh. It runs its own vehicles' messages and hands every other message, as it arrived
(arrival time, key, payload), to the shard that rendezvous hashing gives its vehicle, through that
shard's standard input. Each message crosses Zenoh once: before this, every shard subscribed to
every vehicle's inputs and dropped the others' (K shards received the fleet K times; the Zenoh
threads of a second shard cost a third of a core at 60 vehicles of 200 Hz JSON samples, see
docs/SCALING.md, "One intake for every local shard").

The pipe carries frames: a 4-byte little-endian length, then a MessagePack array of
``[arrival, key, payload]`` arrays (float, str, bin), the messages of one drain of shard 0's
intake for that shard, in their order of arrival. Both ends are this program (same version, same
user, a pipe no one else holds); the shard still validates each message as if it came from Zenoh.

Shard 0 never waits for a shard: its intake thread writes a frame itself when the pipe takes it
whole (non-blocking); what the pipe does not take waits in a bounded queue (``MAX_QUEUED_BYTES``)
for the feed's own thread. A frame that finds the queue full, or the shard dead or not yet
started, is dropped and its messages counted (``lost``, in ServiceHealth ``inputs_forward_lost``).
"""

from __future__ import annotations

import logging
import os
import select
import struct
import threading
import time
from collections import deque
from collections.abc import Callable

import msgspec

log = logging.getLogger("fednav.service")

#: the most bytes of frames waiting for one shard (at 60 vehicles of 200 Hz JSON samples, a shard's
#: share is ~2 MB/s: 32 MB is several seconds of a stalled shard)
MAX_QUEUED_BYTES = 32 * 1024 * 1024
#: the largest frame a shard accepts (a drain is at most 256 messages of at most 1 MiB)
MAX_FRAME_BYTES = 512 * 1024 * 1024
_HEADER = struct.Struct("<I")
#: the most a shard reads from its pipe at once (every whole frame in it is handed on together)
READ_BYTES = 1 << 20

Item = tuple[float, str, bytes]


class ShardFeed:
    """Shard 0's side: messages for one shard, one frame per drain of shard 0's intake.

    The intake thread writes a frame itself when the pipe takes it whole at once (non-blocking:
    the usual case, one system call, no hand-over between threads); what the pipe does not take
    waits in the queue for the feed's own thread, which writes it when the shard has read."""

    def __init__(self, index: int):
        self.index = index
        self.forwarded = 0  # messages handed to the shard's pipe
        self.lost = 0  # messages dropped: queue full, shard dead or not started, feed closed
        self._pending: list[list] = []  # the current drain's messages (intake thread only)
        self._frames: deque[tuple[bytes, int]] = deque()  # (bytes still to write, messages)
        self._queued = 0
        self._cv = threading.Condition()
        self._fd: int | None = None
        self._writing: int | None = None  # the fd the thread is writing to (outside the lock)
        self._close_after: int | None = None  # replaced while being written: closed by the thread
        self._closed = False
        self._enc = msgspec.msgpack.Encoder()
        self._thread = threading.Thread(target=self._write_loop, name=f"fednav-feed-{index}", daemon=True)
        self._thread.start()

    # --- the intake thread ------------------------------------------------------------------
    def add(self, wall: float, key: str, payload: bytes) -> None:
        self._pending.append([wall, key, payload])

    def flush(self) -> None:
        """The end of a drain: what was added becomes one frame."""
        items = self._pending
        if not items:
            return
        self._pending = []
        body = self._enc.encode(items)
        frame = _HEADER.pack(len(body)) + body
        n = len(items)
        with self._cv:
            fd = self._fd
            if self._closed or fd is None:
                self.lost += n
                return
            if not self._frames and self._writing is None:  # nothing before it: write it now
                try:
                    k = os.write(fd, frame)
                except BlockingIOError:
                    k = 0
                except OSError:  # the shard died (EPIPE): lost until it is restarted (attach)
                    self._dead(fd, n)
                    return
                if k == len(frame):
                    self.forwarded += n
                    return
                if k:  # the rest must follow, whatever the queue holds (the stream's framing)
                    self._frames.append((frame[k:], n))
                    self._queued += len(frame) - k
                    self._cv.notify()
                    return
            if self._queued + len(frame) > MAX_QUEUED_BYTES:
                self.lost += n
                return
            self._frames.append((frame, n))
            self._queued += len(frame)
            self._cv.notify()

    # --- the supervisor ---------------------------------------------------------------------
    def attach(self, fd: int, first: list | None = None) -> None:
        """The (re)started shard's standard input (a descriptor this feed now owns and closes):
        frames go there from now on; what waited for the shard before is dropped and counted.
        ``first``: items for the shard before any message (a restarted shard's vehicles' last
        handover states), one frame ahead of everything else."""
        _widen(fd)
        os.set_blocking(fd, False)
        head = None
        if first:
            body = self._enc.encode(first)
            head = _HEADER.pack(len(body)) + body
        with self._cv:
            old, self._fd = self._fd, fd
            self._drop_queued()
            if head is not None:  # counted neither forwarded nor lost: not inputs
                self._frames.append((head, 0))
                self._queued += len(head)
            if old is not None and old == self._writing:
                self._close_after = old
                old = None
            self._cv.notify()
        if old is not None:
            _close(old)

    def close(self, timeout_s: float = 10.0) -> None:
        """Write what waits, then close the pipe: the shard reads to its end, then stops."""
        with self._cv:
            self._closed = True
            self._cv.notify()
        self._thread.join(timeout=timeout_s)
        with self._cv:
            self._drop_queued()
            fd, self._fd = self._fd, None
            if fd is not None and fd == self._writing:  # a stalled shard: the thread gives up on it
                self._close_after, fd = fd, None
        if fd is not None:
            _close(fd)

    def _drop_queued(self) -> None:
        self.lost += sum(n for _, n in self._frames)
        self._frames.clear()
        self._queued = 0

    def _dead(self, fd: int, n: int) -> None:
        """(Under the lock) writing to ``fd`` failed: its shard is gone."""
        self.lost += n
        if self._fd == fd:
            self._fd = None
            self._drop_queued()
            if self._writing == fd:
                self._close_after = fd
            else:
                _close(fd)

    def _write_loop(self) -> None:
        while True:
            with self._cv:
                while not self._frames and not self._closed:
                    self._cv.wait()
                if not self._frames:  # closed, everything written
                    return
                frame, n = self._frames.popleft()
                self._queued -= len(frame)
                fd = self._writing = self._fd
            if fd is None:
                with self._cv:
                    self._writing = None
                    self.lost += n
                continue
            ok = True
            try:
                view = memoryview(frame)
                while view:
                    try:
                        view = view[os.write(fd, view) :]
                    except BlockingIOError:  # the shard has not read yet
                        if self._fd != fd:  # closed or replaced meanwhile: this frame is lost
                            raise OSError("feed closed") from None
                        select.select([], [fd], [], 0.5)
            except OSError:
                ok = False
            with self._cv:
                self._writing = None
                if ok:
                    self.forwarded += n
                else:
                    self._dead(fd, n)
                if self._close_after == fd:
                    self._close_after = None
                    _close(fd)


def _widen(fd: int) -> None:
    """A 1 MiB pipe (Linux's unprivileged maximum) instead of 64 KiB, where the system allows."""
    try:
        import fcntl

        fcntl.fcntl(fd, getattr(fcntl, "F_SETPIPE_SZ", 1031), 1 << 20)
    except (OSError, ImportError):
        pass


def _close(fd: int) -> None:
    try:
        os.close(fd)
    except OSError:
        pass


class FeedIntake:
    """A shard's side: reads the frames of its standard input and hands their messages on, like
    :class:`service.transport.zenoh_io.Intake` (``deliver_many`` for a whole frame, else
    ``deliver`` per message). ``on_end`` is called when shard 0 closes the pipe (or dies): the
    shard then stops as if signalled."""

    def __init__(
        self,
        fd: int,
        deliver: Callable[[float, str, bytes], None],
        deliver_many: Callable[[list[Item]], None] | None = None,
        on_end: Callable[[], None] | None = None,
    ):
        self._fd = fd
        self._deliver = deliver
        self._deliver_many = deliver_many
        self._on_end = on_end
        self._dec = msgspec.msgpack.Decoder()
        self._stop = threading.Event()
        self._deadline: float | None = None
        self.unwanted = 0  # the interface of Intake: a shard receives only its own vehicles'
        self.bad_frames = 0
        self.received = 0
        self._thread = threading.Thread(target=self._run, name="fednav-feed-intake", daemon=True)
        self._thread.start()

    def _chunk(self) -> bytes | None:
        """What the pipe holds now (blocking until something), b"" when stopping with nothing
        more, None at the pipe's end."""
        while True:
            stopping = self._stop.is_set()
            if stopping and self._deadline is not None and time.monotonic() > self._deadline:
                return b""
            ready, _, _ = select.select([self._fd], [], [], 0.05 if stopping else 0.2)
            if ready:
                data = os.read(self._fd, READ_BYTES)
                return data if data else None
            if stopping:
                return b""

    def _run(self) -> None:
        buf = bytearray()
        try:
            while True:
                data = self._chunk()
                if data is None:
                    break
                if not data:  # stopping: nothing more arrived
                    if buf and self._deadline is not None and time.monotonic() <= self._deadline:
                        continue  # the rest of a frame being written
                    break
                buf += data
                items: list = []
                pos = 0
                while len(buf) - pos >= _HEADER.size:  # every whole frame that arrived
                    (size,) = _HEADER.unpack_from(buf, pos)
                    if size > MAX_FRAME_BYTES:
                        log.error(
                            "shard feed: a frame of %d bytes refused: the feed is out of step, ended", size
                        )
                        self.bad_frames += 1
                        return
                    if len(buf) - pos - _HEADER.size < size:
                        break
                    start = pos + _HEADER.size
                    pos = start + size
                    try:
                        items.extend(self._dec.decode(memoryview(buf)[start:pos]))
                    except msgspec.DecodeError:
                        self.bad_frames += 1
                        log.error("shard feed: a frame that is not MessagePack refused")
                del buf[:pos]
                if items:
                    self._hand_on(items)
        finally:
            if not self._stop.is_set() and self._on_end is not None:
                log.info("shard feed ended (shard 0 stopped): stopping")
                self._on_end()

    def _hand_on(self, items: list) -> None:
        self.received += len(items)
        if self._deliver_many is not None:
            try:
                self._deliver_many(items)
            except Exception:  # routing must survive any one drain
                log.exception("shard feed: delivery of %d messages failed", len(items))
            return
        for item in items:
            try:
                self._deliver(*item)
            except Exception:  # routing must survive any one message
                log.exception("shard feed: delivery of %s failed", str(item)[:200])

    def stop(self, drain_s: float = 5.0) -> None:
        """What is already in the pipe is still delivered, for at most ``drain_s``."""
        self._deadline = time.monotonic() + drain_s
        self._stop.set()
        self._thread.join(timeout=drain_s + 2.0)
        if self._thread.is_alive():
            log.warning("shard feed: still delivering %.1f s after shutdown began", drain_s + 2.0)


__all__ = ["FeedIntake", "MAX_QUEUED_BYTES", "ShardFeed"]
