"""Panoptic inference: raw query outputs -> panoptic BEV map and per-query detections.

DESIGN section 9. Pure JAX with static shapes, so it runs inside a jitted eval step:

* Panoptic map: a query is kept when its best foreground class probability is
  >= ``score_threshold`` (no NMS). Each cell goes to the kept query maximising
  ``p_cls * sigmoid(mask)`` among those whose mask probability there is >= ``mask_threshold``;
  cells with no such query are empty (id 0). A segment that keeps fewer than
  ``overlap_threshold`` of its own binarised mask is dropped (its cells become empty).
  Query q owns id q + 1, so ids are static; ids without cells are simply absent.
* Detections (for AP): every query with a non-empty binarised mask is one detection of its most
  probable foreground class, scored ``p_cls * mean(sigmoid(mask) inside the binarised mask)``.
  No score threshold: AP integrates over all scores.

Example::

    out = panoptic_inference(predictions, config.inference)  # last decoder layer
    out.instance_ids  # [B, H, W] int32, 0 = empty, q + 1 = query q
"""

from __future__ import annotations

import functools
import math

import jax
import jax.numpy as jnp
from flax import struct

from indoorbev_jax.config import InferenceConfig
from indoorbev_jax.types import Predictions


@struct.dataclass
class PanopticOutput:
    """Inference result for B frames with Q queries and K - 1 foreground classes.

    Attributes:
      instance_ids: int32 [B, H, W], the panoptic map: 0 = empty, q + 1 = query q.
      instance_classes: int32 [B, Q + 1], class of each id; entry 0 and every query without a
        segment hold ``num_classes`` (background), so the pair feeds ``panoptic_quality``.
      segment_valid: bool [B, Q], query q owns a segment in the panoptic map.
      det_classes: int32 [B, Q], most probable foreground class of each query.
      det_scores: float32 [B, Q], class probability x mean mask probability inside the mask.
      det_masks: bool [B, Q, H, W], binarised masks (probability >= mask_threshold).
      det_valid: bool [B, Q], the binarised mask is non-empty (an AP detection).
    """

    instance_ids: jax.Array
    instance_classes: jax.Array
    segment_valid: jax.Array
    det_classes: jax.Array
    det_scores: jax.Array
    det_masks: jax.Array
    det_valid: jax.Array


_TINY = 1e-30  # far below any probability that matters, far above float32's smallest normal


def _logit(p: float) -> float:
    if p <= 0.0:
        return -math.inf
    if p >= 1.0:
        return math.inf
    return math.log(p / (1.0 - p))


def _check_shapes(logits: jax.Array, mask_logits: jax.Array) -> None:
    if logits.ndim != 3 or logits.shape[-1] < 2:
        raise ValueError(f"logits: expected [B, Q, K] with K >= 2, got shape {logits.shape}")
    if mask_logits.ndim != 4 or mask_logits.shape[:2] != logits.shape[:2]:
        raise ValueError(
            f"mask_logits: expected [B, Q, H, W] with (B, Q) = {logits.shape[:2]}, "
            f"got shape {mask_logits.shape}"
        )


