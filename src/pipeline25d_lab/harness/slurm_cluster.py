"""A one-node SLURM cluster on this machine, for tests and benchmarks of ``--profile profiles/slurm``.

:func:`local_cluster` writes a ``slurm.conf`` for this host (its CPUs and memory, one default
partition), starts ``munged``, ``slurmctld`` and ``slurmd`` in the foreground as children of
this process, waits until the node is idle, and stops and removes them afterwards. Its files
(configuration, state, spool, the MUNGE key and socket, one log per daemon) live in the folder
given (spool and MUNGE in a short-named one under /tmp where that folder's path is too long
for a socket's); the daemons listen on free ports of 127.0.0.1 only. There is no accounting database
(``sacct`` answers "accounting storage is disabled"), so runs on it take Snakemake's
``--slurm-status-command squeue``. It needs root (``SlurmUser=root``; ``munged`` is run as
root with ``--force`` so that its key and socket can stay in that folder) and Debian's
``slurmctld slurmd slurm-client munge`` packages (``make sysdeps``).

CLI (the benchmark, ``make slurm-bench``)::

    python -m pipeline25d_lab.harness.slurm_cluster [--scale 0.5] [--perspectives eight-45+nadir] [--name slurm]

runs one demo city through the SLURM profile on the local cluster and then with ``-j2``, and
writes ``bench/<name>.json``: Snakemake jobs, SLURM submissions, both wall times and whether
every map and web tile is byte-identical.
"""

from __future__ import annotations

import argparse
import ctypes
import json
import os
import re
import shlex
import shutil
import signal
import socket
import subprocess
import sys
import tempfile
import time
from contextlib import ExitStack, contextmanager
from dataclasses import dataclass
from pathlib import Path
from typing import Iterator

from pipeline25d.core.atomic import write_json, write_text
from pipeline25d.core.errors import ClusterError, WorkflowRunError
from pipeline25d.core.stopping import exit_on_sigterm
from pipeline25d_lab.harness.bench import REPO, results_of, run_workflow
from pipeline25d_lab.harness.killtest import demo_config, differences, output_digests

DAEMONS = {"munged": "/usr/sbin/munged", "slurmctld": "/usr/sbin/slurmctld", "slurmd": "/usr/sbin/slurmd"}
CLIENTS = ("sbatch", "squeue", "sinfo", "scontrol", "scancel", "srun")
START_TIMEOUT_S = 60.0
STOP_TIMEOUT_S = 15.0
PARTITION = "local"
SOCKET_PATH_MAX = 107                      # a UNIX socket's path: 108 bytes with the terminating NUL
SUBMITTED = re.compile(r"_slurm_rpc_submit_batch_job: JobId=(\d+)")
STEPS = re.compile(r"\d+ of (\d+) steps")
PROFILE = REPO / "profiles" / "slurm"
# the local cluster keeps no accounting (sacct fails): job status from squeue
SLURM_ARGS = ("--profile", str(PROFILE), "--slurm-status-command", "squeue")


@dataclass(frozen=True)
class ClusterInfo:
    """A running local cluster: its configuration, the environment for its clients, its logs."""

    conf: Path
    env: dict[str, str]
    logs: dict[str, Path]

    def submissions(self) -> list[int]:
        """The ids of every batch job submitted so far, from slurmctld's own log."""
        return [int(m) for m in SUBMITTED.findall(self.logs["slurmctld"].read_text(errors="replace"))]


def missing() -> list[str]:
    """What this machine lacks to start a local cluster (empty when it can): root, or the
    Debian packages' programs."""
    lacks = [] if os.geteuid() == 0 else ["root (slurmd and SlurmUser=root)"]
    lacks += [f"{path} (Debian package {'munge' if name == 'munged' else name})"
              for name, path in DAEMONS.items() if not os.access(path, os.X_OK)]
    lacks += [f"{name} (Debian package slurm-client)" for name in CLIENTS if shutil.which(name) is None]
    return lacks


def free_ports(n: int) -> list[int]:
    """``n`` distinct TCP ports free on 127.0.0.1 now."""
    with ExitStack() as stack:
        socks = [stack.enter_context(socket.socket()) for _ in range(n)]
        for s in socks:
            s.bind(("127.0.0.1", 0))
        return [s.getsockname()[1] for s in socks]


def memory_mb() -> int:
    """This machine's memory in MiB, as slurmd counts it (MemTotal)."""
    meminfo = Path("/proc/meminfo").read_text()
    return int(re.search(r"MemTotal:\s+(\d+) kB", meminfo).group(1)) // 1024


