"""Start fednav-service and fednav-sim as separate processes (demo, tests, benchmarks).

Explicit loopback endpoints on a free port, multicast scouting off (the processes' defaults).
"""

from __future__ import annotations

import json
import os
import signal
import socket
import subprocess
import sys
import threading
import time
from pathlib import Path


def free_port() -> int:
    with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


class Proc:
    """A child process whose output lines are collected by a thread (never blocks the pipe)."""

    def __init__(self, args: list[str], name: str, env: dict | None = None, cwd: str | Path | None = None):
        self.name = name
        self.lines: list[str] = []
        self._cv = threading.Condition()
        e = dict(os.environ)
        e.setdefault("RERUN_ANALYTICS_ENABLED", "false")
        e["PYTHONUNBUFFERED"] = "1"
        if env:
            e.update(env)
        self.p = subprocess.Popen(
            args, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True, env=e, cwd=cwd
        )
        self._t = threading.Thread(target=self._read, daemon=True)
        self._t.start()

    def _read(self) -> None:
        for line in self.p.stdout:
            with self._cv:
                self.lines.append(line.rstrip("\n"))
                self._cv.notify_all()

    def wait_for(self, text: str, timeout: float = 30.0) -> bool:
        deadline = time.monotonic() + timeout
        with self._cv:
            while not any(text in ln for ln in self.lines):
                left = deadline - time.monotonic()
                if left <= 0 or self.p.poll() is not None:
                    return any(text in ln for ln in self.lines)
                self._cv.wait(min(left, 0.2))
        return True

    def output(self) -> str:
        with self._cv:
            return "\n".join(self.lines)

    def signal(self, sig=signal.SIGINT) -> None:
        if self.p.poll() is None:
            self.p.send_signal(sig)

    def wait(self, timeout: float = 60.0) -> int:
        rc = self.p.wait(timeout=timeout)
        self._t.join(timeout=5.0)
        return rc

    def kill(self) -> None:
        if self.p.poll() is None:
            self.p.kill()
            self.p.wait()


def stop_all(procs: list[Proc], timeout: float = 30.0) -> None:
    """Stop processes started together, the last started first: SIGTERM to every one still
    running (a stopped one, SIGSTOP, is continued first: it would not act on SIGTERM), then wait
    for each, killing what does not exit within ``timeout``."""
    for p in reversed(procs):
        if p.p.poll() is None:
            p.signal(signal.SIGCONT)
            p.signal(signal.SIGTERM)
    for p in reversed(procs):
        try:
            p.wait(timeout=timeout)
        except Exception:
            p.kill()


def start_service(
    port: int,
    *,
    config: Path | None = None,
    table: str | None = None,
    rrd: Path | None = None,
    extra: list[str] | None = None,
) -> Proc:
    args = [sys.executable, "-m", "fednav.service", "--listen", f"tcp/127.0.0.1:{port}"]
    if config:
        args += ["--config", str(config)]
    if table:
        args += ["--config-table", table]
    args += ["--rrd", str(rrd)] if rrd else ["--no-record"]
    proc = Proc(args + (extra or []), "fednav-service")
    if not proc.wait_for("fednav-service ready", timeout=60.0):
        proc.kill()
        raise RuntimeError(f"fednav-service did not start:\n{proc.output()}")
    return proc


def start_sim(
    port: int,
    scenario: Path,
    *,
    speed: float = 0.0,
    seed: int | None = None,
    vehicle: str = "v1",
    imu_batch: int | None = None,
) -> Proc:
    args = [
        sys.executable,
        "-m",
        "fednav.simulators",
        "run",
        str(scenario),
        "--speed",
        str(speed),
        "--connect",
        f"tcp/127.0.0.1:{port}",
        "--vehicle",
        vehicle,
    ]
    if seed is not None:
        args += ["--seed", str(seed)]
    if imu_batch is not None:
        args += ["--imu-batch", str(imu_batch)]
    return Proc(args, "fednav-sim")


def query_status(
    port: int, vehicle: str = "v1", prefix: str = "fednav", timeout_s: float = 5.0
) -> dict | None:
    """Ask the service's status queryable (a plain Zenoh client)."""
    import zenoh

    from fednav.service.config import ZenohConfig
    from fednav.service.transport.zenoh_io import make_config

    with zenoh.open(
        make_config(ZenohConfig(mode="client"), listen=[], connect=[f"tcp/127.0.0.1:{port}"])
    ) as s:
        for reply in s.get(f"{prefix}/{vehicle}/service/status", timeout=timeout_s):
            if reply.ok is not None:
                return json.loads(reply.ok.payload.to_bytes())
    return None


def wait_idle(port: int, vehicle: str = "v1", timeout_s: float = 120.0) -> dict | None:
    """Wait until the vehicle's queue is empty and its sensor time and received count stop moving
    (the same over three readings ~0.3 s apart: on a loaded machine a service behind its input
    can make no progress for one interval while messages wait in its Zenoh channel)."""
    deadline = time.monotonic() + timeout_s
    last, same = None, 0
    while time.monotonic() < deadline:
        st = query_status(port, vehicle)
        h = (st or {}).get("health")
        now = (h["t"], h["received"]) if h else None
        idle = h and h["queue_depth"] == 0 and h["t"] is not None
        same = same + 1 if idle and now == last else 0
        if same >= 2:
            return st
        last = now
        time.sleep(0.3)
    return None
