"""losses.set_loss / cost_matrix against a numpy + scipy re-derivation, and invariants."""

import dataclasses
import math

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from scipy.optimize import linear_sum_assignment

from indoorbev_jax.config import LossConfig
from indoorbev_jax.losses import TERMS, _loss_mask_points, cost_matrix, set_loss
from indoorbev_jax.types import Predictions, Targets

L, B, Q, K, M, H, W = 2, 4, 6, 10, 4, 16, 16
CFG = LossConfig()
SAMPLED = dataclasses.replace(CFG, num_mask_points=64)
WEIGHTS = CFG.weights()

# One compiled loss-and-gradient per config, shared by the tests (compiles dominate runtime).
_loss_and_grad = jax.jit(
    jax.value_and_grad(lambda p, t, w, c, k: set_loss(p, t, w, c, key=k), has_aux=True),
    static_argnums=3,
)
_cost = jax.jit(cost_matrix, static_argnames="config")


def _loss(preds, targets, weights=WEIGHTS, config=CFG, key=None):
    """(total, parts, gradients w.r.t. the predictions)."""
    (total, parts), grads = _loss_and_grad(preds, targets, weights, config, key)
    return total, parts, grads


def _random_batch(seed, valid=None):
    rng = np.random.default_rng(seed)
    preds = Predictions(
        logits=rng.normal(size=(L, B, Q, K)).astype(np.float32),
        dims=rng.random((L, B, Q, 3)).astype(np.float32),
        pos=rng.normal(size=(L, B, Q, 3)).astype(np.float32),
        yaw=rng.uniform(-4, 4, (L, B, Q, 1)).astype(np.float32),
        masks=(2 * rng.normal(size=(L, B, Q, H, W))).astype(np.float32),
    )
    if valid is None:
        valid = rng.random((B, M)) < 0.6
        valid[0] = False  # one frame without targets
        valid[1] = True  # one full frame
    targets = Targets(
        classes=np.where(valid, rng.integers(0, K - 1, (B, M)), K - 1).astype(np.int32),
        dims=rng.random((B, M, 3)).astype(np.float32),
        pos=rng.normal(size=(B, M, 3)).astype(np.float32),
        yaw=rng.uniform(-math.pi, math.pi, (B, M)).astype(np.float32),
        valid=valid,
        masks=rng.random((B, M, H, W)) < 0.3,
        instance_ids=np.zeros((B, H, W), np.int32),
    )
    return preds, targets


# --- numpy reference -------------------------------------------------------------------


def _wrap(a):
    return (a + np.pi) % (2 * np.pi) - np.pi


def _sigmoid(x):
    return 1 / (1 + np.exp(-x))


def _focal(x, t, alpha, gamma):
    """Elementwise sigmoid focal loss, straight from its definition."""
    p = _sigmoid(x)
    ce = -(t * np.log(p) + (1 - t) * np.log(1 - p))
    p_t = p * t + (1 - p) * (1 - t)
    return (alpha * t + (1 - alpha) * (1 - t)) * (1 - p_t) ** gamma * ce


def _dice(x, t):
    p = _sigmoid(x)
    return 1 - (2 * (p * t).sum() + 1) / (p.sum() + t.sum() + 1)


def _ref_cost(preds, targets, lyr, b, cfg):
    logits = preds.logits[lyr, b].astype(np.float64)
    prob = np.exp(logits) / np.exp(logits).sum(-1, keepdims=True)
    cost = np.zeros((Q, M))
    for q in range(Q):
        x = preds.masks[lyr, b, q].astype(np.float64).ravel()
        for j in range(M):
            t = targets.masks[b, j].ravel().astype(np.float64)
            reg = (
                np.abs(preds.dims[lyr, b, q] - targets.dims[b, j]).sum()
                + np.abs(preds.pos[lyr, b, q] - targets.pos[b, j]).sum()
                + abs(_wrap(preds.yaw[lyr, b, q, 0] - targets.yaw[b, j]))
            )
            cost[q, j] = (
                cfg.cost_cls * (1 - prob[q, targets.classes[b, j]])
                + cfg.cost_dice * _dice(x, t)
                + cfg.cost_focal * _focal(x, t, cfg.focal_alpha, cfg.focal_gamma).mean()
                + cfg.cost_reg * reg
            )
    return cost


