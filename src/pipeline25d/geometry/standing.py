"""Feet on roofs: which points of a model stand on its own surfaces rather than on the ground.

A city model of buildings alone has no terrain, and where its buildings stand is its ground
(:mod:`pipeline25d.stages.terrain.bases`; a building's own ground height for the heights'
reference, :mod:`pipeline25d.formats.cityjson_buildings`). A tower, a dormer or a chimney drawn
as a solid of its own, or a part whose floor lies on another part, stands on a roof: its feet
are no ground.
"""

from __future__ import annotations

import numpy as np

EDGE_M = 0.001            # a point this close to a surface's edge in plan stands over it


def standing(samples: np.ndarray, owner: np.ndarray, triangles: np.ndarray, tri_owner: np.ndarray,
             tol: float, facing_nz: float) -> np.ndarray:
    """(n,) bool: the samples (n, 3) of buildings ``owner`` that stand on the model rather than on the
    ground, among ``triangles`` (m, 3, 3) of buildings ``tri_owner``. A sample stands where, over it
    in plan (to :data:`EDGE_M`, edges included),

    * a surface lies more than ``tol`` below it (a roof or a floor under a foot), or
    * another building's top surface lies within ``tol`` of it while that building reaches more than
      ``tol`` lower (a foot on the roof of a building drawn without a floor).

    Only surfaces that face up or down are looked at (|normal z| above ``facing_nz``: a wall's plane,
    nearly vertical, says nothing of the height beside its foot). Float64; candidates by an R-tree
    of the surfaces' plan boxes."""
    from rtree.index import Index

    out = np.zeros(len(samples), bool)
    normal = np.cross(triangles[:, 1] - triangles[:, 0], triangles[:, 2] - triangles[:, 0])
    cross = normal[:, 2]                                                   # twice the signed plan area
    keep = np.abs(cross) > facing_nz * np.linalg.norm(normal, axis=1)
    if not keep.any() or not len(samples):
        return out
    lowest = np.full(tri_owner.max() + 1, np.inf)                          # each building's lowest point
    np.minimum.at(lowest, tri_owner, triangles[:, :, 2].min(axis=1))
    tri, cross, tri_owner = triangles[keep], cross[keep], tri_owner[keep]
    index = Index((np.arange(len(tri), dtype=np.int64), tri[:, :, :2].min(axis=1) - EDGE_M,
                   tri[:, :, :2].max(axis=1) + EDGE_M))
    ids, counts = index.intersection_v(samples[:, :2], samples[:, :2])
    which = np.repeat(np.arange(len(samples)), counts.astype(np.int64))
    t, p = tri[ids], samples[which]
    # barycentric coordinates in plan; b_k · |cross| / |edge opposite k| is the distance inside that edge
    d = p[:, :2] - t[:, 0, :2]
    u, v = t[:, 1, :2] - t[:, 0, :2], t[:, 2, :2] - t[:, 0, :2]
    b1 = (d[:, 0] * v[:, 1] - d[:, 1] * v[:, 0]) / cross[ids]
    b2 = (u[:, 0] * d[:, 1] - u[:, 1] * d[:, 0]) / cross[ids]
    b = np.c_[1.0 - b1 - b2, b1, b2]
    opposite = np.linalg.norm(np.roll(t[:, :, :2], -1, axis=1) - np.roll(t[:, :, :2], -2, axis=1), axis=2)
    over = (b * (np.abs(cross[ids])[:, None] / opposite) >= -EDGE_M).all(axis=1)
    b = np.clip(b[over], 0.0, None)                     # at an edge: the edge's height, not beyond it
    b /= b.sum(axis=1, keepdims=True)
    which, ids, z = which[over], ids[over], np.einsum("ij,ij->i", b, t[over][:, :, 2])
    out[which[z < samples[which, 2] - tol]] = True
    # another building's top over the sample: the highest of its surfaces there
    other = tri_owner[ids] != owner[which]
    buildings = np.int64(len(lowest))
    pair, inverse = np.unique(which[other] * buildings + tri_owner[ids][other], return_inverse=True)
    top = np.full(len(pair), -np.inf)
    np.maximum.at(top, inverse, z[other])
    sample, building = np.divmod(pair, buildings)
    height = samples[sample, 2]
    out[sample[(np.abs(top - height) <= tol) & (lowest[building] < height - tol)]] = True
    return out
