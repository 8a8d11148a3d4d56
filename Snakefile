# pipeline25d: 3D city model -> orthorectified multi-perspective 2.5D maps.
# Stages, one rules file each, in data-flow order (see ../shared/DESIGN.md and README.md).
from snakemake.utils import min_version

min_version("9.0")

# A --configfile replaces the default scene instead of being deep-merged into it, so a
# user who runs another scene never inherits the demo's inputs.
if not workflow.overwrite_configfiles:

    configfile: "config/config.yaml"


include: "workflow/rules/common.smk"
include: "workflow/rules/ingest.smk"
include: "workflow/rules/terrain.smk"
include: "workflow/rules/plan.smk"
include: "workflow/rules/render.smk"
include: "workflow/rules/warp.smk"
include: "workflow/rules/tms.smk"
include: "workflow/rules/heights.smk"
include: "workflow/rules/report.smk"
include: "workflow/rules/wms.smk"
include: "workflow/rules/ids.smk"


rule all:
    input:
        expand(f"{RESULTS}/maps/{{pid}}.tif", pid=PERSPECTIVE_IDS),
        ID_MAPS,
        expand(f"{RESULTS}/tms/{{pid}}", pid=PERSPECTIVE_IDS),
        f"{RESULTS}/report/report.json",
        f"{RESULTS}/viewer/index.html",
        PMTILES,
        rules.wms.output.mapfile,
    default_target: True
