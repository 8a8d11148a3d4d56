"""Building heights from the maps: synthetic maps with exactly known heights, footprints, OBJ references, CLI."""

from __future__ import annotations

import csv
import json
import math

import numpy as np
import pytest

from pipeline25d.analysis.heights.cli import main
from pipeline25d.analysis.heights.reference import reference_heights_from_obj
from pipeline25d.analysis.heights.views import measure_heights
from pipeline25d.core.errors import CRSError, InputFileError
from pipeline25d.core.geotiff import write_rgba_geotiff
from pipeline25d.core.grid import Grid, Window
from pipeline25d.formats.footprints import rasterize, read_footprints

GSD = 0.25
X0, Y0 = 85000.0, 447600.0            # RD New, top-left corner of the nadir map
SIZE_M = 64.0                         # nadir map: 64 m x 64 m
SS = 6                                # supersamples per pixel edge (box-filtered anti-aliasing)
LIGHT = np.array([-0.8, -0.6])        # horizontal direction towards the light (wall shading)
VIEWS = [(45, 45), (165, 30), (285, 60)]


def _wkt(epsg: int = 28992) -> str:
    from osgeo import osr

    srs = osr.SpatialReference()
    srs.ImportFromEPSG(epsg)
    return srs.ExportToWkt()


def rect(cx: float, cy: float, w: float, h: float, rot_deg: float) -> np.ndarray:
    """(4, 2) corners of a w×h rectangle centred at local (cx, cy) metres, rotated, in map coordinates."""
    t = math.radians(rot_deg)
    rot = np.array([[math.cos(t), -math.sin(t)], [math.sin(t), math.cos(t)]])
    corners = np.array([[-w / 2, -h / 2], [w / 2, -h / 2], [w / 2, h / 2], [-w / 2, h / 2]]) @ rot.T
    return corners + [X0 + cx, Y0 - SIZE_M + cy]


# id: (rings, height above ground m, roof RGB). Local coordinates: x east, y north from the map's SW corner.
_A = rect(14.0, 50.0, 10.0, 7.0, 17.0)
_B_SHARED = np.array([_A[1], _A[2]])                  # B shares A's east edge: same colour, other height
_edge = _B_SHARED[1] - _B_SHARED[0]
_out = np.array([_edge[1], -_edge[0]]) / np.linalg.norm(_edge) * 6.0
BUILDINGS: dict[str, tuple[list[np.ndarray], float, tuple[int, int, int]]] = {
    "A": ([_A], 6.37, (205, 70, 60)),
    "B": ([np.array([_B_SHARED[0], _B_SHARED[0] + _out, _B_SHARED[1] + _out, _B_SHARED[1]])], 9.83, (205, 70, 60)),
    "court": ([rect(46.0, 50.0, 15.0, 13.0, 8.0), rect(46.5, 50.0, 6.0, 5.0, 8.0)], 11.21, (60, 90, 200)),
    "multi": ([rect(14.0, 24.0, 8.0, 5.0, -23.0), rect(21.0, 16.0, 5.0, 4.0, -23.0)], 4.44, (230, 200, 60)),
    "tall": ([rect(34.0, 13.0, 9.0, 9.0, 31.0)], 14.62, (90, 160, 110)),
    "hidden": ([rect(34.0 + 7.0, 13.0 + 7.0, 2.5, 2.5, 31.0)], 2.91, (170, 90, 170)),   # behind "tall" at az 45
    "nodata": ([rect(55.0, 9.0, 6.0, 5.0, -12.0)], 7.77, (205, 70, 60)),   # roof under alpha 0 at az 285
    "tiny": ([rect(5.0, 5.0, 0.6, 0.6, 0.0)], 3.0, (60, 90, 200)),
}


def ground_colour(x: np.ndarray, y: np.ndarray) -> np.ndarray:
    """Smooth analytic ground texture (RGB float) at map coordinates."""
    u, v = x - X0, y - Y0
    g = (120 + 22 * np.sin(0.9 * u + 0.4 * v) + 18 * np.sin(0.31 * u - 1.3 * v + 1.0)
         + 12 * np.sin(2.1 * u + 1.7 * v + 2.0))
    return np.stack([0.85 * g + 25, 0.95 * g + 15, 0.7 * g + 30], axis=-1)


