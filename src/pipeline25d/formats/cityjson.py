"""CityJSON 1.0 / 1.1 / 2.0 and CityJSONSeq (``.jsonl``) reader.

Each CityObject contributes the geometry of one LOD (its highest by default). Surfaces
are triangulated in float64 (:func:`~pipeline25d.formats.surfaces.triangulate_polygon`);
triangles pass straight through. Colours: :mod:`pipeline25d.formats.surfaces`. One
:class:`MeshPart` (RGBA vertex colours) per colour class; a surface with a material (of the
theme drawn) has its diffuse colour there. Textured surfaces: one MeshPart per image
(:mod:`pipeline25d.formats.cityjson_appearance`, which also picks the theme, ``spec["theme"]``).

Over 400 lines: the documents (a file, CityJSONSeq lines), their transforms, geometry templates
and the object walk share one model type, and the terrain and building readers read it too.
"""

from __future__ import annotations

import json
import warnings
from dataclasses import dataclass, field
from itertools import repeat
from pathlib import Path

import numpy as np

from pipeline25d.core.errors import CRSError, InputFileError
from pipeline25d.core.mesh import Mesh
from pipeline25d.formats.buildings import Buildings, is_building
from pipeline25d.formats.cityjson_appearance import Appearances
from pipeline25d.formats.common import Detail, Loaded, crs_name, in_scene, read_text
from pipeline25d.formats.surfaces import (  # noqa: F401  (PALETTE, triangulate_polygon: public here too)
    GROUND_TYPES,
    OBJECT_CLASS,
    PALETTE,
    SEMANTIC_CLASS,
    class_part,
    lod_key,
    normal_classes,
    pick_lod,
    triangulate_polygon,
)

_SURFACE_DEPTH = {"MultiSurface": 1, "CompositeSurface": 1, "Solid": 2, "MultiSolid": 3, "CompositeSolid": 3}


def read_cityjson(path: Path, spec: dict, detail: Detail = Detail()) -> Loaded:
    """Reader contract (:mod:`pipeline25d.formats`): triangulated, textured/coloured
    CityJSON/CityJSONSeq in its own CRS (``spec["crs"]``, else ``metadata.referenceSystem``),
    LOD ``spec["lod"]``, appearance theme ``spec["theme"]``."""
    model = _read_model(Path(path))
    return _build_parts(model, spec.get("crs"), spec.get("lod"), lambda t: True, spec.get("theme"))


def read_cityjson_terrain(path: Path, spec: dict) -> Loaded:
    """The terrain of a CityJSON file: its TINRelief objects.

    A file without TINRelief (3dfier output such as Delft models the ground as LandUse,
    Road, WaterBody ... polygons) yields its ground-level objects instead:
    :data:`GROUND_TYPES`. PlantCover is left out because 3dfier lifts it to vegetation
    height, which would bias terrain/GCP heights. Appearances are not read (class colours).
    """
    model = _read_model(Path(path))
    terrain = _terrain_types(model)
    return _build_parts(model, spec.get("crs"), None, lambda t: t in terrain, appearances=False)


def load_cityjson(path: str | Path, scene_crs: str, lod: str | None = None, src_crs: str | None = None,
                  include_terrain: bool = True, theme: str | None = None) -> Mesh:
    """Triangulated, textured/coloured CityJSON/CityJSONSeq in ``scene_crs`` (appearance ``theme``).

    ``lod``: per object the geometry of that LOD, else its highest LOD below it, else
    (so no object disappears) its lowest LOD; None takes each object's highest LOD.
    ``src_crs`` overrides ``metadata.referenceSystem``. ``include_terrain=False`` drops
    the objects :func:`read_cityjson_terrain` returns.
    """
    model = _read_model(Path(path))
    terrain = _terrain_types(model)
    keep = (lambda t: True) if include_terrain else (lambda t: t not in terrain)
    return in_scene(_build_parts(model, src_crs, lod, keep, theme), scene_crs, path)


def load_cityjson_terrain(path: str | Path, scene_crs: str, src_crs: str | None = None) -> Mesh:
    """:func:`read_cityjson_terrain` in ``scene_crs``."""
    return in_scene(read_cityjson_terrain(Path(path), {"crs": src_crs}), scene_crs, path)


