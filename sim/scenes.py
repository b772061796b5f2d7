"""Batched procedural scenes: a fixed-capacity MuJoCo template randomised per scene.

The template (``SceneTemplate``) is one MuJoCo model with a floor plane, a ceiling slab,
eight wall boxes and, for every *object slot*, one geom per primitive slot of the slot's
class (``objects.CLASSES``). Geom types never change; a scene sets every geom's size and
world pose (``geom_state``), and a slot or primitive that is off is parked far below the
floor with a tiny size, beyond any ray's reach. So B scenes are B copies of the same model
whose ``geom_size`` and data ``geom_xpos``/``geom_xmat`` differ: static shapes, one jitted
ray cast for the batch.

``sample_scene`` draws one scene (vmap it for B): a floor plan (layouts.py), how many
objects of each class, their variants, dimensions and reflectivity, collision-free poses
with clearance, straight-line motion for persons and robots, and the path of the mobile
robot carrying the lidar. Moving objects and the sensor reserve their whole swept path
over the sequence, so nothing ever collides or overlaps in any frame of it.
"""

from __future__ import annotations

import dataclasses
import functools
import math

import jax
import jax.numpy as jnp
import mujoco
import numpy as np
from flax import struct
from indoorbev_sim import layouts, objects
from indoorbev_sim.objects import CLASSES, MAX_PRIMS, MJCF_TYPE

from indoorbev_jax.config import Config, SimConfig

FLOOR, CEILING = 0, 1
FIRST_WALL = 2
FIRST_OBJECT = FIRST_WALL + layouts.NUM_WALL_GEOMS
PARK_Z = -1000.0  # where geoms that are off wait, far beyond every max_range
PARK_SIZE = 1e-3
# Placement order: big, wall-bound furniture first, clutter last.
PLACE_ORDER = ("Shelf", "Cabinet", "Sofa", "Table", "Robot", "Person", "Chair", "Box", "Misc")
EGO_RADIUS = 0.4  # footprint radius reserved around the robot carrying the lidar
WALL_GAP = (0.03, 0.12)  # distance between a wall and an object placed against it
OBJECT_SCALE_JITTER = 0.05  # bank objects are rescaled by up to +-5 %
TILT_STREAM = 1  # fold_in of a scene's key that draws its lidar tilt


@dataclasses.dataclass(frozen=True, eq=False)
class SceneTemplate:
    """The static part of every scene (hashable by identity for ``jax.jit`` closures).

    Attributes:
      slot_class: int [S], class of each object slot.
      prim_geom: int [S, P], geom index of each primitive slot, -1 where the class has none.
      geom_slot: int [G], object slot of each geom, -1 for floor, ceiling and walls.
      geom_kind: primitive kind of each geom ("plane", "box", "cyl", ...).
      mj_model: the MuJoCo model (geoms at rest).
    """

    slot_class: np.ndarray
    prim_geom: np.ndarray
    geom_slot: np.ndarray
    geom_kind: tuple[str, ...]
    mj_model: mujoco.MjModel

    @property
    def num_slots(self) -> int:
        return len(self.slot_class)

    @property
    def num_geoms(self) -> int:
        return len(self.geom_kind)

    def mjx_model(self):
        """The template as a real ``mjx.Model`` (imports ``mujoco.mjx``: ~5-15 s on a CPU)."""
        from mujoco import mjx

        return mjx.put_model(self.mj_model)


@struct.dataclass
class GeomModel:
    """The ``mjx.Model`` fields the lidar reads, for B scenes sharing one template.

    ``indoorbev_sim.lidar`` reads geoms through these names only, so generation hands it this
    view instead of a full ``mjx.Model`` and never imports ``mujoco.mjx`` (whose import alone
    takes 5-15 s here). ``to_mjx`` builds the real MJX model/data of the same scenes.
    """

    geom_size: jax.Array  # float32 [B, G, 3] (or [G, 3]: one scene)
    geom_rgba: jax.Array  # float32 [G, 4]
    geom_matid: jax.Array  # int32 [G]
    mat_rgba: jax.Array  # float32 [nmat, 4] (none in generated scenes)
    geom_type: np.ndarray = struct.field(pytree_node=False)  # [G], static
    geom_bodyid: np.ndarray = struct.field(pytree_node=False)
    geom_group: np.ndarray = struct.field(pytree_node=False)
    body_weldid: np.ndarray = struct.field(pytree_node=False)
    nbody: int = struct.field(pytree_node=False, default=1)