def slurm_conf(root: Path, sockets: Path, host: str, cpus: int, mem_mb: int, ports: tuple[int, int]) -> str:
    """slurm.conf of a one-node cluster on ``host`` at 127.0.0.1: its state under ``root``, the
    slurmd spool and the MUNGE socket under ``sockets``.

    No cgroups (proctrack/linuxproc, task/none) and no accounting; MinJobAge keeps a finished
    job in squeue for 300 s, which the plugin's squeue status checks rely on.
    """
    ctld_port, slurmd_port = ports
    return "\n".join([
        "ClusterName=local",
        f"SlurmctldHost={host}(127.0.0.1)",
        "SlurmUser=root",
        "SlurmdUser=root",
        f"SlurmctldPort={ctld_port}",
        f"SlurmdPort={slurmd_port}",
        "CommunicationParameters=NoCtldInAddrAny,NoInAddrAny",     # bind to 127.0.0.1, not to every address
        "AuthType=auth/munge",
        "CredType=cred/munge",
        f"AuthInfo=socket={sockets / 'munge' / 'munge.socket'}",
        f"StateSaveLocation={root / 'state'}",
        f"SlurmdSpoolDir={sockets / 'spool'}",
        f"SlurmctldPidFile={root / 'slurmctld.pid'}",
        f"SlurmdPidFile={root / 'slurmd.pid'}",
        "ProctrackType=proctrack/linuxproc",
        "TaskPlugin=task/none",
        "SelectType=select/cons_tres",
        "SelectTypeParameters=CR_Core_Memory",
        "AccountingStorageType=accounting_storage/none",
        "JobAcctGatherType=jobacct_gather/none",
        "JobCompType=jobcomp/none",
        "MpiDefault=none",
        "MailProg=/bin/true",
        "ReturnToService=2",
        "MinJobAge=300",
        "SlurmctldDebug=info",
        "SlurmdDebug=info",
        f"NodeName={host} NodeAddr=127.0.0.1 CPUs={cpus} RealMemory={mem_mb} State=UNKNOWN",
        f"PartitionName={PARTITION} Nodes={host} Default=YES MaxTime=INFINITE State=UP",
        "",
    ])


def srun_keeping_conf(bin_dir: Path, conf: Path) -> None:
    """Write ``bin_dir/srun``, which runs the real srun with SLURM_CONF=``conf``.

    The SLURM jobstep plugin drops every SLURM_* variable but the job's ids before it runs a
    job through srun inside the allocation, SLURM_CONF too, and srun then finds no
    configuration (it looks in /etc/slurm, then DNS). This cluster's slurm.conf is not in /etc.
    """
    srun = bin_dir / "srun"
    write_text(srun, f'#!/bin/sh\nSLURM_CONF={shlex.quote(str(conf))} exec {shlex.quote(shutil.which("srun"))} "$@"\n')
    srun.chmod(0o755)


def _die_with_parent() -> None:
    """In the child before exec: SIGTERM when the process that started it dies (PR_SET_PDEATHSIG),
    so a killed test or benchmark leaves no daemon behind."""
    ctypes.CDLL(None, use_errno=True).prctl(1, signal.SIGTERM)


def _start(name: str, args: list[str], log: Path, env: dict[str, str]) -> subprocess.Popen:
    """Start daemon ``name`` in the foreground (its own session), its output to ``log``."""
    with open(log, "wb") as out:
        return subprocess.Popen([DAEMONS[name], *args], stdout=out, stderr=subprocess.STDOUT, env=env,
                                stdin=subprocess.DEVNULL, start_new_session=True, preexec_fn=_die_with_parent)


def _check_alive(procs: dict[str, subprocess.Popen], logs: dict[str, Path]) -> None:
    for name, proc in procs.items():
        if proc.poll() is not None:
            raise ClusterError(f"{name} exited with status {proc.returncode} at start; see {logs[name]}")


def _wait_idle(env: dict[str, str], procs: dict[str, subprocess.Popen], logs: dict[str, Path]) -> None:
    """Wait until sinfo shows the node idle; a daemon that died or a timeout is a ClusterError."""
    deadline = time.monotonic() + START_TIMEOUT_S
    state = ""
    while time.monotonic() < deadline:
        _check_alive(procs, logs)
        proc = subprocess.run(["sinfo", "-h", "-N", "-o", "%T"], env=env, capture_output=True, text=True)
        state = proc.stdout.strip() or proc.stderr.strip()
        if state == "idle":
            return
        time.sleep(0.5)
    raise ClusterError(f"the node is not idle after {START_TIMEOUT_S:.0f} s (sinfo: {state!r}); "
                       f"see {logs['slurmctld']} and {logs['slurmd']}")


