from pipeline25d.logsetup import log_to
from pipeline25d.stages import build_terrain

log_to(snakemake.log[0])
build_terrain(list(snakemake.input.lods), dict(snakemake.params.inputs), snakemake.params.crs, snakemake.params.gsd,
              snakemake.params.terrain, dict(snakemake.params.ground), snakemake.output.dsm,
              snakemake.output.ground[0] if snakemake.output.ground else None, snakemake.output.meta)
