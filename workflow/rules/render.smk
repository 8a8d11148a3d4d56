# One job per render block (a quadtree node of a perspective's tiles that costs at most render.block
# x render.block whole tiles, see plan.plan_blocks; one process and GL context): each non-empty tile
# gets an RGBA GeoTIFF, its object ids (objects.enabled: <row>_<col>.ids.tif), the GCPs seen in it
# and its spec hash.
# Inputs are the LOD indexes of the districts the block draws (ancient: see block_lods); the block's
# hash (its tiles' spec hashes, which hold each chunk's LOD content hash) re-runs the job when a
# tile's plan entry changes, and the job then re-renders only the tiles whose spec changed.


rule render_block:
    input:
        block_lods,
    output:
        f"{RESULTS}/tiles/{{pid}}/block_{{block}}.json",
    params:
        **job(
            plan=f"{RESULTS}/plans/{{pid}}.json",
            lod_dir=f"{RESULTS}/lod",
            tiles_dir=f"{RESULTS}/tiles/{{pid}}",
            block=RENDER_BLOCK,
            objects=OBJECTS,
        ),
        # for Snakemake's re-run check alone (the job does not read it): beside job(), not in it,
        # so that building the job does not hash the block's tiles twice
        spec_hash=block_hash,
    # Ready jobs run plans first, then renders, warps, the maps' figures, web tiles (priorities 4 to 0):
    # every render is done before the web tiles, so the run does not end on one perspective's render,
    # warp and cut in a row with a core idle (Snakemake's greedy scheduler otherwise prefers the jobs
    # with the largest inputs: web tiles and warps). docs/running.md has the figures.
    priority: 3
    log:
        f"{RESULTS}/logs/render/{{pid}}/block_{{block}}.log",
    shell:
        JOB
