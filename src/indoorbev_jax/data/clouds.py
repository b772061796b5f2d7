"""Point-cloud files other than KITTI ``.bin``: PCL's ``.pcd`` and numpy's ``.npy``.

Both read to float32 [N, 4] = (x, y, z, intensity) in the lidar frame, as
``kitti.read_points`` does; a cloud without an intensity field reads intensity 0. Every
malformed file is a ``kitti.DatasetError`` naming the file (and the header line or field).

``.pcd`` (PCL's format, versions 0.5-0.7): ``DATA ascii`` or ``binary``, any field order,
extra fields (``ring``, ``time``, normals, ``_`` padding), ``COUNT`` > 1, any ``TYPE``/
``SIZE`` PCL writes; intensity from ``intensity``, ``reflectivity`` or ``i``. Organised
clouds (HEIGHT > 1) read row by row with their NaN points. ``binary_compressed`` (LZF) is
refused with the command that converts it.

``.npy``: a float or integer array [N, 3] or [N, 4+] (x, y, z[, intensity, ...]), or a
structured array with fields x, y, z (and intensity).

Example::

    from indoorbev_jax.data.clouds import read_cloud

    points = read_cloud("scan.pcd")  # float32 [N, 4]
"""

from __future__ import annotations

import io
import os
import warnings
from pathlib import Path

import numpy as np

from indoorbev_jax.data.kitti import DatasetError, check_cloud_file, read_points
from indoorbev_jax.geometry import as_points

SUFFIXES = (".bin", ".pcd", ".npy")
INTENSITY_NAMES = ("intensity", "reflectivity", "i")
# PCD TYPE letter and SIZE -> numpy kind.
_PCD_KINDS = {"F": "f", "I": "i", "U": "u"}
_PCD_HEADER = ("VERSION", "FIELDS", "SIZE", "TYPE", "COUNT", "WIDTH", "HEIGHT", "VIEWPOINT",
               "POINTS", "DATA")  # fmt: skip
_PCD_ONE_VALUE = ("VERSION", "WIDTH", "HEIGHT", "POINTS", "DATA")


def read_cloud(path: str | os.PathLike) -> np.ndarray:
    """float32 [N, 4] (x, y, z, intensity) from a ``.bin``, ``.pcd`` or ``.npy`` file."""
    path = Path(path)
    suffix = path.suffix.lower()
    if suffix == ".bin":
        return read_points(path)
    if suffix == ".pcd":
        return read_pcd(path)
    if suffix == ".npy":
        return read_npy(path)
    raise DatasetError(f"{path}: expected a {', '.join(SUFFIXES)} point cloud file")


def _intensity_name(names: list[str]) -> str | None:
    """The field read as intensity: the first of ``INTENSITY_NAMES`` in ``names``."""
    return next((n for n in INTENSITY_NAMES if n in names), None)


def _columns(path: Path, names: list[str], get) -> np.ndarray:
    """Stacks x, y, z and the first intensity-like field (0 when none) as float32 [N, 4]."""
    missing = [n for n in "xyz" if n not in names]
    if missing:
        raise DatasetError(f"{path}: no field(s) {missing} (x, y, z needed); it has {names}")
    xyz = [np.asarray(get(n), np.float32) for n in "xyz"]
    name_i = _intensity_name(names)
    intensity = np.asarray(get(name_i), np.float32) if name_i else np.zeros_like(xyz[0])
    return np.stack([*xyz, intensity], axis=1)


def read_npy(path: str | os.PathLike) -> np.ndarray:
    """float32 [N, 4] from a ``.npy`` array (see the module docstring)."""
    path = Path(path)
    check_cloud_file(path)
    _check_npy_header(path)
    try:
        arr = np.load(path, allow_pickle=False)
    except (ValueError, OSError, EOFError) as e:
        raise DatasetError(f"{path}: not a readable .npy array ({e})") from e
    if arr.dtype.names:  # structured: fields by name
        names = list(arr.dtype.names)
        for name in ("x", "y", "z", _intensity_name(names)):  # the fields _columns reads
            field = arr.dtype.fields.get(name, (None,))[0]
            # Text failed with numpy's bare message, complex lost its imaginary part.
            if field is not None and (field.shape or field.kind not in "fiu"):
                raise DatasetError(
                    f"{path}: field {name!r} is {field}, expected one integer or float per point"
                )
        return _columns(path, names, lambda n: arr[n].reshape(-1))
    try:
        return as_points(arr, str(path))
    except ValueError as e:
        raise DatasetError(str(e)) from e