@struct.dataclass
class GeomData:
    """The ``mjx.Data`` fields the lidar reads: ``geom_xpos`` [B, G, 3], ``geom_xmat``."""

    geom_xpos: jax.Array
    geom_xmat: jax.Array


def geom_model(tpl: SceneTemplate, size: jax.Array) -> GeomModel:
    """Model view of B scenes with geom sizes ``size`` [B, G, 3]."""
    return geom_model_of(tpl.mj_model, size)


def geom_model_of(m: mujoco.MjModel, size: jax.Array) -> GeomModel:
    """Model view of the geoms of ``m`` with sizes ``size`` ([G, 3], or [B, G, 3] for B
    scenes), materials included (alpha 0 hides a geom, as in ``mj_ray``)."""
    return GeomModel(
        geom_size=size,
        geom_rgba=jnp.asarray(m.geom_rgba, jnp.float32),
        geom_matid=jnp.asarray(m.geom_matid, jnp.int32),
        mat_rgba=jnp.asarray(m.mat_rgba, jnp.float32).reshape(-1, 4),
        geom_type=np.asarray(m.geom_type),
        geom_bodyid=np.asarray(m.geom_bodyid),
        geom_group=np.asarray(m.geom_group),
        body_weldid=np.asarray(m.body_weldid),
        nbody=m.nbody,
    )


def to_mjx(tpl: SceneTemplate, size: jax.Array, xpos: jax.Array, xmat: jax.Array):
    """Real MJX model/data of B posed scenes: ``geom_size`` and data geom poses batched."""
    from mujoco import mjx

    model = tpl.mjx_model().replace(geom_size=size)
    data = mjx.put_data(tpl.mj_model, mujoco.MjData(tpl.mj_model))
    return model, data.replace(geom_xpos=xpos, geom_xmat=xmat)


@functools.lru_cache(maxsize=8)
def make_template(slots_per_class: tuple[int, ...]) -> SceneTemplate:
    """Builds (and caches) the template for the given slot count per class."""
    if len(slots_per_class) != objects.NUM_CLASSES:
        raise ValueError(
            f"sim.slots_per_class: expected {objects.NUM_CLASSES} entries, "
            f"got {len(slots_per_class)}"
        )
    kinds = ["plane", "box"] + ["box"] * layouts.NUM_WALL_GEOMS
    slot_class, prim_geom, geom_slot = [], [], [-1] * len(kinds)
    for name in PLACE_ORDER:
        c = objects.CLASS_INDEX[name]
        for _ in range(slots_per_class[c]):
            row = [-1] * MAX_PRIMS
            for p, kind in enumerate(CLASSES[c].prims):
                row[p] = len(kinds)
                kinds.append(kind)
                geom_slot.append(len(slot_class))
            slot_class.append(c)
            prim_geom.append(row)
    geoms = ['<geom type="plane" size="40 40 1"/>']
    for kind in kinds[1:]:
        mj = MJCF_TYPE[kind]
        size = {"box": ".1 .1 .1", "ellipsoid": ".1 .1 .1", "sphere": ".1"}.get(mj, ".1 .1")
        geoms.append(f'<geom type="{mj}" size="{size}" pos="0 0 {PARK_Z}"/>')
    xml = (
        '<mujoco model="indoorbev_scene"><default><geom contype="0" conaffinity="0"/></default>'
        f"<worldbody>{''.join(geoms)}</worldbody></mujoco>"
    )
    return SceneTemplate(
        slot_class=np.asarray(slot_class, np.int32),
        prim_geom=np.asarray(prim_geom, np.int32).reshape(-1, MAX_PRIMS),
        geom_slot=np.asarray(geom_slot, np.int32),
        geom_kind=tuple(kinds),
        mj_model=mujoco.MjModel.from_xml_string(xml),
    )


