"""Benchmarks and test harnesses: the city-scale bench, the sweep, kill-safe resume, district updates, SLURM."""
