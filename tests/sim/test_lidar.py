"""cast_rays against MuJoCo's own C mj_ray on random scenes with every primitive type."""

import os

import jax
import jax.numpy as jnp
import mujoco
import numpy as np
import pytest
from indoorbev_sim import lidar
from mujoco import mjx

MAX_RANGE = 30.0
TYPES = ("box", "sphere", "capsule", "cylinder", "ellipsoid", "plane")


def random_scene_xml(seed: int, n: int = 24) -> str:
    """Random poses/sizes of all six primitives (planes finite and infinite), no collisions."""
    rng = np.random.default_rng(seed)
    geoms = ['<geom type="plane" size="0 0 1" pos="0 0 -1.5"/>']
    for i in range(n):
        t = TYPES[i % len(TYPES)]
        pos = rng.uniform(-3, 3, 3)
        euler = rng.uniform(-180, 180, 3)
        size = rng.uniform(0.1, 1.0, 3)
        if t == "plane":
            size[:2] = rng.uniform(0.3, 2.0, 2) if i % 2 else (0.0, rng.uniform(0.3, 2.0))
        geoms.append(
            f'<geom type="{t}" pos="{pos[0]} {pos[1]} {pos[2]}" '
            f'euler="{euler[0]} {euler[1]} {euler[2]}" size="{size[0]} {size[1]} {size[2]}"/>'
        )
    return (
        '<mujoco><default><geom contype="0" conaffinity="0"/></default><worldbody>'
        + "".join(geoms)
        + "</worldbody></mujoco>"
    )


def mj_ray_reference(m, d, origin, dirs, max_range=MAX_RANGE, **kw):
    dist = np.empty(len(dirs))
    gid = np.empty(len(dirs), np.int32)
    out = np.zeros(1, np.int32)
    group = kw.get("geomgroup")
    for i, v in enumerate(dirs.astype(np.float64)):
        dist[i] = mujoco.mj_ray(
            m, d, origin, v, group, kw.get("flg_static", 1), kw.get("bodyexclude", -1), out
        )
        gid[i] = out[0]
    miss = (dist < 0) | (dist > max_range)
    dist[miss], gid[miss] = -1.0, -1
    return dist, gid


def unit_rays(rng, n):
    v = rng.normal(size=(n, 3))
    return (v / np.linalg.norm(v, axis=1, keepdims=True)).astype(np.float32)


_cast = {
    method: jax.jit(
        lambda mx, dx, o, v, method=method: lidar.cast_rays(mx, dx, o, v, MAX_RANGE, method=method)
    )
    for method in ("binned", "brute", "jax")
}


@pytest.fixture(scope="module")
def scenes():
    out = []
    for seed in range(3):
        m = mujoco.MjModel.from_xml_string(random_scene_xml(seed))
        d = mujoco.MjData(m)
        mujoco.mj_forward(m, d)
        out.append((m, d, mjx.put_model(m), mjx.put_data(m, d)))
    return out


@pytest.mark.parametrize("method", ["binned", "brute", "jax"])
def test_matches_mj_ray_on_random_scenes(scenes, method):
    """>= 99.99 % of rays agree with mj_ray within 1e-4 m, hit/miss and geom id included."""
    rng = np.random.default_rng(1)
    agree = total = 0
    worst = []
    for m, d, mx, dx in scenes:
        # Origins inside primitives (their centres) and in free space.
        origins = [d.geom_xpos[g] for g in rng.choice(np.arange(1, m.ngeom), 3, replace=False)]
        origins += list(rng.uniform(-4, 4, (3, 3)))
        for o in origins:
            dirs = unit_rays(rng, 6000)
            ref_d, ref_g = mj_ray_reference(m, d, o, dirs)
            dist, gid = _cast[method](mx, dx, jnp.asarray(o, jnp.float32), jnp.asarray(dirs))
            dist, gid = np.asarray(dist), np.asarray(gid)
            ok = (np.abs(dist - ref_d) <= 1e-4) & (gid == ref_g)
            agree += ok.sum()
            total += ok.size
            worst += list(zip(dist[~ok], ref_d[~ok], strict=True))
    assert total >= 100_000
    assert agree / total >= 0.9999, f"{total - agree} of {total} disagree: {worst[:10]}"


def test_batched_and_vmapped_scenes_match_single(scenes):
    """B scenes in one call (batched data) == vmap over scenes == one call per scene."""
    rng = np.random.default_rng(2)
    m, d, mx, _ = scenes[0]
    datas, origins = [], rng.uniform(-2, 2, (3, 3)).astype(np.float32)
    for _ in range(3):  # same model, geoms moved per scene
        d2 = mujoco.MjData(m)
        mujoco.mj_forward(m, d2)
        d2.geom_xpos[:] += rng.uniform(-0.5, 0.5, d2.geom_xpos.shape)
        datas.append(mjx.put_data(m, d2))
    dx_b = jax.tree.map(lambda *x: jnp.stack(x), *datas)
    dirs = unit_rays(rng, 4000)
    dist_b, gid_b = _cast["binned"](mx, dx_b, jnp.asarray(origins), jnp.asarray(dirs))
    assert dist_b.shape == (3, 4000) and gid_b.dtype == jnp.int32
    vm = jax.jit(jax.vmap(lambda dx, o: lidar.cast_rays(mx, dx, o, dirs, MAX_RANGE)))
    dist_v, gid_v = vm(dx_b, jnp.asarray(origins))
    for b in range(3):
        dist_1, gid_1 = _cast["brute"](mx, datas[b], jnp.asarray(origins[b]), jnp.asarray(dirs))
        np.testing.assert_array_equal(np.asarray(gid_b[b]), np.asarray(gid_1))
        np.testing.assert_array_equal(np.asarray(gid_v[b]), np.asarray(gid_1))
        np.testing.assert_allclose(np.asarray(dist_b[b]), np.asarray(dist_1), atol=1e-5)
        np.testing.assert_allclose(np.asarray(dist_v[b]), np.asarray(dist_1), atol=1e-5)


