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
    """Benchmark files an earlier configuration left behind (a removed district, a render block of
    another grouping) do not count in the report's timings."""
    from pipeline25d.publish.report import current_jobs, stage_timings

    def tsv(rel: str, seconds: float) -> None:
        path = tmp_path / "benchmarks" / rel
        path.parent.mkdir(parents=True, exist_ok=True)
        path.write_text(f"s\th:m:s\tmax_rss\n{seconds}\t0:00:01\t100.0\n")

    tsv("scene.tsv", 1.0)
    tsv("lod/d0.tsv", 2.0)
    tsv("lod/gone.tsv", 50.0)                            # a district no longer in the config
    tsv("warp/az045_el45.tsv", 3.0)
    tsv("warp/az135_el45.tsv", 60.0)                     # a perspective no longer asked for
    tsv("render/az045_el45/block_0_1_2.tsv", 4.0)
    tsv("render/az045_el45/block_0_9_9.tsv", 70.0)       # an older grouping's block
    tsv("heights.tsv", 0.5)
    tsv("heights/blocks.tsv", 0.25)
    tsv("heights/block_3_-1.tsv", 5.0)
    tsv("heights/block_7_7.tsv", 90.0)                   # a block of footprints no longer there
    current = current_jobs({"d0"}, {"az045_el45": {"0_1_2"}}, {"3_-1"})
    got = stage_timings(tmp_path, current)
    assert {k: (v["jobs"], v["seconds"]) for k, v in got.items()} == \
        {"scene": (1, 1.0), "lod": (1, 2.0), "warp": (1, 3.0), "render": (1, 4.0), "heights": (3, 5.75)}
    assert stage_timings(tmp_path)["render"]["jobs"] == 2         # without the filter: every file
