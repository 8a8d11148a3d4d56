"""The workflow's stages, in the order data moves: ingest, lod, terrain, scene, plan, render
(render_block), gcps, maps (mosaic, warp, patch), tiles (web pyramid, PMTiles).

Each stage function reads and writes files (its rule's inputs and outputs) and knows nothing of
Snakemake; :mod:`pipeline25d.jobs` calls them."""
