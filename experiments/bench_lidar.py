"""Lidar ray-casting throughput: indoorbev_sim.lidar.cast_rays vs MuJoCo and mujoco-lidar.

Scene: a 10 x 10 m room (floor plane, 4 wall boxes) with 60 furniture primitives of every
type; sensor at the room centre, 0.5 m up. Patterns: one MID-360-like frame (20k rays), a
360 x 64 grid, 1M random rays. Backends, all on the same scene and rays, interleaved:
  * ours      - cast_rays inside jax.jit (Warp kernels on the CPU), the jitted function taking
    the MJX Model and Data (flattening the Model's ~120 leaves, a Python pytree, costs
    ~0.15-0.8 ms per call);
  * ours, Data - the same with the Model closed over and the MJX Data passed per call, as
    mujoco-lidar's trace_rays(data, ...) takes the MjData;
  * ours, poses - the jitted function taking only the geom poses that change between
    frames (geom_xpos, geom_xmat), as a simulation loop inside jit sees them;
  * ours, 1 thread - as "ours" with cpu_threads=1;
  * ours, jax caster - cast_rays(method="jax"), the pure-JAX caster for machines without
    warp-lang (every ray against every geom, no culling), "ours, Data" otherwise;
  * mj_multiRay on two threads (the binding releases the GIL; rays split in halves);
  * mujoco-lidar 0.3.x backends "warp" (BVH) and "taichi", if installed. They are benchmark
    only: ``.venv/bin/pip install "mujoco-lidar[taichi]==0.3.5"`` (pulls torch).
Each timed run idles ``--settle`` s, then times one call ("after idle": what a node casting
one frame per sensor period pays, waking the cores) and then ``--calls`` calls back to back
("back to back": the throughput of a loop generating frames). Prints, per backend, the
median over ``--repeats`` interleaved runs of both, rays/s, our speed-up over the best
other backend in each mode, and how many of our rays agree with mj_multiRay (1e-4 m,
hit/miss included).

Usage: JAX_PLATFORMS=cpu .venv/bin/python experiments/bench_lidar.py [--repeats 7]
"""

from __future__ import annotations

import argparse
import functools
import threading
import time

import jax
import jax.numpy as jnp
import mujoco
import numpy as np
from indoorbev_sim import lidar, patterns
from mujoco import mjx

from indoorbev_jax.cli import HelpFormatter, nonnegative_float, nonnegative_int, positive_int

CUTOFF = 30.0
SENSOR = np.array([0.0, 0.0, 0.5])


def room_xml(seed: int = 0, n_furniture: int = 60) -> str:
    rng = np.random.default_rng(seed)
    body = [
        '<geom type="plane" size="5 5 0.1"/>',
        '<geom type="box" pos="5.05 0 1.5" size="0.05 5.1 1.5"/>',
        '<geom type="box" pos="-5.05 0 1.5" size="0.05 5.1 1.5"/>',
        '<geom type="box" pos="0 5.05 1.5" size="5.1 0.05 1.5"/>',
        '<geom type="box" pos="0 -5.05 1.5" size="5.1 0.05 1.5"/>',
        f'<site name="lidar" pos="{SENSOR[0]} {SENSOR[1]} {SENSOR[2]}"/>',
    ]
    types = ["box", "sphere", "capsule", "cylinder", "ellipsoid"]
    for i in range(n_furniture):
        t = types[i % len(types)]
        while True:  # keep furniture off the sensor
            xy = rng.uniform(-4.5, 4.5, 2)
            if np.linalg.norm(xy) > 1.0:
                break
        size = rng.uniform(0.1, 0.6, 3)
        yaw = rng.uniform(0, 360)
        z = size[2] if t in ("box", "ellipsoid") else size[0] + (size[1] if t != "sphere" else 0)
        body.append(
            f'<geom type="{t}" pos="{xy[0]} {xy[1]} {z}" euler="0 0 {yaw}" '
            f'size="{size[0]} {size[1]} {size[2]}"/>'
        )
    return (
        '<mujoco><default><geom contype="0" conaffinity="0"/></default><worldbody>'
        + "".join(body)
        + "</worldbody></mujoco>"
    )


