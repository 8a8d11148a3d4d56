# Gather the GCPs seen in a perspective's tiles into one table.


rule gcps:
    input:
        perspective_blocks,
    params:
        tiles=lambda wc: perspective_tiles(wc, ".gcps.csv"),
    output:
        f"{RESULTS}/gcps/{{pid}}.csv",
    log:
        f"{RESULTS}/logs/gcps/{{pid}}.log",
    benchmark:
        f"{RESULTS}/benchmarks/gcps/{{pid}}.tsv"
    script:
        "../scripts/job.py"
