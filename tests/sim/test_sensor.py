"""Sensor model: sensor-frame points, validity, noise/dropout statistics, intensity."""

import math

import jax
import jax.numpy as jnp
import mujoco
import numpy as np
import pytest
from indoorbev_sim import sensor
from mujoco import mjx
from scipy.spatial.transform import Rotation

XML = """<mujoco><default><geom contype="0" conaffinity="0"/></default><worldbody>
  <geom type="plane" size="0 0 1"/>
  <geom type="box" pos="4 0 1" size="0.1 3 1"/>
  <geom type="sphere" pos="-3 0 1" size="0.5"/>
  <site name="lidar" pos="0.5 0.2 1.0" euler="0 0 30"/>
</worldbody></mujoco>"""


def _edited_scene(old: str, new: str):
    """(MjModel, MjData) of XML with ``old`` replaced by ``new``."""
    m = mujoco.MjModel.from_xml_string(XML.replace(old, new))
    return m, mujoco.MjData(m)


# One jitted scan for all tests: eager calls would compile every small op separately.
_scan = jax.jit(sensor.scan, static_argnames="config")


@pytest.fixture(scope="module")
def scene():
    m = mujoco.MjModel.from_xml_string(XML)
    d = mujoco.MjData(m)
    mujoco.mj_forward(m, d)
    return m, d, mjx.put_model(m), mjx.put_data(m, d)


def unit_rays(n, seed=0):
    v = np.random.default_rng(seed).normal(size=(n, 3))
    return (v / np.linalg.norm(v, axis=1, keepdims=True)).astype(np.float32)


def test_points_are_hits_in_the_sensor_frame(scene):
    """Noise-free points, mapped back to the world with the site pose, match mj_ray hits."""
    m, d, mx, dx = scene
    pose = sensor.pose_from_site(dx, 0)
    dirs = unit_rays(4000)
    cfg = sensor.SensorConfig(range_noise_std=0.0, min_range=0.0, max_range=20.0)
    s = _scan(mx, dx, pose, dirs, jax.random.key(0), cfg)
    assert s.points.shape == (4000, 4) and s.valid.dtype == jnp.bool_
    rot = d.site_xmat[0].reshape(3, 3)
    np.testing.assert_allclose(np.asarray(pose.rot), rot, atol=1e-6)
    world_dirs = dirs @ rot.T
    gid = np.zeros(1, np.int32)
    ref = np.array([mujoco.mj_ray(m, d, d.site_xpos[0], v, None, 1, -1, gid) for v in world_dirs])
    ref_valid = (ref >= 0) & (ref <= 20.0)
    np.testing.assert_array_equal(np.asarray(s.valid), ref_valid)
    pts = np.asarray(s.points)[ref_valid]
    np.testing.assert_allclose(pts[:, :3], dirs[ref_valid] * ref[ref_valid, None], atol=2e-4)
    assert np.all(np.asarray(s.points)[~ref_valid] == 0)
    # Directions of any length are rays: the same points in metres, the same intensity
    # (they scaled the range, the min-range test and the incidence cosine). Zero: a miss.
    scaled = dirs * np.linspace(0.5, 3.0, len(dirs), dtype=np.float32)[:, None]
    scaled[0] = 0.0
    t = _scan(mx, dx, pose, scaled, jax.random.key(0), cfg)
    np.testing.assert_array_equal(np.asarray(t.valid)[1:], ref_valid[1:])
    assert not t.valid[0] and np.all(np.asarray(t.points[0]) == 0)
    np.testing.assert_allclose(np.asarray(t.points)[1:], np.asarray(s.points)[1:], atol=2e-4)
    # A scan pattern's rays (unit within float32 rounding) are used as given, bit for bit:
    # rescaling them would move every simulated frame (and the held-out test set) a little.
    from indoorbev_sim.patterns import Mid360Pattern

    unit = np.asarray(Mid360Pattern().frame(0).directions)
    u = _scan(mx, dx, pose, unit, jax.random.key(0), cfg)
    hit = np.asarray(u.valid)
    assert hit.sum() > 1000
    np.testing.assert_array_equal(
        np.asarray(u.points)[hit, :3], unit[hit] * np.asarray(u.distance)[hit, None]
    )


