"""The job host (pipeline25d.jobhost): a hosted job has its own streams, folder, environment and
status; a stop to its process stops it, and so does its process's death; without a host a job runs
itself; a workflow run with a host makes the same files as one without."""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import pytest

from pipeline25d import jobhost
from pipeline25d.core import cores
from pipeline25d.core.errors import ConfigError

TESTS = Path(__file__).parent


def job_process(runner: str, job: dict, cwd: Path, **env) -> subprocess.Popen:
    """A process that hands ``job`` to the host (as a rule's command does) and runs it itself if
    there is none, printing where it ran."""
    code = ("import sys; sys.path.insert(0, %r)\n"
            "from pipeline25d.jobhost import hand\n"
            "import jobhost_runners\n"
            "job = %r\n"
            "if not hand(%r, job, sys.path):\n"
            "    print('ran itself', flush=True)\n"
            "    getattr(jobhost_runners, %r.split(':')[1])(job)\n") % (str(TESTS), job, runner, runner)
    return subprocess.Popen([sys.executable, "-c", code], cwd=cwd, stdout=subprocess.PIPE, stderr=subprocess.PIPE,
                            text=True, env={**os.environ, **env})


def test_a_hosted_job_has_its_own_folder_environment_streams_and_status(host, tmp_path):
    out = tmp_path / "seen.txt"
    proc = job_process("jobhost_runners:report", {"out": str(out), "status": 3}, tmp_path, JOBHOST_TEST_VALUE="mine")
    stdout, stderr = proc.communicate(timeout=60)
    assert proc.returncode == 3
    assert "ran itself" not in stdout
    assert stdout == "to stdout from the child\n" and "to stderr from the child" in stderr
    cwd, value, pid = out.read_text().splitlines()
    assert (cwd, value) == (str(tmp_path), "mine")
    assert int(pid) != proc.pid                   # a fork of the host ran it, not the job's process
    assert os.stat(os.path.dirname(host)).st_mode & 0o777 == 0o700    # only this user's jobs reach the host


def test_a_hosted_job_ends_after_its_exit_handlers_ran_and_its_output_was_flushed(host, tmp_path):
    """The host's fork ends at once after its job (jobhost.end_now: no teardown of every module),
    but not before what a process's normal end does for a job: exit handlers, buffered output."""
    out = tmp_path / "handler.txt"
    proc = job_process("jobhost_runners:exit_handler", {"out": str(out)}, tmp_path)
    stdout, stderr = proc.communicate(timeout=60)
    assert proc.returncode == 0, stderr
    assert stdout == "printed, not flushed"
    deadline = time.monotonic() + 30           # the fork ends after it has sent the job's status
    while not out.exists() and time.monotonic() < deadline:
        time.sleep(0.05)
    assert out.read_text() == "exit handlers ran"


def test_a_hosted_job_counts_idle_cores_without_waiting(host, tmp_path):
    """Its first count covers the time since the host's last reading (see cores.mark); a job run
    by its own process marks its start and waits out the rest of cores.SAMPLE_S."""
    import json

    time.sleep(2 * cores.SAMPLE_S)                # the host's reading, taken as it started listening, ages
    out = tmp_path / "count.json"
    proc = job_process("jobhost_runners:first_count", {"out": str(out)}, tmp_path)
    proc.communicate(timeout=60)
    count = json.loads(out.read_text())
    assert proc.returncode == 0 and count["slept"] == [] and 0 <= count["idle"] <= (os.cpu_count() or 1) + 0.2


def test_a_failing_hosted_job_prints_its_traceback_and_fails(host, tmp_path):
    proc = job_process("jobhost_runners:fail", {}, tmp_path)
    _, stderr = proc.communicate(timeout=60)
    assert proc.returncode == 1 and "RuntimeError: a job that fails with a traceback" in stderr


