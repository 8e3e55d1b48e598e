"""fednav-inspect on a real run WITHOUT truth (issue 24): per pipeline the status timeline,
sigma levels, gate refusals against their expected rate, the consistency of the claimed sigma
from the recording alone (update jumps x fix residuals), and one verdict; the final status is the
last recorded and the Health after the input stopped is named.

Recordings: a car drive that starts in motion, replayed from an NMEA + IMU CSV log written with
pynmea2 / csv, recorded in-process through the service's own per-vehicle loop and Rerun sink
(tests/replay_files.record_replay), once with the fixes' sigmas as they are, once declared 5x
too small, once 5x too large.
"""

from __future__ import annotations

import re

import pytest

from fednav.dashboards import inspect
from fednav.service.config import from_dict
from fednav.service.messages import Health, PipelineHealth, Solution
from fednav.service.transport.rerun_sink import RerunSink

from . import replay_files as rf

CFG = {
    "vehicles": ["*"],
    "imu": {"grade": "consumer_mems"},
    "init": {"min_speed_mps": 3.0},
    "pipelines": [{"name": "lc", "kind": "loosely_coupled"}],
}


@pytest.fixture(scope="module")
def drive(tmp_path_factory):
    tmp = tmp_path_factory.mktemp("car")
    return rf.trim(rf.simulate_car_drive(tmp, "consumer_mems", 62.5, pos_std_m=0.5), 12.5)


@pytest.fixture(scope="module")
def recordings(drive, tmp_path_factory):
    """{scale: summary} for fix sigmas declared as they are (1), 5x too small (0.2), 5x too large."""
    tmp = tmp_path_factory.mktemp("rec")
    out = {}
    for scale in (1.0, 0.2, 5.0):
        fixes = [
            f.model_copy(update={"pos_std_enu_m": tuple(x * scale for x in f.pos_std_enu_m)})
            for f in drive.fixes
        ]
        p = rf.write_all(tmp / f"logs_{scale}", rf.Drive(drive.imu, fixes, drive.truth), only=("nmea_csv",))
        _speed_sigma(p["nmea_csv"], 1.0)  # the positions' sigmas are the ones mis-declared here
        rrd = tmp / f"run_{scale}.rrd"
        rf.record_replay(p["nmea_csv"], from_dict(CFG), rrd)
        out[scale] = (rrd, inspect.inspect_rrd(rrd))
    return out


def _speed_sigma(mapping, scale: float) -> None:
    """NMEA carries no speed sigma: the mapping declares the simulated one (times ``scale``, like
    the positions'); the replay's default (0.15 m/s for a single fix, 3x the simulated 0.05) is
    what inspect's innovations call underconfident in speed."""
    text = mapping.read_text()
    sig = f"{0.05 * scale:g}, {0.05 * scale:g}, {0.1 * scale:g}"
    mapping.write_text(text.replace('sensor_id = "rx"', f'sensor_id = "rx"\nvel_std_mps = [{sig}]'))


def test_a_consistent_run_is_called_consistent(recordings):
    rrd, s = recordings[1.0]
    p = s["pipelines"]["lc"]
    assert p["error_epochs"] == 0  # no truth in a replay
    assert p["verdict"].startswith("consistent"), p["verdict"]
    (fr,) = p["fix_residuals"].values()
    for axis in ("east", "north"):
        assert 0.75 < fr["axes"][axis]["factor"] < 1.3, fr
    assert p["status"]["reinitialisations"] == 0 and p["status"]["changes"][-1]["status"] == "aided"
    assert p["sigma"]["pos_e_m"]["median"] < 0.3 and p["solution_gaps"] == []
    assert s["inputs"]["nmea_csv"]["rx"]["fixes"] == 500


def test_sigmas_declared_5x_too_small_are_overconfident(recordings):
    _, s = recordings[0.2]
    p = s["pipelines"]["lc"]
    assert p["verdict"].startswith("overconfident in"), p["verdict"]
    (fr,) = p["fix_residuals"].values()
    assert all(a["factor"] > 1.8 for a in fr["axes"].values()), fr  # read low: the gate drops the worst
    gate = p["screening"]["gnss_fix/pos_e"]
    assert gate["tests"] == 500 and gate["rate"] > 0.1 and gate["expected_rate"] < 1e-6
    assert 3.0 < gate["implied_factor"] < 8.0, gate


