"""Keep freed host memory in the process, so a jitted step does not page-fault it in anew.

XLA:CPU allocates each execution's temporaries as one block (5.5 GiB for the ``paper``
forward + backward at batch 1) and frees it when the step ends. glibc's malloc serves blocks over
32 MiB with ``mmap`` and gives them back on ``free``; the next step then page-faults every
4 KiB page in again, and the kernel zeroes each one. On the 2-core benchmark machine that
was 9 s of system time in a 13 s step (docs/BENCHMARKS.md, "Fresh pages every step").

``retain_freed_memory`` tells glibc to serve every block from its main heap (one arena,
no ``mmap``) and never to trim that heap, so a step mostly reuses the pages of the steps
before: the ``paper`` train step at batch 2 took 16.8 s instead of 29.1 s (AMD EPYC VM). The
one arena is needed: XLA allocates the temporaries on JAX's worker threads, and a thread's
own arena cannot hold a block over its 64 MiB heap size and maps it even with ``M_MMAP_MAX``
at 0 (without the cap, tests/test_host_memory.py's 66 MiB temporary was faulted in on every
call). The cap also puts every thread behind one malloc lock, which cost 1.1-1.2x on an Intel
Xeon VM (docs/BENCHMARKS.md, "The one-arena cap"). The price, and why it is opt-in: resident
memory never shrinks, and small allocations that land in the freed blocks fragment the heap,
so it keeps growing for a while (in a 64 MiB-temporary probe, to 4-8 temporaries' worth over
30 calls; the paper step peaked at 12.3 GiB RSS for 11.1 GiB of XLA buffers). With
``INDOORBEV_RETAIN_MEMORY=1`` in the environment, importing ``indoorbev_jax`` applies it (so
every experiment script and both commands do); ``retain_freed_memory(force=True)`` applies
it without the variable. It does nothing on a C library other than glibc, and threads that
allocated before it keep their own arenas, so it has to come before the first JAX
computation.
"""

from __future__ import annotations

import ctypes
import os

# mallopt parameters from glibc's <malloc.h>.
M_TRIM_THRESHOLD = -1
M_MMAP_MAX = -4
M_ARENA_MAX = -8

# Whether this process's malloc has been told to retain freed memory.
retained = False


def glibc() -> ctypes.CDLL | None:
    """The running glibc, or None on another C library."""
    try:
        os.confstr("CS_GNU_LIBC_VERSION")
    except (ValueError, OSError, AttributeError):
        return None
    try:
        return ctypes.CDLL("libc.so.6")
    except OSError:
        return None


def retain_freed_memory(force: bool = False) -> bool:
    """Makes glibc keep freed memory for reuse when ``force`` or ``INDOORBEV_RETAIN_MEMORY=1``;
    returns whether the settings took."""
    if not force and os.environ.get("INDOORBEV_RETAIN_MEMORY", "0") != "1":
        return False
    libc = glibc()
    if libc is None:
        return False
    global retained
    # -1 as size_t is the largest threshold: the heap's top is never given back.
    settings = ((M_ARENA_MAX, 1), (M_MMAP_MAX, 0), (M_TRIM_THRESHOLD, -1))
    retained = all(libc.mallopt(param, value) == 1 for param, value in settings)
    return retained
