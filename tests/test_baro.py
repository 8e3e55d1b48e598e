"""The barometer end to end, added as one file (service/sensors/baro.py) plus one registry line:
its key and message, its model in a loosely coupled and a federated pipeline through the
configuration, the simulator's [sensors.baro] table, the unused-kind count, the ROS 2 hook, and a
real-process run over Zenoh."""

from __future__ import annotations

import math
import signal

import numpy as np
import pytest
from pydantic import ValidationError

from fednav.service import config, keys, sensors
from fednav.service.messages import json_schemas
from fednav.service.sensors.baro import BLOCK, BaroAltitude, from_fluid_pressure, pressure_altitude_m
from fednav.service.vehicle import VehicleLoop
from fednav.simulators.evaluate import CollectingSink
from fednav.simulators.scenario import parse_scenario
from fednav.simulators.stream import Simulation

from .scenario_utils import SCENARIOS, cut_to

OUTAGE = (120.0, 180.0)  # s after the start: no GNSS fix in this window


def test_one_registry_entry_gives_key_message_schema_and_model():
    assert sensors.get("baro").message is BaroAltitude
    k = keys.sensor("v1", "baro", "b1")
    assert k == "fednav/v1/sensor/baro/b1"
    assert keys.parse_input(k) == keys.ParsedKey("v1", "baro", "b1")
    assert sensors.input_message("baro") is BaroAltitude
    assert "BaroAltitude" in json_schemas()
    with pytest.raises(ValidationError):
        BaroAltitude.model_validate_json(b'{"t": 1.0, "altitude_m": NaN}')
    with pytest.raises(ValidationError):
        BaroAltitude.model_validate({"t": 1.0, "altitude_m": 2.0e6})  # above any altitude


def _scenario(pipelines: list[dict], baro: bool = True):
    import tomllib

    data = cut_to({"faults": [], **tomllib.loads((SCENARIOS / "demo_aircraft.toml").read_text())}, 240.0)
    data["gnss"] = dict(data["gnss"], pos_std_enu_m=[3.0, 3.0, 6.0])
    # a tactical IMU: its vertical channel drifts by metres in a 60 s outage
    data["imu"] = dict(
        data["imu"], gyro_bias_dph=[1.0] * 3, accel_bias_ug=[300.0] * 3, arw_dpsh=0.05, vrw_ugpsHz=50.0
    )
    if baro:
        data["sensors"] = {"baro": {"rate_hz": 10.0, "noise_std_m": 0.3, "offset_m": 12.0}}
    imu = {"gyro_bias_dph": 1.0, "accel_bias_ug": 300.0, "arw_dpsh": 0.05, "vrw_ugpsHz": 50.0}
    data["service"] = {"pipelines": pipelines, "imu": imu}
    return parse_scenario(data, "demo with a barometer")


def _run(sc, seed: int = 4):
    cfg = config.from_dict(dict(sc.service))
    sink = CollectingSink(keep_solutions=True)
    loop = VehicleLoop("v1", cfg, sink)
    sim = Simulation(sc, seed=seed)
    t0 = sim.trajectory.t_s[0]
    truth = {}
    for key, msg in sim:
        pk = keys.parse_input(key)
        if pk.kind == "gnss_fix" and OUTAGE[0] <= msg.t - t0 < OUTAGE[1]:
            continue
        if pk.kind == "truth":
            truth[round(msg.t * 1e6)] = msg
        loop.process(pk.kind, pk.sensor_id, msg)
    return loop, sink, sim, truth, t0


def _outage_vertical_errors(sink, truth, t0: float, name: str) -> list[float]:
    """Height errors of pipeline ``name``'s Solutions inside the GNSS outage (against Truth)."""
    return [
        s.height_m - truth[round(s.t * 1e6)].height_m
        for s in sink.records[name].solutions
        if OUTAGE[0] <= s.t - t0 < OUTAGE[1] and round(s.t * 1e6) in truth
    ]


