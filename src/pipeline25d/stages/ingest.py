"""Ingest: one district file -> square chunks on a global grid, written only when changed.

Triangles go to the chunk that holds their centroid (x, y); they are not clipped, so a
chunk's bounds may reach a little past its grid cell. Chunk ids (``c{ix}_{iy}``) come
from the global grid, so they are stable across runs and districts. A chunk whose
content is unchanged keeps its file (and mtime), so Snakemake re-runs nothing downstream
of it; chunks that no longer exist are removed.
"""

from __future__ import annotations

import json
import logging
from pathlib import Path

import numpy as np

from pipeline25d.core.atomic import write_json
from pipeline25d.core.mesh import Mesh, MeshPart
from pipeline25d.stages.chunks import chunk_origin, content_hash, pack_parts, save_npz

log = logging.getLogger(__name__)

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
        keys, inverse = np.unique(cells, axis=0, return_inverse=True)
        order = np.argsort(inverse.ravel(), kind="stable")   # faces grouped by cell, in file order
        ends = np.cumsum(np.bincount(inverse.ravel(), minlength=len(keys)))
        for (ix, iy), faces in zip(keys, np.split(order, ends[:-1])):
            out.setdefault(chunk_id(int(ix), int(iy)), []).append(_subset(part, faces))
    return out


def _subset(part: MeshPart, face_index: np.ndarray) -> MeshPart:
    """The part restricted to some faces, with unused vertices dropped."""
    faces = part.faces[face_index]
    used, new_faces = np.unique(faces, return_inverse=True)
    return MeshPart(
        vertices=part.vertices[used],
        faces=new_faces.reshape(-1, 3),
        colors=None if part.colors is None else part.colors[used],
        uv=None if part.uv is None else part.uv[used],
        texture=part.texture,
        name=part.name,
    )


def write_chunks(mesh: Mesh, district: str, chunk_size: float, out_dir: Path, index_path: Path) -> dict:
    """Write the district's chunks into ``out_dir`` and its index JSON last.

    Returns the index: {district, source, n_triangles, chunk_size, [coarser,] chunks: {id: {...}}};
    ``coarser`` (the input tiles drawn coarser than asked, :class:`~pipeline25d.core.mesh.Coarser`
    as JSON, see :func:`pipeline25d.stages.records.coarser_tiles`) only when there are any.
    """
    out_dir.mkdir(parents=True, exist_ok=True)
    sidecar = index_path.with_suffix(".hashes.json")
    previous = _previous_hashes(sidecar)
    chunks = split_into_chunks(mesh, chunk_size)
    index = {"district": district, "source": mesh.source, "chunk_size": chunk_size,
             "n_triangles": mesh.n_triangles,
             # only when there are any: the index of a district drawn as asked stays as it was
             **({"coarser": [c.to_json() for c in mesh.coarser]} if mesh.coarser else {}),
             "chunks": {}}
    for cid, parts in sorted(chunks.items()):
        bounds = Mesh(parts).bounds()
        origin = chunk_origin(bounds)
        arrays = pack_parts(parts, origin)
        arrays["origin"] = origin
        digest = content_hash(arrays)
        path = out_dir / f"{cid}.npz"
        n_triangles = sum(p.n_triangles for p in parts)
        if previous.get(cid) != digest or not path.exists():
            save_npz(path, arrays)
            log.info("chunk %s/%s written (%d triangles)", district, cid, n_triangles)
        index["chunks"][cid] = {"bounds": bounds.tolist(), "n_triangles": n_triangles, "hash": digest}
    for stale in out_dir.glob("c*.npz"):
        if stale.stem not in index["chunks"]:
            stale.unlink()
    write_json(sidecar, {k: v["hash"] for k, v in index["chunks"].items()})
    write_json(index_path, index)
    return index


def _previous_hashes(sidecar: Path) -> dict[str, str]:
    """Chunk hashes a previous run recorded, kept beside the index because Snakemake
    deletes the index itself before re-running ingest."""
    return json.loads(sidecar.read_text()) if sidecar.exists() else {}


def ingest(spec: dict, district: str, scene_crs: str, chunk_size: float, max_geometric_error: float,
           index_path: str | Path, gsd: float | None = None) -> dict:
    """Read one district and write its chunks beside ``index_path``."""
    from pipeline25d.formats import load_district

    mesh = load_district(spec, scene_crs, max_geometric_error=max_geometric_error, gsd=gsd)
    log.info("%s: %d triangles from %s", district, mesh.n_triangles, spec["path"])
    for c in mesh.coarser:
        log.warning("%s: %s drawn at level %d (%s): missing %s", district, c.tile, c.level, c.drawn,
                    ", ".join(c.missing))
    index_path = Path(index_path)
    return write_chunks(mesh, district, chunk_size, index_path.parent, index_path)
