"""The tile tree of a 3D Tiles tileset: explicit tiles, external tilesets and implicit tiling
(3D Tiles 1.1 ``implicitTiling``, quadtree or octree, binary or JSON subtrees, expanded lazily),
and the choice of the tiles drawn at a geometric error (:func:`select`).

Over 400 lines: explicit tiles, external tilesets and implicit subtrees are nodes of the one tree
that one stack walks, with one rule for unreachable children.

The tree is walked with an explicit stack, so its depth is bounded by nothing but the JSON reader
(Python's ``json`` refuses about 1000 nested objects and arrays, about 490 levels of
``children`` in one file: an InputFileError naming the file). External tilesets that lead back to
one already entered are refused as a cycle. A tileset may name the same external tileset many
times (with different transforms: that is legitimate, so nothing is merged), each parsed once;
a tree that expands to more than :data:`MAX_TILES` tiles is refused with the count (external
tilesets named over and over multiply: ten names of a tileset that names ten... is 10^k tiles).

**Unreachable child content.** Where a child tile's content file (or the external tileset it
names) is missing, the finest level present is drawn, as a 3D Tiles renderer does while a
child cannot be loaded: a REPLACE tile is not refined and draws its own content (a tile
without content has nothing coarser: its reachable children are drawn, the unreachable ones
leave a hole); under ADD the parent is drawn anyway, and only the missing content is left
out. Each such tile is a :class:`~pipeline25d.core.mesh.Coarser`; with ``missing_children:
error`` it is an InputFileError instead. Content missing from the root tile is always an error.
"""

from __future__ import annotations

import json
import struct
from dataclasses import dataclass, field
from pathlib import Path
from typing import Callable

import numpy as np

from pipeline25d.core.errors import InputFileError, UnsupportedFeatureError
from pipeline25d.core.mesh import Coarser
from pipeline25d.formats.common import read_text, side_file
from pipeline25d.formats.gzipped import file_bytes

#: the most tiles one tileset's tree may expand to (external tilesets included, every time
#: they are named); beyond it the tileset is refused
MAX_TILES = 100_000


# --------------------------------------------------------------------------- tile tree


@dataclass
class _Tile:
    """A tile of the (explicit or implicit) tree with its composed world transform."""

    geometric_error: float
    refine: str
    transform: np.ndarray
    contents: list[Path]
    externals: list[Path]
    children: Callable[[], list["_Tile"]] = field(default=lambda: [])
    has_children: bool = False
    missing: list[Path] = field(default_factory=list)   # content files (or external tilesets) absent
    depth: int = 0                                        # tiles above it, from the input's root
    json_path: Path = Path()                              # the tileset JSON that holds it


@dataclass
class _External:
    """An external tileset to enter (``tile`` names it), or with ``leave`` the end of one."""

    path: Path
    tile: _Tile | None = None
    leave: bool = False


@dataclass
class Selection:
    """What :func:`select` chose: (content path, transform) of the tiles drawn, depth first in
    file order, and the tiles drawn coarser than asked because children are unreachable."""

    contents: list[tuple[Path, np.ndarray]] = field(default_factory=list)
    coarser: list[Coarser] = field(default_factory=list)


