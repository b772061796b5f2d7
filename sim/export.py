"""Export simulated frames: the KITTI layout of DESIGN section 3 and ROS2 bags.

``export(out, frames, seed, config)`` writes frames ``000000 ..`` scene by scene: scene j
(T = ``sim.frames_per_sequence`` consecutive frames) goes to the test split when
``j % 10 == 9`` (drawn from the held-out plans and variants), to val when ``j % 10 == 8``,
else to train. Each frame is a pure function of (seed, j, t), so:

* every file is written atomically (temporary name, then rename), the label file last; a
  frame is complete when its points, mask and label files exist (``_complete``);
* a rerun after a kill skips the complete scenes and regenerates the rest, giving exactly
  the files of an uninterrupted run (``export.json`` pins seed, frame count and config;
  a rerun with different ones is refused, naming that file and each differing field);
* a folder without ``export.json`` that holds frames, masks or split lists (another
  dataset, ``indoorbev predict`` output) is refused, never written into;
* the options are checked (frames, seed, throttle, out, the bag's target and place) before
  any frame is generated;
* the split files and the bag are (re)written at the end, from the frames on disk.

ROS2 bag (``rosbags``, pure Python, no ROS install): ``/lidar/points``
(sensor_msgs/PointCloud2 with float32 x, y, z, intensity, frame "lidar") and
``/lidar/objects`` (visualization_msgs/MarkerArray, a DELETEALL, then one CUBE per object:
pose = box centre and yaw, scale = (length, width, height), ``ns`` = class name, ``id`` =
label line, ``text`` = "class occlusion"), one message pair per frame at t = (frame + 1) *
frame_dt.
"""

from __future__ import annotations

import functools
import json
import math
import os
import sys
import time
from pathlib import Path

import jax
import numpy as np

from indoorbev_jax import fileio
from indoorbev_jax.checks import check_folder, check_seed, check_whole
from indoorbev_jax.config import LATER_FIELDS, Config, flatten_dict
from indoorbev_jax.data import kitti
from indoorbev_jax.interrupts import check_interrupted
from indoorbev_jax.rosbag import (
    check_bag_target,
    check_partial,
    markers_to_labels,
    partial_path,
    typestore,
)

SPLITS = ("train", "val", "test")
POINTS_TOPIC, OBJECTS_TOPIC = "/lidar/points", "/lidar/objects"


class ExportError(RuntimeError):
    """An export cannot go on; the message names the file at fault."""


def scene_split(j: int) -> str:
    """Split of scene j: test every 10th (j % 10 == 9), val the one before, else train."""
    return "test" if j % 10 == 9 else "val" if j % 10 == 8 else "train"


# Frame ids have six digits (KITTI's), so that their names sort as their numbers.
MAX_FRAMES = 1_000_000
# Longer pauses overflowed time.sleep after the first scene was written.
MAX_THROTTLE = 3600.0


def frame_id(index: int) -> str:
    return f"{index:06d}"


@functools.lru_cache(maxsize=4)
def scene_fn(config: Config):
    """Jitted ``(key, test flag) -> one scene of T frames`` (one program for every split)."""
    from indoorbev_sim import generate

    def run(key, test):
        return generate.generate_sequences(key, config, 1, test)

    return jax.jit(run)


def _complete(root: Path, fid: str) -> bool:
    paths = kitti.frame_paths(root, fid)
    return all(paths[k].exists() for k in ("points", "mask", "labels"))


# Files a KITTI export or an ``indoorbev predict`` run writes: without export.json they are
# another dataset's, and an export must not mix its frames into them.
_DATA_DIRS = ("velodyne", "label_2", "mask_2")


def _dataset_files(root: Path) -> list[str]:
    """What of a dataset ``root`` holds: its frame folders (with file counts), split lists."""
    held = []
    for name in _DATA_DIRS:
        n = sum(p.is_file() for p in (root / name).glob("*"))
        held += [f"{name}/ ({n} files)"] if n else []
    return held + [f"{s}.txt" for s in SPLITS if (root / f"{s}.txt").is_file()]


