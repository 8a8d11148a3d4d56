from pipeline25d.height_sources import run_stage
from pipeline25d.logsetup import log_to

log_to(snakemake.log[0])
run_stage(dict(snakemake.params.config), dict(zip(snakemake.params.pids, snakemake.input.maps)), snakemake.input.scene,
          snakemake.input.dsm, snakemake.output.csv, snakemake.output.json)
