"""ROS 2 bridge (service/transport/ros2.py): CDR in and out, key formats, time, axes and covariance
conventions, configuration errors."""

from __future__ import annotations

import math
import struct
from fractions import Fraction

import numpy as np
import pytest

from fednav.service import config as config_mod
from fednav.service import earth
from fednav.service.messages import GnssFix, Health, ImuSample, PipelineHealth
from fednav.service.ros2_config import Ros2Config
from fednav.service.transport import ros2

pytest.importorskip("rosbags")

STORE = ros2.typestore("jazzy")
T = STORE.types
T0_UNIX = 1_700_000_000


def cfg(**kw) -> Ros2Config:
    base = {
        "vehicle": "v1",
        "inputs": [
            {"topic": "/imu/data", "type": "sensor_msgs/msg/Imu", "sensor_id": "main"},
            {"topic": "/gnss/fix", "type": "sensor_msgs/msg/NavSatFix", "sensor_id": "rx"},
            {"topic": "/gnss/vel", "type": "geometry_msgs/msg/TwistWithCovarianceStamped", "sensor_id": "rx"},
        ],
    }
    return Ros2Config.model_validate(base | kw)


def header(unix_s: float, frame: str = "base_link"):
    """Stamp of ``unix_s`` (T0_UNIX + a fraction: the fraction is taken apart from the seconds)."""
    sec = math.floor(unix_s)
    frac = round(unix_s - T0_UNIX, 6) - (sec - T0_UNIX)
    return T["std_msgs/msg/Header"](
        stamp=T["builtin_interfaces/msg/Time"](sec=sec, nanosec=round(frac * 1e9)), frame_id=frame
    )


def imu_msg(unix_s, w, a):
    v3 = T["geometry_msgs/msg/Vector3"]
    return T["sensor_msgs/msg/Imu"](
        header=header(unix_s),
        orientation=T["geometry_msgs/msg/Quaternion"](x=0.0, y=0.0, z=0.0, w=1.0),
        orientation_covariance=np.r_[-1.0, np.zeros(8)],
        angular_velocity=v3(x=w[0], y=w[1], z=w[2]),
        angular_velocity_covariance=np.zeros(9),
        linear_acceleration=v3(x=a[0], y=a[1], z=a[2]),
        linear_acceleration_covariance=np.zeros(9),
    )


def navsat_msg(unix_s, lat, lon, alt, cov=None, status=0, cov_type=2):
    return T["sensor_msgs/msg/NavSatFix"](
        header=header(unix_s, "gnss"),
        status=T["sensor_msgs/msg/NavSatStatus"](status=status, service=1),
        latitude=lat,
        longitude=lon,
        altitude=alt,
        position_covariance=np.zeros(9) if cov is None else np.asarray(cov, dtype=float),
        position_covariance_type=cov_type,
    )


def twist_msg(unix_s, v, var=(0.01, 0.04, 0.09)):
    cov = np.zeros(36)
    cov[0], cov[7], cov[14] = var
    v3 = T["geometry_msgs/msg/Vector3"]
    return T["geometry_msgs/msg/TwistWithCovarianceStamped"](
        header=header(unix_s, "gnss"),
        twist=T["geometry_msgs/msg/TwistWithCovariance"](
            twist=T["geometry_msgs/msg/Twist"](
                linear=v3(x=v[0], y=v[1], z=v[2]), angular=v3(x=0.0, y=0.0, z=0.0)
            ),
            covariance=cov,
        ),
    )


def cdr(msg) -> bytes:
    return bytes(STORE.serialize_cdr(msg, msg.__msgtype__))


# --- time and keys ---------------------------------------------------------------------------------------
def test_ros_time_is_utc_and_converts_to_gps_seconds_with_leap_seconds():
    # 2017-01-01T00:00:00 UTC = unix 1483228800; GPS was 18 s ahead of UTC from then on
    assert ros2.stamp_to_t(1_483_228_800, 0) == 1_483_228_800 - 315_964_800 + 18
    assert ros2.stamp_to_t(100, 500_000_000, base="gps") == 100.5
    assert ros2.stamp_to_t(1_483_228_800, 0, leap_seconds=17) == 1_483_228_800 - 315_964_800 + 17
    for t in (1_300_000_000.0, 1_300_000_000.123456789, 1_400_000_000.999999999):
        sec, ns = ros2.t_to_stamp(t)
        assert 0 <= ns < 1_000_000_000
        assert ros2.stamp_to_t(sec, ns) == t  # t -> stamp -> t is the identity for any float
    # stamp -> t rounds once: the float nearest to the exact value
    for sec, ns in ((1_732_512_345, 123_456_789), (1_483_228_800, 999_999_999), (1_900_000_000, 1)):
        exact = Fraction(sec - 315_964_800 + 18) + Fraction(ns, 10**9)
        t = ros2.stamp_to_t(sec, ns)
        assert abs(Fraction(t) - exact) <= Fraction(math.ulp(t)) / 2


def test_stamp_t_stamp_is_exact_for_microsecond_stamps_and_within_a_float_spacing_for_any():
    """fednav's t is float64 GPS seconds: 2**-22 s (238 ns) apart at today's magnitudes, so only
    stamps no finer than 1 us survive the float alone; t_to_stamp inverts stamp_to_t for them."""
    rng = np.random.default_rng(5)
    secs = rng.integers(1_300_000_000, 4_000_000_000 + 315_964_800 - 18, 20_000)
    for sec, us in zip(secs, rng.integers(0, 1_000_000, secs.size), strict=True):
        sec, ns = int(sec), int(us) * 1000
        assert ros2.t_to_stamp(ros2.stamp_to_t(sec, ns)) == (sec, ns)
        assert ros2.t_to_stamp(ros2.stamp_to_t(sec, ns, "gps"), "gps") == (sec, ns)
    # a driver's 100 Hz stamps on a millisecond clock, and whole seconds: exact
    for k in range(1000):
        sec, ns = divmod(1_732_512_345_120_000_000 + k * 10_000_000, 10**9)
        assert ros2.t_to_stamp(ros2.stamp_to_t(sec, ns)) == (sec, ns)
    # nanosecond stamps: within one float spacing through the float alone (the exact stamp comes
    # from the bridge's memory of what it decoded, next test)
    worst = 0
    for sec, ns in zip(secs, rng.integers(0, 10**9, secs.size), strict=True):
        t = ros2.stamp_to_t(int(sec), int(ns))
        s2, n2 = ros2.t_to_stamp(t)
        worst = max(worst, abs((s2 - int(sec)) * 10**9 + n2 - int(ns)))
        assert abs((s2 - int(sec)) * 10**9 + n2 - int(ns)) <= math.ulp(t) * 1e9
    assert 100 < worst <= 477  # 238 ns until 2048, 477 ns until 2116: nanoseconds do not survive


