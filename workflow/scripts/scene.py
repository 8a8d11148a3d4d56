from pipeline25d.logsetup import log_to
from pipeline25d.stages import scene_setup

log_to(snakemake.log[0])
scene_setup(list(snakemake.input.lods), snakemake.input.dsm, snakemake.params.terrain,
            snakemake.input.terrain[0] if snakemake.input.terrain else None, snakemake.params.z0,
            snakemake.params.projection, dict(snakemake.params.gcp), snakemake.params.crs, snakemake.params.gsd,
            list(snakemake.params.perspectives), snakemake.output.scene, snakemake.output.candidates,
            snakemake.output.dtm[0] if snakemake.output.dtm else None, snakemake.params.ground["max_object_size"])
