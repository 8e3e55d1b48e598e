"""A first-time user's mapping mistakes: a typo in ``rinex_options``, a log whose extension names no
format (``receiver.log``, ``drive.csv.gz``), a gzip file renamed ``.csv``. Each is a plain message
naming the stream, never a traceback."""

from __future__ import annotations

import gzip
import inspect
import typing

import pytest

from fednav.replay import mapping
from fednav.replay.__main__ import main as replay_main
from fednav.replay.mapping import MappingError, from_dict
from fednav.replay.sources import stream_events

NMEA = "$GPGGA,100000.00,3031.698,N,11421.342,E,1,08,0.9,25.0,M,12.5,M,,*4C\n"


def _rinex(options: dict) -> dict:
    return {
        "rinex_nav": ["brdc.19n"],
        "streams": [{"source": "site.19o", "kind": "gnss_raw", "sensor_id": "rx", "rinex_options": options}],
    }


def _fix(source: str, **extra) -> dict:
    return {
        "streams": [{"source": source, "kind": "gnss_fix", "sensor_id": "rx", "time_base": "utc", **extra}]
    }


def _imu(source: str) -> dict:
    return {"streams": [{"source": source, "kind": "imu", "sensor_id": "imu", "time_base": "gps"}]}


# --- 1. rinex_options ----------------------------------------------------------------------------
def test_a_typo_in_rinex_options_is_named_with_the_options(tmp_path, capsys):
    with pytest.raises(MappingError) as exc:
        from_dict(_rinex({"sytems": ["G"]}), "m.toml")
    msg = str(exc.value)
    assert "streams.0.rinex_options:" in msg and "unknown option 'sytems' (did you mean 'systems'?)" in msg
    assert "systems, pseudorange_sigma_m, range_rate_sigma_mps, start_gps_s, stop_gps_s, max_age_s" in msg
    # from the command line: the mapping error, exit 1, no traceback (was a TypeError from the reader)
    toml = tmp_path / "rinex.toml"
    toml.write_text(
        'rinex_nav = ["brdc.19n"]\n[[streams]]\nsource = "site.19o"\nkind = "gnss_raw"\nsensor_id = "rx"\n'
        'rinex_options = { sytems = ["G"] }\n'
    )
    assert replay_main([str(toml), "--check"]) == 1
    err = capsys.readouterr().err
    assert "did you mean 'systems'?" in err and "Traceback" not in err


@pytest.mark.parametrize(
    "options, where",
    [
        ({"systems": "G"}, "rinex_options.systems"),  # a string, not a list
        ({"systems": ["R"]}, "rinex_options.systems.0"),  # GLONASS: not converted
        ({"pseudorange_sigma_m": -1.0}, "rinex_options.pseudorange_sigma_m"),
        ({"max_age_s": "a day"}, "rinex_options.max_age_s"),
    ],
)
def test_rinex_option_values_are_checked(options, where):
    with pytest.raises(MappingError, match=f"streams.0.{where}:"):
        from_dict(_rinex(options))


def test_rinex_options_pass_only_what_is_set(tmp_path, monkeypatch):
    import sys
    import types

    calls = []

    def iter_gnss_raw(obs_path, nav_paths, **options):
        calls.append(options)
        return iter(())

    fake = types.ModuleType("fednav.simulators.gnss.rinex_raw")
    fake.iter_gnss_raw = iter_gnss_raw
    monkeypatch.setitem(sys.modules, "fednav.simulators.gnss.rinex_raw", fake)
    m = from_dict(_rinex({"systems": ["G"], "pseudorange_sigma_m": "3"}))  # "3": read as 3.0
    assert list(stream_events(m.streams[0], tmp_path, m)) == []
    assert calls == [{"systems": ["G"], "pseudorange_sigma_m": 3.0}]
    # a copy of the mapping (with_stream dumps and validates again) passes the same
    m2 = mapping.with_stream(m, 0, time_offset_s=1.0)
    assert m2.streams[0].rinex_options.kwargs() == {"systems": ["G"], "pseudorange_sigma_m": 3.0}


def test_rinex_options_are_iter_gnss_raws_keyword_arguments():
    rinex_raw = pytest.importorskip("fednav.simulators.gnss.rinex_raw")
    params = inspect.signature(rinex_raw.iter_gnss_raw).parameters
    keywords = {n for n, p in params.items() if p.kind is inspect.Parameter.KEYWORD_ONLY} - {"stats"}
    assert set(mapping.RinexOptions.model_fields) == keywords
    systems = mapping.RinexOptions.model_fields["systems"].annotation  # list[Literal[...]] | None
    list_of_letters = typing.get_args(systems)[0]
    assert set(typing.get_args(typing.get_args(list_of_letters)[0])) == set(rinex_raw.FREQ_HZ)