def _ref_loss(preds, targets, weights, cfg):
    """Per layer, per frame: scipy matching, then the loss terms summed and normalised."""
    n = max(targets.valid.sum(), 1)
    per_layer = {t: np.zeros(L) for t in TERMS}
    for lyr in range(L):
        ce_sum = w_sum = 0.0
        for b in range(B):
            valid = np.flatnonzero(targets.valid[b])
            rows, cols = linear_sum_assignment(_ref_cost(preds, targets, lyr, b, cfg)[:, valid])
            tgt_cls = np.full(Q, K - 1)
            tgt_cls[rows] = targets.classes[b, valid[cols]]
            logits = preds.logits[lyr, b].astype(np.float64)
            logp = logits - np.log(np.exp(logits).sum(-1, keepdims=True))
            w = np.where(tgt_cls == K - 1, cfg.background_weight, 1.0)
            ce_sum += (w * -logp[np.arange(Q), tgt_cls]).sum()
            w_sum += w.sum()
            for q, j in zip(rows, valid[cols], strict=True):
                x = preds.masks[lyr, b, q].astype(np.float64).ravel()
                t = targets.masks[b, j].ravel().astype(np.float64)
                per_layer["dice"][lyr] += _dice(x, t) / n
                focal = _focal(x, t, cfg.focal_alpha, cfg.focal_gamma).mean()
                per_layer["focal"][lyr] += focal / n
                per_layer["dims"][lyr] += (
                    np.abs(preds.dims[lyr, b, q] - targets.dims[b, j]).sum() / n
                )
                per_layer["pos"][lyr] += np.abs(preds.pos[lyr, b, q] - targets.pos[b, j]).sum() / n
                per_layer["yaw"][lyr] += abs(_wrap(preds.yaw[lyr, b, q, 0] - targets.yaw[b, j])) / n
        per_layer["cls"][lyr] = ce_sum / w_sum
    total = sum(weights[t] * per_layer[t].sum() for t in TERMS)
    return total, per_layer


@pytest.fixture(scope="module")
def batch():
    return _random_batch(0)


# --- tests -----------------------------------------------------------------------------


def test_cost_matrix_matches_reference(batch):
    preds, targets = batch
    cost = np.asarray(_cost(preds, targets, config=CFG))
    assert cost.shape == (L, B, Q, M)
    for lyr in range(L):
        for b in range(B):
            ref = _ref_cost(preds, targets, lyr, b, CFG)
            np.testing.assert_allclose(cost[lyr, b], ref, rtol=1e-4, atol=1e-4)


def test_loss_matches_per_sample_reference(batch):
    """The vmapped (layers x frames) loss equals a per-layer, per-frame numpy/scipy loop."""
    preds, targets = batch
    total, parts, _ = _loss(preds, targets)
    ref_total, ref_layers = _ref_loss(preds, targets, WEIGHTS, CFG)
    np.testing.assert_allclose(total, ref_total, rtol=1e-4)
    for t in TERMS:
        np.testing.assert_allclose(parts[t], ref_layers[t].sum(), rtol=1e-4, atol=1e-6)
        np.testing.assert_allclose(parts[t + "_final"], ref_layers[t][-1], rtol=1e-4, atol=1e-6)
    assert parts["num_targets"] == targets.valid.sum()
    weighted = sum(WEIGHTS[t] * parts[t] for t in TERMS)
    np.testing.assert_allclose(total, weighted, rtol=1e-6)


