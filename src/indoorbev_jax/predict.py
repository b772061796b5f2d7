"""Inference on your own scans: ``indoorbev predict MODEL INPUT --out DIR``.

MODEL is a run directory (``config.json`` + orbax checkpoints; the best checkpoint is
used) or a model file written by ``export_model`` (one msgpack file holding the config and
the parameters, what ``make demo`` ships). INPUT is a ``.bin``, ``.pcd`` (PCL, ascii or
binary) or ``.npy`` file, a folder of them, a KITTI-style folder (``velodyne/``) or a ROS 2
bag folder holding sensor_msgs/PointCloud2 of any field layout
with x, y, z and optional intensity, or Livox's livox_ros_driver2/CustomMsg.

Per frame, DIR receives ``label_2/<id>.txt`` (KITTI lines with a 16th score field, one per
predicted segment), ``mask_2/<id>.png`` (16-bit ids, id k + 1 = line k) and
``pictures/<id>.png`` (raw points | axis-fusion feature map | predicted masks | final BEV);
optionally a bag with the input clouds and the predictions as MarkerArray.
"""

from __future__ import annotations

import dataclasses
import functools
import hashlib
import json
import os
import statistics
import sys
import time
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np

from indoorbev_jax import fileio, viz
from indoorbev_jax.boxes import check_box_source, segment_boxes
from indoorbev_jax.config import Config, GridConfig
from indoorbev_jax.data import kitti
from indoorbev_jax.data.clouds import SUFFIXES as CLOUD_SUFFIXES
from indoorbev_jax.data.clouds import read_cloud
from indoorbev_jax.data.dataset import pad_points
from indoorbev_jax.geometry import as_points, in_workspace, usable, wrap_angle
from indoorbev_jax.inference import apply_views, panoptic_inference, unview_cells
from indoorbev_jax.interrupts import check_interrupted
from indoorbev_jax.models import IndoorBEV
from indoorbev_jax.mount import LEVEL, LidarMount, check_level_frame

MODEL_FORMAT = "indoorbev_jax-model-v1"
MODEL_FIELDS = ("format", "config", "params", "sha256")  # sha256: absent in older files

# The model reads intensity as the simulator makes it: reflectivity x cos(incidence), in
# [0, 1]. Drivers report other units; each factor maps one onto that (then clipped to [0, 1]).
INTENSITY_UNITS = {
    "unit": 1.0,  # already reflectivity in [0, 1]: the simulator and its exports
    "livox": 1 / 150,  # Livox: 0-150 = 0-100 % Lambertian reflectivity, 151-255 retro-reflectors
    "percent": 1 / 100,  # reflectivity in % (e.g. RoboSense: 0-100 diffuse, 101-255 retro)
}


def check_intensity_units(units: str | float) -> None:
    """Raises ``ValueError`` unless ``units`` is "auto", a name of ``INTENSITY_UNITS`` or a
    finite number >= 0 (``intensity_factor``'s ``units``)."""
    if isinstance(units, str):
        if units != "auto" and units not in INTENSITY_UNITS:
            raise ValueError(
                f"intensity units {units!r}: expected 'auto', one of {sorted(INTENSITY_UNITS)} "
                f"or a number"
            )
        return
    factor = float(units)
    if not (np.isfinite(factor) and factor >= 0):
        raise ValueError(f"intensity factor {units!r}: expected a finite number >= 0")


def intensity_factor(units: str | float, points: np.ndarray) -> float:
    """The factor that maps ``points``' intensity (column 3) in ``units`` onto [0, 1].

    Args:
      units: a name of ``INTENSITY_UNITS``, a number (the factor itself), or "auto": "unit"
        when every finite intensity is at most 1, else "livox" (the MID-360's driver).
      points: float [N, 4].
    """
    check_intensity_units(units)
    if units == "auto":
        intensity = np.asarray(points)[:, 3]
        high = np.isfinite(intensity) & (intensity > 1.0)
        return INTENSITY_UNITS["livox"] if high.any() else 1.0
    if isinstance(units, str):
        return INTENSITY_UNITS[units]
    return float(units)


def normalize_intensity(points: np.ndarray, factor: float) -> np.ndarray:
    """float32 [N, 4], intensity times ``factor`` clipped to [0, 1] (the simulator's range).
    Unusable points (``geometry.usable``) keep theirs, so ``pad_points`` still counts them."""
    points = as_points(points).copy()
    scaled = np.clip(points[:, 3] * np.float32(factor), 0.0, 1.0)
    points[:, 3] = np.where(usable(points), scaled, points[:, 3])
    return points


def export_model(params: Any, config: Config, path: str | os.PathLike) -> Path:
    """Writes config + parameters as one msgpack file (atomically), with the sha256 of both
    (``load_model`` checks it)."""
    from flax import serialization

    text, params = config.to_json(), jax.tree.map(np.asarray, params)
    payload = {"format": MODEL_FORMAT, "config": text, "params": params,
               "sha256": _model_file_digest(text, params)}  # fmt: skip
    path = Path(path)
    data = serialization.msgpack_serialize(payload)
    fileio.atomic_write(path, lambda tmp: tmp.write_bytes(data))  # names path if it fails
    return path


