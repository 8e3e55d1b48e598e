"""How a command line that stops on Ctrl-C stays stoppable, and says where it is stuck.

``fednav-sim`` and ``fednav-replay`` stop on SIGINT through Python's ``KeyboardInterrupt`` (exit
130). Python installs that handler only when SIGINT's disposition at start is the default: a
process started in the background by a non-interactive shell (``cmd &`` in a script, a CI runner,
``(make test &)``) inherits SIGINT *ignored*, and Python leaves it ignored. The whole tree below
such a shell then ignores SIGINT: a simulator waiting for its router, sent SIGINT by a test or by
an operator's ``kill -INT``, ran on to its 60 s match timeout (seen on fresh-clone CI runs,
2026-12-01; the stacks showed it in Zenoh's connect, never interrupted). The service already
installs its own SIGINT/SIGTERM handlers whatever it inherited; the command lines here now do the
same: SIGINT raises ``KeyboardInterrupt``.

SIGUSR1 prints every thread's stack to stderr (faulthandler's C handler: it answers even while the
main thread is blocked in a call that does not return to Python) and the process goes on: how a
stuck simulator or replay is looked into.
"""

from __future__ import annotations

import signal
import threading


def stop_on_sigint() -> bool:
    """SIGINT raises ``KeyboardInterrupt`` in this process even if it was started with SIGINT
    ignored; SIGUSR1 dumps every thread's stack. Only from the main thread (in-process callers on
    another thread, e.g. a test's worker, keep theirs). Returns whether SIGINT was ignored before."""
    if threading.current_thread() is not threading.main_thread():
        return False
    was_ignored = signal.getsignal(signal.SIGINT) == signal.SIG_IGN
    signal.signal(signal.SIGINT, signal.default_int_handler)
    if hasattr(signal, "SIGUSR1"):
        import faulthandler

        try:
            faulthandler.register(signal.SIGUSR1, all_threads=True)
        except (OSError, ValueError, AttributeError, RuntimeError):  # (io.UnsupportedOperation is an
            pass  # OSError: a stderr without a file descriptor, as in-process callers may give)
    return was_ignored
