"""A reproducible city-scale benchmark: a real mesh tiled into districts, run end to end.

The Delft LiDAR surface mesh (264 × 229 m, 484k triangles) is copied into an nx × ny grid
of district files, every other copy mirrored in x and/or y so that neighbours differ and
their edges meet; 12 × 10 copies cover about 3.17 × 2.29 km, the paper's Dataset 2
footprint. ``decimate`` keeps that share of each copy's triangles (fast-simplification),
e.g. 0.1 for ~5.8 M triangles instead of ~58 M. The workflow then runs with terrain from
the model (no DTM given) and every result is written to ``bench/<name>.json``: wall time,
per-stage job-seconds and peak RSS (from the jobs' logs), tiles, jobs, map
megapixels and Mpx/s. Times are for comparing runs on one machine, not across machines.

CLI::

    python -m pipeline25d_lab.harness.bench --grid 12x10 --decimate 0.1 --name dataset2 [--gsd 0.25]
"""

from __future__ import annotations

import argparse
import json
import os
import re
import resource
import shutil
import subprocess
import sys
import time
from pathlib import Path
from typing import Mapping, Sequence

import numpy as np
import yaml

from pipeline25d.config import validate_schema
from pipeline25d.core.atomic import write_text
from pipeline25d.core.errors import WorkflowRunError
from pipeline25d.core.logsetup import job_logs, read_job_record, wall_seconds

REPO = Path(__file__).resolve().parents[3]
SOURCE = REPO.parent / "shared" / "data" / "delft" / "delft_dsm_mesh.ply"


def make_scene(out_dir: Path, nx: int, ny: int, decimate: float | None = None, source: Path = SOURCE,
               spread: float = 1.0, stretch: float = 1.0) -> dict:
    """Write the district meshes into ``out_dir`` and return {district: path}.

    ``spread`` is the grid pitch in district sizes: 1 packs the copies edge to edge, larger
    values leave empty land between them (a sparse scene with the same content). ``stretch``
    scales x and y (not z): a coarse mesh over a large area.
    """
    import trimesh

    from pipeline25d.core.mesh import MeshPart
    from pipeline25d.stages.lod import simplify_part

    mesh = trimesh.load(source, process=False)
    verts = np.asarray(mesh.vertices, dtype=np.float64)
    faces = np.asarray(mesh.faces)
    colors = getattr(mesh.visual, "vertex_colors", None)
    if decimate:
        part = simplify_part(MeshPart(vertices=verts, faces=faces, colors=colors), 1.0 - decimate)
        verts, faces, colors = part.vertices, part.faces, part.colors
    lo = verts.min(axis=0)
    verts[:, :2] = lo[:2] + (verts[:, :2] - lo[:2]) * stretch
    hi = verts.max(axis=0)
    size = hi - lo
    out_dir.mkdir(parents=True, exist_ok=True)
    districts = {}
    for i in range(nx):
        for j in range(ny):
            v = verts.copy()
            f = faces.copy()
            if i % 2:
                v[:, 0] = lo[0] + hi[0] - v[:, 0]
            if j % 2:
                v[:, 1] = lo[1] + hi[1] - v[:, 1]
            if (i + j) % 2:                           # one mirror flips the winding: flip it back
                f = f[:, ::-1]
            v[:, 0] += i * size[0] * spread
            v[:, 1] += j * size[1] * spread
            name = f"d{i:02d}-{j:02d}"
            path = out_dir / f"{name}.ply"
            if not path.exists():
                trimesh.Trimesh(v, f, vertex_colors=colors, process=False).export(path)
            districts[name] = path
    return districts


def bench_config(name: str, districts: dict, gsd: float, perspectives: str, samples: int | None = None) -> dict:
    """The bench's config; ``samples``: the colour pass's MSAA samples (None: the schema's default)."""
    return {"scene": name, "crs": "EPSG:28992", "terrain": "auto", "gsd": gsd, "tile_size": 1024,
            "perspectives": perspectives, "gcp": {"spacing": 20},
            **({"render": {"samples": samples}} if samples is not None else {}),
            "inputs": {k: {"path": str(p), "crs": "EPSG:28992"} for k, p in districts.items()}}


