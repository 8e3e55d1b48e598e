"""fednav-inspect / fednav-view entry points and the blueprints (rerun-sdk 0.41 API)."""

from __future__ import annotations

import json

import numpy as np
import pytest
import rerun.blueprint as rrb
from rerun.chunk import RrdReader

from fednav.dashboards import blueprints, inspect, view
from fednav.service.messages import Integrity, SatelliteTest, Solution, Truth
from fednav.service.transport import rerun_paths as paths
from fednav.service.transport.rerun_sink import RerunSink

T0 = 1_300_000_000.0
ALL_FAMILIES = {
    "lc": "loosely_coupled",
    "fed": "federated",
    "mhss": "integrity",
    "imm": "imm",
    "ta": "transfer_alignment",
    "uw": "underwater",
}


def _integrity(t: float, hpl: float, alarm: bool = False, available: bool = True) -> Integrity:
    return Integrity(
        t=t,
        pipeline="raim",
        phase="snapshot",
        hpl_m=hpl,
        vpl_m=hpl,
        hal_m=40.0,
        val_m=None,
        alarm=alarm,
        available=available,
        detected=alarm,
        excluded=[],
        satellites=[SatelliteTest(id="G01", statistic_m=1.0, threshold_m=2.0)],
    )


@pytest.fixture
def stanford_rrd(tmp_path):
    """One epoch per Stanford region (HAL 40 m), plus an unavailable one with error above HPL."""
    cases = [  # (error, HPL, alarm)
        (5.0, 10.0, False),  # normal
        (8.0, 12.0, False),  # normal
        (20.0, 15.0, False),  # MI
        (50.0, 30.0, False),  # HMI
        (45.0, 20.0, True),  # alarm (error above HAL, alarm raised)
        (10.0, 50.0, False),  # unavailable
        (60.0, 55.0, False),  # unavailable, error above PL
    ]
    path = tmp_path / "stanford.rrd"
    with RerunSink(path, recording_id="stanford") as sink:
        for k, (e, h, a) in enumerate(cases):
            sink.log_integrity("uav", _integrity(T0 + k, h, alarm=a, available=h <= 40.0), h_error_m=e)
    return path, cases


def test_stanford_regions_and_hmi(stanford_rrd):
    path, cases = stanford_rrd
    s = inspect.inspect_rrd(path)
    i = s["integrity"]["raim"]
    assert i["epochs"] == len(cases)
    hpl = np.array([c[1] for c in cases])
    assert i["hpl_median_m"] == float(np.median(hpl)) and i["hpl_max_m"] == 55.0
    assert i["stanford_h"] == {
        "normal": 2,
        "mi": 1,
        "hmi": 1,
        "alarm": 1,
        "unavailable": 1,
        "unavailable_mi": 1,
        "total": 7,
    }
    # error > HPL without alarm: MI, HMI, unavailable_mi
    assert i["hmi_epochs"] == 3
    assert i["alarm_epochs"] == 1 and i["unavailable_epochs"] == 2
    assert i["stanford_v"] is None  # no VAL, no vertical error
    assert i["val_m"] is None and i["hal_m"] == 40.0


def test_stanford_region_function():
    assert paths.stanford_region(1.0, 2.0, 3.0, False) == "normal"
    assert paths.stanford_region(2.5, 2.0, 3.0, False) == "mi"
    assert paths.stanford_region(3.5, 2.0, 3.0, False) == "hmi"
    assert paths.stanford_region(3.5, 2.0, 3.0, True) == "alarm"
    assert paths.stanford_region(1.0, 4.0, 3.0, False) == "unavailable"
    assert paths.stanford_region(5.0, 4.0, 3.0, False) == "unavailable_mi"
    assert paths.stanford_region(9.0, 2.0, None, False) == "mi"


def test_main_json_and_text(stanford_rrd, capsys):
    path, _ = stanford_rrd
    assert inspect.main([str(path), "--json"]) == 0
    doc = json.loads(capsys.readouterr().out)
    for key in (
        "file",
        "recording_id",
        "duration_s",
        "t_start",
        "t_end",
        "vehicles",
        "pipelines",
        "integrity",
        "faults",
        "health",
    ):
        assert key in doc
    assert doc["recording_id"] == "stanford" and doc["vehicles"] == ["uav"]
    assert doc["duration_s"] == pytest.approx(6.0, abs=1e-6)
    assert doc["pipelines"]["raim"]["solutions"] == 0
    assert inspect.main([str(path)]) == 0
    text = capsys.readouterr().out
    assert "integrity raim: 7 epochs" in text and "Stanford (horizontal)" in text


