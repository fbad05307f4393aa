"""RealSense input (dataset.kind realsense_bag) on recordings written by pyrealsense2 itself.

pyrealsense2's software device and recorder write a recording of synthetic frames (data_synth
images with exact depth); pyrealsense2 >= 2.58 records the rosbag2 ``.db3`` format (its recorder
refuses another suffix) and plays both ``.db3`` and the older ROS1 ``.bag``. A live camera cannot
be tested without one; it shares the reader's code except for how the stream is opened.
"""
from __future__ import annotations

import time
from pathlib import Path

import numpy as np
import pytest

from mipslam.cli import main
from mipslam.config import DatasetConfig
from mipslam.datasets import StreamEnded, make_sequence
from mipslam.errors import DatasetError

rs = pytest.importorskip("pyrealsense2", reason="pyrealsense2 is not installed (pip install 'mipslam[realsense]')")

# Small enough for a few seconds per run on 2 cores (as tests/test_pipeline.py).
TINY = ["mapping.first_frame_iterations=30", "mapping.iterations=8", "mapping.densify_pixel_stride=2",
        "tracking.iterations=15", "keyframes.window_size=3", "keyframes.random_past=1", "run.threads=1",
        "refine.passes=0"]
DEPTH_UNITS = 0.001  # metres per z16 step, as a D400 camera reports


def write_recording(path: Path, colors: np.ndarray, depths_m: np.ndarray, fx: float, fy: float, cx: float, cy: float,
                    fps: int = 30, depth_to_color_m: tuple[float, float, float] = (0.0, 0.0, 0.0)) -> Path:
    """Record colour [N, H, W, 3] float in [0, 1] and depth [N, H, W] metres through pyrealsense2's software
    device and recorder (frames pushed at ``fps`` in real time, so the recording's clock is realistic).
    ``depth_to_color_m``: the depth camera's offset from the colour camera as the file states it."""
    n, height, width = depths_m.shape
    device = rs.software_device()
    color_sensor, depth_sensor = device.add_sensor("Color"), device.add_sensor("Depth")
    intrinsics = rs.intrinsics()
    intrinsics.width, intrinsics.height, intrinsics.fx, intrinsics.fy = width, height, fx, fy
    intrinsics.ppx, intrinsics.ppy, intrinsics.model, intrinsics.coeffs = cx, cy, rs.distortion.none, [0.0] * 5

    def stream(kind, uid, fmt, bpp):
        s = rs.video_stream()
        s.type, s.index, s.uid, s.width, s.height, s.fps, s.bpp, s.fmt, s.intrinsics = (
            kind, 0, uid, width, height, fps, bpp, fmt, intrinsics)
        return s

    color_profile = color_sensor.add_video_stream(stream(rs.stream.color, 0, rs.format.rgb8, 3))
    depth_profile = depth_sensor.add_video_stream(stream(rs.stream.depth, 1, rs.format.z16, 2))
    depth_sensor.add_read_only_option(rs.option.depth_units, DEPTH_UNITS)
    identity = rs.extrinsics()
    identity.rotation, identity.translation = [1, 0, 0, 0, 1, 0, 0, 0, 1], list(depth_to_color_m)
    depth_profile.register_extrinsics_to(color_profile, identity)
    recorder = rs.recorder(str(path), device)
    sync = rs.syncer()
    color_sensor.open(color_profile)
    depth_sensor.open(depth_profile)
    color_sensor.start(sync)
    depth_sensor.start(sync)
    for i in range(n):
        color_u8 = np.ascontiguousarray((np.clip(colors[i], 0, 1) * 255 + 0.5).astype(np.uint8))
        depth_u16 = np.ascontiguousarray(np.round(depths_m[i] / DEPTH_UNITS).astype(np.uint16))
        for sensor, profile, pixels, bpp in ((color_sensor, color_profile, color_u8, 3),
                                             (depth_sensor, depth_profile, depth_u16, 2)):
            frame = rs.software_video_frame()
            frame.pixels, frame.bpp, frame.stride = pixels, bpp, width * bpp
            frame.timestamp, frame.domain, frame.frame_number = i * 1000.0 / fps, rs.timestamp_domain.system_time, i
            frame.profile = profile.as_video_stream_profile()
            if sensor is depth_sensor:
                frame.depth_units = DEPTH_UNITS
            sensor.on_video_frame(frame)
        sync.wait_for_frames(2000)
        time.sleep(1.0 / fps)
    for sensor in (color_sensor, depth_sensor):
        sensor.stop()
        sensor.close()
    del recorder  # closes the file
    return path


