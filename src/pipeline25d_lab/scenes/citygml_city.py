"""A generated CityGML city with exact truth: textured LOD2 gabled houses (each with a LOD1
box too), LOD1 courtyard blocks (a roof with a hole, X3DMaterial walls) and a TINRelief.

``python -m pipeline25d_lab.scenes.citygml_city resources/citygml`` writes ``city.gml`` (CityGML 2.0,
EPSG:25832), its texture atlas ``city_appearance/atlas.png`` and ``truth.json``, the scene of
``config/examples/citygml.yaml``. Options: ``--version 3.0``, ``--crs EPSG:6697`` (the same
city near Tokyo, written latitude first), ``--appearance local|start|end``, ``--grid NX NY``
(``--grid 320 320`` makes about 100k buildings, ~1 GB), ``--ade`` (ADE attributes under undeclared
prefixes). ``--memory SIZES`` measures the peak
RSS of reading files of growing size (:func:`memory_benchmark`).

The atlas's top half (v in [0.5, 1]) is roof tiles (reds), its bottom half facades (light
walls, dark blue windows): a wrongly flipped v shows at once.

Over 400 lines for one job: one generated CityGML scene (houses, blocks, TIN, appearances).
"""

from __future__ import annotations

import argparse
import io
import json
import math
import subprocess
import sys
from dataclasses import dataclass
from pathlib import Path

import numpy as np

#: where the city lies: a projected CRS in metres for the truth and its origin in it
SITES = {"EPSG:25832": ("EPSG:25832", (691000.0, 5335000.0)),   # Munich, written as is
         "EPSG:6697": ("EPSG:6677", (-10400.0, -35600.0))}      # Tokyo, written as JGD2011 lat/lon/h
GROUND_Z = 500.0
SLOPE = (0.02, 0.01)          # terrain: z = GROUND_Z + SLOPE . (x, y) - origin
HOUSE = dict(width=10.0, depth=8.0, eaves=6.0, ridge=9.0)     # ridge along the width
BLOCK = dict(size=20.0, hole=8.0, height=12.0)
SPACING = 30.0                # one lot per 30 m, houses and blocks alternating
ATLAS = 256                   # atlas edge, px
ROOF_RGB, ROOF_LINE, WALL_RGB, WINDOW_RGB = (178, 58, 40), (120, 30, 24), (226, 214, 190), (40, 52, 96)
BLOCK_WALL = (0.2, 0.4, 0.6)  # X3DMaterial diffuseColor of the blocks' walls

NS = {
    "2.0": dict(core="http://www.opengis.net/citygml/2.0", bldg="http://www.opengis.net/citygml/building/2.0",
                dem="http://www.opengis.net/citygml/relief/2.0", app="http://www.opengis.net/citygml/appearance/2.0",
                gml="http://www.opengis.net/gml"),
    "3.0": dict(core="http://www.opengis.net/citygml/3.0", bldg="http://www.opengis.net/citygml/building/3.0",
                dem="http://www.opengis.net/citygml/relief/3.0", app="http://www.opengis.net/citygml/appearance/3.0",
                con="http://www.opengis.net/citygml/construction/3.0", gml="http://www.opengis.net/gml/3.2"),
}


@dataclass
class Surface:
    """One planar polygon: its id, semantic type, rings (closed, truth CRS) and atlas coordinates."""

    gid: str
    kind: str                      # RoofSurface, WallSurface, GroundSurface
    rings: list[np.ndarray]
    uv: np.ndarray | None = None   # exterior ring's (s, t), closed
    hole_uv: tuple = ()            # each interior ring's (s, t), closed (textured holes)


def terrain_z(x, y, origin) -> np.ndarray:
    return GROUND_Z + SLOPE[0] * (np.asarray(x) - origin[0]) + SLOPE[1] * (np.asarray(y) - origin[1])


