"""AdaptiveUpsampler and SimpleMaskHead: backbone map -> per-query classes, boxes and masks.

DESIGN section 7. The upsampler brings the last Swin stage back to H x W with learned 2x
steps (a dense layer + depth-to-space: the same map as a kernel-2 stride-2 transposed
convolution, whose backward is pathologically slow on CPU). The head projects to C_hid
(``F_proj``), refines N_q learned queries with post-norm decoder layers (self-attention,
cross-attention to ``F_proj`` + a 2D sine code, FFN) and reads every layer's queries out
into class logits, dims, pos, yaw and mask logits ``<m_j, F_proj>``.
"""

from __future__ import annotations

import math

import flax.linen as nn
import jax
import jax.numpy as jnp
import numpy as np

from indoorbev_jax.config import GridConfig, HeadConfig
from indoorbev_jax.geometry import cell_centers
from indoorbev_jax.models.layers import Dense

# Initial foreground probability of the seed head (RetinaNet's prior).
_SEED_PRIOR = 0.01
# Initial mask-prior scale softplus(-2) = 0.13 per m^2: about -1.2 logits at 3 m.
_PRIOR_BIAS = -2.0


def depth_to_space(x: jax.Array, s: int) -> jax.Array:
    """[B, R, R, s*s*C] -> [B, s*R, s*R, C], channel blocks ordered (row offset, col offset)."""
    b, h, w, c = x.shape
    c //= s * s
    x = x.reshape(b, h, w, s, s, c)  # [B, R, R, s_row, s_col, C]
    x = x.transpose(0, 1, 3, 2, 4, 5)  # [B, R, s_row, R, s_col, C]
    return x.reshape(b, h * s, w * s, c)


