"""LOD pyramid per chunk with fast-simplification, each level with its measured error.

Level 0 is the chunk as ingested; level k keeps about 2^-k of the triangles. Open borders
(chunk seams) are never collapsed, so adjacent chunks do not crack. The error of a level is
the Hausdorff distance (metres) between level 0 and the level, both ways, on sample points
(:func:`surface_error`), and for textured parts at least how far the texture moves on the surface
(:func:`texture_drift`). Building stops at the first level whose error exceeds ``max_error`` (the
coarsest error any configured pixel size can use), so no level finer than needed and no
level too coarse to use is kept; such a level is dropped at the first sample found beyond
``max_error``, its exact error never needed (a 3 x 3 Delft LiDAR district: 5x less CPU, no
level kept either way). UVs and vertex colours ride through the collapses: each
new vertex takes the mean of the original vertices merged into it.
"""

from __future__ import annotations

import json
import logging
from collections.abc import Callable
from pathlib import Path

import numpy as np

from pipeline25d.core.atomic import write_json
from pipeline25d.core.mesh import Mesh, MeshPart
from pipeline25d.geometry.proximity import surface_distances
from pipeline25d.stages.chunks import content_hash, load_npz, pack_parts, save_npz, unpack_parts
from pipeline25d.stages.records import LodChunk

log = logging.getLogger(__name__)

MIN_TRIANGLES = 64          # parts smaller than this are kept as they are
ERROR_SAMPLE = 4000         # level-0 vertices sampled per part to measure error
MIN_GAIN = 0.85             # a level must have at most this share of the previous level's triangles
PROBE = 16                  # with a bound, every PROBE-th sample point is measured first (see surface_error)


def simplify_part(part: MeshPart, reduction: float) -> MeshPart:
    """``part`` with about ``reduction`` of its triangles removed (attributes carried)."""
    return _simplify(part, reduction)[0]


def _simplify(part: MeshPart, reduction: float) -> tuple[MeshPart, np.ndarray | None]:
    """:func:`simplify_part` and the new vertex of every original vertex (None: unchanged)."""
    import fast_simplification

    if part.n_triangles < MIN_TRIANGLES or reduction <= 0:
        return part, None
    # Simplify relative to the part's centre: quadrics of UTM-sized coordinates lose precision.
    centre = part.vertices.mean(axis=0)
    local = part.vertices - centre
    points, faces, collapses = fast_simplification.simplify(
        local, part.faces, target_reduction=reduction, return_collapses=True, preserve_border=True)
    _, _, mapping = fast_simplification.replay_simplification(local, part.faces, collapses)
    objects = None
    if part.face_objects is not None:      # the faces left are the originals that did not collapse, in order
        moved = mapping[part.faces]
        kept = (moved[:, 0] != moved[:, 1]) & (moved[:, 1] != moved[:, 2]) & (moved[:, 0] != moved[:, 2])
        objects = part.face_objects[kept]
    return MeshPart(vertices=points + centre, faces=faces,
                    colors=_carry(part.colors, mapping, len(points), np.uint8),
                    uv=_carry(part.uv, mapping, len(points), np.float32),
                    texture=part.texture, name=part.name, objects=part.objects, face_objects=objects,
                    object_ids=part.object_ids), mapping


def _carry(values: np.ndarray | None, mapping: np.ndarray, n_new: int, dtype) -> np.ndarray | None:
    """Average per-vertex ``values`` over the originals that map to each new vertex."""
    if values is None:
        return None
    sums = np.zeros((n_new, values.shape[1]), dtype=np.float64)
    counts = np.zeros(n_new, dtype=np.float64)
    np.add.at(sums, mapping, values.astype(np.float64))
    np.add.at(counts, mapping, 1.0)
    mean = sums / np.maximum(counts, 1)[:, None]
    return np.round(mean).astype(dtype) if dtype == np.uint8 else mean.astype(dtype)