def test_jax_caster_batched_vmapped_and_chunked_equal_warp_brute(scenes, monkeypatch):
    """The pure-JAX caster, over B scenes in one call, under vmap, in ray chunks (a chunk
    size that does not divide R) and with the geom types traced, hits the same geoms as
    Warp's brute kernel."""
    rng = np.random.default_rng(8)
    m, d, mx, _ = scenes[2]
    datas, origins = [], rng.uniform(-2, 2, (3, 3)).astype(np.float32)
    for _ in range(3):
        d2 = mujoco.MjData(m)
        mujoco.mj_forward(m, d2)
        d2.geom_xpos[:] += rng.uniform(-0.5, 0.5, d2.geom_xpos.shape)
        datas.append(mjx.put_data(m, d2))
    dx_b = jax.tree.map(lambda *x: jnp.stack(x), *datas)
    dirs = jnp.asarray(unit_rays(rng, 3001))
    ref = [
        _cast["brute"](mx, dx, jnp.asarray(o), dirs) for dx, o in zip(datas, origins, strict=True)
    ]
    dist_b, gid_b = _cast["jax"](mx, dx_b, jnp.asarray(origins), dirs)
    vm = jax.jit(jax.vmap(lambda dx, o: lidar.cast_rays(mx, dx, o, dirs, MAX_RANGE, method="jax")))
    dist_v, gid_v = vm(dx_b, jnp.asarray(origins))
    monkeypatch.setattr(lidar, "JAX_CHUNK_ELEMENTS", 3 * m.ngeom * 700)  # 5 chunks of 700
    dist_c, gid_c = lidar.cast_rays(mx, dx_b, jnp.asarray(origins), dirs, MAX_RANGE, method="jax")
    for b, (dist_1, gid_1) in enumerate(ref):
        for dist, gid in ((dist_b, gid_b), (dist_v, gid_v), (dist_c, gid_c)):
            np.testing.assert_array_equal(np.asarray(gid[b]), np.asarray(gid_1))
            np.testing.assert_allclose(
                np.asarray(dist[b]), np.asarray(dist_1), rtol=2e-6, atol=1e-6
            )
    np.testing.assert_array_equal(np.asarray(dist_c), np.asarray(dist_b))
    # Without the static per-geom types every routine runs under a select: same answer.
    geo = lidar.scene_geometry(mx, dx_b).replace(types=None)
    dist_s, gid_s = lidar.cast_geometry(geo, jnp.asarray(origins), dirs, MAX_RANGE, method="jax")
    np.testing.assert_array_equal(np.asarray(gid_s), np.asarray(gid_b))
    np.testing.assert_array_equal(np.asarray(dist_s), np.asarray(dist_b))


