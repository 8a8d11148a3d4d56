from pipeline25d.atomic import write_json
from pipeline25d.logsetup import log_to, stop_on_error
from pipeline25d.web_tiles import tms

log_to(snakemake.log[0])
with stop_on_error():
    stats = tms(snakemake.input.cog, snakemake.params.zoom, snakemake.output.tiles, processes=snakemake.threads,
                tile_format=snakemake.params.tile_format, quality=snakemake.params.quality,
                work_dir=snakemake.params.work)
    write_json(snakemake.output.stats, stats)
