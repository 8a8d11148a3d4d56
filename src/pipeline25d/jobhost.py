"""A warm host for a run's jobs: one process that has imported what jobs use, forked once per job.

Every Snakemake job is a new Python process, and before it does any work it imports NumPy, GDAL,
pyproj, SciPy and the stage's modules: 0.15-0.35 s of CPU per job, much of a small job's time. A
run with :data:`MIN_JOBS` jobs or more to do on this machine starts a host when it starts
(``onstart`` in workflow/rules/common.smk) and stops it when it ends. The host imports those
modules once (:data:`PRELOAD`); each job's command (this file run as a stdlib-only script,
:func:`client`) then hands its job to the host, which forks a child that runs it
(:func:`pipeline25d.jobs.run_args`, as ``python -m pipeline25d.jobs`` would) with the job's own
standard streams, working folder, environment and thread settings.

- **The job process stays the job.** It waits for the child's exit status and exits with it, so
  Snakemake sees the same process, streams and status. A stop signal to it (Snakemake cancelling,
  Ctrl-C) is sent on to the child as one byte; the child holds its end of the connection in
  signal-driven mode, so that byte, or the connection's end when the job process is killed
  outright, raises SIGIO in the child, which stops it as a SIGTERM would
  (:mod:`pipeline25d.core.stopping`: no output put in place after it).
- **Anything amiss, the job runs as before.** No host (a short run, ``PIPELINE25D_JOB_HOST=off``,
  a cluster job, a host not yet listening or gone): the command becomes ``python -m pipeline25d.jobs``.
- **Accounting.** The host is Snakemake's child and each job's process is the host's child until
  reaped, so the run's CPU (``RUSAGE_CHILDREN`` of whoever started Snakemake) still holds every job.
  A job's own log has its CPU from the fork on; its start-up (``startup_s``) is then near zero.
- **The host ends with Snakemake** (``PR_SET_PDEATHSIG``), whatever way Snakemake ends.
- **Memory kept for reuse.** Every job's process, hosted or not, and the tools it starts keep what
  they free for their next temporaries (:data:`MALLOC_TUNABLES`), and a job ends without the
  interpreter's teardown (:func:`end_now`).

Over 400 lines for one job: the two ends of one protocol, the job's process (run isolated and
stdlib-only, it can import nothing beside it) and the host, whose wire format and environment are
defined once here.
"""

from __future__ import annotations

import os
import signal
import socket
import struct
import sys
from typing import TYPE_CHECKING

if TYPE_CHECKING:
    import subprocess
    from collections.abc import Mapping

#: the environment variable that names the host's socket to a run's jobs
SOCKET_ENV = "PIPELINE25D_JOB_HOST_SOCKET"
#: set in a job's environment when the host's fork runs it
HOSTED_ENV = "PIPELINE25D_JOB_HOSTED"
#: the user's switch: ``auto`` (the default: a host for runs of MIN_JOBS jobs or more) or ``off``
SWITCH_ENV = "PIPELINE25D_JOB_HOST"
#: the fewest jobs a run must have to start a host: the host's own imports cost about as much CPU
#: as five jobs' (1.2-1.5 s on the bench machine), each hosted job saves 0.15-0.35 s
MIN_JOBS = 12
#: what the host imports: the modules most jobs import, not those few jobs need (trimesh alone is 0.8 s)
PRELOAD = ("numpy", "osgeo.gdal", "osgeo.gdal_array", "osgeo.osr", "pyproj", "affine", "moderngl",
           "scipy.ndimage", "PIL.Image", "osgeo_utils.gdal2tiles",
           "pipeline25d.jobs", "pipeline25d.stages.ingest", "pipeline25d.stages.lod",
           "pipeline25d.stages.terrain.build", "pipeline25d.stages.scene", "pipeline25d.stages.plan",
           "pipeline25d.stages.render_block", "pipeline25d.stages.maps.warp", "pipeline25d.stages.tiles.web",
           "pipeline25d.publish.report_figures", "pipeline25d.publish.report")

#: glibc's malloc in every job's process (``GLIBC_TUNABLES``, read as a process starts; a fork keeps
#: them): blocks up to 32 MiB (glibc's most) from the heap, not a mapping each, and up to 256 MiB freed
#: at its top kept, so a job's temporaries reuse its pages (docs/running.md: 5 % less CPU on the 3 x 3 bench)
MALLOC_TUNABLES = {"glibc.malloc.mmap_threshold": 32 << 20, "glibc.malloc.trim_threshold": 256 << 20,
                   "glibc.malloc.top_pad": 64 << 20}

