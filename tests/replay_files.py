"""Small recorded logs of every format fednav-replay reads, written with the formats' own libraries
(rosbags writers, pynmea2 sentences with checksums, pyubx2 UBX serialisation, csv), from one
simulated drive: a car at rest for ``STATIC_S`` then accelerating and turning, nav-grade IMU at
100 Hz, GNSS fixes at 5 Hz (fednav's simulator: fednav-sim's trajectory and sensor models).

Each writer takes the simulated messages (fednav frames: body RFU, ENU, GPS time) and writes them
the way a real device would (its axes, units, time base); ``write_all`` returns the mapping file
of every case. Used by tests/test_replay*.py and benchmarks/replay.py.

``simulate_car_drive`` is a drive that STARTS IN MOTION (no rest at all) with an IMU of a given
grade (the imu_grades presets' numbers, drawn per run) and 10 Hz fixes: the simulator flies
coordinated turns (its body rolls into a turn, as an aircraft), which ``car_imu`` rolls back into
the level frame of a car body (a car's IMU reads the centripetal acceleration sideways).
"""

from __future__ import annotations

import csv
import datetime as dt
import io
import math
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from fednav.replay.mapping import GPS_EPOCH_UNIX_S, LEAP_SECONDS_NOW, axes_matrix
from fednav.service.messages import GnssFix, ImuSample, Truth

T0_GPS_S = 1_400_000_000.0  # 2024-05-20
STATIC_S = 12.0
GEOID_SEP_M = 12.5  # geoid above the ellipsoid written in GGA (altitude above MSL = h - sep)
BOOT_GPS_S = T0_GPS_S - 1234.5  # the devices' boot time (boot-time stamps)
UBX_TICK_S = 1e-3

SCENARIO_TOML = """
name = "replay_drive"
description = "A car at rest, then accelerating and turning: replay test data."
duration_s = {duration}
t0_gps_s = {t0}
seed = 3
truth_rate_hz = 10.0

[start]
lat_deg = 30.5283
lon_deg = 114.3557
height_m = 25.0
heading_deg = 30.0
speed_mps = 0.0

[[segments]]
kind = "straight"
duration_s = {static}

[[segments]]
kind = "accelerate"
duration_s = 8.0
accel_mps2 = 1.5
ramp_s = 1.0

[[segments]]
kind = "turn"
duration_s = 10.0
turn_rate_dps = 6.0
ramp_s = 1.0

[imu]
id = "main"
rate_hz = 100.0
bias_mode = "random"
gyro_bias_dph = [0.01, 0.01, 0.01]
accel_bias_ug = [50.0, 50.0, 50.0]
arw_dpsh = 0.001
vrw_ugpsHz = 5.0

[gnss]
id = "main"
rate_hz = 5.0
pos_std_enu_m = [1.0, 1.0, 2.0]
vel_std_enu_mps = [0.05, 0.05, 0.1]
constellation = "GPS"

[initial_errors]
mode = "random"
pos_enu_m = [1.0, 1.0, 1.0]
vel_enu_mps = [0.05, 0.05, 0.05]
rpy_arcsec = [60.0, 60.0, 300.0]
"""

SERVICE_TOML = """
prefix = "fednav"
vehicles = ["*"]

[init]
mode = "static"
align_time_s = {align}

[[pipelines]]
name = "lc"
kind = "loosely_coupled"
"""


@dataclass
class Drive:
    imu: list[ImuSample]
    fixes: list[GnssFix]
    truth: list[Truth]


def simulate_drive(tmp: Path, duration_s: float = 40.0, seed: int = 3) -> Drive:
    from fednav.simulators.scenario import load_scenario
    from fednav.simulators.stream import simulate

    p = tmp / "replay_drive.toml"
    p.write_text(SCENARIO_TOML.format(duration=duration_s, t0=T0_GPS_S, static=STATIC_S + 1.0))
    imu, fixes, truth = [], [], []
    for _key, msg in simulate(load_scenario(p), seed=seed):
        if isinstance(msg, ImuSample):
            imu.append(msg)
        elif isinstance(msg, GnssFix):
            fixes.append(msg)
        elif isinstance(msg, Truth):
            truth.append(msg)
    return Drive(imu, fixes, truth)


