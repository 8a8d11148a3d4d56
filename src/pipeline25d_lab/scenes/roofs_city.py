"""Deterministic ROOFS city: steep textured terrain, flat, gabled and hipped roofs, walls tinted like
their roofs, with exact truth for building heights on sloped ground.

The scene on which the heights stage is tested where the demo city is too kind: its terrain,
ground texture, districts and building placement are those of :mod:`pipeline25d_lab.scenes.rugged`
(one pure terrain function, ≥ ``relief`` metres over the square), at a smaller size so that a
run over it stays short. What differs:

* roofs: ``flat`` (one height), ``gabled`` (ridge parallel to the footprint's long side, eave on
  the long sides) or ``hipped`` (ridge inset by half the short side at both ends: four slopes,
  one eave height all round); towers are flat;
* walls are the roof's colour darkened by FACADE_TINT (a colour distance of ~10/255 before
  shading): a roof's outline does not stand out from its walls by colour;
* truth per building (``truth.json``): ``roof`` (kind), ``roof_z`` (flat) or ``eave_z`` and
  ``ridge_z`` (pitched), ``ground_min``/``ground_max``/``own_ground_z`` (lowest, highest and mean
  exact terrain under the footprint; ``own_ground_z`` on the heights stage's 0.25 m grid), and
  ``visible`` {perspective id: share of the roof seen from that view}: roof points ray-marched
  towards the camera against the exact terrain and every other building (:func:`roof_visibility`).

Files and regeneration as the rugged city's (``manifest.json`` last; same parameters: nothing
written).
"""

from __future__ import annotations

import argparse
import logging
import math
import sys
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from pipeline25d.core.atomic import write_bytes
from pipeline25d.geometry.camera import horizontal_direction
from pipeline25d.geometry.perspectives import Perspective
from pipeline25d_lab.scenes.demo import CRS, own_ground_z, run_generator
from pipeline25d_lab.scenes.rugged import (
    ROOF_CLASSES,
    Box,
    _check_args,
    _existing_manifest,
    _ground_piece,
    _json_bytes,
    make_districts,
    obj_text,
    place_buildings,
    rugged_height,
    terrain_params,
    write_dtm,
)
from pipeline25d_lab.scenes.writer import Group, mtl_block

log = logging.getLogger(__name__)

FACADE_TINT = 0.92            # wall colour = roof colour × this
PITCHED_SHARE = (0.35, 0.30)  # shares of gabled and hipped roofs among the non-towers (rest flat)
RISE = (2.0, 5.0)             # ridge above eave (m)
VIEWS = ("az045_el45", "az200_el30")  # perspectives whose roof visibility truth.json records
VISIBLE_STEP = 1.0            # ray-march step (m, horizontal) of the visibility truth
GENERATOR_VERSION = 1


@dataclass
class RoofedBox:
    """A rugged-city box with its roof: ``eave_z`` (= the box's roof_z), ``ridge_z``, ``kind``."""

    box: Box
    kind: str
    ridge_z: float

    @property
    def eave_z(self) -> float:
        return self.box.roof_z


def assign_roofs(boxes: list[Box], seed: int) -> list[RoofedBox]:
    """Seeded roof kinds (towers flat) and ridge heights RISE above the eave, mm-rounded."""
    rng = np.random.default_rng([seed, 7])
    out = []
    for b in boxes:
        r, rise = rng.uniform(), rng.uniform(*RISE)
        kind = ("flat" if b.tower else "gabled" if r < PITCHED_SHARE[0]
                else "hipped" if r < sum(PITCHED_SHARE) else "flat")
        out.append(RoofedBox(b, kind, b.roof_z if kind == "flat" else round(b.roof_z + rise, 3)))
    return out


def ridge_line(rb: RoofedBox) -> tuple[np.ndarray, np.ndarray]:
    """Ends (x, y) of the ridge: parallel to edge 0→1 (the long side), inset at both ends when hipped."""
    p = rb.box.corners
    a, b = (p[0] + p[3]) / 2, (p[1] + p[2]) / 2
    if rb.kind == "hipped":
        half = float(np.linalg.norm(p[3] - p[0])) / 2
        e = (b - a) / float(np.linalg.norm(b - a))
        a, b = a + half * e, b - half * e
    return a, b


