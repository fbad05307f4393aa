"""data_synth: replaying a recorded trajectory file, and motion blur."""
from __future__ import annotations

import json
from pathlib import Path

import cv2
import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from data_synth import generate, ground_truth_poses, read_synth_json, trajectory_poses
from data_synth.trajectories import CORRIDOR_RADIUS_M, LOOP_HEIGHT_M, exposure_poses, replay_poses
from mipslam.cli import main
from mipslam.errors import ConfigError, DatasetError

SMALL = dict(width=48, height=36, supersample=1)


def _write_tum(path: Path, stamps: np.ndarray, positions: np.ndarray, rotations: Rotation) -> Path:
    quats = rotations.as_quat()  # x y z w
    rows = [f"{t:.6f} " + " ".join(f"{v:.9f}" for v in (*p, *q)) for t, p, q in zip(stamps, positions, quats)]
    path.write_text("# timestamp tx ty tz qx qy qz qw\n" + "\n".join(rows) + "\n")
    return path


def _hand_held(path: Path, seconds: float = 1.0, rate: float = 100.0, sway_m: float = 0.2) -> tuple[Path, np.ndarray, Rotation]:
    """A recording at ``rate`` Hz: a sway of ``sway_m`` and a fast yaw/pitch, from a tilted start
    in a world frame far from the room's."""
    stamps = 1305031229.0 + np.arange(int(seconds * rate) + 1) / rate
    s = stamps - stamps[0]
    positions = np.stack([5.0 + sway_m * np.sin(3 * s), -3.0 + 0.05 * s, 1.0 + 0.03 * np.cos(5 * s)], -1)
    rotations = Rotation.from_euler("zyx", np.stack([0.4 + 1.2 * np.sin(4 * s), 0.3 * np.sin(7 * s), 0.7 + 0 * s], -1))
    return _write_tum(path, stamps, positions, rotations), positions, rotations


def test_replay_keeps_the_recorded_motion_and_places_it_in_the_room(tmp_path):
    path, positions, rotations = _hand_held(tmp_path / "gt.txt")
    poses = replay_poses(path, 0, 30.0)
    assert poses.shape == (31, 4, 4)  # 1 s at 30 frames/s, both ends
    # Frame k at k/30 s: every third frame falls on a recorded pose (the others are interpolated).
    recorded = np.tile(np.eye(4), (len(positions), 1, 1))
    recorded[:, :3, :3], recorded[:, :3, 3] = rotations.as_matrix(), positions
    for k, j in ((3, 0), (30, 0), (30, 21)):  # relative motion between samples = recorded relative motion
        i_k, i_j = round(k * 100 / 30), round(j * 100 / 30)
        assert abs(k * 100 / 30 - i_k) < 1e-9 and abs(j * 100 / 30 - i_j) < 1e-9
        want = np.linalg.inv(recorded[i_j]) @ recorded[i_k]
        got = np.linalg.inv(poses[j]) @ poses[k]
        np.testing.assert_allclose(got, want, atol=1e-6)
    # The first camera looks along +x, level (its x axis horizontal, z along +x).
    np.testing.assert_allclose(poses[0, :3, 2], [1, 0, 0], atol=1e-9)
    np.testing.assert_allclose(poses[0, 2, 0], 0, atol=1e-9)
    centre = 0.5 * (poses[:, :3, 3].min(0) + poses[:, :3, 3].max(0))
    np.testing.assert_allclose(centre, [0, 0, LOOP_HEIGHT_M], atol=1e-9)
    # The start and the number of frames choose the part; frames beyond the recording are refused.
    part = replay_poses(path, 4, 30.0, start_s=0.5)
    assert part.shape == (4, 4, 4)
    np.testing.assert_allclose(np.linalg.inv(part[0]) @ part[3], np.linalg.inv(poses[15]) @ poses[18], atol=1e-6)
    with pytest.raises(DatasetError, match="at most 31 frames"):
        replay_poses(path, 32, 30.0)
    with pytest.raises(DatasetError, match="earlier start"):
        replay_poses(path, 0, 30.0, start_s=2.0)


