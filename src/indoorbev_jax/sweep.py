"""Hyperparameter sweeps: K models trained at once by vmapping the train step over learning
rate and loss weights (``experiments/sweep.py`` is the command line).

All K models see the same batches and augmentation keys; each has its own parameters,
optimizer state, peak learning rate and loss weights (traced arrays, ``train.Hyper``).
"""

from __future__ import annotations

import dataclasses
import functools
import json
import math
import time
from pathlib import Path
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np
from tqdm import tqdm

from indoorbev_jax.augment import ObjectDatabase
from indoorbev_jax.config import Config, LossConfig, check_train_seed
from indoorbev_jax.rundir import (
    Checkpoints,
    check_resume,
    check_run_kind,
    holds_workdir,
    read_config,
    read_json,
    read_record,
    run_record,
    truncate_log,
    write_text_atomic,
    writes_run_files,
)
from indoorbev_jax.sources import GT_DATABASE_BATCHES, gt_database, prefetch
from indoorbev_jax.train import (
    KEY_INIT,
    KEY_STEPS,
    Hyper,
    TrainState,
    eval_params,
    init_state,
    jit_train_step,
    make_sources,
    make_train_step,
)


def stack_hypers(config: Config, learning_rates, weight_overrides: dict[str, list[float]]) -> Hyper:
    """K ``Hyper`` stacked on a leading axis; weights not overridden come from the config."""
    base = Hyper.from_config(config)
    learning_rates = _values("learning-rates", learning_rates)
    weight_overrides = {
        name: None if v is None else _values(f"{name}-weights", v)
        for name, v in weight_overrides.items()
    }
    k = len(learning_rates)
    if k == 0:
        raise ValueError("--learning-rates: expected at least one value (K >= 1 models)")
    # Config's rule for each value (a NaN learning rate wrote NaN parameters; NaN in
    # hypers.json is no JSON, and NaN != NaN refused every resume).
    for flag, values in [("learning-rates", learning_rates)] + [
        (f"{name}-weights", v) for name, v in weight_overrides.items() if v is not None
    ]:
        bad = next(((i, v) for i, v in enumerate(values) if not (0 <= v < math.inf)), None)
        if bad is not None:
            raise ValueError(
                f"--{flag}: value {bad[0] + 1} is {bad[1]!r}; expected finite and >= 0"
            )
    unknown = sorted(set(weight_overrides) - set(base.weights))
    if unknown:
        extra = " (the seed weight needs the seed head)" if "seed" in unknown else ""
        raise ValueError(
            f"--{unknown[0]}-weights: this config has no such loss weight{extra}; "
            f"it has {sorted(base.weights)}"
        )
    weights = {}
    for name, value in base.weights.items():
        values = weight_overrides.get(name)
        if values is not None and len(values) != k:
            raise ValueError(f"--{name}-weights: expected {k} values, got {len(values)}")
        weights[name] = jnp.asarray(values if values is not None else [value] * k, jnp.float32)
    return Hyper(learning_rate=jnp.asarray(learning_rates, jnp.float32), weights=weights)


def _values(flag: str, values) -> list[float]:
    """A number or a flat sequence of numbers as a list (a nested one is refused by flag)."""
    array = np.atleast_1d(np.asarray(values, np.float64))
    if array.ndim != 1:
        raise ValueError(f"--{flag}: expected one value per model, got shape {array.shape}")
    return array.tolist()


def check_hypers(hypers: Hyper, config: Config) -> int:
    """K, once ``hypers`` (built by hand or by ``stack_hypers``) holds K >= 1 settings of
    every value ``config`` trains with, each finite and >= 0. Raises ``ValueError`` naming
    the field: ``run_sweep`` checks before it writes anything, where a K that differed
    between fields failed inside vmap after the workdir's files were written (and then
    refused the corrected rerun) and a negative learning rate trained uphill."""
    fields = {"learning_rate": hypers.learning_rate}
    fields.update({f"weights[{name!r}]": v for name, v in dict(hypers.weights).items()})
    want = sorted(Hyper.from_config(config).weights)
    if sorted(hypers.weights) != want:
        raise ValueError(f"hypers.weights: expected the keys {want}, got {sorted(hypers.weights)}")
    lr = np.asarray(hypers.learning_rate)
    k = lr.shape[0] if lr.ndim == 1 else 0
    for name, value in fields.items():
        value = np.asarray(value)
        if value.shape != (k,) or k == 0:
            raise ValueError(
                f"hypers.{name}: expected [K] with K >= 1 the same for every field (K = "
                f"{k} from learning_rate), got shape {value.shape}"
            )
        if not (np.isfinite(value) & (value >= 0)).all():
            raise ValueError(f"hypers.{name}: expected finite values >= 0, got {value.tolist()}")
    return k


