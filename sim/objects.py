"""Object library: the 9 classes built from MuJoCo primitives, several variants each.

Every class has a fixed list of primitive slots (``CLASSES[c].prims``), the union of what
its variants need, so a scene template can hold one MuJoCo geom per slot and stay static in
shape; a variant switches the slots it does not use off. ``build_objects`` draws K objects
of one variant from uniforms (numpy); ``object_bank`` keeps 256 of each variant, from which
the jitted scene sampler gathers (and rescales by a few percent):

    bank = object_bank()          # Prims with [NUM_CLASSES, V, K, P, ...] numpy arrays

Object frame: origin at the centre of the object's tight axis-aligned box in x, y, on the
floor in z (z = 0); length along x. Primitive kinds and their footprints (BEV projection):

  box        MuJoCo box, yawed only                      -> oriented rectangle
  cyl        cylinder, axis vertical                     -> disc
  hcyl       cylinder, axis horizontal (pitch pi/2)      -> oriented rectangle
  capsule    capsule, any pitch                          -> stadium (disc when vertical)
  sphere     sphere                                      -> disc
  ellipsoid  ellipsoid, yawed only                       -> ellipse

so the union of primitive footprints is the object's exact true-shape footprint.
"""

from __future__ import annotations

import dataclasses
import functools
import math

import jax
import jax.numpy as jnp
import numpy as np
from flax import struct

MAX_PRIMS = 8  # primitive slots per object (P)
NUM_UNIFORMS = 8  # random numbers that shape one object

# The MJCF geom type of each primitive kind (hcyl: a cylinder laid on its side by its pitch).
MJCF_TYPE = {
    "box": "box", "cyl": "cylinder", "hcyl": "cylinder", "capsule": "capsule",
    "sphere": "sphere", "ellipsoid": "ellipsoid",
}  # fmt: skip
# Footprint rasteriser of each kind: rectangle, stadium (disc/capsule), ellipse.
RECT, STADIUM, ELLIPSE = 0, 1, 2
FOOTPRINT = {
    "box": RECT, "hcyl": RECT, "cyl": STADIUM, "capsule": STADIUM, "sphere": STADIUM,
    "ellipsoid": ELLIPSE,
}  # fmt: skip


@dataclasses.dataclass(frozen=True)
class ClassSpec:
    """Static description of one class.

    Attributes:
      name: class name (``config.CLASS_NAMES`` order).
      prims: primitive kind of each slot (at most ``MAX_PRIMS``).
      variants: variant names; ``build_object`` takes the index.
      reflectivity: (min, max) lidar reflectivity drawn per object.
      wall_prob: probability of placing the object with its back (-y side) to a wall.
      speed: (min, max) walking/driving speed in m/s of a moving object (0 for static).
    """

    name: str
    prims: tuple[str, ...]
    variants: tuple[str, ...]
    reflectivity: tuple[float, float]
    wall_prob: float = 0.0
    speed: tuple[float, float] = (0.0, 0.0)

    @property
    def dynamic(self) -> bool:
        return self.speed[1] > 0


CLASSES: tuple[ClassSpec, ...] = (
    ClassSpec("Table", ("box",) * 5 + ("cyl",) * 3, ("desk", "round", "coffee"), (0.3, 0.7)),
    ClassSpec("Chair", ("box",) * 7 + ("cyl",), ("office", "plain"), (0.2, 0.6)),
    ClassSpec("Sofa", ("box",) * 6, ("straight", "l_shaped"), (0.1, 0.4), wall_prob=0.6),
    ClassSpec("Shelf", ("box",) * 8, ("bookshelf", "open_low"), (0.4, 0.8), wall_prob=0.9),
    ClassSpec("Cabinet", ("box",) * 3, ("tall", "drawer", "counter"), (0.5, 0.9), wall_prob=0.8),
    ClassSpec("Box", ("box",) * 3, ("carton", "stack"), (0.4, 0.7), wall_prob=0.3),
    ClassSpec(
        "Person",
        ("capsule", "capsule", "ellipsoid", "sphere", "capsule", "capsule"),
        ("standing", "walking"),
        (0.2, 0.6),
        speed=(0.5, 1.4),
    ),
    ClassSpec(
        "Robot",
        ("cyl", "cyl", "cyl", "box", "box", "hcyl", "hcyl"),
        ("cylindrical", "boxy"),
        (0.2, 0.8),
        speed=(0.2, 1.0),
    ),
    ClassSpec(
        "Misc",
        ("cyl", "ellipsoid", "box", "box", "capsule", "capsule", "capsule"),
        ("plant", "bin", "trolley"),
        (0.2, 0.7),
    ),
)
NUM_CLASSES = len(CLASSES)
CLASS_INDEX = {spec.name: k for k, spec in enumerate(CLASSES)}


