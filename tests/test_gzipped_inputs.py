"""Tilesets stored gzipped (3d-tiles-tools' gzip: every file, or the tiles alone, as a server sends
them with Content-Encoding: gzip) read as their plain copies; a corrupt, cut-short or bomb-like
gzip stream is an error naming the file."""

from __future__ import annotations

import gzip
import shutil
from pathlib import Path

import numpy as np
import pytest

from pipeline25d.core.errors import InputFileError
from pipeline25d.formats import detect_format, load_district
from pipeline25d.formats.gzipped import gunzipped
from pipeline25d.formats.has_objects import input_has_objects
from pipeline25d_lab.scenes.model_writers import SCENE_CRS, _png, write_tileset


def plain_tileset(folder: Path) -> Path:
    """A textured one-tile tileset: two triangles, their image beside the tile."""
    folder.mkdir(parents=True)
    v = np.array([[0, 0, 0], [10, 0, 0], [10, 10, 5], [0, 10, 5]], dtype=np.float64)
    f = np.array([[0, 1, 2], [0, 2, 3]])
    (folder / "tex.png").write_bytes(_png())
    write_tileset(folder / "tileset.json", v, f, "tex.png")
    return folder / "tileset.json"


def gzipped_copy(plain: Path, folder: Path, suffixes: tuple[str, ...] | None = None) -> Path:
    """``plain``'s folder copied with every file (or those of ``suffixes``) gzipped in place."""
    shutil.copytree(plain.parent, folder)
    for path in folder.iterdir():
        if suffixes is None or path.suffix in suffixes:
            path.write_bytes(gzip.compress(path.read_bytes(), mtime=0))
    return folder / plain.name


@pytest.mark.parametrize("suffixes", [None, (".b3dm",)], ids=["every-file", "tiles-only"])
def test_a_gzipped_tileset_reads_as_its_plain_copy(tmp_path, suffixes):
    plain = plain_tileset(tmp_path / "plain")
    packed = gzipped_copy(plain, tmp_path / "packed", suffixes)
    assert packed.read_bytes()[:2] == b"\x1f\x8b" or suffixes is not None
    assert (packed.parent / "tileset.b3dm").read_bytes()[:2] == b"\x1f\x8b"
    assert detect_format(packed) == "3dtiles"
    a, b = (load_district({"path": str(p)}, SCENE_CRS) for p in (plain, packed))
    assert a.n_triangles == b.n_triangles == 2
    for pa, pb in zip(a.parts, b.parts):
        np.testing.assert_array_equal(pa.vertices, pb.vertices)
        assert pa.texture == pb.texture and pa.texture is not None        # the gzipped image too
    assert input_has_objects({"path": str(packed)}) == input_has_objects({"path": str(plain)})


def test_broken_gzip_streams_are_errors_naming_the_file(tmp_path):
    plain = plain_tileset(tmp_path / "plain")
    packed = gzipped_copy(plain, tmp_path / "packed", (".b3dm",))
    tile = packed.parent / "tileset.b3dm"
    tile.write_bytes(tile.read_bytes()[:-30])
    with pytest.raises(InputFileError, match="cut short") as err:
        load_district({"path": str(packed)}, SCENE_CRS)
    assert "tileset.b3dm" in str(err.value)
    data = gzip.compress(b"x" * 100_000)
    with pytest.raises(InputFileError, match="corrupt"):
        gunzipped(data[:12] + b"\xff" * 20 + data[32:], tile)
    with pytest.raises(InputFileError, match="more than 1,000 bytes"):
        gunzipped(data, tile, limit=1000)
    assert gunzipped(data, tile, limit=100_000) == b"x" * 100_000
    assert gunzipped(b"b3dm...", tile) == b"b3dm..."                     # not gzip: as it is
