"""A large OBJ read in slabs of faces (formats.obj_slabs) against trimesh's read of the whole file.

The OBJs are generated here: a height field at Dutch national-grid coordinates in three ``o``
objects, each row a textured or a plain material, quads and triangles, one face by negative
indices; and the same with vertex colours and no materials.
"""

from __future__ import annotations

import hashlib
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
from conftest import REPO
from PIL import Image

from pipeline25d.core.errors import InputFileError
from pipeline25d.formats import meshfile, obj_lines, obj_slabs
from pipeline25d.stages.chunks import unpack_parts
from pipeline25d.stages.ingest import write_chunks

E0, N0 = 85000.123456789, 446000.987654321


def write_obj(folder: Path, n: int, colours: bool = False) -> Path:
    """An (n x n)-cell height field as an OBJ in ``folder`` (module docstring); its path."""
    folder.mkdir(parents=True, exist_ok=True)
    lines = []
    if not colours:
        pixels = (np.random.default_rng(1).random((64, 64, 3)) * 255).astype(np.uint8)
        Image.fromarray(pixels).save(folder / "atlas.png")
        (folder / "m.mtl").write_text("newmtl tex\nKd 1 1 1\nmap_Kd atlas.png\n\nnewmtl plain\nKd 0.2 0.6 0.3\n")
        lines.append("mtllib m.mtl")
    for j in range(n + 1):
        for i in range(n + 1):
            x, y, z = E0 + 0.5 * i, N0 + 0.5 * j, 1.0 + np.sin(i * 0.3) * np.cos(j * 0.2)
            lines.append(f"v {x!r} {y!r} {float(z)!r}" + (f" {i / n:.4f} {j / n:.4f} 0.5" if colours else ""))
            if not colours:
                lines.append(f"vt {i / n!r} {j / n!r}")

    def ref(i: int, j: int) -> str:
        k = j * (n + 1) + i + 1
        return str(k) if colours else f"{k}/{k}"

    for o in range(3):
        lines.append(f"o part{o}")
        for j in range(o * n // 3, (o + 1) * n // 3):
            if not colours:
                lines.append("usemtl tex" if j % 2 == 0 else "usemtl plain")
            for i in range(n):
                a, b, c, d = ref(i, j), ref(i + 1, j), ref(i + 1, j + 1), ref(i, j + 1)
                lines += [f"f {a} {b} {c} {d}"] if (i + j) % 3 == 0 else [f"f {a} {b} {c}", f"f {a} {c} {d}"]
    lines.append("f -1 -2 -3" if colours else "f -1/-1 -2/-2 -3/-3")
    path = folder / "m.obj"
    path.write_text("\n".join(lines) + "\n")
    return path


def triangles(parts) -> list[tuple]:
    """Each triangle of ``parts`` as (its corners' positions, uv and colours from its lowest corner on,
    its object, its texture's digest, its part's name), sorted: what a read gives, however split."""
    out = []
    for p in parts:
        tex = hashlib.sha256(p.texture).hexdigest() if p.texture else None
        for k, f in enumerate(p.faces):
            first = min(range(3), key=lambda i: tuple(p.vertices[f[i]]))
            f = [f[(first + i) % 3] for i in range(3)]
            corners = [tuple(p.vertices[i]) for i in f]
            corners += [tuple(p.uv[i]) for i in f] if p.uv is not None else []
            corners += [tuple(p.colors[i]) for i in f] if p.colors is not None else []
            obj = p.objects[p.face_objects[k]] if p.face_objects is not None else None
            out.append((tuple(corners), obj, tex, p.name))
    return sorted(out)


@pytest.fixture()
def slabs_of(monkeypatch):
    """Slabs read for any file size, ``faces`` faces a slab."""
    def read(path: Path, faces: int):
        monkeypatch.setattr(obj_slabs, "SLAB_FILE_BYTES", 0)
        monkeypatch.setattr(obj_slabs, "SLAB_FACES", faces)
        return list(obj_slabs.read_obj_slabs(path, {"crs": "EPSG:28992"}))
    return read


@pytest.mark.parametrize("colours", [False, True], ids=["textured", "vertex-coloured"])
def test_slabs_give_the_triangles_of_the_whole_file(tmp_path, slabs_of, colours):
    path = write_obj(tmp_path, 30, colours)
    whole = meshfile.load_mesh_file(path).parts
    pieces = slabs_of(path, 97)
    face_lines = path.read_text().count("\nf ")
    assert len(pieces) == -(-face_lines // 97) > 10 and all(p.crs == "EPSG:28992" for p in pieces)
    got = triangles([part for piece in pieces for part in piece.parts])
    assert len(got) == 2 * 30 * 30 + 1
    assert got == triangles(whole)
    assert {t[1] for t in got} == {"part0", "part1", "part2"}
    if not colours:
        assert {t[3] for t in got} == {"tex", "plain"} and None not in {t[2] for t in got if t[3] == "tex"}


def test_chunks_of_slabs_hold_the_whole_files_triangles_and_each_texture_once(tmp_path, slabs_of):
    """Ingest's spool joins a chunk's textured part continued by the next slab: one part (and one
    copy of the atlas) per material in each chunk, as the whole file's read gives."""
    path = write_obj(tmp_path / "in", 30)
    whole = write_chunks(meshfile.load_mesh_file(path), "d", 4.0, tmp_path / "w", tmp_path / "w" / "index.json")
    from pipeline25d.core.mesh import Mesh

    pieces = (Mesh(piece.parts, str(path)) for piece in slabs_of(path, 61))
    slabbed = write_chunks(pieces, "d", 4.0, tmp_path / "s", tmp_path / "s" / "index.json")
    assert whole["chunks"].keys() == slabbed["chunks"].keys() and len(whole["chunks"]) == 16
    for cid in whole["chunks"]:
        a, b = (unpack_parts(data, data["origin"]) for data in (np.load(tmp_path / d / f"{cid}.npz") for d in "ws"))
        assert sum(p.texture is not None for p in b) == sum(p.texture is not None for p in a) == 1
        assert triangles(a) == triangles(b), cid


def test_a_slab_read_grows_with_the_vertices_not_the_faces(tmp_path):
    """Peak memory (VmHWM) reading a 180k- and a 720k-triangle OBJ (15 and 62 MB): trimesh's whole
    read grows with the file; the slabs' (50k faces) by their vertex table and not much more. The
    slabs are parsed in a worker process, as where two cores are idle (on a busy machine the reading
    process parses them itself, and its growth was 63 MB against the whole read's 116)."""
    code = ("import sys, re, pathlib; sys.path.insert(0, sys.argv[1]); from pipeline25d.formats import obj_slabs as s\n"
            "import pipeline25d.core.cores as c; c.job_workers = lambda threads, idle=None: 2\n"
            "s.SLAB_FILE_BYTES = int(sys.argv[3]); s.SLAB_FACES = 50_000\n"
            "pieces = s.read_obj_slabs(pathlib.Path(sys.argv[2]), {})\n"
            "n = sum(sum(p.n_triangles for p in piece.parts) for piece in pieces)\n"
            "print(n, re.search(r'VmHWM:\\s+(\\d+)', open('/proc/self/status').read()).group(1))")
    peak = {}
    for n in (300, 600):
        path = write_obj(tmp_path / str(n), n, colours=True)
        for mode, threshold in (("whole", 10 ** 12), ("slabs", 0)):
            out = subprocess.run([sys.executable, "-c", code, str(REPO / "src"), str(path), str(threshold)],
                                 capture_output=True, text=True, check=True).stdout.split()
            assert int(out[0]) == 2 * n * n + 1
            peak[mode, n] = int(out[1]) / 1024
    whole, slabs = (peak[mode, 600] - peak[mode, 300] for mode in ("whole", "slabs"))
    assert whole > 100, peak                                  # the whole read's growth is measured
    assert slabs < 0.5 * whole, peak                          # 0.34-0.38 measured; 5 M triangles: 0.54 GB vs 1.5


def test_a_face_beyond_the_vertices_names_the_file(tmp_path, slabs_of):
    path = write_obj(tmp_path, 6, colours=True)
    path.write_text(path.read_text() + "f 1 2 999\n")
    with pytest.raises(InputFileError, match=r"m\.obj: a face names vertex 999 of 49: out of range"):
        slabs_of(path, 10)


def without_plain_texture_coordinates(path: Path) -> list[str]:
    """``path``'s lines with no texture coordinates on the faces of its untextured material (as
    exporters write them)."""
    lines, plain = path.read_text().splitlines(), False
    for k, line in enumerate(lines):
        plain = line == "usemtl plain" if line.startswith("usemtl") else plain
        if plain and line.startswith("f "):
            lines[k] = "f " + " ".join(c.split("/")[0] for c in line.split()[1:])
    return lines


@pytest.mark.parametrize("faces", [7, 97, 10_000])
def test_faces_with_and_without_texture_coordinates_read_as_the_whole_file(tmp_path, slabs_of, faces):
    """The slabs' triangles are the whole file's, textured where it has texture coordinates,
    whatever the slab size."""
    path = write_obj(tmp_path, 12)
    lines = without_plain_texture_coordinates(path)
    path.write_text("\n".join(lines) + "\n")
    assert sum(line.startswith("f ") and "/" not in line for line in lines) > 50
    whole = meshfile.load_mesh_file(path).parts
    got = triangles([part for piece in slabs_of(path, faces) for part in piece.parts])
    assert got == triangles(whole) and len(got) == 2 * 12 * 12 + 1
    assert {t[3]: t[2] is not None for t in got} == {"tex": True, "plain": False}


def test_a_face_with_texture_coordinates_on_some_corners_is_refused_by_name(tmp_path, slabs_of):
    """trimesh reads such a face one way or another as the faces around it go; slabs refuse it."""
    path = write_obj(tmp_path, 6)
    lines = without_plain_texture_coordinates(path)
    k = next(k for k in range(lines.index("usemtl plain"), len(lines)) if lines[k].startswith("f "))
    a, b, *rest = lines[k].split()[1:]
    lines[k] = " ".join(["f", a, f"{b}/1", *rest])
    path.write_text("\n".join(lines) + "\n")
    with pytest.raises(InputFileError, match=r"m\.obj: a face gives texture coordinates for some of its corners"):
        slabs_of(path, 10_000)


def test_a_missing_texture_in_slabs_is_an_error_naming_it_or_drawn_untextured(tmp_path, monkeypatch):
    from pipeline25d.formats import district_pieces

    path = write_obj(tmp_path, 12)
    (tmp_path / "atlas.png").unlink()
    monkeypatch.setattr(obj_slabs, "SLAB_FILE_BYTES", 0)
    monkeypatch.setattr(obj_slabs, "SLAB_FACES", 50)
    spec = {"path": str(path), "crs": "EPSG:28992"}
    with pytest.raises(InputFileError, match=r"m\.obj: texture 'atlas\.png' is missing"):
        list(district_pieces(spec, "EPSG:28992"))
    pieces = list(district_pieces({**spec, "missing_textures": "untextured"}, "EPSG:28992"))
    parts = [p for piece in pieces for p in piece.parts]
    assert len(pieces) == -(-path.read_text().count("\nf ") // 50) == 5
    assert sum(p.n_triangles for p in parts) == 2 * 12 * 12 + 1
    assert all(p.texture is None for p in parts)


def test_an_obj_with_windows_line_ends_reads_as_with_unix_ones_whole_and_in_slabs(tmp_path, slabs_of):
    """CRLF (Windows exporters): the same objects and materials; the whole read took 'part0\\r' for
    no object and named the faces 'part0_tex'."""
    unix = write_obj(tmp_path / "lf", 9)
    crlf = tmp_path / "lf" / "crlf.obj"
    crlf.write_bytes(unix.read_bytes().replace(b"\n", b"\r\n"))
    expected = [t[:2] + t[3:] for t in triangles(meshfile.load_mesh_file(unix).parts)]
    for parts in (meshfile.load_mesh_file(crlf).parts, [p for piece in slabs_of(crlf, 40) for p in piece.parts]):
        assert [t[:2] + t[3:] for t in triangles(parts)] == expected
    assert {t[1] for t in expected} == {"part0", "part1", "part2"}


@pytest.mark.parametrize("layout", ["tabs", "indented", "bom", "cr", "cr-indented", "comments"])
def test_an_obj_written_with_tabs_indented_or_a_bom_reads_as_a_plain_one_whole_and_in_slabs(tmp_path, slabs_of,
                                                                                            layout, monkeypatch):
    """Whitespace is whitespace: tabs between words, lines indented, or lines ended by CR alone
    (classic Mac OS) read as the same file written with single spaces and LF (trimesh alone read no
    triangle of any of them); a UTF-8 byte order mark before a first ``v`` line is no part of it
    (trimesh dropped that vertex: every index off by one); a comment after a vertex, a texture
    coordinate or a face is no part of it (trimesh refused the file: "unmatched data")."""
    plain = write_obj(tmp_path / "plain", 9)
    folder = tmp_path / layout
    path = write_obj(folder, 9)
    lines = path.read_text().splitlines()
    if layout == "tabs":
        lines = [ln.replace(" ", "\t") for ln in lines]
    elif layout.endswith("indented"):
        lines = [f"  {ln}" if k % 2 else f"\t {ln}" for k, ln in enumerate(lines)]
    elif layout == "bom":
        lines = ["\ufeff" + lines[1], *lines[2:], lines[0]]           # the mark, a vertex, ..., mtllib last
    elif layout == "comments":
        notes = (" # note", "\t#tab", "#", " ## 1 2 3")
        lines = [f"{ln}{notes[k % 4]}" if ln.split()[0] in ("v", "vt", "f") else ln for k, ln in enumerate(lines)]
    end = "\r" if layout.startswith("cr") else "\n"
    path.write_bytes((end.join(lines) + end).encode())
    want = triangles(meshfile.load_mesh_file(plain).parts)
    assert len(want) == 2 * 9 * 9 + 1 and {t[3] for t in want} == {"tex", "plain"}
    assert triangles(meshfile.load_mesh_file(path).parts) == want
    monkeypatch.setattr(obj_lines, "READ_BYTES", 997)        # lines read in many blocks, cut between them
    assert triangles([part for piece in slabs_of(path, 31) for part in piece.parts]) == want


def test_a_nan_coordinate_in_slabs_is_refused_by_name_as_in_a_whole_read(tmp_path, slabs_of):
    """NaN marks a shorter line's missing values in the slab reader's table; a NaN the file writes
    must not pass as one (its vertex would lose a coordinate)."""
    from pipeline25d.formats import load_district

    path = write_obj(tmp_path, 6, colours=True)
    lines = path.read_text().splitlines()
    lines[1] = "v nan " + " ".join(lines[1].split()[2:])             # the second vertex's x
    path.write_text("\n".join(lines) + "\n")
    with pytest.raises(InputFileError, match=r"m\.obj.*NaN or infinite"):
        load_district({"path": str(path), "crs": "EPSG:28992"}, "EPSG:28992")
    with pytest.raises(InputFileError, match=r"m\.obj: has NaN or infinite coordinates"):
        slabs_of(path, 10)


@pytest.mark.parametrize("line, problem", [("f 1 2 x", "a face names a vertex by something other than a number"),
                                           ("v 1.0 two 3.0", "a 'v' line holds something other than numbers")])
def test_a_word_that_is_not_a_number_is_refused_naming_the_file(tmp_path, slabs_of, line, problem):
    """NumPy's parser stops at such a word with a bare ValueError (on 8b0c25c the slab reader's error)."""
    path = write_obj(tmp_path, 6, colours=True)
    path.write_text(path.read_text() + line + "\n")
    with pytest.raises(InputFileError, match=rf"m\.obj: {problem}"):
        slabs_of(path, 10)


def test_slab_texts_are_those_of_the_line_by_line_reader(tmp_path):
    """The slabs' OBJ texts, cut on the file's bytes at once (words, keywords, faces of one size
    formatted together), are the ones worked out by hand: tabs, CRLF, no last newline, negative
    indices, a quad, vertex colours on one line, a third texture coordinate on one, statements
    between faces."""
    rows = ["mtllib m.mtl", "v\t1.5 2 3", "v 4 5 6 0.5 0.5 0.5", "v 7 8 9", "v 1 1 1", "vt 0 0", "vt 1 0",
            "vt 1 1 0.5", "o a", "usemtl tex", "f 1/1 2/2 3/3\r", "f\t-4/-3 -3/-2 -2/-1 -1/-1", "s off", "g g1",
            "f 2/1 3/2 4/3", "o b", "f 1/3 2/2 3/1"]
    path = tmp_path / "q.obj"
    path.write_text("\n".join(rows))                                  # no newline at the end
    table = obj_slabs.VertexTable.read(path)
    assert table.v.take(np.arange(4))[:, :3].tolist() == [[1.5, 2, 3], [4, 5, 6], [7, 8, 9], [1, 1, 1]]
    assert np.isnan(table.v.take(np.array([0]))[0, 3:]).all()
    got = list(obj_slabs.slab_texts(path, table, slab_faces=2))
    # slab 1: the negative corners are vertices 1-4 and coordinates 1-3 (the last twice); slab 2 starts
    # with the statements in force (o a, usemtl tex) and those before its first face (s, g)
    assert got == [
        b"mtllib m.mtl\no a\nusemtl tex\nv 1.5 2.0 3.0\nv 4.0 5.0 6.0 0.5 0.5 0.5\nv 7.0 8.0 9.0\nv 1.0 1.0 1.0\n"
        b"vt 0.0 0.0\nvt 1.0 0.0\nvt 1.0 1.0 0.5\nf 1/1 2/2 3/3\nf 1/1 2/2 3/3 4/3\n",
        b"mtllib m.mtl\no a\nusemtl tex\ns off\ng g1\nv 1.5 2.0 3.0\nv 4.0 5.0 6.0 0.5 0.5 0.5\nv 7.0 8.0 9.0\n"
        b"v 1.0 1.0 1.0\nvt 0.0 0.0\nvt 1.0 0.0\nvt 1.0 1.0 0.5\nf 2/1 3/2 4/3\no b\nf 1/3 2/2 3/1\n"]