def variant_key(class_id: int, variant: int) -> str:
    """The "Class/variant" name used by ``SimConfig.test_variants``."""
    spec = CLASSES[class_id]
    return f"{spec.name}/{spec.variants[variant]}"


ALL_VARIANTS: tuple[str, ...] = tuple(
    variant_key(c, v) for c in range(NUM_CLASSES) for v in range(len(CLASSES[c].variants))
)
_VARIANT_OFFSET = np.cumsum([0] + [len(c.variants) for c in CLASSES])[:-1]


def variant_ids(classes, variants) -> np.ndarray:
    """Index into ``ALL_VARIANTS`` of objects given their class and per-class variant ids.

    Args:
      classes, variants: int arrays of one shape (e.g. ``Targets.classes``, ``FrameInfo.variant``).

    Returns:
      int64 of that shape; -1 where ``variants`` is -1 (padding).
    """
    classes, variants = np.asarray(classes), np.asarray(variants)
    ids = _VARIANT_OFFSET[np.clip(classes, 0, NUM_CLASSES - 1)] + variants
    return np.where(variants >= 0, ids, -1).astype(np.int64)


@struct.dataclass
class Prims:
    """Primitives of one object (or, batched, many), in the object frame.

    Attributes:
      size: float32 [P, 3], MuJoCo geom size (half extents; radius, half length).
      pos: float32 [P, 3], primitive centre.
      yaw: float32 [P], rotation about z (applied after ``pitch``).
      pitch: float32 [P], rotation about y (tilts a capsule or cylinder axis).
      on: bool [P], slots the variant uses.
      dims: float32 [3], (length, width, height) of the tight box around the object.
    """

    size: jax.Array
    pos: jax.Array
    yaw: jax.Array
    pitch: jax.Array
    on: jax.Array
    dims: jax.Array


def _lerp(lo: float, hi: float, u: jax.Array) -> jax.Array:
    return lo + (hi - lo) * u


_OFF = ((0.0, 0.0, 0.0), (0.0, 0.0, 0.0), 0.0, 0.0, False)


def _p(size, pos, yaw=0.0, pitch=0.0):
    return (size, pos, yaw, pitch, True)


def _stack(prims: list, k: int) -> tuple[np.ndarray, ...]:
    """P (size, pos, yaw, pitch, on) tuples of [K] values -> [K, P, 3], [K, P, 3], [K, P] x 3."""
    prims = prims + [_OFF] * (MAX_PRIMS - len(prims))

    def vec(v):
        return np.broadcast_to(np.asarray(v, np.float32), (k,))

    size = np.stack([np.stack([vec(v) for v in p[0]], -1) for p in prims], 1)
    pos = np.stack([np.stack([vec(v) for v in p[1]], -1) for p in prims], 1)
    yaw = np.stack([vec(p[2]) for p in prims], 1)
    pitch = np.stack([vec(p[3]) for p in prims], 1)
    on = np.stack([np.broadcast_to(p[4], (k,)) for p in prims], 1)
    return size, pos, yaw, pitch, on


# Each builder maps u [NUM_UNIFORMS, K] to one list of primitives per variant, slots in the
# order of the class's ``prims``. Dimensions are in metres, drawn from typical furniture.


