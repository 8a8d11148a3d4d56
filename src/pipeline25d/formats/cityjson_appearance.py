"""CityJSON appearances (1.0, 1.1, 2.0): textures and materials, the theme drawn, per surface lookup.

The ``appearance`` object of the file (and of each CityJSONSeq feature that has its own) holds
``textures`` (``image`` relative to the file, ``wrapMode``, ``borderColor``), ``vertices-texture``
(UV pairs; v = 0 is the image's bottom row, as in CityGML and :class:`~pipeline25d.core.mesh.MeshPart`)
and ``materials`` (``diffuseColor``, ``transparency``). A geometry names per theme which texture
covers each ring (``texture.<theme>.values``: the boundaries' nesting, each ring ``[texture index,
UV index per ring vertex]`` or ``[null]``) and which material each surface has
(``material.<theme>.values`` per surface, or one ``value``). Themes exist only inside geometries:
:class:`Appearances` collects them, takes the input's ``theme`` key (it must name a texture or a
material theme of the file; the other kind keeps its default), else the file's
``default-theme-texture`` / ``default-theme-material``, else the first theme met; it logs which
theme is drawn, which others exist and how many textures were drawn. A texture image that is
missing, remote or not an image is a
:class:`~pipeline25d.core.errors.MissingTextureWarning` (once per image): an error at ingest unless
the input says ``missing_textures: untextured``, then its surfaces take their material or class
colour. Wrap modes other than ``wrap`` clamp UVs outside [0, 1] per vertex (the renderer repeats
textures; ``borderColor`` is not drawn), with a warning.
"""

from __future__ import annotations

import logging
import warnings
from collections import Counter
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from pipeline25d.core.errors import ConfigError, InputFileError
from pipeline25d.core.mesh import MeshPart
from pipeline25d.formats.common import texture_file, texture_image
from pipeline25d.formats.surfaces import join_pieces, triangulate_polygon

log = logging.getLogger(__name__)

Rgba = tuple[int, int, int, int]


@dataclass(frozen=True)
class _Texture:
    image: str | None        # resolved image path; None: not a local file (remote URL, outside the folder)
    uri: str                 # as written in the file, for messages
    wrap: str                # wrapMode ("wrap" repeats; others are clamped)
    problem: str | None = None   # why ``image`` is None


@dataclass(frozen=True)
class _Palette:
    """One appearance object: its textures, UV pairs (float64) and material colours."""

    textures: tuple[_Texture, ...]
    uv: np.ndarray
    materials: tuple[Rgba, ...]


def image_path(model: Path, uri: str) -> tuple[str | None, str | None]:
    """(the local file a texture's ``image`` names, None) or (None, why it is not read: a URL, a path
    leaving the model's folder): relative to the model's folder and confined to it
    (:func:`pipeline25d.formats.common.texture_file`); an image not read is a missing texture."""
    if "://" in uri:
        return None, "is a URL (not fetched)"
    target, problem = texture_file(uri, model.parent, model.parent, model, "texture image", url=False)
    return (str(target.resolve()) if target is not None else None), problem


def _texture_of(model: Path, entry: dict) -> _Texture:
    """A CityJSON appearance's texture entry, its image found (or why not) by :func:`image_path`."""
    uri = str(entry["image"])
    image, problem = image_path(model, uri)
    return _Texture(image, uri, str(entry.get("wrapMode", "none")), problem)


def material_rgba(material: dict) -> Rgba:
    """RGBA of a material: ``diffuseColor`` (X3D default 0.8 grey), alpha 1 - ``transparency``."""
    rgb = np.asarray(material.get("diffuseColor", [0.8, 0.8, 0.8]), dtype=np.float64).reshape(3)
    alpha = 1.0 - float(material.get("transparency", 0.0))
    return tuple(int(round(c)) for c in np.clip(np.append(rgb, alpha), 0.0, 1.0) * 255)


