"""Swin window-attention backbone over the BEV map (DESIGN section 6).

The grid is padded once to a multiple of ``window_size * total_stride`` so every stage tiles
into whole windows; padded cells are masked out as attention keys and zeroed before each
patch merging, so valid cells never see them. Window masks and relative-position indices
are static numpy arrays computed once per shape.
"""

from __future__ import annotations

import flax.linen as nn
import jax
import jax.numpy as jnp
import numpy as np

from indoorbev_jax.config import BackboneConfig
from indoorbev_jax.models.layers import Dense

# Added to masked attention logits. Finite (not -inf) so that a window made only of
# padding still gives a finite softmax; its outputs are never read.
_MASKED = -1e9


def window_partition(x: jax.Array, ws: int) -> jax.Array:
    """Split a map into non-overlapping windows.

    Args:
      x: [B, H, W, C] with H and W multiples of ``ws``.
      ws: window size.

    Returns:
      [B, nW, ws*ws, C], windows in row-major order, tokens row-major inside a window.
    """
    b, h, w, c = x.shape
    x = x.reshape(b, h // ws, ws, w // ws, ws, c)  # [B, h', ws, w', ws, C]
    x = x.transpose(0, 1, 3, 2, 4, 5)  # [B, h', w', ws, ws, C]
    return x.reshape(b, (h // ws) * (w // ws), ws * ws, c)


def window_reverse(x: jax.Array, ws: int, h: int, w: int) -> jax.Array:
    """Inverse of ``window_partition``: [B, nW, ws*ws, C] -> [B, H, W, C]."""
    b, _, _, c = x.shape
    x = x.reshape(b, h // ws, w // ws, ws, ws, c)  # [B, h', w', ws, ws, C]
    x = x.transpose(0, 1, 3, 2, 4, 5)  # [B, h', ws, w', ws, C]
    return x.reshape(b, h, w, c)


def space_to_depth(x: jax.Array, s: int) -> jax.Array:
    """Concatenate s x s neighbours: [B, H, W, C] -> [B, H/s, W/s, s*s*C].

    For s = 2 the channel order is Swin's patch-merging order
    (x[0::2, 0::2], x[1::2, 0::2], x[0::2, 1::2], x[1::2, 1::2]): column offset major,
    row offset minor.
    """
    if s == 1:
        return x
    b, h, w, c = x.shape
    x = x.reshape(b, h // s, s, w // s, s, c)  # [B, H/s, s_row, W/s, s_col, C]
    x = x.transpose(0, 1, 3, 4, 2, 5)  # [B, H/s, W/s, s_col, s_row, C]
    return x.reshape(b, h // s, w // s, s * s * c)


def relative_position_index(ws: int) -> np.ndarray:
    """int32 [ws*ws, ws*ws]: row of the (2ws-1)^2 bias table for each (query, key) pair."""
    coords = np.stack(np.meshgrid(np.arange(ws), np.arange(ws), indexing="ij")).reshape(2, -1)
    rel = coords[:, :, None] - coords[:, None, :] + (ws - 1)  # [2, T, T] in 0..2ws-2
    return (rel[0] * (2 * ws - 1) + rel[1]).astype(np.int32)


def _pair(x) -> tuple[int, int]:
    """(rows, cols) of a side given as one int (a square map) or as a pair."""
    return (int(x), int(x)) if np.ndim(x) == 0 else (int(x[0]), int(x[1]))


def window_masks(res, valid, ws: int, shift: int) -> tuple[np.ndarray, np.ndarray]:
    """Static inputs of the attention mask of one block, in the rolled frame.

    Args:
      res: padded size of the map: one int (square) or (rows, cols).
      valid: cells [0, valid) along each axis hold data (an int or a pair); the rest is
        padding.
      ws: window size.
      shift: cyclic shift (0 for W-MSA).

    Returns:
      ``(region, key_ok)``, both [nW, ws*ws]: a token may attend to a key of its window when
      their region ids match (tokens wrapped around by the shift form separate regions, as in
      Swin) and the key is not padding.
    """
    (rh, rw), (vh, vw) = _pair(res), _pair(valid)
    region = np.zeros((rh, rw), np.int32)
    if shift:

        def cuts(r):
            return slice(0, r - ws), slice(r - ws, r - shift), slice(r - shift, r)

        for a, rows in enumerate(cuts(rh)):
            for c, cols in enumerate(cuts(rw)):
                region[rows, cols] = 3 * a + c
    ok = np.zeros((rh, rw), bool)
    ok[:vh, :vw] = True
    ok = np.roll(ok, (-shift, -shift), axis=(0, 1))

    def part(a: np.ndarray) -> np.ndarray:
        a = a.reshape(rh // ws, ws, rw // ws, ws).transpose(0, 2, 1, 3)  # [h', w', ws, ws]
        return a.reshape(-1, ws * ws)

    return part(region), part(ok)


class WindowAttention(nn.Module):
    """Multi-head self-attention inside windows, with a relative position bias per head.

    Attributes:
      dim: channels C.
      num_heads: heads h.
      window_size: ws.
      dtype: computation dtype.
    """

    dim: int
    num_heads: int
    window_size: int
    dtype: jnp.dtype = jnp.float32

    @nn.compact
    def __call__(self, x: jax.Array, region: np.ndarray | None, key_ok: np.ndarray | None):
        """Attend.

        Args:
          x: [B, nW, T, C] window tokens, T = ws * ws.
          region, key_ok: static [nW, T] from ``window_masks``, or None for no mask.

        Returns:
          [B, nW, T, C].
        """
        b, nw, t, c = x.shape
        h = self.num_heads
        d = c // h
        qkv = Dense(3 * c, dtype=self.dtype, name="qkv")(x)
        qkv = qkv.reshape(b, nw, t, 3, h, d)  # [B, nW, T, 3, h, d]
        q, k, v = qkv[..., 0, :, :], qkv[..., 1, :, :], qkv[..., 2, :, :]  # [B, nW, T, h, d]
        logits = jnp.einsum("bwqhd,bwkhd->bwhqk", q * d**-0.5, k)  # [B, nW, h, T, T]

        ws = self.window_size
        table = self.param(
            "relative_position_bias",
            nn.initializers.truncated_normal(0.02),
            ((2 * ws - 1) ** 2, h),
            jnp.float32,  # float32 under jax_enable_x64 too: checkpoints keep one layout
        )
        idx = relative_position_index(ws).reshape(-1)
        bias = jnp.take(table, idx, axis=0).reshape(t, t, h).transpose(2, 0, 1)  # [h, T, T]
        logits = logits.astype(jnp.float32) + bias
        if region is not None:
            allowed = (region[:, :, None] == region[:, None, :]) & key_ok[:, None, :]  # [nW,T,T]
            logits = jnp.where(allowed[None, :, None], logits, _MASKED)
        weights = jax.nn.softmax(logits, axis=-1).astype(self.dtype)  # [B, nW, h, T, T]
        self.sow("intermediates", "attention_weights", weights)
        out = jnp.einsum("bwhqk,bwkhd->bwqhd", weights, v).reshape(b, nw, t, c)  # [B, nW, T, C]
        return Dense(c, dtype=self.dtype, name="proj")(out)


class SwinBlock(nn.Module):
    """Pre-norm Swin block: (S)W-MSA + residual, MLP + residual.

    Attributes:
      dim, num_heads, window_size: as in ``WindowAttention``.
      shift: cyclic shift of the windows (0: W-MSA, > 0: SW-MSA).
      valid: cells [0, valid) along each axis of this stage's map hold data: an int, or
        (rows, cols) for a map that is not square.
      mlp_ratio: hidden width of the MLP relative to ``dim``.
      dtype: computation dtype.
      chunk_windows: 0, or run the block over groups of this many windows, each group under
        ``jax.checkpoint`` (see ``_chunked``); used when the map has more windows than that.
    """

    dim: int
    num_heads: int
    window_size: int
    shift: int
    valid: int | tuple[int, int]
    mlp_ratio: float = 2.0
    dtype: jnp.dtype = jnp.float32
    chunk_windows: int = 0

    @nn.compact
    def __call__(self, x: jax.Array) -> jax.Array:
        """[B, R, R', C] -> [B, R, R', C] on the padded map."""
        b, rh, rw, c = x.shape
        ws, s = self.window_size, self.shift
        if 0 < self.chunk_windows < (rh // ws) * (rw // ws):
            return self._chunked(x)
        y = nn.LayerNorm(dtype=self.dtype, name="norm1")(x)
        if s:
            y = jnp.roll(y, (-s, -s), axis=(1, 2))
        vh, vw = _pair(self.valid)
        masked = s > 0 or vh < rh or vw < rw
        region, key_ok = window_masks((rh, rw), (vh, vw), ws, s) if masked else (None, None)
        y = WindowAttention(c, self.num_heads, ws, self.dtype, name="attn")(
            window_partition(y, ws), region, key_ok
        )
        y = window_reverse(y, ws, rh, rw)  # [B, R, R', C]
        if s:
            y = jnp.roll(y, (s, s), axis=(1, 2))
        x = x + y
        y = nn.LayerNorm(dtype=self.dtype, name="norm2")(x)
        y = Dense(int(c * self.mlp_ratio), dtype=self.dtype, name="fc1")(y)
        y = Dense(c, dtype=self.dtype, name="fc2")(nn.gelu(y))
        return x + y

    def _chunked(self, x: jax.Array) -> jax.Array:
        """The same block, memory-lean: in the rolled frame every op is window-local
        (attention) or per token (LayerNorm, MLP, residuals), so the block runs as a scan over
        groups of ``chunk_windows`` windows with each group checkpointed. The backward pass
        then holds one group's attention scores and MLP activations at a time instead of the
        whole map's. Window counts that ``chunk_windows`` does not divide get padding windows
        (no valid key), cut off again after the scan.
        """
        b, rh, rw, c = x.shape
        ws, s, n = self.window_size, self.shift, self.chunk_windows
        if s:
            x = jnp.roll(x, (-s, -s), axis=(1, 2))
        x = window_partition(x, ws)  # [B, nW, T, C]
        nw, t = x.shape[1], x.shape[2]
        nc = -(-nw // n)
        pad = nc * n - nw
        x = jnp.pad(x, ((0, 0), (0, pad), (0, 0), (0, 0)))
        x = x.reshape(b, nc, n, t, c).transpose(1, 0, 2, 3, 4)  # [nC, B, n, T, C]
        region = key_ok = None
        vh, vw = _pair(self.valid)
        if s > 0 or vh < rh or vw < rw:
            region, key_ok = window_masks((rh, rw), (vh, vw), ws, s)
            region = np.pad(region, ((0, pad), (0, 0))).reshape(nc, n, t)  # [nC, n, T]
            key_ok = np.pad(key_ok, ((0, pad), (0, 0))).reshape(nc, n, t)  # [nC, n, T]
        scan = nn.scan(
            nn.remat(_window_group, prevent_cse=False),  # CSE is safe inside a scan
            variable_broadcast="params",
            split_rngs={"params": False},
            variable_axes={"intermediates": 0},
        )
        _, y = scan(self, None, (x, region, key_ok))  # [nC, B, n, T, C]
        y = y.transpose(1, 0, 2, 3, 4).reshape(b, nc * n, t, c)[:, :nw]  # [B, nW, T, C]
        y = window_reverse(y, ws, rh, rw)  # [B, R, R', C]
        return jnp.roll(y, (s, s), axis=(1, 2)) if s else y


def _window_group(block: SwinBlock, carry: None, xs) -> tuple[None, jax.Array]:
    """Scan body of ``SwinBlock._chunked``: the block on one group of windows, with the
    block's own submodule names so the parameter tree is the unchunked one.

    Args:
      block: the bound ``SwinBlock``.
      carry: unused.
      xs: ``(x, region, key_ok)``: x [B, n, T, C] rolled-frame windows; region and key_ok
        [n, T] (``window_masks`` rows of these windows) or None.

    Returns:
      ``(None, [B, n, T, C])``.
    """
    x, region, key_ok = xs
    c = x.shape[-1]
    y = nn.LayerNorm(dtype=block.dtype, name="norm1")(x)
    y = WindowAttention(c, block.num_heads, block.window_size, block.dtype, name="attn")(
        y, region, key_ok
    )
    x = x + y
    y = nn.LayerNorm(dtype=block.dtype, name="norm2")(x)
    y = Dense(int(c * block.mlp_ratio), dtype=block.dtype, name="fc1")(y)
    y = Dense(c, dtype=block.dtype, name="fc2")(nn.gelu(y))
    return carry, x + y


class PatchMerging(nn.Module):
    """s x s concat -> LayerNorm(s*s*C) -> linear to ``features`` (no bias), as in Swin.

    Attributes:
      features: output channels.
      stride: s.
      dtype: computation dtype.
    """

    features: int
    stride: int = 2
    dtype: jnp.dtype = jnp.float32

    @nn.compact
    def __call__(self, x: jax.Array) -> jax.Array:
        """[B, H, W, C] -> [B, H/s, W/s, features]."""
        x = space_to_depth(x, self.stride)  # [B, H/s, W/s, s*s*C]
        x = nn.LayerNorm(dtype=self.dtype, name="norm")(x)
        return Dense(self.features, use_bias=False, dtype=self.dtype, name="reduction")(x)


class PatchEmbed(nn.Module):
    """Stage-1 embedding: s x s patches -> linear -> LayerNorm (Swin's PatchEmbed).

    Attributes:
      features: output channels.
      stride: patch size s (the paper uses 1: stage 1 keeps full resolution).
      dtype: computation dtype.
    """

    features: int
    stride: int = 1
    dtype: jnp.dtype = jnp.float32

    @nn.compact
    def __call__(self, x: jax.Array) -> jax.Array:
        """[B, H, W, C] -> [B, H/s, W/s, features]."""
        x = Dense(self.features, dtype=self.dtype, name="proj")(space_to_depth(x, self.stride))
        return nn.LayerNorm(dtype=self.dtype, name="norm")(x)


def padded_side(side: int, cfg: BackboneConfig) -> int:
    """The grid side after padding to a multiple of ``cfg.pad_multiple``."""
    m = cfg.pad_multiple
    return -(-side // m) * m


def stage_geometry(side, cfg: BackboneConfig) -> list[tuple]:
    """Per stage ``(res, valid, shift)``: padded size, valid size and the shift its SW-MSA
    blocks use (0 where one window spans the map's shorter side, as in Swin). ``side`` is
    one int for a square grid (sizes are then ints) or (H, W) (sizes are then pairs)."""
    square = np.ndim(side) == 0
    (vh, vw) = _pair(side)
    rh, rw = padded_side(vh, cfg), padded_side(vw, cfg)
    out = []
    for stride in cfg.strides:
        rh, rw, vh, vw = rh // stride, rw // stride, -(-vh // stride), -(-vw // stride)
        shift = cfg.shift_size if min(rh, rw) > cfg.window_size else 0
        out.append((rh, vh, shift) if square else ((rh, rw), (vh, vw), shift))
    return out


def _valid_mask(res, valid) -> np.ndarray:
    (rh, rw), (vh, vw) = _pair(res), _pair(valid)
    m = np.zeros((1, rh, rw, 1), bool)
    m[:, :vh, :vw] = True
    return m


class SwinBackbone(nn.Module):
    """Four-stage Swin over the BEV map.

    Attributes:
      config: backbone fields (dims, depths, heads, strides, shift pattern, window, remat,
        chunk_windows).
      dtype: computation dtype.
    """

    config: BackboneConfig
    dtype: jnp.dtype = jnp.float32

    @nn.compact
    def __call__(self, x: jax.Array) -> dict[int, jax.Array]:
        """Run the stages.

        Args:
          x: F_bev [B, H, W, C_enc] (H and W may differ).

        Returns:
          Stage index -> map [B, R_k, R'_k, C_k] on the padded grid (each side padded to a
          multiple of ``pad_multiple``, divided by the product of strides up to stage k;
          padded cells zeroed), for the stages in ``config.out_indices`` and always the last
          stage (the head's input).
        """
        cfg = self.config
        b, h, w, _ = x.shape
        pad_h, pad_w = padded_side(h, cfg) - h, padded_side(w, cfg) - w
        x = jnp.pad(x.astype(self.dtype), ((0, 0), (0, pad_h), (0, pad_w), (0, 0)))
        block_cls = nn.remat(SwinBlock) if cfg.remat else SwinBlock
        # The full-resolution LayerNorms of the embedding and the merges otherwise keep
        # several map-sized residuals each for the backward pass.
        embed_cls = nn.remat(PatchEmbed) if cfg.remat else PatchEmbed
        merge_cls = nn.remat(PatchMerging) if cfg.remat else PatchMerging
        outs, last = {}, len(cfg.embed_dims) - 1
        for k, (res, valid, shift) in enumerate(stage_geometry((h, w), cfg)):
            dim, stride = cfg.embed_dims[k], cfg.strides[k]
            if k == 0:
                x = embed_cls(dim, stride, self.dtype, name="patch_embed")(x)
            else:
                x = merge_cls(dim, stride, self.dtype, name=f"merge{k}")(x)
            for d in range(cfg.depths[k]):
                # Blocks alternate W and SW as in Swin; ``shifted`` says which one comes first.
                s = shift if (d % 2 == 0) == cfg.shifted[k] else 0
                x = block_cls(
                    dim, cfg.num_heads[k], cfg.window_size, s, valid, cfg.mlp_ratio, self.dtype,
                    cfg.chunk_windows, name=f"stage{k}_block{d}",
                )(x)  # fmt: skip
            # Zero the padding so patch merging and the upsampler only ever mix in zeros.
            if valid != res:
                x = jnp.where(_valid_mask(res, valid), x, 0).astype(self.dtype)
            if k in cfg.out_indices or k == last:
                outs[k] = x
        return outs
