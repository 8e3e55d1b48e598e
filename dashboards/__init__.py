"""Rerun dashboards of fednav: blueprints (viewer layouts), ``fednav-view`` and ``fednav-inspect``.

Depends on ``service`` for the recording layout (``service.transport.rerun_paths``); the service
never imports this package (it receives a blueprint factory from its caller).
"""

import functools
import os
import sys


def quiet_closed_stdout(main):
    """A report command's ``main`` whose reader may stop reading (``fednav-inspect FILE | head``):
    the closed pipe ends the command quietly with 141 (128 + SIGPIPE, as a shell tool's) instead
    of a BrokenPipeError traceback; stdout then points at /dev/null so that Python's final flush
    does not raise again."""

    @functools.wraps(main)
    def run(argv: list[str] | None = None) -> int:
        try:
            rc = main(argv)
            sys.stdout.flush()
            return rc
        except BrokenPipeError:
            devnull = os.open(os.devnull, os.O_WRONLY)
            os.dup2(devnull, sys.stdout.fileno())
            os.close(devnull)
            return 141

    return run
