"""Lidar scan patterns: unit ray directions in the sensor frame plus per-ray time offsets.

Every pattern is a frozen dataclass whose ``frame(k)`` is a pure, jittable function of the
frame index ``k`` (a Python int or a traced int32 scalar) returning a ``ScanFrame``. The ray
count ``num_rays`` is static, and ``covers(directions)`` says which directions (sensor frame)
lie in the pattern's field of view. Sensor frame: x forward, y left, z up; azimuth about +z
from +x, elevation above the x-y plane.

Patterns:
  * ``Mid360Pattern``: Livox MID-360-like non-repetitive scan written from the public spec
    (360 deg horizontal, -7 to +52 deg vertical, 200k points/s, 10 Hz, 4 emitters). The
    proprietary prism trajectory is not published; ours sweeps each emitter's azimuth once per
    frame while its elevation follows a triangle wave whose frequency is incommensurate with
    the frame rate, so frame k + 1 lands between the rays of frame k and the coverage keeps
    filling the field of view as frames accumulate (measured in tests/sim/test_patterns.py).
  * ``SpinningPattern``: multi-beam spinning lidar (``vlp16()``, ``os128()`` presets or any
    list of beam elevations), repetitive by design.
  * ``GridPattern``: a regular azimuth x elevation grid.
"""

from __future__ import annotations

import dataclasses
import math

import jax
import jax.numpy as jnp
import numpy as np
from flax import struct

_GOLDEN = (np.sqrt(5.0) - 1.0) / 2.0  # most irrational number: best-spread phase steps


@struct.dataclass
class ScanFrame:
    """One frame of a scan pattern.

    Attributes:
      directions: float32 [R, 3], unit vectors in the sensor frame.
      time_offsets: float32 [R], seconds since the start of the frame (firing times).
      start_time: float32 [], frame start time, k / frame_rate seconds.
    """

    directions: jax.Array
    time_offsets: jax.Array
    start_time: jax.Array


def _elevation(directions: jax.Array) -> jax.Array:
    """Elevation (radians) of directions [..., 3] in the sensor frame."""
    unit = directions / jnp.maximum(jnp.linalg.norm(directions, axis=-1, keepdims=True), 1e-12)
    return jnp.arcsin(jnp.clip(unit[..., 2], -1.0, 1.0))


def _within(angle: jax.Array, lo_deg: float, hi_deg: float) -> jax.Array:
    slack = 1e-6  # float32 rounding of rays fired exactly at a limit
    return (angle >= np.deg2rad(lo_deg) - slack) & (angle <= np.deg2rad(hi_deg) + slack)


def spherical_to_unit(azimuth: jax.Array, elevation: jax.Array) -> jax.Array:
    """Unit vectors [..., 3] from azimuth/elevation (radians) of broadcastable shapes [...]."""
    azimuth, elevation = jnp.broadcast_arrays(azimuth, elevation)
    ce = jnp.cos(elevation)
    return jnp.stack([ce * jnp.cos(azimuth), ce * jnp.sin(azimuth), jnp.sin(elevation)], -1)


def _frac_u32(step: float) -> np.uint32:
    """A phase step in [0, 1) as a 32-bit fixed-point fraction (exact modular arithmetic)."""
    return np.uint32(int(round((step % 1.0) * 2.0**32)) % 2**32)


def _u32_to_unit(x: jax.Array) -> jax.Array:
    """uint32 fixed-point fraction -> float32 in [0, 1)."""
    return (x >> 8).astype(jnp.float32) * jnp.float32(2.0**-24)


def _check_rate_and_elevations(pattern, elevations_deg) -> None:
    """A finite frame rate > 0 (times divide by it) and elevations in [-90, 90] degrees
    (beyond, they fold back silently while ``covers`` claims the range)."""
    name = type(pattern).__name__
    if not (math.isfinite(pattern.frame_rate) and pattern.frame_rate > 0):
        raise ValueError(f"{name}.frame_rate must be finite and > 0, got {pattern.frame_rate}")
    bad = [e for e in elevations_deg if not -90.0 <= e <= 90.0]
    if bad:
        raise ValueError(f"{name}: elevations must lie in [-90, 90] degrees, got {bad}")


