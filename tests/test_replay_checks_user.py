"""fednav-replay --check on a first-time user's mistakes (a walkthrough with a 180 s car drive):
POSIX stamps declared as GPS time, ``boot_offset_s = "auto"`` one IMU sample early without
turns, one bad GNSS file reported as three errors (two of them wrong), NMEA without checksums
refused without saying why, and ``IMU 'imu''s`` in messages.

Small synthetic logs written to tmp_path: an IMU CSV at rest (rate form, 100 Hz, deg/s and g) and
stationary NMEA fixes (pynmea2 sentences, 5 Hz)."""

from __future__ import annotations

import datetime as dt
import re
from pathlib import Path

import numpy as np
import pytest

from fednav.replay import checks, mapping
from fednav.replay.__main__ import main as replay_main
from fednav.replay.mapping import GPS_EPOCH_UNIX_S
from fednav.replay.sources import stream_events

LEAP = 18
START_UTC = dt.datetime(2024, 5, 17, 10, 0, 0, tzinfo=dt.UTC)
BOOT_FIRST_S = 100.0  # the IMU's first stamp, seconds since boot
IMU_HZ, FIX_HZ, SPAN_S = 100.0, 5.0, 20.0


def fix_gps_s(k: int) -> float:
    return START_UTC.timestamp() + k / FIX_HZ - GPS_EPOCH_UNIX_S + LEAP


def write_imu(path: Path, t0: float) -> Path:
    """An IMU at rest, level (RFU axes: z up reads +1 g), stamps from ``t0``."""
    n = int(SPAN_S * IMU_HZ)
    rows = ["t,gyro_x,gyro_y,gyro_z,accel_x,accel_y,accel_z"]
    rows += [f"{t0 + k / IMU_HZ:.4f},0.01,-0.02,0.01,0.001,-0.002,1.000" for k in range(n)]
    path.write_text("\n".join(rows) + "\n")
    return path


def write_nmea(path: Path, rmc: bool = True, checksum: bool = True) -> Path:
    """Stationary fixes (GGA, RMC with the date) at ``FIX_HZ`` from ``START_UTC``."""
    import pynmea2

    lines = []
    for k in range(int(SPAN_S * FIX_HZ)):
        utc = START_UTC + dt.timedelta(seconds=k / FIX_HZ)
        hms = f"{utc:%H%M%S}.{utc.microsecond // 10000:02d}"
        gga = (hms, "4806.0000", "N", "01130.0000", "E", "1", "09", "0.9", "473.2", "M", "47.0", "M", "", "")
        lines.append(pynmea2.GGA("GP", "GGA", gga).render())
        if rmc:
            r = (hms, "A", "4806.0000", "N", "01130.0000", "E", "0.0", "0.0", f"{utc:%d%m%y}", "", "")
            lines.append(pynmea2.RMC("GP", "RMC", r).render())
    if not checksum:
        lines = [ln.split("*")[0] for ln in lines]
    path.write_text("\n".join(lines) + "\n")
    return path


def write_mapping(d: Path, imu_time: str, nmea: str | None = "fix.nmea") -> Path:
    text = f"""vehicle = "v1"
leap_seconds = {LEAP}

[[streams]]
source = "imu.csv"
kind = "imu"
sensor_id = "imu"
axes = "RFU"
form = "rate"
gyro_unit = "deg/s"
accel_unit = "g"
{imu_time}
"""
    if nmea is not None:
        text += f"""
[[streams]]
source = "{nmea}"
kind = "gnss_fix"
sensor_id = "rx"
time_base = "utc"
sentences = ["GGA", "RMC"]
"""
    p = d / "drive.toml"
    p.write_text(text)
    return p


def check(p: Path) -> checks.Report:
    m, base = mapping.load_mapping(p)
    r = checks.run_checks(m, base)
    assert "''s" not in r.text(), r.text()
    return r


