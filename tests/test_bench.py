"""The benchmark scene: copies of a mesh tiled edge to edge, mirrored, winding kept."""

from __future__ import annotations

import numpy as np
import trimesh

from pipeline25d_lab.harness.bench import against_gdal2tiles, bench_config, make_scene


def test_mirrored_copies_meet_edge_to_edge_and_keep_facing_up(tmp_path):
    # a 10 x 5 m sloping quad, facing up, with a marker vertex near one corner
    v = np.array([[0, 0, 0], [10, 0, 1], [10, 5, 2], [0, 5, 1], [1, 1, 0.5]], float) + [1000.0, 2000.0, 0.0]
    f = np.array([[0, 1, 4], [1, 2, 4], [2, 3, 4], [3, 0, 4]])
    src = tmp_path / "src.ply"
    trimesh.Trimesh(v, f, process=False).export(src)
    districts = make_scene(tmp_path / "scene", 2, 2, source=src)
    assert sorted(districts) == ["d00-00", "d00-01", "d01-00", "d01-01"]
    meshes = {k: trimesh.load(p, process=False) for k, p in districts.items()}
    for k, m in meshes.items():
        assert (m.face_normals[:, 2] > 0).all(), k                           # mirroring kept the winding
    lo = {k: m.bounds[0][:2] for k, m in meshes.items()}
    np.testing.assert_allclose(lo["d01-00"] - lo["d00-00"], [10, 0])        # edge to edge
    np.testing.assert_allclose(lo["d00-01"] - lo["d00-00"], [0, 5])
    # the marker vertex (near the source's south-west corner) is mirrored in the odd copies
    marker = {k: m.vertices[np.argmin(np.abs(m.vertices[:, 2] - 0.5))][:2] - lo[k] for k, m in meshes.items()}
    np.testing.assert_allclose(marker["d00-00"], [1, 1])
    np.testing.assert_allclose(marker["d01-00"], [9, 1])
    np.testing.assert_allclose(marker["d01-01"], [9, 4])
    from pipeline25d.config import validate_schema

    cfg = validate_schema(bench_config("b", districts, 0.5, "nadir"))      # district names the schema accepts
    assert cfg["terrain"] == "auto" and len(cfg["inputs"]) == 4


def test_run_cpu_splits_the_run_into_jobs_per_stage_and_snakemake(tmp_path):
    """Jobs' CPU from their logs' last ``job time:`` line (own + children), per stage; Snakemake's own
    is the run's total less the jobs'; the threads a rule got come from Snakemake's job block."""
    import json

    from pipeline25d.core.logsetup import JOB_TIME_LINE
    from pipeline25d_lab.harness.bench import RUN_CPU, job_cpu, rule_threads, run_cpu

    results = tmp_path / "results" / "s"
    logs = {"render/az000_el45/block_0_0_0.log": (0.1, 5.0, 4.5, 0.0),
            "render/az000_el90/block_0_0_0.log": (0.1, 3.0, 2.5, 0.25),
            "tms/az000_el45.log": (0.1, 2.0, 1.0, 3.0), "terrain.log": (0.1, 9.0, 8.0, 0.5)}
    for rel, times in logs.items():
        path = results / "logs" / rel
        path.parent.mkdir(parents=True, exist_ok=True)
        # an earlier attempt's line first: only the last counts
        path.write_text(f"x INFO pipeline25d.jobs: {JOB_TIME_LINE % (0, 1, 99, 99)}\n"
                        f"x INFO pipeline25d.jobs: {JOB_TIME_LINE % times}\n")
    (results / "logs" / "ingest").mkdir()
    (results / "logs" / "ingest" / "d1.log").write_text("a job that failed before its end line\n")
    assert job_cpu(results) == {"render": 7.25, "tms": 4.0, "terrain": 8.5}
    assert run_cpu(tmp_path, results) is None                       # a run not timed here
    (tmp_path / RUN_CPU).write_text(json.dumps({"cpu_s": 25.0, "wall_s": 20.0}))
    assert run_cpu(tmp_path, results) == {"total_s": 25.0, "jobs_s": 19.75, "snakemake_s": 5.25,
                                          "stages": {"render": 7.25, "tms": 4.0, "terrain": 8.5}}
    (tmp_path / "snakemake.log").write_text(
        "localrule render_block:\n    jobid: 4\n    wildcards: pid=az000_el45\n    resources: tmpdir=/tmp\n"
        "localrule tms:\n    jobid: 7\n    wildcards: pid=az000_el45\n    threads: 2\n    resources: tmpdir=/tmp\n"
        "Select jobs to execute...\n")
    assert rule_threads(tmp_path, "tms") == 2 and rule_threads(tmp_path, "render_block") == 1


def test_a_run_against_gdal2tiles_gives_its_wall_and_the_bound_of_its_cpu_packed():
    """The 3 x 3 run of 2026-11-27: 64.3 s, 104.14 CPU-s on 2 cores, gdal2tiles 10.68 s."""
    run = {"wall_s": 64.3, "cores": 2, "cpu": {"total_s": 104.14},
           "tms_vs_gdal2tiles_default": {"gdal2tiles_default_s": 10.68}}
    assert against_gdal2tiles(run) == {"wall": round(64.3 / 10.68, 2), "cpu_packed": round(104.14 / 2 / 10.68, 2)}
    assert against_gdal2tiles(run)["cpu_packed"] == 4.88                  # above 4 whatever the schedule
    assert against_gdal2tiles({**run, "cpu": None})["cpu_packed"] is None
