"""Lidar sensor model: pose, ray casting, range noise, dropout, range limits, intensity.

``scan`` turns a sensor pose and a ``ScanFrame``'s sensor-frame directions into points in the
sensor frame, ``[R, 4]`` = (x, y, z, intensity), plus a validity mask, with static shapes (one
slot per ray; invalid slots are zero). It is jittable and vmappable over scenes/poses/keys.

Intensity model (documented in docs/SIMULATOR.md): ``reflectivity[geom] * cos(incidence) **
incidence_exponent``, in [0, 1]; incidence is the angle between the ray and the surface normal
of the hit primitive. Dropout drops each return independently with probability
``dropout_prob``; range noise is Gaussian with standard deviation ``range_noise_std`` metres
added along the ray. Returns outside [min_range, max_range] (after noise) are invalid.
"""

from __future__ import annotations

import dataclasses
import math

import jax
import jax.numpy as jnp
import numpy as np
from flax import struct

from . import lidar


@struct.dataclass
class Pose:
    """Rigid transform world <- sensor.

    Attributes:
      pos: float32 [3] (or [B, 3]) sensor origin in the world frame.
      rot: float32 [3, 3] (or [B, 3, 3]); columns are the sensor axes in the world frame.
    """

    pos: jax.Array
    rot: jax.Array


def _frame_pose(xpos, xmat, index: int) -> Pose:
    """Pose of frame ``index`` of ``xpos`` [..., n, 3] and ``xmat`` [..., n, 3, 3] (MJX) or
    [..., n, 9] (``mujoco.MjData``)."""
    pos = jnp.asarray(xpos)[..., index, :]
    rot = jnp.asarray(xmat).reshape(pos.shape[:-1] + (-1, 3, 3))[..., index, :, :]
    return Pose(pos.astype(jnp.float32), rot.astype(jnp.float32))


def pose_from_site(data, site_id: int) -> Pose:
    """Sensor pose of a MuJoCo site (``site_xpos``/``site_xmat`` of ``mjx.Data`` or
    ``mujoco.MjData``; batched data gives [B])."""
    return _frame_pose(data.site_xpos, data.site_xmat, site_id)


def pose_from_body(data, body_id: int) -> Pose:
    """Sensor pose of a MuJoCo body frame (``xpos``/``xmat`` of ``mjx.Data`` or
    ``mujoco.MjData``; batched data gives [B])."""
    return _frame_pose(data.xpos, data.xmat, body_id)


@dataclasses.dataclass(frozen=True)
class SensorConfig:
    """Static sensor parameters.

    Attributes:
      min_range: metres; closer returns are invalid (blind zone, MID-360: 0.1 m).
      max_range: metres; farther returns (and misses) are invalid.
      range_noise_std: metres, Gaussian noise along the ray.
      dropout_prob: probability that a return is lost.
      default_reflectivity: reflectivity of geoms with no entry given, in [0, 1].
      incidence_exponent: intensity falls off as cos(incidence) ** this.
    """

    min_range: float = 0.1
    max_range: float = 40.0
    range_noise_std: float = 0.02
    dropout_prob: float = 0.0
    default_reflectivity: float = 0.5
    incidence_exponent: float = 1.0

    def __post_init__(self):
        if not 0.0 <= self.min_range < self.max_range:
            raise ValueError(
                f"SensorConfig.min_range/max_range must satisfy 0 <= min < max, got "
                f"{self.min_range}, {self.max_range}"
            )
        # Written so that NaN fails each test (NaN < 0 is False).
        for name in ("range_noise_std", "incidence_exponent"):
            value = getattr(self, name)
            if not (math.isfinite(value) and value >= 0.0):
                raise ValueError(f"SensorConfig.{name} must be finite and >= 0, got {value}")
        for name in ("dropout_prob", "default_reflectivity"):
            value = getattr(self, name)
            if not 0.0 <= value <= 1.0:
                raise ValueError(f"SensorConfig.{name} must be in [0, 1], got {value}")


@struct.dataclass
class Scan:
    """One scan per scene.

    Attributes:
      points: float32 [R, 4] or [B, R, 4], (x, y, z, intensity) in the sensor frame.
      valid: bool [R] or [B, R].
      geom_id: int32 [R] or [B, R], hit geom (-1 where nothing was hit within max_range).
      distance: float32 [R] or [B, R], noiseless hit distance (-1 on a miss).
    """

    points: jax.Array
    valid: jax.Array
    geom_id: jax.Array
    distance: jax.Array


