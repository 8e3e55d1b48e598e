"""fednav-replay without a service: the mapping (axes, units, time bases), every parser against the
messages its test file was written from, and the checks with their messages."""

from __future__ import annotations

import json
import re
from pathlib import Path

import numpy as np
import pytest

from fednav.replay import checks, mapping
from fednav.replay.__main__ import main as replay_main
from fednav.replay.events import ImuBuilder, merge, nmea_fix_to_wire
from fednav.replay.mapping import MappingError, axes_matrix, from_dict, to_gps_s
from fednav.replay.sources import stream_events
from fednav.service.messages import (
    DEFAULT_H_STD_M,
    DEFAULT_SPEED_STD_MPS,
    VERTICAL_TO_HORIZONTAL,
    GnssFix,
    ImuSample,
)

from . import replay_files as rf

G0 = 9.80665


@pytest.fixture(scope="module")
def drive(tmp_path_factory):
    tmp = tmp_path_factory.mktemp("replay_drive")
    return rf.simulate_drive(tmp, duration_s=32.0)


@pytest.fixture(scope="module")
def files(drive, tmp_path_factory):
    tmp = tmp_path_factory.mktemp("replay_files")
    return rf.write_all(tmp, drive)


def events_of(mapping_path: Path):
    m, base = mapping.load_mapping(mapping_path)
    return m, {s.kind: list(stream_events(s, base, m)) for s in m.streams}


# --- axes, units, time ------------------------------------------------------------------------------
def test_axes_letters_are_the_rotation_to_rfu():
    # FLU: x forward, y left, z up -> RFU (right, forward, up)
    m = axes_matrix("FLU")
    assert np.allclose(m @ [1, 0, 0], [0, 1, 0])  # forward
    assert np.allclose(m @ [0, 1, 0], [-1, 0, 0])  # left = -right
    assert np.allclose(m @ [0, 0, 1], [0, 0, 1])
    # FRD: gravity reaction at rest reads -g on z (down) -> +g on fednav's up
    assert np.allclose(axes_matrix("FRD") @ [0, 0, -G0], [0, 0, G0])
    assert np.allclose(axes_matrix("RFU"), np.eye(3))
    for name in ("FLU", "FRD", "RFU", "ENU".replace("E", "R").replace("N", "F")):
        r = axes_matrix(name)
        assert np.allclose(r @ r.T, np.eye(3)) and np.isclose(np.linalg.det(r), 1.0)


def test_axes_matrix_form_matches_scipy_rotation():
    from scipy.spatial.transform import Rotation

    rot = Rotation.from_euler("zyx", [30.0, 10.0, -5.0], degrees=True).as_matrix()
    assert np.allclose(axes_matrix(rot.tolist()), rot)
    v = np.array([0.3, -1.2, 9.7])
    b = ImuBuilder(rot, 1.0, 1.0, "increment")
    s = b.push(0.01, v * 1e-3, v * 0.01, dt=0.01)
    assert np.allclose(s.dvel_mps, rot @ v * 0.01) and np.allclose(s.dtheta_rad, rot @ v * 1e-3)


@pytest.mark.parametrize(
    "axes, why",
    [
        ("FRU", "left-handed"),
        ("FFU", "must appear once"),
        ("XYZ", "three letters"),
        ([[1, 0, 0], [0, 1, 0]], "3x3"),
    ],
)
def test_bad_axes_are_refused_naming_the_field(axes, why):
    with pytest.raises(MappingError) as e:
        from_dict({"streams": [{"source": "a.csv", "kind": "imu", "sensor_id": "i", "axes": axes}]})
    assert "streams.0.axes" in str(e.value) and why in str(e.value)


def test_mapping_errors_name_the_field():
    with pytest.raises(MappingError, match=r"streams\.0\.gyro_unit"):
        from_dict({"streams": [{"source": "a.csv", "kind": "imu", "sensor_id": "i", "gyro_unit": "rpm"}]})
    with pytest.raises(MappingError, match=r"streams\.0\.axis: unknown field \(did you mean 'axes'\?\)"):
        from_dict({"streams": [{"source": "a.csv", "kind": "imu", "sensor_id": "i", "axis": "FLU"}]})
    with pytest.raises(MappingError, match="boot_offset_s"):
        from_dict({"streams": [{"source": "a.csv", "kind": "imu", "sensor_id": "i", "time_base": "boot"}]})
    with pytest.raises(MappingError, match="'topic'"):
        from_dict({"streams": [{"source": "x.bag", "kind": "imu", "sensor_id": "i"}]})


