"""A scenario run as a time-ordered stream of ``(key, message)`` pairs, plus its truth.

Order: ``InitialNav`` and ``Truth`` at ``t0``; then for every IMU sample ``k >= 1`` at ``t_k``:
``Truth`` (at the truth rate, listing the active faults), the aiding measurements of that instant
(``GnssFix``, ``GnssRaw``, ``StarAttitude``, ``UsblFix``, then ``DvlVelocity``, faults applied),
and last the ``ImuSample`` ending at ``t_k`` (the engine holds aiding until the INS reaches its
time, so solutions at ``t_k`` are post-update).

Raw GNSS (``scenario.gnss_raw``): a :class:`~simulators.gnss.raw_sensor.GnssRawSensor` measured at
every ``imu_rate / gnss_raw.rate_hz``-th IMU sample (from one period after the start) with the
receiver at the trajectory's true position and velocity of that instant; faults of sensor
``"gnss_raw"`` act on ``"<sat>.pseudorange"`` / ``"<sat>.range_rate"`` at the exact scenario time
``k / imu_rate`` (a fault on a satellite not published at an epoch has no effect there). The
per-epoch sensor truth (clock, noise, applied faults, GDOP) is kept in ``truth.gnss_raw``.

Randomness: one ``np.random.SeedSequence(seed)`` spawns independent streams for the IMU, GNSS,
star tracker, initial errors, faults and raw GNSS (in that order; the first five are the same
children as before raw GNSS existed), so enabling one sensor never changes the noise of another.
Every draw happens when the :class:`Simulation` is created; iteration only builds messages, and
``Simulation.truth`` (biases, initial errors) is available before iterating.
"""

from __future__ import annotations

import zlib
from collections.abc import Iterator
from dataclasses import dataclass, field

import numpy as np

from fednav.service import earth, keys
from fednav.service import sensors as sensor_registry
from fednav.service.messages import (
    MAX_RATE_RPS,
    MAX_SPECIFIC_FORCE_MPS2,
    ImuSample,
    InitialNav,
    Truth,
    WireModel,
)
from fednav.simulators.acoustic import draw_dvl_errors, simulate_dvl, simulate_usbl
from fednav.simulators.faults import FaultSet
from fednav.simulators.gnss.raw_sensor import GnssRawSensor, GnssRawTruth
from fednav.simulators.imu import ImuErrorTruth, apply_imu_errors
from fednav.simulators.scenario import GNSS_RAW_SENSOR, Scenario
from fednav.simulators.sensors import epoch_step, simulate_gnss_fixes, simulate_star
from fednav.simulators.trajectory import Trajectory, radii_vec

ZERO_SIGMA_FLOOR = 1e-3  # std reported for a zero initial-error sigma, in the field's units


@dataclass
class SimulationTruth:
    """What a run really did (for evaluation; never given to filters).

    Attributes
    ----------
    seed : int
    trajectory : Trajectory
    imu_errors : ImuErrorTruth (biases, scale factors, Gauss-Markov states)
    initial_pos_error_enu_m, initial_vel_error_enu_mps : (3,)
    initial_rpy_error_rad : (3,) roll, pitch, yaw (west positive) errors added to the truth
    gnss_raw : list of GnssRawTruth, one per raw GNSS epoch (empty without raw GNSS)
    """

    seed: int
    trajectory: Trajectory
    imu_errors: ImuErrorTruth
    initial_pos_error_enu_m: np.ndarray
    initial_vel_error_enu_mps: np.ndarray
    initial_rpy_error_rad: np.ndarray
    gnss_raw: list[GnssRawTruth] = field(default_factory=list)
    dvl_offset_mps: np.ndarray | None = None  # (3,) DVL offset of the run (None without DVL)
    dvl_scale: np.ndarray | None = None  # (3,) DVL scale-factor error of the run


