"""Barometric altimeter: everything fednav needs of it, in this one file plus one registry line.

A barometer reads the altitude of the standard atmosphere for the pressure it measures. Against
the ellipsoidal height that differs by a slowly varying offset (the day's weather, the geoid, the
sensor's own bias: metres to tens of metres), so the model estimates that offset as a private
state (random walk), observed against the GNSS height; the barometer then holds the vertical
channel with its own low noise and keeps it during GNSS outages.

- Wire message :class:`BaroAltitude` (key ``{prefix}/{vehicle}/sensor/baro/{id}``).
- Measurement model :class:`BaroModel`: ``z = h_ins + b_ref - h_baro = dp_u + db + v`` with the
  offset ``b`` a private state (closed loop: ``b_ref`` absorbs its feedback).
- Options in a pipeline's ``sensor_options.baro`` (:class:`BaroOptions`).
- Simulator: a scenario's ``[sensors.baro]`` table (:class:`BaroSim`).
- fednav-replay: a CSV stream ``kind = "baro"`` with columns ``t, altitude_m[, std_m]``.
- ROS 2: ``sensor_msgs/msg/FluidPressure`` (pressure in Pa) through the standard atmosphere.
"""

from __future__ import annotations

import math

import numpy as np
from pydantic import BaseModel, ConfigDict, Field

from fednav.service.estimation.measurements.base import Measurement, ModelContext, PrivateStates
from fednav.service.ins import error_model as em
from fednav.service.ins.mechanisation import NavState
from fednav.service.messages import Height, Time, WireModel
from fednav.service.sensors import SensorKind

BLOCK = "baro_offset"
#: smallest sigma a barometer reading is given (a claim of less pins the vertical channel)
MIN_STD_M = 0.05


class BaroAltitude(WireModel):
    """A barometric altitude: the standard-atmosphere altitude of the measured pressure, m. Its
    offset from the ellipsoidal height (weather, geoid, bias) is estimated by the service."""

    t: Time
    altitude_m: Height
    std_m: float = Field(0.5, gt=0.0, le=1e4, description="1-sigma noise of the reading, m")


class BaroOptions(BaseModel):
    """Options of the barometer model in a pipeline (``sensor_options.baro``)."""

    model_config = ConfigDict(extra="forbid", frozen=True)

    offset_std_m: float = Field(
        30.0, gt=0.0, le=1e4, description="Prior 1-sigma of the barometer's offset from ellipsoidal height, m"
    )
    offset_rw_mps: float = Field(
        0.01,
        ge=0.0,
        le=10.0,
        description="Random walk of the offset, m/sqrt(s) (weather fronts drift it by ~1 m per 10 min)",
    )


class BaroModel:
    """Barometric height with an estimated offset (private state ``baro_offset``)."""

    kind = "baro"
    # the class has no private states (so any 15-state filter accepts the kind); an instance
    # declares its offset block (the bank is built with it)
    private_states: tuple[PrivateStates, ...] = ()

    def __init__(self, offset_std_m: float = 30.0, offset_rw_mps: float = 0.01):
        q = float(offset_rw_mps) ** 2

        def transition(T: float) -> tuple[np.ndarray, np.ndarray]:
            return np.eye(1), np.array([[q * T]])

        self.private_states = (PrivateStates(BLOCK, ("baro_offset_m",), transition, (float(offset_std_m),)),)

    def __call__(self, nav: NavState, msg: BaroAltitude, ctx: ModelContext) -> Measurement | None:
        cols = ctx.columns.get(BLOCK)
        if cols is None:
            raise ValueError("the barometer model needs a filter with its 'baro_offset' block")
        H = np.zeros((1, ctx.n_states))
        H[0, em.POS.start + 2] = 1.0  # dp_u
        H[0, cols] = 1.0
        z = np.array([nav.h_m + float(ctx.reference[BLOCK][0]) - msg.altitude_m])
        if not np.all(np.isfinite(z)):
            return None
        std = max(float(msg.std_m), MIN_STD_M)
        return Measurement(z, H, np.array([[std * std]]), ("baro_h",), floored=int(msg.std_m < MIN_STD_M))