def _inside(px: np.ndarray, py: np.ndarray, rings: list[np.ndarray]) -> np.ndarray:
    out = np.zeros(px.shape, bool)
    for ring in rings:
        for a, b in zip(ring, np.roll(ring, -1, axis=0)):
            with np.errstate(divide="ignore", invalid="ignore"):
                cross = ((a[1] > py) != (b[1] > py)) & (px < (b[0] - a[0]) * (py - a[1]) / (b[1] - a[1]) + a[0])
            out ^= cross
    return out


def render(azimuth: float, elevation: float, extent: tuple[float, float, float, float]) -> np.ndarray:
    """(h, w, 4) uint8 map of the scene by exact ray casting, SS×SS box-filtered samples per pixel.

    A point h metres above the ground appears at its ground position + h·cot φ·d (terrain-relative
    projection over flat ground); the visible surface along a map point's ray is the highest one.
    """
    xmin, ymin, xmax, ymax = extent
    w, h = round((xmax - xmin) / GSD), round((ymax - ymin) / GSD)
    offs = (np.arange(SS) + 0.5) / SS
    xs = xmin + (np.repeat(np.arange(w), SS) + np.tile(offs, w)) * GSD
    ys = ymax - (np.repeat(np.arange(h), SS) + np.tile(offs, h)) * GSD
    X, Y = np.meshgrid(xs, ys)
    col = ground_colour(X, Y)
    top = np.zeros(X.shape)
    cot = 0.0 if elevation == 90 else 1 / math.tan(math.radians(elevation))
    d = np.array([math.sin(math.radians(azimuth)), math.cos(math.radians(azimuth))])
    for rings, height, roof in BUILDINGS.values():
        U = height * cot
        pts = np.concatenate(rings)
        lo = np.minimum(pts.min(0), pts.min(0) + U * d) - GSD
        hi = np.maximum(pts.max(0), pts.max(0) + U * d) + GSD
        c0, c1 = np.searchsorted(xs, [lo[0], hi[0]])
        r0, r1 = np.searchsorted(-ys, [-hi[1], -lo[1]])
        if c1 <= c0 or r1 <= r0:
            continue
        px, py = X[r0:r1, c0:c1], Y[r0:r1, c0:c1]
        is_roof = _inside(px - U * d[0], py - U * d[1], rings)
        hit = np.where(is_roof, height, -np.inf)
        colour = np.broadcast_to(np.array(roof, float), px.shape + (3,)).copy()
        if U > 0:
            best_u = np.full(px.shape, -np.inf)
            for ring in rings:
                for a, b in zip(ring, np.roll(ring, -1, axis=0)):
                    e = b - a
                    den = d[0] * e[1] - d[1] * e[0]            # d × e
                    if abs(den) < 1e-12:
                        continue
                    mx, my = px - a[0], py - a[1]
                    u = (mx * e[1] - my * e[0]) / den          # (m − a) × e / (d × e)
                    lam = (my * d[0] - mx * d[1]) / den        # (m − a) × d / (e × d)
                    ok = (lam >= 0) & (lam < 1) & (u >= 0) & (u < U) & (u > best_u) & ~is_roof
                    n = np.array([e[1], -e[0]]) / np.linalg.norm(e)
                    if n @ d > 0:
                        n = -n
                    shade = 0.45 + 0.55 * max(float(n @ LIGHT), 0.0)
                    best_u[ok] = u[ok]
                    colour[ok] = np.array([215.0, 210.0, 200.0]) * shade
            hit = np.where(~is_roof & np.isfinite(best_u), best_u / cot, hit)
        better = hit > top[r0:r1, c0:c1]
        top[r0:r1, c0:c1][better] = hit[better]
        col[r0:r1, c0:c1][better] = colour[better]
    img = col.reshape(h, SS, w, SS, 3).mean(axis=(1, 3))
    rgb = np.clip(np.round(img), 0, 255).astype(np.uint8)
    return np.dstack([rgb, np.full((h, w), 255, np.uint8)])