def select(root_path: Path, g: float | None, missing_children: str = "coarser") -> Selection:
    """The tiles of the tileset ``root_path`` drawn at geometric error ``g`` (None: every leaf),
    walked with an explicit stack (no recursion however deep the tree); every file they name
    lies in the root tileset's folder. See the module docstring for unreachable children."""
    files = _Files(root_path.parent)
    root = _json_tile(_root_of(read_json(root_path, files.jsons), root_path), root_path, np.eye(4), "REPLACE", files)
    if root.missing:
        raise InputFileError(root.missing[0], f"content referenced by {root_path} is missing")
    out = Selection()
    chain = {root_path.resolve(): root_path}   # the external tilesets being walked, outermost first
    stack: list[_Tile | _External] = [root]
    walked = 0
    while stack:
        item = stack.pop()
        if isinstance(item, _External):
            if item.leave:
                chain.popitem()
            else:
                stack += _enter(item, chain, files)
            continue
        walked += 1
        if walked > MAX_TILES:
            raise InputFileError(root_path, f"the tile tree expands to more than {MAX_TILES} tiles ({len(files.jsons)} "
                                            "tileset files, some named many times?); pipeline25d reads at most "
                                            f"{MAX_TILES} tiles of a tileset")
        tile = item
        refine = tile.has_children and (g is None or tile.geometric_error > g)
        kids = tile.children() if refine else []
        unreachable = [k for k in kids if k.missing]
        if unreachable:
            if missing_children == "error":
                first = unreachable[0]
                raise InputFileError(first.missing[0], f"content referenced by {first.json_path} is missing (the "
                                                       "input's missing_children: coarser draws the level present)")
            kids = _reachable(tile, kids, unreachable, out.coarser)
            refine = refine and bool(kids)
        if not refine or tile.refine == "ADD":
            out.contents.extend((c, tile.transform) for c in tile.contents)
        stack += [_External(ext, tile) for ext in reversed(tile.externals)]
        stack += reversed(kids)
    return out


def _reachable(tile: _Tile, kids: list[_Tile], unreachable: list[_Tile], coarser: list[Coarser]) -> list[_Tile]:
    """The children of ``tile`` to walk where ``unreachable`` of them have content missing, with
    what is drawn instead noted in ``coarser`` (module docstring): none under REPLACE when the
    tile has content of its own, else the children without their missing content."""
    missing = tuple(str(p) for k in unreachable for p in k.missing)
    name = ", ".join(str(p) for p in tile.contents + tile.externals) or f"a tile without content in {tile.json_path}"
    if tile.refine == "REPLACE" and (tile.contents or tile.externals):
        coarser.append(Coarser(name, tile.depth, missing, "the parent tile's content (refine REPLACE)"))
        return []
    drawn = ("the parent tile's content, the missing content left out (refine ADD)" if tile.refine == "ADD"
             else "nothing there: the parent tile has no content (refine REPLACE)")
    coarser.append(Coarser(name, tile.depth, missing, drawn))
    if tile.refine == "REPLACE":
        return [k for k in kids if not k.missing]
    for k in unreachable:   # ADD: what the child adds is left out, its children still add theirs
        k.missing = []
    return kids


def _enter(ext: _External, chain: dict[Path, Path], files: _Files) -> list[_Tile | _External]:
    """What the stack gets to walk the external tileset ``ext``: its root, then its end marker."""
    key = files.real(ext.path)
    if key in chain:
        names = list(chain.values())
        loop = [p.name for p in names[list(chain).index(key):]] + [ext.path.name]
        raise InputFileError(ext.path, f"external tilesets form a cycle ({' -> '.join(loop)})")
    chain[key] = ext.path
    ext_json = read_json(ext.path, files.jsons)
    root = _json_tile(_root_of(ext_json, ext.path), ext.path, ext.tile.transform, ext.tile.refine, files,
                      ext.tile.depth + 1)
    if root.missing:
        raise InputFileError(root.missing[0], f"content referenced by the root tile of {ext.path} is missing")
    return [_External(ext.path, leave=True), root]


class _Files:
    """What one walk of a tileset has learnt about its files: the root ``folder`` they must lie
    in, the parsed tileset JSONs, and each URI a JSON names resolved (a tileset named many times
    costs its files once)."""

    def __init__(self, folder: Path):
        self.folder = folder
        self.jsons: dict[Path, dict] = {}
        self._refs: dict[tuple[str | None, Path], tuple[Path, bool]] = {}
        self._real: dict[Path, Path] = {}

    def real(self, path: Path) -> Path:
        """``path`` resolved (the key of an external tileset in a chain)."""
        if path not in self._real:
            self._real[path] = path.resolve()
        return self._real[path]

    def content(self, uri: str | None, json_path: Path) -> tuple[Path, bool]:
        """(path, whether the file is there) of a content URI ``json_path`` names."""
        key = (uri, json_path)
        if key not in self._refs:
            path = resolve(uri, json_path, self.folder)
            self._refs[key] = path, path.is_file()
        return self._refs[key]


