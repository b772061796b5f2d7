"""Augmentations: points, boxes and footprints move together; invariants of each step."""

import dataclasses

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from scipy import ndimage

from indoorbev_jax import augment as aug
from indoorbev_jax.config import AugmentConfig, Config
from indoorbev_jax.data.dataset import make_targets
from indoorbev_jax.data.kitti import ObjectLabels
from indoorbev_jax.data.rasterize import instance_ids_from_masks
from indoorbev_jax.geometry import cell_index
from indoorbev_jax.types import Batch

CFG = Config.tiny()
GRID = CFG.grid
OFF = AugmentConfig(
    flip_prob=0.0, rotation=0.0, scale_range=(1.0, 1.0), jitter_std=0.0, point_drop_prob=0.0,
    range_dropout_prob=0.0, noise_points=0.0, shuffle_points=False, box_noise_prob=0.0,
    mask_perturb_prob=0.0,
)  # fmt: skip


def make_frame(seed=0):
    rng = np.random.default_rng(seed)
    labels = ObjectLabels(
        classes=[0, 1, 6],
        dims=[[1.6, 0.8, 0.75], [0.5, 0.5, 0.9], [0.5, 0.4, 1.7]],
        pos=[[1.5, 1.0, 0.375], [-2.0, -1.5, 0.45], [0.0, 3.0, 0.85]],
        yaw=[0.4, -1.0, 2.0],
        occlusion=[0, 0, 0],
    )
    pts = []
    for k in range(3):
        local = rng.uniform(-0.45, 0.45, (150, 3)) * labels.dims[k]
        c, s = np.cos(labels.yaw[k]), np.sin(labels.yaw[k])
        xy = local[:, :2] @ np.array([[c, s], [-s, c]]) + labels.pos[k, :2]
        pts.append(np.column_stack([xy, local[:, 2] + labels.pos[k, 2], rng.random(150)]))
    floor = np.column_stack([rng.uniform(-4.5, 4.5, (300, 2)), np.zeros(300), rng.random(300)])
    pts = np.concatenate(pts + [floor]).astype(np.float32)
    points = np.zeros((CFG.data.max_points, 4), np.float32)
    points[: len(pts)] = pts
    valid = np.arange(CFG.data.max_points) < len(pts)
    targets = make_targets(labels, GRID, CFG.data.max_objects)
    return jax.tree.map(jnp.asarray, Batch(points=points, point_valid=valid, targets=targets))


def membership(frame):
    t = frame.targets
    return np.asarray(aug.points_in_boxes(frame.points, t.pos, t.dims, t.yaw, t.valid, 1e-3))


def check_consistent(frame):
    t = frame.targets
    np.testing.assert_array_equal(t.instance_ids, instance_ids_from_masks(t.masks, t.valid))
    pts = np.asarray(frame.points)
    assert (pts[~np.asarray(frame.point_valid)] == 0).all()


def test_mirror_flips_rows_exactly():
    frame = make_frame()
    out = aug.global_transform(
        jax.random.key(0), frame, GRID, dataclasses.replace(OFF, flip_prob=1.0)
    )
    np.testing.assert_array_equal(out.targets.masks, frame.targets.masks[:, ::-1, :])
    np.testing.assert_allclose(out.points[:, 1], -frame.points[:, 1])
    # The heading vector is mirrored too: (cos, sin) -> (cos, -sin). A mutation audit:
    # pi - yaw (the same outline, the opposite heading, which the yaw loss tells apart)
    # passed.
    v = np.asarray(frame.targets.valid)
    yaw, mirrored = np.asarray(frame.targets.yaw)[v], np.asarray(out.targets.yaw)[v]
    np.testing.assert_allclose(np.cos(mirrored), np.cos(yaw), atol=1e-6)
    np.testing.assert_allclose(np.sin(mirrored), -np.sin(yaw), atol=1e-6)
    check_consistent(out)


@pytest.mark.parametrize("quarter", [1, 2, 3])
def test_warp_by_quarter_turns_equals_rot90(quarter):
    masks = make_frame().targets.masks
    theta = quarter * np.pi / 2
    c, s = np.cos(theta), np.sin(theta)
    inverse = jnp.asarray([[c, s, 0.0], [-s, c, 0.0]], jnp.float32)  # R(-theta)
    out = aug.warp_masks(masks, jnp.broadcast_to(inverse, (masks.shape[0], 2, 3)), GRID)
    # Rows grow with y and columns with x, so a counter-clockwise turn is rot90 on (W, H) axes.
    np.testing.assert_array_equal(out, np.rot90(np.asarray(masks), k=quarter, axes=(2, 1)))


def test_global_transform_keeps_points_in_their_boxes():
    frame = make_frame()
    cfg = dataclasses.replace(OFF, flip_prob=0.5, rotation=np.pi, scale_range=(0.9, 1.1))
    before = membership(frame)
    for seed in range(5):
        out = jax.jit(aug.global_transform, static_argnums=(2, 3))(
            jax.random.key(seed), frame, GRID, cfg
        )
        np.testing.assert_array_equal(membership(out)[:, :600], before[:, :600])
        # Nearest-cell resampling: every footprint cell lies within half a (scaled) cell
        # diagonal of the transformed box, and the footprint survives.
        t = out.targets
        xs, ys = np.meshgrid(*(np.asarray(c) for c in aug.cell_centers(GRID)))
        cells = jnp.asarray(np.stack([xs.ravel(), ys.ravel(), np.zeros(xs.size)], 1))
        flat_dims = t.dims.at[:, 2].set(1.0)
        near = aug.points_in_boxes(cells, t.pos.at[:, 2].set(0), flat_dims, t.yaw, t.valid, 0.2)
        masks = np.asarray(t.masks).reshape(t.masks.shape[0], -1)
        assert not (masks & ~np.asarray(near)).any()
        assert masks[:3].any(1).all()
        check_consistent(out)


def test_a_pure_scale_is_exact_on_points_and_boxes():
    """No flip, no turn, scale 1.25: x, y, z of points and boxes and the box sizes all grow
    by 1.25 and yaw stays. A scale left off z passed every test before (points stayed
    inside their margin-padded boxes; a mutation audit)."""
    frame = make_frame()
    cfg = dataclasses.replace(OFF, flip_prob=0.0, rotation=0.0, scale_range=(1.25, 1.25))
    out = aug.global_transform(jax.random.key(0), frame, GRID, cfg)
    kept = np.asarray(frame.point_valid) & np.asarray(out.point_valid)
    assert kept.sum() > 100
    np.testing.assert_allclose(np.asarray(out.points)[kept],
                               np.asarray(frame.points)[kept] * [1.25, 1.25, 1.25, 1.0],
                               rtol=1e-6, atol=1e-6)  # fmt: skip
    t, t0 = out.targets, frame.targets
    v = np.asarray(t0.valid)
    np.testing.assert_allclose(np.asarray(t.pos)[v], np.asarray(t0.pos)[v] * 1.25, rtol=1e-6)
    np.testing.assert_allclose(np.asarray(t.dims)[v], np.asarray(t0.dims)[v] * 1.25, rtol=1e-6)
    np.testing.assert_allclose(np.asarray(t.yaw)[v], np.asarray(t0.yaw)[v], atol=1e-6)


