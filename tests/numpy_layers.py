"""numpy forms of flax's LayerNorm, Dense and GELU, for the network's re-derivations in
tests/models (written from the layers' definitions, not from the model code)."""

import numpy as np


def layer_norm(x, p, eps=1e-6):
    """flax ``nn.LayerNorm`` (epsilon 1e-6) with parameters ``p`` = {scale, bias}."""
    mu = x.mean(-1, keepdims=True)
    var = ((x - mu) ** 2).mean(-1, keepdims=True)
    return (x - mu) / np.sqrt(var + eps) * p["scale"] + p["bias"]


def gelu(x):
    """flax ``nn.gelu``'s default, the tanh approximation."""
    return 0.5 * x * (1 + np.tanh(np.sqrt(2 / np.pi) * (x + 0.044715 * x**3)))


def dense(x, p):
    """flax ``nn.Dense`` with parameters ``p`` = {kernel, bias} (bias optional)."""
    y = x @ p["kernel"]
    return y + p["bias"] if "bias" in p else y