def results_of(workdir: Path, config: dict) -> Path:
    """The results folder of ``config``'s scene in ``workdir``."""
    return workdir / "results" / config["scene"]


def workflow_command(workdir: Path, cores: int | None = 2, configfile: Path | None = None) -> list[str]:
    """Snakemake on this repository's workflow in ``workdir``, with ``configfile`` (default
    ``workdir/config.yaml``); ``cores`` None leaves ``-j`` to the profiles."""
    return [sys.executable, "-m", "snakemake", "--snakefile", str(REPO / "Snakefile"), "--directory", str(workdir),
            "--configfile", str(configfile or workdir / "config.yaml"), *([f"-j{cores}"] if cores else [])]


def run_workflow(workdir: Path, config: dict, cores: int | None = 2, from_scratch: bool = True, *,
                 extra: Sequence[str] = (), env: Mapping[str, str] | None = None) -> float:
    """Run the whole workflow on ``config`` in ``workdir``; return its wall seconds.

    ``from_scratch``: earlier results of the scene are removed first, so a re-run is timed
    in full; otherwise the run updates them (as a user's re-run does). ``extra`` arguments
    are added to the Snakemake command (e.g. a profile), which runs with ``env`` (default:
    this process's). Raises :class:`WorkflowRunError` naming the Snakemake log when the run
    fails.
    """
    workdir.mkdir(parents=True, exist_ok=True)
    if from_scratch:
        for stale in (results_of(workdir, config), workdir / ".snakemake"):
            shutil.rmtree(stale, ignore_errors=True)
    write_text(workdir / "config.yaml", yaml.safe_dump(config))
    cmd = workflow_command(workdir, cores) + list(extra)
    before = resource.getrusage(resource.RUSAGE_CHILDREN)
    t0 = time.monotonic()
    proc = subprocess.run(cmd, capture_output=True, text=True, env=env)
    wall = time.monotonic() - t0
    after = resource.getrusage(resource.RUSAGE_CHILDREN)
    write_text(workdir / "snakemake.log", proc.stdout + proc.stderr)
    cpu = (after.ru_utime + after.ru_stime) - (before.ru_utime + before.ru_stime)
    write_text(workdir / RUN_CPU, json.dumps({"cpu_s": round(cpu, 2), "wall_s": round(wall, 2)}))
    if proc.returncode != 0:
        raise WorkflowRunError(f"the workflow failed, see {workdir / 'snakemake.log'}")
    return wall


#: beside snakemake.log: the CPU seconds of the whole run (Snakemake, its jobs and their children)
RUN_CPU = "snakemake.cpu.json"


def job_cpu(results: Path) -> dict[str, float]:
    """CPU seconds per stage, each job's own and its children's, from the ``job time:`` line of
    every job log under ``results/logs`` (exact, unlike a sampled figure)."""
    out: dict[str, float] = {}
    for stage, log in job_logs(results / "logs"):
        rec = read_job_record(log)
        if "cpu_s" in rec:
            out[stage] = round(out.get(stage, 0.0) + rec["cpu_s"] + rec["children_cpu_s"], 2)
    return out


def job_seconds(log: Path) -> float:
    """A job's wall seconds (start-up and the rule's function) from its log's time line."""
    seconds = wall_seconds(read_job_record(log))
    if seconds is None:
        raise WorkflowRunError(f"{log}: no job time line (the job did not finish)")
    return seconds


def run_cpu(workdir: Path, results: Path) -> dict | None:
    """The run's CPU seconds: all of it, its jobs' (:func:`job_cpu`) and the rest, Snakemake's own
    (scheduling, DAG updates, output checks); None for a run not timed by :func:`run_workflow`."""
    path = workdir / RUN_CPU
    if not path.exists():
        return None
    total = json.loads(path.read_text())["cpu_s"]
    jobs = job_cpu(results)
    return {"total_s": total, "jobs_s": round(sum(jobs.values()), 2),
            "snakemake_s": round(total - sum(jobs.values()), 2), "stages": jobs}


