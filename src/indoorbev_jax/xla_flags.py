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
"""

from __future__ import annotations

import os

NO_YNN_FUSIONS = "--xla_cpu_experimental_ynn_fusion_type="
TESTED_JAXLIB = ("0.10.",)


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
    return True