def _cancel_all(env: dict[str, str]) -> None:
    """Cancel every job of the cluster (all are ours) and wait until none runs."""
    jobs = subprocess.run(["squeue", "-h", "-o", "%i"], env=env, capture_output=True, text=True).stdout.split()
    if not jobs:
        return
    subprocess.run(["scancel", *jobs], env=env, capture_output=True)
    deadline = time.monotonic() + STOP_TIMEOUT_S
    while time.monotonic() < deadline and subprocess.run(
            ["squeue", "-h", "-t", "PD,R,CG", "-o", "%i"], env=env, capture_output=True, text=True).stdout.strip():
        time.sleep(0.5)


def _stop(procs: dict[str, subprocess.Popen], logs: dict[str, Path]) -> None:
    """SIGTERM each daemon (slurmd, slurmctld, munged, in that order); SIGKILL what outlives the timeout."""
    stubborn = []
    for name in ("slurmd", "slurmctld", "munged"):
        proc = procs.get(name)
        if proc is None or proc.poll() is not None:
            continue
        proc.terminate()
        try:
            proc.wait(STOP_TIMEOUT_S)
        except subprocess.TimeoutExpired:
            proc.kill()
            proc.wait()
            stubborn.append(name)
    if stubborn:
        raise ClusterError(f"{', '.join(stubborn)} did not stop on SIGTERM and were killed; see "
                           + ", ".join(str(logs[n]) for n in stubborn))


def _write_files(tmp: Path, sockets: Path, host: str, conf: Path) -> None:
    """The cluster's folders, slurm.conf, a new MUNGE key (0400) and the srun wrapper."""
    munge = sockets / "munge"
    for folder in (tmp / "log", tmp / "state", tmp / "bin", sockets / "spool", munge):
        folder.mkdir(parents=True, exist_ok=True)
    munge.chmod(0o700)
    write_text(conf, slurm_conf(tmp, sockets, host, os.cpu_count() or 1, memory_mb(), tuple(free_ports(2))))
    key = munge / "munge.key"
    key.unlink(missing_ok=True)
    with os.fdopen(os.open(key, os.O_WRONLY | os.O_CREAT | os.O_EXCL, 0o400), "wb") as f:
        f.write(os.urandom(1024))
    srun_keeping_conf(tmp / "bin", conf)


def _start_daemons(procs: dict[str, subprocess.Popen], munge: Path, conf: Path, logs: dict[str, Path],
                   env: dict[str, str]) -> None:
    """Start munged, then slurmctld and slurmd, into ``procs``; return once the node is idle."""
    procs["munged"] = _start("munged", [
        "--foreground", "--force", f"--socket={munge / 'munge.socket'}", f"--key-file={munge / 'munge.key'}",
        f"--pid-file={munge / 'munged.pid'}", f"--seed-file={munge / 'munged.seed'}"], logs["munged"], env)
    deadline = time.monotonic() + START_TIMEOUT_S
    while not (munge / "munge.socket").exists():
        _check_alive(procs, logs)
        if time.monotonic() > deadline:
            raise ClusterError(f"munged made no socket in {START_TIMEOUT_S:.0f} s; see {logs['munged']}")
        time.sleep(0.1)
    procs["slurmctld"] = _start("slurmctld", ["-D", "-f", str(conf)], logs["slurmctld"], env)
    procs["slurmd"] = _start("slurmd", ["-D", "-f", str(conf)], logs["slurmd"], env)
    _wait_idle(env, procs, logs)