def surface_error(original: MeshPart, simplified: MeshPart, rng: np.random.Generator,
                  bound: float = float("inf")) -> float:
    """Hausdorff distance (m) between the two surfaces, both ways, on sample points (exact
    point-to-surface distances, see :mod:`pipeline25d.geometry.proximity`; inf if nothing is left).

    Points are each surface's vertices, triangle centroids and edge midpoints (up to
    :data:`ERROR_SAMPLE` a side): vertices alone miss where a collapse lifts the surface
    between them, and the simplified surface can stray further from the original than the
    original from it (on a bumpy grid, vertices one way gave 0.78-0.80 of the dense two-way
    Hausdorff distance).

    ``bound``: a level whose error exceeds it is not kept, so its exact error is never needed.
    Every :data:`PROBE`-th point of each side is measured first, and the first distance found
    above ``bound`` is returned (a value above it, not the largest). A level within the bound
    gets its exact error, from the same points as without one.
    """
    if simplified is original:
        return 0.0
    if not len(simplified.faces):
        return float("inf")
    origin = original.vertices[original.faces[0, 0]]
    a, b = _surface_points(original, rng) - origin, _surface_points(simplified, rng) - origin
    sides = ((a, simplified), (b, original))

    def farthest(points: np.ndarray, surface: MeshPart) -> float:
        return float(surface_distances(points, surface.vertices - origin, surface.faces).max())

    if bound < float("inf"):
        for points, surface in sides:
            probe = farthest(points[::PROBE], surface)
            if probe > bound:
                return probe
    error = 0.0
    for points, surface in sides:
        error = max(error, farthest(points, surface))
        if error > bound:
            break
    return error


def _surface_points(part: MeshPart, rng: np.random.Generator) -> np.ndarray:
    """Up to :data:`ERROR_SAMPLE` of the part's vertices, triangle centroids and edge midpoints."""
    tri = part.vertices[part.faces]
    used = np.zeros(len(part.vertices), dtype=bool)
    used[part.faces.ravel()] = True                  # the vertices of faces, in order (np.unique: 35x slower)
    points = np.concatenate([part.vertices[used], tri.mean(axis=1),
                             (tri + np.roll(tri, -1, axis=1)).reshape(-1, 3) / 2])
    if len(points) > ERROR_SAMPLE:
        points = points[rng.choice(len(points), ERROR_SAMPLE, replace=False)]
    return points


def texture_drift(original: MeshPart, simplified: MeshPart, mapping: np.ndarray | None,
                  rng: np.random.Generator) -> float:
    """How far (m) the texture moves on the surface: the largest distance, over sampled original
    vertices, between where a merged vertex now shows its (averaged) texture coordinate and where
    the original surface showed that coordinate. 0 for untextured or unchanged parts.

    Geometry alone misses this: collapses on a flat textured facade cost no geometric error,
    but each merged vertex carries the mean of its originals' texture coordinates to a new
    place, which shifts and shears the image on it (a checker drawn metres off on a
    photogrammetry tile). Where the original showed coordinate t is found through the affine
    texture map of a triangle at the original vertex (the one of largest texture area).
    """
    if mapping is None or original.uv is None or simplified.uv is None or original.texture is None:
        return 0.0
    faces, p, t = original.faces, original.vertices, original.uv.astype(np.float64)
    d1, d2 = t[faces[:, 1]] - t[faces[:, 0]], t[faces[:, 2]] - t[faces[:, 0]]
    det = d1[:, 0] * d2[:, 1] - d1[:, 1] * d2[:, 0]          # twice the signed texture area
    best = np.zeros(len(p))
    np.maximum.at(best, faces.ravel(), np.repeat(np.abs(det), 3))
    tri = np.full(len(p), -1)
    corners = np.flatnonzero(np.repeat(np.abs(det), 3) == best[faces.ravel()])
    tri[faces.ravel()[corners]] = corners // 3
    verts = np.flatnonzero((tri >= 0) & (best > 0))
    if len(verts) > ERROR_SAMPLE:
        verts = verts[rng.choice(len(verts), ERROR_SAMPLE, replace=False)]
    if not len(verts):
        return 0.0
    f = faces[tri[verts]]
    new = mapping[verts]
    # solve t_new - t0 = a d1 + b d2 in the triangle's texture map, then place a, b on its edges
    rhs = simplified.uv[new].astype(np.float64) - t[f[:, 0]]
    k = tri[verts]
    a = (rhs[:, 0] * d2[k, 1] - rhs[:, 1] * d2[k, 0]) / det[k]
    b = (d1[k, 0] * rhs[:, 1] - d1[k, 1] * rhs[:, 0]) / det[k]
    shown = p[f[:, 0]] + a[:, None] * (p[f[:, 1]] - p[f[:, 0]]) + b[:, None] * (p[f[:, 2]] - p[f[:, 0]])
    return float(np.linalg.norm(simplified.vertices[new] - shown, axis=1).max())