def house_surfaces(gid: str, x: float, y: float, z: float) -> list[Surface]:
    """A gabled house: footprint width x depth from (x, y), base z, ridge along x, textured."""
    w, d, he, hr = HOUSE["width"], HOUSE["depth"], HOUSE["eaves"], HOUSE["ridge"]
    a, b, c, e = (x, y), (x + w, y), (x + w, y + d), (x, y + d)
    rz, my = z + hr, y + d / 2

    def ring(*pts):
        return np.array(list(pts) + [pts[0]], dtype=np.float64)

    out = [Surface(f"{gid}_ground", "GroundSurface", [ring((*a, z), (*e, z), (*c, z), (*b, z))])]
    long_walls = [((*a, z), (*b, z), (*b, z + he), (*a, z + he)), ((*c, z), (*e, z), (*e, z + he), (*c, z + he))]
    for k, pts in enumerate(long_walls):
        uv = np.array([[0, 0], [1, 0], [1, he / hr * 0.5], [0, he / hr * 0.5]])
        out.append(Surface(f"{gid}_wall{k}", "WallSurface", [ring(*pts)], np.vstack([uv, uv[:1]])))
    gables = [((*b, z), (*c, z), (*c, z + he), (x + w, my, rz), (*b, z + he)),
              ((*e, z), (*a, z), (*a, z + he), (x, my, rz), (*e, z + he))]
    for k, pts in enumerate(gables):
        uv = np.array([[0, 0], [1, 0], [1, he / hr * 0.5], [0.5, 0.5], [0, he / hr * 0.5]])
        out.append(Surface(f"{gid}_gable{k}", "WallSurface", [ring(*pts)], np.vstack([uv, uv[:1]])))
    roofs = [((*a, z + he), (*b, z + he), (x + w, my, rz), (x, my, rz)),
             ((*c, z + he), (*e, z + he), (x, my, rz), (x + w, my, rz))]
    for k, pts in enumerate(roofs):
        uv = np.array([[0, 0.5], [1, 0.5], [1, 1], [0, 1]])
        out.append(Surface(f"{gid}_roof{k}", "RoofSurface", [ring(*pts)], np.vstack([uv, uv[:1]])))
    return out


def box_surfaces(gid: str, x0: float, y0: float, x1: float, y1: float, z: float, top: float,
                 hole: tuple[float, float, float, float] | None = None) -> list[Surface]:
    """A LOD1 prism (optionally with a courtyard) as plain polygons, outward oriented."""
    def rect(ax, ay, bx, by, zz, ccw):
        pts = [(ax, ay, zz), (bx, ay, zz), (bx, by, zz), (ax, by, zz)]
        pts = pts if ccw else pts[::-1]
        return np.array(pts + [pts[0]], dtype=np.float64)

    def walls(ax, ay, bx, by, outward, tag):
        corners = [(ax, ay), (bx, ay), (bx, by), (ax, by)]
        corners = corners if outward else corners[::-1]
        out = []
        for k in range(4):
            (px, py), (qx, qy) = corners[k], corners[(k + 1) % 4]
            r = np.array([(px, py, z), (qx, qy, z), (qx, qy, top), (px, py, top), (px, py, z)])
            out.append(Surface(f"{gid}_{tag}{k}", "", [r]))
        return out

    holes_top = [rect(*hole, top, False)] if hole else []
    holes_bottom = [rect(*hole, z, True)] if hole else []
    out = [Surface(f"{gid}_bottom", "", [rect(x0, y0, x1, y1, z, False)] + holes_bottom),
           Surface(f"{gid}_top", "", [rect(x0, y0, x1, y1, top, True)] + holes_top)]
    out += walls(x0, y0, x1, y1, True, "w")
    if hole:
        out += walls(*hole, False, "c")
    return out


