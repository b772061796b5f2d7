"""Warp kernels for lidar ray casting against MuJoCo primitives (private; see ``lidar.py``).

Every intersection routine follows MuJoCo's ``engine_ray.c`` (``mj_ray``) conventions:
rays are ``pnt + x * vec`` with ``x >= 0``; a ray starting inside a closed primitive hits
its far side; planes are hit only from their front (+z) face and are unbounded along a local
axis whose size is <= 0; a miss is ``-1``. The arithmetic is float32, with the quadratic
discriminants written in a cancellation-free form (distance of the ray to the centre), so
distances agree with MuJoCo's float64 to ~1e-6 m away from grazing incidence.

All arrays carry a leading scene axis B so one launch serves a batch of scenes.
The kernels group their parameters as ``# Model:`` (the scene's geoms: types and sizes, and
their poses and cull data in the lidar frame of this frame, since the lidar moves), ``# In:``
(the rays and the cube map's fixed cells) and ``# Out:``.

Acceleration ("sensor-centric cube map"): all rays of one scene share one origin (a lidar),
so the build kernel bins ray *directions* into the 6 * N * N cells of a cube map and, per
cell, lists the geoms that a ray of that cell can reach together with a conservative lower
bound on the hit distance, sorted by that bound. A ray walks its cell's list and stops as soon
as the next bound exceeds its closest hit. The culling tests (bounding cone of the cell vs the
geom's bounding sphere and the slabs of its local bounding box) only ever over-include, so the
result is the same as testing every geom. Rebuilding the lists is a single O(cells * geoms)
launch per frame, which is the whole "refit" a moving mocap body needs.
"""

from __future__ import annotations

import functools
import inspect
import threading
from concurrent.futures import ThreadPoolExecutor

import warp as wp

from . import _ray_constants as rc

# No start-up banner or module-load lines on stdout (they mix into the commands' output):
# ``quiet`` before Warp 1.10, ``log_level`` after it.
wp.config.quiet = True
if hasattr(wp, "LOG_WARNING"):
    wp.config.log_level = wp.LOG_WARNING
# Forward only: nothing differentiates through a ray cast, and it halves the compile time.
wp.set_module_options({"enable_backward": False})

# Warp kernels read module-level constants only through wp.constant.
GEOM_PLANE = wp.constant(rc.PLANE)
GEOM_SPHERE = wp.constant(rc.SPHERE)
GEOM_CAPSULE = wp.constant(rc.CAPSULE)
GEOM_ELLIPSOID = wp.constant(rc.ELLIPSOID)
GEOM_CYLINDER = wp.constant(rc.CYLINDER)
GEOM_BOX = wp.constant(rc.BOX)
MINVAL = wp.constant(rc.MINVAL)
PLANE_PARALLEL = wp.constant(rc.PLANE_PARALLEL)
BIG = wp.constant(rc.BIG)
BOUND_REL = wp.constant(rc.BOUND_REL)
BOUND_ABS = wp.constant(rc.BOUND_ABS)


@wp.func
def _quad_first(a: float, b: float, perp2: float, r2: float) -> float:
    """Smallest root >= 0 of a x^2 + 2 b x + c = 0, as MuJoCo's ray_quad; -1 if none.

    The discriminant b^2 - a c equals a (r2 - perp2), perp2 being the squared distance of the
    (scaled) ray line to the centre; that form does not cancel in float32.
    """
    det = a * (r2 - perp2)
    if det < MINVAL:
        return -1.0
    sq = wp.sqrt(det)
    x0 = (-b - sq) / a
    if x0 >= 0.0:
        return x0
    x1 = (-b + sq) / a
    if x1 >= 0.0:
        return x1
    return -1.0


@wp.func
def _perp2_3(p: wp.vec3, v: wp.vec3, a: float, b: float) -> float:
    q = p - (b / a) * v
    return wp.dot(q, q)


@wp.func
def _ray_sphere(p: wp.vec3, v: wp.vec3, r: float) -> float:
    a = wp.dot(v, v)
    b = wp.dot(v, p)
    return _quad_first(a, b, _perp2_3(p, v, a, b), r * r)


