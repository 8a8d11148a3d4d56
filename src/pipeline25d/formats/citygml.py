"""CityGML 1.0 / 2.0 / 3.0 reader, streaming.

The file is read with ``lxml.etree.iterparse``, one ``cityObjectMember`` at a time, each
cleared once drawn, so memory follows the mesh that is returned, not the XML tree.
Elements are matched by local name, so the three versions share one code path (3.0:
``core:boundary``, ``con:WallSurface``, ``core:lod2MultiSurface``, TextureAssociation).

Geometry: every ``lod{0-4}{Solid,MultiSurface,Geometry,FootPrint,RoofEdge}`` property and
``dem:tin`` (TINRelief: ``gml:TriangulatedSurface`` / ``gml:Tin``, the latter triangulated
by Delaunay when it has only control points). Each city object (Building, BuildingPart,
BuildingInstallation, TINRelief, Road ...) draws one LOD, with its thematic surfaces
(``boundedBy``/``boundary``: Wall/Roof/GroundSurface, openings, traffic and water surfaces):
``spec["lod"]``, else the highest below it, else the lowest (CityJSON's rule). Polygons
(with holes) are triangulated by :func:`~pipeline25d.formats.surfaces.triangulate_polygon`;
``xlink:href`` references to polygons in the same top-level object are followed and a
polygon reached twice (a ``lod2Solid`` referencing its ``boundedBy`` surfaces) is drawn
once, with the semantic class of its thematic surface. Interior features (rooms,
furniture) and implicit geometries are not drawn.

Coordinates: ``srsName`` (model envelope, else the first geometry; the input's ``crs``
key overrides) in the CRS's own axis order: geographic CRSs (EPSG:6697, 4326, 4979)
are written latitude first and come out as (lon, lat, h); projected ones are taken
easting first, as written in practice. ``srsDimension`` must be 3.

Appearances: ParameterizedTexture (``TexCoordList`` per ring, or ``TexCoordGen``) makes a
polygon textured (one :class:`MeshPart` per image; CityGML texture coordinates already
have t = 0 at the image bottom); X3DMaterial ``diffuseColor`` (and ``transparency``)
colours it, or every polygon of an aggregate it targets (a MultiSurface, a solid's
CompositeSurface: valid X3DMaterial targets; a polygon's own material wins); else the colour
class's palette colour. With several themes, ``spec["theme"]``
picks one (default: any, the first that targets a surface). Global appearances
(``appearanceMember`` of the CityModel, before or after the objects) are collected by a
first streaming pass that keeps only their targets, run only when the bytes
``appearanceMember`` occur in the file. A texture image that is missing or unreadable
is a :class:`~pipeline25d.core.errors.MissingTextureWarning` (once per image), which
:func:`pipeline25d.formats.load_district` turns into an error unless the input says
``missing_textures: untextured``; then its polygons fall back to colour.
Each top-level object's attributes (:mod:`pipeline25d.formats.citygml_attributes`; BuildingParts
folded into their building) travel on the parts as ``object_info``.
The renderer repeats textures; texture coordinates outside [0, 1]
under wrap modes other than ``wrap`` are clamped per vertex (an approximation).

Forgiving where CityGML tools are: an undeclared namespace prefix (an ADE element such as
``<energy:isHeated>`` whose ``xmlns:energy`` the file never declares) is recovered from outside
the geometry, with one warning per prefix naming the file and its first line; so are stray
characters (a bare ``&``, an undefined entity, a control character), with a warning naming the
line and the element. Inside the geometry, and any other XML error (truncated file, mismatched
tags, a stray ``<``), it refuses the file naming the line (:mod:`pipeline25d.formats.xml_defects`).
Texture images must lie inside the file's folder (:func:`~pipeline25d.formats.common.side_file`); one
that does not is not read and is a missing texture (``missing_textures``).

Over 400 lines for one job: one format's streaming reader (three CityGML versions, geometry,
appearances and terrain share its element walk).
"""

from __future__ import annotations

import mmap
import re
import warnings
from collections import Counter
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from pipeline25d.core.crs import is_geographic, parse_crs
from pipeline25d.core.errors import CRSError, InputFileError
from pipeline25d.core.mesh import MeshPart
from pipeline25d.formats.attributes import Limiter
from pipeline25d.formats.buildings import Buildings, is_building
from pipeline25d.formats.citygml_attributes import GML_ID, city_object_info
from pipeline25d.formats.citygml_attributes import local_name as _local
from pipeline25d.formats.common import Detail, Loaded, crs_name, texture_file, texture_image
from pipeline25d.formats.surfaces import (
    GROUND_TYPES,
    OBJECT_CLASS,
    PALETTE,
    SEMANTIC_CLASS,
    normal_classes,
    pick_lod,
    triangulate_polygon,
)
from pipeline25d.formats.xml_defects import XmlDefects, recovered_name

