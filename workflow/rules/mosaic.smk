# A perspective's render tiles gathered in one job: gdalbuildvrt over them (they share one pixel grid)
# and the GCPs they observed in one table (pipeline25d.stages.gcps); with objects.enabled it mosaics
# the tiles' object ids too (ID_MOSAIC).


rule mosaic:
    input:
        perspective_blocks,
    params:
        tiles=lambda wc: perspective_tiles(wc, ".tif"),
        gcp_tiles=lambda wc: perspective_tiles(wc, ".gcps.csv"),
        **with_ids(id_tiles=lambda wc: perspective_tiles(wc, ".ids.tif")),
    output:
        vrt=f"{RESULTS}/mosaic/{{pid}}.vrt",
        gcps=f"{RESULTS}/gcps/{{pid}}.csv",
        **with_ids(ids=ID_MOSAIC),
    log:
        f"{RESULTS}/logs/mosaic/{{pid}}.log",
    script:
        "../scripts/job.py"
