from pipeline25d.logsetup import log_to
from pipeline25d.tile_archive import write_pmtiles

log_to(snakemake.log[0])
write_pmtiles(snakemake.input.tiles, snakemake.output[0], name=snakemake.wildcards.pid)
