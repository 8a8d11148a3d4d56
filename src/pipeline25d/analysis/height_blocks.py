"""The heights stage as parallel jobs: footprints in blocks, sparse blocks grouped into jobs, the rows merged.

* :func:`write_blocks` (the ``heights_blocks`` checkpoint): the footprints on the maps, their
  blocks (``heights.block_size`` m cells, :mod:`.heights.blocks`) and the jobs that measure them
  (a dense block alone, sparse neighbours together: :func:`.heights.blocks.jobs_of`),
  ``work/heights/blocks.json``.
* :func:`measure_job` (``heights_block``, one job per job of blocks): each block's footprints
  measured on every view, the other footprints near them as the silhouette's neighbours, so each
  row is the one a single job gives. A block's rows are kept in ``work/heights/rows/<block>.json``
  with a digest of everything they were measured from (:func:`.heights.blocks.reads_digest`); a
  block whose digest is unchanged (a district update elsewhere, a map rewritten with the same
  pixels here) keeps them.
* :func:`merge_blocks` (``heights``): the rows in footprint order, then the comparison and the
  outputs of :func:`.height_sources.finish_stage`: the same heights.csv and heights.json (but for
  its ``cost``) as :func:`run_stage` in one job.
"""

from __future__ import annotations

import json
import logging
import time
from functools import cache, partial
from pathlib import Path
from typing import Any

from pipeline25d.analysis.ground_under import ground_sampler
from pipeline25d.analysis.height_sources import buildings_on_maps, finish_stage, plan, settings_of, write_skipped
from pipeline25d.analysis.heights.blocks import (
    blocks_of,
    context_of,
    footprint_from_json,
    footprint_to_json,
    jobs_of,
    reads_digest,
    row_from_json,
    row_to_json,
)
from pipeline25d.analysis.heights.results import NADIR_ID, HeightRow
from pipeline25d.core.atomic import write_json
from pipeline25d.core.errors import InputFileError
from pipeline25d.formats.footprints import Footprint
from pipeline25d.stages.records import Scene

log = logging.getLogger(__name__)


def block_size(config: dict) -> float:
    """The side of a heights block in metres (``heights.block_size``; the schema's default where absent)."""
    return float((config.get("heights") or {}).get("block_size", 250.0))


def write_blocks(config: dict, nadir_map: str | Path | None, out_json: str | Path) -> dict[str, list[str]]:
    """The footprints on the maps in blocks and the blocks in jobs (none where the step is skipped),
    written to ``out_json``; returns {job: its blocks}."""
    p = plan(config)
    fps: list[Footprint] = []
    if not p["skip"] and nadir_map:
        _, fps, _ = buildings_on_maps(p, config, nadir_map)
    size = block_size(config)
    blocks = blocks_of(fps, size)
    jobs = jobs_of(blocks)
    write_json(out_json, {"block_size": size, "footprints": [footprint_to_json(f) for f in fps], "blocks": blocks,
                          "jobs": jobs}, indent=None)
    log.info("%d footprints on the maps in %d blocks of %g m, measured by %d jobs", len(fps), len(blocks), size,
             len(jobs))
    return jobs


def read_blocks(path: str | Path) -> tuple[list[Footprint], dict[str, list[int]], dict[str, list[str]]]:
    """The footprints, blocks and jobs of :func:`write_blocks`' file."""
    try:
        d = json.loads(Path(path).read_text(encoding="utf-8"))
        blocks = {k: list(v) for k, v in d["blocks"].items()}
        jobs = d.get("jobs", {b: [b] for b in blocks})      # a file of before the jobs: a job per block
        return [footprint_from_json(f) for f in d["footprints"]], blocks, {k: list(v) for k, v in jobs.items()}
    except (OSError, ValueError, KeyError, TypeError) as exc:
        raise InputFileError(path, f"cannot read the heights blocks: {exc}") from None


def _read_rows(path: Path) -> dict[str, Any] | None:
    try:
        return json.loads(path.read_text(encoding="utf-8"))
    except (OSError, ValueError):
        return None