def ray_sets(seed: int = 0) -> dict[str, np.ndarray]:
    rng = np.random.default_rng(seed)
    rand = rng.normal(size=(1_000_000, 3))
    rand /= np.linalg.norm(rand, axis=1, keepdims=True)
    return {
        "mid360 frame": np.asarray(patterns.Mid360Pattern().frame(0).directions),
        "grid 360x64": np.asarray(patterns.GridPattern(360, 64).frame(0).directions),
        "random 1M": rand.astype(np.float32),
    }


class MultiRay2:
    """mj_multiRay with the rays split over two threads (one MjData each)."""

    def __init__(self, m, d, dirs):
        self.m = m
        self.halves = np.array_split(dirs.astype(np.float64), 2)
        self.datas = [mujoco.MjData(m) for _ in self.halves]
        for dd in self.datas:
            dd.qpos[:] = d.qpos
            mujoco.mj_forward(m, dd)
        self.out = [(np.zeros(len(h), np.int32), np.zeros(len(h))) for h in self.halves]

    def _run(self, i):
        gid, dist = self.out[i]
        h = self.halves[i]
        mujoco.mj_multiRay(
            self.m,
            self.datas[i],
            SENSOR,
            h.reshape(-1),
            None,
            1,
            -1,
            gid,
            dist,
            None,
            len(h),
            CUTOFF,
        )

    def __call__(self):
        threads = [threading.Thread(target=self._run, args=(i,)) for i in range(2)]
        for t in threads:
            t.start()
        for t in threads:
            t.join()
        return np.concatenate([o[1] for o in self.out]), np.concatenate([o[0] for o in self.out])


def mujoco_lidar_backends(m, d, dirs):
    """Callables for mujoco-lidar's warp and taichi backends, or notes why unavailable."""
    out, notes = {}, []
    try:
        from mujoco_lidar import MjLidarWrapper
    except ImportError as e:
        return out, [f"mujoco-lidar not installed ({e})"]
    theta = np.arctan2(dirs[:, 1], dirs[:, 0]).astype(np.float32)  # azimuth
    phi = np.arcsin(np.clip(dirs[:, 2], -1, 1)).astype(np.float32)  # elevation
    for backend, args in (("warp", {"device": "cpu"}), ("taichi", {"ti_init_args": {}})):
        try:
            if backend == "taichi":
                import taichi as ti

                ti.init(arch=ti.cpu, cpu_max_num_threads=2)
                ti._is_initialized = True
            w = MjLidarWrapper(m, "lidar", backend=backend, cutoff_dist=CUTOFF, args=args)
            w.trace_rays(d, theta, phi)  # compile
            out[f"mujoco-lidar {backend}"] = lambda w=w: w.trace_rays(d, theta, phi)
        except Exception as e:  # noqa: BLE001 - report any backend failure and go on
            notes.append(f"mujoco-lidar {backend}: unavailable ({type(e).__name__}: {e})")
    return out, notes


def median_time(fn, block=lambda x: x):
    t = time.perf_counter()
    block(fn())
    return time.perf_counter() - t


def thread_sweep(mx, dx, origin, sizes, args):
    from indoorbev_sim import _lidar_kernels

    _lidar_kernels.MIN_ITEMS_PER_THREAD = 1
    geo = jax.jit(lidar.scene_geometry)(mx, dx)
    rays = ray_sets()["random 1M"]
    fns = {
        t: jax.jit(lambda g, v, t=t: lidar.cast_geometry(g, origin, v, CUTOFF, cpu_threads=t))
        for t in (1, 2)
    }
    for n in sizes:
        dirs = jnp.asarray(rays[:n])
        times = {t: [] for t in fns}
        cast1, cast2 = (jax.block_until_ready(fn(geo, dirs)) for fn in fns.values())
        if not all(np.array_equal(a, b) for a, b in zip(cast1, cast2, strict=True)):
            raise SystemExit(f"{n} rays: 2 threads cast other rays than 1 thread: not timed")
        for _ in range(args.repeats):
            for t, fn in fns.items():
                time.sleep(args.settle)
                times[t].append(
                    median_time(functools.partial(fn, geo, dirs), jax.block_until_ready)
                )
        one, two = (float(np.median(times[t])) * 1e3 for t in (1, 2))
        print(f"{n:8d} rays: 1 thread {one:8.2f} ms, 2 threads {two:8.2f} ms ({one / two:.2f}x)")


