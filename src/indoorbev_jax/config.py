"""Configuration: frozen dataclasses, named presets, validated once at construction.

Presets:
  * ``Config.paper()``: the paper's network (DESIGN sections 5-8), 0.02 m cells, 500 x 500.
  * ``Config.small()``: trainable on a 2-core CPU, 0.1 m cells, 100 x 100.
  * ``Config.tiny()``: for tests, 0.25 m cells, 40 x 40, 88,642 parameters.

Change a field with ``dataclasses.replace`` (validation runs again)::

    cfg = Config.small()
    cfg = dataclasses.replace(cfg, train=dataclasses.replace(cfg.train, learning_rate=1e-4))

Structural values (grid, widths, depths) are static; values a sweep varies (learning rate,
loss weights) are read from here once and passed into jitted steps as arrays.
"""

from __future__ import annotations

import dataclasses
import functools
import json
import math
import numbers
import os
import sys
import typing
from typing import Any

import jax
import numpy as np

from indoorbev_jax.checks import SEED_LIMIT

CLASS_NAMES: tuple[str, ...] = (
    "Table",
    "Chair",
    "Sofa",
    "Shelf",
    "Cabinet",
    "Box",
    "Person",
    "Robot",
    "Misc",
)
NUM_CLASSES = len(CLASS_NAMES)  # background is index NUM_CLASSES
DYNAMIC_CLASSES: tuple[str, ...] = ("Person", "Robot")

# Test-time views: each one's 2 x 2 map of the points' (x, y). All eight are the symmetries
# of a square grid centred on the sensor, which training's augmentation (mirror, any yaw)
# already covers (``inference.apply_views``).
VIEWS: dict[str, tuple[tuple[int, int], tuple[int, int]]] = {
    "identity": ((1, 0), (0, 1)),
    "mirror_y": ((1, 0), (0, -1)),
    "mirror_x": ((-1, 0), (0, 1)),
    "rotate_180": ((-1, 0), (0, -1)),
    "rotate_90": ((0, -1), (1, 0)),
    "rotate_270": ((0, 1), (-1, 0)),
    "transpose": ((0, 1), (1, 0)),
    "antitranspose": ((0, -1), (-1, 0)),
}


MAX_RAYS = 1 << 22  # sim.num_rays per frame: 32 OS-128 frames


class ConfigError(ValueError):
    """A configuration field holds a value that cannot work; the message names the field."""


_TRUE, _FALSE = ("true", "1"), ("false", "0")


def _as_type(value: Any, hint, python: bool = False) -> Any:
    """``value`` (decoded JSON, or the raw text where it is not JSON; with ``python``, a
    value a section was built with in Python) as a value of the annotation ``hint``; raises
    ``TypeError`` when it is not one, ``NotImplementedError`` for an annotation not checked.
    Numpy numbers count as Python's, a list as a tuple."""
    is_bool = isinstance(value, bool | np.bool_)
    if hint is bool:
        if python and is_bool:
            return bool(value)
        # Python's spelling (True) is not JSON, and the string 'False' would be truthy.
        text = str(value).lower() if isinstance(value, bool | int | str) else None
        if not python and text in _TRUE + _FALSE:
            return text in _TRUE
    elif hint is int:
        if not python and isinstance(value, float) and value.is_integer():
            return int(value)
        if isinstance(value, numbers.Integral) and not is_bool:
            return int(value)
    elif hint is float:
        if isinstance(value, np.floating) and value.dtype.itemsize < 8:
            # np.float32(0.1) means 0.1, not 0.10000000149 (a grid of those is not whole).
            return float(str(value))
        if isinstance(value, numbers.Real) and not is_bool:
            return float(value)
    elif hint is str:
        if isinstance(value, str):
            return value
    elif typing.get_origin(hint) is tuple:
        args = typing.get_args(hint)
        if isinstance(value, dict) and typing.get_origin(args[0]) is tuple:
            value = list(value.items())  # {"Desk": "Table"} for (name, class) pairs
        if isinstance(value, list | tuple):
            types = [args[0]] * len(value) if args[-1] is Ellipsis else list(args)
            if len(types) == len(value):
                return tuple(_as_type(v, h, python) for v, h in zip(value, types, strict=True))
    else:
        raise NotImplementedError(f"--set cannot parse fields of type {hint}")
    raise TypeError(value)


@functools.cache
def _hints(kind) -> dict[str, Any]:
    return typing.get_type_hints(kind)


def _check_types(section, prefix: str, skip: tuple[str, ...] = ()) -> None:
    """Each field of a config ``section`` built in Python has its annotated type, or the
    error names it (``GridConfig(cell_size="0.1")`` raised a bare TypeError deep in a
    check, and a float for an int field passed to fail far later)."""
    for field in dataclasses.fields(section):
        if field.name in skip:  # checked by the section itself, with its own message
            continue
        value, hint = getattr(section, field.name), _hints(type(section))[field.name]
        try:
            fixed = _as_type(value, hint, python=True)
        except NotImplementedError:
            continue
        except TypeError:
            _fail(f"{prefix}.{field.name}", f"got {value!r}, expected {_describe(hint)}")
        if fixed != value or type(fixed) is not type(value):
            object.__setattr__(section, field.name, fixed)


def _fail(field: str, message: str) -> None:
    raise ConfigError(f"config field '{field}': {message}")


def _check_range(field: str, value: tuple[float, float]) -> None:
    if len(value) != 2 or not value[0] < value[1] or not all(map(math.isfinite, value)):
        _fail(field, f"expected finite (min, max) with min < max, got {value!r}")


def _check_positive(field: str, value: float) -> None:
    if not value > 0:
        _fail(field, f"must be > 0, got {value!r}")


def _check_non_negative(field: str, value: float) -> None:
    """NaN and infinity fail too (``value < 0`` lets NaN through)."""
    if not (value >= 0 and math.isfinite(value)):
        _fail(field, f"must be finite and >= 0, got {value!r}")


