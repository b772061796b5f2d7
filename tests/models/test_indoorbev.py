"""The whole network: output shapes, tracing, invariances, remat and the pooled memory."""

import dataclasses
import pathlib
import re
import sys

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from indoorbev_jax.config import Config
from indoorbev_jax.models import IndoorBEV
from indoorbev_jax.models.head import (
    DecoderLayer,
    SimpleMaskHead,
    code_map,
    pool_memory,
    positional_code,
    sine_code_1d,
)
from indoorbev_jax.types import Predictions

sys.path.insert(0, str(pathlib.Path(__file__).parents[1]))
from numpy_layers import dense, layer_norm  # noqa: E402

FAST = {"xla_backend_optimization_level": 0}
TINY = Config.tiny()
MODEL = IndoorBEV(TINY)
TRACES = []


def _forward(params, points, valid):
    TRACES.append(points.shape)  # runs once per trace, not per call
    return MODEL.apply(params, points, valid)


FORWARD = jax.jit(_forward, compiler_options=FAST)


def _points(seed: int, b: int, n: int) -> tuple[np.ndarray, np.ndarray]:
    rng = np.random.default_rng(seed)
    lo, hi = np.array([-5, -5, -3, 0.0]), np.array([5, 5, 3, 1.0])
    pts = (lo + rng.uniform(size=(b, n, 4)) * (hi - lo)).astype(np.float32)
    return pts, rng.uniform(size=(b, n)) > 0.05


@pytest.fixture(scope="module")
def params():
    pts, valid = _points(0, 2, 256)
    return jax.jit(MODEL.init, compiler_options=FAST)(jax.random.key(0), pts, valid)


def test_paper_preset_shapes_and_parameter_count_from_eval_shape():
    cfg = Config.paper()
    model = IndoorBEV(cfg)
    pts = jax.ShapeDtypeStruct((2, 4096, 4), jnp.float32)
    valid = jax.ShapeDtypeStruct((2, 4096), jnp.bool_)
    params = jax.eval_shape(model.init, jax.random.key(0), pts, valid)
    out = jax.eval_shape(model.apply, params, pts, valid)
    assert isinstance(out, Predictions)
    assert cfg.grid.shape == (500, 500)
    assert out.logits.shape == (4, 2, 30, 10)
    assert out.dims.shape == (4, 2, 30, 3) and out.pos.shape == (4, 2, 30, 3)
    assert out.yaw.shape == (4, 2, 30, 1)
    assert out.masks.shape == (4, 2, 30, 500, 500)
    assert all(x.dtype == jnp.float32 for x in jax.tree.leaves(out))
    n = sum(x.size for x in jax.tree.leaves(params))
    # docs/MODEL.md states the count; keep the two in step.
    doc = pathlib.Path(__file__).parents[2] / "docs" / "MODEL.md"
    stated = re.search(r"paper preset has ([\d,]+) parameters", doc.read_text())
    assert stated and int(stated.group(1).replace(",", "")) == n, n
    small = jax.eval_shape(IndoorBEV(Config.small()).init, jax.random.key(0), pts, valid)
    stated = re.search(r"`small` preset has ([\d,]+)", doc.read_text())
    n_small = sum(x.size for x in jax.tree.leaves(small))
    assert stated and int(stated.group(1).replace(",", "")) == n_small, n_small


def test_tiny_forward_traces_once_per_shape_and_ignores_order_and_padding(params):
    h, w = TINY.grid.shape
    pts, valid = _points(1, 2, 256)
    TRACES.clear()
    out = FORWARD(params, pts, valid)
    L, Q, K = TINY.head.num_layers, TINY.head.num_queries, TINY.num_classes + 1
    assert out.logits.shape == (L, 2, Q, K) and out.masks.shape == (L, 2, Q, h, w)
    assert out.yaw.shape == (L, 2, Q, 1) and out.dims.shape == (L, 2, Q, 3)
    for leaf in jax.tree.leaves(out):
        assert np.isfinite(np.asarray(leaf)).all()

    perm = np.random.default_rng(2).permutation(256)
    shuffled = FORWARD(params, pts[:, perm], valid[:, perm])  # same shape: no new trace
    assert len(TRACES) == 1
    # More slots, all unusable (flagged invalid, NaN, or outside the workspace): new shape,
    # one more trace, same predictions.
    junk = np.full((2, 64, 4), 7.0, np.float32)
    junk[:, ::2] = np.nan
    junk_valid = np.zeros((2, 64), bool)
    junk_valid[:, 1::4] = True  # "valid" but at x = y = 7 m, outside [-5, 5)
    padded = FORWARD(params, np.concatenate([pts, junk], 1), np.concatenate([valid, junk_valid], 1))
    FORWARD(params, np.concatenate([pts, junk], 1), np.concatenate([valid, junk_valid], 1))
    assert TRACES == [(2, 256, 4), (2, 320, 4)]
    leaves = zip(*(jax.tree.leaves(x) for x in (out, shuffled, padded)), strict=True)
    for ref, a, b in leaves:
        np.testing.assert_allclose(np.asarray(a), np.asarray(ref), rtol=1e-4, atol=1e-4)
        np.testing.assert_allclose(np.asarray(b), np.asarray(ref), rtol=1e-4, atol=1e-4)
    # Not a constant network: another frame gives other masks.
    other = FORWARD(params, *_points(3, 2, 256))
    assert np.abs(np.asarray(other.masks) - np.asarray(out.masks)).max() > 1e-3