def template_for(config: Config) -> SceneTemplate:
    return make_template(tuple(config.sim.slots_per_class))


@struct.dataclass
class Scene:
    """One sampled scene (batched: leading axes). S object slots, P primitive slots.

    Attributes:
      room: ``layouts.Room``.
      on: bool [S], slots holding an object.
      variant: int32 [S].
      prims: ``objects.Prims`` with [S, P] leading axes (object frames).
      reflectivity: float32 [S] per object; background: float32 [3] (floor, ceiling, walls).
      pose: float32 [S, 3], (x, y, yaw) in the world at frame 0.
      velocity: float32 [S, 2], world m/s (zero for static objects).
      ego: float32 [3], (x, y, heading) of the lidar robot at frame 0; ego_velocity [2].
      sensor_height: float32 [], lidar height above the floor.
      sensor_rpy: float32 [3], the lidar's roll, pitch, yaw in the robot's level frame,
        degrees (``sim.sensor_rpy``, tilted by up to ``sim.sensor_tilt_jitter``).
    """

    room: layouts.Room
    on: jax.Array
    variant: jax.Array
    prims: objects.Prims
    reflectivity: jax.Array
    background: jax.Array
    pose: jax.Array
    velocity: jax.Array
    ego: jax.Array
    ego_velocity: jax.Array
    sensor_height: jax.Array
    sensor_rpy: jax.Array


# How far below the lowest ceiling the lidar must stay: the sensor's body (a MID-360 is 6.5 cm
# tall) under the slab. Not sim.min_range: a blind zone larger than the gap to the ceiling
# only drops the returns straight up.
CEILING_CLEARANCE = 0.1


def check_sensor_height(sim: SimConfig) -> None:
    """Raises ``ValueError`` when ``sim.sensor_height`` reaches within ``CEILING_CLEARANCE``
    of the lowest ceiling of ``sim.layouts``: a lidar in or above the ceiling slab sees no
    object, and its frames would come out without targets, unannounced."""
    kinds = [layouts.LAYOUTS[layouts.LAYOUT_INDEX[k]] for k in sim.layouts]
    lowest = min(k.ceiling[0] for k in kinds)
    if sim.sensor_height[1] > lowest - CEILING_CLEARANCE:
        low = [k.name for k in kinds if k.ceiling[0] == lowest]
        raise ValueError(
            f"sim.sensor_height: up to {sim.sensor_height[1]} m reaches the ceiling: the lowest "
            f"ceilings ({', '.join(low)} rooms) are {lowest} m, so the lidar must stay at or below "
            f"{lowest - CEILING_CLEARANCE:.2f} m ({CEILING_CLEARANCE} m under the ceiling "
            f"slab); or leave {', '.join(low)} out of sim.layouts"
        )


def check_settings(sim: SimConfig) -> None:
    """Raises ``ValueError``, naming the field, for settings no scene can be drawn from (a
    ceiling below the lidar, every plan or a class's every variant held out, an unknown
    variant): what ``sample_scene`` would raise when traced, said before a run writes its
    settings (an export.json or config.json of them would refuse the corrected rerun)."""
    check_sensor_height(sim)
    for split in ("train", "test"):
        allowed_plans(sim, split)
        allowed_variants(sim, split)


