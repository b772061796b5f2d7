"""Training data: on-device simulated batches or a KITTI-style folder, computed ahead.

A source is a function ``step -> Batch`` that gives the same batch for the same step on
every call, so a resumed run reads the data an uninterrupted one would (``SimSource``,
``KittiSource``); ``prefetch`` runs one ahead of the train step on a thread.
"""

from __future__ import annotations

import logging
import queue
import threading
from collections.abc import Callable, Iterator

import jax
import jax.numpy as jnp
import numpy as np

from indoorbev_jax.augment import ObjectDatabase, build_object_database
from indoorbev_jax.config import Config
from indoorbev_jax.data import kitti
from indoorbev_jax.data.rasterize import rasterize_boxes
from indoorbev_jax.types import Batch

log = logging.getLogger(__name__)


def box_targets(batch: Batch, grid) -> Batch:
    """The batch with each object's footprint replaced by its rasterised labelled box
    (``data.mask_targets = "box"``, the ablation against true-shape targets)."""
    t = batch.targets
    boxes = jnp.concatenate([t.pos[..., :2], t.dims[..., :2], t.yaw[..., None]], -1)  # [B, M, 5]
    ids, masks = jax.vmap(rasterize_boxes, in_axes=(0, 0, None))(boxes, t.valid, grid)
    return batch.replace(targets=t.replace(masks=masks, instance_ids=ids))


# Training batches cut into the ground-truth sampling database.
GT_DATABASE_BATCHES = 8


def gt_database(source: Callable[[int], Batch], batches: int, grid) -> ObjectDatabase:
    """Object database for ground-truth sampling from the first ``batches`` training batches
    (``augment.gt_sampling > 0``)."""
    frames = jax.tree.map(lambda *xs: np.concatenate(xs), *[source(i) for i in range(batches)])
    database = build_object_database(frames, grid)  # one compile for all the frames
    if database.classes.shape[0] == 0:
        raise ValueError(
            f"augment.gt_sampling: the first {batches} training batches hold no object clear "
            "of the grid's edge to paste (the object database is empty); set "
            "augment.gt_sampling=0 or check the data's labels"
        )
    return database


class SimSource:
    """On-device simulated batches: batch of step s = ``generate_batch(fold_in(key, s))``
    from the simulator's ``split`` (train, val or test layouts)."""

    def __init__(self, config: Config, key: jax.Array, split: str = "train"):
        from indoorbev_sim import generate_batch

        self.key = key
        # fold_in inside the jit: one dispatch a batch, not an eager fold_in before it.
        self._generate = jax.jit(
            lambda k, step: generate_batch(jax.random.fold_in(k, step), config, split)
        )

    def __call__(self, step: int) -> Batch:
        return self._generate(self.key, step)


class KittiSource:
    """Batches from a KITTI-style folder, reshuffled each epoch from (seed, epoch).

    A frame that fails to load is reported by name; with ``skip_bad`` it is replaced by the
    next good frame of the epoch, otherwise the error stops the run at once.
    """

    def __init__(self, root, split: str, config: Config, seed: int, skip_bad: bool = False):
        from indoorbev_jax.data.dataset import KittiDataset

        self.dataset = KittiDataset(root, split, config)
        self.batch_size = config.train.batch_size
        if len(self.dataset) < self.batch_size:
            raise ValueError(
                f"{root}/{split}.txt: {len(self.dataset)} frames, fewer than "
                f"train.batch_size={self.batch_size}"
            )
        self.seed = seed
        self.skip_bad = skip_bad
        self.bad: set[int] = set()
        if not skip_bad:  # before the run starts (and writes config.json), not at step k
            for frame_id in self.dataset.ids:
                path = kitti.frame_paths(root, frame_id)["labels"]
                check_object_count(path, len(kitti.read_labels(path, config.data)), config)

    def _order(self, epoch: int) -> np.ndarray:
        return np.random.default_rng([self.seed, epoch]).permutation(len(self.dataset))

    def __call__(self, step: int) -> Batch:
        from indoorbev_jax.data.dataset import collate

        per_epoch = len(self.dataset) // self.batch_size
        epoch, k = divmod(step, per_epoch)
        order = self._order(epoch)
        items, pos = [], k * self.batch_size
        while len(items) < self.batch_size:
            index = int(order[pos % len(order)])
            pos += 1
            if index in self.bad:
                continue
            frame = load_or_skip(self.dataset, index, self.skip_bad, "frame")
            if frame is not None:
                items.append(frame)
                continue
            self.bad.add(index)
            if len(self.bad) == len(self.dataset):
                raise kitti.DatasetError(f"{self.dataset.root}: no readable frame left")
        return collate(items)


