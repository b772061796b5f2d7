#!/usr/bin/env bash
# Fetches, here, the wheels a lent GPU machine lacks for the simulator and training
# (experiments/gpu_paper.sh): its image has JAX, flax, optax, orbax, numpy, scipy, pillow,
# tqdm and protobuf for Python 3.12, but not mujoco, mujoco-mjx, trimesh (imported by
# mujoco-mjx) or tensorboardX. warp-lang is not among them (its wheel alone is 149 MB, over
# the 64 MiB a call carries): the simulator casts with its pure-JAX caster there
# (docs/SIMULATOR.md, "Without Warp"). About 18 MB into .whl/, which git ignores.
set -eu
cd "$(dirname "$0")/.."
grep -qx '/.whl/' .git/info/exclude 2>/dev/null || echo '/.whl/' >> .git/info/exclude
PY=${PY:-.venv/bin/python}
"$PY" -m pip download -q --no-deps --only-binary=:all: --python-version 3.12 \
  --implementation cp --platform manylinux_2_28_x86_64 --platform manylinux_2_27_x86_64 \
  --platform manylinux_2_17_x86_64 --platform manylinux2014_x86_64 -d .whl \
  mujoco==4.0.0 mujoco-core==4.0.0 mujoco-mjx==3.17.0 trimesh==4.8.3 tensorboardX==2.6.4
ls -la .whl