def _check_len(field: str, value: tuple, n: int) -> None:
    if len(value) != n:
        _fail(field, f"expected {n} entries, got {len(value)}: {value!r}")


@dataclasses.dataclass(frozen=True)
class GridConfig:
    """The BEV grid in the lidar frame (DESIGN section 2).

    Row i grows with y, column j with x; the centre of cell (i, j) is
    ``(x_range[0] + (j + 0.5) * cell_size, y_range[0] + (i + 0.5) * cell_size)``.
    """

    x_range: tuple[float, float] = (-5.0, 5.0)
    y_range: tuple[float, float] = (-5.0, 5.0)
    z_range: tuple[float, float] = (-3.0, 3.0)
    cell_size: float = 0.02

    def __post_init__(self):
        _check_types(self, "grid")
        _check_positive("grid.cell_size", self.cell_size)
        if not math.isfinite(self.cell_size):
            _fail("grid.cell_size", f"must be finite, got {self.cell_size!r}")
        for name in ("x_range", "y_range", "z_range"):
            _check_range(f"grid.{name}", getattr(self, name))
        for name in ("x_range", "y_range"):
            lo, hi = getattr(self, name)
            cells = (hi - lo) / self.cell_size
            if not 1 <= cells < 2**31:
                _fail(f"grid.{name}", f"extent {hi - lo} m holds {cells} cells of "
                      f"cell_size {self.cell_size} m, expected at least 1")  # fmt: skip
            if abs(cells - round(cells)) > 1e-6:
                _fail(
                    f"grid.{name}",
                    f"extent {hi - lo} m is not divisible by cell_size {self.cell_size} m "
                    f"({cells:.4f} cells)",
                )

    @property
    def shape(self) -> tuple[int, int]:
        """(H, W): rows along y, columns along x."""
        h = round((self.y_range[1] - self.y_range[0]) / self.cell_size)
        w = round((self.x_range[1] - self.x_range[0]) / self.cell_size)
        return h, w


def check_views(views: tuple[str, ...], grid: GridConfig) -> None:
    """Raises ``ConfigError`` unless every view maps the grid onto itself cell for cell:
    symmetric about the sensor along a mirrored axis, square and centred for the views that
    swap x and y."""
    x, y = grid.x_range, grid.y_range
    for v in views:
        (a, b), (_, d) = VIEWS[v]
        if b:  # x and y swap
            if not (math.isclose(x[0], -x[1]) and math.isclose(y[0], -y[1]) and
                    math.isclose(x[1], y[1])):  # fmt: skip
                _fail(
                    "inference.views",
                    f"{v!r} swaps x and y, which needs a square grid centred on the sensor; "
                    f"got grid.x_range = {x}, grid.y_range = {y}",
                )
            continue
        for sign, name, (lo, hi) in ((a, "x_range", x), (d, "y_range", y)):
            if sign < 0 and not math.isclose(lo, -hi):
                _fail(
                    "inference.views",
                    f"{v!r} mirrors grid.{name} = {(lo, hi)}, which is not symmetric about "
                    "the sensor",
                )


def _check_label_name(field: str, name) -> None:
    """A class name must fit a KITTI label line: one whitespace-free field, not "DontCare"
    (whose lines the reader skips)."""
    if not isinstance(name, str) or not name or name.split() != [name] or name == "DontCare":
        _fail(
            field,
            f"{name!r} cannot be a class name in a KITTI label line (one field without "
            "whitespace, not 'DontCare')",
        )


@dataclasses.dataclass(frozen=True)
class DataConfig:
    """Point and target padding, classes (DESIGN sections 3-4)."""

    max_points: int = 24576
    # Targets are padded to this length (N_q in DESIGN section 3); must not exceed the
    # number of queries so that every target can be matched.
    max_objects: int = 30
    class_names: tuple[str, ...] = CLASS_NAMES
    # Extra label names accepted on read, as (name in file, canonical class name) pairs.
    class_map: tuple[tuple[str, str], ...] = ()
    # Training footprint targets: "shape" (true shape: the simulator's union of the object's
    # primitives, or a dataset's mask_2) or "box" (its labelled box rasterised). Validation
    # and evaluation always use the true shape.
    mask_targets: str = "shape"

    def __post_init__(self):
        _check_types(self, "data", skip=("class_map",))
        if self.mask_targets not in ("shape", "box"):
            _fail("data.mask_targets", f"expected 'shape' or 'box', got {self.mask_targets!r}")
        _check_positive("data.max_points", self.max_points)
        _check_positive("data.max_objects", self.max_objects)
        if len(set(self.class_names)) != len(self.class_names):
            _fail("data.class_names", f"names must be unique, got {self.class_names!r}")
        for name in self.class_names:
            _check_label_name("data.class_names", name)
        pairs = self.class_map
        if isinstance(pairs, dict):  # {"Desk": "Table"}, as --set data.class_map=... gives it
            pairs = tuple(pairs.items())
        if isinstance(pairs, str) or not all(
            isinstance(p, (tuple, list)) and len(p) == 2 and all(isinstance(n, str) for n in p)
            for p in pairs
        ):
            _fail("data.class_map", f"expected (name, class) pairs or a dict, got {pairs!r}")
        object.__setattr__(self, "class_map", tuple(tuple(p) for p in pairs))
        sources = [src for src, _ in self.class_map]
        for src in sources:
            _check_label_name("data.class_map", src)
        for src in sources:
            if sources.count(src) > 1:  # dict() would silently keep the last target
                _fail("data.class_map", f"'{src}' is mapped more than once: {self.class_map!r}")
        for src, dst in self.class_map:
            if dst not in self.class_names:
                _fail("data.class_map", f"'{src}' maps to unknown class '{dst}'")

    @property
    def num_classes(self) -> int:
        return len(self.class_names)

    def class_index(self, name: str) -> int:
        """Index of a class name (after ``class_map``); raises KeyError when unknown."""
        canonical = dict(self.class_map).get(name, name)
        if canonical not in self.class_names:
            raise KeyError(name)
        return self.class_names.index(canonical)


