"""Test-time views: the grid maps against the rasteriser, fusion against a loop re-derivation,
and the whole path on the tiny model (mirror equivariance of ``apply_views``)."""

import argparse
import dataclasses
import math

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from indoorbev_jax.cli import parse_views
from indoorbev_jax.config import (
    NUM_CLASSES,
    VIEWS,
    Config,
    ConfigError,
    GridConfig,
    InferenceConfig,
    check_views,
)
from indoorbev_jax.data.rasterize import rasterize_boxes
from indoorbev_jax.inference import (
    apply_views,
    fuse_views,
    panoptic_inference,
    unview_batch,
    unview_predictions,
    view_batch,
    view_points,
)
from indoorbev_jax.types import Predictions

K = NUM_CLASSES + 1
GRID = GridConfig(x_range=(-2.0, 2.0), y_range=(-2.0, 2.0), cell_size=0.1)


def _one_query(mask, pos, yaw):
    """Predictions with L = B = Q = 1."""
    return Predictions(
        logits=jnp.zeros((1, 1, 1, K)),
        dims=jnp.ones((1, 1, 1, 3)),
        pos=jnp.asarray(pos, jnp.float32).reshape(1, 1, 1, 3),
        yaw=jnp.full((1, 1, 1, 1), yaw, jnp.float32),
        masks=jnp.asarray(mask, jnp.float32).reshape((1, 1, 1) + mask.shape),
    )


# Mirror views are allowed on any grid (check_views): every other grid here is square.
NOT_SQUARE = GridConfig(x_range=(-2.0, 2.0), y_range=(-1.0, 1.0), cell_size=0.1)  # 20 x 40


@pytest.mark.parametrize(
    ("view", "grid"),
    [(v, GRID) for v in VIEWS] + [(v, NOT_SQUARE) for v in ("identity", "mirror_x", "mirror_y")],
    ids=[*VIEWS, "identity-20x40", "mirror_x-20x40", "mirror_y-20x40"],
)
def test_unview_maps_the_views_box_back_onto_the_box(view, grid):
    """A box seen in a view (centre and heading through the view's map, rasterised there) and
    mapped back covers exactly the cells of the box rasterised in the lidar frame. A
    mutation audit: the row and column centres swapped in the cell map passed while every
    grid was square."""
    check_views((view,), grid)
    x, y, length, width, yaw = 0.73, -0.41, 1.26, 0.58, 0.37
    a = np.array(VIEWS[view], np.float64)
    xv, yv = a @ [x, y]
    hx, hy = a @ [math.cos(yaw), math.sin(yaw)]
    yaw_v = math.atan2(hy, hx)

    def raster(bx, by, byaw):
        boxes = jnp.array([[bx, by, length, width, byaw]], jnp.float32)
        return np.asarray(rasterize_boxes(boxes, jnp.ones(1, bool), grid)[1][0])

    want = raster(x, y, yaw)
    seen = raster(xv, yv, yaw_v)
    back = unview_predictions(_one_query(seen, [xv, yv, 0.3], yaw_v), view)
    assert want.sum() > 50
    np.testing.assert_array_equal(np.asarray(back.masks[0, 0, 0]) > 0.5, want)
    np.testing.assert_allclose(np.asarray(back.pos).ravel(), [x, y, 0.3], atol=1e-6)
    assert math.isclose(float(back.yaw.ravel()[0]), yaw, abs_tol=1e-6)
    # view_points applies the same map to a cloud.
    pts = jnp.array([[x, y, 0.5, 0.9]], jnp.float32)
    np.testing.assert_allclose(np.asarray(view_points(pts, view))[0], [xv, yv, 0.5, 0.9], atol=1e-6)


