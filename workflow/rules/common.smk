# Config validation (before any job), constants, wildcard constraints and input functions.
# Everything at parse time runs under parse_guard: a Pipeline25dError (a schema violation, a missing
# or unreadable input, DTM or GCP file, an estimate beyond a limit, an unreadable plan) prints
# "pipeline25d: error: <file or key>: <problem>" and exits 1 without a traceback, as a job's does.

import shlex
import sys
from functools import wraps
from pathlib import Path

from snakemake.io import apply_wildcards

from pipeline25d import jobhost, jobspec
from pipeline25d.config import (check_semantics, chunk_size, objects_enabled, perspectives, render_settings,
                                validate_schema)
from pipeline25d.analysis.height_sources import plan as heights_plan
from pipeline25d.core.logsetup import stop_on_error
from pipeline25d.core.snakemake_wakeups import one_pending_wakeup
from pipeline25d.geometry.perspectives import ID_PATTERN
from pipeline25d.stages import budget
from pipeline25d.stages.objects import district_slots
from pipeline25d.stages.extent import cheap_extent
from pipeline25d.stages.plan import block_spec_hash, plan_block, read_plan, read_plan_blocks

# the scheduler's wake-ups: one pending at a time, not one chain per job event (core.snakemake_wakeups)
one_pending_wakeup()


def parse_guard(func):
    """``func`` (an input function) ending the run with its Pipeline25dError's message, no traceback."""

    @wraps(func)
    def guarded(*args, **kwargs):
        with stop_on_error(log=False):
            return func(*args, **kwargs)

    return guarded


with stop_on_error(log=False):
    validate_schema(config, Path(workflow.basedir) / "config" / "schema.yaml")
    check_semantics(config)
    RESULTS = f"results/{config['scene']}"
    DISTRICTS = sorted(config["inputs"])
    OBJECT_SLOTS = district_slots(DISTRICTS)       # each district's object ids (stages.objects)
    PERSPECTIVE_IDS = [p.id for p in perspectives(config)]
    # which object each map pixel shows: id tiles beside the render tiles, an id map beside each map
    OBJECTS = objects_enabled(config)             # auto: where an input names objects (formats.has_objects)
    ID_MOSAIC = f"{RESULTS}/mosaic/{{pid}}.ids.vrt"
    ID_MAP = f"{RESULTS}/maps/{{pid}}.ids.tif"
    # the map's digests as its warp job made them, which its web-tile cut reads instead of the map
    MAP_CELLS_NOTE = f"{RESULTS}/work/warp/{{pid}}/map_cells.json"
    ID_MAPS = expand(ID_MAP, pid=PERSPECTIVE_IDS) if OBJECTS else []
    ID_STAT = f"{RESULTS}/work/ids/{{pid}}.json"
    ID_STATS = expand(ID_STAT, pid=PERSPECTIVE_IDS) if OBJECTS else []
    # the web-tile pyramids as PMTiles archives too (tms.pmtiles), read by the viewer
    PMTILES = [f"{RESULTS}/pmtiles/{pid}.pmtiles" for pid in PERSPECTIVE_IDS] if config["tms"]["pmtiles"] else []
    MAX_LOD_ERROR = config["gsd"] * config["lod"]["max_error_px"]
    TERRAIN_FILE = [] if config["terrain"] in ("auto", "flat") else [config["terrain"]]
    GCP_FILE = [] if config["gcp"]["source"] == "auto" else [config["gcp"]["source"]]
    RENDER_BLOCK = config["render"]["block"]
    HEIGHTS_PLAN = heights_plan(config)
    # what changes a tile's pixels (the block size does not; shadows only when enabled)
    RENDER_SETTINGS = render_settings(config)
    # the work the config asks for, refused beyond config["limits"] before anything is made in
    # proportion to it: here where the inputs' extent is cheap to know, else in the terrain job
    WORK = budget.settings(config)
    EXTENT = cheap_extent(config, RESULTS)
    if EXTENT is not None:
        budget.check(WORK, budget.estimate(WORK, *EXTENT))


# Every rule's command: a stdlib-only process (pipeline25d.jobhost run as a script, no Snakemake
# to import) that hands the job to the run's job host, or runs python -m pipeline25d.jobs itself.
# Its job is the rule's `job` parameter (job() below): the file that describes the job's named
# files, parameters and wildcards (pipeline25d.jobspec), kept beside Snakemake's own records of
# the run, not among its results (and not made in a dry run).
JOB_SPECS = ".snakemake/pipeline25d/jobs"
JOB = (f"{shlex.quote(sys.executable)} -I -S {shlex.quote(jobhost.__file__)} job "
       "{rule} {threads} {params.job:q} {log:q}")


