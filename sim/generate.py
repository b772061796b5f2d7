"""Labelled lidar frames from procedural scenes, batched and jittable end to end.

    batch = indoorbev_sim.generate_batch(key, config)             # indoorbev_jax.types.Batch
    batch, info = generate_batch_with_info(key, config, split="test")
    seq, info = generate_sequences(key, config, num_scenes=2)      # leading [S, T] axes

One call samples B scenes (``scenes.sample_scene``), poses them at the frame time, casts the
scan pattern's rays from the lidar riding its robot (``sensor.scan``: Warp kernels over the
batched MJX model/data; a lidar tilted by ``sim.sensor_rpy``, or per scene within
``sim.sensor_tilt_jitter`` of it, delivers its cloud levelled, ``mount_rotation``), adds
noise and dropout, and derives labels (``labels``): padded targets with true-shape footprint
masks and instance ids. ``FrameInfo`` carries what the ``Batch`` has no room for:
per-object point counts, visibility and KITTI occlusion level, which object each point
belongs to, the plan and the sensor pose.

``reference.reference_frame`` is the plain sequential pipeline (MuJoCo ``mj_multiRay`` +
numpy, one frame at a time) on the same scene: the tests' oracle and the benchmark's baseline.
"""

from __future__ import annotations

import dataclasses
import functools
import math

import jax
import jax.numpy as jnp
from flax import struct
from indoorbev_sim import labels as labels_mod
from indoorbev_sim import scenes as scenes_mod

from indoorbev_jax.checks import check_whole
from indoorbev_jax.config import Config, SimConfig
from indoorbev_jax.data.rasterize import instance_ids_from_masks
from indoorbev_jax.geometry import in_workspace
from indoorbev_jax.types import Batch, Targets, float32_defaults


@struct.dataclass
class FrameInfo:
    """Per-frame extras beside the ``Batch`` (leading [B], or [S, T] for sequences).

    Attributes:
      num_points: int32 [B, M], valid returns on each target object (0 for padding).
      visibility: float32 [B, M], fraction of the object's primitives the sensor sees.
      occlusion: int32 [B, M], KITTI occlusion level 0..3 (0 for padding).
      slot: int32 [B, M], template slot of each target (-1 for padding).
      variant: int32 [B, M], variant index of each target's class (-1 for padding).
      point_object: int32 [B, N], target index of the object each point hit (-1: background
        or an object that is not a target).
      plan: int32 [B], floor-plan id (``layouts.plan_name``).
      sensor_origin: float32 [B, 3] world position; sensor_yaw: float32 [B] (the level
        frame's; the lidar's tilt in it is ``scene.sensor_rpy``).
      time: float32 [B], seconds since the start of the sequence.
      frame_index: int32 [B], scan pattern frame.
      scene: the ``scenes.Scene`` [B] the frame shows, its poses at t = 0
        (``scenes.object_poses(scene, time)`` gives the frame's: moving objects differ).
    """

    num_points: jax.Array
    visibility: jax.Array
    occlusion: jax.Array
    slot: jax.Array
    variant: jax.Array
    point_object: jax.Array
    plan: jax.Array
    sensor_origin: jax.Array
    sensor_yaw: jax.Array
    time: jax.Array
    frame_index: jax.Array
    scene: scenes_mod.Scene


