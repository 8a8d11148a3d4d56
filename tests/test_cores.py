"""A job's workers: the threads Snakemake gave it, or the cores idle when it starts, within its affinity."""

from __future__ import annotations

import multiprocessing
import os
import time

import numpy as np
import pytest

from pipeline25d.core import cores
from pipeline25d.core.cores import idle_cores, job_workers


def _spin(stop) -> None:
    while not stop.is_set():
        pass


def test_a_busy_process_takes_about_one_core_off_the_idle_ones():
    n = os.cpu_count() or 1
    calm = idle_cores(0.3)
    assert calm is not None and -0.05 <= calm <= n + 0.05          # this process sleeps: its core is idle
    stop = multiprocessing.Event()
    spinner = multiprocessing.Process(target=_spin, args=(stop,))
    spinner.start()
    try:
        busy = idle_cores(0.3)
    finally:
        stop.set()
        spinner.join()
    assert busy is not None and busy <= n - 0.6                    # the spinner held one core


def test_a_marked_job_counts_its_own_work_since_the_mark_as_idle_and_does_not_wait(monkeypatch):
    """cores.mark() at a job's start: the first count covers the job's start-up, its own busy core
    included as idle (it is the job asking), without sleeping; a busy child is not the job's own.
    Counted on /proc/stat readings given here (2 CPUs, 100 jiffies a second each), so that other
    work on a shared machine cannot move the figures: 0.3 s with one CPU busy, first by this
    process, then by a child."""
    readings = iter([(0.0, 0.0), (30.0, 60.0), (60.0, 120.0)])       # (idle, total) jiffies of all CPUs
    own = iter([0.0, 0.3, 0.3])                                       # this process's CPU seconds
    slept: list[float] = []
    monkeypatch.setattr(cores, "_cpu_times", lambda: next(readings))
    monkeypatch.setattr(cores, "_own_cpu_s", lambda: next(own))
    monkeypatch.setattr(cores, "_ticks", lambda: 100)
    monkeypatch.setattr(cores.os, "cpu_count", lambda: 2)
    monkeypatch.setattr(cores.time, "sleep", slept.append)
    cores.mark()
    own_busy = idle_cores(0.1)                     # 0.3 s covered: one CPU idle, the other this process's
    child_busy = idle_cores(0.1)                   # the next 0.3 s: one CPU idle, the other a child's
    assert (own_busy, child_busy, slept) == (pytest.approx(2.0), pytest.approx(1.0), [])


def test_a_job_marked_from_another_process_reading_counts_since_it_without_waiting(monkeypatch):
    """A job forked by the job host: marked with the host's earlier reading, its first count covers
    the time since then at once; its own CPU (from its fork) and that of the process that handed it
    over count as its own, the host's own CPU not. 0.3 s on 2 CPUs, one of them busy: 0.05 CPU-s
    this process's, 0.1 the handing process's."""
    readings = iter([(30.0, 60.0)])
    monkeypatch.setattr(cores, "_cpu_times", lambda: next(readings))
    monkeypatch.setattr(cores, "_own_cpu_s", lambda: 0.05)
    monkeypatch.setattr(cores, "_ticks", lambda: 100)
    monkeypatch.setattr(cores.os, "cpu_count", lambda: 2)
    monkeypatch.setattr(cores.time, "monotonic", lambda: 100.3)
    slept: list[float] = []
    monkeypatch.setattr(cores.time, "sleep", slept.append)
    cores.mark(since=((0.0, 0.0), 7.0, 100.0), cpu_elsewhere_s=0.1)
    assert (idle_cores(0.1), slept) == (pytest.approx(1.0 + 0.15 / 0.3), [])


def test_a_marked_job_counts_its_own_busy_core_on_this_machine(monkeypatch):
    """The same on this machine's own /proc/stat: a job busy since its mark finds at least the share
    of a core it used itself idle (other work on the machine only takes the other cores away), and
    asks without sleeping."""
    slept: list[float] = []
    monkeypatch.setattr(cores.time, "sleep", slept.append)
    c0, t0 = time.process_time(), time.monotonic()
    cores.mark()
    while time.monotonic() < t0 + 0.3:                             # this process busy: its start-up
        pass
    own_share = (time.process_time() - c0) / (time.monotonic() - t0)
    own_busy = idle_cores(0.1)
    assert own_busy is not None and own_busy >= own_share - 0.15 and not slept