def tin_triangles(origin, extent: float, n: int) -> np.ndarray:
    """(2 n², 4, 3) closed triangles of the terrain plane over [origin, origin + extent]²."""
    g = np.linspace(0.0, extent, n + 1)
    tris = []
    for i in range(n):
        for j in range(n):
            x0, x1, y0, y1 = origin[0] + g[i], origin[0] + g[i + 1], origin[1] + g[j], origin[1] + g[j + 1]
            for t in (((x0, y0), (x1, y0), (x1, y1)), ((x0, y0), (x1, y1), (x0, y1))):
                pts = [(px, py, float(terrain_z(px, py, origin))) for px, py in t]
                tris.append(pts + [pts[0]])
    return np.array(tris, dtype=np.float64)


def atlas_png(roof=ROOF_RGB, roof_line=ROOF_LINE, wall=WALL_RGB, window_rgb=WINDOW_RGB, noise: int = 0) -> bytes:
    """The texture atlas: roof tiles on top, a facade with windows below (RGB colours of each);
    ``noise``: a seeded per-texel grain of +-noise levels (no two texels alike: a misplaced UV shows)."""
    from PIL import Image

    img = np.zeros((ATLAS, ATLAS, 3), np.uint8)
    half = ATLAS // 2
    img[:half] = roof
    img[:half][(np.arange(half) % 16) < 3] = roof_line          # tile rows
    img[half:] = wall
    rows, cols = np.mgrid[half:ATLAS, 0:ATLAS]
    window = ((cols % 32) >= 10) & ((cols % 32) < 22) & (((rows - half) % 42) >= 14) & (((rows - half) % 42) < 32)
    img[half:][window[:, :]] = window_rgb
    if noise:
        grain = np.random.default_rng(ATLAS).integers(-noise, noise + 1, img.shape)
        img = np.clip(img.astype(np.int64) + grain, 0, 255).astype(np.uint8)
    buf = io.BytesIO()
    Image.fromarray(img).save(buf, format="PNG")
    return buf.getvalue()


