"""Lidar ray casting over MJX scenes with Warp kernels, callable inside ``jax.jit``.

The public entry point is :func:`cast_rays`; it follows MuJoCo's ``mj_ray`` (a miss, or a
hit beyond ``max_range``, gives distance -1 and geom id -1; rays starting inside a primitive
hit its far side; planes only from the front; invisible geoms, ``geomgroup``, ``flg_static``
and ``bodyexclude`` filter as in ``mj_ray``). Kernels live in ``_lidar_kernels.py``; see
docs/SIMULATOR.md ("## Lidar") for the algorithm and the grazing-incidence discussion.
Where warp-lang is not installed, ``method="jax"`` (``_lidar_jax.py``, the same arithmetic
as array code, no culling) casts on any JAX backend, and is the default there.

Example:
  >>> m = mujoco.MjModel.from_xml_string(xml)
  >>> d = mujoco.MjData(m)
  >>> mujoco.mj_forward(m, d)  # poses; mjx.kinematics refuses a model without joints
  >>> mx, dx = mjx.put_model(m), mjx.put_data(m, d)
  >>> dist, geom = jax.jit(cast_rays)(mx, dx, jnp.zeros(3), dirs, 20.0)  # dirs [R, 3]
"""

from __future__ import annotations

import atexit
import functools
import os
import sys
import warnings

import jax
import jax.numpy as jnp
import mujoco
import numpy as np
from flax import struct

from . import _lidar_jax
from . import _ray_constants as rc

SUPPORTED_TYPES = {
    rc.PLANE: "plane",
    rc.SPHERE: "sphere",
    rc.CAPSULE: "capsule",
    rc.ELLIPSOID: "ellipsoid",
    rc.CYLINDER: "cylinder",
    rc.BOX: "box",
}
DEFAULT_CAPACITY = 16


@struct.dataclass
class SceneGeometry:
    """World-frame primitives of B scenes, the kernels' view of an MJX model/data pair.

    Attributes:
      geom_type: int32 [B, G], ``mjtGeom`` ids (unsupported geoms are disabled).
      size: float32 [B, G, 3], ``geom_size``.
      pos: float32 [B, G, 3], ``geom_xpos``.
      mat: float32 [B, G, 3, 3], ``geom_xmat``.
      ext: float32 [B, G, 3], half extents of the local bounding box (1e30: unbounded).
      rbound: float32 [B, G], bounding-sphere radius about ``pos`` (1e30: unbounded).
      enabled: int32 [B, G], 1 for geoms that rays may hit (after all filters).
      front: int32 [B, G], 1 for planes (hit from their +z side only).
      types: static (not a pytree leaf) tuple of the G ``mjtGeom`` ids, or None; the
        "jax" caster casts one type at a time when it is known.
      batched: static; False when made from one unbatched scene (B = 1), whose single-ray-
        set casts then drop the scene axis, as ``cast_rays`` promises.
    """

    geom_type: jax.Array
    size: jax.Array
    pos: jax.Array
    mat: jax.Array
    ext: jax.Array
    rbound: jax.Array
    enabled: jax.Array
    front: jax.Array
    types: tuple[int, ...] | None = struct.field(pytree_node=False, default=None)
    batched: bool = struct.field(pytree_node=False, default=True)


def _static_np(x, name: str) -> np.ndarray:
    try:
        return np.asarray(x)
    except jax.errors.TracerArrayConversionError as e:
        raise ValueError(
            f"model.{name} must be static (a numpy array, as mjx.put_model gives); got a traced "
            "value. Batch the model's geom_size/geom_rgba, not its structure."
        ) from e


