"""fednav-inspect's innovation test (issue 24): with ``gnss_correlated_error`` configured the fix
residuals cannot judge the claimed sigma (part of the residual is the estimated receiver error,
which the recording does not hold); the innovations can, whatever states stand behind their
covariance S. ``RerunSink.log_innovations`` records them as windows (mean r^2 = nu^2 / S per row
and its count, at the ``faults`` decimation), inspect pools them into the NIS per row against
chi-square(1) with the 95 % interval for that many epochs and bases its verdict on it.

The recordings: the consumer-grade car drive starting in motion, fixes 0.15 m white + 0.3 m
Gauss-Markov (30 s, vertical 2x), replayed from an NMEA + IMU CSV log through the service's
per-vehicle loop and Rerun sink, the pipeline with the correlated-error states; the fix error
model (the sigmas the fixes declare and the configured correlated sigma) as simulated, 5x too
small, 5x too large and 2x too small. The rows each update used (``Pipeline.record_rows``: the prior
innovation and the diagonal of S) reach the sink through the service's own ``OutputSink``, which
drains each pipeline's ``innovations`` at its output epochs.
"""

from __future__ import annotations

import math
import re

import numpy as np
import pytest

from fednav.dashboards import inspect
from fednav.service.config import from_dict
from fednav.service.transport import rerun_paths as paths
from fednav.service.transport.rerun_sink import RerunSink

from . import replay_files as rf

GM = (0.3, 0.3, 0.6)


def _cfg(scale: float) -> dict:
    return {
        "vehicles": ["*"],
        "imu": {"grade": "consumer_mems"},
        "init": {"min_speed_mps": 3.0},
        "pipelines": [
            {
                "name": "lc",
                "kind": "loosely_coupled",
                "gnss_correlated_error": {
                    "sigma_enu_m": [x * scale for x in GM],
                    "correlation_time_s": 30.0,
                },
            }
        ],
    }


def record_with_innovations(mapping_path, cfg, out, health_period_s: float = 1.0) -> None:
    """A replay recorded through the service's per-vehicle loop, ``OutputSink`` and Rerun sink (the
    innovations reach ``RerunSink.log_innovations`` by the service's own wiring)."""
    from fednav.dashboards.blueprints import blueprint_factory
    from fednav.replay.mapping import load_mapping
    from fednav.replay.sources import all_events
    from fednav.service import keys
    from fednav.service.app import OutputSink
    from fednav.service.config import recording_kinds
    from fednav.service.vehicle import VehicleLoop

    class _NoPublish:
        def publish(self, key, msg):
            return None

    m, base = load_mapping(mapping_path)
    clock = [0.0]
    sink = RerunSink(
        out,
        blueprint=blueprint_factory(recording_kinds(cfg.pipelines)),
        flush_interval_s=cfg.rrd_flush_interval_s,
        clock=lambda: clock[0],
        background_flush=False,
        decimation=cfg.rrd_decimation,
        slow_flush_interval_s=cfg.rrd_slow_flush_interval_s,
    )
    outputs = OutputSink(cfg.prefix, _NoPublish(), sink, vehicle_interval_s=cfg.rrd_vehicle_interval_s)
    loop = VehicleLoop(m.vehicle, cfg, outputs, on_fix=outputs.log_fix)
    next_health = -np.inf
    for ev in all_events(m, base):
        clock[0] = ev.t_gps_s
        pk = keys.parse_input(f"{m.prefix}/{m.vehicle}/{ev.key_suffix}", m.prefix)
        loop.process(pk.kind, pk.sensor_id, ev.msg)
        if loop.engine.last_t is not None and loop.engine.last_t >= next_health:
            next_health = loop.engine.last_t + health_period_s
            outputs.log_health(m.vehicle, loop.health())
    sink.close()


