"""Web tiles: the XYZ pyramid of a map, kept and updated where the map changed, and its PMTiles archive."""