@wp.func
def _ray_plane(p: wp.vec3, v: wp.vec3, size: wp.vec3) -> float:
    if v[2] > -PLANE_PARALLEL * wp.length(v):
        return -1.0
    x = -p[2] / v[2]
    if x < 0.0:
        return -1.0
    p0 = p[0] + x * v[0]
    p1 = p[1] + x * v[1]
    if (size[0] <= 0.0 or wp.abs(p0) <= size[0]) and (size[1] <= 0.0 or wp.abs(p1) <= size[1]):
        return x
    return -1.0


@wp.func
def _ray_ellipsoid(p: wp.vec3, v: wp.vec3, size: wp.vec3) -> float:
    ps = wp.cw_div(p, size)
    vs = wp.cw_div(v, size)
    a = wp.dot(vs, vs)
    b = wp.dot(vs, ps)
    return _quad_first(a, b, _perp2_3(ps, vs, a, b), 1.0)


@wp.func
def _ray_side(p: wp.vec3, v: wp.vec3, r: float, h: float) -> float:
    """Round side of a z-aligned cylinder of radius r, half-height h (first root only)."""
    a = v[0] * v[0] + v[1] * v[1]
    b = v[0] * p[0] + v[1] * p[1]
    if a < MINVAL:
        return -1.0  # parallel to the axis: MuJoCo's discriminant is 0 < mjMINVAL
    qx = p[0] - (b / a) * v[0]
    qy = p[1] - (b / a) * v[1]
    sol = _quad_first(a, b, qx * qx + qy * qy, r * r)
    if sol >= 0.0 and wp.abs(p[2] + sol * v[2]) <= h:
        return sol
    return -1.0


@wp.func
def _take(x: float, sol: float) -> float:
    if sol >= 0.0 and (x < 0.0 or sol < x):
        return sol
    return x


@wp.func
def _ray_cap(p: wp.vec3, v: wp.vec3, r: float, h: float, side: float, x: float) -> float:
    """Hemispherical cap centred at z = side * h, keeping only the outer half."""
    d = wp.vec3(p[0], p[1], p[2] - side * h)
    a = wp.dot(v, v)
    b = wp.dot(v, d)
    det = a * (r * r - _perp2_3(d, v, a, b))
    if det < MINVAL:
        return x
    sq = wp.sqrt(det)
    x0 = (-b - sq) / a
    x1 = (-b + sq) / a
    if x0 >= 0.0 and side * (p[2] + x0 * v[2]) >= h:
        x = _take(x, x0)
    if x1 >= 0.0 and side * (p[2] + x1 * v[2]) >= h:
        x = _take(x, x1)
    return x


@wp.func
def _ray_capsule(p: wp.vec3, v: wp.vec3, size: wp.vec3) -> float:
    r = size[0]
    h = size[1]
    if _ray_sphere(p, v, r + h) < 0.0:
        return -1.0
    x = _ray_side(p, v, r, h)
    x = _ray_cap(p, v, r, h, 1.0, x)
    x = _ray_cap(p, v, r, h, -1.0, x)
    return x


@wp.func
def _ray_cylinder(p: wp.vec3, v: wp.vec3, size: wp.vec3) -> float:
    r = size[0]
    h = size[1]
    if _ray_sphere(p, v, wp.sqrt(r * r + h * h)) < 0.0:
        return -1.0
    x = wp.float32(-1.0)
    if wp.abs(v[2]) > MINVAL:
        for k in range(2):
            side = float(2 * k - 1)
            sol = (side * h - p[2]) / v[2]
            if sol >= 0.0:
                p0 = p[0] + sol * v[0]
                p1 = p[1] + sol * v[1]
                if p0 * p0 + p1 * p1 <= r * r:
                    x = _take(x, sol)
    return _take(x, _ray_side(p, v, r, h))


