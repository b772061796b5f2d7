"""The simulator without warp-lang: the default caster falls back to the pure-JAX one."""

import dataclasses
import subprocess
import sys
import textwrap

import jax
import numpy as np
from indoorbev_sim import generate

from indoorbev_jax.config import Config

CFG = Config.tiny()
CFG = dataclasses.replace(CFG, sim=dataclasses.replace(CFG.sim, range_noise=0.0, dropout=0.0))

# Runs in a fresh interpreter in which `import warp` fails, as on a machine without it.
CHILD = textwrap.dedent(
    """
    import dataclasses, sys, warnings
    sys.modules["warp"] = None  # any import of warp now raises ImportError
    import jax, numpy as np
    from indoorbev_jax.config import Config
    from indoorbev_sim import generate, lidar
    cfg = Config.tiny()
    cfg = dataclasses.replace(cfg, sim=dataclasses.replace(cfg.sim, range_noise=0.0, dropout=0.0))
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        batch, info = generate.jitted_generate(cfg, "train", 2)(jax.random.key(3))
    assert lidar.default_method() == "jax"
    warned = [w for w in caught if "warp-lang is not installed" in str(w.message)]
    assert warned, caught
    assert warned[0].filename == "<string>", warned[0].filename  # the caller's line, this one
    t = batch.targets
    np.savez(sys.argv[1], points=batch.points, valid=batch.point_valid, masks=t.masks,
             classes=t.classes, dims=t.dims, pos=t.pos, num_points=info.num_points)
    """
)


def test_generate_batch_without_warp_matches_the_warp_caster(tmp_path):
    """Frames made where warp cannot be imported equal those of the Warp caster: the same
    objects and masks, and the same points (a ray may flip only at grazing incidence)."""
    out = tmp_path / "no_warp.npz"
    run = subprocess.run(
        [sys.executable, "-c", CHILD, str(out)], capture_output=True, text=True, timeout=600
    )
    assert run.returncode == 0, run.stderr[-3000:]
    got = np.load(out)
    batch, info = generate.jitted_generate(CFG, "train", 2)(jax.random.key(3))
    for name, want in (
        ("masks", batch.targets.masks),
        ("classes", batch.targets.classes),
        ("dims", batch.targets.dims),
        ("pos", batch.targets.pos),
    ):
        np.testing.assert_array_equal(got[name], np.asarray(want), err_msg=name)
    valid = np.asarray(batch.point_valid)
    assert valid.sum() > 1000
    np.testing.assert_array_equal(got["valid"], valid)
    close = np.all(np.abs(got["points"] - np.asarray(batch.points)) <= 1e-4, axis=-1)
    assert close[valid].mean() >= 0.999, close[valid].mean()
    assert np.abs(got["num_points"] - np.asarray(info.num_points)).sum() <= 2
