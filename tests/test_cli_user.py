"""Defects a user met on the command line: a missing scenario or a non-positive --duration of
fednav-record, "did you mean" suggestions taken from the wrong level of a configuration, comments
of ``--suggest-config`` contradicting their numbers, subcommands missing from ``fednav-sim --help``."""

from __future__ import annotations

from types import SimpleNamespace

import pytest

from fednav.dashboards.record import main as record_main
from fednav.replay import suggest
from fednav.service.config import ConfigError, ServiceConfig, from_dict
from fednav.service.validation_errors import field_names
from fednav.simulators.__main__ import main as sim_main


def _err(capsys) -> str:
    err = capsys.readouterr().err
    assert "Traceback" not in err
    return err


def test_record_names_a_missing_scenario_in_one_line(tmp_path, capsys):
    assert record_main(["nosuchscenario", "-o", str(tmp_path / "x.rrd")]) == 2
    err = _err(capsys)
    assert err.startswith("fednav-record: no scenario 'nosuchscenario'") and err.count("\n") == 1
    assert not (tmp_path / "x.rrd").exists()


@pytest.mark.parametrize("value", ["-5", "0", "nan", "inf"])
def test_record_and_sim_fleet_refuse_a_non_positive_duration(tmp_path, capsys, value):
    with pytest.raises(SystemExit) as e:
        record_main(["demo_aircraft", "-o", str(tmp_path / "x.rrd"), f"--duration={value}"])
    assert e.value.code == 2 and "argument --duration" in _err(capsys)
    assert not (tmp_path / "x.rrd").exists()
    with pytest.raises(SystemExit) as e:
        sim_main(["fleet", f"--duration={value}"])
    assert e.value.code == 2 and "argument --duration" in _err(capsys)


def test_sim_fleet_names_a_missing_scenario_in_one_line(capsys):
    assert sim_main(["fleet", "--scenario", "nosuchscenario"]) == 2
    err = _err(capsys)
    assert err.startswith("fednav-sim fleet: no scenario 'nosuchscenario'") and err.count("\n") == 1


def _config_error(data: dict) -> str:
    with pytest.raises(ConfigError) as e:
        from_dict(data)
    return str(e.value)


def test_suggestions_come_from_the_fields_at_the_errors_location():
    # ros2.vehicle exists, the top level has vehicles: the refused name itself is never suggested
    assert "  vehicle: unknown field (did you mean 'vehicles'?)" in _config_error({"vehicle": ["v1"]})
    # a replay mapping given as a service configuration: leap_seconds is a field of no level here
    text = _config_error({"vehicle": "v1", "leap_seconds": 18, "streams": [{"kind": "imu"}]})
    assert "  leap_seconds: unknown field\n" in text + "\n"
    assert "did you mean 'leap_seconds'" not in text
    # nested models, a list and a union's tag on the way
    text = _config_error({"pipelines": [{"name": "lc", "kind": "loosely_coupled", "nam": 1, "prefx": 1}]})
    assert "pipelines.0.loosely_coupled.nam: unknown field (did you mean 'name'?)" in text
    assert "pipelines.0.loosely_coupled.prefx: unknown field\n" in text + "\n"  # prefix: top level only
    assert "ros2.domain_idd: unknown field (did you mean 'domain_id'?)" in _config_error(
        {"ros2": {"vehicle": "v1", "domain_idd": 0}}
    )


def test_field_names_are_those_of_the_model_at_the_path():
    top = field_names(ServiceConfig)
    assert "vehicles" in top and "vehicle" not in top and "late_tolerance_s" not in top
    assert "late_tolerance_s" in field_names(ServiceConfig, ["intake"])
    assert "vehicle" in field_names(ServiceConfig, ["ros2"])
    assert "name" in field_names(ServiceConfig, ["pipelines", 0, "loosely_coupled"])
    assert field_names(ServiceConfig, ["no_such_field"]) == set()
    assert field_names(ServiceConfig, ["prefix"]) == set()  # a str: no fields


