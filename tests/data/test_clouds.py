"""PCL .pcd and numpy .npy clouds read as KITTI .bin points: known values, bad files named."""

import re

import numpy as np
import pytest

from indoorbev_jax import predict as P
from indoorbev_jax.data import clouds, kitti

RNG = np.random.default_rng(0)
POINTS = np.c_[RNG.uniform(-5, 5, (50, 3)), RNG.uniform(0, 255, 50)].astype(np.float32)


def _header(fields, sizes, types, counts, n, data, height=1, version="0.7"):
    return (
        f"# .PCD v{version} - Point Cloud Data file format\nVERSION {version}\n"
        f"FIELDS {' '.join(fields)}\nSIZE {' '.join(map(str, sizes))}\n"
        f"TYPE {' '.join(types)}\nCOUNT {' '.join(map(str, counts))}\n"
        f"WIDTH {n // height}\nHEIGHT {height}\nVIEWPOINT 0 0 0 1 0 0 0\nPOINTS {n}\n"
        f"DATA {data}\n"
    ).encode()


# What drivers write: extra fields before and after, padding, float64 time, uint16 ring,
# a 3-vector (COUNT 3), intensity as float or as uint8 reflectivity.
LAYOUT = [  # (name, numpy type, PCD SIZE, TYPE, COUNT)
    ("normal", "<f4", 4, "F", 3),
    ("x", "<f4", 4, "F", 1),
    ("y", "<f4", 4, "F", 1),
    ("_", "u1", 1, "U", 1),
    ("z", "<f4", 4, "F", 1),
    ("intensity", "<f4", 4, "F", 1),
    ("ring", "<u2", 2, "U", 1),
    ("time", "<f8", 8, "F", 1),
]


def _structured(points, layout=LAYOUT):
    dtype = [(n if n != "_" else "pad", t, (c,) if c > 1 else ()) for n, t, _, _, c in layout]
    out = np.zeros(len(points), dtype)
    for k, name in enumerate("xyz"):
        out[name] = points[:, k]
    if any(n == "intensity" for n, *_ in layout):
        out["intensity"] = points[:, 3]
    if any(n == "ring" for n, *_ in layout):
        out["ring"] = np.arange(len(points)) % 16
        out["time"] = np.arange(len(points)) * 1e-5
        out["normal"] = 1.0
    return out


def _write_pcd(path, points, data="binary", layout=LAYOUT, height=1, s=None):
    """``points`` in a PCD file of ``layout``; ``s``: the structured array to write instead."""
    s = _structured(points, layout) if s is None else s
    names, _, sizes, types, counts = zip(*layout, strict=True)
    header = _header(names, sizes, types, counts, len(points), data, height)
    if data == "binary":
        path.write_bytes(header + s.tobytes())
    else:
        columns = [np.asarray(s[n], np.float64).reshape(len(s), int(np.prod(s[n].shape[1:])))
                   for n in s.dtype.names]  # fmt: skip
        table = np.concatenate(columns, axis=1).tolist()  # float32 values, exact in repr
        path.write_bytes(header + "".join(" ".join(map(repr, r)) + "\n" for r in table).encode())


@pytest.mark.parametrize("data", ["binary", "ascii"])
def test_pcd_reads_the_points_of_any_field_layout(tmp_path, data):
    _write_pcd(tmp_path / "a.pcd", POINTS, data)
    np.testing.assert_array_equal(clouds.read_cloud(tmp_path / "a.pcd"), POINTS)
    # An organised cloud (2 rows) with NaN points, as a driver writes one.
    organised = POINTS.copy()
    organised[::7, :3] = np.nan
    _write_pcd(tmp_path / "o.pcd", organised, data, height=2)
    np.testing.assert_array_equal(clouds.read_pcd(tmp_path / "o.pcd"), organised)