@dataclasses.dataclass(frozen=True)
class EncoderConfig:
    """AF-PCCN (DESIGN section 5)."""

    channels: int = 64  # C_enc, features per BEV cell

    def __post_init__(self):
        _check_types(self, "encoder")
        _check_positive("encoder.channels", self.channels)
        if self.channels % 2:
            _fail("encoder.channels", f"must be even (two branches of C/2), got {self.channels}")


@dataclasses.dataclass(frozen=True)
class BackboneConfig:
    """Swin backbone (DESIGN section 6)."""

    embed_dims: tuple[int, ...] = (64, 128, 256, 512)
    depths: tuple[int, ...] = (1, 1, 1, 1)
    num_heads: tuple[int, ...] = (2, 4, 8, 8)
    strides: tuple[int, ...] = (1, 2, 2, 2)
    # Per stage: whether its blocks start with a shifted window (SW-MSA). With one block
    # per stage, stages 2 and 4 shift so both W-MSA and SW-MSA occur.
    shifted: tuple[bool, ...] = (False, True, False, True)
    window_size: int = 7
    mlp_ratio: float = 2.0
    out_indices: tuple[int, ...] = (0, 1, 2, 3)
    # Recompute every block, the patch embedding and the merges in the backward pass.
    remat: bool = False
    # Memory-lean blocks: 0 off; n > 0 runs every block whose map has more than n windows as
    # a scan over groups of n windows, each group recomputed in the backward pass, so the
    # training peak holds one group's attention scores and MLP activations, not the map's.
    chunk_windows: int = 0

    def __post_init__(self):
        _check_types(self, "backbone")
        n = len(self.embed_dims)
        if self.chunk_windows < 0:
            _fail("backbone.chunk_windows", f"must be >= 0 (0: off), got {self.chunk_windows}")
        if not n:
            _fail("backbone.embed_dims", "expected at least one stage, got ()")
        for name in ("depths", "num_heads", "strides", "shifted"):
            _check_len(f"backbone.{name}", getattr(self, name), n)
        stages = zip(self.embed_dims, self.depths, self.num_heads, strict=True)
        for k, (dim, depth, heads) in enumerate(stages):
            _check_positive(f"backbone.embed_dims[{k}]", dim)
            if depth < 0:
                _fail(f"backbone.depths[{k}]", f"must be >= 0, got {depth}")
            if heads <= 0 or dim % heads:
                _fail(f"backbone.num_heads[{k}]", f"{heads} heads do not divide width {dim}")
        for k, s in enumerate(self.strides):
            if s not in (1, 2):
                _fail(f"backbone.strides[{k}]", f"must be 1 or 2, got {s}")
        _check_positive("backbone.window_size", self.window_size)
        narrowest = min(self.embed_dims, default=1)
        if not (math.isfinite(self.mlp_ratio) and int(narrowest * self.mlp_ratio) >= 1):
            # The MLP's hidden width is int(width x ratio): 0 units, or inf, failed in init.
            _fail(
                "backbone.mlp_ratio",
                f"must be finite and give the narrowest stage (width {narrowest}) an MLP of "
                f">= 1 unit, got {self.mlp_ratio!r}",
            )
        for k in self.out_indices:
            if not 0 <= k < n:
                _fail("backbone.out_indices", f"index {k} outside 0..{n - 1}")

    @property
    def shift_size(self) -> int:
        return self.window_size // 2

    @property
    def total_stride(self) -> int:
        return math.prod(self.strides)

    @property
    def pad_multiple(self) -> int:
        """The grid is padded once to this multiple so every stage tiles into windows."""
        return self.window_size * self.total_stride


QUERY_INITS = ("learned", "select")


@dataclasses.dataclass(frozen=True)
class HeadConfig:
    """Upsampler and query mask head (DESIGN section 7)."""

    hidden_dim: int = 64  # C_hid
    num_queries: int = 30
    num_layers: int = 4
    num_heads: int = 8
    ffn_dim: int = 256
    # FPN-style skips from earlier stages into the upsampler (paper mode: False).
    upsampler_skips: bool = False
    # Cross-attention memory stride: 1 attends to the full H x W memory (paper); s > 1
    # attends to an s x s average-pooled memory while masks stay at full resolution.
    memory_stride: int = 1
    # Add the 2D sine code to F_proj where the mask logits read it (paper: False), so a
    # query can tell two look-alike objects apart by where they are.
    mask_positional: bool = False
    # Recompute each decoder layer's cross-attention, each upsampler step and the input
    # projection in the backward pass (jax.checkpoint); pair with attention_chunk, without
    # which the peak sits inside one cross-attention (docs/BENCHMARKS.md "## Model").
    remat: bool = False
    # Memory-lean cross-attention: 0 off; n > 0 streams the memory in chunks of n tokens
    # with an online softmax, each chunk recomputed in the backward pass, so the [B, h, Q, S]
    # scores never exist whole (the last chunk is padded and masked).
    attention_chunk: int = 0
    # Where the decoder's queries start: "learned" (paper: N_q learned embeddings) or
    # "select" (two-stage, as in Mask DINO): a dense class head on F_proj, trained on the
    # semantic BEV map, picks the N_q highest-scoring local peaks, whose features and sine
    # code become the queries. Queries then start on objects, which speeds up training.
    query_init: str = "learned"
    # A dense class head on F_proj (``seed_head``) trained by the seed loss even with learned
    # queries (paper: False): dense semantic supervision of F_proj, which the mask-pooled
    # class features read. Always present with query_init = "select".
    semantic_head: bool = False
    # Add a per-query log-prior -a_j |p - c_j|^2 to the mask logits around the query's
    # predicted box centre c_j (a_j >= 0 learned from the query; paper: False). Pixel
    # features of look-alike objects match; the prior keeps each mask near its own object.
    mask_prior: bool = False
    # Class logits read the query plus Dense(mean of F_proj under the query's own mask) (as
    # K-Net's mask pooling; paper: False). Queries that the mask prior ties to places rather
    # than classes then see the object they outline.
    mask_pooled_class: bool = False

    def __post_init__(self):
        _check_types(self, "head")
        if self.query_init not in QUERY_INITS:
            _fail("head.query_init", f"expected one of {QUERY_INITS}, got {self.query_init!r}")
        for name in ("hidden_dim", "num_queries", "num_layers", "ffn_dim", "memory_stride"):
            _check_positive(f"head.{name}", getattr(self, name))
        if self.hidden_dim % 2:
            _fail("head.hidden_dim", f"must be even (y and x halves of the sine code), got "
                  f"{self.hidden_dim}")  # fmt: skip
        if self.attention_chunk < 0:
            _fail("head.attention_chunk", f"must be >= 0 (0: off), got {self.attention_chunk}")
        if self.num_heads <= 0 or self.hidden_dim % self.num_heads:
            _fail(
                "head.num_heads",
                f"{self.num_heads} heads do not divide hidden_dim {self.hidden_dim}",
            )


