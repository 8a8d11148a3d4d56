"""Ground-offset evaluation against synthetic maps with exactly known shifts."""

from __future__ import annotations

import json

import numpy as np
import pytest
from scipy import ndimage

from pipeline25d.analysis.evaluate.cli import main
from pipeline25d.analysis.evaluate.offsets import ground_offsets
from pipeline25d.analysis.evaluate.visibility import (
    GroundModel,
    ground_mask_from_rasters,
    hidden_by_relief,
    visible_ground,
)
from pipeline25d.core.errors import ConfigError
from pipeline25d.core.geotiff import write_rgba_geotiff
from pipeline25d.core.grid import Grid
from pipeline25d.core.raster import gdal

GSD = 0.5
E0, N0 = 691000.0, 5334000.0          # UTM 32N, top-left corner of the big texture
N = 640                               # big periodic texture, px


def _wkt() -> str:
    from osgeo import osr

    srs = osr.SpatialReference()
    srs.ImportFromEPSG(25832)
    return srs.ExportToWkt()


def texture(seed: int, n: int = N) -> np.ndarray:
    """Periodic, band-limited noise (features ~2-8 px), grey levels around 128, float."""
    f = np.fft.fft2(np.random.default_rng(seed).standard_normal((n, n)))
    k = np.hypot(np.fft.fftfreq(n)[:, None], np.fft.fftfreq(n)[None, :])
    img = np.real(np.fft.ifft2(f * np.exp(-2 * (2.5 * k) ** 2) * (1 - np.exp(-(8 * k) ** 2))))
    return (img - img.mean()) / img.std() * 40 + 128


def fourier_shift(img: np.ndarray, d_col: float, d_row: float) -> np.ndarray:
    """Content moved by (+d_col, +d_row) px (exact for a periodic band-limited image)."""
    return np.real(np.fft.ifft2(ndimage.fourier_shift(np.fft.fft2(img), (d_row, d_col))))


