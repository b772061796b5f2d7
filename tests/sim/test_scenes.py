"""Object library, layouts and scene sampling: shapes, placement, splits, motion, config."""

import dataclasses

import jax
import numpy as np
import pytest
import shapely
from indoorbev_sim import generate, layouts, objects, scenes

from indoorbev_jax.config import Config, ConfigError, SimConfig

CFG = Config.tiny()
CFG = dataclasses.replace(CFG, sim=dataclasses.replace(CFG.sim, range_noise=0.0, dropout=0.0))
NUM = 24


@pytest.fixture(scope="module")
def sampled():
    """NUM train scenes and NUM test scenes (one compile: the split flag is traced)."""
    fn = jax.jit(lambda k, test: generate.sample_scenes(k, CFG, NUM, test))
    key = jax.random.key(7)
    return {
        "train": jax.tree.map(np.asarray, fn(key, False)),
        "test": jax.tree.map(np.asarray, fn(key, True)),
    }


def test_object_bank_every_variant_is_a_sound_object():
    bank = objects.object_bank()
    for c, spec in enumerate(objects.CLASSES):
        for v, name in enumerate(spec.variants):
            p = jax.tree.map(lambda x, c=c, v=v: x[c, v], bank)  # [K, P, ...]
            assert p.on.any(axis=1).all(), name
            assert (p.dims > 0.05).all() and (p.dims[:, 2] < 2.3).all(), (spec.name, name)
            # Every primitive lies inside the object's box (which is centred in x, y).
            kinds = spec.prims + ("box",) * (objects.MAX_PRIMS - len(spec.prims))
            half = objects.prim_half_extents(kinds, p.size, p.yaw, p.pitch, np)
            lo, hi = p.pos - half, p.pos + half
            box = p.dims[:, None]
            on = p.on[..., None]
            assert (~on | (np.abs(lo[..., :2]) <= box[..., :2] / 2 + 1e-5)).all()
            assert (~on | (np.abs(hi[..., :2]) <= box[..., :2] / 2 + 1e-5)).all()
            assert (~on | (lo[..., 2:] >= -1e-5)).all() and (
                ~on | (hi[..., 2:] <= box[..., 2:] + 1e-5)
            ).all()
            # Sizes of used primitives are positive (MuJoCo rejects zero sizes).
            assert (p.size[..., 0][p.on] > 0).all()


def _rects(scene, b, time):
    """Shapely rectangles (l x w at the pose) of the objects of scene b at ``time``."""
    out = {}
    for s in np.flatnonzero(scene.on[b]):
        x, y = scene.pose[b, s, :2] + scene.velocity[b, s] * time
        yaw = scene.pose[b, s, 2]
        length, width = scene.prims.dims[b, s, :2]
        rect = shapely.box(-length / 2, -width / 2, length / 2, width / 2)
        rect = shapely.affinity.rotate(rect, yaw, use_radians=True, origin=(0, 0))
        out[s] = shapely.affinity.translate(rect, x, y)
    return out


def test_placement_is_collision_free_inside_the_room_over_the_sequence(sampled):
    span = (CFG.sim.frames_per_sequence - 1) * CFG.sim.frame_dt
    placed = 0
    for scene in sampled.values():
        for b in range(NUM):
            hx, hy = scene.room.size[b] / 2
            room = shapely.box(-hx, -hy, hx, hy)
            for time in (0.0, span / 2, span):
                rects = _rects(scene, b, time)
                ego = shapely.Point(scene.ego[b, :2] + scene.ego_velocity[b] * time)
                for s, r in rects.items():
                    assert room.contains(r), (b, s)
                    assert r.distance(ego) >= scenes.EGO_RADIUS + CFG.sim.clearance - 1e-4
                    for s2, r2 in rects.items():
                        if s2 > s:
                            assert r.distance(r2) >= CFG.sim.clearance - 1e-4, (b, s, s2)
            placed += len(rects)
    assert placed > NUM  # scenes are not empty