def test_box_noise_moves_points_with_boxes_without_new_overlap():
    frame = make_frame()
    cfg = dataclasses.replace(OFF, box_noise_prob=1.0, box_translation_std=0.3, box_yaw_std=0.3)
    before = membership(frame)
    out = aug.box_noise(jax.random.key(1), frame, GRID, cfg)
    assert not np.allclose(out.targets.pos, frame.targets.pos)
    np.testing.assert_array_equal(membership(out)[:, :450], before[:, :450])
    overlap = np.asarray(out.targets.masks.sum(0) > 1).sum()
    assert overlap <= np.asarray(frame.targets.masks.sum(0) > 1).sum()
    check_consistent(out)


def test_box_noise_moves_each_footprint_with_its_box():
    """Each moved footprint is the old one under the box's own move, read back from the
    targets (shift = the centre's change, turn = the yaw's, scale = the sizes' ratio) and
    resampled here in numpy. A footprint turned or shifted the other way passed before."""
    frame = make_frame()
    t0 = frame.targets
    cfg = dataclasses.replace(OFF, box_noise_prob=1.0, box_translation_std=0.3,
                              box_yaw_std=0.5, box_scale_std=0.1)  # fmt: skip
    h, w = GRID.shape
    cols, rows = np.meshgrid(np.arange(w), np.arange(h))
    px = GRID.x_range[0] + (cols + 0.5) * GRID.cell_size  # destination cell centres
    py = GRID.y_range[0] + (rows + 0.5) * GRID.cell_size
    moved = 0
    for seed in range(6):
        t = aug.box_noise(jax.random.key(seed), frame, GRID, cfg).targets
        for k in np.flatnonzero(np.asarray(t0.valid)):
            c, new_c = np.asarray(t0.pos[k, :2], np.float64), np.asarray(t.pos[k, :2], np.float64)
            turn = float(t.yaw[k] - t0.yaw[k])
            scale = float(t.dims[k, 0] / t0.dims[k, 0])
            moved += not np.allclose(new_c, c)
            cos, sin = np.cos(turn), np.sin(turn)
            dx, dy = px - new_c[0], py - new_c[1]  # source = c + R(-turn) (p - c') / scale
            sx = c[0] + (cos * dx + sin * dy) / scale
            sy = c[1] + (-sin * dx + cos * dy) / scale
            col = np.floor((sx - GRID.x_range[0]) / GRID.cell_size).astype(int)
            row = np.floor((sy - GRID.y_range[0]) / GRID.cell_size).astype(int)
            inside = (col >= 0) & (col < w) & (row >= 0) & (row < h)
            want = np.where(inside, np.asarray(t0.masks[k])[row.clip(0, h - 1), col.clip(0, w - 1)],
                            False)  # fmt: skip
            got = np.asarray(t.masks[k])
            # float32 against float64: a cell centre mapped onto a source cell's edge may go
            # either way; a wrong turn or shift moves a whole object's worth of cells.
            assert (got != want).sum() <= 2, (seed, k, (got != want).sum(), want.sum())
    assert moved >= 6  # the check saw moved boxes, not only kept ones


def test_point_noise_only_fills_free_slots_and_stays_in_workspace():
    frame = make_frame()
    n_valid = int(frame.point_valid.sum())
    cfg = dataclasses.replace(OFF, noise_points=0.05, jitter_std=0.01)
    out = aug.point_noise(jax.random.key(2), frame, GRID, cfg)
    assert bool(out.point_valid[:n_valid].all())  # real points are never overwritten
    assert np.abs(out.points[:n_valid, :3] - frame.points[:n_valid, :3]).max() < 0.1
    assert int(out.point_valid[n_valid:].sum()) == round(0.05 * CFG.data.max_points)
    p = np.asarray(out.points)[np.asarray(out.point_valid)]
    assert (np.abs(p[:, :2]) < 5).all()
    check_consistent(out)
    dropped = aug.point_noise(
        jax.random.key(3), frame, GRID, dataclasses.replace(OFF, point_drop_prob=0.1)
    )
    kept = int(dropped.point_valid.sum())
    assert 0.8 * n_valid < kept < n_valid
    np.testing.assert_array_equal(
        dropped.points[dropped.point_valid], frame.points[dropped.point_valid]
    )


def test_intensity_dropout_zeroes_whole_frames_and_leaves_the_rest():
    frame = make_frame()
    keys = jax.random.split(jax.random.key(4), 64)
    base = dataclasses.replace(OFF, point_drop_prob=0.1, jitter_std=0.01, shuffle_points=True)
    run = jax.vmap(lambda k, c: aug.point_noise(k, frame, GRID, c), in_axes=(0, None))
    plain = run(keys, base)
    dropped = run(keys, dataclasses.replace(base, intensity_drop_prob=0.5))
    # Same draws for everything else: validity, order and coordinates are unchanged.
    np.testing.assert_array_equal(dropped.point_valid, plain.point_valid)
    np.testing.assert_array_equal(dropped.points[..., :3], plain.points[..., :3])
    i_plain, i_drop = np.asarray(plain.points[..., 3]), np.asarray(dropped.points[..., 3])
    assert (i_plain > 0).any(axis=1).all()
    zeroed = (i_drop == 0).all(axis=1)
    kept = (i_drop == i_plain).all(axis=1)
    assert (zeroed ^ kept).all()  # a frame loses all of its intensity or none of it
    assert 16 <= zeroed.sum() <= 48  # Binomial(64, 0.5): outside this with p < 1e-4


def test_mask_perturbation_dilates_or_erodes():
    frame = make_frame()
    out = aug.mask_perturbation(
        jax.random.key(3), frame, GRID, dataclasses.replace(OFF, mask_perturb_prob=1.0)
    )
    old, new = np.asarray(frame.targets.masks[:3]), np.asarray(out.targets.masks[:3])
    for o, n in zip(old, new, strict=True):
        square = np.ones((3, 3), bool)
        dilated = ndimage.binary_dilation(o, square)
        eroded = ndimage.binary_erosion(o, square, border_value=1)
        expected = [dilated, eroded if eroded.any() else o]
        assert any((n == e).all() for e in expected)
    check_consistent(out)


