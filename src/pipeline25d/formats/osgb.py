"""OpenSceneGraph binary models (OSGB) with PagedLOD, as ContextCapture / Smart3D export them.

A dataset is a folder ``<dataset>/Data/Tile_<x>_<y>/Tile_<x>_<y>.osgb`` (one root file per
tile; its PagedLOD children in further .osgb files beside it) with ``<dataset>/metadata.xml``
(SRS and SRSOrigin, see :mod:`pipeline25d.formats.contextcapture`); a single .osgb file is
read the same way from that file down.

OpenSceneGraph's own ``osgconv`` (Debian ``openscenegraph``, headless, optimizer off) does all
the binary reading: each visited file is converted to the ``.osgt`` text format, whose
PagedLOD/LOD nodes this module parses (range mode, range list, child file names, user
centre and radius, enclosing MatrixTransforms). The file is written back as .osgt with every
LOD node replaced by a Group of the children drawn at the map's pixel size and every image
renamed to a safe file name, and ``osgconv -O OutputTextureFiles`` turns that into OBJ + MTL +
uncompressed TGA textures (:data:`TEXTURE_SUFFIX`), read with trimesh (:mod:`pipeline25d.formats.meshfile`).

**Level rule.** In an orthographic map of ``gsd`` metres per pixel a node whose bounding
sphere has radius r covers 2·r/gsd pixels (OpenSceneGraph's ``CullStack::clampedPixelSize``
for an orthographic projection, LOD scale 1). A PIXEL_SIZE_ON_SCREEN LOD draws the children
whose range [min, max) holds that pixel size, as OSG would on screen; a child that lives in a
file is read and walked the same way with its own nodes. Beyond the largest max the children
with that max are drawn (the finest), below the smallest min those with that min (the
coarsest), so a very fine or very coarse map still gets geometry. ``gsd`` None (full detail)
draws the finest children everywhere. The level of a node is the number of files between it
and the tile's root file (0: the root file's own geometry).

**Missing children.** A PagedLOD child file that is absent (a partial export, a tile handed
over on its own) is what OpenSceneGraph meets while a child is still loading: it keeps
drawing what it has. So does this reader: where a chosen child file is missing, the node's
finest inline children (its own coarser level) are drawn instead, and one warning per tile
(also in the job's log) names the missing files and the level drawn there, which is coarser
than the gsd asks for. A missing root file (the one the input names, or a dataset's
``Tile_*/Tile_*.osgb``) is still an error.

Child files and texture files must lie inside the dataset folder (a single .osgb: its
folder), see :func:`~pipeline25d.formats.common.side_file`; a DatabasePath stored by the
producer's machine is used only when it leads there.

Over 400 lines for one job: one format's reader (dataset layout, PagedLOD levels and the
osgconv conversion are one path from folder to mesh).
"""

from __future__ import annotations

import argparse
import logging
import os
import re
import shutil
import sys
import tempfile
import warnings
from collections import Counter, deque
from collections.abc import Iterator
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, field, replace
from pathlib import Path

import numpy as np

from pipeline25d.core.errors import InputFileError, MissingTextureWarning, UnsupportedFeatureError
from pipeline25d.core.mesh import Coarser, MeshPart
from pipeline25d.formats.common import Detail, Loaded, dataset_root, in_context, run_converter, side_file

log = logging.getLogger(__name__)

OSGCONV = "osgconv"
WORKERS = max(1, min(4, len(os.sched_getaffinity(0))))   # tiles converted at once (each runs osgconv)
# the scene graph exactly as stored (osgconv optimizes by default), no display, warnings only
OSG_ENV = {"OSG_OPTIMIZER": "OFF", "OSG_NOTIFY_LEVEL": "WARN", "OSG_FILE_PATH": ""}
# the textures osgconv writes beside the OBJ, which the chunks keep as they are: uncompressed TGA (RGB
# or RGBA as the image is), which every render job that draws the chunk reads in 1-2 ms for 512 x 512
# texels, against 10-15 ms to decode the PNG osgconv wrote before (at zlib level 1); twice the bytes
TEXTURE_SUFFIX = ".tga"
_LOD_CLASSES = ("osg::PagedLOD", "osg::LOD")
_TRANSFORM_CLASSES = ("osg::PositionAttitudeTransform", "osg::AutoTransform", "osg::Camera", "osg::Transform",
                      "osgSim::DOFTransform", "osg::Billboard")