@contextmanager
def local_cluster(tmp: Path) -> Iterator[ClusterInfo]:
    """Run a one-node SLURM cluster with its files under ``tmp`` for the ``with`` block.

    Raises :class:`ClusterError` naming the daemon and its log when one does not start. On
    leaving, the cluster's jobs are cancelled, the daemons stopped, and everything but the
    logs (``tmp/log/<daemon>.log``) and ``tmp/slurm.conf`` removed.
    """
    if lacks := missing():
        raise ClusterError("a local SLURM cluster needs " + ", ".join(lacks))
    tmp = Path(tmp).resolve()
    host = socket.gethostname()
    # the sockets (slurmstepd's spool/<host>_<job>.<step>, munged's) need short paths
    sockets = tmp if len(str(tmp)) + len(host) + 40 <= SOCKET_PATH_MAX else Path(tempfile.mkdtemp(prefix="slurm-"))
    conf = tmp / "slurm.conf"
    logs = {name: tmp / "log" / f"{name}.log" for name in DAEMONS}
    env = {**os.environ, "SLURM_CONF": str(conf), "PATH": f"{tmp / 'bin'}:{os.environ['PATH']}"}
    procs: dict[str, subprocess.Popen] = {}
    try:
        _write_files(tmp, sockets, host, conf)
        _start_daemons(procs, sockets / "munge", conf, logs, env)
        yield ClusterInfo(conf=conf, env=env, logs=logs)
    finally:
        try:
            if "slurmd" in procs and procs["slurmctld"].poll() is None:
                _cancel_all(env)
        finally:
            _stop(procs, logs)
            for folder in (tmp / "state", tmp / "bin", sockets / "spool", sockets / "munge",
                           *([sockets] if sockets != tmp else [])):
                shutil.rmtree(folder, ignore_errors=True)


def logged_counts(log: Path) -> dict[str, int]:
    """From a finished run's Snakemake log: its jobs (the last "N of M steps" total), those
    Snakemake ran itself (``localrule``, e.g. ``all``) and the SLURM submissions it logged."""
    text = log.read_text()
    steps = STEPS.findall(text)
    if not steps:
        raise WorkflowRunError(f"no finished step logged in {log}")
    return {"jobs": int(steps[-1]), "local_jobs": len(re.findall(r"^localrule ", text, re.M)),
            "submissions_logged": text.count("has been submitted with SLURM jobid")}


def local_against_slurm(work: Path, config: dict, cores: int = 2) -> dict:
    """Run ``config`` through the SLURM profile on a local cluster (``work/slurm``), then with
    ``-j cores`` (``work/local``); return the jobs, submissions, wall times and whether every
    map and web tile is byte-identical. The SLURM run goes first and pays any cold caches."""
    with local_cluster(work / "cluster") as cluster:
        slurm_wall = run_workflow(work / "slurm", config, None, extra=SLURM_ARGS, env=cluster.env)
        submissions = len(cluster.submissions())
    local_wall = run_workflow(work / "local", config, cores)
    counts = logged_counts(work / "slurm" / "snakemake.log")
    want = output_digests(results_of(work / "local", config))
    got = output_digests(results_of(work / "slurm", config))
    return {"jobs": counts["jobs"], "remote_jobs": counts["jobs"] - counts["local_jobs"],
            "slurm_submissions": submissions, "submissions_logged": counts["submissions_logged"],
            "wall_s": {f"local_j{cores}": round(local_wall, 1), "slurm": round(slurm_wall, 1)},
            "slurm_to_local_wall": round(slurm_wall / local_wall, 2), "files_compared": len(want),
            "identical": bool(want) and got == want, "differing": differences(got, want)}


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(prog="python -m pipeline25d_lab.harness.slurm_cluster",
                                 description=__doc__.split("\n\n")[0])
    ap.add_argument("--scale", type=float, default=0.5, help="demo city scale (1 = the make run demo)")
    ap.add_argument("--perspectives", default="eight-45+nadir")
    ap.add_argument("--cores", type=int, default=2, help="-j of the local run")
    ap.add_argument("--name", default="slurm")
    args = ap.parse_args(argv)
    if lacks := missing():
        raise SystemExit("slurm_cluster: a local SLURM cluster needs " + ", ".join(lacks) + " (make sysdeps)")
    exit_on_sigterm()                              # stop the daemons on SIGTERM too
    work = REPO / "bench" / args.name
    config = {**demo_config(work / "scene", args.scale, args.perspectives), "scene": args.name}
    load_before = os.getloadavg()[0]
    try:
        result = local_against_slurm(work, config, args.cores)
    except (WorkflowRunError, ClusterError) as exc:
        raise SystemExit(f"slurm_cluster: {exc}") from None
    result = {"scale": args.scale, "perspectives": args.perspectives, **result,
              "load_avg": [round(load_before, 2), round(os.getloadavg()[0], 2)]}      # 1-min, before and after
    write_json(REPO / "bench" / f"{args.name}.json", result)
    print(json.dumps({k: v for k, v in result.items() if k != "differing"}))
    return 0 if result["identical"] else 1


if __name__ == "__main__":
    sys.exit(main())
