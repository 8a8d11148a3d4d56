from pipeline25d.logsetup import log_to
from pipeline25d.stages import scene_setup

log_to(snakemake.log[0])
scene_setup(list(snakemake.input.lods), snakemake.params.terrain, snakemake.params.z0, dict(snakemake.params.gcp),
            snakemake.params.crs, snakemake.output.scene, snakemake.output.candidates)