def _table(u):
    def rect(length, width, height):
        t = 0.015  # top half thickness
        legs = [
            _p((0.025, 0.025, (height - 2 * t) / 2), (sx * (length / 2 - 0.06),
               sy * (width / 2 - 0.06), (height - 2 * t) / 2))
            for sx in (-1, 1) for sy in (-1, 1)
        ]  # fmt: skip
        return [_p((length / 2, width / 2, t), (0.0, 0.0, height - t))] + legs + [_OFF] * 3

    desk = rect(_lerp(1.1, 1.8, u[0]), _lerp(0.6, 0.9, u[1]), _lerp(0.70, 0.78, u[2]))
    coffee = rect(_lerp(0.7, 1.2, u[0]), _lerp(0.45, 0.7, u[1]), _lerp(0.38, 0.50, u[2]))
    r, h = _lerp(0.35, 0.6, u[3]), _lerp(0.70, 0.76, u[2])
    round_ = [_OFF] * 5 + [
        _p((r, 0.015, 0.0), (0.0, 0.0, h - 0.015)),
        _p((0.035, h / 2 - 0.02, 0.0), (0.0, 0.0, h / 2)),
        _p((0.45 * r + 0.05, 0.01, 0.0), (0.0, 0.0, 0.01)),
    ]
    return [desk, round_, coffee]


def _chair(u):
    seat, seat_h = _lerp(0.40, 0.50, u[0]), _lerp(0.42, 0.50, u[1])
    back_h = _lerp(0.35, 0.60, u[2])
    seat_p = _p((seat / 2, seat / 2, 0.03), (0.0, 0.0, seat_h))
    back_p = _p((0.025, seat / 2, back_h / 2), (-seat / 2 + 0.025, 0.0, seat_h + 0.03 + back_h / 2))
    # Office chair: five-star base of radius ~0.3 m around a gas-spring column.
    base_r, yaw0 = _lerp(0.26, 0.33, u[3]), _lerp(0.0, 2 * math.pi / 5, u[4])
    star = []
    for k in range(5):
        a = yaw0 + 2 * math.pi * k / 5
        star.append(_p((base_r / 2, 0.02, 0.02), (base_r / 2 * np.cos(a),
                    base_r / 2 * np.sin(a), 0.04), yaw=a))  # fmt: skip
    column = _p((0.03, (seat_h - 0.1) / 2, 0.0), (0.0, 0.0, 0.07 + (seat_h - 0.1) / 2))
    office = [seat_p, back_p] + star + [column]
    legs = [
        _p((0.02, 0.02, (seat_h - 0.03) / 2),
           (sx * (seat / 2 - 0.03), sy * (seat / 2 - 0.03), (seat_h - 0.03) / 2))
        for sx in (-1, 1) for sy in (-1, 1)
    ]  # fmt: skip
    plain = [seat_p, back_p] + legs + [_OFF, _OFF]
    return [office, plain]


def _sofa(u):
    length, depth = _lerp(1.5, 2.3, u[0]), _lerp(0.8, 0.95, u[1])
    seat_h, back_h, arm = _lerp(0.38, 0.46, u[2]), _lerp(0.75, 0.9, u[3]), 0.17
    # Facing +y: the back runs along the -y side, arms at both x ends.
    base = _p((length / 2, depth / 2, seat_h / 2), (0.0, 0.0, seat_h / 2))
    back = _p((length / 2, 0.1, back_h / 2), (0.0, -depth / 2 + 0.1, back_h / 2))
    arm_l = _p((arm / 2, depth / 2, 0.3), (-length / 2 - arm / 2, 0.0, 0.3))
    arm_r = _p((arm / 2, depth / 2, 0.3), (length / 2 + arm / 2, 0.0, 0.3))
    straight = [base, back, arm_l, arm_r, _OFF, _OFF]
    # L-shape: a chaise of length `ext` continues from the +x end towards +y.
    ext = _lerp(0.7, 1.3, u[4])
    chaise = _p((depth / 2, ext / 2, seat_h / 2), (length / 2 - depth / 2, depth / 2 + ext / 2,
                seat_h / 2))  # fmt: skip
    chaise_back = _p((0.1, (ext + depth) / 2, back_h / 2), (length / 2 + 0.1, ext / 2, back_h / 2))
    l_shaped = [base, back, arm_l, _OFF, chaise, chaise_back]
    return [straight, l_shaped]


