"""Pure-JAX ray casting against MuJoCo primitives (private; see ``lidar.py``, method "jax").

The same arithmetic as the Warp kernels of ``_lidar_kernels.py`` (MuJoCo's ``mj_ray``
conventions, float32, cancellation-free discriminants), written as array code over every
(ray, geom) pair of a scene: no culling, so its cost is rays x geoms, which a GPU takes in
its stride. It runs wherever JAX runs (any backend, ``vmap``, ``jit``) and needs no
warp-lang, which is its reason to exist: machines without Warp can still simulate.

Vectors are tuples of three arrays (x, y, z) that broadcast to [B, R, G], so every routine
is elementwise and XLA fuses it.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np

from ._ray_constants import (
    BIG,
    BOUND_ABS,
    BOUND_REL,
    BOX,
    CAPSULE,
    CYLINDER,
    ELLIPSOID,
    MINVAL,
    PLANE,
    PLANE_PARALLEL,
    SPHERE,
)

_MISS = -1.0


def _dot(a, b):
    return a[0] * b[0] + a[1] * b[1] + a[2] * b[2]


def _safe(a):
    """a where it is a usable divisor; 1 elsewhere (those lanes are masked out anyway)."""
    return jnp.where(jnp.abs(a) > 0.0, a, 1.0)


def _quad_first(a, b, perp2, r2):
    """Smallest root >= 0 of a x^2 + 2 b x + c = 0 (det = a (r2 - perp2)); -1 if none."""
    det = a * (r2 - perp2)
    sq = jnp.sqrt(jnp.maximum(det, 0.0))
    a = _safe(a)
    x0 = (-b - sq) / a
    x1 = (-b + sq) / a
    x = jnp.where(x0 >= 0.0, x0, jnp.where(x1 >= 0.0, x1, _MISS))
    return jnp.where(det < MINVAL, _MISS, x)


def _perp2(p, v, a, b):
    """Squared distance of the line p + x v to the origin (a = v.v, b = v.p)."""
    s = b / _safe(a)
    q = tuple(pi - s * vi for pi, vi in zip(p, v, strict=True))
    return _dot(q, q)


def _sphere(p, v, r):
    a, b = _dot(v, v), _dot(v, p)
    return _quad_first(a, b, _perp2(p, v, a, b), r * r)


def _plane(p, v, size):
    downward = v[2] < -PLANE_PARALLEL * jnp.sqrt(_dot(v, v))
    vz = jnp.where(downward, v[2], -1.0)
    x = -p[2] / vz
    inside = ((size[0] <= 0.0) | (jnp.abs(p[0] + x * v[0]) <= size[0])) & (
        (size[1] <= 0.0) | (jnp.abs(p[1] + x * v[1]) <= size[1])
    )
    return jnp.where(downward & (x >= 0.0) & inside, x, _MISS)


def _ellipsoid(p, v, size):
    ps = tuple(pi / _safe(si) for pi, si in zip(p, size, strict=True))
    vs = tuple(vi / _safe(si) for vi, si in zip(v, size, strict=True))
    a, b = _dot(vs, vs), _dot(vs, ps)
    return _quad_first(a, b, _perp2(ps, vs, a, b), 1.0)


def _side(p, v, r, h):
    """Round side of a z-aligned cylinder of radius r, half-height h (first root only)."""
    a = v[0] * v[0] + v[1] * v[1]
    b = v[0] * p[0] + v[1] * p[1]
    s = b / _safe(a)
    qx, qy = p[0] - s * v[0], p[1] - s * v[1]
    sol = _quad_first(a, b, qx * qx + qy * qy, r * r)
    ok = (a >= MINVAL) & (sol >= 0.0) & (jnp.abs(p[2] + sol * v[2]) <= h)
    return jnp.where(ok, sol, _MISS)


def _take(x, sol):
    return jnp.where((sol >= 0.0) & ((x < 0.0) | (sol < x)), sol, x)


def _cap(p, v, r, h, side, x):
    """Hemispherical cap centred at z = side * h, keeping only its outer half."""
    d = (p[0], p[1], p[2] - side * h)
    a, b = _dot(v, v), _dot(v, d)
    det = a * (r * r - _perp2(d, v, a, b))
    sq = jnp.sqrt(jnp.maximum(det, 0.0))
    a = _safe(a)
    for root in ((-b - sq) / a, (-b + sq) / a):
        ok = (det >= MINVAL) & (root >= 0.0) & (side * (p[2] + root * v[2]) >= h)
        x = jnp.where(ok, _take(x, root), x)
    return x


def _capsule(p, v, size):
    r, h = size[0], size[1]
    x = _side(p, v, r, h)
    x = _cap(p, v, r, h, 1.0, x)
    x = _cap(p, v, r, h, -1.0, x)
    return jnp.where(_sphere(p, v, r + h) < 0.0, _MISS, x)


def _cylinder(p, v, size):
    r, h = size[0], size[1]
    x = jnp.full(jnp.broadcast_shapes(p[0].shape, v[0].shape), _MISS, jnp.float32)
    vz = jnp.where(jnp.abs(v[2]) > MINVAL, v[2], 1.0)
    for side in (-1.0, 1.0):
        sol = (side * h - p[2]) / vz
        p0, p1 = p[0] + sol * v[0], p[1] + sol * v[1]
        ok = (jnp.abs(v[2]) > MINVAL) & (sol >= 0.0) & (p0 * p0 + p1 * p1 <= r * r)
        x = jnp.where(ok, _take(x, sol), x)
    x = _take(x, _side(p, v, r, h))
    return jnp.where(_sphere(p, v, jnp.sqrt(r * r + h * h)) < 0.0, _MISS, x)


def _box(p, v, size):
    """Slab test; the same answer as MuJoCo's face-by-face ray_box (far face from inside)."""
    tnear, tfar, out = -BIG, BIG, False
    for pi, vi, si in zip(p, v, size, strict=True):
        moving = jnp.abs(vi) > MINVAL
        inv = 1.0 / jnp.where(moving, vi, 1.0)
        t0, t1 = (-si - pi) * inv, (si - pi) * inv
        tnear = jnp.where(moving, jnp.maximum(tnear, jnp.minimum(t0, t1)), tnear)
        tfar = jnp.where(moving, jnp.minimum(tfar, jnp.maximum(t0, t1)), tfar)
        out = out | (~moving & (jnp.abs(pi) > si))
    x = jnp.where(tnear >= 0.0, tnear, jnp.where(tfar >= 0.0, tfar, _MISS))
    return jnp.where(out | (tnear > tfar), _MISS, x)


