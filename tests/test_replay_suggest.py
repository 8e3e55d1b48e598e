"""``fednav-replay MAPPING --suggest-config OUT.toml`` (replay/suggest.py) on simulated car drives
that START IN MOTION (the log begins inside a turn), one per IMU grade (the imu_grades presets'
numbers, drawn per run), 10 Hz fixes with a white part 0.15 m and a 30 s Gauss-Markov part 0.3 m
(vertical 2x), the fixes' sigma their total: the right grade is picked, the file loads
(``fednav.service.config.load``) and carries where each number came from; the correlated-error
parameters come out near the simulated ones; the suggested configuration is consistent on the
drive where the navigation-grade default is not.
"""

from __future__ import annotations

import math
import re

import numpy as np
import pytest

from fednav.replay import checks, mapping, suggest
from fednav.replay.__main__ import main as replay_main
from fednav.service.config import from_dict, load

from . import replay_files as rf

START_S = 12.5  # the log starts inside the first turn
CASE = {"consumer_mems": "nmea_csv", "industrial_mems": "ros2", "tactical": "mcap"}


def _drive(tmp, grade: str, stop_s: float = 0.0, duration_s: float = 72.5):
    d = rf.simulate_car_drive(tmp, grade, duration_s=duration_s, pos_std_m=0.15, gm_std_m=0.3, stop_s=stop_s)
    return d if stop_s else rf.trim(d, START_S)


@pytest.mark.parametrize("grade", ["consumer_mems", "industrial_mems", "tactical"])
def test_suggest_config_picks_the_grade_and_writes_a_config_that_loads(grade, tmp_path, capsys):
    drive = _drive(tmp_path, grade)
    case = CASE[grade]
    p = rf.write_all(tmp_path / "logs", drive, only=(case,))[case]
    out = tmp_path / "suggested.toml"
    assert replay_main([str(p), "--suggest-config", str(out)]) == 0
    printed = capsys.readouterr().out
    assert f"grade: {grade}" in printed and f"wrote {out}" in printed
    cfg = load(out)
    assert cfg.imu.grade == grade and cfg.vehicles == [case] and cfg.init.mode == "auto"
    (pipe,) = cfg.pipelines
    assert pipe.kind == "loosely_coupled" and pipe.gnss_lever_arm_b_m == (0.0, 0.0, 0.0)
    # the correlated part: sqrt(total^2 - white^2) of the simulated 0.15 (white) and 0.3 (GM) m
    ce = pipe.gnss_correlated_error
    assert ce is not None and ce.correlation_time_s == 30.0
    assert np.allclose(ce.sigma_enu_m, (0.3, 0.3, 0.6), atol=0.06), ce
    text = out.read_text()
    # where every number came from
    assert "# docs/imu_grades.md; why:" in text
    arw = float(re.search(r"ARW ([\d.]+) deg/sqrt\(h\) \(preset", text).group(1))
    assert arw == pytest.approx(suggest.PRESETS[grade].arw_dpsh, rel=0.1)
    assert "sample-to-sample scatter in motion" in text  # no still part in this log
    assert re.search(rf"in-process run of the first 120 s with {grade}: NIS per degree of freedom", text)
    assert "NOT estimated from the" in text  # the lever arm
    assert "white scatter 0.1" in text and "correlation time: the value measured on real receivers" in text


def test_suggest_config_uses_a_still_part_and_reads_the_biases(tmp_path):
    drive = _drive(tmp_path, "industrial_mems", stop_s=25.0, duration_s=75.0)
    p = rf.write_all(tmp_path / "logs", drive, only=("nmea_csv",))["nmea_csv"]
    m, base = mapping.load_mapping(p)
    r = checks.run_checks(m, base)
    assert r.errors == [], r.text()
    s = suggest.suggest_config(m, base, r)
    assert s.grade == "industrial_mems"
    assert s.noise["method"].startswith("Allan deviation on a still part of 2")  # 24-25 s of rest
    assert s.noise["arw_dpsh"] == pytest.approx(0.15, rel=0.1)
    assert s.noise["vrw_ugpsHz"] == pytest.approx(20.0, rel=0.1)
    # biases drawn per run from the preset's sigmas (20 deg/h, 2000 ug): covered by 3 sigma
    assert 0.0 < s.bias["gyro_up_dph"] < 60.0 and 0.0 < s.bias["accel_up_ug"] < 6000.0
    assert "# bias on the still part:" in s.toml.replace("#   bias", "# bias")
    from_dict(__import__("tomllib").loads(s.toml))


def test_the_suggested_config_is_consistent_where_the_default_is_not(tmp_path):
    """The issue's item 2: the navigation-grade service file on a consumer IMU is off by tens of
    times its sigma; the suggested one is within a factor 2.5 (one run, 60 s after 20 s)."""
    drive = _drive(tmp_path, "consumer_mems")
    p = rf.write_all(tmp_path / "logs", drive, only=("nmea_csv",))["nmea_csv"]
    m, base = mapping.load_mapping(p)
    s = suggest.suggest_config(m, base, checks.run_checks(m, base))
    cfg = from_dict({**__import__("tomllib").loads(s.toml), "vehicles": ["v1"]})
    ours = rf.evaluate_config(drive, cfg)
    default = rf.evaluate_config(
        drive,
        from_dict(
            {
                "vehicles": ["v1"],
                "init": {"min_speed_mps": 3.0},
                "pipelines": [{"name": "lc", "kind": "loosely_coupled"}],
            }
        ),
    )
    assert ours["h_rms_m"] < 1.0 and 0.4 < ours["h_err_over_sigma"] < 2.5, ours
    assert default["h_err_over_sigma"] > 10.0 and default["h_rms_m"] > 10.0 * ours["h_rms_m"], default


