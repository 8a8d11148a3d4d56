"""What every reader shares: its return type, reading a text file with clear errors, the one
confinement check of the side files a model names, reprojection."""

from __future__ import annotations

import contextvars
import os
import shutil
import subprocess
import warnings
from collections.abc import Callable, Iterable, Iterator
from contextlib import contextmanager
from dataclasses import replace
from functools import lru_cache
from pathlib import Path, PurePosixPath
from typing import Any, NamedTuple
from urllib.parse import unquote, urlsplit

import numpy as np

from pipeline25d.core.crs import check_within_area_of_use, implied_z_metres, parse_crs, transform_points, z_unit
from pipeline25d.core.errors import CRSError, InputFileError, MissingTextureWarning, UnsupportedFeatureError
from pipeline25d.core.mesh import Coarser, Mesh, MeshPart

AREA_SAMPLE = 2000   # vertices checked against the scene CRS's area of use
MAX_COORDINATE = 1e8  # |x|, |y|, |z| beyond this is no place on Earth in any CRS (ECEF reaches 6.4e6 m)
FLAT = 1e-10          # a triangle whose height is below FLAT x its longest edge has no area (float64)
FACE_BATCH = 1 << 20  # triangles checked at a time (bounds the temporary arrays)
CONVERTER_TIMEOUT_S = 600

#: y-up to z-up, (x, y, z) -> (x, -z, y), a rotation: glTF's convention to 3D Tiles' and the scene's,
#: and a y-up mesh file's (``up_axis: y``)
Y_UP_TO_Z_UP = np.array([[1, 0, 0, 0], [0, 0, -1, 0], [0, 1, 0, 0], [0, 0, 0, 1]], dtype=np.float64)


def z_up(points: np.ndarray) -> np.ndarray:
    """(n, 3) points of a y-up model turned z-up by :data:`Y_UP_TO_Z_UP`."""
    return np.asarray(points, dtype=np.float64) @ Y_UP_TO_Z_UP[:3, :3].T


class Detail(NamedTuple):
    """How much detail the maps need, for readers of multi-resolution formats (3D Tiles, OSGB):
    ``max_error`` the largest geometric error (m) a drawn level may have, ``gsd`` the map's
    metres per pixel; None = full detail / unknown."""

    max_error: float | None = None
    gsd: float | None = None


class Loaded(NamedTuple):
    """What every reader returns (see :mod:`pipeline25d.formats`): the model's parts, float64,
    in the CRS named by ``crs``; None when the file does not say (the input's ``crs`` key,
    else the scene CRS, then applies)."""

    parts: list[MeshPart]
    crs: str | None
    coarser: tuple[Coarser, ...] = ()   # tiles drawn coarser than asked (missing children)


def read_text(path: Path, what: str) -> str:
    """The file's text (UTF-8, BOM tolerated; a gzipped file's: :mod:`.gzipped`); InputFileError naming
    ``what`` when unreadable."""
    from pipeline25d.formats.gzipped import file_bytes

    try:
        return file_bytes(path).decode("utf-8-sig")
    except FileNotFoundError:
        raise InputFileError(path, f"{what} is missing") from None
    except (OSError, UnicodeDecodeError) as exc:
        raise InputFileError(path, f"cannot read {what}: {exc}") from None


def png_or_jpeg(data: bytes) -> bool:
    """Whether encoded image bytes begin as a PNG or a JPEG does (the two a glTF may hold)."""
    return data[:8] == b"\x89PNG\r\n\x1a\n" or data[:3] == b"\xff\xd8\xff"


def raw_tga(data: bytes) -> bool:
    """Whether image bytes begin as an uncompressed true-colour TGA does (no colour map, image type
    2, 24 or 32 bits a pixel): what osgconv writes for an OSGB tile's textures, which the render job
    reads without decoding (a PNG of 512 x 512 texels decoded in 10-15 ms, the same TGA in 1-2 ms)."""
    return len(data) >= 18 and data[1] == 0 and data[2] == 2 and data[16] in (24, 32)


