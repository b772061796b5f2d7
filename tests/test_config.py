"""Config presets and validation messages that name the field."""

import dataclasses
import json
import math
import re

import pytest

from indoorbev_jax.config import (
    AugmentConfig,
    BackboneConfig,
    Config,
    ConfigError,
    DataConfig,
    GridConfig,
    HeadConfig,
    LossConfig,
    SimConfig,
    TrainConfig,
)


def test_preset_grids():
    assert Config.paper().grid.shape == (500, 500)
    assert Config.small().grid.shape == (100, 100)
    assert Config.paper().backbone.pad_multiple == 56
    assert Config.small().backbone.pad_multiple == 112
    for name in ("paper", "small", "tiny"):
        cfg = Config.preset(name)
        assert Config.from_dict(cfg.to_dict()) == cfg


def test_the_paper_preset_holds_designs_numbers():
    """Each value as DESIGN.md (section) and the paper state it: the loss tests take their
    weights from LossConfig itself, so a changed default passed them all."""
    from indoorbev_sim.objects import CLASSES

    from indoorbev_jax.models.swin import stage_geometry

    cfg = Config.paper()
    names = ("Table", "Chair", "Sofa", "Shelf", "Cabinet", "Box", "Person", "Robot", "Misc")
    assert cfg.data.class_names == names  # 4; and the simulator labels in the same order
    assert tuple(spec.name for spec in CLASSES) == names
    grid = cfg.grid  # 2
    assert (grid.x_range, grid.y_range, grid.z_range, grid.cell_size) == (
        (-5.0, 5.0), (-5.0, 5.0), (-3.0, 3.0), 0.02
    )  # fmt: skip
    bb = cfg.backbone  # 6
    assert (bb.embed_dims, bb.depths, bb.num_heads, bb.strides) == (
        (64, 128, 256, 512), (1, 1, 1, 1), (2, 4, 8, 8), (1, 2, 2, 2)
    )  # fmt: skip
    assert (bb.window_size, bb.mlp_ratio, bb.out_indices) == (7, 2.0, (0, 1, 2, 3))
    # Stages 2 and 4 shifted by 3; the grid padded once to 504: 504 -> 252 -> 126 -> 63.
    assert bb.shifted == (False, True, False, True) and bb.shift_size == 3
    assert [res for res, _, _ in stage_geometry(500, bb)] == [504, 252, 126, 63]
    head = cfg.head  # 7: 30 queries, 4 layers, 8 heads of C_hid 64, FFN 256, paper mode
    assert (head.hidden_dim, head.num_queries, head.num_layers) == (64, 30, 4)
    assert (head.num_heads, head.ffn_dim, head.upsampler_skips) == (8, 256, False)
    loss = cfg.loss  # 8, and the paper's loss and cost weights
    weights = (loss.cls_weight, loss.dice_weight, loss.focal_weight, loss.dims_weight,
               loss.pos_weight, loss.yaw_weight, loss.background_weight)  # fmt: skip
    assert weights == (2.0, 5.0, 2.0, 0.1, 0.1, 0.1, 0.1) and loss.aux_loss
    assert (loss.cost_cls, loss.cost_dice, loss.cost_focal, loss.cost_reg) == (2.0, 5.0, 2.0, 0.1)
    inference = cfg.inference  # 9: score 0.8, mask 0.5, a segment keeps 80 % of its mask
    assert (inference.score_threshold, inference.mask_threshold) == (0.8, 0.5)
    assert inference.overlap_threshold == 0.8
    assert (cfg.train.learning_rate, cfg.train.weight_decay) == (5e-5, 1e-4)  # the paper


