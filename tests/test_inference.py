"""Panoptic inference against a direct numpy re-derivation and hand-built cases."""

import jax
import numpy as np
import pytest

from indoorbev_jax.config import NUM_CLASSES, Config, InferenceConfig
from indoorbev_jax.inference import panoptic_inference, panoptic_inference_from_logits
from indoorbev_jax.types import Predictions

K = NUM_CLASSES + 1
BG = NUM_CLASSES


def reference(logits, mask_logits, cfg):
    """Loops over frames and queries; float64."""
    logits = logits.astype(np.float64)
    e = np.exp(logits - logits.max(-1, keepdims=True))
    fg = (e / e.sum(-1, keepdims=True))[..., :-1]
    mp = 1 / (1 + np.exp(-mask_logits.astype(np.float64)))
    b, q = logits.shape[:2]
    ids = np.zeros((b,) + mask_logits.shape[2:], np.int64)
    classes = np.full((b, q + 1), BG)
    scores = np.zeros((b, q))
    for i in range(b):
        best = np.full(mask_logits.shape[2:], -1.0)
        winner = np.full(mask_logits.shape[2:], -1)
        for j in range(q):
            binary = mp[i, j] >= cfg.mask_threshold
            prob = fg[i, j].max()
            scores[i, j] = prob * mp[i, j][binary].mean() if binary.any() else 0.0
            if prob < cfg.score_threshold:
                continue
            better = binary & (prob * mp[i, j] > best)  # strict: ties stay with lower index
            best[better] = prob * mp[i, j][better]
            winner[better] = j
        for j in range(q):
            seg = winner == j
            own = (mp[i, j] >= cfg.mask_threshold).sum()
            if seg.any() and seg.sum() / own >= cfg.overlap_threshold:
                ids[i][seg] = j + 1
                classes[i, j + 1] = fg[i, j].argmax()
    return ids, classes, scores


def predictions(logits, masks):
    """Two decoder layers; the first holds garbage so that using it would show."""
    z = np.zeros(logits.shape[:-1] + (3,), np.float32)
    stack = lambda x: np.stack([np.full_like(x, 7.0), x])  # noqa: E731
    return Predictions(
        logits=stack(logits), dims=stack(z), pos=stack(z), yaw=stack(z[..., :1]), masks=stack(masks)
    )


@pytest.mark.parametrize(
    ("score_threshold", "mask_threshold"), [(0.8, 0.5), (0.4, 0.5), (0.4, 0.3), (0.4, 0.7)]
)
def test_matches_numpy_rederivation(score_threshold, mask_threshold):
    """Also at mask thresholds other than 0.5: binarising at logit 0 whatever the setting
    passed every test before (a mutation audit)."""
    rng = np.random.default_rng(0)
    cfg = InferenceConfig(score_threshold=score_threshold, mask_threshold=mask_threshold)
    logits = (4 * rng.standard_normal((3, 10, K))).astype(np.float32)
    # Rectangles of confident cells in noise: queries overlap partly, some lose too much.
    masks = rng.normal(-3.0, 1.0, (3, 10, 16, 18))
    for i, j in np.ndindex(3, 10):
        y, x = rng.integers(0, 12), rng.integers(0, 14)
        masks[i, j, y : y + rng.integers(2, 8), x : x + rng.integers(2, 8)] += 5.0
    masks = masks.astype(np.float32)
    out = jax.tree.map(np.asarray, panoptic_inference(predictions(logits, masks), cfg))
    ids, classes, scores = reference(logits, masks, cfg)
    np.testing.assert_array_equal(out.instance_ids, ids)
    np.testing.assert_array_equal(out.instance_classes, classes)
    np.testing.assert_array_equal(out.segment_valid, classes[:, 1:] != BG)
    np.testing.assert_allclose(out.det_scores, scores, rtol=1e-5, atol=1e-7)
    binary = 1 / (1 + np.exp(-masks.astype(np.float64))) >= mask_threshold
    np.testing.assert_array_equal(out.det_masks, binary)
    np.testing.assert_array_equal(out.det_valid, binary.any((2, 3)))
    np.testing.assert_array_equal(out.det_classes, logits[..., :-1].argmax(-1))
    # Both branches of the overlap rule occur.
    p = np.exp(logits - logits.max(-1, keepdims=True))
    kept = (p / p.sum(-1, keepdims=True))[..., :-1].max(-1) >= score_threshold
    assert out.segment_valid.any() and (kept & out.det_valid & ~out.segment_valid).any()


def logit(p):
    return float(np.log(p / (1 - p)))