@dataclasses.dataclass(frozen=True)
class Mid360Pattern:
    """Livox MID-360-like non-repetitive pattern.

    Attributes:
      points_per_second: total firing rate of all emitters (spec: 200k).
      frame_rate: frames per second (spec: 10 Hz).
      num_emitters: laser channels firing in parallel (MID-360 reports 4 lines).
      elevation_min_deg, elevation_max_deg: vertical field of view (spec: -7 to 52 deg).
      elevation_cycles_per_frame: triangle-wave periods of each emitter's elevation sweep per
        frame; a non-integer (irrational) value makes consecutive frames interleave.
    """

    points_per_second: int = 200_000
    frame_rate: float = 10.0
    num_emitters: int = 4
    elevation_min_deg: float = -7.0
    elevation_max_deg: float = 52.0
    elevation_cycles_per_frame: float = 161.80339887

    def __post_init__(self):
        _check_rate_and_elevations(self, (self.elevation_min_deg, self.elevation_max_deg))
        if not (isinstance(self.num_emitters, (int, np.integer)) and self.num_emitters >= 1):
            raise ValueError(
                f"Mid360Pattern.num_emitters must be an int >= 1, got {self.num_emitters!r}"
            )
        rays = self.points_per_second / self.frame_rate
        whole = math.isfinite(rays) and abs(rays - round(rays)) < 1e-9
        if not (whole and round(rays) % self.num_emitters == 0):
            raise ValueError(
                f"Mid360Pattern: points_per_second / frame_rate = {rays:g} rays a frame; "
                f"expected a whole multiple of num_emitters ({self.num_emitters}) so every "
                f"emitter fires a whole number of rays"
            )
        if not self.elevation_min_deg < self.elevation_max_deg:
            raise ValueError("Mid360Pattern.elevation_min_deg must be below elevation_max_deg")

    @property
    def num_rays(self) -> int:
        return int(round(self.points_per_second / self.frame_rate))

    def covers(self, directions: jax.Array) -> jax.Array:
        """bool [...]: whether the field of view holds directions [..., 3] (sensor frame)."""
        return _within(_elevation(directions), self.elevation_min_deg, self.elevation_max_deg)

    def frame(self, k) -> ScanFrame:
        """Frame k: directions [R, 3] (R = points_per_second / frame_rate) and firing times."""
        nr = self.num_rays
        per = nr // self.num_emitters
        if isinstance(k, (int, np.integer)):  # wrap as a traced int32 k does (-1: 2^32 - 1)
            k = int(k) % 2**32
        k = jnp.asarray(k, jnp.uint32)
        i = jnp.arange(per, dtype=jnp.uint32)  # firing slot within the frame
        e = jnp.arange(self.num_emitters, dtype=jnp.uint32)
        # Azimuth: one turn per frame, emitters spread evenly, and the whole pattern rotated
        # by a golden-ratio fraction of one slot per frame so slots never repeat.
        slot = i[:, None].astype(jnp.float32) + e[None, :].astype(jnp.float32) / self.num_emitters
        slot_shift = _u32_to_unit(k * _frac_u32(_GOLDEN))
        az = 2.0 * jnp.pi * (slot + slot_shift) / per  # [per, E]
        # Elevation: triangle wave with an irrational number of cycles per frame, phase kept
        # in exact 32-bit fixed point so frame k is exact for any k; each emitter a quarter
        # period apart.
        cyc = self.elevation_cycles_per_frame
        phase_u32 = (
            k * _frac_u32(cyc)
            + i[:, None] * _frac_u32(cyc / per)
            + e[None, :] * _frac_u32(1.0 / self.num_emitters + 0.5 / per)
        )
        ph = _u32_to_unit(phase_u32)
        tri = 1.0 - jnp.abs(2.0 * ph - 1.0)  # [per, E] in [0, 1]
        lo, hi = np.deg2rad(self.elevation_min_deg), np.deg2rad(self.elevation_max_deg)
        # Uniform in sin(elevation) so points spread evenly over the solid angle.
        el = jnp.arcsin(np.sin(lo) + (np.sin(hi) - np.sin(lo)) * tri)
        dirs = spherical_to_unit(az, el).reshape(nr, 3)  # [per * E, 3], slot-major
        times = jnp.repeat(jnp.arange(per, dtype=jnp.float32), self.num_emitters) * (
            self.num_emitters / self.points_per_second
        )
        return ScanFrame(dirs, times, k.astype(jnp.float32) / self.frame_rate)