def _started(proc, pid_file: Path) -> int:
    deadline = time.monotonic() + 60
    while not pid_file.exists():
        assert proc.poll() is None, proc.communicate()
        assert time.monotonic() < deadline
        time.sleep(0.05)
    time.sleep(0.2)
    return int(pid_file.read_text())


def _gone(pid: int, within_s: float = 20) -> bool:
    deadline = time.monotonic() + within_s
    while time.monotonic() < deadline:
        try:
            os.kill(pid, 0)
        except ProcessLookupError:
            return True
        time.sleep(0.05)
    return False


@pytest.mark.parametrize("sig", [signal.SIGTERM, signal.SIGINT])
def test_a_stop_to_the_job_process_stops_its_hosted_job(host, tmp_path, sig):
    files = {"pid": str(tmp_path / "pid"), "ended": str(tmp_path / "ended")}
    proc = job_process("jobhost_runners:wait", files, tmp_path)
    child = _started(proc, tmp_path / "pid")
    proc.send_signal(sig)
    proc.communicate(timeout=30)
    # stopped, not finished (a signal just before the job's process takes it over ends it at once)
    assert proc.returncode in (128 + signal.SIGTERM, 128 + signal.SIGINT, 1, -sig)
    assert _gone(child), "the hosted job still runs after its process was stopped"
    assert (tmp_path / "ended").read_text() == "stopped"     # it ran its clean-up, as a stopped job does


def test_a_job_process_killed_outright_stops_its_hosted_job(host, tmp_path):
    files = {"pid": str(tmp_path / "pid"), "ended": str(tmp_path / "ended")}
    proc = job_process("jobhost_runners:wait", files, tmp_path)
    child = _started(proc, tmp_path / "pid")
    proc.kill()
    proc.communicate(timeout=30)
    assert _gone(child), "the hosted job still runs after its process was killed"
    assert (tmp_path / "ended").read_text() == "stopped"


def test_without_a_host_the_job_runs_itself(tmp_path, monkeypatch):
    monkeypatch.delenv(jobhost.SOCKET_ENV, raising=False)
    out = tmp_path / "seen.txt"
    proc = job_process("jobhost_runners:report", {"out": str(out), "status": 0}, tmp_path)
    stdout, _ = proc.communicate(timeout=60)
    assert proc.returncode == 0 and stdout.startswith("ran itself")
    # a socket named but not there (a host not listening yet, or gone): the same
    proc = job_process("jobhost_runners:report", {"out": str(out), "status": 0}, tmp_path,
                       **{jobhost.SOCKET_ENV: str(tmp_path / "no-such-socket")})
    stdout, _ = proc.communicate(timeout=60)
    assert proc.returncode == 0 and stdout.startswith("ran itself")
    assert int(out.read_text().splitlines()[2]) == proc.pid


def test_a_host_that_ends_before_starting_the_job_leaves_it_to_run_itself(tmp_path):
    """A host stopped between taking a job and forking for it (the run ending): no child has the job."""
    import socket
    import threading

    path = str(tmp_path / "socket")
    listener = socket.socket(socket.AF_UNIX, socket.SOCK_STREAM)
    listener.bind(path)
    listener.listen(1)

    def take_and_end() -> None:
        conn, _ = listener.accept()
        _, fds, _, _ = socket.recv_fds(conn, 8, 3)
        for fd in fds:                  # the job's streams, as the host closes its copies
            os.close(fd)
        conn.close()

    taker = threading.Thread(target=take_and_end)
    taker.start()
    out = tmp_path / "seen.txt"
    proc = job_process("jobhost_runners:report", {"out": str(out), "status": 0}, tmp_path, **{jobhost.SOCKET_ENV: path})
    stdout, _ = proc.communicate(timeout=60)
    taker.join()
    listener.close()
    assert proc.returncode == 0 and stdout.startswith("ran itself")