CAR_SCENARIO_TOML = """
name = "replay_car_{grade}"
description = "A car already driving when the log starts: speed changes and turns, no rest."
duration_s = {duration}
t0_gps_s = {t0}
seed = 5
truth_rate_hz = 100.0

[start]
lat_deg = 30.5283
lon_deg = 114.3557
height_m = 25.0
heading_deg = 30.0
speed_mps = 14.0

{segments}

[imu]
id = "main"
rate_hz = 100.0
bias_mode = "random"
gyro_bias_dph = [{g.gyro_bias_dph}, {g.gyro_bias_dph}, {g.gyro_bias_dph}]
accel_bias_ug = [{g.accel_bias_ug}, {g.accel_bias_ug}, {g.accel_bias_ug}]
arw_dpsh = {g.arw_dpsh}
vrw_ugpsHz = {g.vrw_ugpsHz}
gyro_bias_instability_dph = {g.gyro_bias_instability_dph}
gyro_bias_tau_s = {g.gyro_bias_tau_s}
accel_bias_instability_ug = {g.accel_bias_instability_ug}
accel_bias_tau_s = {g.accel_bias_tau_s}

[gnss]
id = "main"
rate_hz = 10.0
pos_std_enu_m = [{pos_std}, {pos_std}, {pos_std_u}]
vel_std_enu_mps = [0.05, 0.05, 0.1]
correlated_pos_std_enu_m = [{gm}, {gm}, {gm_u}]
correlation_time_s = 30.0
"""

#: a minute of town driving from 14 m/s: speed changes and turns both ways, a stop-free loop
CAR_SEGMENTS = (
    ("straight", 4.0, {}),
    ("accelerate", 6.0, {"accel_mps2": 1.2, "ramp_s": 1.0}),
    ("turn", 9.0, {"turn_rate_dps": 10.0, "ramp_s": 2.0}),
    ("straight", 5.0, {}),
    ("accelerate", 6.0, {"accel_mps2": -1.5, "ramp_s": 1.0}),
    ("turn", 9.0, {"turn_rate_dps": -12.0, "ramp_s": 2.0}),
    ("accelerate", 5.0, {"accel_mps2": 1.0, "ramp_s": 1.0}),
    ("turn", 8.0, {"turn_rate_dps": 8.0, "ramp_s": 2.0}),
    ("straight", 4.0, {}),
    ("turn", 8.0, {"turn_rate_dps": -9.0, "ramp_s": 2.0}),
)


def car_segments(duration_s: float, stop_s: float = 0.0, level_turns: bool = False) -> str:
    """The segments of ``duration_s``; ``stop_s`` > 0: first a stop of that long (braking from
    14 m/s over 8 s, standing, pulling away over 8 s); ``level_turns``: turns without roll."""
    out, t, k = [], 0.0, 0
    if stop_s > 0:
        for kind, d, kw in (
            ("straight", 3.0, {}),
            ("accelerate", 8.0, {"accel_mps2": -2.0, "ramp_s": 1.0}),
            ("straight", stop_s, {}),
            ("accelerate", 8.0, {"accel_mps2": 2.0, "ramp_s": 1.0}),
        ):
            lines = [f'kind = "{kind}"', f"duration_s = {d}"] + [f"{a} = {b}" for a, b in kw.items()]
            out.append("[[segments]]\n" + "\n".join(lines))
            t += d
    while True:
        kind, d, kw = CAR_SEGMENTS[k % len(CAR_SEGMENTS)]
        k += 1
        if t + d > duration_s:  # the rest is padded with straight driving
            break
        lines = [f'kind = "{kind}"', f"duration_s = {d}"] + [f"{a} = {b}" for a, b in kw.items()]
        if kind == "turn" and level_turns:
            lines.append('bank = "level"')
        out.append("[[segments]]\n" + "\n".join(lines))
        t += d
    return "\n\n".join(out)