class Appearances:
    """The appearances of one CityJSON file for one read: themes chosen, images read, counts kept."""

    def __init__(self, path: Path, header: dict, theme: str | None, enabled: bool = True):
        self.path, self.theme, self.enabled = path, theme, enabled
        app = header.get("appearance")
        self.header = app if isinstance(app, dict) else {}
        self.texture_theme: str | None = None
        self.material_theme: str | None = None
        self.texture_themes: Counter = Counter()     # theme -> geometries using it
        self.material_themes: Counter = Counter()
        self.palettes: dict[int, _Palette] = {}      # id(appearance dict) -> parsed
        self.images: dict[str, bytes | None] = {}
        self.declared: set[str] = set()              # images the appearance objects list
        self.drawn: set[str] = set()                 # images of the textured surfaces drawn
        self.surfaces: Counter = Counter()           # "textured", "material"
        self.issues: Counter = Counter()

    # -- themes ------------------------------------------------------------
    def choose_themes(self, geometries) -> None:
        """Collect the theme names of ``geometries`` (every geometry and template of the file) and
        pick the ones to draw; ConfigError when the input's ``theme`` names none of them."""
        if not self.enabled:
            return
        for geom in geometries:
            for key, themes in (("texture", self.texture_themes), ("material", self.material_themes)):
                value = geom.get(key)
                if isinstance(value, dict):
                    themes.update(str(name) for name in value)
        if self.theme is not None:
            if self.theme not in self.texture_themes and self.theme not in self.material_themes:
                raise ConfigError(f"{self.path}: theme {self.theme!r} (the input's theme key) is not an "
                                  f"appearance theme of the file ({self._theme_list()})")
        self.texture_theme = self._pick(self.texture_themes, "default-theme-texture")
        self.material_theme = self._pick(self.material_themes, "default-theme-material")

    def _pick(self, themes: Counter, key: str) -> str | None:
        """The input's theme where it is one of ``themes``, else the file's default, else the first."""
        named = self.theme if self.theme in themes else self.header.get(key)
        if named in themes:
            return str(named)
        return next(iter(themes), None)

    def _theme_list(self) -> str:
        if not self.texture_themes and not self.material_themes:
            return "it has no appearance themes"
        return (f"texture themes: {', '.join(map(repr, self.texture_themes)) or 'none'}; "
                f"material themes: {', '.join(map(repr, self.material_themes)) or 'none'}")

    def themed(self, geom: dict) -> tuple[object, object]:
        """(material values or single index, texture values) of ``geom`` in the themes drawn."""
        if not self.enabled:
            return None, None
        material = (geom.get("material") or {}).get(self.material_theme) if self.material_theme else None
        texture = (geom.get("texture") or {}).get(self.texture_theme) if self.texture_theme else None
        mat = None
        if isinstance(material, dict):
            mat = material["values"] if "values" in material else material.get("value")
        return mat, texture.get("values") if isinstance(texture, dict) else None

    # -- the appearance objects -------------------------------------------
    def palette(self, doc_appearance: dict | None) -> _Palette:
        """The parsed appearance object of a chunk (its own, else the file's)."""
        app = doc_appearance if isinstance(doc_appearance, dict) else self.header
        if id(app) not in self.palettes:
            try:
                textures = tuple(_texture_of(self.path, t) for t in app.get("textures") or [])
                uv = np.asarray(app.get("vertices-texture") or [], dtype=np.float64).reshape(-1, 2)
                materials = tuple(material_rgba(m) for m in app.get("materials") or [])
            except (KeyError, TypeError, ValueError, AttributeError) as exc:
                raise InputFileError(self.path, f"malformed appearance object: {exc!r}") from None
            self.declared.update(t.image or t.uri for t in textures)
            self.palettes[id(app)] = _Palette(textures, uv, materials)
        return self.palettes[id(app)]

    def rgba(self, index, palette: _Palette) -> Rgba:
        """The colour of material ``index``."""
        if not isinstance(index, int) or not 0 <= index < len(palette.materials):
            raise InputFileError(self.path, f"material index {index!r} out of range "
                                            f"({len(palette.materials)} materials)")
        self.surfaces["material"] += 1
        return palette.materials[index]

    # -- textured surfaces -------------------------------------------------
    def textured(self, value, rings: list, verts: np.ndarray, palette: _Palette) -> tuple[str, tuple] | None:
        """(image, (corner positions, faces, UVs)) of a surface its texture ``value`` covers, or None
        (no texture, unusable image, UVs not matching the rings: then it is drawn in colour)."""
        if not isinstance(value, list) or not value or not isinstance(value[0], list) or not value[0] \
                or value[0][0] is None:
            return None
        index = value[0][0]
        if not isinstance(index, int) or not 0 <= index < len(palette.textures):
            raise InputFileError(self.path, f"texture index {index!r} out of range "
                                            f"({len(palette.textures)} textures)")
        if len(value) != len(rings) or any(len(t) != len(r) + 1 or t[0] != index for t, r in zip(value, rings)):
            self.issues["textured surfaces whose texture values do not match their rings drawn in colour"] += 1
            return None
        texture = palette.textures[index]
        if self.image(texture) is None:
            return None
        try:
            ids = [np.asarray(t[1:], dtype=np.int64) for t in value]
        except (TypeError, ValueError):
            ids = None
        if ids is None or any(len(i) and (i.min() < 0 or i.max() >= len(palette.uv)) for i in ids):
            raise InputFileError(self.path, f"texture coordinate index out of range "
                                            f"({len(palette.uv)} vertices-texture)")
        uv_rings = [palette.uv[i] for i in ids]
        piece = textured_polygon(rings, uv_rings, verts)
        if piece is None:
            return None
        if texture.wrap != "wrap" and ((piece[2] < 0) | (piece[2] > 1)).any():
            self.issues[f"texture coordinates outside [0, 1] under wrapMode {texture.wrap!r} clamped per "
                        "vertex (an approximation)"] += 1
            piece = (piece[0], piece[1], np.clip(piece[2], 0.0, 1.0))
        self.surfaces["textured"] += 1
        self.drawn.add(texture.image)
        return texture.image, piece

    def image(self, texture: _Texture) -> bytes | None:
        """Encoded image bytes, or None (warned once per image) when missing, remote or unreadable."""
        key = texture.image or texture.uri
        if key not in self.images:
            self.images[key] = texture_image(self.path, key, texture.problem)
        return self.images[key]

    def parts(self, groups: dict[str, list[tuple]], objects: tuple[str, ...]) -> list[MeshPart]:
        """One textured MeshPart per image of ``groups`` (image -> (positions, faces, UVs, object)
        pieces, the object an index into ``objects``)."""
        out = []
        for image, pieces in sorted(groups.items()):
            vertices, faces = join_pieces([(v, f) for v, f, _, _ in pieces])
            uv = np.concatenate([u for _, _, u, _ in pieces])
            face_objects = np.concatenate([np.full(len(f), k, dtype=np.int32) for _, f, _, k in pieces])
            out.append(MeshPart(vertices, faces, uv=uv, texture=self.images[image], name=Path(image).name,
                                objects=objects, face_objects=face_objects))
        return out

    def report(self) -> None:
        """Log the themes drawn and the textures drawn; warn of the surfaces drawn in colour instead."""
        for issue, n in sorted(self.issues.items()):
            warnings.warn(f"{self.path}: {issue} ({n}x)", stacklevel=3)
        if not self.enabled or not (self.declared or self.texture_themes or self.material_themes):
            return
        log.info("%s: %d of %d textures drawn on %d surfaces (texture theme %s%s); %d surfaces in material "
                 "colours (material theme %s%s)", self.path, len(self.drawn), len(self.declared),
                 self.surfaces["textured"], _quoted(self.texture_theme),
                 _others(self.texture_themes, self.texture_theme), self.surfaces["material"],
                 _quoted(self.material_theme), _others(self.material_themes, self.material_theme))


