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


def exit_handler(job: dict) -> None:
    """Register an exit handler that writes ``job["out"]``, and print a line left in the buffer."""
    import atexit

    atexit.register(Path(job["out"]).write_text, "exit handlers ran")
    sys.stdout.write("printed, not flushed")


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


def reused_pages(job: dict) -> None:
    """Fill and free a 16 MiB array ``job["times"]`` times; write the page faults that took and
    the GLIBC_TUNABLES this process was given (see pipeline25d.jobhost.MALLOC_TUNABLES)."""
    import json

    Path(job["out"]).write_text(json.dumps({"faults": page_faults_of_temporaries(job["times"]),
                                            "tunables": os.environ.get("GLIBC_TUNABLES", "")}))


def page_faults_of_temporaries(times: int) -> int:
    """Minor page faults of filling and freeing a 16 MiB NumPy array ``times`` more times, after a
    first one (whose pages are new to the process either way)."""
    import resource

    import numpy as np

    np.ones(2 << 20)                  # 16 MiB of float64, every page written, freed
    before = resource.getrusage(resource.RUSAGE_SELF).ru_minflt
    for _ in range(times):
        a = np.ones(2 << 20)
        del a
    return resource.getrusage(resource.RUSAGE_SELF).ru_minflt - before