def check_object_count(path, objects: int, config: Config) -> None:
    """More objects than ``data.max_objects`` is an error: the targets keep the first
    ones, and the rest would train (and be scored) as background, without a word."""
    limit = config.data.max_objects
    if objects > limit:
        raise kitti.DatasetError(
            f"{path}: {objects} objects, more than data.max_objects={limit} (the rest would "
            f"be background targets); --set data.max_objects={objects} or more"
        )


def load_or_skip(dataset, index: int, skip_bad: bool, kind: str) -> Batch | None:
    """Frame ``index`` of a ``KittiDataset``; a malformed one (or one with more objects than
    ``data.max_objects``) raises its error naming the file, or with ``skip_bad`` is
    reported by name (as a ``kind``) and gives None."""
    try:
        frame, stats = dataset.load(index)
        path = kitti.frame_paths(dataset.root, dataset.ids[index])["labels"]
        check_object_count(path, stats.objects, dataset.config)
        return frame
    except (kitti.DatasetError, OSError) as e:
        if not skip_bad:
            raise
        log.warning("skipping malformed %s %s: %s", kind, dataset.ids[index], e)
        return None


def prefetch(source: Callable[[int], Batch], start: int, stop: int, size: int = 2) -> Iterator:
    """Yields ``source(s)`` for s in [start, stop), computed ``size`` steps ahead on a
    background thread; an error in the source is raised at the step it belongs to."""
    q: queue.Queue = queue.Queue(maxsize=size)
    done = threading.Event()

    def work():
        for s in range(start, stop):
            if done.is_set():
                return
            try:
                item = (s, source(s), None)
            except Exception as e:  # noqa: BLE001 - handed to the consumer
                item = (s, None, e)
            q.put(item)
            if item[2] is not None:
                return

    worker = threading.Thread(target=work, daemon=True, name="indoorbev-prefetch")
    worker.start()
    try:
        for _ in range(start, stop):
            s, batch, error = q.get()
            if error is not None:
                raise error
            yield s, batch
    finally:
        done.set()
        # Let the worker stop and finish what it dispatched: the simulator's Warp kernels
        # call back into Python, and an interpreter that shuts down under a queued one
        # can hang in its exit (seen after an error raised mid-run).
        while worker.is_alive() or not q.empty():
            try:
                _, batch, _ = q.get(timeout=0.1)
            except queue.Empty:
                continue
            if batch is not None:
                jax.block_until_ready(batch)


def val_batches(val_ds, batch_size: int, batches: int, skip_bad: bool) -> list[Batch]:
    """The first ``batches`` validation batches; with ``skip_bad`` a malformed frame is
    reported by name and left out, as for training (else its error stops the start)."""
    from indoorbev_jax.data.dataset import collate

    items = []
    for index in range(len(val_ds)):
        if len(items) == batches * batch_size:
            break
        frame = load_or_skip(val_ds, index, skip_bad, "validation frame")
        items += [] if frame is None else [frame]
    if not items:
        raise kitti.DatasetError(f"{val_ds.root / 'val.txt'}: no readable frame to validate on")
    return [collate(items[k : k + batch_size]) for k in range(0, len(items), batch_size)]
