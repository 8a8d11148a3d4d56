"""The one seam between the Snakemake rules and the stages: one function per rule.

Every rule's command (``JOB`` in workflow/rules/common.smk) hands its job, a
:class:`~pipeline25d.jobspec.JobSpec`, to :func:`run`: in a fork of the run's job host
(:mod:`pipeline25d.jobhost`) or as ``python -m pipeline25d.jobs RULE THREADS SPEC LOG``. ``run``
logs the job to its rule's log file, makes it stop cleanly on SIGTERM and on a
:class:`~pipeline25d.core.errors.Pipeline25dError` (its message, no traceback), calls the rule's
function here and logs what the job read and its peak memory
(:func:`~pipeline25d.core.logsetup.log_job_resources`). Each function only unpacks the rule's
named inputs, outputs and parameters and calls its stage; the work itself lives in the stage
modules. A function imports its stage when it runs, so a job pays only for the modules it uses.
"""

from __future__ import annotations

import logging
import os
import time
from collections.abc import Callable
from typing import Any

from pipeline25d.core import cores
from pipeline25d.core.cores import allowed_cores, job_workers
from pipeline25d.core.logsetup import log_job_resources, log_to, process_age, stop_on_error
from pipeline25d.core.stopping import end_if_stopped
from pipeline25d.jobhost import HOSTED_ENV

log = logging.getLogger(__name__)

#: a job (:class:`~pipeline25d.jobspec.JobSpec`, or anything with its attributes): input, output,
#: params, wildcards, threads, log, rule; input and output with named and positional access.
Job = Any


def _first(files) -> str | None:
    """The one file of an optional input or output (an empty list when the config has none)."""
    return files[0] if files else None


def ingest_job(job: Job) -> None:
    """A district's chunks, then their LOD pyramids: one job (see workflow/rules/ingest.smk)."""
    from pipeline25d.stages import ingest, lod

    p = job.params
    started = time.perf_counter()
    ingest.ingest(dict(p.spec), job.wildcards.district, p.crs, p.chunk_size, p.max_error, job.output.index,
                  gsd=p.gsd, slot=p.slot)
    chunked = time.perf_counter()
    lod.build_lod(job.output.index, job.output.lod, p.max_error, p.max_levels,
                  processes=lambda: job_workers(job.threads))
    log.info("chunks in %.2f s, their LOD pyramids in %.2f s", chunked - started, time.perf_counter() - chunked)


def terrain_job(job: Job) -> None:
    from pipeline25d.stages.budget import check_ingested
    from pipeline25d.stages.lod import lod_chunks
    from pipeline25d.stages.terrain.build import build_terrain

    p = job.params
    chunks = lod_chunks(list(job.input.lods))
    log.info("work asked for: %s", check_ingested(dict(p.work), chunks).summary())
    build_terrain(chunks, dict(p.inputs), p.crs, p.gsd, p.terrain, dict(p.ground), job.output.dsm,
                  _first(job.output.ground), job.output.meta, processes=job.threads)


def scene_job(job: Job) -> None:
    from pipeline25d.stages import scene

    p = job.params
    scene.scene_setup(list(job.input.lods), job.input.dsm, p.terrain, _first(job.input.terrain), p.z0, p.projection,
                      dict(p.gcp), p.crs, p.gsd, list(p.perspectives), job.output.scene, job.output.candidates,
                      _first(job.output.dtm), p.ground["max_object_size"], job.output.grounds, processes=job.threads,
                      out_holdout=_first(job.output.holdout))


def plan_job(job: Job) -> None:
    from pipeline25d.stages import plan

    p = job.params
    plan.plans(dict(zip(p.perspectives, job.output.plans)), list(job.input.lods), job.input.scene,
               job.input.candidates, p.gsd, p.tile_size, p.max_error_px, p.crs, dict(p.render), work=dict(p.work),
               grounds_json=job.input.grounds)


def render_block_job(job: Job) -> None:
    from pipeline25d.stages import render_block

    p = job.params
    render_block.render_block(p.plan, job.wildcards.block, p.block, p.lod_dir, p.tiles_dir, job.output[0],
                              objects=p.objects, workers=job_workers(job.threads))


def warp_job(job: Job) -> None:
    from pipeline25d.stages import gcps
    from pipeline25d.stages.maps import mosaic_sources, warp

    p, o = job.params, job.output
    mosaic_sources.build_mosaic(sorted(p.tiles), o.mosaic)
    gcps.gather_gcps(list(p.gcp_tiles), o.gcps)
    threads = job.threads                            # each COG encode adds the cores idle when it runs
    cells: dict = {}                                 # the mosaic's digests, made once for both maps
    warp.warp(o.mosaic, o.gcps, job.input.plan, dict(p.warp), o.cog, o.meta, dict(p.maps), work_dir=p.work,
              threads=threads, cells_memo=cells, cells_note=p.cells_note)
    if hasattr(o, "ids"):                            # objects.enabled: the tiles' object ids, by the warp just chosen
        from pipeline25d.stages.maps.ids import id_map

        mosaic_sources.build_mosaic(sorted(p.id_tiles), o.id_mosaic)
        id_map(o.id_mosaic, o.mosaic, o.gcps, o.meta, o.cog, o.ids, o.id_stats, work_dir=p.id_work,
               threads=threads, cells_memo=cells)


