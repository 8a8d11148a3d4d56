"""Run time against error: a one-factor-at-a-time sweep around the default settings.

The defaults run once; then each factor (gsd, lod.max_error_px, render.samples, tile_size,
projection/warp) takes its other values one at a time, everything else at its default. Each
variant is a complete workflow run from scratch in its own folder (the runner of
:mod:`pipeline25d_lab.harness.bench`), and is measured: wall seconds and summed job-seconds,
check-point RMSD in pixels and metres (mean over the oblique views; gsd changes what a
pixel is, so compare gsd variants in metres), the LOD error actually drawn (the largest
over rendered chunks of the chosen level's measured error, in pixels), the map error (mean
absolute difference of its oblique maps from a reference run's: the defaults with the most
MSAA samples the renderer has (8, clamped to the GL limit: 4 on llvmpipe) and the finest
LOD, on the reference's grid; it sees antialiasing, LOD, gsd and seams, which
check points on exposed ground do not), tiles and sizes. The defaults run ``repeats`` times:
their median is their time and the spread the noise band, within which no run counts as
faster. :mod:`pipeline25d_lab.harness.sweep_report` marks the Pareto fronts and writes
``bench/<name>.json`` and ``bench/<name>.png``. Times compare runs of one sweep on one
machine, nothing more.

CLI::

    python -m pipeline25d_lab.harness.sweep [--scene delft:2x2] [--decimate 0.25] [--name sweep] [--quick] [--resume]

Scenes: ``delft:NXxNY`` (the Delft LiDAR mesh tiled by :func:`pipeline25d_lab.harness.bench.make_scene`),
``demo:SCALE`` (:mod:`pipeline25d_lab.scenes.demo`), ``rugged:SIZE`` (:mod:`pipeline25d_lab.scenes.rugged`, relief
0.3 × size).
"""

from __future__ import annotations

import argparse
import copy
import json
import logging
import os
import sys
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from pipeline25d.core.atomic import write_json
from pipeline25d.core.errors import ConfigError, WorkflowRunError
from pipeline25d.core.grid import Grid
from pipeline25d_lab.harness.bench import REPO, SOURCE, collect, make_scene, results_of, run_workflow

log = logging.getLogger(__name__)

# projection/warp options: name -> config overrides (the default, terrain, resolves from projection: auto)
METHODS = {"terrain": {"projection": "terrain"}, "plane": {"projection": "plane"},
           "plane-tps": {"projection": "plane", "warp": {"method": "tps"}}, "paper": {"projection": "paper"}}
FULL = {"gsd": (0.25, 0.5, 1.0), "lod.max_error_px": (0.25, 0.5, 1, 2, 4), "render.samples": (0, 2, 4, 8),
        "tile_size": (256, 512, 1024, 2048), "projection": tuple(METHODS)}
QUICK = {"gsd": (0.25, 0.5), "lod.max_error_px": (0.25, 0.5, 2, 4), "render.samples": (0, 4, 8),
         "tile_size": (512, 1024, 2048), "projection": ("terrain", "plane", "paper")}
SHORT = {"gsd": "gsd", "lod.max_error_px": "lod", "render.samples": "msaa", "tile_size": "tile", "projection": ""}
PERSPECTIVES = [{"azimuth": 0, "elevation": 90}, {"azimuth": 45, "elevation": 45}, {"azimuth": 225, "elevation": 30}]
GCP = {"spacing": 10, "holdout": 0.3}     # denser than the defaults: enough check points in the obliques
                                          # of one district
SCENE, QUICK_SCENE, DECIMATE = "delft:2x2", "delft:1x1", 0.25
REFERENCE = {"render": {"samples": 8}, "lod": {"max_error_px": 0.05}}     # the map error's reference run


@dataclass(frozen=True)
class Variant:
    """One run of the sweep: ``factor`` set to ``value`` by ``overrides``, the rest at the defaults."""

    name: str
    factor: str                  # "default" for the defaults themselves
    value: Any = None
    overrides: dict = field(default_factory=dict)


def nested(key: str, value: Any) -> dict:
    """{"a": {"b": value}} for key "a.b"."""
    head, _, rest = key.partition(".")
    return {head: nested(rest, value) if rest else value}


def merged(base: dict, overrides: dict) -> dict:
    """A deep copy of ``base`` with ``overrides`` merged in (dicts key by key, the rest replaced)."""
    out = copy.deepcopy(base)
    for k, v in overrides.items():
        out[k] = merged(out[k], v) if isinstance(v, dict) and isinstance(out.get(k), dict) else copy.deepcopy(v)
    return out