_TOKEN = re.compile(r'"[^"\\]*(?:\\.[^"\\]*)*"|[{}]|[^\s{}"]+|\n')   # strings unrolled: base64 images are long


# --------------------------------------------------------------------------- public API


@dataclass
class TileRead:
    """One tile (root file) as read: its parts and the triangles drawn per level."""

    name: str
    parts: list[MeshPart]
    levels: Counter = field(default_factory=Counter)   # level -> triangles drawn
    coarser: list[Coarser] = field(default_factory=list)   # per file naming missing children: its level drawn


def read_osgb(path: Path, spec: dict, detail: Detail = Detail()) -> Loaded:
    """Reader contract (:mod:`pipeline25d.formats`): an OSGB dataset folder or one .osgb file.

    A folder's ``metadata.xml`` georeferences it (its SRSOrigin added here, its SRS the
    CRS; a ``crs`` key overrides the SRS) unless the input names its own ``metadata``, which
    :func:`pipeline25d.formats.load_district` applies. Levels follow ``detail.gsd`` (module
    docstring); each tile's levels are logged.
    """
    pieces = list(read_osgb_pieces(path, spec, detail))
    return Loaded([p for piece in pieces for p in piece.parts], pieces[0].crs,
                  tuple(c for piece in pieces for c in piece.coarser))


def read_osgb_pieces(path: Path, spec: dict, detail: Detail = Detail()) -> Iterator[Loaded]:
    """:func:`read_osgb` one tile at a time, in name order (memory follows a few tiles, not the dataset)."""
    path = Path(path)
    crs = spec.get("crs")
    origin = np.zeros(3)
    if path.is_dir() and not spec.get("metadata") and (path / "metadata.xml").is_file():
        from pipeline25d.formats.contextcapture import read_metadata_xml

        meta_crs, origin = read_metadata_xml(path / "metadata.xml")
        crs = crs or meta_crs
    for tile in iter_tiles(path, detail.gsd, spec.get("missing_children", "coarser")):
        parts = [p.transformed(lambda v: v + origin) for p in tile.parts] if origin.any() else tile.parts
        yield Loaded(parts, crs, tuple(tile.coarser))


def read_tiles(path: Path, gsd: float | None, missing_children: str = "coarser") -> list[TileRead]:
    """Every tile of ``path`` (dataset folder or .osgb) at map pixel size ``gsd``, in file
    coordinates; ``missing_children``: ``coarser`` (module docstring) or ``error``."""
    return list(iter_tiles(path, gsd, missing_children))


def iter_tiles(path: Path, gsd: float | None, missing_children: str = "coarser") -> Iterator[TileRead]:
    """:func:`read_tiles` one tile at a time, in name order: :data:`WORKERS` tiles are converted at
    once and at most that many wait to be taken, each tile's converted files removed once it is read."""
    roots = dataset_tiles(path) if path.is_dir() else [path]
    folder = dataset_root(path)
    drawn = False
    with tempfile.TemporaryDirectory(prefix="pipeline25d-osgb-") as tmp, \
            ThreadPoolExecutor(max_workers=min(WORKERS, len(roots))) as pool:
        read = in_context(read_tile)
        queued = iter(enumerate(roots))
        waiting: deque = deque()

        def submit() -> None:
            for k, root in queued:
                work = Path(tmp) / f"t{k}"
                waiting.append((root, work, pool.submit(read, (root, gsd, work, folder, missing_children))))
                return

        for _ in range(WORKERS):
            submit()
        while waiting:
            root, work, future = waiting.popleft()
            tile = future.result()
            submit()
            shutil.rmtree(work, ignore_errors=True)
            _say(tile, root, gsd)
            drawn = drawn or bool(tile.levels)
            yield tile
    if not drawn:
        raise InputFileError(path, f"holds no triangles at gsd {gsd} (an empty OSGB tree)")


