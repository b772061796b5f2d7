"""Bad input to the evaluation, benchmark and plotting scripts gets an error naming it."""

import importlib.util
from pathlib import Path

import pytest

from indoorbev_jax.config import Config

REPO = Path(__file__).resolve().parents[1]


def _params(config: Config, fill=lambda shape: 0.0):
    """A parameter tree of ``config``'s network (what a model file must hold), each array
    ``fill(shape)`` as float32: no network is initialised."""
    import jax
    import numpy as np

    from indoorbev_jax.predict import param_shapes

    shapes = param_shapes(config)
    return jax.tree.map(
        lambda s: np.broadcast_to(fill(s.shape), s.shape).astype(np.float32), shapes
    )


def _script(name: str):
    spec = importlib.util.spec_from_file_location(name, REPO / "experiments" / f"{name}.py")
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def test_plot_curves_names_the_malformed_line(tmp_path):
    plot = _script("plot_curves")
    (tmp_path / "metrics.jsonl").write_text(
        '{"step": 50, "kind": "train", "loss": 3.0}\n{"step": 100, "kind": "train", "loss":\n'
        '{"step": 150, "kind": "train", "loss": 2.0}\n'  # not the last: not a cut write
    )
    with pytest.raises(ValueError, match=r"metrics\.jsonl:2: not a JSON line"):
        plot.read_log(tmp_path)
    for line in ("3", "[1, 2]", '{"step": "x"}'):  # an AttributeError traceback before
        (tmp_path / "metrics.jsonl").write_text('{"step": 50, "loss": 3.0}\n' + line + "\n")
        with pytest.raises(ValueError, match=r"metrics\.jsonl:2: expected a JSON object"):
            plot.read_log(tmp_path)
    (tmp_path / "metrics.jsonl").write_text(
        '{"step": 50, "kind": "train", "loss": 3.0}\n{"step": 50, "kind": "eval", "pq": null}\n'
    )
    log = plot.read_log(tmp_path)
    assert [r["step"] for r in log["train"]] == [50] and log["eval"][0]["pq"] is None


def test_evaluate_sim_names_a_bad_frame_set():
    from indoorbev_jax import sim_eval

    tiny = Config.tiny()
    with pytest.raises(ValueError, match="frames 10 must be a multiple of batch 8"):
        sim_eval.evaluate_sim(tiny, None, "test", 10, 8, 0, progress=False)
    with pytest.raises(ValueError, match="batch: expected a whole number > 0, got 0"):
        sim_eval.evaluate_sim(tiny, None, "test", 8, 0, 0, progress=False)
    with pytest.raises(ValueError, match=r"seed: expected a whole number in \[0, 2\*\*32\)"):
        sim_eval.evaluate_sim(tiny, None, "test", 8, 8, -1, progress=False)
    # Only the held-out sets have a root seed of their own; train frames need one given.
    with pytest.raises(ValueError, match="split: expected 'test' or 'val' .* got 'train'"):
        sim_eval.evaluate_sim(tiny, None, "train", 8, 8, progress=False)
    assert (sim_eval.default_seed("test"), sim_eval.default_seed("val")) == (1_000_003, 1_000_033)
    # The script reads the library's frame sets: one definition of the held-out seeds.
    eval_sim = _script("eval_sim")
    assert eval_sim.evaluate_sim is sim_eval.evaluate_sim
    assert (eval_sim.TEST_SEED, eval_sim.VAL_SEED) == (sim_eval.TEST_SEED, sim_eval.VAL_SEED)


def test_frame_tags_put_each_edge_value_in_the_row_that_names_it():
    """Rows are named ``[a, b)``: an object with exactly a points (cells, metres) belongs to
    the row starting at a; np.digitize(right=True) put it one row lower, unseen. An object
    just below the first edge goes to the first row, ``<a``; the occlusion rows name the
    simulator's visibility thresholds."""
    import types

    import numpy as np
    from indoorbev_sim.labels import VISIBLE_FULL, VISIBLE_PART

    from indoorbev_jax import sim_eval

    names = {g: rows for g, rows, _ in sim_eval.BREAKDOWNS}
    full, part = round(100 * VISIBLE_FULL), round(100 * VISIBLE_PART)
    assert names["occlusion"][:3] == (f"0 (>={full}% seen)", f"1 ({part}-{full}%)", f"2 (<{part}%)")
    for grouping, edges in (("points", sim_eval.POINT_EDGES), ("area", sim_eval.AREA_EDGES),
                            ("range", sim_eval.RANGE_EDGES)):  # fmt: skip
        n = len(edges) + 1  # the last object sits just below the first edge
        pos, masks = np.zeros((n, 3)), np.zeros((n, 8, 16), bool)
        points = np.zeros(n, int)
        for k, edge in enumerate([*edges, edges[0] - 1]):
            if grouping == "points":
                points[k] = edge
            elif grouping == "area":
                masks[k].reshape(-1)[: int(edge)] = True
            else:
                pos[k, 0] = edge
        targets = types.SimpleNamespace(classes=np.zeros(n, int), pos=pos, masks=masks)
        info = types.SimpleNamespace(variant=np.zeros(n, int), num_points=points,
                                     occlusion=np.zeros(n, int))  # fmt: skip
        rows = sim_eval.frame_tags(targets, info)[grouping]
        for edge, row in zip(edges, rows[:-1], strict=True):
            assert names[grouping][row].startswith((f"[{edge:g},", f">={edge:g}")), (edge, row)
        assert rows[-1] == 0 and names[grouping][0].startswith(f"<{edges[0]:g}"), grouping


def test_eval_sim_sweep_fuses_the_views_at_each_rows_mask_threshold():
    """With test-time views, fusion binarises the masks at ``mask_threshold``: every row of
    a mask-threshold sweep must be the evaluation at its own threshold (each row used to be
    fused at the first row's)."""
    import dataclasses

    from indoorbev_jax.evaluate import to_json
    from indoorbev_jax.predict import load_model

    eval_sim = _script("eval_sim")
    # The shipped model: an untrained one finds nothing at either threshold.
    config, params = load_model(Path(__file__).parents[1] / "models" / "indoorbev_small.msgpack")
    views = ("identity", "mirror_x")
    settings = [dataclasses.replace(config.inference, mask_threshold=m, views=views)
                for m in (0.3, 0.7)]  # fmt: skip
    sweep = eval_sim.evaluate_sim_sweep(config, params, "test", 2, 2, 5, settings, False)
    results = [to_json(e.compute()) for e in sweep]
    assert results[0] != results[1]
    for inference, result in zip(settings, results, strict=True):
        alone = dataclasses.replace(config, inference=inference)
        assert (
            to_json(eval_sim.evaluate_sim(alone, params, "test", 2, 2, 5, False).compute())
            == result
        )


def test_eval_sim_names_a_bad_model_and_an_out_of_range_threshold(tmp_path, capsys):

    from indoorbev_jax.predict import export_model

    eval_sim = _script("eval_sim")
    missing = tmp_path / "missing.msgpack"
    with pytest.raises(SystemExit) as exit_info:
        eval_sim.main(["--model", str(missing)])
    assert exit_info.value.code == 2
    assert f"{missing}: no such model file" in capsys.readouterr().err
    # The threshold is checked before the parameters are used: zeros will do.
    path = export_model(_params(Config.tiny()), Config.tiny(), tmp_path / "m.msgpack")
    for bad in ("2", "nan"):
        with pytest.raises(SystemExit) as exit_info:
            eval_sim.main(["--model", str(path), "--score-threshold", bad])
        assert exit_info.value.code == 2
        assert "inference.score_threshold': must lie in [0, 1]" in capsys.readouterr().err
    with pytest.raises(SystemExit) as exit_info:
        eval_sim.main(["--model", str(path), "--score-threshold", "0.3,x"])
    assert exit_info.value.code == 2
    assert "expected numbers separated by commas, got '0.3,x'" in capsys.readouterr().err
    with pytest.raises(SystemExit) as exit_info:
        eval_sim.main(["--model", str(path), "--mask-threshold", "0.5,2"])
    assert exit_info.value.code == 2
    assert "inference.mask_threshold': must lie in [0, 1]" in capsys.readouterr().err
    # A negative first value was "expected one argument", naming no value.
    for flag in ("--score-threshold", "--mask-threshold"):
        with pytest.raises(SystemExit) as exit_info:
            eval_sim.main(["--model", str(path), flag, "-0.1,0.5"])
        assert exit_info.value.code == 2
        assert f"{flag[2:].replace('-', '_')}': must lie in [0, 1], got -0.1" in (
            capsys.readouterr().err
        )
    # A repeat was evaluated twice, an identical second row.
    with pytest.raises(SystemExit) as exit_info:
        eval_sim.main(["--model", str(path), "--score-threshold", "0.3,0.3,0.9"])
    assert exit_info.value.code == 2
    assert "argument --score-threshold: '0.3,0.3,0.9' repeats a value" in capsys.readouterr().err
    for bad, said in (("1,2,3", "expected HEIGHT or MIN,MAX, got 3 values"),
                      ("0.8,0.3", "sim.sensor_height': expected 0 <= min <= max"),
                      ("2.45", "sim.sensor_height: up to 2.45 m reaches the ceiling")):  # fmt: skip
        with pytest.raises(SystemExit) as exit_info:
            eval_sim.main(["--model", str(path), "--sensor-height", bad])
        assert exit_info.value.code == 2
        assert said in capsys.readouterr().err
    with pytest.raises(SystemExit) as exit_info:
        eval_sim.main(["--model", str(path), "--lidar-rpy", "0,20"])
    assert exit_info.value.code == 2
    assert "--lidar-rpy: expected ROLL,PITCH,YAW in degrees, got '0,20'" in capsys.readouterr().err
    with pytest.raises(SystemExit) as exit_info:
        eval_sim.main(["--model", str(path), "--tilt-jitter", "-3"])
    assert exit_info.value.code == 2
    assert "'sim.sensor_tilt_jitter': expected degrees in [0, 90]" in capsys.readouterr().err


