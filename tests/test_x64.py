"""Researchers often turn ``jax_enable_x64`` on. Parameters, simulated frames and
augmentations must not change with it: float64 parameters recompiled the train step and made
a run's own checkpoints unrestorable, and float64 draws gave another held-out test set for
the same key."""

import jax
import numpy as np
from indoorbev_sim.generate import draw_frames, simulate

from indoorbev_jax.config import Config
from indoorbev_jax.train import init_state

CFG = Config.tiny()


def _same(a, b):
    """Equal leaves of equal dtypes."""
    for x, y in zip(jax.tree.leaves(a), jax.tree.leaves(b), strict=True):
        assert np.asarray(x).dtype == np.asarray(y).dtype
        np.testing.assert_array_equal(np.asarray(x), np.asarray(y))


def test_parameters_and_optimizer_state_stay_float32_under_x64():
    """Three parameters (the encoder's empty-cell embedding, the decoder's query embedding,
    the Swin relative position tables) were float64 under x64: Adam's moments followed."""
    with jax.enable_x64(True):
        state = jax.eval_shape(lambda k: init_state(CFG, k), jax.random.key(3))
    floats = {str(x.dtype) for x in jax.tree.leaves(state) if x.dtype.kind == "f"}
    assert floats == {"float32"}


def test_scene_draws_are_the_same_under_x64():
    """The same key draws the same scenes (``draw_frames``: what ``generate_batch``
    simulates), in float32, whether x64 is on or not (test_augment.py checks augmentation)."""
    key = jax.random.key(11)
    drawn = jax.jit(draw_frames, static_argnums=(1, 2, 3))(key, CFG, "test", 2)
    with jax.enable_x64(True):
        drawn64 = jax.jit(draw_frames, static_argnums=(1, 2, 3))(key, CFG, "test", 2)
    _same(drawn[:3], drawn64[:3])  # scene, time, frame index (the last is the noise key)
    # A float64 time given to simulate under x64 (FrameInfo.time stayed float64).
    scene, time, index, noise = drawn
    with jax.enable_x64(True):
        time64 = jax.numpy.asarray(np.asarray(time, np.float64))
        shapes = jax.eval_shape(lambda *a: simulate(a[0], CFG, *a[1:]), noise, scene, time64, index)
    floats = {str(x.dtype) for x in jax.tree.leaves(shapes) if x.dtype.kind == "f"}
    assert floats == {"float32"}
