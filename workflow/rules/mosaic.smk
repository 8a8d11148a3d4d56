# gdalbuildvrt over a perspective's tiles (they share one pixel grid).


rule mosaic:
    input:
        perspective_blocks,
    params:
        tiles=lambda wc: perspective_tiles(wc, ".tif"),
    output:
        f"{RESULTS}/mosaic/{{pid}}.vrt",
    log:
        f"{RESULTS}/logs/mosaic/{{pid}}.log",
    benchmark:
        f"{RESULTS}/benchmarks/mosaic/{{pid}}.tsv"
    script:
        "../scripts/job.py"
