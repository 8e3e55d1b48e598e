"""RerunSink round trip: write real wire messages, verify the .rrd with the rerun CLI, read it back
with Rerun's reader (via dashboards.inspect) and compare with numbers computed directly."""

from __future__ import annotations

import math
import subprocess
import sys
import threading
from pathlib import Path

import numpy as np
import pytest
from rerun.chunk import RrdReader

from fednav.dashboards.blueprints import blueprint_factory
from fednav.dashboards.inspect import inspect_rrd, read_series, render_text
from fednav.service.messages import (
    ActiveFault,
    Faults,
    Health,
    Integrity,
    ObservationFault,
    PipelineHealth,
    SatelliteTest,
    Solution,
    SubsystemFaults,
    Truth,
)
from fednav.service.transport import rerun_paths as paths
from fednav.service.transport.rerun_sink import RerunSink, seconds_to_ns

RERUN = Path(sys.executable).parent / "rerun"
T0 = 1_400_000_000.0  # GPS seconds
VEHICLE = "car1"
PIPELINES = {"fed": "federated", "mhss": "integrity"}
DT = 0.1
N = 201  # 20 s at 10 Hz


class StepClock:
    """Deterministic wall clock: advances 0.05 s per reading (exercises the periodic flush)."""

    def __init__(self) -> None:
        self.t = 0.0

    def __call__(self) -> float:
        self.t += 0.05
        return self.t


def _verify(path: Path) -> None:
    out = subprocess.run(
        [str(RERUN), "rrd", "verify", str(path)], capture_output=True, text=True, timeout=120
    )
    assert out.returncode == 0, out.stdout + out.stderr


def _solution(pipeline: str, t: float, k: int, status: str) -> Solution:
    return Solution(
        t=t,
        pipeline=pipeline,
        lat_deg=30.5 + 1e-6 * k,
        lon_deg=114.3 + 2e-6 * k,
        height_m=50.0 + 0.01 * k,
        vel_enu_mps=(10.0, 5.0, 0.1),
        rpy_deg=(1.0, 2.0, 45.0),
        pos_std_enu_m=(1.0, 1.1, 2.0),
        vel_std_enu_mps=(0.1, 0.1, 0.2),
        rpy_std_deg=(0.01, 0.01, 0.05),
        gyro_bias_dph=(0.01 * k, 0.0, 0.0) if pipeline == "fed" else (0.0, 0.0, 0.0),
        status=status,
    )