XLINK_HREF = "{http://www.w3.org/1999/xlink}href"
_LOD_PROPERTY = re.compile(r"lod([0-4])(Solid|MultiSurface|Geometry|FootPrint|RoofEdge)$")
_POLYGONS = frozenset({"Polygon", "Triangle", "Rectangle", "PolygonPatch"})
#: GML elements under a geometry property that hold no surfaces (cavities of solids included)
_NOT_SURFACES = frozenset({"interior", "LineString", "Curve", "MultiCurve", "CompositeCurve", "Point",
                           "MultiPoint", "OrientableCurve", "LineStringSegment", "controlPoint"})
#: properties whose features are not drawn: indoor features (2.0 interior*, 3.0 rooms/furniture)
_SKIPPED_PROPERTIES = frozenset({"appearance", "buildingRoom", "buildingFurniture", "buildingConstructiveElement",
                                 "interiorRoom", "interiorFurniture", "interiorBuildingInstallation",
                                 "interiorBridgeInstallation", "interiorTunnelInstallation"})
_CITYGML_NS = re.compile(r"http://www\.opengis\.net/citygml/(\d\.\d)$")
#: CityGML-only ground types besides the CityJSON ones, for a file without TINRelief
_GROUND_TYPES = GROUND_TYPES | {"Square", "Track", "TransportationComplex"}
_M_PER_DEGREE = 111_320.0  # only for triangulating and classifying geographic coordinates


def read_citygml(path: Path, spec: dict, detail: Detail = Detail()) -> Loaded:
    """Reader contract (:mod:`pipeline25d.formats`): triangulated, textured/coloured CityGML
    in its own CRS (``spec["crs"]``, else ``srsName``), LOD ``spec["lod"]``, theme ``spec["theme"]``."""
    reader = _Reader(Path(path), spec, textures=True)
    reader.run(lambda t: True)
    return reader.loaded(lambda t: True)


def read_citygml_terrain(path: Path, spec: dict) -> Loaded:
    """The file's ground: its TINRelief objects, or without any, its ground-level objects
    (:data:`~pipeline25d.formats.surfaces.GROUND_TYPES`, Square, Track, TransportationComplex)."""
    reader = _Reader(Path(path), spec, textures=False)
    reader.run(lambda t: t == "TINRelief" or t in _GROUND_TYPES)
    has_tin = "TINRelief" in reader.types_drawn
    return reader.loaded(lambda t: t == "TINRelief" if has_tin else t in _GROUND_TYPES)


def _horizontal(crs_name: str):
    crs = parse_crs(crs_name)
    return crs.sub_crs_list[0] if crs.is_compound else crs


def latitude_first(crs_name: str) -> bool:
    """Whether coordinates in ``crs_name``'s own axis order give latitude first (EPSG:6697, 4326, 4979)."""
    horizontal = _horizontal(crs_name)
    return horizontal.is_geographic and horizontal.axis_info[0].direction.lower() in ("north", "south")


def is_citygml(head: bytes) -> bool:
    """Whether the first bytes of a file look like a CityGML CityModel."""
    return b"CityModel" in head and b"opengis.net/citygml/" in head


# --------------------------------------------------------------------------- appearances


@dataclass
class _Texture:
    """Where one textured polygon takes its colours: an image and per ring coordinates."""

    image: str                                   # resolved image path
    rings: dict[str, str] = field(default_factory=dict)   # ring gml:id -> "s t s t ..." text
    generator: np.ndarray | None = None          # TexCoordGen worldToTexture (3, 4)
    clamp: bool = False                          # wrap mode other than "wrap"


@dataclass
class _Appearances:
    """Texture and material targets by polygon gml:id; first come, first kept."""

    textures: dict[str, _Texture] = field(default_factory=dict)
    materials: dict[str, tuple[int, int, int, int]] = field(default_factory=dict)


#: GML elements whose text or children make a drawn surface or its texture coordinates
_GEOMETRY_PARTS = frozenset({
    "Polygon", "LinearRing", "Ring", "posList", "pos", "coordinates", "coord", "exterior", "interior",
    "outerBoundaryIs", "innerBoundaryIs", "surfaceMember", "surfaceMembers", "MultiSurface", "CompositeSurface",
    "Solid", "Shell", "CompositeSolid", "MultiSolid", "solidMember", "Triangle", "TriangulatedSurface", "Tin",
    "trianglePatches", "patches", "OrientableSurface", "baseSurface", "Surface", "PolygonPatch", "ImplicitGeometry",
    "relativeGMLGeometry", "transformationMatrix", "referencePoint", "textureCoordinates", "TexCoordList"})