@dataclasses.dataclass(frozen=True)
class LossConfig:
    """Matching costs and loss weights (DESIGN section 8)."""

    # Loss weights.
    cls_weight: float = 2.0
    dice_weight: float = 5.0
    focal_weight: float = 2.0
    dims_weight: float = 0.1
    pos_weight: float = 0.1
    yaw_weight: float = 0.1
    background_weight: float = 0.1
    # Matching cost weights.
    cost_cls: float = 2.0
    cost_dice: float = 5.0
    cost_focal: float = 2.0
    cost_reg: float = 0.1
    focal_alpha: float = 0.25
    focal_gamma: float = 2.0
    # Sampled mask points per query for costs and mask losses; 0 = every cell.
    num_mask_points: int = 0
    aux_loss: bool = True
    # Weight of the dense seed loss (sigmoid focal on the semantic BEV map, normalised by
    # the foreground cells) that trains the seed head (head.query_init = "select" or
    # head.semantic_head).
    seed_weight: float = 1.0

    def __post_init__(self):
        _check_types(self, "loss")
        for f in dataclasses.fields(self):
            v = getattr(self, f.name)
            if isinstance(v, float) and (v < 0 or not math.isfinite(v)):
                _fail(f"loss.{f.name}", f"must be finite and >= 0, got {v!r}")
        if self.num_mask_points < 0:
            _fail("loss.num_mask_points", f"must be >= 0, got {self.num_mask_points}")
        if self.focal_alpha > 1:  # the background weight 1 - alpha would turn negative
            _fail("loss.focal_alpha", f"must be in [0, 1], got {self.focal_alpha!r}")

    def weights(self) -> dict[str, float]:
        """Loss weights as a flat dict, the form ``losses.set_loss`` takes (arrays allowed)."""
        return {
            "cls": self.cls_weight,
            "dice": self.dice_weight,
            "focal": self.focal_weight,
            "dims": self.dims_weight,
            "pos": self.pos_weight,
            "yaw": self.yaw_weight,
        }


@dataclasses.dataclass(frozen=True)
class InferenceConfig:
    """Panoptic inference thresholds (DESIGN section 9) and test-time views.

    ``views``: the model runs on each of these symmetries of the cloud (``VIEWS``) and the
    outputs are fused (``inference.apply_views``); ``("identity",)`` is the plain forward.
    ``view_iou``: least mask IoU for two views' queries to be one object (they must overlap,
    so 0 means any overlap).
    """

    score_threshold: float = 0.8
    mask_threshold: float = 0.5
    overlap_threshold: float = 0.8
    views: tuple[str, ...] = ("identity",)
    view_iou: float = 0.5

    def __post_init__(self):
        _check_types(self, "inference")
        for name in ("score_threshold", "mask_threshold", "overlap_threshold", "view_iou"):
            v = getattr(self, name)
            if not 0.0 <= v <= 1.0:
                _fail(f"inference.{name}", f"must lie in [0, 1], got {v!r}")
        views = self.views
        if isinstance(views, str) or not views or any(v not in VIEWS for v in views):
            _fail("inference.views", f"expected names from {', '.join(VIEWS)}, got {views!r}")
        if len(set(views)) != len(views):
            _fail("inference.views", f"{views!r} repeats a view")


@dataclasses.dataclass(frozen=True)
class AugmentConfig:
    """Training augmentations (paper appendix "Data Augmentation"); 0 disables a step."""

    flip_prob: float = 0.5  # mirror y -> -y
    rotation: float = math.pi  # uniform in [-rotation, rotation] about +z
    scale_range: tuple[float, float] = (0.95, 1.05)
    jitter_std: float = 0.01  # metres, per point coordinate
    point_drop_prob: float = 0.05  # each point independently
    range_dropout_prob: float = 0.2  # drop one random range band of the frame
    range_dropout_width: float = 0.5  # metres
    noise_points: float = 0.01  # fraction of max_points injected as uniform clutter
    intensity_drop_prob: float = 0.0  # per frame: every intensity 0 (a sensor without it)
    shuffle_points: bool = True
    box_noise_prob: float = 0.5  # per object
    box_translation_std: float = 0.1  # metres
    box_yaw_std: float = 0.1  # radians
    box_scale_std: float = 0.03
    mask_perturb_prob: float = 0.1  # per object: one-cell dilation or erosion
    gt_sampling: int = 0  # objects pasted from the object database per frame
    gt_sampling_attempts: int = 4  # candidate poses tried per pasted object

    def __post_init__(self):
        _check_types(self, "augment")
        for name in (
            "flip_prob",
            "range_dropout_prob",
            "point_drop_prob",
            "box_noise_prob",
            "mask_perturb_prob",
            "noise_points",
            "intensity_drop_prob",
        ):
            v = getattr(self, name)
            if not 0.0 <= v <= 1.0:
                _fail(f"augment.{name}", f"must lie in [0, 1], got {v!r}")
            # An int 0 or 1 (a hand-edited config.json) would fail jax.random.bernoulli.
            object.__setattr__(self, name, float(v))
        for name in (
            "rotation",
            "jitter_std",
            "range_dropout_width",
            "box_translation_std",
            "box_yaw_std",
            "box_scale_std",
        ):
            _check_non_negative(f"augment.{name}", getattr(self, name))
        lo, hi = self.scale_range
        if not 0 < lo <= hi < math.inf:
            _fail("augment.scale_range", f"expected 0 < min <= max, got {self.scale_range!r}")
        if self.gt_sampling < 0 or self.gt_sampling_attempts < 1:
            _fail("augment.gt_sampling", "needs gt_sampling >= 0 and gt_sampling_attempts >= 1")


