"""Labels of one simulated frame: boxes, true-shape footprints, point counts, occlusion.

Everything is in the lidar frame (x forward, y left, z up, origin at the sensor); for a
tilted lidar (``sim.sensor_rpy``), its level frame, the one the cloud is delivered in.

* Box: the tight box of the object's primitives in its object frame (``objects``), centre
  ``pos``, ``dims`` = (length, width, height), ``yaw`` = object heading minus sensor heading.
* Footprint: the union of the object's primitive footprints rasterised on the BEV grid:
  rectangles, discs/stadiums and ellipses, with the cell rule of
  ``indoorbev_jax.data.rasterize`` (cell centre inside, boundary included; the rectangles
  equal ``box_masks``, tested). Each object is rasterised in a window of cells around it,
  then pasted into the grid. A primitive thinner than one cell is widened to one cell (half
  a cell of radius) first, so thin legs and panels never fall between cell centres.
* Points: a lidar return belongs to the object whose geom the ray hit (``geom_id``);
  ``num_points`` counts the valid returns inside the workspace.
* Occlusion: one extra ray from the sensor to the centre of each of the object's
  primitives; ``visibility`` is the fraction of them whose first hit is the object itself,
  on a ray the sensor could fire (``generate.simulate`` drops rays outside the pattern's
  field of view or within ``sim.min_range``). KITTI level 0 (visibility >= 0.75), 1
  (>= 0.4), 2 (> 0, or seen by points only), 3 (not seen at all).
* Which objects are labelled: placed objects with at least ``sim.min_points`` returns
  whose box centre lies inside the workspace (x, y within the grid). An object crossing the
  workspace edge keeps its full box; its footprint mask is clipped to the grid, and its
  points outside the workspace are invalid like every other point there.
"""

from __future__ import annotations

import functools
import math

import jax
import jax.numpy as jnp
import numpy as np
from flax import struct
from indoorbev_sim import objects
from indoorbev_sim.scenes import (
    OBJECT_SCALE_JITTER,
    Scene,
    SceneTemplate,
    object_poses,
    world_prims,
)

from indoorbev_jax.checks import check_seed, check_whole
from indoorbev_jax.config import Config, GridConfig
from indoorbev_jax.data.rasterize import BOUNDARY_EPS
from indoorbev_jax.geometry import cell_centers, on_grid, wrap_angle
from indoorbev_jax.interrupts import check_interrupted

VISIBLE_FULL, VISIBLE_PART = 0.75, 0.4  # visibility thresholds of occlusion levels 0 and 1


@struct.dataclass
class ObjectLabels:
    """Per-slot labels of one frame (S object slots, before filtering and padding).

    Attributes:
      classes: int32 [S]; dims: float32 [S, 3]; pos: float32 [S, 3]; yaw: float32 [S].
      masks: bool [S, H, W] true-shape footprints.
      num_points: int32 [S] valid returns on the object.
      visibility: float32 [S] in [0, 1]; occlusion: int32 [S] KITTI level 0..3.
      labelled: bool [S], objects that enter the targets.
    """

    classes: jax.Array
    dims: jax.Array
    pos: jax.Array
    yaw: jax.Array
    masks: jax.Array
    num_points: jax.Array
    visibility: jax.Array
    occlusion: jax.Array
    labelled: jax.Array


def _kind_table(tpl: SceneTemplate) -> np.ndarray:
    """Footprint kind (objects.RECT/STADIUM/ELLIPSE, -1 none) of every [S, P] primitive."""
    table = np.full(tpl.prim_geom.shape, -1, np.int32)
    for s, c in enumerate(tpl.slot_class):
        for p, kind in enumerate(objects.CLASSES[c].prims):
            table[s, p] = objects.FOOTPRINT[kind]
    return table


def to_lidar(xy: jax.Array, origin: jax.Array, heading: jax.Array) -> jax.Array:
    """World x, y [..., 2] -> lidar-frame x, y (sensor at ``origin``, facing ``heading``)."""
    c, s = jnp.cos(heading), jnp.sin(heading)
    d = xy - origin[:2]
    return jnp.stack([c * d[..., 0] + s * d[..., 1], -s * d[..., 0] + c * d[..., 1]], -1)