def roof_pieces(rb: RoofedBox) -> tuple[tuple[np.ndarray, np.ndarray], tuple[np.ndarray, np.ndarray]]:
    """(wall vertices, faces), (roof vertices, faces) of a building; faces point outward."""
    b, p = rb.box, rb.box.corners
    ra, rbb = ridge_line(rb)
    walls_v: list[list[list[float]]] = []
    walls_f: list[list[int]] = []
    for e in range(4):
        a, c = p[e], p[(e + 1) % 4]
        n0 = sum(len(w) for w in walls_v)
        quad = [[*a, b.bottom_z], [*c, b.bottom_z], [*c, b.roof_z], [*a, b.roof_z]]
        faces = [[n0, n0 + 1, n0 + 2], [n0, n0 + 2, n0 + 3]]
        if rb.kind == "gabled" and e in (1, 3):       # gable triangle up to the ridge
            quad.append([*(rbb if e == 1 else ra), rb.ridge_z])
            faces.append([n0 + 3, n0 + 2, n0 + 4])
        walls_v.append(quad)
        walls_f += faces
    eave = np.column_stack([p, np.full(4, b.roof_z)])
    if rb.kind == "flat":
        roof_v, roof_f = eave, np.array([[0, 1, 2], [0, 2, 3]])
    else:
        roof_v = np.vstack([eave, [[*ra, rb.ridge_z], [*rbb, rb.ridge_z]]])
        roof_f = np.array([[0, 1, 5], [0, 5, 4], [2, 3, 4], [2, 4, 5]])
        if rb.kind == "hipped":
            roof_f = np.vstack([roof_f, [[1, 2, 5], [3, 0, 4]]])
    return (np.vstack(walls_v), np.array(walls_f)), (roof_v, roof_f)


def roof_z_at(rb: RoofedBox, x: np.ndarray, y: np.ndarray) -> np.ndarray:
    """Height of the roof surface at plan points (x, y) inside the footprint (NaN outside)."""
    from pipeline25d.formats.footprints import Footprint, contains

    p = rb.box.corners
    inside = contains(Footprint("", (p,)), x, y)
    if rb.kind == "flat":
        return np.where(inside, rb.eave_z, np.nan)
    ra, rbb = ridge_line(rb)
    e = (p[1] - p[0]) / float(np.linalg.norm(p[1] - p[0]))
    n = np.array([-e[1], e[0]])
    half = float(np.linalg.norm(p[3] - p[0])) / 2
    q = np.column_stack([x, y]) - (ra + rbb) / 2
    across = np.abs(q @ n)                     # distance from the ridge's line
    dist = across
    if rb.kind == "hipped":
        along = np.abs(q @ e) - float(np.linalg.norm(rbb - ra)) / 2
        dist = np.maximum(across, along)       # hips: the nearer eave decides
    z = rb.ridge_z - (rb.ridge_z - rb.eave_z) * np.clip(dist / half, 0.0, 1.0)
    return np.where(inside, z, np.nan)


def roof_visibility(buildings: list[RoofedBox], params: dict[str, Any], pid: str, spacing: float = 1.0,
                    zmax: float | None = None) -> dict[str, float]:
    """{building id: share of its roof points (``spacing`` grid, 1 m in from the outline) from which
    the ray towards perspective ``pid``'s camera passes over the exact terrain and every other
    building}. Each ray is marched every VISIBLE_STEP m horizontally until it is above ``zmax``
    (default: highest roof + the terrain's range)."""
    from pipeline25d.formats.footprints import Footprint, inside_points

    p = Perspective.from_id(pid)
    d = -np.asarray(horizontal_direction(p), dtype=np.float64)   # towards the camera
    rise = math.tan(math.radians(p.elevation))
    tops = np.array([b.ridge_z for b in buildings])
    lo = np.array([b.box.corners.min(axis=0) for b in buildings])
    hi = np.array([b.box.corners.max(axis=0) for b in buildings])
    top = float(tops.max()) if zmax is None else zmax
    out: dict[str, float] = {}
    for b in buildings:
        pts = inside_points(Footprint(b.box.id, (b.box.corners,)), spacing, margin=1.0)
        if not len(pts):
            pts = b.box.corners.mean(axis=0)[None]
        z0 = roof_z_at(b, pts[:, 0], pts[:, 1]) + 0.05
        ok = np.isfinite(z0)
        n_steps = int(math.ceil((top - float(np.nanmin(z0))) / rise / VISIBLE_STEP)) + 1
        # candidate occluders: boxes the rays' plan sweep can reach, higher than the roof
        reach = n_steps * VISIBLE_STEP
        sweep_lo = np.minimum(pts.min(axis=0), pts.min(axis=0) + reach * d)
        sweep_hi = np.maximum(pts.max(axis=0), pts.max(axis=0) + reach * d)
        near = [o for o, ol, oh in zip(buildings, lo, hi) if o is not b and np.all(ol <= sweep_hi)
                and np.all(oh >= sweep_lo) and o.ridge_z > float(np.nanmin(z0))]
        for k in range(1, n_steps + 1):
            if not ok.any():
                break
            t = k * VISIBLE_STEP
            x, y, z = pts[:, 0] + t * d[0], pts[:, 1] + t * d[1], z0 + t * rise
            ok &= rugged_height(x, y, params) < z
            for o in near:
                zo = roof_z_at(o, x, y)
                ok &= ~(np.isfinite(zo) & (zo >= z))
        out[b.box.id] = round(float(np.mean(ok)), 4)
    return out


