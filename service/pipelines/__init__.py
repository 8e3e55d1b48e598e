"""Pipeline families and their registry.

A family is one module here; each pipeline kind is a :class:`~service.pipelines.base.Pipeline`
subclass registered below under its configuration ``kind`` (the discriminator of
``service.config.PipelineConfig``). Adding a family: its config model in ``service/config.py``
(added to ``PipelineConfig``), its module here, one line in ``_KINDS``.
"""

from __future__ import annotations

import importlib

from fednav.service.pipelines.base import Pipeline

#: configuration kind -> "module:Class" (imported on first use)
_KINDS: dict[str, str] = {
    "loosely_coupled": "fednav.service.pipelines.loosely_coupled:LooselyCoupled",
    "federated": "fednav.service.pipelines.federated:Federated",
    "centralized": "fednav.service.pipelines.federated:Centralized",
    "tightly_coupled": "fednav.service.pipelines.tightly_coupled:TightlyCoupled",
    "transfer_alignment": "fednav.service.pipelines.transfer_alignment:TransferAlignment",
    "underwater": "fednav.service.pipelines.underwater:Underwater",
    "imm_tightly_coupled": "fednav.service.pipelines.imm_tightly_coupled:ImmTightlyCoupled",
}


def pipeline_class(kind: str) -> type[Pipeline]:
    try:
        target = _KINDS[kind]
    except KeyError:
        raise ValueError(f"unknown pipeline kind {kind!r}; known: {sorted(_KINDS)}") from None
    module, cls = target.split(":")
    return getattr(importlib.import_module(module), cls)


def build_pipeline(cfg, config) -> Pipeline:
    """Instantiate a pipeline from its configuration (``cfg.kind``) within the service config."""
    return pipeline_class(cfg.kind)(cfg, config.imu, config.major_interval_s)


def config_errors(config) -> list[tuple[str, str]]:
    """What a validated ``ServiceConfig`` asks for that is not implemented: (field, message) pairs,
    from each pipeline class's :meth:`~service.pipelines.base.Pipeline.config_errors` and from
    building each pipeline (constructors refuse what they cannot run)."""
    errors: list[tuple[str, str]] = []
    for i, cfg in enumerate(config.pipelines):
        cls = pipeline_class(cfg.kind)
        found = [
            (f"pipelines.{i}.{loc}" if loc else f"pipelines.{i}", msg) for loc, msg in cls.config_errors(cfg)
        ]
        if not found:
            try:
                build_pipeline(cfg, config)
            except ValueError as exc:
                found = [(f"pipelines.{i}", str(exc))]
        errors += found
    return errors


__all__ = ["Pipeline", "build_pipeline", "config_errors", "pipeline_class"]
