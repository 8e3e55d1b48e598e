"""Measurement models, one file each, and their registry (the measurement hook: ``base.py``).

Adding a sensor: write ``<sensor>.py`` with a class implementing
:class:`~service.estimation.measurements.base.MeasurementModel` and add one line to ``REGISTRY``.
Pipelines build models with :func:`make` and never call a sensor-specific function.
"""

from __future__ import annotations

from collections.abc import Callable

from fednav.service.estimation.measurements.base import (
    Measurement,
    MeasurementModel,
    ModelContext,
    PrivateStates,
    private_layout,
    private_transition,
)
from fednav.service.estimation.measurements.dvl import DvlModel
from fednav.service.estimation.measurements.gnss_fix import GnssFixModel
from fednav.service.estimation.measurements.gnss_raw import GnssRawModel
from fednav.service.estimation.measurements.star import StarAttitudeModel
from fednav.service.estimation.measurements.usbl import UsblModel

#: sensor kind -> model factory (keyword options from the pipeline's configuration)
REGISTRY: dict[str, Callable[..., MeasurementModel]] = {
    "gnss_fix": GnssFixModel,
    "star": StarAttitudeModel,
    "gnss_raw": GnssRawModel,
    "usbl": UsblModel,
    "dvl": DvlModel,
}


def plain_kinds() -> frozenset[str]:
    """Registered sensor kinds whose models need no options and declare no private states
    (usable by any 15-state filter, e.g. every local of a federated pipeline)."""
    return frozenset(k for k, f in REGISTRY.items() if getattr(f, "private_states", None) == ())


def make(kind: str, **options) -> MeasurementModel:
    """The measurement model of a sensor kind (``ValueError`` naming the known kinds)."""
    try:
        factory = REGISTRY[kind]
    except KeyError:
        raise ValueError(
            f"no measurement model for sensor kind {kind!r}; known: {sorted(REGISTRY)}"
        ) from None
    return factory(**options)


__all__ = [
    "REGISTRY",
    "Measurement",
    "MeasurementModel",
    "ModelContext",
    "PrivateStates",
    "make",
    "plain_kinds",
    "private_layout",
    "private_transition",
]
