"""Inference on your own scans: ``indoorbev predict MODEL INPUT --out DIR``.

MODEL is a run directory (``config.json`` + orbax checkpoints; the best checkpoint is
used) or a model file written by ``export_model`` (one msgpack file holding the config and
the parameters, what ``make demo`` ships). INPUT is a ``.bin`` file, a KITTI-style folder
(``velodyne/``) or a ROS 2 bag folder holding sensor_msgs/PointCloud2 of any field layout
with x, y, z and optional intensity, or Livox's livox_ros_driver2/CustomMsg.

Per frame, DIR receives ``label_2/<id>.txt`` (KITTI lines with a 16th score field, one per
predicted segment), ``mask_2/<id>.png`` (16-bit ids, id k + 1 = line k) and
``pictures/<id>.png`` (raw points | axis-fusion feature map | predicted masks | final BEV);
optionally a bag with the input clouds and the predictions as MarkerArray.
"""

from __future__ import annotations

import dataclasses
import json
import os
import statistics
import time
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np

from indoorbev_jax import viz
from indoorbev_jax.config import Config
from indoorbev_jax.data import kitti
from indoorbev_jax.data.dataset import pad_points
from indoorbev_jax.inference import apply_views, panoptic_inference, unview_cells
from indoorbev_jax.models import IndoorBEV

MODEL_FORMAT = "indoorbev_jax-model-v1"

# The model reads intensity as the simulator makes it: reflectivity x cos(incidence), in
# [0, 1]. Drivers report other units; each factor maps one onto that (then clipped to [0, 1]).
INTENSITY_UNITS = {
    "unit": 1.0,  # already reflectivity in [0, 1]: the simulator and its exports
    "livox": 1 / 150,  # Livox: 0-150 = 0-100 % Lambertian reflectivity, 151-255 retro-reflectors
    "percent": 1 / 100,  # reflectivity in % (e.g. RoboSense: 0-100 diffuse, 101-255 retro)
}


def intensity_factor(units: str | float, points: np.ndarray) -> float:
    """The factor that maps ``points``' intensity (column 3) in ``units`` onto [0, 1].

    Args:
      units: a name of ``INTENSITY_UNITS``, a number (the factor itself), or "auto": "unit"
        when every finite intensity is at most 1, else "livox" (the MID-360's driver).
      points: float [N, 4].
    """
    if units == "auto":
        intensity = np.asarray(points)[:, 3]
        high = np.isfinite(intensity) & (intensity > 1.0)
        return INTENSITY_UNITS["livox"] if high.any() else 1.0
    if isinstance(units, str):
        if units not in INTENSITY_UNITS:
            raise ValueError(
                f"intensity units {units!r}: expected 'auto', one of {sorted(INTENSITY_UNITS)} "
                f"or a number"
            )
        return INTENSITY_UNITS[units]
    factor = float(units)
    if not (np.isfinite(factor) and factor >= 0):
        raise ValueError(f"intensity factor {units!r}: expected a finite number >= 0")
    return factor


def normalize_intensity(points: np.ndarray, factor: float) -> np.ndarray:
    """float32 [N, 4], intensity times ``factor`` clipped to [0, 1] (the simulator's range)."""
    points = np.array(points, np.float32).reshape(-1, 4)
    points[:, 3] = np.clip(points[:, 3] * np.float32(factor), 0.0, 1.0)
    return points


def export_model(params: Any, config: Config, path: str | os.PathLike) -> Path:
    """Writes config + parameters as one msgpack file (atomically)."""
    from flax import serialization

    payload = {
        "format": MODEL_FORMAT,
        "config": config.to_json(),
        "params": jax.tree.map(np.asarray, params),
    }
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_name(path.name + ".tmp")
    tmp.write_bytes(serialization.msgpack_serialize(payload))
    os.replace(tmp, path)
    return path


def load_model(path: str | os.PathLike) -> tuple[Config, Any]:
    """(config, params) from a run directory or an exported model file."""
    from flax import serialization

    path = Path(path)
    if path.is_dir():
        from indoorbev_jax.train import load_params

        return load_params(path)
    if not path.exists():
        raise FileNotFoundError(f"{path}: no such model file or run directory")
    try:
        payload = serialization.msgpack_restore(path.read_bytes())
    except Exception as e:  # noqa: BLE001 - any decoding failure means a bad file
        raise ValueError(f"{path}: not an indoorbev_jax model file ({e})") from None
    if not isinstance(payload, dict) or payload.get("format") != MODEL_FORMAT:
        raise ValueError(f"{path}: not an indoorbev_jax model file (format {MODEL_FORMAT})")
    return Config.from_dict(json.loads(payload["config"])), payload["params"]


