"""The paper's own case: the generated textured OAP3D city (:mod:`pipeline25d_lab.scenes.oap3d`) run end to end.

For each size (``quarter``, ``half``, ``full`` footprint of Dataset 2; ``tiny`` for tests) the
dataset is generated once into ``bench/oap3d-<size>/dataset`` (kept while its manifest matches)
and the workflow runs on its OSGB and on its 3D Tiles copy (9 maps at 25 cm by default), each
from scratch with the dataset evicted from the page cache first. Written to
``bench/textured-<sizes>.json`` and ``.md`` (``textured-<sizes>-<formats>`` when ``--formats`` names
fewer than both, so that one format's run does not overwrite the other's): per run the wall time,
per stage the job-seconds, rendered Mpx per job-second, peak RSS of a job (and of its largest child process), rchar and
read_bytes summed over the stage's jobs, and the dataset bytes read (the ingest jobs' read_bytes:
ingest is the stage that opens the dataset; the dataset's pages resident after the run check
that no other job read it) against the dataset's size and against the levels the gsd uses
(:func:`pipeline25d_lab.scenes.oap3d.levels_used`); how both are measured is
:mod:`pipeline25d_lab.harness.dataset_io`. With several sizes a scaling table gives the wall
seconds per rendered Mpx of each.

CLI::

    python -m pipeline25d_lab.harness.bench_textured --size quarter[,half,full] [--formats osgb,3dtiles] [--gsd 0.25]
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import time
from pathlib import Path

from pipeline25d.core.atomic import write_text
from pipeline25d.core.errors import WorkflowRunError
from pipeline25d_lab.harness.bench import REPO, collect, results_of, run_workflow
from pipeline25d_lab.harness.dataset_io import evict, resident, stage_resources
from pipeline25d_lab.scenes.oap3d import SRS, existing_manifest, level_of_file, levels_used

MB = 1024 * 1024


def generate(out: Path, size: str, seed: int) -> dict:
    """The dataset (:func:`~pipeline25d_lab.scenes.oap3d.generate_oap3d`), generated in a process of
    its own with single-threaded BLAS: its many small matrix products are several times slower
    with OpenBLAS threads spinning on a busy machine."""
    manifest = existing_manifest(out, size, seed)
    if manifest is None:
        env = {**os.environ, "OPENBLAS_NUM_THREADS": "1", "OMP_NUM_THREADS": "1", "MKL_NUM_THREADS": "1"}
        subprocess.run([sys.executable, "-m", "pipeline25d_lab.scenes.oap3d", str(out), "--size", size,
                        "--seed", str(seed)], env=env, check=True)
        manifest = existing_manifest(out, size, seed)
    if manifest is None:
        raise SystemExit(f"bench-textured: generating {out} left no complete manifest")
    return manifest


def read_probe(dataset: Path, manifest: dict, fmt: str, gsd: float) -> dict:
    """What reading one format at ``gsd`` as the ingest job does costs, without the workflow: the
    dataset evicted, :func:`pipeline25d.formats.load_district` in this process; its seconds,
    triangles, read_bytes and rchar (children included), the levels used and the pages resident after."""
    from pipeline25d.formats import load_district

    folder = dataset / manifest["formats"][fmt]["path"]
    evict(folder)
    before, t0 = _proc_io(), time.monotonic()
    mesh = load_district({"path": str(dataset / manifest["inputs"][fmt])}, SRS, max_geometric_error=gsd / 2, gsd=gsd)
    seconds, after = time.monotonic() - t0, _proc_io()
    used = levels_used(manifest, fmt, gsd)
    read = after["read_bytes"] - before["read_bytes"]
    return {"size": manifest["size"], "format": fmt, "gsd": gsd, "seconds": round(seconds, 1),
            "triangles": sum(p.n_triangles for p in mesh.parts), "read_bytes": read,
            "rchar": after["rchar"] - before["rchar"], "dataset_bytes": manifest["formats"][fmt]["bytes"],
            "levels_used": used, "read_over_levels_used": round(read / used["bytes"], 3),
            "resident_after": resident(folder, level_of_file)}


def _proc_io() -> dict[str, int]:
    with open("/proc/self/io") as fh:
        return {k: int(v) for k, v in (line.split(": ") for line in fh.read().splitlines())}


def textured_config(name: str, dataset: Path, manifest: dict, fmt: str, gsd: float, perspectives: str) -> dict:
    """The workflow config of one format of a generated dataset: the dataset as one input, as a user gives it."""
    return {"scene": name, "crs": SRS, "terrain": "auto", "gsd": gsd, "tile_size": 1024,
            "perspectives": perspectives, "gcp": {"spacing": 20},
            "inputs": {"city": {"path": str(dataset / manifest["inputs"][fmt])}}}


def run_format(work: Path, dataset: Path, manifest: dict, fmt: str, args) -> dict:
    """One whole run on one format of the dataset; its figures (see the module docstring)."""
    config = textured_config(f"textured-{manifest['size']}-{fmt}", dataset, manifest, fmt, args.gsd, args.perspectives)
    folder = dataset / manifest["formats"][fmt]["path"]
    evict(folder)
    wall = run_workflow(work, config, args.cores)
    result = collect(work, config, wall, args.cores)
    io = stage_resources(results_of(work, config) / "logs")
    return summarise(result, io, resident(folder, level_of_file), manifest, fmt, args.gsd)


def summarise(result: dict, io: dict[str, dict], touched: dict, manifest: dict, fmt: str, gsd: float) -> dict:
    """The figures of one run from :func:`~pipeline25d_lab.harness.bench.collect`'s ``result``, the
    jobs' resources lines per stage ``io``, the dataset's resident pages after the run ``touched``."""
    mpx = result["rendered_mpx"]
    stages = {}
    for name, s in result["stages"].items():
        r = io.get(name, {})
        stages[name] = {**s, "mpx_per_job_s": round(mpx / s["seconds"], 2) if s["seconds"] else None,
                        "peak_rss_mb_job": r.get("peak_rss_mb"), "peak_rss_mb_child": r.get("child_peak_rss_mb"),
                        "rchar_mb": round(r.get("rchar", 0) / MB, 1),
                        "read_bytes_mb": round(r.get("read_bytes", 0) / MB, 1)}
    size = manifest["formats"][fmt]["bytes"]
    used = levels_used(manifest, fmt, gsd)
    read = io.get("ingest", {}).get("read_bytes", 0)      # the stage that opens the dataset
    return {"format": fmt, "size": manifest["size"], "wall_s": result["wall_s"], "jobs": result["jobs"],
            "rendered_mpx": mpx, "wall_s_per_mpx": round(result["wall_s"] / mpx, 3) if mpx else None,
            "peak_rss_mb_job": max((s["peak_rss_mb_job"] or 0) for s in stages.values()),
            "dataset": {"bytes": size, "levels_used": used, "read_bytes": read,
                        "read_bytes_all_jobs": sum(r.get("read_bytes", 0) for r in io.values()),
                        "read_over_dataset": round(read / size, 4),
                        "read_over_levels_used": round(read / used["bytes"], 3),
                        "resident_after_run": touched,
                        "resident_over_levels_used": round(touched["bytes"] / used["bytes"], 3),
                        "rchar_all_jobs": sum(r.get("rchar", 0) for r in io.values())},
            "stages": stages, "check_rmsd_px": result["check_rmsd_px"]}


def markdown(report: dict) -> str:
    """The report's tables: per run the stages, then the dataset bytes, then scaling."""
    lines = [f"# Textured OAP3D bench (gsd {report['gsd']} m, {report['perspectives']}, {report['cores']} cores)", ""]
    for run in report["runs"]:
        d = run["dataset"]
        lines += [f"## {run['size']} / {run['format']}: {run['wall_s']} s wall, {run['jobs']} jobs, "
                  f"{run['rendered_mpx']} Mpx rendered, peak RSS of a job {run['peak_rss_mb_job']} MB", "",
                  "| stage | jobs | job-s | Mpx/job-s | peak RSS job MB | child MB | rchar MB | read_bytes MB |",
                  "|---|---|---|---|---|---|---|---|"]
        for name, s in run["stages"].items():
            lines.append(f"| {name} | {s['jobs']} | {s['seconds']} | {s['mpx_per_job_s']} | {s['peak_rss_mb_job']} | "
                         f"{s['peak_rss_mb_child']} | {s['rchar_mb']} | {s['read_bytes_mb']} |")
        used = d["levels_used"]
        lines += ["", f"Dataset {d['bytes'] / MB:.1f} MB; levels used at this gsd (level {used['level']}, texel "
                      f"{used['texel_m']:.3f} m, and what a reader must open above it) {used['bytes'] / MB:.1f} MB; "
                      f"read from storage by the ingest jobs {d['read_bytes'] / MB:.1f} MB = "
                      f"{d['read_over_dataset']:.3f} "
                      f"of the dataset (all jobs: {d['read_bytes_all_jobs'] / MB:.1f} MB), "
                      f"{d['read_over_levels_used']} x the levels used; resident after the run "
                      f"{d['resident_after_run']['bytes'] / MB:.1f} MB ({d['resident_over_levels_used']} x), by level "
                      + ", ".join(f"{k}: {v / MB:.1f} MB" for k, v in d["resident_after_run"]["by_level"].items())
                      + f"; rchar of all jobs {d['rchar_all_jobs'] / MB:.1f} MB.", ""]
    if len({r["size"] for r in report["runs"]}) > 1:
        lines += ["## Scaling", "", "| size | format | wall s | Mpx | wall s per Mpx | dataset MB | read MB |",
                  "|---|---|---|---|---|---|---|"]
        for r in report["runs"]:
            lines.append(f"| {r['size']} | {r['format']} | {r['wall_s']} | {r['rendered_mpx']} | "
                         f"{r['wall_s_per_mpx']} | "
                         f"{r['dataset']['bytes'] / MB:.1f} | {r['dataset']['read_bytes'] / MB:.1f} |")
    return "\n".join(lines) + "\n"