def oblique_extent(azimuth: float, elevation: float, frac: float = 0.0) -> tuple[float, float, float, float]:
    """Nadir extent grown to hold every displaced roof, on the gsd grid shifted by ``frac`` px."""
    cot = 1 / math.tan(math.radians(elevation))
    d = np.array([math.sin(math.radians(azimuth)), math.cos(math.radians(azimuth))]) * cot * 16.0
    xmin, ymin = X0 + min(0.0, d[0]) - 2, Y0 - SIZE_M + min(0.0, d[1]) - 2
    xmax, ymax = X0 + SIZE_M + max(0.0, d[0]) + 2, Y0 + max(0.0, d[1]) + 2
    snap = lambda v: math.floor(v / GSD) * GSD + frac * GSD  # noqa: E731
    return snap(xmin), snap(ymin), snap(xmax) + GSD, snap(ymax) + GSD


@pytest.fixture(scope="module")
def scene(tmp_path_factory) -> dict:
    """Nadir + three oblique maps (one with a sub-pixel origin offset, one with a no-data patch) and a GPKG."""
    root = tmp_path_factory.mktemp("heights")
    wkt = _wkt()
    maps = {}
    ext = (X0, Y0 - SIZE_M, X0 + SIZE_M, Y0)
    rgba = render(0, 90, ext)
    maps["az000_el90"] = root / "az000_el90.tif"
    write_rgba_geotiff(maps["az000_el90"], rgba, Grid.north_up(ext[0], ext[3], GSD, rgba.shape[1], rgba.shape[0]), wkt)
    for az, el in VIEWS:
        ext = oblique_extent(az, el, frac=0.3 if az == 165 else 0.0)
        rgba = render(az, el, ext)
        if az == 285:        # no data over the "nodata" building's displaced roof
            cot = 1 / math.tan(math.radians(el))
            c = rect(55.0, 9.0, 6.0, 5.0, -12.0).mean(0) + 7.77 * cot * np.array(
                [math.sin(math.radians(az)), math.cos(math.radians(az))])
            col, row = int((c[0] - ext[0]) / GSD), int((ext[3] - c[1]) / GSD)
            rgba[row - 20:row + 20, col - 20:col + 20, 3] = 0
        pid = f"az{az:03d}_el{el:02d}"
        maps[pid] = root / f"{pid}.tif"
        write_rgba_geotiff(maps[pid], rgba, Grid.north_up(ext[0], ext[3], GSD, rgba.shape[1], rgba.shape[0]), wkt)
    gpkg = root / "footprints.gpkg"
    write_gpkg(gpkg, {k: v[0] for k, v in BUILDINGS.items()}, 28992)
    return {"root": root, "maps": maps, "gpkg": gpkg}


def write_gpkg(path, polys: dict[str, list[np.ndarray]], epsg: int, layer: str = "buildings",
               multi: bool = True) -> None:
    """Write {id: rings} as (multi)polygons with an ``ident`` field; rings inside the first are holes."""
    from osgeo import ogr, osr

    ogr.UseExceptions()
    drv = ogr.GetDriverByName("GPKG")
    ds = drv.CreateDataSource(str(path)) if not path.exists() else ogr.Open(str(path), 1)
    srs = osr.SpatialReference()
    srs.ImportFromEPSG(epsg)
    srs.SetAxisMappingStrategy(osr.OAMS_TRADITIONAL_GIS_ORDER)
    lyr = ds.CreateLayer(layer, srs, ogr.wkbMultiPolygon if multi else ogr.wkbPolygon)
    lyr.CreateField(ogr.FieldDefn("ident", ogr.OFTString))
    for fid, rings in polys.items():
        geom = ogr.Geometry(ogr.wkbMultiPolygon)
        poly = None
        for ring in rings:
            inside = poly is not None and _inside(np.array([ring[:, 0].mean()]), np.array([ring[:, 1].mean()]),
                                                  [rings[0]])[0]
            if poly is None or not inside:
                if poly is not None:
                    geom.AddGeometry(poly)
                poly = ogr.Geometry(ogr.wkbPolygon)
            lr = ogr.Geometry(ogr.wkbLinearRing)
            for x, y in np.vstack([ring, ring[:1]]):
                lr.AddPoint_2D(float(x), float(y))
            poly.AddGeometry(lr)
        geom.AddGeometry(poly)
        feat = ogr.Feature(lyr.GetLayerDefn())
        feat.SetField("ident", fid)
        feat.SetGeometry(geom if multi else geom.GetGeometryRef(0))
        lyr.CreateFeature(feat)
    ds = None