def test_pcd_intensity_names_and_no_intensity(tmp_path):
    xyz = [("x", "<f4", 4, "F", 1), ("y", "<f4", 4, "F", 1), ("z", "<f4", 4, "F", 1)]
    _write_pcd(tmp_path / "xyz.pcd", POINTS, layout=xyz)
    expected = POINTS.copy()
    expected[:, 3] = 0
    np.testing.assert_array_equal(clouds.read_pcd(tmp_path / "xyz.pcd"), expected)
    refl = np.zeros(len(POINTS), [("x", "<f4"), ("y", "<f4"), ("z", "<f4"), ("r", "u1")])
    for k, n in enumerate("xyz"):
        refl[n] = POINTS[:, k]
    refl["r"] = np.round(POINTS[:, 3])
    header = _header(["x", "y", "z", "reflectivity"], [4, 4, 4, 1], "FFFU", [1] * 4, 50, "binary")
    (tmp_path / "r.pcd").write_bytes(header + refl.tobytes())
    got = clouds.read_pcd(tmp_path / "r.pcd")
    np.testing.assert_array_equal(got[:, 3], np.round(POINTS[:, 3]))


def test_pcd_intensity_field_named_i(tmp_path):
    """The module reads intensity from ``intensity``, ``reflectivity`` or ``i``: a cloud whose
    field is ``i`` must give its values, not the zeros of a cloud without intensity."""
    layout = [("x", "<f4", 4, "F", 1), ("y", "<f4", 4, "F", 1), ("z", "<f4", 4, "F", 1),
              ("i", "<f4", 4, "F", 1)]  # fmt: skip
    s = np.zeros(len(POINTS), [(n, t) for n, t, *_ in layout])
    for k, name in enumerate("xyzi"):
        s[name] = POINTS[:, k]
    for data in ("binary", "ascii"):
        _write_pcd(tmp_path / f"i_{data}.pcd", POINTS, data, layout=layout, s=s)
        np.testing.assert_array_equal(clouds.read_pcd(tmp_path / f"i_{data}.pcd"), POINTS)
    # An Ouster-style cloud carries both intensity and reflectivity (listed first here):
    # intensity is read, as from a PointCloud2 (test_pointcloud2_intensity_field_wins...).
    both = [*layout[:3], ("reflectivity", "<u2", 2, "U", 1), ("intensity", "<f4", 4, "F", 1)]
    s = np.zeros(len(POINTS), [(n, t) for n, t, *_ in both])
    for k, name in enumerate("xyz"):
        s[name] = POINTS[:, k]
    s["reflectivity"], s["intensity"] = 77, POINTS[:, 3]
    for data in ("binary", "ascii"):
        _write_pcd(tmp_path / f"both_{data}.pcd", POINTS, data, layout=both, s=s)
        np.testing.assert_array_equal(clouds.read_pcd(tmp_path / f"both_{data}.pcd"), POINTS)


def test_bad_pcd_files_are_named(tmp_path):
    path = tmp_path / "b.pcd"
    _write_pcd(path, POINTS)
    good = path.read_bytes()
    cases = [
        (good.replace(b"DATA binary", b"DATA binary_compressed"),
         r"b\.pcd: DATA binary_compressed \(LZF\) is not read; convert it .*pcl_convert"),
        (good[:-10], r"b\.pcd: DATA binary holds \d+ bytes, expected POINTS 50 x 39 bytes = 1950"),
        # One byte short, the boundary: numpy's "buffer is smaller" named no file.
        (good[:-1], r"b\.pcd: DATA binary holds 1949 bytes, expected POINTS 50 x 39 bytes = 1950"),
        (good.replace(b"FIELDS normal x y _ z", b"FIELDS normal x y _ h"),
         r"b\.pcd: no field\(s\) \['z'\]"),
        (good.replace(b"VIEWPOINT", b"VIEWPINT"), r"b\.pcd:9: unknown PCD header keyword"),
        (good.replace(b"TYPE F F F U", b"TYPE F F F Q"), r"field '_' has TYPE Q SIZE 1"),
        (b"\x89PNG\r\n" + good[:100], r"b\.pcd:1: not a PCD header line|unknown PCD header"),
    ]  # fmt: skip
    for content, message in cases:
        path.write_bytes(content)
        with pytest.raises(kitti.DatasetError, match=message):
            clouds.read_pcd(path)
    _write_pcd(path, POINTS, "ascii")
    ascii_lines = path.read_bytes().splitlines(keepends=True)
    # Errors name the file's line (numpy counted data rows, from 0 or from 1).
    for k, row, message in [
        (14, b"1 2 3\n", r"b\.pcd:15: 3 values, expected 10 \(FIELDS x COUNT\)"),
        (11, b"1 2 3\n", r"b\.pcd:12: 3 values, expected 10"),
        (11, b"1 2 3 4 5 6 7 8 9 x\n", r"b\.pcd:12: a value is not a number \('1 2 3 .* x'\)"),
    ]:
        lines = list(ascii_lines)
        lines[k] = row
        path.write_bytes(b"".join(lines))
        with pytest.raises(kitti.DatasetError, match=message):
            clouds.read_pcd(path)
    # A keyword without its value was a bare IndexError, which stopped a predict run.
    for old, new, message in [
        (b"POINTS 50", b"POINTS", r"b\.pcd:10: POINTS takes one value, got 0"),
        (b"WIDTH 50", b"WIDTH  ", r"b\.pcd:7: WIDTH takes one value, got 0"),
        (b"HEIGHT 1", b"HEIGHT 1 1", r"b\.pcd:8: HEIGHT takes one value, got 2"),
    ]:
        path.write_bytes(good.replace(old, new))
        with pytest.raises(kitti.DatasetError, match=message):
            clouds.read_pcd(path)


