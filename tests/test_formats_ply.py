"""The lean PLY reader against trimesh's, which it replaces for plain (untextured) PLY files."""

from __future__ import annotations

import numpy as np
import pytest
from conftest import DATA, shared_file

from pipeline25d.core.errors import InputFileError
from pipeline25d.formats.meshfile import load_mesh_file
from pipeline25d.formats.ply import load_ply

HEADER = """ply
format ascii 1.0
element vertex 5
property double x
property double y
property double z
property uchar red
property uchar green
property uchar blue
element face 2
property list uchar int vertex_indices
end_header
"""
VERTICES = """85000.5 445000.25 1.0 255 0 0
85010.5 445000.25 2.0 0 255 0
85010.5 445010.25 3.0 0 0 255
85000.5 445010.25 4.0 10 20 30
85005.0 445020.00 5.0 40 50 60
"""


def _canonical(faces):
    """Triangles in any order, each started at its lowest index with its winding kept."""
    start = np.argmin(faces, axis=1)
    rolled = np.stack([faces[np.arange(len(faces)), (start + k) % 3] for k in range(3)], axis=1)
    return np.unique(rolled, axis=0)


def _same(a, b):
    (pa,), (pb,) = a.parts, b.parts
    np.testing.assert_array_equal(pa.vertices, pb.vertices)
    np.testing.assert_array_equal(_canonical(pa.faces), _canonical(pb.faces))
    np.testing.assert_array_equal(pa.colors, pb.colors)


def test_polygons_become_the_same_triangles_and_colours_as_trimesh(tmp_path):
    path = tmp_path / "quad.ply"
    path.write_text(HEADER + VERTICES + "4 0 1 2 3\n3 3 2 4\n")
    mesh = load_ply(path)
    assert mesh.parts[0].faces.tolist() == [[0, 1, 2], [0, 2, 3], [3, 2, 4]]      # fan + triangle
    assert mesh.parts[0].colors[3].tolist() == [10, 20, 30, 255]
    assert mesh.parts[0].vertices[0].tolist() == [85000.5, 445000.25, 1.0]        # float64 as stored
    _same(mesh, load_mesh_file(path))


def test_a_real_binary_lidar_mesh_reads_as_trimesh_reads_it():
    path = DATA / "delft" / "delft_dsm_mesh.ply"
    shared_file(path)
    _same(load_ply(path), load_mesh_file(path))


def test_bad_indices_name_the_file(tmp_path):
    path = tmp_path / "bad.ply"
    path.write_text(HEADER + VERTICES + "3 0 1 9\n3 0 1 2\n")
    with pytest.raises(InputFileError, match=r"bad.ply.*out of range \(5 vertices\)"):
        load_ply(path)


def test_textured_ply_is_left_to_trimesh(tmp_path):
    path = tmp_path / "uv.ply"
    header = HEADER.replace("property uchar blue\n", "property uchar blue\nproperty float s\nproperty float t\n")
    rows = "".join(line + " 0.5 0.5\n" for line in VERTICES.splitlines())
    path.write_text(header + rows + "3 0 1 2\n3 0 2 3\n")
    _same(load_ply(path), load_mesh_file(path))


def _binary(path, faces, cut=0):
    """The HEADER's vertices as a little-endian binary PLY with ``faces`` (lists of any length),
    its last ``cut`` bytes left off."""
    import struct

    body = b"".join(struct.pack("<3d3B", *map(float, row.split()[:3]), *map(int, row.split()[3:]))
                    for row in VERTICES.splitlines())
    body += b"".join(struct.pack(f"<B{len(f)}i", len(f), *f) for f in faces)
    header = HEADER.replace("format ascii", "format binary_little_endian").replace("face 2", f"face {len(faces)}")
    path.write_bytes((header.encode() + body)[:len(header.encode() + body) - cut])
    return path


@pytest.mark.parametrize("faces", [[[0, 1, 2], [3, 2, 4]], [[0, 1, 2, 3], [3, 2, 4]], [[3, 2, 4], [0, 1, 2, 3]]])
def test_binary_faces_of_any_length_read_as_in_the_ascii_file(tmp_path, faces):
    """Triangles are memory-mapped in one piece; a polygon anywhere makes the reader go row by row."""
    ascii_path = tmp_path / "a.ply"
    ascii_path.write_text(HEADER.replace("face 2", f"face {len(faces)}") + VERTICES
                          + "".join(f"{len(f)} {' '.join(map(str, f))}\n" for f in faces))
    binary, text = load_ply(_binary(tmp_path / "b.ply", faces)).parts[0], load_ply(ascii_path).parts[0]
    np.testing.assert_array_equal(binary.faces, text.faces)
    np.testing.assert_array_equal(binary.vertices, text.vertices)
    np.testing.assert_array_equal(binary.colors, text.colors)
    expected = [[a, b, c] for f in faces for a, b, c in zip([f[0]] * (len(f) - 2), f[1:-1], f[2:])]
    assert binary.faces.tolist() == expected


def test_a_truncated_binary_file_is_named(tmp_path):
    with pytest.raises(InputFileError, match=r"cut.ply.*truncated"):
        load_ply(_binary(tmp_path / "cut.ply", [[0, 1, 2], [3, 2, 4]], cut=5))
