"""What a city model's buildings are, for the ground where their walls end.

``terrain: auto`` on a model without terrain takes its ground from where its buildings
stand (:mod:`pipeline25d.stages.terrain.bases`). The CityJSON and CityGML readers
(``read_cityjson_buildings``, ``read_citygml_buildings``) give that stage the model's
building objects (Building, BuildingPart, ... : :data:`~pipeline25d.formats.surfaces.OBJECT_CLASS`
"building") as parts named by colour class ("ground": GroundSurface or, without semantics,
downward-facing; "wall"; "roof"), untextured, at the LOD the map draws, and whether the
file holds anything else (then the model's surface may show real ground between them).
"""

from __future__ import annotations

from typing import NamedTuple

from pipeline25d.formats.common import Loaded
from pipeline25d.formats.surfaces import OBJECT_CLASS


class Buildings(NamedTuple):
    """A model's building objects (``loaded``: parts by colour class) and whether the file
    also draws objects that are neither buildings nor its own terrain (``others``)."""

    loaded: Loaded
    others: bool


def is_building(object_type: str | None) -> bool:
    """Whether a city object type is part of a building (Building, BuildingPart, BuildingInstallation ...)."""
    return OBJECT_CLASS.get(str(object_type)) == "building"
