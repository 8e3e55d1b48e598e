"""ROS 2 bridge over real processes, a robot without a velocity topic: fednav-service runs the stock
``service/configs/ros2.toml`` (its [ros2] table lists Imu, NavSatFix and a Twist topic); the test is
a robot standing still that publishes only sensor_msgs/Imu (100 Hz) and sensor_msgs/NavSatFix
(1 Hz), CDR under rmw_zenoh keys, stamped in integer nanoseconds like real drivers (the fixes off
the IMU's grid), and never a Twist. Each fix goes on position-only once the stamp time passes
``twist_wait_s``; the service aligns statically and the loosely coupled pipeline reaches 'aided'.
The Odometry it republishes carries the input IMU stamps to the nanosecond."""

from __future__ import annotations

import signal
import struct
import threading
import time
from pathlib import Path
from types import SimpleNamespace

import numpy as np
import pytest

from fednav.service import earth

from .plain_zenoh import client

pytest.importorskip("rosbags")
pytestmark = pytest.mark.integration
ROOT = Path(__file__).resolve().parents[1]
STOCK = ROOT / "service" / "configs" / "ros2.toml"
#: the static alignment averages [init] align_time_s (60 s by default), then 20 s of aiding
DURATION_S = 80.0
SPEED = 20.0
IMU_PERIOD_NS = 10_000_000
T0_NS = 1_732_512_345_123_456_789  # unix ns: 2024-11-25, a driver's stamp
FIX_OFFSET_NS = 3_141_593  # the receiver's epochs are not on the IMU's grid
LAT_DEG, LON_DEG, H_M = 40.1, 118.6, 50.0


def robot_samples(cfg, seed: int = 7) -> list[tuple[str, bytes, SimpleNamespace]]:
    """(key, CDR, object with the stamp time ``t`` in s for pacing) of a level robot facing north,
    standing still: gravity and the earth's rate in body FLU plus white noise; fixes with 1.5 m noise."""
    from fednav.service.transport import ros2

    store = ros2.typestore(cfg.distro)
    T = store.types
    rng = np.random.default_rng(seed)
    lat = np.radians(LAT_DEG)
    rfu_to_flu = ros2.FLU_TO_RFU.T
    f_flu = rfu_to_flu @ np.array([0.0, 0.0, earth.gravity_normal(lat, H_M)])  # heading north: RFU = ENU
    w_flu = rfu_to_flu @ earth.earth_rate_n(lat)
    v3 = T["geometry_msgs/msg/Vector3"]
    imu_key = ros2.topic_key(cfg, "/imu/data", "sensor_msgs/msg/Imu")
    fix_key = ros2.topic_key(cfg, "/gnss/fix", "sensor_msgs/msg/NavSatFix")

    def header(stamp_ns: int, frame: str):
        sec, ns = divmod(stamp_ns, 1_000_000_000)
        return T["std_msgs/msg/Header"](
            stamp=T["builtin_interfaces/msg/Time"](sec=sec, nanosec=ns), frame_id=frame
        )

    out = []
    for k in range(int(DURATION_S * 1e9 / IMU_PERIOD_NS) + 1):
        stamp = T0_NS + k * IMU_PERIOD_NS
        w = w_flu + rng.normal(0.0, 2e-6, 3)
        a = f_flu + rng.normal(0.0, 2e-3, 3)
        imu = T["sensor_msgs/msg/Imu"](
            header=header(stamp, "imu_link"),
            orientation=T["geometry_msgs/msg/Quaternion"](x=0.0, y=0.0, z=0.0, w=1.0),
            orientation_covariance=np.r_[-1.0, np.zeros(8)],
            angular_velocity=v3(x=w[0], y=w[1], z=w[2]),
            angular_velocity_covariance=np.zeros(9),
            linear_acceleration=v3(x=a[0], y=a[1], z=a[2]),
            linear_acceleration_covariance=np.zeros(9),
        )
        out.append((stamp, imu_key, bytes(store.serialize_cdr(imu, imu.__msgtype__))))
        if k % 100 == 37:
            d = earth.enu_m_to_llh_delta(rng.normal(0.0, [1.5, 1.5, 3.0]), lat, H_M)
            fix = T["sensor_msgs/msg/NavSatFix"](
                header=header(stamp + FIX_OFFSET_NS, "gnss"),
                status=T["sensor_msgs/msg/NavSatStatus"](status=0, service=1),
                latitude=LAT_DEG + np.degrees(d[0]),
                longitude=LON_DEG + np.degrees(d[1]),
                altitude=H_M + d[2],
                position_covariance=np.diag([2.25, 2.25, 9.0]).reshape(9),
                position_covariance_type=2,
            )
            out.append((stamp + FIX_OFFSET_NS, fix_key, bytes(store.serialize_cdr(fix, fix.__msgtype__))))
    out.sort(key=lambda s: s[0])
    return [(key, payload, SimpleNamespace(t=stamp * 1e-9)) for stamp, key, payload in out]