def test_noise_dropout_and_range_limits(scene):
    m, d, mx, dx = scene
    pose = sensor.Pose(jnp.array([0.0, 0.0, 1.0]), jnp.eye(3))
    # Rays that all hit the wall at x = 3.9: noise and dropout statistics are checkable.
    dirs = np.tile(np.array([[1.0, 0.0, 0.0]], np.float32), (20000, 1))
    cfg = sensor.SensorConfig(range_noise_std=0.05, dropout_prob=0.25)

    def run(key):
        return _scan(mx, dx, pose, dirs, key, cfg)

    s = run(jax.random.key(1))
    valid = np.asarray(s.valid)
    assert abs(valid.mean() - 0.75) < 0.02  # dropout rate
    rng = np.asarray(s.points)[valid, 0]
    assert abs(rng.mean() - 3.9) < 0.003 and abs(rng.std() - 0.05) < 0.003
    # Same key, same scan; another key, another scan.
    np.testing.assert_array_equal(np.asarray(run(jax.random.key(1)).points), np.asarray(s.points))
    assert not np.array_equal(np.asarray(run(jax.random.key(2)).points), np.asarray(s.points))
    # Range limits: the wall lies beyond max_range 3 m, and inside min_range 5 m.
    for c in (sensor.SensorConfig(max_range=3.0), sensor.SensorConfig(min_range=5.0, max_range=9)):
        assert not np.any(np.asarray(_scan(mx, dx, pose, dirs, jax.random.key(0), c).valid))


def test_range_limits_apply_to_the_noisy_range(scene):
    """min_range/max_range judge the measured (noisy) range, not the true distance: with
    limits 2 cm either side of a wall 3.9 m away and 5 cm noise, every valid point's range
    lies within them and the share kept is P(|N(0, 0.05)| <= 0.02) (all were kept, with
    ranges up to 20 cm past the limits)."""
    m, d, mx, dx = scene
    pose = sensor.Pose(jnp.array([0.0, 0.0, 1.0]), jnp.eye(3))
    dirs = np.tile(np.array([[1.0, 0.0, 0.0]], np.float32), (20000, 1))  # the wall at 3.9 m
    cfg = sensor.SensorConfig(min_range=3.88, max_range=3.92, range_noise_std=0.05)
    s = _scan(mx, dx, pose, dirs, jax.random.key(1), cfg)
    np.testing.assert_allclose(np.asarray(s.distance), 3.9, atol=1e-4)  # the noiseless range
    valid = np.asarray(s.valid)
    rng = np.linalg.norm(np.asarray(s.points)[valid, :3], axis=1)
    assert rng.min() >= 3.88 - 1e-6 and rng.max() <= 3.92 + 1e-6, (rng.min(), rng.max())
    expected = math.erf(0.02 / 0.05 / math.sqrt(2.0))  # 0.311; binomial sd 0.003
    assert abs(valid.mean() - expected) < 0.015, (valid.mean(), expected)


def test_pose_from_body_is_the_body_frame_not_its_centre_of_mass():
    """A body whose geom sits off its origin: the pose is the body frame (xpos), where the
    XML puts it, not the inertial frame (xipos, 0.4 m along the body's x)."""
    m, d = _edited_scene(
        "</worldbody>",
        '<body name="robot" pos="1 2 0.3" euler="0 0 90"><geom type="box" pos="0.4 0 0" '
        'size="0.2 0.1 0.1"/></body></worldbody>',
    )
    mujoco.mj_forward(m, d)
    body = m.body("robot").id
    assert np.linalg.norm(d.xipos[body] - d.xpos[body]) > 0.3  # the two frames differ
    for data in (d, mjx.put_data(m, d)):
        pose = sensor.pose_from_body(data, body)
        np.testing.assert_allclose(np.asarray(pose.pos), [1.0, 2.0, 0.3], atol=1e-6)
        np.testing.assert_allclose(
            np.asarray(pose.rot), [[0, -1, 0], [1, 0, 0], [0, 0, 1]], atol=1e-6
        )


