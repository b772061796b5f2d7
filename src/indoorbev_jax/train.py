"""Training: one jitted step (augment -> forward -> match -> loss -> update), exact resume.

``train_and_evaluate(config, workdir)`` is what ``experiments/train.py`` runs. The run
directory holds ``config.json``, ``run.json`` (the kind of run and the data source),
``metrics.jsonl`` (one JSON object a line), TensorBoard event files under ``tb/``, orbax
checkpoints under ``checkpoints/`` (the latest ``train.keep_checkpoints``) and ``best/``
(the best by validation ``metric``).

Exact resume: the data of step s and every random key of step s are pure functions of
(seed, s), and the state is restored bit for bit, so a run killed at any point and
restarted with the same command ends with the parameters of an uninterrupted run.

Values a sweep varies (learning rate, loss weights) live in ``Hyper`` and enter the step as
arrays, so ``jax.vmap`` over a leading axis of K states and K ``Hyper`` trains K models at
once (``experiments/sweep.py``).
"""

from __future__ import annotations

import collections
import functools
import hashlib
import json
import logging
import math
import os
import queue
import threading
import time
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any, NamedTuple

import jax
import jax.numpy as jnp
import numpy as np
import optax
import orbax.checkpoint as ocp
from flax import struct
from jax.sharding import Mesh, NamedSharding, PartitionSpec

from indoorbev_jax.augment import ObjectDatabase, augment_batch, build_object_database
from indoorbev_jax.config import Config, check_train_seed, config_diff
from indoorbev_jax.data import kitti
from indoorbev_jax.data.rasterize import rasterize_boxes
from indoorbev_jax.losses import seed_loss, set_loss
from indoorbev_jax.models import IndoorBEV
from indoorbev_jax.types import Batch
from indoorbev_jax.xla_flags import train_compiler_options

log = logging.getLogger("indoorbev_jax.train")

# What each use of the run's root key ``key(train.seed)`` folds in: one constant per use, so
# no two uses within a run draw the same numbers. The data streams keep 0 and 1, which
# ``experiments/eval_sim.py`` keeps its val and test frames clear of. (``indoorbev-sim export
# --seed a`` roots its scene j at ``fold_in(key(a), j)``, so its scenes 0-3 share these
# keys in another role: no scene key is shared, so no frame is.)
KEY_TRAIN_DATA, KEY_VAL_DATA, KEY_INIT, KEY_STEPS = 0, 1, 2, 3

# Fields a resumed run may change: they set when to log, evaluate and checkpoint and how many
# checkpoints to keep, never what the parameters become. Not ``train.total_steps`` (the
# cosine schedule ends at it) nor ``train.eval_batches`` or ``inference.*`` (they change the
# validation scores that rank ``best/``).
RESUME_MAY_CHANGE = frozenset(
    {"train.log_every", "train.eval_every", "train.checkpoint_every", "train.keep_checkpoints"}
)


@struct.dataclass
class TrainState:
    """Everything that changes during training; checkpointed whole.

    Attributes:
      step: int32 scalar, steps taken so far.
      params: model parameters.
      opt_state: optax state (learning rate among its hyperparameters).
      skipped: int32 scalar, steps whose loss or gradients were not finite (not applied).
    """

    step: jax.Array
    params: Any
    opt_state: Any
    skipped: jax.Array


SEED_KEY = "seed"  # Hyper.weights entry of the seed loss (losses.seed_loss)


@struct.dataclass
class Hyper:
    """Traced hyperparameters: a leading axis K of these trains K models under vmap.

    Attributes:
      learning_rate: peak learning rate (scalar array).
      weights: loss weights as ``LossConfig.weights()`` names them, plus ``"background"``
        and, when the network has the seed head, ``"seed"`` (scalar arrays).
    """

    learning_rate: jax.Array
    weights: dict[str, jax.Array]

    @classmethod
    def from_config(cls, config: Config) -> Hyper:
        weights = config.loss.weights()
        weights["background"] = config.loss.background_weight
        if config.has_seed_head:
            weights[SEED_KEY] = config.loss.seed_weight
        return cls(
            learning_rate=jnp.float32(config.train.learning_rate),
            weights={k: jnp.float32(v) for k, v in weights.items()},
        )


def lr_factor(step: jax.Array, warmup: int, total: int) -> jax.Array:
    """Linear warm-up from 0 to 1 over ``warmup`` steps, then cosine decay to 0 at ``total``."""
    step = jnp.asarray(step, jnp.float32)
    warm = step / max(warmup, 1)
    progress = jnp.clip((step - warmup) / max(total - warmup, 1), 0.0, 1.0)
    cosine = 0.5 * (1.0 + jnp.cos(jnp.pi * progress))
    return jnp.where(step < warmup, warm, cosine)


class ParamsEmaState(NamedTuple):
    """``params_ema``'s state: the average of the parameters after each update."""

    ema: Any


def params_ema(decay: float) -> optax.GradientTransformation:
    """Keeps ``ema <- decay * ema + (1 - decay) * (params + updates)`` in its state, the
    parameters after each step, and passes the updates on unchanged (last in a chain)."""

    def init(params):
        # A copy: the train step donates its state, and a buffer held twice cannot be.
        return ParamsEmaState(ema=jax.tree.map(jnp.copy, params))

    def update(updates, state, params=None):
        if params is None:
            raise ValueError("params_ema needs the parameters: optimizer.update(g, s, params)")
        new = optax.apply_updates(params, updates)
        ema = jax.tree.map(lambda e, p: decay * e + (1.0 - decay) * p, state.ema, new)
        return updates, ParamsEmaState(ema=ema)

    return optax.GradientTransformation(init, update)


