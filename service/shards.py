"""Local shards: one fednav-service spread over K processes where the GIL is the limit.

``fednav-service --shards K`` runs shard 0 in this process and starts shards 1..K-1 as child
processes (``--shard I/K``) of the same command line. Each shard serves the vehicles that
rendezvous hashing (:mod:`service.fleet`) gives it, so all agree without talking. Shard 0 alone
subscribes to the inputs: it hands each other shard its vehicles' messages through that shard's
standard input (:mod:`service.transport.shard_feed`), so each message crosses Zenoh once. Shard 0
keeps the endpoints of the command line; the children connect to it over a unix socket in a private
directory (only the service's user can open it; the outputs guard of
:func:`service.transport.zenoh_io.outputs_guard` applies to network links, so the shards publish
their vehicles' outputs through shard 0), or, when shard 0 is a client of a router, to the same
router. Each shard writes its own recording (``run.rrd``, ``run.shard1.rrd``, ...).

Shard 0 supervises the children: a child that dies is restarted (at most once per
``RESTART_BACKOFF_S``; its vehicles' inputs meanwhile are counted as lost; its vehicles go on
from the last HandoverState it published, which shard 0 writes first into the new shard's pipe),
and SIGINT/SIGTERM of shard 0 stop them all cleanly (each runs what its feed still holds and
closes its recording). A child whose feed ends (shard 0 gone, even killed) stops by itself.
"""

from __future__ import annotations

import logging
import os
import secrets
import signal
import subprocess
import sys
import tempfile
import threading
import time
from pathlib import Path

log = logging.getLogger("fednav.service")

RESTART_BACKOFF_S = 2.0
READY_TEXT = "fednav-service shard {i}/{k} ready"
#: what follows READY_TEXT on a shard's ready line: its Zenoh id (ShardSupervisor.by_zid)
READY_ZID = " zid={zid}"


def parse_shard(text: str) -> tuple[int, int]:
    """``I/K`` -> (I, K) with 0 <= I < K."""
    try:
        i, k = (int(x) for x in text.split("/"))
    except ValueError:
        raise ValueError(f"--shard {text!r}: use I/K, e.g. 1/4") from None
    if not (k >= 1 and 0 <= i < k):
        raise ValueError(f"--shard {text!r}: need 0 <= I < K")
    return i, k


def shard_rrd(rrd: Path, index: int) -> Path:
    """Recording path of shard ``index`` (shard 0 keeps the path)."""
    return rrd if index == 0 else rrd.with_name(f"{rrd.stem}.shard{index}{rrd.suffix}")