# --------------------------------------------------------------------------- heights on synthetic maps

@pytest.fixture(scope="module")
def measured(scene) -> dict:
    fps = read_footprints(scene["gpkg"], id_field="ident")
    rows = measure_heights({k: str(v) for k, v in scene["maps"].items()}, fps)
    return {r.id: r for r in rows}


VISIBLE = {  # (building, view) pairs designed not to be measurable
    ("hidden", "az045_el45"): False, ("nodata", "az285_el60"): False,
}


@pytest.mark.parametrize("bid", ["A", "B", "court", "multi", "tall", "hidden", "nodata"])
def test_heights_per_view_subpixel(measured, bid):
    truth = BUILDINGS[bid][1]
    row = measured[bid]
    for az, el in VIEWS:
        pid = f"az{az:03d}_el{el:02d}"
        if not VISIBLE.get((bid, pid), True):
            assert math.isnan(row.heights[pid]), (bid, pid, row.views[pid])
            continue
        assert row.heights[pid] == pytest.approx(truth, abs=0.1), (bid, pid, row.views[pid])
    assert row.height == pytest.approx(truth, abs=0.1)
    assert row.n_views == row.n_agree == sum(VISIBLE.get((bid, f"az{a:03d}_el{e:02d}"), True) for a, e in VIEWS)


def test_not_measured(measured):
    hidden, nodata, tiny = measured["hidden"], measured["nodata"], measured["tiny"]
    assert math.isnan(hidden.heights["az045_el45"]) and hidden.reasons["az045_el45"]
    assert math.isnan(nodata.heights["az285_el60"]) and nodata.reasons["az285_el60"]
    assert all(math.isnan(h) for h in tiny.heights.values()) and math.isnan(tiny.height) and tiny.n_views == 0
    assert set(tiny.reasons.values()) == {"too_small"}


def test_shared_colour_neighbours_and_holes_rasterize(scene):
    fps = {f.id: f for f in read_footprints(scene["gpkg"], id_field="ident")}
    assert len(fps["court"].rings) == 2 and len(fps["multi"].rings) == 2
    mask = rasterize(fps["court"], Grid.north_up(X0, Y0, GSD, 256, 256), Window(0, 0, 256, 256))
    hole = rect(46.5, 50.0, 6.0, 5.0, 8.0).mean(0)
    col, row = int((hole[0] - X0) / GSD), int((Y0 - hole[1]) / GSD)
    assert not mask[row, col] and mask[row, col + 18]
    assert mask.sum() * GSD ** 2 == pytest.approx(15 * 13 - 6 * 5, rel=0.02)


# --------------------------------------------------------------------------- footprints

def _to_wgs84(rings: list[np.ndarray]) -> list[np.ndarray]:
    from osgeo import osr

    src, dst = osr.SpatialReference(), osr.SpatialReference()
    src.ImportFromEPSG(28992)
    dst.ImportFromEPSG(4326)
    for s in (src, dst):
        s.SetAxisMappingStrategy(osr.OAMS_TRADITIONAL_GIS_ORDER)
    tr = osr.CoordinateTransformation(src, dst)
    return [np.array([tr.TransformPoint(float(x), float(y))[:2] for x, y in ring]) for ring in rings]


