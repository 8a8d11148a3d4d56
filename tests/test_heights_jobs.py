"""The heights stage's jobs: sparse blocks grouped by a quadtree over the world-fixed block grid."""

from __future__ import annotations

import pytest

from pipeline25d.analysis.heights.blocks import jobs_of


def blocks(counts: dict[tuple[int, int], int]) -> dict[str, list[int]]:
    """Blocks named ``<col>_<row>`` holding ``counts`` footprints (indices numbered through)."""
    out, i = {}, 0
    for (c, r), n in sorted(counts.items()):
        out[f"{c}_{r}"] = list(range(i, i + n))
        i += n
    return out


def check_partition(b: dict[str, list[int]], jobs: dict[str, list[str]], most: int) -> None:
    assert sorted(x for bs in jobs.values() for x in bs) == sorted(b)
    for name, bs in jobs.items():
        assert len(bs) == 1 or sum(len(b[x]) for x in bs) <= most, name
        assert (name == bs[0]) == (len(bs) == 1)


def test_a_dense_block_stays_alone_and_its_sparse_neighbours_share_a_job():
    # cells 0..3 x 0..1: (0, 0) holds 30 (over 24), the others 2 each
    counts = {(c, r): 2 for c in range(4) for r in range(2)} | {(0, 0): 30}
    b = blocks(counts)
    jobs = jobs_of(b, 24)
    check_partition(b, jobs, 24)
    assert jobs["0_0"] == ["0_0"]
    # level 1: (0, 0)'s parent holds 30 + 6: its siblings stay alone; (2..3, 0..1) holds 8: one job, the
    # level-1 cell (1, 0)
    assert jobs["L1_1_0"] == ["2_0", "2_1", "3_0", "3_1"]
    assert {"0_1": ["0_1"], "1_0": ["1_0"], "1_1": ["1_1"]}.items() <= jobs.items()
    assert len(jobs) == 5


def test_a_sparse_city_is_a_few_jobs_and_a_dense_one_a_job_per_block():
    sparse = blocks({(37 * k % 40, 11 * k % 40): 1 for k in range(49)})     # 49 buildings over 40 x 40 blocks
    jobs = jobs_of(sparse, 24)
    check_partition(sparse, jobs, 24)
    assert 3 <= len(jobs) <= 8
    dense = blocks({(c, r): 25 for c in range(5) for r in range(5)})
    assert jobs_of(dense, 24) == {b: [b] for b in dense}


def test_the_jobs_are_fixed_in_the_world_an_edit_changes_only_the_jobs_around_it():
    counts = {(c, r): 3 for c in range(0, 16, 2) for r in range(0, 16, 2)}
    before = jobs_of(blocks(counts), 24)
    counts[(15, 15)] = 20                               # a new district in one corner
    after = jobs_of(blocks(counts), 24)
    changed = {j for j in set(before) | set(after) if before.get(j) != after.get(j)}
    touched = {b for j in changed for b in before.get(j, []) + after.get(j, [])}
    assert "15_15" in touched
    assert all(int(b.split("_")[0]) >= 8 and int(b.split("_")[1]) >= 8 for b in touched)


@pytest.mark.parametrize("cells", [[(-1, 0), (0, 0)], [(-1, -1), (0, 0)], [(5, -3)]])
def test_cells_either_side_of_the_origin_end_the_grouping(cells):
    b = blocks({c: 1 for c in cells})
    jobs = jobs_of(b, 24)
    check_partition(b, jobs, 24)
    assert len(jobs) == len(cells)          # -1 and 0 never share a parent: each its own job


def test_a_blocks_file_of_before_the_jobs_reads_as_a_job_per_block(tmp_path):
    """A run resumed over a blocks.json written before blocks were grouped measures them as it did."""
    import json

    from pipeline25d.analysis.height_blocks import read_blocks

    path = tmp_path / "blocks.json"
    path.write_text(json.dumps({"block_size": 250.0, "footprints": [{"id": "a", "rings": [[[0, 0], [1, 0], [1, 1]]]}],
                                "blocks": {"0_0": [0]}}))
    fps, blocks, jobs = read_blocks(path)
    assert [f.id for f in fps] == ["a"] and blocks == {"0_0": [0]} and jobs == {"0_0": ["0_0"]}