def car_imu(imu: list[ImuSample], truth: list[Truth]) -> list[ImuSample]:
    """The simulator's IMU increments (body rolled into coordinated turns) as a car's IMU reads them:
    rotated about the forward axis into the level-roll car body (C_cb from the truth's roll, the
    roll rate taken out of the angle increment). The IMU's errors stay as simulated."""
    from fednav.service import earth

    roll = {round(x.t, 4): math.radians(x.rpy_deg[0]) for x in truth}
    out = []
    for s in imu:
        r1 = roll[round(s.t, 4)]
        r0 = roll.get(round(s.t - s.dt_s, 4), r1)
        rm = 0.5 * (r0 + r1)
        c, sn = math.cos(rm), math.sin(rm)
        c_cb = np.array([[c, 0.0, sn], [0.0, 1.0, 0.0], [-sn, 0.0, c]])  # Ry(roll): right wing down +
        dth = c_cb @ np.asarray(s.dtheta_rad) - np.array([0.0, r1 - r0, 0.0])
        dv = c_cb @ np.asarray(s.dvel_mps)
        out.append(ImuSample(t=s.t, dt_s=s.dt_s, dtheta_rad=tuple(dth), dvel_mps=tuple(dv)))
    del earth
    return out


def simulate_car_drive(
    tmp: Path,
    grade: str = "consumer_mems",
    duration_s: float = 60.0,
    seed: int = 5,
    pos_std_m: float = 0.5,
    gm_std_m: float = 0.0,
    stop_s: float = 0.0,
    level_turns: bool = False,
) -> Drive:
    """A car drive that starts in motion, IMU of ``grade`` (docs/imu_grades.md presets), 10 Hz fixes
    (white ``pos_std_m`` plus a 30 s Gauss-Markov error ``gm_std_m``, vertical 2x); ``stop_s``: a
    stop of that long after 11 s. ``level_turns``: the simulator flies the turns without roll (a
    car's body; the IMU and its errors as simulated, the truth's attitude the body's); else turns
    are coordinated and :func:`car_imu` rotates the IMU into a level-roll body afterwards (its
    biases then turn with the roll: not a real IMU's errors)."""
    from fednav.service.ins.imu_grades import PRESETS
    from fednav.simulators.scenario import load_scenario
    from fednav.simulators.stream import simulate

    p = tmp / f"car_{grade}_{seed}_{stop_s:g}{'_level' if level_turns else ''}.toml"
    p.write_text(
        CAR_SCENARIO_TOML.format(
            grade=grade,
            duration=duration_s,
            t0=T0_GPS_S,
            segments=car_segments(duration_s, stop_s, level_turns),
            g=PRESETS[grade],
            pos_std=pos_std_m,
            pos_std_u=2 * pos_std_m,
            gm=gm_std_m,
            gm_u=2 * gm_std_m,
        )
    )
    imu, fixes, truth = [], [], []
    for _key, msg in simulate(load_scenario(p), seed=seed):
        if isinstance(msg, ImuSample):
            imu.append(msg)
        elif isinstance(msg, GnssFix):
            fixes.append(msg)
        elif isinstance(msg, Truth):
            truth.append(msg)
    return Drive(imu if level_turns else car_imu(imu, truth), fixes, truth)


def trim(drive: Drive, start_s: float) -> Drive:
    """The drive without its first ``start_s`` seconds: a log that starts mid-manoeuvre."""
    t0 = drive.imu[0].t - drive.imu[0].dt_s + start_s
    return Drive(
        [s for s in drive.imu if s.t - s.dt_s >= t0 - 1e-9],
        [f for f in drive.fixes if f.t >= t0],
        [x for x in drive.truth if x.t >= t0],
    )