def test_a_host_stopped_by_its_parent_s_end_removes_its_socket_folder(tmp_path):
    """Snakemake killed outright runs no onerror: the host, told by the kernel, cleans up itself."""
    folder = tempfile.mkdtemp(prefix="p25d-host-")
    path = os.path.join(folder, "socket")
    start_host = (f"subprocess.Popen([sys.executable, '-m', 'pipeline25d.jobhost', 'serve', {path!r}, "
                  "str(os.getpid())])\n")
    parent = subprocess.Popen([sys.executable, "-c", f"import subprocess, sys, os, time\n{start_host}time.sleep(60)"])
    deadline = time.monotonic() + 60
    while not os.path.exists(path):
        assert time.monotonic() < deadline, "the host did not listen within 60 s"
        time.sleep(0.05)
    parent.kill()
    parent.wait()
    deadline = time.monotonic() + 30
    while os.path.exists(folder) and time.monotonic() < deadline:
        time.sleep(0.05)
    assert not os.path.exists(folder)


def test_a_host_is_wanted_for_local_runs_of_enough_jobs(monkeypatch):
    monkeypatch.delenv(jobhost.SWITCH_ENV, raising=False)
    assert jobhost.wanted(jobhost.MIN_JOBS, local=True)
    assert not jobhost.wanted(jobhost.MIN_JOBS - 1, local=True)
    assert not jobhost.wanted(500, local=False)
    monkeypatch.setenv(jobhost.SWITCH_ENV, "off")
    assert not jobhost.wanted(500, local=True)
    monkeypatch.setenv(jobhost.SWITCH_ENV, "yes")
    with pytest.raises(ConfigError, match="PIPELINE25D_JOB_HOST: 'yes' is neither 'auto' nor 'off'"):
        jobhost.wanted(500, local=True)


@pytest.mark.slow
def test_a_run_with_a_host_makes_the_files_a_run_without_one_makes(tmp_path):
    from pipeline25d_lab.harness.bench import results_of, run_workflow
    from pipeline25d_lab.harness.killtest import demo_config, output_digests

    config = demo_config(tmp_path / "scene", 0.25, [{"azimuth": 45, "elevation": 45}, {"azimuth": 0, "elevation": 90}])
    hosted, plain = tmp_path / "hosted", tmp_path / "plain"
    before = _hosts()
    env = {k: v for k, v in os.environ.items() if k not in (jobhost.SOCKET_ENV, jobhost.SWITCH_ENV)}
    run_workflow(hosted, config, cores=2, env=env)
    run_workflow(plain, config, cores=2, env={**env, jobhost.SWITCH_ENV: "off"})
    digests = output_digests(results_of(hosted, config))
    assert digests and digests == output_digests(results_of(plain, config))

    def hosted_jobs(work: Path) -> tuple[int, int]:
        logs = list((results_of(work, config) / "logs").rglob("*.log"))
        return sum("job host" in f.read_text() for f in logs), len(logs)

    n, of = hosted_jobs(hosted)
    # the first jobs may start before the host listens
    assert of >= jobhost.MIN_JOBS and n >= of // 2, f"{n} of {of} jobs hosted"
    assert hosted_jobs(plain)[0] == 0
    assert _hosts() <= before                     # the run's host ended, its socket's folder removed


def _hosts() -> set[str]:
    """Running hosts' pids and their sockets' folders."""
    pids = subprocess.run(["pgrep", "-f", "pipeline25d.jobhost"], capture_output=True, text=True).stdout.split()
    folders = {str(p) for p in Path(tempfile.gettempdir()).glob("p25d-host-*")}
    return set(pids) | folders


