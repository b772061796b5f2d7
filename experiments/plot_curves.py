"""Learning curves of a run: ``python experiments/plot_curves.py RUN [RUN ...] --out P.png``.

Reads each run's ``metrics.jsonl`` (``train`` lines: loss; ``eval`` lines: AP@0.25,
AP@0.50, PQ, mIoU on the validation frames) and draws one panel per quantity, one line per
run. Needs matplotlib (``pip install -e .[plots]``).
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

from indoorbev_jax import fileio
from indoorbev_jax.checks import check_out_file
from indoorbev_jax.cli import HelpFormatter

PANELS = (
    ("train", "loss", "training loss"),
    ("train", "dice_final", "train dice loss (last layer)"),
    ("eval", "ap0.25", "val AP@0.25"),
    ("eval", "ap0.5", "val AP@0.50"),
    ("eval", "pq", "val PQ"),
    ("eval", "miou", "val mIoU"),
)


def read_log(run: Path) -> dict[str, list[dict]]:
    """{"train": [...], "eval": [...]} lines of ``run/metrics.jsonl``."""
    path = run / "metrics.jsonl"
    if not path.is_file():
        sweep = (
            " (a sweep's workdir: its losses are in sweep.jsonl)"
            if (run / "sweep.jsonl").exists()
            else ""
        )
        raise ValueError(f"{path}: no such file: not a training run's workdir{sweep}")
    out: dict[str, list[dict]] = {"train": [], "eval": []}
    lines = path.read_text().splitlines()
    for n, line in enumerate(lines, 1):
        try:
            row = json.loads(line)
        except json.JSONDecodeError as e:
            if n == len(lines):
                # A kill mid-write (or a run still writing) leaves it; training drops it too.
                print(f"plot_curves.py: warning: {path}:{n}: a torn last line, left out",
                      file=sys.stderr)  # fmt: skip
                break
            raise ValueError(f"{path}:{n}: not a JSON line ({e})") from None
        if not isinstance(row, dict) or not _is_number(row.get("step", 0)):
            raise ValueError(f"{path}:{n}: expected a JSON object with a numeric step")
        kind = row.get("kind", "train")
        for key in (key for k, key, _ in PANELS if k == kind):
            # A text value turned the panel's axis into categories, the curve upside down.
            if row.get(key) is not None and not _is_number(row[key]):
                raise ValueError(f"{path}:{n}: field {key!r}: expected a number, got {row[key]!r}")
        out.setdefault(kind, []).append(row)
    if not out["train"] and not out["eval"]:  # an empty picture, exit 0
        raise ValueError(f"{path}: holds no train or eval line to plot")
    return out


def _is_number(value) -> bool:
    return isinstance(value, int | float) and not isinstance(value, bool)


def run_labels(runs: list[Path]) -> list[str]:
    """A legend label per run: its folder's name, or its path where names repeat (two
    runs/small under different parents merged into one line before)."""
    names = [run.resolve().name for run in runs]
    return [str(run) if names.count(n) > 1 else n for n, run in zip(names, runs, strict=True)]


def main(argv=None) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0], formatter_class=HelpFormatter)
    p.add_argument("runs", nargs="+", type=Path, help="run directories (with metrics.jsonl)")
    p.add_argument("--out", required=True, help="picture file to write (.png)")
    args = p.parse_args(argv)
    fig, axes = plt.subplots(1, len(PANELS), figsize=(4 * len(PANELS), 3.2))
    kinds = fig.canvas.get_supported_filetypes()
    suffix = Path(args.out).suffix.lower().lstrip(".")
    if suffix not in kinds:
        p.error(f"--out {args.out}: expected a picture file name ending in one of "
                f"{', '.join('.' + k for k in sorted(kinds))}")  # fmt: skip
    try:  # before the logs are read: a bad path is said at once
        check_out_file("--out", args.out)
        runs = zip(run_labels(args.runs), args.runs, strict=True)
        logs = {name: read_log(run) for name, run in runs}
    except (OSError, ValueError) as e:
        p.error(str(e))
    for ax, (kind, key, title) in zip(axes, PANELS, strict=True):
        for name, log in logs.items():
            rows = [r for r in log[kind] if r.get(key) is not None]
            ax.plot([r["step"] for r in rows], [r[key] for r in rows], label=name,
                    marker="o" if kind == "eval" else None, markersize=3)  # fmt: skip
        ax.set_title(title)
        ax.set_xlabel("step")
        ax.grid(alpha=0.3)
    axes[0].legend(fontsize=8)
    fig.tight_layout()
    fileio.atomic_write(Path(args.out), lambda tmp: fig.savefig(tmp, dpi=100, format=suffix))
    print(f"wrote {args.out}")


if __name__ == "__main__":
    from indoorbev_jax.cli import exit_with

    exit_with(main, "plot_curves.py")  # Ctrl-C: one line and status 130
