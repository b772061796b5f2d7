"""AF-PCCN scatter against a numpy per-cell max; invariance to point order and padding."""

import sys
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from indoorbev_jax.config import Config
from indoorbev_jax.models.encoder import AFPCCN

sys.path.insert(0, str(Path(__file__).parents[1]))
from numpy_layers import dense, layer_norm  # noqa: E402

FAST = {"xla_backend_optimization_level": 0}
GRID = Config.tiny().grid  # 40 x 40 cells of 0.25 m over [-5, 5]^2, z in [-3, 3]
ENC = AFPCCN(GRID, channels=8)
_apply = jax.jit(
    lambda p, pts, valid: ENC.apply(p, pts, valid, mutable=["intermediates"]),
    compiler_options=FAST,
)


def _points(key, b: int, n: int) -> tuple[np.ndarray, np.ndarray]:
    """Points over a slightly larger box than the workspace (some fall outside), clustered so
    cells hold several points, with NaN, Inf, boundary and invalid entries."""
    rng = np.random.default_rng(key)
    xy = rng.choice(np.linspace(-5.5, 5.5, 23), size=(b, n, 2)) + rng.uniform(-0.1, 0.1, (b, n, 2))
    z = rng.uniform(-3.5, 3.5, (b, n, 1))
    pts = np.concatenate([xy, z, rng.uniform(0, 1, (b, n, 1))], -1).astype(np.float32)
    pts[:, 0] = (5.0, 5.0, 0.0, 0.5)  # x = x_max, y = y_max: inside, the last cell (closed)
    pts[:, 1] = (-5.0, -5.0, 3.0, 0.5)  # corner cell, z = z_max: inside (closed)
    pts[:, 2] = (np.nan, 1.0, 0.0, 0.5)
    pts[:, 3] = (1.0, np.inf, 0.0, 0.5)
    valid = rng.uniform(size=(b, n)) > 0.1
    valid[:, :4] = True
    return pts, valid


def _numpy_cells(pts: np.ndarray, valid: np.ndarray):
    """(ok [B, N], cell [B, N]) re-derived from DESIGN section 2 in float64."""
    finite = np.isfinite(pts).all(-1)
    p = np.where(finite[..., None], pts, 0.0).astype(np.float64)
    x, y, z = p[..., 0], p[..., 1], p[..., 2]
    ok = valid & finite & (x >= -5) & (x <= 5) & (y >= -5) & (y <= 5) & (z >= -3) & (z <= 3)
    col = np.minimum(np.floor((x + 5) / 0.25).astype(int), 39)  # x = 5 is in column 39
    row = np.minimum(np.floor((y + 5) / 0.25).astype(int), 39)
    return ok, row * 40 + col


def test_scatter_equals_numpy_per_cell_max_then_layernorm():
    pts, valid = _points(0, 2, 600)
    params = jax.jit(ENC.init, compiler_options=FAST)(jax.random.key(0), pts, valid)
    out, inter = _apply(params, pts, valid)
    feats = np.asarray(inter["intermediates"]["point_features"][0])  # [B, N, C]
    bev_raw = np.asarray(inter["intermediates"]["bev_raw"][0])  # [B, H, W, C]
    p = jax.tree.map(np.asarray, params["params"])
    ok, cell = _numpy_cells(pts, valid)
    assert ok[:, :2].all() and not ok[:, [2, 3]].any() and (cell[:, 0] == 40 * 40 - 1).all()

    ref = np.full((2, 40 * 40, 8), -np.inf, np.float32)
    for b in range(2):
        np.maximum.at(ref[b], cell[b][ok[b]], feats[b][ok[b]])
    empty = np.isinf(ref[..., 0])
    assert 0 < empty.mean() < 1
    ref[empty] = p["empty"]
    ref = ref.reshape(2, 40, 40, 8)
    np.testing.assert_array_equal(bev_raw, ref)
    mu = ref.mean(-1, keepdims=True)
    var = ref.var(-1, keepdims=True)
    ln = (ref - mu) / np.sqrt(var + 1e-6) * p["norm"]["scale"] + p["norm"]["bias"]
    np.testing.assert_allclose(np.asarray(out), ln, rtol=1e-4, atol=1e-4)
    assert np.isfinite(np.asarray(out)).all()


def test_invariant_to_point_order_and_extra_invalid_points():
    pts, valid = _points(1, 2, 600)
    params = jax.jit(ENC.init, compiler_options=FAST)(jax.random.key(1), pts, valid)
    base, _ = _apply(params, pts, valid)
    rng = np.random.default_rng(2)
    perm = rng.permutation(600)
    shuffled, _ = _apply(params, pts[:, perm], valid[:, perm])
    # The cell-mean z is a float sum, so a different order may change the last bit.
    np.testing.assert_allclose(np.asarray(shuffled), np.asarray(base), rtol=1e-5, atol=1e-5)

    # 600 more slots of junk, all of it unusable: flagged invalid, NaN, or outside the box.
    junk = rng.uniform(-50, 50, (2, 600, 4)).astype(np.float32)
    junk[:, ::3, 0] = np.nan
    junk_valid = rng.uniform(size=(2, 600)) > 0.5
    junk[junk_valid, 2] = 10.0  # "valid" junk sits above z_max
    # Valid points in the workspace with an absurd intensity (1e25 NaN'd the whole map).
    loud = np.array(pts[:, :8])
    loud[..., 3] = [1e25, -1e30, 3e38, 1e7, 1e25, 1e20, -1e25, 2e6]
    padded_pts = np.concatenate([pts, junk, loud], 1)
    padded_valid = np.concatenate([valid, junk_valid, np.ones((2, 8), bool)], 1)
    mix = rng.permutation(1208)
    padded, _ = _apply(params, padded_pts[:, mix], padded_valid[:, mix])
    np.testing.assert_allclose(np.asarray(padded), np.asarray(base), rtol=1e-5, atol=1e-5)


