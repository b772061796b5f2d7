"""The rasteriser against a float64 polygon-containment reference (matplotlib-free: shapely)."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest
import shapely
from shapely.geometry import Polygon

from indoorbev_jax.config import GridConfig
from indoorbev_jax.data.rasterize import instance_ids_from_masks, rasterize_boxes
from indoorbev_jax.geometry import cell_index, in_workspace

GRID = GridConfig(x_range=(-5.0, 5.0), y_range=(-4.0, 4.0), cell_size=0.25)  # H 32, W 40
rasterize = jax.jit(rasterize_boxes, static_argnums=2)


def reference_mask(box, grid):
    """Cells whose centre the box polygon covers (boundary included), in float64."""
    x, y, length, width, yaw = (float(v) for v in box)
    c, s = np.cos(yaw), np.sin(yaw)
    corners = [
        (x + c * a - s * b, y + s * a + c * b)
        for a, b in (
            (length / 2, width / 2),
            (-length / 2, width / 2),
            (-length / 2, -width / 2),
            (length / 2, -width / 2),
        )
    ]
    h, w = grid.shape
    xs = grid.x_range[0] + (np.arange(w) + 0.5) * grid.cell_size
    ys = grid.y_range[0] + (np.arange(h) + 0.5) * grid.cell_size
    px, py = np.meshgrid(xs, ys)  # [H, W]
    poly = Polygon(corners)
    return shapely.covers(poly, shapely.points(px, py))


def random_boxes(rng, n):
    kind = rng.integers(0, 4, n)
    x = rng.uniform(-6.5, 6.5, n)  # some partly or wholly outside the grid
    y = rng.uniform(-5.5, 5.5, n)
    length = np.where(kind == 0, rng.uniform(0.01, 0.2, n), rng.uniform(0.1, 4.0, n))  # tiny
    width = np.where(kind == 0, rng.uniform(0.01, 0.2, n), rng.uniform(0.1, 3.0, n))
    yaw = rng.uniform(-3 * np.pi, 3 * np.pi, n)  # beyond +-pi
    yaw = np.where(kind == 1, rng.integers(-4, 5, n) * np.pi / 2, yaw)  # axis-aligned
    return np.stack([x, y, length, width, yaw], 1).astype(np.float32)


def test_matches_polygon_reference_on_1000_random_boxes():
    rng = np.random.default_rng(0)
    boxes = random_boxes(rng, 1000)
    _, masks = rasterize(jnp.asarray(boxes), jnp.ones(1000, bool), GRID)
    masks = np.asarray(masks)
    for k, box in enumerate(boxes):
        ref = reference_mask(box.astype(np.float64), GRID)
        np.testing.assert_array_equal(masks[k], ref, err_msg=f"box {k}: {box}")


def test_edges_on_cell_centres_count_as_inside():
    # Axis-aligned box whose edges pass exactly through cell centres (cell size 0.25).
    box = np.array([[0.125, 0.125, 0.5, 1.0, 0.0]], np.float32)
    _, masks = rasterize(jnp.asarray(box), jnp.ones(1, bool), GRID)
    ref = reference_mask(box[0].astype(np.float64), GRID)
    np.testing.assert_array_equal(np.asarray(masks[0]), ref)
    assert ref.sum() == 3 * 5  # x centres -0.125, 0.125, 0.375; y centres -0.375..0.625


def test_python_lists_rasterize_as_arrays_do():
    """The issue's call with plain lists (read .shape before converting them, it raised)."""
    box = [[0.125, 0.125, 0.5, 1.0, 0.0]]
    ids, masks = rasterize_boxes(box, [True], GRID)
    ref = reference_mask(np.array(box[0]), GRID)
    np.testing.assert_array_equal(np.asarray(masks[0]), ref)
    np.testing.assert_array_equal(np.asarray(ids), ref.astype(np.int32))


def test_invalid_boxes_and_outside_boxes_are_empty():
    boxes = jnp.array([[0.0, 0.0, 1.0, 1.0, 0.0], [20.0, 0.0, 1.0, 1.0, 0.3]])
    ids, masks = rasterize(boxes, jnp.array([False, True]), GRID)
    assert not masks.any()
    assert (ids == 0).all()


def test_overlap_goes_to_the_smaller_footprint_ties_to_lower_index():
    boxes = jnp.array(
        [
            [0.0, 0.0, 3.0, 3.0, 0.0],  # big table
            [0.0, 0.0, 1.0, 1.0, 0.0],  # chair under it
            [0.0, 0.0, 1.0, 1.0, 0.0],
        ]  # identical chair: loses the tie
    )
    ids, masks = rasterize(boxes, jnp.ones(3, bool), GRID)
    ids, masks = np.asarray(ids), np.asarray(masks)
    np.testing.assert_array_equal(ids == 2, masks[1])
    assert not (ids == 3).any()
    np.testing.assert_array_equal(ids == 1, masks[0] & ~masks[1])
    np.testing.assert_array_equal(ids == 0, ~masks.any(0))