def test_export_model_rejects_an_out_of_range_threshold_and_stores_a_good_one(tmp_path, capsys):
    import jax
    import numpy as np

    from indoorbev_jax.predict import load_model

    export = _script("export_model")
    params = _params(Config.tiny(), lambda shape: np.arange(shape[-1]))
    loaded = []
    export.load_run = lambda run, which: (
        loaded.append(which) or (Config.tiny(), params, "best, step 7")
    )
    run = tmp_path / "run"
    run.mkdir()
    out = tmp_path / "m.msgpack"
    with pytest.raises(SystemExit) as exit_info:
        export.main([str(run), "--out", str(out), "--score-threshold", "1.5"])
    assert exit_info.value.code == 2 and not out.exists()
    assert "inference.score_threshold': must lie in [0, 1]" in capsys.readouterr().err
    export.main(
        [str(run), "--out", str(out), "--score-threshold", "0.3", "--mask-threshold", "0.4"]
    )
    config, back = load_model(out)
    assert set(loaded) == {"best"}  # without --which: the best one (docs/TRAINING.md)
    assert f"{run} (best, step 7, preset tiny, " in capsys.readouterr().out  # what was read
    assert (config.inference.score_threshold, config.inference.mask_threshold) == (0.3, 0.4)
    assert config.inference.views == ("identity",)
    jax.tree.map(np.testing.assert_array_equal, back, params)
    # A model file in: the same parameters out with other settings, the rest kept.
    views = tmp_path / "views.msgpack"
    with pytest.raises(SystemExit) as exit_info:
        export.main([str(tmp_path / "gone.msgpack"), "--out", str(views)])
    assert exit_info.value.code == 2 and not views.exists()
    assert "gone.msgpack: no such model file or run directory" in capsys.readouterr().err
    with pytest.raises(SystemExit) as exit_info:
        export.main([str(out), "--out", str(views), "--views", "identity,sideways"])
    assert exit_info.value.code == 2 and not views.exists()
    assert "unknown view 'sideways'" in capsys.readouterr().err
    export.main([str(out), "--out", str(views), "--views", "identity,rotate_90"])
    config, again = load_model(views)
    assert config.inference.views == ("identity", "rotate_90")
    assert config.inference.score_threshold == 0.3
    jax.tree.map(np.testing.assert_array_equal, again, params)


def test_eval_sim_sweep_equals_one_evaluation_per_setting(tmp_path, capsys):
    import dataclasses
    import json

    import jax
    import numpy as np
    from indoorbev_sim.objects import ALL_VARIANTS

    from indoorbev_jax.config import InferenceConfig
    from indoorbev_jax.evaluate import to_json
    from indoorbev_jax.predict import export_model
    from indoorbev_jax.train import init_state

    eval_sim = _script("eval_sim")
    config = Config.tiny()
    params = init_state(config, jax.random.key(0)).params
    model = export_model(params, config, tmp_path / "m.msgpack")
    out = tmp_path / "sweep.json"
    argv = ["--model", str(model), "--frames", "2", "--batch", "2", "--seed", "5", "--json"]
    sweep = ["--score-threshold", "0,0.1", "--mask-threshold", "0.5,0.4", "--tables"]
    eval_sim.main([*argv, str(out), *sweep])
    printed = capsys.readouterr().out
    assert "4 threshold settings" in printed and "    0.1      0.4" in printed
    assert printed.count("per object variant") == 4 and "Misc/trolley*" in printed
    # The batch is part of the frame set (B scenes of frames / B frames each), as the seed.
    assert json.loads(out.read_text())["setup"]["batch"] == 2
    assert "2 simulated 'test' frames, batch 2, seed 5" in printed
    sweep = json.loads(out.read_text())["sweep"]
    metrics = [{k: v for k, v in e.items() if not k.endswith("threshold")} for e in sweep]
    assert metrics[0] != metrics[3]  # the settings matter
    for entry in sweep:
        inference = InferenceConfig(entry["score_threshold"], entry["mask_threshold"])
        one = eval_sim.evaluate_sim(
            dataclasses.replace(config, inference=inference), params, "test", 2, 2, 5, False
        )
        assert {**entry, **json.loads(to_json(one.compute()))} == entry
        tags = one.tag_confusion(len(ALL_VARIANTS), grouping="variant")
        np.testing.assert_array_equal(entry["tag_confusion@0.5"]["counts"], tags)
        # Every breakdown regroups the same matches: equal column totals.
        loose = one.tag_confusion(len(ALL_VARIANTS), 0.25, grouping="variant")
        for grouping, names, _ in eval_sim.BREAKDOWNS:
            for iou, ref in (("0.5", tags), ("0.25", loose)):
                counts = np.array(entry[f"breakdowns@{iou}"][grouping]["counts"])
                assert counts.shape == (len(names), len(config.data.class_names) + 1)
                np.testing.assert_array_equal(counts.sum(0), ref.sum(0))
    assert printed.count("objects no mask found, by lidar points on the object") == 4
    # Row totals re-derived from the simulator's own per-object point counts and positions.
    from indoorbev_sim.generate import jitted_generate

    data, info = jitted_generate(config, "test", 2)(jax.random.fold_in(jax.random.key(5), 0))
    keep = np.asarray(data.targets.valid) & np.asarray(data.targets.masks).any((2, 3))
    points = np.asarray(info.num_points)[keep]
    by_points = np.array(sweep[0]["breakdowns@0.5"]["points"]["counts"]).sum(1)
    np.testing.assert_array_equal(by_points, np.histogram(points, [0, 10, 30, 100, 300, np.inf])[0])
    xy = np.asarray(data.targets.pos)[keep][:, :2]
    by_range = np.array(sweep[0]["breakdowns@0.5"]["range"]["counts"]).sum(1)
    dist = np.sqrt((xy**2).sum(1))
    np.testing.assert_array_equal(by_range, np.histogram(dist, [0, 2, 3, 4, 5, np.inf])[0])
    cells = np.asarray(data.targets.masks).sum((2, 3))[keep]
    by_area = np.array(sweep[0]["breakdowns@0.5"]["area"]["counts"]).sum(1)
    np.testing.assert_array_equal(by_area, np.histogram(cells, [0, 10, 25, 50, 100, np.inf])[0])


def test_bench_model_names_an_xla_option_without_a_value(capsys):
    bench = _script("bench_model")
    with pytest.raises(SystemExit) as exit_info:
        bench.main(["--preset", "tiny", "--xla-vs", "xla_cpu_use_onednn"])
    assert exit_info.value.code == 2
    assert "--xla-vs expects NAME=VALUE, got 'xla_cpu_use_onednn'" in capsys.readouterr().err
    with pytest.raises(SystemExit):  # an empty variant
        bench.main(["--preset", "tiny", "--xla-vs", "a=b", "--xla-vs", " "])
    assert "--xla-vs expects NAME=VALUE, got ''" in capsys.readouterr().err


def test_bench_model_refuses_a_peer_it_cannot_run_before_compiling(capsys, monkeypatch):
    """The peer's preconditions (torch installed, a non-tiny preset) are checked before ours
    compiles (minutes for paper); they used to fail after it, with a traceback for torch."""
    bench = _script("bench_model")
    monkeypatch.setattr(bench, "build_jax", lambda *a, **k: pytest.fail("compiled first"))
    with pytest.raises(SystemExit) as exit_info:
        bench.main(["--preset", "tiny"])
    assert exit_info.value.code == 2
    assert "the peer has no tiny preset; add --only jax" in capsys.readouterr().err
    monkeypatch.setattr(bench.importlib.util, "find_spec", lambda name: None)
    with pytest.raises(SystemExit) as exit_info:
        bench.main(["--preset", "small"])
    assert exit_info.value.code == 2
    assert "the PyTorch peer needs torch" in capsys.readouterr().err


