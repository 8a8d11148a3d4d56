from pipeline25d.logsetup import log_to
from pipeline25d.stages import warp

log_to(snakemake.log[0])
warp(snakemake.input.mosaic, snakemake.input.gcps, snakemake.input.plan, dict(snakemake.params.warp),
     snakemake.output.cog, snakemake.output.meta, dict(snakemake.params.maps), work_dir=snakemake.params.work)