@dataclasses.dataclass(frozen=True)
class TrainConfig:
    """Optimiser, schedule and run control (paper "Implementation Details")."""

    batch_size: int = 4
    learning_rate: float = 5e-5
    weight_decay: float = 1e-4
    warmup_steps: int = 500
    total_steps: int = 50_000
    grad_clip_norm: float = 1.0  # 0 disables clipping
    # Exponential moving average of the parameters, kept in the optimizer state (0: off).
    # Evaluation, the best checkpoint's score and exported models use the average; it starts
    # at the initial (or loaded) parameters, so 1 / (1 - ema_decay) should be well under the
    # run's steps.
    ema_decay: float = 0.0
    bfloat16: bool = False
    augment: bool = True  # run the augmentation chain (config.augment) in the train step
    eval_batches: int = 8  # validation batches per evaluation
    seed: int = 0
    log_every: int = 50
    eval_every: int = 1000
    checkpoint_every: int = 1000
    keep_checkpoints: int = 3

    def __post_init__(self):
        _check_types(self, "train")
        for name in (
            "batch_size",
            "eval_batches",
            "total_steps",
            "log_every",
            "eval_every",
            "checkpoint_every",
            "keep_checkpoints",
        ):
            _check_positive(f"train.{name}", getattr(self, name))
        for name in ("learning_rate", "weight_decay", "grad_clip_norm"):
            v = getattr(self, name)
            if v < 0 or not math.isfinite(v):
                _fail(f"train.{name}", f"must be finite and >= 0, got {v!r}")
        if not 0.0 <= self.ema_decay < 1.0:
            _fail("train.ema_decay", f"must lie in [0, 1) (0: off), got {self.ema_decay!r}")
        if not 0 <= self.warmup_steps <= self.total_steps:
            _fail("train.warmup_steps", f"must lie in [0, total_steps], got {self.warmup_steps}")


def check_train_seed(train: TrainConfig) -> None:
    """Refuses a ``train.seed`` outside [0, 2**32) when a run starts: ``jax.random.key``
    takes 32 bits here (2**32 was seed 0's run again) and numpy's generator refuses < 0 (at
    step 0, after config.json). Not a field check: a model file of an older version with
    such a seed still loads (inference never draws from it)."""
    if not 0 <= train.seed < SEED_LIMIT:
        _fail("train.seed", f"must lie in [0, 2**32) to start a run, got {train.seed}")


@dataclasses.dataclass(frozen=True)
class SimConfig:
    """Procedural scenes and simulated lidar frames (DESIGN section 10, ``indoorbev_sim``).

    Layout plans are named "kind/index" (kind in ``layouts``, index < ``plans_per_layout``);
    the test split draws only ``test_layouts``, train/val never do. ``test_variants``
    ("Class/variant", e.g. "Misc/trolley") appear only in the test split.
    """

    pattern: str = "mid360"  # "mid360", "vlp16", "os128" or "grid" (indoorbev_sim.patterns)
    num_rays: int = 20000  # rays per frame (MID-360: 200k points/s at 10 Hz)
    frames_per_sequence: int = 8  # T frames per scene in sequence mode
    frame_dt: float = 0.1  # seconds between frames
    min_points: int = 5  # objects with fewer lidar points leave the targets
    range_noise: float = 0.01  # metres, 1 sigma
    dropout: float = 0.02  # probability that a return is lost
    min_range: float = 0.1
    max_range: float = 40.0
    sensor_height: tuple[float, float] = (0.35, 0.8)  # lidar above the floor, metres
    # The lidar's roll, pitch, yaw in the robot's level frame, degrees (URDF rpy, as
    # indoorbev_jax.mount.LidarMount): a tilted sensor's coverage; the cloud comes levelled.
    sensor_rpy: tuple[float, float, float] = (0.0, 0.0, 0.0)
    # Each scene's lidar tilted from sensor_rpy by up to this many degrees (its roll and
    # pitch offsets uniform over a disk of this radius): one model for a range of mounts.
    sensor_tilt_jitter: float = 0.0
    ego_speed: tuple[float, float] = (0.2, 1.0)  # m/s of the robot carrying the lidar
    # Object slots per class (CLASS_NAMES order): the capacity of the scene template.
    slots_per_class: tuple[int, ...] = (4, 8, 2, 3, 3, 4, 4, 2, 3)
    max_scene_objects: int = 25  # also capped by data.max_objects
    clearance: float = 0.1  # metres between any two objects' reserved footprints
    placement_tries: int = 16  # candidate poses per object before it is left out
    bank_per_variant: int = 256  # pre-built random instances of each object variant
    layouts: tuple[str, ...] = ("office", "lab", "corridor", "hall")
    plans_per_layout: int = 8
    test_layouts: tuple[str, ...] = ("office/7", "lab/7", "corridor/7", "hall/7")
    test_variants: tuple[str, ...] = ("Misc/trolley",)

    def __post_init__(self):
        _check_types(self, "sim")
        for name in ("num_rays", "frames_per_sequence", "placement_tries", "plans_per_layout",
                     "bank_per_variant"):  # fmt: skip
            _check_positive(f"sim.{name}", getattr(self, name))
        for name in ("frame_dt", "max_range"):
            _check_positive(f"sim.{name}", getattr(self, name))
        for name in ("min_points", "max_scene_objects", "range_noise", "min_range", "clearance"):
            _check_non_negative(f"sim.{name}", getattr(self, name))
        if not 0.0 <= self.dropout < 1.0:
            _fail("sim.dropout", f"must lie in [0, 1), got {self.dropout!r}")
        if self.min_range >= self.max_range:
            _fail("sim.min_range", f"must be < max_range {self.max_range}, got {self.min_range}")
        for name in ("sensor_height", "ego_speed"):
            lo, hi = getattr(self, name)
            if not 0 <= lo <= hi:
                _fail(f"sim.{name}", f"expected 0 <= min <= max, got {getattr(self, name)!r}")
        _check_len("sim.sensor_rpy", self.sensor_rpy, 3)
        if not all(math.isfinite(a) for a in self.sensor_rpy):
            _fail("sim.sensor_rpy", f"expected finite degrees, got {self.sensor_rpy!r}")
        if not 0.0 <= self.sensor_tilt_jitter <= 90.0:
            _fail("sim.sensor_tilt_jitter", f"expected degrees in [0, 90], got "
                  f"{self.sensor_tilt_jitter!r}")  # fmt: skip
        _check_len("sim.slots_per_class", self.slots_per_class, len(CLASS_NAMES))
        if any(n < 0 for n in self.slots_per_class) or not sum(self.slots_per_class):
            _fail("sim.slots_per_class", f"need counts >= 0, not all 0: {self.slots_per_class}")
        patterns = ("mid360", "vlp16", "os128", "grid")
        if self.pattern not in patterns:
            _fail("sim.pattern", f"expected one of {patterns}, got {self.pattern!r}")
        if self.num_rays > MAX_RAYS:  # larger ran out of memory with a message naming no field
            _fail("sim.num_rays", f"at most {MAX_RAYS:,} rays per frame (an OS-128 frame casts "
                  f"131,072, a MID-360 one 20,000), got {self.num_rays:,}")  # fmt: skip
        if self.num_rays % {"mid360": 4, "vlp16": 16, "os128": 128, "grid": 32}[self.pattern]:
            _fail("sim.num_rays", f"must be a multiple of the beams of '{self.pattern}'")
        kinds = ("office", "lab", "corridor", "hall")
        if not self.layouts or any(k not in kinds for k in self.layouts):
            _fail("sim.layouts", f"expected a non-empty subset of {kinds}, got {self.layouts!r}")
        for name in self.test_layouts:
            kind, _, index = name.partition("/")
            if kind not in kinds or not index.isdigit() or int(index) >= self.plans_per_layout:
                _fail(
                    "sim.test_layouts",
                    f"'{name}' is not 'kind/index' with kind in {kinds} and "
                    f"index < plans_per_layout ({self.plans_per_layout})",
                )
        for name in self.test_variants:
            cls, _, variant = name.partition("/")
            if cls not in CLASS_NAMES or not variant:
                _fail("sim.test_variants", f"'{name}' is not 'Class/variant' with a known class")