def test_bench_views_names_a_missing_model(tmp_path, capsys):
    bench = _script("bench_views")
    with pytest.raises(SystemExit) as exit_info:
        bench.main(["--model", str(tmp_path / "none.msgpack")])
    assert exit_info.value.code == 2
    assert "none.msgpack: no such model file or run directory" in capsys.readouterr().err


def test_average_models_is_the_mean_and_names_what_differs(tmp_path, capsys):
    import dataclasses
    import re

    import jax
    import numpy as np

    from indoorbev_jax.predict import average_models, export_model, load_model

    rng = np.random.default_rng(0)
    tiny = Config.tiny()
    trees = [_params(tiny, lambda shape: rng.normal(size=shape)) for _ in range(3)]
    paths = [export_model(t, tiny, tmp_path / f"m{k}.msgpack") for k, t in enumerate(trees)]
    config, mean = average_models(paths)
    assert config == tiny

    def check_mean(got, *leaves):
        assert got.dtype == leaves[0].dtype
        np.testing.assert_allclose(got, np.mean(np.float64(leaves), axis=0), rtol=1e-5)

    jax.tree.map(check_mean, mean, *trees)

    # The script writes the same average with the thresholds it is given.
    script = _script("average_models")
    out = tmp_path / "soup.msgpack"
    script.main([*map(str, paths), "--out", str(out), "--score-threshold", "0.3"])
    back_config, back = load_model(out)
    assert back_config.inference.score_threshold == 0.3
    jax.tree.map(np.testing.assert_array_equal, back, mean)

    # A model of another grid, another shape or another structure is named, nothing written.
    other_grid = dataclasses.replace(tiny, grid=dataclasses.replace(tiny.grid, cell_size=0.2))
    bad_grid = export_model(trees[1], other_grid, tmp_path / "grid.msgpack")
    with pytest.raises(
        ValueError, match=rf"{re.escape(str(bad_grid))}: grid\.cell_size = 0\.2, but"
    ):
        average_models([paths[0], bad_grid])
    wide = jax.tree.map(lambda x: np.zeros((*x.shape, 2), x.dtype), trees[1])
    bad_shape = export_model(wide, tiny, tmp_path / "wide.msgpack")
    with pytest.raises(ValueError, match=rf"{re.escape(str(bad_shape))}: parameter .* has shape "):
        average_models([paths[0], bad_shape])

    # The average was trained on every model's lidar heights; one tilt only.
    def sim(**kw):
        return dataclasses.replace(tiny, sim=dataclasses.replace(tiny.sim, **kw))

    high = export_model(trees[1], sim(sensor_height=(0.6, 1.5)), tmp_path / "high.msgpack")
    low = export_model(trees[2], sim(sensor_height=(0.15, 0.5)), tmp_path / "low.msgpack")
    assert average_models([paths[0], high, low])[0] == sim(sensor_height=(0.15, 1.5))
    shaky = export_model(trees[1], sim(sensor_tilt_jitter=8.0), tmp_path / "shaky.msgpack")
    assert average_models([paths[0], shaky])[0] == sim(sensor_tilt_jitter=8.0)
    turned = export_model(trees[1], sim(sensor_rpy=(0, 0, 360)), tmp_path / "turn.msgpack")
    assert average_models([paths[0], turned])[0].sim.sensor_rpy == (0, 0, 0)  # the same tilt
    tilted = export_model(trees[1], sim(sensor_rpy=(0, 20, 0)), tmp_path / "tilt.msgpack")
    with pytest.raises(ValueError, match=rf"{re.escape(str(tilted))}: sim\.sensor_rpy = .*"
                       r"say which tilt to record \(--sensor-rpy"):  # fmt: skip
        average_models([paths[0], tilted])
    both = tmp_path / "both.msgpack"
    script.main([str(paths[0]), str(tilted), "--out", str(both), "--sensor-rpy", "0,10,0"])
    assert load_model(both)[0].sim.sensor_rpy == (0.0, 10.0, 0.0)
    assert "lidar heights 0.35-0.8 m" in capsys.readouterr().out
    fewer = export_model({"params": {"head": trees[0]["params"]["head"]}}, tiny, tmp_path / "f")
    with pytest.raises(ValueError, match=rf"{re.escape(str(fewer))}: parameter .* is missing"):
        average_models([paths[0], fewer])
    with pytest.raises(SystemExit) as exit_info:
        script.main([str(paths[0]), "--out", str(tmp_path / "one.msgpack")])
    assert exit_info.value.code == 2 and not (tmp_path / "one.msgpack").exists()
    assert "expected at least two models, got 1" in capsys.readouterr().err
    # A malformed or missing model file is named by the script; nothing is written.
    garbage = tmp_path / "garbage.msgpack"
    garbage.write_bytes(b"\x00not msgpack")
    for bad, message in (
        (garbage, "not an indoorbev_jax model file"),
        (tmp_path / "no", "no such"),
    ):
        with pytest.raises(SystemExit) as exit_info:
            script.main([str(paths[0]), str(bad), "--out", str(tmp_path / "two.msgpack")])
        assert exit_info.value.code == 2 and not (tmp_path / "two.msgpack").exists()
        assert f"{bad}: {message}" in capsys.readouterr().err
    # Models of other class lists: their class rows mean other classes.
    names = tuple(reversed(tiny.data.class_names))
    renamed = dataclasses.replace(tiny, data=dataclasses.replace(tiny.data, class_names=names))
    reordered = export_model(trees[1], renamed, tmp_path / "reordered.msgpack")
    with pytest.raises(ValueError, match=rf"{re.escape(str(reordered))}: data\.class_names = "):
        average_models([paths[0], reordered])
    # A negative roll is a value, as for predict's --lidar-rpy.
    neg = tmp_path / "neg.msgpack"
    script.main([str(paths[0]), str(tilted), "--out", str(neg), "--sensor-rpy", "-5,10,0"])
    assert load_model(neg)[0].sim.sensor_rpy == (-5.0, 10.0, 0.0)
    # An out-of-range threshold is named by its field.
    with pytest.raises(SystemExit) as exit_info:
        script.main([*map(str, paths[:2]), "--out", str(out), "--mask-threshold", "2"])
    assert exit_info.value.code == 2
    assert "inference.mask_threshold': must lie in [0, 1]" in capsys.readouterr().err


def test_train_script_refusals_are_one_line(tmp_path, capsys, monkeypatch):
    """A refused start (here: a workdir holding another run's config) prints one line and
    returns status 2, not a traceback."""
    import logging

    ours = logging.getLogger("indoorbev_jax")  # main() configures it: undone afterwards
    monkeypatch.setattr(ours, "handlers", list(ours.handlers))  # main() appends to a copy
    monkeypatch.setattr(ours, "level", ours.level)
    monkeypatch.setattr(ours, "propagate", ours.propagate)
    train = _script("train")
    (tmp_path / "config.json").write_text(Config.small().to_json())
    status = train.main(["--preset", "tiny", "--workdir", str(tmp_path), "--data", str(tmp_path)])
    err = capsys.readouterr().err
    assert status == 2
    assert "train.py: error: " in err and "the workdir holds a run with another config" in err
    assert "Traceback" not in err


def test_sweep_script_refusals_are_one_line(tmp_path, capsys):
    """As train.py: a refused resume (another sweep's settings) is one line, status 2."""
    sweep = _script("sweep")
    (tmp_path / "config.json").write_text(Config.small().to_json())
    argv = ["--preset", "tiny", "--workdir", str(tmp_path), "--learning-rates", "1e-4", "2e-4"]
    status = sweep.main(argv)
    err = capsys.readouterr().err
    assert status == 2
    assert "sweep.py: error: " in err and "the workdir holds a run with another config" in err
    assert "Traceback" not in err


def test_eval_sim_val_frames_are_not_paired_with_the_test_frames():
    """Under one root, val frame i and test frame i shared their sensor noise key, frame time
    and scan pattern frame (and most object draws), so choices made on val were made on
    near-copies of the test frames. Each split now has its own root."""
    import jax
    import numpy as np
    from indoorbev_sim.generate import jitted_draw

    eval_sim = _script("eval_sim")
    config = Config.tiny()
    draws = {}
    for split in ("val", "test"):
        key = jax.random.fold_in(jax.random.key(eval_sim.default_seed(split)), 0)
        _, time, frame_index, noise = jitted_draw(config, split, 4)(key)
        draws[split] = np.asarray(time), int(frame_index), jax.random.key_data(noise)
    (t_val, f_val, n_val), (t_test, f_test, n_test) = draws["val"], draws["test"]
    assert not np.isin(t_val, t_test).any()
    assert f_val != f_test and not np.array_equal(n_val, n_test)


