"""Report formatting: a measurement never prints as a bare zero, size ratios stay readable."""

from __future__ import annotations

from pipeline25d.publish.report import _ratio, fmt_measure, heights_section


def test_measurements_never_print_as_zero():
    assert fmt_measure(None, missing="n/a (2 check points)") == "n/a (2 check points)"
    assert fmt_measure(0.0) == "< 1e-06" and fmt_measure(4e-7) == "< 1e-06"
    assert fmt_measure(0.00042) == "0.00042" and fmt_measure(0.1234) == "0.123"


def test_heights_never_print_zero_where_nothing_was_measured():
    assert heights_section({"skipped": "no nadir perspective"})[-1] == "Not measured: no nadir perspective."
    none = {"n_footprints": 3, "n_measured": 0, "n": 0, "bias": None, "rmsd": None, "median_abs": None, "p90_abs": None}
    some = {"n_footprints": 3, "n_measured": 2, "n": 2, "bias": -0.05, "rmsd": 0.1, "median_abs": 0.08, "p90_abs": 0.12}
    h = {"footprints": {"source": "layer", "paths": ["fp.gpkg"], "n_given": 5, "n_on_maps": 3}, "n_measured": 2,
         "reference": {"source": "CSV ref.csv", "basis": "roof z minus the DTM"}, "settings": {"outlier_m": 2.0},
         "reasons": {"az045_el45": {"measured": 2, "hidden": 1}, "az135_el45": {"flat": 2, "ambiguous": 1}},
         "groups": {"all": {"combined": some, "az045_el45": some, "az135_el45": none}}}
    md = "\n".join(heights_section(h))
    assert "| az135_el45 | 0 / 3 | not measured | not measured | not measured | not measured |" in md
    assert "| az045_el45 | 2 / 3 | 0.100 | -0.050 | 0.080 | 0.120 |" in md
    assert "| az135_el45 | 0 | ambiguous 1, flat 2 |" in md and "| az045_el45 | 2 | hidden 1 |" in md
    assert "0.000" not in md and "3 of 5 within the maps" in md


def test_size_ratio_puts_the_larger_side_first():
    assert _ratio(34.5) == "34.5 : 1"
    assert _ratio(19.76 / 423.86) == "1 : 21.5"          # maps larger than the model: not "0.0 : 1"


def test_stage_timings_count_only_this_configurations_jobs(tmp_path):
    """Job logs an earlier configuration left behind (a removed district, a render block of
    another grouping) do not count in the report's timings, nor a job's log without a time line
    (killed), nor the report's and viewer's own (an earlier run's)."""
    from pipeline25d.core.logsetup import JOB_TIME_LINE, RESOURCES_LINE
    from pipeline25d.publish.report import current_jobs, stage_timings

    def log(rel: str, seconds: float, rss_mb: int = 100, finished: bool = True) -> None:
        path = tmp_path / "logs" / rel
        path.parent.mkdir(parents=True, exist_ok=True)
        lines = ["2026-11-27 00:00:00,000 INFO pipeline25d.x: working"]
        if finished:
            lines += ["... INFO pipeline25d.jobs: " + RESOURCES_LINE % (1, 2, 3, 4, rss_mb * 1024, 10 * 1024),
                      "... INFO pipeline25d.jobs: " + JOB_TIME_LINE % (0.25, seconds - 0.25, seconds, 0.0)]
        path.write_text("\n".join(lines) + "\n")

    log("scene.log", 1.0)
    log("lod/d0.log", 2.0)
    log("lod/gone.log", 50.0)                            # a district no longer in the config
    log("warp/az045_el45.log", 3.0, rss_mb=700)
    log("warp/az135_el45.log", 60.0)                     # a perspective no longer asked for
    log("render/az045_el45/block_0_1_2.log", 4.0)
    log("render/az045_el45/block_0_9_9.log", 70.0)       # an older grouping's block
    log("render/az045_el45/block_0_1_3.log", 80.0, finished=False)
    log("heights.log", 0.5)
    log("heights/blocks.log", 0.25)
    log("heights/block_3_-1.log", 5.0)
    log("heights/block_7_7.log", 90.0)                   # a block of footprints no longer there
    log("heights/block_L4_1_0.log", 2.0)                 # sparse blocks in one job
    log("report.log", 9.0)
    log("viewer.log", 9.0)
    current = current_jobs({"d0"}, {"az045_el45": {"0_1_2", "0_1_3"}}, {"3_-1", "L4_1_0"})
    got = stage_timings(tmp_path, current)
    assert {k: (v["jobs"], v["seconds"]) for k, v in got.items()} == \
        {"scene": (1, 1.0), "lod": (1, 2.0), "warp": (1, 3.0), "render": (1, 4.0), "heights": (4, 7.75)}
    assert got["warp"]["max_rss_mb"] == 710.0                   # the job's process and its largest child
    assert stage_timings(tmp_path)["render"]["jobs"] == 2         # without the filter: every finished job
    # a log removed between its listing and its reading (Snakemake removes a job's log as the job
    # starts again: the wms job runs beside the report's) does not count either
    (tmp_path / "logs" / "wms.log").symlink_to(tmp_path / "logs" / "removed.log")
    assert "wms" not in stage_timings(tmp_path, current) and stage_timings(tmp_path, current)["scene"]["jobs"] == 1


def test_the_heights_jobs_are_read_from_the_blocks_file_and_one_per_block_in_an_older_one(tmp_path):
    """The report counts a heights job's log by the job names of work/heights/blocks.json; a file
    written before blocks were grouped into jobs had one job per block, named as the block."""
    import json

    from pipeline25d.publish.report import _heights_jobs

    path = tmp_path / "work" / "heights" / "blocks.json"
    assert _heights_jobs(tmp_path) == set()
    path.parent.mkdir(parents=True)
    path.write_text(json.dumps({"footprints": [], "blocks": {"3_-1": [0], "4_-1": [1], "9_9": [2]},
                                "jobs": {"L1_1_-1": ["3_-1", "4_-1"], "9_9": ["9_9"]}}))
    assert _heights_jobs(tmp_path) == {"L1_1_-1", "9_9"}
    path.write_text(json.dumps({"footprints": [], "blocks": {"3_-1": [0], "9_9": [2]}}))
    assert _heights_jobs(tmp_path) == {"3_-1", "9_9"}