@dataclasses.dataclass(frozen=True)
class Config:
    """Everything a run needs; see the module docstring for the presets."""

    name: str = "paper"
    grid: GridConfig = GridConfig()
    data: DataConfig = DataConfig()
    encoder: EncoderConfig = EncoderConfig()
    backbone: BackboneConfig = BackboneConfig()
    head: HeadConfig = HeadConfig()
    loss: LossConfig = LossConfig()
    inference: InferenceConfig = InferenceConfig()
    augment: AugmentConfig = AugmentConfig()
    train: TrainConfig = TrainConfig()
    sim: SimConfig = SimConfig()

    def __post_init__(self):
        if self.data.max_objects > self.head.num_queries:
            _fail(
                "data.max_objects",
                f"{self.data.max_objects} targets cannot all be matched to "
                f"{self.head.num_queries} queries (head.num_queries)",
            )
        if self.data.num_classes != len(CLASS_NAMES):
            _fail("data.class_names", f"the network has {len(CLASS_NAMES)} classes")
        check_views(self.inference.views, self.grid)

    @property
    def num_classes(self) -> int:
        return self.data.num_classes

    @property
    def has_seed_head(self) -> bool:
        """Whether the network has the dense seed head that ``losses.seed_loss`` trains."""
        return self.head.query_init == "select" or self.head.semantic_head

    @classmethod
    def paper(cls) -> Config:
        return cls()

    @classmethod
    def small(cls) -> Config:
        return cls(
            name="small",
            grid=GridConfig(cell_size=0.1),
            encoder=EncoderConfig(channels=32),
            backbone=BackboneConfig(
                embed_dims=(32, 64, 128, 256), num_heads=(1, 2, 4, 8), strides=(2, 2, 2, 2)
            ),
            # Skips give the 0.1 m masks the detail a 1.6 m stage-4 cell lacks; attending
            # to a 2 x 2 pooled memory cuts the CPU train step by a fifth.
            # The mask prior: 4-frame overfitting dice 0.420 vs 0.603 without, at 150 steps
            # (pooled classes off); mask-pooled class features keep the class loss
            # learning (docs/MODEL.md).
            head=HeadConfig(
                hidden_dim=32,
                num_heads=4,
                ffn_dim=128,
                upsampler_skips=True,
                memory_stride=2,
                mask_prior=True,
                mask_pooled_class=True,
            ),
            train=TrainConfig(learning_rate=2e-4, warmup_steps=200, total_steps=20_000),
        )

    @classmethod
    def tiny(cls) -> Config:
        return cls(
            name="tiny",
            grid=GridConfig(cell_size=0.25),
            data=DataConfig(max_points=2048, max_objects=8),
            encoder=EncoderConfig(channels=16),
            backbone=BackboneConfig(
                embed_dims=(16, 32, 32, 64), num_heads=(1, 2, 2, 4), window_size=3
            ),
            head=HeadConfig(hidden_dim=16, num_queries=8, num_layers=2, num_heads=2, ffn_dim=32),
            train=TrainConfig(
                batch_size=2,
                learning_rate=1e-3,
                warmup_steps=2,
                total_steps=20,
                log_every=5,
                eval_every=10,
                checkpoint_every=5,
                keep_checkpoints=2,
                eval_batches=1,
            ),
            sim=SimConfig(
                num_rays=2048,
                frames_per_sequence=2,
                slots_per_class=(2, 2, 1, 1, 1, 2, 2, 1, 2),
                placement_tries=8,
            ),
        )

    @classmethod
    def preset(cls, name: str) -> Config:
        presets = {"paper": cls.paper, "small": cls.small, "tiny": cls.tiny}
        if name not in presets:
            raise ConfigError(f"unknown preset '{name}', expected one of {sorted(presets)}")
        return presets[name]()

    def to_dict(self) -> dict[str, Any]:
        return dataclasses.asdict(self)

    def stable_dict(self) -> dict[str, Any]:
        """``to_dict`` without the ``LATER_FIELDS`` that hold their defaults: what files
        compare configs by (a model's hash in predict.json, export.json), so that the files
        written before such a field existed still match the same config."""
        d = self.to_dict()
        for path, default in LATER_FIELDS.items():
            section, name = path.split(".")
            if getattr(getattr(self, section), name) == default:
                del d[section][name]
        return d

    def to_json(self) -> str:
        return json.dumps(self.to_dict(), indent=2)

    @classmethod
    def from_dict(cls, d: dict[str, Any]) -> Config:
        """Inverse of ``to_dict`` (lists become tuples); unknown keys are an error, and so
        are missing ones but the ``OPTIONAL_FIELDS`` (their defaults)."""
        missing: list[str] = []
        config = _from_dict(cls, d, "", missing)
        # A field left out took its default: a model file without head.mask_prior ran with
        # the prior off and detected nothing, exit 0.
        if missing:
            raise ConfigError(f"missing config field(s) {sorted(missing)}")
        return config

    @classmethod
    def from_file_dict(cls, d: dict[str, Any], path: str | os.PathLike) -> Config:
        """``from_dict`` of a config read from ``path`` (a run's config.json, a model
        file): its errors name the file."""
        try:
            return cls.from_dict(d)
        except ConfigError as e:
            raise ConfigError(f"{path}: {e}") from None