def test_gradients_reach_the_branches_and_are_finite_despite_nan_points():
    pts, valid = _points(3, 1, 300)
    params = jax.jit(ENC.init, compiler_options=FAST)(jax.random.key(3), pts, valid)
    grads = jax.jit(
        jax.grad(lambda p: jnp.sum(ENC.apply(p, pts, valid) ** 3)), compiler_options=FAST
    )(params)
    g = grads["params"]
    for leaf in jax.tree.leaves(g):
        assert np.isfinite(np.asarray(leaf)).all()
    for kernel in (g["branch_xz"]["fc1"]["kernel"], g["branch_yz"]["fc1"]["kernel"],
                   g["fuse"]["kernel"], g["empty"]):  # fmt: skip
        assert np.abs(np.asarray(kernel)).sum() > 0


def test_a_cloud_of_no_points_is_a_cloud_of_invalid_points():
    """N = 0 (a reshape once divided by it) gives the all-empty grid of a frame whose points
    are all invalid."""
    pts, valid = _points(1, 2, 16)
    params = jax.jit(ENC.init, compiler_options=FAST)(jax.random.key(0), pts, valid)
    none = ENC.apply(params, np.zeros((2, 0, 4), np.float32), np.zeros((2, 0), bool))
    invalid, _ = _apply(params, pts, np.zeros_like(valid))
    np.testing.assert_allclose(np.asarray(none), np.asarray(invalid), rtol=1e-6, atol=1e-6)


def test_integer_valid_masks_are_read_as_bool_and_float_ones_are_named():
    """0/1 integer masks equal the bool mask (a 2 counts as valid: it was bitwise-anded to
    invalid); a float mask is refused naming ``valid`` (a bare TypeError from ``&``)."""
    pts, valid = _points(2, 2, 64)
    params = jax.jit(ENC.init, compiler_options=FAST)(jax.random.key(0), pts, valid)
    want = np.asarray(_apply(params, pts, valid)[0])
    for ints in (valid.astype(np.int32), 2 * valid.astype(np.uint8)):
        np.testing.assert_array_equal(np.asarray(_apply(params, pts, ints)[0]), want)
    with pytest.raises(ValueError, match="valid must be bool"):
        ENC.apply(params, pts, valid.astype(np.float32))


_ln, _dense = layer_norm, dense


def test_point_features_match_design_section_5():
    """Per-point features equal DESIGN section 5 in numpy: X-Z branch on (x, z, dx, dz, range, i),
    Y-Z branch on (y, z, dy, dz, range, i), dx, dy the offsets from the cell centre in cells, dz
    from the cell's mean z, range = hypot(x, y); each branch Dense-LN-ReLU-Dense, then fused.
    Guards against offsets from the wrong centre, x fed to the Y-Z branch, dz against the z sum
    or a halved single-point mean, range from z, and ReLU before the LayerNorm (the per-cell
    max test only sees features through the scatter)."""
    rng = np.random.default_rng(0)
    n = 300
    xy = rng.choice(np.linspace(-4.6, 4.6, 9), size=(1, n, 2)) + rng.uniform(-0.1, 0.1, (1, n, 2))
    z = rng.uniform(-2.5, 2.5, (1, n, 1))
    pts = np.concatenate([xy, z, rng.uniform(0, 1, (1, n, 1))], -1).astype(np.float32)
    pts[0, -1] = (3.3, -1.7, 0.4, 0.2)  # alone in its cell, off the diagonal
    valid = np.ones((1, n), bool)
    params = jax.jit(ENC.init, compiler_options=FAST)(jax.random.key(0), pts, valid)
    noise = np.random.default_rng(1)  # move off init: zero biases would hide swapped inputs
    params = jax.tree.map(lambda a: a + 0.3 * noise.normal(size=a.shape).astype(np.float32), params)
    _, inter = _apply(params, pts, valid)
    feats = np.asarray(inter["intermediates"]["point_features"][0])[0]
    pp = jax.tree.map(lambda a: np.asarray(a, np.float64), params["params"])

    x, y, z, i = (pts[0, :, k].astype(np.float64) for k in range(4))
    v = 0.25
    col, row = np.floor((x + 5) / v).astype(int), np.floor((y + 5) / v).astype(int)
    cell = row * 40 + col
    z_mean = np.array([z[cell == c].mean() for c in cell])
    dx, dy = (x - (-5 + (col + 0.5) * v)) / v, (y - (-5 + (row + 0.5) * v)) / v
    dz, rng_ = z - z_mean, np.hypot(x, y)

    def branch(f, q):
        return _dense(np.maximum(_ln(_dense(f, q["fc1"]), q["norm"]), 0), q["fc2"])

    f_xz = branch(np.stack([x, z, dx, dz, rng_, i], -1), pp["branch_xz"])
    f_yz = branch(np.stack([y, z, dy, dz, rng_, i], -1), pp["branch_yz"])
    ref = _dense(np.concatenate([f_xz, f_yz], -1), pp["fuse"])
    np.testing.assert_allclose(feats, ref, rtol=1e-4, atol=1e-4)
