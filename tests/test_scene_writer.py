"""The generators' shared OBJ writer: vertices, colours, uv sharing and face indices read back."""

import numpy as np

from pipeline25d_lab.scenes.writer import Group, mtl_block, obj_text


def _parse(text: str):
    v, vt, faces = [], [], {}
    material = None
    for line in text.splitlines():
        head, *rest = line.split()
        if head == "v":
            v.append([float(x) for x in rest])
        elif head == "vt":
            vt.append([float(x) for x in rest])
        elif head == "usemtl":
            material = rest[0]
        elif head == "f":
            faces.setdefault(material, []).append([[int(i) for i in c.split("/")] for c in rest])
    return np.array(v), np.array(vt), faces


def test_shared_uv_block_and_face_indices_point_at_the_right_vertices():
    square = np.array([[0, 0, 0], [1, 0, 0], [1, 1, 0], [0, 1, 0]], float)
    uv = np.array([[0, 0], [1, 0], [1, 1], [0, 1]], float)
    tris = [[0, 1, 2], [0, 2, 3]]
    groups = {"a": Group(), "plain": Group(), "b": Group(), "empty": Group()}
    groups["a"].add(square + [10, 0, 5], tris, (1, 0, 0))
    groups["plain"].add(square + [0, 10, 7], tris, (0, 1, 0))
    groups["b"].add(square + [20, 0, 9], tris, (0, 0, 1))
    text, n_tri = obj_text("# test", "x", groups, {"a": ("k", uv), "b": ("k", uv)}, ("%r", "%r"))
    v, vt, faces = _parse(text)
    assert n_tri == 6 and set(faces) == {"a", "plain", "b"}          # the empty group is left out
    assert len(v) == 12 and len(vt) == 4                             # "a" and "b" share one vt block
    for material, (offset, rgb) in {"a": ([10, 0, 5], (1, 0, 0)), "plain": ([0, 10, 7], (0, 1, 0)),
                                    "b": ([20, 0, 9], (0, 0, 1))}.items():
        idx = np.array(faces[material])
        corners = v[idx[..., 0] - 1]
        np.testing.assert_array_equal(corners[..., :3], (square + offset)[np.array(tris)])
        np.testing.assert_array_equal(corners[..., 3:], np.broadcast_to(rgb, corners[..., 3:].shape))
        if material != "plain":
            np.testing.assert_array_equal(vt[idx[..., 1] - 1], uv[np.array(tris)])
        else:
            assert idx.shape[-1] == 1


def test_mtl_block_names_colour_and_texture():
    assert mtl_block("roof", (0.5, 0.25, 1)).splitlines()[2] == "Kd 0.500 0.250 1.000"
    assert mtl_block("wall", (1, 1, 1), "wall.png").splitlines()[-1] == "map_Kd wall.png"
