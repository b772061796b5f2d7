"""Boxes fitted to masks: known values, a brute-force re-derivation, the rasteriser's boxes
recovered without bias; ``to_labels`` takes them (or the head's) into the label lines."""

import types

import numpy as np
import pytest
from shapely.geometry import Point, Polygon

from indoorbev_jax.boxes import HEADINGS, PAD_CELLS, fit_box, largest_piece, segment_boxes
from indoorbev_jax.config import GridConfig
from indoorbev_jax.data.rasterize import rasterize_boxes
from indoorbev_jax.predict import to_labels

GRID = GridConfig(x_range=(-2.0, 2.0), y_range=(-1.5, 1.5), cell_size=0.05)  # 60 x 80


def _polygon(x, y, length, width, yaw):
    c, s = np.cos(yaw), np.sin(yaw)
    corners = np.array([[1, 1], [1, -1], [-1, -1], [-1, 1]]) * [length / 2, width / 2]
    return Polygon(corners @ np.array([[c, s], [-s, c]]) + [x, y])


def _brute_force(mask, grid, headings=HEADINGS):
    """Every cell centre, every heading: the smallest padded area and its heading index."""
    rows, cols = np.nonzero(mask)
    v = grid.cell_size
    centres = np.stack([grid.x_range[0] + (cols + 0.5) * v, grid.y_range[0] + (rows + 0.5) * v], 1)
    pad = PAD_CELLS * v
    best = None
    for k in range(headings):
        t = k * np.pi / 2 / headings
        u = centres @ [np.cos(t), np.sin(t)]
        w = centres @ [-np.sin(t), np.cos(t)]
        area = (np.ptp(u) + pad) * (np.ptp(w) + pad)
        if best is None or area < best[0]:
            best = (area, k)
    return best


def test_axis_aligned_cells_give_their_rectangle():
    mask = np.zeros(GRID.shape, bool)
    mask[10:15, 20:40] = True  # rows 10-14 (y), columns 20-39 (x)
    x, y, length, width, yaw = fit_box(mask, GRID)
    pad = PAD_CELLS * 0.05  # the centres span 19 x 4 cells
    assert (length, width, yaw) == pytest.approx((0.95 + pad, 0.2 + pad, 0.0), abs=1e-9)
    assert (x, y) == pytest.approx((-2.0 + 30 * 0.05, -1.5 + 12.5 * 0.05), abs=1e-9)
    # Taller than wide: length stays the longer side, the heading turns by 90 degrees.
    tall = np.zeros(GRID.shape, bool)
    tall[10:30, 20:25] = True
    x, y, length, width, yaw = fit_box(tall, GRID)
    assert (length, width, yaw) == pytest.approx((0.95 + pad, 0.2 + pad, np.pi / 2), abs=1e-9)
    assert (x, y) == pytest.approx((-2.0 + 22.5 * 0.05, -1.5 + 20 * 0.05), abs=1e-9)
    with pytest.raises(ValueError, match="no cell set"):
        fit_box(np.zeros(GRID.shape, bool), GRID)
    with pytest.raises(ValueError, match=r"expected shape \(60, 80\)"):
        fit_box(mask[:5], GRID)
    # A mask of another grid's width is refused too (only the row count was checked).
    wide = np.pad(mask, ((0, 0), (0, 10)))  # 60 x 90, its cells where they were
    with pytest.raises(ValueError, match=r"expected shape \(60, 80\) \(the grid\), got \(60, 90\)"):
        fit_box(wide, GRID)


