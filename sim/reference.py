"""The plain sequential pipeline: one frame at a time with MuJoCo ``mj_multiRay`` and numpy.

``reference_frame`` re-derives what ``generate.simulate`` makes for one scene (the cast,
noise, filtering, footprints, point counts, visibility and boxes) with code that shares
nothing with the batched path but the scene and the scan pattern: the tests' oracle and
``experiments/bench_datagen.py``'s baseline. Not used by the pipeline itself.
"""

from __future__ import annotations

import copy
import functools

import jax
import jax.numpy as jnp
import mujoco
import numpy as np
from indoorbev_sim import objects
from indoorbev_sim import scenes as scenes_mod
from indoorbev_sim.generate import make_pattern, mount_rotation, yaw_matrix

from indoorbev_jax.config import Config, GridConfig
from indoorbev_jax.data.rasterize import BOUNDARY_EPS
from indoorbev_jax.geometry import cell_centers


def scene_numpy(scene: scenes_mod.Scene, index: int):
    """Scene ``index`` of a batched ``Scene`` as numpy arrays."""
    return jax.tree.map(lambda x: np.asarray(x[index]), scene)


def reference_cast(tpl: scenes_mod.SceneTemplate, size, xpos, xmat, origin, dirs, max_range):
    """MuJoCo's ``mj_multiRay`` on one posed scene (numpy in, numpy out).

    Args:
      size, xpos: float [G, 3]; xmat: float [G, 3, 3]; origin: float [3]; dirs: float [R, 3].

    Returns:
      distance float64 [R] (-1: miss or beyond max_range), geom_id int32 [R].
    """
    m = copy.copy(tpl.mj_model)  # the template's model is cached and stays at rest
    m.geom_size[:] = size
    rb, aabb = scenes_mod.geom_bounds(tpl, np.asarray(size))
    m.geom_rbound[:] = rb
    m.geom_aabb[:] = aabb
    d = mujoco.MjData(m)
    d.geom_xpos[:] = xpos
    d.geom_xmat[:] = np.asarray(xmat).reshape(-1, 9)
    r = len(dirs)
    dist = np.zeros(r)
    gid = np.zeros(r, np.int32)
    mujoco.mj_multiRay(
        m, d, np.asarray(origin, np.float64), np.asarray(dirs, np.float64).reshape(-1),
        None, 1, -1, gid, dist, None, r, max_range,
    )  # fmt: skip
    miss = (gid < 0) | (dist < 0) | (dist > max_range)
    return np.where(miss, -1.0, dist), np.where(miss, -1, gid).astype(np.int32)


def _np_world_prims(scene, time):
    pose = np.asarray(scene.pose) + 0.0
    pose[:, :2] += np.asarray(scene.velocity) * time
    c, s = np.cos(pose[:, 2]), np.sin(pose[:, 2])
    lx, ly = scene.prims.pos[..., 0], scene.prims.pos[..., 1]
    x = c[:, None] * lx - s[:, None] * ly + pose[:, None, 0]
    y = s[:, None] * lx + c[:, None] * ly + pose[:, None, 1]
    pos = np.stack([x, y, scene.prims.pos[..., 2]], -1)
    return pose, pos, scene.prims.yaw + pose[:, None, 2], scene.prims.on & scene.on[:, None]


def reference_footprints(tpl, scene, time, origin, heading, grid) -> np.ndarray:
    """Numpy re-derivation of ``labels.footprints`` (one scene): bool [S, H, W]."""
    _, pos, yaw, on = _np_world_prims(scene, time)
    h, w = grid.shape
    xs = grid.x_range[0] + (np.arange(w) + 0.5) * grid.cell_size
    ys = grid.y_range[0] + (np.arange(h) + 0.5) * grid.cell_size
    gx, gy = np.meshgrid(xs, ys)  # [H, W]
    c, s = np.cos(heading), np.sin(heading)
    out = np.zeros((tpl.num_slots, h, w), bool)
    eps = 1e-6
    for si in range(tpl.num_slots):
        for p, kind in enumerate(objects.CLASSES[tpl.slot_class[si]].prims):
            if not on[si, p]:
                continue
            dxw, dyw = pos[si, p, 0] - origin[0], pos[si, p, 1] - origin[1]
            cx, cy = c * dxw + s * dyw, -s * dxw + c * dyw
            a = yaw[si, p] - heading
            size = scene.prims.size[si, p]
            along = np.cos(a) * (gx - cx) + np.sin(a) * (gy - cy)
            across = -np.sin(a) * (gx - cx) + np.cos(a) * (gy - cy)
            lo = grid.cell_size / 2  # thin parts widened to one cell (labels.footprints)
            if kind == "box":
                m = np.abs(along) <= max(size[0], lo) + eps
                m &= np.abs(across) <= max(size[1], lo) + eps
            elif kind == "hcyl":
                m = np.abs(along) <= max(size[1], lo) + eps
                m &= np.abs(across) <= max(size[0], lo) + eps
            elif kind == "ellipsoid":
                a, b = max(size[0], lo) + eps, max(size[1], lo) + eps
                m = (along / a) ** 2 + (across / b) ** 2 <= 1
            else:  # sphere, upright cylinder, capsule: distance to the projected axis
                half = size[1] * np.sin(scene.prims.pitch[si, p]) if kind == "capsule" else 0.0
                t = np.clip(along, -abs(half), abs(half))
                m = (along - t) ** 2 + across**2 <= (max(size[0], lo) + eps) ** 2
            out[si] |= m
    return out