def test_main_missing_or_unreadable_file(tmp_path, capsys):
    assert inspect.main([str(tmp_path / "nope.rrd")]) == 2
    assert "no such file" in capsys.readouterr().err
    junk = tmp_path / "junk.rrd"
    junk.write_bytes(b"this is not an rrd file" * 10)
    assert inspect.main([str(junk), "--json"]) == 2
    assert "fednav-inspect: error" in capsys.readouterr().err


def test_multi_vehicle_keys(tmp_path):
    path = tmp_path / "fleet.rrd"
    with RerunSink(path, recording_id="fleet") as sink:
        for v in ("a", "b"):
            for k in range(3):
                sink.log_errors(v, "lc", T0 + k, {"east_m": 1.0 + k}, {"east_m": 3.0})
    s = inspect.inspect_rrd(path)
    assert s["vehicles"] == ["a", "b"]
    assert sorted(s["pipelines"]) == ["a/lc", "b/lc"]
    assert s["pipelines"]["b/lc"]["rms"]["east_m"] == pytest.approx(np.sqrt((1 + 4 + 9) / 3), abs=1e-12)


@pytest.mark.parametrize("family", blueprints.FAMILIES)
def test_build_blueprint_each_family(family):
    bp = blueprints.build_blueprint("car1", {"p1": family, "p2": "federated"})
    assert isinstance(bp, rrb.Blueprint)


def test_blueprint_families_and_bad_config(caplog):
    assert blueprints.family_of("centralized") == "loosely_coupled"
    assert blueprints.family_of("tightly_coupled") == "integrity"
    assert isinstance(blueprints.build_blueprint("car1", {"p": "kalman"}), rrb.Blueprint)
    assert "unknown pipeline family 'kalman'" in caplog.text
    with pytest.raises(ValueError, match="reserved"):
        blueprints.blueprint_factory({"truth": "federated"})


def test_blueprints_are_sent_and_embedded(tmp_path):
    """A factory blueprint is (re)sent when vehicles appear; the file embeds every one."""
    path = tmp_path / "bp.rrd"
    sent = []
    factory = blueprints.blueprint_factory(ALL_FAMILIES)

    def spy(vehicles):
        sent.append(list(vehicles))
        return factory(vehicles)

    with RerunSink(path, recording_id="bp", blueprint=spy) as sink:
        for v in ("car1", "car2"):
            sink.log_solution(
                v,
                Solution(
                    t=T0,
                    pipeline="fed",
                    lat_deg=1.0,
                    lon_deg=2.0,
                    height_m=3.0,
                    vel_enu_mps=(0.0, 0.0, 0.0),
                    rpy_deg=(0.0, 0.0, 0.0),
                    pos_std_enu_m=(1.0, 1.0, 1.0),
                    vel_std_enu_mps=(0.1, 0.1, 0.1),
                    rpy_std_deg=(0.1, 0.1, 0.1),
                    status="aided",
                ),
            )
    assert sent == [["car1"], ["car1", "car2"]]
    reader = RrdReader(path)
    assert len(reader.blueprints()) >= 1
    assert [r.recording_id for r in reader.recordings()] == ["bp"]


def test_static_blueprint_object_is_embedded(tmp_path):
    path = tmp_path / "bp2.rrd"
    bp = blueprints.build_blueprint("car1", ALL_FAMILIES)
    with RerunSink(path, recording_id="bp2", blueprint=bp) as sink:
        sink.log_truth(
            "car1",
            Truth(
                t=T0,
                lat_deg=1.0,
                lon_deg=2.0,
                height_m=3.0,
                vel_enu_mps=(0.0, 0.0, 0.0),
                rpy_deg=(0.0, 0.0, 0.0),
            ),
        )
    assert RrdReader(path).blueprints()
    assert inspect.inspect_rrd(path)["has_blueprint"] is True