def drawn_as_is(data: bytes) -> bool:
    """Whether a texture's bytes are kept as they are (a PNG, a JPEG, an uncompressed TGA), not re-encoded as PNG."""
    return png_or_jpeg(data) or raw_tga(data)


def image_problem(data: bytes) -> str | None:
    """What keeps encoded image bytes from being drawn ("is not an image", "cannot be read (...)":
    truncated, corrupt), or None: what the render job's decoder would meet, found when the file is
    read. A PNG whose chunks all check out (read to its end, a fraction of a decode) is whole; any
    other image (a JPEG or a TGA, whose checks read none of their data) and a PNG that fails its
    check are decoded (a PNG with a wrong checksum but whole data decodes, and is drawn, as the
    renderer would draw it)."""
    import io

    from PIL import Image, UnidentifiedImageError

    try:
        with Image.open(io.BytesIO(data)) as img:
            kind = img.format
            try:
                img.verify()
                checked = kind == "PNG"
            except (OSError, SyntaxError, ValueError):
                checked = False
        if not checked:
            with Image.open(io.BytesIO(data)) as img:
                img.load()
    except UnidentifiedImageError:
        return "is not an image"
    except (OSError, SyntaxError, ValueError) as exc:
        return f"cannot be read ({exc})"
    return None


def texture_image(model: Path, image: str, problem: str | None = None) -> bytes | None:
    """The encoded bytes of texture image file ``image``, or None with a MissingTextureWarning
    ("<model>: texture image <image> <problem>; ...") when it is missing, not an image or
    unreadable (:func:`image_problem`), or when the caller already knows its ``problem``."""
    data = None
    if problem is None:
        try:
            data = Path(image).read_bytes()
        except FileNotFoundError:
            problem = "is missing"
        except OSError as exc:
            problem = f"cannot be read ({exc})"
        else:
            problem = image_problem(data)
    if problem:
        warnings.warn(f"{model}: texture image {image} {problem}; its parts are drawn untextured",
                      MissingTextureWarning, stacklevel=3)
        return None
    return data


def side_file(ref: str, base: Path, root: Path, referrer: Path, what: str, url: bool = True) -> Path:
    """The local file that ``referrer`` names by ``ref`` (relative to folder ``base``), confined to ``root``.

    ``root`` is the dataset's folder: the folder of the file the config's ``inputs`` name (a
    tileset's root tileset.json, a model file), or an OSGB dataset folder. ``..`` that stays
    inside it is fine (tilesets reference siblings). A ``ref`` that resolves outside it (an
    absolute path, a ``file:`` URI, ``..`` climbing out, a symlink pointing out) is an
    InputFileError naming ``referrer`` and ``ref``; a remote URI (``http(s):``...) an
    UnsupportedFeatureError (no network). ``url``: ``ref`` is a URI (glTF, 3D Tiles:
    percent-escapes decoded), else a plain path (CityGML imageURI, OBJ, OSGB). The path is
    returned as joined (not resolved), so messages keep the names the files use. Where no file
    has that name but one differs from it in letter case alone (a model made on Windows or
    macOS, whose file systems ignore case; a 3DS file's upper-case DOS names), that file is
    returned, with a warning.
    """
    parts = urlsplit(ref)
    scheme = parts.scheme.lower()
    if scheme == "file":
        name = unquote(parts.path)
    elif len(scheme) > 1:   # one letter: a Windows drive
        raise UnsupportedFeatureError(referrer, f"{what} {ref!r} is remote; pipeline25d reads local files "
                                                "only (no network)")
    else:
        name = unquote(parts.path) if url else ref
    target = base / name
    _confined(target, ref, root, referrer, what)
    if not target.exists():
        other = other_case(base, name)
        if other is not None:
            _confined(other, ref, root, referrer, what)          # a link of another case may lead out
            on_disk = "/".join(other.parts[-len(PurePosixPath(name).parts):])
            warnings.warn(f"{referrer}: {what} {ref!r} is {on_disk!r} on disk (the letter case differs); that file "
                          "is used", stacklevel=3)
            return other
    return target