def test_gt_sampling_pastes_collision_free_objects_with_their_points():
    frame = make_frame()
    batch = jax.tree.map(lambda a: a[None], frame)
    db = aug.build_object_database(batch, GRID, max_points=64)
    assert db.classes.tolist() == [0, 1, 6]
    # An object cut by the grid's edge stays out of the database.
    masks = batch.targets.masks.at[0, 1, :, 0].set(True)
    cut = batch.replace(targets=batch.targets.replace(masks=masks))
    assert aug.build_object_database(cut, GRID, max_points=64).classes.tolist() == [0, 6]
    assert (np.asarray(db.point_valid).sum(1) == 64).all()
    cfg = dataclasses.replace(OFF, gt_sampling=3, gt_sampling_attempts=8)
    out = aug.gt_sampling(jax.random.key(4), frame, db, GRID, cfg)
    t = out.targets
    added = int(t.valid.sum()) - 3
    assert added >= 1
    masks = np.asarray(t.masks)
    assert (masks.sum(0) <= 1).all()  # no footprint overlaps
    inside = membership(out)
    for k in range(3, 3 + added):
        assert masks[k].any()
        assert inside[k].sum() >= 60  # its pasted points came along
    check_consistent(out)
    # Each pasted footprint lies on its pasted box (the database's are box-shaped here). A
    # patch pasted transposed passed: an oblong object shows it, so the table alone is pasted.
    from indoorbev_jax.data.rasterize import box_masks

    tables = jax.tree.map(lambda x: x[:1], db)  # the database's table alone
    keys = jax.random.split(jax.random.key(5), 32)
    runs = jax.jit(jax.vmap(lambda k: aug.gt_sampling(k, frame, tables, GRID, cfg).targets))(keys)
    pasted = 0
    for seed in range(len(keys)):
        t = jax.tree.map(lambda x, seed=seed: x[seed], runs)
        for k in range(3, int(t.valid.sum())):
            box = jnp.stack([t.pos[k, 0], t.pos[k, 1], t.dims[k, 0], t.dims[k, 1], t.yaw[k]])
            a, b = np.asarray(t.masks[k]), np.asarray(box_masks(box[None], GRID)[0])
            assert (a & b).sum() / (a | b).sum() >= 0.5, (seed, k)
            pasted += 1
    assert pasted >= 3, pasted


def test_full_chain_is_deterministic_and_vmaps():
    batch = jax.tree.map(lambda *a: jnp.stack(a), make_frame(0), make_frame(1))
    run = jax.jit(aug.augment_batch, static_argnums=(2, 3))
    a = run(jax.random.key(7), batch, GRID, CFG.augment)
    b = run(jax.random.key(7), batch, GRID, CFG.augment)
    jax.tree.map(np.testing.assert_array_equal, a, b)
    keys = jax.random.split(jax.random.key(7), 2)
    for i in range(2):
        one = aug.augment(keys[i], jax.tree.map(lambda x, i=i: x[i], batch), GRID, CFG.augment)
        np.testing.assert_allclose(one.points, a.points[i], atol=1e-5)
        np.testing.assert_array_equal(one.targets.masks, a.targets.masks[i])
    # The whole Config for a section failed on an AttributeError of some field.
    with pytest.raises(
        TypeError, match=r"cfg: expected AugmentConfig, got Config; pass config\.augment"
    ):
        aug.augment_batch(jax.random.key(7), batch, GRID, CFG)
    with pytest.raises(
        TypeError, match=r"grid: expected GridConfig, got Config; pass config\.grid"
    ):
        aug.augment_batch(jax.random.key(7), batch, CFG, CFG.augment)


def test_augmentation_is_the_same_under_x64():
    """With ``jax_enable_x64`` on, the draws were float64: another augmentation for the same
    key, and box noise added a float64 shift into float32 boxes (a JAX FutureWarning, an
    error in later JAX releases)."""
    import warnings

    cfg = dataclasses.replace(CFG.augment, box_noise_prob=1.0)
    frame, key = make_frame(0), jax.random.key(11)
    plain = jax.jit(aug.augment, static_argnums=(2, 3))(key, frame, GRID, cfg)
    with jax.enable_x64(True), warnings.catch_warnings():
        warnings.simplefilter("error", FutureWarning)
        x64 = jax.jit(aug.augment, static_argnums=(2, 3))(key, frame, GRID, cfg)
    for a, b in zip(jax.tree.leaves(plain), jax.tree.leaves(x64), strict=True):
        assert a.dtype == b.dtype
        np.testing.assert_array_equal(a, b)


def _move_object_0(frame, shift):
    """``frame`` with object 0 and its points moved by ``shift`` (x, y, z), its targets
    rebuilt from the labels (``make_targets``, as a dataset's)."""
    t, shift = frame.targets, jnp.asarray(shift)
    pts = frame.points
    in_0 = aug.points_in_boxes(pts, t.pos, t.dims, t.yaw, t.valid)[0] & frame.point_valid
    pts = jnp.where(in_0[:, None], pts + jnp.append(shift, 0.0), pts)
    labels = ObjectLabels(classes=np.asarray(t.classes[:3]), dims=np.asarray(t.dims[:3]),
                          pos=np.asarray(t.pos[:3]) + np.stack([shift, 0 * shift, 0 * shift]),
                          yaw=np.asarray(t.yaw[:3]), occlusion=[0, 0, 0])  # fmt: skip
    targets = jax.tree.map(jnp.asarray, make_targets(labels, GRID, t.valid.shape[0]))
    return Batch(points=pts, point_valid=frame.point_valid, targets=targets)


def test_objects_moved_out_of_sight_leave_the_targets():
    """After the chain, every target has its centre in the grid, a footprint and a point;
    a rotation carries the corner object out in some draws, never the central ones."""
    # Object 0 moves to the corner, 6.2 m from the sensor: most rotations take it out.
    frame = _move_object_0(make_frame(), [4.4 - 1.5, 4.4 - 1.0, 0.0])
    cfg = dataclasses.replace(OFF, rotation=float(np.pi))
    keys = jax.random.split(jax.random.key(5), 64)
    out = jax.vmap(lambda k: aug.augment(k, frame, GRID, cfg))(keys)
    valid = np.asarray(out.targets.valid)
    assert valid[:, 1:3].all() and 8 <= (~valid[:, 0]).sum() <= 56
    pos = np.asarray(out.targets.pos)
    inside = (np.abs(pos[..., 0]) <= 5.0) & (np.abs(pos[..., 1]) <= 5.0)
    assert inside[valid].all()
    assert np.asarray(out.targets.masks).any((2, 3))[valid].all()
    seen = jax.vmap(lambda f: aug._object_points(f).any(-1))(out)
    assert np.asarray(seen)[valid].all()
    assert not np.asarray(out.targets.masks)[~valid].any()  # dropped: no footprint left
    check_consistent(jax.tree.map(lambda x: x[0], out))


def test_intensity_drop_is_independent_of_point_drop():
    frame = make_frame()
    cfg = dataclasses.replace(OFF, point_drop_prob=0.05, intensity_drop_prob=0.05)
    keys = jax.random.split(jax.random.key(6), 1000)
    out = jax.vmap(lambda k: aug.point_noise(k, frame, GRID, cfg))(keys)
    no_intensity = np.asarray((out.points[:, :600, 3] == 0).all(1))
    slot0_dropped = ~np.asarray(out.point_valid[:, 0])
    assert 25 <= no_intensity.sum() <= 80  # Binomial(1000, 0.05)
    # P(drop | no intensity) is 0.05; with the two draws on one key it was 1.
    assert slot0_dropped[no_intensity].mean() < 0.3


def test_integer_probabilities_work():
    """A hand-edited config.json may hold 0 or 1 for a probability."""
    cfg = AugmentConfig(**{**dataclasses.asdict(OFF), "range_dropout_prob": 0,
                           "intensity_drop_prob": 1, "flip_prob": 1})  # fmt: skip
    out = aug.augment(jax.random.key(0), make_frame(), GRID, cfg)
    assert (np.asarray(out.points[:, 3]) == 0).all()


