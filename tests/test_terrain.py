"""Terrain from the model (CSF on the detrended DSM, DTM fill) and GCP site selection, against exact truth."""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest
from conftest import grid_plan

from pipeline25d.core.grid import Grid
from pipeline25d.geometry.perspectives import PRESETS, Perspective
from pipeline25d.stages.gcp_sites import SiteRules, select_sites
from pipeline25d.stages.maps.warp import MIN_CHECK_POINTS, choose, residuals
from pipeline25d.stages.records import Observation
from pipeline25d.stages.terrain.dtm import interpolate_dtm
from pipeline25d.stages.terrain.ground import csf_ground, lower_envelope, trim_object_edges

E0, N0 = 600000.0, 5250000.0


def rugged_scene(n: int = 300, seed: int = 0):
    """A 1 m DSM of steep terrain (~200 m relief) with 40 flat-roofed boxes; truth masks and DTM."""
    grid = Grid.north_up(E0, N0 + n, 1.0, n, n)
    xs, ys = grid.cell_centres()
    terrain = 60 * np.sin((xs - E0) / 90) * np.cos((ys - N0) / 110) + 0.3 * (xs - E0)   # slopes up to ~40°
    dsm = terrain.copy()
    objects = np.zeros(dsm.shape, bool)
    rng = np.random.default_rng(seed)
    for _ in range(40):
        r, c = rng.integers(5, n - 30, 2)
        h, w = rng.integers(8, 25, 2)
        dsm[r:r + h, c:c + w] = terrain[r:r + h, c:c + w].max() + rng.uniform(6, 40)
        objects[r:r + h, c:c + w] = True
    return grid, dsm, terrain, objects


def test_csf_on_the_detrended_dsm_finds_the_ground_of_steep_relief():
    grid, dsm, terrain, objects = rugged_scene()
    ground = csf_ground(dsm, grid, max_object_m=60, cloth_resolution=2.0, rigidness=2, class_threshold=0.5)
    assert not (ground & objects).any()                                  # no roof taken as ground
    recall = ground[~objects].mean()
    assert recall > 0.97, recall
    kept = trim_object_edges(ground)
    dtm = interpolate_dtm(np.where(kept, dsm, np.nan), search_cells=30)
    err = dtm - terrain
    assert np.abs(err[kept]).max() < 1e-4                                # ground keeps its own heights (float32 fill)
    rms = {name: float(np.sqrt(np.mean(err[m] ** 2))) for name, m in
           (("missed ground", ~objects & ~kept), ("under objects", objects))}
    # missed ground is mostly on convex crests (the opening cuts them): bounded, not exact
    assert rms["missed ground"] < 2.5 and rms["under objects"] < 1.5, rms


def test_the_cloth_has_decided_the_ground_of_steep_relief_within_its_40_steps():
    """ground.cloth_iterations (40): the cloth falls onto the detrended heights, so more steps settle
    it without moving the ground (500: 6 of 90,000 cells differ; 1 at 50 steps, 20 at 30); after 5
    the cloth is still falling (1,152 differ: the steps are used)."""
    grid, dsm, _, objects = rugged_scene()
    args = dict(max_object_m=60, cloth_resolution=2.0, rigidness=2, class_threshold=0.5)
    default, long = csf_ground(dsm, grid, **args), csf_ground(dsm, grid, **args, iterations=500)
    assert (default != long).sum() < 10, int((default != long).sum())
    early = csf_ground(dsm, grid, **args, iterations=5)
    assert (early != long).sum() > 500, int((early != long).sum())
    assert not (default & objects).any()


_CSF_IN_A_PROCESS = """
import sys, numpy as np
sys.path.insert(0, sys.argv[1])
from test_terrain import rugged_scene
from pipeline25d.stages.terrain.ground import csf_ground
grid, dsm, _, _ = rugged_scene(seed=3)
mask = csf_ground(dsm, grid, max_object_m=60, cloth_resolution=2.0, rigidness=2, class_threshold=0.5)
np.save(sys.argv[2], mask)
"""


