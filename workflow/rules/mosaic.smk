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


# The same over the tiles' object ids (objects.enabled).


rule mosaic_ids:
    input:
        perspective_blocks,
    params:
        tiles=lambda wc: perspective_tiles(wc, ".ids.tif"),
    output:
        f"{RESULTS}/mosaic/{{pid}}.ids.vrt",
    log:
        f"{RESULTS}/logs/mosaic/{{pid}}.ids.log",
    script:
        "../scripts/job.py"