def test_vmap_equals_loop_and_ids_agree_with_masks():
    rng = np.random.default_rng(1)
    boxes = random_boxes(rng, 3 * 6).reshape(3, 6, 5)
    valid = rng.random((3, 6)) > 0.3
    ids, masks = jax.vmap(rasterize_boxes, in_axes=(0, 0, None))(boxes, valid, GRID)
    for b in range(3):
        ids_b, masks_b = rasterize(boxes[b], valid[b], GRID)
        np.testing.assert_array_equal(ids[b], ids_b)
        np.testing.assert_array_equal(masks[b], masks_b)
        np.testing.assert_array_equal(ids_b, instance_ids_from_masks(masks_b, valid[b]))


def test_bad_shapes_are_named():
    with pytest.raises(ValueError, match=r"boxes: expected shape \[N, 5\]"):
        rasterize_boxes(jnp.zeros((3, 4)), jnp.ones(3, bool), GRID)
    with pytest.raises(ValueError, match="valid: expected shape"):
        rasterize_boxes(jnp.zeros((3, 5)), jnp.ones(2, bool), GRID)
    # The right length is not enough: a column of flags or a scalar is not [N] either (a
    # check of the length alone let [3, 1] through to an unnamed unpacking error).
    for valid in (jnp.ones((3, 1), bool), jnp.ones((), bool)):
        with pytest.raises(ValueError, match=r"valid: expected shape \(3,\), got \("):
            rasterize_boxes(jnp.zeros((3, 5)), valid, GRID)


def test_instance_ids_equal_a_numpy_rederivation_with_ties():
    rng = np.random.default_rng(4)
    masks = rng.random((7, 32, 40)) < 0.3
    masks[4] = masks[1]  # equal areas everywhere they overlap: ties go to index 1
    valid = np.array([True, True, True, False, True, True, True])
    ids = np.asarray(jax.jit(instance_ids_from_masks)(masks, valid))
    claim = masks & valid[:, None, None]
    area = claim.sum((1, 2))
    expected = np.zeros((32, 40), np.int32)
    for r, c in np.ndindex(32, 40):
        owners = [k for k in range(7) if claim[k, r, c]]
        if owners:
            expected[r, c] = min(owners, key=lambda k: (area[k], k)) + 1
    np.testing.assert_array_equal(ids, expected)
    assert not (ids == 5).any() and (ids == 2).any()  # the copy of mask 1 never wins


def test_no_boxes_give_an_empty_map():
    """A frame without objects (N = 0): an all-background map of the grid's shape and no
    masks, eagerly and jitted (the reduction over no masks has no identity)."""
    h, w = GRID.shape
    for run in (rasterize_boxes, rasterize):
        ids, masks = run(jnp.zeros((0, 5)), jnp.zeros(0, bool), GRID)
        assert ids.shape == (h, w) and ids.dtype == jnp.int32 and not np.asarray(ids).any()
        assert masks.shape == (0, h, w)
    ids = instance_ids_from_masks(np.zeros((0, h, w), bool), np.zeros(0, bool))
    np.testing.assert_array_equal(ids, np.zeros((h, w), np.int32))


def test_edges_through_inexact_cell_centres_count_as_inside():
    """Boxes on a 0.1 m grid whose edges pass through cell centres (not exact in float32),
    at each quarter-turn heading, cover exactly the cells from edge to edge: columns
    c0..c1, rows r0..r1. Without the boundary slack most of them lost an edge row or column
    (the 0.25 m grids above hold exact centres; a mutation audit)."""
    grid = GridConfig(x_range=(-5.0, 5.0), y_range=(-4.0, 4.0), cell_size=0.1)  # H 80, W 100
    h, w = grid.shape
    rng = np.random.default_rng(2)
    n = 300
    c0, r0 = rng.integers(0, w, n), rng.integers(0, h, n)
    c1, r1 = c0 + rng.integers(1, 25, n), r0 + rng.integers(1, 25, n)  # some past the edge
    turn = rng.integers(0, 4, n)
    v = grid.cell_size
    span_x, span_y = (c1 - c0) * v, (r1 - r0) * v
    boxes = np.stack([
        grid.x_range[0] + (c0 + c1 + 1) / 2 * v, grid.y_range[0] + (r0 + r1 + 1) / 2 * v,
        np.where(turn % 2, span_y, span_x), np.where(turn % 2, span_x, span_y),
        turn * np.pi / 2,
    ], 1).astype(np.float32)  # fmt: skip
    _, masks = rasterize(jnp.asarray(boxes), jnp.ones(n, bool), grid)
    rows, cols = np.arange(h)[:, None], np.arange(w)[None, :]
    for k, mask in enumerate(np.asarray(masks)):
        want = (rows >= r0[k]) & (rows <= r1[k]) & (cols >= c0[k]) & (cols <= c1[k])
        np.testing.assert_array_equal(mask, want, err_msg=f"box {k}: {boxes[k]}")