def test_npy_arrays_and_structured_arrays(tmp_path):
    np.save(tmp_path / "a.npy", POINTS.astype(np.float64))
    np.testing.assert_array_equal(clouds.read_cloud(tmp_path / "a.npy"), POINTS)
    np.save(tmp_path / "b.npy", POINTS[:, :3])
    expected = POINTS.copy()
    expected[:, 3] = 0
    np.testing.assert_array_equal(clouds.read_cloud(tmp_path / "b.npy"), expected)
    np.save(tmp_path / "c.npy", np.c_[POINTS, np.ones(50)])  # a 5th column (ring) is left
    np.testing.assert_array_equal(clouds.read_cloud(tmp_path / "c.npy"), POINTS)
    np.save(tmp_path / "d.npy", _structured(POINTS))
    np.testing.assert_array_equal(clouds.read_cloud(tmp_path / "d.npy"), POINTS)
    for name, arr, message in [
        ("e", POINTS[:, :2], r"e\.npy: expected a numeric array \[N, 3\] or \[N, 4\+\]"),
        ("f", np.array(["a", "b"]), r"f\.npy: expected a numeric array"),
        ("g", np.array([{"x": 1}], object), r"g\.npy: not a readable \.npy array"),
    ]:
        np.save(tmp_path / f"{name}.npy", arr, allow_pickle=True)
        with pytest.raises(kitti.DatasetError, match=message):
            clouds.read_cloud(tmp_path / f"{name}.npy")
    # Fields that are not one number a point: text failed with numpy's bare message and a
    # sub-array with another, a complex z lost its imaginary part silently.
    for name, field in (("text", "U4"), ("pair", ("<f4", (2,))), ("complex", "<c8")):
        dtype = [("x", "<f4"), ("y", "<f4"), ("z", field), ("intensity", "<f4")]
        np.save(tmp_path / f"{name}.npy", np.zeros(5, dtype))
        with pytest.raises(kitti.DatasetError) as refused:
            clouds.read_cloud(tmp_path / f"{name}.npy")
        said = f"{tmp_path / name}.npy: field 'z' is {np.dtype([('z', field)])['z']}, expected one"
        assert str(refused.value).startswith(said)
    # Fields that are not read may be anything: a text "i" beside the intensity read.
    extra = np.zeros(5, [("x", "<f4"), ("y", "<f4"), ("z", "<f4"), ("intensity", "<f4"),
                         ("i", "U4")])  # fmt: skip
    extra["intensity"] = 0.5
    np.save(tmp_path / "extra.npy", extra)
    np.testing.assert_array_equal(clouds.read_cloud(tmp_path / "extra.npy")[:, 3], 0.5)