def texture_file(ref: str, base: Path, root: Path, referrer: Path, what: str,
                 url: bool = True) -> tuple[Path | None, str | None]:
    """(:func:`side_file`, None) for a texture image a model names, or (None, the problem) where it
    leads outside the dataset folder or is remote: that image is not read, and is a missing texture
    (``missing_textures`` decides), where a model or child file there refuses the input."""
    try:
        return side_file(ref, base, root, referrer, what, url=url), None
    except InputFileError as exc:
        return None, exc.problem.removeprefix(f"{what} {ref!r} ")


def _confined(target: Path, ref: str, root: Path, referrer: Path, what: str) -> None:
    real = target.resolve()
    if not any(real.is_relative_to(_real(r)) for r in (root, *_SIDE_FOLDERS.get())):
        raise InputFileError(referrer, f"{what} {ref!r} lies outside the dataset folder {root} (it resolves to "
                                       f"{real}); a model may only name files inside the folder of the input "
                                       "(or in a folder the input's side_folders names)")


def other_case(base: Path, name: str) -> Path | None:
    """The one file under ``base`` whose path ``name`` (``/``-separated, relative) differs from
    it in letter case alone, component by component; None where there is none, or more than
    one (``a.JPG`` and ``a.jpg`` both there: nothing to choose by)."""
    here = base
    for part in PurePosixPath(name).parts:
        if part in (".", ".."):
            here = here / part
            continue
        if (here / part).exists():
            here = here / part
            continue
        try:
            found = [e for e in os.listdir(here) if e.casefold() == part.casefold()]
        except OSError:
            return None
        if len(found) != 1:
            return None
        here = here / found[0]
    return here if here.is_file() else None


#: extra folders side files may lie in while an input is read (its ``side_folders``)
_SIDE_FOLDERS: contextvars.ContextVar[tuple[Path, ...]] = contextvars.ContextVar("side_folders", default=())


@contextmanager
def side_folders(folders: Iterable[Path]) -> Iterator[None]:
    """While inside, :func:`side_file` also accepts files in ``folders`` (an input's
    ``side_folders``: a texture folder its parts share outside the input's own folder). Threads
    a reader starts see them through :func:`in_context`."""
    token = _SIDE_FOLDERS.set(tuple(Path(f) for f in folders))
    try:
        yield
    finally:
        _SIDE_FOLDERS.reset(token)


def in_context(fn: Callable[..., Any]) -> Callable[[tuple], Any]:
    """``fn(*args)`` as a one-argument function for ``pool.map`` that runs in the caller's
    context (its :func:`side_folders`) in whichever thread calls it."""
    context = contextvars.copy_context()
    return lambda args: context.copy().run(fn, *args)


@lru_cache(maxsize=64)
def _real(root: Path) -> Path:
    return root.resolve()


def dataset_root(path: Path) -> Path:
    """The folder a model's side files must lie in: the folder itself for a dataset folder,
    else the folder of the file (see :func:`side_file`)."""
    return path if path.is_dir() else path.parent


#: German AdV CRS names (urn:adv:crs:ETRS89_UTM32*DE_DHHN2016_NH, in most German CityGML):
#: horizontal and height parts, EPSG codes
_ADV = {"ETRS89_UTM31": 25831, "ETRS89_UTM32": 25832, "ETRS89_UTM33": 25833, "ETRS89_GK3": 4647,
        "DE_DHDN_3GK2": 31466, "DE_DHDN_3GK3": 31467, "DE_DHDN_3GK4": 31468, "DE_DHDN_3GK5": 31469,
        "DE_PD/83_3GK3": 3396, "DE_PD/83_3GK4": 3397, "DE_RD/83_3GK4": 3398, "DE_RD/83_3GK5": 3399,
        "DE_DHHN2016_NH": 7837, "DE_DHHN92_NH": 5783, "DE_DHHN85_NH": 5784, "DE_DHHN12_NH": 7699}