def _check_npy_header(path: Path) -> None:
    """Refuses what ``np.load`` would misread: a file without the NUMPY header (it called
    text "pickled data" and an .npz a dict), and a header asking for more bytes than the
    file holds, before they are allocated (a header's shape of 10**11 points stopped a whole
    predict run with a MemoryError that named no file)."""
    try:
        with open(path, "rb") as f:
            magic = f.read(6)
            header = None
            if magic == b"\x93NUMPY":
                f.seek(0)
                version = np.lib.format.read_magic(f)
                read_header = (
                    np.lib.format.read_array_header_1_0
                    if version == (1, 0)
                    else np.lib.format.read_array_header_2_0
                )
                shape, _, dtype = read_header(f)
                header = shape, dtype, os.fstat(f.fileno()).st_size - f.tell()
    except (ValueError, OSError, EOFError) as e:
        raise DatasetError(f"{path}: not a readable .npy array ({e})") from e
    if header is None:
        what = "an .npz archive" if magic.startswith(b"PK") else "no .npy file"
        raise DatasetError(
            f"{path}: {what} (no NUMPY header); expected one array saved with np.save"
        )
    shape, dtype, have = header
    if dtype.hasobject:  # pickled objects: np.load refuses them, named
        return
    need = int(np.prod(shape, dtype=object)) * dtype.itemsize
    if need > have:
        raise DatasetError(
            f"{path}: its header says shape {shape} of {dtype} ({need} bytes), but the file "
            f"holds {have} bytes of data"
        )


def _parse_pcd_header(path: Path, data: bytes) -> tuple[dict[str, list[str]], int]:
    """({keyword: values}, byte offset of the point data) of a PCD file's header."""
    header: dict[str, list[str]] = {}
    pos = 0
    for lineno in range(1, 64):
        end = data.find(b"\n", pos)
        if end < 0:
            raise DatasetError(f"{path}:{lineno}: the header ends without a DATA line")
        # A comment, whole-line or after the values ("WIDTH 3 # per row"), in any encoding.
        content = data[pos:end].split(b"#", 1)[0]
        try:
            line = content.decode("ascii").strip()
        except UnicodeDecodeError as e:
            raise DatasetError(f"{path}:{lineno}: not a PCD header line ({e})") from e
        pos = end + 1
        if not line:
            continue
        key, *values = line.split()
        if key.upper() not in _PCD_HEADER:
            raise DatasetError(
                f"{path}:{lineno}: unknown PCD header keyword {key!r} (expected one of "
                f"{', '.join(_PCD_HEADER)})"
            )
        if key.upper() in _PCD_ONE_VALUE and len(values) != 1:
            raise DatasetError(
                f"{path}:{lineno}: {key} takes one value, got {len(values)} ({line!r})"
            )
        header[key.upper()] = values
        if key.upper() == "DATA":
            return header, pos
    raise DatasetError(f"{path}: no DATA line in the first 64 lines: not a PCD file?")