def scan(
    model,
    data,
    pose: Pose,
    directions: jax.Array,
    key: jax.Array,
    config: SensorConfig = SensorConfig(),
    reflectivity: jax.Array | None = None,
    **cast_kwargs,
) -> Scan:
    """Simulates one lidar scan per scene.

    Args:
      model, data: MJX model/data of one scene or B scenes (as ``lidar.cast_rays``).
      pose: sensor pose world <- sensor, ``pos`` [3] or [B, 3], ``rot`` [3, 3] or [B, 3, 3].
      directions: float [R, 3] ray directions in the sensor frame (e.g.
        ``pattern.frame(k).directions``), shared by all scenes; scaled to unit length (a
        zero or non-finite one is a miss).
      key: ``jax.random`` key, one for all B scenes (each scene and ray draws its own noise).
      config: ``SensorConfig``.
      reflectivity: optional float [G] or [B, G] per-geom reflectivity in [0, 1].
      **cast_kwargs: forwarded to ``lidar.scene_geometry``/``cast_geometry`` (geomgroup,
        bodyexclude, flg_static, skip_unsupported, method, cells_per_edge, capacity,
        cpu_threads).

    Returns:
      ``Scan`` with a leading B axis iff ``data`` or ``pose`` is batched (B poses in one
      unbatched scene scan that scene from each).
    """
    geo_kw = {
        k: cast_kwargs.pop(k)
        for k in ("geomgroup", "flg_static", "bodyexclude", "skip_unsupported")
        if k in cast_kwargs
    }
    geo = lidar.scene_geometry(model, data, **geo_kw)
    nscene, ngeom = geo.pos.shape[:2]
    # Poses given with a batch axis keep it, even a batch of one (as cast_rays does).
    batched = jnp.ndim(data.geom_xpos) == 3 or jnp.ndim(pose.pos) == 2 or jnp.ndim(pose.rot) == 3
    directions = jnp.asarray(directions, jnp.float32)
    if directions.ndim != 2 or directions.shape[-1] != 3:
        raise ValueError(f"directions must be [R, 3] (sensor frame), got {directions.shape}")
    # Ranges, the min-range test and intensity assume unit rays: scale others to length 1
    # (a unit pattern, within rounding, is left bit for bit as it is).
    length = jnp.linalg.norm(directions, axis=-1, keepdims=True)
    directions = jnp.where(jnp.abs(length - 1.0) > 1e-4, directions / length, directions)
    # rot may also be MuJoCo's flat xmat layout, [9] or [B, 9].
    for name, tails in (("pos", ((3,),)), ("rot", ((3, 3), (9,)))):
        shape = tuple(jnp.shape(getattr(pose, name)))
        if not any(shape[-len(t) :] == t and len(shape) <= len(t) + 1 for t in tails):
            note = " (a rotation matrix: pose_from_body / pose_from_site)" if name == "rot" else ""
            wanted = " or ".join(f"{list(t)} or [B, {', '.join(map(str, t))}]" for t in tails)
            raise ValueError(f"pose.{name}: expected {wanted}{note}, got shape {list(shape)}")
    pos = jnp.asarray(pose.pos, jnp.float32).reshape(-1, 3)
    rot = jnp.asarray(pose.rot, jnp.float32).reshape(-1, 3, 3)
    nposes = max(pos.shape[0], rot.shape[0])
    if nscene == 1 and nposes > 1:  # B poses in one scene: the scene is shared
        nscene, batched = nposes, True
        geo = lidar.repeat_scene(geo, nscene)
    for name, x in (("pos", pos), ("rot", rot)):
        if x.shape[0] not in (1, nscene):
            raise ValueError(f"pose.{name} holds {x.shape[0]} poses for {nscene} scenes")
    pos = jnp.broadcast_to(pos, (nscene, 3))
    rot = jnp.broadcast_to(rot, (nscene, 3, 3))
    world_dirs = jnp.einsum("bij,rj->bri", rot, directions)  # [B, R, 3]
    dist, gid = lidar.cast_geometry(geo, pos, world_dirs, config.max_range, **cast_kwargs)
    dist = dist.reshape(nscene, -1)  # [B, R]
    gid = gid.reshape(nscene, -1)

    hit = gid >= 0
    hit_world = pos[:, None] + world_dirs * dist[..., None]  # [B, R, 3]
    normal = lidar.surface_normals(geo, hit_world, gid)
    cos_inc = jnp.abs(jnp.sum(normal * world_dirs, -1))  # [B, R]
    if reflectivity is None:
        refl = jnp.full((nscene, ngeom), config.default_reflectivity, jnp.float32)
    else:
        refl = jnp.asarray(reflectivity, jnp.float32)
        if refl.shape not in ((ngeom,), (1, ngeom), (nscene, ngeom)):
            raise ValueError(
                f"reflectivity: expected one value per geom, [G] or [B, G] with G = {ngeom}, "
                f"B = {nscene}, got shape {list(refl.shape)}"
            )
        refl = jnp.broadcast_to(refl.reshape(-1, ngeom), (nscene, ngeom))
    intensity = jnp.take_along_axis(refl, jnp.maximum(gid, 0), axis=1) * cos_inc ** (
        config.incidence_exponent
    )

    k_noise, k_drop = jax.random.split(key)
    noise = config.range_noise_std * jax.random.normal(k_noise, dist.shape, jnp.float32)
    measured = dist + noise
    kept = jax.random.uniform(k_drop, dist.shape) >= config.dropout_prob
    valid = (
        hit
        & kept
        & (measured >= config.min_range)
        & (measured <= config.max_range)
        & jnp.isfinite(measured)
    )
    xyz = directions[None] * measured[..., None]  # sensor frame: direction times range
    points = jnp.concatenate([xyz, jnp.clip(intensity, 0.0, 1.0)[..., None]], -1)  # [B, R, 4]
    points = jnp.where(valid[..., None], points, 0.0)
    out = Scan(points, valid, gid, dist)
    if not batched:
        out = jax.tree.map(lambda x: x[0], out)
    return out