# --- 1. POSIX stamps declared as GPS time -------------------------------------------------------------
def test_posix_stamps_declared_gps_start_after_the_present_and_are_refused(tmp_path):
    posix = START_UTC.timestamp()  # 2024 in POSIX seconds: 2034 read as GPS seconds
    write_imu(tmp_path / "imu.csv", posix)
    r = check(write_mapping(tmp_path, 'time_base = "gps"', nmea=None))
    e = [e for e in r.errors if "after the present" in e]
    assert len(e) == 1, r.text()
    assert "imu 'imu': the log starts 2034-05-2" in e[0], e[0]
    assert "POSIX (UTC) seconds declared as GPS time: set time_base = 'unix'" in e[0], e[0]
    assert "nothing published" in r.text()
    # declared as what they are: no error
    r = check(write_mapping(tmp_path, 'time_base = "unix"', nmea=None))
    assert r.errors == [], r.text()


def test_a_start_within_a_day_of_the_present_is_accepted(tmp_path):
    now_unix = dt.datetime.now(dt.UTC).timestamp()
    write_imu(tmp_path / "imu.csv", now_unix - 3600.0)
    r = check(write_mapping(tmp_path, 'time_base = "unix"', nmea=None))
    assert r.errors == [], r.text()


# --- 2. boot_offset_s = "auto" without turns: from the first stamp -----------------------------------
def test_auto_boot_offset_without_motion_is_the_first_fix_minus_the_first_stamp(tmp_path):
    write_imu(tmp_path / "imu.csv", BOOT_FIRST_S)
    write_nmea(tmp_path / "fix.nmea")
    r = check(write_mapping(tmp_path, 'time_base = "boot"\nboot_offset_s = "auto"'))
    assert r.errors == [], r.text()
    note = next(n for n in r.notes if n.startswith("boot_offset_s of stream 'imu' derived"))
    want = fix_gps_s(0) - BOOT_FIRST_S
    written = float(re.search(r"write boot_offset_s = (\d+\.\d+)", note).group(1))
    assert written == pytest.approx(want, abs=1e-3), note  # not one IMU sample (10 ms) early
    assert r.mapping.streams[0].boot_offset_s == pytest.approx(want, abs=1e-6)
    # the IMU's first sample (the start of its first interval) at the first fix
    assert float(r.data[0].t[0] - r.data[0].dt[0]) == pytest.approx(fix_gps_s(0), abs=1e-6)


# --- 3. one bad GNSS file: one error, as that problem --------------------------------------------------
@pytest.mark.parametrize(
    ("name", "content", "cause"),
    [
        ("empty", "", "gnss_fix 'rx': no messages read from fix.nmea"),
        ("no_date", "gga", "fix.nmea: no RMC sentence gives the date: set 'date' (YYYY-MM-DD)"),
        ("binary", "junk", "gnss_fix 'rx': no messages read from fix.nmea"),
    ],
)
def test_a_bad_gnss_file_is_one_error_plus_its_consequence(tmp_path, name, content, cause, capsys):
    if content == "gga":
        write_nmea(tmp_path / "fix.nmea", rmc=False)
    elif content == "junk":
        (tmp_path / "fix.nmea").write_bytes(bytes(range(256)) * 20)
    else:
        (tmp_path / "fix.nmea").write_text(content)
    write_imu(tmp_path / "imu.csv", BOOT_FIRST_S)
    p = write_mapping(tmp_path, 'time_base = "boot"\nboot_offset_s = "auto"')
    r = check(p)
    assert len(r.errors) == 2, r.text()
    assert cause in r.errors[0] and not r.errors[0].startswith("boot_offset_s"), r.errors
    assert r.errors[1] == (
        "boot_offset_s = 'auto' for stream 'imu' needs fixes from gnss_fix 'rx', which gave none: "
        "not derived, stream 'imu' not checked"
    ), r.errors
    text = r.text()
    assert "resolved by the checks" not in text and "no GNSS fix stream" not in text, text
    # --force cannot publish an IMU whose offset is not derived: said so, consistently, exit 2
    assert replay_main([str(p), "--force", "--match-timeout", "0.1"]) == 2
    out = capsys.readouterr()
    assert "2 error(s): nothing published" in out.out and "publishing anyway" not in out.out, out.out
    assert "--force cannot publish: boot_offset_s = 'auto' of stream(s) 'imu' was not derived" in out.err


def test_forced_errors_say_publishing_anyway():
    r = checks.Report(errors=["something wrong"])
    assert r.text().endswith("1 error(s): nothing published")
    assert r.text(forced=True).endswith("1 error(s): publishing anyway (--force)")