def test_sigmas_declared_5x_too_large_are_underconfident(recordings):
    _, s = recordings[5.0]
    p = s["pipelines"]["lc"]
    # judged on the innovations' NIS where recorded (the fix residuals then only shown)
    verdict = p["verdict"]
    m = re.match(r"underconfident in (east|north) by (\d+\.\d)x \((fix residuals|innovations) \(", verdict)
    assert m and 3.5 < float(m.group(2)) < 7.0, verdict
    assert p["screening"] == {}  # nothing refused: the gate cannot show underconfidence


def test_correlated_fixes_fused_as_independent_are_named(drive, tmp_path):
    """Real receivers' errors are slow: fused as independent, the filter follows them, its innovations
    look small (ratio below 1) while its error against the truth is many times its sigma. The
    innovations' whiteness says so; checked here against the truth the recording does not hold."""
    tmp = tmp_path / "gm"
    tmp.mkdir()
    d = rf.trim(rf.simulate_car_drive(tmp, "consumer_mems", 62.5, pos_std_m=0.15, gm_std_m=0.3), 12.5)
    p = rf.write_all(tmp / "logs", d, only=("nmea_csv",))["nmea_csv"]
    rrd = tmp / "run.rrd"
    rf.record_replay(p, from_dict(CFG), rrd)
    s = inspect.inspect_rrd(rrd, from_dict(CFG))
    lc = s["pipelines"]["lc"]
    assert lc["verdict"].startswith("fix innovations correlated in time (lag-1 autocorrelation east 0."), lc[
        "verdict"
    ]
    assert "set gnss_correlated_error" in lc["verdict"]
    (fr,) = lc["fix_residuals"].values()
    assert all(a["lag1"] > 0.2 and a["factor"] < 1.0 for a in fr["axes"].values()), fr
    truth = rf.evaluate_config(d, from_dict(dict(CFG, vehicles=["v1"])))
    assert truth["h_err_over_sigma"] > 3.0, truth  # against the truth: overconfident indeed


def test_the_text_says_it(recordings, capsys):
    rrd, _ = recordings[5.0]
    assert inspect.main([str(rrd)]) == 0
    text = capsys.readouterr().out
    assert re.search(r"pipeline lc: 50\d solutions, final status aided \(the last recorded\), no truth", text)
    assert "    status: unaided at +0.0 s -> aided at +" in text
    assert "    1-sigma (median once aided): position E/N/U " in text
    assert re.search(
        r"    fixes rx: real/claimed error \(update jumps x fix residuals, \d+ fixes\): east 0\.\d\d", text
    )
    assert "    verdict: underconfident in" in text
    assert "inputs nmea_csv: 500 GNSS fixes from rx" in text


def test_correlated_error_states_are_not_judged_by_fix_residuals(recordings, drive, tmp_path, monkeypatch):
    """With correlated-error states the fix residuals cannot judge the claimed sigma: the
    recording's innovations decide (tests/test_inspect_nis.py); a recording without them (an older
    service) is not decidable."""
    rrd, _ = recordings[1.0]
    cfg = dict(
        CFG, pipelines=[{**CFG["pipelines"][0], "gnss_correlated_error": {"sigma_enu_m": [0.3, 0.3, 0.6]}}]
    )
    s = inspect.inspect_rrd(rrd, from_dict(cfg))
    p = s["pipelines"]["lc"]
    assert p["fix_residuals_apply"] is False
    assert p["innovations"] and not p["verdict"].startswith("not decidable"), p["verdict"]
    p = rf.write_all(tmp_path / "logs", drive, only=("nmea_csv",))
    _speed_sigma(p["nmea_csv"], 1.0)
    monkeypatch.setattr(RerunSink, "log_innovations", lambda self, *a, **k: None)
    old = tmp_path / "without_innovations.rrd"
    rf.record_replay(p["nmea_csv"], from_dict(cfg), old)
    v = inspect.inspect_rrd(old, from_dict(cfg))["pipelines"]["lc"]["verdict"]
    assert v.startswith("not decidable from this recording (gnss_correlated_error"), v
    path = tmp_path / "svc.toml"
    path.write_text('[[pipelines]]\nname = "lc"\nkind = "loosely_coupled"\n')
    assert inspect.main([str(rrd), "--config", str(path), "--json"]) == 0
    assert inspect.main([str(rrd), "--config", str(tmp_path / "missing.toml")]) == 2