def test_replay_refuses_a_path_outside_the_corridor_and_gaps(tmp_path):
    wide, _, _ = _hand_held(tmp_path / "wide.txt", sway_m=2.5)  # 2.5 m across: 1.25 m off the axis
    with pytest.raises(DatasetError, match="corridor") as info:
        replay_poses(wide, 0, 30.0)
    assert "wide.txt" in str(info.value) and "shorter part" in str(info.value)
    assert 2.5 / 2 > CORRIDOR_RADIUS_M and replay_poses(wide, 0, 30.0, start_s=0.9).shape == (4, 4, 4)
    stamps = np.r_[0.0, 0.05, 0.3, 0.35] + 100.0
    gappy = _write_tum(tmp_path / "gappy.txt", stamps, np.zeros((4, 3)), Rotation.identity(4))
    with pytest.raises(DatasetError, match="gap"):
        replay_poses(gappy, 0, 30.0)
    # Two poses with one timestamp (TUM's freiburg2_desk ground truth has such a pair): the first is replayed.
    stamps = 100.0 + np.r_[0.0, 0.05, 0.05, 0.1]
    twice = _write_tum(tmp_path / "twice.txt", stamps, np.array([[0, 0, 0], [0.1, 0, 0], [0.5, 0, 0], [0.2, 0, 0.0]]),
                       Rotation.identity(4))
    replayed = replay_poses(twice, 0, 30.0)
    assert len(replayed) == 4
    np.testing.assert_allclose(np.linalg.norm(replayed[1, :3, 3] - replayed[0, :3, 3]), 0.1 * (1 / 30) / 0.05)
    with pytest.raises(DatasetError, match="not found"):
        replay_poses(tmp_path / "missing.txt", 0, 30.0)


def test_generate_replays_a_file_with_exact_ground_truth(tmp_path):
    path, _, _ = _hand_held(tmp_path / "gt.txt", seconds=0.2)
    out = generate(tmp_path / "seq", layout="tum", trajectory=str(path), frames=0, **SMALL)
    info = read_synth_json(out)
    assert (info["trajectory"], info["frames"], info["trajectory_options"]) == ("file", 7, {"file": "gt.txt",
                                                                                          "start_s": 0.0})
    np.testing.assert_array_equal(ground_truth_poses(out), replay_poses(path, 0, 30.0))
    assert len((out / "rgb.txt").read_text().split("\n")) - 3 == 7
    with pytest.raises(ConfigError, match="laps"):
        generate(tmp_path / "laps", trajectory=str(path), laps=2, frames=0, **SMALL)
    # A corrupted pose list is named, not trusted.
    info["poses"] = info["poses"][:-1]
    (out / "synth.json").write_text(json.dumps(info))
    with pytest.raises(DatasetError, match="regenerate"):
        ground_truth_poses(out)


def test_exposure_poses_spread_around_the_frame():
    poses = trajectory_poses("line", 5)  # 2 cm a frame along a line, fixed orientation
    still = exposure_poses(poses, 2, 0.0, 8)
    np.testing.assert_array_equal(still, np.repeat(poses[2][None], 8, axis=0))
    spread = exposure_poses(poses, 2, 1.0, 4)  # offsets -3/8, -1/8, 1/8, 3/8 of a frame interval
    step = poses[3, :3, 3] - poses[2, :3, 3]
    for k, u in enumerate((-0.375, -0.125, 0.125, 0.375)):
        np.testing.assert_allclose(spread[k, :3, 3], poses[2, :3, 3] + u * step, atol=1e-12)
    np.testing.assert_allclose(exposure_poses(poses, 0, 1.0, 4)[:2], np.repeat(poses[0][None], 2, axis=0))
    loop = trajectory_poses("loop", 40)
    turning = exposure_poses(loop, 10, 0.5, 2)  # rotations interpolated: orthonormal, between the neighbours
    for R in turning[:, :3, :3]:
        np.testing.assert_allclose(R @ R.T, np.eye(3), atol=1e-12)