def vertices_and_crs(path: str | Path, src_crs: str | None = None) -> tuple[np.ndarray, str]:
    """Every vertex of the file's documents (transform applied, float64) and their CRS
    (``src_crs``, else ``metadata.referenceSystem``): its extent without triangulating it."""
    model = _read_model(Path(path))
    return np.concatenate([c.base for c in model.chunks]), src_crs or source_crs(model.header, Path(path))


# --------------------------------------------------------------------------- reading


@dataclass
class _Chunk:
    """CityObjects sharing one vertex list (the whole file, or one CityJSONSeq feature)."""

    objects: dict
    base: np.ndarray
    appearance: dict | None = None                            # a CityJSONSeq feature's own
    placed: list[np.ndarray] = field(default_factory=list)   # GeometryInstance vertices, appended
    n_vertices: int = -1

    def __post_init__(self) -> None:
        self.n_vertices = len(self.base)

    def add_vertices(self, v: np.ndarray) -> int:
        """Append vertices (a placed GeometryInstance template); return the index of the first.

        Collected in a list and joined once (:attr:`vertices`): one concatenate per
        instance made a file with many instances quadratic in its vertex count."""
        start = self.n_vertices
        self.placed.append(v)
        self.n_vertices += len(v)
        return start

    @property
    def vertices(self) -> np.ndarray:
        """All vertices: the document's, then every placed instance's."""
        if self.placed:
            self.base = np.concatenate([self.base, *self.placed])
            self.placed = []
        return self.base


@dataclass
class _Model:
    path: Path
    header: dict
    chunks: list[_Chunk]
    templates: list
    template_vertices: np.ndarray


def _read_model(path: Path) -> _Model:
    """Read a CityJSON file or a CityJSONSeq stream into chunks of real-coordinate vertices."""
    text = read_text(path, "CityJSON file")
    docs = _parse_json_documents(text, path)
    header = docs[0]
    if not isinstance(header, dict) or header.get("type") != "CityJSON":
        raise InputFileError(path, "not CityJSON (first object lacks \"type\": \"CityJSON\")")
    transform = header.get("transform")
    if len(docs) > 1:  # CityJSONSeq: the header line's (empty) lists may be left out
        header = {"CityObjects": {}, "vertices": [], **header}
    chunks = [_chunk(header, transform, path, "file" if len(docs) == 1 else "line 1")]
    for i, feature in enumerate(docs[1:], start=2):
        if not isinstance(feature, dict) or feature.get("type") != "CityJSONFeature":
            raise InputFileError(path, f"line {i}: not a CityJSONFeature")
        chunks.append(_chunk(feature, transform, path, f"line {i}"))
    templates = header.get("geometry-templates") or {}
    tverts = np.asarray(templates.get("vertices-templates", []), dtype=np.float64).reshape(-1, 3)
    return _Model(path, header, chunks, templates.get("templates", []), tverts)


def _parse_json_documents(text: str, path: Path) -> list:
    """One JSON document, or (CityJSONSeq) one per non-empty line."""
    try:
        return [json.loads(text)]
    except RecursionError:
        raise InputFileError(path, _TOO_DEEP) from None
    except json.JSONDecodeError as whole_error:
        lines = [ln for ln in text.splitlines() if ln.strip()]
        if len(lines) < 2:
            raise InputFileError(path, f"invalid JSON: {whole_error}") from None
        docs = []
        for n, line in enumerate(lines, start=1):
            try:
                docs.append(json.loads(line))
            except json.JSONDecodeError as exc:
                raise InputFileError(path, f"invalid JSON on line {n}: {exc}") from None
            except RecursionError:
                raise InputFileError(path, f"line {n}: {_TOO_DEEP}") from None
        return docs


_TOO_DEEP = ("JSON nested deeper than the JSON reader allows (about 1000 objects and arrays; CityJSON "
             "boundaries nest at most 5 deep)")
#: boundaries nest at most this deep (CompositeSolid: solids, shells, surfaces, rings, indices)
MAX_BOUNDARY_DEPTH = 5