def make_optimizer(config: Config) -> optax.GradientTransformation:
    """Gradient clipping + AdamW whose learning rate the step sets (``inject_hyperparams``),
    + the parameters' moving average when ``train.ema_decay`` > 0."""
    t = config.train
    clip = optax.clip_by_global_norm(t.grad_clip_norm) if t.grad_clip_norm else optax.identity()
    adamw = optax.inject_hyperparams(optax.adamw)(
        learning_rate=t.learning_rate, weight_decay=t.weight_decay
    )
    if t.ema_decay:
        return optax.chain(clip, adamw, params_ema(t.ema_decay))
    return optax.chain(clip, adamw)


def _set_learning_rate(opt_state, lr: jax.Array):
    clip_state, adam_state, *rest = opt_state
    hyper = dict(adam_state.hyperparams, learning_rate=jnp.asarray(lr, jnp.float32))
    return (clip_state, adam_state._replace(hyperparams=hyper), *rest)


def eval_params(state: TrainState) -> Any:
    """The parameters to evaluate and export: their moving average when the run keeps one
    (``train.ema_decay``), else the trained ones."""
    ema = [s for s in state.opt_state if isinstance(s, ParamsEmaState)]
    return ema[0].ema if ema else state.params


def init_state(config: Config, key: jax.Array) -> TrainState:
    """Fresh parameters and optimizer state for ``config`` (one jitted program: run
    eagerly, ``init`` would compile hundreds of small ones)."""
    model = IndoorBEV(config)
    n = config.data.max_points

    @jax.jit
    def init(key):
        params = model.init(key, jnp.zeros((1, n, 4)), jnp.zeros((1, n), bool))
        return TrainState(
            step=jnp.int32(0),
            params=params,
            opt_state=make_optimizer(config).init(params),
            skipped=jnp.int32(0),
        )

    return init(key)


def with_pretrained(
    state: TrainState, config: Config, source: str | os.PathLike, *, strict: bool = True
) -> TrainState:
    """``state`` with the parameters of a trained model (fresh optimizer state).

    ``source`` is a run directory or an exported model file (``predict.load_model``). Its grid
    and class names must equal the run's. With ``strict`` its parameter tree must match name
    for name and shape for shape; the error names the first difference. Without it, every
    parameter the two share by name and shape is loaded, the rest keep ``state``'s fresh
    values and the source's extra ones are dropped (``train_and_evaluate`` logs both lists and
    keeps them in ``init_from.json``), e.g. to start the paper-mode upsampler
    (``head.upsampler_skips=false``) from a model with skips.
    """
    return _load_pretrained(state, config, source, strict)[0]


def _load_pretrained(
    state: TrainState, config: Config, source: str | os.PathLike, strict: bool
) -> tuple[TrainState, dict[str, list[str]]]:
    """``with_pretrained`` and its report: ``fresh`` (the run's parameters not loaded, with
    the reason) and ``unused`` (the source's parameters the run has no place for)."""
    from indoorbev_jax.predict import load_model

    src_config, params = load_model(source)
    for field in ("grid", "data.class_names"):
        ours, theirs = config, src_config
        for part in field.split("."):
            ours, theirs = getattr(ours, part), getattr(theirs, part)
        if ours != theirs:
            raise ValueError(
                f"{source}: config field '{field}' is {theirs!r}, the run has {ours!r}"
            )
    leaves, treedef = jax.tree_util.tree_flatten_with_path(state.params)
    want = dict(leaves)
    have = dict(jax.tree_util.tree_flatten_with_path(params)[0])
    report: dict[str, list[str]] = {"fresh": [], "unused": []}
    matched = set()
    for path in sorted(want.keys() | have.keys(), key=jax.tree_util.keystr):
        name = jax.tree_util.keystr(path)
        if path not in have:
            problem = f"parameter {name} is missing"
            report["fresh"].append(f"{name} (missing)")
        elif path not in want:
            problem = f"parameter {name} is not in the run's model"
            report["unused"].append(name)
        elif np.shape(have[path]) != want[path].shape:
            problem = (
                f"parameter {name} has shape {np.shape(have[path])}, "
                f"the run's model expects {want[path].shape}"
            )
            report["fresh"].append(f"{name} (shape {np.shape(have[path])} != {want[path].shape})")
        else:
            matched.add(path)
            continue
        if strict:
            raise ValueError(f"{source}: {problem}")
    if not matched:
        raise ValueError(f"{source}: no parameter matches the run's model by name and shape")
    loaded = [
        jnp.asarray(have[path], leaf.dtype) if path in matched else leaf for path, leaf in leaves
    ]
    params = jax.tree_util.tree_unflatten(treedef, loaded)
    state = state.replace(params=params, opt_state=make_optimizer(config).init(params))
    return state, report


def _all_finite(tree) -> jax.Array:
    leaves = [jnp.isfinite(x).all() for x in jax.tree.leaves(tree)]
    return jnp.stack(leaves).all()


def jit_train_step(config: Config, step: Callable, **jit_kwargs) -> Callable:
    """``jax.jit`` of a train step (plain or vmapped) with the compiler options of
    ``config``'s grid (``xla_flags.train_compiler_options``), so every train step compiles
    alike: training, sweeps, benchmarks and tests."""
    options = train_compiler_options(config.grid.shape)
    return jax.jit(step, compiler_options=options, **jit_kwargs)


