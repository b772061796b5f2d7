"""indoorbev_jax.host_memory: a jitted step reuses the pages its last call freed."""

import json
import os
import subprocess
import sys
from pathlib import Path

import pytest

from indoorbev_jax import host_memory

# A jitted step whose temporary (the 4096 x 4096 product, 64 MiB) is over glibc's largest
# mmap threshold (32 MiB); prints its temp size and the minor page faults of each of 16 warm
# calls.
PROBE = """
import json, resource, sys
from indoorbev_jax import host_memory  # the import applies it when asked
retained = host_memory.retained
import jax, jax.numpy as jnp
x = jnp.linspace(0.0, 1.0, 4096 * 64, dtype=jnp.float32).reshape(4096, 64)
step = jax.jit(lambda x: jnp.tanh(x @ x.T).sum(axis=1)).lower(x).compile()
for _ in range(4):
    step(x).block_until_ready()
faults = []
for _ in range(16):
    before = resource.getrusage(resource.RUSAGE_SELF).ru_minflt
    step(x).block_until_ready()
    faults.append(resource.getrusage(resource.RUSAGE_SELF).ru_minflt - before)
temp = step.memory_analysis().temp_size_in_bytes
print(json.dumps({"retained": retained, "faults": faults, "temp": temp}))
"""

THP = Path("/sys/kernel/mm/transparent_hugepage/enabled")


def probe(**env) -> dict:
    out = subprocess.run(
        [sys.executable, "-c", PROBE],
        env=dict(os.environ, JAX_PLATFORMS="cpu", **env),
        capture_output=True,
        text=True,
        timeout=300,
    )
    assert out.returncode == 0, out.stderr[-2000:]
    return json.loads(out.stdout.splitlines()[-1])


def test_off_unless_asked(monkeypatch):
    monkeypatch.delenv("INDOORBEV_RETAIN_MEMORY", raising=False)
    assert host_memory.retain_freed_memory() is False
    for value in ("0", "", "false", "no", "off"):  # documented opt-in: =1, nothing else
        monkeypatch.setenv("INDOORBEV_RETAIN_MEMORY", value)
        assert host_memory.retain_freed_memory() is False, value


def test_the_settings_are_one_arena_no_mmap_and_no_trim(monkeypatch):
    """The mallopt calls, seen through a fake glibc: all three settings, with <malloc.h>'s
    parameter numbers (M_ARENA_MAX -8, M_MMAP_MAX -4, M_TRIM_THRESHOLD -1), and retained
    only if every one took. A mutation audit: two arenas, a wrong parameter number, a
    setting left out and "any one took" were not seen by the probe below on every machine."""
    calls, refused = [], set()

    class FakeGlibc:
        def mallopt(self, param, value):
            calls.append((param, value))
            return 0 if param in refused else 1  # mallopt: 1 on success

    monkeypatch.setattr(host_memory, "glibc", FakeGlibc)
    monkeypatch.setattr(host_memory, "retained", False)
    assert host_memory.retain_freed_memory(force=True) is True and host_memory.retained
    # -1 as size_t: the largest trim threshold, so the heap's top is never given back.
    assert sorted(calls) == [(-8, 1), (-4, 0), (-1, -1)]
    for param in (-8, -4, -1):
        refused, calls[:] = {param}, []
        assert host_memory.retain_freed_memory(force=True) is False, param
        assert not host_memory.retained


@pytest.mark.skipif(host_memory.glibc() is None, reason="mallopt settings are glibc's")
def test_retained_memory_is_not_faulted_in_again():
    retained = probe(INDOORBEV_RETAIN_MEMORY="1")
    assert retained["retained"] is True
    pages = retained["temp"] // 4096  # 4 KiB pages of one call's temporary
    assert retained["temp"] >= 64 * 2**20
    # A call faults the temporary in anew when it lands on fresh pages: with glibc's
    # default on every call; retained only while the fragmented heap still grows (seen:
    # 0-4 of 16 calls after 4 warm ones).
    assert sum(f > 0.5 * pages for f in retained["faults"]) <= 8, retained
    default = probe()
    assert default["retained"] is False
    # With 4 KiB pages glibc's default faults the whole temporary in on every call; with
    # transparent huge pages always on, a fault maps 2 MiB and the count says little.
    if THP.exists() and "[always]" not in THP.read_text():
        assert sum(f > 0.5 * pages for f in default["faults"]) >= 12, default