def collect(workdir: Path, config: dict, wall: float, cores: int = 2) -> dict:
    """The figures of a finished run: wall time, per-stage job-seconds and RSS, tiles, check RMSD, sizes."""
    from pipeline25d.publish.report import stage_timings

    results = results_of(workdir, config)
    report = json.loads((results / "report" / "report.json").read_text())
    stages = {k: {"jobs": v["jobs"], "seconds": round(v["seconds"], 2), "max_rss_mb": round(v["max_rss_mb"], 1)}
              for k, v in stage_timings(results).items()}
    tiles = sum(p["tiles_rendered"] for p in report["perspectives"])
    mpx = tiles * config["tile_size"] ** 2 / 1e6
    return {"name": config["scene"], "cores": cores, "wall_s": round(wall, 1), "districts": len(config["inputs"]),
            "gsd": config["gsd"], "perspectives": len(report["perspectives"]), "tiles_rendered": tiles,
            "rendered_mpx": round(mpx, 1), "render_mpx_per_job_s": round(mpx / stages["render"]["seconds"], 2),
            "jobs": sum(s["jobs"] for s in stages.values()), "stages": stages,
            "peak_rss_mb": max(s["max_rss_mb"] for s in stages.values()),
            "check_rmsd_px": {p["id"]: p["rmsd_px"] for p in report["perspectives"]},
            "check_rmsd_m": {p["id"]: p["rmsd_m"] for p in report["perspectives"]},
            "sizes": report["sizes"], "cpu": run_cpu(workdir, results)}


def render_against_plain_loop(results: Path, pid: str, samples: int) -> dict:
    """Render job-seconds per tile of one perspective beside a plain moderngl loop over the same
    tiles in one process (:mod:`pipeline25d_lab.harness.render_reference`), measured in the same run."""
    from pipeline25d.stages.plan import read_plan
    from pipeline25d_lab.harness.render_reference import plain_loop_seconds

    plan = results / "plans" / f"{pid}.json"
    n = len(read_plan(plan).tiles)
    job_s = sum(job_seconds(log) for log in sorted((results / "logs" / "render" / pid).glob("*.log")))
    plain = plain_loop_seconds(plan, results / "lod", samples)
    return {"perspective": pid, "tiles": n, "job_s_per_tile": round(job_s / n, 4),
            "plain_loop_s_per_tile": plain["per_tile_s"], "ratio": round(job_s / n / plain["per_tile_s"], 2)}


def rule_threads(workdir: Path, rule: str) -> int:
    """The threads Snakemake gave ``rule``'s jobs in the last run (its log names them when more than one)."""
    found = re.findall(rf"rule {rule}:\n(?:    .*\n)*?    threads: (\d+)", (workdir / "snakemake.log").read_text())
    return int(found[-1]) if found else 1