def upsample2(img: np.ndarray) -> np.ndarray:
    """Exact 2x band-limited interpolation of a periodic image (fine pixel 2i = coarse pixel i)."""
    n = img.shape[0]
    spec = np.zeros((2 * n, 2 * n), complex)
    spec[n // 2:n // 2 + n, n // 2:n // 2 + n] = np.fft.fftshift(np.fft.fft2(img))
    return np.real(np.fft.ifft2(np.fft.ifftshift(spec))) * 4


def write_map(path, grey: np.ndarray, col0: float, row0: float, alpha: np.ndarray | None = None,
              gsd: float = GSD) -> str:
    """Write a grey float image as RGBA GeoTIFF whose top-left corner is big-texture pixel corner (col0, row0)."""
    g = np.clip(np.round(grey), 0, 255).astype(np.uint8)
    rgba = np.dstack([g, g, (g * 0.8 + 20).astype(np.uint8), np.full_like(g, 255) if alpha is None else alpha])
    write_rgba_geotiff(path, rgba, Grid.north_up(E0 + col0 * GSD, N0 - row0 * GSD, gsd, g.shape[1], g.shape[0]), _wkt())
    return str(path)


@pytest.fixture(scope="module")
def tex() -> np.ndarray:
    return texture(1)


@pytest.fixture
def nadir(tmp_path, tex) -> str:
    return write_map(tmp_path / "az000_el90.tif", tex[40:424, 24:472], 24, 40)     # 384 x 448 px


def test_constant_subpixel_shift_and_other_extent(tmp_path, tex, nadir):
    # ground 1.3 px east and 0.7 px south (map dy = -0.7) in the oblique; extent and origin differ
    moved = fourier_shift(tex, 1.3, 0.7)
    obl = write_map(tmp_path / "az045_el45.tif", moved[10:500, 60:620], 60, 10)
    res = ground_offsets(obl, nadir, step_px=48)
    s = res.summary()
    assert not res.resampled and not res.note and res.n_failed == 0 and res.n_ok >= 40
    assert res.n_windows == res.n_ok + res.n_failed
    assert s["bias_x_px"] == pytest.approx(1.3, abs=0.05)
    assert s["bias_y_px"] == pytest.approx(-0.7, abs=0.05)
    assert s["rms_px"] == pytest.approx(np.hypot(1.3, 0.7), abs=0.05)
    assert s["bias_x_m"] == pytest.approx(1.3 * GSD, abs=0.025)
    assert np.abs(res.dx_px - 1.3).max() < 0.1 and np.abs(res.dy_px + 0.7).max() < 0.1
    assert res.quality.min() > 0.9


def test_sign_convention_from_georeferencing(tmp_path, tex, nadir):
    # same pixels, origin 2 px east and 1 px north: every ground feature shows 2 px east, 1 px north
    obl = write_map(tmp_path / "obl.tif", tex[40:424, 24:472], 24 + 2, 40 - 1)
    res = ground_offsets(obl, nadir)
    s = res.summary()
    assert s["bias_x_px"] == pytest.approx(2.0, abs=0.01)
    assert s["bias_y_px"] == pytest.approx(1.0, abs=0.01)


def test_origin_off_grid_by_a_fraction(tmp_path, tex, nadir):
    # origin 0.25 px east and 0.125 px north of the nadir grid: paired without resampling
    obl = write_map(tmp_path / "obl.tif", fourier_shift(tex, 0.4, -0.2)[40:424, 24:472], 24 + 0.25, 40 - 0.125)
    res = ground_offsets(obl, nadir)
    s = res.summary()
    assert not res.resampled and "off the nadir grid" in res.note and res.n_failed == 0
    assert s["bias_x_px"] == pytest.approx(0.4 + 0.25, abs=0.05)
    assert s["bias_y_px"] == pytest.approx(0.2 + 0.125, abs=0.05)


def test_other_gsd_is_resampled(tmp_path, tex, nadir):
    # oblique at half the gsd (exact 2x interpolation), ground 0.6 px east, 0.3 px north (nadir px)
    # fine pixel j's centre lies at coarse pixel j/2 - 0.25: move the content by +0.25 before upsampling
    fine = upsample2(fourier_shift(tex, 0.6 + 0.25, -0.3 + 0.25))
    obl = write_map(tmp_path / "obl.tif", fine[2 * 40:2 * 424, 2 * 24:2 * 472], 24, 40, gsd=GSD / 2)
    res = ground_offsets(obl, nadir)
    s = res.summary()
    assert res.resampled and "resampled" in res.note and "resampled" in res.summary_line()
    assert res.n_ok >= 20
    assert s["bias_x_px"] == pytest.approx(0.6, abs=0.05)
    assert s["bias_y_px"] == pytest.approx(0.3, abs=0.05)


def test_smooth_shift_field_recovered_per_window(tmp_path, tex, nadir):
    rows, cols = np.mgrid[0:N, 0:N].astype(float)

    def field(c, r):  # px (east, south); content at texture pixel p comes from p - field(p)
        return 1.2 * np.sin(2 * np.pi * c / N) + 0.3, 0.9 * np.cos(2 * np.pi * (r + 0.5 * c) / N)

    dc, dr = field(cols, rows)
    # warp on the 2x-oversampled texture, where cubic interpolation is accurate
    moved = ndimage.map_coordinates(upsample2(tex), [2 * (rows - dr), 2 * (cols - dc)], order=3, mode="grid-wrap")
    obl = write_map(tmp_path / "obl.tif", moved, 0, 0)
    res = ground_offsets(obl, nadir, step_px=48)
    assert res.n_failed == 0 and res.n_ok >= 50
    c, r = (res.x - E0) / GSD - 0.5, (N0 - res.y) / GSD - 0.5     # nadir window centres, texture px
    tc, tr = field(c, r)
    for _ in range(3):                                             # where that ground shows: q = c + field(q)
        tc, tr = field(c + tc, r + tr)
    err = np.hypot(res.dx_px - tc, res.dy_px + tr)
    assert err.max() < 0.1, err.max()


def test_transparent_flat_and_off_ground_windows_excluded(tmp_path, tex):
    grey = tex[:384, :384].copy()
    grey[200:330, 30:170] = 130.0                                  # flat (textureless) area
    nadir = write_map(tmp_path / "nadir.tif", grey, 0, 0)
    alpha = np.full(grey.shape, 255, np.uint8)
    alpha[40:130, 200:300] = 0                                     # transparent hole in the oblique
    obl = write_map(tmp_path / "obl.tif", grey, 0, 0, alpha)
    x_cut = E0 + 330 * GSD                                         # east of this: not ground

    # min_ground_fraction=1: only whole windows of opaque, textured ground
    res = ground_offsets(obl, nadir, ground_mask_fn=lambda x, y: x < x_cut, step_px=32, min_ground_fraction=1.0)
    assert res.n_transparent > 0 and res.n_flat > 0 and res.n_not_ground > 0
    assert res.n_examined == res.n_grid == res.n_transparent + res.n_flat + res.n_not_ground + res.n_windows
    half = res.window_px / 2
    c0, c1 = (res.x - E0) / GSD - half, (res.x - E0) / GSD + half  # window pixel bounds (texture px)
    r0, r1 = (N0 - res.y) / GSD - half, (N0 - res.y) / GSD + half
    assert not ((c1 > 200) & (c0 < 300) & (r1 > 40) & (r0 < 130)).any()      # touches the hole
    assert not ((c0 >= 30) & (c1 <= 170) & (r0 >= 200) & (r1 <= 330)).any()  # inside the flat area
    assert (c1 <= 330).all()                                                  # off ground
    assert res.n_failed == 0 and np.abs(res.dx_px).max() < 0.05 and np.abs(res.dy_px).max() < 0.05
    # default: windows at least half usable are measured too, on their usable pixels only
    part = ground_offsets(obl, nadir, ground_mask_fn=lambda x, y: x < x_cut, step_px=32)
    assert part.n_windows > res.n_windows and part.ground_fraction.min() >= 0.3
    assert (part.ground_fraction < 1).any() and part.n_failed == 0
    assert np.abs(part.dx_px).max() < 0.05 and np.abs(part.dy_px).max() < 0.05
    assert part.n_examined == part.n_transparent + part.n_flat + part.n_not_ground + part.n_windows


def test_ground_mask_from_dsm_and_dtm(tmp_path, tex, capsys):
    nadir = write_map(tmp_path / "nadir.tif", tex[:384, :384], 0, 0)
    g = gdal()
    cell = 1.0                                                      # DSM/DTM at 1 m, 256 x 256 cells
    for name, values in (("dtm", np.full((256, 256), 480.0)), ("dsm", np.full((256, 256), 480.2))):
        if name == "dsm":
            values[100:150, 60:110] = 495.0                         # a building: 15 m above ground
        ds = g.GetDriverByName("GTiff").Create(str(tmp_path / f"{name}.tif"), 256, 256, 1, g.GDT_Float32)
        ds.SetGeoTransform((E0, cell, 0, N0, 0, -cell))
        ds.SetProjection(_wkt())
        ds.GetRasterBand(1).WriteArray(values)
        ds = None
    mask = ground_mask_from_rasters(tmp_path / "dsm.tif", tmp_path / "dtm.tif", max_height=0.5, dilate_m=1.0)
    xs = E0 + np.array([85.5, 59.5, 30.0, 300.0])
    ys = N0 - np.array([125.5, 125.5, 30.0, 30.0])
    assert mask(xs, ys).tolist() == [False, False, True, False]   # roof, dilated edge, ground, outside
    res = ground_offsets(nadir, nadir, ground_mask_fn=mask, step_px=32, min_ground_fraction=1.0)
    assert res.n_not_ground > 0 and res.n_ok > 0
    half = res.window_px / 2 * GSD
    hit = ((res.x + half > E0 + 59) & (res.x - half < E0 + 111)
           & (N0 - res.y + half > 99) & (N0 - res.y - half < 151))
    assert not hit.any()
    dem = ["--dsm", str(tmp_path / "dsm.tif"), "--dtm", str(tmp_path / "dtm.tif"), "--step", "32",
           "--min-ground-fraction", "1"]
    assert main(["ground", nadir, nadir, *dem]) == 0
    assert capsys.readouterr().out == ""                          # the nadir map itself is skipped
    obl = write_map(tmp_path / "obl.tif", tex[:384, :384], 0, 0)
    assert main(["ground", obl, nadir, *dem]) == 1                # which view? not in the file name
    assert "az045_el45" in capsys.readouterr().err
    with pytest.raises(ConfigError, match="perspective id"):
        ground_offsets(obl, nadir, GroundModel(tmp_path / "dsm.tif", tmp_path / "dtm.tif"))
    assert main(["ground", obl, nadir, *dem, "--perspective", "az000_el90"]) == 0
    assert f"{res.n_not_ground} not ground" in capsys.readouterr().out


def test_max_windows_sample_is_seeded(tmp_path, tex, nadir):
    a = ground_offsets(nadir, nadir, step_px=32, max_windows=12, seed=3)
    b = ground_offsets(nadir, nadir, step_px=32, max_windows=12, seed=3)
    assert a.n_windows == 12 and a.n_examined == 12 < a.n_grid
    assert np.array_equal(a.x, b.x) and np.array_equal(a.y, b.y)


def test_unrelated_content_fails_and_prints_na(tmp_path, tex, nadir, capsys):
    obl = write_map(tmp_path / "az135_el45.tif", texture(2)[40:424, 24:472], 24, 40)
    res = ground_offsets(obl, nadir)
    assert res.n_windows > 20 and res.n_ok < 10 and res.n_failed == res.n_windows - res.n_ok
    assert res.summary()["rms_px"] is None
    out = tmp_path / "eval.json"
    assert main(["ground", obl, nadir, "--json", str(out)]) == 0
    line = capsys.readouterr().out.strip()
    assert line.startswith(f"az135_el45: {res.n_windows} windows, {res.n_ok} ok, n/a ({res.n_ok} windows)")
    data = json.loads(out.read_text())
    assert data["maps"]["az135_el45"]["summary"]["n_failed"] == res.n_failed


def test_cli_summary_line_and_json(tmp_path, tex, nadir, capsys):
    obl = write_map(tmp_path / "az045_el45.tif", fourier_shift(tex, -0.4, 0.6)[40:424, 24:472], 24, 40)
    out = tmp_path / "eval.json"
    assert main(["ground", obl, nadir, "--json", str(out)]) == 0
    line = capsys.readouterr().out.strip()
    assert line.startswith("az045_el45: ") and " rms 0.7" in line and "bias (-0.40, -0.60) px" in line
    data = json.loads(out.read_text())["maps"]["az045_el45"]
    assert data["summary"]["n_ok"] == len(data["windows"]["dx_px"]) == data["summary"]["n_windows"]
    assert data["summary"]["rms_m"] == pytest.approx(np.hypot(0.4, 0.6) * GSD, abs=0.025)


# --------------------------------------------------------------------------- partial windows, visible ground

def _write_raster(path, values: np.ndarray, cell: float = GSD) -> str:
    g = gdal()
    ds = g.GetDriverByName("GTiff").Create(str(path), values.shape[1], values.shape[0], 1, g.GDT_Float32)
    ds.SetGeoTransform((E0, cell, 0, N0, 0, -cell))
    ds.SetProjection(_wkt())
    ds.GetRasterBand(1).WriteArray(values)
    ds = None
    return str(path)


def city(tmp_path, dx: float, dy: float, az: int = 45, el: int = 45, height: float = 3.0,
         same_buildings: bool = False, size: int = 256):
    """A dense synthetic city with exact truth: nadir map, oblique map, DSM, DTM (all on one 0.5 m grid).

    Ground: band-limited texture, in the oblique map moved by exactly (dx east, dy north) px
    (Fourier shift). One 12 x 12 px box of ``height`` m in every 32 px cell: the nadir map shows
    its roof (other texture), the oblique map paints the box's whole lean (footprint swept
    along d by height·cot(el), computed here independently of the evaluator) in a wall texture
    that does not move with the ground, so 30-50 % of every window is building. With
    ``same_buildings`` the nadir map shows the same wall texture over the same area (identical
    mask edges and content in both maps). Holes (alpha 0) in both maps.
    """
    ground = texture(1, size)
    rows, cols = np.mgrid[0:size, 0:size] + 0.5
    th = np.radians(az)
    lean = height / np.tan(np.radians(el)) / GSD
    foot = np.zeros((size, size), bool)
    sweep = np.zeros((size, size), bool)
    for r0 in range(8, size, 32):
        for c0 in range(10, size, 32):
            foot |= (rows >= r0) & (rows < r0 + 12) & (cols >= c0) & (cols < c0 + 12)
            for t in np.linspace(0.0, lean, 60):           # p shows the box if p - t*d lies in its footprint
                rr, cc = rows + t * np.cos(th), cols - t * np.sin(th)
                sweep |= (rr >= r0) & (rr < r0 + 12) & (cc >= c0) & (cc < c0 + 12)
    wall = texture(7, size) * 0.5 + 40
    nad = np.where(sweep, wall, ground) if same_buildings else np.where(foot, texture(5, size) * 0.6 + 90, ground)
    obl = np.where(sweep, wall, fourier_shift(ground, dx, -dy))
    rng = np.random.default_rng(3)
    alphas = []
    for _ in range(2):
        alpha = np.full((size, size), 255, np.uint8)
        for r, c in rng.integers(0, size - 8, (12, 2)):
            alpha[r:r + 6, c:c + 6] = 0
        alphas.append(alpha)
    dtm = np.full((size, size), 10.0)
    dsm = dtm + rng.uniform(-0.05, 0.05, (size, size)) + np.where(foot, height, 0.0)
    return (write_map(tmp_path / "az000_el90.tif", nad, 0, 0, alphas[0]),
            write_map(tmp_path / f"az{az:03d}_el{el:02d}.tif", obl, 0, 0, alphas[1]),
            GroundModel(_write_raster(tmp_path / "dsm.tif", dsm), _write_raster(tmp_path / "dtm.tif", dtm)), sweep)


@pytest.mark.parametrize("dx, dy, az, el, height", [(0.37, -0.61, 45, 45, 3.0), (-1.23, 0.48, 200, 30, 2.0)])
def test_partial_windows_recover_ground_shift_beside_buildings(tmp_path, dx, dy, az, el, height):
    nadir, obl, model, sweep = city(tmp_path, dx, dy, az, el, height)
    res = ground_offsets(obl, nadir, model)
    assert res.perspective == f"az{az:03d}_el{el:02d}"
    assert (model.mask(res.perspective).values & sweep).sum() == 0      # no painted building counted as ground
    assert res.n_windows == 64 and res.n_ok == 64
    assert 0.5 <= res.ground_fraction.min() and res.ground_fraction.max() < 0.7   # 30-50 % building per window
    assert np.abs(res.dx_px - dx).max() < 0.05 and np.abs(res.dy_px - dy).max() < 0.05
    s = res.summary()
    assert s["bias_x_px"] == pytest.approx(dx, abs=0.02) and s["bias_y_px"] == pytest.approx(dy, abs=0.02)
    assert res.quality.min() > 0.95 and np.nanmax(res.sigma_px) < 0.05


def test_identical_mask_edges_do_not_pull_toward_zero(tmp_path):
    from skimage.registration import phase_cross_correlation

    from pipeline25d.analysis.evaluate.rasters import _open, _read_window

    nadir, obl, model, _ = city(tmp_path, 0.8, 0.0, az=90, same_buildings=True)
    res = ground_offsets(obl, nadir, model)
    assert res.n_ok == res.n_windows == 64
    assert np.abs(res.dx_px - 0.8).max() < 0.05 and np.abs(res.dy_px).max() < 0.05
    assert res.summary()["bias_x_px"] == pytest.approx(0.8, abs=0.02)
    # the same windows, zero-filled outside the same mask and phase-correlated: pulled toward 0
    mask, nad, ob = model.mask(res.perspective), _open(nadir), _open(obl)
    naive = []
    for x, y in zip(res.x, res.y):
        c, r = round((x - E0) / GSD - 16), round((N0 - y) / GSD - 16)
        (a, aa), (b, ab) = _read_window(nad, c, r, 32), _read_window(ob, c, r, 32)
        xx, yy = np.meshgrid(E0 + (c + np.arange(32) + 0.5) * GSD, N0 - (r + np.arange(32) + 0.5) * GSD)
        m = (aa == 255) & (ab == 255) & mask(xx, yy)
        shift = phase_cross_correlation(np.where(m, a - a[m].mean(), 0), np.where(m, b - b[m].mean(), 0),
                                        upsample_factor=20, normalization=None)[0]
        naive.append(-shift[1])
    assert np.mean(naive) < 0.8 - 0.05                                  # the bias this method avoids


def test_texture_in_one_direction_is_ill_conditioned(tmp_path, tex):
    rows, cols = np.mgrid[0:192, 0:192] + 0.5
    u = cols * np.cos(0.5) + rows * np.sin(0.5)                         # stripes across u, 29 deg off north
    rng = np.random.default_rng(5)
    stripes = 128 + sum(12 * np.sin(2 * np.pi * u / lam + rng.uniform(0, 6.3)) for lam in rng.uniform(3, 12, 8))
    grey = np.where(cols < 96, stripes, tex[:192, :192])
    nadir = write_map(tmp_path / "nadir.tif", grey, 0, 0)
    obl = write_map(tmp_path / "obl.tif", grey, 0, 0)
    res = ground_offsets(obl, nadir, step_px=32)
    c = (res.x - E0) / GSD
    left, right = c < 96, c > 96
    assert left.sum() == 18 and right.sum() == 18
    assert [res.reason[i] for i in np.nonzero(left)[0]] == ["ill_conditioned"] * 18
    assert res.ok[right].all() and not res.ok[left].any() and (res.condition[left] > 50).all()
    assert res.summary()["failed_by_reason"] == {"ill_conditioned": 18}
    assert "18 ill_conditioned" in res.summary_line()


@pytest.mark.parametrize("az, el", [(0, 45), (45, 45), (90, 30), (200, 30), (315, 60)])
def test_hidden_strip_behind_a_box(az, el):
    height, cell = 10.0, 1.0
    z = np.zeros((200, 200))
    z[90:110, 90:110] = height                                          # box of 20 x 20 cells, centre (100, 100)
    hidden = hidden_by_relief(z, az, el, (cell, cell), clearance=0.0)
    assert not hidden[z > 0].any()
    d = np.array([np.sin(np.radians(az)), -np.cos(np.radians(az))])    # (col, row) per metre along d
    t_exit = 10.0 / np.abs(d).max()                                     # from the centre to the box's far edge
    strip = height / np.tan(np.radians(el))                             # hidden length behind it, metres
    t = np.arange(t_exit + 0.01, t_exit + strip + 20, 0.05)
    c, r = (100 + t[:, None] * d / cell).T.astype(int)
    on_ray = hidden[r, c]
    measured = t[on_ray].max() - t_exit
    assert on_ray[t < t_exit + strip - cell].all()
    assert abs(measured - strip) <= cell
    # nothing else is hidden: the hidden area is the strip (footprint width across d, times its length)
    width = 20 * (np.abs(d).sum())                                      # box's extent across d, in cells
    assert hidden.sum() == pytest.approx(width * strip / cell, rel=0.1)
    ground = visible_ground(10 + z, np.full(z.shape, 10.0), f"az{az:03d}_el{el:02d}", (cell, cell), dilate_m=0.0)
    assert np.array_equal(ground, (z == 0) & ~hidden_by_relief(z, az, el, (cell, cell)))
    nadir = visible_ground(10 + z, np.full(z.shape, 10.0), None, (cell, cell), dilate_m=0.0)
    assert np.array_equal(nadir, z == 0)


def test_terrain_hides_only_in_plane_projection():
    rows, cols = np.mgrid[0:160, 0:160] + 0.5
    hill = 30 * np.exp(-((rows - 80) ** 2 + (cols - 80) ** 2) / (2 * 20 ** 2))   # 30 m hill, slopes up to 42 deg
    args = (hill, hill, "az090_el30", (1.0, 1.0))
    assert visible_ground(*args, dilate_m=0.0).all()                   # terrain-relative maps: nothing leans
    plane = visible_ground(*args, dilate_m=0.0, projection="plane")
    assert 0 < (~plane).sum() and (~plane[:, :80]).sum() == 0           # the east (lee) slope is hidden


def test_visible_ground_of_a_large_grid_is_fast():
    import time

    rng = np.random.default_rng(0)
    z = np.zeros((2000, 2000))
    for r, c in rng.integers(0, 1960, (2000, 2)):
        z[r:r + 30, c:c + 30] = rng.uniform(3, 40)
    t0 = time.perf_counter()
    hidden = hidden_by_relief(z, 45, 45, (0.5, 0.5))
    assert time.perf_counter() - t0 < 10 and 0.1 < hidden.mean() < 0.9


def test_masked_integer_shift_agrees_with_skimage(tex):
    from skimage.registration import phase_cross_correlation

    from pipeline25d.analysis.evaluate.correlation import masked_ncc_surface

    rng = np.random.default_rng(2)
    big = tex[100:150, 200:250]
    ok_big = rng.uniform(size=big.shape) > 0.3
    ref, ok_ref = big[9 + 3:9 + 3 + 32, 9 - 2:9 - 2 + 32], ok_big[9 + 3:9 + 3 + 32, 9 - 2:9 - 2 + 32].copy()
    ok_ref[5:20, 5:15] = False
    surface = masked_ncc_surface(ref, ok_ref, big, ok_big)
    peak = np.subtract(np.unravel_index(np.argmax(surface), surface.shape), 9)
    assert peak.tolist() == [3, -2] and surface.max() == pytest.approx(1.0)
    # skimage's masked NCC (big cropped to ref's cells): the shift registering moving onto ref, i.e. -peak
    mov, ok_mov = big[9:41, 9:41], ok_big[9:41, 9:41]
    sk = phase_cross_correlation(ref, mov, reference_mask=ok_ref, moving_mask=ok_mov)
    shift = sk[0] if isinstance(sk, tuple) else sk
    assert np.asarray(shift).tolist() == [-3, 2]