def test_eval_sim_draws_its_first_batch_from_fold_in_of_the_seed(monkeypatch):
    """The frame sets are documented (sim_eval, docs/TRAINING.md) as batch k =
    generate_batch(fold_in(key(seed), k)); the test above reads batch 0 that way, so the
    batches eval_sim scores must be the ones it reads. A mutation audit: keying batch k
    with k + 1 passed every test, and every published figure would change."""
    import jax
    import numpy as np
    from indoorbev_sim import generate

    from indoorbev_jax import sim_eval

    keys = []

    class Drawn(Exception):
        pass

    def generator(config, split, batch):
        def draw(key):
            keys.append(key)
            raise Drawn

        return draw

    monkeypatch.setattr(generate, "jitted_generate", generator)
    with pytest.raises(Drawn):
        sim_eval.evaluate_sim(Config.tiny(), None, "test", 4, 2, 7, progress=False)
    want = jax.random.fold_in(jax.random.key(7), 0)
    np.testing.assert_array_equal(jax.random.key_data(keys[0]), jax.random.key_data(want))


@pytest.mark.parametrize(
    ("script", "argv", "message"),
    [
        ("bench_metrics", ["--size", "60"], "--size must be at least 64 cells, got 60"),
        ("bench_metrics", ["--repeats", "0"], "--repeats must be at least 1"),
        ("bench_matching", ["--grid", "60"], "--grid must be at least 64 cells, got 60"),
        ("bench_ros2", ["--latency-frames", "1"], "--latency-frames gives 1 clouds"),
        ("bench_ros2", ["--seconds", "0.1"], "--seconds x --rate gives 1 clouds"),
        ("pose_errors", ["--model", "m", "--match-iou", "0.4"], "--match-iou must lie in [0.5, 1)"),
        ("pose_errors", ["--model", "m", "--frames", "10"], "--frames 10 must be a multiple of"),
        ("eval_sim", ["--model", "m", "--frames", "10"], "--frames 10 must be a multiple of"),
        ("bench_lidar", ["--sets", "mid360"], "--sets: unknown ['mid360']; the sets are"),
        ("bench_lidar", ["--thread-sizes", "20k"], "--thread-sizes: expected ray counts"),
        ("bench_datagen", ["--ref-frames", "9"], "--ref-frames 9: at most --batch (8) frames"),
        ("bench_train", ["--steps", "0"], "argument --steps: must be > 0, got 0"),
        ("bench_train", ["--sweep-k", "-1"], "argument --sweep-k: must be >= 0, got -1"),
        ("bench_views", ["--reps", "0"], "argument --reps: must be > 0, got 0"),
        ("bench_model", ["--only", "jax", "--set", "head.nope=1"], "head has no field 'nope'"),
        ("bench_metrics", ["--eval-frames", "1"], "--eval-frames 1: at least --eval-batch 4"),
        # Before 2026-12-07 (morning): a traceback after compiling, or a typo'd peer timed
        # as the bilinear one under the name given.
        ("bench_lidar", ["--settle", "-1"], "argument --settle: must be a finite number >= 0"),
        ("bench_model", ["--settle", "nan"], "argument --settle: must be a finite number >= 0"),
        ("bench_model", ["--peer", "convt2"], "--peer: unknown up_mode 'convt2'; expected"),
        ("bench_ros2", ["--rate", "nan"], "argument --rate: must be a finite number > 0, got nan"),
        ("eval_sim", ["--model", "m", "--batch", "0"], "argument --batch: must be > 0, got 0"),
        ("eval_sim", ["--model", "m", "--frames", "-8"], "argument --frames: must be > 0, got -8"),
        ("pose_errors", ["--model", "none.msgpack"], "none.msgpack: no such model file or run"),
        ("export_model", ["nowhere", "--member", "0", "--out", "x"], "nowhere: no such model file"),
        # Before 2026-12-06 (night): ZeroDivisionError or a JAX TypeError after compiling,
        # a silent run, or an override printed as applied and replaced.
        ("demo", ["--frames", "0"], "argument --frames: must be > 0, got 0"),
        ("split_pairing", ["--batch", "0"], "argument --batch: must be > 0, got 0"),
        ("overfit_check", ["--every", "0"], "argument --every: must be > 0, got 0"),
        ("overfit_check", ["--set", "train.augment=true"], "--set train.augment=true: the check"),
        ("eval_sim", ["--model", "m", "--intensity-factor", "-1"], "--intensity-factor: expected"),
        # Before 2026-12-08: NaN missed every object (exit 0); a traceback after 15 s of
        # simulation, or after the config was built; "0 of 0" for a folder of no clouds; a
        # run that timed nothing; an OverflowError.
        ("eval_sim", ["--model", "m", "--z-offset", "nan"], "--z-offset: expected a finite"),
        ("demo", ["--out", str(REPO / "pyproject.toml")], "pyproject.toml: is a file; --out"),
        ("overfit_check", ["--learning-rate", "nan"], "--learning-rate: config field 'train.l"),
        ("column_check_sweep", ["--folders", str(REPO)], f"--folders {REPO}: no velodyne/*.bin"),
        ("bench_model", ["--only", "torch", "--peer", "none"], "--only torch with --peer none"),
        ("bench_views", ["--seed", "-1"], "argument --seed: expected a whole number in [0, 2**32)"),
        ("bench_ros2", ["--seconds", "1e300", "--rate", "1e300"], "--rate gives inf clouds"),
        # Before 2026-12-07: a --json that cannot be written failed after the evaluation;
        # seeds past 32 bits scored seed s's frames under another name (or overflowed); a
        # file that is not a model, an unknown preset or field, an unwritable --out were
        # tracebacks or status 1.
        ("eval_sim", ["--model", "m", "--json", "/proc/no/m.json"], "--json /proc/no/m.json: can"),
        ("pose_errors", ["--model", "m", "--json", str(REPO)], f"--json {REPO}: is a folder"),
        (
            "eval_sim",
            ["--model", "m", "--json", str(REPO / "pyproject.toml" / "m.json")],
            f"cannot make its folder ({REPO / 'pyproject.toml'} is a file)",
        ),  # fmt: skip
        ("eval_sim", ["--model", "m", "--seed", str(2**32 + 5)], "argument --seed: expected a wh"),
        ("demo", ["--seed", "-1"], "argument --seed: expected a whole number in [0, 2**32)"),
        ("demo", ["--model", str(REPO / "pyproject.toml")], "demo.py: "),
        ("demo", ["--model", "models/no_such.msgpack"], "--model: no such file or folder"),
        ("split_pairing", ["--val-seed", str(2**63)], "argument --val-seed: expected a whole"),
        ("split_pairing", ["--preset", "bogus"], "argument --preset: invalid choice: 'bogus'"),
        ("overfit_check", ["--set", "nosuch.field=1"], "error: --set: "),
        ("plot_curves", [str(REPO), "--out", "c.png"], "not a training run's workdir"),
        ("plot_curves", [str(REPO), "--out", "c.foo"], "--out c.foo: expected a picture file"),
        ("plot_curves", [str(REPO), "--out", "/proc/no/c.png"], "--out /proc/no/c.png: cannot"),
        (
            "export_model",
            [str(REPO / "models" / "indoorbev_small.msgpack"), "--out", str(REPO)],
            f"cannot write {REPO}: Is a directory",
        ),  # fmt: skip
        (
            "average_models",
            [str(REPO / "models" / "indoorbev_small.msgpack")] * 2 + ["--out", "/proc/no.msgpack"],
            "cannot write /proc/no.msgpack",
        ),  # fmt: skip
    ],
)
def test_scripts_refuse_arguments_they_cannot_run(script, argv, message, capsys):
    """Sizes that used to end in a numpy traceback (footprints of up to 60 cells on a smaller
    grid) or in a division by zero (one answered cloud), and pose_errors' bad arguments or
    model file, are one line, status 2."""
    with pytest.raises(SystemExit) as exit_info:
        _script(script).main(argv)
    assert exit_info.value.code == 2
    assert message in capsys.readouterr().err


@pytest.mark.parametrize("script", ["eval_sim", "pose_errors"])
def test_the_metrics_never_replace_the_model_they_score(script, tmp_path, capsys):
    """``--json`` at the model file replaced it with the metrics, exit 0 (and a run's
    config.json would have gone the same way)."""
    model = tmp_path / "model.msgpack"
    model.write_bytes(b"the model")
    run = tmp_path / "run"
    run.mkdir()
    (run / "config.json").write_text("{}")
    for json_path, model_path in ((model, model), (run / "config.json", run)):
        with pytest.raises(SystemExit) as exit_info:
            _script(script).main(["--model", str(model_path), "--json", str(json_path)])
        assert exit_info.value.code == 2
        assert f"--json {json_path}: is a file of the model {model_path}" in capsys.readouterr().err
    assert model.read_bytes() == b"the model" and (run / "config.json").read_text() == "{}"