def crs_name(ref: str) -> str:
    """'AUTH:CODE' (compound: 'EPSG:h+v') of a CRS reference: an OGC URL
    (``http://www.opengis.net/def/crs/EPSG/0/6697``), URN (``urn:ogc:def:crs:EPSG::25832``,
    compound ``urn:ogc:def:crs,crs:EPSG::25832,crs:EPSG::5783``), an EPSG XML link
    (``http://www.opengis.net/gml/srs/epsg.xml#25832``) or an AdV name; other text unchanged."""
    ref = ref.strip()
    low = ref.lower()
    if "/def/crs/" in low:  # https://www.opengis.net/def/crs/EPSG/0/7415
        bits = ref.rstrip("/").split("/")
        return f"{bits[-3]}:{bits[-1]}"
    if low.startswith("urn:ogc:def:crs,"):  # compound: one URN per part
        codes = [crs_name("urn:ogc:def:" + part) for part in ref.split(",")[1:]]
        return codes[0] + "".join("+" + c.split(":")[-1] for c in codes[1:])
    if low.startswith("urn:ogc:def:crs:"):  # urn:ogc:def:crs:EPSG::7415
        bits = ref.split(":")
        return f"{bits[4]}:{bits[-1]}"
    if "epsg.xml#" in low:
        return "EPSG:" + ref.rsplit("#", 1)[1]
    if low.startswith("urn:adv:crs:"):
        codes = [_ADV.get(part) for part in ref[len("urn:adv:crs:"):].split("*")]
        if all(codes):
            return "EPSG:" + "+".join(str(c) for c in codes)
    return ref


def run_converter(args: list[str], cwd: Path, output: Path, what: Path, package: str,
                  env: dict[str, str] | None = None) -> str:
    """Run an external model converter (osgconv, assimp) in ``cwd`` without a display; returns
    what it printed (its warnings).

    UnsupportedFeatureError naming ``what`` when the program is not installed (``package``
    provides it), InputFileError naming ``what`` with the program's last words when it fails
    or writes no ``output`` (relative to ``cwd``).
    """
    if shutil.which(args[0]) is None:
        raise UnsupportedFeatureError(what, f"reading it needs {args[0]} (Debian package {package})")
    run_env = {k: v for k, v in os.environ.items() if k != "DISPLAY"} | (env or {})
    try:
        proc = subprocess.run(args, cwd=cwd, env=run_env, capture_output=True, text=True, errors="replace",
                              timeout=CONVERTER_TIMEOUT_S)
    except subprocess.TimeoutExpired:
        raise InputFileError(what, f"{args[0]} took longer than {CONVERTER_TIMEOUT_S} s") from None
    if proc.returncode or not (cwd / output).is_file():
        said = " ".join((proc.stdout + proc.stderr).split())
        tail = said[said.rfind("ERROR:"):] if "ERROR:" in said else said   # assimp: its error, not its log
        tail = tail[-300:]
        raise InputFileError(what, f"{args[0]} cannot read it (corrupt, or not that format): {tail}")
    return proc.stdout + proc.stderr


