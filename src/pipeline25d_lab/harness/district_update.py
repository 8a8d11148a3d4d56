r"""A district update measured: one district of a city replaced, the workflow run again.

The scene is the benchmark's (:func:`pipeline25d_lab.harness.bench.make_scene`: the Delft LiDAR mesh
tiled into NX x NY districts) with a given DTM, as a city that keeps its terrain model apart
from its building models has: the DTM the workflow derives from the model once (``terrain:
auto``, a preparatory run not timed). With ``terrain: auto`` a district's new model also moves
the derived ground, and with it GCPs and tiles far beyond the district (the cloth filter
settles over the whole connected city). The workflow runs from scratch, then
one district's file is replaced by a new model of it (its mesh mirrored within its own
footprint: the same kind of content, every building moved) and the workflow runs again. The
update's wall time is compared with the full run's and with the district's area share; the
map tiles and web tiles that changed are listed by checksum; and a run from scratch of the
updated scene must give the same maps and web tiles, byte for byte. Writes
``bench/<name>.json``.

CLI::

    python -m pipeline25d_lab.harness.district_update --grid 4x3 --decimate 0.1 --gsd 0.125 \
        --district d01-01 --name districts
"""

from __future__ import annotations

import argparse
import json
import shutil
import sys
import time
from pathlib import Path

import numpy as np

from pipeline25d.core.atomic import write_text
from pipeline25d.core.errors import WorkflowRunError
from pipeline25d_lab.harness.bench import REPO, SOURCE, bench_config, make_scene, results_of, run_workflow
from pipeline25d_lab.harness.killtest import differences, file_digests, output_digests

BUDGET_OVER_SHARE = 0.20     # the bound: the district's area share of the full run + 20 % of it


def new_model(path: Path) -> None:
    """Replace a district's PLY by its mesh mirrored in x within its own footprint (winding kept)."""
    import trimesh

    mesh = trimesh.load(path, process=False)
    v = np.asarray(mesh.vertices, dtype=np.float64).copy()
    lo, hi = v[:, 0].min(), v[:, 0].max()
    v[:, 0] = lo + hi - v[:, 0]
    colors = getattr(mesh.visual, "vertex_colors", None)
    trimesh.Trimesh(v, np.asarray(mesh.faces)[:, ::-1], vertex_colors=colors, process=False).export(path)


def stage_seconds(logs: Path, since: float) -> dict[str, float]:
    """Job-seconds per stage of the jobs whose log was written after ``since`` (their time lines)."""
    from pipeline25d.core.logsetup import job_logs, read_job_record, wall_seconds

    out: dict[str, float] = {}
    for stage, log in job_logs(logs):
        seconds = wall_seconds(read_job_record(log)) if log.stat().st_mtime >= since else None
        if seconds is not None:
            out[stage] = round(out.get(stage, 0.0) + seconds, 1)
    return out


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(prog="python -m pipeline25d_lab.harness.district_update",
                                 description=__doc__.split("\n\n")[0])
    ap.add_argument("--grid", default="4x3", help="districts, NXxNY")
    ap.add_argument("--decimate", type=float, default=0.1, help="share of the source's triangles to keep")
    ap.add_argument("--district", default="d01-01", help="the district to replace")
    ap.add_argument("--gsd", type=float, default=0.125, help="fine enough that a district spans several render tiles")
    ap.add_argument("--perspectives", default="eight-45+nadir")
    ap.add_argument("--cores", type=int, default=2)
    ap.add_argument("--name", default="districts")
    args = ap.parse_args(argv)
    if not SOURCE.exists():
        raise SystemExit(f"district update: {SOURCE} not found (the shared Delft data)")
    nx, ny = (int(v) for v in args.grid.lower().split("x"))
    work = REPO / "bench" / args.name
    districts = make_scene(work / "scene", nx, ny, args.decimate)
    if args.district not in districts:
        raise SystemExit(f"district update: no district {args.district!r}; the grid has {', '.join(sorted(districts))}")
    # the scene as it was, rewritten from the source every time (an earlier update is undone)
    districts[args.district].unlink()
    districts = make_scene(work / "scene", nx, ny, args.decimate)
    config = bench_config(args.name, districts, args.gsd, args.perspectives)
    dtm = work / "scene" / "dtm.tif"
    if not dtm.exists():       # the workflow as far as the scene's DTM, not the maps
        derived = results_of(work / "derive", config) / "terrain" / "dtm.tif"
        run_workflow(work / "derive", config, args.cores, extra=[str(derived.relative_to(work / "derive"))])
        shutil.copyfile(derived, dtm)
    config["terrain"] = str(dtm)
    city = work / "city"
    full_s = run_workflow(city, config, args.cores)
    results = results_of(city, config)
    full_job_seconds = stage_seconds(results / "logs", 0.0)
    tiles_before, web_before = file_digests(results / "tiles", "*/*.tif"), file_digests(results / "tms", "**/*")
    new_model(districts[args.district])
    started = time.time()
    try:
        update_s = run_workflow(city, config, args.cores, from_scratch=False)
    except WorkflowRunError as exc:
        raise SystemExit(f"district update: the update run failed: {exc}") from None
    job_seconds = stage_seconds(results / "logs", started)
    tiles_after, web_after = file_digests(results / "tiles", "*/*.tif"), file_digests(results / "tms", "**/*")
    report = json.loads((results / "report" / "report.json").read_text())
    fresh = work / "fresh"
    run_workflow(fresh, config, args.cores)
    mismatch = differences(output_digests(results), output_digests(results_of(fresh, config)))
    share = 1 / len(districts)
    changed_tiles = sorted(k for k in tiles_after if tiles_after[k] != tiles_before.get(k))
    changed_web = sorted(k for k in web_after.keys() | web_before.keys() if web_after.get(k) != web_before.get(k))
    result = {
        "name": args.name, "grid": args.grid, "districts": len(districts), "district": args.district,
        "gsd": args.gsd, "full_job_seconds": full_job_seconds,
        "full_s": round(full_s, 1), "update_s": round(update_s, 1), "update_to_full": round(update_s / full_s, 3),
        "update_job_seconds": job_seconds, "terrain": "given DTM (derived from the model once)",
        "area_share": round(share, 3), "budget": round(share + BUDGET_OVER_SHARE, 3),
        "within_budget": update_s / full_s <= share + BUDGET_OVER_SHARE,
        "map_tiles": len(tiles_after), "map_tiles_changed": len(changed_tiles),
        "web_tiles": len(web_after), "web_tiles_changed": len(changed_web),
        "redone": report.get("updates"), "same_as_fresh_run": not mismatch, "differences": mismatch[:20],
        "map_tiles_changed_list": changed_tiles, "web_tiles_changed_list": changed_web,
    }
    write_text(REPO / "bench" / f"{args.name}.json", json.dumps(result, indent=1))
    print(json.dumps({k: v for k, v in result.items() if not k.endswith("_list") and k != "redone"}))
    return 0 if result["same_as_fresh_run"] else 1


if __name__ == "__main__":
    sys.exit(main())
