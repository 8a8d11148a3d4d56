# Report (accuracy, tiles, sizes, timings) and the web viewer.


# report.html's pictures (a thumbnail and the check-point residuals of each map, the heights scatter):
# they need the maps and the heights, not the web tiles, so they are drawn while the last maps are cut
# (the report waited for those, then drew them: 2 s at the end of a 3 x 3 Delft city's 58 s)
rule report_figures:
    input:
        maps=expand(f"{RESULTS}/maps/{{pid}}.json", pid=PERSPECTIVE_IDS),
        cogs=expand(f"{RESULTS}/maps/{{pid}}.tif", pid=PERSPECTIVE_IDS),
        gcps=expand(f"{RESULTS}/gcps/{{pid}}.csv", pid=PERSPECTIVE_IDS),
        mosaics=expand(f"{RESULTS}/mosaic/{{pid}}.vrt", pid=PERSPECTIVE_IDS),
        heights=rules.heights.output.json,
        heights_csv=rules.heights.output.csv,
    output:
        f"{RESULTS}/work/report/figures.json",
    params:
        **job(
            perspectives=PERSPECTIVE_IDS,
            gsd=config["gsd"],
            results=RESULTS,
        ),
    priority: 1
    log:
        f"{RESULTS}/logs/report_figures.log",
    shell:
        JOB


rule report:
    input:
        maps=expand(f"{RESULTS}/maps/{{pid}}.json", pid=PERSPECTIVE_IDS),
        cogs=expand(f"{RESULTS}/maps/{{pid}}.tif", pid=PERSPECTIVE_IDS),
        plans=expand(f"{RESULTS}/plans/{{pid}}.json", pid=PERSPECTIVE_IDS),
        tms=expand(f"{RESULTS}/tms/{{pid}}", pid=PERSPECTIVE_IDS),
        tms_stats=expand(f"{RESULTS}/work/tms/{{pid}}.json", pid=PERSPECTIVE_IDS),
        scene=rules.scene.output.scene,
        heights=rules.heights.output.json,
        heights_csv=rules.heights.output.csv,
        gcps=expand(f"{RESULTS}/gcps/{{pid}}.csv", pid=PERSPECTIVE_IDS),
        mosaics=expand(f"{RESULTS}/mosaic/{{pid}}.vrt", pid=PERSPECTIVE_IDS),
        id_stats=ID_STATS,
        chunks=expand(f"{RESULTS}/chunks/{{district}}/index.json", district=DISTRICTS),
        figures=rules.report_figures.output[0],
    output:
        json=f"{RESULTS}/report/report.json",
        md=f"{RESULTS}/report/report.md",
        html=f"{RESULTS}/report/report.html",
    params:
        **job(
            config=config,
            results=RESULTS,
        ),
    log:
        f"{RESULTS}/logs/report.log",
    shell:
        JOB


rule viewer:
    input:
        report=rules.report.output.json,
        tms=expand(f"{RESULTS}/tms/{{pid}}", pid=PERSPECTIVE_IDS),
        pmtiles=PMTILES,
        overlays=[o["path"] for o in config["viewer"]["overlays"]],
        ids=lambda wc: id_layer_inputs("tiles"),
    output:
        f"{RESULTS}/viewer/index.html",
    params:
        **job(
            viewer=config["viewer"],
            results=RESULTS,
        ),
    log:
        f"{RESULTS}/logs/viewer.log",
    shell:
        JOB
