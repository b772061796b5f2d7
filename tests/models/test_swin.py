"""Swin backbone pieces against numpy re-derivations, and its attention masks inspected."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from indoorbev_jax.config import Config
from indoorbev_jax.models.head import depth_to_space
from indoorbev_jax.models.swin import (
    PatchMerging,
    SwinBackbone,
    stage_geometry,
    window_partition,
    window_reverse,
)

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


def _layer_norm(x, scale, bias, eps=1e-6):
    mu = x.mean(-1, keepdims=True)
    var = ((x - mu) ** 2).mean(-1, keepdims=True)
    return (x - mu) / np.sqrt(var + eps) * scale + bias


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
    ref = _layer_norm(cat, pp["norm"]["scale"], pp["norm"]["bias"]) @ pp["reduction"]["kernel"]
    assert "bias" not in pp["reduction"]
    np.testing.assert_allclose(out, ref, rtol=1e-5, atol=1e-5)


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
