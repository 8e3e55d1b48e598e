"""A ROS-shaped publisher without ROS: a scenario's IMU and GNSS as sensor_msgs/Imu, NavSatFix and
geometry_msgs/TwistWithCovarianceStamped in CDR over Zenoh, under rmw_zenoh's or
zenoh-bridge-ros2dds' keys (what a robot's drivers publish; docs/ros2.md). For trying and testing
fednav-service's [ros2] bridge.

    python -m fednav.simulators.ros2_publish SCENARIO.toml --connect tcp/127.0.0.1:7447 [--carrier ros2dds]
        [--no-twist]

Imu: angular_velocity and linear_acceleration are each interval's mean rate (increment / dt) in
body FLU (REP 103) stamped at the interval's end, the bridge's ``imu_integration = "rectangle"``
reading recovers the increments exactly. NavSatFix: position with its diagonal covariance (ENU);
Twist: ENU velocity with its covariance, stamped like the fix (``--no-twist``: none, as a robot
whose GNSS driver publishes no velocity; the bridge then forwards each fix position-only after
``twist_wait_s``). InitialNav and Truth are not sent (a ROS robot has neither): the service aligns
in motion from the first fix with a Twist, statically (the vehicle standing still) without.
Each publisher's attachment carries its own 16-byte GID.
"""

from __future__ import annotations

import argparse
import sys
from collections.abc import Iterator
from pathlib import Path

import numpy as np

from fednav.service.messages import GnssFix, ImuSample
from fednav.service.ros2_config import Ros2Config
from fednav.service.transport import ros2

RFU_TO_FLU = ros2.FLU_TO_RFU.T
#: how long the publisher waits for the service (or router) at its endpoint when started first
CONNECT_WAIT_S = 30.0

#: default topics (the bridge's example configuration in docs/ros2.md uses the same)
IMU_TOPIC, FIX_TOPIC, VEL_TOPIC = "/imu/data", "/gnss/fix", "/gnss/vel"


def example_config(vehicle: str = "v1", carrier: str = "rmw_zenoh", **kw) -> Ros2Config:
    """The [ros2] table matching this publisher's topics."""
    return Ros2Config.model_validate(
        {
            "vehicle": vehicle,
            "carrier": carrier,
            "imu_integration": "rectangle",
            "inputs": [
                {"topic": IMU_TOPIC, "type": "sensor_msgs/msg/Imu", "sensor_id": "main"},
                {"topic": FIX_TOPIC, "type": "sensor_msgs/msg/NavSatFix", "sensor_id": "main"},
                {
                    "topic": VEL_TOPIC,
                    "type": "geometry_msgs/msg/TwistWithCovarianceStamped",
                    "sensor_id": "main",
                },
            ],
        }
        | kw
    )


def _header(T, t: float, frame: str, cfg: Ros2Config):
    sec, ns = ros2.t_to_stamp(t, cfg.stamp_time_base, cfg.leap_seconds)
    return T["std_msgs/msg/Header"](
        stamp=T["builtin_interfaces/msg/Time"](sec=sec, nanosec=ns), frame_id=frame
    )


def to_ros(msg, cfg: Ros2Config, twist: bool = True) -> list[tuple[str, object]]:
    """(topic, rosbags message) for one fednav sensor message (ImuSample, GnssFix; others: []);
    ``twist`` False: a GnssFix gives its NavSatFix only."""
    T = ros2.typestore(cfg.distro).types
    v3 = T["geometry_msgs/msg/Vector3"]
    if isinstance(msg, ImuSample):
        w = RFU_TO_FLU @ np.asarray(msg.dtheta_rad) / msg.dt_s
        a = RFU_TO_FLU @ np.asarray(msg.dvel_mps) / msg.dt_s
        imu = T["sensor_msgs/msg/Imu"](
            header=_header(T, msg.t, "imu_link", cfg),
            orientation=T["geometry_msgs/msg/Quaternion"](x=0.0, y=0.0, z=0.0, w=1.0),
            orientation_covariance=np.r_[-1.0, np.zeros(8)],  # REP 145: no orientation estimate
            angular_velocity=v3(x=w[0], y=w[1], z=w[2]),
            angular_velocity_covariance=np.zeros(9),
            linear_acceleration=v3(x=a[0], y=a[1], z=a[2]),
            linear_acceleration_covariance=np.zeros(9),
        )
        return [(IMU_TOPIC, imu)]
    if isinstance(msg, GnssFix):
        fix = T["sensor_msgs/msg/NavSatFix"](
            header=_header(T, msg.t, "gnss", cfg),
            status=T["sensor_msgs/msg/NavSatStatus"](status=0, service=1),
            latitude=msg.lat_deg,
            longitude=msg.lon_deg,
            altitude=msg.height_m,
            position_covariance=np.diag(np.square(msg.pos_std_enu_m)).reshape(9),
            position_covariance_type=2,  # DIAGONAL_KNOWN
        )
        if not twist or msg.vel_enu_mps is None:
            return [(FIX_TOPIC, fix)]
        cov = np.zeros((6, 6))
        cov[:3, :3] = np.diag(np.square(msg.vel_std_enu_mps))
        cov[3:, 3:] = np.eye(3) * ros2.UNKNOWN_VARIANCE
        v = msg.vel_enu_mps
        tw = T["geometry_msgs/msg/TwistWithCovarianceStamped"](
            header=_header(T, msg.t, "gnss", cfg),
            twist=T["geometry_msgs/msg/TwistWithCovariance"](
                twist=T["geometry_msgs/msg/Twist"](
                    linear=v3(x=v[0], y=v[1], z=v[2]), angular=v3(x=0.0, y=0.0, z=0.0)
                ),
                covariance=cov.reshape(36),
            ),
        )
        return [(FIX_TOPIC, fix), (VEL_TOPIC, tw)]
    return []


