"""OBJ, PLY and DAE model files through trimesh: one MeshPart per material/geometry, an OBJ's faces on their `o`.

trimesh keeps OBJ/glTF UVs with v = 0 at the image bottom (our convention); a texture keeps the
bytes of its PNG, JPEG or uncompressed TGA file (an OSGB tile's, which osgconv writes as TGA), any
other image is encoded as PNG, once per image (re-encoding every texture as PNG was 62 % of an OSGB
city's ingest); vertex colours and material colours become RGBA per vertex. Coordinates are float64 as the
file stores them.
"""

from __future__ import annotations

import io
import re
import warnings
from dataclasses import replace
from pathlib import Path, PurePosixPath

import numpy as np
import trimesh

from pipeline25d.core.errors import InputFileError, MissingTextureWarning
from pipeline25d.core.mesh import Mesh, MeshPart, joined
from pipeline25d.formats.common import drawn_as_is, image_problem, side_file


def load_mesh_file(path: str | Path, text: bytes | None = None, files: "_Files | None" = None,
                   objects: bool | None = None) -> Mesh:
    """Read ``path`` with trimesh; InputFileError naming the file on any failure, a
    :class:`MissingTextureWarning` per material library or texture missing, not an image or undecodable.

    ``text``: an OBJ's statements to read instead of the file's (a slab of a large OBJ,
    :mod:`pipeline25d.formats.obj_slabs`), its material libraries and textures found beside
    ``path``; ``files``: the :class:`_Files` of earlier slabs (each file read and warned of once,
    each texture the same bytes in every slab); ``objects``: whether the whole file has two ``o``
    objects or more (None: as ``text`` has them)."""
    path = Path(path)
    kind = path.suffix.lstrip(".").upper()
    model = f"{'an' if kind[:1] in 'AEIOU' else 'a'} {kind} model"
    repaired = None if text is not None else {"OBJ": _check_obj, "DAE": _check_dae}.get(kind, lambda p: None)(path)
    if kind == "OBJ" and text is None:           # read once: for trimesh and for its objects' statements
        data = path.read_bytes()
        text = tidied_obj_text(data) or data
    files = files or _Files(str(path))
    source = ({"file_obj": io.BytesIO(text), "file_type": "obj"} if text is not None else
              {"file_obj": str(path)} if repaired is None else {"file_obj": io.BytesIO(repaired), "file_type": "dae"})
    split = {"split_objects": True} if kind == "OBJ" else {}      # an OBJ's `o` objects (see _objects_joined)
    try:
        scene = trimesh.load(**source, force="scene", process=False, resolver=files, **split)
    except IndexError as exc:
        raise InputFileError(path, f"cannot read it as {model}: an index is out of range ({exc})") from None
    except Exception as exc:  # trimesh raises many exception types for bad files
        raise InputFileError(path, f"cannot read it as {model}: {exc}") from None
    files.check(path)
    parts: list[MeshPart] = []
    encoded: dict[int, bytes] = {}
    for node in scene.graph.nodes_geometry:
        transform, name = scene.graph[node]
        geom = scene.geometry[name]
        if not isinstance(geom, trimesh.Trimesh) or len(geom.faces) == 0:
            continue
        vertices = np.asarray(geom.vertices, dtype=np.float64)
        if not np.allclose(transform, np.eye(4)):
            vertices = trimesh.transformations.transform_points(vertices, transform)
        parts.append(_part(geom, vertices, str(name), encoded, files.asked))
    if not parts:
        raise InputFileError(path, "contains no triangles")
    statements = text.decode("utf-8", "replace") if split else ""
    return Mesh(_objects_joined(parts, path, statements, objects) if split else parts, source=str(path))


