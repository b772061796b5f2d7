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


@pytest.fixture(scope="module")
def long_sampled():
    """64 train scenes of 20-frame (2 s) sequences: paths long enough to leave a room or
    run into an object when their end is not checked."""
    cfg = dataclasses.replace(CFG, sim=dataclasses.replace(CFG.sim, frames_per_sequence=20))
    return jax.tree.map(np.asarray, generate.sample_scenes(jax.random.key(7), cfg, 64, False)), cfg


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


def test_placement_is_collision_free_inside_the_room_over_the_sequence(sampled, long_sampled):
    """No two objects, nor an object and the lidar robot, come closer than the clearance in
    any frame: on the default 2-frame sequences and at each frame of 2 s ones (the lidar
    robot's reserved path ending at its start passed the 2-frame check: a mutation audit)."""
    long_scenes, long_cfg = long_sampled
    cases = [(scene, CFG) for scene in sampled.values()] + [(long_scenes, long_cfg)]
    placed = 0
    for scene, cfg in cases:
        times = np.arange(cfg.sim.frames_per_sequence) * cfg.sim.frame_dt
        for b in range(len(scene.on)):
            hx, hy = scene.room.size[b] / 2
            room = shapely.box(-hx, -hy, hx, hy)
            for time in times:
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
    # No split allows a variant index past its class's variants (it would name another
    # class's variant in variant_ids), and no scene draws one.
    counts = np.array([len(c.variants) for c in objects.CLASSES])
    past = np.arange(scenes.allowed_variants(CFG.sim, "train").shape[1]) >= counts[:, None]
    for split in ("train", "val", "test"):
        assert not scenes.allowed_variants(CFG.sim, split)[past].any(), split
    for scene in sampled.values():
        assert (scene.variant < counts[tpl.slot_class]).all()


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
    # A batch of no frames failed deep in the cast (ZeroDivisionError), -1 inside MLIR.
    for size in (0, -1):
        with pytest.raises(
            ValueError, match=rf"batch_size: expected a whole number > 0, got {size}"
        ):
            generate.generate_batch_with_info(jax.random.key(3), CFG, "train", size)
    with pytest.raises(ValueError, match=r"num_scenes: expected a whole number > 0, got 0"):
        generate.generate_sequences(jax.random.key(3), CFG, 0)


def test_sim_config_validation_names_fields():
    with pytest.raises(ConfigError, match="sim.test_layouts"):
        SimConfig(test_layouts=("office/99",))
    with pytest.raises(ConfigError, match="sim.slots_per_class"):
        SimConfig(slots_per_class=(1, 2))
    with pytest.raises(ConfigError, match="sim.num_rays"):
        SimConfig(pattern="os128", num_rays=1000)
    with pytest.raises(ConfigError, match=r"'sim.num_rays': at most 4,194,304 rays .* 4,194,308"):
        SimConfig(num_rays=(1 << 22) + 4)
    assert SimConfig(num_rays=1 << 22).num_rays == 4_194_304
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


def _rotation(yaw, pitch):
    """Rz(yaw) @ Ry(pitch) (a primitive's orientation, ``objects.prim_axis``), float64."""
    cz, sz, cy, sy = np.cos(yaw), np.sin(yaw), np.cos(pitch), np.sin(pitch)
    rz = np.array([[cz, -sz, 0.0], [sz, cz, 0.0], [0.0, 0.0, 1.0]])
    return rz @ np.array([[cy, 0.0, sy], [0.0, 1.0, 0.0], [-sy, 0.0, cy]])