#: seconds :func:`stop` waits for the host to end after SIGTERM before it kills it
STOP_WAIT_S = 10

_HEADER = struct.Struct("!Q")      # the request's length
_STATUS = struct.Struct("!i")      # the child's exit status
_STOP = b"S"                       # a stop signal, sent on to the child
_STARTED = b"R"                    # the child's first word: it has the job (before it, the job runs itself)


# -- the job's side ---------------------------------------------------------------------------
def client(argv: list[str]) -> int:
    """``python -I -S jobhost.py job RULE THREADS SPEC LOG``: every rule's command (workflow/rules/
    common.smk). Hands the job to the run's host, or becomes ``python -m pipeline25d.jobs`` with the
    same arguments where there is none. Stdlib only: it starts in 0.02 CPU-s."""
    if not hand("pipeline25d.jobs:run_args", argv):
        os.execve(sys.executable, [sys.executable, "-m", "pipeline25d.jobs", *argv], job_env(os.environ))
    return 0                                         # (not reached: hand exits with the job's status)


def hand(runner: str, job, path: list[str] | None = None) -> bool:
    """Hand ``job`` (JSON data) to the run's host and exit with its child's status; False (nothing
    done) where there is no host to hand it to. The child calls ``runner`` (``module:function``)
    on the job, with ``path`` as its ``sys.path`` if given (else the host's)."""
    socket_path = os.environ.get(SOCKET_ENV)
    if not socket_path or "SLURM_JOB_ID" in os.environ:     # a cluster job runs where the scheduler put it
        return False
    import json

    conn = socket.socket(socket.AF_UNIX, socket.SOCK_STREAM)
    try:
        conn.connect(socket_path)
        times = os.times()
        request = json.dumps({"job": job, "runner": runner, "cwd": os.getcwd(), "env": job_env(os.environ),
                              "path": path, "cpu_s": times.user + times.system}).encode()
        socket.send_fds(conn, [_HEADER.pack(len(request))], [0, 1, 2])
        conn.sendall(request)
        started = _receive(conn, 1) == _STARTED
    except OSError:                # no host listening (yet, or any more)
        started = False
    if not started:                # nothing was started: the job runs itself
        conn.close()
        return False

    def send_on(signum, frame) -> None:
        try:
            conn.send(_STOP)
        except OSError:
            pass

    signal.signal(signal.SIGTERM, send_on)
    signal.signal(signal.SIGINT, send_on)
    status = _receive(conn, _STATUS.size)
    if status is None:
        sys.stderr.write("pipeline25d: error: the job's process on the job host ended without a status\n")
        sys.exit(1)
    sys.exit(_STATUS.unpack(status)[0])


def job_env(env: Mapping[str, str]) -> dict[str, str]:
    """A job's environment: ``env`` with :data:`MALLOC_TUNABLES` added to its ``GLIBC_TUNABLES``
    (a tunable ``env`` sets itself keeps its value)."""
    own = env.get("GLIBC_TUNABLES", "")
    named = {item.split("=", 1)[0] for item in own.split(":") if item}
    added = [f"{name}={value}" for name, value in MALLOC_TUNABLES.items() if name not in named]
    return {**env, "GLIBC_TUNABLES": ":".join([own, *added] if own else added)}


def _receive(conn: socket.socket, n: int) -> bytes | None:
    """Exactly ``n`` bytes, or None if the connection ends or fails first."""
    data = b""
    while len(data) < n:
        try:
            more = conn.recv(n - len(data))
        except OSError:
            return None
        if not more:
            return None
        data += more
    return data


# -- starting and stopping it (the Snakefile's hooks) ------------------------------------------
def wanted(jobs: int, local: bool) -> bool:
    """Whether a run of ``jobs`` jobs, executed on this machine (``local``) or not, gets a host."""
    switch = os.environ.get(SWITCH_ENV, "auto")
    if switch not in ("auto", "off"):
        from pipeline25d.core.errors import ConfigError

        raise ConfigError(f"environment variable {SWITCH_ENV}: {switch!r} is neither 'auto' nor 'off'")
    return switch == "auto" and local and jobs >= MIN_JOBS and sys.platform.startswith("linux")


def start() -> subprocess.Popen:
    """Start a host for this process's jobs (they find it through :data:`SOCKET_ENV`)."""
    import subprocess
    import tempfile

    # private (0700: only this user's jobs can hand the host a job) and short (a socket's path has 107 bytes at most)
    folder = tempfile.mkdtemp(prefix="p25d-host-")
    path = os.path.join(folder, "socket")
    host = subprocess.Popen([sys.executable, "-m", "pipeline25d.jobhost", "serve", path, str(os.getpid())],
                            stdin=subprocess.DEVNULL, stdout=subprocess.DEVNULL, env=_host_env())
    os.environ[SOCKET_ENV] = path
    return host