class _Writer:
    """CityGML text for one version and CRS (coordinates written in the file CRS's axis order)."""

    def __init__(self, version: str, crs: str):
        self.v, self.crs = version, crs
        self.truth_crs, self.origin = SITES[crs]
        self.geographic = crs != self.truth_crs
        self.gml_id = "gml:id"
        if self.geographic:
            from pyproj import Transformer

            self.to_file = Transformer.from_crs(self.truth_crs, crs, always_xy=True)

    def pos(self, pts: np.ndarray) -> str:
        if self.geographic:   # written in the CRS's axis order: latitude first
            lon, lat, h = self.to_file.transform(pts[:, 0], pts[:, 1], pts[:, 2])
            return " ".join(f"{a:.11f} {b:.11f} {c:.4f}" for a, b, c in zip(lat, lon, h))
        return " ".join(f"{a:.3f} {b:.3f} {c:.3f}" for a, b, c in pts)

    def polygon(self, s: Surface) -> str:
        rings = []
        for k, r in enumerate(s.rings):
            side = "exterior" if k == 0 else "interior"
            rings.append(f'<gml:{side}><gml:LinearRing gml:id="{s.gid}_r{k}"><gml:posList>{self.pos(r)}'
                         f'</gml:posList></gml:LinearRing></gml:{side}>')
        return f'<gml:Polygon gml:id="{s.gid}">{"".join(rings)}</gml:Polygon>'

    def multi_surface(self, surfaces: list[Surface]) -> str:
        return ("<gml:MultiSurface>" + "".join(f"<gml:surfaceMember>{self.polygon(s)}</gml:surfaceMember>"
                                               for s in surfaces) + "</gml:MultiSurface>")

    def solid(self, members: str, shell_id: str | None = None) -> str:
        shell = "gml:Shell" if self.v == "3.0" else "gml:CompositeSurface"
        gid = f' gml:id="{shell_id}"' if shell_id else ""
        return f"<gml:Solid><gml:exterior><{shell}{gid}>{members}</{shell}></gml:exterior></gml:Solid>"

    def prop(self, name: str) -> str:
        """Element name of a building property: 2.0 bldg:, 3.0 core:."""
        return ("core:" if self.v == "3.0" else "bldg:") + name

    def house(self, gid: str, lod2: list[Surface], lod1: list[Surface], appearance: str = "",
              shell_id: str | None = None) -> str:
        """A Building: LOD1 solid, LOD2 solid (its shell named ``shell_id``) of references to its
        thematic surfaces."""
        bounded = "core:boundary" if self.v == "3.0" else "bldg:boundedBy"
        surf_ns = "con" if self.v == "3.0" else "bldg"
        parts = [f'<bldg:Building gml:id="{gid}">']
        parts.append(appearance)
        lod1_members = "".join(f"<gml:surfaceMember>{self.polygon(s)}</gml:surfaceMember>" for s in lod1)
        parts.append(f"<{self.prop('lod1Solid')}>{self.solid(lod1_members)}</{self.prop('lod1Solid')}>")
        refs = "".join(f'<gml:surfaceMember xlink:href="#{s.gid}"/>' for s in lod2)
        parts.append(f"<{self.prop('lod2Solid')}>{self.solid(refs, shell_id)}</{self.prop('lod2Solid')}>")
        for s in lod2:
            ms = self.prop("lod2MultiSurface")
            parts.append(f'<{bounded}><{surf_ns}:{s.kind} gml:id="{s.gid}_s"><{ms}>{self.multi_surface([s])}'
                         f'</{ms}></{surf_ns}:{s.kind}></{bounded}>')
        parts.append("</bldg:Building>")
        return "".join(parts)

    def block(self, gid: str, surfaces: list[Surface]) -> str:
        members = "".join(f"<gml:surfaceMember>{self.polygon(s)}</gml:surfaceMember>" for s in surfaces)
        return (f'<bldg:Building gml:id="{gid}"><{self.prop("lod1Solid")}>{self.solid(members)}'
                f'</{self.prop("lod1Solid")}></bldg:Building>')

    def relief(self, tris: np.ndarray) -> str:
        patches = "gml:patches" if self.v == "3.0" else "gml:trianglePatches"
        tri = "".join(f"<gml:Triangle><gml:exterior><gml:LinearRing><gml:posList>{self.pos(t)}</gml:posList>"
                      f"</gml:LinearRing></gml:exterior></gml:Triangle>" for t in tris)
        return (f'<dem:ReliefFeature gml:id="relief"><dem:lod>2</dem:lod><dem:reliefComponent>'
                f'<dem:TINRelief gml:id="tin"><dem:lod>2</dem:lod><dem:tin><gml:TriangulatedSurface>'
                f"<{patches}>{tri}</{patches}></gml:TriangulatedSurface></dem:tin></dem:TINRelief>"
                f"</dem:reliefComponent></dem:ReliefFeature>")

    def appearance(self, textured: list[Surface], materials: list[str], image: str) -> str:
        """One Appearance: the atlas on ``textured`` surfaces, the block colour on ``materials`` ids."""
        return self.themed_appearance("rgbTexture", [(image, textured)], [(BLOCK_WALL, materials)] if materials else [])

    def themed_appearance(self, theme: str, textures: list[tuple[str, list[Surface]]],
                          materials: list[tuple[tuple, list[str]]]) -> str:
        """One Appearance of ``theme``: a ParameterizedTexture per (image, surfaces: their rings' (s, t)),
        an X3DMaterial per (diffuse RGB, polygon ids)."""
        data = "app:surfaceData" if self.v == "3.0" else "app:surfaceDataMember"
        out = [f"<app:Appearance><app:theme>{theme}</app:theme>"]
        for image, surfaces in textures:
            assoc = "".join(self._texture_association(s) for s in surfaces)
            out.append(f"<{data}><app:ParameterizedTexture><app:imageURI>{image}</app:imageURI>"
                       f"<app:wrapMode>wrap</app:wrapMode>{assoc}</app:ParameterizedTexture></{data}>")
        for rgb, ids in materials:
            targets = "".join(f"<app:target>#{m}</app:target>" for m in ids)
            rgb_text = " ".join(f"{c:g}" for c in rgb)
            out.append(f"<{data}><app:X3DMaterial><app:diffuseColor>{rgb_text}</app:diffuseColor>{targets}"
                       f"</app:X3DMaterial></{data}>")
        return "".join(out) + "</app:Appearance>"

    def _texture_association(self, s: Surface) -> str:
        """The texture target of one polygon: (s, t) per ring (exterior, then holes)."""
        rings = [(f"{s.gid}_r{k}", uv) for k, uv in enumerate((s.uv, *s.hole_uv))]
        if self.v == "3.0":
            coords = "".join(f"<app:textureCoordinates>{_st(uv)}</app:textureCoordinates>" for _, uv in rings)
            refs = "".join(f"<app:ring>#{ring}</app:ring>" for ring, _ in rings)
            return (f"<app:textureParameterization><app:TextureAssociation><app:target>#{s.gid}</app:target>"
                    f"<app:textureParameterization><app:TexCoordList>{coords}{refs}</app:TexCoordList>"
                    f"</app:textureParameterization></app:TextureAssociation></app:textureParameterization>")
        coords = "".join(f'<app:textureCoordinates ring="#{ring}">{_st(uv)}</app:textureCoordinates>'
                         for ring, uv in rings)
        return f'<app:target uri="#{s.gid}"><app:TexCoordList>{coords}</app:TexCoordList></app:target>'

    def head(self, lower: np.ndarray, upper: np.ndarray) -> str:
        ns = NS[self.v]
        decl = " ".join(f'xmlns:{k}="{u}"' for k, u in ns.items())
        box = np.array([lower, upper])
        if self.geographic:
            corners = self.pos(box).split()
            lo, hi = " ".join(corners[:3]), " ".join(corners[3:])
        else:
            lo, hi = (" ".join(f"{c:.3f}" for c in p) for p in box)
        return (f'<?xml version="1.0" encoding="UTF-8"?>\n<core:CityModel {decl} '
                f'xmlns:xlink="http://www.w3.org/1999/xlink">\n<gml:boundedBy><gml:Envelope srsName="'
                f'{_srs_name(self.crs)}" srsDimension="3"><gml:lowerCorner>{lo}</gml:lowerCorner>'
                f"<gml:upperCorner>{hi}</gml:upperCorner></gml:Envelope></gml:boundedBy>\n")