def _support(kind, size, yaw, pitch):
    """Half extents along x, y, z of a primitive of MuJoCo size ``size`` rotated by R: the
    support of the rotated solid along each axis (box: |R| half sides, ellipsoid: norm of
    each row of R diag(radii), sphere: radius, cylinder/capsule: axis R e_z times the half
    length plus the disc's or the ball's reach)."""
    rot = _rotation(yaw, pitch)
    size = np.asarray(size, np.float64)
    r, hl, axis = size[0], size[1], np.abs(rot[:, 2])
    if kind == "box":
        return np.abs(rot) @ size
    if kind == "ellipsoid":
        return np.linalg.norm(rot * size[None, :], axis=1)
    if kind == "sphere":
        return np.full(3, r)
    if kind == "capsule":
        return axis * hl + r
    return axis * hl + r * np.sqrt(np.clip(1 - axis**2, 0.0, 1.0))  # cyl, hcyl


def test_labelled_dims_are_the_tight_box_of_the_rescaled_primitives(sampled):
    """A scene rescales each bank object by up to +-5 %: its dims (the label's l, w, h) are
    the tight box around its primitives as placed, computed here from each primitive's own
    shape, and the object frame stays centred in x, y with its bottom at z = 0. Dims left
    unscaled passed every test (a mutation audit: up to 9 cm off)."""
    tpl = scenes.template_for(CFG)
    checked = 0
    for scene in sampled.values():
        p = scene.prims  # [NUM, S, P, ...]
        for b, s in np.ndindex(*scene.on.shape):
            kinds = objects.CLASSES[tpl.slot_class[s]].prims
            on = p.on[b, s, : len(kinds)]
            assert not p.on[b, s, len(kinds) :].any()
            half = np.stack([_support(k, p.size[b, s, i], p.yaw[b, s, i], p.pitch[b, s, i])
                             for i, k in enumerate(kinds) if on[i]])  # fmt: skip
            pos = p.pos[b, s, : len(kinds)][on].astype(np.float64)
            lo, hi = (pos - half).min(0), (pos + half).max(0)
            np.testing.assert_allclose(hi - lo, p.dims[b, s], atol=2e-5, err_msg=(b, s))
            np.testing.assert_allclose([lo[0] + hi[0], lo[1] + hi[1], lo[2]], 0, atol=2e-5)
            checked += scene.on[b, s]
    assert checked > NUM


def test_bank_objects_are_rescaled_by_up_to_5_percent_either_way(sampled):
    """SIMULATOR.md: the generator gathers a bank instance and rescales it by up to +-5 %.
    Each slot's dims are one bank instance of its class and variant times one factor: read
    where exactly one instance has three equal ratios (a person's instances are all scaled
    copies of one); the factors fill both sides of 1. A jitter of +0..5 % only passed every
    test (a mutation audit)."""
    assert scenes.OBJECT_SCALE_JITTER == 0.05
    bank = objects.object_bank(CFG.sim.bank_per_variant)
    tpl = scenes.template_for(CFG)
    factors = []
    for scene in sampled.values():
        for b, s in np.ndindex(*scene.on.shape):
            ref = np.asarray(bank.dims[tpl.slot_class[s], scene.variant[b, s]])  # [K, 3]
            ratio = scene.prims.dims[b, s] / ref
            uniform = np.ptp(ratio, axis=1) < 1e-4
            assert uniform.any(), (b, s)
            if uniform.sum() == 1:
                factors.append(ratio[uniform][0, 0])
    factors = np.asarray(factors)
    assert len(factors) > 50
    assert factors.min() >= 0.95 - 1e-5 and factors.max() <= 1.05 + 1e-5
    assert factors.min() < 0.97 and factors.max() > 1.03