def _meta_diff(old: dict, new: dict, limit: int = 10) -> str:
    """Where export.json (``old``) and this run (``new``) differ, as dotted paths
    ``"config.grid.cell_size: 0.1 (saved) vs 0.25 (given)"``: seed, frames and the preset
    name first, at most ``limit`` fields. Compared as JSON rather than through
    ``config_diff``, so that a field only one side has (another version) shows too."""
    a, b = flatten_dict(old), flatten_dict(new)
    absent = object()
    keys = [k for k in a.keys() | b.keys() if a.get(k, absent) != b.get(k, absent)]
    keys.sort(key=lambda k: (k.startswith("config.") and k != "config.name", k))

    def shown(d, k):
        if k in d:
            return repr(d[k])
        field = k.removeprefix("config.")
        if k.startswith("config.") and field in LATER_FIELDS:  # stable_dict leaves it out
            return f"{json.loads(json.dumps(LATER_FIELDS[field]))!r} (the default)"
        return "(absent)"

    rows = [f"{k}: {shown(a, k)} (saved) vs {shown(b, k)} (given)" for k in keys]
    more = [f"and {len(rows) - limit} more fields"] if len(rows) > limit else []
    return "; ".join(rows[:limit] + more)


def _check_meta(root: Path, meta: dict, write: bool = True) -> None:
    """Refuses ``root`` unless it is new or holds an export of ``meta``'s settings, then
    writes ``meta`` as its export.json (unless ``write`` is False: the refusals alone)."""
    path = root / "export.json"
    meta = json.loads(json.dumps(meta))  # tuples -> lists, as read back
    where = root.resolve()
    if where in kitti.frame_folders(where.parent) and (
        _dataset_files(where.parent) or (where.parent / "export.json").exists()
    ):
        raise ExportError(
            f"{root}: the {where.name}/ folder of the dataset {where.parent}, not a dataset "
            "root (an export there broke that dataset); use another --out"
        )
    if path.exists():
        try:
            old = json.loads(path.read_text())
        except ValueError as e:  # JSON, or not UTF-8 text
            raise ExportError(f"{path}: unreadable ({e}); remove it or use another --out") from e
        if not isinstance(old, dict):
            raise ExportError(f"{path}: not an export record (a JSON object); use another --out")
        if old != meta:
            raise ExportError(
                f"{path}: this folder holds an export with other settings: "
                f"{_meta_diff(old, meta)}; rerun with the saved settings to resume, or use "
                "another --out"
            )
    else:
        held = _dataset_files(root)
        if held:
            raise ExportError(
                f"{root}: holds {', '.join(held)} but no export.json, so not an export of "
                "this command to resume; use another --out"
            )
        if write:
            fileio.atomic_write(path, lambda p: p.write_text(json.dumps(meta, indent=1)))


def _check_bag_place(bag: Path, root: Path) -> None:
    """The bag is written last: refuse up front a place it could not take, so that no
    export runs for hours to fail there."""
    b, r = bag.resolve(), root.resolve()
    # The bag is first written to <bag>.partial (rosbag.write_bag): it must not overlap
    # the dataset either, nor hold other files.
    for place in (b, partial_path(b)):
        if place == r or r in place.parents or place in r.parents:
            raise ExportError(
                f"{bag}: the bag folder (or its temporary {place.name}) overlaps the dataset "
                f"folder {root}; choose a bag folder outside it"
            )
    try:
        check_partial(b)  # also refuses a bag another process is writing
    except (FileExistsError, ValueError) as e:
        raise ExportError(str(e)) from None
    existing = next(p for p in b.parents if p.exists())
    if not os.access(existing, os.W_OK | os.X_OK):
        raise ExportError(f"{bag}: cannot be created ({existing} is not writable)")


def _remove_stale_temporaries(root: Path, min_age: float = 60.0) -> None:
    """Deletes what a killed ``fileio.atomic_write`` left (``.<name>.<random>.tmp``,
    ``min_age`` seconds old) in this export's folders (export.json checked); a user's hidden
    file of another name, or another export's write in flight, is left alone."""
    for folder in (root, *(root / d for d in _DATA_DIRS)):
        fileio.remove_stale_temporaries(folder, "*", min_age)


