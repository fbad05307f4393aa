"""Bad input: every case is a DatasetError that names the offending file (and line where there is one)."""
from __future__ import annotations

import shutil
from pathlib import Path

import cv2
import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from mipslam.config import DatasetConfig
from mipslam.datasets import ReplicaSequence, TUMSequence, make_sequence, read_color, read_depth
from mipslam.errors import DatasetError
from test_datasets import H, W, tum_cfg, write_replica, write_tum


def open_replica(root: Path, **kw):
    return ReplicaSequence(root, DatasetConfig(kind="replica", path=str(root), **kw))


def open_tum(root: Path, **kw):
    return TUMSequence(root, tum_cfg(root, **kw))


def expect_error(fn, path: Path, line: int | None = None, match: str | None = None) -> DatasetError:
    with pytest.raises(DatasetError) as info:
        fn()
    err = info.value
    assert err.path == path, f"error names {err.path}, expected {path}: {err}"
    assert str(err).startswith(str(path))
    if line is not None:
        assert err.line == line and f"{path}:{line}:" in str(err)
    if match is not None:
        assert match in str(err), str(err)
    return err


def replace_line(path: Path, line: int, text: str) -> None:
    lines = path.read_text().splitlines()
    lines[line - 1] = text
    path.write_text("\n".join(lines) + "\n")


@pytest.fixture
def replica(tmp_path) -> Path:
    write_replica(tmp_path / "rep", n=4)
    return tmp_path / "rep"


@pytest.fixture
def tum(tmp_path) -> Path:
    write_tum(tmp_path / "tum", n=4)
    return tmp_path / "tum"


# ----------------------------------------------------------------------------- folders and lists

def test_missing_folders_and_files(tmp_path, replica, tum):
    expect_error(lambda: open_replica(tmp_path / "nowhere"), tmp_path / "nowhere", match="not found")
    expect_error(lambda: make_sequence(DatasetConfig(kind="tum", path=str(tmp_path / "no"))), tmp_path / "no")
    shutil.rmtree(replica / "results")
    expect_error(lambda: open_replica(replica), replica / "results", match="not found")
    (tum / "depth.txt").unlink()
    expect_error(lambda: open_tum(tum), tum / "depth.txt", match="not found")
    (tum / "rgb.txt").unlink()
    expect_error(lambda: open_tum(tum), tum / "rgb.txt", match="not found")


def test_empty_sequences(tmp_path):
    (tmp_path / "rep" / "results").mkdir(parents=True)
    expect_error(lambda: open_replica(tmp_path / "rep"), tmp_path / "rep" / "results", match="empty")
    write_tum(tmp_path / "tum", n=2)
    (tmp_path / "tum" / "rgb.txt").write_text("# color images\n# timestamp filename\n")
    expect_error(lambda: open_tum(tmp_path / "tum"), tmp_path / "tum" / "rgb.txt", match="empty")


def test_no_rgb_depth_pair_within_tolerance(tum):
    expect_error(lambda: open_tum(tum, association_tolerance_s=0.001), tum / "rgb.txt", match="no colour image")


def test_first_frame_beyond_the_sequence(replica, tum):
    expect_error(lambda: open_replica(replica, first_frame=4), replica / "results", match="first_frame=4")
    expect_error(lambda: open_tum(tum, first_frame=9), tum / "rgb.txt", match="first_frame=9")


def test_frames_listed_but_missing_on_disk(replica, tum):
    (replica / "results" / "depth000002.png").unlink()
    expect_error(lambda: open_replica(replica), replica / "results" / "depth000002.png", match="missing")
    rgb_names = sorted((tum / "rgb").iterdir())
    rgb_names[1].unlink()
    expect_error(lambda: open_tum(tum), rgb_names[1], match="missing")


@pytest.mark.parametrize(
    "file, line, text, match",
    [
        ("rgb.txt", 4, "1000.033333", "expected 'timestamp filename'"),
        ("rgb.txt", 4, "abc rgb/x.png", "not a number"),
        ("rgb.txt", 4, "nan rgb/x.png", "not finite"),
        ("rgb.txt", 4, "999.0 rgb/1000.000000.png", "not sorted"),
        ("depth.txt", 4, "1000.004000 depth/1000.004000.png", "duplicate timestamp"),
        ("groundtruth.txt", 5, "{t} 1 2 3 0 0 0", "expected 8 numbers"),
        ("groundtruth.txt", 5, "{t} 1 2 3 0 0 0 1 7", "expected 8 numbers"),
        ("groundtruth.txt", 5, "{t} 1 2 inf 0 0 0 1", "not finite"),
        ("groundtruth.txt", 5, "{t} 1 2 3 0 0 0 0", "quaternion qx qy qz qw is zero"),
        ("groundtruth.txt", 5, "{t} 1 2 3 0 0 0.5 0.5", "quaternion qx qy qz qw has norm"),
        ("groundtruth.txt", 5, "999.0 1 2 3 0 0 0 1", "timestamps must increase"),
    ],
)
def test_malformed_tum_lines(tum, file, line, text, match):
    original_timestamp = (tum / file).read_text().splitlines()[line - 1].split()[0]
    replace_line(tum / file, line, text.format(t=original_timestamp))
    expect_error(lambda: open_tum(tum), tum / file, line=line, match=match)


