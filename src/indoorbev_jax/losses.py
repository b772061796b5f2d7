"""Set-prediction loss: matching costs, Hungarian matching per decoder layer, loss terms.

Paper "Training and Loss Function", DESIGN section 8. For every decoder layer l (the
auxiliary losses) and frame b, queries are matched one-to-one to the valid targets by
minimising

    C = cost_cls (1 - p_cls) + cost_dice (1 - Dice) + cost_focal Focal + cost_reg |b - b_hat|_1

and the matched pairs are scored with

    L = w_cls CE + w_dice Dice + w_focal Focal + w_dims L1(dims) + w_pos L1(pos) + w_yaw L1(yaw).

Normalisation (decided here; DETR and Mask2Former do the same):
  * cls: weighted cross-entropy over all queries, every matched query weight 1, every
    unmatched one (target: background) ``background_weight``, divided by the sum of the
    weights (PyTorch's ``F.cross_entropy(weight=...)`` mean, which DETR uses). Its scale thus
    does not depend on how many objects a frame holds.
  * dice, focal, dims, pos, yaw: summed over matched pairs, divided by the number of valid
    targets in the global batch (at least 1). Focal is first averaged over mask cells; L1
    terms sum their coordinates; yaw uses the difference wrapped to [-pi, pi).
  With ``axis_name`` (inside ``shard_map``/``pmap``/a named ``vmap``) both denominators are
  ``psum``-ed, so each shard returns its share and the ``psum`` of the shards' losses (and of
  their gradients) equals the loss of the whole batch. Under plain ``jit`` with sharded
  arrays no axis name is needed: the sums are already global.

Point sampling (``LossConfig.num_mask_points`` = P > 0), as in Mask2Former, bounds memory on
large grids: costs use P cells drawn uniformly per (layer, frame), shared by all queries and
targets; the mask losses of each matched pair use P cells, 75 % of them the most uncertain
(smallest |logit|) among 3 P uniform candidates and the rest uniform. Cells are whole grid
cells, so the targets need no interpolation.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np

from indoorbev_jax import matching
from indoorbev_jax.config import LossConfig
from indoorbev_jax.geometry import wrap_angle
from indoorbev_jax.types import Predictions, Targets, as_predictions, as_targets

TERMS: tuple[str, ...] = ("cls", "dice", "focal", "dims", "pos", "yaw")
# Optional key of ``weights``; when absent ``LossConfig.background_weight`` is used.
BACKGROUND_KEY = "background"
# Mask2Former's importance sampling for the mask losses.
_OVERSAMPLE_RATIO = 3.0
_IMPORTANCE_RATIO = 0.75
# Frozen, so one shared default instance is safe.
DEFAULT_CONFIG = LossConfig()


def _random_cells(key: jax.Array, shape: tuple[int, ...], num_cells: int) -> jax.Array:
    """Uniform cell indices in [0, num_cells), int32 of the given shape."""
    # Raw bits modulo num_cells rather than jax.random.randint: one threefry call compiles
    # several times faster on CPU, and the modulo bias (< num_cells / 2**32 < 1e-4 for a
    # 500 x 500 grid) is irrelevant for sampling loss points.
    bits = jax.random.bits(key, shape, jnp.uint32)
    return (bits % jnp.uint32(num_cells)).astype(jnp.int32)


def _sigmoid_pow(x: jax.Array, gamma: float) -> jax.Array:
    """``sigmoid(x) ** gamma`` with a finite gradient everywhere."""
    # Integer powers go through lax.integer_pow, whose gradient stays finite where sigmoid
    # underflows to 0; gamma = 2 is the common case. Fractional ones as exp(gamma log s):
    # jnp.power's gradient is infinite at 0 and times sigmoid's 0 gave NaN once |x| >= 88.
    if float(gamma).is_integer():
        return jax.nn.sigmoid(x) ** int(gamma)
    return jnp.exp(gamma * jax.nn.log_sigmoid(x))


def _focal_terms(x: jax.Array, alpha: float, gamma: float) -> tuple[jax.Array, jax.Array]:
    """Sigmoid focal loss of logits ``x`` against target 1 and against target 0 (same shape)."""
    # softplus(-x) = -log sigmoid(x) and sigmoid(-x) = 1 - sigmoid(x), both stable at |x| >> 1.
    pos = alpha * _sigmoid_pow(-x, gamma) * jax.nn.softplus(-x)
    neg = (1.0 - alpha) * _sigmoid_pow(x, gamma) * jax.nn.softplus(x)
    return pos, neg


def _device_targets(targets) -> Targets:
    """``as_targets`` with jax arrays: numpy masks indexed by traced sampled cells (targets
    closed over by a jitted function) raised a TracerArrayConversionError. Integer masks are
    read as nonzero: 0/255 masks (as a PNG gives them) took 255 as the target, and the dice
    loss went negative."""
    targets = jax.tree.map(jnp.asarray, as_targets(targets))
    if jnp.issubdtype(targets.masks.dtype, jnp.integer):
        targets = targets.replace(masks=targets.masks != 0)
    return targets


def _check_inputs(predictions: Predictions, targets: Targets) -> None:
    if predictions.logits.ndim != 4:
        raise ValueError(f"predictions.logits must be [L, B, Q, K], got {predictions.logits.shape}")
    lyr, b, q, _ = predictions.logits.shape
    if targets.masks.ndim != 4 or targets.masks.shape[0] != b:
        raise ValueError(f"targets.masks must be [B={b}, M, H, W], got {targets.masks.shape}")
    m, h, w = targets.masks.shape[1:]
    expected = {
        "predictions.dims": (predictions.dims, (lyr, b, q, 3)),
        "predictions.pos": (predictions.pos, (lyr, b, q, 3)),
        "predictions.yaw": (predictions.yaw, (lyr, b, q, 1)),
        "predictions.masks": (predictions.masks, (lyr, b, q, h, w)),
        "targets.classes": (targets.classes, (b, m)),
        "targets.dims": (targets.dims, (b, m, 3)),
        "targets.pos": (targets.pos, (b, m, 3)),
        "targets.yaw": (targets.yaw, (b, m)),
        "targets.valid": (targets.valid, (b, m)),
    }
    for name, (array, shape) in expected.items():
        if array.shape != shape:
            raise ValueError(f"{name} must have shape {shape}, got {array.shape}")
    if m > q:
        raise ValueError(f"targets hold M={m} slots but predictions only Q={q} queries")
    if not jnp.issubdtype(targets.classes.dtype, jnp.integer):  # a take_along_axis error
        raise TypeError(f"targets.classes must be integer class ids, got {targets.classes.dtype}")
    classes, valid = targets.classes, targets.valid
    if not isinstance(classes, jax.core.Tracer) and not isinstance(valid, jax.core.Tracer):
        # Outside jit: a class id >= K - 1 made the loss NaN (K - 1 trained as background).
        k = predictions.logits.shape[-1]
        bad = np.asarray(valid, bool) & ((np.asarray(classes) < 0) | (np.asarray(classes) >= k - 1))
        if bad.any():
            fb, fm = (int(i[0]) for i in np.nonzero(bad))
            raise ValueError(
                f"targets.classes[{fb}, {fm}] = {int(np.asarray(classes)[fb, fm])} is a valid "
                f"target's class outside 0..{k - 2} (logits have K = {k}, K - 1 = background)"
            )


# Mask logits are clipped to this: at +-inf the focal terms give inf - inf and inf * 0 (NaN
# costs and gradients), and +-1e4 already saturates the sigmoid in float32.
MASK_LOGIT_BOUND = 1e4


def _flat_masks(predictions: Predictions) -> jax.Array:
    lyr, b, q, h, w = predictions.masks.shape
    flat = predictions.masks.reshape(lyr, b, q, h * w)  # [L, B, Q, H*W]
    return jnp.clip(flat, -MASK_LOGIT_BOUND, MASK_LOGIT_BOUND)


def _cost_mask_points(
    predictions: Predictions, targets: Targets, config: LossConfig, key: jax.Array | None
) -> tuple[jax.Array, jax.Array]:
    """Mask logits and target masks on the cells the cost looks at.

    Returns:
      float32 [L, B, Q, P] logits and float32 targets: [B, M, P] (P = H*W) for every cell,
      [L, B, M, P] (P = ``num_mask_points``) when sampling.
    """
    logits = _flat_masks(predictions)  # [L, B, Q, H*W]
    b, m = targets.classes.shape
    tgt = targets.masks.reshape(b, m, logits.shape[-1])  # [B, M, H*W]; M may be 0
    k = config.num_mask_points
    if k == 0:
        return logits.astype(jnp.float32), tgt.astype(jnp.float32)
    lyr, _, _, hw = logits.shape
    cells = _random_cells(key, (lyr, b, k), hw)  # [L, B, P], one draw per layer/frame
    pred = jnp.take_along_axis(logits, cells[:, :, None, :], axis=-1)  # [L, B, Q, P]
    bi = jnp.arange(b)[None, :, None, None]
    mi = jnp.arange(m)[None, None, :, None]
    tgt = tgt[bi, mi, cells[:, :, None, :]]  # [L, B, M, P]
    return pred.astype(jnp.float32), tgt.astype(jnp.float32)


def _costs(
    predictions: Predictions,
    targets: Targets,
    mask_logits: jax.Array,
    mask_targets: jax.Array,
    config: LossConfig,
) -> jax.Array:
    """Matching cost [L, B, Q, M] from point-wise mask logits/targets (``_cost_mask_points``)."""
    num_k = predictions.logits.shape[-1]
    prob = jax.nn.softmax(predictions.logits.astype(jnp.float32), axis=-1)  # [L, B, Q, K]
    onehot = jax.nn.one_hot(targets.classes, num_k)  # [B, M, K]
    cost_cls = 1.0 - jnp.einsum("lbqk,bmk->lbqm", prob, onehot)

    tgt_eq = "bmp" if mask_targets.ndim == 3 else "lbmp"
    sig = jax.nn.sigmoid(mask_logits)  # [L, B, Q, P]
    inter = jnp.einsum(f"lbqp,{tgt_eq}->lbqm", sig, mask_targets)
    # Both sums end up [.., Q, M]; the target one lacks L when shared by all layers.
    denom = sig.sum(-1)[..., :, None] + mask_targets.sum(-1)[..., None, :]
    cost_dice = 1.0 - (2.0 * inter + 1.0) / (denom + 1.0)
    pos, neg = _focal_terms(mask_logits, config.focal_alpha, config.focal_gamma)
    # sum_p pos t + neg (1 - t) = sum_p (pos - neg) t + sum_p neg: one contraction, not two.
    cost_focal = jnp.einsum(f"lbqp,{tgt_eq}->lbqm", pos - neg, mask_targets)
    cost_focal = (cost_focal + neg.sum(-1)[..., None]) / mask_logits.shape[-1]

    def l1(pred, tgt):  # [L, B, Q, C], [B, M, C] -> [L, B, Q, M]
        return jnp.abs(pred.astype(jnp.float32)[:, :, :, None] - tgt[None, :, None]).sum(-1)

    yaw_diff = predictions.yaw.astype(jnp.float32) - targets.yaw[None, :, None, :]  # [L,B,Q,M]
    cost_reg = (
        l1(predictions.dims, targets.dims)
        + l1(predictions.pos, targets.pos)
        + jnp.abs(wrap_angle(yaw_diff))
    )
    return (
        config.cost_cls * cost_cls
        + config.cost_dice * cost_dice
        + config.cost_focal * cost_focal
        + config.cost_reg * cost_reg
    )


def cost_matrix(
    predictions: Predictions,
    targets: Targets,
    config: LossConfig = DEFAULT_CONFIG,
    key: jax.Array | None = None,
) -> jax.Array:
    """Matching cost of every (query, target) pair on every decoder layer.

    ``cost_cls (1 - p_cls) + cost_dice (1 - Dice) + cost_focal Focal + cost_reg L1``, where
    p_cls is the softmax probability of the target's class, Dice is the soft Dice
    coefficient of sigmoid(mask logits) with the target footprint (+1 smoothing), Focal the
    sigmoid focal loss averaged over cells, and L1 sums |dims|, |pos| and the wrapped |yaw|
    differences. Padded targets get ordinary (meaningless) values; ``matching.match`` masks
    them out. Not differentiated by the loss.

    Args:
      predictions: ``Predictions`` (or a dict of its fields) with L layers, B frames, Q
        queries.
      targets: ``Targets`` (or a dict of its fields) with M slots, masks [B, M, H, W].
      config: cost weights, focal alpha/gamma and ``num_mask_points``.
      key: ``jax.random`` key, required when ``config.num_mask_points > 0``.

    Returns:
      float32 [L, B, Q, M].
    """
    predictions, targets = as_predictions(predictions), _device_targets(targets)
    _check_inputs(predictions, targets)
    _check_key(config, key)
    mask_logits, mask_targets = _cost_mask_points(predictions, targets, config, key)
    return _costs(predictions, targets, mask_logits, mask_targets, config)


def _check_key(config: LossConfig, key: jax.Array | None) -> None:
    if config.num_mask_points > 0 and key is None:
        raise ValueError(
            f"loss.num_mask_points = {config.num_mask_points} samples mask cells at random: "
            "pass key=jax.random.key(...)"
        )


def _loss_mask_points(
    logits: jax.Array, tgt: jax.Array, query_idx: jax.Array, k: int, key: jax.Array
) -> tuple[jax.Array, jax.Array]:
    """Mask2Former importance sampling for the matched pairs.

    Args:
      logits: [L, B, Q, H*W] mask logits.
      tgt: bool [B, M, H*W] target masks.
      query_idx: int32 [L, B, M] matched query of each target.
      k: cells per pair.
      key: ``jax.random`` key.

    Returns:
      float32 [L, B, M, k] logits of the matched queries and [L, B, M, k] targets.
    """
    lyr, b, _, hw = logits.shape
    m = tgt.shape[1]
    li = jnp.arange(lyr)[:, None, None, None]
    bi = jnp.arange(b)[None, :, None, None]
    mi = jnp.arange(m)[None, None, :, None]
    qi = query_idx[..., None]  # [L, B, M, 1]
    num_candidates = max(int(_OVERSAMPLE_RATIO * k), 1)
    num_important = min(int(_IMPORTANCE_RATIO * k), num_candidates)
    draws = _random_cells(key, (lyr, b, m, num_candidates + k - num_important), hw)
    candidates, uniform = draws[..., :num_candidates], draws[..., num_candidates:]
    # Uncertainty = -|logit|: pick the cells where the prediction is least decided. The choice
    # is not differentiated (Mask2Former samples under torch.no_grad()).
    uncertainty = -jnp.abs(jax.lax.stop_gradient(logits)[li, bi, qi, candidates])
    _, top = jax.lax.top_k(uncertainty, num_important)  # [L, B, M, k_imp]
    cells = jnp.concatenate(
        [jnp.take_along_axis(candidates, top, axis=-1), uniform], axis=-1
    )  # [L, B, M, k]
    return logits[li, bi, qi, cells].astype(jnp.float32), tgt[bi, mi, cells].astype(jnp.float32)


def _check_weights(weights: dict) -> None:
    missing = [k for k in TERMS if k not in weights]
    unknown = [k for k in weights if k not in (*TERMS, BACKGROUND_KEY)]
    if missing or unknown:
        raise ValueError(
            f"loss weights: missing {missing}, unknown {unknown}; expected keys {list(TERMS)} "
            f"and optionally '{BACKGROUND_KEY}'"
        )


def set_loss(
    predictions: Predictions,
    targets: Targets,
    weights: dict | LossConfig | None = None,
    config: LossConfig = DEFAULT_CONFIG,
    *,
    key: jax.Array | None = None,
    axis_name: str | None = None,
) -> tuple[jax.Array, dict[str, jax.Array]]:
    """Hungarian-matched set loss over every decoder layer (auxiliary losses).

    Each layer is matched on its own (``cost_matrix`` + ``matching.match``); the total sums
    the weighted terms of every layer (only the last one when ``config.aux_loss`` is False).
    See the module docstring for the normalisation and for point sampling.

    Args:
      predictions: ``Predictions`` (or a dict of its fields): logits [L, B, Q, K],
        dims/pos [L, B, Q, 3], yaw [L, B, Q, 1], masks [L, B, Q, H, W] (logits); any float
        dtype, losses are float32.
      targets: ``Targets`` (or a dict of its fields, ``instance_ids`` optional): classes
        [B, M], dims/pos [B, M, 3], yaw [B, M], valid [B, M], masks bool [B, M, H, W].
        Frames without targets are fine, and so is M = 0. Valid targets' classes lie in
        0..K-2 (checked when the targets are concrete, not under jit).
      weights: ``{"cls", "dice", "focal", "dims", "pos", "yaw"}`` loss weights, as
        ``LossConfig.weights()`` gives, optionally ``"background"`` (else
        ``config.background_weight``). Python floats or (traced) scalar arrays, so a sweep
        can ``jax.vmap`` over them. A ``LossConfig`` stands for its ``weights()`` and, when
        ``config`` is not given, for ``config`` too; None: ``config.weights()``.
      config: matching-cost weights, background weight, focal alpha/gamma, point sampling,
        ``aux_loss``. Static.
      key: ``jax.random`` key, required when ``config.num_mask_points > 0``.
      axis_name: mapped axis over which the batch is sharded (``shard_map``/``pmap``). The
        normalisers are ``psum``-ed over it, so ``total`` and ``parts`` (but
        ``num_targets``) are this shard's share: ``psum`` them, and the gradients (not
        ``pmean``), for the whole batch's values.

    Returns:
      ``(total, parts)``: the scalar loss and a dict of float32 scalars: for each term t of
      ``TERMS``, ``parts[t]`` (unweighted, summed over the layers in the loss, so that
      ``total = sum_t weights[t] * parts[t]``) and ``parts[t + "_final"]`` (last layer only);
      ``parts["num_targets"]``, the normaliser.

    Example::

        total, parts = set_loss(predictions, targets, LossConfig().weights())
    """
    if weights is None:
        weights = config.weights()
    elif isinstance(weights, LossConfig):
        config = weights if config is DEFAULT_CONFIG else config
        weights = weights.weights()
    predictions = as_predictions(predictions)
    targets = _device_targets(targets)
    _check_inputs(predictions, targets)
    _check_weights(weights)
    _check_key(config, key)
    if not config.aux_loss:
        predictions = jax.tree.map(lambda x: x[-1:], predictions)
    lyr, b, q, num_k = predictions.logits.shape
    m = targets.classes.shape[1]
    if m > q:  # match would leave some target without a query (-1)
        raise ValueError(f"set_loss: {m} target slots cannot all be matched to {q} queries")
    valid = targets.valid.astype(bool)
    key_cost, key_loss = jax.random.split(key) if key is not None else (None, None)

    def global_sum(x):
        return jax.lax.psum(x, axis_name) if axis_name is not None else x

    # Matching (no gradient: the indices are constant almost everywhere).
    cost = cost_matrix(jax.lax.stop_gradient(predictions), targets, config, key_cost)
    query_idx, _ = matching.match(
        cost.reshape(lyr * b, q, m),  # [L*B, Q, M]
        jnp.broadcast_to(valid, (lyr, b, m)).reshape(lyr * b, m),
    )
    query_idx = query_idx.reshape(lyr, b, m)  # [L, B, M]

    num_targets = jnp.maximum(global_sum(valid.sum().astype(jnp.float32)), 1.0)

    # Classification over all queries; assign[l, b, q, j] = query q got valid target j.
    assign = (query_idx[:, :, None, :] == jnp.arange(q)[:, None]) & valid[:, None]  # [L, B, Q, M]
    matched = assign.any(-1)  # [L, B, Q]
    background = num_k - 1
    tgt_cls = jnp.where(matched, (assign * targets.classes[:, None, :]).sum(-1), background)
    log_prob = jax.nn.log_softmax(predictions.logits.astype(jnp.float32), axis=-1)
    ce = -jnp.take_along_axis(log_prob, tgt_cls[..., None], axis=-1)[..., 0]  # [L, B, Q]
    bg_weight = weights.get(BACKGROUND_KEY, config.background_weight)
    ce_weight = jnp.where(matched, 1.0, bg_weight)
    ce_norm = global_sum(ce_weight.sum((1, 2)))
    # Zero only when background_weight = 0 and no frame has a target: the loss is then 0.
    loss_cls = (ce_weight * ce).sum((1, 2)) / jnp.where(ce_norm > 0, ce_norm, 1.0)

    def matched_pred(x):  # [L, B, Q, C] -> [L, B, M, C] for the matched queries
        x = jnp.take_along_axis(x.astype(jnp.float32), query_idx[..., None], axis=2)
        # Padded targets hold leftover queries, whose outputs may be NaN/Inf: zero them
        # before any arithmetic (a later `* valid` would keep NaN, and NaN * 0 gradients).
        return jnp.where(valid[..., None], x, 0.0)

    def per_target_sum(x):  # [L, B, M] -> [L], padded targets dropped
        return jnp.where(valid, x, 0.0).sum((1, 2)) / num_targets

    loss_dims = per_target_sum(jnp.abs(matched_pred(predictions.dims) - targets.dims).sum(-1))
    loss_pos = per_target_sum(jnp.abs(matched_pred(predictions.pos) - targets.pos).sum(-1))
    yaw_diff = matched_pred(predictions.yaw)[..., 0] - targets.yaw  # [L, B, M]
    loss_yaw = per_target_sum(jnp.abs(wrap_angle(yaw_diff)))

    logits_flat = _flat_masks(predictions)  # [L, B, Q, H*W]
    tgt_flat = targets.masks.reshape(b, m, logits_flat.shape[-1])  # [B, M, H*W]; M may be 0
    if config.num_mask_points > 0:
        x, t = _loss_mask_points(
            logits_flat, tgt_flat, query_idx, config.num_mask_points, key_loss
        )  # [L, B, M, P] each
        x = jnp.where(valid[..., None], x, 0.0)  # as in matched_pred
    else:
        x = matched_pred(logits_flat)  # [L, B, M, H*W]
        t = tgt_flat.astype(jnp.float32)[None]  # [1, B, M, H*W]
    sig = jax.nn.sigmoid(x)
    dice = 1.0 - (2.0 * (sig * t).sum(-1) + 1.0) / (sig.sum(-1) + t.sum(-1) + 1.0)  # [L, B, M]
    pos, neg = _focal_terms(x, config.focal_alpha, config.focal_gamma)
    focal = jnp.where(t > 0, pos, neg).mean(-1)  # [L, B, M]
    loss_dice = per_target_sum(dice)
    loss_focal = per_target_sum(focal)

    per_layer = {
        "cls": loss_cls,
        "dice": loss_dice,
        "focal": loss_focal,
        "dims": loss_dims,
        "pos": loss_pos,
        "yaw": loss_yaw,
    }  # each [L]
    parts = {}
    for name, values in per_layer.items():
        parts[name] = values.sum()
        parts[f"{name}_final"] = values[-1]
    parts["num_targets"] = num_targets
    total = sum(weights[name] * parts[name] for name in TERMS)
    return jnp.asarray(total, jnp.float32), parts


def semantic_targets(targets: Targets, num_classes: int) -> jax.Array:
    """Multi-label semantic BEV map: float32 [B, H, W, K], 1 where a valid object of class k
    covers the cell (overlapping footprints may set several classes)."""
    b, m, h, w = targets.masks.shape
    onehot = jax.nn.one_hot(targets.classes, num_classes) * targets.valid[..., None]  # [B, M, K]
    cover = jnp.einsum(
        "bmn,bmk->bnk", targets.masks.reshape(b, m, h * w).astype(jnp.float32), onehot
    )
    return (cover > 0).astype(jnp.float32).reshape(b, h, w, num_classes)


def seed_loss(
    seeds: jax.Array,
    targets: Targets,
    config: LossConfig = DEFAULT_CONFIG,
    *,
    axis_name: str | None = None,
) -> jax.Array:
    """Dense loss of the query-selection head (``HeadConfig.query_init = "select"``).

    Sigmoid focal loss (``config.focal_alpha`` / ``focal_gamma``) of the seed logits against
    ``semantic_targets``, summed over cells and classes and divided by the number of
    foreground (cell, class) pairs in the global batch (at least 1), as RetinaNet
    normalises by its positive anchors.

    Args:
      seeds: [B, H, W, K] logits (the head's ``intermediates/seeds``).
      targets: ``Targets`` of the same frames.
      config: focal alpha and gamma.
      axis_name: as in ``set_loss``: the normaliser is ``psum``-ed over it.

    Returns:
      float32 scalar (this shard's share under ``axis_name``).
    """
    if seeds.ndim != 4 or seeds.shape[:3] != targets.masks.shape[:1] + targets.masks.shape[2:]:
        raise ValueError(
            f"seeds must be [B, H, W, K] on the targets' grid {targets.masks.shape}, "
            f"got {seeds.shape}"
        )
    t = semantic_targets(targets, seeds.shape[-1])
    pos, neg = _focal_terms(seeds.astype(jnp.float32), config.focal_alpha, config.focal_gamma)
    total = jnp.where(t > 0, pos, neg).sum()
    num_pos = t.sum()
    if axis_name is not None:
        num_pos = jax.lax.psum(num_pos, axis_name)
    return total / jnp.maximum(num_pos, 1.0)