def job(described=None, **params):
    """A rule's parameters (``**``-added to its own), with ``job``: a function that writes the job's
    description file (pipeline25d.jobspec) and is its path. The parameters themselves stay the
    rule's, for Snakemake to re-run a job whose parameters changed (it leaves out a parameter that
    takes the job's files, as ``job`` does); in the description they are as Snakemake gives them:
    a function called with the wildcards, a string with the wildcards filled in. ``described``:
    parameters of the description alone, which do not re-run the job when they change (what a job
    only checks, such as the work a config asks for)."""

    def describe(wildcards, input, output):
        with stop_on_error(log=False):
            values = {name: value(wildcards) if callable(value)
                      else apply_wildcards(value, wildcards) if isinstance(value, str) else value
                      for name, value in params.items()}
            values.update(described or {})
            return jobspec.write(JOB_SPECS, jobspec.encode(input, output, values, dict(wildcards.items())),
                                 make=not workflow.dryrun)

    return {**params, "job": describe}


def with_ids(**files):
    """A rule's named inputs, outputs or params of the id layer: the map's own jobs (warp, tms)
    make the ids beside the map in the same job (one start-up, not two more jobs per view), so
    these are ``**``-added to them, and are none without objects.enabled."""
    return files if OBJECTS else {}


wildcard_constraints:
    pid=ID_PATTERN,
    block=r"\d+_-?\d+_-?\d+(_[0-3]+)?",
    district=r"[A-Za-z0-9-]+",
    hblock=r"(L\d+_)?-?\d+_-?\d+",


def district_inputs(wildcards):
    spec = config["inputs"][wildcards.district]
    return [spec[k] for k in ("path", "metadata") if k in spec]


def all_lod_meta(wildcards):
    """The per-district LOD indexes (each lists its chunks' LOD files, see stages.lod_chunks)."""
    return expand(rules.ingest.output.lod, district=DISTRICTS)


@parse_guard
def plan_path(pid):
    """The perspective's plan file (an output of the plan checkpoint: the DAG waits for it)."""
    checkpoints.plan.get()
    return f"{RESULTS}/plans/{pid}.json"


@parse_guard
def block_tiles(wildcards):
    """The tiles (pipeline25d.stages.records.Tile) of a render block."""
    return plan_block(read_plan_blocks(plan_path(wildcards.pid), RENDER_BLOCK), wildcards.block, wildcards.pid)


@parse_guard
def block_lods(wildcards):
    """The LOD indexes of the districts whose chunks a block's tiles draw or take shadows from.

    ancient(): a district's index is rewritten whenever any of its chunks is, so its time must not
    re-run the block; the block's spec hash (a param, with each chunk's LOD content hash) re-runs it
    when a chunk it draws changed. One file per district, not one per chunk: Snakemake stats every
    input of every ready job on each scheduling pass (hundreds of chunks per block in a city).
    """
    districts = {c.district for t in block_tiles(wildcards) for c in (*t.chunks, *t.casters)}
    return [ancient(f"{RESULTS}/lod/{d}/index.json") for d in sorted(districts)]


@parse_guard
def block_hash(wildcards):
    return block_spec_hash(block_tiles(wildcards))


@parse_guard
def perspective_blocks(wildcards):
    """The render-block manifests of a perspective."""
    blocks = read_plan_blocks(plan_path(wildcards.pid), RENDER_BLOCK)
    return [f"{RESULTS}/tiles/{wildcards.pid}/block_{b}.json" for b in sorted(blocks)]


@parse_guard
def perspective_tiles(wildcards, suffix):
    plan = read_plan(plan_path(wildcards.pid))
    return [f"{RESULTS}/tiles/{wildcards.pid}/{t.key}{suffix}" for t in plan.tiles]


@parse_guard
def heights_block_files(wildcards):
    """The heights_block jobs' summaries, one per job of blocks of the heights_blocks checkpoint (none when skipped)."""
    if HEIGHTS_PLAN["skip"]:
        return []
    from pipeline25d.analysis.height_blocks import read_blocks

    _, _, jobs = read_blocks(checkpoints.heights_blocks.get().output.blocks)
    return [f"{RESULTS}/work/heights/block_{j}.json" for j in jobs]


# A warm host for the jobs of a run with enough of them on this machine (pipeline25d.jobhost):
# started once the run knows its jobs, stopped (and waited for) when it ends.
JOB_HOST = []


onstart:
    with stop_on_error(log=False):
        if jobhost.wanted(len(workflow.dag), workflow.local_exec):
            JOB_HOST.append(jobhost.start())


onsuccess:
    jobhost.stop(JOB_HOST.pop() if JOB_HOST else None)
    jobspec.prune(JOB_SPECS)


onerror:
    jobhost.stop(JOB_HOST.pop() if JOB_HOST else None)
