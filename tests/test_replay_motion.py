"""fednav-replay's checks on logs that START IN MOTION (issue 24): written by the formats' own
libraries (rosbags, pynmea2, pyubx2, csv) from a simulated car drive whose log begins inside a
10 deg/s turn (no rest, no steady first second), consumer-grade IMU, 10 Hz fixes.

Every wrong mapping a user can make is named in plain words with the one that fits, and refused
(exit code 2, nothing published): axes FLU vs FRD, the IMU mounted backwards or turned 90
degrees, one axis' sign mirrored, the gyro's sign reversed against the accelerometer's,
accelerations in g, a gyro in deg/s declared rad/s, and wrong time bases (a boot offset 77 ms
off, the leap seconds, boot-time stamps read as POSIX). ``boot_offset_s = "auto"`` derives the
offset from a stream carrying both clocks or the first fix and refines it by the motion. The
check summary says which sigma each GNSS stream carries and why.
"""

from __future__ import annotations

import re
from pathlib import Path

import numpy as np
import pytest

from fednav.replay import checks, mapping
from fednav.replay.__main__ import main as replay_main
from fednav.replay.mapping import MappingError, from_dict

from . import replay_files as rf

START_S = 12.5  # the log starts here: inside the first turn (10 deg/s), after the speed-up


@pytest.fixture(scope="module")
def drive(tmp_path_factory):
    tmp = tmp_path_factory.mktemp("car")
    return rf.trim(rf.simulate_car_drive(tmp, "consumer_mems", duration_s=70.0), START_S)


@pytest.fixture(scope="module")
def files(drive, tmp_path_factory):
    return rf.write_all(tmp_path_factory.mktemp("car_logs"), drive)


def _variant(path: Path, old: str, new: str, name: str) -> Path:
    p = path.with_name(f"{name}.toml")
    text = path.read_text()
    assert old in text, (old, text)
    p.write_text(text.replace(old, new, 1))
    return p


def _check(p: Path) -> checks.Report:
    m, base = mapping.load_mapping(p)
    return checks.run_checks(m, base)


def test_the_log_really_starts_in_motion(drive):
    w = np.array(drive.imu[0].dtheta_rad) / drive.imu[0].dt_s
    assert abs(np.degrees(w[2])) > 5.0  # turning at the first sample
    assert np.hypot(*drive.fixes[0].vel_enu_mps[:2]) > 10.0
    first = drive.imu[:100]
    assert checks.at_rest(first) is False


@pytest.mark.parametrize("case", ["ros2", "ros1", "mcap", "nmea_csv", "ubx"])
def test_right_mappings_pass_in_motion_with_the_motion_checked(files, case):
    r = _check(files[case])
    assert r.errors == [] and r.warnings == [], r.text()
    fit = next(n for n in r.notes if n.startswith("motion:"))
    assert re.search(r"over \d+ windows in motion: axes (FLU|FRD) fit, time offset [+-]0\.0[01]\d s", fit), (
        fit
    )
    mo = r.motion["imu"]
    assert abs(mo["time_offset"]["lag_s"]) < 0.02 and mo["time_offset"]["correlation"] > 0.95
    assert mo["yaw"]["axis"] == "z" and mo["yaw"]["sign"] == 1.0
    assert 0.97 < mo["yaw"]["course_rate_over_yaw_rate"] < 1.03
    assert mo["horizontal_fit_rms_mps2"]["declared"] < 0.5 < mo["rms_horizontal_accel_mps2"]


