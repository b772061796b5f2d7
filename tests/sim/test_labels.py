"""Labels of simulated frames against the sequential reference (MuJoCo mj_multiRay + numpy)
and the invariants the targets promise."""

import dataclasses
import math
import types
import warnings

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from indoorbev_sim import generate, labels, objects, reference, scenes
from scipy.spatial import cKDTree
from scipy.spatial.transform import Rotation

from indoorbev_jax.config import Config, GridConfig
from indoorbev_jax.data.rasterize import instance_ids_from_masks
from indoorbev_jax.geometry import cell_centers

# Noise-free so the reference's hits can be compared ray for ray (shared with test_scenes:
# the jitted generators are cached per config in ``generate``).
CFG = Config.tiny()
CFG = dataclasses.replace(CFG, sim=dataclasses.replace(CFG.sim, range_noise=0.0, dropout=0.0))
B = 4
KEYS = (3, 11)
KEY = jax.random.key(KEYS[0])


@pytest.fixture(scope="module")
def frames():
    """[(batch, info, reference dicts per frame)] for two batches of B frames."""
    gen = generate.jitted_generate(CFG, "train", B)
    at_rest = scenes.template_for(CFG).mj_model.geom_size.copy()
    out = []
    for seed in KEYS:
        batch, info = jax.tree.map(np.asarray, gen(jax.random.key(seed)))
        pattern = generate.make_pattern(CFG.sim).frame(int(info.frame_index[0]))
        dirs = np.asarray(pattern.directions, np.float64)
        refs = [
            reference.reference_frame(
                CFG, reference.scene_numpy(info.scene, b), float(info.time[b]), dirs,
                np.random.default_rng(0),
            )
            for b in range(B)
        ]  # fmt: skip
        out.append((batch, info, refs))
    # The reference poses a copy: the cached template's model stays at rest.
    np.testing.assert_array_equal(scenes.template_for(CFG).mj_model.geom_size, at_rest)
    return out


def test_targets_match_sequential_reference(frames):
    rays = mism = objs = 0
    for batch, info, refs in frames:
        for b, ref in enumerate(refs):
            v = batch.targets.valid[b]
            slots = info.slot[b][v]
            # The same objects are labelled (slot order kept) ...
            np.testing.assert_array_equal(slots, np.flatnonzero(ref["labelled"]))
            objs += len(slots)
            # ... with the same boxes, point counts and visibility.
            np.testing.assert_allclose(batch.targets.pos[b][v], ref["pos"][slots], atol=1e-5)
            np.testing.assert_allclose(batch.targets.dims[b][v], ref["dims"][slots], atol=1e-5)
            dyaw = batch.targets.yaw[b][v] - ref["yaw"][slots]
            np.testing.assert_allclose(np.sin(dyaw), 0, atol=1e-5)
            np.testing.assert_allclose(info.num_points[b][v], ref["num_points"][slots], atol=1)
            np.testing.assert_allclose(info.visibility[b][v], ref["visibility"][slots])
            np.testing.assert_array_equal(
                batch.targets.classes[b][v], scenes.template_for(CFG).slot_class[slots]
            )
            # Footprints equal the numpy re-derivation (cell centres on an edge may differ
            # by float rounding: allow a handful).
            diff = batch.targets.masks[b][v] != ref["masks"][slots]
            assert diff.sum() <= max(2, 0.002 * ref["masks"][slots].sum())
            rays += len(ref["valid"])
            mism += abs(int(batch.point_valid[b].sum()) - int(ref["valid"].sum()))
    assert objs >= 3, "too few labelled objects to compare"
    assert mism <= 1e-3 * rays