def test_cell_index_on_a_workspace_not_centred_on_the_sensor():
    """The cell of (x, y) is (floor((y - y_min)/v), floor((x - x_min)/v)), clipped: on a
    forward-looking grid (x from 0, y from -4) rows and columns start at different origins,
    which the centred grids of the other tests cannot tell apart. The grid is not square,
    so rows clip at H - 1 and columns at W - 1 (a mutation audit: the two bounds swapped
    passed on a square one)."""
    grid = GridConfig(x_range=(0.0, 8.0), y_range=(-3.0, 3.0), cell_size=0.5)  # H 12, W 16
    assert grid.shape == (12, 16)
    rng = np.random.default_rng(3)
    x = rng.uniform(-1.0, 9.0, 500).astype(np.float32)
    y = rng.uniform(-4.0, 4.0, 500).astype(np.float32)
    row, col, inside = cell_index(jnp.asarray(x), jnp.asarray(y), grid)
    v = np.float32(0.5)
    want_row = np.clip(np.floor((y - np.float32(-3.0)) / v), 0, 11).astype(np.int32)
    want_col = np.clip(np.floor((x - np.float32(0.0)) / v), 0, 15).astype(np.int32)
    want_inside = (x >= 0) & (x <= 8) & (y >= -3) & (y <= 3)
    np.testing.assert_array_equal(np.asarray(row), want_row)
    np.testing.assert_array_equal(np.asarray(col), want_col)
    np.testing.assert_array_equal(np.asarray(inside), want_inside)
    assert 0 < want_inside.sum() < 500 and len(np.unique(want_row[want_inside])) == 12
    assert len(np.unique(want_col[want_inside])) == 16


def test_the_workspace_is_closed_in_z():
    """DESIGN section 2: the workspace is closed, so z = z_min and z = z_max are inside (a
    floor return at exactly z_min counts) and the next float beyond either is outside."""
    grid = GridConfig(x_range=(0.0, 8.0), y_range=(-4.0, 4.0), z_range=(-3.0, 3.0), cell_size=0.5)
    lo, hi = np.float32(-3.0), np.float32(3.0)
    z = np.array([lo, hi, np.nextafter(lo, -np.inf), np.nextafter(hi, np.inf), 0.0], np.float32)
    xyz = np.stack([np.full(5, 1.0, np.float32), np.zeros(5, np.float32), z], 1)
    np.testing.assert_array_equal(in_workspace(xyz, grid), [True, True, False, False, True])
    np.testing.assert_array_equal(
        np.asarray(in_workspace(jnp.asarray(xyz), grid)), [True, True, False, False, True]
    )


def test_the_workspace_is_closed_in_x_and_y_and_its_far_edges_fall_in_the_last_cells():
    """DESIGN section 2 and geometry.on_grid: the workspace is closed in x and y as in z, so
    x = x_max and y = y_max are inside (the next float beyond is outside), and ``cell_index``
    puts them in the last column and row (floor((x_max - x_min) / v) = W clipped to W - 1).
    A mutation audit (x <= x_max made x < x_max) passed all tests."""
    grid = GridConfig(x_range=(0.0, 8.0), y_range=(-4.0, 4.0), z_range=(-3.0, 3.0), cell_size=0.5)
    h, w = grid.shape
    x_max, y_max = np.float32(8.0), np.float32(4.0)
    x = np.array([x_max, 0.0, 4.0, 4.0, x_max, np.nextafter(x_max, np.inf), 4.0], np.float32)
    y = np.array([0.0, 0.0, y_max, -4.0, y_max, 0.0, np.nextafter(y_max, np.inf)], np.float32)
    expected = [True, True, True, True, True, False, False]
    xyz = np.stack([x, y, np.zeros_like(x)], 1)
    np.testing.assert_array_equal(in_workspace(xyz, grid), expected)
    np.testing.assert_array_equal(np.asarray(in_workspace(jnp.asarray(xyz), grid)), expected)
    row, col, inside = (np.asarray(a) for a in cell_index(jnp.asarray(x), jnp.asarray(y), grid))
    np.testing.assert_array_equal(inside, expected)
    # Expected cells from DESIGN section 2 (column j covers x_min + [j, j + 1) v), the far
    # edge clipped into the last column / row.
    np.testing.assert_array_equal(col[:5], np.minimum((x[:5] - 0.0) // 0.5, w - 1))
    np.testing.assert_array_equal(row[:5], np.minimum((y[:5] + 4.0) // 0.5, h - 1))
    assert col[0] == w - 1 and row[2] == h - 1 and (row[4], col[4]) == (h - 1, w - 1)
