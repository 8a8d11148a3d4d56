"""Logging for Snakemake script jobs: everything to the rule's log file."""

from __future__ import annotations

import logging


def log_to(path: str) -> None:
    logging.basicConfig(filename=path, level=logging.INFO, force=True,
                        format="%(asctime)s %(levelname)s %(name)s: %(message)s")
