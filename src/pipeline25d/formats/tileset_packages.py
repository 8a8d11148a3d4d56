"""3D Tiles packages, read as the tileset folder they pack.

* **3TZ** (``.3tz``, ``.3dtiles.zip``): a zip archive with the tileset at its top and an index
  entry ``@3dtilesIndex1@`` (the 3D Tiles Archive Format; Cesium ion Self-Hosted and
  3d-tiles-tools write it);
* a **zipped tileset folder** (``.zip``), as Agisoft Metashape exports Cesium 3D Tiles: the
  shallowest ``tileset.json`` in it is the root;
* the **3DTILES** SQLite package (``.3dtiles``, 3d-tiles-tools): a table ``media(key, content)``.

A package is unpacked once into a folder of the cache (``$PIPELINE25D_CACHE``, else
``$XDG_CACHE_HOME/pipeline25d``, else ``~/.cache/pipeline25d``), named by the package's path, size
and modification time (the copy of an older version removed), and read from there like any tileset
folder: its side files stay inside it (:func:`~pipeline25d.formats.common.side_file`). An entry
whose name is absolute or climbs out with ``..`` is refused, naming it; so is a package that needs
more room than the cache's disk has free (keeping :data:`FREE_MARGIN` bytes). Unpacking writes to a
temporary folder renamed into place, so an interrupted one leaves nothing that looks complete.
"""

from __future__ import annotations

import hashlib
import json
import logging
import os
import posixpath
import shutil
import sqlite3
import tempfile
import time
import warnings
import zipfile
from collections.abc import Iterator
from pathlib import Path

from pipeline25d.core.atomic import write_json
from pipeline25d.core.errors import FileProblem, InputFileError

log = logging.getLogger(__name__)

SUFFIXES = (".3tz", ".3dtiles", ".zip")
FREE_MARGIN = 1 << 30          # bytes left free on the cache's disk after unpacking
INDEX_ENTRY = "@3dtilesIndex1@"


def is_package(path: Path) -> bool:
    """Whether ``path`` names a 3D Tiles package (by its suffix; ``.3dtiles.zip`` is a ``.zip``)."""
    return path.suffix.lower() in SUFFIXES and path.is_file()


def tileset_of(path: Path) -> Path:
    """The root tileset JSON of ``path``: ``path`` itself, or for a package its unpacked copy's."""
    path = Path(path)
    return root_tileset(path, unpacked(path)) if is_package(path) else path


def root_tileset(package: Path, folder: Path) -> Path:
    """The root tileset JSON in ``package``'s unpacked ``folder``: its shallowest ``tileset.json``."""
    found = sorted(folder.rglob("tileset.json"), key=lambda p: (len(p.relative_to(folder).parts), str(p)))
    if not found:
        raise InputFileError(package, "is a package without a tileset.json (not a 3D Tiles package)")
    return found[0]


def named_in_package(package: Path, folder: Path, items: Iterator) -> Iterator:
    """``items``, where an error or a warning names a file of ``package``'s unpacked ``folder``, naming
    it inside the package instead (``city.3tz!/tiles/0.b3dm: ...``), as the user knows it. Warnings
    are caught while each item is made (never while the caller holds it) and issued again renamed."""
    items = iter(items)
    while True:
        item, error = _END, None
        with warnings.catch_warnings(record=True) as caught:
            try:
                item = next(items)
            except StopIteration:
                pass
            except Exception as exc:              # raised below, after the warnings made before it
                error = exc
        for w in caught:
            warnings.warn_explicit(_inside(str(w.message), package, folder), w.category, w.filename, w.lineno)
        if isinstance(error, FileProblem) and Path(error.path).is_relative_to(folder):
            inside = f"{package}!/{Path(error.path).relative_to(folder).as_posix()}"
            raise type(error)(inside, _inside(str(error.problem), package, folder)) from None
        if error is not None:
            raise error
        if item is _END:
            return
        yield item


_END = object()


def _inside(text: str, package: Path, folder: Path) -> str:
    """``text`` with the unpacked ``folder`` named as ``package!`` (its files as ``package!/inner``)."""
    return text.replace(str(folder), f"{package}!")


def cache_folder() -> Path:
    base = os.environ.get("PIPELINE25D_CACHE")
    if base:
        return Path(base)
    return Path(os.environ.get("XDG_CACHE_HOME") or Path.home() / ".cache") / "pipeline25d"


