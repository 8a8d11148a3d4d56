"""The textured bench's measuring: the jobs' I/O lines, page-cache residency and the report."""

from __future__ import annotations

import logging
import os

import pytest

from pipeline25d.core.logsetup import RESOURCES_LINE, log_job_resources
from pipeline25d_lab.harness.bench_textured import markdown, summarise
from pipeline25d_lab.harness.dataset_io import evict, job_resources, resident, stage_resources

MB = 1024 * 1024


def test_a_job_logs_what_it_read(tmp_path):
    data = tmp_path / "data.bin"
    data.write_bytes(os.urandom(3 * MB))
    log = tmp_path / "job.log"
    handler = logging.FileHandler(log)
    logging.getLogger().addHandler(handler)
    logging.getLogger().setLevel(logging.INFO)
    try:
        with open("/proc/self/io") as fh:
            before = int(next(line for line in fh if line.startswith("rchar")).split()[1])
        data.read_bytes()
        log_job_resources()
    finally:
        logging.getLogger().removeHandler(handler)
        handler.close()
    rec = job_resources(log.read_text().splitlines())
    assert rec["rchar"] - before >= 3 * MB                 # the 3 MB just read, and little else
    assert rec["rchar"] - before < 4 * MB
    assert rec["max_rss_kb"] > 10_000 and rec["read_bytes"] >= 0


def test_evicted_files_are_read_from_storage_once(tmp_path):
    folder = tmp_path / "ds"
    folder.mkdir()
    for k in range(3):
        (folder / f"L{k}.bin").write_bytes(os.urandom(2 * MB))
    assert evict(folder) == 6 * MB
    if resident(folder)["bytes"] > 0:
        pytest.skip("this file system keeps evicted pages (tmpfs?)")
    (folder / "L1.bin").read_bytes()
    after = resident(folder, lambda p: p.stem)
    assert after["bytes"] == 2 * MB and after["by_level"] == {"L1": 2 * MB}


def test_reading_a_dataset_at_a_gsd_reads_the_levels_it_uses(tmp_path):
    from pipeline25d_lab.harness.bench_textured import read_probe
    from pipeline25d_lab.scenes.oap3d import generate_oap3d

    manifest = generate_oap3d(tmp_path / "tiny", "tiny", seed=5)
    evict(tmp_path / "tiny")
    if resident(tmp_path / "tiny")["bytes"] > 0:
        pytest.skip("this file system keeps evicted pages (tmpfs?)")
    for fmt, levels in (("osgb", {"0", "1", "index"}), ("3dtiles", {"1", "index"})):
        probe = read_probe(tmp_path / "tiny", manifest, fmt, 0.25)
        assert probe["triangles"] == 2 * 4 * 288                     # level 1 of both tiles
        assert set(probe["resident_after"]["by_level"]) <= levels     # no finer level's file was read
        assert probe["resident_after"]["bytes"] <= probe["levels_used"]["bytes"]
        assert probe["read_bytes"] >= 0.9 * probe["resident_after"]["bytes"]


def _log(path, rchar, read, rss, child):
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text("2026 INFO x: start\n2026 INFO pipeline25d.jobs: "
                    + RESOURCES_LINE % (rchar, read, 5, 6, rss * 1024, child * 1024) + "\n")


def test_stage_resources_and_report_on_recorded_runs(tmp_path):
    logs = tmp_path / "logs"
    _log(logs / "ingest" / "city.log", 900 * MB, 40 * MB, 1500, 300)
    _log(logs / "render" / "az000_el45" / "block_0.log", 50 * MB, 0, 700, 0)
    _log(logs / "render" / "az000_el45" / "block_1.log", 60 * MB, 1 * MB, 800, 0)
    (logs / "tms").mkdir()
    (logs / "tms" / "x.log").write_text("no resources line: a job that failed\n")
    io = stage_resources(logs)
    assert io["render"] == {"jobs": 2, "rchar": 110 * MB, "read_bytes": 1 * MB, "peak_rss_mb": 800.0,
                            "child_peak_rss_mb": 0.0}
    assert io["ingest"]["peak_rss_mb"] == 1500.0 and "tms" not in io
    manifest = {"size": "tiny", "spec": {"tiles": [2, 1], "tile": 50.0, "levels": 3, "atlas": 128, "charts": 2,
                                         "gutter": 2, "cells": 6, "quality": 90},
                "levels": [{"level": 0, "osgb_bytes": 10 * MB, "3dtiles_glb_bytes": 0},
                           {"level": 1, "osgb_bytes": 20 * MB, "3dtiles_glb_bytes": 0},
                           {"level": 2, "osgb_bytes": 70 * MB, "3dtiles_glb_bytes": 0}],
                "formats": {"osgb": {"path": "osgb", "bytes": 100 * MB + 300}}}
    result = {"wall_s": 80.0, "jobs": 4, "rendered_mpx": 16.0, "check_rmsd_px": {},
              "stages": {"ingest": {"jobs": 1, "seconds": 20.0, "max_rss_mb": 1400.0},
                         "render": {"jobs": 2, "seconds": 8.0, "max_rss_mb": 750.0}}}
    touched = {"bytes": 31 * MB, "by_level": {"0": 10 * MB, "1": 21 * MB}}
    run = summarise(result, io, touched, manifest, "osgb", 0.25)
    d = run["dataset"]
    # gsd 0.25 draws level 1 (texels 0.417, 0.208, 0.104 m): levels 0 and 1 and metadata.xml are used
    assert d["levels_used"]["level"] == 1 and d["levels_used"]["bytes"] == 30 * MB + 300
    assert d["read_bytes"] == 40 * MB and d["read_bytes_all_jobs"] == 41 * MB
    assert d["read_over_levels_used"] == round(40 * MB / (30 * MB + 300), 3)
    assert run["stages"]["render"]["mpx_per_job_s"] == 2.0 and run["peak_rss_mb_job"] == 1500.0
    assert run["wall_s_per_mpx"] == 5.0
    text = markdown({"gsd": 0.25, "perspectives": "eight-45+nadir", "cores": 2, "runs": [run, {**run, "size": "half"}]})
    assert "| render | 2 | 8.0 | 2.0 | 800.0 | 0.0 | 110.0 | 1.0 |" in text and "## Scaling" in text


def test_one_formats_report_does_not_overwrite_the_others():
    from pipeline25d_lab.harness.bench_textured import report_name

    assert report_name(["full"], ["osgb", "3dtiles"]) == "textured-full"
    assert report_name(["full"], ["3dtiles", "osgb"]) == "textured-full"
    assert report_name(["full"], ["osgb"]) == "textured-full-osgb"
    assert report_name(["quarter", "half"], ["3dtiles"]) == "textured-quarter-half-3dtiles"