def load_model(path: str | os.PathLike, *, check: bool = True) -> tuple[Config, Any]:
    """(config, params) from a run directory or an exported model file.

    A file's config and parameters must match the sha256 it was written with (files
    written before ``export_model`` stored one have none), its config must hold every field
    but ``config.OPTIONAL_FIELDS``, and its parameters must be the tree of arrays that
    config's network has, name for name, shape for shape and dtype for dtype (``check``;
    ``train.with_pretrained`` checks them against the run's network instead), or a
    ``ValueError`` names the file and what differs.
    """
    from flax import serialization

    path = Path(path)
    if path.is_dir():
        from indoorbev_jax.train import load_params

        return load_params(path)
    if not path.exists():
        raise FileNotFoundError(f"{path}: no such model file or run directory")
    kitti.check_regular_file(path, "a model file")  # a pipe blocked the read forever
    data = path.read_bytes()  # an OSError names the file and says why (not "not a model")
    try:
        payload = serialization.msgpack_restore(data)
    except Exception as e:  # noqa: BLE001 - any decoding failure means a bad file
        raise ValueError(f"{path}: not an indoorbev_jax model file ({e})") from None
    if not isinstance(payload, dict) or payload.get("format") != MODEL_FORMAT:
        raise ValueError(f"{path}: not an indoorbev_jax model file (format {MODEL_FORMAT})")
    # A flipped byte in the key "sha256" made a checked file read as an older, unchecked one.
    unknown = sorted(map(str, payload.keys() - MODEL_FIELDS))
    if unknown:
        raise ValueError(
            f"{path}: unexpected field(s) {', '.join(map(repr, unknown))}, expected only "
            f"{', '.join(MODEL_FIELDS)} (a damaged copy, or a newer indoorbev_jax's file)"
        )
    text, params = payload.get("config"), payload.get("params")
    if not isinstance(text, str) or not isinstance(params, dict):
        raise ValueError(
            f"{path}: not an indoorbev_jax model file (expected a config text and a tree of "
            f"parameters, got {type(text).__name__} and {type(params).__name__})"
        )
    # Files written before the checksum lack it; a flipped byte in theirs goes unseen.
    if "sha256" in payload and payload["sha256"] != _model_file_digest(text, params):
        raise ValueError(
            f"{path}: its config and parameters do not match the sha256 written with them "
            "(a damaged copy): copy or export the model again"
        )
    try:
        settings = json.loads(text)
    except json.JSONDecodeError as e:
        raise ValueError(f"{path}: its config is not valid JSON ({e})") from None
    config = Config.from_file_dict(settings, path)
    if check:
        differences = param_differences(params, param_shapes(config), "its config's model")
        if differences:
            raise ValueError(f"{path}: {differences[0][2]}")
    return config, params


@functools.lru_cache(maxsize=4)
def param_shapes(config: Config) -> Any:
    """The parameter tree of ``config``'s network, as shapes (traced, nothing computed)."""
    n = config.data.max_points
    inputs = jax.ShapeDtypeStruct((1, n, 4), jnp.float32), jax.ShapeDtypeStruct((1, n), bool)
    return jax.eval_shape(IndoorBEV(config).init, jax.random.key(0), *inputs)


def param_differences(have: Any, want: Any, whose: str) -> list[tuple[Any, str, str]]:
    """Where parameter tree ``have`` differs from ``want`` (arrays or shapes), in key path
    order: (key path, kind "missing" / "extra" / "shape" / "dtype", the problem in words,
    saying ``whose`` model ``want`` is)."""
    have = dict(jax.tree_util.tree_flatten_with_path(have)[0])
    want = dict(jax.tree_util.tree_flatten_with_path(want)[0])
    out = []
    for path in sorted(want.keys() | have.keys(), key=jax.tree_util.keystr):
        name = jax.tree_util.keystr(path)
        if path not in have:
            out.append((path, "missing", f"parameter {name} is missing"))
        elif path not in want:
            out.append((path, "extra", f"parameter {name} is not in {whose}"))
        elif np.shape(have[path]) != tuple(want[path].shape):
            shape = np.shape(have[path])
            problem = f"parameter {name} has shape {shape}, {whose} expects {want[path].shape}"
            out.append((path, "shape", problem))
        elif _dtype(have[path]) != want[path].dtype:
            # An int or float16 tree of the right shapes ran with truncated weights.
            dtype = _dtype(have[path])
            problem = f"parameter {name} has dtype {dtype}, {whose} expects {want[path].dtype}"
            out.append((path, "dtype", problem))
    return out


def _dtype(x: Any) -> np.dtype:
    return np.dtype(x.dtype) if hasattr(x, "dtype") else np.asarray(x).dtype


def with_thresholds(
    config: Config,
    score_threshold: float | None = None,
    mask_threshold: float | None = None,
    views: tuple[str, ...] | str | None = None,
) -> Config:
    """``config`` with the inference settings that are given (not None) replaced: the
    thresholds and the test-time views (``config.VIEWS``; one name alone, "identity", is
    one view, not its letters); a bad one raises ``ConfigError`` naming the field."""
    views = (views,) if isinstance(views, str) else views
    chosen = {"score_threshold": score_threshold, "mask_threshold": mask_threshold,
              "views": None if views is None else tuple(views)}  # fmt: skip
    chosen = {k: v for k, v in chosen.items() if v is not None}
    if not chosen:
        return config
    return dataclasses.replace(config, inference=dataclasses.replace(config.inference, **chosen))


