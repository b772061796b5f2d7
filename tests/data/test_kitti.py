"""KITTI-style files: round trips, the camera convention, and bad input named clearly."""

import math
import os
import warnings

import numpy as np
import pytest

from indoorbev_jax import fileio
from indoorbev_jax.config import CLASS_NAMES, Config, ConfigError, DataConfig, with_overrides
from indoorbev_jax.data import kitti

DATA = DataConfig()


def random_labels(rng, m, scores=False):
    return kitti.ObjectLabels(
        classes=rng.integers(0, 9, m),
        dims=rng.uniform(0.1, 3.0, (m, 3)),
        pos=rng.uniform(-5, 5, (m, 3)),
        yaw=rng.uniform(-math.pi, math.pi, m),
        occlusion=rng.integers(0, 4, m),
        scores=rng.uniform(0, 1, m) if scores else None,
    )


def yaw_diff(a, b):
    return np.abs(kitti.wrap_angle(a - b))


@pytest.mark.parametrize("scores", [False, True])
def test_label_round_trip(tmp_path, scores):
    rng = np.random.default_rng(0)
    for trial in range(20):
        labels = random_labels(rng, int(rng.integers(0, 30)), scores)
        path = tmp_path / f"{trial}.txt"
        kitti.write_labels(path, labels, CLASS_NAMES)
        back = kitti.read_labels(path, DATA)
        np.testing.assert_array_equal(back.classes, labels.classes)
        np.testing.assert_array_equal(back.occlusion, labels.occlusion)
        np.testing.assert_allclose(back.dims, labels.dims, atol=1e-5)
        np.testing.assert_allclose(back.pos, labels.pos, atol=1e-5)
        assert (yaw_diff(back.yaw, labels.yaw) < 1e-5).all()
        if scores:
            np.testing.assert_allclose(back.scores, labels.scores, atol=1e-5)
        else:
            assert back.scores is None


def test_camera_convention_fields():
    # An object 2 m ahead, 1 m left, centre 0.5 m up, facing +y (yaw = pi/2), l w h = 3 2 1.
    labels = kitti.ObjectLabels([1], [[3.0, 2.0, 1.0]], [[2.0, 1.0, 0.5]], [math.pi / 2], [0])
    (line,) = kitti.labels_to_lines(labels, CLASS_NAMES)
    f = line.split()
    assert len(f) == 15 and f[0] == "Chair"
    assert f[1] == "0.00" and f[2] == "0"  # truncation is 0 (DESIGN 3); occlusion as given
    assert [float(v) for v in f[3:8]] == [-10, 0, 0, 0, 0]
    h, w, l, xc, yc, zc, ry = (float(v) for v in f[8:15])  # noqa: E741
    assert (h, w, l) == (1.0, 2.0, 3.0)
    # x_cam = -y, y_cam = -z of the bottom centre (z = 0), z_cam = x.
    assert (xc, yc, zc) == (-1.0, 0.0, 2.0)
    assert abs(kitti.wrap_angle(ry + math.pi)) < 1e-6  # -yaw - pi/2 = -pi (= pi)
    assert -math.pi <= ry <= math.pi  # KITTI's range, after rounding to six decimals


def test_object_labels_refuse_fields_of_another_shape():
    """pos given as [3, M] was reshaped to [M, 3], scrambling every box without a word; a
    flat array of M * 3 values, or [M, 1] yaws, are still read."""
    pos = np.array([[1.0, 1.0, 0.0], [-2.0, 0.0, 0.0]])
    good = kitti.ObjectLabels([0, 1], np.ones((2, 3)), pos, [0.1, 0.2], [0, 0])
    flat = kitti.ObjectLabels([0, 1], np.ones(6), pos.ravel(), [[0.1], [0.2]], [0, 0])
    for field in ("dims", "pos", "yaw", "occlusion"):
        np.testing.assert_array_equal(getattr(flat, field), getattr(good, field))
    with pytest.raises(
        ValueError, match=r"ObjectLabels\.pos: expected \[M, 3\] with M = 2 .* \[3, 2\]"
    ):
        kitti.ObjectLabels([0, 1], np.ones((2, 3)), pos.T, [0.1, 0.2], [0, 0])
    with pytest.raises(
        ValueError, match=r"ObjectLabels\.scores: expected \[M\] .* got shape \[3\]"
    ):
        kitti.ObjectLabels([0, 1], np.ones((2, 3)), pos, [0.1, 0.2], [0, 0], [0.5, 0.4, 0.3])


def test_prediction_lines_end_with_the_score():
    labels = kitti.ObjectLabels([6], [[0.5, 0.4, 1.7]], [[1.0, 0.0, 0.85]], [0.0], [2], [0.75])
    f = kitti.labels_to_lines(labels, CLASS_NAMES)[0].split()
    assert len(f) == 16 and f[0] == "Person" and f[2] == "2" and float(f[15]) == 0.75


