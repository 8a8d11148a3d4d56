"""Set-up of a job's process: its log (everything to the rule's log file) and its signals."""

from __future__ import annotations

import logging
import os
import re
import resource
import sys
import warnings
from collections.abc import Iterable, Iterator
from contextlib import contextmanager
from pathlib import Path

from pipeline25d.core.errors import Pipeline25dError
from pipeline25d.core.stopping import remember_stop_signals


def log_to(path: str) -> None:
    """Log a Snakemake script job to ``path`` (its Python warnings too: :func:`warnings_to_log`),
    and make it stop cleanly on SIGTERM and SIGINT, remembering either (:mod:`pipeline25d.core.stopping`)."""
    logging.basicConfig(filename=path, level=logging.INFO, force=True,
                        format="%(asctime)s %(levelname)s %(name)s: %(message)s")
    warnings_to_log()
    remember_stop_signals()


def warnings_to_log() -> None:
    """Every warning shown from now on (a reader's recovered defect, a texture drawn without it, a
    tile drawn coarser) is a WARNING line of the job's log, logger ``pipeline25d.warnings``, and one
    line ``pipeline25d: warning: <message>`` on stderr. Without this a job's warnings reached only
    stderr: not its log, and nowhere at all under ``pipeline25d run`` (which condenses the output)."""
    def show(message, category, filename, lineno, file=None, line=None) -> None:
        logging.getLogger("pipeline25d.warnings").warning("%s: %s", category.__name__, message)
        print(f"pipeline25d: warning: {message}", file=sys.stderr if file is None else file)

    warnings.showwarning = show


@contextmanager
def stop_on_error(log: bool = True) -> Iterator[None]:
    """A Pipeline25dError ends the job with its message, in its log (``log``) and on stderr (which
    Snakemake shows on the terminal), and exit status 1, without a traceback. Any other error (a
    bug) goes on with its traceback, written to the log first: Snakemake shows a failed job's log,
    while ``pipeline25d run`` keeps only the last lines of the terminal's. The workflow's
    parse-time checks use it with ``log=False``: no job log exists yet."""
    try:
        yield
    except Pipeline25dError as exc:
        if log:
            logging.getLogger("pipeline25d").error("%s", exc)
        print(f"pipeline25d: error: {exc}", file=sys.stderr)
        sys.exit(1)
    except Exception:
        if log:
            logging.getLogger("pipeline25d").exception("the job stopped on an unexpected error (a bug in "
                                                       "pipeline25d; please report it with this log)")
        raise


#: the line :func:`log_job_resources` writes (the benches parse it from job logs)
RESOURCES_LINE = "job resources: rchar %d read_bytes %d wchar %d write_bytes %d max_rss_kb %d children_max_rss_kb %d"


#: the line :func:`log_job_resources` adds when told the job's times: the process's start-up (interpreter,
#: the job's description, imports) before the rule's function, the function itself, and CPU seconds
JOB_TIME_LINE = "job time: startup_s %.2f run_s %.2f cpu_s %.2f children_cpu_s %.2f"


#: the fields of :data:`RESOURCES_LINE` and :data:`JOB_TIME_LINE`, as :func:`job_record` names them
RESOURCE_KEYS = ("rchar", "read_bytes", "wchar", "write_bytes", "max_rss_kb", "children_max_rss_kb")
TIME_KEYS = ("startup_s", "run_s", "cpu_s", "children_cpu_s")
_RESOURCES = re.compile(RESOURCES_LINE.replace("%d", r"(\d+)"))
_TIME = re.compile(JOB_TIME_LINE.replace("%.2f", r"([\d.]+)"))


def job_record(lines: Iterable[str]) -> dict:
    """A job log's last resources and time lines (:func:`log_job_resources`) as one dict of
    :data:`RESOURCE_KEYS` (int) and :data:`TIME_KEYS` (float); without either line, without its keys."""
    rec: dict = {}
    for line in lines:
        if m := _RESOURCES.search(line):
            rec.update(zip(RESOURCE_KEYS, (int(v) for v in m.groups())))
        elif m := _TIME.search(line):
            rec.update(zip(TIME_KEYS, (float(v) for v in m.groups())))
    return rec


def read_job_record(log: Path) -> dict:
    """:func:`job_record` of the job log at ``log``."""
    with open(log, errors="replace") as fh:
        return job_record(fh)


def wall_seconds(record: dict) -> float | None:
    """A job's wall seconds from its :func:`job_record`: start-up and the rule's function; None
    without a time line (a job still running, or killed)."""
    return record["startup_s"] + record["run_s"] if "run_s" in record else None


def job_logs(logs: Path) -> Iterator[tuple[str, Path]]:
    """(stage, job log) of every job log under a run's ``logs`` folder; the stage is the log's first
    part there (``render/<pid>/block_*.log`` -> render, ``terrain.log`` -> terrain)."""
    for log in sorted(Path(logs).rglob("*.log")):
        yield log.relative_to(logs).parts[0].removesuffix(".log"), log


def process_age() -> float | None:
    """Seconds since this process started (``/proc/self/stat``, clock-tick resolution); None without /proc."""
    try:
        with open("/proc/self/stat") as fh:
            started = int(fh.read().rsplit(")", 1)[1].split()[19]) / os.sysconf("SC_CLK_TCK")
        with open("/proc/uptime") as fh:
            return float(fh.read().split()[0]) - started
    except (OSError, ValueError, IndexError):
        return None


def log_job_resources(startup_s: float | None = None, run_s: float | None = None) -> None:
    """One INFO line with this process's I/O counters (``/proc/self/io``; they include the children
    it has waited for, e.g. the converters it ran) and peak RSS of itself and of its largest child.
    ``rchar`` counts every byte read() returned (the job's own temporary files and imports too),
    ``read_bytes`` only what had to come from storage (not the page cache). A child's peak RSS
    includes the parent's pages it shared from fork until exec (Linux keeps that high-water
    mark), so it bounds the child from above. Given the job's ``startup_s`` (:func:`process_age` when
    the rule's function began) and ``run_s`` (its seconds), a second line (:data:`JOB_TIME_LINE`) adds
    them and the CPU seconds of the process and of its waited-for children. Nothing where the
    system has no ``/proc/self/io``."""
    try:
        with open("/proc/self/io") as fh:
            io = {k: int(v) for k, v in (line.split(": ") for line in fh.read().splitlines() if ": " in line)}
    except (OSError, ValueError):
        return
    own, kids = resource.getrusage(resource.RUSAGE_SELF), resource.getrusage(resource.RUSAGE_CHILDREN)
    logger = logging.getLogger("pipeline25d.jobs")
    logger.info(RESOURCES_LINE, io.get("rchar", 0), io.get("read_bytes", 0), io.get("wchar", 0),
                io.get("write_bytes", 0), own.ru_maxrss, kids.ru_maxrss)
    if startup_s is not None and run_s is not None:
        logger.info(JOB_TIME_LINE, startup_s, run_s, own.ru_utime + own.ru_stime, kids.ru_utime + kids.ru_stime)