def make_train_step(
    config: Config, database: ObjectDatabase | None = None
) -> Callable[[TrainState, Batch, jax.Array, Hyper], tuple[TrainState, dict]]:
    """The un-jitted train step ``(state, batch, key, hyper) -> (state, metrics)``.

    ``key`` is the run's base key; the step's own keys come from ``fold_in(key, step)``.
    A step whose loss or gradients are not finite leaves params and optimizer state as
    they were and counts itself in ``state.skipped``.
    """
    model = IndoorBEV(config)
    optimizer = make_optimizer(config)
    t = config.train
    needs_loss_key = config.loss.num_mask_points > 0
    seeded = config.has_seed_head

    def step_fn(state: TrainState, batch: Batch, key: jax.Array, hyper: Hyper):
        k_aug, k_loss = jax.random.split(jax.random.fold_in(key, state.step))
        if t.augment:
            batch = training_batch(config, batch, k_aug, database)

        def loss_fn(params):
            if seeded:
                predictions, inter = model.apply(
                    params, batch.points, batch.point_valid, mutable=["intermediates"]
                )
            else:
                predictions = model.apply(params, batch.points, batch.point_valid)
            loss, parts = set_loss(
                predictions,
                batch.targets,
                {k: v for k, v in hyper.weights.items() if k != SEED_KEY},
                config.loss,
                key=k_loss if needs_loss_key else None,
            )
            if seeded:
                (seeds,) = inter["intermediates"]["head"]["seeds"]
                parts["seed"] = seed_loss(seeds, batch.targets, config.loss)
                seed_weight = hyper.weights.get(SEED_KEY, config.loss.seed_weight)
                loss = loss + seed_weight * parts["seed"]
            return loss, parts

        (loss, parts), grads = jax.value_and_grad(loss_fn, has_aux=True)(state.params)
        finite = jnp.isfinite(loss) & _all_finite(grads)
        lr = hyper.learning_rate * lr_factor(state.step, t.warmup_steps, t.total_steps)
        opt_state = _set_learning_rate(state.opt_state, lr)
        updates, new_opt_state = optimizer.update(grads, opt_state, state.params)
        new_params = optax.apply_updates(state.params, updates)
        keep = lambda new, old: jax.tree.map(lambda a, b: jnp.where(finite, a, b), new, old)  # noqa: E731
        state = TrainState(
            step=state.step + 1,
            params=keep(new_params, state.params),
            opt_state=keep(new_opt_state, state.opt_state),
            skipped=state.skipped + (~finite).astype(jnp.int32),
        )
        metrics = {
            "loss": loss,
            "learning_rate": lr,
            "grad_norm": optax.tree.norm(grads),
            "finite": finite,
            **{k: v for k, v in parts.items() if k != "num_targets"},
        }
        return state, metrics

    return step_fn


# Data -------------------------------------------------------------------------------------


def data_mesh(devices=None) -> Mesh:
    """A 1-D mesh over all (or the given) devices; the batch is split along ``data``."""
    devices = np.asarray(jax.devices() if devices is None else devices)
    return Mesh(devices, ("data",))


def process_rows(batch: Batch, index: int | None = None, count: int | None = None) -> Batch:
    """Process ``index``'s rows of a global batch of B frames: rows index * B / count up to
    (index + 1) * B / count (default: this process of ``jax.process_count()``; one process
    keeps them all)."""
    count = jax.process_count() if count is None else count
    if count == 1:
        return batch
    index = jax.process_index() if index is None else index
    b = jax.tree.leaves(batch)[0].shape[0]
    if b % count:
        raise ValueError(f"train.batch_size={b} does not split over {count} processes")
    n = b // count
    return jax.tree.map(lambda x: x[index * n : (index + 1) * n], batch)


def shard_batch(batch: Batch, mesh: Mesh) -> Batch:
    """Places the global batch on the mesh, split along its leading axis.

    Multi-host (after ``jax.distributed.initialize()``) every process makes the same global
    batch (same seed and step) and passes its own rows (``process_rows``), so N hosts train
    on the batch one host would (each passed the whole batch until 2026-12-06, which made
    the global batch N copies of it).
    """
    batch = process_rows(batch)
    sharding = NamedSharding(mesh, PartitionSpec("data"))

    def place(x):
        # A simulated batch is already on the device: move it there, not through the host.
        if isinstance(x, jax.Array) and jax.process_count() == 1:
            return jax.device_put(x, sharding)
        return jax.make_array_from_process_local_data(sharding, np.asarray(x))

    return jax.tree.map(place, batch)


def replicate(tree, mesh: Mesh):
    return jax.device_put(tree, NamedSharding(mesh, PartitionSpec()))


def box_targets(batch: Batch, grid) -> Batch:
    """The batch with each object's footprint replaced by its rasterised labelled box
    (``data.mask_targets = "box"``, the ablation against true-shape targets)."""
    t = batch.targets
    boxes = jnp.concatenate([t.pos[..., :2], t.dims[..., :2], t.yaw[..., None]], -1)  # [B, M, 5]
    ids, masks = jax.vmap(rasterize_boxes, in_axes=(0, 0, None))(boxes, t.valid, grid)
    return batch.replace(targets=t.replace(masks=masks, instance_ids=ids))


def training_batch(
    config: Config, batch: Batch, key: jax.Array, database: ObjectDatabase | None = None
) -> Batch:
    """The augmented batch a train step learns from (``train.augment``). With
    ``data.mask_targets = "box"`` the augmented boxes are rasterised afresh: the source's
    rasterised boxes, warped cell by cell, are not the boxes (mean IoU 0.81 with them in
    helper-54's run)."""
    batch = augment_batch(key, batch, config.grid, config.augment, database)
    if config.data.mask_targets == "box":
        batch = box_targets(batch, config.grid)
    return batch


def gt_database(source: Callable[[int], Batch], batches: int, grid) -> ObjectDatabase:
    """Object database for ground-truth sampling from the first ``batches`` training batches
    (``augment.gt_sampling > 0``)."""
    frames = jax.tree.map(lambda *xs: np.concatenate(xs), *[source(i) for i in range(batches)])
    database = build_object_database(frames, grid)  # one compile for all the frames
    if database.classes.shape[0] == 0:
        raise ValueError(
            f"augment.gt_sampling: the first {batches} training batches hold no object clear "
            "of the grid's edge to paste (the object database is empty); set "
            "augment.gt_sampling=0 or check the data's labels"
        )
    return database


