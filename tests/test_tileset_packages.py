"""3D Tiles packages (3TZ, a zipped tileset folder, the 3DTILES SQLite package) read as the folder they
pack: the same triangles, unpacked once into the cache, hostile entries refused."""

from __future__ import annotations

import gzip
import json
import sqlite3
import zipfile
from pathlib import Path

import numpy as np
import pytest

from pipeline25d.core.errors import InputFileError
from pipeline25d.formats import load_district
from pipeline25d_lab.scenes.model_writers import SCENE_CRS, SQUARE, SQUARE_FACES, tileset, write_b3dm


@pytest.fixture(autouse=True)
def cache(tmp_path, monkeypatch):
    folder = tmp_path / "cache"
    monkeypatch.setenv("PIPELINE25D_CACHE", str(folder))
    return folder


@pytest.fixture
def folder(tmp_path):
    """A tileset folder: a root tile and a child in a subfolder, each a b3dm of the square."""
    root = tmp_path / "tiles"
    (root / "sub").mkdir(parents=True)
    write_b3dm(root / "root.b3dm", SQUARE, SQUARE_FACES, None)
    write_b3dm(root / "sub" / "child.b3dm", SQUARE + (0, 0, 5), SQUARE_FACES, None)
    child = {"boundingVolume": {"sphere": [0, 0, 0, 1e7]}, "geometricError": 0, "content": {"uri": "sub/child.b3dm"}}
    (root / "tileset.json").write_text(json.dumps(tileset("root.b3dm", [child])))
    return root


def _files(folder):
    return {p.relative_to(folder).as_posix(): p.read_bytes() for p in sorted(folder.rglob("*")) if p.is_file()}


def _zip(path, entries: dict[str, bytes]):
    with zipfile.ZipFile(path, "w") as z:
        for name, data in entries.items():
            z.writestr(name, data)
    return path


def _vertices(path):
    return np.concatenate([p.vertices for p in load_district({"path": str(path)}, SCENE_CRS).parts])


def test_each_package_reads_as_the_folder_it_packs(folder, tmp_path):
    want = _vertices(folder / "tileset.json")
    files = _files(folder)
    three_tz = _zip(tmp_path / "city.3tz", {**files, "@3dtilesIndex1@": bytes(24)})
    metashape = _zip(tmp_path / "city.zip", {f"Tileset/{k}": v for k, v in files.items()})   # a folder inside
    sqlite_package = tmp_path / "city.3dtiles"
    with sqlite3.connect(sqlite_package) as db:
        db.execute("CREATE TABLE media (key TEXT PRIMARY KEY, content BLOB)")
        db.executemany("INSERT INTO media VALUES (?, ?)",               # contents gzipped, as 3d-tiles-tools may
                       [(k, gzip.compress(v) if k.endswith(".b3dm") else v) for k, v in files.items()])
    assert len(want) == 8
    for package in (three_tz, metashape, sqlite_package):
        np.testing.assert_array_equal(_vertices(package), want)


def test_a_package_is_unpacked_once_and_again_when_replaced(folder, tmp_path, cache):
    package = _zip(tmp_path / "city.3tz", _files(folder))
    _vertices(package)
    (unpacked,) = _copies(cache)
    marker = unpacked / "read-again"
    marker.write_text("the same folder is read again")
    _vertices(package)
    assert _copies(cache) == [unpacked] and marker.exists()
    files = _files(folder)                                    # the package replaced: a child moved up 5 m
    write_b3dm(folder / "sub" / "child.b3dm", SQUARE + (0, 0, 10), SQUARE_FACES, None)
    _zip(package, {**files, "sub/child.b3dm": (folder / "sub" / "child.b3dm").read_bytes()})
    assert _vertices(package)[:, 2].max() - _vertices(folder / "tileset.json")[:, 2].min() > 9.9
    (again,) = _copies(cache)                                 # unpacked anew, the older copy gone
    assert again.name != unpacked.name
    assert sorted(p.name for p in (cache / "packages").iterdir()) == [again.name, f"{again.name}.source.json"]


def _copies(cache):
    return sorted(p for p in (cache / "packages").iterdir() if p.is_dir())