def test_exports_never_replace_their_inputs(tmp_path, capsys):
    """``export_model.py RUN --out RUN/config.json`` and ``average_models.py a b --out a``
    replaced what they read, exit 0; a model file exported in place (new thresholds) is
    still fine."""
    run = tmp_path / "run"
    run.mkdir()
    (run / "config.json").write_text("{}")
    a, b = tmp_path / "a.msgpack", tmp_path / "b.msgpack"
    a.write_bytes(b"a")
    b.write_bytes(b"b")
    for script, argv, given in [
        ("export_model", [str(run), "--out", str(run / "config.json")], run),
        ("average_models", [str(a), str(b), "--out", str(b)], b),
    ]:
        with pytest.raises(SystemExit) as exit_info:
            _script(script).main(argv)
        assert exit_info.value.code == 2
        assert f"--out {argv[-1]}: is a file of the model {given}" in capsys.readouterr().err
    assert (run / "config.json").read_text() == "{}" and b.read_bytes() == b"b"
    with pytest.raises(SystemExit) as exit_info:  # in place: refused only as not a model
        _script("export_model").main([str(a), "--out", str(a)])
    assert "not an indoorbev_jax model file" in capsys.readouterr().err


def test_column_check_sweep_names_a_bad_cloud(tmp_path, capsys):
    """A cloud file of a size no point layout has ended in a DatasetError traceback."""
    (tmp_path / "velodyne").mkdir()
    (tmp_path / "velodyne" / "000000.bin").write_bytes(b"abcdefg")
    with pytest.raises(SystemExit) as exit_info:
        _script("column_check_sweep").main(["--folders", str(tmp_path)])
    assert exit_info.value.code == 2
    assert "000000.bin: size 7 bytes is not a multiple of 16" in capsys.readouterr().err


def test_plot_curves_leaves_out_a_torn_last_line_and_refuses_text_or_nothing(tmp_path, capsys):
    """A killed run's log (training drops its torn last line) could not be plotted; a text
    loss drew its panel as categories, upside down; a log of no line drew empty panels."""
    plot = _script("plot_curves")
    log = tmp_path / "metrics.jsonl"
    log.write_text('{"step": 50, "loss": 3.0}\n{"step": 100, "loss": 2.0}\n{"step": 150, "lo')
    assert [r["step"] for r in plot.read_log(tmp_path)["train"]] == [50, 100]
    assert f"warning: {log}:3: a torn last line, left out" in capsys.readouterr().err
    log.write_text('{"step": 50, "loss": 3.0}\n{"step": 100, "loss": "abc"}\n')
    with pytest.raises(ValueError, match=r"metrics\.jsonl:2: field 'loss': expected a number"):
        plot.read_log(tmp_path)
    for text in ("", '{"step": 5, "kind": "val", "pq": 0.5}\n'):
        log.write_text(text)
        with pytest.raises(ValueError, match=r"metrics\.jsonl: holds no train or eval line"):
            plot.read_log(tmp_path)


def test_bench_ros2_phase_with_one_answer_says_so(capsys, monkeypatch):
    bench = _script("bench_ros2")
    received = {}
    monkeypatch.setattr(bench, "_start_detect", lambda model: (None, []))
    monkeypatch.setattr(bench, "_stop_detect", lambda proc, lines: {"frames": 1})

    def run_phase(node, pub, received, clouds, rate, count):
        received[7] = 9  # one of the three stamps answered
        return [5, 6, 7]

    monkeypatch.setattr(bench, "_run_phase", run_phase)
    bench._phase("latency", "m", None, None, received, [], 1.0, 3)
    out = capsys.readouterr().out
    assert "detections for 1, too few to measure (2 needed)" in out


def test_pose_errors_of_the_true_boxes_are_zero_and_pairs_are_by_mask():
    """pose_errors.frame_errors on outputs that are the targets themselves (masks from the
    rasteriser, boxes equal): zero regressed errors, unit IoU, and the fitted box close."""
    import types

    import numpy as np

    from indoorbev_jax.config import GridConfig
    from indoorbev_jax.data.rasterize import rasterize_boxes

    pose = _script("pose_errors")
    grid = GridConfig(x_range=(-2.0, 2.0), y_range=(-2.0, 2.0), cell_size=0.05)
    boxes = np.array([[0.5, 0.5, 1.0, 0.4, 0.3], [-1.0, -0.5, 0.6, 0.5, -1.0]], np.float32)
    _, masks = rasterize_boxes(boxes, np.ones(2, bool), grid)
    masks = np.asarray(masks)
    pos = np.array([[0.5, 0.5, 0.4], [-1.0, -0.5, 0.3]], np.float32)
    dims = np.array([[1.0, 0.4, 0.8], [0.6, 0.5, 1.0]], np.float32)
    yaw = boxes[:, 4]
    targets = types.SimpleNamespace(valid=np.array([True, True, False]),
                                    classes=np.array([0, 3, 9]), pos=np.r_[pos, pos[:1]],
                                    dims=np.r_[dims, dims[:1]], yaw=np.r_[yaw, yaw[:1]],
                                    masks=np.r_[masks, masks[:1]])  # fmt: skip
    # Queries in the other order, plus one whose class differs from its object's.
    panoptic = np.zeros(grid.shape, np.int32)
    panoptic[masks[1]], panoptic[masks[0] & ~masks[1]] = 1, 2  # query q: id q + 1
    panoptic[0, 0] = 3  # the third query's segment
    output = types.SimpleNamespace(segment_valid=np.array([True, True, True]),
                                   det_classes=np.array([3, 0, 5]),
                                   det_masks=masks[[1, 0, 0]], instance_ids=panoptic)  # fmt: skip
    final = types.SimpleNamespace(pos=pos[[1, 0, 0]], dims=dims[[1, 0, 0]],
                                  yaw=yaw[[1, 0, 0], None])  # fmt: skip
    errors = pose.frame_errors(final, output, targets, grid, 0.5)
    np.testing.assert_array_equal(np.sort(errors["class"]), [0, 3])
    for key in ("centre", "size", "h", "z", "yaw"):
        np.testing.assert_allclose(errors[key], 0.0, atol=1e-4)
    np.testing.assert_allclose(errors["IoU"], 1.0, atol=1e-5)
    assert (errors["fit c."] < 0.05).all() and (errors["fit IoU"] > 0.8).all()
    assert (errors["fit size"] < 0.05).all()
    table = pose.summary(errors, ["a", "b", "c", "d"])
    assert table["all"]["matched"] == 2 and table["a"]["matched"] == 1 and "b" not in table
    assert table["all p90"]["centre"] == 0.0 and table["all p90"]["matched"] == 2


def test_eval_sim_z_offset_is_what_predict_does_for_a_lidar_height():
    """eval_sim --z-offset D measures predict --lidar-height H (D = H - nearest trained)."""
    import jax.numpy as jnp
    import numpy as np

    from indoorbev_jax.mount import LidarMount
    from indoorbev_jax.predict import Predictor

    eval_sim = _script("eval_sim")
    cfg = Config.tiny()
    rng = np.random.default_rng(0)
    cloud = rng.uniform([-4, -4, -1.2, 0], [4, 4, 3.0, 1], (500, 4)).astype(np.float32)
    cloud = cloud[np.linalg.norm(cloud[:, :3], axis=1) > 0.5]  # clear of the blind zone
    mount = LidarMount(height=cfg.sim.sensor_height[1] + 0.5)
    predictor = Predictor(cfg, None, intensity="unit", mount=mount)
    padded, valid, counts = predictor.prepare(cloud)
    assert counts["outside_points"] > 0  # the move pushes the top of the cloud out
    points, kept = eval_sim.model_input(jnp.asarray(cloud), jnp.ones(len(cloud), bool), cfg.grid,
                                        z_offset=predictor.z_offset)  # fmt: skip
    np.testing.assert_allclose(np.asarray(points)[np.asarray(kept)], padded[valid], atol=1e-6)


