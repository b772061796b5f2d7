"""How the lidar sits on the robot: clouds from a mount the model was not trained on.

The simulator trains the model on a level lidar (no roll or pitch) between
``sim.sensor_height`` metres above the floor (DESIGN section 2: x forward, y left, z up,
origin at the sensor). A MID-360 is often pitched down, hung upside down or carried higher.
``LidarMount`` maps such a cloud into the frame the model knows:

- ``roll, pitch, yaw`` (degrees) are the lidar's orientation in a level frame, as in a URDF
  joint's ``rpy`` (fixed axes: R = Rz(yaw) Ry(pitch) Rx(roll)); each point becomes R p. The
  outputs are then in that level frame: origin at the lidar, z up, x along yaw 0.
- ``height`` (metres above the floor), when outside the trained heights, lifts or lowers the
  cloud so the floor lies where it did in training (the nearest trained height); the
  outputs' z is moved back, so it stays relative to the lidar.

Example::

    mount = LidarMount(pitch=20.0, height=1.1)  # pitched 20 degrees down, 1.1 m up
    level = mount.apply(points, trained_heights=(0.35, 0.8))  # [N, 4], z lifted 0.3 m
"""

from __future__ import annotations

import dataclasses
import math

import numpy as np

from indoorbev_jax.geometry import as_points


