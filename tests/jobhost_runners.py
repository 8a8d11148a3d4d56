"""Runners for tests/test_jobhost.py: what a hosted child calls instead of pipeline25d.jobs.run."""

from __future__ import annotations

import os
import sys
import time
from pathlib import Path


def report(job: dict) -> None:
    """Write what the child sees (folder, environment, pid) and some output, then exit with the job's status."""
    Path(job["out"]).write_text(f"{os.getcwd()}\n{os.environ.get('JOBHOST_TEST_VALUE')}\n{os.getpid()}\n")
    print("to stdout from the child", flush=True)
    print("to stderr from the child", file=sys.stderr, flush=True)
    sys.exit(job["status"])


def wait(job: dict) -> None:
    """Note this process's pid, then wait (as a job does: stop signals remembered) until stopped;
    note how it ended."""
    from pipeline25d.core.stopping import remember_stop_signals

    remember_stop_signals()
    Path(job["pid"]).write_text(str(os.getpid()))
    try:
        time.sleep(60)
    finally:
        Path(job["ended"]).write_text("stopped")


def fail(job: dict) -> None:
    raise RuntimeError("a job that fails with a traceback")


def first_count(job: dict) -> None:
    """Count the idle cores as a job's first step does (its workers), noting whether it waited."""
    import json

    from pipeline25d.core import cores

    slept: list[float] = []
    cores.time.sleep = slept.append
    Path(job["out"]).write_text(json.dumps({"idle": cores.idle_cores(), "slept": slept}))
