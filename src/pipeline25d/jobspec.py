"""A job as its rule's shell command hands it on: named files, parameters and wildcards in a JSON file.

Every rule's command (``JOB`` in workflow/rules/common.smk) is ``python -I -S jobhost.py job RULE THREADS
SPEC LOG``: a stdlib-only process that hands the job to the run's host, or runs ``python -m
pipeline25d.jobs`` itself (:mod:`pipeline25d.jobhost`). It does not import Snakemake, which a
``script:`` job's preamble does (0.12 of its 0.15 CPU-s before any work). SPEC is the file
:func:`write` made while Snakemake built the job (the rule's ``job`` parameter): the rule's named
inputs, outputs, parameters and wildcards, named by a digest of what it holds, so that it never
changes once written (a job reads what it was built with, whatever another run writes). A file
rather than the command line: a city's lists of files outgrow a command's 128 KB.

:func:`load` gives the job back as a :class:`JobSpec`, which :mod:`pipeline25d.jobs` reads as it
read Snakemake's own job object (``job.input.cog``, ``job.output[0]``, ``job.params.gsd``).
"""

from __future__ import annotations

import hashlib
import json
import os
from collections.abc import Iterable
from dataclasses import dataclass
from pathlib import Path
from types import SimpleNamespace
from typing import Any

from pipeline25d.core.errors import Pipeline25dError


class Files(list):
    """A rule's inputs or outputs: the files in order, and the named ones as attributes (a file, or
    a list of files where the rule named a list), which hide a list method of the same name
    (``output.index``) as they do on Snakemake's own."""

    def __init__(self, files: Iterable[str], named: dict[str, Any]):
        super().__init__(files)
        self.__dict__.update(named)


@dataclass(frozen=True)
class JobSpec:
    """One job of a rule: what its function in :mod:`pipeline25d.jobs` reads."""

    rule: str
    input: Files
    output: Files
    params: SimpleNamespace
    wildcards: SimpleNamespace
    threads: int
    log: list[str]


def encode(input: Any, output: Any, params: dict[str, Any], wildcards: dict[str, str]) -> str:
    """The JSON of a job's files, parameters and wildcards; ``input`` and ``output`` are Snakemake's
    (lists whose ``items()`` are their named entries)."""

    def files(named_list: Any) -> dict:
        named = {k: (str(v) if isinstance(v, str) else [str(f) for f in v]) for k, v in named_list.items()}
        return {"files": [str(f) for f in named_list], "named": named}

    return json.dumps({"input": files(input), "output": files(output), "params": params,
                       "wildcards": dict(wildcards)}, separators=(",", ":"))


#: a job description no run has used for this long is removed as a run ends (:func:`prune`)
KEEP_UNUSED_S = 7 * 24 * 3600


def write(folder: str | Path, text: str, make: bool = True) -> str:
    """The path of a file in ``folder`` holding ``text``, named by its digest: made now (where
    ``make``) unless a run made it before, whose file is then marked used now."""
    from pipeline25d.core.atomic import write_text

    path = Path(folder) / f"{hashlib.sha256(text.encode()).hexdigest()[:32]}.json"
    if make:
        try:
            os.utime(path)
        except FileNotFoundError:
            path.parent.mkdir(parents=True, exist_ok=True)
            write_text(path, text)
    return str(path)


def prune(folder: str | Path, unused_s: float = KEEP_UNUSED_S) -> int:
    """Remove the job descriptions in ``folder`` that no run has used for ``unused_s`` seconds (each
    job's is marked used as its run builds it); how many. A run still going has marked its own."""
    import time

    removed = 0
    for path in Path(folder).glob("*.json"):
        try:
            if time.time() - path.stat().st_mtime > unused_s:
                path.unlink()
                removed += 1
        except FileNotFoundError:                    # another run's prune took it first
            pass
    return removed


def load(rule: str, threads: str | int, spec: str | Path, log: str) -> JobSpec:
    """The job of ``rule`` described by the file ``spec`` (:func:`write`), on ``threads`` threads,
    logging to ``log``."""
    try:
        data = json.loads(Path(spec).read_text())
    except (OSError, ValueError) as exc:
        raise Pipeline25dError(f"{spec}: the job's description cannot be read ({exc}); run the workflow "
                               "again, which writes it anew") from None
    return JobSpec(rule=rule, input=Files(**data["input"]), output=Files(**data["output"]),
                   params=SimpleNamespace(**data["params"]), wildcards=SimpleNamespace(**data["wildcards"]),
                   threads=int(threads), log=[log] if log else [])
