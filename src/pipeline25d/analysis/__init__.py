"""Measuring the maps: ground offsets against the nadir map (evaluate), building heights (heights,
height_sources: the workflow's heights stage) and measuring on one map (measure)."""
