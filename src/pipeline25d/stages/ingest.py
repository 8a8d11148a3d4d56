"""Ingest: one district file -> square chunks on a global grid, written only when changed.

Triangles go to the chunk that holds their centroid (x, y); they are not clipped, so a
chunk's bounds may reach a little past its grid cell. Chunk ids (``c{ix}_{iy}``) come
from the global grid, so they are stable across runs and districts. A chunk whose
content is unchanged keeps its file (and mtime), so Snakemake re-runs nothing downstream
of it; chunks that no longer exist are removed.

An input read in pieces (:func:`pipeline25d.formats.district_pieces`: an OSGB dataset's tiles,
a tileset's contents, a large OBJ's slabs of faces) is chunked piece by piece; the pieces' share
of each chunk waits in memory up to :data:`SPOOL_BYTES`, beyond that in a spool file beside the
index, and each chunk is assembled on its own, its parts in input order as if the input had been
read whole. Memory then follows a piece and a chunk, not the input.
"""

from __future__ import annotations

import json
import logging
import pickle
import tempfile
from collections.abc import Iterable, Iterator
from dataclasses import replace
from pathlib import Path

import numpy as np

from pipeline25d.core.atomic import write_json
from pipeline25d.core.mesh import Mesh, MeshPart, joined
from pipeline25d.stages.chunks import chunk_origin, content_hash, pack_parts, save_npz
from pipeline25d.stages.objects import object_ids

log = logging.getLogger(__name__)

SPOOL_BYTES = 256 * 2 ** 20     # pieces' chunk shares held in memory before they go to the spool

def chunk_id(ix: int, iy: int) -> str:
    return f"c{ix}_{iy}"


def split_into_chunks(mesh: Mesh, chunk_size: float) -> dict[str, list[MeshPart]]:
    """Partition every part's triangles by the grid cell of their centroid."""
    out: dict[str, list[MeshPart]] = {}
    for part in mesh.parts:
        if not part.n_triangles:
            continue
        centroids = part.vertices[part.faces].mean(axis=1)
        cells = np.floor(centroids[:, :2] / chunk_size).astype(np.int64)
        keys, inverse = _cells(cells)
        order = np.argsort(inverse, kind="stable")            # faces grouped by cell, in file order
        ends = np.cumsum(np.bincount(inverse, minlength=len(keys)))
        for (ix, iy), faces in zip(keys, np.split(order, ends[:-1])):
            out.setdefault(chunk_id(int(ix), int(iy)), []).append(_subset(part, faces))
    return out