def test_intensity_from_reflectivity_and_incidence(scene):
    """Intensity = reflectivity * cos(incidence) on the floor plane (normal +z)."""
    m, d, mx, dx = scene
    pose = sensor.Pose(jnp.array([0.0, 0.0, 1.0]), jnp.eye(3))
    el = np.radians(np.array([-80.0, -60.0, -30.0, -20.0]))
    dirs = np.stack([np.cos(el), np.zeros(4), np.sin(el)], -1).astype(np.float32)
    refl = jnp.array([0.8, 0.3, 0.3])
    cfg = sensor.SensorConfig(range_noise_std=0.0)
    s = _scan(mx, dx, pose, dirs, jax.random.key(0), cfg, reflectivity=refl)
    np.testing.assert_array_equal(np.asarray(s.geom_id), 0)
    np.testing.assert_allclose(np.asarray(s.points[:, 3]), 0.8 * np.abs(np.sin(el)), atol=1e-5)
    # A reflectivity above 1 (retro-reflective tape) still gives an intensity within [0, 1].
    s = _scan(mx, dx, pose, dirs, jax.random.key(0), cfg, reflectivity=1.5 * refl / 0.8)
    want = np.minimum(1.5 * np.abs(np.sin(el)), 1.0)  # 1.48 and 1.30 clip, 0.75 and 0.51 not
    np.testing.assert_allclose(np.asarray(s.points[:, 3]), want, atol=1e-5)
    # One value short, or a quaternion for rot: JAX's reshape errors named neither.
    with pytest.raises(
        ValueError,
        match=r"reflectivity: expected one value per geom, .*G = 3, B = 1, got shape \[2\]",
    ):
        _scan(mx, dx, pose, dirs, jax.random.key(0), cfg, reflectivity=refl[:2])
    quat = sensor.Pose(jnp.array([0.0, 0.0, 1.0]), jnp.array([1.0, 0.0, 0.0, 0.0]))
    with pytest.raises(
        ValueError, match=r"pose\.rot: expected \[3, 3\] or \[B, 3, 3\] or \[9\] .*got shape \[4\]"
    ):
        _scan(mx, dx, quat, dirs, jax.random.key(0), cfg)
    # MuJoCo's flat xmat (MjData.site_xmat[i], [9]) is a rotation matrix, read as [3, 3].
    flat = sensor.Pose(pose.pos, jnp.eye(3).reshape(9))
    got = _scan(mx, dx, flat, dirs, jax.random.key(0), cfg, reflectivity=refl)
    want = _scan(mx, dx, pose, dirs, jax.random.key(0), cfg, reflectivity=refl)
    np.testing.assert_array_equal(np.asarray(got.points), np.asarray(want.points))
    # A pitched sensor: the incidence is the world ray's (R d) on the floor, not the sensor
    # frame's. A mutation audit: the sensor-frame rays (an identity pose cannot tell) passed.
    rot = Rotation.from_euler("y", 30.0, degrees=True).as_matrix()
    pitched = sensor.Pose(jnp.array([0.0, 0.0, 1.0]), jnp.asarray(rot, jnp.float32))
    s = _scan(mx, dx, pitched, dirs, jax.random.key(0), cfg, reflectivity=refl)
    world_z = (dirs.astype(np.float64) @ rot.T)[:, 2]
    assert (world_z < 0).all() and np.asarray(s.geom_id).tolist() == [0] * 4
    np.testing.assert_allclose(np.asarray(s.points[:, 3]), 0.8 * np.abs(world_z), atol=1e-5)


