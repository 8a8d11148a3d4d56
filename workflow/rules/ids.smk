# Which object every map pixel shows, on the web: each perspective's id raster (maps/{pid}.ids.tif, made
# by the warp job) cut into the same XYZ tiles as its map by the tms job (pipeline25d.stages.tiles.ids,
# updated where the ids changed), and one table of the scene's objects (pipeline25d.publish.objects):
# objects/objects.gpkg, objects.csv (MapServer's GetFeatureInfo join) and the viewer's JSON shards.
# The viewer and the WMS take them where the id maps are made (objects.enabled: ID_LAYER).


rule objects:
    input:
        chunks=expand(f"{RESULTS}/chunks/{{district}}/index.json", district=DISTRICTS),
        heights=rules.heights.output.csv,
        sources=[config["inputs"][d]["path"] for d in DISTRICTS],      # their attributes
    output:
        gpkg=f"{RESULTS}/objects/objects.gpkg",
        csv=f"{RESULTS}/objects/objects.csv",
        shards=directory(f"{RESULTS}/objects/shards"),
    params:
        **job(
            config={k: config[k] for k in ("crs", "inputs") if k in config},
            districts=DISTRICTS,
        ),
    log:
        f"{RESULTS}/logs/objects.log",
    shell:
        JOB


# the id layer exists where the id maps are made (objects.enabled)
ID_LAYER = OBJECTS


def id_layer_inputs(kind):
    """The id layer's files a publishing rule takes (none without id rasters): tiles or maps."""
    if not ID_LAYER:
        return []
    if kind == "tiles":
        return expand(rules.tms.output.id_tiles, pid=PERSPECTIVE_IDS) + [rules.objects.output.shards]
    return expand(ID_MAP, pid=PERSPECTIVE_IDS) + [rules.objects.output.csv]