@wp.func
def _ray_box(p: wp.vec3, v: wp.vec3, size: wp.vec3) -> float:
    """Slab test; same answer as MuJoCo's face-by-face ray_box (far face from inside)."""
    tnear = wp.float32(-BIG)
    tfar = wp.float32(BIG)
    for i in range(3):
        if wp.abs(v[i]) > MINVAL:
            inv = 1.0 / v[i]
            t0 = (-size[i] - p[i]) * inv
            t1 = (size[i] - p[i]) * inv
            tnear = wp.max(tnear, wp.min(t0, t1))
            tfar = wp.min(tfar, wp.max(t0, t1))
        elif wp.abs(p[i]) > size[i]:
            return -1.0
    if tnear > tfar:
        return -1.0
    if tnear >= 0.0:
        return tnear
    if tfar >= 0.0:
        return tfar
    return -1.0


@wp.func
def ray_geom(gtype: int, size: wp.vec3, p: wp.vec3, mat: wp.mat33, vec: wp.vec3) -> float:
    """Distance (in units of |vec|) along vec to one primitive, -1 on a miss.

    p: the ray's origin in the geom's local frame (``geom_xmat^T (pnt - geom_xpos)``); all rays
    of a scene share their origin, so it is computed once per geom (``lidar._sensor_frame``).
    """
    v = wp.transpose(mat) * vec
    if gtype == GEOM_BOX:
        return _ray_box(p, v, size)
    if gtype == GEOM_PLANE:
        return _ray_plane(p, v, size)
    if gtype == GEOM_SPHERE:
        return _ray_sphere(p, v, size[0])
    if gtype == GEOM_CAPSULE:
        return _ray_capsule(p, v, size)
    if gtype == GEOM_CYLINDER:
        return _ray_cylinder(p, v, size)
    if gtype == GEOM_ELLIPSOID:
        return _ray_ellipsoid(p, v, size)
    return -1.0


@wp.func
def _better(sol: float, g: int, best: float, best_g: int) -> bool:
    """MuJoCo keeps the first geom (lowest id) among equal distances."""
    if not (sol >= 0.0) or sol > best:  # NaN is no hit, as mj_ray's x >= 0
        return False
    if best_g < 0 or sol < best:
        return True
    return g < best_g


@wp.kernel
def cast_brute(
    # Model:
    geom_type: wp.array2d(dtype=int),
    geom_size: wp.array2d(dtype=wp.vec3),
    geom_mat: wp.array2d(dtype=wp.mat33),
    geom_local: wp.array2d(dtype=wp.vec3),
    geom_rbound: wp.array2d(dtype=float),
    geom_enabled: wp.array2d(dtype=int),
    # In:
    dirs: wp.array2d(dtype=wp.vec3),
    max_range: wp.array(dtype=float),
    # Out:
    dist_out: wp.array2d(dtype=float),
    geom_out: wp.array2d(dtype=int),
):
    """Reference path: every enabled geom, in id order (launch [B, R]).

    geom_local: the scene's ray origin in each geom's frame; its norm is the origin's distance
    to the geom centre, which the bounding-sphere reject needs (rotations keep lengths).
    """
    s, r = wp.tid()
    vec = dirs[s, r]
    inv_len = 1.0 / wp.length(vec)
    best = max_range[s] * inv_len
    best_g = wp.int32(-1)
    for g in range(geom_type.shape[1]):
        if geom_enabled[s, g] == 0:
            continue
        p = geom_local[s, g]
        # Bounding-sphere reject: the ray's closest approach to the centre is too far.
        rb = geom_rbound[s, g]
        if rb < BIG:
            v = wp.transpose(geom_mat[s, g]) * vec  # the direction in the local frame
            tc = -wp.dot(p, v) * inv_len
            perp2 = wp.dot(p, p) - tc * tc
            slack = BOUND_ABS + BOUND_REL * (rb * rb + wp.dot(p, p))
            if perp2 > rb * rb + slack:
                continue
            if tc * inv_len > best + rb * inv_len:
                continue
        sol = ray_geom(geom_type[s, g], geom_size[s, g], p, geom_mat[s, g], vec)
        if _better(sol, g, best, best_g):
            best = sol
            best_g = g
    if best_g < 0:
        dist_out[s, r] = -1.0
    else:
        dist_out[s, r] = best
    geom_out[s, r] = best_g


