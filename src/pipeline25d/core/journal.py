"""The state file of a kept, updatable output (the web-tile pyramid, a warped map): what it was
made from, and a journal ("dirty") of the pieces being redone, written before any is touched."""

from __future__ import annotations

import json
from pathlib import Path

from pipeline25d.core.atomic import write_json


def read_state(work: Path) -> dict | None:
    """``work/state.json``, or None where it is missing or unreadable (then all is redone)."""
    try:
        return json.loads((work / "state.json").read_text())
    except (FileNotFoundError, json.JSONDecodeError):
        return None


def write_state(work: Path, state: dict) -> None:
    """Write ``work/state.json`` atomically; its "dirty" pieces as lists."""
    write_json(work / "state.json", {**state, "dirty": [list(w) for w in state["dirty"]]}, indent=None)