def saved_preset(root: str | os.PathLike) -> str | None:
    """The preset (paper, small, tiny) named by the config ``root/export.json`` records
    (``Config.name``), or None when there is no export.json or it names none of them.

    Raises:
      ExportError: an unreadable export.json (named).
    """
    path = Path(root) / "export.json"
    if not path.exists():
        return None
    try:
        name = json.loads(path.read_text())["config"]["name"]
    except (OSError, ValueError, KeyError, TypeError) as e:
        raise ExportError(f"{path}: cannot read its config ({e!r}); pass --preset") from None
    # A field changed from the preset's is then named by the export's settings check.
    return name if name in ("paper", "small", "tiny") else None


def scene_frame(batch, info, t: int) -> tuple[np.ndarray, kitti.ObjectLabels]:
    """(valid points [N, 4], labels) of frame t of a one-scene batch (arrays [1, T, ...])."""
    valid = np.asarray(batch.targets.valid[0, t])
    labels = kitti.ObjectLabels(
        classes=np.asarray(batch.targets.classes[0, t])[valid],
        dims=np.asarray(batch.targets.dims[0, t])[valid],
        pos=np.asarray(batch.targets.pos[0, t])[valid],
        yaw=np.asarray(batch.targets.yaw[0, t])[valid],
        occlusion=np.asarray(info.occlusion[0, t])[valid],
    )
    points = np.asarray(batch.points[0, t])[np.asarray(batch.point_valid[0, t])]
    return points, labels


def write_scene(root: Path, config: Config, batch, info, frame_ids: list[str]) -> None:
    """Writes the T frames of one scene (arrays [1, T, ...]) under ``frame_ids``."""
    names = config.data.class_names
    for t, fid in enumerate(frame_ids):
        points, labels = scene_frame(batch, info, t)
        ids = np.asarray(batch.targets.instance_ids[0, t])
        kitti.write_frame(root, fid, points, labels, names, instance_ids=ids)


