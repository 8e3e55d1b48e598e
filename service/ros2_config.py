"""Configuration of the ROS 2 bridge: the ``[ros2]`` table of the service configuration.

Validated with the rest of the configuration at load (unknown keys refused, errors name the
field). The bridge itself is :mod:`service.transport.ros2`; docs/ros2.md explains the mapping.
"""

from __future__ import annotations

import re
from typing import Literal

from pydantic import BaseModel, ConfigDict, Field, field_validator, model_validator

#: ROS 2 message types the bridge decodes, and the fednav sensor kind each one feeds
INPUT_TYPES: dict[str, str] = {
    "sensor_msgs/msg/Imu": "imu",
    "sensor_msgs/msg/NavSatFix": "gnss_fix",
    "geometry_msgs/msg/TwistWithCovarianceStamped": "gnss_fix",  # velocity paired with a NavSatFix
}

_TOPIC = re.compile(r"^/?[A-Za-z_~][A-Za-z0-9_]*(/[A-Za-z_][A-Za-z0-9_]*)*$")
_FRAME = re.compile(r"^[A-Za-z_][A-Za-z0-9_/]*$")
_SENSOR_ID = re.compile(r"^[A-Za-z0-9_\-]{1,64}$")


def _topic(v: str) -> str:
    if not _TOPIC.match(v) or v.startswith("/~"):
        raise ValueError(f"{v!r} is not a ROS 2 topic name (letters, digits, '_', '/'-separated tokens)")
    return v if v.startswith("/") else "/" + v


class _Model(BaseModel):
    model_config = ConfigDict(extra="forbid", frozen=True)


class Ros2Input(_Model):
    """One ROS 2 topic read by the bridge."""

    topic: str = Field(description="ROS 2 topic name, e.g. /imu/data (namespace-relative names get a '/')")
    type: str = Field(
        description="ROS 2 message type of the topic: sensor_msgs/msg/Imu, sensor_msgs/msg/NavSatFix, "
        "geometry_msgs/msg/TwistWithCovarianceStamped, or a type a sensor registry entry decodes (e.g. "
        "sensor_msgs/msg/FluidPressure for the barometer)"
    )
    sensor_id: str = Field(
        description="fednav sensor id the messages are delivered as (a NavSatFix and the Twist paired with "
        "it share one id)"
    )
    velocity_frame: Literal["enu", "ned"] = Field(
        "enu",
        description="Twist only: the frame of twist.linear (GNSS receiver drivers publish east/north/up; "
        "'ned' for north/east/down)",
    )

    @field_validator("topic")
    @classmethod
    def _check_topic(cls, v: str) -> str:
        return _topic(v)

    @field_validator("type")
    @classmethod
    def _check_type(cls, v: str) -> str:
        if v in INPUT_TYPES:
            return v
        from fednav.service import sensors

        if sensors.ros2_decoder(v) is None:
            known = sorted(INPUT_TYPES) + sorted(t for s in sensors.registry().values() for t in s.ros2)
            raise ValueError(f"{v!r} is not a ROS 2 type the bridge decodes; known: {known}")
        return v

    @field_validator("sensor_id")
    @classmethod
    def _sid(cls, v: str) -> str:
        if not _SENSOR_ID.match(v):
            raise ValueError("sensor_id: 1-64 letters, digits, '_' or '-'")
        return v


class Ros2Outputs(_Model):
    """Topics the bridge republishes the service's outputs on. ``{vehicle}`` and ``{pipeline}`` in a
    topic are replaced by their names; an empty topic turns that output off."""

    pipelines: list[str] = Field(
        default_factory=list, description="Pipelines republished (empty: every configured pipeline)"
    )
    odometry_topic: str = Field("/fednav/{pipeline}/odometry", description="nav_msgs/msg/Odometry")
    navsatfix_topic: str = Field("/fednav/{pipeline}/fix", description="sensor_msgs/msg/NavSatFix")
    diagnostics_topic: str = Field("/diagnostics", description="diagnostic_msgs/msg/DiagnosticArray")
    tf: bool = Field(False, description="Also publish tf2_msgs/msg/TFMessage map_frame -> base_frame")
    tf_pipeline: str | None = Field(
        None, description="Pipeline whose pose goes on /tf (None: the first republished pipeline)"
    )
    tf_topic: str = Field("/tf", description="Topic of the TFMessage")
    map_frame: str = Field("map", description="header.frame_id of Odometry and TF (local ENU at the datum)")
    base_frame: str = Field("base_link", description="child_frame_id of Odometry and TF (body, REP 103 FLU)")
    navsat_frame: str = Field("gnss", description="header.frame_id of the NavSatFix output")
    datum: tuple[float, float, float] | None = Field(
        None,
        description="Origin of map_frame [lat_deg, lon_deg, height_m] (None: the first solution of each "
        "pipeline)",
    )

    @field_validator("odometry_topic", "navsatfix_topic", "diagnostics_topic", "tf_topic")
    @classmethod
    def _topics(cls, v: str) -> str:
        if v == "":
            return v
        _topic(v.replace("{vehicle}", "vehicle").replace("{pipeline}", "pipeline"))
        return v if v.startswith("/") else "/" + v

    @field_validator("map_frame", "base_frame", "navsat_frame")
    @classmethod
    def _frames(cls, v: str) -> str:
        if not _FRAME.match(v):
            raise ValueError(f"{v!r} is not a frame id (letters, digits, '_', '/')")
        return v

    @field_validator("datum")
    @classmethod
    def _datum(cls, v):
        if v is not None and not (-90.0 <= v[0] <= 90.0 and -180.0 <= v[1] <= 180.0 and -12000 < v[2] < 1e5):
            raise ValueError("datum: [lat_deg in [-90, 90], lon_deg in [-180, 180], height_m]")
        return v