# Fields added after files recording a config were written, with their defaults (the
# behaviour before them): ``Config.stable_dict`` leaves them out at the default.
LATER_FIELDS: dict[str, Any] = {"sim.sensor_rpy": (0.0, 0.0, 0.0), "sim.sensor_tilt_jitter": 0.0}

# The fields a config read from a file may lack, with their defaults (the behaviour before
# them): the ``LATER_FIELDS`` and those added after model files were shipped, which files
# written since always hold (so unlike the ``LATER_FIELDS`` they count in a model's hash).
OPTIONAL_FIELDS: dict[str, Any] = {
    **LATER_FIELDS,
    "train.ema_decay": 0.0,
    "augment.intensity_drop_prob": 0.0,
    "inference.views": ("identity",),
    "inference.view_iou": 0.5,
}


def check_section(arg: str, value, kind: type, field: str):
    """``value`` if it is a ``kind``, else a ``TypeError`` naming ``arg``: a whole ``Config``
    given for its section ``field`` failed later, with an AttributeError of some field."""
    if not isinstance(value, kind):
        hint = f"; pass config.{field}" if isinstance(value, Config) else ""
        raise TypeError(f"{arg}: expected {kind.__name__}, got {type(value).__name__}{hint}")
    return value


def _from_dict(kind, d: dict[str, Any], prefix: str, missing: list[str]):
    """``kind`` from ``d``, its sections included; adds the fields ``d`` lacks but the
    ``OPTIONAL_FIELDS`` to ``missing`` (they take their defaults)."""
    if not isinstance(d, dict):
        section = prefix.rstrip(".") or "config"
        raise ConfigError(f"config section '{section}': expected an object, got {d!r}")
    fields = {f.name: f for f in dataclasses.fields(kind)}
    unknown = set(d) - set(fields)
    if unknown:
        raise ConfigError(f"unknown config field(s) {sorted(prefix + k for k in unknown)}")
    missing += [prefix + k for k in fields if k not in d and prefix + k not in OPTIONAL_FIELDS]
    hints = typing.get_type_hints(kind)
    kwargs = {}
    for name, value in d.items():
        if isinstance(hints[name], type) and dataclasses.is_dataclass(hints[name]):  # a section
            value = _from_dict(hints[name], value, f"{prefix}{name}.", missing)
        else:
            # A hand-edited config.json ("2" for 2, "false" for false) fails here, naming the
            # field, rather than deep inside a jitted function.
            try:
                value = _as_type(value, hints[name])
            except TypeError:
                msg = f"got {value!r}, expected {_describe(hints[name])}"
                raise ConfigError(f"config field '{prefix}{name}': {msg}") from None
            except NotImplementedError:  # a type --set does not parse either: as given
                value = _to_tuple(value) if isinstance(value, list) else value
        kwargs[name] = value
    return kind(**kwargs)


def _to_tuple(value):
    return tuple(_to_tuple(v) if isinstance(v, list) else v for v in value)


def config_diff(a: Config, b: Config) -> dict[str, tuple[Any, Any]]:
    """The fields where ``a`` and ``b`` differ, as ``{"section.field": (a's, b's)}``."""
    flat_a, flat_b = flatten_dict(a.to_dict()), flatten_dict(b.to_dict())
    return {k: (flat_a[k], flat_b[k]) for k in flat_a if flat_a[k] != flat_b[k]}


def flatten_dict(d: dict[str, Any], prefix: str = "") -> dict[str, Any]:
    """Nested dicts as one level with dotted keys: ``{"grid": {"cell_size": 0.1}}`` ->
    ``{"grid.cell_size": 0.1}``."""
    out = {}
    for name, value in d.items():
        if isinstance(value, dict):
            out.update(flatten_dict(value, f"{prefix}{name}."))
        else:
            out[prefix + name] = value
    return out


def _describe(hint) -> str:
    if hint is bool:
        return "bool (true, false, 1 or 0)"
    if isinstance(hint, type):
        return hint.__name__
    if typing.get_origin(typing.get_args(hint)[0]) is tuple:
        return f"{hint} as a JSON list of pairs or a JSON object"
    return f"{hint} as a JSON list"


