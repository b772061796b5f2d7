"""Recording what a node publishes into a rosbag2 folder, through ``rosbags`` (no ROS)."""

from __future__ import annotations

import os
import queue
import shutil
import threading
from pathlib import Path

from indoorbev_jax.rosbag import partial_path

STORAGES = ("sqlite3", "mcap")


def ensure_new(path: str | os.PathLike) -> Path:
    """``path`` as a Path; a ``FileExistsError`` when something is there already, or when
    ``<path>.partial`` (an interrupted recording) is: it is the user's to keep or delete; an
    ``OSError`` naming ``path`` when ``<path>.partial`` cannot be made (its parent folders
    are made, as the recording would); a ``ValueError`` for an empty path (an unset shell
    variable: ``if record:`` took it for no recording, and recorded nothing)."""
    if str(path) == "":
        raise ValueError("record: an empty path; expected a new folder for the bag")
    path = Path(path)
    if path.exists():
        raise FileExistsError(f"{path}: already exists; record into a new folder")
    partial = partial_path(path)
    if partial.exists():
        raise FileExistsError(
            f"{partial}: left by an interrupted recording into {path} (a killed mcap "
            "recording can be recovered with `mcap recover`; a killed sqlite3 one holds no "
            "message); move or delete it, or record into a new folder"
        )
    try:  # a parent that is a file, or not writable: found now, not after a warm-up
        partial.mkdir(parents=True)
        partial.rmdir()
    except OSError as e:
        raise OSError(f"{path}: cannot record here ({e.strerror or e}: {e.filename})") from e
    return path


class BagRecorder:
    """Writes serialized messages (the bytes a node publishes) into a rosbag2 folder.

    A thread of its own does all the writing (sqlite objects must stay in the thread that
    made them, and disk writes stay off the inference loop); ``write`` only queues. The
    bag is written under ``<path>.partial/`` and moved to ``path`` by ``close``, so a
    folder under the final name is always a complete bag.

    Args:
      path: the bag folder to create (it must not exist).
      topics: {topic: message type name}, e.g. ``{"/points": "sensor_msgs/msg/PointCloud2"}``.
      ts: the ``rosbags`` typestore the messages were serialized with.
      storage: "sqlite3" or "mcap".
    """

    def __init__(self, path: str | os.PathLike, topics: dict[str, str], ts, storage="sqlite3"):
        if storage not in STORAGES:
            raise ValueError(f"storage: expected one of {STORAGES}, got '{storage}'")
        self.path = ensure_new(path)
        self._partial = partial_path(self.path)
        self._partial.mkdir(parents=True)
        self.counts = dict.fromkeys(topics, 0)
        self._queue: queue.SimpleQueue = queue.SimpleQueue()
        self._error: BaseException | None = None
        self._opened = threading.Event()
        self._closed = False
        self._thread = threading.Thread(
            target=self._run, args=(topics, ts, storage), name="bag-recorder", daemon=True
        )
        self._thread.start()
        self._opened.wait()
        if self._error is not None:  # nothing was recorded: leave nothing behind
            shutil.rmtree(self._partial, ignore_errors=True)
            self._raise()

    def _run(self, topics, ts, storage) -> None:
        from rosbags.rosbag2 import StoragePlugin, Writer

        try:
            plugin = StoragePlugin.MCAP if storage == "mcap" else StoragePlugin.SQLITE3
            writer = Writer(self._partial / self.path.name, version=8, storage_plugin=plugin)
            writer.open()
            conns = {t: writer.add_connection(t, m, typestore=ts) for t, m in topics.items()}
        except BaseException as e:  # noqa: BLE001 - reported by the constructor
            self._error = e
            self._opened.set()
            return
        self._opened.set()
        try:
            while (item := self._queue.get()) is not None:
                topic, stamp, raw = item
                writer.write(conns[topic], stamp, raw)
                self.counts[topic] += 1
        except BaseException as e:  # noqa: BLE001 - reported by close
            self._error = e
        finally:
            try:
                writer.close()
            except BaseException as e:  # noqa: BLE001 - a full disk, say: reported by close
                self._error = self._error or e

    def _raise(self) -> None:
        if self._error is not None:
            raise RuntimeError(f"{self.path}: recording failed: {self._error}") from self._error

    @property
    def error(self) -> str | None:
        """Why the recording stopped (its writer failed: a full disk, say), else None."""
        return None if self._error is None else f"{self.path}: recording failed: {self._error}"

    @property
    def partial(self) -> Path:
        """The folder the bag is written in until ``close`` moves it (kept when it fails)."""
        return self._partial

    def write(self, topic: str, stamp: int, raw: bytes) -> bool:
        """Queues one serialized message, logged at ``stamp`` (ns). Returns False, dropping
        the message, once the writer has failed (``error``): nothing more is queued, so a
        node that goes on runs in bounded memory (it held every later message before)."""
        if topic not in self.counts:
            raise KeyError(f"{topic}: not one of the recorded topics {sorted(self.counts)}")
        if self._error is not None:
            return False
        self._queue.put((topic, stamp, bytes(raw)))
        return True

    def close(self) -> Path:
        """Writes what is queued, finishes the bag and moves it under its final name; a
        ``RuntimeError`` when the writer failed, naming what it wrote and where (``partial``,
        kept)."""
        if not self._closed:
            self._closed = True
            self._queue.put(None)
            self._thread.join()
            if self._error is not None:
                raise RuntimeError(
                    f"{self.error}; {self.counts} messages were written, into {self._partial}"
                ) from self._error
            os.replace(self._partial / self.path.name, self.path)
            self._partial.rmdir()
        return self.path


def read_bag(bag: str | os.PathLike) -> dict[str, list[tuple[int, bytes]]]:
    """{topic: [(stamp ns, serialized message)]} of a bag, in time order per topic."""
    from rosbags.rosbag2 import Reader

    out: dict[str, list[tuple[int, bytes]]] = {}
    with Reader(bag) as reader:
        for conn, stamp, raw in reader.messages():
            out.setdefault(conn.topic, []).append((stamp, bytes(raw)))
    return out