@dataclasses.dataclass(frozen=True)
class LidarMount:
    """The lidar's orientation in a level frame (degrees) and height above the floor (m).

    ``height=None`` leaves z as it is.
    """

    roll: float = 0.0
    pitch: float = 0.0
    yaw: float = 0.0
    height: float | None = None

    def __post_init__(self):
        for name in ("roll", "pitch", "yaw"):
            if not math.isfinite(getattr(self, name)):
                raise ValueError(f"lidar mount {name}: expected degrees, got {getattr(self, name)}")
        if self.height is not None and not _is_height(self.height):
            raise ValueError(f"lidar height: expected metres >= 0, got {self.height}")

    @property
    def rotated(self) -> bool:
        """Whether the outputs are in a frame other than the cloud's (yaw 360 is not)."""
        return not np.allclose(self.rotation(), np.eye(3), rtol=0.0, atol=1e-12)

    def rotation(self) -> np.ndarray:
        """float64 [3, 3]: R = Rz(yaw) Ry(pitch) Rx(roll), lidar-frame vectors to level."""
        return rpy_matrix(np.array([self.roll, self.pitch, self.yaw], np.float64))

    def z_offset(self, trained_heights: tuple[float, float]) -> float:
        """Metres added to z so the floor lies as it did in training: the height minus the
        nearest trained height (0 without a height or within ``trained_heights``)."""
        if self.height is None:
            return 0.0
        lo, hi = trained_heights
        return float(self.height - min(max(self.height, lo), hi))

    def levelled(self, points: np.ndarray) -> np.ndarray:
        """float32 [N, 4]: ``points`` [N, 4] (x, y, z, intensity) rotated into the level
        frame (no height move); intensity (and NaN) carried through."""
        return self._turned(points, transpose=True)

    def unlevelled(self, points: np.ndarray) -> np.ndarray:
        """float32 [N, 4]: the inverse of ``levelled``, level-frame ``points`` as the tilted
        lidar delivers them (R^T p)."""
        return self._turned(points, transpose=False)

    def _turned(self, points: np.ndarray, transpose: bool) -> np.ndarray:
        """float32 [N, 4]: each point's xyz times R^T (R p) or R (R^T p), in float64."""
        points = as_points(points)
        out = points.copy()
        if self.rotated:
            rotation = self.rotation()
            with np.errstate(invalid="ignore"):  # an Inf coordinate: NaN, invalid anyway
                out[:, :3] = points[:, :3].astype(np.float64) @ (
                    rotation.T if transpose else rotation
                )
        return out

    def apply(self, points: np.ndarray, trained_heights: tuple[float, float]) -> np.ndarray:
        """float32 [N, 4]: ``levelled`` points shifted by ``z_offset``, as the model sees them."""
        out = self.levelled(points)
        out[:, 2] += self.z_offset(trained_heights)
        return out

    def describe(self, trained_heights: tuple[float, float]) -> str:
        """One line for logs: what is done to the clouds."""
        parts = []
        if self.rotated:
            rpy = f"roll {self.roll:g}, pitch {self.pitch:g}, yaw {self.yaw:g} deg"
            parts.append(f"levelled (lidar at {rpy}); outputs in the level frame")
        offset = self.z_offset(trained_heights)
        if offset:
            lo, hi = trained_heights
            parts.append(
                f"z {offset:+.3g} m (lidar {self.height:g} m above the floor, trained "
                f"{lo:g}-{hi:g} m; output z moved back)"
            )
        return "; ".join(parts) or "as read (level lidar within the trained heights)"

    def effect(self, trained_heights: tuple[float, float]) -> dict[str, float]:
        """What the mount does to the outputs, for a run's record: the angles when it
        rotates, ``z_offset`` when it moves; empty when the clouds are read as they are."""
        done = {"roll": self.roll, "pitch": self.pitch, "yaw": self.yaw} if self.rotated else {}
        if offset := self.z_offset(trained_heights):
            done["z_offset"] = offset
        return done

    def radians_hint(self) -> str | None:
        """A note when the angles look like radians (a URDF's rpy) given as degrees."""
        angles = [a for a in (self.roll, self.pitch, self.yaw) if a]
        if angles and all(abs(a) <= math.pi for a in angles) and any(a % 1 for a in angles):
            deg = ",".join(f"{math.degrees(a):.4g}" for a in (self.roll, self.pitch, self.yaw))
            return (
                f"--lidar-rpy is in degrees: {self.roll:g},{self.pitch:g},{self.yaw:g} is a "
                f"tilt of under 4 degrees; if these are a URDF's radians, pass {deg}"
            )
        return None

    def notes(self, config) -> list[str]:
        """The notes (``radians_hint``, ``tilt_hint``) that apply to this mount for a model
        trained with ``config`` (its ``Config``)."""
        trained = config.sim
        every_direction = config.train.augment and config.augment.rotation >= math.pi - 1e-6
        hints = (
            self.radians_hint(),
            self.tilt_hint(trained.sensor_rpy, trained.sensor_tilt_jitter, every_direction),
        )
        return [hint for hint in hints if hint]

    def tilt(self) -> float:
        """Degrees between the lidar's z axis and the level frame's (yaw does not tilt)."""
        return math.degrees(math.acos(float(np.clip(self.rotation()[2, 2], -1.0, 1.0))))

    def tilt_hint(
        self,
        trained_rpy: tuple[float, float, float],
        trained_jitter: float = 0.0,
        every_direction: bool = False,
    ) -> str | None:
        """A note when this mount is not the model's: one tilted further than
        ``LEVEL_TOLERANCE`` degrees for a model trained on a level lidar, or one further than
        a degree (or the jitter) from the tilt the model was trained on (``sim.sensor_rpy``,
        or tilts within ``sim.sensor_tilt_jitter`` of it). A model knows its tilts' coverage.

        ``every_direction``: training turned every scene about z by up to 180 degrees
        (``augment.rotation`` pi), which turns the direction a tilt faces as well, so only
        the size of the tilt counts (a roll of 10 is a pitch of 10 turned by 90 degrees)."""
        trained = LidarMount(*trained_rpy)
        level = trained.tilt() < 1e-9  # maybe turned about z
        if level and not trained_jitter:
            # Yaw leaves a level lidar level: only the tilt of its z axis counts.
            tilt = self.tilt()
            if tilt <= LEVEL_TOLERANCE:
                return None
            return (
                f"the model was trained on a level lidar and this mount's --lidar-rpy "
                f"{self.roll:g},{self.pitch:g},{self.yaw:g} tilts it {tilt:.1f} deg: levelling "
                "cannot show the model what the tilt hides, so expect lower scores; a model "
                "trained on tilts does better (sim.sensor_tilt_jitter, docs/ROBOT.md 'Mount')"
            )
        # The jitter tilts a level lidar in every direction (a disc of tilt directions), so
        # there too only the size of the tilt counts, not the mount's yaw.
        if every_direction or level:
            margin = max(1.0, trained_jitter)
            low, high = max(0.0, trained.tilt() - margin), trained.tilt() + margin
            if low - 1e-6 <= self.tilt() <= high + 1e-6:  # acos rounding at the ends
                return None
            why = "augment.rotation turned the scenes" if every_direction else "the jitter does"
            return (
                f"the model was trained on lidars tilted {low:.1f} to {high:.1f} deg (sim."
                f"sensor_rpy {trained.roll:g},{trained.pitch:g},{trained.yaw:g}"
                + (f", sensor_tilt_jitter {trained_jitter:g}" if trained_jitter else "")
                + f"; in every direction, as {why}) and this "
                f"mount's --lidar-rpy {self.roll:g},{self.pitch:g},{self.yaw:g} tilts it "
                f"{self.tilt():.1f} deg; pass your lidar's real tilt, and note the model was "
                "scored at its trained tilts only"
            )
        turn = trained.rotation().T @ self.rotation()
        angle = math.degrees(math.acos(float(np.clip((np.trace(turn) - 1) / 2, -1.0, 1.0))))
        if angle <= max(1.0, trained_jitter):
            return None
        where, fields = "at", "sim.sensor_rpy"
        if trained_jitter:
            where, fields = f"within {trained_jitter:g} deg of", fields + ", sensor_tilt_jitter"
        return (
            "the model was trained on a lidar {} roll {:g}, pitch {:g}, yaw {:g} deg "
            "({}), {:.1f} deg from this mount's --lidar-rpy {:g},{:g},{:g}; pass "
            "your lidar's real tilt, and note the model was scored at its trained {} "
            "only".format(
                where,
                *trained_rpy,
                fields,
                angle,
                self.roll,
                self.pitch,
                self.yaw,
                "tilts" if trained_jitter else "tilt",
            )
        )