def test_rasterised_boxes_are_recovered_and_equal_the_brute_force():
    rng = np.random.default_rng(0)
    n = 200
    boxes = np.stack(
        [rng.uniform(-1.2, 1.2, n), rng.uniform(-0.8, 0.8, n), rng.uniform(0.3, 1.2, n),
         rng.uniform(0.2, 0.6, n), rng.uniform(-np.pi, np.pi, n)], 1
    ).astype(np.float32)  # fmt: skip
    _, masks = rasterize_boxes(boxes, np.ones(n, bool), GRID)
    ious, bias = [], []
    for box, mask in zip(boxes, np.asarray(masks), strict=True):
        fit = fit_box(mask, GRID)
        area, k = _brute_force(mask, GRID)
        # Only each row's end cells are searched: the same heading and area as every cell's.
        assert fit[2] * fit[3] == pytest.approx(area, rel=1e-9)
        assert fit[4] % (np.pi / 2) == pytest.approx(k * np.pi / 2 / HEADINGS, abs=1e-9)
        # The rectangle holds every cell centre of the mask.
        inside = _polygon(*fit).buffer(1e-9)
        rows, cols = np.nonzero(mask)
        xs = GRID.x_range[0] + (cols + 0.5) * GRID.cell_size
        ys = GRID.y_range[0] + (rows + 0.5) * GRID.cell_size
        assert all(inside.covers(Point(x, y)) for x, y in zip(xs, ys, strict=True))
        true = _polygon(*box)
        ious.append(true.intersection(_polygon(*fit)).area / true.union(_polygon(*fit)).area)
        assert np.hypot(*(fit[:2] - box[:2])) < GRID.cell_size
        bias.append(fit[2:4] - np.sort(box[2:4])[::-1])
    # PAD_CELLS makes the sizes unbiased: whole cells would add about a cell to each.
    assert np.abs(np.mean(bias, 0)).max() < 0.2 * GRID.cell_size
    assert min(ious) > 0.7 and np.median(ious) > 0.85


def test_long_box_heading_is_found_to_a_degree():
    grid = GridConfig(x_range=(-2.0, 2.0), y_range=(-2.0, 2.0), cell_size=0.02)
    for yaw in (0.1, 0.5, 1.2, 2.0, -2.8):
        box = np.array([[0.3, -0.2, 2.0, 0.6, yaw]], np.float32)
        _, masks = rasterize_boxes(box, np.ones(1, bool), grid)
        x, y, length, width, fit_yaw = fit_box(np.asarray(masks)[0], grid)
        turn = (fit_yaw - yaw + np.pi / 2) % np.pi - np.pi / 2  # headings modulo 180 degrees
        assert abs(np.degrees(turn)) <= 1.0
        assert (length, width) == pytest.approx((2.0, 0.6), abs=2 * grid.cell_size)
        assert (x, y) == pytest.approx((0.3, -0.2), abs=grid.cell_size)


def test_segment_boxes_search_the_same_headings_as_fit_box():
    """``segment_boxes`` is ``fit_box`` of each segment: the same 1-degree heading search,
    so the smallest padded area over all 90 headings (brute force). Half the headings passed
    every test (the masks of to_labels below are axis-aligned; a mutation audit): long boxes
    at random yaws on a fine grid, each its own segment id, show the difference."""
    grid = GridConfig(x_range=(-2.0, 2.0), y_range=(-2.0, 2.0), cell_size=0.02)
    rng = np.random.default_rng(0)
    n = 16
    boxes = np.stack([np.full(n, 0.1), np.full(n, -0.2), np.full(n, 2.0), np.full(n, 0.5),
                      rng.uniform(0, np.pi, n)], 1).astype(np.float32)  # fmt: skip
    _, masks = rasterize_boxes(boxes, np.ones(n, bool), grid)
    for k, mask in enumerate(np.asarray(masks)):
        segment = np.where(mask, k + 1, 0)
        got = segment_boxes(segment, [k + 1], grid)[0]
        np.testing.assert_allclose(got, fit_box(mask, grid), atol=1e-9, err_msg=str(boxes[k]))
        area, _ = _brute_force(mask, grid)
        assert got[2] * got[3] == pytest.approx(area, rel=1e-9), boxes[k]