def test_time_bases_and_leap_seconds():
    def s(**kw):
        return from_dict({"streams": [{"source": "a.csv", "kind": "imu", "sensor_id": "i", **kw}]}).streams[0]

    # 2017-01-01T00:00:00Z: POSIX 1483228800; GPS - UTC = 18 s from then on
    assert to_gps_s(1483228800.0, s(time_base="unix"), 18) == pytest.approx(1483228800.0 - 315964800.0 + 18)
    assert to_gps_s(1483228800.0, s(time_base="unix"), 17) == pytest.approx(1167264017.0)
    assert to_gps_s(123.0, s(time_base="gps"), 18) == 123.0
    assert to_gps_s(12.5, s(time_base="boot", boot_offset_s=1.4e9), 18) == pytest.approx(1.4e9 + 12.5)
    assert to_gps_s(12.5, s(time_base="boot", boot_offset_s=1.4e9, time_offset_s=-0.25), 18) == pytest.approx(
        1.4e9 + 12.25
    )


def test_units_and_rate_form_trapezoid():
    # deg/s and g in FRD -> rad and m/s in RFU; rate form integrates the trapezoid of two samples
    b = ImuBuilder(axes_matrix("FRD"), np.pi / 180.0, G0, "rate")
    assert b.push(1.0, [0, 0, 10.0], [0, 0, -1.0]) is None  # opens the first interval
    s = b.push(1.01, [0, 0, 30.0], [0, 0, -1.0])
    assert s.dt_s == pytest.approx(0.01)
    assert np.allclose(s.dtheta_rad, [0, 0, -np.radians(20.0) * 0.01])  # yaw right (FRD z down) = -z RFU
    assert np.allclose(s.dvel_mps, [0, 0, G0 * 0.01])
    assert b.push(1.005, [0, 0, 0], [0, 0, -1]) is None and b.skipped == {"stamp_not_increasing": 1}
    assert b.push(3.0, [0, 0, 0], [0, 0, -1]) is None and b.skipped["gap"] == 1


def test_merge_is_in_time_order_across_streams(files):
    m, base = mapping.load_mapping(files["nmea_csv"])
    ts = [e.t_gps_s for e in merge(stream_events(s, base, m) for s in m.streams)]
    assert ts == sorted(ts) and len(ts) > 2000


# --- every parser against what its file was written from ---------------------------------------------
def _by_t(msgs):
    return {round(x.t, 3): x for x in msgs}


