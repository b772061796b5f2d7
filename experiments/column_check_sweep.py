"""How well the .bin column check (``kitti._other_column_count``) tells 3- and 5-column files.

``python experiments/column_check_sweep.py`` casts frames 0, 1 and 7 of each scan pattern
(``mid360`` with 4, 5 and 8 emitters, ``vlp16``, ``os128``, ``grid``) into box rooms from
3 x 2 m to 40 x 30 m, writes each cloud with 4 columns (it must read) and with 3 or 5 (a
5th column of emitter, ring or time: it must be refused), and prints the counts.
``--folders DIR ...`` does the same with the ``velodyne/*.bin`` clouds of exports.
"""

from __future__ import annotations

import argparse
import collections
from pathlib import Path

import numpy as np

from indoorbev_jax.cli import HelpFormatter
from indoorbev_jax.data import kitti

ROOMS = ((3, 2, 0.5, 2.0), (1.5, 1.0, 0.3, 1.2), (8, 6, 1.0, 3.0), (20, 15, 0.5, 5.0))


def _room(directions: np.ndarray, hx, hy, floor, ceiling) -> np.ndarray:
    """Where rays from the sensor meet a box room of half sizes hx, hy."""
    with np.errstate(divide="ignore"):
        up = np.where(directions[:, 2] < 0, floor / -directions[:, 2], ceiling / directions[:, 2])
        t = np.min(np.abs([hx / directions[:, 0], hy / directions[:, 1], up]), 0)
    return directions * t[:, None]


def _clouds(folders):
    """(name, xyz, intensity) of the clouds to rewrite."""
    rng = np.random.default_rng(0)
    if folders:
        for folder in folders:
            paths = sorted(Path(folder, "velodyne").glob("*.bin"))
            if not paths:  # a typo counted "0 of 0", exit 0
                raise ValueError(f"--folders {folder}: no velodyne/*.bin (an exported dataset)")
            for path in paths:
                pts = kitti.read_points(path)  # a bad file: DatasetError naming it
                yield Path(folder).name, pts[:, :3], pts[:, 3]
        return
    from indoorbev_sim import patterns as P

    pats = {"mid360": P.Mid360Pattern(), "mid360 x5": P.Mid360Pattern(num_emitters=5),
            "mid360 x8": P.Mid360Pattern(num_emitters=8), "vlp16": P.SpinningPattern.vlp16(),
            "os128": P.SpinningPattern.os128(), "grid": P.GridPattern(360, 64)}  # fmt: skip
    for name, pattern in pats.items():
        for k in (0, 1, 7):
            directions = np.asarray(pattern.frame(k).directions, np.float64)
            for room in ROOMS:
                xyz = _room(directions, *room)
                for intensity in (rng.uniform(0, 1, len(xyz)), rng.integers(0, 256, len(xyz))):
                    yield f"{name} {2 * room[0]:g} x {2 * room[1]:g} m", xyz, intensity


def _tally(counts, missed, name: str, xyz: np.ndarray, intensity: np.ndarray) -> None:
    """Counts whether the column check reads one cloud right, and refuses it with 3 or 5
    columns (an emitter, ring or time fifth)."""
    n = len(xyz)
    four = np.c_[xyz, intensity].astype(np.float32).ravel()
    counts["genuine"] += 1
    counts["genuine read"] += kitti._other_column_count(four) is None
    fifths = {
        "emitter": np.arange(n) % 4,
        "ring": np.arange(n) % 16,
        "time": np.arange(n) * 5e-6,
    }
    cases = [("3 columns", xyz)] + [(f"5 columns ({k})", np.c_[xyz, intensity, v])
                                    for k, v in fifths.items()]  # fmt: skip
    for case, points in cases:
        words = points.astype(np.float32).ravel()
        words = words[: words.size // 4 * 4]
        got = kitti._other_column_count(words)
        cols = points.shape[1]
        counts[case] += 1
        counts[f"{case} refused"] += got is not None and got[0] == cols
        missed[(case, name)] += got is None or got[0] != cols


def main(argv=None) -> None:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0], formatter_class=HelpFormatter)
    p.add_argument(
        "--folders",
        nargs="+",
        default=None,
        help="exported datasets whose velodyne/*.bin to rewrite (default: box rooms)",
    )
    args = p.parse_args(argv)
    counts, missed = collections.Counter(), collections.Counter()
    try:  # a folder of no clouds, a bad file: named; the clouds read one at a time
        for name, xyz, intensity in _clouds(args.folders):
            _tally(counts, missed, name, xyz, intensity)
    except (OSError, ValueError) as e:
        p.error(str(e))
    print(f"genuine 4-column clouds read: {counts['genuine read']} of {counts['genuine']}")
    for case in ("3 columns", "5 columns (emitter)", "5 columns (ring)", "5 columns (time)"):
        print(f"{case} refused: {counts[case + ' refused']} of {counts[case]}")
    for (case, name), k in sorted(missed.items()):
        if k:
            print(f"  read as garbage: {k} x {case}, {name}")


if __name__ == "__main__":
    from indoorbev_jax.cli import exit_with

    exit_with(main, "column_check_sweep.py")  # Ctrl-C: one line and status 130