# The config sections that fix what a parameter means; the rest (training, loss, inference
# thresholds) may differ between models that are averaged.
ARCHITECTURE_SECTIONS = ("grid", "encoder", "backbone", "head")


def average_models(
    paths: list[str | os.PathLike], sensor_rpy: tuple[float, float, float] | None = None
) -> tuple[Config, Any]:
    """(config, params): the uniform average of the parameters of ``paths`` (a "model soup").

    Meant for runs continued from one common model, whose average usually lies in the same
    basin and validates better than each. The config is the first model's; every model must
    share its ``ARCHITECTURE_SECTIONS`` and parameter shapes, or the error names the file and
    the field or parameter that differs. The lidar heights the average was trained on
    (``sim.sensor_height``, which predict's ``--lidar-height`` treats as trained) are the
    span of all the models' heights. Models trained for different lidar tilts
    (``sim.sensor_rpy``) need ``sensor_rpy``: the tilt the average is recorded for (what
    ``eval_sim.py`` scores by default and predict's tilt note compares with); the tilt jitter
    recorded (``sim.sensor_tilt_jitter``) is the largest of the models'.

    Args:
      paths: model files or run directories (``load_model``), at least two.
      sensor_rpy: the average's ``sim.sensor_rpy`` (default: the models' common one).
    """
    if len(paths) < 2:
        raise ValueError(f"average_models: expected at least two models, got {len(paths)}")
    first_path, *rest = paths
    config, first = load_model(first_path)
    pairs, treedef = jax.tree_util.tree_flatten_with_path(first)
    flat_first = dict(pairs)
    total = {k: np.array(v, np.float64) for k, v in flat_first.items()}  # a copy
    lo, hi = config.sim.sensor_height
    jitter = config.sim.sensor_tilt_jitter
    for path in rest:
        other_config, params = load_model(path)
        tilts = [LidarMount(*c.sim.sensor_rpy).rotation() for c in (other_config, config)]
        if sensor_rpy is None and not np.allclose(*tilts, rtol=0.0, atol=1e-9):
            raise ValueError(
                f"{path}: sim.sensor_rpy = {other_config.sim.sensor_rpy!r}, but {first_path} "
                f"has {config.sim.sensor_rpy!r}; models trained for different lidar tilts "
                "average into a model for no one tilt: say which tilt to record "
                "(--sensor-rpy ROLL,PITCH,YAW)"
            )
        if other_config.data.class_names != config.data.class_names:
            # The class head's rows mean these classes: rows of other classes must not mix.
            raise ValueError(
                f"{path}: data.class_names = {other_config.data.class_names!r}, but "
                f"{first_path} has {config.data.class_names!r}; only models of one class "
                "list can be averaged"
            )
        lo = min(lo, other_config.sim.sensor_height[0])
        hi = max(hi, other_config.sim.sensor_height[1])
        jitter = max(jitter, other_config.sim.sensor_tilt_jitter)
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
        # load_model checked each tree against its config, and the configs' architectures
        # are equal: the trees are alike, name for name and shape for shape.
        flat = dict(jax.tree_util.tree_flatten_with_path(params)[0])
        for key in flat_first:
            total[key] += np.asarray(flat[key], np.float64)
    leaves = [(total[k] / len(paths)).astype(np.asarray(v).dtype) for k, v in flat_first.items()]
    sim = dataclasses.replace(config.sim, sensor_height=(lo, hi), sensor_tilt_jitter=jitter)
    if sensor_rpy is not None:
        sim = dataclasses.replace(sim, sensor_rpy=tuple(map(float, sensor_rpy)))
    config = dataclasses.replace(config, sim=sim)
    return config, jax.tree_util.tree_unflatten(treedef, leaves)


@dataclasses.dataclass(frozen=True)
class Frame:
    """One input scan: ``points`` float32 [N, 4], or ``error`` when it cannot be read."""

    frame_id: str  # output file stem: the cloud file's stem, or the bag message's index
    points: np.ndarray | None
    log_ns: int | None = None  # a bag's record time
    stamp_ns: int | None = None  # a bag message's header stamp
    frame_name: str = "lidar"
    error: Exception | None = None


def _file_frames(paths: list[Path]) -> Iterator[Frame]:
    for path in paths:
        try:  # a name like a cloud's on no file is a bad frame too (read_cloud's check)
            yield Frame(path.stem, read_cloud(path))
        except (ValueError, OSError) as e:  # DatasetError, or an unreadable file
            yield Frame(path.stem, None, error=e)
        except MemoryError as e:  # the machine's trouble, not the file's: stop, naming it
            e.add_note(f"while reading {path}")
            raise
        except Exception as e:  # a damage no check foresaw: still one bad frame, named
            error = kitti.DatasetError(f"{path}: unreadable ({type(e).__name__}: {e})")
            yield Frame(path.stem, None, error=error)