def allowed_plans(sim: SimConfig, split: str) -> np.ndarray:
    """Plan ids a split draws from: test the held-out plans, train/val all others."""
    n = len(layouts.LAYOUTS) * sim.plans_per_layout
    held = sorted({layouts.plan_id(name, sim.plans_per_layout) for name in sim.test_layouts})
    kinds = [layouts.LAYOUT_INDEX[k] for k in sim.layouts]
    pool = [p for p in range(n) if p // sim.plans_per_layout in kinds]
    if split == "test":
        out = [p for p in held if p in pool] or pool  # no held-out plans: all of them
    elif split in ("train", "val"):
        out = [p for p in pool if p not in held]
    else:
        raise ValueError(f"split: expected 'train', 'val' or 'test', got {split!r}")
    if not out:
        raise ValueError(f"sim.test_layouts holds out every plan of sim.layouts {sim.layouts}")
    return np.asarray(out, np.int32)


def held_out_by_layout(sim: SimConfig) -> bool:
    """Whether the test split's plans are all kept out of train and val. False when no plan
    of ``sim.test_layouts`` lies in ``sim.layouts``: test then draws the training plans."""
    try:
        train = allowed_plans(sim, "train")
    except ValueError:  # every plan held out
        return True
    return not np.isin(allowed_plans(sim, "test"), train).any()


HELD_OUT_NOTE = (
    "note: no plan of sim.test_layouts {held} lies in sim.layouts {kinds}, so the test split "
    "draws the training plans: its frames are not held out by layout"
)


def held_out_note(sim: SimConfig) -> str | None:
    """``HELD_OUT_NOTE`` for ``sim`` when its test plans are the training plans, else None."""
    if held_out_by_layout(sim):
        return None
    return HELD_OUT_NOTE.format(held=list(sim.test_layouts), kinds=list(sim.layouts))


def allowed_variants(sim: SimConfig, split: str) -> np.ndarray:
    """bool [NUM_CLASSES, max variants]: which variants a split may draw."""
    vmax = max(len(c.variants) for c in CLASSES)
    mask = np.zeros((objects.NUM_CLASSES, vmax), bool)
    for c, spec in enumerate(CLASSES):
        mask[c, : len(spec.variants)] = True
    for name in sim.test_variants:
        if name not in objects.ALL_VARIANTS:
            raise ValueError(
                f"sim.test_variants: unknown variant '{name}', expected one of "
                f"{list(objects.ALL_VARIANTS)}"
            )
        if split != "test":
            cls, _, var = name.partition("/")
            c = objects.CLASS_INDEX[cls]
            mask[c, CLASSES[c].variants.index(var)] = False
    for c in range(objects.NUM_CLASSES):
        if not mask[c].any():
            raise ValueError(f"sim.test_variants holds out every variant of {CLASSES[c].name}")
    return mask


def _rot2(yaw):
    c, s = jnp.cos(yaw), jnp.sin(yaw)
    return jnp.stack([jnp.stack([c, -s], -1), jnp.stack([s, c], -1)], -2)  # [..., 2, 2]


def _segment_distance(p0, p1, q0, q1):
    """Distance between 2D segments p0-p1 and q0-q1 (broadcasting over leading axes)."""

    def point_seg(x, a, b):
        ab = b - a
        t = jnp.clip(jnp.sum((x - a) * ab, -1) / jnp.maximum(jnp.sum(ab * ab, -1), 1e-12), 0, 1)
        return jnp.linalg.norm(x - (a + t[..., None] * ab), axis=-1)

    def cross(a, b):
        return a[..., 0] * b[..., 1] - a[..., 1] * b[..., 0]

    d = jnp.minimum(
        jnp.minimum(point_seg(p0, q0, q1), point_seg(p1, q0, q1)),
        jnp.minimum(point_seg(q0, p0, p1), point_seg(q1, p0, p1)),
    )
    # Proper crossing: endpoints on opposite sides of each other's lines.
    r, s = p1 - p0, q1 - q0
    crosses = (cross(r, q0 - p0) * cross(r, q1 - p0) < 0) & (
        cross(s, p0 - q0) * cross(s, p1 - q0) < 0
    )
    return jnp.where(crosses, 0.0, d)


def _footprint_capsule(dims, x, y, yaw):
    """A capsule (p0, p1, radius) holding the object's l x w rectangle."""
    length, width = dims[..., 0], dims[..., 1]
    along = jnp.where(length >= width, 0.0, math.pi / 2) + yaw
    half = jnp.abs(length - width) / 2
    d = jnp.stack([jnp.cos(along), jnp.sin(along)], -1) * half[..., None]
    centre = jnp.stack([x, y], -1)
    return centre - d, centre + d, jnp.minimum(length, width) / math.sqrt(2)


def _corners_inside(dims, xy, yaw, half_room, margin):
    """Whether the l x w rectangle at (xy, yaw) lies inside [-half_room + m, half_room - m]."""
    hl, hw = dims[..., 0] / 2, dims[..., 1] / 2
    ext_x = jnp.abs(jnp.cos(yaw)) * hl + jnp.abs(jnp.sin(yaw)) * hw
    ext_y = jnp.abs(jnp.sin(yaw)) * hl + jnp.abs(jnp.cos(yaw)) * hw
    ext = jnp.stack([ext_x, ext_y], -1)
    return jnp.all(jnp.abs(xy) + ext <= half_room - margin, axis=-1)


def split_flag(split: str) -> bool:
    """True for the test split (held-out plans and variants allowed), False for train/val."""
    if split not in ("train", "val", "test"):
        raise ValueError(f"split: expected 'train', 'val' or 'test', got {split!r}")
    return split == "test"


def sample_scene(key: jax.Array, config: Config, test=False) -> Scene:
    """Draws one scene; ``jax.vmap`` over keys for a batch.

    Args:
      key: PRNG key.
      config: run configuration (static).
      test: bool (Python or traced): draw from the test split's plans and variants instead of
        the train/val ones (``split_flag``).
    """
    sim = config.sim
    check_sensor_height(sim)
    tpl = template_for(config)
    num_slots = tpl.num_slots
    frames_span = (sim.frames_per_sequence - 1) * sim.frame_dt  # seconds from first to last
    test = jnp.asarray(test, bool)
    pools = [allowed_plans(sim, name) for name in ("train", "test")]
    vmask = jnp.where(
        test,
        jnp.asarray(allowed_variants(sim, "test")),
        jnp.asarray(allowed_variants(sim, "train")),
    )
    tries = sim.placement_tries
    # All randomness in one draw (every PRNG call costs compile time), sliced in order.
    sizes = {
        "plan": (), "counts": (objects.NUM_CLASSES,), "variant": (num_slots,),
        "shape": (num_slots, 2), "refl": (num_slots,), "background": (3,),
        "ego": (tries, 4), "height": (), "place": (num_slots, tries, 8),
    }  # fmt: skip
    flat = jax.random.uniform(key, (sum(math.prod(v) for v in sizes.values()),))
    draws, at = {}, 0
    for name, shape in sizes.items():
        draws[name] = flat[at : at + math.prod(shape)].reshape(shape)
        at += math.prod(shape)
    pid = jnp.where(
        test,
        jnp.asarray(pools[1])[jnp.floor(draws["plan"] * len(pools[1])).astype(jnp.int32)],
        jnp.asarray(pools[0])[jnp.floor(draws["plan"] * len(pools[0])).astype(jnp.int32)],
    )
    room = layouts.make_room(pid, sim.plans_per_layout)
    half_room = room.size / 2

    # Objects wanted per class, their variants, shapes and reflectivity.
    counts = layouts.class_counts(draws["counts"], room.kind, tuple(sim.slots_per_class))
    slot_class = jnp.asarray(tpl.slot_class)
    rank = jnp.asarray(
        [int(np.sum(tpl.slot_class[:s] == tpl.slot_class[s])) for s in range(num_slots)]
    )
    wanted = rank < counts[slot_class]
    # Variant: the k-th allowed one, k uniform over the allowed count.
    allowed = vmask[slot_class]  # [S, V]
    k = jnp.floor(draws["variant"] * allowed.sum(-1)).astype(jnp.int32)
    variant = jnp.argmax(jnp.cumsum(allowed, -1) > k[:, None], axis=-1).astype(jnp.int32)
    # Shapes: an instance of the variant from the object bank, rescaled by a few percent
    # (all primitive sizes and offsets scale together, so the shape stays valid).
    bank = objects.object_bank(sim.bank_per_variant)
    pick = jnp.floor(draws["shape"][:, 0] * sim.bank_per_variant).astype(jnp.int32)
    scale = 1.0 + OBJECT_SCALE_JITTER * (2 * draws["shape"][:, 1] - 1)  # [S]
    prims = jax.tree.map(lambda x: jnp.asarray(x)[slot_class, variant, pick], bank)
    prims = prims.replace(
        size=prims.size * scale[:, None, None],
        pos=prims.pos * scale[:, None, None],
        dims=prims.dims * scale[:, None],
    )  # fields [S, P, ...]
    refl_lo = jnp.asarray([c.reflectivity[0] for c in CLASSES])[slot_class]
    refl_hi = jnp.asarray([c.reflectivity[1] for c in CLASSES])[slot_class]
    reflectivity = refl_lo + (refl_hi - refl_lo) * draws["refl"]
    # Floor, ceiling, walls.
    background = jnp.array([0.1, 0.5, 0.5]) + jnp.array([0.3, 0.4, 0.4]) * draws["background"]

    # The lidar robot: a straight path inside the room (standing still when none fits).
    ue = draws["ego"]
    start = (ue[:, :2] * 2 - 1) * (half_room - 0.6)
    heading = (ue[:, 2] * 2 - 1) * math.pi
    speed = sim.ego_speed[0] + (sim.ego_speed[1] - sim.ego_speed[0]) * ue[:, 3]
    vel = jnp.stack([jnp.cos(heading), jnp.sin(heading)], -1) * speed[:, None]
    ok = jnp.all(jnp.abs(start + vel * frames_span) <= half_room - 0.6, axis=-1)
    pick = jnp.argmax(ok)
    ego_vel = jnp.where(ok[pick], vel[pick], 0.0)
    ego = jnp.concatenate([start[pick], heading[pick, None]])
    lo, hi = sim.sensor_height
    sensor_height = lo + (hi - lo) * draws["height"]
    sensor_rpy = jnp.asarray(sim.sensor_rpy, jnp.float32)
    if sim.sensor_tilt_jitter:
        # A key of its own: the draws above, and so every existing dataset, stay as they were.
        u = jax.random.uniform(jax.random.fold_in(key, TILT_STREAM), (2,))
        radius, turn = sim.sensor_tilt_jitter * jnp.sqrt(u[0]), 2 * math.pi * u[1]
        sensor_rpy = sensor_rpy.at[:2].add(radius * jnp.stack([jnp.cos(turn), jnp.sin(turn)]))

    # Collision-free placement, one slot after the other; entry 0 of the reserved capsules
    # is the lidar robot's path.
    wall_prob = jnp.asarray([c.wall_prob for c in CLASSES])[slot_class]
    speed_lo = jnp.asarray([c.speed[0] for c in CLASSES])[slot_class]
    speed_hi = jnp.asarray([c.speed[1] for c in CLASSES])[slot_class]
    # Standing persons stay put.
    moving = (jnp.asarray([c.dynamic for c in CLASSES])[slot_class]) & (
        jnp.where(slot_class == objects.CLASS_INDEX["Person"], variant == 1, True)
    )
    cap = min(sim.max_scene_objects, config.data.max_objects)
    reserved = (
        jnp.zeros((num_slots + 1, 2)).at[0].set(ego[:2]),
        jnp.zeros((num_slots + 1, 2)).at[0].set(ego[:2] + ego_vel * frames_span),
        jnp.zeros(num_slots + 1).at[0].set(EGO_RADIUS),
        jnp.zeros(num_slots + 1, bool).at[0].set(True),
    )

    def place(carry, inputs):
        (p0s, p1s, rs, used), placed = carry
        s, up = inputs  # up: [tries, 8] uniforms
        dims = prims.dims[s]
        # Candidate poses: against a wall (back to it) or free.
        wall = jnp.minimum(jnp.floor(up[:, 0] * 4), 3).astype(jnp.int32)
        along = up[:, 1] * 2 - 1
        gap = WALL_GAP[0] + (WALL_GAP[1] - WALL_GAP[0]) * up[:, 2]
        off = dims[1] / 2 + gap
        hx, hy = half_room[0], half_room[1]
        wx = jnp.select(
            [wall == 0, wall == 1, wall == 2], [along * hx, along * hx, -hx + off], hx - off
        )
        wy = jnp.select(
            [wall == 0, wall == 1, wall == 2], [-hy + off, hy - off, along * hy], along * hy
        )
        wyaw = jnp.select(
            [wall == 0, wall == 1, wall == 2], [0.0, math.pi, -math.pi / 2], math.pi / 2
        )
        free_xy = (up[:, 3:5] * 2 - 1) * half_room
        free_yaw = (up[:, 5] * 2 - 1) * math.pi
        at_wall = up[:, 6] < wall_prob[s]
        xy = jnp.where(at_wall[:, None], jnp.stack([wx, wy], -1), free_xy)  # [tries, 2]
        yaw = jnp.where(at_wall, wyaw, free_yaw)
        spd = speed_lo[s] + (speed_hi[s] - speed_lo[s]) * up[:, 7]
        vel = jnp.stack([jnp.cos(yaw), jnp.sin(yaw)], -1) * (spd * moving[s])[:, None]
        end = xy + vel * frames_span
        inside = _corners_inside(dims, xy, yaw, half_room, 0.02) & _corners_inside(
            dims, end, yaw, half_room, 0.02
        )
        a0, a1, ar = _footprint_capsule(dims, xy[:, 0], xy[:, 1], yaw)
        # A moving object reserves the capsule swept by its bounding circle.
        swept_r = jnp.hypot(dims[0], dims[1]) / 2
        is_moving = jnp.any(vel != 0, axis=-1)
        a0 = jnp.where(is_moving[:, None], xy, a0)
        a1 = jnp.where(is_moving[:, None], end, a1)
        ar = jnp.where(is_moving, swept_r, ar)
        dist = _segment_distance(a0[:, None], a1[:, None], p0s[None], p1s[None])  # [tries, S+1]
        clear = dist - ar[:, None] - rs[None] >= sim.clearance
        ok = inside & jnp.all(clear | ~used[None], axis=-1)
        pick = jnp.argmax(ok)
        on = wanted[s] & ok[pick] & (placed < cap)
        upd = lambda arr, v: arr.at[s + 1].set(jnp.where(on, v, arr[s + 1]))  # noqa: E731
        carry = ((upd(p0s, a0[pick]), upd(p1s, a1[pick]), upd(rs, ar[pick]),
                  used.at[s + 1].set(on)), placed + on)  # fmt: skip
        pose = jnp.concatenate([xy[pick], yaw[pick, None]])
        return carry, (on, pose, jnp.where(on, vel[pick], 0.0))

    _, (on, pose, velocity) = jax.lax.scan(
        place, (reserved, jnp.int32(0)), (jnp.arange(num_slots), draws["place"])
    )
    return Scene(
        room=room, on=on, variant=variant, prims=prims, reflectivity=reflectivity,
        background=background, pose=pose, velocity=velocity, ego=ego, ego_velocity=ego_vel,
        sensor_height=sensor_height, sensor_rpy=sensor_rpy,
    )  # fmt: skip


def object_poses(scene: Scene, time: jax.Array) -> jax.Array:
    """(x, y, yaw) of every slot at ``time`` seconds; [..., S, 3]."""
    xy = scene.pose[..., :2] + scene.velocity * jnp.asarray(time)[..., None, None]
    return jnp.concatenate([xy, scene.pose[..., 2:]], -1)


def sensor_pose(scene: Scene, time: jax.Array) -> tuple[jax.Array, jax.Array]:
    """Lidar origin float32 [..., 3] (world) and heading [...] at ``time`` seconds."""
    xy = scene.ego[..., :2] + scene.ego_velocity * jnp.asarray(time)[..., None]
    origin = jnp.concatenate([xy, scene.sensor_height[..., None]], -1)
    return origin, scene.ego[..., 2]


def _rot_zy(yaw, pitch):
    """Rz(yaw) @ Ry(pitch), [..., 3, 3]."""
    cz, sz, cy, sy = jnp.cos(yaw), jnp.sin(yaw), jnp.cos(pitch), jnp.sin(pitch)
    zero = jnp.zeros_like(yaw)
    rows = [
        [cz * cy, -sz, cz * sy],
        [sz * cy, cz, sz * sy],
        [-sy, zero, cy],
    ]
    return jnp.stack([jnp.stack(r, -1) for r in rows], -2)


def world_prims(scene: Scene, time: jax.Array):
    """Primitives of every slot in the world at ``time`` (one scene).

    Returns:
      pos float32 [S, P, 3], yaw [S, P] (about z, total), pitch [S, P], on bool [S, P].
    """
    pose = object_poses(scene, time)  # [S, 3]
    rot = _rot2(pose[:, 2])  # [S, 2, 2]
    xy = jnp.einsum("sij,spj->spi", rot, scene.prims.pos[..., :2]) + pose[:, None, :2]
    pos = jnp.concatenate([xy, scene.prims.pos[..., 2:]], -1)  # [S, P, 3]
    yaw = scene.prims.yaw + pose[:, 2:3]
    return pos, yaw, scene.prims.pitch, scene.prims.on & scene.on[:, None]


def geom_state(tpl: SceneTemplate, scene: Scene, time: jax.Array):
    """Every template geom's size, world pose and reflectivity at ``time`` (one scene).

    Returns:
      size float32 [G, 3], xpos [G, 3], xmat [G, 3, 3], reflectivity [G].
    """
    g = tpl.num_geoms
    size = jnp.zeros((g, 3)).at[FLOOR].set(jnp.array([40.0, 40.0, 1.0]))
    xpos = jnp.zeros((g, 3))
    xmat = jnp.broadcast_to(jnp.eye(3), (g, 3, 3))
    refl = jnp.zeros(g).at[FLOOR].set(scene.background[0])
    # Ceiling slab and walls.
    half = scene.room.size / 2 + layouts.WALL_THICKNESS
    size = size.at[CEILING].set(jnp.concatenate([half, jnp.array([0.05])]))
    xpos = xpos.at[CEILING].set(jnp.stack([0.0, 0.0, scene.room.ceiling + 0.05]))
    refl = refl.at[CEILING].set(scene.background[1])
    centre, halves = layouts.wall_boxes(scene.room)
    walls = slice(FIRST_WALL, FIRST_OBJECT)
    wall_on = jnp.all(halves > 0, axis=-1)
    size = size.at[walls].set(jnp.where(wall_on[:, None], halves, PARK_SIZE))
    xpos = xpos.at[walls].set(jnp.where(wall_on[:, None], centre, jnp.array([0, 0, PARK_Z])))
    refl = refl.at[walls].set(scene.background[2])
    # Object primitives, gathered into their geoms.
    pos, yaw, pitch, on = world_prims(scene, time)
    idx = jnp.asarray(np.where(tpl.prim_geom >= 0, tpl.prim_geom, g))  # [S, P]; g = dropped
    psize = jnp.where(on[..., None], scene.prims.size, PARK_SIZE)
    ppos = jnp.where(on[..., None], pos, jnp.array([0.0, 0.0, PARK_Z]))
    size = size.at[idx].set(psize, mode="drop")
    xpos = xpos.at[idx].set(ppos, mode="drop")
    xmat = xmat.at[idx].set(_rot_zy(yaw, pitch), mode="drop")
    refl = refl.at[idx].set(jnp.broadcast_to(scene.reflectivity[:, None], on.shape), mode="drop")
    return size, xpos, xmat, refl


def geom_bounds(tpl: SceneTemplate, size: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """MuJoCo's ``geom_rbound`` [..., G] and ``geom_aabb`` [..., G, 6] for these sizes, in
    numpy (eager JAX sliced the G geoms one by one: half the time of the sequential
    reference of experiments/bench_datagen.py went there)."""
    r, hl = size[..., 0], size[..., 1]
    by_kind = {
        "box": (np.linalg.norm(size, axis=-1), size),
        "ellipsoid": (np.max(size, axis=-1), size),
        "sphere": (r, np.stack([r, r, r], -1)),
        "capsule": (r + hl, np.stack([r, r, r + hl], -1)),
        "cyl": (np.hypot(r, hl), np.stack([r, r, hl], -1)),
    }
    by_kind["hcyl"] = by_kind["cyl"]
    by_kind["plane"] = (np.zeros_like(r), np.stack([size[..., 0], size[..., 1], 0 * r], -1))
    rb = np.stack([by_kind[k][0][..., g] for g, k in enumerate(tpl.geom_kind)], -1)
    half = np.stack([by_kind[k][1][..., g, :] for g, k in enumerate(tpl.geom_kind)], -2)
    return rb, np.concatenate([np.zeros_like(half), half], -1)
