"""The ``pipeline25d`` command: its commands, ``run``'s progress from Snakemake's log, a dry run."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import yaml
from conftest import REPO

from pipeline25d.runner import progress_events, progress_line

CLI = str(Path(sys.executable).parent / "pipeline25d")

#: lines of a real Snakemake 9.27.1 log (a 3 x 3 Delft run, 2026-11-27; input, output and reason lines
#: left out), as `pipeline25d run` reads it
SNAKEMAKE_LOG = """\
[Fri Nov 27 21:40:26 2026]
Finished jobid: 6 (Rule: ingest)
9 of 52 steps (17%) done
Select jobs to execute...
Execute 1 jobs...

[Fri Nov 27 21:40:26 2026]
localrule terrain:
    jobid: 14
[Fri Nov 27 21:40:41 2026]
Finished jobid: 14 (Rule: terrain)
10 of 52 steps (19%) done
Select jobs to execute...
Execute 2 jobs...

[Fri Nov 27 21:40:44 2026]
localcheckpoint plan:
    jobid: 3
    wildcards: pid=az000_el45
DAG of jobs will be updated after completion.
[Fri Nov 27 21:40:45 2026]
Finished jobid: 38 (Rule: plan)
12 of 52 steps (23%) done
Updating checkpoint dependencies.
Select jobs to execute...
Execute 1 jobs...

[Fri Nov 27 21:40:45 2026]
Finished jobid: 3 (Rule: plan)
13 of 53 steps (25%) done
Updating checkpoint dependencies.
"""


def test_progress_follows_snakemake_log():
    events = list(progress_events(SNAKEMAKE_LOG.splitlines()))
    # the total grows at checkpoints
    assert events == [(9, 52, "ingest"), (10, 52, "terrain"), (12, 52, "plan"), (13, 53, "plan")]
    # a finished line that names no rule (older Snakemake): the rule is the job id's, from its job block
    older = ["localcheckpoint plan:", "    jobid: 21", "Finished job 21.", "6 of 69 steps (9%) done"]
    assert list(progress_events(older)) == [(6, 69, "plan")]


def test_progress_line_estimates_time_left_from_jobs_done():
    assert progress_line(10, 40, "render_block", 60.0) == "[10/40  25%] render_block done · 1:00 elapsed · ~3:00 left"
    assert progress_line(0, 7, None, 1.0) == "[0/7   0%] job done · 0:01 elapsed"
    assert progress_line(1, 2, "tms", 4000.0).endswith("1:06:40 elapsed · ~1:06:40 left")


def test_help_lists_the_user_commands_and_no_internal_job_commands():
    out = subprocess.run([CLI, "--help"], capture_output=True, text=True, check=True).stdout
    for command in ("run", "measure", "heights", "evaluate", "serve", "wms", "web-tiles", "gl-info", "demo", "sample"):
        assert f"    {command} " in out, command
    assert "render-block" not in out and "    lod " not in out
    for command in ("heights", "evaluate", "serve", "wms", "demo", "sample", "osgb-levels"):
        proc = subprocess.run([CLI, command, "--help"], capture_output=True, text=True)
        assert proc.returncode == 0 and f"usage: pipeline25d {command}" in proc.stdout, (command, proc.stderr)


def test_run_dry_run_lists_the_jobs_of_a_scene(tmp_path):
    from pipeline25d_lab.scenes.demo import generate_demo_city

    generate_demo_city(tmp_path / "resources" / "demo", seed=3, n_buildings=10, scale=0.3)
    config = yaml.safe_load((REPO / "config" / "config.yaml").read_text())
    (tmp_path / "config.yaml").write_text(yaml.safe_dump({**config, "scene": "cli"}))
    proc = subprocess.run([CLI, "run", str(tmp_path / "config.yaml"), "--dry-run", "--directory", str(tmp_path)],
                          capture_output=True, text=True, cwd=tmp_path)
    assert proc.returncode == 0, proc.stderr[-2000:]
    assert "ingest" in proc.stdout and "plan" in proc.stdout
    assert not (tmp_path / "results").exists()


def test_run_names_a_missing_config(tmp_path):
    proc = subprocess.run([CLI, "run", str(tmp_path / "nope.yaml")], capture_output=True, text=True)
    assert proc.returncode == 1 and "nope.yaml: no such config file" in proc.stderr


def test_serve_stops_on_sigint_even_when_started_with_sigint_ignored(tmp_path):
    """A shell without job control starts background commands with SIGINT ignored; `kill -INT`
    must still stop the server (Python alone would never raise KeyboardInterrupt then)."""
    import signal
    import socket
    import time
    import urllib.request

    (tmp_path / "hello.txt").write_text("hello")
    with socket.socket() as sock:
        sock.bind(("127.0.0.1", 0))
        port = sock.getsockname()[1]
    proc = subprocess.Popen([CLI, "serve", str(tmp_path), "--port", str(port)], stdout=subprocess.PIPE,
                            stderr=subprocess.STDOUT, text=True,
                            preexec_fn=lambda: signal.signal(signal.SIGINT, signal.SIG_IGN))
    try:
        for _ in range(100):
            try:
                with urllib.request.urlopen(f"http://127.0.0.1:{port}/hello.txt", timeout=10) as resp:
                    assert resp.read() == b"hello"
                break
            except OSError:
                assert proc.poll() is None, proc.stdout.read()
                time.sleep(0.1)
    finally:
        proc.send_signal(signal.SIGINT)
        proc.communicate(timeout=30)
    assert proc.returncode == 0
