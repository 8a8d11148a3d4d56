# One job per non-empty (perspective, row, col) tile: RGBA GeoTIFF + GCPs seen in it.
# Inputs are the tile's own chunk LODs; the spec hash (chunks, LODs, GCPs, settings)
# re-runs the tile when its plan entry changes, and only then.


rule render_tile:
    input:
        tile_lods,
    output:
        tif=f"{RESULTS}/tiles/{{pid}}/{{row}}_{{col}}.tif",
        gcps=f"{RESULTS}/tiles/{{pid}}/{{row}}_{{col}}.gcps.csv",
    params:
        plan=f"{RESULTS}/plans/{{pid}}.json",
        lod_dir=f"{RESULTS}/lod",
        spec_hash=tile_spec_hash,
    log:
        f"{RESULTS}/logs/render/{{pid}}/{{row}}_{{col}}.log",
    benchmark:
        f"{RESULTS}/benchmarks/render/{{pid}}/{{row}}_{{col}}.tsv"
    group:
        "render"
    shell:
        PYTHON + " -m pipeline25d render-tile --plan {params.plan} --row {wildcards.row} --col {wildcards.col}"
        " --lod-dir {params.lod_dir} --out-tif {output.tif} --out-gcps {output.gcps}"
        " --spec-hash {params.spec_hash} > {log} 2>&1"