@dataclasses.dataclass(frozen=True)
class SpinningPattern:
    """Multi-beam spinning lidar: every beam fires once per azimuth column.

    Attributes:
      elevations_deg: beam elevation angles in degrees (16 to 128 beams typical).
      columns: azimuth columns per revolution.
      frame_rate: revolutions per second.
    """

    elevations_deg: tuple[float, ...]
    columns: int = 1024
    frame_rate: float = 10.0

    def __post_init__(self):
        if len(self.elevations_deg) == 0:
            raise ValueError("SpinningPattern.elevations_deg must list at least one beam")
        _check_rate_and_elevations(self, self.elevations_deg)
        if self.columns <= 0:
            raise ValueError("SpinningPattern.columns must be positive")

    @classmethod
    def vlp16(cls) -> SpinningPattern:
        """Velodyne VLP-16-like: 16 beams, -15..+15 deg every 2 deg, 0.2 deg at 10 Hz."""
        return cls(tuple(np.linspace(-15.0, 15.0, 16).tolist()), columns=1800)

    @classmethod
    def os128(cls) -> SpinningPattern:
        """Ouster OS1-128-like: 128 beams uniform over 45 deg (+-22.5), 1024 columns."""
        return cls(tuple(np.linspace(-22.5, 22.5, 128).tolist()), columns=1024)

    @property
    def num_rays(self) -> int:
        return self.columns * len(self.elevations_deg)

    def covers(self, directions: jax.Array) -> jax.Array:
        """bool [...]: whether directions [..., 3] (sensor frame) lie between the lowest and
        the highest beam (the gaps between beams count as covered)."""
        lo, hi = min(self.elevations_deg), max(self.elevations_deg)
        return _within(_elevation(directions), lo, hi)

    def frame(self, k) -> ScanFrame:
        """Frame k: column-major rays [columns * beams, 3]; a spinner repeats every frame."""
        col = jnp.arange(self.columns, dtype=jnp.float32)
        az = 2.0 * jnp.pi * col / self.columns  # [C]
        el = jnp.deg2rad(jnp.asarray(self.elevations_deg, jnp.float32))  # [L]
        dirs = spherical_to_unit(az[:, None], el[None, :]).reshape(-1, 3)  # [C * L, 3]
        times = jnp.repeat(col / (self.columns * self.frame_rate), len(self.elevations_deg))
        start = jnp.asarray(k, jnp.float32) / self.frame_rate
        return ScanFrame(dirs, times, start)


@dataclasses.dataclass(frozen=True)
class GridPattern:
    """Regular grid: ``azimuth_steps`` x ``elevation_steps`` rays, all fired at once.

    Attributes:
      azimuth_steps: columns over [azimuth_min_deg, azimuth_max_deg) (end excluded when the
        span is a full turn).
      elevation_steps: rows over [elevation_min_deg, elevation_max_deg] (ends included).
      frame_rate: frames per second (only sets ``start_time``).
    """

    azimuth_steps: int = 360
    elevation_steps: int = 64
    azimuth_min_deg: float = -180.0
    azimuth_max_deg: float = 180.0
    elevation_min_deg: float = -30.0
    elevation_max_deg: float = 30.0
    frame_rate: float = 10.0

    def __post_init__(self):
        if self.azimuth_steps <= 0 or self.elevation_steps <= 0:
            raise ValueError("GridPattern.azimuth_steps and elevation_steps must be positive")
        _check_rate_and_elevations(self, (self.elevation_min_deg, self.elevation_max_deg))

    @property
    def num_rays(self) -> int:
        return self.azimuth_steps * self.elevation_steps

    def covers(self, directions: jax.Array) -> jax.Array:
        """bool [...]: whether directions [..., 3] (sensor frame) lie in the grid's
        elevation and azimuth spans."""
        inside = _within(_elevation(directions), self.elevation_min_deg, self.elevation_max_deg)
        if np.isclose(self.azimuth_max_deg - self.azimuth_min_deg, 360.0):
            return inside
        azimuth = jnp.arctan2(directions[..., 1], directions[..., 0])
        # Azimuth measured from the span's start, in [0, 2 pi).
        offset = jnp.mod(azimuth - np.deg2rad(self.azimuth_min_deg), 2 * np.pi)
        span = np.deg2rad(self.azimuth_max_deg - self.azimuth_min_deg)
        return inside & (offset <= span + 1e-6)

    def frame(self, k) -> ScanFrame:
        """Frame k: rays [azimuth_steps * elevation_steps, 3], azimuth-major."""
        span = self.azimuth_max_deg - self.azimuth_min_deg
        full = np.isclose(span, 360.0)
        az = np.deg2rad(
            np.linspace(
                self.azimuth_min_deg, self.azimuth_max_deg, self.azimuth_steps, endpoint=not full
            )
        )
        el = np.deg2rad(
            np.linspace(self.elevation_min_deg, self.elevation_max_deg, self.elevation_steps)
        )
        dirs = spherical_to_unit(jnp.asarray(az)[:, None], jnp.asarray(el)[None, :])
        dirs = dirs.reshape(-1, 3).astype(jnp.float32)  # [A * E, 3]
        times = jnp.zeros((self.num_rays,), jnp.float32)
        return ScanFrame(dirs, times, jnp.asarray(k, jnp.float32) / self.frame_rate)
