"""Hyperparameter sweeps: K models trained at once by vmapping the train step over learning
rate and loss weights (``experiments/sweep.py`` is the command line).

All K models see the same batches and augmentation keys; each has its own parameters,
optimizer state, peak learning rate and loss weights (traced arrays, ``train.Hyper``).
"""

from __future__ import annotations

import json
import time
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np
from tqdm import tqdm

from indoorbev_jax.config import Config
from indoorbev_jax.train import (
    KEY_INIT,
    KEY_STEPS,
    Hyper,
    TrainState,
    init_state,
    jit_train_step,
    make_sources,
    make_train_step,
    prefetch,
)


def stack_hypers(config: Config, learning_rates, weight_overrides: dict[str, list[float]]) -> Hyper:
    """K ``Hyper`` stacked on a leading axis; weights not overridden come from the config."""
    base = Hyper.from_config(config)
    k = len(learning_rates)
    weights = {}
    for name, value in base.weights.items():
        values = weight_overrides.get(name)
        if values is not None and len(values) != k:
            raise ValueError(f"--{name}-weights: expected {k} values, got {len(values)}")
        weights[name] = jnp.asarray(values if values is not None else [value] * k, jnp.float32)
    return Hyper(learning_rate=jnp.asarray(learning_rates, jnp.float32), weights=weights)


def init_sweep(config: Config, k: int, key: jax.Array) -> TrainState:
    """K identical initial states (same init key, so runs differ only by their Hyper)."""
    state = init_state(config, key)
    return jax.tree.map(lambda x: jnp.broadcast_to(x, (k, *jnp.shape(x))), state)


def make_sweep_step(config: Config):
    """``(states[K], batch, key, hypers[K]) -> (states[K], metrics[K])``, jitted."""
    return jit_train_step(config, jax.vmap(make_train_step(config), in_axes=(0, None, None, 0)))


def run_sweep(config: Config, workdir, hypers: Hyper, data=None) -> TrainState:
    """Trains the K models of ``hypers`` for ``config.train.total_steps`` steps and writes
    ``sweep.jsonl`` (per-model training loss, then validation-free summary) in ``workdir``."""
    workdir = Path(workdir)
    workdir.mkdir(parents=True, exist_ok=True)
    t = config.train
    k = int(hypers.learning_rate.shape[0])
    key = jax.random.key(t.seed)
    states = init_sweep(config, k, jax.random.fold_in(key, KEY_INIT))
    step = make_sweep_step(config)
    source, _ = make_sources(config, data, t.seed, skip_bad=False)
    step_key = jax.random.fold_in(key, KEY_STEPS)
    log = (workdir / "sweep.jsonl").open("w")
    start = time.perf_counter()
    for s, batch in tqdm(prefetch(source, 0, t.total_steps), total=t.total_steps):
        states, metrics = step(states, batch, step_key, hypers)
        if (s + 1) % t.log_every == 0 or s + 1 == t.total_steps:
            record = {"step": s + 1, "loss": np.asarray(metrics["loss"]).tolist()}
            log.write(json.dumps(record) + "\n")
            log.flush()
    jax.block_until_ready(states)
    print(f"{k} models x {t.total_steps} steps in {time.perf_counter() - start:.1f} s")
    return states