def stop(host: subprocess.Popen | None) -> None:
    """Stop ``host`` and wait for it (its CPU, and its jobs', then count as this process's children)."""
    import shutil
    import subprocess

    path = os.environ.pop(SOCKET_ENV, None)
    if host is not None and host.poll() is None:
        host.terminate()
        try:
            host.wait(timeout=STOP_WAIT_S)
        except subprocess.TimeoutExpired:        # (it has nothing to save: its jobs are their own processes)
            host.kill()
            host.wait()
    if path:
        shutil.rmtree(os.path.dirname(path), ignore_errors=True)


def _host_env() -> dict[str, str]:
    """The host's environment: a job's (:func:`job_env`: its forks keep its malloc), with one thread
    for the libraries it loads (each child sets its job's own counts)."""
    return {**job_env(os.environ), "OMP_NUM_THREADS": "1", "OPENBLAS_NUM_THREADS": "1"}


# -- the host ---------------------------------------------------------------------------------
def serve(path: str, parent: int) -> int:
    """Import :data:`PRELOAD`, listen on ``path`` and fork a child per job until stopped. Returns
    the host's exit status (0); a child ends with its job's (:func:`end_now`). The host removes ``path``'s folder
    as it ends, however it is stopped (Snakemake killed outright runs no ``onerror``)."""
    host = os.getpid()
    try:
        return _serve(path, parent)
    finally:
        if os.getpid() == host:
            import shutil

            shutil.rmtree(os.path.dirname(path), ignore_errors=True)


def _serve(path: str, parent: int) -> int:
    _end_with(parent)
    signal.signal(signal.SIGINT, signal.SIG_IGN)               # Ctrl-C stops the jobs, not the host
    signal.signal(signal.SIGTERM, _ender(os.getpid(), os.path.dirname(path)))
    import gc
    import importlib

    for name in PRELOAD:
        try:
            importlib.import_module(name)
        except ImportError:
            pass
    gc.collect()
    gc.freeze()                                   # the children's collections leave these pages shared
    from pipeline25d.core import cores

    listener = _listen(path)
    signal.signal(signal.SIGCHLD, _reap)
    latest = cores.reading()
    while True:
        conn, _ = listener.accept()
        previous, latest = latest, cores.reading()    # the machine's idle time since the last job came
        request = _request(conn)
        if request is None:
            conn.close()
            continue
        if os.fork() == 0:
            listener.close()
            end_now(_child(conn, *request, previous))
        for fd in request[0]:
            os.close(fd)
        conn.close()


def _ender(host: int, folder: str):
    """The host's SIGTERM handler: remove ``folder`` and end at once. Not by raising SystemExit: one
    raised inside an import, which some libraries' own handlers swallow, or inside the interpreter's
    shutdown after another stop, left the host running, and Snakemake waiting for it (twice in many
    stopped runs). A fork that has not yet taken its job's signals ends the same way, folder kept."""
    def end(signum, frame) -> None:
        if os.getpid() == host:
            import shutil

            shutil.rmtree(folder, ignore_errors=True)
        os._exit(0)

    return end


def _end_with(parent: int) -> None:
    """SIGTERM this process when ``parent`` ends (Linux), or now if it already has. (The kernel
    watches the thread that started it: Snakemake runs its ``onstart`` on its main thread.)"""
    import ctypes

    PR_SET_PDEATHSIG = 1
    ctypes.CDLL(None, use_errno=True).prctl(PR_SET_PDEATHSIG, signal.SIGTERM)
    if os.getppid() != parent:
        sys.exit(0)


def _listen(path: str) -> socket.socket:
    """A socket listening at ``path``, which appears only once it listens (a job that connects
    earlier finds no file and runs itself)."""
    listener = socket.socket(socket.AF_UNIX, socket.SOCK_STREAM)
    early = path + ".new"
    listener.bind(early)
    listener.listen(64)
    os.replace(early, path)
    return listener


def _reap(signum, frame) -> None:
    """Collect every ended child (their resources then count as the host's children's)."""
    while True:
        try:
            pid, _ = os.waitpid(-1, os.WNOHANG)
        except ChildProcessError:
            return
        if pid == 0:
            return