@pytest.fixture(scope="module")
def recording(tmp_path_factory):
    """A synthetic sequence (exact depth) and its recording: (sequence folder, recording, ReplicaSequence)."""
    root = tmp_path_factory.mktemp("realsense")
    seq_dir = root / "seq"
    assert main(["-q", "synth", "--out", str(seq_dir), "--format", "replica", "--trajectory", "loop", "--width", "48",
                 "--height", "36", "--frames", "8", "--seed", "0", "--supersample", "1"]) == 0
    source = make_sequence(DatasetConfig(kind="replica", path=str(seq_dir)))
    frames = [source[i] for i in range(len(source))]
    k = source.intrinsics
    path = write_recording(root / "synthetic.db3", np.stack([f.color.numpy() for f in frames]),
                           np.stack([f.depth.numpy() for f in frames]), k.fx, k.fy, k.cx, k.cy)
    return seq_dir, path, source


def read_all(seq) -> list:
    """Every frame of a stream, in order, until it ends."""
    frames = []
    with pytest.raises(StreamEnded):
        while True:
            frames.append(seq[len(frames)])
    return frames


# librealsense's pipeline now and then starts a full-speed playback late (see mipslam/datasets/realsense.py):
# completeness is asserted on the best of a few plays; what each play delivers is checked every time.
PLAYS = 4


def play(path: Path, **options):
    """(sequence, frames) of the first of up to PLAYS full-speed plays that starts at the recording's first frame."""
    for attempt in range(PLAYS):
        seq = make_sequence(DatasetConfig(kind="realsense_bag", path=str(path), **options))
        frames = read_all(seq)
        numbers = seq.source_indices
        assert np.all(np.diff(numbers) > 0)  # in order, never a frame twice
        if len(numbers) and numbers[0] == options.get("first_frame", 0):
            break
    return seq, frames


def test_full_speed_playback_delivers_every_frame_with_the_recorded_camera(recording):
    _, path, source = recording
    seq, frames = play(path)
    k, ks = seq.intrinsics, source.intrinsics
    assert (k.width, k.height) == (ks.width, ks.height)
    assert k.fx == pytest.approx(ks.fx, rel=1e-6) and k.cy == pytest.approx(ks.cy, rel=1e-6)
    assert seq.depth_scale == pytest.approx(DEPTH_UNITS, rel=1e-6)
    numbers = list(seq.source_indices)
    assert len(seq) == len(frames) == len(numbers) == len(source)
    assert numbers == list(range(len(source))) and seq.dropped_frames == []
    stamps = np.asarray(seq.timestamps)
    assert np.allclose(stamps, np.asarray(numbers) / 30, atol=1e-6)  # the frames' own timestamps, seconds
    assert seq.gt_T_wc is None and not seq.gt_valid.any()
    for i in (0, len(seq) - 1, 2):  # in any order: the frames read stay available
        frame, expected = seq[i], source[numbers[i]]
        assert frame.timestamp == stamps[i]
        assert np.abs(frame.color.numpy() - expected.color.numpy()).max() <= 0.5 / 255 + 1e-6
        assert np.abs(frame.depth.numpy() - expected.depth.numpy()).max() <= DEPTH_UNITS / 2 + 1e-6