def test_csf_ground_is_the_same_whatever_the_openmp_thread_count(tmp_path):
    """CSF's parallel spring pass races between threads; run with 1, 4 and 4 threads again (in fresh
    processes, as OMP_NUM_THREADS is read when OpenMP starts), the ground masks are identical."""
    import os
    import subprocess
    import sys
    from pathlib import Path

    masks = []
    for k, threads in enumerate((1, 4, 4)):
        out = tmp_path / f"mask{k}.npy"
        env = {**os.environ, "OMP_NUM_THREADS": str(threads)}
        subprocess.run([sys.executable, "-c", _CSF_IN_A_PROCESS, str(Path(__file__).parent), str(out)],
                       env=env, check=True, capture_output=True)
        masks.append(np.load(out))
    assert masks[0].sum() > 0.5 * masks[0].size                # a real ground mask, most of the scene
    for other in masks[1:]:
        assert np.array_equal(masks[0], other), int((masks[0] != other).sum())


def test_sites_are_exposed_clear_of_objects_and_of_their_lines_of_sight():
    """Flat ground with one 30 m tower; a camera in the south at 30° cannot see the ground
    north of the tower up to 30·cot 30° = 52 m: no site there is clear for that view, and with
    that view alone no site lies there at all."""
    n = 200
    grid = Grid.north_up(E0, N0 + n, 1.0, n, n)
    dsm = np.full((n, n), 10.0)
    tower = (slice(90, 110), slice(90, 110))                             # rows (north at 0), cols
    dsm[tower] = 40.0
    dtm = np.full((n, n), 10.0)
    rules = SiteRules(spacing=8.0, radius=1.0, clearance=2.0)
    sites = select_sites(dsm, dtm, grid, rules, [Perspective(0, 30), Perspective(0, 90)])
    x, y = sites["x"] - E0, sites["y"] - N0                              # tower covers x, y in [90, 110]
    assert len(x) > 400
    gap = np.maximum(np.maximum(90 - x, x - 110), np.maximum(90 - y, y - 110))
    assert gap.min() >= rules.radius + rules.clearance - 1.0             # 1 cell of rasterisation
    shadow = (x > 90 - rules.radius) & (x < 110 + rules.radius) & (y > 110) & (y < 110 + 30 / np.tan(np.radians(30)))
    assert shadow.sum() > 10 and not sites["clear"][shadow, 0].any() and sites["clear"][:, 1].all()
    assert sites["clear"][~shadow, 0].mean() > 0.95
    alone = select_sites(dsm, dtm, grid, rules, [Perspective(0, 30)])
    ax, ay = alone["x"] - E0, alone["y"] - N0
    assert len(ax) > 350 and alone["clear"].all()
    assert not ((ax > 90 - rules.radius) & (ax < 110 + rules.radius) & (ay > 110)
                & (ay < 110 + 30 / np.tan(np.radians(30)))).any()
    # one site per 8 m square, ids stable per square
    squares = set(zip(sites["square_col"].tolist(), sites["square_row"].tolist()))
    assert len(squares) == len(x)
    np.testing.assert_allclose(sites["z"], 10.0)


def _obs(n_gcp: int, n_check: int, offset: float, rng, z: float = 0.0) -> list[Observation]:
    rows = []
    for i in range(n_gcp + n_check):
        x, y = rng.uniform(0, 500, 2)
        noise = rng.normal(0, 0.02, 2)
        rows.append(Observation(f"g{i}", x, y, z, 0.0, 0.0, 0.0, "gcp" if i < n_gcp else "check",
                                x + offset + noise[0], y + noise[1], 1))
    return rows



def _plan_45():
    """A plane-projection plan of az045_el45 at 0.5 m (what choose() reads of a plan)."""
    return replace(grid_plan([(0, 0)], 0.5, 256), perspective=Perspective(45, 45))