DEFAULT_FORMATS = ("osgb", "3dtiles")


def report_name(sizes: list[str], formats: list[str]) -> str:
    """The report's file name under ``bench/`` (no suffix): the sizes, and the formats when not both."""
    name = f"textured-{'-'.join(sizes)}"
    return name if sorted(formats) == sorted(DEFAULT_FORMATS) else f"{name}-{'-'.join(formats)}"


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(prog="python -m pipeline25d_lab.harness.bench_textured",
                                 description=__doc__.split("\n\n")[0])
    ap.add_argument("--size", default="full", help="comma-separated: tiny, quarter, half, full")
    ap.add_argument("--formats", default=",".join(DEFAULT_FORMATS))
    ap.add_argument("--gsd", type=float, default=0.25)
    ap.add_argument("--perspectives", default="eight-45+nadir")
    ap.add_argument("--cores", type=int, default=2)
    ap.add_argument("--seed", type=int, default=7)
    ap.add_argument("--generate-only", action="store_true", help="build the datasets and stop")
    ap.add_argument("--read-only", action="store_true",
                    help="only read each format at the gsd as ingest does (bytes read, seconds): "
                         "bench/textured-read-<sizes>.json")
    args = ap.parse_args(argv)
    sizes, formats = args.size.split(","), args.formats.split(",")
    runs = []
    for size in sizes:
        work = REPO / "bench" / f"oap3d-{size}"
        manifest = generate(work / "dataset", size, args.seed)
        print(json.dumps({"size": size, "generation_s": manifest["generation_s"], **manifest["totals"]}))  # noqa: T201
        if args.generate_only:
            continue
        if args.read_only:
            runs += [read_probe(work / "dataset", manifest, fmt, args.gsd) for fmt in formats]
            print(json.dumps(runs[-len(formats):]))  # noqa: T201
            continue
        for fmt in formats:
            try:
                runs.append(run_format(work / fmt, work / "dataset", manifest, fmt, args))
            except WorkflowRunError as exc:
                raise SystemExit(f"bench-textured: {exc}") from None
    if args.generate_only:
        return 0
    if args.read_only:
        write_text(REPO / "bench" / f"textured-read-{'-'.join(sizes)}.json", json.dumps(runs, indent=1))
        return 0
    report = {"gsd": args.gsd, "perspectives": args.perspectives, "cores": args.cores, "runs": runs}
    name = report_name(sizes, formats)
    write_text(REPO / "bench" / f"{name}.json", json.dumps(report, indent=1))
    write_text(REPO / "bench" / f"{name}.md", markdown(report))
    print(markdown(report))  # noqa: T201
    return 0


if __name__ == "__main__":
    sys.exit(main())