def test_eval_sim_simulates_the_mount_it_is_given(tmp_path, monkeypatch):
    """``--lidar-rpy`` fixes one tilt (no jitter), ``--tilt-jitter`` sets the jitter, and
    without them the model's own ``sim`` mount is simulated."""
    import dataclasses

    from indoorbev_jax.predict import export_model

    eval_sim = _script("eval_sim")
    tiny = Config.tiny()
    trained = dataclasses.replace(tiny.sim, sensor_rpy=(0.0, 10.0, 0.0), sensor_tilt_jitter=5.0)
    trained_config = dataclasses.replace(tiny, sim=trained)
    model = str(export_model(_params(trained_config), trained_config, tmp_path / "m"))
    simulated = []

    def capture(config, *args, **kwargs):
        simulated.append((config.sim.sensor_rpy, config.sim.sensor_tilt_jitter))
        raise KeyboardInterrupt  # stop before any frame is simulated

    monkeypatch.setattr(eval_sim, "evaluate_sim_sweep", capture)
    for flags, expected in (
        ([], ((0.0, 10.0, 0.0), 5.0)),
        (["--lidar-rpy", "0,20,0"], ((0.0, 20.0, 0.0), 0.0)),
        (["--tilt-jitter", "3"], ((0.0, 10.0, 0.0), 3.0)),
        (["--lidar-rpy", "5,0,0", "--tilt-jitter", "2"], ((5.0, 0.0, 0.0), 2.0)),
    ):
        with pytest.raises(KeyboardInterrupt):
            eval_sim.main(["--model", model, "--frames", "2", "--batch", "2", *flags])
        assert simulated.pop() == expected, flags


def test_plot_curves_labels_runs_of_one_name_by_their_paths(tmp_path):
    """Two runs named small (a/small, b/small) were one line: the first was dropped."""
    plot = _script("plot_curves")
    runs = [tmp_path / "a" / "small", tmp_path / "b" / "small", tmp_path / "tiny"]
    assert plot.run_labels(runs) == [str(runs[0]), str(runs[1]), "tiny"]
    (tmp_path / "sw").mkdir()
    (tmp_path / "sw" / "sweep.jsonl").write_text("")
    with pytest.raises(ValueError, match=r"sw/metrics\.jsonl: no such file: .*a sweep's workdir"):
        plot.read_log(tmp_path / "sw")


def test_ctrl_c_stops_an_experiment_script_with_one_line(tmp_path):
    """The experiment scripts called main() bare: Ctrl-C in `make demo` printed a traceback
    of about 45 lines and often crashed with a segmentation fault (XLA compiling)."""
    import os
    import signal
    import subprocess
    import sys

    script = REPO / "experiments" / "demo.py"
    argv = [str(script), "--out", str(tmp_path / "o"), "--frames", "1"]
    code = (  # SIGINT's handler even where it is inherited ignored; then the script as main
        "import runpy, signal, sys; signal.signal(signal.SIGINT, signal.default_int_handler); "
        f"sys.argv = {argv!r}; sys.path.insert(0, {str(script.parent)!r}); "
        f"runpy.run_path({str(script)!r}, run_name='__main__')"
    )
    proc = subprocess.Popen(
        [sys.executable, "-c", code], stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
        env={**os.environ, "JAX_PLATFORMS": "cpu"},
    )  # fmt: skip
    assert proc.stdout.readline().startswith("model: ")  # main runs, under exit_with
    proc.send_signal(signal.SIGINT)
    _, err = proc.communicate(timeout=120)
    assert proc.returncode == 130, err
    assert err.strip().splitlines()[-1] == "demo.py: interrupted"


@pytest.mark.parametrize(
    ("script", "argv", "message"),
    [
        ("sweep", ["--batch-size", "0"], "config field 'train.batch_size': must be > 0, got 0"),
        ("sweep", ["--steps", "10", "--warmup-steps", "100"], "train.warmup_steps"),
        ("train", ["--batch-size", "0"], "config field 'train.batch_size': must be > 0, got 0"),
        ("train", ["--set", "loss.nope=1"], "error: --set: 'loss.nope=1': loss has no field"),
    ],
)
def test_config_values_the_config_refuses_are_one_line(script, argv, message, tmp_path, capsys):
    """sweep.py's --batch-size 0 (or --steps below --warmup-steps) ended in a ConfigError
    traceback, status 1; a bad --set exited 1 without the program's name."""
    extra = ["--learning-rates", "1e-3"] if script == "sweep" else []
    with pytest.raises(SystemExit) as exit_info:
        _script(script).main(["--preset", "tiny", "--workdir", str(tmp_path), *extra, *argv])
    assert exit_info.value.code == 2
    err = capsys.readouterr().err
    assert message in err and "Traceback" not in err and ": error: " in err


def test_a_backend_this_machine_lacks_is_one_line():
    """JAX_PLATFORMS=cuda on a machine without a GPU ended every command in a traceback (a
    bare AssertionError); the console and experiment scripts now say it in one line."""
    import os
    import subprocess
    import sys

    code = "from indoorbev_jax.cli import exit_with; exit_with(lambda: 0, 'probe')"
    env = {**os.environ, "JAX_PLATFORMS": "nosuch"}
    run = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True,
                         env=env, timeout=120)  # fmt: skip
    assert run.returncode == 2, run.stderr
    assert run.stderr.startswith("probe: error: JAX_PLATFORMS=nosuch: no such backend here")
    assert len(run.stderr.strip().splitlines()) == 1


def test_benchmarks_refuse_to_time_a_wrong_answer():
    """A benchmark checks both sides agree before it times them: an identity "matcher" was
    timed and its ratio printed, and a caster 1 % long gave speed-ups with 0 % agreement."""
    import numpy as np
    from scipy.optimize import linear_sum_assignment

    bench = _script("bench_matching")
    rng = np.random.default_rng(3)
    cost = rng.random((4, 6, 5)).astype(np.float32)
    valid = np.ones((4, 5), bool)
    valid[1, 3:] = False
    cols = np.broadcast_to(np.arange(5), (4, 5))
    right = np.zeros((4, 5), np.int64)
    for b in range(4):
        rows, picked = linear_sum_assignment(cost[b][:, valid[b]])
        right[b, np.flatnonzero(valid[b])[picked]] = rows
        right[b, ~valid[b]] = 5  # padded targets: anything
    assert bench._check_totals("ours", right, cols, cost, valid) <= 1e-6
    identity = np.broadcast_to(np.arange(5), (4, 5))
    wrong = r"ours: frame 0 matched 5 targets at total .* linear_sum_assignment 5 at"
    with pytest.raises(SystemExit, match=wrong):
        bench._check_totals("ours", identity, cols, cost, valid)
    # A matcher that leaves a valid target out is refused whatever its total.
    short = "ours: frame 0 matched 4 targets at total .* linear_sum_assignment 5 at"
    with pytest.raises(SystemExit, match=short):
        bench._check_totals("ours", [right[0][:4]], [cols[0][:4]], cost[:1], valid[:1])
    lidar_bench = _script("bench_lidar")
    ok = np.ones(100_000, bool)
    ok[:10] = False  # 1 in 10^4 may disagree (float32 grazing rays)
    lidar_bench.check_agreement("ours", ok)
    ok[10] = False
    with pytest.raises(SystemExit, match="ours: 11 of 100000 rays disagree with mj_multiRay"):
        lidar_bench.check_agreement("ours", ok)


def test_benchmark_ratios_are_the_reference_over_ours_of_the_medians(capsys):
    """The printed speed-up is the reference's median over ours (> 1: ours is faster), as
    docs/BENCHMARKS.md reads them. Both directions of bench_train's sweep row and of
    bench_bag_decode's ratio column printed the inverse and passed every test (a mutation
    audit)."""
    import re

    train = _script("bench_train")
    row = train.sweep_row("tiny", 4, 5.0, [0.1, 0.3, 0.11], [0.4, 0.41, 2.0])
    assert row.endswith("vmapped 110 ms vs 4 sequential 410 ms per round -> 3.73x")
    _script("bench_bag_decode").main(["--points", "3000", "--reps", "2", "--rounds", "2"])
    n, ref_ms, ours_ms, ratio = capsys.readouterr().out.splitlines()[-1].split()
    assert n == "3000" and re.fullmatch(r"\d+x", ratio)
    # The columns are rounded (2 and 3 decimals, the ratio to a whole number): the ratio
    # lies within what the printed columns allow.
    ref, ours = float(ref_ms), float(ours_ms)
    low, high = (ref - 0.005) / (ours + 0.0005), (ref + 0.005) / max(ours - 0.0005, 1e-9)
    assert low - 0.5 <= int(ratio[:-1]) <= high + 0.5, (ref_ms, ours_ms, ratio)


