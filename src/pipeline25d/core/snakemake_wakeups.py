"""Snakemake's scheduler woken at most once a second, not once a second per job event so far.

Snakemake 9's scheduler ends every pass over the ready jobs by starting a ``threading.Timer``
that wakes it again after the job-rate limit's timespan (``--max-jobs-per-timespan``, 100/1s by
default). The pass that timer wakes starts another, so each job event (a start, an end) begins a
chain of wake-ups that never stops while jobs wait for cores, and each pass stats the inputs of
every ready job. In one ``make bench`` run (2026-11-27) the scheduler held 126 such timer threads
after 364 jobs, used 0.16 of a core while render jobs ran, and took 203 of the run's 1,904
CPU-seconds; with one timer pending, 42 of 1,858 in the run after it (a similar report upstream:
snakemake/snakemake#3955).

:func:`one_pending_wakeup` keeps Snakemake's own behaviour (the same passes, the same rate limit)
with one pending timer at most: a pass that would start a timer while one is pending leaves it,
since the pending one wakes the scheduler as soon. The timer is a daemon thread, so Snakemake
does not wait for it at exit. The Snakefile installs it at parse time, in the scheduler's process.
"""

from __future__ import annotations

import logging
import threading

log = logging.getLogger(__name__)

#: the attribute of a JobScheduler that holds its pending wake-up timer (None: none pending)
PENDING = "_pipeline25d_wakeup"


def _schedule_one(scheduler, delay: float) -> None:
    """Wake ``scheduler`` (release its ``_open_jobs``) after ``delay`` seconds, unless a wake-up is
    already pending; the timer clears itself before it wakes, so the pass it wakes may start the next."""
    if getattr(scheduler, PENDING, None) is not None:
        return

    def wake() -> None:
        setattr(scheduler, PENDING, None)
        scheduler._open_jobs.release()

    timer = threading.Timer(delay, wake)
    timer.daemon = True
    setattr(scheduler, PENDING, timer)
    timer.start()


def one_pending_wakeup() -> bool:
    """Give Snakemake's scheduler :func:`_schedule_one` in place of its ``_schedule_reevalutation``.
    Returns whether it is in place; False (and Snakemake left as it is) where this Snakemake has
    no such method."""
    try:
        from snakemake.scheduling.job_scheduler import JobScheduler
    except ImportError:
        return False
    current = getattr(JobScheduler, "_schedule_reevalutation", None)
    if current is _schedule_one:
        return True
    if current is None:
        log.debug("this Snakemake's scheduler has no _schedule_reevalutation: left as it is")
        return False
    JobScheduler._schedule_reevalutation = _schedule_one
    return True
