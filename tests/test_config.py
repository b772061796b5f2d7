"""Config presets and validation messages that name the field."""

import dataclasses

import pytest

from indoorbev_jax.config import (
    AugmentConfig,
    BackboneConfig,
    Config,
    ConfigError,
    GridConfig,
    HeadConfig,
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


@pytest.mark.parametrize(
    "build, field",
    [
        (lambda: GridConfig(cell_size=0.03), "grid.x_range"),
        (lambda: GridConfig(cell_size=-1.0), "grid.cell_size"),
        (lambda: GridConfig(z_range=(1.0, -1.0)), "grid.z_range"),
        (lambda: BackboneConfig(num_heads=(2, 3, 8, 8)), r"backbone.num_heads\[1\]"),
        (lambda: BackboneConfig(depths=(1, 1)), "backbone.depths"),
        (lambda: HeadConfig(num_heads=5), "head.num_heads"),
        (lambda: TrainConfig(warmup_steps=10, total_steps=5), "train.warmup_steps"),
        (lambda: TrainConfig(ema_decay=1.0), "train.ema_decay"),
        (lambda: AugmentConfig(intensity_drop_prob=1.5), "augment.intensity_drop_prob"),
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
