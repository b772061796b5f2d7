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

Test-time views (``apply_views``, optional): the model on mirrored and rotated copies of
the cloud, outputs fused into one query set before panoptic inference.

Example::

    out = panoptic_inference(predictions, config.inference)  # last decoder layer
    out.instance_ids  # [B, H, W] int32, 0 = empty, q + 1 = query q
"""

from __future__ import annotations

import functools
import math
from collections.abc import Mapping

import jax
import jax.numpy as jnp
import numpy as np
from flax import struct

from indoorbev_jax.config import VIEWS, InferenceConfig, check_section, check_views
from indoorbev_jax.types import Predictions, as_predictions


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
    if config is not None:
        check_section("config", config, InferenceConfig, "inference")
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
      predictions: network outputs (``Predictions``, or a dict of its fields: only
        ``logits`` and ``masks`` are read, so a dict of those two will do); logits
        [L, B, Q, K], masks [L, B, Q, H, W].
      config: thresholds; None: ``InferenceConfig()``.

    Returns:
      A ``PanopticOutput`` for the B frames.
    """
    if isinstance(predictions, Mapping) and set(predictions) == {"logits", "masks"}:
        logits, masks = predictions["logits"], predictions["masks"]
    else:
        predictions = as_predictions(predictions)
        logits, masks = predictions.logits, predictions.masks
    if logits.ndim != 4:
        raise ValueError(f"predictions.logits: expected [L, B, Q, K], got shape {logits.shape}")
    if masks.ndim != 5:
        raise ValueError(f"predictions.masks: expected [L, B, Q, H, W], got shape {masks.shape}")
    return panoptic_inference_from_logits(logits[-1], masks[-1], config)


# Test-time views ----------------------------------------------------------------------------
#
# The model runs on mirrored and rotated copies of the cloud (``config.VIEWS``); each copy's
# queries are mapped back to the lidar frame and the V * Q queries fused into one set: greedy
# in descending detection score, a query leads a cluster of the best-overlapping free query
# of every view (mask IoU >= view_iou and > 0); the cluster's class probabilities are the views'
# mean (a view without a member counts as background) and its mask probability the members'
# mean. Fused sets are padded with empty queries, so shapes stay static ([B, V * Q, ...]).
# docs/METRICS.md "Test-time views" has the full definition.


def view_points(points: jax.Array, view: str) -> jax.Array:
    """Points [..., 4+] as the sensor sees them in ``view``: (x, y) -> A (x, y)."""
    a = jnp.array(VIEWS[view], points.dtype)
    return points.at[..., :2].set(points[..., :2] @ a.T)


def _view_cells(view: str, shape: tuple[int, int]) -> tuple[np.ndarray, np.ndarray]:
    """(rows, cols) [H, W]: the view's cell over each cell of a centred grid."""
    h, w = shape
    (a, b), (c, d) = VIEWS[view]
    # Cell-centre coordinates in cell units about the grid centre: exact half-integers.
    y, x = np.meshgrid(np.arange(h) - (h - 1) / 2, np.arange(w) - (w - 1) / 2, indexing="ij")
    xv, yv = a * x + b * y, c * x + d * y
    return np.rint(yv + (h - 1) / 2).astype(np.int32), np.rint(xv + (w - 1) / 2).astype(np.int32)


def unview_cells(grid_values: jax.Array, view: str) -> jax.Array:
    """Values [..., H, W] on the grid of ``view_points(points, view)``, on the lidar frame's."""
    rows, cols = _view_cells(view, grid_values.shape[-2:])
    return grid_values[..., rows, cols]


def unview_predictions(predictions: Predictions, view: str) -> Predictions:
    """Predictions made on ``view_points(points, view)``, mapped back to the lidar frame."""
    a = jnp.array(VIEWS[view], jnp.float32)
    masks = unview_cells(predictions.masks, view)
    xy = predictions.pos[..., :2] @ a  # A is orthogonal: A^-1 = A^T
    pos = predictions.pos.at[..., :2].set(xy.astype(predictions.pos.dtype))
    heading = jnp.concatenate([jnp.cos(predictions.yaw), jnp.sin(predictions.yaw)], -1) @ a
    yaw = jnp.arctan2(heading[..., 1:], heading[..., :1]).astype(predictions.yaw.dtype)
    return predictions.replace(masks=masks, pos=pos, yaw=yaw)