def test_loosely_coupled_and_federated_fuse_the_barometer_through_config():
    lc = {"name": "lc", "kind": "loosely_coupled"}
    lc_baro = {
        "name": "lc_baro",
        "kind": "loosely_coupled",
        "sensors": ["gnss_fix", "baro"],
        "sensor_options": {"baro": {"offset_std_m": 30.0}},
    }
    fed = {
        "name": "fed_baro",
        "kind": "federated",
        "subsystems": [
            {"name": "INS/GNSS", "sensors": ["gnss_fix"]},
            {"name": "INS/BARO", "sensors": ["baro"]},
        ],
    }
    sc = _scenario([lc, lc_baro, fed])
    errs: dict[str, list[float]] = {"lc": [], "lc_baro": [], "fed_baro": []}
    for seed in (4, 5, 6, 7):
        loop, sink, sim, truth, t0 = _run(sc, seed)
        # the LC without the barometer counts the kind it does not use (and is otherwise untouched)
        h = loop.health()
        assert h.notes.get("unused:lc:baro", 0) > 2000, h.notes
        assert "unused:lc_baro:baro" not in h.notes and "unused:fed_baro:baro" not in h.notes
        assert set(h.rejected) <= {"not_initialised"}, h.rejected
        for name in errs:
            assert sink.records[name].solutions[-1].status == "aided", name
            errs[name] += _outage_vertical_errors(sink, truth, t0, name)
        # the offset (12 m at the start + a slow random walk) is estimated within 3 sigma
        p = next(p for p in loop.engine.pipelines if p.name == "lc_baro")
        cols = p.bank.columns[BLOCK]
        est, sd = float(p.bank.reference[BLOCK][0]), math.sqrt(p.bank.P[0, cols, cols][0, 0])
        assert sd < 3.0 and abs(est - 12.0) < 3.0 * sd + 0.5, (seed, est, sd)
    # during a 60 s GNSS outage the barometer holds the vertical channel: pooled over four seeds
    # (measured: lc 1.36 m, lc_baro 0.65 m, fed_baro 0.70 m RMS)
    rms = {n: float(np.sqrt(np.mean(np.square(e)))) for n, e in errs.items()}
    assert rms["lc_baro"] < 0.7 * rms["lc"], rms
    assert rms["fed_baro"] < 0.7 * rms["lc"], rms


def test_configuration_names_what_is_wrong():
    with pytest.raises(config.ConfigError, match=r"pipelines\.0\.sensors\.1: sensor kind 'barometer'"):
        config.from_dict(
            {"pipelines": [{"name": "a", "kind": "loosely_coupled", "sensors": ["gnss_fix", "barometer"]}]}
        )
    with pytest.raises(config.ConfigError, match=r"pipelines\.0\.sensor_options\.baro\.offset_std_m"):
        config.from_dict(
            {
                "pipelines": [
                    {
                        "name": "a",
                        "kind": "loosely_coupled",
                        "sensors": ["gnss_fix", "baro"],
                        "sensor_options": {"baro": {"offset_std_m": -1}},
                    }
                ]
            }
        )
    with pytest.raises(config.ConfigError, match=r"sensor_options\.baro: sensor kind 'baro' is not among"):
        config.from_dict(
            {"pipelines": [{"name": "a", "kind": "loosely_coupled", "sensor_options": {"baro": {}}}]}
        )
    with pytest.raises(Exception, match=r"sensors\.baro\.rate_hz"):
        _scenario_with({"rate_hz": -1})
    with pytest.raises(Exception, match=r"sensors\.thermometer: no simulator"):
        parse_scenario({**_base_data(), "sensors": {"thermometer": {}}}, "x")


def _base_data() -> dict:
    import tomllib

    return tomllib.loads((SCENARIOS / "demo_aircraft.toml").read_text())


def _scenario_with(baro: dict):
    return parse_scenario({**_base_data(), "sensors": {"baro": baro}}, "x")


