"""BEV pictures of labelled frames (Pillow): points coloured by height, footprint masks,
boxes and class names. Picture orientation: x (forward) to the right, y (left) up.
"""

from __future__ import annotations

import os
from pathlib import Path

from indoorbev_jax import fileio
from indoorbev_jax.checks import check_folder
from indoorbev_jax.config import Config
from indoorbev_jax.data import kitti
from indoorbev_jax.interrupts import check_interrupted
from indoorbev_jax.viz import render_bev

# One renderer for ground truth and predictions.
render_frame = render_bev


def show(
    root: str | os.PathLike,
    out: str | os.PathLike,
    config: Config,
    ids: list[str] | None = None,
) -> list[Path]:
    """Writes ``<out>/<id>.png`` for frames of the KITTI folder ``root`` (all by default)."""
    root, out = Path(root), check_folder("out", out)
    if out.resolve() in kitti.frame_folders(root):
        # Its pictures replaced the dataset's masks (mask_2/<id>.png), exit 0.
        raise ValueError(f"--out {out}: a data folder of the dataset {root}; use another folder")
    ids = kitti.list_frames(root) if ids is None else ids
    missing = [fid for fid in ids if not kitti.frame_paths(root, fid)["points"].exists()]
    if missing:  # before the output folder is made
        first = kitti.frame_paths(root, missing[0])["points"]
        raise FileNotFoundError(f"{root}: no frame {', '.join(missing[:5])} (no {first})")
    out.mkdir(parents=True, exist_ok=True)
    written = []
    for fid in ids:
        paths = kitti.frame_paths(root, fid)
        points = kitti.read_points(paths["points"])
        labels = kitti.read_labels(paths["labels"], config.data)
        mask = kitti.read_mask(paths["mask"], config.grid.shape) if paths["mask"].exists() else None
        pic = render_frame(points, labels, mask, config.grid, config.data.class_names)
        path = out / f"{fid}.png"
        # Never a half-written picture under its name (Ctrl-C, a full disk on a rerun).
        fileio.atomic_write(path, lambda tmp, pic=pic: pic.save(tmp, format="PNG"))
        written.append(path)
        check_interrupted()
    return written