def test_aux_loss_off_scores_the_last_layer_and_a_config_given_as_weights_is_the_config(batch):
    """set_loss(p, t, cfg) with cfg.aux_loss = False scores the last decoder layer only: its
    terms are the aux run's `_final` parts, which test_loss_matches_per_sample_reference checks
    against the numpy/scipy loop. Two rules meet here: a LossConfig given as `weights` stands
    for config too (the default config, aux_loss on, summed both layers instead), and
    aux_loss=False keeps the last layer (the first one was scored instead)."""
    preds, targets = batch
    _, aux_parts, _ = _loss(preds, targets)
    last_only = dataclasses.replace(CFG, aux_loss=False)
    total, parts = jax.jit(lambda p, t: set_loss(p, t, last_only))(preds, targets)
    for t in TERMS:
        np.testing.assert_allclose(parts[t], aux_parts[t + "_final"], rtol=1e-5, atol=1e-7)
    expected = sum(WEIGHTS[t] * aux_parts[t + "_final"] for t in TERMS)
    np.testing.assert_allclose(total, expected, rtol=1e-5)
    # The config's point sampling, too: it needs a key (raised before any work).
    with pytest.raises(ValueError, match="num_mask_points = 64 samples mask cells"):
        set_loss(preds, targets, SAMPLED)


def test_predictions_read_by_name_and_given_as_a_dict(batch):
    """The containers read like the PyTorch code's dicts, and set_loss takes a dict of the
    outputs and a LossConfig for its weights, with the same result."""
    preds, targets = batch
    assert preds["logits"] is preds.logits and preds.keys() == tuple(dict(preds))
    with pytest.raises(KeyError, match="no field 'logit'"):
        preds["logit"]
    total, parts = set_loss(preds, targets, WEIGHTS)
    total_dict, parts_dict = set_loss(dict(preds), targets, CFG)
    np.testing.assert_allclose(total_dict, total, rtol=1e-6)
    assert parts_dict.keys() == parts.keys()
    with pytest.raises(TypeError, match=r"missing \['masks'\]"):
        set_loss({k: preds[k] for k in preds.keys() if k != "masks"}, targets, WEIGHTS)


def test_targets_as_a_dict_and_default_weights(batch):
    """Targets given as a dict (instance_ids, unread by the loss, may be left out) and
    weights=None (the config's) give the Targets / explicit-weights result."""
    preds, targets = batch
    total, _ = set_loss(preds, targets, WEIGHTS)
    as_dict = {k: targets[k] for k in targets.keys() if k != "instance_ids"}
    np.testing.assert_allclose(set_loss(preds, as_dict, None)[0], total, rtol=1e-6)
    # None is the default, as the docstring says (the argument was required).
    np.testing.assert_allclose(set_loss(preds, as_dict)[0], total, rtol=1e-6)
    np.testing.assert_allclose(cost_matrix(preds, as_dict), cost_matrix(preds, targets))
    with pytest.raises(TypeError, match=r"targets: missing \['valid'\]"):
        set_loss(preds, {k: v for k, v in as_dict.items() if k != "valid"}, WEIGHTS)
    # 0/255 masks, as a PNG gives them, are the bool ones (255 was the target: dice < 0).
    png = dict(as_dict, masks=np.asarray(as_dict["masks"]).astype(np.uint8) * 255)
    np.testing.assert_allclose(set_loss(preds, png, WEIGHTS)[0], total, rtol=1e-6)
    np.testing.assert_allclose(cost_matrix(preds, png), cost_matrix(preds, targets), rtol=1e-6)


def test_no_target_slots_at_all():
    """M = 0 (a batch padded to no slots): every query is background, so with zero logits
    each layer's cross-entropy is ln K; gradients are finite. (A reshape once divided by 0.)"""
    preds, targets = _random_batch(6)
    preds = dataclasses.replace(preds, logits=np.zeros_like(preds.logits))
    empty = jax.tree.map(lambda x: x[:, :0], targets)
    empty = dataclasses.replace(empty, instance_ids=targets.instance_ids)
    total, parts, grads = _loss(preds, empty)
    np.testing.assert_allclose(total, WEIGHTS["cls"] * L * math.log(K), rtol=1e-6)
    assert parts["num_targets"] == 1.0
    assert all(np.isfinite(np.asarray(g)).all() for g in jax.tree.leaves(grads))


