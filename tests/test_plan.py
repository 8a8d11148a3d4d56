"""Plan grouping: render blocks partition a perspective's tiles, and hashes follow what changes pixels."""

from __future__ import annotations

import math

import numpy as np
import pytest

from pipeline25d.geometry.perspectives import Perspective
from pipeline25d.stages.plan import (
    TILE_OVERHEAD,
    TOP_LEVEL,
    block_node,
    block_spec_hash,
    plan_block,
    plan_blocks,
    plan_perspective,
    tile_cost,
)
from pipeline25d.stages.records import GcpCandidate, LodChunk, Plan, Tile, frozen


def _chunk(cid: str, bounds, errors=(0.0,), hash: str = "") -> LodChunk:
    return LodChunk(cid, "d", frozen(bounds), tuple(errors), (0,) * len(errors), hash, "")


def _plan(hashes: dict | None = None, pitch: float = 100.0, size: float = 100.0, n=(5, 3)) -> Plan:
    """Chunks of ``size`` m on a ``pitch`` m grid (pitch > size: empty land between them)."""
    chunks = [_chunk(f"c{i}_{j}", [[i * pitch, j * pitch, 0.0], [i * pitch + size, j * pitch + size, 30.0]],
                     hash=hashes[(i, j)] if hashes else "")
              for i in range(n[0]) for j in range(n[1])]
    return plan_perspective(Perspective(45, 45), chunks, [], 0.0, 0.5, 64, 1.0, "EPSG:25832", {"samples": 4})


