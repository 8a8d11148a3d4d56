# Every rule runs this script: pipeline25d.jobs holds one function per rule (the one seam).
from pipeline25d.jobs import run

run(snakemake)  # noqa: F821 (Snakemake defines it)
