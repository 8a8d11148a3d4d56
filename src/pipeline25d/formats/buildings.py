"""The buildings of a city model (CityJSON, CityGML), for the ground where their walls end.

``terrain: auto`` on a model without terrain takes its ground from where its buildings
stand (:mod:`pipeline25d.stages.terrain.bases`). These readers give that stage the model's
building objects (Building, BuildingPart, ... : :data:`~pipeline25d.formats.surfaces.OBJECT_CLASS`
"building") as parts named by colour class ("ground": GroundSurface or, without semantics,
downward-facing; "wall"; "roof"), untextured, at the LOD the map draws, and whether the
file holds anything else (then the model's surface may show real ground between them).
"""

from __future__ import annotations

from pathlib import Path
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


def read_cityjson_buildings(path: Path, spec: dict) -> Buildings:
    """The building objects of a CityJSON/CityJSONSeq file, in its own CRS."""
    from pipeline25d.formats.cityjson import _build_parts, _read_model, _terrain_types

    model = _read_model(Path(path))
    terrain = _terrain_types(model)
    others = any(isinstance(o, dict) and o.get("geometry") and not is_building(o.get("type"))
                 and o.get("type") not in terrain for c in model.chunks for o in c.objects.values())
    return Buildings(_build_parts(model, spec.get("crs"), spec.get("lod"), is_building), others)


def read_citygml_buildings(path: Path, spec: dict) -> Buildings:
    """The building objects of a CityGML file, in its own CRS (untextured: parts by colour class)."""
    from pipeline25d.formats.citygml import _GROUND_TYPES, _Reader

    reader = _Reader(Path(path), spec, textures=False)
    reader.run(lambda t: True)
    others = any(not is_building(t) and t != "TINRelief" and t not in _GROUND_TYPES for t in reader.types_drawn)
    return Buildings(reader.loaded(is_building), others)