@pytest.mark.parametrize(
    "rpy, jitter",
    [((0.0, 20.0, 0.0), 0.0), ((180.0, 0.0, 30.0), 0.0), ((0.0, 0.0, 0.0), 15.0),
     ((0.0, 10.0, 0.0), 8.0)],
)  # fmt: skip
def test_a_tilted_lidar_sees_its_own_coverage_and_delivers_a_level_cloud(rpy, jitter):
    """``sim.sensor_rpy``: rays leave along R d (URDF rpy: pitch +20 is nose down), the
    cloud comes levelled; checked against MuJoCo's mj_multiRay and the pattern's limits.
    With ``sim.sensor_tilt_jitter`` each scene has its own tilt, cast and levelled by."""
    sim = dataclasses.replace(CFG.sim, sensor_rpy=rpy, sensor_tilt_jitter=jitter)
    cfg = dataclasses.replace(CFG, sim=sim)
    batch, info = jax.tree.map(np.asarray, generate.jitted_generate(cfg, "train", 2)(KEY))
    pattern = generate.make_pattern(cfg.sim)
    dirs = np.asarray(pattern.frame(int(info.frame_index[0])).directions, np.float64)
    lo, hi = np.degrees(reference.elevation_limits(pattern))
    if jitter:  # two different tilts, neither the nominal one, within the jitter
        offsets = np.linalg.norm(info.scene.sensor_rpy[:, :2] - rpy[:2], axis=1)
        assert np.all((offsets > 0.5) & (offsets <= jitter)), info.scene.sensor_rpy
    for b in range(2):
        scene = reference.scene_numpy(info.scene, b)
        rng = np.random.default_rng(0)
        ref = reference.reference_frame(cfg, scene, float(info.time[b]), dirs, rng)
        v = batch.targets.valid[b]
        np.testing.assert_array_equal(info.slot[b][v], np.flatnonzero(ref["labelled"]))
        np.testing.assert_allclose(info.visibility[b][v], ref["visibility"][info.slot[b][v]])
        # The same returns, levelled: every delivered point is one of the reference's.
        mine = batch.points[b][batch.point_valid[b], :3]
        theirs = ref["points"][ref["valid"], :3]
        assert abs(len(mine) - len(theirs)) <= 2
        gap, _ = cKDTree(theirs).query(mine)
        assert (gap < 1e-4).mean() >= 0.995
        # Level means the floor is the plane z = -height, whatever the tilt.
        h = float(scene.sensor_height)
        floor = ref["valid"] & (ref["geom_id"] == scenes.FLOOR)
        assert floor.sum() >= 20
        np.testing.assert_allclose(ref["points"][floor, 2], -h, atol=1e-4)
        # Coverage: the pattern's elevations [lo, hi], tilted, in the level frame.
        el = np.degrees(np.arctan2(mine[:, 2], np.linalg.norm(mine[:, :2], axis=1)))
        azimuth = np.arctan2(mine[:, 1], mine[:, 0])
        if jitter:  # back in this scene's own sensor frame, the pattern's elevations
            tilt = Rotation.from_euler("xyz", info.scene.sensor_rpy[b], degrees=True)
            own = mine @ tilt.as_matrix()  # R^T p
            el = np.degrees(np.arctan2(own[:, 2], np.linalg.norm(own[:, :2], axis=1)))
            assert el.min() >= lo - 0.5 and el.max() <= hi + 0.5 and el.min() < lo + 2.0
            continue
        if rpy[1]:  # nose down 20: ahead reaches 20 lower, behind starts 20 higher
            ahead, behind = np.abs(azimuth) < 0.2, np.abs(azimuth) > np.pi - 0.2
            assert lo - 20 - 1.5 <= el[ahead].min() < lo - 20 + 1.5
            assert el[behind].min() >= lo + 20 - 1.5
        else:  # upside down: the elevations flip, [-hi, -lo]
            assert el.min() >= -hi - 1.0 and el.max() <= -lo + 1.0 and el.min() < -hi + 3.0


def test_points_lie_in_their_own_footprint(frames):
    rows = []
    for batch, info, _ in frames:
        rows += labels.point_footprint_agreement(batch, info, CFG.grid)
    assert rows
    for r in rows:
        assert r["points"] + r["edge"] >= CFG.sim.min_points
        assert r["in_own"] >= 0.99 * r["points"], r
        assert r["in_other"] == 0, r


def test_padding_instance_ids_and_filters(frames):
    m, n = CFG.data.max_objects, CFG.data.max_points
    h, w = CFG.grid.shape
    for batch, info, _ in frames:
        t = batch.targets
        assert batch.points.shape == (B, n, 4) and batch.point_valid.shape == (B, n)
        assert t.masks.shape == (B, m, h, w) and t.instance_ids.shape == (B, h, w)
        assert t.classes.dtype == np.int32 and t.masks.dtype == bool
        # Valid targets first, padding after, with the background class and empty masks.
        for b in range(B):
            k = int(t.valid[b].sum())
            assert t.valid[b][:k].all() and not t.valid[b][k:].any()
        assert (t.classes[~t.valid] == CFG.num_classes).all()
        assert (t.classes[t.valid] < CFG.num_classes).all()
        assert not t.masks[~t.valid].any() and (info.slot[~t.valid] == -1).all()
        ids = jax.vmap(instance_ids_from_masks)(jnp.asarray(t.masks), jnp.asarray(t.valid))
        np.testing.assert_array_equal(t.instance_ids, ids)
        # min_points; occlusion levels follow visibility.
        assert (info.num_points[t.valid] >= CFG.sim.min_points).all()
        vis, occ = info.visibility[t.valid], info.occlusion[t.valid]
        expect = np.select([vis >= 0.75, vis >= 0.4, vis > 0], [0, 1, 2], 2)
        np.testing.assert_array_equal(occ, expect)
        # Points: valid ones first, inside the workspace; invalid ones zero.
        p, pv = batch.points, batch.point_valid
        g = CFG.grid
        assert (p[pv][:, 0] >= g.x_range[0]).all() and (p[pv][:, 0] <= g.x_range[1]).all()
        assert (p[pv][:, 2] >= g.z_range[0]).all() and (p[pv][:, 2] <= g.z_range[1]).all()
        assert (p[~pv] == 0).all()
        assert ((info.point_object >= 0) <= pv).all()
        # Point counts equal the points carrying each target's index.
        for b in range(B):
            counts = np.bincount(info.point_object[b][info.point_object[b] >= 0], minlength=m)
            np.testing.assert_array_equal(counts[t.valid[b]], info.num_points[b][t.valid[b]])
            # Returns of unlabelled objects (too few points, centre off the grid) name no
            # target: they were given a padding target's index.
            assert (counts[~t.valid[b]] == 0).all()


