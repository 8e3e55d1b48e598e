"""ImuBatch: the binary layout, vectorised validation, the engine's record-by-record rules, and the
same solutions as one JSON ImuSample per sample (service/imu_batch.py, service/vehicle.py)."""

from __future__ import annotations

import math
import signal
import struct
import time

import numpy as np
import pytest

from fednav.service import imu_batch, keys
from fednav.service.config import from_dict
from fednav.service.engine import VehicleEngine
from fednav.service.messages import ImuSample
from fednav.service.vehicle import VehicleLoop
from fednav.simulators.evaluate import CollectingSink, service_config
from fednav.simulators.scenario import load_scenario
from fednav.simulators.stream import Simulation

from .scenario_utils import SCENARIOS


def _rows(n: int, t0: float = 1000.0, dt: float = 0.005) -> np.ndarray:
    rng = np.random.default_rng(1)
    r = np.zeros((n, 8))
    r[:, 0] = t0 + dt * np.arange(1, n + 1)
    r[:, 1] = dt
    r[:, 2:5] = rng.normal(0, 1e-4, (n, 3))
    r[:, 5:8] = rng.normal(0, 1e-3, (n, 3)) + [0.0, 0.0, 9.8 * dt]
    return r


def test_layout_round_trip_and_declared_size():
    rows = _rows(7)
    payload = imu_batch.encode(rows)
    assert payload[:4] == b"FNIB" and len(payload) == 16 + 64 * 7
    magic, version, flags, count, reserved = struct.unpack_from("<4sHHII", payload)
    assert (magic, version, flags, count, reserved) == (b"FNIB", 1, 0, 7, 0)
    assert np.array_equal(imu_batch.decode(payload), rows)
    # the records are plain little-endian float64 (a client in any language can write them)
    assert struct.unpack_from("<8d", payload, 16) == tuple(rows[0])
    assert imu_batch.is_batch(payload) and not imu_batch.is_batch(b'{"t": 1.0}')
    assert imu_batch.ENCODING == "application/octet-stream;fednav.ImuBatch/1"


@pytest.mark.parametrize(
    ("mutate", "reason"),
    [
        (lambda p: p[:-1], "batch_truncated"),
        (lambda p: p[:10], "batch_truncated"),
        (lambda p: p + b"\0" * 64, "batch_size"),
        (lambda p: p[:4] + struct.pack("<H", 2) + p[6:], "batch_header"),
        (lambda p: p[:6] + struct.pack("<H", 1) + p[8:], "batch_header"),
        (lambda p: p[:8] + struct.pack("<I", 0) + p[12:], "batch_oversize"),
        (lambda p: p[:8] + struct.pack("<I", imu_batch.MAX_SAMPLES + 1) + p[12:], "batch_oversize"),
    ],
)
def test_refused_whole(mutate, reason):
    with pytest.raises(imu_batch.BatchError) as exc:
        imu_batch.decode(mutate(imu_batch.encode(_rows(5))))
    assert exc.value.reason == reason


def test_vectorised_validation_names_each_bad_record():
    rows = _rows(10).copy()
    rows[1, 3] = np.nan  # non-finite
    rows[3, 1] = 0.0  # interval out of range
    rows[5, 1] = 2.0  # interval out of range (MAX_DT_S = 1)
    rows[7, 2] = 1.0  # 1 rad in 5 ms: 200 rad/s, absurd
    rows[8, 7] = 10.0  # 10 m/s in 5 ms: 2000 m/s^2, absurd
    ok, bad = imu_batch.validate(rows)
    assert bad == {"non_finite": 1, "out_of_range": 2, "absurd_value": 2}
    assert list(np.flatnonzero(~ok)) == [1, 3, 5, 7, 8]
    # the same limits as the per-sample JSON model
    for i in range(10):
        r = rows[i]
        t, dt, a0, a1, a2, v0, v1, v2 = (float(v) for v in r)
        payload = (
            f'{{"t": {t!r}, "dt_s": {dt!r}, "dtheta_rad": [{a0!r}, {a1!r}, {a2!r}], '
            f'"dvel_mps": [{v0!r}, {v1!r}, {v2!r}]}}'
        ).replace("nan", "NaN")
        try:
            ImuSample.model_validate_json(payload)
            valid = True
        except ValueError:
            valid = False
        assert valid == bool(ok[i]), i