def read_pcd(path: str | os.PathLike) -> np.ndarray:
    """float32 [N, 4] from a PCL ``.pcd`` file (see the module docstring)."""
    path = Path(path)
    check_cloud_file(path)
    data = path.read_bytes()
    header, offset = _parse_pcd_header(path, data)
    for key in ("FIELDS", "SIZE", "TYPE", "DATA"):
        if key not in header:
            raise DatasetError(f"{path}: the PCD header has no {key} line")
    fields = header["FIELDS"]
    sizes, types = header["SIZE"], header["TYPE"]
    counts = header.get("COUNT", ["1"] * len(fields))
    if not len(fields) == len(sizes) == len(types) == len(counts):
        raise DatasetError(
            f"{path}: FIELDS, SIZE, TYPE and COUNT list {len(fields)}, {len(sizes)}, "
            f"{len(types)} and {len(counts)} values; they must match"
        )
    try:
        width = int(header.get("WIDTH", ["0"])[0])
        height = int(header.get("HEIGHT", ["1"])[0])
        n = int(header["POINTS"][0]) if "POINTS" in header else width * height
        counts = [int(c) for c in counts]
    except ValueError as e:
        raise DatasetError(f"{path}: WIDTH, HEIGHT, POINTS and COUNT must be integers ({e})") from e
    if min(width, height, n, *counts) < 0:
        raise DatasetError(
            f"{path}: WIDTH {width}, HEIGHT {height}, POINTS {n} and COUNT must be >= 0"
        )
    if "POINTS" in header and "WIDTH" in header and width * height != n:
        # PCL refuses this too: one of the three is wrong, and which one decides the cloud.
        raise DatasetError(
            f"{path}: WIDTH {width} x HEIGHT {height} = {width * height} points, but POINTS "
            f"says {n}; they must agree"
        )
    dtype = []
    for k, (name, size, kind, count) in enumerate(zip(fields, sizes, types, counts, strict=True)):
        letter = _PCD_KINDS.get(kind.upper())
        sizes_ok = ("4", "8") if letter == "f" else ("1", "2", "4", "8")
        if letter is None or size not in sizes_ok:
            raise DatasetError(f"{path}: field {name!r} has TYPE {kind} SIZE {size}, unknown")
        # PCL names padding "_", maybe several times: numpy needs distinct names.
        unique = name if name != "_" else f"_pad{k}"
        dtype.append((unique, f"<{letter}{size}", (count,) if count > 1 else ()))
    try:
        dtype = np.dtype(dtype)
    except ValueError as e:  # a field named twice, say
        raise DatasetError(f"{path}: FIELDS {' '.join(fields)}: {e}") from e
    names = [f for f in fields if f != "_"]
    kind = header["DATA"][0].lower() if header["DATA"] else ""
    if kind == "binary":
        need = n * dtype.itemsize
        if len(data) - offset < need:
            raise DatasetError(
                f"{path}: DATA binary holds {len(data) - offset} bytes, expected POINTS {n} x "
                f"{dtype.itemsize} bytes = {need}"
            )
        points = np.frombuffer(data, dtype, count=n, offset=offset)
        # A COUNT > 1 field reads its first value (x, y, z and intensity have one).
        first = lambda f: points[f] if points[f].ndim == 1 else points[f][:, 0]  # noqa: E731
        return _columns(path, names, first)
    if kind == "ascii":
        first_line = data[:offset].count(b"\n") + 1
        return _read_pcd_ascii(path, data[offset:], dtype, names, n, first_line)
    if kind == "binary_compressed":
        raise DatasetError(
            f"{path}: DATA binary_compressed (LZF) is not read; convert it once with PCL, "
            "`pcl_convert_pcd_ascii_binary IN.pcd OUT.pcd 1` (binary)"
        )
    raise DatasetError(f"{path}: DATA {' '.join(header['DATA'])!r}: expected ascii or binary")


def _read_pcd_ascii(
    path: Path, text: bytes, dtype: np.dtype, names: list[str], n: int, first_line: int
):
    """``first_line``: the file's line number of the first data line, for errors."""
    width = sum(int(np.prod(dtype[f].shape, dtype=int)) for f in dtype.names)
    if n == 0 and not text.strip():
        return _columns(path, names, lambda f: np.zeros(0))
    try:
        with warnings.catch_warnings():  # no rows: the shape check below names the file
            warnings.simplefilter("ignore", UserWarning)
            values = np.loadtxt(io.BytesIO(text), dtype=np.float64, ndmin=2)
    except ValueError as e:
        raise DatasetError(_bad_ascii_row(path, text, width, first_line) or f"{path}: {e}") from e
    if values.size == 0:
        values = values.reshape(0, width)
    if values.shape != (n, width):
        raise DatasetError(
            f"{path}: DATA ascii holds {values.shape[0]} points of {values.shape[1]} values, "
            f"expected POINTS {n} of {width} (FIELDS x COUNT)"
        )
    column, start = {}, 0
    for f in dtype.names:
        column[f] = start
        start += int(np.prod(dtype[f].shape, dtype=int))
    return _columns(path, names, lambda f: values[:, column[f]])


def _bad_ascii_row(path: Path, text: bytes, width: int, first_line: int) -> str | None:
    """The first data line of an ASCII PCD that is not ``width`` numbers, named by its line
    in the file (numpy's own message counts rows of the data section, from 0 or 1)."""
    for k, raw in enumerate(text.split(b"\n")):
        words = raw.split(b"#")[0].split()
        if not words:
            continue
        where = f"{path}:{first_line + k}"
        if len(words) != width:
            return f"{where}: {len(words)} values, expected {width} (FIELDS x COUNT)"
        try:
            [float(w) for w in words]
        except ValueError:
            return f"{where}: a value is not a number ({raw.decode('ascii', 'replace').strip()!r})"
    return None
