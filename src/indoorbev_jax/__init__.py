"""IndoorBEV in JAX/Flax. Importing it sets process defaults: XLA:CPU flags (``xla_flags``)
and, with ``INDOORBEV_RETAIN_MEMORY=1``, glibc's memory retention (``host_memory``)."""

from indoorbev_jax.host_memory import retain_freed_memory
from indoorbev_jax.xla_flags import apply_cpu_defaults

apply_cpu_defaults()
retain_freed_memory()