WRONG = [
    # (case, what to change in the mapping / how the file is written, the words expected)
    (
        "ros2",
        ('axes = "FLU"', 'axes = "FRD"'),
        None,
        "z axis reads +9.9 m/s^2 on average over the log (in motion): axes look like FLU, mapping says FRD",
    ),
    (
        "nmea_csv",
        ('axes = "FRD"', 'axes = "FLU"'),
        None,
        "IMU 'imu' z axis reads -1.0 g on average over the log (in motion): axes look like FRD, "
        "mapping says FLU",
    ),
    (
        "nmea_csv",
        ('accel_unit = "g"', 'accel_unit = "m/s^2"'),
        None,
        "the accelerometer looks like it is in g, mapping says accel_unit = 'm/s^2': set accel_unit = 'g'",
    ),
    (
        "nmea_csv",
        ('gyro_unit = "deg/s"', 'gyro_unit = "rad/s"'),
        None,
        "the gyro looks like it is in deg/s, mapping says gyro_unit = 'rad/s': set gyro_unit = 'deg/s'",
    ),
    (
        "nmea_csv",
        None,
        {"axes": "BLD"},  # the IMU's x points backwards: mounted back to front
        "the IMU's axes look like BLD, not FRD: forward and right both read reversed (mounted backwards); "
        "set axes = 'BLD'",
    ),
    (
        "ubx",
        None,
        {"axes": "RBD"},  # turned 90 degrees
        "the IMU's axes look like RBD, not FRD: forward and right are exchanged (turned 90 degrees); "
        "set axes = 'RBD'",
    ),
    (
        "nmea_csv",
        None,
        {"negate": (2, 5)},  # the logger writes y (gyro and accelerometer) with the wrong sign
        "right reads reversed while forward does not: the data are mirrored (no right-handed axes fit: "
        "one axis' sign is reversed in the log",
    ),
    (
        "nmea_csv",
        None,
        {"negate": (3,)},  # the gyro's z sign convention differs from the accelerometer's
        "its yaw rate appears on fednav's up axis with the opposite sign",
    ),
    (
        "nmea_csv",
        (f"boot_offset_s = {rf.BOOT_GPS_S}", f"boot_offset_s = {rf.BOOT_GPS_S + 0.077}"),
        None,
        "IMU 'imu': its stamps are 0.0",  # completed by the test: late by ~77 ms, with the value to set
    ),
    (
        "nmea_csv",
        (f"boot_offset_s = {rf.BOOT_GPS_S}", f"boot_offset_s = {rf.BOOT_GPS_S - 18.0}"),
        None,
        "early against those of gnss_fix 'rx' (the IMU's rotation against the course over",
    ),
    (
        "nmea_csv",
        (f'time_base = "boot"\nboot_offset_s = {rf.BOOT_GPS_S}\n', ""),  # the default: POSIX
        None,
        "stamps convert to no GPS time (the first, 1247.010 read as time_base 'unix', gives "
        "t = -315963535.0 s): the stamps look like seconds since the device booted: set time_base = 'boot' "
        "with boot_offset_s (or 'auto')",
    ),
]
IDS = [
    "FLU_declared_FRD",
    "FRD_declared_FLU",
    "accel_in_g",
    "gyro_deg_declared_rad",
    "mounted_backwards",
    "turned_90_ubx",
    "mirrored_sign",
    "gyro_sign_flipped",
    "boot_offset_77ms_off",
    "leap_seconds",
    "boot_stamps_read_as_posix",
]


@pytest.mark.parametrize(("case", "edit", "write", "words"), WRONG, ids=IDS)
def test_wrong_mapping_is_named_and_refused(files, drive, case, edit, write, words, capsys, request):
    name = request.node.callspec.id
    p = files[case]
    if write is not None:  # the same drive written by a device mounted or configured differently
        if case == "ubx":
            rf.write_ubx(p.parent / f"{name}.ubx", drive, axes=write["axes"])
            p = _variant(p, 'source = "drive.ubx"', f'source = "{name}.ubx"', name)
            p.write_text(p.read_text().replace('source = "drive.ubx"', f'source = "{name}.ubx"'))
        else:
            rf.write_csv(
                p.parent / f"{name}.csv", drive, axes=write.get("axes", "FRD"), negate=write.get("negate", ())
            )
            p = _variant(p, 'source = "imu.csv"', f'source = "{name}.csv"', name)
    if edit is not None:
        p = _variant(p, *edit, name=name + "_m")
    r = _check(p)
    assert any(words in e for e in r.errors), r.text()
    if name == "boot_offset_77ms_off":
        e = next(e for e in r.errors if words in e)
        late = float(re.search(r"stamps are (\d\.\d+) s late", e).group(1))
        assert abs(late - 0.077) < 0.015, e
        fix = float(re.search(r"set boot_offset_s = (\d+\.\d+) in stream 'imu'", e).group(1))
        assert abs(fix - rf.BOOT_GPS_S) < 0.015
    if name == "boot_stamps_read_as_posix":
        assert f"imu 'imu': no messages read from imu.csv: all {len(drive.imu)} stamps" in r.text()
    if name == "leap_seconds":
        e = next(e for e in r.errors if words in e)
        early = float(re.search(r"stamps are (\d+\.\d+) s early", e).group(1))
        assert abs(early - 18.0) < 0.015 and "the leap seconds" in e, e
    # refused: exit code 2, nothing published (no service runs: publishing would wait for one);
    # the UBX case is not read a second time (pyubx2 parses ~1k messages/s)
    if case != "ubx":
        assert replay_main([str(p), "--match-timeout", "0.1"]) == 2
        assert words in capsys.readouterr().out


