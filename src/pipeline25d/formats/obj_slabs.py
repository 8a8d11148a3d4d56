"""A large OBJ read a slab of faces at a time, so that ingest's memory follows a slab, not the file.

trimesh reads an OBJ whole, at about 300 bytes a triangle. An OBJ of at least
:data:`SLAB_FILE_BYTES` is read in two passes instead. The first keeps every vertex's values
(position and colour, float64 as the file writes them) and texture coordinate; the second cuts
the faces into slabs of :data:`SLAB_FACES`, in file order, and hands each slab to trimesh
(:func:`~pipeline25d.formats.meshfile.load_mesh_file`) as an OBJ of its own: its material
libraries, the object, group and material in force where it starts, the vertices and texture
coordinates its faces use (renumbered; each value written as Python's repr, which reads back to
the same float64) and its statements. Each slab is one piece of the district
(:func:`pipeline25d.formats.district_pieces`), chunked as it comes; ingest joins a chunk's parts
of one texture from several slabs (:class:`pipeline25d.stages.ingest._Spool`). A slab's
triangles, their colours, texture coordinates, textures and objects are those of the whole
file's read; normals are dropped (the renderer shades from the faces). Faces with texture
coordinates and faces without (an untextured material's) may mix; a face with them on some of
its corners only is refused (trimesh reads it one way or another as the faces around it go).
Statements are read one to a line (no ``\\`` continuations).

A 402 MB OBJ of 5.12 M textured triangles, chunked by :func:`pipeline25d.stages.ingest.ingest`
(one run each): whole, 1.53 GB at the peak in 38 s; in slabs on one core, 0.78 GB in 84 s (the
slabs' read alone: 0.54 GB); on two (a slab parsed in a worker while the next is cut), 0.85 GB in
52 s. Memory then grows with the vertices (40-56 bytes each), not the faces.

Both passes cut lines into words on a block's bytes at once (:class:`~.obj_lines.Words`), and a slab's faces
of one size are formatted together: the slabs' texts are the same bytes as a line-by-line cut's,
in half the time. A 138 MB OBJ of 2 M textured triangles (a height field), read on two cores, two
runs each: in slabs 14.3-14.5 s at 0.45 GB, line by line 28.1-28.7 s at 0.51 GB; trimesh on the
whole file 10.3 s at 1.32 GB.
"""

from __future__ import annotations

import logging
from collections.abc import Iterator
from contextlib import nullcontext
from pathlib import Path

import numpy as np

from pipeline25d.core.errors import InputFileError
from pipeline25d.formats.common import Detail, Loaded
from pipeline25d.formats.obj_lines import OTHER, VT, F, V, Words, face_tokens, kinds, line_blocks

log = logging.getLogger(__name__)

#: OBJ files of at least this size are read in slabs (whole: 3-7 x the file's size in memory)
SLAB_FILE_BYTES = 128 * 2 ** 20
#: faces per slab
SLAB_FACES = 200_000
#: statements that change what the faces after them belong to, carried into the next slab
STATE = (b"o", b"g", b"usemtl", b"s")


