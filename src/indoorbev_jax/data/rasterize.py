"""Footprint rasterisation on the BEV grid (DESIGN sections 2-3).

A cell belongs to a footprint when its centre lies inside it, boundary included. Where
footprints overlap, the panoptic ``instance_ids`` map gives the cell to the object with the
fewest footprint cells (so a chair tucked under a table stays visible), ties to the lower
index. Per-object ``masks`` keep the overlaps.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp

from indoorbev_jax.config import GridConfig
from indoorbev_jax.geometry import cell_centers

# Slack for "boundary counts as inside": float32 coordinates of at most a few metres carry
# rounding of ~5e-7 m, so a centre lying exactly on an edge must not fall out by rounding.
BOUNDARY_EPS = 1e-6


def box_masks(boxes: jax.Array, grid: GridConfig) -> jax.Array:
    """Filled oriented rectangles.

    Args:
      boxes: float [N, 5] = (x, y, length, width, yaw), length along the heading.
      grid: the BEV grid.

    Returns:
      bool [N, H, W], True where the cell centre lies inside (or on) the box.
    """
    boxes = jnp.asarray(boxes, jnp.float32)
    if boxes.ndim != 2 or boxes.shape[-1] != 5:
        raise ValueError(f"boxes: expected shape [N, 5], got {boxes.shape}")
    xs, ys = cell_centers(grid)
    x, y, length, width, yaw = (boxes[:, k, None, None] for k in range(5))  # [N, 1, 1]
    dx = xs[None, None, :] - x  # [N, 1, W]
    dy = ys[None, :, None] - y  # [N, H, 1]
    cos, sin = jnp.cos(yaw), jnp.sin(yaw)
    along = cos * dx + sin * dy  # [N, H, W], coordinate along the heading
    across = -sin * dx + cos * dy  # [N, H, W]
    return (jnp.abs(along) <= 0.5 * length + BOUNDARY_EPS) & (
        jnp.abs(across) <= 0.5 * width + BOUNDARY_EPS
    )


def instance_ids_from_masks(masks: jax.Array, valid: jax.Array) -> jax.Array:
    """Panoptic map from per-object masks under the module's overlap rule.

    Args:
      masks: bool [N, H, W].
      valid: bool [N]; invalid objects never claim a cell.

    Returns:
      int32 [H, W]: 0 where no valid object covers the cell, else k + 1 for the covering
      object k with the fewest cells (ties to the lower k).
    """
    masks = jnp.asarray(masks, bool) & jnp.asarray(valid, bool)[:, None, None]
    if masks.shape[0] == 0:
        return jnp.zeros(masks.shape[1:], jnp.int32)
    n, h, w = masks.shape
    area = masks.sum(axis=(1, 2))  # [N]
    big = jnp.iinfo(jnp.int32).max
    if (h * w + 1) * n < big:
        # One min over (area, index) packed in an int32: ties go to the lower index, and
        # it is several times faster than argmin's variadic reduce on XLA:CPU.
        packed = area * n + jnp.arange(n, dtype=area.dtype)
        key = jnp.where(masks, packed[:, None, None], big)
        owner = jnp.min(key, axis=0) % n
    else:
        key = jnp.where(masks, area[:, None, None], big)  # [N, H, W]
        owner = jnp.argmin(key, axis=0)  # first minimum: ties go to the lower index
    return jnp.where(masks.any(axis=0), owner + 1, 0).astype(jnp.int32)


def rasterize_boxes(
    boxes: jax.Array, valid: jax.Array, grid: GridConfig
) -> tuple[jax.Array, jax.Array]:
    """Rasterise oriented boxes into per-object masks and a panoptic instance map.

    Jittable and vmappable (``grid`` is static)::

        ids, masks = rasterize_boxes(boxes, valid, Config.small().grid)
        batched = jax.vmap(rasterize_boxes, in_axes=(0, 0, None))

    Args:
      boxes: float [N, 5] = (x, y, length, width, yaw) in lidar metres.
      valid: bool [N].
      grid: the BEV grid.

    Returns:
      instance_ids: int32 [H, W], 0 = empty, k + 1 = box k (overlaps: fewest cells wins).
      masks: bool [N, H, W]; invalid boxes give all-False masks.
    """
    boxes, valid = jnp.asarray(boxes), jnp.asarray(valid, bool)  # lists too
    if valid.shape != boxes.shape[:1]:
        raise ValueError(f"valid: expected shape {boxes.shape[:1]}, got {valid.shape}")
    masks = box_masks(boxes, grid) & valid[:, None, None]
    return instance_ids_from_masks(masks, valid), masks
