"""The IndoorBEV network (Flax Linen): encoder, Swin backbone, upsampler and mask head."""

from indoorbev_jax.models.indoorbev import IndoorBEV

__all__ = ["IndoorBEV"]