class MjLidar:
    """A lidar on a plain MuJoCo model, scanning ``mujoco.MjData`` states step by step.

    For simulations stepped on the host with ``mujoco.mj_step``: no ``mjx.put_model``, so
    models MJX refuses work (``skip_unsupported=True`` for meshes), and each call copies only
    what rays read (the geoms' poses, sizes, colours and materials, a few floats per geom,
    and the sensor site's pose) into one jitted scan. So edits of ``model.geom_size``,
    ``geom_rgba``, ``geom_matid`` or ``mat_rgba`` between calls (domain randomisation,
    hiding a geom with alpha 0) are seen; geom types, bodies and groups are read once. The
    result is exactly ``scan`` on ``mjx.put_data(model, data)``, without converting the
    whole ``MjData`` each step.

    Example:
      >>> lidar = MjLidar(m, "lidar", patterns.Mid360Pattern())
      >>> for k in range(100):
      ...     mujoco.mj_step(m, d)
      ...     s = lidar(d, jax.random.key(k), frame=k)  # Scan: points [R, 4] sensor frame

    Args:
      model: ``mujoco.MjModel``.
      site: name of the site the sensor rides on (its frame is the sensor frame).
      pattern: a scan pattern (``patterns.Mid360Pattern()`` etc.); frame ``k`` of it is cast.
      config: ``SensorConfig``.
      reflectivity: optional float [G] per-geom reflectivity.
      **cast_kwargs: as ``scan`` (geomgroup, bodyexclude, method, cpu_threads, ...).
        ``bodyexclude`` defaults to the body the site rides on, as MuJoCo's rangefinder
        sensor does, so the lidar does not see its own housing; a site on the world body
        excludes nothing (-1), and ``bodyexclude=-1`` sees every body.
    """

    def __init__(
        self,
        model,
        site: str,
        pattern,
        config: SensorConfig = SensorConfig(),
        reflectivity=None,
        **cast_kwargs,
    ):
        import mujoco
        from indoorbev_sim.scenes import GeomData, geom_model_of

        site_id = mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_SITE, site)
        if site_id < 0:
            names = [model.site(i).name for i in range(model.nsite)]
            raise ValueError(f"MjLidar: the model has no site {site!r}; sites: {names}")
        self.model, self.site_id = model, site_id
        body = int(model.site_bodyid[site_id])
        cast_kwargs.setdefault("bodyexclude", body if body > 0 else -1)
        # Only the fields rays read: mjx.put_model would refuse many robot models for
        # collision pairs MJX lacks (cylinder-box, meshes), which a lidar never needs.
        static = geom_model_of(model, jnp.asarray(model.geom_size, jnp.float32))
        refl = None if reflectivity is None else jnp.asarray(reflectivity, jnp.float32)

        def run(looks, geom_xpos, geom_xmat, site_pos, site_mat, frame, key):
            geoms = static.replace(**looks)
            data = GeomData(geom_xpos=geom_xpos, geom_xmat=geom_xmat)
            pose = Pose(site_pos, site_mat.reshape(3, 3))
            dirs = pattern.frame(frame).directions
            return scan(geoms, data, pose, dirs, key, config, reflectivity=refl, **cast_kwargs)

        self._run = jax.jit(run)

    def __call__(self, data, key: jax.Array, frame: int = 0) -> Scan:
        """Scan of ``data`` (after ``mj_forward``/``mj_step``, which update the poses)."""
        if data.geom_xpos.shape != (self.model.ngeom, 3):
            raise ValueError(
                f"MjLidar: data.geom_xpos has shape {data.geom_xpos.shape}, the model has "
                f"{self.model.ngeom} geoms; pass an MjData of the model given at construction"
            )
        m = self.model
        # Copies: MuJoCo keeps rgba and matid as float32/int32 already, and a view of the
        # live model in this asynchronous call would see an edit made after it returned.
        looks = {
            "geom_size": np.array(m.geom_size, np.float32),
            "geom_rgba": np.array(m.geom_rgba, np.float32),
            "geom_matid": np.array(m.geom_matid, np.int32),
            "mat_rgba": np.array(m.mat_rgba, np.float32).reshape(-1, 4),
        }
        return self._run(
            looks,
            np.asarray(data.geom_xpos, np.float32),
            np.asarray(data.geom_xmat, np.float32).reshape(-1, 3, 3),
            np.asarray(data.site_xpos[self.site_id], np.float32),
            np.asarray(data.site_xmat[self.site_id], np.float32),
            jnp.int32(frame),
            key,
        )