def test_batched_scenes_and_poses(scene):
    """B scenes with B poses in one call equal B single calls, and B poses in one scene."""
    m, d, mx, dx = scene
    dxb = jax.tree.map(lambda x: jnp.stack([x, x]), dx)
    rots = Rotation.from_euler("z", [[0.0], [90.0]], degrees=True).as_matrix().astype(np.float32)
    pose = sensor.Pose(jnp.array([[0.0, 0.0, 1.0], [1.0, 0.5, 0.8]]), jnp.asarray(rots))
    dirs = unit_rays(2000, 1)
    cfg = sensor.SensorConfig(range_noise_std=0.0)
    sb = _scan(mx, dxb, pose, dirs, jax.random.key(0), cfg)
    assert sb.points.shape == (2, 2000, 4)
    for b in range(2):
        pb = sensor.Pose(pose.pos[b], pose.rot[b])
        s1 = _scan(mx, dx, pb, dirs, jax.random.key(0), cfg)
        np.testing.assert_array_equal(np.asarray(sb.valid[b]), np.asarray(s1.valid))
        np.testing.assert_allclose(np.asarray(sb.points[b]), np.asarray(s1.points), atol=1e-5)
    # B poses in one unbatched scene: that scene scanned from each (a broadcast error before).
    sp = _scan(mx, dx, pose, dirs, jax.random.key(0), cfg)
    np.testing.assert_array_equal(np.asarray(sp.valid), np.asarray(sb.valid))
    np.testing.assert_allclose(np.asarray(sp.points), np.asarray(sb.points), atol=1e-6)
    # One position [3] with B rotations [B, 3, 3]: B scans from that position (it raised,
    # counting the poses by the positions only), each as the single pose's scan.
    turned = _scan(mx, dx, sensor.Pose(pose.pos[0], pose.rot), dirs, jax.random.key(0), cfg)
    assert turned.points.shape == (2, 2000, 4)
    for b in range(2):
        s1 = _scan(mx, dx, sensor.Pose(pose.pos[0], pose.rot[b]), dirs, jax.random.key(0), cfg)
        np.testing.assert_array_equal(np.asarray(turned.valid[b]), np.asarray(s1.valid))
        np.testing.assert_allclose(np.asarray(turned.points[b]), np.asarray(s1.points), atol=1e-5)
    # A batch of one pose keeps its axis (it was dropped, unlike cast_rays'), scene batched
    # or not.
    one = sensor.Pose(pose.pos[:1], pose.rot[:1])
    first = jax.tree.map(lambda x: x[:1], dxb)
    for data in (dx, first):
        s1 = _scan(mx, data, one, dirs, jax.random.key(0), cfg)
        assert s1.points.shape == (1, 2000, 4) and s1.valid.shape == (1, 2000)
        np.testing.assert_array_equal(np.asarray(s1.valid), np.asarray(sb.valid[:1]))


def test_bad_config_names_the_field():
    with pytest.raises(ValueError, match="dropout_prob"):
        sensor.SensorConfig(dropout_prob=1.5)
    with pytest.raises(ValueError, match="min_range"):
        sensor.SensorConfig(min_range=5.0, max_range=1.0)
    # NaN passed `value < 0` and gave all-invalid scans or NaN intensities.
    for name, bad in (("range_noise_std", np.nan), ("range_noise_std", np.inf),
                      ("incidence_exponent", np.nan), ("incidence_exponent", -1.0),
                      ("default_reflectivity", np.nan), ("default_reflectivity", 1.5),
                      ("dropout_prob", np.nan)):  # fmt: skip
        with pytest.raises(ValueError, match=f"SensorConfig.{name} must be"):
            sensor.SensorConfig(**{name: bad})


