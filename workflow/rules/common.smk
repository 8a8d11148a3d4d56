# Config validation (before any job), constants, wildcard constraints and input functions.

from snakemake.exceptions import WorkflowError
from snakemake.utils import validate

from pipeline25d.config import check_semantics, chunk_size, perspectives, render_settings
from pipeline25d.analysis.height_sources import plan as heights_plan
from pipeline25d.core.errors import Pipeline25dError
from pipeline25d.geometry.perspectives import ID_PATTERN
from pipeline25d.stages.plan import block_spec_hash, plan_block, read_plan, read_plan_blocks

validate(config, "../../config/schema.yaml")
try:
    check_semantics(config)
except Pipeline25dError as exc:
    raise WorkflowError(f"invalid configuration: {exc}") from None

RESULTS = f"results/{config['scene']}"
DISTRICTS = sorted(config["inputs"])
PERSPECTIVE_IDS = [p.id for p in perspectives(config)]
# the web-tile pyramids as PMTiles archives too (tms.pmtiles), read by the viewer
PMTILES = [f"{RESULTS}/pmtiles/{pid}.pmtiles" for pid in PERSPECTIVE_IDS] if config["tms"]["pmtiles"] else []
MAX_LOD_ERROR = config["gsd"] * config["lod"]["max_error_px"]
TERRAIN_FILE = [] if config["terrain"] in ("auto", "flat") else [config["terrain"]]
GCP_FILE = [] if config["gcp"]["source"] == "auto" else [config["gcp"]["source"]]
RENDER_BLOCK = config["render"]["block"]
HEIGHTS_PLAN = heights_plan(config)
# what changes a tile's pixels (the block size does not; shadows only when enabled)
RENDER_SETTINGS = render_settings(config)


wildcard_constraints:
    pid=ID_PATTERN,
    block=r"\d+_-?\d+_-?\d+(_[0-3]+)?",
    district=r"[A-Za-z0-9-]+",


def district_inputs(wildcards):
    spec = config["inputs"][wildcards.district]
    return [spec[k] for k in ("path", "metadata") if k in spec]


def all_lod_meta(wildcards):
    """The per-district LOD indexes (each lists its chunks' LOD files, see stages.lod_chunks)."""
    return expand(rules.lod.output.index, district=DISTRICTS)


def plan_path(pid):
    """The perspective's plan file (the plan checkpoint's output: the DAG waits for it)."""
    return checkpoints.plan.get(pid=pid).output.plan


def block_tiles(wildcards):
    """The tiles (pipeline25d.stages.records.Tile) of a render block."""
    return plan_block(read_plan_blocks(plan_path(wildcards.pid), RENDER_BLOCK), wildcards.block, wildcards.pid)


def block_lods(wildcards):
    """The LOD files a block's tiles draw or take shadows from (side files of the lod jobs): a block
    depends on its own chunks and their shadow casters only."""
    chunks = {(c.district, c.id) for t in block_tiles(wildcards) for c in (*t.chunks, *t.casters)}
    return [f"{RESULTS}/lod/{d}/{c}.npz" for d, c in sorted(chunks)]


def block_hash(wildcards):
    return block_spec_hash(block_tiles(wildcards))


def perspective_blocks(wildcards):
    """The render-block manifests of a perspective."""
    blocks = read_plan_blocks(plan_path(wildcards.pid), RENDER_BLOCK)
    return [f"{RESULTS}/tiles/{wildcards.pid}/block_{b}.json" for b in sorted(blocks)]


def perspective_tiles(wildcards, suffix):
    plan = read_plan(plan_path(wildcards.pid))
    return [f"{RESULTS}/tiles/{wildcards.pid}/{t.key}{suffix}" for t in plan.tiles]
