from pipeline25d.logsetup import log_to
from pipeline25d.report import write_report

log_to(snakemake.log[0])
write_report(dict(snakemake.params.config), snakemake.params.results, snakemake.output.json, snakemake.output.md)