class SimSource:
    """On-device simulated batches: batch of step s = ``generate_batch(fold_in(key, s))``
    from the simulator's ``split`` (train, val or test layouts)."""

    def __init__(self, config: Config, key: jax.Array, split: str = "train"):
        from indoorbev_sim import generate_batch

        self.key = key
        self._generate = jax.jit(lambda k: generate_batch(k, config, split))

    def __call__(self, step: int) -> Batch:
        return self._generate(jax.random.fold_in(self.key, step))


class KittiSource:
    """Batches from a KITTI-style folder, reshuffled each epoch from (seed, epoch).

    A frame that fails to load is reported by name; with ``skip_bad`` it is replaced by the
    next good frame of the epoch, otherwise the error stops the run at once.
    """

    def __init__(self, root, split: str, config: Config, seed: int, skip_bad: bool = False):
        from indoorbev_jax.data.dataset import KittiDataset

        self.dataset = KittiDataset(root, split, config)
        self.batch_size = config.train.batch_size
        if len(self.dataset) < self.batch_size:
            raise ValueError(
                f"{root}/{split}.txt: {len(self.dataset)} frames, fewer than "
                f"train.batch_size={self.batch_size}"
            )
        self.seed = seed
        self.skip_bad = skip_bad
        self.bad: set[int] = set()
        if not skip_bad:  # before the run starts (and writes config.json), not at step k
            for frame_id in self.dataset.ids:
                path = kitti.frame_paths(root, frame_id)["labels"]
                _check_object_count(path, len(kitti.read_labels(path, config.data)), config)

    def _order(self, epoch: int) -> np.ndarray:
        return np.random.default_rng([self.seed, epoch]).permutation(len(self.dataset))

    def __call__(self, step: int) -> Batch:
        from indoorbev_jax.data.dataset import collate

        per_epoch = len(self.dataset) // self.batch_size
        epoch, k = divmod(step, per_epoch)
        order = self._order(epoch)
        items, pos = [], k * self.batch_size
        while len(items) < self.batch_size:
            index = int(order[pos % len(order)])
            pos += 1
            if index in self.bad:
                continue
            frame = load_or_skip(self.dataset, index, self.skip_bad, "frame")
            if frame is not None:
                items.append(frame)
                continue
            self.bad.add(index)
            if len(self.bad) == len(self.dataset):
                raise kitti.DatasetError(f"{self.dataset.root}: no readable frame left")
        return collate(items)


def _check_object_count(path, objects: int, config: Config) -> None:
    """More objects than ``data.max_objects`` is an error: the targets keep the first
    ones, and the rest would train (and be scored) as background, without a word."""
    limit = config.data.max_objects
    if objects > limit:
        raise kitti.DatasetError(
            f"{path}: {objects} objects, more than data.max_objects={limit} (the rest would "
            f"be background targets); --set data.max_objects={objects} or more"
        )


def _rank(value) -> float:
    """A validation metric as ``best/`` ranks it: NaN or missing (JSON null) is -inf."""
    return float(value) if value is not None and math.isfinite(value) else -math.inf


def load_or_skip(dataset, index: int, skip_bad: bool, kind: str) -> Batch | None:
    """Frame ``index`` of a ``KittiDataset``; a malformed one (or one with more objects than
    ``data.max_objects``) raises its error naming the file, or with ``skip_bad`` is
    reported by name (as a ``kind``) and gives None."""
    try:
        frame, stats = dataset.load(index)
        path = kitti.frame_paths(dataset.root, dataset.ids[index])["labels"]
        _check_object_count(path, stats.objects, dataset.config)
        return frame
    except (kitti.DatasetError, OSError) as e:
        if not skip_bad:
            raise
        log.warning("skipping malformed %s %s: %s", kind, dataset.ids[index], e)
        return None


def prefetch(source: Callable[[int], Batch], start: int, stop: int, size: int = 2) -> Iterator:
    """Yields ``source(s)`` for s in [start, stop), computed ``size`` steps ahead on a
    background thread; an error in the source is raised at the step it belongs to."""
    q: queue.Queue = queue.Queue(maxsize=size)
    done = threading.Event()

    def work():
        for s in range(start, stop):
            if done.is_set():
                return
            try:
                item = (s, source(s), None)
            except Exception as e:  # noqa: BLE001 - handed to the consumer
                item = (s, None, e)
            q.put(item)
            if item[2] is not None:
                return

    worker = threading.Thread(target=work, daemon=True, name="indoorbev-prefetch")
    worker.start()
    try:
        for _ in range(start, stop):
            s, batch, error = q.get()
            if error is not None:
                raise error
            yield s, batch
    finally:
        done.set()
        # Let the worker stop and finish what it dispatched: the simulator's Warp kernels
        # call back into Python, and an interpreter that shuts down under a queued one
        # can hang in its exit (seen after an error raised mid-run).
        while worker.is_alive() or not q.empty():
            try:
                _, batch, _ = q.get(timeout=0.1)
            except queue.Empty:
                continue
            if batch is not None:
                jax.block_until_ready(batch)


# Checkpoints ------------------------------------------------------------------------------


def _layout(tree) -> collections.Counter:
    """How many arrays of each (shape, dtype) a tree of arrays or array metadata holds."""
    leaves = [x for x in jax.tree.leaves(tree) if hasattr(x, "shape")]
    return collections.Counter((tuple(x.shape), str(np.dtype(x.dtype))) for x in leaves)


def _check_layout(folder: Path, stored, abstract) -> None:
    """Raises ``ValueError`` when checkpoint ``folder`` (its orbax metadata ``stored``) holds
    arrays of other shapes than ``abstract``, naming one that differs."""
    have, want = _layout(stored), _layout(abstract)
    if have == want:
        return
    extra = next(iter(have - want), None)
    missing = next(iter(want - have), None)
    raise ValueError(
        f"{folder}: holds {sum(have.values())} arrays, this run's state has "
        f"{sum(want.values())}, and they differ (e.g. stored {extra}, expected {missing}): "
        "the workdir holds another kind of run (a sweep's K stacked models, or a model of "
        "another config or code version). Nothing was changed; use another workdir"
    )