def test_an_npy_header_larger_than_its_file_is_refused_before_loading(tmp_path):
    """A header's shape of 10**11 points made np.load ask for 1.46 TiB: a MemoryError, which
    predict lets through as the machine's, stopped a whole folder run naming no file. The
    header is checked against the file's size first; a truncated file is named the same
    way (np.load said only "could only read 93 elements")."""
    header = {"descr": "<f4", "fortran_order": False, "shape": (10**11, 4)}
    with open(tmp_path / "huge.npy", "wb") as f:
        np.lib.format.write_array_header_1_0(f, header)
        f.write(POINTS[:10].tobytes())
    said = (
        f"{tmp_path / 'huge.npy'}: its header says shape (100000000000, 4) of float32 "
        "(1600000000000 bytes), but the file holds 160 bytes of data"
    )
    with pytest.raises(kitti.DatasetError, match=re.escape(said)):
        clouds.read_cloud(tmp_path / "huge.npy")
    np.save(tmp_path / "cut.npy", POINTS)
    data = (tmp_path / "cut.npy").read_bytes()
    (tmp_path / "cut.npy").write_bytes(data[:-4])
    with pytest.raises(kitti.DatasetError, match=r"cut\.npy: its header says shape \(50, 4\)"):
        clouds.read_cloud(tmp_path / "cut.npy")
    with open(tmp_path / "v2.npy", "wb") as f:  # a version 2.0 header reads the same
        np.lib.format.write_array(f, POINTS, version=(2, 0))
    np.testing.assert_array_equal(clouds.read_cloud(tmp_path / "v2.npy"), POINTS)


def test_files_that_are_no_npy_are_named_as_such(tmp_path, recwarn):
    """A text file or an .npz named .npy: numpy called the first "pickled data" (with a hint
    to unpickle it) and the second an AttributeError. An ASCII PCD whose header promises
    points but holds no row is named without numpy's warning about a BytesIO."""
    (tmp_path / "t.npy").write_text("1 2 3 4\n")
    np.savez(tmp_path / "z.npz", POINTS)
    (tmp_path / "z.npz").rename(tmp_path / "z.npy")
    (tmp_path / "e.npy").write_bytes(b"")
    for name, what in (("t", "no .npy file"), ("z", "an .npz archive"), ("e", "no .npy file")):
        message = rf"{name}\.npy: {what} \(no NUMPY header\); expected one array saved with"
        with pytest.raises(kitti.DatasetError, match=message):
            clouds.read_cloud(tmp_path / f"{name}.npy")
    with pytest.raises(kitti.DatasetError, match=r"missing\.npy: not a readable \.npy array"):
        clouds.read_npy(tmp_path / "missing.npy")
    _write_pcd(tmp_path / "r.pcd", POINTS, "ascii")
    text = (tmp_path / "r.pcd").read_bytes()
    (tmp_path / "r.pcd").write_bytes(text[: text.index(b"DATA ascii\n") + 11])
    with pytest.raises(kitti.DatasetError, match=r"r\.pcd: DATA ascii holds 0 points"):
        clouds.read_pcd(tmp_path / "r.pcd")
    assert not [str(w.message) for w in recwarn]


def test_predict_input_reads_pcd_and_npy_files_and_folders(tmp_path):
    (tmp_path / "scans").mkdir()
    _write_pcd(tmp_path / "scans" / "000001.pcd", POINTS)
    np.save(tmp_path / "scans" / "000000.npy", POINTS)
    kitti.write_points(tmp_path / "scans" / "000002.bin", POINTS)
    (tmp_path / "scans" / "notes.txt").write_text("not a cloud")
    count, frames = P.open_input(tmp_path / "scans")
    frames = list(frames)
    assert count == 3 and [f.frame_id for f in frames] == ["000000", "000001", "000002"]
    for f in frames:
        np.testing.assert_array_equal(f.points, POINTS)
    count, frames = P.open_input(tmp_path / "scans" / "000001.pcd")
    assert count == 1 and next(frames).frame_id == "000001"
    np.save(tmp_path / "scans" / "000001.npy", POINTS)  # two clouds would write one output
    with pytest.raises(ValueError, match=r"000001\.npy and 000001\.pcd: two clouds named"):
        P.open_input(tmp_path / "scans")