# --- 4. NMEA without checksums -------------------------------------------------------------------------
def test_nmea_without_checksums_is_refused_saying_why(tmp_path):
    write_nmea(tmp_path / "fix.nmea", checksum=False)
    write_imu(tmp_path / "imu.csv", BOOT_FIRST_S)
    p = write_mapping(tmp_path, 'time_base = "boot"\nboot_offset_s = 0.0')
    m, base = mapping.load_mapping(p)
    stats: dict = {}
    assert list(stream_events(m.streams[1], base, m, stats=stats)) == []
    assert stats == {"no_checksum": 200}, stats
    r = check(p)
    e = next(e for e in r.errors if e.startswith("gnss_fix 'rx'"))
    assert "(skipped: 200 no checksum)" in e, e
    assert "NMEA sentences without a '*hh' checksum are refused" in e, e
    # a wrong checksum is still a bad sentence
    lines = write_nmea(tmp_path / "fix.nmea").read_text().splitlines()
    lines[0] = lines[0][:-2] + ("00" if lines[0][-2:] != "00" else "01")
    (tmp_path / "fix.nmea").write_text("\n".join(lines) + "\n")
    stats = {}
    assert len(list(stream_events(m.streams[1], base, m, stats=stats))) == 99
    assert stats.get("bad_sentence") == 1 and "no_checksum" not in stats, stats


# --- 5. no doubled apostrophes -------------------------------------------------------------------------
@pytest.mark.parametrize(
    ("correlation", "zero", "min_corr", "words"),
    [
        (0.99, 0.5, 0.8, "IMU 'imu': its stamps are 0.077 s late against those of gnss_fix 'rx' ("),
        (0.7, 0.2, 1.01, "IMU 'imu': its stamps look 0.077 s late against those of gnss_fix 'rx': "),
        (0.4, 0.2, 1.01, "TIME ALIGNMENT NOT CONFIRMED: the stamps of IMU 'imu' against those of gnss_fix"),
    ],
)
def test_motion_check_messages_name_the_stream_without_a_doubled_apostrophe(
    monkeypatch, correlation, zero, min_corr, words
):
    lag = {
        "lag_s": 0.077,
        "correlation": correlation,
        "zero_correlation": zero,
        "turn_windows": 30,
        "searched_s": [-2.0, 2.0],
        "at_edge": False,
        "score": correlation,
        "runner_up": None,
    }
    monkeypatch.setattr(checks, "estimate_lag", lambda imu, kin, *a: lag)
    monkeypatch.setattr(checks, "LAG_MIN_CORRELATION", min_corr)
    st = {"source": "i.csv", "kind": "imu", "sensor_id": "imu", "time_base": "boot", "boot_offset_s": 5.0}
    m = mapping.from_dict({"streams": [st]})
    n = 10
    imu = checks.ImuData(np.arange(1, n + 1) * 0.01, np.full(n, 0.01), np.zeros((n, 3)), np.zeros((n, 3)))
    z = np.zeros(0)
    kin = checks.Kinematics(z, z, np.zeros((0, 3)), z, z, z)
    r = checks.Report()
    checks.motion_check(m.streams[0], imu, kin, r, "gnss_fix 'rx'", LEAP)
    said = r.errors + r.warnings
    assert any(words in s for s in said), said
    assert not any("''s" in s for s in said), said


@pytest.mark.parametrize(
    "name, kind, hint",
    [
        ("fix.nmea", "gzip", "it is compressed with gzip: decompress it first (gunzip)"),
        ("fix.ubx", "nmea", "it holds NMEA text (it starts with '$'): set format = 'nmea'"),
    ],
)
def test_a_file_whose_bytes_say_another_format_is_named_by_them(tmp_path, name, kind, hint):
    """A gzip file under a plain .nmea name, NMEA text in a .ubx: no message is read, and the error
    says what the file's first bytes are instead of leaving "no messages read" alone."""
    import gzip

    nmea = write_nmea(tmp_path / "plain.nmea")
    data = nmea.read_bytes()
    (tmp_path / name).write_bytes(gzip.compress(data) if kind == "gzip" else data)
    write_imu(tmp_path / "imu.csv", fix_gps_s(0))
    r = check(write_mapping(tmp_path, 'time_base = "gps"', nmea=name))
    err = next(e for e in r.errors if e.startswith("gnss_fix 'rx': no messages read"))
    assert err.endswith(hint), r.text()
