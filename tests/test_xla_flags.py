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
    # The user's other flags are kept, ours added after them.
    monkeypatch.setenv("XLA_FLAGS", "--xla_force_host_platform_device_count=4")
    assert xla_flags.apply_cpu_defaults() == TESTED
    assert os.environ["XLA_FLAGS"] == "--xla_force_host_platform_device_count=4" + (
        f" {xla_flags.NO_YNN_FUSIONS}" if TESTED else ""
    )
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


def test_train_compiler_options_give_dot_fusions_to_small_grids_only(monkeypatch):
    monkeypatch.setattr(xla_flags, "_applied", True)
    assert xla_flags.train_compiler_options((100, 100)) == xla_flags.DOT_FUSIONS
    assert xla_flags.train_compiler_options((500, 500)) == {}
    # Up to 128 x 128 cells (docs/BENCHMARKS.md, "YNNPACK fusion types"), no more.
    assert xla_flags.train_compiler_options((128, 128)) == xla_flags.DOT_FUSIONS
    assert xla_flags.train_compiler_options((128, 129)) == {}
    monkeypatch.setattr(xla_flags, "_applied", False)  # the user's flags or another jaxlib
    assert xla_flags.train_compiler_options((100, 100)) == {}
    # CPU options only: a GPU run compiles with XLA's own (a mutation audit: passed).
    monkeypatch.setattr(xla_flags, "_applied", True)
    monkeypatch.setattr("jax.default_backend", lambda: "gpu")
    assert xla_flags.train_compiler_options((100, 100)) == {}


# A dense layer's gradient compiled with the small-grid options: YNNPACK fusions, dots only.
DOT_PROBE = """
import indoorbev_jax, jax, jax.numpy as jnp
from indoorbev_jax.xla_flags import train_compiler_options
x, w = jnp.ones((512, 64)), jnp.ones((64, 64))
def loss(w, x):
    h = x @ w
    return ((h - h.mean(-1, keepdims=True)) ** 2).sum()
for shape in [(100, 100), (500, 500)]:
    hlo = jax.jit(jax.grad(loss), compiler_options=train_compiler_options(shape)).lower(w, x)
    text = hlo.compile().as_text()
    print(text.count("__ynn_fusion"), " reduce(" in text)
"""


@pytest.mark.skipif(not TESTED, reason="flag only applied on the jaxlib versions measured")
def test_small_grid_options_reach_xla():
    env = dict(os.environ, JAX_PLATFORMS="cpu", XLA_FLAGS="")
    env.pop("INDOORBEV_XLA_DEFAULTS", None)
    out = subprocess.run([sys.executable, "-c", DOT_PROBE], env=env,
                         capture_output=True, text=True, timeout=300)  # fmt: skip
    assert out.returncode == 0, out.stderr[-2000:]
    small, paper = out.stdout.split("\n")[-3:-1]
    assert int(small.split()[0]) > 0 and paper.split()[0] == "0"
    assert small.split()[1] == "True"  # the mean's reduction stays an XLA op