def _say(tile: TileRead, root: Path, gsd: float | None) -> None:
    """Log the tile's levels; warn of its PagedLOD children that are missing."""
    log.info("%s at gsd %s: %s", tile.name, gsd, describe_levels(tile.levels))
    if tile.coarser:
        asked = f"gsd {gsd}" if gsd else "full detail"
        said = (f"{root}: {sum(len(c.missing) for c in tile.coarser)} PagedLOD child file(s) missing, drawn "
                f"coarser than {asked} asks for, at the level of the file that names them: "
                + ", ".join(f"{name} (level {c.level} drawn)" for c in tile.coarser for name in c.missing))
        warnings.warn(said, stacklevel=3)      # a job's log has it too (core.logsetup.warnings_to_log)


def dataset_tiles(folder: Path) -> list[Path]:
    """The root .osgb of every tile of a ContextCapture dataset folder, sorted by name."""
    data = folder / "Data"
    if not data.is_dir():
        raise InputFileError(folder, "is not an OSGB dataset: no Data/ folder")
    roots = []
    for tile_dir in sorted(p for p in data.iterdir() if p.is_dir() and p.name.startswith("Tile")):
        root = tile_dir / f"{tile_dir.name}.osgb"
        if not root.is_file():
            raise InputFileError(root, "tile root file is missing")
        roots.append(root)
    if not roots:
        raise InputFileError(data, "holds no Tile_* folders with a root .osgb")
    return roots


def describe_levels(levels: Counter) -> str:
    """'level 1 (512 triangles)' or 'levels 1-2 (1: 256, 2: 4096 triangles)'."""
    if not levels:
        return "no triangles"
    keys = sorted(levels)
    if len(keys) == 1:
        return f"level {keys[0]} ({levels[keys[0]]} triangles)"
    return f"levels {keys[0]}-{keys[-1]} (" + ", ".join(f"{k}: {levels[k]}" for k in keys) + " triangles)"


#: what OpenSceneGraph prints for an image file it cannot load -> the problem, as other readers word it
_IMAGE_PROBLEMS = {"file not found": "is missing", "file not handled": "is not an image",
                   "read error": "cannot be read (truncated or corrupt)"}


def osgconv(src: Path, dst: Path, options: list[str], cwd: Path, what: Path) -> None:
    """Run ``osgconv -O "<options>" src dst`` in ``cwd`` headless; InputFileError naming ``what``.

    The options go in one ``-O`` (space separated): a second ``-O`` replaces the first. An image
    OpenSceneGraph could not load (it drops it and goes on) is a MissingTextureWarning naming it.
    """
    args = [OSGCONV] + (["-O", " ".join(options)] if options else []) + [str(src), str(dst)]
    said = run_converter(args, cwd, dst, what, "openscenegraph", OSG_ENV)
    for problem, image in re.findall(r"readImage\(\): (file not found|file not handled|read error), filename: (.+)",
                                     said):
        warnings.warn(f"{what}: texture '{image.strip()}' {_IMAGE_PROBLEMS[problem]}; its parts are drawn "
                      "untextured", MissingTextureWarning, stacklevel=2)


# --------------------------------------------------------------------------- one tile