def factor_value(factor: str, config: dict) -> Any:
    """The value of ``factor`` in a validated config (projection: the method name of :data:`METHODS`)."""
    if factor == "projection":
        proj = config["projection"]
        if proj == "auto":
            proj = "plane" if config["terrain"] == "flat" else "terrain"
        method = config["warp"]["method"]
        return proj if method == "auto" or proj == "paper" else f"{proj}-{method}"
    value = config
    for part in factor.split("."):
        value = value[part]
    return value


def variants(levels: dict[str, tuple], base: dict) -> list[Variant]:
    """The defaults, then every other value of each factor in ``levels`` (the defaults are ``base``'s)."""
    from pipeline25d.config import validate_schema

    config = validate_schema(copy.deepcopy(base))
    out = [Variant("default", "default")]
    for factor, values in levels.items():
        default = factor_value(factor, config)
        for v in values:
            if v != default:
                name = f"{SHORT[factor]}-{v}" if SHORT[factor] else str(v)
                out.append(Variant(name, factor, v, METHODS[v] if factor == "projection" else nested(factor, v)))
    return out


def build_scene(spec: str, out_dir: Path, decimate: float | None = DECIMATE) -> dict:
    """Write scene ``spec`` (see the module doc) under ``out_dir``; return the sweep's base config."""
    kind, _, arg = spec.partition(":")
    unknown = ConfigError(f"sweep: unknown scene {spec!r} (delft:NXxNY, demo:SCALE or rugged:SIZE)")
    try:
        if kind == "delft":
            if not SOURCE.exists():
                raise ConfigError(f"sweep: {SOURCE} not found (the shared Delft data)")
            nx, ny = (int(v) for v in (arg or "2x2").lower().split("x"))
            paths = make_scene(out_dir / f"delft-{nx}x{ny}-{decimate or 1}", nx, ny, decimate)
            crs = "EPSG:28992"
        elif kind in ("demo", "rugged"):
            manifest, where = generated_city(kind, float(arg) if arg else None, out_dir)
            paths = {k: where / v for k, v in manifest["districts"].items()}
            crs = manifest["crs"]
        else:
            raise unknown
    except ConfigError:
        raise
    except ValueError:                      # a grid or size that is not a number
        raise unknown from None
    return {"scene": "sweep", "crs": crs, "terrain": "auto", "perspectives": PERSPECTIVES, "gcp": dict(GCP),
            "inputs": {k: {"path": str(p), "crs": crs} for k, p in sorted(paths.items())}}


def generated_city(kind: str, arg: float | None, out_dir: Path) -> tuple[dict, Path]:
    """A generated city (manifest, folder): the demo city at scale ``arg`` or the rugged one of edge ``arg`` m."""
    if kind == "demo":
        from pipeline25d_lab.scenes.demo import generate_demo_city

        scale = arg or 0.5
        where = out_dir / f"demo-{scale}"
        return generate_demo_city(where, seed=3, n_buildings=max(8, round(200 * scale ** 2)), scale=scale), where
    from pipeline25d_lab.scenes.rugged import generate_rugged_city

    size = arg or 500.0
    where = out_dir / f"rugged-{size:g}"
    return generate_rugged_city(where, size=size, relief=0.3 * size,
                                n_buildings=max(4, round(250 * (size / 2000) ** 2))), where


def lod_error_px(results: Path) -> float:
    """The largest geometric error (px) of the LOD level any rendered tile draws of any chunk."""
    from pipeline25d.stages.lod import lod_chunks
    from pipeline25d.stages.plan import read_plan

    errors = {(c.district, c.id): c.errors for c in lod_chunks(sorted((results / "lod").glob("*/index.json")))}
    worst = 0.0
    for plan_path in sorted((results / "plans").glob("*.json")):
        plan = read_plan(plan_path)
        for tile in plan.tiles:
            for chunk in tile.chunks:
                levels = errors[(chunk.district, chunk.id)]
                worst = max(worst, levels[min(chunk.lod, len(levels) - 1)] / plan.gsd)
    return worst


def map_error(results: Path, reference: Path, views: list[str]) -> float | None:
    """Mean absolute difference (grey levels, colour times alpha, over pixels either map covers)
    of ``results``' maps of ``views`` from ``reference``'s, each resampled (bilinear) onto the
    reference map's grid; None where a map is missing."""
    import numpy as np

    from pipeline25d.core.raster import gdal

    g = gdal()
    total, count = 0.0, 0
    for view in views:
        ref_path, run_path = reference / "maps" / f"{view}.tif", results / "maps" / f"{view}.tif"
        if not (ref_path.exists() and run_path.exists()):
            return None
        ref = g.Open(str(ref_path))
        grid = Grid.of_dataset(ref)
        run = g.Warp("", str(run_path), format="MEM", outputBounds=grid.bounds, width=grid.width, height=grid.height,
                     resampleAlg="bilinear", dstSRS=ref.GetProjection())
        a, b = (ds.ReadAsArray().astype(np.float64) for ds in (ref, run))
        a_rgb, b_rgb = a[:3] * a[3] / 255, b[:3] * b[3] / 255
        seen = (a[3] > 0) | (b[3] > 0)
        total += float(np.abs(a_rgb - b_rgb)[:, seen].sum()) / 3
        count += int(seen.sum())
    return round(total / count, 4) if count else None


