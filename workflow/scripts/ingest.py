from pipeline25d.logsetup import log_to, stop_on_error
from pipeline25d.stages import ingest

log_to(snakemake.log[0])
with stop_on_error():
    ingest(dict(snakemake.params.spec), snakemake.wildcards.district, snakemake.params.crs,
           snakemake.params.chunk_size, snakemake.params.max_error, snakemake.output.index,
           gsd=snakemake.params.gsd)