def _random_views(rng, views, b, q, h, w, spread):
    """V views of the same B frames: shared query logits plus per-view noise."""
    base_logits = rng.normal(0, 2, (b, q, K))
    base_masks = rng.normal(0, 3, (b, q, h, w))
    noise = lambda shape: rng.normal(0, spread, shape)  # noqa: E731
    logits = np.stack([base_logits + noise(base_logits.shape) for _ in range(views)])
    masks = np.stack([base_masks + noise(base_masks.shape) for _ in range(views)])
    masks[:, :, 0] = -9.0  # query 0: an empty mask in every view
    return Predictions(
        logits=jnp.asarray(logits[:, None], jnp.float32),
        dims=jnp.asarray(rng.uniform(0.2, 2, (views, 1, b, q, 3)), jnp.float32),
        pos=jnp.asarray(rng.normal(0, 2, (views, 1, b, q, 3)), jnp.float32),
        yaw=jnp.asarray(rng.uniform(-3, 3, (views, 1, b, q, 1)), jnp.float32),
        masks=jnp.asarray(masks[:, None], jnp.float32),
    )


def _fuse_reference(pred, mask_threshold, iou_threshold):
    """Loops in float64: greedy clusters by score, one member per view, means."""
    logits = np.asarray(pred.logits[:, -1], np.float64)  # [V, B, Q, K]
    masks = np.asarray(pred.masks[:, -1], np.float64)
    dims, pos, yaw = (np.asarray(x[:, -1], np.float64) for x in (pred.dims, pred.pos, pred.yaw))
    v, b, q = logits.shape[:3]
    e = np.exp(logits - logits.max(-1, keepdims=True))
    probs = (e / e.sum(-1, keepdims=True))[..., :-1]
    prob = 1 / (1 + np.exp(-masks))
    binary = prob >= mask_threshold
    out = {k: [] for k in ("fg", "mask", "dims", "pos", "yaw", "count")}
    for f in range(b):
        flat = lambda x: x[:, f].reshape((v * q,) + x.shape[3:])  # noqa: E731,B023
        pb, pp, pr = flat(probs), flat(prob), flat(binary).reshape(v * q, -1)
        pd, ppos, pyaw = flat(dims), flat(pos), flat(yaw)
        area = pr.sum(-1)
        score = [
            pb[i].max() * pp[i].ravel()[pr[i]].mean() if area[i] else -1.0 for i in range(v * q)
        ]
        free = [area[i] > 0 for i in range(v * q)]
        fg = np.zeros((v * q, K - 1))
        mask = np.full((v * q,) + pp.shape[1:], np.nan)
        d, p, y = np.zeros((v * q, 3)), np.zeros((v * q, 3)), np.zeros((v * q, 1))
        count = np.zeros(v * q, int)
        for i in sorted(range(v * q), key=lambda i: -score[i]):  # stable: lower index first
            if not free[i]:
                continue
            members = [i]
            for view in range(v):
                if view == i // q:
                    continue
                best, best_iou = None, iou_threshold
                for j in range(view * q, (view + 1) * q):
                    if not free[j]:
                        continue
                    iou = (pr[i] & pr[j]).sum() / (pr[i] | pr[j]).sum()
                    if iou > 0 and iou >= best_iou and (best is None or iou > best_iou):
                        best, best_iou = j, iou
                if best is not None:
                    members.append(best)
            for j in members:
                free[j] = False
            wts = np.array([pb[j].max() for j in members])
            fg[i] = pb[members].sum(0) / v
            mask[i] = pp[members].mean(0)
            d[i], p[i] = wts @ pd[members] / wts.sum(), wts @ ppos[members] / wts.sum()
            y[i] = np.arctan2(wts @ np.sin(pyaw[members]), wts @ np.cos(pyaw[members]))
            count[i] = len(members)
        for k, x in zip(out, (fg, mask, d, p, y, count), strict=True):
            out[k].append(x)
    return {k: np.stack(x) for k, x in out.items()}


