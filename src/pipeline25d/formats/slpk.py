"""The entries of an I3S scene layer package: a ``.slpk`` (a zip, its entries mostly stored gzipped)
or the package unpacked into a folder. An entry is read by its name with or without ``.gz`` (and
the suffixes a caller tries), decompressed at most to :data:`~pipeline25d.formats.gzipped.MAX_BYTES`
(a larger entry, or a gzip bomb, is an error naming it).
"""

from __future__ import annotations

import json
import zipfile
from pathlib import Path

from pipeline25d.core.errors import InputFileError
from pipeline25d.formats.gzipped import MAX_BYTES, gunzipped


class Package:
    """The entries of a scene layer package (``.slpk``) or of its unpacked folder, gunzipped."""

    def __init__(self, path: Path):
        self.path = Path(path)
        self._zip = None
        if self.path.is_file():
            try:
                self._zip = zipfile.ZipFile(self.path)
            except (zipfile.BadZipFile, OSError) as exc:
                raise InputFileError(self.path, f"is not a scene layer package (not a zip: {exc})") from None
            self._names = {info.filename: info for info in self._zip.infolist()}

    def read(self, name: str, *suffixes: str) -> bytes | None:
        """The entry ``name`` (tried as is, with each of ``suffixes``, each also gzipped); None if absent."""
        for stem in (name, *(name + s for s in suffixes)):
            for entry in (stem, stem + ".gz"):
                data = self._entry(entry)
                if data is not None:
                    return gunzipped(data, self.path / entry)
        return None

    def _entry(self, name: str) -> bytes | None:
        if self._zip is None:
            file = self.path / name
            if not file.is_file():
                return None
            if file.stat().st_size > MAX_BYTES:
                raise InputFileError(file, f"is larger than {MAX_BYTES:,} bytes")
            return file.read_bytes()
        info = self._names.get(name)
        if info is None:
            return None
        if info.file_size > MAX_BYTES:
            raise InputFileError(self.path, f"entry {name} is larger than {MAX_BYTES:,} bytes")
        try:
            return self._zip.read(info)
        except (zipfile.BadZipFile, OSError, EOFError, NotImplementedError) as exc:
            raise InputFileError(self.path, f"entry {name} cannot be read (a corrupt or cut-short package: "
                                            f"{exc})") from None

    def json(self, name: str) -> dict:
        """A JSON entry (``name``, ``name.json``, gzipped or not); InputFileError naming it when absent or bad."""
        data = self.read(name, ".json")
        if data is None:
            raise InputFileError(self.path, f"has no {name}.json (is it an I3S scene layer?)")
        try:
            doc = json.loads(data)
        except (ValueError, RecursionError) as exc:
            raise InputFileError(self.path, f"{name}.json is not valid JSON: {exc}") from None
        if not isinstance(doc, dict):
            raise InputFileError(self.path, f"{name}.json is not a JSON object")
        return doc


def is_scene_layer_folder(path: Path) -> bool:
    """Whether ``path`` is an unpacked scene layer package (a folder with ``3dSceneLayer.json``)."""
    return path.is_dir() and any((path / f"3dSceneLayer.json{gz}").is_file() for gz in ("", ".gz"))

