# Scene set-up (reference plane, projection, GCP candidates on exposed ground) and the plan checkpoint (every perspective's plan).


rule scene:
    input:
        indexes=expand(f"{RESULTS}/chunks/{{district}}/index.json", district=DISTRICTS),
        lods=all_lod_meta,
        dsm=rules.terrain.output.dsm,
        terrain=rules.terrain.output.ground if config["terrain"] == "auto" else TERRAIN_FILE,
        gcps=GCP_FILE,
    output:
        scene=f"{RESULTS}/scene.json",
        candidates=f"{RESULTS}/gcps/candidates.csv",
        dtm=[f"{RESULTS}/terrain/dtm.tif"] if config["terrain"] == "auto" else [],
        # where the DTM leaves the ground out: each check square's site (stages.scene)
        holdout=[f"{RESULTS}/terrain/dtm_holdout.csv"] if config["terrain"] == "auto" else [],
        # the DTM under each chunk, sampled once for every perspective's plan (terrain-relative mode)
        grounds=f"{RESULTS}/terrain/grounds.json",
    params:
        **job(
            terrain=config["terrain"],
            z0=config["z0"],
            projection=config["projection"],
            gcp=config["gcp"],
            crs=config["crs"],
            gsd=config["gsd"],
            perspectives=PERSPECTIVE_IDS,
            ground=config["ground"],
        ),
    # the DTM's blocks are interpolated on both cores (nothing else can run beside this job)
    threads: 2
    log:
        f"{RESULTS}/logs/scene.log",
    shell:
        JOB


# Every perspective's plan in one job: the scene, chunks and GCP candidates read once, one start-up,
# and one checkpoint (each finished checkpoint makes Snakemake re-evaluate the whole DAG: nine of
# them cost the 3 x 3 bench ~2 s of its wall time). The plans' inputs are the same for every
# perspective, so a changed district re-planned every one before too.


checkpoint plan:
    input:
        lods=all_lod_meta,
        scene=rules.scene.output.scene,
        candidates=rules.scene.output.candidates,
        grounds=rules.scene.output.grounds,
    output:
        plans=expand(f"{RESULTS}/plans/{{pid}}.json", pid=PERSPECTIVE_IDS),
    params:
        **job(
            perspectives=PERSPECTIVE_IDS,
            gsd=config["gsd"],
            tile_size=config["tile_size"],
            max_error_px=config["lod"]["max_error_px"],
            crs=config["crs"],
            render=RENDER_SETTINGS,
            work=WORK,
        ),
    priority: 4
    log:
        f"{RESULTS}/logs/plan.log",
    shell:
        JOB
