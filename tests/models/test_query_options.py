"""Head options off the paper's path: the per-query mask prior and two-stage query
selection (``HeadConfig.mask_prior`` / ``query_init="select"``), and the seed loss that
trains the selection head."""

import dataclasses
import sys
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from scipy import ndimage

from indoorbev_jax import losses
from indoorbev_jax.config import Config, ConfigError, HeadConfig, LossConfig
from indoorbev_jax.geometry import cell_centers
from indoorbev_jax.models.head import SimpleMaskHead, peak_cells
from indoorbev_jax.types import Targets

sys.path.insert(0, str(Path(__file__).parents[1]))
from numpy_layers import dense  # noqa: E402

CFG = Config.tiny()
H, W = CFG.grid.shape


def _head(**changes) -> SimpleMaskHead:
    return SimpleMaskHead(dataclasses.replace(CFG.head, **changes), CFG.num_classes, grid=CFG.grid)


@pytest.fixture(scope="module")
def feats():
    return jax.random.normal(jax.random.key(0), (2, H, W, 12))


def test_mask_prior_is_minus_a_squared_distance_to_the_predicted_centre(feats):
    with_prior = _head(mask_prior=True)
    params = with_prior.init(jax.random.key(1), feats)
    out = with_prior.apply(params, feats)
    # The same parameters minus the prior's own give the plain masks.
    plain_params = {"params": {k: v for k, v in params["params"].items() if k != "prior_scale"}}
    plain = _head().apply(plain_params, feats)
    np.testing.assert_array_equal(out["pos"], plain["pos"])
    diff = np.asarray(out["masks"] - plain["masks"], np.float64)  # [L, B, Q, H, W]
    xs, ys = (np.asarray(v, np.float64) for v in cell_centers(CFG.grid))
    pos = np.asarray(out["pos"], np.float64)
    d2 = (ys[:, None] - pos[..., 1, None, None]) ** 2 + (xs[None, :] - pos[..., 0, None, None]) ** 2
    a = -(diff * d2).sum((-2, -1)) / (d2**2).sum((-2, -1))  # least-squares scale per query
    assert (a > 0).all()
    np.testing.assert_allclose(diff, -a[..., None, None] * d2, rtol=1e-4, atol=1e-4)


def test_peak_cells_match_a_scipy_maximum_filter():
    score = np.array(jax.random.uniform(jax.random.key(2), (3, 9, 11)))
    score[1] = 0.5  # a flat map: every cell is a peak; ties may pick any of them
    k = 7
    cells = np.asarray(peak_cells(jnp.asarray(score), k))
    for b in range(3):
        peak = score[b] >= ndimage.maximum_filter(score[b], size=3, mode="constant", cval=-np.inf)
        flat = np.where(peak.ravel(), score[b].ravel(), -np.inf)
        want = np.sort(flat)[::-1][:k]
        if np.isfinite(want).all():
            np.testing.assert_array_equal(flat[cells[b]], want)  # best peaks, best first
        assert len(set(cells[b].tolist())) == k


def test_peak_cells_fill_up_with_non_peaks_when_there_are_few_peaks():
    score = np.zeros((1, 4, 4), np.float32)
    score[0, 0, 0] = 1.0  # one peak; zeros around it are not peaks (their 3x3 max is 1)
    score[0, 3, 3] = 0.5
    cells = np.asarray(peak_cells(jnp.asarray(score), 5))[0]
    assert cells[0] == 0 and cells[1] == 15  # the two peaks first, best first
    assert len(set(cells.tolist())) == 5


def test_peak_cells_rank_every_peak_first_on_logits():
    """The seed head gives logits: a strong object's ring (6.16) was ranked above weaker
    objects' peaks (3.34), which a fixed offset of 2 below the peaks cannot order, so every
    query started on one object. Peaks come first, best first, whatever the range."""
    score = np.full((1, 12, 12), -4.6, np.float32)  # the seed head's initial bias
    score[0, 2:5, 2:5] = 6.16  # the strong object's ring...
    score[0, 3, 3] = 6.40  # ...around its peak
    weak = [(2, 9), (9, 2), (9, 9)]
    for r, c in weak:
        score[0, r, c] = 3.34
    cells = np.asarray(peak_cells(jnp.asarray(score), 4))[0]
    assert cells[0] == 3 * 12 + 3 and sorted(cells[1:]) == sorted(r * 12 + c for r, c in weak)
    # Probabilities pick the same cells: the order depends on the scores' ranking only.
    probs = np.asarray(peak_cells(jax.nn.sigmoid(jnp.asarray(score)), 4))[0]
    np.testing.assert_array_equal(np.sort(probs), np.sort(cells))