def _in_geometry(elem) -> bool:
    """Whether ``elem`` is part of a geometry (a GML geometry element or a lod*Geometry/Solid/... property)."""
    tag = elem.tag
    if not isinstance(tag, str):
        return False
    name = _local(tag)
    return name in _GEOMETRY_PARTS or (name.startswith("lod") and name[3:4].isdigit())


def _child_text(elem, name: str) -> str | None:
    for child in elem:
        if _local(child.tag) == name:
            return (child.text or "").strip()
    return None


def _target_id(uri: str | None) -> str:
    return (uri or "").strip().lstrip("#")


# --------------------------------------------------------------------------- reader


class _Reader:
    """One streaming read of a CityGML file into colour-class and texture groups."""

    def __init__(self, path: Path, spec: dict, textures: bool):
        self.path = path
        self.lod = spec.get("lod")
        self.theme = spec.get("theme")
        self.textures = textures
        self.crs: str | None = spec.get("crs")
        self.crs_fixed = self.crs is not None    # the input's crs key beats every srsName
        self.srs_names: dict[str, str] = {}     # srsName text -> resolved CRS name
        self.swap: bool | None = None            # latitude first (decided with the CRS)
        self.swapped_axes = spec.get("axis_order") == "swapped"     # the file writes the CRS's axes exchanged
        self.scale = np.ones(3)                  # to near-metres, for triangulation and normals
        self.global_app = _Appearances()
        self.images: dict[str, bytes | None] = {}
        self.groups: dict[tuple[str, str], _Group] = {}
        self.keys: list[str] = []                  # top-level city objects drawn: gml:id, else type#n
        self.info: dict[str, dict] = {}            # key -> its type and attributes (citygml_attributes)
        self.limiter = Limiter(path)
        self.types_drawn: set[str] = set()
        self.issues: Counter = Counter()
        self.version: str | None = None
        self.xml = XmlDefects(path)
        self.image_paths: dict[str, str] = {}   # imageURI -> confined, resolved image path (else the URI)
        self.image_problems: dict[str, str] = {}   # image -> why it is not read (outside the folder, remote)

    # -- passes ------------------------------------------------------------
    def run(self, keep) -> None:
        """Stream the file: global appearances first when it has any, then the objects."""
        if not self.path.is_file():
            raise InputFileError(self.path, "CityGML file is missing")
        if self.textures and self._has_global_appearances():
            self._stream(("appearanceMember", "cityObjectMember"), self._global_appearance)
        self._stream(("cityObjectMember", "featureMember", "Envelope"), lambda el: self._member(el, keep))
        self.xml.warn(stacklevel=4)
        self.limiter.warn(stacklevel=3)
        for issue, n in sorted(self.issues.items()):
            warnings.warn(f"{self.path}: {issue} ({n}x)", stacklevel=3)

    def _has_global_appearances(self) -> bool:
        with open(self.path, "rb") as f:
            try:
                with mmap.mmap(f.fileno(), 0, access=mmap.ACCESS_READ) as mm:
                    return mm.find(b"appearanceMember") >= 0
            except ValueError:  # empty file: the parse says what is wrong
                return False

    def _stream(self, names: tuple[str, ...], handle) -> None:
        from lxml import etree

        self.xml.start()
        try:
            # our own handle, closed on every exit: iterparse's own stays open until collected;
            # recover: namespace defects are read on, every other error refuses (self.xml.check)
            with open(self.path, "rb") as source:
                self._iterate(etree.iterparse(source, events=("end",), tag=[f"{{*}}{n}" for n in names],
                                              huge_tree=True, resolve_entities=False, no_network=True,
                                              remove_comments=True, recover=True), handle)
        except etree.XMLSyntaxError as exc:
            raise InputFileError(self.path, f"malformed XML at line {exc.lineno}: {exc.msg}") from None
        except InputFileError:
            raise
        except OSError as exc:
            raise InputFileError(self.path, f"cannot read CityGML file: {exc}") from None

    def _iterate(self, context, handle) -> None:
        """Hand every streamed element to ``handle``, then free it and what came before it."""
        for _, elem in context:
            self.xml.check(context)
            self.xml.place(elem, _in_geometry)
            if self.version is None:
                self._check_root(elem.getroottree().getroot())
            if _local(elem.tag) == "Envelope":
                self._envelope(elem)
                continue
            handle(elem)
            elem.clear()
            parent = elem.getparent()
            while parent is not None and elem.getprevious() is not None:
                del parent[0]
        self.xml.check(context)
        self.xml.place(None, _in_geometry)
        if self.version is None:
            self._check_root(context.root)

    def _check_root(self, root) -> None:
        if root is None or _local(root.tag) != "CityModel":
            raise InputFileError(self.path, f"not a CityGML CityModel (root element "
                                            f"{_local(getattr(root, 'tag', '')) or 'none'})")
        ns = root.tag[1:root.tag.find("}")] if root.tag.startswith("{") else ""
        match = _CITYGML_NS.match(ns)
        if not match:
            raise InputFileError(self.path, f"CityModel in namespace {ns!r}: not CityGML 1.0, 2.0 or 3.0")
        self.version = match.group(1)

    def _envelope(self, elem) -> None:
        if not self.crs and elem.get("srsName"):
            self._set_crs(elem.get("srsName"), elem)

    # -- CRS ---------------------------------------------------------------
    def _resolve(self, srs_name: str, elem) -> str:
        if srs_name not in self.srs_names:
            name = crs_name(srs_name)
            try:
                parse_crs(name)
            except CRSError:
                raise InputFileError(self.path, f"line {elem.sourceline}: unknown srsName {srs_name!r} "
                                                f"(set the input's crs key)") from None
            self.srs_names[srs_name] = name
        return self.srs_names[srs_name]

    def _set_crs(self, srs_name: str, elem) -> None:
        self.crs = self._resolve(srs_name, elem)

    def _check_geometry_crs(self, srs_name: str | None, elem) -> None:
        """First geometry sets the file's CRS; later ones must agree (unless crs is given)."""
        if srs_name and not self.crs_fixed:
            name = self._resolve(srs_name, elem)
            if self.crs is None:
                self.crs = name
            elif name != self.crs and parse_crs(name) != parse_crs(self.crs):
                raise InputFileError(self.path, f"line {elem.sourceline}: srsName {srs_name!r} differs from the "
                                                f"file's {self.crs} (one CRS per file is supported)")
        if self.swap is None:
            self._decide_axes()

    def _decide_axes(self) -> None:
        geographic = self.crs is not None and is_geographic(self.crs)
        self.swap = self.crs is not None and latitude_first(self.crs) != (geographic and self.swapped_axes)
        if geographic:
            self.scale = None  # set from the first vertex (cos latitude)

    # -- appearances -------------------------------------------------------
    def _global_appearance(self, elem) -> None:
        if _local(elem.tag) == "appearanceMember":
            for app in elem.iter("{*}Appearance"):
                self._appearance(app, self.global_app)

    def _appearance(self, app, table: _Appearances) -> None:
        if self.theme is not None and _child_text(app, "theme") != self.theme:
            return
        for member in app:
            if _local(member.tag) not in ("surfaceDataMember", "surfaceData"):
                continue
            if member.get(XLINK_HREF) is not None and not len(member):
                self.issues["shared surface data by xlink:href not drawn"] += 1
            for data in member:
                kind = _local(data.tag)
                if kind == "ParameterizedTexture":
                    self._parameterized_texture(data, table)
                elif kind == "X3DMaterial":
                    self._material(data, table)
                elif kind == "GeoreferencedTexture":
                    self.issues["GeoreferencedTexture not drawn (surfaces keep their colour)"] += 1

    def _parameterized_texture(self, data, table: _Appearances) -> None:
        uri = _child_text(data, "imageURI")
        if not uri:
            return
        if uri not in self.image_paths:
            target, problem = texture_file(uri, self.path.parent, self.path.parent, self.path, "texture imageURI",
                                           url=False)
            self.image_paths[uri] = str(target.resolve()) if target is not None else uri
            if problem:
                self.image_problems[self.image_paths[uri]] = problem
        image = self.image_paths[uri]
        clamp = (_child_text(data, "wrapMode") or "none") != "wrap"
        for target in data.iter("{*}target"):
            with_uri = target.get("uri") is not None            # 2.0: <target uri="#poly">coords</target>
            poly = _target_id(target.get("uri") if with_uri else target.text)
            holder = target if with_uri else target.getparent()  # 3.0: TextureAssociation
            if not poly or poly in table.textures:
                continue
            tex = _Texture(image, clamp=clamp)
            for coords in holder.iter("{*}TexCoordList"):
                texts = [(tc.get("ring"), tc.text or "") for tc in coords.iter("{*}textureCoordinates")]
                rings = [r.text for r in coords.iter("{*}ring")]   # 3.0: ring elements in order
                for i, (ring, text) in enumerate(texts):
                    ring = ring if ring is not None else (rings[i] if i < len(rings) else None)
                    tex.rings.setdefault(_target_id(ring), text)
            for gen in holder.iter("{*}TexCoordGen"):
                text = _child_text(gen, "worldToTexture") or ""
                tex.generator = self._numbers(text, gen, 12).reshape(3, 4)
            table.textures[poly] = tex

    def _material(self, data, table: _Appearances) -> None:
        diffuse = _child_text(data, "diffuseColor")
        rgb = self._numbers(diffuse, data, 3) if diffuse else np.full(3, 0.8)  # X3D default 0.8
        alpha = 1.0 - float(_child_text(data, "transparency") or 0.0)
        rgba = tuple(int(round(c)) for c in np.clip(np.append(rgb, alpha), 0, 1) * 255)
        for child in data:
            if _local(child.tag) == "target":
                table.materials.setdefault(_target_id(child.text), rgba)

    def _image(self, image: str) -> bytes | None:
        """Encoded image bytes, or None (warned once) when missing or unreadable."""
        if image not in self.images:
            self.images[image] = texture_image(self.path, image, self.image_problems.get(image))
        return self.images[image]

    # -- objects -----------------------------------------------------------
    def _member(self, member, keep) -> None:
        local_app = _Appearances()
        if self.textures:
            for app in member.iter("{*}Appearance"):
                self._appearance(app, local_app)
        for obj in member:
            if isinstance(obj.tag, str):
                _Member(self, obj, local_app, keep).draw()

    def loaded(self, keep) -> Loaded:
        """The groups of the object types ``keep`` accepts as MeshParts."""
        parts = [group.part(keep, tuple(self.keys), self.info) for _, group in sorted(self.groups.items())]
        return Loaded([p for p in parts if p is not None], self.crs)

    def group(self, kind: str, key: str) -> "_Group":
        if (kind, key) not in self.groups:
            self.groups[(kind, key)] = _Group(kind, key, self._image(key) if kind == "tex" else None)
        return self.groups[(kind, key)]

    # -- numbers -----------------------------------------------------------
    def _numbers(self, text: str, elem, multiple: int) -> np.ndarray:
        try:
            values = np.array(text.split(), dtype=np.float64)
        except ValueError:
            raise InputFileError(self.path, f"line {elem.sourceline}: non-numeric coordinates in "
                                            f"<{_local(elem.tag)}>") from None
        if len(values) % multiple:
            raise InputFileError(self.path, f"line {elem.sourceline}: {len(values)} numbers in "
                                            f"<{_local(elem.tag)}>, not a multiple of {multiple}")
        return values


