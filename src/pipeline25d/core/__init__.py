"""What every layer uses: errors, atomic output, logging, CRS, the mesh, rasters and grids."""
