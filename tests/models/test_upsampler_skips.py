"""Upsampler skips: a backbone whose first stride is 2 gets the encoder map at full size."""

import dataclasses
import sys
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np

from indoorbev_jax.config import Config
from indoorbev_jax.models.head import AdaptiveUpsampler

sys.path.insert(0, str(Path(__file__).parents[1]))
from numpy_layers import dense, gelu  # noqa: E402


def _param_names(skips: bool, first_stride: int) -> set[str]:
    cfg = Config.tiny()
    bb = dataclasses.replace(cfg.backbone, strides=(first_stride, 2, 2, 2))
    res = 48 if first_stride == 2 else 24  # padded input side; last stage is 3 x 3
    stages = {k: jnp.zeros((1, res // (first_stride * 2**k), res // (first_stride * 2**k), c))
              for k, c in enumerate(bb.embed_dims)}  # fmt: skip
    bev = jnp.zeros((1, res, res, cfg.encoder.channels))
    steps = bb.total_stride.bit_length() - 1
    up = AdaptiveUpsampler(steps, cfg.head.hidden_dim, skips)
    params = jax.eval_shape(up.init, jax.random.key(0), stages, bev)["params"]
    return set(params)


def test_encoder_map_is_a_skip_only_when_no_stage_has_full_resolution():
    assert "lateral_bev" in _param_names(skips=True, first_stride=2)
    assert "lateral_bev" not in _param_names(skips=True, first_stride=1)
    assert "lateral0" in _param_names(skips=True, first_stride=1)
    assert not any(n.startswith("lateral") for n in _param_names(False, 2))


def test_bev_skip_changes_the_output_cellwise():
    # A bump in one encoder cell changes the upsampled map in that cell only (the lateral
    # Dense is per cell), so 1-cell detail reaches the masks.
    cfg = Config.tiny()
    stages = {0: jnp.zeros((1, 12, 12, 16)), 1: jnp.zeros((1, 6, 6, 32))}
    up = AdaptiveUpsampler(2, 8, skips=True)
    bev = jnp.zeros((1, 24, 24, cfg.encoder.channels))
    params = up.init(jax.random.key(0), stages, bev)
    base = up.apply(params, stages, bev)
    moved = up.apply(params, stages, bev.at[0, 5, 7].set(1.0))
    changed = np.argwhere(np.abs(np.asarray(moved - base)).sum(-1)[0] > 0)
    np.testing.assert_array_equal(changed, [[5, 7]])


def test_stage_skip_lands_on_its_own_cell():
    """A bump in one cell of the full-resolution stage changes the upsampled map in that cell
    only. Guards against the lateral skip added misaligned (flipped) onto the upsampled map."""
    stages = {0: jnp.zeros((1, 24, 24, 16)), 1: jnp.zeros((1, 12, 12, 32))}
    up = AdaptiveUpsampler(1, 8, skips=True)
    params = up.init(jax.random.key(0), stages)
    base = up.apply(params, stages)
    moved = up.apply(params, {0: stages[0].at[0, 5, 7].set(1.0), 1: stages[1]})
    changed = np.argwhere(np.abs(np.asarray(moved - base)).sum(-1)[0] > 0)
    np.testing.assert_array_equal(changed, [[5, 7]])


def test_a_step_is_dense_depth_to_space_gelu_plus_the_lateral_skip():
    """One step from DESIGN section 7 / the class docstring, against numpy: Dense(4 C'), 2x
    depth-to-space, GELU (flax's tanh form), then the same-resolution stage through its
    lateral Dense. A mutation audit: the step without its GELU passed."""
    x1 = np.asarray(jax.random.normal(jax.random.key(1), (2, 3, 3, 16)))
    x0 = np.asarray(jax.random.normal(jax.random.key(2), (2, 6, 6, 8)))
    up = AdaptiveUpsampler(1, 4, skips=True)
    params = up.init(jax.random.key(0), {0: x0, 1: x1})
    got = np.asarray(up.apply(params, {0: x0, 1: x1}), np.float64)
    p = jax.tree.map(lambda a: np.asarray(a, np.float64), params["params"])
    y = dense(x1.astype(np.float64), p["up0"])  # [2, 3, 3, 4 * 8]
    y = y.reshape(2, 3, 3, 2, 2, 8).transpose(0, 1, 3, 2, 4, 5).reshape(2, 6, 6, 8)
    want = gelu(y) + dense(x0.astype(np.float64), p["lateral0"])
    np.testing.assert_allclose(got, want, atol=2e-5)