def test_primitive_half_extents_are_reached_by_mujoco_rays():
    """``objects.prim_half_extents`` of every kind, turned (and tilted, for the kinds that
    tilt), against MuJoCo's own geometry: 40,000 rays cast by ``mj_multiRay`` from the geom's
    centre leave it at surface points, whose extremes the half extents must hold and reach.
    An ellipse's x and y extents swapped (a mutation audit) passed the bank test, which
    uses the same function. The support formulas of the dims test above agree too."""
    import mujoco

    n = 40_000  # directions on a Fibonacci sphere
    k = np.arange(n) + 0.5
    z = 1 - 2 * k / n
    phi = np.pi * (1 + 5**0.5) * k
    dirs = np.stack([np.sqrt(1 - z**2) * np.cos(phi), np.sqrt(1 - z**2) * np.sin(phi), z], 1)
    mj_type = {"box": "box", "ellipsoid": "ellipsoid", "sphere": "sphere", "cyl": "cylinder",
               "hcyl": "cylinder", "capsule": "capsule"}  # fmt: skip
    rng = np.random.default_rng(0)
    for kind in ("box", "ellipsoid", "sphere", "cyl", "hcyl", "capsule"):
        for _ in range(6):
            size = rng.uniform(0.05, 0.5, 3)
            yaw = rng.uniform(-np.pi, np.pi)
            pitch = {"cyl": 0.0, "hcyl": np.pi / 2, "capsule": rng.uniform(-np.pi, np.pi),
                     "sphere": rng.uniform(-np.pi, np.pi)}.get(kind, 0.0)  # fmt: skip
            quat = np.zeros(4)
            mujoco.mju_mat2Quat(quat, _rotation(yaw, pitch).ravel())
            attrs = {"size": size, "quat": quat}
            geom = " ".join(f'{a}="{" ".join(map(repr, v.tolist()))}"' for a, v in attrs.items())
            xml = (f'<mujoco><worldbody><geom type="{mj_type[kind]}" pos="0 0 1" {geom}/>'
                   "</worldbody></mujoco>")  # fmt: skip
            m = mujoco.MjModel.from_xml_string(xml)
            d = mujoco.MjData(m)
            mujoco.mj_forward(m, d)
            dist, hit = np.zeros(n), np.zeros(n, np.int32)
            mujoco.mj_multiRay(m, d, np.array([0.0, 0.0, 1.0]), dirs.ravel(), None, 1, -1,
                               hit, dist, None, n, 10.0)  # fmt: skip
            assert (hit == 0).all()
            reach = np.abs(dirs * dist[:, None]).max(0)  # extremes of the surface points
            half = objects.prim_half_extents(
                (kind,), size[None].astype(np.float32), np.float32([yaw]),
                np.float32([pitch]), np,
            )[0]  # fmt: skip
            assert (half >= reach - 1e-5).all(), (kind, size, yaw, pitch, half, reach)
            assert (half <= reach + 0.01 * size.max()).all(), (kind, size, yaw, pitch, half, reach)
            np.testing.assert_allclose(_support(kind, size, yaw, pitch), half, atol=1e-5)


def test_plan_index_must_be_below_plans_per_layout():
    """'kind/index' names one of plans_per_layout plans: index plans_per_layout is the next
    kind's plan 0 (it was taken as 'lab/0' for 'office/8'; a mutation audit)."""
    for per in (1, 3, 8):
        for k, kind in enumerate(layouts.LAYOUTS):
            assert layouts.plan_id(f"{kind.name}/{per - 1}", per) == k * per + per - 1
            with pytest.raises(ValueError, match=f"index < {per}"):
                layouts.plan_id(f"{kind.name}/{per}", per)


def test_plan_sizes_and_ceilings_stay_in_their_layout_ranges():
    """Every plan's room size_y and ceiling lie in its LayoutKind's ranges (the fixed-geometry
    test checks size_x only: a size_y drawn from size_x passed it; a mutation audit), and
    each range is used, not only its lower end."""
    per = 8
    pids = np.arange(len(layouts.LAYOUTS) * per)
    rooms = jax.tree.map(np.asarray, jax.vmap(lambda p: layouts.make_room(p, per))(pids))
    for k, kind in enumerate(layouts.LAYOUTS):
        mine = slice(k * per, (k + 1) * per)
        for name, got in (
            ("size_x", rooms.size[mine, 0]),
            ("size_y", rooms.size[mine, 1]),
            ("ceiling", rooms.ceiling[mine]),
        ):
            lo, hi = getattr(kind, name)
            assert lo - 1e-5 <= got.min() and got.max() <= hi + 1e-5, (kind.name, name, got)
            assert got.max() - got.min() > 0.1 * (hi - lo), (kind.name, name, got)