def _cells(cells: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The distinct (ix, iy) rows of ``cells`` sorted by ix then iy, and each row's index in them:
    ``np.unique(cells, axis=0, return_inverse=True)`` through one int64 key a row (0.9 s of 1.0 s
    splitting 484k faces went to sorting the rows as records)."""
    low = cells.min(axis=0)
    span = int(cells[:, 1].max() - low[1]) + 1
    keys, inverse = np.unique((cells[:, 0] - low[0]) * span + (cells[:, 1] - low[1]), return_inverse=True)
    return np.column_stack([keys // span + low[0], keys % span + low[1]]), inverse.ravel()


def _subset(part: MeshPart, face_index: np.ndarray) -> MeshPart:
    """The part restricted to some faces, with unused vertices (and objects) dropped."""
    faces = part.faces[face_index]
    used, new_faces = np.unique(faces, return_inverse=True)
    objects, face_objects = part.objects, None
    if part.face_objects is not None:          # only the objects its faces belong to, in input order
        held, face_objects = np.unique(part.face_objects[face_index], return_inverse=True)
        objects = tuple(part.objects[k] for k in held)
    return MeshPart(
        vertices=part.vertices[used],
        faces=new_faces.reshape(-1, 3),
        colors=None if part.colors is None else part.colors[used],
        uv=None if part.uv is None else part.uv[used],
        texture=part.texture,
        name=part.name,
        objects=objects,
        face_objects=face_objects,
    )


def write_chunks(mesh: Mesh | Iterable[Mesh], district: str, chunk_size: float, out_dir: Path,
                 index_path: Path, slot: int = 0) -> dict:
    """Write the district's chunks into ``out_dir``, its objects' ids (``objects.json``: key -> id,
    :mod:`pipeline25d.stages.objects`, district id ``slot``), what the input says of them
    (``attributes.json``: key -> {type, attributes}, only the objects it says anything of, see
    :attr:`~pipeline25d.core.mesh.MeshPart.object_info`) and its index JSON last; ``mesh`` whole
    or in pieces (module docstring). Every face belongs to an object (:meth:`~pipeline25d.core.mesh.MeshPart.named`).

    Returns the index: {district, source, n_triangles, chunk_size, [coarser,] chunks: {id: {...}}};
    ``coarser`` (the input tiles drawn coarser than asked, :class:`~pipeline25d.core.mesh.Coarser`
    as JSON, see :func:`pipeline25d.stages.records.coarser_tiles`) only when there are any.
    """
    out_dir.mkdir(parents=True, exist_ok=True)
    sidecar = index_path.with_suffix(".hashes.json")
    previous = _previous_hashes(sidecar)
    pieces = [mesh] if isinstance(mesh, Mesh) else mesh
    with _Spool(out_dir) as spool:
        source, n_triangles, coarser, info = "", 0, [], {}
        for piece in pieces:
            source, n_triangles = piece.source, n_triangles + piece.n_triangles
            coarser += piece.coarser
            info.update(piece.object_info())
            spool.add(split_into_chunks(Mesh([p.named() for p in piece.parts], piece.source), chunk_size))
        ids = object_ids(spool.keys, slot, source or district)
        index = {"district": district, "source": source, "chunk_size": chunk_size, "n_triangles": n_triangles,
                 # only when there are any: the index of a district drawn as asked stays as it was
                 **({"coarser": [c.to_json() for c in coarser]} if coarser else {}),
                 "chunks": {}}
        for cid, parts in spool.chunks():
            parts = [replace(p, object_ids=np.array([ids[k] for k in p.objects], dtype=np.uint32)) for p in parts]
            bounds = Mesh(parts).bounds()
            origin = chunk_origin(bounds)
            arrays = pack_parts(parts, origin)
            arrays["origin"] = origin
            digest = content_hash(arrays)
            path = out_dir / f"{cid}.npz"
            n = sum(p.n_triangles for p in parts)
            if previous.get(cid) != digest or not path.exists():
                save_npz(path, arrays)
                log.info("chunk %s/%s written (%d triangles)", district, cid, n)
            index["chunks"][cid] = {"bounds": bounds.tolist(), "n_triangles": n, "hash": digest}
    for stale in out_dir.glob("c*.npz"):
        if stale.stem not in index["chunks"]:
            stale.unlink()
    write_json(sidecar, {k: v["hash"] for k, v in index["chunks"].items()})
    write_json(out_dir / "objects.json", dict(sorted(ids.items())))
    write_json(out_dir / "attributes.json", {k: info[k] for k in sorted(ids) if info.get(k)}, indent=None)
    write_json(index_path, index)
    return index


class _Spool:
    """Each chunk's parts from every piece, in order: in memory up to :data:`SPOOL_BYTES`, then
    appended to one pickle file per chunk in a temporary folder beside the chunks."""

    def __init__(self, out_dir: Path):
        self.out_dir = out_dir
        self.held: dict[str, list[MeshPart]] = {}
        self.held_bytes = 0
        self.folder: tempfile.TemporaryDirectory | None = None
        self.spooled: set[str] = set()
        self.keys: set[str] = set()          # every object of every part added

    def __enter__(self) -> "_Spool":
        return self

    def __exit__(self, *exc) -> None:
        if self.folder is not None:
            self.folder.cleanup()

    def add(self, chunks: dict[str, list[MeshPart]]) -> None:
        """One piece's share of each chunk. A textured part that continues one the chunk holds (same
        name, same texture: a large OBJ's slabs, :mod:`pipeline25d.formats.obj_slabs`) is joined to it,
        as one material is one part of the OBJ read whole, and the chunk stores its texture once."""
        for cid, parts in chunks.items():
            held = self.held.setdefault(cid, [])
            self.keys.update(k for p in parts for k in p.objects)
            self.held_bytes += sum(_part_bytes(p) for p in parts)
            for part in parts:
                same = next((i for i, h in enumerate(held) if _continues(h, part)), None)
                if same is None:
                    held.append(part)
                else:
                    held[same] = joined([held[same], part], part.name)
        if self.held_bytes > SPOOL_BYTES:
            self._spill()

    def _spill(self) -> None:
        if self.folder is None:
            self.folder = tempfile.TemporaryDirectory(prefix=".spool-", dir=self.out_dir)
        for cid, parts in self.held.items():
            with open(Path(self.folder.name) / cid, "ab") as f:
                pickle.dump(parts, f, protocol=pickle.HIGHEST_PROTOCOL)
            self.spooled.add(cid)
        log.info("spooled %.0f MB of chunk parts", self.held_bytes / 2 ** 20)
        self.held, self.held_bytes = {}, 0

    def chunks(self) -> Iterator[tuple[str, list[MeshPart]]]:
        """(chunk id, its parts in input order), one chunk at a time, sorted by id."""
        for cid in sorted(self.spooled | set(self.held)):
            parts: list[MeshPart] = []
            if cid in self.spooled:
                with open(Path(self.folder.name) / cid, "rb") as f:
                    while True:
                        try:
                            parts.extend(pickle.load(f))
                        except EOFError:
                            break
            parts.extend(self.held.pop(cid, []))
            yield cid, parts


def _continues(held: MeshPart, part: MeshPart) -> bool:
    """Whether ``part`` is more of ``held``: both textured with the same image, same name, same kinds
    of vertex data (a part joined from several pieces: its faces in the pieces' order)."""
    return (held.texture is not None and held.name == part.name and (held.colors is None) == (part.colors is None)
            and (held.uv is None) == (part.uv is None) and held.texture == part.texture)


def _part_bytes(part: MeshPart) -> int:
    arrays = (part.vertices, part.faces, part.colors, part.uv)
    return sum(a.nbytes for a in arrays if a is not None) + len(part.texture or b"")


def _previous_hashes(sidecar: Path) -> dict[str, str]:
    """Chunk hashes a previous run recorded, kept beside the index because Snakemake
    deletes the index itself before re-running ingest."""
    return json.loads(sidecar.read_text()) if sidecar.exists() else {}


def ingest(spec: dict, district: str, scene_crs: str, chunk_size: float, max_geometric_error: float,
           index_path: str | Path, gsd: float | None = None, slot: int = 0) -> dict:
    """Read one district and write its chunks beside ``index_path``."""
    from pipeline25d.formats import district_pieces

    def pieces() -> Iterator[Mesh]:
        for piece in district_pieces(spec, scene_crs, max_geometric_error=max_geometric_error, gsd=gsd):
            for c in piece.coarser:
                log.warning("%s: %s drawn at level %d (%s): missing %s", district, c.tile, c.level, c.drawn,
                            ", ".join(c.missing))
            yield piece

    index_path = Path(index_path)
    index = write_chunks(pieces(), district, chunk_size, index_path.parent, index_path, slot)
    log.info("%s: %d triangles from %s", district, index["n_triangles"], spec["path"])
    return index