def _write_recording(path: Path, seed: int = 7) -> dict:
    """Write the synthetic scenario; return the ground numbers the summary must reproduce."""
    rng = np.random.default_rng(seed)
    errors = {p: {n: rng.normal(0.0, 1.0 + i, N) for i, n in enumerate(paths.ERROR_NAMES)} for p in PIPELINES}
    bounds = {p: {n: np.full(N, 3.0 * (1.0 + i)) for i, n in enumerate(paths.ERROR_NAMES)} for p in PIPELINES}
    hpl, herr, vpl = [], [], []
    sink = RerunSink(
        path,
        recording_id="rec-test-1",
        blueprint=blueprint_factory(PIPELINES),
        flush_interval_s=0.5,
        clock=StepClock(),
        track_interval_s=5.0,
    )
    for k in range(N):
        t = T0 + k * DT
        faults = [ActiveFault(sensor="gnss", kind="step", channels=["pe"])] if 100 <= k < 120 else []
        sink.log_truth(
            VEHICLE,
            Truth(
                t=t,
                lat_deg=30.5,
                lon_deg=114.3,
                height_m=50.0,
                vel_enu_mps=(10.0, 5.0, 0.0),
                rpy_deg=(1.0, 2.0, 45.0),
                faults=faults,
            ),
        )
        for p in PIPELINES:
            status = "unaided" if k < 10 else ("coasting" if p == "fed" and k >= 150 else "aided")
            sink.log_solution(VEHICLE, _solution(p, t, k, status))
            sink.log_errors(
                VEHICLE,
                p,
                t,
                {n: float(v[k]) for n, v in errors[p].items()},
                {n: float(v[k]) for n, v in bounds[p].items()},
            )
        if k % 10 == 0:  # 1 Hz aiding epochs
            j = k // 10
            flagged = j in (3, 4, 9)
            sink.log_faults(
                VEHICLE,
                Faults(
                    t=t,
                    pipeline="fed",
                    subsystems=[
                        SubsystemFaults(
                            name="gnss",
                            isolated=flagged,
                            observations=[
                                ObservationFault(
                                    label="pe",
                                    statistic=20.0 if flagged else 1.0,
                                    threshold=6.63,
                                    flagged=flagged,
                                    isolated=False,
                                ),
                                ObservationFault(
                                    label="pn", statistic=0.5, threshold=6.63, flagged=False, isolated=False
                                ),
                            ],
                        ),
                        SubsystemFaults(
                            name="star",
                            isolated=False,
                            observations=[
                                ObservationFault(
                                    label="roll",
                                    statistic=7.0 if j == 5 else 0.1,
                                    threshold=6.63,
                                    flagged=j == 5,
                                    isolated=j == 5,
                                ),
                            ],
                        ),
                    ],
                    sharing={"gnss": [0.5] * 15, "star": [0.5] * 15},
                ),
            )
            h = 10.0 + j  # HPL 10..30 m
            # j=7: HMI (HPL 17 < HAL 30 < 35); j=8: MI (HPL 18 < 20 < HAL 30)
            e = 35.0 if j == 7 else (20.0 if j == 8 else 2.0)
            hpl.append(h)
            herr.append(e)
            vpl.append(2.0 * h)
            sink.log_integrity(
                VEHICLE,
                Integrity(
                    t=t,
                    pipeline="mhss",
                    phase="tracking",
                    hpl_m=h,
                    vpl_m=2.0 * h,
                    hal_m=30.0,
                    val_m=50.0,
                    alarm=j == 12,
                    available=h <= 30.0,
                    detected=j in (12, 13),
                    excluded=["C03"] if j >= 13 else [],
                    satellites=[
                        SatelliteTest(id=s, statistic_m=1.0 + j, threshold_m=5.0) for s in ("C03", "G12")
                    ],
                ),
                h_error_m=e,
                v_error_m=3.0,
            )
            sink.log_health(
                VEHICLE,
                Health(
                    t=t,
                    uptime_s=float(j),
                    received=100 * (j + 1),
                    accepted=99 * (j + 1),
                    rejected={"late": j, "nan": 1},
                    dropped_overload=0,
                    queue_depth=j % 3,
                    latency_ms={"p50": 1.5, "p99": 4.0, "max": 9.0},
                    pipelines={p: PipelineHealth(status="aided", last_t=t, updates=k) for p in PIPELINES},
                ),
            )
    sink.close()
    return {
        "errors": errors,
        "bounds": bounds,
        "hpl": np.array(hpl),
        "herr": np.array(herr),
        "vpl": np.array(vpl),
    }


@pytest.fixture(scope="module")
def recording(tmp_path_factory):
    path = tmp_path_factory.mktemp("rrd") / "sub" / "run.rrd"  # parent folder created by the sink
    truth = _write_recording(path)
    return path, truth


def test_rrd_verifies_and_embeds_blueprint(recording):
    path, _ = recording
    _verify(path)
    reader = RrdReader(path)
    recs = reader.recordings()
    assert [r.recording_id for r in recs] == ["rec-test-1"]
    assert recs[0].application_id == "fednav"
    assert reader.blueprints(), "the recording must embed its blueprint"


def test_summary_matches_synthetic_numbers(recording):
    path, truth = recording
    s = inspect_rrd(path)
    assert s["recording_id"] == "rec-test-1"
    assert s["vehicles"] == [VEHICLE]
    assert sorted(s["pipelines"]) == sorted(PIPELINES)
    assert s["t_start"] == pytest.approx(T0, abs=1e-6)
    assert s["t_end"] == pytest.approx(T0 + (N - 1) * DT, abs=1e-6)
    assert s["duration_s"] == pytest.approx((N - 1) * DT, abs=1e-6)
    for p in PIPELINES:
        ps = s["pipelines"][p]
        assert ps["solutions"] == N
        assert ps["error_epochs"] == N
        for name, x in truth["errors"][p].items():
            assert ps["rms"][name] == pytest.approx(float(np.sqrt(np.mean(x**2))), abs=1e-9, rel=0)
            assert ps["max"][name] == pytest.approx(float(np.max(np.abs(x))), abs=1e-9, rel=0)
            out = float(np.mean(np.abs(x) > truth["bounds"][p][name]))
            assert ps["outside_3sigma"][name] == pytest.approx(out, abs=1e-12)
        h = np.hypot(truth["errors"][p]["east_m"], truth["errors"][p]["north_m"])
        assert ps["h_rms_m"] == pytest.approx(float(np.sqrt(np.mean(h**2))), abs=1e-9, rel=0)
        assert ps["rms"]["horizontal_m"] == ps["h_rms_m"]
    assert s["pipelines"]["fed"]["final_status"] == "coasting"
    assert s["pipelines"]["fed"]["status_changes"] == 3
    assert s["pipelines"]["mhss"]["final_status"] == "aided"