@pytest.mark.parametrize(("threads", "allowed", "idle", "expected"), [
    (1, 2, 1.9, 2),      # alone on a 2-core machine: both cores
    (1, 2, 1.4, 1),      # the other core mostly busy: its own
    (1, 2, 0.2, 1),      # even when its own core looks busy, never fewer than given
    (1, 16, 6.6, 7),     # the idle cores of a larger machine
    (1, 4, 9.0, 4),      # never beyond its affinity
    (2, 2, 0.0, 2),      # given all it may use: no sampling, those
    (3, 2, 2.0, 2),      # given more than it may use: its affinity
])
def test_workers_are_the_idle_cores_within_the_threads_given_and_the_affinity(monkeypatch, threads, allowed, idle,
                                                                                 expected):
    monkeypatch.setattr(cores, "allowed_cores", lambda: allowed)
    assert job_workers(threads, idle=idle) == expected


def test_without_proc_stat_a_job_keeps_its_threads(monkeypatch):
    monkeypatch.setattr(cores, "allowed_cores", lambda: 8)
    monkeypatch.setattr(cores, "_cpu_times", lambda: None)
    assert idle_cores(0.01) is None
    assert job_workers(1) == 1 and job_workers(3) == 3


def test_the_idle_meter_reads_the_time_since_its_last_figure_and_sees_a_busy_process():
    n = os.cpu_count() or 1
    meter = cores.IdleMeter()
    assert meter() is None                                         # no time has passed: too few ticks to tell
    time.sleep(cores.METER_MIN_S + 0.1)
    calm = meter()
    assert calm is not None and -0.05 <= calm <= n + 0.05
    stop = multiprocessing.Event()
    spinner = multiprocessing.Process(target=_spin, args=(stop,))
    spinner.start()
    try:
        time.sleep(cores.METER_MIN_S + 0.2)
        busy = meter()
    finally:
        stop.set()
        spinner.join()
    assert busy is not None and busy <= n - 0.6


def _note_times(folder: str, item: int) -> None:
    start = time.monotonic()
    time.sleep(0.05)
    with open(os.path.join(folder, str(item)), "w") as fh:
        fh.write(f"{start} {time.monotonic()} {os.getpid()}")


@pytest.mark.parametrize(("idle", "at_once"), [(2.0, 2), (0.0, 1), (None, 1)])
def test_a_cut_takes_a_worker_more_only_while_a_core_is_idle(tmp_path, idle, at_once):
    """Workers(1, most=2) runs a stage one piece at a time and two at a time once the meter
    says a core was idle (None: the meter cannot tell); every item runs once, in a worker."""
    from functools import partial

    from pipeline25d.stages.tiles.workers import Workers

    with Workers(1, most=2, idle=lambda: idle) as workers:
        workers.map(partial(_note_times, str(tmp_path)), list(range(32)))
    assert sorted(int(p.name) for p in tmp_path.iterdir()) == list(range(32))
    runs = [[float(v) for v in p.read_text().split()] for p in tmp_path.iterdir()]
    assert os.getpid() not in {int(pid) for *_, pid in runs}
    edges = sorted([(start, 1) for start, _, _ in runs] + [(end, -1) for _, end, _ in runs])
    running = np.cumsum([step for _, step in edges])
    assert running.max() == at_once
    assert workers.grown == (1 if idle else 0)


def test_map_ahead_keeps_order_and_reads_no_further_than_ahead():
    """Results in the order of the arguments, on forked workers or here; the argument generator (a
    job's data reads) is drawn at most ``ahead`` calls before the results taken."""
    from pipeline25d.core.cores import fork_pool, map_ahead

    drawn = []

    def args():
        for i in range(12):
            drawn.append(i)
            yield i, 3

    here = list(map_ahead(None, pow, args(), 4))
    drawn.clear()
    with fork_pool(2) as pool:
        out = []
        for value in map_ahead(pool, pow, args(), 3):
            assert len(drawn) <= len(out) + 3
            out.append(value)
    assert out == here == [i ** 3 for i in range(12)]
