# LOD pyramid per chunk (fast-simplification), with each level's measured error.


rule lod:
    input:
        f"{RESULTS}/chunks/{{district}}/{{chunk}}.npz",
    output:
        npz=f"{RESULTS}/lod/{{district}}/{{chunk}}.npz",
        meta=f"{RESULTS}/lod/{{district}}/{{chunk}}.json",
    params:
        max_error=MAX_LOD_ERROR,
        max_levels=config["lod"]["max_levels"],
    log:
        f"{RESULTS}/logs/lod/{{district}}/{{chunk}}.log",
    benchmark:
        f"{RESULTS}/benchmarks/lod/{{district}}/{{chunk}}.tsv"
    shell:
        PYTHON + " -m pipeline25d lod {input} {output.npz} {output.meta}"
        " --max-error {params.max_error} --max-levels {params.max_levels} > {log} 2>&1"
