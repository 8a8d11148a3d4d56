"""Not the product: sample scenes with exact truth (scenes/) and the benchmark and test harnesses (harness/).

The make targets and the tests use it; nothing in :mod:`pipeline25d` imports it."""
