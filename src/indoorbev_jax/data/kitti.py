"""KITTI-style dataset files (DESIGN section 3).

Layout::

    <root>/<split>.txt           frame ids, one a line
    <root>/velodyne/<id>.bin     float32 N x 4 (x, y, z, intensity), lidar frame
    <root>/label_2/<id>.txt      KITTI label_2 lines, 15 fields (+ score for predictions)
    <root>/mask_2/<id>.png       optional 16-bit instance ids, H x W, 0 = none,
                                 id k = the k-th object line of the label file
                                 (blank lines and DontCare regions do not count)

There is no camera, so labels use KITTI's camera convention through a fixed axis
permutation of the lidar frame: x_cam = -y, y_cam = -z, z_cam = x. A label line is::

    type truncated occluded alpha  0 0 0 0  h w l  x_cam y_cam z_cam  rotation_y  [score]

with location the bottom centre of the box, rotation_y = -yaw - pi/2, truncation 0,
alpha -10, bbox 0 0 0 0. Mask PNG row i is grid row i (y grows with the row index) and
column j grid column j.

Every writer replaces its file atomically (``fileio.atomic_write``: a temporary name, then
a rename), so a killed export never leaves a half-written file under a final name.
"""

from __future__ import annotations

import dataclasses
import logging
import math
import os
from pathlib import Path

import numpy as np
from PIL import Image

from indoorbev_jax.config import DataConfig
from indoorbev_jax.fileio import atomic_write
from indoorbev_jax.geometry import wrap_angle

log = logging.getLogger(__name__)

ROT_Y_LIMIT = 3.141592  # the largest six-decimal |rotation_y| inside [-pi, pi]

_FLOAT32_MAX = float(np.finfo(np.float32).max)
# PIL modes of integer single-channel images: 1-bit, 8-bit grey, palette, 16- and 32-bit grey.
_ID_MODES = ("1", "L", "P", "I;16", "I;16B", "I;16L", "I")


class DatasetError(ValueError):
    """A dataset file is malformed; the message names the file (and line)."""


def _labels_field(name: str, value, dtype, shape: tuple[int, ...]) -> np.ndarray:
    """``value`` as ``dtype`` of ``shape``; a flat array of as many values (or one with
    singleton axes) is reshaped, any other shape refused: [3, M] positions read as [M, 3]
    scrambled every box without a word."""
    arr = np.asarray(value, dtype)
    squeezed = arr.reshape([n for n in arr.shape if n != 1])
    if arr.shape != shape and not (squeezed.ndim <= 1 and arr.size == math.prod(shape)):
        want = ", ".join(("M" if k == 0 else str(n)) for k, n in enumerate(shape))
        raise ValueError(
            f"ObjectLabels.{name}: expected [{want}] with M = {shape[0]} (one a class in "
            f"classes), got shape {list(arr.shape)}"
        )
    return arr.reshape(shape)


@dataclasses.dataclass
class ObjectLabels:
    """Objects of one frame, in the lidar frame (numpy).

    Attributes:
      classes: int32 [M], class index.
      dims: float32 [M, 3], (length, width, height).
      pos: float32 [M, 3], box centre.
      yaw: float32 [M], heading about +z from +x.
      occlusion: int32 [M], 0 (fully visible) .. 3 (unknown / hardly seen).
      scores: float64 [M] for predictions (as read: scores float32 would tie rank AP as the
        file does not), None for ground truth.
    """

    classes: np.ndarray
    dims: np.ndarray
    pos: np.ndarray
    yaw: np.ndarray
    occlusion: np.ndarray
    scores: np.ndarray | None = None

    def __post_init__(self):
        self.classes = np.asarray(self.classes, np.int32).reshape(-1)
        m = len(self.classes)
        self.dims = _labels_field("dims", self.dims, np.float32, (m, 3))
        self.pos = _labels_field("pos", self.pos, np.float32, (m, 3))
        self.yaw = _labels_field("yaw", self.yaw, np.float32, (m,))
        self.occlusion = _labels_field("occlusion", self.occlusion, np.int32, (m,))
        if self.scores is not None:
            self.scores = _labels_field("scores", self.scores, np.float64, (m,))

    def __len__(self) -> int:
        return len(self.classes)

    @classmethod
    def empty(cls, with_scores: bool = False) -> ObjectLabels:
        return cls(
            np.zeros(0),
            np.zeros((0, 3)),
            np.zeros((0, 3)),
            np.zeros(0),
            np.zeros(0),
            np.zeros(0) if with_scores else None,
        )

    def boxes_bev(self) -> np.ndarray:
        """float32 [M, 5] = (x, y, length, width, yaw), the rasteriser's box format."""
        return np.concatenate([self.pos[:, :2], self.dims[:, :2], self.yaw[:, None]], axis=1)