def test_hand_case_overlap_drop_and_scores():
    h, w, q = 6, 8, 4
    logits = np.full((1, q, K), -20.0, np.float32)
    masks = np.full((1, q, h, w), -20.0, np.float32)
    # Query 0: Table, p ~ 0.9, mask prob 0.9 on rows 0-2, cols 0-3 (12 cells).
    logits[0, 0, 0], logits[0, 0, BG] = logit(0.9), 0.0
    masks[0, 0, 0:3, 0:4] = logit(0.9)
    # Query 1: Chair, p ~ 0.95, mask prob 0.7 on rows 0-2, cols 2-5: it loses cols 2-3 to
    # query 0 (0.9 * 0.9 > 0.95 * 0.7) and keeps 6 / 12 < 80 %: dropped, cells left empty.
    logits[0, 1, 1], logits[0, 1, BG] = logit(0.95), 0.0
    masks[0, 1, 0:3, 2:6] = logit(0.7)
    # Query 2: Sofa below the threshold (p ~ 0.79): a detection, never a segment.
    logits[0, 2, 2], logits[0, 2, BG] = logit(0.79), 0.0
    masks[0, 2, 4:6, 0:2] = logit(0.6)
    # Query 3: confident but an empty mask: neither a detection nor a segment.
    logits[0, 3, 3], logits[0, 3, BG] = logit(0.99), 0.0
    out = jax.tree.map(np.asarray, panoptic_inference_from_logits(logits, masks))
    expected = np.zeros((h, w), np.int64)
    expected[0:3, 0:4] = 1
    np.testing.assert_array_equal(out.instance_ids[0], expected)
    np.testing.assert_array_equal(out.instance_classes[0], [BG, 0, BG, BG, BG])
    np.testing.assert_array_equal(out.det_valid[0], [True, True, True, False])
    np.testing.assert_array_equal(out.det_classes[0, :3], [0, 1, 2])
    np.testing.assert_allclose(out.det_scores[0, :3], [0.9 * 0.9, 0.95 * 0.7, 0.79 * 0.6], 1e-4)
    # With a laxer overlap rule query 1 keeps its 6 uncontested cells.
    lax = panoptic_inference_from_logits(logits, masks, InferenceConfig(overlap_threshold=0.5))
    assert (np.asarray(lax.instance_ids[0]) == 2).sum() == 6


def test_jittable_inside_outer_jit_and_checks_shapes():
    rng = np.random.default_rng(1)
    logits = rng.standard_normal((2, 5, K)).astype(np.float32)
    masks = rng.standard_normal((2, 5, 4, 4)).astype(np.float32)
    outer = jax.jit(lambda a, b: panoptic_inference_from_logits(a, b).instance_ids.sum())
    direct = np.asarray(panoptic_inference_from_logits(logits, masks).instance_ids).sum()
    assert int(outer(logits, masks)) == int(direct)
    with pytest.raises(ValueError, match="mask_logits"):
        panoptic_inference_from_logits(logits, masks[:, :3])
    with pytest.raises(ValueError, match="predictions.logits"):
        panoptic_inference(Predictions(logits[0], None, None, None, masks))
    # The whole Config for its inference section failed on an AttributeError of a field.
    with pytest.raises(
        TypeError, match=r"config: expected InferenceConfig, got Config; pass config\.inference"
    ):
        panoptic_inference(Predictions(logits[None], None, None, None, masks[None]), Config.tiny())
    # A dict of the outputs, as PyTorch code passes them, gives the same result.
    preds = Predictions(logits[None], None, None, None, masks[None])
    as_dict = {k: preds[k] for k in preds.keys()}
    a, b = panoptic_inference(preds), panoptic_inference(as_dict)
    np.testing.assert_array_equal(np.asarray(a.instance_ids), np.asarray(b.instance_ids))
    # Only logits and masks are read: a dict of those two is enough.
    c = panoptic_inference({"logits": preds["logits"], "masks": preds["masks"]})
    np.testing.assert_array_equal(np.asarray(a.instance_ids), np.asarray(c.instance_ids))
    with pytest.raises(TypeError, match=r"missing \['logits'"):
        panoptic_inference({"masks": preds["masks"]})


def test_identical_queries_tie_to_the_lower_index():
    logits = np.full((1, 3, K), -20.0, np.float32)
    logits[0, :, 5] = 5.0
    masks = np.full((1, 3, 4, 4), -20.0, np.float32)
    masks[0, 1:, 1:3, 1:3] = 4.0  # queries 1 and 2 are the same object
    out = panoptic_inference_from_logits(logits, masks)
    ids = np.asarray(out.instance_ids[0])
    assert set(np.unique(ids)) == {0, 2}  # query 1 wins every cell; query 2 keeps none
    np.testing.assert_array_equal(out.segment_valid[0], [False, True, False])
    # With an overlap rule that any share passes (0), a query that keeps no cell (2, or 0
    # with its empty mask) is still no segment: segment_valid and the classes follow the map.
    lax = panoptic_inference_from_logits(logits, masks, InferenceConfig(overlap_threshold=0.0))
    np.testing.assert_array_equal(lax.instance_ids, out.instance_ids)
    np.testing.assert_array_equal(lax.segment_valid[0], [False, True, False])
    np.testing.assert_array_equal(lax.instance_classes[0], [BG, BG, 5, BG])