def test_infinite_mask_logits_give_finite_costs_and_gradients(batch):
    """A mask logit of +-inf (an overflowed bfloat16, say) costs what the clipped logit
    costs: +inf used to give inf - inf in the focal cost (NaN, so the query was never
    matched) and a NaN gradient."""
    preds, targets = batch
    masks = preds.masks.copy()
    masks[:, :, 0, 0, :3] = np.inf
    masks[:, :, 1, 1, :3] = -np.inf
    clipped = np.clip(masks, -1e4, 1e4)
    inf_preds = dataclasses.replace(preds, masks=masks)
    clip_preds = dataclasses.replace(preds, masks=clipped)
    cost = np.asarray(_cost(inf_preds, targets, config=CFG))
    assert np.isfinite(cost).all()
    np.testing.assert_allclose(cost, _cost(clip_preds, targets, config=CFG), rtol=1e-6)
    total, _, grads = _loss(inf_preds, targets)
    np.testing.assert_allclose(total, _loss(clip_preds, targets)[0], rtol=1e-6)
    assert all(np.isfinite(np.asarray(g)).all() for g in jax.tree.leaves(grads))


def test_fractional_focal_gamma_matches_reference_with_finite_gradients(batch):
    """A non-integer gamma is the focal loss of its definition, and its gradient stays
    finite where the sigmoid underflows (|logit| >= 88 gave NaN: every step skipped)."""
    preds, targets = batch
    config = dataclasses.replace(CFG, focal_gamma=0.5)
    total, _, _ = _loss(preds, targets, config=config)
    np.testing.assert_allclose(total, _ref_loss(preds, targets, WEIGHTS, config)[0], rtol=1e-4)
    masks = preds.masks.copy()
    masks[:, :, :, 0, :4] = [90.0, -90.0, 200.0, -200.0]
    _, _, grads = _loss(dataclasses.replace(preds, masks=masks), targets, config=config)
    assert all(np.isfinite(np.asarray(g)).all() for g in jax.tree.leaves(grads))


def test_numpy_targets_closed_over_by_jit_with_sampled_points(batch):
    """Targets held as numpy arrays by a jitted function (not passed in) are indexed at
    traced sampled cells: a TracerArrayConversionError before."""
    preds, targets = batch
    key = jax.random.key(3)
    closed = jax.jit(lambda p, k: set_loss(p, targets, WEIGHTS, SAMPLED, key=k)[0])
    np.testing.assert_allclose(
        closed(preds, key), _loss(preds, targets, config=SAMPLED, key=key)[0], rtol=1e-6
    )
    cost = jax.jit(lambda p, k: cost_matrix(p, targets, SAMPLED, k))(preds, key)
    np.testing.assert_allclose(cost, _cost(preds, targets, config=SAMPLED, key=key), rtol=1e-6)


def test_invariant_to_permuting_queries_and_targets(batch):
    preds, targets = batch
    rng = np.random.default_rng(3)
    perm_q, perm_m = rng.permutation(Q), rng.permutation(M)
    permuted_preds = jax.tree.map(lambda x: x[:, :, perm_q], preds)
    permuted_targets = dataclasses.replace(
        targets, **{f: getattr(targets, f)[:, perm_m] for f in ("classes", "dims", "pos", "yaw")}
    )
    permuted_targets = dataclasses.replace(
        permuted_targets, valid=targets.valid[:, perm_m], masks=targets.masks[:, perm_m]
    )
    total, parts, grads = _loss(preds, targets)
    grads_by_perm = {}
    for name_p, p, t in (("q", permuted_preds, targets), ("m", preds, permuted_targets)):
        total_p, parts_p, grads_by_perm[name_p] = _loss(p, t)
        np.testing.assert_allclose(total_p, total, rtol=1e-5)
        for name in parts:
            np.testing.assert_allclose(parts_p[name], parts[name], rtol=1e-5, atol=1e-7)
    # Gradients follow the queries they belong to, and ignore the order of the targets.
    unpermuted = jax.tree.map(lambda g: np.asarray(g)[:, :, np.argsort(perm_q)], grads_by_perm["q"])
    for grads_p in (unpermuted, grads_by_perm["m"]):
        for g_p, g in zip(jax.tree.leaves(grads_p), jax.tree.leaves(grads), strict=True):
            np.testing.assert_allclose(g_p, g, rtol=1e-4, atol=1e-7)
    # Sampled mask points are drawn per target slot, so the queries' order changes nothing
    # there either (a query read its own index's target mask, not its match's: not seen).
    key = jax.random.key(5)
    total, parts, _ = _loss(preds, targets, config=SAMPLED, key=key)
    total_p, parts_p, _ = _loss(permuted_preds, targets, config=SAMPLED, key=key)
    np.testing.assert_allclose(total_p, total, rtol=1e-5)
    for name in ("dice", "focal"):
        np.testing.assert_allclose(parts_p[name], parts[name], rtol=1e-5, atol=1e-7)


