"""Constants shared by the two ray casters, the Warp kernels and the pure-JAX routines, and by
``lidar.py`` (private). Plain Python numbers, so importing them needs no Warp."""

from __future__ import annotations

import mujoco

MINVAL = 1.0e-15  # mjMINVAL
# A ray counts as parallel to a plane when its direction's normal component is under this
# fraction of its length. MuJoCo's float64 test is v_z > -MINVAL, but a float32 direction
# rotated into the plane's frame carries ~1e-8 of rounding: a ray lying in a tilted plane
# would hit it at t = 0, or 1e8 m away. Any real hit it drops lies beyond 1e6 x the
# origin's height above the plane.
PLANE_PARALLEL = 1.0e-6
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