def read_obj_slabs(path: Path, spec: dict, detail: Detail = Detail()) -> Iterator[Loaded]:
    """The OBJ at ``path`` as pieces: the whole file in one where it is under :data:`SLAB_FILE_BYTES`,
    else one piece per slab (module docstring)."""
    from pipeline25d.core.cores import fork_pool, job_workers, map_ahead
    from pipeline25d.formats.meshfile import _check_obj, _Files, load_mesh_file

    if path.stat().st_size < SLAB_FILE_BYTES:
        yield Loaded(load_mesh_file(path).parts, spec.get("crs"))
        return
    _check_obj(path)
    table = VertexTable.read(path)
    slabs = -(-table.n_faces // SLAB_FACES)
    log.info("%s: %d vertices, %d texture coordinates, %d faces: read in %d slabs", path, len(table.v),
             len(table.vt), table.n_faces, slabs)
    global _FILES
    _FILES = _Files(str(path))                  # before the workers fork: each reads a file once
    workers = job_workers(1) if slabs > 1 else 1
    texts = ((path, text, len(table.objects) >= 2) for text in slab_texts(path, table, SLAB_FACES))
    with fork_pool(workers) if workers > 1 else nullcontext() as pool:
        for k, parts in enumerate(map_ahead(pool, _slab_parts, texts, workers)):
            log.info("%s: slab %d of %d read", path.name, k + 1, slabs)
            yield Loaded(parts, spec.get("crs"))


#: the material libraries and textures of the OBJ being read in slabs (set before the workers fork)
_FILES = None


def _slab_parts(path: Path, text: bytes, objects: bool) -> list:
    """A slab's parts (trimesh on its OBJ text), in a worker or here."""
    from pipeline25d.formats.meshfile import load_mesh_file

    return load_mesh_file(path, text=text, files=_FILES, objects=objects).parts


class VertexTable:
    """Every ``v`` line's values (positions, colours where given) and every ``vt`` line's, float64
    (NaN past a shorter line's values), the ``mtllib`` lines and the ``o`` object names of an OBJ."""

    def __init__(self, v: "Rows", vt: "Rows", mtllib: list[bytes], objects: set[bytes], n_faces: int = 0):
        self.v, self.vt, self.mtllib, self.objects, self.n_faces = v, vt, mtllib, objects, n_faces

    @classmethod
    def read(cls, path: Path) -> "VertexTable":
        v_rows: list[np.ndarray] = []
        vt_rows: list[np.ndarray] = []
        mtllib: list[bytes] = []
        objects: set[bytes] = set()
        n_faces = 0
        for lines in line_blocks(path):
            kind = kinds(lines)
            n_faces += int((kind == F).sum())
            v_rows.append(_values([lines[i] for i in np.flatnonzero(kind == V).tolist()], path, "v"))
            vt_rows.append(_values([lines[i] for i in np.flatnonzero(kind == VT).tolist()], path, "vt"))
            others = [lines[i] for i in np.flatnonzero(kind == OTHER).tolist()]      # statements, comments
            mtllib += [ln.strip() for ln in others if ln.startswith(b"mtllib")]
            objects.update(ln.split(maxsplit=1)[1].strip() for ln in others
                           if ln[:2] in (b"o ", b"o\t") and len(ln.split()) > 1)
        return cls(Rows(v_rows), Rows(vt_rows), mtllib, objects, n_faces)


def _values(lines: list[bytes], path: Path, what: str) -> np.ndarray:
    """(n, k) float64 values after the keyword of ``lines``; k the most values a line has, NaN
    where a line has fewer. Lines of one width are parsed at once (C's strtod, as trimesh does)."""
    if not lines:
        return np.zeros((0, 0))
    words = Words(lines)
    widths = words.count
    if (widths == widths[0]).all():                 # the usual file: lines of one width, parsed at once
        flat = _parsed(words.numbers_text(), np.float64, path, f"a '{what}' line holds something other than numbers")
        return _checked(flat, len(lines), int(widths[0]), path, what).reshape(len(lines), int(widths[0]))
    out = np.full((len(lines), int(widths.max())), np.nan)
    for n in np.unique(widths).tolist():
        idx = np.flatnonzero(widths == n)
        text = b" ".join(lines[i].split(maxsplit=1)[1] if n else b"" for i in idx.tolist())
        flat = _checked(_parsed(text, np.float64, path, f"a '{what}' line holds something other than numbers"),
                        len(idx), n, path, what)
        out[idx, :n] = flat.reshape(-1, n) if n else out[idx, :n]
    return out


def _parsed(text: bytes, dtype, path: Path, problem: str) -> np.ndarray:
    """The numbers of ``text`` (C's strtod, as trimesh reads them); a word that is not one is
    ``problem``, naming the file (NumPy stops there with a bare ValueError, or reads fewer)."""
    try:
        return np.fromstring(text, dtype=dtype, sep=" ")
    except ValueError:
        raise InputFileError(path, problem) from None


def _checked(flat: np.ndarray, lines: int, width: int, path: Path, what: str) -> np.ndarray:
    """``flat``, the numbers of ``lines`` lines of ``width`` each, refused where they are not that many
    (a word that is not a number) or, for vertices, not finite (as a whole read refuses them)."""
    if flat.size != lines * width:
        raise InputFileError(path, f"a '{what}' line holds something other than numbers")
    if what == "v" and not np.isfinite(flat).all():
        raise InputFileError(path, "has NaN or infinite coordinates")
    return flat


class Rows:
    """An OBJ's ``v`` or ``vt`` values kept in the blocks they were read in (joining them into one
    array would hold them twice at once): ``len``, and :meth:`take` of rows by index."""

    def __init__(self, blocks: list[np.ndarray]):
        self.blocks = [b for b in blocks if len(b)]
        self.starts = np.cumsum([0] + [len(b) for b in self.blocks])
        self.width = max((b.shape[1] for b in self.blocks), default=0)

    def __len__(self) -> int:
        return int(self.starts[-1])

    def take(self, index: np.ndarray) -> np.ndarray:
        """(len(index), width) float64 rows (NaN beyond a shorter block's width)."""
        out = np.full((len(index), self.width), np.nan)
        block = np.searchsorted(self.starts, index, side="right") - 1
        for k in np.unique(block).tolist():
            sel = block == k
            values = self.blocks[k]
            out[sel, :values.shape[1]] = values[index[sel] - self.starts[k]]
        return out


def slab_texts(path: Path, table: VertexTable, slab_faces: int = SLAB_FACES) -> Iterator[bytes]:
    """The OBJ text of each slab of ``path``'s faces (module docstring), in file order."""
    state: dict[bytes, bytes] = {}              # statement keyword -> its last line
    nv = nvt = 0                                # v and vt lines so far (negative indices count back from them)
    slab = _Slab(state)
    for lines in line_blocks(path):
        kind = kinds(lines)
        seen = np.column_stack([nv + np.cumsum(kind == V), nvt + np.cumsum(kind == VT)])
        faces = np.flatnonzero(kind == F)
        statements = [i for i in np.flatnonzero(kind == OTHER).tolist() if _word(lines[i]) in STATE]
        done = 0                                # faces of this block taken
        for i in [*statements, len(lines)]:
            before = int(np.searchsorted(faces, i))
            while done < before:
                take = faces[done:done + min(before - done, slab_faces - slab.n_faces)]
                slab.add([lines[k] for k in take.tolist()], seen[take])
                done += len(take)
                if slab.n_faces >= slab_faces:
                    yield slab.text(path, table)
                    slab = _Slab(state)
            if i < len(lines):
                state[_word(lines[i])] = lines[i].rstrip(b"\r\n")
                slab.statement(state[_word(lines[i])])
        nv, nvt = (int(c) for c in seen[-1])
    if slab.n_faces:
        yield slab.text(path, table)


def _word(line: bytes) -> bytes:
    return line.split(maxsplit=1)[0] if line.strip() else b""


class _Slab:
    """One slab's face lines as they are read, the v and vt lines before each (negative indices count
    back from those), and the statements between its faces."""

    def __init__(self, state: dict[bytes, bytes]):
        self.start = dict(state)                # the statements in force where the slab starts
        self.body: list[bytes | int] = []       # statements, and the count of each run of faces between
        self.faces: list[bytes] = []
        self.counts: list[np.ndarray] = []      # (faces, 2): v and vt lines before each face
        self.n_faces = 0

    def statement(self, line: bytes) -> None:
        if self.n_faces:
            self.body.append(line)
        else:
            self.start = {**self.start, line.split(maxsplit=1)[0]: line}

    def add(self, faces: list[bytes], counts: np.ndarray) -> None:
        self.faces += faces
        self.counts.append(counts)
        self.body.append(len(faces))
        self.n_faces += len(faces)

    def text(self, path: Path, table: VertexTable) -> bytes:
        """The slab as an OBJ of its own: material libraries, the state where it starts, the vertices
        and texture coordinates its faces use, then its statements with the faces renumbered."""
        sizes, v, vt = _corners(self.faces, np.concatenate(self.counts), path)
        _in_range(v, len(table.v), path, "vertex")
        has_vt = vt >= 0
        used_v, local = _renumbered(v)
        out = [*table.mtllib, *self.start.values(), _rows(b"v", table.v.take(used_v))]
        numbers = [local + 1]
        if has_vt.any():                        # faces without them (an untextured material's) keep none
            given = np.add.reduceat(has_vt, np.cumsum(sizes) - sizes)
            if ((given > 0) & (given < sizes)).any():
                raise InputFileError(path, "a face gives texture coordinates for some of its corners only")
            _in_range(vt[has_vt], len(table.vt), path, "texture coordinate")
            used_vt, local_vt = _renumbered(vt[has_vt])
            out.append(_rows(b"vt", table.vt.take(used_vt)))
            numbers.append(np.zeros(len(vt), np.int64))
            numbers[1][has_vt] = local_vt + 1
        faces, at = _face_lines(sizes, numbers), 0
        for entry in self.body:
            if isinstance(entry, int):
                out += faces[at:at + entry]
                at += entry
            else:
                out.append(entry)
        return b"\n".join(out) + b"\n"


def _face_lines(sizes: np.ndarray, numbers: list[np.ndarray]) -> list[bytes]:
    """Each face's line ``f 1/1 2/2 3/3`` from its corners' 1-based vertex numbers (and texture
    coordinates' where ``numbers`` has two arrays, 0 at a corner that has none: written ``f 1 2 3``
    there, as the file wrote it); faces of one size are formatted at once."""
    corner = "/".join(["%d"] * len(numbers))
    mixed = len(numbers) == 2 and not numbers[1].all()      # a file mixing faces with and without them
    if len(sizes) and (sizes == sizes[0]).all() and not mixed:
        face = "f " + " ".join([corner] * int(sizes[0]))
        values = np.column_stack(numbers).ravel().tolist()
        return ("\n".join([face] * len(sizes)) % tuple(values)).encode().split(b"\n")
    if mixed:
        corners = [f"{a}/{t}" if t else str(a) for a, t in zip(*(n.tolist() for n in numbers))]
    else:
        corners = [corner % c for c in zip(*(n.tolist() for n in numbers))]
    ends = np.cumsum(sizes).tolist()
    return [("f " + " ".join(corners[e - n:e])).encode() for e, n in zip(ends, sizes.tolist())]


def _corners(lines: list[bytes], counts: np.ndarray, path: Path) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(corners of each face line, each corner's 0-based vertex index, its texture coordinate's or -1),
    negative indices counted back from ``counts`` (the v and vt lines before each face)."""
    sizes, slashes, text = face_tokens(lines)
    fields = _parsed(text.replace(b"//", b"/0/").replace(b"/", b" "), np.int64, path,
                     "a face names a vertex by something other than a number")
    width = slashes + 1
    if fields.size != int(width.sum()):
        raise InputFileError(path, "a face names a vertex by something other than a number")
    first = np.concatenate([[0], np.cumsum(width)[:-1]])
    at = np.repeat(counts, sizes, axis=0)
    v = fields[first]
    t = np.where(slashes >= 1, fields[np.minimum(first + 1, fields.size - 1)], 0)
    v = np.where(v > 0, v - 1, at[:, 0] + v)
    t = np.where(t > 0, t - 1, np.where(t < 0, at[:, 1] + t, -1))
    return sizes, v, t


def _renumbered(idx: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """``np.unique(idx, return_inverse=True)``: the indices used, ascending, and each one's place among
    them. Where they span few more values than they are (a slab's faces name nearby vertices, as
    exporters write them), by marking the span instead of sorting."""
    lo, hi = int(idx.min()), int(idx.max())
    if hi - lo >= 4 * len(idx):
        return np.unique(idx, return_inverse=True)
    used = np.zeros(hi - lo + 1, dtype=bool)
    used[idx - lo] = True
    place = np.cumsum(used) - 1
    return np.flatnonzero(used) + lo, place[idx - lo]


def _in_range(idx: np.ndarray, n: int, path: Path, what: str) -> None:
    bad = (idx < 0) | (idx >= n)
    if bad.any():
        k = int(idx[bad][0])
        raise InputFileError(path, f"a face names {what} {k + 1 if k >= 0 else k} of {n}: out of range")


def _rows(keyword: bytes, values: np.ndarray) -> bytes:
    """Lines ``keyword x y ...`` of ``values``, each number as Python's repr writes it (it reads back
    to the same float64), a NaN column left out."""
    finite = np.isfinite(values)
    word = keyword.decode()
    if finite.all():                            # every line as wide as the widest (the usual file)
        cols = [list(map(repr, values[:, j].tolist())) for j in range(values.shape[1])]
        return "\n".join(map(" ".join, zip([word] * len(values), *cols))).encode()
    out: list[tuple[int, str]] = []
    for pattern in np.unique(finite, axis=0):
        rows = np.flatnonzero((finite == pattern).all(axis=1))
        cols = [list(map(repr, values[rows, j].tolist())) for j in np.flatnonzero(pattern)]
        text = map(" ".join, zip([word] * len(rows), *cols))
        if len(rows) == len(values):
            return "\n".join(text).encode()
        out += zip(rows.tolist(), text)
    return "\n".join(line for _, line in sorted(out)).encode()
