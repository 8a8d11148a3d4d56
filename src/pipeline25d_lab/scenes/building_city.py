"""Building-only city models with exact truth: box buildings standing on a known sloped plane,
no terrain objects (the commonest city models: CityJSON, CityGML LOD1/2, 3D BAG, PLATEAU).

Every bottom corner lies on :func:`plane`; a flat roof ``height`` above the highest. Written as
CityJSON 1.1 (LOD2 MultiSurface with semantics: walls, roof, a GroundSurface on some, a window
hole on some), CityGML 2.0 (LOD1 solids without semantics) or OBJ (bare triangles: no objects, no
semantics; floors facing down, up or missing; optionally on the plane drawn as terrain).
:func:`write_sparse_city` spreads clusters of them over a large empty box (``terrain: auto`` must
find the ground at their bases).
"""

from __future__ import annotations

import json
from collections.abc import Callable, Sequence
from pathlib import Path

import numpy as np

CRS = "EPSG:28992"
X0, Y0 = 85000.0, 447000.0
SLOPE = (0.04, -0.025, 3.0)           # z = a·(x - X0) + b·(y - Y0) + c
Footprint = tuple[float, float, float, float]


def plane(x, y) -> np.ndarray:
    """The ground the buildings stand on (float64)."""
    a, b, c = SLOPE
    return a * (np.asarray(x) - X0) + b * (np.asarray(y) - Y0) + c


def boxes(origins: Sequence[tuple[float, float]], size=(12.0, 9.0), spacing=30.0, n=3) -> list[Footprint]:
    """Footprints (x0, y0, x1, y1) of n x n boxes per origin, ``spacing`` apart."""
    return [(ox + i * spacing, oy + j * spacing, ox + i * spacing + size[0], oy + j * spacing + size[1])
            for ox, oy in origins for i in range(n) for j in range(n)]


def box_surfaces(fp: Footprint, ground: bool, window: bool, height=8.0, floor_z: float | None = None
                 ) -> tuple[list, list]:
    """(vertices, surfaces [(rings, semantic type)]) of a box on the plane: bottom corners on it
    (or all at ``floor_z``: a box standing on another's roof), a flat roof ``height`` above the
    highest; a window (hole in the south wall) if asked."""
    x0, y0, x1, y1 = fp
    xy = [(x0, y0), (x1, y0), (x1, y1), (x0, y1)]
    bottom = [(x, y, float(plane(x, y)) if floor_z is None else floor_z) for x, y in xy]
    roof = max(z for *_, z in bottom) + height
    verts = bottom + [(x, y, roof) for x, y in xy]
    walls = [[[k, (k + 1) % 4, 4 + (k + 1) % 4, 4 + k]] for k in range(4)]
    if window:
        wx0, wx1 = x0 + 3.0, x0 + 5.0
        sill, top = float(plane(wx0, y0)) + 1.0, float(plane(wx0, y0)) + 2.2
        verts += [(wx0, y0, sill), (wx1, y0, sill), (wx1, y0, top), (wx0, y0, top)]
        walls[0].append([8, 11, 10, 9])
    surfaces = [(w, "WallSurface") for w in walls] + [([[4, 5, 6, 7]], "RoofSurface")]
    if window:
        surfaces.append(([[8, 9, 10, 11]], "Window"))
    if ground:
        surfaces.append(([[0, 3, 2, 1]], "GroundSurface"))
    return verts, surfaces


TOWER_HEIGHT = 15.0


def roof_z(fp: Footprint, height=8.0) -> float:
    """The flat roof's height of the box on ``fp`` (:func:`box_surfaces`)."""
    return max(float(plane(x, y)) for x in fp[::2] for y in fp[1::2]) + height


def tower_on(fp: Footprint, inset=3.0) -> Footprint:
    """A footprint ``inset`` inside ``fp``: a tower standing on that box's roof, sharing no vertex with it."""
    return fp[0] + inset, fp[1] + inset, fp[2] - inset, fp[3] - inset


def write_cityjson(path: Path, footprints: Sequence[Footprint], ground: Callable[[int], bool] = lambda i: i % 2 == 0,
                   window: Callable[[int], bool] = lambda i: i == 1, towers: Sequence[int] = (),
                   tower_part: bool = True) -> Path:
    """A CityJSON 1.1 file of the boxes (no terrain), vertices at 1 mm; building i has a
    GroundSurface where ``ground(i)``, a window where ``window(i)``. ``towers``: the buildings with
    a tower (:func:`tower_on`, :data:`TOWER_HEIGHT` high) standing on their roof, a separate
    solid: their BuildingPart with a GroundSurface of its own on the roof (``tower_part``), or a
    Building of its own without one."""
    vertices, objects = [], {}

    def add(key: str, surfaces: list, verts: list, **extra) -> None:
        base = len(vertices)
        vertices.extend(verts)
        types = sorted({t for _, t in surfaces})
        objects[key] = {**extra, "geometry": [{
            "type": "MultiSurface", "lod": "2",
            "boundaries": [[[base + v for v in ring] for ring in rings] for rings, _ in surfaces],
            "semantics": {"surfaces": [{"type": t} for t in types], "values": [types.index(t) for _, t in surfaces]},
        }]}

    for i, fp in enumerate(footprints):
        verts, surfaces = box_surfaces(fp, ground(i), window(i))
        add(f"b{i}", surfaces, verts, type="Building", **({"children": [f"b{i}-tower"]} if i in towers and tower_part
                                                             else {}))
        if i in towers:
            verts, surfaces = box_surfaces(tower_on(fp), tower_part, False, TOWER_HEIGHT, floor_z=roof_z(fp))
            add(f"b{i}-tower" if tower_part else f"t{i}", surfaces, verts,
                **({"type": "BuildingPart", "parents": [f"b{i}"]} if tower_part else {"type": "Building"}))
    scale = 0.001
    ints = [[round((x - X0) / scale), round((y - Y0) / scale), round(z / scale)] for x, y, z in vertices]
    doc = {"type": "CityJSON", "version": "1.1", "transform": {"scale": [scale] * 3, "translate": [X0, Y0, 0.0]},
           "metadata": {"referenceSystem": f"https://www.opengis.net/def/crs/EPSG/0/{CRS.split(':')[1]}"},
           "CityObjects": objects, "vertices": ints}
    path.write_text(json.dumps(doc))
    return path