def test_small_batch_check_agrees_with_the_vectorised_one_at_the_limits(monkeypatch):
    """A batch of up to SMALL_BATCH records is passed by a plain loop first: whatever it passes,
    the vectorised check passes too, and a batch it does not pass gets the vectorised verdicts.
    Records on and one ulp around every limit (interval, time, rate, specific force), NaN and
    infinities, in random batches."""
    from fednav.service.messages import MAX_DT_S, MAX_RATE_RPS, MAX_SPECIFIC_FORCE_MPS2, T_MAX_S

    rng = np.random.default_rng(7)
    base = _rows(1)[0]

    def near(x):
        return [np.nextafter(x, -np.inf), x, np.nextafter(x, np.inf)]

    edge = []
    for dt in [*near(MAX_DT_S), np.nextafter(0.0, 1.0), 0.0, 0.005]:
        edge.append(np.r_[base[0], dt, base[2:]])
    edge.append(np.r_[base[0], 0.0, np.zeros(6)])  # no interval, no increments: out of range all the same
    for t in [*near(T_MAX_S), 0.0, -0.0, np.nextafter(0.0, -1.0)]:
        edge.append(np.r_[t, base[1:]])
    for col, limit in ((2, MAX_RATE_RPS), (5, MAX_SPECIFIC_FORCE_MPS2)):
        for norm in near(limit * 0.005):
            for axis in range(3):  # the whole norm on one axis, and spread over three
                r = base.copy()
                r[1] = 0.005
                r[col : col + 3] = 0.0
                r[col + axis] = norm
                edge.append(r)
            r = base.copy()
            r[1] = 0.005
            r[col : col + 3] = norm / np.sqrt(3.0)
            edge.append(r)
    for v in (np.nan, np.inf, -np.inf):
        r = base.copy()
        r[int(rng.integers(0, 8))] = v
        edge.append(r)
    edge = np.array(edge)
    with monkeypatch.context() as m:
        m.setattr(imu_batch, "SMALL_BATCH", 0)
        good = edge[imu_batch.validate(edge)[0]]  # the records the vectorised check passes
    assert 0 < len(good) < len(edge)
    all_good = 0
    for i in range(600):
        # batches of any records, of good ones only, and of good ones with one record of the
        # edge set among them (a failing record alone in a batch is the one the loop must see)
        pool = edge if i % 3 == 0 else good
        rows = pool[rng.integers(0, len(pool), int(rng.integers(1, imu_batch.SMALL_BATCH + 1)))]
        if i % 3 == 2:
            rows[int(rng.integers(0, len(rows)))] = edge[i // 3 % len(edge)]
        ok, bad = imu_batch.validate(rows)
        with monkeypatch.context() as m:
            m.setattr(imu_batch, "SMALL_BATCH", 0)  # the vectorised check only
            ok_v, bad_v = imu_batch.validate(rows)
        assert list(ok) == list(ok_v) and bad == bad_v, rows
        all_good += not bad
    assert 200 <= all_good < 600  # both paths taken


def _loop(cfg=None) -> VehicleLoop:
    sc = load_scenario(SCENARIOS / "demo_aircraft.toml")
    return VehicleLoop("v1", cfg or service_config(sc), CollectingSink())


def test_bad_record_loses_only_itself_and_time_rules_per_record():
    loop = _loop()
    rows = _rows(20).copy()
    rows[4, 5] = np.inf  # non-finite
    rows[9, 0] = rows[8, 0]  # same time as the previous record: duplicate
    rows[14, 0] = rows[12, 0] - 0.001  # behind the running time: time_backwards
    loop.process("imu", "main", imu_batch.encode(rows))
    assert loop.received == 20
    assert loop.counters == {"non_finite": 1, "duplicate": 1, "time_backwards": 1}
    assert loop.accepted == 17
    assert loop.engine.last_imu_t == rows[-1, 0]
    # a truncated batch is refused whole: one received, one refusal
    loop.process("imu", "main", imu_batch.encode(_rows(5, t0=rows[-1, 0]))[:-8])
    assert loop.received == 21 and loop.counters["batch_truncated"] == 1
    # an oversized payload (over the 1 MiB message limit) is refused before decoding
    loop.process("imu", "main", b"FNIB" + b"\0" * (1 << 20))
    assert loop.counters["oversize"] == 1
    # a second IMU id is refused for every record, as for JSON samples
    loop.process("imu", "other", imu_batch.encode(_rows(3, t0=2000.0)))
    assert loop.counters["unexpected_sensor"] == 3


def _run(scenario, batch: int, duration_s: float = 60.0):
    cfg = service_config(scenario)
    loop = VehicleLoop("v1", cfg, CollectingSink(keep_solutions=True))
    pending: list[ImuSample] = []
    t_end = None
    for key, msg in Simulation(scenario, seed=3):
        t_end = msg.t if t_end is None else t_end
        if msg.t - t_end > duration_s:
            break
        pk = keys.parse_input(key, cfg.prefix)
        if pk.kind == "imu" and batch > 1:
            pending.append(msg)
            if len(pending) == batch:
                loop.process("imu", pk.sensor_id, imu_batch.encode_samples(pending))
                pending = []
            continue
        loop.process(pk.kind, pk.sensor_id, msg.to_json() if pk.kind != "truth" else msg)
    return loop


def test_batches_give_the_same_solutions_as_json_samples():
    sc = load_scenario(SCENARIOS / "demo_aircraft.toml")
    json_loop, batch_loop = _run(sc, 1), _run(sc, 10)
    a = json_loop.engine.sink.records
    b = batch_loop.engine.sink.records
    assert a.keys() == b.keys() and a
    for name in a:
        sa, sb = a[name].solutions, b[name].solutions
        assert len(sa) == len(sb) > 500
        for x, y in zip(sa, sb, strict=True):
            assert x == y  # identical to the last bit (same floats, same order of operations)
        assert a[name].solutions[-1].status == "aided"
    assert json_loop.accepted == batch_loop.accepted
    assert json_loop.counters == batch_loop.counters


def _first_40_s(seed: int) -> tuple:
    """(service config, the first 40 s of (key, message)) of the demo aircraft's stream."""
    sc = load_scenario(SCENARIOS / "demo_aircraft.toml")
    msgs = []
    for key, msg in Simulation(sc, seed=seed):
        if msgs and msg.t - msgs[0][1].t > 40.0:
            break
        msgs.append((key, msg))
    return service_config(sc), msgs


def _irregular(msgs: list, rng: np.random.Generator) -> list:
    """The IMU samples of a stream with what a real or hostile sender does to them, at random
    places: duplicates, samples behind the running time, overlapping intervals, short gaps (a
    stretched sample), a gap beyond max_imu_gap_s (the INS lost, re-initialised), samples delayed
    past the aiding they precede."""
    out = []
    imu = [i for i, (_, m) in enumerate(msgs) if isinstance(m, ImuSample)]
    kinds = ["dup", "back", "overlap", "drop", "swap"]
    chosen = {int(i): str(rng.choice(kinds)) for i in rng.choice(imu, 40)}
    big_gap = imu[len(imu) // 2]
    skip = set(range(big_gap, big_gap + 60))  # 0.3 s of IMU lost at 200 Hz
    for i, (key, m) in enumerate(msgs):
        if i in skip and isinstance(m, ImuSample):
            continue
        what = chosen.get(i)
        if what is None or not isinstance(m, ImuSample):
            out.append((key, m))
        elif what == "dup":
            out += [(key, m), (key, m)]
        elif what == "back":
            out += [(key, m), (key, m.model_copy(update={"t": m.t - 0.0123}))]
        elif what == "overlap":
            out.append((key, m.model_copy(update={"t": m.t - 0.6 * m.dt_s})))
        elif what == "drop":
            pass  # one sample lost: the next one is stretched over the gap
        elif what == "swap" and out:
            out.insert(len(out) - 1, (key, m))  # arrives before its predecessor (an aiding in between)
    return out


def _assert_same_vehicle(run: VehicleLoop, ref: VehicleLoop) -> None:
    """The same solutions to the last bit (more than 200 per pipeline), the same counts, the same
    stream bookkeeping (each stream's last time and interval)."""
    a, b = ref.engine.sink.records, run.engine.sink.records
    assert a.keys() == b.keys() and a
    for name in a:
        assert len(a[name].solutions) == len(b[name].solutions) > 200
        assert a[name].solutions == b[name].solutions
    assert run.counters == ref.counters
    assert run.accepted == ref.accepted
    assert run.engine.streams == ref.engine.streams


def _feed(cfg, msgs: list, batch: int, as_json: bool) -> VehicleLoop:
    """The messages with the IMU samples grouped by ``batch`` as a sender batches them (an aiding
    message that arrives while samples wait in the sender's batch goes ahead of them), then each
    group published as one ImuBatch, or (``as_json``) as its samples one by one in the same order:
    the same arrivals, through the batch path or the per-sample path."""
    loop = VehicleLoop("v1", cfg, CollectingSink(keep_solutions=True))
    pending: list[ImuSample] = []
    for key, msg in msgs:
        pk = keys.parse_input(key, cfg.prefix)
        if pk.kind == "imu":
            pending.append(msg)
            if len(pending) == batch:
                if as_json:
                    for m in pending:
                        loop.process("imu", pk.sensor_id, m.to_json())
                else:
                    loop.process("imu", pk.sensor_id, imu_batch.encode_samples(pending))
                pending = []
            continue
        loop.process(pk.kind, pk.sensor_id, msg.to_json() if pk.kind != "truth" else msg)
    return loop


@pytest.mark.parametrize("seed", [5, 6])
def test_the_usual_imu_step_takes_an_irregular_stream_as_the_general_path(seed, monkeypatch):
    """The one-step path of the usual IMU interval (service/engine.py ``_usual_imu``, taken by
    JSON samples, and ``_usual_run``, by batch records) against the general path (the rules'
    verdict, then ``_imu_values``) on every irregularity: the same solutions to the last bit, the
    same counts; and batches against JSON samples with the same arrivals."""
    cfg, msgs = _first_40_s(seed)
    msgs = _irregular(msgs, np.random.default_rng(seed))
    runs = [_feed(cfg, msgs, 7, as_json=True), _feed(cfg, msgs, 7, as_json=False)]
    with monkeypatch.context() as m:
        m.setattr(VehicleEngine, "_usual_imu", lambda self, *args: False)  # the general path only
        m.setattr(VehicleEngine, "_usual_run", lambda self, *args: 0)
        runs += [_feed(cfg, msgs, 7, as_json=True), _feed(cfg, msgs, 7, as_json=False)]
    ref = runs[2]
    assert ref.counters != {}
    for reason in ("duplicate", "time_backwards", "overlap", "imu_gap"):
        assert ref.counters.get(reason, 0) > 0, (reason, ref.counters)
    for run in (runs[0], runs[1], runs[3]):
        _assert_same_vehicle(run, ref)


def _feed_runs(cfg, msgs: list, rng: np.random.Generator | None) -> VehicleLoop:
    """The messages as JSON, one by one through :meth:`VehicleLoop.process` (``rng`` None), or
    as the service's intake hands a loaded drain over: the routed inputs of drains of random
    sizes cut into runs by :func:`service.app.json_imu_runs` (with a second vehicle's inputs
    between them), each run of JSON IMU samples through :meth:`VehicleLoop.process_imu_json`."""
    from fednav.service.app import json_imu_runs

    loop = VehicleLoop("v1", cfg, CollectingSink(keep_solutions=True))
    other = VehicleLoop("v2", cfg, CollectingSink(keep_solutions=True))
    items = []
    for key, msg in msgs:
        pk = keys.parse_input(key, cfg.prefix)
        payload = msg.to_json() if pk.kind != "truth" else msg
        items.append((time.monotonic(), pk.kind, pk.sensor_id, payload))
    if rng is None:
        for item in items:
            loop.process(*item[1:], item[0])
        return loop
    i = 0
    while i < len(items):
        n = int(rng.integers(1, 40))
        drain = []
        for item in items[i : i + n]:
            drain.append((loop, item))
            if rng.random() < 0.3:  # another vehicle's input in between: runs are per vehicle
                drain.append((other, (item[0], "imu", "", b'{"t": 1.0}')))
        i += n
        for w, run in json_imu_runs(drain):
            if len(run) > 1:
                w.process_imu_json(run[0][2], run)
            else:
                w.process(*run[0][1:], run[0][0])
    return loop


@pytest.mark.parametrize("seed", [5, 6])
def test_json_samples_of_a_drain_taken_together_change_nothing(seed):
    """A loaded service's drain: a vehicle's consecutive JSON IMU samples of one stream are run
    together (service/app.py ``json_imu_runs``, ``VehicleLoop.process_imu_json``). On an irregular
    stream with bad samples among the good (NaN, an implausible rate, a malformed document): the
    same solutions to the last bit, the same counts and stream bookkeeping as one by one."""
    cfg, msgs = _first_40_s(seed)
    rng = np.random.default_rng(seed)
    msgs = _irregular(msgs, rng)

    class Raw:  # a payload that is not a valid ImuSample
        def __init__(self, text: bytes):
            self.text = text
            self.t = 0.0

        def to_json(self) -> bytes:
            return self.text

    imu_key = next(k for k, m in msgs if isinstance(m, ImuSample))
    bad = [
        b'{"t": 5.0, "dt_s": 0.005, "dtheta_rad": [NaN, 0, 0], "dvel_mps": [0, 0, 0.05]}',
        b'{"t": 5.0, "dt_s": 0.005, "dtheta_rad": [1.0, 0, 0], "dvel_mps": [0, 0, 0.05]}',
        b'{"t": 5.0, "dt_s": 0.005',
        b'{"t": 5.0, "dt_s": 0.005, "dtheta_rad": [0, 0, 0], "dvel_mps": [0, 0, 0.05], "x": 1}',
    ]
    for j, i in enumerate(rng.choice(len(msgs), 12, replace=False)):
        msgs.insert(int(i), (imu_key, Raw(bad[j % len(bad)])))
    ref = _feed_runs(cfg, msgs, None)
    run = _feed_runs(cfg, msgs, np.random.default_rng(seed + 100))
    for reason in (
        "duplicate",
        "time_backwards",
        "overlap",
        "non_finite",
        "absurd_value",
        "malformed_json",
        "schema",
    ):
        assert ref.counters.get(reason, 0) > 0, (reason, ref.counters)
    _assert_same_vehicle(run, ref)
    assert run.received == ref.received
    assert len(run.latency_s) == len(ref.latency_s)


def test_json_imu_runs_keep_each_vehicles_order():
    """Runs are cut by any other input of the same vehicle and by another IMU stream; a batch
    payload, a rejection and a decoded message are never part of one."""
    from fednav.service.app import json_imu_runs

    j = b'{"t": 1}'
    drain = [
        ("a", (0, "imu", "", j)),
        ("b", (1, "imu", "", j)),
        ("a", (2, "imu", "", j)),
        ("b", (3, "gnss_fix", "", j)),
        ("a", (4, "imu", "", j)),
        ("b", (5, "imu", "", j)),
        ("a", (6, "imu", "aux", j)),
        ("a", (7, "imu", "aux", imu_batch.MAGIC + b"...")),
        ("a", (8, "imu", "aux", j)),
        ("a", (9, None, "oversize", j)),
        ("a", (10, "imu", "aux", j)),
        ("b", (11, "imu", "", j)),
    ]
    got = [(w, [it[0] for it in run]) for w, run in json_imu_runs(drain)]
    assert got == [
        ("a", [0, 2, 4]),
        ("b", [1]),
        ("b", [3]),
        ("b", [5, 11]),
        ("a", [6]),
        ("a", [7]),
        ("a", [8]),
        ("a", [9]),
        ("a", [10]),
    ]


@pytest.mark.integration
def test_service_takes_batches_and_counts_bad_ones(tmp_path):
    """Real processes: the simulator publishes ImuBatches (the default), the service navigates
    ('aided'); a plain Zenoh client's truncated batch and a batch with one NaN record are counted."""
    from fednav.simulators.processes import free_port, query_status, start_service, start_sim, wait_idle

    from .plain_zenoh import client as zenoh_client

    scenario = SCENARIOS / "demo_aircraft.toml"
    port = free_port()
    svc = start_service(port, config=scenario, table="service")
    try:
        sim = start_sim(port, scenario, speed=0.0)
        assert sim.wait(timeout=120) == 0, sim.output()
        st = wait_idle(port, timeout_s=60)
        h = st["health"]
        assert h["pipelines"]["lc"]["status"] in ("aided", "coasting"), h
        assert h["pipelines"]["lc"]["updates"] > 20
        assert h["received"] >= 30000 and not {"non_finite", "batch_truncated"} & set(h["rejected"])
        t_last = h["t"]
        s = zenoh_client(port)
        try:
            key = keys.sensor("v1", "imu", "main")
            rows = _rows(10, t0=t_last)
            rows[3, 6] = math.nan
            pub = s.declare_publisher(key)
            deadline = time.monotonic() + 10
            while not pub.matching_status.matching and time.monotonic() < deadline:
                time.sleep(0.01)
            pub.put(imu_batch.encode(rows))
            pub.put(imu_batch.encode(_rows(4, t0=rows[-1, 0]))[:-3])
            time.sleep(1.0)
        finally:
            s.close()
        h2 = query_status(port)["health"]
        assert h2["rejected"].get("non_finite") == 1
        assert h2["rejected"].get("batch_truncated") == 1
        assert h2["received"] - h["received"] == 11  # 10 records + 1 refused batch
    finally:
        svc.signal(signal.SIGTERM)
        assert svc.wait(timeout=60) == 0, svc.output()


def test_max_vehicles_default_is_a_fleet():
    assert from_dict({}).intake.max_vehicles == 1000