def test_empty_and_odd_pcd_headers(tmp_path):
    """A frame without returns (0 points) reads empty; POINTS -1 is named; a comment line
    in another encoding is a comment (it was refused as not ASCII)."""
    for data in ("binary", "ascii"):
        _write_pcd(tmp_path / f"e_{data}.pcd", POINTS[:0], data)
        assert clouds.read_pcd(tmp_path / f"e_{data}.pcd").shape == (0, 4)
    good = tmp_path / "g.pcd"
    _write_pcd(good, POINTS)
    content = good.read_bytes()
    good.write_bytes("# scanné à Lyon\n".encode() + content)
    np.testing.assert_array_equal(clouds.read_pcd(good), POINTS)
    # Comments after the values, as PCL reads them ("WIDTH 3 # points" was refused).
    commented = content.replace(b"WIDTH 50", b"WIDTH 50 # per row").replace(
        b"DATA binary", "DATA binary\t# écrit à Lyon".encode()
    )
    good.write_bytes(commented)
    np.testing.assert_array_equal(clouds.read_pcd(good), POINTS)
    good.write_bytes(content.replace(b"POINTS 50", b"POINTS -1"))
    with pytest.raises(kitti.DatasetError, match=r"g\.pcd: WIDTH 50, HEIGHT 1, POINTS -1"):
        clouds.read_pcd(good)
    # WIDTH x HEIGHT and POINTS disagreeing was read as POINTS, silently; PCL refuses it.
    for old, new, counts in [
        (b"POINTS 50", b"POINTS 49", "50 x HEIGHT 1 = 50 points, but POINTS says 49"),
        (b"WIDTH 50", b"WIDTH 25", "25 x HEIGHT 1 = 25 points, but POINTS says 50"),
    ]:
        good.write_bytes(content.replace(old, new))
        with pytest.raises(kitti.DatasetError, match=rf"g\.pcd: WIDTH {counts}"):
            clouds.read_pcd(good)


def test_channels_first_npy_is_named(tmp_path):
    """nuScenes keeps clouds as [4, N]: read as [N, 4] they were 4 garbage points."""
    np.save(tmp_path / "cn.npy", POINTS.T)
    with pytest.raises(kitti.DatasetError, match=r"cn\.npy: shape \[4, 50\] looks channels-first"):
        clouds.read_npy(tmp_path / "cn.npy")
    np.save(tmp_path / "few.npy", POINTS[:4])  # 4 points of 4 values: [N, C] as documented
    np.testing.assert_array_equal(clouds.read_npy(tmp_path / "few.npy"), POINTS[:4])


@pytest.mark.parametrize("channels", [3, 4, 5])
def test_channels_first_npy_of_any_readable_width_is_named(tmp_path, channels):
    """[N, C] is read for C = 3, 4 or 5 (x, y, z, intensity, ring/time), so [C, N] of each of
    them must be refused: read as rows, [5, N] gave 5 "points" made of channel values."""
    arr = np.c_[POINTS, np.ones(len(POINTS))][:, :channels].T
    np.save(tmp_path / "cf.npy", arr)
    with pytest.raises(
        kitti.DatasetError, match=rf"cf\.npy: shape \[{channels}, 50\] looks channels-first"
    ):
        clouds.read_npy(tmp_path / "cf.npy")


def test_a_bad_file_in_a_folder_is_a_bad_frame_not_a_stop(tmp_path, monkeypatch):
    """Any ValueError of a reader is that frame's error (--skip-bad-frames goes on), not the
    end of the run: an empty binary .pcd raised numpy's own before it was caught. A
    MemoryError stops the run, with a note naming the file it was reading."""
    np.save(tmp_path / "a.npy", POINTS)
    np.save(tmp_path / "b.npy", POINTS)
    read = clouds.read_cloud

    np.save(tmp_path / "c.npy", POINTS)

    def flaky(path):
        if path.name == "a.npy":
            raise ValueError("cannot reshape array of size 0 into shape (0,newaxis)")
        if path.name == "b.npy":  # a damage no reader check foresaw
            raise IndexError("list index out of range")
        return read(path)

    monkeypatch.setattr(P, "read_cloud", flaky)
    count, frames = P.open_input(tmp_path)
    a, b, c = list(frames)
    assert count == 3 and isinstance(a.error, ValueError) and c.error is None
    assert isinstance(b.error, kitti.DatasetError)
    assert str(b.error) == f"{tmp_path / 'b.npy'}: unreadable (IndexError: list index out of range)"

    def no_memory(path):
        raise MemoryError

    monkeypatch.setattr(P, "read_cloud", no_memory)  # the machine's trouble: it stops the run
    with pytest.raises(MemoryError) as stopped:
        list(P.open_input(tmp_path)[1])
    assert stopped.value.__notes__ == [f"while reading {tmp_path / 'a.npy'}"]