#: Application Domain Extension elements a real city file carries (PLATEAU's ``uro:``, the energy
#: ADE), written by ``write_city(ade=True)`` under prefixes the file never declares: an element and an
#: attribute in each building's attributes (outside its geometry), as CityGML tools meet them
ADE_PREFIXES = ("energy", "uro")


def ade_attributes(gid: str) -> str:
    """A building's ADE attributes under the undeclared :data:`ADE_PREFIXES` (deterministic per id)."""
    area = 80 + sum(map(ord, gid)) % 40
    return (f"<energy:isHeated>{'true' if len(gid) % 2 else 'false'}</energy:isHeated>"
            f'<uro:buildingDetails><uro:BuildingDetails uro:surveyYear="2020">'
            f'<uro:buildingRoofEdgeArea uom="m2">{area}</uro:buildingRoofEdgeArea>'
            f"</uro:BuildingDetails></uro:buildingDetails>")


def _with_ade(member: str, gid: str) -> str:
    """``member`` (one bldg:Building) with :func:`ade_attributes` right after its start tag."""
    start = f'<bldg:Building gml:id="{gid}">'
    return member.replace(start, start + ade_attributes(gid), 1)


def _st(uv: np.ndarray) -> str:
    return " ".join(f"{s:g} {t:g}" for s, t in uv)


def _srs_name(crs: str) -> str:
    auth, code = crs.split(":")
    return f"http://www.opengis.net/def/crs/{auth}/0/{code}"