def _prim_masks(kind, dx, dy, yaw, size, pitch, is_hcyl, cell):
    """Masks of n primitives of one footprint kind at cell offsets from their centres.

    Args:
      kind: objects.RECT, STADIUM or ELLIPSE (static).
      dx: float [n, 1, Kw], cell-centre x minus primitive centre x; dy: [n, Kh, 1].
      yaw, pitch: float [n] (lidar frame); size: float [n, 3]; is_hcyl: bool [n] (static).
      cell: cell size; parts thinner than a cell are widened to one cell.

    Returns:
      bool [n, Kh, Kw].
    """
    c, s = jnp.cos(yaw)[:, None, None], jnp.sin(yaw)[:, None, None]
    along, across = c * dx + s * dy, -s * dx + c * dy  # [n, Kh, Kw]
    if kind == objects.RECT:
        # Boxes: half extents (sx, sy); horizontal cylinders: axis along yaw, (half length, r).
        half_l = jnp.where(is_hcyl, size[:, 1], size[:, 0])
        half_w = jnp.where(is_hcyl, size[:, 0], size[:, 1])
        half_l = jnp.maximum(half_l, cell / 2)[:, None, None] + BOUNDARY_EPS
        half_w = jnp.maximum(half_w, cell / 2)[:, None, None] + BOUNDARY_EPS
        return (jnp.abs(along) <= half_l) & (jnp.abs(across) <= half_w)
    if kind == objects.STADIUM:
        # Distance to the projected axis, a segment of half length hl |sin(pitch)| along yaw.
        half = (size[:, 1] * jnp.abs(jnp.sin(pitch)))[:, None, None]
        t = jnp.clip(along, -half, half)
        r = jnp.maximum(size[:, 0], cell / 2)[:, None, None] + BOUNDARY_EPS
        return (along - t) ** 2 + across**2 <= r * r
    a = jnp.maximum(size[:, 0], cell / 2)[:, None, None] + BOUNDARY_EPS
    b = jnp.maximum(size[:, 1], cell / 2)[:, None, None] + BOUNDARY_EPS
    return (along / a) ** 2 + (across / b) ** 2 <= 1.0


@functools.lru_cache(maxsize=8)
def footprint_reach(bank_per_variant: int, cell: float) -> float:
    """Largest distance from an object's centre to any cell its footprint can mark (m)."""
    dims = objects.object_bank(bank_per_variant).dims  # [C, V, K, 3]
    half_diag = float(np.hypot(dims[..., 0], dims[..., 1]).max()) / 2
    return half_diag * (1 + OBJECT_SCALE_JITTER) + cell + 0.05


def footprints(
    tpl: SceneTemplate, scene: Scene, time, origin, heading, grid: GridConfig, reach=None
) -> jax.Array:
    """True-shape footprint of every object slot in the lidar frame.

    With ``reach`` (metres, static: ``footprint_reach``), each object is rasterised in a
    window of cells around its centre that holds its whole footprint and the window is then
    pasted into the grid: on a fine grid that is far less work than testing every cell for
    every primitive. Without it every primitive is tested on the whole grid.

    Returns:
      bool [S, H, W]; all False for slots that hold no object.
    """
    pos, yaw, pitch, on = world_prims(scene, time)  # [S, P, 3], [S, P] x 3
    xy = to_lidar(pos[..., :2], origin, heading)  # [S, P, 2]
    yaw = yaw - heading
    size = scene.prims.size  # [S, P, 3]
    kinds = _kind_table(tpl)
    h, w = grid.shape
    cell = grid.cell_size
    num = tpl.num_slots
    xs, ys = cell_centers(grid)
    k = None if reach is None else 2 * math.ceil(reach / cell) + 2
    window = k is not None and k < min(h, w)
    if window:
        centre = to_lidar(object_poses(scene, time)[:, :2], origin, heading)  # [S, 2]
        j0 = jnp.floor((centre[:, 0] - grid.x_range[0]) / cell).astype(jnp.int32) - k // 2
        i0 = jnp.floor((centre[:, 1] - grid.y_range[0]) / cell).astype(jnp.int32) - k // 2
        wx = grid.x_range[0] + (j0[:, None] + jnp.arange(k) + 0.5) * cell  # [S, K]
        wy = grid.y_range[0] + (i0[:, None] + jnp.arange(k) + 0.5) * cell  # [S, K]
    else:
        wx, wy = jnp.broadcast_to(xs, (num, w)), jnp.broadcast_to(ys, (num, h))
    out = jnp.zeros((num, wy.shape[1], wx.shape[1]), bool)
    for kind in (objects.RECT, objects.STADIUM, objects.ELLIPSE):
        ss, pp = np.nonzero(kinds == kind)  # static primitive list of this kind
        if not len(ss):
            continue
        is_hcyl = np.array([objects.CLASSES[tpl.slot_class[s]].prims[p] == "hcyl"
                            for s, p in zip(ss, pp, strict=True)])  # fmt: skip
        kxy = xy[ss, pp]  # [n, 2]
        dx = wx[ss][:, None, :] - kxy[:, 0, None, None]  # [n, 1, Kw]
        dy = wy[ss][:, :, None] - kxy[:, 1, None, None]  # [n, Kh, 1]
        m = _prim_masks(kind, dx, dy, yaw[ss, pp], size[ss, pp], pitch[ss, pp], is_hcyl, cell)
        out = out.at[ss].max(m & on[ss, pp][:, None, None])
    if not window:
        return out
    # Paste each window into a grid padded by K on every side; a window that misses the
    # grid entirely is blanked (its start index would otherwise be clamped into view).
    overlaps = (i0 > -k) & (i0 < h) & (j0 > -k) & (j0 < w)
    out = out & overlaps[:, None, None]
    i0, j0 = jnp.clip(i0, -k, h) + k, jnp.clip(j0, -k, w) + k
    canvas = jnp.zeros((h + 2 * k, w + 2 * k), bool)
    paste = jax.vmap(lambda win, i, j: jax.lax.dynamic_update_slice(canvas, win, (i, j)))
    return paste(out, i0, j0)[:, k : k + h, k : k + w]  # [S, H, W]


