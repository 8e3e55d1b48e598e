"""``fednav-inspect`` on a ``fednav-fleet record`` file (docs/fleet.md): the fleet recording is on the
``wall_time`` timeline, not the services' ``sensor_time``; until 2026-12-01 fednav-inspect said "no
data on the sensor_time timeline" about it (exit 0) and nothing else."""

from __future__ import annotations

import json

import pytest

from fednav.dashboards import inspect
from fednav.dashboards.fleet import FleetRecorder

A, B = "a" * 32, "b" * 32


def _snap(owners: dict[str, str | None], status: dict[str, str]) -> dict:
    vehicles = []
    for i, (v, zid) in enumerate(owners.items()):
        rows = {"lc": {"status": status.get(v, "aided"), "position": [40.0 + 1e-4 * i, 116.0, 50.0]}}
        vehicles.append(
            {
                "vehicle": v,
                "served_twice": False,
                "services": [zid] if zid else [],
                "pipelines": rows if zid else {},
                "by_service": {zid: {"received": 100}} if zid else {},
            }
        )
    services = [
        {"zid": z, "alive": True, "vehicles": [v for v, o in owners.items() if o == z]}
        for z in sorted({z for z in owners.values() if z})
    ]
    return {"vehicles": vehicles, "services": services}


def test_inspect_summarises_a_fleet_recording(tmp_path, capsys):
    rrd = tmp_path / "fleet.rrd"
    rec = FleetRecorder(rrd)
    wall = 1_796_000_000.0
    two = {"Tr.k-A_000": A, "Tr.k-A_001": B, "veh2": B}
    for k in range(3):  # both services serve
        rec.log(_snap(two, {"veh2": "degraded" if k == 0 else "aided"}), {}, wall + k)
    # service B is killed: its vehicles go without an answer for a snapshot, then to A
    rec.log(_snap({"Tr.k-A_000": A, "Tr.k-A_001": None, "veh2": None}, {}), {}, wall + 3)
    for k in range(4, 6):
        rec.log(_snap(dict.fromkeys(two, A), {"Tr.k-A_001": "degraded"}), {}, wall + k)
    rec.close()

    assert inspect.main([str(rrd)]) == 0
    text = capsys.readouterr().out
    assert "no data on the sensor_time timeline" not in text, text
    assert "fleet recording" in text and "6 snapshots" in text, text
    assert inspect.main([str(rrd), "--json"]) == 0
    s = json.loads(capsys.readouterr().out)
    assert s["kind"] == "fleet"
    assert s["snapshots"] == 6
    assert abs(s["duration_s"] - 5.0) < 1e-6
    assert sorted(s["vehicles"]) == ["Tr.k-A_000", "Tr.k-A_001", "veh2"]
    assert s["vehicles"]["Tr.k-A_001"]["statuses"] == ["aided", "no answer", "degraded"]
    assert s["vehicles"]["Tr.k-A_001"]["final_status"] == "degraded"
    assert s["vehicles"]["veh2"]["statuses"] == ["degraded", "aided", "no answer", "aided"]
    assert s["vehicles"]["Tr.k-A_000"]["positions"] == 6
    assert s["services"][A] == {"final_vehicles": 3, "max_vehicles": 3, "left": False}
    assert s["services"][B] == {"final_vehicles": 0, "max_vehicles": 2, "left": True}


def test_a_reader_that_stops_reading_ends_inspect_quietly(tmp_path):
    """``fednav-inspect FILE | head -1``: the reader closes the pipe before the report is written;
    the command ends with 141 (as a shell tool killed by SIGPIPE) and no BrokenPipeError traceback."""
    import subprocess
    import sys

    rrd = tmp_path / "fleet.rrd"
    rec = FleetRecorder(rrd)
    for k in range(3):
        rec.log(_snap({"veh0": A, "veh1": B}, {}), {}, 1_796_000_000.0 + k)
    rec.close()
    p = subprocess.Popen(
        [sys.executable, "-m", "fednav.dashboards.inspect", str(rrd)],
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
    )
    p.stdout.close()  # before the report is written: the recording is read first
    err = p.stderr.read().decode()
    assert p.wait(timeout=60) == 141, err
    assert "Traceback" not in err and "BrokenPipeError" not in err, err


def _boundaries(path) -> list[int]:
    """Where each whole message of an .rrd ends (its framing: ``inspect.whole_messages``)."""
    import struct

    b = path.read_bytes()
    pos, ends = 12, []
    while pos + 16 <= len(b):
        kind, length = struct.unpack_from("<QQ", b, pos)
        if kind == 0:
            break
        pos += 16 + length
        ends.append(pos)
    return ends


def test_a_recording_whose_writer_died_is_read_up_to_its_last_whole_message(tmp_path):
    """A recording cut inside a message (its writer SIGKILLed mid-write, a full disk) was "not a
    readable Rerun recording" as a whole; cut between two messages, Rerun read it with a warning
    about a missing footer. Both are read now, and the summary says what happened."""
    rrd = tmp_path / "fleet.rrd"
    rec = FleetRecorder(rrd)
    for k in range(40):
        rec.log(_snap({"veh0": A, "veh1": B}, {}), {}, 1_796_000_000.0 + k)
    rec.close()
    whole = inspect.inspect_rrd(rrd)
    assert whole["snapshots"] == 40 and not whole["unfinished"], whole["unfinished"]
    ends = _boundaries(rrd)
    data = rrd.read_bytes()
    mid = (ends[-3] + ends[-2]) // 2  # inside the second-to-last message
    cut = tmp_path / "cut.rrd"
    cut.write_bytes(data[:mid])
    s = inspect.inspect_rrd(cut)
    assert s["unfinished"] == {"read_bytes": ends[-3], "lost_bytes": mid - ends[-3]}, s["unfinished"]
    assert 0 < s["snapshots"] <= 40, s["snapshots"]
    assert "ends inside a message" in inspect.render_fleet_text(s)
    closed_not = tmp_path / "boundary.rrd"
    closed_not.write_bytes(data[: ends[-3]])
    s2 = inspect.inspect_rrd(closed_not)
    assert s2["unfinished"] == {"read_bytes": ends[-3], "lost_bytes": 0}, s2["unfinished"]
    assert s2["snapshots"] == s["snapshots"]
    assert "was not closed" in inspect.render_fleet_text(s2)
    garbage = tmp_path / "garbage.rrd"
    garbage.write_bytes(b"RRF2" + bytes(8) + b"\xff" * 64)
    with pytest.raises(inspect.InspectError):
        inspect.inspect_rrd(garbage)
