"""IndoorBEV: AF-PCCN encoder -> Swin backbone -> AdaptiveUpsampler -> SimpleMaskHead.

The composer that builds the whole network from a ``Config`` (DESIGN section 1)::

    cfg = Config.tiny()
    model = IndoorBEV(cfg)
    params = model.init(jax.random.key(0), points, valid)
    preds = model.apply(params, points, valid)  # Predictions, masks [L, B, Q, H, W]
"""

from __future__ import annotations

from typing import Any

import flax.linen as nn
import jax
import jax.numpy as jnp

from indoorbev_jax.config import Config
from indoorbev_jax.models.encoder import AFPCCN
from indoorbev_jax.models.head import AdaptiveUpsampler, SimpleMaskHead
from indoorbev_jax.models.swin import SwinBackbone, padded_side
from indoorbev_jax.types import Predictions


class IndoorBEV(nn.Module):
    """The IndoorBEV network.

    Attributes:
      config: the run configuration (grid, encoder, backbone and head fields are read).
      dtype: computation dtype; None takes bfloat16 when ``config.train.bfloat16`` is set,
        else float32. Parameters, the encoder and the outputs stay float32.
    """

    config: Config
    dtype: Any = None

    @nn.compact
    def __call__(self, points: jax.Array, valid: jax.Array) -> Predictions:
        """Predict objects from a padded batch of point clouds.

        Args:
          points: float [B, N, 4], (x, y, z, intensity) in the lidar frame, metres, with
            intensity in [0, 1] as the simulator gives it (other units:
            ``predict.normalize_intensity``; 0-255 clouds find next to nothing).
          valid: bool [B, N]; invalid, non-finite and out-of-workspace points are ignored.

        Returns:
          ``Predictions`` with logits [L, B, Q, K], dims / pos [L, B, Q, 3], yaw [L, B, Q, 1]
          and masks [L, B, Q, H, W] on the unpadded grid (L decoder layers, the last final).
        """
        cfg = self.config
        dtype = self.dtype or (jnp.bfloat16 if cfg.train.bfloat16 else jnp.float32)
        h, w = cfg.grid.shape
        bev = AFPCCN(cfg.grid, cfg.encoder.channels, name="encoder")(points, valid)
        stages = SwinBackbone(cfg.backbone, dtype, name="backbone")(bev)
        steps = cfg.backbone.total_stride.bit_length() - 1  # strides are 1 or 2
        side_h, side_w = padded_side(h, cfg.backbone), padded_side(w, cfg.backbone)
        up = AdaptiveUpsampler(
            steps, cfg.head.hidden_dim, cfg.head.upsampler_skips, dtype, cfg.head.remat,
            name="upsampler",
        )(stages, jnp.pad(bev, ((0, 0), (0, side_h - h), (0, side_w - w), (0, 0))))  # fmt: skip
        up = up[:, :h, :w]  # [B, H, W, C'] crop the padding
        out = SimpleMaskHead(cfg.head, cfg.num_classes, dtype, cfg.grid, name="head")(up)
        return Predictions(**out)
