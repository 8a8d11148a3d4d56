"""A job's stop signals, remembered, so that a stopped job never ends as if it had finished.

SIGTERM (a scheduler's cancel, Snakemake stopping its jobs) and SIGINT (Ctrl-C) raise an
exception in whatever code runs when they arrive. A library that catches ``BaseException`` there
swallows it: trimesh's OBJ reader does around material and texture loading, and then returns the
mesh untextured. The job went on and wrote that mesh as a finished chunk, which a resumed run kept
(a killtest trial found it). So the signal is also recorded here: :func:`end_if_stopped` ends the
job before any output is put in place (:func:`pipeline25d.core.atomic.atomic_path`) and after the
job's function returns.
"""

from __future__ import annotations

import signal
import sys

_received: list[int] = []


def _on_term(signum: int, frame) -> None:
    _received.append(signum)
    sys.exit(128 + signum)


def _on_int(signum: int, frame) -> None:
    _received.append(signum)
    signal.default_int_handler(signum, frame)


def exit_on_sigterm() -> None:
    """SIGTERM raises SystemExit like Ctrl-C raises KeyboardInterrupt, so a job's ``finally`` and
    ``except BaseException`` blocks remove its temporary files (by default SIGTERM ends Python at
    once, leaving them behind). The signal is remembered (:func:`stop_signal`)."""
    signal.signal(signal.SIGTERM, _on_term)


def remember_stop_signals() -> None:
    """:func:`exit_on_sigterm`, and SIGINT raises KeyboardInterrupt as before, remembered too.
    A SIGINT that the process ignores (a background job of a shell) stays ignored."""
    exit_on_sigterm()
    if signal.getsignal(signal.SIGINT) is signal.default_int_handler:
        signal.signal(signal.SIGINT, _on_int)


def die_on_stop_signals() -> None:
    """For a forked worker (a pool's ``initializer``): SIGTERM and SIGINT end it at once. It holds
    no output of its own, and a signal it took as an exception could be dropped in a library and
    its result handed back as complete; dead, its pool fails the job instead."""
    signal.signal(signal.SIGTERM, signal.SIG_DFL)
    signal.signal(signal.SIGINT, signal.SIG_DFL)


def stop_signal() -> int | None:
    """The first stop signal this process received, or None."""
    return _received[0] if _received else None


def end_if_stopped() -> None:
    """End the process (SystemExit, status 128 + signal) if it received a stop signal, even one
    whose exception some code caught and dropped."""
    signum = stop_signal()
    if signum is not None:
        raise SystemExit(128 + signum)