def view_batch(points: jax.Array, valid: jax.Array, views) -> tuple[jax.Array, jax.Array]:
    """(points [V * B, N, 4], valid [V * B, N]): the B clouds in each of the V views,
    view-major, as one batch for the model."""
    clouds = jnp.concatenate([view_points(points, v) for v in views])
    return clouds, jnp.concatenate([valid] * len(views))


def unview_batch(predictions: Predictions, views) -> Predictions:
    """Predictions of a ``view_batch`` (batch axis V * B), each view mapped back to the
    lidar frame and stacked: fields [V, L, B, ...], as ``fuse_views`` takes them."""
    b = predictions.logits.shape[1] // len(views)
    per_view = [
        unview_predictions(jax.tree.map(lambda x, i=i: x[:, i * b : (i + 1) * b], predictions), v)
        for i, v in enumerate(views)
    ]
    return jax.tree.map(lambda *x: jnp.stack(x), *per_view)


def _fuse_frame(logits, masks, dims, pos, yaw, *, views, mask_threshold, iou_threshold):
    """One frame: V * Q queries (view-major) -> V * Q fused ones; see the section comment."""
    p, k = logits.shape
    q = p // views
    probs = jax.nn.softmax(logits.astype(jnp.float32), -1)[:, : k - 1]  # [P, K-1]
    cls_prob = probs.max(-1)
    grid_shape = masks.shape[1:]
    masks = masks.astype(jnp.float32).reshape(p, -1)
    prob = jax.nn.sigmoid(masks)  # [P, HW]
    binary = (masks >= _logit(mask_threshold)).astype(jnp.float32)
    area = binary.sum(-1)
    inter = binary @ binary.T  # [P, P]
    iou = inter / jnp.maximum(area[:, None] + area[None] - inter, 1.0)
    # Detection score as in panoptic inference; queries with empty masks never lead.
    score = jnp.where(area > 0, cls_prob * (prob * binary).sum(-1) / jnp.maximum(area, 1), -1.0)

    def step(_, state):
        leader_of, free = state
        i = jnp.argmax(jnp.where(free, score, -2.0))
        active = free[i] & (score[i] >= 0)
        # The leader itself is its view's member; elsewhere the best free overlap per view.
        # Members must overlap the leader: at view_iou 0 an IoU of 0 (an empty or disjoint
        # mask) would pass.
        joins = free & (inter[i] > 0) & (iou[i] >= iou_threshold)
        overlap = jnp.where(joins, iou[i], -1.0).at[i].set(2.0)
        overlap = overlap.reshape(views, q)
        best = jnp.argmax(overlap, 1) + jnp.arange(views) * q  # [V]
        member = jnp.zeros(p, bool).at[best].set(overlap.max(1) >= 0) & active
        return jnp.where(member, i, leader_of), free & ~member

    leader_of, _ = jax.lax.fori_loop(0, p, step, (jnp.full(p, -1, jnp.int32), jnp.ones(p, bool)))
    member = (leader_of[None, :] == jnp.arange(p)[:, None]).astype(jnp.float32)  # [lead, P]
    count = member.sum(-1)
    fg = member @ probs / views
    fused_logits = jnp.log(
        jnp.maximum(jnp.concatenate([fg, 1.0 - fg.sum(-1, keepdims=True)], -1), _TINY)
    )
    mask_prob = jnp.clip(member @ prob / jnp.maximum(count, 1)[:, None], 1e-6, 1 - 1e-6)
    fused_masks = jnp.where(count[:, None] > 0, jnp.log(mask_prob) - jnp.log1p(-mask_prob), -1e9)
    weight = member * cls_prob[None]
    norm = jnp.maximum(weight.sum(-1, keepdims=True), _TINY)
    fused_yaw = jnp.arctan2(weight @ jnp.sin(yaw), weight @ jnp.cos(yaw))
    return (
        fused_logits.astype(logits.dtype),
        fused_masks.reshape((p,) + grid_shape),
        weight @ dims / norm,
        weight @ pos / norm,
        fused_yaw,
    )