def with_thresholds(
    config: Config,
    score_threshold: float | None = None,
    mask_threshold: float | None = None,
    views: tuple[str, ...] | None = None,
) -> Config:
    """``config`` with the inference settings that are given (not None) replaced: the
    thresholds and the test-time views (``config.VIEWS``); a bad one raises ``ConfigError``
    naming the field."""
    chosen = {"score_threshold": score_threshold, "mask_threshold": mask_threshold,
              "views": None if views is None else tuple(views)}  # fmt: skip
    chosen = {k: v for k, v in chosen.items() if v is not None}
    if not chosen:
        return config
    return dataclasses.replace(config, inference=dataclasses.replace(config.inference, **chosen))


# The config sections that fix what a parameter means; the rest (training, loss, inference
# thresholds) may differ between models that are averaged.
ARCHITECTURE_SECTIONS = ("grid", "encoder", "backbone", "head")


def average_models(paths: list[str | os.PathLike]) -> tuple[Config, Any]:
    """(config, params): the uniform average of the parameters of ``paths`` (a "model soup").

    Meant for runs continued from one common model, whose average usually lies in the same
    basin and validates better than each. The config is the first model's; every model must
    share its ``ARCHITECTURE_SECTIONS`` and parameter shapes, or the error names the file and
    the field or parameter that differs.

    Args:
      paths: model files or run directories (``load_model``), at least two.
    """
    if len(paths) < 2:
        raise ValueError(f"average_models: expected at least two models, got {len(paths)}")
    first_path, *rest = paths
    config, first = load_model(first_path)
    pairs, treedef = jax.tree_util.tree_flatten_with_path(first)
    flat_first = dict(pairs)
    total = {k: np.array(v, np.float64) for k, v in flat_first.items()}  # a copy
    for path in rest:
        other_config, params = load_model(path)
        for section in ARCHITECTURE_SECTIONS:
            mine, theirs = getattr(config, section), getattr(other_config, section)
            if mine != theirs:
                field = next(
                    f for f in mine.__dataclass_fields__ if getattr(mine, f) != getattr(theirs, f)
                )
                raise ValueError(
                    f"{path}: {section}.{field} = {getattr(theirs, field)!r}, but "
                    f"{first_path} has {getattr(mine, field)!r}; only models of one "
                    f"architecture can be averaged"
                )
        flat = dict(jax.tree_util.tree_flatten_with_path(params)[0])
        for key in flat_first.keys() | flat.keys():
            name = jax.tree_util.keystr(key)
            if key not in flat or key not in flat_first:
                where = path if key not in flat else first_path
                raise ValueError(f"{where}: no parameter {name}; the models differ in structure")
            if np.shape(flat[key]) != np.shape(flat_first[key]):
                raise ValueError(
                    f"{path}: parameter {name} has shape {np.shape(flat[key])}, but "
                    f"{first_path} has {np.shape(flat_first[key])}"
                )
            total[key] += np.asarray(flat[key], np.float64)
    leaves = [(total[k] / len(paths)).astype(np.asarray(v).dtype) for k, v in flat_first.items()]
    return config, jax.tree_util.tree_unflatten(treedef, leaves)


def iter_frames(path: str | os.PathLike, topic: str | None = None) -> Iterator:
    """Yields (frame id, points [N, 4], stamp ns or None, frame name) from INPUT."""
    path = Path(path)
    if path.is_file() and path.suffix == ".bin":
        yield path.stem, kitti.read_points(path), None, "lidar"
    elif (path / "velodyne").is_dir():
        for bin_path in sorted((path / "velodyne").glob("*.bin")):
            yield bin_path.stem, kitti.read_points(bin_path), None, "lidar"
    elif (path / "metadata.yaml").exists():
        from indoorbev_jax.rosbag import read_clouds

        for k, (stamp, frame, points) in enumerate(read_clouds(path, topic)):
            yield f"{k:06d}", points, stamp, frame
    else:
        raise ValueError(
            f"{path}: expected a .bin file, a KITTI-style folder with velodyne/, or a "
            f"ROS 2 bag folder with metadata.yaml"
        )


