"""The web-tile cut's worker processes: one pool for every stage of a cut, that grows while cores are idle.

A stage starts on the job's workers and takes one more, up to the cores the job may use,
whenever the machine had a core idle since the last piece of work ended
(:class:`pipeline25d.core.cores.IdleMeter`): a cut that started beside another job takes the
core that job leaves. What a cut writes does not depend on the count.
"""

from __future__ import annotations

import logging
from collections.abc import Callable

log = logging.getLogger(__name__)

IDLE_TO_GROW = 0.75    # a cut takes one more worker after a piece of work in which this many cores were idle


class Workers:
    """One pool of forked worker processes (as gdal2tiles' own) for every stage of a cut, started
    at the first stage with more than one item; a stage runs in this process where neither
    ``processes`` nor ``most`` exceeds one.
    Each stage starts on ``processes`` workers and takes one more, up to ``most``, whenever the
    machine had a core idle since the last piece of work ended (``idle``: cores idle since the
    previous call, :class:`pipeline25d.core.cores.IdleMeter`): a cut that started beside another
    job takes the core that job leaves. The tiles do not depend on the count.
    A worker dies on SIGTERM or SIGINT (it would otherwise, with the job's SystemExit handler, fail
    one tile and take the next: :func:`~pipeline25d.core.stopping.die_on_stop_signals`), and leaving
    on an exception kills the workers at once.

    concurrent.futures, not multiprocessing.Pool: the pool's exit terminates its workers,
    which can leave one waiting for a queue lock a terminated sibling held (seen: a hung job).
    """

    def __init__(self, processes: int, most: int | None = None, idle: Callable[[], float | None] | None = None):
        self.processes = max(1, processes)
        self.most = max(self.processes, most or 1)
        self.idle = idle
        self.pool = None
        self.grown = 0            # workers taken beyond ``processes``, summed over the stages

    def __enter__(self) -> "Workers":
        return self

    def __exit__(self, exc_type, *exc) -> None:
        if self.pool is None:
            return
        if exc_type is None:
            self.pool.shutdown()
            return
        # stopping (an error, or SIGTERM's SystemExit): the tiles in flight are not waited for;
        # the state's journal has them cut again by the next run
        for proc in list(self.pool._processes.values()):        # no public way before Python 3.14
            proc.kill()
        self.pool.shutdown(wait=False, cancel_futures=True)

    def map(self, fn, items: list) -> None:
        """``fn`` over ``items``; their results are not kept."""
        if self.most <= 1 or len(items) <= 1:
            for item in items:
                fn(item)
            return
        if self.pool is None:
            import multiprocessing
            from concurrent.futures import ProcessPoolExecutor

            from pipeline25d.core.cores import IdleMeter
            from pipeline25d.core.stopping import die_on_stop_signals

            self.idle = self.idle or IdleMeter()
            self.pool = ProcessPoolExecutor(self.most, mp_context=multiprocessing.get_context("fork"),
                                            initializer=die_on_stop_signals)
        from concurrent.futures import FIRST_COMPLETED, wait

        size = max(1, min(16, len(items) // (8 * self.most)))
        pieces = iter([items[i:i + size] for i in range(0, len(items), size)])
        limit, pending = self.processes, set()
        self.idle()                     # a reading now (if 0.25 s have passed): the next covers this stage only
        while True:
            while len(pending) < limit and (piece := next(pieces, None)) is not None:
                pending.add(self.pool.submit(_each, fn, piece))
            if not pending:
                break
            done, pending = wait(pending, return_when=FIRST_COMPLETED)
            for future in done:
                future.result()
            idle = self.idle()
            if limit < self.most and idle is not None and idle >= IDLE_TO_GROW:
                limit += 1
                self.grown += 1
                log.debug("web tiles: a worker more, %d of at most %d (%.1f cores idle)", limit, self.most, idle)


def _each(fn, items: list) -> None:
    """``fn`` over one piece of a stage's items (in a worker)."""
    for item in items:
        fn(item)