class Checkpoints:
    """Orbax checkpoints: the latest ``keep`` under ``checkpoints/``, the best by a
    validation metric under ``best/``. Restoring falls back to older checkpoints, with a
    warning, when the latest is corrupt or partial."""

    def __init__(self, workdir: Path, keep: int, metric: str | None = "pq"):
        """``metric`` None: no ``best/`` (a sweep, which does not validate)."""
        self.metric = metric
        options = ocp.CheckpointManagerOptions(max_to_keep=keep, enable_async_checkpointing=False)
        # One unnamed item, said up front: left to infer it, orbax reads the layout off the
        # newest step folder, and a partial one (empty, no default/) makes every step fail.
        single = ocp.StandardCheckpointHandler
        self.latest = ocp.CheckpointManager(
            Path(workdir).absolute() / "checkpoints", options=options, item_handlers=single()
        )
        self.unreadable: set[int] = set()  # steps restore() skipped: save() replaces them
        if metric is None:
            self.best = None
            return
        best_options = ocp.CheckpointManagerOptions(
            max_to_keep=1,
            # NaN (a validation split without objects, nothing predicted) ranks last: as a
            # number it replaced a better best/ for good.
            best_fn=lambda m: _rank(m[metric]),
            best_mode="max",
            enable_async_checkpointing=False,
        )
        self.best = ocp.CheckpointManager(
            Path(workdir).absolute() / "best", options=best_options, item_handlers=single()
        )

    def save(self, state: TrainState, step: int | None = None) -> None:
        """Saves ``state`` as ``step`` (default ``state.step``; a sweep's states hold K)."""
        step = int(state.step) if step is None else step
        if step in self.unreadable:  # a corrupt one the run fell back past: write it anew
            self.latest.delete(step)
            self.unreadable.discard(step)
        if step not in self.latest.all_steps():
            self.latest.save(step, args=ocp.args.StandardSave(state))

    def save_best(self, state: TrainState, metrics: dict) -> None:
        step = int(state.step)
        if step not in self.best.all_steps():
            self.best.save(
                step, args=ocp.args.StandardSave(state), metrics={self.metric: metrics[self.metric]}
            )

    def restore(self, template: TrainState) -> TrainState | None:
        """The newest readable checkpoint, or None when there is none. A checkpoint whose
        arrays are not the template's (another kind of run: a sweep's K stacked models, a
        model of another shape) raises ``ValueError``: falling back past it would delete it."""
        abstract = jax.tree.map(ocp.utils.to_shape_dtype_struct, template)
        self.latest.reload()
        for step in sorted(self.latest.all_steps(), reverse=True):
            try:
                stored = self.latest.item_metadata(step)
            except Exception:  # noqa: BLE001 - no readable layout: the restore below decides
                stored = None
            if stored is not None:
                _check_layout(self.latest.directory / str(step), stored, abstract)
            try:
                return self.latest.restore(step, args=ocp.args.StandardRestore(abstract))
            except Exception as e:  # noqa: BLE001 - any unreadable checkpoint falls back
                log.warning("checkpoint %d is unreadable (%s); trying an older one", step, e)
                self.unreadable.add(step)
        return None

    def close(self) -> None:
        self.latest.close()
        if self.best is not None:
            self.best.close()


# Logging ----------------------------------------------------------------------------------


def truncate_log(path: Path, step: int) -> None:
    """Keeps the records of a JSON-lines log up to ``step`` (a resume from that step).

    A last line that is not a JSON object (a write cut off by a kill) is dropped with a
    warning; such a line anywhere else is corruption and raises ``ValueError`` naming it.
    """
    lines = [
        (n, line)
        for n, line in enumerate(path.read_text(errors="replace").splitlines(), 1)
        if line.strip()
    ]
    kept = []
    for k, (n, line) in enumerate(lines):
        try:
            record = json.loads(line)
        except json.JSONDecodeError:
            record = None
        if isinstance(record, dict):
            if record.get("step", 0) <= step:
                kept.append(line)
        elif k < len(lines) - 1:
            raise ValueError(f"{path}: line {n} is not a JSON object: {line[:80]!r}")
        else:
            log.warning("%s: line %d is cut off (an interrupted write); dropped", path, n)
    write_text_atomic(path, "".join(line + "\n" for line in kept))


class MetricsLog:
    """``metrics.jsonl`` plus TensorBoard; on resume, lines past the restored step go.

    A last line that is not a JSON object (a write cut off by a kill) is dropped with a
    warning; such a line anywhere else is corruption and raises ``ValueError`` naming it.
    """

    def __init__(self, workdir: Path, resume_step: int):
        self.path = Path(workdir) / "metrics.jsonl"
        self.tb = None
        if not writes_run_files():  # the other hosts of a multi-host run: process 0 logs
            return
        if self.path.exists():
            truncate_log(self.path, resume_step)
        from tensorboardX import SummaryWriter

        self.tb = SummaryWriter(str(Path(workdir) / "tb"), purge_step=resume_step + 1)

    def write(self, step: int, kind: str, values: dict) -> None:
        if self.tb is None:
            return
        # Undefined metrics (NaN) are written as null: strict JSON.
        clean = {
            k: (None if isinstance(v, float) and not math.isfinite(v) else v)
            for k, v in values.items()
        }
        record = {"step": step, "kind": kind, **clean}
        with self.path.open("a") as f:
            f.write(json.dumps(record) + "\n")
        for name, value in values.items():
            if isinstance(value, int | float) and math.isfinite(value):
                self.tb.add_scalar(f"{kind}/{name}", value, step)
        self.tb.flush()

    def close(self) -> None:
        if self.tb is not None:
            self.tb.close()