def _shelf(u):
    def shelf(length, depth, height, boards, with_back):
        t = 0.01
        prims = [
            _p((t, depth / 2, height / 2), (-length / 2 + t, 0.0, height / 2)),
            _p((t, depth / 2, height / 2), (length / 2 - t, 0.0, height / 2)),
            _p((length / 2, t, height / 2), (0.0, -depth / 2 + t, height / 2))
            if with_back
            else _OFF,
        ]
        for k in range(5):
            z = 0.05 + (height - 0.06) * k / (boards - 1) if k < boards else 0.0
            prims.append(_p((length / 2 - 2 * t, depth / 2, t), (0.0, 0.0, z)) if k < boards
                         else _OFF)  # fmt: skip
        return prims

    length, depth = _lerp(0.6, 1.2, u[0]), _lerp(0.28, 0.42, u[1])
    return [
        shelf(length, depth, _lerp(1.6, 2.2, u[2]), 5, True),
        shelf(length, depth, _lerp(0.7, 1.2, u[2]), 3, False),
    ]


def _cabinet(u):
    def cabinet(length, depth, height, top):
        body = _p((length / 2, depth / 2, height / 2), (0.0, 0.0, height / 2))
        handle = _p((0.01, 0.05, 0.01), (0.0, depth / 2 + 0.01, height * 0.7))
        slab = _p((length / 2 + 0.02, depth / 2 + 0.02, 0.015), (0.0, 0.0, height + 0.015))
        return [body, handle, slab if top else _OFF]

    return [
        cabinet(_lerp(0.6, 1.2, u[0]), _lerp(0.4, 0.6, u[1]), _lerp(1.7, 2.0, u[2]), False),
        cabinet(_lerp(0.4, 0.6, u[0]), _lerp(0.45, 0.6, u[1]), _lerp(0.55, 0.75, u[2]), True),
        cabinet(_lerp(1.0, 2.0, u[0]), _lerp(0.55, 0.65, u[1]), _lerp(0.85, 0.95, u[2]), True),
    ]


def _box(u):
    a = (_lerp(0.15, 0.3, u[0]), _lerp(0.15, 0.3, u[1]), _lerp(0.12, 0.3, u[2]))
    carton = [_p(a, (0.0, 0.0, a[2]))]
    # A stack of three smaller cartons, each yawed a little, bottom two side by side.
    b = (_lerp(0.12, 0.22, u[3]), _lerp(0.12, 0.2, u[4]), _lerp(0.1, 0.18, u[5]))
    wiggle = _lerp(-0.15, 0.15, u[6])
    stack = [
        _p(b, (-b[0] - 0.01, 0.0, b[2]), yaw=wiggle),
        _p(b, (b[0] + 0.01, 0.0, b[2]), yaw=-wiggle),
        _p(b, (0.0, 0.0, 3 * b[2]), yaw=0.5 * wiggle),
    ]
    return [carton, stack]


def _person(u):
    height = _lerp(1.55, 1.95, u[0])
    s = height / 1.75  # proportions of a 1.75 m adult
    leg_r, leg_h = 0.065 * s, 0.42 * s  # capsule radius, half length
    hip, shoulder = 0.09 * s, 0.2 * s
    torso = _p((0.13 * s, 0.2 * s, 0.3 * s), (0.0, 0.0, 1.16 * s))
    head = _p((0.105 * s, 0.0, 0.0), (0.0, 0.0, height - 0.105 * s))
    arm_r, arm_h = 0.045 * s, 0.3 * s

    def body(swing):
        legs = [
            _p((leg_r, leg_h - leg_r, 0.0),
               (-sgn * np.sin(swing) * leg_h, sgn * hip, leg_h * np.cos(swing)),
               pitch=sgn * swing)
            for sgn in (-1, 1)
        ]  # fmt: skip
        arms = [
            _p((arm_r, arm_h - arm_r, 0.0),
               (sgn * np.sin(swing) * arm_h, sgn * shoulder, 1.42 * s - arm_h * np.cos(swing)),
               pitch=-sgn * swing)
            for sgn in (-1, 1)
        ]  # fmt: skip
        return [legs[0], legs[1], torso, head, arms[0], arms[1]]

    return [body(0.0), body(_lerp(0.2, 0.4, u[1]))]