def build_levels(mesh: Mesh, max_error: float, max_levels: int, seed: int = 0) -> list[tuple[list[MeshPart], float]]:
    """[(parts, error_m), ...] from level 0 (error 0) to the coarsest usable level."""
    rng = np.random.default_rng(seed)
    levels = [(mesh.parts, 0.0)]
    for k in range(1, max_levels):
        reduction = 1.0 - 0.5 ** k
        parts, error = [], 0.0
        for part in mesh.parts:
            simple, mapping = _simplify(part, reduction)
            error = max(error, surface_error(part, simple, rng, max_error))
            if error > max_error:       # the level is not kept: its other parts need no simplifying
                break
            error = max(error, texture_drift(part, simple, mapping, rng))
            parts.append(simple)
        if error > max_error:
            break
        n_prev = sum(p.n_triangles for p in levels[-1][0])
        n_new = sum(p.n_triangles for p in parts)
        if n_new > MIN_GAIN * n_prev:
            break
        levels.append((parts, error))
    return levels


def choose_level(errors: list[float], max_error: float) -> int:
    """Index of the coarsest level whose error is at most ``max_error`` (0 if none)."""
    ok = [k for k, e in enumerate(errors) if e <= max_error]
    return max(ok) if ok else 0


#: the fewest triangles to build for which a district's chunks go to worker processes: less is about
#: a second of work (a 48k-triangle district took 0.27 s), done here sooner than workers are counted and forked
POOL_TRIANGLES = 200_000


def build_lod(chunk_index: str | Path, out_index: str | Path, max_error: float, max_levels: int,
              processes: int | Callable[[], int] = 1) -> dict:
    """Write the LOD pyramid of every chunk of a district beside ``out_index``, then the index.

    ``chunk_index``: the district's ingest index (its chunk npz files beside it). One npz per
    chunk (:func:`build_chunk_lod`); a chunk whose ingest hash and LOD parameters are those of
    the previous run keeps its file (and mtime), so no tile drawing it re-runs. The previous
    run's entries live in ``index.hashes.json``, which is no declared output: Snakemake deletes
    the index itself before the job. Files of chunks no longer in the district are removed.
    ``processes``: chunks built at once, each in a forked worker (a city that is one district,
    as one photogrammetry model is, then uses every core it is given); the files are the same.
    A function giving that count is asked only where the chunks to build hold at least
    :data:`POOL_TRIANGLES` (:func:`~pipeline25d.core.cores.job_workers` reads the machine's idle cores).
    Returns the index: {district, max_error, max_levels, chunks: {id: {bounds, errors, triangles, hash}}}.
    """
    chunk_index, out_index = Path(chunk_index), Path(out_index)
    ingested = json.loads(chunk_index.read_text())
    params = {"max_error": max_error, "max_levels": max_levels}
    sidecar = out_index.with_suffix(".hashes.json")
    kept = _reusable_lods(sidecar, params, ingested["chunks"], out_index.parent)
    # before any npz is rewritten: no false record survives a crash
    write_json(sidecar, {"params": params, "chunks": kept})
    todo = [cid for cid in sorted(ingested["chunks"]) if cid not in kept]
    pairs = [(chunk_index.parent / f"{cid}.npz", out_index.parent / f"{cid}.npz") for cid in todo]
    if callable(processes):
        small = sum(ingested["chunks"][cid].get("n_triangles", POOL_TRIANGLES) for cid in todo) < POOL_TRIANGLES
        processes = 1 if small or len(pairs) < 2 else processes()
    built = _built_chunks(pairs, max_error, max_levels, processes)
    record = {cid: kept.get(cid) or {"source": info["hash"], **built[cid]}
              for cid, info in sorted(ingested["chunks"].items())}
    _remove_stale_lods(out_index.parent, record)
    write_json(sidecar, {"params": params, "chunks": record})
    index = {"district": ingested["district"], **params,
             "chunks": {cid: {k: v for k, v in r.items() if k != "source"} for cid, r in record.items()}}
    write_json(out_index, index)
    log.info("%s: %d chunk LODs built, %d unchanged", ingested["district"], len(record) - len(kept), len(kept))
    return index


