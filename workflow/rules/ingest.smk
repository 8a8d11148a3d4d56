# Ingest, one job per district: the district file -> chunks (float64 origin + float32 local),
# unchanged chunks untouched, and its objects' numeric ids (objects.json beside the index) in the
# district's id slot; then each chunk's LOD pyramid (fast-simplification, each level with its
# measured error). One job, not two: interpreter start-up, imports and Snakemake's own bookkeeping
# are paid once per district (120 districts in `make bench`). A plain rule, no checkpoint: nothing
# downstream asks for its chunks by name (the lod step reads them from the index), and each
# finished checkpoint made Snakemake re-evaluate the DAG.
# The declared outputs are the two indexes; the per-chunk files beside them ({chunk}.npz) are side
# files that the LOD step and the render_block jobs read. A chunk whose ingest hash and LOD
# parameters are unchanged keeps its LOD file, mtime and content hash (record in
# index.hashes.json), so its tiles do not re-run (render_block reruns on its tiles' spec hashes,
# not on the index's time).


rule ingest:
    input:
        district_inputs,
    output:
        index=f"{RESULTS}/chunks/{{district}}/index.json",
        lod=f"{RESULTS}/lod/{{district}}/index.json",
    params:
        **job(
            spec=lambda wc: config["inputs"][wc.district],
            crs=config["crs"],
            chunk_size=chunk_size(config),
            max_error=MAX_LOD_ERROR,
            max_levels=config["lod"]["max_levels"],
            gsd=config["gsd"],
            slot=lambda wc: OBJECT_SLOTS[wc.district],
        ),
    log:
        f"{RESULTS}/logs/ingest/{{district}}.log",
    shell:
        JOB
