"""Shared fixtures: paths, the shared datasets, a GL context (skip without EGL), and the small demo run
served to headless Chromium (test_viewer_browser, test_viewer_identify)."""

from __future__ import annotations

import os
import shutil
import threading
import time
from pathlib import Path

import numpy as np
import pytest
import trimesh

from pipeline25d import jobhost
from pipeline25d.core.mesh import MeshPart
from pipeline25d.publish.serve import make_server

REPO = Path(__file__).resolve().parents[1]
DATA = REPO.parent / "shared" / "data"
CHROMIUM = shutil.which("chromium")


@pytest.fixture(scope="session", autouse=True)
def package_cache(tmp_path_factory):
    """Tileset packages a test reads unpack into a folder of the test run, not the user's cache
    (``PIPELINE25D_CACHE``, inherited by the workflow runs a test starts)."""
    folder = tmp_path_factory.mktemp("package-cache")
    patch = pytest.MonkeyPatch()
    patch.setenv("PIPELINE25D_CACHE", str(folder))
    yield folder
    patch.undo()


def shared_file(path: Path) -> Path:
    """``path`` (a real dataset under ``../shared/data``), or skip the test where it is absent."""
    if not Path(path).exists():
        pytest.skip(f"test data {path} not present")
    return Path(path)


@pytest.fixture(scope="session")
def gl_ctx():
    from pipeline25d.core.errors import RenderError
    from pipeline25d.stages.render import create_context

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


@pytest.fixture(scope="session")
def small_run(tmp_path_factory):
    """The small demo city (test_workflow.SMALL_CONFIG) run end to end once per session, with no DTM
    given (terrain from the model, terrain-relative projection): (workdir, results)."""
    from test_workflow import demo_run

    return demo_run(tmp_path_factory, "small")


def serve(workdir: Path, results: Path):
    """Serve ``results`` on 127.0.0.1 (with Range support) for the duration of a fixture."""
    if CHROMIUM is None:
        pytest.skip("no chromium on PATH: apt-get install chromium (make sysdeps does)")
    pytest.importorskip("playwright.sync_api", reason="the playwright package is not installed (requirements.txt)")
    server = make_server(results, port=0)
    thread = threading.Thread(target=server.serve_forever, daemon=True)
    thread.start()
    yield f"http://127.0.0.1:{server.server_address[1]}", workdir, results
    server.shutdown()
    server.server_close()
    thread.join()


@pytest.fixture(scope="module")
def served(small_run):
    """(base URL, workdir, results) with results/<scene>/ served on 127.0.0.1."""
    yield from serve(*small_run)


@pytest.fixture(scope="module")
def browser(served):
    from playwright.sync_api import sync_playwright

    with sync_playwright() as pw:
        chromium = pw.chromium.launch(executable_path=CHROMIUM)
        yield chromium
        chromium.close()


def vertical_edge(building: dict, azimuth: float, elevation: float) -> tuple[np.ndarray, np.ndarray, float]:
    """A demo building's (truth.json entry) vertical edge nearest the camera, from the geometry alone:
    (base, top) map positions on a terrain-relative map and its true height (eave − terrain) in metres.

    The nearest corner (smallest p·d) has both its facades facing the camera, so its edge is seen.
    """
    from pipeline25d_lab.scenes.demo import terrain_height

    t, f = np.radians(azimuth), np.radians(elevation)
    d = np.array([np.sin(t), np.cos(t)])
    corners = np.asarray(building["footprint"], dtype=np.float64)
    base = corners[np.argmin(corners @ d)]
    height = building["eave_z"] - terrain_height(base[0], base[1])
    return base, base + height * np.cos(f) / np.sin(f) * d, height


def roof_colour(results: Path, building: dict) -> np.ndarray:
    """(3,) float RGB of a demo building's roof on the run's nadir map, at its footprint centre."""
    from osgeo import gdal

    nadir = gdal.Open(str(results / "maps" / "az000_el90.tif"))
    gt = nadir.GetGeoTransform()
    x, y = np.mean(building["footprint"], axis=0)
    return nadir.ReadAsArray(int((x - gt[0]) / gt[1]), int((y - gt[3]) / gt[5]), 1, 1)[:3, 0, 0].astype(float)


def grid_plan(cells, gsd: float, tile_size: int, crs: str = "EPSG:25832", contents: dict | None = None):
    """A nadir plan (pipeline25d.stages.records.Plan) of tiles at (row, col) ``cells``, each drawing
    nothing, its content box the whole tile unless ``contents`` gives one."""
    from pipeline25d.geometry.perspectives import Perspective
    from pipeline25d.stages.records import Plan, Tile, tile_extent

    contents = contents or {}
    tiles = tuple(Tile(r, c, (), (0.0, 1.0), tuple(contents.get((r, c), tile_extent(gsd, tile_size, r, c))), (), {},
                       f"{r}_{c}") for r, c in cells)
    return Plan(Perspective(0, 90), crs, 0.0, gsd, gsd, tile_size, "plane", None, tiles, len(tiles), 0)


@pytest.fixture
def host(monkeypatch):
    """A job host (pipeline25d.jobhost) started by this process, its socket in this process's
    environment; stopped after."""
    monkeypatch.delenv(jobhost.SOCKET_ENV, raising=False)
    started = jobhost.start()
    path = os.environ[jobhost.SOCKET_ENV]
    deadline = time.monotonic() + 60
    while not os.path.exists(path):
        assert started.poll() is None, "the host ended before it listened"
        assert time.monotonic() < deadline, "the host did not listen within 60 s"
        time.sleep(0.05)
    yield path
    jobhost.stop(started)
    assert not os.path.exists(path)


def held_out(holdout_csv: Path, candidates_csv: Path) -> np.ndarray:
    """(n, 2) x, y where the scene stage left the ground out of the DTM, after checking that every
    check point is one of them (its own ground unseen by the DTM)."""
    import csv

    from pipeline25d.stages.gcps import read_candidates

    with open(holdout_csv, newline="") as fh:
        held = {row["id"]: (float(row["x"]), float(row["y"])) for row in csv.DictReader(fh)}
    checks = [c for c in read_candidates(candidates_csv) if c.role == "check"]
    assert all(held[c.id] == (c.x, c.y) for c in checks), "a check point whose ground the DTM saw"
    return np.array(list(held.values())).reshape(-1, 2)
