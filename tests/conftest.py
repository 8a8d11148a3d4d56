"""Shared fixtures: paths, the shared datasets, and a GL context (skip without EGL)."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
import trimesh

from pipeline25d.mesh import MeshPart

REPO = Path(__file__).resolve().parents[1]
DATA = REPO.parent / "shared" / "data"


@pytest.fixture(scope="session")
def gl_ctx():
    from pipeline25d.errors import RenderError
    from pipeline25d.render import create_context

    try:
        ctx = create_context()
    except RenderError as exc:
        pytest.skip(str(exc))
    yield ctx
    ctx.release()


def box_part(lo, hi, rgba=(200, 60, 40, 255)) -> MeshPart:
    """An axis-aligned box (float64 corners) as a vertex-coloured part."""
    lo, hi = np.asarray(lo, float), np.asarray(hi, float)
    box = trimesh.creation.box(extents=hi - lo)
    verts = np.asarray(box.vertices) + (lo + hi) / 2
    return MeshPart(verts, np.asarray(box.faces), colors=np.tile(np.array(rgba, np.uint8), (len(verts), 1)))


def ground_part(x0, y0, x1, y1, z, rgba=(90, 140, 60, 255)) -> MeshPart:
    verts = np.array([[x0, y0, z], [x1, y0, z], [x1, y1, z], [x0, y1, z]], dtype=float)
    return MeshPart(verts, np.array([[0, 1, 2], [0, 2, 3]]), colors=np.tile(np.array(rgba, np.uint8), (4, 1)))
