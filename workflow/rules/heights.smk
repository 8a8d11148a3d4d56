# Building heights measured on the maps: each footprint's roof displacement between the nadir
# map and every oblique map, compared with the model's own heights (see height_sources.py).


rule heights:
    input:
        maps=expand(f"{RESULTS}/maps/{{pid}}.tif", pid=PERSPECTIVE_IDS),
        scene=rules.scene.output.scene,
        dsm=rules.terrain.output.dsm,
        sources=HEIGHTS_PLAN["files"],
    output:
        csv=f"{RESULTS}/heights.csv",
        json=f"{RESULTS}/heights.json",
    params:
        # only what the step reads: a change elsewhere (web tiles, shadows ...) must not re-run it
        config={k: config[k] for k in ("crs", "gsd", "inputs", "perspectives", "heights") if k in config},
        pids=PERSPECTIVE_IDS,
    threads: workflow.cores   # footprints in blocks on this many processes (views.measure_parallel)
    log:
        f"{RESULTS}/logs/heights.log",
    benchmark:
        f"{RESULTS}/benchmarks/heights.tsv"
    script:
        "../scripts/job.py"