def test_augmentation_lowers_to_plain_xla_ops():
    """No foreign calls in the chain (the train step's augmentation): a 2 x 2 inverse by
    jnp.linalg.inv lowered to LAPACK calls on the CPU and cuSOLVER ones on a GPU."""
    batch = jax.tree.map(lambda *a: jnp.stack(a), make_frame(0), make_frame(1))
    lowered = jax.jit(aug.augment_batch, static_argnums=(2, 3)).lower(
        jax.random.key(7), batch, GRID, CFG.augment
    )
    assert "custom_call" not in lowered.as_text()


@pytest.mark.parametrize("flip", [0.0, 1.0])
def test_global_transform_warps_masks_by_the_exact_inverse(flip):
    """The masks are resampled through the inverse of the point map: equal to warping by
    numpy's inverse of the same matrix."""
    frame = make_frame()
    cfg = dataclasses.replace(OFF, flip_prob=flip, rotation=np.pi, scale_range=(0.8, 1.2))
    key = jax.random.key(3)
    out = aug.global_transform(key, frame, GRID, cfg)
    # The point map, read back from the transformed points (xy -> linear @ xy).
    xy, new_xy = np.asarray(frame.points[:450, :2]), np.asarray(out.points[:450, :2])  # objects
    linear = np.linalg.lstsq(xy, new_xy, rcond=None)[0].T
    inverse = np.concatenate([np.linalg.inv(linear), np.zeros((2, 1))], axis=1)
    want = aug.warp_masks(
        frame.targets.masks,
        jnp.broadcast_to(jnp.asarray(inverse, jnp.float32), (frame.targets.masks.shape[0], 2, 3)),
        GRID,
    )
    np.testing.assert_array_equal(out.targets.masks[:3], want[:3])


def test_box_noise_never_leaves_a_new_overlap_in_a_crowded_row():
    """Undoing one move can expose another's (moved into the undone one's place)."""
    n = 5
    labels = ObjectLabels(
        classes=[0] * n, dims=[[0.8, 0.8, 0.8]] * n,
        pos=[[-1.8 + 0.9 * i, 0.0, 0.4] for i in range(n)], yaw=[0.0] * n, occlusion=[0] * n,
    )  # fmt: skip
    targets = make_targets(labels, GRID, CFG.data.max_objects)
    frame = jax.tree.map(jnp.asarray, Batch(
        points=np.zeros((CFG.data.max_points, 4), np.float32),
        point_valid=np.zeros(CFG.data.max_points, bool), targets=targets,
    ))  # fmt: skip
    cfg = dataclasses.replace(OFF, box_noise_prob=1.0, box_translation_std=0.4, box_yaw_std=0.3)
    out = jax.jit(jax.vmap(lambda k: aug.box_noise(k, frame, GRID, cfg)))(
        jax.random.split(jax.random.key(0), 64)
    )
    masks = np.asarray(out.targets.masks)
    shared = (masks & (masks.sum(1, keepdims=True) - masks > 0)).sum((2, 3))
    assert (shared == 0).all(), np.flatnonzero(shared.any(1))


def _with_points(frame, extra):
    """``frame`` with float32 rows ``extra`` [K, 4] in its first free point slots."""
    n = int(frame.point_valid.sum())
    points = frame.points.at[n : n + len(extra)].set(jnp.asarray(extra, jnp.float32))
    valid = frame.point_valid.at[n : n + len(extra)].set(True)
    return frame.replace(points=points, point_valid=valid)


def _wall(axis, at, lo, hi, count, rng):
    """Points of a vertical wall: coordinate ``axis`` = ``at``, the other in [lo, hi], z in
    [0.1, 1.5], intensity 0.5."""
    along, z = rng.uniform(lo, hi, count), rng.uniform(0.1, 1.5, count)
    xy = np.stack([np.full(count, at), along], -1)[:, :: 1 if axis == 0 else -1]
    return np.c_[xy, z, np.full(count, 0.5)]


def _box_frame(points, centre, yaw):
    """xy of ``points`` [P, >=2] in the frame of a box centred on ``centre`` (its xy) and
    turned by ``yaw`` (its heading along +x): [P, 2]."""
    d = points[:, :2] - centre[:2]
    c, s = np.cos(yaw), np.sin(yaw)
    return np.stack([c * d[:, 0] + s * d[:, 1], -s * d[:, 0] + c * d[:, 1]], -1)


def test_box_noise_does_not_push_objects_into_a_wall():
    """Object 1 (0.5 x 0.5 m at x = -2.0) stands 0.1 m from a wall at x = -2.45: a move into
    the wall is undone, as ground-truth sampling refuses a pose with wall points inside."""
    rng = np.random.default_rng(0)
    frame = _with_points(make_frame(), _wall(0, -2.45, -4.5, 4.5, 400, rng))
    cfg = dataclasses.replace(OFF, box_noise_prob=1.0, box_translation_std=0.3)
    t0 = frame.targets
    scene = np.asarray(frame.point_valid & ~aug.points_in_boxes(
        frame.points, t0.pos, t0.dims, t0.yaw, t0.valid).any(0))  # fmt: skip
    out = jax.vmap(lambda k: aug.box_noise(k, frame, GRID, cfg))(
        jax.random.split(jax.random.key(0), 64)
    )
    moved = np.asarray(out.targets.pos[:, 1, 0]) != float(t0.pos[1, 0])
    assert 8 <= moved.sum() <= 60
    pts = np.asarray(frame.points)
    for k in np.flatnonzero(moved):
        pos, dims, yaw = (np.asarray(a[k, 1]) for a in (out.targets.pos, out.targets.dims,
                                                        out.targets.yaw))  # fmt: skip
        inside = (np.abs(_box_frame(pts, pos, yaw)) <= dims[:2] / 2).all(-1) & (pts[:, 2] > 0.05)
        inside &= pts[:, 2] <= pos[2] + dims[2] / 2
        assert (inside & scene).sum() <= aug.SCENE_POINTS_LIMIT, k


