"""Kill-safe resume: interrupt runs at random moments, resume them, compare with an uninterrupted run.

A reference run of the scene goes to the end undisturbed. Then each trial runs the workflow
from scratch in its own folder, as its own process group, and at a random moment within the
reference's wall time sends a signal to the whole group: SIGKILL (a crash, an out-of-memory
kill), SIGINT (Ctrl-C) or SIGTERM (a scheduler's cancel). It waits until no live process of
the group is left: SIGINT and SIGTERM must stop the run within ``stop_limit`` seconds. Then
``snakemake --unlock`` and a re-run to the end, and the sha256 of every map (COG) and web
tile is compared with the reference's: a resumed run must be byte-identical.

CLI::

    python -m pipeline25d_lab.harness.killtest [--trials 20] [--signals KILL,INT,TERM] [--scale 0.5] [--seed 1]

writes ``bench/<name>.json`` and exits 1 when a trial failed.
"""

from __future__ import annotations

import argparse
import hashlib
import json
import logging
import os
import random
import shutil
import signal
import subprocess
import sys
import time
from pathlib import Path

import yaml

from pipeline25d.core.atomic import write_json, write_text
from pipeline25d.core.errors import WorkflowRunError
from pipeline25d_lab.harness.bench import REPO, results_of, run_workflow, workflow_command

log = logging.getLogger(__name__)

SIGNALS = {"KILL": signal.SIGKILL, "INT": signal.SIGINT, "TERM": signal.SIGTERM}
STOP_LIMIT_S = 10.0


def output_digests(results: Path) -> dict[str, str]:
    """sha256 of every map (maps/*.tif) and web tile (tms/**) of a results folder, by relative path."""
    return file_digests(results, "maps/*.tif", "tms/**/*")


def file_digests(folder: Path, *patterns: str) -> dict[str, str]:
    """sha256 of the files under ``folder`` matching ``patterns``, by relative path; hidden
    names (a job's temporaries, see :mod:`pipeline25d.core.atomic`) are not outputs."""
    files = sorted(p for pattern in patterns for p in folder.glob(pattern) if p.is_file())
    return {str(p.relative_to(folder)): hashlib.sha256(p.read_bytes()).hexdigest() for p in files
            if not _hidden(p.relative_to(folder))}


def temporaries(results: Path) -> list[str]:
    """Hidden files and folders anywhere in a results folder (Snakemake's own
    ``.snakemake_timestamp`` markers aside): what an interrupted job left."""
    return sorted(str(p.relative_to(results)) for p in results.rglob(".*")
                  if p.name != ".snakemake_timestamp" and not _hidden(p.parent.relative_to(results)))


def _hidden(rel: Path) -> bool:
    return any(part.startswith(".") for part in rel.parts)


def differences(got: dict[str, str], want: dict[str, str]) -> list[str]:
    """The paths missing, extra or different in ``got`` against ``want``."""
    return sorted(k for k in want.keys() | got.keys() if got.get(k) != want.get(k))


def live_members(pgid: int) -> list[int]:
    """Pids of the live (not zombie) processes of process group ``pgid``, read from /proc."""
    pids = []
    for stat in Path("/proc").glob("[0-9]*/stat"):
        try:
            text = stat.read_text()
        except OSError:                    # the process ended while we looked
            continue
        fields = text[text.rindex(")") + 2:].split()       # after "pid (comm) "
        if fields[0] != "Z" and int(fields[2]) == pgid:
            pids.append(int(stat.parent.name))
    return pids


def _default_signals() -> None:
    """In the child before exec: SIGINT and SIGTERM as a terminal would deliver them (a shell
    starts background commands with SIGINT ignored, and an ignored signal stays ignored across exec)."""
    for sig in (signal.SIGINT, signal.SIGTERM):
        signal.signal(sig, signal.SIG_DFL)


