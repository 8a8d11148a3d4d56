"""How many cores a job may use now: the cores it holds, and more where the machine has them idle.

Snakemake gives a job the threads its rule declares, and holds them until it ends. The warp and
web-tile jobs declare one: holding two, each waited until both cores were free and then used 1.1
and 1.6 of them, while render jobs waited. Alone at the end of a run (the last map, nothing else
ready) one core leaves the other idle. :func:`job_workers` lets such a job take, when it starts
(the web tiles; the LOD job of a city that is one district, alone after its ingest) or when a
step of it starts (the warp's COG encodes), the cores that are idle at that moment as well;
:class:`IdleMeter` lets a job that works in pieces take one more as a core falls idle later (the
web-tile cut: its workers grow). What a job writes does not depend on the count.
"""

from __future__ import annotations

import logging
import os
import time
from collections import deque
from collections.abc import Callable, Iterable, Iterator
from concurrent.futures import Executor
from contextlib import contextmanager

log = logging.getLogger(__name__)

#: the shortest time the machine's idle time is sampled over before a job picks its worker count
SAMPLE_S = 0.1
#: the shortest interval an :class:`IdleMeter` reading covers (/proc/stat counts in 10 ms ticks)
METER_MIN_S = 0.25
#: the longest past an :func:`idle_cores` reading covers (an older mark is the machine of another moment)
RECENT_S = 2.0
#: the reading :func:`idle_cores` covers the time since: (/proc/stat's, this process's CPU seconds, when)
_last: tuple[tuple[float, float] | None, float, float] | None = None


def allowed_cores() -> int:
    """The cores this process may run on (its CPU affinity: a SLURM job's own CPUs, a container's)."""
    try:
        return len(os.sched_getaffinity(0))
    except (AttributeError, OSError):
        return os.cpu_count() or 1


def _cpu_times() -> tuple[float, float] | None:
    """(idle, total) jiffies of all CPUs from /proc/stat; None where there is none."""
    try:
        with open("/proc/stat") as fh:
            fields = [float(v) for v in fh.readline().split()[1:]]
    except (OSError, ValueError):
        return None
    if len(fields) < 5:
        return None
    return fields[3] + fields[4], sum(fields[:8])          # idle + iowait; user .. steal


def idle_cores(interval: float = SAMPLE_S) -> float | None:
    """Cores idle on the machine, this process's own counted as idle (the job asking is what would use
    them); None without /proc/stat.

    The reading covers the time since :func:`mark` or the previous call, where that is at least
    ``interval`` and at most :data:`RECENT_S` seconds: a job that marks its start pays no wait for
    its first count (its start-up is the interval). Otherwise this process sleeps until ``interval``
    is covered.
    """
    global _last
    if _last is None or _last[0] is None or time.monotonic() - _last[2] > RECENT_S:
        mark()
    first, own, _ = _last
    now = _cpu_times()
    if first is None or now is None:
        return None
    per_s = _ticks() * (os.cpu_count() or 1)                # jiffies of all CPUs in a second
    short = interval - (now[1] - first[1]) / per_s
    if short > 0:
        time.sleep(short)
        now = _cpu_times()
        if now is None:
            return None
    idle = _idle_between(first, now)
    _last = (now, _own_cpu_s(), time.monotonic())
    if idle is None:
        return None
    return idle + (_last[1] - own) / ((now[1] - first[1]) / per_s)


def mark(since: tuple | None = None, cpu_elsewhere_s: float = 0.0) -> None:
    """Start the reading the next :func:`idle_cores` covers (a job calls this when it starts).

    ``since``: a :func:`reading` taken earlier by another process (the job host's, before it forked
    this job: :mod:`pipeline25d.jobhost`), so that the job's first count covers the time since then
    without a wait; this process's CPU is counted from its fork, and ``cpu_elsewhere_s`` (the CPU of
    the job's own process, which handed the job over) as its own too."""
    global _last
    _last = reading() if since is None else (since[0], -cpu_elsewhere_s, since[2])


def reading() -> tuple[tuple[float, float] | None, float, float]:
    """(/proc/stat's idle and total jiffies, this process's CPU seconds, when): what :func:`mark`
    takes, for another process's ``mark(since=...)``."""
    return _cpu_times(), _own_cpu_s(), time.monotonic()


def _own_cpu_s() -> float:
    """CPU seconds of this process and of the children it has waited for."""
    t = os.times()
    return t.user + t.system + t.children_user + t.children_system


def _ticks() -> int:
    """/proc/stat's jiffies per second."""
    return os.sysconf("SC_CLK_TCK") if hasattr(os, "sysconf") else 100


def _idle_between(first: tuple[float, float], second: tuple[float, float]) -> float | None:
    """Cores idle between two :func:`_cpu_times` readings; None if no time passed between them."""
    if second[1] <= first[1]:
        return None
    return (os.cpu_count() or 1) * (second[0] - first[0]) / (second[1] - first[1])


def job_workers(threads: int, idle: float | None = None) -> int:
    """Workers for a job Snakemake gave ``threads``: those, or the cores idle now (``idle``, by default
    :func:`idle_cores`; this job's own included) where that is more, at most the cores it may run on."""
    allowed = allowed_cores()
    if threads >= allowed:
        workers, idle = max(1, allowed), None
    else:
        idle = idle_cores() if idle is None else idle
        workers = max(1, threads) if idle is None else max(1, threads, min(allowed, int(idle + 0.5)))
    log.info("workers: %d (%d thread(s) given, %d cores allowed, %s idle)", workers, threads, allowed,
             "not measured" if idle is None else f"{idle:.1f}")
    return workers


class IdleMeter:
    """Cores idle on the machine since the previous reading, without sleeping: each call covers
    the time since the last one that gave a figure, and gives None while that is under
    :data:`METER_MIN_S` (too few ticks to tell) or without /proc/stat."""

    def __init__(self) -> None:
        self._last = _cpu_times()

    def __call__(self) -> float | None:
        now = _cpu_times()
        if now is None or self._last is None:
            self._last = self._last or now
            return None
        if now[1] - self._last[1] < METER_MIN_S * _ticks() * (os.cpu_count() or 1):
            return None
        idle, self._last = _idle_between(self._last, now), now
        return idle


@contextmanager
def fork_pool(processes: int) -> Iterator[Executor]:
    """``processes`` worker processes, forked now, all of them: a job that makes them before it grows
    keeps their memory small, as a forked child's resident pages count again in the job's process
    tree; what they run is inherited, not imported again. A stop signal ends a worker at once
    (:func:`~pipeline25d.core.stopping.die_on_stop_signals`), and the job with it."""
    import multiprocessing
    from concurrent.futures import ProcessPoolExecutor

    from pipeline25d.core.stopping import die_on_stop_signals

    with ProcessPoolExecutor(processes, mp_context=multiprocessing.get_context("fork"),
                             initializer=die_on_stop_signals) as pool:
        list(pool.map(abs, range(processes)))          # a fork pool starts all its workers at its first task
        yield pool


def map_ahead(pool: Executor | None, func: Callable, args: Iterable[tuple], ahead: int) -> Iterator:
    """``func(*a)`` for each ``a`` of ``args``, in order: on ``pool`` with at most ``ahead`` calls in
    flight, so that ``args`` (a generator reading each call's data) is drawn no further than that
    ahead of the results; without a pool, here, one after another."""
    if pool is None:
        for a in args:
            yield func(*a)
        return
    pending: deque = deque()
    for a in args:
        pending.append(pool.submit(func, *a))
        del a
        if len(pending) >= ahead:
            yield pending.popleft().result()
    while pending:
        yield pending.popleft().result()