def test_box_noise_refuses_exactly_the_moves_that_reach_into_a_wall():
    """Object 0 (1.6 x 0.8 m, yaw 0.4, its corner 0.1 m from a wall at x = 2.5): a move is
    undone exactly when its box, in the box's own turned frame (with BOX_MARGIN, above the
    floor margin), holds more than SCENE_POINTS_LIMIT wall points. The moves proposed are
    read from the same keys on the frame without the wall, where none is refused for it. A
    mutation audit: the across coordinate's sign flipped (a box turned the other way
    checked, most legal moves undone) passed the square object's test above."""
    rng = np.random.default_rng(0)
    wall = _wall(0, 2.5, -4.5, 4.5, 400, rng)
    free = make_frame()
    cfg = dataclasses.replace(OFF, box_noise_prob=1.0, box_translation_std=0.3)
    keys = jax.random.split(jax.random.key(0), 64)
    noise = jax.jit(jax.vmap(lambda k, f: aug.box_noise(k, f, GRID, cfg), in_axes=(0, None)))
    proposed, walled = noise(keys, free).targets, noise(keys, _with_points(free, wall)).targets
    t0 = free.targets
    x0 = float(t0.pos[0, 0])
    was_moved = np.asarray(proposed.pos[:, 0, 0]) != x0
    kept = np.asarray(walled.pos[:, 0, 0]) != x0
    bottom = float(t0.pos[0, 2] - t0.dims[0, 2] / 2) + aug.FLOOR_MARGIN
    want = np.zeros(len(keys), bool)
    for k in np.flatnonzero(was_moved):
        pos, dims, yaw = (np.asarray(a[k, 0], np.float64) for a in (
            proposed.pos, proposed.dims, proposed.yaw))  # fmt: skip
        inside = (np.abs(_box_frame(wall, pos, yaw)) <= dims[:2] / 2 + aug.BOX_MARGIN).all(-1)
        inside &= (wall[:, 2] > bottom) & (wall[:, 2] <= float(t0.pos[0, 2]) + dims[2] / 2)
        want[k] = inside.sum() <= aug.SCENE_POINTS_LIMIT
    assert 10 <= want.sum() <= was_moved.sum() - 10  # both outcomes, many times
    np.testing.assert_array_equal(kept, want)
    np.testing.assert_array_equal(np.asarray(walled.pos)[kept], np.asarray(proposed.pos)[kept])


@pytest.mark.parametrize(
    "new_valid", [(True, True, True), (True, False, False), (False, True, True)]
)
@pytest.mark.parametrize("free", [(1, 3, 4, 6), (1, 3)])
def test_fill_free_slots_writes_the_ith_new_row_into_the_ith_free_slot(new_valid, free):
    """Ground-truth sampling pastes points through ``_fill_free_slots``: row i of the new
    points goes into the i-th free slot, where valid; rows past the free slots are dropped.
    Against a loop. A mutation audit: the rank off by one (row 0 lost, an object whose only
    point is its first pasted with none) passed."""
    points = np.zeros((8, 4), np.float32)
    points[:, 0] = np.arange(8) + 100
    valid = ~np.isin(np.arange(8), free)
    new = np.zeros((3, 4), np.float32)
    new[:, 0] = [1, 2, 3]
    want_points, want_valid = points.copy(), valid.copy()
    for i, slot in enumerate(np.flatnonzero(~valid)[: len(new)]):
        if new_valid[i]:
            want_points[slot], want_valid[slot] = new[i], True
    got_points, got_valid = aug._fill_free_slots(
        jnp.asarray(points), jnp.asarray(valid), jnp.asarray(new), jnp.asarray(new_valid)
    )
    np.testing.assert_array_equal(np.asarray(got_points), want_points)
    np.testing.assert_array_equal(np.asarray(got_valid), want_valid)


def test_gt_sampling_pastes_nothing_behind_the_walls():
    """In a 7.2 m square room inside the 10 m grid, every pasted footprint lies in the room
    (behind a wall the lidar sees nothing, so the other tests pass: half the pastes went
    there before)."""
    rng = np.random.default_rng(1)
    frame = make_frame()
    p = np.asarray(frame.points)
    in_room = (np.abs(p[:, :2]) < 3.6).all(-1)
    frame = frame.replace(
        points=jnp.where(in_room[:, None], frame.points, 0.0),
        point_valid=frame.point_valid & in_room,
    )
    walls = [_wall(a, at, -3.6, 3.6, 200, rng) for a in (0, 1) for at in (-3.6, 3.6)]
    frame = _with_points(frame, np.concatenate(walls))
    db = aug.build_object_database(jax.tree.map(lambda a: a[None], frame), GRID, max_points=64)
    cfg = dataclasses.replace(OFF, gt_sampling=3, gt_sampling_attempts=8)
    out = jax.vmap(lambda k: aug.gt_sampling(k, frame, db, GRID, cfg))(
        jax.random.split(jax.random.key(2), 32)
    )
    pasted = np.asarray(out.targets.masks)[:, 3:] & np.asarray(out.targets.valid)[:, 3:, None, None]
    assert pasted.any((2, 3)).sum() >= 32
    xs = np.asarray(GRID.x_range[0] + (np.arange(GRID.shape[1]) + 0.5) * GRID.cell_size)
    ys = np.asarray(GRID.y_range[0] + (np.arange(GRID.shape[0]) + 0.5) * GRID.cell_size)
    outside = (np.abs(xs)[None, :] > 3.6) | (np.abs(ys)[:, None] > 3.6)  # [H, W]
    assert not (pasted & outside).any()


def test_an_object_centred_off_the_grid_stays_a_target():
    """A dataset's sofa centred 0.3 m beyond the grid's edge, its footprint and points partly
    on the grid, is a target in validation (make_targets): training keeps it too."""
    frame = _move_object_0(make_frame(), [5.3 - 1.5, 0.0, 0.0])
    targets = frame.targets
    assert bool(targets.valid[0]) and bool(targets.masks[0].any())
    out = aug.augment(jax.random.key(0), frame, GRID, OFF)
    np.testing.assert_array_equal(out.targets.valid, targets.valid)
    np.testing.assert_array_equal(out.targets.masks, targets.masks)


def test_disabled_augmentations_leave_the_frame_bit_for_bit():
    frame = make_frame()
    out = aug.augment(jax.random.key(0), frame, GRID, OFF)
    jax.tree.map(np.testing.assert_array_equal, out, frame)