@pytest.mark.parametrize("case", ["ros2", "ros1", "mcap", "nmea_csv", "ubx"])
def test_each_format_reads_back_what_was_written(case, files, drive):
    m, ev = events_of(files[case])
    imu = [e.msg for e in ev["imu"]]
    fixes = [e.msg for e in ev["gnss_fix"]]
    assert all(isinstance(x, ImuSample) for x in imu) and all(isinstance(x, GnssFix) for x in fixes)
    assert all(e.key_suffix == "sensor/imu/imu" for e in ev["imu"])
    assert all(e.key_suffix == "sensor/gnss/rx/fix" for e in ev["gnss_fix"])
    ref_fix = _by_t(drive.fixes)
    assert len(imu) >= len(drive.imu) - 1 and len(fixes) == len(drive.fixes)
    # IMU: increments in RFU. CSV is written as increments: read back exactly (text precision).
    # The others are written as rates (increment / dt), which the rate form re-integrates by the
    # trapezoid: the expected increment is 0.5 (r_{k-1} + r_k) dt_k of the written rates (closed
    # form). ESF-RAW is quantised: half an LSB (2^-12 deg/s, 2^-10 m/s^2) times dt; stamps of
    # unix time in float64 carry ~1e-7 s, so dt agrees to 2e-6 s.
    ref_list = drive.imu
    index = {round(x.t, 3): k for k, x in enumerate(ref_list)}
    q_th, q_v = (
        (0.5 * np.radians(2.0**-12) * 0.0101, 0.5 * 2.0**-10 * 0.0101) if case == "ubx" else (0.0, 0.0)
    )
    for s in imu:
        k = index[round(s.t, 3)]
        r = ref_list[k]
        assert s.dt_s == pytest.approx(r.dt_s, abs=2e-6)
        if case == "nmea_csv":
            exp_th, exp_v = np.asarray(r.dtheta_rad), np.asarray(r.dvel_mps)
        else:
            p = ref_list[k - 1]
            exp_th = 0.5 * (np.asarray(p.dtheta_rad) / p.dt_s + np.asarray(r.dtheta_rad) / r.dt_s) * s.dt_s
            exp_v = 0.5 * (np.asarray(p.dvel_mps) / p.dt_s + np.asarray(r.dvel_mps) / r.dt_s) * s.dt_s
        assert np.allclose(s.dtheta_rad, exp_th, rtol=1e-6, atol=1e-12 + q_th), (s, r)
        assert np.allclose(s.dvel_mps, exp_v, rtol=1e-6, atol=1e-10 + q_v), (s, r)
    for f in fixes:
        r = ref_fix[round(f.t, 3)]
        assert f.t == pytest.approx(r.t, abs=1e-6)
        assert f.lat_deg == pytest.approx(r.lat_deg, abs=2e-7) and f.lon_deg == pytest.approx(
            r.lon_deg, abs=2e-7
        )
        assert f.height_m == pytest.approx(r.height_m, abs=2e-3)
        if case == "nmea_csv":  # the speed + course variant: no vertical velocity is invented
            assert f.variant == "speed_course" and f.vel_enu_mps is None
            assert f.vertical_rate_mps is None and f.vel_std_enu_mps is None
            assert np.allclose(f.velocity()[:2], r.vel_enu_mps[:2], atol=1e-3)
            assert f.speed_std_mps is None and f.speed_std() == DEFAULT_SPEED_STD_MPS["single"]
            assert np.allclose(f.pos_std_enu_m, r.pos_std_enu_m, atol=1e-3)  # from GST
            assert f.fix_type == "single" and f.hdop is not None
        else:
            assert np.allclose(f.vel_enu_mps, r.vel_enu_mps, atol=1e-3)
            assert np.allclose(f.pos_std_enu_m, r.pos_std_enu_m, atol=2e-3)


def test_nmea_without_rmc_needs_a_date_and_takes_it_from_the_mapping(tmp_path, drive):
    import pynmea2

    lines = [ln for ln in rf.nmea_lines(drive) if ln.startswith("$GPGGA")]
    lines.insert(3, "$GPGGA,garbage*00")
    (tmp_path / "gga.nmea").write_text("\n".join(lines) + "\n")
    assert pynmea2.parse(lines[0], check=True).sentence_type == "GGA"
    base = {"source": "gga.nmea", "kind": "gnss_fix", "sensor_id": "rx", "time_base": "utc"}
    m = from_dict({"streams": [base]})
    with pytest.raises(ValueError, match="set 'date'"):
        list(stream_events(m.streams[0], tmp_path, m))
    date = rf.gps_to_utc(drive.fixes[0].t).date().isoformat()
    m = from_dict({"streams": [{**base, "date": date}]})
    stats: dict = {}
    from fednav.replay import nmea_source

    fixes = list(nmea_source.events(m.streams[0], tmp_path, m, stats=stats))
    # one bad line; every fix's position sigma is GnssFix's default (no GST, no pos_std_m)
    assert stats == {"bad_sentence": 1, "sigma_pos:default": len(drive.fixes)}
    assert len(fixes) == len(drive.fixes)
    assert fixes[5].t_gps_s == pytest.approx(drive.fixes[5].t, abs=1e-6)
    f = fixes[5].msg  # no GST, no RMC: position only, sigmas the documented defaults from GGA
    assert f.variant == "position" and f.velocity() is None and f.vel_std() is None
    assert f.pos_std_enu_m is None and f.fix_type == "single"
    gga = pynmea2.parse(lines[6], check=True)  # lines[3] is the garbage one
    assert f.hdop == pytest.approx(float(gga.horizontal_dil))
    h = DEFAULT_H_STD_M["single"] * f.hdop
    assert f.pos_std() == pytest.approx((h, h, VERTICAL_TO_HORIZONTAL * h))
    # the mapping's pos_std_m, when given, overrides the defaults
    m = from_dict({"streams": [{**base, "date": date, "pos_std_m": [2.0, 2.0, 4.0]}]})
    f = list(nmea_source.events(m.streams[0], tmp_path, m))[5].msg
    assert f.pos_std_enu_m == (2.0, 2.0, 4.0) and f.variant == "position"


