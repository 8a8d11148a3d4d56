# Building heights measured on the maps: each footprint's roof displacement between the nadir
# map and every oblique map, compared with the model's own heights (see height_sources.py).
# In parallel jobs (analysis/height_blocks.py): the heights_blocks checkpoint puts the footprints on
# the maps in blocks of heights.block_size m and the blocks in jobs (sparse neighbours together), one
# heights_block job measures each job's blocks (and keeps a block's rows where nothing they were
# measured from changed: a district update re-measures only the blocks it reaches), the heights job
# merges the rows and compares them with the model.

# only what the steps read: a change elsewhere (web tiles, shadows ...) must not re-run them
HEIGHTS_CONFIG = {k: config[k] for k in ("crs", "gsd", "inputs", "perspectives", "heights") if k in config}
HEIGHTS_ROWS = f"{RESULTS}/work/heights/rows"   # each block's rows and their digest, kept between runs
HEIGHTS_NADIR = [f"{RESULTS}/maps/{pid}.tif" for pid in PERSPECTIVE_IDS if pid == "az000_el90"]


checkpoint heights_blocks:
    input:
        nadir=HEIGHTS_NADIR,
        sources=HEIGHTS_PLAN["files"],
    output:
        blocks=f"{RESULTS}/work/heights/blocks.json",
    params:
        **job(
            config=HEIGHTS_CONFIG,
        ),
    log:
        f"{RESULTS}/logs/heights/blocks.log",
    shell:
        JOB


rule heights_block:
    input:
        maps=expand(f"{RESULTS}/maps/{{pid}}.tif", pid=PERSPECTIVE_IDS),
        scene=rules.scene.output.scene,
        blocks=rules.heights_blocks.output.blocks,
    output:
        f"{RESULTS}/work/heights/block_{{hblock}}.json",
    params:
        **job(
            config=HEIGHTS_CONFIG,
            pids=PERSPECTIVE_IDS,
            rows_dir=HEIGHTS_ROWS,
        ),
    log:
        f"{RESULTS}/logs/heights/block_{{hblock}}.log",
    shell:
        JOB


rule heights:
    input:
        maps=expand(f"{RESULTS}/maps/{{pid}}.tif", pid=PERSPECTIVE_IDS),
        scene=rules.scene.output.scene,
        dsm=rules.terrain.output.dsm,
        sources=HEIGHTS_PLAN["files"],
        blocks=[] if HEIGHTS_PLAN["skip"] else [rules.heights_blocks.output.blocks],
        block_jobs=heights_block_files,
    output:
        csv=f"{RESULTS}/heights.csv",
        json=f"{RESULTS}/heights.json",
    params:
        **job(
            config=HEIGHTS_CONFIG,
            pids=PERSPECTIVE_IDS,
            rows_dir=HEIGHTS_ROWS,
        ),
    priority: 1
    log:
        f"{RESULTS}/logs/heights.log",
    shell:
        JOB