def test_motion_blur_blurs_colour_and_keeps_depth(tmp_path):
    sharp = generate(tmp_path / "sharp", layout="tum", trajectory="loop", frames=6, **SMALL)
    blurred = generate(tmp_path / "blurred", layout="tum", trajectory="loop", frames=6, motion_blur=0.8,
                       blur_samples=4, **SMALL)
    name = sorted((sharp / "rgb").iterdir())[3].name
    a = cv2.imread(str(sharp / "rgb" / name)).astype(np.float64)
    b = cv2.imread(str(blurred / "rgb" / name)).astype(np.float64)
    assert np.abs(a - b).mean() > 0.5
    # Blur is a low-pass: less high-frequency energy than the sharp frame.
    assert cv2.Laplacian(b, cv2.CV_64F).var() < cv2.Laplacian(a, cv2.CV_64F).var()
    assert (sharp / "depth" / name).read_bytes() == (blurred / "depth" / name).read_bytes()
    assert read_synth_json(blurred)["render"]["motion_blur"] == 0.8
    with pytest.raises(ConfigError, match="motion_blur"):
        generate(tmp_path / "bad", motion_blur=1.5, frames=2, **SMALL)


def test_cli_synth_replays_a_file(tmp_path, capsys):
    path, _, _ = _hand_held(tmp_path / "gt.txt", seconds=0.1)
    out = tmp_path / "seq"
    argv = ["-q", "synth", "--out", str(out), "--format", "tum", "--trajectory", str(path), "--frames", "0",
            "--width", "24", "--height", "18", "--supersample", "1", "--motion-blur", "0.5"]
    assert main(argv) == 0
    assert read_synth_json(out)["frames"] == 4
    assert main(["-q", "synth", "--out", str(tmp_path / "other"), "--trajectory", str(tmp_path / "nope.txt")]) != 0
    assert "trajectory" in capsys.readouterr().err


def test_depth_delay_takes_depth_later_than_colour(tmp_path):
    from data_synth import load_scene, render_view, synth_intrinsics
    from data_synth.trajectories import pose_at

    together = generate(tmp_path / "together", layout="tum", trajectory="zoom", frames=5, **SMALL)
    delayed = generate(tmp_path / "delayed", layout="tum", trajectory="zoom", frames=5, depth_delay=0.4, **SMALL)
    names = sorted((together / "rgb").iterdir())
    assert all((together / "rgb" / n.name).read_bytes() == (delayed / "rgb" / n.name).read_bytes() for n in names)
    poses = ground_truth_poses(delayed)  # the colour's poses
    np.testing.assert_array_equal(poses, ground_truth_poses(together))
    depth_names = sorted((delayed / "depth").iterdir())
    assert [float(n.stem) for n in depth_names] == pytest.approx([1000 + (i + 0.4) / 30 for i in range(5)], abs=1e-6)
    depth = cv2.imread(str(depth_names[1]), cv2.IMREAD_UNCHANGED).astype(np.float64) / 5000
    later = render_view(load_scene(delayed), pose_at(poses, 1, 0.4), synth_intrinsics(delayed), supersample=1)[1]
    np.testing.assert_allclose(depth, np.round(later * 5000) / 5000, atol=1e-9)
    # The dolly moves towards the wall: depth taken later is nearer than at the colour's instant.
    at_frame = cv2.imread(str(together / "depth" / names[1].name), cv2.IMREAD_UNCHANGED).astype(np.float64)
    assert np.median(depth * 5000 - at_frame) < 0
    np.testing.assert_allclose(pose_at(poses, 4, 0.4), poses[4])  # the last frame holds still
    # The reader pairs each colour image with its later depth image and knows the offset.
    from mipslam.config import DatasetConfig
    from mipslam.datasets import make_sequence
    frame = make_sequence(DatasetConfig(kind="synthetic", path=str(delayed)))[2]
    assert frame.depth_time_offset == pytest.approx(0.4 / 30, abs=2e-6)
    assert make_sequence(DatasetConfig(kind="synthetic", path=str(together)))[2].depth_time_offset == 0.0
    with pytest.raises(ConfigError, match="depth_delay"):
        generate(tmp_path / "bad", depth_delay=0.5, frames=2, **SMALL)


