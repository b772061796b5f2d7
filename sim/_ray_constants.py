"""Constants shared by the two ray casters, the Warp kernels and the pure-JAX routines, and by
``lidar.py`` (private). Plain Python numbers, so importing them needs no Warp."""

from __future__ import annotations

import mujoco

MINVAL = 1.0e-15  # mjMINVAL
BIG = 1.0e30  # "unbounded": bounding radii and extents of planes, the slab walk's start
# Slack on the culling bounds: they are computed in float32, so shrink them a little to
# stay conservative (a too-small lower bound only costs a test, a too-large one a miss).
BOUND_REL = 1.0e-4
BOUND_ABS = 1.0e-4

# Geom type ids, as mujoco.mjtGeom numbers them.
PLANE = int(mujoco.mjtGeom.mjGEOM_PLANE)
SPHERE = int(mujoco.mjtGeom.mjGEOM_SPHERE)
CAPSULE = int(mujoco.mjtGeom.mjGEOM_CAPSULE)
ELLIPSOID = int(mujoco.mjtGeom.mjGEOM_ELLIPSOID)
CYLINDER = int(mujoco.mjtGeom.mjGEOM_CYLINDER)
BOX = int(mujoco.mjtGeom.mjGEOM_BOX)
