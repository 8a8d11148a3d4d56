"""CityJSON Building objects as footprints with their roof and ground heights (for the heights step).

Per Building (its BuildingParts' geometry included), at the LOD the map drew (``lod``, else the
highest): the footprint is the 2-D union of its GroundSurface polygons, or where the surfaces
carry no semantics (3dfier's LOD1 solids) of its downward-facing surfaces, or failing those of
all its non-vertical surfaces, projected to the ground (OGR union, float64). Roof z = the
mean z (weighted by area seen from above) of its RoofSurface (else upward-facing) surfaces; own ground z = that of
the ground surfaces that stand on the ground, not on the building (a dormer's or a part's floor on a roof;
NaN when there are none).
"""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np

from pipeline25d.formats.cityjson import (
    _SURFACE_DEPTH,
    _iter_surfaces,
    _pick_geometries,
    _read_model,
    source_crs,
    triangulate_polygon,
)
from pipeline25d.formats.footprints import Footprint, RefBuilding
from pipeline25d.formats.surfaces import ROOF_NZ

GROUND_TOL_M = 0.5        # a ground surface with a surface of its building this far below it stands on a roof

BUILDING_TYPES = ("Building", "BuildingPart")


def _surfaces(obj: dict, lod: str | None, verts: np.ndarray, model) -> list[tuple[np.ndarray, str]]:
    """(triangle corners (n, 3, 3) in file coordinates, kind 'roof'|'ground'|'other') per surface."""
    out = []
    for geom in _pick_geometries([g for g in obj.get("geometry") or [] if isinstance(g, dict)], lod, model):
        depth = _SURFACE_DEPTH.get(geom.get("type"))
        if depth is None:
            continue
        sem = geom.get("semantics") or {}
        types = [s.get("type") if isinstance(s, dict) else None for s in sem.get("surfaces") or []]
        for rings, value in _iter_surfaces(geom.get("boundaries") or [], sem.get("values"), depth):
            tris, normal = triangulate_polygon(rings, verts)
            if not len(tris):
                continue
            nz = float(normal[2] / max(np.linalg.norm(normal), 1e-300))
            st = types[value] if isinstance(value, int) and 0 <= value < len(types) else None
            kind = ("roof" if st == "RoofSurface" else "ground" if st == "GroundSurface" else "other" if st
                    else "roof" if nz > ROOF_NZ else "ground" if nz < -ROOF_NZ else "other")
            out.append((verts[np.asarray(tris)], kind, nz))
    return out


def _union_rings(tris: list[np.ndarray]) -> list[np.ndarray]:
    """Rings (n, 2) float64 of the 2-D union of triangles (OGR)."""
    from osgeo import ogr

    ogr.UseExceptions()
    multi = ogr.Geometry(ogr.wkbMultiPolygon)
    for t in tris:
        if abs((t[1, 0] - t[0, 0]) * (t[2, 1] - t[0, 1]) - (t[2, 0] - t[0, 0]) * (t[1, 1] - t[0, 1])) < 1e-10:
            continue
        ring = ogr.Geometry(ogr.wkbLinearRing)
        for x, y in (t[0], t[1], t[2], t[0]):
            ring.AddPoint_2D(float(x), float(y))
        poly = ogr.Geometry(ogr.wkbPolygon)
        poly.AddGeometry(ring)
        multi.AddGeometry(poly)
    if multi.GetGeometryCount() == 0:
        return []
    from pipeline25d.formats.footprints import _rings

    return _rings(multi.UnionCascaded())


def cityjson_buildings(path: str | Path, scene_crs: str, src_crs: str | None = None, lod: str | None = None,
                       offset=None) -> dict[str, RefBuilding]:
    """{building id: RefBuilding} of a CityJSON/CityJSONSeq file in ``scene_crs`` (``offset``
    [x, y, z] added first, as for the map)."""
    from pipeline25d.core.crs import transform_points

    model = _read_model(Path(path))
    src = src_crs or source_crs(model.header, model.path)
    off = np.asarray(offset if offset is not None else [0.0, 0.0, 0.0], dtype=np.float64)
    out: dict[str, RefBuilding] = {}
    for chunk in model.chunks:
        objs = chunk.objects
        verts = chunk.vertices
        for oid, obj in objs.items():
            if not isinstance(obj, dict) or obj.get("type") != "Building":
                continue
            members = [obj] + [objs[c] for c in obj.get("children") or []
                               if isinstance(objs.get(c), dict) and objs[c].get("type") in BUILDING_TYPES]
            surf = [(s, i) for i, m in enumerate(members) for s in _surfaces(m, lod, verts, model)]
            if not surf:
                continue
            pieces = [(np.asarray(t, dtype=np.float64).reshape(-1, 3, 3) + off, k, nz) for (t, k, nz), _ in surf]
            if src != scene_crs:
                pieces = [(transform_points(t.reshape(-1, 3), src, scene_crs).reshape(-1, 3, 3), k, nz)
                          for t, k, nz in pieces]
            ground = [t for t, k, _ in pieces if k == "ground"]
            outline = ground or [t for t, _, nz in pieces if abs(nz) > 1e-3]
            rings = _union_rings([tri[:, :2] for t in outline for tri in t])
            if not rings:
                continue
            out[str(oid)] = RefBuilding(Footprint(str(oid), tuple(rings)),
                                        _mean_z([t for t, k, _ in pieces if k == "roof"]),
                                        own_ground_z=_mean_z(_on_the_ground(pieces, [i for _, i in surf])))
    return out


def _on_the_ground(pieces: list[tuple[np.ndarray, str, float]], member: list[int]) -> list[np.ndarray]:
    """The ground surfaces of a building's ``pieces`` (triangles, kind, normal z; of its parts
    ``member``) that stand on the ground, not on the building (:func:`~pipeline25d.geometry.standing.standing`
    at their centroids: a dormer's or a chimney's floor on the roof, a part's on another part);
    none where every one does (a building whose only ground surface is a part's on its roof)."""
    from pipeline25d.geometry.standing import standing

    ground = [(t, m) for (t, k, _), m in zip(pieces, member) if k == "ground"]
    if not ground:
        return []
    tris = np.concatenate([t for t, _, _ in pieces])
    owner = np.concatenate([np.full(len(t), m) for (t, _, _), m in zip(pieces, member)])
    centres = np.concatenate([t.mean(axis=1) for t, _ in ground])
    stands = standing(centres, np.concatenate([np.full(len(t), m) for t, m in ground]), tris, owner,
                      GROUND_TOL_M, ROOF_NZ)
    kept = np.split(~stands, np.cumsum([len(t) for t, _ in ground])[:-1])
    return [t[k] for (t, _), k in zip(ground, kept) if k.any()]


def _mean_z(tris: list[np.ndarray]) -> float:
    """Mean z of triangles (n, 3, 3) weighted by their area seen from above (NaN for none)."""
    if not tris:
        return math.nan
    t = np.concatenate(tris)
    a, b = t[:, 1, :2] - t[:, 0, :2], t[:, 2, :2] - t[:, 0, :2]
    area = 0.5 * np.abs(a[:, 0] * b[:, 1] - a[:, 1] * b[:, 0])
    return float(np.sum(area * t[:, :, 2].mean(axis=1)) / area.sum()) if area.sum() > 0 else math.nan
