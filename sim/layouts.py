"""Floor plans: offices, labs, corridors and halls, keyed so a test split can hold them out.

A *plan* is one concrete room: its size, ceiling height and door gaps. There are
``sim.plans_per_layout`` plans of each layout kind, plan ``kind/index`` having the fixed id
``kind_number * plans_per_layout + index``; its geometry is a pure function of that id (drawn
from a fixed key), so a held-out plan (``SimConfig.test_layouts``) is never seen in training,
whatever the seeds. Per scene the plan only fixes the room; the furniture is drawn afresh
with class counts typical of the layout kind (``LAYOUTS``).

World frame of a scene: origin at the room centre on the floor, walls along the axes.
Each of the four walls is two box geoms with a door gap between them (gap width 0 when the
wall has no door), so every plan has the same geom count.
"""

from __future__ import annotations

import dataclasses

import jax
import jax.numpy as jnp
import numpy as np
from flax import struct
from indoorbev_sim.objects import CLASS_INDEX, NUM_CLASSES

WALL_THICKNESS = 0.1
NUM_WALL_GEOMS = 8  # 4 walls x 2 segments
_PLAN_SEED = 20261121  # plans are fixed geometry, independent of every run's seed


@dataclasses.dataclass(frozen=True)
class LayoutKind:
    """Static description of one layout kind.

    Attributes:
      name: "office", "lab", "corridor" or "hall".
      size_x, size_y: (min, max) interior room extent in metres.
      ceiling: (min, max) ceiling height.
      door_prob: probability that a wall has a door gap.
      fill: per class, the largest fraction of that class's slots used in a scene.
    """

    name: str
    size_x: tuple[float, float]
    size_y: tuple[float, float]
    ceiling: tuple[float, float]
    door_prob: float
    fill: dict[str, float]

    def fill_vector(self) -> np.ndarray:
        out = np.zeros(NUM_CLASSES, np.float32)
        for name, f in self.fill.items():
            out[CLASS_INDEX[name]] = f
        return out


LAYOUTS: tuple[LayoutKind, ...] = (
    LayoutKind("office", (6.0, 10.0), (6.0, 10.0), (2.6, 3.0), 0.5,
               {"Table": 1.0, "Chair": 1.0, "Sofa": 0.5, "Shelf": 1.0, "Cabinet": 1.0,
                "Box": 0.6, "Person": 0.7, "Robot": 0.5, "Misc": 1.0}),
    LayoutKind("lab", (7.0, 11.0), (6.0, 9.0), (2.8, 3.3), 0.5,
               {"Table": 1.0, "Chair": 0.7, "Sofa": 0.0, "Shelf": 1.0, "Cabinet": 1.0,
                "Box": 1.0, "Person": 0.7, "Robot": 1.0, "Misc": 1.0}),
    LayoutKind("corridor", (12.0, 20.0), (2.0, 3.2), (2.5, 2.8), 0.8,
               {"Table": 0.0, "Chair": 0.3, "Sofa": 0.0, "Shelf": 0.3, "Cabinet": 0.7,
                "Box": 1.0, "Person": 1.0, "Robot": 1.0, "Misc": 1.0}),
    LayoutKind("hall", (11.0, 16.0), (11.0, 16.0), (3.2, 4.5), 0.7,
               {"Table": 1.0, "Chair": 1.0, "Sofa": 1.0, "Shelf": 0.5, "Cabinet": 0.5,
                "Box": 0.5, "Person": 1.0, "Robot": 0.7, "Misc": 1.0}),
)  # fmt: skip
LAYOUT_INDEX = {k.name: i for i, k in enumerate(LAYOUTS)}


@struct.dataclass
class Room:
    """One room (batched: leading axes).

    Attributes:
      plan: int32 [], the plan id.
      kind: int32 [], index into ``LAYOUTS``.
      size: float32 [2], interior extent (x, y).
      ceiling: float32 [], ceiling height.
      door_lo, door_hi: float32 [4], door gap along each wall (walls -y, +y, -x, +x), as
        coordinates along the wall; lo == hi when there is no door.
    """

    plan: jax.Array
    kind: jax.Array
    size: jax.Array
    ceiling: jax.Array
    door_lo: jax.Array
    door_hi: jax.Array