LEVEL = LidarMount()  # a level lidar read as it is: the default everywhere
# Degrees of tilt a level-trained model takes without a note (2 cost the shipped model about
# 2 points of AP@0.50, 5 about 11: docs/ROBOT.md "Mount").
LEVEL_TOLERANCE = 2.0


def rpy_matrix(rpy_degrees, xp=np):
    """[..., 3, 3]: R = Rz(yaw) Ry(pitch) Rx(roll) of ``rpy_degrees`` [..., 3] (``LidarMount``'s
    convention); ``xp`` is numpy or ``jax.numpy`` (the simulator draws a tilt per scene)."""
    r, p, y = (xp.radians(rpy_degrees[..., i]) for i in range(3))
    zero, one = xp.zeros_like(r), xp.ones_like(r)

    def matrix(rows):
        return xp.stack([xp.stack(row, -1) for row in rows], -2)

    rx = matrix([[one, zero, zero], [zero, xp.cos(r), -xp.sin(r)], [zero, xp.sin(r), xp.cos(r)]])
    ry = matrix([[xp.cos(p), zero, xp.sin(p)], [zero, one, zero], [-xp.sin(p), zero, xp.cos(p)]])
    rz = matrix([[xp.cos(y), -xp.sin(y), zero], [xp.sin(y), xp.cos(y), zero], [zero, zero, one]])
    return rz @ ry @ rx


def _is_height(value: float) -> bool:
    return math.isfinite(value) and value >= 0


def check_level_frame(mount: LidarMount, level_frame: str | None) -> None:
    """A levelled cloud's outputs are not in the cloud's frame: they need a frame id; a
    cloud that is not rotated keeps its own, so a level frame would name a wrong one."""
    if mount.rotated and not level_frame:
        raise ValueError(
            "--lidar-rpy levels the clouds, so the outputs are not in the cloud's frame: name "
            "their frame with --level-frame (the lidar's origin with the robot's level axes) "
            "and publish its transform"
        )
    if level_frame and not mount.rotated:
        raise ValueError(
            f"--level-frame {level_frame!r} without a --lidar-rpy rotation: the outputs stay "
            "in the cloud's frame and keep its id; drop --level-frame"
        )


def parse_rpy(text: str) -> tuple[float, float, float]:
    """argparse helper: ``"ROLL,PITCH,YAW"`` in degrees."""
    try:
        values = tuple(float(v) for v in text.split(","))
    except ValueError:
        values = ()
    if len(values) != 3 or not all(math.isfinite(v) for v in values):
        raise ValueError(f"expected ROLL,PITCH,YAW in degrees, got {text!r}")
    return values


def parse_height(text: str) -> float:
    """argparse helper: the lidar's height above the floor, metres >= 0."""
    try:
        value = float(text)
    except ValueError:
        value = math.nan
    if not _is_height(value):
        raise ValueError(f"expected metres >= 0, got {text!r}")
    return value