def test_navsatfix_without_twist_is_position_only(files):
    # the same bag without twist_topic: position-only fixes, the bag's covariance as sigmas
    m, base = mapping.load_mapping(_with(files["ros2"], 'twist_topic = "/gnss/vel"\n', ""))
    fix_stream = next(s for s in m.streams if s.kind == "gnss_fix")
    out = [e.msg for e in stream_events(fix_stream, base, m)]
    assert out and all(f.variant == "position" and f.vel_std_enu_mps is None for f in out)
    assert all(f.fix_type == "single" and f.pos_std_enu_m == pytest.approx((1.0, 1.0, 2.0)) for f in out)
    # with the twist: the 3-D velocity variant (the receiver's own velocity)
    m, base = mapping.load_mapping(files["ros2"])
    fix_stream = next(s for s in m.streams if s.kind == "gnss_fix")
    out3 = [e.msg for e in stream_events(fix_stream, base, m)]
    assert len(out3) == len(out) and all(f.variant == "velocity" for f in out3)


def test_ubx_nav_pvt_keeps_its_measured_3d_velocity(files):
    m, base = mapping.load_mapping(files["ubx"])
    fix_stream = next(s for s in m.streams if s.kind == "gnss_fix")
    out = [e.msg for e in stream_events(fix_stream, base, m)]
    assert out and all(f.variant == "velocity" and f.vel_std_enu_mps is not None for f in out)
    assert all(f.fix_type == "single" for f in out)


def test_nmea_fix_to_wire_speed_and_course():
    f = nmea_fix_to_wire(1.0, 10.0, 20.0, 5.0, 10.0, 90.0, (1.0, 1.0, 2.0), 0.2, num_sats=7)
    assert f.variant == "speed_course" and f.vel_enu_mps is None and f.vertical_rate_mps is None
    assert np.allclose(f.velocity(), [10.0, 0.0, 0.0], atol=1e-12)  # east at course 90 deg
    assert f.speed_std_mps == 0.2 and f.course_std_deg is None and f.num_sats == 7
    assert f.pos_std_enu_m == (1.0, 1.0, 2.0)
    # no speed or no course: position only, nothing invented; sigmas default from fix type/HDOP
    for speed, course in ((None, None), (3.0, None), (None, 45.0)):
        g = nmea_fix_to_wire(1.0, 10.0, 20.0, 5.0, speed, course, None, 0.2, fix_type="dgnss", hdop=2.0)
        assert g.variant == "position" and g.speed_mps is None and g.speed_std_mps is None
        h = DEFAULT_H_STD_M["dgnss"] * 2.0
        assert g.pos_std() == pytest.approx((h, h, VERTICAL_TO_HORIZONTAL * h))
    # without a speed sigma: the fix type's documented default
    g = nmea_fix_to_wire(1.0, 10.0, 20.0, 5.0, 2.0, 10.0, None, None, fix_type="float")
    assert g.speed_std() == DEFAULT_SPEED_STD_MPS["float"]


@pytest.mark.parametrize(
    ("qual", "fix_type"), [(1, "single"), (2, "dgnss"), (4, "fixed"), (5, "float"), (9, "sbas")]
)
def test_nmea_fix_type_from_gga_quality(tmp_path, drive, qual, fix_type):
    import pynmea2

    src = [ln for ln in rf.nmea_lines(drive) if ln.startswith("$GPGGA")][:3]
    lines = []
    for ln in src:
        f = ln[1 : ln.index("*")].split(",")
        f[6] = str(qual)
        body = ",".join(f)
        lines.append(f"${body}*{pynmea2.NMEASentence.checksum(body):02X}")
    (tmp_path / "q.nmea").write_text("\n".join(lines) + "\n")
    date = rf.gps_to_utc(drive.fixes[0].t).date().isoformat()
    m = from_dict(
        {
            "streams": [
                {"source": "q.nmea", "kind": "gnss_fix", "sensor_id": "rx", "time_base": "utc", "date": date}
            ]
        }
    )
    out = [e.msg for e in stream_events(m.streams[0], tmp_path, m)]
    assert len(out) == 3 and {f.fix_type for f in out} == {fix_type}