# Float32 grazing rays (a ray tangent to a capsule within 1e-7 m) may legitimately hit or
# miss against MuJoCo's float64: about 1 ray in 10^5 to 10^6. More is a wrong caster.
MIN_AGREEMENT = 0.9999


def check_agreement(label: str, ok: np.ndarray) -> None:
    """Ends the run before any timing when ``label``'s rays (bool ``ok``: equal to
    mj_multiRay) agree less than ``MIN_AGREEMENT``: a fast wrong answer is no result."""
    if ok.mean() < MIN_AGREEMENT:
        raise SystemExit(
            f"{label}: {ok.size - int(ok.sum())} of {ok.size} rays disagree with mj_multiRay "
            f"(1e-4 m, hit/miss, geom; at most {1 - MIN_AGREEMENT:.2%} may, float32 grazing "
            "rays): not timed"
        )


def scenes_run(m, d, mx, dx, nscene, args):
    """B sensor poses in the room, one MID-360 frame each: ours in one batched call (vmap
    folds into one launch) against mj_multiRay over the poses on two threads."""
    rng = np.random.default_rng(1)
    angle = rng.uniform(0, 2 * np.pi, nscene)
    radius = rng.uniform(0, 0.8, nscene)  # furniture keeps 1 m clear of the room centre
    origins = np.stack([radius * np.cos(angle), radius * np.sin(angle),
                        np.full(nscene, SENSOR[2])], 1)  # fmt: skip
    pattern = patterns.Mid360Pattern()
    dirs = np.stack([np.asarray(pattern.frame(k).directions) for k in range(nscene)])
    ours = jax.jit(jax.vmap(lambda o, v: lidar.cast_rays(mx, dx, o, v, CUTOFF)))
    o_j, v_j = jnp.asarray(origins, jnp.float32), jnp.asarray(dirs)
    t0 = time.perf_counter()
    dist, gid = jax.block_until_ready(ours(o_j, v_j))
    first = time.perf_counter() - t0

    datas = [mujoco.MjData(m) for _ in range(2)]
    for dd in datas:
        mujoco.mj_forward(m, dd)

    def ref_half(h, out):
        for b in range(h, nscene, 2):
            g, x = np.zeros(dirs.shape[1], np.int32), np.zeros(dirs.shape[1])
            mujoco.mj_multiRay(m, datas[h], origins[b], dirs[b].astype(np.float64).reshape(-1),
                               None, 1, -1, g, x, None, dirs.shape[1], CUTOFF)  # fmt: skip
            out[b] = (np.where((x < 0) | (x > CUTOFF), -1.0, x), g)

    def ref():
        out = {}
        threads = [threading.Thread(target=ref_half, args=(h, out)) for h in range(2)]
        for t in threads:
            t.start()
        for t in threads:
            t.join()
        return out

    want = ref()
    agree = np.stack([
        (np.abs(np.asarray(dist[b]) - want[b][0]) <= 1e-4)
        & (np.asarray(gid[b]) == np.where(want[b][0] < 0, -1, want[b][1]))
        for b in range(nscene)
    ])  # fmt: skip
    check_agreement("ours, one batched call", agree)
    ok = agree.mean()
    times = {"ours": [], "ref": []}
    for _ in range(args.repeats):
        time.sleep(args.settle)
        times["ours"].append(median_time(lambda: ours(o_j, v_j), jax.block_until_ready))
        time.sleep(args.settle)
        times["ref"].append(median_time(ref))
    rays = dirs.shape[0] * dirs.shape[1]
    med = {k: float(np.median(v)) for k, v in times.items()}
    print(f"\n== {nscene} scenes x one MID-360 frame: {rays} rays (ours: first call {first:.2f} s)")
    for k, label in (("ours", "ours, one batched call"), ("ref", "mj_multiRay x2 threads")):
        print(f"  {label:28s} {med[k] * 1e3:9.2f} ms  {rays / med[k] / 1e6:8.2f} M rays/s")
    print(f"  speed-up {med['ref'] / med['ours']:.2f}x; agreement {ok * 100:.4f} %")