def _cloud_files(folder: Path) -> list[Path]:
    """The ``.bin`` / ``.pcd`` / ``.npy`` entries of a folder, by name; two of one stem would
    write the same outputs, so they are refused. Entries so named that are no file (a folder,
    a dangling symlink) are kept: ``_file_frames`` makes them bad frames, named."""
    files = sorted(
        p for p in folder.iterdir()
        if p.suffix.lower() in CLOUD_SUFFIXES and not kitti.is_hidden(p)
    )  # fmt: skip
    stems: dict[str, Path] = {}
    for p in files:
        if p.stem in stems:
            raise ValueError(f"{stems[p.stem]} and {p.name}: two clouds named {p.stem!r}")
        stems[p.stem] = p
    return files


def _bag_frames(path: Path, topic: str | None) -> Iterator[Frame]:
    from indoorbev_jax.rosbag import iter_clouds

    for c in iter_clouds(path, topic):
        frame_id = f"{c.index:06d}"
        yield Frame(frame_id, c.points, c.log_ns, c.stamp_ns, c.frame_id or "lidar", c.error)


def _is_bag_folder(path: Path) -> bool:
    return path.is_dir() and (path / "metadata.yaml").exists()


def open_input(path: str | os.PathLike, topic: str | None = None) -> tuple[int, Iterator[Frame]]:
    """(number of frames, an iterator of ``Frame``) over INPUT: a ``.bin``, ``.pcd`` or
    ``.npy`` file (``data.clouds``), a folder of them (frames in name order), a KITTI-style
    folder (``velodyne/*.bin``) or a ROS 2 bag folder. A frame that cannot be read
    comes with its ``error`` set, so that a caller may skip it; a bad INPUT path raises.
    A bag's ``.db3`` / ``.mcap`` file is read on its own when no ``metadata.yaml`` lies beside
    it (a Foxglove recording, a recovered killed one)."""
    path = Path(path)
    storage_file = path.is_file() and path.suffix.lower() in (".db3", ".mcap")
    if storage_file and (path.parent / "metadata.yaml").exists():
        # One file of a bag may hold only part of it: read the whole bag.
        raise ValueError(f"{path}: a storage file of the bag {path.parent}; pass that folder")
    is_bag = storage_file or _is_bag_folder(path)
    if topic is not None and path.exists() and not is_bag:
        raise ValueError(f"{path}: --topic {topic} applies to ROS 2 bag input only")
    if path.is_file() and path.suffix.lower() in CLOUD_SUFFIXES:
        return 1, _file_frames([path])
    if (path / "velodyne").is_dir():
        files = _cloud_files(path / "velodyne")
        if not files:
            raise ValueError(
                f"{path / 'velodyne'}: no {', '.join(CLOUD_SUFFIXES)} cloud files in it"
            )
        return len(files), _file_frames(files)
    if is_bag:
        from indoorbev_jax.rosbag import count_clouds

        return count_clouds(path, topic), _bag_frames(path, topic)
    if not path.exists():
        raise FileNotFoundError(f"{path}: no such file or folder")
    files = _cloud_files(path) if path.is_dir() else []
    if files:
        return len(files), _file_frames(files)
    raise ValueError(
        f"{path}: expected a .bin, .pcd or .npy file, a folder of them, a KITTI-style folder "
        "with velodyne/, a ROS 2 bag folder with metadata.yaml, or a lone .mcap / .db3 file"
    )


def _damaged_outputs(label_path: Path, mask_path: Path, picture_path, config: Config):
    """Why a frame written by an earlier run cannot be kept, or None: its files must read,
    and the mask's ids must be exactly 1..(label lines), as ``to_labels`` writes them (an
    emptied label file would otherwise be kept as a frame without objects)."""
    try:
        labels = kitti.read_labels(label_path, config.data)
        ids = kitti.read_mask(mask_path, config.grid.shape)
    except (ValueError, OSError) as e:  # DatasetError names the file
        return str(e)
    if picture_path:
        try:
            with viz.Image.open(picture_path) as im:
                im.verify()
        except (OSError, ValueError, SyntaxError) as e:  # what PIL raises for broken files
            return f"{picture_path}: not a readable PNG ({type(e).__name__}: {e})"
    present = np.unique(ids[ids > 0])
    if not np.array_equal(present, np.arange(1, len(labels) + 1)):
        return (
            f"{mask_path} holds ids {present.tolist()[:5]}{'...' if len(present) > 5 else ''} "
            f"but {label_path} has {len(labels)} lines"
        )
    return None


def iter_frames(path: str | os.PathLike, topic: str | None = None) -> Iterator:
    """Yields (frame id, points [N, 4], stamp ns or None, frame name) from INPUT; the stamp
    is a bag message's header stamp (its record time when the header has none), None for
    files. The first frame that cannot be read raises (``open_input`` goes on past it)."""
    for frame in open_input(path, topic)[1]:
        if frame.error is not None:
            raise frame.error
        stamp = frame.stamp_ns if frame.stamp_ns is not None else frame.log_ns
        yield frame.frame_id, frame.points, stamp, frame.frame_name


