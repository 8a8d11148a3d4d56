# LOD pyramids (fast-simplification, each level with its measured error): one job per district,
# not per chunk, so interpreter start-up and imports are paid once per district. The declared
# output is the district's LOD index; the per-chunk LOD files beside it ({chunk}.npz) are side
# files that render_block jobs read. A chunk whose ingest hash and LOD parameters are unchanged
# keeps its file, mtime and content hash (record in index.hashes.json), so its tiles do not re-run
# (render_block reruns on its tiles' spec hashes, not on the index's time).


rule lod:
    input:
        rules.ingest.output.index,
    output:
        index=f"{RESULTS}/lod/{{district}}/index.json",
    params:
        max_error=MAX_LOD_ERROR,
        max_levels=config["lod"]["max_levels"],
    log:
        f"{RESULTS}/logs/lod/{{district}}.log",
    script:
        "../scripts/job.py"