class Ros2Config(_Model):
    """The ROS 2 bridge: ROS 2 topics in (CDR over Zenoh) -> fednav sensors of one vehicle; the
    vehicle's solutions and health out as ROS 2 messages (CDR over Zenoh)."""

    carrier: Literal["rmw_zenoh", "ros2dds"] = Field(
        "rmw_zenoh",
        description="Key format: rmw_zenoh (<domain_id>/<topic>/<type>/<type hash>) or zenoh-bridge-ros2dds "
        "(<namespace>/<topic>)",
    )
    domain_id: int = Field(0, ge=0, le=232, description="ROS_DOMAIN_ID (rmw_zenoh keys)")
    namespace: str = Field(
        "", description="zenoh-bridge-ros2dds 'namespace' option: a key prefix of every topic (ros2dds keys)"
    )
    distro: Literal["humble", "jazzy"] = Field(
        "jazzy",
        description="Message definitions and type hash: jazzy (RIHS01 hashes) or humble (rmw_zenoh on "
        "Humble writes 'TypeHashNotSupported')",
    )
    vehicle: str = Field(description="fednav vehicle the ROS 2 inputs feed and whose outputs are republished")
    stamp_time_base: Literal["utc", "gps"] = Field(
        "utc",
        description="header.stamp time base: utc (ROS time: unix seconds, converted to GPS time with "
        "leap_seconds) or gps (already seconds of GPS time)",
    )
    leap_seconds: int = Field(18, ge=0, le=100, description="GPS - UTC in seconds (18 since 2017-01-01)")
    imu_integration: Literal["trapezoid", "rectangle"] = Field(
        "trapezoid",
        description="Rates -> increments over the interval between two Imu stamps: the mean of both "
        "samples' rates (trapezoid) or the newer sample's rate (rectangle) times dt",
    )
    pair_tolerance_s: float = Field(
        0.05,
        gt=0.0,
        le=1.0,
        description="A NavSatFix and a Twist are one fix when their stamps differ by less",
    )
    twist_wait_s: float = Field(
        0.2,
        gt=0.0,
        le=1.0,
        description="A NavSatFix of a receiver with a Twist topic waits at most this long (stamp time: the "
        "newest header.stamp decoded) for its Twist, or until the receiver's next fix; then it goes on "
        "position-only (counted fix_without_velocity). Keep it below [intake] late_tolerance_s",
    )
    fix_std_m: float = Field(
        10.0,
        gt=0.0,
        description="1-sigma position used when a NavSatFix reports no covariance (type UNKNOWN)",
    )
    vel_std_mps: float = Field(
        0.5, gt=0.0, description="1-sigma velocity used when a Twist reports no covariance (zeros)"
    )
    attachment: Literal["rmw_zenoh", "rmw_zenoh_keyed", "none"] = Field(
        "rmw_zenoh",
        description="rmw_zenoh carrier: the attachment on published samples: rmw_zenoh (int64 sequence "
        "number, int64 source timestamp ns, 16-byte GID, Zenoh's serializer: rmw_zenoh since its zenoh-cpp "
        "port), rmw_zenoh_keyed (the earlier layout, a key string before each value) or none",
    )
    liveliness: bool = Field(
        True,
        description="rmw_zenoh carrier: declare rmw_zenoh graph tokens (a node, its publishers and "
        "subscriptions) so ros2 node/topic list and matched counts see the bridge",
    )
    node_name: str = Field("fednav", description="ROS 2 node name of the bridge in the graph tokens")
    inputs: list[Ros2Input] = Field(default_factory=list, description="ROS 2 topics read")
    outputs: Ros2Outputs = Field(default_factory=Ros2Outputs, description="ROS 2 topics written")

    @field_validator("node_name")
    @classmethod
    def _node(cls, v: str) -> str:
        if not re.match(r"^[A-Za-z_][A-Za-z0-9_]*$", v):
            raise ValueError(f"{v!r} is not a ROS 2 node name (letters, digits, '_')")
        return v

    @field_validator("namespace")
    @classmethod
    def _ns(cls, v: str) -> str:
        v = v.strip("/")
        if v and not _TOPIC.match(v):
            raise ValueError(f"{v!r} is not a namespace ('/'-separated names)")
        return v

    @model_validator(mode="after")
    def _pairs(self):
        seen: dict[tuple[str, str], str] = {}
        for i in self.inputs:
            key = (i.type, i.sensor_id)
            if key in seen:
                raise ValueError(
                    f"inputs: two {i.type} topics ({seen[key]}, {i.topic}) share sensor_id {i.sensor_id!r}"
                )
            seen[key] = i.topic
        fixes = {i.sensor_id for i in self.inputs if i.type == "sensor_msgs/msg/NavSatFix"}
        for i in self.inputs:
            if i.type == "geometry_msgs/msg/TwistWithCovarianceStamped" and i.sensor_id not in fixes:
                raise ValueError(
                    f"inputs: the Twist topic {i.topic} has sensor_id {i.sensor_id!r} but no NavSatFix topic "
                    "has it (a Twist is the velocity of a NavSatFix)"
                )
        # a NavSatFix without a Twist topic is fine: it gives position-only GnssFix messages
        if self.twist_wait_s < self.pair_tolerance_s:
            raise ValueError(
                f"twist_wait_s ({self.twist_wait_s}) is below pair_tolerance_s ({self.pair_tolerance_s}): a "
                "fix would give up on a Twist that still pairs with it"
            )
        return self
