"""BEV pictures (Pillow). Orientation: x (forward) to the right, y (left) up."""

from __future__ import annotations

import numpy as np
from PIL import Image, ImageDraw

from indoorbev_jax.config import GridConfig
from indoorbev_jax.data import kitti
from indoorbev_jax.geometry import box_corners, on_grid

PALETTE = np.array(
    [[230, 25, 75], [60, 180, 75], [255, 225, 25], [0, 130, 200], [245, 130, 48],
     [145, 30, 180], [70, 240, 240], [240, 50, 230], [210, 245, 60], [250, 190, 212],
     [0, 128, 128], [220, 190, 255], [170, 110, 40], [128, 0, 0], [170, 255, 195]],
    np.uint8,
)  # fmt: skip


def height_colour(z: np.ndarray, z_range: tuple[float, float]) -> np.ndarray:
    """A blue -> green -> red ramp over z; [N, 3] uint8."""
    t = np.clip((z - z_range[0]) / (z_range[1] - z_range[0]), 0.0, 1.0)[:, None]
    lo, mid, hi = np.array([40, 80, 255]), np.array([40, 220, 80]), np.array([255, 60, 40])
    c = np.where(t < 0.5, lo + (mid - lo) * (2 * t), mid + (hi - mid) * (2 * t - 1))
    return c.astype(np.uint8)


def picture_scale(grid: GridConfig, pixels_per_cell: int = 1, min_size: int = 600) -> int:
    return max(pixels_per_cell, -(-min_size // grid.shape[1]))


def grid_image(rgb: np.ndarray, scale: int) -> np.ndarray:
    """[H, W, 3] grid-ordered colours -> [H*s, W*s, 3] picture with y up."""
    return np.kron(rgb[::-1], np.ones((scale, scale, 1), np.uint8))


def render_bev(
    points: np.ndarray,
    labels: kitti.ObjectLabels | None,
    instance_ids: np.ndarray | None,
    grid: GridConfig,
    class_names: tuple[str, ...],
    pixels_per_cell: int = 1,
    min_size: int = 600,
) -> Image.Image:
    """Points coloured by height over footprints, with boxes, headings and class names.

    Args:
      points: float [N, 4] lidar-frame points.
      labels: the frame's objects (None: no boxes); a score, when present, follows the name.
      instance_ids: int [H, W] footprint ids (0 = none) or None.
      grid: the BEV grid.
      class_names: class names by index.
      pixels_per_cell: scale; raised so the picture is at least ``min_size`` wide.
    """
    h, w = grid.shape
    scale = picture_scale(grid, pixels_per_cell, min_size)
    img = np.full((h, w, 3), 20, np.uint8)
    if instance_ids is not None:
        ids = np.asarray(instance_ids)
        colours = PALETTE[(ids - 1) % len(PALETTE)] // 2 + 10
        img = np.where(ids[..., None] > 0, colours, img).astype(np.uint8)
    img = grid_image(img, scale)
    x0, y1, v = grid.x_range[0], grid.y_range[1], grid.cell_size

    def px(x, y):
        return (x - x0) / v * scale, (y1 - y) / v * scale

    # Points outside the grid (or NaN) are not drawn: clipped onto the border, an 8 m wall
    # showed as a false one at the 5 m edge.
    points = np.asarray(points)
    if len(points):
        points = points[on_grid(points[:, 0], points[:, 1], grid)]  # NaN is off the grid
    if len(points):
        pts = points[np.argsort(points[:, 2])]  # higher points drawn last, on top
        u, r = px(pts[:, 0], pts[:, 1])
        # x_max / y_min fall on the last pixel's far edge: the 2 x 2 dot stays inside.
        u = np.minimum(u.astype(int), img.shape[1] - 2)
        r = np.minimum(r.astype(int), img.shape[0] - 2)
        cols = height_colour(pts[:, 2], grid.z_range)
        for du in (0, 1):  # 2 x 2 pixel dots
            for dr in (0, 1):
                img[r + dr, u + du] = cols
    pic = Image.fromarray(img)
    draw = ImageDraw.Draw(pic)
    corners = (
        box_corners(labels.pos[:, :2], labels.dims[:, :2], labels.yaw)
        if labels is not None
        else None
    )
    for k in range(len(labels) if labels is not None else 0):
        (x, y, _), (length, _, _) = labels.pos[k], labels.dims[k]
        c, s = np.cos(labels.yaw[k]), np.sin(labels.yaw[k])
        colour = tuple(int(q) for q in PALETTE[k % len(PALETTE)])
        draw.polygon([px(*p) for p in corners[k]], outline=colour)
        draw.line([px(x, y), px(x + c * length / 2, y + s * length / 2)], fill=colour)
        text = class_names[int(labels.classes[k])]
        if labels.scores is not None:
            text += f" {float(labels.scores[k]):.2f}"
        draw.text(px(x, y), text, fill=(255, 255, 255))
    return pic


def feature_image(features: np.ndarray) -> np.ndarray:
    """[H, W, C] features -> [H, W, 3] uint8: the first three principal components."""
    h, w, c = features.shape
    flat = features.reshape(-1, c).astype(np.float64)
    flat = flat - flat.mean(0)
    _, _, vt = np.linalg.svd(flat, full_matrices=False)
    proj = flat @ vt[:3].T  # [H*W, <=3]
    proj = np.pad(proj, ((0, 0), (0, 3 - proj.shape[1])))
    lo, hi = np.percentile(proj, 1, axis=0), np.percentile(proj, 99, axis=0)
    rgb = np.clip((proj - lo) / np.maximum(hi - lo, 1e-9), 0, 1)
    return (rgb.reshape(h, w, 3) * 255).astype(np.uint8)


def masks_image(masks: np.ndarray) -> np.ndarray:
    """[Q, H, W] bool masks -> [H, W, 3] uint8, each mask its own colour (overlaps blended)."""
    q = masks.shape[0]
    colours = PALETTE[np.arange(q) % len(PALETTE)].astype(np.float32)  # [Q, 3]
    count = masks.sum(0)[..., None]
    total = np.einsum("qhw,qc->hwc", masks.astype(np.float32), colours)
    return np.where(count > 0, total / np.maximum(count, 1), 20).astype(np.uint8)


def panels(images: list[tuple[str, Image.Image]], gap: int = 8) -> Image.Image:
    """Side-by-side panels with titles."""
    title_h = 18
    w = sum(im.width for _, im in images) + gap * (len(images) - 1)
    h = max(im.height for _, im in images) + title_h
    out = Image.new("RGB", (w, h), (0, 0, 0))
    draw = ImageDraw.Draw(out)
    x = 0
    for title, im in images:
        out.paste(im, (x, title_h))
        draw.text((x + 4, 2), title, fill=(255, 255, 255))
        x += im.width + gap
    return out