@pytest.fixture(scope="module")
def recordings(tmp_path_factory):
    """{scale: (rrd, summary with --config)}: the fix error model as simulated (1), 5x too small,
    5x too large, 2x too small."""
    tmp = tmp_path_factory.mktemp("nis")
    drive = rf.trim(rf.simulate_car_drive(tmp, "consumer_mems", 62.5, pos_std_m=0.15, gm_std_m=0.3), 12.5)
    out = {}
    for scale in (1.0, 0.2, 5.0, 0.5):
        fixes = [
            f.model_copy(update={"pos_std_enu_m": tuple(x * scale for x in f.pos_std_enu_m)})
            for f in drive.fixes
        ]
        p = rf.write_all(tmp / f"logs_{scale}", rf.Drive(drive.imu, fixes, drive.truth), only=("nmea_csv",))
        # NMEA carries no speed sigma: the mapping says the simulated one (the default, 0.15 m/s for
        # a single fix, is 3x the simulated 0.05: inspect calls that underconfident in speed)
        text = p["nmea_csv"].read_text()
        sig = ", ".join(f"{0.05 * scale:g}" for _ in range(2)) + f", {0.1 * scale:g}"
        p["nmea_csv"].write_text(text.replace('sensor_id = "rx"', f'sensor_id = "rx"\nvel_std_mps = [{sig}]'))
        rrd = tmp / f"run_{scale}.rrd"
        cfg = from_dict(_cfg(scale))
        record_with_innovations(p["nmea_csv"], cfg, rrd)
        out[scale] = (rrd, inspect.inspect_rrd(rrd, cfg))
    return out


def _nis(p: dict) -> dict:
    (r,) = p["innovations"].values()
    return r["rows"]


def test_the_innovations_are_recorded_as_cheap_windows(recordings):
    rrd, s = recordings[1.0]
    _, data = inspect.read_series(rrd)
    root = paths.innovations("nmea_csv", "lc", "gnss_fix/rx")
    assert root == "/nmea_csv/lc/innovations/gnss_fix/rx"
    r2 = data[f"{root}/pos_u/r2_mean"]
    n = data[f"{root}/pos_u/count"]
    # one window per faults decimation interval (2 s): ~25 rows for 500 fixes, each pooling ~20
    assert 20 <= len(r2) <= 30 and np.array_equal(r2.t_ns, n.t_ns)
    assert 450 <= float(np.sum(n.values)) <= 500
    rows = _nis(s["pipelines"]["lc"])
    assert list(rows)[:3] == ["pos_e", "pos_n", "pos_u"]


def test_a_consistent_run_with_correlated_error_states_is_called_consistent(recordings):
    _, s = recordings[1.0]
    p = s["pipelines"]["lc"]
    assert p["fix_residuals_apply"] is False
    assert p["verdict"].startswith("consistent (innovations: real / claimed spread within 1.5x: east "), p[
        "verdict"
    ]
    for label, a in _nis(p).items():
        assert 1 / 1.5 < a["factor"] < 1.5, (label, a)
        lo, hi = a["interval95"]
        assert lo < 1.0 < hi and a["epochs"] > 300


def test_fix_error_model_5x_too_small_is_overconfident(recordings):
    _, s = recordings[0.2]
    p = s["pipelines"]["lc"]
    m = re.match(r"overconfident in ([\w -]+?) by (\d+\.\d)x \(gate refusals", p["verdict"])
    assert m and float(m.group(2)) > 3.0, p["verdict"]
    # the gate refuses most rows; those it lets through (speed, and the position rows of the first
    # epochs, whose covariance holds the receiver error the first fix carried) show it too
    (r,) = p["innovations"].values()
    assert r["refused"] > 500, r
    assert all(a["factor"] > 2.0 and a["nis"] > a["interval95"][1] for a in r["rows"].values()), r