def test_splits_hold_out_plans_and_variants(sampled):
    held = {layouts.plan_id(n, CFG.sim.plans_per_layout) for n in CFG.sim.test_layouts}
    assert not set(sampled["train"].room.plan.tolist()) & held
    assert set(sampled["test"].room.plan.tolist()) <= held
    trolley = (
        objects.CLASS_INDEX["Misc"],
        objects.CLASSES[objects.CLASS_INDEX["Misc"]].variants.index("trolley"),
    )
    tpl = scenes.template_for(CFG)
    misc = tpl.slot_class == trolley[0]
    assert not (sampled["train"].variant[:, misc] == trolley[1]).any()
    # The pools themselves: train/val never draw a held-out plan or variant.
    assert not set(scenes.allowed_plans(CFG.sim, "train").tolist()) & held
    assert not scenes.allowed_variants(CFG.sim, "val")[trolley]
    assert scenes.allowed_variants(CFG.sim, "test")[trolley]


def test_a_test_split_without_held_out_plans_is_said():
    """Test falls back to the training plans when no held-out plan lies in sim.layouts; the
    export and eval_sim say so instead of calling its frames held out."""
    assert scenes.held_out_by_layout(CFG.sim) and scenes.held_out_note(CFG.sim) is None
    for sim in (
        dataclasses.replace(CFG.sim, layouts=("office",), test_layouts=("lab/7",)),
        dataclasses.replace(CFG.sim, test_layouts=()),
    ):
        test, train = scenes.allowed_plans(sim, "test"), scenes.allowed_plans(sim, "train")
        assert np.isin(test, train).all()  # the fallback the note is about
        assert not scenes.held_out_by_layout(sim)
        assert "not held out by layout" in scenes.held_out_note(sim)
    office = dataclasses.replace(CFG.sim, layouts=("office",), test_layouts=("office/7",))
    assert scenes.held_out_by_layout(office)


def test_variant_ids_index_all_variants():
    pairs = [(c, v) for c, spec in enumerate(objects.CLASSES) for v in range(len(spec.variants))]
    classes, variants = np.array(pairs).T
    ids = objects.variant_ids(classes, variants)
    assert [objects.ALL_VARIANTS[i] for i in ids] == [objects.variant_key(c, v) for c, v in pairs]
    np.testing.assert_array_equal(objects.variant_ids([[0, 8]], [[-1, -1]]), [[-1, -1]])