def test_a_cut_cloud_counts_the_points_it_delivers():
    """With more returns than data.max_points, labels count each object's points in the
    delivered (cut) cloud, so no target has fewer than sim.min_points; they used to count
    the uncut returns."""
    cfg = dataclasses.replace(CFG, data=dataclasses.replace(CFG.data, max_points=256))
    batch, info = jax.tree.map(np.asarray, generate.jitted_generate(cfg, "train", 2)(
        jax.random.key(5)))  # fmt: skip
    assert batch.point_valid.all()  # 2,048 rays, 256 slots: every frame is cut
    t = batch.targets
    assert t.valid.any()
    assert (info.num_points[t.valid] >= cfg.sim.min_points).all()
    for b in range(2):
        owner = info.point_object[b]
        counts = np.bincount(owner[owner >= 0], minlength=t.valid.shape[1])
        np.testing.assert_array_equal(counts[t.valid[b]], info.num_points[b][t.valid[b]])
    # The sequential reference cuts the same returns and counts the same points (a mutation
    # audit: the reference keeping the first 256 returns, not an even spread, passed).
    dirs = generate.make_pattern(cfg.sim).frame(int(info.frame_index[0])).directions
    for b in range(2):
        scene = reference.scene_numpy(info.scene, b)
        ref = reference.reference_frame(
            cfg, scene, float(info.time[b]), np.asarray(dirs, np.float64), np.random.default_rng(0)
        )
        np.testing.assert_allclose(
            batch.points[b][:, :3], ref["points"][ref["valid"]][:, :3], atol=1e-4
        )
        v = t.valid[b]
        np.testing.assert_array_equal(info.num_points[b][v], ref["num_points"][info.slot[b][v]])


@pytest.mark.parametrize(
    ("shape", "p_keep"),
    [((3, 20000), 0.7), ((2, 5, 33), 0.1), ((1, 1), 1.0), ((2, 64), 0.0), ((2, 0), 0.5)]
    + [((7,), 0.5)],
)
def test_front_order_equals_stable_argsort(shape, p_keep):
    keep = jnp.asarray(np.random.default_rng(len(shape)).random(shape) < p_keep)
    np.testing.assert_array_equal(
        jax.jit(generate.front_order)(keep), jnp.argsort(~keep, axis=-1, stable=True)
    )


@pytest.mark.parametrize("n", [1, 7, 2048, 46340, 46341])
def test_spread_positions_equal_integer_floor(n):
    rng = np.random.default_rng(n)
    counts = np.concatenate([[0, 1, n - 1, n, n + 1, 2 * n, 3 * n - 1], rng.integers(0, 2**24, 25)])
    got = np.asarray(jax.jit(generate.spread_positions, static_argnums=1)(jnp.asarray(counts), n))
    k = np.arange(n, dtype=np.int64)
    for c, row in zip(counts, got, strict=True):
        expected = k * c // n if c > n else k
        if n * n < 2**31:  # the int32 path is exact
            np.testing.assert_array_equal(row, expected)
        else:  # float32 beyond: within one position, never past the last return
            assert np.abs(row - expected).max() <= 1 and row.max() < max(c, n), c
        if c > n:
            assert row.min() >= 0 and (np.diff(row) >= 0).all()


def test_frames_past_max_points_keep_an_even_spread_of_the_returns():
    def config(n):
        tiny = Config.tiny()
        return dataclasses.replace(tiny, data=dataclasses.replace(tiny.data, max_points=n))

    key, n = jax.random.key(3), 512
    batch = jax.jit(generate.generate_batch, static_argnums=(1,))
    full, cut = batch(key, config(4096)), batch(key, config(n))  # 2,048 rays: never cut
    for b in range(full.points.shape[0]):
        returns = np.asarray(full.points[b])[np.asarray(full.point_valid[b])]
        assert len(returns) > n
        assert np.asarray(cut.point_valid[b]).all()
        spread = np.arange(n) * len(returns) // n
        np.testing.assert_array_equal(cut.points[b], returns[spread])