def _check_quadtree(plan: Plan, block: int) -> dict[str, tuple[Tile, ...]]:
    """The defining properties of plan_blocks: a partition into quadtree squares, each within
    the budget or a smallest square, and no square whose parent would have been within it."""
    blocks = plan_blocks(plan, block)
    tiles = [(t.row, t.col) for ts in blocks.values() for t in ts]
    assert sorted(tiles) == sorted((t.row, t.col) for t in plan.tiles)     # each tile once
    budget = block * block * (1 + TILE_OVERHEAD) * plan.tile_size ** 2
    cost = lambda ts: sum(tile_cost(plan, t) for t in ts)
    inside = lambda t, r0, c0, side: r0 <= t.row < r0 + side and c0 <= t.col < c0 + side
    for bid, ts in blocks.items():
        r0, c0, side, level, quadrants = block_node(bid, block)
        assert all(inside(t, r0, c0, side) for t in ts)
        assert (level == 0 and not quadrants) or cost(ts) <= budget
        assert [plan.tiles.index(t) for t in ts] == sorted(plan.tiles.index(t) for t in ts)   # plan order
        if quadrants:                  # children of a node that was split, each in one of those quadrants
            half = side // 2
            assert len(quadrants) > 1 and quadrants == "".join(sorted(set(quadrants)))
            assert all(any(inside(t, r0 + int(q) // 2 * half, c0 + int(q) % 2 * half, half) for q in quadrants)
                       for t in ts)
            assert cost([t for t in plan.tiles if inside(t, r0, c0, side)]) > budget     # it was split
        elif level < TOP_LEVEL:        # its parent was split: the parent's tiles cost more than the budget
            pr, pc, pside = r0 // (2 * side) * 2 * side, c0 // (2 * side) * 2 * side, 2 * side
            assert cost([t for t in plan.tiles if inside(t, pr, pc, pside)]) > budget
    return blocks


def test_dense_land_gets_block_squares_and_sparse_land_fewer_jobs_than_a_fixed_grid():
    dense = _check_quadtree(_plan(), 3)
    assert all(block_node(b, 3)[3] == 0 for b, ts in dense.items() if len(ts) == 9)     # full squares stay squares
    fixed = lambda plan, b: {(t.row // b, t.col // b) for t in plan.tiles}
    assert len(dense) <= len(fixed(_plan(), 3))
    sparse_plan = _plan(pitch=1000.0, size=20.0, n=(4, 4))       # 16 small buildings, 1 km apart
    sparse = _check_quadtree(sparse_plan, 3)
    least = math.ceil(sum(tile_cost(sparse_plan, t) for t in sparse_plan.tiles)
                      / (9 * (1 + TILE_OVERHEAD) * 64 ** 2))      # jobs no grouping can go below
    assert len(sparse) <= 2 * least < len(fixed(sparse_plan, 3)) / 2
    some = next(iter(sparse))
    assert plan_block(sparse, some, sparse_plan.id) == sparse[some]
    with pytest.raises(KeyError, match="not in the plan"):
        plan_block(sparse, "0_99_99", sparse_plan.id)


def test_a_chunk_content_change_rehashes_only_the_tiles_and_blocks_that_draw_it():
    hashes = {(i, j): f"h{i}{j}" for i in range(5) for j in range(3)}
    before = _plan(hashes)
    after = _plan({**hashes, (2, 1): "changed"})
    spec = lambda plan: {(t.row, t.col): t.spec_hash for t in plan.tiles}
    changed = {k for k, v in spec(after).items() if v != spec(before)[k]}
    draws = {(t.row, t.col) for t in after.tiles if any(c.id == "c2_1" for c in t.chunks)}
    assert changed == draws and 0 < len(changed) < len(after.tiles)
    b_before, b_after = plan_blocks(before, 4), plan_blocks(after, 4)
    assert b_before.keys() == b_after.keys()        # same content boxes: the same grouping
    rehashed = {k for k in b_after if block_spec_hash(b_after[k]) != block_spec_hash(b_before[k])}
    assert rehashed == {k for k, ts in b_after.items() if any((t.row, t.col) in draws for t in ts)}
    assert 0 < len(rehashed) < len(b_after)


def test_a_tiles_content_box_holds_its_chunks_projected_boxes_and_no_more():
    from pipeline25d.geometry.camera import projected_box

    chunks = [_chunk("a", [[3.0, 4.0, 0.0], [21.0, 9.0, 12.0]])]
    plan = plan_perspective(Perspective(45, 45), chunks, [], 0.0, 0.5, 64, 1.0, "EPSG:25832", {"samples": 4})
    box, _ = projected_box(np.array(chunks[0].bounds), Perspective(45, 45), 0.0, None, "map")
    span = 32.0
    covered = []
    for t in plan.tiles:
        x0, y0, x1, y1 = t.content
        assert t.col * span <= x0 < x1 <= (t.col + 1) * span and t.row * span <= y0 < y1 <= (t.row + 1) * span
        assert all(abs(v / 0.5 - round(v / 0.5)) < 1e-9 for v in t.content)      # whole pixels
        covered.append(t.content)
    c = np.array(covered)
    assert c[:, 0].min() <= box.xmin < c[:, 0].min() + 0.5 and c[:, 2].max() - 0.5 < box.xmax <= c[:, 2].max()
    assert c[:, 1].min() <= box.ymin < c[:, 1].min() + 0.5 and c[:, 3].max() - 0.5 < box.ymax <= c[:, 3].max()


def test_a_plan_is_a_frozen_record_with_one_json_round_trip():
    import dataclasses
    import json

    cand = GcpCandidate("g1_2", 40.0, 50.0, 1.5, 1.25, 0.01, -0.02, "check")
    chunks = [_chunk("a", [[3.0, 4.0, 0.0], [71.0, 59.0, 12.0]], errors=(0.0, 0.4), hash="abc")]
    plan = plan_perspective(Perspective(45, 45), chunks, [cand], 0.0, 0.5, 64, 1.0, "EPSG:25832", {"samples": 4})
    text = json.dumps(plan.to_json())
    assert Plan.from_json(json.loads(text)) == plan and json.dumps(Plan.from_json(json.loads(text)).to_json()) == text
    assert [g for t in plan.tiles for g in t.gcps] == [cand]          # the candidate, as a record, in its tile
    with pytest.raises(dataclasses.FrozenInstanceError):
        plan.tiles[0].row = 5
    with pytest.raises(TypeError):
        plan.tiles[0].render["samples"] = 8                            # read-only: no caller can change a shared plan
    assert plan.tile_extent(0, 0) == (0.0, 0.0, 32.0, 32.0) and plan.span == 32.0 and plan.camera == "map"
