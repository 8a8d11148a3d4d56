# gdal2tiles XYZ pyramid per perspective.


rule tms:
    input:
        cog=rules.warp.output.cog,
        meta=rules.warp.output.meta,
    output:
        directory(f"{RESULTS}/tms/{{pid}}"),
    params:
        zoom=config["tms"]["zoom"],
        tile_format=config["tms"]["format"],
        quality=config["tms"]["quality"],
    threads: 2
    log:
        f"{RESULTS}/logs/tms/{{pid}}.log",
    benchmark:
        f"{RESULTS}/benchmarks/tms/{{pid}}.tsv"
    script:
        "../scripts/tms.py"
