"""fednav-replay's CSV reader (replay/csv_source.py) on the files a new user's logger or spreadsheet
writes: physical line numbers in messages, a truncated last row, empty fields, a byte order mark,
column names in other cases / with units / other separators, stamps in milliseconds (``tick_s``),
an unresolved ``boot_offset_s = 'auto'`` and the line of the first skipped sample."""

from __future__ import annotations

import pytest

from fednav.replay import checks
from fednav.replay.mapping import MappingError, from_dict
from fednav.replay.sources import SourceError, stream_events

HEADER = "t,gyro_x,gyro_y,gyro_z,accel_x,accel_y,accel_z"
T0 = 1.4e9  # GPS seconds


def imu_rows(n: int, t0: float = T0, step: float = 0.01, fmt: str = "{:.2f}") -> list[str]:
    """``n`` rows of an IMU at rest in RFU axes (gravity's reaction on z), ``step`` apart."""
    return [f"{fmt.format(t0 + k * step)},0.001,-0.002,0.003,0.01,-0.02,9.81" for k in range(n)]


def read(tmp_path, text: str | bytes, name: str = "imu.csv", **stream):
    """(events, stats) of an IMU CSV stream reading ``text``."""
    p = tmp_path / name
    if isinstance(text, bytes):
        p.write_bytes(text)
    else:
        p.write_text(text)
    st = {"source": name, "kind": "imu", "sensor_id": "i", "axes": "RFU", "time_base": "gps", **stream}
    m = from_dict({"streams": [st]})
    stats: dict = {}
    return list(stream_events(m.streams[0], tmp_path, m, stats=stats)), stats


def samples(ev) -> list:
    return [(e.t_gps_s, e.msg) for e in ev]


# --- 1. physical line numbers -------------------------------------------------------------------------------
def test_an_error_names_the_physical_line_counting_comments_and_blank_lines(tmp_path):
    rows = imu_rows(6)
    rows[3] = rows[3].replace("0.003", "0.0x3")
    lines = ["# logger v2", "# columns:", HEADER, rows[0], "", "# a comment between rows", *rows[1:3]]
    lines += ["", rows[3], *rows[4:]]
    assert lines.index(rows[3]) + 1 == 10
    with pytest.raises(SourceError, match=r"imu\.csv line 10: gyro_z = '0\.0x3' is not a number"):
        read(tmp_path, "\n".join(lines) + "\n")


def test_a_registry_kind_csv_names_the_physical_line(tmp_path):
    lines = [
        "# barometer",
        "t,altitude_m,std_m",
        f"{T0},10.0,0.4",
        "",
        f"{T0 + 1},ten,0.4",
        f"{T0 + 2},10.2,0.4",
    ]
    (tmp_path / "baro.csv").write_text("\n".join(lines) + "\n")
    m = from_dict({"streams": [{"source": "baro.csv", "kind": "baro", "sensor_id": "b", "time_base": "gps"}]})
    with pytest.raises(SourceError, match=r"baro\.csv line 5: altitude_m = 'ten' is not a number"):
        list(stream_events(m.streams[0], tmp_path, m))


# --- 2. a truncated last row --------------------------------------------------------------------------------
@pytest.mark.parametrize(
    "cut",
    [
        "{t:.2f},0.001,-0.002",  # fewer fields
        "{t:.2f},0.001,-0.002,0.003,0.01,-0.02,9.8e",  # a value cut into no number
        "{t:.2f},0.001,-0.002,0.003,0.01,-0.02,",  # cut after a separator
        "1400",  # cut in the stamp
    ],
)
def test_an_incomplete_last_row_is_skipped_and_counted(tmp_path, cut):
    rows = imu_rows(50)
    whole, _ = read(tmp_path, "\n".join([HEADER, *rows]) + "\n", name="whole.csv")
    last = cut.format(t=T0 + 0.5)
    ev, stats = read(tmp_path, "\n".join(["# log", HEADER, *rows, last]))  # no newline at the end
    assert samples(ev) == samples(whole)
    assert stats["truncated_last_row"] == 1 and stats["_first_line_truncated_last_row"] == 53


def test_a_last_row_cut_before_its_extra_columns_is_skipped_a_complete_one_kept(tmp_path):
    # header with a temperature column after the IMU's: a last line ending inside accel_z has fewer
    # fields than the header and no newline: its accel_z may be cut ("9.8" of "9.81")
    rows = [r + ",31.5" for r in imu_rows(20)]
    text = "\n".join([HEADER + ",temp_c", *rows[:-1], rows[-1][: -len("1,31.5")]])
    ev, stats = read(tmp_path, text)
    assert len(ev) == 18 and stats == {"truncated_last_row": 1, "_first_line_truncated_last_row": 21}
    # a complete last row without a final newline is a valid file: kept, nothing counted
    ev, stats = read(tmp_path, "\n".join([HEADER + ",temp_c", *rows]), name="whole.csv")
    assert len(ev) == 19 and stats == {}
    # so is one as long as the rows before it (a header with a trailing separator, rows without)
    ev, stats = read(tmp_path, "\n".join([HEADER + ",", *imu_rows(20)]), name="trailing.csv")
    assert len(ev) == 19 and stats == {}


