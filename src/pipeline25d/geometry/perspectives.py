"""Perspectives (azimuth, elevation), their ids and presets.

Azimuth θ is the compass bearing of the viewing direction (0 looks north, 90 east);
elevation φ is the angle of the view above the horizon (90 = nadir).
"""

from __future__ import annotations

import re
from typing import NamedTuple

ID_PATTERN = r"az\d{3}_el\d{2}"

PRESETS: dict[str, tuple[tuple[int, int], ...]] = {
    "eight-45+nadir": tuple((az, 45) for az in range(0, 360, 45)) + ((0, 90),),
    "four-45+nadir": tuple((az, 45) for az in range(0, 360, 90)) + ((0, 90),),
    "nadir": ((0, 90),),
}


class Perspective(NamedTuple):
    """A view direction in whole degrees; hashable, so usable as a key."""

    azimuth: int
    elevation: int

    @property
    def id(self) -> str:
        """Stable id such as ``az045_el45``; nadir is ``az000_el90``."""
        return f"az{self.azimuth:03d}_el{self.elevation:02d}"

    @classmethod
    def from_id(cls, text: str) -> "Perspective":
        match = re.fullmatch(r"az(\d{3})_el(\d{2})", text)
        if not match:
            raise ValueError(f"not a perspective id: {text!r}")
        return cls(int(match.group(1)), int(match.group(2)))


def expand(spec: str | list[dict]) -> list[Perspective]:
    """The perspectives of a config value (a preset name or a list of dicts), deduplicated."""
    if isinstance(spec, str):
        pairs = PRESETS[spec]
    else:
        pairs = [(int(p["azimuth"]), int(p["elevation"])) for p in spec]
    seen: dict[str, Perspective] = {}
    for az, el in pairs:
        # Every azimuth gives the same nadir view; keep one id for it.
        persp = Perspective(0 if el == 90 else az % 360, el)
        seen.setdefault(persp.id, persp)
    return list(seen.values())