def with_overrides(config: Config, items: list[str] | tuple[str, ...]) -> Config:
    """``config`` with ``SECTION.FIELD=VALUE`` overrides, as the experiment scripts' ``--set``
    passes them::

        cfg = with_overrides(Config.small(), ["head.upsampler_skips=false", "data.max_objects=20"])

    VALUE is checked against the field's annotation: a bool takes true/false/1/0 (any case),
    an int an integral number, a float any number, a str the text as given (or a quoted JSON
    string), a tuple a JSON list of such values (a JSON object for ``data.class_map``).

    Raises:
      ConfigError: naming the item, for a malformed item, an unknown field or a bad value.
    """
    d = config.to_dict()
    for item in items:
        path, sep, raw = item.partition("=")
        parts = path.split(".")
        if not sep or len(parts) != 2 or not isinstance(d.get(parts[0]), dict):
            sections = [k for k, v in d.items() if isinstance(v, dict)]
            raise ConfigError(
                f"{item!r}: expected SECTION.FIELD=VALUE, e.g. head.remat=true "
                f"(sections: {', '.join(sections)})"
            )
        section, name = parts
        if name not in d[section]:
            raise ConfigError(
                f"{item!r}: {section} has no field '{name}' (fields: {', '.join(d[section])})"
            )
        hint = typing.get_type_hints(type(getattr(config, section)))[name]
        try:
            value = json.loads(raw)
        except json.JSONDecodeError:
            value = raw
        if hint is str and not isinstance(value, str):
            value = raw  # text that happens to be JSON (a number, null) is still text
        try:
            d[section][name] = _as_type(value, hint)
        except TypeError:
            msg = f"got {raw!r}, expected {_describe(hint)}"
            raise ConfigError(f"config field '{path}': {msg}") from None
    return Config.from_dict(d)


# Every config is a pytree without leaves (its values are static): ``jax.jit(f)(x, grid)``
# and ``jax.vmap(f)(x, grid)`` then work without ``static_argnums`` / ``in_axes=None``, and
# jit retraces when a config value changes (they are frozen, so hashable).
for _kind in (GridConfig, DataConfig, EncoderConfig, BackboneConfig, HeadConfig, LossConfig,
              InferenceConfig, AugmentConfig, TrainConfig, SimConfig, Config):  # fmt: skip
    jax.tree_util.register_static(_kind)


# Command lines ----------------------------------------------------------------------------

# (flag, train field, type, help) of the options experiments/train.py and sweep.py share.
_TRAIN_FLAGS = (
    ("--steps", "total_steps", int,
     "training steps, train.total_steps (alone it also caps train.warmup_steps)"),
    ("--batch-size", "batch_size", int, "frames per training step, train.batch_size"),
    ("--learning-rate", "learning_rate", float,
     "peak learning rate after the linear warm-up, train.learning_rate"),
    ("--warmup-steps", "warmup_steps", int, "steps of learning-rate warm-up, train.warmup_steps"),
    ("--eval-every", "eval_every", int, "steps between validations, train.eval_every"),
    ("--checkpoint-every", "checkpoint_every", int,
     "steps between checkpoints, train.checkpoint_every"),
    ("--seed", "seed", int,
     "root seed of the run (initialisation, batches, augmentation), train.seed"),
)  # fmt: skip


def add_config_arguments(parser, skip: tuple[str, ...] = ()) -> None:
    """The config options of the training scripts on an ``argparse`` parser: ``--preset``,
    the ``train`` fields of ``_TRAIN_FLAGS`` (less the flags in ``skip``), ``--no-augment``,
    ``--bfloat16`` and ``--set FIELD=VALUE``; ``config_from_args`` reads them back."""
    parser.add_argument(
        "--preset",
        default="small",
        choices=("paper", "small", "tiny"),
        help="config preset: the model, grid and training settings the other options change",
    )
    for flag, _, kind, text in _TRAIN_FLAGS:
        if flag not in skip:
            parser.add_argument(flag, type=kind, help=f"{text} (default: the preset's)")
    parser.add_argument(
        "--no-augment",
        action="store_true",
        help="train without the augmentation chain (train.augment = False)",
    )
    parser.add_argument(
        "--bfloat16",
        action="store_true",
        help="compute in bfloat16 (train.bfloat16 = True; worthwhile on GPUs)",
    )
    parser.add_argument(
        "--set",
        action="append",
        default=[],
        metavar="FIELD=VALUE",
        help="override a config field, SECTION.FIELD (any section's), VALUE checked against "
        "its type (repeatable), e.g. --set head.upsampler_skips=false --set "
        "augment.gt_sampling=4",
    )


def config_from_args(args) -> Config:
    """The config that ``add_config_arguments``' options give; a value the config refuses
    (``--batch-size 0``, ``--steps`` below ``--warmup-steps``, a bad ``--set``) exits with
    one line and status 2, as argparse's errors do. ``--steps`` alone caps
    ``train.warmup_steps`` at the new total."""
    config = Config.preset(args.preset)
    train = {
        field: getattr(args, flag[2:].replace("-", "_"), None) for flag, field, *_ in _TRAIN_FLAGS
    }
    train = {k: v for k, v in train.items() if v is not None}
    if args.no_augment:
        train["augment"] = False
    if args.bfloat16:
        train["bfloat16"] = True
    if "total_steps" in train and "warmup_steps" not in train:
        train["warmup_steps"] = min(config.train.warmup_steps, train["total_steps"])
    prog = os.path.basename(sys.argv[0]) or "indoorbev"
    try:
        config = dataclasses.replace(config, train=dataclasses.replace(config.train, **train))
    except ConfigError as e:
        print(f"{prog}: error: {e}", file=sys.stderr)
        raise SystemExit(2) from None
    try:
        return with_overrides(config, args.set)
    except ConfigError as e:
        print(f"{prog}: error: --set: {e}", file=sys.stderr)
        raise SystemExit(2) from None
