"""matching.match against scipy.optimize.linear_sum_assignment (compare totals: ties make
the optimal indices ambiguous)."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from scipy.optimize import linear_sum_assignment

from indoorbev_jax.matching import COST_CAP, clean_cost, match

_match = jax.jit(match)


def _scipy_total(cost, valid):
    sub = cost[:, valid]
    rows, cols = linear_sum_assignment(sub)
    return sub[rows, cols].sum()


def _our_total(cost, valid, query_idx):
    return cost[query_idx[valid], np.flatnonzero(valid)].sum()


def _problems(rng, n, q, m):
    """n random problems in six kinds: uniform, ties, duplicate rows, padding, empty, full."""
    kinds = np.arange(n) % 6
    cost = rng.random((n, q, m))
    ties = kinds == 1
    cost[ties] = rng.integers(0, 3, (ties.sum(), q, m))  # many equal entries
    dup = np.flatnonzero(kinds == 2)
    for i in dup:  # whole duplicated rows, some rows repeated several times
        src = rng.integers(0, q, q)
        cost[i] = cost[i][np.where(rng.random(q) < 0.5, src, np.arange(q))]
    valid = np.ones((n, m), bool)
    padded = kinds == 3
    valid[padded] = rng.random((padded.sum(), m)) < 0.5  # anywhere, not only a suffix
    valid[kinds == 4] = False  # frames without targets
    # Duplicated rows with padding too, and integer ties with padding.
    valid[kinds == 2] = rng.random(((kinds == 2).sum(), m)) < 0.8
    valid[ties] = rng.random((ties.sum(), m)) < 0.8
    return cost.astype(np.float32), valid


@pytest.mark.parametrize("q, m, n", [(12, 8, 1200), (30, 30, 60), (30, 12, 60)])
def test_total_cost_equals_scipy(q, m, n):
    rng = np.random.default_rng(q * 100 + m)
    cost, valid = _problems(rng, n, q, m)
    query_idx, target_idx = map(np.asarray, _match(cost, valid))
    assert query_idx.shape == target_idx.shape == (n, m)
    assert query_idx.dtype == target_idx.dtype == np.int32
    np.testing.assert_array_equal(target_idx, np.broadcast_to(np.arange(m), (n, m)))
    ours = np.array([_our_total(cost[i], valid[i], query_idx[i]) for i in range(n)])
    ref = np.array([_scipy_total(cost[i], valid[i]) for i in range(n)])
    np.testing.assert_allclose(ours, ref, rtol=1e-5, atol=1e-5)
    # A one-to-one assignment: distinct queries in range, padded targets included.
    assert ((query_idx >= 0) & (query_idx < q)).all()
    assert all(len(set(row)) == m for row in query_idx)


@pytest.mark.parametrize("scale", [1e3, 1e6, 1e9, 1e30, -1e6])
def test_large_finite_costs_keep_their_order(scale):
    """Costs far above COST_CAP (and padded entries larger still) are matched as scipy
    matches them, not clipped into ties."""
    rng = np.random.default_rng(7)
    cost, valid = _problems(rng, 60, 12, 8)
    cost = cost * np.float32(scale)
    cost = np.where(valid[:, None], cost, np.float32(3e38))  # padding must not set the scale
    query_idx = np.asarray(_match(cost, valid)[0])
    for i in range(len(cost)):
        ref = _scipy_total(cost[i].astype(np.float64), valid[i])
        ours = _our_total(cost[i].astype(np.float64), valid[i], query_idx[i])
        np.testing.assert_allclose(ours, ref, rtol=1e-6, atol=abs(scale) * 1e-6)


def test_large_costs_are_not_clipped_into_ties():
    # The diagonal costs twice the anti-diagonal; clipped to COST_CAP both would tie.
    big = jnp.array([[[2e6, 1e6], [1e6, 2e6]]], jnp.float32)
    np.testing.assert_array_equal(np.asarray(_match(big, jnp.ones((1, 2), bool))[0]), [[1, 0]])


def test_python_lists_are_matched_as_arrays():
    """Nested lists, as a test written from the issue might pass them (read .ndim first)."""
    query_idx, target_idx = match([[[1.0, 0.0, 5.0], [0.0, 1.0, 5.0]]], [[True, True, False]])
    np.testing.assert_array_equal(np.asarray(query_idx)[:, :2], [[1, 0]])
    np.testing.assert_array_equal(np.asarray(target_idx), [[0, 1, 2]])


def test_no_targets_gives_empty_indices():
    query_idx, target_idx = _match(jnp.zeros((2, 5, 0)), jnp.zeros((2, 0), bool))
    assert query_idx.shape == target_idx.shape == (2, 0)


def test_no_queries_leaves_every_target_unmatched():
    """Q = 0 was a gather error; as with more valid targets than queries, each gets -1."""
    query_idx, target_idx = _match(jnp.zeros((2, 0, 3)), jnp.ones((2, 3), bool))
    np.testing.assert_array_equal(query_idx, np.full((2, 3), -1))
    np.testing.assert_array_equal(target_idx, np.tile(np.arange(3), (2, 1)))


def test_clean_cost_scales_only_frames_past_the_bound():
    cost = jnp.array([[[1.0, -50.0], [np.inf, 3.0]], [[4e6, 1.0], [np.nan, -np.inf]]])
    cleaned = np.asarray(clean_cost(cost))
    bound = COST_CAP / (2 * 3)
    np.testing.assert_array_equal(cleaned[0], [[1.0, -50.0], [COST_CAP, 3.0]])  # unchanged
    scale = 2.0 ** np.ceil(np.log2(4e6 / bound))  # the least power of two
    assert 4e6 / scale <= bound < 4e6 / (scale / 2)
    np.testing.assert_array_equal(cleaned[1], [[4e6 / scale, 1.0 / scale], [COST_CAP, -COST_CAP]])


def test_clean_cost_scale_is_set_by_valid_targets_only():
    """clean_cost's docstring: only valid targets' finite entries set a frame's scale. A
    padded slot holding 1e9 (meaningless) left the valid entries divided by 2**16 (1.0 became
    1.5e-5); the frame is under the bound COST_CAP / (2 (M + 1)), so nothing is rescaled, the
    padded entry included. Once a valid entry is past the bound, the padded one is rescaled
    with its frame; with valid=None every entry counts."""
    cost = jnp.array([[[1.0, 1e9], [2.0, 3.0]]])
    bound = COST_CAP / (2 * 3)
    np.testing.assert_array_equal(clean_cost(cost, jnp.array([[True, False]])), cost)
    scale = 2.0 ** np.ceil(np.log2(1e9 / bound))  # least power of two taking 1e9 under it
    np.testing.assert_array_equal(clean_cost(cost), np.asarray(cost) / scale)
    big = cost.at[0, 1, 0].set(4e6)
    scale = 2.0 ** np.ceil(np.log2(4e6 / bound))
    cleaned = clean_cost(big, jnp.array([[True, False]]))
    np.testing.assert_array_equal(cleaned, np.asarray(big) / scale)


def test_non_finite_costs_are_avoided():
    rng = np.random.default_rng(1)
    n, q, m = 200, 12, 6
    cost = rng.random((n, q, m)).astype(np.float32)
    bad = rng.random((n, q, m)) < 0.2
    cost[bad] = rng.choice(np.array([np.nan, np.inf, -np.inf], np.float32), bad.sum())
    cost[: n // 2][np.isneginf(cost[: n // 2])] = np.nan  # first half: NaN and +Inf only
    valid = rng.random((n, m)) < 0.8
    query_idx = np.asarray(_match(cost, valid)[0])
    cleaned = np.asarray(clean_cost(jnp.asarray(cost)))
    assert np.isfinite(cleaned).all() and np.abs(cleaned).max() <= COST_CAP
    for i in range(n):
        assert len(set(query_idx[i])) == m
        np.testing.assert_allclose(
            _our_total(cleaned[i], valid[i], query_idx[i]),
            _scipy_total(cleaned[i], valid[i]),
            rtol=1e-6,
        )
        # Without -Inf, a pair costing COST_CAP is never worth it when an assignment of
        # finite pairs exists (scipy on the 0/1 "is bad" matrix finds one if it does).
        is_bad = ~np.isfinite(cost[i])
        if i < n // 2 and _scipy_total(is_bad.astype(float), valid[i]) == 0:
            assert not is_bad[query_idx[i][valid[i]], np.flatnonzero(valid[i])].any()


def test_a_target_with_only_non_finite_costs_still_gets_a_free_query():
    """match's docstring: with at most Q valid targets each still gets its query. A valid
    target whose every cost is NaN or +Inf (a diverging loss term) costs COST_CAP on every
    query, so it must still take a query rather than its dummy column: the dummies must cost
    more than COST_CAP (at 0.5 COST_CAP it got -1). The total equals scipy's on the cleaned
    costs."""
    rng = np.random.default_rng(9)
    q, m = 5, 3
    cost = rng.random((6, q, m)).astype(np.float32)
    cost[0, :, 1] = np.nan
    cost[1, :, 0] = np.inf
    cost[2, :, 2] = np.nan
    cost[2, :, 0] = np.inf  # two such targets in one frame
    cost[3, :, :] = np.nan  # every target
    valid = np.ones((6, m), bool)
    valid[4:, 1] = False  # with a padded slot beside it
    cost[4, :, 0] = np.nan
    cost[5, :, 2] = np.inf
    query_idx = np.asarray(_match(jnp.asarray(cost), jnp.asarray(valid))[0])
    cleaned = np.asarray(clean_cost(jnp.asarray(cost), jnp.asarray(valid)))
    for b in range(len(cost)):
        got = query_idx[b, valid[b]]
        assert ((got >= 0) & (got < q)).all() and len(set(got)) == len(got)
        np.testing.assert_allclose(
            _our_total(cleaned[b], valid[b], query_idx[b]),
            _scipy_total(cleaned[b], valid[b]),
            rtol=1e-6,
        )


def test_gradient_is_finite_for_nan_costs():
    rng = np.random.default_rng(2)
    x = jnp.asarray(rng.random((4, 7, 5)), jnp.float32)
    valid = jnp.asarray(rng.random((4, 5)) < 0.7)

    def picked_cost(x):
        # The cost handed to the matcher has NaN/Inf entries (as a diverging loss term would);
        # the matched entries of x are then summed.
        nan_cost = jnp.where(x > 0.8, jnp.nan, x) / jnp.where(x < 0.1, 0.0, 1.0)
        query_idx, target_idx = match(nan_cost, valid)
        picked = jnp.take_along_axis(x, query_idx[:, None, :], axis=1)[:, 0]  # [B, M]
        return jnp.where(valid, picked, 0.0).sum(), (query_idx, target_idx)

    grad, (query_idx, _) = jax.jit(jax.grad(picked_cost, has_aux=True))(x)
    assert np.isfinite(np.asarray(grad)).all()
    # d(sum of matched entries)/dx is the assignment's indicator.
    expected = np.zeros(x.shape, np.float32)
    for b in range(4):
        for j in np.flatnonzero(np.asarray(valid[b])):
            expected[b, query_idx[b, j], j] = 1.0
    np.testing.assert_array_equal(np.asarray(grad), expected)


def test_more_target_slots_than_queries_matches_like_scipy():
    """M > Q: the valid targets still get the optimum scipy finds; when more than Q are
    valid, Q of them are matched (scipy's rectangular case) and the rest get -1."""
    rng = np.random.default_rng(5)
    q, m = 4, 7
    cost = rng.random((12, q, m)).astype(np.float32)
    valid = np.zeros((12, m), bool)
    for b in range(12):
        valid[b, rng.choice(m, size=b % (m + 1), replace=False)] = True
    query_idx = np.asarray(_match(jnp.asarray(cost), jnp.asarray(valid))[0])
    for b in range(12):
        js = np.flatnonzero(valid[b])
        got = query_idx[b, js]
        matched = got >= 0
        assert matched.sum() == min(len(js), q)
        assert np.all(got[~matched] == -1)
        assert len(set(got[matched])) == matched.sum()  # distinct queries
        total = cost[b, got[matched], js[matched]].sum()
        np.testing.assert_allclose(total, _scipy_total(cost[b], valid[b]), rtol=1e-5)


@pytest.mark.parametrize(("q", "m", "frames"), [(8, 12, 200), (30, 40, 12)])
def test_more_valid_targets_than_queries_reach_scipys_optimum(q, m, frames):
    """Every target valid, M > Q: the Q matched pairs cost what scipy's do. With the fixed
    3e5 dummy cost the potentials' float32 spacing (0.03) left 89 of 200 frames of 8 x 12
    up to 0.07 above the optimum."""
    rng = np.random.default_rng(0)
    cost = rng.random((frames, q, m)).astype(np.float32)
    valid = np.ones((frames, m), bool)
    query_idx = np.asarray(_match(jnp.asarray(cost), jnp.asarray(valid))[0])
    for b in range(frames):
        js = np.flatnonzero(query_idx[b] >= 0)
        assert len(js) == q and len(set(query_idx[b, js])) == q
        total = cost[b].astype(np.float64)[query_idx[b, js], js].sum()
        np.testing.assert_allclose(total, _scipy_total(cost[b], valid[b]), rtol=0, atol=1e-5)


def test_bad_shapes_raise():
    with pytest.raises(ValueError, match="valid must be"):
        match(jnp.zeros((1, 4, 3)), jnp.ones((1, 4), bool))
    with pytest.raises(ValueError, match=r"\[B, Q, M\]"):
        match(jnp.zeros((4, 3)), jnp.ones((1, 3), bool))