def test_a_host_ends_on_sigterm_even_inside_code_that_swallows_exceptions(tmp_path):
    """A library swallowing every exception during the host's imports once kept a host, stopped by
    SIGTERM's SystemExit, running (and Snakemake waiting for it): its handler ends it outright."""
    folder = tmp_path / "p25d-host-x"
    folder.mkdir()
    code = ("import os, signal, sys, time\n"
            "from pipeline25d.jobhost import _ender\n"
            f"signal.signal(signal.SIGTERM, _ender(os.getpid(), {str(folder)!r}))\n"
            "print('ready', flush=True)\n"
            "while True:\n"
            "    try:\n"
            "        time.sleep(0.01)\n"
            "    except BaseException:\n"               # as a bare except: in an imported module
            "        pass\n")
    proc = subprocess.Popen([sys.executable, "-c", code], stdout=subprocess.PIPE, text=True)
    assert proc.stdout.readline() == "ready\n"
    proc.send_signal(signal.SIGTERM)
    assert proc.wait(timeout=30) == 0
    assert not folder.exists()


GLIBC = __import__("platform").libc_ver()[0] == "glibc"
TIMES = 20


def faults_in_a_process(env: dict) -> int:
    """Page faults of a fresh process with ``env`` that fills and frees a 16 MiB array TIMES times
    after a first one."""
    code = ("import sys; sys.path.insert(0, %r)\n"
            "from jobhost_runners import page_faults_of_temporaries\n"
            "print(page_faults_of_temporaries(%d))\n") % (str(TESTS), TIMES)
    return int(subprocess.run([sys.executable, "-c", code], env=env, capture_output=True, text=True,
                              check=True).stdout)


def test_a_job_s_environment_adds_the_malloc_tunables_and_keeps_the_user_s_own():
    env = jobhost.job_env({"PATH": "/bin", "GLIBC_TUNABLES": "glibc.malloc.trim_threshold=1:glibc.cpu.x86_ibt=on"})
    items = env["GLIBC_TUNABLES"].split(":")
    assert env["PATH"] == "/bin"
    assert items[:2] == ["glibc.malloc.trim_threshold=1", "glibc.cpu.x86_ibt=on"]      # the user's, as given
    assert sorted(items[2:]) == ["glibc.malloc.mmap_threshold=33554432", "glibc.malloc.top_pad=67108864"]
    plain = jobhost.job_env({})["GLIBC_TUNABLES"].split(":")
    assert dict(item.split("=") for item in plain) == {k: str(v) for k, v in jobhost.MALLOC_TUNABLES.items()}


@pytest.mark.skipif(not GLIBC, reason="GLIBC_TUNABLES are glibc's")
def test_a_job_s_temporaries_reuse_its_pages_where_a_plain_process_faults_them_in_each_time():
    """The same loop in a process with a job's environment and in one without its tunables: a
    16 MiB temporary filled and freed 20 times after a first. Without them each one is a fresh
    mapping, faulted in again (by 4 KiB or, where NumPy asks for them, 2 MiB pages: at least one
    fault each); with them the first one's pages serve all."""
    plain = {k: v for k, v in os.environ.items() if k != "GLIBC_TUNABLES"}
    without, with_ = faults_in_a_process(plain), faults_in_a_process(jobhost.job_env(plain))
    assert without >= TIMES and with_ * 10 < without, (with_, without)


@pytest.mark.skipif(not GLIBC, reason="GLIBC_TUNABLES are glibc's")
def test_a_hosted_job_runs_with_the_malloc_tunables_and_reuses_its_pages(host, tmp_path):
    """The host started with them; its fork keeps them (and has them in its environment, for the
    tools a job starts)."""
    import json

    out = tmp_path / "faults.json"
    proc = job_process("jobhost_runners:reused_pages", {"out": str(out), "times": TIMES}, tmp_path)
    stdout, stderr = proc.communicate(timeout=60)
    assert proc.returncode == 0 and "ran itself" not in stdout, stderr
    seen = json.loads(out.read_text())
    assert {f"{k}={v}" for k, v in jobhost.MALLOC_TUNABLES.items()} <= set(seen["tunables"].split(":"))
    without = faults_in_a_process({k: v for k, v in os.environ.items() if k != "GLIBC_TUNABLES"})
    assert without >= TIMES and seen["faults"] * 10 < without, (seen["faults"], without)