def test_points_round_trip_and_bad_size(tmp_path):
    pts = np.random.default_rng(0).normal(size=(100, 4)).astype(np.float32)
    kitti.write_points(tmp_path / "a.bin", pts)
    # The format itself (DESIGN 3): little-endian float32, N x 4, nothing else in the file.
    raw = np.fromfile(tmp_path / "a.bin", "<f4")
    np.testing.assert_array_equal(raw.reshape(-1, 4), pts)
    np.testing.assert_array_equal(kitti.read_points(tmp_path / "a.bin"), pts)
    (tmp_path / "bad.bin").write_bytes(b"\0" * 20)
    with pytest.raises(kitti.DatasetError, match=r"bad\.bin: size 20 bytes"):
        kitti.read_points(tmp_path / "bad.bin")
    (tmp_path / "empty.bin").write_bytes(b"")
    assert kitti.read_points(tmp_path / "empty.bin").shape == (0, 4)
    # Garbage bytes (signalling NaNs among them) read or are refused without numpy's
    # RuntimeWarning, which names no file.
    garbage = np.random.default_rng(1).integers(0, 256, 64 * 16, dtype=np.uint8).tobytes()
    (tmp_path / "garbage.bin").write_bytes(garbage)
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        try:
            kitti.read_points(tmp_path / "garbage.bin")
        except kitti.DatasetError:
            pass


def test_float64_points_are_refused_and_float32_clouds_are_not(tmp_path):
    """numpy's default float64 passes the size rule (32 bytes a point): random and round
    values are both named; float32 clouds with NaN rows, zero rows, zero intensity or a flat
    z, however their sizes fall, are read as written."""
    rng = np.random.default_rng(0)
    cloud = np.c_[rng.uniform(-4, 4, (2000, 3)), rng.uniform(0, 1, 2000)]
    widened = cloud.astype(np.float32).astype(np.float64)  # float32 values via float64
    for name, points in (("random", cloud), ("round", np.round(cloud * 4) / 4), ("wide", widened)):
        points.tofile(tmp_path / f"{name}.bin")  # float64
        with pytest.raises(kitti.DatasetError, match=rf"{name}\.bin: looks like float64"):
            kitti.read_points(tmp_path / f"{name}.bin")
    f32 = cloud.astype(np.float32)
    variants = {"plain": f32, "no_intensity": f32 * [1, 1, 1, 0], "flat": f32 * [1, 1, 0, 1]}
    variants["nan_rows"] = np.where(rng.uniform(size=(2000, 1)) < 0.5, np.nan, f32)
    variants["zero_rows"] = np.where(rng.uniform(size=(2000, 1)) < 0.8, 0, f32)
    variants["odd_count"] = f32[:1999]
    variants["one_point"] = f32[:1]
    for name, points in variants.items():
        points = points.astype(np.float32)
        kitti.write_points(tmp_path / f"{name}.bin", points)
        np.testing.assert_array_equal(kitti.read_points(tmp_path / f"{name}.bin"), points)


def test_empty_label_file_is_valid(tmp_path):
    (tmp_path / "e.txt").write_text("")
    assert len(kitti.read_labels(tmp_path / "e.txt", DATA)) == 0


GOOD = "Table 0.00 0 -10 0 0 0 0 1.0 1.0 1.0 0.0 0.0 2.0 0.0"


@pytest.mark.parametrize(
    "line, message",
    [
        ("Table 0 0 -10 0 0 0 0 1 1 1 0 0 2", r"l\.txt:2: expected 15 fields .* got 14"),
        (GOOD.replace("2.0", "abc"), r"l\.txt:2: non-numeric field"),
        (GOOD.replace("Table", "Sofabed"), r"l\.txt:2: unknown class 'Sofabed'"),
        (GOOD.replace("2.0", "nan"), r"l\.txt:2: non-finite"),
        (GOOD + " nan", r"l\.txt:2: non-finite .* score"),
        (GOOD.replace("0.00 0 -10", "0.00 7 -10"), r"l\.txt:2: occlusion must be 0, .* got 7$"),
        (GOOD.replace("0.00 0 -10", "0.00 inf -10"), r"l\.txt:2: occlusion .* got inf"),
        (GOOD.replace("0.00 0 -10", "0.00 1.7 -10"), r"l\.txt:2: occlusion .* got 1\.7"),
        (GOOD.replace("0.00 0 -10", "1.50 0 -10"), r"l\.txt:2: truncation .* got 1\.50"),
        (GOOD.replace("1.0 1.0 1.0", "-1.0 1.0 1.0"), r"l\.txt:2: dimensions h w l must be"),
        # A zero size is no object either (ground truth; a box without cells).
        (GOOD.replace("1.0 1.0 1.0", "1.0 0.0 1.0"), r"l\.txt:2: .* positive, got 1\.0 0\.0 1\.0"),
        # Each of h, w and l (a mutation audit: l left unchecked passed).
        (GOOD.replace("1.0 1.0 1.0", "0.0 1.0 1.0"), r"l\.txt:2: .* positive, got 0\.0 1\.0 1\.0"),
        (GOOD.replace("1.0 1.0 1.0", "1.0 1.0 0.0"), r"l\.txt:2: .* positive, got 1\.0 1\.0 0\.0"),
        (GOOD + " 0.9", r"l\.txt:2: some lines .* \(line 2 has one, line 1 has none\)"),
        # float() reads "0_5" as 5.0; 1e39 is finite in float64 but inf in float32.
        (GOOD.replace("2.0", "0_5"), r"l\.txt:2: non-numeric field \('_' in '0_5'\)"),
        (GOOD.replace("2.0", "1e39"), r"l\.txt:2: non-finite"),
        (GOOD + " -1e39", r"l\.txt:2: non-finite .* score"),
    ],
)
def test_bad_label_lines_name_file_and_line(tmp_path, line, message):
    (tmp_path / "l.txt").write_text(GOOD + "\n" + line + "\n")
    with pytest.raises(kitti.DatasetError, match=message):
        kitti.read_labels(tmp_path / "l.txt", DATA)


