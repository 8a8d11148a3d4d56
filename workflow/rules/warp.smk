# A perspective's map, in one job: its render tiles gathered (gdalbuildvrt over them: they share one
# pixel grid) with the GCPs they observed in one table (pipeline25d.stages.gcps), then orthorectified:
# the warp with the lowest check-point error (or none), written as a COG. The mosaic was a job of its
# own: nine start-ups (and nine cluster submissions) for 0.2 s of work each.
# With objects.enabled the same job mosaics the tiles' object ids (ID_MOSAIC) and then makes the id
# map (ID_MAP): the ids through the warp the map chose, nearest neighbour, on the map's grid and made
# as it is (parts, or kept blocks patched where a mosaic changed); its stats file holds the agreement
# with the map's alpha and the bytes.


rule warp:
    input:
        blocks=perspective_blocks,
        plan=f"{RESULTS}/plans/{{pid}}.json",
    output:
        mosaic=f"{RESULTS}/mosaic/{{pid}}.vrt",
        gcps=f"{RESULTS}/gcps/{{pid}}.csv",
        cog=f"{RESULTS}/maps/{{pid}}.tif",
        meta=f"{RESULTS}/maps/{{pid}}.json",
        **with_ids(id_mosaic=ID_MOSAIC, ids=ID_MAP, id_stats=ID_STAT),
    params:
        **job(
            tiles=lambda wc: perspective_tiles(wc, ".tif"),
            gcp_tiles=lambda wc: perspective_tiles(wc, ".gcps.csv"),
            **with_ids(id_tiles=lambda wc: perspective_tiles(wc, ".ids.tif")),
            warp=config["warp"],
            maps=config["maps"],
            work=f"{RESULTS}/work/warp/{{pid}}",
            cells_note=MAP_CELLS_NOTE,
            id_work=f"{RESULTS}/work/ids/{{pid}}",
        ),
    # one core: the warp used 1.13 of two and, holding two, kept render jobs off the other (with the
    # web tiles on one core too: a 3 x 3 Delft city 126 s -> 101 and 111 s in two runs); each COG
    # encode takes the cores idle when it runs too (stages.maps.warp.encode_options); on a cluster
    # profiles/slurm gives it two (GDAL's NUM_THREADS compresses the COG's blocks on all: the same bytes)
    threads: 1
    priority: 2
    log:
        f"{RESULTS}/logs/warp/{{pid}}.log",
    shell:
        JOB