def test_cpu_threads_split_launches_without_changing_results(scenes, monkeypatch):
    """Rays and cells dealt over 1-3 CPU threads: the same bits as one launch, and mj_ray's."""
    from indoorbev_sim import _lidar_kernels as K

    monkeypatch.setattr(K, "MIN_ITEMS_PER_THREAD", 1)  # split even these few rays
    launches = []
    real_launch = K.wp.launch

    def counting_launch(kernel, dim, **kw):
        launches.append((kernel.key, tuple(dim)))
        return real_launch(kernel, dim, **kw)

    monkeypatch.setattr(K.wp, "launch", counting_launch)
    rng = np.random.default_rng(7)
    m, d, mx, _ = scenes[0]
    datas = []
    for _ in range(2):
        d2 = mujoco.MjData(m)
        mujoco.mj_forward(m, d2)
        d2.geom_xpos[:] += rng.uniform(-0.3, 0.3, d2.geom_xpos.shape)
        datas.append(d2)
    dx_b = jax.tree.map(lambda *x: jnp.stack(x), *[mjx.put_data(m, dd) for dd in datas])
    origins = rng.uniform(-2, 2, (2, 3)).astype(np.float32)
    dirs = unit_rays(rng, 4001)  # not a multiple of the thread counts
    for method in ("binned", "brute"):
        out = {}
        for threads in (1, 2, 3):
            launches.clear()
            fn = jax.jit(
                lambda dx, o, v, t=threads, meth=method: lidar.cast_rays(
                    mx, dx, o, v, MAX_RANGE, method=meth, cpu_threads=t
                )
            )
            out[threads] = [np.asarray(x) for x in fn(dx_b, origins, jnp.asarray(dirs))]
            kernel = "cast_" + method
            shares = [n for key, (b, n) in launches if key == kernel and b == 2]
            # One thread is the plain FFI kernel; more deal the rays out round-robin, and
            # each kernel thread of cast_binned casts CPU_RAYS_PER_THREAD of a share's rays.
            per = K.CPU_RAYS_PER_THREAD if method == "binned" else 1
            want = [-(-len(range(t, 4001, threads)) // per) for t in range(threads)]
            want = want if threads > 1 else []
            assert sorted(shares) == sorted(want)
        for threads in (2, 3):
            np.testing.assert_array_equal(out[threads][0], out[1][0])
            np.testing.assert_array_equal(out[threads][1], out[1][1])
        for b in range(2):
            ref_d, ref_g = mj_ray_reference(m, datas[b], origins[b].astype(np.float64), dirs)
            ok = (np.abs(out[3][0][b] - ref_d) <= 1e-4) & (out[3][1][b] == ref_g)
            assert ok.mean() >= 0.9999
    with pytest.raises(ValueError, match="cpu_threads"):
        lidar.cast_rays(mx, mjx.put_data(m, d), origins[0], dirs, MAX_RANGE, cpu_threads=0)
    # Per-ray origins are not a per-scene batch: the error says so instead of broadcasting.
    with pytest.raises(ValueError, match=r"one origin per scene \(1 here\), got \(5, 3\).*vmap"):
        lidar.cast_rays(mx, mjx.put_data(m, d), np.zeros((5, 3)), dirs[:5], MAX_RANGE)
    # Two ranges for one scene: JAX's broadcasting error did not name max_range.
    with pytest.raises(
        ValueError,
        match=r"max_range: expected a scalar or one value per scene \[B\] = \[1\], got shape \[2\]",
    ):
        lidar.cast_rays(mx, mjx.put_data(m, d), origins[0], dirs, np.full(2, MAX_RANGE))


@pytest.mark.parametrize("method", ["binned", "jax"])
def test_filters_max_range_and_plane_conventions(method):
    """geomgroup / flg_static / bodyexclude / invisible geoms / max_range follow mj_ray."""
    xml = """<mujoco><default><geom contype="0" conaffinity="0"/></default><worldbody>
      <geom type="plane" size="1 1 1" pos="0 0 -1"/>
      <geom type="box" size=".2 .2 .2" pos="2 0 0" group="1"/>
      <geom type="sphere" size=".3" pos="0 2 0" rgba="1 1 1 0"/>
      <body name="b" pos="-2 0 0"><joint type="slide"/><geom type="sphere" size=".3"/></body>
      <body name="c" pos="0 -2 0"><joint type="slide"/><geom type="cylinder" size=".3 .3"/>
      </body></worldbody></mujoco>"""
    m = mujoco.MjModel.from_xml_string(xml)
    d = mujoco.MjData(m)
    mujoco.mj_forward(m, d)
    mx, dx = mjx.put_model(m), mjx.put_data(m, d)
    rng = np.random.default_rng(3)
    dirs = unit_rays(rng, 3000)
    origin = np.array([0.05, 0.02, 0.01])
    cases = [
        dict(),
        dict(geomgroup=np.array([1, 0, 1, 1, 1, 1], np.uint8)),
        dict(flg_static=0),
        dict(bodyexclude=m.body("b").id),
    ]
    for kw in cases:
        for max_range in (30.0, 1.9):
            ref_d, ref_g = mj_ray_reference(m, d, origin, dirs, max_range, **kw)
            dist, gid = lidar.cast_rays(
                mx, dx, jnp.asarray(origin), dirs, max_range, method=method, **kw
            )
            np.testing.assert_array_equal(np.asarray(gid), ref_g, err_msg=str(kw))
            np.testing.assert_allclose(np.asarray(dist), ref_d, atol=1e-4)
    # The finite plane is hit from above only: from below every ray misses it.
    dist, gid = lidar.cast_rays(mx, dx, jnp.array([0.0, 0.0, -1.5]), dirs, 30.0, method=method)
    assert not np.any(np.asarray(gid) == 0)
    # inf: no limit (mj_ray's answer); NaN, which compared as no limit, is refused, and
    # under jit (where it cannot be seen) every ray misses rather than every hit passing.
    ref_d, ref_g = mj_ray_reference(m, d, origin, dirs, np.inf)
    dist, gid = lidar.cast_rays(mx, dx, jnp.asarray(origin), dirs, np.inf, method=method)
    np.testing.assert_array_equal(np.asarray(gid), ref_g)
    with pytest.raises(ValueError, match=r"max_range: NaN; expected metres \(inf: no limit\)"):
        lidar.cast_rays(mx, dx, jnp.asarray(origin), dirs, np.nan, method=method)
    with pytest.raises(ValueError, match=r"max_range: NaN"):  # no ray to cast: refused too
        lidar.cast_rays(mx, dx, jnp.asarray(origin), dirs[:0], np.nan, method=method)
    cast = jax.jit(lambda r: lidar.cast_rays(mx, dx, jnp.asarray(origin), dirs, r, method=method))
    dist, gid = cast(jnp.float32(np.nan))
    assert (np.asarray(gid) == -1).all() and (np.asarray(dist) == -1).all()


@pytest.mark.parametrize("method", ["binned", "brute", "jax"])
def test_rays_parallel_to_a_tilted_plane_miss_it(method):
    """Rays lying in (or parallel to) a tilted plane miss it, as in mj_ray, even with no range
    limit: float32 rounding of the rotated direction must not turn them into hits at t = 0
    or at 1e8 m."""
    xml = """<mujoco><worldbody><geom type="plane" size="0 0 1" pos=".3 -.2 .1"
      euler="25 -40 70" contype="0" conaffinity="0"/></worldbody></mujoco>"""
    m = mujoco.MjModel.from_xml_string(xml)
    d = mujoco.MjData(m)
    mujoco.mj_forward(m, d)
    frame = d.geom_xmat[0].reshape(3, 3)  # columns: the plane's x, y and normal
    angle = np.linspace(0, 2 * np.pi, 64, endpoint=False)
    dirs = np.cos(angle)[:, None] * frame[:, 0] + np.sin(angle)[:, None] * frame[:, 1]
    mx, dx = mjx.put_model(m), mjx.put_data(m, d)
    for height in (0.0, 0.5):
        origin = d.geom_xpos[0] + height * frame[:, 2]
        ref_d, ref_g = mj_ray_reference(m, d, origin, dirs, np.inf)
        assert (ref_g == -1).all()
        dist, gid = lidar.cast_rays(
            mx, dx, jnp.asarray(origin, jnp.float32), jnp.asarray(dirs, jnp.float32), np.inf,
            method=method,
        )  # fmt: skip
        np.testing.assert_array_equal(np.asarray(gid), ref_g, err_msg=f"height {height}")
        np.testing.assert_array_equal(np.asarray(dist), ref_d)


def test_unsupported_geoms_raise_unless_skipped():
    xml = """<mujoco><asset><mesh name="t" vertex="0 0 0 1 0 0 0 1 0 0 0 1"/></asset>
      <worldbody><geom type="mesh" mesh="t" contype="0" conaffinity="0"/>
      <geom type="sphere" size=".5" pos="3 0 0" contype="0" conaffinity="0"/>
      </worldbody></mujoco>"""
    m = mujoco.MjModel.from_xml_string(xml)
    d = mujoco.MjData(m)
    mujoco.mj_forward(m, d)
    mx, dx = mjx.put_model(m), mjx.put_data(m, d)
    dirs = jnp.array([[1.0, 0.0, 0.0], [-1.0, 0.0, 0.0]])
    with pytest.raises(ValueError, match="geom 0 \\(mjGEOM_MESH\\)"):
        lidar.cast_rays(mx, dx, jnp.array([0.0, 0.0, 5.0]), dirs, 10.0)
    dist, gid = lidar.cast_rays(
        mx, dx, jnp.array([0.0, 0.0, 0.0]), dirs, 10.0, skip_unsupported=True
    )
    np.testing.assert_allclose(np.asarray(dist), [2.5, -1.0], atol=1e-5)
    np.testing.assert_array_equal(np.asarray(gid), [1, -1])


def test_mocap_motion_needs_only_new_kinematics():
    """Moving a mocap body and re-running mjx kinematics gives mj_ray's answer (no re-init)."""
    xml = """<mujoco><default><geom contype="0" conaffinity="0"/></default><worldbody>
      <geom type="plane" size="0 0 1"/>
      <body name="person" mocap="true" pos="2 0 0.9"><geom type="capsule" size=".25 .6"/></body>
      <body pos="0 3 0.5"><joint type="slide"/><geom type="box" size=".5 .5 .5"/></body>
      </worldbody></mujoco>"""
    m = mujoco.MjModel.from_xml_string(xml)
    d = mujoco.MjData(m)
    mx = mjx.put_model(m)
    dx = mjx.put_data(m, d)
    step = jax.jit(
        lambda dx, p, v: lidar.cast_rays(
            mx, mjx.kinematics(mx, dx.replace(mocap_pos=p)), jnp.array([0.0, 0.0, 1.0]), v, 20.0
        )
    )
    dirs = unit_rays(np.random.default_rng(4), 3000)
    for x in (2.0, 1.0, -1.5):
        d.mocap_pos[0] = [x, 0.5 * x, 0.9]
        mujoco.mj_forward(m, d)
        ref_d, ref_g = mj_ray_reference(m, d, np.array([0.0, 0.0, 1.0]), dirs, 20.0)
        dist, gid = step(dx, jnp.asarray(d.mocap_pos, jnp.float32), jnp.asarray(dirs))
        np.testing.assert_array_equal(np.asarray(gid), ref_g)
        np.testing.assert_allclose(np.asarray(dist), ref_d, atol=1e-4)


def test_overflowing_cells_stay_exact(scenes):
    """A tiny candidate capacity forces the overflow path; results must not change."""
    m, d, mx, dx = scenes[1]
    dirs = unit_rays(np.random.default_rng(5), 3000)
    o = np.array([0.3, -0.2, 0.1], np.float32)
    ref_d, ref_g = mj_ray_reference(m, d, o, dirs)
    dist, gid = lidar.cast_rays(mx, dx, o, dirs, MAX_RANGE, capacity=2, cells_per_edge=4)
    ok = (np.abs(np.asarray(dist) - ref_d) <= 1e-4) & (np.asarray(gid) == ref_g)
    assert ok.mean() >= 0.999


def test_surface_normals_are_unit_and_face_the_ray(scenes):
    """Normals from outside are unit, and a ray entering a closed primitive opposes them."""
    m, d, mx, dx = scenes[2]
    geo = lidar.scene_geometry(mx, dx)
    o = jnp.array([5.5, 5.5, 5.5])
    dirs = jnp.asarray(unit_rays(np.random.default_rng(6), 3000))
    dist, gid = lidar.cast_geometry(geo, o, dirs, MAX_RANGE)
    pts = o + dirs * dist[:, None]
    n = lidar.surface_normals(geo, pts[None], gid[None])[0]
    hit = np.asarray(gid) >= 0
    assert hit.sum() > 100
    np.testing.assert_allclose(np.linalg.norm(np.asarray(n)[hit], axis=-1), 1.0, atol=1e-5)
    # Every hit from a point outside all primitives is on a front face.
    assert np.all(np.sum(np.asarray(n) * np.asarray(dirs), -1)[hit] < 1e-3)


@pytest.mark.parametrize("cells", [3, 12, 20])
def test_culling_never_changes_a_ray(scenes, cells):
    """The cube-map culling (cones, slab bounds, lazily built cells) only skips tests that
    cannot hit: binned and brute give the same geom and distance for every ray."""
    rng = np.random.default_rng(11 + cells)
    for m, d, mx, dx in scenes:
        origins = [d.geom_xpos[g] for g in rng.choice(np.arange(1, m.ngeom), 2, replace=False)]
        origins += list(rng.uniform(-4, 4, (2, 3)))
        for o in origins:
            o = jnp.asarray(o, jnp.float32)
            dirs = jnp.asarray(unit_rays(rng, 20_000))
            dist_b, gid_b = lidar.cast_rays(mx, dx, o, dirs, MAX_RANGE, cells_per_edge=cells)
            dist_r, gid_r = lidar.cast_rays(mx, dx, o, dirs, MAX_RANGE, method="brute")
            np.testing.assert_array_equal(np.asarray(gid_b), np.asarray(gid_r))
            np.testing.assert_array_equal(np.asarray(dist_b), np.asarray(dist_r))


def test_kernels_compile_for_cuda(tmp_path):
    """The CUDA path (two launches, one ray per thread) is never run on these CPU machines;
    compiling the module to sm_90 PTX with Warp's NVRTC at least proves it builds."""
    import warp as wp
    from indoorbev_sim import _lidar_kernels as K

    out = wp.compile_aot_module(K, arch=90, module_dir=tmp_path, use_ptx=True)
    assert any(str(p).endswith(".sm90.ptx") for p in out), out


def test_default_method_follows_the_environment(monkeypatch):
    """INDOORBEV_LIDAR_METHOD picks the caster; a bad value is named; unset, Warp's binned."""
    for value, want in (("jax", "jax"), ("brute", "brute"), ("", "binned")):
        monkeypatch.setenv("INDOORBEV_LIDAR_METHOD", value)
        lidar.default_method.cache_clear()
        assert lidar.default_method() == want
    monkeypatch.setenv("INDOORBEV_LIDAR_METHOD", "bvh")
    lidar.default_method.cache_clear()
    with pytest.raises(ValueError, match="INDOORBEV_LIDAR_METHOD must be one of"):
        lidar.default_method()
    monkeypatch.delenv("INDOORBEV_LIDAR_METHOD")
    lidar.default_method.cache_clear()
    with pytest.raises(ValueError, match="method must be one of"):
        lidar.cast_rays(None, None, jnp.zeros(3), jnp.ones((2, 3)), 1.0, method="bvh")


def test_warp_prints_nothing_on_stdout():
    """Warp's start-up banner and module-load lines would mix into the commands' output."""
    import subprocess
    import sys

    code = (
        "import indoorbev_sim._lidar_kernels as k, warp as wp; wp.init(); "
        "wp.load_module(k, device='cpu')"
    )
    run = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=300)
    assert run.returncode == 0, run.stderr
    assert run.stdout == ""


@pytest.mark.parametrize("method", ["binned", "brute", "jax"])
def test_degenerate_directions_miss_and_one_scene_takes_ray_sets(method):
    """A zero, tiny, NaN or infinite direction is a miss (-1, -1) for every method (mj_ray
    refuses it; the box test once answered 1e30 m from inside a box); the other rays of the
    call are untouched. One scene with ray sets [B, R, 3] gives [B, R], each set as cast on
    its own; a ray-set count other than the scenes' is named."""
    m = mujoco.MjModel.from_xml_string(random_scene_xml(5, n=8))
    d = mujoco.MjData(m)
    mujoco.mj_forward(m, d)
    mx, dx = mjx.put_model(m), mjx.put_data(m, d)
    rng = np.random.default_rng(8)
    dirs = unit_rays(rng, 64)
    bad = np.array([[0, 0, 0], [1e-20, 0, 0], [np.nan, 0, 0], [np.inf, 0, 1]], np.float32)
    origin = np.zeros(3, np.float32)  # inside or near some geoms of the random scene
    dist, gid = _cast[method](mx, dx, origin, jnp.asarray(np.r_[bad, dirs]))
    np.testing.assert_array_equal(np.asarray(dist[:4]), -1.0)
    np.testing.assert_array_equal(np.asarray(gid[:4]), -1)
    ref_d, ref_g = mj_ray_reference(m, d, origin.astype(np.float64), dirs)
    np.testing.assert_allclose(np.asarray(dist[4:]), ref_d, atol=1e-4)
    np.testing.assert_array_equal(np.asarray(gid[4:]), ref_g)
    sets = unit_rays(rng, 3 * 50).reshape(3, 50, 3)
    origins = rng.uniform(-1, 1, (3, 3)).astype(np.float32)
    dist, gid = _cast[method](mx, dx, origins, jnp.asarray(sets))
    assert dist.shape == gid.shape == (3, 50)
    for b in range(3):
        ref_d, ref_g = mj_ray_reference(m, d, origins[b].astype(np.float64), sets[b])
        np.testing.assert_allclose(np.asarray(dist[b]), ref_d, atol=1e-4)
        np.testing.assert_array_equal(np.asarray(gid[b]), ref_g)
    two = jax.tree.map(lambda x: jnp.stack([x, x]), dx)
    with pytest.raises(ValueError, match=r"one ray set per scene \(2 here\), got \(3, 50, 3\)"):
        lidar.cast_rays(mx, two, origins[:2], sets, MAX_RANGE, method=method)


@pytest.mark.parametrize("method", ["binned", "brute", "jax"])
def test_non_finite_origins_and_geom_poses_miss_like_mj_ray(method):
    """A NaN origin misses every ray and a geom with a NaN pose (here the infinite floor) is
    never hit, as in mj_ray; the Warp casters reported NaN distances on geom 0, and a NaN
    plane hid the real geoms behind it."""
    m = mujoco.MjModel.from_xml_string(random_scene_xml(6, n=8))
    d = mujoco.MjData(m)
    mujoco.mj_forward(m, d)
    dirs = unit_rays(np.random.default_rng(9), 256)
    origin = np.array([0.3, -0.2, 0.4], np.float32)
    nan_origin = np.array([np.nan, 0.0, 0.0], np.float32)
    dist, gid = _cast[method](mjx.put_model(m), mjx.put_data(m, d), nan_origin, dirs)
    np.testing.assert_array_equal(np.asarray(dist), -1.0)
    np.testing.assert_array_equal(np.asarray(gid), -1)
    d.geom_xpos[0] = np.nan  # the floor plane
    dist, gid = _cast[method](mjx.put_model(m), mjx.put_data(m, d), origin, dirs)
    ref_d, ref_g = mj_ray_reference(m, d, origin.astype(np.float64), dirs)
    assert (ref_g == -1).sum() > 50  # rays that only the floor would stop
    np.testing.assert_allclose(np.asarray(dist), ref_d, atol=1e-4)
    np.testing.assert_array_equal(np.asarray(gid), ref_g)


@pytest.mark.parametrize("method", ["binned", "jax"])
def test_a_batch_of_one_keeps_its_axis_and_empty_casts_are_empty(method):
    """Data batched over B = 1 scene gives [1, R] like any B (it gave [R]); zero rays give
    empty arrays and a model without geoms all misses (both crashed in a reshape)."""
    m = mujoco.MjModel.from_xml_string(random_scene_xml(7, n=6))
    d = mujoco.MjData(m)
    mujoco.mj_forward(m, d)
    mx, dx = mjx.put_model(m), mjx.put_data(m, d)
    dirs = unit_rays(np.random.default_rng(3), 32)
    origin = np.zeros(3, np.float32)
    one = jax.tree.map(lambda x: x[None], dx)
    dist, gid = _cast[method](mx, one, origin, dirs)
    assert dist.shape == gid.shape == (1, 32)
    ref_d, ref_g = mj_ray_reference(m, d, origin.astype(np.float64), dirs)
    np.testing.assert_allclose(np.asarray(dist[0]), ref_d, atol=1e-4)
    np.testing.assert_array_equal(np.asarray(gid[0]), ref_g)
    dist, gid = _cast[method](mx, dx, origin, np.zeros((0, 3), np.float32))
    assert dist.shape == gid.shape == (0,) and gid.dtype == jnp.int32
    empty = mujoco.MjModel.from_xml_string("<mujoco><worldbody/></mujoco>")
    e = mujoco.MjData(empty)
    mujoco.mj_forward(empty, e)
    dist, gid = _cast[method](mjx.put_model(empty), mjx.put_data(empty, e), origin, dirs)
    assert dist.shape == (32,)
    np.testing.assert_array_equal(np.asarray(dist), -1.0)
    np.testing.assert_array_equal(np.asarray(gid), -1)


def _scene(xml):
    m = mujoco.MjModel.from_xml_string(xml)
    d = mujoco.MjData(m)
    mujoco.mj_forward(m, d)
    return m, d, mjx.put_model(m), mjx.put_data(m, d)


@pytest.mark.parametrize("method", ["binned", "brute", "jax"])
def test_a_direction_shorter_than_mjminval_misses(method):
    """cast_rays documents a direction of length < mjMINVAL (1e-15) as a miss. Straight down
    from 1 m over the floor plane, (0, 0, -1e-16) misses (-1, -1) while (0, 0, -1) hits the
    floor at 1 m, as mj_ray gives for that unit ray. Guards against casting tiny directions,
    which answered 1e16 (1 m in units of |direction|)."""
    m, d, mx, dx = _scene(
        '<mujoco><worldbody><geom type="plane" size="0 0 1"/></worldbody></mujoco>'
    )
    origin = np.array([0.0, 0.0, 1.0])
    dirs = np.array([[0, 0, -1e-16], [0, 0, -1]], np.float32)
    ref_d, ref_g = mj_ray_reference(m, d, origin, dirs[1:])
    assert ref_d.tolist() == [1.0] and ref_g.tolist() == [0]
    dist, gid = _cast[method](mx, dx, jnp.asarray(origin, jnp.float32), jnp.asarray(dirs))
    assert np.asarray(dist).tolist() == [-1.0, 1.0] and np.asarray(gid).tolist() == [-1, 0]


@pytest.mark.parametrize("method", ["binned", "brute", "jax"])
def test_rays_from_on_or_inside_a_surface_match_mj_ray(method):
    """A ray starting exactly on a sphere's surface (r = 1, origin (1, 0, 0)) hits it at 0
    going in and going out (mj_ray's ray_quad keeps a root of exactly 0); a ray from inside
    a capsule (r 0.5, half-length 1, origin (0, 0, 0.8)) going down and out at 45 degrees
    leaves through its side at 0.707107 (mj_ray). Guards against refusing a root of 0 (the
    jax caster answered 2 going in, a miss going out) and against testing the cap sphere's
    root against the capsule's middle plane instead of its end (0.338162). Rays from a box's
    face and a cylinder's cap hit at 0 too."""
    s = 1 / np.sqrt(2)
    for xml, origin, dirs in [
        ('<geom type="sphere" size="1"/>', [1, 0, 0], [[-1, 0, 0], [1, 0, 0]]),
        ('<geom type="capsule" size="0.5 1"/>', [0, 0, 0.8], [[s, 0, -s]]),
        # On a box's face (the Warp box test once refused t = 0, giving the far face: 2).
        ('<geom type="box" size="1 1 1"/>', [1, 0, 0], [[-1, 0, 0], [1, 0, 0], [-1, 0.3, 0.2]]),
        (
            '<geom type="box" size="0.5 0.8 0.3" pos="0.2 0 0.5"/>',
            [0.2, 0.8, 0.5],
            [[0, -1, 0], [0, 1, 0]],
        ),  # fmt: skip
        ('<geom type="cylinder" size="0.5 1"/>', [0, 0, 1], [[0, 0, -1], [0, 0, 1]]),
    ]:
        m, d, mx, dx = _scene(f"<mujoco><worldbody>{xml}</worldbody></mujoco>")
        origin, dirs = np.array(origin, np.float64), np.array(dirs, np.float32)
        ref_d, ref_g = mj_ray_reference(m, d, origin, dirs)
        assert (ref_g == 0).all()
        dist, gid = _cast[method](mx, dx, jnp.asarray(origin, jnp.float32), jnp.asarray(dirs))
        np.testing.assert_allclose(np.asarray(dist), ref_d, atol=1e-5, err_msg=xml)
        np.testing.assert_array_equal(np.asarray(gid), ref_g, err_msg=xml)


@pytest.mark.parametrize("method", ["binned", "brute", "jax"])
def test_rays_along_a_box_axis_hit_or_pass_it_as_mj_ray(method):
    """Rays along a box's axes (two direction components exactly 0) from beside, within
    and beyond each pair of faces they run parallel to hit or pass it as in mj_ray. A
    mutation audit: the jax caster's "parallel to a slab and outside it" test at twice the
    half-size passed (random rays never have a zero component)."""
    xml = '<mujoco><worldbody><geom type="box" size="0.5 0.4 0.1" pos="0.2 -0.1 0.45"/>'
    m, d, mx, dx = _scene(xml + "</worldbody></mujoco>")
    centre, half = d.geom_xpos[0], m.geom_size[0]
    for axis in range(3):
        across = [(axis + 1) % 3, (axis + 2) % 3]
        for sign in (1.0, -1.0):
            v = np.zeros((1, 3), np.float32)
            v[0, axis] = sign
            # In units of the half-sizes across the ray: in the box's shadow when both < 1.
            for a, b in ((-1.5, 0.8), (0.8, -1.5), (0.8, 0.8), (1.5, 1.5)):
                offset = np.zeros(3)
                offset[axis] = -4 * sign * half[axis]
                offset[across] = np.array([a, b]) * half[across]
                origin = centre + offset
                ref_d, ref_g = mj_ray_reference(m, d, origin, v)
                assert (ref_g[0] == 0) == (max(abs(a), abs(b)) < 1)
                dist, gid = _cast[method](mx, dx, jnp.asarray(origin, jnp.float32), jnp.asarray(v))
                where = f"axis {axis} sign {sign} offsets {a, b}"
                np.testing.assert_array_equal(np.asarray(gid), ref_g, err_msg=where)
                np.testing.assert_allclose(np.asarray(dist), ref_d, atol=1e-5, err_msg=where)


@pytest.mark.parametrize("method", ["binned", "brute", "jax"])
def test_max_range_is_in_metres_for_a_non_unit_direction(method):
    """Distances are in units of |direction| (as mj_ray's), max_range in metres: with
    direction (2, 0, 0) a sphere whose surface is 8 m away is hit at 4.0 (mj_ray) within
    10 m and missed with max_range 6 m. Guards against comparing the distance in units of
    |direction| (4) with the range in metres (6)."""
    m, d, mx, dx = _scene(
        '<mujoco><worldbody><geom type="sphere" size="1" pos="9 0 0"/></worldbody></mujoco>'
    )
    origin, dirs = np.zeros(3), np.array([[2.0, 0, 0]], np.float32)
    ref_d, ref_g = mj_ray_reference(m, d, origin, dirs)
    assert ref_d.tolist() == [4.0] and ref_g.tolist() == [0]
    for max_range, want in ((10.0, (4.0, 0)), (6.0, (-1.0, -1))):
        dist, gid = lidar.cast_rays(
            mx, dx, jnp.zeros(3), jnp.asarray(dirs), max_range, method=method
        )
        assert (float(dist[0]), int(gid[0])) == want, max_range


@pytest.mark.parametrize("method", ["binned", "brute", "jax"])
def test_an_exact_tie_goes_to_the_lower_geom_id(method):
    """Two geoms of different types at exactly the same distance (a cylinder, id 0, and a
    box, id 1, both with their top at z = 1) give the lower id, as mj_ray does (1.0, 0) for
    a ray straight down from z = 2. Guards against a tie rule that keeps the later geom or
    the higher id."""
    m, d, mx, dx = _scene(
        """<mujoco><worldbody><geom type="cylinder" size="0.5 0.5" pos="0 0 0.5"/>
        <geom type="box" size="0.5 0.5 0.5" pos="0 0 0.5"/></worldbody></mujoco>"""
    )
    origin, dirs = np.array([0.0, 0.0, 2.0]), np.array([[0.0, 0, -1]], np.float32)
    ref_d, ref_g = mj_ray_reference(m, d, origin, dirs)
    assert ref_d.tolist() == [1.0] and ref_g.tolist() == [0]
    dist, gid = _cast[method](mx, dx, jnp.asarray(origin, jnp.float32), jnp.asarray(dirs))
    assert (float(dist[0]), int(gid[0])) == (1.0, 0)


@pytest.mark.parametrize("method", ["binned", "jax"])
def test_material_zero_alpha_and_jointless_child_bodies_follow_mj_ray(method):
    """A geom whose material (id 0, the only one) has alpha 0 is invisible to mj_ray, which
    misses it (-1); with flg_static=0 a body without joints is welded to the world and
    skipped like the world's own geoms, so the ray along +x passes the shelf at 4.5 m and
    hits the free cart at 7.5 m (mj_ray: 7.5, geom 1). Guards against testing material ids
    > 0 only (id 0 is a material) and against skipping only the world body's geoms."""
    m, d, mx, dx = _scene(
        """<mujoco><asset><material name="clear" rgba="1 1 1 0"/></asset><worldbody>
        <geom type="sphere" size="1" pos="5 0 0" material="clear"/></worldbody></mujoco>"""
    )
    dirs = np.array([[1.0, 0, 0]], np.float32)
    ref_d, ref_g = mj_ray_reference(m, d, np.zeros(3), dirs)
    assert ref_g.tolist() == [-1]
    dist, gid = _cast[method](mx, dx, jnp.zeros(3), jnp.asarray(dirs))
    assert (float(dist[0]), int(gid[0])) == (-1.0, -1)
    m, d, mx, dx = _scene(
        """<mujoco><worldbody>
        <body name="shelf" pos="5 0 0"><geom type="box" size="0.5 0.5 0.5"/></body>
        <body name="cart" pos="8 0 0"><freejoint/><geom type="box" size="0.5 0.5 0.5"/></body>
        </worldbody></mujoco>"""
    )
    ref_d, ref_g = mj_ray_reference(m, d, np.zeros(3), dirs, flg_static=0)
    assert ref_d.tolist() == [7.5] and ref_g.tolist() == [1]
    dist, gid = lidar.cast_rays(
        mx, dx, jnp.zeros(3), jnp.asarray(dirs), MAX_RANGE, flg_static=False, method=method
    )
    assert (float(dist[0]), int(gid[0])) == (7.5, 1)


def test_binned_culling_keeps_geoms_on_cell_corners():
    """The binned caster's cube-map culling must keep a geom seen exactly along a cell's
    corner or edge direction: 25 spheres of radius 0.5 mm, 5 m away along the 5 x 5 grid
    of cell-corner directions (1, u, w) of a 4-cell cube face, are each hit by the ray aimed
    at its centre, as the brute caster (every geom per ray) and mj_ray hit them. Guards
    against shrinking the cone's widening margin (the cell's angular radius plus 1e-3 rad)
    instead of growing it, which lost 7 of the 25."""
    edges = np.linspace(-1, 1, 5)
    dirs = np.array([[1.0, u, w] for u in edges for w in edges])
    dirs /= np.linalg.norm(dirs, axis=1, keepdims=True)
    geoms = "".join(
        f'<geom type="sphere" size="0.0005" pos="{x:.9f} {y:.9f} {z:.9f}"/>' for x, y, z in 5 * dirs
    )
    m, d, mx, dx = _scene(f"<mujoco><worldbody>{geoms}</worldbody></mujoco>")
    ref_d, ref_g = mj_ray_reference(m, d, np.zeros(3), dirs)
    assert (ref_g == np.arange(25)).all()
    ray = jnp.asarray(dirs, jnp.float32)
    dist, gid = lidar.cast_rays(mx, dx, jnp.zeros(3), ray, 20.0, method="binned", cells_per_edge=4)
    np.testing.assert_array_equal(np.asarray(gid), ref_g)
    np.testing.assert_allclose(np.asarray(dist), ref_d, atol=1e-4)


def test_cylinder_normals_are_the_axis_on_a_cap_and_radial_on_the_side():
    """The surface normal at a hit on a cylinder (r 0.5, half-height 0.5) is its axis
    (0, 0, 1) at a point of the flat top cap (0.1, 0, 0.5) and radial (1, 0, 0) at a point
    of the side (0.5, 0, 0.1); intensity is reflectivity x cos(incidence) on these normals.
    Guards against choosing cap or side the wrong way round."""
    _, _, mx, dx = _scene(
        '<mujoco><worldbody><geom type="cylinder" size="0.5 0.5"/></worldbody></mujoco>'
    )
    geo = lidar.scene_geometry(mx, dx)
    pts = jnp.asarray([[[0.1, 0.0, 0.5], [0.5, 0.0, 0.1]]], jnp.float32)
    n = lidar.surface_normals(geo, pts, jnp.zeros((1, 2), jnp.int32))[0]
    np.testing.assert_allclose(np.asarray(n), [[0, 0, 1], [1, 0, 0]], atol=1e-6)


README_SNIPPET = """
import os

import jax
from indoorbev_jax.config import Config
from indoorbev_sim import generate_batch

batch = jax.jit(generate_batch, static_argnums=(1,))(jax.random.key(0), Config.small())
print(batch.points.shape, batch.targets.masks.shape)
# A result dropped while it is computed: no live array is left to wait for.
print(jax.jit(generate_batch, static_argnums=(1,))(jax.random.key(1), Config.small()).points.dtype)
"""


@pytest.mark.skipif(not lidar.warp_available(), reason="the hang needs Warp's host casts")
def test_a_script_that_reads_only_shapes_exits():
    """README's snippet reads only the shapes, so the batch is still being cast when Python
    shuts down; Warp's casts need the interpreter lock, and the script used to hang for good
    (3 of 3 runs on the 2-core VM). ``lidar`` now waits for the device's work at exit."""
    import subprocess
    import sys

    env = {k: v for k, v in os.environ.items() if k != "INDOORBEV_LIDAR_METHOD"}
    try:
        proc = subprocess.run([sys.executable, "-c", README_SNIPPET], env=env, timeout=300,
                              capture_output=True, text=True)  # fmt: skip
    except subprocess.TimeoutExpired:
        pytest.fail("the script did not exit within 300 s")
    assert proc.returncode == 0, proc.stderr[-2000:]
    assert proc.stdout.split("\n")[:2] == ["(4, 24576, 4) (4, 30, 100, 100)", "float32"]
