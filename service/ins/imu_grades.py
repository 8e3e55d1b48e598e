"""IMU grade presets: the process-model numbers a filter should assume for a class of IMU.

``imu.grade = "consumer_mems"`` in the service configuration fills every ``[imu]`` field the file
does not set from the preset below (explicit numbers override). docs/imu_grades.md gives the
sources and the reasoning per number; in short:

* ``navigation``: ring-laser / fibre-optic navigation grade (Groves, "Principles of GNSS,
  Inertial and Multisensor Integrated Navigation Systems", 2nd ed. 2013, ch. 4 and its IMU
  grade tables): the service's historical default, unchanged.
* ``tactical``: tactical-grade IMU (FOG or high-end MEMS; Groves 2013 ch. 4, tactical class).
* ``industrial_mems``: calibrated industrial MEMS (Analog Devices ADIS16465/ADIS16490 class
  datasheets: in-run bias stability ~2 deg/h, ARW ~0.15 deg/sqrt(h)).
* ``consumer_mems``: phone / wearable MEMS (Bosch BMI160/BMI088, ST LSM6DSO class datasheets:
  gyro noise 3.8-7 mdps/sqrt(Hz), accel noise 70-180 ug/sqrt(Hz), zero-rate offsets of a
  fraction of a deg/s before calibration).

The filter models each bias as a random constant (initial sigma) plus a random walk. A bias
instability quoted as a first-order Gauss-Markov process (sigma_BI, correlation time tau) is
mapped onto the random walk of the same short-term growth: the GM driving density
sqrt(2 sigma_BI^2 / tau) (the exact GM discretisation Qd = sigma^2 (1 - e^(-2T/tau)) is
~ 2 sigma^2 T / tau for T << tau). Over tau the walk reaches sigma_BI sqrt(2): bounding, never
overconfident, for the minutes a GNSS outage lasts.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

GRADES = ("navigation", "tactical", "industrial_mems", "consumer_mems")


@dataclass(frozen=True)
class ImuGrade:
    """One grade in datasheet units (the ``[imu]`` configuration's units)."""

    gyro_bias_dph: float  # initial (turn-on) gyro bias 1-sigma, deg/h
    accel_bias_ug: float  # initial accelerometer bias 1-sigma, micro-g
    arw_dpsh: float  # angle random walk, deg/sqrt(h)
    vrw_ugpsHz: float  # velocity random walk, micro-g/sqrt(Hz)
    gyro_bias_instability_dph: float  # in-run bias instability (GM sigma), deg/h
    gyro_bias_tau_s: float  # its correlation time, s
    accel_bias_instability_ug: float  # in-run accel bias instability (GM sigma), micro-g
    accel_bias_tau_s: float  # its correlation time, s

    @property
    def gyro_bias_rw_dphpsh(self) -> float:
        """Bias random walk of the same short-term growth as the GM instability, deg/h/sqrt(h)."""
        return gm_to_random_walk(self.gyro_bias_instability_dph, self.gyro_bias_tau_s)

    @property
    def accel_bias_rw_ugpsh(self) -> float:
        """Accel bias random walk, micro-g/sqrt(h) (see ``gyro_bias_rw_dphpsh``)."""
        return gm_to_random_walk(self.accel_bias_instability_ug, self.accel_bias_tau_s)

    def config_fields(self) -> dict[str, float]:
        """The ``[imu]`` fields of the service configuration this grade sets."""
        return {
            "gyro_bias_dph": self.gyro_bias_dph,
            "accel_bias_ug": self.accel_bias_ug,
            "arw_dpsh": self.arw_dpsh,
            "vrw_ugpsHz": self.vrw_ugpsHz,
            "gyro_bias_rw_dphpsh": self.gyro_bias_rw_dphpsh,
            "accel_bias_rw_ugpsh": self.accel_bias_rw_ugpsh,
        }


def gm_to_random_walk(sigma: float, tau_s: float) -> float:
    """Random-walk density (unit per sqrt(h)) matching a GM process (sigma, tau) over T << tau:
    q = 2 sigma^2 / tau per second, i.e. sigma sqrt(2 / tau) per sqrt(s), times 60 per sqrt(h)."""
    if sigma == 0.0:
        return 0.0
    return sigma * math.sqrt(2.0 / tau_s) * 60.0


PRESETS: dict[str, ImuGrade] = {
    # The service's historical default (and seed 000's IMU): navigation grade. No bias walk.
    "navigation": ImuGrade(0.01, 50.0, 0.001, 5.0, 0.0, 3600.0, 0.0, 3600.0),
    # Tactical: 1 deg/h and 1 mg turn-on, ARW 0.1 deg/sqrt(h), VRW 50 ug/sqrt(Hz); in-run
    # 0.3 deg/h and 50 ug over 10 min.
    "tactical": ImuGrade(1.0, 1000.0, 0.1, 50.0, 0.3, 600.0, 50.0, 600.0),
    # Industrial MEMS (ADIS16465 class): 20 deg/h, 2 mg turn-on after factory calibration;
    # ARW 0.15 deg/sqrt(h); VRW 0.012 m/s/sqrt(h) = 20 ug/sqrt(Hz); in-run 2 deg/h, 10 ug
    # (datasheet 3.6 ug, raised for temperature) at ~300 s.
    "industrial_mems": ImuGrade(20.0, 2000.0, 0.15, 20.0, 2.0, 300.0, 10.0, 300.0),
    # Consumer MEMS (phone: BMI160 / LSM6DSO class): 500 deg/h (0.14 deg/s) residual gyro offset
    # after the OS's calibration, 10 mg accel offset; ARW 0.3 deg/sqrt(h) (5 mdps/sqrt(Hz));
    # VRW 150 ug/sqrt(Hz); in-run 20 deg/h and 100 ug at ~100 s.
    "consumer_mems": ImuGrade(500.0, 10000.0, 0.3, 150.0, 20.0, 100.0, 100.0, 100.0),
}

__all__ = ["GRADES", "PRESETS", "ImuGrade", "gm_to_random_walk"]