def test_demo_scores_each_frame_against_its_own_ground_truth(tmp_path, capsys, monkeypatch):
    """``make demo`` on two frames: a picture per frame, and the metrics table counts the
    ground truth of both frames (the sum of the per-frame object counts it printed), not
    one frame's twice; without the table the demo would print no metrics at all (a mutation
    audit: both passed, only argument errors were tested)."""
    import re

    _script("demo").main(["--frames", "2", "--out", str(tmp_path)])
    out = capsys.readouterr().out
    counts = [int(n) for n in re.findall(r"^frame \d: \d+ points, (\d+) objects", out, re.M)]
    assert len(counts) == 2 and min(counts) > 0
    assert sorted(p.name for p in tmp_path.iterdir()) == ["frame_0.png", "frame_1.png"]
    assert "AP@0.5" in out
    mean = next(line.split() for line in out.splitlines() if line.startswith("mean "))
    assert int(mean[1]) == sum(counts)
    # Pillow wrote under the picture's name: a Ctrl-C (or a full disk) mid-save left a cut
    # PNG there. A rerun that fails in its first save leaves the earlier picture whole.
    from PIL import Image

    before = (tmp_path / "frame_0.png").read_bytes()

    def full_disk(self, fp, format=None, **params):
        Path(fp).write_bytes(b"\x89PNG partial")
        raise OSError(28, "No space left on device")

    monkeypatch.setattr(Image.Image, "save", full_disk)
    with pytest.raises(OSError, match=r"frame_0\.png: No space left"):
        _script("demo").main(["--frames", "2", "--out", str(tmp_path)])
    assert (tmp_path / "frame_0.png").read_bytes() == before
    assert sorted(p.name for p in tmp_path.iterdir()) == ["frame_0.png", "frame_1.png"]


def test_bench_matching_checks_matches_with_more_targets_than_queries():
    """With more valid targets than queries ``match`` leaves the extra ones at -1, as scipy
    matches only Q of them: the bench's check took -1 as the last query and refused a
    right answer ("matched 8 of 8 targets")."""
    import numpy as np

    from indoorbev_jax.matching import match

    bench = _script("bench_matching")
    cost = np.random.default_rng(5).random((2, 3, 5)).astype(np.float32)
    valid = np.ones((2, 5), bool)
    valid[1, 4] = False
    rows = np.asarray(match(cost, valid)[0])
    assert (rows == -1).any()
    cols = np.broadcast_to(np.arange(5), (2, 5))
    assert bench._check_totals("ours", rows, cols, cost, valid) <= 1e-6


def test_distributed_runs_join_before_training_and_name_a_failed_join(monkeypatch, capsys):
    """--distributed calls jax.distributed.initialize (with the host settings given) before
    the run starts; a failed join, or host settings without --distributed, is one error line
    naming the flag (the docs asked for the call, which no script could make)."""
    import jax

    calls = []

    def initialize(**kwargs):
        calls.append(("initialize", kwargs))
        if kwargs["process_id"] == 7:
            raise RuntimeError("connection refused")

    monkeypatch.setattr(jax.distributed, "initialize", initialize)
    train = _script("train")
    monkeypatch.setattr(train, "train_and_evaluate", lambda *a, **k: calls.append(("train",)))
    hosts = ["--coordinator-address", "10.0.0.1:1234", "--num-processes", "2"]
    argv = ["--workdir", "w", "--preset", "tiny", "--distributed", *hosts, "--process-id"]
    assert train.main(argv + ["1"]) == 0
    settings = {"coordinator_address": "10.0.0.1:1234", "num_processes": 2, "process_id": 1}
    assert calls == [("initialize", settings), ("train",)]
    assert train.main(argv + ["7"]) == 2
    assert "--distributed: jax.distributed.initialize() failed (connection refused)" in (
        capsys.readouterr().err
    )
    calls.clear()
    assert train.main(["--workdir", "w", "--preset", "tiny", "--process-id", "1"]) == 2
    assert "--process-id: only with --distributed" in capsys.readouterr().err and not calls
    sweep = _script("sweep")
    with pytest.raises(SystemExit) as stop:
        sweep.main(["--workdir", "w", "--learning-rates", "1e-3", *hosts])
    assert stop.value.code == 2 and not calls
    assert "--coordinator-address, --num-processes: only with --distributed" in (
        capsys.readouterr().err
    )
    # A sweep's state is not sharded: across hosts its first checkpoint failed, steps lost.
    with pytest.raises(SystemExit) as stop:
        sweep.main(["--workdir", "w", "--learning-rates", "1e-3", "--distributed", *hosts])
    assert stop.value.code == 2 and not calls
    assert "--distributed: a sweep trains its K models in one process on one device" in (
        capsys.readouterr().err
    )


def test_eval_sim_scores_the_split_and_seed_it_is_given(tmp_path, monkeypatch, capsys, full_disk):
    """``--split val`` must simulate the val scenes under ``VAL_SEED`` and the JSON must
    record the seed used. A mutation audit: the split not passed on to the simulator, the
    two default seeds swapped and ``setup.seed`` the default seed all passed."""
    import json

    import indoorbev_sim.generate

    from indoorbev_jax.config import InferenceConfig
    from indoorbev_jax.metrics import Evaluator
    from indoorbev_jax.predict import export_model

    eval_sim = _script("eval_sim")
    model = str(export_model(_params(Config.tiny()), Config.tiny(), tmp_path / "m.msgpack"))
    argv = ["--model", model, "--frames", "2", "--batch", "2", "--no-progress"]
    scored = []

    def capture(config, params, split, frames, batch, seed, inferences, *args):
        scored.append((split, seed))
        return [Evaluator(i, class_names=config.data.class_names) for i in inferences]

    monkeypatch.setattr(eval_sim, "evaluate_sim_sweep", capture)
    # The default seeds of docs/RESULTS.md: test 1000003, val 1000033.
    for flags, expected in (([], ("test", 1_000_003)), (["--split", "val"], ("val", 1_000_033)),
                            (["--split", "val", "--seed", "7"], ("val", 7))):  # fmt: skip
        eval_sim.main([*argv, *flags, "--json", str(tmp_path / "r.json")])
        assert scored.pop() == expected, flags
        setup = json.loads((tmp_path / "r.json").read_text())["setup"]
        assert (setup["split"], setup["seed"]) == expected, flags
    capsys.readouterr()
    # A disk that filled up during the evaluation: one line after the metrics, no traceback.
    with full_disk(), pytest.raises(SystemExit) as stop:
        eval_sim.main([*argv, "--json", str(tmp_path / "full.json")])
    assert stop.value.code == (
        f"eval_sim.py: error: [Errno 28] cannot write {tmp_path / 'full.json'}: No space left "
        "on device (the metrics are printed above)"
    )
    printed = capsys.readouterr().out
    assert "mask threshold" in printed and "metrics written" not in printed
    # evaluate_sim_sweep simulates the split it is given.
    simulated = []

    def generator(config, split, batch):
        simulated.append(split)
        raise KeyboardInterrupt  # stop before anything is compiled

    monkeypatch.setattr(indoorbev_sim.generate, "jitted_generate", generator)
    eval_sim = _script("eval_sim")
    for split in ("val", "test"):
        with pytest.raises(KeyboardInterrupt):
            eval_sim.evaluate_sim_sweep(Config.tiny(), None, split, 2, 2, 0, [InferenceConfig()])
        assert simulated.pop() == split


def test_eval_sim_columns_ranges_and_intensity_are_what_they_say():
    """The sweep line's AP@0.25 column holds AP@0.25, the range rows are the distance in the
    BEV plane (docstring of RANGE_EDGES) and ``--intensity-factor`` scales the intensity. A
    mutation audit: the AP columns swapped, the 3D distance and a factor of 1 all passed."""
    import types

    import jax.numpy as jnp
    import numpy as np

    from indoorbev_jax.config import InferenceConfig

    eval_sim = _script("eval_sim")
    row = {"ap": {"0.25": 0.9, "0.5": 0.5}, "pq": 0.4, "sq": 0.8, "rq": 0.5, "miou": 0.6,
           "semantic_miou": 0.7}  # fmt: skip
    head, line = eval_sim.sweep_table([(InferenceConfig(0.3, 0.5), row)]).splitlines()
    columns = dict(zip(head.split(), line.split(), strict=True))
    assert columns == {"score": "0.3", "mask": "0.5", "AP@0.25": "90.0", "AP@0.50": "50.0",
                       "PQ": "40.0", "SQ": "80.0", "RQ": "50.0", "mIoU": "60.0",
                       "semIoU": "70.0"}  # fmt: skip
    # An object 2.9 m ahead and 1 m up: 2.9 m in the BEV plane (3.07 m in 3D).
    targets = types.SimpleNamespace(pos=np.array([[[2.9, 0.0, 1.0]]], np.float32),
                                    classes=np.array([[0]]),
                                    masks=np.ones((1, 1, 4, 4), bool))  # fmt: skip
    info = types.SimpleNamespace(variant=np.array([[0]]), num_points=np.array([[50]]),
                                 occlusion=np.array([[0]]))  # fmt: skip
    rows = dict((name, names) for name, names, _ in eval_sim.BREAKDOWNS)["range"]
    assert rows[int(eval_sim.frame_tags(targets, info)["range"][0, 0])] == "[2, 3) m"
    # Intensity 0.5 x 2 = 1; z 0.25 + 0.5 = 0.75.
    points = jnp.array([[1.0, 1.0, 0.25, 0.5]])
    tiny = Config.tiny().grid
    moved, kept = eval_sim.model_input(points, jnp.array([True]), tiny, 2.0, 0.5)
    np.testing.assert_allclose(np.asarray(moved), [[1.0, 1.0, 0.75, 1.0]])
    assert bool(kept[0])


