"""The web viewer: snapshot geometry, reading a run folder, the frame-loop observer (the run stays
bit-identical), and the page itself loaded in headless Chromium (splats drawn in the map's colours)."""
from __future__ import annotations

import math
import os
import signal
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

import data_synth
from mipslam.cli import main
from mipslam.config import load_config
from mipslam.observer import Observer
from mipslam.pipeline import run_slam
from mipslam.types import Intrinsics
from mipslam.viewer.browser import find_chromium, screenshot
from mipslam.viewer.server import frustum_segments
from mipslam.viewer.snapshot import (Headline, Splats, aligned_ate_rmse, matrix_to_quaternion_wxyz,
                                     quaternion_wxyz_to_matrix, snapshot_from_run_dir)

REPO = Path(__file__).resolve().parent.parent
TINY = ["mapping.first_frame_iterations=30", "mapping.iterations=8", "mapping.densify_pixel_stride=2",
        "tracking.iterations=15", "keyframes.window_size=3", "keyframes.random_past=1", "run.threads=1",
        "refine.passes=0"]


def _random_rotations(n: int, seed: int = 0) -> tuple[np.ndarray, np.ndarray]:
    q = np.random.default_rng(seed).normal(size=(n, 4))
    q /= np.linalg.norm(q, axis=1, keepdims=True)
    return q, quaternion_wxyz_to_matrix(q)


# ----------------------------------------------------------------------------- geometry

def test_quaternions_give_rotations_and_back():
    q, R = _random_rotations(50)
    assert np.allclose(R @ R.transpose(0, 2, 1), np.eye(3), atol=1e-12)
    assert np.allclose(np.linalg.det(R), 1.0)
    for qi, Ri in zip(q, R):
        back = matrix_to_quaternion_wxyz(Ri)
        assert np.allclose(back, qi, atol=1e-9) or np.allclose(back, -qi, atol=1e-9)  # q and -q: one rotation


def test_splat_covariances_are_rotated_squared_scales():
    q, R = _random_rotations(20, seed=1)
    scales = np.random.default_rng(2).uniform(0.01, 0.2, size=(20, 3))
    splats = Splats.from_activated(np.zeros((20, 3)), q, scales, np.full((20, 3), 0.5), np.full(20, 0.9))
    cov = splats.covariances.astype(np.float64)
    assert np.allclose(cov, cov.transpose(0, 2, 1), atol=1e-9)
    assert np.allclose(np.sort(np.linalg.eigvalsh(cov), 1), np.sort(scales**2, 1), rtol=1e-4)
    axis = cov @ R[:, :, 0:1]  # the first local axis is an eigenvector with eigenvalue s_x^2
    assert np.allclose(axis[..., 0], R[:, :, 0] * scales[:, 0:1] ** 2, atol=1e-6)


def test_keyframe_frusta_end_at_the_image_corners():
    K = Intrinsics(fx=50.0, fy=55.0, cx=23.5, cy=17.0, width=48, height=36)
    T = np.eye(4)[None].repeat(2, 0)
    T[1, :3, :3] = quaternion_wxyz_to_matrix(np.array([[0.9, 0.1, -0.3, 0.2]]))[0]
    T[1, :3, 3] = [1.0, -2.0, 0.5]
    segments = frustum_segments(T, K, depth_m=0.4).astype(np.float64)
    assert segments.shape == (16, 2, 3)
    for k in range(2):
        spokes = segments[8 * k: 8 * k + 4]
        assert np.allclose(spokes[:, 0], T[k, :3, 3], atol=1e-6)  # from the camera centre
        local = (spokes[:, 1] - T[k, :3, 3]) @ T[k, :3, :3]  # world -> camera frame
        assert np.allclose(local[:, 2], 0.4, atol=1e-5)
        u = K.fx * local[:, 0] / local[:, 2] + K.cx
        v = K.fy * local[:, 1] / local[:, 2] + K.cy
        assert np.allclose(sorted(set(np.round(u, 4))), [-0.5, K.width - 0.5], atol=1e-3)
        assert np.allclose(sorted(set(np.round(v, 4))), [-0.5, K.height - 0.5], atol=1e-3)


def test_aligned_ate_ignores_a_rigid_motion_and_measures_noise():
    rng = np.random.default_rng(3)
    gt = rng.normal(size=(40, 3))
    _, R = _random_rotations(1, seed=4)
    moved = gt @ R[0].T + np.array([0.3, -1.0, 2.0])
    assert aligned_ate_rmse(moved, gt) == pytest.approx(0.0, abs=1e-9)
    noise = rng.normal(scale=0.01, size=gt.shape)
    assert 0.005 < aligned_ate_rmse(gt + noise, gt) < 0.02
    assert aligned_ate_rmse(gt[:2], gt[:2]) is None  # too few poses to align