def _built_chunks(paths: list[tuple[Path, Path]], max_error: float, max_levels: int,
                  processes: int) -> dict[str, dict]:
    """{chunk id: :func:`build_chunk_lod`'s entry} of each (ingested npz, LOD npz) pair, in
    ``processes`` forked workers where more than one chunk and one process."""
    from functools import partial

    build = partial(_build_pair, max_error=max_error, max_levels=max_levels)
    processes = min(processes, len(paths))
    if processes <= 1:
        return dict(map(build, paths))
    from pipeline25d.core.cores import fork_pool

    log.info("%d chunks on %d processes", len(paths), processes)
    with fork_pool(processes) as pool:
        return dict(pool.map(build, paths))


def _build_pair(paths: tuple[Path, Path], max_error: float, max_levels: int) -> tuple[str, dict]:
    source, out = paths
    return source.stem, build_chunk_lod(source, out, max_error, max_levels)


def _reusable_lods(sidecar: Path, params: dict, chunks: dict[str, dict], out_dir: Path) -> dict[str, dict]:
    """The previous run's entries {id: {"source": ingest hash, ...}} still valid for ``chunks``."""
    if not sidecar.exists():
        return {}
    previous = json.loads(sidecar.read_text())
    if previous.get("params") != params:
        return {}
    return {cid: entry for cid, entry in previous["chunks"].items()
            if cid in chunks and entry["source"] == chunks[cid]["hash"] and (out_dir / f"{cid}.npz").exists()}


def _remove_stale_lods(out_dir: Path, keep: dict) -> None:
    """Remove LOD npz files of chunks not in ``keep``, and the per-chunk JSON of the former layout."""
    for path in [*out_dir.glob("c*.npz"), *out_dir.glob("c*.json")]:
        if path.suffix == ".json" or path.stem not in keep:
            path.unlink()


def build_chunk_lod(chunk_path: str | Path, out_npz: str | Path, max_error: float, max_levels: int) -> dict:
    """Write the LOD pyramid of one chunk (npz); returns its {bounds, errors, triangles, hash}."""
    data = load_npz(chunk_path)
    origin = data["origin"]
    mesh = Mesh(unpack_parts(data, origin), source=str(chunk_path))
    levels = build_levels(mesh, max_error=max_error, max_levels=max_levels)
    arrays = {"origin": origin, "n_levels": np.array(len(levels))}
    for k, (parts, _) in enumerate(levels):
        arrays.update(pack_parts(parts, origin, prefix=f"L{k}_"))
    save_npz(out_npz, arrays, compress=False)        # read by every render job that draws it
    return {"bounds": mesh.bounds().tolist(), "errors": [e for _, e in levels],
            "triangles": [sum(p.n_triangles for p in ps) for ps, _ in levels], "hash": content_hash(arrays)}


def lod_chunks(lod_indexes: list[str | Path]) -> list[LodChunk]:
    """Every chunk of the given district LOD indexes, in their order then by id."""
    out = []
    for path in lod_indexes:
        index = json.loads(Path(path).read_text())
        out += [LodChunk.from_index(cid, index["district"], entry, str(Path(path).parent / f"{cid}.npz"))
                for cid, entry in sorted(index["chunks"].items())]
    return out


def load_chunk_level(lod_npz: str | Path, level: int) -> tuple[np.ndarray, list]:
    data = load_npz(lod_npz)
    origin = data["origin"]
    level = min(level, int(data["n_levels"]) - 1)
    return origin, unpack_parts(data, origin, prefix=f"L{level}_")


def chunk_loaders(chunks: list[LodChunk], max_error: float) -> list[tuple[np.ndarray, object]]:
    """(bounds, load) per chunk of :func:`lod_chunks`; load() -> (origin, parts) at the coarsest
    LOD within ``max_error`` m."""
    from functools import partial

    return [(np.array(c.bounds), partial(load_chunk_level, c.npz, choose_level(c.errors, max_error)))
            for c in chunks]


def scene_bounds(chunks: list[LodChunk]) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Every chunk's bounds (n, 2, 3) and the scene's lowest and highest corners."""
    bounds = np.array([c.bounds for c in chunks])
    return bounds, bounds[:, 0].min(axis=0), bounds[:, 1].max(axis=0)