def main(argv=None):
    ap = argparse.ArgumentParser(
        description=__doc__.split("\n\n")[0], formatter_class=HelpFormatter
    )
    ap.add_argument(
        "--repeats",
        type=positive_int,
        default=7,
        help="interleaved timed runs per backend (their median)",
    )
    ap.add_argument(
        "--sets",
        default="mid360 frame,grid 360x64,random 1M",
        help="comma list of the ray sets to time",
    )
    ap.add_argument(
        "--calls",
        type=positive_int,
        default=5,
        help="back-to-back calls timed after the first call of each run (their median)",
    )
    ap.add_argument(
        "--settle",
        type=nonnegative_float,
        default=0.3,
        help="seconds idle before each timed run, so that one backend's spin-waiting worker "
        "threads (Taichi, XLA) are not charged to the next",
    )
    ap.add_argument(
        "--thread-sizes",
        default="",
        help="comma-separated ray counts: instead of the backends, time ours on that many of "
        "the random rays with cpu_threads 1 vs 2, both forced to split (how the one-thread "
        "threshold in _lidar_kernels.MIN_ITEMS_PER_THREAD was chosen)",
    )
    ap.add_argument(
        "--scenes",
        type=nonnegative_int,
        default=0,
        help="instead of the backends: this many sensor poses, one MID-360 frame each, ours "
        "batched in one call against mj_multiRay over the poses (the issue's GPU row is 64)",
    )
    args = ap.parse_args(argv)
    unknown = set(args.sets.split(",")) - set(ray_sets())
    if unknown:
        ap.error(f"--sets: unknown {sorted(unknown)}; the sets are {', '.join(ray_sets())}")
    try:
        sizes = [int(n) for n in args.thread_sizes.split(",")] if args.thread_sizes else []
    except ValueError:
        ap.error(
            f"--thread-sizes: expected ray counts separated by commas, got {args.thread_sizes!r}"
        )
    if any(n < 1 for n in sizes):
        ap.error(f"--thread-sizes: counts must be > 0, got {args.thread_sizes!r}")

    m = mujoco.MjModel.from_xml_string(room_xml())
    d = mujoco.MjData(m)
    mujoco.mj_forward(m, d)
    mx, dx = mjx.put_model(m), mjx.put_data(m, d)
    print(f"scene: {m.ngeom} geoms; {jax.device_count()} JAX device(s); repeats {args.repeats}")
    origin = jnp.asarray(SENSOR, jnp.float32)
    ours_fn = jax.jit(lambda mx, dx, v: lidar.cast_rays(mx, dx, origin, v, CUTOFF))
    ours_data = jax.jit(lambda dx, v: lidar.cast_rays(mx, dx, origin, v, CUTOFF))
    ours_1t = jax.jit(lambda mx, dx, v: lidar.cast_rays(mx, dx, origin, v, CUTOFF, cpu_threads=1))
    ours_jax = jax.jit(lambda dx, v: lidar.cast_rays(mx, dx, origin, v, CUTOFF, method="jax"))
    ours_poses = jax.jit(
        lambda xpos, xmat, v: lidar.cast_rays(
            mx, dx.replace(geom_xpos=xpos, geom_xmat=xmat), origin, v, CUTOFF
        )
    )

    if args.scenes:
        scenes_run(m, d, mx, dx, args.scenes, args)
        return
    if args.thread_sizes:
        thread_sweep(mx, dx, origin, sizes, args)
        return
    for name, dirs in ray_sets().items():
        if name not in args.sets.split(","):
            continue
        dirs_j = jnp.asarray(dirs)
        backends = {
            "ours": lambda dirs_j=dirs_j: ours_fn(mx, dx, dirs_j),
            "ours, Data": lambda dirs_j=dirs_j: ours_data(dx, dirs_j),
            "ours, poses": lambda dirs_j=dirs_j: ours_poses(dx.geom_xpos, dx.geom_xmat, dirs_j),
            "ours, 1 thread": lambda dirs_j=dirs_j: ours_1t(mx, dx, dirs_j),
            "ours, jax caster": lambda dirs_j=dirs_j: ours_jax(dx, dirs_j),
            "mj_multiRay x2 threads": MultiRay2(m, d, dirs),
        }
        ml, notes = mujoco_lidar_backends(m, d, dirs)
        backends.update(ml)
        t0 = time.perf_counter()
        ours = jax.block_until_ready(backends["ours"]())
        first = time.perf_counter() - t0
        for k in ("ours, Data", "ours, poses", "ours, 1 thread"):
            same = jax.block_until_ready(backends[k]())
            assert all(np.array_equal(a, b) for a, b in zip(same, ours, strict=True)), k
        t0 = time.perf_counter()
        ours_j = jax.block_until_ready(backends["ours, jax caster"]())
        first_jax = time.perf_counter() - t0
        ref_d, ref_g = backends["mj_multiRay x2 threads"]()
        ref_d = np.where((ref_d < 0) | (ref_d > CUTOFF), -1.0, ref_d)

        def agreement(out, ref_d=ref_d, ref_g=ref_g):
            return (np.abs(np.asarray(out[0]) - ref_d) <= 1e-4) & (
                np.asarray(out[1]) == np.where(ref_d < 0, -1, ref_g)
            )

        ok, ok_jax = agreement(ours), agreement(ours_j)
        check_agreement(f"{name}: ours", ok)
        check_agreement(f"{name}: ours, jax caster", ok_jax)
        idle = {k: [] for k in backends}
        loop = {k: [] for k in backends}
        for _ in range(args.repeats):
            for k, fn in backends.items():
                time.sleep(args.settle)
                block = jax.block_until_ready if k.startswith("ours") else (lambda x: x)
                idle[k].append(median_time(fn, block))
                loop[k].append(np.median([median_time(fn, block) for _ in range(args.calls)]))
        print(
            f"\n== {name}: {len(dirs)} rays (first call incl. compile: ours {first:.2f} s, "
            f"jax caster {first_jax:.2f} s)"
        )
        for note in notes:
            print("  " + note)
        print(f"  {'':28s} {'after idle':>22s} {'back to back':>24s}")
        med = {}
        for mode, times in (("after idle", idle), ("back to back", loop)):
            med[mode] = {k: float(np.median(v)) for k, v in times.items()}
        for k in backends:
            a, b = med["after idle"][k], med["back to back"][k]
            print(
                f"  {k:28s} {a * 1e3:8.2f} ms {len(dirs) / a / 1e6:6.2f} M/s"
                f" {b * 1e3:9.2f} ms {len(dirs) / b / 1e6:7.2f} M/s"
            )
        for mode, t in med.items():
            best = min(v for k, v in t.items() if not k.startswith("ours"))
            ratios = ", ".join(f"{k} {best / v:.2f}x" for k, v in t.items() if k.startswith("ours"))
            print(f"  speed-up over the best other backend, {mode}: {ratios}")
        print(
            f"  agreement with mj_multiRay (1e-4 m, hit/miss, geom): ours {ok.mean() * 100:.4f} %,"
            f" jax caster {ok_jax.mean() * 100:.4f} %"
        )


if __name__ == "__main__":
    from indoorbev_jax.cli import exit_with

    exit_with(main, "bench_lidar.py")  # Ctrl-C: one line and status 130