def test_simulated_readings_follow_the_true_height_plus_offset():
    sc = _scenario_with({"rate_hz": 5.0, "noise_std_m": 0.2, "offset_m": 7.0, "offset_rw_mps": 0.0})
    sim = Simulation(sc, seed=2)
    traj = sim.trajectory
    got = [(m.t, m.altitude_m) for k, m in sim if keys.parse_input(k).kind == "baro"]
    assert len(got) == int(sc.duration_s * 5.0)
    idx = [traj.index_of(t) for t, _ in got]
    resid = np.array([a - traj.llh[i, 2] - 7.0 for (_, a), i in zip(got, idx, strict=True)])
    assert abs(resid.mean()) < 0.05 and 0.15 < resid.std() < 0.25
    # the other streams are unchanged by the extra sensor (same seed, same values)
    plain = parse_scenario(_base_data(), "x")
    a = [m for k, m in Simulation(plain, seed=2) if keys.parse_input(k).kind == "gnss_fix"]
    b = [m for k, m in Simulation(sc, seed=2) if keys.parse_input(k).kind == "gnss_fix"]
    assert a == b


def test_ros2_fluid_pressure_decodes_straight_into_the_message():
    class Msg:  # the fields of sensor_msgs/msg/FluidPressure
        fluid_pressure = 89_874.6  # Pa: 1000 m in the standard atmosphere
        variance = 4.0  # Pa^2

    m = from_fluid_pressure(Msg(), 1.3e9, "b")
    assert isinstance(m, BaroAltitude) and abs(m.altitude_m - 1000.0) < 0.5
    assert abs(m.std_m - 2.0 * 0.0946) < 0.01  # 2 Pa at ~0.095 m/Pa near 1000 m
    assert abs(pressure_altitude_m(101_325.0)) < 1e-9
    assert sensors.ros2_decoder("sensor_msgs/msg/FluidPressure")[0] == "baro"

    class Bad(Msg):
        fluid_pressure = float("nan")

    with pytest.raises(ValueError):
        from_fluid_pressure(Bad(), 1.3e9, "b")


@pytest.mark.integration
def test_barometer_over_zenoh(tmp_path):
    """Real processes: the simulator publishes the scenario's barometer under its registry key; the
    service fuses it in a loosely coupled pipeline configured with it (Health shows the stream and
    no unused-kind note)."""
    from fednav.simulators.processes import free_port, start_service, start_sim, wait_idle

    scen = tmp_path / "baro.toml"
    text = (SCENARIOS / "demo_aircraft.toml").read_text()
    text = text.replace(
        '[service]\npipelines = [{ name = "lc", kind = "loosely_coupled" }]',
        "[sensors.baro]\nrate_hz = 10.0\n\n[service]\n"
        'pipelines = [{ name = "lc", kind = "loosely_coupled", sensors = ["gnss_fix", "baro"] }]',
    )
    assert "[sensors.baro]" in text
    scen.write_text(text)
    port = free_port()
    svc = start_service(port, config=scen, table="service")
    try:
        sim = start_sim(port, scen, speed=0.0)
        assert sim.wait(timeout=120) == 0, sim.output()
        st = wait_idle(port, timeout_s=60)
        h = st["health"]
    finally:
        svc.signal(signal.SIGTERM)
        assert svc.wait(timeout=60) == 0
    assert "baro/baro" in h["sensors"], h["sensors"]
    assert not h.get("notes"), h.get("notes")
    assert h["pipelines"]["lc"]["status"] in ("aided", "coasting")
    assert h["accepted"] >= 30000 + 2990, h  # IMU samples and baro readings
    assert not h["rejected"], h["rejected"]


