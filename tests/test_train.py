"""Training: non-finite steps skipped, vmapped sweeps equal separate runs, sharded equals
single-device, checkpoints fall back past a corrupt one, and kill -9 + rerun is bitwise."""

import dataclasses
import hashlib
import json
import math
import os
import re
import shutil
import subprocess
import sys
import textwrap
import time
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np
import optax
import pytest

from indoorbev_jax import rundir, sources
from indoorbev_jax import train as T
from indoorbev_jax.config import Config, with_overrides
from indoorbev_jax.data import kitti
from indoorbev_jax.data.dataset import KittiDataset
from indoorbev_jax.sweep import init_sweep, make_sweep_step, stack_hypers

sys.path.insert(0, str(Path(__file__).parent))
from synthetic import write_synthetic_dataset  # noqa: E402

REPO = Path(__file__).resolve().parents[1]
CFG = Config.tiny()


@pytest.fixture(scope="module")
def data(tmp_path_factory):
    root = tmp_path_factory.mktemp("synthetic")
    write_synthetic_dataset(root, frames=8)
    return root


@pytest.fixture(scope="module")
def batch(data):
    return next(KittiDataset(data, "train", CFG).batches(CFG.train.batch_size))


@pytest.fixture(scope="module")
def step_fn():
    # Compiled as train.train compiles it, so the sweep test compares like with like.
    return T.jit_train_step(CFG, T.make_train_step(CFG))


def test_lr_schedule_warmup_then_cosine():
    f = lambda s: float(T.lr_factor(s, 10, 110))  # noqa: E731
    assert f(0) == 0.0 and f(5) == pytest.approx(0.5) and f(10) == pytest.approx(1.0)
    assert f(60) == pytest.approx(0.5, abs=1e-6) and f(110) == pytest.approx(0.0, abs=1e-7)


def test_lr_schedule_without_warmup_starts_at_the_full_rate():
    """warmup_steps = 0 is allowed: the cosine starts at step 0 at the full rate. Guards against
    the warm-up test ``step <= warmup``, which gives step 0 a rate of 0 when warmup is 0."""
    assert float(T.lr_factor(0, 0, 100)) == 1.0
    assert float(T.lr_factor(50, 0, 100)) == pytest.approx(0.5, abs=1e-6)


def test_optimizer_is_global_norm_clip_then_adamw_with_the_configs_weight_decay():
    """make_optimizer updates parameters as optax's clip_by_global_norm then adamw with the
    config's weight_decay. One huge gradient then small ones: guards against elementwise
    clipping (changes the update direction) and a weight_decay left at optax's default (equal to
    the config default 1e-4, so 0.05 here)."""
    train = dataclasses.replace(CFG.train, grad_clip_norm=1.0, weight_decay=0.05)
    ours = T.make_optimizer(dataclasses.replace(CFG, train=train))
    ref = optax.chain(optax.clip_by_global_norm(1.0), optax.adamw(1e-2, weight_decay=0.05))
    params = {"w": jnp.array([1.0, -2.0, 3.0]), "b": jnp.array(0.5)}
    s_ours, s_ref, p_ours, p_ref = ours.init(params), ref.init(params), params, params
    for scale in (100.0, 0.01, 5.0):
        g = {"w": jnp.array([scale, -0.1 * scale, 0.0]), "b": jnp.array(0.3 * scale)}
        s_ours = T._set_learning_rate(s_ours, jnp.float32(1e-2))
        u, s_ours = ours.update(g, s_ours, p_ours)
        p_ours = optax.apply_updates(p_ours, u)
        u, s_ref = ref.update(g, s_ref, p_ref)
        p_ref = optax.apply_updates(p_ref, u)
    jax.tree.map(lambda a, b: np.testing.assert_allclose(a, b, rtol=1e-6), p_ours, p_ref)


def test_non_finite_step_is_skipped(batch, step_fn):
    state = T.init_state(CFG, jax.random.key(0))
    hyper = T.Hyper.from_config(CFG)
    good, metrics = step_fn(state, batch, jax.random.key(1), hyper)
    assert bool(metrics["finite"]) and int(good.skipped) == 0
    bad_hyper = hyper.replace(weights=dict(hyper.weights, dice=jnp.float32(jnp.nan)))
    bad, metrics = step_fn(good, batch, jax.random.key(1), bad_hyper)
    assert not bool(metrics["finite"])
    assert int(bad.skipped) == 1 and int(bad.step) == 2
    jax.tree.map(np.testing.assert_array_equal, bad.params, good.params)
    # The optimizer's state is kept too: NaN moments passed the next step's finite check
    # (which reads the loss and gradients) and turned every parameter NaN for good.
    jax.tree.map(np.testing.assert_array_equal, bad.opt_state, good.opt_state)
    after, metrics = step_fn(bad, batch, jax.random.key(2), hyper)
    assert bool(metrics["finite"])
    assert all(np.isfinite(p).all() for p in jax.tree.leaves(after.params))


def test_vmapped_sweep_equals_separate_runs(batch, step_fn):
    lrs = [1e-3, 3e-3]
    hypers = stack_hypers(CFG, lrs, {"dice": [5.0, 1.0]})
    states = init_sweep(CFG, 2, jax.random.key(0))
    sweep = make_sweep_step(CFG)
    swept = []
    for _ in range(2):
        states, metrics = sweep(states, batch, jax.random.key(1), hypers)
        swept.append(metrics)
    for k in range(2):
        state = T.init_state(CFG, jax.random.key(0))
        hyper = jax.tree.map(lambda x, k=k: x[k], hypers)
        for s in range(2):
            state, metrics = step_fn(state, batch, jax.random.key(1), hyper)
            for name in ("loss", "grad_norm", "dice", "cls"):
                np.testing.assert_allclose(swept[s][name][k], metrics[name], rtol=1e-4)
        # Adam divides by sqrt(v): on near-zero gradients vmap's float reassociation can
        # move a parameter by up to a fraction of one learning-rate step.
        jax.tree.map(
            lambda a, b, k=k: np.testing.assert_allclose(a[k], b, rtol=1e-3, atol=0.1 * lrs[k]),
            states.params,
            state.params,
        )


def test_a_sweep_initialises_its_models_with_trains_init_key(tmp_path, monkeypatch):
    """Member k of ``sweep.py --seed S`` starts from the parameters ``train.py --seed S``
    starts from (the sweep takes train's --seed and its KEY_* constants). A mutation audit:
    the sweep initialising from the step key passed every test."""
    from indoorbev_jax import sweep

    keys = []

    def init(config, k, key):
        keys.append(key)
        raise _Stop

    monkeypatch.setattr(sweep, "init_sweep", init)
    cfg = dataclasses.replace(CFG, train=dataclasses.replace(CFG.train, seed=5))
    with pytest.raises(_Stop):
        sweep.run_sweep(cfg, tmp_path / "sw", stack_hypers(cfg, [1e-3], {}), progress=False)
    want = jax.random.fold_in(jax.random.key(5), T.KEY_INIT)
    np.testing.assert_array_equal(jax.random.key_data(keys[0]), jax.random.key_data(want))


def test_sweep_refuses_a_weight_the_config_has_not():
    """``--seed-weights`` without the seed head would be ignored silently; it is named."""
    with pytest.raises(ValueError, match="--seed-weights.*seed head"):
        stack_hypers(CFG, [1e-3, 2e-3], {"seed": [1.0, 2.0]})
    seeded = dataclasses.replace(CFG, head=dataclasses.replace(CFG.head, semantic_head=True))
    hypers = stack_hypers(seeded, [1e-3, 2e-3], {"seed": [1.0, 2.0]})
    np.testing.assert_array_equal(hypers.weights["seed"], [1.0, 2.0])
    assert "seed" not in T.Hyper.from_config(CFG).weights


def test_run_sweep_checks_hand_built_hypers_before_writing(tmp_path):
    """``run_sweep`` read K off the learning rates alone: K differing between fields failed
    inside vmap after config.json, hypers.json and run.json were written (and the corrected
    rerun was refused), and a negative learning rate trained uphill."""
    from indoorbev_jax import sweep
    from indoorbev_jax.sweep import check_hypers

    good = stack_hypers(CFG, [1e-3, 2e-3], {})
    assert check_hypers(good, CFG) == 2
    short = good.replace(weights=dict(good.weights, dice=jnp.ones(1)))
    uphill = good.replace(learning_rate=jnp.array([1e-3, -1e-3]))
    missing = good.replace(weights={k: v for k, v in good.weights.items() if k != "dice"})
    none = good.replace(learning_rate=jnp.zeros(0), weights={k: jnp.zeros(0) for k in good.weights})
    cases = (
        (none, r"hypers\.learning_rate: expected \[K\] with K >= 1 .*got shape \(0,\)"),
        (short, r"hypers\.weights\['dice'\]: expected \[K\] .*K = 2.*got shape \(1,\)"),
        (uphill, r"hypers\.learning_rate: expected finite values >= 0, got \[0\.001.*-0\.001"),
        (missing, r"hypers\.weights: expected the keys \[.*'dice'"),
    )
    for hypers, message in cases:
        with pytest.raises(ValueError, match=message):
            sweep.run_sweep(CFG, tmp_path / "sw", hypers, progress=False)
        assert not [p.name for p in (tmp_path / "sw").iterdir() if p.name != ".lock"]
    with pytest.raises(ValueError, match=r"--learning-rates: expected at least one value"):
        stack_hypers(CFG, [], {})
    np.testing.assert_array_equal(stack_hypers(CFG, 1e-3, {}).learning_rate, np.float32([1e-3]))
    one = stack_hypers(CFG, 1e-3, {"dice": 2.0})  # scalars: one model
    np.testing.assert_array_equal(one.weights["dice"], np.float32([2.0]))
    with pytest.raises(
        ValueError, match=r"--learning-rates: expected one value per model, got shape \(1, 2\)"
    ):
        stack_hypers(CFG, [[1e-3, 2e-3]], {})


def test_hypers_json_keeps_the_values_given():
    """hypers.json (and a member's exported config) held float32 round-offs: 1e-4 was
    9.999999747378752e-05, and weights never set (0.1) 0.10000000149011612."""
    from indoorbev_jax.sweep import hypers_to_json, same_settings

    lrs = [1e-4, 4e-4, 3e-3]
    settings = hypers_to_json(stack_hypers(CFG, lrs, {"dice": [5.0, 0.3, 2.5]}))
    assert settings["learning_rate"] == lrs and settings["weights"]["dice"] == [5.0, 0.3, 2.5]
    for name, values in settings["weights"].items():
        if name != "dice":
            assert values == [getattr(CFG.loss, f"{name}_weight")] * 3, name
    # A hypers.json written with the full digits still resumes; other settings do not.
    older = {"learning_rate": [float(np.float32(v)) for v in lrs],
             "weights": {k: [float(np.float32(v)) for v in vs]
                         for k, vs in settings["weights"].items()}}  # fmt: skip
    assert older["learning_rate"][0] == 9.999999747378752e-05 and same_settings(older, settings)
    assert not same_settings({**older, "learning_rate": [1e-4, 4e-4, 2e-3]}, settings)
    assert not same_settings({"learning_rate": lrs}, settings) and not same_settings({}, settings)