def init_sweep(config: Config, k: int, key: jax.Array) -> TrainState:
    """K identical initial states (same init key, so runs differ only by their Hyper)."""
    state = init_state(config, key)
    return jax.tree.map(lambda x: jnp.broadcast_to(x, (k, *jnp.shape(x))), state)


def _read_hypers(path: Path, loss: LossConfig) -> dict:
    """A sweep's hypers.json (``hypers_to_json``): K > 0 learning rates and K values of
    weights of ``loss``, or a ValueError naming the file and what is wrong."""
    settings = read_record(path, ("learning_rate", "weights"))
    rates, weights = settings["learning_rate"], settings["weights"]
    if not isinstance(weights, dict):
        raise ValueError(f"{path}: 'weights' is {weights!r}, expected an object of lists")
    k = len(rates) if isinstance(rates, list) and rates else None
    lists = {"learning_rate": rates, **{f"weights.{name}": v for name, v in weights.items()}}
    for name, values in lists.items():
        numbers = isinstance(values, list) and all(
            isinstance(v, int | float) and not isinstance(v, bool) for v in values
        )
        if not numbers or len(values) != k:
            raise ValueError(f"{path}: '{name}' is {values!r}, expected {k or 'K > 0'} numbers")
    unknown = sorted(name for name in weights if not hasattr(loss, f"{name}_weight"))
    if unknown:
        raise ValueError(f"{path}: no such loss weight(s) {unknown}")
    return settings


def load_member(workdir, member: int) -> tuple[Config, Any]:
    """(config, params) of model ``member`` of a sweep's latest checkpoint, as
    ``train.load_params`` gives a training run's: the config carries that member's learning
    rate and loss weights, as ``train.py`` would train it."""
    workdir = Path(workdir)
    if not (workdir / "hypers.json").is_file():
        raise FileNotFoundError(f"{workdir}: not a sweep's workdir (no hypers.json)")
    config = read_config(workdir / "config.json")
    settings = _read_hypers(workdir / "hypers.json", config.loss)
    k = len(settings["learning_rate"])
    if not 0 <= member < k:
        raise ValueError(f"--member {member}: the sweep in {workdir} has members 0..{k - 1}")
    if not (workdir / "checkpoints").is_dir():  # orbax would create the folder: read only
        raise FileNotFoundError(f"{workdir}: no checkpoint found")
    # metric=None: no best/ (a training run's mark), as run_sweep itself.
    checkpoints = Checkpoints(workdir, config.train.keep_checkpoints, None)
    try:
        state = checkpoints.restore(init_sweep(config, k, jax.random.key(0)))
    finally:
        checkpoints.close()
    if state is None:
        raise FileNotFoundError(f"{workdir}: no checkpoint found")
    params = jax.tree.map(lambda x: x[member], eval_params(state))
    # _shortest: a hypers.json of an older version holds the float32 values' full digits.
    loss = {
        f"{name}_weight": _shortest(values[member])[0]
        for name, values in settings["weights"].items()
    }
    learning_rate = _shortest(settings["learning_rate"][member])[0]
    config = dataclasses.replace(
        config,
        train=dataclasses.replace(config.train, learning_rate=learning_rate),
        loss=dataclasses.replace(config.loss, **loss),
    )
    return config, params


def make_sweep_step(config: Config, database: ObjectDatabase | None = None):
    """``(states[K], batch, key, hypers[K]) -> (states[K], metrics[K])``, jitted; ``database``
    feeds ground-truth sampling as in ``train.make_train_step``."""
    if database is None:
        return _cached_sweep_step(config)
    step = make_train_step(config, database)
    return jit_train_step(config, jax.vmap(step, in_axes=(0, None, None, 0)))


@functools.lru_cache(maxsize=4)
def _cached_sweep_step(config: Config):
    # One compile per config: a resumed or repeated sweep in one process reuses it.
    step = make_train_step(config)
    return jit_train_step(config, jax.vmap(step, in_axes=(0, None, None, 0)))


def _shortest(values) -> list[float]:
    """float32 values as the shortest decimals that read back to them: the 1e-4 given, not
    its float32 9.999999747378752e-05 (which export --member copied into a model's config)."""
    return [float(str(v)) for v in np.asarray(values, np.float32).reshape(-1)]


def hypers_to_json(hypers: Hyper) -> dict:
    return {
        "learning_rate": _shortest(hypers.learning_rate),
        "weights": {k: _shortest(v) for k, v in sorted(hypers.weights.items())},
    }