@pytest.mark.parametrize("data", ["binary", "ascii"])
def test_a_count_2_intensity_reads_its_first_value(tmp_path, data):
    """The module docstring: a COUNT > 1 field reads its first value. Intensity stored with
    COUNT 2 (say a first and a last return's), after a COUNT 3 field and before others: the
    first of the two, never the second (-7) nor a neighbour's column."""
    layout = [("normal", "<f4", 4, "F", 3), ("x", "<f4", 4, "F", 1), ("y", "<f4", 4, "F", 1),
              ("z", "<f4", 4, "F", 1), ("intensity", "<f4", 4, "F", 2),
              ("ring", "<u2", 2, "U", 1)]  # fmt: skip
    s = np.zeros(len(POINTS), [(n, t, (c,) if c > 1 else ()) for n, t, _, _, c in layout])
    for k, name in enumerate("xyz"):
        s[name] = POINTS[:, k]
    s["intensity"] = np.c_[POINTS[:, 3], np.full(len(POINTS), -7.0)]
    s["normal"], s["ring"] = 1.0, 3
    _write_pcd(tmp_path / "c.pcd", POINTS, data, layout, s=s)
    np.testing.assert_array_equal(clouds.read_pcd(tmp_path / "c.pcd"), POINTS)


def test_trailing_bytes_headers_without_height_and_upper_case_suffixes(tmp_path):
    """Bytes after a binary PCD's points (a trailing newline some writers add) are not
    points; a header without HEIGHT and POINTS (PCD 0.5) has WIDTH x 1 points; a .PCD,
    .NPY or .BIN file (cameras, Windows tools) is read as its lower-case suffix would be."""
    _write_pcd(tmp_path / "t.pcd", POINTS)
    (tmp_path / "t.pcd").write_bytes((tmp_path / "t.pcd").read_bytes() + b"\n")
    np.testing.assert_array_equal(clouds.read_pcd(tmp_path / "t.pcd"), POINTS)
    header = b"VERSION .5\nFIELDS x y z intensity\nSIZE 4 4 4 4\nTYPE F F F F\nWIDTH 50\n"
    (tmp_path / "b05.pcd").write_bytes(header + b"DATA binary\n" + POINTS.tobytes())
    rows = "".join(" ".join(map(repr, p)) + "\n" for p in POINTS.astype(np.float64).tolist())
    (tmp_path / "a05.pcd").write_bytes(header + b"DATA ascii\n" + rows.encode())
    for name in ("b05", "a05"):
        np.testing.assert_array_equal(clouds.read_pcd(tmp_path / f"{name}.pcd"), POINTS)
    _write_pcd(tmp_path / "SCAN.PCD", POINTS)
    np.save(tmp_path / "scan.npy", POINTS)
    (tmp_path / "scan.npy").rename(tmp_path / "SCAN.NPY")
    kitti.write_points(tmp_path / "SCAN.BIN", POINTS)
    for suffix in ("PCD", "NPY", "BIN"):
        np.testing.assert_array_equal(clouds.read_cloud(tmp_path / f"SCAN.{suffix}"), POINTS)


def test_readers_name_what_is_no_cloud_file_and_never_block_on_a_pipe(
    tmp_path, errors_without_blocking
):
    """read_cloud / read_points / read_pcd / read_npy called directly (not through predict's
    listing) on a pipe blocked forever in open(); a folder or a dangling symlink gave
    IsADirectoryError / FileNotFoundError without saying what the path is."""
    import functools
    import os

    os.mkfifo(tmp_path / "scan.npy")
    (tmp_path / "scan.pcd").mkdir()
    (tmp_path / "scan.bin").symlink_to(tmp_path / "unmounted.bin")
    kinds = {"npy": "a pipe, socket or device", "pcd": "a folder",
             "bin": "a broken or looping symlink"}  # fmt: skip
    readers = {"npy": clouds.read_npy, "pcd": clouds.read_pcd, "bin": kitti.read_points}
    errors = errors_without_blocking({
        (ext, read.__name__): functools.partial(read, tmp_path / f"scan.{ext}")
        for ext in kinds
        for read in (clouds.read_cloud, readers[ext])
    })  # fmt: skip
    assert len(errors) == 6
    for (ext, _), e in errors.items():
        assert isinstance(e, kitti.DatasetError)
        assert str(e) == f"{tmp_path / f'scan.{ext}'}: {kinds[ext]}, not a cloud file"
    with pytest.raises(FileNotFoundError):  # a missing file stays the read's own error
        clouds.read_cloud(tmp_path / "missing.bin")
