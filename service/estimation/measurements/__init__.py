"""Measurement models, one file each, and their registry (the measurement hook: ``base.py``).

A sensor's model is declared in its entry of the sensor registry (``service.sensors``; a new
sensor is one file there plus one registry line, docs/ARCHITECTURE.md). Pipelines build models
with :func:`make` and never call a sensor-specific function.
"""

from __future__ import annotations

from collections.abc import Callable, Mapping

from fednav.service.estimation.measurements.base import (
    Measurement,
    MeasurementModel,
    ModelContext,
    PrivateStates,
    private_layout,
    private_transition,
    refused_with_source,
    rows_of,
)


class _Models(Mapping):
    """Sensor kind -> model factory: a read-only view of the sensor registry (``service.sensors``),
    the one place a kind is declared."""

    def _map(self) -> dict[str, Callable[..., MeasurementModel]]:
        from fednav.service import sensors

        return {k: s.model for k, s in sensors.registry().items() if s.model is not None}

    def __getitem__(self, kind: str):
        return self._map()[kind]

    def __iter__(self):
        return iter(self._map())

    def __len__(self) -> int:
        return len(self._map())


#: sensor kind -> model factory (keyword options from the pipeline's configuration)
REGISTRY: Mapping[str, Callable[..., MeasurementModel]] = _Models()


def plain_kinds() -> frozenset[str]:
    """Registered sensor kinds whose model classes declare no private states (usable by any
    15-state filter, e.g. every local of a federated pipeline; an instance configured with
    options may add its own blocks, which the federated core feeds back)."""
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
    "refused_with_source",
    "rows_of",
]
