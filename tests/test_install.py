"""constraints.txt, the versions `make` installs, against pyproject.toml's requirements."""

from __future__ import annotations

import re
import shutil
import subprocess
import sys
import tomllib
import zipfile
from pathlib import Path

import pytest
from packaging.requirements import Requirement
from packaging.utils import canonicalize_name
from packaging.version import Version

ROOT = Path(__file__).resolve().parents[1]
PIN = re.compile(r"^([A-Za-z0-9][A-Za-z0-9._-]*)==([^\s;#]+)$")


def read_pins() -> dict[str, Version]:
    pins: dict[str, Version] = {}
    path = ROOT / "constraints.txt"
    for lineno, line in enumerate(path.read_text().splitlines(), start=1):
        if not line.strip() or line.startswith("#"):
            continue
        found = PIN.match(line.strip())
        assert found, f"constraints.txt line {lineno}: expected NAME==VERSION, got {line!r}"
        name = canonicalize_name(found.group(1))
        assert name not in pins, f"constraints.txt line {lineno}: {name} is pinned twice"
        pins[name] = Version(found.group(2))
    return pins


def declared_requirements() -> list[tuple[str, Requirement]]:
    project = tomllib.loads((ROOT / "pyproject.toml").read_text())["project"]
    found = [("dependencies", Requirement(r)) for r in project["dependencies"]]
    for extra, reqs in project["optional-dependencies"].items():
        found += [(f"optional-dependencies.{extra}", Requirement(r)) for r in reqs]
    return found


def test_every_declared_requirement_is_pinned_within_its_bounds():
    pins = read_pins()
    declared = declared_requirements()
    assert len(declared) > 10
    for where, req in declared:
        name = canonicalize_name(req.name)
        assert name in pins, f"pyproject {where}: {req.name} has no pin in constraints.txt"
        assert req.specifier.contains(pins[name], prereleases=True), (
            f"pyproject {where}: {req} excludes the pinned {req.name}=={pins[name]}"
        )


@pytest.mark.parametrize("name", ["jax", "jaxlib", "flax", "optax", "warp-lang", "mujoco-mjx"])
def test_the_core_stack_is_pinned(name):
    # jaxlib is no requirement of ours but must move with jax.
    assert canonicalize_name(name) in read_pins()


def test_a_built_package_holds_every_module(tmp_path):
    # What `pip install .` (not -e) installs: the wheel pip builds, from a copy without the
    # editable install's egg-info (whose file list filled the gaps of a local build).
    src = tmp_path / "src"
    ignore = shutil.ignore_patterns("__pycache__")
    shutil.copytree(ROOT / "src", src / "src", ignore=ignore)
    shutil.copytree(ROOT / "sim", src / "sim", ignore=ignore)
    shutil.copy(ROOT / "pyproject.toml", src)
    shutil.copy(ROOT / "README.md", src)
    subprocess.run(
        [sys.executable, "-m", "pip", "wheel", str(src), "--no-deps", "-q", "-w", str(tmp_path)],
        check=True,
        capture_output=True,
    )
    (wheel,) = tmp_path.glob("*.whl")
    built = {n for n in zipfile.ZipFile(wheel).namelist() if n.endswith(".py")}
    for package, folder in (("indoorbev_jax", "src/indoorbev_jax"), ("indoorbev_sim", "sim")):
        source = {f"{package}/{p.relative_to(src / folder).as_posix()}"
                  for p in (src / folder).rglob("*.py")}  # fmt: skip
        assert source <= built, f"{package}: not in the wheel {sorted(source - built)}"