@pytest.mark.parametrize(
    "text, match",
    [
        ("1 0 0 0 0 1 0 0 0 0 1 0 0 0 0", "expected 16 numbers"),
        ("1 0 0 0 0 1 0 0 0 0 1 0 0 0 0 1 5", "expected 16 numbers"),
        ("1 0 0 0 0 1 0 0 0 0 nan 0 0 0 0 1", "not finite"),
        ("2 0 0 0 0 1 0 0 0 0 1 0 0 0 0 1", "not a rigid transform"),
        ("1 0 0 0 0 1 0 0 0 0 -1 0 0 0 0 1", "not a rigid transform"),  # a reflection, det -1
        ("1 0 0 0 0 1 0 0 0 0 1 0 0 0.5 0 1", "not a rigid transform"),  # bottom row
    ],
)
def test_malformed_replica_trajectory(replica, text, match):
    replace_line(replica / "traj.txt", 3, text)
    expect_error(lambda: open_replica(replica), replica / "traj.txt", line=3, match=match)


def test_replica_trajectory_shorter_than_the_frames(replica):
    lines = (replica / "traj.txt").read_text().splitlines()
    (replica / "traj.txt").write_text("\n".join(lines[:3]) + "\n")
    expect_error(lambda: open_replica(replica), replica / "traj.txt", match="has 3 poses")


def test_replica_bad_cam_params(replica):
    (replica / "cam_params.json").write_text('{"camera": {"w": 16, "h": 12,\n "fx": "twenty"}}')
    expect_error(lambda: open_replica(replica), replica / "cam_params.json", match="camera.fx")
    (replica / "cam_params.json").write_text('{"camera": {\n "fx": 1,\n}}')
    expect_error(lambda: open_replica(replica), replica / "cam_params.json", line=3, match="invalid JSON")
    (replica / "cam_params.json").write_text('{"camera": {"w": 20, "h": 12, "fx": 1, "fy": 1, "cx": 1, "cy": 1}}')
    expect_error(lambda: open_replica(replica), replica / "results" / "frame000000.png", match="says 20x12")


def test_duplicate_frame_files(replica):
    shutil.copy(replica / "results" / "frame000001.png", replica / "results" / "frame1.png")
    expect_error(lambda: open_replica(replica), replica / "results" / "frame1.png", match="appears twice")


# ----------------------------------------------------------------------------- images

