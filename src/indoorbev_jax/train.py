"""Training: one jitted step (augment -> forward -> match -> loss -> update), exact resume.

``train_and_evaluate(config, workdir)`` is what ``experiments/train.py`` runs. The run
directory holds ``config.json``, ``run.json`` (the kind of run and the data source),
``metrics.jsonl`` (one JSON object a line), TensorBoard event files under ``tb/``, orbax
checkpoints under ``checkpoints/`` (the latest ``train.keep_checkpoints``) and ``best/``
(the best by validation ``metric``); ``rundir`` writes and checks them. The data come
from ``sources``.

Exact resume: the data of step s and every random key of step s are pure functions of
(seed, s), and the state is restored bit for bit, so a run killed at any point and
restarted with the same command ends with the parameters of an uninterrupted run.

Values a sweep varies (learning rate, loss weights) live in ``Hyper`` and enter the step as
arrays, so ``jax.vmap`` over a leading axis of K states and K ``Hyper`` trains K models at
once (``experiments/sweep.py``).
"""

from __future__ import annotations

import hashlib
import json
import logging
import math
import os
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any, NamedTuple

import jax
import jax.numpy as jnp
import numpy as np
import optax
from flax import struct
from jax.sharding import Mesh, NamedSharding, PartitionSpec

from indoorbev_jax.augment import ObjectDatabase, augment_batch
from indoorbev_jax.config import Config, check_train_seed
from indoorbev_jax.data import kitti
from indoorbev_jax.losses import seed_loss, set_loss
from indoorbev_jax.models import IndoorBEV
from indoorbev_jax.rundir import (
    Checkpoints,
    MetricsLog,
    check_resume,
    check_run_kind,
    holds_workdir,
    other_kind,
    read_config,
    run_record,
    write_text_atomic,
    writes_run_files,
)
from indoorbev_jax.sources import (
    GT_DATABASE_BATCHES,
    KittiSource,
    SimSource,
    box_targets,
    gt_database,
    prefetch,
    val_batches,
)
from indoorbev_jax.types import Batch
from indoorbev_jax.xla_flags import train_compiler_options

log = logging.getLogger("indoorbev_jax.train")

# What each use of the run's root key ``key(train.seed)`` folds in: one constant per use, so
# no two uses within a run draw the same numbers. The data streams keep 0 and 1, which
# ``experiments/eval_sim.py`` keeps its val and test frames clear of. (``indoorbev-sim export
# --seed a`` roots its scene j at ``fold_in(key(a), j)``, so its scenes 0-3 share these
# keys in another role: no scene key is shared, so no frame is.)
KEY_TRAIN_DATA, KEY_VAL_DATA, KEY_INIT, KEY_STEPS = 0, 1, 2, 3


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
    for name, shape for shape and dtype for dtype; the error names the first difference.
    Without it, every parameter the two share by name, shape and dtype is loaded, the rest
    keep ``state``'s fresh values and the source's extra ones are dropped
    (``train_and_evaluate`` logs both lists and keeps them in ``init_from.json``), e.g. to
    start the paper-mode upsampler (``head.upsampler_skips=false``) from a model with skips.
    """
    return _load_pretrained(state, config, source, strict)[0]


def _load_pretrained(
    state: TrainState, config: Config, source: str | os.PathLike, strict: bool
) -> tuple[TrainState, dict[str, list[str]]]:
    """``with_pretrained`` and its report: ``fresh`` (the run's parameters not loaded, with
    the reason) and ``unused`` (the source's parameters the run has no place for)."""
    from indoorbev_jax.predict import load_model, param_differences

    src_config, params = load_model(source, check=False)  # checked against the run's model
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
    differences = param_differences(params, state.params, "the run's model")
    if strict and differences:
        raise ValueError(f"{source}: {differences[0][2]}")
    for path, kind, _ in differences:
        name = jax.tree_util.keystr(path)
        if kind == "extra":
            report["unused"].append(name)
        elif kind == "missing":
            report["fresh"].append(f"{name} (missing)")
        elif kind == "shape":
            report["fresh"].append(f"{name} (shape {np.shape(have[path])} != {want[path].shape})")
        else:
            dtype = np.asarray(have[path]).dtype
            report["fresh"].append(f"{name} (dtype {dtype} != {want[path].dtype})")
    matched = (want.keys() & have.keys()) - {path for path, *_ in differences}
    if not matched:
        raise ValueError(f"{source}: no parameter matches the run's model by name, shape and dtype")
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
            val = val_batches(val_ds, t.batch_size, t.eval_batches, skip_bad)
    if config.data.mask_targets == "box":  # training targets only; validation stays true shape
        boxed = jax.jit(box_targets, static_argnums=1)
        return (lambda step, shaped=train: boxed(shaped(step), config.grid)), val
    return train, val


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
    differs at most in ``rundir.RESUME_MAY_CHANGE``; ``config.json`` and ``run.json`` are written
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
    """(config, params) of a run directory's ``best`` (or ``latest``) checkpoint.

    ``predict.load_model`` reads a run directory or an exported model file alike.
    """
    return load_run(workdir, which)[:2]


def load_run(workdir: str | os.PathLike, which: str = "best") -> tuple[Config, Any, str]:
    """``load_params`` and which checkpoint it read, in words: "best, step 3", "latest,
    step 5", or "latest, step 5 (best/ unreadable)" when the best one could not be read."""
    if which not in ("best", "latest"):  # a typo loaded the latest checkpoint
        raise ValueError(f"which: expected 'best' or 'latest', got {which!r}")
    workdir = Path(workdir)
    config_file = workdir / "config.json"
    if workdir.is_file():
        raise ValueError(
            f"{workdir}: a file, not a run directory; read an exported model file with "
            "predict.load_model"
        )
    if not config_file.is_file():
        raise FileNotFoundError(
            f"{workdir}: not a training run directory (no config.json); expected the --workdir "
            "of experiments/train.py"
        )
    config = read_config(config_file)
    if other_kind(workdir, "train"):
        raise ValueError(
            f"{workdir}: a sweep's workdir: its checkpoints hold K stacked models, which "
            "predict, export and --init-from cannot load as one model (export one with "
            "experiments/export_model.py WORKDIR --member K --out F)"
        )
    if not any((workdir / name).is_dir() for name in ("checkpoints", "best")):
        # Before orbax, which makes the folder it is given.
        raise FileNotFoundError(f"{workdir}: no checkpoint found")
    template = init_state(config, jax.random.key(0))
    # No best/ made where there is none (orbax creates the folder it is given).
    has_best = (workdir / "best").is_dir()
    checkpoints = Checkpoints(workdir, config.train.keep_checkpoints, "pq" if has_best else None)
    state, source, unreadable = None, "best", False
    if which == "best" and has_best:
        state = checkpoints.restore_best(template)
        unreadable = state is None and bool(checkpoints.best.all_steps())
    if state is None:
        state, source = checkpoints.restore(template), "latest"
    checkpoints.close()
    if state is None:
        said = f" ({workdir / 'best'} unreadable)" if unreadable else ""
        raise FileNotFoundError(f"{workdir}: no checkpoint found{said}")
    source = f"{source}, step {int(state.step)}"
    if unreadable:
        log.warning("%s: read the latest readable checkpoint instead (step %d)",
                    workdir / "best", int(state.step))  # fmt: skip
        source += " (best/ unreadable)"
    return config, eval_params(state), source
