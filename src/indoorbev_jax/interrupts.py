"""Ctrl-C for the commands: one line and status 130 instead of a traceback, even when
Python drops the KeyboardInterrupt.

Python prints and drops a KeyboardInterrupt raised inside a garbage-collector callback (JAX
has one), so a Ctrl-C during a start-up could be lost and a long job run on.
``catch_interrupts`` (called by ``cli.exit_with``) remembers every Ctrl-C, and long loops
call ``check_interrupted`` between units of work.
"""

from __future__ import annotations

import _thread
import signal
import sys
import threading

INTERRUPTED = 130  # the shell's status for a command stopped by Ctrl-C
# Set by exit_with's SIGINT handler: Python prints and drops a KeyboardInterrupt raised
# inside a garbage-collector callback (JAX has one), so a Ctrl-C during a start-up could be
# lost and a node run on until the next one; ros2.runtime.start_node checks it.
SIGINT_SEEN = threading.Event()


# Set when Python dropped our KeyboardInterrupt (raised inside a garbage-collector
# callback): ``check_interrupted`` acts on it between units of work.
SIGINT_DROPPED = threading.Event()


def _remember_sigint(signum, frame):
    SIGINT_SEEN.set()
    SIGINT_DROPPED.clear()  # this one is raised
    raise KeyboardInterrupt


def _redeliver_soon() -> None:
    """SIGINT to the main thread again in 50 ms, from another thread: delivered at once it
    is handled inside the unraisable hook itself, and dropped there for good."""
    timer = threading.Timer(0.05, _thread.interrupt_main)
    timer.daemon = True
    timer.start()


def _quiet_dropped_interrupts(hook, redeliver=_redeliver_soon):
    """A ``sys.unraisablehook`` that, for a dropped KeyboardInterrupt, delivers the Ctrl-C
    again (``redeliver``: as if it came now, outside the callback) instead of printing
    "Exception ignored in: <function _xla_gc_callback> ... KeyboardInterrupt" and going on;
    ``SIGINT_DROPPED`` stays set until it is raised, for ``check_interrupted``."""

    def handle(unraisable):
        if isinstance(unraisable.exc_value, KeyboardInterrupt):
            SIGINT_DROPPED.set()
            redeliver()
            return
        hook(unraisable)

    return handle


def check_interrupted() -> None:
    """Raises the KeyboardInterrupt of a Ctrl-C that Python dropped (see
    ``SIGINT_DROPPED``); long loops call it between frames, so such a Ctrl-C still stops
    them (``indoorbev-sim show`` wrote all its pictures and exited 0)."""
    if SIGINT_DROPPED.is_set():
        SIGINT_DROPPED.clear()
        raise KeyboardInterrupt


def catch_interrupts() -> None:
    """Installs the SIGINT handler and the unraisable hook above (not when SIGINT is
    ignored, e.g. a job started in the background by a non-interactive shell)."""
    if signal.getsignal(signal.SIGINT) is signal.default_int_handler:
        signal.signal(signal.SIGINT, _remember_sigint)
        sys.unraisablehook = _quiet_dropped_interrupts(sys.unraisablehook)