def _objects_joined(parts: list[MeshPart], path: Path, text: str, several: bool | None = None) -> list[MeshPart]:
    """An OBJ read object by object (trimesh names each piece ``<object>_<usemtl>``, or ``<object>``
    with one material) as one part per material again (few draw calls), each face keeping its ``o``
    object (3dfier writes one per building, road, terrain patch). An OBJ with fewer than two ``o``
    objects is one part per material, as trimesh reads it without splitting. ``text``: the OBJ's
    statements; ``several``: whether the whole file has two objects or more (a slab's text may hold one)."""
    statements = re.findall(r"^(o|usemtl)[ \t]+(.*?)[ \t\r]*$", text, re.M)    # CRLF lines too
    names = {v for k, v in statements if k == "o"}
    usemtl = {v for k, v in statements if k == "usemtl"}
    groups: dict[tuple, list[tuple[str | None, MeshPart]]] = {}
    for part in parts:
        obj = max((n for n in names if part.name == n or part.name.startswith(n + "_")), key=len, default=None)
        material = part.name if obj is None else part.name[len(obj) + 1:]
        material = material if material in usemtl else ""     # else trimesh's "_1" making a name unique
        key = (material, part.texture, part.colors is None, part.uv is None)
        groups.setdefault(key, []).append((obj, part))
    out = []
    for (material, *_), pieces in groups.items():
        if not (len(names) >= 2 if several is None else several):
            out += [replace(p, name=material or p.name) if len(pieces) == 1 else p for _, p in pieces]
            continue
        # faces before the first `o` are an object of their own, named as trimesh names them
        out.append(joined([replace(p, objects=(obj or p.name,), face_objects=np.zeros(p.n_triangles, np.int32))
                           for obj, p in pieces], material or path.name))
    return out


#: OBJ statements and the fewest values each takes; a last line with fewer was cut short.
OBJ_VALUES = {"v": 3, "vt": 2, "vn": 3, "f": 3}
OBJ_HEAD = 4096        # bytes of an OBJ checked for binary data


#: the byte order mark some Windows tools write first in a UTF-8 text
UTF8_BOM = b"\xef\xbb\xbf"


def cr_only(data: bytes) -> bool:
    """Whether an OBJ's text (or its first block) ends its lines with CR alone (classic Mac OS)."""
    return b"\n" not in data and b"\r" in data


#: a comment after a statement of numbers (``v 1 2 3 # ground``), which some exporters write: the
#: statement, the comment (OBJ's ``#`` starts one anywhere); names (``o``, ``usemtl``) keep theirs
_TRAILING_COMMENT = re.compile(rb"(?m)^([ \t]*(?:v[tnp]?|[flp])[ \t][^#\n]*?)[ \t]*#[^\n]*")
_NUMBERS_STATEMENT = re.compile(rb"[ \t]*(?:v[tnp]?|[flp])[ \t]")


def _has_trailing_comment(data: bytes) -> bool:
    """Whether a ``#`` of ``data`` follows a statement of numbers on its line (each ``#`` looked at
    alone: a header's comment lines cost nothing, where a pattern over every line took 0.2 s a 8 MB)."""
    at = data.find(b"#")
    while at >= 0:
        if _NUMBERS_STATEMENT.match(data, data.rfind(b"\n", 0, at) + 1):
            return True
        end = data.find(b"\n", at)
        at = data.find(b"#", end) if end >= 0 else -1
    return False


def needs_tidying(data: bytes) -> bool:
    """Whether an OBJ's text (or a run of its lines) holds what :func:`tidied_obj_text` tidies."""
    return (cr_only(data) or b"\t" in data or data[:1] == b" " or b"\n " in data
            or data.startswith(UTF8_BOM) or _has_trailing_comment(data))


def tidied_obj_text(data: bytes) -> bytes | None:
    """An OBJ's text without a byte order mark, with tabs as spaces, no whitespace before a line's
    keyword, no comment after a statement of numbers and LF line ends where it has only CRs
    (classic Mac OS), where it has any of them; None where it has none. trimesh finds statements by
    a newline, the keyword and a space: a file written with tabs, indented or with CRs alone read as
    no triangle at all, a mark before a first ``v`` line dropped that vertex (every index after it
    off by one), and a comment after a vertex refused the file."""
    if not needs_tidying(data):
        return None
    data = data.replace(b"\r", b"\n") if cr_only(data) else data
    data = _TRAILING_COMMENT.sub(rb"\1", data) if b"#" in data else data
    return re.sub(rb"(?m)^ +", b"", data.removeprefix(UTF8_BOM).replace(b"\t", b" "))