@pytest.mark.parametrize("spread", [0.3, 2.0])
def test_fuse_views_matches_loop_rederivation(spread):
    rng = np.random.default_rng(int(spread * 10))
    pred = _random_views(rng, views=3, b=2, q=5, h=6, w=7, spread=spread)
    fused = jax.jit(fuse_views, static_argnums=(1, 2))(pred, 0.5, 0.4)
    ref = _fuse_reference(pred, 0.5, 0.4)
    assert fused.logits.shape == (1, 2, 15, K) and fused.masks.shape == (1, 2, 15, 6, 7)
    lead = ref["count"] > 0
    assert 0 < lead.sum() < lead.size  # some clusters merge, some queries are absorbed
    assert not lead[:, [0, 5, 10]].any()  # empty masks lead nothing
    probs = np.asarray(jax.nn.softmax(fused.logits[0], -1))
    np.testing.assert_allclose(probs[..., :-1][lead], ref["fg"][lead], atol=1e-5)
    assert (probs[..., :-1][~lead] < 1e-20).all()
    mask_prob = np.asarray(jax.nn.sigmoid(fused.masks[0]))
    np.testing.assert_allclose(mask_prob[lead], np.clip(ref["mask"][lead], 1e-6, 1 - 1e-6),
                               atol=1e-5)  # fmt: skip
    assert (mask_prob[~lead] == 0).all()
    for name in ("dims", "pos", "yaw"):
        np.testing.assert_allclose(
            np.asarray(getattr(fused, name)[0])[lead], ref[name][lead], atol=1e-4, err_msg=name
        )


def test_a_duplicate_in_the_leaders_own_view_does_not_replace_the_leader():
    """A leader is always a member of its own cluster, even when a lower-index query of its
    own view has the same mask (Mask2Former-style duplicates): checked against the loop
    re-derivation. A mutation audit: the leader not forced into its cluster (the duplicate
    taken instead, the leader's own prediction lost) passed."""
    v, q, h, w = 2, 3, 6, 6
    logits = np.full((v, 1, 1, q, K), -5.0, np.float32)
    masks = np.full((v, 1, 1, q, h, w), -10.0, np.float32)
    logits[0, ..., 0, 0], masks[0, ..., 0, :3, :3] = 1.0, 2.0  # the duplicate, lower score
    logits[0, ..., 1, 0], masks[0, ..., 1, :3, :3] = 5.0, 4.0  # the leader
    logits[1, ..., 0, 0], masks[1, ..., 0, :3, :3] = 4.0, 3.0
    rng = np.random.default_rng(0)

    def uniform(*shape):
        return jnp.asarray(rng.uniform(0.5, 1.5, (v, 1, 1, q) + shape), jnp.float32)

    pred = Predictions(logits=jnp.asarray(logits), masks=jnp.asarray(masks), dims=uniform(3),
                       pos=uniform(3), yaw=uniform(1))  # fmt: skip
    ref = _fuse_reference(pred, 0.5, 0.5)
    fused = fuse_views(pred, 0.5, 0.5)
    lead = ref["count"] > 0
    assert lead.sum() == 2  # the duplicate leads its own cluster, the leader takes view 1's
    probs = np.asarray(jax.nn.softmax(fused.logits[0], -1))[..., :-1]
    np.testing.assert_allclose(probs[lead], ref["fg"][lead], atol=1e-5)
    np.testing.assert_allclose(np.asarray(fused.pos[0])[lead], ref["pos"][lead], atol=1e-5)


def test_fuse_views_reads_only_the_last_decoder_layer():
    """Fusion is of the final predictions: the earlier layers change nothing. A mutation
    audit: fusing layer 0 passed every unit test (their predictions have one layer)."""
    rng = np.random.default_rng(1)

    def normal(*shape):
        return jnp.asarray(rng.normal(0, 2, (2, 2, 1, 3) + shape), jnp.float32)  # [V, L, B, Q]

    pred = Predictions(logits=normal(K), masks=normal(6, 7), dims=normal(3), pos=normal(3),
                       yaw=normal(1))  # fmt: skip
    got = fuse_views(pred, 0.5, 0.5)
    want = fuse_views(jax.tree.map(lambda x: x[:, -1:], pred), 0.5, 0.5)
    for a, b in zip(jax.tree.leaves(got), jax.tree.leaves(want), strict=True):
        np.testing.assert_array_equal(np.asarray(a), np.asarray(b))