def test_summary_integrity_faults_health(recording):
    path, truth = recording
    s = inspect_rrd(path)
    assert list(s["integrity"]) == ["mhss"]
    i = s["integrity"]["mhss"]
    assert i["epochs"] == 21
    assert i["hpl_median_m"] == pytest.approx(float(np.median(truth["hpl"])), abs=1e-12)
    assert i["hpl_max_m"] == pytest.approx(30.0, abs=1e-12)
    assert i["vpl_median_m"] == pytest.approx(float(np.median(truth["vpl"])), abs=1e-12)
    assert i["vpl_max_m"] == pytest.approx(60.0, abs=1e-12)
    assert i["hal_m"] == 30.0 and i["val_m"] == 50.0
    assert i["alarm_epochs"] == 1 and i["alarm_events"] == 1
    assert i["detected_epochs"] == 2 and i["detection_events"] == 1
    assert i["exclusion_events"] == 1 and i["excluded_sats"] == ["C03"]
    assert i["unavailable_epochs"] == 0  # HPL <= 30 everywhere
    # "HMI epochs" = error > HPL without alarm: j=7 and j=8
    expected_hmi = int(np.sum(truth["herr"] > truth["hpl"]))
    assert i["hmi_epochs"] == expected_hmi == 2
    st = i["stanford_h"]
    assert (st["normal"], st["mi"], st["hmi"], st["alarm"], st["unavailable"]) == (19, 1, 1, 0, 0)
    assert st["total"] == 21
    sv = i["stanford_v"]  # error 3 m; VPL = 2 HPL = 20..60 m > VAL 50 m from j=16 on
    assert (sv["normal"], sv["unavailable"], sv["total"]) == (16, 5, 21)
    f = s["faults"]["fed"]
    assert f["flagged"] == {"gnss/pe": 3, "gnss/pn": 0, "star/roll": 1}
    assert f["observations"]["star/roll"]["isolated"] == 1
    assert f["observations"]["gnss/pe"]["tests"] == 21
    assert f["observations"]["gnss/pe"]["max_statistic"] == 20.0
    assert f["subsystem_isolated_epochs"] == {"gnss": 3, "star": 0}
    assert f["sharing_last"]["gnss"]["14"] == 0.5
    hl = s["health"][VEHICLE]
    assert hl["received"] == 2100 and hl["accepted"] == 2079 and hl["rejected_total"] == 21
    assert hl["rejected"] == {"late": 20, "nan": 1}  # why, per reason (Health rejected), most first
    assert hl["latency_p99_ms"] == 4.0
    assert "rejected_total 21 (late 20, nan 1)" in render_text(s)


def test_entities_follow_the_layout(recording):
    path, _ = recording
    _, data = read_series(path)
    v = VEHICLE
    for name in paths.SOLUTION_SCALARS:
        assert paths.truth(v, name) in data
        assert len(data[paths.solution(v, "fed", name)]) == N
    for name in paths.STD_SCALARS:
        assert paths.solution_std(v, "mhss", name) in data
    for name in paths.ERROR_NAMES:
        assert paths.bound(v, "fed", name) in data
    assert paths.solution(v, "fed", "gyro_bias_dph") in data
    assert paths.solution(v, "mhss", "gyro_bias_dph") not in data  # all-zero biases are not logged
    assert paths.integrity_sat(v, "mhss", "G12", "statistic_m") in data
    assert paths.sharing(v, "fed", "star", 0) in data
    # the injected-fault log states the fault state from the first truth on (an empty panel in a
    # run without faults would read as missing data)
    assert [x for x in data[paths.truth(v, "faults")].values] == [
        "no active faults",
        "gnss step [pe]",
        "no active faults",
    ]
    assert paths.health(v, "queue_depth") in data
    # bounds are recorded as [+3σ, -3σ]; the reader keeps +3σ
    assert float(data[paths.bound(v, "fed", "east_m")].values[0]) == 3.0
    # times are exact to the nanosecond of the float seconds
    t = data[paths.solution(v, "fed", "lat_deg")].t_ns
    assert t[0] == seconds_to_ns(T0) and t[-1] == seconds_to_ns(T0 + (N - 1) * DT)


