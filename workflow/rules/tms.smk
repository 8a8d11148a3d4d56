# gdal2tiles XYZ pyramid per perspective, kept in work/tms/{pid} and updated where the map changed
# (see pipeline25d.stages.tiles.web); the published folder hard-links the kept tiles. The stats file says
# how many web tiles the run redid. With objects.enabled the same job cuts the id map into the same
# XYZ tiles (idtiles/{pid}, pipeline25d.stages.tiles.ids, updated where the ids changed).


rule tms:
    input:
        cog=rules.warp.output.cog,
        **with_ids(ids=ID_MAP),
    output:
        tiles=directory(f"{RESULTS}/tms/{{pid}}"),
        stats=f"{RESULTS}/work/tms/{{pid}}.json",
        **with_ids(id_tiles=directory(f"{RESULTS}/idtiles/{{pid}}"), id_stats=f"{RESULTS}/work/idtiles/{{pid}}.json"),
    params:
        **job(
            zoom=config["tms"]["zoom"],
            tile_format=config["tms"]["format"],
            quality=config["tms"]["quality"],
            webp_method=config["tms"]["webp_method"],
            work=f"{RESULTS}/work/tms/{{pid}}",
            cells_note=MAP_CELLS_NOTE,
            id_work=f"{RESULTS}/work/idtiles/{{pid}}",
        ),
    # one core (a job holding two waited for both to be free), and the cores idle when it starts
    # (core.cores); on a cluster profiles/slurm gives it two
    threads: 1
    log:
        f"{RESULTS}/logs/tms/{{pid}}.log",
    shell:
        JOB


# With tms.pmtiles: the pyramid also as one PMTiles archive per perspective (pipeline25d.stages.tiles.archive),
# which the viewer then reads by HTTP range requests.
rule pmtiles:
    input:
        tiles=rules.tms.output.tiles,
    output:
        f"{RESULTS}/pmtiles/{{pid}}.pmtiles",
    params:
        **job(),
    log:
        f"{RESULTS}/logs/pmtiles/{{pid}}.log",
    shell:
        JOB
