"""ROS 2 bridge over real processes: fednav-service with a [ros2] table on loopback Zenoh; the test
is the robot: a plain Zenoh client publishing sensor_msgs/Imu, NavSatFix and
TwistWithCovarianceStamped in CDR under rmw_zenoh keys (a 40 s straight flight of the demo aircraft,
no InitialNav, no Truth); another plain client receives nav_msgs/Odometry, sensor_msgs/NavSatFix,
tf2_msgs/TFMessage and diagnostic_msgs/DiagnosticArray and decodes them with rosbags; the .rrd reads
back with Rerun's reader."""

from __future__ import annotations

import re
import signal
import struct
import threading
import time
from pathlib import Path

import numpy as np
import pytest

from fednav.service import earth

from .plain_zenoh import client

pytest.importorskip("rosbags")
pytestmark = pytest.mark.integration
ROOT = Path(__file__).resolve().parents[1]
DEMO = ROOT / "simulators" / "scenarios" / "demo_aircraft.toml"
DURATION_S = 40.0
#: x real time: fast, and slow enough that the service keeps up (each topic is its own subscription)
SPEED = 5.0


def short_demo(tmp_path: Path) -> Path:
    text = DEMO.read_text().replace("duration_s = 300.0", f"duration_s = {DURATION_S}", 1)
    text = re.sub(r"(?s)\[\[segments\]\].*?(?=\n\[)", "", text)  # straight and level at 120 m/s
    p = tmp_path / "demo_short.toml"
    p.write_text(text)
    return p


SERVICE_TOML = """
vehicles = ["v1"]
pipelines = [{ name = "lc", kind = "loosely_coupled" }]
[imu]
gyro_bias_dph = 0.01
accel_bias_ug = 50.0
arw_dpsh = 0.001
vrw_ugpsHz = 5.0
[ros2]
carrier = "rmw_zenoh"
vehicle = "v1"
imu_integration = "rectangle"
inputs = [
  { topic = "/imu/data", type = "sensor_msgs/msg/Imu", sensor_id = "main" },
  { topic = "/gnss/fix", type = "sensor_msgs/msg/NavSatFix", sensor_id = "main" },
  { topic = "/gnss/vel", type = "geometry_msgs/msg/TwistWithCovarianceStamped", sensor_id = "main" },
  # a topic the robot does not publish (a typo, a sensor not fitted): named once, noted in Health
  { topic = "/baro/pressur", type = "sensor_msgs/msg/FluidPressure", sensor_id = "main" },
]
[ros2.outputs]
tf = true
"""


@pytest.fixture(scope="module")
def ros_run(tmp_path_factory):
    from fednav.service.transport import ros2
    from fednav.simulators.processes import free_port, query_status, start_service, wait_idle
    from fednav.simulators.ros2_publish import example_config, publish, ros_samples
    from fednav.simulators.scenario import load_scenario

    tmp = tmp_path_factory.mktemp("ros2")
    sc = load_scenario(short_demo(tmp))
    conf = tmp / "service.toml"
    conf.write_text(SERVICE_TOML)
    rrd = tmp / "ros2.rrd"
    cfg = example_config()
    samples = list(ros_samples(sc, 1, cfg))
    from fednav.simulators.stream import simulate

    truth = {round(m.t, 3): m for k, m in simulate(sc, seed=1) if k.endswith("/truth")}

    port = free_port()
    svc = start_service(port, config=conf, rrd=rrd)
    got: list[tuple[str, bytes, bytes | None]] = []
    lock = threading.Lock()

    def cb(sample):
        att = sample.attachment.to_bytes() if sample.attachment is not None else None
        with lock:
            got.append((str(sample.key_expr), sample.payload.to_bytes(), att))

    sub_session = client(port)
    subs = [sub_session.declare_subscriber(k, cb) for k in ("0/fednav/**", "0/diagnostics/**", "0/tf/**")]
    pub_session = client(port)
    try:
        time.sleep(0.5)
        n = publish(pub_session, samples, speed=SPEED)
        # garbage on the IMU topic and a Twist-typed payload truncated: counted, never a crash
        imu_key = ros2.topic_key(cfg, "/imu/data", "sensor_msgs/msg/Imu")
        pub_session.put(imu_key, b"\x00\x01\x00\x00garbage")
        pub_session.put(imu_key, samples[0][1][:20])
        status = wait_idle(port, timeout_s=120)
        assert status is not None, "service did not become idle"
        time.sleep(1.5)  # one more health period: DiagnosticArray with the final counts
        status = query_status(port)
        tokens = [
            str(r.ok.key_expr) for r in sub_session.liveliness().get("@ros2_lv/0/**", timeout=5.0) if r.ok
        ]
    finally:
        svc.signal(signal.SIGTERM)
        rc = svc.wait(timeout=60)
        for s in subs:
            s.undeclare()
        sub_session.close()
        pub_session.close()
    with lock:
        items = list(got)
    return {
        "items": items,
        "rc": rc,
        "out": svc.output(),
        "n": n,
        "status": status,
        "truth": truth,
        "rrd": rrd,
        "samples": samples,
        "tokens": tokens,
    }