def read_tile(root: Path, gsd: float | None, work: Path, folder: Path | None = None,
              missing_children: str = "coarser") -> TileRead:
    """The parts drawn at ``gsd`` of the tile whose root file is ``root`` (files walked breadth
    first); its child and texture files must lie in ``folder`` (default: ``root``'s folder).
    A missing child file is drawn coarser, or with ``missing_children="error"`` an error."""
    work.mkdir(parents=True)
    folder = root.parent if folder is None else folder
    tile = TileRead(root.stem, [])
    queue = [_Child(root, np.eye(4), True, 0, None)]
    seen: set[Path] = set()
    while queue:
        child = queue.pop(0)
        key = child.path.resolve()
        if key in seen:
            raise InputFileError(child.path, f"is referenced twice in the tree of {root} (a cycle?)")
        seen.add(key)
        walk = _read_file(child, gsd, work / f"f{len(seen)}", folder, missing_children == "error")
        for part in walk.parts:
            tile.parts.append(part)
            tile.levels[child.level] += part.n_triangles
        queue.extend(walk.children)
        if walk.missing:
            tile.coarser.append(Coarser(str(child.path), child.level, tuple(walk.missing),
                                        "the finest level of the file that names them"))
    return tile


@dataclass
class _Child:
    """A file to read: its path, the matrix placing it (row vectors, OSG order), whether that
    matrix is known, its level and the file that names it."""

    path: Path
    matrix: np.ndarray
    placed: bool
    level: int
    parent: Path | None


@dataclass
class _Walked:
    parts: list[MeshPart]
    children: list[_Child]
    missing: list[str]        # child files named but absent (their parent's level drawn there)


def _read_file(child: _Child, gsd: float | None, work: Path, folder: Path, strict: bool = False) -> _Walked:
    """One file: its LOD nodes resolved at ``gsd``, its geometry as parts, the child files to read."""
    path = child.path
    if not path.is_file():
        named = f" (named by {child.parent})" if child.parent else ""
        raise InputFileError(path, f"OSGB file is missing{named}")
    work.mkdir()
    osgconv(path.resolve(), Path("in.osgt"), ["WriteImageHint=IncludeData", "precision=17"], work, path)
    text = (work / "in.osgt").read_text(errors="replace")
    walker = _Walker(text, path, gsd, child, folder, strict)
    pruned = walker.emit(parse_osgt(text, path), child.matrix, child.placed)
    if "osg::Geometry" not in pruned:
        return _Walked([], walker.children, walker.missing)
    (work / "sel.osgt").write_text(pruned)
    osgconv(Path("sel.osgt"), Path("sel.obj"), ["OutputTextureFiles"], work, path)
    return _Walked(_obj_parts(work / "sel.obj", path, child.matrix), walker.children, walker.missing)


def _obj_parts(obj: Path, source: Path, matrix: np.ndarray) -> list[MeshPart]:
    """The OBJ osgconv wrote, as parts placed by ``matrix``; every texture it names must exist."""
    from pipeline25d.formats.meshfile import load_mesh_file

    mtl = obj.with_suffix(".mtl")
    for name in re.findall(r"^\s*map_Kd\s+(\S+)", mtl.read_text() if mtl.is_file() else "", re.M):
        if not (obj.parent / name).is_file():
            raise UnsupportedFeatureError(source, "an embedded texture could not be decoded by OpenSceneGraph "
                                                  "(compressed pixel format?)")
    if "\nf " not in obj.read_text():
        return []
    try:
        read = load_mesh_file(obj)
    except InputFileError as exc:   # the OBJ is ours: name the .osgb it came from
        raise InputFileError(source, str(exc).replace(f"{obj}: ", "")
                             .replace("it as an OBJ model", "its geometry")) from None
    parts = [replace(p, name=f"{source.name}:{p.name}") for p in read.parts]
    if np.allclose(matrix, np.eye(4)):
        return parts
    placed = [p.transformed(lambda v: v @ matrix[:3, :3] + matrix[3, :3]) for p in parts]
    if np.linalg.det(matrix[:3, :3]) < 0:       # a mirroring matrix: wind the faces back, front faces front
        placed = [replace(p, faces=p.faces[:, [0, 2, 1]]) for p in placed]
    return placed


# --------------------------------------------------------------------------- osgt text


@dataclass
class Stmt:
    """A property line of an .osgt file: its tokens and character span."""

    tokens: list[str]
    start: int
    end: int


