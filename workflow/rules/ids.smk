# Which object every map pixel shows, on the web: each perspective's id raster (maps/{pid}.ids.tif)
# cut into the same XYZ tiles as its map (pipeline25d.stages.tiles.ids, updated where the ids changed),
# and one table of the scene's objects (pipeline25d.publish.objects): objects/objects.gpkg, objects.csv
# (MapServer's GetFeatureInfo join) and the viewer's JSON shards. The viewer and the WMS take them
# where the id maps are made (objects.enabled: ID_LAYER).

ID_MAP = f"{RESULTS}/maps/{{pid}}.ids.tif"


rule id_tiles:
    input:
        cog=ID_MAP,
    output:
        tiles=directory(f"{RESULTS}/idtiles/{{pid}}"),
        stats=f"{RESULTS}/work/idtiles/{{pid}}.json",
    params:
        zoom=config["tms"]["zoom"],
        tile_format="ids",
        quality=0,
        work=f"{RESULTS}/work/idtiles/{{pid}}",
    threads: 2
    log:
        f"{RESULTS}/logs/id_tiles/{{pid}}.log",
    script:
        "../scripts/job.py"


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
        config={k: config[k] for k in ("crs", "inputs") if k in config},
        districts=DISTRICTS,
    log:
        f"{RESULTS}/logs/objects.log",
    script:
        "../scripts/job.py"


# the id layer exists where the id maps are made (objects.enabled)
ID_LAYER = OBJECTS


def id_layer_inputs(kind):
    """The id layer's files a publishing rule takes (none without id rasters): tiles or maps."""
    if not ID_LAYER:
        return []
    if kind == "tiles":
        return expand(rules.id_tiles.output.tiles, pid=PERSPECTIVE_IDS) + [rules.objects.output.shards]
    return expand(ID_MAP, pid=PERSPECTIVE_IDS) + [rules.objects.output.csv]