def _decode(items, prefix: str, msgtype: str):
    from fednav.service.transport import ros2

    store = ros2.typestore("jazzy")
    return [(k, store.deserialize_cdr(p, msgtype), a) for k, p, a in items if k.startswith(prefix)]


def test_service_takes_ros_input_through_the_intake(ros_run):
    assert ros_run["rc"] == 0, ros_run["out"]
    h = ros_run["status"]["health"]
    n_imu = sum(1 for k, _, _ in ros_run["samples"] if "/imu/" in k)
    n_fix = sum(1 for k, _, _ in ros_run["samples"] if "/gnss/fix/" in k)
    # every Imu but the first (it opens the interval), every fix paired with its Twist, 2 bad samples
    assert h["received"] == (n_imu - 1) + n_fix + 2, h
    assert h["rejected"].get("bad_cdr") == 2, h["rejected"]
    # everything else accepted: the intake delivers the three topics in header.stamp order
    assert h["accepted"] == (n_imu - 1) + n_fix, h["rejected"]
    # aided while the data flowed; queried after the input stopped, the wall-clock stale rule (2 s
    # without input) truthfully turns it to coasting when the machine is slow to go idle. Either
    # means it was aided (a pipeline never aided is "unaided"); the diagnostics below show OK.
    assert h["pipelines"]["lc"]["status"] in ("aided", "coasting"), h["pipelines"]["lc"]
    assert h["pipelines"]["lc"]["updates"] >= 30


def test_odometry_in_cdr_with_frames_covariance_and_rmw_attachment(ros_run):
    from fednav.service.transport import ros2
    from fednav.simulators.ros2_publish import example_config

    odo = _decode(ros_run["items"], "0/fednav/lc/odometry/", "nav_msgs/msg/Odometry")
    assert len(odo) >= 0.8 * DURATION_S * 10, len(odo)
    key = odo[0][0]
    assert key == ros2.topic_key(example_config(), "/fednav/lc/odometry", "nav_msgs/msg/Odometry")
    seqs = []
    for _, m, att in odo:
        assert (m.header.frame_id, m.child_frame_id) == ("map", "base_link")
        cov = m.pose.covariance.reshape(6, 6)
        assert np.allclose(cov, cov.T) and np.all(np.linalg.eigvalsh(cov) > 0)
        q = np.array(
            [
                m.pose.pose.orientation.x,
                m.pose.pose.orientation.y,
                m.pose.pose.orientation.z,
                m.pose.pose.orientation.w,
            ]
        )
        assert abs(np.linalg.norm(q) - 1.0) < 1e-9
        assert att is not None and len(att) == 33 and att[16] == 16  # seq, timestamp, GID
        seqs.append(int.from_bytes(att[:8], "little", signed=True))
    assert seqs == list(range(1, len(seqs) + 1))
    last = odo[-1][1]
    # straight flight at heading 45 deg, 120 m/s. The in-motion alignment takes the heading of the
    # GNSS velocity; straight flight hardly observes yaw, so the check is against the filter's own
    # yaw sigma (the pose covariance's rotation-about-Z entry): ENU yaw = 90 - 45 deg, and the lateral
    # velocity in the child frame ~ 120 m/s x yaw error
    sig_yaw_deg = np.degrees(np.sqrt(last.pose.covariance.reshape(6, 6)[5, 5]))
    q = last.pose.pose.orientation
    yaw = np.degrees(np.arctan2(2 * (q.w * q.z + q.x * q.y), 1 - 2 * (q.y**2 + q.z**2)))
    assert abs(yaw - 45.0) < 3.0 * sig_yaw_deg + 0.05, (yaw, sig_yaw_deg)
    assert abs(last.twist.twist.linear.x - 120.0) < 0.5
    v_left = last.twist.twist.linear.y
    assert v_left == pytest.approx(-120.0 * np.radians(yaw - 45.0), abs=0.5), (v_left, yaw)