@dataclass
class Block:
    """A bracketed block (an object ``osg::Geode {`` or a property ``RangeList 2 {``)."""

    head: list[str]
    items: list["Stmt | Block"]
    start: int
    end: int = -1

    def stmt(self, name: str) -> list[str] | None:
        """Tokens after ``name`` of the first line starting with it, or None."""
        return next((i.tokens[1:] for i in self.items if isinstance(i, Stmt) and i.tokens[0] == name), None)

    def block(self, name: str) -> "Block | None":
        return next((i for i in self.items if isinstance(i, Block) and i.head[:1] == [name]), None)

    def objects(self) -> list["Block"]:
        """Sub-blocks that are objects (``osg::Geode {``...)."""
        return [i for i in self.items if isinstance(i, Block) and i.head and "::" in i.head[0]]


def parse_osgt(text: str, path: Path) -> Block:
    """The bracket tree of an .osgt file (statements split at line ends, strings may span lines).
    A ``vector`` block of plain values (no brace or string inside: vertex, index and coordinate
    arrays, most of a file) is kept whole, without its lines: nothing reads them, and they are
    most of the tokens."""
    root = Block([], [], 0, len(text))
    stack, stmt, stmt_start, stmt_end = [root], [], 0, 0
    pos = 0
    while pos is not None:
        tokens, pos = _TOKEN.finditer(text, pos), None
        for m in tokens:
            tok = m.group()
            if tok in ("\n", "{", "}") and stmt and tok != "{":
                stack[-1].items.append(Stmt(stmt, stmt_start, stmt_end))
                stmt = []
            if tok == "{":
                block = Block(stmt, [], stmt_start if stmt else m.start())
                stack[-1].items.append(block)
                stack.append(block)
                stmt = []
                close = _plain_end(text, m.end()) if block.head[:1] == ["vector"] else None
                if close is not None:
                    stack.pop().end = pos = close + 1
                    break
            elif tok == "}":
                if len(stack) == 1:
                    raise InputFileError(path, f"osgt text has an unmatched '}}' at character {m.start()}")
                stack.pop().end = m.end()
            elif tok != "\n":
                if not stmt:
                    stmt_start = m.start()
                stmt.append(tok)
                stmt_end = m.end()
    if len(stack) != 1:
        raise InputFileError(path, "osgt text ends inside a block (truncated?)")
    return root


def _plain_end(text: str, start: int) -> int | None:
    """Where the block opened just before ``start`` closes if nothing in it is a block or a string."""
    close = text.find("}", start)
    if close < 0 or text.find("{", start, close) >= 0 or text.find('"', start, close) >= 0:
        return None
    return close


def _unquote(token: str) -> str:
    return re.sub(r'\\(.)', r"\1", token[1:-1]) if token.startswith('"') else token


def _numbers(tokens: list[str] | None, n: int, what: str, path: Path) -> list[float]:
    try:
        values = [float(t) for t in (tokens or [])]
    except ValueError:
        values = []
    if len(values) != n:
        raise InputFileError(path, f"{what} is not {n} numbers: {tokens!r}")
    return values