# Points ------------------------------------------------------------------------------------


def check_regular_file(path: Path, what: str) -> None:
    """Raises ``DatasetError`` when ``path`` names something that is no regular file (a
    folder, a broken symlink, a pipe that would block the read forever), saying it is not
    ``what``; a missing path is left to the read's own ``FileNotFoundError``."""
    if path.is_file() or not (path.exists() or path.is_symlink()):
        return
    kind = (
        "a folder" if path.is_dir()
        else "a broken or looping symlink" if path.is_symlink()
        else "a pipe, socket or device"
    )  # fmt: skip
    raise DatasetError(f"{path}: {kind}, not {what}")


def check_cloud_file(path: Path) -> None:
    """``check_regular_file`` for a point cloud."""
    check_regular_file(path, "a cloud file")


def read_points(path: str | os.PathLike) -> np.ndarray:
    """Reads a ``velodyne/*.bin`` file: float32 [N, 4] = (x, y, z, intensity)."""
    path = Path(path)
    check_cloud_file(path)
    size = path.stat().st_size
    if size % 16:
        raise DatasetError(
            f"{path}: size {size} bytes is not a multiple of 16 (float32 x, y, z, intensity)"
        )
    words = np.fromfile(path, dtype=np.float32)
    if _looks_like_float64(words):
        raise DatasetError(
            f"{path}: looks like float64 values (read as float32 they are mostly absurd); "
            "expected float32 x, y, z, intensity (points.astype(np.float32).tofile(path))"
        )
    misread = _other_column_count(words)
    if misread is not None:
        cols, spread4, spread = misread
        raise DatasetError(
            f"{path}: looks like {cols} float32 values per point, not 4 (x, y, z, intensity): "
            f"nearby points in the file lie {spread4:.2f} m apart (median) read as 4 columns "
            f"and {spread:.2f} m read as {cols}; write 4 columns "
            "(np.c_[xyz, intensity].astype(np.float32).tofile(path))"
        )
    return words.reshape(-1, 4)


# Point gaps compared per stride. Lidars interleave emitters (the MID-360 fires 4 at once),
# so a point's neighbour in firing order may be 2 or 4 points on: in a 40 x 30 m hall a
# 5-column MID-360 file read as 4 columns was only 1.35x less coherent at gap 1. No stride
# may use a gap at which another stride's file realigns: 3 skips 4 (a 4-column file read
# as 3), 4 skips 3 and 5. Stride 5's gap 4 is also where a 4-column file realigns (20
# words), so a 5-emitter lidar's genuine file looked like 5 columns; stride 5 uses it only
# when the 5th column holds whole numbers (a ring, line or tag id) or never decreases (a
# time), which a 4-column file read as 5 (x, y, z and intensity in turn) does not.
_STEP_GAPS = {3: (1, 2, 3), 4: (1, 2, 4), 5: (1, 2)}


