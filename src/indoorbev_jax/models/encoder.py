"""AF-PCCN: the axis-fusion point encoder that turns a padded point cloud into a BEV map.

DESIGN section 5. Every valid point gets X-Z and Y-Z view features, two learned branches
and a learned fusion; the per-point features are scattered to the grid with a segment max
over flattened cell ids (no per-pillar padding), empty cells get one learned vector, and a
LayerNorm over channels gives ``F_bev`` of shape [B, H, W, C_enc].
"""

from __future__ import annotations

import flax.linen as nn
import jax
import jax.numpy as jnp

from indoorbev_jax.config import GridConfig
from indoorbev_jax.geometry import cell_index, in_workspace, usable
from indoorbev_jax.models.layers import Dense


def point_cells(
    points: jax.Array, valid: jax.Array, grid: GridConfig
) -> tuple[jax.Array, jax.Array, jax.Array, jax.Array]:
    """Cell indices and usability of each point (DESIGN section 2).

    Args:
      points: float [B, N, 4], (x, y, z, intensity) in the lidar frame.
      valid: bool [B, N].
      grid: the BEV grid.

    Returns:
      ``(points, ok, row, col)``: points with unusable entries zeroed [B, N, 4]; ok bool
      [B, N], True for valid, finite points inside the (closed) workspace (an intensity
      beyond ``geometry.MAX_ABS_INTENSITY`` counts as non-finite);
      row, col int32 [B, N] (clipped into the grid, meaningful only where ok).
    """
    finite = usable(points)
    pts = jnp.where(finite[..., None], points, 0.0)
    ok = valid & finite & in_workspace(pts, grid)
    row, col, _ = cell_index(pts[..., 0], pts[..., 1], grid)
    pts = jnp.where(ok[..., None], pts, 0.0)  # NaN / far-away points must not reach the MLPs
    return pts, ok, row, col


class _Branch(nn.Module):
    """Dense -> LayerNorm -> ReLU -> Dense on one axis view."""

    features: int

    @nn.compact
    def __call__(self, x: jax.Array) -> jax.Array:
        x = Dense(self.features, name="fc1")(x)
        x = nn.relu(nn.LayerNorm(name="norm")(x))
        return Dense(self.features, name="fc2")(x)


class AFPCCN(nn.Module):
    """Axis-Fusion Point Cloud Compact Network + BEV scatter + LayerNorm.

    Attributes:
      grid: the BEV grid (H x W from ``grid.shape``).
      channels: C_enc.
    """

    grid: GridConfig
    channels: int = 64

    @nn.compact
    def __call__(self, points: jax.Array, valid: jax.Array) -> jax.Array:
        """Encode points into the BEV map.

        Args:
          points: float [B, N, 4], (x, y, z, intensity in [0, 1]); NaN/Inf and out-of-range
            points are ignored, as are points with ``valid`` False.
          valid: bool [B, N].

        Returns:
          F_bev of shape [B, H, W, C_enc], float32.
        """
        if points.ndim != 3 or points.shape[-1] != 4:
            raise ValueError(f"points must be [B, N, 4], got shape {points.shape}")
        if valid.shape != points.shape[:2]:
            raise ValueError(f"valid must be [B, N] = {points.shape[:2]}, got {valid.shape}")
        if not (jnp.issubdtype(valid.dtype, jnp.bool_) or jnp.issubdtype(valid.dtype, jnp.integer)):
            raise ValueError(f"valid must be bool (or 0/1 integers) [B, N], got {valid.dtype}")
        valid = valid.astype(bool)
        b, n, _ = points.shape
        h, w = self.grid.shape
        v = self.grid.cell_size
        pts, ok, row, col = point_cells(points.astype(jnp.float32), valid, self.grid)
        x, y, z, intensity = (pts[..., k] for k in range(4))

        # Flattened cell id over the whole batch; unusable points get an out-of-range id,
        # which the segment ops drop.
        n_cells = b * h * w
        cell = jnp.arange(b, dtype=jnp.int32)[:, None] * (h * w) + row * w + col  # [B, N]
        cell = jnp.where(ok, cell, n_cells).reshape(-1)  # [B*N]

        count = jax.ops.segment_sum(ok.reshape(-1).astype(jnp.float32), cell, n_cells)
        z_sum = jax.ops.segment_sum(z.reshape(-1), cell, n_cells)
        z_mean = z_sum / jnp.maximum(count, 1.0)  # [B*H*W]
        dz = z - jnp.take(z_mean, cell, mode="fill", fill_value=0.0).reshape(b, n)  # [B, N]
        # Offsets to the cell centre in cell units, so they stay O(1) at any cell size.
        dx = (x - (self.grid.x_range[0] + (col + 0.5) * v)) / v
        dy = (y - (self.grid.y_range[0] + (row + 0.5) * v)) / v
        rng = jnp.sqrt(x * x + y * y)
        f_xz = jnp.stack([x, z, dx, dz, rng, intensity], axis=-1)  # [B, N, 6]
        f_yz = jnp.stack([y, z, dy, dz, rng, intensity], axis=-1)  # [B, N, 6]

        half = self.channels // 2
        feats = jnp.concatenate(
            [_Branch(half, name="branch_xz")(f_xz), _Branch(half, name="branch_yz")(f_yz)], -1
        )
        feats = Dense(self.channels, name="fuse")(feats)  # [B, N, C]
        self.sow("intermediates", "point_features", feats)

        flat = feats.reshape(b * n, feats.shape[-1])  # not -1: N may be 0
        bev = jax.ops.segment_max(flat, cell, n_cells)  # [B*H*W, C]
        empty = self.param("empty", nn.initializers.normal(0.02), (self.channels,), jnp.float32)
        bev = jnp.where((count > 0)[:, None], bev, empty[None, :])
        bev = bev.reshape(b, h, w, self.channels)  # [B, H, W, C]
        self.sow("intermediates", "bev_raw", bev)
        return nn.LayerNorm(name="norm")(bev)