# Evaluation -------------------------------------------------------------------------------


def make_predict_fn(config: Config) -> Callable:
    """Jitted ``(params, points, valid) -> PanopticOutput`` (last decoder layer)."""
    from indoorbev_jax.inference import apply_views, panoptic_inference

    model = IndoorBEV(config)
    return jax.jit(
        lambda params, points, valid: panoptic_inference(
            apply_views(model, params, points, valid, config.inference), config.inference
        )
    )


def evaluate(config: Config, params, batches, predict_fn=None) -> dict:
    """All metrics of ``params`` over an iterable of ``Batch``."""
    from indoorbev_jax.metrics import Evaluator

    predict_fn = predict_fn or make_predict_fn(config)
    evaluator = Evaluator(config.inference, class_names=config.data.class_names)
    for batch in batches:
        evaluator.add_output(predict_fn(params, batch.points, batch.point_valid), batch.targets)
    return evaluator.compute()


# The loop ---------------------------------------------------------------------------------


def _scalars(metrics: dict) -> dict:
    """Means over the logged window (and over sweep members, if any) of the finite values:
    a skipped step's NaN loss (``skipped_steps`` counts it) left the window's mean NaN, the
    applied steps' losses lost. NaN when none is finite."""
    out = {}
    for k, v in metrics.items():
        a = np.asarray(v, np.float64)
        finite = a[np.isfinite(a)]
        out[k] = float(finite.mean()) if finite.size else math.nan
    return out


# Training batches cut into the ground-truth sampling database.
GT_DATABASE_BATCHES = 8


def _val_batches(val_ds, batch_size: int, batches: int, skip_bad: bool) -> list[Batch]:
    """The first ``batches`` validation batches; with ``skip_bad`` a malformed frame is
    reported by name and left out, as for training (else its error stops the start)."""
    from indoorbev_jax.data.dataset import collate

    items = []
    for index in range(len(val_ds)):
        if len(items) == batches * batch_size:
            break
        frame = load_or_skip(val_ds, index, skip_bad, "validation frame")
        items += [] if frame is None else [frame]
    if not items:
        raise kitti.DatasetError(f"{val_ds.root / 'val.txt'}: no readable frame to validate on")
    return [collate(items[k : k + batch_size]) for k in range(0, len(items), batch_size)]


def make_sources(
    config: Config, data: str | None, seed: int, skip_bad: bool, validate: bool = True
):
    """(train source, list of validation batches) for ``data`` = None (simulator) or a
    KITTI-style folder with ``train`` and ``val`` splits (``validate`` False: no ``val``
    needed, the list is empty; a sweep does not validate)."""
    t = config.train
    val = []
    if data is None:
        key = jax.random.key(seed)
        train = SimSource(config, jax.random.fold_in(key, KEY_TRAIN_DATA))
        if validate:
            val_source = SimSource(config, jax.random.fold_in(key, KEY_VAL_DATA), "val")
            val = [val_source(k) for k in range(t.eval_batches)]
    else:
        from indoorbev_jax.data.dataset import KittiDataset

        train = KittiSource(data, "train", config, seed, skip_bad)
        if validate:
            val_ds = KittiDataset(data, "val", config)
            if len(val_ds) == 0:  # every evaluation would be NaN, and best/ chosen on NaN
                raise kitti.DatasetError(
                    f"{Path(data) / 'val.txt'}: lists no frames to validate on"
                )
            val = _val_batches(val_ds, t.batch_size, t.eval_batches, skip_bad)
    if config.data.mask_targets == "box":  # training targets only; validation stays true shape
        boxed = jax.jit(box_targets, static_argnums=1)
        return (lambda step, shaped=train: boxed(shaped(step), config.grid)), val
    return train, val


def writes_run_files() -> bool:
    """Whether this process writes a run's own files (config.json, run.json, the metrics
    logs): the hosts of a multi-host run share the workdir, and each wrote every line of
    metrics.jsonl (orbax coordinates the checkpoints itself)."""
    return jax.process_index() == 0


def write_text_atomic(path: Path, text: str) -> None:
    kitti.atomic_write(Path(path), lambda tmp: tmp.write_text(text))


def _describe_source(data: str | None) -> str:
    return "the simulator" if data is None else data


SPLIT_FILES = ("train.txt", "val.txt")


def _elsewhere(kind: str) -> str:
    if kind == "sweep":
        return "sweep in another workdir"
    return "train in another workdir (--init-from this one to start from its parameters)"


def run_record(data: str | None, kind: str = "train") -> dict:
    """What ``run.json`` records: the kind of run ("train" or "sweep"), the data source (a
    folder, None for the simulator) and, for a folder, the sha256 of its split lists, so a
    resume that would read other frames, or the same ones in another order, is refused."""
    if data is None:
        return {"kind": kind, "data": None}
    splits = {}
    for name in SPLIT_FILES[:1] if kind == "sweep" else SPLIT_FILES:  # a sweep reads train only
        path = Path(data) / name
        splits[name] = hashlib.sha256(path.read_bytes()).hexdigest() if path.is_file() else None
    return {"kind": kind, "data": data, "splits": splits}


# Files only one kind of run writes (also in workdirs from before run.json named the kind).
_KIND_FILES = {"train": ("metrics.jsonl", "best"), "sweep": ("hypers.json", "sweep.jsonl")}


def read_json(path: Path):
    """``path``'s JSON; a file that is not JSON is a ValueError naming it."""
    try:
        return json.loads(path.read_text())
    except json.JSONDecodeError as e:
        raise ValueError(f"{path}: not valid JSON ({e})") from None