def _fifth_column_is_id_or_time(words: np.ndarray) -> bool:
    """Whether the 5th of 5 columns reads as an id (whole numbers) or a time (never
    decreasing), in 99 % of the points."""
    fifth = words[: words.size // 5 * 5].reshape(-1, 5)[:, 4]
    fifth = fifth[np.isfinite(fifth)]
    if len(fifth) < 64:
        return False
    whole = float(np.mean(fifth == np.round(fifth)))
    rising = float(np.mean(np.diff(fifth) >= 0))
    return max(whole, rising) >= 0.99


def _median_step(words: np.ndarray, cols: int) -> float:
    """The least, over the gaps of ``_STEP_GAPS`` (and gap 4 for a 5th column of ids or
    times), median distance between finite points that many apart in ``words`` read as
    ``cols`` columns (x, y, z first)."""
    n = words.size // cols
    with np.errstate(invalid="ignore"):  # signalling NaNs in garbage bytes
        xyz = words[: n * cols].reshape(n, cols)[:, :3].astype(np.float64)
    xyz = xyz[np.isfinite(xyz).all(axis=1) & (np.abs(xyz) < 1e6).all(axis=1)]
    if len(xyz) < 64:
        return np.nan
    gaps = _STEP_GAPS[cols] + ((4,) if cols == 5 and _fifth_column_is_id_or_time(words) else ())
    return min(float(np.median(np.linalg.norm(xyz[g:] - xyz[:-g], axis=1))) for g in gaps)


def _other_column_count(words: np.ndarray) -> tuple[int, float, float] | None:
    """(columns, spread as 4, spread as columns) when ``words`` read far more coherently as 3
    (x, y, z) or 5 (x, y, z, intensity, ring) columns than as 4, else None. A scan stores its
    points in firing order, so consecutive points are near; read with the wrong stride,
    coordinates and intensities mix and the steps grow (``experiments/column_check_sweep.py``
    measures the rule; docs/DATASET.md has its figures). A file
    of 12 or 20 bytes a point passes the size rule whenever N % 4 == 0, a quarter of them."""
    words = words[:60_000]  # about 15,000 points decide
    spread4 = _median_step(words, 4)
    if not spread4 > 0:
        return None
    for cols in (3, 5):
        spread = _median_step(words, cols)
        if spread * 2 < spread4:
            return cols, spread4, spread
    return None


def _looks_like_float64(words: np.ndarray) -> bool:
    """Whether float32 ``words`` are rather the halves of finite float64 points: numpy's
    default dtype has the same size rule (32 bytes a point), so size alone cannot tell."""
    if words.size == 0 or words.size % 8:
        return False
    doubles = words.view(np.float64).reshape(-1, 4)
    # NaN/Inf points are legal data (invalid, not an error), in float64 files too: rows
    # holding them cannot tell, so the test reads the finite rows (8 float32 words each).
    # Rows beyond 1e6 (a 1e30 "no return", say) cannot tell either: most rows must be
    # plausible, not all (one far point, or a cloud in millimetres, hid the float64).
    finite = np.isfinite(doubles).all(axis=1)
    plausible = finite.copy()
    plausible[finite] = np.abs(doubles[finite, :3]).max(axis=1) <= 1e6
    if not plausible.any() or plausible.sum() < 0.5 * finite.sum():
        return False
    words = words.reshape(-1, 8)[plausible].reshape(-1)
    xyz = np.abs(words.reshape(-1, 4)[:, :3])
    xyz = xyz[xyz != 0]
    # The low halves of doubles read as float32 are huge, tiny or not finite; or all zero
    # when the doubles are round numbers (the high halves then look plausible); or, for
    # float32 values widened to float64 (open3d's points, say), zero but in their top 3
    # bits, which a float32 coordinate almost never is.
    absurd = ~np.isfinite(xyz) | (xyz > 1e6) | (xyz < 1e-20)
    low_zero = np.mean(words[0::2] == 0) > 0.9 and np.mean(words[1::2] != 0) > 0.5
    low = words.view(np.uint32)[0::2]
    low = low[low != 0]
    widened = low.size > 0 and np.mean((low & 0x1FFFFFFF) == 0) > 0.9
    return bool(xyz.size and absurd.mean() > 0.2) or bool(low_zero) or bool(widened)


def write_points(path: str | os.PathLike, points: np.ndarray) -> None:
    points = np.asarray(points, np.float32)
    if points.ndim != 2 or points.shape[1] != 4:
        raise ValueError(f"points for {path}: expected shape [N, 4], got {points.shape}")
    atomic_write(Path(path), lambda p: p.write_bytes(points.tobytes()))


# Labels ------------------------------------------------------------------------------------


def labels_to_lines(labels: ObjectLabels, class_names: tuple[str, ...]) -> list[str]:
    """Formats objects as KITTI label_2 lines (see the module docstring)."""
    lines = []
    for k in range(len(labels)):
        length, width, height = (float(v) for v in labels.dims[k])
        x, y, z = (float(v) for v in labels.pos[k])
        values = [length, width, height, x, y, z, float(labels.yaw[k])]
        if labels.scores is not None:
            values.append(float(labels.scores[k]))
        # Refused here, not when the file is read back (by eval, maybe much later).
        if not all(math.isfinite(v) for v in values):
            raise ValueError(
                f"object {k}: non-finite size, position, yaw or score {values} "
                "(a label file holds finite numbers)"
            )
        written = [float(f"{v:.6f}") for v in (length, width, height)]
        if labels.scores is None and not all(v > 0 for v in written):
            raise ValueError(
                f"object {k}: ground-truth size {length:g} x {width:g} x {height:g} m is not "
                "positive at the label file's six decimals"
            )
        rot_y = float(wrap_angle(-float(labels.yaw[k]) - math.pi / 2))
        # Six decimals round +-pi to +-3.141593, outside KITTI's [-pi, pi].
        rot_y = min(max(rot_y, -ROT_Y_LIMIT), ROT_Y_LIMIT)
        # Camera location of the bottom centre.
        cam = (-y, -(z - height / 2), x)
        fields = [
            class_names[int(labels.classes[k])],
            "0.00",
            str(int(labels.occlusion[k])),
            "-10",
            "0.00",
            "0.00",
            "0.00",
            "0.00",
            *(f"{v:.6f}" for v in (height, width, length, *cam, rot_y)),
        ]
        if labels.scores is not None:
            fields.append(f"{float(labels.scores[k]):.6f}")
        lines.append(" ".join(fields))
    return lines


def write_labels(
    path: str | os.PathLike, labels: ObjectLabels, class_names: tuple[str, ...]
) -> None:
    try:
        text = "".join(line + "\n" for line in labels_to_lines(labels, class_names))
    except ValueError as e:
        raise ValueError(f"{path}: {e}") from None
    atomic_write(Path(path), lambda p: p.write_text(text))


def _label_error(source: str, lineno: int, what: str) -> DatasetError:
    return DatasetError(f"{source}:{lineno}: {what}")


def parse_label_lines(lines: list[str], data: DataConfig, source: str) -> ObjectLabels:
    """Parses KITTI label_2 lines; ``source`` names the file in error messages.

    Blank lines and KITTI's ``DontCare`` regions are not objects: instance k of a mask is the
    k-th object line. Every other line must be a valid object, or the error names its line.
    """
    rows, names, occl, scores = [], [], [], []
    first_scored = first_unscored = None
    for lineno, line in enumerate(lines, start=1):
        fields = line.split()
        if not fields or fields[0] == "DontCare":
            continue
        if len(fields) not in (15, 16):
            raise _label_error(
                source, lineno, f"expected 15 fields (16 with a score), got {len(fields)}"
            )
        name = fields[0]
        try:
            cls = data.class_index(name)
        except KeyError:
            raise _label_error(
                source, lineno, f"unknown class '{name}' (expected one of "
                f"{list(data.class_names)} or a name mapped in data.class_map)",
            ) from None  # fmt: skip
        try:
            separated = next((v for v in fields[1:] if "_" in v), None)
            if separated is not None:  # float() reads "0_5" as 5.0
                raise ValueError(f"'_' in {separated!r}")
            values = [float(v) for v in fields[1:]]
        except ValueError as e:
            raise _label_error(source, lineno, f"non-numeric field ({e})") from None
        truncation, occlusion = values[0], values[1]
        if not 0.0 <= truncation <= 1.0:
            raise _label_error(source, lineno, f"truncation must lie in [0, 1], got {fields[1]}")
        if occlusion not in (0.0, 1.0, 2.0, 3.0):
            raise _label_error(source, lineno, f"occlusion must be 0, 1, 2 or 3, got {fields[2]}")
        if not all(math.isfinite(v) and abs(v) <= _FLOAT32_MAX for v in values[7:]):
            # Past float32's range a value turns into inf in the arrays built from it.
            raise _label_error(source, lineno, "non-finite dimensions, location, angle or score")
        if len(fields) == 15 and not all(v > 0 for v in values[7:10]):
            # Ground truth only: a prediction's regressed size may come out <= 0.
            raise _label_error(
                source, lineno, f"dimensions h w l must be positive, got {' '.join(fields[8:11])}"
            )
        names.append(cls)
        occl.append(int(occlusion))
        rows.append(values[7:14])
        if len(fields) == 16:
            scores.append(values[14])
            first_scored = first_scored or lineno
        else:
            first_unscored = first_unscored or lineno
    if first_scored and first_unscored:
        raise _label_error(
            source, max(first_scored, first_unscored), "some lines carry a score and some do "
            f"not (line {first_scored} has one, line {first_unscored} has none)",
        )  # fmt: skip
    if not rows:
        return ObjectLabels.empty()
    h, w, l, xc, yc, zc, rot_y = np.asarray(rows, np.float64).T  # noqa: E741
    # Invert the camera permutation; location is the bottom centre.
    pos = np.stack([zc, -xc, -yc + h / 2], axis=1)
    yaw = wrap_angle(-rot_y - np.pi / 2)
    return ObjectLabels(
        classes=np.asarray(names),
        dims=np.stack([l, w, h], axis=1),
        pos=pos,
        yaw=yaw,
        occlusion=np.asarray(occl),
        scores=np.asarray(scores) if scores else None,
    )


def _read_lines(path: Path, what: str) -> list[str]:
    """The lines of a UTF-8 text file (``what``, for errors); a leading byte-order mark
    (Windows editors) is not part of the first line. An undecodable byte is named by its
    line."""
    check_regular_file(path, what)  # a pipe there hung eval and dataset check
    raw = path.read_bytes()
    try:
        text = raw.decode("utf-8-sig")
    except UnicodeDecodeError as e:
        line = raw[: e.start].count(b"\n") + 1
        raise DatasetError(f"{path}:{line}: not a UTF-8 text file ({e.reason} at byte "
                           f"{e.start}: {raw[e.start:e.start + 1]!r})") from None  # fmt: skip
    return text.splitlines()


def read_labels(path: str | os.PathLike, data: DataConfig) -> ObjectLabels:
    """Reads a ``label_2/*.txt`` file. Errors name the file and line."""
    path = Path(path)
    return parse_label_lines(_read_lines(path, "a label file"), data, str(path))


# Masks -------------------------------------------------------------------------------------


def read_mask(path: str | os.PathLike, shape: tuple[int, int]) -> np.ndarray:
    """Reads a 16-bit instance-id PNG as int32 [H, W]; its size must equal ``shape``."""
    path = Path(path)
    check_regular_file(path, "a PNG mask")
    try:
        # verify() checks every chunk's CRC, which loading does not: a flipped bit in the
        # image data otherwise reads as other ids, silently. It leaves the image unusable.
        with Image.open(path) as im:
            im.verify()
        with Image.open(path) as im:
            image_format, mode = im.format, im.mode
            ids = np.asarray(im)
    except (OSError, ValueError, SyntaxError, Image.DecompressionBombError) as e:
        # PIL raises all of these for broken files (a bad IHDR length: ValueError).
        raise DatasetError(f"{path}: not a readable PNG ({type(e).__name__}: {e})") from None
    # A JPEG's lossy compression changes ids silently, and float images hold no ids.
    if image_format != "PNG" or mode not in _ID_MODES:
        raise DatasetError(
            f"{path}: a {image_format} image in mode {mode}; expected a PNG of integer "
            "instance ids (16-bit grey, or 8-bit grey / palette)"
        )
    if ids.shape != tuple(shape):
        raise DatasetError(
            f"{path}: mask of shape {ids.shape} (H, W), expected {tuple(shape)} from the grid "
            "of the config in use (another --preset?)"
        )
    return ids.astype(np.int32)


def write_mask(path: str | os.PathLike, instance_ids: np.ndarray) -> None:
    ids = np.asarray(instance_ids)
    if ids.ndim != 2 or ids.min(initial=0) < 0 or ids.max(initial=0) > 65535:
        raise ValueError(f"mask for {path}: expected [H, W] ids in 0..65535, got {ids.shape}")
    image = Image.fromarray(ids.astype(np.uint16))

    def write(tmp: Path) -> None:
        image.save(tmp, format="PNG")

    atomic_write(Path(path), write)


# Frames and splits -------------------------------------------------------------------------


def frame_paths(root: str | os.PathLike, frame_id: str) -> dict[str, Path]:
    root = Path(root)
    return {
        "points": root / "velodyne" / f"{frame_id}.bin",
        "labels": root / "label_2" / f"{frame_id}.txt",
        "mask": root / "mask_2" / f"{frame_id}.png",
    }


def frame_folders(root: str | os.PathLike) -> set[Path]:
    """The folders of a dataset ``root`` that hold its frame files (resolved), which an
    output must not be written into."""
    return {path.parent.resolve() for path in frame_paths(root, "0").values()}


def write_frame(
    root: str | os.PathLike,
    frame_id: str,
    points: np.ndarray,
    labels: ObjectLabels,
    class_names: tuple[str, ...],
    instance_ids: np.ndarray | None = None,
) -> None:
    """Writes one frame. The label file is written last, so its presence marks the frame
    complete (readers and resumable exports rely on that)."""
    paths = frame_paths(root, frame_id)
    write_points(paths["points"], points)
    if instance_ids is not None:
        write_mask(paths["mask"], instance_ids)
    write_labels(paths["labels"], labels, class_names)


def read_split(root: str | os.PathLike, split: str) -> list[str]:
    path = Path(root) / f"{split}.txt"
    if not path.exists():
        raise DatasetError(f"{path}: split file not found")
    try:
        lines = _read_lines(path, "a split file")
    except OSError as e:  # unreadable
        raise DatasetError(f"{path}: cannot read the split file ({e.strerror})") from None
    ids, first_line = [], {}
    for n, line in enumerate(lines, 1):
        frame_id = line.strip()
        if not frame_id:
            continue
        if frame_id in first_line:  # counted twice, it would weigh twice in every metric
            raise DatasetError(
                f"{path}:{n}: frame id {frame_id!r} again (first on line {first_line[frame_id]})"
            )
        first_line[frame_id] = n
        ids.append(frame_id)
    return ids


def write_split(root: str | os.PathLike, split: str, ids: list[str]) -> None:
    text = "".join(f"{i}\n" for i in ids)
    atomic_write(Path(root) / f"{split}.txt", lambda p: p.write_text(text))


def list_frames(root: str | os.PathLike) -> list[str]:
    """Frame ids that have a label file, sorted; hidden files (macOS ``._*``) are not frames."""
    return sorted(p.stem for p in (Path(root) / "label_2").glob("*.txt") if not is_hidden(p))


def is_hidden(path: Path) -> bool:
    """Dot files: pathlib's glob matches them, but they are not frames (macOS writes ``._x``
    metadata files next to every file copied to a foreign disk)."""
    return path.name.startswith(".")