def write_citygml_lod1(path: Path, footprints: Sequence[Footprint]) -> Path:
    """A CityGML 2.0 file of LOD1 box solids without semantics (the floor faces down)."""
    def poly(pts):
        coords = " ".join(f"{x:.3f} {y:.3f} {z:.3f}" for x, y, z in pts + pts[:1])
        return (f"<gml:surfaceMember><gml:Polygon><gml:exterior><gml:LinearRing><gml:posList>{coords}"
                "</gml:posList></gml:LinearRing></gml:exterior></gml:Polygon></gml:surfaceMember>")

    members = []
    for i, fp in enumerate(footprints):
        verts, surfaces = box_surfaces(fp, True, False)
        polys = "".join(poly([verts[v] for v in rings[0]]) for rings, _ in surfaces)
        members.append(f"<cityObjectMember><bldg:Building gml:id=\"b{i}\"><bldg:lod1Solid><gml:Solid><gml:exterior>"
                       f"<gml:CompositeSurface>{polys}</gml:CompositeSurface></gml:exterior></gml:Solid>"
                       "</bldg:lod1Solid></bldg:Building></cityObjectMember>")
    path.write_text(
        '<?xml version="1.0" encoding="UTF-8"?>\n<CityModel xmlns="http://www.opengis.net/citygml/2.0" '
        'xmlns:gml="http://www.opengis.net/gml" xmlns:bldg="http://www.opengis.net/citygml/building/2.0">'
        f'<gml:boundedBy><gml:Envelope srsName="{CRS}" srsDimension="3"><gml:lowerCorner>0 0 0</gml:lowerCorner>'
        '<gml:upperCorner>1 1 1</gml:upperCorner></gml:Envelope></gml:boundedBy>'
        + "".join(members) + "</CityModel>")
    return path


def write_obj(path: Path, footprints: Sequence[Footprint], floor: Callable[[int], str] = lambda i: "down~up~none"
              .split("~")[i % 3], terrain: bool = False, towers: Sequence[int] = ()) -> Path:
    """An OBJ of the boxes as bare triangles (no objects, no semantics: what a glTF or 3D Tiles export
    of buildings gives): box i's floor faces ``floor(i)``: "down", "up" (as some exporters flip
    it) or "none" (an open shell). ``terrain``: the plane itself as one more surface, a 5 m grid
    under and around the boxes, 20 m beyond them (a model that draws its own ground). ``towers``:
    the boxes with a tower on their roof (:func:`write_cityjson`), a closed box of its own."""
    verts, tris = [], []
    shapes = [(fp, {}) for fp in footprints]
    shapes += [(tower_on(footprints[i]), {"height": TOWER_HEIGHT, "floor_z": roof_z(footprints[i])}) for i in towers]
    for i, (fp, tower) in enumerate(shapes):
        box, surfaces = box_surfaces(fp, bool(tower) or floor(i) != "none", False, **tower)
        base = len(verts)
        verts += box
        for rings, kind in surfaces:
            ring = rings[0][::-1] if kind == "GroundSurface" and not tower and floor(i) == "up" else rings[0]
            tris += [(base + ring[0], base + ring[k], base + ring[k + 1]) for k in (1, 2)]
    if terrain:
        x0, y0 = min(f[0] for f in footprints) - 20, min(f[1] for f in footprints) - 20
        nx, ny = (int(np.ceil((max(f[j] for f in footprints) + 20 - o) / 5.0)) for j, o in ((2, x0), (3, y0)))
        base = len(verts)
        verts += [(x, y, float(plane(x, y)))
                  for y in y0 + 5.0 * np.arange(ny + 1) for x in x0 + 5.0 * np.arange(nx + 1)]
        for r in range(ny):
            for c in range(nx):
                a = base + r * (nx + 1) + c
                tris += [(a, a + 1, a + nx + 2), (a, a + nx + 2, a + nx + 1)]
    lines = [f"v {x:.4f} {y:.4f} {z:.4f}" for x, y, z in verts] + [f"f {a + 1} {b + 1} {c + 1}" for a, b, c in tris]
    path.write_text("\n".join(lines) + "\n")
    return path


#: the sparse city's cluster origins: the corners and the middle of a 5 km square
SPARSE_ORIGINS = [(X0, Y0), (X0 + 5000, Y0), (X0, Y0 + 5000), (X0 + 5000, Y0 + 5000), (X0 + 2500, Y0 + 2500)]


def write_sparse_city(path: Path, origins: Sequence[tuple[float, float]] = SPARSE_ORIGINS,
                      n: int = 3) -> list[Footprint]:
    """A buildings-only CityJSON city: n x n boxes at each origin (default: five clusters over
    5 x 5 km, 45 buildings; every other one with a GroundSurface), on the sloped :func:`plane`.
    Returns the footprints."""
    fps = boxes(origins, n=n)
    write_cityjson(path, fps)
    return fps