def service_config(tmp: Path, align_s: float = 8.0) -> Path:
    p = tmp / "service.toml"
    p.write_text(SERVICE_TOML.format(align=align_s))
    return p


# --- helpers --------------------------------------------------------------------------------------
def to_source(axes: str, v_rfu) -> np.ndarray:
    """A vector in fednav's RFU body axes -> the source's axes."""
    return axes_matrix(axes).T @ np.asarray(v_rfu, float)


def rates(s: ImuSample) -> tuple[np.ndarray, np.ndarray]:
    return np.asarray(s.dtheta_rad) / s.dt_s, np.asarray(s.dvel_mps) / s.dt_s


def gps_to_unix(t: float, leap: int = LEAP_SECONDS_NOW) -> float:
    return t + GPS_EPOCH_UNIX_S - leap


def gps_to_utc(t: float, leap: int = LEAP_SECONDS_NOW) -> dt.datetime:
    return dt.datetime.fromtimestamp(gps_to_unix(t, leap), dt.UTC)


# --- ROS (rosbags writers) ---------------------------------------------------------------------------
def _ros_msgs(ts, drive: Drive, axes: str, ros1: bool, imu_boot: bool = False):
    """(topic, msgtype, receive time (POSIX s), message) of sensor_msgs/Imu, NavSatFix and
    TwistWithCovarianceStamped. ``imu_boot``: the IMU's header stamps are seconds since the device
    booted (``BOOT_GPS_S``), received 2 ms after they were taken."""
    T = ts.types
    Time, Header = T["builtin_interfaces/msg/Time"], T["std_msgs/msg/Header"]
    V3, Q = T["geometry_msgs/msg/Vector3"], T["geometry_msgs/msg/Quaternion"]

    def header(t_unix: float, frame: str):
        sec = int(np.floor(t_unix))
        ns = int(round((t_unix - sec) * 1e9))
        if ns >= 1_000_000_000:
            sec, ns = sec + 1, ns - 1_000_000_000
        kw = {"stamp": Time(sec=sec, nanosec=ns), "frame_id": frame}
        if ros1:
            kw["seq"] = 0
        return Header(**kw)

    out = []
    for s in drive.imu:
        w, f = rates(s)
        w, f = to_source(axes, w), to_source(axes, f)
        tu = gps_to_unix(s.t)
        stamp = s.t - BOOT_GPS_S if imu_boot else tu
        if imu_boot:
            tu += 0.002
        msg = T["sensor_msgs/msg/Imu"](
            header=header(stamp, "imu_link"),
            orientation=Q(x=0.0, y=0.0, z=0.0, w=1.0),
            orientation_covariance=np.array([-1.0] + [0.0] * 8),
            angular_velocity=V3(x=w[0], y=w[1], z=w[2]),
            angular_velocity_covariance=np.zeros(9),
            linear_acceleration=V3(x=f[0], y=f[1], z=f[2]),
            linear_acceleration_covariance=np.zeros(9),
        )
        out.append(("/imu/data", "sensor_msgs/msg/Imu", tu, msg))
    for g in drive.fixes:
        tu = gps_to_unix(g.t)
        fix = T["sensor_msgs/msg/NavSatFix"](
            header=header(tu, "gnss"),
            status=T["sensor_msgs/msg/NavSatStatus"](status=0, service=1),
            latitude=g.lat_deg,
            longitude=g.lon_deg,
            altitude=g.height_m,
            position_covariance=np.diag(np.square(g.pos_std_enu_m)).ravel(),
            position_covariance_type=2,
        )
        out.append(("/gnss/fix", "sensor_msgs/msg/NavSatFix", tu, fix))
        cov = np.zeros((6, 6))
        cov[:3, :3] = np.diag(np.square(g.vel_std_enu_mps))
        cov[3:, 3:] = np.eye(3) * 1e6
        v = g.vel_enu_mps
        tw = T["geometry_msgs/msg/TwistWithCovarianceStamped"](
            header=header(tu, "gnss"),
            twist=T["geometry_msgs/msg/TwistWithCovariance"](
                twist=T["geometry_msgs/msg/Twist"](
                    linear=V3(x=v[0], y=v[1], z=v[2]), angular=V3(x=0.0, y=0.0, z=0.0)
                ),
                covariance=cov.ravel(),
            ),
        )
        out.append(("/gnss/vel", "geometry_msgs/msg/TwistWithCovarianceStamped", tu, tw))
    out.sort(key=lambda x: x[2])
    return out