def tms_against_gdal2tiles_default(results: Path, pid: str, work: Path, config: dict) -> dict:
    """The workflow's web-tile job of one map beside gdal2tiles with its defaults (``--xyz``, one
    process, same zoom levels) on the same COG, timed back to back here on an otherwise idle machine.

    ``job_alone_s``: the job's own work (:func:`pipeline25d.stages.tiles.web.tms` on the map, and on
    its id map where there is one) with the workers it took in the run (its log's ``workers:``, see
    :func:`pipeline25d.core.cores.job_workers`; else the rule's threads), against ``job_s_in_run``
    (its seconds in the run, from its log): what running beside other jobs cost it. ``cut_s``: the map's
    cut alone on 1 and on 2 processes, each against gdal2tiles (``speed_up``). Each cut runs as the job
    would, in a process of its own with a job's environment (:func:`pipeline25d.jobhost.job_env`) and
    the host's modules imported, timed from the call; gdal2tiles runs as a user would, with this
    process's environment."""
    import shutil

    from pipeline25d.jobhost import job_env

    cog, ids = results / "maps" / f"{pid}.tif", results / "maps" / f"{pid}.ids.tif"
    zooms = sorted(int(z.name) for z in (results / "tms" / pid).iterdir() if z.name.isdigit())
    zoom = f"{zooms[0]}-{zooms[-1]}"
    cfg = validate_schema(config)["tms"]
    workers = re.findall(r"workers: (\d+)", (results / "logs" / "tms" / f"{pid}.log").read_text())
    threads = int(workers[-1]) if workers else rule_threads(results.parents[1], "tms")
    out = work / "tms-compare"

    def timed(source: Path, processes: int, tile_format: str, quality: int) -> float:
        """Seconds of the cut in a process of its own with a job's environment (its malloc) and the
        modules a job finds imported (the host's), from the call."""
        shutil.rmtree(out, ignore_errors=True)
        code = ("import importlib, time\nfrom pipeline25d.jobhost import PRELOAD\n"
                "for name in PRELOAD:\n    importlib.import_module(name)\n"
                "from pipeline25d.stages.tiles.web import tms\nt0 = time.monotonic()\n"
                f"tms({str(source)!r}, {zoom!r}, {str(out / 'ours')!r}, processes={processes}, "
                f"tile_format={tile_format!r}, quality={quality}, webp_method={cfg['webp_method']})\n"
                "print(time.monotonic() - t0)\n")
        proc = subprocess.run([sys.executable, "-c", code], env=job_env(os.environ), capture_output=True, text=True,
                              check=True)
        return float(proc.stdout.split()[-1])

    cut = {n: timed(cog, n, cfg["format"], cfg["quality"]) for n in (1, 2)}
    alone = cut[threads] if threads in cut else timed(cog, threads, cfg["format"], cfg["quality"])
    if ids.exists():
        alone += timed(ids, threads, "ids", 0)
    shutil.rmtree(out, ignore_errors=True)
    t0 = time.monotonic()
    subprocess.run([sys.executable, "-m", "osgeo_utils.gdal2tiles", "-q", "--xyz", "-z", zoom, str(cog),
                    str(out / "default")], check=True)
    default_s = time.monotonic() - t0
    shutil.rmtree(out, ignore_errors=True)
    in_run = job_seconds(results / "logs" / "tms" / f"{pid}.log")
    return {"perspective": pid, "zoom": zoom, "workers": threads, "job_s_in_run": round(in_run, 2),
            "job_alone_s": round(alone, 2), "in_run_to_alone": round(in_run / alone, 2),
            "cut_s": {str(n): round(v, 2) for n, v in cut.items()}, "gdal2tiles_default_s": round(default_s, 2),
            "speed_up": {str(n): round(default_s / v, 2) for n, v in cut.items()}}


def against_gdal2tiles(result: dict) -> dict:
    """The run's wall time in units of gdal2tiles' default cut of one of its maps (measured in the same
    run, ``tms_vs_gdal2tiles_default``), and the least it could be on its cores: all the run's CPU
    seconds packed without a gap, a bound no schedule beats (None for a run without its CPU figure)."""
    g2t = result["tms_vs_gdal2tiles_default"]["gdal2tiles_default_s"]
    cpu = (result.get("cpu") or {}).get("total_s")
    return {"wall": round(result["wall_s"] / g2t, 2),
            "cpu_packed": round(cpu / result["cores"] / g2t, 2) if cpu else None}


