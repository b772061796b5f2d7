"""Memory-lean paths (backbone.chunk_windows, head.attention_chunk) against the plain ones:
same parameters, same outputs, same gradients."""

import dataclasses

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from indoorbev_jax.config import BackboneConfig, Config, ConfigError, HeadConfig
from indoorbev_jax.models import IndoorBEV
from indoorbev_jax.models.head import Attention, chunk_memory
from indoorbev_jax.models.swin import SwinBlock

FAST = {"xla_backend_optimization_level": 0}


def _assert_trees_close(a, b, rtol=1e-5, atol=1e-6):
    assert jax.tree.structure(a) == jax.tree.structure(b)
    for x, y in zip(jax.tree.leaves(a), jax.tree.leaves(b), strict=True):
        assert x.shape == y.shape
        np.testing.assert_allclose(np.asarray(y), np.asarray(x), rtol=rtol, atol=atol)


def _value_and_grads(apply, params, *args):
    """Output of ``apply(params, *args)``, and the gradients of a non-linear scalar of it
    w.r.t. the parameters and every input."""

    def loss(p, *a):
        out = apply(p, *a)
        return jnp.sum(jnp.sin(out) * jnp.cos(0.3 * out)), out

    fn = jax.value_and_grad(loss, argnums=tuple(range(len(args) + 1)), has_aux=True)
    (_, out), grads = jax.jit(fn, compiler_options=FAST)(params, *args)
    return out, grads


# res, valid, shift, chunk: 16 windows of 3 x 3 on a 12 x 12 map. Shift + padded cells with
# 3 (not dividing 16: padding windows), padded cells only with 5, shift + padding with 4
# (divides), and no mask at all with 6.
@pytest.mark.parametrize(
    "res,valid,shift,chunk", [(12, 10, 1, 3), (12, 10, 0, 5), (12, 8, 1, 4), (12, 12, 0, 6)]
)
def test_chunked_swin_block_matches_plain_block(res, valid, shift, chunk):
    x = jax.random.normal(jax.random.key(0), (2, res, res, 8))
    plain = SwinBlock(8, 2, 3, shift, valid)
    lean = SwinBlock(8, 2, 3, shift, valid, chunk_windows=chunk)
    params = plain.init(jax.random.key(1), x)
    # Same parameter tree, so a checkpoint loads either way; init draws the same values.
    _assert_trees_close(params, lean.init(jax.random.key(1), x), rtol=0, atol=0)
    # Non-trivial LayerNorm affines and position biases so the test sees them.
    rng = np.random.default_rng(2)
    params = jax.tree.map(lambda a: a + 0.1 * rng.normal(size=a.shape).astype(np.float32), params)
    out0, g0 = _value_and_grads(plain.apply, params, x)
    out1, g1 = _value_and_grads(lean.apply, params, x)
    np.testing.assert_allclose(np.asarray(out1), np.asarray(out0), rtol=1e-5, atol=1e-5)
    _assert_trees_close(g0, g1, rtol=1e-4, atol=1e-5)
    assert max(float(jnp.abs(g).max()) for g in jax.tree.leaves(g0)) > 1e-2

    # The attention weights of every real window are the plain block's (masks line up).
    _, i0 = plain.apply(params, x, mutable=["intermediates"])
    _, i1 = lean.apply(params, x, mutable=["intermediates"])
    (w0,) = i0["intermediates"]["attn"]["attention_weights"]  # [B, nW, h, T, T]
    (w1,) = i1["intermediates"]["attn"]["attention_weights"]  # [nC, B, n, h, T, T]
    w1 = np.moveaxis(np.asarray(w1), 0, 1).reshape(2, -1, *w0.shape[2:])[:, : w0.shape[1]]
    np.testing.assert_allclose(w1, np.asarray(w0), rtol=1e-5, atol=1e-6)