def write_ros2(
    path: Path, drive: Drive, axes: str = "FLU", storage: str = "sqlite3", imu_boot: bool = False
) -> Path:
    """A ROS 2 bag directory (sqlite3 or MCAP storage); ``imu_boot``: IMU header stamps in boot time."""
    from rosbags.rosbag2 import StoragePlugin, Writer
    from rosbags.typesys import Stores, get_typestore

    ts = get_typestore(Stores.ROS2_HUMBLE)
    plugin = StoragePlugin.MCAP if storage == "mcap" else StoragePlugin.SQLITE3
    with Writer(path, version=9, storage_plugin=plugin) as w:
        conns = {}
        for topic, typ, tu, msg in _ros_msgs(ts, drive, axes, ros1=False, imu_boot=imu_boot):
            if topic not in conns:
                conns[topic] = w.add_connection(topic, typ, typestore=ts)
            w.write(conns[topic], int(round(tu * 1e9)), ts.serialize_cdr(msg, typ))
    return path


def write_mcap(path: Path, drive: Drive, axes: str = "FLU") -> Path:
    """A bare .mcap file (the MCAP file of a ROS 2 bag written with MCAP storage)."""
    bag = write_ros2(path.with_suffix(""), drive, axes, storage="mcap")
    (mcap,) = bag.glob("*.mcap")
    mcap.rename(path)
    return path


def write_ros1(path: Path, drive: Drive, axes: str = "FLU") -> Path:
    from rosbags.rosbag1 import Writer
    from rosbags.typesys import Stores, get_typestore

    ts = get_typestore(Stores.ROS1_NOETIC)
    with Writer(path) as w:
        conns = {}
        for topic, typ, tu, msg in _ros_msgs(ts, drive, axes, ros1=True):
            if topic not in conns:
                conns[topic] = w.add_connection(topic, typ, typestore=ts)
            w.write(conns[topic], int(round(tu * 1e9)), ts.serialize_ros1(msg, typ))
    return path


# --- NMEA (pynmea2) ---------------------------------------------------------------------------------
def _ddmm(deg: float, pos: str, neg: str, width: int) -> tuple[str, str]:
    a = abs(deg)
    d = int(a)
    return f"{d:0{width}d}{(a - d) * 60.0:011.8f}", pos if deg >= 0 else neg


def nmea_lines(drive: Drive, gst: bool = True) -> list[str]:
    import pynmea2

    lines = []
    for g in drive.fixes:
        utc = gps_to_utc(g.t)
        hms = f"{utc:%H%M%S}.{utc.microsecond // 10000:02d}"
        lat, ns = _ddmm(g.lat_deg, "N", "S", 2)
        lon, ew = _ddmm(g.lon_deg, "E", "W", 3)
        alt = g.height_m - GEOID_SEP_M
        gga = (hms, lat, ns, lon, ew, "1", "09", "0.9", f"{alt:.3f}", "M", f"{GEOID_SEP_M:.3f}", "M", "", "")
        lines.append(pynmea2.GGA("GP", "GGA", gga).render())
        ve, vn = g.vel_enu_mps[0], g.vel_enu_mps[1]
        speed = float(np.hypot(ve, vn))
        course = float(np.degrees(np.arctan2(ve, vn)) % 360.0)
        rmc = (
            hms,
            "A",
            lat,
            ns,
            lon,
            ew,
            f"{speed / (1852.0 / 3600.0):.4f}",
            f"{course:.3f}",
            f"{utc:%d%m%y}",
            "",
            "",
        )
        lines.append(pynmea2.RMC("GP", "RMC", rmc).render())
        if gst:
            e, n, u = g.pos_std_enu_m
            lines.append(
                pynmea2.GST(
                    "GP", "GST", (hms, "1.0", "", "", "", f"{n:.3f}", f"{e:.3f}", f"{u:.3f}")
                ).render()
            )
    return lines