def logged_wall(workdir: Path) -> float:
    """Wall seconds of the last run in ``workdir``, from the "Elapsed time: H:MM:SS" line Snakemake logs."""
    import re

    log = workdir / "snakemake.log"
    found = re.findall(r"Elapsed time: (\d+):(\d+):([\d.]+)", log.read_text()) if log.exists() else []
    if not found:
        raise WorkflowRunError(f"no finished run logged in {log}")
    h, m, s = found[-1]
    return int(h) * 3600 + int(m) * 60 + float(s)


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(prog="python -m pipeline25d_lab.harness.bench", description=__doc__.split("\n\n")[0])
    ap.add_argument("--grid", default="2x2", help="districts, NXxNY (12x10 = the paper's Dataset 2 footprint)")
    ap.add_argument("--decimate", type=float, default=None, help="share of the source's triangles to keep")
    ap.add_argument("--gsd", type=float, default=0.25)
    ap.add_argument("--perspectives", default="eight-45+nadir")
    ap.add_argument("--name", default=None)
    ap.add_argument("--cores", type=int, default=2)
    ap.add_argument("--spread", type=float, default=1.0,
                    help="grid pitch in district sizes; > 1 leaves empty land between districts and also runs "
                         "the packed twin (spread 1) to give the sparse : packed wall-time ratio")
    ap.add_argument("--stretch", type=float, default=1.0,
                    help="scale each district's x and y (not z) by this: a coarse mesh over a large area")
    ap.add_argument("--samples", type=int, choices=(0, 2, 4, 8), default=None,
                    help="the colour pass's MSAA samples (render.samples; default: the schema's)")
    ap.add_argument("--collect", action="store_true",
                    help="collect the figures of the last finished run again instead of running "
                         "(wall time from its log)")
    args = ap.parse_args(argv)
    nx, ny = (int(v) for v in args.grid.lower().split("x"))
    name = args.name or f"delft{nx}x{ny}"
    if not SOURCE.exists():
        raise SystemExit(f"bench: {SOURCE} not found (the shared Delft data)")
    if args.spread > 1:
        return sparse_against_packed(name, nx, ny, args)
    work = REPO / "bench" / name
    districts = make_scene(work / "scene", nx, ny, args.decimate, stretch=args.stretch)
    config = bench_config(name, districts, args.gsd, args.perspectives, args.samples)
    try:
        wall = logged_wall(work) if args.collect else run_workflow(work, config, args.cores)
    except WorkflowRunError as exc:
        raise SystemExit(f"bench: {exc}") from None
    result = collect(work, config, wall, args.cores)
    result["decimate"], result["stretch"] = args.decimate, args.stretch
    oblique = next(p for p in sorted(result["check_rmsd_px"]) if not p.endswith("el90"))
    samples = validate_schema(config)["render"]["samples"]          # the run's own MSAA setting
    result["render_vs_plain_loop"] = render_against_plain_loop(work / "results" / name, oblique, samples)
    result["tms_vs_gdal2tiles_default"] = tms_against_gdal2tiles_default(work / "results" / name, oblique, work, config)
    result["against_gdal2tiles"] = against_gdal2tiles(result)
    write_text(REPO / "bench" / f"{name}.json", json.dumps(result, indent=1))
    print(json.dumps({k: result[k] for k in ("wall_s", "tiles_rendered", "jobs", "peak_rss_mb", "render_vs_plain_loop",
                                      "tms_vs_gdal2tiles_default", "against_gdal2tiles")}))
    return 0


def sparse_against_packed(name: str, nx: int, ny: int, args) -> int:
    """Run the packed twin (spread 1) and then the sparse scene, back to back: bench/<name>.json."""
    runs = {}
    for label, spread in (("packed", 1.0), ("sparse", args.spread)):
        work = REPO / "bench" / f"{name}-{label}"
        districts = make_scene(work / "scene", nx, ny, args.decimate, spread=spread)
        config = bench_config(f"{name}-{label}", districts, args.gsd, args.perspectives)
        try:
            wall = logged_wall(work) if args.collect else run_workflow(work, config, args.cores)
        except WorkflowRunError as exc:
            raise SystemExit(f"bench: {exc}") from None
        runs[label] = {**collect(work, config, wall, args.cores), "spread": spread, "decimate": args.decimate}
    result = {"name": name, "sparse_to_packed_wall": round(runs["sparse"]["wall_s"] / runs["packed"]["wall_s"], 2),
              **runs}
    write_text(REPO / "bench" / f"{name}.json", json.dumps(result, indent=1))
    print(json.dumps({"sparse_to_packed_wall": result["sparse_to_packed_wall"],
                      **{k: {"wall_s": v["wall_s"], "tiles_rendered": v["tiles_rendered"]} for k, v in runs.items()}}))
    return 0


if __name__ == "__main__":
    sys.exit(main())