def test_headline_states_the_numbers():
    text = Headline(frame=12, total_frames=30, frames_per_second=2.5, gaussians=12345, keyframes=4,
                    ate_rmse_m=0.0123).markdown()
    for part in ("12 / 30", "2.50", "12,345", "**keyframes** 4", "1.23 cm"):
        assert part in text
    assert "ATE" not in Headline(frame=1, total_frames=0, frames_per_second=None, gaussians=0, keyframes=0).markdown()


# ----------------------------------------------------------------------------- runs

@pytest.fixture(scope="module")
def tiny_run(tmp_path_factory):
    """A tiny run (with an observer that records what it saw) -> (config overrides, run folder, observed)."""
    root = tmp_path_factory.mktemp("viewer")
    seq = root / "seq"
    data_synth.generate(seq, layout="replica", trajectory="loop", width=48, height=36, frames=8, seed=0, supersample=2)
    overrides = [f"dataset.path={seq}", *TINY]
    observed = []

    class Recorder(Observer):
        def on_frame(self, record, state):
            assert self.frames[record.index].index == record.index  # the run's frames are attached
            observed.append((record.index, state.next_frame, len(state.gaussian_map)))

    run_slam(load_config("synthetic", overrides=overrides), root / "run", observer=Recorder())
    return overrides, root / "run", observed


def test_observers_see_every_frame_once_after_it_completes(tiny_run):
    _, _, observed = tiny_run
    assert [index for index, _, _ in observed] == list(range(8))
    assert [done for _, done, _ in observed] == list(range(1, 9))
    assert all(count > 0 for _, _, count in observed)


def test_snapshot_of_a_run_folder(tiny_run):
    _, run_dir, _ = tiny_run
    run = snapshot_from_run_dir(run_dir)
    snap = run.snapshot
    est = np.loadtxt(run_dir / "traj_est.txt")
    assert snap.est_T_wc.shape == (8, 4, 4) and np.allclose(snap.est_T_wc[:, :3, 3], est[:, 1:4])
    assert snap.gt_positions is not None and snap.gt_positions.shape == (8, 3)
    assert len(snap.keyframe_T_wc) == len(np.loadtxt(run_dir / "keyframes.txt", ndmin=2))
    assert len(snap.splats) > 0 and np.isfinite(snap.splats.covariances).all()
    assert snap.headline.ate_rmse_m is not None and snap.headline.finished
    assert snap.intrinsics.width == 48 and run.config is not None


def test_view_of_a_missing_or_unfinished_run_exits_2_with_one_line(tmp_path, capsys):
    (tmp_path / "unfinished").mkdir()
    for path, what in ((tmp_path / "nothing", "no such run folder"), (tmp_path / "unfinished", "map.ply")):
        assert main(["view", str(path), "--port", "0"]) == 2
        err = capsys.readouterr().err.strip()
        assert len(err.splitlines()) == 1 and what in err, err


# ----------------------------------------------------------------------------- with viser and a browser

