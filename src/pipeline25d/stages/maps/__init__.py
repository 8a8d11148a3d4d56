"""Maps: the mosaic of a perspective's tiles, the warp chosen on its GCPs, the COG (parts for sparse
scenes, patched where the mosaic changed)."""