def _mean(values: list[float | None]) -> float | None:
    found = [v for v in values if v is not None]
    return sum(found) / len(found) if found else None


def measure(workdir: Path, config: dict, wall: float, cores: int, reference: Path | None = None) -> dict:
    """The sweep's figures of a finished run (see the module doc); ``reference``: the reference
    run's results folder, for the map error."""
    bench = collect(workdir, config, wall, cores)
    results = results_of(workdir, config)
    report = json.loads((results / "report" / "report.json").read_text())
    views = [p for p in report["perspectives"] if p["elevation"] < 90] or report["perspectives"]
    rmsd_px, rmsd_m = _mean([p["rmsd_px"] for p in views]), _mean([p["rmsd_m"] for p in views])
    return {"wall_s": bench["wall_s"], "job_s": round(sum(s["seconds"] for s in bench["stages"].values()), 1),
            "rmsd_px": rmsd_px, "rmsd_m": rmsd_m, "rmsd_views": [p["id"] for p in views],
            "lod_px": round(lod_error_px(results), 4), "lod_px_bound": config["lod"]["max_error_px"],
            "map_mad": map_error(results, reference, [p["id"] for p in views]) if reference else None,
            "gsd": config["gsd"], "tile_size": config["tile_size"], "samples": config["render"]["samples"],
            "projection": report["projection"],
            "views": {p["id"]: {"warp": p["warp"]["method"], "rmsd_px": p["rmsd_px"], "rmsd_m": p["rmsd_m"],
                                "n_check": p["n_check"]} for p in report["perspectives"]},
            "tiles_rendered": bench["tiles_rendered"], "rendered_mpx": bench["rendered_mpx"], "jobs": bench["jobs"],
            "peak_rss_mb": bench["peak_rss_mb"], "stages": bench["stages"],
            "maps_mb": round(report["sizes"]["maps_bytes"] / 1e6, 2),
            "tms_mb": round(report["sizes"]["tms_bytes"] / 1e6, 2)}


def run_sweep(base: dict, plan: list[Variant], work: Path, cores: int = 2, resume: bool = False,
              repeats: int = 3) -> list[dict]:
    """Run every variant in ``work/runs/<variant>/``; return one row per variant.

    First, untimed, the reference run (the defaults with :data:`REFERENCE`), whose maps the map
    error compares with; it also pays the cold file caches and bytecode compilation the first
    run of a session pays (a first run took 37 s where runs of identical work took 31-33 s).
    The defaults run ``repeats`` times, spread through the sweep (:func:`schedule`;
    ``wall_runs``, ``wall_s`` is their median). A failed run gives a row with ``error`` and no
    figures. ``load_avg`` is the lowest and highest 1-minute load average seen before and after
    the variant's runs: above ``cores`` other work shared the cores and the times are inflated.
    With ``resume`` a variant whose row was written by an earlier sweep (``variant.json``) is
    not run again.
    """
    from statistics import median

    from pipeline25d.config import validate_schema

    ref_config = validate_schema(merged(base, REFERENCE))
    ref_dir = work / "runs" / "reference"
    reference: Path | None = results_of(ref_dir, ref_config)
    if not (resume and (reference / "report" / "report.json").exists()):
        log.info("sweep: reference run (most MSAA samples, finest LOD; untimed, also the warm-up)")
        try:
            run_workflow(ref_dir, ref_config, cores)
        except WorkflowRunError as exc:
            log.warning("sweep: the reference run failed, no map error: %s", exc)
            reference = None

    walls: dict[str, list[float]] = {}
    errors: dict[str, str] = {}
    loads: dict[str, list[float]] = {}
    configs = {v.name: validate_schema(merged(base, v.overrides)) for v in plan}
    todo = [(v, r) for v, r in schedule(plan, repeats) if not (resume and _saved(work, v).exists())]
    for k, (v, r) in enumerate(todo, 1):
        if v.name in errors:
            continue
        folder = work / "runs" / (v.name if r == 0 else f"{v.name}-repeat{r}")
        log.info("sweep %d/%d: %s%s", k, len(todo), v.name, f" (repeat {r})" if r else "")
        loads.setdefault(v.name, []).append(round(os.getloadavg()[0], 2))
        try:
            walls.setdefault(v.name, []).append(run_workflow(folder, configs[v.name], cores))
        except WorkflowRunError as exc:
            errors[v.name] = str(exc)
            log.warning("sweep: %s: %s", v.name, exc)
        loads[v.name].append(round(os.getloadavg()[0], 2))

    rows = []
    for v in plan:
        if resume and _saved(work, v).exists():
            rows.append(json.loads(_saved(work, v).read_text()))
            continue
        row: dict[str, Any] = {"name": v.name, "factor": v.factor, "value": v.value}
        if v.name in errors:
            row["error"] = errors[v.name]
        else:
            row |= measure(work / "runs" / v.name, configs[v.name], median(walls[v.name]), cores, reference)
            if len(walls[v.name]) > 1:
                row["wall_runs"] = [round(w, 1) for w in walls[v.name]]
        row["load_avg"] = [min(loads[v.name]), max(loads[v.name])]      # others' jobs skew the times
        write_json(_saved(work, v), row)
        rows.append(row)
    return rows