class _Group:
    """Triangles of one colour class or one texture image, collected in blocks, per object type."""

    def __init__(self, kind: str, key: str, texture: bytes | None):
        self.kind, self.key, self.texture = kind, key, texture
        # object type -> [vertices, faces, colours/uvs, face objects] lists
        self.blocks: dict[str, list[list]] = {}
        self.pending: dict[str, list[list]] = {}

    def add(self, obj_type: str, vertices: np.ndarray, faces: np.ndarray, extra: np.ndarray, obj: int) -> None:
        """Triangles of the object ``obj`` (an index into the reader's keys)."""
        pend = self.pending.setdefault(obj_type, [[], [], [], []])
        for lst, arr in zip(pend, (vertices, faces, extra, np.full(len(faces), obj, dtype=np.int32))):
            lst.append(arr)
        if len(pend[0]) >= 256:
            self._compact(obj_type)

    def _compact(self, obj_type: str) -> None:
        pend = self.pending.pop(obj_type, None)
        if not pend or not pend[0]:
            return
        verts, faces, extra, objects = pend
        sizes = np.cumsum([0] + [len(v) for v in verts[:-1]])
        block = [np.concatenate(verts), np.concatenate([f + o for f, o in zip(faces, sizes)]),
                 np.concatenate(extra), np.concatenate(objects)]
        self.blocks.setdefault(obj_type, []).append(block)

    def part(self, keep, keys: tuple[str, ...], info: dict[str, dict]) -> MeshPart | None:
        for obj_type in list(self.pending):
            self._compact(obj_type)
        blocks = [b for t, bl in sorted(self.blocks.items()) if keep(t) for b in bl]
        if not blocks:
            return None
        sizes = np.cumsum([0] + [len(b[0]) for b in blocks[:-1]])
        vertices = np.concatenate([b[0] for b in blocks])
        faces = np.concatenate([b[1] + o for b, o in zip(blocks, sizes)])
        extra = np.concatenate([b[2] for b in blocks])
        ids = {"objects": keys, "face_objects": np.concatenate([b[3] for b in blocks]), "object_info": info}
        if self.kind == "tex":
            return MeshPart(vertices, faces, uv=extra, texture=self.texture, name=Path(self.key).name, **ids)
        return MeshPart(vertices, faces, colors=extra, name=self.key, **ids)


