"""BEV pictures: points land on their pixels (x right, y up); nothing off the grid drawn."""

import numpy as np
from PIL import Image

from indoorbev_jax import viz
from indoorbev_jax.config import CLASS_NAMES, Config, GridConfig
from indoorbev_jax.data import kitti

GRID = Config.tiny().grid  # x, y in [-5, 5] m, 0.25 m cells: a 600 x 600 picture, 60 px/m


def _changed(points):
    empty = np.asarray(viz.render_bev(np.zeros((0, 4)), None, None, GRID, CLASS_NAMES))
    drawn = np.asarray(viz.render_bev(np.asarray(points, float), None, None, GRID, CLASS_NAMES))
    return np.argwhere((drawn != empty).any(-1))  # (row, column) pixels


def test_a_point_lands_on_its_pixels():
    # (4, 1): column (4 + 5) * 60 = 540, row (5 - 1) * 60 = 240; a 2 x 2 dot.
    assert _changed([[4.0, 1.0, 0.5, 0.3]]).tolist() == [[240, 540], [240, 541], [241, 540],
                                                          [241, 541]]  # fmt: skip


def test_points_off_the_grid_and_nan_points_are_not_drawn():
    """They were clipped onto the border: a wall 8 m ahead showed at the 5 m edge."""
    inside = _changed([[4.0, 1.0, 0.5, 0.3]])
    outside = [[8.0, 1.0, 0.5, 0.3], [0.0, -7.0, 0.5, 0.3], [np.nan, 0.0, 0.5, 0.3]]
    np.testing.assert_array_equal(_changed([[4.0, 1.0, 0.5, 0.3], *outside]), inside)
    # The grid's far edges are on it: drawn on the last pixels.
    assert _changed([[5.0, -5.0, 0.5, 0.3]]).max(0).tolist() == [599, 599]


def _pixel(x, y):
    """(row, column) of a lidar-frame point in a GRID picture (x right, y up), from the grid."""
    s = 600 // GRID.shape[1]
    return (int((GRID.y_range[1] - y) / GRID.cell_size * s),
            int((x - GRID.x_range[0]) / GRID.cell_size * s))  # fmt: skip


def _boxes(centres, yaws):
    n = len(centres)
    pos = [[x, y, 0.5] for x, y in centres]
    return kitti.ObjectLabels([0] * n, [[1.0, 1.0, 1.0]] * n, pos, list(yaws), [0] * n)