def _deg_msg(llh: np.ndarray, rpy: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Vectorised message forms: lat_deg, lon_deg (wrapped), rpy_deg [roll, pitch, heading]."""
    lat = np.degrees(llh[:, 0])
    lon = np.degrees(earth.wrap_pi(llh[:, 1]))
    roll = np.degrees(earth.wrap_pi(rpy[:, 0]))
    pitch = np.degrees(rpy[:, 1])
    heading = (-np.degrees(rpy[:, 2])) % 360.0
    return lat, lon, llh[:, 2], np.stack([roll, pitch, heading], axis=-1)


class Simulation(Iterator[tuple[str, WireModel]]):
    """Iterator over the messages of one run; ``truth`` holds what the run really did.

    Parameters
    ----------
    scenario : Scenario
    seed : int, optional
        Defaults to ``scenario.seed``.
    vehicle : str
        Vehicle name in the keys.
    trajectory : Trajectory, optional
        ``scenario.build_trajectory()`` built once and shared across runs (must match the scenario).
    prefix : str
        Key prefix.
    """

    def __init__(
        self,
        scenario: Scenario,
        seed: int | None = None,
        vehicle: str = "v1",
        trajectory: Trajectory | None = None,
        prefix: str = keys.DEFAULT_PREFIX,
    ):
        sc = scenario
        seed = sc.seed if seed is None else int(seed)
        traj = sc.build_trajectory() if trajectory is None else trajectory
        n_expected = int(round(sc.duration_s * sc.imu.rate_hz)) + 1
        if traj.imu_rate_hz != sc.imu.rate_hz or traj.t_s.size != n_expected or traj.t0_gps_s != sc.t0_gps_s:
            raise ValueError("trajectory does not match the scenario (rate, duration or t0 differ)")
        self.scenario = sc
        self.vehicle = vehicle
        # children 7 and 8 (USBL, DVL) leave the first six streams as they were
        rng_imu, rng_gnss, rng_star, rng_init, rng_faults, rng_raw, rng_usbl, rng_dvl = (
            np.random.default_rng(s) for s in np.random.SeedSequence(seed).spawn(8)
        )
        self._dth, self._dv, imu_truth = apply_imu_errors(sc.imu, traj.dtheta_rad, traj.dvel_mps, rng_imu)
        # ImuSample messages are built without per-message validation (see _messages): check the
        # whole arrays once against the wire limits instead
        dt_imu = 1.0 / traj.imu_rate_hz
        for name, arr, limit in (
            ("dtheta_rad", self._dth, MAX_RATE_RPS * dt_imu),
            ("dvel_mps", self._dv, MAX_SPECIFIC_FORCE_MPS2 * dt_imu),
        ):
            if not np.all(np.isfinite(arr)) or np.max(np.linalg.norm(arr, axis=1)) > limit:
                raise ValueError(f"simulated {name} is not finite or beyond the ImuSample limits")
        self.faults = FaultSet(sc.faults, rng_faults)
        self._gnss = simulate_gnss_fixes(sc.gnss, traj, rng_gnss, self.faults) if sc.gnss else []
        self._star = simulate_star(sc.star, traj, rng_star, self.faults) if sc.star else []
        self._raw, raw_truth = simulate_gnss_raw(sc, traj, rng_raw, self.faults) if sc.gnss_raw else ([], [])
        self._usbl = simulate_usbl(sc.usbl, traj, rng_usbl, self.faults) if sc.usbl else []
        dvl_offset = dvl_scale = None
        self._dvl = []
        if sc.dvl:
            dvl_offset, dvl_scale = draw_dvl_errors(sc.dvl, rng_dvl)
            self._dvl = simulate_dvl(sc.dvl, traj, rng_dvl, dvl_offset, dvl_scale, self.faults)

        ie = sc.initial_errors
        if ie.mode == "random":
            z = rng_init.standard_normal(9)
            dp = z[0:3] * np.asarray(ie.pos_enu_m)
            dv = z[3:6] * np.asarray(ie.vel_enu_mps)
            da = z[6:9] * np.asarray(ie.rpy_arcsec) * earth.ARCSEC
        else:
            dp, dv = np.asarray(ie.pos_enu_m, float), np.asarray(ie.vel_enu_mps, float)
            da = np.asarray(ie.rpy_arcsec, float) * earth.ARCSEC
        self.truth = SimulationTruth(seed, traj, imu_truth, dp, dv, da, raw_truth, dvl_offset, dvl_scale)

        def floor(v) -> tuple[float, float, float]:
            return tuple(float(abs(x)) if x != 0.0 else ZERO_SIGMA_FLOOR for x in v)

        lat, lon, h = traj.llh[0]
        r_m, r_n = radii_vec(lat)
        llh0 = np.array([[lat + dp[1] / (r_m + h), lon + dp[0] / ((r_n + h) * np.cos(lat)), h + dp[2]]])
        la, lo, hh, rpy_deg = _deg_msg(llh0, (traj.rpy_rad[0] + da)[None, :])
        self.initial_nav = InitialNav(
            t=float(traj.t_s[0]),
            lat_deg=float(la[0]),
            lon_deg=float(lo[0]),
            height_m=float(hh[0]),
            vel_enu_mps=tuple((traj.vel_enu_mps[0] + dv).tolist()),
            rpy_deg=tuple(rpy_deg[0].tolist()),
            pos_std_enu_m=floor(ie.pos_enu_m),
            vel_std_enu_mps=floor(ie.vel_enu_mps),
            rpy_std_deg=floor([a / 3600.0 for a in ie.rpy_arcsec]),
        )
        # sensors of the registry ([sensors.<kind>]): each its own generator, seeded from the run's
        # seed and its kind (the streams above keep their values whether or not these are present)
        self._extra: list[tuple[str, list]] = []
        for kind, spec in sc.registry_sensor_specs().items():
            entry = sensor_registry.get(kind)
            rng_k = np.random.default_rng([seed, zlib.crc32(kind.encode())])
            key = keys.sensor(vehicle, kind, getattr(spec, "id", kind), prefix)
            self._extra.append((key, entry.simulate(spec, traj, rng_k)))
        self._truth_step = epoch_step(sc.imu.rate_hz, sc.truth_rate_hz, "truth_rate_hz")
        self._keys = {
            "imu": keys.sensor(vehicle, "imu", sc.imu.id, prefix),
            "gnss": keys.sensor(vehicle, "gnss_fix", sc.gnss.id, prefix) if sc.gnss else "",
            "star": keys.sensor(vehicle, "star", sc.star.id, prefix) if sc.star else "",
            "gnss_raw": keys.sensor(vehicle, "gnss_raw", sc.gnss_raw.id, prefix) if sc.gnss_raw else "",
            "usbl": keys.sensor(vehicle, "usbl", sc.usbl.id, prefix) if sc.usbl else "",
            "dvl": keys.sensor(vehicle, "dvl", sc.dvl.id, prefix) if sc.dvl else "",
            "init": keys.init(vehicle, prefix),
            "truth": keys.truth(vehicle, prefix),
        }
        self._gen = self._messages()

    @property
    def trajectory(self) -> Trajectory:
        return self.truth.trajectory

    def __iter__(self) -> Simulation:
        return self

    def __next__(self) -> tuple[str, WireModel]:
        return next(self._gen)

    def _messages(self) -> Iterator[tuple[str, WireModel]]:
        traj = self.truth.trajectory
        # Truth rows in message units, converted once (row j is sample k = j * truth_step).
        kt = np.arange(0, traj.t_s.size, self._truth_step)
        lat, lon, h, rpy = (x.tolist() for x in _deg_msg(traj.llh[kt], traj.rpy_rad[kt]))
        vel = traj.vel_enu_mps[kt].tolist()
        t_list = traj.t_s.tolist()

        def truth_msg(k: int) -> Truth:
            j = k // self._truth_step
            return Truth(
                t=t_list[k],
                lat_deg=lat[j],
                lon_deg=lon[j],
                height_m=h[j],
                vel_enu_mps=tuple(vel[j]),
                rpy_deg=tuple(rpy[j]),
                faults=self.faults.active(k / traj.imu_rate_hz),
            )

        k_imu, k_init, k_truth = self._keys["imu"], self._keys["init"], self._keys["truth"]
        yield k_init, self.initial_nav
        yield k_truth, truth_msg(0)
        dt = 1.0 / traj.imu_rate_hz
        dth, dv = self._dth.tolist(), self._dv.tolist()
        gnss, star, raw, usbl, dvl = self._gnss, self._star, self._raw, self._usbl, self._dvl
        ig = istar = iraw = iusbl = idvl = 0
        extra, i_extra = self._extra, [0] * len(self._extra)
        for k in range(1, traj.t_s.size):
            # Truth and aiding of instant t_k come before the IMU sample ending at t_k: the engine
            # queues aiding until the INS reaches t_k, so the solution at t_k is post-update.
            if k % self._truth_step == 0:
                yield k_truth, truth_msg(k)
            if ig < len(gnss) and gnss[ig][0] == k:
                yield self._keys["gnss"], gnss[ig][1]
                ig += 1
            if iraw < len(raw) and raw[iraw][0] == k:
                yield self._keys["gnss_raw"], raw[iraw][1]
                iraw += 1
            if istar < len(star) and star[istar][0] == k:
                yield self._keys["star"], star[istar][1]
                istar += 1
            if iusbl < len(usbl) and usbl[iusbl][0] == k:
                yield self._keys["usbl"], usbl[iusbl][1]
                iusbl += 1
            if idvl < len(dvl) and dvl[idvl][0] == k:
                yield self._keys["dvl"], dvl[idvl][1]
                idvl += 1
            for j, (key, msgs) in enumerate(extra):
                if i_extra[j] < len(msgs) and msgs[i_extra[j]][0] == k:
                    yield key, msgs[i_extra[j]][1]
                    i_extra[j] += 1
            # constructed without re-validation: the values come from the validated scenario and
            # finite arrays (checked once in __init__); receivers validate what they get anyway
            yield (
                k_imu,
                ImuSample.model_construct(
                    t=t_list[k], dt_s=dt, dtheta_rad=tuple(dth[k]), dvel_mps=tuple(dv[k])
                ),
            )


def simulate_gnss_raw(
    scenario: Scenario, traj: Trajectory, rng: np.random.Generator, faults: FaultSet | None = None
) -> tuple[list, list[GnssRawTruth]]:
    """Raw GNSS epochs as ``(imu_sample_index, GnssRaw)`` pairs in time order, and their truths.

    Epochs at every ``epoch_step``-th IMU sample from one period after the start; the receiver
    (antenna at the IMU) at the trajectory's true position/velocity of that sample. Faults of
    sensor ``"gnss_raw"`` are applied at the exact scenario time ``k / imu_rate``; channels of
    satellites not published at an epoch are given to the fault set as zeros and dropped after, so
    a fault on an unpublished satellite has no effect (scenario validation requires faulted
    satellites to be required ones unless every visible satellite is used).
    """
    spec = scenario.gnss_raw
    step = epoch_step(traj.imu_rate_hz, spec.rate_hz, "gnss_raw.rate_hz")
    ks = np.arange(step, traj.t_s.size, step)
    raw_faults = faults.for_sensor(GNSS_RAW_SENSOR) if faults else []
    fault_channels = sorted({c for f in raw_faults if f.kind != "outliers" for c in f.channels})
    t_rel = {"now": 0.0}

    def fault_fn(_t_rel_sensor: float, values: dict[str, float]) -> dict[str, float]:
        full = {c: 0.0 for c in fault_channels}
        full.update(values)
        out = faults.apply(GNSS_RAW_SENSOR, t_rel["now"], full, published=values.keys())
        return {c: out[c] for c in values}

    sensor = GnssRawSensor(spec, rng, fault_fn=fault_fn if raw_faults else None, t0_gps_s=float(traj.t_s[0]))
    lat, lon = traj.llh[ks, 0], traj.llh[ks, 1]
    pos = earth.llh_to_ecef(traj.llh[ks])
    sl, cl, so, co = np.sin(lat), np.cos(lat), np.sin(lon), np.cos(lon)
    ve, vn, vu = traj.vel_enu_mps[ks].T
    vel = np.stack(
        [-so * ve - sl * co * vn + cl * co * vu, co * ve - sl * so * vn + cl * so * vu, cl * vn + sl * vu], -1
    )
    out, truths = [], []
    for i, k in enumerate(ks.tolist()):
        t_rel["now"] = k / traj.imu_rate_hz
        ep = sensor.measure(float(traj.t_s[k]), pos[i], vel[i])
        out.append((k, ep.message))
        truths.append(ep.truth)
    return out, truths


def simulate(
    scenario: Scenario, seed: int | None = None, vehicle: str = "v1", trajectory: Trajectory | None = None
) -> Simulation:
    """Messages of one run of ``scenario`` as an iterator of ``(key, message)``; see :class:`Simulation`.

    The returned object's ``truth`` attribute (a :class:`SimulationTruth`) holds the IMU biases and
    initial errors the run drew.
    """
    return Simulation(scenario, seed, vehicle, trajectory)