def test_read_footprints_reprojected_and_fid(tmp_path):
    polys = {k: BUILDINGS[k][0] for k in ("court", "multi", "A")}
    path = tmp_path / "wgs84.gpkg"
    write_gpkg(path, {k: _to_wgs84(v) for k, v in polys.items()}, 4326, multi=False, layer="first")
    write_gpkg(path, {k: _to_wgs84(v) for k, v in polys.items()}, 4326, layer="second")
    fps = read_footprints(path, layer="second", id_field="ident", crs=_wkt())
    assert [f.id for f in fps] == ["court", "multi", "A"]
    for f in fps:
        for got, want in zip(f.rings, polys[f.id]):
            assert got.dtype == np.float64 and np.abs(got - want).max() < 1e-3      # metres, RD New again
    raw = read_footprints(path, layer="second", id_field="ident")                   # no crs: the layer's own
    assert abs(raw[0].rings[0][0, 0] - 4.36) < 0.1 and abs(raw[0].rings[0][0, 1] - 52.0) < 0.1
    first = read_footprints(path)                      # first polygon layer, single polygons, ids = feature ids
    assert [f.id for f in first] == ["1", "2", "3"] and len(first[0].rings) == 2 and len(first[1].rings) == 1


def test_footprint_errors_name_the_file(tmp_path):
    from osgeo import ogr

    with pytest.raises(InputFileError, match="nothere.gpkg"):
        read_footprints(tmp_path / "nothere.gpkg")
    bad = tmp_path / "bad.gpkg"
    bad.write_text("not a geopackage")
    with pytest.raises(InputFileError, match="bad.gpkg"):
        read_footprints(bad)
    pts = tmp_path / "points.gpkg"
    ds = ogr.GetDriverByName("GPKG").CreateDataSource(str(pts))
    lyr = ds.CreateLayer("pts", None, ogr.wkbPoint)
    feat = ogr.Feature(lyr.GetLayerDefn())
    feat.SetGeometry(ogr.CreateGeometryFromWkt("POINT (1 2)"))
    lyr.CreateFeature(feat)
    ds = None
    with pytest.raises(InputFileError, match=r"points.gpkg.*no polygon layer"):
        read_footprints(pts)
    good = tmp_path / "good.gpkg"
    write_gpkg(good, {"A": BUILDINGS["A"][0]}, 28992)
    with pytest.raises(InputFileError, match=r"good.gpkg.*no layer 'nope'"):
        read_footprints(good, layer="nope")
    with pytest.raises(InputFileError, match=r"good.gpkg.*no field 'gml_id'"):
        read_footprints(good, id_field="gml_id")


# --------------------------------------------------------------------------- reference from OBJ

OBJ = """# two buildings and some terrain, 3dfier style
mtllib ./3dfier.mtl
v 85000.0 447000.0 1.50
v 85002.0 447000.0 1.60
v 85002.0 447001.0 1.70
v 85000.0 447001.0 1.55
v 85000.0 447000.0 10.0
v 85002.0 447000.0 10.0
v 85002.0 447001.0 10.0
v 85000.0 447001.0 10.0
v 85002.0 447000.0 13.0
v 85003.0 447000.0 13.0
v 85003.0 447001.0 13.0
v 85002.0 447001.0 13.0
v 85003.0 447000.0 1.40
vt 0 0
vn 0 0 1
o terrain1
usemtl Terrain
f 1 2 3
o bldg-1
usemtl Building
f 5/1/1 6/1/1 7/1/1
f 5 7 8
f -5 -4 -3 -2
usemtl BuildingWall
f 1 2 6 5
f 2 13 10 9
o bldg-roof-only
usemtl Building
f 5 6 7
"""


def test_reference_heights_from_obj(tmp_path):
    path = tmp_path / "tiny.obj"
    path.write_text(OBJ)
    # roof: 2 m² at z 10 and 1 m² at z 13 -> 11; ground where the walls meet the terrain
    # face (vertices 1 and 2): 1.55; the lowest wall vertex: 1.40
    assert reference_heights_from_obj(path) == {"bldg-1": pytest.approx(11.0 - 1.55, abs=1e-9)}
    assert reference_heights_from_obj(path, ground="lowest") == {"bldg-1": pytest.approx(11.0 - 1.40, abs=1e-9)}
    with pytest.raises(InputFileError, match="missing.obj"):
        reference_heights_from_obj(tmp_path / "missing.obj")