class Predictor:
    """A jitted model + panoptic inference for one frame at a time (static shapes).

    ``intensity`` gives the units of the clouds' intensity (``intensity_factor``); each
    cloud's intensity is mapped onto the simulator's [0, 1] before the model sees it.
    """

    def __init__(self, config: Config, params: Any, intensity: str | float = "auto"):
        self.config = config
        self.params = params
        intensity_factor(intensity, np.zeros((0, 4), np.float32))  # bad units fail here
        self.intensity = intensity
        self.last_counts: dict[str, int] = {}
        self.last_intensity_factor = 1.0
        model = IndoorBEV(config)
        views = config.inference.views

        def run(params, points, valid):
            predictions, state = apply_views(
                model,
                params,
                points,
                valid,
                config.inference,
                capture_intermediates=lambda mdl, _: mdl.name == "encoder",
            )
            output = panoptic_inference(predictions, config.inference)
            # The first view's features, mapped back to the lidar frame.
            bev = state["intermediates"]["encoder"]["__call__"][0][: points.shape[0]]
            bev = jnp.moveaxis(unview_cells(jnp.moveaxis(bev, -1, 0), views[0]), 0, -1)
            final = jax.tree.map(lambda x: x[-1], predictions)
            return final, output, bev

        self._run = jax.jit(run)

    def prepare(self, points: np.ndarray) -> tuple[np.ndarray, np.ndarray, dict[str, int]]:
        """A raw cloud as the model takes it: (points padded [N, 4] with intensity in [0, 1],
        valid [N], ``pad_points``' counts of non-finite, out-of-workspace and dropped points
        (past ``data.max_points``, thinned evenly)). Also kept as ``last_counts``, and the
        intensity's factor as ``last_intensity_factor``."""
        cfg = self.config
        self.last_intensity_factor = intensity_factor(self.intensity, points)
        points = normalize_intensity(points, self.last_intensity_factor)
        padded, valid, self.last_counts = pad_points(points, cfg.grid, cfg.data.max_points)
        return padded, valid, self.last_counts

    def __call__(self, points: np.ndarray):
        """(points padded [N, 4], valid, final-layer predictions, panoptic output, BEV
        features [H, W, C]) of one raw cloud (``prepare``), all numpy, batch axis removed."""
        padded, valid, _ = self.prepare(points)
        return (padded, valid, *self.infer(padded, valid))

    def infer(self, padded: np.ndarray, valid: np.ndarray):
        """(final-layer predictions, panoptic output, BEV features [H, W, C]) of one
        ``prepare``d cloud, all numpy, batch axis removed."""
        final, output, bev = self._run(self.params, padded[None], valid[None])
        final, output, bev = jax.device_get((final, output, bev))
        one = lambda tree: jax.tree.map(lambda x: np.asarray(x)[0], tree)  # noqa: E731
        return one(final), one(output), np.asarray(bev)[0]


def to_labels(final, output) -> tuple[kitti.ObjectLabels, np.ndarray]:
    """Predicted segments as labels with scores, and the panoptic map renumbered so that
    id k + 1 is label line k."""
    queries = np.flatnonzero(output.segment_valid)
    labels = kitti.ObjectLabels(
        classes=output.det_classes[queries],
        dims=np.abs(final.dims[queries]),
        pos=final.pos[queries],
        yaw=final.yaw[queries, 0],
        occlusion=np.zeros(len(queries)),
        scores=output.det_scores[queries],
    )
    remap = np.zeros(output.instance_ids.max(initial=0) + 1, np.int32)
    remap[queries + 1] = np.arange(1, len(queries) + 1)
    return labels, remap[output.instance_ids]


def render_prediction(config: Config, points, valid, output, bev, labels, ids):
    grid, names = config.grid, config.data.class_names
    scale = viz.picture_scale(grid, min_size=400)
    pts = points[valid]
    raw = viz.render_bev(pts, None, None, grid, names, min_size=400)
    feats = viz.grid_image(viz.feature_image(bev), scale)
    masks = viz.grid_image(
        viz.masks_image(output.det_masks & output.det_valid[:, None, None]), scale
    )
    final = viz.render_bev(pts, labels, ids, grid, names, min_size=400)
    return viz.panels(
        [
            ("raw points (height)", raw),
            ("axis-fusion features (PCA)", viz.Image.fromarray(feats)),
            ("query masks", viz.Image.fromarray(masks)),
            ("panoptic BEV", final),
        ]
    )