def test_outputs_carry_the_input_stamps_to_the_nanosecond():
    """Real drivers stamp in integer ns (here 200 Hz and 100 Hz from 1732512345.123456789, and a
    GNSS receiver off the IMU's grid): every output at a decoded sample's time carries that
    sample's stamp exactly, in header.stamp of Odometry, NavSatFix, TF and DiagnosticArray."""
    for period_ns in (5_000_000, 10_000_000):
        c = cfg(imu_integration="rectangle", outputs={"tf": True})
        rin, enc = ros2.RosInput(c), ros2.RosEncoder(c)
        stamps = [1_732_512_345_123_456_789 + k * period_ns for k in range(400)]
        ts = {}
        for s in stamps:
            msg = imu_msg(0.0, (0.0, 0.0, 0.01), (0.0, 0.0, 9.8))
            msg.header.stamp.sec, msg.header.stamp.nanosec = divmod(s, 10**9)
            for _, _, sample in rin.decode(IMU_KEY, cdr(msg)):
                ts[sample.t] = s
        assert len(ts) == len(stamps) - 1  # every stamp its own float: 5 ms >> 238 ns
        fix = navsat_msg(0.0, 40.0, 118.0, 50.0)
        fix.header.stamp.sec, fix.header.stamp.nanosec = divmod(stamps[200] + 3_141_593, 10**9)
        only = ros2.RosInput(cfg(inputs=[{"topic": "/gnss/fix", "type": fix.__msgtype__, "sensor_id": "rx"}]))
        [(_, _, g)] = only.decode(FIX_KEY, cdr(fix))
        ts[g.t] = stamps[200] + 3_141_593  # another RosInput, another memory: the fallback below
        P9 = np.eye(9) * 1e-2
        for t, s in ts.items():
            nav = _Nav(t, 40.0, 118.0, 50.0, (1.0, 2.0, 0.0), (0.0, 0.0, 10.0))
            for m in (enc.odometry("lc", nav, P9), enc.navsatfix(nav, P9, "aided"), enc.tf("lc", nav)):
                back = STORE.deserialize_cdr(enc.cdr(m), m.__msgtype__)
                h = back.transforms[0].header if m.__msgtype__ == "tf2_msgs/msg/TFMessage" else back.header
                got = h.stamp.sec * 10**9 + h.stamp.nanosec
                if t == g.t:  # not decoded by enc's bridge: the float's stamp, within its spacing
                    assert abs(got - s) <= math.ulp(t) * 1e9
                else:
                    assert got == s
        assert enc.stamp(None) == (0, 0)
        health = Health(
            t=next(iter(ts)),
            uptime_s=1.0,
            received=1,
            accepted=1,
            rejected={},
            pipelines={},
            dropped_overload=0,
            queue_depth=0,
            latency_ms={"p50": 1.0, "p99": 1.0, "max": 1.0},
        )
        arr = STORE.deserialize_cdr(
            enc.cdr(enc.diagnostics("v1", health)), "diagnostic_msgs/msg/DiagnosticArray"
        )
        assert arr.header.stamp.sec * 10**9 + arr.header.stamp.nanosec == ts[health.t]


def test_key_formats_of_both_carriers():
    c = cfg()
    key = ros2.topic_key(c, "/imu/data", "sensor_msgs/msg/Imu")
    assert key.startswith("0/imu/data/sensor_msgs::msg::dds_::Imu_/RIHS01_")
    assert len(key.rsplit("/", 1)[1]) == len("RIHS01_") + 64
    assert ros2.topic_key(c, "/imu/data", "sensor_msgs/msg/Imu", any_hash=True) == (
        "0/imu/data/sensor_msgs::msg::dds_::Imu_/*"
    )
    humble = cfg(distro="humble", domain_id=7)
    assert ros2.topic_key(humble, "/fix", "sensor_msgs/msg/NavSatFix") == (
        "7/fix/sensor_msgs::msg::dds_::NavSatFix_/TypeHashNotSupported"
    )
    dds = cfg(carrier="ros2dds")
    assert ros2.topic_key(dds, "/imu/data", "sensor_msgs/msg/Imu") == "imu/data"
    assert (
        ros2.topic_key(cfg(carrier="ros2dds", namespace="/robot1"), "/imu/data", "x/msg/Y")
        == "robot1/imu/data"
    )
    # the decoder finds the input whatever the publisher's type hash (Humble or Jazzy)
    rin = ros2.RosInput(c)
    assert rin.input_of("0/imu/data/sensor_msgs::msg::dds_::Imu_/TypeHashNotSupported").sensor_id == "main"
    assert rin.input_of(key).sensor_id == "main"
    assert rin.input_of("1/imu/data/sensor_msgs::msg::dds_::Imu_/x") is None


# --- a NavSatFix laid out by hand -------------------------------------------------------------------------
def navsat_by_hand() -> bytes:
    """NavSatFix in CDR little-endian, built from the layout: 4-byte encapsulation header, then each
    field aligned to its size counted from the end of that header."""
    b = bytearray(b"\x00\x01\x00\x00")  # CDR_LE, options 0
    b += struct.pack("<iI", T0_UNIX, 250_000_000)  # stamp: int32 sec, uint32 nanosec   @0
    b += struct.pack("<I", 5) + b"gnss\x00"  # frame_id: uint32 length incl. NUL, bytes      @8
    b += struct.pack("<b", 0)  # status.status int8 (STATUS_FIX)                               @17
    b += struct.pack("<H", 1)  # status.service uint16 (GPS), aligned to 2                     @18
    b += b"\x00" * 4  # pad to 8                                                              @20
    b += struct.pack("<3d", 40.5, 118.25, 123.5)  # latitude, longitude, altitude              @24
    b += struct.pack("<9d", 4.0, 0, 0, 0, 9.0, 0, 0, 0, 16.0)  # position_covariance            @48
    b += struct.pack("<B", 2)  # position_covariance_type: DIAGONAL_KNOWN                     @120
    return bytes(b)


def test_hand_laid_navsatfix_equals_rosbags_bytes_and_decodes_to_the_fields():
    by_hand = navsat_by_hand()
    assert ros2.header_stamp_s(by_hand) == T0_UNIX + 0.25  # the intake's ordering key
    assert ros2.header_stamp_s(by_hand[:8]) == 0.0
    msg = navsat_msg(T0_UNIX + 0.25, 40.5, 118.25, 123.5, cov=[4.0, 0, 0, 0, 9.0, 0, 0, 0, 16.0])
    assert cdr(msg) == by_hand
    d = STORE.deserialize_cdr(by_hand, "sensor_msgs/msg/NavSatFix")
    assert (d.header.stamp.sec, d.header.stamp.nanosec, d.header.frame_id) == (T0_UNIX, 250_000_000, "gnss")
    assert (d.latitude, d.longitude, d.altitude, d.position_covariance_type) == (40.5, 118.25, 123.5, 2)
    # through the bridge (paired with its Twist) into a GnssFix: sigmas are the covariance diagonal
    rin = ros2.RosInput(cfg())
    assert rin.decode("0/gnss/fix/sensor_msgs::msg::dds_::NavSatFix_/h", by_hand) == []
    out = rin.decode(
        "0/gnss/vel/geometry_msgs::msg::dds_::TwistWithCovarianceStamped_/h",
        cdr(twist_msg(T0_UNIX + 0.25, (1.0, 2.0, 0.5))),
    )
    [(kind, sid, fix)] = out
    assert isinstance(fix, GnssFix)  # the wire model itself, validated: no JSON in between
    assert (kind, sid) == ("gnss_fix", "rx")
    assert fix.t == (T0_UNIX - 315_964_800 + 18) + 0.25
    assert (fix.lat_deg, fix.lon_deg, fix.height_m) == (40.5, 118.25, 123.5)
    assert fix.pos_std_enu_m == (2.0, 3.0, 4.0)
    assert fix.vel_enu_mps == (1.0, 2.0, 0.5)
    assert fix.vel_std_enu_mps == pytest.approx((0.1, 0.2, 0.3))


