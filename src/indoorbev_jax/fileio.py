"""Writing files so that a kill or a second job loses nothing.

``atomic_write`` puts a file in place whole or not at all; ``remove_stale_temporaries``
clears what a killed write left; ``hold_folder`` is the lock a long job (training, an
export, a predict run) holds on its output folder, so a second one is refused by name.
"""

from __future__ import annotations

import contextlib
import errno
import fcntl
import logging
import os
import re
import tempfile
import time
from collections.abc import Callable
from pathlib import Path

log = logging.getLogger(__name__)


def _umask() -> int:
    mask = os.umask(0)
    os.umask(mask)
    return mask


# mkstemp makes owner-only files; a dataset is shared, so files get the usual umask mode.
_FILE_MODE = 0o666 & ~_umask()


def file_in_path(folder: Path) -> Path | None:
    """The first of ``folder`` and its parents that is a file (a folder cannot be made
    under it), or None."""
    for part in (*reversed(Path(folder).parents), Path(folder)):
        if os.path.isfile(part):  # False, not an error, for a name too long or unreadable
            return part
    return None


def atomic_write(path: Path, write: Callable[[Path], None]) -> None:
    """Calls ``write(tmp)`` on a temporary file beside ``path``, then renames it into place,
    so that ``path`` is either absent, the old file or the whole new one. The file gets the
    mode a plain ``open`` would give (0o666 less the process umask). Its data reach the
    disk before the rename (fsync, about 2 ms a file): a robot that loses power must not
    keep an empty file under the final name."""
    path = Path(path)
    tmp = None
    try:  # a read-only folder fails in mkdir or mkstemp: named as the file below
        path.parent.mkdir(parents=True, exist_ok=True)
        fd, tmp = tempfile.mkstemp(dir=path.parent, prefix=f".{path.name}.", suffix=".tmp")
        os.close(fd)
        write(Path(tmp))
        os.chmod(tmp, _FILE_MODE)
        fd = os.open(tmp, os.O_RDONLY)
        try:
            os.fsync(fd)
        finally:
            os.close(fd)
        os.replace(tmp, path)
    except OSError as e:
        if tmp is not None:
            Path(tmp).unlink(missing_ok=True)
        # Name the file and the reason: a full disk under ndarray.tofile said only "6464
        # requested and 1024 written"; a file where a folder must be said "File exists".
        reason = e.strerror or str(e)
        if (blocker := file_in_path(path.parent)) is not None:
            reason = f"{blocker} is a file, not a folder"
        raise OSError(e.errno, f"cannot write {path}: {reason}") from e
    except BaseException:
        if tmp is not None:
            Path(tmp).unlink(missing_ok=True)
        raise


# atomic_write's temporary name: mkstemp's ".<name>.<8 characters>.tmp".
_TEMPORARY = re.compile(r"\..+\.[a-z0-9_]{8}\.tmp")


def remove_stale_temporaries(folder: Path, names: str, min_age: float = 60.0) -> None:
    """Removes the temporary files a killed ``atomic_write`` left in ``folder`` for files
    matching the glob ``names``: regular files of its naming, ``min_age`` seconds old (a
    write in flight, of another process writing the same folder, takes milliseconds). A
    user's hidden file of another name is never touched."""
    now = time.time()
    for path in Path(folder).glob(f".{names}.*.tmp"):
        try:
            if (
                _TEMPORARY.fullmatch(path.name)
                and path.is_file()
                and not path.is_symlink()
                and now - path.stat().st_mtime > min_age
            ):
                path.unlink()
        except OSError:  # gone meanwhile, or not ours to remove: left alone
            pass


def age_since(started: float) -> float:
    """``remove_stale_temporaries``' ``min_age`` at the end of a job that has held its
    folder's lock since ``started`` (``time.time()``): a write killed less than a minute
    before the job outlived the clean-up at its start, and one from before the job started
    is no write in flight now. The 1 s floor guards a job that was itself that short."""
    return max(time.time() - started, 1.0)