def reproject_parts(parts: list[MeshPart], src_crs: str, scene_crs: str, where: str | Path) -> list[MeshPart]:
    """Parts moved from ``src_crs`` to ``scene_crs`` in one transform call.

    First checks that a sample of the vertices (converted to lon/lat) lies in the areas of
    use of ``src_crs`` and of the scene CRS, so a model in the wrong place or labelled with
    the wrong CRS fails with a CRSError naming ``where`` instead of yielding silently
    distorted coordinates; so does a transform that fails.
    """
    if not parts or parse_crs(src_crs) == parse_crs(scene_crs):
        return parts
    if implied_z_metres(src_crs) != 1.0:
        unit, metres = z_unit(src_crs)
        warnings.warn(f"{where}: {src_crs} names no vertical CRS; its heights are taken in its horizontal unit, "
                      f"the {unit} ({metres:.7g} m), as its x and y are", stacklevel=3)
    allv = np.concatenate([p.vertices for p in parts])
    try:
        lonlat = transform_points(allv[:: max(1, len(allv) // AREA_SAMPLE)], src_crs, "EPSG:4979")
        check_within_area_of_use(lonlat, src_crs, where=str(where))
        check_within_area_of_use(lonlat, scene_crs, where=str(where))
        moved = transform_points(allv, src_crs, scene_crs)
    except CRSError as exc:
        message = str(exc)
        raise CRSError(message if message.startswith(f"{where}:") else f"{where}: {message}") from None
    ends = np.cumsum([len(p.vertices) for p in parts])
    return [replace(p, vertices=v) for p, v in zip(parts, np.split(moved, ends[:-1]))]


def in_scene(loaded: Loaded, scene_crs: str, where: str | Path) -> Mesh:
    """A reader's result, checked (:func:`checked_parts`), as a Mesh in ``scene_crs``
    (``loaded.crs`` None: already there)."""
    parts = checked_parts(loaded.parts, where)
    parts = parts if loaded.crs is None else reproject_parts(parts, loaded.crs, scene_crs, where)
    return Mesh(parts, source=str(where), coarser=loaded.coarser)


def checked_parts(parts: list[MeshPart], where: str | Path) -> list[MeshPart]:
    """The parts with their degenerate triangles (repeated vertex, zero area) dropped, with a
    warning naming ``where`` and the count; every other triangle is kept as it is.

    InputFileError naming ``where`` when a triangle has a NaN or infinite vertex (it must
    not reach the GPU), when a coordinate is beyond :data:`MAX_COORDINATE`, or when every
    triangle is degenerate. A model with no triangles at all passes (readers warn of it).
    """
    out, dropped, total = [], 0, 0
    for part in parts:
        keep = _valid_faces(part, where)
        total += len(keep)
        dropped += int((~keep).sum())
        out.append(part if keep.all() else part.with_faces(part.faces[keep], keep))
    if dropped == total and total:
        raise InputFileError(where, f"all {total} triangles are degenerate (zero area)")
    if dropped:
        warnings.warn(f"{where}: dropped {dropped} of {total} triangles that are degenerate (zero area)",
                      stacklevel=3)
    return out


def _valid_faces(part: MeshPart, where: str | Path) -> np.ndarray:
    """(m,) bool: the part's triangles that have an area; raises on unusable coordinates."""
    faces, v = part.faces, part.vertices
    if not len(faces):
        return np.ones(0, dtype=bool)
    if faces.min() < 0 or faces.max() >= len(v):
        bad = faces.max() if faces.max() >= len(v) else faces.min()
        raise InputFileError(where, f"vertex index {bad} out of range ({len(v)} vertices)")
    used = np.zeros(len(v), dtype=bool)
    used[faces.ravel()] = True
    finite = np.isfinite(v).all(axis=1)
    if not finite[used].all():
        bad = np.flatnonzero(used & ~finite)
        raise InputFileError(where, f"{len(bad)} vertices have NaN or infinite coordinates "
                                    f"(first: vertex {bad[0]} of {part.name or 'the model'})")
    reach = np.abs(v[used]).max()
    if reach > MAX_COORDINATE:
        raise InputFileError(where, f"coordinates reach {reach:.3g}, beyond any place on Earth "
                                    f"(|x|, |y|, |z| <= {MAX_COORDINATE:.0e}; wrong units or CRS?)")
    keep = np.empty(len(faces), dtype=bool)
    for start in range(0, len(faces), FACE_BATCH):
        f = faces[start:start + FACE_BATCH]
        a, b, c = v[f[:, 0]], v[f[:, 1]], v[f[:, 2]]
        ab, ac, bc = b - a, c - a, c - b
        twice_area = np.linalg.norm(np.cross(ab, ac), axis=1)
        longest = np.sqrt(np.max([np.einsum("ij,ij->i", e, e) for e in (ab, ac, bc)], axis=0))
        keep[start:start + FACE_BATCH] = twice_area > FLAT * longest * longest
    return keep