def test_truncation_one_is_inside_kittis_range(tmp_path):
    """KITTI's truncation lies in [0, 1], both ends included (1.0 = fully truncated, as the
    refusal message itself quotes): a line with truncation 1.00 is one object, not an error.
    Guards against a half-open check (``0 <= t < 1``) that refuses the upper end."""
    (tmp_path / "l.txt").write_text(GOOD.replace("0.00 0 -10", "1.00 0 -10") + "\n")
    assert len(kitti.read_labels(tmp_path / "l.txt", DATA)) == 1


def test_unknown_class_mapped_in_config(tmp_path):
    (tmp_path / "l.txt").write_text(GOOD.replace("Table", "Desk") + "\n")
    data = DataConfig(class_map=(("Desk", "Table"),))
    assert kitti.read_labels(tmp_path / "l.txt", data).classes.tolist() == [0]
    # The JSON object a --set override gives is the same map; a malformed one names the field.
    cfg = with_overrides(Config.tiny(), ['data.class_map={"Desk": "Table"}'])
    assert cfg.data.class_map == (("Desk", "Table"),)
    assert Config.from_dict(cfg.to_dict()) == cfg
    with pytest.raises(ConfigError, match="data.class_map.*pairs or a dict"):
        DataConfig(class_map=(("Desk", "Table", "x"),))


def test_mask_round_trip_and_wrong_size(tmp_path):
    shape = Config.tiny().grid.shape
    ids = np.random.default_rng(0).integers(0, 40000, shape)
    kitti.write_mask(tmp_path / "m.png", ids)
    np.testing.assert_array_equal(kitti.read_mask(tmp_path / "m.png", shape), ids)
    with pytest.raises(kitti.DatasetError, match=r"m\.png: mask of shape \(40, 40\)"):
        kitti.read_mask(tmp_path / "m.png", (50, 50))
    # 16-bit PNG: 65535 is the largest id; 65536 would wrap to 0 (no object), so it is refused.
    ids[0, 0] = 65535
    kitti.write_mask(tmp_path / "m.png", ids)
    assert kitti.read_mask(tmp_path / "m.png", shape)[0, 0] == 65535
    ids[0, 0] = 65536
    with pytest.raises(ValueError, match=r"big\.png: expected \[H, W\] ids in 0\.\.65535"):
        kitti.write_mask(tmp_path / "big.png", ids)
    assert not (tmp_path / "big.png").exists()


def test_a_mask_of_the_wrong_width_alone_is_refused(tmp_path):
    """A mask must match the grid in both H and W: one with the grid's height but 10 more
    columns (40 x 50 for the tiny 40 x 40 grid) is refused, not read. Guards against a check
    of the height only, which would pair the labels with the wrong cells."""
    shape = Config.tiny().grid.shape
    kitti.write_mask(tmp_path / "m.png", np.zeros((shape[0], shape[1] + 10), np.int32))
    with pytest.raises(kitti.DatasetError, match=r"m\.png: mask of shape \(40, 50\)"):
        kitti.read_mask(tmp_path / "m.png", shape)