class Predictor:
    """A jitted model + panoptic inference for one frame at a time (static shapes).

    ``intensity`` gives the units of the clouds' intensity (``intensity_factor``); each
    cloud's intensity is mapped onto the simulator's [0, 1] before the model sees it. With
    "auto", the first cloud with an intensity above 1 switches the stream to Livox units for
    good, so that a later dark scan (all values <= 1) is not read as [0, 1] reflectivity.
    ``mount`` (``mount.LidarMount``) levels the clouds of a tilted lidar and moves one
    mounted outside the trained heights to the nearest; ``labels`` undoes the height move.
    """

    def __init__(
        self,
        config: Config,
        params: Any,
        intensity: str | float = "auto",
        mount: LidarMount = LEVEL,
    ):
        self.config = config
        self.params = params
        self.mount = mount
        self.z_offset = mount.z_offset(config.sim.sensor_height)
        check_intensity_units(intensity)  # bad units fail here, not at the first frame
        self.intensity = intensity
        self.last_counts: dict[str, int] = {}
        self.last_intensity_factor = 1.0
        self._auto_factor = 1.0  # "auto": Livox once a cloud has shown intensity above 1
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
        in the mount's level frame, valid [N], ``pad_points``' counts of non-finite,
        blind-zone (within ``sim.min_range``), out-of-workspace and dropped points (past
        ``data.max_points``, thinned evenly)). Also kept as ``last_counts``, and the
        intensity's factor as ``last_intensity_factor``."""
        cfg = self.config
        points = self.mount.apply(points, cfg.sim.sensor_height)
        # "auto" reads the workspace's usable points only: a garbage frame's (1e30 m, NaN,
        # an intensity of 1e25) values must not switch the units of every later frame.
        usable_here = in_workspace(points, cfg.grid) & usable(points)
        factor = intensity_factor(self.intensity, points[usable_here])
        if self.intensity == "auto":
            self._auto_factor = factor = min(factor, self._auto_factor)
        self.last_intensity_factor = factor
        points = normalize_intensity(points, factor)
        padded, valid, self.last_counts = pad_points(
            points, cfg.grid, cfg.data.max_points, cfg.sim.min_range, (0.0, 0.0, self.z_offset)
        )
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

    def labels(self, final, output, boxes: str = "mask") -> tuple[kitti.ObjectLabels, np.ndarray]:
        """``to_labels`` of one ``infer``red frame, in the mount's level frame: the height
        correction's z offset is taken back off the boxes."""
        labels, ids = to_labels(final, output, boxes, self.config.grid)
        labels.pos[:, 2] -= self.z_offset
        return labels, ids