def _check_obj(path: Path) -> None:
    """InputFileError when an OBJ holds binary data at its start (corrupt) or ends in the middle
    of a statement (truncated): trimesh would read what it can and say nothing."""
    with path.open("rb") as f:
        head = f.read(OBJ_HEAD)
        f.seek(max(0, path.stat().st_size - 256))
        tail = f.read()
    if b"\0" in head:
        raise InputFileError(path, "is not a text OBJ file (binary data in its first bytes: corrupt)")
    words = tail.rstrip(b"\r\n").rsplit(b"\n", 1)[-1].decode("latin-1").split()
    if words and len(words) - 1 < OBJ_VALUES.get(words[0], 0):
        raise InputFileError(path, f"ends in the middle of a statement ({' '.join(words)!r}): truncated")


#: COLLADA elements whose text or children make triangles or place them
_DAE_GEOMETRY = frozenset({"float_array", "int_array", "p", "vcount", "v", "h", "source", "accessor", "param",
                           "triangles", "polylist", "polygons", "tristrips", "trifans", "vertices", "input", "mesh",
                           "geometry", "matrix", "translate", "rotate", "scale", "lookat", "skew"})


def _dae_geometry(elem) -> bool:
    tag = elem.tag
    return isinstance(tag, str) and tag[tag.rfind("}") + 1:] in _DAE_GEOMETRY


#: COLLADA elements whose text is numbers: where an exporter under a European locale writes decimal commas
_DAE_NUMBERS = re.compile(rb"(<(?:float_array|color|float|translate|rotate|scale|matrix|lookat|skew)\b[^>]*>)([^<]*)")
#: libraries never drawn, which pycollada refuses when incomplete (a ``<light/>`` with no technique)
_DAE_UNDRAWN = re.compile(rb"<(library_lights|library_cameras)\b.*?</\1\s*>", re.S)


def _dae_repaired(data: bytes, path: Path) -> bytes:
    """A COLLADA document without its lights and cameras (never drawn; pycollada refuses the
    file over an incomplete one) and with decimal commas read as points (``0,588235`` in an
    element of numbers that holds no decimal point: 3ds Max's exporter under a European locale),
    with a warning for the commas."""
    data = _DAE_UNDRAWN.sub(b"", data)
    changed = 0

    def points(m: re.Match) -> bytes:
        nonlocal changed
        text = m.group(2)
        if re.search(rb"\d,\d", text) is None or re.search(rb"\d\.\d", text) is not None:
            return m.group(0)
        changed += 1
        return m.group(1) + re.sub(rb"(\d),(\d)", rb"\1.\2", text)

    data = _DAE_NUMBERS.sub(points, data)
    if changed:
        warnings.warn(f"{path}: {changed} elements of numbers are written with decimal commas (an exporter "
                      "under a European locale); they are read as decimal points", stacklevel=3)
    return data


def _check_dae(path: Path) -> bytes | None:
    """InputFileError for what trimesh's COLLADA reading (pycollada) hides: NaN/inf coordinates
    (read as 0) and malformed geometry such as indices beyond their source (geometry dropped).
    XML defects outside the geometry (stray characters, undeclared prefixes) are recovered from
    with a warning (:func:`~pipeline25d.formats.xml_defects.recovered_xml`), lights, cameras and
    decimal commas as :func:`_dae_repaired` says; the repaired document is returned then (None:
    the file is read as it is)."""
    import collada

    from pipeline25d.formats.xml_defects import recovered_xml

    original = path.read_bytes()
    data = _dae_repaired(recovered_xml(original, path, _dae_geometry), path)
    if re.search(rb"<float_array[^>]*>[^<]*?(?<![\w.])[+-]?(nan|inf)", data, re.IGNORECASE):
        raise InputFileError(path, "has NaN or infinite coordinates")
    try:
        collada.Collada(io.BytesIO(data), ignore=[collada.common.DaeUnsupportedError,
                                                  collada.common.DaeBrokenRefError])
    except collada.common.DaeError as exc:
        raise InputFileError(path, f"cannot read it as a DAE model: {exc}") from None
    return None if data == original else data


