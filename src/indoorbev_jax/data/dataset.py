"""Frames as padded, static-shape arrays: what the model and loss consume.

``KittiDataset`` reads a KITTI-style folder (``kitti.py``) and yields unbatched ``Batch``
items (numpy) with points ``[N_max, 4]`` + validity and targets padded to
``data.max_objects``; ``collate`` stacks them into a batch. Footprints come from
``mask_2`` when the file exists (true shape), otherwise from the labelled boxes
(``rasterize.py``).

Rules for what does not fit:
  * NaN/Inf points, points closer to the sensor than ``sim.min_range`` (its blind zone;
    lidar drivers write (0, 0, 0) for a pulse with no return) and points outside the
    workspace (``grid`` x/y/z ranges) are marked invalid and counted, never an error;
  * a frame with more valid points than ``data.max_points`` keeps ``max_points`` of them
    evenly spread over the scan order, so a spinning lidar's scan loses density everywhere
    instead of a whole sector (the excess is counted in ``FrameStats.dropped_points``);
  * a frame with more objects than ``data.max_objects`` keeps the first ones (counted in
    ``FrameStats.dropped_objects``).
"""

from __future__ import annotations

import dataclasses
import os
from collections.abc import Iterator
from pathlib import Path

import numpy as np

from indoorbev_jax.config import NUM_CLASSES, Config, GridConfig
from indoorbev_jax.data import kitti
from indoorbev_jax.data.rasterize import instance_ids_from_masks, rasterize_boxes
from indoorbev_jax.geometry import as_points, in_workspace, usable
from indoorbev_jax.types import Batch, Targets


@dataclasses.dataclass
class FrameStats:
    """What happened to one frame's raw data on the way to static shapes."""

    frame_id: str
    raw_points: int
    nonfinite_points: int
    outside_points: int
    dropped_points: int
    objects: int
    dropped_objects: int
    blind_points: int = 0

    @property
    def invalid_points(self) -> int:
        """Non-finite, blind-zone and out-of-workspace points."""
        return self.nonfinite_points + self.blind_points + self.outside_points

    @property
    def valid_points(self) -> int:
        return self.raw_points - self.invalid_points - self.dropped_points


