"""One small textured city with two appearance themes, written both as CityJSON 2.0 and as CityGML 2.0.

``pipeline25d sample themed OUT`` writes ``themed.city.json`` (quantised
vertices: mm), ``themed.gml``, their images ``themed_appearance/{summer,winter}.png`` and
``themed.truth.json``. The city: :data:`GRID` gabled LOD2 houses of
:mod:`~pipeline25d_lab.scenes.citygml_city` (each with its LOD1 box), every first long wall with
a window hole, all on the mm grid in EPSG:25832, so both files hold the same numbers. Themes
(CityJSON: texture and material themes of one name; CityGML: one Appearance each):

- ``summer``: walls textured from ``summer.png`` (citygml_city's atlas), roofs in a red
  material, except house 0 whose roofs are textured (the atlas's roof tiles);
- ``winter``: walls textured from ``winter.png`` (a grey facade with lit windows, snowy tiles),
  except house 1 (no appearance), roofs in a snow material; house 3 takes the snow material
  as a whole, its ground too (CityJSON ``material.winter.value``; CityGML an X3DMaterial whose
  target is its LOD2 solid's CompositeSurface, a valid X3DMaterial target: "gml:MultiSurface or
  descendants of gml:AbstractSurfaceType");
- ground surfaces and the last house: no appearance in either theme.

Writing only: nothing here imports a reader. The truth lists per theme which surfaces take which
image (with their rings) and which take which material colour.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np

from pipeline25d.core.atomic import write_bytes, write_json, write_text
from pipeline25d_lab.scenes.citygml_city import (
    GROUND_Z,
    HOUSE,
    SITES,
    Surface,
    _srs_name,
    _Writer,
    atlas_png,
    box_surfaces,
    house_surfaces,
)

CRS = "EPSG:25832"
GRID = (3, 2)                 # houses in x and y
SPACING = (16.0, 14.0)        # m between house origins
SCALE = 0.001                 # CityJSON transform scale: every coordinate is on the mm grid
THEMES = ("summer", "winter")
#: each theme's atlas colours (roof, roof line, wall, window) and grain for citygml_city.atlas_png
ATLAS_COLOURS = {"summer": dict(noise=12),
                 "winter": dict(roof=(236, 240, 246), roof_line=(150, 160, 176), wall=(150, 150, 158),
                                window_rgb=(250, 214, 90), noise=12)}
MATERIALS = {"summer": ("roof tiles", (0.7, 0.25, 0.15)), "winter": ("snow", (0.94, 0.95, 0.97))}
#: theme -> the house whose LOD2 geometry takes one material as a whole
WHOLE = {"winter": 3}
WINDOW = (4.0, 6.0, 2.0, 4.0)  # hole in the first long wall: along it from, to; height from, to (m)
NAME = "themed"


def houses(origin: tuple[float, float]) -> list[dict]:
    """The houses: id, LOD2 surfaces (UVs rounded to 1e-6, a window hole), LOD1 box surfaces."""
    out = []
    for i in range(GRID[0]):
        for j in range(GRID[1]):
            gid = f"h{i}_{j}"
            x, y = origin[0] + 4 + i * SPACING[0], origin[1] + 4 + j * SPACING[1]
            z = round(GROUND_Z + 0.25 * i + 0.125 * j, 3)
            lod2 = house_surfaces(gid, x, y, z)
            for s in lod2:
                s.rings = [np.round(r, 3) for r in s.rings]
                if s.uv is not None:
                    s.uv = np.round(s.uv, 6)
            _add_window(lod2[1], z)
            lod1 = box_surfaces(gid + "_l1", x, y, x + HOUSE["width"], y + HOUSE["depth"], z,
                                round(z + (HOUSE["eaves"] + HOUSE["ridge"]) / 2, 3))
            out.append({"id": gid, "lod2": lod2, "lod1": lod1})
    return out


def _add_window(wall: Surface, z: float) -> None:
    """A rectangular hole in the first long wall (from corner a along +x), its ring oriented
    against the wall's, with (s, t) by the wall's own mapping (s along, t = height / 2 ridge)."""
    x0, y0 = wall.rings[0][0][:2]
    a0, a1, h0, h1 = WINDOW
    pts = [(a0, h0), (a0, h1), (a1, h1), (a1, h0)]
    ring = np.array([(x0 + a, y0, z + h) for a, h in pts + pts[:1]])
    uv = np.array([(a / HOUSE["width"], h / (2 * HOUSE["ridge"])) for a, h in pts + pts[:1]])
    wall.rings.append(np.round(ring, 3))
    wall.hole_uv = (np.round(uv, 6),)


def looks(houses_: list[dict]) -> dict[str, dict[str, tuple]]:
    """Per theme, per LOD2 surface id: ("texture", theme image) or ("material", theme); absent: none."""
    out = {}
    for theme in THEMES:
        look = {}
        for k, h in enumerate(houses_):
            if k == len(houses_) - 1:
                continue                       # the last house: no appearance at all
            for s in h["lod2"]:
                if s.kind == "WallSurface" and not (theme == "winter" and k == 1):
                    look[s.gid] = ("texture", theme)
                elif s.kind == "RoofSurface":
                    look[s.gid] = ("texture", theme) if (theme == "summer" and k == 0) else ("material", theme)
                elif WHOLE.get(theme) == k:
                    look[s.gid] = ("material", theme)
        out[theme] = look
    return out


# --------------------------------------------------------------------------- CityGML


def citygml_text(houses_: list[dict], look: dict, images: dict[str, str]) -> str:
    """The city as CityGML 2.0: the houses, then one global Appearance per theme."""
    w = _Writer("2.0", CRS)
    pts = np.concatenate([r for h in houses_ for s in h["lod2"] for r in s.rings])
    parts = [w.head(pts.min(axis=0), pts.max(axis=0))]
    parts += [f"<core:cityObjectMember>{w.house(h['id'], h['lod2'], h['lod1'], shell_id=h['id'] + '_lod2')}"
              f"</core:cityObjectMember>\n" for h in houses_]
    surfaces = {s.gid: s for h in houses_ for s in h["lod2"]}
    for theme in THEMES:
        textured = [surfaces[g] for g, (kind, _) in look[theme].items() if kind == "texture"]
        whole = houses_[WHOLE[theme]] if theme in WHOLE else None
        own = {s.gid for s in whole["lod2"]} if whole else set()
        painted = [g for g, (kind, _) in look[theme].items() if kind == "material" and g not in own]
        painted += [whole["id"] + "_lod2"] if whole else []
        app = w.themed_appearance(theme, [(images[theme], textured)], [(MATERIALS[theme][1], painted)])
        parts.append(f"<app:appearanceMember>{app}</app:appearanceMember>\n")
    return "".join(parts) + "</core:CityModel>\n"


# --------------------------------------------------------------------------- CityJSON


class _Indexer:
    """A list of distinct items and the index of each (vertices, texture vertices)."""

    def __init__(self):
        self.items: list = []
        self.index: dict = {}

    def __call__(self, item) -> int:
        if item not in self.index:
            self.index[item] = len(self.items)
            self.items.append(item)
        return self.index[item]


def cityjson_doc(houses_: list[dict], look: dict, images: dict[str, str], translate: list[float]) -> dict:
    """The city as a CityJSON 2.0 object: quantised vertices, each house a Building with a LOD1
    and a LOD2 Solid, the LOD2 one with semantics and per-theme ``texture`` and ``material``."""
    verts, uvs = _Indexer(), _Indexer()

    def ring_ids(ring: np.ndarray) -> list[int]:
        return [verts(tuple(int(round((c - t) / SCALE)) for c, t in zip(p, translate))) for p in ring[:-1]]

    textures = {theme: k for k, theme in enumerate(THEMES)}
    materials = {theme: k for k, theme in enumerate(THEMES)}
    objects = {}
    for h in houses_:
        lod1 = {"type": "Solid", "lod": "1", "boundaries": [[[ring_ids(r) for r in s.rings] for s in h["lod1"]]]}
        kinds = sorted({s.kind for s in h["lod2"]})
        lod2 = {"type": "Solid", "lod": "2",
                "boundaries": [[[ring_ids(r) for r in s.rings] for s in h["lod2"]]],
                "semantics": {"surfaces": [{"type": k} for k in kinds],
                              "values": [[kinds.index(s.kind) for s in h["lod2"]]]}}
        if any(s.gid in look[t] for t in THEMES for s in h["lod2"]):
            lod2["texture"], lod2["material"] = {}, {}
            for theme in THEMES:
                tex, mat = [], []
                for s in h["lod2"]:
                    kind, which = look[theme].get(s.gid, (None, None))
                    if kind == "texture":
                        tex.append([[textures[which]] + [uvs(tuple(map(float, st))) for st in uv[:-1]]
                                    for uv in (s.uv, *s.hole_uv)])
                    else:
                        tex.append([[None]])
                    mat.append(materials[which] if kind == "material" else None)
                lod2["texture"][theme] = {"values": [tex]}
                whole = theme in WHOLE and houses_[WHOLE[theme]] is h
                lod2["material"][theme] = {"value": materials[theme]} if whole else {"values": [mat]}
        objects[h["id"]] = {"type": "Building", "geometry": [lod1, lod2]}
    return {
        "type": "CityJSON", "version": "2.0",
        "transform": {"scale": [SCALE] * 3, "translate": translate},
        "metadata": {"referenceSystem": _srs_name(CRS).replace("http://", "https://")},
        "CityObjects": objects,
        "vertices": [list(v) for v in verts.items],
        "appearance": {
            "materials": [{"name": MATERIALS[t][0], "diffuseColor": list(MATERIALS[t][1]), "transparency": 0.0}
                          for t in THEMES],
            "textures": [{"type": "PNG", "image": images[t], "wrapMode": "wrap"} for t in THEMES],
            "vertices-texture": [list(uv) for uv in uvs.items],
            "default-theme-texture": THEMES[0], "default-theme-material": THEMES[0]},
    }


# --------------------------------------------------------------------------- both


def write_themed_city(out_dir: str | Path, origin: tuple[float, float] | None = None) -> dict:
    """Write ``themed.city.json``, ``themed.gml``, the two atlases and ``themed.truth.json``
    into ``out_dir`` (houses from ``origin``, default citygml_city's Munich site); return the truth."""
    out = Path(out_dir)
    origin = tuple(origin) if origin is not None else SITES[CRS][1]
    (out / f"{NAME}_appearance").mkdir(parents=True, exist_ok=True)
    images = {t: f"{NAME}_appearance/{t}.png" for t in THEMES}
    for theme, path in images.items():
        write_bytes(out / path, atlas_png(**ATLAS_COLOURS[theme]))
    city = houses(origin)
    look = looks(city)
    write_text(out / f"{NAME}.gml", citygml_text(city, look, images))
    doc = cityjson_doc(city, look, images, [float(origin[0]), float(origin[1]), GROUND_Z])
    write_json(out / f"{NAME}.city.json", doc, indent=None)
    surfaces = {s.gid: s for h in city for s in h["lod2"]}
    truth = {"crs": CRS, "houses": [h["id"] for h in city],
             "surfaces": {g: {"kind": s.kind, "rings": [r.tolist() for r in s.rings]} for g, s in surfaces.items()},
             "themes": {t: {"textured": {images[t]: sorted(g for g, (k, _) in look[t].items() if k == "texture")},
                            "material": {g: list(MATERIALS[t][1]) for g, (k, _) in look[t].items() if k == "material"}}
                        for t in THEMES}}
    write_json(out / f"{NAME}.truth.json", truth)
    return truth


def main(argv: list[str] | None = None, prog: str | None = None) -> int:
    ap = argparse.ArgumentParser(prog=prog, description=__doc__.split("\n\n")[0])
    ap.add_argument("out", type=Path)
    args = ap.parse_args(argv)
    truth = write_themed_city(args.out)
    print(f"{args.out / (NAME + '.city.json')}, {args.out / (NAME + '.gml')}: {len(truth['houses'])} houses, "
          f"themes {', '.join(THEMES)}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