@pytest.mark.parametrize("s,chunk", [(50, 7), (50, 25), (50, 49), (13, 13)])
def test_streamed_attention_matches_plain_attention(s, chunk):
    k1, k2, k3 = jax.random.split(jax.random.key(3), 3)
    q_in = jax.random.normal(k1, (2, 5, 16))
    # Large activations: logits of several hundred, where a softmax without a running max
    # would overflow float32.
    k_in = 40.0 * jax.random.normal(k2, (2, s, 16))
    v_in = jax.random.normal(k3, (2, s, 16))
    mod = Attention(num_heads=4)
    params = mod.init(jax.random.key(4), q_in, k_in, v_in)
    kc, key_ok = chunk_memory(k_in, chunk)
    vc, _ = chunk_memory(v_in, chunk)
    n = -(-s // chunk)
    assert kc.shape == (n, 2, chunk, 16) and key_ok.shape == (n, chunk)
    assert key_ok.sum() == s and key_ok[-1].any()
    np.testing.assert_array_equal(
        np.asarray(kc).transpose(1, 0, 2, 3).reshape(2, -1, 16)[:, :s], np.asarray(k_in)
    )

    out0, (gp0, gq0, gk0, gv0) = _value_and_grads(mod.apply, params, q_in, k_in, v_in)

    def streamed(p, q, k, v):
        return mod.apply(p, q, chunk_memory(k, chunk)[0], chunk_memory(v, chunk)[0], key_ok)

    out1, (gp1, gq1, gk1, gv1) = _value_and_grads(streamed, params, q_in, k_in, v_in)
    assert np.isfinite(np.asarray(out1)).all()
    np.testing.assert_allclose(np.asarray(out1), np.asarray(out0), rtol=1e-5, atol=1e-5)
    # Tolerances relative to the largest gradient: logits of several hundred carry float32
    # rounding of ~1e-5 relative, and the key bias's true gradient is exactly zero (softmax
    # ignores a per-query constant), so both paths leave only rounding there.
    scale = max(float(jnp.abs(g).max()) for g in jax.tree.leaves((gp0, gq0, gk0, gv0)))
    _assert_trees_close((gp0, gq0, gk0, gv0), (gp1, gq1, gk1, gv1), rtol=1e-4, atol=1e-5 * scale)
    assert float(jnp.abs(gv0).max()) > 1e-2 and float(jnp.abs(gk0).max()) > 1e-4


def test_lean_tiny_network_matches_plain_network():
    tiny = Config.tiny()
    # Tiny: stages of 256, 64, 16 and 4 windows; 7 chunks the first three (padding windows
    # in each). Memory of 40 x 40 = 1600 tokens in chunks of 333 (the last one padded).
    lean_cfg = dataclasses.replace(
        tiny,
        backbone=dataclasses.replace(tiny.backbone, chunk_windows=7, remat=True),
        head=dataclasses.replace(tiny.head, attention_chunk=333, remat=True),
    )
    rng = np.random.default_rng(5)
    lo, hi = np.array([-5, -5, -3, 0.0]), np.array([5, 5, 3, 1.0])
    pts = (lo + rng.uniform(size=(2, 256, 4)) * (hi - lo)).astype(np.float32)
    valid = rng.uniform(size=(2, 256)) > 0.05
    plain, lean = IndoorBEV(tiny), IndoorBEV(lean_cfg)
    init = jax.jit(plain.init, compiler_options=FAST)
    params = init(jax.random.key(0), pts, valid)
    lean_params = jax.jit(lean.init, compiler_options=FAST)(jax.random.key(0), pts, valid)
    _assert_trees_close(params, lean_params, rtol=0, atol=0)

    def loss(model, p):
        out = model.apply(p, pts, valid)
        return sum(jnp.mean(jnp.sin(x)) for x in jax.tree.leaves(out)), out

    both = jax.jit(
        lambda p: (jax.value_and_grad(lambda q: loss(plain, q), has_aux=True)(p),
                   jax.value_and_grad(lambda q: loss(lean, q), has_aux=True)(p)),
        compiler_options=FAST,
    )  # fmt: skip
    ((l0, out0), g0), ((l1, out1), g1) = both(params)
    np.testing.assert_allclose(l1, l0, rtol=1e-6)
    _assert_trees_close(out0, out1, rtol=1e-4, atol=1e-5)
    scale = max(float(jnp.abs(g).max()) for g in jax.tree.leaves(g0))
    assert scale > 0
    _assert_trees_close(g0, g1, rtol=1e-3, atol=1e-5 * scale)


@pytest.mark.parametrize(
    "build,field",
    [
        (lambda: BackboneConfig(chunk_windows=-1), "backbone.chunk_windows"),
        (lambda: HeadConfig(attention_chunk=-3), "head.attention_chunk"),
    ],
)
def test_negative_chunk_sizes_are_config_errors(build, field):
    with pytest.raises(ConfigError, match=field):
        build()


def test_presets_keep_the_plain_paths():
    for cfg in (Config.paper(), Config.small(), Config.tiny()):
        assert cfg.backbone.chunk_windows == 0 and cfg.head.attention_chunk == 0