def test_rinex_slot_says_plainly_when_it_is_not_available(tmp_path, monkeypatch):
    from fednav.replay import rinex_source

    monkeypatch.setattr(rinex_source, "available", lambda: False)
    m = from_dict({"streams": [{"source": "site.19o", "kind": "gnss_raw", "sensor_id": "rx"}]})
    assert m.streams[0].resolved_format() == "rinex"
    with pytest.raises(ValueError, match="RINEX replay is not available"):
        list(stream_events(m.streams[0], tmp_path, m))


# --- checks ---------------------------------------------------------------------------------------
def _with(path: Path, old: str, new: str) -> Path:
    p = path.with_name(path.stem + "_variant.toml")
    text = path.read_text()
    assert old in text
    p.write_text(text.replace(old, new, 1))
    return p


def test_good_files_pass_every_check(files):
    for case, p in files.items():
        m, base = mapping.load_mapping(p)
        r = checks.run_checks(m, base)
        assert r.errors == [] and r.warnings == [], (case, r.text())
        imu = next(s for s in r.streams if s.kind == "imu")
        assert imu.rate_hz == pytest.approx(100.0, rel=1e-3)


def test_gravity_check_names_the_axes(files):
    # the bag is FLU; a mapping that says FRD sees gravity on z the wrong way
    m, base = mapping.load_mapping(_with(files["ros2"], 'axes = "FLU"', 'axes = "FRD"'))
    r = checks.run_checks(m, base)
    assert "IMU 'imu' z axis reads +9.8 m/s^2 at rest: axes look like FLU, mapping says FRD" in r.errors
    # the CSV is FRD; declared FLU
    m, base = mapping.load_mapping(_with(files["nmea_csv"], 'axes = "FRD"', 'axes = "FLU"'))
    r = checks.run_checks(m, base)
    assert any("z axis reads -1.0 g at rest: axes look like FRD, mapping says FLU" in e for e in r.errors), (
        r.errors
    )


def test_gravity_check_names_the_units(files):
    m, base = mapping.load_mapping(_with(files["nmea_csv"], 'accel_unit = "g"', 'accel_unit = "m/s^2"'))
    r = checks.run_checks(m, base)
    assert any("looks like it is in g, mapping says accel_unit = 'm/s^2'" in e for e in r.errors), r.errors


def test_time_bases_differ_is_named(files):
    # the CSV's boot offset forgotten by an hour
    bad = _with(
        files["nmea_csv"], f"boot_offset_s = {rf.BOOT_GPS_S}", f"boot_offset_s = {rf.BOOT_GPS_S - 3600.0}"
    )
    m, base = mapping.load_mapping(bad)
    r = checks.run_checks(m, base)
    assert any(
        e.startswith("time bases differ:") and re.search(r"\+3600\.\d s \(and ends \+3600\.0 s\) apart", e)
        for e in r.errors
    )
    # GNSS in UTC read as GPS: 18 s apart, named as a leap-second suspicion
    m, base = mapping.load_mapping(
        _with(
            files["nmea_csv"], f"boot_offset_s = {rf.BOOT_GPS_S}", f"boot_offset_s = {rf.BOOT_GPS_S - 18.0}"
        )
    )
    r = checks.run_checks(m, base)
    assert any("the leap seconds" in w for w in r.warnings), r.warnings