def test_plans_are_fixed_geometry():
    a = layouts.make_room(5, 8)
    b = layouts.make_room(5, 8)
    np.testing.assert_array_equal(a.size, b.size)
    for pid in range(len(layouts.LAYOUTS) * 8):
        room = layouts.make_room(pid, 8)
        kind = layouts.LAYOUTS[pid // 8]
        assert kind.size_x[0] <= room.size[0] <= kind.size_x[1]
        assert layouts.plan_id(layouts.plan_name(pid, 8), 8) == pid
    with pytest.raises(ValueError, match="layout plan"):
        layouts.plan_id("garage/1", 8)


def test_only_persons_and_robots_move(sampled):
    for scene in sampled.values():
        speed = np.linalg.norm(scene.velocity, axis=-1)  # [N, S]
        cls = scenes.template_for(CFG).slot_class[None].repeat(NUM, 0)
        dynamic = np.isin(cls, [objects.CLASS_INDEX["Person"], objects.CLASS_INDEX["Robot"]])
        assert (speed[~dynamic] == 0).all()
        standing = (cls == objects.CLASS_INDEX["Person"]) & (scene.variant == 0)
        assert (speed[standing] == 0).all()
        walking = (cls == objects.CLASS_INDEX["Person"]) & (scene.variant == 1) & scene.on
        assert (
            speed[walking] >= objects.CLASSES[objects.CLASS_INDEX["Person"]].speed[0] - 1e-6
        ).all()
        # Poses advance by velocity x time.
        later = np.asarray(scenes.object_poses(scene, 0.3))
        np.testing.assert_allclose(
            later[..., :2], scene.pose[..., :2] + 0.3 * scene.velocity, atol=1e-5
        )


def test_generate_batch_contract():
    from indoorbev_sim import generate_batch  # the package-level export

    assert generate_batch is generate.generate_batch
    batch, info = generate.jitted_generate(CFG, "train", 4)(jax.random.key(3))
    m, n = CFG.data.max_objects, CFG.data.max_points
    assert batch.points.shape == (4, n, 4) and batch.points.dtype == np.float32
    assert batch.targets.masks.shape == (4, m, *CFG.grid.shape)
    assert batch.targets.dims.shape == (4, m, 3) and batch.targets.yaw.shape == (4, m)
    assert info.num_points.shape == (4, m) and info.point_object.shape == (4, n)


def test_sim_config_validation_names_fields():
    with pytest.raises(ConfigError, match="sim.test_layouts"):
        SimConfig(test_layouts=("office/99",))
    with pytest.raises(ConfigError, match="sim.slots_per_class"):
        SimConfig(slots_per_class=(1, 2))
    with pytest.raises(ConfigError, match="sim.num_rays"):
        SimConfig(pattern="os128", num_rays=1000)
    with pytest.raises(ConfigError, match="sim.dropout"):
        SimConfig(dropout=1.5)
    with pytest.raises(ValueError, match="sim.test_variants"):
        scenes.allowed_variants(SimConfig(test_variants=("Chair/throne",)), "train")


def test_tilt_jitter_draws_each_scene_a_tilt_and_moves_no_other_draw(sampled):
    """``sim.sensor_tilt_jitter``: roll and pitch offsets uniform over a disk of that radius
    around ``sim.sensor_rpy``, drawn on a key of their own (a dataset's scenes stay put)."""
    sim = dataclasses.replace(CFG.sim, sensor_rpy=(0.0, 10.0, 30.0), sensor_tilt_jitter=8.0)
    cfg = dataclasses.replace(CFG, sim=sim)
    n = 400  # the fixture's NUM keys first, so their scenes can be compared
    keys = jax.numpy.concatenate(
        [jax.random.split(jax.random.key(7), NUM), jax.random.split(jax.random.key(8), n - NUM)]
    )
    sample = jax.jit(jax.vmap(lambda k: scenes.sample_scene(k, cfg)))
    scene = jax.tree.map(np.asarray, sample(keys))
    same = jax.tree.map(lambda a, b: a[:NUM], scene, sampled["train"])
    for name in ("on", "variant", "pose", "velocity", "ego", "sensor_height", "reflectivity"):
        np.testing.assert_array_equal(getattr(same, name), getattr(sampled["train"], name))
    np.testing.assert_array_equal(sampled["train"].sensor_rpy, 0.0)  # the default: level
    np.testing.assert_array_equal(scene.sensor_rpy[:, 2], 30.0)  # yaw is not jittered
    offset = scene.sensor_rpy[:, :2] - [0.0, 10.0]
    radius = np.linalg.norm(offset, axis=1)
    assert radius.max() <= 8.0 + 1e-4 and radius.max() > 7.5
    # Uniform over the disk: P(r < R/2) = 1/4, each quadrant 1/4 (binomial sd ~0.022).
    assert abs((radius < 4.0).mean() - 0.25) < 0.07
    quadrant = (offset[:, 0] > 0) * 2 + (offset[:, 1] > 0)
    np.testing.assert_allclose(np.bincount(quadrant, minlength=4) / n, 0.25, atol=0.07)
    with pytest.raises(ConfigError, match=r"'sim.sensor_tilt_jitter': expected degrees in"):
        SimConfig(sensor_tilt_jitter=-1.0)


def test_a_lidar_at_the_ceiling_is_refused():
    """A ceiling mount above the lowest ceiling (corridors, 2.5 m) gave frames without
    targets, unannounced; in halls alone (3.2 m up) it is below every ceiling."""
    high = dataclasses.replace(CFG.sim, sensor_height=(2.75, 2.75), sensor_rpy=(180.0, 0.0, 0.0))
    with pytest.raises(ValueError, match=r"sim.sensor_height: up to 2.75 m reaches the ceiling: "
                       r"the lowest ceilings \(corridor rooms\) are 2.5 m"):  # fmt: skip
        generate.sample_scenes(jax.random.key(0), dataclasses.replace(CFG, sim=high), 2)
    halls = dataclasses.replace(high, layouts=("hall",), test_layouts=("hall/7",))
    scene = generate.sample_scenes(jax.random.key(0), dataclasses.replace(CFG, sim=halls), 8)
    assert (np.asarray(scene.sensor_height) < np.asarray(scene.room.ceiling) - 0.1).all()