def test_masks_must_be_png_of_integer_ids(tmp_path):
    """8-bit grey and palette PNGs hold ids; a JPEG (lossy: ids change) or a float TIFF saved
    under .png does not, and is named."""
    from PIL import Image

    shape = Config.tiny().grid.shape
    ids = np.random.default_rng(0).integers(0, 5, shape).astype(np.uint8)
    Image.fromarray(ids, "L").save(tmp_path / "grey.png")
    palette = Image.fromarray(ids, "L").convert("P")
    palette.save(tmp_path / "palette.png")
    for name in ("grey", "palette"):
        np.testing.assert_array_equal(kitti.read_mask(tmp_path / f"{name}.png", shape), ids)
    Image.fromarray(ids, "L").save(tmp_path / "jpeg.png", format="JPEG")
    with pytest.raises(kitti.DatasetError, match=r"jpeg\.png: a JPEG image .* expected a PNG"):
        kitti.read_mask(tmp_path / "jpeg.png", shape)
    Image.fromarray(ids.astype(np.float32), "F").save(tmp_path / "float.png", format="TIFF")
    with pytest.raises(kitti.DatasetError, match=r"float\.png: a TIFF image in mode F"):
        kitti.read_mask(tmp_path / "float.png", shape)
    # A colour PNG (an overlay saved by a viewer) holds no ids either, whatever its size.
    for mode in ("RGB", "RGBA", "LA"):
        Image.fromarray(ids, "L").convert(mode).save(tmp_path / "colour.png")
        with pytest.raises(kitti.DatasetError, match=rf"colour\.png: a PNG image in mode {mode};"):
            kitti.read_mask(tmp_path / "colour.png", shape)