def reference_frame(
    config: Config, scene, time: float, directions: np.ndarray, rng: np.random.Generator
) -> dict[str, np.ndarray]:
    """The plain sequential pipeline for one frame: MuJoCo ``mj_multiRay`` + numpy.

    Same scene and rays as ``simulate`` (``scene`` a numpy ``Scene`` of one scene), noise
    drawn from ``rng``; labels derived with numpy (``reference_footprints``).

    Returns:
      dict: points [R, 4], valid [R] (the returns the cloud keeps), geom_id [R], distance [R],
      point_slot [R], and per
      slot (S): masks [S, H, W], num_points, visibility, labelled, pos, dims, yaw.
    """
    sim, grid = config.sim, config.grid
    tpl = scenes_mod.template_for(config)
    size, xpos, xmat, refl = (np.asarray(x) for x in _geom_state_jit(config)(scene, time))
    pose, _, _, _ = _np_world_prims(scene, time)
    origin = np.array([*(scene.ego[:2] + scene.ego_velocity * time), scene.sensor_height])
    heading = float(scene.ego[2])
    tilt = mount_rotation(sim, scene)
    tilt = np.eye(3) if tilt is None else np.asarray(tilt, np.float64)
    rot = np.asarray(yaw_matrix(jnp.float32(heading)), np.float64) @ tilt  # world <- lidar
    world_dirs = directions @ rot.T
    dist, gid = reference_cast(tpl, size, xpos, xmat, origin, world_dirs, sim.max_range)
    hit = gid >= 0
    measured = dist + sim.range_noise * rng.standard_normal(len(dist))
    valid = hit & (rng.random(len(dist)) >= sim.dropout)
    valid &= (measured >= sim.min_range) & (measured <= sim.max_range)
    xyz = directions * measured[:, None] @ tilt.T  # levelled
    g = grid
    valid &= (xyz[:, 0] >= g.x_range[0]) & (xyz[:, 0] <= g.x_range[1])
    valid &= (xyz[:, 1] >= g.y_range[0]) & (xyz[:, 1] <= g.y_range[1])
    valid &= (xyz[:, 2] >= g.z_range[0]) & (xyz[:, 2] <= g.z_range[1])
    point_slot = np.where(hit, tpl.geom_slot[np.maximum(gid, 0)], -1)
    # Of more than data.max_points returns, the evenly spread ones the cloud keeps.
    kept = np.flatnonzero(valid)
    n = config.data.max_points
    if len(kept) > n:
        kept = kept[np.arange(n, dtype=np.int64) * len(kept) // n]
    valid = np.zeros_like(valid)
    valid[kept] = True
    s = tpl.num_slots
    counts = np.bincount(point_slot[valid & (point_slot >= 0)], minlength=s)[:s]
    # Visibility rays at primitive centres.
    _, ppos, _, pon = _np_world_prims(scene, time)
    to = ppos.reshape(-1, 3) - origin
    vd = to / np.maximum(np.linalg.norm(to, axis=-1, keepdims=True), 1e-9)
    vdist, vg = reference_cast(tpl, size, xpos, xmat, origin, vd, sim.max_range)
    elevation = np.arcsin(np.clip((vd @ rot)[:, 2], -1, 1))  # the sensor frame's
    pattern = make_pattern(sim)
    lo, hi = elevation_limits(pattern)
    fired = (vg >= 0) & (elevation >= lo - 1e-6) & (elevation <= hi + 1e-6)
    fired &= vdist >= sim.min_range
    vslot = np.where(fired, tpl.geom_slot[np.maximum(vg, 0)], -1).reshape(s, -1)
    seen = (vslot == np.arange(s)[:, None]) & pon
    visibility = seen.sum(-1) / np.maximum(pon.sum(-1), 1)
    c, sn = np.cos(heading), np.sin(heading)
    d = pose[:, :2] - origin[:2]
    pos = np.stack(
        [c * d[:, 0] + sn * d[:, 1], -sn * d[:, 0] + c * d[:, 1],
         scene.prims.dims[:, 2] / 2 - origin[2]], -1
    )  # fmt: skip
    inside = (pos[:, 0] >= g.x_range[0]) & (pos[:, 0] <= g.x_range[1])
    inside &= (pos[:, 1] >= g.y_range[0]) & (pos[:, 1] <= g.y_range[1])
    return {
        "points": np.concatenate([xyz, np.zeros((len(xyz), 1))], -1) * valid[:, None],
        "valid": valid,
        "geom_id": gid,
        "distance": dist,
        "point_slot": point_slot,
        "masks": reference_footprints(tpl, scene, time, origin, heading, grid),
        "num_points": counts,
        "visibility": visibility,
        "labelled": scene.on & inside & (counts >= sim.min_points),
        "pos": pos,
        "dims": scene.prims.dims,
        "yaw": (pose[:, 2] - heading + np.pi) % (2 * np.pi) - np.pi,
        "reflectivity": refl,
    }


def elevation_limits(pattern) -> tuple[float, float]:
    """(lowest, highest) ray elevation of a full-turn pattern, radians (the reference's own
    reading of the pattern's settings, apart from ``covers``)."""
    if hasattr(pattern, "elevations_deg"):
        lo, hi = min(pattern.elevations_deg), max(pattern.elevations_deg)
    else:
        lo, hi = pattern.elevation_min_deg, pattern.elevation_max_deg
    return float(np.deg2rad(lo)), float(np.deg2rad(hi))


@functools.lru_cache(maxsize=4)
def _geom_state_jit(config: Config):
    tpl = scenes_mod.template_for(config)
    return jax.jit(functools.partial(scenes_mod.geom_state, tpl))


# Analytic footprints on the whole grid, for the tests (``labels`` marks its own, in windows).
def stadium_masks(p0: jax.Array, p1: jax.Array, radius: jax.Array, grid: GridConfig) -> jax.Array:
    """Cells whose centre lies within ``radius`` of the segment p0-p1 (a disc if p0 == p1).

    Args:
      p0, p1: float [N, 2]; radius: float [N].

    Returns:
      bool [N, H, W].
    """
    xs, ys = cell_centers(grid)
    ab = p1 - p0  # [N, 2]
    dx = xs[None, None, :] - p0[:, 0, None, None]  # [N, 1, W]
    dy = ys[None, :, None] - p0[:, 1, None, None]  # [N, H, 1]
    len2 = jnp.maximum(jnp.sum(ab * ab, -1), 1e-12)[:, None, None]
    t = jnp.clip((dx * ab[:, 0, None, None] + dy * ab[:, 1, None, None]) / len2, 0.0, 1.0)
    ex = dx - t * ab[:, 0, None, None]  # [N, H, W]
    ey = dy - t * ab[:, 1, None, None]
    r = radius[:, None, None] + BOUNDARY_EPS
    return ex * ex + ey * ey <= r * r


def ellipse_masks(centre: jax.Array, axes: jax.Array, yaw: jax.Array, grid: GridConfig):
    """Cells whose centre lies inside the ellipse (semi-axes ``axes`` along yaw and across).

    Args:
      centre: float [N, 2]; axes: float [N, 2] (> 0); yaw: float [N].

    Returns:
      bool [N, H, W].
    """
    xs, ys = cell_centers(grid)
    dx = xs[None, None, :] - centre[:, 0, None, None]  # [N, 1, W]
    dy = ys[None, :, None] - centre[:, 1, None, None]  # [N, H, 1]
    c, s = jnp.cos(yaw)[:, None, None], jnp.sin(yaw)[:, None, None]
    a = axes[:, 0, None, None] + BOUNDARY_EPS
    b = axes[:, 1, None, None] + BOUNDARY_EPS
    along, across = c * dx + s * dy, -s * dx + c * dy  # [N, H, W]
    return (along / a) ** 2 + (across / b) ** 2 <= 1.0
