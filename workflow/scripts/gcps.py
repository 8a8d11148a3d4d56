from pipeline25d.logsetup import log_to
from pipeline25d.stages import gather_gcps

log_to(snakemake.log[0])
gather_gcps(list(snakemake.params.tiles), snakemake.output[0])