def test_fix_error_model_5x_too_large_is_underconfident(recordings):
    _, s = recordings[5.0]
    p = s["pipelines"]["lc"]
    m = re.match(
        r"underconfident in (east|north|up) by (\d+\.\d)x \(innovations \(gnss_fix/rx: NIS ", p["verdict"]
    )
    assert m and 3.0 < float(m.group(2)) < 8.0, p["verdict"]
    pos = {k: a for k, a in _nis(p).items() if k.startswith("pos")}
    assert all(a["factor"] < 0.4 and a["nis"] < a["interval95"][0] for a in pos.values()), pos


def test_fix_error_model_2x_too_small_is_overconfident(recordings):
    _, s = recordings[0.5]
    p = s["pipelines"]["lc"]
    m = re.match(r"overconfident in ([\w -]+?) by (\d+\.\d)x \(", p["verdict"])
    assert m and 1.5 < float(m.group(2)) < 3.0, p["verdict"]
    # the innovations of the rows the gate let through: about 2x their claimed spread
    for label, a in _nis(p).items():
        assert 1.5 < a["factor"] < 2.5 and a["nis"] > a["interval95"][1], (label, a)


def test_the_text_says_it(recordings, capsys, tmp_path):
    rrd, _ = recordings[0.5]
    svc = tmp_path / "svc.toml"
    svc.write_text(
        '[[pipelines]]\nname = "lc"\nkind = "loosely_coupled"\n'
        "gnss_correlated_error = { sigma_enu_m = [0.15, 0.15, 0.3], correlation_time_s = 30.0 }\n"
    )
    assert inspect.main([str(rrd), "--config", str(svc)]) == 0
    text = capsys.readouterr().out
    assert re.search(
        r"    innovations gnss_fix/rx \(\d+ epochs\): NIS per row against chi-square\(1\) \(95 % interval, "
        r"real/claimed spread\): east \d+\.\d\d \(0\.\d\d-1\.\d\d, x1\.\d\d\), north ",
        text,
    ), text
    assert "    verdict: overconfident in " in text
    assert inspect.main([str(rrd), "--json", "--config", str(svc)]) == 0


def test_nis_interval_is_chi_square_of_the_epochs():
    from scipy.stats import chi2

    n = 400
    lo, hi = chi2.ppf(0.025, n) / n, chi2.ppf(0.975, n) / n
    assert lo == pytest.approx(1 - 1.96 * math.sqrt(2 / n), abs=0.01)
    assert hi == pytest.approx(1 + 1.96 * math.sqrt(2 / n), abs=0.01)


def test_inspect_prints_the_estimated_states(tmp_path):
    """Faults ``states`` (an estimated lever arm, scale factors, a DVL offset) reach the recording
    and ``fednav-inspect`` reports the last value and 1-sigma of each (read back with Rerun's reader)."""
    from fednav.service.messages import Faults, StateEstimate, SubsystemFaults

    out = tmp_path / "states.rrd"
    sink = RerunSink(out)
    for t, value, std in ((10.0, 0.5, 0.3), (11.0, 0.82, 0.04)):
        sub = SubsystemFaults(name="gnss_fix", isolated=False, observations=[])
        states = [
            StateEstimate(name="gnss_lever_arm_y_m", value=value, std=std),
            StateEstimate(name="gyro_scale_z_ppm", value=100.0 * value, std=10.0 * std),
        ]
        sink.log_faults("v1", Faults(t=t, pipeline="lc", subsystems=[sub], states=states))
    sink.close()
    s = inspect.inspect_rrd(out)
    got = s["faults"]["lc"]["states_last"]  # one vehicle: keyed by pipeline
    assert got["gnss_lever_arm_y_m"] == {"value": pytest.approx(0.82), "std": pytest.approx(0.04)}
    assert got["gyro_scale_z_ppm"] == {"value": pytest.approx(82.0), "std": pytest.approx(0.4)}
    text = inspect.render_text(s)
    assert re.search(r"state gnss_lever_arm_y_m\s+0\.82\d* \+- 0\.04", text), text
