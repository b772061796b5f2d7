"""Test-session settings, applied before JAX starts (subprocesses inherit them).

The suite is compile-bound: XLA's backend optimisation level 0 compiles several times
faster and the tiny test configs run fast enough without the optimisations.
"""

import os

os.environ.setdefault("JAX_PLATFORMS", "cpu")
if "xla_backend_optimization_level" not in os.environ.get("XLA_FLAGS", ""):
    flags = os.environ.get("XLA_FLAGS", "") + " --xla_backend_optimization_level=0"
    os.environ["XLA_FLAGS"] = flags.strip()