def _part(geom, vertices: np.ndarray, name: str, encoded: dict[int, bytes],
          served: dict[str, bytes | None]) -> MeshPart:
    visual = geom.visual
    faces = np.asarray(geom.faces, dtype=np.int64)
    if visual.kind == "texture":
        material = visual.material
        image = getattr(material, "image", None) or getattr(material, "baseColorTexture", None)
        usable = image is not None and visual.uv is not None and len(visual.uv) == len(vertices)
        if usable and id(image) not in encoded:
            encoded[id(image)] = _texture_bytes(image, served)
        if usable and encoded[id(image)] is not None:
            return MeshPart(vertices, faces, uv=np.asarray(visual.uv), texture=encoded[id(image)], name=name)
        colour = np.asarray(getattr(material, "main_color", [180, 180, 180, 255]), dtype=np.uint8)
        return MeshPart(vertices, faces, colors=np.tile(colour, (len(vertices), 1)), name=name)
    if visual.kind in ("vertex", "face"):
        return MeshPart(vertices, faces, colors=np.asarray(visual.vertex_colors)[:, :4], name=name)
    return MeshPart(vertices, faces, name=name)


def _texture_bytes(image, served: dict[str, bytes | None]) -> bytes | None:
    """The encoded bytes of a texture trimesh opened: those of its file where that is a PNG, a JPEG
    or an uncompressed TGA (trimesh records the file in ``image.info["file_path"]``; ``served``: what the resolver read,
    by name, None for a file :meth:`_Files.check` found missing or broken), else the image encoded
    as PNG; None where it cannot be (already warned of, or warned of here)."""
    name = image.info.get("file_path")
    data = served.get(name)
    if name in served and data is None:
        return None
    if data is not None and drawn_as_is(data):
        return data
    buf = io.BytesIO()
    try:
        image.save(buf, format="PNG")
    except (OSError, SyntaxError, ValueError) as exc:
        warnings.warn(f"texture {name or image.format!r} cannot be read ({exc}); its parts are drawn untextured",
                      MissingTextureWarning, stacklevel=4)
        return None
    return buf.getvalue()


#: the options a material library's map statement may give before its file name (MTL: -o 0.1 0.2,
#: -clamp on ...) and how many values each takes; -o, -s and -t take one to three numbers
MAP_OPTIONS = {"-blendu": 1, "-blendv": 1, "-bm": 1, "-boost": 1, "-cc": 1, "-clamp": 1, "-imfchan": 1,
               "-mm": 2, "-o": 3, "-s": 3, "-t": 3, "-texres": 1, "-type": 1}


#: the suffixes of the images a material library's maps name
IMAGE_SUFFIXES = frozenset({".png", ".jpg", ".jpeg", ".jpe", ".tga", ".bmp", ".tif", ".tiff", ".gif", ".webp",
                            ".dds", ".ktx", ".ktx2", ".exr", ".hdr", ".psd", ".rgb", ".sgi", ".pcx", ".ppm"})


def map_file_name(ref: str) -> str:
    """The file an OBJ's ``mtllib`` or a material library's ``map_*`` statement names: its options
    (:data:`MAP_OPTIONS`) dropped, ``\\`` read as ``/``; a name with spaces kept whole, a quoted
    one unquoted."""
    tokens = ref.strip().split(" ")
    while len(tokens) > 1 and tokens[0].lower() in MAP_OPTIONS:
        option, tokens = tokens[0].lower(), tokens[1:]
        numeric = option in ("-o", "-s", "-t")
        for _ in range(MAP_OPTIONS[option]):
            if len(tokens) > 1 and (not numeric or _is_number(tokens[0])):
                tokens = tokens[1:]
    name = " ".join(tokens)
    if len(name) > 1 and name[0] == name[-1] == '"':
        name = name[1:-1]
    return name.replace("\\", "/")