def _chunk(doc: dict, transform: dict | None, path: Path, where: str) -> _Chunk:
    """Vertices (transform applied, float64) and CityObjects of one document."""
    if "vertices" not in doc:
        raise InputFileError(path, f"{where}: no \"vertices\" array")
    objects = doc.get("CityObjects")
    if not isinstance(objects, dict):
        raise InputFileError(path, f"{where}: no \"CityObjects\" object")
    try:
        v = np.asarray(doc["vertices"], dtype=np.float64).reshape(-1, 3)
    except (ValueError, TypeError):
        raise InputFileError(path, f"{where}: \"vertices\" is not a list of [x, y, z]") from None
    if transform:
        v = v * np.asarray(transform.get("scale", [1, 1, 1]), dtype=np.float64) \
            + np.asarray(transform.get("translate", [0, 0, 0]), dtype=np.float64)
    return _Chunk(objects, v, doc.get("appearance"))


def source_crs(header: dict, path: Path) -> str:
    """'AUTH:CODE' of ``metadata.referenceSystem`` (OGC URL or URN), or of 0.x ``crs.epsg``."""
    meta = header.get("metadata") or {}
    ref = meta.get("referenceSystem")
    if ref is None and isinstance(meta.get("crs"), dict) and "epsg" in meta["crs"]:
        return f"EPSG:{int(meta['crs']['epsg'])}"
    if not ref:
        raise CRSError(f"{path}: no metadata.referenceSystem says its CRS (set the input's crs key)")
    return crs_name(str(ref))


# --------------------------------------------------------------------------- geometry


@dataclass
class _Out:
    """Where one chunk's surfaces go: faces on the chunk's vertices per (colour class, material
    RGBA or None), and textured pieces (own corners and UVs) per image, shared by all chunks."""

    look: Appearances
    palette: object                    # the chunk's parsed appearance object (None: not read)
    textured: dict
    colour: dict = field(default_factory=dict)
    obj: int = -1                      # the object whose faces go in now (index into the model's keys)


def _build_parts(model: _Model, src_crs: str | None, lod: str | None, keep, theme: str | None = None,
                 appearances: bool = True) -> Loaded:
    """Triangulate the kept objects and group them by colour class (material colours on their
    surfaces) and by texture image, in the source CRS."""
    src = src_crs or source_crs(model.header, model.path)
    look = Appearances(model.path, model.header, theme, appearances)
    look.choose_themes(_all_geometries(model))
    by_class: dict[str, list[tuple]] = {}
    textured: dict[str, list[tuple]] = {}
    keys: list[str] = []                # every drawn CityObject's id, in file order
    for chunk in model.chunks:
        out = _Out(look, look.palette(chunk.appearance) if appearances else None, textured)
        for key, obj in chunk.objects.items():
            if isinstance(obj, dict) and keep(obj.get("type")):
                out.obj = len(keys)
                keys.append(str(key))
                _object_triangles(obj, lod, chunk, model, out)
        verts = chunk.vertices
        for (cls, rgba), pieces in out.colour.items():
            faces = np.concatenate([f for f, _ in pieces])
            if faces.size and (faces.min() < 0 or faces.max() >= len(verts)):
                bad = faces.max() if faces.max() >= len(verts) else faces.min()
                raise InputFileError(model.path, f"vertex index {bad} out of range ({len(verts)} vertices)")
            used, inv = np.unique(faces, return_inverse=True)
            objects = np.concatenate([np.full(len(f), k, dtype=np.int32) for f, k in pieces])
            by_class.setdefault(cls, []).append((verts[used], inv.reshape(-1, 3), rgba, objects))
    parts = [class_part(cls, pieces, tuple(keys)) for cls, pieces in sorted(by_class.items())]
    look.report()
    return Loaded(parts + look.parts(textured, tuple(keys)), src)


def _all_geometries(model: _Model):
    """Every geometry of the file (objects of every chunk, and templates), for their theme names."""
    for chunk in model.chunks:
        for obj in chunk.objects.values():
            if isinstance(obj, dict):
                yield from (g for g in obj.get("geometry") or [] if isinstance(g, dict))
    yield from (t for t in model.templates if isinstance(t, dict))


