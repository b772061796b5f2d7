"""IndoorBEV in JAX/Flax. Importing it sets XLA:CPU defaults (see ``xla_flags``)."""

from indoorbev_jax.xla_flags import apply_cpu_defaults

apply_cpu_defaults()