def make_pattern(sim: SimConfig):
    """The scan pattern named by ``sim.pattern`` with ``sim.num_rays`` rays per frame."""
    from indoorbev_sim import patterns

    n = sim.num_rays
    if sim.pattern == "mid360":
        return patterns.Mid360Pattern(points_per_second=n * 10)
    if sim.pattern == "vlp16":
        return dataclasses.replace(patterns.SpinningPattern.vlp16(), columns=n // 16)
    if sim.pattern == "os128":
        return dataclasses.replace(patterns.SpinningPattern.os128(), columns=n // 128)
    return patterns.GridPattern(
        azimuth_steps=n // 32, elevation_steps=32, elevation_min_deg=-7.0, elevation_max_deg=52.0
    )


def front_order(keep: jax.Array) -> jax.Array:
    """``jnp.argsort(~keep, axis=-1, stable=True)``: kept indices first, each group in index order.

    Built from one cumulative sum and a scatter: XLA:CPU's sorts cost several times more.

    Args:
      keep: bool [..., R].

    Returns:
      int32 [..., R], a permutation of 0..R-1 along the last axis.
    """
    r = keep.shape[-1]
    index = jnp.arange(r, dtype=jnp.int32)
    kept = jnp.cumsum(keep, axis=-1, dtype=jnp.int32)  # kept up to and including each index
    # A kept index goes after the kept ones before it; a dropped one after all kept ones and
    # the dropped ones before it (index - kept of those).
    dest = jnp.where(keep, kept - 1, kept[..., -1:] + index - kept)

    def scatter(d):
        return jnp.zeros(r, jnp.int32).at[d].set(index, unique_indices=True)

    flat = dest.reshape(math.prod(keep.shape[:-1]), r)  # also for R = 0
    return jax.vmap(scatter)(flat).reshape(keep.shape)


def spread_positions(count: jax.Array, n: int) -> jax.Array:
    """``floor(k * count / n)`` for k in 0..n-1 where ``count > n``, else k: which of ``count``
    kept returns fill ``n`` slots, evenly spread over the scan order (the rule of
    ``indoorbev_jax.data.dataset.pad_points``).

    Computed as ``k * (count // n) + floor(k * (count % n) / n)``: exact in int32 up to
    n = 46340 (the second product stays under n^2); beyond that the second term is float32,
    which may put a slot one return off.

    Args:
      count: int [...] kept returns per frame.
      n: slots (static).

    Returns:
      int32 [..., n].
    """
    count = count.astype(jnp.int32)[..., None]
    k = jnp.arange(n, dtype=jnp.int32)
    rest = count % n
    if n * n < 2**31:
        part = k * rest // n
    else:
        part = jnp.floor(k * (rest.astype(jnp.float32) / n)).astype(jnp.int32)
    pos = jnp.minimum(k * (count // n) + part, count - 1)
    return jnp.where(count > n, pos, k)


def yaw_matrix(yaw: jax.Array) -> jax.Array:
    c, s, z, o = jnp.cos(yaw), jnp.sin(yaw), jnp.zeros_like(yaw), jnp.ones_like(yaw)
    return jnp.stack(
        [jnp.stack([c, -s, z], -1), jnp.stack([s, c, z], -1), jnp.stack([z, z, o], -1)], -2
    )  # [..., 3, 3]


def mount_rotation(sim: SimConfig, scene: scenes_mod.Scene) -> jax.Array | None:
    """float32, lidar-frame vectors to the level frame (``indoorbev_jax.mount.LidarMount``'s
    convention): [..., 3, 3] for each scene's ``sensor_rpy`` with ``sim.sensor_tilt_jitter``,
    [3, 3] for the one tilt ``sim.sensor_rpy``; None when level."""
    from indoorbev_jax.mount import LidarMount, rpy_matrix

    if sim.sensor_tilt_jitter:
        return rpy_matrix(jnp.asarray(scene.sensor_rpy, jnp.float32), jnp)
    mount = LidarMount(*sim.sensor_rpy)  # one matrix, as a fixed tilt's exports were made with
    return jnp.asarray(mount.rotation(), jnp.float32) if mount.rotated else None


@float32_defaults
def simulate(
    key: jax.Array, config: Config, scene: scenes_mod.Scene, time: jax.Array, frame_index
) -> tuple[Batch, FrameInfo]:
    """Ray-casts and labels B posed scenes.

    Args:
      key: PRNG key for sensor noise and dropout.
      config: run configuration (static).
      scene: ``Scene`` batched over B.
      time: float [B], seconds since the start of each scene's sequence.
      frame_index: int scalar, scan pattern frame (shared by the B scenes).

    Returns:
      (``Batch``, ``FrameInfo``) with leading axis B.
    """
    from indoorbev_sim import lidar, sensor

    time = jnp.asarray(time, jnp.float32)  # a float64 time under x64: FrameInfo.time float32
    sim = config.sim
    tpl = scenes_mod.template_for(config)
    m, n = config.data.max_objects, config.data.max_points
    size, xpos, xmat, refl = jax.vmap(functools.partial(scenes_mod.geom_state, tpl))(scene, time)
    model = scenes_mod.geom_model(tpl, size)  # geom_size [B, G, 3]: one model per scene
    data = scenes_mod.GeomData(geom_xpos=xpos, geom_xmat=xmat)
    origin, heading = jax.vmap(scenes_mod.sensor_pose)(scene, time)  # [B, 3], [B]
    tilt = mount_rotation(sim, scene)  # [3, 3] or [B, 3, 3]
    rot = yaw_matrix(heading) if tilt is None else yaw_matrix(heading) @ tilt
    pose = sensor.Pose(origin, rot)
    directions = make_pattern(sim).frame(frame_index).directions  # [R, 3] sensor frame
    sensor_cfg = sensor.SensorConfig(
        min_range=sim.min_range, max_range=sim.max_range, range_noise_std=sim.range_noise,
        dropout_prob=sim.dropout,
    )  # fmt: skip
    scan = sensor.scan(model, data, pose, directions, key, sensor_cfg, reflectivity=refl)
    if tilt is not None:  # the cloud levelled, as LidarMount.levelled delivers it
        per_scene = "bij" if tilt.ndim == 3 else "ij"
        xyz = jnp.einsum(f"{per_scene},brj->bri", tilt, scan.points[..., :3])
        scan = scan.replace(points=scan.points.at[..., :3].set(xyz))
    valid = scan.valid & in_workspace(scan.points[..., :3], config.grid)  # [B, R]
    geom_slot = jnp.asarray(tpl.geom_slot)
    point_slot = jnp.where(scan.geom_id >= 0, geom_slot[jnp.maximum(scan.geom_id, 0)], -1)

    # Points: valid returns first, padded to N; of more than N, N spread over the scan order
    # (a spinning pattern then loses density everywhere, not a sector).
    r = valid.shape[1]
    porder = front_order(valid)  # [B, R]
    if r < n:
        psel = jnp.concatenate([porder, jnp.full((porder.shape[0], n - r), r)], 1)
    else:
        psel = jnp.take_along_axis(porder, spread_positions(valid.sum(-1), n), 1)  # [B, N]

    def ptake(x, fill):
        x = jnp.concatenate([x, jnp.full_like(x[:, :1], fill)], 1)
        return jnp.take_along_axis(x, psel.reshape(psel.shape + (1,) * (x.ndim - 2)), 1)

    pvalid = ptake(valid, False)
    # The returns kept, in ray order: labels count an object's points in the delivered cloud,
    # so a cut cloud cannot leave a target with fewer than data.min_points.
    if r < n:  # nothing can be cut
        kept = valid
    else:
        kept = jnp.zeros((valid.shape[0], r + 1), bool)
        kept = jax.vmap(lambda k, i, v: k.at[i].set(v))(kept, psel, pvalid)[:, :r]

    # Visibility: one ray per primitive, aimed at its centre; it sees the primitive only
    # where the sensor could fire it (field of view, min_range).
    target, _ = jax.vmap(labels_mod.visibility_targets)(scene, time)
    to_target = target - origin[:, None]  # [B, S * P, 3]
    vdirs = to_target / jnp.maximum(jnp.linalg.norm(to_target, axis=-1, keepdims=True), 1e-9)
    vdist, vgeom = lidar.cast_rays(model, data, origin, vdirs, sim.max_range)
    in_view = make_pattern(sim).covers(jnp.einsum("brj,bji->bri", vdirs, pose.rot))
    fired = (vgeom >= 0) & in_view & (vdist >= sim.min_range)
    vis_slot = jnp.where(fired, geom_slot[jnp.maximum(vgeom, 0)], -1)

    per_slot = jax.vmap(functools.partial(labels_mod.object_labels, tpl, config=config))(
        scene, time, origin, heading, point_slot, kept, vis_slot
    )  # fields [B, S, ...]

    # Targets: labelled slots first (slot order kept), padded or cut to M.
    s = tpl.num_slots
    order = front_order(per_slot.labelled)  # [B, S]
    if s < m:
        order = jnp.concatenate([order, jnp.full((order.shape[0], m - s), s)], 1)
    sel = order[:, :m]  # [B, M], index s = padding

    def take(x, fill):
        x = jnp.concatenate([x, jnp.full_like(x[:, :1], fill)], 1)  # [B, S + 1, ...]
        return jnp.take_along_axis(x, sel.reshape(sel.shape + (1,) * (x.ndim - 2)), 1)

    tvalid = take(per_slot.labelled, False)
    classes = jnp.where(tvalid, take(per_slot.classes, 0), config.num_classes).astype(jnp.int32)
    masks = take(per_slot.masks, False) & tvalid[..., None, None]
    targets = Targets(
        classes=classes,
        dims=jnp.where(tvalid[..., None], take(per_slot.dims, 0.0), 0.0),
        pos=jnp.where(tvalid[..., None], take(per_slot.pos, 0.0), 0.0),
        yaw=jnp.where(tvalid, take(per_slot.yaw, 0.0), 0.0),
        valid=tvalid,
        masks=masks,
        instance_ids=jax.vmap(instance_ids_from_masks)(masks, tvalid),
    )

    points = jnp.where(pvalid[..., None], ptake(scan.points, 0.0), 0.0)
    # Slot -> target index, to say which target each point belongs to.
    target_of_slot = jnp.full((sel.shape[0], s + 1), -1, jnp.int32)
    target_of_slot = jax.vmap(lambda t, i: t.at[i].set(jnp.arange(m, dtype=jnp.int32)))(
        target_of_slot, sel
    )
    target_of_slot = jnp.where(
        jnp.concatenate([per_slot.labelled, jnp.zeros_like(per_slot.labelled[:, :1])], 1),
        target_of_slot,
        -1,
    )
    pslot = jnp.where(pvalid, ptake(point_slot, -1), -1)
    point_object = jnp.take_along_axis(target_of_slot, jnp.where(pslot >= 0, pslot, s), 1)

    info = FrameInfo(
        num_points=jnp.where(tvalid, take(per_slot.num_points, 0), 0),
        visibility=jnp.where(tvalid, take(per_slot.visibility, 0.0), 0.0),
        occlusion=jnp.where(tvalid, take(per_slot.occlusion, 0), 0),
        slot=jnp.where(tvalid, sel, -1).astype(jnp.int32),
        variant=jnp.where(tvalid, take(scene.variant, -1), -1),
        point_object=point_object,
        plan=scene.room.plan,
        sensor_origin=origin,
        sensor_yaw=heading,
        time=time,
        frame_index=jnp.full(time.shape, frame_index, jnp.int32),
        scene=scene,
    )
    return Batch(points=points, point_valid=pvalid, targets=targets), info


@float32_defaults
def sample_scenes(key: jax.Array, config: Config, num_scenes: int, split="train"):
    """``num_scenes`` scenes (``Scene`` batched over a leading axis).

    ``split`` is "train", "val", "test", or a (possibly traced) bool meaning "test".
    """
    test = scenes_mod.split_flag(split) if isinstance(split, str) else split
    keys = jax.random.split(key, check_whole("num_scenes", num_scenes, 1))
    return jax.vmap(lambda k: scenes_mod.sample_scene(k, config, test))(keys)


@float32_defaults
def generate_batch_with_info(
    key: jax.Array, config: Config, split: str = "train", batch_size: int | None = None
) -> tuple[Batch, FrameInfo]:
    """B independent labelled frames and their ``FrameInfo`` (jittable; config static).

    Args:
      key: PRNG key.
      config: run configuration; B defaults to ``config.train.batch_size``.
      split: "train"/"val" (plans and variants not held out) or "test" (held-out plans).
      batch_size: overrides B.
    """
    scene, time, frame_index, k_noise = draw_frames(key, config, split, batch_size)
    return simulate(k_noise, config, scene, time, frame_index)


@float32_defaults
def draw_frames(key: jax.Array, config: Config, split="train", batch_size: int | None = None):
    """What ``generate_batch_with_info`` simulates for this key, before any ray is cast.

    Returns:
      (scene ``Scene`` [B], time float32 [B], pattern frame index int32 [], noise key).
    """
    # Checked here: 0 failed deep in the ray cast (ZeroDivisionError), -1 in MLIR.
    b = config.train.batch_size if batch_size is None else check_whole("batch_size", batch_size, 1)
    k_scene, k_frame, k_time, k_noise = jax.random.split(key, 4)
    scene = sample_scenes(k_scene, config, b, split)
    span = (config.sim.frames_per_sequence - 1) * config.sim.frame_dt
    time = jax.random.uniform(k_time, (b,), maxval=span)  # anywhere along the sequence
    frame_index = jax.random.randint(k_frame, (), 0, 1 << 20)
    return scene, time, frame_index, k_noise


@float32_defaults
def generate_batch(key: jax.Array, config: Config, split: str = "train") -> Batch:
    """B = ``config.train.batch_size`` labelled frames as the model and loss consume them.

    Jittable end to end (``jax.jit(generate_batch, static_argnums=(1, 2))``): scene
    sampling, ray casting, noise, labels, masks and padded targets, all on the device.
    """
    return generate_batch_with_info(key, config, split)[0]


@float32_defaults
def generate_sequences(
    key: jax.Array, config: Config, num_scenes: int, split: str = "train"
) -> tuple[Batch, FrameInfo]:
    """``num_scenes`` scenes x T = ``sim.frames_per_sequence`` consecutive frames.

    Persons and robots move along their paths, the lidar rides its robot, and frame t uses
    scan pattern frame t, so the non-repetitive pattern keeps filling in.

    Returns:
      (``Batch``, ``FrameInfo``) whose arrays have leading axes [S, T].
    """
    k_scene, k_noise = jax.random.split(key)
    scene = sample_scenes(k_scene, config, num_scenes, split)
    t = config.sim.frames_per_sequence

    def frame(k):
        time = jnp.full((num_scenes,), k * config.sim.frame_dt, jnp.float32)
        return simulate(jax.random.fold_in(k_noise, k), config, scene, time, k)

    out = jax.lax.map(frame, jnp.arange(t))  # [T, S, ...]
    return jax.tree.map(lambda x: jnp.swapaxes(x, 0, 1), out)


@functools.lru_cache(maxsize=8)
def jitted_generate(config: Config, split: str = "train", batch_size: int | None = None):
    """``generate_batch_with_info`` jitted for (config, split, B), cached per process."""
    return jax.jit(lambda key: generate_batch_with_info(key, config, split, batch_size))


@functools.lru_cache(maxsize=8)
def jitted_draw(config: Config, split: str = "train", batch_size: int | None = None):
    """``draw_frames`` jitted for (config, split, B), cached per process."""
    return jax.jit(lambda key: draw_frames(key, config, split, batch_size))


_MOVED_TO_REFERENCE = ("reference_frame", "reference_cast", "reference_footprints", "scene_numpy")


def __getattr__(name: str):
    # The sequential reference moved to ``reference.py`` (2026-12-07); scripts that read it
    # here, as docs/SIMULATOR.md said to, still find it. Imported on first use: it imports us.
    if name in _MOVED_TO_REFERENCE:
        from indoorbev_sim import reference

        return getattr(reference, name)
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