@wp.func
def _toward(cos_t: float, cos_b: float, sin_b: float) -> float:
    """Max of cos(angle to a unit vector e) over a cone of half-angle b whose axis makes
    angle t with e, i.e. cos(max(0, t - b))."""
    if cos_t >= cos_b:
        return 1.0
    sin_t = wp.sqrt(wp.max(0.0, 1.0 - cos_t * cos_t))
    return cos_t * cos_b + sin_t * sin_b


@wp.func
def _least(cos_t: float, cos_b: float, sin_b: float) -> float:
    """Min of cos(angle to e) over the same cone, i.e. cos(min(pi, t + b))."""
    if -cos_t >= cos_b:
        return -1.0
    sin_t = wp.sqrt(wp.max(0.0, 1.0 - cos_t * cos_t))
    return cos_t * cos_b - sin_t * sin_b


@wp.func
def _build_cell(
    s: int,
    k: int,
    # Model:
    geom_mat: wp.array2d(dtype=wp.mat33),
    geom_local: wp.array2d(dtype=wp.vec3),
    geom_ext: wp.array2d(dtype=wp.vec3),
    geom_cone: wp.array2d(dtype=wp.vec4),
    geom_enabled: wp.array2d(dtype=int),
    geom_front: wp.array2d(dtype=int),
    # In:
    bin_axis: wp.array2d(dtype=wp.vec3),
    bin_cos: wp.array2d(dtype=float),
    bin_sin: wp.array2d(dtype=float),
    # Out:
    cand_geom_out: wp.array3d(dtype=int),
    cand_t_out: wp.array3d(dtype=float),
    cand_n_out: wp.array2d(dtype=int),
    cand_drop_out: wp.array2d(dtype=float),
):
    """Cell k of scene s: the geoms a ray of the cell may hit, sorted by a lower bound on
    the hit distance (``build_bins``).

    geom_local: the sensor in each geom's frame. geom_cone: (unit direction from the sensor to
    the bounding sphere's centre, sine of the sphere's angular radius), or w >= 1 when the
    sensor is inside the sphere or the geom is unbounded (then no cone test); all per geom
    from ``lidar._sensor_frame``, so that the per-cell loop only does what depends on the cell.
    geom_ext: half extents of the local bounding box (>= BIG for an unbounded plane axis);
    geom_front: 1 for planes (hit only from the front face, +z local).
    """
    axis = bin_axis[s, k]
    cb = bin_cos[s, k]
    sb = bin_sin[s, k]
    cap = cand_geom_out.shape[2]
    n = wp.int32(0)
    drop = wp.float32(BIG)
    for g in range(geom_local.shape[1]):
        if geom_enabled[s, g] == 0:
            continue
        cone = geom_cone[s, g]
        sa = cone[3]
        if sa < 1.0:
            # Cone of the cell vs cone subtended by the bounding sphere: reject when the angle
            # between the axes exceeds the sum of the half-angles (cos(a + b) when a + b < pi).
            ca = wp.sqrt(1.0 - sa * sa)
            thr = ca * cb - sa * sb
            if thr > -1.0 + 1.0e-6:
                if wp.dot(axis, wp.vec3(cone[0], cone[1], cone[2])) < thr - 1.0e-5:
                    continue
        # Slabs of the local bounding box. From outside slab i a ray must travel at least
        # the gap over the largest direction component toward it (a lower bound on the hit);
        # from inside, it leaves the slab after at most the distance to a face over the
        # smallest component toward that face (an upper bound). Every hit point lies in all
        # slabs at once, so a cell whose lower bound passes its upper bound cannot hit.
        lp = geom_local[s, g]
        la = wp.transpose(geom_mat[s, g]) * axis
        ext = geom_ext[s, g]
        t_lo = wp.float32(0.0)
        t_hi = wp.float32(BIG)
        reject = wp.int32(0)
        for i in range(3):
            e = ext[i]
            if e < BIG:
                gap = wp.abs(lp[i]) - e
                if gap > 0.0:
                    sgn = wp.float32(1.0)
                    if lp[i] > 0.0:
                        sgn = -1.0
                    m = _toward(sgn * la[i], cb, sb)
                    if m <= 1.0e-6:
                        reject = 1
                    else:
                        t_lo = wp.max(t_lo, gap / m)
                else:
                    # 1e-5 below the exact minimum: a margin for float32 rounding.
                    up = _least(la[i], cb, sb) - 1.0e-5
                    if up > 1.0e-6:
                        t_hi = wp.min(t_hi, (e - lp[i]) / up)
                    down = _least(-la[i], cb, sb) - 1.0e-5
                    if down > 1.0e-6:
                        t_hi = wp.min(t_hi, (e + lp[i]) / down)
        if geom_front[s, g] != 0:
            if lp[2] < 0.0:
                reject = 1  # behind a plane: mj_ray never hits its back face
        if sa < 1.0:
            t_lo = wp.max(t_lo, wp.length(lp) * (1.0 - sa))  # distance to the sphere
        if reject != 0:
            continue
        t_lo = t_lo * (1.0 - BOUND_REL) - BOUND_ABS
        if t_hi < BIG and t_lo > t_hi * (1.0 + BOUND_REL) + BOUND_ABS:
            continue
        # Sorted insertion into a list of capacity `cap`; the farthest falls off.
        if n == cap:
            if t_lo >= cand_t_out[s, k, cap - 1]:
                drop = wp.min(drop, t_lo)
                continue
            drop = wp.min(drop, cand_t_out[s, k, cap - 1])
            n = cap - 1
        j = n
        while j > 0 and cand_t_out[s, k, j - 1] > t_lo:
            cand_t_out[s, k, j] = cand_t_out[s, k, j - 1]
            cand_geom_out[s, k, j] = cand_geom_out[s, k, j - 1]
            j -= 1
        cand_t_out[s, k, j] = t_lo
        cand_geom_out[s, k, j] = g
        n += 1
    cand_n_out[s, k] = n
    cand_drop_out[s, k] = drop