FINE = GridConfig(x_range=(-2.0, 2.0), y_range=(-2.0, 2.0), cell_size=0.01)


def test_round_footprints_have_their_analytic_area():
    cell = FINE.cell_size**2
    disc = reference.stadium_masks(jnp.zeros((1, 2)), jnp.zeros((1, 2)), jnp.array([0.6]), FINE)
    assert disc.sum() * cell == pytest.approx(math.pi * 0.36, rel=0.01)
    seg = jnp.array([[-0.5, 0.2]]), jnp.array([[0.7, -0.3]])
    stad = reference.stadium_masks(*seg, jnp.array([0.25]), FINE)
    length = float(jnp.linalg.norm(seg[1] - seg[0]))
    assert stad.sum() * cell == pytest.approx(math.pi * 0.0625 + 0.5 * length, rel=0.01)
    ell = reference.ellipse_masks(
        jnp.array([[0.3, -0.2]]), jnp.array([[0.9, 0.4]]), jnp.array([0.7]), FINE
    )
    assert ell.sum() * cell == pytest.approx(math.pi * 0.36, rel=0.01)


def _single_object_scene(class_name: str, variant: str):
    """A numpy scene holding one bank object at the origin, for ``reference_footprints``."""
    c = objects.CLASS_INDEX[class_name]
    bank = objects.object_bank()
    v = objects.CLASSES[c].variants.index(variant)
    prims = jax.tree.map(lambda x: x[c, v, :1], bank)
    on = np.ones(1, bool)
    scene = types.SimpleNamespace(
        pose=np.zeros((1, 3)), velocity=np.zeros((1, 2)), prims=prims, on=on
    )
    tpl = types.SimpleNamespace(num_slots=1, slot_class=np.array([c]))
    fp = reference.reference_footprints(tpl, scene, 0.0, np.zeros(3), 0.0, FINE)[0]
    return fp, prims


def test_true_shape_footprints_round_table_and_l_sofa():
    fp, prims = _single_object_scene("Table", "round")
    r = prims.size[0, 5, 0]  # the round top
    assert fp.sum() * FINE.cell_size**2 == pytest.approx(math.pi * r * r, rel=0.02)
    # L-sofa: the footprint fills its box only partly, one corner quadrant stays empty.
    fp, prims = _single_object_scene("Sofa", "l_shaped")
    length, width = prims.dims[0, :2]
    box_cells = length * width / FINE.cell_size**2
    assert 0.3 * box_cells < fp.sum() < 0.9 * box_cells
    # And the JAX rasteriser agrees with the numpy one on it.
    scene = scenes.Scene(
        room=None, on=jnp.ones(1, bool), variant=jnp.zeros(1, jnp.int32),
        prims=jax.tree.map(jnp.asarray, prims), reflectivity=jnp.zeros(1),
        background=jnp.zeros(3), pose=jnp.zeros((1, 3)), velocity=jnp.zeros((1, 2)),
        ego=jnp.zeros(3), ego_velocity=jnp.zeros(2), sensor_height=jnp.zeros(()),
        sensor_rpy=jnp.zeros(3),
    )  # fmt: skip
    c = objects.CLASS_INDEX["Sofa"]
    tpl = types.SimpleNamespace(
        num_slots=1, slot_class=np.array([c]),
        prim_geom=np.array([[0] * len(objects.CLASSES[c].prims) + [-1] * 2]),
    )  # fmt: skip
    ours = labels.footprints(tpl, scene, 0.0, jnp.zeros(3), jnp.float32(0.0), FINE)[0]
    assert (np.asarray(ours) != fp).sum() <= 4