def to_labels(
    final, output, boxes: str = "head", grid: GridConfig | None = None
) -> tuple[kitti.ObjectLabels, np.ndarray]:
    """Predicted segments as labels with scores, and the panoptic map renumbered so that
    id k + 1 is label line k.

    Args:
      final, output: one frame's final-layer predictions and panoptic output (numpy).
      boxes: ``"head"``: the regressed boxes; ``"mask"``: x, y, length, width and yaw of
        the rectangle around the largest piece of each object's segment in the panoptic map
        (``boxes.segment_boxes``; needs ``grid``), z and height from the head. Yaw is
        wrapped to [-pi, pi) either way.
    """
    check_box_source(boxes)
    queries = np.flatnonzero(output.segment_valid)
    dims = np.abs(final.dims[queries]).astype(np.float32)
    pos = np.array(final.pos[queries], np.float32)
    yaw = np.array(final.yaw[queries, 0], np.float32)
    if boxes == "mask":
        if grid is None:
            raise ValueError('boxes="mask" needs the grid the masks lie on')
        fitted = segment_boxes(output.instance_ids, queries + 1, grid)
        pos[:, :2], dims[:, :2], yaw[:] = fitted[:, :2], fitted[:, 2:4], fitted[:, 4]
    labels = kitti.ObjectLabels(
        classes=output.det_classes[queries],
        dims=dims,
        pos=pos,
        yaw=wrap_angle(yaw),
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


PREDICT_FORMAT = "indoorbev_jax-predict-v1"
# What --out holds from a predict run, per frame; predict.json says which run wrote them.
OUTPUT_DIRS = {"label_2": ".txt", "mask_2": ".png", "pictures": ".png"}


def model_fingerprint(config: Config, params: Any) -> str:
    """sha256 of the config and every parameter's bytes: the same model, the same hash
    (``Config.stable_dict``: also the hash older versions gave it, so their runs resume)."""
    digest = hashlib.sha256(json.dumps(config.stable_dict(), indent=2).encode())
    return _hash_params(digest, params).hexdigest()


def _model_file_digest(text: str, params: Any) -> str:
    """The sha256 a model file stores: of its config text as written and its parameters."""
    return _hash_params(hashlib.sha256(text.encode()), params).hexdigest()


def _hash_params(digest: Any, params: Any) -> Any:
    """``digest`` updated with every parameter's key path, dtype, shape and bytes."""
    for path, leaf in jax.tree_util.tree_flatten_with_path(params)[0]:
        leaf = np.asarray(leaf)
        digest.update(f"{jax.tree_util.keystr(path)}{leaf.dtype}{leaf.shape}".encode())
        digest.update(np.ascontiguousarray(leaf).tobytes())
    return digest


def _remove_stale_temporaries(out: Path, min_age: float = 60.0) -> None:
    """What a kill -9 mid-write left of this run's outputs (``min_age`` seconds old); no
    run reads it."""
    for d, ext in OUTPUT_DIRS.items():
        fileio.remove_stale_temporaries(out / d, f"*{ext}", min_age)
    fileio.remove_stale_temporaries(out, "predict.json", min_age)


def _prepare_out(out: Path, run: dict, overwrite: bool, check_only: bool = False) -> None:
    """Checks that ``out`` holds nothing but this run's outputs (then they are resumed), or
    clears the earlier outputs when ``overwrite``; writes ``predict.json``. A
    ``predict.json`` without outputs (a run stopped before its first frame) is replaced.
    ``check_only``: the refusals alone, writing nothing (before the lock is taken)."""
    manifest = out / "predict.json"
    ours = [p for d, ext in OUTPUT_DIRS.items() for p in (out / d).glob(f"*{ext}")]
    if manifest.exists():
        try:
            saved = json.loads(manifest.read_text())
        except (OSError, ValueError) as e:
            saved = {"unreadable": str(e)}
        if not isinstance(saved, dict):  # a JSON list (COCO results), null, a string
            saved = {"unreadable": f"not a JSON object but a {type(saved).__name__}"}
        if "model" in saved:
            saved.setdefault("boxes", "head")  # runs before the entry wrote the head's boxes
        if saved == run:
            if not check_only:
                _remove_stale_temporaries(out)
            return
        # A run stopped before its first frame (Ctrl-C while compiling) left only its
        # predict.json: nothing to mix, so another run's settings may take the folder.
        # Another tool's (or an unreadable) predict.json is never replaced unasked.
        if not overwrite and (ours or saved.get("format") != PREDICT_FORMAT):
            diff = sorted(k for k in run.keys() | saved.keys() if run.get(k) != saved.get(k))
            shown = ", ".join(f"{k}: {saved.get(k)!r} -> {run.get(k)!r}" for k in diff)
            raise ValueError(
                f"{out} holds the predictions of another run ({shown}); pass --overwrite to "
                f"replace them, or choose another --out"
            )
    elif ours and not overwrite:
        raise ValueError(
            f"{out} already holds {len(ours)} label, mask or picture files that no predict run "
            f"wrote (no predict.json); pass --overwrite to replace them, or choose another --out"
        )
    if check_only:
        return
    if overwrite:
        for path in ours:
            path.unlink()
    _remove_stale_temporaries(out)
    fileio.atomic_write(manifest, lambda p: p.write_text(json.dumps(run, indent=1) + "\n"))


def _eta(seconds: float) -> str:
    seconds = int(round(seconds))
    return f"{seconds // 3600}:{seconds // 60 % 60:02d}:{seconds % 60:02d}"


def _first_ids(ids: list[str], limit: int = 10) -> str:
    """The first ``limit`` ids, and how many more there are."""
    more = f", ... ({len(ids) - limit} more)" if len(ids) > limit else ""
    return ", ".join(ids[:limit]) + more


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
    skip_bad_frames: bool = False,
    overwrite: bool = False,
    boxes: str = "mask",
    mount: LidarMount = LEVEL,
    level_frame: str | None = None,
) -> dict:
    """Runs the model over INPUT and writes labels, masks, pictures (and a bag).

    Every file is written atomically, a frame's label last, and ``out/predict.json`` names
    the model, the input and the settings: the same command after a kill resumes, skipping
    the frames whose outputs are there. ``out`` must be empty or hold the outputs of the same
    run; ``overwrite`` clears another run's label, mask and picture files first.

    Args:
      intensity: the units of INPUT's intensity (``intensity_factor``; "auto" reads values
        above 1 as Livox reflectivity 0-255).
      views: test-time views (``config.VIEWS``; None: the model file's
        ``inference.views``).
      bag_out: also write the input clouds (with their header stamps) on ``/points`` and
        the predictions (as in ``label_2``) on ``/detections``; an existing folder is only
        replaced when it is such a bag (``rosbag.check_bag_target``).
      skip_bad_frames: a frame that cannot be read is reported and skipped (else the
        error names it and stops the run).
      boxes: where the label boxes' x, y, length, width and yaw come from (``to_labels``):
        ``"mask"``, the rectangle around each object's segment (the default: several times
        closer to the true box on the simulated test set, docs/RESULTS.md), or ``"head"``,
        the regressed box.
      mount: how the lidar sits (``mount.LidarMount``; default level, read as it is);
        with a rotation, every output is in its level frame, and ``bag_out`` writes the
        levelled clouds with the detections under ``level_frame`` (then required) as their
        frame id.

    Returns:
      ``{"frames", "latency_ms": {"median", "p90", "max"}, "objects", "thinned_frames",
      "resumed_frames", "bad_frames", "empty_frames"}``; latency is the jitted model +
      inference time per frame, the first (compiling) frame excluded; ``thinned_frames``
      counts the frames with more valid points than ``data.max_points`` (each kept
      ``max_points``, evenly spread); ``bad_frames`` lists the ids of skipped frames,
      ``empty_frames`` those with no valid point in the workspace.
    """
    check_intensity_units(intensity)  # bad units fail first
    check_box_source(boxes)
    if bag_out is not None or level_frame:
        check_level_frame(mount, level_frame)
    config, params = load_model(model_path)
    fingerprint = model_fingerprint(config, params)  # the model file's, before --views
    config = with_thresholds(config, views=views)
    out = Path(out)
    total, frames_in = open_input(input_path, topic)
    _check_out_paths(input_path, out, bag_out)
    run = {
        "format": PREDICT_FORMAT,
        "model": fingerprint,
        "input": str(Path(input_path).resolve()),
        "topic": topic,
        "intensity": intensity,
        "views": list(config.inference.views),
        "boxes": boxes,
    }
    if effect := mount.effect(config.sim.sensor_height):  # none: as older runs read clouds
        run["mount"] = effect
    # A second run into this --out is refused while one runs: both wrote every frame. A
    # folder refused as another's outputs is refused before the lock leaves a file in it
    # (and checked again under the lock, which another run may have held meanwhile).
    _prepare_out(out, run, overwrite, check_only=True)
    with fileio.hold_folder(out, "predict run", "--out"):
        run_started = time.time()
        _prepare_out(out, run, overwrite)
        predictor = Predictor(config, jax.tree.map(jnp.asarray, params), intensity, mount)
        say = functools.partial(print, flush=True) if verbose else (lambda *a, **k: None)
        if mount != LEVEL:
            say(f"lidar mount: {mount.describe(config.sim.sensor_height)}")
        for hint in mount.notes(config):
            print(f"note: {hint}", file=sys.stderr, flush=True)
        if level_frame and bag_out is None:
            print(f"note: --level-frame {level_frame!r} names the frame of --bag-out's messages; "
                  "without --bag-out it is unused (KITTI labels carry no frame id)",
                  file=sys.stderr, flush=True)  # fmt: skip
        job = _PredictRun(predictor, out, total, pictures, boxes, skip_bad_frames, say)
        if bag_out is not None:
            from indoorbev_jax.rosbag import write_bag

            names = config.data.class_names
            write_bag(bag_out, job.run(frames_in, level_frame), names, "/points", "/detections")
        else:
            for _ in job.run(frames_in, level_frame):
                pass
        _remove_stale_temporaries(out, fileio.age_since(run_started))
        return job.finish(input_path)