@pytest.mark.parametrize("kind", range(len(layouts.LAYOUTS)))
def test_class_counts_span_zero_to_the_full_share_of_slots(kind):
    """``class_counts`` is uniform in 0..round(fill * slots): u = 0 asks for none and the
    largest u below 1 for round(fill * slots) of every class (u * top instead of
    u * (top + 1) never reached the top; a mutation audit)."""
    slots = SimConfig().slots_per_class
    layout = layouts.LAYOUTS[kind]
    top = [round(layout.fill.get(c.name, 0.0) * n) for c, n in zip(objects.CLASSES, slots,
                                                                    strict=True)]  # fmt: skip
    below_one = np.nextafter(np.float32(1), np.float32(0))
    for u, want in ((0.0, [0] * len(top)), (below_one, top)):
        got = layouts.class_counts(np.full(objects.NUM_CLASSES, u, np.float32), kind, slots)
        np.testing.assert_array_equal(got, want, err_msg=f"u = {u}")
    # And each count in between is drawn for its share of u.
    t = top[objects.CLASS_INDEX["Chair"]]
    u = (np.arange(t + 1) + 0.5) / (t + 1)
    got = [int(layouts.class_counts(np.full(objects.NUM_CLASSES, v, np.float32), kind, slots)
               [objects.CLASS_INDEX["Chair"]]) for v in u]  # fmt: skip
    assert got == list(range(t + 1))


def test_max_scene_objects_caps_the_objects_placed():
    """No scene places more than min(sim.max_scene_objects, data.max_objects) objects, and
    with a cap below what the layouts ask for the cap is reached (``placed <= cap`` put one
    object too many in a scene, passing every test; a mutation audit)."""
    sim = dataclasses.replace(CFG.sim, max_scene_objects=3)
    cap = min(sim.max_scene_objects, CFG.data.max_objects)
    assert cap == 3
    scene = generate.sample_scenes(jax.random.key(0), dataclasses.replace(CFG, sim=sim), 16)
    placed = np.asarray(scene.on).sum(-1)
    assert placed.max() == cap, placed


def test_a_lidar_within_its_clearance_of_the_ceiling_is_refused():
    """``check_sensor_height`` keeps the lidar ``CEILING_CLEARANCE`` below the lowest ceiling
    (its docstring): a height between the ceiling less the clearance and the ceiling itself
    is refused, one just below that margin is accepted (only heights above the ceiling were
    tested; the margin dropped passed; a mutation audit). The blind zone plays no part: a
    0.6 m gap with sim.min_range 0.8 was refused as "reaches the ceiling" (helper-107)."""
    lowest = min(layouts.LAYOUTS[layouts.LAYOUT_INDEX[k]].ceiling[0] for k in CFG.sim.layouts)
    assert lowest == 2.5  # corridors
    m = scenes.CEILING_CLEARANCE
    near = round(lowest - m / 2, 6)
    with pytest.raises(ValueError, match=f"sim.sensor_height: up to {near} m reaches the ceiling"):
        scenes.check_sensor_height(dataclasses.replace(CFG.sim, sensor_height=(near, near)))
    ok = round(lowest - 1.5 * m, 6)
    scenes.check_sensor_height(dataclasses.replace(CFG.sim, sensor_height=(ok, ok)))
    # Exactly the clearance under the ceiling is allowed, as the message says ("at or below").
    edge = lowest - m
    scenes.check_sensor_height(dataclasses.replace(CFG.sim, sensor_height=(edge, edge)))
    with pytest.raises(ValueError, match=f"must stay at or below {edge:.2f} m"):
        scenes.check_sensor_height(dataclasses.replace(CFG.sim, sensor_height=(near, near)))
    blind = dataclasses.replace(CFG.sim, sensor_height=(1.6, 1.9), min_range=0.8)
    scenes.check_sensor_height(blind)