def export(
    out: str | os.PathLike,
    frames: int,
    seed: int,
    config: Config,
    rosbag: str | os.PathLike | None = None,
    progress: bool = True,
    throttle: float = 0.0,
) -> dict[str, list[str]]:
    """Writes (or completes) an export; returns the frame ids of each split.

    Args:
      out: dataset root.
      frames: number of frames.
      seed: base seed; scene j uses ``fold_in(key(seed), j)``.
      config: run configuration (grid, data, sim).
      rosbag: optional path of a ROS2 bag to (re)write from the exported frames.
      progress: show a tqdm progress bar.
      throttle: seconds to pause after each generated scene (to leave a shared machine some
        breath; the resume test uses it to kill an export midway).

    Raises:
      ValueError: frames not a whole number in [1, MAX_FRAMES], seed not one in
        [0, 2**32), throttle not a number in [0, MAX_THROTTLE], an empty ``out`` or
        ``rosbag`` (named); ``rosbag`` names an existing
        path that is not a bag of this export (``BagError``, a ValueError); sim settings
        no scene can be drawn from (``scenes.check_settings``). All checked before any
        frame, and before export.json is written.
      ExportError: ``out`` is a file, holds an export with other settings, or dataset files
        without export.json, or is a data folder of a dataset (its ``label_2/``, say);
        ``rosbag`` overlaps ``out`` or cannot be created.
    """
    from indoorbev_sim.scenes import check_settings, held_out_note
    from tqdm import tqdm

    if check_whole("frames", frames, 1) > MAX_FRAMES:
        raise ValueError(
            f"frames: at most {MAX_FRAMES:,} (frame ids have six digits), got {frames!r}"
        )
    check_seed("seed", seed)
    is_number = isinstance(throttle, int | float) and not isinstance(throttle, bool)
    if not (is_number and 0 <= throttle <= MAX_THROTTLE):  # NaN fails both
        raise ValueError(
            f"throttle: must be a number of seconds in [0, {MAX_THROTTLE:g}], got {throttle!r}"
        )
    root = check_folder("out", out, ExportError)
    if rosbag is not None:  # write_bag runs last: refuse a bad target before hours of frames
        _check_bag_place(check_folder("rosbag", rosbag, ExportError), root)
        check_bag_target(rosbag, (POINTS_TOPIC, OBJECTS_TOPIC))
    check_settings(config.sim)  # before export.json keeps settings that cannot run
    meta = {"seed": int(seed), "frames": int(frames), "config": config.stable_dict()}
    # stable_dict: an export.json of an older version still matches.
    _check_meta(root, meta, write=False)
    # A second export into this folder is refused while one runs: both wrote every frame.
    # Taken after the refusals, so that a refused export leaves the folder as it was.
    with fileio.hold_folder(root, "export", "--out"):
        # Again under the lock: two exports of other settings started together both found
        # no export.json, and the one refused by the lock could leave its own there.
        _check_meta(root, meta)
        started = time.time()
        _remove_stale_temporaries(root)
        t_len = config.sim.frames_per_sequence
        scenes = [
            [frame_id(i) for i in range(j * t_len, min((j + 1) * t_len, frames))]
            for j in range(math.ceil(frames / t_len))
        ]
        todo = [j for j, ids in enumerate(scenes) if not all(_complete(root, fid) for fid in ids)]
        done = frames - sum(len(scenes[j]) for j in todo)
        if done:
            print(f"resuming: {done} of {frames} frames already written", file=sys.stderr)
        if note := held_out_note(config.sim):
            print(note, file=sys.stderr)
        key = jax.random.key(seed)
        splits: dict[str, list[str]] = {s: [] for s in SPLITS}
        for j, ids in enumerate(scenes):
            splits[scene_split(j)] += ids
        fn = scene_fn(config)
        # initial=done: frames kept from an earlier run do not count toward the rate and ETA.
        bar = tqdm(total=frames, initial=done, desc="export", unit="frame", disable=not progress)
        with bar:
            for j in todo:
                check_interrupted()
                batch, info = fn(jax.random.fold_in(key, j), scene_split(j) == "test")
                write_scene(root, config, batch, info, scenes[j])
                time.sleep(throttle)
                bar.update(len(scenes[j]))
        for split, ids in splits.items():
            kitti.write_split(root, split, ids)
        _remove_stale_temporaries(root, fileio.age_since(started))
        if rosbag is not None:
            all_ids = sorted(i for ids in splits.values() for i in ids)
            write_rosbag(root, rosbag, all_ids, config)
        return splits


# ------------------------------------------------------------------------- ROS2 bags


def write_rosbag(root, bag: str | os.PathLike, ids: list[str], config: Config) -> None:
    """Writes the frames ``ids`` of the KITTI folder ``root`` into a ROS2 bag (atomically:
    a temporary bag folder renamed into place)."""
    from indoorbev_jax.rosbag import write_bag

    dt_ns = round(config.sim.frame_dt * 1e9)

    def frames():
        for fid in ids:
            paths = kitti.frame_paths(root, fid)
            points = kitti.read_points(paths["points"])
            labels = kitti.read_labels(paths["labels"], config.data)
            yield (int(fid) + 1) * dt_ns, "lidar", points, labels

    write_bag(bag, frames(), config.data.class_names, POINTS_TOPIC, OBJECTS_TOPIC)


def read_rosbag(
    bag: str | os.PathLike, config: Config
) -> list[tuple[np.ndarray, kitti.ObjectLabels]]:
    """Reads a bag written by ``write_rosbag``: per frame (points [N, 4], labels)."""
    from rosbags.rosbag2 import Reader

    ts = typestore()
    clouds, objects = {}, {}
    with Reader(bag) as reader:
        for conn, stamp, raw in reader.messages():
            msg = ts.deserialize_cdr(raw, conn.msgtype)
            if conn.topic == POINTS_TOPIC:
                clouds[stamp] = np.frombuffer(bytes(msg.data), "<f4").reshape(-1, 4)
            elif conn.topic == OBJECTS_TOPIC:
                objects[stamp] = markers_to_labels(msg, config.data)
    return [(clouds[s], objects[s]) for s in sorted(clouds)]