def _robot(u):
    r, h = _lerp(0.17, 0.3, u[0]), _lerp(0.12, 0.4, u[1])
    cylindrical = [
        _p((r, h / 2, 0.0), (0.0, 0.0, 0.02 + h / 2)),
        _p((0.8 * r, 0.01, 0.0), (0.0, 0.0, 0.03 + h)),
        _p((0.04, 0.05, 0.0), (0.0, 0.0, 0.04 + h + 0.05)),
        _OFF, _OFF, _OFF, _OFF,
    ]  # fmt: skip
    length, width, bh = _lerp(0.45, 0.9, u[2]), _lerp(0.35, 0.6, u[3]), _lerp(0.2, 0.4, u[4])
    wheel = 0.07
    boxy = [
        _OFF, _OFF, _OFF,
        _p((length / 2, width / 2, bh / 2), (0.0, 0.0, wheel + bh / 2)),
        _p((0.25 * length, 0.3 * width, 0.08), (-0.1 * length, 0.0, wheel + bh + 0.08)),
        _p((wheel, 0.03, 0.0), (0.0, width / 2 + 0.03, wheel), pitch=math.pi / 2,
           yaw=math.pi / 2),
        _p((wheel, 0.03, 0.0), (0.0, -width / 2 - 0.03, wheel), pitch=math.pi / 2,
           yaw=math.pi / 2),
    ]  # fmt: skip
    return [cylindrical, boxy]


def _misc(u):
    pot_r, pot_h = _lerp(0.12, 0.22, u[0]), _lerp(0.25, 0.45, u[1])
    leaf_r, leaf_h = _lerp(1.2, 1.8, u[2]) * pot_r, _lerp(0.3, 0.6, u[3])
    plant = [
        _p((pot_r, pot_h / 2, 0.0), (0.0, 0.0, pot_h / 2)),
        _p((leaf_r, 0.9 * leaf_r, leaf_h), (0.0, 0.0, pot_h + 0.8 * leaf_h)),
    ] + [_OFF] * 5
    bin_ = [_p((pot_r + 0.03, pot_h + 0.1, 0.0), (0.0, 0.0, pot_h + 0.1))] + [_OFF] * 6
    length, width = _lerp(0.6, 1.0, u[4]), _lerp(0.4, 0.6, u[5])
    handle_h = _lerp(0.85, 1.0, u[6])
    post = (handle_h - 0.12) / 2
    trolley = [
        _OFF, _OFF,
        _p((length / 2, width / 2, 0.02), (0.0, 0.0, 0.14)),
        _p((length / 2, width / 2, 0.015), (0.0, 0.0, 0.55)),
        _p((0.015, post, 0.0), (-length / 2 - 0.02, -width / 2 + 0.04, 0.12 + post)),
        _p((0.015, post, 0.0), (-length / 2 - 0.02, width / 2 - 0.04, 0.12 + post)),
        _p((0.015, width / 2 - 0.04, 0.0), (-length / 2 - 0.02, 0.0, handle_h),
           pitch=math.pi / 2, yaw=math.pi / 2),
    ]  # fmt: skip
    return [plant, bin_, trolley]


_BUILDERS = (_table, _chair, _sofa, _shelf, _cabinet, _box, _person, _robot, _misc)


def prim_axis(yaw, pitch, xp=jnp):
    """Unit axis (local z) of a primitive rotated by Rz(yaw) Ry(pitch); [..., 3]."""
    sp = xp.sin(pitch)
    return xp.stack([sp * xp.cos(yaw), sp * xp.sin(yaw), xp.cos(pitch)], axis=-1)