def _geometry_lod(geom: dict, model: _Model) -> tuple[int, ...]:
    """LOD key of a geometry; a GeometryInstance has the LOD of its template."""
    if geom.get("type") == "GeometryInstance":
        try:
            return lod_key(model.templates[int(geom["template"])].get("lod", -1))
        except (KeyError, IndexError, TypeError, ValueError, AttributeError):
            return (-1,)
    return lod_key(geom.get("lod", -1))


def _pick_geometries(geoms: list, lod: str | None, model: _Model) -> list:
    """Geometries of the chosen LOD (:func:`~pipeline25d.formats.surfaces.pick_lod`)."""
    keyed = [(_geometry_lod(g, model), g) for g in geoms]
    chosen = pick_lod([k for k, _ in keyed], lod)
    return [g for k, g in keyed if k == chosen]


def _object_triangles(obj: dict, lod: str | None, chunk: _Chunk, model: _Model, out: _Out) -> None:
    """Append the triangles of one CityObject to ``out``."""
    obj_class = OBJECT_CLASS.get(str(obj.get("type", "")), "other")
    geoms = [g for g in obj.get("geometry") or [] if isinstance(g, dict)]
    for geom in _pick_geometries(geoms, lod, model):
        if geom.get("type") != "GeometryInstance":
            _geometry_triangles(geom, obj_class, chunk.base, model.path, out)
            continue
        placed = _instantiate(geom, chunk, model)
        if placed is not None:
            template, verts = placed
            start = chunk.add_vertices(verts)
            _geometry_triangles(template, obj_class, verts, model.path, out, offset=start)


def _instantiate(inst: dict, chunk: _Chunk, model: _Model) -> tuple[dict, np.ndarray] | None:
    """A GeometryInstance as a plain geometry and its own placed vertices (template, matrix, anchor)."""
    try:
        template = dict(model.templates[int(inst["template"])])
        anchor = chunk.base[int(inst["boundaries"][0])]
        matrix = np.asarray(inst.get("transformationMatrix", np.eye(4).ravel()), dtype=np.float64).reshape(4, 4)
    except (KeyError, IndexError, TypeError, ValueError) as exc:
        warnings.warn(f"{model.path}: GeometryInstance skipped ({exc!r})", stacklevel=4)
        return None
    used = _indices(template.get("boundaries", []))
    if used is None:
        warnings.warn(f"{model.path}: GeometryInstance skipped (its template's boundaries nest deeper than "
                      f"{MAX_BOUNDARY_DEPTH} levels)", stacklevel=4)
        return None
    if not used or max(used) >= len(model.template_vertices):
        warnings.warn(f"{model.path}: GeometryInstance with bad template vertices skipped", stacklevel=4)
        return None
    local = model.template_vertices[used]
    placed = local @ matrix[:3, :3].T + matrix[:3, 3] + anchor
    template["boundaries"] = _remap(template["boundaries"], {old: new for new, old in enumerate(used)})
    return template, placed


def _indices(boundaries: list) -> list[int] | None:
    """The sorted vertex indices in ``boundaries`` (walked without recursion); None when they
    nest deeper than :data:`MAX_BOUNDARY_DEPTH`."""
    found, stack = set(), [(boundaries, 1)]
    while stack:
        item, depth = stack.pop()
        if not isinstance(item, list):
            found.add(int(item))
        elif depth > MAX_BOUNDARY_DEPTH:
            return None
        else:
            stack += [(x, depth + 1) for x in item]
    return sorted(found)


def _remap(b, mapping: dict):
    """``b`` with every index mapped (its depth checked by :func:`_indices` first)."""
    return [_remap(x, mapping) for x in b] if isinstance(b, list) else mapping[int(b)]