def test_navsatfix_out_follows_the_truth_and_tf_and_diagnostics_arrive(ros_run):
    from fednav.service.transport import ros2

    fixes = _decode(ros_run["items"], "0/fednav/lc/fix/", "sensor_msgs/msg/NavSatFix")
    assert len(fixes) >= 0.8 * DURATION_S * 10
    truth = ros_run["truth"]
    errs = []
    for _, m, _ in fixes:
        t = ros2.stamp_to_t(m.header.stamp.sec, m.header.stamp.nanosec)
        tr = truth.get(round(t, 3))
        if tr is None or t - min(truth) < 10.0:
            continue
        d = earth.llh_delta_to_enu_m(
            np.radians([m.latitude - tr.lat_deg, m.longitude - tr.lon_deg, 0.0])
            + [0, 0, m.altitude - tr.height_m],
            np.radians(tr.lat_deg),
            tr.height_m,
        )
        errs.append(d)
        assert m.status.status == 0 and m.position_covariance_type == 3
    errs = np.array(errs)
    assert len(errs) >= 200
    assert np.sqrt(np.mean(np.sum(errs[:, :2] ** 2, axis=1))) < 10.0  # GNSS 10 m per axis, 1 Hz
    tf = _decode(ros_run["items"], "0/tf/", "tf2_msgs/msg/TFMessage")
    assert len(tf) == len(_decode(ros_run["items"], "0/fednav/lc/odometry/", "nav_msgs/msg/Odometry"))
    assert tf[-1][1].transforms[0].header.frame_id == "map"
    diags = _decode(ros_run["items"], "0/diagnostics/", "diagnostic_msgs/msg/DiagnosticArray")
    assert diags, "no DiagnosticArray"
    final = {s.name: s for s in diags[-1][1].status}
    assert final["fednav/v1/lc"].level in (0, 1) and final["fednav/v1/lc"].message in ("aided", "coasting")
    assert any(s.name == "fednav/v1/lc" and s.level == 0 for _, d, _ in diags for s in d.status)
    svc_vals = {kv.key: kv.value for kv in final["fednav/v1/service"].values}
    assert svc_vals["rejected.bad_cdr"] == "2"


def test_recording_reads_back(ros_run):
    from fednav.dashboards.inspect import read_series

    _, data = read_series(ros_run["rrd"])
    assert any(p.startswith("/v1/lc/solution") for p in data), sorted(data)[:20]


def test_output_stamps_are_the_input_imu_stamps(ros_run):
    imu_stamps = {struct.unpack_from("<iI", p, 4) for k, p, _ in ros_run["samples"] if "/imu/" in k}
    for prefix, msgtype in (
        ("0/fednav/lc/odometry/", "nav_msgs/msg/Odometry"),
        ("0/fednav/lc/fix/", "sensor_msgs/msg/NavSatFix"),
    ):
        out = _decode(ros_run["items"], prefix, msgtype)
        assert out and all((m.header.stamp.sec, m.header.stamp.nanosec) in imu_stamps for _, m, _ in out)


def test_each_publisher_attaches_the_gid_of_its_graph_token(ros_run):
    from fednav.service.transport import ros2

    toks = [t for t in ros_run["tokens"] if t.split("/")[5] == "MP"]
    gid_of = {t.split("/")[9]: ros2.entity_gid(t) for t in toks}
    assert len(set(gid_of.values())) == len(toks) == 4
    for topic, prefix in (("%fednav%lc%odometry", "0/fednav/lc/odometry/"), ("%tf", "0/tf/")):
        atts = {a[17:] for k, _, a in ros_run["items"] if k.startswith(prefix)}
        assert atts == {gid_of[topic]}, topic


def test_rmw_zenoh_graph_tokens_declared(ros_run):
    toks = ros_run["tokens"]
    # rmw_zenoh's QoS chunk: reliable, volatile, keep last 10 (depth 42, rmw_zenoh's default, is empty)
    assert all(t.endswith("/::,10:,:,:,,") for t in toks if t.split("/")[5] != "NN"), toks
    kinds = sorted(t.split("/")[5] for t in toks)
    # one node; publishers: odometry, fix, tf, diagnostics; subscriptions: the four inputs
    assert kinds == ["MP"] * 4 + ["MS"] * 4 + ["NN"], toks
    topics = {t.split("/")[9] for t in toks if t.split("/")[5] != "NN"}
    assert topics == {
        "%fednav%lc%odometry",
        "%fednav%lc%fix",
        "%tf",
        "%diagnostics",
        "%imu%data",
        "%gnss%fix",
        "%gnss%vel",
        "%baro%pressur",
    }


def test_a_configured_topic_without_samples_is_named_in_the_log_and_health(ros_run):
    out = ros_run["out"]
    assert out.count("no sample on /baro/pressur") == 1, out[-3000:]
    notes = ros_run["status"]["health"]["notes"]
    assert notes.get("silent_topic:/baro/pressur") == 1, notes
    silent = [k for k in notes if k.startswith("silent_topic:")]
    assert silent == ["silent_topic:/baro/pressur"], notes