def write_city(out_dir: str | Path, crs: str = "EPSG:25832", version: str = "2.0", appearance: str = "end",
               grid: tuple[int, int] = (4, 4), tin_cells: int = 8, name: str = "city", ade: bool = False) -> dict:
    """Write ``<name>.gml``, ``<name>_appearance/atlas.png`` and return (and write) the truth.

    ``grid``: lots in x and y, ``SPACING`` m apart, houses and courtyard blocks alternating
    (a chessboard). ``appearance``: global at the ``start`` or ``end`` of the file, or ``local``
    (inside each house). The TINRelief (``tin_cells``² squares, 2 triangles each) covers the lots.
    ``ade``: every building carries :func:`ade_attributes` under prefixes the file never declares
    (the file's geometry and appearances are the same as without).
    """
    out = Path(out_dir)
    (out / f"{name}_appearance").mkdir(parents=True, exist_ok=True)
    image = f"{name}_appearance/atlas.png"
    (out / image).write_bytes(atlas_png())
    w = _Writer(version, crs)
    origin = w.origin
    extent = SPACING * max(grid)
    textured, materials = [], []
    truth = {"crs": w.truth_crs, "file_crs": crs, "version": version, "houses": [], "blocks": [],
             "tin": {"triangles": 2 * tin_cells ** 2, "extent": extent, "origin": list(origin),
                     "slope": list(SLOPE), "z": GROUND_Z}}
    gml = out / f"{name}.gml"
    top = GROUND_Z + extent * (SLOPE[0] + SLOPE[1]) + BLOCK["height"] + 1
    with open(gml, "w", encoding="utf-8") as f:
        f.write(w.head(np.array([*origin, GROUND_Z - 1]), np.array([origin[0] + extent, origin[1] + extent, top])))
        app_text = ""
        for i in range(grid[0]):
            for j in range(grid[1]):
                x, y = origin[0] + i * SPACING + 5, origin[1] + j * SPACING + 5
                gid = f"b{i}_{j}"
                if (i + j) % 2 == 0:
                    z = float(terrain_z(x + HOUSE["width"] / 2, y + HOUSE["depth"] / 2, origin))
                    lod2 = house_surfaces(gid, x, y, z)
                    lod1 = box_surfaces(gid + "_l1", x, y, x + HOUSE["width"], y + HOUSE["depth"], z,
                                        z + (HOUSE["eaves"] + HOUSE["ridge"]) / 2)
                    tex = [s for s in lod2 if s.uv is not None]
                    local = ""
                    if appearance == "local":
                        tag = "core:appearance" if version == "3.0" else "app:appearance"
                        local = f"<{tag}>{w.appearance(tex, [], image)}</{tag}>"
                    else:
                        textured += tex
                    member = w.house(gid, lod2, lod1, local)
                    truth["houses"].append({"id": gid, "x": x, "y": y, "z": z})
                else:
                    s, hole = BLOCK["size"], BLOCK["hole"]
                    z = float(terrain_z(x + s / 2, y + s / 2, origin))
                    h0 = (s - hole) / 2
                    surfaces = box_surfaces(gid, x, y, x + s, y + s, z, z + BLOCK["height"],
                                            (x + h0, y + h0, x + h0 + hole, y + h0 + hole))
                    materials += [m.gid for m in surfaces if "_w" in m.gid or "_c" in m.gid]
                    member = w.block(gid, surfaces)
                    truth["blocks"].append({"id": gid, "x": x, "y": y, "z": z})
                member = _with_ade(member, gid) if ade else member
                f.write(f"<core:cityObjectMember>{member}</core:cityObjectMember>\n")
        app_member = "core:appearanceMember" if version == "3.0" else "app:appearanceMember"
        if appearance != "local" or materials:
            app_text = f"<{app_member}>{w.appearance(textured, materials, image)}</{app_member}>\n"
        f.write(f"<core:cityObjectMember>{w.relief(tin_triangles(origin, extent, tin_cells))}"
                f"</core:cityObjectMember>\n")
        if app_text and appearance != "start":
            f.write(app_text)
        f.write("</core:CityModel>\n")
    if app_text and appearance == "start":   # rewrite with the appearance before the objects
        text = gml.read_text(encoding="utf-8")
        cut = text.index("<core:cityObjectMember>")
        gml.write_text(text[:cut] + app_text + text[cut:], encoding="utf-8")
    (out / f"{name}.truth.json").write_text(json.dumps(truth, indent=1))
    return truth