def test_auto_warp_keeps_none_unless_a_warp_clearly_wins_and_never_looks_at_check_points():
    rng = np.random.default_rng(2)
    plan = _plan_45()
    gt = Grid.north_up(0.0, 500.0, 0.5, 1000, 1000)
    obs = _obs(60, 20, 0.0, rng, z=3.0)                                  # relief 3 m: the warp is considered
    assert choose(obs, plan, gt, "auto", 3)["method"] == "none"           # nothing to correct
    shifted = _obs(60, 20, 2.0, rng, z=3.0)
    best = choose(shifted, plan, gt, "auto", 3)
    assert best["method"] == "polynomial" and best["rmsd_px"] < 0.2      # a 4 px shift is corrected
    # corrupting the check points' observations changes their score, not the choice
    broken = [replace(r, map_x=r.map_x + 50) if r.role == "check" else r for r in shifted]
    again = choose(broken, plan, gt, "auto", 3)
    assert (again["method"], again["order"]) == (best["method"], best["order"]) and again["rmsd_m"] > 40


@pytest.mark.parametrize("n_check", [0, 1, MIN_CHECK_POINTS - 1])
def test_too_few_check_points_give_no_figure(n_check):
    rng = np.random.default_rng(3)
    res = residuals("none", 0, _obs(20, n_check, 0.0, rng), Grid.north_up(0.0, 500.0, 0.5, 1000, 1000), 0.5)
    assert res["rmsd_m"] is None and res["check_note"] == f"n/a ({n_check} check points)"


def test_a_large_tps_that_is_not_chosen_is_not_fitted_on_every_gcp():
    """TPS is cubic in the GCP count: with more GCPs than cross-validation samples, a TPS that
    loses is recorded with its CV score but no full fit; the polynomials are still scored."""
    from pipeline25d.stages.maps.warp import CV_MAX_GCPS

    rng = np.random.default_rng(4)
    plan = _plan_45()
    obs = _obs(CV_MAX_GCPS + 100, 30, 2.0, rng, z=3.0)
    choice = choose(obs, plan, Grid.north_up(0.0, 500.0, 0.5, 1000, 1000), "auto", 3)
    assert choice["method"] == "polynomial"                              # a shift: order 1 fits it
    tps = next(c for c in choice["candidates"] if c["method"] == "tps")
    assert tps["cv_rmsd_m"] is not None and tps["rmsd_m"] is None and "not scored" in tps["check_note"]
    assert all(c["rmsd_m"] is not None for c in choice["candidates"] if c["method"] == "polynomial")


def test_dtm_cells_beyond_the_search_reach_take_the_nearest_ground_not_a_nodata_value():
    """FillNodata works in float32: cells it leaves unfilled must not come back as −1e30."""
    seed = np.full((60, 80), np.nan)
    seed[:10, :10] = 3.0
    seed[50:, 70:] = 5.0
    dtm = interpolate_dtm(seed, search_cells=5)
    assert np.isfinite(dtm).all()
    assert dtm.min() == 3.0 and dtm.max() == 5.0
    assert dtm[0, 79] in (3.0, 5.0) and dtm[30, 40] in (3.0, 5.0)     # far from both: nearest value