def test_remat_changes_neither_outputs_nor_gradients(params):
    cfg = dataclasses.replace(
        TINY,
        backbone=dataclasses.replace(TINY.backbone, remat=True),
        head=dataclasses.replace(TINY.head, remat=True),
    )
    pts, valid = _points(4, 2, 256)

    def loss(model, p):
        out = model.apply(p, pts, valid)
        return sum(jnp.mean(jnp.sin(x)) for x in jax.tree.leaves(out))

    grad = jax.jit(
        lambda p: (jax.value_and_grad(lambda q: loss(MODEL, q))(p),
                   jax.value_and_grad(lambda q: loss(IndoorBEV(cfg), q))(p)),
        compiler_options=FAST,
    )  # fmt: skip
    (l0, g0), (l1, g1) = grad(params)
    np.testing.assert_allclose(l1, l0, rtol=1e-6)
    for a, b in zip(jax.tree.leaves(g0), jax.tree.leaves(g1), strict=True):
        np.testing.assert_allclose(np.asarray(b), np.asarray(a), rtol=1e-4, atol=1e-6)
    assert max(np.abs(np.asarray(a)).max() for a in jax.tree.leaves(g0)) > 0


@pytest.mark.parametrize("h,w,s", [(10, 10, 2), (10, 7, 4), (5, 6, 1)])
def test_pooled_memory_and_code_match_numpy_block_means(h, w, s):
    f = np.random.default_rng(5).normal(size=(2, h, w, 6)).astype(np.float32)
    out = np.asarray(pool_memory(jnp.asarray(f), s))
    hp, wp = -(-h // s), -(-w // s)
    assert out.shape == (2, hp, wp, 6)
    for i in range(hp):
        for j in range(wp):
            ref = f[:, i * s : (i + 1) * s, j * s : (j + 1) * s].mean((1, 2))
            np.testing.assert_allclose(out[:, i, j], ref, rtol=1e-5, atol=1e-6)
    # The pooled code is the block mean of the full-resolution code, half y, half x.
    cy, cx = positional_code(h, w, 8, s)
    full = np.concatenate(
        [np.broadcast_to(sine_code_1d(h, 4)[:, None], (h, w, 4)),
         np.broadcast_to(sine_code_1d(w, 4)[None], (h, w, 4))], -1,
    )  # fmt: skip
    pooled = np.asarray(pool_memory(jnp.asarray(full[None]), s))[0]
    np.testing.assert_allclose(
        pooled[..., :4], np.broadcast_to(cy[:, None], (hp, wp, 4)), atol=1e-6
    )
    np.testing.assert_allclose(pooled[..., 4:], np.broadcast_to(cx[None], (hp, wp, 4)), atol=1e-6)
    # The map the decoder adds to its keys is that code laid out per cell, y half first (the
    # trained checkpoints' order: x first cost the shipped model 16 points of AP@0.5).
    per_cell = [np.broadcast_to(cy[:, None], (hp, wp, 4)), np.broadcast_to(cx[None], (hp, wp, 4))]
    np.testing.assert_array_equal(code_map(cy, cx, jnp.float32), np.concatenate(per_cell, -1))
    # DETR's code: sin on even channels, cos on odd ones, position (p + 1) / n * 2 pi.
    p = (np.arange(h) + 1) / h * 2 * np.pi
    np.testing.assert_allclose(sine_code_1d(h, 4)[:, 0], np.sin(p), atol=1e-6)
    np.testing.assert_allclose(sine_code_1d(h, 4)[:, 3], np.cos(p / 10000**0.5), atol=1e-6)


def test_grid_that_is_not_square():
    """DESIGN section 2 sizes H (along y) and W (along x) apart: a 4 m x 10 m grid gives
    16 x 40 masks and stays invariant to point order."""
    grid = dataclasses.replace(TINY.grid, y_range=(-2.0, 2.0))
    cfg = dataclasses.replace(TINY, grid=grid)
    assert grid.shape == (16, 40)
    model = IndoorBEV(cfg)
    pts, valid = _points(5, 2, 256)
    pts[..., 1] *= 0.4  # y within [-2, 2]
    p = jax.jit(model.init, compiler_options=FAST)(jax.random.key(1), pts, valid)
    apply = jax.jit(model.apply, compiler_options=FAST)
    out = apply(p, pts, valid)
    assert out.masks.shape == (TINY.head.num_layers, 2, TINY.head.num_queries, 16, 40)
    perm = np.random.default_rng(0).permutation(pts.shape[1])
    again = apply(p, pts[:, perm], valid[:, perm])
    np.testing.assert_allclose(again.masks, out.masks, atol=1e-4)


def test_bfloat16_model_computes_its_output_heads_in_float32(params):
    """With ``train.bfloat16`` the box and class heads still run in float32: positions
    4-5 m out used to snap to bfloat16's 3 cm lattice (1.5 cells of the paper grid)."""
    shifted = jax.tree_util.tree_map_with_path(
        lambda k, a: a + 4.5 if "pos_head" in jax.tree_util.keystr(k) else a, params
    )
    bf16 = dataclasses.replace(TINY, train=dataclasses.replace(TINY.train, bfloat16=True))
    pts, valid = _points(3, 1, 256)
    out = jax.jit(IndoorBEV(bf16).apply, compiler_options=FAST)(shifted, pts, valid)
    for field in (out.pos, out.dims, out.yaw, out.logits):
        x = np.asarray(field)
        on_lattice = np.asarray(jnp.asarray(x).astype(jnp.bfloat16).astype(jnp.float32)) == x
        assert x.dtype == np.float32 and on_lattice.mean() < 0.5
    ref = np.asarray(FORWARD(shifted, pts, valid).pos)
    # The same model: the bfloat16 trunk alone moves these untrained outputs by up to 0.1 m.
    np.testing.assert_allclose(np.asarray(out.pos), ref, atol=0.2)
    # The flag alone (no dtype given, as train and predict build the model) makes the trunk
    # bfloat16. A mutation audit: the model ignoring it (all float32) passed.
    _, inter = jax.eval_shape(
        lambda p: IndoorBEV(bf16).apply(
            p, pts, valid, capture_intermediates=True, mutable=["intermediates"]
        ),
        shifted,
    )
    stages = inter["intermediates"]["backbone"]["__call__"][0]
    assert {v.dtype for v in stages.values()} == {jnp.dtype(jnp.bfloat16)}


# numpy re-derivations written from DESIGN section 7 / DETR, not from head.py


_ln, _dense = layer_norm, dense


def _mha(q_in, k_in, v_in, p, heads):
    """DETR multi-head attention for one frame, [Tq, C], [Tk, C] -> [Tq, C]; head.py scales the
    query input by 1/sqrt(d) before its projection (so the bias is scaled by sqrt(d) here)."""
    c = q_in.shape[-1]
    d = c // heads
    q = (q_in @ p["q"]["kernel"] / np.sqrt(d) + p["q"]["bias"]).reshape(-1, heads, d)
    k = _dense(k_in, p["k"]).reshape(-1, heads, d)
    v = _dense(v_in, p["v"]).reshape(-1, heads, d)
    logits = np.einsum("qhd,khd->hqk", q, k)
    w = np.exp(logits - logits.max(-1, keepdims=True))
    w /= w.sum(-1, keepdims=True)
    return _dense(np.einsum("hqk,khd->qhd", w, v).reshape(-1, c), p["out"])


def _f64(tree):
    return jax.tree.map(lambda a: np.asarray(a, np.float64), tree)


@pytest.mark.parametrize("mask_positional", [False, True])
def test_masks_are_mask_embedding_dot_f_proj(mask_positional):
    """DESIGN 7: masks[l, b, j] = <m_j, F_proj[b]> with m_j the mask MLP of layer l's query j of
    frame b. Batch 2 on a 40 x 40 grid: guards against the embeddings' layer and batch axes mixed
    (same at batch 1) and the mask map transposed (same shape on square grids). With
    ``head.mask_positional`` (docs/MODEL.md) the masks read F_proj + the full-resolution sine
    code (a mutation audit: the flag doing nothing passed)."""
    cfg = TINY
    h, w = cfg.grid.shape
    head_cfg = dataclasses.replace(cfg.head, mask_positional=mask_positional)
    head = SimpleMaskHead(head_cfg, cfg.num_classes, grid=cfg.grid)
    feats = jax.random.normal(jax.random.key(0), (2, h, w, 12))
    p = jax.jit(head.init, compiler_options=FAST)(jax.random.key(1), feats)
    run = jax.jit(
        lambda p: head.apply(p, feats, capture_intermediates=True, mutable=["intermediates"]),
        compiler_options=FAST,
    )
    out, inter = run(p)
    it, pp = inter["intermediates"], _f64(p["params"])
    f_proj = np.asarray(it["input_proj_norm"]["__call__"][0], np.float64)  # [B, H, W, C]
    q = np.stack(
        [
            np.asarray(it[f"decoder{i}"]["__call__"][0], np.float64)
            for i in range(cfg.head.num_layers)
        ]
    )
    m = np.maximum(_dense(q, pp["mask_embed0"]), 0)
    m = _dense(np.maximum(_dense(m, pp["mask_embed1"]), 0), pp["mask_embed2"])  # [L, B, Q, C]
    if mask_positional:
        f_proj = f_proj + np.asarray(
            code_map(*positional_code(h, w, cfg.head.hidden_dim), jnp.float32)
        )
    ref = np.einsum("lbqc,bhwc->lbqhw", m, f_proj)
    np.testing.assert_allclose(np.asarray(out["masks"]), ref, atol=1e-4)  # measured 2.2e-06


def test_decoder_layer_matches_post_norm_detr():
    """A decoder layer is DETR's post-norm layer: LN(t + self-attn), LN(x + cross-attn) with keys
    memory + code and values memory, LN(x + FFN(ReLU)); attention logits scaled by 1/sqrt(d_head).
    Guards against 1/sqrt(C), a dropped self-attention residual and the code on the values
    instead of the keys (the streamed-vs-plain test shares these, so cannot see them)."""
    layer = DecoderLayer(TINY.head)
    k = jax.random.split(jax.random.key(2), 3)
    t = jax.random.normal(k[0], (2, 5, 16))
    mem = jax.random.normal(k[1], (2, 30, 16))
    mem_pos = mem + jax.random.normal(k[2], (2, 30, 16))
    p = layer.init(jax.random.key(3), t, mem, mem_pos)
    noise = np.random.default_rng(4)  # move off init: zero biases and unit norms hide a lot
    p = jax.tree.map(lambda a: a + 0.3 * noise.normal(size=a.shape).astype(np.float32), p)
    out = np.asarray(jax.jit(layer.apply, compiler_options=FAST)(p, t, mem, mem_pos))
    pp, heads = _f64(p["params"]), TINY.head.num_heads
    for b in range(2):
        tb, mb, kb = (np.asarray(a[b], np.float64) for a in (t, mem, mem_pos))
        x = _ln(tb + _mha(tb, tb, tb, pp["self_attn"], heads), pp["norm1"])
        x = _ln(x + _mha(x, kb, mb, pp["cross_attn"], heads), pp["norm2"])
        y = _dense(np.maximum(_dense(x, pp["ffn1"]), 0), pp["ffn2"])
        np.testing.assert_allclose(out[b], _ln(x + y, pp["norm3"]), rtol=1e-4, atol=1e-4)


def test_fresh_learned_queries_predict_distinct_boxes():
    """Freshly initialised learned queries differ, so the queries do not all predict the same
    box (identical queries stay identical through the decoder and never break symmetry)."""
    h, w = TINY.grid.shape
    head = SimpleMaskHead(TINY.head, TINY.num_classes, grid=TINY.grid)
    feats = jax.random.normal(jax.random.key(0), (1, h, w, 12))
    p = jax.jit(head.init, compiler_options=FAST)(jax.random.key(1), feats)
    pos = np.asarray(jax.jit(head.apply, compiler_options=FAST)(p, feats)["pos"])[-1, 0]  # [Q, 3]
    assert np.abs(pos - pos[0]).max() > 1e-3, "every query predicts the same box"


def test_head_reads_the_top_left_crop_of_the_upsampled_map(params):
    """The upsampled map is padded past the grid at its far (bottom, right) edges; the head's
    input is its top-left H x W crop, the cells that match the grid. Guards against cropping
    from the wrong corner (shifts every mask and box by the padding)."""
    h, w = TINY.grid.shape
    pts, valid = _points(0, 2, 256)
    run = jax.jit(
        lambda p: MODEL.apply(p, pts, valid, capture_intermediates=True, mutable=["intermediates"]),
        compiler_options=FAST,
    )
    it = run(params)[1]["intermediates"]
    up = np.asarray(it["upsampler"]["__call__"][0], np.float64)  # [B, H', W', C'] padded
    proj = np.asarray(it["head"]["input_proj"]["__call__"][0], np.float64)
    assert up.shape[1] > h and up.shape[2] > w
    ref = _dense(up[:, :h, :w], _f64(params["params"]["head"]["input_proj"]))
    np.testing.assert_allclose(proj, ref.reshape(proj.shape), rtol=1e-4, atol=1e-4)