# --- time bases without guesswork ---------------------------------------------------------------------
def _auto(files, name: str, imu_edit: tuple[str, str] | None = None, nmea: str = "drive.nmea") -> Path:
    p = _variant(files["nmea_csv"], f"boot_offset_s = {rf.BOOT_GPS_S}", 'boot_offset_s = "auto"', name)
    if nmea != "drive.nmea":
        p.write_text(p.read_text().replace('source = "drive.nmea"', f'source = "{nmea}"'))
    return p


def _derived(r: checks.Report) -> tuple[float, str]:
    note = next(n for n in r.notes if n.startswith("boot_offset_s of stream 'imu' derived"))
    return float(re.search(r"write boot_offset_s = (\d+\.\d+)", note).group(1)), note


def test_boot_offset_from_the_loggers_receive_stamps_refined_by_the_motion(files, drive):
    # the logger writes its own boot-clock stamp in front of each NMEA line; the receiver outputs
    # each epoch 77 ms after it (its latency): the pairs alone are 77 ms off, the motion finds it
    rf.write_nmea(files["nmea_csv"].parent / "stamped.nmea", drive, receive_latency_s=0.077)
    r = _check(_auto(files, "auto_nmea", nmea="stamped.nmea"))
    assert r.errors == [], r.text()
    off, note = _derived(r)
    assert abs(off - rf.BOOT_GPS_S) < 0.015, note
    assert "the logger's receive stamps on" in note and "includes the receiver's output latency" in note
    step = float(re.search(r"then ([+-]0\.\d+) s from its rotation", note).group(1))
    assert abs(step - 0.077) < 0.015, note  # the pairs put the IMU 77 ms early: the motion adds it
    assert r.mapping.streams[0].boot_offset_s == pytest.approx(off, abs=1e-3)


def test_boot_offset_from_the_first_fix(files):
    r = _check(_auto(files, "auto_first"))
    assert r.errors == [], r.text()
    off, note = _derived(r)
    assert "the first fix's GPS time minus the stream's first stamp" in note
    assert abs(off - rf.BOOT_GPS_S) < 0.015, note


def test_boot_offset_from_a_bags_receive_times(files, drive):
    d = files["ros2"].parent
    rf.write_ros2(d / "boot_ros2", drive, imu_boot=True)
    text = files["ros2"].read_text().replace("drive_ros2", "boot_ros2")
    text = text.replace(
        'topic = "/imu/data"\naxes = "FLU"\ntime_base = "unix"',
        'topic = "/imu/data"\naxes = "FLU"\ntime_base = "boot"\nboot_offset_s = "auto"',
    )
    (d / "boot_ros2.toml").write_text(text)
    r = _check(d / "boot_ros2.toml")
    assert r.errors == [], r.text()
    off, note = _derived(r)
    assert "its bag's receive times against its stamps" in note
    assert abs(off - rf.BOOT_GPS_S) < 0.015, note  # the 2 ms transport latency taken out by the motion