@wp.kernel
def build_bins(
    # Model:
    geom_mat: wp.array2d(dtype=wp.mat33),
    geom_local: wp.array2d(dtype=wp.vec3),
    geom_ext: wp.array2d(dtype=wp.vec3),
    geom_cone: wp.array2d(dtype=wp.vec4),
    geom_enabled: wp.array2d(dtype=int),
    geom_front: wp.array2d(dtype=int),
    # In:
    bin_axis: wp.array2d(dtype=wp.vec3),
    bin_cos: wp.array2d(dtype=float),
    bin_sin: wp.array2d(dtype=float),
    # Out:
    cand_geom_out: wp.array3d(dtype=int),
    cand_t_out: wp.array3d(dtype=float),
    cand_n_out: wp.array2d(dtype=int),
    cand_drop_out: wp.array2d(dtype=float),
):
    """Per cube-map cell, the geoms a ray of the cell may hit, sorted (launch [B, cells])."""
    s, k = wp.tid()
    _build_cell(
        s,
        k,
        geom_mat,
        geom_local,
        geom_ext,
        geom_cone,
        geom_enabled,
        geom_front,
        bin_axis,
        bin_cos,
        bin_sin,
        cand_geom_out,
        cand_t_out,
        cand_n_out,
        cand_drop_out,
    )


