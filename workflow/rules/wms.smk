# Map services: a MapServer mapfile publishing every perspective's map as a WMS layer
# (pipeline25d.publish.wms); its paths are relative to it, so the results folder can move.


rule wms:
    input:
        maps=expand(rules.warp.output.cog, pid=PERSPECTIVE_IDS),
        ids=lambda wc: id_layer_inputs("maps"),
    output:
        mapfile=f"{RESULTS}/wms/{config['scene']}.map",
    params:
        **job(
            scene=config["scene"],
        ),
    # one core, and the cores idle when it starts (core.cores): each map's row raster (the id
    # layer) on its own thread; holding two, it waited for the last web-tile job to end (make bench:
    # 12 s alone at the end of the run)
    threads: 1
    priority: 1
    log:
        f"{RESULTS}/logs/wms.log",
    shell:
        JOB