# --------------------------------------------------------------------------- CLI

def test_cli_csv_reference_and_json(scene, tmp_path, capsys):
    ref = tmp_path / "ref.csv"
    ref.write_text("id,height\n" + "".join(f"{k},{v[1]}\n" for k, v in BUILDINGS.items()))
    out, js = tmp_path / "heights.csv", tmp_path / "stats.json"
    rc = main([str(scene["root"]), "--footprints", str(scene["gpkg"]), "--id-field", "ident", "--out", str(out),
               "--reference", str(ref), "--json", str(js), "--max-height", "40"])
    assert rc == 0
    printed = capsys.readouterr().out
    assert "8 footprints, 7 measured" in printed and "combined: n 7" in printed
    rows = {r["id"]: r for r in csv.DictReader(out.open())}
    assert rows["tiny"]["height"] == "" and rows["tiny"]["reason_az045_el45"] == "too_small"
    assert float(rows["court"]["height"]) == pytest.approx(11.21, abs=0.1) and rows["court"]["n_views"] == "3"
    stats = json.loads(js.read_text())
    comb = stats["reference"]["combined"]
    assert comb["n"] == 7 and abs(comb["bias"]) < 0.05 and comb["rmsd"] < 0.1 and comb["within_0.5m"] == 1.0
    assert stats["reference"]["az045_el45"]["n"] == 6 and stats["n_measured_per_view"]["az285_el60"] == 6
    assert not list(tmp_path.glob(".heights.csv*"))                         # atomic: no temporary left


def test_cli_errors_name_the_file(scene, tmp_path, capsys):
    maps = str(scene["root"])
    assert main([maps, "--footprints", str(tmp_path / "none.gpkg"), "--out", str(tmp_path / "h.csv")]) == 1
    assert "none.gpkg" in capsys.readouterr().err
    assert main([str(tmp_path), "--footprints", str(scene["gpkg"]), "--out", str(tmp_path / "h.csv")]) == 1
    assert f"{tmp_path}: no nadir map" in capsys.readouterr().err
    far = tmp_path / "far.gpkg"          # right CRS tag, wrong coordinates: nothing overlaps
    write_gpkg(far, {"A": [r - [80000.0, 0.0] for r in BUILDINGS["A"][0]]}, 28992)
    assert main([maps, "--footprints", str(far), "--out", str(tmp_path / "h.csv")]) == 1
    assert "far.gpkg: no footprint overlaps the maps" in capsys.readouterr().err
    bad_ref = tmp_path / "ref.csv"
    bad_ref.write_text("building,h\nA,3\n")
    assert main([maps, "--footprints", str(scene["gpkg"]), "--out", str(tmp_path / "h.csv"),
                 "--reference", str(bad_ref)]) == 1
    assert "ref.csv: needs columns" in capsys.readouterr().err


def test_maps_in_other_crs_rejected(scene, tmp_path):
    from osgeo import gdal

    other = tmp_path / "az045_el45.tif"
    gdal.Translate(str(other), str(scene["maps"]["az045_el45"]), outputSRS="EPSG:32631")
    fps = read_footprints(scene["gpkg"], id_field="ident")[:1]
    with pytest.raises(CRSError, match=r"az045_el45.tif and .*az000_el90.tif are in different CRSs"):
        measure_heights({"az000_el90": str(scene["maps"]["az000_el90"]), "az045_el45": str(other)}, fps)


