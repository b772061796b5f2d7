"""XLA:CPU defaults applied when ``indoorbev_jax`` is imported, before JAX starts its backend.

XLA:CPU (jaxlib 0.10) hands reductions such as LayerNorm's to YNNPACK fusions, whose
backward passes made a Swin block's forward + backward 1.3x slower and the lean ``paper``
train step 15 % slower with 47 % more XLA memory (docs/BENCHMARKS.md, "YNNPACK fusions").
``apply_cpu_defaults`` turns those fusions off through ``XLA_FLAGS``:

- only for jaxlib versions where the flag was measured (an unknown XLA flag aborts the
  process, so newer versions are left alone until re-measured);
- never over a ``ynn`` setting the user already put in ``XLA_FLAGS``;
- not at all when ``INDOORBEV_XLA_DEFAULTS=0``;
- XLA reads ``XLA_FLAGS`` once, when the first computation starts its backend, so it has no
  effect in a process that ran JAX code before importing ``indoorbev_jax``.

Small grids train faster with YNNPACK's dot fusions alone (the reductions stay with XLA):
``train_compiler_options`` gives them back to the train steps of grids up to
``DOT_FUSION_MAX_CELLS`` cells, for that compile only (docs/BENCHMARKS.md, "YNNPACK fusion
types").
"""

from __future__ import annotations

import os

NO_YNN_FUSIONS = "--xla_cpu_experimental_ynn_fusion_type="
TESTED_JAXLIB = ("0.10.",)
# Measured: 100 x 100 cells faster with dot fusions, 500 x 500 slower; in between untested.
DOT_FUSION_MAX_CELLS = 128 * 128
DOT_FUSIONS = {"xla_cpu_experimental_ynn_fusion_type": "LIBRARY_FUSION_TYPE_DOT"}
_applied = False  # whether this process runs under NO_YNN_FUSIONS set by us


def apply_cpu_defaults() -> bool:
    """Adds ``NO_YNN_FUSIONS`` to ``XLA_FLAGS`` where safe; returns whether it did."""
    if os.environ.get("INDOORBEV_XLA_DEFAULTS", "1") == "0":
        return False
    flags = os.environ.get("XLA_FLAGS", "")
    if "ynn_fusion_type" in flags:
        return False
    try:
        from jaxlib import version as jaxlib_version
    except ImportError:
        return False
    if not jaxlib_version.__version__.startswith(TESTED_JAXLIB):
        return False
    os.environ["XLA_FLAGS"] = f"{flags} {NO_YNN_FUSIONS}".strip()
    global _applied
    _applied = True
    return True


def train_compiler_options(grid_shape: tuple[int, int]) -> dict:
    """``jax.jit`` compiler options for a train step on a ``grid_shape`` BEV grid: YNNPACK dot
    fusions on small grids, where they measured 1.12-1.38x faster; nothing otherwise, nor
    when the import defaults are not in force (the user's own flags, another jaxlib)."""
    import jax

    small = grid_shape[0] * grid_shape[1] <= DOT_FUSION_MAX_CELLS
    if _applied and small and jax.default_backend() == "cpu":
        return dict(DOT_FUSIONS)
    return {}