def test_consumer_overrides_say_whether_the_preset_or_the_measurement_was_kept():
    # the walkthrough's numbers: ARW and both biases below consumer_mems', VRW above
    noise = {"arw_dpsh": 0.129, "vrw_ugpsHz": 281.0}
    bias = {"gyro_up_dph": 71.3, "accel_up_ug": 130.0}
    overrides, why = suggest.consumer_overrides(noise, bias)
    assert overrides == {
        "arw_dpsh": 0.3,
        "vrw_ugpsHz": 351.25,
        "gyro_bias_dph": 500.0,
        "accel_bias_ug": 10000.0,
    }
    assert why["arw_dpsh"] == "the preset's: measured 0.129 x 1.25 is below it"
    assert why["vrw_ugpsHz"] == "measured 281 x 1.25 (above the preset's 150.0)"
    assert why["gyro_bias_dph"] == "the preset's: measured 71.3 is below it"
    s = _suggestion([0.5, 0.5, 1.0], [0.49, 0.55, 1.04], overrides, imu_override_why=why)
    text = suggest.render_toml(SimpleNamespace(prefix="fednav", vehicle="v1"), s)
    assert "arw_dpsh = 0.3   # the preset's: measured 0.129 x 1.25 is below it" in text
    assert "measured x 1.25 (noisier than the preset)" not in text
    overrides, why = suggest.consumer_overrides(noise, {"gyro_up_dph": 1600.0, "accel_up_ug": 130.0})
    assert overrides["gyro_bias_dph"] == 1600.0
    assert why["gyro_bias_dph"] == "measured 1.6e+03 (above the preset's 500.0)"


def _suggestion(sigma, white, overrides=None, **kw) -> suggest.Suggestion:
    ratio = [s / w for s, w in zip(sigma, white, strict=True)]
    fixes = {
        "stream": "rx",
        "sigma_enu_m": sigma,
        "origin": "GST",
        "white_enu_m": white,
        "sigma_over_white": ratio,
    }
    correlated = {"sigma_enu_m": [0.15, 0.15, 0.3], "correlation_time_s": 30.0}
    noise = {"method": "m", "arw_dpsh": 0.1, "vrw_ugpsHz": 100.0}
    return suggest.Suggestion("consumer_mems", overrides or {}, noise, None, [], fixes, correlated, **kw)


@pytest.mark.parametrize(
    "sigma, white, expected",
    [
        ([0.5, 0.5, 1.0], [0.49, 0.55, 1.09], ("does not exceed their white scatter on N/U", "on E it does")),
        (
            [0.5, 0.5, 1.0],
            [0.52, 0.55, 1.09],
            ("does not exceed their white scatter on E/N/U", "all the same"),
        ),
        ([0.6, 0.6, 1.2], [0.5, 0.5, 1.0], ("the fixes' sigma exceeds their white scatter",)),
    ],
)
def test_the_correlated_part_comment_matches_sigma_against_scatter(sigma, white, expected):
    text = suggest.render_toml(SimpleNamespace(prefix="fednav", vehicle="v1"), _suggestion(sigma, white))
    assert all(e in text for e in expected), text
    if len(expected) > 1:
        assert "sigma exceeds their white scatter" not in text


def test_sim_help_lists_every_subcommand(capsys):
    with pytest.raises(SystemExit) as e:
        sim_main(["--help"])
    out = capsys.readouterr().out
    assert e.value.code == 0
    assert "{run,eval,fleet,eval-rinex,rinex2raw}" in out
    for cmd in ("run", "eval", "fleet", "eval-rinex", "rinex2raw"):
        line = next(x for x in out.splitlines() if x.strip().startswith(cmd + " "))
        assert len(line.split()) > 1, line  # a description beside it
    with pytest.raises(SystemExit):  # still their own parsers
        sim_main(["eval-rinex", "--help"])
    assert "--no-exclusion" in capsys.readouterr().out