@wp.func
def dir_cell(v: wp.vec3, n: int) -> int:
    """Cube-map cell of a direction (faces +x, -x, +y, -y, +z, -z; n x n cells each)."""
    ax = wp.abs(v[0])
    ay = wp.abs(v[1])
    az = wp.abs(v[2])
    face = wp.int32(0)
    u = wp.float32(0.0)
    w = wp.float32(0.0)
    if ax >= ay and ax >= az:
        face = 0
        if v[0] < 0.0:
            face = 1
        u = v[1] / ax
        w = v[2] / ax
    elif ay >= az:
        face = 2
        if v[1] < 0.0:
            face = 3
        u = v[0] / ay
        w = v[2] / ay
    else:
        face = 4
        if v[2] < 0.0:
            face = 5
        u = v[0] / az
        w = v[1] / az
    i = wp.clamp(int((u + 1.0) * 0.5 * float(n)), 0, n - 1)
    j = wp.clamp(int((w + 1.0) * 0.5 * float(n)), 0, n - 1)
    return (face * n + i) * n + j


@wp.func
def _cast_ray(
    s: int,
    r: int,
    k: int,
    # Model:
    geom_type: wp.array2d(dtype=int),
    geom_size: wp.array2d(dtype=wp.vec3),
    geom_mat: wp.array2d(dtype=wp.mat33),
    geom_local: wp.array2d(dtype=wp.vec3),
    geom_enabled: wp.array2d(dtype=int),
    cand_geom: wp.array3d(dtype=int),
    cand_t: wp.array3d(dtype=float),
    cand_n: wp.array2d(dtype=int),
    cand_drop: wp.array2d(dtype=float),
    # In:
    dirs: wp.array2d(dtype=wp.vec3),
    max_range: wp.array(dtype=float),
    # Out:
    dist_out: wp.array2d(dtype=float),
    geom_out: wp.array2d(dtype=int),
):
    """Closest hit of ray r of scene s, whose direction lies in cube-map cell k, using the
    cell lists of ``build_bins``."""
    vec = dirs[s, r]
    inv_len = 1.0 / wp.length(vec)
    best = max_range[s] * inv_len
    best_g = wp.int32(-1)
    for c in range(cand_n[s, k]):
        # Bounds are in metres; ray parameters are in units of |vec|.
        if cand_t[s, k, c] * inv_len > best:
            break
        g = cand_geom[s, k, c]
        sol = ray_geom(geom_type[s, g], geom_size[s, g], geom_local[s, g], geom_mat[s, g], vec)
        if _better(sol, g, best, best_g):
            best = sol
            best_g = g
    if cand_drop[s, k] < BIG and cand_drop[s, k] * inv_len <= best:
        # The cell overflowed its list: finish with every geom (rare, still exact).
        for g in range(geom_type.shape[1]):
            if geom_enabled[s, g] == 0:
                continue
            sol = ray_geom(geom_type[s, g], geom_size[s, g], geom_local[s, g], geom_mat[s, g], vec)
            if _better(sol, g, best, best_g):
                best = sol
                best_g = g
    if best_g < 0:
        dist_out[s, r] = -1.0
    else:
        dist_out[s, r] = best
    geom_out[s, r] = best_g


@wp.kernel
def cast_binned(
    # Model:
    geom_type: wp.array2d(dtype=int),
    geom_size: wp.array2d(dtype=wp.vec3),
    geom_mat: wp.array2d(dtype=wp.mat33),
    geom_local: wp.array2d(dtype=wp.vec3),
    geom_enabled: wp.array2d(dtype=int),
    cand_geom: wp.array3d(dtype=int),
    cand_t: wp.array3d(dtype=float),
    cand_n: wp.array2d(dtype=int),
    cand_drop: wp.array2d(dtype=float),
    # In:
    dirs: wp.array2d(dtype=wp.vec3),
    max_range: wp.array(dtype=float),
    cells_per_edge: int,
    rays_per_thread: int,
    # Out:
    dist_out: wp.array2d(dtype=float),
    geom_out: wp.array2d(dtype=int),
):
    """Closest hit per ray (launch [B, ceil(R / rays_per_thread)]).

    Each thread casts ``rays_per_thread`` consecutive rays: 1 on CUDA; on the CPU, where a
    launch runs its threads one after another and sets each up anew, ``CPU_RAYS_PER_THREAD``
    (at one ray per thread the setup was a third of a 20k-ray frame).
    """
    s, q = wp.tid()
    for r in range(q * rays_per_thread, wp.min((q + 1) * rays_per_thread, dirs.shape[1])):
        k = dir_cell(dirs[s, r], cells_per_edge)
        _cast_ray(s, r, k, geom_type, geom_size, geom_mat, geom_local, geom_enabled, cand_geom,
                  cand_t, cand_n, cand_drop, dirs, max_range, dist_out, geom_out)  # fmt: skip