def mtl_text(name: str, ground_tiles: Sequence[str]) -> str:
    """MTL of one district: its ground tiles (map_Kd PNG), roof colours and their tinted walls."""
    parts = [f"# pipeline25d roofs city materials, district {name}\n"]
    parts += [mtl_block(t, (1.0, 1.0, 1.0), f"{t}.png") for t in ground_tiles]
    parts += [mtl_block(f"roof_{c}", rgb) for c, rgb in ROOF_CLASSES.items()]
    parts += [mtl_block(f"wall_{c}", tuple(FACADE_TINT * v for v in rgb)) for c, rgb in ROOF_CLASSES.items()]
    return "\n".join(parts)


def building_truth(rb: RoofedBox, params: dict[str, Any], visible: dict[str, dict[str, float]]) -> dict[str, Any]:
    """One building of truth.json (see the module docstring)."""
    b = rb.box
    roof = {"roof_z": b.roof_z} if rb.kind == "flat" else {"eave_z": b.roof_z, "ridge_z": rb.ridge_z}
    return {"id": b.id, "district": b.district, "footprint": b.corners.tolist(), "roof": rb.kind, **roof,
            "ground_min": b.ground_min, "ground_max": b.ground_max, "bottom_z": b.bottom_z,
            "own_ground_z": own_ground_z(b.corners, lambda x, y: rugged_height(x, y, params)),
            "tower": b.tower, "roof_material": f"roof_{b.roof_class}", "wall_material": f"wall_{b.roof_class}",
            "visible": {pid: v[b.id] for pid, v in visible.items()}}


