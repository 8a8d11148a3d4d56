from pipeline25d.logsetup import log_to
from pipeline25d.stages import tms

log_to(snakemake.log[0])
tms(snakemake.input[0], snakemake.params.zoom, snakemake.output[0], processes=snakemake.threads,
    tile_format=snakemake.params.tile_format, quality=snakemake.params.quality)