def test_a_malformed_row_in_the_middle_stays_an_error(tmp_path):
    rows = imu_rows(10)
    rows[4] = rows[4][:20]
    with pytest.raises(SourceError, match=r"line 6: 3 field\(s\) where the header has 7: no gyro_z"):
        read(tmp_path, "\n".join([HEADER, *rows]) + "\n")


def test_a_nul_padded_tail_of_a_crashed_logger_is_a_truncated_row(tmp_path):
    rows = imu_rows(20)
    ev, stats = read(tmp_path, ("\n".join([HEADER, *rows, rows[0][:25]]) + "\0" * 40).encode())
    assert len(ev) == 19 and stats["truncated_last_row"] == 1
    # NUL bytes inside the log: an error naming the line
    rows[5] = rows[5][:10] + "\0\0" + rows[5][10:]
    with pytest.raises(SourceError, match=r"line 7: t = .* is not a number"):
        read(tmp_path, "\n".join([HEADER, *rows]) + "\n", name="nul.csv")
    # the csv module's own errors (a binary file's huge field) are a SourceError naming the line,
    # not a csv.Error (no ValueError: a traceback out of the checks)
    rows[5] = "x" * 200_000
    with pytest.raises(SourceError, match="line 7: field larger than field limit"):
        read(tmp_path, "\n".join([HEADER, *rows]) + "\n", name="big.csv")


def test_the_checks_warn_about_a_truncated_last_row_and_pass(tmp_path):
    rows = imu_rows(300)
    (tmp_path / "imu.csv").write_text("\n".join([HEADER, *rows, rows[0][:30]]))
    m = from_dict(
        {
            "streams": [
                {"source": "imu.csv", "kind": "imu", "sensor_id": "i", "axes": "RFU", "time_base": "gps"}
            ]
        }
    )
    r = checks.run_checks(m, tmp_path)
    assert not r.errors, r.text()
    assert "imu 'i': 1 sample(s) skipped (truncated last row)" in r.warnings, r.warnings


# --- 3. empty fields, whitespace-only lines -----------------------------------------------------------------
def test_an_empty_field_is_skipped_and_counted_like_nan(tmp_path):
    rows = imu_rows(20)
    whole, _ = read(tmp_path, "\n".join([HEADER, *rows]) + "\n", name="whole.csv")
    nan = list(rows)
    nan[7] = nan[7].replace("-0.002", "nan")
    ev_nan, st_nan = read(tmp_path, "\n".join([HEADER, *nan]) + "\n", name="nan.csv")
    empty = list(rows)
    empty[7] = empty[7].replace("-0.002", "")
    ev, stats = read(tmp_path, "\n".join([HEADER, *empty]) + "\n")
    assert stats == {"empty_field": 1, "_first_line_empty_field": 9}
    assert st_nan == {"not_finite": 1, "_first_line_not_finite": 9}
    assert samples(ev) == samples(ev_nan) and len(ev) == len(whole) - 1
    # an empty stamp is an empty field too
    empty[7] = "," + empty[7].split(",", 1)[1]
    assert read(tmp_path, "\n".join([HEADER, *empty]) + "\n")[1]["empty_field"] == 1


def test_a_whitespace_only_line_is_a_blank_line(tmp_path):
    rows = imu_rows(10)
    whole, _ = read(tmp_path, "\n".join([HEADER, *rows]) + "\n", name="whole.csv")
    ev, stats = read(tmp_path, "\r\n".join([HEADER, *rows[:4], "   ", "\t", " \t ", *rows[4:]]) + "\r\n")
    assert samples(ev) == samples(whole) and stats == {}


# --- 4. byte order mark -------------------------------------------------------------------------------------
def test_a_utf8_byte_order_mark_is_dropped(tmp_path):
    text = "\r\n".join([HEADER, *imu_rows(10)]) + "\r\n"
    whole, _ = read(tmp_path, text, name="whole.csv")
    ev, _ = read(tmp_path, b"\xef\xbb\xbf" + text.encode())
    assert samples(ev) == samples(whole) and len(ev) == 9