def test_params_ema_is_the_average_of_the_stepped_params(tmp_path):
    decay = 0.9
    cfg = dataclasses.replace(CFG, train=dataclasses.replace(CFG.train, ema_decay=decay))
    optimizer = T.make_optimizer(cfg)
    params = {"w": jnp.array([1.0, -2.0, 3.0]), "b": jnp.array(0.5)}
    state = T.TrainState(
        step=jnp.int32(0), params=params, opt_state=optimizer.init(params), skipped=jnp.int32(0)
    )
    ema = jax.tree.map(np.asarray, params)
    for k, lr in enumerate((0.1, 0.05, 0.2, 0.1)):
        grads = jax.tree.map(lambda p, k=k: 2 * p + k, state.params)  # d/dp (p^2 + k p)
        opt_state = T._set_learning_rate(state.opt_state, jnp.float32(lr))
        updates, opt_state = optimizer.update(grads, opt_state, state.params)
        new_params = optax.apply_updates(state.params, updates)
        state = state.replace(params=new_params, opt_state=opt_state)
        assert float(opt_state[1].hyperparams["learning_rate"]) == pytest.approx(lr)
        ema = jax.tree.map(lambda e, p: decay * e + (1 - decay) * np.asarray(p), ema, state.params)
    got = T.eval_params(state)
    jax.tree.map(lambda a, b: np.testing.assert_allclose(a, b, rtol=1e-6), got, ema)
    assert not np.allclose(got["w"], state.params["w"])
    # Without the average, evaluation reads the trained parameters.
    plain = state.replace(opt_state=T.make_optimizer(CFG).init(params))
    assert T.eval_params(plain) is plain.params


def test_run_with_ema_checkpoints_and_exports_the_average(tmp_path):
    cfg = dataclasses.replace(CFG, train=dataclasses.replace(CFG.train, ema_decay=0.99))
    state = T.init_state(cfg, jax.random.key(0))
    ema = T.eval_params(state)
    jax.tree.map(np.testing.assert_array_equal, ema, state.params)  # starts at the params
    # ... in buffers of its own, also when set up eagerly (with_pretrained): the train step
    # donates the state, and a buffer held twice cannot be donated.
    for s in (state, state.replace(opt_state=T.make_optimizer(cfg).init(state.params))):
        pointers = [x.unsafe_buffer_pointer() for x in jax.tree.leaves(s)]
        assert len(set(pointers)) == len(pointers)
    shifted = jax.tree.map(lambda x: x + 1.0, ema)
    opt_state = tuple(
        s._replace(ema=shifted) if isinstance(s, T.ParamsEmaState) else s for s in state.opt_state
    )
    (tmp_path / "config.json").write_text(cfg.to_json())
    ckpt = rundir.Checkpoints(tmp_path, cfg.train.keep_checkpoints)
    ckpt.save(state.replace(step=jnp.int32(5), opt_state=opt_state))
    ckpt.close()
    config, params = T.load_params(tmp_path, which="latest")
    assert config.train.ema_decay == 0.99
    jax.tree.map(np.testing.assert_array_equal, params, shifted)


@pytest.mark.parametrize("damage", ["garbage", "empty"])
def test_corrupt_latest_checkpoint_falls_back_and_is_written_anew(tmp_path, caplog, damage):
    """A corrupt latest checkpoint, or an empty step folder (a partial save: it used to make
    the intact older ones unreadable too), falls back to the previous one; a run that fell
    back past a bad step saves that step anew."""
    import shutil

    state = T.TrainState(
        step=jnp.int32(0), params={"w": jnp.arange(4.0)}, opt_state=(), skipped=jnp.int32(0)
    )
    ckpt = rundir.Checkpoints(tmp_path, keep=3)
    for step in (1, 2):
        ckpt.save(state.replace(step=jnp.int32(step), params={"w": jnp.arange(4.0) * step}))
    ckpt.close()
    bad = tmp_path / "checkpoints" / "2"
    if damage == "empty":
        shutil.rmtree(bad)
        bad.mkdir()
    else:
        for f in bad.rglob("*"):
            if f.is_file():
                f.write_bytes(b"garbage")
    ckpt = rundir.Checkpoints(tmp_path, keep=3)
    with caplog.at_level("WARNING"):
        restored = ckpt.restore(state)
    assert restored is not None and int(restored.step) == 1
    np.testing.assert_array_equal(restored.params["w"], np.arange(4.0))
    assert "checkpoint 2 is unreadable" in caplog.text
    ckpt.save(state.replace(step=jnp.int32(2), params={"w": jnp.arange(4.0) * 7}))
    ckpt.close()
    again = rundir.Checkpoints(tmp_path, keep=3).restore(state)
    assert int(again.step) == 2
    np.testing.assert_array_equal(again.params["w"], np.arange(4.0) * 7)


SHARDED = textwrap.dedent(
    """
    import os, sys
    flags = os.environ.get("XLA_FLAGS", "")
    os.environ["XLA_FLAGS"] = flags + " --xla_force_host_platform_device_count=4"
    import jax, jax.numpy as jnp, numpy as np
    from indoorbev_jax import train as T
    from indoorbev_jax.config import Config
    from indoorbev_jax.data.dataset import KittiDataset
    import dataclasses
    cfg = Config.tiny()
    cfg = dataclasses.replace(cfg, train=dataclasses.replace(cfg.train, batch_size=4))
    assert jax.device_count() == 4
    batch = next(KittiDataset(sys.argv[1], "train", cfg).batches(4))
    state = T.init_state(cfg, jax.random.key(0))
    step = T.make_train_step(cfg)
    hyper = T.Hyper.from_config(cfg)
    run = jax.jit(lambda s, b: step(s, b, jax.random.key(1), hyper))
    single_state, single = run(state, batch)
    mesh = T.data_mesh()
    sharded_batch = T.shard_batch(batch, mesh)
    assert len(sharded_batch.points.sharding.device_set) == 4
    multi_state, multi = run(T.replicate(state, mesh), sharded_batch)
    np.testing.assert_allclose(multi["loss"], single["loss"], rtol=1e-5)
    np.testing.assert_allclose(multi["grad_norm"], single["grad_norm"], rtol=1e-4)
    jax.tree.map(lambda a, b: np.testing.assert_allclose(a, b, rtol=1e-4, atol=1e-6),
                 multi_state.params, single_state.params)
    print("SHARDED_OK", float(single["loss"]), float(multi["loss"]))
    """
)


def _env(cache):
    env = dict(os.environ, JAX_PLATFORMS="cpu")
    env.setdefault("JAX_COMPILATION_CACHE_DIR", str(cache))  # the Makefile sets a shared one
    env.setdefault("JAX_PERSISTENT_CACHE_MIN_COMPILE_TIME_SECS", "0")
    return env


def test_sharded_step_equals_single_device(data, tmp_path):
    out = subprocess.run(
        [sys.executable, "-c", SHARDED, str(data)],
        capture_output=True, text=True, env=_env(tmp_path / "cache"), timeout=900,
    )  # fmt: skip
    assert "SHARDED_OK" in out.stdout, out.stderr[-3000:]


def _train_cmd(data, workdir, init_from):
    return [
        sys.executable, str(REPO / "experiments" / "train.py"), "--preset", "tiny",
        "--workdir", str(workdir), "--data", str(data), "--steps", "6",
        "--checkpoint-every", "2", "--eval-every", "6", "--no-progress",
        "--init-from", str(init_from),
    ]  # fmt: skip


def test_kill_and_rerun_resumes_bitwise(data, tmp_path):
    """A run started from a trained model (--init-from), killed after its step-2 checkpoint
    and rerun, ends bitwise equal to an uninterrupted one: the rerun resumes from its own
    checkpoint instead of loading the model again."""
    from indoorbev_jax.predict import export_model

    pretrained = export_model(
        T.init_state(CFG, jax.random.key(3)).params, CFG, tmp_path / "pretrained.msgpack"
    )
    env = _env(tmp_path / "cache")
    full, killed = tmp_path / "full", tmp_path / "killed"
    first = subprocess.run(
        _train_cmd(data, full, pretrained), check=True, env=env, timeout=900,
        capture_output=True, text=True,
    )  # fmt: skip
    assert f"indoorbev_jax.train: parameters from {pretrained}" in first.stderr  # logs show
    proc = subprocess.Popen(
        _train_cmd(data, killed, pretrained), env=env, stderr=subprocess.DEVNULL
    )
    deadline = time.time() + 600
    # Until checkpoint 2 appears, or the run ends without it (a failure, told at once).
    while time.time() < deadline and not (killed / "checkpoints" / "2").is_dir():
        if proc.poll() is not None:
            break
        time.sleep(0.2)
    proc.kill()  # SIGKILL; nothing when the run has ended
    proc.wait()
    assert (killed / "checkpoints" / "2").is_dir()
    subprocess.run(_train_cmd(data, killed, pretrained), check=True, env=env, timeout=900)
    record = json.loads((killed / "init_from.json").read_text())
    assert record["sha256"] == hashlib.sha256(Path(pretrained).read_bytes()).hexdigest()

    template = T.init_state(CFG, jax.random.key(0))
    a = rundir.Checkpoints(full, 2).restore(template)
    b = rundir.Checkpoints(killed, 2).restore(template)
    assert int(a.step) == int(b.step) == 6
    jax.tree.map(np.testing.assert_array_equal, a.params, b.params)
    jax.tree.map(np.testing.assert_array_equal, a.opt_state, b.opt_state)
    text = (killed / "metrics.jsonl").read_text()
    assert "NaN" not in text  # undefined metrics are written as null
    steps = [json.loads(line)["step"] for line in text.splitlines()]
    assert steps == sorted(steps) and len(steps) == len(set(steps)) + 1  # train + eval at 6
    assert (killed / "config.json").exists() and any((killed / "tb").iterdir())


def test_config_mismatch_in_workdir_is_an_error(tmp_path):
    (tmp_path / "config.json").write_text(Config.small().to_json())
    with pytest.raises(ValueError, match="config.json: the workdir holds a run") as refused:
        T.train_and_evaluate(CFG, tmp_path, data=str(tmp_path), progress=False)
    # Nothing was trained there: the message says how to start afresh.
    assert "no checkpoint yet, so nothing was trained: remove its config.json" in str(refused.value)


