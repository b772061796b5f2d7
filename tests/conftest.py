"""Test-session settings, applied before JAX starts (subprocesses inherit them), and the
file order.

The suite is compile-bound: XLA's backend optimisation level 0 compiles several times
faster and the tiny test configs run fast enough without the optimisations.
"""

import contextlib
import errno
import os
from pathlib import Path

import pytest

os.environ.setdefault("JAX_PLATFORMS", "cpu")
if "xla_backend_optimization_level" not in os.environ.get("XLA_FLAGS", ""):
    flags = os.environ.get("XLA_FLAGS", "") + " --xla_backend_optimization_level=0"
    os.environ["XLA_FLAGS"] = flags.strip()


# The longest files start first, so with pytest-xdist (``make test``) they do not end last.
LONGEST_FIRST = ("test_train.py", "test_chunked.py", "test_ros2.py", "test_query_options.py")


def pytest_collection_modifyitems(items):
    def rank(item):
        name = item.path.name
        return LONGEST_FIRST.index(name) if name in LONGEST_FIRST else len(LONGEST_FIRST)

    items.sort(key=rank)  # stable: the order within a file stays as written


@pytest.fixture
def full_disk():
    """A context in which ``Path.write_text`` writes 10 characters and then fails as a full
    disk does: what an atomic write must survive with the old file whole."""
    real_write = Path.write_text

    def cut_off(self, text, *args, **kwargs):
        real_write(self, text[:10], *args, **kwargs)
        raise OSError(errno.ENOSPC, "No space left on device")

    @contextlib.contextmanager
    def context():
        with pytest.MonkeyPatch.context() as patch:
            patch.setattr(Path, "write_text", cut_off)
            yield

    return context


@pytest.fixture
def errors_without_blocking():
    """``run(reads)``: {name: the exception ``reads[name]()`` raised, or None}, the reads
    made in a daemon thread, so that one that blocks (a pipe opened for reading waits for
    a writer forever) fails the test after ``timeout`` seconds instead of hanging the
    suite."""
    import threading

    def run(reads: dict, timeout: float = 30.0) -> dict:
        errors = {}

        def read_all():
            for name, read in reads.items():
                try:
                    read()
                    errors[name] = None
                except Exception as e:  # noqa: BLE001 - the test checks what was raised
                    errors[name] = e

        reading = threading.Thread(target=read_all, daemon=True)
        reading.start()
        reading.join(timeout)
        assert not reading.is_alive(), f"a read blocked: {sorted(set(reads) - set(errors))}"
        return errors

    return run
