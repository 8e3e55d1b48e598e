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


def test_sim_prints_every_threads_stack_on_sigusr1():
    """``fednav-sim`` answers SIGUSR1 with every thread's stack on stderr (faulthandler) and goes on:
    how a stuck simulator is looked into (a fleet generator that did not stop on SIGINT on a loaded
    CI run, tests/test_shards.py)."""
    import signal
    import subprocess
    import sys
    import time

    from fednav.simulators.processes import Proc, free_port

    gen = Proc(
        [sys.executable, "-m", "fednav.simulators", "fleet", "--vehicles", "1", "--duration", "5"]
        + ["--connect", f"tcp/127.0.0.1:{free_port()}", "--match-timeout", "60"],
        "fleet",
    )
    try:
        assert gen.wait_for("variants built", timeout=60), gen.output()  # (no service: it waits for one)
        gen.signal(signal.SIGUSR1)
        assert gen.wait_for("most recent call first", timeout=20), gen.output()
        assert gen.p.poll() is None, gen.output()  # the dump does not stop it
    finally:
        gen.signal(signal.SIGINT)
        try:
            rc = gen.wait(timeout=60)
        except subprocess.TimeoutExpired:
            gen.signal(signal.SIGUSR1)
            time.sleep(2.0)
            gen.signal(signal.SIGKILL)
            gen.wait(timeout=30)
            rc = None
    if rc is None:  # a known open defect, kept visible (closing note of 2026-12-01, thirty-first session)
        pytest.xfail(f"fednav-sim fleet waiting for its router did not stop on SIGINT:\n{gen.output()}")
    assert rc == 130 and "Traceback" not in gen.output(), (rc, gen.output())
