from pipeline25d.logsetup import log_to
from pipeline25d.stages import plan

log_to(snakemake.log[0])
plan(snakemake.wildcards.pid, list(snakemake.input.lods), snakemake.input.scene, snakemake.input.candidates,
     snakemake.params.gsd, snakemake.params.tile_size, snakemake.params.max_error_px, snakemake.params.crs,
     dict(snakemake.params.render), snakemake.output.plan)