def _saved(work: Path, variant: Variant) -> Path:
    return work / "runs" / variant.name / "variant.json"


def schedule(plan: list[Variant], repeats: int) -> list[tuple[Variant, int]]:
    """The order of the runs: (variant, repeat), the defaults' repeats spread evenly through the
    sweep (first, then after every (number of other variants) / (repeats - 1) of them, the
    last at the end), so that their spread also holds whatever drifts while the sweep runs."""
    default = next((v for v in plan if v.factor == "default"), None)
    others = [v for v in plan if v is not default]
    if default is None:
        return [(v, 0) for v in others]
    after: dict[int, list[int]] = {}            # how many other variants run before each repeat
    for r in range(1, repeats):
        after.setdefault(round(r * len(others) / (repeats - 1)), []).append(r)
    order = [(default, 0)] + [(default, r) for r in after.get(0, [])]
    for k, v in enumerate(others, 1):
        order += [(v, 0)] + [(default, r) for r in after.get(k, [])]
    return order


def main(argv: list[str] | None = None) -> int:
    from pipeline25d.config import validate_schema
    from pipeline25d.geometry.perspectives import expand
    from pipeline25d_lab.harness.sweep_report import format_table, summarize, write_sweep

    ap = argparse.ArgumentParser(prog="python -m pipeline25d_lab.harness.sweep", description=__doc__.split("\n\n")[0])
    ap.add_argument("--scene", default=None, help=f"delft:NXxNY, demo:SCALE or rugged:SIZE (default {SCENE}, "
                                                  f"{QUICK_SCENE} with --quick)")
    ap.add_argument("--decimate", type=float, default=DECIMATE, help="delft: share of the mesh's triangles kept")
    ap.add_argument("--name", default="sweep", help="results: bench/<name>.json, .png and bench/<name>/runs/")
    ap.add_argument("--quick", action="store_true", help="fewer values per factor and a smaller default scene")
    ap.add_argument("--cores", type=int, default=2)
    ap.add_argument("--resume", action="store_true", help="keep the variants an interrupted sweep finished")
    ap.add_argument("--repeats", type=int, default=3, help="runs of the defaults (their spread is the noise band)")
    args = ap.parse_args(argv)
    logging.basicConfig(level=logging.INFO, format="%(asctime)s %(message)s", datefmt="%H:%M:%S")
    spec = args.scene or (QUICK_SCENE if args.quick else SCENE)
    work = REPO / "bench" / args.name
    try:
        base = build_scene(spec, work / "scene", args.decimate)
    except ConfigError as exc:
        raise SystemExit(str(exc)) from None
    levels = QUICK if args.quick else FULL
    rows = run_sweep(base, variants(levels, base), work, args.cores, args.resume, args.repeats)
    config = validate_schema(copy.deepcopy(base))
    meta = {"name": args.name, "scene": spec, "decimate": args.decimate if spec.startswith("delft") else None,
            "perspectives": [p.id for p in expand(base["perspectives"])], "cores": args.cores, "quick": args.quick,
            "defaults": {f: factor_value(f, config) for f in levels}, "base_config": base}
    summary = summarize(rows, meta)
    write_sweep(summary, REPO / "bench" / f"{args.name}.json", REPO / "bench" / f"{args.name}.png")
    print(format_table(summary))
    print(f"wrote bench/{args.name}.json and bench/{args.name}.png")
    return 0 if not any("error" in r for r in rows) else 1


if __name__ == "__main__":
    sys.exit(main())