def scene_geometry(
    model,
    data,
    *,
    geomgroup=None,
    flg_static: bool = True,
    bodyexclude: int = -1,
    skip_unsupported: bool = False,
) -> SceneGeometry:
    """Collects the primitives of one scene or a batch of B scenes.

    Args:
      model: ``mjx.Model``; ``geom_size``/``geom_rgba``/``geom_matid``/``mat_rgba`` may carry a
        leading batch axis B, ``geom_type`` and the body tables must be static (numpy).
      data: ``mjx.Data`` after kinematics; ``geom_xpos`` of shape [G, 3] or [B, G, 3].
      geomgroup: optional 6 flags; geoms whose group flag is 0 are skipped (as ``mj_ray``).
      flg_static: if False, geoms on bodies welded to the world are skipped.
      bodyexclude: geoms of this body id are skipped (-1: none).
      skip_unsupported: skip mesh/hfield/sdf geoms instead of raising.

    Returns:
      ``SceneGeometry`` with a leading scene axis (B = 1 for an unbatched scene).

    Raises:
      ValueError: unsupported geom types present (naming them) and not skipped.
    """
    geom_type = _static_np(model.geom_type, "geom_type").astype(np.int32)
    if geom_type.ndim == 2:
        if not (geom_type == geom_type[:1]).all():
            raise ValueError("model.geom_type differs across the batch; scenes must share it")
        geom_type = geom_type[0]
    ngeom = geom_type.shape[0]
    supported = np.isin(geom_type, list(SUPPORTED_TYPES))
    if not supported.all() and not skip_unsupported:
        bad = [
            f"geom {i} ({mujoco.mjtGeom(int(t)).name})"
            for i, t in enumerate(geom_type)
            if not supported[i]
        ]
        raise ValueError(
            "cast_rays supports plane, sphere, capsule, ellipsoid, cylinder and box geoms; "
            f"unsupported: {', '.join(bad)} (pass skip_unsupported=True to ignore them)"
        )

    # Static filters, as mj_ray's ray_eliminate.
    # reshape(-1)[:ngeom]: the first scene's row, also for ngeom = 0 (reshape(-1, 0) fails).
    bodyid = _static_np(model.geom_bodyid, "geom_bodyid").reshape(-1)[:ngeom]
    keep = supported & (bodyid != bodyexclude)
    if not flg_static:
        weld = _static_np(model.body_weldid, "body_weldid").reshape(-1, model.nbody)[0]
        keep &= weld[bodyid] != 0
    if geomgroup is not None:
        flags = np.asarray(geomgroup).reshape(-1)
        if flags.shape != (mujoco.mjNGROUP,):
            raise ValueError(f"geomgroup must hold {mujoco.mjNGROUP} flags, got {flags.shape}")
        group = _static_np(model.geom_group, "geom_group").reshape(-1)[:ngeom]
        keep &= flags[np.clip(group, 0, mujoco.mjNGROUP - 1)] != 0

    pos = jnp.asarray(data.geom_xpos, jnp.float32)
    batched = pos.ndim == 3
    pos = pos if batched else pos[None]  # [B, G, 3]
    nscene = pos.shape[0]
    mat = jnp.asarray(data.geom_xmat, jnp.float32).reshape(nscene, ngeom, 3, 3)

    def per_scene(x, tail):  # broadcast model fields to [B, G, *tail]
        x = jnp.asarray(x)
        x = x.reshape(-1, ngeom, *tail) if ngeom else jnp.zeros((1, 0, *tail), x.dtype)
        return jnp.broadcast_to(x, (nscene, ngeom, *tail))

    size = per_scene(model.geom_size, (3,)).astype(jnp.float32)
    # Invisible geoms (alpha 0 of the geom or of its material) are skipped by mj_ray.
    rgba_a = per_scene(model.geom_rgba, (4,))[..., 3]
    matid = per_scene(model.geom_matid, ())
    mat_rgba = jnp.asarray(model.mat_rgba)
    if mat_rgba.shape[-2] > 0:
        mat_a = jnp.broadcast_to(
            mat_rgba.reshape(-1, *mat_rgba.shape[-2:]), (nscene,) + mat_rgba.shape[-2:]
        )
        mat_a = jnp.take_along_axis(mat_a[..., 3], jnp.maximum(matid, 0), axis=1)
        alpha = jnp.where(matid >= 0, mat_a, rgba_a)
    else:
        alpha = rgba_a
    enabled = (alpha != 0) & jnp.asarray(keep)[None]

    gtype = jnp.broadcast_to(jnp.asarray(geom_type)[None], (nscene, ngeom))
    ext, rbound = _bounds(geom_type, size)
    front = jnp.broadcast_to(jnp.asarray(geom_type == rc.PLANE, jnp.int32)[None], (nscene, ngeom))
    return SceneGeometry(
        geom_type=gtype,
        size=size,
        pos=pos,
        mat=mat,
        ext=ext,
        rbound=rbound,
        enabled=enabled.astype(jnp.int32),
        front=front,
        types=tuple(int(t) for t in geom_type),
        batched=batched,
    )


