"""Boxes read off footprint masks: the smallest rectangle that covers a mask's cells.

The query head regresses each object's centre, size and yaw (paper, DESIGN 7), but its mask
locates the object far better: on the simulated test set the regressed BEV centres of the
shipped ``small`` model lie a median 0.26 m from the true ones (0.46 m with one view), the
centres of the rectangles around its masks 0.05 m (``experiments/pose_errors.py``,
docs/RESULTS.md "Box poses"). So the
outputs can take x, y, length, width and yaw from the mask (``BOX_SOURCES``: ``"mask"``)
and keep the head's z and height, which the BEV mask does not see.

A rectangle's heading is known only modulo 90 degrees; the fitted box takes length >= width
and yaw in [0, pi). Host-side numpy, per output object: a few hundred boundary cells.
"""

from __future__ import annotations

import numpy as np

from indoorbev_jax.config import GridConfig

BOX_SOURCES = ("head", "mask")  # where an output box's x, y, length, width and yaw come from
HEADINGS = 90  # candidate headings in [0, 90) degrees: 1 degree apart


def boundary_cells(mask: np.ndarray) -> np.ndarray:
    """bool [H, W]: cells of ``mask`` with a 4-neighbour outside it (or on the grid edge);
    the rectangle covering these covers the whole mask."""
    padded = np.pad(mask, 1)
    inner = (
        padded[:-2, 1:-1] & padded[2:, 1:-1] & padded[1:-1, :-2] & padded[1:-1, 2:]
    )  # all four neighbours in the mask
    return mask & ~inner


def fit_box(mask: np.ndarray, grid: GridConfig, headings: int = HEADINGS) -> np.ndarray:
    """The smallest rectangle over ``headings`` headings in [0, 90) degrees that covers the
    cells (whole squares, not centres) of a mask.

    Args:
      mask: bool [H, W] on ``grid``, at least one cell set.
      grid: the BEV grid (row i grows with y, column j with x, DESIGN 2).

    Returns:
      float64 [5]: (x, y, length, width, yaw) in the lidar frame, length >= width, yaw in
      [0, pi), the format of ``kitti.ObjectLabels.boxes_bev``.
    """
    mask = np.asarray(mask, bool)
    if mask.shape != grid.shape:
        raise ValueError(f"mask: expected shape {grid.shape} (the grid), got {mask.shape}")
    in_rows, in_cols = np.flatnonzero(mask.any(1)), np.flatnonzero(mask.any(0))
    if in_rows.size == 0:
        raise ValueError("mask: no cell set; an empty mask has no box")
    r0, c0 = in_rows[0], in_cols[0]  # the object's bounding cells only: 500 x 500 grids
    rows, cols = np.nonzero(boundary_cells(mask[r0 : in_rows[-1] + 1, c0 : in_cols[-1] + 1]))
    rows, cols = rows + r0, cols + c0
    v = grid.cell_size
    centres = np.stack(
        [grid.x_range[0] + (cols + 0.5) * v, grid.y_range[0] + (rows + 0.5) * v], axis=1
    )
    half = np.array([[1, 1], [1, -1], [-1, 1], [-1, -1]]) * (v / 2)
    corners = (centres[:, None] + half).reshape(-1, 2)  # [4N, 2]
    theta = np.arange(headings) * (np.pi / 2 / headings)
    along = np.stack([np.cos(theta), np.sin(theta)], axis=1)  # [S, 2]
    across = np.stack([-along[:, 1], along[:, 0]], axis=1)
    u, w = corners @ along.T, corners @ across.T  # [4N, S]
    u_lo, u_hi, w_lo, w_hi = u.min(0), u.max(0), w.min(0), w.max(0)
    k = int(np.argmin((u_hi - u_lo) * (w_hi - w_lo)))
    centre = (u_lo[k] + u_hi[k]) / 2 * along[k] + (w_lo[k] + w_hi[k]) / 2 * across[k]
    length, width, yaw = u_hi[k] - u_lo[k], w_hi[k] - w_lo[k], theta[k]
    if length < width:
        length, width, yaw = width, length, yaw + np.pi / 2
    return np.array([centre[0], centre[1], length, width, yaw])
