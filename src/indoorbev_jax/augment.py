"""Training augmentations (paper appendix "Data Augmentation"), jittable with explicit keys.

Each function takes and returns one unbatched ``Batch`` (points [N, 4], point_valid [N],
targets with M objects and [M, H, W] masks); ``augment_batch`` vmaps the whole chain over a
batch. Points, boxes and footprints always move together: footprints are resampled with the
inverse of the map applied to the points (nearest cell centre), so a true-shape footprint
stays true-shape. After every step the panoptic map is re-derived from the masks.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
from flax import struct

from indoorbev_jax.config import AugmentConfig, GridConfig, check_section
from indoorbev_jax.data.rasterize import instance_ids_from_masks
from indoorbev_jax.geometry import cell_centers, cell_index, in_workspace, on_grid, wrap_angle
from indoorbev_jax.types import Batch, Targets, float32_defaults

# Points this close outside a box still belong to it (lidar hits lie on its surface).
BOX_MARGIN = 0.03
# A moved or pasted box may hold at most this many scene points (no object's) above the
# floor it stands on, FLOOR_MARGIN up: more means a wall or unlabelled clutter.
SCENE_POINTS_LIMIT = 5
FLOOR_MARGIN = 0.05
# Most azimuth bins of the free-space test of ground-truth sampling (_beyond_returns).
FREE_SPACE_BINS = 720
# fold_in constant of the intensity-drop draw (see point_noise).
INTENSITY_FOLD = 1_000_003


def _wrap(yaw: jax.Array) -> jax.Array:
    """``wrap_angle`` that leaves yaws already in [-pi, pi) bit for bit (the float32 round
    trip through ``+ pi`` moves about half of them by an ulp)."""
    return jnp.where((yaw >= -jnp.pi) & (yaw < jnp.pi), yaw, wrap_angle(yaw))


def _rot(theta: jax.Array) -> jax.Array:
    """2 x 2 rotation matrices [..., 2, 2] for angles [...]."""
    c, s = jnp.cos(theta), jnp.sin(theta)
    return jnp.stack([jnp.stack([c, -s], -1), jnp.stack([s, c], -1)], -2)


def _sample_masks(masks: jax.Array, x: jax.Array, y: jax.Array, grid: GridConfig) -> jax.Array:
    """masks [M, H, W] read at the grid cells under points (x, y) of shape [M, ...];
    False where a point falls outside the grid."""
    row, col, inside = cell_index(x, y, grid)
    m = masks.shape[0]
    flat = (row * grid.shape[1] + col).reshape(m, -1)
    out = jnp.take_along_axis(masks.reshape(m, -1), flat, axis=1)
    return out.reshape(x.shape) & inside


def warp_masks(masks: jax.Array, inverse: jax.Array, grid: GridConfig) -> jax.Array:
    """Resamples masks under a per-mask affine map of the plane.

    Args:
      masks: bool [M, H, W] on ``grid``.
      inverse: float [M, 2, 3], maps a destination point (x, y, 1) to its source point.
      grid: the BEV grid.

    Returns:
      bool [M, H, W]: each destination cell takes the source cell under its mapped centre,
      False where that falls outside the grid.
    """
    xs, ys = cell_centers(grid)
    px, py = jnp.meshgrid(xs, ys)  # [H, W]
    sx = inverse[:, 0, 0, None, None] * px + inverse[:, 0, 1, None, None] * py
    sy = inverse[:, 1, 0, None, None] * px + inverse[:, 1, 1, None, None] * py
    sx = sx + inverse[:, 0, 2, None, None]  # [M, H, W]
    sy = sy + inverse[:, 1, 2, None, None]
    return _sample_masks(masks, sx, sy, grid)


def points_in_boxes(points: jax.Array, pos, dims, yaw, valid, margin=BOX_MARGIN) -> jax.Array:
    """bool [M, N]: point n lies inside (oriented 3D) box m, grown by ``margin``."""
    d = points[None, :, :3] - pos[:, None, :]  # [M, N, 3]
    local = jnp.einsum("mji,mnj->mni", _rot(yaw), d[..., :2])  # rotate by -yaw
    half = 0.5 * dims[:, None, :] + margin
    inside = (jnp.abs(local) <= half[..., :2]).all(-1) & (jnp.abs(d[..., 2]) <= half[..., 2])
    return inside & valid[:, None]


def _finish(points, point_valid, targets: Targets, grid: GridConfig) -> Batch:
    point_valid = point_valid & in_workspace(points, grid)
    points = jnp.where(point_valid[:, None], points, 0.0)
    masks = targets.masks & targets.valid[:, None, None]
    targets = targets.replace(
        masks=masks, instance_ids=instance_ids_from_masks(masks, targets.valid)
    )
    return Batch(points=points, point_valid=point_valid, targets=targets)


def _fill_free_slots(points, valid, new, new_valid) -> tuple[jax.Array, jax.Array]:
    """Writes ``new[i]`` [K, 4] into the i-th free (invalid) slot of ``points`` [N, 4], in
    index order, where ``new_valid[i]``; rows of ``new`` beyond the free slots are dropped.
    Free slots are ranked by a running count (a stable argsort of ``valid`` picks the same
    slots and costs 4x more on XLA:CPU)."""
    k = new.shape[0]
    count = jnp.cumsum(~valid)  # free slots up to and including each index
    rank = jnp.clip(count - 1, 0, k - 1)
    fill = ~valid & (count <= k) & new_valid[rank]
    return jnp.where(fill[:, None], new[rank], points), valid | fill


def global_transform(key: jax.Array, frame: Batch, grid: GridConfig, cfg: AugmentConfig) -> Batch:
    """Random mirror (y -> -y), rotation about +z and uniform scaling about the origin."""
    k_flip, k_rot, k_scale = jax.random.split(key, 3)
    flip = jax.random.bernoulli(k_flip, cfg.flip_prob)
    theta = jax.random.uniform(k_rot, (), minval=-cfg.rotation, maxval=cfg.rotation)
    scale = jax.random.uniform(k_scale, (), minval=cfg.scale_range[0], maxval=cfg.scale_range[1])
    mirror = jnp.diag(jnp.array([1.0, jnp.where(flip, -1.0, 1.0)]))
    linear = scale * _rot(theta) @ mirror  # [2, 2], points: xy -> linear @ xy
    # Closed form (mirror is its own inverse): jnp.linalg.inv would put LAPACK / cuSOLVER
    # calls into the train step.
    linear_inverse = mirror @ _rot(-theta) / scale
    t = frame.targets
    xy = frame.points[:, :2] @ linear.T
    points = jnp.concatenate([xy, frame.points[:, 2:3] * scale, frame.points[:, 3:]], axis=1)
    pos = jnp.concatenate([t.pos[:, :2] @ linear.T, t.pos[:, 2:] * scale], axis=1)
    yaw = _wrap(jnp.where(flip, -t.yaw, t.yaw) + theta)
    inverse = jnp.concatenate([linear_inverse, jnp.zeros((2, 1))], axis=1)  # [2, 3]
    masks = warp_masks(t.masks, jnp.broadcast_to(inverse, (t.masks.shape[0], 2, 3)), grid)
    targets = t.replace(pos=pos, dims=t.dims * scale, yaw=yaw, masks=masks)
    return _finish(points, frame.point_valid, targets, grid)


def point_noise(key: jax.Array, frame: Batch, grid: GridConfig, cfg: AugmentConfig) -> Batch:
    """Jitter, random dropping, one range-band dropout, clutter injection, intensity
    dropout (the whole frame's), shuffling."""
    k_jit, k_drop, k_band, k_r0, k_noise, k_perm = jax.random.split(key, 6)
    n = frame.points.shape[0]
    points = frame.points.at[:, :3].add(cfg.jitter_std * jax.random.normal(k_jit, (n, 3)))
    valid = frame.point_valid & ~jax.random.bernoulli(k_drop, cfg.point_drop_prob, (n,))
    max_range = float(np.hypot(max(map(abs, grid.x_range)), max(map(abs, grid.y_range))))
    r0 = jax.random.uniform(k_r0, (), maxval=max_range)
    r = jnp.hypot(points[:, 0], points[:, 1])
    band = jax.random.bernoulli(k_band, cfg.range_dropout_prob) & (r >= r0)
    valid &= ~(band & (r < r0 + cfg.range_dropout_width))
    # Clutter goes into free slots only (invalid slots sort first), never over real points.
    n_noise = int(round(cfg.noise_points * n))
    if n_noise:
        lo = jnp.array([grid.x_range[0], grid.y_range[0], grid.z_range[0], 0.0])
        hi = jnp.array([grid.x_range[1], grid.y_range[1], grid.z_range[1], 1.0])
        clutter = jax.random.uniform(k_noise, (n_noise, 4), minval=lo, maxval=hi)
        points, valid = _fill_free_slots(points, valid, clutter, jnp.ones(n_noise, bool))
    if cfg.intensity_drop_prob:
        # A folded key leaves the other draws unchanged. Not a small constant: fold_in(key, i)
        # equals split(key, n)[i] for i < n under partitionable threefry, i.e. k_drop for 1.
        k_intensity = jax.random.fold_in(key, INTENSITY_FOLD)
        no_intensity = jax.random.bernoulli(k_intensity, cfg.intensity_drop_prob)
        points = points.at[:, 3].multiply(jnp.where(no_intensity, 0.0, 1.0))
    if cfg.shuffle_points:
        # One sort by random 32-bit keys (jax.random.permutation sorts twice to break
        # ties; a tie among 2^32 keys only keeps two points in their order).
        perm = jnp.argsort(jax.random.bits(k_perm, (n,), jnp.uint32))
        points, valid = points[perm], valid[perm]
    return _finish(points, valid, frame.targets, grid)


def box_noise(key: jax.Array, frame: Batch, grid: GridConfig, cfg: AugmentConfig) -> Batch:
    """Moves, turns and rescales single objects together with their points and footprints.

    An object whose moved box would hold more than ``SCENE_POINTS_LIMIT`` scene points
    (points of no object: walls, unlabelled clutter) above its floor keeps its original pose,
    as ground-truth sampling refuses such a pose; wall-bound furniture would otherwise be
    pushed into the wall. An object whose moved footprint would overlap another object's
    more than before keeps its original pose too. Every object is checked against the
    others' new poses, again after each round of undone moves (an undone object returns to a
    place another may have moved into), until no kept move overlaps more than before.
    """
    t = frame.targets
    m = t.classes.shape[0]
    k_on, k_t, k_yaw, k_s = jax.random.split(key, 4)
    on = jax.random.bernoulli(k_on, cfg.box_noise_prob, (m,)) & t.valid
    shift = cfg.box_translation_std * jax.random.normal(k_t, (m, 2))
    dyaw = cfg.box_yaw_std * jax.random.normal(k_yaw, (m,))
    scale = jnp.exp(cfg.box_scale_std * jax.random.normal(k_s, (m,)))

    inside = points_in_boxes(frame.points, t.pos, t.dims, t.yaw, t.valid)  # [M, N]
    has_owner = inside.any(0) & frame.point_valid
    scene = frame.point_valid & ~has_owner
    new_dims = t.dims * scale[:, None]
    bottom = t.pos[:, 2] - 0.5 * t.dims[:, 2] + FLOOR_MARGIN  # [M], the floor it stands on
    top = t.pos[:, 2] + 0.5 * new_dims[:, 2]
    # Elementwise (rotate by -yaw'): one fused loop over [M, N], no batched 2 x 2 matmul.
    centre = t.pos[:, :2] + shift
    dx = frame.points[None, :, 0] - centre[:, 0, None]  # [M, N]
    dy = frame.points[None, :, 1] - centre[:, 1, None]
    c, s = jnp.cos(t.yaw + dyaw)[:, None], jnp.sin(t.yaw + dyaw)[:, None]
    # With the margin that makes a point the box's own: a wall 2 cm away would be.
    half = 0.5 * new_dims[:, :2, None] + BOX_MARGIN  # [M, 2, 1]
    z = frame.points[None, :, 2]
    in_moved = (jnp.abs(c * dx + s * dy) <= half[:, 0]) & (jnp.abs(c * dy - s * dx) <= half[:, 1])
    in_moved &= (z > bottom[:, None]) & (z <= top[:, None]) & scene[None]
    on &= in_moved.sum(1) <= SCENE_POINTS_LIMIT

    # dest -> source: c + R(-dyaw) (dest - c - shift) / scale
    rinv = jnp.swapaxes(_rot(dyaw), -1, -2) / scale[:, None, None]  # [M, 2, 2]
    c = t.pos[:, :2]
    offset = c - jnp.einsum("mij,mj->mi", rinv, c + shift)
    moved_masks = warp_masks(t.masks, jnp.concatenate([rinv, offset[:, :, None]], axis=2), grid)

    def overlap(masks):
        count = masks.sum(0)  # [H, W]
        return (masks & (count - masks > 0)).sum((1, 2))  # [M] cells shared with others

    before = overlap(t.masks)

    def undo(carry):
        on, _ = carry
        candidate = jnp.where(on[:, None, None], moved_masks, t.masks) & t.valid[:, None, None]
        kept = on & (overlap(candidate) <= before)
        return kept, (kept != on).any()

    # Each round only undoes moves, so at most M rounds; usually one or two.
    on, _ = jax.lax.while_loop(lambda carry: carry[1], undo, (on, jnp.array(True)))
    masks = jnp.where(on[:, None, None], moved_masks, t.masks)
    shift_on = jnp.where(on[:, None], shift, 0.0)
    dyaw_on = jnp.where(on, dyaw, 0.0)
    scale_on = jnp.where(on, scale, 1.0)

    # First containing box (a min over indices; argmax over bool is slow on XLA:CPU).
    owner = jnp.min(jnp.where(inside, jnp.arange(m)[:, None], m - 1), axis=0)
    c = t.pos[owner]  # [N, 3]
    rel = frame.points[:, :3] - c
    xy = jnp.einsum("nij,nj->ni", _rot(dyaw_on[owner]), rel[:, :2]) * scale_on[owner, None]
    z = rel[:, 2:] * scale_on[owner, None]
    moved = jnp.concatenate([c[:, :2] + shift_on[owner] + xy, c[:, 2:] + z], axis=1)
    xyz = jnp.where(has_owner[:, None], moved, frame.points[:, :3])
    points = jnp.concatenate([xyz, frame.points[:, 3:]], axis=1)

    pos = t.pos.at[:, :2].add(shift_on)
    targets = t.replace(
        pos=pos,
        dims=t.dims * scale_on[:, None],
        yaw=_wrap(t.yaw + dyaw_on),
        masks=masks,
    )
    return _finish(points, frame.point_valid, targets, grid)


def _pool3x3(masks: jax.Array, op, outside: bool) -> jax.Array:
    """``op`` over each cell's 3 x 3 neighbourhood of bool [M, H, W], cells beyond the edge
    read as ``outside``; separable shifted slices (XLA:CPU's reduce_window is 2x slower)."""
    h, w = masks.shape[1:]
    x = jnp.pad(masks, ((0, 0), (1, 1), (1, 1)), constant_values=outside)
    x = op(op(x[:, :, :w], x[:, :, 1 : w + 1]), x[:, :, 2:])
    return op(op(x[:, :h], x[:, 1 : h + 1]), x[:, 2:])


def mask_perturbation(key: jax.Array, frame: Batch, grid: GridConfig, cfg: AugmentConfig) -> Batch:
    """Per object, with probability ``mask_perturb_prob``: one-cell dilation or erosion
    (3 x 3). An erosion that would empty a mask leaves it unchanged."""
    t = frame.targets
    m = t.classes.shape[0]
    k_on, k_kind = jax.random.split(key)
    on = jax.random.bernoulli(k_on, cfg.mask_perturb_prob, (m,)) & t.valid
    dilate = jax.random.bernoulli(k_kind, 0.5, (m,))
    dilated = _pool3x3(t.masks, jnp.logical_or, False)
    eroded = _pool3x3(t.masks, jnp.logical_and, True)  # cells outside the grid count as set
    eroded = jnp.where(eroded.any((1, 2))[:, None, None], eroded, t.masks)
    new = jnp.where(dilate[:, None, None], dilated, eroded)
    masks = jnp.where(on[:, None, None], new, t.masks)
    return _finish(frame.points, frame.point_valid, t.replace(masks=masks), grid)


@struct.dataclass
class ObjectDatabase:
    """Objects cut out of training frames for ground-truth sampling (static shapes).

    Attributes:
      points: float32 [D, P, 4], object-local (centre at 0, heading along +x) + intensity.
      point_valid: bool [D, P].
      classes: int32 [D]; dims: float32 [D, 3]; z: float32 [D], centre height.
      footprints: bool [D, S, S], object-local footprint at the grid's cell size; local
        cell (a, b) has centre ((b - S/2 + 0.5) v, (a - S/2 + 0.5) v).
    """

    points: jax.Array
    point_valid: jax.Array
    classes: jax.Array
    dims: jax.Array
    z: jax.Array
    footprints: jax.Array


def _local_patch_centres(size: int, cell: float) -> jax.Array:
    c = (jnp.arange(size) - size / 2 + 0.5) * cell
    u, v = jnp.meshgrid(c, c)  # [S, S], u along x (columns)
    return jnp.stack([u, v], -1)  # [S, S, 2]


def build_object_database(
    batch: Batch, grid: GridConfig, max_points: int = 256, patch_cells: int | None = None
) -> ObjectDatabase:
    """Cuts every valid object (its points and true footprint) out of a batch of frames,
    except those whose footprint touches the grid's edge (cut off in their frame).

    Args:
      batch: a batch (leading axis B) of frames.
      grid: the BEV grid of the batch.
      max_points: P, points kept per object (evenly spaced over its points in cloud order).
      patch_cells: S, side of the local footprint patch in cells (default: 4 m worth).

    Returns:
      An ``ObjectDatabase`` of the D valid objects of the batch clear of the edge.
    """
    s = patch_cells or int(np.ceil(4.0 / grid.cell_size))
    local_centres = _local_patch_centres(s, grid.cell_size)  # [S, S, 2]

    def one_frame(frame_points, frame_valid, t: Targets):
        inside = points_in_boxes(frame_points, t.pos, t.dims, t.yaw, t.valid)  # [M, N]
        inside &= frame_valid[None]
        # P points evenly spaced over the object's (a scan stores them in firing order: the
        # first P would be an azimuth slice of a large object).
        order = jnp.argsort(~inside, axis=1, stable=True)  # [M, N], the object's points first
        count = inside.sum(1, keepdims=True)  # [M, 1]
        pick = jnp.arange(max_points)[None, :] * jnp.maximum(count, max_points) // max_points
        order = jnp.take_along_axis(order, jnp.minimum(pick, order.shape[1] - 1), axis=1)
        keep = jnp.take_along_axis(inside, order, axis=1)
        pts = frame_points[order]  # [M, P, 4]
        rel = pts[..., :2] - t.pos[:, None, :2]
        local_xy = jnp.einsum("mji,mpj->mpi", _rot(t.yaw), rel)  # rotate by -yaw
        local = jnp.concatenate(
            [local_xy, pts[..., 2:3] - t.pos[:, None, 2:3], pts[..., 3:]], axis=-1
        )
        # Local patch cell -> world -> grid cell (nearest), like warp_masks.
        world = jnp.einsum("mij,abj->mabi", _rot(t.yaw), local_centres) + t.pos[:, None, None, :2]
        fp = _sample_masks(t.masks, world[..., 0], world[..., 1], grid)  # [M, S, S]
        return jnp.where(keep[..., None], local, 0.0), keep, fp

    pts, keep, fps = jax.jit(jax.vmap(one_frame))(batch.points, batch.point_valid, batch.targets)
    # Objects cut by the grid edge carry a clipped footprint and lost points: pasted
    # elsewhere, the cut would show mid-grid.
    m = np.asarray(batch.targets.masks)
    edge = (
        m[..., 0, :].any(-1) | m[..., -1, :].any(-1) | m[..., :, 0].any(-1) | m[..., :, -1].any(-1)
    )
    sel = (np.asarray(batch.targets.valid) & ~edge).reshape(-1)
    flat = lambda a: jnp.asarray(np.asarray(a).reshape(-1, *a.shape[2:])[sel])  # noqa: E731
    t = batch.targets
    return ObjectDatabase(
        points=flat(pts),
        point_valid=flat(keep),
        classes=flat(t.classes),
        dims=flat(t.dims),
        z=flat(t.pos)[:, 2],
        footprints=flat(fps),
    )


def _beyond_returns(points: jax.Array, valid: jax.Array, grid: GridConfig) -> jax.Array:
    """bool [H, W]: cells farther from the sensor (the origin) than every valid return in
    their direction: the farthest return of each azimuth bin (half a degree, or wider for a
    point buffer under 5,760: N / 8 bins; an empty bin takes the nearer of its neighbours';
    without either it counts as unseen). Cells just behind a wall may pass (up to the wall's
    range change across a bin, a few cm), whole objects behind it do not."""
    # About 8 points a bin, at most half a degree: a sparse cloud leaves fine bins empty.
    bins = int(np.clip(points.shape[0] // 8, 36, FREE_SPACE_BINS))
    azimuth = jnp.arctan2(points[:, 1], points[:, 0])
    b = jnp.clip(jnp.floor((azimuth + jnp.pi) / (2 * jnp.pi) * bins), 0, bins - 1)
    r = jnp.where(valid, jnp.hypot(points[:, 0], points[:, 1]), 0.0)
    farthest = jnp.zeros(bins).at[b.astype(jnp.int32)].max(r)
    nearer_neighbour = jnp.minimum(jnp.roll(farthest, 1), jnp.roll(farthest, -1))
    farthest = jnp.where(farthest > 0, farthest, nearer_neighbour)
    xs, ys = cell_centers(grid)
    px, py = jnp.meshgrid(xs, ys)  # [H, W]
    cb = jnp.clip(jnp.floor((jnp.arctan2(py, px) + jnp.pi) / (2 * jnp.pi) * bins), 0, bins - 1)
    return jnp.hypot(px, py) > farthest[cb.astype(jnp.int32)]


def gt_sampling(
    key: jax.Array, frame: Batch, database: ObjectDatabase, grid: GridConfig, cfg: AugmentConfig
) -> Batch:
    """Pastes up to ``cfg.gt_sampling`` database objects at random free poses.

    A candidate pose is rejected when its footprint touches any existing or already pasted
    footprint, when more than 5 scene points above floor level fall inside its box (walls,
    unlabelled clutter), or when any footprint cell lies beyond the lidar's returns in its
    direction (``_beyond_returns``: behind the room's walls, where the sensor sees nothing
    and both other tests pass). Pasted objects take free target slots and free point
    slots; scene points under a pasted footprint and inside its height are removed.
    """
    d_count, s = database.footprints.shape[0], database.footprints.shape[1]
    n_attempts = cfg.gt_sampling_attempts
    xs, ys = cell_centers(grid)
    px, py = jnp.meshgrid(xs, ys)  # [H, W]

    def footprint_at(d, x, y, yaw):
        # Grid cell -> object-local patch cell (nearest).
        rel = jnp.stack([px - x, py - y], -1)  # [H, W, 2]
        local = jnp.einsum("ji,hwj->hwi", _rot(yaw), rel)
        b = jnp.floor(local[..., 0] / grid.cell_size + s / 2).astype(jnp.int32)
        a = jnp.floor(local[..., 1] / grid.cell_size + s / 2).astype(jnp.int32)
        ok = (a >= 0) & (a < s) & (b >= 0) & (b < s)
        return database.footprints[d, jnp.clip(a, 0, s - 1), jnp.clip(b, 0, s - 1)] & ok

    def paste(carry, key):
        points, valid, t = carry
        k_d, k_xy, k_yaw = jax.random.split(key, 3)
        d = jax.random.randint(k_d, (), 0, d_count)
        lo = jnp.array([grid.x_range[0], grid.y_range[0]])
        hi = jnp.array([grid.x_range[1], grid.y_range[1]])
        xy = jax.random.uniform(k_xy, (n_attempts, 2), minval=lo, maxval=hi)
        yaw = jax.random.uniform(k_yaw, (n_attempts,), minval=-jnp.pi, maxval=jnp.pi)
        fps = jax.vmap(footprint_at, in_axes=(None, 0, 0, 0))(d, xy[:, 0], xy[:, 1], yaw)
        occupied = (t.masks & t.valid[:, None, None]).any(0)
        hits_object = (fps & occupied).any((1, 2))
        ci, cj, _ = cell_index(points[:, 0], points[:, 1], grid)
        floor_z = database.z[d] - 0.5 * database.dims[d, 2] + FLOOR_MARGIN
        top_z = database.z[d] + 0.5 * database.dims[d, 2]
        in_height = (points[:, 2] > floor_z) & (points[:, 2] <= top_z) & valid  # [N]
        under = fps[:, ci, cj]  # [A, N]
        hits_scene = (under & in_height).sum(1) > SCENE_POINTS_LIMIT
        unseen = (fps & beyond).any((1, 2))
        ok = fps.any((1, 2)) & ~hits_object & ~hits_scene & ~unseen
        pick = jnp.argmax(ok)
        slot = jnp.argmin(t.valid)  # first free target slot
        accept = ok[pick] & ~t.valid[slot]
        fp = fps[pick]
        # Points: drop the scene points the object hides, then fill free slots.
        valid = valid & ~(accept & under[pick] & in_height)
        local = database.points[d]  # [P, 4]
        world_xy = local[:, :2] @ _rot(yaw[pick]).T + xy[pick]
        new = jnp.concatenate(
            [world_xy, local[:, 2:3] + database.z[d], local[:, 3:]], axis=1
        )  # [P, 4]
        new_valid = database.point_valid[d] & accept
        points, valid = _fill_free_slots(points, valid, new, new_valid)
        put = lambda a, v: a.at[slot].set(jnp.where(accept, v, a[slot]))  # noqa: E731
        t = t.replace(
            classes=put(t.classes, database.classes[d]),
            dims=put(t.dims, database.dims[d]),
            pos=put(t.pos, jnp.concatenate([xy[pick], database.z[d][None]])),
            yaw=put(t.yaw, _wrap(yaw[pick])),
            valid=put(t.valid, True),
            masks=put(t.masks, fp),
        )
        return (points, valid, t), None

    beyond = _beyond_returns(frame.points, frame.point_valid, grid)
    keys = jax.random.split(key, cfg.gt_sampling)
    (points, valid, t), _ = jax.lax.scan(
        paste, (frame.points, frame.point_valid, frame.targets), keys
    )
    return _finish(points, valid, t, grid)


@float32_defaults
def augment(
    key: jax.Array,
    frame: Batch,
    grid: GridConfig,
    cfg: AugmentConfig,
    database: ObjectDatabase | None = None,
) -> Batch:
    """The full chain on one frame: GT sampling, box noise, global transform, mask
    perturbation, point noise.

    Args:
      key: a ``jax.random`` key; each step draws from its own split of it.
      frame: one unbatched ``Batch``: points [N, 4], point_valid [N], targets with M slots
        and masks [M, H, W] on ``grid``.
      grid: the BEV grid of the masks.
      cfg: which augmentations run and how strongly (``config.augment``).
      database: objects for ground-truth sampling (``build_object_database``); None or
        ``cfg.gt_sampling`` 0 pastes none.

    Returns:
      The augmented frame, of the same shapes; targets moved out of sight are dropped
      (``drop_lost_objects``).
    """
    k_gt, k_box, k_glob, k_mask, k_pts = jax.random.split(key, 5)
    if database is not None and cfg.gt_sampling:
        frame = gt_sampling(k_gt, frame, database, grid, cfg)
    had_points = _object_points(frame).sum(-1) > 0
    had_centre = _centre_in(frame.targets, grid)
    if cfg.box_noise_prob:
        frame = box_noise(k_box, frame, grid, cfg)
    frame = global_transform(k_glob, frame, grid, cfg)
    if cfg.mask_perturb_prob:
        frame = mask_perturbation(k_mask, frame, grid, cfg)
    frame = point_noise(k_pts, frame, grid, cfg)
    return drop_lost_objects(frame, had_points, grid, had_centre)


def _object_points(frame: Batch) -> jax.Array:
    """bool [M, N]: valid point n lies in the box of valid object m."""
    t = frame.targets
    inside = points_in_boxes(frame.points, t.pos, t.dims, t.yaw, t.valid)
    return inside & frame.point_valid[None, :]


def _centre_in(t: Targets, grid: GridConfig) -> jax.Array:
    return on_grid(t.pos[:, 0], t.pos[:, 1], grid)


def drop_lost_objects(
    frame: Batch, had_points: jax.Array, grid: GridConfig, had_centre: jax.Array | None = None
) -> Batch:
    """Targets an augmentation moved out of sight leave the frame: as the simulator labels
    (``sim/labels.py``), an object stays only with its centre inside the grid (when it was
    inside before, ``had_centre`` [M], default all: a dataset's object centred just off the
    grid is a target, in training as in validation), a non-empty footprint and, when it had
    lidar points before (``had_points`` [M]), at least one still; a rotation near a corner
    would otherwise leave targets with nothing to see."""
    t = frame.targets
    centre_ok = _centre_in(t, grid)
    if had_centre is not None:
        centre_ok |= ~had_centre
    seen = _object_points(frame).any(-1) | ~had_points
    valid = t.valid & centre_ok & t.masks.any((1, 2)) & seen
    return _finish(frame.points, frame.point_valid, t.replace(valid=valid), grid)


@float32_defaults
def augment_batch(
    key: jax.Array,
    batch: Batch,
    grid: GridConfig,
    cfg: AugmentConfig,
    database: ObjectDatabase | None = None,
) -> Batch:
    """``augment`` over a batch, one independent key per frame.

    Args:
      key: a ``jax.random`` key, split into one per frame.
      batch: a ``Batch`` with a leading axis B (points [B, N, 4], masks [B, M, H, W]).
      grid, cfg, database: as for ``augment``.

    Returns:
      The augmented batch, of the same shapes.

    Example::

        batch = augment_batch(jax.random.key(0), batch, config.grid, config.augment)
    """
    check_section("grid", grid, GridConfig, "grid")
    check_section("cfg", cfg, AugmentConfig, "augment")
    keys = jax.random.split(key, batch.points.shape[0])
    return jax.vmap(lambda k, f: augment(k, f, grid, cfg, database))(keys, batch)