def test_to_labels_takes_the_fitted_or_the_regressed_box():
    q = 3
    det_masks = np.zeros((q, *GRID.shape), bool)
    det_masks[0, 10:15, 20:40] = True
    det_masks[2, 30:50, 50:54] = True
    panoptic = np.zeros(GRID.shape, np.int32)
    panoptic[det_masks[0]], panoptic[det_masks[2]] = 1, 3  # id q + 1
    panoptic[55, 2] = 3  # a speck of segment 3 far from it: not part of its box
    output = types.SimpleNamespace(
        segment_valid=np.array([True, False, True]),
        det_classes=np.array([1, 2, 3]),
        det_scores=np.array([0.9, 0.8, 0.7], np.float32),
        det_masks=det_masks,
        instance_ids=panoptic,
    )
    final = types.SimpleNamespace(
        dims=np.array([[-0.5, 0.4, 1.1], [1, 1, 1], [0.3, 0.2, 0.9]], np.float32),
        pos=np.array([[0.1, 0.2, 0.3], [0, 0, 0], [-0.4, 0.5, 0.6]], np.float32),
        yaw=np.array([[4.0], [0.0], [-3.5]], np.float32),
    )
    head, _ = to_labels(final, output)
    np.testing.assert_allclose(head.dims, np.abs(final.dims[[0, 2]]))
    np.testing.assert_allclose(head.pos, final.pos[[0, 2]])
    np.testing.assert_allclose(head.yaw, [4.0 - 2 * np.pi, -3.5 + 2 * np.pi], rtol=1e-6)
    mask, _ = to_labels(final, output, "mask", GRID)
    for k, query in enumerate((0, 2)):
        fit = fit_box(det_masks[query], GRID)  # the segment's largest piece
        np.testing.assert_allclose(mask.boxes_bev()[k], fit, atol=1e-6)
        # z and height stay the head's: a BEV mask does not see them.
        assert mask.pos[k, 2] == final.pos[query, 2] and mask.dims[k, 2] == final.dims[query, 2]
    np.testing.assert_array_equal(mask.classes, [1, 3])
    _, ids = to_labels(final, output, "mask", GRID)
    np.testing.assert_array_equal(ids, np.where(panoptic == 3, 2, panoptic))  # line k: id k + 1
    expected = [fit_box(det_masks[2], GRID), fit_box(det_masks[0], GRID)]
    np.testing.assert_allclose(segment_boxes(panoptic, [3, 1], GRID), expected)
    with pytest.raises(ValueError, match="segment 2 has no cell"):
        segment_boxes(panoptic, [2], GRID)
    # A transposed (or cropped) map is refused: it fitted boxes in the wrong place.
    with pytest.raises(ValueError, match=r"instance_ids: expected shape \(\d+, \d+\) \(the grid\)"):
        segment_boxes(panoptic.T, [3], GRID)
    with pytest.raises(ValueError, match=r"ids must be >= 1 \(0 is the background\), got \[0\]"):
        segment_boxes(panoptic, [0, 3], GRID)
    with pytest.raises(ValueError, match='boxes="mask" needs the grid'):
        to_labels(final, output, "mask")
    with pytest.raises(ValueError, match=r"boxes: expected one of \('head', 'mask'\)"):
        to_labels(final, output, "masks", GRID)


def test_largest_piece_keeps_the_biggest_8_connected_part():
    mask = np.zeros((6, 8), bool)
    mask[0:2, 0:2] = True  # 4 cells
    mask[3, 3], mask[4, 4], mask[5, 5] = True, True, True  # 3 cells, joined diagonally
    mask[2, 7] = True
    np.testing.assert_array_equal(largest_piece(mask), mask & (np.arange(6)[:, None] < 2))
    mask[5, 6] = mask[4, 6] = True  # the diagonal piece grows to 5
    expected = np.zeros_like(mask)
    expected[3, 3] = expected[4, 4] = expected[5, 5] = expected[5, 6] = expected[4, 6] = True
    np.testing.assert_array_equal(largest_piece(mask), expected)