def _bounds(geom_type: np.ndarray, size: jax.Array) -> tuple[jax.Array, jax.Array]:
    """Local bounding-box half extents [B, G, 3] and bounding-sphere radius [B, G]."""
    r, h = size[..., 0], size[..., 1]
    t = jnp.asarray(geom_type)[None, :, None]
    big = jnp.float32(rc.BIG)
    plane = jnp.stack(
        [jnp.where(r > 0, r, big), jnp.where(h > 0, h, big), jnp.zeros_like(r)], axis=-1
    )
    ext = jnp.select(
        [t == rc.PLANE, t == rc.SPHERE, t == rc.CAPSULE, t == rc.CYLINDER],
        [
            plane,
            jnp.stack([r, r, r], -1),
            jnp.stack([r, r, h + r], -1),
            jnp.stack([r, r, h], -1),
        ],
        size,  # ellipsoid, box: size is the half extent
    )
    tt = t[..., 0]
    rbound = jnp.select(
        [tt == rc.SPHERE, tt == rc.CAPSULE, tt == rc.ELLIPSOID],
        [r, r + h, jnp.max(size, axis=-1)],
        jnp.linalg.norm(jnp.minimum(ext, 1.0e6), axis=-1),  # box, cylinder, finite plane
    )
    rbound = jnp.where(jnp.any(ext >= big, axis=-1), big, rbound)
    return ext.astype(jnp.float32), rbound.astype(jnp.float32)


# ----------------------------------------------------------------------------- cube map