def test_bad_training_labels_and_an_empty_val_split_stop_the_start(data, tmp_path, quick_start):
    """A training label file with an unknown class is named before config.json is written
    (it used to fail at its step, leaving a config.json that refused the corrected command);
    a val split without frames is refused (every evaluation would be NaN)."""
    import shutil

    own = tmp_path / "own"
    shutil.copytree(data, own)
    first = kitti.read_split(own, "train")[-1]
    label = own / "label_2" / f"{first}.txt"
    label.write_text(label.read_text().replace(label.read_text().split()[0], "Desk", 1))
    workdir = tmp_path / "run"
    with pytest.raises(kitti.DatasetError, match=rf"{first}\.txt:1: unknown class 'Desk'"):
        T.train_and_evaluate(CFG, workdir, data=str(own), progress=False)
    assert not (workdir / "config.json").exists()
    mapped = with_overrides(CFG, ['data.class_map={"Desk": "Table"}'])
    kitti.write_split(own, "val", [])
    with pytest.raises(kitti.DatasetError, match=r"val\.txt: lists no frames to validate on"):
        T.train_and_evaluate(mapped, workdir, data=str(own), progress=False)
    assert not (workdir / "config.json").exists()


def test_a_malformed_validation_frame_is_named_and_skipped_when_asked(data, tmp_path, caplog):
    """--skip-bad-frames covers the val split too (it stopped the start), and only the
    frames validation uses are read."""
    import shutil

    own = tmp_path / "own"
    shutil.copytree(data, own)
    val_ids = kitti.read_split(own, "val")
    bad = own / "velodyne" / f"{val_ids[0]}.bin"
    bad.write_bytes(bad.read_bytes()[:100])
    with pytest.raises(kitti.DatasetError, match=rf"{val_ids[0]}\.bin"):
        T.make_sources(CFG, str(own), 0, skip_bad=False)
    with caplog.at_level("WARNING"):
        _, val = T.make_sources(CFG, str(own), 0, skip_bad=True)
    assert f"skipping malformed validation frame {val_ids[0]}" in caplog.text
    frames = sum(int(b.points.shape[0]) for b in val)
    want = min(len(val_ids) - 1, CFG.train.eval_batches * CFG.train.batch_size)
    assert frames == want
    good = KittiDataset(own, "val", CFG).load(1)[0]  # the first readable frame leads
    np.testing.assert_array_equal(val[0].points[0], good.points)
    # A sweep does not validate: no val split needed.
    (own / "val.txt").unlink()
    source, none = T.make_sources(CFG, str(own), 0, skip_bad=False, validate=False)
    assert none == [] and source is not None


def test_a_malformed_training_frame_is_named_and_skipped_when_asked(data, tmp_path, caplog):
    """KittiSource: without --skip-bad-frames a truncated .bin stops at its step, naming
    it; with it the frame is reported, left out of every batch, and a split with no
    readable frame left is an error."""
    import shutil

    own = tmp_path / "own"
    shutil.copytree(data, own)
    ids = kitti.read_split(own, "train")
    bad = own / "velodyne" / f"{ids[0]}.bin"
    bad.write_bytes(bad.read_bytes()[:100])
    strict = sources.KittiSource(own, "train", CFG, seed=0)
    per_epoch = len(ids) // CFG.train.batch_size
    with pytest.raises(kitti.DatasetError, match=rf"{ids[0]}\.bin"):
        for step in range(per_epoch):
            strict(step)
    lenient = sources.KittiSource(own, "train", CFG, seed=0, skip_bad=True)
    with caplog.at_level("WARNING"):
        batches = [lenient(step) for step in range(per_epoch)]
    assert f"skipping malformed frame {ids[0]}" in caplog.text
    good = KittiDataset(own, "train", CFG)
    firsts = {good.load(k)[0].points.tobytes() for k in range(1, len(ids))}
    for b in batches:
        for points in np.asarray(b.points):
            assert points.tobytes() in firsts  # never the bad frame, every one readable
    for frame_id in ids[1:]:
        path = own / "velodyne" / f"{frame_id}.bin"
        path.write_bytes(path.read_bytes()[:100])
    with pytest.raises(kitti.DatasetError, match="no readable frame left"):
        sources.KittiSource(own, "train", CFG, seed=0, skip_bad=True)(0)


def test_kitti_source_reshuffles_every_epoch_and_with_the_seed(data):
    """docs/TRAINING.md: with --data, frames come from train.txt "reshuffled every epoch from
    the seed": each epoch reads every frame at most once, a later epoch in another order, and
    another train.seed in another order. A mutation audit (the order drawn from the seed alone,
    so every epoch repeats it; or from a fixed seed, so train.seed is ignored) passed all
    tests. Frames are told apart by their point bytes, read with KittiDataset."""
    dataset = KittiDataset(data, "train", CFG)
    index = {dataset.load(k)[0].points.tobytes(): k for k in range(len(dataset))}
    assert len(index) == len(dataset) >= 2 * CFG.train.batch_size
    per_epoch = len(dataset) // CFG.train.batch_size

    def read(seed, epoch):
        source = sources.KittiSource(data, "train", CFG, seed=seed)
        order = []
        for step in range(epoch * per_epoch, (epoch + 1) * per_epoch):
            order += [index[p.tobytes()] for p in np.asarray(source(step).points)]
        assert len(set(order)) == len(order) == per_epoch * CFG.train.batch_size
        return order

    first = read(0, 0)
    assert read(0, 0) == first  # the same (seed, epoch) reads the same frames
    assert read(0, 1) != first
    assert read(1, 0) != first


def test_an_epoch_of_a_split_that_batches_do_not_divide_reads_no_frame_twice(data, tmp_path):
    """5 frames in batches of 2: an epoch is 2 steps (4 distinct frames of its order), the
    fifth waits for a later epoch, and step 2 starts epoch 1's order. A mutation audit: the
    steps per epoch rounded up (step 2 wrapped to epoch 0's first frame again) passed, every
    other split dividing evenly."""
    import shutil

    own = tmp_path / "own"
    shutil.copytree(data, own)
    (own / "train.txt").write_text("\n".join(kitti.read_split(own, "train")[:5]) + "\n")
    dataset = KittiDataset(own, "train", CFG)
    index = {dataset.load(k)[0].points.tobytes(): k for k in range(len(dataset))}
    assert len(index) == len(dataset) == 5 and CFG.train.batch_size == 2
    source = sources.KittiSource(own, "train", CFG, seed=3)
    read = [[index[p.tobytes()] for p in np.asarray(source(step).points)] for step in range(3)]
    assert read[0] + read[1] == source._order(0)[:4].tolist()
    assert read[2] == source._order(1)[:2].tolist()


