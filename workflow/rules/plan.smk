# Scene set-up (reference plane, GCP candidates) and the per-perspective plan checkpoint.


rule scene:
    input:
        indexes=expand(f"{RESULTS}/chunks/{{district}}/index.json", district=DISTRICTS),
        lods=all_lod_meta,
        terrain=TERRAIN_FILE,
        gcps=GCP_FILE,
    output:
        scene=f"{RESULTS}/scene.json",
        candidates=f"{RESULTS}/gcps/candidates.csv",
    params:
        terrain=config["terrain"],
        z0=config["z0"],
        gcp=config["gcp"],
        crs=config["crs"],
    log:
        f"{RESULTS}/logs/scene.log",
    benchmark:
        f"{RESULTS}/benchmarks/scene.tsv"
    script:
        "../scripts/scene.py"


checkpoint plan:
    input:
        lods=all_lod_meta,
        scene=rules.scene.output.scene,
        candidates=rules.scene.output.candidates,
    output:
        plan=f"{RESULTS}/plans/{{pid}}.json",
    params:
        gsd=config["gsd"],
        tile_size=config["tile_size"],
        max_error_px=config["lod"]["max_error_px"],
        crs=config["crs"],
        render=RENDER_SETTINGS,
    log:
        f"{RESULTS}/logs/plan/{{pid}}.log",
    benchmark:
        f"{RESULTS}/benchmarks/plan/{{pid}}.tsv"
    script:
        "../scripts/plan.py"