@pytest.mark.parametrize(
    "build, field",
    [
        (lambda: GridConfig(cell_size=0.03), "grid.x_range"),
        (lambda: GridConfig(cell_size=-1.0), "grid.cell_size"),
        (lambda: GridConfig(z_range=(1.0, -1.0)), "grid.z_range"),
        (lambda: BackboneConfig(num_heads=(2, 3, 8, 8)), r"backbone.num_heads\[1\]"),
        (lambda: BackboneConfig(depths=(1, 1)), "backbone.depths"),
        (lambda: HeadConfig(num_heads=5), "head.num_heads"),
        (lambda: HeadConfig(hidden_dim=15, num_heads=3), "head.hidden_dim"),
        (lambda: TrainConfig(warmup_steps=10, total_steps=5), "train.warmup_steps"),
        (lambda: TrainConfig(ema_decay=1.0), "train.ema_decay"),
        (lambda: AugmentConfig(intensity_drop_prob=1.5), "augment.intensity_drop_prob"),
        # Non-finite and non-positive values that used to pass or crash unnamed.
        (lambda: GridConfig(cell_size=math.inf), "grid.cell_size"),
        (lambda: GridConfig(x_range=(-5.0, math.inf)), "grid.x_range"),
        (lambda: GridConfig(x_range=(-1e308, 1e308)), "grid.x_range"),
        (lambda: BackboneConfig(embed_dims=(-64, 128, 256, 512)), r"backbone.embed_dims\[0\]"),
        (lambda: BackboneConfig(embed_dims=(64, 0, 256, 512)), r"backbone.embed_dims\[1\]"),
        (lambda: BackboneConfig(depths=(1, -1, 1, 1)), r"backbone.depths\[1\]"),
        (
            lambda: BackboneConfig(
                embed_dims=(), depths=(), num_heads=(), strides=(), shifted=(), out_indices=()
            ),
            "backbone.embed_dims",
        ),
        (lambda: AugmentConfig(rotation=math.nan), "augment.rotation"),
        (lambda: AugmentConfig(jitter_std=math.inf), "augment.jitter_std"),
        (lambda: AugmentConfig(scale_range=(1.0, math.inf)), "augment.scale_range"),
        (lambda: SimConfig(min_range=math.nan), "sim.min_range"),
        # A workspace of no height: no point inside, and a height ramp dividing by zero.
        (lambda: GridConfig(z_range=(1.0, 1.0)), "grid.z_range"),
        # int(width x ratio) hidden units: 0 or inf failed in the model's init, a traceback.
        (lambda: BackboneConfig(mlp_ratio=0.01), "backbone.mlp_ratio"),
        (lambda: BackboneConfig(mlp_ratio=math.inf), "backbone.mlp_ratio"),
        (lambda: BackboneConfig(mlp_ratio=0.0), "backbone.mlp_ratio"),
        (lambda: SimConfig(clearance=math.nan), "sim.clearance"),
        # Open bounds: the documented [0, 1) and min_range < max_range (a mutation audit).
        (lambda: SimConfig(dropout=1.0), "sim.dropout"),
        (lambda: SimConfig(min_range=5.0, max_range=5.0), "sim.min_range"),
        (lambda: DataConfig(class_map=(("Desk", "Table"), ("Desk", "Chair"))), "data.class_map"),
        # Background weight 1 - alpha < 0 rewards positive background logits.
        (lambda: LossConfig(focal_alpha=1.5), "loss.focal_alpha"),
        # Names a KITTI label line cannot hold: split on whitespace, or skipped by the reader.
        (lambda: DataConfig(class_names=("Table", "Misc item")), "data.class_names"),
        (lambda: DataConfig(class_names=("Table", "DontCare")), "data.class_names"),
        (lambda: DataConfig(class_names=("Table", "")), "data.class_names"),
        (lambda: DataConfig(class_map=(("Side table", "Table"),)), "data.class_map"),
        (lambda: DataConfig(class_map=(("DontCare", "Table"),)), "data.class_map"),
        (
            lambda: dataclasses.replace(Config.tiny(), head=HeadConfig(num_queries=4)),
            "data.max_objects",
        ),
    ],
)
def test_errors_name_the_field(build, field):
    with pytest.raises(ConfigError, match=f"config field '{field}'"):
        build()


def test_from_dict_rejects_unknown_fields():
    d = Config.tiny().to_dict()
    d["grid"]["cellsize"] = 0.1
    with pytest.raises(ConfigError, match="grid.cellsize"):
        Config.from_dict(d)