def test_map_entities_and_tracks(recording):
    path, _ = recording
    seen = {}
    geo = ["GeoPoints:positions", "GeoLineStrings:line_strings"]
    for ch in RrdReader(path).stream().filter(components=geo):
        if not ch.is_static:
            seen[ch.entity_path] = seen.get(ch.entity_path, 0) + ch.num_rows
    assert seen[paths.truth(VEHICLE, "position")] == N
    assert seen[paths.solution(VEHICLE, "fed", "position")] == N
    assert seen[paths.solution(VEHICLE, "mhss", "track")] >= 4  # every 5 s of sensor time + final
    assert seen[paths.truth(VEHICLE, "track")] >= 4


def test_close_is_idempotent_and_late_calls_are_noops(tmp_path):
    path = tmp_path / "twice.rrd"
    sink = RerunSink(path, recording_id="twice")
    sink.log_truth(
        "v1",
        Truth(
            t=T0, lat_deg=1.0, lon_deg=2.0, height_m=3.0, vel_enu_mps=(0.0, 0.0, 0.0), rpy_deg=(0.0, 0.0, 0.0)
        ),
    )
    sink.close()
    sink.close()
    assert sink.closed
    sink.log_truth(
        "v1",
        Truth(
            t=T0 + 1,
            lat_deg=1.0,
            lon_deg=2.0,
            height_m=3.0,
            vel_enu_mps=(0.0, 0.0, 0.0),
            rpy_deg=(0.0, 0.0, 0.0),
        ),
    )
    sink.flush()
    sink.close()
    _verify(path)
    s = inspect_rrd(path)
    assert s["vehicles"] == ["v1"] and s["duration_s"] == 0.0 and s["pipelines"] == {}


def test_disabled_sink_is_a_noop(tmp_path):
    sink = RerunSink(None)
    assert not sink.enabled and sink.closed
    sink.log_solution("v", _solution("p", T0, 0, "aided"))
    sink.log_errors("v", "p", T0, {"east_m": 1.0}, {"east_m": 3.0})
    sink.log_health(
        "v",
        Health(
            t=None,
            uptime_s=0.0,
            received=0,
            accepted=0,
            rejected={},
            dropped_overload=0,
            queue_depth=0,
            latency_ms={},
            pipelines={},
        ),
    )
    sink.flush()
    sink.close()
    sink.close()
    assert list(tmp_path.iterdir()) == []


def test_bad_arguments_raise(tmp_path):
    with RerunSink(tmp_path / "bad.rrd") as sink:
        with pytest.raises(ValueError, match="unknown error names"):
            sink.log_errors("v", "p", T0, {"east": 1.0})
        with pytest.raises(ValueError, match="reserved"):
            sink.log_errors("v", "truth", T0, {"east_m": 1.0})
        with pytest.raises(ValueError, match="fixed layout"):
            sink.log_scalars("v", "p", T0, "error", {"x": 1.0})
        sink.log_scalars("v", "imm1", T0, "imm", {"p_cv": 0.8, "p_ct": 0.2})
    _, data = read_series(tmp_path / "bad.rrd")
    assert float(data[paths.group("v", "imm1", "imm", "p_cv")].values[0]) == 0.8


def test_close_from_another_thread_loses_nothing(tmp_path):
    """close() from a signal-handling thread while the worker logs: every accepted row is in the file."""
    path = tmp_path / "race.rrd"
    sink = RerunSink(path, recording_id="race", flush_interval_s=3600.0)  # only close() sends
    started = threading.Event()
    logged = []

    def worker():
        for k in range(100_000):
            if sink.closed:
                break
            sink.log_errors("v", "p", T0 + k * 0.01, {"east_m": float(k)})
            if not sink.closed:
                logged.append(k)
            if k == 200:
                started.set()

    th = threading.Thread(target=worker)
    th.start()
    started.wait(10)
    sink.close()
    th.join(10)
    s = inspect_rrd(path)
    # every row logged before close() is recorded (a row racing with close() may be recorded or not)
    assert len(logged) - 1 <= s["pipelines"]["p"]["error_epochs"] <= len(logged) + 1
    assert s["pipelines"]["p"]["error_epochs"] > 200