def interrupt(workdir: Path, cores: int, sig: signal.Signals, at_s: float, stop_limit: float) -> dict:
    """Start the workflow in ``workdir`` as a new process group, send ``sig`` to the group after
    ``at_s`` seconds and wait for it to stop; SIGKILL it after ``stop_limit`` s if it has not."""
    with open(workdir / "interrupted.log", "w") as out:
        proc = subprocess.Popen(workflow_command(workdir, cores), stdout=out, stderr=subprocess.STDOUT,
                                start_new_session=True, preexec_fn=_default_signals)
        try:
            proc.wait(timeout=at_s)
            return {"finished_before_signal": True, "rc": proc.returncode}
        except subprocess.TimeoutExpired:
            pass
        os.killpg(proc.pid, sig)
        sent = time.monotonic()
        while live_members(proc.pid) and time.monotonic() - sent < stop_limit:
            proc.poll()
            time.sleep(0.05)
        stop_s = time.monotonic() - sent
        left = [_cmdline(pid) for pid in live_members(proc.pid)]
        if left:
            os.killpg(proc.pid, signal.SIGKILL)
        proc.wait()
    return {"finished_before_signal": False, "stop_s": round(stop_s, 2), "stopped": not left,
            **({"left_running": left} if left else {})}


def _cmdline(pid: int) -> str:
    try:
        return Path(f"/proc/{pid}/cmdline").read_bytes().replace(b"\0", b" ").decode(errors="replace")[:160]
    except OSError:
        return f"{pid} (gone)"


def trial(workdir: Path, config: dict, sig_name: str, at_s: float, reference: dict[str, str], cores: int = 2,
          stop_limit: float = STOP_LIMIT_S) -> dict:
    """One trial (see the module doc): interrupt, unlock, resume, compare. Returns its record."""
    shutil.rmtree(workdir, ignore_errors=True)
    workdir.mkdir(parents=True)
    write_text(workdir / "config.yaml", yaml.safe_dump(config))
    record = {"signal": sig_name, "at_s": round(at_s, 2),
              **interrupt(workdir, cores, SIGNALS[sig_name], at_s, stop_limit)}
    locks = workdir / ".snakemake" / "locks"
    record["left_locked"] = locks.is_dir() and any(locks.iterdir())       # SIGKILL leaves the lock behind
    unlock = subprocess.run(workflow_command(workdir, cores) + ["--unlock"], capture_output=True, text=True)
    resumed = subprocess.run(workflow_command(workdir, cores), capture_output=True, text=True)
    write_text(workdir / "resumed.log", unlock.stdout + unlock.stderr + resumed.stdout + resumed.stderr)
    differ = differences(output_digests(results_of(workdir, config)), reference)
    record["temporaries_left"] = temporaries(results_of(workdir, config))
    record.update({"unlock_rc": unlock.returncode, "resume_rc": resumed.returncode,
                   "identical": resumed.returncode == 0 and not differ, "differing": differ[:20]})
    if not record["identical"]:            # what a failure needs to be read where only its message is kept (CI)
        record.update(what_ran(workdir))
    record["ok"] = record["identical"] and (sig_name == "KILL" or record.get("stopped", True))
    return record


def what_ran(workdir: Path) -> dict:
    """The jobs the interrupted run started and the resumed run ran (by their log lines), and the
    interrupted run's last lines: which job a signal stopped, for a trial that did not resume identical."""
    def jobs(log: Path) -> list[str]:
        found: list[str] = []
        for line in (log.read_text(errors="replace") if log.exists() else "").splitlines():
            if line.startswith(("rule ", "localrule ", "checkpoint ", "localcheckpoint ")):
                found.append(line.split()[-1].rstrip(":"))
            elif line.strip().startswith("wildcards:") and found:
                found[-1] += f" ({line.strip().removeprefix('wildcards:').strip()})"
        return found

    interrupted = workdir / "interrupted.log"
    tail = interrupted.read_text(errors="replace").splitlines()[-12:] if interrupted.exists() else []
    return {"interrupted_jobs": jobs(interrupted), "resumed_jobs": jobs(workdir / "resumed.log"),
            "interrupted_tail": tail}