def _geometry_triangles(geom: dict, obj_class: str, verts: np.ndarray, path: Path, out: _Out,
                        offset: int = 0) -> None:
    """Triangulate every surface of a (Multi/Composite)Surface/Solid geometry on ``verts``;
    the faces go to ``out`` shifted by ``offset`` (where ``verts`` start in the chunk), a
    textured surface's to ``out.textured`` with its own corners and UVs.

    Surfaces that are already triangles (3dfier TINs: the common case) are handled
    together in numpy; other polygons go through :func:`triangulate_polygon`.
    """
    depth = _SURFACE_DEPTH.get(geom.get("type"))
    if depth is None:
        return  # points, lines: nothing to draw
    semantics = geom.get("semantics") or {}
    sem_surfaces = semantics.get("surfaces") or []
    boundaries = geom.get("boundaries") or []
    materials, textures = out.look.themed(geom)
    per_material = (repeat((None, materials)) if materials is None or isinstance(materials, int)
                    else _iter_surfaces(boundaries, materials, depth))
    per_texture = repeat((None, None)) if textures is None else _iter_surfaces(boundaries, textures, depth)
    tris, values, colour_ids, rgbas = [], [], [], {}
    try:
        for (rings, value), (_, material), (_, texture) in zip(
                _iter_surfaces(boundaries, semantics.get("values"), depth), per_material, per_texture):
            if texture is not None:
                hit = out.look.textured(texture, rings, verts, out.palette)
                if hit is not None:
                    out.textured.setdefault(hit[0], []).append((*hit[1], out.obj))
                    continue
            rgba = None if material is None else out.look.rgba(material, out.palette)
            if len(rings) == 1 and len(rings[0]) == 3:
                tris.append(rings[0])
                values.append(value)
                colour_ids.append(rgbas.setdefault(rgba, len(rgbas)))
                continue
            poly, normal = triangulate_polygon(rings, verts)
            if len(poly):
                cls = _surface_classes(sem_surfaces, [value], obj_class, normal[None])[0]
                out.colour.setdefault((cls, rgba), []).append((poly + offset, out.obj))
        if tris:
            tris = np.asarray(tris, dtype=np.int64)
            p = verts[tris]
            normals = np.cross(p[:, 1] - p[:, 0], p[:, 2] - p[:, 0])
            classes = _surface_classes(sem_surfaces, values, obj_class, normals)
            ids, colours = np.asarray(colour_ids), list(rgbas)
            for cls in set(classes):
                for k in np.unique(ids[classes == cls]):
                    out.colour.setdefault((cls, colours[k]), []).append(
                        (tris[(classes == cls) & (ids == k)] + offset, out.obj))
    except (TypeError, ValueError, KeyError) as exc:
        raise InputFileError(path, f"malformed geometry boundaries: {exc!r}") from None
    except IndexError:
        raise InputFileError(path, f"vertex index out of range ({len(verts)} vertices)") from None


def _iter_surfaces(boundaries: list, values, depth: int):
    """(rings, semantic value) of each surface, walking ``depth`` nesting levels."""
    for i, item in enumerate(boundaries):
        value = values[i] if isinstance(values, list) and i < len(values) else None
        if depth == 1:
            yield item, value
        else:
            yield from _iter_surfaces(item, value, depth - 1)


def _surface_classes(sem_surfaces: list, values: list, obj_class: str, normals: np.ndarray) -> np.ndarray:
    """Colour class per surface: semantic type, else object type, else (buildings) normal."""
    out = np.empty(len(values), dtype=object)
    for i, value in enumerate(values):
        cls = None
        if isinstance(value, int) and 0 <= value < len(sem_surfaces):
            cls = SEMANTIC_CLASS.get(sem_surfaces[value].get("type"))
        out[i] = cls or obj_class
    derive = out == "building"
    if derive.any():
        out[derive] = normal_classes(normals[derive])
    return out


def _terrain_types(model: _Model) -> frozenset[str]:
    """{'TINRelief'} when the file has TINRelief objects, else :data:`GROUND_TYPES`."""
    for chunk in model.chunks:
        if any(isinstance(o, dict) and o.get("type") == "TINRelief" for o in chunk.objects.values()):
            return frozenset({"TINRelief"})
    return GROUND_TYPES


def read_cityjson_buildings(path: Path, spec: dict) -> Buildings:
    """The building objects of a CityJSON/CityJSONSeq file, in its own CRS, untextured
    (see :mod:`pipeline25d.formats.buildings`)."""
    model = _read_model(Path(path))
    terrain = _terrain_types(model)
    others = any(isinstance(o, dict) and o.get("geometry") and not is_building(o.get("type"))
                 and o.get("type") not in terrain for c in model.chunks for o in c.objects.values())
    return Buildings(_build_parts(model, spec.get("crs"), spec.get("lod"), is_building, appearances=False), others)