def test_depth_from_an_offset_camera_is_aligned_to_colour(recording, tmp_path):
    _, _, source = recording
    frames = [source[i] for i in range(4)]
    k = source.intrinsics
    path = write_recording(tmp_path / "offset.db3", np.stack([f.color.numpy() for f in frames]),
                           np.stack([f.depth.numpy() for f in frames]), k.fx, k.fy, k.cx, k.cy,
                           depth_to_color_m=(0.2, 0.0, 0.0))  # a few pixels of parallax
    seq, played = play(path)  # librealsense may start a play late: the first of up to PLAYS that delivers
    assert played, "no play of the recording delivered a frame"
    try:
        depth = played[0].depth.numpy()
        expected = frames[int(seq.source_indices[0])].depth.numpy()
        assert depth.shape == expected.shape
        valid = depth > 0
        assert 0.5 < valid.mean() < 1.0  # reprojected: the image edge the depth camera does not see stays empty
        assert not np.allclose(depth[valid], expected[valid], atol=DEPTH_UNITS)  # moved, not copied
        assert abs(np.median(depth[valid]) - np.median(expected)) < 0.05
    finally:
        seq.close()


def test_frame_selection_and_downscale_apply(recording):
    _, path, source = recording
    seq, frames = play(path, first_frame=1, stride=2, downscale=2)
    assert list(seq.source_indices) == [1, 3, 5, 7] and seq.dropped_frames == []
    assert frames[1].color.shape == (source.intrinsics.height // 2, source.intrinsics.width // 2, 3)
    assert seq.intrinsics.fx == pytest.approx(source.intrinsics.fx / 2, rel=1e-6)


def test_realtime_playback_drops_frames_it_is_too_slow_for_and_records_them(recording):
    _, path, _ = recording
    seq = make_sequence(DatasetConfig(kind="realsense_bag", path=str(path), realtime=True))
    delivered = []
    try:
        with pytest.raises(StreamEnded):
            for i in range(100):
                stamp = seq.timestamps[i]  # waits for the frame, as the pipeline does
                delivered.append((stamp, seq[i]))
                time.sleep(0.1)  # three camera frames at 30 frames/s
        numbers = list(seq.source_indices)
        assert 1 <= len(delivered) < 8
        assert sorted(set(numbers) | set(seq.dropped_frames)) == list(range(numbers[0], numbers[-1] + 1))
        if len(numbers) >= 2:  # 0.1 s apart: the camera made about three frames in between
            assert seq.dropped_frames, "a consumer slower than the recording must drop frames"
        assert len(seq) == len(delivered)  # the sequence ends where the stream ended
    finally:
        seq.close()


def test_missing_and_corrupt_recordings_exit_2_with_one_line(tmp_path, capsys):
    missing = tmp_path / "missing.bag"
    corrupt = tmp_path / "corrupt.bag"
    corrupt.write_bytes(b"this is not a rosbag" * 100)
    for path in (missing, corrupt):
        code = main(["-q", "run", "synthetic", "--set", "dataset.kind=realsense_bag",
                     "--set", f"dataset.path={path}", "--out", str(tmp_path / f"run-{path.stem}")])
        err = capsys.readouterr().err.strip()
        assert code == 2
        assert len(err.splitlines()) == 1 and str(path) in err, err
    with pytest.raises(DatasetError, match="folder, expected a RealSense recording"):
        make_sequence(DatasetConfig(kind="realsense_bag", path=str(tmp_path)))
    (tmp_path / "frames.txt").write_text("0 rgb/0.png\n")
    with pytest.raises(DatasetError, match="not a RealSense recording"):
        make_sequence(DatasetConfig(kind="realsense_bag", path=str(tmp_path / "frames.txt")))


def test_a_run_on_a_recording_tracks_the_synthetic_camera(recording, tmp_path):
    seq_dir, path, _ = recording
    out = tmp_path / "run"
    assert main(["-q", "run", "synthetic", "--preset", "fast",
                 "--set", "dataset.kind=realsense_bag", "--set", f"dataset.path={path}",
                 *(f"--set={o}" for o in TINY), "--out", str(out)]) == 0  # no ground truth: no evaluation
    assert not (out / "metrics.json").exists()
    est = np.loadtxt(out / "traj_est.txt")
    assert est.shape[1] == 8 and len(est) >= 7 and np.isfinite(est).all()  # see the full-speed test for the 7
