"""``make demo``: simulate indoor scenes, run IndoorBEV, write BEV pictures, print metrics.

Scenes come from the simulator's held-out test layouts. The network is the shipped
``small`` checkpoint (``models/indoorbev_small.msgpack``) when the repository has one;
otherwise a freshly initialised network runs, which says so, and whose metrics are ~0.
"""

from __future__ import annotations

import argparse
import time
from pathlib import Path

import jax
import numpy as np

from indoorbev_jax import fileio, viz
from indoorbev_jax.checks import check_folder
from indoorbev_jax.cli import HelpFormatter, positive_int, seed_int
from indoorbev_jax.config import Config
from indoorbev_jax.data import kitti
from indoorbev_jax.metrics import Evaluator
from indoorbev_jax.predict import Predictor, load_model, render_prediction, to_labels

REPO = Path(__file__).resolve().parents[1]
SHIPPED = REPO / "models" / "indoorbev_small.msgpack"


def targets_to_labels(targets, k: int) -> kitti.ObjectLabels:
    valid = np.asarray(targets.valid[k])
    return kitti.ObjectLabels(
        classes=np.asarray(targets.classes[k])[valid],
        dims=np.asarray(targets.dims[k])[valid],
        pos=np.asarray(targets.pos[k])[valid],
        yaw=np.asarray(targets.yaw[k])[valid],
        occlusion=np.zeros(int(valid.sum())),
    )


def main(argv=None) -> None:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0], formatter_class=HelpFormatter)
    p.add_argument(
        "--out", default="demo_out", help="folder for frame_<k>.png (ground truth | prediction)"
    )
    p.add_argument(
        "--frames", type=positive_int, default=4, help="held-out test frames to simulate and run"
    )
    p.add_argument(
        "--model",
        help="model file or run directory (default: the repository's "
        "models/indoorbev_small.msgpack; an untrained network runs when the repository has none)",
    )
    p.add_argument(
        "--seed",
        type=seed_int,
        default=2026,
        help="seed of the simulated scenes (and of the untrained network's initialisation)",
    )
    args = p.parse_args(argv)
    from indoorbev_sim.generate import jitted_generate

    try:  # now, not after the simulation (a FileExistsError traceback)
        out = check_folder("--out", args.out)
        out.mkdir(parents=True, exist_ok=True)
    except (OSError, ValueError) as e:
        p.exit(2, f"demo.py: {e}\n")
    if args.model is not None and not Path(args.model).exists():  # a typo must not run untrained
        p.exit(2, f"demo.py: --model: no such file or folder: {args.model}\n")
    model = Path(args.model) if args.model is not None else SHIPPED
    if model.exists():
        try:
            config, params = load_model(model)
        except (OSError, ValueError) as e:  # not a model file: one line, as eval_sim's
            p.exit(2, f"demo.py: {e}\n")
        print(f"model: {model}")
    else:
        from indoorbev_jax.train import init_state

        config = Config.small()
        params = init_state(config, jax.random.key(args.seed)).params
        print(f"model: no checkpoint at {model}; running an UNTRAINED network")

    start = time.perf_counter()
    batch, _ = jitted_generate(config, "test", args.frames)(jax.random.key(args.seed))
    batch = jax.device_get(batch)
    print(f"simulated {args.frames} frames in {time.perf_counter() - start:.1f} s "
          f"(held-out test layouts, {config.sim.pattern} pattern)")  # fmt: skip

    predictor = Predictor(config, params)
    evaluator = Evaluator(config.inference, class_names=config.data.class_names)
    names = config.data.class_names
    for k in range(args.frames):
        valid = np.asarray(batch.point_valid[k])
        points = np.asarray(batch.points[k])[valid]
        t0 = time.perf_counter()
        padded, pvalid, final, output, bev = predictor(points)
        ms = 1e3 * (time.perf_counter() - t0)
        evaluator.add_output(
            jax.tree.map(lambda x: x[None], output),
            jax.tree.map(lambda x, k=k: x[k : k + 1], batch.targets),
        )
        labels, ids = to_labels(final, output, "mask", config.grid)
        truth = viz.render_bev(
            points, targets_to_labels(batch.targets, k), np.asarray(batch.targets.instance_ids[k]),
            config.grid, names, min_size=400,
        )  # fmt: skip
        pic = render_prediction(config, padded, pvalid, output, bev, labels, ids)
        picture = viz.panels([("ground truth", truth), ("prediction", pic)])
        path = out / f"frame_{k}.png"
        # A Ctrl-C mid-save left a cut PNG under its name.
        fileio.atomic_write(path, lambda tmp, pic=picture: pic.save(tmp, format="PNG"))
        n_gt = int(np.asarray(batch.targets.valid[k]).sum())
        print(f"frame {k}: {len(points)} points, {n_gt} objects, {len(labels)} predicted, "
              f"{ms:.0f} ms -> {path}")  # fmt: skip
    print("metrics against the simulator's ground truth (simulated data, not the paper's "
          "real-world test set):")  # fmt: skip
    print(evaluator.table())


if __name__ == "__main__":
    from indoorbev_jax.cli import exit_with

    exit_with(main, "demo.py")  # Ctrl-C: one line and status 130