@functools.partial(jax.jit, static_argnames="config")
def panoptic_inference_from_logits(
    logits: jax.Array, mask_logits: jax.Array, config: InferenceConfig | None = None
) -> PanopticOutput:
    """Panoptic map and detections from one decoder layer's outputs.

    Args:
      logits: [B, Q, K] class logits, index K - 1 = background.
      mask_logits: [B, Q, H, W] mask logits.
      config: thresholds (static under jit); None: ``InferenceConfig()``.

    Returns:
      A ``PanopticOutput``.
    """
    config = config or InferenceConfig()
    _check_shapes(logits, mask_logits)
    b, q = logits.shape[:2]
    num_classes = logits.shape[-1] - 1
    probs = jax.nn.softmax(logits.astype(jnp.float32), axis=-1)[..., :num_classes]  # [B, Q, K-1]
    cls_prob = probs.max(-1)  # [B, Q]
    det_classes = probs.argmax(-1).astype(jnp.int32)  # [B, Q]
    mask_logits = mask_logits.astype(jnp.float32)
    # sigmoid(x) >= t  <=>  x >= logit(t): exact. The floor keeps every binarised cell > 0
    # even where the probability underflows, so "> 0" recovers the binary mask below.
    binary = mask_logits >= _logit(config.mask_threshold)  # [B, Q, H, W]
    prob = jnp.maximum(jax.nn.sigmoid(mask_logits), _TINY)
    # Materialised once (barrier): XLA's CPU backend otherwise fuses the producers into each
    # consumer below, several times slower than reading a plain array.
    inside = jax.lax.optimization_barrier(jnp.where(binary, prob, 0.0))  # [B, Q, H, W]
    binary = inside > 0.0
    # Float sums are exact below 2**24 cells; XLA's CPU reductions of bools are much slower.
    own_area = binary.astype(jnp.float32).sum((-2, -1)).astype(jnp.int32)  # [B, Q]
    det_scores = cls_prob * inside.sum((-2, -1)) / jnp.maximum(own_area, 1)
    det_valid = own_area > 0

    kept = cls_prob >= config.score_threshold  # [B, Q]
    # Each cell goes to the kept query maximising p_cls * mask probability among those whose
    # binarised mask covers it (-1: not a candidate; candidates score >= 0).
    pixel_score = jax.lax.optimization_barrier(
        jnp.where(binary & kept[:, :, None, None], cls_prob[:, :, None, None] * inside, -1.0)
    )  # [B, Q, H, W]
    # A running maximum unrolled over the static Q, strict ">" so ties keep the lower index
    # (argmax order): one fused pass, several times faster on CPU than an argmax over axis 1.
    best = jnp.full((b,) + mask_logits.shape[2:], -1.0, jnp.float32)  # [B, H, W]
    winner = jnp.full(best.shape, q, jnp.int32)  # q = no query
    for j in range(q):
        better = pixel_score[:, j] > best
        best = jnp.where(better, pixel_score[:, j], best)
        winner = jnp.where(better, j, winner)
    winner = jax.lax.optimization_barrier(winner)
    seg_area = jax.vmap(lambda w: jnp.bincount(w.ravel(), length=q + 1))(winner)[:, :q]  # [B, Q]
    kept_fraction = seg_area / jnp.maximum(own_area, 1)
    segment_valid = kept & (seg_area > 0) & (kept_fraction >= config.overlap_threshold)
    # Index q (no query) reads the appended False.
    valid_or_none = jnp.concatenate([segment_valid, jnp.zeros((b, 1), bool)], axis=1)  # [B, Q+1]
    winner_valid = jnp.take_along_axis(valid_or_none, winner.reshape(b, -1), axis=1).reshape(
        winner.shape
    )  # [B, H, W]
    instance_ids = jnp.where(winner_valid, winner + 1, 0).astype(jnp.int32)
    background = jnp.full((b, 1), num_classes, jnp.int32)
    instance_classes = jnp.concatenate(
        [background, jnp.where(segment_valid, det_classes, num_classes)], axis=1
    )  # [B, Q + 1]
    return PanopticOutput(
        instance_ids=instance_ids,
        instance_classes=instance_classes,
        segment_valid=segment_valid,
        det_classes=det_classes,
        det_scores=det_scores,
        det_masks=binary,
        det_valid=det_valid,
    )


def panoptic_inference(
    predictions: Predictions, config: InferenceConfig | None = None
) -> PanopticOutput:
    """``panoptic_inference_from_logits`` on the last decoder layer of ``predictions``.

    Args:
      predictions: network outputs; logits [L, B, Q, K], masks [L, B, Q, H, W].
      config: thresholds; None: ``InferenceConfig()``.

    Returns:
      A ``PanopticOutput`` for the B frames.
    """
    if predictions.logits.ndim != 4:
        raise ValueError(
            f"predictions.logits: expected [L, B, Q, K], got shape {predictions.logits.shape}"
        )
    if predictions.masks.ndim != 5:
        raise ValueError(
            f"predictions.masks: expected [L, B, Q, H, W], got shape {predictions.masks.shape}"
        )
    return panoptic_inference_from_logits(predictions.logits[-1], predictions.masks[-1], config)
