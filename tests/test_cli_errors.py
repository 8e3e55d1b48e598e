"""Mistakes on the command line get one line (or one line per field) naming the problem and the
closest valid name, with exit code 2 and no traceback (in-process calls of the entry points)."""

from __future__ import annotations

import pytest

from fednav.service.__main__ import main as service_main
from fednav.service.__main__ import zenoh_error_text
from fednav.simulators.__main__ import main as sim_main


def _err(capsys) -> str:
    out = capsys.readouterr()
    assert "Traceback" not in out.err and "errors.pydantic.dev" not in out.err
    return out.err


@pytest.mark.parametrize(
    "args, expected",
    [
        (["--listen", "localhost:7447"], "expected PROTOCOL/HOST:PORT, e.g. tcp/localhost:7447"),
        (["--connect", "tcp:127.0.0.1"], "e.g. tcp/127.0.0.1:7447"),
        (["--listen", "tcp/127.0.0.1:99999"], "a port 1-65535"),
        (["--zenoh-config", "/nonexistent.json5"], "--zenoh-config /nonexistent.json5: no such file"),
    ],
)
def test_service_endpoint_and_file_mistakes(capsys, args, expected):
    assert service_main(args) == 2
    err = _err(capsys)
    assert expected in err and err.count("\n") == 1


def test_service_config_typos_suggest_the_field(tmp_path, capsys):
    bad = tmp_path / "c.toml"
    bad.write_text('[[pipelines]]\nname = "lc"\nkind = "loosly_coupled"\n[intake]\nlate_tolerance = 1\n')
    assert service_main(["--config", str(bad)]) == 2
    err = _err(capsys)
    assert "intake.late_tolerance: unknown field (did you mean 'late_tolerance_s'?)" in err
    assert "unknown kind 'loosly_coupled' (did you mean 'loosely_coupled'?)" in err


def test_sim_scenario_and_endpoint_mistakes(tmp_path, capsys):
    assert sim_main(["eval", "demo_aircrft"]) == 2
    assert "no scenario 'demo_aircrft' (did you mean 'demo_aircraft'?)" in _err(capsys)
    assert sim_main(["run", "demo_aircraft", "--connect", "localhost:7447"]) == 2
    assert "invalid Zenoh endpoint 'localhost:7447'" in _err(capsys)
    bad = tmp_path / "s.toml"
    bad.write_text('name = "x"\nduration_s = 10\n[imuu]\nrate_hz = 100\n')
    assert sim_main(["eval", str(bad)]) == 2
    assert "imuu: unknown field (did you mean 'imu'?)" in _err(capsys)


def test_version_and_help_with_examples(capsys):
    with pytest.raises(SystemExit) as e:
        service_main(["--version"])
    assert e.value.code == 0 and capsys.readouterr().out.startswith("fednav-service ")
    with pytest.raises(SystemExit):
        sim_main(["eval", "--help"])
    out = capsys.readouterr().out
    assert "examples:" in out and "--runs" in out and "default 1" in out


def test_zenoh_errors_lose_their_rust_source_paths():
    exc = Exception(
        "Can not create a new TCP listener bound to tcp/127.0.0.1:1: [Address already in use (os error 98) "
        "at /root/.cargo/git/checkouts/zenoh/io/tcp.rs:61.] at /root/.cargo/git/zenoh/unicast.rs:338."
    )
    assert zenoh_error_text(exc) == (
        "Can not create a new TCP listener bound to tcp/127.0.0.1:1: [Address already in use (os error 98)]"
    )


def test_ros2_publisher_refuses_a_vehicle_name_that_is_no_key_chunk(capsys):
    from fednav.simulators.ros2_publish import main as ros2_main

    from .scenario_utils import SCENARIOS

    assert ros2_main([str(SCENARIOS / "demo_aircraft.toml"), "--vehicle", "a/b"]) == 2
    err = _err(capsys)
    assert "--vehicle 'a/b' is not a valid vehicle name" in err and err.count("\n") == 1


@pytest.mark.parametrize("value", ["nan", "inf", "-1", "0", "soon"])
def test_publishers_refuse_a_wait_that_is_no_positive_finite_time(capsys, value):
    """``--match-timeout`` of fednav-sim fleet and fednav-replay: NaN would wait for ever (every
    comparison with the deadline false), 0 or less not at all."""
    with pytest.raises(SystemExit) as exc:
        sim_main(["fleet", "--match-timeout", value])
    assert exc.value.code == 2
    assert "argument --match-timeout" in _err(capsys)
    from fednav.replay.__main__ import main as replay_main

    with pytest.raises(SystemExit) as exc:
        replay_main(["mapping.toml", "--match-timeout", value])
    assert exc.value.code == 2
    assert "argument --match-timeout" in _err(capsys)


def test_command_help_has_no_restructuredtext_quotes():
    import subprocess
    import sys

    for mod in ("fednav.simulators.fleet", "fednav.simulators.demo", "fednav.dashboards.record"):
        out = subprocess.run(
            [sys.executable, "-m", mod, "--help"], capture_output=True, text=True, timeout=60
        )
        assert out.returncode == 0 and "usage:" in out.stdout, (mod, out.stderr)
        assert "``" not in out.stdout, (mod, out.stdout)
