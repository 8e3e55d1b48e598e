"""Rerun dashboards of fednav: blueprints (viewer layouts), ``fednav-view`` and ``fednav-inspect``.

Depends on ``service`` for the recording layout (``service.transport.rerun_paths``); the service
never imports this package (it receives a blueprint factory from its caller).
"""