def test_a_view_far_from_the_others_is_rejected_as_inconsistent():
    from pipeline25d.analysis.heights.combine import drop_inconsistent
    from pipeline25d.analysis.heights.results import ViewMeasurement

    def views(*hs):
        return {f"v{i}": ViewMeasurement(h, h, 1.0, 1.0, 0.0, "") for i, h in enumerate(hs)}

    v = views(10.0, 10.2, 9.9, 25.0, 7.9)
    drop_inconsistent(v, 2.0)
    # medians of the other views (all five decide together): 10.05, 9.95, 10.1, 9.95, 10.1 ->
    # off by 0.05, 0.25, 0.2, 15.05, 2.2
    assert [m.reason for m in v.values()] == ["", "", "", "inconsistent", "inconsistent"]
    assert math.isnan(v["v3"].height) and v["v0"].height == 10.0
    v = views(10.0, 10.2, 9.9, 25.0, 7.9)
    drop_inconsistent(v, 2.5)
    assert [m.reason for m in v.values()] == ["", "", "", "inconsistent", ""]
    v = views(10.0, 30.0)                                               # two views: no majority,
    drop_inconsistent(v, 2.0)                                          # neither can be trusted
    assert all(m.reason == "inconsistent" and math.isnan(m.height) for m in v.values())
    v = views(10.0, 11.5)                                               # two that agree are kept
    drop_inconsistent(v, 2.0)
    assert all(m.reason == "" for m in v.values())


def test_blocks_on_two_processes_give_the_serial_rows(scene):
    """measure_parallel: blocks of footprints on two processes, the rows measure_heights gives."""
    from pipeline25d.analysis.heights.views import measure_parallel

    fps = read_footprints(scene["gpkg"], id_field="ident")
    maps = {k: str(v) for k, v in scene["maps"].items()}
    serial = measure_heights(maps, fps)
    parallel = measure_parallel(maps, fps, workers=2, block=3)
    assert [r.id for r in parallel] == [r.id for r in serial]
    for a, b in zip(serial, parallel):
        assert a.reasons == b.reasons
        np.testing.assert_array_equal([a.height, *a.heights.values()], [b.height, *b.heights.values()])


def test_footprints_in_blocks_give_the_whole_runs_rows_and_a_change_reaches_only_its_blocks(scene, measured, tmp_path):
    """The heights stage's block jobs: each block measured alone (its neighbours as context) gives
    the rows of one job over all footprints, exactly (through their JSON records); a block's digest
    stays where the maps are rewritten with the same pixels and changes only where a changed pixel
    lies within its reach."""
    import shutil
    from pathlib import Path

    from osgeo import gdal

    from pipeline25d.analysis.heights.blocks import blocks_of, context_of, reads_digest, row_from_json, row_to_json
    from pipeline25d.analysis.heights.results import MatchSettings

    fps = read_footprints(scene["gpkg"], id_field="ident")
    maps = {k: str(v) for k, v in scene["maps"].items()}
    blocks = blocks_of(fps, 32.0)
    assert len(blocks) >= 3 and sorted(i for b in blocks.values() for i in b) == list(range(len(fps)))
    rows: list = [None] * len(fps)
    for idx in blocks.values():
        members = [fps[i] for i in idx]
        for i, r in zip(idx, measure_heights(maps, members, context=context_of(members, fps))):
            rows[i] = row_from_json(json.loads(json.dumps(row_to_json(r))))
    assert [json.dumps(row_to_json(r)) for r in rows] == [json.dumps(row_to_json(measured[f.id])) for f in fps]

    s = MatchSettings(max_height=5.0)          # a reach of at most 5 m x cot 30 deg: blocks apart

    def digests(m: dict) -> dict[str, str]:
        return {b: reads_digest(m, [fps[i] for i in idx], context_of([fps[i] for i in idx], fps), s, None)
                for b, idx in blocks.items()}

    before = digests(maps)
    copies = {k: str(shutil.copy(v, tmp_path / Path(v).name)) for k, v in maps.items()}
    assert digests(copies) == before
    by_id = {f.id: f for f in fps}
    ds = gdal.Open(copies["az000_el90"], gdal.GA_Update)
    gt = ds.GetGeoTransform()
    x, y = by_id["nodata"].rings[0].mean(0)
    col, row = int((x - gt[0]) / gt[1]), int((y - gt[3]) / gt[5])
    ds.GetRasterBand(1).WriteArray(np.array([[0, 255], [255, 0]], dtype=np.uint8), col, row)
    ds = None
    after = digests(copies)
    changed = {b for b in blocks if after[b] != before[b]}
    assert next(b for b, idx in blocks.items() if fps.index(by_id["nodata"]) in idx) in changed
    assert next(b for b, idx in blocks.items() if fps.index(by_id["A"]) in idx) not in changed