@pytest.fixture(scope="module")
def fix_only_run(tmp_path_factory):
    from fednav.service import config as config_mod
    from fednav.simulators.processes import free_port, query_status, start_service, wait_idle
    from fednav.simulators.ros2_publish import publish

    cfg = config_mod.load(STOCK).ros2
    assert any(i.type.endswith("TwistWithCovarianceStamped") for i in cfg.inputs)  # configured, never sent
    samples = robot_samples(cfg)
    port = free_port()
    svc = start_service(port, config=STOCK)
    got: list[tuple[str, bytes]] = []
    lock = threading.Lock()

    def cb(sample):
        with lock:
            got.append((str(sample.key_expr), sample.payload.to_bytes()))

    sub_session = client(port)
    subs = [sub_session.declare_subscriber(k, cb) for k in ("0/fednav/**", "0/diagnostics/**")]
    pub_session = client(port)
    try:
        time.sleep(0.5)
        publish(pub_session, samples, speed=SPEED)
        status = query_status(port, vehicle="robot1")  # right after the input: before the stale rule
        idle = wait_idle(port, vehicle="robot1", timeout_s=120)
        assert idle is not None, "service did not become idle"
        time.sleep(1.5)  # one more health period
    finally:
        svc.signal(signal.SIGTERM)
        rc = svc.wait(timeout=60)
        for s in subs:
            s.undeclare()
        sub_session.close()
        pub_session.close()
    with lock:
        items = list(got)
    return {"items": items, "rc": rc, "out": svc.output(), "status": status, "idle": idle, "samples": samples}


def test_imu_and_navsatfix_alone_reach_aided_with_the_stock_config(fix_only_run):
    from fednav.service.transport import ros2

    run = fix_only_run
    assert run["rc"] == 0, run["out"]
    n_imu = sum(1 for k, _, _ in run["samples"] if "/imu/" in k)
    n_fix = sum(1 for k, _, _ in run["samples"] if "/gnss/fix/" in k)
    h = run["idle"]["health"]
    # every fix went on (position-only: no Twist ever came), every Imu but the first; the fixes of
    # the static alignment's 60 s served it and are counted not_initialised, all others accepted
    assert h["received"] == (n_imu - 1) + n_fix, h
    rejected = {k: v for k, v in h["rejected"].items() if v}
    assert set(rejected) <= {"not_initialised"} and rejected.get("not_initialised", 0) <= 61, rejected
    assert h["accepted"] == (n_imu - 1) + n_fix - rejected.get("not_initialised", 0)
    assert n_fix - rejected.get("not_initialised", 0) >= 15  # fixes taken as aiding
    # counted, not silent: every fix went on position-only (Health notes of the bridge's vehicle)
    assert h["notes"].get("fix_without_velocity", 0) >= n_fix - 1, h["notes"]
    lc = run["status"]["health"]["pipelines"]["lc"]
    assert lc["status"] == "aided", lc
    assert run["idle"]["health"]["pipelines"]["lc"]["updates"] >= 15
    store = ros2.typestore("jazzy")
    diags = [
        store.deserialize_cdr(p, "diagnostic_msgs/msg/DiagnosticArray")
        for k, p in run["items"]
        if k.startswith("0/diagnostics/")
    ]
    assert any(
        s.name == "fednav/robot1/lc" and s.level == 0 and s.message == "aided"
        for d in diags
        for s in d.status
    )


def test_odometry_stamps_are_the_input_imu_stamps_to_the_nanosecond(fix_only_run):
    from fednav.service.transport import ros2

    store = ros2.typestore("jazzy")
    imu_stamps = {struct.unpack_from("<iI", p, 4) for k, p, _ in fix_only_run["samples"] if "/imu/" in k}
    odo = [
        store.deserialize_cdr(p, "nav_msgs/msg/Odometry")
        for k, p in fix_only_run["items"]
        if k.startswith("0/fednav/lc/odometry/")
    ]
    assert len(odo) >= 10 * 15, len(odo)  # 10 Hz from the alignment on
    stamps = [(m.header.stamp.sec, m.header.stamp.nanosec) for m in odo]
    assert all(s in imu_stamps for s in stamps), [s for s in stamps if s not in imu_stamps][:5]
    assert all(ns % 1_000_000 == 456_789 for _, ns in stamps)  # nanoseconds that no float holds
    # the map-frame position of a robot standing still stays near the datum (position-only aiding)
    last = odo[-1].pose.pose.position
    assert np.hypot(last.x, last.y) < 5.0
