# gdalbuildvrt over a perspective's tiles (they share one pixel grid); with objects.enabled the same
# job mosaics the tiles' object ids too (ID_MOSAIC).


rule mosaic:
    input:
        perspective_blocks,
    params:
        tiles=lambda wc: perspective_tiles(wc, ".tif"),
        **with_ids(id_tiles=lambda wc: perspective_tiles(wc, ".ids.tif")),
    output:
        vrt=f"{RESULTS}/mosaic/{{pid}}.vrt",
        **with_ids(ids=ID_MOSAIC),
    log:
        f"{RESULTS}/logs/mosaic/{{pid}}.log",
    benchmark:
        f"{RESULTS}/benchmarks/mosaic/{{pid}}.tsv"
    script:
        "../scripts/job.py"