class AdaptiveUpsampler(nn.Module):
    """Learned 2x steps from the last backbone stage to the padded input resolution.

    Each step: Dense(4 C') + depth-to-space + GELU, channels halved (never below
    ``min_channels``). With ``skips`` (FPN-style), a stage map of the same resolution is
    added through a lateral Dense after each step.

    Attributes:
      steps: number of 2x steps (log2 of the backbone's total stride).
      min_channels: channel floor (C_hid).
      skips: add lateral connections from earlier stages.
      dtype: computation dtype.
      remat: recompute each step in the backward pass (``jax.checkpoint``), keeping only
        its input.
    """

    steps: int
    min_channels: int
    skips: bool = False
    dtype: jnp.dtype = jnp.float32
    remat: bool = False

    @nn.compact
    def __call__(self, stages: dict[int, jax.Array], bev: jax.Array | None = None) -> jax.Array:
        """Upsample.

        Args:
          stages: stage index -> [B, R_k, R_k, C_k] from ``SwinBackbone``.
          bev: the encoder map padded to [B, R, R, C_enc]; with ``skips`` it is added
            through a lateral Dense at the last step when no stage has the full resolution
            (backbones whose first stride is 2), so masks see the 1-cell detail.

        Returns:
          [B, R, R, C'] at the padded input resolution R.
        """
        last = max(stages)
        x = stages[last]
        by_res = {v.shape[1]: (k, v) for k, v in stages.items() if k != last}
        for i in range(self.steps):
            c = max(x.shape[-1] // 2, self.min_channels)

            def step(mdl: AdaptiveUpsampler, x: jax.Array, i=i, c=c) -> jax.Array:
                x = Dense(4 * c, dtype=mdl.dtype, name=f"up{i}")(x)
                return nn.gelu(depth_to_space(x, 2))  # [B, 2R, 2R, C']

            # The function form of remat keeps the parameter names (up{i}).
            x = (nn.remat(step) if self.remat else step)(self, x)
            if self.skips and x.shape[1] in by_res:
                k, skip = by_res[x.shape[1]]
                x = x + Dense(c, dtype=self.dtype, name=f"lateral{k}")(skip)
        full_res = x.shape[1]
        if self.skips and bev is not None and bev.shape[1] == full_res and full_res not in by_res:
            x = x + Dense(x.shape[-1], dtype=self.dtype, name="lateral_bev")(bev)
        return x


def sine_code_1d(n: int, features: int, temperature: float = 10000.0) -> np.ndarray:
    """DETR's normalised sine code along one axis: float32 [n, features].

    Position p in 0..n-1 maps to (p + 1) / n * 2 pi; channels alternate sin / cos with
    geometric frequencies.
    """
    pos = (np.arange(n, dtype=np.float64) + 1.0) / n * 2.0 * math.pi
    dim_t = temperature ** (2 * (np.arange(features) // 2) / features)
    arg = pos[:, None] / dim_t  # [n, features]
    code = np.where(np.arange(features) % 2 == 0, np.sin(arg), np.cos(arg))
    return code.astype(np.float32)


def _pool_weights(n: int, s: int) -> np.ndarray:
    """[ceil(n/s), n]: row k averages cells [k s, min((k+1) s, n))."""
    m = -(-n // s)
    w = np.zeros((m, n), np.float32)
    for k in range(m):
        cells = np.arange(k * s, min((k + 1) * s, n))
        w[k, cells] = 1.0 / len(cells)
    return w


def pool_memory(f: jax.Array, s: int) -> jax.Array:
    """s x s average pooling of [B, H, W, C] -> [B, ceil(H/s), ceil(W/s), C] (ragged edges
    average over the cells they hold)."""
    if s == 1:
        return f
    b, h, w, c = f.shape
    hp, wp = -(-h // s) * s, -(-w // s) * s
    f = jnp.pad(f, ((0, 0), (0, hp - h), (0, wp - w), (0, 0)))
    f = f.reshape(b, hp // s, s, wp // s, s, c).sum(axis=(2, 4))  # [B, H/s, W/s, C]
    count = np.outer(
        np.minimum(s, h - s * np.arange(hp // s)), np.minimum(s, w - s * np.arange(wp // s))
    )
    return f / jnp.asarray(count[None, :, :, None], f.dtype)


def positional_code(h: int, w: int, features: int, s: int = 1) -> tuple[np.ndarray, np.ndarray]:
    """Separable 2D sine code of an (s-pooled) H x W map.

    Returns:
      ``(code_y, code_x)`` of shapes [H', features/2] and [W', features/2]; the code of cell
      (i, j) is ``concat(code_y[i], code_x[j])`` (y half first, as in DETR). With s > 1 each
      half is averaged over the pooled cells, like the features.
    """
    half = features // 2
    cy, cx = sine_code_1d(h, half), sine_code_1d(w, half)
    if s > 1:
        cy, cx = _pool_weights(h, s) @ cy, _pool_weights(w, s) @ cx
    return cy, cx


def code_map(code_y: np.ndarray, code_x: np.ndarray, dtype) -> jax.Array:
    """[H', W', C] map of the separable code from ``positional_code`` (y half first)."""
    hm, wm, half = len(code_y), len(code_x), code_y.shape[-1]
    return jnp.concatenate(
        [
            jnp.broadcast_to(jnp.asarray(code_y, dtype)[:, None, :], (hm, wm, half)),
            jnp.broadcast_to(jnp.asarray(code_x, dtype)[None, :, :], (hm, wm, half)),
        ],
        axis=-1,
    )


class KeysMajorDense(nn.Dense):
    """``nn.Dense`` (same parameters) whose output comes as [B, heads, d, T] from a [B, T, C]
    input: the product is taken as kernel^T x^T, so the keys come out token-minor with no
    transpose of the [B, T, C] map (a d = 8 strided copy over 250k tokens per decoder layer
    in the ``paper`` preset).
    """

    heads: int = 1

    @nn.compact
    def __call__(self, inputs: jax.Array) -> jax.Array:
        b, t, c_in = inputs.shape
        kernel = self.param("kernel", self.kernel_init, (c_in, self.features), self.param_dtype)
        bias = self.param("bias", self.bias_init, (self.features,), self.param_dtype)
        x, kernel, bias = nn.dtypes.promote_dtype(inputs, kernel, bias, dtype=self.dtype)
        y = jax.lax.dot_general(kernel, x.reshape(b * t, c_in), (((0,), (1,)), ((), ())))
        # [heads * d, B * T] -> [h, d, B, T]
        y = (y + bias[:, None]).reshape(self.heads, self.features // self.heads, b, t)
        return y.transpose(2, 0, 1, 3)  # [B, h, d, T]


class Attention(nn.Module):
    """Multi-head attention with separate query / key / value inputs.

    Attributes:
      num_heads: heads h.
      dtype: computation dtype.
    """

    num_heads: int
    dtype: jnp.dtype = jnp.float32

    @nn.compact
    def __call__(
        self,
        q_in: jax.Array,
        k_in: jax.Array,
        v_in: jax.Array,
        key_ok: np.ndarray | jax.Array | None = None,
    ) -> jax.Array:
        """Attend.

        Args:
          q_in: [B, Tq, C] queries.
          k_in, v_in: [B, Tk, C] keys and values; or, with ``key_ok``, the same split into
            chunks, [N, B, Tc, C] from ``chunk_memory``.
          key_ok: None, or bool [N, Tc]: which chunk slots hold a real token; the chunks are
            then streamed through an online softmax (``_attend_chunk``).

        Returns:
          [B, Tq, C].
        """
        b, tq, c = q_in.shape
        h, d = self.num_heads, c // self.num_heads
        q = Dense(c, dtype=self.dtype, name="q")(q_in * d**-0.5)
        if key_ok is not None:
            q = q.reshape(b, tq, h, d).transpose(0, 2, 1, 3)  # [B, h, Tq, d]
            scan = nn.scan(
                nn.remat(_attend_chunk, prevent_cse=False),  # CSE is safe inside a scan
                variable_broadcast="params",
                split_rngs={"params": False},
                in_axes=(0, 0, 0, nn.broadcast),
            )
            init = (
                jnp.full((b, h, tq), -jnp.inf, jnp.float32),  # running max of the logits
                jnp.zeros((b, h, tq), jnp.float32),  # running softmax denominator
                jnp.zeros((b, h, tq, d), jnp.float32),  # running weighted sum of values
            )
            (_, den, acc), _ = scan(self, init, k_in, v_in, key_ok, q)
            out = (acc / den[..., None]).astype(self.dtype)  # [B, h, Tq, d]
            out = out.transpose(0, 2, 1, 3).reshape(b, tq, c)  # [B, Tq, h * d]
            return Dense(c, dtype=self.dtype, name="out")(out)
        # Heads-major layouts with keys as [B, h, d, Tk]: with few queries, long memories
        # and d = 8, this runs the CPU train step about 2x faster than
        # jax.nn.dot_product_attention's [B, T, h, d] (measured in experiments/bench_model.py).
        k = KeysMajorDense(c, heads=h, dtype=self.dtype, name="k")(k_in)  # [B, h, d, Tk]
        v = Dense(c, dtype=self.dtype, name="v")(v_in)
        q = q.reshape(b, tq, h, d).transpose(0, 2, 1, 3)  # [B, h, Tq, d]
        v = v.reshape(b, -1, h, d).transpose(0, 2, 1, 3)  # [B, h, Tk, d]
        out = softmax_attention(q, k, v).transpose(0, 2, 1, 3).reshape(b, tq, c)  # [B, Tq, C]
        return Dense(c, dtype=self.dtype, name="out")(out)


def _softmax_attention_fwd(q: jax.Array, k: jax.Array, v: jax.Array):
    logits = jnp.einsum("bhqd,bhdk->bhqk", q, k).astype(jnp.float32)  # [B, h, Tq, Tk]
    p = jax.nn.softmax(logits, axis=-1).astype(q.dtype)
    out = jnp.einsum("bhqk,bhkd->bhqd", p, v)
    return out, (q, k, v, p, out)


def _softmax_attention_bwd(res, g: jax.Array):
    q, k, v, p, out = res
    f32 = jnp.float32
    dv = jnp.einsum("bhqk,bhqd->bhkd", p, g)
    dp = jnp.einsum("bhqd,bhkd->bhqk", g, v).astype(f32)
    # sum_k p_qk dp_qk = <g_q, out_q>: a d-long dot instead of autodiff's Tk-long reduction
    # of the softmax backward, which dominated the cross-attention backward over 250k
    # memory tokens (docs/BENCHMARKS.md, "An Intel Xeon VM, and the cross-attention backward").
    delta = jnp.sum(g.astype(f32) * out.astype(f32), axis=-1, keepdims=True)
    ds = (p.astype(f32) * (dp - delta)).astype(q.dtype)
    dq = jnp.einsum("bhqk,bhdk->bhqd", ds, k)
    dk = jnp.einsum("bhqd,bhqk->bhdk", q, ds)
    return dq, dk, dv


@jax.custom_vjp
def softmax_attention(q: jax.Array, k: jax.Array, v: jax.Array) -> jax.Array:
    """softmax(q k) v per head, with a hand-written backward (same gradients as autodiff).

    Args:
      q: [B, h, Tq, d] scaled queries.
      k: [B, h, d, Tk] keys.
      v: [B, h, Tk, d] values.

    Returns:
      [B, h, Tq, d]; logits and softmax in float32, products in q's dtype.
    """
    return _softmax_attention_fwd(q, k, v)[0]


softmax_attention.defvjp(_softmax_attention_fwd, _softmax_attention_bwd)


def _attend_chunk(attn: Attention, carry, k_in, v_in, key_ok, q):
    """Scan body of the streamed ``Attention``: one memory chunk of an online softmax
    (flash-attention style), with the module's own ``k`` / ``v`` projections.

    Args:
      attn: the bound ``Attention``.
      carry: ``(m, den, acc)``: running max [B, h, Tq], softmax denominator [B, h, Tq] and
        unnormalised output [B, h, Tq, d], all float32.
      k_in, v_in: [B, Tc, C] this chunk's keys and values.
      key_ok: bool [Tc], False on padding slots.
      q: [B, h, Tq, d] scaled, projected queries.

    Returns:
      ``(carry, None)`` with the carry updated by this chunk.
    """
    m, den, acc = carry
    b, tc, c = k_in.shape
    h, d = attn.num_heads, c // attn.num_heads
    k = KeysMajorDense(c, heads=h, dtype=attn.dtype, name="k")(k_in)  # [B, h, d, Tc]
    v = Dense(c, dtype=attn.dtype, name="v")(v_in)
    v = v.reshape(b, tc, h, d).transpose(0, 2, 1, 3)  # [B, h, Tc, d]
    logits = jnp.einsum("bhqd,bhdk->bhqk", q, k).astype(jnp.float32)  # [B, h, Tq, Tc]
    logits = jnp.where(key_ok, logits, -jnp.inf)
    # The result does not depend on the stabilising max, so no gradient flows through it.
    # Every chunk holds a real token (padding < chunk), so m_new is finite after chunk 1.
    m_new = jax.lax.stop_gradient(jnp.maximum(m, logits.max(-1)))  # [B, h, Tq]
    p = jnp.exp(logits - m_new[..., None])  # [B, h, Tq, Tc]
    scale = jnp.exp(m - m_new)  # [B, h, Tq], 0 on the first chunk
    den = den * scale + p.sum(-1)
    pv = jnp.einsum("bhqk,bhkd->bhqd", p.astype(attn.dtype), v).astype(jnp.float32)
    return (m_new, den, acc * scale[..., None] + pv), None


def peak_cells(score: jax.Array, k: int) -> jax.Array:
    """The k best local peaks of a score map, best first.

    Args:
      score: [B, H, W] finite scores of any range (the seed head's logits).
      k: cells to pick, at most H * W.

    Returns:
      int32 [B, k] flat cell indices (row * W + col). Cells that equal the maximum of their
      3 x 3 neighbourhood come first, by score; if a map has fewer than k of them, the best
      remaining cells fill the rest.
    """
    b, h, w = score.shape
    peak = jax.lax.reduce_window(score, -jnp.inf, jax.lax.max, (1, 3, 3), (1, 1, 1), "SAME")
    # Non-peaks drop below every peak of their map, whatever the scores' range (a fixed
    # offset of 2 assumed probabilities; logits put a strong object's ring before weaker
    # objects' peaks, and every query on one object).
    span = score.max(axis=(1, 2), keepdims=True) - score.min(axis=(1, 2), keepdims=True) + 1.0
    rank = jnp.where(score >= peak, score, score - span).reshape(b, h * w)
    return jax.lax.top_k(rank, k)[1]


def chunk_memory(mem: jax.Array, chunk: int) -> tuple[jax.Array, np.ndarray]:
    """Split a memory into equal chunks for the streamed ``Attention``.

    Args:
      mem: [B, S, C].
      chunk: tokens per chunk Tc; S is zero-padded up to a multiple of it.

    Returns:
      ``(chunks, key_ok)``: [N, B, Tc, C] with N = ceil(S / Tc), and bool [N, Tc], False on
      the padding slots (all in the last chunk, which keeps at least one real token).
    """
    b, n_tok, c = mem.shape
    n = -(-n_tok // chunk)
    mem = jnp.pad(mem, ((0, 0), (0, n * chunk - n_tok), (0, 0)))
    chunks = mem.reshape(b, n, chunk, c).transpose(1, 0, 2, 3)  # [N, B, Tc, C]
    return chunks, (np.arange(n * chunk) < n_tok).reshape(n, chunk)


class DecoderLayer(nn.Module):
    """Post-norm DETR decoder layer: self-attention, cross-attention (keys carry the
    positional code), FFN.

    Attributes:
      config: head fields (heads, FFN width, remat).
      dtype: computation dtype.
    """

    config: HeadConfig
    dtype: jnp.dtype = jnp.float32

    @nn.compact
    def __call__(
        self,
        t: jax.Array,
        mem: jax.Array,
        mem_pos: jax.Array,
        key_ok: np.ndarray | None = None,
    ) -> jax.Array:
        """Refine the queries.

        Args:
          t: [B, Q, C] queries.
          mem, mem_pos: [B, S, C] memory and memory + code; or, with ``key_ok``, both as
            [N, B, Tc, C] chunks from ``chunk_memory`` (streamed cross-attention).
          key_ok: None, or bool [N, Tc] from ``chunk_memory``.

        Returns:
          [B, Q, C].
        """
        cfg = self.config
        # Remat the cross-attention: its scores over S memory tokens ([B, h, Q, S]) and the
        # key / value projections ([B, S, C]) dominate the training peak; recomputing them in
        # the backward pass keeps only one layer's worth alive at a time.
        cross_cls = nn.remat(Attention) if cfg.remat else Attention
        t = nn.LayerNorm(dtype=self.dtype, name="norm1")(
            t + Attention(cfg.num_heads, self.dtype, name="self_attn")(t, t, t)
        )
        t = nn.LayerNorm(dtype=self.dtype, name="norm2")(
            t + cross_cls(cfg.num_heads, self.dtype, name="cross_attn")(t, mem_pos, mem, key_ok)
        )
        y = Dense(cfg.ffn_dim, dtype=self.dtype, name="ffn1")(t)
        y = Dense(t.shape[-1], dtype=self.dtype, name="ffn2")(nn.relu(y))
        return nn.LayerNorm(dtype=self.dtype, name="norm3")(t + y)


class SimpleMaskHead(nn.Module):
    """Query-based decoder head with class, box and mask outputs for every decoder layer.

    Attributes:
      config: head fields.
      num_classes: foreground classes (logits get one more, the background).
      dtype: computation dtype.
      grid: the BEV grid (cell centres in metres); needed by ``query_init="select"``
        (anchors) and ``mask_prior``.
    """

    config: HeadConfig
    num_classes: int
    dtype: jnp.dtype = jnp.float32
    grid: GridConfig | None = None

    @nn.compact
    def __call__(self, feats: jax.Array) -> dict[str, jax.Array]:
        """Decode.

        Args:
          feats: upsampled features [B, H, W, C'] on the unpadded grid.

        Returns:
          dict with logits [L, B, Q, K], dims [L, B, Q, 3], pos [L, B, Q, 3],
          yaw [L, B, Q, 1], masks [L, B, Q, H, W] (mask logits).
        """
        cfg = self.config
        c, s = cfg.hidden_dim, cfg.memory_stride
        b, h, w, _ = feats.shape

        def project(mdl: SimpleMaskHead, feats: jax.Array) -> jax.Array:
            f = Dense(c, dtype=mdl.dtype, name="input_proj")(feats)
            return nn.LayerNorm(dtype=mdl.dtype, name="input_proj_norm")(f)  # [B, H, W, C]

        # With remat, the full-resolution LayerNorm's residuals are recomputed, not kept.
        f_proj = (nn.remat(project) if cfg.remat else project)(self, feats)

        # Cross-attention memory: F_proj itself (paper) or its s x s average (memory_stride).
        mem = pool_memory(f_proj, s)  # [B, H', W', C]
        hm, wm = mem.shape[1:3]
        code = code_map(*positional_code(h, w, c, s), self.dtype)  # [H', W', C]
        mem_pos = (mem + code).reshape(b, hm * wm, c)  # [B, S, C]
        mem = mem.reshape(b, hm * wm, c)  # [B, S, C]
        key_ok = None
        if 0 < cfg.attention_chunk < hm * wm:
            # Chunked once here, shared by every decoder layer.
            mem, key_ok = chunk_memory(mem, cfg.attention_chunk)  # [N, B, Tc, C], [N, Tc]
            mem_pos, _ = chunk_memory(mem_pos, cfg.attention_chunk)

        needs_grid = cfg.query_init == "select" or cfg.mask_prior
        if needs_grid and self.grid is None:
            raise ValueError("SimpleMaskHead needs `grid` for query_init='select' / mask_prior")
        if needs_grid:
            xs, ys = cell_centers(self.grid)  # [W], [H] metres
        anchor = None
        if cfg.query_init == "select":
            t, cells = self._select_queries(f_proj)  # [B, Q, C], [B, Q]
            # Box centres are predicted as offsets from the selected cells.
            anchor_x, anchor_y = xs[cells % w], ys[cells // w]  # [B, Q] each
            anchor = jnp.stack([anchor_x, anchor_y, jnp.zeros_like(anchor_x)], -1)  # float32
        else:
            query = self.param(
                "query_embed", nn.initializers.normal(1.0), (cfg.num_queries, c), jnp.float32
            )
            t = jnp.broadcast_to(query.astype(self.dtype), (b, cfg.num_queries, c))
            if cfg.semantic_head:
                self._seed_logits(f_proj)  # trained by the seed loss only
        outs = []
        for i in range(cfg.num_layers):
            t = DecoderLayer(cfg, self.dtype, name=f"decoder{i}")(t, mem, mem_pos, key_ok)
            outs.append(t)
        q = jnp.stack(outs)  # [L, B, Q, C]

        m = nn.relu(Dense(c, dtype=self.dtype, name="mask_embed0")(q))
        m = nn.relu(Dense(c, dtype=self.dtype, name="mask_embed1")(m))
        m = Dense(c, dtype=self.dtype, name="mask_embed2")(m)  # [L, B, Q, C]
        # As one batched [L*Q, C] @ [C, H*W] product per frame: 2-3x faster on CPU than the
        # plain "lbqc,bhwc->lbqhw" einsum, whose layouts XLA resolves with extra transposes.
        n_l, n_q = m.shape[0], m.shape[2]
        m = m.transpose(1, 0, 2, 3).reshape(b, n_l * n_q, c)  # [B, L*Q, C]
        pixels = f_proj
        if cfg.mask_positional:
            pixels = pixels + code_map(*positional_code(h, w, c), self.dtype)  # [H, W, C]
        masks = jnp.einsum("bkc,bcn->bkn", m, pixels.reshape(b, h * w, c).transpose(0, 2, 1))
        masks = masks.reshape(b, n_l, n_q, h, w).transpose(1, 0, 2, 3, 4)  # [L, B, Q, H, W]
        # The small output heads run in float32 whatever self.dtype: in bfloat16 a position
        # near 4.5 m would snap to a 3 cm lattice (1.5 cells of the paper grid).
        qf = q.astype(jnp.float32)
        pos = Dense(3, dtype=jnp.float32, name="pos_head")(qf)  # [L, B, Q, 3]
        if anchor is not None:
            pos = pos + anchor
        if cfg.mask_prior:
            # log-prior -a_j |p - c_j|^2 around the query's own predicted centre c_j, so a
            # mask need not tell look-alike objects apart from features alone.
            a = nn.softplus(
                Dense(1, dtype=self.dtype, name="prior_scale",
                      bias_init=nn.initializers.constant(_PRIOR_BIAS))(q)
            )  # fmt: skip  # [L, B, Q, 1]
            centre = pos.astype(self.dtype)  # masks stay in self.dtype
            dx = xs.astype(self.dtype) - centre[..., 0:1]  # [L, B, Q, W]
            dy = ys.astype(self.dtype) - centre[..., 1:2]  # [L, B, Q, H]
            masks = masks - a[..., None] * (dy[..., :, None] ** 2 + dx[..., None, :] ** 2)
        q_cls = q
        if cfg.mask_pooled_class:
            # Mean of F_proj under each query's own mask (weights without gradient, so the
            # class loss does not shape the masks): the class reads the object it outlines.
            # [L, B, Q, H, W] -> [L, B, Q, H * W]
            weight = jax.lax.stop_gradient(jax.nn.sigmoid(masks)).reshape(n_l, b, n_q, h * w)
            pooled = jnp.einsum("lbqn,bnc->lbqc", weight, f_proj.reshape(b, h * w, c))
            pooled = pooled / (weight.sum(-1, keepdims=True) + 1.0)  # [L, B, Q, C]
            q_cls = q + Dense(c, dtype=self.dtype, name="pooled_proj")(pooled)
        out = {
            "logits": Dense(self.num_classes + 1, dtype=jnp.float32, name="class_head")(
                q_cls.astype(jnp.float32)
            ),
            "dims": Dense(3, dtype=jnp.float32, name="dims_head")(qf),
            "pos": pos,
            "yaw": Dense(1, dtype=jnp.float32, name="yaw_head")(qf),
            "masks": masks,
        }
        return {k: v.astype(jnp.float32) for k, v in out.items()}

    def _seed_logits(self, f_proj: jax.Array) -> jax.Array:
        """Dense class logits [B, H, W, K] (``seed_head``, RetinaNet prior init), sown as
        ``intermediates/seeds`` for ``losses.seed_loss``."""
        prior = -math.log((1 - _SEED_PRIOR) / _SEED_PRIOR)
        seeds = Dense(
            self.num_classes, dtype=self.dtype, name="seed_head",
            bias_init=nn.initializers.constant(prior),
        )(f_proj).astype(jnp.float32)  # fmt: skip
        self.sow("intermediates", "seeds", seeds)
        return seeds

    def _select_queries(self, f_proj: jax.Array) -> tuple[jax.Array, jax.Array]:
        """Two-stage query init (``query_init="select"``): queries from the top local peaks
        of a dense class head.

        The seed logits [B, H, W, K] are sown as ``intermediates/seeds`` for the seed loss
        (``losses.seed_loss``). A cell is a candidate when its best class score is the
        maximum of its 3 x 3 neighbourhood, so one object does not take every query; the
        selection itself carries no gradient, the gathered features do.

        Returns:
          ``(queries, cells)``: [B, Q, C] initial queries, LayerNorm(Dense(feature) +
          Dense(sine code)), and int32 [B, Q] the selected cells (row * W + col).
        """
        cfg = self.config
        b, h, w, c = f_proj.shape
        seeds = self._seed_logits(f_proj)  # [B, H, W, K]
        cells = peak_cells(jax.lax.stop_gradient(seeds.max(-1)), cfg.num_queries)  # [B, Q]
        feat = jnp.take_along_axis(f_proj.reshape(b, h * w, c), cells[..., None], axis=1)
        code = code_map(*positional_code(h, w, c), self.dtype).reshape(h * w, c)[cells]
        t = Dense(c, dtype=self.dtype, name="query_content")(feat)
        t = t + Dense(c, dtype=self.dtype, name="query_pos")(code)
        return nn.LayerNorm(dtype=self.dtype, name="query_norm")(t), cells  # [B, Q, C], [B, Q]