def test_rolling_shutter_reads_each_band_of_rows_at_its_own_time(tmp_path):
    from data_synth import load_scene, render_view, synth_intrinsics
    from data_synth.trajectories import pose_at
    from data_synth.writer import ROLLING_SHUTTER_BANDS

    still = generate(tmp_path / "still", layout="tum", trajectory="static", frames=3, **SMALL)
    still_rs = generate(tmp_path / "still_rs", layout="tum", trajectory="static", frames=3, rolling_shutter=0.8, **SMALL)
    assert _files_equal(still / "rgb", still_rs / "rgb")  # a camera at rest: no read-out effect
    moving = generate(tmp_path / "rs", layout="tum", trajectory="loop", frames=6, rolling_shutter=0.8, **SMALL)
    poses, intrinsics, scene = ground_truth_poses(moving), synth_intrinsics(moving), load_scene(moving)
    image = cv2.imread(str(sorted((moving / "rgb").iterdir())[3]))[..., ::-1].astype(np.float64) / 255
    H = SMALL["height"]
    for band in (0, ROLLING_SHUTTER_BANDS - 1):  # the top rows are read first, the bottom rows last
        r0, r1 = band * H // ROLLING_SHUTTER_BANDS, (band + 1) * H // ROLLING_SHUTTER_BANDS
        readout = (0.5 * (r0 + r1) / H - 0.5) * 0.8
        full = render_view(scene, pose_at(poses, 3, readout), intrinsics, supersample=1)[0]
        np.testing.assert_allclose(image[r0:r1], full[r0:r1], atol=0.51 / 255)
    at_frame = render_view(scene, poses[3], intrinsics, supersample=1)[0]
    assert np.abs(image[:2] - at_frame[:2]).mean() > 1 / 255  # ... not at the frame's own time
    with pytest.raises(ConfigError, match="rolling_shutter"):
        generate(tmp_path / "bad", rolling_shutter=-0.1, frames=2, **SMALL)


def _files_equal(a: Path, b: Path) -> bool:
    return [p.read_bytes() for p in sorted(a.iterdir())] == [p.read_bytes() for p in sorted(b.iterdir())]


def test_radial_depth_bias_grows_from_the_centre():
    from data_synth.sensor import SensorOptions, apply_depth_effects

    depth = np.full((31, 41), 2.0, dtype=np.float32)
    biased = apply_depth_effects(depth, SensorOptions(depth_radial_bias=0.01), seed=0, frame=0)
    assert biased[15, 20] == pytest.approx(2.0)  # the centre
    assert biased[15, 0] == pytest.approx(2.02) and biased[0, 20] == pytest.approx(2.02)  # the middle of the edges
    assert biased[0, 0] == pytest.approx(2.04) and biased[30, 40] == pytest.approx(2.04)  # the corners
    missing = depth.copy()
    missing[3, 4] = 0
    assert apply_depth_effects(missing, SensorOptions(depth_radial_bias=0.01), seed=0, frame=0)[3, 4] == 0


def test_generate_records_the_radial_bias(tmp_path):
    out = generate(tmp_path / "b", layout="tum", trajectory="static", frames=1, depth_radial_bias=0.02, **SMALL)
    assert read_synth_json(out)["sensor"]["depth_radial_bias"] == 0.02
    with pytest.raises(ConfigError, match="depth_radial_bias"):
        generate(tmp_path / "bad", depth_radial_bias=0.5, frames=1, **SMALL)
