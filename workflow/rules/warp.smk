# Orthorectify: the warp with the lowest check-point error (or none), written as a COG.


rule warp:
    input:
        mosaic=rules.mosaic.output[0],
        gcps=rules.gcps.output[0],
        plan=f"{RESULTS}/plans/{{pid}}.json",
    output:
        cog=f"{RESULTS}/maps/{{pid}}.tif",
        meta=f"{RESULTS}/maps/{{pid}}.json",
    params:
        warp=config["warp"],
        maps=config["maps"],
        work=f"{RESULTS}/work/warp/{{pid}}",
    # the COG's blocks are compressed on both cores (GDAL's NUM_THREADS: the same bytes, 1.34x on one map)
    threads: 2
    log:
        f"{RESULTS}/logs/warp/{{pid}}.log",
    benchmark:
        f"{RESULTS}/benchmarks/warp/{{pid}}.tsv"
    script:
        "../scripts/job.py"


# The id map (objects.enabled): the tiles' object ids through the warp the map chose, nearest
# neighbour, on the map's grid and made as it is (parts, or kept blocks patched where a mosaic
# changed); its stats file holds the agreement with the map's alpha and the bytes.


rule id_map:
    input:
        ids=rules.mosaic_ids.output[0],
        mosaic=rules.mosaic.output[0],
        gcps=rules.gcps.output[0],
        cog=rules.warp.output.cog,
        meta=rules.warp.output.meta,
    output:
        ids=f"{RESULTS}/maps/{{pid}}.ids.tif",
        stats=f"{RESULTS}/work/ids/{{pid}}.json",
    params:
        work=f"{RESULTS}/work/ids/{{pid}}",
    threads: 2
    log:
        f"{RESULTS}/logs/id_map/{{pid}}.log",
    benchmark:
        f"{RESULTS}/benchmarks/id_map/{{pid}}.tsv"
    script:
        "../scripts/job.py"