def plan_id(name: str, plans_per_layout: int) -> int:
    """Id of a plan named "kind/index" (e.g. "office/7"); ValueError when malformed."""
    kind, _, index = name.partition("/")
    if kind not in LAYOUT_INDEX or not index.isdigit() or int(index) >= plans_per_layout:
        raise ValueError(
            f"layout plan '{name}': expected 'kind/index' with kind in "
            f"{sorted(LAYOUT_INDEX)} and index < {plans_per_layout}"
        )
    return LAYOUT_INDEX[kind] * plans_per_layout + int(index)


def plan_name(pid: int, plans_per_layout: int) -> str:
    return f"{LAYOUTS[pid // plans_per_layout].name}/{pid % plans_per_layout}"


def _table(field: str) -> jax.Array:
    return jnp.asarray([getattr(k, field) for k in LAYOUTS], jnp.float32)


def make_room(pid: jax.Array, plans_per_layout: int) -> Room:
    """The room of plan ``pid`` (a pure function of the id; jittable)."""
    pid = jnp.asarray(pid, jnp.int32)
    kind = pid // plans_per_layout
    # One draw (a PRNG call costs compile time): 3 for the room, 4 x 4 for the doors.
    u = jax.random.uniform(jax.random.fold_in(jax.random.key(_PLAN_SEED), pid), (19,))
    sx, sy, ceil = _table("size_x")[kind], _table("size_y")[kind], _table("ceiling")[kind]
    size = jnp.stack([sx[0] + (sx[1] - sx[0]) * u[0], sy[0] + (sy[1] - sy[0]) * u[1]])
    ceiling = ceil[0] + (ceil[1] - ceil[0]) * u[2]
    # Door gaps: walls 0, 1 run along x (length size_x), walls 2, 3 along y.
    wall_len = jnp.stack([size[0], size[0], size[1], size[1]])
    has_door = u[3:7] < _table("door_prob")[kind]
    width = jnp.minimum(0.9 + 0.7 * u[7:11], wall_len - 1.0)
    centre = (u[11:15] - 0.5) * (wall_len - width - 0.6)
    lo = jnp.where(has_door, centre - width / 2, 0.0)
    hi = jnp.where(has_door, centre + width / 2, 0.0)
    return Room(plan=pid, kind=kind, size=size, ceiling=ceiling, door_lo=lo, door_hi=hi)


def wall_boxes(room: Room) -> tuple[jax.Array, jax.Array]:
    """Box geoms of the walls, two segments per wall around its door gap.

    Returns:
      centre: float32 [8, 3] world positions; half: float32 [8, 3] half extents (a segment
      of zero length has zero x/y half extent).
    """
    hx, hy = room.size[0] / 2, room.size[1] / 2
    t = WALL_THICKNESS / 2
    h = room.ceiling / 2
    centres, halves = [], []
    for w in range(4):
        along_x = w < 2
        half_len = (hx if along_x else hy) + 2 * t  # walls overlap at the corners
        offset = (-(hy + t) if w == 0 else hy + t) if along_x else (-(hx + t) if w == 2 else hx + t)
        for a, b in ((-half_len, room.door_lo[w]), (room.door_hi[w], half_len)):
            # Without a door lo == hi == 0: the two segments simply meet in the middle.
            mid, half = (a + b) / 2, jnp.maximum(b - a, 0.0) / 2
            if along_x:
                centres.append(jnp.stack([mid, offset, h]))
                halves.append(jnp.stack([half, t, h]))
            else:
                centres.append(jnp.stack([offset, mid, h]))
                halves.append(jnp.stack([t, half, h]))
    return jnp.stack(centres), jnp.stack(halves)


def class_counts(u: jax.Array, kind: jax.Array, slots: tuple[int, ...]) -> jax.Array:
    """How many objects of each class a scene of this layout kind asks for.

    Uniform in 0..round(fill * slots) per class.

    Args:
      u: float [NUM_CLASSES] uniforms in [0, 1).
      kind: int, layout kind.
      slots: static slot count per class.

    Returns:
      int32 [NUM_CLASSES].
    """
    fill = jnp.asarray(np.stack([k.fill_vector() for k in LAYOUTS]))[kind]  # [C]
    top = jnp.round(fill * jnp.asarray(slots, jnp.float32))
    return jnp.floor(u * (top + 1)).astype(jnp.int32)