def _other_kind(workdir: Path, kind: str) -> str | None:
    """What says ``workdir`` holds the other kind of run than ``kind`` ("train" or
    "sweep"), or None: run.json's kind, or for a run.json from before it named one, the
    files only the other kind writes."""
    other = "sweep" if kind == "train" else "train"
    run_path = workdir / "run.json"
    recorded = read_json(run_path).get("kind") if run_path.exists() else None
    if recorded:
        return f"run.json says {other!r}" if recorded == other else None
    found = [name for name in _KIND_FILES[other] if (workdir / name).exists()]
    return f"it has {found[0]}" if found else None


def check_run_kind(workdir: Path, kind: str) -> None:
    """Raises ``ValueError`` when ``workdir`` holds the other kind of run (a training run
    for a sweep, or a sweep for training): with the same config and data the resume checks
    passed, and the first checkpoint save deleted the other run's checkpoints."""
    what = _other_kind(workdir, kind)
    if what:
        held, verb = ("a sweep", "train") if kind == "train" else ("a training run", "sweep")
        raise ValueError(f"{workdir}: holds {held} ({what}); {verb} in another workdir")


def _has_checkpoint(workdir: Path) -> bool:
    """Whether ``workdir/checkpoints`` holds a finished step (orbax names them by step;
    an interrupted save is a ``<step>.orbax-checkpoint-tmp`` folder)."""
    folder = workdir / "checkpoints"
    return folder.is_dir() and any(p.name.isdigit() for p in folder.iterdir())


def check_resume(
    config_path: Path, run_path: Path, config: Config, data: str | None, kind: str = "train"
) -> None:
    """Raises ``ValueError`` unless the run (``kind`` "train" or "sweep") in
    ``config_path``'s folder may go on with ``config`` and ``data`` (a resolved folder, or
    None for the simulator): only fields in ``RESUME_MAY_CHANGE`` may differ (logged as a
    note), and the data source and the split lists it reads may not."""
    diff = config_diff(Config.from_dict(json.loads(config_path.read_text())), config)
    lines = {k: f"  {k}: {a!r} -> {b!r}" for k, (a, b) in diff.items()}
    refused = [line for k, line in lines.items() if k not in RESUME_MAY_CHANGE]
    elsewhere = _elsewhere(kind)
    if refused:
        fresh = (
            "it has no checkpoint yet, so nothing was trained: remove its config.json and "
            f"run.json to start it afresh with these settings, or {elsewhere}"
            if not _has_checkpoint(config_path.parent)
            else elsewhere
        )
        raise ValueError(
            f"{config_path}: the workdir holds a run with another config (saved -> given):\n"
            + "\n".join(refused)
            + f"\nonly {', '.join(sorted(RESUME_MAY_CHANGE))} may change on resume; {fresh}"
        )
    if lines:
        log.info("note: resuming with (saved -> given):\n%s", "\n".join(lines.values()))
    if not run_path.exists():  # a run from before run.json was kept: nothing to compare
        return
    record = read_json(run_path)
    saved = record["data"]
    if saved != data:
        raise ValueError(
            f"{run_path}: the run trained on {_describe_source(saved)}, this command gives "
            f"{_describe_source(data)} (if the same data moved, edit the data field of run.json)"
        )
    if data is None or "splits" not in record or not _has_checkpoint(run_path.parent):
        return  # the simulator, a run.json from before the digests, or nothing trained yet
    now = run_record(data, kind)["splits"]
    for name, digest in record["splits"].items():
        if name in now and now[name] != digest:
            raise ValueError(
                f"{run_path}: {Path(data) / name} changed since the run started (sha256 "
                f"{str(digest)[:12]} -> {str(now[name])[:12]}), so the resumed run would "
                f"read other frames or another order: restore the list, or {elsewhere}"
            )


def holds_workdir(run_fn):
    """Runs ``run_fn(config, workdir, ...)`` holding ``kitti.hold_folder``'s lock on
    ``workdir/.lock``: two runs started in one workdir both ran to the end, writing one
    metrics log and one set of checkpoints. Only process 0 of a multi-host run takes it
    (its hosts share the workdir)."""

    @functools.wraps(run_fn)
    def run(config, workdir, *args, **kwargs):
        workdir = Path(workdir)
        with kitti.hold_folder(workdir, "run", "workdir", take=writes_run_files()):
            return run_fn(config, workdir, *args, **kwargs)

    return run