@dataclass
class _Candidate:
    lod: int
    semantic: str | None      # colour class of a thematic surface, None: the object's class
    prop: object              # the geometry property element


class _Member:
    """One top-level city object (with its parts, surfaces and references) being drawn."""

    def __init__(self, reader: _Reader, root, local_app: _Appearances, keep):
        self.r, self.root, self.app, self.keep = reader, root, local_app, keep
        self.ids: dict[str, object] | None = None
        self.obj = len(reader.keys)                # its faces' object: the member's gml:id, else type#n
        reader.keys.append(root.get(GML_ID[0]) or root.get(GML_ID[1]) or f"{_local(root.tag)}#{self.obj}")
        reader.info[reader.keys[-1]] = city_object_info(root, reader.limiter)

    def draw(self) -> None:
        objects, chosen = [self.root], []
        while objects:
            obj = objects.pop()
            own: list[_Candidate] = []
            self._walk(obj, None, own, objects)
            obj_type = _local(obj.tag)
            if not own or not self.keep(obj_type):
                continue
            lod = pick_lod([(c.lod,) for c in own], self.r.lod)
            cls = OBJECT_CLASS.get(obj_type, "other")
            chosen += [(c, obj_type, cls) for c in own if (c.lod,) == lod]
        # a polygon reached twice (solid + thematic surface) is drawn once, with its semantics
        chosen.sort(key=lambda item: item[0].semantic is None)
        found = [(poly, flip, held, cand.semantic or cls, obj_type)
                 for cand, obj_type, cls in chosen for poly, flip, held in self._polygons(cand.prop)]
        inherited = self._aggregate_materials(found)
        drawn: set[str] = set()
        for poly, flip, held, cls, obj_type in found:
            key = poly.get(GML_ID[0]) or poly.get(GML_ID[1])
            if key is not None:
                if key in drawn:
                    continue
                drawn.add(key)
            rgba = self._material(key) or (inherited.get(key) if key is not None else self._held_material(held))
            self._draw(poly, flip, key, cls, obj_type, rgba)

    def _material(self, gid: str | None):
        """RGBA of the X3DMaterial (of the theme drawn) targeting ``gid``, local before global; None."""
        return self.app.materials.get(gid) or self.r.global_app.materials.get(gid)

    def _held_material(self, held: tuple[str, ...]):
        """RGBA of the innermost aggregate in ``held`` (gml:ids enclosing a polygon) a material targets."""
        return next((m for gid in reversed(held) if (m := self._material(gid))), None)

    def _aggregate_materials(self, found: list) -> dict:
        """{polygon gml:id: RGBA} for polygons inside an aggregate an X3DMaterial targets (CityGML 2.0:
        "gml:MultiSurface or descendants of gml:AbstractSurfaceType are valid targets", e.g. a
        thematic surface's MultiSurface or a solid's CompositeSurface), whichever path reaches them."""
        out: dict = {}
        for poly, _, held, _, _ in found:
            key = poly.get(GML_ID[0]) or poly.get(GML_ID[1])
            if held and key is not None and key not in out and (rgba := self._held_material(held)):
                out[key] = rgba
        return out

    def _walk(self, feature, semantic: str | None, own: list, objects: list) -> None:
        """Collect ``feature``'s geometry properties into ``own``; child city objects into ``objects``."""
        for prop in feature:
            name = _local(prop.tag)
            match = _LOD_PROPERTY.match(name)
            if match:
                own.append(_Candidate(int(match.group(1)), semantic, prop))
            elif name == "tin":
                own.append(_Candidate(int(float(_child_text(feature, "lod") or 0)), semantic, prop))
            elif name.startswith("lod") and name.endswith("ImplicitRepresentation"):
                self.r.issues["implicit geometries (lod*ImplicitRepresentation) not drawn"] += 1
            elif name not in _SKIPPED_PROPERTIES:
                for child in prop:
                    child_name = _local(child.tag)
                    if not child_name[:1].isupper() or child.tag.startswith("{http://www.opengis.net/gml"):
                        continue
                    if child_name in SEMANTIC_CLASS:
                        self._walk(child, SEMANTIC_CLASS[child_name], own, objects)
                    else:
                        objects.append(child)

    # -- geometry ----------------------------------------------------------
    def _polygons(self, prop):
        """(polygon element, flipped, gml:ids of the aggregates around it on the way, outermost first)
        under a geometry property, references followed; the ids only where materials are read."""
        track = bool(self.app.materials or self.r.global_app.materials)
        stack, seen = [(prop, False, ())], set()
        while stack:
            elem, flip, held = stack.pop()
            for child in reversed(elem):
                name = self._name(child)
                if not name or name in _NOT_SURFACES:
                    continue
                href = child.get(XLINK_HREF)
                if href is not None and not len(child):
                    target = self._ref(href)
                    if target is None or href in seen:
                        self.r.issues["unresolved xlink:href (outside its top-level object) not drawn"] += \
                            target is None
                        continue
                    seen.add(href)
                    child, name = target, self._name(target)
                if name in _POLYGONS:
                    yield child, flip, held
                elif name == "Tin" and not any(_local(c.tag) in ("trianglePatches", "patches") for c in child):
                    yield child, flip, held
                else:
                    gid = (child.get(GML_ID[0]) or child.get(GML_ID[1])) if track else None
                    inner = held + (gid,) if gid else held
                    if name == "OrientableSurface":
                        stack.append((child, flip ^ (child.get("orientation") == "-"), inner))
                    else:
                        stack.append((child, flip, inner))

    def _name(self, elem) -> str:
        """Local name of a geometry element; InputFileError when it or one of its attributes kept
        an undeclared namespace prefix (the parser recovered it: its meaning is lost)."""
        if self.r.xml.recovered:
            bad = recovered_name(elem)
            if bad:
                raise InputFileError(self.r.path, f"line {elem.sourceline}: {bad} inside a geometry has an "
                                                  "undeclared namespace prefix (its polygons cannot be read)")
        return _local(elem.tag)

    def _ref(self, href: str):
        if self.ids is None:
            self.ids = {}
            for elem in self.root.iter():
                gid = elem.get(GML_ID[0]) or elem.get(GML_ID[1])
                if gid is not None:
                    self.ids[gid] = elem
        return self.ids.get(_target_id(href))

    def _frame(self, elem) -> tuple[str | None, int]:
        """srsName and srsDimension in force at ``elem`` (inherited from its ancestors)."""
        srs, dim = None, None
        node = elem
        while node is not None and (srs is None or dim is None):
            srs = srs or node.get("srsName")
            dim = dim or node.get("srsDimension")
            node = node.getparent()
        return srs, int(dim or 3)

    def _ring(self, ring) -> np.ndarray:
        """(k, 3) float64 coordinates of a LinearRing (posList, pos or coordinates), file order."""
        srs, dim = self._frame(ring)
        self.r._check_geometry_crs(srs, ring)
        texts = []
        for child in ring:
            name = self._name(child)
            if name == "posList":
                dim = int(child.get("srsDimension") or dim)
                texts.append(child.text or "")
            elif name == "pos":
                texts.append(child.text or "")
            elif name == "coordinates":
                texts.append((child.text or "").replace(",", " "))
        if dim != 3:
            raise InputFileError(self.r.path, f"line {ring.sourceline}: srsDimension {dim}; CityGML "
                                              f"geometry must be 3D")
        return self.r._numbers(" ".join(texts), ring, 3).reshape(-1, 3)

    def _rings(self, poly) -> list[tuple[str | None, np.ndarray]]:
        """(ring gml:id, coordinates without the closing repeat) of a polygon, exterior first."""
        out = []
        for side in poly:
            name = self._name(side)
            if name not in ("exterior", "interior"):
                continue
            for ring in side:
                if self._name(ring) != "LinearRing":
                    self.r.issues[f"{_local(ring.tag)} rings (curves) not drawn"] += 1
                    continue
                pts = self._ring(ring)
                if len(pts) > 1 and np.array_equal(pts[0], pts[-1]):
                    pts = pts[:-1]
                entry = (ring.get(GML_ID[0]) or ring.get(GML_ID[1]), pts)
                if name == "exterior":
                    out.insert(0, entry)
                else:
                    out.append(entry)
        return out

    def _draw(self, poly, flip: bool, key: str | None, cls: str, obj_type: str, rgba=None) -> None:
        """Triangulate one polygon into its texture's group, else its class's in ``rgba`` (its
        material) or the class colour."""
        if _local(poly.tag) == "Tin":
            self._draw_tin(poly, flip, cls, obj_type)
            return
        rings = self._rings(poly)
        if not rings or len(rings[0][1]) < 3:
            return
        file_pts = np.concatenate([p for _, p in rings])
        verts = self._xy(file_pts)
        ends = np.cumsum([len(p) for _, p in rings])
        index = [list(range(a, b)) for a, b in zip(np.r_[0, ends[:-1]], ends)]
        faces, normal = triangulate_polygon(index, verts * self._scale(verts))
        if not len(faces):
            return
        if flip:
            faces, normal = faces[:, ::-1], -normal
        if cls == "building":
            cls = normal_classes(normal[None])[0]
        uv, texture = self._uv(key, rings, file_pts)
        used, faces = np.unique(faces, return_inverse=True)
        faces = faces.reshape(-1, 3)
        if texture is not None:
            self.r.group("tex", texture).add(obj_type, verts[used], faces, uv[used], self.obj)
        else:
            colors = np.tile(np.asarray(rgba or PALETTE[cls], dtype=np.uint8), (len(used), 1))
            self.r.group("col", cls).add(obj_type, verts[used], faces, colors, self.obj)
        self.r.types_drawn.add(obj_type)

    def _draw_tin(self, tin, flip: bool, cls: str, obj_type: str) -> None:
        """A gml:Tin given by control points only: their Delaunay triangulation in plan."""
        from scipy.spatial import Delaunay

        texts = [c for c in tin.iter("{*}posList", "{*}pos")]
        srs, _ = self._frame(tin)
        self.r._check_geometry_crs(srs, tin)
        pts = self.r._numbers(" ".join(t.text or "" for t in texts), tin, 3).reshape(-1, 3)
        if len(pts) < 3:
            return
        verts = self._xy(pts)
        faces = Delaunay(verts[:, :2] * self._scale(verts)[:2]).simplices.astype(np.int64)
        p = verts[faces]
        up = np.cross(p[:, 1] - p[:, 0], p[:, 2] - p[:, 0])[:, 2] < 0
        faces[up] = faces[up][:, ::-1]   # counter-clockwise seen from above
        colors = np.tile(np.asarray(PALETTE[cls], dtype=np.uint8), (len(verts), 1))
        self.r.group("col", cls).add(obj_type, verts, faces[:, ::-1] if flip else faces, colors, self.obj)
        self.r.types_drawn.add(obj_type)

    def _xy(self, pts: np.ndarray) -> np.ndarray:
        """File-order coordinates as (x/lon, y/lat, z)."""
        return pts[:, [1, 0, 2]] if self.r.swap else pts

    def _scale(self, verts: np.ndarray) -> np.ndarray:
        """Per-axis factors to near-metres (geographic CRS: degrees scaled at the file's latitude)."""
        if self.r.scale is None:
            lat = np.radians(verts[0, 1])
            self.r.scale = np.array([_M_PER_DEGREE * np.cos(lat), _M_PER_DEGREE, 1.0])
        return self.r.scale

    def _uv(self, key: str | None, rings, file_pts: np.ndarray) -> tuple[np.ndarray | None, str | None]:
        """Texture coordinates of a polygon's vertices and its image, or (None, None)."""
        if key is None or not self.r.textures:
            return None, None
        tex = self.app.textures.get(key) or self.r.global_app.textures.get(key)
        if tex is None or self.r._image(tex.image) is None:
            return None, None
        if tex.generator is not None:
            h = np.column_stack([file_pts, np.ones(len(file_pts))]) @ tex.generator.T
            uv = h[:, :2] / np.where(h[:, 2:3] == 0, 1.0, h[:, 2:3])
        else:
            pieces = []
            for ring_id, pts in rings:
                text = tex.rings.get(ring_id or "")
                if text is None:
                    self.r.issues["textured polygons with a ring lacking texture coordinates drawn in colour"] += 1
                    return None, None
                try:
                    st = np.array(text.split(), dtype=np.float64).reshape(-1, 2)
                except ValueError:
                    st = np.empty((0, 2))
                if len(st) == len(pts) + 1:
                    st = st[:-1]
                if len(st) != len(pts):
                    self.r.issues["texture coordinates not matching their ring drawn in colour"] += 1
                    return None, None
                pieces.append(st)
            uv = np.concatenate(pieces)
        if tex.clamp:
            uv = np.clip(uv, 0.0, 1.0)
        return uv, tex.image


def read_citygml_buildings(path: Path, spec: dict) -> Buildings:
    """The building objects of a CityGML file, in its own CRS, untextured: parts by colour class
    (see :mod:`pipeline25d.formats.buildings`)."""
    reader = _Reader(Path(path), spec, textures=False)
    reader.run(lambda t: True)
    others = any(not is_building(t) and t != "TINRelief" and t not in _GROUND_TYPES for t in reader.types_drawn)
    return Buildings(reader.loaded(is_building), others)
