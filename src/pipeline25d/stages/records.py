"""The records that pass between stages: frozen and typed, each with one round trip to its file form.

A plan is written once by its checkpoint and read by the rules, the render jobs, the warp and
the report; its tiles, their chunk entries and GCP candidates are records too, as are a
district's LOD chunks, the scene and the GCP rows of the CSV tables. ``from_json``/``to_json``
(``from_row``/``to_row`` for CSV rows) give back exactly what was read, key order included, so
files written from records are the files written before the records existed. Nothing is
mutable: sequences are tuples and mappings read-only (``MappingProxyType``); a changed record
is a new one (``dataclasses.replace``).
"""

from __future__ import annotations

import json
import math
from collections.abc import Mapping
from dataclasses import dataclass, fields
from functools import cache
from pathlib import Path
from types import MappingProxyType
from typing import Any, ClassVar

from pipeline25d.core.grid import Extent, Grid
from pipeline25d.core.mesh import Coarser
from pipeline25d.geometry.perspectives import Perspective


def frozen(value: Any) -> Any:
    """A JSON value made immutable: objects as read-only mappings, arrays as tuples."""
    if isinstance(value, Mapping):
        return MappingProxyType({k: frozen(v) for k, v in value.items()})
    if isinstance(value, (list, tuple)):
        return tuple(frozen(v) for v in value)
    return value