@wp.kernel
def build_and_cast_cpu(
    # Model (build):
    geom_mat: wp.array2d(dtype=wp.mat33),
    geom_local: wp.array2d(dtype=wp.vec3),
    geom_ext: wp.array2d(dtype=wp.vec3),
    geom_cone: wp.array2d(dtype=wp.vec4),
    geom_enabled: wp.array2d(dtype=int),
    geom_front: wp.array2d(dtype=int),
    # In (build):
    bin_axis: wp.array2d(dtype=wp.vec3),
    bin_cos: wp.array2d(dtype=float),
    bin_sin: wp.array2d(dtype=float),
    # Model (cast):
    geom_type: wp.array2d(dtype=int),
    geom_size: wp.array2d(dtype=wp.vec3),
    # In:
    dirs: wp.array2d(dtype=wp.vec3),
    max_range: wp.array(dtype=float),
    cells_per_edge: int,
    rays_per_thread: int,
    # Out:
    cand_geom_out: wp.array3d(dtype=int),
    cand_t_out: wp.array3d(dtype=float),
    cand_n_out: wp.array2d(dtype=int),
    cand_drop_out: wp.array2d(dtype=float),
    dist_out: wp.array2d(dtype=float),
    geom_out: wp.array2d(dtype=int),
):
    """``build_bins`` and ``cast_binned`` in one CPU launch ([B, cells + ray chunks]), each
    cell built only when a ray first falls in it.

    The first ``cells`` threads of a scene mark its cells unbuilt (``cand_n_out`` -1); the
    ray chunks then build a cell on its first use. That relies on a CPU launch running its
    threads one after another, in order (Warp's CPU backend), so never launch this on CUDA.
    One launch instead of two halves the FFI round trips, and cells no ray reaches (most of
    the cube below a MID-360's -7 deg, for one) cost nothing. ``cand_*_out`` of unbuilt cells
    are left undefined.
    """
    s, t = wp.tid()
    ncell = bin_axis.shape[1]
    if t < ncell:
        cand_n_out[s, t] = -1
        return
    q = t - ncell
    for r in range(q * rays_per_thread, wp.min((q + 1) * rays_per_thread, dirs.shape[1])):
        k = dir_cell(dirs[s, r], cells_per_edge)
        if cand_n_out[s, k] < 0:
            _build_cell(s, k, geom_mat, geom_local, geom_ext, geom_cone, geom_enabled, geom_front,
                        bin_axis, bin_cos, bin_sin, cand_geom_out, cand_t_out, cand_n_out,
                        cand_drop_out)  # fmt: skip
        _cast_ray(s, r, k, geom_type, geom_size, geom_mat, geom_local, geom_enabled,
                  cand_geom_out, cand_t_out, cand_n_out, cand_drop_out, dirs, max_range,
                  dist_out, geom_out)  # fmt: skip


# ----------------------------------------------------------------------------- CPU threads
# A Warp CPU launch runs on one thread, and XLA runs FFI calls one after another, so on the
# CPU the bridge (``lidar.py``) calls the functions below through ``wp.jax_callable``: each
# deals the launch's second axis (rays, or cube-map cells) out round-robin over ``threads``
# threads (neighbouring rays cost about the same, so the shares balance). The kernels release
# the GIL while they run; results are identical to one launch.