def test_non_monotonic_stamps_and_low_rate_are_named(tmp_path, drive, files):
    text = (files["nmea_csv"].parent / "imu.csv").read_text().splitlines()
    rows = text[2:]
    rows[50], rows[51] = rows[51], rows[50]  # two samples swapped
    (tmp_path / "imu.csv").write_text("\n".join(text[:2] + rows) + "\n")
    (tmp_path / "imu10.csv").write_text("\n".join(text[:2] + rows[::10]) + "\n")
    (tmp_path / "drive.nmea").write_text((files["nmea_csv"].parent / "drive.nmea").read_text())
    p = tmp_path / "m.toml"
    p.write_text(files["nmea_csv"].read_text())
    m, base = mapping.load_mapping(p)
    r = checks.run_checks(m, base)
    assert any("stamp(s) go backwards or repeat: the stamps are not monotonic" in e for e in r.errors), (
        r.errors
    )
    p.write_text(
        files["nmea_csv"]
        .read_text()
        .replace("imu.csv", "imu10.csv")
        .replace('form = "increment"', 'form = "increment"')
    )
    m, base = mapping.load_mapping(p)
    r = checks.run_checks(m, base)
    assert any("IMU at 10.0 Hz, below 50 Hz" in w for w in r.warnings), r.warnings


def test_missing_topic_and_missing_file_are_named(files):
    m, base = mapping.load_mapping(_with(files["ros1"], 'topic = "/imu/data"', 'topic = "/imu/raw"'))
    r = checks.run_checks(m, base)
    assert any(
        "no topic '/imu/raw'; the file has: /gnss/fix (sensor_msgs/msg/NavSatFix)" in e for e in r.errors
    )
    assert any("no IMU" in e or "imu 'imu'" in e for e in r.errors)


def test_an_orientation_only_imu_topic_is_named_not_integrated(tmp_path, drive):
    """An Imu topic from an orientation-only driver (an AHRS's filter output: zero rates with
    angular_velocity_covariance[0] = -1, sensor_msgs/Imu's "no estimate") carries no rates: its
    messages are skipped (``no_rates``) and the check says to map the raw IMU topic, instead of
    integrating zeros (until then the check blamed the accelerometer's unit)."""
    from rosbags.rosbag2 import Writer
    from rosbags.typesys import Stores, get_typestore

    ts = get_typestore(Stores.ROS2_JAZZY)
    msgs = rf._ros_msgs(ts, drive, "FLU", ros1=False)
    V3 = ts.types["geometry_msgs/msg/Vector3"]
    with Writer(tmp_path / "ahrs", version=9) as w:
        conns = {}
        for topic, typ, tu, msg in msgs:
            if typ == "sensor_msgs/msg/Imu":  # the AHRS's message: orientation only
                msg.angular_velocity = msg.linear_acceleration = V3(x=0.0, y=0.0, z=0.0)
                msg.angular_velocity_covariance = np.r_[-1.0, np.zeros(8)]
                msg.linear_acceleration_covariance = np.r_[-1.0, np.zeros(8)]
                msg.orientation_covariance = np.eye(3).ravel() * 1e-4
            if topic not in conns:
                conns[topic] = w.add_connection(topic, typ, typestore=ts)
            w.write(conns[topic], int(round(tu * 1e9)), ts.serialize_cdr(msg, typ))
    p = tmp_path / "ahrs.toml"
    p.write_text(files_mapping("ahrs"))
    m, base = mapping.load_mapping(p)
    r = checks.run_checks(m, base)
    imu = next(s for s in r.streams if s.kind == "imu")
    assert imu.count == 0 and imu.skipped == {"no_rates": len(drive.imu)}
    assert any("no rates" in e and "/imu/data_raw" in e for e in r.errors), r.text()
    assert not any("accel_unit" in e for e in r.errors), r.text()  # (the message until then)


def test_imu_stamps_left_unset_are_named_not_taken_for_boot_time(tmp_path, drive):
    """A ROS driver that never fills header.stamp (every stamp 0): the check says so; until then it
    said "seconds since the device booted: set time_base = 'boot' with boot_offset_s (or 'auto')",
    which reads every sample as the same instant."""
    from rosbags.rosbag2 import Writer
    from rosbags.typesys import Stores, get_typestore

    ts = get_typestore(Stores.ROS2_JAZZY)
    with Writer(tmp_path / "nostamp", version=9) as w:
        conns = {}
        for topic, typ, tu, msg in rf._ros_msgs(ts, drive, "FLU", ros1=False):
            if typ == "sensor_msgs/msg/Imu":
                msg.header.stamp.sec, msg.header.stamp.nanosec = 0, 0
            if topic not in conns:
                conns[topic] = w.add_connection(topic, typ, typestore=ts)
            w.write(conns[topic], int(round(tu * 1e9)), ts.serialize_cdr(msg, typ))
    p = tmp_path / "nostamp.toml"
    p.write_text(files_mapping("nostamp"))
    m, base = mapping.load_mapping(p)
    r = checks.run_checks(m, base)
    [err] = [e for e in r.errors if e.startswith("imu 'imu'")]
    assert "unset, 0" in err and "header.stamp" in err, err
    assert "boot" not in err, err