def test_unview_batch_undoes_view_batch_with_several_frames():
    """``view_batch`` stacks the V views view-major ([view 0 of every frame, view 1 ...]);
    ``unview_batch`` must slice them back that way. A mutation audit: slicing frame-major
    passed (every test used one frame, where both orders agree)."""
    views, b = ("identity", "mirror_y"), 3
    points = jnp.arange(b, dtype=jnp.float32)[:, None, None] * jnp.ones((b, 5, 4))
    clouds, _ = view_batch(points, jnp.ones((b, 5), bool), views)
    frame_of = np.asarray(clouds[:, 0, 2])  # z (no view changes it) carries the frame
    n = len(views) * b
    tag = jnp.asarray(frame_of, jnp.float32)[None, :, None, None] * jnp.ones((1, n, 2, K))

    def zeros(*shape):
        return jnp.zeros((1, n, 2) + shape)

    stacked = unview_batch(
        Predictions(logits=tag, dims=zeros(3), pos=zeros(3), yaw=zeros(1), masks=zeros(4, 4)), views
    )
    np.testing.assert_array_equal(np.asarray(stacked.logits[:, 0, :, 0, 0]), [[0, 1, 2]] * 2)


def test_an_empty_or_disjoint_mask_joins_no_cluster_at_view_iou_0():
    """An IoU of 0 passed a view_iou of 0: an empty mask joined the cluster, added its class
    probability and halved the mask probability, so the leader's 9-cell object vanished."""
    v, q, h, w = 2, 2, 6, 6
    logits = np.full((v, 1, 1, q, K), -5.0, np.float32)
    masks = np.full((v, 1, 1, q, h, w), -10.0, np.float32)
    logits[0, ..., 0, 0], masks[0, ..., 0, :3, :3] = 5.0, 5.0  # view 0: the object
    logits[1, ..., 0, 0] = 5.0  # view 1: the same class with an empty mask
    logits[1, ..., 1, 0], masks[1, ..., 1, 4:, 4:] = 5.0, 5.0  # view 1: the class elsewhere
    zeros = lambda *s: jnp.zeros((v, 1, 1, q) + s)  # noqa: E731
    pred = Predictions(logits=jnp.asarray(logits), masks=jnp.asarray(masks),
                       dims=zeros(3), pos=zeros(3), yaw=zeros(1))  # fmt: skip
    alone = float(jax.nn.softmax(logits[0, 0, 0, 0])[0]) / v  # no other view's member
    for view_iou in (0.0, 0.5):
        fused = fuse_views(pred, 0.5, view_iou)
        fg = float(jax.nn.softmax(fused.logits[0, 0, 0])[0])
        assert fg == pytest.approx(alone, rel=1e-5), view_iou
        assert int((fused.masks[0, 0, 0] >= 0).sum()) == 9, view_iou


def _fg_logits(p):
    """Class logits [K] whose softmax puts ``p`` on class 0 and the rest on background."""
    probs = np.full(K, 1e-9)
    probs[0], probs[-1] = p, 1.0 - p - (K - 2) * 1e-9
    return np.log(probs)


def _two_views(p_cls, row_logits):
    """Predictions of V = Q = 2 on a 6 x 6 grid (the shapes of the test above, so that the
    compiled fusion is reused): class-0 probabilities [V * Q] and mask logits [V * Q, 6] of
    grid row 0 (the other rows empty), view-major."""
    logits = np.stack([_fg_logits(p) for p in p_cls]).reshape(2, 1, 1, 2, K)
    masks = np.full((2, 1, 1, 2, 6, 6), -10.0)
    masks[..., 0, :] = np.reshape(row_logits, (2, 1, 1, 2, 6))
    zeros = lambda *s: jnp.zeros((2, 1, 1, 2) + s)  # noqa: E731
    return Predictions(logits=jnp.asarray(logits, jnp.float32), dims=zeros(3), pos=zeros(3),
                       yaw=zeros(1), masks=jnp.asarray(masks, jnp.float32))  # fmt: skip


