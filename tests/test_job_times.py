"""A job's log gives its start-up, its function's time and its CPU (core.logsetup, pipeline25d.jobs.run)."""

from __future__ import annotations

import re
import subprocess
import sys

from pipeline25d.core.logsetup import JOB_TIME_LINE, job_logs, job_record, read_job_record, wall_seconds

SCRIPT = """
import time, subprocess, sys
t = time.process_time()
while time.process_time() - t < 0.4:          # start-up: 0.4 s of CPU before the job begins
    pass
from types import SimpleNamespace
from pipeline25d import jobs

def busy(job):
    t0 = time.process_time()
    while time.process_time() - t0 < 0.5:     # the rule's function: 0.5 s of CPU
        pass
    subprocess.run([sys.executable, "-c",
                    "import time\\nt = time.process_time()\\nwhile time.process_time() - t < 0.3: pass"])

jobs.RULES["busy"] = busy
jobs.run(SimpleNamespace(rule="busy", log=[sys.argv[1]]))
"""


def test_a_job_logs_its_startup_its_run_and_its_cpu(tmp_path):
    log = tmp_path / "job.log"
    subprocess.run([sys.executable, "-c", SCRIPT, str(log)], check=True, timeout=60)
    pattern = JOB_TIME_LINE.replace("%.2f", r"([\d.]+)")
    startup, run, cpu, children = map(float, re.search(pattern, log.read_text()).groups())
    assert startup >= 0.4                      # the busy start-up, and the interpreter's own before it
    assert run >= 0.5                          # wall: at least its CPU
    assert cpu >= 0.4 + 0.5 - 0.05             # the start-up's and the function's CPU (clock ticks: 10 ms)
    assert 0.3 - 0.05 <= children < 5


def test_a_job_record_is_what_the_log_says_its_last_run_took(tmp_path):
    """job_record reads the last time and resources lines of a job log (a log appended to by two
    runs gives the second), as the report's timings and the benches take them."""
    log = tmp_path / "logs" / "render" / "p" / "block_0_0_0.log"
    log.parent.mkdir(parents=True)
    for _ in range(2):
        subprocess.run([sys.executable, "-c", SCRIPT, str(log)], check=True, timeout=60)
    text = log.read_text()
    pattern = JOB_TIME_LINE.replace("%.2f", r"([\d.]+)")
    last = [float(v) for v in re.findall(pattern, text)[-1]]
    rec = job_record(text.splitlines())
    assert [rec[k] for k in ("startup_s", "run_s", "cpu_s", "children_cpu_s")] == last
    assert rec["max_rss_kb"] > 10_000 and rec["children_max_rss_kb"] > 1_000
    assert list(job_logs(tmp_path / "logs")) == [("render", log)]
    assert job_record(["nothing here"]) == {}
    assert read_job_record(log) == rec and wall_seconds(rec) == last[0] + last[1]
    assert wall_seconds(job_record(["nothing here"])) is None


def test_a_job_that_fails_on_a_bug_leaves_its_traceback_in_its_log(tmp_path):
    """Snakemake shows a failed job's log; ``pipeline25d run`` keeps only the terminal's last lines,
    so an unexpected error's traceback must be in the log (a Pipeline25dError: its message alone)."""
    script = SCRIPT.replace("def busy(job):", "def busy(job):\n    FAIL\n")
    for fail, expect in (("{}.not_there", "AttributeError: 'dict' object has no attribute 'not_there'"),
                         ("from pipeline25d.core.errors import ConfigError; raise ConfigError('no such key')",
                          "ERROR pipeline25d: no such key")):
        log = tmp_path / f"{len(expect)}.log"
        done = subprocess.run([sys.executable, "-c", script.replace("FAIL", fail), str(log)], capture_output=True,
                              text=True, timeout=60)
        text = log.read_text()
        assert done.returncode == 1 and expect in text
        assert ("Traceback (most recent call last)" in text) == ("Attribute" in expect)
        assert "job time:" not in text                # no record of a run that did not finish