# --- inputs -----------------------------------------------------------------------------------------------
IMU_KEY = "0/imu/data/sensor_msgs::msg::dds_::Imu_/h"
FIX_KEY = "0/gnss/fix/sensor_msgs::msg::dds_::NavSatFix_/h"
VEL_KEY = "0/gnss/vel/geometry_msgs::msg::dds_::TwistWithCovarianceStamped_/h"


def test_imu_rates_in_flu_become_increments_in_rfu_over_the_stamp_interval():
    rin = ros2.RosInput(cfg())
    w0, a0 = (0.1, 0.2, 0.3), (1.0, -2.0, 9.8)
    w1, a1 = (0.3, 0.0, 0.1), (3.0, 0.0, 9.6)
    assert rin.decode(IMU_KEY, cdr(imu_msg(T0_UNIX, w0, a0))) == []  # the first opens the interval
    [(kind, sid, s)] = rin.decode(IMU_KEY, cdr(imu_msg(T0_UNIX + 0.01, w1, a1)))
    assert isinstance(s, ImuSample)
    assert (kind, sid) == ("imu", "main")
    assert s.dt_s == pytest.approx(0.01, abs=1e-9)
    w, a = 0.5 * (np.array(w0) + w1), 0.5 * (np.array(a0) + a1)  # trapezoid
    # FLU (forward, left, up) -> RFU (right, forward, up): right = -left
    np.testing.assert_allclose(s.dtheta_rad, np.array([-w[1], w[0], w[2]]) * 0.01, atol=1e-12)
    np.testing.assert_allclose(s.dvel_mps, np.array([-a[1], a[0], a[2]]) * 0.01, atol=1e-9)
    # a repeated stamp is a counted duplicate; a stamp going back reopens the interval (counted)
    with pytest.raises(ros2.RosDecodeError) as e:
        rin.decode(IMU_KEY, cdr(imu_msg(T0_UNIX + 0.01, w1, a1)))
    assert e.value.reason == "duplicate"
    with pytest.raises(ros2.RosDecodeError) as e:
        rin.decode(IMU_KEY, cdr(imu_msg(T0_UNIX - 5.0, w0, a0)))
    assert e.value.reason == "time_backwards"
    [(_, _, s)] = rin.decode(IMU_KEY, cdr(imu_msg(T0_UNIX - 4.99, w1, a1)))
    assert s.dt_s == pytest.approx(0.01, abs=1e-9)
    rect = ros2.RosInput(cfg(imu_integration="rectangle"))
    rect.decode(IMU_KEY, cdr(imu_msg(T0_UNIX, w0, a0)))
    [(_, _, s)] = rect.decode(IMU_KEY, cdr(imu_msg(T0_UNIX + 0.01, w1, a1)))
    np.testing.assert_allclose(s.dtheta_rad, np.array([-w1[1], w1[0], w1[2]]) * 0.01)


def test_an_orientation_only_imu_is_refused_not_integrated_as_zero_rates():
    """sensor_msgs/Imu says "element 0 of the covariance = -1: no estimate of this data element". A
    driver publishing only orientation (an AHRS's filter output) sends zero rates so marked: they are
    no measurement (integrated, they are an IMU in free fall at rest), so such a message is refused,
    counted ``ros_no_rates``, and opens no interval."""
    for part in ("angular_velocity", "linear_acceleration"):
        rin = ros2.RosInput(cfg())
        for k in range(3):
            m = imu_msg(T0_UNIX + 0.01 * k, (0.0, 0.0, 0.0), (0.0, 0.0, 0.0))
            setattr(m, f"{part}_covariance", np.r_[-1.0, np.zeros(8)])
            m.orientation_covariance = np.eye(3).ravel() * 1e-4
            with pytest.raises(ros2.RosDecodeError) as e:
                rin.decode(IMU_KEY, cdr(m))
            assert e.value.reason == "ros_no_rates" and part in str(e.value)
        # the raw topic's next sample opens the interval (no interval from a refused one)
        assert rin.decode(IMU_KEY, cdr(imu_msg(T0_UNIX + 0.03, (0, 0, 0.01), (0, 0, 9.8)))) == []
    # an unknown orientation (the usual raw IMU: orientation_covariance[0] = -1) is fine
    rin = ros2.RosInput(cfg())
    rin.decode(IMU_KEY, cdr(imu_msg(T0_UNIX, (0, 0, 0.01), (0, 0, 9.8))))
    [(_, _, s)] = rin.decode(IMU_KEY, cdr(imu_msg(T0_UNIX + 0.01, (0, 0, 0.01), (0, 0, 9.8))))
    assert s.dvel_mps[2] == pytest.approx(0.098)


def test_an_unset_header_stamp_is_refused_in_ros_words():
    """A driver that leaves header.stamp 0: refused with the service's reason (a time before GPS
    time 0, out_of_range) and a text naming the stamp (until then: "imu/main: t: Input should be
    greater than or equal to 0", from the second message on: the first opened an interval at 0)."""
    rin = ros2.RosInput(cfg())
    for key, m in (
        (IMU_KEY, imu_msg(0.0, (0, 0, 0.01), (0, 0, 9.8))),
        (FIX_KEY, navsat_msg(0.0, 40, 118, 5)),
    ):
        m.header.stamp.sec, m.header.stamp.nanosec = 0, 0
        for _ in range(2):
            with pytest.raises(ros2.RosDecodeError) as e:
                rin.decode(key, cdr(m))
            assert e.value.reason == "out_of_range" and "header.stamp is 0" in str(e.value)


def test_fix_and_twist_pair_in_either_order_and_only_within_the_tolerance():
    rin = ros2.RosInput(cfg())
    fix = cdr(navsat_msg(T0_UNIX + 1.0, 40.0, 118.0, 50.0, cov_type=0))
    assert rin.decode(VEL_KEY, cdr(twist_msg(T0_UNIX + 1.0, (0.0, 10.0, 0.0)))) == []
    [(_, _, g)] = rin.decode(FIX_KEY, fix)
    assert g.variant == "velocity" and g.vel_enu_mps == (0.0, 10.0, 0.0)
    assert g.pos_std_enu_m == (10.0, 10.0, 10.0)  # covariance UNKNOWN -> fix_std_m
    # a Twist 0.5 s away is another epoch: no pair; its stamp moves the bridge's stamp time past
    # the fix's wait (0.2 s), so the fix goes on position-only, counted, and the Twist waits
    assert rin.decode(FIX_KEY, cdr(navsat_msg(T0_UNIX + 2.0, 40.0, 118.0, 50.0))) == []
    [(_, _, g)] = rin.decode(VEL_KEY, cdr(twist_msg(T0_UNIX + 2.5, (0.0, 10.0, 0.0))))
    assert g.variant == "position" and g.t == ros2.stamp_to_t(T0_UNIX + 2, 0)
    assert rin.counters == {"fix_without_velocity": 1, "twist_without_fix": 0}
    # NED velocity frame
    ned = ros2.RosInput(
        cfg(
            inputs=[
                {"topic": "/fix", "type": "sensor_msgs/msg/NavSatFix", "sensor_id": "rx"},
                {
                    "topic": "/vel",
                    "type": "geometry_msgs/msg/TwistWithCovarianceStamped",
                    "sensor_id": "rx",
                    "velocity_frame": "ned",
                },
            ]
        )
    )
    ned.decode("0/fix/sensor_msgs::msg::dds_::NavSatFix_/h", fix)
    [(_, _, g)] = ned.decode(
        "0/vel/geometry_msgs::msg::dds_::TwistWithCovarianceStamped_/h",
        cdr(twist_msg(T0_UNIX + 1.0, (3.0, 4.0, 1.0))),
    )
    assert g.vel_enu_mps == (4.0, 3.0, -1.0)
    assert g.vel_std_enu_mps == pytest.approx((0.2, 0.1, 0.3))


