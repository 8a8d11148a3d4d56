# Every rule runs this script: pipeline25d.jobs holds one function per rule (the one seam). A run with
# a job host (pipeline25d.jobhost) has the host's fork run it, which has imported what jobs use.
from pipeline25d.jobhost import run_on_host

if not run_on_host(snakemake):  # noqa: F821 (Snakemake defines it)
    from pipeline25d.jobs import run

    run(snakemake)  # noqa: F821