def test_footprint_reach_windows_hold_the_whole_footprint_of_the_largest_objects():
    """``footprints`` with ``reach=footprint_reach(...)`` rasterises each object in a window
    that must hold its whole footprint: for the largest bank instance of every class and
    variant, grown by the full scale jitter, at several yaws and a turned sensor, the
    windowed footprints equal the whole-grid ones, and no marked cell lies beyond the reach."""
    from indoorbev_sim.scenes import OBJECT_SCALE_JITTER

    grid = GridConfig(x_range=(-5.0, 5.0), y_range=(-5.0, 5.0), cell_size=0.05)  # 200 x 200
    per = CFG.sim.bank_per_variant
    bank = objects.object_bank(per)
    picks = []  # (class, variant, instance) of the widest instance of every variant
    for c, spec in enumerate(objects.CLASSES):
        for v in range(len(spec.variants)):
            k = int(np.argmax(np.hypot(bank.dims[c, v, :, 0], bank.dims[c, v, :, 1])))
            picks += [(c, v, k)] * 3  # three yaws each
    cs, vs, ks = map(np.array, zip(*picks, strict=True))
    num = len(picks)
    scale = 1 + OBJECT_SCALE_JITTER
    prims = jax.tree.map(lambda x: jnp.asarray(x[cs, vs, ks]), bank)
    prims = prims.replace(size=prims.size * scale, pos=prims.pos * scale, dims=prims.dims * scale)
    yaw = np.tile([0.0, math.pi / 4, 2.0], num // 3)
    pose = np.stack([np.full(num, 0.37), np.full(num, -0.21), yaw], 1)
    scene = scenes.Scene(
        room=None, on=jnp.ones(num, bool), variant=jnp.asarray(vs, jnp.int32), prims=prims,
        reflectivity=jnp.zeros(num), background=jnp.zeros(3),
        pose=jnp.asarray(pose, jnp.float32), velocity=jnp.zeros((num, 2)),
        ego=jnp.zeros(3), ego_velocity=jnp.zeros(2), sensor_height=jnp.zeros(()),
        sensor_rpy=jnp.zeros(3),
    )  # fmt: skip
    geom = np.full((num, objects.MAX_PRIMS), -1)
    for s, c in enumerate(cs):
        geom[s, : len(objects.CLASSES[c].prims)] = 0
    tpl = types.SimpleNamespace(num_slots=num, slot_class=cs, prim_geom=geom)
    origin, heading = jnp.array([0.1, -0.2, 0.0]), jnp.float32(0.4)
    reach = labels.footprint_reach(per, grid.cell_size)
    assert 2 * math.ceil(reach / grid.cell_size) + 2 < 200  # the windowed path is taken
    windowed = np.asarray(labels.footprints(tpl, scene, 0.0, origin, heading, grid, reach))
    whole = np.asarray(labels.footprints(tpl, scene, 0.0, origin, heading, grid, None))
    assert whole.sum(axis=(1, 2)).min() > 0
    np.testing.assert_array_equal(windowed, whole)
    # The reach is what its docstring says: no marked cell centre lies farther from the centre.
    centre = np.asarray(labels.to_lidar(jnp.asarray(pose[:1, :2], jnp.float32), origin, heading))
    xs, ys = (np.asarray(a) for a in cell_centers(grid))
    dist = np.hypot(xs[None, :] - centre[0, 0], ys[:, None] - centre[0, 1])  # [H, W]
    assert dist[whole.any(0)].max() <= reach


def test_occlusion_levels_are_kittis_at_their_boundaries():
    """KITTI levels: 0 for visibility >= 0.75, 1 for >= 0.4, 2 for any visibility or any
    point, 3 for none. 3 of 4 primitives seen is exactly 0.75, which is fully visible."""
    vis = jnp.array([1.0, 0.75, 0.7499, 0.4, 0.3999, 0.0, 0.0], jnp.float32)
    points = jnp.array([9, 1, 1, 1, 1, 1, 0])
    np.testing.assert_array_equal(labels.occlusion_level(vis, points), [0, 0, 1, 1, 2, 2, 3])


def test_rectangles_match_the_shared_box_rasteriser():
    """Box footprints follow indoorbev_jax.data.rasterize.box_masks' cell rule exactly."""
    from indoorbev_jax.data.rasterize import box_masks, cell_centers

    grid = Config.small().grid
    rng = np.random.default_rng(0)
    n = 64
    boxes = np.concatenate(
        [rng.uniform(-4, 4, (n, 2)), rng.uniform(0.15, 2.0, (n, 2)), rng.uniform(-3, 3, (n, 1))],
        -1,
    ).astype(np.float32)
    xs, ys = cell_centers(grid)
    dx = xs[None, None, :] - boxes[:, 0, None, None]
    dy = ys[None, :, None] - boxes[:, 1, None, None]
    size = np.stack([boxes[:, 2] / 2, boxes[:, 3] / 2, np.zeros(n)], -1)
    ours = labels._prim_masks(
        objects.RECT, dx, dy, jnp.asarray(boxes[:, 4]), jnp.asarray(size), jnp.zeros(n),
        np.zeros(n, bool), grid.cell_size,
    )  # fmt: skip
    np.testing.assert_array_equal(ours, box_masks(jnp.asarray(boxes), grid))


def test_reference_frame_labels_objects_on_a_workspace_not_centred_on_the_sensor():
    """The oracle's "box centre in the workspace" must read x_range/y_range as given, not
    as symmetric about the sensor (x_range (-8, 2): an object at x = -3 is inside)."""
    cfg = dataclasses.replace(CFG, grid=dataclasses.replace(CFG.grid, x_range=(-8.0, 2.0)))
    batch, info = jax.tree.map(np.asarray, generate.jitted_generate(cfg, "train", 8)(KEY))
    dirs = np.asarray(generate.make_pattern(cfg.sim).frame(int(info.frame_index[0])).directions)
    far_back = 0
    for b in range(8):
        ref = reference.reference_frame(
            cfg, reference.scene_numpy(info.scene, b), float(info.time[b]),
            dirs.astype(np.float64), np.random.default_rng(0),
        )  # fmt: skip
        slots = info.slot[b][batch.targets.valid[b]]
        np.testing.assert_array_equal(slots, np.flatnonzero(ref["labelled"]))
        far_back += int((batch.targets.pos[b][batch.targets.valid[b], 0] < -2).sum())
    assert far_back, "no labelled object behind x = -2: the case is not exercised"


def test_pipeline_ellipses_and_discs_have_their_analytic_footprints():
    """The pipeline rasterises with ``_prim_masks`` (``footprints``), not with
    ``stadium_masks``/``ellipse_masks``, so the analytic areas of the SIMULATOR.md rule
    ("ellipsoids ellipses, upright cylinders discs, capsules stadiums - exact projections")
    are checked on it too: an ellipse keeps its first semi-axis along yaw (a point 0.8 m
    along yaw from the centre of a 0.9 x 0.4 ellipse is inside, 0.5 m across is not) and
    equals ``ellipse_masks``. Its axes swapped turned every person torso and plant foliage
    by 90 degrees and passed every test (a mutation audit)."""
    xs, ys = (np.asarray(a) for a in cell_centers(FINE))
    cell = FINE.cell_size**2
    c, yaw, size = np.array([0.3, -0.2]), 0.7, np.array([[0.9, 0.4, 0.3]])
    dx = jnp.asarray(xs[None, None, :] - c[0])
    dy = jnp.asarray(ys[None, :, None] - c[1])
    ell = np.asarray(labels._prim_masks(
        objects.ELLIPSE, dx, dy, jnp.array([yaw]), jnp.asarray(size), jnp.zeros(1),
        np.zeros(1, bool), FINE.cell_size,
    ))[0]  # fmt: skip
    assert ell.sum() * cell == pytest.approx(math.pi * 0.9 * 0.4, rel=0.01)
    along = np.cos(yaw) * (xs[None, :] - c[0]) + np.sin(yaw) * (ys[:, None] - c[1])
    across = -np.sin(yaw) * (xs[None, :] - c[0]) + np.cos(yaw) * (ys[:, None] - c[1])
    inside = (along / 0.9) ** 2 + (across / 0.4) ** 2 <= 1.0
    assert (ell != inside).sum() <= 4  # cells on the boundary only
    assert ell[(np.abs(along - 0.8) < 0.01) & (np.abs(across) < 0.01)].all()
    assert not ell[(np.abs(across - 0.5) < 0.01) & (np.abs(along) < 0.01)].any()
    ref = reference.ellipse_masks(jnp.asarray(c[None]), jnp.asarray(size[:, :2]), jnp.array([yaw]),
                               FINE)  # fmt: skip
    np.testing.assert_array_equal(ell, np.asarray(ref)[0])
    # Upright cylinder (radius 0.6): a disc; a capsule of half length 0.5 lying along yaw
    # (pitch 90 degrees), radius 0.25: a stadium of length 1.0 between its caps.
    disc = labels._prim_masks(
        objects.STADIUM, dx, dy, jnp.array([yaw]), jnp.array([[0.6, 0.4, 0.0]]),
        jnp.zeros(1), np.zeros(1, bool), FINE.cell_size,
    )  # fmt: skip
    assert disc.sum() * cell == pytest.approx(math.pi * 0.36, rel=0.01)
    stad = labels._prim_masks(
        objects.STADIUM, dx, dy, jnp.array([yaw]), jnp.array([[0.25, 0.5, 0.0]]),
        jnp.array([math.pi / 2]), np.zeros(1, bool), FINE.cell_size,
    )  # fmt: skip
    assert stad.sum() * cell == pytest.approx(math.pi * 0.0625 + 0.5 * 1.0, rel=0.01)


def test_horizontal_cylinders_are_rectangles_along_their_axis():
    """A horizontal cylinder (``hcyl``: size (r, half length), axis along yaw) projects to a
    2 half-length x 2 r rectangle along yaw, equal to ``rasterize.box_masks`` of that box
    (SIMULATOR.md, Labels: "horizontal cylinders are rectangles (equal to
    rasterize.box_masks)"). Treating it as a box with (r, half length) turned the wheels
    of boxy robots by 90 degrees and passed every test (a mutation audit)."""
    from indoorbev_jax.data.rasterize import box_masks

    grid = GridConfig(x_range=(-2.0, 2.0), y_range=(-2.0, 2.0), cell_size=0.05)
    xs, ys = (np.asarray(a) for a in cell_centers(grid))
    boxes = np.array([[0.2, -0.1, 1.0, 0.2, 0.3], [-0.7, 0.5, 0.6, 0.3, -1.1]], np.float32)
    size = np.array([[0.1, 0.5, 0.0], [0.15, 0.3, 0.0]], np.float32)  # (r, half length)
    dx = jnp.asarray(xs[None, None, :] - boxes[:, 0, None, None])
    dy = jnp.asarray(ys[None, :, None] - boxes[:, 1, None, None])
    ours = labels._prim_masks(
        objects.RECT, dx, dy, jnp.asarray(boxes[:, 4]), jnp.asarray(size), jnp.zeros(2),
        np.ones(2, bool), grid.cell_size,
    )  # fmt: skip
    np.testing.assert_array_equal(ours, box_masks(jnp.asarray(boxes), grid))


@pytest.fixture(scope="module")
def drawn():
    """64 frames' scenes and times as ``generate_batch`` draws them (no rays cast)."""
    return generate.jitted_draw(CFG, "train", 64)(jax.random.key(0))


def test_frame_times_lie_within_the_sequence(drawn):
    """A batch frame is "anywhere along the sequence" (draw_frames): its time lies in
    [0, (T - 1) frame_dt], the span over which placement reserved every moving object's
    path (SIMULATOR.md, Placement). Times up to 1 s past a 0.1 s sequence put objects past
    their reserved paths and passed every test (a mutation audit)."""
    _, time, _, _ = drawn
    time = np.asarray(time)
    span = (CFG.sim.frames_per_sequence - 1) * CFG.sim.frame_dt
    assert time.min() >= 0.0 and time.max() <= span + 1e-6
    assert time.max() - time.min() > 0.5 * span  # spread over the span, not one instant


def test_exactly_min_points_returns_make_a_target(drawn):
    """Targets have "at least sim.min_points (5) valid returns and the box centre inside
    the workspace" (SIMULATOR.md): ``object_labels`` with exactly min_points crafted returns
    on a slot whose centre is inside labels it, 4 returns do not, and 20 returns on a slot
    whose centre is outside do not. ``counts > min_points`` passed every test (a mutation
    audit: real frames rarely give an object exactly 5 returns)."""
    from indoorbev_jax.geometry import on_grid

    tpl = scenes.template_for(CFG)
    scene_b, time_b, _, _ = drawn
    n = CFG.sim.min_points
    assert n == 5
    rays = 64
    sizes, pn = tpl.num_slots, tpl.prim_geom.shape[1]
    vis = jnp.asarray(np.repeat(np.arange(sizes), pn).astype(np.int32))  # every ray sees its own
    label = jax.jit(lambda sc, t, o, h, slot, valid: labels.object_labels(
        tpl, sc, t, o, h, slot, valid, vis, CFG))  # fmt: skip
    for b in range(time_b.shape[0]):  # the first scene with a slot on each side of the edge
        sc = jax.tree.map(lambda x, b=b: x[b], scene_b)
        t = time_b[b]
        origin, heading = scenes.sensor_pose(sc, t)
        pos, _, _ = labels.box_labels(sc, t, origin, heading)
        grid_in = np.asarray(on_grid(pos[:, 0], pos[:, 1], CFG.grid))
        on = np.asarray(sc.on)
        ins, outs = np.flatnonzero(grid_in & on), np.flatnonzero(~grid_in & on)
        if len(ins) and len(outs):
            break
    else:
        pytest.fail("no scene with objects both inside and outside the workspace")
    for k, want in ((n, True), (n - 1, False)):
        slot = np.full(rays, -1, np.int32)
        valid = np.zeros(rays, bool)
        slot[:k], valid[:k] = ins[0], True
        slot[10:30], valid[10:30] = outs[0], True
        lab = label(sc, t, origin, heading, jnp.asarray(slot), jnp.asarray(valid))
        assert int(lab.num_points[ins[0]]) == k
        assert bool(lab.labelled[ins[0]]) is want, k
        assert int(lab.num_points[outs[0]]) == 20 and not bool(lab.labelled[outs[0]])


def test_visibility_rays_inside_min_range_are_not_fired():
    """Visibility counts only rays "beyond sim.min_range" (SIMULATOR.md, Occlusion). At the
    default 0.1 m no primitive comes that close (EGO_RADIUS + clearance), so sim.min_range
    is raised to 1.5 m, where the reference pipeline (``reference_frame``) drops some
    visibility rays. Ignoring min_range for them passed every test (a mutation audit)."""
    cfg = dataclasses.replace(CFG, sim=dataclasses.replace(CFG.sim, min_range=1.5))
    batch, info = jax.tree.map(np.asarray, generate.jitted_generate(cfg, "train", B)(KEY))
    dirs = generate.make_pattern(cfg.sim).frame(int(info.frame_index[0])).directions
    n = 0
    for b in range(B):
        ref = reference.reference_frame(
            cfg, reference.scene_numpy(info.scene, b), float(info.time[b]),
            np.asarray(dirs, np.float64), np.random.default_rng(0),
        )  # fmt: skip
        v = batch.targets.valid[b]
        slots = info.slot[b][v]
        np.testing.assert_array_equal(slots, np.flatnonzero(ref["labelled"]))
        np.testing.assert_allclose(info.visibility[b][v], ref["visibility"][slots], atol=1e-6)
        n += len(slots)
    assert n > 0


def test_the_reference_is_still_found_where_the_docs_put_it():
    """docs/SIMULATOR.md named ``generate.reference_frame`` until the sequential reference
    moved to ``reference.py``; scripts reading it there still find the same functions."""
    for name in ("reference_frame", "reference_cast", "reference_footprints", "scene_numpy"):
        assert getattr(generate, name) is getattr(reference, name)
    with pytest.raises(AttributeError, match="has no attribute 'reference_nothing'"):
        generate.reference_nothing  # noqa: B018


def test_points_in_the_outermost_cell_ring_are_counted_as_edge():
    """point_footprint_agreement leaves out the points in the outermost ring of cells
    (its docstring): one point in each of the four border strips, one inside. The last
    column left in the ring's place passed every test (a mutation audit)."""
    grid = CFG.grid
    h, w = grid.shape
    cell = grid.cell_size
    mid_x, mid_y = np.mean(grid.x_range), np.mean(grid.y_range)
    xy = [(grid.x_range[0] + cell / 2, mid_y), (grid.x_range[1] - cell / 2, mid_y),
          (mid_x, grid.y_range[0] + cell / 2), (mid_x, grid.y_range[1] - cell / 2),
          (mid_x + cell / 2, mid_y + cell / 2)]  # fmt: skip
    points = np.zeros((1, len(xy), 4), np.float32)
    points[0, :, :2] = xy
    mask = np.zeros((1, 1, h, w), bool)
    mask[0, 0, h // 2, w // 2] = True  # the inside point's cell
    targets = types.SimpleNamespace(masks=mask, valid=np.ones((1, 1), bool),
                                    classes=np.zeros((1, 1), int))  # fmt: skip
    batch = types.SimpleNamespace(points=points, targets=targets)
    info = types.SimpleNamespace(point_object=np.zeros((1, len(xy)), int),
                                 occlusion=np.zeros((1, 1), int))  # fmt: skip
    (row,) = labels.point_footprint_agreement(batch, info, grid)
    assert (row["edge"], row["points"], row["in_own"], row["in_other"]) == (4, 1, 1, 0)


def test_check_counts_objects_and_frames_per_class(frames):
    """``indoorbev-sim check``'s table: per class the labelled objects and the frames that
    hold one, against the same frames counted here (6 frames: a whole batch of B and part of
    the next). Counting objects for frames_with passed every test (a mutation audit)."""
    seed, count = 3, 6
    out = labels.check(CFG, count, B, seed)
    gen = generate.jitted_generate(CFG, "train", B)  # check's generator: compiled already
    objects_, frames_with = np.zeros(CFG.num_classes, int), np.zeros(CFG.num_classes, int)
    for start in range(0, count, B):
        batch, _ = gen(jax.random.fold_in(jax.random.key(seed), start))
        classes, valid = np.asarray(batch.targets.classes), np.asarray(batch.targets.valid)
        for b in range(min(B, count - start)):
            present = classes[b][valid[b]]
            objects_ += np.bincount(present, minlength=CFG.num_classes)
            frames_with += np.isin(np.arange(CFG.num_classes), present)
    lines = out.splitlines()
    table = lines[lines.index("class       objects  frames_with") + 1 :]
    got = {line.split()[0]: [int(v) for v in line.split()[1:]] for line in table}
    want = {name: [int(objects_[c]), int(frames_with[c])]
            for c, name in enumerate(CFG.data.class_names)}  # fmt: skip
    assert got == want
    assert (frames_with <= count).all() and (objects_ > frames_with).any()
    assert f"labelled objects: {objects_.sum()}," in out


def test_check_says_n_a_when_no_object_has_points(frames, monkeypatch):
    """No points on labelled objects (data.max_points=10) printed "0.00000" (read as a
    failed check) and numpy's "Mean of empty slice" with a nan."""
    monkeypatch.setattr(labels, "point_footprint_agreement", lambda *args: [])
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        out = labels.check(CFG, B, B, 3)
    assert "points inside own footprint dilated by 1 cell: n/a (no points on objects)" in out
    assert "objects with >= 99% of their points inside: n/a\n" in out