def test_navsatfix_without_twist_topic_gives_position_only_fixes():
    # the configuration takes a NavSatFix topic alone (no Twist of its sensor_id)
    only = {"topic": "/gnss/fix", "type": "sensor_msgs/msg/NavSatFix", "sensor_id": "rx"}
    c = cfg(inputs=[only])
    ok = {"vehicles": ["v1"], "ros2": c.model_dump()}
    assert config_mod.from_dict(ok).ros2.inputs[0].sensor_id == "rx"
    rin = ros2.RosInput(c)
    cov = np.diag([4.0, 9.0, 16.0]).ravel()
    [(kind, sid, g)] = rin.decode(
        FIX_KEY, cdr(navsat_msg(T0_UNIX + 1.0, 40.0, 118.0, 50.0, cov=cov, status=1))
    )
    assert (kind, sid) == ("gnss_fix", "rx") and g.variant == "position"
    assert g.vel_enu_mps is None and g.vel_std_enu_mps is None and g.speed_mps is None
    assert g.pos_std_enu_m == pytest.approx((2.0, 3.0, 4.0)) and g.fix_type == "sbas"
    assert g.t == ros2.stamp_to_t(T0_UNIX + 1, 0, "utc", 18)
    assert rin.counters["fix_without_velocity"] == 0  # position-only by configuration: no note
    # the pure function: None twist -> position only; with a twist -> 3-D velocity
    fix = {"t": 1.0, "lat_deg": 1.0, "lon_deg": 2.0, "height_m": 3.0, "pos_std_enu_m": [1.0, 1.0, 2.0]}
    assert ros2.gnss_fix_from_ros(fix, None).variant == "position"
    tw = {"t": 1.0, "vel_enu_mps": [1.0, 2.0, 0.1], "vel_std_enu_mps": [0.1, 0.1, 0.2]}
    g3 = ros2.gnss_fix_from_ros(fix, tw)
    assert g3.variant == "velocity" and g3.vel_enu_mps == (1.0, 2.0, 0.1)
    # a receiver with a Twist topic waits for its pair (no position-only fix at once)
    assert ros2.RosInput(cfg()).decode(FIX_KEY, cdr(navsat_msg(T0_UNIX + 1.0, 40.0, 118.0, 50.0))) == []