def ros_samples(
    scenario, seed: int, cfg: Ros2Config, twist: bool = True
) -> Iterator[tuple[str, bytes, object]]:
    """(Zenoh key, CDR payload, fednav message) of a scenario run, in time order (``twist`` False:
    no Twist messages)."""
    from fednav.simulators.stream import simulate

    store = ros2.typestore(cfg.distro)
    for _, m in simulate(scenario, seed=seed, vehicle=cfg.vehicle):
        for topic, rmsg in to_ros(m, cfg, twist):
            yield (
                ros2.topic_key(cfg, topic, rmsg.__msgtype__),
                bytes(store.serialize_cdr(rmsg, rmsg.__msgtype__)),
                m,
            )


def publish(session, samples, *, attachment: bool = True, speed: float = 1.0) -> int:
    """Publish (key, payload, message) samples reliably, blocking on congestion, paced at ``speed``
    x real time by the messages' sensor time (0: as fast as possible), rmw_zenoh's attachment on
    each (a GID per publisher: :func:`ros2.entity_gid` of its key). Pacing matters: the service
    subscribes each ROS topic separately (as a ROS node does), so only samples published in time
    order across topics arrive in time order."""
    import time

    import zenoh

    t0 = wall0 = None

    pubs: dict[str, object] = {}
    seq: dict[str, int] = {}
    gids: dict[str, bytes] = {}
    n = 0
    for key, payload, m in samples:
        if speed > 0:
            if t0 is None:
                t0, wall0 = m.t, time.monotonic()
            ahead = (m.t - t0) / speed - (time.monotonic() - wall0)
            if ahead > 0:
                time.sleep(ahead)
        pub = pubs.get(key)
        if pub is None:
            pub = pubs[key] = session.declare_publisher(
                key, congestion_control=zenoh.CongestionControl.BLOCK, reliability=zenoh.Reliability.RELIABLE
            )
            gids[key] = ros2.entity_gid(f"fednav.simulators.ros2_publish/{key}")
        seq[key] = seq.get(key, 0) + 1
        att = ros2.rmw_attachment(seq[key], time.time_ns(), gids[key]) if attachment else None
        pub.put(payload, attachment=att)
        n += 1
    for p in pubs.values():
        p.undeclare()
    return n


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(
        description="Publish a scenario's IMU and GNSS as ROS 2 messages (CDR) over Zenoh",
        epilog="example: python -m fednav.simulators.ros2_publish simulators/scenarios/demo_aircraft.toml "
        "--connect tcp/127.0.0.1:7447",
    )
    ap.add_argument("scenario", type=Path, help="scenario TOML (simulators/scenarios/)")
    ap.add_argument("--connect", default="tcp/127.0.0.1:7447", help="Zenoh endpoint (default: %(default)s)")
    ap.add_argument("--carrier", choices=["rmw_zenoh", "ros2dds"], default="rmw_zenoh", help="key format")
    ap.add_argument("--domain-id", type=int, default=0, help="ROS_DOMAIN_ID (default: %(default)s)")
    ap.add_argument("--seed", type=int, default=None, help="seed (default: the scenario's)")
    ap.add_argument(
        "--speed", type=float, default=1.0, help="x real time, 0 = unpaced (default: %(default)s)"
    )
    ap.add_argument(
        "--no-twist", action="store_true", help="publish no Twist (a receiver without a velocity topic)"
    )
    ap.add_argument(
        "--vehicle",
        default="*",
        help="the fednav vehicle the service feeds from these topics: the end-of-stream check asks "
        "its status (default: every vehicle's)",
    )
    args = ap.parse_args(argv)

    from fednav.service import keys
    from fednav.service.config import ZenohConfig
    from fednav.service.transport.zenoh_io import PUBLISHER_BLOCK_WAIT_S, make_config
    from fednav.simulators.publisher import MatchTimeout, drain, open_session
    from fednav.simulators.scenario import load_scenario_cli

    if args.vehicle != "*" and not keys.valid_name(args.vehicle):
        print(f"ros2_publish: --vehicle {args.vehicle!r} is not a valid vehicle name", file=sys.stderr)
        return 2
    sc = load_scenario_cli(args.scenario, "ros2_publish")
    if sc is None:
        return 2
    cfg = example_config(carrier=args.carrier, domain_id=args.domain_id)
    seed = sc.seed if args.seed is None else args.seed
    conf = make_config(
        ZenohConfig(mode="client"),
        listen=[],
        connect=[args.connect],
        block_wait_s=PUBLISHER_BLOCK_WAIT_S,
    )
    try:
        session = open_session(conf, CONNECT_WAIT_S)
    except MatchTimeout as exc:
        print(f"ros2_publish: {exc}", file=sys.stderr)
        return 3
    with session as s:
        samples = ros_samples(sc, seed, cfg, twist=not args.no_twist)
        n = publish(s, samples, attachment=args.carrier == "rmw_zenoh", speed=args.speed)
        # what is still queued reaches the service before the session closes (publisher.drain);
        # by default every vehicle's status: the service maps the topics to a vehicle of its own
        drained = drain(s, [f"{keys.DEFAULT_PREFIX}/{args.vehicle}/service/status"])
    print(f"published {n} ROS 2 samples")
    if drained is False:
        print("ros2_publish: the service did not confirm the end of the stream in time", file=sys.stderr)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
