"""Swin backbone pieces against numpy re-derivations, and its attention masks inspected."""

import sys
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from indoorbev_jax.config import Config
from indoorbev_jax.models.head import depth_to_space
from indoorbev_jax.models.swin import (
    PatchEmbed,
    PatchMerging,
    SwinBackbone,
    SwinBlock,
    WindowAttention,
    relative_position_index,
    stage_geometry,
    window_masks,
    window_partition,
    window_reverse,
)

sys.path.insert(0, str(Path(__file__).parents[1]))
from numpy_layers import dense, gelu, layer_norm  # noqa: E402

# Tests only need correct numbers; skipping LLVM's optimisation halves compile time.
FAST = {"xla_backend_optimization_level": 0}


@pytest.mark.parametrize("shape,ws", [((2, 6, 6, 3), 3), ((1, 14, 21, 5), 7), ((3, 4, 8, 2), 2)])
def test_window_partition_matches_numpy_and_reverse_inverts_it(shape, ws):
    x = np.random.default_rng(0).normal(size=shape).astype(np.float32)
    b, h, w, c = shape
    win = np.asarray(window_partition(jnp.asarray(x), ws))
    assert win.shape == (b, (h // ws) * (w // ws), ws * ws, c)
    # Window (a, e) in row-major order holds rows a*ws.., columns e*ws.., row-major inside.
    for a in range(h // ws):
        for e in range(w // ws):
            ref = x[:, a * ws : (a + 1) * ws, e * ws : (e + 1) * ws].reshape(b, ws * ws, c)
            np.testing.assert_array_equal(win[:, a * (w // ws) + e], ref)
    np.testing.assert_array_equal(np.asarray(window_reverse(jnp.asarray(win), ws, h, w)), x)


def test_depth_to_space_matches_numpy():
    x = np.random.default_rng(1).normal(size=(2, 3, 4, 4 * 5)).astype(np.float32)
    y = np.asarray(depth_to_space(jnp.asarray(x), 2))
    assert y.shape == (2, 6, 8, 5)
    for r in range(2):
        for c in range(2):
            np.testing.assert_array_equal(
                y[:, r::2, c::2], x[..., (2 * r + c) * 5 : (2 * r + c + 1) * 5]
            )


def test_patch_merging_matches_numpy():
    rng = np.random.default_rng(2)
    x = rng.normal(size=(2, 6, 8, 3)).astype(np.float32)
    mod = PatchMerging(features=5)
    params = mod.init(jax.random.key(0), jnp.asarray(x))
    # Non-trivial LayerNorm affine so the test sees it.
    p = jax.tree.map(lambda a: a + rng.normal(size=a.shape).astype(np.float32) * 0.1, params)
    out = np.asarray(mod.apply(p, jnp.asarray(x)))
    # Swin: x0 = x[0::2, 0::2], x1 = x[1::2, 0::2], x2 = x[0::2, 1::2], x3 = x[1::2, 1::2].
    cat = np.concatenate(
        [x[:, 0::2, 0::2], x[:, 1::2, 0::2], x[:, 0::2, 1::2], x[:, 1::2, 1::2]], -1
    )
    pp = jax.tree.map(np.asarray, p["params"])
    ref = layer_norm(cat, pp["norm"]) @ pp["reduction"]["kernel"]
    assert "bias" not in pp["reduction"]
    np.testing.assert_allclose(out, ref, rtol=1e-5, atol=1e-5)


@pytest.mark.parametrize(("stride", "c_in"), [(1, 7), (2, 5)])
def test_patch_embed_is_a_projection_then_layer_norm(stride, c_in):
    """Swin's PatchEmbed: s x s patches (channels in PatchMerging's order: column offset,
    then row offset), a linear map, then LayerNorm. With stride 1 and C_in equal to the
    features (the paper preset), LayerNorm before the projection loads the same checkpoint."""
    rng = np.random.default_rng(4)
    x = rng.normal(size=(2, 6, 8, c_in)).astype(np.float32) * 3 + 1
    mod = PatchEmbed(features=7, stride=stride)
    params = mod.init(jax.random.key(0), jnp.asarray(x))
    p = jax.tree.map(lambda a: a + rng.normal(size=a.shape).astype(np.float32) * 0.1, params)
    out = np.asarray(mod.apply(p, jnp.asarray(x)))
    b, h, w, c = x.shape
    s = stride
    patches = x.reshape(b, h // s, s, w // s, s, c).transpose(0, 1, 3, 4, 2, 5)
    pp = jax.tree.map(np.asarray, p["params"])
    want = layer_norm(dense(patches.reshape(b, h // s, w // s, -1), pp["proj"]), pp["norm"])
    np.testing.assert_allclose(out, want, rtol=1e-5, atol=1e-5)


def _original_coords(res: tuple[int, int], ws: int, shift: int) -> np.ndarray:
    """[nW, T, 2]: (row, col) in the unrolled map of every token of every (shifted) window."""
    rh, rw = res
    rows, cols = np.meshgrid(np.arange(rh), np.arange(rw), indexing="ij")
    grid = np.stack([rows, cols], -1)
    grid = np.roll(grid, (-shift, -shift), axis=(0, 1))
    grid = grid.reshape(rh // ws, ws, rw // ws, ws, 2).transpose(0, 2, 1, 3, 4)
    return grid.reshape(-1, ws * ws, 2)


# The tiny grid (40 x 40), and 16 x 40 (DESIGN section 2 sizes H and W apart).
@pytest.mark.parametrize("shape", [(40, 40), (16, 40)])
def test_shifted_window_attention_never_crosses_a_shift_boundary_or_reads_padding(shape):
    cfg = Config.tiny().backbone
    assert Config.tiny().grid.shape == (40, 40)
    geo = stage_geometry(shape, cfg)
    if shape[0] == shape[1]:  # a square side given as one int gives the same, as ints
        assert stage_geometry(shape[0], cfg) == [(r[0], v[0], s) for r, v, s in geo]
    assert any(s for _, _, s in geo), "the grid must exercise SW-MSA"
    assert any(v != r for r, v, _ in geo), "the grid must exercise padding"
    x = jax.random.normal(jax.random.key(3), (2, *shape, 16))
    mod = SwinBackbone(cfg)
    params = jax.jit(mod.init, compiler_options=FAST)(jax.random.key(4), x)
    _, inter = jax.jit(
        lambda p, x: mod.apply(p, x, mutable=["intermediates"]), compiler_options=FAST
    )(params, x)
    ws = cfg.window_size
    checked_shift = checked_pad = 0
    for k, (res, valid, shift) in enumerate(geo):
        s = shift if cfg.shifted[k] else 0
        (w,) = inter["intermediates"][f"stage{k}_block0"]["attn"]["attention_weights"]
        w = np.asarray(w).transpose(0, 2, 1, 3, 4)  # [B, h, nW, T, T]
        xy = _original_coords(res, ws, s)  # [nW, T, 2]
        # Tokens of one window that are neighbours in the unrolled map: a pair wrapped around
        # by the shift is >= res - ws apart.
        d = np.abs(xy[:, :, None, :] - xy[:, None, :, :]).max(-1)  # [nW, T, T]
        contiguous = d < ws
        key_valid = (xy < np.asarray(valid)).all(-1)  # [nW, T]
        allowed = contiguous & key_valid[:, None, :]
        q_valid = key_valid[:, :, None] & np.ones_like(allowed)
        forbidden = ~allowed & q_valid
        assert np.all(w[:, :, forbidden] == 0.0), f"stage {k}: attention crosses a boundary"
        assert np.all(w[:, :, allowed & q_valid] > 0.0), f"stage {k}: over-masked"
        np.testing.assert_allclose(w.sum(-1), 1.0, rtol=1e-5)
        checked_shift += int((~contiguous).any())
        checked_pad += int((~key_valid).any())
    assert checked_shift >= 1 and checked_pad >= 1


# numpy re-derivations written from Swin (Liu et al. 2021), not from swin.py


_ln, _dense = layer_norm, dense


def _softmax(z):
    e = np.exp(z - z.max(-1, keepdims=True))
    return e / e.sum(-1, keepdims=True)


def _swin_rel_index(ws):
    """Swin's bias-table row for (query, key): (dy + ws - 1) * (2 ws - 1) + dx + ws - 1 with
    (dy, dx) = query - key."""
    idx = np.zeros((ws * ws, ws * ws), int)
    for q in range(ws * ws):
        for k in range(ws * ws):
            dy, dx = q // ws - k // ws, q % ws - k % ws
            idx[q, k] = (dy + ws - 1) * (2 * ws - 1) + (dx + ws - 1)
    return idx


def _window_attention(x, p, heads, ws, allowed):
    """x [nW, T, C], allowed [nW, T, T] bool: multi-head attention scaled by 1/sqrt(d_head)."""
    nw, t, c = x.shape
    d = c // heads
    qkv = _dense(x, p["qkv"]).reshape(nw, t, 3, heads, d)
    q, k, v = qkv[:, :, 0], qkv[:, :, 1], qkv[:, :, 2]
    logits = np.einsum("wqhd,wkhd->whqk", q, k) / np.sqrt(d)
    logits = logits + p["relative_position_bias"][_swin_rel_index(ws)].transpose(2, 0, 1)[None]
    w = _softmax(np.where(allowed[:, None], logits, -np.inf))
    return _dense(np.einsum("whqk,wkhd->wqhd", w, v).reshape(nw, t, c), p["proj"])


def _windows(m, ws):  # [R, R, C] -> [nW, T, C], windows row-major
    n = m.shape[0] // ws
    return np.stack(
        [
            m[a * ws : (a + 1) * ws, e * ws : (e + 1) * ws].reshape(ws * ws, -1)
            for a in range(n)
            for e in range(n)
        ]
    )


def _unwindows(w, ws, r):
    m, n = np.zeros((r, r, w.shape[-1])), r // ws
    for i in range(n * n):
        a, e = divmod(i, n)
        m[a * ws : (a + 1) * ws, e * ws : (e + 1) * ws] = w[i].reshape(ws, ws, -1)
    return m


def _perturbed_f64(params, seed):
    """Params moved off their init (zero biases and bias tables hide index bugs), and a float64
    copy for the numpy side."""
    rng = np.random.default_rng(seed)
    p = jax.tree.map(lambda a: a + 0.3 * rng.normal(size=a.shape).astype(np.float32), params)
    return p, jax.tree.map(lambda a: np.asarray(a, np.float64), p["params"])


def test_relative_position_index_is_swins_table():
    """Row (query, key) of the bias table is Swin's (dy, dx) = query - key, dy major. Guards
    against swapped (dy, dx), key - query, or |dq - dk| (direction lost): a swap or negation
    would put every shipped checkpoint's learned bias on the wrong offset."""
    want2 = [[4, 3, 1, 0], [5, 4, 2, 1], [7, 6, 4, 3], [8, 7, 5, 4]]  # Swin, ws = 2
    np.testing.assert_array_equal(relative_position_index(2), want2)
    np.testing.assert_array_equal(relative_position_index(3), _swin_rel_index(3))


def test_window_attention_matches_numpy():
    """WindowAttention with a shift mask and padded keys equals numpy multi-head attention with
    logits q.k / sqrt(d_head) + Swin's relative bias. Guards against 1/sqrt(C) scaling and a
    mis-indexed bias table."""
    mod = WindowAttention(8, 2, 3)
    x = jax.random.normal(jax.random.key(0), (1, 4, 9, 8))
    region, key_ok = window_masks(6, 5, 3, 1)
    p, pp = _perturbed_f64(mod.init(jax.random.key(1), x, region, key_ok), 2)
    out = np.asarray(mod.apply(p, x, region, key_ok))[0]
    allowed = (region[:, :, None] == region[:, None, :]) & key_ok[:, None, :]
    ref = _window_attention(np.asarray(x, np.float64)[0], pp, 2, 3, allowed)
    np.testing.assert_allclose(out, ref, rtol=1e-4, atol=1e-4)


def test_shifted_swin_block_matches_numpy():
    """A shifted SwinBlock equals Swin's recipe in numpy: roll by -s, attend within the rolled
    map's 3 x 3 regions, roll back, residual, then a GELU MLP with residual. Guards against a
    ReLU MLP (the plain and chunked paths share it, so comparing them cannot see it), the
    attention scale and the bias index."""
    r, ws, s = 6, 3, 1
    blk = SwinBlock(8, 2, ws, s, r)
    x = np.asarray(jax.random.normal(jax.random.key(3), (r, r, 8)), np.float64)
    x32 = jnp.asarray(x[None], jnp.float32)
    p, pp = _perturbed_f64(blk.init(jax.random.key(4), x32), 5)
    out = np.asarray(blk.apply(p, x32))[0]
    lab = np.zeros((r, r), int)  # Swin's mask: label the regions of the rolled map
    cuts = [slice(0, r - ws), slice(r - ws, r - s), slice(r - s, r)]
    for a, rows in enumerate(cuts):
        for c, cols in enumerate(cuts):
            lab[rows, cols] = 3 * a + c
    lw = _windows(lab[..., None], ws)[..., 0]
    y = _windows(np.roll(_ln(x, pp["norm1"]), (-s, -s), (0, 1)), ws)
    y = _window_attention(y, pp["attn"], 2, ws, lw[:, :, None] == lw[:, None, :])
    x1 = x + np.roll(_unwindows(y, ws, r), (s, s), (0, 1))
    ref = x1 + _dense(gelu(_dense(_ln(x1, pp["norm2"]), pp["fc1"])), pp["fc2"])
    np.testing.assert_allclose(out, ref, rtol=1e-4, atol=1e-4)


def test_backbone_outputs_are_zero_on_padding():
    """SwinBackbone zeroes padded cells after each stage (its docstring). 10 valid cells of 24
    give stage maps with 10, 5, 3, 2 valid of 24, 12, 6, 3; without the zeroing the padding holds
    MLP outputs and a patch merge pairs the last valid cell of an odd map with padding, so
    padding-derived values reach valid cells (as in the small preset, 100 of 112). A mutation
    audit: valid sizes rounded down (the last row of data dropped) and only the last stage
    returned (every skip of the upsampler gone) passed."""
    cfg = Config.tiny().backbone
    x = jax.random.normal(jax.random.key(6), (1, 10, 10, 16))
    mod = SwinBackbone(cfg)
    params = jax.jit(mod.init, compiler_options=FAST)(jax.random.key(7), x)
    outs = jax.jit(mod.apply, compiler_options=FAST)(params, x)
    geometry = stage_geometry(10, cfg)
    # A cell is valid when it holds any valid cell of the stage before: ceil, not floor.
    strides = np.cumprod(cfg.strides)
    assert [v for _, v, _ in geometry] == [-(-10 // int(s)) for s in strides] == [10, 5, 3, 2]
    # The stages out_indices names and the last (the upsampler's skips read them).
    assert sorted(outs) == sorted(set(cfg.out_indices) | {len(cfg.strides) - 1})
    for k, (_, valid, _) in enumerate(geometry):
        if k in outs:
            o = np.asarray(outs[k])
            assert np.all(o[:, valid:] == 0) and np.all(o[:, :, valid:] == 0), k
            # The last valid row and column hold data (from the grid's last cells).
            assert np.abs(o[:, valid - 1]).sum() > 0 and np.abs(o[:, :, valid - 1]).sum() > 0, k
