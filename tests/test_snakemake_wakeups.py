"""Snakemake's scheduler with one pending wake-up timer (pipeline25d.core.snakemake_wakeups)."""

from __future__ import annotations

import json
import subprocess
import sys
import threading
from pathlib import Path

import pytest

from pipeline25d.core.snakemake_wakeups import PENDING, _schedule_one, one_pending_wakeup

REPO = Path(__file__).resolve().parents[1]

# A workflow of short jobs whose Snakefile samples, in the scheduler's own process, how many
# wake-up timers are alive (every 20 ms), and writes the most it saw when the run ends.
SNAKEFILE = """
import json, threading, time
from pathlib import Path
from pipeline25d.core.snakemake_wakeups import one_pending_wakeup

if config["one_pending"]:
    one_pending_wakeup()

most = [0]

def sample():
    while True:
        most[0] = max(most[0], sum(isinstance(t, threading.Timer) for t in threading.enumerate()))
        time.sleep(0.02)

threading.Thread(target=sample, daemon=True).start()

rule all:
    input: expand("out/{i}.txt", i=range(30))

rule one:
    output: "out/{i}.txt"
    shell: "sleep 0.1; echo {wildcards.i} > {output}"

onsuccess:
    Path("timers.json").write_text(json.dumps({"most": most[0]}))
"""


def _run(tmp_path: Path, one_pending: bool) -> int:
    work = tmp_path / ("one" if one_pending else "chained")
    work.mkdir()
    (work / "Snakefile").write_text(SNAKEFILE)
    proc = subprocess.run([sys.executable, "-m", "snakemake", "-j2", "--quiet", "all",
                           "--config", f"one_pending={one_pending}"],
                          cwd=work, capture_output=True, text=True, timeout=300)
    assert proc.returncode == 0, proc.stderr[-2000:]
    assert sorted(int(p.read_text()) for p in (work / "out").glob("*.txt")) == list(range(30))
    return json.loads((work / "timers.json").read_text())["most"]


def test_a_workflow_holds_one_wakeup_timer_at_most(tmp_path):
    assert _run(tmp_path, one_pending=True) <= 1
    chained = _run(tmp_path, one_pending=False)
    if chained <= 1:
        pytest.skip("this Snakemake no longer keeps a timer chain per job event")
    assert chained >= 4, chained     # Snakemake's own: one chain per job event, 60 events here


class _Scheduler:
    def __init__(self):
        self._open_jobs = threading.Semaphore(0)


def test_one_timer_pending_then_the_next_after_it_wakes():
    s = _Scheduler()
    for _ in range(5):
        _schedule_one(s, 0.05)
    timer = getattr(s, PENDING)
    assert isinstance(timer, threading.Timer) and timer.daemon
    assert s._open_jobs.acquire(timeout=5)            # woken once ...
    timer.join(5)
    assert getattr(s, PENDING) is None
    assert not s._open_jobs.acquire(timeout=0.2)      # ... and only once
    _schedule_one(s, 0.01)                            # the pass it woke may start the next
    assert s._open_jobs.acquire(timeout=5)


def test_installed_in_place_of_snakemakes_method():
    from snakemake.scheduling.job_scheduler import JobScheduler

    before = JobScheduler._schedule_reevalutation
    try:
        assert one_pending_wakeup() and one_pending_wakeup()
        assert JobScheduler._schedule_reevalutation is _schedule_one
    finally:
        JobScheduler._schedule_reevalutation = before


def test_the_workflow_installs_it():
    common = (REPO / "workflow" / "rules" / "common.smk").read_text()
    assert "\none_pending_wakeup()\n" in common