def test_select_queries_start_at_their_cells_and_sow_the_seeds(feats):
    """Each query starts at its selected cell: its anchor the cell's centre, its content
    Dense(F_proj at the cell). A mutation audit: the features gathered from the transposed
    map and the seed prior's sign flipped (probability 0.99) passed."""
    head = _head(query_init="select")
    params = head.init(jax.random.key(3), feats)
    assert "query_embed" not in params["params"] and "seed_head" in params["params"]
    out, inter = head.apply(params, feats, capture_intermediates=True, mutable=["intermediates"])
    (seeds,) = inter["intermediates"]["seeds"]
    assert seeds.shape == (2, H, W, CFG.num_classes)
    cells = np.asarray(peak_cells(seeds.max(-1), CFG.head.num_queries))  # [B, Q]
    # pos = pos_head(query) + the centre of the query's selected cell.
    # Our Dense records its flattened inner call first, then its own [L, B, Q, 3] output.
    offset = inter["intermediates"]["pos_head"]["__call__"][-1]
    xs, ys = (np.asarray(v) for v in cell_centers(CFG.grid))
    anchor = np.stack([xs[cells % W], ys[cells // W], np.zeros(cells.shape)], -1)
    np.testing.assert_allclose(
        np.asarray(out["pos"]) - np.asarray(offset),
        np.broadcast_to(anchor, offset.shape),
        atol=1e-5,
    )
    # The query's content is F_proj at its selected cell (row-major: cell = row * W + col).
    f_proj = np.asarray(inter["intermediates"]["input_proj_norm"]["__call__"][0])
    content = np.asarray(inter["intermediates"]["query_content"]["__call__"][-1])  # [B, Q, C]
    at_cells = np.take_along_axis(f_proj.reshape(2, H * W, -1), cells[..., None], axis=1)
    np.testing.assert_allclose(
        content, dense(at_cells, params["params"]["query_content"]), atol=1e-4
    )
    # The seed head starts at the RetinaNet prior: every class at probability 0.01.
    np.testing.assert_allclose(params["params"]["seed_head"]["bias"], -np.log(99), rtol=1e-6)


def test_semantic_head_sows_seeds_beside_learned_queries(feats):
    head = _head(semantic_head=True)
    params = head.init(jax.random.key(7), feats)
    assert {"query_embed", "seed_head"} <= set(params["params"])
    _, inter = head.apply(params, feats, mutable=["intermediates"])
    (seeds,) = inter["intermediates"]["seeds"]
    assert seeds.shape == (2, H, W, CFG.num_classes)
    assert "seed_head" not in _head().init(jax.random.key(7), feats)["params"]
    assert Config.small().has_seed_head is False
    assert dataclasses.replace(CFG, head=head.config).has_seed_head


def test_head_without_grid_names_the_missing_field(feats):
    head = SimpleMaskHead(dataclasses.replace(CFG.head, mask_prior=True), CFG.num_classes)
    with pytest.raises(ValueError, match="grid"):
        head.init(jax.random.key(0), feats)


def test_query_init_is_validated():
    with pytest.raises(ConfigError, match="head.query_init"):
        HeadConfig(query_init="anchors")


def _targets(rng: np.random.Generator, b=2, m=3, h=6, w=5, k=4) -> Targets:
    valid = rng.random((b, m)) < 0.7
    return Targets(
        classes=jnp.asarray(rng.integers(0, k, (b, m)), jnp.int32),
        dims=jnp.zeros((b, m, 3)),
        pos=jnp.zeros((b, m, 3)),
        yaw=jnp.zeros((b, m)),
        valid=jnp.asarray(valid),
        masks=jnp.asarray(rng.random((b, m, h, w)) < 0.3),
        instance_ids=jnp.zeros((b, h, w), jnp.int32),
    )


def test_seed_loss_matches_a_numpy_focal_rederivation():
    rng = np.random.default_rng(4)
    t = _targets(rng)
    k = 4
    seeds = rng.normal(size=(2, 6, 5, k)) * 2
    sem = np.zeros((2, 6, 5, k))
    for b in range(2):
        for j in range(3):
            if t.valid[b, j]:
                sem[b, ..., int(t.classes[b, j])] += np.asarray(t.masks[b, j])
    sem = sem > 0
    np.testing.assert_array_equal(losses.semantic_targets(t, k), sem)
    cfg = LossConfig()
    p = 1 / (1 + np.exp(-seeds))
    pos = -cfg.focal_alpha * (1 - p) ** cfg.focal_gamma * np.log(p)
    neg = -(1 - cfg.focal_alpha) * p**cfg.focal_gamma * np.log(1 - p)
    want = np.where(sem, pos, neg).sum() / max(sem.sum(), 1)
    got = losses.seed_loss(jnp.asarray(seeds, jnp.float32), t, cfg)
    np.testing.assert_allclose(float(got), want, rtol=1e-5)


def test_seed_loss_rejects_a_map_off_the_targets_grid():
    t = _targets(np.random.default_rng(5))
    with pytest.raises(ValueError, match=r"\[B, H, W, K\]"):
        losses.seed_loss(jnp.zeros((2, 5, 6, 4)), t)


def test_select_train_step_adds_the_weighted_seed_loss(tmp_path):
    import sys
    from pathlib import Path

    from indoorbev_jax import train as T
    from indoorbev_jax.data.dataset import KittiDataset

    sys.path.insert(0, str(Path(__file__).parents[1]))
    from synthetic import write_synthetic_dataset

    write_synthetic_dataset(tmp_path, frames=8)
    cfg = dataclasses.replace(
        CFG,
        head=dataclasses.replace(CFG.head, query_init="select", mask_prior=True),
        loss=dataclasses.replace(CFG.loss, seed_weight=3.0),
        train=dataclasses.replace(CFG.train, augment=False),
    )
    batch = next(KittiDataset(tmp_path, "train", cfg).batches(2))
    state = T.init_state(cfg, jax.random.key(0))
    hyper = T.Hyper.from_config(cfg)
    step = T.jit_train_step(cfg, T.make_train_step(cfg))
    first, m = step(state, batch, jax.random.key(1), hyper)
    set_total = sum(float(hyper.weights[t]) * float(m[t]) for t in losses.TERMS)
    np.testing.assert_allclose(float(m["loss"]), set_total + 3.0 * float(m["seed"]), rtol=1e-5)
    assert bool(m["finite"]) and float(m["seed"]) > 0
    # The seed weight is a traced Hyper entry, so sweeps vmap over it; same compiled step.
    assert float(hyper.weights["seed"]) == 3.0
    halved = hyper.replace(weights=dict(hyper.weights, seed=jnp.float32(0.5)))
    _, m2 = step(state, batch, jax.random.key(1), halved)
    np.testing.assert_allclose(float(m2["loss"]), set_total + 0.5 * float(m["seed"]), rtol=1e-5)
    second, _ = step(first, batch, jax.random.key(1), hyper)  # step 0 has lr 0 (warm-up)

    def seed_kernel(s):
        return s.params["params"]["head"]["seed_head"]["kernel"]

    assert float(jnp.abs(seed_kernel(second) - seed_kernel(state)).max()) > 0


def test_mask_pooled_class_reads_the_mean_feature_under_each_mask(feats):
    head = _head(mask_prior=True, mask_pooled_class=True)
    params = head.init(jax.random.key(6), feats)
    out, inter = head.apply(params, feats, capture_intermediates=True, mutable=["intermediates"])
    it, p = inter["intermediates"], params["params"]
    f_proj = np.asarray(it["input_proj_norm"]["__call__"][0], np.float64)  # [B, H, W, C]
    q = np.stack([np.asarray(it[f"decoder{i}"]["__call__"][0]) for i in range(CFG.head.num_layers)])
    w = 1 / (1 + np.exp(-np.asarray(out["masks"], np.float64)))  # [L, B, Q, H, W]
    pooled = np.einsum("lbqhw,bhwc->lbqc", w, f_proj) / (w.sum((-2, -1))[..., None] + 1)
    dense = lambda x, name: x @ np.asarray(p[name]["kernel"]) + np.asarray(p[name]["bias"])  # noqa: E731
    want = dense(q + dense(pooled, "pooled_proj"), "class_head")
    np.testing.assert_allclose(out["logits"], want, rtol=1e-4, atol=1e-4)
    # Only the class logits read the pooled feature; the box heads read the query itself
    # (MODEL.md): in the shipped small model a leak moved dims by up to 2.1 m.
    np.testing.assert_allclose(out["dims"], dense(q, "dims_head"), rtol=1e-5, atol=1e-5)
    np.testing.assert_allclose(out["yaw"], dense(q, "yaw_head"), rtol=1e-5, atol=1e-5)