def test_bad_cdr_and_no_fix_are_counted_rejections_not_exceptions():
    rin = ros2.RosInput(cfg())
    good = cdr(imu_msg(T0_UNIX, (0, 0, 0), (0, 0, 9.8)))
    for bad in (b"", b"\x00\x01\x00\x00", good[: len(good) // 2], b"\xff" * 40):
        with pytest.raises(ros2.RosDecodeError) as e:
            rin.decode(IMU_KEY, bad)
        assert e.value.reason == "bad_cdr"
    with pytest.raises(ros2.RosDecodeError) as e:
        rin.decode(FIX_KEY, cdr(navsat_msg(T0_UNIX, 40.0, 118.0, 50.0, status=-1)))
    assert e.value.reason == "ros_no_fix" and "NO_FIX" in str(e.value)
    with pytest.raises(ros2.RosDecodeError) as e:  # Jazzy's STATUS_UNKNOWN, named as such
        rin.decode(FIX_KEY, cdr(navsat_msg(T0_UNIX, 40.0, 118.0, 50.0, status=-2)))
    assert e.value.reason == "ros_no_fix" and "STATUS_UNKNOWN" in str(e.value)
    with pytest.raises(ros2.RosDecodeError) as e:
        rin.decode("0/other/x::msg::dds_::Y_/h", good)
    assert e.value.reason == "unknown_key"
    # the wire model refuses what it refuses in JSON, with the service's reasons, at decode
    rin.decode(IMU_KEY, good)
    with pytest.raises(ros2.RosDecodeError) as e:
        rin.decode(IMU_KEY, cdr(imu_msg(T0_UNIX + 0.01, (math.nan, 0, 0), (0, 0, 9.8))))
    assert e.value.reason == "non_finite" and str(e.value).startswith("imu/main: ")
    rect = ros2.RosInput(cfg(imu_integration="rectangle"))
    rect.decode(IMU_KEY, good)
    with pytest.raises(ros2.RosDecodeError) as e:  # 100 rad/s: above the plausibility limit
        rect.decode(IMU_KEY, cdr(imu_msg(T0_UNIX + 0.01, (100.0, 0, 0), (0, 0, 9.8))))
    assert e.value.reason == "absurd_value"
    with pytest.raises(ros2.RosDecodeError) as e:  # a 3 s interval: dt_s above 1 s
        rect.decode(IMU_KEY, cdr(imu_msg(T0_UNIX + 3.01, (0, 0, 0), (0, 0, 9.8))))
    assert e.value.reason == "out_of_range"
    with pytest.raises(ros2.RosDecodeError) as e:
        rin.decode(FIX_KEY, cdr(navsat_msg(T0_UNIX, 95.0, 118.0, 50.0)))
    assert e.value.reason == "out_of_range" and "gnss_fix/rx" in str(e.value)
    with pytest.raises(ros2.RosDecodeError) as e:  # 5 km/s: absurd, refused alone (its fix unharmed)
        rin.decode(VEL_KEY, cdr(twist_msg(T0_UNIX, (5000.0, 0.0, 0.0))))
    assert e.value.reason == "absurd_value"


def test_a_fix_whose_twist_does_not_come_goes_on_position_only_and_is_counted():
    rin = ros2.RosInput(cfg())
    assert rin.cfg.twist_wait_s == 0.2
    assert rin.counters == {"fix_without_velocity": 0, "twist_without_fix": 0}
    rin.decode(IMU_KEY, cdr(imu_msg(T0_UNIX, (0, 0, 0), (0, 0, 9.8))))
    assert rin.decode(FIX_KEY, cdr(navsat_msg(T0_UNIX + 0.005, 40.0, 118.0, 50.0))) == []
    for k in range(1, 21):  # IMU stamps up to 0.2 s after the fix: it still waits
        [(kind, _, _)] = rin.decode(IMU_KEY, cdr(imu_msg(T0_UNIX + 0.01 * k, (0, 0, 0), (0, 0, 9.8))))
        assert kind == "imu"
    # past the wait: the fix comes first (older), position-only, then the IMU sample
    [(k1, s1, g), (k2, _, imu)] = rin.decode(IMU_KEY, cdr(imu_msg(T0_UNIX + 0.21, (0, 0, 0), (0, 0, 9.8))))
    assert (k1, s1, k2) == ("gnss_fix", "rx", "imu") and g.variant == "position" and g.t < imu.t
    assert g.t == ros2.stamp_to_t(T0_UNIX, 5_000_000)
    assert rin.counters["fix_without_velocity"] == 1
    # its Twist arriving now finds no fix: it waits, and is dropped (counted) after the wait
    assert rin.decode(VEL_KEY, cdr(twist_msg(T0_UNIX + 0.005, (1.0, 0.0, 0.0)))) == []
    assert rin.counters["twist_without_fix"] == 1  # already 0.2 s behind the stamp time

    # a 10 Hz receiver without Twists: each fix goes on when the next one arrives (0.1 s < wait)
    rin = ros2.RosInput(cfg())
    assert rin.decode(FIX_KEY, cdr(navsat_msg(T0_UNIX + 1.0, 40.0, 118.0, 50.0))) == []
    for k in range(1, 5):
        [(_, _, g)] = rin.decode(FIX_KEY, cdr(navsat_msg(T0_UNIX + 1.0 + 0.1 * k, 40.0, 118.0, 50.0)))
        assert g.variant == "position" and g.t == ros2.stamp_to_t(T0_UNIX + 1, (k - 1) * 100_000_000)
    assert rin.counters["fix_without_velocity"] == 4
    assert [g.t for _, _, g in rin.flush()] == [ros2.stamp_to_t(T0_UNIX + 1, 400_000_000)]

    # a bad Twist is refused alone; its fix still goes on (position-only after the wait)
    rin = ros2.RosInput(cfg(twist_wait_s=0.5, imu_integration="rectangle"))
    assert rin.decode(FIX_KEY, cdr(navsat_msg(T0_UNIX + 2.0, 40.0, 118.0, 50.0))) == []
    with pytest.raises(ros2.RosDecodeError) as e:
        rin.decode(VEL_KEY, cdr(twist_msg(T0_UNIX + 2.0, (math.inf, 0.0, 0.0))))
    assert e.value.reason == "non_finite"
    rin.decode(IMU_KEY, cdr(imu_msg(T0_UNIX + 2.4, (0, 0, 0), (0, 0, 9.8))))
    # a refused sample past the wait: the fix it released is kept for the next decode, not lost
    with pytest.raises(ros2.RosDecodeError):
        rin.decode(IMU_KEY, cdr(imu_msg(T0_UNIX + 2.6, (math.nan, 0, 0), (0, 0, 9.8))))
    out = rin.decode(IMU_KEY, cdr(imu_msg(T0_UNIX + 2.61, (0, 0, 0), (0, 0, 9.8))))
    assert [k for k, _, _ in out] == ["gnss_fix", "imu"]
    assert out[0][2].variant == "position" and rin.counters["fix_without_velocity"] == 1
    with pytest.raises(config_mod.ConfigError, match="twist_wait_s"):
        config_mod.from_dict({"vehicles": ["v1"], "ros2": cfg().model_dump() | {"twist_wait_s": 0.01}})


def test_ros2_classify_is_the_services():
    from pydantic import ValidationError

    from fednav.service.app import classify

    cases = [
        {"t": 1.0, "dt_s": 0.01, "dtheta_rad": (math.nan, 0.0, 0.0), "dvel_mps": (0.0, 0.0, 0.0)},
        {"t": 1.0, "dt_s": 0.01, "dtheta_rad": (9.0, 0.0, 0.0), "dvel_mps": (0.0, 0.0, 0.0)},
        {"t": 1.0, "dt_s": 2.0, "dtheta_rad": (0.0, 0.0, 0.0), "dvel_mps": (0.0, 0.0, 0.0)},
        {"t": 1.0, "dt_s": 0.01, "dtheta_rad": [0.0, 0.0, 0.0], "dvel_mps": (0.0, 0.0, 0.0)},
    ]
    reasons = []
    for d in cases:
        with pytest.raises(ValidationError) as v:
            ImuSample.model_validate(d)
        reasons.append(ros2.classify(v.value))
        assert reasons[-1] == classify(v.value)
    assert reasons == ["non_finite", "absurd_value", "out_of_range", "schema"]
    with pytest.raises(ValidationError) as v:
        ImuSample.model_validate_json(b"{")
    assert ros2.classify(v.value) == classify(v.value) == "malformed_json"


def test_the_bridge_and_fednav_replay_turn_the_same_bag_into_the_same_messages(tmp_path):
    """The live bridge and fednav-replay decode one bag alike: the same ImuSample (trapezoid of
    FLU rates over jittered stamps, RFU), the same GnssFix (fix + Twist, sigmas from the
    covariances, UTC stamps + leap seconds), so a live/replay accuracy gap is not the conversion's.
    The bag's fixes are received 50 ms after their stamp, the IMU 2 ms after: live, the service
    gets each fix after the IMU samples of the next 40-48 ms and applies it late (docs/ros2.md
    "Fix latency"); fednav-replay publishes in stamp order."""
    from rosbags.rosbag2 import Writer

    from fednav.replay.mapping import from_dict
    from fednav.replay.sources import all_events

    rng = np.random.default_rng(7)
    msgs = []  # (receive ns, topic, message)
    t = T0_UNIX + 0.123456
    for _ in range(300):
        t += 0.01 + rng.uniform(-4e-4, 4e-4)
        m = imu_msg(t, rng.normal(0, 0.2, 3), rng.normal([0, 0, 9.8], 1.0))
        msgs.append((round((t + 0.002) * 1e9), "/imu/data", m))
    for k in range(1, 30):
        tf = T0_UNIX + 0.1 * k
        cov = np.diag([0.25, 0.36, 1.0]).ravel()
        fix = navsat_msg(tf, 30.5 + 1e-6 * k, 114.3, 20.0, cov)
        msgs.append((round((tf + 0.05) * 1e9), "/gnss/fix", fix))
        msgs.append((round((tf + 0.051) * 1e9), "/gnss/vel", twist_msg(tf, rng.normal(0, 5, 3))))
    msgs.sort(key=lambda x: x[0])
    bag = tmp_path / "bag"
    with Writer(bag, version=9) as w:
        conns = {}
        for rx, topic, m in msgs:
            if topic not in conns:
                conns[topic] = w.add_connection(topic, m.__msgtype__, typestore=STORE)
            w.write(conns[topic], rx, cdr(m))
    c = cfg()
    rin = ros2.RosInput(c)
    live = []
    for _, topic, m in msgs:  # as received (bag order)
        live += rin.decode(ros2.topic_key(c, topic, m.__msgtype__), cdr(m))
    live += rin.flush()
    assert dict(rin.counters) == {"fix_without_velocity": 0, "twist_without_fix": 0}
    mapping = from_dict(
        {
            "vehicle": "v1",
            "leap_seconds": 18,
            "streams": [
                {"source": "bag", "kind": "imu", "sensor_id": "main", "topic": "/imu/data", "axes": "FLU"},
                {
                    "source": "bag",
                    "kind": "gnss_fix",
                    "sensor_id": "rx",
                    "topic": "/gnss/fix",
                    "twist_topic": "/gnss/vel",
                    "twist_frame": "ENU",
                },
            ],
        }
    )
    rep = list(all_events(mapping, tmp_path))
    for kind, fields in (("imu", ("t", "dt_s", "dtheta_rad", "dvel_mps")), ("gnss_fix", GNSS_FIELDS)):
        a = [m for k, _, m in live if k == kind]
        prefix = "sensor/gnss" if kind == "gnss_fix" else "sensor/imu"
        b = [e.msg for e in rep if e.key_suffix.startswith(prefix)]
        assert len(a) == len(b) == (299 if kind == "imu" else 29)
        for f in fields:
            x = np.array([getattr(m, f) for m in a], float)
            y = np.array([getattr(m, f) for m in b], float)
            # the bridge takes dt from the integer stamps, the replay from float GPS seconds (spaced
            # 2.4e-7 s): dt and the increments agree to a few 1e-5 of themselves, times exactly
            tol = {"rtol": 5e-5, "atol": 1e-12} if f != "t" else {"rtol": 0.0, "atol": 0.0}
            np.testing.assert_allclose(x, y, **tol, err_msg=f"{kind}.{f}")
    # live, each fix is decoded after the IMU samples of the next ~40 ms (its receive latency)
    imu_t, lag = None, []
    for k, _, m in live:
        if k == "imu":
            imu_t = m.t
        elif imu_t is not None:
            lag.append(imu_t - m.t)
    assert 0.035 < np.median(lag) < 0.05


GNSS_FIELDS = ("t", "lat_deg", "lon_deg", "height_m", "pos_std_enu_m", "vel_enu_mps", "vel_std_enu_mps")


# --- outputs: conventions ---------------------------------------------------------------------------------
def test_quaternion_of_known_attitudes_rep103():
    # heading north (fednav heading 0), level: the FLU x axis points north = ENU yaw +90 deg
    q = ros2.quat_enu_flu(earth.rpy_to_mat_nb(earth.rpy_from_msg_deg([0.0, 0.0, 0.0])))
    np.testing.assert_allclose(q, [0.0, 0.0, math.sqrt(0.5), math.sqrt(0.5)], atol=1e-12)
    # heading east: ENU yaw 0, identity
    q = ros2.quat_enu_flu(earth.rpy_to_mat_nb(earth.rpy_from_msg_deg([0.0, 0.0, 90.0])))
    np.testing.assert_allclose(np.abs(q), [0.0, 0.0, 0.0, 1.0], atol=1e-12)
    # any attitude: the quaternion maps FLU forward/left/up to fednav's forward/-right/up in ENU
    rng = np.random.default_rng(12)
    for _ in range(20):
        rpy = [rng.uniform(-170, 170), rng.uniform(-80, 80), rng.uniform(0, 360)]
        m = earth.rpy_to_mat_nb(earth.rpy_from_msg_deg(rpy))
        x, y, z, w = ros2.quat_enu_flu(m)
        R = earth.quat_to_mat(np.array([w, x, y, z]))
        np.testing.assert_allclose(R[:, 0], m[:, 1], atol=1e-12)
        np.testing.assert_allclose(R[:, 1], -m[:, 0], atol=1e-12)
        np.testing.assert_allclose(R[:, 2], m[:, 2], atol=1e-12)


def test_pose_covariance_attitude_block_is_the_error_of_the_published_orientation():
    """fednav's phi (C_computed = (I - [phi x]) C_true) is -1 x the world-axes rotation error of the
    published orientation: Monte Carlo of phi, the rotation errors of the published quaternions, and
    their sample covariance against pose_covariance's rotation block and its cross terms."""
    rng = np.random.default_rng(3)
    m_true = earth.rpy_to_mat_nb(earth.rpy_from_msg_deg([5.0, -3.0, 30.0]))
    A = rng.normal(size=(6, 6)) * 1e-3
    P6 = A @ A.T  # joint covariance of (dp, phi)
    P9 = np.zeros((9, 9))
    idx = np.r_[0:3, 6:9]
    P9[np.ix_(idx, idx)] = P6
    P9[3:6, 3:6] = np.eye(3) * 0.01
    x = rng.multivariate_normal(np.zeros(6), P6, size=4000)
    qt = ros2.quat_enu_flu(m_true)
    Rt = earth.quat_to_mat(np.r_[qt[3], qt[:3]])
    errs = []
    for dp, phi in zip(x[:, :3], x[:, 3:], strict=True):
        m_comp = (np.eye(3) - earth.skew(phi)) @ m_true
        m_comp = np.linalg.qr(m_comp)[0] * np.sign(np.diag(np.linalg.qr(m_comp)[1]))  # re-orthonormalise
        qc = ros2.quat_enu_flu(m_comp)
        Rc = earth.quat_to_mat(np.r_[qc[3], qc[:3]])
        errs.append(np.r_[dp, earth.quat_to_rotvec(earth.mat_to_quat(Rc @ Rt.T))])
    C_mc = np.cov(np.array(errs).T)
    C = ros2.pose_covariance(P9)
    np.testing.assert_allclose(C, C_mc, atol=0.1 * np.abs(P6).max())
    assert np.all(
        np.sign(C[:3, 3:][np.abs(P6[:3, 3:]) > 3e-6]) == -np.sign(P6[:3, 3:][np.abs(P6[:3, 3:]) > 3e-6])
    )


def test_twist_in_child_frame_and_its_covariance():
    m = earth.rpy_to_mat_nb(earth.rpy_from_msg_deg([0.0, 0.0, 0.0]))  # heading north
    P9 = np.zeros((9, 9))
    P9[3:6, 3:6] = np.diag([1.0, 4.0, 9.0])  # east, north, up
    C = ros2.twist_covariance(P9, m)
    np.testing.assert_allclose(np.diag(C)[:3], [4.0, 1.0, 9.0])  # forward = north, left = west
    assert np.all(np.diag(C)[3:] == ros2.UNKNOWN_VARIANCE)


class _Nav:
    def __init__(self, t, lat_deg, lon_deg, h, vel, rpy_deg):
        self.t, self.lat_rad, self.lon_rad, self.h_m = t, math.radians(lat_deg), math.radians(lon_deg), h
        self.vel_enu_mps = np.array(vel, dtype=float)
        self.mat_nb = earth.rpy_to_mat_nb(earth.rpy_from_msg_deg(rpy_deg))
        self.llh = np.array([self.lat_rad, self.lon_rad, h])


def test_odometry_navsatfix_tf_and_diagnostics_roundtrip_through_cdr():
    c = cfg(outputs={"tf": True, "datum": [40.0, 118.0, 0.0]})
    enc = ros2.RosEncoder(c)
    t = 1_300_000_000.5
    nav = _Nav(t, 40.001, 118.0, 10.0, (0.0, 20.0, 0.0), (0.0, 0.0, 0.0))
    P9 = np.diag([1.0, 4.0, 9.0, 0.01, 0.04, 0.09, 1e-6, 2e-6, 3e-6])
    odo = STORE.deserialize_cdr(enc.cdr(enc.odometry("lc", nav, P9)), "nav_msgs/msg/Odometry")
    assert (odo.header.frame_id, odo.child_frame_id) == ("map", "base_link")
    assert ros2.stamp_to_t(odo.header.stamp.sec, odo.header.stamp.nanosec) == pytest.approx(t, abs=1e-6)
    p = odo.pose.pose.position
    assert (
        p.x == pytest.approx(0.0, abs=1e-6)
        and p.y == pytest.approx(111.03, abs=0.05)
        and p.z == pytest.approx(10.0, abs=0.01)
    )
    assert odo.twist.twist.linear.x == pytest.approx(20.0) and abs(odo.twist.twist.linear.y) < 1e-9
    cov = odo.pose.covariance.reshape(6, 6)
    np.testing.assert_allclose(np.diag(cov), [1.0, 4.0, 9.0, 1e-6, 2e-6, 3e-6], rtol=1e-4)
    fix = STORE.deserialize_cdr(enc.cdr(enc.navsatfix(nav, P9, "aided")), "sensor_msgs/msg/NavSatFix")
    assert fix.latitude == pytest.approx(40.001) and fix.position_covariance_type == 3
    np.testing.assert_allclose(fix.position_covariance, [1, 0, 0, 0, 4, 0, 0, 0, 9])
    assert (
        STORE.deserialize_cdr(
            enc.cdr(enc.navsatfix(nav, P9, "initialising")), "sensor_msgs/msg/NavSatFix"
        ).status.status
        == -1
    )
    tf = STORE.deserialize_cdr(enc.cdr(enc.tf("lc", nav)), "tf2_msgs/msg/TFMessage")
    assert tf.transforms[0].child_frame_id == "base_link"
    assert tf.transforms[0].transform.translation.y == pytest.approx(p.y)
    h = Health(
        t=t,
        uptime_s=1.0,
        received=10,
        accepted=9,
        rejected={"bad_cdr": 1},
        dropped_overload=0,
        queue_depth=0,
        latency_ms={"p50": 1.0, "p99": 2.0, "max": 3.0},
        pipelines={
            "lc": PipelineHealth(status="aided", last_t=t, updates=3),
            "fed": PipelineHealth(status="failed", last_t=t, updates=0),
            "tc": PipelineHealth(status="coasting", last_t=t, updates=1),
            "new": PipelineHealth(status="initialising", last_t=None, updates=0),
        },
    )
    arr = STORE.deserialize_cdr(enc.cdr(enc.diagnostics("v1", h)), "diagnostic_msgs/msg/DiagnosticArray")
    levels = {s.name: s.level for s in arr.status}
    assert levels == {
        "fednav/v1/service": 0,
        "fednav/v1/lc": 0,
        "fednav/v1/fed": 2,
        "fednav/v1/tc": 1,
        "fednav/v1/new": 3,
    }
    svc = arr.status[0]
    assert {kv.key: kv.value for kv in svc.values}["rejected.bad_cdr"] == "1"
    stale = h.model_copy(update={"stale": ["imu/main"]})
    assert (
        STORE.deserialize_cdr(enc.cdr(enc.diagnostics("v1", stale)), "diagnostic_msgs/msg/DiagnosticArray")
        .status[0]
        .level
        == 1
    )


def test_rmw_zenoh_attachment_layout():
    gid = bytes(range(16))
    # rmw_zenoh (zenoh-cpp serializer): int64 seq, int64 timestamp, std::array<uint8_t,16> as a sequence
    a = ros2.rmw_attachment(7, 1_700_000_000_123_456_789, gid)
    assert len(a) == 8 + 8 + 1 + 16
    assert struct.unpack_from("<qq", a) == (7, 1_700_000_000_123_456_789)
    assert a[16] == 16 and a[17:] == gid
    # the earlier keyed layout
    k = ros2.rmw_attachment(7, 1_700_000_000_123_456_789, gid, keyed=True)
    assert k[0] == 15 and k[1:16] == b"sequence_number"
    assert struct.unpack_from("<q", k, 16)[0] == 7
    assert k[24] == 16 and k[25:41] == b"source_timestamp"
    assert struct.unpack_from("<q", k, 41)[0] == 1_700_000_000_123_456_789
    assert k[49] == 10 and k[50:60] == b"source_gid" and k[60] == 16 and k[61:] == gid


def test_rmw_zenoh_graph_tokens():
    c = cfg(node_name="nav")
    h = ros2.type_hash("nav_msgs/msg/Odometry")
    toks = ros2.graph_tokens(
        c,
        "abc123",
        [("/fednav/lc/odometry", "nav_msgs/msg/Odometry")],
        [("/imu/data", "sensor_msgs/msg/Imu")],
    )
    assert toks[0] == "@ros2_lv/0/abc123/0/0/NN/%/%/nav"
    assert (
        toks[1] == "@ros2_lv/0/abc123/0/1/MP/%/%/nav/%fednav%lc%odometry/nav_msgs::msg::dds_::Odometry_/"
        f"{h}/::,10:,:,:,,"
    )
    assert toks[2].startswith(
        "@ros2_lv/0/abc123/0/2/MS/%/%/nav/%imu%data/sensor_msgs::msg::dds_::Imu_/RIHS01_"
    )
    for t in toks:  # valid Zenoh key expressions, 9 chunks for the node and 13 for the topics
        import zenoh

        zenoh.KeyExpr(t)
        assert len(t.split("/")) in (9, 13)


def test_xxh3_128_matches_the_reference_implementation():
    # digests of the xxHash library (xxh3_128, seed 0) for every length class of the algorithm
    ref = {
        b"": "99aa06d3014798d86001c324468d497f",
        b"a": "a96faf705af16834e6c632b61e964e1f",
        b"abc": "06b05ab6733a618578af5f94892f3950",
        b"abcd1234": "ea07bff96e7b492e32500856f68ba7c2",
        b"0123456789abcdef": "ccba8085a0434e9e0befb4873dbe58f8",
        b"x" * 100: "add9998d55ed3962e18dc405a95cc094",
        b"y" * 200: "833cf59a501ae2a8661514be62296c9c",
        b"z" * 1000: "66a9b2d587876ce7cd3a574700eddf41",
    }
    for data, hexdigest in ref.items():
        lo, hi = ros2.xxh3_128(data)
        assert format(hi << 64 | lo, "032x") == hexdigest, len(data)


def test_each_publisher_has_the_gid_rmw_zenoh_derives_from_its_token():
    c = cfg(node_name="nav")
    pubs = [("/fednav/lc/odometry", "nav_msgs/msg/Odometry"), ("/fednav/lc/fix", "sensor_msgs/msg/NavSatFix")]
    ents = ros2.graph_entities(c, "abc123", pubs, [("/imu/data", "sensor_msgs/msg/Imu")])
    assert [(e.kind, e.entity_id) for e in ents] == [("NN", 0), ("MP", 1), ("MP", 2), ("MS", 3)]
    # the GID of a token: XXH3-128 of the key expression, low then high 64 bits little-endian
    # (value of the xxHash library for this token)
    assert ents[1].gid.hex() == "f2466f86e422934b60d5db45be4350c5"
    assert len({e.gid for e in ents}) == 4
    sent = []
    sink = ros2.RosSink(c, ["lc"], lambda k, p, a: sent.append((k, a)), gid=bytes(16))
    # before any token: per-publisher GIDs derived from the base GID, topic and type
    g_odo = sink.gid_of("/fednav/lc/odometry", "nav_msgs/msg/Odometry")
    assert g_odo == ros2.derived_gid(bytes(16), "/fednav/lc/odometry", "nav_msgs/msg/Odometry")
    assert g_odo != sink.gid_of("/fednav/lc/fix", "sensor_msgs/msg/NavSatFix") != bytes(16)
    assert g_odo != ros2.derived_gid(bytes(range(16)), "/fednav/lc/odometry", "nav_msgs/msg/Odometry")
    # the tokens the service declares for this configuration: the sink's attachments carry their GIDs
    assert ros2.graph_tokens(c, "abc123", pubs, []) == [e.token for e in ents[:3]]
    nav = _Nav(1_300_000_000.5, 40.0, 118.0, 10.0, (0.0, 20.0, 0.0), (0.0, 0.0, 0.0))
    sink._send("/fednav/lc/odometry", sink.enc.odometry("lc", nav, np.eye(9)))
    sink._send("/fednav/lc/fix", sink.enc.navsatfix(nav, np.eye(9), "aided"))
    sink._send("/fednav/lc/odometry", sink.enc.odometry("lc", nav, np.eye(9)))
    gids = [a[17:] for _, a in sent]
    assert gids == [ents[1].gid, ents[2].gid, ents[1].gid]
    assert [struct.unpack_from("<q", a)[0] for _, a in sent] == [1, 1, 2]  # sequence per publisher
    # another configuration object (another service) keeps its own
    assert ros2.RosSink(cfg(node_name="nav"), ["lc"], None, bytes(16)).gid_of(*pubs[0]) == g_odo


def test_qos_chunk_as_rmw_zenoh_writes_it():
    # fields equal to rmw_zenoh's defaults (reliable, volatile, keep last, depth 42) are empty
    assert ros2.qos_keyexpr(depth=42) == "::,:,:,:,,"
    assert ros2.QOS_CHUNK == ros2.qos_keyexpr() == "::,10:,:,:,,"  # ROS 2's default profile: keep last 10
    assert ros2.qos_keyexpr(ros2.QOS_BEST_EFFORT, ros2.QOS_TRANSIENT_LOCAL, ros2.QOS_KEEP_ALL, 5) == (
        "2:1:2,5:,:,:,,"
    )
    # what rmw_zenoh's keyexpr_to_qos splits: 6 ':' parts; history 2, deadline 2, lifespan 2 and
    # liveliness 3 ',' parts
    parts = ros2.QOS_CHUNK.split(":")
    assert [len(p.split(",")) for p in parts] == [1, 1, 2, 2, 2, 3]


# --- configuration ------------------------------------------------------------------------------------------
def test_config_errors_name_the_field():
    ok = {"vehicles": ["v1"], "ros2": cfg().model_dump()}
    assert config_mod.from_dict(ok).ros2.vehicle == "v1"
    with pytest.raises(config_mod.ConfigError, match="ros2.vehicle 'v9' is not a served vehicle"):
        config_mod.from_dict(ok | {"ros2": ok["ros2"] | {"vehicle": "v9"}})
    with pytest.raises(config_mod.ConfigError, match=r"ros2\.inputs\.0\.topic"):
        config_mod.from_dict(
            ok
            | {
                "ros2": ok["ros2"]
                | {"inputs": [{"topic": "imu data", "type": "sensor_msgs/msg/Imu", "sensor_id": "a"}]}
            }
        )
    with pytest.raises(config_mod.ConfigError, match="no NavSatFix topic"):
        config_mod.from_dict(
            ok
            | {
                "ros2": ok["ros2"]
                | {
                    "inputs": [
                        {
                            "topic": "/v",
                            "type": "geometry_msgs/msg/TwistWithCovarianceStamped",
                            "sensor_id": "a",
                        }
                    ]
                }
            }
        )
    with pytest.raises(config_mod.ConfigError, match=r"ros2\.carrier"):
        config_mod.from_dict(ok | {"ros2": ok["ros2"] | {"carrier": "dds"}})
    with pytest.raises(config_mod.ConfigError, match="ros2.outputs.tf_pipeline"):
        config_mod.from_dict(ok | {"ros2": ok["ros2"] | {"outputs": {"tf": True, "tf_pipeline": "x"}}})
    with pytest.raises(config_mod.ConfigError, match="not a configured pipeline"):
        config_mod.from_dict(ok | {"ros2": ok["ros2"] | {"outputs": {"pipelines": ["nope"]}}})


def test_example_config_loads_and_missing_rosbags_is_one_line(monkeypatch, capsys):
    from pathlib import Path

    from fednav.service import __main__ as service_main

    example = Path(__file__).resolve().parents[1] / "service" / "configs" / "ros2.toml"
    c = config_mod.load(example)
    assert c.ros2.vehicle == "robot1" and c.ros2.outputs.tf and len(c.ros2.inputs) == 3

    def missing(distro="jazzy"):
        raise ros2.RosUnavailable(ros2.INSTALL_HINT)

    monkeypatch.setattr(ros2, "typestore", missing)
    assert service_main.main(["--config", str(example), "--no-record"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "install fednav[ros]" in err[0]


def test_a_configured_topic_that_never_comes_is_named_once():
    """A typo in an input topic (``/imu/dta``) showed as nothing but every fix refused
    ``not_initialised``: the bridge names a configured topic without a sample once the others' stamps
    span ``SILENT_AFTER_S``, once, and Health notes it while it stays silent."""
    c = cfg(
        inputs=[
            {"topic": "/imu/dta", "type": "sensor_msgs/msg/Imu", "sensor_id": "main"},
            {"topic": "/gnss/fix", "type": "sensor_msgs/msg/NavSatFix", "sensor_id": "rx"},
        ]
    )
    rin = ros2.RosInput(c)
    fix_key = ros2.topic_key(c, "/gnss/fix", "sensor_msgs/msg/NavSatFix", any_hash=False)
    said = []
    for k in range(60):  # 10 Hz fixes for 6 s of stamps, no IMU sample
        rin.decode(fix_key, cdr(navsat_msg(T0_UNIX + 0.1 * k, 40.0, 118.0, 50.0)))
        said += rin.newly_silent()
        if k < 49:
            assert not said, (k, said)  # not before 5 s of the robot's time
    assert len(said) == 1 and "/imu/dta" in said[0] and "/gnss/fix" not in said[0], said
    assert rin.silent_topics() == ["/imu/dta"]
    imu_key = ros2.topic_key(c, "/imu/dta", "sensor_msgs/msg/Imu", any_hash=False)
    rin.decode(imu_key, cdr(imu_msg(T0_UNIX + 6.0, (0, 0, 0), (0, 0, 9.8))))
    assert rin.silent_topics() == [] and rin.newly_silent() == []