@pytest.mark.parametrize(("view1_cells", "joins"), [((0, 2), True), ((3, 5), False)])
def test_view_iou_is_inclusive(view1_cells, joins):
    """docs/METRICS.md: a query joins a cluster when its mask IoU with the leader is
    >= view_iou. View 0's mask has cells 0-3; view 1's the 2 cells 0-1 (IoU 2 / 4 = 0.5,
    exactly the default view_iou: one object) or cells 3-4 (IoU 1 / 5: two objects)."""
    rows = np.full((4, 6), -10.0)
    rows[0, 0:4] = 5.0
    rows[2, slice(*view1_cells)] = 5.0
    pred = _two_views([0.9, 0.01, 0.7, 0.01], rows)  # queries 1 of each view: no mask
    fused = fuse_views(pred, 0.5, 0.5)
    fg = np.asarray(jax.nn.softmax(fused.logits[0, 0], -1))[:, 0]  # per slot
    want = [(0.9 + 0.7) / 2, 0, 0, 0] if joins else [0.9 / 2, 0, 0.7 / 2, 0]
    np.testing.assert_allclose(fg, want, atol=1e-6)
    ref = _fuse_reference(pred, 0.5, 0.5)
    np.testing.assert_array_equal(ref["count"][0], [2, 0, 0, 0] if joins else [1, 0, 1, 0])
    np.testing.assert_allclose(fg, ref["fg"][0, :, 0], atol=1e-6)


def test_clusters_form_in_decreasing_detection_score():
    """docs/METRICS.md: greedy in decreasing score = p_cls * mean mask probability, not in
    decreasing p_cls. View 0: A (p_cls 0.9, mask probability 0.6: score 0.54) and B (0.85,
    0.993: 0.84); view 1: C (0.8, 0.993: 0.79) overlaps both with IoU 3 / 5, and D has no
    mask. B leads first and takes C; A is left alone. In p_cls order A would take C."""
    rows = np.full((4, 6), -10.0)
    rows[0, 0:4] = np.log(0.6 / 0.4)  # A: cells 0-3
    rows[1, 2:6] = 5.0  # B: cells 2-5
    rows[2, 1:5] = 5.0  # C: cells 1-4
    pred = _two_views([0.9, 0.85, 0.8, 0.01], rows)
    fused = fuse_views(pred, 0.5, 0.5)
    fg = np.asarray(jax.nn.softmax(fused.logits[0, 0], -1))[:, 0]  # slots A, B, C, D
    np.testing.assert_allclose(fg, [0.9 / 2, (0.85 + 0.8) / 2, 0.0, 0.0], atol=1e-6)
    ref = _fuse_reference(pred, 0.5, 0.5)
    np.testing.assert_array_equal(ref["count"][0], [1, 2, 0, 0])
    np.testing.assert_allclose(fg, ref["fg"][0, :, 0], atol=1e-6)
    # B's slot holds the mean of B's and C's mask probabilities: cell 1 is C's alone.
    mask_prob = np.asarray(jax.nn.sigmoid(fused.masks[0, 0, 1, 0]))
    sig = lambda x: 1 / (1 + np.exp(-x))  # noqa: E731
    np.testing.assert_allclose(mask_prob[:2], [sig(-10.0), (sig(-10.0) + sig(5.0)) / 2],
                               atol=1e-6)  # fmt: skip


def test_identical_views_fuse_to_the_plain_inference():
    rng = np.random.default_rng(5)
    pred = _random_views(rng, views=1, b=2, q=6, h=8, w=8, spread=0.0)
    copies = jax.tree.map(lambda x: jnp.concatenate([x] * 4), pred)
    cfg = InferenceConfig(score_threshold=0.2, overlap_threshold=0.5)
    plain = panoptic_inference(jax.tree.map(lambda x: x[0], pred), cfg)
    fused = panoptic_inference(fuse_views(copies, cfg.mask_threshold, cfg.view_iou), cfg)
    assert np.asarray(plain.segment_valid).any()
    np.testing.assert_array_equal(fused.instance_ids, plain.instance_ids)
    np.testing.assert_array_equal(fused.det_valid[:, :6], plain.det_valid)
    assert not np.asarray(fused.det_valid[:, 6:]).any()
    np.testing.assert_allclose(fused.det_scores[:, :6], plain.det_scores, rtol=1e-5)
    detected = np.asarray(plain.det_valid)
    assert detected.sum() == 10  # all but the empty query 0 of each frame
    np.testing.assert_array_equal(
        np.asarray(fused.det_classes[:, :6])[detected], np.asarray(plain.det_classes)[detected]
    )