def test_view_print_command_and_errors(stanford_rrd, tmp_path, capsys, monkeypatch):
    path, _ = stanford_rrd
    assert view.main([str(path), "--print-command"]) == 0
    cmd = capsys.readouterr().out.strip()
    assert cmd.endswith(str(path)) and "rerun" in cmd
    assert view.main([str(path), "--web", "--print-command"]) == 0
    assert "--serve-web" in capsys.readouterr().out
    assert view.main([str(tmp_path / "missing.rrd")]) == 2
    monkeypatch.delenv("DISPLAY", raising=False)
    monkeypatch.delenv("WAYLAND_DISPLAY", raising=False)
    monkeypatch.setattr(view, "has_display", lambda: False)
    assert view.main([str(path)]) == 3
    err = capsys.readouterr().err
    assert "no display" in err and "fednav-view --web" in err


def test_view_rebuild_blueprint(stanford_rrd, capsys):
    path, _ = stanford_rrd
    assert view.main([str(path), "--rebuild-blueprint", "--print-command"]) == 0
    out = capsys.readouterr()
    assert ".rbl" in out.out and "'raim': 'integrity'" in out.err


def test_a_restart_straight_to_unaided_counts_as_a_reinitialisation():
    """A restart shows as unaided (or initialising while the INS is lost) after another status;
    unaided at the start, and initialising followed by unaided, count once."""
    from fednav.dashboards.inspect import Series, _status_timeline

    vals = ["unaided", "aided", "degraded", "unaided", "aided", "initialising", "unaided", "aided"]
    s = Series(np.arange(len(vals), dtype=np.int64) * 1_000_000_000, vals)
    tl = _status_timeline(s, None)
    assert tl["reinitialisations"] == 2


def _innov_rows(factors: dict[str, float], epochs: int = 500) -> dict:
    from scipy.stats import chi2

    lo, hi = float(chi2.ppf(0.025, epochs) / epochs), float(chi2.ppf(0.975, epochs) / epochs)
    return {
        k: {"epochs": epochs, "windows": 50, "nis": f * f, "interval95": [lo, hi], "factor": f}
        for k, f in factors.items()
    }


def test_a_fault_in_the_data_is_named_not_called_overconfidence():
    """The demo's injected faults read as overconfidence: one satellite's pseudorange far off while
    the receiver's other rows are consistent is that row's fault; gate refusals of fixes whose used
    innovations are consistent are faulty fixes refused. A filter whose every row is off is
    overconfident."""
    from fednav.dashboards.inspect import _truth_verdict, _verdict

    raw = {
        "gnss_raw/main": {
            "rows": _innov_rows({"C01.pr": 1.0, "C03.pr": 74.6, "C25.pr": 0.95, "C28.pr": 1.02})
        }
    }
    verdict, _ = _verdict(None, {}, None, raw)
    assert verdict.startswith("consistent (innovations") and "C03.pr 74" not in verdict.split(";")[0], verdict
    assert "faulty data, not overconfidence: gnss_raw/main C03.pr" in verdict, verdict
    fix = {"gnss_fix/main": {"rows": _innov_rows({"pos_e": 0.8, "pos_n": 0.95, "pos_u": 1.1})}}
    gate = {
        "gnss_fix/pos_e": {
            "test": "innovation gate |r|/sqrt(S)",
            "refused": 5,
            "flagged": 5,
            "implied_factor": 2.45,
        }
    }
    verdict, _ = _verdict(None, gate, None, fix)
    assert verdict.startswith("consistent") and "gnss_fix/pos_e (5 rows refused by the gate" in verdict, (
        verdict
    )
    bad = {"gnss_fix/main": {"rows": _innov_rows({"pos_e": 2.5, "pos_n": 2.6, "pos_u": 2.4, "vel_e": 2.2})}}
    verdict, _ = _verdict(None, gate, None, bad)
    assert verdict.startswith("overconfident in north by 2.6x (innovations"), verdict
    assert _truth_verdict({"east_m": 0.0, "north_m": 0.002, "up_m": 0.0}).startswith("consistent: ")
    assert _truth_verdict({"east_m": 0.12, "north_m": 0.01, "up_m": 0.0}).startswith(
        "overconfident in east: "
    )
    assert _truth_verdict({}) is None