def test_fix_sigmas_smaller_than_their_scatter_are_named(tmp_path):
    # the receiver's GST claims 5x less than its fixes scatter from one to the next
    drive = _drive(tmp_path, "consumer_mems", duration_s=52.5)
    small = [
        f.model_copy(update={"pos_std_enu_m": tuple(x / 5.0 for x in f.pos_std_enu_m)}) for f in drive.fixes
    ]
    drive = rf.Drive(drive.imu, small, drive.truth)
    p = rf.write_all(tmp_path / "logs", drive, only=("nmea_csv",))["nmea_csv"]
    m, base = mapping.load_mapping(p)
    s = suggest.suggest_config(m, base, checks.run_checks(m, base))
    assert s.correlated is None
    assert any("more than the sigma they carry" in n and "trust them too much" in n for n in s.notes), s.notes
    assert "# note: the fixes scatter" in s.toml


def test_suggest_config_is_refused_on_a_wrong_mapping(tmp_path, capsys):
    drive = _drive(tmp_path, "consumer_mems", duration_s=42.5)
    p = rf.write_all(tmp_path / "logs", drive, only=("nmea_csv",))["nmea_csv"]
    p.write_text(p.read_text().replace('axes = "FRD"', 'axes = "FLU"'))
    assert replay_main([str(p), "--suggest-config", str(tmp_path / "x.toml")]) == 2
    assert "--suggest-config needs a mapping that passes the checks" in capsys.readouterr().err
    assert not (tmp_path / "x.toml").exists()


def test_allan_deviation_and_the_in_motion_scatter_read_the_white_noise_density():
    rng = np.random.default_rng(4)
    dt, n_density = 0.01, 2.0e-3  # unit / sqrt(Hz)
    white = rng.standard_normal(60_000) * n_density / math.sqrt(dt)
    taus, adev = suggest.allan_deviation(white, dt, [1, 10, 100, 1000])
    assert np.allclose(adev * np.sqrt(taus), n_density, rtol=0.06)  # sigma(tau) = N / sqrt(tau)
    # in motion: a smooth manoeuvre on top (a 0.2 Hz swing 100x the noise) hardly counts
    t = np.arange(len(white)) * dt
    motion = 100 * n_density / math.sqrt(dt) * np.sin(2 * np.pi * 0.2 * t)
    assert suggest.white_density_in_motion(white + motion, dt) == pytest.approx(n_density, rel=0.03)
    # a rate-form source is integrated by the trapezoid: neighbours averaged, the estimate corrects it
    trapezoid = 0.5 * (white[1:] + white[:-1])
    assert suggest.white_density_in_motion(trapezoid, dt, "rate") == pytest.approx(n_density, rel=0.03)
    assert suggest.white_density_in_motion(trapezoid, dt, "increment") < 0.5 * n_density


def test_a_correlated_part_below_the_white_one_is_still_modelled(tmp_path):
    """Fixes with 0.5 m white + 0.3 m correlated error (the sigma they claim, 0.58 m, only ~1.17x
    their white part: measured 1.09-1.35 on this log): at 10 Hz the white part averages out and the
    correlated part dominates, so the suggestion models it (it used to fuse them as independent
    below 1.3x on any axis: 5x overconfident on such a drive)."""
    d = rf.trim(rf.simulate_car_drive(tmp_path, "consumer_mems", 72.5, pos_std_m=0.5, gm_std_m=0.3), START_S)
    p = rf.write_all(tmp_path / "logs", d, only=("nmea_csv",))["nmea_csv"]
    m, base = mapping.load_mapping(p)
    s = suggest.suggest_config(m, base, checks.run_checks(m, base))
    # the case of the change: below 1.3x on an axis, where it used to fuse them as independent
    assert min(s.fixes["sigma_over_white"]) < 1.3, s.fixes
    assert s.correlated is not None and all(0.15 < x < 0.6 for x in s.correlated["sigma_enu_m"][:2]), (
        s.correlated
    )
    cfg = {**__import__("tomllib").loads(s.toml), "vehicles": ["v1"]}
    res = rf.evaluate_config(d, from_dict(cfg))
    # as independent (the old suggestion): 0.49 m against a 1-sigma of 0.076 m on this drive
    white = dict(cfg["pipelines"][0])
    white.pop("gnss_correlated_error")
    old = rf.evaluate_config(d, from_dict({**cfg, "pipelines": [white]}))
    print(res, old)
    assert res["h_rms_m"] < 0.45 and 0.5 < res["h_err_over_sigma"] < 1.5, res  # 0.37 m, 0.99 here
    assert old["h_err_over_sigma"] > 3.0 and old["h_rms_m"] > res["h_rms_m"], old