def test_sites_closer_than_their_markers_reach_are_thinned_locally():
    """Spacing below the marker size: no two kept markers may touch in any view (the render
    would reject both), and removing sites far away does not change which ones are kept."""
    from scipy.spatial.distance import pdist

    n = 80
    grid = Grid.north_up(E0, N0 + n, 1.0, n, n)
    dsm = np.full((n, n), 5.0)
    rules = SiteRules(spacing=2.0, radius=1.0, clearance=0.0)
    views = [Perspective(0, 90), Perspective(45, 45)]
    sites = select_sites(dsm, dsm, grid, rules, views)
    reach = rules.radius + grid.res                                      # flat ground: no stretch
    assert pdist(np.column_stack([sites["x"], sites["y"]])).min() >= 2 * reach
    assert len(sites["x"]) > (n / (2 * reach + 2)) ** 2                 # thinning keeps a dense set
    # the western half alone keeps the same sites away from the cut
    half = dsm.copy()
    half[:, 40:] = np.nan
    west = select_sites(half, half, grid, rules, views)
    far = sites["x"] - E0 < 30
    kept = set(zip(sites["square_col"][far].tolist(), sites["square_row"][far].tolist()))
    kept_west = set(zip(west["square_col"].tolist(), west["square_row"].tolist()))
    assert kept <= kept_west


def test_object_edges_keep_the_ground_at_a_walls_foot_and_drop_what_rises_above_it():
    """On a 30 % slope: a block with a 0.4 m 'wall foot' ramp on its east side (what a LiDAR
    mesh gives, and what the filter may call ground). The ramp cells are dropped; the other
    cells along the block lie on the terrain plane and are kept, so the DTM under the block
    is interpolated from the ground right at its foot."""
    n = 60
    cols, rows = np.meshgrid(np.arange(n), np.arange(n))
    terrain = 0.3 * cols - 0.1 * rows
    dsm = terrain.copy()
    block = (slice(20, 40), slice(20, 40))
    dsm[block] += 12.0
    ramp = np.zeros((n, n), bool)
    ramp[20:40, 40] = True
    dsm[ramp] += 0.4
    ground = np.ones((n, n), bool)
    ground[block] = False
    kept = trim_object_edges(ground, dsm)
    assert not (kept & ramp).any()
    edge_on_terrain = ground & ~ramp & ~trim_object_edges(ground)          # the one-cell ring, ramp excluded
    assert edge_on_terrain.sum() > 60 and kept[edge_on_terrain].all()
    assert (trim_object_edges(ground) == (ground & ~edge_on_terrain & ~ramp)).all()   # without a DSM: all dropped


def test_a_rounded_hilltop_with_buildings_on_it_stays_ground():
    """A Gaussian hill whose top the lower envelope shaves by tens of metres (the cloth then sees
    it as an object), boxes on its top: the smooth hilltop is ground again, no roof is, and the
    DTM under the boxes follows the hill as closely as one filled from the exact ground (the
    roofs city's hilltop lay 31 m above the DTM before)."""

    n = 240
    grid = Grid.north_up(E0, N0 + n, 1.0, n, n)
    xs, ys = grid.cell_centres()
    r2 = (xs - E0 - 120) ** 2 + (ys - N0 - 120) ** 2
    terrain = 150 * np.exp(-r2 / (2 * 60.0 ** 2)) + 0.2 * (xs - E0)
    dsm = terrain.copy()
    objects = np.zeros(dsm.shape, bool)
    for r, c, size, h in ((100, 100, 14, 12.0), (125, 130, 18, 25.0), (95, 135, 10, 7.0), (135, 95, 16, 30.0)):
        dsm[r:r + size, c:c + size] = terrain[r:r + size, c:c + size].max() + h
        objects[r:r + size, c:c + size] = True
    top = (r2 < 40.0 ** 2) & ~objects
    shaved = terrain - lower_envelope(terrain, 1.0, 60)
    assert shaved[top].max() > 10                       # what the cloth alone would take for an object
    ground = csf_ground(dsm, grid, max_object_m=60, cloth_resolution=2.0, rigidness=2, class_threshold=0.5)
    assert not (ground & objects).any()
    assert ground[top].mean() > 0.97, ground[top].mean()
    kept = trim_object_edges(ground, dsm)
    dtm = interpolate_dtm(np.where(kept, dsm, np.nan), search_cells=30)
    err = (dtm - terrain)[objects]
    # as good under the boxes as the same interpolation from the exact ground (a convex top is
    # underestimated by any fill from its sides)
    exact = (interpolate_dtm(np.where(objects, np.nan, terrain), search_cells=30) - terrain)[objects]
    rms = lambda e: float(np.sqrt(np.mean(e ** 2)))  # noqa: E731
    assert rms(err) < rms(exact) + 0.2 and np.abs(err).max() < np.abs(exact).max() + 0.5, (rms(err), rms(exact))