def fuse_views(
    predictions: Predictions, mask_threshold: float = 0.5, iou_threshold: float = 0.5
) -> Predictions:
    """Fuses the final layers of V views' predictions, all already in the lidar frame.

    Args:
      predictions: fields with a leading view axis: logits [V, L, B, Q, K], masks
        [V, L, B, Q, H, W], ...; only the last decoder layer is read.
      mask_threshold: binarises the masks for the overlaps and the scores.
      iou_threshold: least mask IoU for two views' queries to be one object.

    Returns:
      ``Predictions`` with one layer and V * Q queries: logits [1, B, V * Q, K], ...; a
      query that no cluster kept has background probability 1 and an empty mask.
    """
    views = predictions.logits.shape[0]
    b = predictions.logits.shape[2]

    def last(x):  # [V, L, B, Q, ...] -> [B, V * Q, ...], view-major
        x = jnp.moveaxis(x[:, -1], 0, 1)
        return x.reshape((b, -1) + x.shape[3:])

    fuse = functools.partial(
        _fuse_frame, views=views, mask_threshold=mask_threshold, iou_threshold=iou_threshold
    )
    fields = (predictions.logits, predictions.masks, predictions.dims, predictions.pos,
              predictions.yaw)  # fmt: skip
    logits, masks, dims, pos, yaw = jax.vmap(fuse)(*(last(x) for x in fields))
    return Predictions(logits=logits[None], dims=dims[None], pos=pos[None], yaw=yaw[None],
                       masks=masks[None])  # fmt: skip


def apply_views(
    model, params, points: jax.Array, valid: jax.Array, config: InferenceConfig | None = None,
    **apply_kwargs,
) -> Predictions:  # fmt: skip
    """``model.apply`` with ``config.views``: one batched forward of the V views of the
    clouds, mapped back to the lidar frame and fused (``fuse_views``). With the single view
    ``("identity",)`` it is the plain forward, every layer.

    Args:
      model: an ``IndoorBEV``; its grid must suit the views (``config.check_views``).
      params, points [B, N, 4], valid [B, N]: as for ``model.apply``.
      config: the views, ``view_iou`` and the ``mask_threshold`` that binarises masks for the
        overlaps; None: ``InferenceConfig()``.
      **apply_kwargs: passed to ``model.apply`` (e.g. ``capture_intermediates``); its
        extra outputs then come back as well, batch axis [V * B] in view-major order.

    Returns:
      ``Predictions`` in the lidar frame (with ``(predictions, state)`` when ``model.apply``
      returns a pair); with several views, one layer of V * Q queries.
    """
    config = config or InferenceConfig()
    out = forward_views(model, params, points, valid, config.views, **apply_kwargs)
    if config.views == ("identity",):
        return out
    stacked, extra = out if isinstance(out, tuple) else (out, None)
    fused = fuse_views(stacked, config.mask_threshold, config.view_iou)
    return fused if extra is None else (fused, extra)


def forward_views(
    model, params, points: jax.Array, valid: jax.Array, views: tuple[str, ...], **apply_kwargs
) -> Predictions:
    """The first half of ``apply_views``: one batched forward of the V views, mapped back
    to the lidar frame but not fused, so that one forward can be fused at several mask
    thresholds (``fuse_views``); with ``("identity",)``, the plain forward.

    Returns:
      ``Predictions`` with a leading view axis [V, L, B, ...] (none for the identity), with
      ``model.apply``'s extra outputs as in ``apply_views``.
    """
    check_views(views, model.config.grid)
    if views == ("identity",):
        return model.apply(params, points, valid, **apply_kwargs)
    out = model.apply(params, *view_batch(points, valid, views), **apply_kwargs)
    out, extra = out if isinstance(out, tuple) else (out, None)
    stacked = unview_batch(out, views)
    return stacked if extra is None else (stacked, extra)
