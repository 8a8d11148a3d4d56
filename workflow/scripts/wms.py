from pipeline25d.logsetup import log_to
from pipeline25d.wms import write_mapfile

log_to(snakemake.log[0])
write_mapfile(snakemake.params.scene, list(snakemake.input.maps), snakemake.output.mapfile)
