"""XLA:CPU defaults set on import (indoorbev_jax.xla_flags)."""

import os
import subprocess
import sys

import pytest
from jaxlib import version as jaxlib_version

from indoorbev_jax import xla_flags

TESTED = jaxlib_version.__version__.startswith(xla_flags.TESTED_JAXLIB)

# Compiles a LayerNorm's gradient and says whether XLA used YNNPACK fusions for it.
PROBE = """
import indoorbev_jax, jax, jax.numpy as jnp, flax.linen as nn
x = jnp.ones((4, 56, 56, 32))
ln = nn.LayerNorm()
p = ln.init(jax.random.key(0), x)
grad = jax.jit(jax.grad(lambda p, x: (ln.apply(p, x) ** 2).sum(), argnums=(0, 1)))
print("YNN" if "ynn_fusion" in grad.lower(p, x).compile().as_text() else "NO_YNN")
"""


def test_apply_cpu_defaults_respects_the_user(monkeypatch):
    monkeypatch.delenv("XLA_FLAGS", raising=False)
    monkeypatch.delenv("INDOORBEV_XLA_DEFAULTS", raising=False)
    assert xla_flags.apply_cpu_defaults() == TESTED
    assert os.environ.get("XLA_FLAGS", "") == (xla_flags.NO_YNN_FUSIONS if TESTED else "")
    mine = "--xla_backend_optimization_level=0 --xla_cpu_experimental_ynn_fusion_type=reduce"
    monkeypatch.setenv("XLA_FLAGS", mine)
    assert not xla_flags.apply_cpu_defaults() and os.environ["XLA_FLAGS"] == mine
    monkeypatch.setenv("XLA_FLAGS", "--xla_backend_optimization_level=0")
    monkeypatch.setenv("INDOORBEV_XLA_DEFAULTS", "0")
    assert not xla_flags.apply_cpu_defaults()
    assert os.environ["XLA_FLAGS"] == "--xla_backend_optimization_level=0"


@pytest.mark.skipif(not TESTED, reason="flag only applied on the jaxlib versions measured")
def test_importing_the_package_turns_off_ynn_fusions():
    base = dict(os.environ, JAX_PLATFORMS="cpu", XLA_FLAGS="")

    def probe(**env):
        out = subprocess.run([sys.executable, "-c", PROBE], env=dict(base, **env),
                             capture_output=True, text=True, timeout=300)  # fmt: skip
        assert out.returncode == 0, out.stderr[-2000:]
        return out.stdout.split()[-1]

    assert probe(INDOORBEV_XLA_DEFAULTS="0") == "YNN"  # XLA's default, which the flag changes
    assert probe() == "NO_YNN"