@pytest.mark.parametrize("mask_threshold", [0.0, 1.0])
def test_mask_threshold_at_the_ends_of_its_range(mask_threshold):
    """sigmoid(x) lies strictly inside (0, 1) for finite x: at mask_threshold 1 no cell is in
    any mask (no detection, no segment, an empty map), at 0 every cell is. Checked against
    the float64 re-derivation, which compares the probabilities themselves."""
    rng = np.random.default_rng(2)
    cfg = InferenceConfig(score_threshold=0.3, mask_threshold=mask_threshold,
                          overlap_threshold=0.0)  # fmt: skip
    logits = (4 * rng.standard_normal((2, 6, K))).astype(np.float32)
    masks = rng.uniform(-8.0, 8.0, (2, 6, 5, 7)).astype(np.float32)
    out = jax.tree.map(np.asarray, panoptic_inference_from_logits(logits, masks, cfg))
    ids, classes, scores = reference(logits, masks, cfg)
    np.testing.assert_array_equal(out.det_masks, np.full(masks.shape, mask_threshold == 0.0))
    np.testing.assert_array_equal(out.det_valid, np.full((2, 6), mask_threshold == 0.0))
    np.testing.assert_array_equal(out.instance_ids, ids)
    np.testing.assert_array_equal(out.instance_classes, classes)
    np.testing.assert_allclose(out.det_scores, scores, rtol=1e-5, atol=1e-7)
    assert (ids > 0).any() == (mask_threshold == 0.0)


def test_thresholds_are_inclusive_at_equality():
    """A query whose class probability equals score_threshold is kept and a cell whose mask
    probability equals mask_threshold is in the mask (">=", module docstring, DESIGN 9).
    With K = 2 equal logits p_fg is exactly 0.5 and mask logit 0 gives exactly 0.5, so
    the case is exact in float32; ">" at either threshold passed every test (a mutation
    audit)."""
    logits = np.zeros((1, 1, 2), np.float32)  # one foreground class and background
    masks = np.zeros((1, 1, 2, 3), np.float32)
    cfg = InferenceConfig(score_threshold=0.5, mask_threshold=0.5, overlap_threshold=0.8)
    out = jax.tree.map(np.asarray, panoptic_inference_from_logits(logits, masks, cfg))
    np.testing.assert_array_equal(out.det_masks, np.ones(masks.shape, bool))
    np.testing.assert_array_equal(out.det_valid, [[True]])
    np.testing.assert_array_equal(out.det_scores, [[0.25]])  # 0.5 * mean(0.5)
    np.testing.assert_array_equal(out.segment_valid, [[True]])
    np.testing.assert_array_equal(out.instance_ids, np.ones((1, 2, 3), np.int32))
    np.testing.assert_array_equal(out.instance_classes, [[1, 0]])


def test_cells_whose_probability_underflows_stay_in_the_mask_at_threshold_0():
    """At mask_threshold 0 every cell is in the mask (probability >= 0), also where
    sigmoid(logit) underflows to 0 in float32 (logit -200): the floor ``_TINY`` keeps those
    cells. The other test of threshold 0 used logits that never underflow, and dropping
    the floor passed it (a mutation audit)."""
    logits = np.full((1, 2, K), -20.0, np.float32)
    logits[0, :, 4] = 5.0
    masks = np.full((1, 2, 4, 5), -200.0, np.float32)
    masks[0, 0, :2] = 2.0  # query 0: half its cells confident, half underflowing
    assert (np.asarray(jax.nn.sigmoid(masks[0, 1])) == 0).all()  # underflows in float32
    cfg = InferenceConfig(score_threshold=0.5, mask_threshold=0.0, overlap_threshold=0.0)
    out = jax.tree.map(np.asarray, panoptic_inference_from_logits(logits, masks, cfg))
    ids, classes, scores = reference(logits, masks, cfg)
    np.testing.assert_array_equal(out.det_masks, np.ones(masks.shape, bool))
    np.testing.assert_array_equal(out.det_valid, [[True, True]])
    # Query 0 wins every cell (its score there is larger); query 1 keeps none.
    np.testing.assert_array_equal(ids, np.ones((1, 4, 5)))
    np.testing.assert_array_equal(out.instance_ids, ids)
    np.testing.assert_array_equal(out.instance_classes, classes)
    np.testing.assert_allclose(out.det_scores, scores, rtol=1e-5, atol=1e-7)
