"""``pipeline25d run``: Snakemake on a scene's config, its output condensed to progress lines.

Snakemake stays the engine (``snakemake -j2 --configfile …`` does the same work); this front
door finds the workflow, passes the config and any further Snakemake options, and turns
Snakemake's log into one line per finished job: jobs done of the total known so far, the
stage (rule) that finished, the time spent and an estimate of the time left. The total grows
while the plan checkpoint adds jobs. Snakemake's whole log stays in
``.snakemake/log/``; on a failure its last lines are shown.
"""

from __future__ import annotations

import re
import subprocess
import sys
import time
from collections import deque
from collections.abc import Iterable, Iterator, Sequence
from pathlib import Path

from pipeline25d.core.errors import ConfigError

PROGRESS = re.compile(r"^(\d+) of (\d+) steps \((\d+)%\) done")
RULE = re.compile(r"^(?:local)?(?:rule|checkpoint) (\w+):")
FINISHED = re.compile(r"^Finished job(?:id)?:? (\d+)\.?(?: \(Rule: (\w+)\))?")


def find_workflow(start: Path | None = None) -> Path:
    """The folder holding the workflow's Snakefile: the current folder, else this source checkout's."""
    for root in (start or Path.cwd(), Path(__file__).resolve().parents[2]):
        if (root / "Snakefile").is_file() and (root / "workflow" / "rules").is_dir():
            return root
    raise ConfigError("no pipeline25d workflow here: run `pipeline25d run` in the pipeline25d checkout "
                      "(the folder holding Snakefile and workflow/)")


def _own_directory(extra: Sequence[str]) -> bool:
    """Whether the Snakemake options name their own working directory."""
    return any(a in ("--directory", "-d") or a.startswith("--directory=") for a in extra)


def snakemake_command(config: str | Path, jobs: str, dry_run: bool, extra: Sequence[str], root: Path) -> list[str]:
    """The snakemake command line this run stands for: the working directory is the workflow's
    folder (where ``results/`` goes and relative input paths start) unless ``extra`` names one."""
    config = Path(config)
    if not config.is_file():
        raise ConfigError(f"{config}: no such config file")
    own_directory = _own_directory(extra)
    cmd = [sys.executable, "-m", "snakemake", "--snakefile", str(root / "Snakefile"),
           *([] if own_directory else ["--directory", str(root)]),
           "--configfile", str(config.resolve()), "--cores", str(jobs)]
    return cmd + (["--dry-run"] if dry_run else []) + list(extra)


def work_estimate(config: str | Path, root: Path) -> str | None:
    """The start line's estimate of the work ``config`` asks for (:mod:`pipeline25d.stages.budget`),
    where the scene's extent is cheap to know before ingest; None otherwise, or when the config is
    invalid (Snakemake then stops on it with the message)."""
    from pipeline25d.config import load_config
    from pipeline25d.core.errors import Pipeline25dError
    from pipeline25d.stages import budget
    from pipeline25d.stages.extent import cheap_extent

    try:
        cfg = load_config(config, base_dir=root, schema_path=root / "config" / "schema.yaml")
        work = budget.settings(cfg)
        extent = cheap_extent(cfg, root / "results" / cfg["scene"], base_dir=root)
        return None if extent is None else budget.estimate(work, *extent).summary()
    except Pipeline25dError:
        return None


def _clock(seconds: float) -> str:
    seconds = int(round(seconds))
    return f"{seconds // 3600}:{seconds // 60 % 60:02d}:{seconds % 60:02d}" if seconds >= 3600 else \
        f"{seconds // 60}:{seconds % 60:02d}"


def progress_line(done: int, total: int, rule: str | None, elapsed: float) -> str:
    """``[ 12/387   3%] render_block done · 0:42 elapsed · ~19:30 left`` (no estimate before a job ends)."""
    width = len(str(total))
    left = f" · ~{_clock(elapsed / done * (total - done))} left" if done else ""
    return f"[{done:>{width}}/{total} {100 * done // max(total, 1):>3}%] {rule or 'job'} done · " \
           f"{_clock(elapsed)} elapsed{left}"


def progress_events(lines: Iterable[str]) -> Iterator[tuple[int, int, str | None]]:
    """(jobs done, jobs known, rule of the job that finished) for each progress line of a Snakemake log."""
    rules: dict[str, str] = {}          # job id -> rule, from Snakemake's job blocks
    current_rule, last_rule = None, None
    for line in lines:
        text = line.strip()
        if m := RULE.match(text):
            current_rule = m.group(1)
        elif text.startswith("jobid:") and current_rule:
            rules[text.split(":", 1)[1].strip()] = current_rule
        elif m := FINISHED.match(text):
            last_rule = m.group(2) or rules.get(m.group(1))
        elif m := PROGRESS.match(text):
            yield int(m.group(1)), int(m.group(2)), last_rule


def run_workflow(config: str | Path, jobs: str = "2", dry_run: bool = False, snakemake_args: Sequence[str] = (),
                 stream=sys.stderr) -> int:
    """Run the workflow on ``config``; returns Snakemake's exit status."""
    root = find_workflow()
    cmd = snakemake_command(config, jobs, dry_run, snakemake_args, root)
    if dry_run or any(a in ("--help", "-h", "--unlock", "--summary", "-S", "--list-rules") for a in snakemake_args):
        return subprocess.run(cmd).returncode
    start = time.monotonic()
    tail: deque[str] = deque(maxlen=40)
    estimate = None if _own_directory(snakemake_args) else work_estimate(config, root)
    stream.write(f"pipeline25d: running {config}{f': {estimate}' if estimate else ''} ({' '.join(cmd[2:])})\n")

    def lines(source):
        for line in source:
            tail.append(line.rstrip("\n"))
            yield line

    with subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True, bufsize=1) as proc:
        for done, total, rule in progress_events(lines(proc.stdout)):
            stream.write(progress_line(done, total, rule, time.monotonic() - start) + "\n")
            stream.flush()
        code = proc.wait()
    if code:
        stream.write("pipeline25d: the run failed; Snakemake's last lines (whole log in .snakemake/log/):\n")
        stream.write("\n".join(tail) + "\n")
    else:
        stream.write(f"pipeline25d: done in {_clock(time.monotonic() - start)}\n")
    return code