def files_mapping(src: str) -> str:
    """The ROS mapping of ``rf.write_all`` on bag ``src``."""
    return f"""vehicle = "v1"
[[streams]]
source = "{src}"
kind = "imu"
sensor_id = "imu"
topic = "/imu/data"
axes = "FLU"
time_base = "unix"

[[streams]]
source = "{src}"
kind = "gnss_fix"
sensor_id = "rx"
topic = "/gnss/fix"
twist_topic = "/gnss/vel"
time_base = "unix"
"""


def test_cli_check_only_publishes_nothing_and_reports_json(files, capsys):
    assert replay_main([str(files["ubx"]), "--check", "--json"]) == 0
    out = json.loads(capsys.readouterr().out)
    assert out["check"]["errors"] == [] and "published" not in out and out["check"]["messages"] > 2000
    bad = _with(files["ros2"], 'axes = "FLU"', 'axes = "FRD"')
    assert replay_main([str(bad), "--check"]) == 2
    assert "axes look like FLU, mapping says FRD" in capsys.readouterr().out
    # a failed check publishes nothing (no service is running: it would wait for one otherwise)
    assert replay_main([str(bad), "--match-timeout", "0.1"]) == 2


def test_example_mappings_and_service_config_are_valid():
    from fednav.service.config import load

    root = Path(__file__).resolve().parents[1] / "replay" / "examples"
    names = sorted(p.name for p in root.glob("*.toml"))
    assert names == [
        "nmea_imu_csv.toml",
        "nmea_service.toml",
        "rinex.toml",
        "rinex_service.toml",
        "ros2_bag.toml",
        "service.toml",
    ]
    for name, service, kinds in (
        ("nmea_imu_csv.toml", "nmea_service.toml", {"imu", "gnss_fix"}),
        ("ros2_bag.toml", "service.toml", {"imu", "gnss_fix"}),
        ("rinex.toml", "rinex_service.toml", {"imu", "gnss_raw"}),
    ):
        m, _ = mapping.load_mapping(root / name)
        assert {s.kind for s in m.streams} == kinds
        cfg = load(root / service)
        assert cfg.vehicles == [m.vehicle]
    # the first service file the README shows is not navigation grade (issue 24): the cautious preset
    assert load(root / "service.toml").imu.grade == "consumer_mems"
    assert mapping.load_mapping(root / "ros2_bag.toml")[0].endpoint == "tcp/127.0.0.1:7447"
    csv_imu = mapping.load_mapping(root / "nmea_imu_csv.toml")[0].streams[0]
    assert csv_imu.time_base == "boot" and csv_imu.boot_offset_s == "auto"
    nmea = load(root / "nmea_service.toml")
    assert nmea.imu.grade == "consumer_mems" and nmea.pipelines[0].gnss_correlated_error is not None
    tc = load(root / "rinex_service.toml")
    assert tc.init.mode == "auto" and tc.pipelines[0].kind == "tightly_coupled"
    rinex = mapping.load_mapping(root / "rinex.toml")[0]
    assert [s.resolved_format() for s in rinex.streams] == ["csv", "rinex"]


def test_progress_bar_draws_only_when_enabled():
    import io

    from fednav.replay.__main__ import Progress

    out = io.StringIO()
    p = Progress(4, enabled=True, stream=out)
    for t in (10.0, 10.5, 11.0, 12.0):
        p.step(t)
    p.close()
    last = out.getvalue().rstrip("\n").split("\r")[-1]
    assert last.startswith("[" + "#" * 30 + "] 100.0% 4/4 msgs") and "+    2.0 s log" in last
    quiet = io.StringIO()
    q = Progress(4, enabled=False, stream=quiet)
    q.step(1.0)
    q.close()
    assert quiet.getvalue() == ""