def test_mjlidar_scans_host_mujoco_states_like_scan():
    """MjLidar on a stepped MjData (a mocap body moving) equals scan on mjx.put_data."""
    from indoorbev_sim import patterns

    m, d = _edited_scene(
        "</worldbody>",
        '<body name="cart" mocap="true" pos="2 1 0.5"><geom type="box" size="0.3 0.3 0.5"/>'
        "</body></worldbody>",
    )
    pattern = patterns.GridPattern(90, 8)
    cfg = sensor.SensorConfig(range_noise_std=0.01, dropout_prob=0.1, max_range=20.0)
    lidar = sensor.MjLidar(m, "lidar", pattern, cfg)
    mx = mjx.put_model(m)
    for k in range(3):
        d.mocap_pos[0] = [2.0 - 0.5 * k, 1.0, 0.5]
        mujoco.mj_forward(m, d)
        key = jax.random.key(k)
        got = lidar(d, key, frame=k)
        dx = mjx.put_data(m, d)
        dirs = pattern.frame(k).directions
        want = _scan(mx, dx, sensor.pose_from_site(dx, 0), dirs, key, cfg)
        for a, b in zip(jax.tree.leaves(got), jax.tree.leaves(want), strict=True):
            np.testing.assert_array_equal(np.asarray(a), np.asarray(b))
        assert np.asarray(got.geom_id == m.ngeom - 1).sum() > 0  # the cart is seen
    # Edits of the model between calls are seen (they were copied once, at construction).
    for edit in ("size", "alpha"):
        if edit == "size":
            m.geom_size[-1] = [0.6, 0.6, 0.5]
        else:
            m.geom_rgba[-1, 3] = 0.0  # hidden, as mj_ray hides it
        key = jax.random.key(7)
        got = lidar(d, key, frame=0)
        dx, mx = mjx.put_data(m, d), mjx.put_model(m)
        want = _scan(mx, dx, sensor.pose_from_site(dx, 0), pattern.frame(0).directions, key, cfg)
        for a, b in zip(jax.tree.leaves(got), jax.tree.leaves(want), strict=True):
            np.testing.assert_array_equal(np.asarray(a), np.asarray(b))
        seen = np.asarray(got.geom_id == m.ngeom - 1).sum()
        assert (seen > 0) == (edit == "size"), edit
    # An edit right after a call must not reach that call: rgba and matid went in as views
    # of the live model (float32 / int32 already) while the call ran asynchronously.
    m.geom_rgba[-1, 3] = 1.0
    for k in range(10):
        scan = lidar(d, jax.random.key(k), frame=0)
        m.geom_rgba[-1, 3] = 0.0
        assert np.asarray(scan.geom_id == m.ngeom - 1).sum() > 0, k
        m.geom_rgba[-1, 3] = 1.0
    # pose_from_site reads MjData's [n, 9] matrices as MJX's [n, 3, 3] (an IndexError).
    host, device = sensor.pose_from_site(d, 0), sensor.pose_from_site(mjx.put_data(m, d), 0)
    np.testing.assert_array_equal(host.rot, device.rot)
    np.testing.assert_array_equal(host.pos, device.pos)
    body = int(m.site_bodyid[0])
    np.testing.assert_array_equal(sensor.pose_from_body(d, body).rot, d.xmat[body].reshape(3, 3))
    with pytest.raises(ValueError, match="no site 'lidar2'; sites: \\['lidar'\\]"):
        sensor.MjLidar(m, "lidar2", pattern)
    other = mujoco.MjData(mujoco.MjModel.from_xml_string(XML))  # one geom fewer
    with pytest.raises(ValueError, match=r"geom_xpos has shape \(3, 3\), the model has 4 geoms"):
        lidar(other, jax.random.key(0))