def predict(
    model_path: str | os.PathLike,
    input_path: str | os.PathLike,
    out: str | os.PathLike,
    *,
    topic: str | None = None,
    bag_out: str | os.PathLike | None = None,
    pictures: bool = True,
    verbose: bool = True,
    intensity: str | float = "auto",
    views: tuple[str, ...] | None = None,
) -> dict:
    """Runs the model over INPUT and writes labels, masks, pictures (and a bag).

    ``intensity``: the units of INPUT's intensity (``intensity_factor``; "auto" reads values
    above 1 as Livox reflectivity 0-255). ``views``: test-time views (``config.VIEWS``;
    None: the model file's ``inference.views``).

    Returns:
      ``{"frames", "latency_ms": {"median", "p90", "max"}, "objects", "thinned_frames"}``;
      latency is the jitted model + inference time per frame, the first (compiling) frame
      excluded; ``thinned_frames`` counts the frames with more valid points than
      ``data.max_points`` (each kept ``max_points``, evenly spread).
    """
    config, params = load_model(model_path)
    config = with_thresholds(config, views=views)
    predictor = Predictor(config, jax.tree.map(jnp.asarray, params), intensity)
    out = Path(out)
    names = config.data.class_names
    latencies, objects, frames, thinned = [], 0, 0, 0
    factors_said = set()
    bag_frames = []
    for frame_id, points, stamp, frame_name in iter_frames(input_path, topic):
        start = time.perf_counter()
        padded, valid, final, output, bev = predictor(points)
        ms = 1e3 * (time.perf_counter() - start)
        if frames:
            latencies.append(ms)
        frames += 1
        labels, ids = to_labels(final, output)
        objects += len(labels)
        kitti.write_mask(out / "mask_2" / f"{frame_id}.png", ids)
        kitti.write_labels(out / "label_2" / f"{frame_id}.txt", labels, names)
        if pictures:
            pic = render_prediction(config, padded, valid, output, bev, labels, ids)
            (out / "pictures").mkdir(parents=True, exist_ok=True)
            pic.save(out / "pictures" / f"{frame_id}.png")
        if bag_out is not None:
            bag_frames.append((stamp, frame_name, points, labels))
        dropped = predictor.last_counts["dropped_points"]
        thinned += int(dropped > 0)
        factor = predictor.last_intensity_factor
        if verbose and factor != 1.0 and factor not in factors_said:
            factors_said.add(factor)
            print(
                f"{frame_id}: intensity scaled by {factor:.6g} and clipped to [0, 1], the "
                f"simulator's reflectivity range ({intensity!r} units; --intensity sets them)"
            )
        if verbose:
            note = (
                f"; {dropped} of {dropped + config.data.max_points} valid points left out "
                f"(data.max_points={config.data.max_points}, the rest spread over the scan)"
                if dropped
                else ""
            )
            print(f"{frame_id}: {len(labels)} objects, {ms:.1f} ms{note}")
    if frames == 0:
        raise ValueError(f"{input_path}: no frames found")
    if bag_out is not None:
        write_prediction_bag(bag_out, bag_frames, names)
    summary = {"frames": frames, "objects": objects, "thinned_frames": thinned}
    if latencies:
        lat = np.asarray(latencies)
        summary["latency_ms"] = {
            "median": float(statistics.median(lat)),
            "p90": float(np.percentile(lat, 90)),
            "max": float(lat.max()),
        }
    if verbose:
        lat = summary.get("latency_ms")
        tail = f", median {lat['median']:.1f} ms/frame (first frame compiles)" if lat else ""
        print(f"{frames} frames, {objects} objects written to {out}{tail}")
        if thinned:
            print(
                f"{thinned} frames had more valid points than data.max_points="
                f"{config.data.max_points}: each kept that many, evenly spread"
            )
    return summary


def write_prediction_bag(bag: str | os.PathLike, frames: list, names) -> None:
    """Input clouds on ``/points`` and predictions on ``/detections`` (MarkerArray)."""
    from indoorbev_jax.rosbag import write_bag

    stamped = (
        (stamp if stamp is not None else (k + 1) * 100_000_000, frame, points, labels)
        for k, (stamp, frame, points, labels) in enumerate(frames)
    )
    write_bag(bag, stamped, names, "/points", "/detections")