_ROUTINES = {  # each (p, v, size) -> distance
    BOX: _box,
    PLANE: _plane,
    SPHERE: lambda p, v, sz: _sphere(p, v, sz[0]),
    CAPSULE: _capsule,
    CYLINDER: _cylinder,
    ELLIPSOID: _ellipsoid,
}


def _solve(gtype, static_type, p, v, sz):
    """Hit distances [B, R, g]: one routine for a group of one static type, else all six
    under a select on the (traced) types."""
    if static_type is not None:
        return _ROUTINES[static_type](p, v, sz)
    return jnp.select(
        [gtype == t for t in _ROUTINES], [f(p, v, sz) for f in _ROUTINES.values()], _MISS
    )


def cast(geom_type, size, mat, local, rbound, enabled, dirs, max_range, types=None):
    """Closest hit of every ray of B scenes over all their enabled primitives.

    Args:
      geom_type, size, mat, rbound, enabled: the ``SceneGeometry`` fields, [B, G, ...].
      local: [B, G, 3] the scene's ray origin in each geom's frame.
      dirs: [B, R, 3] ray directions (world frame, any nonzero length).
      max_range: [B].
      types: optional static ``mjtGeom`` id per geom (G ints, shared by the B scenes): the
        geoms are then cast in one group per type, each with its own routine only, instead
        of every routine for every geom.

    Returns:
      ``(dist, geom)``: [B, R] float32 distance in units of |dir| (-1: miss) and int32 geom
      id (-1: miss); ties keep the lowest id, as ``mj_ray``.
    """
    ngeom = geom_type.shape[1]
    if types is None:
        groups = [(None, np.arange(ngeom))]
    else:
        types = np.asarray(types).reshape(ngeom)
        groups = [(int(t), np.flatnonzero(types == t)) for t in _ROUTINES if (types == t).any()]
    inv_len = jax.lax.rsqrt(jnp.sum(dirs * dirs, axis=-1))[..., None]  # [B, R, 1]
    limit = max_range[:, None, None] * inv_len
    best_d = jnp.full(dirs.shape[:2], jnp.inf, jnp.float32)
    best_g = jnp.full(dirs.shape[:2], -1, jnp.int32)
    for static_type, idx in groups:
        take = lambda x, idx=idx: x[:, idx]  # noqa: E731  the group's geoms, [B, g, ...]
        loc, sz3, m3 = take(local), take(size), take(mat)
        p = tuple(loc[:, None, :, i] for i in range(3))  # [B, 1, g]
        sz = tuple(sz3[:, None, :, i] for i in range(3))
        # The direction in each geom's frame: v_i = sum_j mat[j, i] dir_j.
        v = tuple(jnp.einsum("bgj,brj->brg", m3[..., :, i], dirs) for i in range(3))
        sol = _solve(take(geom_type)[:, None, :], static_type, p, v, sz)
        # The kernels' bounding-sphere reject, kept so grazing rays agree with them.
        pp = _dot(p, p)
        tc = -_dot(p, v) * inv_len
        rb = take(rbound)[:, None, :]
        slack = BOUND_ABS + BOUND_REL * (rb * rb + pp)
        rejected = (rb < BIG) & (pp - tc * tc > rb * rb + slack)
        hit = (take(enabled)[:, None, :] != 0) & ~rejected & (sol >= 0.0) & (sol <= limit)
        sol = jnp.where(hit, sol, jnp.inf)
        d = jnp.min(sol, axis=-1)
        g = jnp.asarray(idx, jnp.int32)[jnp.argmin(sol, axis=-1)]  # lowest id among equals
        better = (d < best_d) | ((d == best_d) & (g < best_g))
        best_d, best_g = jnp.where(better, d, best_d), jnp.where(better, g, best_g)
    found = jnp.isfinite(best_d)
    return jnp.where(found, best_d, _MISS), jnp.where(found, best_g, -1)