def _json_tile(tile: dict, json_path: Path, parent_transform: np.ndarray, parent_refine: str,
               files: _Files, depth: int = 0) -> _Tile:
    """A :class:`_Tile` from a tileset JSON tile object (children built on demand)."""
    own = tile.get("transform")
    transform = parent_transform if own is None else parent_transform @ tile_matrix(own, json_path)
    refine = str(tile.get("refine", parent_refine)).upper()
    if "implicitTiling" in tile:
        return _implicit_root(tile, json_path, transform, refine, files.folder, depth)
    uris = [c["uri"] if "uri" in c else c.get("url") for c in _content_list(tile)]
    contents, externals, missing = _split_contents([files.content(u, json_path) for u in uris])
    kids = tile.get("children") or []
    return _Tile(
        geometric_error=float(tile.get("geometricError", 0.0)),
        refine=refine,
        transform=transform,
        contents=contents,
        externals=externals,
        children=lambda: [_json_tile(c, json_path, transform, refine, files, depth + 1) for c in kids],
        has_children=bool(kids),
        missing=missing,
        depth=depth,
        json_path=json_path,
    )


def _split_contents(found: list[tuple[Path, bool]]) -> tuple[list[Path], list[Path], list[Path]]:
    """(renderable contents, external tileset JSONs, files that are missing) of (path, present) pairs."""
    here = [p for p, present in found if present]
    return ([p for p in here if p.suffix.lower() != ".json"], [p for p in here if p.suffix.lower() == ".json"],
            [p for p, present in found if not present])


def _content_list(tile: dict) -> list[dict]:
    """The tile's content objects (1.0 ``content``, 1.1 ``contents``)."""
    contents = list(tile.get("contents") or [])
    if tile.get("content"):
        contents.insert(0, tile["content"])
    return contents


def _root_of(tileset: dict, path: Path) -> dict:
    root = tileset.get("root")
    if not isinstance(root, dict):
        raise InputFileError(path, "tileset JSON has no root tile")
    return root


def tile_matrix(values: list | None, where: Path) -> np.ndarray:
    """4x4 float64 matrix from a column-major 16-number list (identity when absent)."""
    if values is None:
        return np.eye(4)
    try:
        return np.asarray(values, dtype=np.float64).reshape(4, 4).T
    except ValueError:
        raise InputFileError(where, f"tile transform is not 16 numbers: {values!r}") from None


def resolve(uri: str | None, base: Path, folder: Path) -> Path:
    """Local path of a content/subtree URI relative to the JSON (or subtree) that names it,
    inside the tileset's root ``folder``."""
    if not uri:
        raise InputFileError(base, "tile content without uri")
    return side_file(uri, base.parent, folder, base, "content")


#: tileset extensions read (glTF content) or whose absence leaves the drawing unchanged (metadata, the
#: batch table hierarchy, Draco in point clouds, which are not drawn); a tileset that requires any other
#: (the pre-1.1 drafts of implicit tiling and multiple contents, S2 bounding volumes ...) is refused naming it
TILESET_EXTENSIONS = frozenset({"3DTILES_content_gltf", "3DTILES_metadata", "3DTILES_batch_table_hierarchy",
                                "3DTILES_draco_point_compression"})


