"""Raw GNSS sensor: per-satellite pseudoranges and pseudorange rates as ``service.messages.GnssRaw``.

Measurement model (what the simulator produces, per selected satellite i at receive time t_r)
---------------------------------------------------------------------------------------------
    pseudorange_i = rho_i + b - c dt_i + A_i + n_i,          n_i ~ N(0, pseudorange_sigma_m^2)
    range_rate_i  = rho_dot_i + d - c ddt_i + m_i,           m_i ~ N(0, range_rate_sigma_mps^2)

- ``rho_i``, ``rho_dot_i``: geometric range and its exact receive-time derivative under the shared
  ranging model (``orbits.range_geometry``: satellite at its transmit time, exact earth rotation
  during the light time, light-time iteration). The filter inverts it with the same functions.
- ``b``, ``d``: receiver clock bias (m) and drift (m/s), seed 001's model
  ``db/dt = d + w_b``, ``dd/dt = -d / T_c + w_d`` (first-order Markov drift, beta = 1/T_c), simulated
  with the exact discrete transition of :func:`clock_transition`. One receiver clock serves every
  constellation (no inter-system bias).
- ``dt_i``, ``ddt_i``: satellite clock and drift from the orbit source (zero for nominal orbits;
  SP3 and broadcast clocks include the relativistic term), published as ``sat_clock_m`` and
  ``sat_clock_drift_mps`` so that a receiver predicts ``rho + b - sat_clock_m``.
- ``A_i``: optional residual atmosphere (``atmosphere=True``): zenith residuals times elevation
  mapping functions, a slowly varying bias the filter does not model (off by default). Its effect
  on the range rate (millimetres per second) is not modelled.
- Faults: after noise, ``fault_fn(t_rel_s, values)`` may change any channel
  (``"C03.pseudorange"``, ``"C03.range_rate"``); what it changed is recorded in the truth.

Published satellite state: ``sat_pos_ecef_m`` / ``sat_vel_ecef_mps`` are the state at the true
transmit time, in the ECEF frame *of the transmit time* (as an ephemeris gives it); the receiver
applies the earth rotation itself via ``orbits.range_geometry``. The message time ``t`` is the true
GPS time of reception (the receiver clock offset appears only in the ranges, as with steered time
tags). ``elevation_deg`` is seen from the true receiver position.

Satellite selection: candidates are the satellites of the configured constellations above the
elevation mask; the rule (``constellation.SELECTION_RULES``) picks ``selection_count`` of them.
With ``reselect="on_loss"`` (default) the set is kept until one of its satellites sets or becomes
invalid, then chosen again; ``"every_epoch"`` re-chooses each epoch; ``"never"`` keeps the first
set, dropping satellites as they set.

Also here: atmosphere models (:func:`tropo_delay_m`, Saastamoinen with a standard atmosphere). The
single-epoch least-squares solvers are the service's (:mod:`service.estimation.snapshot`).

References: Groves 2nd ed. ch. 9 (pseudo-range and rate models, receiver clock), Brown & Hwang,
*Introduction to Random Signals and Applied Kalman Filtering*, 4th ed., section 9.3 (clock PSDs
from Allan-variance coefficients h0, h-2), Saastamoinen 1972, RTKLIB ``tropmodel``.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Literal

import numpy as np
import scipy.linalg
from pydantic import BaseModel, ConfigDict, Field, field_validator, model_validator

from fednav.service.earth import A_M, C_MPS
from fednav.service.messages import GnssRaw, SatObservation
from fednav.simulators.gnss.constellation import SELECTION_RULES, az_el, dop, select_satellites
from fednav.simulators.gnss.orbits import (
    NominalConstellation,
    OrbitSource,
    RangeGeometry,
    SatStates,
    constellation_of,
    light_time_states,
    resolve_sat_id,
)

FaultFn = Callable[[float, dict[str, float]], dict[str, float]]
"""``fault_fn(t_rel_s, values) -> values``; values keys are ``"<id>.pseudorange"`` (m) and
``"<id>.range_rate"`` (m/s). Plug a fault set in with
``fault_fn=lambda t_rel_s, v: fault_set.apply("gnss", t_rel_s, v)``."""

CHANNELS = ("pseudorange", "range_rate")

# Brown & Hwang table 9.2, low-grade TCXO: h0 = 2e-19, h-2 = 2e-20.
# Clock phase (bias) white-noise PSD S_b = h0/2 c^2; frequency (drift) random-walk PSD S_d = 2 pi^2 h-2 c^2.
TCXO_BIAS_PSD_M2PS = 2e-19 / 2.0 * C_MPS**2  # 8.99e-3 m^2/s
TCXO_DRIFT_PSD_M2PS3 = 2.0 * math.pi**2 * 2e-20 * C_MPS**2  # 3.55e-2 m^2/s^3


# --- configuration --------------------------------------------------------------------------------------
class _Spec(BaseModel):
    model_config = ConfigDict(extra="forbid", frozen=True)


class ReceiverClockSpec(_Spec):
    """Receiver clock: ``db/dt = d + w_b``, ``dd/dt = -d / drift_correlation_time_s + w_d``."""

    initial_bias_m: float = Field(
        0.0, ge=-1.0e6, le=1.0e6, description="Clock bias at the first epoch, m (c x s)"
    )
    initial_drift_mps: float = Field(
        0.0, ge=-1.0e3, le=1.0e3, description="Clock drift at the first epoch, m/s"
    )
    bias_psd_m2ps: float = Field(
        TCXO_BIAS_PSD_M2PS, ge=0.0, description="PSD of w_b, m^2/s (default TCXO h0 = 2e-19: h0/2 c^2)"
    )
    drift_psd_m2ps3: float = Field(
        TCXO_DRIFT_PSD_M2PS3,
        ge=0.0,
        description="PSD of w_d, m^2/s^3 (default TCXO h-2 = 2e-20: 2 pi^2 h-2 c^2)",
    )
    drift_correlation_time_s: float = Field(
        600.0, gt=0.0, le=1.0e7, description="Correlation time T_c of the Markov drift (beta = 1/T_c), s"
    )


class GnssRawSpec(_Spec):
    """Configuration of :class:`GnssRawSensor` (validated whole; errors name the field)."""

    rate_hz: float = Field(1.0, gt=0.0, le=100.0, description="Measurement rate, Hz")
    constellations: tuple[Literal["BDS", "GPS"], ...] = Field(
        ("BDS",), min_length=1, description="Systems used"
    )
    orbit_source: str = Field(
        "nominal",
        description='"nominal" (circular-orbit BDS-3 / GPS), or a path to an SP3 or RINEX 2 GPS nav file',
    )
    elevation_mask_deg: float = Field(10.0, ge=0.0, lt=90.0, description="Elevation mask, deg")
    selection: str = Field("all", description=f"Selection rule, one of {sorted(SELECTION_RULES)}")
    selection_count: int | None = Field(
        None, ge=4, le=64, description="Satellites to select (rules other than 'all')"
    )
    gdop_limit: float | None = Field(
        None,
        gt=0.0,
        description="max_gdop/min_gdop consider only subsets with GDOP <= this (None: any finite)",
    )
    required_satellites: tuple[str, ...] = Field(
        (), description="Ids or role names (e.g. GEO3) every selection must contain while visible"
    )
    excluded_satellites: tuple[str, ...] = Field((), description="Ids or role names never used")
    reselect: Literal["on_loss", "every_epoch", "never"] = Field(
        "on_loss", description="When to re-run selection"
    )
    pseudorange_sigma_m: float = Field(
        3.0, gt=0.0, le=1.0e3, description="Pseudorange white noise 1-sigma, m"
    )
    range_rate_sigma_mps: float = Field(
        0.05, gt=0.0, le=1.0e2, description="Range-rate white noise 1-sigma, m/s"
    )
    clock: ReceiverClockSpec = Field(default_factory=ReceiverClockSpec)
    atmosphere: bool = Field(False, description="Add the residual atmosphere bias")
    tropo_zenith_residual_m: float = Field(0.1, ge=0.0, le=10.0, description="Zenith troposphere residual, m")
    iono_zenith_residual_m: float = Field(
        1.0, ge=0.0, le=50.0, description="Zenith ionosphere residual (L1), m"
    )

    @field_validator("selection")
    @classmethod
    def _known_rule(cls, v: str) -> str:
        if v not in SELECTION_RULES:
            raise ValueError(f"unknown selection rule {v!r}; choose from {sorted(SELECTION_RULES)}")
        return v

    @field_validator("constellations")
    @classmethod
    def _unique(cls, v: tuple[str, ...]) -> tuple[str, ...]:
        if len(set(v)) != len(v):
            raise ValueError(f"duplicate constellation in {v}")
        return v

    @field_validator("required_satellites", "excluded_satellites")
    @classmethod
    def _ids(cls, v: tuple[str, ...]) -> tuple[str, ...]:
        out = tuple(resolve_sat_id(s) for s in v)
        bad = [s for s in out if len(s) != 3 or s[0] not in "GC" or not s[1:].isdigit()]
        if bad:
            raise ValueError(f"not satellite ids (e.g. C03, G12) or role names (e.g. GEO3): {bad}")
        return out

    @field_validator("orbit_source")
    @classmethod
    def _source(cls, v: str) -> str:
        if v != "nominal":
            orbit_file_kind(v)  # raises with a clear message
        return v

    @model_validator(mode="after")
    def _consistent(self) -> GnssRawSpec:
        if self.selection != "all" and self.selection_count is None:
            raise ValueError(f"selection_count: required by selection rule {self.selection!r}")
        if (
            self.orbit_source != "nominal"
            and orbit_file_kind(self.orbit_source) == "rinex_nav"
            and "BDS" in self.constellations
        ):
            raise ValueError("constellations: a RINEX 2 GPS navigation file has no BDS satellites")
        systems = {"G": "GPS", "C": "BDS"}
        for name in ("required_satellites", "excluded_satellites"):
            for s in getattr(self, name):
                if systems[s[0]] not in self.constellations:
                    raise ValueError(f"{name}: {s} is not in constellations {self.constellations}")
        if self.selection_count is not None and len(self.required_satellites) > self.selection_count:
            raise ValueError("required_satellites: more satellites than selection_count")
        return self


def orbit_file_kind(path: str | Path) -> Literal["sp3", "rinex_nav"]:
    """Sniff an orbit file: ``"sp3"`` or ``"rinex_nav"`` (raises ``ValueError`` otherwise)."""
    p = Path(path)
    if not p.is_file():
        raise ValueError(f"orbit file {str(p)!r} does not exist")
    with p.open(errors="replace") as f:
        first = f.readline()
    if first.startswith("#c") or first.startswith("#d"):
        return "sp3"
    if first[:9].strip().startswith("2") and first[20:21].upper() == "N":
        return "rinex_nav"
    raise ValueError(f"orbit file {str(p)!r} is neither SP3-c/d nor a RINEX 2 GPS navigation file")


def make_orbit_source(spec: GnssRawSpec) -> OrbitSource:
    """The orbit source a spec names."""
    if spec.orbit_source == "nominal":
        return NominalConstellation(spec.constellations)
    if orbit_file_kind(spec.orbit_source) == "sp3":
        from fednav.simulators.gnss.sp3 import Sp3Orbits

        return Sp3Orbits.from_file(spec.orbit_source)
    from fednav.simulators.gnss.rinex import BroadcastEphemeris

    return BroadcastEphemeris.from_file(spec.orbit_source)


# --- receiver clock ---------------------------------------------------------------------------------------
def clock_transition(
    dt_s: float, correlation_time_s: float, bias_psd_m2ps: float, drift_psd_m2ps3: float
) -> tuple[np.ndarray, np.ndarray]:
    """Exact discrete model of the clock ``x = [b, d]``: ``x_k+1 = Phi x_k + w``, ``w ~ N(0, Qd)``.

    ``F = [[0, 1], [0, -beta]]``, ``Qc = diag(S_b, S_d)``; Phi = expm(F dt) and
    ``Qd = int_0^dt Phi(s) Qc Phi(s)' ds`` by Van Loan's method.
    Returns (Phi (2, 2), Qd (2, 2)).
    """
    beta = 1.0 / correlation_time_s
    f = np.array([[0.0, 1.0], [0.0, -beta]])
    qc = np.diag([bias_psd_m2ps, drift_psd_m2ps3])
    m = np.zeros((4, 4))
    m[:2, :2] = -f
    m[:2, 2:] = qc
    m[2:, 2:] = f.T
    e = scipy.linalg.expm(m * dt_s)
    phi = e[2:, 2:].T
    qd = phi @ e[:2, 2:]
    return phi, 0.5 * (qd + qd.T)


class ReceiverClock:
    """Simulated receiver clock (bias m, drift m/s) advanced with the exact discrete model."""

    def __init__(self, spec: ReceiverClockSpec, rng: np.random.Generator):
        self.spec = spec
        self.rng = rng
        self.state = np.array([spec.initial_bias_m, spec.initial_drift_mps])
        self._cache: tuple[float, np.ndarray, np.ndarray] | None = None

    @property
    def bias_m(self) -> float:
        return float(self.state[0])

    @property
    def drift_mps(self) -> float:
        return float(self.state[1])

    def step(self, dt_s: float) -> None:
        if dt_s <= 0.0:
            raise ValueError(f"clock step must be positive, got {dt_s}")
        # dt_s of a fixed-rate sensor differs in the last bits (differences of ~1e9 s GPS
        # times, spacing ~2e-7 s): reuse the model within 1 us (an expm per epoch otherwise)
        if self._cache is None or abs(self._cache[0] - dt_s) > 1e-6:
            s = self.spec
            phi, qd = clock_transition(dt_s, s.drift_correlation_time_s, s.bias_psd_m2ps, s.drift_psd_m2ps3)
            lq = np.linalg.cholesky(qd + 1e-300 * np.eye(2)) if np.any(qd) else np.zeros((2, 2))
            self._cache = (dt_s, phi, lq)
        _, phi, lq = self._cache
        self.state = phi @ self.state + lq @ self.rng.standard_normal(2)


# --- atmosphere -----------------------------------------------------------------------------------------
def tropo_delay_m(
    el_rad: np.ndarray, lat_rad: float, height_m: float, rel_humidity: float = 0.7
) -> np.ndarray:
    """Saastamoinen zenith delays with a standard atmosphere, mapped by 1/cos(zenith) (RTKLIB
    ``tropmodel``). Metres, (N,). Zero below the horizon."""
    el = np.asarray(el_rad, dtype=float)
    h = max(height_m, 0.0)
    pres = 1013.25 * (1.0 - 2.2557e-5 * h) ** 5.2568
    temp = 15.0 - 6.5e-3 * h + 273.16
    e = 6.108 * rel_humidity * math.exp((17.15 * temp - 4684.0) / (temp - 38.45))
    cos_z = np.cos(np.pi / 2.0 - np.maximum(el, 1e-3))
    hydro = 0.0022768 * pres / (1.0 - 0.00266 * math.cos(2.0 * lat_rad) - 0.00028 * h / 1e3) / cos_z
    wet = 0.002277 * (1255.0 / temp + 0.05) * e / cos_z
    return np.where(el > 0.0, hydro + wet, 0.0)


def tropo_mapping(el_rad: np.ndarray) -> np.ndarray:
    """Simple troposphere mapping ``1.001 / sqrt(0.002001 + sin^2 el)`` (RTCA DO-229)."""
    s = np.sin(np.asarray(el_rad, dtype=float))
    return 1.001 / np.sqrt(0.002001 + s * s)


def iono_obliquity(el_rad: np.ndarray, shell_height_m: float = 350e3) -> np.ndarray:
    """Single-layer ionosphere obliquity factor ``1 / sqrt(1 - (R cos el / (R + h))^2)``."""
    x = A_M * np.cos(np.asarray(el_rad, dtype=float)) / (A_M + shell_height_m)
    return 1.0 / np.sqrt(1.0 - x * x)


# --- sensor ----------------------------------------------------------------------------------------------
@dataclass(frozen=True)
class GnssRawTruth:
    """Truth of one epoch, per published satellite (arrays (N,) in message order)."""

    t_gps_s: float
    ids: tuple[str, ...]
    range_m: np.ndarray
    range_rate_mps: np.ndarray
    sat_clock_m: np.ndarray
    sat_clock_drift_mps: np.ndarray
    rx_clock_bias_m: float
    rx_clock_drift_mps: float
    atmosphere_m: np.ndarray
    pseudorange_noise_m: np.ndarray
    range_rate_noise_mps: np.ndarray
    pseudorange_fault_m: np.ndarray
    range_rate_fault_mps: np.ndarray
    azimuth_deg: np.ndarray
    elevation_deg: np.ndarray
    gdop: float
    visible_ids: tuple[str, ...] = field(default=())


@dataclass(frozen=True)
class GnssRawEpoch:
    message: GnssRaw
    truth: GnssRawTruth
    states: SatStates
    geometry: RangeGeometry


class GnssRawSensor:
    """Raw GNSS sensor (module docstring has the model).

    Parameters
    ----------
    spec : configuration.
    seed : seed of ``np.random.default_rng`` (or a Generator).
    source : orbit source overriding ``spec.orbit_source`` (e.g. one shared by several sensors).
    fault_fn : optional fault hook (see :data:`FaultFn`).
    t0_gps_s : time origin of ``t_rel_s`` passed to the fault hook (default: the first epoch).
    """

    def __init__(
        self,
        spec: GnssRawSpec,
        seed: int | np.random.Generator = 0,
        *,
        source: OrbitSource | None = None,
        fault_fn: FaultFn | None = None,
        t0_gps_s: float | None = None,
    ):
        self.spec = spec
        self.rng = seed if isinstance(seed, np.random.Generator) else np.random.default_rng(seed)
        self.source = source if source is not None else make_orbit_source(spec)
        self.fault_fn = fault_fn
        self.t0_gps_s = t0_gps_s
        self.clock = ReceiverClock(spec.clock, self.rng)
        self.candidates = [
            s
            for s in self.source.satellite_ids()
            if s[0] in "GC"
            and constellation_of(s) in spec.constellations
            and s not in spec.excluded_satellites
        ]
        if not self.candidates:
            raise ValueError(f"constellations: orbit source has no satellites of {spec.constellations}")
        self.selected: tuple[str, ...] = ()
        self._t_last: float | None = None

    def channels(self, ids: Sequence[str] | None = None) -> list[str]:
        """Fault-hook channel names (``"C03.pseudorange"``, ...) of ``ids`` (default: all candidates)."""
        return [f"{s}.{c}" for s in (ids if ids is not None else self.candidates) for c in CHANNELS]

    def epoch_times(self, t_start_gps_s: float, t_end_gps_s: float) -> np.ndarray:
        """Measurement times at ``rate_hz`` from ``t_start`` through ``t_end`` (inclusive, rounded grid)."""
        dt = 1.0 / self.spec.rate_hz
        n = int(math.floor((t_end_gps_s - t_start_gps_s) / dt + 1e-9)) + 1
        return t_start_gps_s + dt * np.arange(n)

    def _visible(self, t: float, rx: np.ndarray) -> tuple[list[str], np.ndarray, np.ndarray]:
        st = self.source.states(self.candidates, t - 0.075)
        az, el = az_el(rx, np.where(np.isfinite(st.pos_ecef_m), st.pos_ecef_m, 0.0))
        ok = st.valid & (el >= math.radians(self.spec.elevation_mask_deg))
        idx = np.flatnonzero(ok)
        return [self.candidates[i] for i in idx], az[idx], el[idx]

    def _select(self, vis: list[str], az: np.ndarray, el: np.ndarray) -> tuple[str, ...]:
        s = self.spec
        if s.selection == "all":
            return tuple(vis)
        need_new = (
            s.reselect == "every_epoch"
            or not self.selected
            or (s.reselect == "on_loss" and any(x not in vis for x in self.selected))
        )
        if not need_new:
            return tuple(x for x in self.selected if x in vis)
        req = [vis.index(r) for r in s.required_satellites if r in vis]
        lim = s.gdop_limit if s.gdop_limit is not None else math.inf
        idx = select_satellites(az, el, s.selection, s.selection_count, req, lim)
        return tuple(vis[i] for i in idx)

    def measure(self, t_gps_s: float, rx_pos_ecef_m: np.ndarray, rx_vel_ecef_mps: np.ndarray) -> GnssRawEpoch:
        """One epoch at receive time ``t_gps_s`` for a receiver (antenna) at the given true ECEF
        position and velocity. Times must increase from call to call."""
        t = float(t_gps_s)
        rx = np.asarray(rx_pos_ecef_m, dtype=float).reshape(3)
        v_rx = np.asarray(rx_vel_ecef_mps, dtype=float).reshape(3)
        if self._t_last is not None:
            self.clock.step(t - self._t_last)  # raises unless time increases
        if self.t0_gps_s is None:
            self.t0_gps_s = t
        self._t_last = t

        vis, az_v, el_v = self._visible(t, rx)
        self.selected = self._select(vis, az_v, el_v)
        ids = list(self.selected)
        n = len(ids)
        st, geo = light_time_states(self.source, ids, t, rx, v_rx)
        az, el = az_el(rx, geo.sat_pos_rx_frame_m) if n else (np.zeros(0), np.zeros(0))
        sat_clk_m = C_MPS * st.clock_s
        sat_drift_mps = C_MPS * st.clock_drift_sps
        rate = geo.range_rate_mps if geo.range_rate_mps is not None else np.zeros(n)

        s = self.spec
        atm = np.zeros(n)
        if s.atmosphere and n:
            atm = s.tropo_zenith_residual_m * tropo_mapping(el) + s.iono_zenith_residual_m * iono_obliquity(
                el
            )
        noise_pr = s.pseudorange_sigma_m * self.rng.standard_normal(n)
        noise_rr = s.range_rate_sigma_mps * self.rng.standard_normal(n)
        pr = geo.range_m + self.clock.bias_m - sat_clk_m + atm + noise_pr
        rr = rate + self.clock.drift_mps - sat_drift_mps + noise_rr

        fault_pr, fault_rr = np.zeros(n), np.zeros(n)
        if self.fault_fn is not None and n:
            values = {}
            for i, sid in enumerate(ids):
                values[f"{sid}.pseudorange"] = float(pr[i])
                values[f"{sid}.range_rate"] = float(rr[i])
            out = self.fault_fn(t - self.t0_gps_s, dict(values))
            unknown = set(out) - set(values)
            if unknown:
                raise KeyError(f"fault_fn returned unknown channels {sorted(unknown)}")
            new_pr = np.array(
                [out.get(f"{sid}.pseudorange", pr[i]) for i, sid in enumerate(ids)], dtype=float
            )
            new_rr = np.array([out.get(f"{sid}.range_rate", rr[i]) for i, sid in enumerate(ids)], dtype=float)
            fault_pr, fault_rr = new_pr - pr, new_rr - rr
            pr, rr = new_pr, new_rr

        obs = [
            SatObservation(
                id=sid,
                constellation=constellation_of(sid),  # type: ignore[arg-type]
                pseudorange_m=float(pr[i]),
                range_rate_mps=float(rr[i]),
                pseudorange_sigma_m=float(s.pseudorange_sigma_m),
                range_rate_sigma_mps=float(s.range_rate_sigma_mps),
                sat_pos_ecef_m=(
                    float(st.pos_ecef_m[i, 0]),
                    float(st.pos_ecef_m[i, 1]),
                    float(st.pos_ecef_m[i, 2]),
                ),
                sat_vel_ecef_mps=(
                    float(st.vel_ecef_mps[i, 0]),
                    float(st.vel_ecef_mps[i, 1]),
                    float(st.vel_ecef_mps[i, 2]),
                ),
                sat_clock_m=float(sat_clk_m[i]),
                sat_clock_drift_mps=float(sat_drift_mps[i]),
                elevation_deg=float(np.degrees(el[i])),
            )
            for i, sid in enumerate(ids)
        ]
        msg = GnssRaw(t=t, sats=obs)
        truth = GnssRawTruth(
            t_gps_s=t,
            ids=tuple(ids),
            range_m=geo.range_m,
            range_rate_mps=rate,
            sat_clock_m=sat_clk_m,
            sat_clock_drift_mps=sat_drift_mps,
            rx_clock_bias_m=self.clock.bias_m,
            rx_clock_drift_mps=self.clock.drift_mps,
            atmosphere_m=atm,
            pseudorange_noise_m=noise_pr,
            range_rate_noise_mps=noise_rr,
            pseudorange_fault_m=fault_pr,
            range_rate_fault_mps=fault_rr,
            azimuth_deg=np.degrees(az),
            elevation_deg=np.degrees(el),
            gdop=float(dop(az, el).gdop),
            visible_ids=tuple(vis),
        )
        return GnssRawEpoch(msg, truth, st, geo)