def test_from_dict_refuses_missing_fields_but_those_older_files_lack():
    """A missing field took its default (a model file without head.mask_prior detected
    nothing, exit 0); but configs written before a field existed, the models shipped until
    2026-12-05 among them, lack it and must read as they did: with the behaviour before it."""
    from pathlib import Path

    from indoorbev_jax.config import LATER_FIELDS, OPTIONAL_FIELDS, flatten_dict

    config = Config.small()
    assert LATER_FIELDS.items() <= OPTIONAL_FIELDS.items()
    # The config of the first model shipped (git show a336423:models/indoorbev_small.msgpack)
    # lacks exactly the optional fields, and reads.
    shipped = json.loads(
        (Path(__file__).parent / "data" / "small_config_2026-11-22.json").read_text()
    )
    assert set(flatten_dict(config.to_dict())) - set(flatten_dict(shipped)) == set(OPTIONAL_FIELDS)
    first = Config.from_dict(shipped)
    assert all(flatten_dict(first.to_dict())[k] == v for k, v in OPTIONAL_FIELDS.items())
    older = config.to_dict()
    for path, default in OPTIONAL_FIELDS.items():
        section, name = path.split(".")
        assert getattr(getattr(config, section), name) == default  # what a file lacking it gets
        del older[section][name]
    assert Config.from_dict(older) == config
    # Every missing field is named at once, whichever sections they are in.
    del older["head"]["mask_prior"], older["train"]["learning_rate"], older["loss"]
    with pytest.raises(ConfigError) as refused:
        Config.from_dict(older)
    assert str(refused.value) == (
        "missing config field(s) ['head.mask_prior', 'loss', 'train.learning_rate']"
    )
    with pytest.raises(ConfigError, match=r"^run/config\.json: missing config field\(s\)"):
        Config.from_file_dict(older, "run/config.json")


def test_from_dict_checks_each_value_against_the_field_type():
    """A hand-edited config.json fails naming the field, not deep inside a jitted step."""
    d = Config.tiny().to_dict()
    d["train"]["batch_size"] = "8"
    with pytest.raises(ConfigError, match=r"'train\.batch_size': got '8', expected"):
        Config.from_dict(d)
    d = Config.tiny().to_dict()
    d["grid"] = 3
    with pytest.raises(ConfigError, match="config section 'grid': expected an object, got 3"):
        Config.from_dict(d)
    d = Config.tiny().to_dict()
    d["backbone"]["depths"] = [1, "x", 1, 1]
    with pytest.raises(ConfigError, match=r"'backbone\.depths'"):
        Config.from_dict(d)
    d = Config.tiny().to_dict()
    d["train"]["learning_rate"] = 1  # an int where a float goes is that float
    assert Config.from_dict(d).train.learning_rate == 1.0
    assert isinstance(Config.from_dict(d).train.learning_rate, float)


def test_with_overrides_parses_json_values_and_names_bad_items():
    from indoorbev_jax.config import with_overrides

    cfg = with_overrides(
        Config.small(),
        ["head.upsampler_skips=false", "data.mask_targets=box", "backbone.strides=[2,2,2,2]"],
    )
    assert cfg.head.upsampler_skips is False and cfg.data.mask_targets == "box"
    assert cfg.backbone.strides == (2, 2, 2, 2) and cfg.head.mask_prior  # the rest is kept
    for item, message in [
        ("head.nope=1", "head has no field 'nope'"),
        ("x=1", "expected SECTION.FIELD=VALUE"),
        ("head.upsampler_skips", "expected SECTION.FIELD=VALUE"),
        ("data.mask_targets=circle", "data.mask_targets"),
    ]:
        with pytest.raises(ConfigError, match=message):
            with_overrides(Config.small(), [item])


