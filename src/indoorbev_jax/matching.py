"""Exact bipartite matching of queries to targets inside ``jax.jit`` (DESIGN section 8).

The solver is ``optax.assignment.hungarian_algorithm``, a pure-JAX exact linear sum
assignment solver (no host callback), so matching runs inside the jitted train step and
vmaps over the batch. This module only prepares its input: padded targets, non-finite
costs, dtype and gradients.

Example::

    cost = jnp.array([[[0.9, 0.1], [0.2, 0.8], [0.5, 0.5]]])  # [B=1, Q=3, M=2]
    valid = jnp.array([[True, True]])
    query_idx, target_idx = match(cost, valid)  # [[1, 0]], [[0, 1]]
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
import optax

# Non-finite costs become +-COST_CAP. The solver adds and subtracts costs to update dual
# potentials: inf - inf would give NaN and an assignment made of garbage, so every entry
# must be finite. Finite costs keep their order: a frame whose costs could sum past the cap
# is scaled down by a power of two (exact in float32, the optimum unchanged), so M finite
# pairs always cost less than one non-finite pair. The loss's costs (each term O(1)-O(100))
# are never scaled, and float32 potentials stay precise (spacing 0.008 at 1e5).
COST_CAP = 1e5

# The solver sees a [M, Q + M] matrix: targets as rows, the Q queries, then M private
# "dummy" columns. A padded target costs the same constant on every query (so it cannot
# change which queries the valid targets get) and less on its own dummy column, which it
# therefore takes at once; valid targets pay _DUMMY_COST > COST_CAP on dummies and never
# take one while a query is free (more valid targets than queries: ``_overflow_cost``).
# Without the dummies a padded target competes with every other for the queries and, all
# its costs tied, walks long augmenting paths: 16 frames of 30 x 30 with 5-15 valid
# targets solve 3.4-4.2x faster with them, full frames 1.4-3x slower (wider matrix;
# docs/BENCHMARKS.md).
_PAD_QUERY_COST = 2.0
_DUMMY_COST = 3.0 * COST_CAP


def clean_cost(cost: jax.Array, valid: jax.Array | None = None) -> jax.Array:
    """The cost with every entry finite, as the solver sees it.

    Args:
      cost: [..., Q, M] matching costs, any float dtype, may hold NaN or +-Inf.
      valid: bool [..., M], which targets are real (None: all); only their finite entries
        set a frame's scale.

    Returns:
      float32 of the same shape: NaN and +Inf become ``COST_CAP`` (a pair to avoid), -Inf
      becomes ``-COST_CAP``. A frame whose largest finite |cost| of a valid target exceeds
      ``COST_CAP / (2 (M + 1))`` has its finite entries divided by the least power of two
      that brings it under that bound; any other frame's are unchanged. So every entry of a
      valid target lies in [-COST_CAP, COST_CAP]; a padded target's finite entries are only
      rescaled with their frame (``match`` ignores them).
    """
    cost = cost.astype(jnp.float32)
    m = cost.shape[-1]
    finite = jnp.isfinite(cost)
    sets_scale = finite if valid is None else finite & valid[..., None, :]
    # initial=0: a frame with no targets (M = 0) has nothing to scale.
    largest = jnp.max(
        jnp.where(sets_scale, jnp.abs(cost), 0.0), axis=(-2, -1), keepdims=True, initial=0.0
    )
    bound = COST_CAP / (2 * (m + 1))
    # log2 rather than largest / bound: no overflow for costs near float32's max.
    exponent = jnp.ceil(jnp.log2(jnp.maximum(largest, bound)) - jnp.log2(bound))
    cost = jnp.where(finite, jnp.ldexp(cost, -exponent.astype(jnp.int32)), cost)
    return jnp.nan_to_num(cost, nan=COST_CAP, posinf=COST_CAP, neginf=-COST_CAP)


def _overflow_cost(cost: jax.Array, valid: jax.Array) -> jax.Array:
    """What a valid target pays on a dummy column, for one frame: cost [Q, M] (clean).

    With at most Q valid targets no valid target ends on a dummy, and the fixed
    ``_DUMMY_COST`` keeps the solver's path (and every training run) as it was. With more,
    n - Q of them must, and the solver's potentials climb to this cost: at 3e5 the float32
    spacing (0.03) swamped O(1) cost differences (an audit: 89 of 200 frames of 8 x 12
    above scipy's optimum). Then the least cost that still makes every augmenting path pay
    is used: raising the matched count by one changes the real costs by at most
    k (hi - lo) + hi for k < n matched targets. A frame holding capped entries keeps
    ``_DUMMY_COST``, which the bound then exceeds.
    """
    q = cost.shape[0]
    n = jnp.sum(valid)
    hi = jnp.max(jnp.where(valid[None], cost, -jnp.inf), initial=0.0)
    lo = jnp.min(jnp.where(valid[None], cost, jnp.inf), initial=0.0)
    tight = (n + 1) * (hi - lo) + jnp.abs(hi) + jnp.abs(lo) + 1.0
    return jnp.where(n > q, jnp.minimum(tight, _DUMMY_COST), _DUMMY_COST)


def _match_one(cost: jax.Array, valid: jax.Array) -> jax.Array:
    """Query index of each target of one frame: cost [Q, M] (clean), valid [M] -> int32 [M]."""
    q, m = cost.shape
    real = jnp.where(valid[:, None], cost.T, _PAD_QUERY_COST)  # [M, Q]
    dummy = jnp.where(valid[:, None], _overflow_cost(cost, valid), 1.0 - jnp.eye(m))  # [M, M]
    rows, cols = optax.assignment.hungarian_algorithm(jnp.concatenate([real, dummy], axis=1))
    # Every row (target) is assigned; the solver lists them in its own order.
    col = jnp.zeros(m, jnp.int32).at[rows].set(cols.astype(jnp.int32))  # [M], dummies >= Q
    # Padded targets sit on dummies: hand them the unused queries in order, so the result
    # stays a set of distinct, in-range query indices.
    used = jnp.zeros(q, bool).at[jnp.where(valid, col, q)].set(True, mode="drop")  # [Q]
    unused = jnp.argsort(used, stable=True).astype(jnp.int32)  # unused queries first
    pad_rank = jnp.cumsum(~valid) - 1  # [M]
    # A valid target on a dummy had no query left (more valid targets than queries): -1.
    col = jnp.where(col < q, col, -1)
    return jnp.where(valid, col, unused[jnp.clip(pad_rank, 0, q - 1)])


def match(cost: jax.Array, valid: jax.Array) -> tuple[jax.Array, jax.Array]:
    """Optimal one-to-one assignment of targets to queries, batched over frames.

    Minimises the summed cost of the valid targets, each getting a distinct query; the total
    equals that of ``scipy.optimize.linear_sum_assignment(cost[b][:, valid[b]])`` (ties may
    pick different indices with the same total). No gradient flows through the result.

    Args:
      cost: [B, Q, M] cost of giving target j to query q. NaN/Inf entries are allowed: they
        are treated as very expensive (see ``clean_cost``), never as an error. Entries of
        padded targets are ignored. A frame that cannot avoid such capped pairs is solved
        up to float32 rounding of the solver's potentials near ``COST_CAP``: an audit saw
        its finite part off scipy's by 1.3e-3 to 5.9e-3 in 4 of 2,240 such frames.
      valid: bool [B, M], which targets are real.

    Returns:
      ``(query_idx, target_idx)``, int32 [B, M] each, sorted by target: ``target_idx[b] =
      0..M-1`` and ``query_idx[b, j]`` is the query matched to target j. Entries of padded
      targets hold leftover queries (distinct while M <= Q) and carry no meaning. M may
      exceed Q: with at most Q valid targets each still gets its query; with more, as in
      scipy, Q of them are matched (least total cost) and the rest get -1.

    Works inside ``jax.shard_map`` (see ``_match_gathered``), ``pmap`` and named ``vmap``.

    Raises:
      ValueError: when shapes disagree.
    """
    cost, valid = jnp.asarray(cost), jnp.asarray(valid)  # nested lists too
    if cost.ndim != 3:
        raise ValueError(f"match: cost must be [B, Q, M], got shape {cost.shape}")
    b, q, m = cost.shape
    if valid.shape != (b, m):
        raise ValueError(
            f"match: valid must be [B, M] = {(b, m)} to fit cost {cost.shape}, got {valid.shape}"
        )
    # The solver's while loops are not reverse-differentiable and the indices are piecewise
    # constant anyway: stopping the gradient here keeps jax.grad of the loss well defined.
    cost = jax.lax.stop_gradient(clean_cost(cost, valid.astype(bool)))
    target_idx = jnp.broadcast_to(jnp.arange(m, dtype=jnp.int32), (b, m))
    if m == 0 or q == 0:  # nothing to match: every target (if any) gets -1
        return jnp.full((b, m), -1, jnp.int32), target_idx
    axes = _varying_axes(cost)
    if axes:  # inside shard_map: see _match_gathered
        query_idx = _match_gathered(cost, valid.astype(bool), axes)
    else:
        query_idx = jax.vmap(_match_one)(cost, valid.astype(bool))  # [B, M]
    return query_idx, target_idx


def _varying_axes(x: jax.Array) -> tuple[str, ...]:
    """The ``shard_map`` mesh axes along which ``x`` differs (empty outside one)."""
    manual = getattr(jax.typeof(x), "manual_axis_type", None)
    return tuple(sorted(getattr(manual, "varying", ()) or ()))


def _match_gathered(cost: jax.Array, valid: jax.Array, axes: tuple[str, ...]) -> jax.Array:
    """``match`` on this shard's frames inside ``shard_map`` (its default ``check_vma``).

    optax's solver starts its loops from fresh zeros, which are the same on every shard, and
    ``shard_map`` refuses a loop whose carry turns shard-dependent. So every shard solves the
    whole batch (a psum of the shards' costs, each at its place: the same on all shards) and
    keeps its own rows; costs are small ([B, Q, M]) next to the step's masks.
    """
    b = cost.shape[0]
    index, size = jax.lax.axis_index(axes), jax.lax.axis_size(axes)

    def gather(x):
        placed = jnp.zeros((size * b,) + x.shape[1:], x.dtype)
        placed = jax.lax.dynamic_update_slice_in_dim(placed, x, index * b, 0)
        return jax.lax.psum(placed, axes)

    every = jax.vmap(_match_one)(gather(cost), gather(valid.astype(jnp.int32)).astype(bool))
    return jax.lax.dynamic_slice_in_dim(every, index * b, b, 0)
