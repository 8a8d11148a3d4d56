"""The style gate: ``ruff check`` passes on the sources and tests, as ``make test`` runs it
(the rules are in pyproject.toml's [tool.ruff])."""

from __future__ import annotations

import importlib.util
import subprocess
import sys
from pathlib import Path

REPO = Path(__file__).parents[1]
PATHS = ["src", "tests"]


def test_ruff_finds_nothing():
    assert importlib.util.find_spec("ruff") is not None, \
        "ruff is not installed in this environment: run `make test` (it installs the test extras, ruff among them)"
    proc = subprocess.run([sys.executable, "-m", "ruff", "check", *PATHS], cwd=REPO, capture_output=True, text=True)
    assert proc.returncode == 0, proc.stdout + proc.stderr
