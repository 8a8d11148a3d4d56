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