def test_ros2_bridge_takes_fluid_pressure_from_the_registry():
    """A [ros2] input of type sensor_msgs/msg/FluidPressure (the barometer entry's ROS 2 hook):
    CDR decoded straight into a BaroAltitude, a bad pressure refused with a reason."""
    from fednav.service.ros2_config import Ros2Config
    from fednav.service.transport import ros2

    c = Ros2Config.model_validate(
        {
            "vehicle": "v1",
            "inputs": [{"topic": "/baro", "type": "sensor_msgs/msg/FluidPressure", "sensor_id": "b"}],
        }
    )
    store = ros2.typestore("jazzy")
    t = store.types

    def fp(pa: float) -> bytes:
        msg = t["sensor_msgs/msg/FluidPressure"](
            header=t["std_msgs/msg/Header"](
                stamp=t["builtin_interfaces/msg/Time"](sec=1_700_000_000, nanosec=0), frame_id="baro"
            ),
            fluid_pressure=pa,
            variance=0.0,
        )
        return bytes(store.serialize_cdr(msg, msg.__msgtype__))

    rin = ros2.RosInput(c)
    key = ros2.topic_key(c, "/baro", "sensor_msgs/msg/FluidPressure")
    [(kind, sid, m)] = rin.decode(key, fp(89_874.6))
    assert (kind, sid) == ("baro", "b") and isinstance(m, BaroAltitude)
    assert abs(m.altitude_m - 1000.0) < 0.5 and m.std_m == 0.5  # variance 0: unknown, the default
    with pytest.raises(ros2.RosDecodeError) as exc:
        rin.decode(key, fp(-5.0))
    assert exc.value.reason == "absurd_value"
    with pytest.raises(ValidationError, match="not a ROS 2 type the bridge decodes"):
        Ros2Config.model_validate(
            {"vehicle": "v1", "inputs": [{"topic": "/x", "type": "sensor_msgs/msg/Range", "sensor_id": "r"}]}
        )


def test_replay_reads_a_barometer_csv_through_the_registry(tmp_path):
    """fednav-replay: a CSV stream of kind 'baro' (the entry's columns t, altitude_m[, std_m]) next
    to an IMU CSV and NMEA: BaroAltitude events under the barometer's key, in the stream's time base;
    a missing column and a kind without a CSV hook are refused naming them."""
    from fednav.replay import mapping as rmapping
    from fednav.replay.checks import run_checks
    from fednav.replay.sources import SourceError, all_events

    from . import replay_files as rf

    drive = rf.simulate_drive(tmp_path, duration_s=32.0)
    files = rf.write_all(tmp_path, drive, only=("nmea_csv",))
    rows = ["t,altitude_m,std_m"] + [
        f"{tr.t - rf.BOOT_GPS_S!r},{tr.height_m + 7.5!r},0.4" for tr in drive.truth[::5]
    ]
    (tmp_path / "baro.csv").write_text("\n".join(rows) + "\n")
    text = files["nmea_csv"].read_text() + (
        f'\n[[streams]]\nsource = "baro.csv"\nkind = "baro"\nsensor_id = "b1"\n'
        f'time_base = "boot"\nboot_offset_s = {rf.BOOT_GPS_S}\n'
    )
    path = tmp_path / "with_baro.toml"
    path.write_text(text)
    m, base = rmapping.load_mapping(path)
    baro = [e for e in all_events(m, base) if e.key_suffix == "sensor/baro/b1"]
    assert len(baro) == len(rows) - 1
    truth = {round(tr.t, 6): tr.height_m for tr in drive.truth}
    for e in baro:
        assert isinstance(e.msg, BaroAltitude) and e.msg.std_m == 0.4
        assert abs(e.msg.altitude_m - 7.5 - truth[round(e.t_gps_s, 6)]) < 1e-6
    assert not run_checks(m, base).errors
    (tmp_path / "bad.csv").write_text("t,std_m\n1.0,0.3\n")
    path.write_text(text.replace('source = "baro.csv"', 'source = "bad.csv"'))
    m, base = rmapping.load_mapping(path)
    with pytest.raises(SourceError, match="altitude_m"):
        list(all_events(m, base))
    path.write_text(text.replace('kind = "baro"', 'kind = "star"'))
    with pytest.raises(rmapping.MappingError, match="star"):
        rmapping.load_mapping(path)