def read_json(path: Path, cache: dict[Path, dict] | None = None) -> dict:
    """Parsed tileset JSON (each file parsed once per ``cache``); InputFileError when missing,
    invalid or nested too deep to parse."""
    if cache is not None and path in cache:
        return cache[path]
    text = read_text(path, "tileset JSON")
    try:
        data = json.loads(text)
    except json.JSONDecodeError as exc:
        raise InputFileError(path, f"invalid JSON: {exc}") from None
    except RecursionError:
        raise InputFileError(path, "JSON nested deeper than the JSON reader allows (about 1000 objects and "
                                   "arrays; a tile tree that deep belongs in external tilesets)") from None
    if not isinstance(data, dict):
        raise InputFileError(path, "tileset JSON is not an object")
    required = data.get("extensionsRequired") or []
    if not isinstance(required, list):
        raise InputFileError(path, f"extensionsRequired is not an array: {required!r}")
    unsupported = [str(e) for e in required if e not in TILESET_EXTENSIONS]
    if unsupported:
        raise UnsupportedFeatureError(path, f"tileset requires unsupported extension(s) {', '.join(unsupported)}"
                                            " (3D Tiles 1.1 has implicit tiling, multiple contents and metadata"
                                            " in its core: a tileset written to 1.1 reads)")
    if cache is not None:
        cache[path] = data
    return data


# --------------------------------------------------------------------------- implicit tiling


@dataclass
class _Subtree:
    """Availability bitstreams of one implicit-tiling subtree."""

    tiles: np.ndarray
    contents: list[np.ndarray]
    child_subtrees: np.ndarray


@dataclass
class _Implicit:
    """Shared state of an implicit tileset: templates, scheme, subtree cache."""

    json_path: Path
    branching: int
    subtree_levels: int
    available_levels: int
    subtree_uri: str
    content_uris: list[str]
    root_error: float
    refine: str
    transform: np.ndarray
    folder: Path              # the tileset's root folder (every file named must lie in it)
    depth: int = 0            # tiles above the implicit root
    cache: dict = field(default_factory=dict)

    def uri(self, template: str, level: int, xyz: tuple[int, int, int]) -> Path:
        text = (template.replace("{level}", str(level)).replace("{x}", str(xyz[0]))
                .replace("{y}", str(xyz[1])).replace("{z}", str(xyz[2])))
        return resolve(text, self.json_path, self.folder)

    def subtree(self, level: int, xyz: tuple[int, int, int]) -> _Subtree:
        key = (level, xyz)
        if key not in self.cache:
            self.cache[key] = _read_subtree(self.uri(self.subtree_uri, level, xyz), self)
        return self.cache[key]


def _implicit_root(tile: dict, json_path: Path, transform: np.ndarray, refine: str, folder: Path,
                   depth: int = 0) -> _Tile:
    """Root :class:`_Tile` of an implicit tileset (3D Tiles 1.1 ``implicitTiling``)."""
    spec = tile["implicitTiling"]
    scheme = str(spec.get("subdivisionScheme", "")).upper()
    if scheme not in ("QUADTREE", "OCTREE"):
        raise UnsupportedFeatureError(json_path, f"implicit subdivisionScheme {scheme!r} is not supported")
    try:
        levels = int(spec["availableLevels"]) if "availableLevels" in spec else int(spec["maximumLevel"]) + 1
        ctx = _Implicit(json_path, 4 if scheme == "QUADTREE" else 8, int(spec["subtreeLevels"]), levels,
                        spec["subtrees"]["uri"], [c["uri"] for c in _content_list(tile)],
                        float(tile.get("geometricError", 0.0)), refine, transform, folder, depth)
    except (KeyError, TypeError, ValueError) as exc:
        raise InputFileError(json_path, f"incomplete implicitTiling object: {exc}") from None
    return _implicit_tile(ctx, ctx.subtree(0, (0, 0, 0)), 0, 0, 0, (0, 0, 0))


