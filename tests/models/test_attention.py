"""The head's attention core: the hand-written backward equals autodiff, and the keys-major
projection is nn.Dense plus a transpose (same parameters, outputs and gradients)."""

import flax.linen as nn
import jax
import jax.numpy as jnp
import numpy as np
import pytest

from indoorbev_jax.models.head import KeysMajorDense, softmax_attention


def _plain_attention(q, k, v):
    w = jax.nn.softmax(jnp.einsum("bhqd,bhdk->bhqk", q, k), axis=-1)
    return jnp.einsum("bhqk,bhkd->bhqd", w, v)


@pytest.mark.parametrize("tq,tk", [(5, 37), (1, 300)])
def test_softmax_attention_values_and_gradients_equal_autodiff(tq, tk):
    ks = jax.random.split(jax.random.key(0), 4)
    # Large logits: the softmax is peaked, where a wrong backward shows most.
    q = 3.0 * jax.random.normal(ks[0], (2, 3, tq, 4))
    k = jax.random.normal(ks[1], (2, 3, 4, tk))
    v = jax.random.normal(ks[2], (2, 3, tk, 4))
    cotangent = jax.random.normal(ks[3], (2, 3, tq, 4))
    np.testing.assert_allclose(softmax_attention(q, k, v), _plain_attention(q, k, v), atol=1e-6)

    def grads(fn):
        return jax.grad(lambda *a: jnp.sum(fn(*a) * cotangent), argnums=(0, 1, 2))(q, k, v)

    for ours, ref in zip(grads(softmax_attention), grads(_plain_attention), strict=True):
        np.testing.assert_allclose(ours, ref, rtol=1e-5, atol=1e-5)


def test_keys_major_dense_is_dense_then_heads_major_transpose():
    x = jax.random.normal(jax.random.key(0), (2, 11, 6))
    ours, ref = KeysMajorDense(8, heads=2), nn.Dense(8)
    params = ref.init(jax.random.key(1), x)
    assert jax.tree.map(jnp.shape, ours.init(jax.random.key(1), x)) == jax.tree.map(
        jnp.shape, params
    )

    def ref_apply(p, x):  # [B, T, C] -> [B, h, d, T]
        return ref.apply(p, x).reshape(2, 11, 2, 4).transpose(0, 2, 3, 1)

    np.testing.assert_allclose(ours.apply(params, x), ref_apply(params, x), atol=1e-6)
    w = jax.random.normal(jax.random.key(2), (2, 2, 4, 11))
    g_ours = jax.grad(lambda p, x: jnp.sum(ours.apply(p, x) * w), argnums=(0, 1))(params, x)
    g_ref = jax.grad(lambda p, x: jnp.sum(ref_apply(p, x) * w), argnums=(0, 1))(params, x)
    for a, b in zip(jax.tree.leaves(g_ours), jax.tree.leaves(g_ref), strict=True):
        np.testing.assert_allclose(a, b, rtol=1e-5, atol=1e-5)
