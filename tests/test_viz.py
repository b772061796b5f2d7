"""BEV pictures: points land on their pixels (x right, y up); nothing off the grid drawn."""

import numpy as np

from indoorbev_jax import viz
from indoorbev_jax.config import CLASS_NAMES, Config

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