# --- 2. formats from the file name -------------------------------------------------------------
@pytest.mark.parametrize("name", ["receiver.log", "gnss.txt", "drive.dat"])
def test_an_unknown_extension_asks_for_the_format(name):
    with pytest.raises(MappingError) as exc:
        from_dict(_fix(name), "m.toml")
    msg = str(exc.value)
    assert f"streams.0: Value error, cannot tell the format of {name} from its extension" in msg
    assert "set format = one of 'ros', 'nmea', 'ubx', 'csv', 'rinex'" in msg and "topic" not in msg
    assert from_dict(_fix(name, format="nmea")).streams[0].resolved_format() == "nmea"


@pytest.mark.parametrize(
    "data", [_fix("drive.nmea.gz"), _fix("drive.nmea.gz", format="nmea"), _imu("drive.csv.gz")]
)
def test_a_gzip_file_is_told_to_be_decompressed(data):
    source = data["streams"][0]["source"]
    with pytest.raises(MappingError, match=rf"compressed with gzip: decompress it first \(gunzip {source}\)"):
        from_dict(data)


def test_a_gzip_navigation_file_is_told_to_be_decompressed():
    with pytest.raises(MappingError, match=r"rinex_nav: Value error, brdc.19n.gz is compressed with gzip"):
        from_dict({**_rinex({}), "rinex_nav": ["brdc.19n.gz"]})


@pytest.mark.parametrize(
    "source, fmt",
    [
        ("bag/bag.db3", "ros"),
        ("drive.MCAP", "ros"),
        ("drive.bag", "ros"),
        ("my_drive", "ros"),
        ("my_drive/", "ros"),
        ("site.19o", "rinex"),
        ("site.rnx", "rinex"),
        ("Drive.NMEA", "nmea"),
        ("imu.csv", "csv"),
        ("rx.ubx", "ubx"),
    ],
)
def test_formats_recognised_from_the_name(source, fmt):
    kind = {"ros": "imu", "rinex": "gnss_raw", "nmea": "gnss_fix", "csv": "imu", "ubx": "gnss_fix"}[fmt]
    st = {"source": source, "kind": kind, "sensor_id": "s", "topic": "/t" if fmt == "ros" else None}
    if fmt == "nmea":
        st["time_base"] = "utc"
    assert from_dict({"streams": [st]}).streams[0].resolved_format() == fmt


def test_a_name_without_extension_is_a_bag_directory_and_says_so(tmp_path):
    with pytest.raises(
        MappingError, match="needs 'topic' \\(receiver has no extension: it is read as a ROS 2"
    ):
        from_dict(_fix("receiver"))
    # with a topic, the file itself is looked at: an NMEA file is named as one
    (tmp_path / "receiver").write_text(NMEA)
    m = from_dict(_fix("receiver", topic="/fix"))
    with pytest.raises(ValueError, match="not a ROS bag .*NMEA text .*set format = 'nmea'"):
        list(stream_events(m.streams[0], tmp_path, m))
    (tmp_path / "ubx").write_bytes(b"\xb5\x62\x01\x07")
    m = from_dict(_fix("ubx", topic="/fix"))
    with pytest.raises(ValueError, match="not a ROS bag .*u-blox UBX .*set format = 'ubx'"):
        list(stream_events(m.streams[0], tmp_path, m))
    (tmp_path / "notabag").mkdir()
    m = from_dict(_fix("notabag", topic="/fix"))
    with pytest.raises(ValueError, match="a directory without metadata.yaml"):
        list(stream_events(m.streams[0], tmp_path, m))


def test_a_gzip_file_renamed_csv_is_named_as_gzip(tmp_path):
    text = "t,gyro_x,gyro_y,gyro_z,accel_x,accel_y,accel_z\n" + "1.4e9,0,0,0,0,0,9.81\n" * 10
    (tmp_path / "imu.csv").write_bytes(gzip.compress(text.encode()))
    m = from_dict(_imu("imu.csv"))
    with pytest.raises(
        ValueError, match=r"imu.csv: compressed with gzip \(it starts with gzip's bytes 1f 8b\)"
    ):
        list(stream_events(m.streams[0], tmp_path, m))
    (tmp_path / "latin.csv").write_bytes(text.replace("t,", "t\xe9,", 1).encode("latin-1"))
    m = from_dict(_imu("latin.csv"))
    with pytest.raises(ValueError, match="not UTF-8 text"):  # other bytes: as before
        list(stream_events(m.streams[0], tmp_path, m))