def test_tree_crowns_without_walls_stay_objects_beside_a_hilltop_that_is_ground_again():
    """Tree crowns as a decimated or photogrammetric mesh has them: smooth mounds with no wall
    step (paraboloids 5-8 m high, 8-16 m across the rim, overlapping in a park), on flat ground
    and on a Gaussian hill's flank. The cloth takes none for ground and misses the hill's top;
    putting smooth pieces back must return the hilltop but no crown: a crown rises from the ground
    with a kink (its slope jumps from the ground's to 1.3-4 at its rim), the hillside goes on.
    Before the bend test 53 % of the crown cells here were ground again (on the Delft LiDAR mesh
    decimated to 10 %, 46 %: DTM p95 6.6 m against the LiDAR's ground returns, 0.24 m after)."""
    n = 260
    grid = Grid.north_up(E0, N0 + n, 1.0, n, n)
    xs, ys = grid.cell_centres()
    x, y = xs - E0, ys - N0
    r2 = (x - 170) ** 2 + (y - 130) ** 2
    terrain = 120 * np.exp(-r2 / (2 * 45.0 ** 2)) + 0.05 * x
    rng = np.random.default_rng(3)
    crowns = [(rng.uniform(15, 70), rng.uniform(15, 245), rng.uniform(4, 8), rng.uniform(5, 8)) for _ in range(18)]
    crowns += [(115, 60, 6.0, 6.0), (120, 200, 7.0, 7.0)]               # on the hill's flanks
    dsm = terrain.copy()
    for cx, cy, radius, h in crowns:
        d2 = (x - cx) ** 2 + (y - cy) ** 2
        inside = d2 < radius ** 2
        dsm[inside] = np.maximum(dsm[inside], terrain[inside].max() + h * (1 - d2[inside] / radius ** 2))
    crown = dsm - terrain > 1.0                 # a crown's rim lies within the cloth's 0.5 m of the ground
    top = (r2 < 25.0 ** 2) & (dsm == terrain)
    assert (terrain - lower_envelope(terrain, 1.0, 60))[top].max() > 10      # the cloth alone misses the top
    ground = csf_ground(dsm, grid, max_object_m=60, cloth_resolution=2.0, rigidness=2, class_threshold=0.5)
    assert crown.sum() > 2000 and not (ground & crown).any(), (int(crown.sum()), int((ground & crown).sum()))
    assert ground[top].mean() > 0.97, ground[top].mean()