def test_sim_prints_every_threads_stack_on_sigusr1_and_stops_on_sigint_even_if_started_ignoring_it():
    """``fednav-sim`` answers SIGUSR1 with every thread's stack on stderr (faulthandler) and goes on;
    SIGINT then stops it (130, no traceback) while it waits for its router, even when it was started
    with SIGINT ignored, as a process started in the background by a non-interactive shell (a CI
    runner, ``cmd &`` in a script) is: Python leaves an inherited SIG_IGN alone, and a fresh-clone CI
    run's simulator so ran on to its 60 s match timeout (service/stop_signals.py)."""
    import signal
    import subprocess
    import sys
    import time

    from fednav.simulators.processes import Proc, free_port

    sim = [sys.executable, "-m", "fednav.simulators", "fleet", "--vehicles", "1", "--duration", "5"]
    sim += ["--connect", f"tcp/127.0.0.1:{free_port()}", "--match-timeout", "60"]
    gen = Proc(["sh", "-c", 'trap "" INT; exec "$@"', "sh"] + sim, "fleet")  # SIGINT ignored, inherited
    try:
        assert gen.wait_for("variants built", timeout=60), gen.output()  # (no service: it waits for one)
        gen.signal(signal.SIGUSR1)
        assert gen.wait_for("most recent call first", timeout=20), gen.output()
        assert gen.p.poll() is None, gen.output()  # the dump does not stop it
        time.sleep(0.5)  # (inside its wait for the router)
    finally:
        gen.signal(signal.SIGINT)
        t0 = time.monotonic()
        try:
            rc = gen.wait(timeout=30)
        except subprocess.TimeoutExpired:
            gen.signal(signal.SIGUSR1)
            time.sleep(2.0)
            gen.kill()
            rc = None
    assert rc == 130, (rc, gen.output())
    assert time.monotonic() - t0 < 10.0, gen.output()  # not the 60 s match timeout
    assert "interrupted" in gen.output() and "Traceback" not in gen.output(), gen.output()


def test_replay_stops_on_sigint_even_if_started_ignoring_it(tmp_path):
    """``fednav-replay`` waiting for its router, started with SIGINT ignored (as a background job
    of a non-interactive shell is): SIGINT stops it at once with 130 (service/stop_signals.py)."""
    import signal
    import subprocess
    import sys
    import time

    from fednav.simulators.processes import Proc, free_port

    from . import replay_files as rf

    mapping = rf.write_all(tmp_path / "logs", rf.simulate_drive(tmp_path, duration_s=32.0), only=("ubx",))
    args = [sys.executable, "-m", "fednav.replay", str(mapping["ubx"])]
    args += ["--connect", f"tcp/127.0.0.1:{free_port()}", "--match-timeout", "60"]
    p = Proc(["sh", "-c", 'trap "" INT; exec "$@"', "sh"] + args, "fednav-replay")
    time.sleep(3.0)  # (reading the log, then waiting for the router that is not there)
    assert p.p.poll() is None, p.output()
    p.signal(signal.SIGINT)
    try:
        rc = p.wait(timeout=20)
    except subprocess.TimeoutExpired:
        p.kill()
        rc = None
    assert rc == 130 and "interrupted" in p.output() and "Traceback" not in p.output(), (rc, p.output())


def test_stop_on_sigint_undoes_an_inherited_ignore():
    """The helper itself, in a child started with SIGINT ignored: afterwards SIGINT raises
    KeyboardInterrupt."""
    import subprocess
    import sys

    code = (
        "import os, signal\n"
        "assert signal.getsignal(signal.SIGINT) == signal.SIG_IGN\n"
        "from fednav.service.stop_signals import stop_on_sigint\n"
        "assert stop_on_sigint() is True\n"
        "try:\n"
        "    os.kill(os.getpid(), signal.SIGINT)\n"
        "    import time; time.sleep(5)\n"
        "except KeyboardInterrupt:\n"
        "    print('interrupted')\n"
    )
    out = subprocess.run(
        ["sh", "-c", 'trap "" INT; exec "$@"', "sh", sys.executable, "-c", code],
        capture_output=True,
        text=True,
        timeout=60,
    )
    assert out.returncode == 0 and out.stdout.strip() == "interrupted", (out.stdout, out.stderr)