def write_nmea(path: Path, drive: Drive, gst: bool = True, receive_latency_s: float | None = None) -> Path:
    """NMEA sentences; ``receive_latency_s``: every line led by the logger's own receive stamp in
    seconds since boot (``BOOT_GPS_S``), the receiver's output coming that long after its epoch."""
    lines = nmea_lines(drive, gst)
    if receive_latency_s is not None:
        per_epoch = len(lines) // len(drive.fixes)
        lines = [
            f"{drive.fixes[i // per_epoch].t - BOOT_GPS_S + receive_latency_s:.3f},{ln}"
            for i, ln in enumerate(lines)
        ]
    path.write_text("\n".join(lines) + "\n")
    return path


# --- CSV --------------------------------------------------------------------------------------------
def write_csv(
    path: Path,
    drive: Drive,
    axes: str = "FRD",
    form: str = "increment",
    boot: bool = True,
    negate: tuple[int, ...] = (),
) -> Path:
    """IMU CSV in ``axes``; increment form (deg, g*s) with a dt column, or rate form (deg/s, g).
    ``negate``: columns (1-3 gyro x/y/z, 4-6 accelerometer x/y/z) written with the opposite sign
    (a logger with one axis or one sensor's sign convention reversed)."""
    g0 = 9.80665
    out = io.StringIO()
    w = csv.writer(out)
    out.write("# fednav-replay IMU CSV test file\n")
    if form == "increment":
        w.writerow(["t", "dtheta_x", "dtheta_y", "dtheta_z", "dvel_x", "dvel_y", "dvel_z", "dt"])
    else:
        w.writerow(["t", "gyro_x", "gyro_y", "gyro_z", "accel_x", "accel_y", "accel_z"])
    for s in drive.imu:
        t = s.t - BOOT_GPS_S if boot else gps_to_unix(s.t)
        if form == "increment":
            vals = np.concatenate(
                [np.degrees(to_source(axes, s.dtheta_rad)), to_source(axes, s.dvel_mps) / g0]
            )
        else:
            wr, f = rates(s)
            vals = np.concatenate([np.degrees(to_source(axes, wr)), to_source(axes, f) / g0])
        for c in negate:
            vals[c - 1] = -vals[c - 1]
        row = [f"{t:.6f}", *(f"{x:.10e}" for x in vals)]
        w.writerow(row + [f"{s.dt_s:.6f}"] if form == "increment" else row)
    path.write_text(out.getvalue())
    return path


# --- UBX (pyubx2) -----------------------------------------------------------------------------------
def _esf_word(value: float, lsb: float, dtype: int) -> bytes:
    v = int(round(value / lsb)) & 0xFFFFFF
    return (v | (dtype << 24)).to_bytes(4, "little")


