"""Checks of library and command arguments, and the output-file helpers they share.

Each check returns the value or raises an error that names the argument and what it
expected, so a Python caller gets the message a command's user gets from argparse
(``cli``'s argument types use the same bounds).
"""

from __future__ import annotations

import json
import math
import numbers
import os
from pathlib import Path

import numpy as np

from indoorbev_jax.fileio import atomic_write, file_in_path


def whole_bound(minimum: int) -> str:
    """How a message states the bound of a whole number: \"> 0\" or \">= N\"."""
    return "> 0" if minimum == 1 else f">= {minimum}"


# jax.random.key folds a seed into 32 bits: larger or negative seeds would repeat others.
SEED_LIMIT = 2**32


def _is_whole(value) -> bool:
    """An int or numpy integer, not a bool."""
    return isinstance(value, numbers.Integral) and not isinstance(value, (bool, np.bool_))


def check_whole(name: str, value, minimum: int, note: str = "") -> int:
    """``value`` if it is an int (not a bool) >= ``minimum``; ``note`` follows the bound in
    the message, e.g. " (0: never)"."""
    if not _is_whole(value) or value < minimum:
        raise ValueError(
            f"{name}: expected a whole number {whole_bound(minimum)}{note}, got {value!r}"
        )
    return int(value)  # numpy integers too


def check_seed(name: str, value) -> int:
    """``value`` if it is a whole number in [0, 2**32) (``jax.random.key``'s distinct seeds)."""
    if not (_is_whole(value) and 0 <= value < SEED_LIMIT):
        raise ValueError(f"{name}: expected a whole number in [0, 2**32), got {value!r}")
    return int(value)


def check_folder(name: str, path, file_error: type[Exception] = ValueError) -> Path:
    """``path`` as a Path, unless it is empty (an unset shell variable would mean the current
    folder; a ValueError) or an existing file (``file_error``)."""
    if str(path) == "":
        raise ValueError(f"{name}: an empty path; expected a folder")
    path = Path(path)
    if path.exists() and not path.is_dir():
        raise file_error(f"{path}: is a file; {name} must be a folder")
    return path


def check_out_file(flag: str, path) -> Path:
    """``path``, an output file given by ``flag``, checked before a long run writes it (a
    bad path failed after the whole evaluation, losing it): not empty, not a folder, and its
    folder made and writable. Raises ``OSError`` / ``ValueError`` naming ``flag``."""
    if str(path) == "":
        raise ValueError(f"{flag}: an empty path; expected a file name")
    path = Path(path)
    if path.is_dir():
        raise IsADirectoryError(f"{flag} {path}: is a folder, expected a file name")
    try:
        path.parent.mkdir(parents=True, exist_ok=True)
    except OSError as e:
        blocker = file_in_path(path.parent)
        reason = f"{blocker} is a file" if blocker is not None else (e.strerror or str(e))
        raise OSError(e.errno, f"{flag} {path}: cannot make its folder ({reason})") from e
    if not os.access(path.parent, os.W_OK | os.X_OK):
        raise PermissionError(f"{flag} {path}: its folder {path.parent} is not writable")
    return path


# The records of a run directory that an output written into it must not replace.
RUN_RECORDS = ("config.json", "run.json", "init_from.json", "hypers.json", "metrics.jsonl",
               "sweep.jsonl")  # fmt: skip


def check_not_an_input(flag: str, out, inputs, *, files: bool = True) -> None:
    """Raises ``ValueError`` when the output ``out`` given by ``flag`` would replace one of
    the model ``inputs`` (when ``files``) or a record of an input run directory (a --json
    at the model file replaced it with the metrics, exit 0)."""
    target = Path(out).resolve()
    for given in inputs:
        source = Path(given).resolve()
        if (files and target == source) or (target.parent == source and target.name in RUN_RECORDS):
            raise ValueError(f"{flag} {out}: is a file of the model {given}; expected a new file")


def write_json(path, payload, indent: int = 2) -> None:
    """``payload`` as JSON in ``path``, atomically (``fileio.atomic_write``)."""
    text = json.dumps(payload, indent=indent) + "\n"
    atomic_write(Path(path), lambda tmp: tmp.write_text(text))


def check_positive(name: str, value, unit: str = "seconds") -> float:
    """``value`` if it is a finite number > 0 (not a bool), ``unit`` naming it in the message."""
    ok = isinstance(value, int | float) and not isinstance(value, bool)
    if not (ok and math.isfinite(value) and value > 0):
        raise ValueError(f"{name}: expected {unit} > 0, got {value!r}")
    return value
