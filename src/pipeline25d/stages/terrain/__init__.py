"""Terrain from the model itself: a nadir height map (DSM), ground cells, an interpolated DTM.

1. **DSM**: the scene rendered straight down, tile by tile, through the tile renderer's
   depth pass (no multisampling, so each cell holds the model's top surface exactly at
   its centre; 24-bit depth over the scene's height range).
2. **Ground**: an input's own terrain where it has one (CityJSON TINRelief or ground
   semantics); elsewhere the Cloth Simulation Filter (Zhang et al. 2016,
   ``cloth-simulation-filter``, maintained by the method's authors). CSF is run on the DSM
   minus a smooth lower envelope (a grey opening wider than the largest above-ground
   object, then a Gaussian), so steep relief does not tear the cloth: on a 1 km test with
   600 m of relief this lifts ground recall from 0.92–0.95 to 1.00 with no object cell
   taken as ground. Buildings standing on ground the model does not carry give it where their
   walls end (``bases``: a TIN of their ground surfaces' vertices or wall bottoms; in formats
   that name no buildings, ``shapes`` finds them by their shape); an input made of buildings
   alone is not filtered (its surface holds roofs only).
3. **DTM**: ground cells keep the DSM's height; the rest (under buildings, trees) is filled
   by GDAL's inverse-distance ``FillNodata``, corrected along local planes where ground surrounds
   the gap (``gap_planes``; the scene stage fills it, without the check points' ground).
All heights are float64 metres in the scene CRS; the rasters are written as float32 GeoTIFFs.

Memory follows a block, not the city: the DSM is written tile by tile as it is rendered, and
the ground filter and the DTM fill run per block of cells (:func:`cell_blocks`), each on a
window reaching far enough around its core that the core comes out as on the whole grid
(exactly for the envelope, the edge trimming and the fill; the cloth's own edges aside).

Modules: ``dsm`` (the nadir height map), ``ground`` (ground cells: the envelope and the cloth),
``bases`` (ground from building bases), ``shapes`` (buildings by their shape),
``dtm`` (the fill between ground cells), ``gap_planes`` (its local planes), ``build`` (the
terrain stage's job); the cell grid and its float GeoTIFFs are :mod:`pipeline25d.core.grid`.
"""