def test_apply_views_is_mirror_equivariant_on_the_tiny_model():
    """The same two clouds in the same order, read as (P; identity, mirror_y) and as
    (mirror_y(P); mirror_y, identity): the fused outputs are each other's mirror images."""
    from indoorbev_jax.models import IndoorBEV
    from indoorbev_jax.train import init_state

    config = Config.tiny()
    params = init_state(config, jax.random.key(0)).params
    model = IndoorBEV(config)
    rng = np.random.default_rng(3)
    n = config.data.max_points
    points = jnp.asarray(rng.uniform(-4, 4, (1, n, 4)) * [1, 1, 0.3, 0.1], jnp.float32)
    valid = jnp.asarray(rng.uniform(size=(1, n)) < 0.5)
    first = InferenceConfig(views=("identity", "mirror_y"), mask_threshold=0.45)
    second = dataclasses.replace(first, views=("mirror_y", "identity"))
    run = jax.jit(lambda p, c, cfg: apply_views(model, p, c, valid, cfg), static_argnums=2)
    a = run(params, points, first)
    b = run(params, view_points(points, "mirror_y"), second)
    q = config.head.num_queries
    assert a.logits.shape == (1, 1, 2 * q, K) and a.masks.shape[:3] == (1, 1, 2 * q)
    np.testing.assert_allclose(a.logits, b.logits, atol=1e-5)
    np.testing.assert_allclose(a.masks, jnp.flip(b.masks, -2), atol=1e-4)
    np.testing.assert_allclose(a.pos, b.pos * jnp.array([1, -1, 1]), atol=1e-5)
    np.testing.assert_allclose(jnp.sin(a.yaw), -jnp.sin(b.yaw), atol=1e-5)
    plain = jax.jit(model.apply)(params, points, valid)
    identity = run(params, points, InferenceConfig())
    jax.tree.map(np.testing.assert_array_equal, identity, plain)


def test_bad_views_are_named():
    with pytest.raises(ConfigError, match=r"inference\.views.*'sideways'"):
        InferenceConfig(views=("identity", "sideways"))
    with pytest.raises(ConfigError, match=r"inference\.views.*repeats"):
        InferenceConfig(views=("identity", "identity"))
    off_centre = GridConfig(x_range=(0.0, 8.0), y_range=(-4.0, 4.0), cell_size=0.5)
    with pytest.raises(ConfigError, match=r"'mirror_x' mirrors grid\.x_range"):
        Config(grid=off_centre, inference=InferenceConfig(views=("identity", "mirror_x")))
    Config(grid=off_centre, inference=InferenceConfig(views=("identity", "mirror_y")))
    # Off centre in y: every view that mirrors y is refused (a mutation audit: y unchecked).
    off_y = GridConfig(x_range=(-4.0, 4.0), y_range=(-2.0, 6.0), cell_size=0.5)
    for view in ("mirror_y", "rotate_180"):
        with pytest.raises(ConfigError, match=rf"'{view}' mirrors grid\.y_range"):
            Config(grid=off_y, inference=InferenceConfig(views=("identity", view)))
    oblong = GridConfig(x_range=(-4.0, 4.0), y_range=(-2.0, 2.0), cell_size=0.5)
    square_off_y = GridConfig(x_range=(-4.0, 4.0), y_range=(-6.0, 4.0), cell_size=0.5)
    for grid in (oblong, square_off_y):  # a swap needs the grid square and y centred too
        with pytest.raises(ConfigError, match=r"'rotate_90' swaps x and y"):
            Config(grid=grid, inference=InferenceConfig(views=("rotate_90",)))
    assert parse_views("all") == tuple(VIEWS) and len(VIEWS) == 8
    assert parse_views("identity, mirror_y") == ("identity", "mirror_y")
    with pytest.raises(argparse.ArgumentTypeError, match="unknown view 'flip'"):
        parse_views("identity,flip")
    # Refused here, not once the model has loaded (seconds later, in the detect node).
    with pytest.raises(argparse.ArgumentTypeError, match="'identity,identity' repeats a view"):
        parse_views("identity,identity")