def _implicit_tile(ctx: _Implicit, sub: _Subtree, sub_level: int, local_level: int, morton: int,
                   xyz: tuple[int, int, int]) -> _Tile:
    """The available tile at local (level, morton) of subtree ``sub`` rooted at ``sub_level``."""
    level = sub_level + local_level
    bit = _level_offset(ctx.branching, local_level) + morton
    contents, externals, missing = _split_contents(
        [(p, p.is_file()) for p in (ctx.uri(t, level, xyz) for t, avail in zip(ctx.content_uris, sub.contents)
                                    if _bit(avail, bit))])

    available = []  # (morton, xyz, inside this subtree) of each available child
    if level + 1 < ctx.available_levels:
        for c in range(ctx.branching):
            child_xyz = tuple(2 * v + ((c >> i) & 1) for i, v in enumerate(xyz))
            child_morton = morton * ctx.branching + c
            if local_level + 1 < ctx.subtree_levels:
                if _bit(sub.tiles, _level_offset(ctx.branching, local_level + 1) + child_morton):
                    available.append((child_morton, child_xyz, True))
            elif _bit(sub.child_subtrees, child_morton):
                available.append((child_morton, child_xyz, False))

    def children() -> list[_Tile]:
        return [_implicit_tile(ctx, sub, sub_level, local_level + 1, m, c_xyz) if inside
                else _implicit_tile(ctx, ctx.subtree(level + 1, c_xyz), level + 1, 0, 0, c_xyz)
                for m, c_xyz, inside in available]

    return _Tile(
        geometric_error=ctx.root_error / 2.0 ** level,
        refine=ctx.refine,
        transform=ctx.transform,
        contents=contents,
        externals=externals,
        children=children,
        has_children=bool(available),
        missing=missing,
        depth=ctx.depth + level,
        json_path=ctx.json_path,
    )


def _level_offset(branching: int, level: int) -> int:
    """Index of the first bit of ``level`` in a subtree's tile availability bitstream."""
    return (branching ** level - 1) // (branching - 1)


def _bit(bits: np.ndarray, index: int) -> bool:
    """Bit ``index`` of a little-endian-bit-order bitstream (or a constant: 0-d array)."""
    if bits.ndim == 0:
        return bool(bits)
    byte = index >> 3
    return byte < len(bits) and bool((bits[byte] >> (index & 7)) & 1)


def _read_subtree(path: Path, ctx: _Implicit) -> _Subtree:
    """Parse a binary (``subt``) or JSON subtree file into availability bitstreams."""
    try:
        data = file_bytes(path)
    except FileNotFoundError:
        raise InputFileError(path, f"subtree file named by {ctx.json_path} is missing") from None
    if data[:4] == b"subt":
        if len(data) < 24:
            raise InputFileError(path, "subtree file is truncated")
        json_len, bin_len = struct.unpack_from("<QQ", data, 8)
        if 24 + json_len + bin_len > len(data):
            raise InputFileError(path, "subtree file is shorter than its header says (truncated)")
        raw_json, internal = data[24:24 + json_len], data[24 + json_len:24 + json_len + bin_len]
    else:
        raw_json, internal = data, b""
    try:
        doc = json.loads(raw_json.decode("utf-8"))
    except (UnicodeDecodeError, json.JSONDecodeError) as exc:
        raise InputFileError(path, f"subtree JSON is invalid: {exc}") from None
    buffers = [internal if "uri" not in b else _read_buffer(resolve(b["uri"], path, ctx.folder), path)
               for b in doc.get("buffers", [])]

    def availability(obj: dict | None) -> np.ndarray:
        if obj is None:
            return np.array(0, dtype=np.uint8)
        if "constant" in obj:
            return np.array(int(obj["constant"]), dtype=np.uint8)
        view = doc["bufferViews"][int(obj.get("bitstream", obj.get("bufferView")))]
        buf = buffers[int(view["buffer"])]
        start = int(view.get("byteOffset", 0))
        return np.frombuffer(buf, np.uint8, int(view["byteLength"]), start)

    try:
        contents = doc.get("contentAvailability") or []
        if isinstance(contents, dict):
            contents = [contents]
        return _Subtree(availability(doc.get("tileAvailability")), [availability(c) for c in contents],
                        availability(doc.get("childSubtreeAvailability")))
    except (KeyError, IndexError, TypeError, ValueError) as exc:
        raise InputFileError(path, f"malformed subtree availability: {exc}") from None


def _read_buffer(path: Path, subtree: Path) -> bytes:
    """The bytes of a subtree's external buffer; InputFileError naming both when unreadable."""
    try:
        return file_bytes(path)
    except OSError as exc:
        raise InputFileError(path, f"subtree buffer named by {subtree} cannot be read: {exc.strerror or exc}") from None