_MEASURE = """
import sys, warnings
from pathlib import Path
warnings.simplefilter("ignore")
def vm(key):
    for line in open("/proc/self/status"):
        if line.startswith(key):
            return int(line.split()[1]) / 1024
from lxml import etree
from pipeline25d.formats.citygml import read_citygml
open("/proc/self/clear_refs", "w").write("5")   # peak RSS from here (fork inherits the parent's)
base = vm("VmRSS:")
if sys.argv[2] == "dom":
    n = sum(1 for _ in etree.parse(sys.argv[1]).iter())
else:
    parts = read_citygml(Path(sys.argv[1]), {}).parts
    n = sum(p.n_triangles for p in parts)
    mesh = sum(a.nbytes for p in parts for a in (p.vertices, p.faces, p.colors, p.uv) if a is not None) / 2**20
    print(mesh, end=" ")
print(base, vm("VmHWM:"), n)
"""


def memory_benchmark(out_dir: Path, sizes: list[int], dom_up_to: int = 80) -> list[dict]:
    """Peak RSS of reading generated cities of ``sizes`` lots per side, each in a fresh process
    (Linux: VmHWM, reset after the imports): the file size, the RSS the read added, the bytes of
    the mesh it returned, and (up to ``dom_up_to`` lots per side) a whole-tree ``etree.parse``."""
    rows = []
    for n in sizes:
        write_city(out_dir, grid=(n, n), tin_cells=4, name=f"mem{n}")
        path = out_dir / f"mem{n}.gml"
        run = [sys.executable, "-c", _MEASURE, str(path)]
        mesh, base, peak, tris = (float(v) for v in
                                  subprocess.run(run + ["stream"], capture_output=True, text=True,
                                                 check=True).stdout.split())
        size = path.stat().st_size / 2**20
        row = {"lots": n * n, "file_mb": round(size, 1), "read_mb": round(peak - base, 1),
               "mesh_mb": round(mesh, 1), "triangles": int(tris), "read_to_file": round((peak - base) / size, 3)}
        if n <= dom_up_to:
            _, dbase, dpeak, _ = (float(v) for v in
                                  ["0"] + subprocess.run(run + ["dom"], capture_output=True, text=True,
                                                         check=True).stdout.split())
            row["dom_mb"] = round(dpeak - dbase, 1)
            row["dom_to_file"] = round((dpeak - dbase) / size, 3)
        rows.append(row)
        path.unlink()
    return rows


def main(argv: list[str] | None = None, prog: str | None = None) -> int:
    ap = argparse.ArgumentParser(prog=prog, description=__doc__.split("\n\n")[0])
    ap.add_argument("out", type=Path)
    ap.add_argument("--crs", default="EPSG:25832", choices=sorted(SITES))
    ap.add_argument("--version", default="2.0", choices=sorted(NS))
    ap.add_argument("--appearance", default="end", choices=["start", "end", "local"])
    ap.add_argument("--grid", type=int, nargs=2, default=(4, 4))
    ap.add_argument("--ade", action="store_true", help="ADE attributes under undeclared prefixes (energy:, uro:)")
    ap.add_argument("--memory", type=int, nargs="+", help="lots per side of each benchmark file")
    args = ap.parse_args(argv)
    if args.memory:
        rows = memory_benchmark(args.out, args.memory)
        print(json.dumps(rows, indent=1))
        return 0
    truth = write_city(args.out, args.crs, args.version, args.appearance, tuple(args.grid),
                       tin_cells=max(2, math.ceil(max(args.grid) * 2)), ade=args.ade)
    print(f"{args.out / 'city.gml'}: {len(truth['houses'])} houses, {len(truth['blocks'])} blocks")
    return 0


if __name__ == "__main__":
    sys.exit(main())