def pad_points(
    points: np.ndarray,
    grid: GridConfig,
    max_points: int,
    min_range: float = 0.0,
    origin: tuple[float, float, float] = (0.0, 0.0, 0.0),
) -> tuple[np.ndarray, np.ndarray, dict[str, int]]:
    """Pads a raw cloud to ``[max_points, 4]`` with a validity mask.

    Non-finite points (an intensity beyond ``geometry.MAX_ABS_INTENSITY`` counts as
    non-finite), points closer to the sensor (at ``origin``: a ``mount.LidarMount``
    height correction moves it off zero) than ``min_range`` and out-of-workspace points are
    left out (counted). Callers pass ``sim.min_range``: the
    simulated training scans have no return that close, and lidar drivers (Livox's among
    them) write a pulse with no return as (0, 0, 0), which lies inside the workspace. Of
    more than ``max_points`` valid points, ``max_points`` evenly spaced in the input order
    are kept (deterministic; the order is kept too): lidar drivers emit points by time or
    azimuth, so keeping the first ones would cut whole sectors out of the scan.

    Returns:
      points float32 [max_points, 4] (invalid rows zeroed), valid bool [max_points], and
      counts of non-finite, blind-zone, out-of-workspace and dropped points.
    """
    points = as_points(points)
    finite = usable(points)
    # float64 and a 1e-5 margin: a simulated return at exactly min_range stays valid.
    radius = np.linalg.norm(points[:, :3].astype(np.float64) - np.asarray(origin), axis=1)
    blind = finite & (radius < min_range * (1.0 - 1e-5))
    inside = finite & ~blind & in_workspace(points, grid)
    keep = np.flatnonzero(inside)
    dropped = max(0, len(keep) - max_points)
    if dropped:
        keep = keep[np.arange(max_points, dtype=np.int64) * len(keep) // max_points]
    out = np.zeros((max_points, 4), np.float32)
    out[: len(keep)] = points[keep]
    valid = np.zeros(max_points, bool)
    valid[: len(keep)] = True
    counts = {
        "nonfinite_points": int((~finite).sum()),
        "blind_points": int(blind.sum()),
        "outside_points": int((finite & ~blind & ~inside).sum()),
        "dropped_points": dropped,
    }
    return out, valid, counts


def make_targets(
    labels: kitti.ObjectLabels,
    grid: GridConfig,
    max_objects: int,
    instance_ids: np.ndarray | None = None,
) -> Targets:
    """Padded targets of one frame (numpy, no batch axis).

    Args:
      labels: the frame's objects; only the first ``max_objects`` are kept.
      grid: the BEV grid.
      max_objects: M, the padded length.
      instance_ids: optional int32 [H, W] true-shape footprints (id k + 1 = object k);
        without it, footprints are the labelled boxes.

    Returns:
      ``Targets`` with classes [M] (padding: num_classes), dims [M, 3], pos [M, 3],
      yaw [M], valid [M], masks [M, H, W], instance_ids [H, W].
    """
    m = min(len(labels), max_objects)
    classes = np.full(max_objects, NUM_CLASSES, np.int32)  # padding = background index
    classes[:m] = labels.classes[:m]
    dims = np.zeros((max_objects, 3), np.float32)
    dims[:m] = labels.dims[:m]
    pos = np.zeros((max_objects, 3), np.float32)
    pos[:m] = labels.pos[:m]
    yaw = np.zeros(max_objects, np.float32)
    yaw[:m] = labels.yaw[:m]
    valid = np.arange(max_objects) < m
    if instance_ids is None:
        boxes = np.zeros((max_objects, 5), np.float32)
        boxes[:m] = labels.boxes_bev()[:m]
        ids, masks = rasterize_boxes(boxes, valid, grid)
        ids, masks = np.asarray(ids), np.asarray(masks)
    else:
        instance_ids = np.asarray(instance_ids)
        if instance_ids.shape != grid.shape:  # set_loss blamed the predictions' masks
            raise ValueError(
                f"instance_ids: expected the grid's [H, W] = {list(grid.shape)}, got shape "
                f"{list(instance_ids.shape)}"
            )
        masks = instance_ids[None] == np.arange(1, max_objects + 1)[:, None, None]
        masks &= valid[:, None, None]
        # Ids beyond max_objects were dropped with their objects; re-derive the map.
        ids = np.asarray(instance_ids_from_masks(masks, valid))
    return Targets(
        classes=classes,
        dims=dims,
        pos=pos,
        yaw=yaw,
        valid=valid,
        masks=masks,
        instance_ids=ids.astype(np.int32),
    )


def collate(items: list[Batch]) -> Batch:
    """Stacks unbatched items into one batch along a new leading axis."""
    return Batch(
        points=np.stack([b.points for b in items]),
        point_valid=np.stack([b.point_valid for b in items]),
        targets=Targets(
            **{
                f.name: np.stack([getattr(b.targets, f.name) for b in items])
                for f in dataclasses.fields(Targets)
            }
        ),
    )


class KittiDataset:
    """Frames of a KITTI-style folder as padded, static-shape arrays.

    Example::

        ds = KittiDataset("data/sim", "train", Config.small())
        item, stats = ds.load(0)
        for batch in ds.batches(4): ...

    Args:
      root: dataset folder.
      split: a split name (``<root>/<split>.txt``) or None for every labelled frame.
      config: supplies the grid, ``data.max_points``, ``data.max_objects`` and classes.
    """

    def __init__(self, root: str | os.PathLike, split: str | None, config: Config):
        self.root = Path(root)
        self.config = config
        if not (self.root / "label_2").is_dir():
            raise kitti.DatasetError(f"{self.root}: no label_2/ folder, not a dataset root")
        self.ids = kitti.list_frames(self.root) if split is None else kitti.read_split(root, split)
        paths = {i: kitti.frame_paths(root, i) for i in self.ids}
        missing = [
            str(p[kind].relative_to(self.root))
            for p in paths.values()
            for kind in ("points", "labels")
            if not p[kind].exists()
        ]
        if missing:
            listed_in = self.root / (f"{split}.txt" if split is not None else "label_2")
            raise kitti.DatasetError(
                f"{listed_in}: {len(missing)} file(s) of its frames are missing, e.g. {missing[:5]}"
            )

    def __len__(self) -> int:
        return len(self.ids)

    def load(self, index: int) -> tuple[Batch, FrameStats]:
        """Reads frame ``index``; raises ``DatasetError`` naming the file on bad input."""
        frame_id = self.ids[index]
        paths = kitti.frame_paths(self.root, frame_id)
        cfg = self.config
        raw = kitti.read_points(paths["points"])
        labels = kitti.read_labels(paths["labels"], cfg.data)
        if labels.scores is not None:  # predictions; their sizes were not checked either
            raise kitti.DatasetError(
                f"{paths['labels']}: a score column (16th field); ground truth has 15 fields"
            )
        ids = kitti.read_mask(paths["mask"], cfg.grid.shape) if paths["mask"].exists() else None
        if ids is not None and ids.max(initial=0) > len(labels):
            raise kitti.DatasetError(
                f"{paths['mask']}: instance id {ids.max()} but the label file has "
                f"{len(labels)} objects"
            )
        points, valid, counts = pad_points(raw, cfg.grid, cfg.data.max_points, cfg.sim.min_range)
        targets = make_targets(labels, cfg.grid, cfg.data.max_objects, ids)
        stats = FrameStats(
            frame_id=frame_id,
            raw_points=len(raw),
            objects=len(labels),
            dropped_objects=max(0, len(labels) - cfg.data.max_objects),
            **counts,
        )
        return Batch(points=points, point_valid=valid, targets=targets), stats

    def __iter__(self) -> Iterator[Batch]:
        for k in range(len(self)):
            yield self.load(k)[0]

    def batches(
        self, batch_size: int, *, order: np.ndarray | None = None, drop_remainder: bool = True
    ) -> Iterator[Batch]:
        """Yields collated batches in ``order`` (default: file order)."""
        order = np.arange(len(self)) if order is None else np.asarray(order)
        stop = len(order) - len(order) % batch_size if drop_remainder else len(order)
        for start in range(0, stop, batch_size):
            yield collate([self.load(int(k))[0] for k in order[start : start + batch_size]])


def dataset_config(
    root: str | os.PathLike, preset: str | None = None, overrides=()
) -> tuple[Config, str]:
    """(config, where it came from) for reading the dataset folder ``root``: the ``preset``
    when given, else the config recorded in ``root/export.json`` (a simulator export), else
    the ``small`` preset; then the ``SECTION.FIELD=VALUE`` ``overrides`` (``--set``).

    Raises:
      kitti.DatasetError: an unreadable export.json (named).
      config.ConfigError: a bad override (named).
    """
    import json

    from indoorbev_jax.config import with_overrides

    meta_path = Path(root) / "export.json"
    if preset is not None:
        config, source = Config.preset(preset), f"preset {preset}"
    elif meta_path.exists():
        try:
            config = Config.from_dict(json.loads(meta_path.read_text())["config"])
        except (OSError, ValueError, KeyError, TypeError) as e:
            raise kitti.DatasetError(
                f"{meta_path}: cannot read its config ({e!r}); pass --preset"
            ) from None
        source = f"the config of {meta_path} (preset {config.name})"
    else:
        config, source = Config.small(), "preset small (the default; no export.json)"
    if overrides:
        config = with_overrides(config, list(overrides))
        source += " with --set " + " ".join(overrides)
    return config, source