def unpacked(path: Path) -> Path:
    """The folder ``path`` unpacks to in the cache, unpacking it first where it is not there. Named by
    the package's path and, after it, its size and modification time: a package replaced in place (a
    district updated) unpacks anew, and its older copies in the cache are removed, as are the copies
    of packages that no longer exist (:func:`sweep`)."""
    stat = path.stat()
    place = hashlib.sha256(str(path.resolve()).encode()).hexdigest()[:12]
    version = hashlib.sha256(f"{stat.st_size}\0{stat.st_mtime_ns}".encode()).hexdigest()[:8]
    target = cache_folder() / "packages" / f"{path.name}-{place}-{version}"
    if target.is_dir():
        return target
    target.parent.mkdir(parents=True, exist_ok=True)
    started = time.monotonic()
    entries = _sqlite_entries(path) if path.suffix.lower() == ".3dtiles" else _zip_entries(path)
    tmp = Path(tempfile.mkdtemp(prefix=f".{path.name}.", dir=target.parent))
    try:
        count = entries(tmp)
        try:
            os.replace(tmp, target)
        except OSError:               # another job unpacked it meanwhile: theirs is the same
            shutil.rmtree(tmp, ignore_errors=True)
    except BaseException:
        shutil.rmtree(tmp, ignore_errors=True)
        raise
    log.info("%s: unpacked %d files to %s in %.1f s", path, count, target, time.monotonic() - started)
    write_json(_source_note(target), {"source": str(path.resolve())})
    for older in target.parent.glob(f"{path.name}-{place}-*"):
        if older != target and older.is_dir():
            _remove_copy(older)
    sweep(target.parent)
    return target


#: a copy whose package no longer exists is removed once it was unpacked this long ago (s): never
#: under a run that is still reading it
ORPHAN_AGE_S = 3600


def sweep(packages: Path, now: float | None = None) -> list[Path]:
    """Remove the copies in ``packages`` (the cache's folder of unpacked packages) whose package no
    longer exists at the path it was unpacked from and which were unpacked over
    :data:`ORPHAN_AGE_S` ago; return them. Without it the cache would keep a copy of every package
    ever read (a renamed or deleted download's, as large as its package unpacked)."""
    now = time.time() if now is None else now
    removed = []
    for note in packages.glob("*.source.json"):
        copy = packages / note.name.removesuffix(".source.json")
        try:
            source = Path(json.loads(note.read_text())["source"])
            unpacked_at = note.stat().st_mtime
        except (OSError, ValueError, KeyError, TypeError):
            continue
        if not source.exists() and now - unpacked_at > ORPHAN_AGE_S:
            _remove_copy(copy)
            removed.append(copy)
            log.info("removed the cache's copy of %s (the package no longer exists): %s", source, copy)
    return removed


def _source_note(copy: Path) -> Path:
    """The file beside an unpacked copy that names the package it came from."""
    return copy.with_name(copy.name + ".source.json")


def _remove_copy(copy: Path) -> None:
    shutil.rmtree(copy, ignore_errors=True)
    _source_note(copy).unlink(missing_ok=True)


def _entry_path(root: Path, name: str, package: Path) -> Path | None:
    """Where entry ``name`` goes under ``root``; None for a folder or the 3TZ index entry."""
    if name.endswith("/") or name == INDEX_ENTRY:
        return None
    clean = posixpath.normpath(name.replace("\\", "/"))
    if clean.startswith("/") or clean == ".." or clean.startswith("../") or ":" in clean.split("/")[0]:
        raise InputFileError(package, f"entry {name!r} lies outside the package (an absolute name or one "
                                      "climbing out with ..)")
    return root / clean


def _room(package: Path, folder: Path, needed: int) -> None:
    free = shutil.disk_usage(folder).free
    if needed > free - FREE_MARGIN:
        raise InputFileError(package, f"unpacking needs {needed / 1e9:.1f} GB, the cache {folder.parent} has "
                                      f"{free / 1e9:.1f} GB free (set PIPELINE25D_CACHE to a larger disk)")


def _zip_entries(path: Path):
    try:
        archive = zipfile.ZipFile(path)
    except (zipfile.BadZipFile, OSError) as exc:
        raise InputFileError(path, f"is not a zip archive ({exc})") from None

    def write(root: Path) -> int:
        with archive:
            infos = archive.infolist()
            _room(path, root, sum(i.file_size for i in infos))
            count = 0
            for info in infos:
                target = _entry_path(root, info.filename, path)
                if target is None:
                    continue
                target.parent.mkdir(parents=True, exist_ok=True)
                try:
                    with archive.open(info) as src, open(target, "wb") as dst:
                        shutil.copyfileobj(src, dst, 1 << 20)
                except (zipfile.BadZipFile, EOFError, NotImplementedError, ValueError) as exc:
                    raise InputFileError(path, f"entry {info.filename} cannot be read (a corrupt or cut-short "
                                               f"archive: {exc})") from None
                count += 1
            return count
    return write


def _sqlite_entries(path: Path):
    def write(root: Path) -> int:
        try:
            with sqlite3.connect(f"file:{path}?mode=ro", uri=True) as db:
                (needed,) = db.execute("SELECT COALESCE(SUM(LENGTH(content)), 0) FROM media").fetchone()
                _room(path, root, needed)
                count = 0
                for key, content in db.execute("SELECT key, content FROM media"):
                    target = _entry_path(root, str(key), path)
                    if target is None or content is None:
                        continue
                    target.parent.mkdir(parents=True, exist_ok=True)
                    target.write_bytes(bytes(content))
                    count += 1
                return count
        except sqlite3.Error as exc:
            raise InputFileError(path, f"is not a 3DTILES package (SQLite with a media table: {exc})") from None
    return write