def test_the_stage_in_block_jobs_writes_the_single_jobs_files_and_keeps_unchanged_blocks(scene, tmp_path):
    """height_blocks: the checkpoint's blocks and jobs, one measure_job per job and merge_blocks write
    the heights.csv of run_stage in one job byte for byte and its heights.json but for "cost", with
    the blocks in one job each or grouped (sparse blocks share a job); measured again with nothing
    changed, every block keeps its rows and the files stay the same."""
    import json

    from pipeline25d.analysis.height_blocks import measure_job, merge_blocks, read_blocks, run_stage, write_blocks
    from pipeline25d.core.atomic import write_json

    maps = {k: str(v) for k, v in scene["maps"].items() if k in ("az000_el90", "az045_el45")}
    config = {"crs": "EPSG:28992", "gsd": GSD, "inputs": {},
              "perspectives": [{"azimuth": 0, "elevation": 90}, {"azimuth": 45, "elevation": 45}],
              "heights": {"footprints": str(scene["gpkg"]), "id_field": "ident", "reference": "none",
                          "block_size": 32.0}}
    scene_json = tmp_path / "scene.json"
    write_json(scene_json, {"bounds": [[X0, Y0 - SIZE_M, 0.0], [X0 + SIZE_M, Y0, 20.0]], "z0": 0.0, "terrain": "flat",
                            "projection": "plane", "dtm": None, "n_candidates": 0, "n_check": 0,
                            "dtm_check_holdout_m": None, "n_chunks": 1})
    one = run_stage(config, maps, scene_json, None, tmp_path / "one.csv", tmp_path / "one.json")
    blocks_json = tmp_path / "work" / "blocks.json"
    grouped = write_blocks(config, maps["az000_el90"], blocks_json)
    _, blocks, jobs = read_blocks(blocks_json)
    assert jobs == grouped and len(blocks) >= 3 and len(jobs) < len(blocks)     # a few footprints: grouped
    assert sorted(b for bs in jobs.values() for b in bs) == sorted(blocks)

    def in_blocks(tag: str, jobs: dict[str, list[str]]) -> tuple[dict, list[dict]]:
        d = json.loads(blocks_json.read_text())
        write_json(blocks_json, {**d, "jobs": jobs})
        outs = [tmp_path / "work" / f"block_{j}.{tag}.json" for j in jobs]
        summaries = [measure_job(config, maps, scene_json, blocks_json, j, tmp_path / "work" / "rows", out)
                     for j, out in zip(jobs, outs)]
        merged = merge_blocks(config, maps, scene_json, None, blocks_json, [str(o) for o in outs],
                              tmp_path / "work" / "rows", tmp_path / f"{tag}.csv", tmp_path / f"{tag}.json")
        return merged, summaries

    strip = lambda d: {k: v for k, v in d.items() if k != "cost"}  # noqa: E731
    for tag, js in (("alone", {b: [b] for b in blocks}), ("blocks", jobs)):
        for f in (tmp_path / "work" / "rows").glob("*.json"):
            f.unlink()
        merged, summaries = in_blocks(tag, js)
        assert sum(s["measured"] for s in summaries) == len(blocks)
        assert sum(s["n"] for s in summaries) == one["footprints"]["n_on_maps"]
        assert (tmp_path / f"{tag}.csv").read_bytes() == (tmp_path / "one.csv").read_bytes()
        assert strip(json.loads((tmp_path / f"{tag}.json").read_text())) == \
            strip(json.loads((tmp_path / "one.json").read_text()))
        assert merged["cost"]["jobs"] == len(js) and merged["cost"]["blocks_measured"] == len(blocks)
    again, summaries = in_blocks("again", jobs)
    assert not any(s["measured"] for s in summaries) and again["cost"]["blocks_measured"] == 0
    assert (tmp_path / "again.csv").read_bytes() == (tmp_path / "one.csv").read_bytes()