def test_pose_errors_compare_rectangles_in_the_bev_plane():
    """A box is a BEV rectangle: the same rectangle given turned 90 degrees with its sides
    swapped has no yaw or size error, a z error is no centre error, and a query of another
    class is no match. IoU must exceed --match-iou, and the p90 row holds 90th percentiles.
    A mutation audit: yaw modulo 180, unsorted sides, the 3D centre error, matching across
    classes, IoU >= and the medians in the p90 row all passed."""
    import types

    import numpy as np

    from indoorbev_jax.config import GridConfig
    from indoorbev_jax.data.rasterize import rasterize_boxes

    pose = _script("pose_errors")
    grid = GridConfig(x_range=(-2.0, 2.0), y_range=(-2.0, 2.0), cell_size=0.05)
    _, masks = rasterize_boxes(np.array([[0.8, -0.4, 1.0, 0.4, 0.3]], np.float32),
                               np.ones(1, bool), grid)  # fmt: skip
    masks = np.asarray(masks)
    targets = types.SimpleNamespace(valid=np.array([True]), classes=np.array([0]),
                                    pos=np.array([[0.8, -0.4, 0.4]], np.float32),
                                    dims=np.array([[1.0, 0.4, 0.8]], np.float32),
                                    yaw=np.array([0.3], np.float32), masks=masks)  # fmt: skip
    # Query 0: class 5 on the object's mask, 1 m off; query 1: class 0, the rectangle as
    # width x length turned 90 degrees, 0.5 m too high. Only query 1 may match.
    panoptic = np.where(masks[0], 2, 0).astype(np.int32)  # query q: segment q + 1
    panoptic[0, 0] = 1  # query 0's segment: a corner cell
    output = types.SimpleNamespace(segment_valid=np.array([True, True]),
                                   det_classes=np.array([5, 0]), det_masks=masks[[0, 0]],
                                   instance_ids=panoptic)  # fmt: skip
    final = types.SimpleNamespace(pos=np.array([[1.8, -0.4, 0.4], [0.8, -0.4, 0.9]], np.float32),
                                  dims=np.array([[1.0, 0.4, 0.8], [0.4, 1.0, 0.8]], np.float32),
                                  yaw=np.array([[0.3], [0.3 + np.pi / 2]], np.float32))  # fmt: skip
    errors = pose.frame_errors(final, output, targets, grid, 0.5)
    assert errors["class"].tolist() == [0]
    for key, expected in (("centre", 0.0), ("yaw", 0.0), ("size", 0.0), ("z", 0.5), ("h", 0.0),
                          ("IoU", 1.0)):  # fmt: skip
        np.testing.assert_allclose(errors[key], [expected], atol=1e-4, err_msg=key)
    # The rasterised footprint's centroid is the box centre (x 0.8, y -0.4) within a cell.
    assert errors["gt c."][0] < grid.cell_size
    # Mask IoU exactly 1/2 (one cell of two) is no match at --match-iou 0.5: it must exceed.
    gt = np.zeros((1, 4, 4), bool)
    gt[0, 0, :2] = True
    d, g = pose.match_frame(gt & np.eye(4, dtype=bool)[0], np.array([0]), gt, np.array([0]), 0.5)
    assert len(d) == len(g) == 0
    d, g = pose.match_frame(gt, np.array([0]), gt, np.array([0]), 0.5)
    assert (d.tolist(), g.tolist()) == ([0], [0])
    # 0, 1, ..., 9: median 4.5, 90th percentile 8.1 (linear interpolation, 0.9 x 9).
    errors = {k: np.arange(10.0) for k in pose.COLUMNS} | {"class": np.zeros(10, int)}
    table = pose.summary(errors, ["a"])
    assert table["all"]["centre"] == 4.5
    np.testing.assert_allclose(table["all p90"]["centre"], 8.1)


def test_split_pairing_pairs_frame_i_of_each_set_and_counts_the_test_objects(monkeypatch):
    """split_pairing compares val frame i with test frame i and counts the test set's
    objects. A mutation audit: val batch k + 1 against test batch k and the objects counted
    from val passed. Fake draws: each frame's layout kind and variants are its key's."""
    import collections

    import jax
    import numpy as np

    pairing = _script("split_pairing")
    Scene = collections.namedtuple("Scene", "on variant prims room")
    Prims = collections.namedtuple("Prims", "dims")
    Room = collections.namedtuple("Room", "kind")

    def jitted_draw(config, split, batch):
        def draw(key):
            mark = int(np.asarray(jax.random.key_data(key)).sum() % 100_000)
            on = np.zeros((batch, 3), bool)
            on[:, : 3 if split == "test" else 2] = True  # 3 test objects a frame, 2 val ones
            variant = np.full((batch, 3), mark)
            prims = Prims(np.zeros((batch, 3, 3), np.float32))
            return (Scene(on, variant, prims, Room(np.full(batch, mark))),)

        return draw

    monkeypatch.setattr(pairing.generate, "jitted_draw", jitted_draw)
    # One root for both sets (--val-seed = the test seed, 1000003): frame i of each set has
    # the same key, so all 4 frames share the layout kind and every val object (2 a frame)
    # is a twin; the test set has 3 objects a frame.
    counts = pairing.main(["--val-seed", "1000003", "--frames", "4", "--batch", "2"])
    assert counts == {"frames": 4, "same layout kind": 4, "test objects": 12, "twins in val": 8}


def test_plot_curves_draws_every_quantity_a_training_log_holds(tmp_path, monkeypatch):
    """Each panel gets the points of its key in a run's metrics.jsonl, whose eval lines
    train.py writes as ``f"ap{threshold}"`` for the thresholds 0.25 and 0.5: "ap0.25",
    "ap0.5". A mutation audit: the AP@0.50 panel reading "ap0.50" (empty) passed."""
    import json

    import matplotlib.axes

    plot = _script("plot_curves")
    run = tmp_path / "run"
    run.mkdir()
    rows = [{"step": s, "kind": "train", "loss": 1.0 / s, "dice_final": 0.5 / s}
            for s in (1, 2, 3)]  # fmt: skip
    rows += [{"step": s, "kind": "eval", "ap0.25": 0.1 * s, "ap0.5": 0.05 * s, "pq": 0.1,
              "miou": 0.2} for s in (2, 3)]  # fmt: skip
    (run / "metrics.jsonl").write_text("".join(json.dumps(r) + "\n" for r in rows))
    drawn = []
    real = matplotlib.axes.Axes.plot

    def count(self, x, y, *args, **kwargs):
        drawn.append(len(x))
        return real(self, x, y, *args, **kwargs)

    monkeypatch.setattr(matplotlib.axes.Axes, "plot", count)
    plot.main([str(run), "--out", str(tmp_path / "curves.png")])
    # 3 train lines, 2 eval lines.
    assert dict(zip([t for _, _, t in plot.PANELS], drawn, strict=True)) == {
        "training loss": 3, "train dice loss (last layer)": 3, "val AP@0.25": 2,
        "val AP@0.50": 2, "val PQ": 2, "val mIoU": 2}  # fmt: skip


def test_distributed_joins_before_the_platform_check_starts_the_backends(tmp_path):
    """Under JAX_PLATFORMS other than cpu (cuda, tpu: a cluster's usual setting) the
    command's platform check calls jax.devices(), after which JAX refuses to join a
    multi-host run: --distributed always failed there ("must be called before any JAX
    calls"). A one-process run on this CPU ("cpu,cpu" takes the same path) now joins and
    goes on to read its data."""
    import os
    import socket
    import subprocess
    import sys

    with socket.socket() as s:
        s.bind(("localhost", 0))
        port = s.getsockname()[1]
    env = {**os.environ, "JAX_PLATFORMS": "cpu,cpu"}
    argv = ["--workdir", str(tmp_path / "w"), "--preset", "tiny", "--data", str(tmp_path / "no"),
            "--distributed", "--coordinator-address", f"localhost:{port}",
            "--num-processes", "1", "--process-id", "0"]  # fmt: skip
    done = subprocess.run([sys.executable, str(REPO / "experiments" / "train.py"), *argv],
                          env=env, capture_output=True, text=True, timeout=300)  # fmt: skip
    assert done.returncode == 2, done.stderr
    assert "must be called before" not in done.stderr
    assert "train.py: error: " in done.stderr and f"{tmp_path / 'no'}" in done.stderr