def _map_colour_fraction(png: Path, splats: Splats) -> float:
    """Share of the 3D view's pixels (left part of the page, below the notification area) whose colour is
    one of the map's (Gaussians with opacity > 0.5, quantised to 16 levels, and their neighbours)."""
    import cv2

    image = cv2.imread(str(png), cv2.IMREAD_COLOR)[..., ::-1].astype(np.int64)  # RGB
    H, W, _ = image.shape
    view = image[int(0.3 * H):, : int(0.6 * W)].reshape(-1, 3)
    levels = 16
    step = 256 // levels
    colours = (splats.colors[splats.opacities > 0.5] * 255).astype(np.int64) // step
    offsets = np.stack(np.meshgrid(*[np.arange(-1, 2)] * 3, indexing="ij"), -1).reshape(-1, 3)
    palette = np.unique((colours[:, None, :] + offsets[None]).reshape(-1, 3).clip(0, levels - 1), axis=0)
    code = lambda c: (c[:, 0] * levels + c[:, 1]) * levels + c[:, 2]  # noqa: E731
    background = (view >= 240).all(1)  # the page's white background
    matches = np.isin(code(view // step), code(palette)) & ~background
    return float(matches.mean())


needs_viewer = pytest.mark.skipif(find_chromium() is None,
                                  reason="no Chromium on PATH (Debian: apt-get install chromium)")


@needs_viewer
def test_mipslam_view_draws_the_splats_in_a_browser(tiny_run, tmp_path):
    pytest.importorskip("viser", reason="viser is not installed (pip install 'mipslam[viewer]')")
    _, run_dir, _ = tiny_run
    env = {**os.environ, "PYTHONPATH": os.pathsep.join([str(REPO), os.environ.get("PYTHONPATH", "")])}
    command = [sys.executable, "-m", "mipslam", "-q", "view", str(run_dir), "--port", "0", "--map-only"]
    server = subprocess.Popen(command,
                              stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, env=env, cwd=REPO)
    try:
        line = server.stdout.readline()
        assert line.startswith("viewer: http://127.0.0.1:"), (line, server.stderr.read() if server.poll() else "")
        url = line.split()[1]
        shot = screenshot(url, tmp_path / "view.png", width=800, height=600)
    finally:
        server.send_signal(signal.SIGINT)
        try:
            code = server.wait(timeout=30)
        except subprocess.TimeoutExpired:
            server.kill()
            raise
    assert code == 0
    fraction = _map_colour_fraction(shot, snapshot_from_run_dir(run_dir).snapshot.splats)
    assert fraction > 0.3, f"only {fraction:.1%} of the view shows the map's colours"


def test_live_viewer_leaves_the_trajectory_bit_identical(tiny_run, tmp_path):
    pytest.importorskip("viser", reason="viser is not installed (pip install 'mipslam[viewer]')")
    from mipslam.viewer.live import LiveOptions, LiveViewer
    from mipslam.viewer.server import ViewerOptions

    overrides, run_dir, _ = tiny_run
    config = load_config("synthetic", overrides=overrides)
    viewer = LiveViewer(config.render, ViewerOptions(port=0), LiveOptions(min_interval_s=0.0, max_busy_fraction=1.0))
    try:
        run_slam(config, tmp_path / "live", observer=viewer)
        viewer.finish(tmp_path / "live")
        assert viewer.updates >= 1 and viewer.captures >= viewer.updates
        assert (tmp_path / "live" / "traj_est.txt").read_bytes() == (run_dir / "traj_est.txt").read_bytes()
        assert (tmp_path / "live" / "map.ply").read_bytes() == (run_dir / "map.ply").read_bytes()
        if find_chromium() is not None:
            shot = screenshot(viewer.url, tmp_path / "live.png", width=800, height=600,
                              ready=lambda: viewer.server.clients > 0)
            assert _map_colour_fraction(shot, snapshot_from_run_dir(run_dir).snapshot.splats) > 0.1
    finally:
        viewer.close()


def test_a_failing_viewer_turns_itself_off_and_the_run_goes_on(tiny_run, tmp_path, caplog):
    pytest.importorskip("viser", reason="viser is not installed (pip install 'mipslam[viewer]')")
    from mipslam.viewer.live import LiveViewer
    from mipslam.viewer.server import ViewerOptions

    overrides, run_dir, _ = tiny_run
    config = load_config("synthetic", overrides=overrides + ["dataset.max_frames=3"])
    viewer = LiveViewer(config.render, ViewerOptions(port=0))

    def broken(*args):
        raise RuntimeError("no snapshot today")

    viewer._capture = broken
    try:
        summary = run_slam(config, tmp_path / "broken", observer=viewer, evaluate=False)
    finally:
        viewer.close()
    assert summary.frames == 3
    assert any("viewer: turned off" in r.getMessage() for r in caplog.records)
    assert math.isfinite(float(np.loadtxt(tmp_path / "broken" / "traj_est.txt")[:, 1:].sum()))


def test_the_frame_slider_shows_the_frame_beside_the_map_rendered_at_its_pose(tiny_run):
    pytest.importorskip("viser", reason="viser is not installed (pip install 'mipslam[viewer]')")
    from mipslam.viewer.recorded import RecordedViewer
    from mipslam.viewer.server import ViewerOptions

    _, run_dir, _ = tiny_run
    viewer = RecordedViewer(run_dir, ViewerOptions(port=0, follow=True))
    try:
        viewer.select_frame(5)
        shown = viewer.server.shown
        assert shown.current == 5
        frame, rendered = shown.frame_image, shown.rendered_image
        assert frame.shape == rendered.shape == (36, 48, 3) and frame.dtype == np.uint8
        error = np.abs(frame.astype(float) - rendered.astype(float)).mean() / 255
        other = np.abs(frame.astype(float) - viewer.images(0)["frame_image"].astype(float)).mean() / 255
        assert error < 0.08 and error < other  # the render matches this frame, not merely any frame
    finally:
        viewer.close()
