"""Grid and angle helpers shared by every stage (DESIGN section 2).

The workspace rule lives here once: closed in x, y and z (DESIGN 2: x, y in [-5, 5], z in
[-3, 3]); cell (row, col) of a point is ``floor((y - y_min) / v), floor((x - x_min) / v)``,
except that x = x_max (y = y_max) falls in the last column (row).
``wrap_angle`` and ``in_workspace`` use plain operators, so numpy and JAX arrays both work.
"""

from __future__ import annotations

import math

import jax
import jax.numpy as jnp
import numpy as np

from indoorbev_jax.config import GridConfig


def wrap_angle(a):
    """Angles wrapped to [-pi, pi) (numpy, JAX or Python floats)."""
    return (a + math.pi) % (2 * math.pi) - math.pi


# Points whose |intensity| exceeds this are unusable, like non-finite ones: the encoder's
# LayerNorm variance overflows float32 near 1e20 and NaNs the whole frame's output. Real
# units (Livox 0-255, percent, [0, 1]) stay far below it.
MAX_ABS_INTENSITY = 1e6


def usable(points):
    """bool [...]: points ``[..., 4]`` with finite coordinates and a finite intensity of at
    most ``MAX_ABS_INTENSITY`` in size (numpy or JAX arrays)."""
    xp = jnp if isinstance(points, jax.Array) else np
    return xp.isfinite(points).all(-1) & (xp.abs(points[..., 3]) <= MAX_ABS_INTENSITY)


def as_points(points, name: str = "points") -> np.ndarray:
    """float32 [N, 4] (x, y, z, intensity) from a numeric [N, 3] (intensity 0) or [N, 4+]
    (columns past the fourth dropped) array; anything else is refused, naming ``name``.

    A flat reshape to [N, 4] would read an open3d [N, 3] cloud as groups of four numbers,
    and a channels-first [C, N] cloud read as C points finds nothing, without a word.
    """
    arr = np.asarray(points)
    if arr.ndim != 2 or arr.shape[1] < 3 or arr.dtype.kind not in "fiu":
        raise ValueError(
            f"{name}: expected a numeric array [N, 3] or [N, 4+] (x, y, z[, intensity]), "
            f"got {arr.dtype} {list(arr.shape)}"
        )
    if arr.shape[0] in (3, 4, 5) and arr.shape[1] > 16:
        raise ValueError(
            f"{name}: shape {list(arr.shape)} looks channels-first ([C, N], as nuScenes and "
            "many torch pipelines keep clouds); expected [N, C]: transpose it (arr.T)"
        )
    if arr.shape[1] == 4:
        return arr.astype(np.float32, copy=False)
    out = np.zeros((arr.shape[0], 4), np.float32)
    out[:, : min(4, arr.shape[1])] = arr[:, :4]
    return out


def on_grid(x, y, grid: GridConfig):
    """bool [...]: (x, y) inside the grid's closed x and y ranges; NaN is outside (numpy or
    JAX arrays)."""
    return (
        (x >= grid.x_range[0])
        & (x <= grid.x_range[1])
        & (y >= grid.y_range[0])
        & (y <= grid.y_range[1])
    )


def in_workspace(xyz, grid: GridConfig):
    """bool [...]: points ``xyz [..., 3+]`` inside the workspace; NaN is outside."""
    z = xyz[..., 2]
    return on_grid(xyz[..., 0], xyz[..., 1], grid) & (z >= grid.z_range[0]) & (z <= grid.z_range[1])


def cell_centers(grid: GridConfig) -> tuple[jax.Array, jax.Array]:
    """Cell-centre coordinates of the grid.

    Returns:
      (xs, ys): float32 arrays of shape [W] (column centres along x) and [H] (row centres
      along y).
    """
    h, w = grid.shape
    xs = grid.x_range[0] + (jnp.arange(w, dtype=jnp.float32) + 0.5) * grid.cell_size
    ys = grid.y_range[0] + (jnp.arange(h, dtype=jnp.float32) + 0.5) * grid.cell_size
    return xs, ys


def cell_index(x: jax.Array, y: jax.Array, grid: GridConfig):
    """The cells under points (x, y) of any shape.

    Returns:
      (row, col, inside): int32 row and column clipped into the grid, and bool ``inside``,
      False where (x, y) lies outside the grid's closed x and y ranges (NaN included).
    """
    h, w = grid.shape
    col = jnp.floor((x - grid.x_range[0]) / grid.cell_size).astype(jnp.int32)
    row = jnp.floor((y - grid.y_range[0]) / grid.cell_size).astype(jnp.int32)
    return jnp.clip(row, 0, h - 1), jnp.clip(col, 0, w - 1), on_grid(x, y, grid)


def box_corners(xy, lw, yaw) -> np.ndarray:
    """float [M, 4, 2]: xy corners of boxes with centres ``xy [M, 2]``, sizes ``lw [M, 2]``
    (length along the heading, width) and headings ``yaw [M]``, counter-clockwise from
    (+length/2, +width/2) in the box frame."""
    xy, lw, yaw = np.asarray(xy), np.asarray(lw), np.asarray(yaw)
    c, s = np.cos(yaw), np.sin(yaw)  # [M]
    signs = np.array([(1, 1), (-1, 1), (-1, -1), (1, -1)], np.float32)  # [4, 2]
    half = signs[None] * lw[:, None, :] / 2  # [M, 4, 2] in the box frame
    x = c[:, None] * half[..., 0] - s[:, None] * half[..., 1]  # [M, 4]
    y = s[:, None] * half[..., 0] + c[:, None] * half[..., 1]  # [M, 4]
    return np.stack([x, y], -1) + xy[:, None, :]