class _Walker:
    """Rewrites one file's .osgt text: LOD nodes become Groups of their drawn children, images
    get safe names; the child files to read are collected in ``children``."""

    def __init__(self, text: str, path: Path, gsd: float | None, parent: _Child, folder: Path, strict: bool = False):
        self.text, self.path, self.gsd, self.parent, self.folder = text, path, gsd, parent, folder
        self.strict = strict   # a missing child file is an error (missing_children: error)
        self.children: list[_Child] = []
        self.missing: list[str] = []
        self.next_id = max((int(v) for v in re.findall(r"UniqueID\s+(\d+)", text)), default=0) + 1
        self.images = 0

    def emit(self, block: Block, matrix: np.ndarray, placed: bool) -> str:
        """The text of ``block`` with its LOD nodes and image names replaced."""
        pieces, pos = [], block.start
        for item in block.items:
            new = self._replacement(item, matrix, placed)
            if new is not None:
                pieces += [self.text[pos:item.start], new]
                pos = item.end
        pieces.append(self.text[pos:block.end])
        return "".join(pieces)

    def _replacement(self, item: Stmt | Block, matrix: np.ndarray, placed: bool) -> str | None:
        if isinstance(item, Stmt):
            return None
        cls = item.head[0] if item.head else ""
        if cls in _LOD_CLASSES:
            return self._lod(item, matrix, placed)
        if cls == "Image":
            return self._image(item)
        if cls == "osg::MatrixTransform":
            return self.emit(item, self._matrix(item) @ matrix, placed)
        return self.emit(item, matrix, placed and cls not in _TRANSFORM_CLASSES)

    def _image(self, image: Block) -> str:
        """The image with a file name osgconv may write in its working folder (never a path of the input's)."""
        self.images += 1
        name = next((i for i in image.items if isinstance(i, Stmt) and i.tokens[0] == "FileName"), None)
        if name is None:
            return self.emit(image, np.eye(4), True)
        stored = _unquote(name.tokens[1]) if len(name.tokens) > 1 else ""
        if stored and (self.path.parent / stored).exists():   # osgconv loaded it: it must be ours
            side_file(stored, self.path.parent, self.folder, self.path, "texture file", url=False)
        head = self.text[image.start:name.start]
        return f'{head}FileName "img{self.images}{TEXTURE_SUFFIX}"{self.text[name.end:image.end]}'

    def _matrix(self, node: Block) -> np.ndarray:
        block = node.block("Matrix")
        if block is None:
            return np.eye(4)
        tokens = [t for s in block.items if isinstance(s, Stmt) for t in s.tokens]
        return np.array(_numbers(tokens, 16, "MatrixTransform Matrix", self.path)).reshape(4, 4)

    def _lod(self, node: Block, matrix: np.ndarray, placed: bool) -> str:
        """A Group of the children ``node`` draws at this map's pixel size; files queued."""
        cls = node.head[0]
        mode = (node.stmt("RangeMode") or ["DISTANCE_FROM_EYE_POINT"])[0]
        if mode != "PIXEL_SIZE_ON_SCREEN":
            raise UnsupportedFeatureError(self.path, f"{cls} RangeMode {mode}: only PIXEL_SIZE_ON_SCREEN "
                                                     "(as ContextCapture writes) has a meaning in a map")
        ranges_block = node.block("RangeList")
        ranges = [_numbers(s.tokens, 2, f"{cls} range", self.path)
                  for s in (ranges_block.items if ranges_block else []) if isinstance(s, Stmt)]
        names_block = node.block("RangeDataList")
        names = [_unquote(s.tokens[0]) for s in (names_block.items if names_block else []) if isinstance(s, Stmt)]
        children_block = node.block("Children")
        inline = children_block.objects() if children_block else []
        chosen = select_ranges(ranges, self._pixel_size(node, matrix))
        files = {i: self._child_path(node, names[i]) for i in chosen if i < len(names) and names[i] != ""}
        missing = {i for i, p in files.items() if not p.is_file()}
        if missing and self.strict:
            raise InputFileError(files[min(missing)], f"OSGB file is missing (named by {self.path}); the input's "
                                                      "missing_children: coarser draws the level present instead")
        if missing:
            self.missing += [names[i] for i in sorted(missing)]
            chosen = (chosen - missing) | self._finest_inline(ranges, names, chosen - missing)
        texts, k_inline = [], 0
        for i in range(len(ranges)):
            external = i < len(names) and names[i] != ""
            if not external:
                k_inline += 1
            if i not in chosen:
                continue
            if external:
                if not placed:
                    raise UnsupportedFeatureError(self.path, f"child file {names[i]!r} lies under a transform other "
                                                             "than MatrixTransform")
                self.children.append(_Child(files[i], matrix, True, self.parent.level + 1, self.path))
            elif k_inline - 1 < len(inline):
                texts.append(self.emit(inline[k_inline - 1], matrix, placed))
        return self._group(texts)

    @staticmethod
    def _finest_inline(ranges: list[list[float]], names: list[str], kept: set[int]) -> set[int]:
        """The inline children with the largest max range (the node's own finest level), drawn
        where chosen child files are missing; none when something chosen is still drawn."""
        inline = [i for i in range(len(ranges)) if i >= len(names) or names[i] == ""]
        if kept or not inline:
            return set()
        top = max(ranges[i][1] for i in inline)
        return {i for i in inline if ranges[i][1] == top}

    def _pixel_size(self, node: Block, matrix: np.ndarray) -> float:
        """2·r/gsd: the pixels the node's bounding sphere covers in the map (inf for full detail)."""
        centre_mode = (node.stmt("CenterMode") or ["USE_BOUNDING_SPHERE_CENTER"])[0]
        if centre_mode == "USE_BOUNDING_SPHERE_CENTER":
            raise UnsupportedFeatureError(self.path, f"{node.head[0]} without a user-defined centre and radius "
                                                     "(ContextCapture always writes one)")
        radius = _numbers(node.stmt("UserCenter"), 4, f"{node.head[0]} UserCenter", self.path)[3]
        if radius < 0:
            raise InputFileError(self.path, f"{node.head[0]} has no radius (UserCenter radius {radius})")
        scale = abs(np.linalg.det(matrix[:3, :3])) ** (1.0 / 3.0)
        return np.inf if self.gsd is None else 2.0 * radius * scale / self.gsd

    def _child_path(self, node: Block, name: str) -> Path:
        """A child file: under the node's DatabasePath when it is there (osgconv sets it to the
        folder it read), else beside this file (a path stored by the producer's machine)."""
        here = side_file(name, self.path.parent, self.folder, self.path, "PagedLOD child file", url=False)
        flag = node.stmt("DatabasePath") or ["FALSE"]
        if flag[0] == "TRUE" and len(flag) > 1 and _unquote(flag[1]):
            stored = Path(_unquote(flag[1])) / name
            inside = stored.resolve().is_relative_to(self.folder.resolve())
            return stored if inside and (stored.is_file() or not here.is_file()) else here
        return here

    def _group(self, texts: list[str]) -> str:
        uid, self.next_id = self.next_id, self.next_id + 1
        if not texts:
            return f"osg::Group {{\n UniqueID {uid}\n}}"
        return f"osg::Group {{\n UniqueID {uid}\n Children {len(texts)} {{\n" + "\n".join(texts) + "\n }\n}"