def _request(conn: socket.socket) -> tuple[list[int], bytes] | None:
    """(standard stream fds, JSON request) from a job process, or None if it sent less."""
    try:
        header, fds, _, _ = socket.recv_fds(conn, _HEADER.size, 3)
    except OSError:
        return None
    whole = len(header) == _HEADER.size and len(fds) == 3
    body = _receive(conn, _HEADER.unpack(header)[0]) if whole else None
    if body is None:
        for fd in fds:
            os.close(fd)
        return None
    return fds, body


def _child(conn: socket.socket, fds: list[int], body: bytes, since: tuple) -> int:
    """Run the request's job in this forked child as its own process would; send its
    status; return it. ``since``: the host's reading of the machine's CPU times before this job
    came (:func:`pipeline25d.core.cores.reading`): the job's first count of idle cores covers the
    time since, where that is long enough and recent, instead of waiting for a count of its own."""
    import json
    import time

    from pipeline25d.core import cores

    signal.signal(signal.SIGCHLD, signal.SIG_DFL)
    signal.signal(signal.SIGTERM, signal.SIG_DFL)
    signal.signal(signal.SIGINT, signal.default_int_handler)
    for target, fd in enumerate(fds):
        os.dup2(fd, target)
        os.close(fd)
    conn.sendall(_STARTED)
    _stop_on_word(conn)
    request = json.loads(body)
    os.chdir(request["cwd"])
    os.environ.clear()
    os.environ.update(request["env"])
    if request["path"] is not None:
        sys.path[:] = request["path"]
    _job_threads()
    recent = cores.SAMPLE_S <= time.monotonic() - since[2] <= cores.RECENT_S
    cores.mark(since if recent else None, request["cpu_s"])
    os.environ[HOSTED_ENV] = "1"
    status = 1
    try:
        import importlib

        module, function = request["runner"].split(":")
        getattr(importlib.import_module(module), function)(request["job"])
        status = 0
    except SystemExit as exc:
        status = exc.code if isinstance(exc.code, int) else (0 if exc.code is None else 1)
    except BaseException:                           # as an uncaught exception would: traceback, status 1
        import traceback

        traceback.print_exc()
    finally:
        signal.signal(signal.SIGIO, signal.SIG_IGN)
        for stream in (sys.stdout, sys.stderr):
            stream.flush()
        try:
            conn.sendall(_STATUS.pack(status))
        except OSError:
            pass
    return status


def end_now(status: int) -> None:
    """End this process with ``status`` once its exit handlers have run (the job's log closed, a
    KTX2 transcoder stopped) and its streams are flushed, without the interpreter's teardown of
    every module and object (0.05 CPU-s in a fork of the host that did nothing, more after a job)."""
    import atexit

    try:
        atexit._run_exitfuncs()
        for stream in (sys.stdout, sys.stderr):
            stream.flush()
    finally:
        os._exit(status)


def _job_threads() -> None:
    """The job's thread counts (Snakemake sets OMP_NUM_THREADS and the like to its threads) on the
    libraries the host loaded with one."""
    threads = os.environ.get("OMP_NUM_THREADS", "")
    if threads.isdigit() and int(threads) > 1:
        from threadpoolctl import threadpool_limits

        threadpool_limits(limits=int(threads))


def _stop_on_word(conn: socket.socket) -> None:
    """SIGIO when the job process sends a stop or its end of ``conn`` closes; either stops this job
    as a SIGTERM does."""
    import fcntl

    from pipeline25d.core.stopping import stop_signal

    def on_io(signum, frame) -> None:
        if stop_signal() is not None:               # stopping already (a signal to the whole group)
            return
        try:
            word = conn.recv(1, socket.MSG_PEEK | socket.MSG_DONTWAIT)
        except BlockingIOError:                     # a wake-up with nothing to read: not a stop
            return
        except OSError:
            word = b""
        if word in (b"", _STOP):
            signal.raise_signal(signal.SIGTERM)

    signal.signal(signal.SIGIO, on_io)
    fcntl.fcntl(conn.fileno(), fcntl.F_SETOWN, os.getpid())
    fcntl.fcntl(conn.fileno(), fcntl.F_SETFL, fcntl.fcntl(conn.fileno(), fcntl.F_GETFL) | os.O_ASYNC)
    on_io(signal.SIGIO, None)                       # a stop, or the end, that came before


def main(argv: list[str] | None = None) -> int:
    """``python -m pipeline25d.jobhost serve SOCKET PARENT_PID``: the host (started by :func:`start`);
    ``jobhost.py job RULE THREADS SPEC LOG``: a job (:func:`client`)."""
    word, *args = argv if argv is not None else sys.argv[1:]
    if word == "job":
        return client(args)
    path, parent = args
    return serve(path, int(parent))


if __name__ == "__main__":
    sys.exit(main())