def box_labels(scene: Scene, time, origin, heading):
    """Boxes of every slot in the lidar frame: pos [S, 3], dims [S, 3], yaw [S]."""
    pose = object_poses(scene, time)  # [S, 3]
    xy = to_lidar(pose[:, :2], origin, heading)
    z = scene.prims.dims[:, 2] / 2 - origin[2]
    pos = jnp.concatenate([xy, z[:, None]], -1)
    return pos, scene.prims.dims, wrap_angle(pose[:, 2] - heading)


def visibility_targets(scene: Scene, time) -> tuple[jax.Array, jax.Array]:
    """World centres [S * P, 3] of all primitives (rays aim at them) and which are on."""
    pos, _, _, on = world_prims(scene, time)
    return pos.reshape(-1, 3), on.reshape(-1)  # [S * P, 3], [S * P]


def occlusion_level(visibility: jax.Array, num_points: jax.Array) -> jax.Array:
    return jnp.select(
        [
            visibility >= VISIBLE_FULL,
            visibility >= VISIBLE_PART,
            (visibility > 0) | (num_points > 0),
        ],
        [0, 1, 2],
        3,
    ).astype(jnp.int32)


def object_labels(
    tpl: SceneTemplate,
    scene: Scene,
    time,
    origin: jax.Array,
    heading: jax.Array,
    point_slot: jax.Array,
    point_valid: jax.Array,
    vis_slot: jax.Array,
    config: Config,
) -> ObjectLabels:
    """Per-slot labels of one frame.

    Args:
      tpl, scene, time: the scene and the frame's time in seconds.
      origin: float [3] sensor position (world); heading: float [] sensor yaw.
      point_slot: int32 [R], object slot hit by each ray (-1: background or miss).
      point_valid: bool [R], valid returns inside the workspace.
      vis_slot: int32 [S * P], object slot first hit by the visibility ray of each primitive.
      config: the run configuration (grid, ``sim.min_points``).

    Returns:
      ``ObjectLabels`` with [S] leading axes.
    """
    s = tpl.num_slots
    grid = config.grid
    counts = jax.ops.segment_sum(
        point_valid.astype(jnp.int32), jnp.where(point_valid, point_slot, s), num_segments=s + 1
    )[:s]
    _, _, _, prim_on = world_prims(scene, time)
    own = jnp.arange(s)[:, None]
    seen = (vis_slot.reshape(s, -1) == own) & prim_on  # [S, P]
    visibility = seen.sum(-1) / jnp.maximum(prim_on.sum(-1), 1)
    pos, dims, yaw = box_labels(scene, time, origin, heading)
    inside = on_grid(pos[:, 0], pos[:, 1], grid)
    labelled = scene.on & inside & (counts >= config.sim.min_points)
    return ObjectLabels(
        classes=jnp.asarray(tpl.slot_class),
        dims=dims,
        pos=pos,
        yaw=yaw,
        masks=footprints(
            tpl,
            scene,
            time,
            origin,
            heading,
            grid,
            footprint_reach(config.sim.bank_per_variant, grid.cell_size),
        ),  # fmt: skip
        num_points=counts,
        visibility=visibility,
        occlusion=occlusion_level(visibility, counts),
        labelled=labelled,
    )


# ------------------------------------------------------------- consistency checks (numpy)


def dilate(mask: np.ndarray, cells: int = 1) -> np.ndarray:
    """Binary dilation of bool [..., H, W] by a (2 cells + 1)^2 square."""
    out = mask.copy()
    h, w = mask.shape[-2:]
    padded = np.pad(mask, [(0, 0)] * (mask.ndim - 2) + [(cells, cells), (cells, cells)])
    for di in range(2 * cells + 1):
        for dj in range(2 * cells + 1):
            out |= padded[..., di : di + h, dj : dj + w]
    return out