def thawed(value: Any) -> Any:
    """The JSON form of a :func:`frozen` value (and of records inside it)."""
    if hasattr(value, "to_json"):
        return value.to_json()
    if isinstance(value, Mapping):
        return {k: thawed(v) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return [thawed(v) for v in value]
    return value


# --------------------------------------------------------------------------- ingest


def coarser_tiles(index: Mapping[str, Any]) -> tuple[Coarser, ...]:
    """The input tiles a district's chunk index (``chunks/<district>/index.json``) says were
    drawn coarser than the gsd asks for (none: the key is absent)."""
    return tuple(Coarser.from_json(c) for c in index.get("coarser", ()))


# --------------------------------------------------------------------------- GCPs

@dataclass(frozen=True)
class GcpCandidate:
    """A ground control point candidate: its ground position (x, y, z), the DTM height and slope
    (dz/dx, dz/dy) under it, and its role (``gcp`` fits the warp, ``check`` only scores it)."""

    id: str
    x: float
    y: float
    z: float
    ground: float
    sx: float
    sy: float
    role: str

    FIELDS: ClassVar[tuple[str, ...]] = ("id", "x", "y", "z", "ground", "sx", "sy", "role")
    TEXT: ClassVar[frozenset[str]] = frozenset({"id", "role"})

    @classmethod
    def from_row(cls, row: Mapping[str, Any]):
        """From a CSV row (numbers as text; an empty cell is 0) or a JSON object."""
        return cls(*[parse(row[name]) for name, parse in _parsers(cls)])

    from_json = from_row

    def to_row(self) -> dict[str, Any]:
        return {k: getattr(self, k) for k in self.FIELDS}

    to_json = to_row


@dataclass(frozen=True)
class Observation(GcpCandidate):
    """A candidate seen whole on the model in a tile: where its marker's centroid lies on the map."""

    map_x: float
    map_y: float
    n_pixels: int

    FIELDS: ClassVar[tuple[str, ...]] = GcpCandidate.FIELDS + ("map_x", "map_y", "n_pixels")


def _float(value: Any) -> float:
    return 0.0 if value in ("", None) else float(value)


def _int(value: Any) -> int:
    return 0 if value in ("", None) else int(float(value))


@cache
def _parsers(cls: type) -> tuple[tuple[str, Any], ...]:
    """(field, text -> value) of a GCP record class, in field order, made once per class (a plan's
    tiles hold thousands of candidates and every render job reads them all)."""
    return tuple((f.name, str if f.name in cls.TEXT else _int if f.type in ("int", int) else _float)
                 for f in fields(cls))


# --------------------------------------------------------------------------- chunks and scene

@dataclass(frozen=True)
class LodChunk:
    """One chunk of a district's LOD index: its bounds (2 x 3, scene CRS), the error of each level
    (m), triangles per level, the content hash, and its LOD file."""

    id: str
    district: str
    bounds: tuple[tuple[float, float, float], tuple[float, float, float]]
    errors: tuple[float, ...]
    triangles: tuple[int, ...]
    hash: str
    npz: str

    @classmethod
    def from_index(cls, cid: str, district: str, entry: Mapping[str, Any], npz: str) -> LodChunk:
        return cls(cid, district, frozen(entry["bounds"]), tuple(entry["errors"]), tuple(entry["triangles"]),
                   entry["hash"], npz)


@dataclass(frozen=True)
class ChunkGround:
    """The DTM under a chunk's footprint: its lowest and highest height (m, widened by a margin)
    and a digest of the samples, which enters the tile spec (terrain-relative maps)."""

    lowest: float
    highest: float
    digest: str


@dataclass(frozen=True)
class Scene:
    """``scene.json``: the scene's bounds, reference plane, terrain and projection, GCP counts."""

    bounds: tuple[tuple[float, float, float], tuple[float, float, float]]
    z0: float
    terrain: str
    projection: str
    dtm: str | None
    n_candidates: int
    n_check: int
    dtm_check_holdout_m: float | None
    n_chunks: int

    @classmethod
    def from_json(cls, data: Mapping[str, Any]) -> Scene:
        return cls(**{f.name: frozen(data[f.name]) for f in fields(cls)})

    def to_json(self) -> dict[str, Any]:
        return {f.name: thawed(getattr(self, f.name)) for f in fields(self)}

    @classmethod
    def read(cls, path: str | Path) -> Scene:
        return cls.from_json(json.loads(Path(path).read_text()))


# --------------------------------------------------------------------------- plan

def tile_span(pixel: float, tile_size: int) -> float:
    """A tile's edge in metres: ``tile_size`` pixels of ``pixel`` metres."""
    return pixel * tile_size


#: overlaps shorter than this share of a cell do not count (a box 1 µm short of a cell edge,
#: as an ECEF round trip leaves it, would otherwise get a column of empty tiles)
EDGE_TOLERANCE = 1e-6


def index_range(lo: float, hi: float, span: float) -> range:
    """Cells of a grid of ``span`` (origin 0) that [lo, hi] overlaps by more than
    :data:`EDGE_TOLERANCE` of a cell (one cell at least): a box ending on a cell edge, or a hair
    past it, does not reach the next cell, which would get an empty job."""
    first = math.floor(lo / span + EDGE_TOLERANCE)
    return range(first, max(math.ceil(hi / span - EDGE_TOLERANCE), first + 1))


def camera_of(projection: str | None) -> str:
    """The camera a projection renders with: the paper's image plane, else the map-aligned one."""
    return "paper" if projection == "paper" else "map"


def tile_extent(pixel: float, tile_size: int, row: int, col: int, margin_px: int = 0) -> Extent:
    """Extent of tile (row, col) of the global grid of ``tile_size`` pixels of ``pixel`` metres,
    optionally grown by ``margin_px`` pixels on every side."""
    span, m = tile_span(pixel, tile_size), margin_px * pixel
    return Extent(col * span - m, row * span - m, (col + 1) * span + m, (row + 1) * span + m)


@dataclass(frozen=True)
class ChunkRef:
    """A chunk as a tile draws it: which chunk, at which LOD, its plan-view box (x0, y0, x1, y1), and
    what its pixels depend on (content hash; digest of the DTM under it in terrain mode)."""

    id: str
    district: str
    lod: int
    xy: tuple[float, float, float, float]
    hash: str | None = None
    ground: str | None = None

    @classmethod
    def from_json(cls, data: Mapping[str, Any]) -> ChunkRef:
        return cls(data["id"], data["district"], data["lod"], tuple(data["xy"]), data.get("hash"), data.get("ground"))

    def to_json(self) -> dict[str, Any]:
        out = {"id": self.id, "district": self.district, "lod": self.lod, "xy": list(self.xy)}
        if self.hash is not None:
            out["hash"] = self.hash
        if self.ground is not None:
            out["ground"] = self.ground
        return out


@dataclass(frozen=True)
class TileShadow:
    """A tile's sun shadows: the other tiles' chunks that can shadow it, its shadow map's window on the
    scene's texel grid and its depth (height) range."""

    casters: tuple[ChunkRef, ...]
    window: tuple[int, ...]
    depth: tuple[float, float]

    @classmethod
    def from_json(cls, data: Mapping[str, Any]) -> TileShadow:
        return cls(tuple(ChunkRef.from_json(c) for c in data["casters"]), tuple(data["window"]), tuple(data["depth"]))

    def to_json(self) -> dict[str, Any]:
        return {"casters": [c.to_json() for c in self.casters], "window": list(self.window), "depth": list(self.depth)}


@dataclass(frozen=True)
class Tile:
    """One tile of a plan: its place on the global grid, the chunks it draws, the view-depth range,
    its content box (what can hold data), the GCP candidates it shows, its render settings, the
    hash of everything its files depend on (``spec_hash``) and of what its image depends on
    (``image_hash``: the same less its GCPs)."""

    row: int
    col: int
    chunks: tuple[ChunkRef, ...]
    depth_range: tuple[float, float]
    content: tuple[float, float, float, float]
    gcps: tuple[GcpCandidate, ...]
    render: Mapping[str, Any]
    spec_hash: str
    shadow: TileShadow | None = None
    image_hash: str = ""       # its spec less its GCPs (plan.image_hash); "" in plans made before it

    @classmethod
    def from_json(cls, data: Mapping[str, Any]) -> Tile:
        shadow = data.get("shadow")
        return cls(data["row"], data["col"], tuple(ChunkRef.from_json(c) for c in data["chunks"]),
                   tuple(data["depth_range"]), tuple(data["content"]),
                   tuple(GcpCandidate.from_json(g) for g in data["gcps"]), frozen(data["render"]), data["spec_hash"],
                   TileShadow.from_json(shadow) if shadow is not None else None, data.get("image_hash", ""))

    def to_json(self) -> dict[str, Any]:
        out = {"row": self.row, "col": self.col, "chunks": [c.to_json() for c in self.chunks],
               "depth_range": list(self.depth_range), "content": list(self.content),
               "gcps": [g.to_json() for g in self.gcps]}
        if self.shadow is not None:
            out["shadow"] = self.shadow.to_json()
        out["render"] = thawed(self.render)
        out["spec_hash"] = self.spec_hash
        if self.image_hash:
            out["image_hash"] = self.image_hash
        return out

    @property
    def key(self) -> str:
        """``<row>_<col>``: the tile's file stem."""
        return f"{self.row}_{self.col}"

    @property
    def casters(self) -> tuple[ChunkRef, ...]:
        """The other tiles' chunks that can shadow what it draws (none without shadows)."""
        return self.shadow.casters if self.shadow is not None else ()


@dataclass(frozen=True)
class Plan:
    """One perspective's plan: the frame every tile shares and the non-empty tiles, north row first.

    ``pixel_size``: metres per render pixel (the gsd, or the paper camera's image-plane pixel);
    ``projection``: terrain, plane or paper; ``dtm``: the DTM a terrain-relative render reads."""

    perspective: Perspective
    crs: str
    z0: float
    gsd: float
    pixel_size: float
    tile_size: int
    projection: str
    dtm: str | None
    tiles: tuple[Tile, ...]
    n_tiles_total: int
    n_tiles_skipped: int
    shadows: Mapping[str, Any] | None = None

    @classmethod
    def from_json(cls, data: Mapping[str, Any]) -> Plan:
        p = data["perspective"]
        return cls(Perspective(p["azimuth"], p["elevation"]), data["crs"], data["z0"], data["gsd"],
                   data.get("pixel_size", data["gsd"]), data["tile_size"], data.get("projection", "plane"),
                   data.get("dtm"), tuple(Tile.from_json(t) for t in data["tiles"]), data["n_tiles_total"],
                   data["n_tiles_skipped"], frozen(data["shadows"]) if data.get("shadows") else None)

    def to_json(self) -> dict[str, Any]:
        p = self.perspective
        out = {"perspective": {"id": p.id, "azimuth": p.azimuth, "elevation": p.elevation},
               "crs": self.crs, "z0": self.z0, "gsd": self.gsd, "pixel_size": self.pixel_size,
               "tile_size": self.tile_size, "projection": self.projection, "dtm": self.dtm,
               "tiles": [t.to_json() for t in self.tiles],
               "n_tiles_total": self.n_tiles_total, "n_tiles_skipped": self.n_tiles_skipped}
        if self.shadows:
            out["shadows"] = thawed(self.shadows)
        return out

    @property
    def id(self) -> str:
        """The perspective's id, e.g. ``az045_el45``."""
        return self.perspective.id

    @property
    def camera(self) -> str:
        """The camera the tiles are rendered with: the paper's image plane, else the map-aligned one."""
        return camera_of(self.projection)

    @property
    def span(self) -> float:
        """A tile's edge in metres (of map, or of the paper camera's image plane)."""
        return tile_span(self.pixel_size, self.tile_size)

    def tile_extent(self, row: int, col: int, margin_px: int = 0) -> Extent:
        """Extent of tile (row, col), optionally grown by ``margin_px`` pixels on every side."""
        return tile_extent(self.pixel_size, self.tile_size, row, col, margin_px)

    def content(self, tile: Tile) -> tuple[Extent, tuple[int, int]]:
        """The extent a tile renders (its content box, whole pixels) and its size in pixels."""
        e, px = Extent(*tile.content), self.pixel_size
        return e, (max(round((e.xmax - e.xmin) / px), 1), max(round((e.ymax - e.ymin) / px), 1))

    def tile_grid(self, tile: Tile) -> Grid:
        """The pixel grid a tile renders (its content box, north up)."""
        e, (w, h) = self.content(tile)
        return Grid.north_up(e.xmin, e.ymax, self.pixel_size, w, h)