# --- 5. column names ----------------------------------------------------------------------------------------
@pytest.mark.parametrize(
    "header,sep",
    [
        ("T, Gyro_X, Gyro_Y, Gyro_Z, Accel_X, Accel_Y, Accel_Z", ","),
        (" t ,GYRO_X,gyro_y,gyro_z,ACCEL_x,accel_y,accel_z ", ","),
        (HEADER.replace(",", ";"), ";"),
        (HEADER.replace(",", "\t"), "\t"),
    ],
)
def test_column_names_ignore_case_and_spaces_and_semicolon_or_tab_separate(tmp_path, header, sep):
    rows = imu_rows(10)
    whole, _ = read(tmp_path, "\n".join([HEADER, *rows]) + "\n", name="whole.csv")
    ev, _ = read(tmp_path, "\n".join([header, *(r.replace(",", sep) for r in rows)]) + "\n")
    assert samples(ev) == samples(whole) and len(ev) == 9


@pytest.mark.parametrize("unit", ["[deg/s]", "(deg/s)"])
def test_a_unit_in_a_column_name_is_refused_with_the_mapping_fields(tmp_path, unit):
    header = HEADER.replace("gyro_x", f"gyro_x {unit}").replace("accel_z", "Accel_Z [g]")
    with pytest.raises(SourceError) as exc:
        read(tmp_path, "\n".join([header, *imu_rows(5)]) + "\n")
    msg = str(exc.value)
    assert "missing gyro_x, accel_z" in msg
    assert f"'gyro_x {unit}' looks like gyro_x, 'Accel_Z [g]' looks like accel_z" in msg
    assert "units belong in the mapping (accel_unit, gyro_unit), not in the header" in msg


def test_other_header_mistakes_get_a_hint(tmp_path):
    with pytest.raises(SourceError, match="separated by ','.*not spaces"):
        read(tmp_path, "\n".join([HEADER.replace(",", " "), *imu_rows(3)]) + "\n")
    inc = "t,dtheta_x,dtheta_y,dtheta_z,dvel_x,dvel_y,dvel_z,dt"
    with pytest.raises(SourceError, match="set form = 'increment'"):
        read(tmp_path, inc + "\n1.0,0,0,0,0,0,0,0.01\n", name="inc.csv")
    with pytest.raises(SourceError, match="no header line"):
        read(tmp_path, "# nothing\n\n", name="empty.csv")
    rows = [r.replace(",", ";").replace(".", ",") for r in imu_rows(3)]
    with pytest.raises(SourceError, match=r"line 2: t = '1400000000,00' is not a number: a decimal comma"):
        read(tmp_path, "\n".join([HEADER.replace(",", ";"), *rows]) + "\n", name="semi.csv")
    with pytest.raises(SourceError, match="columns 'Gyro_X', 'GYRO_X' all read as 'gyro_x'"):
        read(tmp_path, "\n".join([HEADER.replace("gyro_x", "Gyro_X,GYRO_X")]) + "\n", name="two.csv")


# --- 6. boot_offset_s = 'auto' not derived ------------------------------------------------------------------
def test_an_unresolved_auto_boot_offset_reports_the_files_own_problem(tmp_path):
    rows = imu_rows(200, t0=1000.0)
    rows[150] = rows[150].replace("0.003", "x")
    (tmp_path / "imu.csv").write_text("\n".join([HEADER, *rows]) + "\n")
    st = {"source": "imu.csv", "kind": "imu", "sensor_id": "i", "axes": "RFU", "time_base": "boot"}
    m = from_dict({"streams": [{**st, "boot_offset_s": "auto"}]})
    with pytest.raises(SourceError, match="line 152: gyro_z = 'x' is not a number"):
        list(stream_events(m.streams[0], tmp_path, m))
    r = checks.run_checks(m, tmp_path)
    assert r.errors and not any("resolved by the checks" in e for e in r.errors), r.errors
    assert len(r.errors) == 1 and "line 152: gyro_z = 'x' is not a number" in r.errors[0], r.errors
    # a file that reads well: the offset not derived is the problem, and said so
    (tmp_path / "imu.csv").write_text("\n".join([HEADER, *imu_rows(20, t0=1000.0)]) + "\n")
    with pytest.raises(SourceError, match="boot_offset_s = 'auto' is resolved by the checks"):
        list(stream_events(m.streams[0], tmp_path, m))