def test_a_check_squares_site_and_so_the_dtms_holdout_do_not_depend_on_the_perspectives():
    """The tower scene seen from the south at 30°, then also from the north: the check squares'
    sites (chosen by the default perspectives, what the DTM leaves out) are the same places for
    both view sets, so adding a view cannot move the DTM (every tile would be drawn again); a
    check square whose site no view sees keeps its hole but gives no site; the GCP squares still
    take the option seen in the most of the config's views; with the default perspectives the
    sites are those chosen without check squares."""
    n = 200
    grid = Grid.north_up(E0, N0 + n, 1.0, n, n)
    dsm = np.full((n, n), 10.0)
    dsm[90:110, 90:110] = 40.0
    dtm = np.full((n, n), 10.0)
    rules = SiteRules(spacing=8.0, radius=1.0, clearance=2.0)

    def checks(cols, rows):
        return (np.asarray(cols) + np.asarray(rows)) % 2 == 0

    south = select_sites(dsm, dtm, grid, rules, [Perspective(0, 30)], check_square=checks)
    both = select_sites(dsm, dtm, grid, rules, [Perspective(0, 30), Perspective(180, 30)], check_square=checks)
    free = select_sites(dsm, dtm, grid, rules, [Perspective(0, 30)])
    def held_of(sites):
        return np.column_stack([sites[f"held_{k}"] for k in ("col", "row", "x", "y")])

    held = held_of(south)
    np.testing.assert_array_equal(held, held_of(both))
    assert len(held) > 200 and checks(held[:, 0], held[:, 1]).all()
    at = {(int(c), int(r)): (x, y) for c, r, x, y in held}
    for sites in (south, both):
        is_check = checks(sites["square_col"], sites["square_row"])
        assert is_check.sum() > 150 and (~is_check).sum() > 150
        for c, r, x, y in zip(sites["square_col"][is_check], sites["square_row"][is_check], sites["x"][is_check],
                              sites["y"][is_check]):
            assert at[int(c), int(r)] == (x, y)
    # north of the tower the south view sees no ground: those check squares are held out but give no site
    hidden = (held[:, 2] > E0 + 90) & (held[:, 2] < E0 + 110) & (held[:, 3] > N0 + 113) & (held[:, 3] < N0 + 150)
    south_squares = set(zip(south["square_col"].tolist(), south["square_row"].tolist()))
    assert hidden.sum() >= 3 and not any((int(c), int(r)) in south_squares for c, r in held[hidden, :2])
    # a GCP square's site is where the choice by views alone puts it
    chosen = {(c, r): (x, y) for c, r, x, y in zip(free["square_col"].tolist(), free["square_row"].tolist(),
                                                   free["x"].tolist(), free["y"].tolist())}
    gcp = ~checks(south["square_col"], south["square_row"])
    for c, r, x, y in zip(south["square_col"][gcp].tolist(), south["square_row"][gcp].tolist(),
                          south["x"][gcp].tolist(), south["y"][gcp].tolist()):
        assert chosen[c, r] == (x, y)
    default = [Perspective(az, el) for az, el in PRESETS["eight-45+nadir"]]
    plain, held_too = (select_sites(dsm, dtm, grid, rules, default, check_square=c) for c in (None, checks))
    for key in ("x", "y", "z", "square_col", "square_row", "clear"):
        np.testing.assert_array_equal(plain[key], held_too[key])
    is_check = checks(held_too["square_col"], held_too["square_row"])
    np.testing.assert_array_equal(np.column_stack([held_too["x"][is_check], held_too["y"][is_check]]),
                                  np.column_stack([held_too["held_x"], held_too["held_y"]]))


def test_check_squares_are_the_squares_whose_candidates_are_check_points():
    """The check squares known before any site is chosen are the squares whose candidates get the
    role check (the same hash of seed and id), a ``holdout`` share of them within binomial noise;
    each square is drawn once however many options it has."""
    from pipeline25d.stages.gcps import candidates_from_sites, check_squares

    rng = np.random.default_rng(7)
    cols, rows = rng.integers(-300, 300, 4000), rng.integers(-300, 300, 4000)
    sites = {"x": cols * 20.0 + 3, "y": rows * 20.0 + 5, "z": np.zeros(4000), "ground": np.zeros(4000),
             "sx": np.zeros(4000), "sy": np.zeros(4000), "square_col": cols, "square_row": rows}
    for holdout, seed in ((0.2, 0), (0.5, 11)):
        roles = np.array([c.role == "check" for c in candidates_from_sites(sites, holdout, seed)])
        drawn = check_squares(holdout, seed)(np.repeat(cols, 3).astype(float), np.repeat(rows, 3).astype(float))
        np.testing.assert_array_equal(drawn, np.repeat(roles, 3))
        assert abs(roles.mean() - holdout) < 4 * np.sqrt(holdout * (1 - holdout) / 4000)
