"""The in-memory mesh that every reader returns and every stage consumes.

A :class:`MeshPart` is one draw call: triangles with at most one texture. Positions
are float64 in the scene CRS (metres) until they are written to a chunk, where they
become float32 relative to the chunk's float64 origin (see :mod:`pipeline25d.stages.chunks`).
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass, field, replace

import numpy as np


@dataclass
class MeshPart:
    """Triangles sharing one appearance.

    vertices: (n, 3) float64, scene CRS metres (x east, y north, z up).
    faces:    (m, 3) int64 indices into ``vertices``.
    colors:   (n, 4) uint8 RGBA per vertex, or None (then ``texture`` or grey).
    uv:       (n, 2) float32 texture coordinates (origin bottom-left, glTF/OBJ v flipped
              to GL convention: v=0 is the bottom row of the image), or None.
    texture:  encoded image bytes (PNG/JPEG) for ``uv``, or None.
    name:     free text for messages (material or object name).
    objects:  the keys of the input objects (CityJSON/CityGML ids ...) its faces belong to.
    face_objects: (m,) int32 index into ``objects`` of every face, or None (the faces carry
              no object identity).
    object_ids: (len(objects),) uint32 numeric id of each object (see
              :mod:`pipeline25d.stages.objects`), once ingest has given them; else None.
    object_info: what the input says of its objects, key -> {"type": str, "attributes": dict}
              (either key optional; :mod:`pipeline25d.formats.attributes`), or None. It may name
              more objects than the part's own (a reader shares one mapping between its parts);
              ingest gathers it before chunking (:meth:`Mesh.object_info`).
    """

    vertices: np.ndarray
    faces: np.ndarray
    colors: np.ndarray | None = None
    uv: np.ndarray | None = None
    texture: bytes | None = None
    name: str = ""
    objects: tuple[str, ...] = ()
    face_objects: np.ndarray | None = None
    object_ids: np.ndarray | None = None
    object_info: Mapping[str, dict] | None = None

    def __post_init__(self) -> None:
        self.vertices = np.ascontiguousarray(self.vertices, dtype=np.float64).reshape(-1, 3)
        self.faces = np.ascontiguousarray(self.faces, dtype=np.int64).reshape(-1, 3)
        if self.colors is not None:
            self.colors = np.ascontiguousarray(self.colors, dtype=np.uint8).reshape(-1, 4)
        if self.uv is not None:
            self.uv = np.ascontiguousarray(self.uv, dtype=np.float32).reshape(-1, 2)
        if self.texture is None:
            self.uv = None
        if self.face_objects is not None:
            self.face_objects = np.ascontiguousarray(self.face_objects, dtype=np.int32).reshape(-1)
            if len(self.face_objects) != len(self.faces):
                raise ValueError(f"{len(self.face_objects)} face objects for {len(self.faces)} faces")
        if self.object_ids is not None:
            self.object_ids = np.ascontiguousarray(self.object_ids, dtype=np.uint32).reshape(-1)

    @property
    def n_triangles(self) -> int:
        return int(len(self.faces))

    def bounds(self) -> np.ndarray:
        """(2, 3) float64 min/max corner of the vertices that faces use."""
        used = self.vertices[np.unique(self.faces)] if len(self.faces) else self.vertices
        return np.array([used.min(axis=0), used.max(axis=0)])

    def with_faces(self, faces: np.ndarray, kept: np.ndarray) -> "MeshPart":
        """A copy drawing ``faces``, which are the faces ``kept`` (indices or mask) of this part
        (renumbered, merged or moved: their objects are those of the kept faces)."""
        objects = None if self.face_objects is None else self.face_objects[kept]
        return replace(self, faces=faces, face_objects=objects)

    def named(self) -> "MeshPart":
        """This part if its faces carry objects; else a copy whose faces all belong to the object
        named after the part (its material, mesh or tile), ``"part"`` if it has no name."""
        if self.face_objects is not None:
            return self
        return replace(self, objects=(self.name or "part",), face_objects=np.zeros(len(self.faces), np.int32))

    def transformed(self, fn) -> "MeshPart":
        """A copy whose vertices are ``fn(vertices)`` ((n, 3) float64 -> (n, 3) float64)."""
        return replace(self, vertices=np.asarray(fn(self.vertices), dtype=np.float64))


@dataclass(frozen=True)
class Coarser:
    """One input tile drawn coarser than the map's gsd asks for, because finer parts of it are
    missing (an OSGB PagedLOD child file, a 3D Tiles child's content): the ``tile`` (the file
    whose level is drawn there), the ``level`` drawn (its depth below the input's root: files
    for OSGB, tiles for 3D Tiles), the ``missing`` files, and ``drawn``: what stands in for them."""

    tile: str
    level: int
    missing: tuple[str, ...]
    drawn: str

    @classmethod
    def from_json(cls, data: dict) -> "Coarser":
        return cls(str(data["tile"]), int(data["level"]), tuple(data["missing"]), str(data["drawn"]))

    def to_json(self) -> dict:
        return {"tile": self.tile, "level": self.level, "missing": list(self.missing), "drawn": self.drawn}


@dataclass
class Mesh:
    """A district or chunk: a list of parts plus provenance for messages, and the input tiles
    drawn coarser than asked (:class:`Coarser`)."""

    parts: list[MeshPart] = field(default_factory=list)
    source: str = ""
    coarser: tuple[Coarser, ...] = ()

    @property
    def n_triangles(self) -> int:
        return sum(p.n_triangles for p in self.parts)

    def bounds(self) -> np.ndarray:
        """(2, 3) float64 bounds over all parts; raises ValueError when empty."""
        boxes = [p.bounds() for p in self.parts if p.n_triangles]
        if not boxes:
            raise ValueError(f"{self.source or 'mesh'} has no triangles")
        stacked = np.stack(boxes)
        return np.array([stacked[:, 0].min(axis=0), stacked[:, 1].max(axis=0)])

    def object_info(self) -> dict[str, dict]:
        """What the input says of the objects of all parts (:attr:`MeshPart.object_info`), merged."""
        return merged_info(self.parts)

    def transformed(self, fn) -> "Mesh":
        return Mesh([p.transformed(fn) for p in self.parts], self.source, self.coarser)


def joined(parts: list[MeshPart], name: str) -> MeshPart:
    """``parts`` of one appearance (all with vertex colours or none, all with uv or none, the first's
    texture) as one part, their faces in order, each on its object (:func:`joined_objects`)."""
    offsets = np.cumsum([0] + [len(p.vertices) for p in parts])
    objects, face_objects = joined_objects(parts)
    first = parts[0]
    return MeshPart(np.concatenate([p.vertices for p in parts]),
                    np.concatenate([p.faces + o for p, o in zip(parts, offsets)]),
                    colors=None if first.colors is None else np.concatenate([p.colors for p in parts]),
                    uv=None if first.uv is None else np.concatenate([p.uv for p in parts]),
                    texture=first.texture, name=name, objects=objects, face_objects=face_objects,
                    object_info=merged_info(parts) or None)


def repeated(part: MeshPart, matrices: np.ndarray) -> MeshPart:
    """One part holding ``part`` (in its own frame) under each of the (k, 4, 4) ``matrices``: its
    vertices, faces (wound back where a matrix mirrors), colours, UVs and faces' objects repeated."""
    k, n = len(matrices), len(part.vertices)
    verts = np.einsum("kij,nj->kni", matrices[:, :3, :3], part.vertices) + matrices[:, None, :3, 3]
    faces = np.repeat(part.faces[None], k, axis=0)
    mirrored = np.linalg.det(matrices[:, :3, :3]) < 0
    faces[mirrored] = faces[mirrored][:, :, [0, 2, 1]]
    faces += (np.arange(k) * n)[:, None, None]
    rep = (lambda a: None if a is None else np.tile(a, (k, 1)))
    face_objects = None if part.face_objects is None else np.tile(part.face_objects, k)
    return MeshPart(verts.reshape(-1, 3), faces.reshape(-1, 3), rep(part.colors), rep(part.uv), part.texture,
                    part.name, objects=part.objects, face_objects=face_objects, object_info=part.object_info)


def merged_info(parts: list[MeshPart]) -> dict[str, dict]:
    """The :attr:`MeshPart.object_info` of ``parts`` in one mapping (each shared mapping once)."""
    out: dict[str, dict] = {}
    seen: set[int] = set()
    for p in parts:
        if p.object_info and id(p.object_info) not in seen:
            seen.add(id(p.object_info))
            out.update(p.object_info)
    return out


def joined_objects(parts: list[MeshPart]) -> tuple[tuple[str, ...], np.ndarray | None]:
    """(objects, face objects) of the faces of ``parts`` concatenated in order; (), None when no
    part carries objects (else each part without them is its own object, :meth:`MeshPart.named`)."""
    if all(p.face_objects is None for p in parts):
        return (), None
    named = [p.named() for p in parts]
    keys: dict[str, int] = {}
    for p in named:
        for key in p.objects:
            keys.setdefault(key, len(keys))
    face_objects = np.concatenate([np.array([keys[k] for k in p.objects], dtype=np.int32)[p.face_objects]
                                   for p in named])
    return tuple(keys), face_objects