# Below this many rays per thread a launch stays on one thread: waking an idle second core
# costs milliseconds on the 2-core VMs we measured, so a split pays only from about 300k rays
# after an idle spell (docs/BENCHMARKS.md, "Lidar"). A cube-map cell costs about as much as
# CELL_COST rays (it tests every geom; ~0.3 us vs 0.045 us).
MIN_ITEMS_PER_THREAD = 131072
CELL_COST = 8
# Rays one CPU kernel thread casts (``cast_binned``'s rays_per_thread; 1 on CUDA).
CPU_RAYS_PER_THREAD = 256
_pool: ThreadPoolExecutor | None = None
_pool_workers = 0
_pool_lock = threading.Lock()


def _executor(workers: int) -> ThreadPoolExecutor:
    global _pool, _pool_workers
    with _pool_lock:
        if _pool_workers < workers:
            if _pool is not None:
                _pool.shutdown(wait=False)
            _pool = ThreadPoolExecutor(workers, thread_name_prefix="indoorbev-lidar")
            _pool_workers = workers
        return _pool


def split_threads(threads: int, nscene: int, n: int, item_cost: int = 1) -> int:
    """Threads a launch of ``nscene * n`` items of cost ``item_cost`` rays is shared over."""
    return max(1, min(int(threads), (nscene * n * item_cost) // MIN_ITEMS_PER_THREAD))


def launch_split(
    kernel,
    inputs: list,
    outputs: list,
    split: set[int],
    threads: int,
    item_cost: int = 1,
    per_thread: int = 1,
) -> None:
    """``wp.launch`` over the (B, N) items of ``outputs[0].shape``, N shared by up to ``threads``.

    ``split``: positions of the inputs indexed by the second launch axis (every output is).
    ``item_cost``: work of one launch item in rays, for the one-thread threshold.
    ``per_thread``: items one kernel thread handles (the launch is [B, ceil(N / per_thread)]).
    """
    nscene, n = outputs[0].shape[:2]
    threads = split_threads(threads, nscene, n, item_cost)
    device = outputs[0].device

    def dims(outs) -> tuple[int, int]:
        return nscene, -(-outs[0].shape[1] // per_thread)

    def share(t: int) -> None:
        ins = [x[:, t::threads] if i in split else x for i, x in enumerate(inputs)]
        outs = [x[:, t::threads] for x in outputs]
        wp.launch(kernel, dim=dims(outs), inputs=ins, outputs=outs, device=device)

    if threads == 1 or not device.is_cpu:
        wp.launch(kernel, dim=dims(outputs), inputs=inputs, outputs=outputs, device=device)
        return
    pending = [_executor(threads - 1).submit(share, t) for t in range(1, threads)]
    share(0)
    for p in pending:
        p.result()


def threaded(kernel, num_outputs: int, split: tuple[str, ...], item_cost: int = 1):
    """A host function for ``wp.jax_callable`` that runs ``kernel`` through ``launch_split``.

    Its signature is the kernel's, with ``threads: int`` after the inputs (``jax_callable``
    reads the annotations); ``split`` names the inputs indexed by the second launch axis. A
    kernel input named ``rays_per_thread`` sets ``launch_split``'s ``per_thread``.
    """
    hints = inspect.get_annotations(kernel.func, eval_str=True)
    names = list(inspect.signature(kernel.func).parameters)
    inputs, outputs = names[:-num_outputs], names[-num_outputs:]
    split_at = {inputs.index(n) for n in split}
    per_at = inputs.index("rays_per_thread") if "rays_per_thread" in inputs else None
    n_in = len(inputs)

    def host(*args):
        per = 1 if per_at is None else int(args[per_at])
        launch_split(kernel, list(args[:n_in]), list(args[n_in + 1 :]), split_at, args[n_in],
                     item_cost, per)  # fmt: skip

    param = functools.partial(inspect.Parameter, kind=inspect.Parameter.POSITIONAL_OR_KEYWORD)
    params = [param(n, annotation=hints[n]) for n in inputs]
    params += [param("threads", annotation=int)] + [param(n, annotation=hints[n]) for n in outputs]
    host.__signature__ = inspect.Signature(params)
    host.__annotations__ = {q.name: q.annotation for q in params}
    host.__name__ = host.__qualname__ = f"{kernel.key}_threads"
    return host
