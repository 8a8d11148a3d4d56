"""Plan grouping: render blocks partition a perspective's tiles, and hashes follow what changes pixels."""

from __future__ import annotations

import numpy as np

from pipeline25d.perspectives import Perspective
from pipeline25d.plan import block_of, block_spec_hash, plan_block, plan_blocks, plan_perspective


def test_block_of_floors_negative_rows_and_cols():
    assert block_of(0, 0, 4) == (0, 0)
    assert block_of(3, 3, 4) == (0, 0)
    assert block_of(4, -1, 4) == (1, -1)
    assert block_of(-4, -5, 4) == (-1, -2)


def _plan(hashes: dict | None = None) -> dict:
    chunks = [{"id": f"c{i}_{j}", "district": "d", "errors": [0.0],
               "bounds": [[i * 100.0, j * 100.0, 0.0], [i * 100.0 + 100, j * 100.0 + 100, 30.0]],
               "ground": None, **({"hash": hashes[(i, j)]} if hashes else {})}
              for i in range(5) for j in range(3)]
    return plan_perspective(Perspective(45, 45), chunks, [], 0.0, 0.5, 64, 1.0, "EPSG:25832", {"samples": 4})


def test_blocks_partition_the_tiles_into_squares_of_the_block_size():
    plan = _plan()
    blocks = plan_blocks(plan, 3)
    tiles = [(t["row"], t["col"]) for ts in blocks.values() for t in ts]
    assert sorted(tiles) == sorted((t["row"], t["col"]) for t in plan["tiles"])     # each tile once
    for (br, bc), ts in blocks.items():
        assert 1 <= len(ts) <= 9
        assert all(block_of(t["row"], t["col"], 3) == (br, bc) for t in ts)
    assert len(blocks) < len(plan["tiles"]) / 4
    some = next(iter(blocks))
    assert plan_block(plan, *some, 3) == blocks[some]


def test_a_chunk_content_change_rehashes_only_the_tiles_and_blocks_that_draw_it():
    hashes = {(i, j): f"h{i}{j}" for i in range(5) for j in range(3)}
    before = _plan(hashes)
    after = _plan({**hashes, (2, 1): "changed"})
    spec = lambda plan: {(t["row"], t["col"]): t["spec_hash"] for t in plan["tiles"]}
    changed = {k for k, v in spec(after).items() if v != spec(before)[k]}
    draws = {(t["row"], t["col"]) for t in after["tiles"] if any(c["id"] == "c2_1" for c in t["chunks"])}
    assert changed == draws and 0 < len(changed) < len(after["tiles"])
    b_before, b_after = plan_blocks(before, 4), plan_blocks(after, 4)
    rehashed = {k for k in b_after if block_spec_hash(b_after[k]) != block_spec_hash(b_before[k])}
    assert rehashed == {block_of(r, c, 4) for r, c in draws}


def test_a_tiles_content_box_holds_its_chunks_projected_boxes_and_no_more():
    from pipeline25d.camera import projected_box

    chunks = [{"id": "a", "district": "d", "bounds": [[3.0, 4.0, 0.0], [21.0, 9.0, 12.0]], "errors": [0.0],
               "ground": None}]
    plan = plan_perspective(Perspective(45, 45), chunks, [], 0.0, 0.5, 64, 1.0, "EPSG:25832", {"samples": 4})
    box, _ = projected_box(np.array(chunks[0]["bounds"]), Perspective(45, 45), 0.0, None, "map")
    span = 32.0
    covered = []
    for t in plan["tiles"]:
        x0, y0, x1, y1 = t["content"]
        assert t["col"] * span <= x0 < x1 <= (t["col"] + 1) * span and t["row"] * span <= y0 < y1 <= (t["row"] + 1) * span
        assert all(abs(v / 0.5 - round(v / 0.5)) < 1e-9 for v in t["content"])      # whole pixels
        covered.append(t["content"])
    c = np.array(covered)
    assert c[:, 0].min() <= box.xmin < c[:, 0].min() + 0.5 and c[:, 2].max() - 0.5 < box.xmax <= c[:, 2].max()
    assert c[:, 1].min() <= box.ymin < c[:, 1].min() + 0.5 and c[:, 3].max() - 0.5 < box.ymax <= c[:, 3].max()