def ubx_bytes(drive: Drive, axes: str = "FRD") -> bytes:
    from pyubx2 import GET, UBXMessage

    msgs: list[tuple[float, bytes]] = []
    for s in drive.imu:
        wr, f = rates(s)
        w_deg, f_src = np.degrees(to_source(axes, wr)), to_source(axes, f)
        tag = int(round((s.t - BOOT_GPS_S) / UBX_TICK_S)).to_bytes(4, "little")
        payload = b"\0\0\0\0"
        for val, lsb, typ in (
            (w_deg[0], 2.0**-12, 14),
            (w_deg[1], 2.0**-12, 13),
            (w_deg[2], 2.0**-12, 5),
            (f_src[0], 2.0**-10, 16),
            (f_src[1], 2.0**-10, 17),
            (f_src[2], 2.0**-10, 18),
        ):
            payload += _esf_word(val, lsb, typ) + tag
        msgs.append((s.t, UBXMessage("ESF", "ESF-RAW", GET, payload=payload).serialize()))
    for g in drive.fixes:
        utc = gps_to_utc(g.t)
        tow_ms = int(round((g.t % 604800.0) * 1000.0))
        whole = utc.replace(microsecond=0)
        m = UBXMessage(
            "NAV",
            "NAV-PVT",
            GET,
            iTOW=tow_ms,
            year=whole.year,
            month=whole.month,
            day=whole.day,
            hour=whole.hour,
            min=whole.minute,
            second=whole.second,
            nano=utc.microsecond * 1000,
            validDate=1,
            validTime=1,
            fixType=3,
            gnssFixOk=1,
            numSV=12,
            lat=g.lat_deg,
            lon=g.lon_deg,
            height=int(round(g.height_m * 1000.0)),
            hMSL=int(round((g.height_m - GEOID_SEP_M) * 1000.0)),
            hAcc=int(round(g.pos_std_enu_m[0] * np.sqrt(2.0) * 1000.0)),
            vAcc=int(round(g.pos_std_enu_m[2] * 1000.0)),
            velN=int(round(g.vel_enu_mps[1] * 1000.0)),
            velE=int(round(g.vel_enu_mps[0] * 1000.0)),
            velD=int(round(-g.vel_enu_mps[2] * 1000.0)),
            sAcc=int(round(g.vel_std_enu_mps[0] * 1000.0)),
        )
        msgs.append((g.t, m.serialize()))
    msgs.sort(key=lambda x: x[0])
    return b"".join(b for _, b in msgs)


def write_ubx(path: Path, drive: Drive, axes: str = "FRD") -> Path:
    path.write_bytes(ubx_bytes(drive, axes))
    return path


# --- mappings ---------------------------------------------------------------------------------------
def write_all(tmp: Path, drive: Drive, only: tuple[str, ...] | None = None) -> dict[str, Path]:
    """Every format's files and a mapping file for each (``only``: these cases: ros2, ros1, mcap,
    nmea_csv, ubx); returns {case: mapping path}."""
    tmp.mkdir(parents=True, exist_ok=True)
    want = set(only or ("ros2", "ros1", "mcap", "nmea_csv", "ubx"))
    if "ros2" in want:
        write_ros2(tmp / "drive_ros2", drive)
    if "ros1" in want:
        write_ros1(tmp / "drive.bag", drive)
    if "mcap" in want:
        write_mcap(tmp / "drive.mcap", drive)
    if "nmea_csv" in want:
        write_nmea(tmp / "drive.nmea", drive)
        write_csv(tmp / "imu.csv", drive)
    if "ubx" in want:
        write_ubx(tmp / "drive.ubx", drive)
    ros = """
[[streams]]
source = "{src}"
kind = "imu"
sensor_id = "imu"
topic = "/imu/data"
axes = "FLU"
time_base = "unix"

[[streams]]
source = "{src}"
kind = "gnss_fix"
sensor_id = "rx"
topic = "/gnss/fix"
twist_topic = "/gnss/vel"
time_base = "unix"
"""
    cases = {
        "ros2": ros.format(src="drive_ros2"),
        "ros1": ros.format(src="drive.bag"),
        "mcap": ros.format(src="drive.mcap"),
        "nmea_csv": f"""
[[streams]]
source = "imu.csv"
kind = "imu"
sensor_id = "imu"
axes = "FRD"
form = "increment"
gyro_unit = "deg/s"
accel_unit = "g"
time_base = "boot"
boot_offset_s = {BOOT_GPS_S}

[[streams]]
source = "drive.nmea"
kind = "gnss_fix"
sensor_id = "rx"
time_base = "utc"
""",
        "ubx": f"""
[[streams]]
source = "drive.ubx"
kind = "imu"
sensor_id = "imu"
axes = "FRD"
time_base = "boot"
boot_offset_s = {BOOT_GPS_S}
tick_s = {UBX_TICK_S}

[[streams]]
source = "drive.ubx"
kind = "gnss_fix"
sensor_id = "rx"
time_base = "gps"
""",
    }
    out = {}
    for name, text in cases.items():
        if name not in want:
            continue
        p = tmp / f"{name}.toml"
        p.write_text(f'vehicle = "{name}"\n' + text)
        out[name] = p
    return out