def test_a_frame_with_more_objects_than_max_objects_is_named(data, tmp_path, caplog):
    """Targets keep the first data.max_objects objects; the rest trained (and were scored)
    as background without a word. Now the start refuses naming the file, and with
    --skip-bad-frames the frame is left out, reported."""
    import dataclasses
    import shutil

    own = tmp_path / "own"
    shutil.copytree(data, own)
    ids = kitti.read_split(own, "train")
    counts = {i: len(kitti.read_labels(own / "label_2" / f"{i}.txt", CFG.data)) for i in ids}
    crowded = max(counts, key=counts.get)
    assert counts[crowded] >= 2
    cfg = dataclasses.replace(
        CFG, data=dataclasses.replace(CFG.data, max_objects=counts[crowded] - 1)
    )
    message = rf"{crowded}\.txt: {counts[crowded]} objects, more than data\.max_objects="
    with pytest.raises(kitti.DatasetError, match=message + str(counts[crowded] - 1)):
        sources.KittiSource(own, "train", cfg, seed=0)
    lenient = sources.KittiSource(own, "train", cfg, seed=0, skip_bad=True)
    with caplog.at_level("WARNING"):
        for step in range(len(ids) // cfg.train.batch_size):
            lenient(step)
    assert f"skipping malformed frame {crowded}" in caplog.text


def _scalar_state(step: int) -> T.TrainState:
    """A train state of step ``step`` whose one parameter is the step."""
    return T.TrainState(step=jnp.int32(step), params={"w": jnp.float32(step)}, opt_state=(),
                        skipped=jnp.int32(0))  # fmt: skip


@pytest.mark.parametrize("keep", [1, 2])
def test_checkpoints_keep_the_latest_keep_steps(tmp_path, keep):
    """``train.keep_checkpoints`` steps stay, the latest among them: with one fewer, keep=1
    kept none and a resume started again from step 0."""
    ckpt = rundir.Checkpoints(tmp_path, keep=keep)
    for step in (1, 2, 3, 4):
        ckpt.save(_scalar_state(step))
    ckpt.close()
    kept = sorted(int(p.name) for p in (tmp_path / "checkpoints").iterdir())
    assert kept == [*range(5 - keep, 5)]
    restored = rundir.Checkpoints(tmp_path, keep=keep).restore(_scalar_state(0))
    assert int(restored.step) == 4 and float(restored.params["w"]) == 4.0


def test_a_nan_validation_score_never_replaces_a_better_best(tmp_path):
    """PQ is NaN on a validation split without objects when nothing is predicted: as a
    number it took best/ from a step with PQ 0.3 for good."""
    ckpt = rundir.Checkpoints(tmp_path, keep=2)
    for step, pq in ((1, 0.3), (2, float("nan")), (3, 0.1)):
        ckpt.save_best(_scalar_state(step), {"pq": pq})
    assert ckpt.best.best_step() == 1 and ckpt.best.all_steps() == [1]
    ckpt.close()


class _Stop(Exception):
    """Raised by a spy once what a test checks has run: the first train step of
    ``quick_start`` (the start's checks have run), or a function whose key a test reads."""


_INITS: dict = {}


@pytest.fixture
def quick_start(monkeypatch):
    """``train_and_evaluate`` stops at its first step (raising ``_Stop``) and initialises
    each (config, key) once, so the tests of a run's start stay quick. Returns the keys
    each train step was called with."""
    init_state, step_keys = T.init_state, []

    def cached_init(config, key):
        index = (config, np.asarray(jax.random.key_data(key)).tobytes())
        if index not in _INITS:
            _INITS[index] = init_state(config, key)
        return _INITS[index]

    def stop(state, batch, key, hyper):
        step_keys.append(key)
        raise _Stop

    monkeypatch.setattr(T, "init_state", cached_init)
    monkeypatch.setattr(T, "jit_train_step", lambda *args, **kwargs: stop)
    return step_keys


class _FakeSim:
    """Stands in for ``SimSource`` and records the key it was given."""

    keys: dict = {}

    def __init__(self, config, key, split="train"):
        _FakeSim.keys[split] = key

    def __call__(self, step):
        return None


def test_a_kill_during_evaluation_redoes_it(data, tmp_path, quick_start, monkeypatch):
    """A step that evaluates and checkpoints evaluates first: killed inside the evaluation,
    the run has no checkpoint of that step, so the rerun trains it again and evaluates it
    (the other order resumed past it, and its eval line and best/ candidate were lost)."""
    cfg = dataclasses.replace(
        CFG,
        train=dataclasses.replace(
            CFG.train, total_steps=4, eval_every=2, checkpoint_every=2, log_every=2
        ),
    )

    def fake_step(state, batch, key, hyper):  # the loop's bookkeeping, without compiling
        return state.replace(step=state.step + 1), {"loss": jnp.float32(1.0), "finite": True}

    evaluated = []

    def fake_evaluate(config, params, batches, predict_fn):
        evaluated.append(len(evaluated))
        if len(evaluated) == 2:  # the evaluation of step 4
            raise KeyboardInterrupt
        return {"pq": 0.5, "ap": {0.5: 0.25}}

    monkeypatch.setattr(T, "jit_train_step", lambda *args, **kwargs: fake_step)
    monkeypatch.setattr(T, "evaluate", fake_evaluate)
    workdir = tmp_path / "run"
    with pytest.raises(KeyboardInterrupt):
        T.train_and_evaluate(cfg, workdir, data=str(data), progress=False)
    assert sorted(int(p.name) for p in (workdir / "checkpoints").iterdir()) == [2]
    T.train_and_evaluate(cfg, workdir, data=str(data), progress=False)
    lines = [json.loads(x) for x in (workdir / "metrics.jsonl").read_text().splitlines()]
    assert [(r["step"], r["kind"]) for r in lines] == [
        (2, "train"),
        (2, "eval"),
        (4, "train"),
        (4, "eval"),
    ]


def test_a_seed_past_32_bits_is_refused_before_anything_is_written(data, tmp_path):
    """-1 failed at step 0 after config.json kept it; 2**32 trained seed 0's run again."""
    from indoorbev_jax import sweep

    for seed in (-1, 2**32):
        bad = dataclasses.replace(CFG, train=dataclasses.replace(CFG.train, seed=seed))
        with pytest.raises(ValueError, match=r"'train\.seed': must lie in \[0, 2\*\*32\)"):
            T.train_and_evaluate(bad, tmp_path / "run", data=str(data), progress=False)
        with pytest.raises(ValueError, match=r"'train\.seed': must lie in \[0, 2\*\*32\)"):
            sweep.run_sweep(bad, tmp_path / "sw", stack_hypers(bad, [1e-3], {}), str(data))
    assert not list(tmp_path.glob("*/*.json"))  # no config.json, run.json or hypers.json


def test_a_resumed_train_line_says_how_many_steps_it_averages(data, tmp_path, monkeypatch):
    """Resumed from a checkpoint between two log lines, the first train line averages only
    the steps since: its ``steps`` says so (the line looked like a full window)."""
    cfg = dataclasses.replace(
        CFG,
        train=dataclasses.replace(
            CFG.train, total_steps=8, eval_every=8, checkpoint_every=3, log_every=4
        ),
    )
    kill_at = []

    def fake_step(state, batch, key, hyper):  # loss = step + 1, without compiling
        if int(state.step) in kill_at:
            kill_at.clear()
            raise KeyboardInterrupt
        loss = jnp.float32(state.step + 1)
        return state.replace(step=state.step + 1), {"loss": loss, "finite": True}

    monkeypatch.setattr(T, "jit_train_step", lambda *args, **kwargs: fake_step)
    monkeypatch.setattr(T, "evaluate", lambda *args: {"pq": 0.5, "ap": {0.5: 0.25}})

    def train_lines(workdir):
        rows = [json.loads(x) for x in (workdir / "metrics.jsonl").read_text().splitlines()]
        return [(r["step"], r["steps"], r["loss"]) for r in rows if r["kind"] == "train"]

    T.train_and_evaluate(cfg, tmp_path / "full", data=str(data), progress=False)
    assert train_lines(tmp_path / "full") == [(4, 4, 2.5), (8, 4, 6.5)]
    kill_at.append(3)  # after the step-3 checkpoint, before the step-4 line
    with pytest.raises(KeyboardInterrupt):
        T.train_and_evaluate(cfg, tmp_path / "cut", data=str(data), progress=False)
    T.train_and_evaluate(cfg, tmp_path / "cut", data=str(data), progress=False)
    assert train_lines(tmp_path / "cut") == [(4, 1, 4.0), (8, 4, 6.5)]


def test_an_interrupted_save_is_no_checkpoint(tmp_path):
    """orbax writes a step under ``<step>.orbax-checkpoint-tmp`` first: a run killed there
    has trained nothing that a changed config would contradict."""
    (tmp_path / "checkpoints" / "100.orbax-checkpoint-tmp").mkdir(parents=True)
    assert not rundir._has_checkpoint(tmp_path)
    (tmp_path / "checkpoints" / "100").mkdir()
    assert rundir._has_checkpoint(tmp_path)


def test_metrics_log_drops_a_torn_last_line_only(tmp_path, caplog, full_disk):
    path = tmp_path / "metrics.jsonl"
    good = ['{"step": 5, "kind": "train", "loss": 2.0}', '{"step": 10, "kind": "train"}']
    path.write_text("\n".join(good) + '\n\n{"step": 15, "kind": "tr')  # killed mid-write
    with caplog.at_level("WARNING"):
        rundir.MetricsLog(tmp_path, resume_step=10).close()
    assert path.read_text() == "".join(line + "\n" for line in good)
    assert f"{path}: line 4 is cut off" in caplog.text
    assert not list(tmp_path.glob("*.tmp"))  # rewritten through a temporary file
    # The resumed run appends to the repaired log.
    log = rundir.MetricsLog(tmp_path, resume_step=10)
    log.write(15, "train", {"loss": 1.0, "pq": float("nan"), "grad_norm": float("inf")})
    log.close()

    def refuse(constant):  # json.loads reads NaN and Infinity, which JSON has not
        raise ValueError(f"not JSON: {constant}")

    records = [json.loads(line, parse_constant=refuse) for line in path.read_text().splitlines()]
    assert [r["step"] for r in records] == [5, 10, 15]
    assert records[-1]["pq"] is None and records[-1]["grad_norm"] is None
    # TensorBoard drops events from the resumed run's first new step on: step 10's records
    # were written before its checkpoint, and purging from 10 lost them there.
    from tensorboardX.proto import event_pb2

    newest = max((tmp_path / "tb").glob("events.*"), key=lambda f: f.stat().st_mtime_ns)
    data, starts = newest.read_bytes(), []
    while data:  # TFRecords: length (8), its crc (4), the event, its crc (4)
        n = int.from_bytes(data[:8], "little")
        event = event_pb2.Event.FromString(data[12 : 12 + n])
        if event.HasField("session_log") and event.session_log.status == 1:  # START
            starts.append(event.step)
        data = data[16 + n :]
    assert starts == [11]
    # A rewrite the disk cannot finish leaves the log as it was.
    before = path.read_text()
    with full_disk(), pytest.raises(OSError, match=f"{re.escape(str(path))}: No space left"):
        rundir.MetricsLog(tmp_path, resume_step=5)
    assert path.read_text() == before and not list(tmp_path.glob(".*.tmp"))
    # A bad line with lines after it is corruption, not a torn write.
    path.write_text(good[0] + '\n{"step": 7, "ki\n' + good[1] + "\n")
    with pytest.raises(ValueError, match=f"{re.escape(str(path))}: line 2 is not a JSON object"):
        rundir.MetricsLog(tmp_path, resume_step=10)


def test_refused_start_leaves_no_config_json(data, tmp_path, quick_start):
    workdir = tmp_path / "run"
    big = dataclasses.replace(CFG, train=dataclasses.replace(CFG.train, batch_size=16))
    with pytest.raises(ValueError, match="fewer than train.batch_size=16"):
        T.train_and_evaluate(big, workdir, data=str(data), progress=False)
    assert not (workdir / "config.json").exists() and not (workdir / "run.json").exists()
    with pytest.raises(_Stop):  # the corrected command starts
        T.train_and_evaluate(CFG, workdir, data=str(data), progress=False)
    assert Config.from_dict(json.loads((workdir / "config.json").read_text())) == CFG


def test_a_workdir_in_use_by_another_run_is_refused(data, tmp_path, quick_start, monkeypatch):
    """Two runs in one workdir both ran to the end, writing one metrics log (steps 5..20
    twice) and one set of checkpoints; the second is now refused, naming the first."""
    import fcntl

    from indoorbev_jax.sweep import run_sweep

    workdir = tmp_path / "run"
    workdir.mkdir()
    with open(workdir / ".lock", "w") as other:  # the first run, as its lock shows it
        fcntl.flock(other, fcntl.LOCK_EX | fcntl.LOCK_NB)
        other.write("pid 4242\n")
        other.flush()
        with pytest.raises(ValueError, match=r"run: in use by another run \(pid 4242\)"):
            T.train_and_evaluate(CFG, workdir, data=str(data), progress=False)
        with pytest.raises(ValueError, match=r"run: in use by another run \(pid 4242\)"):
            run_sweep(CFG, workdir, stack_hypers(CFG, [1e-3], {}), str(data), progress=False)
        assert not (workdir / "config.json").exists()
        # The other hosts of a multi-host run share the workdir: only process 0 locks it.
        with monkeypatch.context() as m, pytest.raises(_Stop):
            m.setattr(jax, "process_index", lambda: 1)
            T.train_and_evaluate(CFG, workdir, data=str(data), progress=False)
        # ... and leaves the run's own files to process 0: each host wrote every metrics line.
        for name in ("config.json", "run.json", "metrics.jsonl", "tb"):
            assert not (workdir / name).exists(), name
    # A filesystem without flock (Lustre without -o flock): a warning, and the run starts.
    import errno

    def no_flock(*_):
        raise OSError(errno.ENOSYS, "Function not implemented")

    with monkeypatch.context() as m, pytest.raises(_Stop):
        m.setattr(fcntl, "flock", no_flock)
        T.train_and_evaluate(CFG, workdir, data=str(data), progress=False)
    with pytest.raises(_Stop):  # once the first run has ended, it starts
        T.train_and_evaluate(CFG, workdir, data=str(data), progress=False)


def test_resume_refuses_another_data_source(data, tmp_path, quick_start, monkeypatch):
    monkeypatch.setattr(T, "SimSource", _FakeSim)
    workdir = tmp_path / "run"
    with pytest.raises(_Stop):
        T.train_and_evaluate(CFG, workdir, data=str(data), progress=False)
    folder = str(Path(data).resolve())
    assert json.loads((workdir / "run.json").read_text()) == rundir.run_record(folder)
    with pytest.raises(ValueError) as refused:
        T.train_and_evaluate(CFG, workdir, data=None, progress=False)
    assert str(refused.value) == (
        f"{workdir / 'run.json'}: the run trained on {folder}, this command gives the simulator "
        "(if the same data moved, edit the data field of run.json)"
    )
    other = tmp_path / "other"
    write_synthetic_dataset(other, frames=8, seed=1)
    with pytest.raises(ValueError, match=f"trained on {re.escape(folder)}, .* gives {other}"):
        T.train_and_evaluate(CFG, workdir, data=str(other), progress=False)
    monkeypatch.chdir(Path(data).parent)  # the same folder spelled another way resumes
    with pytest.raises(_Stop):
        T.train_and_evaluate(CFG, workdir, data=f"./{Path(data).name}/", progress=False)


def test_resume_refuses_a_changed_split_list(data, tmp_path, quick_start):
    workdir, data = tmp_path / "run", shutil.copytree(data, tmp_path / "data")
    with pytest.raises(_Stop):
        T.train_and_evaluate(CFG, workdir, data=str(data), progress=False)
    train_txt = Path(data) / "train.txt"
    ids = train_txt.read_text().split()
    # Before any checkpoint a changed list costs nothing: the run starts again (TRAINING.md).
    train_txt.write_text("\n".join(ids[::-1]) + "\n")
    with pytest.raises(_Stop):
        T.train_and_evaluate(CFG, workdir, data=str(data), progress=False)
    train_txt.write_text("\n".join(ids) + "\n")
    with pytest.raises(_Stop):
        T.train_and_evaluate(CFG, workdir, data=str(data), progress=False)
    (workdir / "checkpoints" / "3").mkdir(parents=True)  # as if step 3 were saved
    record = json.loads((workdir / "run.json").read_text())
    assert record["splits"]["train.txt"] == hashlib.sha256(train_txt.read_bytes()).hexdigest()
    train_txt.write_text("\n".join(ids[::-1]) + "\n")  # the same frames in another order
    with pytest.raises(ValueError) as refused:
        T.train_and_evaluate(CFG, workdir, data=str(data), progress=False)
    assert str(refused.value).startswith(
        f"{workdir / 'run.json'}: {Path(data).resolve() / 'train.txt'} changed since the run "
        f"started (sha256 {record['splits']['train.txt'][:12]} -> "
    )
    train_txt.write_text("\n".join(ids) + "\n")  # restored: resumes
    with pytest.raises(_Stop):
        T.train_and_evaluate(CFG, workdir, data=str(data), progress=False)


def test_resume_names_changed_fields_and_allows_schedule_only_ones(
    data, tmp_path, quick_start, caplog
):
    with pytest.raises(_Stop):
        T.train_and_evaluate(CFG, tmp_path, data=str(data), progress=False)
    t = CFG.train
    sched = dataclasses.replace(
        CFG,
        train=dataclasses.replace(
            t, eval_every=5, log_every=1, checkpoint_every=2, keep_checkpoints=4
        ),
    )
    with caplog.at_level("INFO", logger="indoorbev_jax.rundir"), pytest.raises(_Stop):
        T.train_and_evaluate(sched, tmp_path, data=str(data), progress=False)
    for line in ("train.eval_every: 10 -> 5", "train.log_every: 5 -> 1",
                 "train.checkpoint_every: 5 -> 2", "train.keep_checkpoints: 2 -> 4"):  # fmt: skip
        assert line in caplog.text
    assert Config.from_dict(json.loads((tmp_path / "config.json").read_text())) == sched
    changed = dataclasses.replace(
        sched,
        train=dataclasses.replace(sched.train, learning_rate=2e-3, total_steps=30, eval_every=3),
        loss=dataclasses.replace(CFG.loss, dice_weight=1.0),
    )
    with pytest.raises(ValueError) as refused:
        T.train_and_evaluate(changed, tmp_path, data=str(data), progress=False)
    lines = str(refused.value).splitlines()
    assert lines[0].startswith(f"{tmp_path / 'config.json'}: the workdir holds a run with")
    assert lines[1:-1] == [  # each refused field, and only those
        "  loss.dice_weight: 5.0 -> 1.0",
        "  train.learning_rate: 0.001 -> 0.002",
        "  train.total_steps: 20 -> 30",
    ]
    assert Config.from_dict(json.loads((tmp_path / "config.json").read_text())) == sched


def test_each_use_of_the_run_key_has_its_own_stream(tmp_path, quick_start, monkeypatch):
    """Model init, training data, validation data and the train steps' keys are four
    different streams of key(train.seed), in a run and in a sweep alike."""
    from indoorbev_jax import sweep

    monkeypatch.setattr(T, "SimSource", _FakeSim)
    inits = []
    cached_init = T.init_state
    monkeypatch.setattr(T, "init_state", lambda c, key: inits.append(key) or cached_init(c, key))
    with pytest.raises(_Stop):
        T.train_and_evaluate(CFG, tmp_path / "run", progress=False)

    def fake_step(states, batch, key, hypers):
        quick_start.append(key)
        raise _Stop

    monkeypatch.setattr(sweep, "init_sweep", lambda c, k, key: inits.append(key))
    monkeypatch.setattr(sweep, "make_sweep_step", lambda c, database=None: fake_step)
    runs = [dict(_FakeSim.keys, init=inits[0], steps=quick_start[0])]
    with pytest.raises(_Stop):
        sweep.run_sweep(CFG, tmp_path / "sweep", stack_hypers(CFG, [1e-3], {}))
    runs.append(dict(_FakeSim.keys, init=inits[1], steps=quick_start[1]))
    root = jax.random.key(CFG.train.seed)
    for keys in runs:
        data = {name: np.asarray(jax.random.key_data(k)) for name, k in keys.items()}
        assert sorted(data) == ["init", "steps", "train", "val"]
        distinct = {v.tobytes() for v in data.values()}
        assert len(distinct) == 4, {name: v.tolist() for name, v in data.items()}
        # experiments/eval_sim.py keeps its frames clear of these two streams.
        for name, n in (("train", 0), ("val", 1)):
            want = jax.random.key_data(jax.random.fold_in(root, n))
            np.testing.assert_array_equal(data[name], want)


def test_each_train_step_draws_its_own_augmentation(monkeypatch):
    """The step's keys come from fold_in(run key, step): the same step draws the same
    augmentation, the next step another. A mutation audit: every step augmenting with the
    same key passed (the tests above check only the run key the steps are handed)."""
    import types

    seen = []

    def record(config, batch, key, database):
        seen.append(key)
        raise _Stop

    monkeypatch.setattr(T, "training_batch", record)
    cfg = dataclasses.replace(CFG, train=dataclasses.replace(CFG.train, augment=True))
    step, key = T.make_train_step(cfg), jax.random.key(7)
    for s in (0, 0, 1):
        with pytest.raises(_Stop):
            step(types.SimpleNamespace(step=jnp.int32(s)), None, key, None)
    got = [np.asarray(jax.random.key_data(k)) for k in seen]
    np.testing.assert_array_equal(got[0], got[1])
    assert not np.array_equal(got[1], got[2])


def test_box_targets_are_the_rasterised_labelled_boxes(batch):
    from indoorbev_jax.data.rasterize import rasterize_boxes

    boxed = sources.box_targets(batch, CFG.grid).targets
    t = batch.targets
    for b in range(t.valid.shape[0]):
        boxes = np.concatenate(
            [
                np.asarray(t.pos[b, :, :2]),
                np.asarray(t.dims[b, :, :2]),
                np.asarray(t.yaw[b])[:, None],
            ],
            1,
        )
        ids, masks = rasterize_boxes(jnp.asarray(boxes), t.valid[b], CFG.grid)
        np.testing.assert_array_equal(boxed.masks[b], masks)
        np.testing.assert_array_equal(boxed.instance_ids[b], ids)
    np.testing.assert_array_equal(boxed.classes, t.classes)


def test_gt_database_holds_every_valid_object_of_its_batches(batch):
    steps = []
    db = sources.gt_database(lambda i: steps.append(i) or batch, 2, CFG.grid)
    assert steps == [0, 1]  # "the first N training batches"
    n = int(np.asarray(batch.targets.valid).sum())
    assert db.classes.shape == (2 * n,)
    want = np.asarray(batch.targets.classes)[np.asarray(batch.targets.valid)]
    np.testing.assert_array_equal(db.classes, np.concatenate([want, want]))


def test_box_mask_targets_apply_to_training_batches_of_any_source(data):
    import dataclasses

    boxed_cfg = dataclasses.replace(CFG, data=dataclasses.replace(CFG.data, mask_targets="box"))
    train, val = T.make_sources(boxed_cfg, str(data), 0, False)
    shaped, shaped_val = T.make_sources(CFG, str(data), 0, False)
    want = sources.box_targets(shaped(0), CFG.grid).targets
    got = train(0).targets
    np.testing.assert_array_equal(got.masks, want.masks)
    np.testing.assert_array_equal(got.instance_ids, want.instance_ids)
    np.testing.assert_array_equal(val[0].targets.masks, shaped_val[0].targets.masks)


def test_with_pretrained_loads_a_model_file_and_names_mismatches(tmp_path):
    from indoorbev_jax.predict import export_model

    trained = T.init_state(CFG, jax.random.key(7)).params
    path = export_model(trained, CFG, tmp_path / "trained.msgpack")
    state = T.init_state(CFG, jax.random.key(0))
    moved = state.replace(opt_state=jax.tree.map(lambda x: x + 1, state.opt_state))
    loaded = T.with_pretrained(moved, CFG, path)
    for a, b in zip(jax.tree.leaves(loaded.params), jax.tree.leaves(trained), strict=True):
        np.testing.assert_array_equal(np.asarray(a), np.asarray(b))
    fresh = T.make_optimizer(CFG).init(loaded.params)
    for a, b in zip(jax.tree.leaves(loaded.opt_state), jax.tree.leaves(fresh), strict=True):
        np.testing.assert_array_equal(np.asarray(a), np.asarray(b))
    assert int(loaded.step) == int(moved.step)

    names = tuple(reversed(CFG.data.class_names))
    renamed = dataclasses.replace(CFG, data=dataclasses.replace(CFG.data, class_names=names))
    with pytest.raises(ValueError, match="data.class_names"):
        T.with_pretrained(T.init_state(renamed, jax.random.key(0)), renamed, path)

    wider = dataclasses.replace(CFG, head=dataclasses.replace(CFG.head, ffn_dim=64))
    with pytest.raises(ValueError, match=r"trained.msgpack: parameter .* has shape"):
        T.train_and_evaluate(wider, tmp_path / "run", data=str(tmp_path), init_from=path)

    # Partial load: a source with an extra array, one missing, one of another shape and one
    # of another dtype.
    src = jax.tree.map(np.asarray, trained)
    flat = {jax.tree_util.keystr(p): p for p, _ in jax.tree_util.tree_flatten_with_path(src)[0]}
    missing, halved, reshaped = sorted(flat)[0], sorted(flat)[1], sorted(flat)[-1]
    holder = _get(src, flat[halved])
    holder[flat[halved][-1].key] = holder[flat[halved][-1].key].astype(np.float16)
    head = src["params"]["head"]
    head["lateral_extra"] = {"kernel": np.ones((3, 3), np.float32)}
    del _get(src, flat[missing])[flat[missing][-1].key]
    last = _get(src, flat[reshaped])
    last[flat[reshaped][-1].key] = np.zeros((*np.shape(last[flat[reshaped][-1].key]), 2))
    odd = export_model(src, CFG, tmp_path / "odd.msgpack")
    with pytest.raises(ValueError, match=r"odd.msgpack: parameter .* is missing"):
        T.with_pretrained(state, CFG, odd)
    part, report = T._load_pretrained(state, CFG, odd, strict=False)
    assert report["unused"] == ["['params']['head']['lateral_extra']['kernel']"]
    assert [r.split(" ")[0] for r in report["fresh"]] == [missing, halved, reshaped]
    assert report["fresh"][1] == f"{halved} (dtype float16 != float32)"
    got = dict(jax.tree_util.tree_flatten_with_path(part.params)[0])
    fresh = dict(jax.tree_util.tree_flatten_with_path(state.params)[0])
    ref = dict(jax.tree_util.tree_flatten_with_path(trained)[0])
    for path_, leaf in got.items():
        expect = fresh if jax.tree_util.keystr(path_) in (missing, halved, reshaped) else ref
        np.testing.assert_array_equal(np.asarray(leaf), np.asarray(expect[path_]))
    unrelated = jax.tree.map(lambda x: np.zeros((*np.shape(x), 2), np.float32), trained)
    unrelated = export_model(unrelated, CFG, tmp_path / "unrelated.msgpack")
    no_match = r"unrelated.msgpack: no parameter matches the run's model by name, shape and dtype"
    with pytest.raises(ValueError, match=no_match):
        T.with_pretrained(state, CFG, unrelated, strict=False)


def _get(tree, path):
    """The dict holding the leaf at a key path."""
    for k in path[:-1]:
        tree = tree[k.key]
    return tree


def test_shard_batch_keeps_device_arrays_off_the_host(monkeypatch):
    """A simulated batch (jax arrays) is placed device to device; numpy data still works.
    On a CPU host and device share memory, so the round trip is caught at numpy."""

    class NoDeviceToHost:
        def __getattr__(self, name):
            return getattr(np, name)

        @staticmethod
        def asarray(x, *args, **kwargs):
            assert not isinstance(x, jax.Array), "a device array went through the host"
            return np.asarray(x, *args, **kwargs)

    monkeypatch.setattr(T, "np", NoDeviceToHost())
    x = jnp.arange(8.0).reshape(4, 2)
    host = np.arange(6, dtype=np.int32).reshape(2, 3)
    out = T.shard_batch({"sim": x, "disk": host}, T.data_mesh())
    assert out["sim"].sharding.spec == jax.sharding.PartitionSpec("data")
    np.testing.assert_array_equal(out["sim"], x)
    np.testing.assert_array_equal(out["disk"], host)


def test_sweep_resumes_exactly(data, tmp_path):
    """A sweep killed after its step-2 checkpoint (its log cut mid-line) and rerun ends
    bit for bit where the uninterrupted sweep does, with the same log; a workdir holding
    another sweep is refused."""
    import shutil

    from indoorbev_jax import sweep

    t = dataclasses.replace(CFG.train, total_steps=4, log_every=2, checkpoint_every=2,
                            keep_checkpoints=3, warmup_steps=1, augment=False)  # fmt: skip
    cfg = dataclasses.replace(CFG, train=t)
    hypers = stack_hypers(cfg, [1e-3, 3e-3], {"dice": [5.0, 2.0]})
    ref = sweep.run_sweep(cfg, tmp_path / "ref", hypers, data, progress=False)
    ref_log = (tmp_path / "ref" / "sweep.jsonl").read_text()
    assert [json.loads(x)["step"] for x in ref_log.splitlines()] == [2, 4]
    # The kill: the step-4 checkpoint never landed, the last record was half written.
    killed = tmp_path / "killed"
    shutil.copytree(tmp_path / "ref", killed)
    shutil.rmtree(killed / "checkpoints" / "4")
    (killed / "sweep.jsonl").write_text(ref_log.splitlines()[0] + '\n{"step": 4, "los')
    resumed = sweep.run_sweep(cfg, killed, hypers, data, progress=False)
    jax.tree.map(np.testing.assert_array_equal, resumed, ref)
    assert (killed / "sweep.jsonl").read_text() == ref_log
    with pytest.raises(ValueError, match=r"hypers\.json: the workdir holds a sweep of other"):
        sweep.run_sweep(cfg, killed, stack_hypers(cfg, [1e-3, 2e-3], {}), data, progress=False)
    # One member taken out: its parameters and its settings, as train.py would train it; the
    # workdir is only read (a best/ made by the restore marked it a training run).
    listing = sorted(p.name for p in (tmp_path / "ref").iterdir())
    config, params = sweep.load_member(tmp_path / "ref", 1)
    assert sorted(p.name for p in (tmp_path / "ref").iterdir()) == listing
    want = jax.tree.map(lambda x: x[1], T.eval_params(ref))
    jax.tree.map(np.testing.assert_array_equal, params, want)
    assert config.train.learning_rate == 3e-3 and config.loss.dice_weight == 2.0
    # A hypers.json of an older version held the float32 values' full digits; the member's
    # config still gets the values given (it had 0.003000000026077032).
    saved = json.loads((tmp_path / "ref" / "hypers.json").read_text())
    widen = lambda vs: [float(np.float32(v)) for v in vs]  # noqa: E731
    older = {"learning_rate": widen(saved["learning_rate"]),
             "weights": {k: widen(v) for k, v in saved["weights"].items()}}  # fmt: skip
    assert older["learning_rate"][1] == 0.003000000026077032
    (tmp_path / "ref" / "hypers.json").write_text(json.dumps(older))
    config, _ = sweep.load_member(tmp_path / "ref", 1)
    assert config.train.learning_rate == 3e-3 and config.loss.yaw_weight == CFG.loss.yaw_weight
    assert (config.backbone, config.head, config.grid) == (cfg.backbone, cfg.head, cfg.grid)
    for member in (2, -1):  # -1 is not Python's last member: export_model takes any int
        with pytest.raises(ValueError, match=rf"--member {member}: the sweep in .* members 0\.\.1"):
            sweep.load_member(tmp_path / "ref", member)
    (killed / "hypers.json").write_text('{"learning_rate": [1e-3,')
    with pytest.raises(ValueError, match=r"killed/hypers\.json: not valid JSON"):
        sweep.load_member(killed, 0)
    import importlib.util

    path = Path(__file__).resolve().parents[1] / "experiments" / "export_model.py"
    spec = importlib.util.spec_from_file_location("export_model", path)
    export_script = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(export_script)
    out = tmp_path / "member1.msgpack"
    with pytest.raises(SystemExit):  # a sweep member comes from the latest checkpoint
        export_script.main([str(tmp_path / "ref"), "--member", "1", "--which", "best",
                            "--out", str(out)])  # fmt: skip
    export_script.main([str(tmp_path / "ref"), "--member", "1", "--out", str(out)])
    from indoorbev_jax.predict import load_model

    _, exported = load_model(out)
    jax.tree.map(np.testing.assert_array_equal, exported, want)


def test_sweep_logs_the_mean_loss_of_each_window(data, tmp_path, monkeypatch):
    """Each sweep.jsonl record holds, per model, the mean loss of the steps since the last
    record (here step s gives model j the loss (s + 1) * (j + 1))."""
    from indoorbev_jax import sweep

    calls = []

    def fake_step(states, batch, key, hypers):
        calls.append(None)
        return states, {"loss": len(calls) * jnp.arange(1.0, 3.0)}

    monkeypatch.setattr(sweep, "make_sweep_step", lambda c, database=None: fake_step)
    t = dataclasses.replace(CFG.train, total_steps=7, log_every=3, augment=False)
    cfg = dataclasses.replace(CFG, train=t)
    sweep.run_sweep(cfg, tmp_path, stack_hypers(cfg, [1e-3, 2e-3], {}), data, progress=False)
    records = [json.loads(x) for x in (tmp_path / "sweep.jsonl").read_text().splitlines()]
    windows = [[1, 2, 3], [4, 5, 6], [7]]
    assert [(r["step"], r["steps"]) for r in records] == [(3, 3), (6, 3), (7, 1)]
    for record, window in zip(records, windows, strict=True):
        np.testing.assert_allclose(record["loss"], [np.mean(window), 2 * np.mean(window)])
    # The other hosts of a multi-host sweep leave the run's files to process 0.
    monkeypatch.setattr(sweep, "writes_run_files", lambda: False)
    other = tmp_path / "other_host"
    sweep.run_sweep(cfg, other, stack_hypers(cfg, [1e-3, 2e-3], {}), data, progress=False)
    for name in ("config.json", "run.json", "hypers.json", "sweep.jsonl"):
        assert not (other / name).exists(), name


def test_prefetch_finishes_its_dispatched_work_when_the_consumer_stops():
    """Stopped early (an error in the step, say), prefetch lets its worker end and blocks
    on the batches it had dispatched, so that none is left queued at interpreter exit (a
    queued Warp kernel calls back into Python and could hang the exit)."""
    import threading

    made = []

    def source(step):
        time.sleep(0.05)
        made.append(jnp.full((4,), step))
        return made[-1]

    before = set(threading.enumerate())
    steps = sources.prefetch(source, 0, 100, size=2)
    assert [next(steps)[0] for _ in range(3)] == [0, 1, 2]
    time.sleep(0.3)  # the worker fills the queue and waits to put the next batch
    steps.close()
    assert set(threading.enumerate()) <= before  # the worker has ended
    assert 3 <= len(made) < 100  # it stopped early ...
    for x in made:  # ... and every batch it made is complete
        assert x.is_ready()


def test_train_step_lowers_to_plain_xla_ops(batch, step_fn):
    """One XLA program with no foreign calls (LAPACK, cuSOLVER, host callbacks) on KITTI
    data, so nothing in the step leaves the device or serialises it."""
    state = T.init_state(CFG, jax.random.key(0))
    lowered = step_fn.lower(state, batch, jax.random.key(1), T.Hyper.from_config(CFG))
    assert "custom_call" not in lowered.as_text()


def test_box_targets_are_the_augmented_boxes_rasterised(data):
    """data.mask_targets=box trains on each object's labelled box: after augmentation, the
    boxes as moved, rasterised afresh (the warped source rasters differ cell by cell)."""
    from indoorbev_jax.augment import augment_batch
    from indoorbev_jax.data.rasterize import rasterize_boxes

    config = with_overrides(CFG, ["data.mask_targets=box"])
    batch = sources.box_targets(next(KittiDataset(data, "train", config).batches(2)), config.grid)
    key = jax.random.key(3)
    out = T.training_batch(config, batch, key)
    t = out.targets
    boxes = jnp.concatenate([t.pos[..., :2], t.dims[..., :2], t.yaw[..., None]], -1)
    ids, masks = jax.vmap(rasterize_boxes, in_axes=(0, 0, None))(boxes, t.valid, config.grid)
    np.testing.assert_array_equal(t.masks, masks)
    np.testing.assert_array_equal(t.instance_ids, ids)
    warped = augment_batch(key, batch, config.grid, config.augment)  # what was trained before
    assert (np.asarray(warped.targets.masks) != np.asarray(masks)).any()


def test_an_empty_object_database_is_named(data):
    batch = next(KittiDataset(data, "train", CFG).batches(2))
    empty = batch.replace(targets=batch.targets.replace(valid=batch.targets.valid & False))
    with pytest.raises(ValueError, match="augment.gt_sampling: the first 2 training batches"):
        sources.gt_database(lambda i: empty, 2, CFG.grid)


def test_sweep_window_means_leave_out_skipped_steps(data, tmp_path, monkeypatch):
    """A skipped (non-finite) step blanked its member's whole window; the mean is now that
    of the finite steps, and null only when none was finite."""
    from indoorbev_jax import sweep

    calls = []

    def fake_step(states, batch, key, hypers):
        calls.append(None)
        s = len(calls)
        loss = jnp.array([float(s), np.nan if s == 2 else 10.0 * s, np.nan])
        return states, {"loss": loss}

    monkeypatch.setattr(sweep, "make_sweep_step", lambda c, database=None: fake_step)
    t = dataclasses.replace(CFG.train, total_steps=3, log_every=3, augment=False)
    cfg = dataclasses.replace(CFG, train=t)
    sweep.run_sweep(cfg, tmp_path, stack_hypers(cfg, [1e-3, 2e-3, 3e-3], {}), data, progress=False)
    (record,) = [json.loads(x) for x in (tmp_path / "sweep.jsonl").read_text().splitlines()]
    assert record["loss"] == [2.0, 20.0, None]  # (1+2+3)/3, (10+30)/2, no finite step


def test_train_log_means_leave_out_skipped_steps():
    window = {"loss": np.array([1.0, np.nan, 3.0, np.inf]), "skipped_steps": np.array([0, 1, 1, 1])}
    assert T._scalars(window) == {"loss": 2.0, "skipped_steps": 0.75}
    assert math.isnan(T._scalars({"loss": np.array([np.nan, np.nan])})["loss"])


@pytest.mark.parametrize("values, flag", [
    (([1e-3, float("nan")], {}), r"--learning-rates: value 2 is nan"),
    (([-1e-3, 1e-3], {}), r"--learning-rates: value 1 is -0\.001"),
    (([1e-3, 1e-3], {"dice": [5.0, float("inf")]}), r"--dice-weights: value 2 is inf"),
])  # fmt: skip
def test_sweep_refuses_values_the_config_would(values, flag):
    with pytest.raises(ValueError, match=f"{flag}; expected finite and >= 0"):
        stack_hypers(CFG, *values)


def test_sweep_takes_zeros_as_the_config_does():
    """An ablation sweeps a loss weight down to 0, which LossConfig allows (>= 0), as it
    allows a learning rate of 0; weights not given are the config's for every member."""
    dataclasses.replace(CFG.loss, dice_weight=0.0)  # the config's rule: 0 is a weight
    hypers = stack_hypers(CFG, [0.0, 1e-3], {"dice": [0.0, 1.0]})
    np.testing.assert_array_equal(hypers.learning_rate, np.float32([0.0, 1e-3]))
    np.testing.assert_array_equal(hypers.weights["dice"], [0.0, 1.0])
    np.testing.assert_array_equal(hypers.weights["cls"], np.float32([CFG.loss.cls_weight] * 2))


def test_sweep_weight_lists_need_one_value_per_learning_rate():
    """Each --NAME-weights list gives one value per model: a shorter or longer list is named
    (a [1] weight against [2] learning rates failed later inside the vmapped step)."""
    for given in ([1.0], [1.0, 2.0, 3.0]):
        message = rf"--dice-weights: expected 2 values, got {len(given)}"
        with pytest.raises(ValueError, match=message):
            stack_hypers(CFG, [1e-3, 2e-3], {"dice": given})


def test_same_settings_compares_the_weight_names_too():
    """A resumed sweep must have the same learning rates and the same named weights: equal
    values under another weight's name are other settings."""
    from indoorbev_jax.sweep import hypers_to_json, same_settings

    saved = hypers_to_json(stack_hypers(CFG, [1e-3, 2e-3], {"dice": [1.0, 2.0]}))
    assert same_settings(saved, json.loads(json.dumps(saved)))
    for name in ("dice", "cls"):
        renamed = json.loads(json.dumps(saved))
        renamed["weights"]["other"] = renamed["weights"].pop(name)
        assert not same_settings(saved, renamed) and not same_settings(renamed, saved)
    one = {"learning_rate": [1e-3], "weights": {"dice": [1.0]}}
    assert not same_settings(one, {"learning_rate": [1e-3], "weights": {"focal": [1.0]}})


def test_a_malformed_hypers_json_is_named(tmp_path):
    """Exporting a sweep member read hypers.json unchecked: a KeyError, or an IndexError
    after the checkpoint was read, for a list one member short."""
    from indoorbev_jax import sweep
    from indoorbev_jax.sweep import hypers_to_json

    settings = CFG.to_dict()
    settings["head"]["bogus"] = 1
    (tmp_path / "config.json").write_text(json.dumps(settings))
    (tmp_path / "hypers.json").write_text("{}")
    with pytest.raises(
        ValueError, match=r"config\.json: unknown config field\(s\) \['head\.bogus'\]$"
    ):
        sweep.load_member(tmp_path, 0)  # the config, named as load_params names it
    (tmp_path / "config.json").write_text(CFG.to_json())
    good = hypers_to_json(stack_hypers(CFG, [1e-3, 2e-3], {"dice": [1.0, 2.0]}))
    path = tmp_path / "hypers.json"
    cases = [
        ({"weights": good["weights"]}, "has no field(s) ['learning_rate']"),
        ({**good, "weights": [1.0]}, "'weights' is [1.0], expected an object of lists"),
        ({**good, "learning_rate": []}, "'learning_rate' is [], expected K > 0 numbers"),
        ({**good, "weights": {**good["weights"], "dice": [1.0]}},
         "'weights.dice' is [1.0], expected 2 numbers"),
        ({**good, "weights": {**good["weights"], "dice": [1.0, "2"]}},
         "'weights.dice' is [1.0, '2'], expected 2 numbers"),
        ({**good, "weights": {**good["weights"], "shape": [1.0, 2.0]}},
         "no such loss weight(s) ['shape']"),
    ]  # fmt: skip
    for settings, message in cases:
        path.write_text(json.dumps(settings))
        with pytest.raises(ValueError, match=f"^{re.escape(f'{path}: {message}')}$"):
            sweep.load_member(tmp_path, 0)
    path.write_text(json.dumps(good))  # well formed: on to the missing checkpoints
    with pytest.raises(FileNotFoundError, match="no checkpoint found"):
        sweep.load_member(tmp_path, 1)


def test_train_and_sweep_refuse_each_others_workdir(data, tmp_path):
    """With the same config and data the resume checks passed, and the first checkpoint
    save deleted the other run's checkpoints as 'unreadable'."""
    from indoorbev_jax import sweep

    swept, trained = tmp_path / "sweep", tmp_path / "train"
    swept.mkdir()
    (swept / "hypers.json").write_text("{}\n")
    with pytest.raises(ValueError, match=r"sweep: holds a sweep \(it has hypers\.json\); train in"):
        T.train_and_evaluate(CFG, swept, data=str(data), progress=False)
    trained.mkdir()
    (trained / "run.json").write_text(json.dumps(rundir.run_record(None)) + "\n")
    hypers = stack_hypers(CFG, [1e-3], {})
    with pytest.raises(ValueError, match=r"holds a training run \(run\.json says 'train'\); sweep"):
        sweep.run_sweep(CFG, trained, hypers, None, progress=False)
    # A workdir from before run.json named its kind: either file of a training run marks it.
    for marker in ("metrics.jsonl", "best"):
        old = tmp_path / f"old_{marker}"
        old.mkdir()
        (old / marker).mkdir() if marker == "best" else (old / marker).write_text("")
        with pytest.raises(ValueError, match=rf"holds a training run \(it has {marker}\); sweep"):
            sweep.run_sweep(CFG, old, hypers, None, progress=False)


def test_a_checkpoint_of_another_layout_is_refused_not_deleted(tmp_path):
    """A sweep's K stacked states read as 'unreadable' by a training run, which then
    deleted them; now the restore names the step and leaves it."""
    one = T.TrainState(
        step=jnp.int32(0), params={"w": jnp.arange(4.0)}, opt_state=(), skipped=jnp.int32(0)
    )
    stacked = jax.tree.map(lambda x: jnp.stack([x, x]), one)
    ckpt = rundir.Checkpoints(tmp_path, keep=3, metric=None)
    ckpt.save(stacked, 2)
    ckpt.close()
    ckpt = rundir.Checkpoints(tmp_path, keep=3, metric=None)
    with pytest.raises(ValueError, match=r"checkpoints/2: holds 3 arrays, this run's state has 3"):
        ckpt.restore(one)
    assert ckpt.latest.all_steps() == [2] and int(ckpt.restore(stacked).step[0]) == 0
    ckpt.close()


def test_each_process_trains_on_its_rows_of_the_global_batch():
    batch = {"points": np.arange(8 * 3).reshape(8, 3), "ids": np.arange(8)}
    parts = [T.process_rows(batch, i, 4) for i in range(4)]
    np.testing.assert_array_equal(np.concatenate([p["ids"] for p in parts]), np.arange(8))
    assert T.process_rows(batch) is batch  # one process: the whole batch
    with pytest.raises(ValueError, match="train.batch_size=8 does not split over 3 processes"):
        T.process_rows(batch, 0, 3)


def test_load_params_refuses_a_sweep_workdir_and_leaves_it_resumable(tmp_path):
    """load_params (predict, export, --init-from) made best/ in a sweep's workdir, which
    then counted as a training run's and refused every resume of the sweep."""
    (tmp_path / "config.json").write_text(CFG.to_json())
    (tmp_path / "run.json").write_text(json.dumps(rundir.run_record(None, "sweep")) + "\n")
    with pytest.raises(ValueError, match=r"a sweep's workdir: its checkpoints hold K stacked"):
        T.load_params(tmp_path)
    assert not (tmp_path / "best").exists()
    (tmp_path / "best").mkdir()  # as those versions left it: run.json's kind decides
    rundir.check_run_kind(tmp_path, "sweep")


def test_load_params_names_what_is_wrong_and_leaves_the_folder_alone(tmp_path):
    """A typo in ``which`` loaded the latest checkpoint; a folder with only config.json got
    an empty checkpoints/; a foreign config.json's error did not name the file; an exported
    model file was "not a run directory ... expected ... a .msgpack"."""
    with pytest.raises(ValueError, match=r"which: expected 'best' or 'latest', got 'bset'"):
        T.load_params(tmp_path, which="bset")
    (tmp_path / "config.json").write_text(CFG.to_json())
    with pytest.raises(FileNotFoundError, match="no checkpoint found"):
        T.load_params(tmp_path)
    assert sorted(p.name for p in tmp_path.iterdir()) == ["config.json"]
    (tmp_path / "config.json").write_text('{"lr": 0.1}')
    with pytest.raises(ValueError, match=r"config\.json: unknown config field\(s\) \['lr'\]"):
        T.load_params(tmp_path)
    (tmp_path / "m.msgpack").write_bytes(b"x")
    with pytest.raises(ValueError, match=r"m\.msgpack: a file, not a run directory; .*load_model"):
        T.load_params(tmp_path / "m.msgpack")


def test_a_sweep_resumes_after_val_txt_changes(data, tmp_path):
    """A sweep reads train.txt only: a changed val.txt refused its resume, with advice
    (train in another workdir, --init-from) a sweep cannot follow."""
    import shutil

    folder = Path(shutil.copytree(data, tmp_path / "data")).resolve()
    record = rundir.run_record(str(folder), "sweep")
    assert record["kind"] == "sweep" and list(record["splits"]) == ["train.txt"]
    workdir = tmp_path / "sweep"
    (workdir / "checkpoints" / "3").mkdir(parents=True)  # as if step 3 were saved
    (workdir / "config.json").write_text(CFG.to_json())
    (workdir / "run.json").write_text(json.dumps(record) + "\n")
    (folder / "val.txt").write_text("000000\n")
    rundir.check_resume(workdir / "config.json", workdir / "run.json", CFG, str(folder), "sweep")
    (folder / "train.txt").write_text("000001\n")
    with pytest.raises(ValueError, match=r"train\.txt changed .* or sweep in another workdir$"):
        rundir.check_resume(
            workdir / "config.json", workdir / "run.json", CFG, str(folder), "sweep"
        )


def test_a_malformed_run_json_is_named_not_taken_for_a_sweep(tmp_path):
    (tmp_path / "config.json").write_text(CFG.to_json())
    (tmp_path / "run.json").write_text('{"kind": "tr')  # cut off
    for call in (lambda: T.load_params(tmp_path), lambda: rundir.check_run_kind(tmp_path, "train")):
        with pytest.raises(ValueError, match=r"run\.json: not valid JSON"):
            call()
    # JSON, but not the object it must be: AttributeError and KeyError tracebacks before.
    (tmp_path / "run.json").write_text("[]")
    with pytest.raises(ValueError, match=r"run\.json: expected a JSON object, got list$"):
        T.load_params(tmp_path)
    (tmp_path / "run.json").write_text('{"kind": "train"}')
    with pytest.raises(ValueError, match=r"run\.json: has no field\(s\) \['data'\]$"):
        rundir.check_resume(tmp_path / "config.json", tmp_path / "run.json", CFG, None)


def test_resume_names_a_bad_config_json_and_needs_one_beside_checkpoints(tmp_path):
    """A resume's config.json errors named the field but not the file; a workdir whose
    config.json was deleted resumed its checkpoints with whatever config was given, and
    recorded that as theirs."""
    config_path, run_path = tmp_path / "config.json", tmp_path / "run.json"
    rundir.check_resume(config_path, run_path, CFG, None)  # nothing there: a fresh run
    (tmp_path / "checkpoints" / "3").mkdir(parents=True)  # as if step 3 were saved
    with pytest.raises(ValueError, match=r"holds checkpoints but no config\.json, so what "):
        rundir.check_resume(config_path, run_path, CFG, None)
    settings = CFG.to_dict()
    del settings["train"]["learning_rate"]
    config_path.write_text(json.dumps(settings))
    expected = f"{config_path}: missing config field(s) ['train.learning_rate']"
    with pytest.raises(ValueError, match=f"^{re.escape(expected)}$"):
        rundir.check_resume(config_path, run_path, CFG, None)


def test_train_and_sweep_refuse_checkpoints_without_config_json(tmp_path):
    """The refusal at the start of each kind of run, before anything is written."""
    from indoorbev_jax.sweep import run_sweep

    (tmp_path / "checkpoints" / "3").mkdir(parents=True)  # as if step 3 were saved
    hypers = stack_hypers(CFG, [1e-3], {})
    for start in (
        lambda: T.train_and_evaluate(CFG, tmp_path),
        lambda: run_sweep(CFG, tmp_path, hypers),
    ):
        with pytest.raises(ValueError, match=r"holds checkpoints but no config\.json"):
            start()
        assert sorted(p.name for p in tmp_path.iterdir()) == [".lock", "checkpoints"]  # its lock


def test_an_unreadable_or_foreign_best_checkpoint(tmp_path, caplog, monkeypatch):
    """An emptied best/<step> (a kill during its save) stopped export and predict with
    orbax's KeyError: the latest readable checkpoint is read instead, said (load_run says
    which it read, as export_model.py prints). A best/ of another layout (config.json
    edited) raised orbax's shape error, naming no folder."""
    monkeypatch.setattr(T, "init_state", lambda config, key: _scalar_state(0))
    (tmp_path / "config.json").write_text(CFG.to_json())
    ckpt = rundir.Checkpoints(tmp_path, keep=2)
    ckpt.save(_scalar_state(3))
    ckpt.save_best(_scalar_state(2), {"pq": 0.5})
    ckpt.close()
    assert float(T.load_params(tmp_path)[1]["w"]) == 2.0  # best/ by default
    assert T.load_run(tmp_path)[2] == "best, step 2"
    assert T.load_run(tmp_path, "latest")[2] == "latest, step 3"
    shutil.copytree(tmp_path / "best" / "2", tmp_path / "best_2")
    shutil.rmtree(tmp_path / "best" / "2")
    (tmp_path / "best" / "2").mkdir()
    with caplog.at_level("WARNING"):
        _, params, source = T.load_run(tmp_path)
    assert float(params["w"]) == 3.0 and source == "latest, step 3 (best/ unreadable)"
    assert f"{tmp_path / 'best' / '2'} is unreadable (" in caplog.text
    assert f"{tmp_path / 'best'}: read the latest readable checkpoint instead (step 3)" in (
        caplog.text
    )
    # No other checkpoint: said so, not "read the latest" and then "no checkpoint found".
    shutil.move(tmp_path / "checkpoints", tmp_path / "checkpoints_kept")
    (tmp_path / "checkpoints").mkdir()
    caplog.clear()
    with pytest.raises(FileNotFoundError, match=r": no checkpoint found \(.*best unreadable\)$"):
        T.load_params(tmp_path)
    assert "read the latest" not in caplog.text
    shutil.rmtree(tmp_path / "checkpoints")
    shutil.move(tmp_path / "checkpoints_kept", tmp_path / "checkpoints")
    shutil.rmtree(tmp_path / "best" / "2")
    shutil.copytree(tmp_path / "best_2", tmp_path / "best" / "2")
    wide = T.TrainState(step=jnp.int32(0), params={"w": jnp.zeros(3)}, opt_state=(),
                        skipped=jnp.int32(0))  # fmt: skip
    monkeypatch.setattr(T, "init_state", lambda config, key: wide)
    with pytest.raises(ValueError, match=f"^{re.escape(str(tmp_path / 'best' / '2'))}: holds 3"):
        T.load_params(tmp_path)


def test_sim_source_draws_step_s_from_fold_in_of_its_key_in_one_compile(monkeypatch):
    """Batch s is ``generate_batch(fold_in(key, s))``, the fold_in inside the jit (it ran
    eagerly before it, a dispatch of its own each step); a new step compiles nothing."""
    import indoorbev_sim

    calls = []

    def fake_generate(key, config, split):  # the simulator's contract, cheap to compile
        calls.append(split)
        return jax.random.uniform(key, (3,))

    monkeypatch.setattr(indoorbev_sim, "generate_batch", fake_generate)
    key = jax.random.key(7)
    source = sources.SimSource(CFG, key, "val")
    got = [np.asarray(source(s)) for s in (0, 3, 3)]
    want = [np.asarray(jax.random.uniform(jax.random.fold_in(key, s), (3,))) for s in (0, 3)]
    np.testing.assert_array_equal(got[0], want[0])
    np.testing.assert_array_equal(got[1], want[1])
    np.testing.assert_array_equal(got[2], want[1])
    assert calls == ["val"] and source._generate._cache_size() == 1


def test_data_generation_and_the_train_step_trace_as_one_jit():
    """DESIGN 1: every stage is a pure function with static shapes, "so the whole train
    step, data generation included, can sit under one jax.jit". Lowered (traced, not
    compiled: seconds, not the minute a compile takes), with the simulator's Warp cast the
    only call out of XLA: no Python host callback in the step."""
    from indoorbev_sim import generate_batch

    cfg = Config.tiny()
    state = jax.eval_shape(lambda key: T.init_state(cfg, key), jax.random.key(0))
    step, hyper = T.make_train_step(cfg), T.Hyper.from_config(cfg)

    def whole(state, key, hyper):
        batch = generate_batch(jax.random.fold_in(key, state.step), cfg)
        return step(state, batch, key, hyper)

    text = jax.jit(whole).lower(state, jax.random.key(1), hyper).as_text()
    calls = set(re.findall(r"custom_call @(\w+)", text))
    assert all(name.startswith("build_and_cast") for name in calls), calls  # Warp, if any
    assert "callback" not in text
    new_state, _ = jax.eval_shape(whole, state, jax.random.key(1), hyper)
    assert jax.tree.structure(new_state) == jax.tree.structure(state)
