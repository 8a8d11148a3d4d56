from pipeline25d.logsetup import log_to
from pipeline25d.stages import mosaic

log_to(snakemake.log[0])
mosaic(list(snakemake.params.tiles), snakemake.output[0])