def test_a_corrupt_mask_png_is_named(tmp_path):
    """A flipped bit in the IHDR length (PIL: ValueError) or in the image data (PIL reads
    other ids without a word: it checks no CRC when loading) is a DatasetError naming the
    file."""
    shape = Config.tiny().grid.shape
    ids = np.zeros(shape, np.int64)
    ids[5:9, 3:30] = 1
    ids[20:25, 10:12] = 2
    kitti.write_mask(tmp_path / "m.png", ids)
    data = bytearray((tmp_path / "m.png").read_bytes())
    header = bytearray(data)
    header[11] ^= 0x01  # the IHDR chunk's length field
    (tmp_path / "ihdr.png").write_bytes(bytes(header))
    idat = data.index(b"IDAT")
    silent = 0
    for bit in range(8 * 24):  # the first bytes of the compressed image data
        flipped = bytearray(data)
        flipped[idat + 4 + bit // 8] ^= 1 << (bit % 8)
        (tmp_path / "idat.png").write_bytes(bytes(flipped))
        with pytest.raises(kitti.DatasetError, match=r"idat\.png: not a readable PNG"):
            kitti.read_mask(tmp_path / "idat.png", shape)
        from PIL import Image

        try:
            with Image.open(tmp_path / "idat.png") as im:
                silent += not np.array_equal(np.asarray(im), ids)
        except (OSError, ValueError):
            pass
    assert silent > 0  # PIL alone reads some of them as other ids
    with pytest.raises(kitti.DatasetError, match=r"ihdr\.png: not a readable PNG"):
        kitti.read_mask(tmp_path / "ihdr.png", shape)


def test_a_lock_that_cannot_be_written_is_named_once(tmp_path, monkeypatch):
    """On a full disk every long job said only "[Errno 28] No space left on device": the
    line written into the folder's lock was the one write not named."""
    real_write = os.write

    def full(fd, data):
        if data.startswith(b"export, pid"):
            raise OSError(28, "No space left on device")
        return real_write(fd, data)

    monkeypatch.setattr(os, "write", full)
    with pytest.raises(OSError) as failed:
        with fileio.hold_folder(tmp_path / "out", "export", "--out"):
            pass
    lock = tmp_path / "out" / ".lock"
    assert str(failed.value) == f"[Errno 28] cannot write {lock}: No space left on device"
    monkeypatch.setattr(os, "write", real_write)
    with fileio.hold_folder(tmp_path / "out", "export", "--out"):  # the rerun takes it
        assert lock.read_text() == f"export, pid {os.getpid()}\n"


def test_a_failed_write_names_the_file_and_leaves_nothing(tmp_path):
    """A full disk under ndarray.tofile said only "6464 requested and 1024 written"."""

    def full(path):
        path.write_bytes(b"partial")
        raise OSError(28, "No space left on device")

    target = tmp_path / "velodyne" / "000000.bin"
    with pytest.raises(OSError, match=r"cannot write .*000000\.bin: No space left on device"):
        fileio.atomic_write(target, full)
    assert list(target.parent.iterdir()) == []
    # A file where a folder must be: named as such (it said only "File exists").
    (tmp_path / "afile").write_text("")
    with pytest.raises(OSError, match=r"cannot write .*afile/x/a\.bin: .*afile is a file, not"):
        fileio.atomic_write(tmp_path / "afile" / "x" / "a.bin", full)
    # Looking for that file must not replace the message (Path.is_file raised here).
    with pytest.raises(OSError, match=r"cannot write .*a\.bin: File name too long"):
        fileio.atomic_write(tmp_path / ("n" * 300) / "a.bin", full)


def test_a_pipe_where_a_label_mask_or_split_file_goes_is_named_not_read(
    tmp_path, errors_without_blocking
):
    """A named pipe in label_2/, mask_2/ or as a split list blocked `indoorbev eval` and
    `dataset check` forever in open(), as it did the cloud readers before (test_clouds)."""
    for name in ("train.txt", "a.txt", "a.png"):
        os.mkfifo(tmp_path / name)
    errors = errors_without_blocking({
        "train.txt": lambda: kitti.read_split(tmp_path, "train"),
        "a.txt": lambda: kitti.read_labels(tmp_path / "a.txt", DataConfig()),
        "a.png": lambda: kitti.read_mask(tmp_path / "a.png", (8, 8)),
    })  # fmt: skip
    what = {"train.txt": "a split file", "a.txt": "a label file", "a.png": "a PNG mask"}
    for name, error in errors.items():
        assert isinstance(error, kitti.DatasetError), (name, error)
        assert str(error) == f"{tmp_path / name}: a pipe, socket or device, not {what[name]}"


def test_split_files_from_other_editors(tmp_path):
    """A byte-order mark and CRLF (Windows editors) are read; a split that is not UTF-8 or
    is a folder is a DatasetError naming it; hidden files are not frames."""
    (tmp_path / "bom.txt").write_bytes(b"\xef\xbb\xbf000000\r\n000001\r\n")
    assert kitti.read_split(tmp_path, "bom") == ["000000", "000001"]
    (tmp_path / "latin.txt").write_bytes(b"000000\n\xff000001\n")
    with pytest.raises(kitti.DatasetError, match=r"latin\.txt:2: not a UTF-8 text file"):
        kitti.read_split(tmp_path, "latin")
    (tmp_path / "folder.txt").mkdir()
    with pytest.raises(kitti.DatasetError, match=r"folder\.txt: a folder, not a split file"):
        kitti.read_split(tmp_path, "folder")
    (tmp_path / "label_2").mkdir()
    for name in ("000000.txt", "._000000.txt", ".hidden.txt"):
        (tmp_path / "label_2" / name).write_text("")
    assert kitti.list_frames(tmp_path) == ["000000"]


def test_atomic_write_leaves_no_partial_file(tmp_path):
    class Boom(Exception):
        pass

    def write(p):
        p.write_text("half")
        raise Boom

    with pytest.raises(Boom):
        fileio.atomic_write(tmp_path / "x.txt", write)
    assert list(tmp_path.iterdir()) == []
    # A folder that cannot be made (here: a file in the way) names the file being written,
    # not a hidden temporary one.
    (tmp_path / "a_file").write_text("")
    with pytest.raises(OSError, match=r"cannot write .*a_file/sub/y\.txt: "):
        fileio.atomic_write(tmp_path / "a_file" / "sub" / "y.txt", lambda p: p.write_text("y"))


def test_atomic_write_syncs_the_data_before_the_rename(tmp_path, monkeypatch):
    """atomic_write's documented order: the temporary file's data reach the disk (fsync)
    before it is renamed into place, so a power cut cannot leave an empty file under the
    final name. Guards against dropping the fsync (invisible without a power cut, so the
    calls are recorded here)."""
    calls = []
    real_fsync, real_replace = os.fsync, os.replace

    def fsync(fd):
        calls.append(("fsync", os.path.basename(os.readlink(f"/proc/self/fd/{fd}"))))
        real_fsync(fd)

    def replace(a, b):
        calls.append(("replace", os.path.basename(a), os.path.basename(b)))
        real_replace(a, b)

    monkeypatch.setattr(os, "fsync", fsync)
    monkeypatch.setattr(os, "replace", replace)
    fileio.atomic_write(tmp_path / "x.txt", lambda p: p.write_text("x"))
    assert [c[0] for c in calls] == ["fsync", "replace"]
    assert calls[0][1] == calls[1][1] and calls[1][2] == "x.txt"
    assert (tmp_path / "x.txt").read_text() == "x"


def test_dontcare_blank_lines_and_bom_are_not_objects(tmp_path):
    """KITTI's DontCare regions and blank lines are skipped, a byte-order mark is not part of
    the first name, and mask instance k is the k-th object line."""
    chair = GOOD.replace("Table", "Chair")
    dontcare = "DontCare -1 -1 -10 0 0 0 0 -1 -1 -1 -1000 -1000 -1000 -10"
    text = "\ufeff" + GOOD + "\n\n" + dontcare + "\n" + chair + "\n"
    (tmp_path / "l.txt").write_text(text, encoding="utf-8")
    labels = kitti.read_labels(tmp_path / "l.txt", DATA)
    assert labels.classes.tolist() == [CLASS_NAMES.index("Table"), CLASS_NAMES.index("Chair")]
    (tmp_path / "bad.txt").write_bytes(b"Table \xff\xfe\n")
    with pytest.raises(kitti.DatasetError, match=r"bad\.txt:1: not a UTF-8 text file"):
        kitti.read_labels(tmp_path / "bad.txt", DATA)
    (tmp_path / "bad.txt").write_bytes(GOOD.encode() + b"\r\nTable \xe4\n")
    with pytest.raises(kitti.DatasetError, match=r"bad\.txt:2: not a UTF-8 .* b'\\xe4'"):
        kitti.read_labels(tmp_path / "bad.txt", DATA)


def test_labels_the_reader_would_refuse_are_not_written(tmp_path):
    """A NaN value, or a ground-truth size that six decimals round to 0, made a file that
    only failed when read back (by eval, maybe much later); the writer names the object."""
    rng = np.random.default_rng(0)
    for scores in (False, True):
        labels = random_labels(rng, 3, scores)
        labels.yaw[1] = np.nan
        with pytest.raises(ValueError, match=r"bad\.txt: object 1: non-finite size, position"):
            kitti.write_labels(tmp_path / "bad.txt", labels, CLASS_NAMES)
        assert not (tmp_path / "bad.txt").exists()
    labels = random_labels(rng, 3)
    labels.dims[2, 0] = 4e-7
    with pytest.raises(ValueError, match=r"object 2: ground-truth size 4e-07 x .* not positive"):
        kitti.write_labels(tmp_path / "bad.txt", labels, CLASS_NAMES)
    # The smallest size that is written is read back; a prediction's size may be anything.
    labels.dims[2, 0] = 6e-7
    kitti.write_labels(tmp_path / "gt.txt", labels, CLASS_NAMES)
    assert kitti.read_labels(tmp_path / "gt.txt", DATA).dims[2, 0] == np.float32(1e-6)
    labels = random_labels(rng, 3, scores=True)
    labels.dims[2] = [-0.5, 0.0, 1e-9]
    kitti.write_labels(tmp_path / "pred.txt", labels, CLASS_NAMES)
    np.testing.assert_allclose(kitti.read_labels(tmp_path / "pred.txt", DATA).dims[2], [-0.5, 0, 0])


def test_predicted_sizes_may_be_negative(tmp_path):
    """A scored line is a prediction: its regressed size is read as written (ground truth
    must be positive, test above)."""
    (tmp_path / "p.txt").write_text(GOOD.replace("1.0 1.0 1.0", "-0.5 1.0 1.0") + " 0.9\n")
    labels = kitti.read_labels(tmp_path / "p.txt", DATA)
    np.testing.assert_allclose(labels.dims, [[1.0, 1.0, -0.5]])


def test_float64_points_with_nan_rows_are_refused(tmp_path):
    """NaN points are legal, in a float64 file too: one must not hide the float64 (read as
    float32, the file gave twice the points, hundreds of garbage ones in the workspace); nor
    must one point beyond 1e4, or a cloud in millimetres."""
    rng = np.random.default_rng(0)
    cloud = np.c_[rng.uniform(-4, 4, (1000, 3)), rng.uniform(0, 1, 1000)]
    organised = np.where((np.arange(1000) % 100 == 0)[:, None], np.nan, cloud)
    far = np.r_[cloud, [[1e30, 1e30, 1e30, 0.0]]]  # one "no return" written as 1e30
    millimetres = cloud * [1000, 1000, 1000, 1]  # beyond 1e4 everywhere
    mostly_nan = np.where((np.arange(1000) % 10 != 0)[:, None], np.nan, cloud)
    cases = {"one_nan": np.r_[cloud, [[np.nan] * 3 + [0.0]]], "rows": organised, "far": far,
             "mm": millimetres, "mostly_nan": mostly_nan}  # fmt: skip
    for name, points in cases.items():
        points.tofile(tmp_path / f"{name}.bin")  # float64
        with pytest.raises(kitti.DatasetError, match=rf"{name}\.bin: looks like float64"):
            kitti.read_points(tmp_path / f"{name}.bin")


def _in_room(d: np.ndarray, ceiling: float = np.inf, half=(3.0, 2.0)) -> np.ndarray:
    """float32 [R, 4]: where rays ``d`` [R, 3] from the sensor, in firing order, meet a
    room of ``2 half`` m (6 x 4 m: walls, floor 0.5 m below, a ceiling ``ceiling`` m above),
    with random intensities."""
    with np.errstate(divide="ignore"):
        floor = np.where(d[:, 2] < 0, 0.5 / -d[:, 2], ceiling / d[:, 2])
        t = np.min(np.abs([half[0] / d[:, 0], half[1] / d[:, 1], floor]), 0)
    intensity = np.random.default_rng(0).uniform(0, 1, len(d))
    return np.c_[d * t[:, None], intensity].astype(np.float32)


def _room_scan(rows: int = 16, cols: int = 600) -> np.ndarray:
    """float32 [rows * cols, 4]: a spinning lidar's points, in firing order, in a 6 x 4 m
    room (walls, floor 0.5 m below, no ceiling)."""
    az, el = np.meshgrid(np.linspace(-np.pi, np.pi, cols), np.radians(np.linspace(-15, 15, rows)))
    d = np.stack([np.cos(el) * np.cos(az), np.cos(el) * np.sin(az), np.sin(el)], -1).reshape(-1, 3)
    return _in_room(d)


def test_three_or_five_column_clouds_are_refused(tmp_path):
    """12 or 20 bytes a point pass the size rule whenever N % 4 == 0: read as 4 columns, the
    points are garbage. A scan in firing order tells (consecutive points are near)."""
    scan = _room_scan()
    kitti.write_points(tmp_path / "ok.bin", scan)
    np.testing.assert_array_equal(kitti.read_points(tmp_path / "ok.bin"), scan)
    ring = np.arange(len(scan)) % 16
    for cols, points in ((3, scan[:, :3]), (5, np.c_[scan, ring].astype(np.float32))):
        assert points[: len(points) // 4 * 4].nbytes % 16 == 0
        points[: len(points) // 4 * 4].tofile(tmp_path / f"c{cols}.bin")
        with pytest.raises(kitti.DatasetError, match=rf"c{cols}\.bin: looks like {cols} float32"):
            kitti.read_points(tmp_path / f"c{cols}.bin")
    # Points in no particular order cannot tell: read as written (as before the check).
    shuffled = scan[np.random.default_rng(1).permutation(len(scan))]
    kitti.write_points(tmp_path / "shuffled.bin", shuffled)
    np.testing.assert_array_equal(kitti.read_points(tmp_path / "shuffled.bin"), shuffled)


@pytest.mark.parametrize("half, ceiling", [((3.0, 2.0), 2.0), ((20.0, 15.0), 5.0)])
def test_a_five_emitter_scan_in_four_columns_is_read(tmp_path, half, ceiling):
    """Read as 5 columns, a 4-column file realigns every 20 words, where a 5-emitter lidar's
    next shot of the same emitter lies: comparing points 4 apart at stride 5 refused this
    genuine file (d14627b)."""
    from indoorbev_sim.patterns import Mid360Pattern

    directions = np.asarray(Mid360Pattern(num_emitters=5).frame(0).directions, np.float64)
    scan = _in_room(directions, ceiling=ceiling, half=half)
    kitti.write_points(tmp_path / "ok.bin", scan)
    np.testing.assert_array_equal(kitti.read_points(tmp_path / "ok.bin"), scan)


@pytest.mark.parametrize("intensity", [0.0, 1.0])
def test_a_five_emitter_scan_with_a_constant_intensity_is_read(tmp_path, intensity):
    """A genuine 4-column 5-emitter MID-360 frame whose intensity column is constant (0 or
    1, e.g. a driver that fills no intensity) in the 6 x 4 m room is read as written. Read
    as 5 columns, its "5th column" cycles through x, y, z and the constant intensity: a
    quarter or more of it whole numbers and about half of it not decreasing, far from the
    99 % that marks a real id or time column. Guards against a looser id-or-time rule
    (>= 50 %), under which this file was refused as 5 columns."""
    from indoorbev_sim.patterns import Mid360Pattern

    directions = np.asarray(Mid360Pattern(num_emitters=5).frame(0).directions, np.float64)
    scan = _in_room(directions, ceiling=2.0, half=(3.0, 2.0))
    scan[:, 3] = intensity
    kitti.write_points(tmp_path / "ok.bin", scan)
    np.testing.assert_array_equal(kitti.read_points(tmp_path / "ok.bin"), scan)


@pytest.mark.parametrize("half, ceiling", [((3.0, 2.0), 2.0), ((20.0, 15.0), 5.0)])
def test_a_mid360_scan_with_three_or_five_columns_is_refused(tmp_path, half, ceiling):
    """The MID-360's non-repetitive pattern is the closest case (docs/DATASET.md): a frame
    of the simulator's Mid360Pattern in a room with a ceiling, written with 3 or 5 float32
    columns, is refused; written with 4 it is read as written. In a 40 x 30 m hall a
    5-column file was read as garbage while only neighbouring points were compared."""
    from indoorbev_sim.patterns import Mid360Pattern

    directions = np.asarray(Mid360Pattern().frame(0).directions, np.float64)
    scan = _in_room(directions, ceiling=ceiling, half=half)
    assert np.isfinite(scan).all() and len(scan) % 4 == 0
    kitti.write_points(tmp_path / "ok.bin", scan)
    np.testing.assert_array_equal(kitti.read_points(tmp_path / "ok.bin"), scan)
    line = np.arange(len(scan)) % 4  # the emitter, as a 5th column
    time = np.arange(len(scan)) * 5e-6  # or each point's time (read in a hall before)
    for name, cols, points in (("xyz", 3, scan[:, :3]), ("line", 5, np.c_[scan, line]),
                               ("time", 5, np.c_[scan, time])):  # fmt: skip
        points.astype(np.float32).tofile(tmp_path / f"{name}.bin")
        with pytest.raises(kitti.DatasetError, match=rf"{name}\.bin: looks like {cols} float32"):
            kitti.read_points(tmp_path / f"{name}.bin")


def test_stale_temporaries_go_by_their_age_and_the_jobs(tmp_path):
    """A killed write's temporary older than ``min_age`` goes; one younger (another
    process's write in flight) stays, at the start of a job (60 s) and at its end, when
    ``age_since`` gives the job's age with a 1 s floor. Both passed with the age ignored."""
    import time

    now = time.time()
    assert fileio.age_since(now - 30) == pytest.approx(30, abs=1)
    assert fileio.age_since(now) == 1.0
    ages = {".a.txt.abcd1234.tmp": 0.5, ".b.txt.efgh5678.tmp": 10, ".c.txt.ijkl9012.tmp": 45,
            ".d.txt.mnop3456.tmp": 120}  # fmt: skip
    for name, age in ages.items():
        (tmp_path / name).write_bytes(b"x")
        os.utime(tmp_path / name, (now - age, now - age))
    fileio.remove_stale_temporaries(tmp_path, "*", 60.0)
    assert sorted(p.name for p in tmp_path.iterdir()) == sorted(ages)[:3]
    # At the end of a 30 s job: what is older than the job goes, what is younger stays.
    fileio.remove_stale_temporaries(tmp_path, "*", fileio.age_since(now - 30))
    assert sorted(p.name for p in tmp_path.iterdir()) == sorted(ages)[:2]
    # Only atomic_write's own: a hidden file of another name (not 8 characters before
    # .tmp) and a symlink of its naming (its target is someone's) stay, however old.
    theirs = tmp_path / "theirs"
    theirs.mkdir()
    (theirs / "notes.txt").write_text("mine")
    (theirs / ".e.txt.old.tmp").write_bytes(b"x")
    (theirs / ".f.txt.abcd1234.tmp").write_bytes(b"x")
    (theirs / ".g.txt.efgh5678.tmp").symlink_to(theirs / "notes.txt")
    for path in theirs.iterdir():
        os.utime(path, (now - 7200, now - 7200))
    fileio.remove_stale_temporaries(theirs, "*", 60.0)
    left = sorted(p.name for p in theirs.iterdir())
    assert left == [".e.txt.old.tmp", ".g.txt.efgh5678.tmp", "notes.txt"]


def test_hold_folder_names_the_holder_and_what_stands_in_its_way(tmp_path, monkeypatch):
    """The lock names the job holding it (a predict into an export's folder was told "in
    use by another predict run"), an --out under a file says so (a bare "File exists"
    before), and a read-only folder, where no run can write, is not locked (a finished
    predict output on read-only media stopped at opening its .lock)."""
    import errno
    import fcntl

    held = tmp_path / "held"
    with fileio.hold_folder(held, "predict run", "--out"):  # the next holder's line replaces it
        pass
    with fileio.hold_folder(held, "export", "--out"):
        assert (held / ".lock").read_text() == f"export, pid {os.getpid()}\n"
        said = rf"held: in use by another export \(pid {os.getpid()}\); wait .* another --out"
        with pytest.raises(ValueError, match=said):
            with fileio.hold_folder(held, "predict run", "--out"):
                pass
    with open(held / ".lock", "w") as old:  # a lock of an older version: the pid alone
        fcntl.flock(old, fcntl.LOCK_EX | fcntl.LOCK_NB)
        old.write("pid 4242\n")
        old.flush()
        with pytest.raises(ValueError, match=r"in use by another run \(pid 4242\)"):
            with fileio.hold_folder(held, "run", "workdir"):
                pass
    (tmp_path / "afile").write_text("x")
    for out in (tmp_path / "afile", tmp_path / "afile" / "sub"):
        with pytest.raises(OSError, match=r"cannot write in .*: .*afile is a file, not a folder"):
            with fileio.hold_folder(out, "predict run", "--out"):
                pass
    # A symlink where the lock goes: refused, its target left as it was (the lock's line
    # overwrote it).
    target = tmp_path / "notes.txt"
    target.write_text("mine")
    (tmp_path / "linked").mkdir()
    (tmp_path / "linked" / ".lock").symlink_to(target)
    with pytest.raises(OSError, match=r"linked/\.lock: a symlink where the lock goes"):
        with fileio.hold_folder(tmp_path / "linked", "predict run", "--out"):
            pass
    assert target.read_text() == "mine"

    # Read-only media, and a folder this user may not write (chmod, as root never sees).
    for code in (errno.EROFS, errno.EACCES):

        def read_only(folder, *args, code=code, **kwargs):
            raise OSError(code, os.strerror(code))

        monkeypatch.setattr(fileio, "_open_lock", read_only)
        ran = []
        with fileio.hold_folder(held, "predict run", "--out"):
            ran.append(True)
        assert ran == [True]
