# Ingest: one district file -> chunks (float64 origin + float32 local), unchanged chunks untouched;
# its objects' numeric ids (objects.json beside the index) in the district's id slot. A plain rule,
# no checkpoint: nothing downstream asks for its chunks by name (the lod job reads them from the
# index), and each finished checkpoint made Snakemake re-evaluate the DAG.


rule ingest:
    input:
        district_inputs,
    output:
        index=f"{RESULTS}/chunks/{{district}}/index.json",
    params:
        spec=lambda wc: config["inputs"][wc.district],
        crs=config["crs"],
        chunk_size=chunk_size(config),
        max_error=MAX_LOD_ERROR,
        gsd=config["gsd"],
        slot=lambda wc: OBJECT_SLOTS[wc.district],
    log:
        f"{RESULTS}/logs/ingest/{{district}}.log",
    script:
        "../scripts/job.py"