def test_vmapped_sweep_equals_loop():
    """K models with traced loss weights under jax.vmap equal K separate calls."""
    sweeps = [_random_batch(10 + i) for i in range(3)]
    preds = jax.tree.map(lambda *x: np.stack(x), *[s[0] for s in sweeps])
    targets = jax.tree.map(lambda *x: np.stack(x), *[s[1] for s in sweeps])
    weights = {t: jnp.array([1.0, 2.0, 0.5]) * v for t, v in WEIGHTS.items()}
    weights["background"] = jnp.array([0.1, 0.2, 0.05])
    totals, parts = jax.jit(jax.vmap(lambda p, t, w: set_loss(p, t, w, CFG)))(
        preds, targets, weights
    )
    for i, (p, t) in enumerate(sweeps):
        w = {name: float(v[i]) for name, v in weights.items()}
        cfg = dataclasses.replace(CFG, background_weight=w.pop("background"))
        ref_total, ref_layers = _ref_loss(p, t, w, cfg)
        np.testing.assert_allclose(totals[i], ref_total, rtol=1e-4)
        np.testing.assert_allclose(parts["cls"][i], ref_layers["cls"].sum(), rtol=1e-4)


def test_sharded_shares_sum_to_whole_batch(batch):
    """With axis_name, the shards' losses add up to the unsharded loss (psum-ed counts)."""
    preds, targets = batch
    shards = 2

    def split(x, axis):  # [.., B, ..] -> [S, .., B/S, ..]
        x = np.moveaxis(x, axis, 0).reshape(shards, B // shards, *np.delete(x.shape, axis))
        return np.moveaxis(x, 1, axis + 1)

    sharded_preds = jax.tree.map(lambda x: split(x, 1), preds)
    sharded_targets = jax.tree.map(lambda x: split(x, 0), targets)
    per_shard = jax.vmap(
        lambda p, t: set_loss(p, t, WEIGHTS, CFG, axis_name="data"), axis_name="data"
    )
    totals, parts = jax.jit(per_shard)(sharded_preds, sharded_targets)
    total, whole_parts, _ = _loss(preds, targets)
    np.testing.assert_allclose(totals.sum(), total, rtol=1e-5)
    for t in TERMS:
        np.testing.assert_allclose(parts[t].sum(), whole_parts[t], rtol=1e-5, atol=1e-7)
    np.testing.assert_array_equal(parts["num_targets"], whole_parts["num_targets"])


SHARD_MAP = """
import os, sys
flags = os.environ.get("XLA_FLAGS", "")
os.environ["XLA_FLAGS"] = flags + " --xla_force_host_platform_device_count=2"
sys.path.insert(0, sys.argv[1])
import jax, numpy as np
from jax.sharding import Mesh, PartitionSpec as P
from test_losses import CFG, WEIGHTS, _random_batch
from indoorbev_jax.losses import set_loss
from indoorbev_jax.matching import match

preds, targets = _random_batch(0)
mesh = Mesh(np.array(jax.devices()), ("data",))
pspec = jax.tree.map(lambda x: P(None, "data"), preds)
tspec = jax.tree.map(lambda x: P("data"), targets)

def loss(p, t, **kw):
    return set_loss(p, t, WEIGHTS, CFG, **kw)

def local(p, t):
    (share, _), grads = jax.value_and_grad(loss, has_aux=True)(p, t, axis_name="data")
    return jax.lax.psum(share, "data"), grads

# shard_map's default check_vma: the solver's loops must not turn shard-dependent.
sharded = jax.jit(jax.shard_map(local, mesh=mesh, in_specs=(pspec, tspec), out_specs=(P(), pspec)))
total, grads = sharded(preds, targets)
(whole, _), whole_grads = jax.value_and_grad(loss, has_aux=True)(preds, targets)
np.testing.assert_allclose(total, whole, rtol=1e-5)
for a, b in zip(jax.tree.leaves(grads), jax.tree.leaves(whole_grads), strict=True):
    np.testing.assert_allclose(a, b, rtol=1e-4, atol=1e-7)
cost = np.random.default_rng(1).normal(size=targets.valid.shape[:1] + (6, 4)).astype(np.float32)
per_shard = jax.shard_map(
    lambda c, v: match(c, v)[0], mesh=mesh, in_specs=(P("data"), P("data")), out_specs=P("data")
)
whole_idx = match(cost, targets.valid)[0]
np.testing.assert_array_equal(jax.jit(per_shard)(cost, targets.valid), whole_idx)
print("SHARD_MAP_OK", float(total), float(whole))
"""


def test_shard_map_loss_and_gradients_equal_the_whole_batch(tmp_path):
    """Inside jax.shard_map (2 host devices, default check_vma) set_loss with axis_name:
    the psum of the shards' losses and each shard's gradients equal the unsharded ones, and
    match gives the unsharded indices (optax's loops once refused shard-dependent carries)."""
    import os
    import subprocess
    import sys
    from pathlib import Path

    env = dict(os.environ, JAX_PLATFORMS="cpu")
    env.setdefault("JAX_COMPILATION_CACHE_DIR", str(tmp_path / "cache"))
    out = subprocess.run(
        [sys.executable, "-c", SHARD_MAP, str(Path(__file__).parent)],
        capture_output=True, text=True, env=env, timeout=600,
    )  # fmt: skip
    assert "SHARD_MAP_OK" in out.stdout, out.stderr[-3000:]


def _perfect(targets, big=20.0):
    """Predictions equal to the targets on the first M queries, background on the rest."""
    rng = np.random.default_rng(4)
    valid = targets.valid
    onehot = np.eye(K, dtype=np.float32)[np.where(valid, targets.classes, K - 1)]  # [B, M, K]
    logits = np.full((B, Q, K), -big, np.float32)
    logits[..., K - 1] = big
    logits[:, :M] = big * (2 * onehot - 1)
    masks = np.full((B, Q, H, W), -big, np.float32)
    masks[:, :M] = np.where(targets.masks & valid[..., None, None], big, -big)
    dims = rng.random((B, Q, 3)).astype(np.float32)
    pos = rng.normal(size=(B, Q, 3)).astype(np.float32)
    yaw = rng.normal(size=(B, Q, 1)).astype(np.float32)
    dims[:, :M], pos[:, :M] = targets.dims, targets.pos
    yaw[:, :M, 0] = targets.yaw + 2 * np.pi * rng.integers(-1, 2, (B, M))  # same heading
    fields = {"logits": logits, "dims": dims, "pos": pos, "yaw": yaw, "masks": masks}
    return Predictions(**{name: np.stack([x] * L) for name, x in fields.items()})  # [L, ...]


@pytest.mark.parametrize("config", [CFG, SAMPLED], ids=["dense", "sampled"])
def test_perfect_predictions_give_near_zero_loss(batch, config):
    _, targets = batch
    preds = _perfect(targets)
    key = jax.random.key(0) if config.num_mask_points else None
    _, parts, _ = _loss(preds, targets, config=config, key=key)
    for t in ("dice", "focal", "dims", "pos", "cls"):
        assert parts[t] < 1e-5, (t, parts[t])
    assert parts["yaw"] < 1e-5 * targets.valid.sum()  # float32 rounding of the 2 pi offsets


def test_no_targets_gives_finite_loss_and_gradients():
    preds, targets = _random_batch(5, valid=np.zeros((B, M), bool))
    total, parts, grads = _loss(preds, targets)
    assert np.isfinite(total)
    for t in ("dice", "focal", "dims", "pos", "yaw"):
        assert parts[t] == 0.0
    # All queries are background: the weighted mean CE is the plain mean CE.
    logp = jax.nn.log_softmax(preds.logits, axis=-1)[..., K - 1]
    np.testing.assert_allclose(parts["cls"], -logp.mean((1, 2)).sum(), rtol=1e-5)
    for g in jax.tree.leaves(grads):
        assert np.isfinite(np.asarray(g)).all()


@pytest.mark.parametrize("config", [CFG, SAMPLED], ids=["dense", "sampled"])
def test_nan_costs_give_finite_loss_and_gradients(batch, config):
    """NaN boxes and masks on two queries nobody should match poison the cost matrix only:
    the loss and its gradients equal those with huge finite values there. Queries 0 and 1 are
    the ones padded targets are handed (leftovers go lowest index first), so this also checks
    that their outputs never leak into the loss (NaN * 0 = NaN)."""
    preds, targets = batch
    assert targets.valid.sum(1).max() <= Q - 2

    def with_outputs(value):  # boxes and mask logits of queries 0 and 1 set to value
        fields = {f: getattr(preds, f).copy() for f in ("dims", "pos", "yaw", "masks")}
        for x in fields.values():
            x[:, :, :2] = value
        return dataclasses.replace(preds, **fields)

    nan_preds, far_preds = with_outputs(np.nan), with_outputs(1e3)
    assert not np.isfinite(np.asarray(_cost(nan_preds, targets, config=CFG))).all()
    key = jax.random.key(3) if config.num_mask_points else None
    total_nan, _, grads_nan = _loss(nan_preds, targets, config=config, key=key)
    total_far, _, grads_far = _loss(far_preds, targets, config=config, key=key)
    assert np.isfinite(total_nan)
    np.testing.assert_allclose(total_nan, total_far, rtol=1e-6)
    for g_nan, g_far in zip(jax.tree.leaves(grads_nan), jax.tree.leaves(grads_far), strict=True):
        assert np.isfinite(np.asarray(g_nan)).all()
        np.testing.assert_allclose(g_nan, g_far, rtol=1e-5, atol=1e-8)


def test_sampled_cost_estimates_dense_cost(batch):
    """Uniformly sampled cells give an unbiased focal term and a consistent Dice term."""
    preds, targets = batch
    dense = np.asarray(_cost(preds, targets, config=CFG))
    many = dataclasses.replace(CFG, num_mask_points=8192)
    sampled = np.asarray(_cost(preds, targets, config=many, key=jax.random.key(1)))
    np.testing.assert_allclose(sampled, dense, rtol=0.02, atol=0.02)
    assert not np.allclose(sampled, dense, rtol=1e-5, atol=1e-5)  # it did sample


def test_sampled_costs_draw_cells_per_layer_and_frame(batch):
    """The module docstring: cost cells are drawn per (layer, frame). Two identical decoder
    layers, and two identical frames, must get different sampled costs (one draw shared by
    the layers gave them equal costs, so every layer was matched on the same cells)."""
    preds, targets = batch
    key = jax.random.key(4)
    same_layers = jax.tree.map(lambda x: np.concatenate([x[:1], x[:1]]), preds)
    cost = np.asarray(_cost(same_layers, targets, config=SAMPLED, key=key))
    dense = np.asarray(_cost(same_layers, targets, config=CFG))
    np.testing.assert_array_equal(dense[0], dense[1])  # the layers differ only by their cells
    assert not np.allclose(cost[0], cost[1], rtol=1e-3, atol=1e-3)
    same_frames = jax.tree.map(lambda x: np.concatenate([x[:, 1:2], x[:, 1:]], 1), preds)
    same_targets = dataclasses.replace(
        targets, **{f: np.concatenate([getattr(targets, f)[1:2], getattr(targets, f)[1:]])
                    for f in ("classes", "dims", "pos", "yaw", "valid", "masks")}
    )  # fmt: skip
    cost = np.asarray(_cost(same_frames, same_targets, config=SAMPLED, key=key))
    assert not np.allclose(cost[:, 0], cost[:, 1], rtol=1e-3, atol=1e-3)


def test_mask_loss_points_are_three_quarters_the_most_uncertain():
    """Mask2Former's importance sampling (module docstring): of P cells per matched pair,
    0.75 P are the most uncertain (least |logit|) of 3 P uniform candidates, the rest uniform.
    Half the map has |logit| 0.01, half 20: about 1.5 P candidates are uncertain, so the 0.75 P
    important cells all are, and the P / 4 uniform ones add about P / 8: at least 0.75 P
    uncertain cells per pair, about 0.875 P on average. (Sampling the most certain cells gave
    about P / 8; a quarter important, about 0.625 P.)"""
    lyr, b, q, m, side, p = 1, 2, 3, 3, 16, 64
    logit = np.where(np.arange(side) < side // 2, 0.01, 20.0) * np.ones((side, 1))
    logits = np.broadcast_to(logit.ravel(), (lyr, b, q, side * side)).astype(np.float32)
    targets = jnp.zeros((b, m, side * side), bool)
    query_idx = jnp.asarray(np.broadcast_to(np.arange(m, dtype=np.int32), (lyr, b, m)))
    x, t = _loss_mask_points(jnp.asarray(logits), targets, query_idx, p, jax.random.key(0))
    assert x.shape == t.shape == (lyr, b, m, p)
    uncertain = (np.abs(np.asarray(x)) < 1).sum(-1)  # [L, B, M]
    assert uncertain.min() >= 0.75 * p
    assert uncertain.sum() < uncertain.size * p  # the uniform quarter also finds certain cells
    assert abs(uncertain.mean() / p - 0.875) < 0.05


def test_sampled_mask_gradient_touches_at_most_p_cells(batch):
    preds, targets = batch
    _, _, grads = _loss(preds, targets, config=SAMPLED, key=jax.random.key(2))
    touched = (np.asarray(grads.masks) != 0).reshape(L, B, Q, -1).sum(-1)  # [L, B, Q]
    # Each matched query sees the P loss cells only (the cost is not differentiated).
    assert touched.max() <= SAMPLED.num_mask_points
    assert touched.max() > 0
    assert np.isfinite(np.asarray(grads.masks)).all()


def test_bad_inputs_raise(batch):
    preds, targets = batch
    with pytest.raises(ValueError, match="missing"):
        set_loss(preds, targets, {"cls": 1.0})
    with pytest.raises(ValueError, match="predictions.masks"):
        set_loss(dataclasses.replace(preds, masks=preds.masks[..., :8]), targets, WEIGHTS)
    with pytest.raises(ValueError, match="num_mask_points"):
        set_loss(preds, targets, WEIGHTS, SAMPLED)
    as_float = dataclasses.replace(targets, classes=jnp.asarray(targets.classes, jnp.float32))
    with pytest.raises(TypeError, match="targets.classes must be integer class ids, got float32"):
        set_loss(preds, as_float, WEIGHTS)
    # A valid target of class >= K - 1 gave a NaN loss (K - 1: trained as background).
    k = preds.logits.shape[-1]
    b, m = np.argwhere(np.asarray(targets.valid))[0]
    for bad in (k - 1, k, -1):
        classes = np.asarray(targets.classes).copy()
        classes[b, m] = bad
        with pytest.raises(ValueError, match=rf"targets.classes\[{b}, {m}\] = {bad} .*0..{k - 2}"):
            set_loss(preds, dataclasses.replace(targets, classes=jnp.asarray(classes)), WEIGHTS)
    # Padded slots may hold any class.
    classes = np.where(np.asarray(targets.valid), np.asarray(targets.classes), k + 5)
    padded = dataclasses.replace(targets, classes=jnp.asarray(classes))
    assert set_loss(preds, padded, WEIGHTS)[0] == set_loss(preds, targets, WEIGHTS)[0]