def tms_job(job: Job) -> None:
    from pipeline25d.core.atomic import write_json
    from pipeline25d.stages.tiles.web import tms

    p, o = job.params, job.output
    processes = job_workers(job.threads)             # the cut on the cores idle now too,
    most = allowed_cores()                           # and on those that fall idle while it runs
    stats = tms(job.input.cog, p.zoom, o.tiles, processes=processes, tile_format=p.tile_format,
                quality=p.quality, work_dir=p.work, most=most, webp_method=p.webp_method, cells_note=p.cells_note)
    write_json(o.stats, stats)
    if hasattr(o, "id_tiles"):                       # objects.enabled: the id map's tiles, same positions
        stats = tms(job.input.ids, p.zoom, o.id_tiles, processes=processes, tile_format="ids", quality=0,
                    work_dir=p.id_work, most=most)
        write_json(o.id_stats, stats)


def pmtiles_job(job: Job) -> None:
    from pipeline25d.stages.tiles.archive import write_pmtiles

    write_pmtiles(job.input.tiles, job.output[0], name=job.wildcards.pid)


def objects_job(job: Job) -> None:
    from pathlib import Path

    from pipeline25d.analysis.height_sources import cityjson_inputs
    from pipeline25d.core.crs import horizontal_wkt
    from pipeline25d.publish.objects import scene_objects, write_objects

    config = dict(job.params.config)
    cityjson = {d: config["inputs"][d]["path"] for d in cityjson_inputs(config)}
    rows = scene_objects(Path(job.input.chunks[0]).parents[1], list(job.params.districts), cityjson, job.input.heights)
    write_objects(rows, Path(job.output.gpkg).parent, horizontal_wkt(config["crs"]))


def heights_blocks_job(job: Job) -> None:
    from pipeline25d.analysis.height_blocks import write_blocks

    write_blocks(dict(job.params.config), _first(job.input.nadir), job.output.blocks)


def heights_block_job(job: Job) -> None:
    from pipeline25d.analysis.height_blocks import measure_job

    measure_job(dict(job.params.config), dict(zip(job.params.pids, job.input.maps)), job.input.scene,
                  job.input.blocks, job.wildcards.hblock, job.params.rows_dir, job.output[0])


def heights_job(job: Job) -> None:
    from pipeline25d.analysis.height_blocks import merge_blocks

    merge_blocks(dict(job.params.config), dict(zip(job.params.pids, job.input.maps)), job.input.scene,
                 job.input.dsm, _first(job.input.blocks), list(job.input.block_jobs), job.params.rows_dir,
                 job.output.csv, job.output.json)


def report_figures_job(job: Job) -> None:
    from pipeline25d.publish.report_html import write_figures

    # beside the last web-tile cuts: its maps on the cores idle too
    p = job.params
    write_figures(list(p.perspectives), p.gsd, p.results, job.output[0], processes=job_workers(job.threads))


def report_job(job: Job) -> None:
    from pipeline25d.publish.report import write_report
    from pipeline25d.publish.report_html import write_html

    rep = write_report(dict(job.params.config), job.params.results, job.output.json, job.output.md)
    write_html(rep, job.params.results, job.input.figures, job.output.html)


def viewer_job(job: Job) -> None:
    from pipeline25d.publish.viewer import write_viewer

    write_viewer(job.input.report, job.output[0], archives=job.input.pmtiles, overlays=job.params.viewer["overlays"],
                 basemap=job.params.viewer.get("basemap"),
                 ids=job.params.results if job.input.ids else None)


def wms_job(job: Job) -> None:
    from pipeline25d.publish.wms import write_mapfile

    objects = [f for f in job.input.ids if str(f).endswith(".csv")]
    write_mapfile(job.params.scene, list(job.input.maps), job.output.mapfile, objects=_first(objects),
                  threads=job_workers(job.threads))      # the id layers on the cores idle now too


#: rule name -> its function, in the order data moves through the workflow
RULES: dict[str, Callable[[Job], None]] = {
    "ingest": ingest_job, "terrain": terrain_job, "scene": scene_job, "plan": plan_job,
    "render_block": render_block_job, "warp": warp_job, "tms": tms_job, "pmtiles": pmtiles_job,
    "objects": objects_job, "heights_blocks": heights_blocks_job, "heights_block": heights_block_job,
    "heights": heights_job, "report_figures": report_figures_job, "report": report_job, "viewer": viewer_job,
    "wms": wms_job,
}


def run_args(args: list[str]) -> None:
    """Run the job that a rule's command names: ``[RULE, THREADS, SPEC, LOG]`` (:func:`pipeline25d.jobspec.load`)."""
    from pipeline25d.jobspec import load

    with stop_on_error(log=False):
        job = load(*args)
    run(job)


def run(job: Job) -> None:
    """Run the rule's function of a job, logged to its log file with its resources
    and times (start-up before the function, the function, CPU)."""
    startup, t0 = process_age(), time.monotonic()
    hosted = bool(os.environ.get(HOSTED_ENV))
    if not hosted:                    # (the host's fork was marked as it was forked)
        cores.mark()                  # the idle cores a step asks for are read over the time since
    log_to(job.log[0])
    if hosted:
        log.info("run by a fork of the run's job host (its modules imported once per run)")
    with stop_on_error():
        RULES[job.rule](job)
    end_if_stopped()                  # stopped, though some code dropped the signal's exception: failed
    log_job_resources(startup, time.monotonic() - t0)


if __name__ == "__main__":
    import sys

    from pipeline25d.jobhost import end_now

    run_args(sys.argv[1:])
    if sys.getprofile() is None:      # done: no teardown of every module (python -m cProfile: its figures first)
        end_now(0)
