"""GNSS simulation: orbits (nominal BDS-3/GPS, SP3, broadcast), visibility/DOP/selection, raw sensor.

Modules
-------
orbits         time helpers, nominal constellations, the ``OrbitSource`` protocol and the shared
               ranging model (``range_geometry``, ``predicted_range``, ``predicted_range_rate``).
sp3            SP3-c/d reader and Lagrange interpolation (``Sp3Orbits``).
rinex          RINEX 2 GPS navigation reader + IS-GPS-200 ephemeris (``BroadcastEphemeris``) and
               RINEX 2 observation reader (``read_rinex2_obs``).
rinex_raw      RINEX 2/3 observation + GPS/Galileo/BeiDou navigation -> GnssRaw (``iter_gnss_raw``).
constellation  azimuth/elevation, DOPs, satellite selection rules (``select_satellites``).
raw_sensor     ``GnssRawSpec`` / ``GnssRawSensor`` producing ``service.messages.GnssRaw``, receiver
               clock model, atmosphere models (the single-point solvers are service.estimation.snapshot).
"""

from fednav.simulators.gnss.constellation import (
    SELECTION_RULES,
    Dop,
    az_el,
    dop,
    dop_batch,
    select_satellites,
    visible,
)
from fednav.simulators.gnss.orbits import (
    NOMINAL_ALIASES,
    NominalConstellation,
    OrbitSource,
    RangeGeometry,
    SatStates,
    gps_seconds,
    light_time_states,
    predicted_range,
    predicted_range_rate,
    range_geometry,
    resolve_sat_id,
)
from fednav.simulators.gnss.raw_sensor import (
    GnssRawEpoch,
    GnssRawSensor,
    GnssRawSpec,
    GnssRawTruth,
    ReceiverClockSpec,
    clock_transition,
)
from fednav.simulators.gnss.rinex import BroadcastEphemeris, read_rinex2_nav, read_rinex2_obs
from fednav.simulators.gnss.sp3 import Sp3Orbits, read_sp3

__all__ = [
    "NOMINAL_ALIASES",
    "SELECTION_RULES",
    "BroadcastEphemeris",
    "Dop",
    "GnssRawEpoch",
    "GnssRawSensor",
    "GnssRawSpec",
    "GnssRawTruth",
    "NominalConstellation",
    "OrbitSource",
    "RangeGeometry",
    "ReceiverClockSpec",
    "SatStates",
    "Sp3Orbits",
    "az_el",
    "clock_transition",
    "dop",
    "dop_batch",
    "gps_seconds",
    "light_time_states",
    "predicted_range",
    "predicted_range_rate",
    "range_geometry",
    "read_rinex2_nav",
    "read_rinex2_obs",
    "read_sp3",
    "resolve_sat_id",
    "select_satellites",
    "visible",
]
