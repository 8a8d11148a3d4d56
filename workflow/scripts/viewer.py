from pipeline25d.logsetup import log_to
from pipeline25d.viewer import write_viewer

log_to(snakemake.log[0])
write_viewer(snakemake.input.report, snakemake.output[0], archives=snakemake.input.pmtiles)