def test_footprints_lie_under_their_boxes_in_the_boxes_colours():
    """Footprint ids were drawn mirrored in y (away from their points and boxes), or each in
    the next box's colour: id k + 1 is object k, its fill a dimmed copy of box k's outline."""
    centres = [(2.0, 3.0), (-2.0, -3.0)]
    h, w = GRID.shape
    # Cell centres as GridConfig documents them: row i along y, column j along x.
    ys = GRID.y_range[0] + (np.arange(h) + 0.5) * GRID.cell_size
    xs = GRID.x_range[0] + (np.arange(w) + 0.5) * GRID.cell_size
    ids = np.zeros((h, w), np.int32)
    for k, (x, y) in enumerate(centres):
        ids[(np.abs(ys[:, None] - y) < 0.5) & (np.abs(xs[None] - x) < 0.5)] = k + 1
    img = np.asarray(viz.render_bev(np.zeros((0, 4)), _boxes(centres, [0, 0]), ids, GRID,
                                    CLASS_NAMES)).astype(int)  # fmt: skip
    for x, y in centres:
        outline = img[_pixel(x - 0.5, y)]  # the box's left edge
        fill = img[_pixel(x - 0.25, y + 0.25)]  # inside the box, clear of the tick and text
        np.testing.assert_array_equal(fill, outline // 2 + 10, err_msg=f"box at {(x, y)}")
        # The mirror image (y -> -y) of the fill is background: no other footprint there.
        np.testing.assert_array_equal(img[_pixel(x - 0.25, -y - 0.25)], [20, 20, 20])
    assert not np.array_equal(img[_pixel(1.75, 3.25)], img[_pixel(-2.25, -2.75)])


def test_heading_tick_points_along_the_yaw():
    """Yaw is about +z from +x (docs/DATASET.md): yaw 0 ticks towards +x (right), yaw pi/2
    towards +y (up). x and y were swapped."""
    for yaw, along, across in ((0.0, (2.45, 3.0), (2.0, 3.45)),
                               (np.pi / 2, (2.0, 3.45), (2.45, 3.0))):  # fmt: skip
        img = np.asarray(viz.render_bev(np.zeros((0, 4)), _boxes([(2.0, 3.0)], [yaw]), None,
                                        GRID, CLASS_NAMES))  # fmt: skip
        outline = img[_pixel(1.5, 3.0)]
        assert outline.tolist() != [20, 20, 20]
        np.testing.assert_array_equal(img[_pixel(*along)], outline, err_msg=f"yaw {yaw}")
        np.testing.assert_array_equal(img[_pixel(*across)], [20, 20, 20], err_msg=f"yaw {yaw}")
        # The tick ends at the box's front edge (x + 0.5 for yaw 0): beyond it, background.
        beyond = (2.6, 3.0) if yaw == 0.0 else (2.0, 3.6)
        np.testing.assert_array_equal(img[_pixel(*beyond)], [20, 20, 20], err_msg=f"yaw {yaw}")


def test_height_ramp_runs_blue_green_red():
    """Low z blue, mid green, high red (the ramp's halves were swapped)."""
    lo, hi = GRID.z_range
    low, mid, high = viz.height_colour(np.array([lo, (lo + hi) / 2, hi]), GRID.z_range)
    assert low.argmax() == 2 and mid.argmax() == 1 and high.argmax() == 0, (low, mid, high)
    # Linear in each half and continuous at the middle (a half-slope first half jumped
    # there and passed): each quarter point is the blend of its half's ends.
    z = lo + (hi - lo) * np.array([0.0, 0.25, 0.5 - 1e-6, 0.5, 0.75, 1.0])
    c = viz.height_colour(z, GRID.z_range).astype(int)
    assert np.abs(c[1] - (c[0] + c[3]) / 2).max() <= 1 and np.abs(c[2] - c[3]).max() <= 1
    assert np.abs(c[4] - (c[3] + c[5]) / 2).max() <= 1, c
    # Outside z_range the ends' colours, not a wrapped uint8 (render_bev draws such points:
    # its on-grid test is x and y only).
    outside = viz.height_colour(np.array([lo - 2.0, hi + 2.0]), GRID.z_range)
    np.testing.assert_array_equal(outside, c[[0, 5]])


def test_higher_points_are_drawn_on_top():
    """Of two points on one pixel the higher is drawn last, whatever their order."""
    lo, hi = GRID.z_range
    pts = np.array([[1.0, 1.0, hi - 0.01, 0.0], [1.0, 1.0, lo + 0.01, 0.0]])
    for order in (pts, pts[::-1]):
        img = np.asarray(viz.render_bev(order, None, None, GRID, CLASS_NAMES))
        dot = img[_pixel(1.0, 1.0)]
        assert dot.argmax() == 0, dot  # red: the high point
        np.testing.assert_array_equal(dot, viz.height_colour(pts[:1, 2], GRID.z_range)[0])


def test_pictures_are_at_least_min_size_wide():
    """The scale is the smallest whole number of pixels a cell that makes the picture
    min_size wide (it rounded down: a 500-cell grid gave a 500-pixel picture)."""
    for cell, x_range, want in ((0.25, (-5.0, 5.0), 15), (0.02, (-5.0, 5.0), 2),
                                (1.0, (0.0, 7.0), 86)):  # fmt: skip
        grid = GridConfig(x_range=x_range, cell_size=cell)
        w = grid.shape[1]
        scale = viz.picture_scale(grid)
        assert scale * w >= 600 and (scale - 1) * w < 600 and scale == want, (grid, scale)
        assert viz.picture_scale(grid, pixels_per_cell=want + 3) == want + 3
    pic = viz.render_bev(np.zeros((0, 4)), None, None, GridConfig(cell_size=0.02), CLASS_NAMES)
    assert pic.size == (1000, 1000)


def test_masks_image_blends_overlaps_as_the_mean_colour():
    """An overlap is the mean of the masks' colours (the sum was written, wrapping uint8)."""
    masks = np.zeros((2, 4, 4), bool)
    masks[0, :2] = True
    masks[1, 1:3] = True  # row 1 in both, row 3 in neither
    img = viz.masks_image(masks).astype(int)
    a, b = img[0, 0], img[2, 0]
    assert not np.array_equal(a, b)
    assert np.abs(img[1] - (a + b) / 2).max() <= 0.5 + 1e-9
    np.testing.assert_array_equal(img[3], 20)


def test_feature_image_red_is_the_first_principal_component():
    """Two regions whose features differ along one direction are black and white in red
    (the first component), whatever offset the features share: they were not centred, so
    the offset took the first component."""
    rng = np.random.default_rng(0)
    feat = 100.0 + np.zeros((8, 8, 4))  # a common offset along (1, 1, 1, 1)
    feat[:, :4, 0] += 1.0
    feat[:, :4, 1] -= 1.0  # the left half differs along ch0 - ch1
    feat += 0.01 * rng.normal(size=feat.shape)
    red = viz.feature_image(feat)[..., 0].astype(float)
    left, right = red[:, :4].mean(), red[:, 4:].mean()
    assert abs(left - right) > 230, (left, right)


def test_panels_show_every_image_whole_below_its_title():
    """The titles' band was not added to the height: the images' last 18 rows were cut."""
    a = Image.fromarray(np.full((50, 40, 3), 200, np.uint8))
    b = Image.fromarray(np.full((30, 20, 3), 100, np.uint8))
    out = np.asarray(viz.panels([("a", a), ("b", b)], gap=8))
    assert out.shape[1] == 40 + 8 + 20
    assert (out[:, :40] == 200).all(-1).all(-1).sum() == 50  # rows wholly image a
    assert (out[:, 48:] == 100).all(-1).all(-1).sum() == 30
    assert out.shape[0] > 50 and (out[-50:, :40] == 200).all()


def test_a_wide_grid_draws_a_point_near_its_right_edge_at_its_place():
    """On a grid wider than tall (DESIGN 2 allows H != W) a point near the right edge is drawn at
    its own column. Guards against clipping the column to the picture's height."""
    grid = GridConfig(y_range=(-2.0, 2.0), cell_size=0.25)  # 16 x 40 cells
    h, w = grid.shape
    assert h < w
    empty = np.asarray(viz.render_bev(np.zeros((0, 4)), None, None, grid, CLASS_NAMES))
    x = 4.4
    img = np.asarray(viz.render_bev(np.array([[x, 0.0, 0.0, 0.0]]), None, None, grid, CLASS_NAMES))
    cols = np.argwhere((img != empty).any(-1))[:, 1]
    s = viz.picture_scale(grid)
    assert img.shape[1] == w * s and w * s >= 600
    assert cols.min() == int((x - grid.x_range[0]) / grid.cell_size * s), cols


def test_each_box_is_named_by_its_own_class_and_score(monkeypatch):
    """The text by a box is its class name and score. A mutation audit: names taken by the
    box's line number (a Person labelled Table) passed."""
    from PIL import ImageDraw

    said = []
    draw_text = ImageDraw.ImageDraw.text

    def text(self, xy, words, *args, **kwargs):
        said.append(words)
        return draw_text(self, xy, words, *args, **kwargs)

    monkeypatch.setattr(ImageDraw.ImageDraw, "text", text)
    person = CLASS_NAMES.index("Person")
    labels = kitti.ObjectLabels(
        classes=np.array([person, 0]),
        dims=np.array([[0.5, 0.5, 1.7], [1.2, 0.8, 0.75]]),
        pos=np.array([[1.0, 1.0, 0.85], [-2.0, 0.0, 0.375]]),
        yaw=np.zeros(2),
        occlusion=np.zeros(2, int),
        scores=np.array([0.9, 0.7]),
    )
    viz.render_bev(np.zeros((0, 4)), labels, None, GRID, CLASS_NAMES)
    assert "Person 0.90" in said and f"{CLASS_NAMES[0]} 0.70" in said
