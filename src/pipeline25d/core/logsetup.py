"""Set-up of a job's process: its log (everything to the rule's log file) and its signals."""

from __future__ import annotations

import logging
import signal
import sys
from collections.abc import Iterator
from contextlib import contextmanager

from pipeline25d.core.errors import Pipeline25dError


def exit_on_sigterm() -> None:
    """SIGTERM (a scheduler's cancel, Snakemake stopping its jobs) raises SystemExit like Ctrl-C
    raises KeyboardInterrupt, so a job's ``finally`` and ``except BaseException`` blocks remove
    its temporary files (by default SIGTERM ends Python at once, leaving them behind)."""
    signal.signal(signal.SIGTERM, lambda signum, frame: sys.exit(128 + signum))


def log_to(path: str) -> None:
    """Log a Snakemake script job to ``path``, and make it stop cleanly on SIGTERM."""
    logging.basicConfig(filename=path, level=logging.INFO, force=True,
                        format="%(asctime)s %(levelname)s %(name)s: %(message)s")
    exit_on_sigterm()


@contextmanager
def stop_on_error(log: bool = True) -> Iterator[None]:
    """A Pipeline25dError ends the job with its message, in its log (``log``) and on stderr (which
    Snakemake shows on the terminal), and exit status 1, without a traceback. The workflow's
    parse-time checks use it with ``log=False``: no job log exists yet."""
    try:
        yield
    except Pipeline25dError as exc:
        if log:
            logging.getLogger("pipeline25d").error("%s", exc)
        print(f"pipeline25d: error: {exc}", file=sys.stderr)
        sys.exit(1)