def generate_roofs_city(out_dir: Path, seed: int = 5, size: float = 800.0, relief: float = 500.0,
                        n_buildings: int = 120, spacing: float = 5.0, views: Sequence[str] = VIEWS,
                        *, progress: Callable[[str], None] | None = None) -> dict:
    """Write the roofs city (one district ``h0``) into ``out_dir`` and return its manifest.

    Files: h0.obj/.mtl, ground_*.png, dtm.tif (exact terrain, 1 m; truth only), truth.json,
    manifest.json (last). When ``out_dir`` already holds this scene nothing is written.
    """
    _check_args(seed, size, relief, n_buildings, spacing, (1, 1))
    seed, n_buildings, size, relief, spacing = int(seed), int(n_buildings), float(size), float(relief), float(spacing)
    out_dir = Path(out_dir)
    key = {"kind": "roofs", "seed": seed, "size": size, "relief": relief, "n_buildings": n_buildings,
           "spacing": spacing, "views": list(views), "version": GENERATOR_VERSION}
    existing = _existing_manifest(out_dir, key)
    if existing is not None:
        log.info("roofs city in %s is up to date", out_dir)
        return existing
    out_dir.mkdir(parents=True, exist_ok=True)
    (out_dir / "manifest.json").unlink(missing_ok=True)

    params = terrain_params(seed, size, relief, spacing)
    n = int(round(size / spacing))
    xs = np.round(params["origin"][0] + np.arange(n + 1) * spacing, 3)
    ys = np.round(params["origin"][1] + np.arange(n + 1) * spacing, 3)
    z = rugged_height(xs[None, :], ys[:, None], params)
    relief_m = float(z.max() - z.min())
    (district,) = make_districts(size, spacing, (1, 1))
    district.name = "h0"
    buildings = assign_roofs(place_buildings(seed, n_buildings, size, params, [district], spacing), seed)
    groups: dict[str, Group] = {t.name: Group() for t in district.tiles}
    groups |= {f"roof_{c}": Group() for c in ROOF_CLASSES} | {f"wall_{c}": Group() for c in ROOF_CLASSES}
    uv_sets: dict[str, tuple[tuple, np.ndarray]] = {}
    files: list[str] = []
    for t in district.tiles:
        vertices, faces, rgb, uv, png = _ground_piece(t, xs, ys, params, seed)
        groups[t.name].add(vertices, faces, rgb)
        uv_sets[t.name] = ((t.i1 - t.i0, t.j1 - t.j0, t.width, t.height), uv)
        write_bytes(out_dir / f"{t.name}.png", png)
        files.append(f"{t.name}.png")
    for rb in buildings:
        (wv, wf), (rv, rf) = roof_pieces(rb)
        rgb = ROOF_CLASSES[rb.box.roof_class]
        groups[f"wall_{rb.box.roof_class}"].add(wv, wf, tuple(FACADE_TINT * v for v in rgb))
        groups[f"roof_{rb.box.roof_class}"].add(rv, rf, rgb)
    text, n_tri = obj_text(district.name, groups, uv_sets)
    write_bytes(out_dir / "h0.mtl", mtl_text("h0", [t.name for t in district.tiles]).encode("ascii"))
    write_bytes(out_dir / "h0.obj", text.encode("ascii"))
    files += ["h0.mtl", "h0.obj"]
    if progress is not None:
        progress(f"roofs city: {len(buildings)} buildings, {n_tri} triangles")
    visible = {pid: roof_visibility(buildings, params, pid) for pid in views}
    write_dtm(out_dir / "dtm.tif", size, params)
    truth = {"crs": CRS, "seed": seed, "size": size, "relief": relief, "spacing": spacing,
             "terrain": {"function": "pipeline25d_lab.scenes.rugged.rugged_height", "params": params,
                         "grid_min": float(z.min()), "grid_max": float(z.max()), "grid_relief": relief_m},
             "districts": {"h0": {"obj": "h0.obj"}},
             "facade_tint": FACADE_TINT, "views": list(views),
             "buildings": [building_truth(rb, params, visible) for rb in buildings]}
    write_bytes(out_dir / "truth.json", _json_bytes(truth))
    files += ["dtm.tif", "truth.json"]
    manifest = {**key, "crs": CRS, "districts": {"h0": "h0.obj"}, "dtm": "dtm.tif", "truth": "truth.json",
                "n_triangles": n_tri, "relief_m": relief_m, "files": files,
                "roofs": {k: sum(rb.kind == k for rb in buildings) for k in ("flat", "gabled", "hipped")}}
    write_bytes(out_dir / "manifest.json", _json_bytes(manifest))
    return manifest


def main(argv: list[str] | None = None, prog: str | None = None) -> int:
    """CLI: ``python -m pipeline25d_lab.scenes.roofs_city OUT [--seed --size --relief --buildings]``."""
    parser = argparse.ArgumentParser(prog=prog, description="Generate the roofs test city.")
    parser.add_argument("out_dir", type=Path, help="output folder (created if missing)")
    parser.add_argument("--seed", type=int, default=5, help="random seed (default 5)")
    parser.add_argument("--size", type=float, default=800.0, help="scene edge in metres (default 800)")
    parser.add_argument("--relief", type=float, default=500.0, help="least terrain range in metres (default 500)")
    parser.add_argument("--buildings", type=int, default=120, help="number of buildings (default 120)")
    args = parser.parse_args(argv)
    return run_generator(
        lambda progress: generate_roofs_city(args.out_dir, args.seed, args.size, args.relief, args.buildings,
                                             progress=progress),
        lambda m: f"roofs city: {m['n_buildings']} buildings {m['roofs']}, {m['n_triangles']} triangles, "
                  f"relief {m['relief_m']:.1f} m in {args.out_dir}")


if __name__ == "__main__":
    sys.exit(main())