def _check_out_paths(input_path, out: Path, bag_out) -> None:
    """Refuses an ``--out`` or ``--bag-out`` that would replace INPUT (or each other)."""
    if out.resolve() == Path(input_path).resolve():
        raise ValueError(f"--out {out} is INPUT: its label_2/ and mask_2/ would be replaced")
    if bag_out is None:
        return
    from indoorbev_jax.rosbag import check_bag_target, check_partial

    bag, source = Path(bag_out).resolve(), Path(input_path).resolve()
    for other, what in ((source, "INPUT"), (out.resolve(), "--out")):
        if bag == other or bag in other.parents:
            raise ValueError(f"--bag-out {bag_out} would replace {what} {other}")
    if _is_bag_folder(source) and source in bag.parents:
        raise ValueError(f"--bag-out {bag_out} lies inside the INPUT bag {source}")
    check_bag_target(bag_out, ("/points", "/detections"))
    try:  # a bag another run is writing: said before any frame is predicted
        check_partial(Path(bag_out))
    except FileExistsError as e:
        raise ValueError(str(e)) from None


class _PredictRun:
    """One ``predict`` run over its frames: predicts each (or keeps a finished one), prints
    its line and keeps the summary ``predict`` returns."""

    def __init__(
        self,
        predictor: Predictor,
        out: Path,
        total: int,
        pictures: bool,
        boxes: str,
        skip_bad: bool,
        say: Callable[[str], None],
    ):
        self.predictor, self.config = predictor, predictor.config
        self.out, self.total, self.pictures, self.boxes = out, total, pictures, boxes
        self.skip_bad, self.say = skip_bad, say
        grid, mount = self.config.grid, predictor.mount
        z_range = [z - predictor.z_offset for z in grid.z_range]  # in the cloud's height
        self.workspace = f"x {list(grid.x_range)}, y {list(grid.y_range)}, z {z_range} m"
        if mount.rotated:
            self.workspace += " in the level frame (--lidar-rpy)"
        self.summary = {"frames": 0, "objects": 0, "thinned_frames": 0, "resumed_frames": 0,
                        "bad_frames": [], "empty_frames": []}  # fmt: skip
        self.latencies: list[float] = []
        self.compiled = False
        self.factors_said: set[float] = set()
        self.started = time.perf_counter()

    def run(self, frames_in: Iterator[Frame], level_frame: str | None) -> Iterator:
        """Yields each frame's (log time ns, frame id, points, labels, stamp ns), the
        messages of ``--bag-out``, once its outputs are written."""
        summary, out, config, mount = self.summary, self.out, self.config, self.predictor.mount
        for position, frame in enumerate(frames_in, 1):
            check_interrupted()
            count = f"[{position}/{self.total}] {frame.frame_id}"
            if frame.error is not None:
                if not self.skip_bad:
                    raise type(frame.error)(
                        f"{frame.error} (frame {frame.frame_id}; --skip-bad-frames skips it)"
                    ) from None
                summary["bad_frames"].append(frame.frame_id)
                print(f"{count}: skipped: {frame.error}", file=sys.stderr, flush=True)
                continue
            label_path = out / "label_2" / f"{frame.frame_id}.txt"
            mask_path = out / "mask_2" / f"{frame.frame_id}.png"
            picture_path = out / "pictures" / f"{frame.frame_id}.png"
            wanted = [label_path, mask_path] + ([picture_path] if self.pictures else [])
            summary["frames"] += 1
            done = all(p.exists() for p in wanted)
            picture = self.pictures and picture_path
            damage = done and _damaged_outputs(label_path, mask_path, picture, config)
            if damage:  # a power cut or an edit: predicted again below
                print(f"{count}: {damage}; predicting it again", file=sys.stderr, flush=True)
            if done and not damage:
                summary["resumed_frames"] += 1
                # No model call, but the cloud is read as the first run read it: "auto"
                # intensity units carry over to later frames (a resumed run read a dark Livox
                # scan after them in other units), and the summary counts it again.
                _, valid, counts = self.predictor.prepare(frame.points)
                self._tally(frame, valid, counts)
            else:
                self.say(self._predict(frame, count, label_path, mask_path, picture_path))
            labels = kitti.read_labels(label_path, config.data)  # what the bag gets too
            summary["objects"] += len(labels)
            default_ns = position * 100_000_000  # 10 Hz for inputs without times
            log_ns = frame.log_ns if frame.log_ns is not None else default_ns
            if mount.rotated:  # the bag's cloud in the detections' frame
                yield log_ns, level_frame, mount.levelled(frame.points), labels, frame.stamp_ns
            else:
                yield log_ns, frame.frame_name, frame.points, labels, frame.stamp_ns

    def _tally(self, frame: Frame, valid, counts) -> str:
        """Counts a thinned or empty frame into the summary; the note its line gets."""
        config, summary = self.config, self.summary
        dropped = counts["dropped_points"]
        summary["thinned_frames"] += int(dropped > 0)
        note = (
            f"; {dropped} of {dropped + config.data.max_points} valid points left out "
            f"(data.max_points={config.data.max_points}, the rest spread over the scan)"
            if dropped
            else ""
        )
        if not valid.any():
            summary["empty_frames"].append(frame.frame_id)
            note += (
                f"; warning: none of its {len(frame.points)} points is valid "
                f"({counts['nonfinite_points']} non-finite, {counts['blind_points']} within "
                f"sim.min_range={config.sim.min_range} m of the sensor, "
                f"{counts['outside_points']} outside the workspace {self.workspace}): check "
                "the cloud's frame and units"
            )
        return note

    def _predict(self, frame: Frame, count: str, label_path, mask_path, picture_path) -> str:
        """Predicts one frame and writes its outputs, its label file last; its line."""
        predictor, summary = self.predictor, self.summary
        start = time.perf_counter()
        padded, valid, _ = predictor.prepare(frame.points)
        final, output, bev = predictor.infer(padded, valid)
        ms = 1e3 * (time.perf_counter() - start)
        if self.compiled:  # the first model call of this process compiles: not timed
            self.latencies.append(ms)
        self.compiled = True
        labels, ids = predictor.labels(final, output, self.boxes)
        kitti.write_mask(mask_path, ids)
        if self.pictures:
            pic = render_prediction(self.config, padded, valid, output, bev, labels, ids)
            fileio.atomic_write(picture_path, lambda p: pic.save(p, format="PNG"))
        kitti.write_labels(label_path, labels, self.config.data.class_names)  # marks it done
        note = self._tally(frame, valid, predictor.last_counts)
        factor = predictor.last_intensity_factor
        if factor != 1.0 and factor not in self.factors_said:
            self.factors_said.add(factor)
            self.say(
                f"{frame.frame_id}: intensity scaled by {factor:.6g} and clipped to [0, 1], "
                f"the simulator's reflectivity range ({predictor.intensity!r} units; "
                "--intensity sets them)"
            )
        done = summary["frames"] - summary["resumed_frames"]
        left = self.total - (summary["frames"] + len(summary["bad_frames"]))
        eta = (time.perf_counter() - self.started) / done * left
        objects = f"{len(labels)} object" + ("" if len(labels) == 1 else "s")
        return f"{count}: {objects}, {ms:.1f} ms{note} (ETA {_eta(eta)})"

    def finish(self, input_path) -> dict:
        """The summary, said; a run that found no frame is an error naming INPUT."""
        summary, say, config = self.summary, self.say, self.config
        frames = summary["frames"]
        if frames == 0:
            bad = f" ({len(summary['bad_frames'])} unreadable)" if summary["bad_frames"] else ""
            raise ValueError(f"{input_path}: no frames found{bad}")
        if self.latencies:
            lat = np.asarray(self.latencies)
            summary["latency_ms"] = {
                "median": float(statistics.median(lat)),
                "p90": float(np.percentile(lat, 90)),
                "max": float(lat.max()),
            }
        lat = summary.get("latency_ms")
        tail = f", median {lat['median']:.1f} ms/frame (first frame compiles)" if lat else ""
        say(f"{frames} frames, {summary['objects']} objects written to {self.out}{tail}")
        if summary["resumed_frames"]:
            say(f"{summary['resumed_frames']} frames were done by an earlier run and kept")
        if summary["bad_frames"]:
            bad = summary["bad_frames"]
            say(f"{len(bad)} unreadable frames skipped: {_first_ids(bad)}")
        if summary["empty_frames"]:
            empty = summary["empty_frames"]
            say(f"{len(empty)} frames had no valid point in the workspace: {_first_ids(empty)}")
        if summary["thinned_frames"]:
            say(
                f"{summary['thinned_frames']} frames had more valid points than data.max_points="
                f"{config.data.max_points}: each kept that many, evenly spread"
            )
        return summary