def point_footprint_agreement(batch, info, grid: GridConfig) -> list[dict]:
    """For every target object: its points inside its own footprint dilated by one cell, and
    inside any other object's footprint.

    Args:
      batch, info: ``Batch`` and ``FrameInfo`` of B frames (numpy or jax arrays).

    Points in the outermost ring of cells are left out (counted in ``edge``): there the
    footprint of an object crossing the workspace edge may lie beyond the grid, where the
    dilation cannot reach it.

    Returns:
      one dict per object: class, points, in_own (dilated), in_other, edge, occlusion.
    """
    points = np.asarray(batch.points)
    owner = np.asarray(info.point_object)
    masks = np.asarray(batch.targets.masks)
    valid_t = np.asarray(batch.targets.valid)
    out = []
    h, w = grid.shape
    for b in range(points.shape[0]):
        own_d = dilate(masks[b])
        j = np.floor((points[b, :, 0] - grid.x_range[0]) / grid.cell_size).astype(int)
        i = np.floor((points[b, :, 1] - grid.y_range[0]) / grid.cell_size).astype(int)
        i, j = np.clip(i, 0, h - 1), np.clip(j, 0, w - 1)
        border = (i == 0) | (i == h - 1) | (j == 0) | (j == w - 1)
        for k in np.flatnonzero(valid_t[b]):
            edge = int(((owner[b] == k) & border).sum())
            sel = (owner[b] == k) & ~border
            others = np.delete(masks[b], k, axis=0)
            in_other = (
                others[:, i[sel], j[sel]].any(0) if len(others) else np.zeros(sel.sum(), bool)
            )
            out.append({
                "class": int(batch.targets.classes[b, k]),
                "points": int(sel.sum()),
                "in_own": int(own_d[k, i[sel], j[sel]].sum()),
                "in_other": int(in_other.sum()),
                "edge": edge,
                "occlusion": int(info.occlusion[b, k]),
            })  # fmt: skip
    return out


def check(config: Config, frames: int, batch_size: int, seed: int, split: str = "train") -> str:
    """Generates ``frames`` frames and reports the done-when statistics as text: points in
    their own dilated footprint / in another's, and objects per class.

    Raises:
      ValueError: ``frames`` or ``batch_size`` is not a whole number > 0, or ``seed`` not
        one in [0, 2**32) (named).
    """
    import time

    check_whole("frames", frames, 1)
    check_whole("batch_size", batch_size, 1)
    check_seed("seed", seed)

    import jax
    from indoorbev_sim import generate

    fn = generate.jitted_generate(config, split, batch_size)
    rows, frames_done, t0 = [], 0, time.time()
    counts = np.zeros(config.num_classes, int)
    frames_with = np.zeros(config.num_classes, int)
    key = jax.random.key(seed)
    while frames_done < frames:
        check_interrupted()
        batch, info = fn(jax.random.fold_in(key, frames_done))
        n = min(batch_size, frames - frames_done)
        batch, info = jax.tree.map(lambda x, n=n: np.asarray(x)[:n], (batch, info))
        rows += point_footprint_agreement(batch, info, config.grid)
        for b in range(n):
            cls = batch.targets.classes[b][batch.targets.valid[b]]
            counts += np.bincount(cls, minlength=config.num_classes)
            frames_with += np.bincount(np.unique(cls), minlength=config.num_classes)
        frames_done += n
    pts = np.array([r["points"] for r in rows])
    own = np.array([r["in_own"] for r in rows])
    other = np.array([r["in_other"] for r in rows])
    edge = sum(r["edge"] for r in rows)
    frac = own / np.maximum(pts, 1)
    # No points on labelled objects (a tiny data.max_points): nothing to check, not 0 %.
    inside = f"{own.sum() / pts.sum():.5f}" if pts.sum() else "n/a (no points on objects)"
    whole = f"{(frac >= 0.99).mean():.5f} (min fraction {frac.min():.4f})" if len(frac) else "n/a"
    lines = [
        f"{frames} frames ({config.name}, split {split}, cell {config.grid.cell_size} m, "
        f"range noise {config.sim.range_noise} m, dropout {config.sim.dropout}), "
        f"{time.time() - t0:.0f} s",
        f"labelled objects: {len(rows)}, points on them: {pts.sum()} "
        f"(+ {edge} in the outermost cell ring, left out)",
        f"points inside own footprint dilated by 1 cell: {inside}",
        f"objects with >= 99% of their points inside: {whole}",
        f"points inside another object's footprint: {other.sum()} "
        f"(objects affected: {(other > 0).sum()})",
        "class       objects  frames_with",
    ]
    for c, name in enumerate(config.data.class_names):
        lines.append(f"{name:<10} {counts[c]:>8} {frames_with[c]:>12}")
    return "\n".join(lines)