# --- 7. stamps in milliseconds: tick_s ----------------------------------------------------------------------
def test_millisecond_stamps_are_named_and_tick_s_reads_them(tmp_path):
    boot = {"time_base": "boot", "boot_offset_s": T0}
    ms = [
        r.replace(f"{T0 + 0.01 * k:.2f}", f"{123456.789 + 10.0 * k:.3f}", 1)
        for k, r in enumerate(imu_rows(40))
    ]
    text = "\n".join([HEADER, *ms]) + "\n"
    with pytest.raises(
        SourceError, match=r"look like milliseconds: .* 10 apart, a 100 Hz IMU .* set tick_s = 0\.001"
    ):
        read(tmp_path, text, **boot)
    ev, stats = read(tmp_path, text, tick_s=0.001, **boot)
    secs = [
        r.replace(f"{T0 + 0.01 * k:.2f}", f"{123.456789 + 0.01 * k:.6f}", 1)
        for k, r in enumerate(imu_rows(40))
    ]
    ref, _ = read(tmp_path, "\n".join([HEADER, *secs]) + "\n", name="s.csv", **boot)
    assert len(ev) == len(ref) == 39 and stats == {}
    assert all(
        abs(a.t_gps_s - b.t_gps_s) < 1e-6 and abs(a.msg.dt_s - b.msg.dt_s) < 1e-6
        for a, b in zip(ev, ref, strict=True)
    )
    # microseconds of a 200 Hz IMU
    us = [f"{5000 * k},0,0,0,0,0,9.81" for k in range(40)]
    with pytest.raises(SourceError, match=r"look like microseconds: .* a 200 Hz IMU .* tick_s = 1e-06"):
        read(tmp_path, "\n".join([HEADER, *us]) + "\n", name="us.csv", **boot)
    # tick_s scales dt as well (increment form), and must be finite
    inc = ["t,dtheta_x,dtheta_y,dtheta_z,dvel_x,dvel_y,dvel_z,dt"]
    inc += [f"{10 * k},0,0,0,0,0,0.0981,10" for k in range(1, 30)]
    ev, _ = read(tmp_path, "\n".join(inc) + "\n", name="inc.csv", form="increment", tick_s=0.001, **boot)
    assert len(ev) == 29 and all(e.msg.dt_s == pytest.approx(0.01) for e in ev)
    with pytest.raises(MappingError, match="tick_s: Input should be a finite number"):  # refused at load
        read(tmp_path, text, tick_s=float("inf"), **boot)
    # stamps in seconds are not touched by the test (a 10 Hz IMU, a 1 s gap)
    ev, stats = read(tmp_path, "\n".join([HEADER, *imu_rows(40, step=0.1)]) + "\n", name="10hz.csv")
    assert len(ev) == 39


# --- 8. the line of the first skipped sample ----------------------------------------------------------------
def test_skip_counts_carry_the_first_offending_line(tmp_path):
    rows = imu_rows(30)
    rows[10], rows[11] = rows[11], rows[10]  # swapped: line 14 goes backwards
    rows[20] = rows[19]  # repeated: line 23
    ev, stats = read(tmp_path, "\n".join(["# swapped and repeated", HEADER, *rows]) + "\n")
    assert stats["stamp_not_increasing"] == 2 and stats["_first_line_stamp_not_increasing"] == 14
    assert len(ev) == 27


def test_a_skipped_row_does_not_start_the_next_interval(tmp_path):
    """Swapped rows: the row going backwards is skipped and the next interval starts at the last
    sample taken (from the skipped one it overlapped the interval already published: 0.01 s
    integrated twice, and the service refuses an overlapping sample)."""
    rows = imu_rows(30)
    rows[10], rows[11] = rows[11], rows[10]
    ev, _ = read(tmp_path, "\n".join([HEADER, *rows]) + "\n")
    out = samples(ev)
    for (t0, _m0), (t1, m1) in zip(out, out[1:], strict=False):
        assert t1 - m1.dt_s >= t0 - 1e-9, (t0, t1, m1.dt_s)
    assert sum(m.dt_s for _, m in out) == pytest.approx(0.29, abs=1e-6)  # every interval once


def _checked(tmp_path, rows: list[str]):
    (tmp_path / "imu.csv").write_text("\n".join([HEADER, *rows]) + "\n")
    st = {"source": "imu.csv", "kind": "imu", "sensor_id": "i", "axes": "RFU", "time_base": "gps"}
    return checks.run_checks(from_dict({"streams": [st]}), tmp_path)


def test_a_few_repeated_rows_are_a_warning_naming_the_line_many_an_error(tmp_path):
    rows = imu_rows(1000)
    rows[500] = rows[499]  # one logger hiccup: line 502 repeats line 501
    r = _checked(tmp_path, rows)
    assert not any("backwards or repeat" in e for e in r.errors), r.errors
    (w,) = [w for w in r.warnings if "backwards or repeat" in w]
    assert "1 stamp(s)" in w and "line 502" in w and "those samples are skipped" in w, w
    for k in range(100, 400, 10):  # 30 of 1000: the stamps themselves are wrong
        rows[k] = rows[k - 1]
    r = _checked(tmp_path, rows)
    assert any("31 stamp(s) go backwards or repeat (the first at line 102)" in e for e in r.errors), r.errors
