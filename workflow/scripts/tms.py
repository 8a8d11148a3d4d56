import json

from pipeline25d.logsetup import log_to
from pipeline25d.web_tiles import tms

log_to(snakemake.log[0])
parts = json.loads(open(snakemake.input.meta).read()).get("parts")
tms(snakemake.input.cog, snakemake.params.zoom, snakemake.output[0], processes=snakemake.threads,
    tile_format=snakemake.params.tile_format, quality=snakemake.params.quality, parts=parts)