def _found_tail(ref: str, folder: Path) -> str | None:
    """The longest tail of the path ``ref`` (``C:/work/city/tex/a.jpg``: ``work/city/tex/a.jpg`` ...
    ``tex/a.jpg``, ``a.jpg``) that is a file inside ``folder``; None where none is."""
    parts = [p for p in PurePosixPath(ref).parts if p not in ("/", "..", ".") and not p.endswith(":")]
    for k in range(len(parts)):
        tail = "/".join(parts[k:])
        if tail != ref and (folder / tail).is_file() and (folder / tail).resolve().is_relative_to(folder.resolve()):
            return tail
    return None


def _is_number(text: str) -> bool:
    try:
        float(text)
    except ValueError:
        return False
    return True


class _Files(trimesh.resolvers.FilePathResolver):
    """Files next to the model, each request recorded: trimesh only logs a material library
    or texture it cannot find or decode, and draws the parts in a plain colour. A file outside
    the model's folder is never opened (:func:`~pipeline25d.formats.common.side_file`)."""

    def __init__(self, source: str):
        super().__init__(source)
        self.asked: dict[str, bytes | None] = {}
        self.model = Path(source)
        self.outside: InputFileError | None = None
        self.checked: set[str] = set()

    def get(self, name: str) -> bytes:
        """The file a model names: a material library's map options dropped and Windows separators
        read as '/' (:func:`map_file_name`); where no such file lies in the model's folder (an
        exporter's absolute path, ``C:\\Users\\...\\tex.jpg``), the one its path ends in inside that
        folder, with a warning (:func:`_found_tail`)."""
        if name in self.asked:                          # asked before (an earlier slab): the same bytes
            if self.asked[name] is None:
                raise FileNotFoundError(f"{name}: missing or not drawable (warned of once)")
            return self.asked[name]
        what = self.kind(name)
        folder, wanted = self.model.parent, map_file_name(name)
        try:
            found = side_file(wanted, folder, folder, self.model, what, url=False)    # its letter case may differ
            wanted, outside = (wanted if found == folder / wanted else str(found)), None
        except InputFileError as exc:
            outside = exc
        if outside is not None or not (folder / wanted).is_file():
            tail = _found_tail(wanted, folder)
            if tail is not None:
                warnings.warn(f"{self.model}: {what} '{name.strip()}' is not where it says; {tail} in the model's "
                              "folder is used", stacklevel=5)
                wanted, outside = tail, None
        if outside is not None:
            self.outside = self.outside or outside
            raise outside
        try:
            data = super().get(wanted)
        except Exception:
            self.asked[name] = None
            raise
        self.asked[name] = data
        return data

    def kind(self, name: str) -> str:
        """What the model names by ``name``: an OBJ's material library (``.mtl``, or any name not an
        image's: ``mtllib city.mat``) or a texture."""
        suffix = PurePosixPath(map_file_name(name)).suffix.lower()
        obj = self.model.suffix.lower() == ".obj"
        return "material library" if suffix == ".mtl" or (obj and suffix not in IMAGE_SUFFIXES) else "texture"

    def check(self, model: Path) -> None:
        """Warn of each material library or texture that was missing or cannot be drawn (not an
        image, truncated, corrupt: :func:`~pipeline25d.formats.common.image_problem`); such a
        texture's file is served as None from then on, so its parts are drawn untextured."""
        if self.outside is not None:
            raise self.outside
        for name, data in self.asked.items():
            if name in self.checked:                    # an earlier slab's file: checked then
                continue
            self.checked.add(name)
            what = self.kind(name)
            problem = "is missing" if data is None else image_problem(data) if what == "texture" else None
            if problem is not None:
                self.asked[name] = None
                warnings.warn(f"{model}: {what} {name!r} {problem}; its parts are drawn untextured",
                              MissingTextureWarning, stacklevel=3)