def measure_job(config: dict, maps: dict[str, str], scene_json: str | Path, blocks_json: str | Path, job: str,
                rows_dir: str | Path, out_json: str | Path) -> dict[str, Any]:
    """Measure the footprints of one job's blocks, block by block (or keep a block's rows where
    nothing they depend on changed); writes each block's rows to ``rows_dir/<block>.json`` and a
    summary of the job to ``out_json``."""
    from pipeline25d.analysis.heights.views import measure_heights

    fps, blocks, jobs = read_blocks(blocks_json)
    if job not in jobs:
        raise InputFileError(blocks_json, f"no heights job {job!r}")
    scene = Scene.read(scene_json)
    s = settings_of(config)
    ground = cache(partial(ground_sampler, scene, config["crs"]))      # one DTM read for all the blocks
    n = measured = 0
    seconds = cpu_seconds = 0.0
    for block in jobs[job]:
        members = [fps[i] for i in blocks[block]]
        context = context_of(members, fps)
        digest = reads_digest(maps, members, context, s, scene.dtm, f"{scene.dtm}|{scene.z0}|{config['crs']}")
        rows_path = Path(rows_dir) / f"{block}.json"
        kept = _read_rows(rows_path)
        if not (kept and kept.get("digest") == digest and "cpu_seconds" in kept
                and len(kept.get("rows", ())) == len(members)):
            t0, c0 = time.perf_counter(), time.process_time()
            rows = measure_heights(maps, members, NADIR_ID, s, context, ground)
            kept = {"digest": digest, "seconds": round(time.perf_counter() - t0, 3),
                    "cpu_seconds": round(time.process_time() - c0, 3), "rows": [row_to_json(r) for r in rows]}
            write_json(rows_path, kept, indent=None)
            measured += 1
        n += len(members)
        seconds += kept["seconds"]
        cpu_seconds += kept["cpu_seconds"]
    summary = {"job": job, "blocks": len(jobs[job]), "n": n, "measured": measured, "seconds": round(seconds, 3),
               "cpu_seconds": round(cpu_seconds, 3)}
    write_json(out_json, summary)
    log.info("job %s: %d footprints in %d blocks, %d measured, %d kept (nothing they were measured from "
             "changed) (%.2f s)", job, n, len(jobs[job]), measured, len(jobs[job]) - measured, seconds)
    return summary


def merge_blocks(config: dict, maps: dict[str, str], scene_json: str | Path, dsm_path: str | Path | None,
                 blocks_json: str | Path | None, block_jsons: list[str], rows_dir: str | Path,
                 out_csv: str | Path, out_json: str | Path) -> dict[str, Any]:
    """The blocks' rows in footprint order, compared and written as :func:`.height_sources.finish_stage` does."""
    p = plan(config)
    if p["skip"]:
        return write_skipped(p["skip"], out_csv, out_json)
    if blocks_json is None:
        raise InputFileError(out_json, "no heights blocks file (the heights_blocks checkpoint's output)")
    fps, blocks, _ = read_blocks(blocks_json)
    rows: list[HeightRow | None] = [None] * len(fps)
    summaries = [json.loads(Path(b).read_text(encoding="utf-8")) for b in block_jsons]
    for name, idx in blocks.items():
        kept = _read_rows(Path(rows_dir) / f"{name}.json")
        if kept is None or len(kept["rows"]) != len(idx):
            raise InputFileError(Path(rows_dir) / f"{name}.json", "missing or incomplete: run its heights_block job")
        for i, r in zip(idx, kept["rows"]):
            rows[i] = row_from_json(r)
    fps_all, on_maps, model = buildings_on_maps(p, config, maps[NADIR_ID])
    if [f.id for f in on_maps] != [f.id for f in fps]:
        raise InputFileError(blocks_json, "the footprints changed since the blocks were made: run again")
    cost = {"jobs": len(summaries), "workers": 1,
            "job_seconds": round(sum(float(s["seconds"]) for s in summaries), 2),
            "job_cpu_seconds": round(sum(float(s["cpu_seconds"]) for s in summaries), 2),
            "blocks": len(blocks), "blocks_measured": sum(int(s["measured"]) for s in summaries),
            "block_size": block_size(config)}
    return finish_stage(config, p, Scene.read(scene_json), [r for r in rows if r is not None],
                        (fps_all, on_maps, model), dsm_path, out_csv, out_json, cost)


def run_stage(config: dict, maps: dict[str, str], scene_json: str | Path, dsm_path: str | Path | None,
              out_csv: str | Path, out_json: str | Path, workers: int = 1) -> dict[str, Any]:
    """The heights step in one job: measure every footprint on the maps (on ``workers`` processes),
    then :func:`.height_sources.finish_stage`: the files the block jobs write, but for "cost"."""
    from pipeline25d.analysis.heights.views import measure_parallel

    p = plan(config)
    if p["skip"]:
        return write_skipped(p["skip"], out_csv, out_json)
    scene = Scene.read(scene_json)
    fps_all, fps, model = buildings_on_maps(p, config, maps[NADIR_ID])
    t0, c0 = time.perf_counter(), time.process_time()
    rows = (measure_parallel(maps, fps, settings=settings_of(config), workers=workers,
                             ground=partial(ground_sampler, scene, config["crs"])) if fps else [])
    seconds = time.perf_counter() - t0
    cost = {"jobs": 1, "workers": workers, "job_seconds": round(seconds * workers, 2)}
    if workers <= 1:
        cost["job_cpu_seconds"] = round(time.process_time() - c0, 2)
    return finish_stage(config, p, scene, rows, (fps_all, fps, model), dsm_path, out_csv, out_json, cost)