@functools.cache
def _cube_cells(n: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Axis, cos and sin of the bounding cone of each of the 6 n n cube-map cells.

    Cell order matches ``_lidar_kernels.dir_cell``. Returns arrays [6 n n, 3], [6 n n],
    [6 n n] (float32).
    """
    edges = np.linspace(-1.0, 1.0, n + 1)
    mid = 0.5 * (edges[:-1] + edges[1:])

    def on_face(face, u, w):  # face-local (u, w) -> direction, as dir_cell inverts it
        one = np.ones_like(u)
        s = 1.0 if face % 2 == 0 else -1.0
        return [
            np.stack([s * one, u, w], -1),
            np.stack([s * one, u, w], -1),
            np.stack([u, s * one, w], -1),
            np.stack([u, s * one, w], -1),
            np.stack([u, w, s * one], -1),
            np.stack([u, w, s * one], -1),
        ][face]

    def unit(x):
        return x / np.linalg.norm(x, axis=-1, keepdims=True)

    axes, cosb = [], []
    for face in range(6):
        ui, wi = np.meshgrid(np.arange(n), np.arange(n), indexing="ij")  # [n, n]
        axis = unit(on_face(face, mid[ui], mid[wi]))
        worst = np.ones(ui.shape)
        for du in (0, 1):
            for dw in (0, 1):
                corner = unit(on_face(face, edges[ui + du], edges[wi + dw]))
                worst = np.minimum(worst, np.sum(axis * corner, -1))
        axes.append(axis.reshape(-1, 3))
        cosb.append(worst.reshape(-1))
    axis = np.concatenate(axes)
    # Widen each cone a little (about 1e-3 rad) so float32 cell lookups stay inside it.
    beta = np.arccos(np.clip(np.concatenate(cosb), -1.0, 1.0)) + 1.0e-3
    return axis.astype(np.float32), np.cos(beta).astype(np.float32), np.sin(beta).astype(np.float32)


def default_cells_per_edge(num_rays: int) -> int:
    """Cube-map resolution (cells per cube edge), 12 for a 20k-ray frame, 16 from ~400k rays.

    Finer cells shorten each ray's candidate list but cost build time (cells x geoms); these
    values were the fastest in experiments/bench_lidar.py's room (docs/BENCHMARKS.md).
    """
    return int(np.clip(round(num_rays**0.2 * 1.7), 6, 16))


# ----------------------------------------------------------------------------- Warp bridge


METHODS = ("binned", "brute", "jax")


@functools.cache
def _warp():
    """``(warp, _lidar_kernels)``, imported on first use so the "jax" method needs no Warp."""
    try:
        import warp as wp
    except ImportError as e:
        raise ImportError(
            "the 'binned' and 'brute' ray casters need warp-lang (pip install warp-lang); "
            "method='jax' casts without it"
        ) from e
    from . import _lidar_kernels

    return wp, _lidar_kernels


def warp_available() -> bool:
    """Whether warp-lang can be imported (it decides the default ``method``)."""
    try:
        _warp()
    except ImportError:
        return False
    return True


@functools.cache
def default_method() -> str:
    """The caster used when ``method`` is None: ``$INDOORBEV_LIDAR_METHOD`` if set, else
    "binned" (Warp), or "jax" with a warning where warp-lang is not installed."""
    env = os.environ.get("INDOORBEV_LIDAR_METHOD", "")
    if env:
        if env not in METHODS:
            raise ValueError(f"INDOORBEV_LIDAR_METHOD must be one of {METHODS}, got {env!r}")
        return env
    if warp_available():
        return "binned"
    warnings.warn(
        "warp-lang is not installed: casting lidar rays with the pure-JAX caster "
        "(method='jax', every ray against every geom; fine on a GPU, slow on a CPU)",
        stacklevel=_caller_stacklevel(),
    )
    return "jax"


def _caller_stacklevel() -> int:
    """The ``warnings.warn`` stack level, for a warning raised by our caller, of the first
    frame outside our packages, JAX, Flax and the standard library: the user's line, however
    deep inside a trace the warning was raised."""
    import contextlib

    import flax
    import jaxlib

    modules = [jax, jaxlib, flax, sys.modules[__package__], sys.modules.get("indoorbev_jax")]
    packages = tuple(os.path.dirname(m.__file__) + os.sep for m in modules if m is not None)
    stdlib = os.path.dirname(contextlib.__file__)

    def internal(filename: str) -> bool:
        return filename.startswith(packages) or os.path.dirname(filename) == stdlib

    frame, level = sys._getframe(2), 2
    while frame.f_back is not None and internal(frame.f_code.co_filename):
        frame, level = frame.f_back, level + 1
    return level


def _resolve_method(method: str | None) -> str:
    """``method``, or ``default_method()`` for None; a ValueError for an unknown name."""
    method = default_method() if method is None else method
    if method not in METHODS:
        raise ValueError(f"method must be one of {METHODS} (or None), got {method!r}")
    return method


def _kernels(name: str):
    """Kernel, number of outputs, inputs indexed by the second launch axis, cost of one
    launch item in rays (for the one-thread threshold of ``_lidar_kernels.launch_split``)."""
    K = _warp()[1]
    return {
        "brute": (K.cast_brute, 2, ("dirs",), 1),
        "build": (K.build_bins, 4, ("bin_axis", "bin_cos", "bin_sin"), K.CELL_COST),
        "binned": (K.cast_binned, 2, ("dirs",), 1),
        "fused": (K.build_and_cast_cpu, 6, (), 1),  # CPU only, one thread
    }[name]


@functools.cache
def _wait_at_exit() -> None:
    """Registers, once, an exit hook that waits for the device work still running.

    Warp's casts run as Python host functions inside XLA programs. A script that ends while
    one is queued (it read only ``.shape`` of a batch) hung for good: Python's shutdown
    waits for XLA's worker thread, which waits for the interpreter lock to run the cast.
    The hook blocks on the live arrays, then on one trivial program per device: a device
    runs its programs in order (JAX's runtime tokens rely on it), so that also waits for
    programs whose results were dropped."""

    def wait() -> None:
        try:
            step = jax.jit(lambda x: x + 1)
            for platform in {"cpu", jax.default_backend()}:  # casts may sit on the CPU
                jax.block_until_ready(jax.live_arrays(platform))
                for device in jax.local_devices(backend=platform):
                    step(jax.device_put(np.int32(0), device)).block_until_ready()
        except Exception:  # noqa: BLE001 - at exit there is no one left to tell
            pass

    atexit.register(wait)


@functools.cache
def _ffi(name: str):
    """One Warp launch per call (CUDA, or a CPU caster told to use one thread)."""
    _wait_at_exit()
    kernel, nout, _, _ = _kernels(name)
    return _warp()[0].jax_kernel(kernel, num_outputs=nout)


@functools.cache
def _ffi_threads(name: str):
    """The launch shared over CPU threads (``_lidar_kernels.launch_split``)."""
    _wait_at_exit()
    kernel, nout, split, cost = _kernels(name)
    wp, K = _warp()
    return wp.jax_callable(
        K.threaded(kernel, nout, split, cost), num_outputs=nout, vmap_method=None
    )


def default_cpu_threads() -> int:
    """CPU threads a caster uses by default: the cores this process may run on."""
    try:
        return len(os.sched_getaffinity(0))
    except AttributeError:  # not on Linux
        return os.cpu_count() or 1


def _launch(name: str, *arrays, static=(), launch_dims, output_dims=None, threads: int = 1):
    """A kernel launch that shares its second axis over ``threads`` threads on the CPU.

    ``static``: the kernel's trailing scalar arguments (Python values, not traced).
    """
    if output_dims is None:
        output_dims = launch_dims

    def one_launch(*a):
        return _ffi(name)(*a, *static, launch_dims=launch_dims, output_dims=output_dims)

    if threads <= 1:
        return one_launch(*arrays)

    def on_threads(*a):
        return _ffi_threads(name)(*a, *static, threads, output_dims=output_dims)

    return jax.lax.platform_dependent(*arrays, cpu=on_threads, default=one_launch)


def _sensor_frame(geo: SceneGeometry, origin: jax.Array) -> tuple[jax.Array, jax.Array]:
    """What every ray of a scene shares per geom, computed once instead of per ray or cell.

    Args:
      geo: B scenes.
      origin: [B, 3] the scenes' ray origins.

    Returns:
      ``(local, cone)``: local [B, G, 3] the origin in each geom's frame
      (``geom_xmat^T (origin - geom_xpos)``); cone [B, G, 4] the unit direction from the
      origin to the geom centre and the sine of its bounding sphere's angular radius, whose
      value 1 means no cone (origin inside the sphere, or an unbounded geom).
    """
    dif = geo.pos - origin[:, None, :]  # [B, G, 3] origin -> centre
    local = jnp.einsum("bgji,bgj->bgi", geo.mat, -dif)
    d = jnp.linalg.norm(dif, axis=-1)  # [B, G]
    has_cone = (geo.rbound < rc.BIG) & (d > geo.rbound)
    sin_a = jnp.where(has_cone, geo.rbound / jnp.where(has_cone, d, 1.0), 1.0)
    unit = dif / jnp.where(d > 0, d, 1.0)[..., None]
    return local, jnp.concatenate([unit, sin_a[..., None]], -1).astype(jnp.float32)


def _cast_impl(geo: SceneGeometry, dirs, origin, max_range, *, method, cells, capacity, threads):
    """All inputs batched over scenes: dirs [B, R, 3], origin [B, 3], max_range [B]."""
    nscene, nray = dirs.shape[:2]
    local, cone = _sensor_frame(geo, origin)
    if method == "brute":
        return _launch(
            "brute",
            geo.geom_type,
            geo.size,
            geo.mat,
            local,
            geo.rbound,
            geo.enabled,
            dirs,
            max_range,
            launch_dims=(nscene, nray),
            threads=threads,
        )
    axis, cosb, sinb = _cube_cells(cells)
    ncell = axis.shape[0]
    tables = [jnp.broadcast_to(jnp.asarray(x), (nscene,) + x.shape) for x in (axis, cosb, sinb)]
    cand_dims = {
        "cand_geom_out": (nscene, ncell, capacity),
        "cand_t_out": (nscene, ncell, capacity),
        "cand_n_out": (nscene, ncell),
        "cand_drop_out": (nscene, ncell),
    }
    ray_dims = {"dist_out": (nscene, nray), "geom_out": (nscene, nray)}

    def two_launches(mat, local, ext, cone, enabled, front, ax, cb, sb, gtype, size, dirs, mr,
                     *, per: int, split: int):  # fmt: skip
        """build_bins, then cast_binned (per rays a kernel thread, split CPU threads)."""
        cell_in = (mat, local, ext, cone, enabled, front, ax, cb, sb)
        if split > 1:
            cand = _ffi_threads("build")(*cell_in, split, output_dims=cand_dims)
            return _ffi_threads("binned")(gtype, size, mat, local, enabled, *cand, dirs, mr,
                                          cells, per, split, output_dims=ray_dims)  # fmt: skip
        cand = _ffi("build")(*cell_in, launch_dims=(nscene, ncell), output_dims=cand_dims)
        chunks = -(-nray // per)
        return _ffi("binned")(gtype, size, mat, local, enabled, *cand, dirs, mr, cells, per,
                              launch_dims=(nscene, chunks), output_dims=ray_dims)  # fmt: skip

    def on_cpu(*args):
        K = _warp()[1]
        per = K.CPU_RAYS_PER_THREAD
        ray_split = K.split_threads(threads, nscene, nray)
        cell_split = K.split_threads(threads, nscene, ncell, K.CELL_COST)
        if max(ray_split, cell_split) > 1:
            return two_launches(*args, per=per, split=threads)
        # One launch that builds each cell on first use (CPU launches run threads in order).
        out = _ffi("fused")(*args, cells, per, launch_dims=(nscene, ncell + -(-nray // per)),
                            output_dims={**cand_dims, **ray_dims})  # fmt: skip
        return out[-2:]

    def on_gpu(*args):
        return two_launches(*args, per=1, split=1)

    args = (geo.mat, local, geo.ext, cone, geo.enabled, geo.front, *tables, geo.geom_type,
            geo.size, dirs, max_range)  # fmt: skip
    dist, gid = jax.lax.platform_dependent(*args, cpu=on_cpu, default=on_gpu)
    return dist, gid


@functools.cache
def _batched_caster(method: str, cells: int, capacity: int, threads: int):
    """A scene-batched caster whose vmap folds the mapped axis into the scene axis."""

    @jax.custom_batching.custom_vmap
    def cast(geo, dirs, origin, max_range):
        dist, gid = _cast_impl(
            geo,
            dirs,
            origin,
            max_range,
            method=method,
            cells=cells,
            capacity=capacity,
            threads=threads,
        )
        return dist, gid

    @cast.def_vmap
    def _(axis_size, in_batched, geo, dirs, origin, max_range):
        def fold(x, batched):  # [V, B, ...] -> [V * B, ...]
            if not batched:
                x = jnp.broadcast_to(x, (axis_size,) + x.shape)
            return x.reshape((-1,) + x.shape[2:])

        flat = jax.tree.map(fold, (geo, dirs, origin, max_range), tuple(in_batched))
        dist, gid = cast(*flat)
        nscene = dirs.shape[1] if in_batched[1] else dirs.shape[0]
        unfold = lambda x: x.reshape((axis_size, nscene) + x.shape[1:])  # noqa: E731
        return (unfold(dist), unfold(gid)), (True, True)

    return cast


# Elements of one [B, R, G] array the "jax" caster holds at once; more rays go in chunks.
JAX_CHUNK_ELEMENTS = 1 << 25


def _cast_jax(geo: SceneGeometry, dirs, origin, max_range):
    """The "jax" method: dirs [B, R, 3], origin [B, 3], max_range [B]."""
    local, _ = _sensor_frame(geo, origin)
    nscene, nray = dirs.shape[:2]
    ngeom = geo.geom_type.shape[1]
    chunk = max(1, JAX_CHUNK_ELEMENTS // max(1, nscene * ngeom))
    fields = (geo.geom_type, geo.size, geo.mat, local, geo.rbound, geo.enabled)
    if nray <= chunk:
        return _lidar_jax.cast(*fields, dirs, max_range, geo.types)
    nchunk = -(-nray // chunk)
    padded = jnp.pad(dirs, ((0, 0), (0, nchunk * chunk - nray), (0, 0)), constant_values=1.0)
    pieces = padded.reshape(nscene, nchunk, chunk, 3).transpose(1, 0, 2, 3)  # [K, B, chunk, 3]
    dist, gid = jax.lax.map(lambda d: _lidar_jax.cast(*fields, d, max_range, geo.types), pieces)
    # [K, B, chunk] -> [B, R]
    unchunk = lambda x: x.transpose(1, 0, 2).reshape(nscene, -1)[:, :nray]  # noqa: E731
    return unchunk(dist), unchunk(gid)


def repeat_scene(geo: SceneGeometry, n: int) -> SceneGeometry:
    """One scene's ``SceneGeometry`` as n identical scenes (a broadcast: no copies), for n
    ray sets or sensor poses in that scene."""
    return jax.tree.map(lambda x: jnp.broadcast_to(x, (n,) + x.shape[1:]), geo)


def cast_geometry(
    geo: SceneGeometry,
    origins: jax.Array,
    directions: jax.Array,
    max_range,
    *,
    method: str | None = None,
    cells_per_edge: int | None = None,
    capacity: int = DEFAULT_CAPACITY,
    cpu_threads: int | None = None,
) -> tuple[jax.Array, jax.Array]:
    """``cast_rays`` on a prepared ``SceneGeometry`` (B scenes); shapes as ``cast_rays``."""
    nscene = geo.pos.shape[0]
    origins = jnp.asarray(origins, jnp.float32)
    directions = jnp.asarray(directions, jnp.float32)
    if origins.shape[-1:] != (3,) or origins.ndim > 2:
        raise ValueError(f"origins must be [3] or [B, 3], got {origins.shape}")
    if directions.shape[-1:] != (3,) or directions.ndim not in (2, 3):
        raise ValueError(f"directions must be [R, 3] or [B, R, 3], got {directions.shape}")
    if nscene == 1 and directions.ndim == 3 and directions.shape[0] > 1:
        # B ray sets in one scene: the scene is shared (a broadcast of its few fields).
        nscene = directions.shape[0]
        geo = repeat_scene(geo, nscene)
    if origins.ndim == 2 and origins.shape[0] not in (1, nscene):
        raise ValueError(
            f"origins [B, 3] holds one origin per scene ({nscene} here), got {origins.shape}; "
            "for several origins in one scene, jax.vmap the cast over the origins"
        )
    if directions.ndim == 3 and directions.shape[0] not in (1, nscene):
        raise ValueError(
            f"directions [B, R, 3] hold one ray set per scene ({nscene} here), got "
            f"{directions.shape}"
        )
    single = origins.ndim == 1 and directions.ndim == 2
    method = _resolve_method(method)
    mr = jnp.asarray(max_range, jnp.float32).reshape(-1)
    if mr.shape[0] not in (1, nscene):
        raise ValueError(
            f"max_range: expected a scalar or one value per scene [B] = [{nscene}], got shape "
            f"{list(jnp.shape(max_range))}"
        )
    if not isinstance(mr, jax.core.Tracer) and bool(jnp.isnan(mr).any()):
        raise ValueError(f"max_range: NaN; expected metres (inf: no limit), got {max_range!r}")
    nray = directions.shape[-2]
    if nray == 0 or geo.pos.shape[1] == 0:  # nothing to cast, or nothing to hit
        dist = jnp.full((nscene, nray), -1.0, jnp.float32)
        gid = jnp.full((nscene, nray), -1, jnp.int32)
        return (dist[0], gid[0]) if single and not geo.batched else (dist, gid)
    dirs = jnp.broadcast_to(directions.reshape(-1, nray, 3), (nscene, nray, 3))
    # mj_ray refuses a direction shorter than mjMINVAL; here such a ray (or a non-finite
    # one) is a miss, and the kernels see a harmless unit vector in its place.
    length = jnp.linalg.norm(dirs, axis=-1)
    castable = jnp.isfinite(length) & (length >= rc.MINVAL)
    dirs = jnp.where(castable[..., None], dirs, jnp.array([1.0, 0.0, 0.0], jnp.float32))
    origin = jnp.broadcast_to(origins.reshape(-1, 3), (nscene, 3))
    # A non-finite origin misses everything, as in mj_ray (the kernels gave NaN hits).
    castable &= jnp.isfinite(origin).all(-1)[:, None]
    origin = jnp.where(jnp.isfinite(origin), origin, 0.0)
    mr = jnp.broadcast_to(mr, (nscene,))
    castable &= ~jnp.isnan(mr)[:, None]  # traced NaN (unseen above): every ray misses
    if method == "jax":
        dist, gid = _cast_jax(geo, dirs, origin, mr)
    else:
        cells = default_cells_per_edge(nray) if cells_per_edge is None else int(cells_per_edge)
        threads = default_cpu_threads() if cpu_threads is None else int(cpu_threads)
        if threads < 1:
            raise ValueError(f"cpu_threads must be >= 1, got {cpu_threads}")
        dist, gid = _batched_caster(method, cells, int(capacity), threads)(geo, dirs, origin, mr)
    dist = jnp.where(castable, dist, -1.0)
    gid = jnp.where(castable, gid, -1)
    if single and not geo.batched:
        return dist[0], gid[0]
    return dist, gid


def cast_rays(
    model,
    data,
    origins: jax.Array,
    directions: jax.Array,
    max_range,
    *,
    geomgroup=None,
    flg_static: bool = True,
    bodyexclude: int = -1,
    skip_unsupported: bool = False,
    method: str | None = None,
    cells_per_edge: int | None = None,
    capacity: int = DEFAULT_CAPACITY,
    cpu_threads: int | None = None,
) -> tuple[jax.Array, jax.Array]:
    """Casts rays from one origin per scene against MJX primitives, like ``mj_ray``.

    Works inside ``jax.jit`` and under ``jax.vmap`` (a vmapped call runs as one batched
    kernel launch). Geometry is read from ``data.geom_xpos``/``geom_xmat`` (run kinematics
    first) and ``model.geom_size``; moving mocap bodies need nothing but new kinematics.

    Args:
      model: ``mjx.Model`` (one scene; or geom_size etc. batched over B scenes).
      data: ``mjx.Data`` of one scene (``geom_xpos`` [G, 3]) or B scenes ([B, G, 3]).
      origins: float [3] or [B, 3], world frame (a non-finite one: every ray misses).
      directions: float [R, 3] or [B, R, 3], unit vectors, world frame (a direction of
        length < mjMINVAL, or not finite, is a miss; ``mj_ray`` stops the process on the
        first and gives no reliable answer for the second). With one
        scene, B ray sets [B, R, 3] are cast in that scene, giving [B, R].
      max_range: float scalar or [B]; hits farther than this count as misses (inf: no
        limit; NaN is refused, or under ``jax.jit`` makes every ray of its scene miss).
      geomgroup: optional 6 flags (``mj_ray``'s geomgroup); None includes every group.
      flg_static: include geoms of bodies welded to the world (``mj_ray``'s flg_static).
      bodyexclude: body id whose geoms are ignored (-1: none).
      skip_unsupported: ignore mesh/hfield/sdf geoms instead of raising ValueError.
      method: "binned" (Warp, cube-map culling), "brute" (Warp, every geom per ray) or
        "jax" (pure JAX, every geom per ray: any backend, no warp-lang needed); None:
        ``default_method()``, i.e. "binned", or "jax" where warp-lang is not installed.
      cells_per_edge: cube-map resolution (static); default from R. Warp methods only.
      capacity: candidate list length per cell (static); overflowing cells stay exact.
      cpu_threads: threads sharing each Warp launch on the CPU (static); None: every core
        this process may use. Results do not depend on it; on CUDA it is ignored.

    Returns:
      distance: float32 [R] or [B, R] ([R] only for origins [3], directions [R, 3] and an
        unbatched ``data``), along the ray (in units of |direction|), -1 on a miss.
      geom_id: int32 [R] or [B, R], the hit geom, -1 on a miss.
    """
    method = _resolve_method(method)  # before any work on the model
    geo = scene_geometry(
        model,
        data,
        geomgroup=geomgroup,
        flg_static=flg_static,
        bodyexclude=bodyexclude,
        skip_unsupported=skip_unsupported,
    )
    return cast_geometry(
        geo,
        origins,
        directions,
        max_range,
        method=method,
        cells_per_edge=cells_per_edge,
        capacity=capacity,
        cpu_threads=cpu_threads,
    )


def surface_normals(geo: SceneGeometry, points: jax.Array, geom_id: jax.Array) -> jax.Array:
    """Outward unit normals of the hit primitives at world points.

    Args:
      geo: ``SceneGeometry`` of B scenes.
      points: float [B, R, 3] hit points (world frame).
      geom_id: int [B, R] hit geoms (-1: miss; the normal is then arbitrary but finite).

    Returns:
      float32 [B, R, 3] world-frame unit normals.
    """
    g = jnp.maximum(geom_id, 0)
    take = lambda x: jnp.take_along_axis(x, g.reshape(g.shape + (1,) * (x.ndim - 2)), axis=1)  # noqa: E731
    gtype = jnp.take_along_axis(geo.geom_type, g, axis=1)  # [B, R]
    size = take(geo.size)  # [B, R, 3]
    pos = take(geo.pos)  # [B, R, 3]
    mat = take(geo.mat)  # [B, R, 3, 3]
    p = jnp.einsum("brji,brj->bri", mat, points - pos)  # local frame
    r, h = size[..., 0:1], size[..., 1:2]
    eps = 1e-12
    ez = jnp.zeros_like(p).at[..., 2].set(1.0)
    sphere = p
    ellipsoid = p / jnp.maximum(size**2, eps)
    axis_ix = jnp.argmax(jnp.abs(p) / jnp.maximum(size, eps), axis=-1)
    box = jax.nn.one_hot(axis_ix, 3) * jnp.sign(p)
    radial = p.at[..., 2].set(0.0)
    rad_len = jnp.linalg.norm(radial, axis=-1, keepdims=True)
    on_cap = (h - jnp.abs(p[..., 2:3])) < (r - rad_len)
    cylinder = jnp.where(on_cap, ez * jnp.sign(p[..., 2:3]), radial)
    capsule = p - ez * jnp.clip(p[..., 2:3], -h, h)
    t = gtype[..., None]
    n = jnp.select(
        [t == rc.PLANE, t == rc.SPHERE, t == rc.CAPSULE, t == rc.ELLIPSOID, t == rc.CYLINDER],
        [ez, sphere, capsule, ellipsoid, cylinder],
        box,
    )
    n = n / jnp.maximum(jnp.linalg.norm(n, axis=-1, keepdims=True), eps)
    return jnp.einsum("brij,brj->bri", mat, n)
