"""Boxes read off footprint masks: the smallest rectangle around a mask's cells.

The query head regresses each object's centre, size and yaw (paper, DESIGN 7), but its mask
locates the object far better (``experiments/pose_errors.py``, docs/RESULTS.md "Box
poses"). So the outputs can take x, y, length, width and yaw from the mask
(``BOX_SOURCES``: ``"mask"``): from the largest piece of the object's segment in the
panoptic map, the published ``mask_2``; z and height stay the head's, which a BEV mask does
not see.

A rectangle's heading is known only modulo 90 degrees; the fitted box takes length >= width
and yaw in [0, pi). Host-side numpy and scipy, per output object.
"""

from __future__ import annotations

import numpy as np
from scipy import ndimage

from indoorbev_jax.config import GridConfig

BOX_SOURCES = ("head", "mask")  # where an output box's x, y, length, width and yaw come from
HEADINGS = 90  # candidate headings in [0, 90) degrees: 1 degree apart
PAD_CELLS = 0.3  # cells added to the length and the width of the centres' extent


def check_box_source(boxes: str) -> None:
    """Raises ``ValueError`` unless ``boxes`` is one of ``BOX_SOURCES``."""
    if boxes not in BOX_SOURCES:
        raise ValueError(f"boxes: expected one of {BOX_SOURCES}, got {boxes!r}")


def largest_piece(mask: np.ndarray) -> np.ndarray:
    """bool [...]: the largest 8-connected piece of a 2D mask (the first in row order on a
    tie); a speck a mask leaves elsewhere then does not stretch its box."""
    labels, count = ndimage.label(mask, structure=np.ones((3, 3), bool))
    if count <= 1:
        return np.asarray(mask, bool)
    return labels == 1 + int(np.bincount(labels.ravel())[1:].argmax())


def _fit_cells(rows: np.ndarray, cols: np.ndarray, grid: GridConfig, headings: int) -> np.ndarray:
    """``fit_box`` of the cells (rows[k], cols[k]), given in row-major order."""
    v = grid.cell_size
    # Each row's first and last cell span the same convex hull as all of them.
    starts = np.flatnonzero(np.r_[True, rows[1:] != rows[:-1]])
    ends = np.r_[starts[1:], rows.size] - 1
    r = np.concatenate([rows[starts], rows[ends]])
    c = np.concatenate([cols[starts], cols[ends]])
    centres = np.stack([grid.x_range[0] + (c + 0.5) * v, grid.y_range[0] + (r + 0.5) * v], 1)
    theta = np.arange(headings) * (np.pi / 2 / headings)
    along = np.stack([np.cos(theta), np.sin(theta)], axis=1)  # [S, 2]
    across = np.stack([-along[:, 1], along[:, 0]], axis=1)
    u, w = centres @ along.T, centres @ across.T  # [2R, S]
    u_lo, u_hi, w_lo, w_hi = u.min(0), u.max(0), w.min(0), w.max(0)
    pad = PAD_CELLS * v
    k = int(np.argmin((u_hi - u_lo + pad) * (w_hi - w_lo + pad)))
    centre = (u_lo[k] + u_hi[k]) / 2 * along[k] + (w_lo[k] + w_hi[k]) / 2 * across[k]
    length, width, yaw = u_hi[k] - u_lo[k] + pad, w_hi[k] - w_lo[k] + pad, theta[k]
    if length < width:
        length, width, yaw = width, length, yaw + np.pi / 2
    return np.array([centre[0], centre[1], length, width, yaw])


def fit_box(mask: np.ndarray, grid: GridConfig, headings: int = HEADINGS) -> np.ndarray:
    """The smallest rectangle, over ``headings`` headings in [0, 90) degrees, around the
    centres of a mask's cells, its length and width then grown by ``PAD_CELLS`` cells.

    A cell is in a footprint when its centre is (``data.rasterize``), so the centres' extent
    understates a box and whole cells overstate it (they add up to half a cell at each end).
    ``PAD_CELLS`` = 0.3 leaves a mean bias under 0.01 m on rasterised random boxes
    (tests/test_boxes.py). Only each row's first and last cells are looked at: they span the
    same convex hull, so a speckled mask costs no more than a solid one.

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
    rows, cols = np.nonzero(mask)
    if rows.size == 0:
        raise ValueError("mask: no cell set; an empty mask has no box")
    return _fit_cells(rows, cols, grid, headings)


def segment_boxes(instance_ids: np.ndarray, ids, grid: GridConfig) -> np.ndarray:
    """float64 [K, 5]: ``fit_box`` of the largest piece of each segment ``instance_ids == id``
    of a panoptic map [H, W] (the published ``mask_2``), for the K ``ids``, each present."""
    instance_ids = np.asarray(instance_ids)
    if instance_ids.shape != grid.shape:  # a transposed map gave other boxes, silently
        raise ValueError(
            f"instance_ids: expected shape {grid.shape} (the grid), got {instance_ids.shape}"
        )
    ids = np.asarray(ids, np.int64).reshape(-1)
    if (ids < 1).any():
        raise ValueError(f"ids must be >= 1 (0 is the background), got {ids[ids < 1].tolist()}")
    slices = ndimage.find_objects(instance_ids, max_label=int(ids.max(initial=0)))
    out = np.zeros((len(ids), 5))
    for k, i in enumerate(ids):
        where = slices[i - 1] if i >= 1 else None
        if where is None:
            raise ValueError(f"instance_ids: segment {i} has no cell")
        rows, cols = np.nonzero(largest_piece(instance_ids[where] == i))
        out[k] = _fit_cells(rows + where[0].start, cols + where[1].start, grid, HEADINGS)
    return out