def test_mjlidar_does_not_see_its_own_body():
    """A site inside a robot's housing: MjLidar excludes the site's body by default (as
    MuJoCo's rangefinder does); bodyexclude=-1 brings the housing back."""
    from indoorbev_sim import patterns

    m, d = _edited_scene(
        '<site name="lidar" pos="0.5 0.2 1.0" euler="0 0 30"/>',
        '<body name="robot" pos="0.5 0.2 1.0"><geom type="cylinder" size="0.1 0.1"/>'
        '<site name="lidar" euler="0 0 30"/></body>',
    )
    mujoco.mj_forward(m, d)
    housing = m.body("robot").geomadr[0]
    pattern = patterns.GridPattern(90, 8)
    cfg = sensor.SensorConfig(range_noise_std=0.0, dropout_prob=0.0, min_range=0.0)
    own = np.asarray(sensor.MjLidar(m, "lidar", pattern, cfg)(d, jax.random.key(0)).geom_id)
    seen = np.asarray(
        sensor.MjLidar(m, "lidar", pattern, cfg, bodyexclude=-1)(d, jax.random.key(0)).geom_id
    )
    assert (seen == housing).all()  # every ray starts inside the housing
    assert not (own == housing).any() and (own >= 0).any()
    # The default is mj_ray's answer with the site's body excluded.
    site = d.site_xpos[m.site("lidar").id]
    dirs = np.asarray(pattern.frame(0).directions, np.float64) @ d.site_xmat[0].reshape(3, 3).T
    out = np.zeros(1, np.int32)
    ref = []
    for v in dirs:
        mujoco.mj_ray(m, d, site, v, None, 1, m.body("robot").id, out)
        ref.append(out[0])
    np.testing.assert_array_equal(own, ref)


def test_mjlidar_takes_robot_models_mjx_refuses():
    """An ordinary robot MJCF: geoms that collide (contype 1: a cylinder-box pair MJX lacks),
    a mesh on the robot (skipped), a material with alpha 0 (invisible to mj_ray). MjLidar
    needs no collision support; its hits equal mj_ray's with the robot body excluded."""
    from indoorbev_sim import patterns

    xml = """<mujoco><asset><material name="glass" rgba="1 1 1 0"/>
      <mesh name="tet" vertex="0 0 0 .1 0 0 0 .1 0 0 0 .1"/></asset><worldbody>
      <geom type="plane" size="0 0 1"/>
      <geom type="box" size=".1 3 1" pos="3 0 1"/>
      <geom type="box" size=".1 3 1" pos="-3 0 1" material="glass"/>
      <geom type="sphere" size=".3" pos="1 1 .5"/>
      <body name="robot" pos="0 0 .3"><freejoint/><geom type="cylinder" size=".2 .2"/>
        <geom type="mesh" mesh="tet" pos="0 0 .2"/><site name="lidar" pos="0 0 .35"/></body>
      </worldbody></mujoco>"""
    m = mujoco.MjModel.from_xml_string(xml)
    d = mujoco.MjData(m)
    mujoco.mj_forward(m, d)
    with pytest.raises(NotImplementedError):  # why MjLidar must not go through MJX
        mjx.put_model(m)
    pattern = patterns.GridPattern(90, 8)
    cfg = sensor.SensorConfig(range_noise_std=0.0, dropout_prob=0.0, min_range=0.0)
    got = sensor.MjLidar(m, "lidar", pattern, cfg, skip_unsupported=True)(d, jax.random.key(0))
    site = m.site("lidar").id
    dirs = np.asarray(pattern.frame(0).directions, np.float64) @ d.site_xmat[site].reshape(3, 3).T
    out = np.zeros(1, np.int32)
    ref_d, ref_g = [], []
    for v in dirs:
        ref_d.append(mujoco.mj_ray(m, d, d.site_xpos[site], v, None, 1, m.body("robot").id, out))
        ref_g.append(out[0])
    ref_d, ref_g = np.asarray(ref_d), np.asarray(ref_g)
    np.testing.assert_array_equal(np.asarray(got.geom_id), ref_g)
    np.testing.assert_allclose(np.asarray(got.distance)[ref_g >= 0], ref_d[ref_g >= 0], atol=1e-4)
    assert m.geom_matid[2] >= 0 and not (ref_g == 2).any()  # the glass wall is not hit
    assert {1, 3} <= set(ref_g.tolist())  # the wall and the sphere are seen