# --- simulator hook ---------------------------------------------------------------------------------
class BaroSim(BaseModel):
    """A scenario's ``[sensors.baro]`` table."""

    model_config = ConfigDict(extra="forbid", frozen=True)

    id: str = Field("baro", description="Sensor id in the key")
    rate_hz: float = Field(10.0, gt=0.0, le=1000.0, description="Reading rate, Hz (divides the IMU rate)")
    noise_std_m: float = Field(0.3, gt=0.0, description="White noise of a reading, m")
    offset_m: float = Field(12.0, description="Offset from ellipsoidal height at the start, m")
    offset_rw_mps: float = Field(0.005, ge=0.0, description="Random walk of the offset, m/sqrt(s)")


def simulate(spec: BaroSim, traj, rng: np.random.Generator) -> list[tuple[int, BaroAltitude]]:
    """Readings at ``rate_hz`` on the trajectory: true height + drifting offset + white noise,
    as (IMU sample index, message)."""
    step = max(1, int(round(traj.imu_rate_hz / spec.rate_hz)))
    ks = np.arange(step, traj.t_s.size, step)
    dt = step / traj.imu_rate_hz
    offset = spec.offset_m + np.cumsum(rng.normal(0.0, spec.offset_rw_mps * math.sqrt(dt), ks.size))
    alt = traj.llh[ks, 2] + offset + rng.normal(0.0, spec.noise_std_m, ks.size)
    t = traj.t_s[ks]
    return [
        (int(k), BaroAltitude(t=float(tk), altitude_m=float(a), std_m=spec.noise_std_m))
        for k, tk, a in zip(ks.tolist(), t.tolist(), alt.tolist(), strict=True)
    ]


# --- fednav-replay hook -----------------------------------------------------------------------------
def from_csv(row: dict[str, float], sensor_id: str) -> BaroAltitude:
    """A CSV row (``t`` already in GPS seconds) -> a reading; ``std_m`` optional."""
    fields = {"t": row["t"], "altitude_m": row["altitude_m"]}
    if row.get("std_m") is not None:
        fields["std_m"] = row["std_m"]
    return BaroAltitude.model_validate(fields)


# --- ROS 2 hook -------------------------------------------------------------------------------------
P0_PA, T0_K, LAPSE_KPM, G0, R_AIR = 101_325.0, 288.15, 0.0065, 9.80665, 287.05287


def pressure_altitude_m(p_pa: float) -> float:
    """Altitude of the ICAO standard atmosphere (troposphere) for a static pressure, m."""
    return T0_K / LAPSE_KPM * (1.0 - (p_pa / P0_PA) ** (R_AIR * LAPSE_KPM / G0))


def from_fluid_pressure(msg, t: float, sensor_id: str) -> BaroAltitude | None:
    """``sensor_msgs/msg/FluidPressure`` (Pa; variance in Pa^2, 0 = unknown) -> a reading."""
    p = float(msg.fluid_pressure)
    if not (1.0 < p < 2.0e5):
        raise ValueError(f"fluid_pressure {p} Pa is not an atmospheric pressure")
    alt = pressure_altitude_m(p)
    # dh/dp of the standard atmosphere near p (~0.083 m/Pa at sea level)
    dh_dp = abs(pressure_altitude_m(p + 1.0) - alt)
    var = float(msg.variance)
    fields = {"t": t, "altitude_m": alt}
    if var > 0.0:
        fields["std_m"] = math.sqrt(var) * dh_dp
    return BaroAltitude.model_validate(fields)


SENSOR = SensorKind(
    kind="baro",
    message=BaroAltitude,
    key=("baro", "{id}"),
    model=BaroModel,
    options=BaroOptions,
    ros2={"sensor_msgs/msg/FluidPressure": from_fluid_pressure},
    simulate=simulate,
    simulate_spec=BaroSim,
    csv_columns=("t", "altitude_m", "std_m"),
    csv_optional=("std_m",),
    from_csv=from_csv,
    doc="barometric altitude with an estimated offset",
)