def _quoted(theme: str | None) -> str:
    return repr(theme) if theme is not None else "none"


def _others(themes: Counter, chosen: str | None) -> str:
    rest = [repr(t) for t in themes if t != chosen]
    return f"; not drawn: {', '.join(rest)}" if rest else ""


def textured_polygon(rings: list, uv_rings: list[np.ndarray],
                     verts: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray] | None:
    """(corner positions (k, 3), faces (m, 3) into them, UVs (k, 2)) of a polygon whose ring
    vertices each carry their own UV, triangulated like every other surface
    (:func:`~pipeline25d.formats.surfaces.triangulate_polygon`); None when it has no area.

    Corners, not shared vertices: a vertex on a texture seam has a UV per surface. Repeated
    consecutive vertices and a closing repeat are dropped as the triangulation drops them."""
    index, uvs, local, n = [], [], [], 0
    for ring, uv in zip(rings, uv_rings):
        ring = [int(i) for i in ring]
        keep = [k for k in range(len(ring)) if k == 0 or ring[k] != ring[k - 1]]
        while len(keep) > 1 and ring[keep[-1]] == ring[keep[0]]:
            keep.pop()
        index += [ring[k] for k in keep]
        uvs.append(uv[keep])
        local.append(list(range(n, n + len(keep))))
        n += len(keep)
    if n < 3:
        return None
    if min(index) < 0:
        raise IndexError(min(index))
    positions = verts[np.asarray(index, dtype=np.int64)]
    faces, _ = triangulate_polygon(local, positions)
    if not len(faces):
        return None
    return positions, faces, np.concatenate(uvs)