@contextlib.contextmanager
def hold_folder(folder: str | os.PathLike, job: str, place: str, take: bool = True):
    """Holds an exclusive ``flock`` on ``folder/.lock`` (its content: ``job`` and the pid)
    while the block runs, so that a second job started on the same folder is refused,
    naming the first: two runs writing one folder both ran to the end before. The lock
    goes with its process, a kill -9 included; a left-over file means nothing. A
    filesystem without ``flock`` gets a warning and no lock, a read-only folder no lock;
    ``take=False`` takes none (the other processes of a multi-host run, which share the
    folder). ``folder`` is made if missing.

    Raises:
      ValueError: another process holds the lock; the message names its job and pid and
        suggests another ``place`` (say "workdir" or "--out").
      OSError: ``folder`` cannot be made (named, with the file in its way if there is one).
    """
    folder, lock = Path(folder), None
    try:
        folder.mkdir(parents=True, exist_ok=True)
        lock = _open_lock(folder)
    except OSError as e:
        # Read-only: no run can write here, so there is nothing to lock (a finished
        # predict output on read-only media is still read back and summed up).
        if not (e.errno in (errno.EROFS, errno.EACCES) and folder.is_dir()):
            reason = e.strerror or str(e)
            if (blocker := file_in_path(folder)) is not None:
                reason = f"{blocker} is a file, not a folder"
            raise OSError(e.errno, f"cannot write in {folder}: {reason}") from e
    if lock is None:
        yield
        return
    with lock:
        if take and _take_lock(lock, folder, job, place):
            try:  # unbuffered: a line that failed is not tried again, unnamed, on close
                os.ftruncate(lock.fileno(), 0)
                os.write(lock.fileno(), f"{job}, pid {os.getpid()}\n".encode())
            except OSError as e:  # a full disk: named, as atomic_write names its files
                raise OSError(e.errno, f"cannot write {folder / '.lock'}: {e.strerror}") from e
        yield


def _open_lock(folder: Path, create: bool = True):
    """``folder/.lock`` opened for ``flock``, never through a symlink (whose target the
    lock's line would overwrite)."""
    flags = os.O_RDWR | os.O_APPEND | os.O_NOFOLLOW | (os.O_CREAT if create else 0)
    try:
        fd = os.open(folder / ".lock", flags, 0o666)
    except OSError as e:
        if e.errno == errno.ELOOP:
            raise OSError(e.errno, f"{folder / '.lock'}: a symlink where the lock goes") from e
        raise
    return os.fdopen(fd, "a+")


def check_unheld(folder: str | os.PathLike, job: str, place: str) -> None:
    """Raises ``hold_folder``'s ValueError if a job now holds ``folder``'s lock, so that a
    long run that takes the lock only at its end learns it at the start; no lock is kept."""
    folder = Path(folder)
    if not (folder / ".lock").is_file():
        return
    try:
        lock = _open_lock(folder, create=False)
    except OSError:
        return  # unreadable or gone: the write itself will say
    with lock:
        if _take_lock(lock, folder, job, place):
            fcntl.flock(lock, fcntl.LOCK_UN)


def _take_lock(lock, folder: Path, job: str, place: str) -> bool:
    """``hold_folder``'s lock on the open ``lock`` file: True when taken, False when the job
    goes on without one; another process holding it is a ValueError naming it."""
    try:
        fcntl.flock(lock, fcntl.LOCK_EX | fcntl.LOCK_NB)
    except BlockingIOError:
        lock.seek(0)
        # "export, pid 123"; a lock of an older version holds "pid 123" alone.
        holder, sep, pid = lock.read().strip().rpartition(", ")
        if not sep:
            holder, pid = job, pid or "another process"
        raise ValueError(
            f"{folder}: in use by another {holder} ({pid}); wait for it to end, or use "
            f"another {place}"
        ) from None
    except OSError as e:  # a filesystem without flock (Lustre without -o flock)
        if e.errno not in (errno.ENOSYS, errno.EOPNOTSUPP, errno.ENOLCK):
            raise
        log.warning("%s: cannot lock the folder (%s); running without", folder, e)
        return False
    return True