def test_unreadable_and_truncated_images(replica, tmp_path):
    color = replica / "results" / "frame000002.png"
    depth = replica / "results" / "depth000003.png"
    seq = open_replica(replica)
    color.write_bytes(b"this is not an image")
    expect_error(lambda: seq[2], color, match="unreadable")
    data = depth.read_bytes()
    depth.write_bytes(data[: len(data) // 2])
    expect_error(lambda: seq[3], depth, match="truncated")
    # a truncated JPEG decodes silently in OpenCV (grey padding): it must still be refused
    jpg = tmp_path / "frame.jpg"
    cv2.imwrite(str(jpg), np.random.default_rng(0).integers(0, 255, (40, 40, 3), dtype=np.uint8))
    data = jpg.read_bytes()
    jpg.write_bytes(data[: int(len(data) * 0.8)])
    assert cv2.imread(str(jpg)) is not None  # the trap this guards against
    expect_error(lambda: read_color(jpg), jpg, match="truncated")
    empty = tmp_path / "empty.png"
    empty.write_bytes(b"")
    expect_error(lambda: read_depth(empty, 5000.0), empty, match="empty")


def test_colour_depth_size_mismatch(replica):
    depth = replica / "results" / "depth000001.png"
    cv2.imwrite(str(depth), np.full((H, W + 2), 1000, np.uint16))
    expect_error(lambda: open_replica(replica)[1], depth, match="colour and depth")
    color = replica / "results" / "frame000002.png"
    cv2.imwrite(str(color), np.zeros((H + 4, W, 3), np.uint8))
    expect_error(lambda: open_replica(replica)[2], color, match="the sequence is 16x12")


@pytest.mark.parametrize(
    "which, image, match",
    [
        ("depth", np.full((H, W), 100, np.uint8), "16-bit"),
        ("depth", np.full((H, W, 3), 100, np.uint16), "1 channel"),
        ("color", np.full((H, W, 3), 100, np.uint16), "8-bit"),
        ("color", np.full((H, W), 100, np.uint8), "3 channels"),
        ("color", np.full((H, W, 4), 100, np.uint8), "3 channels"),
    ],
)
def test_wrong_bit_depth_or_channels(replica, which, image, match):
    path = replica / "results" / ("depth000001.png" if which == "depth" else "frame000001.png")
    assert cv2.imwrite(str(path), image)
    seq = open_replica(replica)  # reads only frame 0 at construction
    expect_error(lambda: seq[1], path, match=match)
    if which == "color":  # the first selected frame is checked when the sequence is opened
        expect_error(lambda: open_replica(replica, first_frame=1), path, match=match)


# ----------------------------------------------------------------------------- property: garbage in -> frame or DatasetError

def _valid_png_bytes(kind: str) -> bytes:
    rng = np.random.default_rng(5)
    image = rng.integers(0, 255, (9, 13, 3), dtype=np.uint8) if kind == "color" else rng.integers(0, 60000, (9, 13), dtype=np.uint16)
    ok, encoded = cv2.imencode(".png", image)
    assert ok
    return encoded.tobytes()


_VALID = {"color": _valid_png_bytes("color"), "depth": _valid_png_bytes("depth")}
ok_jpg, _jpg = cv2.imencode(".jpg", np.random.default_rng(6).integers(0, 255, (9, 13, 3), dtype=np.uint8))
_VALID_JPG = _jpg.tobytes()


def _damaged(draw_source: bytes, cut: float, flips: list[tuple[float, int]]) -> bytes:
    data = bytearray(draw_source[: int(len(draw_source) * cut)])
    for position, value in flips:
        if data:
            data[int(position * (len(data) - 1))] = value
    return bytes(data)


def _check_outcome(read, path: Path) -> None:
    try:
        out = read(path)
    except DatasetError as err:
        assert err.path == path
        return
    assert out.dtype == np.float32 and np.isfinite(out).all()
    if out.ndim == 3:
        assert out.shape[2] == 3 and out.min() >= 0.0 and out.max() <= 1.0
    else:
        assert out.ndim == 2 and out.min() >= 0.0


@settings(max_examples=60, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(
    source=st.sampled_from(["color", "depth", "jpg", "random"]),
    random_bytes=st.binary(min_size=0, max_size=300),
    cut=st.one_of(st.just(1.0), st.floats(0.0, 1.0)),  # 1.0: whole file (then only the flips damage it)
    flips=st.lists(st.tuples(st.floats(0.0, 1.0), st.integers(0, 255)), max_size=3),
)
def test_image_readers_return_a_valid_image_or_dataset_error(tmp_path, source, random_bytes, cut, flips):
    if source == "random":
        data = random_bytes
    else:
        data = _damaged(_VALID_JPG if source == "jpg" else _VALID[source], cut, flips)
    path = tmp_path / "image.png"
    path.write_bytes(data)
    _check_outcome(read_color, path)
    _check_outcome(lambda p: read_depth(p, 5000.0), path)


def test_undamaged_images_read_back_exactly(tmp_path):
    path = tmp_path / "depth.png"
    path.write_bytes(_VALID["depth"])
    depth = read_depth(path, 5000.0)
    expected = np.random.default_rng(5).integers(0, 60000, (9, 13), dtype=np.uint16) / 5000.0
    np.testing.assert_allclose(depth, expected, rtol=1e-6)


def test_repeated_ground_truth_timestamp_is_tolerated_like_the_benchmark_files(tmp_path):
    """TUM's own fr2_desk groundtruth.txt repeats a timestamp (line 10863); such a sequence must load."""
    import numpy as np

    from mipslam.datasets.tum import read_ground_truth

    path = tmp_path / "groundtruth.txt"
    path.write_text("# timestamp tx ty tz qx qy qz qw\n1.0 0 0 0 0 0 0 1\n1.0 0.1 0 0 0 0 0 1\n2.0 1 0 0 0 0 0 1\n")
    times, poses = read_ground_truth(path)
    np.testing.assert_array_equal(times, [1.0, 2.0])
    assert float(poses[0, 0, 3]) == 0.0 and float(poses[1, 0, 3]) == 1.0
