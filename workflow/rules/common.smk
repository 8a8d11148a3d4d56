# Config validation (before any job), constants, wildcard constraints and input functions.
import shlex
import sys

from snakemake.exceptions import WorkflowError
from snakemake.utils import validate

from pipeline25d.config import check_semantics, chunk_size, perspectives
from pipeline25d.errors import Pipeline25dError
from pipeline25d.perspectives import ID_PATTERN
from pipeline25d.plan import plan_tile, read_plan

validate(config, "../../config/schema.yaml")
try:
    check_semantics(config)
except Pipeline25dError as exc:
    raise WorkflowError(f"invalid configuration: {exc}") from None

RESULTS = f"results/{config['scene']}"
# Jobs run this workflow's own interpreter (the venv snakemake runs in), whatever PATH says.
PYTHON = shlex.quote(sys.executable)
DISTRICTS = sorted(config["inputs"])
PERSPECTIVE_IDS = [p.id for p in perspectives(config)]
MAX_LOD_ERROR = config["gsd"] * config["lod"]["max_error_px"]
TERRAIN_FILE = [] if config["terrain"] in ("auto", "flat") else [config["terrain"]]
GCP_FILE = [] if config["gcp"]["source"] == "auto" else [config["gcp"]["source"]]
RENDER_SETTINGS = {**config["render"], "marker_px": config["gcp"]["marker_px"],
                   "depth_bias": config["gcp"]["depth_bias"], "max_float_px": config["gcp"]["max_float_px"]}


wildcard_constraints:
    pid=ID_PATTERN,
    row=r"-?\d+",
    col=r"-?\d+",
    district=r"[A-Za-z0-9-]+",


def district_inputs(wildcards):
    spec = config["inputs"][wildcards.district]
    return [spec[k] for k in ("path", "metadata") if k in spec]


def all_lod_meta(wildcards):
    """The per-district LOD indexes (each lists its chunks' LOD files, see stages.lod_chunks)."""
    return expand(rules.lod.output.index, district=DISTRICTS)


def plan_of(pid):
    return read_plan(checkpoints.plan.get(pid=pid).output.plan)


def tile_entry(wildcards):
    return plan_tile(plan_of(wildcards.pid), int(wildcards.row), int(wildcards.col))


def tile_lods(wildcards):
    """The LOD files a tile draws (side files of the lod jobs): a tile depends on its own chunks only."""
    return [f"{RESULTS}/lod/{c['district']}/{c['id']}.npz" for c in tile_entry(wildcards)["chunks"]]


def tile_spec_hash(wildcards):
    return tile_entry(wildcards)["spec_hash"]


def perspective_tiles(wildcards, suffix):
    plan = plan_of(wildcards.pid)
    return [f"{RESULTS}/tiles/{wildcards.pid}/{t['row']}_{t['col']}{suffix}" for t in plan["tiles"]]