def test_health_without_time_uses_latest_sensor_time(tmp_path):
    path = tmp_path / "h.rrd"
    with RerunSink(path) as sink:
        h = Health(
            t=None,
            uptime_s=0.0,
            received=1,
            accepted=0,
            rejected={"schema": 1},
            dropped_overload=0,
            queue_depth=0,
            latency_ms={},
            pipelines={},
        )
        sink.log_health("v", h)  # nothing processed yet: skipped
        sink.log_truth(
            "v",
            Truth(
                t=T0 + 5,
                lat_deg=1.0,
                lon_deg=2.0,
                height_m=3.0,
                vel_enu_mps=(0.0, 0.0, 0.0),
                rpy_deg=(0.0, 0.0, 0.0),
            ),
        )
        sink.log_health("v", h)
    _, data = read_series(path)
    s = data[paths.health("v", "rejected_total")]
    assert list(s.t_ns) == [seconds_to_ns(T0 + 5)] and float(s.values[0]) == 1.0
    assert paths.health("v", "latency_p50_ms") not in data


def test_seconds_to_ns():
    assert seconds_to_ns(0.0) == 0
    assert seconds_to_ns(1.5) == 1_500_000_000
    t = T0 + 0.1
    assert abs(seconds_to_ns(t) - t * 1e9) <= 256  # within float64 resolution at 1.4e18 ns
    assert seconds_to_ns(T0 + 0.25) == 1_400_000_000_250_000_000
    assert math.isclose(seconds_to_ns(1e10) / 1e9, 1e10)


def test_optimize_on_close_keeps_content(tmp_path):
    plain, packed = tmp_path / "plain.rrd", tmp_path / "packed.rrd"
    for path, optimize in ((plain, False), (packed, True)):
        with RerunSink(
            path,
            recording_id="opt",
            flush_interval_s=0.0,
            optimize_on_close=optimize,
            blueprint=blueprint_factory(PIPELINES),
        ) as sink:
            for k in range(50):
                sink.log_errors("v", "fed", T0 + k * DT, {"east_m": math.sin(k), "north_m": math.cos(k)})
                sink.log_solution("v", _solution("fed", T0 + k * DT, k, "aided"))
    _verify(packed)
    n_chunks = {p: sum(1 for _ in RrdReader(p).stream()) for p in (plain, packed)}
    assert n_chunks[packed] < n_chunks[plain]
    assert RrdReader(packed).blueprints()
    a, b = inspect_rrd(plain), inspect_rrd(packed)
    a.pop("file"), b.pop("file")
    assert a == b
    assert not list(tmp_path.glob("*.optimizing"))


def test_stanford_tick_labels_are_short_and_do_not_crowd():
    """Short labels (1cm .. 10km); every decade up to five decades, every other one beyond (and the
    top one); the x axis starts one decade in, away from the y axis's lowest label."""
    assert [paths._metres(d) for d in range(-2, 5)] == ["1cm", "10cm", "1m", "10m", "100m", "1km", "10km"]

    def ticks(lo, hi):
        _, _, (pos, texts, _) = paths.stanford_frame(lo, hi, None, None)
        x = [t for p, t in zip(pos, texts, strict=True) if p[1] == -lo + 0.12]
        y = [t for p, t in zip(pos, texts, strict=True) if p[0] == lo - 0.12]
        return x, y

    assert ticks(-1, 2) == (["1m", "10m", "100m"], ["10cm", "1m", "10m", "100m"])
    x, y = ticks(-2, 4)  # six decades: every other one
    assert y == ["1cm", "1m", "100m", "10km"] and x == ["1m", "100m", "10km"]


def test_alignment_error_series_carry_axis_labels_and_colours():
    from fednav.service.app import alignment_styles

    s = alignment_styles("wing2")
    assert len(s) == 27  # 3 quantities x 3 axes x (error, +3σ, -3σ)
    assert s["wing2.lever_x"] == ("x error", paths.AXIS_COLOURS[0])
    assert s["wing2.flexure_z_p3s"] == ("z +3σ", paths.AXIS_COLOURS[2])
    assert s["wing2.misalignment_y_m3s"][1] == paths.AXIS_COLOURS[1]