def test_the_copy_of_a_package_that_no_longer_exists_is_removed_once_old(folder, tmp_path, cache):
    import os
    import time

    from pipeline25d.formats.tileset_packages import ORPHAN_AGE_S, sweep

    gone, kept = (_zip(tmp_path / name, _files(folder)) for name in ("gone.3tz", "kept.3tz"))
    _vertices(gone)
    _vertices(kept)
    (gone_copy, kept_copy) = _copies(cache)
    gone.unlink()
    assert sweep(cache / "packages") == [] and gone_copy.is_dir()      # just unpacked: perhaps still read
    old = time.time() - ORPHAN_AGE_S - 60
    for note in (cache / "packages").glob("*.source.json"):
        os.utime(note, (old, old))
    third = _zip(tmp_path / "third.3tz", _files(folder))
    _vertices(third)                                           # unpacking a package sweeps the cache
    assert [p.name.split("-")[0] for p in _copies(cache)] == ["kept.3tz", "third.3tz"]
    assert not gone_copy.exists() and not Path(f"{gone_copy}.source.json").exists() and kept_copy.is_dir()


def test_hostile_packages_are_refused_naming_the_package(folder, tmp_path, monkeypatch):
    files = _files(folder)
    slip = _zip(tmp_path / "slip.3tz", {**files, "../outside.b3dm": b"x"})
    with pytest.raises(InputFileError, match=r"slip\.3tz: entry '\.\./outside\.b3dm' lies outside the package"):
        _vertices(slip)
    assert not (tmp_path / "outside.b3dm").exists()
    empty = _zip(tmp_path / "no-tileset.zip", {"readme.txt": b"hello"})
    with pytest.raises(InputFileError, match=r"no-tileset\.zip: is a package without a tileset\.json"):
        _vertices(empty)
    (tmp_path / "not-a-zip.3tz").write_bytes(b"3TZ? no")
    with pytest.raises(InputFileError, match=r"not-a-zip\.3tz: is not a zip archive"):
        _vertices(tmp_path / "not-a-zip.3tz")
    (tmp_path / "not-sqlite.3dtiles").write_bytes(b"not a database, long enough to be looked at" * 10)
    with pytest.raises(InputFileError, match=r"not-sqlite\.3dtiles: is not a 3DTILES package"):
        _vertices(tmp_path / "not-sqlite.3dtiles")
    cut = _zip(tmp_path / "cut.3tz", {**files, "sub/child.b3dm": files["sub/child.b3dm"][:40]})
    with pytest.raises(InputFileError, match=r"cut\.3tz!/sub/child\.b3dm: "):     # named inside the package
        _vertices(cut)
    from pipeline25d.formats import tileset_packages

    monkeypatch.setattr(tileset_packages, "FREE_MARGIN", 1 << 62)          # no disk has that room
    big = _zip(tmp_path / "big.3tz", files)
    with pytest.raises(InputFileError, match=r"big\.3tz: unpacking needs .* GB free \(set PIPELINE25D_CACHE"):
        _vertices(big)
    assert not [p for p in (tmp_path / "cache" / "packages").iterdir() if p.name.startswith("big.3tz")]


def test_a_warning_about_a_file_in_a_package_names_it_inside_the_package(folder, tmp_path, cache):
    files = _files(folder)
    package = _zip(tmp_path / "trailing.3tz", {**files, "sub/child.b3dm": files["sub/child.b3dm"] + bytes(12)})
    with pytest.warns(UserWarning) as caught:
        got = _vertices(package)
    np.testing.assert_array_equal(got, _vertices(folder / "tileset.json"))   # the bytes after it ignored
    said = [str(w.message) for w in caught]
    assert f"{package}!/sub/child.b3dm: 12 bytes after the tile's byteLength ignored" in said
    assert not any(str(cache) in text for text in said)          # the cache's copy is never named
    both = _zip(tmp_path / "both.3tz", {**files, "root.b3dm": files["root.b3dm"] + bytes(4),
                                        "sub/child.b3dm": files["sub/child.b3dm"][:40]})
    with pytest.warns(UserWarning, match=r"both\.3tz!/root\.b3dm: 4 bytes after"):  # before the error, kept
        with pytest.raises(InputFileError, match=r"both\.3tz!/sub/child\.b3dm: "):
            _vertices(both)


def test_the_box_before_reading_and_objects_look_inside_the_package(folder, tmp_path):
    from pipeline25d.formats.boxes import input_box
    from pipeline25d.formats.has_objects import input_has_objects

    package = _zip(tmp_path / "city.3tz", _files(folder))
    want, got = input_box({"path": str(folder / "tileset.json")}), input_box({"path": str(package)})
    assert got is not None and got.crs == want.crs
    np.testing.assert_array_equal(got.corners, want.corners)
    assert input_has_objects({"path": str(package)}) == input_has_objects({"path": str(folder / "tileset.json")})