class ShardSupervisor:
    """Starts, watches and stops shards 1..K-1 of this service."""

    def __init__(self, argv: list[str], count: int, connect: list[str] | None, rrd: Path | None):
        self.count = count
        self._argv = _strip(argv)
        self.rrd = rrd
        self._dir = tempfile.mkdtemp(prefix="fednav-shards-")  # mode 0700: this user only
        os.chmod(self._dir, 0o700)
        self.socket_endpoint = f"unixsock-stream/{Path(self._dir) / 'shards.sock'}"
        self._connect = connect or [self.socket_endpoint]
        self._procs: dict[int, subprocess.Popen] = {}
        self._ready: dict[int, threading.Event] = {}
        self._stopping = threading.Event()
        self._watch: threading.Thread | None = None
        self.restarts = 0
        from fednav.service.transport.shard_feed import ShardFeed

        #: shard i's inputs, handed over by shard 0's intake (Service(feeds=...))
        self.feeds = {i: ShardFeed(i) for i in range(1, count)}
        #: the private group under which shards 1..K-1 publish their vehicles' handover states
        self.group = f"_shards-{secrets.token_hex(6)}"
        #: (shard index) -> the latest states of its vehicles (Service.shard_states), handed to a
        #: restarted shard first: its vehicles go on from where the dead shard left them
        self.states_for = None
        #: the Zenoh id of each running shard 1..K-1 (from its ready line) -> its index: in a fleet
        #: group ([fleet] sharding = 'rendezvous') each shard is a member under its own id, and
        #: shard 0 hands a vehicle's inputs to the shard the fleet gives it (Service._forward)
        self.by_zid: dict[str, int] = {}

    def _command(self, i: int) -> list[str]:
        args = [sys.executable, "-m", "fednav.service", *self._argv, "--shard", f"{i}/{self.count}"]
        args += ["--shard-group", self.group]
        for ep in self._connect:
            args += ["--connect", ep]
        if self.rrd is not None:
            args += ["--rrd", str(shard_rrd(self.rrd, i))]
        return args

    def _spawn(self, i: int) -> None:
        env = dict(os.environ, PYTHONUNBUFFERED="1")
        p = subprocess.Popen(
            self._command(i),
            stdin=subprocess.PIPE,
            stdout=subprocess.PIPE,
            stderr=subprocess.STDOUT,
            text=True,
            env=env,
        )
        first = self.states_for(i) if self.states_for is not None and i in self._procs else None
        self.feeds[i].attach(os.dup(p.stdin.fileno()), first)  # the feed owns its descriptor
        p.stdin.close()
        p.stdin = None
        self._procs[i] = p
        ready = self._ready[i] = threading.Event()
        text = READY_TEXT.format(i=i, k=self.count)

        def relay() -> None:  # the child's output on ours, each line marked with its shard
            for line in p.stdout:
                if text in line:
                    zid = line.split(" zid=", 1)[1].split()[0] if " zid=" in line else None
                    if zid:  # (the restarted shard's new id replaces the old one)
                        for z in [z for z, j in self.by_zid.items() if j == i]:
                            self.by_zid.pop(z, None)
                        self.by_zid[zid] = i
                    ready.set()
                sys.stdout.write(f"[shard {i}] {line}")
                sys.stdout.flush()

        threading.Thread(target=relay, name=f"fednav-shard-{i}-out", daemon=True).start()

    def start(self, timeout_s: float = 60.0) -> bool:
        """Start the children and wait until each says it is ready."""
        for i in range(1, self.count):
            self._spawn(i)
        deadline = time.monotonic() + timeout_s
        ok = all(e.wait(max(0.0, deadline - time.monotonic())) for e in self._ready.values())
        self._watch = threading.Thread(target=self._supervise, name="fednav-shards", daemon=True)
        self._watch.start()
        return ok

    def _supervise(self) -> None:
        last: dict[int, float] = {}
        while not self._stopping.wait(0.5):
            for i, p in list(self._procs.items()):
                if p.poll() is None or self._stopping.is_set():
                    continue
                if time.monotonic() - last.get(i, -1e9) < RESTART_BACKOFF_S:
                    continue
                last[i] = time.monotonic()
                log.error("shard %d/%d exited with %s: restarting it", i, self.count, p.returncode)
                self.restarts += 1
                self._spawn(i)

    def alive(self) -> list[int]:
        return [i for i, p in self._procs.items() if p.poll() is None]

    def stop(self, timeout_s: float = 60.0) -> None:
        self._stopping.set()
        for feed in self.feeds.values():  # what waits is written; the end of the pipe stops them
            feed.close()
        for p in self._procs.values():
            if p.poll() is None:
                p.send_signal(signal.SIGTERM)
        deadline = time.monotonic() + timeout_s
        for i, p in self._procs.items():
            try:
                p.wait(timeout=max(0.1, deadline - time.monotonic()))
            except subprocess.TimeoutExpired:
                log.error("shard %d did not stop within %.0f s: killed", i, timeout_s)
                p.kill()
                p.wait()
        try:
            for f in Path(self._dir).iterdir():
                f.unlink()
            os.rmdir(self._dir)
        except OSError:
            pass


def _strip(argv: list[str]) -> list[str]:
    """The command line without what each shard sets itself (endpoints, recording, shards)."""
    out, skip = [], False
    value_opts = {"--listen", "--connect", "--rrd", "--shards", "--shard", "--shard-group", "--viewer"}
    for a in argv:
        if skip:
            skip = False
            continue
        name = a.split("=", 1)[0]
        if name in value_opts:
            skip = "=" not in a
            continue
        out.append(a)
    return out


__all__ = ["READY_TEXT", "READY_ZID", "ShardSupervisor", "parse_shard", "shard_rrd"]
