"""The service's shutdown watchdog (service/__main__.py ``shutdown_watchdog``): a stop that hangs
ends the process with every thread's stack on stderr, the recording's close is not counted, and a
deadlock that holds the GIL is ended by faulthandler's own timer. Each case runs in a child process
(the watchdog exits the process it runs in)."""

from __future__ import annotations

import subprocess
import sys
import textwrap
import time


def _run(body: str, timeout: float = 30.0) -> tuple[int, str, float]:
    code = textwrap.dedent(
        """
        import time, types
        from fednav.service.__main__ import shutdown_watchdog
        svc = types.SimpleNamespace(stopping=None)
        """
    ) + textwrap.dedent(body)
    t0 = time.monotonic()
    p = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=timeout)
    return p.returncode, p.stderr, time.monotonic() - t0


def test_a_stop_stuck_in_a_stage_exits_3_with_the_stacks():
    rc, err, _ = _run(
        """
        shutdown_watchdog(svc, limit_s=1.0)
        svc.stopping = "session"
        def hung_close():
            time.sleep(600)
        hung_close()
        """
    )
    assert rc == 3, err
    assert "shutdown stuck for 1 s in stage 'session'" in err, err
    assert "hung_close" in err and "Thread" in err, err  # the stuck thread's stack


def test_the_recordings_close_is_not_counted_and_a_finished_stop_exits_normally():
    rc, err, took = _run(
        """
        from fednav.service.app import RECORDING_STAGE
        shutdown_watchdog(svc, limit_s=1.0, backstop_after_s=1.0)
        svc.stopping = RECORDING_STAGE
        time.sleep(4.0)  # a long recording close: more than limit and backstop together
        svc.stopping = "done"
        print("closed")
        """
    )
    assert rc == 0, err
    assert "stuck" not in err and "Timeout" not in err, err
    assert took > 4.0


def test_a_deadlock_holding_the_gil_is_ended_by_the_backstop():
    rc, err, took = _run(
        """
        import ctypes
        shutdown_watchdog(svc, limit_s=1.0, backstop_after_s=1.0)
        svc.stopping = "session"
        ctypes.PyDLL(None).sleep(600)  # a C call that keeps the GIL: no Python thread runs
        """
    )
    assert rc == 1, err
    assert "Timeout (0:00:02)!" in err, err
    assert took < 20.0