def test_leap_seconds_in_a_stream_is_told_to_move_and_endpoint_is_a_field():
    with pytest.raises(MappingError) as e:
        from_dict({"streams": [{"source": "a.csv", "kind": "imu", "sensor_id": "i", "leap_seconds": 18}]})
    assert "streams.0.leap_seconds: 'leap_seconds' is a top-level field of the mapping" in str(e.value)
    assert "move the line 'leap_seconds = ...' above the first [[streams]]" in str(e.value)
    with pytest.raises(MappingError, match="'axes' is a field of a stream"):
        from_dict({"axes": "FLU", "streams": [{"source": "a.csv", "kind": "imu", "sensor_id": "i"}]})
    m = from_dict(
        {"endpoint": "tcp/10.0.0.2:7447", "streams": [{"source": "a.csv", "kind": "imu", "sensor_id": "i"}]}
    )
    assert m.endpoint == "tcp/10.0.0.2:7447"
    with pytest.raises(MappingError, match="endpoint"):
        from_dict({"endpoint": "10.0.0.2", "streams": [{"source": "a.csv", "kind": "imu", "sensor_id": "i"}]})
    with pytest.raises(MappingError, match="boot_offset_s applies to time_base 'boot' only"):
        from_dict({"streams": [{"source": "a.csv", "kind": "imu", "sensor_id": "i", "boot_offset_s": 5.0}]})


def test_the_mappings_endpoint_is_where_the_replay_connects(files, capsys):
    from fednav.simulators.processes import free_port

    port = free_port()
    p = files["nmea_csv"].with_name("endpoint.toml")
    p.write_text(f'endpoint = "tcp/127.0.0.1:{port}"\n' + files["nmea_csv"].read_text())
    assert replay_main([str(p), "--match-timeout", "0.3"]) == 3
    assert f"tcp/127.0.0.1:{port}" in capsys.readouterr().err


# --- sigmas ------------------------------------------------------------------------------------------
def test_each_stream_says_its_sigma_and_why(files, drive, tmp_path):
    r = _check(files["nmea_csv"])
    fix = next(s for s in r.streams if s.kind == "gnss_fix")
    assert fix.sigma["pos_origin"] == {"GST": len(drive.fixes)}
    assert fix.sigma["text"].startswith(
        "position E/N/U 0.50/0.50/1.00 m (median) from the log's GST sentences"
    )
    assert (
        "speed 0.150 m/s (median) from GnssFix's default for fix type 'single' (0.15 m/s)"
        in fix.sigma["text"]
    )
    assert "    sigmas: position E/N/U" in r.text()
    # without GST: the fix type's default times HDOP, said so
    rf.write_nmea(files["nmea_csv"].parent / "nogst.nmea", drive, gst=False)
    r = _check(_variant(files["nmea_csv"], 'source = "drive.nmea"', 'source = "nogst.nmea"', "nogst"))
    fix = next(s for s in r.streams if s.kind == "gnss_fix")
    assert fix.sigma["pos_origin"] == {"default": len(drive.fixes)}
    assert (
        "from GnssFix's default for fix type 'single' (2.5 m per horizontal axis x HDOP (median 0.90)"
        in (fix.sigma["text"])
    )
    assert fix.sigma["pos_std_enu_m_median"] == pytest.approx([2.25, 2.25, 3.825])
    for case, origin in (("ros2", "covariance"), ("ubx", "receiver")):
        fix = next(s for s in _check(files[case]).streams if s.kind == "gnss_fix")
        assert fix.sigma["pos_origin"] == {origin: len(drive.fixes)}
        assert fix.sigma["vel_origin"] == {origin: len(drive.fixes)}


@pytest.mark.parametrize("case", ["ros2", "mcap"])
def test_a_twist_in_the_wrong_frame_is_named_not_blamed_on_the_imu(files, case):
    """The Twist is ENU; a mapping that says twist_frame = "NED" gets its velocities with east and
    north exchanged: the check names twist_frame (from the velocities against the positions' track)
    and checks the IMU against the velocities in the other frame, so the IMU is not called mirrored."""
    p = _variant(
        files[case], 'twist_topic = "/gnss/vel"\n', 'twist_topic = "/gnss/vel"\ntwist_frame = "NED"\n', "ned"
    )
    r = _check(p)
    assert len(r.errors) == 1, r.text()
    assert (
        "the Twist's velocities look ENU, the mapping says twist_frame = 'NED': set twist_frame = 'ENU'"
        in (r.errors[0])
    )
    assert not [w for w in r.warnings if "mirrored" in w or "gyro" in w], r.text()
    mo = r.motion["imu"]
    assert abs(mo["time_offset"]["lag_s"]) < 0.02 and mo["yaw"]["sign"] == 1.0
    assert replay_main([str(p), "--check"]) == 2  # refused: nothing published
