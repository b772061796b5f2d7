"""Array containers shared by every stage, and the glossary of axis letters.

Axis letters used in shape comments and docstrings:
  B  frames in a batch             N  points per frame (padded to ``data.max_points``)
  H  BEV rows (along y)            W  BEV columns (along x)
  C  channels                      Q  queries (``head.num_queries``)
  M  targets per frame (padded to ``data.max_objects``)
  L  decoder layers                K  classes + background (``num_classes + 1``)
  R  rays                          T  frames in a sequence

Boxes (DESIGN sections 2-3), all in the lidar frame (x forward, y left, z up, metres):
  pos   box centre (x, y, z), the geometric centre, not KITTI's bottom centre;
  dims  (length, width, height), length along the heading;
  yaw   heading angle about +z from +x, in radians.
"""

from __future__ import annotations

import functools
from collections.abc import Callable, Mapping

import jax
from flax import struct


def float32_defaults(fn: Callable) -> Callable:
    """Runs ``fn`` (traced or not) with JAX's 32-bit defaults even when the caller turned
    ``jax_enable_x64`` on: random float draws stay float32, so a key gives the same scenes
    and augmentations (and the float32 arrays these containers document) either way."""

    @functools.wraps(fn)
    def wrapped(*args, **kwargs):
        with jax.enable_x64(False):
            return fn(*args, **kwargs)

    return wrapped


class _ByName:
    """``x["logits"]`` as well as ``x.logits``, and ``keys()``: the containers read like the
    dicts of the PyTorch code (``{logits, dims, pos, yaw, masks}``) they replace."""

    def __getitem__(self, name: str):
        if not isinstance(name, str) or name not in self.keys():
            raise KeyError(f"{type(self).__name__} has no field {name!r}; fields: {self.keys()}")
        return getattr(self, name)

    def keys(self) -> tuple[str, ...]:
        return tuple(self.__dataclass_fields__)


@struct.dataclass
class Targets(_ByName):
    """Ground truth of B frames, padded to M objects.

    Attributes:
      classes: int32 [B, M], class index in 0..num_classes-1 (padding: num_classes).
      dims: float32 [B, M, 3], (length, width, height).
      pos: float32 [B, M, 3], box centre.
      yaw: float32 [B, M].
      valid: bool [B, M], which slots hold an object.
      masks: bool [B, M, H, W], each object's footprint (overlaps allowed).
      instance_ids: int32 [B, H, W], 0 = empty, k + 1 = object k (the panoptic map).
    """

    classes: jax.Array
    dims: jax.Array
    pos: jax.Array
    yaw: jax.Array
    valid: jax.Array
    masks: jax.Array
    instance_ids: jax.Array


@struct.dataclass
class Batch(_ByName):
    """Model inputs plus targets: what a data source yields and the train step consumes.

    Attributes:
      points: float32 [B, N, 4], (x, y, z, intensity) in the lidar frame.
      point_valid: bool [B, N].
      targets: ``Targets`` of the same B frames.
    """

    points: jax.Array
    point_valid: jax.Array
    targets: Targets


@struct.dataclass
class Predictions(_ByName):
    """Raw network outputs for every decoder layer (the last layer is the final one).

    Attributes:
      logits: [L, B, Q, K] class logits, index num_classes = background.
      dims: [L, B, Q, 3]; pos: [L, B, Q, 3]; yaw: [L, B, Q, 1].
      masks: [L, B, Q, H, W] mask logits on the unpadded grid.
    """

    logits: jax.Array
    dims: jax.Array
    pos: jax.Array
    yaw: jax.Array
    masks: jax.Array


def _from_mapping(cls, x, name: str, optional: tuple[str, ...] = ()):
    """``x`` if it is a ``cls``, or a mapping with the fields of ``cls`` as one (fields in
    ``optional`` may be left out: None); a ``TypeError`` naming missing or unknown keys."""
    if isinstance(x, cls):
        return x
    if isinstance(x, Mapping):
        fields = tuple(cls.__dataclass_fields__)
        missing = [k for k in fields if k not in x and k not in optional]
        unknown = [k for k in x if k not in fields]
        if missing or unknown:
            raise TypeError(f"{name}: missing {missing}, unknown {unknown}; fields {fields}")
        return cls(**{**dict.fromkeys(optional), **x})
    raise TypeError(f"{name}: expected {cls.__name__} or a mapping, got {type(x).__name__}")


def as_predictions(x: Predictions | Mapping) -> Predictions:
    """``x``, or a mapping with the fields of ``Predictions`` as one (a ``TypeError``
    naming the missing or unknown keys otherwise)."""
    return _from_mapping(Predictions, x, "predictions")


def as_targets(x: Targets | Mapping) -> Targets:
    """``x``, or a mapping with the fields of ``Targets`` as one; ``instance_ids`` may be
    left out (the loss does not read it). Missing or unknown keys are a ``TypeError``."""
    return _from_mapping(Targets, x, "targets", optional=("instance_ids",))