def test_database_keeps_points_evenly_spaced_over_each_object():
    """A scan stores an object's points in firing order: the first P would be a slice."""
    frame = make_frame()
    t = frame.targets
    inside = aug.points_in_boxes(frame.points, t.pos, t.dims, t.yaw, t.valid)
    inside = np.asarray(inside & frame.point_valid)
    db = aug.build_object_database(jax.tree.map(lambda a: a[None], frame), GRID, max_points=64)
    for k in range(3):
        rows = np.flatnonzero(inside[k])
        expected = rows[np.arange(64) * len(rows) // 64]
        # Intensity is copied unchanged: it identifies the rows kept.
        np.testing.assert_array_equal(db.points[k, :, 3], np.asarray(frame.points)[expected, 3])


def _edge_objects_frame():
    """A frame without points whose three objects are cut by the grid's edges: a shelf by
    +x, a cabinet by -y, a sofa in the (-x, +y) corner."""
    (x0, x1), (y0, y1) = GRID.x_range, GRID.y_range
    labels = ObjectLabels(
        classes=[3, 4, 2], dims=[[2.0, 1.2, 1.8], [1.0, 1.4, 1.9], [1.8, 1.0, 0.8]],
        pos=[[x1 - 0.6, 0.0, 0.9], [-1.5, y0 + 0.4, 0.95], [x0 + 0.5, y1 - 0.3, 0.4]],
        yaw=[0.0, 0.0, 0.3], occlusion=[0, 0, 0],
    )  # fmt: skip
    n = CFG.data.max_points
    return jax.tree.map(jnp.asarray, Batch(
        points=np.zeros((n, 4), np.float32), point_valid=np.zeros(n, bool),
        targets=make_targets(labels, GRID, CFG.data.max_objects),
    ))  # fmt: skip


def test_erosion_reads_cells_beyond_the_grid_as_set():
    """Footprints cut by the grid's edge erode as scipy's binary erosion with border value 1:
    their cells on the edge stay (an object goes on beyond it). Reading outside as empty
    ate the edge row or column and passed every test (a mutation audit)."""
    frame = _edge_objects_frame()
    cfg = dataclasses.replace(OFF, mask_perturb_prob=1.0)
    out = jax.jit(jax.vmap(lambda k: aug.mask_perturbation(k, frame, GRID, cfg)))(
        jax.random.split(jax.random.key(0), 16)
    )
    square = np.ones((3, 3), bool)
    for k, mask in enumerate(np.asarray(frame.targets.masks[:3])):
        edge = mask[0].any() | mask[-1].any() | mask[:, 0].any() | mask[:, -1].any()
        assert edge, k
        dilated = ndimage.binary_dilation(mask, square)
        eroded = ndimage.binary_erosion(mask, square, border_value=1)
        assert eroded.any() and (eroded != ndimage.binary_erosion(mask, square)).any()
        new = np.asarray(out.targets.masks[:, k])
        is_dilated, is_eroded = (new == dilated).all((1, 2)), (new == eroded).all((1, 2))
        assert (is_dilated | is_eroded).all(), k
        assert 3 <= is_eroded.sum() <= 13, k  # a fair coin per draw: both kinds occur


def test_database_leaves_out_objects_cut_by_any_grid_edge():
    """An object whose box crosses any of the grid's four edges (footprint and points cut
    off) stays out of the database, the +x edge too (only three edges were checked and the
    tests cut the -x one; a mutation audit); the objects wholly inside are all in it."""
    frame = make_frame()
    base = frame.targets
    (x0, x1), (y0, y1) = GRID.x_range, GRID.y_range
    cut = ObjectLabels(
        classes=[3, 4, 5, 7], dims=[[1.0, 0.4, 1.8]] * 4,
        pos=[[x1 - 0.1, -2.5, 0.9], [x0 + 0.1, 2.5, 0.9], [2.5, y1 - 0.1, 0.9],
             [-2.5, y0 + 0.1, 0.9]],
        yaw=[0.0] * 4, occlusion=[0] * 4,
    )  # fmt: skip
    v = np.asarray(base.valid)
    labels = ObjectLabels(
        classes=np.r_[np.asarray(base.classes)[v], cut.classes],
        dims=np.r_[np.asarray(base.dims)[v], cut.dims],
        pos=np.r_[np.asarray(base.pos)[v], cut.pos],
        yaw=np.r_[np.asarray(base.yaw)[v], cut.yaw],
        occlusion=[0] * (v.sum() + 4),
    )
    # Which boxes lie wholly inside the grid, from their corners.
    c, s = np.cos(labels.yaw), np.sin(labels.yaw)
    corners = np.array([[1, 1], [1, -1], [-1, -1], [-1, 1]])[None] * labels.dims[:, None, :2] / 2
    xs = labels.pos[:, None, 0] + c[:, None] * corners[..., 0] - s[:, None] * corners[..., 1]
    ys = labels.pos[:, None, 1] + s[:, None] * corners[..., 0] + c[:, None] * corners[..., 1]
    inside = ((xs > x0) & (xs < x1) & (ys > y0) & (ys < y1)).all(1)
    assert inside.sum() == 3 and (~inside).sum() == 4
    frame = frame.replace(targets=jax.tree.map(jnp.asarray, make_targets(labels, GRID, 8)))
    db = aug.build_object_database(jax.tree.map(lambda a: a[None], frame), GRID, max_points=64)
    assert db.classes.tolist() == labels.classes[inside].tolist()


@pytest.fixture(scope="module")
def database_256():
    """The database of ``make_frame(0)`` with P = 256 points an object (more than each has)."""
    return aug.build_object_database(jax.tree.map(lambda a: a[None], make_frame(0)), GRID, 256)


def test_database_keeps_each_point_once_below_max_points(database_256):
    """An object with fewer points than P keeps each of them once, in cloud order, and its
    other slots stay empty (picks spread over P repeated points: 256 kept out of ~150; a
    mutation audit)."""
    frame, db = make_frame(0), database_256
    t = frame.targets
    inside = aug.points_in_boxes(frame.points, t.pos, t.dims, t.yaw, t.valid)
    inside = np.asarray(inside & frame.point_valid)
    for k in range(3):
        rows = np.flatnonzero(inside[k])
        assert 100 < len(rows) < 256
        keep = np.asarray(db.point_valid[k])
        np.testing.assert_array_equal(keep, np.arange(256) < len(rows))
        # Intensity is copied unchanged: it identifies the rows kept.
        np.testing.assert_array_equal(db.points[k, keep, 3], np.asarray(frame.points)[rows, 3])


def test_gt_sampling_pastes_nothing_when_every_target_slot_is_taken(database_256):
    """With all M target slots valid a pasted object has no slot: the frame stays as it was
    (it overwrote the first target; a mutation audit). With one slot free, the same draw
    pastes an object there."""
    db = database_256
    m = CFG.data.max_objects
    cfg = dataclasses.replace(OFF, gt_sampling=4)
    paste = jax.jit(lambda f: aug.gt_sampling(jax.random.key(0), f, db, GRID, cfg))
    xs = np.linspace(-1.0, 1.0, m)
    for n in (m - 1, m):  # small boxes in a row near the sensor
        labels = ObjectLabels(classes=[5] * n, dims=[[0.2, 0.2, 0.3]] * n,
                              pos=[[x, -3.0, 0.15] for x in xs[:n]], yaw=[0.0] * n,
                              occlusion=[0] * n)  # fmt: skip
        targets = jax.tree.map(jnp.asarray, make_targets(labels, GRID, m))
        frame = make_frame(1).replace(targets=targets)
        out = paste(frame)
        if n < m:
            assert bool(out.targets.valid[m - 1]) and out.targets.masks[m - 1].any()
            np.testing.assert_array_equal(out.targets.pos[: m - 1], targets.pos[: m - 1])
        else:
            jax.tree.map(np.testing.assert_array_equal, out.targets, frame.targets)
            np.testing.assert_array_equal(out.point_valid, frame.point_valid)
            np.testing.assert_array_equal(out.points, frame.points)


def test_an_empty_azimuth_bin_takes_the_nearer_neighbours_return():
    """``_beyond_returns`` against its docstring, re-derived in numpy: 288 points give 36 bins
    of 10 degrees, each holding the farthest return in it; an empty bin takes the nearer of
    its two neighbours' (bin 18 between 1.5 m and 3.5 m: 1.5 m), and a bin with no return
    in it or beside it (bin 6 of 5-7) counts as unseen, every cell beyond. The farther
    neighbour passed every test (a mutation audit): it pasted objects behind a wall."""
    bins = 36
    which = np.repeat(np.arange(bins), 8)  # 8 points per bin, at the bin's middle azimuth
    az = -np.pi + (which + 0.5) * 2 * np.pi / bins
    r = np.where(which == 17, 1.5, 3.5)
    valid = ~np.isin(which, [18, 5, 6, 7])
    pts = np.column_stack([r * np.cos(az), r * np.sin(az), np.zeros_like(r), np.ones_like(r)])
    beyond = np.asarray(aug._beyond_returns(jnp.asarray(pts, jnp.float32), jnp.asarray(valid),
                                            GRID))  # fmt: skip
    expected_range = np.full(bins, 3.5)
    expected_range[[17, 18]] = 1.5  # bin 17's own return, bin 18's nearer neighbour
    expected_range[6] = 0.0  # unseen
    xs = GRID.x_range[0] + (np.arange(GRID.shape[1]) + 0.5) * GRID.cell_size
    ys = GRID.y_range[0] + (np.arange(GRID.shape[0]) + 0.5) * GRID.cell_size
    px, py = np.meshgrid(xs, ys)
    f = (np.arctan2(py, px) + np.pi) / (2 * np.pi) * bins
    cell_bin = np.floor(f).astype(int) % bins
    dist = np.hypot(px, py)
    want = dist > expected_range[cell_bin]
    # Compared away from bin edges and returns, and not in bins 5 and 7 (one neighbour each).
    clear = (np.abs(f - np.round(f)) > 1e-3) & (np.abs(dist - 1.5) > 0.01)
    clear &= (np.abs(dist - 3.5) > 0.01) & ~np.isin(cell_bin, [5, 7])
    np.testing.assert_array_equal(beyond[clear], want[clear])
    between = clear & (cell_bin == 18) & (dist > 1.5) & (dist < 3.5)
    assert between.sum() >= 2 and beyond[between].all()  # the case the rule is about
    assert beyond[clear & (cell_bin == 6)].all() and (clear & (cell_bin == 6)).sum() >= 10


def test_gt_sampling_ignores_floor_points_under_a_pose():
    """Only scene points above floor level (the object's bottom + FLOOR_MARGIN) inside a
    candidate's box reject it or are removed under a paste (gt_sampling docstring): a dense
    floor at z = 0, as a real scan has, gives the same pastes as the same points lifted
    above every object (z = 2.5), and no floor point is removed. make_frame's floor was
    too sparse for the floor cut to matter: counting floor points passed every test (a
    mutation audit)."""
    frame = make_frame()
    db = aug.build_object_database(jax.tree.map(lambda a: a[None], frame), GRID, max_points=64)
    rng = np.random.default_rng(3)
    n = 1000  # ~12 points per m^2 over 9 x 9 m; leaves free slots for the pasted points
    xy = rng.uniform(-4.5, 4.5, (n, 2))
    floor = _with_points(frame, np.c_[xy, np.zeros(n), rng.random(n)])
    lifted = _with_points(frame, np.c_[xy, np.full(n, 2.5), rng.random(n)])
    first = int(frame.point_valid.sum())
    assert float(db.z.max() + db.dims[:, 2].max() / 2) < 2.5 and int(floor.point_valid.sum()) < (
        CFG.data.max_points - 3 * 64
    )
    cfg = dataclasses.replace(OFF, gt_sampling=3, gt_sampling_attempts=8)
    run = jax.jit(jax.vmap(lambda k, f: aug.gt_sampling(k, f, db, GRID, cfg), (0, None)))
    keys = jax.random.split(jax.random.key(2), 16)
    a, b = run(keys, floor), run(keys, lifted)
    jax.tree.map(np.testing.assert_array_equal, a.targets, b.targets)
    added = np.asarray(a.targets.valid).sum(1) - 3
    assert (added >= 1).sum() >= 12, added
    assert np.asarray(a.point_valid)[:, first : first + n].all()  # the floor stays
    np.testing.assert_array_equal(np.asarray(a.points)[:, first : first + n],
                                  np.broadcast_to(np.asarray(floor.points)[first : first + n],
                                                  (16, n, 4)))  # fmt: skip


def test_box_noise_scales_points_with_the_box_and_floor_returns_block_nothing():
    """box_noise moves, turns and rescales an object "together with its points" (its
    docstring): in the moved box's frame each point of the object sits at ``scale`` times its
    place in the old box's frame, z included (the box height scales). And only scene points
    *above its floor* can undo a move, so a dense floor at z = 0 (the objects stand on it)
    gives the same targets as no floor. A mutation audit passed all tests with point z left
    unscaled, and with the floor test dropped (floor returns undid moves)."""
    rng = np.random.default_rng(0)
    frame = make_frame()
    n, first = 1200, int(frame.point_valid.sum())
    with_floor = _with_points(frame, np.c_[rng.uniform(-4.5, 4.5, (n, 2)), np.zeros(n),
                                           rng.random(n)])  # fmt: skip
    cfg = dataclasses.replace(OFF, box_noise_prob=1.0, box_translation_std=0.1,
                              box_yaw_std=0.1, box_scale_std=0.2)  # fmt: skip
    run = jax.jit(jax.vmap(lambda k, f: aug.box_noise(k, f, GRID, cfg), (0, None)))
    keys = jax.random.split(jax.random.key(0), 6)
    a, b = run(keys, frame), run(keys, with_floor)
    jax.tree.map(np.testing.assert_array_equal, b.targets, a.targets)
    t0 = frame.targets
    pos0, dims0, yaw0 = (np.asarray(x)[:3] for x in (t0.pos, t0.dims, t0.yaw))
    pos, dims, yaw = (np.asarray(x)[:, :3] for x in (a.targets.pos, a.targets.dims,
                                                     a.targets.yaw))  # fmt: skip

    def local(p, centre, heading):  # [P, 3] in the box frame (heading along +x)
        return np.c_[_box_frame(p, centre, heading), p[:, 2] - centre[2]]

    p0, p1 = np.asarray(frame.points), np.asarray(a.points)
    rescaled = floor_under = 0
    for j in range(len(keys)):
        for k in range(3):
            rows = slice(150 * k, 150 * (k + 1))  # object k's points in make_frame
            scale = dims[j, k] / dims0[k]
            np.testing.assert_allclose(scale, scale[0], rtol=1e-5)  # one scale per object
            np.testing.assert_allclose(local(p1[j, rows], pos[j, k], yaw[j, k]),
                                       scale[0] * local(p0[rows], pos0[k], yaw0[k]),
                                       atol=2e-5)  # fmt: skip
            rescaled += abs(scale[0] - 1) > 0.05
            # Floor points under the moved box: enough to undo the move if they counted.
            fl = local(np.asarray(with_floor.points)[first : first + n], pos[j, k], yaw[j, k])
            moved = not np.allclose(pos[j, k], pos0[k])
            under = (np.abs(fl[:, :2]) <= dims[j, k, :2] / 2).all(-1).sum()
            floor_under += moved and under > aug.SCENE_POINTS_LIMIT
    assert rescaled >= 6 and floor_under >= 6, (rescaled, floor_under)


def test_range_band_dropout_drops_one_band_of_its_width():
    """point_noise's range-band dropout (AugmentConfig.range_dropout_prob: "drop one random
    range band of the frame", range_dropout_width metres wide): at probability 1 the points
    dropped are exactly the valid points with r0 <= r < r0 + width for one r0, i.e. all
    within one band of that width, every point between the nearest and farthest dropped one
    dropped, nothing else touched. A mutation audit (the band never drops a point) passed
    all tests."""
    frame = make_frame()
    width = 2.0
    cfg = dataclasses.replace(OFF, range_dropout_prob=1.0, range_dropout_width=width)
    keys = jax.random.split(jax.random.key(0), 4)
    out = jax.jit(jax.vmap(lambda k: aug.point_noise(k, frame, GRID, cfg)))(keys)
    valid0, pts0 = np.asarray(frame.point_valid), np.asarray(frame.points)
    r = np.hypot(pts0[:, 0], pts0[:, 1])
    banded = 0
    for j in range(len(keys)):
        kept = np.asarray(out.point_valid[j])
        assert not (kept & ~valid0).any()
        np.testing.assert_array_equal(np.asarray(out.points[j])[kept], pts0[kept])
        dropped = valid0 & ~kept
        if not dropped.any():
            continue  # r0 drawn beyond the farthest point
        banded += 1
        lo, hi = r[dropped].min(), r[dropped].max()
        assert hi - lo < width
        between = valid0 & (r >= lo) & (r <= hi)
        np.testing.assert_array_equal(dropped, between)
    assert banded >= 3, banded


def test_gt_sampling_respects_unseen_objects_five_point_clutter_and_pastes_whole_objects():
    """gt_sampling's docstring on one generated batch of 12 frames:
    - the database holds each object's points object-local (ObjectDatabase: centre at 0,
      heading along +x), the frame's rows turned by -yaw, re-derived in numpy;
    - a candidate is rejected when its footprint touches an existing footprint, even of
      labelled objects with no points (occluded: the scene-point test cannot catch them);
    - it is rejected only with *more than* 5 scene points above floor level under it: a pose
      over a 5-point clutter cluster is accepted (and those points removed);
    - a pasted object's points lie inside its pasted box (its yaw is the one its points
      were turned by), each of the database object's points once.
    A mutation audit passed all tests with the footprint test off, with ">= 5" points
    rejecting, with the pasted box turned 90 degrees, and with the database turned by +yaw."""
    base = make_frame()
    t0 = base.targets
    owned = np.asarray(aug.points_in_boxes(base.points, t0.pos, t0.dims, t0.yaw, t0.valid))
    db = aug.build_object_database(jax.tree.map(lambda a: a[None], base), GRID, max_points=64)
    pts0 = np.asarray(base.points)
    for d in range(3):  # the rows kept are known by their intensity, copied unchanged
        keep = np.asarray(db.point_valid[d])
        rows = [int(np.flatnonzero(pts0[:, 3] == v)[0]) for v in np.asarray(db.points[d, keep, 3])]
        assert owned[d, rows].all()
        rel = pts0[rows, :3] - np.asarray(t0.pos[d])
        c, s = np.cos(float(t0.yaw[d])), np.sin(float(t0.yaw[d]))
        want = np.c_[c * rel[:, 0] + s * rel[:, 1], -s * rel[:, 0] + c * rel[:, 1], rel[:, 2]]
        np.testing.assert_allclose(np.asarray(db.points[d, keep, :3]), want, atol=1e-5)
    # The frame: the same floor, 4 labelled objects without points, 5-point clusters 0.3 m up.
    labels = ObjectLabels(classes=[0] * 4, dims=[[2.0, 1.2, 0.75]] * 4,
                          pos=[[-2.0, -2.0, 0.375], [2.0, -2.0, 0.375], [2.0, 2.0, 0.375],
                               [-2.0, 2.0, 0.375]], yaw=[0.3, -0.5, 1.0, 0.0],
                          occlusion=[2] * 4)  # fmt: skip
    targets = jax.tree.map(jnp.asarray, make_targets(labels, GRID, CFG.data.max_objects))
    floor = pts0[~owned.any(0) & np.asarray(base.point_valid)]
    grid_1m = np.arange(-4.0, 4.5, 1.0)  # 81 clusters of 5 coincident points, 1 m apart
    cluster = np.array([(x, y, 0.3, 0.5) for x in grid_1m for y in grid_1m for _ in range(5)])
    n_floor = len(floor)
    points = np.zeros((CFG.data.max_points, 4), np.float32)
    points[: n_floor + len(cluster)] = np.concatenate([floor, cluster])
    frame = Batch(points=jnp.asarray(points), targets=targets,
                  point_valid=jnp.arange(CFG.data.max_points) < n_floor + len(cluster))  # fmt: skip
    cfg = dataclasses.replace(OFF, gt_sampling=3, gt_sampling_attempts=8)
    n_keys = 12
    out = jax.jit(jax.vmap(lambda k: aug.gt_sampling(k, frame, db, GRID, cfg)))(
        jax.random.split(jax.random.key(0), n_keys)
    )
    t = out.targets
    valid = np.asarray(t.valid)
    masks = np.asarray(t.masks) & valid[..., None, None]
    pasted = valid[:, 4:]
    assert pasted.sum() >= n_keys, pasted.sum()
    assert (masks.sum(1) <= 1).all()  # never over an existing (pointless) footprint
    # Scene points per pasted footprint: cluster points under it, at 0.3 m (in every height).
    row, col, _ = (np.asarray(a) for a in cell_index(jnp.asarray(cluster[:, 0]),
                                                     jnp.asarray(cluster[:, 1]), GRID))  # fmt: skip
    under = masks[:, 4:, row, col]  # [K, 4, 405]
    assert under.sum(-1).max() <= aug.SCENE_POINTS_LIMIT
    over_five = under.sum(-1) == aug.SCENE_POINTS_LIMIT
    assert over_five.sum() >= 2, over_five.sum()  # the boundary case is exercised
    # Scene points under a paste are removed (their slots may take pasted points).
    slots = slice(n_floor, n_floor + len(cluster))
    same = (np.asarray(out.points)[:, slots] == cluster).all(-1)
    assert not (np.asarray(out.point_valid)[:, slots] & same & under.any(1)).any()
    # Pasted points: each inside its own pasted box.
    inside = np.asarray(
        jax.vmap(
            lambda f: aug.points_in_boxes(
                f.points, f.targets.pos, f.targets.dims, f.targets.yaw, f.targets.valid, 1e-3
            )
        )(out)
    )
    unchanged = (np.asarray(out.points) == points).all(-1) & np.asarray(frame.point_valid)
    new = np.asarray(out.point_valid) & ~unchanged  # pasted points, in freed slots too
    n_db = {int(c): int(np.asarray(db.point_valid[d]).sum()) for d, c in enumerate(db.classes)}
    for j, k in np.argwhere(pasted):
        assert (inside[j, 4 + k] & new[j]).sum() == n_db[int(t.classes[j, 4 + k])], (j, k)
    assert new.sum() == sum(n_db[int(c)] for c in np.asarray(t.classes)[:, 4:][pasted])