# --- a configuration on a drive, against its truth ------------------------------------------------------
def evaluate_config(drive: Drive, cfg, vehicle: str = "v1", skip_s: float = 20.0) -> dict:
    """Run the service's per-vehicle loop in-process on the drive's messages (IMU, fixes, truth in
    time order) with configuration ``cfg``; position errors against truth after ``skip_s`` from the
    first solution: horizontal / vertical RMS error, RMS reported sigma, their ratio, NEES/3."""
    import heapq

    from fednav.service.vehicle import VehicleLoop

    class Sink:
        def __init__(self):
            self.rows = []

        def on_estimate(self, v, out):
            if out.err9 is not None:
                self.rows.append((out.t, np.asarray(out.err9[:3]), np.asarray(out.P9[:3, :3])))

        def on_output(self, v, msg, err9=None):
            pass

        def on_truth(self, v, truth):
            pass

    sink = Sink()
    loop = VehicleLoop(vehicle, cfg, sink)
    streams = [
        [(m.t, 1, "imu", "imu", m) for m in drive.imu],
        [(m.t, 0, "gnss_fix", "rx", m) for m in drive.fixes],
        [(m.t, -1, "truth", "", m) for m in drive.truth],
    ]
    for _t, _o, kind, sid, msg in heapq.merge(*streams, key=lambda x: (x[0], x[1])):
        loop.process(kind, sid, msg)
    if not sink.rows:
        return {"solutions": 0}
    t0 = sink.rows[0][0]
    rows = [r for r in sink.rows if r[0] - t0 >= skip_s]
    e = np.array([r[1] for r in rows])
    P = np.array([r[2] for r in rows])
    h_err = np.hypot(e[:, 0], e[:, 1])
    h_sig = np.sqrt(P[:, 0, 0] + P[:, 1, 1])
    nees = [float(x @ np.linalg.solve(p, x)) for x, p in zip(e, P, strict=True)]
    return {
        "solutions": len(rows),
        "h_rms_m": float(np.sqrt(np.mean(h_err**2))),
        "h_max_m": float(h_err.max()),
        "h_sigma_rms_m": float(np.sqrt(np.mean(h_sig**2))),
        "h_err_over_sigma": float(np.sqrt(np.mean(h_err**2)) / np.sqrt(np.mean(h_sig**2))),
        "v_err_over_sigma": float(np.sqrt(np.mean(e[:, 2] ** 2)) / np.sqrt(np.mean(P[:, 2, 2]))),
        "nees_per_dof": float(np.mean(nees) / 3.0),
    }


def record_replay(mapping_path: Path, cfg, out: Path, health_period_s: float = 1.0) -> dict:
    """A replay recorded in-process, as fednav-record records a scenario: the mapping's events
    through the service's per-vehicle loop (service.vehicle.VehicleLoop) into the service's output
    sink and Rerun sink (the recording the service would write), health every ``health_period_s`` of
    sensor time. Returns the loop's counters."""
    from fednav.dashboards.blueprints import blueprint_factory
    from fednav.replay.mapping import load_mapping
    from fednav.replay.sources import all_events
    from fednav.service import keys
    from fednav.service.app import OutputSink
    from fednav.service.config import recording_kinds
    from fednav.service.transport.rerun_sink import RerunSink
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
    return {"received": loop.received, "accepted": loop.accepted, "rejected": dict(loop.counters)}
