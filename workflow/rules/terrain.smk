# Terrain from the model: the nadir DSM of the whole scene, and with terrain: auto its ground
# cells (the inputs' own terrain where they carry one, else the Cloth Simulation Filter on the
# DSM). The scene rule interpolates the DTM from them, holding the check points out.


rule terrain:
    input:
        lods=all_lod_meta,
        terrain=TERRAIN_FILE,
    output:
        dsm=f"{RESULTS}/terrain/dsm.tif",
        meta=f"{RESULTS}/terrain/terrain.json",
        ground=[f"{RESULTS}/terrain/ground.tif"] if config["terrain"] == "auto" else [],
    params:
        **job(
            inputs=config["inputs"],
            crs=config["crs"],
            gsd=config["gsd"],
            terrain=config["terrain"],
            ground=config["ground"],
            # checked against config["limits"] before the DSM is made; not a re-run: another
            # perspective or limit makes the same terrain
            described={"work": WORK},
        ),
    # the ground filter's blocks run on both cores (nothing else can run beside this job)
    threads: 2
    log:
        f"{RESULTS}/logs/terrain.log",
    shell:
        JOB
