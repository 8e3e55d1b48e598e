"""Shortened variants of the shipped scenarios for fast tests, and a polling wait."""

from __future__ import annotations

import subprocess
import sys
import time
import tomllib
from pathlib import Path

from fednav.simulators.scenario import parse_scenario

SCENARIOS = Path(__file__).resolve().parents[1] / "simulators" / "scenarios"


def shortened(name: str, duration_s: float, **overrides):
    """The scenario ``name`` cut to ``duration_s`` (segments truncated), with top-level overrides."""
    data = tomllib.loads((SCENARIOS / name).read_text())
    data["duration_s"] = duration_s
    segs, total = [], 0.0
    for seg in data.get("segments", []):
        if total >= duration_s:
            break
        seg = dict(seg)
        if total + seg["duration_s"] > duration_s:
            break
        segs.append(seg)
        total += seg["duration_s"]
    data["segments"] = segs
    data["faults"] = [f for f in data.get("faults", []) if f["start_s"] < duration_s]
    for k, v in overrides.items():
        data[k] = v
    return parse_scenario(data, f"{name} shortened to {duration_s} s")


def cut_to(data: dict, duration_s: float) -> dict:
    """A scenario mapping cut to ``duration_s``: the segments that fit, faults starting before the
    end and clipped to it."""
    d = dict(data, duration_s=duration_s)
    segs, total = [], 0.0
    for s in d["segments"]:
        if total + s["duration_s"] > duration_s:
            break
        segs.append(s)
        total += s["duration_s"]
    d["segments"] = segs
    d["faults"] = [
        {**f, "duration_s": min(f["duration_s"], duration_s - f["start_s"])}
        for f in d["faults"]
        if f["start_s"] < duration_s
    ]
    return d


def initial_nav_message(t: float, nav, pos_std_enu_m, vel_std_enu_mps, rpy_std_deg):
    """The InitialNav wire message for a NavState-like ``nav`` (lat_rad, lon_rad, h_m, vel_enu_mps,
    rpy_rad) and the given 1-sigma uncertainties."""
    import math

    from fednav.service import earth
    from fednav.service.messages import InitialNav

    return InitialNav(
        t=t,
        lat_deg=math.degrees(nav.lat_rad),
        lon_deg=math.degrees(nav.lon_rad),
        height_m=nav.h_m,
        vel_enu_mps=tuple(float(v) for v in nav.vel_enu_mps),
        rpy_deg=tuple(float(v) for v in earth.rpy_msg_deg(nav.rpy_rad)),
        pos_std_enu_m=tuple(float(v) for v in pos_std_enu_m),
        vel_std_enu_mps=tuple(float(v) for v in vel_std_enu_mps),
        rpy_std_deg=tuple(float(v) for v in rpy_std_deg),
    )


def wait_until(cond, timeout: float = 10.0, poll_s: float = 0.01) -> bool:
    """Poll ``cond()`` until it is true or ``timeout`` seconds have passed; its last value."""
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        if cond():
            return True
        time.sleep(poll_s)
    return cond()


def split_zids(vehicles: list[str], count: int) -> list[str]:
    """``count`` Zenoh ids (hex) under which rendezvous gives each of any two of them some of
    ``vehicles``. With random ids, two services of six vehicles leave one with none once in 32 runs
    (a flaky CI run found it); tests that need both to serve set these ids in the services' Zenoh
    configs. Deterministic: the first such ids."""
    import itertools

    from fednav.service import fleet

    def split(members) -> bool:
        return len({fleet.owner(v, list(members)) for v in vehicles}) == 2

    chosen: list[str] = []
    for i in itertools.count(1):
        z = f"fed{i:029x}"
        if all(split((z, c)) for c in chosen):
            chosen.append(z)
            if len(chosen) == count:
                return chosen
        if i > 10_000:
            raise AssertionError(f"no {count} ids split {len(vehicles)} vehicles")
    raise AssertionError  # unreachable


def fleet_status(port: int) -> subprocess.CompletedProcess:
    """``fednav-fleet status --json`` through the Zenoh endpoint on loopback ``port``."""
    return subprocess.run(
        [sys.executable, "-m", "fednav.dashboards.fleet", "status", "--json"]
        + ["--connect", f"tcp/127.0.0.1:{port}"],
        capture_output=True,
        text=True,
        timeout=60,
    )