def demo_config(scene_dir: Path, scale: float, perspectives: str | list[dict]) -> dict:
    """The repository's demo configuration on a demo city of ``scale`` (the sweep's) under ``scene_dir``."""
    from pipeline25d_lab.harness.sweep import generated_city

    manifest, where = generated_city("demo", scale, scene_dir)
    config = yaml.safe_load((REPO / "config" / "config.yaml").read_text())
    viewer = config.get("viewer") or {}
    overlays = [{**o, "path": str(where / manifest["streets"])} for o in viewer.get("overlays") or []]
    config.update({"scene": "killtest", "perspectives": perspectives, "terrain": str(where / manifest["dtm"]),
                   "inputs": {k: {"path": str(where / v)} for k, v in manifest["districts"].items()},
                   "viewer": {**viewer, "overlays": overlays}})      # the demo's streets, written beside it
    return config


def run_trials(work: Path, config: dict, trials: int, signals: list[str], seed: int, cores: int = 2,
               stop_limit: float = STOP_LIMIT_S) -> dict:
    """The reference run, then ``trials`` trials cycling through ``signals``, each at a random
    moment (seeded) between 2 % and 80 % of the reference's wall time (a trial on a machine less loaded than
    the reference's ran out before a later signal)."""
    ref_dir = work / "reference"
    wall = run_workflow(ref_dir, config, cores)
    reference = output_digests(results_of(ref_dir, config))
    log.info("killtest: reference run %.1f s, %d maps and web tiles", wall, len(reference))
    rng = random.Random(seed)
    records = []
    for k in range(trials):
        sig_name = signals[k % len(signals)]
        at_s = rng.uniform(0.02, 0.8) * wall
        rec = trial(work / f"trial{k:02d}", config, sig_name, at_s, reference, cores, stop_limit)
        log.info("killtest %d/%d: SIG%s at %.1f s: %s", k + 1, trials, sig_name, at_s,
                 "ok" if rec["ok"] else f"FAILED {rec}")
        records.append(rec)
    summary = {}
    for name in signals:
        mine = [r for r in records if r["signal"] == name]
        stops = [r["stop_s"] for r in mine if "stop_s" in r]
        summary[name] = {"trials": len(mine), "identical": sum(r["identical"] for r in mine),
                         "ok": sum(r["ok"] for r in mine), "max_stop_s": max(stops, default=None)}
    return {"reference_wall_s": round(wall, 1), "files_compared": len(reference), "stop_limit_s": stop_limit,
            "summary": summary, "trials": records}


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(prog="python -m pipeline25d_lab.harness.killtest",
                                 description=__doc__.split("\n\n")[0])
    ap.add_argument("--trials", type=int, default=20)
    ap.add_argument("--signals", default="KILL,INT,TERM", help="cycled through the trials: KILL, INT, TERM")
    ap.add_argument("--scale", type=float, default=0.5, help="demo city scale (1 = the make run demo)")
    ap.add_argument("--perspectives", default="eight-45+nadir")
    ap.add_argument("--seed", type=int, default=1)
    ap.add_argument("--cores", type=int, default=2)
    ap.add_argument("--name", default="killtest")
    args = ap.parse_args(argv)
    logging.basicConfig(level=logging.INFO, format="%(asctime)s %(message)s", datefmt="%H:%M:%S")
    signals = [s.strip().upper().removeprefix("SIG") for s in args.signals.split(",")]
    if unknown := [s for s in signals if s not in SIGNALS]:
        raise SystemExit(f"killtest: unknown signal(s) {', '.join(unknown)} (KILL, INT, TERM)")
    work = REPO / "bench" / args.name
    config = demo_config(work / "scene", args.scale, args.perspectives)
    try:
        result = run_trials(work, config, args.trials, signals, args.seed, args.cores)
    except WorkflowRunError as exc:
        raise SystemExit(f"killtest: the reference run failed: {exc}") from None
    write_json(REPO / "bench" / f"{args.name}.json", result)
    print(json.dumps(result["summary"]))
    return 0 if all(r["ok"] for r in result["trials"]) else 1


if __name__ == "__main__":
    sys.exit(main())