def same_settings(saved: dict, given: dict) -> bool:
    """Whether two ``hypers_to_json`` dicts hold the same float32 settings (an older
    hypers.json wrote the float32 values' full float64 digits)."""

    def flat(settings):
        weights = settings.get("weights")
        if not isinstance(weights, dict):
            return None
        return [("learning_rate", settings.get("learning_rate"))] + sorted(weights.items())

    a, b = flat(saved), flat(given)
    if a is None or b is None or [k for k, _ in a] != [k for k, _ in b]:
        return False
    try:
        return all(
            np.array_equal(np.asarray(x, np.float32), np.asarray(y, np.float32))
            for (_, x), (_, y) in zip(a, b, strict=True)
        )
    except (TypeError, ValueError):
        return False


@holds_workdir
def run_sweep(
    config: Config,
    workdir,
    hypers: Hyper,
    data=None,
    *,
    skip_bad_frames: bool = False,
    progress: bool = True,
) -> TrainState:
    """Trains the K models of ``hypers`` for ``config.train.total_steps`` steps.

    ``workdir`` receives ``config.json``, ``run.json`` (the kind of run and the data source),
    ``hypers.json`` (the K settings), ``sweep.jsonl`` (per model, the mean training loss of
    the finite steps of each ``train.log_every``) and orbax checkpoints of all K states under
    ``checkpoints/`` every ``train.checkpoint_every`` steps. Rerunning the same command after
    a kill resumes from the latest checkpoint, exactly as ``train.train_and_evaluate`` does;
    a workdir holding another sweep (config, data, its train.txt or hypers) or a training
    run is refused, naming what differs.
    """
    check_train_seed(config.train)  # holds_workdir made workdir, a Path
    t = config.train
    k = check_hypers(hypers, config)
    config_path, run_path = workdir / "config.json", workdir / "run.json"
    hypers_path = workdir / "hypers.json"
    data_source = None if data is None else str(Path(data).resolve())
    settings = hypers_to_json(hypers)
    check_run_kind(workdir, "sweep")
    check_resume(config_path, run_path, config, data_source, "sweep")
    saved = read_json(hypers_path) if hypers_path.exists() else None
    if saved is not None and not same_settings(saved, settings):
        raise ValueError(
            f"{hypers_path}: the workdir holds a sweep of other settings "
            f"({saved}, given {settings}); sweep in another workdir"
        )
    key = jax.random.key(t.seed)
    states = init_sweep(config, k, jax.random.fold_in(key, KEY_INIT))
    checkpoints = Checkpoints(workdir, t.keep_checkpoints, metric=None)
    restored = checkpoints.restore(states)
    start = 0 if restored is None else int(np.asarray(restored.step)[0])
    states = states if restored is None else restored
    source, _ = make_sources(config, data, t.seed, skip_bad=skip_bad_frames, validate=False)
    log_path = workdir / "sweep.jsonl"
    primary = writes_run_files()  # one host of a multi-host run writes the run's files
    if primary and log_path.exists():
        truncate_log(log_path, start)
    if primary:  # written once every check has passed, as train_and_evaluate does
        write_text_atomic(run_path, json.dumps(run_record(data_source, "sweep")) + "\n")
        write_text_atomic(config_path, config.to_json())
        write_text_atomic(hypers_path, json.dumps(settings) + "\n")
    database = None
    if t.augment and config.augment.gt_sampling > 0:
        database = gt_database(source, GT_DATABASE_BATCHES, config.grid)
    step = make_sweep_step(config, database)
    step_key = jax.random.fold_in(key, KEY_STEPS)
    # Per member: the sum and count of its finite losses (a skipped step's NaN left the
    # window's mean NaN) and the steps of the window.
    loss_sum, finite, window = jnp.zeros(k), jnp.zeros(k), 0
    started = time.perf_counter()
    try:
        batches = prefetch(source, start, t.total_steps)
        for s, batch in tqdm(batches, total=t.total_steps, initial=start, disable=not progress):
            states, metrics = step(states, batch, step_key, hypers)
            ok = jnp.isfinite(metrics["loss"])  # stays on the device
            loss_sum = loss_sum + jnp.where(ok, metrics["loss"], 0.0)
            finite, window = finite + ok, window + 1
            done = s + 1
            if done % t.log_every == 0 or done == t.total_steps:
                sums, counts = np.asarray(loss_sum), np.asarray(finite)
                # null (strict JSON) for a member none of whose steps was finite.
                mean = [float(a / c) if c else None for a, c in zip(sums, counts, strict=True)]
                record = {"step": done, "steps": window, "loss": mean}
                if primary:
                    with log_path.open("a") as f:
                        f.write(json.dumps(record) + "\n")
                loss_sum, finite, window = jnp.zeros(k), jnp.zeros(k), 0
            if done % t.checkpoint_every == 0 or done == t.total_steps:
                checkpoints.save(states, done)
    finally:
        checkpoints.close()
    jax.block_until_ready(states)
    ran = t.total_steps - start
    print(f"{k} models x {ran} steps in {time.perf_counter() - started:.1f} s")
    return states