def test_with_overrides_checks_each_value_against_the_field_type():
    from indoorbev_jax.config import with_overrides

    base = Config.tiny()
    # Python's spelling of a bool is not JSON: it used to become the truthy string 'False'.
    for raw, want in [("False", False), ("FALSE", False), ("0", False), ("true", True),
                      ("True", True), ("1", True)]:  # fmt: skip
        assert with_overrides(base, [f"train.augment={raw}"]).train.augment is want
    cfg = with_overrides(
        base,
        [
            "train.batch_size=3",
            "train.seed=4.0",
            "train.learning_rate=1",
            "grid.x_range=[-5, 5]",
            "data.mask_targets=box",
            'data.class_map={"Desk": "Table"}',
            "backbone.shifted=[false, true, 0, 1]",
        ],
    )
    assert type(cfg.train.batch_size) is int and cfg.train.batch_size == 3
    assert type(cfg.train.seed) is int and cfg.train.seed == 4
    assert type(cfg.train.learning_rate) is float and cfg.train.learning_rate == 1.0
    assert cfg.grid.x_range == (-5.0, 5.0) and all(type(v) is float for v in cfg.grid.x_range)
    assert cfg.data.mask_targets == "box" and cfg.data.class_map == (("Desk", "Table"),)
    assert cfg.backbone.shifted == (False, True, False, True)
    for item, expected in [
        ("train.augment=maybe", "bool"),
        ("train.augment=2", "bool"),
        ("train.batch_size=2.5", "int"),
        ("train.batch_size=four", "int"),
        ("train.learning_rate=fast", "float"),
        ("train.learning_rate=true", "float"),
        ("grid.x_range=5", r"tuple\[float, float\]"),
        ("grid.x_range=[1, 2, 3]", r"tuple\[float, float\]"),
        ("backbone.strides=[1, 2.5, 2, 2]", r"tuple\[int, \.\.\.\]"),
    ]:
        key, _, raw = item.partition("=")
        message = f"config field '{key}': got '{re.escape(raw)}', expected {expected}"
        with pytest.raises(ConfigError, match=message):
            with_overrides(base, [item])
    with pytest.raises(ConfigError, match="train has no field 'nope' .*augment, eval_batches"):
        with_overrides(base, ["train.nope=1"])
    # The simulated lidar's tilt: three finite angles.
    assert with_overrides(base, ["sim.sensor_rpy=[0, 20, 0]"]).sim.sensor_rpy == (0.0, 20.0, 0.0)
    with pytest.raises(ConfigError, match=r"'sim.sensor_rpy': got '\[0, 20\]', expected"):
        with_overrides(base, ["sim.sensor_rpy=[0, 20]"])
    with pytest.raises(ConfigError, match="'sim.sensor_rpy': expected finite degrees"):
        dataclasses.replace(base.sim, sensor_rpy=(0.0, math.nan, 0.0))


def test_configs_pass_through_jit_and_vmap_without_static_argnums():
    """Configs are pytrees without leaves: plain jax.jit / jax.vmap take them, and a jitted
    function retraces when a config value changes."""
    import jax
    import jax.numpy as jnp
    import numpy as np

    from indoorbev_jax.data.rasterize import rasterize_boxes

    grid = Config.tiny().grid
    boxes = jnp.array([[0.0, 0.0, 1.0, 0.5, 0.3], [1.0, -1.0, 0.4, 0.4, 0.0]])
    valid = jnp.array([True, True])
    ids, masks = rasterize_boxes(boxes, valid, grid)
    jit_ids, jit_masks = jax.jit(rasterize_boxes)(boxes, valid, grid)
    np.testing.assert_array_equal(jit_ids, ids)
    np.testing.assert_array_equal(jit_masks, masks)
    v_ids, _ = jax.vmap(rasterize_boxes)(boxes[None], valid[None], grid)
    np.testing.assert_array_equal(v_ids[0], ids)
    traces = []

    @jax.jit
    def cells(config, x):
        traces.append(config.cell_size)
        return x * config.shape[0]

    cells(grid, 1.0)
    cells(grid, 2.0)
    coarse = dataclasses.replace(grid, cell_size=2 * grid.cell_size)
    assert float(cells(coarse, 1.0)) == coarse.shape[0]
    assert traces == [grid.cell_size, coarse.cell_size]
    assert jax.tree.leaves(Config.tiny()) == []


def test_a_run_refuses_a_seed_past_32_bits_but_a_file_with_one_loads():
    """jax.random.key keeps 32 bits: 2**32 was seed 0's run again; -1 failed at step 0.
    A run refuses them; a config (a model file of an older version) still holds them."""
    from indoorbev_jax.config import check_train_seed, with_overrides

    for seed in (-1, 2**32):
        config = with_overrides(Config.tiny(), [f"train.seed={seed}"])
        assert Config.from_dict(json.loads(config.to_json())) == config
        with pytest.raises(ConfigError, match=r"'train\.seed': must lie in \[0, 2\*\*32\)"):
            check_train_seed(config.train)
    check_train_seed(TrainConfig(seed=2**32 - 1))