def select_ranges(ranges: list[list[float]], pixels: float) -> set[int]:
    """Indices of the ranges [min, max) holding ``pixels``; the finest past the last max, the
    coarsest below the first min (see the module docstring)."""
    if not ranges:
        return set()
    hit = {i for i, (lo, hi) in enumerate(ranges) if lo <= pixels < hi}
    if hit:
        return hit
    top = max(hi for _, hi in ranges)
    if pixels >= top:
        return {i for i, (_, hi) in enumerate(ranges) if hi == top}
    bottom = min(lo for lo, _ in ranges)
    if pixels < bottom:
        return {i for i, (lo, _) in enumerate(ranges) if lo == bottom}
    return set()   # a gap between ranges: OSG draws nothing there either


# --------------------------------------------------------------------------- CLI


def main(argv: list[str] | None = None) -> int:
    """``python -m pipeline25d.formats.osgb DATASET --gsd G [--gsd G2 ...]``: the level read per tile."""
    parser = argparse.ArgumentParser(prog="pipeline25d osgb-levels",
                                     description="Print the PagedLOD level drawn per tile of an OSGB dataset.")
    parser.add_argument("path", type=Path, help="dataset folder (with Data/) or one .osgb file")
    parser.add_argument("--gsd", type=float, action="append", required=True,
                        help="map metres per pixel (repeat for several)")
    args = parser.parse_args(argv)
    for gsd in args.gsd:
        for tile in read_tiles(args.path, gsd):
            print(f"gsd {gsd:g}\t{tile.name}\t{describe_levels(tile.levels)}")  # noqa: T201
    return 0


if __name__ == "__main__":
    sys.exit(main())