@holds_workdir
def train_and_evaluate(
    config: Config,
    workdir: str | os.PathLike,
    *,
    data: str | None = None,
    skip_bad_frames: bool = False,
    progress: bool = True,
    init_from: str | os.PathLike | None = None,
    init_strict: bool = True,
) -> TrainState:
    """Trains ``config`` in ``workdir``, resuming from its latest readable checkpoint.

    A workdir that holds a run resumes only with the same data source and a config that
    differs at most in ``RESUME_MAY_CHANGE``; ``config.json`` and ``run.json`` are written
    once every check has passed.

    Args:
      config: the run configuration (``config.train`` sets steps, batch size, schedule).
      workdir: run directory (created when missing).
      data: None to train on on-device simulated batches (``indoorbev_sim``), or a
        KITTI-style folder with ``train.txt`` and ``val.txt``.
      skip_bad_frames: with a folder, skip (and report) malformed frames instead of failing.
      progress: show a progress bar.
      init_from: start from this trained model's parameters (run directory or exported
        model file; ``with_pretrained``) instead of random ones. Only a fresh run uses it:
        a resumed run continues from its own checkpoint. Recorded in ``init_from.json``.
      init_strict: require ``init_from``'s parameter tree to match the model's exactly;
        False loads what matches by name and shape (``with_pretrained(strict=False)``).

    Returns:
      The final ``TrainState``.
    """
    from tqdm import tqdm

    check_train_seed(config.train)  # holds_workdir made workdir, a Path
    # Every check runs before config.json is written, so a refused start leaves nothing
    # that would refuse the corrected command too.
    config_path, run_path = workdir / "config.json", workdir / "run.json"
    data_source = None if data is None else str(Path(data).resolve())
    check_run_kind(workdir, "train")
    if config_path.exists():
        check_resume(config_path, run_path, config, data_source)

    t = config.train
    mesh = data_mesh()
    if t.batch_size % mesh.size:
        raise ValueError(f"train.batch_size={t.batch_size} does not split over {mesh.size} devices")
    key = jax.random.key(t.seed)
    state = init_state(config, jax.random.fold_in(key, KEY_INIT))
    checkpoints = Checkpoints(workdir, t.keep_checkpoints)
    restored = checkpoints.restore(state)
    record = None
    if restored is not None:
        state = restored
        log.info("resumed from step %d", int(state.step))
    elif init_from is not None:
        state, report = _load_pretrained(state, config, init_from, init_strict)
        record = {"init_from": str(Path(init_from).resolve())}
        if Path(init_from).is_file():
            record["sha256"] = hashlib.sha256(Path(init_from).read_bytes()).hexdigest()
        if not init_strict:
            record.update(strict=False, **report)
            log.info(
                "partial load: %d parameter arrays fresh %s, %d unused %s",
                len(report["fresh"]),
                report["fresh"],
                len(report["unused"]),
                report["unused"],
            )
        log.info("parameters from %s", init_from)
    start = int(state.step)
    state = replicate(state, mesh)
    hyper = replicate(Hyper.from_config(config), mesh)
    step_key = jax.random.fold_in(key, KEY_STEPS)
    train_source, val_batches = make_sources(config, data, t.seed, skip_bad_frames)
    metrics_log = MetricsLog(workdir, start)
    if writes_run_files():
        if record is not None:
            write_text_atomic(workdir / "init_from.json", json.dumps(record, indent=2) + "\n")
        write_text_atomic(run_path, json.dumps(run_record(data_source)) + "\n")
        write_text_atomic(config_path, config.to_json())

    database = None
    if t.augment and config.augment.gt_sampling > 0:
        # Cut from the first training batches; the same ones on every resume.
        database = gt_database(train_source, GT_DATABASE_BATCHES, config.grid)
        log.info("ground-truth sampling database: %d objects", database.classes.shape[0])
    train_step = jit_train_step(config, make_train_step(config, database), donate_argnums=0)
    predict_fn = make_predict_fn(config)

    bar = tqdm(total=t.total_steps, initial=start, disable=not progress, unit="step")
    pending, window_start, window_steps = [], time.perf_counter(), 0
    try:
        for step, batch in prefetch(train_source, start, t.total_steps):
            state, metrics = train_step(state, shard_batch(batch, mesh), step_key, hyper)
            pending.append(metrics)
            window_steps += 1
            done = step + 1
            if done % t.log_every == 0 or done == t.total_steps:
                values = _scalars(jax.tree.map(lambda *xs: np.stack(xs), *pending))
                values.pop("finite")
                values["skipped_steps"] = int(state.skipped)
                # The steps averaged: fewer than log_every in the first window after a
                # resume from a checkpoint between two log lines.
                values["steps"] = window_steps
                values["steps_per_s"] = window_steps / (time.perf_counter() - window_start)
                metrics_log.write(done, "train", values)
                if values["skipped_steps"]:
                    log.warning("%d non-finite steps skipped so far", values["skipped_steps"])
                bar.set_postfix(loss=f"{values['loss']:.4f}", sps=f"{values['steps_per_s']:.2f}")
                pending, window_start, window_steps = [], time.perf_counter(), 0
            bar.update(1)
            # Evaluate before the checkpoint of the same step: a run killed in between
            # resumes from the previous checkpoint and evaluates again, where the other
            # order would skip this evaluation (and its best/ candidate) for good.
            if done % t.eval_every == 0 or done == t.total_steps:
                results = evaluate(config, eval_params(state), val_batches, predict_fn)
                scalars = {k: v for k, v in results.items() if isinstance(v, int | float)}
                scalars.update({f"ap{thr}": v for thr, v in results["ap"].items()})
                metrics_log.write(done, "eval", scalars)
                checkpoints.save_best(state, scalars)
                bar.write(f"step {done}: " + ", ".join(f"{k} {v:.4f}" for k, v in scalars.items()))
            if done % t.checkpoint_every == 0 or done == t.total_steps:
                checkpoints.save(state)
    finally:
        bar.close()
        metrics_log.close()
        checkpoints.close()
    return state


def load_params(workdir: str | os.PathLike, which: str = "best") -> tuple[Config, Any]:
    """(config, params) of a run directory's ``best`` (or ``latest``) checkpoint."""
    workdir = Path(workdir)
    config_file = workdir / "config.json"
    if not config_file.is_file():
        raise FileNotFoundError(
            f"{workdir}: not a training run directory (no config.json); expected the --workdir "
            "of experiments/train.py or an exported model file (.msgpack)"
        )
    config = Config.from_dict(read_json(config_file))
    if _other_kind(workdir, "train"):
        raise ValueError(
            f"{workdir}: a sweep's workdir: its checkpoints hold K stacked models, which "
            "predict, export and --init-from cannot load as one model (export one with "
            "experiments/export_model.py WORKDIR --member K --out F)"
        )
    template = init_state(config, jax.random.key(0))
    # No best/ made where there is none (orbax creates the folder it is given).
    has_best = (workdir / "best").is_dir()
    checkpoints = Checkpoints(workdir, config.train.keep_checkpoints, "pq" if has_best else None)
    use_best = which == "best" and has_best and checkpoints.best.all_steps()
    manager = checkpoints.best if use_best else None
    state = None
    if manager is not None:
        abstract = jax.tree.map(ocp.utils.to_shape_dtype_struct, template)
        state = manager.restore(manager.best_step(), args=ocp.args.StandardRestore(abstract))
    if state is None:
        state = checkpoints.restore(template)
    checkpoints.close()
    if state is None:
        raise FileNotFoundError(f"{workdir}: no checkpoint found")
    return config, eval_params(state)