def test_python_built_sections_check_each_fields_type():
    """GridConfig(cell_size="0.1") raised a bare TypeError inside a range check, and an int
    field given 2.5 passed to fail far later; numpy numbers and lists are what Python
    callers pass, and read as the annotated type (lists as tuples: configs are hashed)."""
    import numpy as np

    for build, message in [
        (lambda: GridConfig(cell_size="0.1"), "'grid.cell_size': got '0.1', expected float"),
        (lambda: TrainConfig(batch_size=2.5), "'train.batch_size': got 2.5, expected int"),
        (lambda: TrainConfig(augment="no"), "'train.augment': got 'no', expected bool"),
        (lambda: SimConfig(sensor_height=(0.3, "x")), "'sim.sensor_height': got (0.3, 'x')"),
    ]:
        with pytest.raises(ConfigError, match=re.escape(message)):
            build()
    grid = GridConfig(x_range=[-4, 4], cell_size=np.float32(0.25))
    assert grid == GridConfig(x_range=(-4.0, 4.0), cell_size=0.25)
    assert type(grid.cell_size) is float and type(grid.x_range) is tuple
    hash(grid)
    assert TrainConfig(batch_size=np.int64(8)).batch_size == 8
    # A float32 means its shortest decimal: np.float32(0.1) gave 99.99999851 cells of 10 m.
    assert GridConfig(cell_size=np.float32(0.1)).cell_size == 0.1
    grid = GridConfig(
        x_range=list(np.float32([-4.2, 4.2])), y_range=(-3, 3), cell_size=np.float32(0.3)
    )
    assert grid.x_range == (-4.2, 4.2) and grid.cell_size == 0.3


def test_refuses_zero_gt_sampling_attempts_and_a_grid_a_fraction_of_a_cell_off():
    """``augment.gt_sampling`` needs at least one candidate pose per pasted object (zero
    attempts crashed inside the jitted paste, an argmax over nothing), and a grid extent must
    hold a whole number of cells (DESIGN section 2: W = (x_max - x_min) / v): 10 m / 0.099 m
    is 101.0101 cells, whose centres drift off the documented formula. A mutation audit
    (gt_sampling_attempts < 0 checked; divisibility tolerance 0.1 cell) passed all tests."""
    with pytest.raises(ConfigError, match=r"config field 'augment\.gt_sampling'.*attempts"):
        AugmentConfig(gt_sampling=2, gt_sampling_attempts=0)
    assert AugmentConfig(gt_sampling=2, gt_sampling_attempts=1).gt_sampling_attempts == 1
    extent = GridConfig().x_range[1] - GridConfig().x_range[0]
    cells = extent / 0.099
    assert 1e-3 < abs(cells - round(cells)) < 0.1  # a near miss, not a gross one
    with pytest.raises(ConfigError, match=r"config field 'grid\.x_range'.*not divisible"):
        GridConfig(cell_size=0.099)


def test_documented_zeros_a_float_cell_count_and_steps_alone():
    """TRAINING.md: ``train.grad_clip_norm`` 0 turns clipping off and ``train.weight_decay``
    0 is none; a grid of 2.4 m in 0.1 m cells is 24 cells though the float quotient is
    23.999999999999996; ``--steps`` alone caps ``train.warmup_steps`` at the new total
    (config_from_args). Refusing the zeros, a grid one cell short and a warm-up one step
    short each passed every test (a mutation audit)."""
    import argparse

    from indoorbev_jax.config import add_config_arguments, config_from_args, with_overrides

    off = with_overrides(Config.tiny(), ["train.grad_clip_norm=0", "train.weight_decay=0"])
    assert (off.train.grad_clip_norm, off.train.weight_decay) == (0.0, 0.0)
    grid = GridConfig(x_range=(-1.2, 1.2), y_range=(-2.3, 2.3), cell_size=0.1)
    assert (2.4 / 0.1, grid.shape) == (23.999999999999996, (46, 24))
    parser = argparse.ArgumentParser()
    add_config_arguments(parser)
    for steps in (50, 150):  # below and above the small preset's warm-up
        config = config_from_args(parser.parse_args(["--preset", "small", "--steps", str(steps)]))
        want = min(steps, Config.small().train.warmup_steps)
        assert (config.train.total_steps, config.train.warmup_steps) == (steps, want)


def test_with_overrides_refuses_a_path_deeper_than_section_field():
    """``with_overrides`` takes SECTION.FIELD=VALUE items only; ``head.remat.x=true`` is a
    malformed item and must be a ConfigError naming the expected form (the CLI turns it into a
    one-line exit 2), not a bare ValueError traceback from unpacking three parts. A mutation
    audit (a.b.c accepted past the form check) passed all tests."""
    from indoorbev_jax.config import with_overrides

    for item in ("head.remat.x=true", "grid.x_range.0=1.0"):
        with pytest.raises(ConfigError, match="expected SECTION.FIELD=VALUE"):
            with_overrides(Config.tiny(), [item])
