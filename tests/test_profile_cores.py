"""The workflow profile with the command lines that run it (README ``-j2``, ``pipeline25d run``'s
``--cores``): Snakemake never runs more threads at once than the cores it was given.

Snakemake 9.27, given cores by a profile and ``-j`` on the command line (or the reverse), takes
``-j`` for a count of jobs and stops counting threads: with ``cores: 2`` in profiles/default,
``-j2`` ran a 2-thread job beside a 1-thread one (3 threads on 2 cores), and the warp and web-tile
jobs (2 threads each) side by side.
"""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[1]

SNAKEFILE = """
rule all:
    input: "wide", "n1", "n2", "n3"
rule wide:
    output: "wide"
    threads: 2
    shell: "echo start 2 $(date +%s.%N) >> times; sleep 1.5; echo end 2 $(date +%s.%N) >> times; touch {output}"
rule narrow:
    output: "n{i}"
    threads: 1
    shell: "echo start 1 $(date +%s.%N) >> times; sleep 1; echo end 1 $(date +%s.%N) >> times; touch {output}"
"""


def most_threads_at_once(times: Path) -> int:
    """The largest sum of running jobs' threads, from their logged start and end times."""
    events = sorted((float(t), kind == "start", int(n)) for kind, n, t in (ln.split() for ln in times.open()))
    running = most = 0
    for _, start, n in events:            # at equal times an end sorts first
        running += n if start else -n
        most = max(most, running)
    return most


@pytest.mark.parametrize("cores", [["-j2"], ["--cores", "2"]])
def test_the_profile_keeps_threads_within_the_cores_given(tmp_path, cores):
    (tmp_path / "Snakefile").write_text(SNAKEFILE)
    subprocess.run([sys.executable, "-m", "snakemake", "--workflow-profile", str(REPO / "profiles" / "default"),
                    "--directory", str(tmp_path), "--snakefile", str(tmp_path / "Snakefile"), *cores, "--quiet"],
                   check=True, capture_output=True, timeout=120)
    assert most_threads_at_once(tmp_path / "times") == 2       # the 2-thread job alone, or two 1-thread jobs