def test_a_due_flush_is_sent_by_the_flusher_not_the_logging_thread(tmp_path):
    """The logging call that finds a flush due only wakes the background flusher: a fleet's flush
    (a chunk per entity) must not run in the service's intake thread; every row is in the file."""
    path = tmp_path / "bg.rrd"
    now = [0.0]
    sink = RerunSink(path, recording_id="bg", flush_interval_s=1.0, clock=lambda: now[0])
    senders: list[str] = []
    send = sink._send

    def spy(series):
        if series:
            senders.append(threading.current_thread().name)
        send(series)

    sink._send = spy
    for k in range(50):
        now[0] = 0.1 * k  # five flushes due over the run
        sink.log_errors("v", "p", T0 + 0.1 * k, {"east_m": float(k)})
    deadline = threading.Event()
    for _ in range(100):  # the flusher wakes within a quarter of the interval of wall time
        if senders:
            break
        deadline.wait(0.05)
    assert senders and set(senders) == {"fednav-rerun-flush"}, senders
    sink.close()
    assert inspect_rrd(path)["pipelines"]["p"]["error_epochs"] == 50


def test_entities_flushed_together_keep_their_own_times_and_values(tmp_path):
    """One flush sends many entities; those whose rows share times share their time columns
    (made once per flush): each entity reads back with its own times and values, whether its rows'
    times equal another entity's or not."""
    path = tmp_path / "shared.rrd"
    now = [0.0]
    sink = RerunSink(
        path, recording_id="shared", flush_interval_s=5.0, clock=lambda: now[0], background_flush=False
    )
    offsets = {"a": 0.0, "b": 0.0, "c": 0.05}  # a and b at the same times, c between them
    for k in range(30):
        now[0] = 0.1 * k  # the 5 s flush interval: everything goes in the final flush at close
        for i, (v, off) in enumerate(offsets.items()):
            sink.log_errors(v, "p", T0 + 0.1 * k + off, {"east_m": 100.0 * i + k, "north_m": -100.0 * i - k})
    sink.close()
    _, series = read_series(path)
    for i, (v, off) in enumerate(offsets.items()):
        for name, sign in (("east_m", 1.0), ("north_m", -1.0)):
            ent = [e for e in series if e.startswith(f"/{v}/") and e.endswith(f"/{name}")]
            assert len(ent) == 1, (v, name, sorted(series))
            s = series[ent[0]]
            want_t = np.array([seconds_to_ns(T0 + 0.1 * k + off) for k in range(30)], dtype=np.int64)
            np.testing.assert_array_equal(s.t_ns, want_t)
            np.testing.assert_array_equal(s.values, sign * (100.0 * i + np.arange(30)))


def test_forget_writes_a_vehicles_pending_rows_and_drops_its_books(tmp_path):
    """A vehicle the service released (``[intake] vehicle_idle_s``): what it logged is in the file
    (rows still buffered at the release and its map track included), nothing of it stays in the
    sink's books, the other vehicle is untouched, and the vehicle can come back."""
    path = tmp_path / "forget.rrd"
    sink = RerunSink(path, recording_id="forget", flush_interval_s=3600.0)  # nothing sent by time
    for k in range(50):
        for v in ("gone", "stays"):
            sink.log_solution(v, _solution("fed", T0 + k * DT, k, "aided"))
            sink.log_errors(v, "fed", T0 + k * DT, {"east_m": float(k)})
    sink.forget("gone")
    root = paths.vehicle_root("gone") + "/"
    assert not any(p.startswith(root) for p in sink._series)
    assert not any(p.startswith(root) for p in sink._tracks)
    assert not any(k[0] == "gone" for k in (*sink._status, *sink._colors, *sink._enu_last))
    assert any(p.startswith(paths.vehicle_root("stays") + "/") for p in sink._series)
    sink.log_solution("gone", _solution("fed", T0 + 100.0, 0, "aided"))  # back later
    sink.close()
    _, data = read_series(path)
    gone, stays = data[paths.error("gone", "fed", "east_m")], data[paths.error("stays", "fed", "east_m")]
    assert len(gone.t_ns) == len(stays.t_ns) == 50
    rows = {}
    reader = RrdReader(path)
    for ch in reader.stream(store=reader.recordings()[0]):
        if not ch.is_static:
            rows[ch.entity_path] = rows.get(ch.entity_path, 0) + ch.num_rows
    assert (
        rows.get(paths.solution("gone", "fed", "status"), 0)
        == rows.get(paths.solution("stays", "fed", "status"), 0) + 1
    ), rows
