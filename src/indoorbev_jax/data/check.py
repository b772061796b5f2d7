"""Checking a KITTI-style dataset folder before training on it (``indoorbev dataset check``).

    report = check_dataset("data/my_robot", split="train")
    print(report.format())
    if not report.ok:  # unreadable frames, too many objects, an empty split
        ...

Problems are what training or evaluation would fail on or silently lose; warnings are
legal but suspicious frames (an empty cloud, points or labels off the grid, intensity in
0-255), which often mean a cloud or labels in the wrong frame or units.
"""

from __future__ import annotations

import dataclasses
import os
from pathlib import Path

import numpy as np

from indoorbev_jax.config import Config
from indoorbev_jax.data import kitti
from indoorbev_jax.data.dataset import KittiDataset, dataset_config


@dataclasses.dataclass
class DatasetReport:
    """What ``check_dataset`` found in a dataset folder."""

    root: Path
    split: str | None  # None: every frame
    config: Config  # the grid, classes and limits the frames were read with
    source: str  # where ``config`` came from
    frames: int  # frames listed (readable or not)
    class_counts: np.ndarray  # [K] objects per class over the readable frames
    valid_points: list[int]  # per readable frame
    raw_points: list[int]  # per readable frame
    invalid_points: int  # non-finite, in the blind zone or outside the workspace
    dropped_points: int  # beyond data.max_points
    dropped_objects: int  # beyond data.max_objects
    warnings: list[str]
    problems: list[str]

    @property
    def ok(self) -> bool:
        """No problems (warnings allowed)."""
        return not self.problems

    def format(self, max_problems: int = 10) -> str:
        """The statistics and the first ``max_problems`` warnings and problems, as text."""
        config = self.config
        lines = [
            f"dataset {self.root} (split: {self.split or 'all'}, {self.source})",
            f"frames: {self.frames} ({self.frames - len(self.valid_points)} unreadable)",
            "objects per class:",
        ]
        for name, n in zip(config.data.class_names, self.class_counts, strict=True):
            lines.append(f"  {name:<8} {n:>8}")
        lines.append(f"  {'total':<8} {self.class_counts.sum():>8}")
        if self.valid_points:
            v = np.asarray(self.valid_points)
            lines.append(
                f"points per frame (valid): min {v.min()}  median {int(np.median(v))}  "
                f"mean {v.mean():.1f}  max {v.max()}  (raw total {sum(self.raw_points)})"
            )
        lines.append(
            f"invalid points (non-finite, within sim.min_range={config.sim.min_range} m of the "
            f"sensor, or outside the workspace): {self.invalid_points}"
        )
        lines.append(
            f"points beyond data.max_points={config.data.max_points}: {self.dropped_points}"
        )
        if self.dropped_objects:
            lines.append(f"objects beyond data.max_objects: {self.dropped_objects}")
        for kind, found in (("warnings", self.warnings), ("problems", self.problems)):
            if found:
                lines.append(f"{kind}: {len(found)}; the first {min(len(found), max_problems)}:")
                lines.extend(f"  {p}" for p in found[:max_problems])
        if self.ok:
            n = len(self.warnings)
            lines.append("no problems found" + (f" ({n} warnings above)" if n else ""))
        return "\n".join(lines)