def test_rinex_slot_calls_iter_gnss_raw_when_present(tmp_path, monkeypatch):
    import sys
    import types

    from fednav.service.messages import GnssRaw

    calls = []

    def iter_gnss_raw(obs_path, nav_paths, **options):
        calls.append((obs_path, nav_paths, options))
        yield 1.4e9, GnssRaw(t=1.4e9, sats=[])
        yield 1.4e9 + 1.0, GnssRaw(t=1.4e9 + 1.0, sats=[])

    fake = types.ModuleType("fednav.simulators.gnss.rinex_raw")
    fake.iter_gnss_raw = iter_gnss_raw
    monkeypatch.setitem(sys.modules, "fednav.simulators.gnss.rinex_raw", fake)
    m = from_dict(
        {
            "rinex_nav": ["brdc.19n"],
            "streams": [
                {
                    "source": "site.19o",
                    "kind": "gnss_raw",
                    "sensor_id": "rx",
                    "rinex_options": {"systems": ["G"], "max_age_s": 7200},
                }
            ],
        }
    )
    ev = list(stream_events(m.streams[0], tmp_path, m))
    assert [e.t_gps_s for e in ev] == [1.4e9, 1.4e9 + 1.0] and ev[0].key_suffix == "sensor/gnss/rx/raw"
    assert calls == [(tmp_path / "site.19o", [tmp_path / "brdc.19n"], {"systems": ["G"], "max_age_s": 7200})]


def test_gyro_in_deg_per_s_declared_rad_per_s_is_named(tmp_path):
    # rate-form CSV in FLU, deg/s, turning at 60 deg/s after a static second: declared rad/s,
    # the turn reads 60 rad/s, above the wire's plausibility limit
    rows = ["t,gyro_x,gyro_y,gyro_z,accel_x,accel_y,accel_z"]
    for k in range(300):
        t = 1.4e9 + 0.01 * k
        rows.append(f"{t:.2f},0,0,{60.0 if k >= 150 else 0.0},0,0,9.81")
    (tmp_path / "imu.csv").write_text("\n".join(rows) + "\n")
    m = from_dict({"streams": [{"source": "imu.csv", "kind": "imu", "sensor_id": "i", "time_base": "gps"}]})
    r = checks.run_checks(m, tmp_path)
    assert any("skipped (implausible)" in w and "deg/s data declared rad/s?" in w for w in r.warnings), (
        r.warnings
    )


def test_no_service_and_unserved_vehicle_are_named(files, capsys):
    import zenoh

    from fednav.simulators.processes import free_port

    dead = free_port()
    assert (
        replay_main([str(files["nmea_csv"]), "--connect", f"tcp/127.0.0.1:{dead}", "--match-timeout", "0.5"])
        == 3
    )
    err = capsys.readouterr().err
    assert f"no fednav service or Zenoh router answered on tcp/127.0.0.1:{dead} within 0.5 s" in err, err
    # a Zenoh peer is there, but nothing subscribes to this vehicle's keys
    port = free_port()
    c = zenoh.Config()
    c.insert_json5("mode", '"peer"')
    c.insert_json5("scouting/multicast/enabled", "false")
    c.insert_json5("listen/endpoints", json.dumps([f"tcp/127.0.0.1:{port}"]))
    with zenoh.open(c):
        args = [str(files["nmea_csv"]), "--connect", f"tcp/127.0.0.1:{port}", "--match-timeout", "0.5"]
        assert replay_main(args) == 3
    err = capsys.readouterr().err
    assert "no subscriber matched fednav/nmea_csv/sensor/" in err and "serving vehicle 'nmea_csv'" in err


def test_ubx_vertical_velocity_sigma_follows_the_geometry(files):
    """sAcc is east and north; the vertical velocity's sigma is scaled by vAcc / (hAcc / sqrt 2):
    the test receiver's (1, 1, 2) m position and (0.05, 0.05, 0.1) m/s velocity noise come back."""
    m, base = mapping.load_mapping(files["ubx"])
    fix_stream = next(s for s in m.streams if s.kind == "gnss_fix")
    out = [e.msg for e in stream_events(fix_stream, base, m)]
    assert out and all(f.pos_std_enu_m == pytest.approx((1.0, 1.0, 2.0), abs=1e-3) for f in out)
    assert all(f.vel_std_enu_mps == pytest.approx((0.05, 0.05, 0.1), abs=1e-3) for f in out)
