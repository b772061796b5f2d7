"""Small synthetic frames for tests that need data but not the simulator."""

from __future__ import annotations

import numpy as np

from indoorbev_jax.config import CLASS_NAMES
from indoorbev_jax.data import kitti


def synthetic_frame(rng: np.random.Generator, n_objects: int = 3):
    """(points [N, 4], labels): boxes with points filling them, plus floor points."""
    dims = rng.uniform([0.4, 0.4, 0.5], [2.0, 1.2, 1.8], (n_objects, 3))
    pos = np.column_stack(
        [rng.uniform(-3.5, 3.5, (n_objects, 2)), dims[:, 2] / 2]
    )  # objects stand on the floor
    yaw = rng.uniform(-np.pi, np.pi, n_objects)
    pts = []
    for k in range(n_objects):
        local = rng.uniform(-0.5, 0.5, (120, 3)) * dims[k]
        c, s = np.cos(yaw[k]), np.sin(yaw[k])
        xy = local[:, :2] @ np.array([[c, s], [-s, c]]) + pos[k, :2]
        pts.append(np.column_stack([xy, local[:, 2] + pos[k, 2], rng.random(120)]))
    floor = np.column_stack([rng.uniform(-4.5, 4.5, (200, 2)), np.zeros(200), rng.random(200)])
    labels = kitti.ObjectLabels(
        classes=rng.integers(0, len(CLASS_NAMES), n_objects),
        dims=dims,
        pos=pos,
        yaw=yaw,
        occlusion=np.zeros(n_objects),
    )
    return np.concatenate(pts + [floor]).astype(np.float32), labels


def write_synthetic_dataset(root, frames: int = 8, seed: int = 0, val: int = 2) -> None:
    """A KITTI-style folder with ``train`` and ``val`` splits of synthetic frames."""
    rng = np.random.default_rng(seed)
    ids = [f"{k:06d}" for k in range(frames)]
    for frame_id in ids:
        points, labels = synthetic_frame(rng, int(rng.integers(1, 4)))
        kitti.write_frame(root, frame_id, points, labels, CLASS_NAMES)
    kitti.write_split(root, "train", ids[: frames - val])
    kitti.write_split(root, "val", ids[frames - val :])