def check_dataset(
    root: str | os.PathLike,
    split: str | None = None,
    config: Config | None = None,
    source: str | None = None,
    progress: bool = False,
) -> DatasetReport:
    """Reads every frame of ``root`` (of ``<root>/<split>.txt``; None: every frame) as
    training would and reports what it found; an unreadable frame is a problem, not an error.

    Args:
      config: the grid, classes and limits to read with (default: ``dataset_config(root)``,
        the folder's export.json or the ``small`` preset).
      source: where ``config`` came from, for the report's first line.
      progress: a progress bar on stderr.

    Raises:
      kitti.DatasetError, OSError: the folder or its split file cannot be listed (named).
    """
    from tqdm import tqdm

    root = Path(root)
    if config is None:
        config, default_source = dataset_config(root)
        source = source or default_source
    ds = KittiDataset(root, split, config)
    problems: list[str] = []
    warnings: list[str] = []
    if len(ds) == 0:
        problems.append(f"{root}: no frames in split {split or 'all'}")
    warnings.extend(_unpaired_files(root, ds.ids, every_frame=split is None))
    class_counts = np.zeros(config.num_classes, np.int64)
    valid_points, raw_points = [], []
    invalid = dropped_points = dropped_objects = 0
    for k in tqdm(range(len(ds)), disable=not progress, unit="frame", leave=False):
        try:
            item, stats = ds.load(k)
        except (kitti.DatasetError, OSError) as e:
            problems.append(str(e))
            continue
        t = item.targets
        class_counts += np.bincount(t.classes[t.valid], minlength=config.num_classes)
        raw_points.append(stats.raw_points)
        valid_points.append(stats.valid_points)
        invalid += stats.invalid_points
        dropped_points += stats.dropped_points
        # Legal, so warned about rather than failed: a blocked sensor gives an empty cloud and
        # labels may reach past the grid; but points or labels in mm or in a map frame look so.
        if stats.raw_points == 0:
            warnings.append(f"{ds.ids[k]}: an empty cloud")
        elif stats.valid_points == 0:
            warnings.append(
                f"{ds.ids[k]}: none of its {stats.raw_points} points is valid (check the cloud's "
                "frame and units against the grid's workspace)"
            )
        seen = np.asarray(item.points)[np.asarray(item.point_valid), 3]
        if seen.size and seen.max() > 1.0:  # trained on, not rescaled: unlike predict's input
            warnings.append(
                f"{ds.ids[k]}: intensity up to {seen.max():g}; the model takes [0, 1] (the "
                "simulator's reflectivity): write the clouds scaled (Livox 0-255: / 255)"
            )
        off_grid = int((t.valid & ~t.masks.any(axis=(1, 2))).sum())
        if off_grid:  # the evaluator leaves such objects out
            warnings.append(
                f"{ds.ids[k]}: {off_grid} of {int(t.valid.sum())} objects cover no cell of the "
                f"grid x {list(config.grid.x_range)} y {list(config.grid.y_range)} m (check "
                "the labels' frame and units, or --preset)"
            )
        if stats.dropped_objects:
            dropped_objects += stats.dropped_objects
            problems.append(
                f"{ds.ids[k]}: {stats.objects} objects, only the first "
                f"{config.data.max_objects} fit data.max_objects"
            )
    return DatasetReport(
        root, split, config, source or f"preset {config.name}", len(ds), class_counts,
        valid_points, raw_points, invalid, dropped_points, dropped_objects, warnings, problems,
    )  # fmt: skip


def _unpaired_files(root: Path, ids: list[str], every_frame: bool) -> list[str]:
    """Warnings for clouds without labels (not frames: a lost label file, say) and, where
    ``mask_2/`` exists, frames without a mask (their footprints fall back to the boxes)."""
    found = []
    if every_frame:
        clouds = {p.stem for p in (root / "velodyne").glob("*.bin") if not kitti.is_hidden(p)}
        orphans = sorted(clouds - set(ids))
        if orphans:
            found.append(
                f"{root / 'velodyne'}: {len(orphans)} cloud(s) have no label_2 file, so are no "
                f"frame, e.g. {[f'{i}.bin' for i in orphans[:5]]}"
            )
    if (root / "mask_2").is_dir():
        no_mask = [i for i in ids if not kitti.frame_paths(root, i)["mask"].exists()]
        if no_mask:
            found.append(
                f"{root / 'mask_2'}: {len(no_mask)} frame(s) have no mask, so their footprints "
                f"are the label boxes, e.g. {[f'{i}.png' for i in no_mask[:5]]}"
            )
    return found