def _all_rooms(per):
    """Every plan's Room (numpy), plans_per_layout = per, and each plan's LayoutKind."""
    pids = np.arange(len(layouts.LAYOUTS) * per)
    rooms = jax.tree.map(np.asarray, jax.vmap(lambda p: layouts.make_room(p, per))(pids))
    return rooms, [layouts.LAYOUTS[p // per] for p in pids]


def test_walls_close_the_room_around_its_door_gaps():
    """The 8 wall boxes of every plan cover exactly the ring of thickness WALL_THICKNESS
    around the interior (size_x x size_y, centred on the origin; the module docstring),
    corners included, less each wall's door gap [door_lo, door_hi]; floor to ceiling. A wall
    moved into the room or corners left open (a mutation audit) passed every test."""
    rooms, _ = _all_rooms(8)
    th = layouts.WALL_THICKNESS
    checked_doors = 0
    for i in range(len(rooms.plan)):
        room = jax.tree.map(lambda a, i=i: a[i], rooms)
        centre, half = map(np.asarray, layouts.wall_boxes(room))
        hx, hy = np.float64(room.size) / 2
        ring = shapely.box(-hx - th, -hy - th, hx + th, hy + th) - shapely.box(-hx, -hy, hx, hy)
        lo, hi = np.float64(room.door_lo), np.float64(room.door_hi)
        doors = [
            shapely.box(lo[0], -hy - th, hi[0], -hy),  # wall 0: -y
            shapely.box(lo[1], hy, hi[1], hy + th),  # wall 1: +y
            shapely.box(-hx - th, lo[2], -hx, hi[2]),  # wall 2: -x
            shapely.box(hx, lo[3], hx + th, hi[3]),  # wall 3: +x
        ]
        want = ring.difference(shapely.union_all([d for d in doors if d.area > 0]))
        boxes = [shapely.box(*(c[:2] - h[:2]), *(c[:2] + h[:2]))
                 for c, h in zip(centre.astype(np.float64), half.astype(np.float64), strict=True)
                 if (h[:2] > 0).all()]  # fmt: skip
        got = shapely.union_all(boxes)
        assert want.symmetric_difference(got).area < 1e-4, (i, want.symmetric_difference(got))
        np.testing.assert_allclose(centre[:, 2] - half[:, 2], 0.0, atol=1e-6)
        np.testing.assert_allclose(centre[:, 2] + half[:, 2], room.ceiling, rtol=1e-6)
        checked_doors += (hi > lo).sum()
    assert checked_doors > 0


def test_door_gaps_lie_inside_their_walls_and_follow_door_prob():
    """A door gap [door_lo, door_hi] keeps at least 0.3 m of wall at each end (make_room
    draws its centre so), and the share of walls with a door is the kind's ``door_prob``
    (64 plans of each kind: 256 walls, binomial sd <= 0.032). Gaps running past the wall's
    end and the door test inverted (a mutation audit) passed every test."""
    rooms, kinds = _all_rooms(64)
    wall_len = rooms.size[:, [0, 0, 1, 1]]
    door = rooms.door_hi > rooms.door_lo
    assert ((rooms.door_lo == 0) & (rooms.door_hi == 0))[~door].all()
    end = np.maximum(np.abs(rooms.door_lo), np.abs(rooms.door_hi))
    assert (end[door] <= wall_len[door] / 2 - 0.3 + 1e-5).all()
    for kind in layouts.LAYOUTS:
        share = door[[i for i, kd in enumerate(kinds) if kd is kind]].mean()
        assert abs(share - kind.door_prob) < 0.15, (kind.name, share, kind.door_prob)


def test_room_size_x_and_y_are_independent_draws():
    """Each plan's size_x, size_y and ceiling are drawn independently in their ranges: over
    256 plans their normalised positions in the ranges are uncorrelated and never equal (one
    draw for two of them, a mutation audit, passed the range tests)."""
    rooms, kinds = _all_rooms(64)
    fx = np.array([(s[0] - k.size_x[0]) / (k.size_x[1] - k.size_x[0])
                   for s, k in zip(rooms.size, kinds, strict=True)])  # fmt: skip
    fy = np.array([(s[1] - k.size_y[0]) / (k.size_y[1] - k.size_y[0])
                   for s, k in zip(rooms.size, kinds, strict=True)])  # fmt: skip
    fc = np.array([(c - k.ceiling[0]) / (k.ceiling[1] - k.ceiling[0])
                   for c, k in zip(rooms.ceiling, kinds, strict=True)])  # fmt: skip
    for a, b in ((fx, fy), (fx, fc), (fy, fc)):  # the ceiling is a draw of its own too
        assert not np.isclose(a, b, atol=1e-5).any()
        assert abs(np.corrcoef(a, b)[0, 1]) < 0.3


def test_bank_objects_follow_the_documented_sizes_and_facing():
    """The object library's rules (SIMULATOR.md table, objects.py): standing persons are
    1.55-1.95 m tall, range used; the object frame's -y side is its back, the side a
    wall-bound object turns to the wall (``ClassSpec.wall_prob``): the sofa's back rest
    lies on -y and the cabinet's handle on its front, +y; a person's torso ellipsoid is
    wider across the shoulders (y, where the arms hang) than deep (x, the way it faces).
    Persons up to 2.15 m, the sofa back or the cabinet handle on the other side and the
    torso turned by 90 degrees each passed every test (a mutation audit)."""
    bank = objects.object_bank()
    person = objects.CLASS_INDEX["Person"]
    standing = bank.dims[person, objects.CLASSES[person].variants.index("standing"), :, 2]
    assert standing.min() >= 1.55 - 1e-4 and standing.max() <= 1.95 + 1e-4
    assert standing.min() < 1.6 and standing.max() > 1.9
    # Person primitives: legs 0-1, torso 2 (ellipsoid semi-axes x, y, z).
    assert objects.CLASSES[person].prims[2] == "ellipsoid"
    torso = bank.size[person, :, :, 2]  # [V, N, 3]
    assert (torso[..., 1] > torso[..., 0]).all()
    sofa = objects.CLASS_INDEX["Sofa"]  # prims: base 0, back 1
    back_y, base_y = bank.pos[sofa, :2, :, 1, 1], bank.pos[sofa, :2, :, 0, 1]
    assert (back_y < base_y).all() and (back_y < 0).all()
    cab = objects.CLASS_INDEX["Cabinet"]  # prims: body 0, handle 1, all 3 variants
    assert (bank.pos[cab, :3, :, 1, 1] > 0).all()
    assert (bank.pos[cab, :3, :, 1, 1] > bank.pos[cab, :3, :, 0, 1]).all()  # before the body
    # The bookshelf's back panel (prim 2 of variant 0; the low shelf has none) on -y too:
    # on +y, a wall-bound bookshelf stood open side to the wall (passed before).
    shelf = objects.CLASS_INDEX["Shelf"]
    bookshelf = objects.CLASSES[shelf].variants.index("bookshelf")
    assert objects.CLASSES[shelf].prims[2] == "box"
    assert (bank.pos[shelf, bookshelf, :, 2, 1] < 0).all()
    # A robot drives along its x (scenes.py: velocity (cos yaw, sin yaw) x speed): the boxy
    # robot's wheels (prims 5, 6) turn about y. One wheel turned by 90 degrees passed.
    robot = objects.CLASS_INDEX["Robot"]
    boxy = objects.CLASSES[robot].variants.index("boxy")
    assert objects.CLASSES[robot].prims[5:] == ("hcyl", "hcyl")
    wheels = objects.prim_axis(bank.yaw[robot, boxy, :, 5:7], bank.pitch[robot, boxy, :, 5:7], np)
    np.testing.assert_allclose(np.abs(wheels[..., 1]), 1.0, atol=1e-6)


def test_door_widths_are_in_the_documented_range():
    """ "Each wall has a door gap (0.9-1.6 m)" (SIMULATOR.md, Layouts): every door of 256
    plans is 0.9-1.6 m wide and the range is used. Doors of 0.5-1.2 m (a mutation audit)
    passed every test."""
    rooms, _ = _all_rooms(64)
    width = rooms.door_hi - rooms.door_lo
    door = width > 0
    assert door.sum() > 100
    assert width[door].min() >= 0.9 - 1e-5 and width[door].max() <= 1.6 + 1e-5
    assert width[door].min() < 1.0 and width[door].max() > 1.5


def test_ceiling_slab_sits_on_the_walls_at_the_room_ceiling(sampled):
    """The ceiling slab's underside is the room's ceiling height, which is where the walls
    end (``wall_boxes``: floor to ceiling); a slab 10 cm low, cutting the walls and the
    room's height short, passed every test (a mutation audit)."""
    tpl = scenes.template_for(CFG)
    for b in range(3):
        one = jax.tree.map(lambda x, b=b: x[b], sampled["train"])
        size, xpos, _, _ = (np.asarray(a) for a in scenes.geom_state(tpl, one, 0.0))
        ceiling = float(one.room.ceiling)
        assert xpos[scenes.CEILING, 2] - size[scenes.CEILING, 2] == pytest.approx(ceiling, abs=1e-5)
        centre, half = (np.asarray(a) for a in layouts.wall_boxes(one.room))
        np.testing.assert_allclose(centre[:, 2] + half[:, 2], ceiling, rtol=1e-6)


def test_scenes_place_at_most_the_class_counts_and_turn_their_backs_to_walls(sampled):
    """Per scene and class, at most round(fill x slots) objects (SIMULATOR.md: "uniform
    0..round(fill x slots)", so no Sofa in labs), and every object placed against a wall
    ("back to it, 3-12 cm gap", Placement) has its -y side (its back, objects.py) facing
    that wall: the back edge's midpoint within the gap of the nearest wall, the back's
    outward direction that wall's normal. One object more per class, and wall-bound
    objects facing the wall, each passed every test (a mutation audit)."""
    tpl = scenes.template_for(CFG)
    slots = CFG.sim.slots_per_class
    lo_gap, hi_gap = scenes.WALL_GAP
    at_wall, walls = 0, set()
    for scene in sampled.values():
        for b in range(NUM):
            kind = layouts.LAYOUTS[int(scene.room.kind[b])]
            for c, spec in enumerate(objects.CLASSES):
                top = int(np.round(kind.fill.get(spec.name, 0.0) * slots[c]))
                assert scene.on[b][tpl.slot_class == c].sum() <= top, (kind.name, spec.name)
            hx, hy = scene.room.size[b] / 2
            for s in np.flatnonzero(scene.on[b]):
                x, y, yaw = scene.pose[b, s].astype(np.float64)
                length, width = scene.prims.dims[b, s, :2].astype(np.float64)
                back = np.array([np.sin(yaw), -np.cos(yaw)])  # the object's -y, in the world
                front = np.array([x, y]) - back * width / 2
                fgaps = [front[1] + hy, hy - front[1], front[0] + hx, hx - front[0]]
                # Free objects with a random yaw: only those turned square to the walls and
                # touching one with their front would be wall placements facing the wall.
                square = abs(np.sin(2 * yaw)) < 1e-4
                assert not (square and min(fgaps) <= hi_gap + 0.02), (b, s, yaw, fgaps)
                mid = np.array([x, y]) + back * width / 2
                gaps = [mid[1] + hy, hy - mid[1], mid[0] + hx, hx - mid[0]]
                k = int(np.argmin(gaps))
                if gaps[k] > hi_gap + 0.005 or not square:  # a free object near a wall
                    continue
                at_wall += 1
                walls.add(k)
                assert gaps[k] >= lo_gap - 0.005, (b, s, gaps)
                normal = np.array([[0, -1], [0, 1], [-1, 0], [1, 0]][k])
                assert back @ normal > 0.999, (b, s, yaw, k)
    assert at_wall > 10
    assert walls == {0, 1, 2, 3}  # -y, +y, -x, +x: each wall gets objects


def test_the_lidar_robot_keeps_its_wall_margin_over_the_sequence(sampled, long_sampled):
    """The lidar robot drives "a straight path inside the room" (scenes.py), its centre at
    least 0.6 m from every wall at the first and at the last frame (the margin scenes.py
    draws the start in and checks the end against). Checked on the default 2-frame
    sequences and on 20-frame ones (2 s, where a path not checked at its end leaves the
    room). A start drawn over the whole room,
    and an end never checked, each passed every test (a mutation audit)."""
    long_scenes, long_cfg = long_sampled
    cases = [(s, CFG) for s in sampled.values()] + [(long_scenes, long_cfg)]
    for scene, cfg in cases:
        span = (cfg.sim.frames_per_sequence - 1) * cfg.sim.frame_dt
        margin = scene.room.size / 2 - 0.6
        for t in (0.0, span):
            xy = scene.ego[:, :2] + scene.ego_velocity * t
            assert (np.abs(xy) <= margin + 1e-5).all(), (t, (margin - np.abs(xy)).min())
    assert (np.linalg.norm(long_scenes.ego_velocity, axis=-1) > 0).mean() > 0.5  # they drive


def test_sensor_height_is_drawn_independently_of_the_plan(sampled):
    """The lidar's height is a draw of its own in sim.sensor_height (SimConfig), not a
    function of the room: scenes of one plan get heights spread over the range. A height
    taken from the plan's draw (every scene of a plan at nearly one height) passed every
    test (a mutation audit)."""
    lo, hi = CFG.sim.sensor_height
    scene = sampled["test"]  # 4 held-out plans: several scenes each
    spreads = [np.ptp(scene.sensor_height[scene.room.plan == p])
               for p in np.unique(scene.room.plan)]  # fmt: skip
    assert max(spreads) > 0.3 * (hi - lo), spreads
    h = sampled["train"].sensor_height
    assert h.min() >= lo - 1e-6 and h.max() <= hi + 1e-6


def test_to_mjx_gives_the_real_mjx_scene_the_generator_casts_against(sampled):
    """DESIGN 10's "batched MJX model/data": ``scenes.to_mjx`` builds real ``mjx.Model`` /
    ``mjx.Data`` from posed scenes, which no test called; the generator casts against a
    lighter view with MJX's field names (docs/SIMULATOR.md). Both must cast every ray of a
    frame alike: the same distances and geom ids."""
    from indoorbev_sim import lidar

    scene = jax.tree.map(lambda a: a[:2], sampled["train"])  # two scenes, frame 0
    time = np.zeros(2, np.float32)
    tpl = scenes.template_for(CFG)
    size, xpos, xmat, _ = jax.vmap(lambda s, t: scenes.geom_state(tpl, s, t))(scene, time)
    origin, _ = jax.vmap(scenes.sensor_pose)(scene, time)
    dirs = generate.make_pattern(CFG.sim).frame(0).directions
    view = scenes.geom_model(tpl, size), scenes.GeomData(geom_xpos=xpos, geom_xmat=xmat)
    model, data = scenes.to_mjx(tpl, size, xpos, xmat)
    assert model.geom_size.shape == size.shape and data.geom_xpos.shape == xpos.shape
    dist_view, geom_view = lidar.cast_rays(*view, origin, dirs, CFG.sim.max_range)
    dist_mjx, geom_mjx = lidar.cast_rays(model, data, origin, dirs, CFG.sim.max_range)
    assert (np.asarray(geom_view) >= 0).sum() > dirs.shape[0]  # the rooms are hit
    np.testing.assert_array_equal(np.asarray(dist_mjx), np.asarray(dist_view))
    np.testing.assert_array_equal(np.asarray(geom_mjx), np.asarray(geom_view))