def prim_half_extents(kinds: tuple[str, ...], size, yaw, pitch, xp=jnp):
    """Half extents of each primitive's axis-aligned bounding box.

    Args:
      kinds: primitive kind per slot (static), length P.
      size, yaw, pitch: [..., P, 3], [..., P], [..., P].
      xp: the array module (``jax.numpy`` or ``numpy``).

    Returns:
      float32 [..., P, 3].
    """
    c, s = xp.abs(xp.cos(yaw)), xp.abs(xp.sin(yaw))
    sx, sy, sz = size[..., 0], size[..., 1], size[..., 2]
    box = xp.stack([c * sx + s * sy, s * sx + c * sy, sz], -1)
    ell = xp.stack([xp.hypot(sx * c, sy * s), xp.hypot(sx * s, sy * c), sz], -1)
    axis = xp.abs(prim_axis(yaw, pitch, xp))  # [..., P, 3]
    r, hl = sx[..., None], sy[..., None]
    capsule = axis * hl + r
    cylinder = axis * hl + r * xp.sqrt(xp.clip(1 - axis**2, 0.0, 1.0))
    sphere = xp.broadcast_to(r, box.shape)
    by_kind = {"box": box, "ellipsoid": ell, "capsule": capsule, "cyl": cylinder,
               "hcyl": cylinder, "sphere": sphere}  # fmt: skip
    return xp.stack([by_kind[k][..., p, :] for p, k in enumerate(kinds)], axis=-2)


def build_objects(class_id: int, variant: int, u: np.ndarray) -> Prims:
    """K objects of one class and variant, in their object frames (numpy).

    Args:
      class_id: class index.
      variant: variant index.
      u: float [K, NUM_UNIFORMS] uniforms in [0, 1) that set the dimensions.

    Returns:
      ``Prims`` of numpy arrays with a leading [K] axis, recentred so each object's tight
      box is centred in x, y and starts at z = 0.
    """
    spec = CLASSES[class_id]
    u = np.asarray(u, np.float32)
    options = _BUILDERS[class_id](u.T)
    size, pos, yaw, pitch, on = _stack(options[variant], len(u))
    kinds = spec.prims + ("box",) * (MAX_PRIMS - len(spec.prims))
    half = prim_half_extents(kinds, size, yaw, pitch, np)  # [K, P, 3]
    lo = np.min(np.where(on[..., None], pos - half, np.inf), axis=1)  # [K, 3]
    hi = np.max(np.where(on[..., None], pos + half, -np.inf), axis=1)  # [K, 3]
    centre = np.array([0.5, 0.5, 0.0]) * (lo + hi) + np.array([0.0, 0.0, 1.0]) * lo
    pos = np.where(on[..., None], pos - centre[:, None], 0.0)
    size = np.where(on[..., None], size, 0.0)
    f32 = lambda x: np.asarray(x, np.float32)  # noqa: E731
    return Prims(f32(size), f32(pos), f32(yaw), f32(pitch), on, f32(hi - lo))


@functools.lru_cache(maxsize=4)
def object_bank(per_variant: int = 256, seed: int = 0) -> Prims:
    """A bank of pre-built objects: ``per_variant`` random instances of every variant.

    Building objects from dozens of scalar formulas inside a jitted generator costs tens of
    seconds of XLA compile time on a CPU; a numpy bank costs milliseconds, and the
    generator gathers from it (and rescales each object a little, see ``scenes``).

    Returns:
      ``Prims`` of numpy arrays with leading axes [NUM_CLASSES, V, K] (V the most variants
      of any class; missing variants repeat the class's last; scenes never draw them).
    """
    rng = np.random.default_rng(seed)
    vmax = max(len(c.variants) for c in CLASSES)
    rows = []
    for c, spec in enumerate(CLASSES):
        per = [
            build_objects(
                c, min(v, len(spec.variants) - 1), rng.random((per_variant, NUM_UNIFORMS))
            )
            for v in range(vmax)
        ]
        rows.append(jax.tree.map(lambda *x: np.stack(x), *per))
    return jax.tree.map(lambda *x: np.stack(x), *rows)