T0 = 1_400_000_000.0


def _sol(t: float, status: str) -> Solution:
    return Solution(
        t=t,
        pipeline="lc",
        lat_deg=30.0,
        lon_deg=114.0,
        height_m=20.0,
        vel_enu_mps=(0.0, 10.0, 0.0),
        rpy_deg=(0.0, 0.0, 0.0),
        pos_std_enu_m=(0.2, 0.2, 0.4),
        vel_std_enu_mps=(0.05, 0.05, 0.1),
        rpy_std_deg=(0.1, 0.1, 0.5),
        status=status,
    )


def _health(t: float, received: int, status: str) -> Health:
    return Health(
        t=t,
        uptime_s=1.0,
        received=received,
        accepted=received,
        rejected={},
        dropped_overload=0,
        queue_depth=0,
        latency_ms={"p50": 0.1, "p99": 0.2, "max": 0.3},
        pipelines={"lc": PipelineHealth(status=status, last_t=t, updates=10)},
    )


@pytest.mark.parametrize("after", [0, 1, 4])
def test_final_status_is_the_last_recorded_and_the_stopped_input_is_named(tmp_path, capsys, after):
    """The service's Health keeps coming once a second after the input stops (same sensor time); from
    the third report (2 s without input) it says coasting: inspect says so beside the last recorded
    status (aided), instead of contradicting it."""
    path = tmp_path / "stop.rrd"
    with RerunSink(path, recording_id="stop") as sink:
        sink.log_solution("car", _sol(T0, "initialising"))
        for k in range(1, 30):
            sink.log_solution("car", _sol(T0 + 0.1 * k, "aided"))
            if k % 10 == 0:
                sink.log_health("car", _health(T0 + 0.1 * k, 10 * k, "aided"))
        last = T0 + 2.9
        sink.log_health("car", _health(last, 300, "aided"))
        for i in range(after):  # reports after the input stopped: wall time passes, sensor time does not
            sink.log_health("car", _health(last, 300, "aided" if i == 0 else "coasting"))
    s = inspect.inspect_rrd(path)
    p = s["pipelines"]["lc"]
    assert p["final_status"] == "aided"
    assert [c["status"] for c in p["status"]["changes"]] == ["initialising", "aided"]
    inspect.main([str(path)])
    text = capsys.readouterr().out
    if after >= inspect.STOPPED_HEALTH_ROWS - 1:
        assert s["input_stopped"]["car"]["health_reports_after"] == after
        assert p["health_final_status"] == "coasting"
        assert re.search(
            r"final status aided \(the last recorded\); input stopped at \+2\.9 s: the service's "
            rf"{after} Health reports after it said coasting \(no input for 2 s of wall time\)",
            text,
        ), text
    else:
        assert s["input_stopped"] == {} and "health_final_status" not in p
        assert "final status aided (the last recorded), no truth" in text


def test_two_runs_over_the_same_times_in_one_recording_are_named(tmp_path, capsys):
    """The same log replayed twice into one running service: its second run's solutions land at the
    times of the first's, and the reader interleaves them; the summary says so instead of showing
    doubled counts as one run."""
    path = tmp_path / "twice.rrd"
    with RerunSink(path, recording_id="twice") as sink:
        for _run in range(2):
            sink.log_solution("car", _sol(T0, "initialising"))
            for k in range(1, 30):
                sink.log_solution("car", _sol(T0 + 0.1 * k, "aided"))
    s = inspect.inspect_rrd(path)
    assert s["pipelines"]["lc"]["repeated_times"] == 30
    inspect.main([str(path)])
    assert "WARNING: 30 solutions share their time with an earlier one" in capsys.readouterr().out
    once = tmp_path / "once.rrd"
    with RerunSink(once, recording_id="once") as sink:
        for k in range(30):
            sink.log_solution("car", _sol(T0 + 0.1 * k, "aided"))
    assert inspect.inspect_rrd(once)["pipelines"]["lc"]["repeated_times"] == 0
